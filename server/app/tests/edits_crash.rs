//! Crash safety of live edits, on the real binary: `canopy-server --data DIR` takes a steady load of plants, sets
//! and fells from two editors and is killed with SIGKILL at a random moment (or right as an acknowledgement
//! arrives, or while its commits wait on a stalled store), several times over, each time restarted on the same
//! data directory. Afterwards the edit store holds every acknowledged edit exactly once, at the version it was
//! acknowledged with, each cell's versions are exactly 1..=n, every stored edit is a whole op that was sent (an
//! edit sent but never answered is either wholly there or absent), a fresh client of the restarted server sees
//! exactly what the store holds, and a client that watched the first round resumes with only the deltas it missed.
//! A bad setup (an editor rate of 0, a data directory that is a file) is refused in plain words, writing nothing.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::AtomicBool;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Duration, Instant};

use canopy_client::net::endpoint;
use canopy_client::state::{ClientState, Event};
use canopy_client::{ConnectConfig, Connection, Trust};
use canopy_protocol::aoi::{Grid, Viewpoint};
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_protocol::messages::ServerMsgKind;
use canopy_protocol::record::dequantize;
use canopy_protocol::xorshift::XorShift64;
use canopy_protocol::{CellCoord, InstanceId, InstanceRecord};
use canopy_server::edits::{CellEdit, EditStore, SqliteEditStore};

/// A small flat world (64 cells of 64 m, about 1,200 conifers): the server starts in milliseconds even unoptimised.
const WORLD: &str = "\
world crash
seed 12345
bounds -256 -256 256 256
cell 64
species conifer conifer
species worm worm
scatter conifer {
  spacing 12
  param height = 10 .. 20 step 1
}
";
/// The cells the load goes to (a handful, so that versions pile up in each).
const CELLS: [(i32, i32); 4] = [(0, 0), (-1, 0), (0, -1), (2, 1)];
/// Rounds of start, load, SIGKILL, of three kinds in turn ([`Kill`]).
const ROUNDS: usize = 6;
/// Editors connected in each round.
const EDITORS: usize = 2;
/// Each editor sends an edit this often.
const PERIOD: Duration = Duration::from_millis(4);
/// Most edits an editor has sent and not had answered (below the server's `MAX_EDITS_IN_FLIGHT`).
const MAX_WAITING: usize = 32;
/// Bound of every wait for the server or a client.
const WAIT: Duration = Duration::from_secs(20);
/// Parameter values tag edits (each plant and set carries a value of its own); they stay below the server's bound.
const MAX_TAG: u32 = 10_000;

/// A running `canopy-server`, killed and reaped when dropped (so none outlives a failing test).
struct Running {
    child: Child,
    addr: SocketAddr,
    fingerprint: String,
}

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Running {
    /// SIGKILL (what `Child::kill` sends on Unix), then reap.
    fn kill(&mut self) {
        self.child.kill().expect("killing the server");
        self.child.wait().expect("reaping the server");
    }

    fn config(&self, token: Option<Vec<u8>>) -> ConnectConfig {
        let mut cfg = ConnectConfig::new(self.addr, Trust::pinned(&self.fingerprint).expect("a fingerprint"));
        cfg.token = token;
        cfg.timeout = WAIT;
        cfg
    }
}

fn server() -> Command {
    Command::new(env!("CARGO_BIN_EXE_canopy-server"))
}

