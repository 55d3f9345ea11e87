//! The scene description the renderer consumes: species graphs by id, instances (species, position, seed,
//! parameters), the terrain, optionally ready-made hypertree volumes per species, and the far field beyond the
//! records (summary nodes, issue 15). No networking: `canopy walk` builds one from the client library's state,
//! `canopy render` from a world.

use std::sync::Arc;

use canopy_protocol::summary::NodeSummary;
use canopy_protocol::{CellCoord, SpeciesGraph};
use canopy_worlds::hypertree::Hypertree;
use canopy_worlds::world::{Ground, GroundCover, InstanceId, Terrain, World};

/// One tree (or bush, or weed) to draw.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneInstance {
    /// Instance id: its cell and index in the cell (stable while the instance is held; the key of its
    /// level-of-detail state).
    pub id: InstanceId,
    /// Species id: index into [`Scene::species`].
    pub species: u16,
    /// World position of the species origin (x, terrain height, z).
    pub position: [f32; 3],
    /// Instance seed.
    pub seed: u64,
    /// Parameter values that differ from the species defaults, `(slot, value)`.
    pub params: Vec<(u16, f32)>,
}

/// A ready-made far-field volume for a species: a hypertree (seed 000) and where it stands.
#[derive(Clone, Debug)]
pub struct SceneVolume {
    /// The hypertree.
    pub tree: Arc<Hypertree>,
    /// Where the species origin (an instance's position) lies in the hypervolume, box units.
    pub origin: [f32; 3],
    /// Metres per box unit.
    pub units: f32,
}

/// The far field beyond the records: summary nodes and the cells records already draw.
#[derive(Clone, Debug, Default)]
pub struct SceneFar {
    /// Summary nodes held, any order. A node is drawn where none of its children is held to replace it: a node whose
    /// four children are all held is not drawn (its children are); partially refined nodes draw their sub-squares
    /// not covered by held children.
    pub nodes: Vec<Arc<NodeSummary>>,
    /// The world's cell edge, metres.
    pub cell_size: f32,
    /// Cells whose records are held complete (sorted): summary coverage inside them is not drawn — records draw them.
    pub record_cells: Vec<CellCoord>,
    /// Changes whenever nodes or record cells change.
    pub generation: u64,
}

/// Everything drawn (see the module docs).
#[derive(Clone, Debug)]
pub struct Scene {
    /// Species graphs by id; `None` for a species not held (its instances are skipped).
    pub species: Vec<Option<Arc<SpeciesGraph>>>,
    /// Far-field volumes by species id; `None` lets the renderer voxelise the species itself on a worker thread.
    pub volumes: Vec<Option<SceneVolume>>,
    /// The instances, sorted by id (the renderer carries their level-of-detail state across generations by
    /// merging on id; an instance out of order starts afresh).
    pub instances: Vec<SceneInstance>,
    /// The ground: a height grid, or a fractal the renderer draws in a window around the viewer.
    pub ground: Ground,
    /// What covers the ground, from the world's rules: the terrain's colours (forest floor, meadow, rock, snow).
    /// `None` colours it by relative height and slope (single-tree views, a world not known yet).
    pub cover: Option<Arc<GroundCover>>,
    /// Changes whenever species or instances change (the renderer rebuilds its per-instance state then).
    pub generation: u64,
    /// The far field beyond the records: summary nodes drawn as forest (empty: nothing beyond the instances).
    pub far: SceneFar,
}

impl Scene {
    /// One instance of `graph` with `seed` at the origin, on `ground` (test scenes and single-tree views).
    pub fn lone(graph: SpeciesGraph, seed: u64, ground: Terrain) -> Scene {
        Scene {
            species: vec![Some(Arc::new(graph))],
            volumes: vec![None],
            instances: vec![SceneInstance {
                id: InstanceId(0),
                species: 0,
                position: [0.0; 3],
                seed,
                params: Vec::new(),
            }],
            ground: Arc::new(ground).into(),
            cover: None,
            generation: 1,
            far: SceneFar::default(),
        }
    }

    /// Every instance of a loaded world, sorted by id.
    pub fn from_world(world: &World) -> Scene {
        let mut instances: Vec<SceneInstance> = (0..world.instances.len() as u32)
            .map(|index| {
                let p = &world.instances[index as usize];
                let id = world.instance_id(index);
                SceneInstance {
                    id,
                    species: p.species,
                    position: world.position(index),
                    seed: world.instance_seed(id),
                    params: p.params.clone(),
                }
            })
            .collect();
        // The world's order is row-major by cell (z, then x); ids order by (x, z, index).
        instances.sort_by_key(|i| i.id);
        Scene {
            species: world.species.iter().map(|s| Some(Arc::new(s.graph.clone()))).collect(),
            volumes: vec![None; world.species.len()],
            instances,
            ground: Ground::of_world(world),
            cover: Some(Arc::new(GroundCover::of_world(world))),
            generation: 1,
            far: SceneFar::default(),
        }
    }

    /// An empty scene on a ground (a height grid `Arc<Terrain>` or a fractal `Arc<Fractal>`).
    pub fn empty(ground: impl Into<Ground>) -> Scene {
        Scene {
            species: Vec::new(),
            volumes: Vec::new(),
            instances: Vec::new(),
            ground: ground.into(),
            cover: None,
            generation: 0,
            far: SceneFar::default(),
        }
    }

    /// The graph of a species id, if held.
    pub fn graph(&self, species: u16) -> Option<&Arc<SpeciesGraph>> {
        self.species.get(usize::from(species)).and_then(|g| g.as_ref())
    }
}
