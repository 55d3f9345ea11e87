//! Cells amplified where they are drawn: a worker pool that expands granted cells from the world function,
//! nearest first, with a byte-bounded cache of expanded cells. One [`Expander`] serves one client, or every bot of
//! a process (they share its cache: the same world function gives the same cells).
//!
//! Far-view summary nodes ([`FarJob`]) are computed by the same workers into their world's memo, coarsest first,
//! and only while no cell waits: cells go first, and wait for one block of a node's leaves at most (a coarse node is
//! computed a block at a time, its job queued again after each).
//!
//! A job is dropped unexpanded when its grant is no longer wanted ([`Job::cancel`]: the cell was released or left
//! the area of interest). Worlds are built once per world function ([`Expander::world`]) from the manifest and the
//! species table, and expanded with the same function the server uses ([`World::expand_cell`]); records are
//! quantised on the welcome's grid, as the server quantises them.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BinaryHeap};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Condvar, Mutex, OnceLock};
use std::thread::JoinHandle;

use canopy_protocol::aoi::Grid;
use canopy_protocol::lru::Lru;
use canopy_protocol::messages::WorldFunction;
use canopy_protocol::record::ParamOverride;
use canopy_protocol::summary::NodeKey;
use canopy_protocol::sync::{Locked, Waited};
use canopy_protocol::{CellCoord, InstanceRecord, SpeciesGraph, SpeciesHash};
use canopy_worlds::world::far::Summaries;
use canopy_worlds::world::{CellKey, Placement, World};

/// The default bound of the expanded-cell cache, bytes.
pub const DEFAULT_CACHE_BYTES: usize = 64 << 20;

/// Worlds kept built, by world function (a process rarely serves more than one).
const WORLDS_KEPT: usize = 4;

/// A world function built into a world, with the grid its records are quantised on and the memo of its far-view
/// summary nodes (shared, like the world, by every client of the process).
#[derive(Debug)]
pub struct ExpandWorld {
    /// The world function's hash.
    pub hash: SpeciesHash,
    /// The world.
    pub world: Arc<World>,
    /// The welcome's cell grid.
    pub grid: Grid,
    summaries: OnceLock<Mutex<Summaries>>,
    /// The version of each cell whose edits the memo's leaves take (far cells): a connection told of an older
    /// version than another one of the process was does not take the memo back.
    corrected: Mutex<std::collections::BTreeMap<CellCoord, u32>>,
}

impl ExpandWorld {
    /// The world `world` of the world function `hash`, quantised on `grid`.
    pub fn new(hash: SpeciesHash, world: Arc<World>, grid: Grid) -> ExpandWorld {
        ExpandWorld { hash, world, grid, summaries: OnceLock::new(), corrected: Mutex::default() }
    }

    /// Correct the memo by the edits of `cell` at `version` ([`Summaries::correct`]) unless it holds a later
    /// version of them; whether the memo now holds this version's (changed now, or by another connection before).
    pub fn correct(&self, cell: CellCoord, version: u32, edits: Arc<[canopy_worlds::world::LeafEdit]>) -> bool {
        let mut corrected = self.corrected.locked();
        if corrected.get(&cell).is_some_and(|&v| v > version) {
            return false;
        }
        let key = canopy_worlds::world::far::cell_key(cell);
        let mut memo = self.summaries().locked();
        let held = memo.edits_of(key).is_some_and(|e| **e == *edits);
        if held || memo.correct(key, Some(edits)) {
            corrected.insert(cell, version);
            return true;
        }
        false
    }

    /// The memo of its far-view summary nodes (bounded: [`Summaries::new`]).
    pub fn summaries(&self) -> &Mutex<Summaries> {
        self.summaries.get_or_init(|| Mutex::new(Summaries::new(Arc::clone(&self.world))))
    }
}

/// One cell's records as the world function places them: record `i` is instance `(cell, i)`; overrides by index
/// in the cell, sorted by `(record, slot)`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Expanded {
    /// The records.
    pub records: Vec<InstanceRecord>,
    /// Parameter overrides.
    pub overrides: Vec<ParamOverride>,
}