/// Start the server on `dir`'s data and wait (bounded) for its address and fingerprint on stdout.
fn start(dir: &Path, n: usize) -> Running {
    let log = dir.join(format!("server-{n}.log"));
    let child = server()
        .arg("--data")
        .arg(dir.join("data"))
        .arg("--editors")
        .arg(dir.join("editors"))
        .arg("--world")
        .arg(dir.join("crash.world"))
        .args(["--listen", "127.0.0.1:0", "--no-metrics", "--stats-every", "0"])
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).expect("the server's log file"))
        .spawn()
        .expect("starting canopy-server");
    let mut running = Running { child, addr: "0.0.0.0:0".parse().unwrap(), fingerprint: String::new() };
    // Read stdout on a thread (to its end, so the server never blocks on a full pipe) and wait here with a bound.
    let out = running.child.stdout.take().expect("piped stdout");
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines() {
            let Ok(line) = line else { return };
            if tx.send(line).is_err() {
                return;
            }
        }
    });
    let deadline = Instant::now() + WAIT;
    let (mut addr, mut fingerprint) = (None, None);
    while addr.is_none() || fingerprint.is_none() {
        let left = deadline.saturating_duration_since(Instant::now());
        let line = rx.recv_timeout(left).unwrap_or_else(|e| {
            let log = std::fs::read_to_string(&log).unwrap_or_default();
            panic!("the server did not say where it listens ({e:?}); its log:\n{log}")
        });
        if let Some(rest) = line.strip_prefix("listening on ") {
            addr = Some(rest.split_whitespace().next().unwrap().parse().expect("a socket address"));
        } else if let Some(rest) = line.strip_prefix("fingerprint ") {
            fingerprint = Some(rest.trim().to_owned());
        }
    }
    running.addr = addr.unwrap();
    running.fingerprint = fingerprint.unwrap();
    running
}

/// One edit sent, and its answer if one came.
#[derive(Debug)]
struct Sent {
    op: EditOp,
    answer: Option<EditOutcome>,
}

/// Everything the editors sent over all rounds, and the instances each may still set or fell (planted by it,
/// acknowledged, no fell sent).
#[derive(Default)]
struct Model {
    sent: Vec<Sent>,
    next_tag: u32,
    live: [Vec<InstanceId>; EDITORS],
    /// Why each editor's load ended, this round (for a failure's message).
    ended: Vec<String>,
}

impl Model {
    fn tag(&mut self) -> f32 {
        self.next_tag += 1;
        assert!(self.next_tag < MAX_TAG, "too many edits for the tags");
        self.next_tag as f32
    }
}

/// The next edit of editor `me`: mostly plants in [`CELLS`], else a set or a fell of an instance it planted.
fn next_op(model: &mut Model, me: usize, grid: &Grid, rng: &mut XorShift64) -> EditOp {
    let roll = rng.next() % 10;
    let live = &mut model.live[me];
    if roll >= 6 && !live.is_empty() {
        let i = (rng.next() % live.len() as u64) as usize;
        if roll >= 8 {
            // Never touched again: its fell may be stored without an answer.
            let id = live.swap_remove(i);
            return EditOp::Fell { id };
        }
        let id = live[i];
        return EditOp::Set { id, params: vec![(0, model.tag())] };
    }
    let (cx, cz) = CELLS[(rng.next() % CELLS.len() as u64) as usize];
    let o = grid.cell_origin(CellCoord::new(cx, cz));
    let unit = |r: u64| (r % 1_000_000) as f32 / 1_000_000.0;
    let x = o[0] + 0.5 + unit(rng.next()) * (grid.cell_size - 1.0);
    let z = o[1] + 0.5 + unit(rng.next()) * (grid.cell_size - 1.0);
    EditOp::Plant { species: (rng.next() % 2) as u8, x, z, params: vec![(0, model.tag())] }
}

/// How a round kills the server, after a random delay once the load is under way (its first edit acknowledged).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kill {
    /// Then and there.
    Random,
    /// At the first acknowledgement the editors receive after it (where a server that acknowledged an edit before
    /// its commit was durable would lose that edit).
    AtAck,
    /// A slow disk: from then on another process holds the store's write lock, so the server's commits wait; the
    /// kill comes while they wait, and no edit sent meanwhile may have been acknowledged.
    Stalled,
}

/// When to kill: once `armed`, the next acknowledgement an editor receives is `fired`.
#[derive(Default)]
struct Trigger {
    armed: AtomicBool,
    fired: tokio::sync::Notify,
}

