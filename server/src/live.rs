//! The live world: a [`WorldStore`] that lays each cell's edits ([`canopy_edits::Overlay`]) over the world
//! function's records of another store, reading a cell's edit log from the [`EditStore`] when the cell is first
//! needed and keeping overlays in an LRU bounded by bytes. Nothing is loaded at start, and a session never waits
//! for a log: a cell whose overlay is not cached is [`CellState::Pending`] while loader threads read it (an edit
//! store may be a network away), and the session's waker is woken when it is.
//!
//! A cell never edited costs one look-up in the edit store and a small entry; an edited cell also keeps its records
//! at the current version ([`CellData`] with its batches encoded once, shared by every session like any cell).
//! [`crate::editing`] publishes an overlay here after its edit is durable, and this tells the sessions
//! ([`EditHub`]); an overlay only ever moves forward (the newer version wins), so a log read racing a publish cannot
//! take a cell back.
//!
//! It also keeps an index of the edited cells and their versions (read from the edit store at start and every
//! [`INDEX_REFRESH`], kept current by every announcement and, for a store other servers write, by the store's
//! stream-wide watch, [`EditStore::watch_all`]), for the far views of clients that expand cells
//! ([`WorldStore::edited_cells`]): another edge's edit of a cell no session here holds reaches it at once (within a
//! refresh where the store cannot watch its whole stream).
//! The same cells correct the base store's far-view summaries for clients that take records ([`correct`]).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Duration;

use canopy_edits::{EditRules, EditStore, EditStoreError, Overlay};
use canopy_protocol::lru::Lru;
use canopy_protocol::sync::{Locked, Waited};
use canopy_protocol::{CellCoord, SpeciesGraph};
use tracing::{error, warn};

use canopy_session::{
    CellData, CellState, CellWaker, Changes, StoreHead, SummaryCorrections, SummaryState, VersionState, Waiters,
    WorldStore,
};

mod correct;

/// A cell changed: it is at `version` now.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CellChange {
    /// The cell.
    pub cell: CellCoord,
    /// Its version.
    pub version: u32,
}

/// Tells every session of a server which cells changed (each keeps those it holds).
#[derive(Debug)]
pub struct EditHub {
    tx: tokio::sync::broadcast::Sender<CellChange>,
}

impl EditHub {
    /// A hub keeping up to `capacity` changes for a slow listener (past it, the listener is told it lagged).
    fn new(capacity: usize) -> EditHub {
        EditHub { tx: tokio::sync::broadcast::channel(capacity.max(16)).0 }
    }

    /// Listen to every change from now on.
    pub fn subscribe(&self) -> tokio::sync::broadcast::Receiver<CellChange> {
        self.tx.subscribe()
    }

    /// Tell every session that a cell changed.
    fn announce(&self, change: CellChange) {
        // Nobody listening is fine.
        let _ = self.tx.send(change);
    }
}

/// Changes a slow listener may fall behind by before it is told it lagged (and reloads what it holds).
const HUB_CAPACITY: usize = 1 << 14;

/// How often the index of edited cells is read again from the edit store (another edge's edits of cells no
/// session here holds reach it so).
pub(crate) const INDEX_REFRESH: Duration = Duration::from_secs(30);

/// Most cells the index of edited cells keeps (about 40 bytes each); past it, cells beyond are not indexed and a
/// far view does not show their edits (their records still do).
const MAX_INDEXED: usize = 1 << 18;

/// Bytes an overlay entry costs beyond the overlay and the records it keeps (map, LRU slot).
const ENTRY_OVERHEAD: usize = 96;

struct Entry {
    overlay: Arc<Overlay>,
    /// The cell's records at the overlay's version (edited cells only), built on first need.
    applied: Option<Arc<CellData>>,
}

