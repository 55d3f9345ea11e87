//! The quinn/tokio driver: a small loop per connection around the sans-IO [`Session`], the UDP sockets with
//! buffers sized for many clients, the metrics endpoint, and graceful shutdown.
//!
//! A server listens on one UDP port with [`ServerConfig::endpoints`] sockets (`SO_REUSEPORT`: the kernel spreads
//! clients over them by their address and port, so a connection's packets always reach the same socket). Each
//! socket has its own quinn endpoint, whose driver task does that socket's I/O and demultiplexing, and its own
//! accept loop; the endpoints share one TLS identity, Retry token key and stateless-reset key, one admission (client
//! slots, handshakes and per-source caps count for the whole server) and one set of counters.
//!
//! Browsers connect to the same port: ALPN `h3` is a WebTransport session (CONNECT to [`WEB_PATH`], answered by
//! `web-transport-quinn` on the connection quinn accepted), ALPN `canopy/1` native QUIC; both become one
//! [`web_transport_quinn::Session`] (a native one through `Session::raw`), so the session loop has one path. A
//! browser is given the short-lived certificate it can pin ([`WebCertificate`]), rotated while the server runs.
//!
//! Per connection: the client opens one bidirectional control stream (hello, ready, viewpoints up; the welcome
//! down); the server opens up to [`SessionConfig::lanes`] unidirectional lanes, ordered streams whose QUIC priority
//! falls with the lane number, and writes each [`Transmit`](canopy_session::Transmit) to the stream the session
//! names. A writer task does the writes (taken from the session's [`Outbox`]) and reports flushed bytes back, which
//! reopens the session's window. Anything wrong in what a client sends closes that one connection with a
//! [`CloseCode`] and a reason; the server carries on.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant, SystemTime};

use canopy_protocol::frame::{FrameDecoder, FrameError};
use canopy_protocol::sync::Locked;
use canopy_protocol::{CloseCode, Phase, netlimits};
use quinn::{ConnectionError, Endpoint, VarInt};
use tokio::sync::{mpsc, watch};
use tracing::{debug, info, warn};
use web_transport_quinn::{SendStream, Session as Link, SessionError, WebTransportError};

use crate::admission::{Admission, AdmissionConfig, Refusal, Verdict};
use crate::editing::{EditJob, EditService};
use crate::http::{WebPage, serve_http};
use crate::metrics::Metrics;
use crate::outbox::Outbox;
use crate::tls::{Identity, IdentityError, WEB_ALPN, WebCertificate};
use canopy_protocol::edit::EditOutcome;
use canopy_session::{CellWaker, WorldStore};
use canopy_session::{SendBudget, Session, SessionConfig, StreamId};

/// UDP socket buffer size: 1,000 concurrent handshakes on loopback overflow the default buffers.
pub(crate) const SOCKET_BUFFER: usize = 4 * 1024 * 1024;

/// Bytes of unacknowledged send data quinn keeps per connection (224 KiB: ~36 Mbit/s at 50 ms round trip).
pub const SEND_WINDOW: u64 = 224 * 1024;

/// Bytes past its window a session may owe its client before the driver stops reading the client's requests. With
/// reads of at most [`netlimits::MAX_CLIENT_FRAME`] bytes, the answers to one read (an edit request of 9 bytes
/// denied in about 60) add at most a few KiB more.
pub const OWED_SLACK: usize = 16 * 1024;

/// The path a browser's WebTransport CONNECT must name; any other is answered 404 and closed.
pub const WEB_PATH: &str = "/canopy";

/// Metrics connections open at once; the next one accepted closes the oldest, so idle sockets cannot keep a scraper
/// out (its request arrives with its connection).
const MAX_METRICS_CONNECTIONS: usize = 16;

/// Page connections open at once (each may be downloading the client's wasm).
const MAX_PAGE_CONNECTIONS: usize = 64;

/// How long a refused WebTransport CONNECT's 404 may take to reach the client before its connection is closed.
const REJECT_GRACE: Duration = Duration::from_secs(1);

/// How often the server checks whether the WebTransport certificate is due for rotation.
const WEB_CERT_CHECK: Duration = Duration::from_secs(3600);

