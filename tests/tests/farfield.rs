//! The far field a client computes itself (issue 30, item 5), over real QUIC on loopback: a client that expands
//! its cells computes the far view's summary nodes from the world function, and ends holding exactly the nodes,
//! bit for bit, that the server sends a client that takes records from the same place, after moves too; the server
//! sends it none, and a second client of the same process computes none again. Edits reach both far views: an
//! editor's fells in a cell 1.4 km away lower the count of the node each client holds over it by exactly what was
//! felled (the expanding client is told of the cell; the server corrects its own nodes and sends the other client
//! the node again), and the two hold the same nodes after.

use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;

use canopy_client::expand::Expander;
use canopy_client::net::endpoint;
use canopy_client::{ConnectConfig, Connection};
use canopy_protocol::aoi::Viewpoint;
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_protocol::messages::{CellMode, ServerMsgKind, Welcome};
use canopy_protocol::summary::{FarView, NodeKey};
use canopy_protocol::{CellCoord, InstanceId};
use canopy_server::edits::{EditStore, MemoryEditStore};
use canopy_server::session::{Editors, SessionConfig, editor_line};
use canopy_server::{CellCache, CellCacheConfig, Edits, ServeOptions, ServerConfig, serve_store};
use canopy_test_support::{forest, pinned};

use crate::support::ALICE;

/// Connect with `cfg` at (300, −200), ask for `view` and wait until the area of interest is complete and no
/// summary node has come for a while.
async fn settled(cfg: &ConnectConfig, view: FarView) -> Connection {
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let place = |_: &Welcome| Viewpoint::at(0, [300.0, -200.0], 100.0);
    let mut c = Connection::connect(&ep, cfg, None, place).await.unwrap();
    assert!(c.set_far_view(view).await.unwrap());
    settle(&mut c).await;
    c
}

/// Wait until the area of interest is complete and no summary node has come for a while.
async fn settle(c: &mut Connection) {
    c.wait_complete(Duration::from_secs(60)).await.unwrap();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    let mut quiet = 0;
    while quiet < 3 && tokio::time::Instant::now() < deadline {
        let generation = c.state().summaries_generation();
        if let Ok(r) = tokio::time::timeout(Duration::from_millis(700), c.next_event()).await {
            r.unwrap();
        }
        quiet = if c.state().summaries_generation() == generation { quiet + 1 } else { 0 };
    }
}

