//! The world store: species and instance records arranged spatially (seed 001 §4: "the server stores the data for
//! a very large virtual environment, composed of objects that are arranged spatially"), behind a trait so a
//! session does not care where they live or whether they exist yet: [`GridStore`] quantises every cell up front,
//! the server's cell cache (`canopy_server::CellCache`) expands cells on demand. Both hold a cell as a [`CellData`], quantised the same way.

use std::sync::{Arc, OnceLock};

use bytes::Bytes;
use canopy_protocol::aoi::Grid;
use canopy_protocol::edit::CellDelta;
use canopy_protocol::messages::{
    MessageError, ServerStreaming, SpeciesData, SpeciesEntry, TerrainDesc, WelcomeHead, WorldFunction, WorldInfo,
};
use canopy_protocol::record::ParamOverride;
use canopy_protocol::summary::{NodeKey, NodeSummary};
use canopy_protocol::{
    CellBatch, CellCoord, InstanceId, InstanceRecord, POSITION_STEPS, ServerMsg, SpeciesGraph, SpeciesHash, netlimits,
};
use canopy_worlds::world::{CellKey, Placement, World};

use crate::batch::BatchBody;

/// One cell's records as a store holds them, quantised: record `i` is the instance `(cell, i)` ([`InstanceId`]).
/// Shared by `Arc` between the store and the sessions sending it (a cell being sent stays alive while a cache
/// evicts it).
#[derive(Debug)]
pub struct CellData {
    /// The cell.
    pub cell: CellCoord,
    /// The cell's records, by index in the cell.
    pub records: Vec<InstanceRecord>,
    /// Parameter overrides, `record` = index within the cell, sorted by `(record, slot)`.
    pub overrides: Vec<ParamOverride>,
    /// The cell's version: 0 for the world function's records, one more for every edit (`canopy_edits`).
    pub version: u32,
    /// Indices of records felled by edits, increasing (they keep their index and are marked in batches).
    pub felled: Vec<u16>,
    /// The batches' shared bodies for one batch size (the first asked for: a server runs one).
    bodies: OnceLock<(usize, Vec<BatchBody>)>,
}

impl CellData {
    /// A cell of instances already quantised (`(species, [qx, qz], params)`, each step below [`POSITION_STEPS`]),
    /// checked: species in a table of `species_count`, at most 65,535 instances, finite parameters, no slot twice.
    pub fn from_quantised<'p>(
        cell: CellCoord,
        species_count: usize,
        instances: impl ExactSizeIterator<Item = (u16, [u16; 2], &'p [(u16, f32)])>,
    ) -> Result<CellData, StoreError> {
        let n = instances.len();
        if n > usize::from(u16::MAX) {
            return Err(StoreError::CellFull(cell, n));
        }
        if !InstanceId::names(cell) {
            return Err(StoreError::Cell(cell));
        }
        let mut records = Vec::with_capacity(n);
        let mut overrides = Vec::new();
        for (i, (species, q, params)) in instances.enumerate() {
            // The cell can be named and holds at most 65,535 instances.
            let id = InstanceId::new(cell, i as u16).expect("a nameable cell");
            if usize::from(species) >= species_count {
                return Err(StoreError::UnknownSpecies { id, species });
            }
            records.push(InstanceRecord::new(species as u8, q[0], q[1]));
            let sorted;
            let params = if params.is_sorted_by(|a, b| a.0 < b.0) {
                params
            } else {
                // Out of order (worlds keep them sorted): sort a copy; a repeated slot stays next to itself.
                let mut copy = params.to_vec();
                copy.sort_by_key(|&(s, _)| s);
                sorted = copy;
                &sorted[..]
            };
            if params.windows(2).any(|w| w[0].0 == w[1].0) || params.iter().any(|(_, v)| !v.is_finite()) {
                return Err(StoreError::Param(id));
            }
            let record = i as u16;
            overrides.extend(params.iter().map(|&(slot, value)| ParamOverride { record, slot, value }));
        }
        records.shrink_to_fit();
        overrides.shrink_to_fit();
        Ok(CellData { cell, records, overrides, version: 0, felled: Vec::new(), bodies: OnceLock::new() })
    }

