//! Far-view summaries from a session on virtual time (issue 15): over the default world's cell cache (workers run
//! on the test's thread through `CellCache::run_queued`), a session sends exactly the nodes the refinement rule
//! wants, parents before children and the most visible first, keeps them through small moves (hysteresis),
//! releases them when the viewer goes away, lets records go first near the viewer, and sends a held node again
//! when a cell's edits corrected it.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_protocol::aoi::Viewpoint;
use canopy_protocol::edit::CellDelta;
use canopy_protocol::messages::ServerMsgKind;
use canopy_protocol::messages::{ClientStreaming, ServerStreaming};
use canopy_protocol::summary::{FarView, NodeKey, NodeSummary, Refine};
use canopy_protocol::{ClientMsg, Phase, ServerMsg};
use canopy_server::session::{CellState, SummaryState, WorldStore};
use canopy_server::session::{NODE_REBUILD_INTERVAL, REBUILD_INTERVAL};
use canopy_server::session::{Session, SessionConfig, Transmit};
use canopy_server::{CellCache, CellCacheConfig};
use canopy_test_support::forest as world;

fn cache() -> Arc<CellCache> {
    let cfg = CellCacheConfig { limit_bytes: 64 << 20, workers: 0, ..CellCacheConfig::default() };
    Arc::new(CellCache::new((**world()).clone(), cfg).unwrap())
}

fn view() -> FarView {
    FarView { error_px: 8.0, height_px: 720, fov_y: 1.0, range: 2500.0, altitude: 120.0 }
}

fn viewpoint(seq: u32, position: [f32; 2]) -> Viewpoint {
    Viewpoint { seq, position, yaw: 0.0, velocity: [0.0, 0.0], radius: 256.0 }
}

fn session(cache: &Arc<CellCache>, at: [f32; 2], t0: Instant) -> Session {
    let store = Arc::clone(cache) as Arc<dyn WorldStore>;
    let mut s = Session::new(store, SessionConfig::default(), t0);
    s.handle(t0, ClientMsg::hello("far")).unwrap();
    let w = s.poll_transmit(t0).unwrap();
    s.on_flushed(w.len());
    s.handle(t0, ClientMsg::ready(vec![], viewpoint(1, at))).unwrap();
    assert_eq!(s.phase(), Phase::Streaming);
    s.handle(t0, ClientMsg::Streaming(ClientStreaming::FarView(view()))).unwrap();
    s
}

/// What a client holds of the far view, and the order nodes came in.
#[derive(Default)]
struct Far {
    held: BTreeSet<NodeKey>,
    arrived: Vec<NodeKey>,
    released: Vec<NodeKey>,
    bytes: u64,
    /// Held nodes that may come again (corrected), until they do.
    again: BTreeSet<NodeKey>,
    /// Each held node as it came last.
    nodes: BTreeMap<NodeKey, NodeSummary>,
}

impl Far {
    fn take(&mut self, t: &Transmit) {
        if t.class != ServerMsgKind::Summaries {
            return;
        }
        self.bytes += t.len() as u64;
        let frame = t.frame();
        let ServerMsg::Streaming(ServerStreaming::Summaries(b)) = ServerMsg::decode(&frame[4..]).unwrap() else {
            panic!("a summaries transmit is a summaries message")
        };
        for k in b.released {
            assert!(self.held.remove(&k), "released {k:?}, which was not held");
            self.released.push(k);
        }
        for n in b.nodes {
            assert!(self.held.insert(n.key) || self.again.remove(&n.key), "{:?} sent twice", n.key);
            self.arrived.push(n.key);
            self.nodes.insert(n.key, n);
        }
    }
}

/// Poll the session, computing whatever it asked for, until it has nothing more to send; virtual time advances
/// past each rebuild interval.
fn run(s: &mut Session, cache: &CellCache, far: &mut Far, mut now: Instant) -> (Instant, Vec<Transmit>) {
    let mut all = vec![];
    for _ in 0..200 {
        while let Some(t) = s.poll_transmit(now) {
            s.on_flushed(t.len());
            far.take(&t);
            all.push(t);
        }
        let computed = cache.run_queued();
        let rebuild = s.poll_timeout().is_some();
        if computed == 0 && !rebuild && s.far().is_some_and(|f| f.queued() == 0) {
            return (now, all);
        }
        now += Duration::from_millis(250);
    }
    panic!("the far view never settled");
}

/// The nodes the rule wants at `at`, from the cache's nodes (all computed by now).
fn wanted(cache: &CellCache, at: [f32; 2]) -> BTreeSet<NodeKey> {
    let grid = *cache.grid();
    let r = Refine {
        view: view(),
        eye: at,
        origin: grid.origin,
        cell_size: grid.cell_size,
        root_level: cache.summary_root_level(),
        record_radius: 256.0,
    };
    let error = |k: NodeKey| match cache.summary(k, None) {
        SummaryState::Ready(n) => Some(n.node.error),
        _ => None,
    };
    // Nodes reached with a known error that the rule selects (a root or a refined parent, in range).
    r.reach(error).into_iter().filter(|(k, e)| e.is_some() && r.selects(*k, false, error)).map(|(k, _)| k).collect()
}

