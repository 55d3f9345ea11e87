//! The embedded edit store: one SQLite file, `edits.sqlite`, in the server's data directory.
//!
//! The file is opened in WAL mode with `synchronous = FULL`, so an [`EditStore::append`] that returns has been
//! fsynced to the write-ahead log and survives a crash of the process or of the machine. Two connections share it:
//! the *writer* (appends, one `BEGIN IMMEDIATE` transaction per group) and the *reader* (loads, the cell list, the
//! count), each behind its own mutex, so a load never waits behind an append's fsync (WAL lets a reader see the last
//! committed state while the writer writes).
//!
//! Schema (version [`SCHEMA_VERSION`]): `edits(cx, cz, version, op)` keyed by `(cx, cz, version)` without a rowid,
//! so a cell's edits are adjacent in the file and its load is one index range; `op` is [`CellEdit::encode`]'s bytes.
//! A `meta` table holds the schema version; a file with another version is refused rather than guessed at.

use std::fs;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};
use std::time::Duration;

use canopy_protocol::CellCoord;
use canopy_protocol::sync::Locked;
use rusqlite::{Connection, ErrorCode, OpenFlags, TransactionBehavior, ffi, params};

use crate::log::{CellEdit, StoredEdit};
use crate::store::{EditStore, EditStoreError};

/// The store's file name inside its directory.
pub const FILE_NAME: &str = "edits.sqlite";

/// The schema version this build writes and reads.
pub const SCHEMA_VERSION: i64 = 1;

/// How long a connection waits for a lock another connection (or process) holds before failing.
const BUSY_TIMEOUT: Duration = Duration::from_secs(5);

/// The WAL is truncated back to this size after a checkpoint (a large group commit may have grown it).
const JOURNAL_SIZE_LIMIT: i64 = 64 * 1024 * 1024;

const INSERT: &str = "INSERT INTO edits (cx, cz, version, op) VALUES (?1, ?2, ?3, ?4)";
const LOAD: &str = "SELECT version, op FROM edits WHERE cx = ?1 AND cz = ?2 ORDER BY version";
const CELLS: &str = "SELECT cx, cz, MAX(version) FROM edits GROUP BY cx, cz ORDER BY cx, cz";
const COUNT: &str = "SELECT COUNT(*) FROM edits";

/// The durable edit store in one SQLite file (see the module documentation).
#[derive(Debug)]
pub struct SqliteEditStore {
    path: PathBuf,
    writer: Mutex<Connection>,
    reader: Mutex<Connection>,
}

impl SqliteEditStore {
    /// Open the store in `dir` (created if missing), creating `dir/edits.sqlite` if it does not exist. Refuses a
    /// `dir/edits.sqlite` (or its `-wal`/`-shm` companion) that is not a regular file (a symbolic link, a FIFO, a
    /// device, a directory), a file that is not SQLite, and a store of an unknown schema version.
    pub fn open(dir: &Path) -> Result<SqliteEditStore, EditStoreError> {
        create_dir(dir)?;
        let path = dir.join(FILE_NAME);
        for companion in [path.clone(), suffixed(&path, "-wal"), suffixed(&path, "-shm")] {
            check_regular(&companion)?;
        }

        let mut writer = open_connection(&path, OpenFlags::SQLITE_OPEN_CREATE)?;
        let mode: String = writer
            .pragma_update_and_check(None, "journal_mode", "WAL", |row| row.get(0))
            .map_err(sql_err(&path, "set journal_mode = WAL"))?;
        if !mode.eq_ignore_ascii_case("wal") {
            return Err(EditStoreError::Io(format!(
                "{}: the file system does not allow WAL mode (journal_mode is {mode})",
                path.display()
            )));
        }
        writer
            .pragma_update(None, "journal_size_limit", JOURNAL_SIZE_LIMIT)
            .map_err(sql_err(&path, "set journal_size_limit"))?;
        init_schema(&mut writer, &path)?;

        let reader = open_connection(&path, OpenFlags::empty())?;
        reader.pragma_update(None, "query_only", true).map_err(sql_err(&path, "set query_only"))?;

        Ok(SqliteEditStore { path, writer: Mutex::new(writer), reader: Mutex::new(reader) })
    }

    /// The store's file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn writer(&self) -> MutexGuard<'_, Connection> {
        // A panic while the lock was held dropped its transaction, which rolled back: the connection is usable.
        self.writer.locked()
    }

    fn reader(&self) -> MutexGuard<'_, Connection> {
        self.reader.locked()
    }
}

