//! The lazy cell cache on virtual time over the default world: its memory bound while a session walks across the
//! world, the same bytes after an eviction, one expansion however many sessions ask, sessions that never wait for
//! a pending cell, batch bodies shared between sessions and decoding to the batches the eager store gives, and
//! real worker threads waking a session, and a world that exists only cell by cell (highlands). Workers run
//! deterministically in most tests (`workers: 0` and [`CellCache::run_queued`]); the worker test waits on its
//! waker's condition variable, never on a sleep.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Condvar, Mutex, OnceLock};
use std::time::{Duration, Instant};

use canopy_protocol::aoi::{Aoi, Viewpoint};
use canopy_protocol::messages::ServerMsgKind;
use canopy_protocol::messages::ServerStreaming;
use canopy_protocol::record::ParamOverride;
use canopy_protocol::{CellBatch, CellCoord, ClientMsg, Phase, ServerMsg};
use canopy_server::session::{CellState, CellWaker, GridStore, WorldStore};
use canopy_server::session::{Session, SessionConfig, Transmit};
use canopy_server::{CellCache, CellCacheConfig};
use canopy_test_support::forest as world;
use canopy_worlds::diag::SourceFile;
use canopy_worlds::world::World;

const MIB: usize = 1 << 20;

/// The eager store of the default world: what the lazy one must match.
fn eager() -> &'static GridStore {
    static STORE: OnceLock<GridStore> = OnceLock::new();
    STORE.get_or_init(|| GridStore::from_world(world()).unwrap())
}

fn cache(limit_bytes: usize, workers: usize) -> Arc<CellCache> {
    let cfg = CellCacheConfig {
        limit_bytes,
        workers,
        batch_records: SessionConfig::default().batch_records,
        ..CellCacheConfig::default()
    };
    Arc::new(CellCache::new((**world()).clone(), cfg).unwrap())
}

/// The cache as a session's store (the same object).
fn as_store(c: &Arc<CellCache>) -> Arc<dyn WorldStore> {
    Arc::clone(c) as Arc<dyn WorldStore>
}

/// A session at `vp`, streaming, its welcome taken.
fn session(store: Arc<dyn WorldStore>, vp: Viewpoint, t0: Instant) -> Session {
    let mut s = Session::new(store, SessionConfig::default(), t0);
    s.handle(t0, ClientMsg::hello("cells")).unwrap();
    let w = s.poll_transmit(t0).unwrap();
    s.on_flushed(w.len());
    s.handle(t0, ClientMsg::ready(vec![], vp)).unwrap();
    assert_eq!(s.phase(), Phase::Streaming);
    s
}

/// Everything a session sends until nothing is ready.
fn drain(s: &mut Session, now: Instant) -> Vec<Transmit> {
    let mut out = vec![];
    while let Some(t) = s.poll_transmit(now) {
        s.on_flushed(t.len());
        out.push(t);
    }
    out
}

fn decode(t: &Transmit) -> ServerMsg {
    let frame = t.frame();
    assert_eq!(u32::from_le_bytes(frame[..4].try_into().unwrap()) as usize, frame.len() - 4);
    ServerMsg::decode(&frame[4..]).unwrap()
}

fn batch_of(t: &Transmit) -> Option<CellBatch> {
    match decode(t) {
        ServerMsg::Streaming(ServerStreaming::Cells(b)) => Some(b),
        _ => None,
    }
}

/// The batch the eager store's records give for `b`'s cell, grant and range, built here from the records and
/// overrides (as the session built every batch before bodies were shared).
fn expected(b: &CellBatch) -> CellBatch {
    let data = eager().cell(b.cell, None).ready().unwrap();
    let (start, end) = (usize::from(b.start), usize::from(b.start) + b.records.len());
    let overrides: Vec<ParamOverride> = data
        .overrides
        .iter()
        .filter(|o| (start..end).contains(&usize::from(o.record)))
        .map(|o| ParamOverride { record: o.record - b.start, ..*o })
        .collect();
    let records = data.records[start..end].to_vec();
    CellBatch::new(b.cell, b.grant, data.records.len() as u16, b.start, records, &overrides)
}

