//! The quinn/tokio driver: a small loop per connection around the sans-IO [`Session`], the UDP socket with
//! buffers sized for many clients, the metrics endpoint, and graceful shutdown.
//!
//! Per connection: the client opens one bidirectional control stream (hello, ready, viewpoints up; the welcome
//! down); the server opens up to [`SessionConfig::lanes`] unidirectional lanes, ordered streams whose QUIC priority
//! falls with the lane number, and writes each [`Transmit`] to the stream the session names. A writer task does
//! the writes and reports flushed bytes back, which reopens the session's window. Anything wrong in what a client
//! sends closes that one connection with a [`CloseCode`] and a reason; the server carries on.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use canopy_protocol::frame::{FrameDecoder, FrameError};
use canopy_protocol::{CloseCode, Phase, netlimits};
use quinn::{Connection, ConnectionError, Endpoint, SendStream, VarInt};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::{mpsc, watch};
use tracing::{debug, info, warn};

use crate::metrics::Metrics;
use crate::session::{Session, SessionConfig, StreamId, Transmit};
use crate::store::WorldStore;
use crate::tls::{Identity, IdentityError};

/// UDP socket buffer size: 1,000 concurrent handshakes on loopback overflow the default buffers.
pub const SOCKET_BUFFER: usize = 4 * 1024 * 1024;

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
    /// Most clients at once; more are refused.
    pub max_clients: usize,
    /// UDP socket send and receive buffer size, bytes.
    pub socket_buffer: usize,
    /// A connection with no traffic for this long is closed.
    pub idle_timeout: Duration,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            listen: SocketAddr::from(([127, 0, 0, 1], 4433)),
            metrics: None,
            data_dir: None,
            session: SessionConfig::default(),
            max_clients: 20_000,
            socket_buffer: SOCKET_BUFFER,
            idle_timeout: Duration::from_secs(30),
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

/// A running server: the endpoint, its accept loop and the metrics endpoint.
pub struct Server {
    endpoint: Endpoint,
    local_addr: SocketAddr,
    metrics_addr: Option<SocketAddr>,
    fingerprint: String,
    identity_generated: bool,
    metrics: Arc<Metrics>,
    shutdown: watch::Sender<bool>,
    accept: tokio::task::JoinHandle<()>,
    socket_buffers: (usize, usize),
}

impl std::fmt::Debug for Server {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Server").field("local_addr", &self.local_addr).finish()
    }
}

/// A UDP socket bound to `addr` with send and receive buffers of `size` bytes (as far as the OS allows).
fn udp_socket(addr: SocketAddr, size: usize) -> std::io::Result<(std::net::UdpSocket, (usize, usize))> {
    use socket2::{Domain, Protocol, Socket, Type};
    let socket = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
    if let Err(e) = socket.set_recv_buffer_size(size) {
        warn!("cannot set the UDP receive buffer to {size} bytes: {e}");
    }
    if let Err(e) = socket.set_send_buffer_size(size) {
        warn!("cannot set the UDP send buffer to {size} bytes: {e}");
    }
    socket.bind(&addr.into())?;
    let got = (socket.recv_buffer_size().unwrap_or(0), socket.send_buffer_size().unwrap_or(0));
    Ok((socket.into(), got))
}

fn transport(cfg: &ServerConfig) -> quinn::TransportConfig {
    let mut t = quinn::TransportConfig::default();
    t.max_concurrent_bidi_streams(VarInt::from_u32(1))
        .max_concurrent_uni_streams(VarInt::from_u32(0))
        .stream_receive_window(VarInt::from_u32(64 * 1024))
        .receive_window(VarInt::from_u32(128 * 1024))
        .send_window(2 * 1024 * 1024)
        .max_idle_timeout(cfg.idle_timeout.try_into().ok());
    t
}