impl Expanded {
    /// Quantise a cell's placements on `grid` (as the server's store does).
    pub fn of_placements(grid: &Grid, cell: CellCoord, placements: &[Placement]) -> Expanded {
        let mut out = Expanded { records: Vec::with_capacity(placements.len()), overrides: Vec::new() };
        for (i, p) in placements.iter().enumerate() {
            let [qx, qz] = grid.steps(cell, p.x, p.z);
            out.records.push(InstanceRecord::new(p.species as u8, qx, qz));
            let record = i as u16;
            out.overrides.extend(p.params.iter().map(|&(slot, value)| ParamOverride { record, slot, value }));
        }
        out.overrides.sort_by_key(|o| (o.record, o.slot));
        out
    }

    fn bytes(&self) -> usize {
        64 + self.records.len() * size_of::<InstanceRecord>() + self.overrides.len() * size_of::<ParamOverride>()
    }
}

/// A cell to expand, for whoever asked: `done` is called with the records on a worker thread, unless the job was
/// cancelled first.
pub struct Job {
    /// The world to expand it in.
    pub world: Arc<ExpandWorld>,
    /// The cell.
    pub cell: CellCoord,
    /// Smaller first: the cell's distance from the viewer that asked.
    pub priority: f32,
    /// Set when the cell is no longer wanted.
    pub cancelled: Arc<AtomicBool>,
    /// Called with the records.
    pub done: Box<dyn FnOnce(Arc<Expanded>) + Send>,
}

/// A far-view summary node to compute into its world's memo ([`ExpandWorld::summaries`]), for whoever asked:
/// `done` is called on a worker thread once the node is there, unless the job was cancelled first.
pub struct FarJob {
    /// The world.
    pub world: Arc<ExpandWorld>,
    /// The node.
    pub node: NodeKey,
    /// Set when the node is no longer wanted.
    pub cancelled: Arc<AtomicBool>,
    /// Called once the node is in the memo.
    pub done: Box<dyn FnOnce() + Send>,
}

impl Job {
    /// Cancel the job (a no-op once it ran).
    pub fn cancel(flag: &AtomicBool) {
        flag.store(true, Relaxed);
    }
}

struct Queued(Job, u64);

impl PartialEq for Queued {
    fn eq(&self, other: &Queued) -> bool {
        self.cmp(other).is_eq()
    }
}
impl Eq for Queued {}
impl PartialOrd for Queued {
    fn partial_cmp(&self, other: &Queued) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Queued {
    // The heap pops the largest: the nearest, then the oldest.
    fn cmp(&self, other: &Queued) -> std::cmp::Ordering {
        other.0.priority.total_cmp(&self.0.priority).then(other.1.cmp(&self.1))
    }
}

#[derive(Default)]
struct Queue {
    jobs: BinaryHeap<Queued>,
    /// Far-view nodes, coarsest first, then the oldest; taken only while `jobs` is empty.
    far: BTreeMap<(Reverse<u8>, u64), FarJob>,
    next: u64,
    stop: bool,
}

/// Counters of an expander.
#[derive(Debug, Default)]
pub struct ExpandStats {
    /// Cells expanded.
    pub expanded: AtomicU64,
    /// Jobs answered from the cache.
    pub hits: AtomicU64,
    /// Jobs dropped because they were cancelled before a worker took them.
    pub cancelled: AtomicU64,
    /// Nanoseconds spent expanding.
    pub nanos: AtomicU64,
    /// Far-view node jobs run.
    pub far_jobs: AtomicU64,
}

struct Inner {
    queue: Mutex<Queue>,
    work: Condvar,
    cache: Mutex<Lru<(SpeciesHash, CellCoord), Arc<Expanded>>>,
    cache_bytes: usize,
    worlds: Mutex<Vec<Arc<ExpandWorld>>>,
    functions: Mutex<Vec<Arc<WorldFunction>>>,
    stats: ExpandStats,
}

/// The worker pool (see the module docs). Dropping it stops its workers; queued jobs are dropped.
pub struct Expander {
    inner: Arc<Inner>,
    workers: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for Expander {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Expander").field("workers", &self.workers.len()).finish()
    }
}

impl Expander {
    /// A pool of `workers` threads (at least one) and a cache of `cache_bytes`.
    pub fn new(workers: usize, cache_bytes: usize) -> Arc<Expander> {
        let inner = Arc::new(Inner {
            queue: Mutex::new(Queue::default()),
            work: Condvar::new(),
            cache: Mutex::new(Lru::new()),
            cache_bytes,
            worlds: Mutex::new(Vec::new()),
            functions: Mutex::new(Vec::new()),
            stats: ExpandStats::default(),
        });
        let workers = (0..workers.max(1))
            .map(|i| {
                let inner = Arc::clone(&inner);
                std::thread::Builder::new()
                    .name(format!("canopy-expand-{i}"))
                    .spawn(move || inner.run())
                    .expect("spawning an expansion worker")
            })
            .collect();
        Arc::new(Expander { inner, workers })
    }