/// Bytes of every cell of the world with its batches encoded: what the cache would hold unbounded.
fn world_bytes() -> usize {
    let grid = *eager().grid();
    let mut total = 0;
    for z in grid.min.z..=grid.max.z {
        for x in grid.min.x..=grid.max.x {
            let d = eager().cell(CellCoord::new(x, z), None).ready().unwrap();
            d.bodies(SessionConfig::default().batch_records);
            total += d.heap_bytes();
        }
    }
    total
}

#[test]
fn walking_across_the_world_never_takes_the_cache_past_its_bound() {
    let limit = MIB;
    assert!(world_bytes() > 2 * limit, "the world ({} B) is larger than the cache", world_bytes());
    let cache = cache(limit, 0);
    let t0 = Instant::now();
    // Back and forth across the world in rows 400 m apart: every part of it passes through the area of interest.
    let b = world().bounds;
    let mut path = vec![];
    let mut z = b.min[1] + 150.0;
    while z < b.max[1] {
        let row: Vec<[f32; 2]> =
            (0..=24).map(|i| [b.min[0] + 50.0 + (b.size()[0] - 100.0) * i as f32 / 24.0, z]).collect();
        path.extend(if path.len() % 50 == 0 { row } else { row.into_iter().rev().collect() });
        z += 400.0;
    }
    let mut s = session(as_store(&cache), Viewpoint::at(1, path[0], 200.0), t0);
    let mut records = 0u64;
    for (i, p) in path.iter().enumerate() {
        // A step a tenth of a second (virtual time): a walker, not a flood of viewpoints.
        let now = t0 + Duration::from_millis(100 * i as u64);
        if i > 0 {
            s.handle(now, ClientMsg::viewpoint(Viewpoint::at(i as u32 + 1, *p, 200.0))).unwrap();
        }
        // Send what is ready, expand what was asked for, until the area of interest is sent in full.
        loop {
            for t in drain(&mut s, now) {
                if let Some(b) = batch_of(&t) {
                    assert_eq!(b, expected(&b), "a batch of the lazy store is the eager store's");
                    records += b.records.len() as u64;
                }
            }
            if s.is_complete() {
                break;
            }
            assert!(cache.run_queued() > 0, "an incomplete session waits for queued cells");
        }
        assert!(cache.bytes() <= limit, "step {i}: {} B cached", cache.bytes());
    }
    let m = cache.metrics();
    use std::sync::atomic::Ordering::Relaxed;
    assert!(cache.peak_bytes() <= limit, "peak {} B", cache.peak_bytes());
    assert!(m.evictions.load(Relaxed) > 0, "the walk evicted cells");
    assert!(m.expansions.load(Relaxed) as usize > m.cells.load(Relaxed) as usize, "more expanded than cached");
    assert!(records > 10_000, "{records} records");
    assert_eq!(m.bytes.load(Relaxed) as usize, cache.bytes());
}

#[test]
fn an_evicted_cell_expands_again_to_the_same_bytes() {
    let cache = cache(256 * 1024, 0);
    let grid = *cache.grid();
    let c = CellCoord::new(grid.min.x + 3, grid.min.z + 4);
    assert!(matches!(cache.cell(c, None), CellState::Pending));
    assert_eq!(cache.run_queued(), 1);
    let first = cache.cell(c, None).ready().unwrap();
    let batch_records = SessionConfig::default().batch_records;
    let bodies: Vec<_> = first.bodies(batch_records).unwrap().to_vec();
    assert!(!first.records.is_empty() && bodies.len() > 1, "a cell of several batches");
    // Other cells push it out.
    let mut others = 0;
    'fill: for z in grid.min.z..=grid.max.z {
        for x in grid.min.x..=grid.max.x {
            if !cache.is_cached(c) {
                break 'fill;
            }
            let o = CellCoord::new(x, z);
            if o != c {
                cache.cell(o, None);
                cache.run_queued();
                others += 1;
            }
        }
    }
    assert!(!cache.is_cached(c), "evicted after {others} other cells");
    let expansions = cache.metrics().expansions.load(std::sync::atomic::Ordering::Relaxed);
    assert!(matches!(cache.cell(c, None), CellState::Pending), "asked again: expanded again");
    assert_eq!(cache.run_queued(), 1);
    assert_eq!(cache.metrics().expansions.load(std::sync::atomic::Ordering::Relaxed), expansions + 1);
    let again = cache.cell(c, None).ready().unwrap();
    assert!(!Arc::ptr_eq(&first, &again), "a new expansion");
    assert_eq!((&again.records, &again.overrides), (&first.records, &first.overrides));
    let again_bodies = again.bodies(batch_records).unwrap();
    assert_eq!(again_bodies, &bodies[..], "the same encoded bytes");
    assert_ne!(again_bodies[0].body.as_ptr(), bodies[0].body.as_ptr());
    // And the eager store's.
    assert_eq!(eager().cell(c, None).ready().unwrap().bodies(batch_records).unwrap(), &bodies[..]);
}