/// Send edits every [`PERIOD`] until `stop`, record every answer, then take what already arrived.
async fn load(
    mut conn: Connection,
    me: usize,
    model: Arc<Mutex<Model>>,
    seed: u64,
    trigger: Arc<Trigger>,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    let grid = conn.welcome().world.grid;
    let mut rng = XorShift64::new(seed);
    let mut requests: HashMap<u32, usize> = HashMap::new();
    let answer = |requests: &HashMap<u32, usize>, ev: Event| {
        let Event::EditResult(r) = ev else { return };
        if matches!(r.outcome, EditOutcome::Ok { .. }) && trigger.armed.load(Relaxed) {
            trigger.fired.notify_one();
        }
        let mut m = model.lock().unwrap();
        let i = *requests.get(&r.request).expect("an answer to a request sent");
        let sent = &mut m.sent[i];
        assert!(sent.answer.is_none(), "request {} answered twice", r.request);
        if let (EditOp::Plant { x, z, .. }, EditOutcome::Ok { id, .. }) = (&sent.op, &r.outcome) {
            assert_eq!(id.cell(), grid.cell_of(*x, *z));
            let id = *id;
            sent.answer = Some(r.outcome);
            m.live[me].push(id);
        } else {
            sent.answer = Some(r.outcome);
        }
    };
    let mut tick = tokio::time::interval(PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Answers awaited, bounded as an editing client bounds them: a slow disk slows the load instead of filling the
    // session's window of edits in flight (whose overflow the server denies, and a flood of denials ends a session).
    let mut waiting = 0usize;
    loop {
        tokio::select! {
            _ = stop.changed() => break,
            ev = conn.next_event() => match ev {
                Ok(ev) => {
                    waiting -= usize::from(matches!(ev, Event::EditResult(_)));
                    answer(&requests, ev)
                }
                Err(e) => {
                    model.lock().unwrap().ended.push(format!("editor {me}: {e}"));
                    break;
                }
            },
            _ = tick.tick(), if waiting < MAX_WAITING => {
                let (op, i) = {
                    let mut m = model.lock().unwrap();
                    let op = next_op(&mut m, me, &grid, &mut rng);
                    m.sent.push(Sent { op: op.clone(), answer: None });
                    (op, m.sent.len() - 1)
                };
                // A write the dead server never takes leaves the edit sent and unanswered; a slow one is waited for
                // until the server is killed.
                let sent = tokio::select! {
                    _ = stop.changed() => break,
                    sent = conn.edit(op) => sent,
                };
                match sent {
                    Ok(request) => {
                        requests.insert(request, i);
                        waiting += 1;
                    }
                    Err(e) => {
                        model.lock().unwrap().ended.push(format!("editor {me} sending: {e}"));
                        break;
                    }
                }
            }
        }
    }
    // The server is dead: answers already on their way still count.
    while let Ok(Ok(ev)) = tokio::time::timeout(Duration::from_millis(200), conn.next_event()).await {
        answer(&requests, ev);
    }
}

/// A viewpoint whose area of interest holds the whole world.
fn whole_world() -> Viewpoint {
    Viewpoint::at(0, [0.0, 0.0], 400.0)
}

/// Apply what arrives until `stop`, then what already arrived; the state, to resume.
async fn watch(mut conn: Connection, mut stop: tokio::sync::watch::Receiver<bool>) -> ClientState {
    loop {
        tokio::select! {
            _ = stop.changed() => break,
            ev = conn.next_event() => if ev.is_err() { break },
        }
    }
    while let Ok(Ok(_)) = tokio::time::timeout(Duration::from_millis(200), conn.next_event()).await {}
    conn.close_into_state()
}

/// An instance as compared: id bits, species, the position's bits, seed, parameters (values' bits).
type Flat = (u64, u8, [u32; 3], u64, Vec<(u16, u32)>);

/// Every instance a client holds, comparable (the floats' bits).
fn sorted(c: &Connection) -> Vec<Flat> {
    let mut v: Vec<_> = c
        .state()
        .instances(&|_, _| 0.0)
        .map(|i| {
            let params = i.params.iter().map(|p| (p.0, p.1.to_bits())).collect();
            (i.id.0, i.species, i.position.map(f32::to_bits), i.seed, params)
        })
        .collect();
    v.sort();
    v
}

/// What a stored edit is: the request it came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
enum Key {
    /// A plant or a set, by its tag.
    Tag(u32),
    /// A fell, by its instance (each is felled at most once).
    Fell(u64),
}

fn key_of_op(op: &EditOp) -> Key {
    match op {
        EditOp::Plant { params, .. } | EditOp::Set { params, .. } => Key::Tag(params[0].1 as u32),
        EditOp::Fell { id } => Key::Fell(id.0),
    }
}

fn key_of_stored(cell: CellCoord, op: &CellEdit) -> Key {
    match op {
        CellEdit::Plant { params, .. } | CellEdit::Set { params, .. } => {
            assert_eq!(params.len(), 1, "{op:?}");
            Key::Tag(params[0].1 as u32)
        }
        CellEdit::Fell { index } => Key::Fell(InstanceId::new(cell, *index).unwrap().0),
    }
}

/// Whether stored `op` (in `cell`, at `index`) is wholly what `sent` asked for.
fn same_op(grid: &Grid, cell: CellCoord, stored: &CellEdit, sent: &EditOp) -> bool {
    match (stored, sent) {
        (CellEdit::Plant { record, params, .. }, EditOp::Plant { species, x, z, params: asked }) => {
            let q = grid.steps(cell, (*x).into(), (*z).into());
            grid.cell_of(*x, *z) == cell && *record == InstanceRecord::new(*species, q[0], q[1]) && params == asked
        }
        (CellEdit::Set { index, params }, EditOp::Set { id, params: asked }) => {
            id.cell() == cell && id.index() == *index && params == asked
        }
        (CellEdit::Fell { index }, EditOp::Fell { id }) => id.cell() == cell && id.index() == *index,
        _ => false,
    }
}

/// An instance as compared here: species, quantised position in its cell, parameters.
type Held = (u8, u16, u16, Vec<(u16, f32)>);

/// What one edited cell holds beyond the world function's records, folded from its log: its version, the live
/// planted instances by index, the felled indices.
#[derive(Debug, Default, PartialEq)]
struct Planted {
    version: u32,
    records: BTreeMap<u16, Held>,
    felled: BTreeSet<u16>,
}

#[test]
fn acknowledged_edits_survive_sigkill_once_each_and_nothing_is_half_applied() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::write(dir.join("crash.world"), WORLD).unwrap();
    // A token for the editors (a rate far above the load's).
    let out = server()
        .args(["--add-editor", "crash", "--rate", "100000", "--editors"])
        .arg(dir.join("editors"))
        .output()
        .expect("running canopy-server --add-editor");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let token = String::from_utf8(out.stdout).unwrap().trim().to_owned();
    assert_eq!(token.len(), 64, "{token:?}");
    let token = canopy_server::session::unhex(&token).expect("a hexadecimal token");

    let started = Instant::now();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let model = Arc::new(Mutex::new(Model::default()));
    let mut rng = XorShift64::new(0x5eed_c4a5);
    let mut acked_before = 0;
    let mut watched = None;
    for round in 0..ROUNDS {
        let mut running = start(dir, round);
        let kill = [Kill::Random, Kill::AtAck, Kill::Stalled][round % 3];
        let kill_after = Duration::from_millis(match kill {
            Kill::AtAck => 50 + rng.next() % 101,
            Kill::Random | Kill::Stalled => 150 + rng.next() % 451,
        });
        let state = rt.block_on(async {
            let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
            let cfg = running.config(Some(token.clone()));
            let mut editors = Vec::new();
            for _ in 0..EDITORS {
                let mut c = Connection::connect(&ep, &cfg, None, |w| {
                    let o = w.world.grid.cell_origin(CellCoord::new(0, 0));
                    Viewpoint::at(0, o, 100.0)
                })
                .await
                .expect("an editor connects");
                c.wait_complete(WAIT).await.expect("an editor's area of interest fills");
                editors.push(c);
            }
            // A read-only watcher of the whole world, complete before the load (the first round's resumes at the end).
            let mut watcher = Connection::connect(&ep, &running.config(None), None, |_| whole_world())
                .await
                .expect("a watcher connects");
            watcher.wait_complete(WAIT).await.expect("the watcher's area of interest fills");
            let (stop, stopped) = tokio::sync::watch::channel(false);
            let trigger = Arc::new(Trigger::default());
            let watching = tokio::spawn(watch(watcher, stopped.clone()));
            model.lock().unwrap().ended.clear();
            let tasks: Vec<_> = editors
                .into_iter()
                .enumerate()
                .map(|(me, c)| {
                    let seed = rng.next();
                    tokio::spawn(load(c, me, Arc::clone(&model), seed, Arc::clone(&trigger), stopped.clone()))
                })
                .collect();
            // The kill comes at a random moment once the load is under way (its first edit acknowledged), so that
            // every round has acknowledged edits to lose if the server acknowledged too early.
            let acked = || model.lock().unwrap().sent.iter().filter(|s| s.answer.is_some()).count();
            let first = acked();
            tokio::time::timeout(WAIT, async {
                while acked() == first {
                    tokio::time::sleep(Duration::from_millis(2)).await;
                }
            })
            .await
            .expect("the server answers an edit");
            let mut stall = None;
            match kill {
                Kill::Random => tokio::time::sleep(kill_after).await,
                Kill::AtAck => {
                    tokio::time::sleep(kill_after).await;
                    trigger.armed.store(true, Relaxed);
                    if tokio::time::timeout(WAIT, trigger.fired.notified()).await.is_err() {
                        let m = model.lock().unwrap();
                        let mut answers = BTreeMap::new();
                        for s in &m.sent {
                            *answers.entry(s.answer.as_ref().map_or("none", EditOutcome::label)).or_insert(0) += 1;
                        }
                        let last: Vec<_> = m.sent.iter().rev().take(4).collect();
                        let ended = &m.ended;
                        let log = std::fs::read_to_string(dir.join(format!("server-{round}.log"))).unwrap_or_default();
                        panic!(
                            "no edit acknowledged within {WAIT:?} once armed: {} sent, answers {answers:?}, last \
                             {last:?}, editors ended {ended:?}; the server's log:\n{log}",
                            m.sent.len()
                        );
                    }
                }
                Kill::Stalled => {
                    let lock = rusqlite::Connection::open(dir.join("data").join("edits.sqlite")).unwrap();
                    lock.busy_timeout(WAIT).unwrap();
                    // Taken between two of the server's commits: what is sent from now on cannot be committed.
                    lock.execute_batch("BEGIN IMMEDIATE").expect("the store's write lock");
                    let from = model.lock().unwrap().sent.len();
                    tokio::time::sleep(kill_after).await;
                    stall = Some((lock, from));
                }
            }
            running.kill();
            let _ = stop.send(true);
            for t in tasks {
                tokio::time::timeout(WAIT, t).await.expect("an editor stops").expect("an editor's task");
            }
            if let Some((lock, from)) = stall {
                let m = model.lock().unwrap();
                assert!(m.sent.len() > from + 10, "edits were sent while the commits waited");
                if let Some(s) = m.sent[from..].iter().find(|s| s.answer.is_some()) {
                    panic!("{:?} was answered {:?} while the store could not commit it", s.op, s.answer);
                }
                lock.execute_batch("ROLLBACK").unwrap();
            }
            tokio::time::timeout(WAIT, watching).await.expect("the watcher stops").expect("the watcher's task")
        });
        if round == 0 {
            watched = Some(state);
        }
        let m = model.lock().unwrap();
        let acked = m.sent.iter().filter(|s| matches!(s.answer, Some(EditOutcome::Ok { .. }))).count();
        assert!(acked > acked_before, "round {round}: no edit acknowledged before the kill");
        acked_before = acked;
    }

    // Restart once more: a fresh read-only client sees the edited cells as the store holds them.
    let running = start(dir, ROUNDS);
    let held = rt.block_on(async {
        let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
        let mut c =
            Connection::connect(&ep, &running.config(None), None, |_| whole_world()).await.expect("a reader connects");
        c.wait_complete(WAIT).await.expect("the reader's area of interest fills");
        let grid = c.welcome().world.grid;
        let mut held: BTreeMap<CellCoord, Planted> = BTreeMap::new();
        for &(x, z) in &CELLS {
            let cell = CellCoord::new(x, z);
            let h = c.state().cells().get(&cell).expect("the reader holds every edited cell");
            assert!(h.is_complete());
            held.insert(cell, Planted { version: h.version, ..Planted::default() });
        }
        for i in c.state().instances(&|_, _| 0.0) {
            let Some(p) = held.get_mut(&i.id.cell()) else { continue };
            let o = grid.cell_origin(i.id.cell());
            let q = grid.steps(i.id.cell(), i.position[0].into(), i.position[2].into());
            assert_eq!(dequantize(q[0], o[0], grid.cell_size), i.position[0]);
            p.records.insert(i.id.index(), (i.species, q[0], q[1], i.params.clone()));
        }
        for (cell, p) in held.iter_mut() {
            p.felled = c.state().cells()[cell].felled.clone();
        }
        // The first round's watcher comes back with the cells it held: it is sent what changed since its versions
        // (the edits of the later rounds, from the log the restarted server read back) as one delta a cell, no
        // cell again, and ends holding exactly what the fresh reader holds.
        let state = ClientState::resuming(watched.take().expect("a watcher's state"));
        let mut back = Connection::connect_resuming(&ep, &running.config(None), None, state, |_| whole_world())
            .await
            .expect("the watcher reconnects");
        tokio::time::timeout(WAIT, async {
            while held.iter().any(|(cell, p)| back.state().cells().get(cell).is_none_or(|h| h.version < p.version)) {
                back.next_event().await.expect("the resumed watcher's connection carries on");
            }
        })
        .await
        .expect("the resumed watcher catches up");
        while let Ok(ev) = tokio::time::timeout(Duration::from_millis(200), back.next_event()).await {
            ev.expect("the resumed watcher's connection carries on");
        }
        assert!(back.state().is_complete());
        assert_eq!(back.frame_bytes_received()[ServerMsgKind::Cells], 0, "a cell was sent again");
        assert_eq!(back.state().stats().deltas, CELLS.len() as u64, "one delta for each edited cell");
        assert_eq!(sorted(&back), sorted(&c));
        back.close();
        c.close();
        (grid, held)
    });
    drop(running);
    let (grid, mut held) = held;

    // The store, opened after the last server is gone.
    let store = SqliteEditStore::open(&dir.join("data")).expect("the edit store opens");
    let model = model.lock().unwrap();
    let by_key: HashMap<Key, usize> = model.sent.iter().enumerate().map(|(i, s)| (key_of_op(&s.op), i)).collect();
    assert_eq!(by_key.len(), model.sent.len(), "every edit sent has a key of its own");
    let mut found: HashMap<usize, (CellCoord, u32)> = HashMap::new();
    let mut stored = 0;
    let cells = store.cells().expect("the store lists its cells");
    for &(cell, last) in &cells {
        assert!(CELLS.contains(&(cell.x, cell.z)), "cell {cell:?} was never edited");
        // Every stored edit decodes whole (a damaged one fails the load).
        let log = store.load(cell).expect("the cell's log loads");
        let versions: Vec<u32> = log.iter().map(|e| e.version).collect();
        assert_eq!(versions, (1..=last).collect::<Vec<_>>(), "cell {cell:?}: versions 1..=n, none missing or twice");
        let base_total = log.iter().find_map(|e| match e.op {
            CellEdit::Plant { index, .. } => Some(index),
            _ => None,
        });
        let mut want = Planted { version: last, ..Planted::default() };
        for e in &log {
            let key = key_of_stored(cell, &e.op);
            let &i = by_key.get(&key).unwrap_or_else(|| panic!("{e:?} was never sent"));
            assert!(found.insert(i, (cell, e.version)).is_none(), "{:?} stored twice", model.sent[i].op);
            assert!(same_op(&grid, cell, &e.op, &model.sent[i].op), "{e:?} is not {:?}", model.sent[i].op);
            match &model.sent[i].answer {
                Some(EditOutcome::Ok { id, version }) => {
                    assert_eq!((id.cell(), id.index(), *version), (cell, e.op.index(), e.version), "{e:?}");
                }
                None => {}
                Some(other) => panic!("{e:?} is stored but was answered {other:?}"),
            }
            match &e.op {
                CellEdit::Plant { index, record, params } => {
                    want.records.insert(*index, (record.species, record.qx(), record.qz(), params.clone()));
                }
                CellEdit::Set { index, params } => {
                    let r = want.records.get_mut(index).expect("a set of a planted instance");
                    r.3 = canopy_server::edits::merge_params(&r.3, params);
                }
                CellEdit::Fell { index } => {
                    want.records.remove(index);
                    want.felled.insert(*index);
                }
            }
            stored += 1;
        }
        // The reader's view of the cell: the planted instances (past the world function's records) and the felled.
        let base = base_total.expect("every edited cell had a plant first");
        let got = held.get_mut(&cell).unwrap();
        got.records.retain(|&i, _| i >= base);
        assert_eq!(*got, want, "cell {cell:?}: the restarted server serves what the store holds");
    }
    assert_eq!(store.count().unwrap(), stored);
    // Every acknowledged edit is stored, at its version; the others are wholly there or absent, and none was
    // refused.
    let (mut acked, mut unanswered, mut unanswered_stored) = (0, 0, 0);
    for (i, s) in model.sent.iter().enumerate() {
        match &s.answer {
            Some(EditOutcome::Ok { id, version }) => {
                acked += 1;
                assert_eq!(found.get(&i), Some(&(id.cell(), *version)), "acknowledged {:?} is not stored", s.op);
            }
            Some(other) => panic!("{:?} was answered {other:?}", s.op),
            None => {
                unanswered += 1;
                unanswered_stored += usize::from(found.contains_key(&i));
            }
        }
    }
    // Cells never edited by the load are untouched; the edited ones piled up versions.
    for (cell, p) in &held {
        if !cells.iter().any(|(c, _)| c == cell) {
            assert_eq!(p.version, 0);
        }
    }
    assert_eq!(cells.len(), CELLS.len(), "{cells:?}");
    assert!(cells.iter().all(|&(_, v)| v >= 10), "{cells:?}");
    eprintln!(
        "{ROUNDS} kills: {} edits sent, {acked} acknowledged, {unanswered} unanswered ({unanswered_stored} of them \
         stored), {stored} stored in {} cells, {:.1} s",
        model.sent.len(),
        cells.len(),
        started.elapsed().as_secs_f64()
    );
    assert!(started.elapsed() < Duration::from_secs(50), "the test must stay well under a minute");
}

#[test]
fn bad_setups_are_refused_in_plain_words_and_write_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let editors = tmp.path().join("editors");
    // A rate of 0 is refused before the editors file is touched.
    let out = server().args(["--add-editor", "x", "--rate", "0", "--editors"]).arg(&editors).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("rate"), "{err}");
    assert!(!editors.exists(), "nothing written");
    // A data directory that is a file.
    let file = tmp.path().join("data");
    std::fs::write(&file, "not a directory").unwrap();
    let out = server().arg("--data").arg(&file).args(["--listen", "127.0.0.1:0"]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("not a directory"), "{err}");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "not a directory");
}