    /// A pool with a worker per available core (one fewer, at least one, so the driver keeps a core) and the
    /// default cache.
    pub fn default_pool() -> Arc<Expander> {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        Expander::new(cores.saturating_sub(1).max(1), DEFAULT_CACHE_BYTES)
    }

    /// The counters.
    pub fn stats(&self) -> &ExpandStats {
        &self.inner.stats
    }

    /// A world function this process already holds, by hash.
    pub fn function(&self, hash: &SpeciesHash) -> Option<Arc<WorldFunction>> {
        self.inner.functions.locked().iter().find(|f| f.hash() == *hash).cloned()
    }

    /// The world of a world function, built once per function: from its manifest with `species` (the welcome's
    /// table, by id) and the terrain species, quantised on `grid`. The error is the manifest's diagnostics.
    pub fn world(
        &self,
        name: &str,
        function: &Arc<WorldFunction>,
        species: &[SpeciesGraph],
        terrain: Option<&SpeciesGraph>,
        grid: Grid,
    ) -> Result<Arc<ExpandWorld>, String> {
        let hash = function.hash();
        if let Some(w) = self.inner.worlds.locked().iter().find(|w| w.hash == hash) {
            return Ok(Arc::clone(w));
        }
        let world = World::from_function(name, &function.manifest, species, terrain).map_err(|d| d.to_string())?;
        let built = Arc::new(ExpandWorld::new(hash, Arc::new(world), grid));
        let mut worlds = self.inner.worlds.locked();
        if let Some(w) = worlds.iter().find(|w| w.hash == hash) {
            return Ok(Arc::clone(w));
        }
        if worlds.len() >= WORLDS_KEPT {
            worlds.remove(0);
        }
        worlds.push(Arc::clone(&built));
        let mut functions = self.inner.functions.locked();
        if !functions.iter().any(|f| f.hash() == hash) {
            if functions.len() >= WORLDS_KEPT {
                functions.remove(0);
            }
            functions.push(Arc::clone(function));
        }
        Ok(built)
    }

    /// Use `world` for its hash from now on, in place of building it from the world function (a world built
    /// elsewhere; tests use it to make a client whose expansion differs from the server's).
    pub fn adopt(&self, world: ExpandWorld) {
        let mut worlds = self.inner.worlds.locked();
        worlds.retain(|w| w.hash != world.hash);
        worlds.push(Arc::new(world));
    }

    /// Queue a job (answered at once from the cache when the cell is there).
    pub fn submit(&self, job: Job) {
        let cached = self.inner.cache.locked().get(&(job.world.hash, job.cell)).cloned();
        if let Some(e) = cached {
            self.inner.stats.hits.fetch_add(1, Relaxed);
            (job.done)(e);
            return;
        }
        let mut q = self.inner.queue.locked();
        let n = q.next;
        q.next += 1;
        q.jobs.push(Queued(job, n));
        drop(q);
        self.inner.work.notify_one();
    }

    /// Queue a far-view node (computed once no cell waits).
    pub fn submit_far(&self, job: FarJob) {
        let mut q = self.inner.queue.locked();
        let n = q.next;
        q.next += 1;
        q.far.insert((Reverse(job.node.level), n), job);
        drop(q);
        self.inner.work.notify_one();
    }

    /// Jobs queued and not taken by a worker yet (cancelled ones included until a worker passes them).
    pub fn queued(&self) -> usize {
        self.inner.queue.locked().jobs.len()
    }
}

impl Drop for Expander {
    fn drop(&mut self) {
        {
            let mut q = self.inner.queue.locked();
            q.stop = true;
            q.jobs.clear();
            q.far.clear();
        }
        self.inner.work.notify_all();
        for w in self.workers.drain(..) {
            let _ = w.join();
        }
    }
}

impl Inner {
    /// A block of the far job's node: done when it was the last (the job's `done` called), else the job goes back
    /// to its place in the queue, so that a cell granted meanwhile waits for one block at most.
    fn run_far(&self, order: (Reverse<u8>, u64), job: FarJob) {
        if job.cancelled.load(Relaxed) {
            return;
        }
        if Summaries::step_shared(job.world.summaries(), job.node).is_none() {
            self.queue.locked().far.insert(order, job);
            return;
        }
        self.stats.far_jobs.fetch_add(1, Relaxed);
        (job.done)();
    }

