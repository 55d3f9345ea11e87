//! What a frame did ([`FrameStats`]): the counts per band, the geometry cache and the workers, filled in by the
//! selection, the cache and the renderer (for overlays, logs and tests).

/// What a frame did: the counts per band, the cache, the workers (for overlays, logs and tests).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameStats {
    /// Instances in the scene.
    pub instances: usize,
    /// Instances in the view frustum and above the cull size.
    pub in_view: usize,
    /// Trees out of view drawn for the shadows they cast into it.
    pub shadow_casters: usize,
    /// Primitives drawn into the shadow maps, every cascade's summed.
    pub shadow_primitives: u64,
    /// Instances drawn at full detail.
    pub near: usize,
    /// Instances drawn with LOD substitutes.
    pub mid: usize,
    /// Instances drawn as hypertree volumes.
    pub far: usize,
    /// Instances in view whose wanted level is still being made or uploaded.
    pub waiting: usize,
    /// Instances in view with nothing to draw yet.
    pub hidden: usize,
    /// Primitive instances drawn.
    pub primitives: u64,
    /// Mesh triangles drawn (leaves, trunk bases, merged meshes).
    pub mesh_triangles: u64,
    /// Terrain triangles drawn.
    pub terrain_triangles: u64,
    /// Draw calls.
    pub draw_calls: u32,
    /// Geometry cache entries (species, seed, detail).
    pub cache_entries: usize,
    /// Bytes of the geometry arenas in use.
    pub cache_bytes: u64,
    /// Bytes of the geometry arenas in all (the cache's bound).
    pub cache_capacity: u64,
    /// Species whose far-field volumes are resident.
    pub volumes: usize,
    /// Jobs queued or running on the workers.
    pub jobs: usize,
    /// Finished geometry waiting for upload budget.
    pub uploads_waiting: usize,
    /// Bytes uploaded this frame.
    pub uploaded_bytes: u64,
    /// Cache entries evicted this frame.
    pub evicted: usize,
    /// Cache keys that failed to amplify (drawn far instead).
    pub failed: usize,
    /// Geometry given up this frame because the cache was full of what is in view (drawn at a stand-in level).
    pub deferred: usize,
    /// Summary nodes in the scene's far field.
    pub summary_nodes: usize,
    /// Summary nodes drawn (in view, above the cull size, with a species to draw).
    pub forest_nodes: usize,
    /// Forest patch instances drawn (one per node, species and fading part).
    pub forest_patches: usize,
    /// Sub-squares those patches march (their covered sub-squares and the neighbours their stands thin into).
    pub forest_squares: u64,
    /// Trees' worth of forest the drawn nodes stand for: each species' count times the share of its covered
    /// sub-squares drawn.
    pub forest_trees: f64,
    /// Summary nodes whose ground, and (node, species) pairs whose canopy tile, are still being made.
    pub forest_waiting: usize,
    /// CPU time of [`Renderer::update`](super::Renderer::update), milliseconds.
    pub update_ms: f64,
}

impl FrameStats {
    /// Whether the frame drew everything in view at its wanted level: nothing in view waits for a worker or an
    /// upload, no job is queued or running, and the far field's ground and tiles are made.
    pub fn settled(&self) -> bool {
        self.waiting == 0 && self.uploads_waiting == 0 && self.forest_waiting == 0 && self.jobs == 0
    }
}