/// How a server runs.
#[derive(Clone, Debug)]
pub struct ServerConfig {
    /// The UDP address to listen on (port 0: any free port).
    pub listen: SocketAddr,
    /// The TCP address of the Prometheus metrics endpoint (`None`: no endpoint).
    pub metrics: Option<SocketAddr>,
    /// Serve the browser client's page over HTTP (`None`: browsers can still connect, from a page served
    /// elsewhere).
    pub web: Option<WebConfig>,
    /// Where the certificate lives (`None`: a fresh in-memory certificate, for tests).
    pub data_dir: Option<PathBuf>,
    /// Per-session behaviour.
    pub session: SessionConfig,
    /// Admission: most clients, handshakes and connections per source; when to ask for a Retry.
    pub admission: AdmissionConfig,
    /// Bytes queued for clients and not yet taken by the transport, across every session, beyond which sessions
    /// pause (`None`: only each session's own window).
    pub send_budget: Option<usize>,
    /// UDP socket send and receive buffer size, bytes.
    pub socket_buffer: usize,
    /// A connection with no traffic for this long is closed.
    pub idle_timeout: Duration,
    /// A session that sent no viewpoint for this long is closed while the server is near capacity (it holds a
    /// client slot without streaming: keep-alive PINGs alone do not keep a slot).
    pub idle_slot: Duration,
    /// The edit pipeline (`None`: the world cannot change; every edit is denied). [`crate::serve`] sets it from
    /// [`crate::ServeOptions::edits`].
    pub edits: Option<Arc<EditService>>,
    /// UDP sockets on the listening port, each with its own QUIC endpoint (0: one per core). More than one needs
    /// `SO_REUSEPORT` (Unix); elsewhere the server opens one.
    pub endpoints: usize,
    /// Send a connection's datagrams in batches of up to ten through one system call (GSO, where the kernel has
    /// it), at the cost of a ~16 KiB buffer kept per connection. Received datagrams are batched (GRO) either way.
    pub segmentation_offload: bool,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            listen: SocketAddr::from(([127, 0, 0, 1], 4433)),
            metrics: None,
            web: None,
            data_dir: None,
            session: SessionConfig::default(),
            admission: AdmissionConfig::default(),
            send_budget: None,
            socket_buffer: SOCKET_BUFFER,
            idle_timeout: Duration::from_secs(30),
            idle_slot: Duration::from_secs(120),
            edits: None,
            endpoints: 1,
            segmentation_offload: false,
        }
    }
}

/// Where the browser client's page is served from.
#[derive(Clone, Debug)]
pub struct WebConfig {
    /// The TCP address of the page (HTTP; a secure context on loopback, behind a TLS proxy elsewhere).
    pub listen: SocketAddr,
    /// The folder `scripts/build-web` writes (`client/web/dist`).
    pub root: PathBuf,
}

/// Why the server could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The certificate could not be loaded or generated.
    #[error(transparent)]
    Identity(#[from] IdentityError),
    /// The socket could not be opened or bound.
    #[error("binding {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// What failed.
        source: std::io::Error,
    },
    /// The TLS configuration is not usable for QUIC.
    #[error("TLS configuration: {0}")]
    Quic(String),
}

/// A running server: its endpoints, their accept loops and the metrics endpoint.
pub struct Server {
    endpoints: Vec<Endpoint>,
    local_addr: SocketAddr,
    metrics_addr: Option<SocketAddr>,
    web_addr: Option<SocketAddr>,
    fingerprint: String,
    identity_generated: bool,
    web_certificate: Arc<WebCertificate>,
    metrics: Arc<Metrics>,
    shutdown: watch::Sender<bool>,
    accept: Vec<tokio::task::JoinHandle<()>>,
    socket_buffers: (usize, usize),
}

impl std::fmt::Debug for Server {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Server").field("local_addr", &self.local_addr).finish()
    }
}

/// `n` UDP sockets bound to `addr` (port 0: one free port for all of them), with send and receive buffers of `size`
/// bytes (as far as the OS allows): more than one share the port through `SO_REUSEPORT`.
///
/// The address is first bound alone, without `SO_REUSEPORT`: that fails as it always did where anything holds the
/// port (another server's reuse-port sockets included), so a second server cannot silently share this one's port.
fn udp_sockets(addr: SocketAddr, size: usize, n: usize) -> std::io::Result<(Vec<std::net::UdpSocket>, (usize, usize))> {
    use socket2::{Domain, Protocol, Socket, Type};
    let open = |reuse: bool| -> std::io::Result<Socket> {
        let socket = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
        if let Err(e) = socket.set_recv_buffer_size(size) {
            warn!("cannot set the UDP receive buffer to {size} bytes: {e}");
        }
        if let Err(e) = socket.set_send_buffer_size(size) {
            warn!("cannot set the UDP send buffer to {size} bytes: {e}");
        }
        #[cfg(unix)]
        if reuse {
            socket.set_reuse_port(true)?;
        }
        #[cfg(not(unix))]
        let _ = reuse;
        Ok(socket)
    };
    let probe = open(false)?;
    probe.bind(&addr.into())?;
    let got = (probe.recv_buffer_size().unwrap_or(0), probe.send_buffer_size().unwrap_or(0));
    if got.0 < size || got.1 < size {
        // Linux caps what a socket may ask for at net.core.rmem_max and wmem_max (208 KiB by default): thousands of
        // clients' handshakes then overflow the buffer, and their packets are lost.
        warn!(
            "the OS granted UDP buffers of {} B (receive) and {} B (send) of the {size} B asked for; with many \
             clients raise net.core.rmem_max and net.core.wmem_max",
            got.0, got.1
        );
    }
    if n <= 1 || cfg!(not(unix)) {
        return Ok((vec![probe.into()], got));
    }
    let bound = probe.local_addr()?;
    drop(probe);
    let sockets = (0..n)
        .map(|_| {
            let s = open(true)?;
            s.bind(&bound)?;
            Ok(s.into())
        })
        .collect::<std::io::Result<Vec<_>>>()?;
    Ok((sockets, got))
}

