//! The quinn/tokio driver: a small loop per connection around the sans-IO [`Session`], the UDP sockets with
//! buffers sized for many clients, the metrics endpoint, and graceful shutdown.
//!
//! A server listens on one UDP port with [`ServerConfig::endpoints`] sockets (`SO_REUSEPORT`: the kernel spreads
//! clients over them by their address and port, so a connection's packets always reach the same socket). Each
//! socket has its own quinn endpoint, whose driver task does that socket's I/O and demultiplexing, and its own
//! accept loop; the endpoints share one TLS identity, Retry token key and stateless-reset key, one admission (client
//! slots, handshakes and per-source caps count for the whole server) and one set of counters.
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
use std::time::{Duration, Instant};

use canopy_protocol::frame::{FrameDecoder, FrameError};
use canopy_protocol::sync::Locked;
use canopy_protocol::{CloseCode, Phase, netlimits};
use quinn::{Connection, ConnectionError, Endpoint, SendStream, VarInt};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::{mpsc, watch};
use tracing::{debug, info, warn};

use crate::admission::{Admission, AdmissionConfig, Refusal, Verdict};
use crate::editing::{EditJob, EditService};
use crate::metrics::Metrics;
use crate::outbox::Outbox;
use crate::tls::{Identity, IdentityError};
use canopy_protocol::edit::EditOutcome;
use canopy_session::{CellWaker, WorldStore};
use canopy_session::{SendBudget, Session, SessionConfig, StreamId};

/// UDP socket buffer size: 1,000 concurrent handshakes on loopback overflow the default buffers.
pub const SOCKET_BUFFER: usize = 4 * 1024 * 1024;

/// Bytes of unacknowledged send data quinn keeps per connection (224 KiB: ~36 Mbit/s at 50 ms round trip).
pub const SEND_WINDOW: u64 = 224 * 1024;

/// Bytes past its window a session may owe its client before the driver stops reading the client's requests. With
/// reads of at most [`netlimits::MAX_CLIENT_FRAME`] bytes, the answers to one read (an edit request of 9 bytes
/// denied in about 60) add at most a few KiB more.
pub const OWED_SLACK: usize = 16 * 1024;

/// How a server runs.
#[derive(Clone, Debug)]
pub struct ServerConfig {
    /// The UDP address to listen on (port 0: any free port).
    pub listen: SocketAddr,
    /// The TCP address of the Prometheus metrics endpoint (`None`: no endpoint).
    pub metrics: Option<SocketAddr>,
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
    fingerprint: String,
    identity_generated: bool,
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
    t.max_concurrent_bidi_streams(VarInt::from_u32(1))
        .max_concurrent_uni_streams(VarInt::from_u32(0))
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
        let tls = identity.server_config()?;
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
                tokio::spawn(serve_metrics(listener, Arc::clone(&metrics), shutdown_rx.clone()));
                Some(bound)
            }
            None => None,
        };
        tokio::spawn(tick_metrics(Arc::clone(&metrics), shutdown_rx.clone()));
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
            fingerprint: identity.fingerprint(),
            identity_generated: identity.generated,
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

    /// The certificate's SHA-256 fingerprint (what clients pin).
    pub fn fingerprint(&self) -> &str {
        &self.fingerprint
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
    conn: Connection,
    store: Arc<dyn WorldStore>,
    cfg: &ServerConfig,
    metrics: &Metrics,
    admission: &std::sync::Mutex<Admission>,
) -> Option<CloseCode> {
    let peer = conn.remote_address();
    match run_session(&conn, store, cfg, metrics, admission).await {
        Ok(()) => Some(CloseCode::Normal),
        Err(Closing { code: Some(code), reason }) => {
            if code != CloseCode::Normal && code != CloseCode::Shutdown {
                info!(%peer, ?code, "closing connection: {reason}");
            }
            conn.close(VarInt::from_u32(code as u32), reason.as_bytes());
            Some(code)
        }
        Err(Closing { code: None, reason }) => {
            debug!(%peer, "connection lost: {reason}");
            None
        }
    }
}

fn lost(e: ConnectionError) -> Closing {
    match e {
        ConnectionError::ApplicationClosed(_) | ConnectionError::LocallyClosed => {
            Closing { code: Some(CloseCode::Normal), reason: "client closed".into() }
        }
        e => Closing { code: None, reason: e.to_string() },
    }
}