/// The cached overlays, bounded by bytes.
#[derive(Default)]
struct Overlays {
    lru: Lru<CellCoord, Entry>,
    /// Cells whose log was read without their records (for clients that expand cells): `false` for an empty log
    /// (watched, so another writer's first edit is announced), `true` for an edited one. Bounded by count
    /// ([`KNOWN_PER_BYTE`]); a cell with an overlay in `lru` is not here.
    known: Lru<CellCoord, bool>,
    /// Cells whose overlays left the cache since the last look (their watches end).
    dropped: Vec<CellCoord>,
}

/// Cells whose edit state is known without an overlay: one per this many bytes of the overlay cache's bound.
const KNOWN_PER_BYTE: usize = 64;

impl Overlays {
    fn get(&self, c: CellCoord) -> Option<&Entry> {
        self.lru.peek(&c)
    }

    fn remove(&mut self, c: CellCoord) {
        if self.lru.remove(&c).is_some() | self.known.remove(&c).is_some() {
            self.dropped.push(c);
        }
    }

    /// Whether cell `c` is edited, if known (touched as used).
    fn edited(&mut self, c: CellCoord) -> Option<bool> {
        match self.lru.get(&c) {
            Some(e) => Some(e.overlay.version() > 0),
            None => self.known.get(&c).copied(),
        }
    }

    /// Remember whether cell `c`'s log holds edits (read without its records), within `limit` bytes' worth.
    fn set_known(&mut self, c: CellCoord, edited: bool, limit: usize) {
        if self.lru.peek(&c).is_some() {
            return;
        }
        self.known.insert(c, edited, 1);
        self.dropped.retain(|d| *d != c);
        let gone = self.known.evict_to((limit / KNOWN_PER_BYTE).max(1), Some(&c));
        self.dropped.extend(gone.into_iter().filter(|(_, edited)| !edited).map(|(c, _)| c));
    }

    /// Put `overlay` for `c` unless a newer one is there; then evict beyond `limit`.
    fn put(&mut self, c: CellCoord, overlay: Arc<Overlay>, limit: usize) -> Arc<Overlay> {
        if let Some(e) = self.lru.get(&c)
            && e.overlay.version() >= overlay.version()
        {
            return Arc::clone(&e.overlay);
        }
        self.lru.remove(&c);
        self.known.remove(&c);
        self.dropped.retain(|d| *d != c);
        let bytes = overlay.heap_bytes() + ENTRY_OVERHEAD;
        self.lru.insert(c, Entry { overlay: Arc::clone(&overlay), applied: None }, bytes);
        self.evict(limit, c);
        overlay
    }

    /// Evict the least recently used entries beyond `limit`, never `keep`.
    fn evict(&mut self, limit: usize, keep: CellCoord) {
        let gone = self.lru.evict_to(limit, Some(&keep));
        self.dropped.extend(gone.into_iter().map(|(c, _)| c));
    }
}

/// Threads reading cells' edit logs.
pub(crate) const LOADERS: usize = 2;

/// A cell whose log is to be read, with its world-function records, or without them only to tell whether it is
/// edited (the same cell is the same load).
#[derive(Clone)]
struct Load {
    cell: CellCoord,
    base: Option<Arc<CellData>>,
}

impl PartialEq for Load {
    fn eq(&self, other: &Load) -> bool {
        self.cell == other.cell
    }
}

impl Eq for Load {}

impl std::hash::Hash for Load {
    fn hash<H: std::hash::Hasher>(&self, h: &mut H) {
        self.cell.hash(h);
    }
}

/// Cells whose logs are queued or being read, and the wakers to wake.
#[derive(Default)]
struct Loads {
    waiters: Waiters<Load>,
    stop: bool,
}

/// How often the same failure to read a cell's log is logged again while it goes on.
const FAILURE_LOG_EVERY: Duration = Duration::from_secs(10);

/// Skipped edits named in the log at most this many times (each once); beyond, only counted.
const SKIPS_REPORTED: usize = 4096;