#[test]
fn a_session_sends_what_the_rule_wants_coarse_and_visible_first() {
    let cache = cache();
    let t0 = Instant::now();
    let at = [300.0, -200.0];
    // A first session fills the cache; a second finds every node ready and sends in order at once.
    let mut first = session(&cache, at, t0);
    let mut far = Far::default();
    run(&mut first, &cache, &mut far, t0);
    assert!(far.held.len() > 20, "{} nodes", far.held.len());
    let want = wanted(&cache, at);
    assert_eq!(far.held, want, "the session sends exactly what the rule wants");
    assert!(want.iter().any(|k| k.level == 0) && want.iter().any(|k| k.level >= 4), "{want:?}");

    let mut second = session(&cache, at, t0);
    let mut far = Far::default();
    let (_, sent) = run(&mut second, &cache, &mut far, t0);
    assert_eq!(far.held, want);
    // Parents first.
    let position: BTreeMap<NodeKey, usize> = far.arrived.iter().enumerate().map(|(i, k)| (*k, i)).collect();
    for (k, i) in &position {
        if let Some(p) = k.parent().and_then(|p| position.get(&p)) {
            assert!(p < i, "{k:?} came before its parent");
        }
    }
    // The most visible first: the mean level of the first half is coarser than the second half's, and nodes near
    // the eye come before far ones of the same level.
    let half = far.arrived.len() / 2;
    let mean = |ks: &[NodeKey]| ks.iter().map(|k| f64::from(k.level)).sum::<f64>() / ks.len() as f64;
    assert!(mean(&far.arrived[..half]) > mean(&far.arrived[half..]), "{:?}", far.arrived);
    let level0: Vec<&NodeKey> = far.arrived.iter().filter(|k| k.level == 0).collect();
    let dist = |k: &NodeKey| {
        let c = k.first_cell();
        ((c.x as f32 * 64.0 + 32.0 - at[0]).powi(2) + (c.z as f32 * 64.0 + 32.0 - at[1]).powi(2)).sqrt()
    };
    let q = level0.len() / 4;
    let near: f32 = level0[..q].iter().map(|k| dist(k)).sum::<f32>() / q as f32;
    let late: f32 = level0[level0.len() - q..].iter().map(|k| dist(k)).sum::<f32>() / q as f32;
    assert!(near < late, "level-0 nodes: first quarter {near} m away on average, last quarter {late} m");
    // Records keep priority: until the last cell batch went, summaries took at most a quarter of the bytes (one
    // message of slack).
    let last_cell = sent.iter().rposition(|t| t.class == ServerMsgKind::Cells).expect("cells were sent");
    let bytes = |class| sent[..=last_cell].iter().filter(|t| t.class == class).map(|t| t.len()).sum::<usize>();
    let (cells, summaries) = (bytes(ServerMsgKind::Cells), bytes(ServerMsgKind::Summaries));
    assert!(summaries <= cells / 3 + 9 * 1024, "{summaries} B of summaries before the last of {cells} B of cells");
    assert!(summaries > 0, "summaries were interleaved, not held back until the records were done");
}

#[test]
fn summaries_are_kept_through_small_moves_and_released_when_the_viewer_leaves() {
    let cache = cache();
    let t0 = Instant::now();
    let a = [0.0, 0.0];
    let mut s = session(&cache, a, t0);
    let mut far = Far::default();
    let (mut now, _) = run(&mut s, &cache, &mut far, t0);
    let settled = far.held.clone();
    // Back and forth by 40 m: nodes at the edge of the rule stay (hysteresis), so nothing is released or sent
    // twice (`Far::take` would fail on a node sent twice).
    let mut seq = 2;
    for i in 0..6 {
        let x = if i % 2 == 0 { 40.0 } else { 0.0 };
        s.handle(now, ClientMsg::viewpoint(viewpoint(seq, [x, 0.0]))).unwrap();
        seq += 1;
        now += Duration::from_millis(300);
        (now, _) = run(&mut s, &cache, &mut far, now);
    }
    assert!(far.released.is_empty(), "small moves released {:?}", far.released);
    assert!(far.held.is_superset(&settled));
    let at_b = wanted(&cache, [40.0, 0.0]);
    assert!(at_b.is_subset(&far.held), "what the rule wants is held");
    // Far away: everything held near the old place goes, coarse before fine within each message.
    s.handle(now, ClientMsg::viewpoint(viewpoint(seq, [9000.0, 9000.0]))).unwrap();
    now += Duration::from_millis(300);
    run(&mut s, &cache, &mut far, now);
    assert!(far.held.iter().all(|k| !settled.contains(k)), "nothing near the old place is held");
    assert!(!far.released.is_empty());
    // Everything held afterwards is what is kept at the new place.
    let kept_new = wanted(&cache, [9000.0, 9000.0]);
    assert!(far.held.is_subset(&kept_new) || far.held.is_empty(), "{:?}", far.held);
}

