//! The shared cell cache: a [`WorldStore`] that expands cells on demand ([`World::expand_cell`]) on a pool of
//! worker threads and keeps them, quantised ([`CellData`], exactly as [`canopy_session::GridStore`] holds them) with
//! their batches encoded once ([`CellData::bodies`]), in an LRU bounded by bytes.
//!
//! A session never waits: asking for a cell that is not cached queues its expansion (once, however many sessions
//! ask while it is queued or running; a worker takes the queued cells of one aligned block of [`BLOCK`] × [`BLOCK`]
//! together, sharing their neighbourhood's work) and answers [`CellState::Pending`]; the session sends other cells meanwhile
//! and the waker it passed is woken when the cell is ready. Evicting a cell only drops the cache's reference: a
//! session in the middle of sending it keeps it alive by its `Arc`, and asking again expands it again to the same
//! bytes (expansion is a pure function of the manifest and the cell).
//!
//! Memory bound: the cached cells' bytes ([`CellData::heap_bytes`]: records, overrides, encoded bodies, plus an
//! estimate of the index's cost per cell) stay at or below the limit, except that a single cell larger than the
//! whole limit is still kept, alone, so it can be sent.
//! Cells pinned by sessions mid-send are bounded per session by its area of interest.
//!
//! The far view's summary nodes are computed on the same workers when no cell waits, and corrected by cells'
//! edits ([`WorldStore::correct_summaries`], called by the live store): the memo first, then the cached nodes,
//! and a node computed across a correction is computed again, so that what is cached is never older than a
//! correction the sessions were told of ([`WorldStore::summary_corrections`]).

use std::sync::atomic::AtomicU64;
use std::sync::atomic::Ordering::{Acquire, Relaxed, Release};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Instant;

use canopy_protocol::CellCoord;
use canopy_protocol::aoi::Grid;
use canopy_protocol::edit::CellDelta;
use canopy_protocol::lru::Lru;
use canopy_protocol::summary::NodeKey;
use canopy_protocol::sync::{Locked, Waited};
use canopy_worlds::world::far::Summaries;
use canopy_worlds::world::{CellKey, World};
use tracing::{error, warn};

use crate::metrics::CellMetrics;
use canopy_session::{
    CellData, CellState, CellWaker, EncodedSummary, StoreError, StoreHead, SummaryCorrections, SummaryState,
    VersionState, WorldStore,
};
use canopy_session::{SummaryLru, Waiters};

/// Queued cells of one aligned block of `BLOCK` × `BLOCK` cells are expanded together.
pub(crate) const BLOCK: i32 = 4;
/// Times a summary node computed across a correction is computed again before its waiters are left to ask again.
const SUMMARY_TRIES: usize = 3;
/// Most cells whose edits the summaries take (as many as the live store indexes).
const MAX_CORRECTED_CELLS: usize = 1 << 18;

/// How a cell cache runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CellCacheConfig {
    /// Most bytes of cached cells.
    pub limit_bytes: usize,
    /// Worker threads expanding cells; 0: none, cells queued are expanded only by [`CellCache::run_queued`]
    /// (deterministic tests).
    pub workers: usize,
    /// The batch size whose bodies are encoded with each cell (the sessions' [`canopy_session::SessionConfig::batch_records`]).
    pub batch_records: usize,
    /// Most bytes of cached far-view summary nodes (encoded, shared by sessions); the workers compute them when no
    /// cell is queued.
    pub summary_limit_bytes: usize,
}

impl Default for CellCacheConfig {
    fn default() -> Self {
        CellCacheConfig {
            limit_bytes: 256 << 20,
            workers: std::thread::available_parallelism().map_or(1, |n| n.get()),
            batch_records: canopy_session::SessionConfig::default().batch_records,
            summary_limit_bytes: 64 << 20,
        }
    }
}

