//! The browser client's sans-IO driver: what `canopy_client::net::Connection` does around [`ClientState`], minus
//! QUIC, tokio and worker threads. Bytes read from the control stream and from each lane go in; the bytes to write
//! on the control stream come out ([`Session::take_outbox`]); granted cells are expanded a few at a time, nearest
//! first, whenever the page has time for them ([`Session::expand`]); nothing here reads a clock or touches a socket.
//!
//! The protocol is the native client's: the client opens one bidirectional stream (control) and writes
//! length-prefixed frames on it: hello, then, once the welcome has been read on the same stream, the ready with the
//! first viewpoint, and later viewpoints as the camera moves ([`canopy_client::state::viewpoint_due`]). The server
//! opens unidirectional lanes and writes species, cell batches, grants, releases and deltas on them; after the
//! welcome the control stream carries only edit results. Anything wrong from the server closes the session with a
//! [`CloseCode`] and a reason ([`Session::take_close`] says which, for the driver to close the transport with).

use std::sync::Arc;
use std::time::Duration;

use canopy_client::state::{ClientState, Event, StateError, viewpoint_due};
use canopy_protocol::aoi::{Grid, Viewpoint};
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_protocol::frame::{FrameDecoder, FrameError, frame};
use canopy_protocol::messages::{CellMode, PhaseError, ServerStreaming, Welcome};
use canopy_protocol::record::ParamOverride;
use canopy_protocol::{CellCoord, ClientMsg, CloseCode, InstanceRecord, MessageError, Phase, ServerMsg, netlimits};
use canopy_protocol::{InstanceId, SpeciesGraph, SpeciesHash};
use canopy_worlds::world::{CellKey, Ground, GroundCover, Placement, World};

use crate::far::{Far, default_view};

/// Where the link is, as the page and its tests name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Link {
    /// Connecting, or in the handshake.
    Connecting,
    /// Welcomed and streaming.
    Streaming,
    /// Ended (the reason is [`Session::error`]).
    Closed,
}

impl Link {
    /// `"connecting"`, `"streaming"` or `"closed"`.
    pub fn name(self) -> &'static str {
        match self {
            Link::Connecting => "connecting",
            Link::Streaming => "streaming",
            Link::Closed => "closed",
        }
    }
}

/// Why the session ended, and the close code to send when it is the server's fault.
#[derive(Clone, Debug, PartialEq)]
pub struct Fault {
    /// The code to close the transport with (`None`: nothing to send, e.g. the transport is gone).
    pub code: Option<CloseCode>,
    /// What went wrong.
    pub reason: String,
}

impl Fault {
    fn frame(e: FrameError) -> Fault {
        let code = if matches!(e, FrameError::TooLarge { .. }) { CloseCode::TooLarge } else { CloseCode::Malformed };
        Fault { code: Some(code), reason: e.to_string() }
    }

    fn message(e: MessageError) -> Fault {
        Fault { code: Some(e.close_code()), reason: e.to_string() }
    }

    fn state(e: StateError) -> Fault {
        let code = if matches!(e, StateError::Phase(_)) { CloseCode::OutOfOrder } else { CloseCode::Invalid };
        Fault { code: Some(code), reason: e.to_string() }
    }

    fn invalid(reason: String) -> Fault {
        Fault { code: Some(CloseCode::Invalid), reason }
    }
}

/// How the session starts.
#[derive(Clone, Debug, PartialEq)]
pub struct Options {
    /// The client's name in the server's logs.
    pub name: String,
    /// Where the first viewpoint is on (x, z) (`None`: [`default_start`]).
    pub start: Option<[f32; 2]>,
    /// The first heading, radians.
    pub yaw: f32,
    /// The area-of-interest radius to ask for, metres (the server caps it).
    pub radius: f32,
    /// An editor's token for the hello (`None`: a read-only session).
    pub token: Option<Vec<u8>>,
}

impl Default for Options {
    fn default() -> Options {
        Options { name: "canopy web".into(), start: None, yaw: DEFAULT_YAW, radius: DEFAULT_RADIUS, token: None }
    }
}

