//! What the welcome tells a client about the world: its name, seed and cell grid, its terrain (a tiled terrain
//! species or a fractal's numbers) and the hash of its world function; each checked as a decoder checks it.

use serde::{Deserialize, Serialize};

use crate::aoi::Grid;
use crate::messages::{MessageError, SpeciesHash, count};
use crate::record::POSITION_STEPS;
use crate::{limits, netlimits};

/// What a client needs to know about the world to place and amplify instances.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorldInfo {
    /// The world's name.
    pub name: String,
    /// The world seed; instance seeds derive from it and the [`InstanceId`] (cell, index in the cell).
    pub seed: u64,
    /// The cell grid.
    pub grid: Grid,
    /// Positions are quantised to `cell_size / position_steps` per axis (always [`POSITION_STEPS`] today).
    pub position_steps: u32,
    /// How many instances the world holds.
    pub instances: u32,
    /// The terrain, from which the client computes heights.
    pub terrain: TerrainDesc,
    /// The hash of the world function ([`WorldFunction::hash`]) for clients that expand cells themselves; `None`
    /// where the server offers records only.
    pub function: Option<SpeciesHash>,
}

impl WorldInfo {
    /// Check the name's length, the terrain, the position steps and the grid (the welcome's decoder calls this;
    /// a server checks its world with it before it welcomes anyone).
    pub fn validate(&self) -> Result<(), MessageError> {
        count("world name", self.name.len(), netlimits::MAX_WORLD_NAME)?;
        self.terrain.validate()?;
        if self.position_steps != POSITION_STEPS {
            return Err(MessageError::World("position steps differ from 4096"));
        }
        Ok(self.grid.validate()?)
    }
}

/// The world's terrain as the client rebuilds it (seed 001 §5, Figure 7: a fractal terrain species tiled over the
/// world): the terrain species and its tiling. The client amplifies the tiles itself, bit for bit as the server.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TerrainDesc {
    /// The terrain species' encoded graph; `None` for flat ground at height 0.
    pub graph: Option<Vec<u8>>,
    /// The instance seed of every tile.
    pub seed: u64,
    /// World (x, z) of the corner of tile (0, 0).
    pub origin: [f32; 2],
    /// Tile edge, metres.
    pub tile_size: f32,
    /// Tiles per axis.
    pub tiles: [u32; 2],
    /// Recursion depth of every tile.
    pub depth: u32,
    /// Heights at the tile corners, `(tiles[0] + 1) × (tiles[1] + 1)`, rows of increasing z.
    pub corners: Vec<f32>,
    /// Other parameter values of the terrain species, sorted by slot.
    pub params: Vec<(u16, f32)>,
    /// The terrain as a function (`terrain fractal { … }`): when present it is the ground, computed by the client
    /// from these numbers bit for bit as the server, and the fields above describe only a flat placeholder.
    pub fractal: Option<FractalDesc>,
}

/// A fractal terrain's numbers (`canopy_worlds::world::Fractal`): no height grid, only what computes one.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FractalDesc {
    /// Noise seed.
    pub seed: u64,
    /// World (x, z) of lattice point (0, 0) at every level.
    pub origin: [f64; 2],
    /// Level-0 lattice spacing, metres.
    pub tile: f64,
    /// Levels of subdivision at full detail (at most [`netlimits::MAX_FRACTAL_DEPTH`]).
    pub depth: u32,
    /// Fractal dimension in [`netlimits::FRACTAL_DIMENSION`].
    pub dimension: f32,
    /// Displacement amplitude of level 1, metres.
    pub relief: f32,
    /// Control grid points per axis (x, z); `[0, 0]` without control heights.
    pub dims: [u32; 2],
    /// Control heights, `dims[0] × dims[1]` (at most [`netlimits::MAX_CONTROL_HEIGHTS`]), rows of increasing z.
    pub heights: Vec<f32>,
}

impl FractalDesc {
    /// Check counts and numbers: the depth and finest spacing, the dimension's range, finite numbers, a control
    /// grid that matches its dimensions.
    pub fn validate(&self) -> Result<(), MessageError> {
        let bad = |what| Err(MessageError::World(what));
        if self.depth > netlimits::MAX_FRACTAL_DEPTH {
            return bad("fractal depth out of range");
        }
        let spacing = self.tile / f64::from(1u32 << self.depth);
        if !(self.tile.is_finite() && spacing >= netlimits::MIN_FRACTAL_SPACING) {
            return bad("fractal tile out of range");
        }
        let (lo, hi) = netlimits::FRACTAL_DIMENSION;
        let numbers = (lo..hi).contains(&self.dimension)
            && self.relief.is_finite()
            && self.relief >= 0.0
            && self.origin.iter().all(|v| v.is_finite());
        if !numbers {
            return bad("fractal numbers out of range");
        }
        let expected = u64::from(self.dims[0]) * u64::from(self.dims[1]);
        if self.heights.len() > netlimits::MAX_CONTROL_HEIGHTS
            || expected != self.heights.len() as u64
            || (self.dims[0] == 0) != (self.dims[1] == 0)
            || !self.heights.iter().all(|h| h.is_finite())
        {
            return bad("fractal control heights do not match their grid");
        }
        Ok(())
    }
}

impl TerrainDesc {
    /// Flat ground at height 0: one tile of edge `tile_size` with its corner at `origin`, no terrain species.
    pub fn flat(origin: [f32; 2], tile_size: f32) -> TerrainDesc {
        TerrainDesc {
            graph: None,
            seed: 0,
            origin,
            tile_size,
            tiles: [1, 1],
            depth: 0,
            corners: vec![0.0; 4],
            params: Vec::new(),
            fractal: None,
        }
    }

    /// Check counts and numbers (decoders call this; the graph itself is checked when decoded).
    pub fn validate(&self) -> Result<(), MessageError> {
        let bad = |what| Err(MessageError::World(what));
        if self.graph.as_ref().is_some_and(|g| g.len() > limits::MAX_SPECIES_BYTES) {
            return bad("terrain species too large");
        }
        if self.tiles.iter().any(|&t| t == 0 || t > netlimits::MAX_TERRAIN_TILES) {
            return bad("terrain tile count out of range");
        }
        if self.depth > netlimits::MAX_TERRAIN_DEPTH {
            return bad("terrain depth out of range");
        }
        let corners = (self.tiles[0] as usize + 1) * (self.tiles[1] as usize + 1);
        if self.corners.len() != corners || !self.corners.iter().all(|h| h.is_finite()) {
            return bad("terrain corners do not match the tiles");
        }
        if self.params.len() > limits::MAX_PARAMS || !self.params.iter().all(|(_, v)| v.is_finite()) {
            return bad("terrain parameters out of range");
        }
        if !(self.tile_size.is_finite() && self.tile_size > 0.0 && self.origin.iter().all(|v| v.is_finite())) {
            return bad("terrain tile size or origin out of range");
        }
        self.fractal.as_ref().map_or(Ok(()), FractalDesc::validate)
    }
}
