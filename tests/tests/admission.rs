//! Admission over real QUIC on loopback: half-open handshakes from one source (Initials that are never followed
//! up, as a spoofing flood sends them) hold no client slots and do not stop another source from connecting (it is
//! asked for a Retry and gets in); a source over its share is refused; a session that holds a slot without
//! streaming is closed while the server is near capacity, and kept while it is not; a session whose task panics
//! gives its slot back. A server with two endpoints (UDP sockets on one port) carries sessions on both, counts its
//! handshakes and client slots for the whole server, and a second server cannot take its port. A client refused as
//! full asks again after a pause and gets the slot once it is free.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;

use canopy_client::net::endpoint;
use canopy_client::{ClientError, ConnectConfig, Connection, Trust};
use canopy_protocol::CloseCode;
use canopy_protocol::aoi::Viewpoint;
use canopy_server::Refusal;
use canopy_server::session::SessionConfig;
use canopy_server::{AdmissionConfig, ServeOptions, Served, Server, ServerConfig, serve_store};
use canopy_test_support::{forest_store, pinned};

async fn start_server(admission: AdmissionConfig, idle_slot: Duration) -> Served {
    start_on("127.0.0.1:0", 1, admission, idle_slot).await.expect("server starts")
}

/// A server of the default world on `listen` with `endpoints` UDP sockets.
async fn start_on(
    listen: &str,
    endpoints: usize,
    admission: AdmissionConfig,
    idle_slot: Duration,
) -> Result<Served, canopy_server::ServeError> {
    let cfg = ServerConfig {
        listen: listen.parse().unwrap(),
        endpoints,
        session: SessionConfig { handshake_timeout: Duration::from_secs(5), ..SessionConfig::default() },
        admission,
        idle_slot,
        ..ServerConfig::default()
    };
    serve_store(forest_store(), ServeOptions { server: cfg, ..ServeOptions::default() }).await
}

/// A client bound to `from` (any loopback address), connected with a small area of interest.
async fn connect_from(server: &Server, from: &str) -> Result<Connection, ClientError> {
    let ep = endpoint(from.parse::<SocketAddr>().unwrap()).unwrap();
    Connection::connect(&ep, &pinned(server), None, |_| Viewpoint::at(0, [0.0, 0.0], 60.0)).await
}

/// How the connection ends, if it does within `limit` (events until then are taken and dropped).
async fn ended_within(c: &mut Connection, limit: Duration) -> Result<ClientError, tokio::time::error::Elapsed> {
    tokio::time::timeout(limit, async {
        loop {
            if let Err(e) = c.next_event().await {
                return e;
            }
        }
    })
    .await
}

