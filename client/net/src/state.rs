//! The client's sans-IO core: the session phase, the species it holds, the cells and instance records of its
//! area of interest, and when that area is complete. It is fed the server's messages and the viewpoint, reads no
//! clock and touches no socket; [`crate::net`] drives it over QUIC and the renderer reads it.
//!
//! Consistency over several ordered lanes: all batches of one grant of a cell, and the grant's release, travel on
//! one lane, so within a grant the order is exact; across lanes a newer grant of a cell may overtake the release of
//! an older one, which the grant numbers sort out (a newer grant replaces an older one, an older batch is stale).
//! The client also evicts by distance itself, with the same hysteresis rule as the server
//! ([`canopy_protocol::aoi`]): it never keeps a cell beyond radius + hysteresis, even before the server's release
//! arrives, and drops the rest of such a grant until that release.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::sync::Arc;
use std::time::Duration;

use canopy_protocol::aoi::{Aoi, Grid, Viewpoint};
use canopy_protocol::edit::EditResult;
use canopy_protocol::messages::{
    CellDigest, CellMode, ClientStreaming, PhaseError, Release, ServerHandshake, ServerStreaming, SpeciesData, Welcome,
    WorldFunction,
};
use canopy_protocol::record::{ParamOverride, dequantize};
use canopy_protocol::summary::{FarView, NodeKey, NodeSummary};
use canopy_protocol::{
    CellBatch, CellCoord, ClientMsg, InstanceId, InstanceRecord, Phase, ServerMsg, SpeciesGraph, SpeciesHash,
};
use canopy_protocol::{DecodeError, PROTOCOL_VERSION};

mod edits;
mod expand;
mod far;

pub use expand::{DIGEST_EVERY, MAX_DEFERRED_DELTAS};

use edits::Resumable;

/// A cell the client holds: one grant's records at one version of the cell, complete when `records.len() ==
/// total`. Record `i` is the instance `(cell, i)` ([`InstanceId`]); felled records keep their index.
#[derive(Clone, Debug, PartialEq)]
pub struct HeldCell {
    /// The grant the records belong to.
    pub grant: u32,
    /// How many records the cell has.
    pub total: u16,
    /// The records received so far, by index in the cell.
    pub records: Vec<InstanceRecord>,
    /// Parameter overrides; `record` is the index within the cell.
    pub overrides: Vec<ParamOverride>,
    /// The cell's version the records are at (0: the world function alone; one more per edit).
    pub version: u32,
    /// Indices felled by edits (skipped by [`ClientState::instances`]).
    pub felled: BTreeSet<u16>,
    /// Granted to expand, and not expanded yet (no records).
    pub expanding: bool,
    /// Asked for again after a gap: its deltas are dropped until the new grant replaces it (one request a gap, not
    /// one a delta that follows it, which a server takes as a flood).
    pub refreshing: bool,
}

impl HeldCell {
    /// Whether every record of the cell has arrived (or been expanded).
    pub fn is_complete(&self) -> bool {
        !self.expanding && self.records.len() == usize::from(self.total)
    }
}

/// One instance as the client exposes it to the application and the renderer.
#[derive(Clone, Debug, PartialEq)]
pub struct InstanceView {
    /// The instance: its cell and index in the cell.
    pub id: InstanceId,
    /// The species id (index into the welcome's table).
    pub species: u8,
    /// World position: x, terrain height (0 without a terrain), z.
    pub position: [f32; 3],
    /// The instance seed, [`instance_seed`]`(world seed, id)`.
    pub seed: u64,
    /// Parameters that differ from the species defaults, `(slot, value)`.
    pub params: Vec<(u16, f32)>,
}

/// What handling a message changed.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// The welcome arrived.
    Welcomed,
    /// Species `id` arrived (its encoding is in the message, for the cache).
    Species {
        /// The species id.
        id: u8,
        /// Its content address.
        hash: SpeciesHash,
    },
    /// Records of a cell arrived; `complete` once the cell has all of them.
    Records {
        /// The cell.
        cell: CellCoord,
        /// How many records arrived.
        count: usize,
        /// Whether the cell is now complete.
        complete: bool,
    },
    /// A cell's grant was released.
    Released(CellCoord),
    /// The message was stale (an older grant) or for a cell already evicted, and was dropped.
    Dropped,
    /// A held cell changed (a delta was applied): it is at `version` now.
    Changed {
        /// The cell.
        cell: CellCoord,
        /// Its version now.
        version: u32,
    },
    /// A delta did not start at the version held: the cell must be sent again ([`ClientState::refresh`]).
    Gap(CellCoord),
    /// A cell was granted to expand here (the driver expands it and calls [`ClientState::on_expanded`]).
    Granted {
        /// The cell.
        cell: CellCoord,
        /// The grant.
        grant: u32,
    },
    /// The world function arrived.
    Function,
    /// An edited cell beyond the area of interest (a client that computes its far view itself): the driver
    /// corrects its far view's nodes by the cell's edits.
    FarCell(Box<canopy_protocol::messages::FarCell>),
    /// A delta for a cell still being expanded: applied after the expansion.
    Deferred(CellCoord),
    /// This client's expansion of a cell does not fit the server's overlay: it must take the cell's records
    /// ([`ClientState::records`]).
    Differs(CellCoord),
    /// The server answered an edit.
    EditResult(EditResult),
    /// A chunk of explicit geometry arrived (bandwidth baselines; counted and discarded).
    Geometry {
        /// What it is.
        kind: canopy_protocol::messages::GeometryKind,
        /// Its instance's id bits, species id or first instance's id bits ([`GeometryKind`]).
        ///
        /// [`GeometryKind`]: canopy_protocol::messages::GeometryKind
        id: u64,
        /// Where the chunk starts in its blob.
        offset: u32,
        /// The blob's size.
        total: u32,
        /// Payload bytes in the chunk.
        bytes: usize,
    },
    /// Far-view summary nodes arrived or were released.
    Summaries {
        /// Nodes added (or replaced).
        added: usize,
        /// Nodes released.
        released: usize,
    },
}