/// Edits whose requests and outcomes a session remembers (the oldest are forgotten).
pub(crate) const EDITS_KEPT: usize = 32;

/// An edit this session asked for: its request number and, once the server answered, the outcome.
#[derive(Clone, Debug, PartialEq)]
pub struct EditAsked {
    /// The request number.
    pub request: u32,
    /// `None` while unanswered; `Ok(instance)` applied and durable; `Err(why)` refused.
    pub outcome: Option<Result<InstanceId, String>>,
}

/// The radius asked for by default (the native walk's).
pub(crate) const DEFAULT_RADIUS: f32 = 600.0;

/// Where a session starts by default: the native default view's (40, −760) where the grid holds it (the default
/// world's valley), else the grid's centre.
pub(crate) fn default_start(grid: &Grid) -> [f32; 2] {
    let view = [40.0, -760.0];
    if grid.contains(grid.cell_of(view[0], view[1])) {
        return view;
    }
    let centre = |min: i32, max: i32, origin: f32| origin + (min as f32 + max as f32 + 1.0) * 0.5 * grid.cell_size;
    [centre(grid.min.x, grid.max.x, grid.origin[0]), centre(grid.min.z, grid.max.z, grid.origin[1])]
}

/// The camera's height over the ground at the start, metres (the default view's): the far view's first altitude.
pub(crate) const DEFAULT_ALTITUDE: f32 = 28.0;

/// The default view's heading: from (40, −760) towards (0, −300), up the valley.
pub(crate) const DEFAULT_YAW: f32 = -0.086_738_5;

/// One cell's placements quantised on the welcome's grid, as the native expander and the server's store quantise
/// them (`canopy_client::expand::Expanded::of_placements`, which is native-only): record `i` is instance
/// `(cell, i)`, overrides by index in the cell, sorted by `(record, slot)`.
pub(crate) fn quantise(
    grid: &Grid,
    cell: CellCoord,
    placements: &[Placement],
) -> (Vec<InstanceRecord>, Vec<ParamOverride>) {
    let mut records = Vec::with_capacity(placements.len());
    let mut overrides = Vec::new();
    for (i, p) in placements.iter().enumerate() {
        let [qx, qz] = grid.steps(cell, p.x, p.z);
        records.push(InstanceRecord::new(p.species as u8, qx, qz));
        let record = i as u16;
        overrides.extend(p.params.iter().map(|&(slot, value)| ParamOverride { record, slot, value }));
    }
    overrides.sort_by_key(|o| (o.record, o.slot));
    (records, overrides)
}

/// See the module docs.
#[derive(Debug)]
pub struct Session {
    opts: Options,
    state: ClientState,
    link: Link,
    error: Option<String>,
    control: FrameDecoder,
    /// One decoder a lane, by the index [`Session::open_lane`] gave (`None` once the lane ended).
    lanes: Vec<Option<FrameDecoder>>,
    outbox: Vec<u8>,
    close: Option<Fault>,
    ground: Option<Ground>,
    /// The world built from the welcome's world function and species, with the function's hash.
    world: Option<(SpeciesHash, Arc<World>)>,
    /// What covers its ground (the terrain's colours), with the world.
    cover: Option<Arc<GroundCover>>,
    seq: u32,
    edits: std::collections::VecDeque<EditAsked>,
    expanded: u64,
    bytes_in: u64,
    bytes_out: u64,
    /// The far view computed here ([`Session::far_step`]).
    far: Far,
    /// The eye's height over the ground, metres (the far view's altitude).
    altitude: f32,
}

impl Session {
    /// A session that has said hello (the hello is in the outbox).
    pub fn new(opts: Options) -> Session {
        let mut state = ClientState::new();
        let hello = state.hello_as(&opts.name, opts.token.clone()).expect("a new state says hello");
        let mut s = Session {
            opts,
            state,
            link: Link::Connecting,
            error: None,
            control: FrameDecoder::new(netlimits::MAX_SERVER_FRAME),
            lanes: Vec::new(),
            outbox: Vec::new(),
            close: None,
            ground: None,
            world: None,
            cover: None,
            seq: 0,
            edits: std::collections::VecDeque::new(),
            expanded: 0,
            bytes_in: 0,
            bytes_out: 0,
            far: Far::default(),
            altitude: DEFAULT_ALTITUDE,
        };
        s.send(&hello);
        s
    }

