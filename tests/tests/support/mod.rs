//! What the edit tests share: a small live world, its edit writer and editors, and a session paired with a client
//! state without sockets (lanes delivered in a random interleaving), stepped until both settle.
#![allow(dead_code)]

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use canopy_client::state::{ClientState, Event, InstanceView};
use canopy_protocol::aoi::{AoiParams, Grid, Viewpoint};
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_protocol::messages::TerrainDesc;
use canopy_protocol::xorshift::XorShift64;
use canopy_protocol::{CellCoord, InstanceId, ServerMsg, SpeciesGraph};
use canopy_server::LiveStore;
use canopy_server::edits::{EditStore, MemoryEditStore};
use canopy_server::session::{Editors, editor_line};
use canopy_server::session::{PlacedInstance, StoreBuilder, WorldStore};
use canopy_server::session::{Session, SessionConfig, StreamId};
use canopy_server::{CellChange, EditJob, EditService};

pub(crate) const CELL: f32 = 32.0;
pub(crate) const ALICE: [u8; 32] = [1; 32];
pub(crate) const BOB: [u8; 32] = [2; 32];
/// Carol may edit only the cells with x < 0.
pub(crate) const CAROL: [u8; 32] = [3; 32];
/// Dave may make 3 edits a second.
pub(crate) const DAVE: [u8; 32] = [4; 32];

/// A 8 × 8 grid of 32 m cells around the origin (the world's bounds end 8 m short of its high edges), 1 to 5
/// instances a cell of two species.
pub(crate) fn base() -> Arc<dyn WorldStore> {
    let species: Vec<SpeciesGraph> =
        ["worm", "conifer"].iter().map(|n| canopy_worlds::library::find(n).unwrap().load().unwrap()).collect();
    let grid = Grid { origin: [0.0, 0.0], cell_size: CELL, min: CellCoord::new(-4, -4), max: CellCoord::new(3, 3) };
    // Bounds short of the grid's last cells on the high sides: those cells reach past the world.
    let mut b = StoreBuilder::new("edits", 7, grid, TerrainDesc::flat([-128.0, -128.0], 256.0), &species)
        .unwrap()
        .bounds([-128.0, -128.0, 120.0, 120.0]);
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

/// A live world over an edit store, its edit writer, and the sessions' configuration (editors Alice, Bob,
/// Carol, Dave).
pub(crate) struct World {
    pub live: Arc<LiveStore>,
    pub service: Arc<EditService>,
    pub edits: Arc<dyn EditStore>,
    pub cfg: SessionConfig,
}

/// The world over an in-memory edit store.
pub(crate) fn world() -> World {
    world_over(Arc::new(MemoryEditStore::new()))
}

/// The world over `edits`.
pub(crate) fn world_over(edits: Arc<dyn EditStore>) -> World {
    world_on(base(), edits)
}

/// The world of `base` (the world function's records) over `edits`.
pub(crate) fn world_on(base: Arc<dyn WorldStore>, edits: Arc<dyn EditStore>) -> World {
    let live = Arc::new(LiveStore::new(base, Arc::clone(&edits), 1 << 20));
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

/// An edit's outcome for the request that asked it.
type Answer = (u32, EditOutcome);

/// An instance as the tests compare it: id, species, position bits and parameter bits.
pub(crate) type Seen = (u64, u8, [u32; 3], Vec<(u16, u32)>);

/// One client and its session, lanes delivered in a random interleaving, edits through the pipeline.
pub(crate) struct Pair {
    pub server: Session,
    pub client: ClientState,
    lanes: HashMap<StreamId, VecDeque<Vec<u8>>>,
    changes: tokio::sync::broadcast::Receiver<CellChange>,
    answers: (mpsc::Sender<Answer>, mpsc::Receiver<Answer>),
    /// Edit results the client received, by request.
    pub results: HashMap<u32, EditOutcome>,
    rng: XorShift64,
    pub now: Instant,
}

impl Pair {
    pub(crate) fn connect(w: &World, client: ClientState, token: Option<[u8; 32]>, seed: u64) -> Pair {
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

    pub(crate) fn edit(&mut self, op: EditOp) -> u32 {
        let (request, msg) = self.client.edit(op).unwrap();
        self.server.handle(self.now, msg).unwrap();
        request
    }

    /// Hand edits to the pipeline, take its answers and the announced changes, let the server send and deliver
    /// a few messages in a random lane order. Returns whether anything moved.
    pub(crate) fn step(&mut self, w: &World) -> bool {
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
/// Step every pair until nothing moves and every edit is answered (the writer runs on its own thread).
pub(crate) fn settle(w: &World, pairs: &mut [&mut Pair]) {
    let mut each: Vec<(&World, &mut Pair)> = pairs.iter_mut().map(|p| (w, &mut **p)).collect();
    settle_each(&mut each);
}

/// [`settle`] for pairs on different edges, each with its own world.
pub(crate) fn settle_each(pairs: &mut [(&World, &mut Pair)]) {
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut quiet = 0;
    while quiet < 20 {
        assert!(Instant::now() < deadline, "pairs did not settle");
        let moved = pairs.iter_mut().fold(false, |m, (w, p)| p.step(w) | m);
        if moved {
            quiet = 0;
        } else {
            quiet += 1;
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

/// Step the pairs until `done` holds of them (changes from other edges come over the network), at most 20 s.
pub(crate) fn settle_until(pairs: &mut [(&World, &mut Pair)], done: impl Fn(&[(&World, &mut Pair)]) -> bool) {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        settle_each(pairs);
        if done(pairs) {
            return;
        }
        assert!(Instant::now() < deadline, "pairs did not reach the state waited for");
        std::thread::sleep(Duration::from_millis(20));
    }
}

pub(crate) fn sorted(mut v: Vec<InstanceView>) -> Vec<Seen> {
    v.sort_by_key(|i| i.id);
    v.into_iter()
        .map(|i| {
            (i.id.0, i.species, i.position.map(f32::to_bits), i.params.iter().map(|p| (p.0, p.1.to_bits())).collect())
        })
        .collect()
}

/// What the store says every cell holds now, as a client would see it.
pub(crate) fn expected(w: &World) -> Vec<Seen> {
    let mut c = ClientState::new();
    let mut p = Pair::connect(w, std::mem::take(&mut c), None, 99);
    settle_until(&mut [(w, &mut p)], |p| p[0].1.client.is_complete());
    sorted(p.client.instances(&|_, _| 0.0).collect())
}

pub(crate) fn version(w: &World, c: CellCoord) -> u32 {
    w.live.cell(c, None).ready().unwrap().version
}

pub(crate) fn id(x: i32, z: i32, i: u16) -> InstanceId {
    InstanceId::new(CellCoord::new(x, z), i).unwrap()
}