#[test]
fn a_computed_subtree_goes_out_at_once_when_its_root_is_ready() {
    let cache = cache();
    let store = Arc::clone(&cache) as Arc<dyn WorldStore>;
    let t0 = Instant::now();
    let at = [300.0, -200.0];
    let mut s = session(&cache, at, t0);
    let mut far = Far::default();
    let drain = |s: &mut Session, far: &mut Far, now| {
        while let Some(t) = s.poll_transmit(now) {
            s.on_flushed(t.len());
            far.take(&t);
        }
    };
    drain(&mut s, &mut far, t0);
    assert!(far.held.is_empty(), "nothing is computed yet");
    // The workers compute the roots the session asked for (and the cells): the memo then holds their subtrees.
    assert!(cache.run_queued() > 0);
    // A node it asked for is ready: the far view rebuilds after NODE_REBUILD_INTERVAL, not REBUILD_INTERVAL ...
    let early = t0 + NODE_REBUILD_INTERVAL;
    assert_eq!(s.far().unwrap().due_at(&*store), Some(early));
    assert!(NODE_REBUILD_INTERVAL < REBUILD_INTERVAL);
    drain(&mut s, &mut far, early);
    // ... and that one rebuild walks down the computed subtrees: every node the rule wants whose error is known
    // (all but the leaves, which the memo does not keep) went out without the workers running again.
    let want = wanted(&cache, at);
    assert!(want.iter().any(|k| k.level == 1) && want.iter().any(|k| k.level >= 4), "{want:?}");
    assert_eq!(far.held, want);
    // The leaves the rebuild found pending come with the next.
    assert!(cache.run_queued() > 0);
    run(&mut s, &cache, &mut far, early);
    assert!(far.held.iter().any(|k| k.level == 0));
    assert_eq!(far.held, wanted(&cache, at));
}

#[test]
fn a_held_node_goes_again_once_its_cells_edits_corrected_it() {
    let cache = cache();
    let t0 = Instant::now();
    let at = [300.0, -200.0];
    let mut s = session(&cache, at, t0);
    let mut far = Far::default();
    let (now, _) = run(&mut s, &cache, &mut far, t0);
    // A cell under a held leaf 1 km from the viewer, beyond its records; three of its trees felled.
    let leaf = *far
        .held
        .iter()
        .filter(|k| k.level == 0)
        .max_by_key(|k| {
            let c = k.first_cell();
            ((c.x * 64 - 300).abs() < 1100 && (c.z * 64 + 200).abs() < 1100, c.x.abs() + c.z.abs())
        })
        .expect("leaves held");
    let cell = leaf.first_cell();
    let records = loop {
        match cache.cell(cell, None) {
            CellState::Ready(d) => break d,
            _ => assert!(cache.run_queued() > 0),
        }
    };
    assert!(records.records.len() >= 3, "{} records", records.records.len());
    let felled: Vec<u8> = records.records[..3].iter().map(|r| r.species).collect();
    let delta = CellDelta {
        cell,
        grant: 0,
        from_version: 0,
        to_version: 3,
        total: records.records.len() as u16,
        adds: vec![],
        removes: vec![0, 1, 2],
        updates: vec![],
    };
    let over: BTreeSet<NodeKey> = far.held.iter().filter(|k| k.contains(cell)).copied().collect();
    let before: BTreeMap<NodeKey, NodeSummary> = over.iter().map(|k| (*k, far.nodes[k].clone())).collect();
    let seen = cache.summary_corrections(u64::MAX).now;
    assert!(cache.correct_summaries(cell, Some(&delta)));
    assert!(!cache.correct_summaries(cell, Some(&delta)), "the same edits again change nothing");
    assert_eq!(cache.summary_corrections(seen).cells, Some(vec![cell]));
    // Every held node over the cell comes again, computed anew, each short of exactly the felled trees; nothing
    // else comes.
    far.again = over.clone();
    let arrived = far.arrived.len();
    run(&mut s, &cache, &mut far, now + Duration::from_millis(250));
    assert!(far.again.is_empty(), "not sent again: {:?}", far.again);
    assert_eq!(far.arrived[arrived..].iter().copied().collect::<BTreeSet<_>>(), over);
    let count = |n: &NodeSummary, species: u8| {
        n.species.iter().filter(|c| c.species == u16::from(species)).map(|c| c.count).sum::<u32>()
    };
    for k in &over {
        for species in felled.iter().copied().collect::<BTreeSet<u8>>() {
            let gone = felled.iter().filter(|&&f| f == species).count() as u32;
            assert_eq!(count(&far.nodes[k], species) + gone, count(&before[k], species), "{k:?}, species {species}");
        }
    }
    // The edits taken back: the nodes are the world function's again, bit for bit.
    far.again = over.clone();
    assert!(cache.correct_summaries(cell, None));
    run(&mut s, &cache, &mut far, now + Duration::from_secs(1));
    for k in &over {
        assert_eq!(far.nodes[k], before[k], "{k:?}");
    }
}
