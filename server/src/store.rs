//! The world store: species and instance records arranged spatially (seed 001 §4: "the server stores the data for
//! a very large virtual environment, composed of objects that are arranged spatially"), behind a trait so a
//! session does not care where they live. The embedded default is [`GridStore`], an in-memory grid of cells.

use std::sync::Arc;

use bytes::Bytes;
use canopy_protocol::aoi::Grid;
use canopy_protocol::messages::{
    MessageError, ServerStreaming, SpeciesData, SpeciesEntry, TerrainDesc, WelcomeHead, WorldInfo,
};
use canopy_protocol::record::{ParamOverride, quantize};
use canopy_protocol::{
    CellCoord, InstanceId, InstanceRecord, POSITION_STEPS, ServerMsg, SpeciesGraph, SpeciesHash, netlimits,
};
use canopy_worlds::world::{CellKey, World};

/// One cell's records as a store holds them: record `i` is the instance `(cell, i)` ([`InstanceId`]).
#[derive(Clone, Copy, Debug)]
pub struct CellView<'a> {
    /// The cell's records, by index in the cell.
    pub records: &'a [InstanceRecord],
    /// Parameter overrides, `record` = index within the cell, sorted by `(record, slot)`.
    pub overrides: &'a [ParamOverride],
}

/// Where a session reads the world from.
pub trait WorldStore: Send + Sync + 'static {
    /// What a client needs to know about the world (sent in the welcome).
    fn world(&self) -> &WorldInfo;
    /// The species table; index = species id.
    fn species(&self) -> &[SpeciesEntry];
    /// The encoded graph of species `id`.
    fn species_graph(&self, id: u8) -> Option<&[u8]>;
    /// The framed species message of species `id` (its graph), encoded once and shared by every session.
    fn species_frame(&self, id: u8) -> Option<Bytes>;
    /// The welcome's part that is the same for every client, encoded once.
    fn welcome_head(&self) -> &WelcomeHead;
    /// A cell's records; `None` for a cell outside the grid. A cell inside the grid without instances is empty.
    fn cell(&self, c: CellCoord) -> Option<CellView<'_>>;
    /// The cell grid; it lies within the cells an [`InstanceId`] can name, so record `i` of a cell is the instance
    /// `(cell, i)`.
    fn grid(&self) -> &Grid {
        &self.world().grid
    }
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
    /// A cell was added twice or out of row-major order, lies outside the grid, or would take the store past
    /// `u32::MAX` records.
    #[error("cell {0:?} is outside the grid, repeated, out of order, or past the store's record count")]
    Cell(CellCoord),
    /// The grid's numbers are not acceptable, or it reaches past the cells an [`InstanceId`] can name.
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

/// The embedded default store: every instance's record, cells in row-major order (z, then x) as ranges of them,
/// each cell's records by index in the cell.
#[derive(Debug)]
pub struct GridStore {
    world: WorldInfo,
    species: Vec<SpeciesEntry>,
    /// Per species, its framed [`ServerStreaming::Species`] message; the graph is the frame's last `size` bytes.
    species_frames: Vec<Bytes>,
    welcome: WelcomeHead,
    cells: Cells,
}

/// Records and parameter overrides of a grid's cells, row-major: cell `i` holds records
/// `starts[i][0]..starts[i + 1][0]` (by index in the cell) and overrides `starts[i][1]..starts[i + 1][1]`.
#[derive(Debug)]
struct Cells {
    records: Vec<InstanceRecord>,
    /// Overrides, `record` = index within the cell.
    overrides: Vec<ParamOverride>,
    starts: Vec<[u32; 2]>,
}

impl Cells {
    /// The row-major index of a cell of the grid.
    fn index(grid: &Grid, c: CellCoord) -> Option<usize> {
        let width = i64::from(grid.max.x) - i64::from(grid.min.x) + 1;
        let (dx, dz) = (i64::from(c.x) - i64::from(grid.min.x), i64::from(c.z) - i64::from(grid.min.z));
        grid.contains(c).then(|| (dz * width + dx) as usize)
    }

    /// How many cells the grid has.
    fn count(grid: &Grid) -> usize {
        Cells::index(grid, grid.max).map_or(0, |i| i + 1)
    }

    /// Cells begun so far (added or skipped).
    fn len(&self) -> usize {
        self.starts.len() - 1
    }