impl EditStore for SqliteEditStore {
    fn append(&self, edits: &[StoredEdit]) -> Result<(), EditStoreError> {
        if edits.is_empty() {
            return Ok(());
        }
        let path = &self.path;
        let mut conn = self.writer();
        // Dropping `tx` before its commit succeeded rolls the whole group back.
        let tx = conn.transaction_with_behavior(TransactionBehavior::Immediate).map_err(sql_err(path, "begin"))?;
        {
            let mut insert = tx.prepare_cached(INSERT).map_err(sql_err(path, "prepare insert"))?;
            for e in edits {
                match insert.execute(params![e.cell.x, e.cell.z, e.version, e.op.encode()]) {
                    Ok(_) => {}
                    Err(err) if is_primary_key_violation(&err) => {
                        return Err(EditStoreError::Conflict { cell: e.cell, version: e.version });
                    }
                    Err(err) => {
                        return Err(sql_err(path, &format!("insert cell {:?} version {}", e.cell, e.version))(err));
                    }
                }
            }
        }
        tx.commit().map_err(sql_err(path, "commit"))
    }

    fn load(&self, cell: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError> {
        let path = &self.path;
        let conn = self.reader();
        let mut stmt = conn.prepare_cached(LOAD).map_err(sql_err(path, "prepare load"))?;
        let mut rows = stmt.query(params![cell.x, cell.z]).map_err(sql_err(path, "load"))?;
        let mut out = Vec::new();
        while let Some(row) = rows.next().map_err(sql_err(path, "load"))? {
            let version =
                row.get_ref(0).map_err(sql_err(path, "load"))?.as_i64().ok().and_then(|v| u32::try_from(v).ok());
            let Some(version) = version else {
                return Err(EditStoreError::Corrupt(format!("cell {cell:?}: a version is not a u32")));
            };
            let op = match row.get_ref(1).map_err(sql_err(path, "load"))?.as_blob() {
                Ok(bytes) => CellEdit::decode(bytes).map_err(|e| e.to_string()),
                Err(_) => Err("the op is not a blob".to_string()),
            };
            match op {
                Ok(op) => out.push(StoredEdit { cell, version, op }),
                Err(why) => {
                    let store = path.display().to_string();
                    return Err(EditStoreError::Damaged { store, cell, version, why, readable: out });
                }
            }
        }
        Ok(out)
    }

    fn cells(&self) -> Result<Vec<(CellCoord, u32)>, EditStoreError> {
        let path = &self.path;
        let conn = self.reader();
        let mut stmt = conn.prepare_cached(CELLS).map_err(sql_err(path, "prepare cells"))?;
        let mut rows = stmt.query([]).map_err(sql_err(path, "cells"))?;
        let mut out = Vec::new();
        while let Some(row) = rows.next().map_err(sql_err(path, "cells"))? {
            let cell = (row.get::<_, i32>(0), row.get::<_, i32>(1), row.get::<_, u32>(2));
            match cell {
                (Ok(x), Ok(z), Ok(version)) => out.push((CellCoord::new(x, z), version)),
                _ => return Err(EditStoreError::Corrupt("a cell coordinate or version is out of range".into())),
            }
        }
        Ok(out)
    }

    fn count(&self) -> Result<u64, EditStoreError> {
        let path = &self.path;
        // rusqlite reads a u64 only with its `fallible_uint` feature: read an i64.
        let n: i64 = self.reader().query_row(COUNT, [], |row| row.get(0)).map_err(sql_err(path, "count"))?;
        u64::try_from(n).map_err(|_| EditStoreError::Corrupt(format!("count {n}")))
    }

    fn describe(&self) -> String {
        self.path.display().to_string()
    }
}

/// Create `dir` if it is missing, and make its entry durable in its parent.
fn create_dir(dir: &Path) -> Result<(), EditStoreError> {
    if dir.is_dir() {
        return Ok(());
    }
    if dir.exists() {
        return Err(EditStoreError::Io(format!("{}: not a directory (it would keep {FILE_NAME})", dir.display())));
    }
    fs::create_dir_all(dir).map_err(|e| EditStoreError::Io(format!("create {}: {e}", dir.display())))?;
    if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
        fs::File::open(parent)
            .and_then(|d| d.sync_all())
            .map_err(|e| EditStoreError::Io(format!("sync {}: {e}", parent.display())))?;
    }
    Ok(())
}

/// `path` with `suffix` appended to its file name (SQLite's `-wal` and `-shm` companions).
fn suffixed(path: &Path, suffix: &str) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(suffix);
    PathBuf::from(name)
}