    /// The cell at an edit overlay's version: these records (the world function's, then the planted), overrides
    /// and felled indices.
    pub fn edited(
        cell: CellCoord,
        version: u32,
        records: Vec<InstanceRecord>,
        overrides: Vec<ParamOverride>,
        felled: Vec<u16>,
    ) -> CellData {
        CellData { cell, records, overrides, version, felled, bodies: OnceLock::new() }
    }

    /// A cell of a world's placements (`World::expand_cell`), quantised within the cell exactly as
    /// [`World::quantize`] does after finding the cell.
    pub fn from_placements(
        grid: &Grid,
        cell: CellCoord,
        species_count: usize,
        placements: &[Placement],
    ) -> Result<CellData, StoreError> {
        let instances = placements.iter().map(|p| (p.species, grid.steps(cell, p.x, p.z), p.params.as_slice()));
        CellData::from_quantised(cell, species_count, instances)
    }

    /// Records `start..end` as a batch of `grant`, overrides renumbered from the batch's first record.
    pub fn batch(&self, grant: u32, start: usize, end: usize) -> CellBatch {
        let lo = self.overrides.partition_point(|o| usize::from(o.record) < start);
        let hi = self.overrides.partition_point(|o| usize::from(o.record) < end);
        let overrides: Vec<ParamOverride> =
            self.overrides[lo..hi].iter().map(|o| ParamOverride { record: o.record - start as u16, ..*o }).collect();
        let total = self.records.len() as u16;
        let lo = self.felled.partition_point(|&i| usize::from(i) < start);
        let hi = self.felled.partition_point(|&i| usize::from(i) < end);
        let felled = self.felled[lo..hi].iter().map(|&i| i - start as u16);
        CellBatch::new(self.cell, grant, total, start as u16, self.records[start..end].to_vec(), &overrides)
            .at_version(self.version, felled)
    }

    /// The shared bodies of the cell's batches of `batch_records` records (one empty batch for an empty cell),
    /// encoded at the first call and kept; `None` for another batch size than the one kept (encode per session).
    pub fn bodies(&self, batch_records: usize) -> Option<&[BatchBody]> {
        let batch_records = batch_records.max(1);
        let (size, bodies) = self.bodies.get_or_init(|| {
            let n = self.records.len();
            let starts = (0..n.max(1)).step_by(batch_records);
            (batch_records, starts.map(|s| BatchBody::of(&self.batch(0, s, (s + batch_records).min(n)))).collect())
        });
        (*size == batch_records).then_some(bodies.as_slice())
    }

    /// Bytes it holds (records, overrides and the bodies encoded so far).
    pub fn heap_bytes(&self) -> usize {
        let bodies = self.bodies.get().map_or(0, |(_, b)| b.iter().map(BatchBody::heap_bytes).sum());
        std::mem::size_of::<CellData>()
            + self.records.capacity() * std::mem::size_of::<InstanceRecord>()
            + self.overrides.capacity() * std::mem::size_of::<ParamOverride>()
            + self.felled.capacity() * 2
            + bodies
    }
}

/// A cell as a store answers for it.
#[derive(Clone, Debug)]
pub enum CellState {
    /// Its records, ready to send.
    Ready(Arc<CellData>),
    /// Being expanded: the waker passed along is woken when it is ready (ask again then).
    Pending,
    /// Outside the grid.
    Outside,
}

impl CellState {
    /// The records, if ready.
    pub fn ready(self) -> Option<Arc<CellData>> {
        match self {
            CellState::Ready(d) => Some(d),
            _ => None,
        }
    }
}

/// A far-view summary node as a store answers for it ([`WorldStore::summary`]).
#[derive(Clone, Debug)]
pub enum SummaryState {
    /// The node, with its encoding.
    Ready(Arc<EncodedSummary>),
    /// Being computed: the waker passed along is woken when it is ready.
    Pending,
    /// The store has no summaries (or the node lies outside the world).
    Unavailable,
}

/// A summary node and its postcard encoding, made once and shared by every session that sends it.
#[derive(Debug, PartialEq)]
pub struct EncodedSummary {
    /// The node.
    pub node: Arc<NodeSummary>,
    /// Its encoding: what a summaries message carries for it.
    pub bytes: Bytes,
}