/// Bytes a cached cell costs beyond its [`CellData::heap_bytes`]: its entry, its LRU slot and their share of the
/// maps' tables (an estimate, counted against the bound).
const ENTRY_OVERHEAD: usize =
    std::mem::size_of::<(Arc<CellData>, usize, u64)>() + std::mem::size_of::<(u64, CellCoord)>() + 64;

/// What the lock guards.
#[derive(Default)]
struct State {
    /// Expanded cells, bounded by bytes.
    cached: Lru<CellCoord, Arc<CellData>>,
    /// The most bytes ever cached at once.
    peak: usize,
    /// Cells queued or being expanded, with the wakers to wake when each is ready.
    pending: Waiters<CellCoord>,
    /// Far-view summary nodes: cached, queued, pending.
    summaries: SummaryLru,
    stop: bool,
}

/// A worker's next job: cells first, summaries when no cell waits.
enum Work {
    Cells(Vec<CellCoord>),
    Summary(NodeKey),
}

/// What the cache and its workers share.
struct Shared {
    world: Arc<World>,
    /// The summary hierarchy's memo (a node computed from its children, leaves in blocks); one worker at a time.
    memo: Mutex<Summaries>,
    /// The level of the summary roots: nodes of at least 4 km.
    root_level: u8,
    grid: Grid,
    species_count: usize,
    cfg: CellCacheConfig,
    state: Mutex<State>,
    work: Condvar,
    metrics: Arc<CellMetrics>,
    /// Bumped (under the lock, after caching) each time a cell becomes ready: [`WorldStore::generation`].
    generation: AtomicU64,
    /// The summaries' count of corrections, read without the lock by every session's poll.
    corrected: AtomicU64,
}