/// How many endpoints `asked` means here: 0 is one per core; more than one only where `SO_REUSEPORT` is.
fn endpoint_count(asked: usize) -> usize {
    let n = if asked == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { asked };
    if cfg!(unix) { n.clamp(1, MAX_ENDPOINTS) } else { 1 }
}

/// The most endpoints one server opens.
pub const MAX_ENDPOINTS: usize = 256;

fn transport(cfg: &ServerConfig) -> quinn::TransportConfig {
    let mut t = quinn::TransportConfig::default();
    // A native client opens one bidirectional stream (control) and no unidirectional ones. A browser's WebTransport
    // session needs one more bidirectional stream (the CONNECT request) and three unidirectional ones (HTTP/3's
    // control stream and QPACK's two): every connection gets those limits, which cost nothing while unused (what a
    // client may send on streams the server does not read is bounded by the connection's receive window).
    t.max_concurrent_bidi_streams(VarInt::from_u32(2))
        .max_concurrent_uni_streams(VarInt::from_u32(3))
        .stream_receive_window(VarInt::from_u32(64 * 1024))
        .receive_window(VarInt::from_u32(128 * 1024))
        // Send data quinn holds for one connection until it is acknowledged: with the session's window of bytes
        // handed to the writer (`SessionConfig::window`) this bounds what a client that never acknowledges pins.
        .send_window(SEND_WINDOW)
        .max_idle_timeout(cfg.idle_timeout.try_into().ok());
    // With segmentation offload each connection keeps a buffer of ten datagrams (~16 KiB) from its first burst on: a
    // third of what it costs in memory, for lower latency under load at the same CPU (docs/streaming.md).
    t.enable_segmentation_offload(cfg.segmentation_offload);
    t
}

