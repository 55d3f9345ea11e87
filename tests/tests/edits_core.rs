//! Live edits without sockets: sessions, client states and the edit pipeline over a live store, paired like
//! `streaming_core.rs` (lanes delivered in a random interleaving). Concurrent edits of one cell from two sessions
//! apply in one order and every client converges on the store; denied and invalid edits leave no trace; a version
//! gap brings the whole cell again; a client that reconnects gets only what changed since its versions.

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use canopy_client::state::{ClientState, Event, InstanceView};
use canopy_protocol::aoi::{AoiParams, Grid, Viewpoint};
use canopy_protocol::edit::{CellDelta, EditOp, EditOutcome};
use canopy_protocol::messages::{ServerStreaming, TerrainDesc};
use canopy_protocol::xorshift::XorShift64;
use canopy_protocol::{CellCoord, InstanceId, ServerMsg, SpeciesGraph};
use canopy_server::LiveStore;
use canopy_server::editing::{CellChange, EditJob, EditService};
use canopy_server::editors::{Editors, editor_line};
use canopy_server::edits::{EditStore, MemoryEditStore};
use canopy_server::session::{MsgClass, Session, SessionConfig, StreamId};
use canopy_server::store::{PlacedInstance, StoreBuilder, WorldStore};

const CELL: f32 = 32.0;
const ALICE: [u8; 32] = [1; 32];
const BOB: [u8; 32] = [2; 32];
/// Carol may edit only the cells with x < 0.
const CAROL: [u8; 32] = [3; 32];
/// Dave may make 3 edits a second.
const DAVE: [u8; 32] = [4; 32];

/// A 8 × 8 grid of 32 m cells around the origin, 1 to 5 instances a cell of two species.
fn base() -> Arc<dyn WorldStore> {
    let species: Vec<SpeciesGraph> =
        ["worm", "conifer"].iter().map(|n| canopy_worlds::library::find(n).unwrap().load().unwrap()).collect();
    let grid = Grid { origin: [0.0, 0.0], cell_size: CELL, min: CellCoord::new(-4, -4), max: CellCoord::new(3, 3) };
    let mut b = StoreBuilder::new("edits", 7, grid, TerrainDesc::flat([-128.0, -128.0], 256.0), &species).unwrap();
    for z in -4i32..4 {
        for x in -4i32..4 {
            let o = grid.cell_origin(CellCoord::new(x, z));
            let n = (x + z).rem_euclid(5) as usize + 1;
            let instances: Vec<PlacedInstance> = (0..n)
                .map(|i| PlacedInstance {
                    species: (i % 2) as u16,
                    x: o[0] + 1.0 + i as f32 * 5.0,
                    z: o[1] + 2.0 + i as f32 * 3.0,
                    params: if i % 2 == 0 { vec![(0, 3.0 + i as f32)] } else { vec![] },
                })
                .collect();
            b.add_cell(CellCoord::new(x, z), &instances).unwrap();
        }
    }
    b.finish().shared()
}

struct World {
    live: Arc<LiveStore>,
    service: Arc<EditService>,
    edits: Arc<MemoryEditStore>,
    cfg: SessionConfig,
}

fn world() -> World {
    world_over(Arc::new(MemoryEditStore::new()), None)
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
    fn append(&self, edits: &[canopy_server::edits::StoredEdit]) -> Result<(), canopy_server::edits::EditStoreError> {
        let _held = self.hold.lock().unwrap();
        if self.fail.load(std::sync::atomic::Ordering::SeqCst) {
            self.inner.append(&edits[..1])?;
            return Err(canopy_server::edits::EditStoreError::Io("the disk failed".into()));
        }
        self.inner.append(edits)
    }
    fn load(
        &self,
        c: CellCoord,
    ) -> Result<Vec<canopy_server::edits::StoredEdit>, canopy_server::edits::EditStoreError> {
        self.inner.load(c)
    }
    fn cells(&self) -> Result<Vec<(CellCoord, u32)>, canopy_server::edits::EditStoreError> {
        self.inner.cells()
    }
    fn count(&self) -> Result<u64, canopy_server::edits::EditStoreError> {
        self.inner.count()
    }
}