/// The shared cell cache (see the module docs).
pub struct CellCache {
    head: StoreHead,
    shared: Arc<Shared>,
    workers: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for CellCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CellCache").field("cfg", &self.shared.cfg).field("workers", &self.workers.len()).finish()
    }
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.locked()
    }

    /// Expand, quantise and encode `cells` (no lock held): queued cells of one aligned block of [`BLOCK`] ×
    /// [`BLOCK`] cells, expanded together through [`World::expand_cells`] — the same bytes as one at a time, with
    /// the neighbourhood's work shared (about 3× less per cell on the highlands world when the block is full).
    fn expand(&self, cells: &[CellCoord]) -> Vec<(CellCoord, Result<CellData, StoreError>)> {
        let (mut lo, mut hi) = (cells[0], cells[0]);
        for c in cells {
            (lo.x, lo.z, hi.x, hi.z) = (lo.x.min(c.x), lo.z.min(c.z), hi.x.max(c.x), hi.z.max(c.z));
        }
        let expanded = self.world.expand_cells(CellKey { x: lo.x, z: lo.z }, CellKey { x: hi.x, z: hi.z });
        expanded
            .into_iter()
            .map(|(k, placements)| (CellCoord::new(k.x, k.z), placements))
            .filter(|(c, _)| cells.contains(c))
            .map(|(c, placements)| {
                let data = CellData::from_placements(&self.grid, c, self.species_count, &placements);
                if let Ok(d) = &data {
                    d.bodies(self.cfg.batch_records);
                }
                (c, data)
            })
            .collect()
    }

    /// Expand `cells` (see [`Shared::expand`]) and cache them, then wake whoever waits for each. The expansion
    /// time is recorded per cell, the block's shared by its cells.
    fn complete(&self, cells: &[CellCoord]) {
        let started = Instant::now();
        let expanded = self.expand(cells);
        let per_cell = started.elapsed() / cells.len().max(1) as u32;
        for (c, data) in expanded {
            let data = match data {
                Ok(data) => data,
                Err(e) => {
                    // Worlds are checked when loaded, so this is a bug; the cell goes out empty rather than never.
                    error!(cell = ?c, "cell expansion failed: {e}");
                    self.metrics.failures.fetch_add(1, Relaxed);
                    CellData::from_quantised(c, 0, std::iter::empty()).expect("an empty cell")
                }
            };
            self.metrics.expansion_time.record(per_cell);
            self.cache(c, data);
        }
    }

    /// Do one job.
    fn run(&self, work: Work) -> usize {
        match work {
            Work::Cells(cells) => {
                self.complete(&cells);
                cells.len()
            }
            Work::Summary(key) => {
                self.summarise(key);
                1
            }
        }
    }

    /// Compute a summary node (through the memo, which keeps the nodes below it), encode it, cache it and wake its
    /// waiters. A node computed across a correction of the memo is computed again (it may hold the cell
    /// corrected); one corrected every time is left to its waiters to ask for again.
    fn summarise(&self, key: NodeKey) {
        for _ in 0..SUMMARY_TRIES {
            let started = Instant::now();
            let seen = self.lock().summaries.corrections();
            // The leaves are computed outside the memo's lock, so both workers compute at once.
            let node = Summaries::get_shared(&self.memo, key);
            let encoded = Arc::new(EncodedSummary::new(node));
            self.metrics.summary_time.record(started.elapsed());
            self.metrics.summaries.fetch_add(1, Relaxed);
            if self.publish(key, encoded, seen) {
                return;
            }
        }
        let wakers = self.lock().summaries.abandon(key);
        wakers.iter().for_each(|w| w.wake());
    }

    /// Node `key` if the memo holds it already (computed with an ancestor, or for another session), published so
    /// that no worker computes it: a session walking down a computed subtree gets it at once instead of queueing
    /// every node behind the roots still being computed. `None` if not memoised, the memo is busy, or it was
    /// corrected meanwhile.
    fn memoised(&self, key: NodeKey) -> Option<Arc<EncodedSummary>> {
        let seen = self.lock().summaries.corrections();
        let node = Arc::clone(self.memo.try_lock().ok()?.peek(key)?);
        let encoded = Arc::new(EncodedSummary::new(node));
        self.publish(key, Arc::clone(&encoded), seen).then_some(encoded)
    }

    /// Cache an encoded node computed when the summaries had seen `seen` corrections and wake its waiters; whether
    /// it was (not if a correction came since: it may be stale).
    fn publish(&self, key: NodeKey, encoded: Arc<EncodedSummary>, seen: u64) -> bool {
        let wakers = {
            let mut st = self.lock();
            if st.summaries.corrections() != seen {
                return false;
            }
            let wakers = st.summaries.insert(key, encoded, self.cfg.summary_limit_bytes);
            self.metrics.summary_bytes.store(st.summaries.bytes() as u64, Relaxed);
            self.generation.fetch_add(1, Release);
            wakers
        };
        for w in wakers {
            w.wake();
        }
        true
    }

    /// Correct the memo's nodes holding cell `c` by its edits, then drop the cached ones and count the correction
    /// (in that order: a node computed from the memo before it was corrected is not cached after).
    fn correct(&self, c: CellCoord, delta: Option<&CellDelta>) -> bool {
        let key = CellKey { x: c.x, z: c.z };
        let edits = delta.map(|d| {
            let placements = self.world.expand_cell(key);
            Arc::from(self.world.leaf_edits(key, &placements, d))
        });
        if !self.memo.locked().correct(key, edits) {
            return false;
        }
        let mut st = self.lock();
        st.summaries.correct(c, self.root_level);
        self.corrected.store(st.summaries.corrections(), Release);
        self.metrics.summary_bytes.store(st.summaries.bytes() as u64, Relaxed);
        self.generation.fetch_add(1, Release);
        true
    }

    /// Cache an expanded cell, evicting the least recently used ones past the bound, and wake its waiters.
    fn cache(&self, c: CellCoord, data: CellData) {
        let data = Arc::new(data);
        let bytes = data.heap_bytes() + ENTRY_OVERHEAD;
        let wakers = {
            let mut st = self.lock();
            if bytes > self.cfg.limit_bytes {
                warn!(cell = ?c, bytes, limit = self.cfg.limit_bytes, "one cell is larger than the cell cache");
            }
            st.cached.insert(c, data, bytes);
            let evicted = st.cached.evict_to(self.cfg.limit_bytes, Some(&c));
            self.metrics.evictions.fetch_add(evicted.len() as u64, Relaxed);
            st.peak = st.peak.max(st.cached.cost());
            self.metrics.bytes.store(st.cached.cost() as u64, Relaxed);
            self.metrics.cells.store(st.cached.len() as u64, Relaxed);
            self.metrics.expansions.fetch_add(1, Relaxed);
            self.generation.fetch_add(1, Release);
            st.pending.done(&c)
        };
        for w in wakers {
            w.wake();
        }
    }

    /// Take the next queued cell and every other queued cell of its aligned block of [`BLOCK`] × [`BLOCK`] cells
    /// (expanded together), waiting for one unless `wait` is false; `None` when stopped or (not waiting) when the
    /// queue is empty.
    fn next(&self, wait: bool) -> Option<Work> {
        let mut st = self.lock();
        loop {
            if st.stop {
                return None;
            }
            if st.pending.queued() == 0
                && let Some(k) = st.summaries.next_queued()
            {
                return Some(Work::Summary(k));
            }
            if let Some(c) = st.pending.take() {
                let block = |c: CellCoord| (c.x.div_euclid(BLOCK), c.z.div_euclid(BLOCK));
                let mut cells = vec![c];
                cells.extend(st.pending.take_if(|&q| block(q) == block(c)));
                self.metrics.queued.store(st.pending.queued() as u64, Relaxed);
                return Some(Work::Cells(cells));
            }
            if !wait {
                return None;
            }
            st = self.work.waited(st);
        }
    }
}