/// A fresh client Initial packet: a real client connects to a UDP socket that never answers, and its first
/// datagram is kept.
async fn initial_packet() -> Vec<u8> {
    let trap = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let cfg = ConnectConfig::new(trap.local_addr().unwrap(), Trust::Insecure);
    let attempt = tokio::spawn(async move {
        let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
        Connection::connect(&ep, &cfg, None, |_| Viewpoint::at(0, [0.0, 0.0], 60.0)).await
    });
    let mut buf = vec![0u8; 2048];
    let (n, _) = tokio::time::timeout(Duration::from_secs(5), trap.recv_from(&mut buf)).await.unwrap().unwrap();
    attempt.abort();
    buf.truncate(n);
    buf
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn half_open_handshakes_from_one_source_do_not_lock_out_another() {
    let admission = AdmissionConfig { max_clients: 4, max_handshakes: 16, retry_above: 3, max_per_source: 6 };
    // Two endpoints: the flood lands on both, and the handshake and client limits count for the whole server.
    let server = start_on("127.0.0.1:0", 2, admission, Duration::from_secs(120)).await.expect("server starts");
    assert_eq!(server.endpoints(), 2);
    // Twelve half-open handshakes from 127.0.0.1: each Initial sent once from its own port, never followed up.
    let mut flood = Vec::new();
    for _ in 0..12 {
        let initial = initial_packet().await;
        let s = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        s.send_to(&initial, server.local_addr()).await.unwrap();
        flood.push(s);
    }
    let m = Arc::clone(server.metrics());
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    // The server answers each Initial in turn: wait until it has seen them all.
    while (m.handshakes.load(Relaxed) < 3 || m.retries.load(Relaxed) < 9) && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(m.handshakes.load(Relaxed), 3, "three take handshake slots, the rest are asked for a Retry");
    assert_eq!(m.clients.load(Relaxed), 0, "a half-open handshake holds no client slot");
    assert!(m.retries.load(Relaxed) >= 9, "retries: {}", m.retries.load(Relaxed));
    // Honest clients from other sources answer the Retry and get in, up to the client slots.
    let mut honest = Vec::new();
    for from in ["127.0.0.2:0", "127.0.0.3:0", "127.0.0.4:0", "127.0.0.5:0"] {
        let mut c = connect_from(&server, from).await.unwrap_or_else(|e| panic!("{from}: {e}"));
        c.wait_complete(Duration::from_secs(30)).await.unwrap();
        honest.push(c);
    }
    assert_eq!(m.clients.load(Relaxed), 4);
    // Every client slot taken: the next one is refused, however it asks.
    assert!(connect_from(&server, "127.0.0.6:0").await.is_err());
    assert!(m.refused[Refusal::Full as usize].load(Relaxed) >= 1, "refused as full");
    drop(flood);
    server.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_endpoints_of_one_server_both_carry_sessions() {
    let admission = AdmissionConfig { max_clients: 64, max_handshakes: 64, retry_above: 64, max_per_source: 64 };
    let server = start_on("127.0.0.1:0", 2, admission, Duration::from_secs(120)).await.expect("server starts");
    // The kernel spreads clients over the sockets by source port: 16 clients all on one of two has odds 2⁻¹⁵.
    let mut clients = Vec::new();
    for _ in 0..16 {
        let mut c = connect_from(&server, "127.0.0.1:0").await.expect("connects");
        c.wait_complete(Duration::from_secs(30)).await.expect("its area of interest completes");
        clients.push(c);
    }
    let m = Arc::clone(server.metrics());
    let per: Vec<u64> = m.endpoint_clients.iter().map(|n| n.load(Relaxed)).collect();
    assert_eq!(per.len(), 2);
    assert_eq!(per.iter().sum::<u64>(), 16, "{per:?}");
    assert!(per.iter().all(|&n| n > 0), "both endpoints carry sessions: {per:?}");
    assert!(m.render().contains("canopy_endpoint_clients{endpoint=\"1\"}"));
    // Sessions on both sockets go on streaming: every client still answers with a complete area of interest after
    // a move.
    for c in &mut clients {
        c.set_viewpoint(Viewpoint::at(1, [200.0, 150.0], 60.0)).await.expect("a viewpoint");
    }
    for c in &mut clients {
        c.wait_complete(Duration::from_secs(30)).await.expect("complete after the move");
    }
    // Another server cannot share the port (its reuse-port sockets included).
    let taken = server.local_addr().to_string();
    let again = start_on(&taken, 2, AdmissionConfig::default(), Duration::from_secs(120)).await;
    assert!(again.is_err(), "a second server bound {taken}");
    drop(clients);
    server.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_refused_as_full_asks_again_and_gets_the_freed_slot() {
    let admission = AdmissionConfig { max_clients: 1, ..AdmissionConfig::default() };
    let server = start_server(admission, Duration::from_secs(120)).await;
    let holder = connect_from(&server, "127.0.0.1:0").await.expect("the one slot");
    // The slot frees in 1.5 s; meanwhile the second client is refused as full and asks again.
    let release = tokio::spawn(async move {
        tokio::time::sleep(Duration::from_millis(1500)).await;
        drop(holder);
    });
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let started = std::time::Instant::now();
    let refused = Connection::connect(&ep, &pinned(&server), None, |_| Viewpoint::at(0, [0.0, 0.0], 60.0)).await;
    assert!(refused.as_ref().is_err_and(ClientError::busy), "a full server says it is busy: {:?}", refused.err());
    let mut c = Connection::connect_any(&ep, &pinned(&server), None, |_| Viewpoint::at(0, [0.0, 0.0], 60.0))
        .await
        .expect("connect_any asks again until the slot is free");
    assert!(started.elapsed() >= Duration::from_millis(1400), "in after {:?}", started.elapsed());
    c.wait_complete(Duration::from_secs(30)).await.unwrap();
    assert!(server.metrics().refused[Refusal::Full as usize].load(Relaxed) >= 2, "refused as full, then asked again");
    release.await.unwrap();
    server.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_source_gets_its_share_and_no_more() {
    let admission = AdmissionConfig { max_clients: 10, max_handshakes: 16, retry_above: 16, max_per_source: 2 };
    let server = start_server(admission, Duration::from_secs(120)).await;
    let a = connect_from(&server, "127.0.0.7:0").await.unwrap();
    let b = connect_from(&server, "127.0.0.7:0").await.unwrap();
    assert!(connect_from(&server, "127.0.0.7:0").await.is_err(), "a third connection from one source");
    assert!(server.metrics().refused[Refusal::PerSource as usize].load(Relaxed) >= 1, "refused for the source's share");
    let c = connect_from(&server, "127.0.0.8:0").await.expect("another source is admitted");
    drop((a, b, c));
    server.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_that_only_holds_its_slot_is_closed_near_capacity() {
    // Near capacity (2 of 2 slots), sessions that send no viewpoint for a second are closed with a reason.
    let admission = AdmissionConfig { max_clients: 2, ..AdmissionConfig::default() };
    let server = start_server(admission, Duration::from_secs(1)).await;
    let mut idle = connect_from(&server, "127.0.0.1:0").await.unwrap();
    let mut walker = connect_from(&server, "127.0.0.1:0").await.unwrap();
    // The other client walks (a viewpoint every 200 ms), so only the idle one holds a slot without streaming.
    let walking = tokio::spawn(async move {
        for i in 0..60 {
            tokio::time::sleep(Duration::from_millis(200)).await;
            if walker.set_viewpoint(Viewpoint::at(0, [i as f32, 0.0], 60.0)).await.is_err() {
                return false;
            }
        }
        true
    });
    let closed = ended_within(&mut idle, Duration::from_secs(10)).await.expect("closed within 10 s");
    assert!(matches!(closed, ClientError::Closed { code: Some(CloseCode::Full), .. }), "{closed}");
    assert!(closed.to_string().contains("no viewpoint"), "{closed}");
    assert!(walking.await.unwrap(), "the walking client was kept");
    // Well below capacity, the same idleness is kept.
    let roomy = AdmissionConfig { max_clients: 100, ..AdmissionConfig::default() };
    let server2 = start_server(roomy, Duration::from_secs(1)).await;
    let mut kept = connect_from(&server2, "127.0.0.1:0").await.unwrap();
    kept.wait_complete(Duration::from_secs(30)).await.unwrap();
    let quiet = ended_within(&mut kept, Duration::from_secs(3)).await;
    assert!(quiet.is_err(), "not closed: {quiet:?}");
    server.shutdown(Duration::from_secs(1)).await;
    server2.shutdown(Duration::from_secs(1)).await;
}

/// A store whose cells panic while `armed` (a bug reached by data: the session's task dies mid-stream).
struct Panicking {
    inner: Arc<dyn canopy_server::session::WorldStore>,
    armed: std::sync::atomic::AtomicBool,
}

impl canopy_server::session::WorldStore for Panicking {
    fn head(&self) -> &canopy_server::session::StoreHead {
        self.inner.head()
    }
    fn cell(
        &self,
        c: canopy_protocol::CellCoord,
        waker: Option<&Arc<dyn canopy_server::session::CellWaker>>,
    ) -> canopy_server::session::CellState {
        assert!(!self.armed.load(Relaxed), "a session met cell {c:?} while the store is armed");
        self.inner.cell(c, waker)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_whose_task_panics_gives_its_slot_back() {
    let store = Arc::new(Panicking { inner: forest_store(), armed: true.into() });
    let cfg = ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        admission: AdmissionConfig { max_clients: 1, ..AdmissionConfig::default() },
        ..ServerConfig::default()
    };
    let shared = Arc::clone(&store) as Arc<dyn canopy_server::session::WorldStore>;
    let server = serve_store(shared, ServeOptions { server: cfg, ..ServeOptions::default() }).await.unwrap();
    // The one slot's session panics at its first cell; its client sees the connection end.
    let mut doomed = connect_from(&server, "127.0.0.1:0").await.unwrap();
    let ended = ended_within(&mut doomed, Duration::from_secs(10)).await.expect("the connection ends within 10 s");
    assert!(!matches!(ended, ClientError::Closed { code: Some(CloseCode::Full), .. }), "{ended}");
    tokio::time::timeout(Duration::from_secs(5), async {
        while server.metrics().clients.load(Relaxed) != 0 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await
    .expect("the slot is returned");
    // The slot is free again: the next client gets in and streams its area of interest to the end.
    store.armed.store(false, Relaxed);
    let mut next = connect_from(&server, "127.0.0.1:0").await.expect("the freed slot is taken");
    next.wait_complete(Duration::from_secs(30)).await.unwrap();
    server.shutdown(Duration::from_secs(1)).await;
}