    /// The client state.
    pub fn state(&self) -> &ClientState {
        &self.state
    }

    /// Where the link is.
    pub fn link(&self) -> Link {
        self.link
    }

    /// Why the session ended, once it did.
    pub fn error(&self) -> Option<&str> {
        self.error.as_deref()
    }

    /// The ground from the welcome, once it arrived.
    pub fn ground(&self) -> Option<&Ground> {
        self.ground.as_ref()
    }

    /// What covers the ground, once the world is built from its function.
    pub fn cover(&self) -> Option<&Arc<GroundCover>> {
        self.cover.as_ref()
    }

    /// The terrain height at (x, z) (0 before the welcome).
    pub fn height(&self, x: f32, z: f32) -> f32 {
        self.ground.as_ref().map_or(0.0, |g| g.height(x, z))
    }

    /// The welcome, once it arrived.
    pub fn welcome(&self) -> Option<&Arc<Welcome>> {
        self.state.welcome()
    }

    /// Whether the world the cells are expanded in is built.
    pub fn world_built(&self) -> bool {
        self.world.is_some()
    }

    /// Cells this client expanded.
    pub fn expanded(&self) -> u64 {
        self.expanded
    }

    /// Frame bytes read (control stream and lanes).
    pub fn bytes_in(&self) -> u64 {
        self.bytes_in
    }

    /// Frame bytes written on the control stream.
    pub fn bytes_out(&self) -> u64 {
        self.bytes_out
    }

    /// The radius asked for.
    pub fn radius(&self) -> f32 {
        self.opts.radius
    }