impl EncodedSummary {
    /// Encode a node.
    pub fn new(node: Arc<NodeSummary>) -> EncodedSummary {
        let bytes = Bytes::from(postcard::to_allocvec(&*node).expect("encoding a node into a Vec cannot fail"));
        EncodedSummary { node, bytes }
    }

    /// Bytes it holds (the node, its species, its encoding), for cache bounds.
    pub fn heap_bytes(&self) -> usize {
        std::mem::size_of::<EncodedSummary>()
            + std::mem::size_of::<NodeSummary>()
            + self.node.species.capacity() * std::mem::size_of::<canopy_protocol::summary::SpeciesCover>()
            + self.bytes.len()
    }
}

/// Told when cells a session asked for became ready (the driver's wake-up; the session itself never waits).
pub trait CellWaker: Send + Sync {
    /// A cell this waker was registered for is ready.
    fn wake(&self);
}

/// Where a session reads the world from.
pub trait WorldStore: Send + Sync + 'static {
    /// What every client is told the same way: the world's description, species and welcome.
    fn head(&self) -> &StoreHead;
    /// What a client needs to know about the world (sent in the welcome).
    fn world(&self) -> &WorldInfo {
        self.head().world()
    }
    /// The species table; index = species id.
    fn species(&self) -> &[SpeciesEntry] {
        self.head().species()
    }
    /// The encoded graph of species `id`.
    fn species_graph(&self, id: u8) -> Option<&[u8]> {
        self.head().species_graph(id)
    }
    /// The framed species message of species `id` (its graph), encoded once and shared by every session.
    fn species_frame(&self, id: u8) -> Option<Bytes> {
        self.head().species_frame(id)
    }
    /// The welcome's part that is the same for every client, encoded once.
    fn welcome_head(&self) -> &WelcomeHead {
        self.head().welcome_head()
    }
    /// The framed world function for clients that expand cells themselves (`None`: records only).
    fn function_frame(&self) -> Option<Bytes> {
        self.head().function_frame()
    }
    /// A cell's version, never waiting, for a client that expands the cell itself: a cell nobody edited is known
    /// at version 0 without expanding it wherever the store can tell. This default asks [`WorldStore::cell`].
    fn version(&self, c: CellCoord, waker: Option<&Arc<dyn CellWaker>>) -> VersionState {
        match self.cell(c, waker) {
            CellState::Ready(d) if d.version == 0 => VersionState::Unedited,
            CellState::Ready(_) => VersionState::Edited,
            CellState::Pending => VersionState::Pending,
            CellState::Outside => VersionState::Outside,
        }
    }
    /// A cell's records, never waiting: ready, pending (its expansion is queued, once however many ask, and
    /// `waker`, if any, is woken when it is ready), or outside the grid. A cell inside the grid without instances is
    /// ready and empty.
    fn cell(&self, c: CellCoord, waker: Option<&Arc<dyn CellWaker>>) -> CellState;
    /// `waker` no longer wants cell `c` (its session moved on or ended): a cell queued for expansion that nobody
    /// wants any more leaves the queue unexpanded. A store that never queues ignores it.
    fn unwait(&self, c: CellCoord, waker: &Arc<dyn CellWaker>) {
        let _ = (c, waker);
    }
    /// A number that changes whenever a pending cell becomes ready: while it is unchanged, a cell found pending
    /// is still pending, so a session need not ask again (a store whose cells are always ready keeps it at 0).
    fn generation(&self) -> u64 {
        0
    }
    /// The cell grid.
    fn grid(&self) -> &Grid {
        &self.world().grid
    }
    /// A far-view summary node, never waiting (like [`WorldStore::cell`]; the generation moves when a pending one
    /// becomes ready). A store without summaries answers [`SummaryState::Unavailable`].
    fn summary(&self, key: NodeKey, waker: Option<&Arc<dyn CellWaker>>) -> SummaryState {
        let _ = (key, waker);
        SummaryState::Unavailable
    }
    /// The level of the summary hierarchy's roots (the coarsest nodes a session sends).
    fn summary_root_level(&self) -> u8 {
        0
    }
    /// Correct the summary nodes holding cell `c` by its edits (`delta`: the cell's edits from version 0; `None`:
    /// it has none), blocking while the cell's world-function placements are computed: a node holding the cell
    /// answers as corrected from when this returns. Whether the nodes changed; a store without summaries has
    /// nothing to correct.
    fn correct_summaries(&self, c: CellCoord, delta: Option<&CellDelta>) -> bool {
        let _ = (c, delta);
        false
    }
    /// The cells whose summary nodes were corrected after the store had made `since` corrections (a session that
    /// holds nodes over them sends them again), and its count now ([`SummaryCorrections`]).
    fn summary_corrections(&self, since: u64) -> SummaryCorrections {
        let _ = since;
        SummaryCorrections { now: 0, cells: Some(Vec::new()) }
    }
    /// The cell cache's counters, for a store that expands cells on demand.
    fn cache_metrics(&self) -> Option<Arc<crate::counters::CellMetrics>> {
        None
    }
    /// The edited cells in the rectangle `lo ..= hi` with their versions, at most `max` of them, for the far views
    /// of clients that expand cells (see `session/far_edits.rs`). A store without edits has none.
    fn edited_cells(&self, _lo: CellCoord, _hi: CellCoord, _max: usize) -> Vec<(CellCoord, u32)> {
        Vec::new()
    }

    /// What changed in cell `c` since version `from`, for a session that holds it at `from` (never waiting, like
    /// [`WorldStore::cell`]). A store without edits is always at version 0, so this default only tells whether the
    /// session is current; the server's live store (`canopy_server::LiveStore`) composes deltas.
    fn changes(&self, c: CellCoord, from: u32, waker: Option<&Arc<dyn CellWaker>>) -> Changes {
        match self.cell(c, waker) {
            CellState::Ready(d) if d.version == from => Changes::Current { total: d.records.len() as u16 },
            CellState::Ready(_) | CellState::Outside => Changes::Whole,
            CellState::Pending => Changes::Pending,
        }
    }
}