#[test]
fn many_sessions_asking_for_one_area_cause_one_expansion_per_cell_and_share_the_bodies() {
    use std::sync::atomic::Ordering::Relaxed;
    let cache = cache(64 * MIB, 0);
    let t0 = Instant::now();
    let vp = Viewpoint::at(1, [100.0, -300.0], 150.0);
    let mut sessions: Vec<Session> = (0..40).map(|_| session(as_store(&cache), vp, t0)).collect();
    // Nothing is cached: every session asks for every cell of its area and sends nothing.
    for s in &mut sessions {
        assert!(drain(s, t0).is_empty());
        assert!(!s.is_complete());
    }
    let cells = Aoi::new(&vp, &SessionConfig::default().aoi).inner_cells(cache.grid()).len();
    assert_eq!(cache.metrics().misses.load(Relaxed) as usize, cells, "one miss per cell");
    assert_eq!(cache.pending(), cells);
    assert_eq!(cache.run_queued(), cells, "one expansion per cell, not per session");
    assert_eq!(cache.metrics().expansions.load(Relaxed) as usize, cells);
    // Every session now sends the whole area; the same batch has the same body allocation in every session.
    let mut bodies: HashMap<(CellCoord, u16), (usize, usize)> = HashMap::new();
    for s in &mut sessions {
        let mut got = HashSet::new();
        for t in drain(s, t0) {
            if t.class != ServerMsgKind::Cells {
                continue;
            }
            let b = batch_of(&t).unwrap();
            assert_eq!(b, expected(&b));
            assert!(
                !t.body.is_empty() && t.bytes.len() <= 16,
                "a small head ({} B) and the shared body",
                t.bytes.len()
            );
            let ptr = (t.body.as_ptr() as usize, t.body.len());
            assert_eq!(*bodies.entry((b.cell, b.start)).or_insert(ptr), ptr, "{:?} shares its body", (b.cell, b.start));
            got.insert(b.cell);
        }
        assert!(s.is_complete());
        assert_eq!(got.len(), cells);
    }
    assert_eq!(cache.metrics().expansions.load(Relaxed) as usize, cells, "no expansion more");
    assert!(cache.metrics().hits.load(Relaxed) >= (cells * sessions.len()) as u64);
}

/// Counts wake-ups; waits for the next one on a condition variable.
#[derive(Default)]
struct CountingWaker {
    count: Mutex<u64>,
    woken: Condvar,
}

impl CellWaker for CountingWaker {
    fn wake(&self) {
        *self.count.lock().unwrap() += 1;
        self.woken.notify_all();
    }
}

impl CountingWaker {
    fn count(&self) -> u64 {
        *self.count.lock().unwrap()
    }

    /// Wait until the count passes `seen`.
    fn wait_past(&self, seen: u64) {
        let mut n = self.count.lock().unwrap();
        while *n <= seen {
            n = self.woken.wait(n).unwrap();
        }
    }
}

