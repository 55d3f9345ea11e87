//! The terrain description sent in the welcome, from which clients rebuild the terrain and compute heights.

use canopy_protocol::messages::TerrainDesc;
use canopy_worlds::world::Terrain;

/// Describe the world's terrain for the welcome: its species' encoding and its tiling.
pub fn describe(terrain: &Terrain) -> TerrainDesc {
    TerrainDesc {
        graph: terrain.species.as_ref().map(|g| g.encode()),
        seed: terrain.seed,
        origin: terrain.origin,
        tile_size: terrain.tile_size,
        tiles: terrain.tiles,
        depth: terrain.depth,
        corners: terrain.corners.clone(),
        params: terrain.params.clone(),
    }
}
