//! The far view computed in the page against the scripted server: the nodes laid into the state are the ones the
//! server session's selection picks over the world's summaries, none is computed while a granted cell waits, a
//! slice with no time left computes one step, and what is asked stays within the bound.

use std::collections::BTreeMap;

use canopy_protocol::farview::{DEFAULT_FOV_DEG, Eye, MAX_SESSION_NODES, NodeState, Selection, Take};
use canopy_protocol::summary::{NodeKey, NodeSummary, overlaps, root_level};
use canopy_worlds::world::far::Summaries;

use super::*;
use crate::far::default_view;

/// A session holding the function, the species and every inner cell granted (`expand`: and expanded).
fn granted(expand: bool) -> (Session, usize) {
    let mut s = welcomed();
    let lane = s.open_lane();
    let mut bytes = streaming(ServerStreaming::Function(WorldFunction { manifest: MANIFEST.into() }));
    bytes.extend(streaming(ServerStreaming::Species(SpeciesData { id: 0, graph: worm() })));
    let vp = *s.state().viewpoint().unwrap();
    for (i, c) in Aoi::new(&vp, &params()).inner_cells(&grid()).iter().enumerate() {
        let g = CellGrant { cell: *c, grant: i as u32 + 1, version: 0, delta: None };
        bytes.extend(streaming(ServerStreaming::Grant(g)));
    }
    s.on_lane(lane, &bytes);
    if expand {
        s.expand(&mut || true);
    }
    assert_eq!(s.link(), Link::Streaming, "{:?}", s.error());
    (s, lane)
}

/// The server session's selection for the scripted world, every node computed on the spot, and the nodes it
/// handed out and did not release.
struct Reference {
    memo: Summaries,
    selection: Selection,
    held: BTreeMap<NodeKey, NodeSummary>,
}

impl Reference {
    fn new() -> Reference {
        let world = World::from_function("t", MANIFEST, &[SpeciesGraph::decode(&worm()).unwrap()], None).unwrap();
        Reference { memo: Summaries::new(Arc::new(world)), selection: Selection::default(), held: BTreeMap::new() }
    }

    /// Walk again for the session's viewpoint and the eye at `altitude`, and hand out everything.
    fn follow(&mut self, s: &Session, altitude: f32) -> &BTreeMap<NodeKey, NodeSummary> {
        let (vp, aoi) = (s.state().viewpoint().unwrap(), s.state().aoi().unwrap());
        let eye = Eye::new(aoi, vp.heading(), DEFAULT_FOV_DEG);
        let levels = root_level(grid().cell_size);
        let refine = eye.refine(default_view(altitude), &grid(), levels);
        let memo = &mut self.memo;
        self.selection.rebuild(&refine, &eye, |k| {
            if !k.is_valid() || k.level > levels || !overlaps(&grid(), k) {
                return NodeState::Unavailable;
            }
            NodeState::Ready(memo.get(k).error)
        });
        while self.selection.has_work() {
            let before = self.held.len();
            for k in self.selection.releases(usize::MAX) {
                self.held.remove(&k);
            }
            self.selection.next(levels, |k| {
                let n = memo.get(k);
                self.held.insert(k, (*n).clone());
                Take::Node(n.error)
            });
            if self.held.len() == before && !self.selection.has_releases() {
                break;
            }
        }
        &self.held
    }
}

/// Run slices at `t` milliseconds on, 50 ms apart, until one computes nothing and nothing is left to do.
fn run(s: &mut Session, mut t: u64) -> (u64, usize) {
    let mut slices = 0;
    loop {
        let n = s.far_step(Duration::from_millis(t), &mut || true);
        t += 50;
        slices += 1;
        assert!(slices < 10_000, "the far field never settles");
        assert!(s.far().queued() <= MAX_SESSION_NODES);
        if n == 0 && s.far().settled() {
            return (t, slices);
        }
    }
}