/// What the store and its loader threads share.
struct Shared {
    edits: Arc<dyn EditStore>,
    overlays: Mutex<Overlays>,
    limit_bytes: usize,
    loads: Mutex<Loads>,
    work: Condvar,
    /// Bumped whenever a load finishes (or fails): [`WorldStore::generation`] adds it to the base's.
    loaded: AtomicU64,
    /// Where every change is announced: this server's edits ([`LiveStore::publish`]) and other writers' (a shared
    /// store's watch, a reload).
    hub: Arc<EditHub>,
    /// What the world as loaded accepts; stored edits it refuses are skipped.
    rules: EditRules,
    /// Stored edits not served (counted at every read of their cell).
    skipped: Arc<AtomicU64>,
    /// Skipped edits already named in the log, `(cell, version)`.
    reported: Mutex<std::collections::BTreeSet<(CellCoord, u32)>>,
    /// Cells whose logs are damaged, with where and why: served as they were before the damage, and taking no
    /// edits until a read finds them whole again.
    damaged: Mutex<std::collections::BTreeMap<CellCoord, String>>,
    /// The last failure to read a log that was logged, and when, and how many since went unlogged.
    failures: Mutex<(String, Option<std::time::Instant>, u64)>,
    /// Edited cells and their versions, at most [`MAX_INDEXED`].
    index: Mutex<std::collections::BTreeMap<CellCoord, u32>>,
    /// Notified when the store stops (the index thread waits on it between reads).
    stopping: Condvar,
    /// Cells whose far-view summaries are to be corrected by their edits ([`correct`]).
    corrector: correct::Corrector,
    /// Whether a session asked for a summary node (corrections start then).
    summaries_wanted: AtomicBool,
}

/// A cell's world-function records and its overlay.
pub(crate) type BaseAndOverlay = (Arc<CellData>, Arc<Overlay>);

/// The live world (see the module docs).
pub struct LiveStore {
    base: Arc<dyn WorldStore>,
    shared: Arc<Shared>,
    loaders: Vec<JoinHandle<()>>,
}

impl Drop for LiveStore {
    fn drop(&mut self) {
        self.shared.loads.locked().stop = true;
        self.shared.corrector.stop();
        self.shared.work.notify_all();
        self.shared.stopping.notify_all();
        for t in self.loaders.drain(..) {
            let _ = t.join();
        }
    }
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Overlays> {
        self.overlays.locked()
    }

    /// Do `f` with the overlays, then stop watching the cells it dropped from the cache (outside the lock).
    fn with<T>(&self, f: impl FnOnce(&mut Overlays) -> T) -> T {
        let (out, dropped) = {
            let mut o = self.lock();
            let out = f(&mut o);
            (out, std::mem::take(&mut o.dropped))
        };
        for c in dropped {
            self.edits.unwatch(c);
        }
        out
    }

    /// Read a cell's log, cache its overlay and watch the cell (`base`: its world-function records). Edits the
    /// world's rules refuse are skipped, counted and named in the log once, with the store.
    fn load(self: &Arc<Self>, c: CellCoord, base: &CellData) -> Result<Arc<Overlay>, EditStoreError> {
        if let Some(e) = self.lock().get(c) {
            return Ok(Arc::clone(&e.overlay));
        }
        let (log, damage) = match self.edits.load(c) {
            Ok(log) => (log, None),
            // A stored edit that does not decode: the cell is served as it was before it.
            Err(e @ EditStoreError::Damaged { .. }) => {
                let why = e.to_string();
                let EditStoreError::Damaged { version, readable, .. } = e else { unreachable!() };
                (readable, Some((version, why)))
            }
            Err(e) => return Err(e),
        };
        let species = |i: u16| base.records.get(usize::from(i)).map(|r| r.species);
        let (overlay, skipped) = Overlay::from_log_checked(base.records.len() as u16, species, &self.rules, &log)
            .map_err(|e| EditStoreError::Corrupt(format!("{}: cell {c:?}: {e}", self.edits.describe())))?;
        self.report(c, &skipped);
        match damage {
            Some((version, why)) => {
                self.skipped.fetch_add(1, Relaxed);
                if self.first_report(c, version) {
                    error!("{why}: the cell is served as it was at version {}, and takes no edits", version - 1);
                }
                self.damaged.locked().insert(c, why);
            }
            None => {
                self.damaged.locked().remove(&c);
            }
        }
        let kept = self.with(|o| o.put(c, Arc::new(overlay), self.limit_bytes));
        // Weakly: the store the watch lives in belongs to this, and must not keep it alive.
        self.edits.watch(c, Arc::new(Watcher(Arc::downgrade(self))));
        // What was read may be newer than what sessions hold (another writer's edit, or one whose append was
        // answered by a failure but kept): they are told, and those holding the cell catch up.
        if kept.version() > 0 {
            self.announce(c, kept.version());
        }
        Ok(kept)
    }