impl CellCache {
    /// A cache of `world`'s cells; starts `cfg.workers` worker threads.
    pub fn new(world: World, cfg: CellCacheConfig) -> Result<CellCache, StoreError> {
        let head = StoreHead::of_world(&world)?;
        let world = Arc::new(world);
        let root_level = canopy_session::root_level(head.world().grid.cell_size);
        let metrics = Arc::new(CellMetrics::default());
        metrics.limit.store(cfg.limit_bytes as u64, Relaxed);
        let mut memo = Summaries::new(Arc::clone(&world));
        memo.set_max_corrected(MAX_CORRECTED_CELLS);
        let shared = Arc::new(Shared {
            grid: head.world().grid,
            species_count: head.species().len(),
            memo: Mutex::new(memo),
            root_level,
            world,
            cfg,
            state: Mutex::new(State::default()),
            work: Condvar::new(),
            metrics,
            generation: AtomicU64::new(0),
            corrected: AtomicU64::new(0),
        });
        let workers = (0..cfg.workers)
            .map(|i| {
                let shared = Arc::clone(&shared);
                std::thread::Builder::new()
                    .name(format!("canopy-cells-{i}"))
                    .spawn(move || {
                        while let Some(work) = shared.next(true) {
                            shared.run(work);
                        }
                    })
                    .expect("spawning a cell worker")
            })
            .collect();
        Ok(CellCache { head, shared, workers })
    }

    /// Share it between sessions.
    pub fn shared(self) -> Arc<dyn WorldStore> {
        Arc::new(self)
    }

    /// Expand every queued cell and compute every queued summary node on this thread, those queued meanwhile
    /// included; how many. With no workers this is the only way cells get expanded (tests run the pool
    /// deterministically with it).
    pub fn run_queued(&self) -> usize {
        let mut n = 0;
        while let Some(work) = self.shared.next(false) {
            n += self.shared.run(work);
        }
        n
    }

    /// Summary nodes cached now, and their bytes.
    pub fn summaries_cached(&self) -> (usize, usize) {
        let st = self.shared.lock();
        (st.summaries.len(), st.summaries.bytes())
    }

    /// The counters.
    pub fn metrics(&self) -> &Arc<CellMetrics> {
        &self.shared.metrics
    }