#[test]
fn a_session_with_pending_cells_keeps_sending_the_ready_ones_in_order() {
    let cache = cache(64 * MIB, 0);
    let t0 = Instant::now();
    let vp = Viewpoint::at(1, [-200.0, 400.0], 180.0);
    let mut s = session(as_store(&cache), vp, t0);
    let waker = Arc::new(CountingWaker::default());
    s.set_cell_waker(Arc::clone(&waker) as Arc<dyn CellWaker>);
    // The farther half of the area is expanded already; the nearer half is not.
    let grid = *cache.grid();
    let mut area = Aoi::new(&vp, &SessionConfig::default().aoi).inner_cells(&grid);
    area.sort_by(|a, b| grid.distance2(*a, vp.position).total_cmp(&grid.distance2(*b, vp.position)));
    let (near, far) = area.split_at(area.len() / 2);
    for c in far {
        cache.cell(*c, None);
    }
    cache.run_queued();
    // The session sends every far cell in full without waiting for the near ones, then has nothing ready.
    let sent = drain(&mut s, t0);
    let cells: Vec<CellCoord> = sent.iter().filter_map(batch_of).map(|b| b.cell).collect();
    let unique: HashSet<CellCoord> = cells.iter().copied().collect();
    assert_eq!(unique, far.iter().copied().collect::<HashSet<_>>(), "the ready cells, all of them");
    assert!(!s.is_complete());
    assert_eq!(cache.pending(), near.len(), "the near cells were asked for");
    assert_eq!(waker.count(), 0);
    // Expansion wakes the session, once per cell it waits for, and then it sends the rest.
    assert_eq!(cache.run_queued(), near.len());
    assert_eq!(waker.count() as usize, near.len());
    let rest = drain(&mut s, t0);
    let rest_cells: HashSet<CellCoord> = rest.iter().filter_map(batch_of).map(|b| b.cell).collect();
    assert_eq!(rest_cells, near.iter().copied().collect::<HashSet<_>>());
    assert!(s.is_complete());
}

#[test]
fn worker_threads_expand_and_wake_the_session_until_it_is_complete() {
    let cache = cache(4 * MIB, 2);
    let t0 = Instant::now();
    let waker = Arc::new(CountingWaker::default());
    let b = world().bounds;
    let mut s = session(as_store(&cache), Viewpoint::at(1, [b.min[0] + 300.0, 0.0], 250.0), t0);
    s.set_cell_waker(Arc::clone(&waker) as Arc<dyn CellWaker>);
    let mut batches = 0;
    for (seq, x) in [(2, b.min[0] + 600.0), (3, b.max[0] - 300.0)] {
        if seq > 2 {
            s.handle(t0, ClientMsg::viewpoint(Viewpoint::at(seq, [x, 0.0], 250.0))).unwrap();
        }
        loop {
            let seen = waker.count();
            let sent = drain(&mut s, t0);
            for t in &sent {
                if let Some(b) = batch_of(t) {
                    assert_eq!(b, expected(&b));
                    batches += 1;
                }
            }
            if s.is_complete() {
                break;
            }
            // Nothing ready now: a worker wakes the session when a cell it asked for is.
            waker.wait_past(seen);
        }
    }
    assert!(batches > 100, "{batches} batches");
    assert!(waker.count() > 0);
    assert!(cache.peak_bytes() <= 4 * MIB);
}

#[test]
fn a_world_expanded_only_on_demand_streams_from_the_cache() {
    // The highlands world (102.4 km square) is never materialised: `World::instances` is empty and every cell
    // exists only when expanded.
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../worlds/highlands/highlands.world");
    let world = World::load(&path).unwrap();
    assert!(world.instances.is_empty() && !world.is_materialised());
    let cfg = CellCacheConfig {
        limit_bytes: 4 * MIB,
        workers: 0,
        batch_records: SessionConfig::default().batch_records,
        ..CellCacheConfig::default()
    };
    let cache = Arc::new(CellCache::new(world.clone(), cfg).unwrap());
    let total = streams_exactly(&world, &cache, Viewpoint::at(1, [12_345.0, -6_789.0], 160.0));
    assert!(total > 1_000, "{total} instances around the viewpoint");
    assert!(cache.bytes() <= 4 * MIB);
}

