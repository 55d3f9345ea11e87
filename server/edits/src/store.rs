//! The durable edit store's trait, its errors, and the in-memory store tests use.

use std::collections::BTreeMap;
use std::sync::Mutex;

use canopy_protocol::CellCoord;
use canopy_protocol::sync::Locked;

use crate::log::StoredEdit;

/// Why a store could not do what it was asked.
#[derive(Clone, Debug, thiserror::Error)]
pub enum EditStoreError {
    /// A `(cell, version)` of the group is already stored (another writer got there first): nothing of the group
    /// was stored.
    #[error("cell {cell:?} already has version {version}")]
    Conflict {
        /// The cell.
        cell: CellCoord,
        /// The version already taken.
        version: u32,
    },
    /// A stored edit does not decode or the log of a cell has a gap: the store is damaged.
    #[error("edit store damaged: {0}")]
    Corrupt(String),
    /// A cell's log is readable up to `version`, whose stored edit does not decode: `readable` holds the edits
    /// before it (versions 1..`version`), so the cell can be served as it was before the damage.
    #[error("{store}: cell {cell:?} version {version} is damaged: {why}")]
    Damaged {
        /// The store (a file's path, an engine's stream).
        store: String,
        /// The cell.
        cell: CellCoord,
        /// The first version that cannot be read.
        version: u32,
        /// Why it cannot.
        why: String,
        /// The edits before it.
        readable: Vec<StoredEdit>,
    },
    /// The store's file or database failed (disk full, permissions, not a regular file…): for an append, nothing
    /// of the group that failed was stored by it (a read of the cells says what was).
    #[error("edit store: {0}")]
    Io(String),
    /// The store did not answer (a network store electing a leader, a lost connection): an append's edits may yet be
    /// stored or not. A writer reads the cells again later and does not answer by a guess.
    #[error("edit store: no answer: {0}")]
    Unanswered(String),
}

/// Where edits are kept durably. Implementations are shared between threads; every call may block (on a disk or a
/// network), so an async caller runs them off its reactor.
pub trait EditStore: Send + Sync + 'static {
    /// Store a group of edits and return only once they are durable (they survive a crash of the process, or of
    /// the machine where the store syncs to disk). A `(cell, version)` that is already stored is refused with
    /// [`EditStoreError::Conflict`]. A group may hold several consecutive versions of one cell. A transactional
    /// store (SQLite) stores all or none; after an error a caller must not assume none was stored, but read the
    /// cells again (a store without multi-key transactions, or a commit that failed after its data reached the
    /// disk, may have kept a prefix of a cell's versions).
    fn append(&self, edits: &[StoredEdit]) -> Result<(), EditStoreError>;
    /// A cell's edits in version order (empty for a cell never edited).
    fn load(&self, cell: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError>;
    /// Store a group as [`EditStore::append`] does, and say for each of its cells (in cell order) whether that
    /// cell's edits were stored: a store without multi-key transactions stores cells on their own, and a writer
    /// then acknowledges the cells stored without reading them again. By default every cell gets `append`'s answer.
    fn append_cells(&self, edits: &[StoredEdit]) -> Vec<(CellCoord, Result<(), EditStoreError>)> {
        let result = self.append(edits);
        let cells: std::collections::BTreeSet<CellCoord> = edits.iter().map(|e| e.cell).collect();
        cells.into_iter().map(|c| (c, result.clone())).collect()
    }
    /// Every edited cell and its latest version, in cell order.
    fn cells(&self) -> Result<Vec<(CellCoord, u32)>, EditStoreError>;
    /// How many edits are stored.
    fn count(&self) -> Result<u64, EditStoreError>;
    /// Tell `watcher` of every edit stored for `cell` after the last [`EditStore::load`] of it, by any writer (a
    /// store several servers share; call it after the load, nothing between the two is missed). A store only one
    /// server writes has nothing to tell.
    fn watch(&self, _cell: CellCoord, _watcher: std::sync::Arc<dyn EditWatcher>) {}
    /// Stop telling of `cell`'s edits.
    fn unwatch(&self, _cell: CellCoord) {}
    /// Tell `watcher` of every edit any writer stores from now on, in every cell (a store several servers share: a
    /// server learns at once which cells another one edited, those it does not watch included). What is told is
    /// what was published, a lost race's edits too: only a cell's versions, not its log, may be taken from it. A
    /// store only one server writes has nothing to tell.
    fn watch_all(&self, _watcher: std::sync::Arc<dyn EditWatcher>) {}
    /// Where the edits are, for logs: a file's path, an engine's stream and servers.
    fn describe(&self) -> String;
}

/// Told of edits stored by any writer of a shared store ([`EditStore::watch`]): its own included, and perhaps
/// again or out of order after a reconnection, so it checks the version.
pub trait EditWatcher: Send + Sync + 'static {
    /// `edit` was stored.
    fn edited(&self, edit: StoredEdit);
}

/// An edit store in memory (tests, and a server that keeps no edits across restarts).
#[derive(Debug, Default)]
pub struct MemoryEditStore {
    log: Mutex<BTreeMap<(CellCoord, u32), StoredEdit>>,
}

impl MemoryEditStore {
    /// An empty store.
    pub fn new() -> MemoryEditStore {
        MemoryEditStore::default()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<(CellCoord, u32), StoredEdit>> {
        self.log.locked()
    }
}

impl EditStore for MemoryEditStore {
    fn append(&self, edits: &[StoredEdit]) -> Result<(), EditStoreError> {
        let mut log = self.lock();
        let mut seen = std::collections::BTreeSet::new();
        for e in edits {
            if log.contains_key(&(e.cell, e.version)) || !seen.insert((e.cell, e.version)) {
                return Err(EditStoreError::Conflict { cell: e.cell, version: e.version });
            }
        }
        for e in edits {
            log.insert((e.cell, e.version), e.clone());
        }
        Ok(())
    }

    fn load(&self, cell: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError> {
        Ok(self.lock().range((cell, 0)..=(cell, u32::MAX)).map(|(_, e)| e.clone()).collect())
    }

    fn cells(&self) -> Result<Vec<(CellCoord, u32)>, EditStoreError> {
        let mut out: Vec<(CellCoord, u32)> = Vec::new();
        for &(cell, version) in self.lock().keys() {
            match out.last_mut() {
                Some(last) if last.0 == cell => last.1 = last.1.max(version),
                _ => out.push((cell, version)),
            }
        }
        Ok(out)
    }

    fn count(&self) -> Result<u64, EditStoreError> {
        Ok(self.lock().len() as u64)
    }

    fn describe(&self) -> String {
        "the in-memory edit store".into()
    }
}
