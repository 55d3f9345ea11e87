//! The edit log on NATS JetStream, for real: a 3-node cluster started by `scripts/cluster.sh` on loopback and
//! stateless edges over it (each its own `NatsEditStore`, `LiveStore` and writer). An edit made through one edge
//! reaches the clients of another; edges racing for one cell's versions never take one twice (the engine's
//! compare-and-set, the writer's retry); a new edge starts with nothing and serves the same world; a cell whose
//! last message is a lost race's, deleted, reads whole and takes its next version. Then bots over
//! three real QUIC edges while the stream's leader node is killed with SIGKILL and an edge dies (its runtime dropped: its clients
//! hear nothing more, as after a SIGKILL): the bots of the dead edge resume on the others, every bot ends exact
//! against the world function + edits, and every acknowledged edit is read back from the stream, none lost and none
//! stored twice.

mod support;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use canopy_client::state::ClientState;
use canopy_protocol::CellCoord;
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_server::{NatsConfig, NatsEditStore};
use support::*;

fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/cluster.sh")
}

/// A cluster for one test, taken down (and its directory removed) when dropped.
struct Cluster {
    dir: tempfile::TempDir,
    port: u16,
}

impl Cluster {
    fn run(&self, args: &[&str]) -> String {
        let o = Command::new("bash")
            .arg(script())
            .args(args)
            .env("CLUSTER_DIR", self.dir.path().join("c"))
            .env("NATS_PORT", self.port.to_string())
            .env("READY_S", "30")
            .output()
            .expect("bash runs scripts/cluster.sh");
        let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
        assert!(o.status.success(), "scripts/cluster.sh {args:?} failed:\n{text}");
        text
    }

    /// Cluster `slot` (0..3) of this process.
    fn up(slot: u16) -> Cluster {
        // Client ports PORT..PORT+2, routes +100, monitoring +200: a block of ten of this process's own, three
        // ports of it a slot, all below Linux's ephemeral ports (32768 on): a port the kernel gave another socket
        // for the moment made a node fail to bind ("address already in use", CI on 2026-11-29).
        let port = 20_000 + (std::process::id() % 1_200) as u16 * 10 + slot * 3;
        let c = Cluster { dir: tempfile::tempdir().unwrap(), port };
        c.run(&["up", "0"]);
        c
    }

    /// The node (0..3) leading the edit stream now.
    fn leader(&self) -> String {
        let out = self.run(&["leader"]);
        let n = out.trim().to_string();
        assert!(["0", "1", "2"].contains(&n.as_str()), "scripts/cluster.sh leader said {out:?}");
        n
    }

    fn urls(&self) -> Vec<String> {
        (0..3).map(|i| format!("nats://127.0.0.1:{}", self.port + i)).collect()
    }

    /// A new edge of `world` over the cluster.
    fn edge(&self, world: &str) -> World {
        let cfg = NatsConfig { servers: self.urls(), world: world.into(), replicas: 3 };
        world_over(Arc::new(NatsEditStore::connect(cfg).expect("connecting to the cluster")))
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = Command::new("bash")
            .arg(script())
            .arg("down")
            .env("CLUSTER_DIR", self.dir.path().join("c"))
            .env("NATS_PORT", self.port.to_string())
            .output();
    }
}

