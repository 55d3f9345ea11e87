//! The ground truth visible completeness is measured against, and what a client held at each sample.
//!
//! [`GroundTruth`] reads the world cell by cell: a world materialised at load from [`World::instances`], any
//! other (the highlands, 102.4 km square, never materialised) from its function, [`World::expand_cells`] of one
//! cell, memoised in an LRU bounded in cells, since bots sample the same cells again and again. Either way an
//! instance is `(cell, index in the cell)`, as the server's records name it.
//!
//! Expanding a cell costs 5–15 ms, and a flight's samples cover ~200 cells each; so a bot never evaluates its
//! samples while it moves: it takes a [`HeldSnapshot`] (the records it holds in each cell within view, a few
//! hundred map look-ups), and [`evaluate`] computes visible completeness from the snapshots once the bots are done,
//! expanding only the cells the samples cover, on several threads.

use std::ops::Range;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use canopy_client::state::ClientState;
use canopy_protocol::aoi::Grid;
use canopy_protocol::lru::Lru;
use canopy_protocol::sync::Locked;
use canopy_protocol::{CellCoord, InstanceId};
use canopy_worlds::world::{CellKey, World};

use super::measure::Sample;

/// Cells a [`GroundTruth`] of a world never materialised keeps by default: two 30 s flights at 250 m/s with a
/// 512 m record radius cover ~4,200 cells, and a second scenario over the same paths should find them all (an LRU
/// smaller than a cyclic pass misses every time). At a few kB of positions per cell, some tens of MB.
pub const DEFAULT_MEMO_CELLS: usize = 8192;

/// A cell's instance positions on the ground, by index in the cell.
type CellPositions = Arc<[[f32; 2]]>;

/// The cells of a world as functions of the cell, most recently used kept.
struct Memo {
    capacity: usize,
    cells: Lru<CellCoord, CellPositions>,
}

impl std::fmt::Debug for Memo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Memo").field("capacity", &self.capacity).field("cells", &self.cells.len()).finish()
    }
}

impl Memo {
    fn new(capacity: usize) -> Memo {
        Memo { capacity: capacity.max(1), cells: Lru::new() }
    }

    /// The cell if memoised, now the most recently used.
    fn get(&mut self, c: CellCoord) -> Option<CellPositions> {
        self.cells.get(&c).map(|cell| Arc::clone(cell))
    }

    /// Keep `cell` (unless another thread memoised it meanwhile: then that one), the least recently used going
    /// beyond the capacity.
    fn insert(&mut self, c: CellCoord, cell: CellPositions) -> CellPositions {
        if let Some(had) = self.get(c) {
            return had;
        }
        // Each cell counts one: the bound is a count of cells.
        self.cells.insert(c, Arc::clone(&cell), 1);
        self.cells.evict_to(self.capacity, None);
        cell
    }
}

/// Where a ground truth reads its cells.
#[derive(Debug)]
enum Source {
    /// [`World::instances`], a materialised world's cell ranges.
    Instances,
    /// The world's function, memoised.
    Function(Mutex<Memo>),
}

/// What a [`GroundTruth`] computed from the world's function.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TruthStats {
    /// Cells expanded.
    pub expanded: u64,
    /// Cells found in the memo.
    pub hits: u64,
    /// Seconds spent expanding, summed over threads.
    pub seconds: f64,
    /// Cells memoised now.
    pub memoised: usize,
}

/// The ground truth visible completeness is measured against: the world's instances, cell by cell over the cells
/// within view distance (the area of interest's [`Grid`]); see the module docs.
#[derive(Debug)]
pub struct GroundTruth {
    world: Arc<World>,
    grid: Grid,
    source: Source,
    expanded: AtomicU64,
    hits: AtomicU64,
    nanos: AtomicU64,
}

impl GroundTruth {
    /// The ground truth of a world: read from [`World::instances`] if it is materialised, else from its function
    /// with a memo of [`DEFAULT_MEMO_CELLS`].
    pub fn new(world: Arc<World>) -> GroundTruth {
        if world.is_materialised() {
            GroundTruth::with_source(world, Source::Instances)
        } else {
            GroundTruth::from_function(world, DEFAULT_MEMO_CELLS)
        }
    }