    fn run(&self) {
        loop {
            let job = {
                let mut q = self.queue.locked();
                loop {
                    if q.stop {
                        return;
                    }
                    if let Some(Queued(job, _)) = q.jobs.pop() {
                        break job;
                    }
                    if let Some((order, far)) = q.far.pop_first() {
                        drop(q);
                        self.run_far(order, far);
                        q = self.queue.locked();
                        continue;
                    }
                    q = self.work.waited(q);
                }
            };
            if job.cancelled.load(Relaxed) {
                self.stats.cancelled.fetch_add(1, Relaxed);
                continue;
            }
            let key = (job.world.hash, job.cell);
            let cached = self.cache.locked().get(&key).cloned();
            let expanded = match cached {
                Some(e) => {
                    self.stats.hits.fetch_add(1, Relaxed);
                    e
                }
                None => {
                    let t = std::time::Instant::now();
                    let w = &job.world;
                    let placements = w.world.expand_cell(CellKey { x: job.cell.x, z: job.cell.z });
                    let e = Arc::new(Expanded::of_placements(&w.grid, job.cell, &placements));
                    self.stats.nanos.fetch_add(t.elapsed().as_nanos() as u64, Relaxed);
                    self.stats.expanded.fetch_add(1, Relaxed);
                    let mut cache = self.cache.locked();
                    cache.insert(key, Arc::clone(&e), e.bytes());
                    cache.evict_to(self.cache_bytes, Some(&key));
                    e
                }
            };
            (job.done)(expanded);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_protocol::aoi::Grid;

    fn grid() -> Grid {
        Grid { origin: [0.0, 0.0], cell_size: 32.0, min: CellCoord::new(-4, -4), max: CellCoord::new(3, 3) }
    }

    fn worm() -> SpeciesGraph {
        canopy_worlds::library::find("worm").unwrap().load().unwrap()
    }

    /// A world function over ±`half` metres in cells of `cell` metres whose species `a` is the worm, `rest` after it.
    fn worm_function(half: u32, cell: u32, rest: &str) -> Arc<WorldFunction> {
        let manifest = format!("seed 7\nbounds -{half} -{half} {half} {half}\ncell {cell}\nspecies a worm\n{rest}");
        Arc::new(WorldFunction { manifest })
    }

    #[test]
    fn a_world_function_that_does_not_build_is_refused_with_its_line_and_column() {
        let expander = Expander::new(1, 1 << 20);
        let worm = worm();
        let bad = worm_function(128, 32, "scatter a {\n  spacing -3\n}\n");
        let err = expander.world("bad", &bad, std::slice::from_ref(&worm), None, grid()).unwrap_err();
        assert!(err.contains("bad.world:6:"), "{err}");
        // A function naming more species than the table holds says so, and names no file it could not read.
        let two = worm_function(128, 32, "species b worm\n");
        let err = expander.world("two", &two, std::slice::from_ref(&worm), None, grid()).unwrap_err();
        assert!(err.contains("species table"), "{err}");
    }

    /// A cell granted while a coarse far-view node is being computed waits for one block of its leaves, not for
    /// the node: with one worker, the cell is done before the node. A node cancelled while it is computed stops
    /// within a block: the next far job runs, and the cancelled node has that one block.
    ///
    /// No race with the worker's speed: the test holds the memo's lock, which the worker's first block of a node
    /// waits for, from before the node is queued until the worker has taken it and the cell is queued (or the node
    /// cancelled).
    #[test]
    fn a_cell_goes_between_the_blocks_of_a_far_node() {
        let expander = Expander::new(1, 1 << 20);
        let f = worm_function(2048, 64, "scatter a {\n  spacing 4\n}\n");
        let grid =
            Grid { origin: [0.0, 0.0], cell_size: 64.0, min: CellCoord::new(-32, -32), max: CellCoord::new(31, 31) };
        let world = expander.world("t", &f, &[worm()], None, grid).unwrap();
        // 4 × 4 blocks of 16 × 16 cells.
        let block = canopy_worlds::world::far::LEAF_BLOCK_LEVEL;
        let node = NodeKey::of_cell(CellCoord::new(0, 0), block + 2);
        let (tx, rx) = std::sync::mpsc::channel();
        let far = |node: NodeKey, cancelled: &Arc<AtomicBool>, name: &'static str| {
            let tx = tx.clone();
            FarJob {
                world: Arc::clone(&world),
                node,
                cancelled: Arc::clone(cancelled),
                done: Box::new(move || tx.send(name).unwrap()),
            }
        };
        // The worker has taken the node from the queue: it is under way, in its first block.
        let taken = || {
            while !expander.inner.queue.locked().far.is_empty() {
                std::thread::yield_now();
            }
        };
        let gate = world.summaries().locked();
        expander.submit_far(far(node, &Arc::default(), "node"));
        taken();
        let cell_tx = tx.clone();
        expander.submit(Job {
            world: Arc::clone(&world),
            cell: CellCoord::new(3, 3),
            priority: 0.0,
            cancelled: Arc::default(),
            done: Box::new(move |_| cell_tx.send("cell").unwrap()),
        });
        drop(gate);
        assert_eq!([rx.recv().unwrap(), rx.recv().unwrap()], ["cell", "node"]);
        let memo = world.summaries().locked().peek(node).cloned().expect("the node is in the memo");
        assert_eq!(*memo, world.world.node_summary(node));

        // The other 16 blocks' node, cancelled while its first block is computed; then a node of one block.
        let blocks_of = |key: NodeKey| {
            let (memo, side) = (world.summaries().locked(), 1 << (key.level - block));
            let at = |i: i32| NodeKey { level: block, x: key.x * side + i % side, z: key.z * side + i / side };
            (0..side * side).filter(|&i| memo.peek(at(i)).is_some()).count()
        };
        let other = NodeKey::of_cell(CellCoord::new(-32, -32), block + 2);
        let cancel = Arc::new(AtomicBool::new(false));
        let gate = world.summaries().locked();
        expander.submit_far(far(other, &cancel, "cancelled"));
        taken();
        Job::cancel(&cancel);
        drop(gate);
        expander.submit_far(far(NodeKey::of_cell(CellCoord::new(16, -32), block), &Arc::default(), "small"));
        assert_eq!(rx.recv().unwrap(), "small", "the cancelled node's done is never called");
        assert_eq!(blocks_of(other), 1, "the cancelled node stopped after the block it was computing");
    }

    #[test]
    fn cancelled_jobs_are_dropped_and_the_rest_expand_nearest_first_once_each() {
        let expander = Expander::new(1, 1 << 20);
        let worm = worm();
        let f = worm_function(128, 32, "scatter a {\n  spacing 4\n}\n");
        let world = expander.world("t", &f, std::slice::from_ref(&worm), None, grid()).unwrap();
        assert!(Arc::ptr_eq(&world, &expander.world("t", &f, &[worm], None, grid()).unwrap()), "built once");
        assert_eq!(expander.function(&f.hash()).as_deref(), Some(&*f));
        let (tx, rx) = std::sync::mpsc::channel();
        let job = |cell: CellCoord, priority: f32, cancelled: bool| Job {
            world: Arc::clone(&world),
            cell,
            priority,
            cancelled: Arc::new(AtomicBool::new(cancelled)),
            done: {
                let tx = tx.clone();
                Box::new(move |e| tx.send((cell, e)).unwrap())
            },
        };
        let cells = [CellCoord::new(0, 0), CellCoord::new(1, 0), CellCoord::new(2, 0)];
        expander.submit(job(cells[0], 2.0, false));
        expander.submit(job(cells[1], 1.0, true));
        expander.submit(job(cells[2], 3.0, false));
        let got: Vec<(CellCoord, Arc<Expanded>)> = (0..2).map(|_| rx.recv().unwrap()).collect();
        assert!(got.iter().all(|(c, _)| *c != cells[1]), "the cancelled job never ran");
        for (c, e) in &got {
            let want = world.world.expand_cell(CellKey { x: c.x, z: c.z });
            assert_eq!(**e, Expanded::of_placements(&grid(), *c, &want));
            assert!(!e.records.is_empty());
        }
        // Asked again, a cell comes from the cache.
        expander.submit(job(cells[0], 0.0, false));
        assert_eq!(rx.recv().unwrap().1, got.iter().find(|(c, _)| *c == cells[0]).unwrap().1);
        assert_eq!(expander.stats().expanded.load(Relaxed), 2);
        assert!(expander.stats().hits.load(Relaxed) >= 1);
    }
}
