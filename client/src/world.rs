//! The client's picture of the world from the welcome: the terrain rebuilt from its description (amplified
//! locally, bit for bit as on the server), so instance heights are derived rather than sent.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

use canopy_protocol::messages::TerrainDesc;
use canopy_protocol::{SpeciesGraph, SpeciesHash};
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

/// Rebuild the terrain of a welcome. Many connections of one process share one build per description.
pub fn terrain(desc: &TerrainDesc) -> Result<Arc<Terrain>, TerrainBuildError> {
    static BUILT: OnceLock<Mutex<HashMap<SpeciesHash, Arc<Terrain>>>> = OnceLock::new();
    let key = SpeciesHash::of(&postcard::to_allocvec(desc).expect("encoding into a Vec cannot fail"));
    let built = BUILT.get_or_init(Mutex::default);
    // Holding the lock while building makes concurrent connections wait for one build instead of each doing it.
    let mut map = built.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(t) = map.get(&key) {
        return Ok(Arc::clone(t));
    }
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
    let t = Arc::new(t);
    if map.len() >= 8 {
        map.clear();
    }
    map.insert(key, Arc::clone(&t));
    Ok(t)
}