impl Server {
    /// Bind, load or generate the certificate, and start accepting clients of `store`.
    pub(crate) async fn start(store: Arc<dyn WorldStore>, mut cfg: ServerConfig) -> Result<Server, StartError> {
        if let Some(limit) = cfg.send_budget {
            cfg.session.send_budget = Some(SendBudget::new(limit));
        }
        let identity = match &cfg.data_dir {
            Some(dir) => Identity::load_or_generate(dir)?,
            None => Identity::generate()?,
        };
        let web_certificate = Arc::new(WebCertificate::generate(SystemTime::now())?);
        let tls = identity.server_config(&web_certificate)?;
        let crypto =
            quinn::crypto::rustls::QuicServerConfig::try_from(tls).map_err(|e| StartError::Quic(e.to_string()))?;
        let mut server_config = quinn::ServerConfig::with_crypto(Arc::new(crypto));
        server_config.transport_config(Arc::new(transport(&cfg)));
        let bind = |source| StartError::Bind { addr: cfg.listen, source };
        cfg.endpoints = endpoint_count(cfg.endpoints);
        let (sockets, socket_buffers) = udp_sockets(cfg.listen, cfg.socket_buffer, cfg.endpoints).map_err(bind)?;
        // One endpoint configuration (its stateless-reset key) and one server configuration (its Retry token key)
        // for every endpoint: a token or reset made by one is good at all of them.
        let endpoint_config = quinn::EndpointConfig::default();
        let endpoints = sockets
            .into_iter()
            .map(|socket| {
                let runtime = Arc::new(quinn::TokioRuntime);
                Endpoint::new(endpoint_config.clone(), Some(server_config.clone()), socket, runtime)
            })
            .collect::<std::io::Result<Vec<_>>>()
            .map_err(bind)?;
        let local_addr = endpoints[0].local_addr().map_err(bind)?;
        let metrics = Arc::new(Metrics::new(endpoints.len()));
        if let Some(cells) = store.cache_metrics() {
            metrics.attach_cells(cells);
        }
        if let Some(edits) = &cfg.edits {
            metrics.attach_edits(Arc::clone(edits.metrics()));
        }
        let (shutdown, shutdown_rx) = watch::channel(false);
        let metrics_addr = match cfg.metrics {
            Some(addr) => {
                let listener =
                    tokio::net::TcpListener::bind(addr).await.map_err(|source| StartError::Bind { addr, source })?;
                let bound = listener.local_addr().map_err(|source| StartError::Bind { addr, source })?;
                let route = crate::http::metrics_route(Arc::clone(&metrics));
                tokio::spawn(serve_http(listener, "metrics", MAX_METRICS_CONNECTIONS, route, shutdown_rx.clone()));
                Some(bound)
            }
            None => None,
        };
        let web_addr = match &cfg.web {
            Some(web) => {
                let addr = web.listen;
                let bind = |source| StartError::Bind { addr, source };
                let listener = tokio::net::TcpListener::bind(addr).await.map_err(bind)?;
                let bound = listener.local_addr().map_err(bind)?;
                let page = WebPage {
                    root: web.root.clone(),
                    port: local_addr.port(),
                    certificate: Arc::clone(&web_certificate),
                };
                tokio::spawn(serve_http(listener, "page", MAX_PAGE_CONNECTIONS, page.route(), shutdown_rx.clone()));
                Some(bound)
            }
            None => None,
        };
        tokio::spawn(tick_metrics(Arc::clone(&metrics), shutdown_rx.clone()));
        tokio::spawn(rotate_web_certificate(Arc::clone(&web_certificate), shutdown_rx.clone()));
        let admission = Arc::new(std::sync::Mutex::new(Admission::new(cfg.admission.clone())));
        let cfg = Arc::new(cfg);
        let accept = endpoints
            .iter()
            .enumerate()
            .map(|(at, endpoint)| {
                let shared = Shared {
                    store: Arc::clone(&store),
                    cfg: Arc::clone(&cfg),
                    metrics: Arc::clone(&metrics),
                    admission: Arc::clone(&admission),
                    endpoint: at,
                };
                tokio::spawn(accept_loop(endpoint.clone(), shared, shutdown_rx.clone()))
            })
            .collect();
        info!(%local_addr, endpoints = endpoints.len(), ?socket_buffers, "canopy-server listening");
        Ok(Server {
            endpoints,
            local_addr,
            metrics_addr,
            web_addr,
            fingerprint: identity.fingerprint(),
            identity_generated: identity.generated,
            web_certificate,
            metrics,
            shutdown,
            accept,
            socket_buffers,
        })
    }

    /// The UDP address clients connect to.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The metrics endpoint's address, if it has one.
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.metrics_addr
    }

    /// The browser client's page address, if it serves one.
    pub fn web_addr(&self) -> Option<SocketAddr> {
        self.web_addr
    }

    /// The certificate's SHA-256 fingerprint (what clients pin).
    pub fn fingerprint(&self) -> &str {
        &self.fingerprint
    }

    /// The SHA-256 fingerprint of the certificate browsers are given now (ALPN `h3`): what a page passes to
    /// WebTransport's `serverCertificateHashes`. It changes when the certificate rotates.
    pub fn web_fingerprint(&self) -> String {
        self.web_certificate.fingerprint()
    }

    /// The short-lived certificate browsers are given.
    pub fn web_certificate(&self) -> &Arc<WebCertificate> {
        &self.web_certificate
    }

    /// Whether the certificate was generated at this start.
    pub fn identity_generated(&self) -> bool {
        self.identity_generated
    }

    /// The counters.
    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.metrics
    }

    /// The socket buffer sizes the OS granted (receive, send).
    pub fn socket_buffers(&self) -> (usize, usize) {
        self.socket_buffers
    }

    /// How many UDP sockets (QUIC endpoints) the server listens with on its port.
    pub fn endpoints(&self) -> usize {
        self.endpoints.len()
    }

    /// Close every connection with [`CloseCode::Shutdown`] and wait (up to `grace`) for them to go.
    pub async fn shutdown(self, grace: Duration) {
        let _ = self.shutdown.send(true);
        for (accept, endpoint) in self.accept.iter().zip(&self.endpoints) {
            accept.abort();
            endpoint.close(VarInt::from_u32(CloseCode::Shutdown as u32), b"server shutting down");
        }
        let idle = async {
            for endpoint in &self.endpoints {
                endpoint.wait_idle().await;
            }
        };
        let _ = tokio::time::timeout(grace, idle).await;
    }
}