fn world_over(edits: Arc<MemoryEditStore>, store: Option<Arc<dyn EditStore>>) -> World {
    let store = store.unwrap_or_else(|| Arc::clone(&edits) as Arc<dyn EditStore>);
    let live = Arc::new(LiveStore::new(base(), store, 1 << 20));
    let service = EditService::start(Arc::clone(&live));
    let text = [
        editor_line("alice", &ALICE, None, Some(1000)),
        editor_line("bob", &BOB, None, Some(1000)),
        editor_line("carol", &CAROL, Some([-128.0, -128.0, 0.0, 128.0]), None),
        editor_line("dave", &DAVE, None, Some(3)),
    ]
    .join("\n");
    let cfg = SessionConfig {
        aoi: AoiParams { max_radius: 300.0, hysteresis: 24.0, lookahead_s: 0.0, max_lookahead: 0.0 },
        batch_records: 2,
        editors: Some(Arc::new(Editors::parse("editors", &text).unwrap())),
        ..SessionConfig::default()
    };
    World { live, service, edits, cfg }
}

/// One client and its session, lanes delivered in a random interleaving, edits through the pipeline.
struct Pair {
    server: Session,
    client: ClientState,
    lanes: HashMap<StreamId, VecDeque<Vec<u8>>>,
    changes: tokio::sync::broadcast::Receiver<CellChange>,
    answers: (mpsc::Sender<(u32, EditOutcome)>, mpsc::Receiver<(u32, EditOutcome)>),
    /// Edit results the client received, by request.
    results: HashMap<u32, EditOutcome>,
    rng: XorShift64,
    now: Instant,
}

impl Pair {
    fn connect(w: &World, client: ClientState, token: Option<[u8; 32]>, seed: u64) -> Pair {
        let now = Instant::now();
        let store = Arc::clone(&w.live) as Arc<dyn WorldStore>;
        let mut server = Session::new(store, w.cfg.clone(), now);
        let mut client = client;
        server.handle(now, client.hello_as("pair", token.map(|t| t.to_vec())).unwrap()).unwrap();
        let welcome = server.poll_transmit(now).unwrap();
        server.on_flushed(welcome.len());
        client.on_welcome(ServerMsg::decode(&welcome.bytes[4..]).unwrap()).unwrap();
        for m in client.resume().unwrap() {
            server.handle(now, m).unwrap();
        }
        server.handle(now, client.ready(Viewpoint::at(1, [0.0, 0.0], 300.0)).unwrap()).unwrap();
        let changes = w.service.hub().subscribe();
        Pair {
            server,
            client,
            lanes: HashMap::new(),
            changes,
            answers: mpsc::channel(),
            results: HashMap::new(),
            rng: XorShift64::new(seed),
            now,
        }
    }

    fn edit(&mut self, op: EditOp) -> u32 {
        let (request, msg) = self.client.edit(op).unwrap();
        self.server.handle(self.now, msg).unwrap();
        request
    }

    /// Hand edits to the pipeline, take its answers and the announced changes, let the server send and deliver
    /// a few messages in a random lane order. Returns whether anything moved.
    fn step(&mut self, w: &World) -> bool {
        let mut moved = false;
        while let Some((request, op, editor)) = self.server.poll_edit() {
            let tx = self.answers.0.clone();
            w.service.submit(EditJob { op, editor, reply: Box::new(move |o| tx.send((request, o)).unwrap()) });
            moved = true;
        }
        while let Ok((request, outcome)) = self.answers.1.try_recv() {
            self.server.on_edit_result(request, outcome);
            moved = true;
        }
        loop {
            match self.changes.try_recv() {
                Ok(c) => self.server.on_cell_changed(c.cell),
                Err(tokio::sync::broadcast::error::TryRecvError::Lagged(_)) => self.server.on_changes_missed(),
                Err(_) => break,
            }
        }
        for _ in 0..8 {
            let Some(t) = self.server.poll_transmit(self.now) else { break };
            self.server.on_flushed(t.len());
            self.lanes.entry(t.stream).or_default().push_back(t.frame().to_vec());
            moved = true;
        }
        for _ in 0..8 {
            let mut busy: Vec<StreamId> = self.lanes.iter().filter(|(_, q)| !q.is_empty()).map(|(k, _)| *k).collect();
            if busy.is_empty() {
                break;
            }
            busy.sort_by_key(|s| match s {
                StreamId::Control => 0,
                StreamId::Lane(i) => 1 + u16::from(*i),
            });
            let lane = busy[(self.rng.next() as usize) % busy.len()];
            let bytes = self.lanes.get_mut(&lane).unwrap().pop_front().unwrap();
            match self.client.handle(ServerMsg::decode(&bytes[4..]).unwrap()).unwrap() {
                Event::EditResult(r) => {
                    self.results.insert(r.request, r.outcome);
                }
                Event::Gap(c) => {
                    let msg = self.client.refresh(c).unwrap();
                    self.server.handle(self.now, msg).unwrap();
                }
                _ => {}
            }
            moved = true;
        }
        self.now += Duration::from_millis(10);
        moved
    }
}

