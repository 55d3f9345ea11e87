//! Live edits without sockets: sessions, client states and the edit pipeline over a live store, paired like
//! `streaming_core.rs` (lanes delivered in a random interleaving). Concurrent edits of one cell from two sessions
//! apply in one order and every client converges on the store; denied and invalid edits leave no trace; a version
//! gap brings the whole cell again; a client that reconnects gets only what changed since its versions.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::support::*;
use canopy_client::state::{ClientState, Event};
use canopy_protocol::edit::{CellDelta, EditOp, EditOutcome};
use canopy_protocol::messages::ServerMsgKind;
use canopy_protocol::messages::ServerStreaming;
use canopy_protocol::{CellCoord, InstanceId, ServerMsg};
use canopy_server::edits::{EditStore, EditStoreError, MemoryEditStore, StoredEdit};

/// The part of a test store that passes through to the memory store it wraps (`self.$inner`).
macro_rules! passes_through {
    ($inner:tt) => {
        fn cells(&self) -> Result<Vec<(CellCoord, u32)>, EditStoreError> {
            self.$inner.cells()
        }
        fn count(&self) -> Result<u64, EditStoreError> {
            self.$inner.count()
        }
        fn describe(&self) -> String {
            std::any::type_name::<Self>().into()
        }
    };
}

/// A store that, when `fail` is set, keeps only the first edit of a group and then fails (a commit that failed
/// after part of it reached the disk, or a store without multi-key transactions).
struct Flaky {
    inner: Arc<MemoryEditStore>,
    fail: std::sync::atomic::AtomicBool,
    /// Held by the test to keep the writer in its first append while more edits queue (one group after it).
    hold: std::sync::Mutex<()>,
}