    /// Bytes to write on the control stream, in order.
    pub fn take_outbox(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.outbox)
    }

    /// The close to send on the transport, once, if the session ended by a fault of the server's.
    pub fn take_close(&mut self) -> Option<Fault> {
        self.close.take()
    }

    fn send(&mut self, msg: &ClientMsg) {
        let bytes = frame(&msg.encode());
        self.bytes_out += bytes.len() as u64;
        self.outbox.extend_from_slice(&bytes);
    }

    /// End the session for `fault` (the first fault is the one kept).
    pub fn fail(&mut self, fault: Fault) {
        if self.link == Link::Closed {
            return;
        }
        self.link = Link::Closed;
        self.error = Some(fault.reason.clone());
        self.outbox.clear();
        if fault.code.is_some() {
            self.close = Some(fault);
        }
    }

    /// The transport ended (closed by the server, lost, or refused): nothing to send.
    pub fn closed(&mut self, reason: impl Into<String>) {
        self.fail(Fault { code: None, reason: reason.into() });
    }

    fn run(&mut self, r: Result<(), Fault>) {
        if let Err(f) = r {
            self.fail(f);
        }
    }

    /// Bytes read from the control stream: the welcome (answered with the ready), then edit results.
    pub fn on_control(&mut self, bytes: &[u8]) {
        if self.link == Link::Closed {
            return;
        }
        self.bytes_in += bytes.len() as u64;
        self.control.push(bytes);
        let r = self.drain_control();
        self.run(r);
    }

    /// The control stream ended.
    pub fn end_control(&mut self) {
        if self.link == Link::Closed {
            return;
        }
        let r = self.control.finish().map_err(Fault::frame);
        self.run(r);
        if self.state.phase() != Phase::Streaming {
            self.fail(Fault { code: None, reason: "the server ended its streams before the welcome".into() });
        }
    }

    fn drain_control(&mut self) -> Result<(), Fault> {
        loop {
            let msg = match self.control.next_frame().map_err(Fault::frame)? {
                Some(f) => ServerMsg::decode(f).map_err(Fault::message)?,
                None => return Ok(()),
            };
            if self.state.phase() == Phase::Hello {
                self.on_welcome(msg)?;
            } else if matches!(msg, ServerMsg::Streaming(ServerStreaming::EditResult(_))) {
                self.handle(msg)?;
            } else {
                let e = PhaseError { phase: Phase::Streaming, message: msg.name() };
                return Err(Fault::state(StateError::Phase(e)));
            }
        }
    }

    fn on_welcome(&mut self, msg: ServerMsg) -> Result<(), Fault> {
        let w = self.state.on_welcome(msg).map_err(|e| match e {
            StateError::Version(_) => Fault { code: Some(CloseCode::Version), reason: e.to_string() },
            e => Fault::state(e),
        })?;
        let ground = canopy_client::world::ground(&w.world.terrain).map_err(|e| Fault::invalid(e.to_string()))?;
        self.ground = Some(ground);
        let position = self.opts.start.unwrap_or_else(|| default_start(&w.world.grid));
        let vp = Viewpoint { seq: 0, position, yaw: self.opts.yaw, velocity: [0.0, 0.0], radius: self.opts.radius };
        vp.validate().map_err(|e| Fault { code: None, reason: format!("the first viewpoint: {e}") })?;
        // Expand where the server offers a world function, as the native client with an expander does.
        let mode =
            if w.world.function.is_some() { CellMode::Expand { have_function: false } } else { CellMode::Records };
        let ready = self.state.ready_with(vp, mode).map_err(Fault::state)?;
        self.send(&ready);
        self.seq = vp.seq;
        self.link = Link::Streaming;
        Ok(())
    }

    /// A lane the server opened: the index to pass its bytes with.
    pub fn open_lane(&mut self) -> usize {
        self.lanes.push(Some(FrameDecoder::new(netlimits::MAX_SERVER_FRAME)));
        self.lanes.len() - 1
    }

    /// Bytes read from lane `lane`.
    pub fn on_lane(&mut self, lane: usize, bytes: &[u8]) {
        if self.link == Link::Closed {
            return;
        }
        self.bytes_in += bytes.len() as u64;
        let r = self.drain_lane(lane, bytes);
        self.run(r);
    }

    fn drain_lane(&mut self, lane: usize, bytes: &[u8]) -> Result<(), Fault> {
        let Some(Some(decoder)) = self.lanes.get_mut(lane) else { return Ok(()) };
        decoder.push(bytes);
        loop {
            let Some(Some(decoder)) = self.lanes.get_mut(lane) else { return Ok(()) };
            let msg = match decoder.next_frame().map_err(Fault::frame)? {
                Some(f) => ServerMsg::decode(f).map_err(Fault::message)?,
                None => return Ok(()),
            };
            self.handle(msg)?;
        }
    }

    /// Lane `lane` ended (a frame cut short is the server's fault).
    pub fn end_lane(&mut self, lane: usize) {
        if self.link == Link::Closed {
            return;
        }
        if let Some(slot) = self.lanes.get_mut(lane)
            && let Some(decoder) = slot.take()
        {
            let r = decoder.finish().map_err(Fault::frame);
            self.run(r);
        }
    }

    /// Apply a server message (the lanes' and the control stream's after the welcome).
    fn handle(&mut self, msg: ServerMsg) -> Result<(), Fault> {
        let ev = self.state.handle(msg).map_err(Fault::state)?;
        self.follow(ev)
    }

    /// What an event asks of the driver: a cell to ask for again after a gap, or as records when this client's
    /// expansion does not fit the server's overlay.
    fn follow(&mut self, ev: Event) -> Result<(), Fault> {
        match ev {
            Event::Gap(c) => {
                let msg = self.state.refresh(c).map_err(Fault::state)?;
                self.send(&msg);
            }
            Event::Differs(c) => {
                let msg = self.state.records(c).map_err(Fault::state)?;
                self.send(&msg);
            }
            Event::FarCell(f) => self.far.far_cell(*f),
            Event::EditResult(r) => {
                if let Some(e) = self.edits.iter_mut().find(|e| e.request == r.request) {
                    e.outcome = Some(match r.outcome {
                        EditOutcome::Ok { id, .. } => Ok(id),
                        EditOutcome::Denied(why) => Err(format!("denied: {why}")),
                        EditOutcome::Invalid(why) => Err(format!("invalid: {why}")),
                        EditOutcome::Conflict => Err("conflict: the cell changed; try again".into()),
                    });
                }
            }
            _ => {}
        }
        Ok(())
    }

    /// Build the world once the world function and every species are held (as the native `Expanding::build`).
    fn build_world(&mut self) -> Result<bool, Fault> {
        if self.world.is_some() {
            return Ok(true);
        }
        let (Some(w), Some(f)) = (self.state.welcome(), self.state.function()) else { return Ok(false) };
        let n = w.species.len();
        let species: Option<Vec<SpeciesGraph>> =
            (0..n).map(|i| self.state.species(i as u8).map(|g| (**g).clone())).collect();
        let Some(species) = species else { return Ok(false) };
        let terrain = match &w.world.terrain.graph {
            Some(bytes) => Some(
                SpeciesGraph::decode(bytes)
                    .map_err(|e| Fault::invalid(format!("the server's world function does not build: {e}")))?,
            ),
            None => None,
        };
        let world = World::from_function(&w.world.name, &f.manifest, &species, terrain.as_ref())
            .map_err(|d| Fault::invalid(format!("the server's world function does not build: {d}")))?;
        self.cover = Some(Arc::new(GroundCover::of_world(&world)));
        self.world = Some((f.hash(), Arc::new(world)));
        Ok(true)
    }

    /// Ask for an edit (an editor's session: the hello carried a token, else the server denies it); its request
    /// number. The outcome comes later ([`Session::edits`]).
    pub fn edit(&mut self, op: EditOp) -> Result<u32, String> {
        if self.link != Link::Streaming {
            return Err(format!("cannot edit while {}", self.link.name()));
        }
        let (request, msg) = self.state.edit(op).map_err(|e| e.to_string())?;
        self.send(&msg);
        if self.edits.len() == EDITS_KEPT {
            self.edits.pop_front();
        }
        self.edits.push_back(EditAsked { request, outcome: None });
        Ok(request)
    }

    /// The edits asked for lately, oldest first.
    pub fn edits(&self) -> impl Iterator<Item = &EditAsked> {
        self.edits.iter()
    }

    /// Whether the session said hello with an editor's token.
    pub fn editor(&self) -> bool {
        self.opts.token.is_some()
    }

    /// The instances held in cell `c`: species and world position, by index.
    pub fn cell_instances(&self, c: CellCoord) -> Vec<(u8, [f32; 3])> {
        let height = |x: f32, z: f32| self.height(x, z);
        let mut v: Vec<_> = self.state.instances(&height).filter(|i| i.id.cell() == c).collect();
        v.sort_by_key(|i| i.id.index());
        v.into_iter().map(|i| (i.species, i.position)).collect()
    }

    /// Cells waiting for their expansion.
    pub fn pending(&self) -> usize {
        self.state.awaiting_expansion().count()
    }

    /// Expand granted cells, nearest the viewpoint first, one at least (when any waits and the world is built),
    /// then as long as `more()` says there is time; the digests due go to the outbox. Returns the cells expanded.
    /// Building the world (once, when the function and every species are in) happens here too.
    pub fn expand(&mut self, more: &mut dyn FnMut() -> bool) -> usize {
        if self.link != Link::Streaming {
            return 0;
        }
        let r = self.expand_inner(more);
        match r {
            Ok(n) => n,
            Err(f) => {
                self.fail(f);
                0
            }
        }
    }

    fn expand_inner(&mut self, more: &mut dyn FnMut() -> bool) -> Result<usize, Fault> {
        if self.state.awaiting_expansion().next().is_none() || !self.build_world()? {
            return Ok(0);
        }
        let Some((_, world)) = self.world.clone() else { return Ok(0) };
        let grid = self.state.welcome().expect("streaming implies welcomed").world.grid;
        let at = self.state.viewpoint().map_or([0.0, 0.0], |v| v.position);
        let mut todo: Vec<(f32, CellCoord, u32)> =
            self.state.awaiting_expansion().map(|(c, g)| (grid.distance2(c, at), c, g)).collect();
        todo.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut n = 0;
        for (_, cell, grant) in todo {
            if n > 0 && !more() {
                break;
            }
            let placements = world.expand_cell(CellKey { x: cell.x, z: cell.z });
            let (records, overrides) = quantise(&grid, cell, &placements);
            let ev = self.state.on_expanded(cell, grant, records, overrides).map_err(Fault::state)?;
            self.follow(ev)?;
            self.expanded += 1;
            n += 1;
        }
        for msg in self.state.take_digests() {
            self.send(&msg);
        }
        Ok(n)
    }

    /// The camera is at `position` heading `yaw` moving at `velocity`, `since_sent` after the last viewpoint: send
    /// a viewpoint if one is due ([`viewpoint_due`]) or the radius changed. Returns whether one was sent.
    pub fn move_to(&mut self, position: [f32; 2], yaw: f32, velocity: [f32; 2], since_sent: Duration) -> bool {
        if self.link != Link::Streaming {
            return false;
        }
        let (Some(w), Some(sent)) = (self.state.welcome(), self.state.viewpoint()) else { return false };
        let radius = self.opts.radius;
        if sent.radius == radius && !viewpoint_due(&w.world.grid, sent, position, yaw, since_sent) {
            return false;
        }
        let vp = Viewpoint { seq: self.seq + 1, position, yaw, velocity, radius };
        if vp.validate().is_err() {
            // Off the protocol's map (a coordinate or speed past its limit): stay with the last viewpoint.
            return false;
        }
        match self.state.set_viewpoint(vp) {
            Ok(msg) => {
                self.seq = vp.seq;
                self.send(&msg);
                self.far.moved();
                true
            }
            Err(e) => {
                self.fail(Fault::state(e));
                false
            }
        }
    }

    /// Ask for another radius from the next viewpoint on.
    pub fn set_radius(&mut self, radius: f32) {
        if radius.is_finite() && radius > 0.0 {
            self.opts.radius = radius;
        }
    }

    /// The eye is `altitude` metres over the ground (the far view's altitude, taken when it changed enough:
    /// [`ClientState::far_view_due`]).
    pub fn set_altitude(&mut self, altitude: f32) {
        if altitude.is_finite() {
            self.altitude = altitude;
        }
    }

    /// The far field: its nodes held are [`ClientState::summaries`].
    pub fn far(&self) -> &Far {
        &self.far
    }

    /// Say the far view (the native walk's default, at the eye's altitude) when it is due, as the native
    /// `Connection::set_far_view`: a session that expands its cells computes the nodes itself (the server tells it
    /// of the edited cells within the view's range), one that takes records asks the server for them.
    fn update_far_view(&mut self) -> Result<(), Fault> {
        let view = default_view(self.altitude);
        if !self.state.far_view_due(&view) {
            return Ok(());
        }
        let msg = self.state.set_far_view(view).map_err(Fault::state)?;
        if self.state.welcome().is_some_and(|w| w.world.function.is_some()) {
            self.far.set_view(view);
        }
        // The server sends the nodes (records) or tells of the edited cells within the view's range (expanding).
        self.send(&msg);
        Ok(())
    }

    /// Compute far-view summary nodes at `now` (time since any fixed moment), coarse first, one block or node at
    /// least, then as long as `more()` says there is time — only while no granted cell waits (cells first, as
    /// natively) — and lay them into the state. Returns the nodes computed.
    pub fn far_step(&mut self, now: Duration, more: &mut dyn FnMut() -> bool) -> usize {
        if self.link != Link::Streaming {
            return 0;
        }
        let r = self.far_inner(now, more);
        match r {
            Ok(n) => n,
            Err(f) => {
                self.fail(f);
                0
            }
        }
    }

    fn far_inner(&mut self, now: Duration, more: &mut dyn FnMut() -> bool) -> Result<usize, Fault> {
        self.update_far_view()?;
        if self.far.view().is_none() || self.pending() > 0 || !self.build_world()? {
            return Ok(0);
        }
        if !self.far.has_world()
            && let (Some((_, world)), Some(w)) = (&self.world, self.state.welcome())
        {
            self.far.set_world(Arc::clone(world), w.world.grid);
        }
        self.far.step(&mut self.state, now, more).map_err(Fault::state)
    }
}

#[cfg(test)]
mod tests;