/// What [`WorldStore::summary_corrections`] answers.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SummaryCorrections {
    /// The store's count of corrections now (what to ask from next).
    pub now: u64,
    /// The cells corrected since the count asked from, oldest first; `None` when that count is older than the
    /// store remembers (any node may have changed).
    pub cells: Option<Vec<CellCoord>>,
}

/// A cell's version as [`WorldStore::version`] finds it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VersionState {
    /// At version 0: the world function's records alone.
    Unedited,
    /// Edited: [`WorldStore::changes`] from version 0 gives its overlay.
    Edited,
    /// Not known yet (ask again when the waker fires).
    Pending,
    /// Outside the grid.
    Outside,
}

/// What changed in a cell since a version a session holds ([`WorldStore::changes`]).
#[derive(Clone, Debug, PartialEq)]
pub enum Changes {
    /// Nothing: the cell is at that version, and has `total` records (felled ones included).
    Current {
        /// The cell's record count at that version.
        total: u16,
    },
    /// What changed, for grant 0 (the session sets its own).
    Delta(canopy_protocol::edit::CellDelta),
    /// It cannot be said from that version (too old, unknown, too large a change): send the whole cell again.
    Whole,
    /// Not known yet: the cell is being expanded (ask again when the waker fires).
    Pending,
}

/// Why a world could not be turned into a store.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StoreError {
    /// More species than a record's byte can name.
    #[error("world has {0} species (allowed {max})", max = netlimits::MAX_SPECIES)]
    Species(usize),
    /// A cell holds more instances than a batch index can address.
    #[error("cell {0:?} holds {1} instances (allowed 65535)")]
    CellFull(CellCoord, usize),
    /// An instance names a species the table does not have.
    #[error("instance {id:?} names species {species}, which is not in the table")]
    UnknownSpecies {
        /// The instance.
        id: InstanceId,
        /// The species id.
        species: u16,
    },
    /// A cell was added twice or out of order, lies outside the grid, or outside the cells ids can name.
    #[error("cell {0:?} is outside the grid or the cells ids can name, repeated, or out of order")]
    Cell(CellCoord),
    /// The grid's numbers are not acceptable.
    #[error("grid: {0}")]
    Grid(#[from] canopy_protocol::aoi::GridError),
    /// The world's description (terrain, name) would not pass a client's check of the welcome.
    #[error("world: {0}")]
    World(MessageError),
    /// A species graph is invalid.
    #[error("species {0}: {1}")]
    Graph(usize, canopy_protocol::ValidateError),
    /// A parameter override is not finite or its slot repeats.
    #[error("instance {0:?} has a non-finite or repeated parameter")]
    Param(InstanceId),
}