impl EditStore for Flaky {
    fn append(&self, edits: &[StoredEdit]) -> Result<(), EditStoreError> {
        let _held = self.hold.lock().unwrap();
        if self.fail.load(std::sync::atomic::Ordering::SeqCst) {
            self.inner.append(&edits[..1])?;
            return Err(EditStoreError::Io("the disk failed".into()));
        }
        self.inner.append(edits)
    }
    fn load(&self, c: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError> {
        self.inner.load(c)
    }
    passes_through!(inner);
}

#[test]
fn concurrent_edits_of_one_cell_apply_in_one_order_and_every_client_converges() {
    let w = world();
    let mut a = Pair::connect(&w, ClientState::new(), Some(ALICE), 1);
    let mut b = Pair::connect(&w, ClientState::new(), Some(BOB), 2);
    let mut watcher = Pair::connect(&w, ClientState::new(), None, 3);
    settle(&w, &mut [&mut a, &mut b, &mut watcher]);
    let before = sorted(a.client.instances(&|_, _| 0.0).collect());
    let c = CellCoord::new(1, 1);
    // Cell (1, 1) has 3 instances (0, 1, 2). Both editors change it at once, in rounds.
    let mut asked = Vec::new();
    for round in 0..5 {
        let x = 32.0 + 4.0 + round as f32 * 5.0;
        asked.push(a.edit(EditOp::Plant { species: 1, x, z: 40.0, params: vec![(0, 2.5 + round as f32)] }));
        asked.push(b.edit(EditOp::Set { id: id(1, 1, 1), params: vec![(0, round as f32)] }));
        asked.push(b.edit(EditOp::Plant { species: 0, x: 60.0, z: 33.0 + round as f32, params: vec![] }));
        if round == 2 {
            asked.push(a.edit(EditOp::Fell { id: id(1, 1, 0) }));
            asked.push(b.edit(EditOp::Fell { id: id(1, 1, 0) }));
        }
        a.step(&w);
        b.step(&w);
    }
    settle(&w, &mut [&mut a, &mut b, &mut watcher]);
    let results: Vec<&EditOutcome> = a.results.values().chain(b.results.values()).collect();
    assert_eq!(results.len(), asked.len(), "every edit answered");
    let oks: Vec<u32> = results
        .iter()
        .filter_map(|o| match o {
            EditOutcome::Ok { version, .. } => Some(*version),
            _ => None,
        })
        .collect();
    // One of the two fells of instance 0 lost: it was felled already.
    assert_eq!(oks.len(), asked.len() - 1);
    let mut versions = oks.clone();
    versions.sort_unstable();
    assert_eq!(versions, (1..=oks.len() as u32).collect::<Vec<_>>(), "one order: versions 1..n, none twice");
    assert_eq!(version(&w, c), oks.len() as u32);
    assert_eq!(w.edits.count().unwrap(), oks.len() as u64);
    // Every client holds what the store holds.
    let want = expected(&w);
    assert_ne!(want, before);
    for p in [&a, &b, &watcher] {
        assert!(p.client.is_complete());
        assert_eq!(sorted(p.client.instances(&|_, _| 0.0).collect()), want);
        assert_eq!(p.client.cells()[&c].version, oks.len() as u32);
        assert!(p.client.stats().deltas > 0, "changes came as deltas");
    }
    // 10 plants, instance 0 felled, instance 1's parameter 0 last set to 4.
    let cell: Vec<_> = want.iter().filter(|i| InstanceId(i.0).cell() == c).collect();
    assert_eq!(cell.len(), 3 - 1 + 10);
    let one = cell.iter().find(|i| InstanceId(i.0).index() == 1).unwrap();
    assert_eq!(one.3, vec![(0, 4f32.to_bits())]);
}

#[test]
fn denied_and_invalid_edits_leave_no_trace() {
    let w = world();
    let mut reader = Pair::connect(&w, ClientState::new(), None, 4);
    let mut stranger = Pair::connect(&w, ClientState::new(), Some([9; 32]), 5);
    let mut carol = Pair::connect(&w, ClientState::new(), Some(CAROL), 6);
    let mut alice = Pair::connect(&w, ClientState::new(), Some(ALICE), 7);
    settle(&w, &mut [&mut reader, &mut stranger, &mut carol, &mut alice]);
    let before = expected(&w);
    let plant = EditOp::Plant { species: 0, x: -20.0, z: 5.0, params: vec![] };
    let r0 = reader.edit(plant.clone());
    let r1 = stranger.edit(plant.clone());
    let east = carol.edit(EditOp::Plant { species: 0, x: 20.0, z: 5.0, params: vec![] });
    let fell_east = carol.edit(EditOp::Fell { id: id(1, 1, 0) });
    let invalid = [
        alice.edit(EditOp::Plant { species: 7, x: 5.0, z: 5.0, params: vec![] }),
        alice.edit(EditOp::Plant { species: 0, x: 500.0, z: 5.0, params: vec![] }),
        // In a cell of the grid, past the world's bounds.
        alice.edit(EditOp::Plant { species: 0, x: 124.0, z: 5.0, params: vec![] }),
        alice.edit(EditOp::Fell { id: id(0, 0, 40) }),
        alice.edit(EditOp::Fell { id: id(90, 0, 0) }),
        alice.edit(EditOp::Set { id: id(0, 0, 0), params: vec![(60, 1.0)] }),
        alice.edit(EditOp::Set { id: id(0, 0, 0), params: vec![(0, 1.0e9)] }),
    ];
    settle(&w, &mut [&mut reader, &mut stranger, &mut carol, &mut alice]);
    for (p, r) in [(&reader, r0), (&stranger, r1), (&carol, east), (&carol, fell_east)] {
        assert!(matches!(p.results[&r], EditOutcome::Denied(_)), "{:?}", p.results[&r]);
    }
    for r in invalid {
        assert!(matches!(alice.results[&r], EditOutcome::Invalid(_)), "{:?}", alice.results[&r]);
    }
    assert_eq!(w.edits.count().unwrap(), 0);
    assert_eq!(expected(&w), before);
    for p in [&reader, &stranger, &carol, &alice] {
        assert_eq!(p.server.stats().deltas, 0);
        assert!(p.client.cells().values().all(|h| h.version == 0));
    }
    // Just inside the bounds is inside the world.
    let inside = alice.edit(EditOp::Plant { species: 0, x: 119.5, z: 5.0, params: vec![] });
    settle(&w, &mut [&mut alice]);
    assert!(matches!(alice.results[&inside], EditOutcome::Ok { .. }), "{:?}", alice.results[&inside]);
    // Carol's own region works.
    let west = carol.edit(EditOp::Plant { species: 0, x: -60.0, z: 5.0, params: vec![] });
    // Dave's rate: 3 a second, a burst of 6, all asked at one instant: the rest are denied.
    let mut dave = Pair::connect(&w, ClientState::new(), Some(DAVE), 13);
    let mine: Vec<u32> =
        (0..8).map(|i| dave.edit(EditOp::Plant { species: 0, x: 60.0 + i as f32, z: 5.0, params: vec![] })).collect();
    settle(&w, &mut [&mut carol, &mut dave]);
    assert!(matches!(carol.results[&west], EditOutcome::Ok { .. }));
    let ok = mine.iter().filter(|r| matches!(dave.results[r], EditOutcome::Ok { .. })).count();
    assert_eq!(ok, 6);
    assert!(mine.iter().all(|r| !matches!(dave.results[r], EditOutcome::Invalid(_))));
    assert_eq!(w.edits.count().unwrap(), 8);
}

/// Hand `p`'s client a delta of held cell `c` from a version it does not hold (as if one had been lost): a gap.
fn gap(p: &mut Pair, c: CellCoord) -> CellDelta {
    let h = &p.client.cells()[&c];
    let stray = CellDelta {
        cell: c,
        grant: h.grant,
        from_version: h.version + 4,
        to_version: h.version + 5,
        total: h.total,
        adds: vec![],
        removes: vec![],
        updates: vec![],
    };
    assert_eq!(p.client.handle(ServerMsg::Streaming(ServerStreaming::Delta(stray.clone()))), Ok(Event::Gap(c)));
    stray
}

#[test]
fn a_version_gap_brings_the_whole_cell_at_its_current_version() {
    let w = world();
    let mut a = Pair::connect(&w, ClientState::new(), Some(ALICE), 8);
    settle(&w, &mut [&mut a]);
    let c = CellCoord::new(0, 0);
    a.edit(EditOp::Plant { species: 1, x: 3.0, z: 3.0, params: vec![] });
    settle(&w, &mut [&mut a]);
    assert_eq!(a.client.cells()[&c].version, 1);
    // A delta that does not start at the version held (as if one had been lost) is a gap: the client asks again.
    let grant = a.client.cells()[&c].grant;
    let stray = gap(&mut a, c);
    // The deltas that follow while the cell comes again ask nothing more: one refresh a gap (one a delta would
    // flood the server's budget of requests under a stream of edits).
    for v in 6..40 {
        let next = CellDelta { from_version: v, to_version: v + 1, ..stray.clone() };
        assert_eq!(a.client.handle(ServerMsg::Streaming(ServerStreaming::Delta(next))), Ok(Event::Dropped));
    }
    let batches = a.server.stats().messages[ServerMsgKind::Cells];
    let refresh = a.client.refresh(c).unwrap();
    a.server.handle(a.now, refresh).unwrap();
    settle(&w, &mut [&mut a]);
    assert!(a.server.stats().messages[ServerMsgKind::Cells] > batches, "the cell came again");
    assert!(a.client.cells()[&c].grant > grant);
    assert_eq!(a.client.cells()[&c].version, 1);
    assert_eq!(sorted(a.client.instances(&|_, _| 0.0).collect()), expected(&w));
}

#[test]
fn a_client_that_reconnects_gets_exactly_the_missing_deltas() {
    let w = world();
    let mut a = Pair::connect(&w, ClientState::new(), Some(ALICE), 10);
    settle(&w, &mut [&mut a]);
    a.edit(EditOp::Plant { species: 1, x: 3.0, z: 3.0, params: vec![] });
    settle(&w, &mut [&mut a]);
    // A finds a gap in cell (0, 0) and goes away before the cell comes again: resumed, its deltas apply again.
    gap(&mut a, CellCoord::new(0, 0));
    // A goes away holding every cell, cell (0, 0) at version 1; B edits two cells meanwhile.
    let held = a.client.cells().len();
    let state = std::mem::take(&mut a.client);
    drop(a);
    let mut b = Pair::connect(&w, ClientState::new(), Some(BOB), 11);
    settle(&w, &mut [&mut b]);
    b.edit(EditOp::Fell { id: id(0, 0, 0) });
    b.edit(EditOp::Plant { species: 0, x: -50.0, z: -50.0, params: vec![(0, 1.0)] });
    b.edit(EditOp::Set { id: id(-2, -2, 0), params: vec![(0, 8.0)] });
    settle(&w, &mut [&mut b]);
    let mut again = Pair::connect(&w, ClientState::resuming(state), Some(ALICE), 12);
    settle(&w, &mut [&mut again]);
    assert!(again.client.is_complete());
    assert_eq!(again.client.cells().len(), held);
    let stats = again.server.stats();
    assert_eq!(stats.messages[ServerMsgKind::Cells], 0, "no cell sent again");
    assert_eq!(stats.messages[ServerMsgKind::Species], 0, "species come from the cache, not resent");
    assert_eq!(stats.deltas, 2, "a delta for each changed cell");
    assert_eq!(stats.messages[ServerMsgKind::Delta], 2);
    assert_eq!(again.client.cells()[&CellCoord::new(0, 0)].version, 2);
    assert_eq!(again.client.cells()[&CellCoord::new(-2, -2)].version, 2);
    assert_eq!(sorted(again.client.instances(&|_, _| 0.0).collect()), expected(&w));
}

#[test]
fn a_failed_write_acknowledges_exactly_what_the_store_kept() {
    let inner = Arc::new(MemoryEditStore::new());
    let flaky = Arc::new(Flaky {
        inner: Arc::clone(&inner),
        fail: std::sync::atomic::AtomicBool::new(false),
        hold: std::sync::Mutex::new(()),
    });
    let w = world_over(Arc::clone(&flaky) as Arc<dyn EditStore>);
    let mut a = Pair::connect(&w, ClientState::new(), Some(ALICE), 14);
    let mut watcher = Pair::connect(&w, ClientState::new(), None, 15);
    settle(&w, &mut [&mut a, &mut watcher]);
    flaky.fail.store(true, std::sync::atomic::Ordering::SeqCst);
    // Edits of one cell asked at once: each group the writer takes, the store keeps only its first of. The writer
    // is held in its first append while the rest queue, so they form at most two groups.
    let gate = flaky.hold.lock().unwrap();
    let asked: Vec<u32> =
        (0..4).map(|i| a.edit(EditOp::Plant { species: 0, x: 3.0 + i as f32, z: 3.0, params: vec![] })).collect();
    a.step(&w);
    std::thread::sleep(Duration::from_millis(50));
    drop(gate);
    settle(&w, &mut [&mut a, &mut watcher]);
    let mut oks: Vec<u32> = asked
        .iter()
        .filter_map(|r| match &a.results[r] {
            EditOutcome::Ok { version, .. } => Some(*version),
            EditOutcome::Denied(_) => None,
            other => panic!("{other:?}"),
        })
        .collect();
    oks.sort_unstable();
    // Exactly what the store kept is acknowledged, at consecutive versions; the rest is refused.
    assert!(!oks.is_empty() && oks.len() < asked.len(), "{:?}", a.results);
    assert_eq!(inner.count().unwrap(), oks.len() as u64);
    assert_eq!(oks, (1..=oks.len() as u32).collect::<Vec<_>>());
    assert_eq!(version(&w, CellCoord::new(0, 0)), oks.len() as u32);
    // Every client sees the edit that was kept, and only it.
    let want = expected(&w);
    for p in [&a, &watcher] {
        assert_eq!(sorted(p.client.instances(&|_, _| 0.0).collect()), want);
    }
    // The store works again: the next edit takes the next version.
    flaky.fail.store(false, std::sync::atomic::Ordering::SeqCst);
    let next = a.edit(EditOp::Fell { id: id(0, 0, 0) });
    settle(&w, &mut [&mut a, &mut watcher]);
    assert!(matches!(a.results[&next], EditOutcome::Ok { version, .. } if version == oks.len() as u32 + 1));
}

/// A store whose reads take long (an edit store a network away).
struct Slow(Arc<MemoryEditStore>);

impl EditStore for Slow {
    fn append(&self, edits: &[StoredEdit]) -> Result<(), EditStoreError> {
        self.0.append(edits)
    }
    fn load(&self, c: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError> {
        if c == CellCoord::new(0, 0) {
            std::thread::sleep(Duration::from_millis(1000));
        }
        self.0.load(c)
    }
    passes_through!(0);
}

#[test]
fn a_slow_edit_store_never_blocks_a_session() {
    let inner = Arc::new(MemoryEditStore::new());
    let w = world_over(Arc::new(Slow(Arc::clone(&inner))) as Arc<dyn EditStore>);
    let mut p = Pair::connect(&w, ClientState::new(), None, 16);
    // Cell (0, 0)'s log takes a second to read: the session sends the other cells meanwhile, never waiting.
    let started = Instant::now();
    let mut slowest = Duration::ZERO;
    while !p.client.is_complete() {
        assert!(started.elapsed() < Duration::from_secs(20), "never completed");
        let t = Instant::now();
        if !p.step(&w) {
            std::thread::sleep(Duration::from_millis(5));
        }
        slowest = slowest.max(t.elapsed());
    }
    assert!(started.elapsed() >= Duration::from_millis(1000), "the read really was slow");
    assert!(slowest < Duration::from_millis(500), "a step waited {slowest:?} for a read");
    assert_eq!(sorted(p.client.instances(&|_, _| 0.0).collect()), expected(&w));
}

#[test]
fn a_flood_of_refused_edits_ends_the_session_instead_of_queueing_answers() {
    let w = world();
    let mut reader = Pair::connect(&w, ClientState::new(), None, 17);
    settle(&w, &mut [&mut reader]);
    let mut refused = 0;
    let ended = (0..1_000).find_map(|i| {
        let (_, msg) =
            reader.client.edit(EditOp::Plant { species: 0, x: i as f32 * 0.01, z: 5.0, params: vec![] }).unwrap();
        match reader.server.handle(reader.now, msg) {
            Ok(()) => {
                refused += 1;
                None
            }
            Err(e) => Some(e),
        }
    });
    let e = ended.expect("the flood ended the session");
    assert_eq!(e.close_code(), canopy_protocol::CloseCode::Invalid);
    // About the burst of the viewpoint budget (100, and what refilled while the pair settled).
    assert!((100..=110).contains(&refused), "{refused} refused before the end");
    assert_eq!(reader.server.stats().edits_denied, refused);
}

/// A store in an election: an append stores its whole group yet answers a failure (a conflict, or no answer), as an
/// engine whose leader died after committing does; the reads after it fail for a while.
#[derive(Default)]
struct Election {
    inner: MemoryEditStore,
    /// Appends still to answer with a failure though they stored (`true`: a conflict; `false`: no answer).
    lost: std::sync::Mutex<Vec<bool>>,
    /// Reads still to fail.
    unreadable: std::sync::atomic::AtomicUsize,
    /// Appends still to store nothing and answer nothing (a publish lost with its node).
    dropped: std::sync::atomic::AtomicUsize,
}

impl EditStore for Election {
    fn append(&self, edits: &[StoredEdit]) -> Result<(), EditStoreError> {
        if self.dropped.fetch_update(SeqCst, SeqCst, |n| n.checked_sub(1)).is_ok() {
            return Err(EditStoreError::Unanswered("NATS publishing an edit: timed out".into()));
        }
        self.inner.append(edits)?;
        match self.lost.lock().unwrap().pop() {
            Some(true) => Err(EditStoreError::Conflict { cell: edits[0].cell, version: edits[0].version }),
            Some(false) => Err(EditStoreError::Unanswered("NATS: no answer within 10s".into())),
            None => Ok(()),
        }
    }
    fn load(&self, c: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError> {
        let failing = self.unreadable.fetch_update(SeqCst, SeqCst, |n| n.checked_sub(1)).is_ok();
        if failing {
            return Err(EditStoreError::Io("NATS: no answer within 10s".into()));
        }
        self.inner.load(c)
    }
    passes_through!(inner);
}

use std::sync::atomic::Ordering::SeqCst;

#[test]
fn edits_whose_appends_failed_are_acknowledged_once_whether_stored_or_not_though_reads_fail_for_a_while() {
    let store = Arc::new(Election::default());
    let w = world_over(Arc::clone(&store) as Arc<dyn EditStore>);
    let mut a = Pair::connect(&w, ClientState::new(), Some(ALICE), 21);
    let mut watcher = Pair::connect(&w, ClientState::new(), None, 22);
    settle(&w, &mut [&mut a, &mut watcher]);
    let c = CellCoord::new(0, 0);
    let before = version(&w, c);
    // Plants whose append is stored but answered as a conflict, then as no answer; the next reads fail.
    *store.lost.lock().unwrap() = vec![false, true];
    store.unreadable.store(3, SeqCst);
    let plants: Vec<u32> =
        (0..3).map(|i| a.edit(EditOp::Plant { species: 0, x: 4.0 + i as f32, z: 6.0, params: vec![] })).collect();
    // The writer looks again after a pause while the store cannot be read: wait for the answers.
    let answered =
        |asked: Vec<u32>| move |p: &[(&World, &mut Pair)]| asked.iter().all(|r| p[0].1.results.contains_key(r));
    settle_until(&mut [(&w, &mut a), (&w, &mut watcher)], answered(plants.clone()));
    // Then a fell the same way.
    *store.lost.lock().unwrap() = vec![true];
    store.unreadable.store(2, SeqCst);
    let fell = a.edit(EditOp::Fell { id: id(0, 0, 0) });
    settle_until(&mut [(&w, &mut a), (&w, &mut watcher)], answered(vec![fell]));
    // Then a plant whose first two appends store nothing and answer nothing: tried again, stored once.
    store.dropped.store(2, SeqCst);
    let late = a.edit(EditOp::Plant { species: 1, x: 20.0, z: 20.0, params: vec![] });
    settle_until(&mut [(&w, &mut a), (&w, &mut watcher)], answered(vec![late]));

    // Each acknowledged once, at the version the store holds it, and stored once.
    let mut versions: Vec<u32> = plants
        .iter()
        .chain([&fell, &late])
        .map(|r| match &a.results[r] {
            EditOutcome::Ok { version, .. } => *version,
            other => panic!("a stored edit answered {other:?}"),
        })
        .collect();
    versions.sort_unstable();
    assert_eq!(versions, (before + 1..=before + 5).collect::<Vec<_>>());
    let log = store.inner.load(c).unwrap();
    assert_eq!(log.len(), 5, "each edit stored once: {log:?}");
    let felled = log.iter().filter(|e| matches!(e.op, canopy_server::edits::CellEdit::Fell { index: 0 })).count();
    assert_eq!(felled, 1);
    assert_eq!(version(&w, c), before + 5);
    // Every client catches up (the overlay loaders pause after a failed read).
    settle_until(&mut [(&w, &mut a), (&w, &mut watcher)], |p| {
        p.iter().all(|(_, p)| p.client.cells().get(&c).is_some_and(|h| h.version == before + 5))
    });
    let want = expected(&w);
    for p in [&a, &watcher] {
        assert_eq!(sorted(p.client.instances(&|_, _| 0.0).collect()), want);
    }
}

#[test]
fn an_edit_whose_cell_cannot_be_read_for_a_while_waits_for_the_store_instead_of_being_refused() {
    // Reads fail from the start (an engine in an election): the writer's first look at the cell fails too.
    let store = Arc::new(Election::default());
    store.unreadable.store(20, SeqCst);
    let w = world_over(Arc::clone(&store) as Arc<dyn EditStore>);
    let mut a = Pair::connect(&w, ClientState::new(), Some(ALICE), 23);
    let plant = a.edit(EditOp::Plant { species: 0, x: 70.0, z: -50.0, params: vec![] });
    settle_until(&mut [(&w, &mut a)], |p| p[0].1.results.contains_key(&plant) && p[0].1.client.is_complete());
    assert_eq!(store.unreadable.load(SeqCst), 0, "the reads failed meanwhile");
    let c = CellCoord::new(2, -2);
    assert!(matches!(a.results[&plant], EditOutcome::Ok { version: 1, .. }), "{:?}", a.results[&plant]);
    assert_eq!(store.inner.load(c).unwrap().len(), 1);
    assert_eq!(sorted(a.client.instances(&|_, _| 0.0).collect()), expected(&w));
}

#[test]
fn stored_edits_the_world_cannot_take_are_skipped_and_the_cell_is_served_with_the_rest() {
    use canopy_protocol::InstanceRecord;
    use canopy_server::edits::CellEdit;
    // A store written by another world (or damaged): a plant of species 9, a parameter slot 99 = 1e30, between
    // edits this world takes.
    let store = Arc::new(MemoryEditStore::new());
    let c = CellCoord::new(1, 1);
    let plant = |index: u16, species: u8, params: Vec<(u16, f32)>| CellEdit::Plant {
        index,
        record: InstanceRecord::new(species, 400, 500),
        params,
    };
    let base_total = base().cell(c, None).ready().unwrap().records.len() as u16;
    let log = [
        plant(base_total, 9, vec![]),
        plant(base_total + 1, 0, vec![(0, 2.0)]),
        CellEdit::Set { index: 0, params: vec![(99, 1.0e30)] },
        CellEdit::Fell { index: 1 },
    ];
    let log: Vec<StoredEdit> =
        log.into_iter().enumerate().map(|(i, op)| StoredEdit { cell: c, version: i as u32 + 1, op }).collect();
    store.append(&log).unwrap();
    let w = world_over(Arc::clone(&store) as Arc<dyn EditStore>);
    let mut a = Pair::connect(&w, ClientState::new(), Some(ALICE), 31);
    settle_until(&mut [(&w, &mut a)], |p| p[0].1.client.is_complete());
    // Served at version 4 with the valid plant and the fell; the skipped plant's index stays a hole.
    let held = &a.client.cells()[&c];
    assert_eq!(held.version, 4);
    let ids: Vec<u16> = a.client.instances(&|_, _| 0.0).filter(|i| i.id.cell() == c).map(|i| i.id.index()).collect();
    assert!(ids.contains(&(base_total + 1)) && !ids.contains(&base_total) && !ids.contains(&1), "{ids:?}");
    assert!(a.client.instances(&|_, _| 0.0).all(|i| i.params.iter().all(|p| p.0 < 8 && p.1.abs() < 1.0e4)));
    assert_eq!(w.live.skipped().load(SeqCst), 2);
    // Edits go on at the next version.
    let next = a.edit(EditOp::Plant { species: 1, x: 40.0, z: 40.0, params: vec![] });
    settle(&w, &mut [&mut a]);
    assert!(matches!(a.results[&next], EditOutcome::Ok { version: 5, .. }), "{:?}", a.results[&next]);
}

/// The world function's records, counting the cells asked for.
struct Counting {
    inner: Arc<dyn canopy_server::session::WorldStore>,
    asked: std::sync::Mutex<Vec<CellCoord>>,
}

impl canopy_server::session::WorldStore for Counting {
    fn head(&self) -> &canopy_server::session::StoreHead {
        self.inner.head()
    }
    fn cell(
        &self,
        c: CellCoord,
        waker: Option<&Arc<dyn canopy_server::session::CellWaker>>,
    ) -> canopy_server::session::CellState {
        self.asked.lock().unwrap().push(c);
        self.inner.cell(c, waker)
    }
}

#[test]
fn an_edit_outside_the_editors_region_is_refused_before_its_cell_is_built() {
    let counting = Arc::new(Counting { inner: base(), asked: Default::default() });
    let w = world_on(Arc::clone(&counting) as _, Arc::new(MemoryEditStore::new()));
    let carol = w.cfg.editors.as_ref().unwrap().find(&CAROL).unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    // Carol may edit only x ≤ 0: fells and sets in every cell wholly east of that, then one of her own.
    let mut asked = Vec::new();
    for x in 1..4 {
        for z in -4..4 {
            asked.push(EditOp::Fell { id: id(x, z, 0) });
            asked.push(EditOp::Set { id: id(x, z, 0), params: vec![(0, 1.0)] });
        }
    }
    asked.push(EditOp::Fell { id: id(-2, 1, 0) });
    let n = asked.len();
    for op in asked {
        let tx = tx.clone();
        w.service.submit(canopy_server::EditJob {
            op,
            editor: Arc::clone(&carol),
            reply: Box::new(move |o| tx.send(o).unwrap()),
        });
    }
    let outcomes: Vec<EditOutcome> = (0..n).map(|_| rx.recv_timeout(Duration::from_secs(10)).unwrap()).collect();
    assert_eq!(outcomes.iter().filter(|o| matches!(o, EditOutcome::Denied(_))).count(), n - 1, "{outcomes:?}");
    assert!(matches!(outcomes.last(), Some(EditOutcome::Ok { .. })), "{outcomes:?}");
    // Only Carol's own cell was read for her.
    assert_eq!(*counting.asked.lock().unwrap(), vec![CellCoord::new(-2, 1)]);
}

/// A store whose cell (1, 1) is damaged at version 3: the two edits before it read, the rest do not.
struct Damaging(MemoryEditStore);

impl EditStore for Damaging {
    fn append(&self, edits: &[StoredEdit]) -> Result<(), EditStoreError> {
        self.0.append(edits)
    }
    fn load(&self, c: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError> {
        let mut log = self.0.load(c)?;
        if c != CellCoord::new(1, 1) || log.len() < 3 {
            return Ok(log);
        }
        log.truncate(2);
        Err(EditStoreError::Damaged {
            store: "damaging.sqlite".into(),
            cell: c,
            version: 3,
            why: "stored edit does not decode".into(),
            readable: log,
        })
    }
    passes_through!(0);
}

#[test]
fn a_damaged_cell_log_is_served_as_it_was_before_the_damage_and_takes_no_edits() {
    use canopy_server::edits::CellEdit;
    let store = Arc::new(Damaging(MemoryEditStore::new()));
    let c = CellCoord::new(1, 1);
    let log: Vec<StoredEdit> = [CellEdit::Fell { index: 0 }, CellEdit::Fell { index: 1 }, CellEdit::Fell { index: 2 }]
        .into_iter()
        .enumerate()
        .map(|(i, op)| StoredEdit { cell: c, version: i as u32 + 1, op })
        .collect();
    store.append(&log).unwrap();
    let w = world_over(Arc::clone(&store) as Arc<dyn EditStore>);
    let mut a = Pair::connect(&w, ClientState::new(), Some(ALICE), 41);
    // Served, not left pending: at version 2, instance 2 still standing.
    settle_until(&mut [(&w, &mut a)], |p| p[0].1.client.is_complete());
    assert_eq!(a.client.cells()[&c].version, 2);
    let live: Vec<u16> = a.client.instances(&|_, _| 0.0).filter(|i| i.id.cell() == c).map(|i| i.id.index()).collect();
    assert_eq!(live, vec![2]);
    assert!(w.live.damaged(c).is_some_and(|why| why.contains("damaging.sqlite") && why.contains("version 3")));
    assert_eq!(w.live.skipped().load(SeqCst), 1);
    // The damaged cell takes no edits; the others do.
    let refused = a.edit(EditOp::Plant { species: 0, x: 40.0, z: 40.0, params: vec![] });
    let taken = a.edit(EditOp::Plant { species: 0, x: 8.0, z: 8.0, params: vec![] });
    settle(&w, &mut [&mut a]);
    assert!(matches!(&a.results[&refused], EditOutcome::Denied(why) if why.contains("damaged")), "{:?}", a.results);
    assert!(matches!(a.results[&taken], EditOutcome::Ok { .. }), "{:?}", a.results);
}

/// The world function's records, each cell east of x = 0 expanded only 300 ms after it is first asked for.
struct SlowEast {
    inner: Arc<dyn canopy_server::session::WorldStore>,
    asked: std::sync::Mutex<std::collections::BTreeMap<CellCoord, Instant>>,
}

impl canopy_server::session::WorldStore for SlowEast {
    fn head(&self) -> &canopy_server::session::StoreHead {
        self.inner.head()
    }
    fn cell(
        &self,
        c: CellCoord,
        waker: Option<&Arc<dyn canopy_server::session::CellWaker>>,
    ) -> canopy_server::session::CellState {
        if c.x > 0 {
            let first = *self.asked.lock().unwrap().entry(c).or_insert_with(Instant::now);
            if first.elapsed() < Duration::from_millis(300) {
                return canopy_server::session::CellState::Pending;
            }
        }
        self.inner.cell(c, waker)
    }
}

#[test]
fn an_editor_whose_cells_are_being_expanded_does_not_hold_up_another() {
    let slow = Arc::new(SlowEast { inner: base(), asked: Default::default() });
    let w = world_on(slow as _, Arc::new(MemoryEditStore::new()));
    let editors = w.cfg.editors.as_ref().unwrap();
    let (alice, bob) = (editors.find(&ALICE).unwrap(), editors.find(&BOB).unwrap());
    let (tx, rx) = std::sync::mpsc::channel();
    let submit = |op: EditOp, editor: &Arc<canopy_server::session::Editor>, who: &'static str| {
        let tx = tx.clone();
        w.service.submit(canopy_server::EditJob {
            op,
            editor: Arc::clone(editor),
            reply: Box::new(move |o| tx.send((who, o, Instant::now())).unwrap()),
        });
    };
    // Alice fells in 24 cells none of which is expanded yet; then Bob plants in a cell that is.
    let asked = Instant::now();
    for x in 1..4 {
        for z in -4..4 {
            submit(EditOp::Fell { id: id(x, z, 0) }, &alice, "alice");
        }
    }
    submit(EditOp::Plant { species: 0, x: -40.0, z: -40.0, params: vec![] }, &bob, "bob");
    let answers: Vec<_> = (0..25).map(|_| rx.recv_timeout(Duration::from_secs(20)).unwrap()).collect();
    let (_, bob_answer, bob_at) = answers.iter().find(|a| a.0 == "bob").unwrap();
    assert!(matches!(bob_answer, EditOutcome::Ok { .. }), "{bob_answer:?}");
    assert!(bob_at.duration_since(asked) < Duration::from_millis(250), "Bob waited {:?}", bob_at.duration_since(asked));
    // Alice's fells are all made once their cells are ready.
    assert!(answers.iter().filter(|a| a.0 == "alice").all(|a| matches!(a.1, EditOutcome::Ok { .. })), "{answers:?}");
    let last = answers.iter().map(|a| a.2).max().unwrap();
    assert!(last.duration_since(asked) >= Duration::from_millis(300));
}

/// An answer nobody waits for any more (its session ended), or one somebody does.
struct Gone(bool, std::sync::mpsc::Sender<EditOutcome>);

impl canopy_server::Reply for Gone {
    fn answer(self: Box<Self>, outcome: EditOutcome) {
        let _ = self.1.send(outcome);
    }
    fn abandoned(&self) -> bool {
        self.0
    }
}

#[test]
fn an_edit_whose_session_ended_before_it_was_written_is_not_made() {
    let w = world();
    let alice = w.cfg.editors.as_ref().unwrap().find(&ALICE).unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    for gone in [true, false] {
        let op = EditOp::Plant { species: 0, x: 5.0, z: 5.0, params: vec![] };
        let reply = Box::new(Gone(gone, tx.clone()));
        w.service.submit(canopy_server::EditJob { op, editor: Arc::clone(&alice), reply });
    }
    // Only the one still wanted is answered and stored.
    assert!(matches!(rx.recv_timeout(Duration::from_secs(10)).unwrap(), EditOutcome::Ok { version: 1, .. }));
    assert!(rx.recv_timeout(Duration::from_millis(200)).is_err());
    assert_eq!(w.edits.count().unwrap(), 1);
    assert_eq!(w.service.metrics().abandoned.load(SeqCst), 1);
}

/// A store shared with another writer that takes cell `contested`'s next version just before each of this writer's
/// next `rivals` appends to it (as an edge sharing a busy cell does), storing cells on their own; it counts the
/// reads of each cell, and `gate` holds an append while the test queues requests behind it.
struct Rival {
    inner: MemoryEditStore,
    contested: CellCoord,
    rivals: std::sync::atomic::AtomicUsize,
    reads: std::sync::Mutex<std::collections::BTreeMap<CellCoord, usize>>,
    gate: std::sync::Mutex<()>,
}

impl EditStore for Rival {
    fn append(&self, edits: &[StoredEdit]) -> Result<(), EditStoreError> {
        self.append_cells(edits).into_iter().map(|(_, r)| r).find(Result::is_err).unwrap_or(Ok(()))
    }
    fn append_cells(&self, edits: &[StoredEdit]) -> Vec<(CellCoord, Result<(), EditStoreError>)> {
        drop(self.gate.lock().unwrap());
        let cells: std::collections::BTreeSet<CellCoord> = edits.iter().map(|e| e.cell).collect();
        let mut out = Vec::new();
        for c in cells {
            if c == self.contested && self.rivals.fetch_update(SeqCst, SeqCst, |n| n.checked_sub(1)).is_ok() {
                let version = self.inner.load(c).unwrap().len() as u32 + 1;
                let op = canopy_server::edits::CellEdit::Set { index: 0, params: vec![(0, version as f32)] };
                self.inner.append(&[StoredEdit { cell: c, version, op }]).unwrap();
            }
            let mine: Vec<StoredEdit> = edits.iter().filter(|e| e.cell == c).cloned().collect();
            out.push((c, self.inner.append(&mine)));
        }
        out
    }
    fn load(&self, c: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError> {
        *self.reads.lock().unwrap().entry(c).or_default() += 1;
        self.inner.load(c)
    }
    passes_through!(inner);
}

#[test]
fn writers_sharing_a_busy_cell_take_turns_and_a_conflict_in_one_cell_holds_back_no_other() {
    let (a, b, c) = (CellCoord::new(0, 0), CellCoord::new(1, 0), CellCoord::new(-1, 0));
    // More conflicts in a row than a writer used to try (three) before it answered `conflict`.
    let store = Arc::new(Rival {
        inner: MemoryEditStore::new(),
        contested: a,
        rivals: 5.into(),
        reads: Default::default(),
        gate: Default::default(),
    });
    let w = world_over(Arc::clone(&store) as Arc<dyn EditStore>);
    let alice = w.cfg.editors.as_ref().unwrap().find(&ALICE).unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let submit = |tag: char, x: f32| {
        let op = EditOp::Plant { species: 0, x, z: 5.0, params: vec![] };
        let tx = tx.clone();
        let reply = Box::new(move |o: EditOutcome| tx.send((tag, o)).unwrap());
        w.service.submit(canopy_server::EditJob { op, editor: Arc::clone(&alice), reply });
    };
    // A first edit (cell c) holds the writer in its append while the next two queue: they make one group.
    let gate = store.gate.lock().unwrap();
    submit('c', -20.0);
    std::thread::sleep(Duration::from_millis(100));
    submit('a', 5.0);
    submit('b', 40.0);
    std::thread::sleep(Duration::from_millis(100));
    drop(gate);
    let mut answers: Vec<(char, EditOutcome)> =
        (0..3).map(|_| rx.recv_timeout(Duration::from_secs(10)).unwrap()).collect();
    answers.sort_by_key(|(t, _)| *t);
    let acked = |o: &EditOutcome| match o {
        EditOutcome::Ok { version, .. } => *version,
        other => panic!("{other:?}"),
    };
    // Cell b was stored with the group and acknowledged without being read again; cell a, after five turns of the
    // other writer, takes the version after them.
    assert_eq!(answers.iter().map(|(t, o)| (*t, acked(o))).collect::<Vec<_>>(), [('a', 6), ('b', 1), ('c', 1)]);
    let reads = store.reads.lock().unwrap().clone();
    assert_eq!(reads[&b], 1, "cell b read once, to prepare its edit: {reads:?}");
    assert!(reads[&a] > 5, "cell a read again after each conflict: {reads:?}");
    assert_eq!(w.edits.load(a).unwrap().len(), 6);
    assert_eq!(version(&w, a), 6);
    assert_eq!((version(&w, b), version(&w, c)), (1, 1));
    assert_eq!(w.service.metrics().cell_conflicts.load(SeqCst), 5, "one conflict a turn of the other writer");
}
