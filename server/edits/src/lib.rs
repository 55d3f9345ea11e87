//! Canopy's live world edits (issue 16): a cell's **edit log**, its **overlay** on the world function's records,
//! and the durable **edit stores** behind one trait.
//!
//! A cell's records are the world function's (version 0) followed by what editors did to it, one edit per version:
//! instances planted at the cell's next index, instances felled (their index stays taken), parameters set. The log
//! is the truth; [`Overlay`] folds it into what a server sends (and composes deltas between versions), and an
//! [`EditStore`] keeps it durable: [`SqliteEditStore`] embedded (the default, one file in the server's data
//! directory), [`MemoryEditStore`] for tests. A store appends a group of edits in one transaction and returns only
//! once it is durable, so a server acknowledges an edit only after that; it refuses a `(cell, version)` it already
//! holds, which is what keeps two writers from applying one version twice.
//!
//! [`suite::check`] is the store contract as one test: every store (these two, and the edges' JetStream store in
//! `canopy-server`) passes the same suite.
//!
//! Contract: no networking and no clock; the SQLite store is the only code here that touches a file.

mod log;
mod overlay;
mod rules;
pub mod sqlite;
mod store;
pub mod suite;

pub use log::{CellEdit, LogError, MAX_RUN, StoredEdit, decode_run, encode_run};
pub use overlay::{Overlay, OverlayError, merge_params};
pub use rules::{EditRules, MAX_PARAM_VALUE};
pub use sqlite::SqliteEditStore;
pub use store::{EditStore, EditStoreError, EditWatcher, MemoryEditStore};