/// What every connection of a server shares, and which endpoint accepted it.
#[derive(Clone)]
struct Shared {
    store: Arc<dyn WorldStore>,
    cfg: Arc<ServerConfig>,
    metrics: Arc<Metrics>,
    admission: Arc<std::sync::Mutex<Admission>>,
    endpoint: usize,
}

async fn accept_loop(endpoint: Endpoint, shared: Shared, mut shutdown: watch::Receiver<bool>) {
    let Shared { metrics, admission, .. } = &shared;
    loop {
        let incoming = tokio::select! {
            i = endpoint.accept() => match i { Some(i) => i, None => break },
            _ = shutdown.changed() => break,
        };
        let peer = incoming.remote_address();
        let validated = incoming.remote_address_validated();
        let verdict = admission.locked().incoming(peer.ip(), validated);
        let refusal = match verdict {
            Verdict::Accept => None,
            Verdict::Retry if incoming.may_retry() => {
                metrics.retries.fetch_add(1, Relaxed);
                let _ = incoming.retry();
                continue;
            }
            // A Retry was asked for but this Initial already carries one: the server is busy.
            Verdict::Retry => Some(Refusal::Busy),
            Verdict::Refuse(r) => Some(r),
        };
        if let Some(r) = refusal {
            metrics.refused(r);
            incoming.refuse();
            continue;
        }
        metrics.connections.fetch_add(1, Relaxed);
        metrics.handshakes.fetch_add(1, Relaxed);
        let shared = shared.clone();
        tokio::spawn(async move {
            let Shared { store, cfg, metrics, admission, endpoint } = shared;
            let lock = || admission.locked();
            let handshake = tokio::time::timeout(cfg.session.handshake_timeout, incoming).await;
            metrics.handshakes.fetch_sub(1, Relaxed);
            let code = match handshake {
                Ok(Ok(conn)) => {
                    // A completed handshake has proved its address: only now does it take a client slot. The slot
                    // is returned when the guard drops: when the session ends, and if its task panics too.
                    if lock().handshake_done(peer.ip(), true) {
                        let _slot = Slot::take(&admission, &metrics, peer.ip(), endpoint);
                        serve_connection(conn, store, &cfg, &metrics, &admission).await
                    } else {
                        conn.close(VarInt::from_u32(CloseCode::Full as u32), b"the server is full");
                        Some(CloseCode::Full)
                    }
                }
                Ok(Err(e)) => {
                    debug!(%peer, "QUIC handshake failed: {e}");
                    lock().handshake_done(peer.ip(), false);
                    None
                }
                Err(_) => {
                    debug!(%peer, "QUIC handshake timed out");
                    lock().handshake_done(peer.ip(), false);
                    Some(CloseCode::Timeout)
                }
            };
            metrics.closed(code);
        });
    }
}

/// An edit's answer on its way back to the session that asked; abandoned once the session has ended.
struct SessionReply {
    tx: mpsc::UnboundedSender<(u32, EditOutcome)>,
    request: u32,
}

impl crate::editing::Reply for SessionReply {
    fn answer(self: Box<Self>, outcome: EditOutcome) {
        let _ = self.tx.send((self.request, outcome));
    }

    fn abandoned(&self) -> bool {
        self.tx.is_closed()
    }
}

/// A client slot taken by a session, returned when it drops (however the session's task ends, a panic included).
struct Slot<'a> {
    admission: &'a std::sync::Mutex<Admission>,
    metrics: &'a Metrics,
    peer: std::net::IpAddr,
    endpoint: usize,
}

impl<'a> Slot<'a> {
    /// Count a client of `endpoint` from `peer`, whose handshake admission has let through.
    fn take(
        admission: &'a std::sync::Mutex<Admission>,
        metrics: &'a Metrics,
        peer: std::net::IpAddr,
        endpoint: usize,
    ) -> Self {
        metrics.clients.fetch_add(1, Relaxed);
        metrics.endpoint_clients[endpoint].fetch_add(1, Relaxed);
        Slot { admission, metrics, peer, endpoint }
    }
}

impl Drop for Slot<'_> {
    fn drop(&mut self) {
        self.metrics.clients.fetch_sub(1, Relaxed);
        self.metrics.endpoint_clients[self.endpoint].fetch_sub(1, Relaxed);
        self.admission.locked().closed(self.peer);
    }
}

/// Why a session ended, as the driver closes it.
struct Closing {
    code: Option<CloseCode>,
    reason: String,
}

impl Closing {
    fn new(code: CloseCode, reason: impl std::fmt::Display) -> Closing {
        Closing { code: Some(code), reason: reason.to_string() }
    }
}