    /// Log a failed read of a cell's log: a new failure at once, the same one again at most every
    /// [`FAILURE_LOG_EVERY`] with how many went unlogged.
    fn failed(&self, c: CellCoord, e: &EditStoreError) {
        let now = std::time::Instant::now();
        let text = e.to_string();
        let mut f = self.failures.locked();
        let due = f.0 != text || f.1.is_none_or(|at| now.duration_since(at) >= FAILURE_LOG_EVERY);
        if due {
            let more = std::mem::take(&mut f.2);
            *f = (text, Some(now), 0);
            drop(f);
            error!(store = %self.edits.describe(), cell = ?c, "reading the cell's edits: {e} ({more} similar failures since the last report)");
        } else {
            f.2 += 1;
        }
    }

    /// Whether the stored edit `(c, version)` is named in the log now: the first time, for the first
    /// [`SKIPS_REPORTED`] such edits.
    fn first_report(&self, c: CellCoord, version: u32) -> bool {
        let mut r = self.reported.locked();
        r.len() < SKIPS_REPORTED && r.insert((c, version))
    }

    /// Count skipped edits and name each in the log once.
    fn report(&self, c: CellCoord, skipped: &[(u32, String)]) {
        self.skipped.fetch_add(skipped.len() as u64, Relaxed);
        for (version, why) in skipped {
            if self.first_report(c, *version) {
                warn!(store = %self.edits.describe(), cell = ?c, version, "a stored edit the world cannot take is skipped: {why}");
            }
        }
    }

    fn announce(&self, cell: CellCoord, version: u32) {
        self.index_version(cell, version);
        self.hub.announce(CellChange { cell, version });
    }

    /// Put a cell's version in the index of edited cells (a version only moves forward); whether it moved. A cell
    /// whose version moved is queued for correcting the summaries ([`correct`]): every way an edit is heard of
    /// passes here.
    fn index_version(&self, cell: CellCoord, version: u32) -> bool {
        let moved = {
            let mut index = self.index.locked();
            let full = index.len() >= MAX_INDEXED;
            match index.get_mut(&cell) {
                Some(v) if *v >= version => false,
                Some(v) => {
                    *v = version;
                    true
                }
                None if version > 0 && !full => {
                    index.insert(cell, version);
                    true
                }
                None => false,
            }
        };
        if moved {
            self.queue_correction(cell, version);
        }
        moved
    }

    /// The index thread: read every edited cell's version from the edit store at start and every
    /// [`INDEX_REFRESH`]; a version that moved is announced (the sessions whose far views hold the cell look again).
    fn run_index(self: &Arc<Self>) {
        let mut first = true;
        loop {
            match self.edits.cells() {
                Ok(cells) => {
                    for (cell, version) in cells {
                        if self.index_version(cell, version) && !first {
                            self.hub.announce(CellChange { cell, version });
                        }
                    }
                    first = false;
                }
                Err(e) => warn!(store = %self.edits.describe(), "listing the edited cells failed: {e}"),
            }
            let deadline = std::time::Instant::now() + INDEX_REFRESH;
            let mut loads = self.loads.locked();
            loop {
                if loads.stop {
                    return;
                }
                let now = std::time::Instant::now();
                if now >= deadline {
                    break;
                }
                loads = self.stopping.waited_for(loads, deadline - now).0;
            }
        }
    }

