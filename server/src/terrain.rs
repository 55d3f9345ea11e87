//! The terrain description sent in the welcome, from which clients rebuild the terrain and compute heights: a
//! terrain species and its tiling, or a fractal's numbers (the terrain as a function: no height grid is sent).

use canopy_protocol::messages::{FractalDesc, TerrainDesc};
use canopy_worlds::world::{Fractal, Terrain, World};

/// Describe the world's ground for the welcome: its fractal when it has one, else its terrain species' encoding and
/// tiling.
pub fn describe(world: &World) -> TerrainDesc {
    TerrainDesc { fractal: world.fractal.as_ref().map(describe_fractal), ..describe_terrain(&world.terrain) }
}

/// A terrain species' encoding and tiling (no fractal).
pub fn describe_terrain(terrain: &Terrain) -> TerrainDesc {
    TerrainDesc {
        graph: terrain.species.as_ref().map(|g| g.encode()),
        seed: terrain.seed,
        origin: terrain.origin,
        tile_size: terrain.tile_size,
        tiles: terrain.tiles,
        depth: terrain.depth,
        corners: terrain.corners.clone(),
        params: terrain.params.clone(),
        fractal: None,
    }
}

/// A fractal's numbers.
pub fn describe_fractal(f: &Fractal) -> FractalDesc {
    FractalDesc {
        seed: f.seed,
        origin: f.origin,
        tile: f.tile,
        depth: f.depth,
        dimension: f.dimension,
        relief: f.relief,
        dims: f.dims,
        heights: f.corners.clone(),
    }
}
