//! Live edits over real QUIC on loopback: an in-process server over a small world with an in-memory edit store. A
//! plant made on one connection reaches every connection holding its cell (and no other) and a fell takes it away
//! from all of them; a client that reconnects is sent only the deltas it missed, no cell again; read-only sessions
//! and unknown tokens are denied and change nothing. Every wait is bounded: a hang fails the test.

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;

use crate::support::{ALICE, BOB, CELL, base};
use canopy_client::expand::Expander;
use canopy_client::net::endpoint;
use canopy_client::state::{ClientState, Event, InstanceView};
use canopy_client::{ConnectConfig, Connection, Trust};
use canopy_protocol::aoi::{AoiParams, Viewpoint};
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_protocol::messages::ServerMsgKind;
use canopy_protocol::record::position_step;
use canopy_protocol::{CellCoord, InstanceId};
use canopy_server::edits::{EditStore, MemoryEditStore};
use canopy_server::session::editor_line;
use canopy_server::session::{Editors, GridStore, SessionConfig, WorldStore};
use canopy_server::{EditService, Edits, ServeOptions, Served, ServerConfig, serve_store};

/// Far more than any wait here should take, short enough that a hang fails well within CI's patience.
const WAIT: Duration = Duration::from_secs(20);
/// A viewpoint whose area of interest holds the whole 8 × 8 grid.
const EVERYWHERE: f32 = 200.0;

/// A server over [`base`] with live edits; Alice and Bob are editors.
struct Fixture {
    server: Served,
    edits: Arc<MemoryEditStore>,
    service: Arc<EditService>,
}

impl Fixture {
    async fn start() -> Fixture {
        Fixture::start_on(base()).await
    }

    /// [`Fixture::start`] over another world.
    async fn start_on(store: Arc<dyn WorldStore>) -> Fixture {
        let edits = Arc::new(MemoryEditStore::new());
        let text = [editor_line("alice", &ALICE, None, Some(1000)), editor_line("bob", &BOB, None, Some(1000))];
        let cfg = ServerConfig {
            listen: "127.0.0.1:0".parse().unwrap(),
            session: SessionConfig {
                aoi: AoiParams { max_radius: 300.0, hysteresis: 24.0, lookahead_s: 0.0, max_lookahead: 0.0 },
                handshake_timeout: Duration::from_secs(5),
                editors: Some(Arc::new(Editors::parse("editors", &text.join("\n")).unwrap())),
                ..SessionConfig::default()
            },
            ..ServerConfig::default()
        };
        let opts = ServeOptions {
            server: cfg,
            edits: Edits::Store(Arc::clone(&edits) as Arc<dyn EditStore>),
            overlay_cache_bytes: 1 << 20,
            ..ServeOptions::default()
        };
        let server = serve_store(store, opts).await.expect("server starts");
        let service = Arc::clone(server.edits().expect("a server taking edits"));
        Fixture { server, edits, service }
    }

    fn config(&self, token: Option<[u8; 32]>) -> ConnectConfig {
        let mut cfg = ConnectConfig::new(self.server.local_addr(), Trust::pinned(self.server.fingerprint()).unwrap());
        cfg.token = token.map(|t| t.to_vec());
        cfg
    }

    /// A client whose area of interest holds every cell, complete.
    async fn client(&self, token: Option<[u8; 32]>) -> Connection {
        self.resume(token, ClientState::new()).await
    }

    /// A client resuming `state`, its area of interest every cell; complete (which a resumed client is at once).
    async fn resume(&self, token: Option<[u8; 32]>, state: ClientState) -> Connection {
        self.client_at(token, state, Viewpoint::at(0, [0.0, 0.0], EVERYWHERE)).await
    }

    /// A client (resuming `state`) at `viewpoint`, complete.
    async fn client_at(&self, token: Option<[u8; 32]>, state: ClientState, viewpoint: Viewpoint) -> Connection {
        self.client_with(self.config(token), state, viewpoint).await
    }

    /// A client of configuration `cfg` (resuming `state`) at `viewpoint`, complete.
    async fn client_with(&self, cfg: ConnectConfig, state: ClientState, viewpoint: Viewpoint) -> Connection {
        let ep = endpoint(local()).unwrap();
        let connect = Connection::connect_resuming(&ep, &cfg, None, state, |_| viewpoint);
        let mut c = within("connecting", connect).await.expect("connects");
        c.wait_complete(WAIT).await.expect("the area of interest fills");
        c
    }

    async fn stop(self) {
        // Closes the connections, then stops the edit writer.
        self.server.shutdown(Duration::from_secs(1)).await;
    }
}

fn local() -> SocketAddr {
    "127.0.0.1:0".parse().unwrap()
}