    /// A loader thread: read queued cells' logs, wake who waits for them.
    fn run_loader(self: &Arc<Self>) {
        loop {
            let load = {
                let mut l = self.loads.locked();
                loop {
                    if l.stop {
                        return;
                    }
                    if let Some(next) = l.waiters.take() {
                        break next;
                    }
                    l = self.work.waited(l);
                }
            };
            let read = match &load.base {
                Some(base) => self.load(load.cell, base).map(drop),
                None => self.probe(load.cell),
            };
            if let Err(e) = read {
                // Asked again, it is read again; not at once, so a store that is down is not hammered.
                self.failed(load.cell, &e);
                std::thread::sleep(Duration::from_millis(100));
            }
            let wakers = self.loads.locked().waiters.done(&load);
            self.loaded.fetch_add(1, Relaxed);
            for w in wakers {
                w.wake();
            }
        }
    }

    /// Read cell `c`'s log only to tell whether it is edited (for clients that expand cells: its records are not
    /// needed, nor expanded, unless it is). An empty log is watched, so another writer's first edit is announced.
    fn probe(self: &Arc<Self>, c: CellCoord) -> Result<(), EditStoreError> {
        if self.lock().edited(c).is_some() {
            return Ok(());
        }
        let edited = match self.edits.load(c) {
            Ok(log) => !log.is_empty(),
            // The read with its records skips and reports the damage.
            Err(EditStoreError::Damaged { .. }) => true,
            Err(e) => return Err(e),
        };
        self.with(|o| o.set_known(c, edited, self.limit_bytes));
        if !edited {
            self.edits.watch(c, Arc::new(Watcher(Arc::downgrade(self))));
        }
        Ok(())
    }

    /// Queue cell `c`'s log (once however many ask) and have `waker` woken when it is read; without `base`, only
    /// to tell whether it is edited ([`Shared::probe`]).
    fn queue(&self, c: CellCoord, base: Option<&Arc<CellData>>, waker: Option<&Arc<dyn CellWaker>>) {
        let mut l = self.loads.locked();
        if l.waiters.wait(Load { cell: c, base: base.cloned() }, waker) {
            drop(l);
            self.work.notify_one();
        }
    }
}

impl std::fmt::Debug for LiveStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveStore").field("limit_bytes", &self.shared.limit_bytes).finish()
    }
}

impl LiveStore {
    /// The world of `base` with the edits of `edits`, overlays cached up to `limit_bytes`, logs read by
    /// [`LOADERS`] threads.
    pub fn new(base: Arc<dyn WorldStore>, edits: Arc<dyn EditStore>, limit_bytes: usize) -> LiveStore {
        let head = base.head();
        let graphs: Vec<SpeciesGraph> = (0..head.species().len())
            .map(|i| {
                let bytes = head.species_graph(i as u8).expect("every species of the table has a graph");
                SpeciesGraph::decode(bytes).expect("a head's graphs decode: it encoded them from validated graphs")
            })
            .collect();
        let shared = Arc::new(Shared {
            edits,
            overlays: Mutex::new(Overlays::default()),
            limit_bytes,
            loads: Mutex::new(Loads::default()),
            work: Condvar::new(),
            loaded: AtomicU64::new(0),
            hub: Arc::new(EditHub::new(HUB_CAPACITY)),
            rules: EditRules::of_species(&graphs),
            skipped: Arc::default(),
            reported: Mutex::default(),
            damaged: Mutex::default(),
            failures: Mutex::new((String::new(), None, 0)),
            index: Mutex::default(),
            stopping: Condvar::new(),
            corrector: correct::Corrector::default(),
            summaries_wanted: AtomicBool::new(false),
        });
        let mut loaders: Vec<JoinHandle<()>> = (0..LOADERS)
            .map(|i| {
                let shared = Arc::clone(&shared);
                std::thread::Builder::new()
                    .name(format!("canopy-overlay-{i}"))
                    .spawn(move || shared.run_loader())
                    .expect("spawning an overlay loader")
            })
            .collect();
        shared.edits.watch_all(Arc::new(IndexWatcher(Arc::downgrade(&shared))));
        let indexer = Arc::clone(&shared);
        let index = std::thread::Builder::new().name("canopy-edit-index".into()).spawn(move || indexer.run_index());
        loaders.push(index.expect("spawning the edited cells' indexer"));
        let (corrector, of) = (Arc::clone(&shared), Arc::clone(&base));
        let correct =
            std::thread::Builder::new().name("canopy-far-correct".into()).spawn(move || corrector.run_corrector(&of));
        loaders.push(correct.expect("spawning the far view's corrector"));
        LiveStore { base, shared, loaders }
    }

