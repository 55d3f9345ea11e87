//! The client's picture of the world from the welcome: the ground rebuilt from its description — a terrain species
//! amplified locally, or a fractal's numbers turned back into the [`Fractal`] — bit for bit as on the server, so
//! instance heights are derived rather than sent.

use std::sync::Arc;

use canopy_protocol::SpeciesGraph;
use canopy_protocol::messages::{FractalDesc, TerrainDesc};
use canopy_worlds::world::{Fractal, FractalError, Ground, Terrain};

/// Why the terrain could not be rebuilt.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TerrainBuildError {
    /// The terrain species does not decode.
    #[error("terrain species: {0}")]
    Graph(#[from] canopy_protocol::DecodeError),
    /// The description does not pass the protocol's checks.
    #[error("terrain description: {0}")]
    Description(#[from] canopy_protocol::MessageError),
    /// Amplifying the tiles failed.
    #[error("terrain: {0}")]
    Build(String),
    /// The fractal's numbers are refused.
    #[error("{0}")]
    Fractal(#[from] FractalError),
}

/// Rebuild the ground of a welcome (once per session): the fractal when the description has one, else the terrain
/// grid.
pub fn ground(desc: &TerrainDesc) -> Result<Ground, TerrainBuildError> {
    desc.validate()?;
    match &desc.fractal {
        Some(f) => Ok(Ground::Fractal(Arc::new(fractal(f)?))),
        None => Ok(Ground::Grid(terrain(desc)?)),
    }
}

/// The fractal of a description (checked by [`Fractal::new`], whose bounds are the protocol's).
pub fn fractal(desc: &FractalDesc) -> Result<Fractal, TerrainBuildError> {
    desc.validate()?;
    let rows: Vec<Vec<f32>> = match desc.dims[0] {
        0 => Vec::new(),
        w => desc.heights.chunks(w as usize).map(<[f32]>::to_vec).collect(),
    };
    Ok(Fractal::new(desc.seed, desc.origin, desc.tile, desc.depth, desc.dimension, desc.relief, &rows)?)
}

/// Rebuild the terrain grid of a welcome (a flat placeholder when its ground is a fractal: see [`ground`]).
pub fn terrain(desc: &TerrainDesc) -> Result<Arc<Terrain>, TerrainBuildError> {
    desc.validate()?;
    let t = match &desc.graph {
        None => Terrain::flat(desc.origin, desc.tile_size * desc.tiles[0].max(desc.tiles[1]) as f32),
        Some(bytes) => {
            let graph = SpeciesGraph::decode(bytes)?;
            Terrain::build(
                graph,
                "welcome".into(),
                desc.seed,
                desc.origin,
                desc.tile_size,
                desc.tiles,
                desc.depth,
                desc.corners.clone(),
                desc.params.clone(),
            )
            .map_err(|e| TerrainBuildError::Build(e.to_string()))?
        }
    };
    Ok(Arc::new(t))
}

#[cfg(test)]
mod tests {
    use canopy_protocol::messages::{ServerHandshake, Welcome};
    use canopy_protocol::{ServerMsg, netlimits};
    use canopy_worlds::world::World;

    use super::*;

    /// The welcome's description of a world's fractal, as `canopy_session::terrain_desc` writes it, sent through
    /// the wire's encoder and decoder.
    fn over_the_wire(world: &World) -> TerrainDesc {
        let fractal = world.fractal.as_ref().expect("a fractal world").describe();
        let desc = TerrainDesc { fractal: Some(fractal), ..TerrainDesc::flat([0.0, 0.0], 1.0) };
        let grid = canopy_protocol::aoi::Grid {
            origin: [0.0, 0.0],
            cell_size: world.cell_size,
            min: canopy_protocol::CellCoord::new(-4, -4),
            max: canopy_protocol::CellCoord::new(3, 3),
        };
        let welcome = Welcome {
            version: canopy_protocol::PROTOCOL_VERSION,
            world: canopy_protocol::messages::WorldInfo {
                name: world.name.clone(),
                seed: world.seed,
                grid,
                position_steps: canopy_protocol::POSITION_STEPS,
                instances: 0,
                terrain: desc,
                function: None,
            },
            species: Vec::new(),
            aoi: canopy_protocol::aoi::AoiParams::default(),
        };
        let bytes = ServerMsg::Handshake(ServerHandshake::Welcome(welcome)).encode();
        assert!(bytes.len() < netlimits::MAX_SERVER_FRAME);
        match ServerMsg::decode(&bytes) {
            Ok(ServerMsg::Handshake(ServerHandshake::Welcome(w))) => w.world.terrain,
            other => panic!("not a welcome: {other:?}"),
        }
    }

    #[test]
    fn highlands_heights_from_the_welcome_equal_the_servers_bit_for_bit() {
        let world = World::embedded("highlands").expect("embedded");
        let ground = ground(&over_the_wire(&world)).expect("rebuilt");
        assert!(matches!(ground, Ground::Fractal(_)));
        let mut rng = canopy_protocol::xorshift::XorShift64::new(0x4849);
        let mut unit = || (rng.next() >> 11) as f64 / (1u64 << 53) as f64;
        let mut checked = 0;
        // In the world, and far beyond it (the function is defined everywhere).
        for extent in [51_200.0, 51_200.0, 2.0e6] {
            for _ in 0..500 {
                let x = ((unit() * 2.0 - 1.0) * extent) as f32;
                let z = ((unit() * 2.0 - 1.0) * extent) as f32;
                let (a, b) = (ground.height_and_slope(x, z), world.height_and_slope(x, z));
                assert_eq!((a.0.to_bits(), a.1.to_bits()), (b.0.to_bits(), b.1.to_bits()), "at ({x}, {z})");
                assert_eq!(ground.height(x, z).to_bits(), world.height(x, z).to_bits());
                checked += 1;
            }
        }
        assert_eq!(checked, 1500);
    }

    #[test]
    fn a_bad_fractal_is_refused() {
        let world = World::embedded("highlands").expect("embedded");
        let mut desc = over_the_wire(&world);
        desc.fractal.as_mut().expect("fractal").dimension = 3.5;
        assert!(matches!(ground(&desc), Err(TerrainBuildError::Description(_))));
        let mut desc = over_the_wire(&world);
        desc.fractal.as_mut().expect("fractal").relief = -2.0;
        assert!(ground(&desc).is_err());
    }
}
