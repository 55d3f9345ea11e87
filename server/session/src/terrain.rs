//! The terrain description sent in the welcome, from which clients rebuild the terrain and compute heights: a
//! terrain species and its tiling, or a fractal's numbers (the terrain as a function: no height grid is sent).

use canopy_protocol::messages::TerrainDesc;
use canopy_worlds::world::{Fractal, Terrain, World};

/// Describe the world's ground for the welcome: its fractal when it has one, else its terrain species' encoding and
/// tiling.
pub fn terrain_desc(world: &World) -> TerrainDesc {
    TerrainDesc { fractal: world.fractal.as_ref().map(Fractal::describe), ..describe_terrain(&world.terrain) }
}

/// A terrain species' encoding and tiling (no fractal).
fn describe_terrain(terrain: &Terrain) -> TerrainDesc {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fractal_world_is_described_by_its_numbers_and_a_grid_world_by_its_species() {
        let world = World::embedded("highlands").expect("embedded");
        let desc = terrain_desc(&world);
        desc.validate().expect("a valid description");
        let f = desc.fractal.as_ref().expect("the highlands' fractal");
        let rows: Vec<Vec<f32>> = f.heights.chunks(f.dims[0] as usize).map(<[f32]>::to_vec).collect();
        let rebuilt = Fractal::new(f.seed, f.origin, f.tile, f.depth, f.dimension, f.relief, &rows).expect("valid");
        assert_eq!(Some(&rebuilt), world.fractal.as_ref());
        let forest = World::default_world();
        let desc = terrain_desc(&forest);
        assert!(desc.fractal.is_none());
        assert!(desc.graph.is_some());
    }
}