    fn lock(&self) -> MutexGuard<'_, Overlays> {
        self.shared.lock()
    }

    /// The store of the world function's records.
    pub fn base(&self) -> &Arc<dyn WorldStore> {
        &self.base
    }

    /// The durable edit store.
    pub fn edit_store(&self) -> &Arc<dyn EditStore> {
        &self.shared.edits
    }

    /// What the world as loaded accepts in an edit (the writer checks requests with it, and stored edits are
    /// checked with it when read).
    pub fn rules(&self) -> &EditRules {
        &self.shared.rules
    }

    /// Stored edits not served: the world cannot take them, or a cell's log is damaged from them on (counted at
    /// every read of their cell).
    pub fn skipped(&self) -> &Arc<AtomicU64> {
        &self.shared.skipped
    }

    /// Why cell `c`'s stored log is damaged, if it is (as its last read found it): the cell is served as it was
    /// before the damage and takes no edits.
    pub fn damaged(&self, c: CellCoord) -> Option<String> {
        self.shared.damaged.locked().get(&c).cloned()
    }

    /// Bytes the overlays hold now.
    pub fn overlay_bytes(&self) -> usize {
        self.lock().lru.cost()
    }

    /// The overlay of cell `c`, whose world-function records are `base`: cached, or read from the edit store now
    /// (blocking: the edit writer's path; sessions go through [`WorldStore::cell`], which never waits).
    pub fn overlay(&self, c: CellCoord, base: &CellData) -> Result<Arc<Overlay>, EditStoreError> {
        self.shared.load(c, base)
    }

    /// The overlay of cell `c` if it is cached (touched as used); else its log is queued for the loaders and
    /// `waker` woken when it is read.
    fn cached_or_queue(
        &self,
        c: CellCoord,
        base: &Arc<CellData>,
        waker: Option<&Arc<dyn CellWaker>>,
    ) -> Option<Arc<Overlay>> {
        {
            let mut o = self.lock();
            if let Some(e) = o.lru.get(&c) {
                return Some(Arc::clone(&e.overlay));
            }
        }
        self.shared.queue(c, Some(base), waker);
        None
    }

    /// Make `overlay` cell `c`'s (after its edits are durable) and announce the cell's version to the sessions. A
    /// newer overlay already there is kept.
    pub fn publish(&self, c: CellCoord, overlay: Overlay) {
        let limit = self.shared.limit_bytes;
        let version = overlay.version();
        self.shared.with(|o| o.put(c, Arc::new(overlay), limit));
        self.shared.announce(c, version);
    }

    /// Where every change of a cell is announced: each session subscribes and keeps those it holds.
    pub fn hub(&self) -> &Arc<EditHub> {
        &self.shared.hub
    }

    /// Cell `c`'s overlay as this server holds it now, if it holds one (never reads the store).
    pub fn cached(&self, c: CellCoord) -> Option<Arc<Overlay>> {
        self.shared.with(|o| o.lru.peek(&c).map(|e| Arc::clone(&e.overlay)))
    }

    /// Read cell `c`'s log again (after another writer changed it, or a write failed), cache and watch it; what
    /// was read (an edited cell's version) is announced to the sessions, as every read of a log is.
    pub fn reload(&self, c: CellCoord, base: &CellData) -> Result<Arc<Overlay>, EditStoreError> {
        self.forget(c);
        self.shared.load(c, base)
    }

    /// Forget cell `c`'s overlay (another writer changed the cell: read its log again on next need).
    pub fn forget(&self, c: CellCoord) {
        self.shared.with(|o| o.remove(c));
    }

    /// The cell's records at `overlay`'s version over `base`, built once per version and kept with the overlay.
    fn applied(&self, c: CellCoord, base: &Arc<CellData>, overlay: &Arc<Overlay>) -> Arc<CellData> {
        if overlay.version() == 0 {
            return Arc::clone(base);
        }
        if let Some(e) = self.lock().get(c)
            && Arc::ptr_eq(&e.overlay, overlay)
            && let Some(a) = &e.applied
        {
            return Arc::clone(a);
        }
        let a = overlay.apply_to(&base.records, &base.overrides);
        let data = Arc::new(CellData::edited(c, overlay.version(), a.records, a.overrides, a.felled));
        let limit = self.shared.limit_bytes;
        self.shared.with(|o| {
            if let Some(e) = o.lru.get(&c)
                && Arc::ptr_eq(&e.overlay, overlay)
                && e.applied.is_none()
            {
                e.applied = Some(Arc::clone(&data));
                let bytes = overlay.heap_bytes() + ENTRY_OVERHEAD + data.heap_bytes();
                o.lru.set_cost(&c, bytes);
                o.evict(limit, c);
            }
        });
        data
    }

    /// The cell's world-function records and overlay, never waiting (`Ok(None)`: pending or outside the grid).
    pub fn base_and_overlay(
        &self,
        c: CellCoord,
        waker: Option<&Arc<dyn CellWaker>>,
    ) -> Result<Option<BaseAndOverlay>, EditStoreError> {
        match self.base.cell(c, waker) {
            CellState::Ready(base) => {
                let overlay = self.overlay(c, &base)?;
                Ok(Some((base, overlay)))
            }
            _ => Ok(None),
        }
    }
}

