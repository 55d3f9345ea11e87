//! Streaming over real QUIC on loopback (port 0): `canopy-server` on the default world, several clients and bots.
//! Every bot ends holding exactly the instances of its area of interest (checked against the world), each species
//! once; a reconnecting client with its cache receives no species again; malformed, oversized and out-of-order
//! input closes that one connection with a reason while the others carry on; certificates are pinned.

use std::net::SocketAddr;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use canopy_client::cache::{CacheLimits, SpeciesCache};
use canopy_client::expand::{ExpandWorld, Expander};
use canopy_client::net::{endpoint, tls};
use canopy_client::state::ClientState;
use canopy_client::{ClientError, ConnectConfig, Connection, Trust};
use canopy_harness::bots::{self, BotsConfig, BotsSummary, PathKind, Progress};
use canopy_protocol::aoi::Viewpoint;
use canopy_protocol::frame::frame;
use canopy_protocol::messages::{CellMode, ClientHandshake, Hello, ServerMsgKind, Welcome};
use canopy_protocol::{ClientMsg, CloseCode, SpeciesGraph};
use canopy_server::session::{SessionConfig, WorldStore};
use canopy_server::{CellCache, CellCacheConfig, ServeOptions, Served, Server, ServerConfig, serve_store};
use canopy_test_support::{forest, pinned};
use canopy_worlds::world::World;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The server's store as `canopy-server` runs it: cells expanded on demand by worker threads, here into a cache
/// (2 MiB) smaller than the world, so bots walking and teleporting also exercise eviction and re-expansion.
fn store() -> Arc<dyn WorldStore> {
    static STORE: OnceLock<Arc<dyn WorldStore>> = OnceLock::new();
    Arc::clone(STORE.get_or_init(|| {
        let cfg = CellCacheConfig { limit_bytes: 2 << 20, workers: 2, ..CellCacheConfig::default() };
        CellCache::new((**forest()).clone(), cfg).expect("the default world builds a store").shared()
    }))
}

async fn start_server() -> Served {
    let cfg = ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        metrics: Some("127.0.0.1:0".parse().unwrap()),
        session: SessionConfig { handshake_timeout: Duration::from_secs(3), ..SessionConfig::default() },
        ..ServerConfig::default()
    };
    serve_store(store(), ServeOptions { server: cfg, ..ServeOptions::default() }).await.expect("server starts")
}

fn local() -> SocketAddr {
    "127.0.0.1:0".parse().unwrap()
}