/// What every store tells every client the same way: the world's description, the species table and frames, the
/// welcome's shared part.
#[derive(Debug)]
pub struct StoreHead {
    world: WorldInfo,
    species: Vec<SpeciesEntry>,
    /// Per species, its framed [`ServerStreaming::Species`] message; the graph is the frame's last `size` bytes.
    species_frames: Vec<Bytes>,
    /// The framed [`ServerStreaming::Function`] message, for a world offered to clients that expand cells.
    function_frame: Option<Bytes>,
    welcome: WelcomeHead,
    bounds: [f32; 4],
}

impl StoreHead {
    /// The head of a world with `instances` instances, from a builder's description.
    fn new(mut b: StoreBuilder, instances: u32) -> StoreHead {
        b.world.instances = instances;
        let function_frame = b.function.map(|f| {
            b.world.function = Some(f.hash());
            Bytes::from(ServerMsg::Streaming(ServerStreaming::Function(f)).encode_framed())
        });
        let welcome = WelcomeHead::new(&b.world, &b.species);
        StoreHead {
            world: b.world,
            species: b.species,
            species_frames: b.species_frames,
            function_frame,
            welcome,
            bounds: b.bounds,
        }
    }

    /// The framed world function, for a world offered to clients that expand cells themselves (its hash is the
    /// welcome's [`WorldInfo::function`]).
    pub fn function_frame(&self) -> Option<Bytes> {
        self.function_frame.clone()
    }

    /// The world's bounds `[x0, z0, x1, z1]` (x1 and z1 exclusive): where instances may stand. The cell grid covers
    /// them and may reach past them (cells are aligned to the origin).
    pub fn bounds(&self) -> [f32; 4] {
        self.bounds
    }

    /// The head of a loaded world: its name, seed, cell grid, terrain and species, and its instance count (0 for
    /// a world expanded on demand, which has no count).
    pub fn of_world(world: &World) -> Result<StoreHead, StoreError> {
        let b = StoreBuilder::of_world(world)?;
        Ok(StoreHead::new(b, world.instances.len() as u32))
    }

    /// The description sent in the welcome.
    pub fn world(&self) -> &WorldInfo {
        &self.world
    }

    /// The species table.
    pub fn species(&self) -> &[SpeciesEntry] {
        &self.species
    }

    /// The encoded graph of species `id`.
    pub fn species_graph(&self, id: u8) -> Option<&[u8]> {
        let frame = self.species_frames.get(usize::from(id))?;
        Some(&frame[frame.len() - self.species[usize::from(id)].size as usize..])
    }

    /// The framed species message of species `id`.
    pub fn species_frame(&self, id: u8) -> Option<Bytes> {
        self.species_frames.get(usize::from(id)).cloned()
    }

    /// The welcome's shared part.
    pub fn welcome_head(&self) -> &WelcomeHead {
        &self.welcome
    }
}

/// The row-major index of a cell of the grid.
pub(crate) fn cell_index(grid: &Grid, c: CellCoord) -> Option<usize> {
    let width = i64::from(grid.max.x) - i64::from(grid.min.x) + 1;
    let (dx, dz) = (i64::from(c.x) - i64::from(grid.min.x), i64::from(c.z) - i64::from(grid.min.z));
    grid.contains(c).then(|| (dz * width + dx) as usize)
}

/// The eager store: every cell quantised up front, row-major (z, then x). Tests and small worlds use it; a server
/// of a large world uses the server's cell cache (`canopy_server::CellCache`), which quantises cells the same way ([`CellData`]) on demand.
#[derive(Debug)]
pub struct GridStore {
    head: StoreHead,
    cells: Vec<Arc<CellData>>,
}

/// One instance as a store builder takes it: world position and parameters that differ from the defaults.
#[derive(Clone, Debug, PartialEq)]
pub struct PlacedInstance {
    /// Species id.
    pub species: u16,
    /// World position on (x, z), metres (quantised within its cell).
    pub x: f32,
    /// See `x`.
    pub z: f32,
    /// `(slot, value)` overrides.
    pub params: Vec<(u16, f32)>,
}