/// Serve one connection to its end; returns how it was closed (`None`: the transport failed).
async fn serve_connection(
    conn: quinn::Connection,
    store: Arc<dyn WorldStore>,
    cfg: &ServerConfig,
    metrics: &Metrics,
    admission: &std::sync::Mutex<Admission>,
) -> Option<CloseCode> {
    let peer = conn.remote_address();
    let web = alpn(&conn).as_deref() == Some(WEB_ALPN);
    let link = if web {
        match tokio::time::timeout(cfg.session.handshake_timeout, accept_web(conn.clone())).await {
            Ok(Ok(link)) => link,
            Ok(Err(Closing { code, reason })) => {
                debug!(%peer, "WebTransport session refused: {reason}");
                let code = code.unwrap_or(CloseCode::Malformed);
                conn.close(VarInt::from_u32(code as u32), close_reason(&reason));
                return Some(code);
            }
            Err(_) => {
                conn.close(VarInt::from_u32(CloseCode::Timeout as u32), b"no WebTransport CONNECT in time");
                return Some(CloseCode::Timeout);
            }
        }
    } else {
        Link::raw(conn)
    };
    let _web = web.then(|| Gauge::up(&metrics.web_clients));
    match run_session(&link, store, cfg, metrics, admission).await {
        Ok(()) => Some(CloseCode::Normal),
        Err(Closing { code: Some(code), reason }) => {
            if code != CloseCode::Normal && code != CloseCode::Shutdown {
                info!(%peer, ?code, web, "closing connection: {reason}");
            }
            link.close(code as u32, close_reason(&reason));
            Some(code)
        }
        Err(Closing { code: None, reason }) => {
            debug!(%peer, "connection lost: {reason}");
            None
        }
    }
}

/// The ALPN the handshake of `conn` settled on.
fn alpn(conn: &quinn::Connection) -> Option<Vec<u8>> {
    let data = conn.handshake_data()?.downcast::<quinn::crypto::rustls::HandshakeData>().ok()?;
    data.protocol
}

/// A close reason as sent: at most 1,024 bytes (WebTransport's limit), cut at a character boundary.
fn close_reason(reason: &str) -> &[u8] {
    let mut end = reason.len().min(1024);
    while !reason.is_char_boundary(end) {
        end -= 1;
    }
    &reason.as_bytes()[..end]
}

/// The HTTP/3 side of a browser's session: its SETTINGS, and its CONNECT, answered 200 when it names [`WEB_PATH`]
/// and 404 otherwise.
async fn accept_web(conn: quinn::Connection) -> Result<Link, Closing> {
    let web = |e: web_transport_quinn::ServerError| Closing::new(CloseCode::Malformed, format!("WebTransport: {e}"));
    let request = web_transport_quinn::Request::accept(conn).await.map_err(web)?;
    if request.url.path() != WEB_PATH {
        let path = request.url.path().to_string();
        let conn = request.conn().clone();
        let _ = request.reject(web_transport_quinn::http::StatusCode::NOT_FOUND).await;
        // Give the answer a moment to arrive before the connection closes (the client closes it on reading it).
        let _ = tokio::time::timeout(REJECT_GRACE, conn.closed()).await;
        return Err(Closing::new(CloseCode::Invalid, format!("no WebTransport endpoint at {path} (it is {WEB_PATH})")));
    }
    request.ok().await.map_err(web)
}

/// A gauge counted up while this lives.
struct Gauge<'a>(&'a std::sync::atomic::AtomicU64);

impl<'a> Gauge<'a> {
    fn up(g: &'a std::sync::atomic::AtomicU64) -> Self {
        g.fetch_add(1, Relaxed);
        Gauge(g)
    }
}

impl Drop for Gauge<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Relaxed);
    }
}

fn lost(e: SessionError) -> Closing {
    match e {
        SessionError::ConnectionError(ConnectionError::ApplicationClosed(_) | ConnectionError::LocallyClosed)
        | SessionError::WebTransportError(WebTransportError::Closed(..)) => {
            Closing { code: Some(CloseCode::Normal), reason: "client closed".into() }
        }
        e => Closing { code: None, reason: e.to_string() },
    }
}

