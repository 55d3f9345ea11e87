//! The network client: connect to a `canopy-server` over QUIC, say hello, answer the welcome with the species the
//! cache holds, send viewpoints as they move, and feed the server's lanes into the sans-IO [`ClientState`].
//!
//! One [`Connection`] is one session. Its lanes are read by small tasks that only split frames and decode; the
//! state is changed by whoever owns the connection (a bot's task, the app's loop), so there is no lock on it.
//! Anything wrong from the server closes the connection with a [`CloseCode`] and a reason.

mod expanding;
mod failover;
mod farfield;
pub mod tls;

use std::net::SocketAddr;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use canopy_protocol::aoi::Viewpoint;
use canopy_protocol::frame::{FrameDecoder, FrameError, frame};
use canopy_protocol::messages::{ByKind, MessageError, ServerMsgKind, ServerStreaming, Welcome};
use canopy_protocol::{CloseCode, ServerMsg, netlimits};
use quinn::Endpoint;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use web_transport_quinn::{Session as Link, SessionError, WebTransportError};

use crate::cache::{CacheError, SpeciesCache};
use crate::expand::Expander;
use crate::state::{ClientState, Event, StateError};
pub use failover::{Edges, FAILOVER_IDLE, FAILOVER_TIMEOUT};
pub use tls::Trust;

/// UDP socket buffer size of a client endpoint (a bots process multiplexes thousands of connections on one).
pub const SOCKET_BUFFER: usize = 4 * 1024 * 1024;

/// Where and how to connect.
#[derive(Clone, Debug)]
pub struct ConnectConfig {
    /// The server's UDP address.
    pub server: SocketAddr,
    /// The TLS server name (the server's certificate is issued for `localhost` and `canopy`).
    pub server_name: String,
    /// How the server's certificate is trusted.
    pub trust: Trust,
    /// A label for the server's logs.
    pub client_name: String,
    /// How long connecting and the handshake may take.
    pub timeout: Duration,
    /// An editor token for the hello (`None`: a read-only session).
    pub token: Option<Vec<u8>>,
    /// Every edge serving the world, `server` among them: where [`Connection::fail_over`] goes when the session
    /// with `server` ends (empty: `server` alone).
    pub edges: Vec<SocketAddr>,
    /// How long the connection may hear nothing before it counts as lost (keep-alives go at a quarter of it). With
    /// edges to fail over to it is [`FAILOVER_IDLE`], so a dead edge is noticed in seconds.
    pub idle_timeout: Duration,
    /// Where cells are expanded when the client expands them itself (the default where the server offers a
    /// world function); `None`: the client takes records.
    pub expander: Option<Arc<Expander>>,
    /// Ask for grants and expand nothing ([`ClientState::set_grants_only`]): a load generator's client.
    pub grants_only: bool,
    /// Speak WebTransport as a browser does (ALPN `h3`, an HTTP/3 CONNECT to this path, e.g. `/canopy`) instead
    /// of native QUIC (`None`). `trust` then pins the server's short-lived WebTransport certificate.
    pub web: Option<String>,
    /// The QUIC client configuration built for `trust`, `idle_timeout` and the protocol, shared by this
    /// configuration's clones.
    quic: Arc<OnceLock<(QuicKey, quinn::ClientConfig)>>,
}

/// What a QUIC client configuration is built for: the trust, the idle timeout, WebTransport or not.
type QuicKey = (Trust, Duration, bool);

impl ConnectConfig {
    /// Connect to `server`, trusting as `trust` says.
    pub fn new(server: SocketAddr, trust: Trust) -> ConnectConfig {
        ConnectConfig {
            server,
            server_name: "localhost".into(),
            trust,
            client_name: "canopy".into(),
            timeout: Duration::from_secs(20),
            token: None,
            edges: Vec::new(),
            idle_timeout: tls::IDLE_TIMEOUT,
            expander: None,
            grants_only: false,
            web: None,
            quic: Arc::default(),
        }
    }

    /// Connect to the first of `edges` and fail over to the others ([`Connection::fail_over`]); with more than
    /// one edge the idle timeout is [`FAILOVER_IDLE`].
    pub fn new_edges(edges: &Edges, trust: Trust) -> ConnectConfig {
        let mut cfg = ConnectConfig::new(edges.first(), trust);
        if edges.len() > 1 {
            cfg.edges = edges.to_vec();
            cfg.idle_timeout = FAILOVER_IDLE;
        }
        cfg
    }

