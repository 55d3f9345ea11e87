//! The server's session core and the client's state, paired without sockets (like quinn-proto's `Pair`): lanes are
//! ordered streams but are delivered to the client in a random interleaving, the client walks, teleports and stops,
//! and at every rest both sides agree — the client holds exactly the cells of its area of interest, in full, as the
//! store has them, each species once.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use canopy_client::state::ClientState;
use canopy_harness::bots::verify;
use canopy_protocol::aoi::{Aoi, Viewpoint};
use canopy_protocol::xorshift::XorShift64;
use canopy_protocol::{CellCoord, InstanceId, ServerMsg};
use canopy_server::session::{GridStore, WorldStore};
use canopy_server::session::{Session, SessionConfig, StreamId};
use canopy_test_support::forest as world;
use canopy_worlds::world::{CellKey, instance_seed};

struct Pair {
    server: Session,
    client: ClientState,
    lanes: HashMap<StreamId, VecDeque<Vec<u8>>>,
    rng: XorShift64,
    now: Instant,
    seq: u32,
}

impl Pair {
    fn new(store: Arc<dyn WorldStore>, cfg: SessionConfig, start: Viewpoint, seed: u64) -> Pair {
        let now = Instant::now();
        let mut server = Session::new(store, cfg, now);
        let mut client = ClientState::new();
        server.handle(now, client.hello("pair").unwrap()).unwrap();
        let welcome = server.poll_transmit(now).unwrap();
        assert_eq!(welcome.stream, StreamId::Control);
        server.on_flushed(welcome.bytes.len());
        client.on_welcome(ServerMsg::decode(&welcome.bytes[4..]).unwrap()).unwrap();
        server.handle(now, client.ready(start).unwrap()).unwrap();
        Pair { server, client, lanes: HashMap::new(), rng: XorShift64::new(seed), now, seq: 0 }
    }

    fn next(&mut self) -> u64 {
        self.rng.next()
    }

    /// Let the server send up to `n` messages into the lanes, and deliver up to `m` of the queued ones, picking a
    /// random lane each time (each lane stays in order).
    fn step(&mut self, n: usize, m: usize) {
        for _ in 0..n {
            let Some(t) = self.server.poll_transmit(self.now) else { break };
            self.server.on_flushed(t.len());
            self.lanes.entry(t.stream).or_default().push_back(t.frame().to_vec());
        }
        for _ in 0..m {
            let busy: Vec<StreamId> = self.lanes.iter().filter(|(_, q)| !q.is_empty()).map(|(k, _)| *k).collect();
            if busy.is_empty() {
                break;
            }
            let mut busy = busy;
            busy.sort_by_key(|s| match s {
                StreamId::Control => 0,
                StreamId::Lane(i) => 1 + u16::from(*i),
            });
            let lane = busy[(self.next() as usize) % busy.len()];
            let bytes = self.lanes.get_mut(&lane).unwrap().pop_front().unwrap();
            let msg = ServerMsg::decode(&bytes[4..]).unwrap();
            self.client.handle(msg).unwrap();
        }
    }

    fn moved(&mut self, position: [f32; 2], velocity: [f32; 2], radius: f32) {
        // A viewpoint every 100 ms of virtual time, as a walking client sends them.
        self.now += std::time::Duration::from_millis(100);
        self.seq += 1;
        let vp = Viewpoint { seq: self.seq, position, yaw: velocity[0].atan2(velocity[1]), velocity, radius };
        let msg = self.client.set_viewpoint(vp).unwrap();
        self.server.handle(self.now, msg).unwrap();
    }

    fn settle(&mut self) {
        for _ in 0..100_000 {
            self.step(64, 64);
            if self.server.is_complete() && self.lanes.values().all(VecDeque::is_empty) {
                return;
            }
        }
        panic!("did not settle");
    }
}