async fn run_session(
    conn: &Link,
    store: Arc<dyn WorldStore>,
    cfg: &ServerConfig,
    metrics: &Metrics,
    admission: &std::sync::Mutex<Admission>,
) -> Result<(), Closing> {
    let started = Instant::now();
    let mut last_viewpoint = started;
    let mut idle_check = tokio::time::Instant::from_std(started + cfg.idle_slot);
    let mut session = Session::new(store, cfg.session.clone(), started);
    // The store wakes this loop when a cell the session found pending is ready (a permit is kept if it is not
    // waiting at that moment, so no wake-up is lost).
    let cells_ready = Arc::new(NotifyWaker(tokio::sync::Notify::new()));
    session.set_cell_waker(Arc::clone(&cells_ready) as Arc<dyn CellWaker>);
    let deadline = tokio::time::Instant::from_std(started + cfg.session.handshake_timeout);
    let (ctl_send, mut ctl_recv) = match tokio::time::timeout_at(deadline, conn.accept_bi()).await {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => return Err(lost(e)),
        Err(_) => return Err(Closing::new(CloseCode::Timeout, "no control stream opened in time")),
    };
    let outbox = Arc::new(Outbox::default());
    // Aborted when this function ends, however it ends (a panic included): the writer holds the connection open.
    let mut writer = AbortOnDrop(tokio::spawn(write_loop(conn.clone(), ctl_send, Arc::clone(&outbox))));
    let mut decoder = FrameDecoder::new(netlimits::MAX_CLIENT_FRAME);
    let mut streaming = false;
    // Edits go to the edit writer; its answers come back here (on a channel made at the session's first edit).
    // Changed cells are announced to every session.
    let mut answers: Option<(AnswerTx, mpsc::UnboundedReceiver<(u32, EditOutcome)>)> = None;
    let mut changes = cfg.edits.as_ref().map(|e| e.hub().subscribe());
    loop {
        let now = Instant::now();
        while let Some((request, op, editor)) = session.poll_edit() {
            match &cfg.edits {
                Some(service) => {
                    let (tx, _) = answers.get_or_insert_with(mpsc::unbounded_channel);
                    let reply = Box::new(SessionReply { tx: tx.clone(), request });
                    service.submit(EditJob { op, editor, reply });
                }
                None => session.on_edit_result(request, EditOutcome::Denied("this server takes no edits".into())),
            }
        }
        let digests = (session.stats().digests_checked, session.stats().digest_mismatches);
        while let Some(t) = session.poll_transmit(now) {
            metrics.sent(t.class, t.len(), t.records);
            outbox.push(t);
        }
        metrics.digests_checked.fetch_add(session.stats().digests_checked - digests.0, Relaxed);
        metrics.digest_mismatches.fetch_add(session.stats().digest_mismatches - digests.1, Relaxed);
        if !streaming && session.phase() == Phase::Streaming {
            streaming = true;
            metrics.sessions.fetch_add(1, Relaxed);
        }
        let wake = session.poll_timeout().map(tokio::time::Instant::from_std);
        // Answers (edit results, releases) go out past the session's window: while it owes the client more than
        // the window and `OWED_SLACK`, read no more requests, so a client that never reads or acknowledges them
        // cannot make it queue more (quinn then grants it no more credit).
        let reading = session.unflushed() < cfg.session.window + OWED_SLACK;
        tokio::select! {
            chunk = ctl_recv.read_chunk(netlimits::MAX_CLIENT_FRAME, true), if reading => match chunk {
                Ok(Some(chunk)) => {
                    metrics.bytes_in.fetch_add(chunk.bytes.len() as u64, Relaxed);
                    decoder.push(&chunk.bytes);
                    let (before, denied) = (session.stats().viewpoints, session.stats().edits_denied);
                    let handled = handle_frames(&mut decoder, &mut session, Instant::now());
                    let viewpoints = session.stats().viewpoints - before;
                    if let Some(edits) = &cfg.edits {
                        // The session's own refusals count with the writer's.
                        let n = session.stats().edits_denied - denied;
                        edits.metrics().refused(n);
                    }
                    metrics.viewpoints.fetch_add(viewpoints, Relaxed);
                    if viewpoints > 0 {
                        last_viewpoint = Instant::now();
                    }
                    if let Err(c) = handled {
                        break Err(c);
                    }
                }
                Ok(None) => {
                    break match decoder.finish() {
                        Ok(()) => Err(Closing::new(CloseCode::Normal, "control stream finished")),
                        Err(e) => Err(Closing::new(CloseCode::Malformed, e)),
                    };
                }
                Err(web_transport_quinn::ReadError::SessionError(e)) => break Err(lost(e)),
                Err(e) => break Err(Closing::new(CloseCode::Malformed, format!("control stream: {e}"))),
            },
            n = outbox.take_flushed() => session.on_flushed(n),
            _ = cells_ready.0.notified() => {}
            answer = or_never(answers.as_mut().map(|(_, rx)| rx.recv())) => {
                if let Some((request, outcome)) = answer {
                    session.on_edit_result(request, outcome);
                }
            }
            change = or_never(changes.as_mut().map(|rx| rx.recv())) => match change {
                Ok(c) => session.on_cell_changed(c.cell),
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => session.on_changes_missed(),
                Err(tokio::sync::broadcast::error::RecvError::Closed) => changes = None,
            },
            _ = or_never(wake.map(tokio::time::sleep_until)) => {
                if let Err(e) = session.handle_timeout(Instant::now()) {
                    break Err(Closing::new(e.close_code(), e));
                }
            }
            _ = tokio::time::sleep_until(idle_check) => {
                let now = Instant::now();
                let near_capacity = admission.locked().near_capacity();
                if now.duration_since(last_viewpoint) >= cfg.idle_slot && near_capacity {
                    let reason = format!("no viewpoint for {:?} while the server is near capacity", cfg.idle_slot);
                    break Err(Closing::new(CloseCode::Full, reason));
                }
                let next = (last_viewpoint + cfg.idle_slot).max(now + Duration::from_secs(1));
                idle_check = tokio::time::Instant::from_std(next);
            }
            w = &mut writer.0 => {
                break Err(match w {
                    Ok(Err(e)) => e,
                    _ => Closing { code: Some(CloseCode::Internal), reason: "writer stopped".into() },
                });
            }
        }
    }
}