/// A cell whose last message is a lost race's publish, deleted by its writer, reads whole and takes the next
/// version (nats-server 2.9 answers "no message" for such a subject's last; the store must not).
fn a_cell_whose_last_message_is_a_deleted_lost_race_reads_whole(cluster: &Cluster) {
    use canopy_server::edits::{CellEdit, EditStore, StoredEdit};
    let cfg =
        NatsConfig { servers: cluster.urls(), world: format!("deleted-last-{}", std::process::id()), replicas: 3 };
    let store = NatsEditStore::connect(cfg.clone()).expect("connecting to the cluster");
    let c = CellCoord::new(3, -2);
    let edit = |version, index| StoredEdit { cell: c, version, op: CellEdit::Fell { index } };
    store.append(&[edit(1, 0), edit(2, 1)]).unwrap();
    // A lost race as nats-server before 2.9.21 lets one through (two publishes naming the same last sequence both
    // taken): a second version 2 after the winner, which its writer then takes out of the stream. The cell's last
    // message is now a deleted one.
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let client = async_nats::connect(cfg.servers[0].as_str()).await.unwrap();
        let js = async_nats::jetstream::new(client);
        let stream = js.get_stream(cfg.stream()).await.unwrap();
        let ack = js.publish(cfg.subject(c), edit(2, 5).encode().into()).await.unwrap().await.unwrap();
        assert!(stream.delete_message(ack.sequence).await.unwrap());
    });
    // Every edge reads the cell whole, the one that wrote it and a new one.
    assert_eq!(store.load(c).unwrap(), vec![edit(1, 0), edit(2, 1)]);
    let fresh = NatsEditStore::connect(cfg).expect("connecting to the cluster");
    assert_eq!(fresh.load(c).unwrap(), vec![edit(1, 0), edit(2, 1)]);
    // And the next edit takes the next version.
    fresh.append(&[edit(3, 2)]).unwrap();
    assert_eq!(store.load(c).unwrap().len(), 3);
}

fn cell_version(p: &Pair, c: CellCoord) -> u32 {
    p.client.cells().get(&c).map_or(0, |h| h.version)
}