#[test]
fn client_and_server_agree_under_lane_reordering_through_walks_and_teleports() {
    let world = world();
    let store = GridStore::from_world(world).unwrap().shared();
    let grid = *store.grid();
    for seed in [1u64, 0x9e37_79b9, 0xdead_beef_cafe] {
        let cfg = SessionConfig { batch_records: 16, ..SessionConfig::default() };
        let aoi_params = cfg.aoi;
        let mut pair = Pair::new(Arc::clone(&store), cfg, Viewpoint::at(0, [0.0, 0.0], 150.0), seed);
        let mut pos = [0.0f32, 0.0];
        for round in 0..12 {
            // Walk a while, letting only part of the traffic through, so grants are released mid-way.
            let dir = [((pair.next() % 200) as f32 - 100.0) / 10.0, ((pair.next() % 200) as f32 - 100.0) / 10.0];
            for _ in 0..20 {
                pos = [(pos[0] + dir[0] * 4.0).clamp(-900.0, 900.0), (pos[1] + dir[1] * 4.0).clamp(-900.0, 900.0)];
                pair.moved(pos, dir, 150.0);
                let (n, m) = ((pair.next() % 12) as usize, (pair.next() % 12) as usize);
                pair.step(n, m);
            }
            if round % 4 == 3 {
                pos = [((pair.next() % 1800) as f32) - 900.0, ((pair.next() % 1800) as f32) - 900.0];
                pair.moved(pos, [0.0, 0.0], 150.0);
                pair.step(3, 1);
            }
            // Stop and settle: both sides agree, and the client holds exactly its area of interest.
            pair.moved(pos, [0.0, 0.0], 150.0);
            pair.settle();
            assert!(pair.client.is_complete(), "seed {seed} round {round}: {} missing", pair.client.missing());
            let server_cells: HashMap<CellCoord, u32> = pair.server.held_cells().collect();
            let client_cells: HashMap<CellCoord, u32> =
                pair.client.cells().iter().map(|(c, h)| (*c, h.grant)).collect();
            assert_eq!(server_cells, client_cells, "seed {seed} round {round}");
            let vp = *pair.client.viewpoint().unwrap();
            let aoi = Aoi::new(&vp, &aoi_params);
            assert!(aoi.inner_cells(&grid).iter().all(|c| client_cells.contains_key(c)));
            verify(&pair.client, world).unwrap_or_else(|e| panic!("seed {seed} round {round}: {e}"));
        }
        assert!(pair.client.stats().dropped > 0 || pair.client.stats().evicted > 0, "reordering was exercised");
        assert_eq!(pair.client.stats().species_duplicates, 0);
    }
}

#[test]
fn a_clients_instances_have_the_worlds_seeds_for_the_same_cell_and_index() {
    let world = world();
    let store = GridStore::from_world(world).unwrap().shared();
    // Somewhere off the origin, so cells of negative and positive coordinates are held.
    let mut pair = Pair::new(store, SessionConfig::default(), Viewpoint::at(0, [-300.0, 200.0], 150.0), 5);
    pair.settle();
    assert!(pair.client.is_complete());
    let mut cells = HashSet::new();
    let mut n = 0;
    for inst in pair.client.instances(&|_, _| 0.0) {
        let (cell, index) = (inst.id.cell(), inst.id.index());
        // The world's instance at the same (cell, index in the cell).
        let range = world.cell_instances(CellKey { x: cell.x, z: cell.z });
        let world_index = range.start + u32::from(index);
        assert!(range.contains(&world_index), "{:?}", inst.id);
        assert_eq!(world.instance_id(world_index), inst.id);
        assert_eq!(world.index_of(inst.id), Some(world_index));
        let expected = world.instance(world_index, 0).seed;
        assert_eq!(inst.seed, expected, "{:?}", inst.id);
        assert_eq!(inst.seed, instance_seed(world.seed, InstanceId::new(cell, index).unwrap()));
        cells.insert(cell);
        n += 1;
    }
    assert!(n > 100 && cells.iter().any(|c| c.x < 0) && cells.iter().any(|c| c.z > 0), "{n} instances");
}