#[test]
fn cells_at_the_far_corner_of_the_coordinate_range_stream_exactly() {
    // ±2^20 cells of 64 m: an f32 world coordinate there is good to 8 m, the records' steps to 1.6 cm.
    let text = "world edge\nseed 11\nbounds -67108864 -67108864 67108864 67108864\ncell 64\nterrain fractal {\n  \
                tile 65536\n  depth 14\n  param relief = 200\n}\nspecies a worm\nscatter a {\n  spacing 6\n}\n";
    let world = World::parse(&SourceFile::new("edge.world", text), None).unwrap();
    let cfg = CellCacheConfig { limit_bytes: 4 * MIB, workers: 0, ..CellCacheConfig::default() };
    let cache = Arc::new(CellCache::new(world.clone(), cfg).unwrap());
    assert_eq!(cache.grid().max, CellCoord::new((1 << 20) - 1, (1 << 20) - 1));
    let total = streams_exactly(&world, &cache, Viewpoint::at(1, [67_108_800.0, 67_108_800.0], 160.0));
    assert!(total > 1_000, "{total} instances around the corner");
}

/// Stream a viewpoint's area of interest from `cache` (cells expanded on this thread) and check every record
/// against the world's own expansion of its cell: the same species and the same steps in the cell, exactly.
/// Returns how many records.
fn streams_exactly(world: &World, cache: &Arc<CellCache>, vp: Viewpoint) -> usize {
    let t0 = Instant::now();
    let mut s = session(as_store(cache), vp, t0);
    let mut batches: Vec<CellBatch> = vec![];
    loop {
        batches.extend(drain(&mut s, t0).iter().filter_map(batch_of));
        if s.is_complete() {
            break;
        }
        assert!(cache.run_queued() > 0);
    }
    let grid = *cache.grid();
    let area: HashSet<CellCoord> =
        Aoi::new(&vp, &SessionConfig::default().aoi).inner_cells(&grid).into_iter().collect();
    let mut records: HashMap<CellCoord, Vec<(u8, [u16; 2])>> = HashMap::new();
    for b in &batches {
        for r in &b.records {
            records.entry(b.cell).or_default().push((r.species, [r.qx(), r.qz()]));
        }
    }
    assert_eq!(batches.iter().map(|b| b.cell).collect::<HashSet<_>>(), area);
    let mut total = 0;
    for c in &area {
        // Each record is its placement in the world's own expansion of the cell: the same steps in the cell.
        let key = canopy_worlds::world::CellKey { x: c.x, z: c.z };
        let placements = world.expand_cell(key);
        let got = records.remove(c).unwrap_or_default();
        assert_eq!(got.len(), placements.len(), "cell {c:?}");
        for ((species, steps), p) in got.iter().zip(&placements) {
            assert_eq!(u16::from(*species), p.species);
            assert_eq!(*steps, world.steps(key, p), "cell {c:?}");
            assert_eq!(world.dequantize(key, *steps), [p.x, p.z], "the steps give the placement back exactly");
        }
        total += placements.len();
    }
    total
}