/// A client at `position` with a small area of interest, complete.
async fn complete_client(server: &Server, position: [f32; 2], cache: Option<Arc<SpeciesCache>>) -> Connection {
    let ep = endpoint(local()).unwrap();
    let mut c = Connection::connect(&ep, &pinned(server), cache, |_| Viewpoint::at(0, position, 100.0)).await.unwrap();
    c.wait_complete(Duration::from_secs(60)).await.unwrap();
    c
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bots_on_every_path_end_holding_exactly_their_area_of_interest() {
    let server = start_server().await;
    let progress = Arc::new(Progress::default());
    let mut runs = vec![];
    // 20 bots (the CI-sized load run): five on each kind of path; those walking a line or teleporting expand their
    // cells themselves (one expander for them all, as in `canopy bots`), the others take records.
    let expander = Expander::new(2, 8 << 20);
    for (i, path) in [PathKind::Line, PathKind::Circle, PathKind::Random, PathKind::Teleport].into_iter().enumerate() {
        let mut connect = pinned(&server);
        if matches!(path, PathKind::Line | PathKind::Teleport) {
            connect.expander = Some(Arc::clone(&expander));
        }
        let mut cfg = BotsConfig::new(5, connect);
        cfg.path = path;
        cfg.speed = 25.0;
        cfg.duration = Duration::from_secs(if path == PathKind::Teleport { 10 } else { 5 });
        cfg.radius = 120.0;
        cfg.seed = 100 * i as u64;
        cfg.verify = Some(Arc::clone(forest()));
        runs.push(tokio::spawn(bots::run(cfg, Arc::clone(&progress))));
    }
    let mut reports = vec![];
    for r in runs {
        reports.extend(r.await.unwrap().unwrap());
    }
    let summary = BotsSummary::new(&reports, Duration::ZERO);
    assert!(summary.ok(), "{summary}");
    assert_eq!(summary.verified, 20, "{summary}");
    for r in &reports {
        assert_eq!(r.species_duplicates, 0);
        assert!(r.held > 0 && !r.latencies.is_empty(), "bot {} {r:?}", r.id);
        // Each species at most once per bot, and only species its area of interest needed.
        assert!(r.species_received as usize <= forest().species.len());
    }
    assert!(summary.batch_bytes_per_record <= 8.0, "{summary}");
    let m = server.metrics();
    assert_eq!(m.sessions.load(Relaxed), 20);
    assert!(m.records.load(Relaxed) >= summary.records);
    server.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reconnecting_client_is_sent_no_species_again() {
    let server = start_server().await;
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("cache");
    let open = || Arc::new(SpeciesCache::open(&dir, CacheLimits::default()).unwrap());
    let first = complete_client(&server, [0.0, 0.0], Some(open())).await;
    let received = first.state().stats().species_received;
    assert!(received >= 2, "the valley floor needs several species, got {received}");
    assert_eq!(received as usize, first.state().species_held());
    let held_first: usize = first.state().record_count();
    first.close();
    // A new session, a new cache object on the same directory: the species come from disk.
    let species_before = server.metrics().messages[ServerMsgKind::Species].load(Relaxed);
    let again = complete_client(&server, [0.0, 0.0], Some(open())).await;
    assert_eq!(again.state().stats().species_received, 0, "species were sent again");
    assert_eq!(server.metrics().messages[ServerMsgKind::Species].load(Relaxed), species_before);
    assert_eq!(again.state().record_count(), held_first);
    bots::verify(again.state(), forest()).unwrap();
    again.close();
    server.shutdown(Duration::from_secs(1)).await;
}

/// Open a raw connection, write `bytes` on the control stream, and return how the server closed it.
async fn misbehave(server: &Server, bytes: Vec<u8>) -> (Option<CloseCode>, String) {
    let ep = endpoint(local()).unwrap();
    let conn = ep.connect_with(tls::client_config(Trust::Insecure).unwrap(), server.local_addr(), "localhost").unwrap();
    let conn = conn.await.unwrap();
    let (mut send, _recv) = conn.open_bi().await.unwrap();
    if !bytes.is_empty() {
        let _ = send.write_all(&bytes).await;
    }
    match tokio::time::timeout(Duration::from_secs(20), conn.closed()).await.expect("server closes in time") {
        quinn::ConnectionError::ApplicationClosed(c) => {
            (CloseCode::from_code(c.error_code.into_inner()), String::from_utf8_lossy(&c.reason).into_owned())
        }
        e => panic!("expected an application close, got {e}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_closes_that_connection_with_a_reason_and_the_others_carry_on() {
    let server = start_server().await;
    let mut good = vec![];
    for p in [[-300.0, 200.0], [0.0, 0.0], [400.0, -400.0]] {
        good.push(complete_client(&server, p, None).await);
    }
    let hello = frame(&ClientMsg::hello("x").encode());
    let cases: Vec<(Vec<u8>, CloseCode, &str)> = vec![
        (frame(&[0xff, 0xff, 0xff, 0xff]), CloseCode::Malformed, "malformed message"),
        ((1u32 << 20).to_le_bytes().to_vec(), CloseCode::TooLarge, "exceeds the limit"),
        (frame(&[0; 2000]), CloseCode::TooLarge, "exceeds the limit"),
        (
            frame(&ClientMsg::viewpoint(Viewpoint::at(1, [0.0, 0.0], 50.0)).encode()),
            CloseCode::OutOfOrder,
            "not legal in phase Start",
        ),
        ([hello.clone(), hello.clone()].concat(), CloseCode::OutOfOrder, "hello is not legal in phase Welcomed"),
        (
            frame(
                &ClientMsg::Handshake(ClientHandshake::Hello(Hello {
                    version: 99,
                    client: "future".into(),
                    token: None,
                }))
                .encode(),
            ),
            CloseCode::Version,
            "client speaks protocol version 99",
        ),
        (
            [hello.clone(), frame(&ClientMsg::ready(vec![200], Viewpoint::at(0, [0.0, 0.0], 50.0)).encode())].concat(),
            CloseCode::Invalid,
            "not in the table",
        ),
        (vec![], CloseCode::Timeout, "no control stream"),
    ];
    let mut tasks = vec![];
    for (bytes, code, reason) in cases {
        tasks.push((code, reason, misbehave(&server, bytes)));
    }
    for (code, reason, task) in tasks {
        let (got, why) = task.await;
        assert_eq!(got, Some(code), "{why}");
        assert!(why.contains(reason), "expected `{reason}` in `{why}`");
    }
    // The well-behaved clients carry on: they move, and their areas of interest fill again.
    for (i, c) in good.iter_mut().enumerate() {
        c.set_viewpoint(Viewpoint::at(0, [100.0 * i as f32, 300.0], 100.0)).await.unwrap();
        c.wait_complete(Duration::from_secs(60)).await.unwrap();
        bots::verify(c.state(), forest()).unwrap();
    }
    let m = server.metrics();
    assert_eq!(m.closed[CloseCode::Malformed as usize].load(Relaxed), 1);
    assert_eq!(m.closed[CloseCode::TooLarge as usize].load(Relaxed), 2);
    assert_eq!(m.closed[CloseCode::OutOfOrder as usize].load(Relaxed), 2);
    for _ in 0..100 {
        if m.clients.load(Relaxed) == 3 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(m.clients.load(Relaxed), 3, "the misbehaving connections are gone, the good ones stay");
    for c in good {
        c.close();
    }
    server.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_certificate_is_pinned_by_its_fingerprint() {
    let server = start_server().await;
    let ep = endpoint(local()).unwrap();
    let wrong = Trust::pinned(&"00".repeat(32)).unwrap();
    let cfg = ConnectConfig::new(server.local_addr(), wrong);
    let err = Connection::connect(&ep, &cfg, None, |_| Viewpoint::at(0, [0.0, 0.0], 10.0)).await.unwrap_err();
    assert!(matches!(err, ClientError::Lost(_)), "{err}");
    let cfg = ConnectConfig::new(server.local_addr(), Trust::Insecure);
    let c = Connection::connect(&ep, &cfg, None, |_| Viewpoint::at(0, [0.0, 0.0], 10.0)).await.unwrap();
    c.close();
    assert!(Trust::pinned("not hex").is_none());
    server.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_metrics_endpoint_serves_prometheus_text_and_idle_sockets_do_not_block_it() {
    let server = start_server().await;
    let c = complete_client(&server, [0.0, 0.0], None).await;
    server.metrics().tick(std::time::Instant::now());
    let mut sock = tokio::net::TcpStream::connect(server.metrics_addr().unwrap()).await.unwrap();
    sock.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n").await.unwrap();
    let mut body = String::new();
    sock.read_to_string(&mut body).await.unwrap();
    assert!(body.starts_with("HTTP/1.1 200 OK"), "{body}");
    assert!(body.contains("Content-Type: text/plain; version=0.0.4"));
    assert!(body.contains("canopy_clients 1"), "{body}");
    let records = c.state().stats().records;
    assert!(body.contains(&format!("canopy_records_sent_total {records}")), "{body}");
    assert!(body.contains("canopy_sent_bytes_total{class=\"cells\"}"));
    assert!(body.contains("canopy_records_per_second"));
    // The cell cache's families: the client's cells were expanded by the workers (or found cached).
    let value = |name: &str| -> u64 {
        let line =
            body.lines().find(|l| l.starts_with(&format!("{name} "))).unwrap_or_else(|| panic!("{name}: {body}"));
        line[name.len() + 1..].parse().unwrap()
    };
    assert!(value("canopy_cell_expansions_total") > 0, "{body}");
    assert!(value("canopy_cell_cache_hits_total") > 0, "{body}");
    assert!(value("canopy_cell_cache_bytes") <= value("canopy_cell_cache_limit_bytes"), "{body}");
    assert!(value("canopy_cell_cache_cells") > 0, "{body}");
    assert!(value("canopy_cell_expansion_p99_microseconds") >= value("canopy_cell_expansion_p50_microseconds"));
    assert!(body.contains("canopy_cell_expansion_seconds_bucket{le=\"+Inf\"}"), "{body}");
    assert!(body.contains("canopy_cell_expansions_per_second"), "{body}");
    // Idle sockets that never send a request do not keep a scraper out: 40 held open, then one that asks.
    let mut idle = Vec::new();
    for _ in 0..40 {
        idle.push(tokio::net::TcpStream::connect(server.metrics_addr().unwrap()).await.unwrap());
    }
    let scraped = tokio::time::timeout(Duration::from_secs(2), async {
        let mut sock = tokio::net::TcpStream::connect(server.metrics_addr().unwrap()).await.unwrap();
        sock.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n").await.unwrap();
        let mut body = String::new();
        sock.read_to_string(&mut body).await.unwrap();
        body
    })
    .await
    .expect("answered while 40 idle sockets are open");
    assert!(scraped.starts_with("HTTP/1.1 200 OK"), "{scraped}");
    drop(idle);
    c.close();
    server.shutdown(Duration::from_secs(1)).await;
}

/// A server on a cell cache of its own (nothing expanded yet), and its store, whose counters tell how many cells
/// the server expanded.
async fn server_on_own_cache() -> (Served, Arc<dyn WorldStore>) {
    let cfg = CellCacheConfig { limit_bytes: 64 << 20, workers: 2, ..CellCacheConfig::default() };
    let store = CellCache::new((**forest()).clone(), cfg).expect("the default world builds a store").shared();
    let server_cfg = ServerConfig { listen: local(), ..ServerConfig::default() };
    let served = serve_store(Arc::clone(&store), ServeOptions { server: server_cfg, ..ServeOptions::default() })
        .await
        .expect("server starts");
    (served, store)
}

/// A client that expands its cells, with `expander`, complete at `position`.
async fn expanding_client(server: &Server, expander: &Arc<Expander>, state: ClientState) -> Connection {
    let ep = endpoint(local()).unwrap();
    let mut cfg = pinned(server);
    cfg.expander = Some(Arc::clone(expander));
    let place = |_: &Welcome| Viewpoint::at(0, [0.0, 0.0], 100.0);
    let mut c = Connection::connect_resuming(&ep, &cfg, None, state, place).await.unwrap();
    c.wait_complete(Duration::from_secs(60)).await.unwrap();
    c
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_expands_its_cells_is_sent_no_records_and_holds_exactly_the_world() {
    let (server, store) = server_on_own_cache().await;
    let expander = Expander::new(2, 8 << 20);
    let c = expanding_client(&server, &expander, ClientState::new()).await;
    assert_eq!(c.state().cell_mode(), CellMode::Expand { have_function: false });
    bots::verify(c.state(), forest()).unwrap();
    let frames = c.frame_bytes_received();
    assert_eq!(frames[ServerMsgKind::Cells], 0, "records were sent to a client that expands");
    assert!(frames[ServerMsgKind::Grant] > 0 && frames[ServerMsgKind::Function] > 0);
    let stats = c.state().stats().clone();
    assert!(stats.grants >= 4 && stats.records_expanded > 100, "{stats:?}");
    assert_eq!(stats.species_received as usize, c.state().species_held());
    // The server expanded a cell only to check a digest.
    let expanded = store.cache_metrics().unwrap().misses.load(Relaxed);
    assert!(expanded <= stats.digests, "the server expanded {expanded} cells for {} digests", stats.digests);
    c.close();
    // A second client of the same process holds the world function already: it is not sent again.
    let again = expanding_client(&server, &expander, ClientState::new()).await;
    assert_eq!(again.state().cell_mode(), CellMode::Expand { have_function: true });
    assert_eq!(again.frame_bytes_received()[ServerMsgKind::Function], 0);
    bots::verify(again.state(), forest()).unwrap();
    // A load generator's client takes the same grants and expands nothing: complete at once, no records held.
    let ep = endpoint(local()).unwrap();
    let mut thin = pinned(&server);
    thin.grants_only = true;
    let place = |_: &Welcome| Viewpoint::at(0, [0.0, 0.0], 100.0);
    let mut thin = Connection::connect(&ep, &thin, None, place).await.unwrap();
    thin.wait_complete(Duration::from_secs(60)).await.unwrap();
    assert_eq!(thin.state().cells().len(), again.state().cells().len());
    assert_eq!((thin.state().record_count(), thin.frame_bytes_received()[ServerMsgKind::Cells]), (0, 0));
    thin.close();
    again.close();
    server.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_whose_expansion_differs_is_caught_by_its_digests_and_served_records() {
    let (server, _store) = server_on_own_cache().await;
    let expander = Expander::new(2, 8 << 20);
    // The server's world function with another seed, adopted under the server's hash: this client's trees stand
    // elsewhere.
    let plain = complete_client(&server, [0.0, 0.0], None).await;
    let w = Arc::clone(plain.welcome());
    plain.close();
    let manifest = forest().function.replace("seed 0x5eed_f0e5", "seed 0x5eed_f0e6");
    assert_ne!(&*forest().function, manifest, "the forest's seed statement changed");
    let species: Vec<_> = forest().species.iter().map(|s| s.graph.clone()).collect();
    let terrain = SpeciesGraph::decode(w.world.terrain.graph.as_ref().unwrap()).unwrap();
    let world = World::from_function("forest", &manifest, &species, Some(&terrain)).unwrap();
    expander.adopt(ExpandWorld::new(w.world.function.unwrap(), Arc::new(world), w.world.grid));
    let mut state = ClientState::new();
    state.set_digest_every(1);
    let c = expanding_client(&server, &expander, state).await;
    // Every cell was reported; those that differ came again as records, and the client ends holding the world.
    let mut c = c;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    while bots::verify(c.state(), forest()).is_err() {
        assert!(tokio::time::Instant::now() < deadline, "the differing cells were never served as records");
        let _ = tokio::time::timeout(Duration::from_millis(200), c.next_event()).await;
    }
    assert!(server.metrics().digest_mismatches.load(Relaxed) > 0);
    assert!(c.frame_bytes_received()[ServerMsgKind::Cells] > 0);
    c.close();
    server.shutdown(Duration::from_secs(1)).await;
}