/// Step every pair until nothing moves and every edit is answered (the writer runs on its own thread).
fn settle(w: &World, pairs: &mut [&mut Pair]) {
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut quiet = 0;
    while quiet < 20 {
        assert!(Instant::now() < deadline, "pairs did not settle");
        let moved = pairs.iter_mut().fold(false, |m, p| p.step(w) | m);
        if moved {
            quiet = 0;
        } else {
            quiet += 1;
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

fn sorted(mut v: Vec<InstanceView>) -> Vec<(u64, u8, [u32; 3], Vec<(u16, u32)>)> {
    v.sort_by_key(|i| i.id);
    v.into_iter()
        .map(|i| {
            (i.id.0, i.species, i.position.map(f32::to_bits), i.params.iter().map(|p| (p.0, p.1.to_bits())).collect())
        })
        .collect()
}

/// What the store says every cell holds now, as a client would see it.
fn expected(w: &World) -> Vec<(u64, u8, [u32; 3], Vec<(u16, u32)>)> {
    let mut c = ClientState::new();
    let mut p = Pair::connect(w, std::mem::take(&mut c), None, 99);
    settle(w, &mut [&mut p]);
    assert!(p.client.is_complete());
    sorted(p.client.instances(&|_, _| 0.0).collect())
}

fn version(w: &World, c: CellCoord) -> u32 {
    w.live.cell(c, None).ready().unwrap().version
}

fn id(x: i32, z: i32, i: u16) -> InstanceId {
    InstanceId::new(CellCoord::new(x, z), i).unwrap()
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
    assert_eq!(w.edits.count().unwrap(), 7);
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
    let total = a.client.cells()[&c].total;
    let stray = CellDelta {
        cell: c,
        grant,
        from_version: 5,
        to_version: 6,
        total,
        adds: vec![],
        removes: vec![0],
        updates: vec![],
    };
    assert_eq!(a.client.handle(ServerMsg::Streaming(ServerStreaming::Delta(stray))), Ok(Event::Gap(c)));
    let batches = a.server.stats().messages[MsgClass::Cells];
    let refresh = a.client.refresh(c).unwrap();
    a.server.handle(a.now, refresh).unwrap();
    settle(&w, &mut [&mut a]);
    assert!(a.server.stats().messages[MsgClass::Cells] > batches, "the cell came again");
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
    assert_eq!(stats.messages[MsgClass::Cells], 0, "no cell sent again");
    assert_eq!(stats.messages[MsgClass::Species], 0, "species come from the cache, not resent");
    assert_eq!(stats.deltas, 2, "a delta for each changed cell");
    assert_eq!(stats.messages[MsgClass::Delta], 2);
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
    let w = world_over(Arc::clone(&inner), Some(Arc::clone(&flaky) as Arc<dyn EditStore>));
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
    fn append(&self, edits: &[canopy_server::edits::StoredEdit]) -> Result<(), canopy_server::edits::EditStoreError> {
        self.0.append(edits)
    }
    fn load(
        &self,
        c: CellCoord,
    ) -> Result<Vec<canopy_server::edits::StoredEdit>, canopy_server::edits::EditStoreError> {
        if c == CellCoord::new(0, 0) {
            std::thread::sleep(Duration::from_millis(1000));
        }
        self.0.load(c)
    }
    fn cells(&self) -> Result<Vec<(CellCoord, u32)>, canopy_server::edits::EditStoreError> {
        self.0.cells()
    }
    fn count(&self) -> Result<u64, canopy_server::edits::EditStoreError> {
        self.0.count()
    }
}

#[test]
fn a_slow_edit_store_never_blocks_a_session() {
    let inner = Arc::new(MemoryEditStore::new());
    let w = world_over(Arc::clone(&inner), Some(Arc::new(Slow(Arc::clone(&inner))) as Arc<dyn EditStore>));
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