/// Builds a [`GridStore`] cell by cell, in row-major order (z, then x), each cell's instances by index in the cell;
/// cells not added are empty.
#[derive(Debug)]
pub struct StoreBuilder {
    world: WorldInfo,
    species: Vec<SpeciesEntry>,
    species_frames: Vec<Bytes>,
    /// The world function offered to clients that expand cells ([`StoreBuilder::function`]).
    function: Option<WorldFunction>,
    cells: Vec<Arc<CellData>>,
    /// Instances added so far.
    count: u32,
    /// Where instances may stand, `[x0, z0, x1, z1]`; the grid's extent unless [`StoreBuilder::bounds`] says less.
    bounds: [f32; 4],
}

impl StoreBuilder {
    /// Start a store for a world with this name (cut to [`netlimits::MAX_WORLD_NAME`] bytes), seed, grid, terrain
    /// description and species, checked as a client checks the welcome.
    pub fn new<'a>(
        name: &str,
        seed: u64,
        grid: Grid,
        terrain: TerrainDesc,
        species: impl IntoIterator<Item = &'a SpeciesGraph, IntoIter: ExactSizeIterator>,
    ) -> Result<StoreBuilder, StoreError> {
        let species = species.into_iter();
        if species.len() > netlimits::MAX_SPECIES {
            return Err(StoreError::Species(species.len()));
        }
        let mut entries = Vec::with_capacity(species.len());
        let mut species_frames = Vec::with_capacity(species.len());
        for (i, g) in species.enumerate() {
            g.validate().map_err(|e| StoreError::Graph(i, e))?;
            let graph = g.encode();
            entries.push(SpeciesEntry { hash: SpeciesHash::of(&graph), size: graph.len() as u32 });
            let msg = ServerMsg::Streaming(ServerStreaming::Species(SpeciesData { id: i as u8, graph }));
            species_frames.push(Bytes::from(msg.encode_framed()));
        }
        // The name limit counts bytes: cut at the last character boundary within it.
        let mut end = name.len().min(netlimits::MAX_WORLD_NAME);
        while !name.is_char_boundary(end) {
            end -= 1;
        }
        let world = WorldInfo {
            name: name[..end].to_owned(),
            seed,
            grid,
            position_steps: POSITION_STEPS,
            instances: 0,
            terrain,
            function: None,
        };
        world.validate().map_err(|e| match e {
            MessageError::Grid(e) => StoreError::Grid(e),
            e => StoreError::World(e),
        })?;
        if !InstanceId::names(grid.min) || !InstanceId::names(grid.max) {
            return Err(StoreError::Grid(canopy_protocol::aoi::GridError::Range { min: grid.min, max: grid.max }));
        }
        let [x0, z0] = grid.cell_origin(grid.min);
        let [x1, z1] = grid.cell_origin(CellCoord::new(grid.max.x + 1, grid.max.z + 1));
        Ok(StoreBuilder {
            world,
            species: entries,
            species_frames,
            function: None,
            cells: vec![],
            count: 0,
            bounds: [x0, z0, x1, z1],
        })
    }

    /// Say where instances may stand, `[x0, z0, x1, z1]` (x1 and z1 exclusive; within the grid's cells).
    pub fn bounds(mut self, bounds: [f32; 4]) -> StoreBuilder {
        self.bounds = bounds;
        self
    }

    /// A builder for a loaded world's description (no cells added yet).
    fn of_world(world: &World) -> Result<StoreBuilder, StoreError> {
        let first = world.first_cell();
        let dims = world.cell_dims();
        let grid = Grid {
            origin: world.cell_origin(CellKey { x: 0, z: 0 }),
            cell_size: world.cell_size,
            min: CellCoord::new(first.x, first.z),
            max: CellCoord::new(first.x + dims[0] as i32 - 1, first.z + dims[1] as i32 - 1),
        };
        let terrain = crate::terrain::terrain_desc(world);
        let graphs = world.species.iter().map(|s| &s.graph);
        let [x0, z0] = world.bounds.min;
        let [x1, z1] = world.bounds.max;
        let builder = StoreBuilder::new(&world.name, world.seed, grid, terrain, graphs)?.bounds([x0, z0, x1, z1]);
        Ok(builder.function(&world.function))
    }

    /// Offer the world to clients that expand cells themselves, by this world function (the manifest its cells
    /// are the expansion of); a manifest over [`netlimits::MAX_FUNCTION_BYTES`], or none, offers records only.
    pub fn function(mut self, manifest: &str) -> StoreBuilder {
        let fits = !manifest.is_empty() && manifest.len() <= netlimits::MAX_FUNCTION_BYTES;
        self.function = fits.then(|| WorldFunction { manifest: manifest.to_owned() });
        self
    }

    /// Add one cell's instances, by index in the cell (instance `i` is `(cell, i)`). Positions are quantised to the
    /// cell's [`POSITION_STEPS`] grid.
    pub fn add_cell(&mut self, cell: CellCoord, instances: &[PlacedInstance]) -> Result<(), StoreError> {
        let grid = self.world.grid;
        let quantised =
            instances.iter().map(|p| (p.species, grid.steps(cell, p.x.into(), p.z.into()), p.params.as_slice()));
        let index = self.next_index(cell)?;
        let data = CellData::from_quantised(cell, self.species.len(), quantised)?;
        self.push(index, data);
        Ok(())
    }

    /// The index of `cell` if it may be added next (inside the grid, after every cell added so far).
    fn next_index(&self, cell: CellCoord) -> Result<usize, StoreError> {
        match cell_index(&self.world.grid, cell) {
            Some(i) if i >= self.cells.len() => Ok(i),
            _ => Err(StoreError::Cell(cell)),
        }
    }

    /// Add a quantised cell at `index`, the cells before it not added empty.
    fn push(&mut self, index: usize, data: CellData) {
        self.pad_to(index);
        self.count = self.count.saturating_add(data.records.len() as u32);
        self.cells.push(Arc::new(data));
    }

    /// Add empty cells up to (not including) `index`.
    fn pad_to(&mut self, index: usize) {
        let grid = self.world.grid;
        let width = (i64::from(grid.max.x) - i64::from(grid.min.x) + 1) as usize;
        while self.cells.len() < index {
            let i = self.cells.len();
            let cell = CellCoord::new(grid.min.x + (i % width) as i32, grid.min.z + (i / width) as i32);
            let empty = CellData::from_quantised(cell, 0, std::iter::empty()).expect("an empty cell");
            self.cells.push(Arc::new(empty));
        }
    }

    /// Finish: cells of the grid that were not added are empty.
    pub fn finish(mut self) -> GridStore {
        let count = cell_index(&self.world.grid, self.world.grid.max).map_or(0, |i| i + 1);
        self.pad_to(count);
        let cells = std::mem::take(&mut self.cells);
        let instances = self.count;
        GridStore { head: StoreHead::new(self, instances), cells }
    }
}