#[test]
fn the_far_nodes_computed_in_the_page_are_the_selections_and_wait_for_the_cells() {
    let (mut s, _) = granted(false);
    assert!(s.pending() > 0);
    // Cells first: nothing is computed while one waits (the far view is said all the same).
    assert_eq!(s.far_step(Duration::ZERO, &mut || true), 0);
    assert_eq!((s.far().queued(), s.far().computed(), s.state().summaries().len()), (0, 0, 0));
    assert_eq!(s.state().far_view(), Some(&default_view(DEFAULT_ALTITUDE)));
    s.expand(&mut || true);
    assert_eq!(s.pending(), 0);

    // No time left: one step all the same (a block, or a node), coarse first.
    assert!(s.far_step(Duration::from_millis(1), &mut || false) <= 1);
    assert!(s.far().queued() > 0, "the roots are asked for");
    let (t, _) = run(&mut s, 2);
    let mut reference = Reference::new();
    let want = reference.follow(&s, DEFAULT_ALTITUDE).clone();
    assert!(!want.is_empty());
    let held: BTreeMap<NodeKey, NodeSummary> = s.state().summaries().iter().map(|(k, n)| (*k, (**n).clone())).collect();
    assert_eq!(held.keys().collect::<Vec<_>>(), want.keys().collect::<Vec<_>>());
    assert!(held == want, "the same nodes, bit for bit");
    assert!(held.len() <= MAX_SESSION_NODES);
    assert_eq!(PageState::of(&s, [16.0, 30.0, 16.0], 0.0).far_nodes, held.len());
    // The page computes its far field itself: the server is told the far view once (for the edited cells within
    // it), and nothing else but digests.
    let out = sent(&s.take_outbox());
    let views = out.iter().filter(|m| matches!(m, ClientMsg::Streaming(ClientStreaming::FarView(_)))).count();
    assert_eq!(views, 1);
    for m in out {
        let ok = matches!(m, ClientMsg::Streaming(ClientStreaming::Digest(_) | ClientStreaming::FarView(_)));
        assert!(ok, "{m:?}");
    }

    let before: Vec<NodeKey> = held.keys().copied().collect();
    // The viewpoint moves and the eye climbs: the selection follows, within the bound.
    assert!(s.move_to([-90.0, -70.0], 2.0, [0.0, 0.0], Duration::from_secs(1)));
    s.set_altitude(3000.0);
    run(&mut s, t);
    assert_eq!(s.state().far_view().unwrap().altitude, 3000.0);
    let want = reference.follow(&s, 3000.0);
    let held: Vec<NodeKey> = s.state().summaries().keys().copied().collect();
    assert_eq!(held, want.keys().copied().collect::<Vec<_>>());
    assert_ne!(held, before, "another selection");
    assert!(held.len() <= MAX_SESSION_NODES);
}

#[test]
fn a_far_cell_corrects_the_nodes_the_page_holds_over_it() {
    use canopy_protocol::edit::CellDelta;
    use canopy_protocol::messages::FarCell;
    let (mut s, lane) = granted(true);
    run(&mut s, 0);
    // The finest node held over a cell the page does not hold.
    let (key, cell) = s
        .state()
        .summaries()
        .keys()
        .flat_map(|k| {
            let first = k.first_cell();
            (0..k.side()).map(move |i| (*k, CellCoord::new(first.x + i, first.z)))
        })
        .filter(|(_, c)| grid().contains(*c) && !s.state().cells().contains_key(c))
        .min_by_key(|(k, _)| k.level)
        .expect("a node beyond the held cells");
    let count = |s: &Session| s.state().summaries()[&key].species.iter().map(|n| n.count).sum::<u32>();
    let before = count(&s);
    let world = World::from_function("t", MANIFEST, &[SpeciesGraph::decode(&worm()).unwrap()], None).unwrap();
    let total = world.expand_cell(canopy_worlds::world::far::cell_key(cell)).len() as u16;
    assert!(total >= 3 && before >= 3, "{total} instances in the cell, {before} in {key:?}");
    let delta = CellDelta {
        cell,
        grant: 0,
        from_version: 0,
        to_version: 3,
        total,
        adds: vec![],
        removes: vec![0, 1, 2],
        updates: vec![],
    };
    s.on_lane(lane, &streaming(ServerStreaming::FarCell(FarCell { cell, delta })));
    assert!(s.far().busy(), "the far cell waits for a step");
    run(&mut s, 10_000);
    assert_eq!(count(&s), before - 3, "{key:?}");
}