/// A task aborted when its handle is dropped.
struct AbortOnDrop<T>(tokio::task::JoinHandle<T>);

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// A session's [`CellWaker`]: wakes its connection's loop.
struct NotifyWaker(tokio::sync::Notify);

impl CellWaker for NotifyWaker {
    fn wake(&self) {
        self.0.notify_one();
    }
}

/// Where a session's edit answers are sent from.
type AnswerTx = mpsc::UnboundedSender<(u32, EditOutcome)>;

/// `f`'s output, or never when there is nothing to wait for (a session that has not edited, a server without edits,
/// no timer set).
async fn or_never<F: std::future::Future>(f: Option<F>) -> F::Output {
    match f {
        Some(f) => f.await,
        None => std::future::pending().await,
    }
}

fn handle_frames(decoder: &mut FrameDecoder, session: &mut Session, now: Instant) -> Result<(), Closing> {
    loop {
        match decoder.next_frame() {
            Ok(Some(frame)) => {
                session.handle_frame(now, frame).map_err(|e| Closing::new(e.close_code(), e))?;
            }
            Ok(None) => return Ok(()),
            Err(e @ FrameError::TooLarge { .. }) => return Err(Closing::new(CloseCode::TooLarge, e)),
            Err(e) => return Err(Closing::new(CloseCode::Malformed, e)),
        }
    }
}

/// Writes transmits in order to the stream each names, opening lanes on first use; reports flushed bytes.
async fn write_loop(conn: Link, mut control: SendStream, outbox: Arc<Outbox>) -> Result<(), Closing> {
    let _ = control.set_priority(1);
    let mut lanes: Vec<Option<SendStream>> = (0..8).map(|_| None).collect();
    let write_err = |e: web_transport_quinn::WriteError| match e {
        web_transport_quinn::WriteError::SessionError(e) => lost(e),
        e => Closing { code: Some(CloseCode::Normal), reason: format!("client stopped a stream: {e}") },
    };
    loop {
        let t = outbox.next().await;
        let stream = match t.stream {
            StreamId::Control => &mut control,
            StreamId::Lane(i) => {
                let slot = &mut lanes[usize::from(i).min(7)];
                if slot.is_none() {
                    let s = conn.open_uni().await.map_err(lost)?;
                    let _ = s.set_priority(-i32::from(i));
                    *slot = Some(s);
                }
                slot.as_mut().expect("opened above")
            }
        };
        let len = t.len();
        if t.body.is_empty() {
            stream.write_chunk(t.bytes).await.map_err(write_err)?;
        } else {
            // The session's head, then the body shared with every other session sending the cell.
            stream.write_all_chunks(&mut [t.bytes, t.body]).await.map_err(write_err)?;
        }
        outbox.flushed(len);
    }
}

async fn rotate_web_certificate(web: Arc<WebCertificate>, mut shutdown: watch::Receiver<bool>) {
    let mut every = tokio::time::interval(WEB_CERT_CHECK);
    loop {
        tokio::select! {
            _ = every.tick() => match web.rotate(SystemTime::now()) {
                Ok(true) => info!(fingerprint = %web.fingerprint(), "new WebTransport certificate"),
                Ok(false) => {}
                Err(e) => warn!("cannot make a new WebTransport certificate: {e}"),
            },
            _ = shutdown.changed() => return,
        }
    }
}

async fn tick_metrics(metrics: Arc<Metrics>, mut shutdown: watch::Receiver<bool>) {
    let mut every = tokio::time::interval(Duration::from_secs(1));
    loop {
        tokio::select! {
            _ = every.tick() => metrics.tick(Instant::now()),
            _ = shutdown.changed() => return,
        }
    }
}
