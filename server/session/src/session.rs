//! The sans-IO session core: one client's handshake, area of interest, what it holds, what to send next and when.
//!
//! Like quinn-proto, it has no sockets and reads no clock: the driver feeds it `now` and the client's messages,
//! polls it for [`Transmit`]s to write, reports how many bytes the transport took ([`Session::on_flushed`]), and
//! wakes it at [`Session::poll_timeout`]. Tests drive it on virtual time.
//!
//! What it decides (seed 001 §4, demand-driven transmission):
//! - the area of interest from the viewpoint's position, heading and velocity ([`canopy_protocol::aoi`]): cells
//!   within the radius of the position or of the look-ahead point are sent, held cells beyond radius + hysteresis
//!   are released;
//! - the order: nearest first, cells in view before cells behind (a cell out of view counts
//!   [`OUT_OF_VIEW_FACTOR`] times its distance), a started cell finished before the next;
//! - species once: a species goes out just before the first batch that needs it, unless the client said it holds
//!   it;
//! - pacing: an optional token bucket (bandwidth cap) and a window of bytes handed to the transport but not yet
//!   flushed, so a slow link always gets the most important records next rather than a backlog of stale ones.
//!
//! What it sends per instance and species is the [`Payload`]: the species programs and instance records
//! (procedural, the default), or — for the bandwidth baselines of `canopy bandwidth` — explicit geometry in their
//! place, decided by the same area of interest, order and pacing: every instance's own mesh ([`PayloadMode::UniqueMesh`])
//! or one mesh per species plus per-instance transforms ([`PayloadMode::Instanced`]). The records still go out in
//! the explicit modes (a few bytes each), so the client's bookkeeping of what it holds stays the same.