impl GridStore {
    /// The store of a loaded world: its species table, its cells expanded ([`World::expand_cell`]) with their
    /// instances by index in the cell, quantised positions exactly as [`World::quantize`] gives them, and its terrain
    /// description for the welcome.
    pub fn from_world(world: &World) -> Result<GridStore, StoreError> {
        let mut b = StoreBuilder::of_world(world)?;
        let grid = b.world.grid;
        for c in world.cells() {
            let cell = CellCoord::new(c.x, c.z);
            let index = b.next_index(cell)?;
            let data = CellData::from_placements(&grid, cell, b.species.len(), &world.expand_cell(c))?;
            b.push(index, data);
        }
        Ok(b.finish())
    }

    /// How many cells hold at least one instance.
    pub fn occupied_cells(&self) -> usize {
        self.cells.iter().filter(|c| !c.records.is_empty()).count()
    }

    /// Share it between sessions.
    pub fn shared(self) -> Arc<dyn WorldStore> {
        Arc::new(self)
    }
}

impl WorldStore for GridStore {
    fn head(&self) -> &StoreHead {
        &self.head
    }

    fn cell(&self, c: CellCoord, _waker: Option<&Arc<dyn CellWaker>>) -> CellState {
        match cell_index(self.grid(), c) {
            Some(i) => CellState::Ready(Arc::clone(&self.cells[i])),
            None => CellState::Outside,
        }
    }
}