/// `f`, or a panic naming `what` after [`WAIT`].
async fn within<T>(what: &str, f: impl Future<Output = T>) -> T {
    match tokio::time::timeout(WAIT, f).await {
        Ok(v) => v,
        Err(_) => panic!("timed out {what}"),
    }
}

/// Ask for an edit and wait for its answer (other events are applied meanwhile).
async fn edit(c: &mut Connection, op: EditOp) -> EditOutcome {
    let request = c.edit(op).await.expect("the edit is sent");
    within("waiting for an edit's answer", async {
        loop {
            match c.next_event().await.expect("the connection carries on") {
                Event::EditResult(r) if r.request == request => return r.outcome,
                Event::EditResult(r) => panic!("answer to request {} while waiting for {request}", r.request),
                _ => {}
            }
        }
    })
    .await
}

/// Ask for an edit that must succeed: the instance and the cell's version.
async fn edit_ok(c: &mut Connection, op: EditOp) -> (InstanceId, u32) {
    match edit(c, op.clone()).await {
        EditOutcome::Ok { id, version } => (id, version),
        other => panic!("{op:?}: {other:?}"),
    }
}

/// Apply events until the client holds `cell` at `version` (or later).
async fn until_version(c: &mut Connection, cell: CellCoord, version: u32) {
    within("waiting for a delta", async {
        while c.state().cells().get(&cell).is_none_or(|h| h.version < version) {
            if let Event::EditResult(r) = c.next_event().await.expect("the connection carries on") {
                panic!("unexpected edit answer {r:?}");
            }
        }
    })
    .await
}

/// Apply whatever arrives for `quiet`; returns the events.
async fn drain(c: &mut Connection, quiet: Duration) -> Vec<Event> {
    let mut events = Vec::new();
    while let Ok(ev) = tokio::time::timeout(quiet, c.next_event()).await {
        events.push(ev.expect("the connection carries on"));
    }
    events
}

fn by_id(c: &Connection) -> HashMap<InstanceId, InstanceView> {
    c.state().instances(&|_, _| 0.0).map(|i| (i.id, i)).collect()
}

/// An instance as compared: id bits, species, the position's bits, seed, parameters (values' bits).
type Flat = (u64, u8, [u32; 3], u64, Vec<(u16, u32)>);