    /// The ground truth computed from the world's function cell by cell ([`World::expand_cells`] of one cell,
    /// whether or not the world is materialised), keeping the `capacity` cells most recently used.
    pub fn from_function(world: Arc<World>, capacity: usize) -> GroundTruth {
        GroundTruth::with_source(world, Source::Function(Mutex::new(Memo::new(capacity))))
    }

    fn with_source(world: Arc<World>, source: Source) -> GroundTruth {
        let (first, dims) = (world.first_cell(), world.cell_dims());
        let grid = Grid {
            origin: world.cell_origin(CellKey { x: 0, z: 0 }),
            cell_size: world.cell_size,
            min: CellCoord::new(first.x, first.z),
            max: CellCoord::new(first.x + dims[0] as i32 - 1, first.z + dims[1] as i32 - 1),
        };
        GroundTruth {
            world,
            grid,
            source,
            expanded: AtomicU64::new(0),
            hits: AtomicU64::new(0),
            nanos: AtomicU64::new(0),
        }
    }

    /// Instances in the world as a server's welcome counts them: every instance of a materialised world, 0 for
    /// one expanded cell by cell.
    pub fn len(&self) -> usize {
        self.world.instances.len()
    }

    /// Whether [`GroundTruth::len`] is 0.
    pub fn is_empty(&self) -> bool {
        self.world.instances.is_empty()
    }

    /// The world.
    pub fn world(&self) -> &Arc<World> {
        &self.world
    }

    /// The world's grid (the welcome's).
    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// What it computed from the world's function so far (zeros when it reads [`World::instances`]).
    pub fn stats(&self) -> TruthStats {
        TruthStats {
            expanded: self.expanded.load(Relaxed),
            hits: self.hits.load(Relaxed),
            seconds: self.nanos.load(Relaxed) as f64 * 1e-9,
            memoised: match &self.source {
                Source::Instances => 0,
                Source::Function(m) => m.locked().cells.len(),
            },
        }
    }

    /// The cells within `distance` of `p` (their squares; the boundary counts), row by row.
    pub fn cells_within(&self, p: [f32; 2], distance: f32) -> Vec<CellCoord> {
        let mut cells = Vec::new();
        self.grid.cells_within(p, distance, &mut cells);
        cells
    }

    /// A cell from the world's function: memoised, or expanded now (outside the lock, so that threads expand
    /// different cells at once).
    fn function_cell(&self, memo: &Mutex<Memo>, c: CellCoord) -> CellPositions {
        let lock = || memo.locked();
        if let Some(cell) = lock().get(c) {
            self.hits.fetch_add(1, Relaxed);
            return cell;
        }
        let t = Instant::now();
        let key = CellKey { x: c.x, z: c.z };
        let placements = self.world.expand_cells(key, key).pop().map(|(_, v)| v).unwrap_or_default();
        // A cell the protocol can stream holds at most 65,535 instances (the server refuses more).
        let cell: CellPositions =
            placements.iter().take(usize::from(u16::MAX)).map(|q| [q.x as f32, q.z as f32]).collect();
        self.nanos.fetch_add(t.elapsed().as_nanos() as u64, Relaxed);
        self.expanded.fetch_add(1, Relaxed);
        lock().insert(c, cell)
    }

    /// Expand the cells of `cells` the memo lacks, on up to `threads` threads (nothing to do for a materialised
    /// world). The memo keeps what its capacity allows, most recent last.
    pub fn prefetch(&self, cells: &[CellCoord], threads: usize) {
        let Source::Function(memo) = &self.source else { return };
        let missing: Vec<CellCoord> = {
            let m = memo.locked();
            cells.iter().copied().filter(|c| !m.cells.contains(c)).collect()
        };
        let threads = threads.clamp(1, missing.len().max(1));
        if threads == 1 {
            for &c in &missing {
                self.function_cell(memo, c);
            }
            return;
        }
        let next = AtomicUsize::new(0);
        std::thread::scope(|s| {
            for _ in 0..threads {
                s.spawn(|| {
                    while let Some(&c) = missing.get(next.fetch_add(1, Relaxed)) {
                        self.function_cell(memo, c);
                    }
                });
            }
        });
    }