impl Server {
    /// Bind, load or generate the certificate, and start accepting clients of `store`.
    pub async fn start(store: Arc<dyn WorldStore>, cfg: ServerConfig) -> Result<Server, StartError> {
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
        let (socket, socket_buffers) = udp_socket(cfg.listen, cfg.socket_buffer).map_err(bind)?;
        let runtime = Arc::new(quinn::TokioRuntime);
        let endpoint =
            Endpoint::new(quinn::EndpointConfig::default(), Some(server_config), socket, runtime).map_err(bind)?;
        let local_addr = endpoint.local_addr().map_err(bind)?;
        let metrics = Arc::new(Metrics::new());
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
        let accept = tokio::spawn(accept_loop(endpoint.clone(), store, cfg, Arc::clone(&metrics), shutdown_rx));
        info!(%local_addr, ?socket_buffers, "canopy-server listening");
        Ok(Server {
            endpoint,
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

    /// Close every connection with [`CloseCode::Shutdown`] and wait (up to `grace`) for them to go.
    pub async fn shutdown(self, grace: Duration) {
        let _ = self.shutdown.send(true);
        self.accept.abort();
        self.endpoint.close(VarInt::from_u32(CloseCode::Shutdown as u32), b"server shutting down");
        let _ = tokio::time::timeout(grace, self.endpoint.wait_idle()).await;
    }
}

async fn accept_loop(
    endpoint: Endpoint,
    store: Arc<dyn WorldStore>,
    cfg: ServerConfig,
    metrics: Arc<Metrics>,
    mut shutdown: watch::Receiver<bool>,
) {
    let cfg = Arc::new(cfg);
    loop {
        let incoming = tokio::select! {
            i = endpoint.accept() => match i { Some(i) => i, None => break },
            _ = shutdown.changed() => break,
        };
        if metrics.clients.load(Relaxed) as usize >= cfg.max_clients {
            metrics.closed(Some(CloseCode::Full));
            incoming.refuse();
            continue;
        }
        metrics.connections.fetch_add(1, Relaxed);
        metrics.clients.fetch_add(1, Relaxed);
        let (store, cfg, metrics) = (Arc::clone(&store), Arc::clone(&cfg), Arc::clone(&metrics));
        tokio::spawn(async move {
            let peer = incoming.remote_address();
            let code = match tokio::time::timeout(cfg.session.handshake_timeout, incoming).await {
                Ok(Ok(conn)) => serve(conn, store, &cfg, &metrics).await,
                Ok(Err(e)) => {
                    debug!(%peer, "QUIC handshake failed: {e}");
                    None
                }
                Err(_) => {
                    debug!(%peer, "QUIC handshake timed out");
                    Some(CloseCode::Timeout)
                }
            };
            metrics.closed(code);
            metrics.clients.fetch_sub(1, Relaxed);
        });
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
async fn serve(
    conn: Connection,
    store: Arc<dyn WorldStore>,
    cfg: &ServerConfig,
    metrics: &Metrics,
) -> Option<CloseCode> {
    let peer = conn.remote_address();
    match run_session(&conn, store, cfg, metrics).await {
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
) -> Result<(), Closing> {
    let started = Instant::now();
    let mut session = Session::new(store, cfg.session.clone(), started);
    let deadline = tokio::time::Instant::from_std(started + cfg.session.handshake_timeout);
    let (ctl_send, mut ctl_recv) = match tokio::time::timeout_at(deadline, conn.accept_bi()).await {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => return Err(lost(e)),
        Err(_) => return Err(Closing::new(CloseCode::Timeout, "no control stream opened in time")),
    };
    let (tx, rx) = mpsc::unbounded_channel::<Transmit>();
    let (flushed_tx, mut flushed_rx) = mpsc::unbounded_channel::<usize>();
    let mut writer = tokio::spawn(write_loop(conn.clone(), ctl_send, rx, flushed_tx));
    let mut decoder = FrameDecoder::new(netlimits::MAX_CLIENT_FRAME);
    let mut streaming = false;
    let result = loop {
        let now = Instant::now();
        while let Some(t) = session.poll_transmit(now) {
            metrics.sent(t.class, t.bytes.len(), t.records);
            if tx.send(t).is_err() {
                break;
            }
        }
        if !streaming && session.phase() == Phase::Streaming {
            streaming = true;
            metrics.sessions.fetch_add(1, Relaxed);
        }
        let wake = session.poll_timeout().map(tokio::time::Instant::from_std);
        tokio::select! {
            chunk = ctl_recv.read_chunk(64 * 1024, true) => match chunk {
                Ok(Some(chunk)) => {
                    metrics.bytes_in.fetch_add(chunk.bytes.len() as u64, Relaxed);
                    decoder.push(&chunk.bytes);
                    let before = session.stats().viewpoints;
                    let handled = handle_frames(&mut decoder, &mut session, Instant::now());
                    metrics.viewpoints.fetch_add(session.stats().viewpoints - before, Relaxed);
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
            n = flushed_rx.recv() => {
                let mut n = n.unwrap_or(0);
                while let Ok(m) = flushed_rx.try_recv() {
                    n += m;
                }
                session.on_flushed(n);
            }
            _ = sleep_until(wake) => {
                if let Err(e) = session.handle_timeout(Instant::now()) {
                    break Err(Closing::new(e.close_code(), e));
                }
            }
            w = &mut writer => {
                break Err(match w {
                    Ok(Err(e)) => e,
                    _ => Closing { code: Some(CloseCode::Internal), reason: "writer stopped".into() },
                });
            }
        }
    };
    writer.abort();
    result
}

async fn sleep_until(at: Option<tokio::time::Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
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
async fn write_loop(
    conn: Connection,
    mut control: SendStream,
    mut rx: mpsc::UnboundedReceiver<Transmit>,
    flushed: mpsc::UnboundedSender<usize>,
) -> Result<(), Closing> {
    let _ = control.set_priority(1);
    let mut lanes: Vec<Option<SendStream>> = (0..8).map(|_| None).collect();
    let write_err = |e: quinn::WriteError| match e {
        quinn::WriteError::ConnectionLost(e) => lost(e),
        e => Closing { code: Some(CloseCode::Normal), reason: format!("client stopped a stream: {e}") },
    };
    while let Some(t) = rx.recv().await {
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
        let len = t.bytes.len();
        stream.write_chunk(t.bytes).await.map_err(write_err)?;
        let _ = flushed.send(len);
    }
    Ok(())
}

async fn serve_metrics(listener: tokio::net::TcpListener, metrics: Arc<Metrics>, mut shutdown: watch::Receiver<bool>) {
    loop {
        let (mut sock, _) = tokio::select! {
            a = listener.accept() => match a { Ok(a) => a, Err(e) => { warn!("metrics endpoint: {e}"); continue } },
            _ = shutdown.changed() => return,
        };
        let metrics = Arc::clone(&metrics);
        tokio::spawn(async move {
            // Read the request head (bounded in size and time); only `GET /metrics` is served.
            let mut buf = vec![0u8; 4096];
            let mut n = 0;
            let read = tokio::time::timeout(Duration::from_secs(5), async {
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
            if read.await.is_err() {
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
            let _ = sock.write_all(response.as_bytes()).await;
            let _ = sock.shutdown().await;
        });
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