/// Most far-view summary nodes a client holds; a server that sends more is faulty (it releases as it refines).
pub const MAX_HELD_SUMMARIES: usize = 1 << 16;

/// Why a server message is not acceptable (the client closes the connection).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StateError {
    /// Not legal in the session's phase.
    #[error(transparent)]
    Phase(#[from] PhaseError),
    /// The server speaks another protocol version.
    #[error("server speaks protocol version {0}, client speaks {PROTOCOL_VERSION}")]
    Version(u16),
    /// A species id is outside the table.
    #[error("species {0} is not in the table")]
    UnknownSpecies(u8),
    /// A species' bytes do not hash to its table entry.
    #[error("species {0} does not match its content address")]
    Hash(u8),
    /// A species' bytes do not decode to a valid graph.
    #[error("species {0}: {1}")]
    Graph(u8, DecodeError),
    /// A batch does not continue its grant where the previous one ended, or its cell is outside the grid.
    #[error("batch of cell {cell:?} grant {grant} starts at {start}, expected {expected}")]
    Order {
        /// The cell.
        cell: CellCoord,
        /// The grant.
        grant: u32,
        /// Where it starts.
        start: u16,
        /// Where it should start.
        expected: u16,
    },
    /// A batch's version differs from its grant's, or a delta does not fit the cell it changes.
    #[error("cell {0:?}: {1}")]
    Edit(CellCoord, &'static str),
    /// The server sent more summary nodes than a client holds.
    #[error("more than {MAX_HELD_SUMMARIES} summary nodes held")]
    TooManySummaries,
    /// The world function is not the one the welcome names, or cannot be built.
    #[error("world function: {0}")]
    Function(&'static str),
}

/// Counters of what the client received.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ClientStats {
    /// Species received over the wire.
    pub species_received: u32,
    /// Species received that the client already held (the protocol promises none).
    pub species_duplicates: u32,
    /// Instance records received.
    pub records: u64,
    /// Batches received.
    pub batches: u64,
    /// Batches dropped as stale or evicted.
    pub dropped: u64,
    /// Releases received.
    pub releases: u64,
    /// Cells the client evicted by distance before the server's release.
    pub evicted: u64,
    /// Explicit-geometry payload bytes received (bandwidth baselines), by kind: instance meshes, species meshes,
    /// transforms (the frames that carried them are the connection's geometry class).
    pub geometry_bytes: [u64; 3],
    /// Deltas applied.
    pub deltas: u64,
    /// Deltas that did not start at the version held (each asks for the cell again).
    pub gaps: u64,
    /// Far-view summary nodes received.
    pub summaries: u64,
    /// Far-view summary nodes released.
    pub summaries_released: u64,
    /// Edited cells beyond the area of interest told of (far cells).
    pub far_cells: u64,
    /// Cells granted to expand here.
    pub grants: u64,
    /// Records this client expanded itself.
    pub records_expanded: u64,
    /// Expanded cells whose overlay did not fit (each asked for as records).
    pub mismatches: u64,
    /// Digests of expanded cells reported to the server.
    pub digests: u64,
}

/// The client's view of its session (see the module docs).
#[derive(Clone, Debug)]
pub struct ClientState {
    phase: Phase,
    welcome: Option<Arc<Welcome>>,
    species: Vec<Option<Arc<SpeciesGraph>>>,
    cells: HashMap<CellCoord, HeldCell>,
    tombstones: HashMap<CellCoord, u32>,
    viewpoint: Option<Viewpoint>,
    aoi: Option<Aoi>,
    inner: HashSet<CellCoord>,
    missing: usize,
    stats: ClientStats,
    /// The next edit's request number.
    next_request: u32,
    /// Cells kept from an earlier session of the same world, to name in resume messages (between the welcome and
    /// `ready`), and that world.
    resumable: Option<Resumable>,
    /// Far-view summary nodes held.
    summaries: BTreeMap<NodeKey, Arc<NodeSummary>>,
    /// Bumped whenever `summaries` changes.
    summaries_generation: u64,
    /// The far view last sent.
    far_view: Option<FarView>,
    /// How cells come in this session.
    cell_mode: CellMode,
    /// The world function, for a client that expands cells.
    function: Option<Arc<WorldFunction>>,
    /// Granted cells waiting for their expansion.
    expanding: HashMap<CellCoord, expand::Awaiting>,
    /// Digests due, and one expanded cell in how many is reported.
    digests: Vec<CellDigest>,
    digest_every: u32,
    /// Take grants and expand nothing (a load generator's client): see [`ClientState::set_grants_only`].
    grants_only: bool,
}

impl Default for ClientState {
    fn default() -> Self {
        ClientState::new()
    }
}

impl ClientState {
    /// A session that has not said hello yet.
    pub fn new() -> ClientState {
        ClientState {
            phase: Phase::Start,
            welcome: None,
            species: Vec::new(),
            cells: HashMap::new(),
            tombstones: HashMap::new(),
            viewpoint: None,
            aoi: None,
            inner: HashSet::new(),
            missing: 0,
            stats: ClientStats::default(),
            next_request: 1,
            resumable: None,
            summaries: BTreeMap::new(),
            summaries_generation: 0,
            far_view: None,
            cell_mode: CellMode::Records,
            function: None,
            expanding: HashMap::new(),
            digests: Vec::new(),
            digest_every: DIGEST_EVERY,
            grants_only: false,
        }
    }

    /// The message asking for species `id`'s program (sent at most once a session; it arrives as an
    /// [`Event::Species`]).
    pub fn fetch(&mut self, id: u8) -> Result<ClientMsg, StateError> {
        let msg = ClientMsg::Streaming(ClientStreaming::Fetch(id));
        msg.next_phase(self.phase)?;
        Ok(msg)
    }

    /// The session phase.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// The welcome, once it arrived.
    pub fn welcome(&self) -> Option<&Arc<Welcome>> {
        self.welcome.as_ref()
    }

    /// What the client received.
    pub fn stats(&self) -> &ClientStats {
        &self.stats
    }

    /// The area of interest of the latest viewpoint.
    pub fn aoi(&self) -> Option<&Aoi> {
        self.aoi.as_ref()
    }

    /// The latest viewpoint.
    pub fn viewpoint(&self) -> Option<&Viewpoint> {
        self.viewpoint.as_ref()
    }

    /// The species held, by id.
    pub fn species(&self, id: u8) -> Option<&Arc<SpeciesGraph>> {
        self.species.get(usize::from(id)).and_then(Option::as_ref)
    }

    /// How many species of the table the client holds.
    pub fn species_held(&self) -> usize {
        self.species.iter().filter(|s| s.is_some()).count()
    }

    /// The cells held.
    pub fn cells(&self) -> &HashMap<CellCoord, HeldCell> {
        &self.cells
    }

    /// The cells of the current area of interest.
    pub fn inner_cells(&self) -> &HashSet<CellCoord> {
        &self.inner
    }

    /// How many cells are still to come: cells of the area of interest not held in full, and held cells in the
    /// hysteresis band whose grant is not finished (the server finishes them; the client keeps them).
    pub fn missing(&self) -> usize {
        self.missing
    }

    /// Whether every cell of the area of interest, and every cell held, is held in full.
    pub fn is_complete(&self) -> bool {
        self.phase == Phase::Streaming && self.missing == 0
    }

    /// Records a square metre over the cells held (their counts as the server announced them, received or not):
    /// what a client on a slow link fits its radius with ([`canopy_protocol::aoi::AoiParams::link_radius`]).
    /// `None` before a welcome and a first cell.
    pub fn record_density(&self) -> Option<f64> {
        let s = f64::from(self.welcome.as_ref()?.world.grid.cell_size);
        let records: u64 = self.cells.values().map(|c| u64::from(c.total)).sum();
        (!self.cells.is_empty()).then(|| records as f64 / (self.cells.len() as f64 * s * s))
    }

    /// Instance records held (felled ones not counted).
    pub fn record_count(&self) -> usize {
        self.cells.values().map(|c| c.records.len() - c.felled.len()).sum()
    }

    /// The first message: hello.
    pub fn hello(&mut self, client: &str) -> Result<ClientMsg, StateError> {
        self.hello_as(client, None)
    }

    /// The first message, carrying an editor token (at most [`canopy_protocol::netlimits::MAX_TOKEN_BYTES`]
    /// bytes): the session may edit if the server knows it.
    pub fn hello_as(&mut self, client: &str, token: Option<Vec<u8>>) -> Result<ClientMsg, StateError> {
        let name: String = client.chars().take(canopy_protocol::netlimits::MAX_CLIENT_NAME / 4).collect();
        let mut msg = ClientMsg::hello(name);
        if let ClientMsg::Handshake(canopy_protocol::messages::ClientHandshake::Hello(h)) = &mut msg {
            h.token = token;
        }
        self.phase = msg.next_phase(self.phase)?;
        Ok(msg)
    }

    /// Handle the server's answer to the hello.
    pub fn on_welcome(&mut self, msg: ServerMsg) -> Result<Arc<Welcome>, StateError> {
        self.phase = msg.next_phase(self.phase)?;
        let ServerMsg::Handshake(ServerHandshake::Welcome(w)) = msg else {
            unreachable!("next_phase admits only a welcome in phase Hello")
        };
        if w.version != PROTOCOL_VERSION {
            return Err(StateError::Version(w.version));
        }
        self.species = vec![None; w.species.len()];
        let w = Arc::new(w);
        self.welcome = Some(Arc::clone(&w));
        Ok(w)
    }

    /// Species the client already holds (from its cache): `(id, graph)` pairs whose content address matched the
    /// table. Call between the welcome and [`ClientState::ready`].
    pub fn preload_species(&mut self, id: u8, graph: Arc<SpeciesGraph>) {
        if let Some(slot) = self.species.get_mut(usize::from(id)) {
            *slot = Some(graph);
        }
    }

    /// The answer to the welcome: the species held and the first viewpoint.
    pub fn ready(&mut self, viewpoint: Viewpoint) -> Result<ClientMsg, StateError> {
        let have: Vec<u8> = (0..self.species.len()).filter(|&i| self.species[i].is_some()).map(|i| i as u8).collect();
        let msg = ClientMsg::ready(have, viewpoint);
        self.phase = msg.next_phase(self.phase)?;
        self.move_to(viewpoint);
        Ok(msg)
    }

    /// A new viewpoint (its `seq` must increase): evicts what is beyond radius + hysteresis and returns the
    /// message to send.
    pub fn set_viewpoint(&mut self, viewpoint: Viewpoint) -> Result<ClientMsg, StateError> {
        let msg = ClientMsg::viewpoint(viewpoint);
        self.phase = msg.next_phase(self.phase)?;
        self.move_to(viewpoint);
        Ok(msg)
    }

    fn move_to(&mut self, vp: Viewpoint) {
        let Some(w) = self.welcome.clone() else { return };
        let grid = &w.world.grid;
        let aoi = Aoi::new(&vp, &w.aoi);
        let gone: Vec<CellCoord> = self.cells.keys().filter(|c| !aoi.is_kept(grid, **c)).copied().collect();
        for c in gone {
            self.expanding.remove(&c);
            if let Some(h) = self.cells.remove(&c) {
                self.tombstones.insert(c, h.grant);
                self.stats.evicted += 1;
            }
        }
        self.inner = aoi.inner_cells(grid).into_iter().collect();
        let band = self.cells.keys().filter(|c| !self.inner.contains(c));
        self.missing = self.inner.iter().chain(band).map(|c| self.missing_at(*c)).sum();
        self.viewpoint = Some(vp);
        self.aoi = Some(aoi);
    }

    /// Handle a streaming message from a lane.
    pub fn handle(&mut self, msg: ServerMsg) -> Result<Event, StateError> {
        msg.next_phase(self.phase)?;
        let ServerMsg::Streaming(msg) = msg else { unreachable!("next_phase admits only streaming messages") };
        match msg {
            ServerStreaming::Species(s) => self.on_species(s),
            ServerStreaming::Cells(b) => self.on_batch(b),
            ServerStreaming::Release(r) => Ok(self.on_release(r)),
            ServerStreaming::Delta(d) => self.on_delta(d),
            ServerStreaming::Summaries(b) => self.on_summaries(b),
            ServerStreaming::Grant(g) => self.on_grant(g),
            ServerStreaming::Function(f) => self.on_function(f),
            ServerStreaming::FarCell(f) => Ok(self.on_far_cell(f)),
            ServerStreaming::EditResult(r) => Ok(Event::EditResult(r)),
            ServerStreaming::Geometry(g) => {
                // Explicit geometry (a bandwidth baseline): counted, not kept; the records that follow it are what
                // the session's bookkeeping tracks.
                self.stats.geometry_bytes[g.kind as usize] += g.bytes.len() as u64;
                Ok(Event::Geometry { kind: g.kind, id: g.id, offset: g.offset, total: g.total, bytes: g.bytes.len() })
            }
        }
    }

    fn on_species(&mut self, s: SpeciesData) -> Result<Event, StateError> {
        let w = self.welcome.as_ref().expect("streaming implies welcomed");
        let entry = w.species.get(usize::from(s.id)).ok_or(StateError::UnknownSpecies(s.id))?;
        let hash = SpeciesHash::of(&s.graph);
        if hash != entry.hash {
            return Err(StateError::Hash(s.id));
        }
        self.stats.species_received += 1;
        if self.species[usize::from(s.id)].is_some() {
            self.stats.species_duplicates += 1;
        } else {
            let graph = SpeciesGraph::decode(&s.graph).map_err(|e| StateError::Graph(s.id, e))?;
            self.species[usize::from(s.id)] = Some(Arc::new(graph));
        }
        Ok(Event::Species { id: s.id, hash })
    }

    /// A cell granted for an older viewpoint and already out of range (the release will follow): forgotten, and
    /// later messages of that grant dropped. `before` is what the cell counted missing before the message.
    fn drop_out_of_range(&mut self, cell: CellCoord, grant: u32, before: usize) -> Event {
        self.cells.remove(&cell);
        self.expanding.remove(&cell);
        self.missing = self.missing + self.missing_at(cell) - before;
        self.tombstones.insert(cell, grant);
        self.stats.dropped += 1;
        Event::Dropped
    }

    fn on_batch(&mut self, b: CellBatch) -> Result<Event, StateError> {
        self.stats.batches += 1;
        let w = Arc::clone(self.welcome.as_ref().expect("streaming implies welcomed"));
        let order = |expected: u16| StateError::Order { cell: b.cell, grant: b.grant, start: b.start, expected };
        // A cell outside the grid, or one instance ids cannot name (decoded batches never are).
        if !w.world.grid.contains(b.cell) || !InstanceId::names(b.cell) {
            return Err(order(0));
        }
        if let Some(r) = b.records.iter().find(|r| usize::from(r.species) >= w.species.len()) {
            return Err(StateError::UnknownSpecies(r.species));
        }
        if self.tombstones.get(&b.cell).is_some_and(|&g| g >= b.grant) {
            self.stats.dropped += 1;
            return Ok(Event::Dropped);
        }
        let before = self.missing_at(b.cell);
        match self.cells.get(&b.cell) {
            Some(h) if h.grant > b.grant => {
                self.stats.dropped += 1;
                return Ok(Event::Dropped);
            }
            Some(h) if h.grant == b.grant => {
                // Records received again (the protocol promises none) or a gap: the batch is an error.
                if b.start != h.records.len() as u16 || b.total != h.total {
                    return Err(order(h.records.len() as u16));
                }
            }
            _ => {
                // A new grant (replacing an older one, whose release is still on its way on another lane).
                if b.start != 0 {
                    return Err(order(0));
                }
                if !self.aoi.is_some_and(|a| a.is_kept(&w.world.grid, b.cell)) {
                    return Ok(self.drop_out_of_range(b.cell, b.grant, before));
                }
                let cell = HeldCell {
                    grant: b.grant,
                    total: b.total,
                    records: Vec::with_capacity(usize::from(b.total)),
                    overrides: Vec::new(),
                    version: b.version,
                    felled: BTreeSet::new(),
                    expanding: false,
                    refreshing: false,
                };
                self.cells.insert(b.cell, cell);
                self.expanding.remove(&b.cell);
            }
        }
        let h = self.cells.get_mut(&b.cell).expect("inserted or present");
        if h.version != b.version {
            return Err(StateError::Edit(b.cell, "a batch's version differs from its grant's"));
        }
        let base = h.records.len() as u16;
        h.felled.extend((0..b.records.len()).filter(|&i| b.is_felled(i)).map(|i| base + i as u16));
        h.overrides.extend(b.overrides().into_iter().map(|o| ParamOverride { record: o.record + base, ..o }));
        h.records.extend_from_slice(&b.records);
        let complete = h.is_complete();
        self.stats.records += b.records.len() as u64;
        self.missing = self.missing + self.missing_at(b.cell) - before;
        Ok(Event::Records { cell: b.cell, count: b.records.len(), complete })
    }

    /// Whether cell `c` counts as missing: in the area of interest and not held in full, or held (in the band)
    /// and not finished.
    fn missing_at(&self, c: CellCoord) -> usize {
        let complete = self.cells.get(&c).map(HeldCell::is_complete);
        usize::from(if self.inner.contains(&c) { complete != Some(true) } else { complete == Some(false) })
    }

    fn on_release(&mut self, r: Release) -> Event {
        self.stats.releases += 1;
        if self.tombstones.get(&r.cell) == Some(&r.grant) {
            self.tombstones.remove(&r.cell);
        }
        match self.cells.get(&r.cell) {
            Some(h) if h.grant == r.grant => {
                let before = self.missing_at(r.cell);
                self.cells.remove(&r.cell);
                self.expanding.remove(&r.cell);
                self.missing = self.missing + self.missing_at(r.cell) - before;
                Event::Released(r.cell)
            }
            _ => Event::Dropped,
        }
    }

    /// Every instance held, cell by cell, each cell's by index. `height` gives the terrain height at (x, z).
    pub fn instances<'a>(&'a self, height: &'a dyn Fn(f32, f32) -> f32) -> impl Iterator<Item = InstanceView> + 'a {
        let w = self.welcome.as_ref();
        self.cells.iter().flat_map(move |(c, h)| {
            let w = w.expect("cells imply a welcome");
            let grid = &w.world.grid;
            let origin = grid.cell_origin(*c);
            let seed = w.world.seed;
            h.records.iter().enumerate().filter(|(i, _)| !h.felled.contains(&(*i as u16))).map(move |(i, r)| {
                let x = dequantize(r.qx(), origin[0], grid.cell_size);
                let z = dequantize(r.qz(), origin[1], grid.cell_size);
                // Batches are validated (their cell can be named) and a cell holds at most 65,535 records.
                let id = InstanceId::new(*c, i as u16).expect("a held cell can be named");
                let lo = h.overrides.partition_point(|o| usize::from(o.record) < i);
                let hi = h.overrides.partition_point(|o| usize::from(o.record) <= i);
                InstanceView {
                    id,
                    species: r.species,
                    position: [x, height(x, z), z],
                    seed: instance_seed(seed, id),
                    params: h.overrides[lo..hi].iter().map(|o| (o.slot, o.value)).collect(),
                }
            })
        })
    }
}

pub use canopy_worlds::world::instance_seed;

/// The one rule for when a client sends a new viewpoint (bots, the bandwidth harness and the walkthrough window
/// alike): it moved at least a sixteenth of a cell (and at least 1 m) from the viewpoint last `sent`, turned more
/// than a quarter radian, or moved at all and the last one is `STALE` old. `since_sent` is an argument: the rule
/// reads no clock.
pub fn viewpoint_due(grid: &Grid, sent: &Viewpoint, position: [f32; 2], yaw: f32, since_sent: Duration) -> bool {
    /// After this long any movement is worth a viewpoint (the look-ahead and the server's priorities use it).
    const STALE: Duration = Duration::from_secs(2);
    let min_move = (grid.cell_size / 16.0).max(1.0);
    let moved = ((position[0] - sent.position[0]).powi(2) + (position[1] - sent.position[1]).powi(2)).sqrt();
    moved >= min_move || (yaw - sent.yaw).abs() > 0.25 || (since_sent >= STALE && moved > 0.0)
}

#[cfg(test)]
mod tests {
    use canopy_protocol::POSITION_STEPS;
    use canopy_protocol::aoi::AoiParams;
    use canopy_protocol::messages::{SpeciesEntry, TerrainDesc, WorldInfo};
    use canopy_protocol::summary::SummaryBatch;

    use super::*;

    fn worm() -> Vec<u8> {
        canopy_worlds::library::find("worm").unwrap().load().unwrap().encode()
    }

    fn welcome() -> ServerMsg {
        let grid =
            Grid { origin: [0.0, 0.0], cell_size: 10.0, min: CellCoord::new(-50, -50), max: CellCoord::new(49, 49) };
        let terrain = TerrainDesc::flat([-500.0, -500.0], 1000.0);
        let w = Welcome {
            version: PROTOCOL_VERSION,
            world: WorldInfo {
                name: "t".into(),
                seed: 1,
                grid,
                position_steps: POSITION_STEPS,
                instances: 100,
                terrain,
                function: None,
            },
            species: vec![SpeciesEntry { hash: SpeciesHash::of(&worm()), size: worm().len() as u32 }],
            aoi: AoiParams { max_radius: 100.0, hysteresis: 10.0, lookahead_s: 0.0, max_lookahead: 0.0 },
        };
        ServerMsg::Handshake(ServerHandshake::Welcome(w))
    }

    fn streaming() -> ClientState {
        let mut s = ClientState::new();
        s.hello("t").unwrap();
        s.on_welcome(welcome()).unwrap();
        // Radius 4 at the centre of cell (0, 0): the area of interest is that cell alone.
        s.ready(Viewpoint::at(0, [5.0, 5.0], 4.0)).unwrap();
        s
    }

    fn batch(cell: CellCoord, grant: u32, start: u16, n: u16, total: u16) -> ServerMsg {
        ServerMsg::Streaming(ServerStreaming::Cells(CellBatch {
            cell,
            grant,
            total,
            start,
            records: (0..n).map(|i| InstanceRecord::new(0, i, i)).collect(),
            params: vec![],
            version: 0,
            felled: vec![],
        }))
    }

    fn release(cell: CellCoord, grant: u32) -> ServerMsg {
        ServerMsg::Streaming(ServerStreaming::Release(Release { cell, grant }))
    }

    #[test]
    fn summaries_are_held_until_released_and_bounded() {
        use canopy_protocol::summary::SpeciesCover;
        let mut s = streaming();
        let view = FarView { error_px: 16.0, height_px: 720, fov_y: 1.0, range: 5000.0, altitude: 300.0 };
        assert!(s.far_view_due(&view));
        s.set_far_view(view).unwrap();
        assert!(!s.far_view_due(&view) && !s.far_view_due(&FarView { altitude: 330.0, ..view }));
        assert!(
            s.far_view_due(&FarView { altitude: 400.0, ..view }) && s.far_view_due(&FarView { range: 1.0, ..view })
        );
        let node = |level, x, species| NodeSummary {
            key: NodeKey { level, x, z: 0 },
            error: 8.0,
            species: vec![SpeciesCover { species, count: 5, height_dm: 100, spread_dm: 0, cover: 1 }],
        };
        let msg = |nodes, released| ServerMsg::Streaming(ServerStreaming::Summaries(SummaryBatch { nodes, released }));
        let g0 = s.summaries_generation();
        assert_eq!(
            s.handle(msg(vec![node(2, 0, 0), node(1, 0, 0)], vec![])),
            Ok(Event::Summaries { added: 2, released: 0 })
        );
        assert_eq!(s.summaries().len(), 2);
        assert!(s.summaries_generation() > g0);
        let gone = NodeKey { level: 2, x: 0, z: 0 };
        assert_eq!(s.handle(msg(vec![node(1, 1, 0)], vec![gone])), Ok(Event::Summaries { added: 1, released: 1 }));
        assert!(!s.summaries().contains_key(&gone) && s.summaries().len() == 2);
        // A species outside the table is refused.
        assert_eq!(s.handle(msg(vec![node(0, 9, 4)], vec![])), Err(StateError::UnknownSpecies(4)));
        // No more than the bound.
        let mut refused = None;
        for x in 0..(MAX_HELD_SUMMARIES / 64 + 2) as i32 {
            let nodes = (0..64).map(|i| node(0, x * 64 + i, 0)).collect();
            if let Err(e) = s.handle(msg(nodes, vec![])) {
                refused = Some(e);
                break;
            }
        }
        assert_eq!(refused, Some(StateError::TooManySummaries));
    }

    #[test]
    fn species_must_match_their_content_address() {
        let mut s = streaming();
        let species = |id, graph| ServerMsg::Streaming(ServerStreaming::Species(SpeciesData { id, graph }));
        assert_eq!(s.handle(species(0, vec![1, 2, 3])), Err(StateError::Hash(0)));
        assert_eq!(s.handle(species(3, worm())), Err(StateError::UnknownSpecies(3)));
        assert!(matches!(s.handle(species(0, worm())), Ok(Event::Species { id: 0, .. })));
        assert!(s.species(0).is_some());
        s.handle(species(0, worm())).unwrap();
        assert_eq!(s.stats().species_duplicates, 1);
    }

    #[test]
    fn messages_out_of_phase_are_errors() {
        let mut s = ClientState::new();
        assert!(matches!(s.handle(batch(CellCoord::new(0, 0), 1, 0, 1, 1)), Err(StateError::Phase(_))));
        s.hello("t").unwrap();
        s.on_welcome(welcome()).unwrap();
        assert!(matches!(s.on_welcome(welcome()), Err(StateError::Phase(_))));
        assert!(matches!(s.handle(batch(CellCoord::new(0, 0), 1, 0, 1, 1)), Err(StateError::Phase(_))));
    }

    /// The density a slow client fits its radius with: the announced totals of the cells held, over their area
    /// (a cell counts from its first batch, before its last record arrives).
    #[test]
    fn record_density_is_the_held_cells_announced_records_over_their_area() {
        let mut s = streaming();
        assert_eq!(s.record_density(), None, "nothing held yet");
        s.handle(batch(CellCoord::new(0, 0), 1, 0, 2, 30)).unwrap();
        // 30 records in a 10 m × 10 m cell, 2 of them received.
        assert_eq!(s.record_density(), Some(0.3));
        assert_eq!(ClientState::new().record_density(), None, "no welcome");
    }

    #[test]
    fn a_cell_completes_in_order_and_gaps_are_errors() {
        let mut s = streaming();
        let c = CellCoord::new(0, 0);
        assert!(!s.is_complete());
        assert!(matches!(s.handle(batch(c, 1, 2, 2, 4)), Err(StateError::Order { expected: 0, .. })));
        s.handle(batch(c, 1, 0, 2, 4)).unwrap();
        assert!(matches!(s.handle(batch(c, 1, 3, 1, 4)), Err(StateError::Order { expected: 2, .. })));
        // Records received twice are rejected too (whole batch again, or overlapping the held ones).
        assert!(matches!(s.handle(batch(c, 1, 0, 2, 4)), Err(StateError::Order { expected: 2, .. })));
        assert!(matches!(s.handle(batch(c, 1, 1, 2, 4)), Err(StateError::Order { expected: 2, .. })));
        assert!(!s.is_complete());
        assert_eq!(s.handle(batch(c, 1, 2, 2, 4)), Ok(Event::Records { cell: c, count: 2, complete: true }));
        assert!(s.is_complete());
        let ids: Vec<(CellCoord, u16)> = s.instances(&|_, _| 0.0).map(|i| (i.id.cell(), i.id.index())).collect();
        assert_eq!(ids, vec![(c, 0), (c, 1), (c, 2), (c, 3)]);
        let first = InstanceId::new(c, 0).unwrap();
        assert_eq!(s.instances(&|_, _| 0.0).next().unwrap().seed, instance_seed(1, first));
        assert!(matches!(s.handle(batch(CellCoord::new(0, 99), 2, 0, 1, 1)), Err(StateError::Order { .. })));
    }

    #[test]
    fn grants_sort_out_lanes_overtaking_each_other() {
        let mut s = streaming();
        let c = CellCoord::new(0, 0);
        s.handle(batch(c, 1, 0, 2, 2)).unwrap();
        assert!(s.is_complete());
        // Grant 3 overtakes grant 1's release: it replaces grant 1.
        s.handle(batch(c, 3, 0, 1, 2)).unwrap();
        assert_eq!(s.cells()[&c].grant, 3);
        assert!(!s.is_complete());
        // The old release and an old batch change nothing.
        assert_eq!(s.handle(release(c, 1)), Ok(Event::Dropped));
        assert_eq!(s.handle(batch(c, 1, 0, 2, 2)), Ok(Event::Dropped));
        s.handle(batch(c, 3, 1, 1, 2)).unwrap();
        assert!(s.is_complete());
        assert_eq!(s.handle(release(c, 3)), Ok(Event::Released(c)));
        assert!(!s.is_complete() && s.cells().is_empty());
    }

    #[test]
    fn a_held_cell_in_the_band_must_finish_before_the_area_of_interest_is_complete() {
        let mut s = streaming();
        let c = CellCoord::new(0, 0);
        s.handle(batch(c, 1, 0, 1, 2)).unwrap();
        // Move so the half-received cell is in the hysteresis band (12 m away) and the new area of interest is
        // cells (1, 0) and (2, 0).
        s.set_viewpoint(Viewpoint::at(1, [22.0, 5.0], 4.0)).unwrap();
        assert!(s.cells().contains_key(&c));
        s.handle(batch(CellCoord::new(1, 0), 2, 0, 1, 1)).unwrap();
        s.handle(batch(CellCoord::new(2, 0), 3, 0, 1, 1)).unwrap();
        assert_eq!(s.missing(), 1);
        assert!(!s.is_complete(), "the band cell is still coming");
        s.handle(batch(c, 1, 1, 1, 2)).unwrap();
        assert!(s.is_complete());
    }

    #[test]
    fn eviction_by_distance_with_hysteresis() {
        let mut s = streaming();
        let c = CellCoord::new(0, 0);
        s.handle(batch(c, 1, 0, 1, 2)).unwrap();
        // 12 m away: beyond the radius (4) but within radius + hysteresis (14) of the cell: kept.
        s.set_viewpoint(Viewpoint::at(1, [22.0, 5.0], 4.0)).unwrap();
        assert!(s.cells().contains_key(&c));
        // Far away: evicted now, before the server's release; the rest of the grant is dropped until it comes.
        s.set_viewpoint(Viewpoint::at(2, [300.0, 5.0], 4.0)).unwrap();
        assert!(s.cells().is_empty());
        assert_eq!(s.stats().evicted, 1);
        assert_eq!(s.handle(batch(c, 1, 1, 1, 2)), Ok(Event::Dropped));
        s.handle(release(c, 1)).unwrap();
        // Back again: a new grant is accepted.
        s.set_viewpoint(Viewpoint::at(3, [5.0, 5.0], 4.0)).unwrap();
        s.handle(batch(c, 2, 0, 2, 2)).unwrap();
        assert!(s.is_complete());
        // A new grant for a cell already out of range is dropped (its release follows).
        assert_eq!(s.handle(batch(CellCoord::new(40, 40), 4, 0, 1, 1)), Ok(Event::Dropped));
        assert!(!s.cells().contains_key(&CellCoord::new(40, 40)));
    }

    #[test]
    fn a_viewpoint_is_due_after_a_sixteenth_of_a_cell_a_quarter_radian_or_two_quiet_seconds() {
        let grid = Grid { origin: [0.0, 0.0], cell_size: 64.0, min: CellCoord::new(-5, -5), max: CellCoord::new(5, 5) };
        let sent = Viewpoint { seq: 1, position: [10.0, 10.0], yaw: 0.5, velocity: [0.0, 0.0], radius: 100.0 };
        let fresh = Duration::from_millis(100);
        assert!(!viewpoint_due(&grid, &sent, [10.0, 10.0], 0.5, Duration::from_secs(60)), "still: never due");
        assert!(!viewpoint_due(&grid, &sent, [13.9, 10.0], 0.5, fresh), "3.9 m < 64/16 m");
        assert!(viewpoint_due(&grid, &sent, [14.0, 10.0], 0.5, fresh), "4 m");
        assert!(!viewpoint_due(&grid, &sent, [10.0, 10.0], 0.74, fresh));
        assert!(viewpoint_due(&grid, &sent, [10.0, 10.0], 0.76, fresh), "turned more than 0.25 rad");
        assert!(viewpoint_due(&grid, &sent, [10.5, 10.0], 0.5, Duration::from_secs(2)), "stale and moved");
        let small = Grid { cell_size: 8.0, ..grid };
        assert!(!viewpoint_due(&small, &sent, [10.9, 10.0], 0.5, fresh), "at least 1 m even for small cells");
    }
}