    /// Call `f` with each cell within `distance` of `p` and the indices in the cell of its instances within
    /// `distance` of `p` (on the ground plane; the boundary counts), cells in row-major order, indices increasing.
    fn each_cell(&self, p: [f32; 2], distance: f32, mut f: impl FnMut(CellCoord, &mut dyn Iterator<Item = u16>)) {
        let d2 = distance * distance;
        let near = |[x, z]: [f32; 2]| {
            let (dx, dz) = (x - p[0], z - p[1]);
            dx * dx + dz * dz <= d2
        };
        for c in self.cells_within(p, distance) {
            match &self.source {
                Source::Instances => {
                    let range = self.world.cell_instances(CellKey { x: c.x, z: c.z });
                    let cell = &self.world.instances[range.start as usize..range.end as usize];
                    let it = cell.iter().take(usize::from(u16::MAX)).enumerate();
                    f(c, &mut it.filter_map(|(i, q)| near([q.x as f32, q.z as f32]).then_some(i as u16)));
                }
                Source::Function(memo) => {
                    let cell = self.function_cell(memo, c);
                    f(c, &mut cell.iter().enumerate().filter_map(|(i, &q)| near(q).then_some(i as u16)));
                }
            }
        }
    }

    /// The instances within `distance` of `p` (on the ground plane): cells in row-major order, each cell's by index.
    pub fn visible(&self, p: [f32; 2], distance: f32) -> Vec<InstanceId> {
        let mut out = Vec::new();
        self.each_cell(p, distance, |c, indices| {
            out.extend(indices.map(|i| InstanceId::new(c, i).expect("a world's cells can be named")));
        });
        out
    }
}

/// The indices in cell `c` of the instances a client holds (their ids are `(c, index)`): the cell's records that
/// have arrived (empty if the cell is not held).
pub fn held_indices(state: &ClientState, c: CellCoord) -> Range<u16> {
    state.cells().get(&c).map_or(0..0, |h| 0..h.records.len() as u16)
}

/// Visible completeness: of the instances within `distance` of `p`, how many the client holds, where `held(c)`
/// gives the indices it holds in cell `c` (as [`held_indices`] reads them from a client's state; asked once per
/// cell). Returns `(visible, held)`.
pub fn completeness(
    truth: &GroundTruth,
    p: [f32; 2],
    distance: f32,
    held: impl Fn(CellCoord) -> Range<u16>,
) -> (usize, usize) {
    let (mut visible, mut n) = (0, 0);
    truth.each_cell(p, distance, |c, indices| {
        let have = held(c);
        for i in indices {
            visible += 1;
            n += usize::from(have.contains(&i));
        }
    });
    (visible, n)
}

/// What a client held at one sample, cell by cell: the records of each held cell within view distance of where
/// it was (`(c, n)`: indices `0..n`), sorted by cell.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct HeldSnapshot {
    cells: Vec<(CellCoord, u16)>,
}

impl HeldSnapshot {
    /// Read a client's state at `p`: the cells of `truth`'s grid within `distance` it holds records of.
    pub fn take(truth: &GroundTruth, state: &ClientState, p: [f32; 2], distance: f32) -> HeldSnapshot {
        let mut cells: Vec<(CellCoord, u16)> = truth
            .cells_within(p, distance)
            .into_iter()
            .map(|c| (c, held_indices(state, c).end))
            .filter(|&(_, n)| n > 0)
            .collect();
        cells.sort_unstable();
        HeldSnapshot { cells }
    }

    /// The indices held in cell `c` then.
    pub fn held(&self, c: CellCoord) -> Range<u16> {
        match self.cells.binary_search_by(|(x, _)| x.cmp(&c)) {
            Ok(i) => 0..self.cells[i].1,
            Err(_) => 0..0,
        }
    }
}