    /// Close every cell before `index` not begun yet: they are empty.
    fn pad_to(&mut self, index: usize) {
        let last = *self.starts.last().expect("starts has its first entry");
        self.starts.resize(self.starts.len().max(index + 1), last);
    }
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
    cells: Cells,
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
        };
        world.validate().map_err(|e| match e {
            MessageError::Grid(e) => StoreError::Grid(e),
            e => StoreError::World(e),
        })?;
        if !InstanceId::names(grid.min) || !InstanceId::names(grid.max) {
            return Err(StoreError::Grid(canopy_protocol::aoi::GridError::Range { min: grid.min, max: grid.max }));
        }
        let cells = Cells { records: vec![], overrides: vec![], starts: vec![[0, 0]] };
        Ok(StoreBuilder { world, species: entries, species_frames, cells })
    }

    /// Add one cell's instances, by index in the cell (instance `i` is `(cell, i)`). Positions are quantised to the
    /// cell's [`POSITION_STEPS`] grid.
    pub fn add_cell(&mut self, cell: CellCoord, instances: &[PlacedInstance]) -> Result<(), StoreError> {
        let grid = self.world.grid;
        let origin = grid.cell_origin(cell);
        let quantised = instances.iter().map(|p| {
            let q = [quantize(p.x, origin[0], grid.cell_size), quantize(p.z, origin[1], grid.cell_size)];
            (p.species, q, p.params.as_slice())
        });
        self.add_quantised(cell, quantised)
    }

    /// Add one cell's instances already quantised (`(species, [qx, qz], params)`, each step below
    /// [`POSITION_STEPS`]).
    fn add_quantised<'p>(
        &mut self,
        cell: CellCoord,
        instances: impl ExactSizeIterator<Item = (u16, [u16; 2], &'p [(u16, f32)])>,
    ) -> Result<(), StoreError> {
        let index = match Cells::index(&self.world.grid, cell) {
            Some(i) if i >= self.cells.len() => i,
            _ => return Err(StoreError::Cell(cell)),
        };
        let n = instances.len();
        if n > usize::from(u16::MAX) {
            return Err(StoreError::CellFull(cell, n));
        }
        self.record_count().checked_add(n as u32).ok_or(StoreError::Cell(cell))?;
        self.cells.pad_to(index);
        let cells = &mut self.cells;
        let (records, overrides) = (cells.records.len(), cells.overrides.len());
        let added = Self::push_instances(cells, self.species.len(), cell, instances);
        if added.is_err() {
            // Leave the builder as it was: the cell was not added.
            cells.records.truncate(records);
            cells.overrides.truncate(overrides);
            return added;
        }
        cells.starts.push([cells.records.len() as u32, cells.overrides.len() as u32]);
        Ok(())
    }

    fn push_instances<'p>(
        cells: &mut Cells,
        species_count: usize,
        cell: CellCoord,
        instances: impl ExactSizeIterator<Item = (u16, [u16; 2], &'p [(u16, f32)])>,
    ) -> Result<(), StoreError> {
        cells.records.reserve(instances.len());
        for (i, (species, q, params)) in instances.enumerate() {
            // The grid lies within the cells ids can name (`StoreBuilder::new`) and the cell holds at most 65,535.
            let id = || InstanceId::new(cell, i as u16).expect("a nameable cell");
            if usize::from(species) >= species_count {
                return Err(StoreError::UnknownSpecies { id: id(), species });
            }
            cells.records.push(InstanceRecord::new(species as u8, q[0], q[1]));
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
                return Err(StoreError::Param(id()));
            }
            let record = i as u16;
            cells.overrides.extend(params.iter().map(|&(slot, value)| ParamOverride { record, slot, value }));
        }
        Ok(())
    }

    /// How many instances the cells added so far hold.
    fn record_count(&self) -> u32 {
        self.cells.records.len() as u32
    }

    /// Finish: cells of the grid that were not added are empty.
    pub fn finish(mut self) -> GridStore {
        self.world.instances = self.record_count();
        self.cells.pad_to(Cells::count(&self.world.grid));
        let welcome = WelcomeHead::new(&self.world, &self.species);
        GridStore {
            world: self.world,
            species: self.species,
            species_frames: self.species_frames,
            welcome,
            cells: self.cells,
        }
    }
}

impl GridStore {
    /// The store of a loaded world: its species table, its cells with their instances by index in the cell
    /// ([`World::cell_instances`]), quantised positions exactly as [`World::quantize`] gives them, and its terrain
    /// description for the welcome.
    pub fn from_world(world: &World) -> Result<GridStore, StoreError> {
        let first = world.first_cell();
        let dims = world.cell_dims();
        let grid = Grid {
            origin: world.cell_origin(CellKey { x: 0, z: 0 }),
            cell_size: world.cell_size,
            min: CellCoord::new(first.x, first.z),
            max: CellCoord::new(first.x + dims[0] as i32 - 1, first.z + dims[1] as i32 - 1),
        };
        let terrain = crate::terrain::describe(&world.terrain);
        let graphs = world.species.iter().map(|s| &s.graph);
        let mut b = StoreBuilder::new(&world.name, world.seed, grid, terrain, graphs)?;
        for c in world.cells() {
            let range = world.cell_instances(c);
            let cell = CellCoord::new(c.x, c.z);
            // The cell is known: quantise within it (what `World::quantize` does after finding the cell).
            let origin = grid.cell_origin(cell);
            let instances = world.instances[range.start as usize..range.end as usize].iter().map(|p| {
                let q = [quantize(p.x, origin[0], grid.cell_size), quantize(p.z, origin[1], grid.cell_size)];
                (p.species, q, p.params.as_slice())
            });
            b.add_quantised(cell, instances)?;
        }
        Ok(b.finish())
    }

    /// How many cells hold at least one instance.
    pub fn occupied_cells(&self) -> usize {
        self.cells.starts.windows(2).filter(|w| w[1][0] > w[0][0]).count()
    }

    /// Share it between sessions.
    pub fn shared(self) -> Arc<dyn WorldStore> {
        Arc::new(self)
    }
}

impl WorldStore for GridStore {
    fn world(&self) -> &WorldInfo {
        &self.world
    }

    fn species(&self) -> &[SpeciesEntry] {
        &self.species
    }

    fn species_graph(&self, id: u8) -> Option<&[u8]> {
        let frame = self.species_frames.get(usize::from(id))?;
        Some(&frame[frame.len() - self.species[usize::from(id)].size as usize..])
    }

    fn species_frame(&self, id: u8) -> Option<Bytes> {
        self.species_frames.get(usize::from(id)).cloned()
    }

    fn welcome_head(&self) -> &WelcomeHead {
        &self.welcome
    }

    fn cell(&self, c: CellCoord) -> Option<CellView<'_>> {
        let i = Cells::index(&self.world.grid, c)?;
        let ([r0, o0], [r1, o1]) = (self.cells.starts[i], self.cells.starts[i + 1]);
        Some(CellView {
            records: &self.cells.records[r0 as usize..r1 as usize],
            overrides: &self.cells.overrides[o0 as usize..o1 as usize],
        })
    }
}