    /// The QUIC client configuration trusting as `trust` says: built on first use and shared by the clones (many
    /// connections, one TLS configuration).
    pub fn client_config(&self) -> Result<quinn::ClientConfig, ClientError> {
        let key = (self.trust.clone(), self.idle_timeout, self.web.is_some());
        let alpn = if self.web.is_some() { WEB_ALPN } else { canopy_protocol::ALPN };
        let build = || tls::client_config_alpn(self.trust.clone(), self.idle_timeout, alpn);
        match self.quic.get() {
            Some((k, cfg)) if *k == key => Ok(cfg.clone()),
            // `trust`, the timeout or the protocol was changed after the first build: build for them, uncached.
            Some(_) => Ok(build()?),
            None => {
                let cfg = build()?;
                Ok(self.quic.get_or_init(|| (key, cfg)).1.clone())
            }
        }
    }
}

/// Why a connection failed or ended.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The TLS or QUIC configuration could not be built.
    #[error(transparent)]
    Tls(#[from] tls::TlsError),
    /// The connection could not be started.
    #[error("connecting: {0}")]
    Connect(#[from] quinn::ConnectError),
    /// The server closed the connection, with its reason.
    #[error("server closed the connection ({code:?}): {reason}")]
    Closed {
        /// The close code, if it is one of ours.
        code: Option<CloseCode>,
        /// The server's reason.
        reason: String,
    },
    /// The connection was lost.
    #[error("connection lost: {0}")]
    Lost(quinn::ConnectionError),
    /// The WebTransport session could not be opened or failed (HTTP/3 settings, the CONNECT answered other than
    /// 200, a malformed stream header).
    #[error("WebTransport: {0}")]
    Web(String),
    /// Reading a stream failed (other than by losing the connection).
    #[error("reading a stream: {0}")]
    Read(web_transport_quinn::ReadError),
    /// Writing the control stream failed (other than by losing the connection).
    #[error("writing the control stream: {0}")]
    Write(web_transport_quinn::WriteError),
    /// The server ended its streams before the step named here.
    #[error("the server ended its streams {0}")]
    Ended(&'static str),
    /// The species cache could not be opened.
    #[error("species cache: {0}")]
    Cache(#[from] CacheError),
    /// A frame was too large, empty or truncated.
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// A message did not decode or is not acceptable.
    #[error(transparent)]
    Message(#[from] MessageError),
    /// A message is not acceptable in the session's state.
    #[error(transparent)]
    State(#[from] StateError),
    /// Something took too long.
    #[error("timed out {0}")]
    Timeout(&'static str),
    /// The UDP socket could not be set up.
    #[error("socket: {0}")]
    Socket(#[from] std::io::Error),
    /// The server's world function did not build into a world.
    #[error("the server's world function does not build: {0}")]
    Function(String),
}

impl ClientError {
    fn from_write(e: web_transport_quinn::WriteError) -> ClientError {
        match e {
            web_transport_quinn::WriteError::SessionError(e) => ClientError::from_session(e),
            e => ClientError::Write(e),
        }
    }

    fn from_session(e: SessionError) -> ClientError {
        match e {
            SessionError::ConnectionError(e) => ClientError::from_connection(e),
            SessionError::WebTransportError(WebTransportError::Closed(code, reason)) => {
                ClientError::Closed { code: CloseCode::from_code(u64::from(code)), reason }
            }
            e => ClientError::Web(e.to_string()),
        }
    }

    fn from_connection(e: quinn::ConnectionError) -> ClientError {
        match e {
            quinn::ConnectionError::ApplicationClosed(c) => ClientError::Closed {
                code: CloseCode::from_code(c.error_code.into_inner()),
                reason: String::from_utf8_lossy(&c.reason).into_owned(),
            },
            e => ClientError::Lost(e),
        }
    }

    /// Whether the session ended because its edge is gone or going — the connection lost or timed out, closed by
    /// a shutdown, its streams ended, or no answer — rather than by a fault of either side's messages or a
    /// refusal: what [`Connection::fail_over`] is for.
    pub fn edge_lost(&self) -> bool {
        match self {
            ClientError::Lost(_)
            | ClientError::Web(_)
            | ClientError::Ended(_)
            | ClientError::Read(_)
            | ClientError::Write(_)
            | ClientError::Timeout(_)
            | ClientError::Connect(_) => true,
            ClientError::Closed { code, .. } => {
                matches!(code, None | Some(CloseCode::Shutdown | CloseCode::Timeout | CloseCode::Internal))
            }
            _ => false,
        }
    }

    /// Whether the server said it is too busy for this connection now: it refused it (its handshakes or clients at
    /// their limit), closed it as full, cut its handshake at its timeout, closed the session's handshake as timed
    /// out, or found the address-validation (Retry) token it gave expired by the time the client answered. Worth
    /// asking again after a pause ([`Connection::connect_any`] does).
    pub fn busy(&self) -> bool {
        use quinn::TransportErrorCode as T;
        match self {
            ClientError::Closed { code: Some(CloseCode::Full | CloseCode::Timeout), .. } => true,
            ClientError::Lost(quinn::ConnectionError::ConnectionClosed(c)) => {
                [T::CONNECTION_REFUSED, T::APPLICATION_ERROR, T::INVALID_TOKEN].contains(&c.error_code)
            }
            _ => false,
        }
    }

    /// The close code the client sends for this error, if it is the server's fault.
    fn close_code(&self) -> Option<CloseCode> {
        match self {
            ClientError::Frame(FrameError::TooLarge { .. }) => Some(CloseCode::TooLarge),
            ClientError::Frame(_) => Some(CloseCode::Malformed),
            ClientError::Message(e) => Some(e.close_code()),
            ClientError::State(StateError::Phase(_)) => Some(CloseCode::OutOfOrder),
            ClientError::State(_) | ClientError::Function(_) => Some(CloseCode::Invalid),
            ClientError::Timeout(_) => Some(CloseCode::Timeout),
            _ => None,
        }
    }
}

/// A loopback address of `server`'s family with any port (`127.0.0.1:0` or `[::1]:0`): where local clients and
/// relays bind.
pub fn loopback_for(server: SocketAddr) -> SocketAddr {
    use std::net::{Ipv4Addr, Ipv6Addr};
    if server.is_ipv6() { (Ipv6Addr::LOCALHOST, 0).into() } else { (Ipv4Addr::LOCALHOST, 0).into() }
}

/// A client endpoint bound to `bind` (e.g. `127.0.0.1:0`) with large socket buffers; many connections share it.
pub fn endpoint(bind: SocketAddr) -> Result<Endpoint, ClientError> {
    use socket2::{Domain, Protocol, Socket, Type};
    let socket = Socket::new(Domain::for_address(bind), Type::DGRAM, Some(Protocol::UDP))?;
    // Best effort: the OS may cap the buffers (net.core.rmem_max); the endpoint works either way.
    let _ = socket.set_recv_buffer_size(SOCKET_BUFFER);
    let _ = socket.set_send_buffer_size(SOCKET_BUFFER);
    socket.bind(&bind.into())?;
    let runtime = Arc::new(quinn::TokioRuntime);
    Ok(Endpoint::new(quinn::EndpointConfig::default(), None, socket.into(), runtime)?)
}

enum Inbound {
    Msg(Box<ServerMsg>, usize),
    Failed(ClientError),
}

struct AbortOnDrop(Vec<JoinHandle<()>>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        for t in &self.0 {
            t.abort();
        }
    }
}

/// One session with a server (see the module docs).
pub struct Connection {
    conn: Link,
    control: web_transport_quinn::SendStream,
    inbox: mpsc::Receiver<Inbound>,
    state: ClientState,
    cache: Option<Arc<SpeciesCache>>,
    seq: u32,
    /// Cells to ask for again (after a [`Event::Gap`]), sent before the next wait.
    refresh: Vec<canopy_protocol::CellCoord>,
    /// Cells this client expands itself: the expander, the world, the jobs in flight and their results.
    expanding: expanding::Expanding,
    /// The far field this client computes itself, where it expands its cells.
    far: farfield::FarField,
    bytes_out: u64,
    frame_bytes: ByKind<u64>,
    _tasks: AbortOnDrop,
}

impl std::fmt::Debug for Connection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Connection").field("remote", &self.conn.remote_address()).finish()
    }
}

async fn read_frame(
    recv: &mut web_transport_quinn::RecvStream,
    decoder: &mut FrameDecoder,
) -> Result<Option<(ServerMsg, usize)>, ClientError> {
    loop {
        if let Some(f) = decoder.next_frame()? {
            let len = f.len() + canopy_protocol::frame::PREFIX;
            return Ok(Some((ServerMsg::decode(f)?, len)));
        }
        match recv.read_chunk(64 * 1024, true).await {
            Ok(Some(chunk)) => decoder.push(&chunk.bytes),
            Ok(None) => {
                decoder.finish()?;
                return Ok(None);
            }
            Err(web_transport_quinn::ReadError::SessionError(e)) => return Err(ClientError::from_session(e)),
            Err(e) => return Err(ClientError::Read(e)),
        }
    }
}

/// The ALPN under which a browser speaks WebTransport (HTTP/3).
pub const WEB_ALPN: &[u8] = b"h3";

/// Open the WebTransport session on `conn` (ALPN `h3`): HTTP/3 settings, then CONNECT to `path` on the server's
/// name and port.
async fn open_web(conn: quinn::Connection, cfg: &ConnectConfig, path: &str) -> Result<Link, ClientError> {
    let at = format!("https://{}:{}{path}", cfg.server_name, cfg.server.port());
    let url = url::Url::parse(&at).map_err(|e| ClientError::Web(format!("{at}: {e}")))?;
    let request = web_transport_quinn::proto::ConnectRequest::new(url);
    Link::connect(conn, request).await.map_err(|e| match e {
        web_transport_quinn::ClientError::Connection(e) => ClientError::from_connection(e),
        e => ClientError::Web(e.to_string()),
    })
}

impl Connection {
    /// Connect, say hello, read the welcome, tell the server which species the cache holds and where the
    /// viewpoint is (`viewpoint` places it, knowing the world from the welcome). Species held by `cache` are
    /// preloaded into the state.
    pub async fn connect(
        endpoint: &Endpoint,
        cfg: &ConnectConfig,
        cache: Option<Arc<SpeciesCache>>,
        viewpoint: impl FnOnce(&Welcome) -> Viewpoint,
    ) -> Result<Connection, ClientError> {
        Connection::connect_resuming(endpoint, cfg, cache, ClientState::new(), viewpoint).await
    }

    /// [`Connection::connect`] resuming an earlier session's state ([`ClientState::resuming`]): cells it held in
    /// full are kept, and the server sends only what changed in them since.
    pub async fn connect_resuming(
        endpoint: &Endpoint,
        cfg: &ConnectConfig,
        cache: Option<Arc<SpeciesCache>>,
        state: ClientState,
        viewpoint: impl FnOnce(&Welcome) -> Viewpoint,
    ) -> Result<Connection, ClientError> {
        let client_cfg = cfg.client_config()?;
        let connecting = endpoint.connect_with(client_cfg, cfg.server, &cfg.server_name)?;
        let deadline = tokio::time::Instant::now() + cfg.timeout;
        let conn = match tokio::time::timeout_at(deadline, connecting).await {
            Ok(Ok(c)) => c,
            Ok(Err(e)) => return Err(ClientError::from_connection(e)),
            Err(_) => return Err(ClientError::Timeout("connecting")),
        };
        let conn = match &cfg.web {
            None => Link::raw(conn),
            Some(path) => match tokio::time::timeout_at(deadline, open_web(conn, cfg, path)).await {
                Ok(r) => r?,
                Err(_) => return Err(ClientError::Timeout("opening the WebTransport session")),
            },
        };
        match tokio::time::timeout_at(deadline, Connection::handshake(conn.clone(), cfg, cache, state, viewpoint)).await
        {
            Ok(Ok(c)) => Ok(c),
            Ok(Err(e)) => {
                if let Some(code) = e.close_code() {
                    conn.close(code as u32, e.to_string().as_bytes());
                }
                Err(e)
            }
            Err(_) => {
                conn.close(CloseCode::Timeout as u32, b"handshake timed out");
                Err(ClientError::Timeout("in the handshake"))
            }
        }
    }

    async fn handshake(
        conn: Link,
        cfg: &ConnectConfig,
        cache: Option<Arc<SpeciesCache>>,
        mut state: ClientState,
        viewpoint: impl FnOnce(&Welcome) -> Viewpoint,
    ) -> Result<Connection, ClientError> {
        let (mut control, mut recv) = conn.open_bi().await.map_err(ClientError::from_session)?;
        let hello = frame(&state.hello_as(&cfg.client_name, cfg.token.clone())?.encode());
        control.write_all(&hello).await.map_err(ClientError::from_write)?;
        let mut decoder = FrameDecoder::new(netlimits::MAX_SERVER_FRAME);
        let (msg, welcome_len) =
            read_frame(&mut recv, &mut decoder).await?.ok_or(ClientError::Ended("before the welcome"))?;
        let welcome = state.on_welcome(msg)?;
        if let Some(cache) = &cache {
            for (id, entry) in welcome.species.iter().enumerate() {
                if let Some(g) = cache.get(&entry.hash) {
                    state.preload_species(id as u8, g);
                }
            }
        }
        let viewpoint = viewpoint(&welcome);
        let mut ready = Vec::new();
        for msg in state.resume()? {
            ready.extend_from_slice(&frame(&msg.encode()));
        }
        let expanding = expanding::Expanding::new(cfg.expander.clone(), cfg.grants_only);
        let mode = expanding.mode(&mut state);
        ready.extend_from_slice(&frame(&state.ready_with(viewpoint, mode)?.encode()));
        control.write_all(&ready).await.map_err(ClientError::from_write)?;
        let (tx, inbox) = mpsc::channel(256);
        let mut tasks = Vec::new();
        // After the welcome the control stream carries only the answers to edits: anything else is out of order.
        let ctl_tx = tx.clone();
        tasks.push(tokio::spawn(async move {
            let failed = loop {
                match read_frame(&mut recv, &mut decoder).await {
                    Ok(None) => return,
                    Ok(Some((m @ ServerMsg::Streaming(ServerStreaming::EditResult(_)), len))) => {
                        if ctl_tx.send(Inbound::Msg(Box::new(m), len)).await.is_err() {
                            return;
                        }
                    }
                    Ok(Some((m, _))) => {
                        break ClientError::State(StateError::Phase(canopy_protocol::messages::PhaseError {
                            phase: canopy_protocol::Phase::Streaming,
                            message: m.name(),
                        }));
                    }
                    Err(e) => break e,
                }
            };
            let _ = ctl_tx.send(Inbound::Failed(failed)).await;
        }));
        let lanes_conn = conn.clone();
        tasks.push(tokio::spawn(async move {
            let mut lanes = Vec::new();
            loop {
                let mut stream = match lanes_conn.accept_uni().await {
                    Ok(s) => s,
                    Err(e) => {
                        let _ = tx.send(Inbound::Failed(ClientError::from_session(e))).await;
                        return;
                    }
                };
                let tx = tx.clone();
                lanes.push(AbortOnDrop(vec![tokio::spawn(async move {
                    let mut decoder = FrameDecoder::new(netlimits::MAX_SERVER_FRAME);
                    loop {
                        match read_frame(&mut stream, &mut decoder).await {
                            Ok(Some((m, len))) => {
                                if tx.send(Inbound::Msg(Box::new(m), len)).await.is_err() {
                                    return;
                                }
                            }
                            Ok(None) => return,
                            Err(e) => {
                                let _ = tx.send(Inbound::Failed(e)).await;
                                return;
                            }
                        }
                    }
                })]));
            }
        }));
        Ok(Connection {
            conn,
            control,
            inbox,
            state,
            cache,
            seq: viewpoint.seq,
            refresh: Vec::new(),
            expanding,
            far: farfield::FarField::new(),
            bytes_out: (hello.len() + ready.len()) as u64,
            frame_bytes: {
                let mut b = ByKind::default();
                b[ServerMsgKind::Welcome] = welcome_len as u64;
                b
            },
            _tasks: AbortOnDrop(tasks),
        })
    }

    /// The session's state: species, cells, instances, completeness.
    pub fn state(&self) -> &ClientState {
        &self.state
    }

    /// The world built from the session's world function, once built (a connection that expands its cells).
    pub fn world(&self) -> Option<&Arc<canopy_worlds::world::World>> {
        self.expanding.built().map(|(w, _)| &w.world)
    }

    /// The welcome.
    pub fn welcome(&self) -> &Arc<Welcome> {
        self.state.welcome().expect("a connection is welcomed")
    }

    /// Bytes received on the connection (UDP payloads, QUIC overhead included).
    pub fn bytes_received(&self) -> u64 {
        quinn::Connection::stats(&self.conn).udp_rx.bytes
    }

    /// Bytes sent on the connection (UDP payloads, QUIC overhead included).
    pub fn bytes_sent(&self) -> u64 {
        quinn::Connection::stats(&self.conn).udp_tx.bytes
    }

    /// Frame bytes received by message class.
    pub fn frame_bytes_received(&self) -> ByKind<u64> {
        self.frame_bytes
    }

    /// Frame bytes the client wrote on its control stream (hello, ready, viewpoints).
    pub fn frame_bytes_sent(&self) -> u64 {
        self.bytes_out
    }

    /// Move the viewpoint: evicts what left the area of interest and tells the server. `vp.seq` is set here.
    pub async fn set_viewpoint(&mut self, mut vp: Viewpoint) -> Result<(), ClientError> {
        self.seq += 1;
        vp.seq = self.seq;
        let msg = self.state.set_viewpoint(vp)?;
        self.expanding.sweep(&self.state);
        self.far.moved();
        let bytes = frame(&msg.encode());
        self.bytes_out += bytes.len() as u64;
        self.control.write_all(&bytes).await.map_err(ClientError::from_write)
    }

    /// Say how the client wants the far field (summary nodes beyond the records), if it differs enough from the
    /// far view last sent ([`ClientState::far_view_due`]); `true` when it was taken. A client that expands its
    /// cells computes the nodes itself from the world function, and the server tells it of the edited cells within
    /// the view's range ([`Event::FarCell`]); one that takes records asks the server for the nodes. Either costs
    /// the server a request like a viewpoint does.
    pub async fn set_far_view(&mut self, view: canopy_protocol::summary::FarView) -> Result<bool, ClientError> {
        if !self.state.far_view_due(&view) {
            return Ok(false);
        }
        let msg = self.state.set_far_view(view)?;
        if self.expanding.expands(&self.state) {
            self.far.set_view(view);
        }
        self.write(&msg).await?;
        Ok(true)
    }

    /// Ask for an edit; its answer arrives as an [`Event::EditResult`] with the request number returned here.
    pub async fn edit(&mut self, op: canopy_protocol::edit::EditOp) -> Result<u32, ClientError> {
        let (request, msg) = self.state.edit(op)?;
        self.write(&msg).await?;
        Ok(request)
    }

    /// Every species of the world's table, fetched where the client does not hold it yet (waiting at most
    /// `timeout`); the graphs are then in [`Connection::state`].
    pub async fn fetch_all_species(&mut self, timeout: Duration) -> Result<(), ClientError> {
        let n = self.welcome().species.len();
        for id in 0..n {
            if self.state.species(id as u8).is_none() {
                let msg = self.state.fetch(id as u8)?;
                self.write(&msg).await?;
            }
        }
        let deadline = tokio::time::Instant::now() + timeout;
        while self.state.species_held() < n {
            match tokio::time::timeout_at(deadline, self.next_event()).await {
                Ok(r) => {
                    r?;
                }
                Err(_) => return Err(ClientError::Timeout("fetching the species")),
            }
        }
        Ok(())
    }

    async fn write(&mut self, msg: &canopy_protocol::ClientMsg) -> Result<(), ClientError> {
        let bytes = frame(&msg.encode());
        self.bytes_out += bytes.len() as u64;
        self.control.write_all(&bytes).await.map_err(ClientError::from_write)
    }

    /// Ask again for the cells whose deltas did not follow the version held; send the digests and requests for
    /// records that expanding cells gave.
    async fn send_refreshes(&mut self) -> Result<(), ClientError> {
        for c in std::mem::take(&mut self.refresh) {
            let msg = self.state.refresh(c)?;
            self.write(&msg).await?;
        }
        for msg in self.expanding.outbox(&mut self.state)? {
            self.write(&msg).await?;
        }
        Ok(())
    }

    fn apply(&mut self, inbound: Inbound) -> Result<Event, ClientError> {
        let result = match inbound {
            Inbound::Failed(e) => Err(e),
            Inbound::Msg(m, len) => {
                let m = *m;
                self.frame_bytes[m.kind()] += len as u64;
                // The program's bytes are kept only for a cache to store.
                let species = match (&m, &self.cache) {
                    (ServerMsg::Streaming(ServerStreaming::Species(s)), Some(_)) => Some(s.graph.clone()),
                    _ => None,
                };
                let ev = self.state.handle(m).map_err(ClientError::from);
                if let Ok(Event::Gap(c)) = &ev {
                    self.refresh.push(*c);
                }
                let ev = match ev {
                    Ok(e) => self.expanding.on_event(&mut self.state, &e).map(|()| e),
                    e => e,
                };
                if self.expanding.expands(&self.state)
                    && !self.far.has_source()
                    && let Some((world, expander)) = self.expanding.built()
                {
                    self.far.set_world(world, expander);
                }
                if let Ok(Event::FarCell(f)) = &ev {
                    self.far.far_cell((**f).clone());
                }
                if let (Ok(Event::Species { id, hash }), Some(bytes), Some(cache)) = (&ev, species, &self.cache)
                    && let Some(g) = self.state.species(*id)
                    && let Err(e) = cache.insert(*hash, &bytes, Arc::clone(g))
                {
                    tracing::warn!("species cache: {e}");
                }
                ev
            }
        };
        if let Err(e) = &result
            && let Some(code) = e.close_code()
        {
            self.conn.close(code as u32, e.to_string().as_bytes());
        }
        result
    }

    /// Wait for the next message from the server, or the next cell this client expanded, and apply it.
    pub async fn next_event(&mut self) -> Result<Event, ClientError> {
        self.send_refreshes().await?;
        loop {
            tokio::select! {
                biased;
                Some(e) = self.expanding.next() => return self.apply_expanded(e),
                i = self.inbox.recv() => return match i {
                    Some(i) => self.apply(i),
                    None => Err(self.closed_error()),
                },
                Some(()) = self.far.next() => {
                    if let Some(ev) = self.far.advance(&mut self.state, std::time::Instant::now()) {
                        return ev.map_err(ClientError::from);
                    }
                }
            }
        }
    }

    fn apply_expanded(&mut self, e: expanding::Done) -> Result<Event, ClientError> {
        let ev = self.expanding.on_expanded(&mut self.state, e);
        if let Ok(Event::Gap(c)) = &ev {
            self.refresh.push(*c);
        }
        ev
    }

    /// Apply a message (or an expanded cell) that has already arrived, without waiting (`None`: nothing pending).
    pub fn try_next_event(&mut self) -> Option<Result<Event, ClientError>> {
        if let Some(e) = self.expanding.try_next() {
            return Some(self.apply_expanded(e));
        }
        while self.far.try_next() {
            if let Some(ev) = self.far.advance(&mut self.state, std::time::Instant::now()) {
                return Some(ev.map_err(ClientError::from));
            }
        }
        match self.inbox.try_recv() {
            Ok(i) => Some(self.apply(i)),
            Err(mpsc::error::TryRecvError::Empty) => None,
            Err(mpsc::error::TryRecvError::Disconnected) => Some(Err(self.closed_error())),
        }
    }

    fn closed_error(&self) -> ClientError {
        match self.conn.close_reason() {
            Some(e) => ClientError::from_session(e),
            None => ClientError::Ended("while streaming"),
        }
    }

    /// The server this session is with.
    pub fn server(&self) -> SocketAddr {
        self.conn.remote_address()
    }

    /// Wait until the area of interest is complete (or `timeout` passes).
    pub async fn wait_complete(&mut self, timeout: Duration) -> Result<(), ClientError> {
        let deadline = tokio::time::Instant::now() + timeout;
        while !self.state.is_complete() {
            match tokio::time::timeout_at(deadline, self.next_event()).await {
                Ok(r) => {
                    r?;
                }
                Err(_) => return Err(ClientError::Timeout("waiting for a complete area of interest")),
            }
        }
        Ok(())
    }

    /// End the session normally.
    pub fn close(self) {
        self.conn.close(CloseCode::Normal as u32, b"bye");
    }

    /// End the session normally and keep what it received.
    pub fn close_into_state(self) -> ClientState {
        self.conn.close(CloseCode::Normal as u32, b"bye");
        self.state
    }
}