use std::collections::{BTreeSet, HashMap, HashSet, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;
use canopy_protocol::aoi::{Aoi, AoiParams, Viewpoint};
use canopy_protocol::edit::{EditOp, EditOutcome, ResumeCell};
use canopy_protocol::messages::{
    CellDigest, ClientHandshake, ClientStreaming, GeometryChunk, GeometryKind, MessageError, PhaseError, Release,
    ServerMsgKind, ServerStreaming,
};
use canopy_protocol::{CellCoord, ClientMsg, CloseCode, InstanceId, PROTOCOL_VERSION, Phase, ServerMsg, netlimits};

use crate::editors::{Editor, Editors};
use crate::far::{Eye, FarSession};
use crate::pacing::SendBudget;
use crate::pacing::TokenBucket;
use crate::store::{CellData, CellState, CellWaker, WorldStore};
use crate::transmit::{StreamId, Transmit};

mod edits;
mod expand;
mod far_edits;
mod stats;

pub use far_edits::{MAX_FAR_CELLS, cells_in};

pub use stats::SessionStats;

/// Most edits of one session handed to the writer and not yet answered; more are denied until answers come.
pub const MAX_EDITS_IN_FLIGHT: usize = 256;

/// Most digests of a session waiting to be checked; more are not checked (the client samples, the server need not
/// keep up with a flood).
pub(crate) const MAX_DIGESTS_WAITING: usize = 16;

/// Most cells a client that expands cells may ask records for in one session (beyond, its asks are ignored and it
/// keeps its grants).
pub(crate) const MAX_RECORD_CELLS: usize = 4096;

/// A cell out of view is scheduled as if it were this many times farther away.
pub const OUT_OF_VIEW_FACTOR: f32 = 2.0;

use crate::payload::{Payload, PayloadMode};

/// How a session behaves.
#[derive(Clone, Debug, PartialEq)]
pub struct SessionConfig {
    /// The area-of-interest rules (announced in the welcome).
    pub aoi: AoiParams,
    /// Records per cell batch (at most [`netlimits::MAX_BATCH_RECORDS`]).
    pub batch_records: usize,
    /// Bandwidth cap in bytes per second (`None`: as fast as the transport takes it).
    pub bandwidth: Option<u64>,
    /// Bytes the bucket holds when full.
    pub burst: u64,
    /// Most bytes handed to the transport and not yet flushed.
    pub window: usize,
    /// Ordered lanes (streams) by priority; lane 0 is the most important.
    pub lanes: u8,
    /// Full angle of the view cone, degrees: cells inside it are in view.
    pub fov_deg: f32,
    /// How long a client may take from connecting to being ready.
    pub handshake_timeout: Duration,
    /// What goes out per instance and species (procedural unless a bandwidth baseline asks otherwise).
    pub payload: Payload,
    /// Most viewpoints a second a client may send, and the burst; faster is a flood and ends the session
    /// (viewpoints are never coalesced: each one releases cells on both sides).
    pub viewpoint_rate: (u32, u32),
    /// The budget of unflushed bytes shared by every session of a server (`None`: only each session's window).
    pub send_budget: Option<Arc<SendBudget>>,
    /// Who may edit (`None`: every session is read-only).
    pub editors: Option<Arc<Editors>>,
}

impl Default for SessionConfig {
    fn default() -> Self {
        SessionConfig {
            aoi: AoiParams::default(),
            batch_records: 128,
            bandwidth: None,
            burst: 16 * 1024,
            window: 64 * 1024,
            lanes: 4,
            fov_deg: canopy_protocol::farview::DEFAULT_FOV_DEG,
            handshake_timeout: Duration::from_secs(10),
            payload: Payload::default(),
            viewpoint_rate: (50, 100),
            send_budget: None,
            editors: None,
        }
    }
}

/// Why a session must end. Each maps to a [`CloseCode`] and a reason for the client.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SessionError {
    /// A message is not legal in the session's phase.
    #[error(transparent)]
    Phase(#[from] PhaseError),
    /// A message did not decode or is not acceptable.
    #[error(transparent)]
    Message(#[from] MessageError),
    /// The client speaks another protocol version.
    #[error("client speaks protocol version {client}, server speaks {server}")]
    Version {
        /// The client's version.
        client: u16,
        /// Ours.
        server: u16,
    },
    /// A viewpoint's sequence number did not increase.
    #[error("viewpoint {seq} does not follow viewpoint {last}")]
    Stale {
        /// The new sequence number.
        seq: u32,
        /// The last one.
        last: u32,
    },
    /// The have-list names a species id outside the table.
    #[error("have-list names species {0}, which is not in the table")]
    UnknownSpecies(u8),
    /// The client did not finish its handshake in time.
    #[error("handshake not finished within {0:?}")]
    HandshakeTimeout(Duration),
    /// Viewpoints (with refreshes and refused edits) arrive faster than the session's rate allows.
    #[error("viewpoints, refreshes and refused edits faster than {0} a second")]
    ViewpointFlood(u32),
    /// The resume messages name more cells than allowed, or not in increasing order.
    #[error("resume names more than {0} cells or repeats one")]
    Resume(usize),
}

impl SessionError {
    /// The close code for this error.
    pub fn close_code(&self) -> CloseCode {
        match self {
            SessionError::Phase(_) | SessionError::Stale { .. } => CloseCode::OutOfOrder,
            SessionError::Message(e) => e.close_code(),
            SessionError::Version { .. } => CloseCode::Version,
            SessionError::UnknownSpecies(_) => CloseCode::Invalid,
            SessionError::HandshakeTimeout(_) => CloseCode::Timeout,
            SessionError::ViewpointFlood(_) | SessionError::Resume(_) => CloseCode::Invalid,
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct Held {
    grant: u32,
    lane: u8,
    sent: u16,
    total: u16,
    /// The cell's version the client holds (or is being sent).
    version: u32,
    /// Granted to expand (no records sent).
    expanded: bool,
}

/// One client's session (see the module docs).
pub struct Session {
    store: Arc<dyn WorldStore>,
    cfg: SessionConfig,
    phase: Phase,
    deadline: Instant,
    client: String,
    has_species: [u64; 4],
    viewpoint: Option<Viewpoint>,
    /// The area of interest of `viewpoint`.
    aoi: Option<Aoi>,
    dirty: bool,
    held: HashMap<CellCoord, Held>,
    /// Cells begun and not finished: kept alive here whatever the store evicts, so every batch of a grant comes
    /// from the same records.
    pinned: HashMap<CellCoord, Arc<CellData>>,
    /// Woken by the store when a cell this session found pending is ready.
    waker: Option<Arc<dyn CellWaker>>,
    /// Cells found pending at store generation `waiting.0`: not asked again until the generation changes.
    waiting: (u64, HashSet<CellCoord>),
    /// Cells this session's waker waits for in the store: told to the store when no longer wanted.
    registered: HashSet<CellCoord>,
    /// Cells to send (or finish), least important first, so the next is at the end.
    queue: Vec<(f32, CellCoord)>,
    urgent: VecDeque<Transmit>,
    /// Messages of a started unit (a batch and the geometry before it), paced like batches; by cell, so a release
    /// can take back what has not gone out.
    staged: VecDeque<(CellCoord, Transmit)>,
    next_grant: u32,
    bucket: Option<TokenBucket>,
    /// Viewpoints a client may still send (one token each).
    viewpoints: TokenBucket,
    unflushed: usize,
    /// When the shared send budget last paused this session.
    paused: Option<Instant>,
    stats: SessionStats,
    /// The editor the hello's token names (`None`: read-only).
    editor: Option<Arc<Editor>>,
    /// Edits to hand to the writer: `(request, op)`.
    edits_out: VecDeque<(u32, EditOp)>,
    /// Edits handed out and not answered yet.
    edits_in_flight: usize,
    /// Held cells that may have changed since the version the client holds, and the store generation they were
    /// last looked at (a cell still expanding is looked at again when it moves).
    changed: (BTreeSet<CellCoord>, Option<u64>),
    /// Cells a reconnecting client said it holds (between the welcome and `ready`).
    resume: Vec<ResumeCell>,
    /// The far view, once the client asked for one: summary nodes beyond the records.
    far: Option<FarSession>,
    /// The client expands cells itself ([`CellMode::Expand`]): it gets grants, not records.
    expand: bool,
    /// For a client that expands cells and said how far it sees: the edited cells beyond its area of interest it
    /// is told of (it computes its far view itself).
    far_edits: Option<far_edits::FarEdits>,
    /// Cells this client takes as records although it expands cells (it asked, or its digest differed).
    record_cells: HashSet<CellCoord>,
    /// Digests to check, and the store generation they were last looked at.
    digests: (VecDeque<CellDigest>, Option<u64>),
}

impl Drop for Session {
    fn drop(&mut self) {
        // Whatever was never flushed goes back to the shared budget with the session.
        if let Some(b) = &self.cfg.send_budget {
            b.sub(self.unflushed);
        }
        // Cells queued for this session alone are not expanded after it.
        if let Some(w) = &self.waker {
            for c in self.registered.drain() {
                self.store.unwait(c, w);
            }
        }
    }
}

impl std::fmt::Debug for Session {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Session")
            .field("client", &self.client)
            .field("phase", &self.phase)
            .field("held", &self.held.len())
            .field("queue", &self.queue.len())
            .finish()
    }
}

impl Session {
    /// A new session for a client that just connected at `now`.
    pub fn new(store: Arc<dyn WorldStore>, mut cfg: SessionConfig, now: Instant) -> Session {
        cfg.batch_records = cfg.batch_records.clamp(1, netlimits::MAX_BATCH_RECORDS);
        cfg.lanes = cfg.lanes.clamp(1, 8);
        let bucket = cfg.bandwidth.map(|rate| TokenBucket::new(rate, cfg.burst, now));
        let (rate, burst) = cfg.viewpoint_rate;
        let viewpoints = TokenBucket::new(u64::from(rate), u64::from(burst), now);
        Session {
            store,
            deadline: now + cfg.handshake_timeout,
            cfg,
            phase: Phase::Start,
            client: String::new(),
            has_species: [0; 4],
            viewpoint: None,
            aoi: None,
            dirty: false,
            held: HashMap::new(),
            pinned: HashMap::new(),
            waker: None,
            waiting: (0, HashSet::new()),
            registered: HashSet::new(),
            queue: Vec::new(),
            urgent: VecDeque::new(),
            staged: VecDeque::new(),
            next_grant: 1,
            bucket,
            viewpoints,
            unflushed: 0,
            paused: None,
            stats: SessionStats::default(),
            editor: None,
            edits_out: VecDeque::new(),
            edits_in_flight: 0,
            changed: (BTreeSet::new(), None),
            resume: Vec::new(),
            far: None,
            far_edits: None,
            expand: false,
            record_cells: HashSet::new(),
            digests: (VecDeque::new(), None),
        }
    }

    /// Release a held grant now (its release goes out on its lane) and forget it.
    fn release(&mut self, cell: CellCoord) {
        let Some(h) = self.held.remove(&cell) else { return };
        self.pinned.remove(&cell);
        self.staged.retain(|(c, _)| *c != cell);
        self.changed.0.remove(&cell);
        let msg = ServerMsg::Streaming(ServerStreaming::Release(Release { cell, grant: h.grant }));
        self.urgent.push_back(Self::transmit(StreamId::Lane(h.lane), &msg));
    }

    /// Have `waker` woken when a cell this session asked for and found pending is ready (then poll again). A
    /// session never waits for a cell: it sends the next ready one meanwhile.
    pub fn set_cell_waker(&mut self, waker: Arc<dyn CellWaker>) {
        self.waker = Some(waker);
    }

    /// The phase the session is in.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// The client's label from its hello.
    pub fn client(&self) -> &str {
        &self.client
    }

    /// What has been sent so far.
    pub fn stats(&self) -> &SessionStats {
        &self.stats
    }

    /// The latest viewpoint.
    pub fn viewpoint(&self) -> Option<&Viewpoint> {
        self.viewpoint.as_ref()
    }

    /// Cells the client holds or is being sent, with their grant.
    pub fn held_cells(&self) -> impl Iterator<Item = (CellCoord, u32)> + '_ {
        self.held.iter().map(|(c, h)| (*c, h.grant))
    }

    /// Whether every cell of the current area of interest has been sent in full.
    pub fn is_complete(&self) -> bool {
        self.phase == Phase::Streaming && !self.dirty && self.queue.is_empty() && self.staged.is_empty()
    }

    /// Whether the client holds (or has been sent) species `id`.
    pub fn has_species(&self, id: u8) -> bool {
        self.has_species[usize::from(id / 64)] & (1 << (id % 64)) != 0
    }

    fn set_species(&mut self, id: u8) {
        self.has_species[usize::from(id / 64)] |= 1 << (id % 64);
    }

    /// Decode and handle one frame from the control stream.
    pub fn handle_frame(&mut self, now: Instant, frame: &[u8]) -> Result<(), SessionError> {
        // The decoder validates.
        self.handle_valid(now, ClientMsg::decode(frame)?)
    }

    /// Handle one decoded message from the client.
    pub fn handle(&mut self, now: Instant, msg: ClientMsg) -> Result<(), SessionError> {
        msg.validate()?;
        self.handle_valid(now, msg)
    }

    fn handle_valid(&mut self, now: Instant, msg: ClientMsg) -> Result<(), SessionError> {
        let next = msg.next_phase(self.phase)?;
        match msg {
            ClientMsg::Handshake(ClientHandshake::Hello(h)) => {
                if h.version != PROTOCOL_VERSION {
                    return Err(SessionError::Version { client: h.version, server: PROTOCOL_VERSION });
                }
                self.client = h.client;
                self.editor = match (&h.token, &self.cfg.editors) {
                    (Some(token), Some(editors)) => editors.find(token),
                    _ => None,
                };
                // The hello moves to `next` (Hello), the welcome sent at once on to the phase after it.
                self.phase = ServerMsgKind::Welcome.next_phase(next)?;
                let bytes = Bytes::from(self.store.welcome_head().framed(&self.cfg.aoi));
                let t = Transmit {
                    stream: StreamId::Control,
                    bytes,
                    body: Bytes::new(),
                    class: ServerMsgKind::Welcome,
                    records: 0,
                };
                self.urgent.push_back(t);
            }
            ClientMsg::Handshake(ClientHandshake::Ready(r)) => {
                let table = self.store.species().len();
                if let Some(&bad) = r.have.iter().find(|&&id| usize::from(id) >= table) {
                    return Err(SessionError::UnknownSpecies(bad));
                }
                for id in r.have {
                    self.set_species(id);
                }
                self.phase = next;
                self.start_expanding(r.cells);
                // Resumed cells take grants 1, 2, … in the order named; what changed since their version is sent
                // once the store knows (those the viewpoint does not keep are released at once).
                let grid = *self.store.grid();
                for rc in std::mem::take(&mut self.resume) {
                    let grant = self.next_grant;
                    self.next_grant += 1;
                    if grid.contains(rc.cell) {
                        let h = Held { grant, lane: 0, sent: 0, total: 0, version: rc.version, expanded: false };
                        self.held.insert(rc.cell, h);
                        self.changed.0.insert(rc.cell);
                    } else {
                        let msg = ServerMsg::Streaming(ServerStreaming::Release(Release { cell: rc.cell, grant }));
                        self.urgent.push_back(Self::transmit(StreamId::Lane(0), &msg));
                    }
                }
                self.set_viewpoint(r.viewpoint);
            }
            ClientMsg::Handshake(ClientHandshake::Resume(r)) => {
                let ordered = match (self.resume.last(), r.cells.first()) {
                    (Some(a), Some(b)) => a.cell < b.cell,
                    _ => true,
                };
                if !ordered || self.resume.len() + r.cells.len() > netlimits::MAX_RESUME_CELLS {
                    return Err(SessionError::Resume(netlimits::MAX_RESUME_CELLS));
                }
                self.resume.extend(r.cells);
                self.phase = next;
            }
            ClientMsg::Streaming(ClientStreaming::Edit(e)) => {
                self.stats.edits += 1;
                let denied = match &self.editor {
                    None => Some("read-only session: connect with an editor token".to_string()),
                    Some(_) if self.edits_in_flight >= MAX_EDITS_IN_FLIGHT => {
                        Some("too many edits waiting for an answer".to_string())
                    }
                    Some(editor) if !editor.take(now) => {
                        Some(format!("over {}'s rate of {} edits a second", editor.name, editor.rate))
                    }
                    Some(_) => None,
                };
                match denied {
                    Some(why) => {
                        // Refused edits cost the server an answer each: they draw on the same budget as
                        // viewpoints, so a flood of them ends the session instead of queueing answers.
                        self.take_request(now)?;
                        self.stats.edits_denied += 1;
                        self.answer(e.request, EditOutcome::Denied(why));
                    }
                    None => {
                        self.edits_in_flight += 1;
                        self.edits_out.push_back((e.request, e.op));
                    }
                }
            }
            ClientMsg::Streaming(ClientStreaming::Fetch(id)) => {
                if usize::from(id) >= self.store.species().len() {
                    return Err(SessionError::UnknownSpecies(id));
                }
                self.send_species_once(id, StreamId::Lane(0));
            }
            ClientMsg::Streaming(ClientStreaming::Refresh(c)) => {
                // A refresh sends a whole cell again: at most as often as viewpoints.
                self.take_request(now)?;
                if self.held.contains_key(&c) {
                    self.release(c);
                    self.dirty = true;
                }
            }
            ClientMsg::Streaming(ClientStreaming::Records(c)) => self.on_records(now, c)?,
            ClientMsg::Streaming(ClientStreaming::Digest(d)) => self.on_digest(now, d)?,
            ClientMsg::Streaming(ClientStreaming::FarView(f)) => {
                // Each far view costs a rebuild: the same budget as viewpoints. A client that expands cells computes
                // its far view itself and is told only of the edited cells within its range.
                self.take_request(now)?;
                if self.expand {
                    match &mut self.far_edits {
                        Some(far) => far.set_range(f.range),
                        None => self.far_edits = Some(far_edits::FarEdits::new(f.range)),
                    }
                } else {
                    match &mut self.far {
                        Some(far) => far.set_view(f),
                        None => self.far = Some(FarSession::new(f)),
                    }
                }
            }
            ClientMsg::Streaming(ClientStreaming::Viewpoint(v)) => {
                let last = self.viewpoint.map_or(0, |v| v.seq);
                if v.seq <= last {
                    return Err(SessionError::Stale { seq: v.seq, last });
                }
                // A flood of viewpoints costs the server a release pass each: bounded by a token bucket.
                self.take_request(now)?;
                self.set_viewpoint(v);
            }
        }
        Ok(())
    }

    /// Take one request (a viewpoint, a refresh, a refused edit: each costs the server work or an answer) from the
    /// session's budget; past it the client floods and the session ends.
    fn take_request(&mut self, now: Instant) -> Result<(), SessionError> {
        if !self.viewpoints.ready(now) {
            return Err(SessionError::ViewpointFlood(self.cfg.viewpoint_rate.0));
        }
        self.viewpoints.take(now, 1);
        Ok(())
    }

    /// Send species `id`'s program on `stream` now, unless the client holds it or was sent it.
    fn send_species_once(&mut self, id: u8, stream: StreamId) {
        if !self.has_species(id)
            && let Some(bytes) = self.store.species_frame(id)
        {
            self.set_species(id);
            let t = Transmit { stream, bytes, body: Bytes::new(), class: ServerMsgKind::Species, records: 0 };
            self.urgent.push_back(t);
        }
    }

    /// Take a new viewpoint. Releases happen now, viewpoint by viewpoint, exactly as the client evicts when it sends
    /// each one (the same rule on the same inputs), so both sides agree on what is held; the send queue is rebuilt
    /// lazily, once for however many viewpoints arrived before the next poll.
    fn set_viewpoint(&mut self, v: Viewpoint) {
        self.stats.viewpoints += 1;
        self.viewpoint = Some(v);
        let aoi = Aoi::new(&v, &self.cfg.aoi);
        let store = Arc::clone(&self.store);
        let grid = store.grid();
        let mut gone: Vec<(CellCoord, Held)> =
            self.held.iter().filter(|(c, _)| !aoi.is_kept(grid, **c)).map(|(c, h)| (*c, *h)).collect();
        gone.sort_unstable_by_key(|(c, _)| *c);
        for (cell, _) in gone {
            self.release(cell);
        }
        self.aoi = Some(aoi);
        self.dirty = true;
        if let Some(far) = &mut self.far {
            far.moved();
        }
    }

    /// Check the handshake deadline.
    pub fn handle_timeout(&mut self, now: Instant) -> Result<(), SessionError> {
        if self.phase != Phase::Streaming && now >= self.deadline {
            return Err(SessionError::HandshakeTimeout(self.cfg.handshake_timeout));
        }
        Ok(())
    }

    /// When to call [`Session::handle_timeout`] and poll again, if nothing else happens first.
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.phase != Phase::Streaming {
            return Some(self.deadline);
        }
        let far_due = self.far.as_ref().and_then(|f| f.due_at(&*self.store));
        let look_due = self.far_edits.as_ref().and_then(|f| f.look_due());
        let far_due = match (far_due, look_due) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        let far_work = self.far_work();
        if self.queue.is_empty() && self.staged.is_empty() && !far_work {
            return far_due;
        }
        // Paused by the shared budget: other sessions' flushes do not wake this one, so look again shortly.
        if let Some(at) = self.paused {
            return Some(at + Duration::from_millis(5));
        }
        let paced = self.bucket.as_ref().and_then(TokenBucket::ready_at);
        match (paced, far_due) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// The transport took `bytes` of what was transmitted (reopens the window).
    pub fn on_flushed(&mut self, bytes: usize) {
        let n = bytes.min(self.unflushed);
        self.unflushed -= n;
        if let Some(b) = &self.cfg.send_budget {
            b.sub(n);
        }
    }

    /// Bytes handed to the transport and not yet flushed.
    pub fn unflushed(&self) -> usize {
        self.unflushed
    }

    /// The next message to write, or `None` until a message arrives, bytes are flushed or the timeout passes.
    pub fn poll_transmit(&mut self, now: Instant) -> Option<Transmit> {
        if self.dirty {
            self.update_aoi();
        }
        self.send_changes();
        self.check_digests();
        self.update_far(now);
        self.look_for_far_cells(now);
        if let Some(t) = self.urgent.pop_front() {
            return Some(self.account(now, t));
        }
        let far_work = self.far_work();
        let idle = self.queue.is_empty() && self.staged.is_empty() && !far_work;
        if self.phase != Phase::Streaming || idle || self.unflushed >= self.cfg.window {
            return None;
        }
        if self.cfg.send_budget.as_ref().is_some_and(|b| b.spent()) {
            self.paused = Some(now);
            return None;
        }
        self.paused = None;
        if let Some(b) = &mut self.bucket
            && !b.ready(now)
        {
            return None;
        }
        if self.staged.is_empty() {
            // Summaries take their turn, or go when no cell is ready.
            let cell_bytes = self.stats.bytes[ServerMsgKind::Cells];
            if far_work
                && (self.queue.is_empty() || self.far.as_ref().is_some_and(|f| f.turn(cell_bytes)))
                && let Some(t) = self.next_far_batch()
            {
                return Some(self.account(now, t));
            }
            // Nothing staged and no queued cell ready: the store wakes the session's waker when one is.
            if !self.stage_next_unit() {
                let t = if far_work { self.next_far_batch() } else { None };
                return t.map(|t| self.account(now, t));
            }
        }
        let (cell, t) = self.staged.pop_front()?;
        if self.changed.0.contains(&cell) {
            // Its changes wait for its batches: look again once this one is out.
            self.changed.1 = None;
        }
        Some(self.account(now, t))
    }

    /// Rebuild the far view's queue if due (see [`FarSession::update`]).
    fn update_far(&mut self, now: Instant) {
        let (Some(far), Some(vp), Some(aoi)) = (&mut self.far, self.viewpoint, self.aoi) else { return };
        let eye = Eye::new(&aoi, vp.heading(), self.cfg.fov_deg);
        far.update(now, &*self.store, self.waker.as_ref(), &eye);
    }

    /// The far view's next message, on the last lane: an edited cell beyond the area of interest, else summaries.
    fn next_far_batch(&mut self) -> Option<Transmit> {
        if let Some(t) = self.next_far_cell() {
            return Some(t);
        }
        let lane = self.cfg.lanes - 1;
        self.far.as_mut()?.next_batch(&*self.store, self.waker.as_ref(), lane)
    }

    /// Whether the far view has something to send: summaries, or edited cells beyond the area of interest.
    fn far_work(&self) -> bool {
        self.far.as_ref().is_some_and(FarSession::has_work) || self.far_edits.as_ref().is_some_and(|f| f.has_work())
    }

    /// The far view, once the client asked for one.
    pub fn far(&self) -> Option<&FarSession> {
        self.far.as_ref()
    }

    fn account(&mut self, now: Instant, t: Transmit) -> Transmit {
        let len = t.len();
        self.stats.bytes[t.class] += len as u64;
        self.stats.messages[t.class] += 1;
        self.stats.records += u64::from(t.records);
        self.unflushed += len;
        if let Some(b) = &self.cfg.send_budget {
            b.add(len);
        }
        if let Some(b) = &mut self.bucket {
            b.take(now, len);
        }
        t
    }

    fn transmit(stream: StreamId, msg: &ServerMsg) -> Transmit {
        let bytes = Bytes::from(msg.encode_framed());
        Transmit { stream, bytes, body: Bytes::new(), class: msg.kind(), records: msg.records() }
    }

    /// Rebuild the send queue for the latest viewpoint: what the area of interest needs, in priority order.
    fn update_aoi(&mut self) {
        self.dirty = false;
        let (Some(vp), Some(aoi)) = (self.viewpoint, self.aoi) else { return };
        let store = Arc::clone(&self.store);
        let grid = store.grid();
        let heading = vp.heading();
        let cos_half = (self.cfg.fov_deg.to_radians() * 0.5).cos();
        let near = grid.cell_size;
        let key = |c: CellCoord| {
            let d = grid.distance2(c, aoi.position).sqrt();
            let [dx, dz] = grid.centre_offset(c, aoi.position);
            let len = grid.centre_distance2(c, aoi.position).sqrt();
            let in_view = d <= near || len == 0.0 || (dx * heading[0] + dz * heading[1]) >= cos_half * len;
            if in_view { d } else { d * OUT_OF_VIEW_FACTOR }
        };
        self.queue.clear();
        for c in aoi.inner_cells(grid) {
            match self.held.get(&c) {
                Some(h) if h.sent >= h.total => {}
                _ => self.queue.push((key(c), c)),
            }
        }
        // Held cells in the hysteresis band that are not finished yet are finished too: the client keeps them.
        let mut band: Vec<CellCoord> =
            self.held.iter().filter(|(c, h)| h.sent < h.total && !aoi.is_inner(grid, **c)).map(|(c, _)| *c).collect();
        band.sort_unstable();
        self.queue.extend(band.into_iter().map(|c| (key(c), c)));
        // Least important first; ties by cell so the order is deterministic.
        self.queue.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(b.1.cmp(&a.1)));
        // Cells waited for that the area of interest no longer holds: the store need not expand them for us.
        if let Some(w) = &self.waker
            && !self.registered.is_empty()
        {
            let queued: HashSet<CellCoord> = self.queue.iter().map(|q| q.1).collect();
            let gone: Vec<CellCoord> = self.registered.iter().filter(|c| !queued.contains(c)).copied().collect();
            for c in gone {
                self.registered.remove(&c);
                store.unwait(c, w);
            }
        }
    }

    fn lane_for(&self, key: f32) -> u8 {
        let radius = self.aoi.map_or(1.0, |a| a.radius.max(1.0));
        let lanes = f32::from(self.cfg.lanes);
        ((key / radius * lanes).max(0.0) as u32).min(u32::from(self.cfg.lanes) - 1) as u8
    }

    /// Stage `blob` as geometry chunks for `cell` on `lane` (before whatever is staged after them).
    fn stage_geometry(&mut self, cell: CellCoord, lane: u8, kind: GeometryKind, id: u64, blob: &[u8]) {
        if blob.len() > netlimits::MAX_GEOMETRY_BYTES {
            self.stats.oversize += 1;
            return;
        }
        let total = blob.len() as u32;
        let mut offset = 0usize;
        loop {
            let end = (offset + netlimits::MAX_GEOMETRY_CHUNK).min(blob.len());
            let chunk = GeometryChunk { kind, id, offset: offset as u32, total, bytes: blob[offset..end].to_vec() };
            let msg = ServerMsg::Streaming(ServerStreaming::Geometry(chunk));
            let t = Self::transmit(StreamId::Lane(lane), &msg);
            self.staged.push_back((cell, t));
            offset = end;
            if offset >= blob.len() {
                return;
            }
        }
    }

    /// Stage the next unit of the most important queued cell that is ready: a species (its program, or its mesh
    /// when instanced), or a batch with, in the explicit modes, its geometry before it. Cells found pending are
    /// skipped (their expansion queued, the waker registered); `false` when no queued cell is ready.
    fn stage_next_unit(&mut self) -> bool {
        let store = Arc::clone(&self.store);
        // Read before asking: a cell that becomes ready after it was found pending changes the generation.
        let generation = store.generation();
        if generation != self.waiting.0 {
            self.waiting = (generation, HashSet::new());
        }
        for i in (0..self.queue.len()).rev() {
            let (key, cell) = self.queue[i];
            if self.waiting.1.contains(&cell) {
                continue;
            }
            if self.expand && !self.pinned.contains_key(&cell) && !self.record_cells.contains(&cell) {
                match self.grant(&*store, cell, key) {
                    Some(true) => {
                        self.queue.remove(i);
                        return true;
                    }
                    Some(false) => {
                        self.waiting.1.insert(cell);
                        self.registered.insert(cell);
                        continue;
                    }
                    // No delta from version 0 can be made: this cell goes as records.
                    None => {
                        self.record_cells.insert(cell);
                    }
                }
            }
            let data = match self.pinned.get(&cell) {
                Some(d) => Arc::clone(d),
                None => match store.cell(cell, self.waker.as_ref()) {
                    CellState::Ready(d) => {
                        self.registered.remove(&cell);
                        d
                    }
                    CellState::Pending => {
                        self.waiting.1.insert(cell);
                        self.registered.insert(cell);
                        continue;
                    }
                    CellState::Outside => unreachable!("queued cells are in the grid"),
                },
            };
            self.stage_cell(i, key, &data);
            return true;
        }
        false
    }

    /// Stage the next unit of queued cell `i` (see [`Session::stage_next_unit`]), its records `data`.
    fn stage_cell(&mut self, i: usize, key: f32, data: &Arc<CellData>) {
        let (store, cell) = (Arc::clone(&self.store), data.cell);
        let total = data.records.len() as u16;
        let h = match self.held.get(&cell) {
            Some(h) => *h,
            None => {
                let lane = self.lane_for(key);
                let h = Held { grant: self.next_grant, lane, sent: 0, total, version: data.version, expanded: false };
                self.next_grant = self.next_grant.wrapping_add(1).max(1);
                self.stats.grants += 1;
                self.held.insert(cell, h);
                h
            }
        };
        let mode = self.cfg.payload.effective();
        let geometry = self.cfg.payload.geometry.clone();
        // Baseline 1 sends one instance per unit, so its mesh and record go out together and pacing stays fine.
        let per_unit = if mode == PayloadMode::UniqueMesh { 1 } else { self.cfg.batch_records };
        let start = usize::from(h.sent);
        let end = (start + per_unit).min(usize::from(total));
        let records = &data.records[start..end];
        let lane = StreamId::Lane(h.lane);
        // A species goes out just before the first batch that needs it, on the same lane: its program, or its mesh
        // when instanced; unique meshes need none.
        if mode != PayloadMode::UniqueMesh
            && let Some(r) = records.iter().find(|r| !self.has_species(r.species))
        {
            let id = r.species;
            self.set_species(id);
            match (mode, &geometry) {
                (PayloadMode::Instanced, Some(g)) => {
                    let blob = g.species_mesh(id);
                    self.stage_geometry(cell, h.lane, GeometryKind::SpeciesMesh, u64::from(id), &blob);
                }
                // A live store serves no record of a species the table lacks (stored edits are checked when read);
                // should one come anyway, the client refuses its cell, and the session goes on.
                _ => {
                    if let Some(bytes) = store.species_frame(id) {
                        let t = Transmit {
                            stream: lane,
                            bytes,
                            body: Bytes::new(),
                            class: ServerMsgKind::Species,
                            records: 0,
                        };
                        self.staged.push_back((cell, t));
                    }
                }
            }
            self.pinned.insert(cell, Arc::clone(data));
            return;
        }
        // Record `i` of the cell is the instance `(cell, i)`.
        let id = |i: usize| InstanceId::new(cell, i as u16).expect("a store's cells can be named");
        match (mode, &geometry) {
            (PayloadMode::UniqueMesh, Some(g)) => {
                for id in (start..end).map(id) {
                    let blob = g.instance_mesh(id);
                    self.stage_geometry(cell, h.lane, GeometryKind::InstanceMesh, id.0, &blob);
                }
            }
            (PayloadMode::Instanced, Some(g)) if !records.is_empty() => {
                let blob = g.transforms(cell, start as u16..end as u16);
                self.stage_geometry(cell, h.lane, GeometryKind::Transforms, id(start).0, &blob);
            }
            _ => {}
        }
        if let Some(held) = self.held.get_mut(&cell) {
            held.sent = end as u16;
        }
        if end >= usize::from(total) {
            self.queue.remove(i);
            self.pinned.remove(&cell);
        } else {
            self.pinned.insert(cell, Arc::clone(data));
        }
        // Procedurally, the batch's body is the cell's, encoded once and shared; this session adds its head.
        let shared = (mode == PayloadMode::Procedural)
            .then(|| data.bodies(self.cfg.batch_records))
            .flatten()
            .and_then(|b| b.get(start / per_unit))
            .filter(|b| usize::from(b.start) == start && usize::from(b.end) == end);
        let t = match shared {
            Some(b) => Transmit {
                stream: lane,
                bytes: b.head(cell, h.grant),
                body: b.body.clone(),
                class: ServerMsgKind::Cells,
                records: (end - start) as u32,
            },
            None => {
                Self::transmit(lane, &ServerMsg::Streaming(ServerStreaming::Cells(data.batch(h.grant, start, end))))
            }
        };
        self.staged.push_back((cell, t));
    }
}