/// The watcher a shared store tells of a cell's edits: the live store, if it still exists.
struct Watcher(std::sync::Weak<Shared>);

impl canopy_edits::EditWatcher for Watcher {
    fn edited(&self, e: canopy_edits::StoredEdit) {
        if let Some(shared) = self.0.upgrade() {
            canopy_edits::EditWatcher::edited(&*shared, e);
        }
    }
}

/// The index's watcher of a shared store's whole stream ([`EditStore::watch_all`]): every edit any writer stored
/// moves its cell's version in the index of edited cells (only the version: a lost race's edits come too), and a
/// cell whose version moved is announced (the far views within range look again) and queued for correcting.
struct IndexWatcher(std::sync::Weak<Shared>);

impl canopy_edits::EditWatcher for IndexWatcher {
    fn edited(&self, e: canopy_edits::StoredEdit) {
        if let Some(shared) = self.0.upgrade()
            && shared.index_version(e.cell, e.version)
        {
            shared.hub.announce(CellChange { cell: e.cell, version: e.version });
        }
    }
}

/// Edits other writers of a shared store made (and this server's own, coming back): a cached overlay one version
/// behind takes the edit, one further behind is dropped (read again on next need); sessions are told either way.
impl canopy_edits::EditWatcher for Shared {
    fn edited(&self, e: canopy_edits::StoredEdit) {
        let cell = e.cell;
        let version = e.version;
        let limit = self.limit_bytes;
        let changed = self.with(|o| {
            // A cell known to be unedited (a client expands it) is edited now: its overlay is read on next need.
            if o.known.peek(&cell) == Some(&false) {
                o.known.insert(cell, true, 1);
                return true;
            }
            let Some(entry) = o.get(cell) else { return false };
            let current = entry.overlay.version();
            if version <= current {
                return false;
            }
            let mut next = (*entry.overlay).clone();
            // An edit the world cannot take is left to the read of the whole log, which skips and reports it.
            let species =
                |i: u16| entry.applied.as_ref().and_then(|a| a.records.get(usize::from(i))).map(|r| r.species);
            let refused = next.refusal(&e, species, &self.rules).is_some();
            if version == current + 1 && !refused && next.apply(&e).is_ok() {
                o.put(cell, Arc::new(next), limit);
            } else {
                o.remove(cell);
            }
            true
        });
        if changed {
            self.announce(cell, version);
        }
    }
}

