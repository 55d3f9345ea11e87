//! The world store: species and instance records arranged spatially (seed 001 §4: "the server stores the data for
//! a very large virtual environment, composed of objects that are arranged spatially"), behind a trait so a
//! session does not care where they live. The embedded default is [`GridStore`], an in-memory grid of cells.

use std::collections::HashMap;
use std::sync::Arc;

use canopy_protocol::aoi::Grid;
use bytes::Bytes;
use canopy_protocol::messages::{
    MessageError, ServerStreaming, SpeciesData, SpeciesEntry, TerrainDesc, WelcomeHead, WorldInfo,
};
use canopy_protocol::record::{ParamOverride, quantize};
use canopy_protocol::{CellCoord, InstanceRecord, POSITION_STEPS, ServerMsg, SpeciesGraph, SpeciesHash, netlimits};
use canopy_worlds::world::{CellKey, World};

/// One cell's records as a store holds them: consecutive instance ids from `first_id`.
#[derive(Clone, Copy, Debug)]
pub struct CellView<'a> {
    /// Instance id of `records[0]`.
    pub first_id: u32,
    /// The cell's records.
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
    /// The cell grid.
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
    #[error("instance {id} names species {species}, which is not in the table")]
    UnknownSpecies {
        /// The instance id.
        id: u32,
        /// The species id.
        species: u16,
    },
    /// A cell was added twice, lies outside the grid, or its ids do not follow the previous cell's.
    #[error("cell {0:?} is outside the grid, repeated, or out of id order")]
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
    #[error("instance {0} has a non-finite or repeated parameter")]
    Param(u32),
}

#[derive(Debug, Default)]
struct CellData {
    first_id: u32,
    records: Vec<InstanceRecord>,
    overrides: Vec<ParamOverride>,
}

/// The embedded default store: every cell's records in memory, found by cell coordinate.
#[derive(Debug)]
pub struct GridStore {
    world: WorldInfo,
    species: Vec<SpeciesEntry>,
    /// Per species, its framed [`ServerStreaming::Species`] message; the graph is the frame's last `size` bytes.
    species_frames: Vec<Bytes>,
    welcome: WelcomeHead,
    cells: HashMap<CellCoord, CellData>,
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

/// Builds a [`GridStore`] cell by cell, in instance id order.
#[derive(Debug)]
pub struct StoreBuilder {
    world: WorldInfo,
    species: Vec<SpeciesEntry>,
    species_frames: Vec<Bytes>,
    cells: HashMap<CellCoord, CellData>,
    next_id: u32,
}

impl StoreBuilder {
    /// Start a store for a world with this name (cut to [`netlimits::MAX_WORLD_NAME`] bytes), seed, grid, terrain
    /// description and species, checked as a client checks the welcome.
    pub fn new(
        name: &str,
        seed: u64,
        grid: Grid,
        terrain: TerrainDesc,
        species: &[SpeciesGraph],
    ) -> Result<StoreBuilder, StoreError> {
        if species.len() > netlimits::MAX_SPECIES {
            return Err(StoreError::Species(species.len()));
        }
        let mut entries = Vec::with_capacity(species.len());
        let mut species_frames = Vec::with_capacity(species.len());
        for (i, g) in species.iter().enumerate() {
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
        let world =
            WorldInfo { name: name[..end].to_owned(), seed, grid, position_steps: POSITION_STEPS, instances: 0, terrain };
        world.validate().map_err(|e| match e {
            MessageError::Grid(e) => StoreError::Grid(e),
            e => StoreError::World(e),
        })?;
        Ok(StoreBuilder { world, species: entries, species_frames, cells: HashMap::new(), next_id: 0 })
    }

    /// Add one cell's instances; their ids continue from the previous cell's. Positions are quantised to the
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

    /// Add one cell's instances already quantised: `(species, [qx, qz], params)`.
    pub fn add_quantised<'p>(
        &mut self,
        cell: CellCoord,
        instances: impl ExactSizeIterator<Item = (u16, [u16; 2], &'p [(u16, f32)])>,
    ) -> Result<(), StoreError> {
        if !self.world.grid.contains(cell) || self.cells.contains_key(&cell) {
            return Err(StoreError::Cell(cell));
        }
        let n = instances.len();
        if n > usize::from(u16::MAX) {
            return Err(StoreError::CellFull(cell, n));
        }
        let mut data = CellData { first_id: self.next_id, records: Vec::with_capacity(n), overrides: vec![] };
        for (i, (species, q, params)) in instances.enumerate() {
            let id = self.next_id + i as u32;
            if usize::from(species) >= self.species.len() {
                return Err(StoreError::UnknownSpecies { id, species });
            }
            let steps = POSITION_STEPS as u16 - 1;
            data.records.push(InstanceRecord::new(species as u8, q[0].min(steps), q[1].min(steps)));
            let mut params = params.to_vec();
            params.sort_by_key(|&(s, _)| s);
            if params.windows(2).any(|w| w[0].0 == w[1].0) || params.iter().any(|(_, v)| !v.is_finite()) {
                return Err(StoreError::Param(id));
            }
            data.overrides.extend(params.into_iter().map(|(slot, value)| ParamOverride {
                record: i as u16,
                slot,
                value,
            }));
        }
        self.next_id = self.next_id.checked_add(n as u32).ok_or(StoreError::Cell(cell))?;
        self.cells.insert(cell, data);
        Ok(())
    }

    /// Finish: cells of the grid that were not added are empty.
    pub fn finish(mut self) -> GridStore {
        self.world.instances = self.next_id;
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
    /// The store of a loaded world: its species table, its cells with their instances in id order, quantised
    /// positions exactly as [`World::quantize`] gives them, and its terrain description for the welcome.
    pub fn from_world(world: &World) -> Result<GridStore, StoreError> {
        let first = world.first_cell();
        let dims = world.cell_dims();
        let grid = Grid {
            origin: world.cell_origin(CellKey { x: 0, z: 0 }),
            cell_size: world.cell_size,
            min: CellCoord::new(first.x, first.z),
            max: CellCoord::new(first.x + dims[0] as i32 - 1, first.z + dims[1] as i32 - 1),
        };
        let graphs: Vec<SpeciesGraph> = world.species.iter().map(|s| s.graph.clone()).collect();
        let terrain = crate::terrain::describe(&world.terrain);
        let mut b = StoreBuilder::new(&world.name, world.seed, grid, terrain, &graphs)?;
        for c in world.cells() {
            let ids = world.cell_instances(c);
            if ids.start != b.next_id {
                return Err(StoreError::Cell(CellCoord::new(c.x, c.z)));
            }
            let instances = ids.map(|id| {
                let p = &world.instances[id as usize];
                let (_, q) = world.quantize(id);
                (p.species, q, p.params.as_slice())
            });
            b.add_quantised(CellCoord::new(c.x, c.z), instances)?;
        }
        Ok(b.finish())
    }

    /// How many cells hold at least one instance.
    pub fn occupied_cells(&self) -> usize {
        self.cells.values().filter(|c| !c.records.is_empty()).count()
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
        if !self.world.grid.contains(c) {
            return None;
        }
        Some(match self.cells.get(&c) {
            Some(d) => CellView { first_id: d.first_id, records: &d.records, overrides: &d.overrides },
            None => CellView { first_id: 0, records: &[], overrides: &[] },
        })
    }
}