/// Fill in each sample's `visible` and `held` from its snapshot (`samples[i]` with `held[i]`): the instances of
/// `truth` within `distance` of the sample's position and those of them the client held. Cells are expanded as the
/// samples need them, in sample order, on up to `threads` threads.
pub fn evaluate(truth: &GroundTruth, samples: &mut [Sample], held: &[HeldSnapshot], threads: usize) {
    for (s, h) in samples.iter_mut().zip(held) {
        truth.prefetch(&truth.cells_within(s.position, s.view), threads);
        (s.visible, s.held) = completeness(truth, s.position, s.view, |c| h.held(c));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bandwidth::measure::{Bytes, CompletenessStats, SamplePhase, fraction};

    #[test]
    fn the_memo_keeps_the_most_recently_used_cells() {
        let mut m = Memo::new(2);
        let cell = |v: f32| -> CellPositions { Arc::from(vec![[v, v]]) };
        let c = |x| CellCoord::new(x, 0);
        m.insert(c(0), cell(0.0));
        m.insert(c(1), cell(1.0));
        assert!(m.get(c(0)).is_some());
        // (1, 0) is the least recently used now: it goes.
        m.insert(c(2), cell(2.0));
        assert!(m.get(c(1)).is_none() && m.get(c(0)).is_some() && m.get(c(2)).is_some());
        assert_eq!((m.cells.len(), m.cells.cost()), (2, 2));
        // A cell memoised twice keeps the first (another thread's) copy.
        assert_eq!(m.insert(c(2), cell(9.0))[0], [2.0, 2.0]);
        assert_eq!((m.cells.len(), m.cells.cost()), (2, 2));
    }

    /// A small world of 8 m cells: a species and one instance per `(x, z)`, in that order.
    fn world(bounds: &str, at: &[[f32; 2]]) -> Arc<World> {
        let mut src = format!("seed 1\nbounds {bounds}\ncell 8\nspecies worm worm\n");
        for [x, z] in at {
            src += &format!("instance worm at {x} {z}\n");
        }
        let file = canopy_worlds::diag::SourceFile::new("test.world", &src);
        Arc::new(World::parse(&file, None).unwrap_or_else(|d| panic!("{d}")))
    }

    /// 3 × 3 cells of 8 m from (-1, 0): ids 0..2 in the first, 2 in the next, 3 in (0, 1), 4 in (1, 2); read from
    /// the instances, and from the function with a memo of 2 cells.
    fn truths() -> (Arc<World>, [GroundTruth; 2]) {
        let w = world("-8 0 16 24", &[[-5.0, 5.0], [-1.0, 1.0], [5.0, 5.0], [1.0, 11.0], [9.0, 19.0]]);
        for (id, cell) in [(0, (-1, 0)), (1, (-1, 0)), (2, (0, 0)), (3, (0, 1)), (4, (1, 2))] {
            assert!(w.cell_instances(CellKey { x: cell.0, z: cell.1 }).contains(&id), "instance {id} in cell {cell:?}");
        }
        (Arc::clone(&w), [GroundTruth::new(Arc::clone(&w)), GroundTruth::from_function(w, 2)])
    }

    fn id(x: i32, z: i32, index: u16) -> InstanceId {
        InstanceId::new(CellCoord::new(x, z), index).unwrap()
    }

    #[test]
    fn ground_truth_finds_cells_and_visible_instances() {
        let (w, truths) = truths();
        for t in &truths {
            assert_eq!(t.len(), 5);
            // By the world's index: the ids are (cell, index in the cell).
            let ids = |v: &[u32]| v.iter().map(|&i| w.instance_id(i)).collect::<Vec<_>>();
            assert_eq!(ids(&[0, 1, 2]), [(-1, 0, 0), (-1, 0, 1), (0, 0, 0)].map(|(x, z, i)| id(x, z, i)));
            assert_eq!(t.visible([0.0, 0.0], 2.0), ids(&[1]));
            assert_eq!(t.visible([0.0, 5.0], 6.0), ids(&[0, 1, 2]));
            // (1, 11) is √37 > 6 away; from a little higher up it is in.
            assert_eq!(t.visible([0.0, 6.0], 6.0), ids(&[0, 1, 2, 3]));
            assert_eq!(t.visible([0.0, 0.0], 100.0), ids(&[0, 1, 2, 3, 4]));
            assert!(t.visible([500.0, 500.0], 10.0).is_empty());
            // The boundary counts as visible.
            assert_eq!(t.visible([5.0, 0.0], 5.0), ids(&[2]));
        }
        let [instances, function] = truths;
        assert_eq!(instances.stats(), TruthStats::default());
        let s = function.stats();
        assert!(s.expanded >= 9 && s.hits > 0 && s.memoised == 2, "{s:?}");
    }

    #[test]
    fn completeness_counts_what_is_held_of_what_is_visible() {
        let (_, truths) = truths();
        for t in &truths {
            // Of the visible 0..4: the even ones (the first of cell (-1, 0), cell (0, 0)'s only one).
            let even = |c: CellCoord| match (c.x, c.z) {
                (-1, 0) | (0, 0) => 0..1,
                _ => 0..0,
            };
            assert_eq!(completeness(t, [0.0, 6.0], 6.0, even), (4, 2));
            assert_eq!(completeness(t, [0.0, 6.0], 6.0, |_| 0..u16::MAX), (4, 4));
            assert_eq!(completeness(t, [0.0, 6.0], 6.0, |_| 0..0), (4, 0));
        }
        assert_eq!(fraction(4, 2), 0.5);
        assert_eq!(fraction(0, 0), 1.0);
        let samples = [sample(0.0, 10, 10), sample(1.0, 10, 5), sample(2.0, 0, 0), sample(3.0, 20, 20)];
        let c = CompletenessStats::over(&samples, |x| x.t >= 1.0);
        assert_eq!((c.samples, c.visible, c.held), (3, 30, 25));
        assert!((c.mean() - 25.0 / 30.0).abs() < 1e-12);
        assert_eq!(c.min, 0.5);
    }

    fn sample(t: f64, visible: usize, held: usize) -> Sample {
        Sample {
            t,
            phase: SamplePhase::Walking,
            position: [0.0; 2],
            view: 6.0,
            bytes: Bytes::default(),
            visible,
            held,
            aoi_complete: false,
        }
    }

    /// The default world, materialised at load: the ground truth from its function cell by cell (a memo smaller
    /// than what one position covers, so cells are evicted and expanded again) gives the same answers as
    /// `World::instances`, ids included.
    #[test]
    fn per_cell_ground_truth_matches_the_materialised_instances_on_the_default_world() {
        let w = Arc::new(World::default_world());
        assert!(w.is_materialised());
        let instances = GroundTruth::new(Arc::clone(&w));
        let function = GroundTruth::from_function(Arc::clone(&w), 16);
        let (lo, hi) = (w.bounds.min, w.bounds.max);
        // Places spread over the world (a low-discrepancy sequence), the world's corner (three quarters of the
        // circle outside) and a place beyond its edge.
        let spread = |i: u32, a: f32, k: usize| lo[k] + (i as f32 * a).fract() * (hi[k] - lo[k]);
        let mut at: Vec<[f32; 2]> = (1..=10).map(|i| [spread(i, 0.618_034, 0), spread(i, 0.414_214, 1)]).collect();
        at.extend([lo, [hi[0] + 50.0, 0.0]]);
        // Records held: the first half of the cells whose coordinates sum to an even number.
        let held = |c: CellCoord| {
            let n = w.cell_instances(CellKey { x: c.x, z: c.z }).len() as u16;
            if (c.x + c.z) % 2 == 0 { 0..n / 2 } else { 0..0 }
        };
        let mut total = 0;
        for p in at {
            let visible = instances.visible(p, 100.0);
            assert_eq!(function.visible(p, 100.0), visible, "at {p:?}");
            assert_eq!(completeness(&function, p, 100.0, held), completeness(&instances, p, 100.0, held), "at {p:?}");
            total += visible.len();
            // Every instance of every cell there, not only those within the distance.
            let d = 100.0 + w.cell_size * 1.5;
            let all = |t: &GroundTruth| completeness(t, p, d, |_| 0..u16::MAX);
            assert_eq!(all(&function), all(&instances), "at {p:?}");
        }
        assert!(total > 1_000, "{total} instances compared");
        let s = function.stats();
        assert!(s.expanded > 16 && s.memoised == 16, "{s:?}");
    }

    #[test]
    fn snapshots_hold_what_the_client_held_and_evaluate_against_the_truth() {
        let (_, [instances, function]) = truths();
        let snap = HeldSnapshot { cells: vec![(CellCoord::new(-1, 0), 1), (CellCoord::new(0, 0), 1)] };
        assert_eq!(snap.held(CellCoord::new(-1, 0)), 0..1);
        assert_eq!(snap.held(CellCoord::new(0, 1)), 0..0);
        let mut samples = [sample(0.0, 0, 0), sample(1.0, 0, 0), sample(2.0, 0, 0)];
        samples[1].position = [0.0, 6.0];
        // Each sample is judged within its own view distance (a radius fitted to the link shrinks it).
        (samples[2].position, samples[2].view) = ([0.0, 6.0], 0.5);
        let held = [HeldSnapshot::default(), snap.clone(), snap];
        for t in [&instances, &function] {
            evaluate(t, &mut samples, &held, 2);
            // At (0, 0): 1 visible ((-5, 5) is √50 away), not held; at (0, 6): 0..4 visible, 0 and 2 held; within
            // 0.5 m of it, none.
            assert_eq!(samples.map(|s| (s.visible, s.held)), [(1, 0), (4, 2), (0, 0)]);
        }
    }

    #[test]
    fn held_indices_read_the_client_state() {
        use canopy_protocol::aoi::{AoiParams, Viewpoint};
        use canopy_protocol::messages::SpeciesEntry;
        use canopy_protocol::messages::{ServerHandshake, ServerStreaming, TerrainDesc, Welcome, WorldInfo};
        use canopy_protocol::{CellBatch, InstanceRecord, POSITION_STEPS, PROTOCOL_VERSION, ServerMsg, SpeciesHash};
        let worm = canopy_worlds::library::find("worm").unwrap().load().unwrap().encode();
        // Cell (-1, 0) holds 10 instances, cell (0, 0) 4.
        let at: Vec<[f32; 2]> = [[-5.0, 5.0]; 10].into_iter().chain([[5.0, 5.0]; 4]).collect();
        let t = GroundTruth::new(world("-8 0 8 8", &at));
        let grid = Grid { origin: [0.0, 0.0], cell_size: 8.0, min: CellCoord::new(-1, 0), max: CellCoord::new(0, 0) };
        assert_eq!(&grid, t.grid());
        let terrain = TerrainDesc::flat([-8.0, 0.0], 16.0);
        let welcome = Welcome {
            version: PROTOCOL_VERSION,
            world: WorldInfo {
                name: "t".into(),
                seed: 1,
                grid,
                position_steps: POSITION_STEPS,
                instances: 14,
                terrain,
                function: None,
            },
            species: vec![SpeciesEntry { hash: SpeciesHash::of(&worm), size: worm.len() as u32 }],
            aoi: AoiParams { max_radius: 100.0, hysteresis: 10.0, lookahead_s: 0.0, max_lookahead: 0.0 },
        };
        let mut state = ClientState::new();
        state.hello("t").unwrap();
        state.on_welcome(ServerMsg::Handshake(ServerHandshake::Welcome(welcome))).unwrap();
        // Radius 3 at the centre of cell (0, 0): the area of interest is that cell alone.
        state.ready(Viewpoint::at(0, [4.0, 4.0], 3.0)).unwrap();
        let cells = [CellCoord::new(-1, 0), CellCoord::new(0, 0)];
        assert!(cells.iter().all(|&c| held_indices(&state, c).is_empty()));
        let records: Vec<InstanceRecord> = (0..2).map(|i| InstanceRecord::new(0, i, i)).collect();
        let batch = CellBatch::new(CellCoord::new(0, 0), 1, 4, 0, records, &[]);
        state.handle(ServerMsg::Streaming(ServerStreaming::Cells(batch))).unwrap();
        assert_eq!(cells.map(|c| held_indices(&state, c)), [0..0, 0..2]);
        // Everything visible from the cell's centre within 8 m is in that cell: 2 of 4 held.
        assert_eq!(completeness(&t, [4.0, 4.0], 8.0, |c| held_indices(&state, c)), (4, 2));
        // A snapshot of the state reads the same, and is what completeness is evaluated on.
        let snap = HeldSnapshot::take(&t, &state, [4.0, 4.0], 8.0);
        assert_eq!(snap.cells, [(CellCoord::new(0, 0), 2)]);
        assert_eq!(completeness(&t, [4.0, 4.0], 8.0, |c| snap.held(c)), (4, 2));
    }
}
