//! The SQLite edit store: it keeps what it acknowledged across reopening and across a SIGKILL, agrees with the
//! in-memory reference store on a randomised sequence (conflicts included), refuses files that are not regular files
//! and rows that do not decode.

use canopy_protocol::xorshift::XorShift64;
use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use canopy_edits::{CellEdit, EditStore, EditStoreError, MemoryEditStore, SqliteEditStore, StoredEdit};
use canopy_protocol::{CellCoord, InstanceRecord};

/// The project's seeded test generator, with a bounded draw.
struct Rng(XorShift64);

impl Rng {
    fn new(seed: u64) -> Rng {
        Rng(XorShift64::new(seed))
    }

    fn next(&mut self) -> u64 {
        self.0.next()
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// A valid op (parameters finite, slots increasing), so that it decodes when loaded.
fn random_op(rng: &mut Rng, version: u32) -> CellEdit {
    let index = (version % 60_000) as u16;
    match rng.below(3) {
        0 => {
            let first = rng.below(8) as u16;
            let mut params = vec![(first, rng.below(1000) as f32 * 0.25)];
            if rng.below(2) == 0 {
                params.push((first + 1 + rng.below(4) as u16, -(rng.below(100) as f32)));
            }
            let record = InstanceRecord::new(rng.below(200) as u8, rng.below(4096) as u16, rng.below(4096) as u16);
            CellEdit::Plant { index, record, params }
        }
        1 => CellEdit::Fell { index },
        _ => CellEdit::Set { index, params: vec![(rng.below(16) as u16, rng.below(50) as f32 + 0.5)] },
    }
}

const CELLS: [CellCoord; 9] = [
    CellCoord::new(0, 0),
    CellCoord::new(-1, -1),
    CellCoord::new(-1, 1),
    CellCoord::new(1, -1),
    CellCoord::new(i32::MIN, i32::MIN),
    CellCoord::new(i32::MIN, i32::MAX),
    CellCoord::new(i32::MAX, i32::MIN),
    CellCoord::new(i32::MAX, i32::MAX),
    CellCoord::new(123_456, -987_654),
];

fn latest(store: &dyn EditStore, cell: CellCoord) -> u32 {
    store.cells().unwrap().into_iter().find(|(c, _)| *c == cell).map_or(0, |(_, v)| v)
}

fn assert_same(sqlite: &dyn EditStore, memory: &dyn EditStore) {
    assert_eq!(sqlite.cells().unwrap(), memory.cells().unwrap());
    assert_eq!(sqlite.count().unwrap(), memory.count().unwrap());
    for cell in CELLS {
        assert_eq!(sqlite.load(cell).unwrap(), memory.load(cell).unwrap(), "cell {cell:?}");
    }
}

#[test]
fn matches_the_memory_store_and_survives_reopening() {
    let dir = tempfile::tempdir().unwrap();
    let memory = MemoryEditStore::new();
    let mut rng = Rng::new(0x9e37_79b9_7f4a_7c15);
    let mut conflicts = 0;
    {
        let sqlite = SqliteEditStore::open(dir.path()).unwrap();
        for round in 0..300 {
            // A group: consecutive versions of one to three cells, sometimes made to conflict.
            let mut group = Vec::new();
            for _ in 0..=rng.below(3) {
                let cell = CELLS[rng.below(CELLS.len() as u64) as usize];
                let already = group.iter().filter(|e: &&StoredEdit| e.cell == cell).count() as u32;
                let next = latest(&memory, cell) + already + 1;
                for v in next..next + 1 + rng.below(4) as u32 {
                    group.push(StoredEdit { cell, version: v, op: random_op(&mut rng, v) });
                }
            }
            match rng.below(10) {
                // A version already stored (if there is one), placed anywhere in the group.
                0 | 1 => {
                    let cell = group[0].cell;
                    let v = latest(&memory, cell);
                    if v > 0 {
                        let at = rng.below(group.len() as u64 + 1) as usize;
                        group.insert(
                            at,
                            StoredEdit {
                                cell,
                                version: 1 + rng.below(v as u64) as u32,
                                op: CellEdit::Fell { index: 0 },
                            },
                        );
                    }
                }
                // A duplicate within the group.
                2 => {
                    let dup = group[rng.below(group.len() as u64) as usize].clone();
                    group.push(dup);
                }
                _ => {}
            }
            let a = sqlite.append(&group);
            let b = memory.append(&group);
            match (&a, &b) {
                (Ok(()), Ok(())) => {}
                (
                    Err(EditStoreError::Conflict { cell: c1, version: v1 }),
                    Err(EditStoreError::Conflict { cell: c2, version: v2 }),
                ) => {
                    assert_eq!((c1, v1), (c2, v2), "round {round}");
                    conflicts += 1;
                }
                _ => panic!("round {round}: sqlite {a:?}, memory {b:?}"),
            }
            if round % 50 == 0 {
                assert_same(&sqlite, &memory);
            }
        }
        assert_same(&sqlite, &memory);
    }
    assert!(conflicts > 30, "only {conflicts} conflicting groups");
    let reopened = SqliteEditStore::open(dir.path()).unwrap();
    assert_same(&reopened, &memory);
    assert!(reopened.count().unwrap() > 500);
    for (cell, latest) in reopened.cells().unwrap() {
        let versions: Vec<u32> = reopened.load(cell).unwrap().iter().map(|e| e.version).collect();
        assert_eq!(versions, (1..=latest).collect::<Vec<_>>());
    }
}

#[test]
fn a_conflict_in_the_middle_of_a_group_stores_nothing_of_it() {
    let dir = tempfile::tempdir().unwrap();
    let store = SqliteEditStore::open(dir.path()).unwrap();
    let a = CellCoord::new(3, -4);
    let b = CellCoord::new(-7, 2);
    let first = vec![
        StoredEdit { cell: a, version: 1, op: CellEdit::Fell { index: 0 } },
        StoredEdit { cell: a, version: 2, op: CellEdit::Fell { index: 1 } },
    ];
    store.append(&first).unwrap();
    let group = vec![
        StoredEdit { cell: b, version: 1, op: CellEdit::Fell { index: 0 } },
        StoredEdit { cell: a, version: 3, op: CellEdit::Fell { index: 2 } },
        StoredEdit { cell: a, version: 2, op: CellEdit::Fell { index: 9 } },
        StoredEdit { cell: b, version: 2, op: CellEdit::Fell { index: 1 } },
    ];
    match store.append(&group) {
        Err(EditStoreError::Conflict { cell, version }) => assert_eq!((cell, version), (a, 2)),
        other => panic!("{other:?}"),
    }
    assert_eq!(store.load(a).unwrap(), first);
    assert_eq!(store.load(b).unwrap(), vec![]);
    assert_eq!(store.count().unwrap(), 2);
    assert_eq!(store.cells().unwrap(), vec![(a, 2)]);
    // A duplicate within a group is a conflict too, and the store still takes the next group.
    let dup = vec![group[0].clone(), group[0].clone()];
    assert!(matches!(store.append(&dup), Err(EditStoreError::Conflict { version: 1, .. })));
    assert_eq!(store.count().unwrap(), 2);
    store.append(&group[..2]).unwrap();
    assert_eq!(store.cells().unwrap(), vec![(b, 1), (a, 3)]);
    store.append(&[]).unwrap();
    assert_eq!(store.count().unwrap(), 4);
}

fn assert_not_regular(dir: &Path) {
    match SqliteEditStore::open(dir) {
        Err(EditStoreError::Io(msg)) => assert!(msg.contains("not a regular file"), "{msg}"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn refuses_an_edits_file_that_is_a_symlink() {
    let dir = tempfile::tempdir().unwrap();
    std::os::unix::fs::symlink("/dev/null", dir.path().join("edits.sqlite")).unwrap();
    assert_not_regular(dir.path());
    // A link to a regular file is refused too, as is a link in place of the WAL.
    let other = tempfile::tempdir().unwrap();
    SqliteEditStore::open(other.path()).unwrap();
    std::fs::remove_file(dir.path().join("edits.sqlite")).unwrap();
    std::os::unix::fs::symlink(other.path().join("edits.sqlite"), dir.path().join("edits.sqlite")).unwrap();
    assert_not_regular(dir.path());
    std::fs::remove_file(dir.path().join("edits.sqlite")).unwrap();
    std::os::unix::fs::symlink("/dev/null", dir.path().join("edits.sqlite-wal")).unwrap();
    assert_not_regular(dir.path());
}

#[test]
fn refuses_an_edits_file_that_is_a_fifo_without_blocking() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("edits.sqlite");
    let status = Command::new("mkfifo").arg(&fifo).status().expect("run mkfifo");
    assert!(status.success());
    let (tx, rx) = mpsc::channel();
    let path = dir.path().to_path_buf();
    std::thread::spawn(move || {
        let _ = tx.send(SqliteEditStore::open(&path).map(|_| ()));
    });
    match rx.recv_timeout(Duration::from_secs(5)) {
        Ok(Err(EditStoreError::Io(msg))) => assert!(msg.contains("not a regular file"), "{msg}"),
        Ok(other) => panic!("{other:?}"),
        Err(_) => panic!("open blocked on a FIFO"),
    }
}

#[test]
fn refuses_an_edits_file_that_is_a_directory() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("edits.sqlite")).unwrap();
    assert_not_regular(dir.path());
}

#[test]
fn creates_its_directory_and_refuses_foreign_files() {
    let dir = tempfile::tempdir().unwrap();
    let nested = dir.path().join("a/b");
    let store = SqliteEditStore::open(&nested).unwrap();
    assert_eq!(store.count().unwrap(), 0);
    assert_eq!(store.cells().unwrap(), vec![]);
    assert!(nested.join("edits.sqlite").is_file());
    drop(store);

    // Not SQLite at all.
    let junk = tempfile::tempdir().unwrap();
    std::fs::write(junk.path().join("edits.sqlite"), vec![0x5a; 8192]).unwrap();
    assert!(matches!(SqliteEditStore::open(junk.path()), Err(EditStoreError::Io(_))));

    // SQLite, but someone else's.
    let foreign = tempfile::tempdir().unwrap();
    let conn = rusqlite::Connection::open(foreign.path().join("edits.sqlite")).unwrap();
    conn.execute_batch("CREATE TABLE t (x INTEGER)").unwrap();
    drop(conn);
    match SqliteEditStore::open(foreign.path()) {
        Err(EditStoreError::Io(msg)) => assert!(msg.contains("not a Canopy edit store"), "{msg}"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn refuses_an_unknown_schema_version() {
    let dir = tempfile::tempdir().unwrap();
    drop(SqliteEditStore::open(dir.path()).unwrap());
    let conn = rusqlite::Connection::open(dir.path().join("edits.sqlite")).unwrap();
    conn.execute("UPDATE meta SET value = 99 WHERE key = 'schema_version'", []).unwrap();
    drop(conn);
    match SqliteEditStore::open(dir.path()) {
        Err(EditStoreError::Io(msg)) => assert!(msg.contains("unknown edit store schema version 99"), "{msg}"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_row_that_does_not_decode_is_damage_with_the_readable_edits_before_it() {
    let dir = tempfile::tempdir().unwrap();
    let cell = CellCoord::new(-5, 6);
    let other = CellCoord::new(5, 6);
    {
        let store = SqliteEditStore::open(dir.path()).unwrap();
        store.append(&[StoredEdit { cell, version: 1, op: CellEdit::Fell { index: 0 } }]).unwrap();
        store.append(&[StoredEdit { cell: other, version: 1, op: CellEdit::Fell { index: 0 } }]).unwrap();
    }
    let conn = rusqlite::Connection::open(dir.path().join("edits.sqlite")).unwrap();
    conn.execute("INSERT INTO edits (cx, cz, version, op) VALUES (-5, 6, 2, ?1)", [vec![9u8, 9]]).unwrap();
    drop(conn);
    let store = SqliteEditStore::open(dir.path()).unwrap();
    match store.load(cell) {
        Err(e @ EditStoreError::Damaged { version: 2, .. }) => {
            let msg = e.to_string();
            assert!(msg.contains("x: -5") && msg.contains("z: 6") && msg.contains("version 2"), "{msg}");
            assert!(msg.contains("edits.sqlite"), "the file is named: {msg}");
            let EditStoreError::Damaged { readable, .. } = e else { unreachable!() };
            assert_eq!(readable, vec![StoredEdit { cell, version: 1, op: CellEdit::Fell { index: 0 } }]);
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(store.load(other).unwrap().len(), 1);

    // An op stored as text, and a version out of u32's range, are corrupt as well.
    let conn = rusqlite::Connection::open(dir.path().join("edits.sqlite")).unwrap();
    conn.execute("INSERT INTO edits (cx, cz, version, op) VALUES (1, 1, 1, 'text')", []).unwrap();
    conn.execute(
        "INSERT INTO edits (cx, cz, version, op) VALUES (2, 2, -1, ?1)",
        [CellEdit::Fell { index: 0 }.encode()],
    )
    .unwrap();
    drop(conn);
    assert!(matches!(store.load(CellCoord::new(1, 1)), Err(EditStoreError::Damaged { version: 1, .. })));
    assert!(matches!(store.load(CellCoord::new(2, 2)), Err(EditStoreError::Corrupt(_))));
}

#[test]
fn loads_see_a_consistent_prefix_while_a_writer_appends() {
    let dir = tempfile::tempdir().unwrap();
    let store = std::sync::Arc::new(SqliteEditStore::open(dir.path()).unwrap());
    let cell = CellCoord::new(-1, 7);
    let writer = {
        let store = store.clone();
        std::thread::spawn(move || {
            for v in (1..=200u32).step_by(4) {
                let group: Vec<StoredEdit> = (v..v + 4)
                    .map(|v| StoredEdit { cell, version: v, op: CellEdit::Fell { index: v as u16 } })
                    .collect();
                store.append(&group).unwrap();
            }
        })
    };
    let mut seen = 0;
    let check = |seen: &mut usize| {
        let versions: Vec<u32> = store.load(cell).unwrap().iter().map(|e| e.version).collect();
        assert_eq!(versions.len() % 4, 0, "a group seen in part");
        assert_eq!(versions, (1..=versions.len() as u32).collect::<Vec<_>>());
        assert!(versions.len() >= *seen);
        *seen = versions.len();
    };
    while !writer.is_finished() {
        check(&mut seen);
    }
    writer.join().unwrap();
    check(&mut seen);
    assert_eq!(seen, 200);
}

/// The child's side of [`acknowledged_appends_survive_sigkill`]: append to the store in `dir` until killed (or 20
/// seconds), printing `ack <version>` once each append has returned.
fn append_until_killed(dir: &Path) {
    let store = SqliteEditStore::open(dir).unwrap();
    let cells = [CellCoord::new(-3, 9), CellCoord::new(i32::MAX, i32::MIN)];
    let mut rng = Rng::new(7);
    let mut next = [1u32; 2];
    let mut out = std::io::stdout().lock();
    let start = Instant::now();
    // On a line of its own: libtest may have printed "test … " without a newline.
    writeln!(out).unwrap();
    while start.elapsed() < Duration::from_secs(20) {
        let which = rng.below(2) as usize;
        let n = 1 + rng.below(3) as u32;
        let group: Vec<StoredEdit> = (next[which]..next[which] + n)
            .map(|v| StoredEdit { cell: cells[which], version: v, op: random_op(&mut rng, v) })
            .collect();
        store.append(&group).unwrap();
        for e in &group {
            writeln!(out, "ack {} {}", which, e.version).unwrap();
        }
        out.flush().unwrap();
        next[which] += n;
    }
}

#[test]
fn acknowledged_appends_survive_sigkill() {
    const CHILD: &str = "CANOPY_EDITS_CHILD";
    if let Some(dir) = std::env::var_os(CHILD) {
        append_until_killed(Path::new(&dir));
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(std::env::current_exe().unwrap())
        .args(["--exact", "acknowledged_appends_survive_sigkill", "--nocapture", "--test-threads=1"])
        .env(CHILD, dir.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    let reader = std::thread::spawn(move || {
        let mut acked: [Vec<u32>; 2] = [Vec::new(), Vec::new()];
        let mut told = false;
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            let mut words = line.split_whitespace();
            if words.next() == Some("ack") {
                let which: usize = words.next().unwrap().parse().unwrap();
                acked[which].push(words.next().unwrap().parse().unwrap());
                if !told {
                    told = true;
                    let _ = tx.send(());
                }
            }
        }
        acked
    });
    // Kill it ~300 ms after its first acknowledgement (its start-up is not counted).
    let first = rx.recv_timeout(Duration::from_secs(20));
    if first.is_ok() {
        std::thread::sleep(Duration::from_millis(300));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    first.expect("the child acknowledged nothing");
    let acked = reader.join().unwrap();

    let store = SqliteEditStore::open(dir.path()).unwrap();
    let cells = [CellCoord::new(-3, 9), CellCoord::new(i32::MAX, i32::MIN)];
    let mut total = 0;
    for (which, cell) in cells.into_iter().enumerate() {
        let stored: Vec<u32> = store.load(cell).unwrap().iter().map(|e| e.version).collect();
        assert_eq!(stored, (1..=stored.len() as u32).collect::<Vec<_>>(), "a gap in cell {cell:?}");
        let printed = acked[which].last().copied().unwrap_or(0);
        assert!(stored.len() as u32 >= printed, "cell {cell:?}: acknowledged {printed}, stored {}", stored.len());
        assert_eq!(acked[which], (1..=printed).collect::<Vec<_>>());
        total += acked[which].len();
    }
    assert!(total > 0);
    eprintln!("child acknowledged {total} edits before SIGKILL; store holds {}", store.count().unwrap());
}

#[test]
fn passes_the_store_suite() {
    let dir = tempfile::tempdir().unwrap();
    canopy_edits::suite::check(&SqliteEditStore::open(dir.path()).unwrap());
}