/// Both clients' far fields hold the same nodes, bit for bit.
fn same_nodes(records: &Connection, expands: &Connection) {
    let (sent, computed) = (records.state().summaries(), expands.state().summaries());
    assert_eq!(sent.keys().collect::<Vec<_>>(), computed.keys().collect::<Vec<_>>(), "the same nodes");
    for (k, n) in sent {
        assert_eq!(**n, *computed[k], "node {k:?}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_expands_computes_the_far_view_the_server_would_send() {
    let cfg = CellCacheConfig { limit_bytes: 64 << 20, workers: 2, ..CellCacheConfig::default() };
    let store = CellCache::new((**forest()).clone(), cfg).expect("the default world builds a store").shared();
    let server_cfg = ServerConfig { listen: "127.0.0.1:0".parse().unwrap(), ..ServerConfig::default() };
    let server =
        serve_store(store, ServeOptions { server: server_cfg, ..ServeOptions::default() }).await.expect("starts");
    let view = FarView { error_px: 8.0, height_px: 720, fov_y: 1.0, range: 2500.0, altitude: 120.0 };

    let records = settled(&pinned(&server), view).await;
    assert_eq!(records.state().cell_mode(), CellMode::Records);
    let mut cfg = pinned(&server);
    let expander = Expander::new(2, 8 << 20);
    cfg.expander = Some(Arc::clone(&expander));
    let expands = settled(&cfg, view).await;
    assert!(matches!(expands.state().cell_mode(), CellMode::Expand { .. }));

    let sent = records.state().summaries();
    assert!(sent.len() > 20, "the server sent {} nodes", sent.len());
    assert!(sent.keys().any(|k| k.level == 0) && sent.keys().any(|k| k.level >= 4), "coarse and fine nodes");
    same_nodes(&records, &expands);
    // The memo is shared by the clients of one process: a second client there computes no node again.
    let far_jobs = expander.stats().far_jobs.load(Relaxed);
    assert!(far_jobs > 0, "the expander computed the far field");
    let again = settled(&cfg, view).await;
    same_nodes(&records, &again);
    assert_eq!(expander.stats().far_jobs.load(Relaxed), far_jobs, "nodes computed again");
    again.close();
    // A move, then two in quick succession (back, and again: the second inside the walks' rate limit, every node
    // already computed, so nothing but the held-back walk wakes the client), then rest: both follow to the end.
    let (mut records, mut expands) = (records, expands);
    let there = Viewpoint::at(1, [-700.0, 500.0], 100.0);
    for c in [&mut records, &mut expands] {
        c.set_viewpoint(there).await.unwrap();
        settle(c).await;
    }
    for c in [&mut records, &mut expands] {
        c.set_viewpoint(Viewpoint::at(2, [300.0, -200.0], 100.0)).await.unwrap();
        // What has arrived is applied (the expanding client walks for the first move now), then the second.
        while let Some(r) = c.try_next_event() {
            r.unwrap();
        }
        c.set_viewpoint(Viewpoint { seq: 3, ..there }).await.unwrap();
    }
    settle(&mut records).await;
    settle(&mut expands).await;
    assert!(records.state().summaries().keys().any(|k| k.level == 0));
    same_nodes(&records, &expands);
    assert!(records.frame_bytes_received()[ServerMsgKind::Summaries] > 0);
    assert_eq!(expands.frame_bytes_received()[ServerMsgKind::Summaries], 0, "the server sent summaries");
    records.close();
    expands.close();
    server.shutdown(Duration::from_secs(1)).await;
}

/// Species ids and their counts in a node.
type Counts = Vec<(u16, u32)>;

/// The species counts of the finest node `c` holds over `cell`, and its key.
fn counts_over(c: &Connection, cell: CellCoord) -> Option<(NodeKey, Counts)> {
    let held = c.state().summaries();
    let (k, n) = held.iter().filter(|(k, _)| k.contains(cell)).min_by_key(|(k, _)| k.level)?;
    Some((*k, n.species.iter().map(|s| (s.species, s.count)).collect()))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_editors_fells_reach_the_far_views_of_clients_that_expand_and_that_take_records() {
    let cfg = CellCacheConfig { limit_bytes: 64 << 20, workers: 2, ..CellCacheConfig::default() };
    let store = CellCache::new((**forest()).clone(), cfg).expect("the default world builds a store").shared();
    let editors = Editors::parse("editors", &editor_line("alice", &ALICE, None, Some(1000))).unwrap();
    let session = SessionConfig { editors: Some(Arc::new(editors)), ..SessionConfig::default() };
    let server_cfg = ServerConfig { listen: "127.0.0.1:0".parse().unwrap(), session, ..ServerConfig::default() };
    let edits: Arc<dyn EditStore> = Arc::new(MemoryEditStore::new());
    let opts = ServeOptions { server: server_cfg, edits: Edits::Store(edits), ..ServeOptions::default() };
    let server = serve_store(store, opts).await.expect("starts");

    // Two observers 1.4 km east of the editor, looking west at it: one expands its cells and computes its far
    // view, the other takes records and summaries from the server.
    let mut cfg = pinned(&server);
    cfg.expander = Some(Expander::new(2, 8 << 20));
    let view = FarView { error_px: 8.0, height_px: 720, fov_y: 1.0, range: 2500.0, altitude: 120.0 };
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let west = Viewpoint { yaw: -std::f32::consts::FRAC_PI_2, ..Viewpoint::at(0, [700.0, -200.0], 100.0) };
    let mut observers = Vec::new();
    for cfg in [cfg, pinned(&server)] {
        let mut observer = Connection::connect(&ep, &cfg, None, |_: &Welcome| west).await.unwrap();
        assert!(observer.set_far_view(view).await.unwrap());
        settle(&mut observer).await;
        observers.push(observer);
    }
    assert_eq!(observers[1].state().cell_mode(), CellMode::Records);
    same_nodes(&observers[1], &observers[0]);

    // The editor fells three trees of one species in the fullest cell of its area of interest.
    let mut editor_cfg = pinned(&server);
    editor_cfg.token = Some(ALICE.to_vec());
    let place = |_: &Welcome| Viewpoint::at(0, [-700.0, -200.0], 60.0);
    let mut editor = Connection::connect(&ep, &editor_cfg, None, place).await.unwrap();
    editor.wait_complete(Duration::from_secs(60)).await.unwrap();
    let flat = |_: f32, _: f32| 0.0;
    let mut by_cell: std::collections::BTreeMap<(CellCoord, u8), Vec<InstanceId>> = Default::default();
    for v in editor.state().instances(&flat) {
        by_cell.entry((v.id.cell(), v.species)).or_default().push(v.id);
    }
    let ((cell, species), ids) = by_cell.into_iter().max_by_key(|(_, ids)| ids.len()).expect("trees near the editor");
    assert!(ids.len() >= 3, "{} trees", ids.len());
    let (key, before) = counts_over(&observers[0], cell).expect("the observer's far view holds the cell");
    assert_eq!(counts_over(&observers[1], cell), Some((key, before.clone())));
    let count = |counts: &[(u16, u32)]| counts.iter().find(|s| s.0 == u16::from(species)).map_or(0, |s| s.1);
    assert!(count(&before) >= 3, "{key:?}: {before:?}");
    let summary_bytes = observers[1].frame_bytes_received()[ServerMsgKind::Summaries];
    for id in &ids[..3] {
        let request = editor.edit(EditOp::Fell { id: *id }).await.unwrap();
        loop {
            match editor.next_event().await.unwrap() {
                canopy_client::state::Event::EditResult(r) if r.request == request => {
                    assert!(matches!(r.outcome, EditOutcome::Ok { .. }), "{:?}", r.outcome);
                    break;
                }
                _ => {}
            }
        }
    }

    // Each observer's node over the cell loses exactly the three trees, nothing else: the expanding one told of
    // the cell, the other sent the node again as the server corrected it. Both are read in turn, each time
    // measured from the last fell's answer.
    let acked = tokio::time::Instant::now();
    let deadline = acked + Duration::from_secs(60);
    let mut after: [Option<(Duration, Counts)>; 2] = [None, None];
    while after.iter().any(Option::is_none) {
        for (i, observer) in observers.iter_mut().enumerate() {
            if let Ok(r) = tokio::time::timeout(Duration::from_millis(20), observer.next_event()).await {
                r.unwrap();
            }
            let now = counts_over(observer, cell).expect("still held");
            if after[i].is_none() && now.0 == key && count(&now.1) + 3 == count(&before) {
                after[i] = Some((acked.elapsed(), now.1));
            }
        }
        assert!(tokio::time::Instant::now() < deadline, "{key:?} {before:?}, now {after:?}");
    }
    let others = |c: &[(u16, u32)]| c.iter().filter(|s| s.0 != u16::from(species)).copied().collect::<Vec<_>>();
    for ((elapsed, counts), (observer, kind)) in
        after.into_iter().flatten().zip(observers.iter().zip(["expands", "takes records"]))
    {
        eprintln!(
            "far cell {cell:?}: the node {key:?} of the client that {kind} corrected {elapsed:.0?} after the last \
             fell's answer; {} far-cell bytes received",
            observer.frame_bytes_received()[ServerMsgKind::FarCell]
        );
        assert_eq!(others(&counts), others(&before), "{kind}");
    }
    let [expands, records] = &mut observers[..] else { unreachable!() };
    assert!(expands.frame_bytes_received()[ServerMsgKind::FarCell] > 0);
    // Told of the cell once a version at most (the edits may arrive together).
    assert!((1..=3).contains(&expands.state().stats().far_cells), "{}", expands.state().stats().far_cells);
    assert_eq!(records.frame_bytes_received()[ServerMsgKind::FarCell], 0);
    assert!(records.frame_bytes_received()[ServerMsgKind::Summaries] > summary_bytes, "the node sent again");
    // Both hold the same nodes again, bit for bit.
    settle(expands).await;
    settle(records).await;
    same_nodes(records, expands);
    editor.close();
    for o in observers {
        o.close();
    }
    server.shutdown(Duration::from_secs(1)).await;
}