    /// Bytes cached now.
    pub fn bytes(&self) -> usize {
        self.shared.lock().cached.cost()
    }

    /// The most bytes cached at any one time so far.
    pub fn peak_bytes(&self) -> usize {
        self.shared.lock().peak
    }

    /// Whether a cell is cached now.
    pub fn is_cached(&self, c: CellCoord) -> bool {
        self.shared.lock().cached.contains(&c)
    }

    /// Cells queued or being expanded now.
    pub fn pending(&self) -> usize {
        self.shared.lock().pending.waiting()
    }

    /// The configuration.
    pub fn config(&self) -> &CellCacheConfig {
        &self.shared.cfg
    }
}

impl Drop for CellCache {
    fn drop(&mut self) {
        self.shared.lock().stop = true;
        self.shared.work.notify_all();
        for w in self.workers.drain(..) {
            let _ = w.join();
        }
    }
}

impl WorldStore for CellCache {
    fn head(&self) -> &StoreHead {
        &self.head
    }

    fn cell(&self, c: CellCoord, waker: Option<&Arc<dyn CellWaker>>) -> CellState {
        if !self.shared.grid.contains(c) {
            return CellState::Outside;
        }
        let m = &self.shared.metrics;
        let mut st = self.shared.lock();
        if let Some(data) = st.cached.get(&c) {
            let data = Arc::clone(data);
            m.hits.fetch_add(1, Relaxed);
            return CellState::Ready(data);
        }
        if st.pending.wait(c, waker) {
            m.misses.fetch_add(1, Relaxed);
            m.queued.store(st.pending.queued() as u64, Relaxed);
            drop(st);
            self.shared.work.notify_one();
        }
        CellState::Pending
    }

    fn unwait(&self, c: CellCoord, waker: &Arc<dyn CellWaker>) {
        let mut st = self.shared.lock();
        if st.pending.unwait(&c, waker) {
            self.shared.metrics.cancelled.fetch_add(1, Relaxed);
            self.shared.metrics.queued.store(st.pending.queued() as u64, Relaxed);
        }
    }

    // The world function's cells are never edited: every cell in the grid is at version 0, known without
    // expanding it.
    fn version(&self, c: CellCoord, _waker: Option<&Arc<dyn CellWaker>>) -> VersionState {
        if self.shared.grid.contains(c) { VersionState::Unedited } else { VersionState::Outside }
    }

    fn generation(&self) -> u64 {
        self.shared.generation.load(Acquire)
    }

    fn summary(&self, key: NodeKey, waker: Option<&Arc<dyn CellWaker>>) -> SummaryState {
        if !key.is_valid() || key.level > self.shared.root_level || !canopy_session::overlaps(&self.shared.grid, key) {
            return SummaryState::Unavailable;
        }
        // Cached; else held by the memo (computed with an ancestor); else queued.
        if let Some(node) = self.shared.lock().summaries.cached(key) {
            return SummaryState::Ready(node);
        }
        if let Some(node) = self.shared.memoised(key) {
            return SummaryState::Ready(node);
        }
        let (state, queued) = self.shared.lock().summaries.lookup(key, waker);
        if queued {
            self.shared.work.notify_one();
        }
        state
    }

    fn summary_root_level(&self) -> u8 {
        self.shared.root_level
    }

    fn correct_summaries(&self, c: CellCoord, delta: Option<&CellDelta>) -> bool {
        self.shared.grid.contains(c) && self.shared.correct(c, delta)
    }

    fn summary_corrections(&self, since: u64) -> SummaryCorrections {
        let now = self.shared.corrected.load(Acquire);
        if since >= now {
            return SummaryCorrections { now, cells: Some(Vec::new()) };
        }
        self.shared.lock().summaries.corrected_since(since)
    }

    fn cache_metrics(&self) -> Option<Arc<CellMetrics>> {
        Some(Arc::clone(&self.shared.metrics))
    }
}
