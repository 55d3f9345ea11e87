//! The client's picture of the world from the welcome: the terrain rebuilt from its description (amplified
//! locally, bit for bit as on the server), so instance heights are derived rather than sent.

use std::sync::Arc;

use canopy_protocol::SpeciesGraph;
use canopy_protocol::messages::TerrainDesc;
use canopy_worlds::world::Terrain;

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
}

/// Rebuild the terrain of a welcome (once per session).
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