#[test]
fn a_session_teleporting_over_a_world_of_a_million_metres_square_stays_within_the_bound() {
    // 10^6 m × 10^6 m (1,000,000 km²) on a fractal terrain: 7,813 × 7,813 cells of 128 m, none expanded at load.
    let text = "world vast\nseed 77\nbounds -500000 -500000 500000 500000\ncell 128\nterrain fractal {\n  tile 131072\n  \
                depth 12\n  param relief = 400\n}\nspecies tree monopodial\nspecies weed worm\n\
                scatter tree {\n  spacing 9\n  density 0.7\n  altitude -300 -100 .. 300 500\n  param height = 10 .. 20 step 1\n}\n\
                scatter weed {\n  spacing 6\n  density 0.5\n  avoid tree 2\n}\n";
    let world = World::parse(&canopy_worlds::diag::SourceFile::new("vast.world", text), None).unwrap();
    assert!(!world.is_materialised() && world.cell_count() > 60_000_000);
    let limit = MIB;
    let cfg = CellCacheConfig {
        limit_bytes: limit,
        workers: 0,
        batch_records: SessionConfig::default().batch_records,
        ..CellCacheConfig::default()
    };
    let cache = Arc::new(CellCache::new(world.clone(), cfg).unwrap());
    let t0 = Instant::now();
    let mut s = session(as_store(&cache), Viewpoint::at(1, [0.0, 0.0], 300.0), t0);
    // Teleports across the whole world (virtual time, a second apart), the first place visited again at the end.
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut places: Vec<[f32; 2]> = (0..24)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let v = |bits: u64| ((bits % 980_000) as f32) - 490_000.0;
            [v(state), v(state >> 32)]
        })
        .collect();
    places.push(places[0]);
    let mut first_visit: HashMap<CellCoord, CellBatch> = HashMap::new();
    let mut records = 0usize;
    let aoi_cells =
        Aoi::new(&Viewpoint::at(1, [0.0, 0.0], 300.0), &SessionConfig::default().aoi).inner_cells(cache.grid()).len();
    for (i, p) in places.iter().enumerate() {
        let now = t0 + Duration::from_secs(i as u64 + 1);
        s.handle(now, ClientMsg::viewpoint(Viewpoint::at(i as u32 + 2, *p, 300.0))).unwrap();
        loop {
            for t in drain(&mut s, now) {
                if let Some(b) = batch_of(&t) {
                    records += b.records.len();
                    // A cell seen again after its eviction comes back with the same records.
                    match first_visit.get(&b.cell) {
                        Some(old) if old.start == b.start => assert_eq!(old.records, b.records, "cell {:?}", b.cell),
                        _ => {
                            first_visit.insert(b.cell, b);
                        }
                    }
                }
            }
            if s.is_complete() {
                break;
            }
            assert!(cache.run_queued() > 0);
        }
        assert!(cache.bytes() <= limit, "teleport {i}: {} B cached", cache.bytes());
        assert!(s.held_cells().count() <= 2 * aoi_cells, "the session holds its area of interest, not the world");
    }
    assert!(cache.peak_bytes() <= limit, "peak {} B", cache.peak_bytes());
    assert!(records > 5_000, "{records} records");
    use std::sync::atomic::Ordering::Relaxed;
    assert!(cache.metrics().evictions.load(Relaxed) > 0);
}

/// Work no longer wanted is dropped: cells queued for a session that moved on, or left, are never expanded; a
/// cell another session still wants is.
#[test]
fn cells_queued_for_sessions_that_moved_on_or_left_are_never_expanded() {
    let cache = cache(64 * MIB, 0);
    let t0 = Instant::now();
    let here = Viewpoint::at(1, [-600.0, -600.0], 150.0);
    let mut a = session(as_store(&cache), here, t0);
    a.set_cell_waker(Arc::new(CountingWaker::default()) as Arc<dyn CellWaker>);
    let mut b = session(as_store(&cache), Viewpoint::at(1, [600.0, 600.0], 150.0), t0);
    b.set_cell_waker(Arc::new(CountingWaker::default()) as Arc<dyn CellWaker>);
    assert!(drain(&mut a, t0).iter().all(|t| batch_of(t).is_none()) && drain(&mut b, t0).is_empty());
    let grid = *cache.grid();
    let mine = Aoi::new(&here, &SessionConfig::default().aoi).inner_cells(&grid).len();
    let both = cache.pending();
    assert!(both > mine, "both sessions' cells are queued ({both})");
    // `a` moves across the world: what it asked for here is dropped, what it asks for there is queued.
    let there = Viewpoint::at(2, [-600.0, 600.0], 150.0);
    a.handle(t0, ClientMsg::viewpoint(there)).unwrap();
    drain(&mut a, t0);
    let cancelled = || cache.metrics().cancelled.load(std::sync::atomic::Ordering::Relaxed);
    assert_eq!(cancelled() as usize, mine);
    // `b` leaves: its cells too.
    let b_cells = cache.pending() - Aoi::new(&there, &SessionConfig::default().aoi).inner_cells(&grid).len();
    drop(b);
    assert_eq!(cancelled() as usize, mine + b_cells);
    // Only what `a` still wants is expanded.
    let expanded = cache.run_queued();
    assert_eq!(expanded, Aoi::new(&there, &SessionConfig::default().aoi).inner_cells(&grid).len());
    assert_eq!(cache.pending(), 0);
    drain(&mut a, t0);
    assert!(a.is_complete());
}