/// Refuse `path` if it exists and is not a regular file (checked without following a link, before SQLite opens it:
/// opening a FIFO would block, a link could point anywhere).
fn check_regular(path: &Path) -> Result<(), EditStoreError> {
    match fs::symlink_metadata(path) {
        Ok(meta) if meta.file_type().is_file() => Ok(()),
        Ok(_) => Err(EditStoreError::Io(format!("{}: not a regular file", path.display()))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(EditStoreError::Io(format!("{}: {e}", path.display()))),
    }
}

/// Open a read-write connection to `path` (`extra`: `SQLITE_OPEN_CREATE` for the writer) that refuses a symbolic
/// link, with the busy timeout and `synchronous = FULL` (the writer's commits are fsynced before they return; the
/// reader may run the last checkpoint when it closes).
fn open_connection(path: &Path, extra: OpenFlags) -> Result<Connection, EditStoreError> {
    let flags = OpenFlags::SQLITE_OPEN_READ_WRITE
        | OpenFlags::SQLITE_OPEN_NO_MUTEX
        | OpenFlags::SQLITE_OPEN_NOFOLLOW
        | OpenFlags::SQLITE_OPEN_EXRESCODE
        | extra;
    let conn = Connection::open_with_flags(path, flags).map_err(sql_err(path, "open"))?;
    conn.busy_timeout(BUSY_TIMEOUT).map_err(sql_err(path, "set busy timeout"))?;
    conn.pragma_update(None, "synchronous", "FULL").map_err(sql_err(path, "set synchronous = FULL"))?;
    let synchronous: i64 =
        conn.pragma_query_value(None, "synchronous", |row| row.get(0)).map_err(sql_err(path, "read synchronous"))?;
    if synchronous != 2 {
        return Err(EditStoreError::Io(format!("{}: synchronous is {synchronous}, not FULL (2)", path.display())));
    }
    Ok(conn)
}

/// Create the schema in an empty file, or check that the file holds this schema version.
fn init_schema(conn: &mut Connection, path: &Path) -> Result<(), EditStoreError> {
    // Immediate: two processes creating the file at once do not both create the schema.
    let tx = conn.transaction_with_behavior(TransactionBehavior::Immediate).map_err(sql_err(path, "begin"))?;
    let tables: Vec<String> = {
        let mut stmt = tx
            .prepare("SELECT name FROM sqlite_schema WHERE type = 'table' ORDER BY name")
            .map_err(sql_err(path, "read schema"))?;
        let names = stmt.query_map([], |row| row.get(0)).map_err(sql_err(path, "read schema"))?;
        names.collect::<Result<_, _>>().map_err(sql_err(path, "read schema"))?
    };
    if tables.is_empty() {
        tx.execute_batch(
            "CREATE TABLE meta (key TEXT PRIMARY KEY NOT NULL, value INTEGER NOT NULL) WITHOUT ROWID;
             CREATE TABLE edits (
                 cx INTEGER NOT NULL,
                 cz INTEGER NOT NULL,
                 version INTEGER NOT NULL,
                 op BLOB NOT NULL,
                 PRIMARY KEY (cx, cz, version)
             ) WITHOUT ROWID;",
        )
        .map_err(sql_err(path, "create schema"))?;
        tx.execute("INSERT INTO meta (key, value) VALUES ('schema_version', ?1)", [SCHEMA_VERSION])
            .map_err(sql_err(path, "create schema"))?;
        return tx.commit().map_err(sql_err(path, "commit schema"));
    }
    if !tables.iter().any(|t| t == "meta") {
        return Err(EditStoreError::Io(format!(
            "{}: not a Canopy edit store (no meta table; tables: {})",
            path.display(),
            tables.join(", ")
        )));
    }
    let version: Option<i64> = tx
        .query_row("SELECT value FROM meta WHERE key = 'schema_version'", [], |row| row.get(0))
        .map(Some)
        .or_else(|e| if matches!(e, rusqlite::Error::QueryReturnedNoRows) { Ok(None) } else { Err(e) })
        .map_err(sql_err(path, "read schema version"))?;
    match version {
        Some(SCHEMA_VERSION) if tables.iter().any(|t| t == "edits") => Ok(()),
        Some(SCHEMA_VERSION) => Err(EditStoreError::Corrupt(format!("{}: the edits table is missing", path.display()))),
        Some(v) => Err(EditStoreError::Io(format!(
            "{}: unknown edit store schema version {v} (this build reads version {SCHEMA_VERSION})",
            path.display()
        ))),
        None => Err(EditStoreError::Io(format!("{}: no schema version in the meta table", path.display()))),
    }
}

fn is_primary_key_violation(err: &rusqlite::Error) -> bool {
    err.sqlite_error().is_some_and(|e| {
        e.code == ErrorCode::ConstraintViolation && e.extended_code == ffi::SQLITE_CONSTRAINT_PRIMARYKEY
    })
}

/// Map a SQLite error to [`EditStoreError::Io`] with the file and what was being done.
fn sql_err<'a>(path: &'a Path, what: &'a str) -> impl Fn(rusqlite::Error) -> EditStoreError + 'a {
    move |e| EditStoreError::Io(format!("{}: {what}: {e}", path.display()))
}