#[test]
fn edges_over_jetstream_share_the_edits_and_their_versions() {
    let cluster = Cluster::up(0);
    let world = format!("edits-test-{}", std::process::id());
    let (ea, eb) = (cluster.edge(&world), cluster.edge(&world));
    let mut a = Pair::connect(&ea, ClientState::new(), Some(ALICE), 1);
    let mut b = Pair::connect(&eb, ClientState::new(), Some(BOB), 2);
    settle_each(&mut [(&ea, &mut a), (&eb, &mut b)]);

    // An edit through edge A reaches B's client (B watches the cell: its overlay is cached).
    let c = CellCoord::new(1, 1);
    let plant = a.edit(EditOp::Plant { species: 1, x: 36.0, z: 40.0, params: vec![(0, 2.5)] });
    let fell = a.edit(EditOp::Fell { id: canopy_protocol::InstanceId::new(c, 0).unwrap() });
    settle_until(&mut [(&ea, &mut a), (&eb, &mut b)], |p| cell_version(p[1].1, c) == 2);
    assert!(matches!(a.results[&plant], EditOutcome::Ok { version: 1, .. }));
    assert!(matches!(a.results[&fell], EditOutcome::Ok { version: 2, .. }));
    assert_eq!(sorted(b.client.instances(&|_, _| 0.0).collect()), sorted(a.client.instances(&|_, _| 0.0).collect()));

    // Both edges race for one cell's versions: each version is taken once, every edit answered.
    let race = CellCoord::new(2, 2);
    let mut asked = Vec::new();
    for i in 0..8 {
        let z = 70.0 + i as f32;
        asked.push((0, a.edit(EditOp::Plant { species: 0, x: 66.0, z, params: vec![] })));
        asked.push((1, b.edit(EditOp::Plant { species: 0, x: 90.0, z, params: vec![] })));
        a.step(&ea);
        b.step(&eb);
    }
    settle_until(&mut [(&ea, &mut a), (&eb, &mut b)], |p| p[0].1.results.len() == 10 && p[1].1.results.len() == 8);
    let mut versions: Vec<u32> = asked
        .iter()
        .filter_map(|(who, r)| {
            let p = if *who == 0 { &a } else { &b };
            match &p.results[r] {
                EditOutcome::Ok { version, .. } => Some(*version),
                EditOutcome::Conflict => None,
                other => panic!("{other:?}"),
            }
        })
        .collect();
    versions.sort_unstable();
    assert_eq!(versions, (1..=versions.len() as u32).collect::<Vec<_>>(), "versions 1..n, none twice");
    let log = ea.edits.load(race).unwrap();
    assert_eq!(log.len(), versions.len(), "exactly the acknowledged edits are stored");
    settle_until(&mut [(&ea, &mut a), (&eb, &mut b)], |p| {
        cell_version(p[0].1, race) == versions.len() as u32 && cell_version(p[1].1, race) == versions.len() as u32
    });
    assert_eq!(sorted(b.client.instances(&|_, _| 0.0).collect()), sorted(a.client.instances(&|_, _| 0.0).collect()));

    // A new edge holds nothing of its own: it serves the same world, edits included.
    let ec = cluster.edge(&world);
    assert_eq!(expected(&ec), sorted(a.client.instances(&|_, _| 0.0).collect()));
    assert_eq!(ec.edits.count().unwrap(), 2 + versions.len() as u64);

    // Another edge's edit of a cell nobody here holds reaches this edge's index of edited cells (its far views) at
    // once, through the stream's watch, not at the next read of the whole index (30 s).
    use canopy_server::session::WorldStore;
    let far = CellCoord::new(-30, 25);
    let indexed = |e: &World| e.live.edited_cells(far, far, 4);
    assert!(indexed(&ec).is_empty());
    let record = canopy_protocol::InstanceRecord::new(0, 100, 100);
    let op = canopy_server::edits::CellEdit::Plant { index: 40, record, params: vec![] };
    ea.edits.append(&[canopy_server::edits::StoredEdit { cell: far, version: 1, op }]).unwrap();
    let told = std::time::Instant::now();
    while indexed(&ec).is_empty() {
        assert!(told.elapsed() < std::time::Duration::from_secs(10), "edge C's index never learned of the cell");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    eprintln!(
        "another edge's edit of a cell nobody held was in this edge's index {:.0?} after it was stored",
        told.elapsed()
    );
    assert_eq!(indexed(&ec), vec![(far, 1)]);
}

/// A real edge: canopy-server over the default world's cell cache and the cluster's edit log, on a runtime of its
/// own so that it can die at once.
struct Edge {
    rt: Option<tokio::runtime::Runtime>,
    server: Option<canopy_server::Served>,
    service: Arc<canopy_server::EditService>,
    addr: std::net::SocketAddr,
}

impl Edge {
    fn start(cluster: &Cluster, name: &str, world: &canopy_worlds::world::World) -> Edge {
        use canopy_server::session::{Editors, SessionConfig};
        use canopy_server::{Cells, Edits, ServeOptions, ServerConfig, serve};
        let editors = canopy_server::session::editor_line("bots", &ALICE, None, Some(10_000));
        let opts = ServeOptions {
            server: ServerConfig {
                listen: "127.0.0.1:0".parse().unwrap(),
                session: SessionConfig {
                    editors: Some(Arc::new(Editors::parse("editors", &editors).unwrap())),
                    ..SessionConfig::default()
                },
                ..ServerConfig::default()
            },
            cells: Cells::OnDemand(canopy_server::CellCacheConfig::default()),
            edits: Edits::Nats(NatsConfig { servers: cluster.urls(), world: name.into(), replicas: 3 }),
            overlay_cache_bytes: 16 << 20,
        };
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let server = rt.block_on(serve(world.clone(), opts)).expect("the edge starts");
        let service = Arc::clone(server.edits().expect("an edge taking edits"));
        let addr = server.local_addr();
        Edge { rt: Some(rt), server: Some(server), service, addr }
    }

    /// Die at once: the runtime and its tasks are dropped, nothing more is sent to the clients.
    fn kill(&mut self) {
        if let Some(rt) = self.rt.take() {
            rt.shutdown_background();
        }
        drop(self.server.take());
        self.service.stop();
    }
}

impl Drop for Edge {
    fn drop(&mut self) {
        self.kill();
    }
}

#[test]
fn bots_fail_over_between_edges_and_no_acknowledged_edit_is_lost() {
    use canopy_client::{ConnectConfig, Trust};
    use canopy_harness::bots::{self, BotsConfig, BotsSummary, EditPlan, PathKind, Progress, check_ledger};
    use std::time::{Duration, Instant};

    let cluster = Cluster::up(1);
    let name = format!("failover-test-{}", std::process::id());
    let world = Arc::new(canopy_worlds::world::World::default_world());
    let mut edges: Vec<Edge> = (0..3).map(|_| Edge::start(&cluster, &name, &world)).collect();
    let list = edges.iter().map(|e| e.addr.to_string()).collect::<Vec<_>>().join(",");
    let mut cfg = BotsConfig::new(9, ConnectConfig::new_edges(&list.parse().unwrap(), Trust::Insecure));
    cfg.path = PathKind::Random;
    cfg.speed = 2.0;
    cfg.duration = Duration::from_secs(16);
    cfg.radius = 96.0;
    cfg.spread = Some(64.0);
    cfg.connect_rate = 20.0;
    cfg.settle = Duration::from_secs(60);
    cfg.verify = Some(Arc::clone(&world));
    let mut plan = EditPlan::new(10.0, 6, ALICE.to_vec());
    plan.warmup = Duration::from_secs(1);
    let fanout = Arc::clone(&plan.fanout);
    cfg.edits = Some(plan);

    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let started = Instant::now();
    let run = rt.spawn(bots::run(cfg, Arc::new(Progress::default())));
    // Half-way: the stream's leader and an edge die (bot i started on edge i mod 3, so three bots lose theirs),
    // while edits of shared cells race for their versions; the stream elects a new leader.
    std::thread::sleep(Duration::from_secs(8));
    let leader = cluster.leader();
    cluster.run(&["kill", "nats", &leader]);
    edges[1].kill();
    std::thread::sleep(Duration::from_secs(3));
    cluster.run(&["start", "nats", &leader]);
    let reports = rt.block_on(run).unwrap().expect("the bots ran");
    let summary = BotsSummary::new(&reports, started.elapsed()).with_fanout(fanout.report());

    // Every acknowledged edit read back from the stream (the killed node is back): none lost, none twice.
    let check = NatsEditStore::connect(NatsConfig { servers: cluster.urls(), world: name, replicas: 3 }).unwrap();
    let grid = canopy_server::session::StoreHead::of_world(&world).unwrap().world().grid;
    let ledger = check_ledger(&check, &grid, BotsSummary::acknowledged(&reports)).unwrap();
    let summary = summary.with_ledger(ledger.clone());
    println!("{summary}");
    assert!(summary.ok(), "{summary}");
    assert_eq!(summary.checked, 9, "every bot checked against the world function + edits");
    assert!(summary.reconnects >= 3, "the dead edge's bots resumed elsewhere: {summary}");
    assert!(ledger.acknowledged >= 20, "edits went on being acknowledged: {summary}");
    assert_eq!((ledger.lost, ledger.duplicated), (0, 0));
    assert!(summary.fanout.as_ref().is_some_and(|f| f.visible().is_some()), "edits reached bots of other edges");
    drop(edges);
}

/// Edits a watch told of.
#[derive(Default)]
struct Seen(std::sync::Mutex<Vec<canopy_server::edits::StoredEdit>>);

impl canopy_server::edits::EditWatcher for Seen {
    fn edited(&self, e: canopy_server::edits::StoredEdit) {
        self.0.lock().unwrap().push(e);
    }
}

#[test]
fn a_writer_behind_a_watch_never_takes_a_version_twice_the_store_passes_the_suite_and_reads_past_deleted_races() {
    use canopy_protocol::InstanceRecord;
    use canopy_server::edits::{CellEdit, EditStore, EditStoreError, StoredEdit};
    use std::time::{Duration, Instant};

    let cluster = Cluster::up(2);
    let cfg = NatsConfig { servers: cluster.urls(), world: format!("stale-test-{}", std::process::id()), replicas: 3 };
    let (a, b) = (NatsEditStore::connect(cfg.clone()).unwrap(), NatsEditStore::connect(cfg).unwrap());
    let c = CellCoord::new(3, 4);
    let plant = |version: u32, index: u16| StoredEdit {
        cell: c,
        version,
        op: CellEdit::Plant { index, record: InstanceRecord::new(0, index, 9), params: vec![] },
    };
    assert!(b.load(c).unwrap().is_empty());
    let seen = Arc::new(Seen::default());
    b.watch(c, seen.clone());
    a.append(&[plant(1, 5)]).unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    while seen.0.lock().unwrap().is_empty() {
        assert!(Instant::now() < deadline, "B's watch never told of A's edit");
        std::thread::sleep(Duration::from_millis(20));
    }
    // B's writer has not seen the watch's news yet (its overlay is at version 0): its version 1 is a conflict,
    // not a second version 1 naming A's edit as the cell's last.
    assert!(matches!(b.append(&[plant(1, 5)]), Err(EditStoreError::Conflict { version: 1, .. })));
    // Read again, B writes on top of A's edit.
    assert_eq!(b.load(c).unwrap().len(), 1);
    b.append(&[plant(2, 6)]).unwrap();
    let versions: Vec<u32> = a.load(c).unwrap().iter().map(|e| e.version).collect();
    assert_eq!(versions, [1, 2]);
    // A group's edits of a cell are one message (a run), and a cell read again reads only its new messages: 20
    // more edits in 4 groups, then read twice.
    let reads = || a.metrics().log_reads.load(std::sync::atomic::Ordering::Relaxed);
    let more: Vec<StoredEdit> = (3..23).map(|v| plant(v, 4 + v as u16)).collect();
    for group in more.chunks(5) {
        b.append(group).unwrap();
    }
    let before = reads();
    assert_eq!(a.load(c).unwrap().len(), 22);
    assert_eq!(reads() - before, 4, "the 4 new messages, not the cell's 6");
    assert_eq!(a.load(c).unwrap(), b.load(c).unwrap());
    assert_eq!(reads() - before, 4, "nothing new: nothing read");
    // A lost race that nats-server before 2.9.21 lets through, as a run (versions 20..=25 after the cell's 22, not
    // yet taken out by its writer): readers and watches skip the whole run, and the next version follows 22.
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let cfg = b.config().clone();
    rt.block_on(async {
        let client = async_nats::connect(cfg.servers[0].as_str()).await.unwrap();
        let js = async_nats::jetstream::new(client);
        let mut headers = async_nats::HeaderMap::new();
        headers.insert("Canopy-Run", "1");
        let race: Vec<StoredEdit> = (20..26).map(|v| plant(v, 900 + v as u16)).collect();
        let bytes = canopy_server::edits::encode_run(&race);
        js.publish_with_headers(cfg.subject(c), headers, bytes.into()).await.unwrap().await.unwrap();
    });
    // A writer that meets the race reads the cell again, which names the race as the subject's last message.
    assert!(matches!(a.append(&[plant(23, 50)]), Err(EditStoreError::Conflict { version: 23, .. })));
    assert_eq!(a.load(c).unwrap().len(), 22);
    a.append(&[plant(23, 50)]).unwrap();
    let versions: Vec<u32> = b.load(c).unwrap().iter().map(|e| e.version).collect();
    assert_eq!(versions, (1..=23).collect::<Vec<u32>>(), "the lost race is skipped");
    let deadline = Instant::now() + Duration::from_secs(20);
    while seen.0.lock().unwrap().last().map(|e| e.version) != Some(23) {
        assert!(Instant::now() < deadline, "B's watch never told of version 23");
        std::thread::sleep(Duration::from_millis(20));
    }
    let told: Vec<(u32, u16)> = seen.0.lock().unwrap().iter().map(|e| (e.version, e.op.index())).collect();
    let expected: Vec<(u32, u16)> = a.load(c).unwrap().iter().map(|e| (e.version, e.op.index())).collect();
    assert_eq!(told, expected, "the watch tells every version once, in order, and never the lost race");

    // The JetStream store passes the suite every edit store passes (a world of its own: an empty stream).
    let fresh =
        NatsConfig { servers: cluster.urls(), world: format!("suite-test-{}", std::process::id()), replicas: 3 };
    canopy_server::edits::suite::check(&NatsEditStore::connect(fresh).unwrap());

    a_cell_whose_last_message_is_a_deleted_lost_race_reads_whole(&cluster);
}