impl WorldStore for LiveStore {
    fn head(&self) -> &StoreHead {
        self.base.head()
    }

    fn cell(&self, c: CellCoord, waker: Option<&Arc<dyn CellWaker>>) -> CellState {
        match self.base.cell(c, waker) {
            CellState::Ready(base) => match self.cached_or_queue(c, &base, waker) {
                Some(overlay) => CellState::Ready(self.applied(c, &base, &overlay)),
                None => CellState::Pending,
            },
            other => other,
        }
    }

    fn generation(&self) -> u64 {
        self.base.generation().wrapping_add(self.shared.loaded.load(Relaxed))
    }

    fn unwait(&self, c: CellCoord, waker: &Arc<dyn CellWaker>) {
        self.base.unwait(c, waker);
    }

    // Whether a cell is edited takes a read of its log, not its records: a cell nobody edited is never expanded
    // for a client that expands it.
    fn version(&self, c: CellCoord, waker: Option<&Arc<dyn CellWaker>>) -> VersionState {
        if self.base.version(c, None) == VersionState::Outside {
            return VersionState::Outside;
        }
        match self.lock().edited(c) {
            Some(false) => return VersionState::Unedited,
            Some(true) => return VersionState::Edited,
            None => {}
        }
        self.shared.queue(c, None, waker);
        VersionState::Pending
    }

    fn cache_metrics(&self) -> Option<Arc<canopy_session::counters::CellMetrics>> {
        self.base.cache_metrics()
    }

    // The base store's summaries, corrected by the edits from the first ask on (`correct`).
    fn summary(&self, key: canopy_protocol::summary::NodeKey, waker: Option<&Arc<dyn CellWaker>>) -> SummaryState {
        self.shared.want_summaries();
        self.base.summary(key, waker)
    }

    fn correct_summaries(&self, c: CellCoord, delta: Option<&canopy_protocol::edit::CellDelta>) -> bool {
        self.base.correct_summaries(c, delta)
    }

    fn summary_corrections(&self, since: u64) -> SummaryCorrections {
        self.base.summary_corrections(since)
    }

    fn summary_root_level(&self) -> u8 {
        self.base.summary_root_level()
    }

    fn edited_cells(&self, lo: CellCoord, hi: CellCoord, max: usize) -> Vec<(CellCoord, u32)> {
        canopy_session::cells_in(&self.shared.index.locked(), lo, hi, max)
    }

    fn changes(&self, c: CellCoord, from: u32, waker: Option<&Arc<dyn CellWaker>>) -> Changes {
        let base = match self.base.cell(c, waker) {
            CellState::Ready(base) => base,
            CellState::Pending => return Changes::Pending,
            CellState::Outside => return Changes::Whole,
        };
        match self.cached_or_queue(c, &base, waker) {
            Some(overlay) if from == overlay.version() => Changes::Current { total: overlay.total() },
            Some(overlay) => overlay.delta(from).map_or(Changes::Whole, Changes::Delta),
            None => Changes::Pending,
        }
    }
}