/// Every instance held, in a comparable form (bits of the floats).
fn sorted(c: &Connection) -> Vec<Flat> {
    let mut v: Vec<_> = c
        .state()
        .instances(&|_, _| 0.0)
        .map(|i| {
            (
                i.id.0,
                i.species,
                i.position.map(f32::to_bits),
                i.seed,
                i.params.iter().map(|p| (p.0, p.1.to_bits())).collect(),
            )
        })
        .collect();
    v.sort();
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plant_reaches_every_connection_holding_the_cell_and_a_fell_takes_it_from_all() {
    let f = Fixture::start().await;
    let mut alice = f.client(Some(ALICE)).await;
    let mut watchers = Vec::new();
    for _ in 0..5 {
        watchers.push(f.client(None).await);
    }
    // A client whose area of interest is the far corner does not hold the cell: it hears nothing of the change.
    let mut far = f.client_at(None, ClientState::new(), Viewpoint::at(0, [-112.0, -112.0], 20.0)).await;
    let (x, z) = (37.3, 45.9);
    let cell = CellCoord::new(1, 1);
    assert!(!far.state().cells().contains_key(&cell));
    let before = watchers[0].state().cells()[&cell].clone();
    assert_eq!(before.version, 0);
    let params = vec![(0, 17.25)];
    let (id, version) = edit_ok(&mut alice, EditOp::Plant { species: 1, x, z, params: params.clone() }).await;
    assert_eq!(id.cell(), cell);
    assert_eq!(usize::from(id.index()), before.records.len(), "planted at the cell's next index");
    assert_eq!(version, 1);
    let step = position_step(CELL);
    let check_planted = |c: &Connection| {
        let i = by_id(c).remove(&id).expect("the planted instance is held");
        assert_eq!(i.species, 1);
        assert!((0.0..step).contains(&(x - i.position[0])), "x {} for {x}", i.position[0]);
        assert!((0.0..step).contains(&(z - i.position[2])), "z {} for {z}", i.position[2]);
        assert_eq!(i.params, params);
        assert_eq!(c.state().cells()[&cell].version, version);
    };
    for w in &mut watchers {
        let changed = within("waiting for the plant's delta", async {
            loop {
                match w.next_event().await.expect("the watcher's connection carries on") {
                    Event::Changed { cell: c, version: v } => return (c, v),
                    Event::Records { cell: c, .. } if c == cell => panic!("the cell came whole, not as a delta"),
                    _ => {}
                }
            }
        })
        .await;
        assert_eq!(changed, (cell, version));
        check_planted(w);
    }
    // The editor's own connection holds the cell too.
    until_version(&mut alice, cell, version).await;
    check_planted(&alice);
    let (felled, v2) = edit_ok(&mut alice, EditOp::Fell { id }).await;
    assert_eq!((felled, v2), (id, 2));
    for w in watchers.iter_mut().chain(std::iter::once(&mut alice)) {
        until_version(w, cell, v2).await;
        assert!(!by_id(w).contains_key(&id), "the felled instance is gone");
        let held = &w.state().cells()[&cell];
        assert_eq!(held.records.len(), before.records.len() + 1, "its index stays taken");
        assert!(held.felled.contains(&id.index()));
        assert_eq!(w.state().stats().deltas, 2, "both changes came as deltas");
    }
    // Every client holds exactly what the store holds: a fresh client agrees with each.
    let fresh = f.client(None).await;
    let want = sorted(&fresh);
    for w in watchers.iter().chain(std::iter::once(&alice)) {
        assert_eq!(sorted(w), want);
    }
    assert_eq!(f.edits.count().unwrap(), 2);
    let heard = drain(&mut far, Duration::from_millis(100)).await;
    assert!(heard.is_empty(), "{heard:?}");
    assert_eq!(far.frame_bytes_received()[ServerMsgKind::Delta], 0);
    for c in watchers.into_iter().chain([alice, fresh, far]) {
        c.close();
    }
    f.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reconnecting_client_gets_exactly_the_missing_deltas() {
    let f = Fixture::start().await;
    let away = f.client(None).await;
    let held = away.state().cells().len();
    let cells_before = away.frame_bytes_received()[ServerMsgKind::Cells];
    assert!(held == 64 && cells_before > 0, "{held} cells held");
    let state = away.close_into_state();
    // Bob edits two cells while the client is away.
    let mut bob = f.client(Some(BOB)).await;
    let (a, b) = (CellCoord::new(0, 0), CellCoord::new(-2, -2));
    let (planted, _) = edit_ok(&mut bob, EditOp::Plant { species: 0, x: 9.0, z: 11.0, params: vec![(0, 2.5)] }).await;
    assert_eq!(planted.cell(), a);
    edit_ok(&mut bob, EditOp::Fell { id: InstanceId::new(a, 0).unwrap() }).await;
    let (_, va) = edit_ok(&mut bob, EditOp::Set { id: planted, params: vec![(0, 4.0)] }).await;
    let (_, vb) = edit_ok(&mut bob, EditOp::Set { id: InstanceId::new(b, 0).unwrap(), params: vec![(0, 8.0)] }).await;
    assert_eq!((va, vb), (3, 1));
    // Bob holds every cell: once his deltas came, the server's counters say what it sent before the resume.
    until_version(&mut bob, a, va).await;
    until_version(&mut bob, b, vb).await;
    let metrics = Arc::clone(f.server.metrics());
    let batches = metrics.messages[ServerMsgKind::Cells].load(Relaxed);
    let deltas = metrics.messages[ServerMsgKind::Delta].load(Relaxed);
    // Back: the cells it held are named with their versions; only the two changed ones are sent, as deltas.
    let mut back = f.resume(None, ClientState::resuming(state)).await;
    until_version(&mut back, a, va).await;
    until_version(&mut back, b, vb).await;
    // Nothing else is on its way.
    let late = drain(&mut back, Duration::from_millis(300)).await;
    assert!(late.is_empty(), "{late:?}");
    let got = back.frame_bytes_received();
    assert_eq!(got[ServerMsgKind::Cells], 0, "no cell sent again");
    assert_eq!(got[ServerMsgKind::Species], 0, "the species were kept, not resent");
    assert!(got[ServerMsgKind::Delta] > 0);
    assert_eq!(back.state().stats().deltas, 2, "one delta for each changed cell");
    assert_eq!(back.state().cells().len(), held);
    assert_eq!(metrics.messages[ServerMsgKind::Cells].load(Relaxed), batches, "the server sent no batch");
    // Bob's session got the same two changes as deltas; the resumed client its two.
    assert_eq!(metrics.messages[ServerMsgKind::Delta].load(Relaxed), deltas + 2);
    let fresh = f.client(None).await;
    assert_eq!(sorted(&back), sorted(&fresh));
    let i = by_id(&back).remove(&planted).expect("the plant made while away is held");
    assert_eq!(i.params, vec![(0, 4.0)]);
    assert!(!by_id(&back).contains_key(&InstanceId::new(a, 0).unwrap()));
    for c in [back, bob, fresh] {
        c.close();
    }
    f.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn read_only_sessions_and_unknown_tokens_are_denied_and_change_nothing() {
    let f = Fixture::start().await;
    let mut reader = f.client(None).await;
    let mut stranger = f.client(Some([9; 32])).await;
    let mut watcher = f.client(None).await;
    let before = sorted(&watcher);
    let existing = InstanceId::new(CellCoord::new(1, 0), 0).unwrap();
    let ops = [
        EditOp::Plant { species: 0, x: 5.0, z: 5.0, params: vec![] },
        EditOp::Fell { id: existing },
        EditOp::Set { id: existing, params: vec![(0, 1.0)] },
    ];
    for c in [&mut reader, &mut stranger] {
        for op in &ops {
            let outcome = edit(c, op.clone()).await;
            assert!(matches!(outcome, EditOutcome::Denied(_)), "{op:?}: {outcome:?}");
        }
    }
    // Nothing was stored, announced or changed.
    assert_eq!(f.edits.count().unwrap(), 0);
    let events = drain(&mut watcher, Duration::from_millis(300)).await;
    assert!(events.is_empty(), "{events:?}");
    for c in [&reader, &stranger, &watcher] {
        assert!(c.state().cells().values().all(|h| h.version == 0));
        assert_eq!(c.frame_bytes_received()[ServerMsgKind::Delta], 0);
        assert_eq!(sorted(c), before);
    }
    let fresh = f.client(None).await;
    assert_eq!(sorted(&fresh), before);
    assert_eq!(f.server.metrics().messages[ServerMsgKind::Delta].load(Relaxed), 0);
    // Refused by the sessions themselves: nothing reached the writer, and the metrics count the refusals.
    assert_eq!(f.service.metrics().groups.load(Relaxed), 0, "read-only sessions' edits never reach the writer");
    let outcomes: Vec<u64> = f.service.metrics().outcomes.iter().map(|o| o.load(Relaxed)).collect();
    assert_eq!(outcomes, vec![0, 6, 0, 0], "ok, denied, invalid, conflict");
    for c in [reader, stranger, watcher, fresh] {
        c.close();
    }
    f.stop().await;
}

/// A small world as a function (the same 8 × 8 grid of 32 m cells as [`base`]): clients may expand it themselves.
fn function_world() -> Arc<dyn WorldStore> {
    let text = "world tiny\nseed 7\nbounds -128 -128 128 128\ncell 32\nspecies worm worm\nspecies conifer conifer\n\
                scatter conifer {\n  spacing 9\n  param height = 8 .. 12 step 0.5\n}\n";
    let world = canopy_worlds::world::World::parse(&canopy_worlds::diag::SourceFile::new("tiny.world", text), None)
        .expect("the test world parses");
    GridStore::from_world(&world).unwrap().shared()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_expands_its_cells_holds_edited_cells_exactly_and_follows_their_changes() {
    let f = Fixture::start_on(function_world()).await;
    let mut alice = f.client(Some(ALICE)).await;
    // Edits before the expanding client comes: a plant, a fell and a set in three cells.
    let (planted, _) = edit_ok(&mut alice, EditOp::Plant { species: 1, x: 37.3, z: 45.9, params: vec![] }).await;
    let some = |c: &Connection, cell: CellCoord| by_id(c).into_keys().filter(|id| id.cell() == cell).min().unwrap();
    let felled = some(&alice, CellCoord::new(-2, 0));
    edit_ok(&mut alice, EditOp::Fell { id: felled }).await;
    let set = some(&alice, CellCoord::new(0, -3));
    edit_ok(&mut alice, EditOp::Set { id: set, params: vec![(0, 11.75)] }).await;
    let mut cfg = f.config(None);
    cfg.expander = Some(Expander::new(2, 1 << 20));
    let mut expanding = f.client_with(cfg, ClientState::new(), Viewpoint::at(0, [0.0, 0.0], EVERYWHERE)).await;
    let frames = expanding.frame_bytes_received();
    assert_eq!(frames[ServerMsgKind::Cells], 0, "records were sent");
    assert!(frames[ServerMsgKind::Grant] > 0);
    let mut records = f.client(None).await;
    let want = sorted(&records);
    assert_eq!(sorted(&expanding), want, "the expanding client holds what the store holds");
    assert!(by_id(&expanding).contains_key(&planted) && !by_id(&expanding).contains_key(&felled));
    // A change after the grant comes as a delta, as for records.
    let (again, v) = edit_ok(&mut alice, EditOp::Plant { species: 0, x: 40.5, z: 50.25, params: vec![] }).await;
    until_version(&mut expanding, again.cell(), v).await;
    until_version(&mut records, again.cell(), v).await;
    assert_eq!(sorted(&expanding), sorted(&records));
    assert!(by_id(&expanding).contains_key(&again));
    assert_eq!(expanding.frame_bytes_received()[ServerMsgKind::Cells], 0);
    for c in [alice, expanding, records] {
        c.close();
    }
    f.stop().await;
}