async fn run_session(
    conn: &Connection,
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
                Err(quinn::ReadError::ConnectionLost(e)) => break Err(lost(e)),
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
async fn write_loop(conn: Connection, mut control: SendStream, outbox: Arc<Outbox>) -> Result<(), Closing> {
    let _ = control.set_priority(1);
    let mut lanes: Vec<Option<SendStream>> = (0..8).map(|_| None).collect();
    let write_err = |e: quinn::WriteError| match e {
        quinn::WriteError::ConnectionLost(e) => lost(e),
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

/// Metrics connections still sending their request at once; the next one accepted closes the oldest, so idle
/// sockets cannot keep a scraper out (its request arrives with its connection).
const MAX_METRICS_CONNECTIONS: usize = 16;

/// How long a metrics connection may take to send its request, and to take the answer.
const METRICS_TIMEOUT: Duration = Duration::from_secs(5);

async fn serve_metrics(listener: tokio::net::TcpListener, metrics: Arc<Metrics>, mut shutdown: watch::Receiver<bool>) {
    // Connections reading their request, oldest first: (number, task).
    let reading: Arc<std::sync::Mutex<std::collections::VecDeque<(u64, tokio::task::AbortHandle)>>> = Arc::default();
    let mut backoff = AcceptBackoff::default();
    for number in 0u64.. {
        let accepted = tokio::select! {
            a = listener.accept() => a,
            _ = shutdown.changed() => return,
        };
        let mut sock = match accepted {
            Ok((sock, _)) => {
                backoff.accepted();
                sock
            }
            Err(e) => {
                // At the file-descriptor limit (EMFILE, ENFILE) accept fails at once, again and again: wait before
                // the next try, longer each time, and log once per interval instead of once per failure.
                let (wait, log) = backoff.failed(Instant::now());
                if let Some(suppressed) = log {
                    warn!("metrics endpoint: {e} ({suppressed} more since the last report); retrying in {wait:?}");
                }
                tokio::select! {
                    _ = tokio::time::sleep(wait) => continue,
                    _ = shutdown.changed() => return,
                }
            }
        };
        let (metrics, readers) = (Arc::clone(&metrics), Arc::clone(&reading));
        // Held until the task is in the list, so it cannot take itself out before it is put in.
        let mut list = reading.locked();
        if list.len() >= MAX_METRICS_CONNECTIONS
            && let Some((_, oldest)) = list.pop_front()
        {
            oldest.abort();
        }
        let task = tokio::spawn(async move {
            // Read the request head (bounded in size and time); only `GET /metrics` is served.
            let mut buf = vec![0u8; 4096];
            let mut n = 0;
            let read = tokio::time::timeout(METRICS_TIMEOUT, async {
                while n < buf.len() {
                    match sock.read(&mut buf[n..]).await {
                        Ok(0) | Err(_) => break,
                        Ok(m) => n += m,
                    }
                    if buf[..n].windows(4).any(|w| w == b"\r\n\r\n") {
                        break;
                    }
                }
            });
            let timed_out = read.await.is_err();
            readers.locked().retain(|(k, _)| *k != number);
            if timed_out {
                return;
            }
            let head = String::from_utf8_lossy(&buf[..n]);
            let response = if head.starts_with("GET /metrics ") || head.starts_with("GET / ") {
                let body = metrics.render();
                format!(
                    "HTTP/1.1 200 OK\r\nContent-Type: text/plain; version=0.0.4\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                    body.len()
                )
            } else {
                "HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n".to_string()
            };
            let _ = tokio::time::timeout(METRICS_TIMEOUT, async {
                let _ = sock.write_all(response.as_bytes()).await;
                let _ = sock.shutdown().await;
            })
            .await;
        });
        list.push_back((number, task.abort_handle()));
    }
}

/// The accept loop's answer to failures: exponential backoff from 10 ms to 1 s, and a log line at most every
/// 10 s that counts the failures it did not report. Sans-IO: `now` is an argument.
#[derive(Debug, Default)]
struct AcceptBackoff {
    /// Failures in a row.
    failures: u32,
    /// When a failure was last logged.
    logged: Option<Instant>,
    /// Failures since then.
    unreported: u64,
}

impl AcceptBackoff {
    const FIRST: Duration = Duration::from_millis(10);
    const MAX: Duration = Duration::from_secs(1);
    const LOG_EVERY: Duration = Duration::from_secs(10);

    /// An accept succeeded: the next failure waits the shortest time again.
    fn accepted(&mut self) {
        self.failures = 0;
    }

    /// An accept failed at `now`: how long to wait, and `Some(failures not reported)` if this one is to be logged.
    fn failed(&mut self, now: Instant) -> (Duration, Option<u64>) {
        let wait = Self::FIRST.saturating_mul(1 << self.failures.min(7)).min(Self::MAX);
        self.failures = self.failures.saturating_add(1);
        let log = match self.logged {
            Some(t) if now.duration_since(t) < Self::LOG_EVERY => {
                self.unreported += 1;
                None
            }
            _ => {
                self.logged = Some(now);
                Some(std::mem::take(&mut self.unreported))
            }
        };
        (wait, log)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accept_failures_back_off_and_log_once_per_interval() {
        let t0 = Instant::now();
        let mut b = AcceptBackoff::default();
        let mut logged = 0;
        let mut waited = Duration::ZERO;
        // A million failures within 10 s of virtual time (an accept loop at the fd limit).
        for i in 0..1_000_000u32 {
            let now = t0 + Duration::from_micros(u64::from(i) * 9);
            let (wait, log) = b.failed(now);
            assert!(wait >= AcceptBackoff::FIRST && wait <= AcceptBackoff::MAX);
            waited += wait;
            logged += usize::from(log.is_some());
        }
        assert_eq!(logged, 1, "one line for a burst under 10 s");
        assert!(waited >= Duration::from_secs(900_000), "the waits add up: at most ~1 try a second once backed off");
        let (wait, log) = b.failed(t0 + Duration::from_secs(11));
        assert_eq!(wait, AcceptBackoff::MAX);
        assert_eq!(log, Some(999_999), "the next line counts what was not reported");
        b.accepted();
        assert_eq!(b.failed(t0 + Duration::from_secs(12)).0, AcceptBackoff::FIRST);
    }
}
