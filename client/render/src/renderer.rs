//! The renderer proper (see the module docs of [`super`]): per-frame LOD selection, the geometry cache in GPU
//! arenas, the far-field atlas, and the render pass.

use std::collections::{BTreeSet, HashMap, HashSet, VecDeque};
use std::ops::Range;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytemuck::{Pod, Zeroable};
use canopy_worlds::amplify::Instance;
use canopy_worlds::world::Terrain;
use glam::{Mat4, Vec3};
use wgpu::util::DeviceExt;

use super::RenderConfig;
use super::arena::Arena;
use super::camera::{Camera, Frustum};
use super::geometry::{MeshVertex, PrimInstance, TreeGeometry};
use super::lod::{Band, InstanceLod, Level, projected_size};
use super::pipelines::{ATLAS_FORMAT, DEPTH_FORMAT, Pipelines};
use super::scene::Scene;
use super::terrain::TerrainMesh;
use super::volume::{FarVolume, instance_scale};
use super::workers::{Job, JobResult, TreeKey, Workers};

/// What a frame did: the counts per band, the cache, the workers (for overlays, logs and tests).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameStats {
    /// Instances in the scene.
    pub instances: usize,
    /// Instances in the view frustum and above the cull size.
    pub in_view: usize,
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
    /// CPU time of [`Renderer::update`], milliseconds.
    pub update_ms: f64,
}

impl FrameStats {
    /// Whether nothing in view waits for a worker or an upload.
    pub fn settled(&self) -> bool {
        self.waiting == 0 && self.uploads_waiting == 0
    }
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Globals {
    view_proj: [[f32; 4]; 4],
    inv_view_proj: [[f32; 4]; 4],
    eye: [f32; 4],
    sun_dir: [f32; 4],
    sun_color: [f32; 4],
    sky_zenith: [f32; 4],
    sky_horizon: [f32; 4],
    viewport: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct Segment {
    first: u32,
    base: u32,
    vbase: u32,
    count: u32,
    pos: [f32; 3],
    mask: f32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct DrawUniform {
    seg_first: u32,
    seg_count: u32,
    kind: u32,
    pad: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct FarInstance {
    pos_scale: [f32; 4],
    volume: u32,
    mask: f32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct VolumeInfo {
    atlas: [u32; 4],
    dims: [u32; 4],
    voxel: [f32; 4],
    lo: [f32; 4],
    hi: [f32; 4],
    origin: [f32; 4],
}

/// Frames before geometry that did not fit the cache is asked for again.
const DEFER_FRAMES: u64 = 120;

/// Alignment of per-draw uniforms (the WebGPU minimum for dynamic offsets).
const DRAW_STRIDE: u64 = 256;
/// Draw slots: 3 unit shapes × 4 tessellations + meshes.
const DRAW_SLOTS: u64 = 16;

struct CacheEntry {
    prims: Range<u64>,
    shape_ranges: [Range<u32>; 3],
    verts: Range<u64>,
    indices: Range<u64>,
    last_used: u64,
}

#[derive(Clone, Copy, Debug)]
struct SpeciesVol {
    full: u32,
    low: u32,
    center: Vec3,
    radius: f32,
    height: Option<(u16, f32)>,
}

#[derive(Clone, Copy, Debug)]
enum VolState {
    Pending,
    Ready(SpeciesVol),
    Failed,
}

#[derive(Clone, Copy, Debug, Default)]
struct InstState {
    id: u32,
    lod: InstanceLod,
    target: Option<Level>,
    scale: Option<f32>,
}

struct Atlas {
    texture: wgpu::Texture,
    slot: u32,
    per_row: u32,
    rows: u32,
    used: u32,
    /// CPU copies of every volume, to re-upload when the atlas grows.
    volumes: Vec<(u32, Arc<FarVolume>)>,
}

struct TerrainGpu {
    source: Arc<Terrain>,
    mesh: TerrainMesh,
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
}

/// Grow-only GPU buffer.
struct Growable {
    buffer: wgpu::Buffer,
    usage: wgpu::BufferUsages,
    label: &'static str,
}

impl Growable {
    fn new(device: &wgpu::Device, label: &'static str, size: u64, usage: wgpu::BufferUsages) -> Growable {
        let usage = usage | wgpu::BufferUsages::COPY_DST;
        Growable {
            buffer: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            }),
            usage,
            label,
        }
    }

    /// Write `data`, growing to the next power of two if needed; true when the buffer was replaced.
    fn write(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, data: &[u8]) -> bool {
        let mut grew = false;
        if data.len() as u64 > self.buffer.size() {
            let size = (data.len() as u64).next_power_of_two();
            self.buffer = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(self.label),
                size,
                usage: self.usage,
                mapped_at_creation: false,
            });
            grew = true;
        }
        if !data.is_empty() {
            queue.write_buffer(&self.buffer, 0, data);
        }
        grew
    }
}

/// One draw of the frame.
#[derive(Clone, Copy, Debug)]
struct PrimDraw {
    shape: usize,
    tess: usize,
    slot: u32,
    instances: u32,
}

/// The working lists of [`Renderer::update`]'s selection, kept between frames so that a frame allocates only when
/// one of them grows.
#[derive(Default)]
struct Scratch {
    /// Geometry to draw: key, position, dither mask.
    geo_draws: Vec<(TreeKey, [f32; 3], f32)>,
    /// Far instances with their distance.
    far: Vec<(f32, FarInstance)>,
    /// Far instances back to front, as uploaded.
    far_sorted: Vec<FarInstance>,
    /// Geometry to ask the workers for: projected size, instance index, detail.
    requests: Vec<(f32, usize, u8)>,
    /// Segments per (unit shape, tessellation).
    lists: [[Vec<Segment>; 4]; 3],
    /// Mesh segments.
    meshes: Vec<Segment>,
    /// Every segment of the frame, as uploaded.
    all: Vec<Segment>,
    /// The per-draw uniforms, as uploaded.
    uniforms: Vec<u8>,
}

/// The renderer (see the module docs of [`super`]).
pub struct Renderer {
    cfg: RenderConfig,
    device: wgpu::Device,
    queue: wgpu::Queue,
    size: (u32, u32),
    depth: wgpu::TextureView,
    p: Pipelines,
    globals: wgpu::Buffer,
    globals_bg: wgpu::BindGroup,
    prim_buf: wgpu::Buffer,
    prim_arena: Arena,
    vert_buf: wgpu::Buffer,
    vert_arena: Arena,
    index_buf: wgpu::Buffer,
    index_arena: Arena,
    segments: Growable,
    draws: wgpu::Buffer,
    draw_bg: wgpu::BindGroup,
    prims_bg: Option<wgpu::BindGroup>,
    mesh_bg: Option<wgpu::BindGroup>,
    far_buf: Growable,
    volume_infos: Vec<VolumeInfo>,
    volume_buf: Growable,
    volume_bg: Option<wgpu::BindGroup>,
    atlas: Option<Atlas>,
    terrain: Option<TerrainGpu>,
    workers: Workers,
    received: VecDeque<JobResult>,
    cache: HashMap<TreeKey, CacheEntry>,
    lru: BTreeSet<(u64, TreeKey)>,
    pending: HashSet<TreeKey>,
    /// Keys whose geometry did not fit the cache, by the frame they were given up; retried after
    /// [`DEFER_FRAMES`].
    deferred: HashMap<TreeKey, u64>,
    failed: HashSet<TreeKey>,
    uploads: VecDeque<(TreeKey, TreeGeometry)>,
    vols: Vec<Option<VolState>>,
    inst: Vec<InstState>,
    /// The previous scene generation's states while they are carried over (kept for its allocation).
    inst_spare: Vec<InstState>,
    generation: Option<u64>,
    /// Every level an instance can show, finest first (for cross-fades).
    levels: Vec<Level>,
    scratch: Scratch,
    frame: u64,
    instant: bool,
    // This frame's draw lists.
    prim_draws: Vec<PrimDraw>,
    mesh_draw: Option<(u32, u32)>,
    far_count: u32,
    terrain_draws: Vec<Range<u32>>,
    last: FrameStats,
}

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer").field("size", &self.size).field("frame", &self.frame).finish()
    }
}

fn depth_view(device: &wgpu::Device, (w, h): (u32, u32)) -> wgpu::TextureView {
    device
        .create_texture(&wgpu::TextureDescriptor {
            label: Some("depth"),
            size: wgpu::Extent3d { width: w.max(1), height: h.max(1), depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DEPTH_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        })
        .create_view(&wgpu::TextureViewDescriptor::default())
}

fn tess(detail: u8) -> usize {
    usize::from(detail).min(3)
}

impl Renderer {
    /// Create a renderer drawing into targets of `format` and `size` (init). `cfg` must be validated.
    pub fn new(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        format: wgpu::TextureFormat,
        size: (u32, u32),
        cfg: RenderConfig,
    ) -> std::io::Result<Renderer> {
        let p = Pipelines::new(device, format);
        let globals = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("globals"),
            size: size_of::<Globals>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let globals_bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("globals"),
            layout: &p.globals_layout,
            entries: &[wgpu::BindGroupEntry { binding: 0, resource: globals.as_entire_binding() }],
        });
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let prim_units = cfg.prim_memory / size_of::<PrimInstance>() as u64;
        let vert_units = cfg.vertex_memory() / size_of::<MeshVertex>() as u64;
        let index_units = cfg.index_memory() / 4;
        let buf = |label: &str, bytes: u64| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage: storage,
                mapped_at_creation: false,
            })
        };
        let prim_buf = buf("primitive arena", prim_units * size_of::<PrimInstance>() as u64);
        let vert_buf = buf("vertex arena", vert_units * size_of::<MeshVertex>() as u64);
        let index_buf = buf("index arena", index_units * 4);
        let draws = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("draws"),
            size: DRAW_STRIDE * DRAW_SLOTS,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let draw_bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("draw"),
            layout: &p.draw_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &draws,
                    offset: 0,
                    size: wgpu::BufferSize::new(16),
                }),
            }],
        });
        let workers = Workers::new(cfg.workers)?;
        Ok(Renderer {
            depth: depth_view(device, size),
            device: device.clone(),
            queue: queue.clone(),
            size,
            p,
            globals,
            globals_bg,
            prim_buf,
            prim_arena: Arena::new(prim_units),
            vert_buf,
            vert_arena: Arena::new(vert_units),
            index_buf,
            index_arena: Arena::new(index_units),
            segments: Growable::new(device, "segments", 64 * 1024, wgpu::BufferUsages::STORAGE),
            draws,
            draw_bg,
            prims_bg: None,
            mesh_bg: None,
            far_buf: Growable::new(device, "far instances", 64 * 1024, wgpu::BufferUsages::VERTEX),
            volume_infos: Vec::new(),
            volume_buf: Growable::new(device, "volume infos", 4096, wgpu::BufferUsages::STORAGE),
            volume_bg: None,
            atlas: None,
            terrain: None,
            workers,
            received: VecDeque::new(),
            cache: HashMap::new(),
            lru: BTreeSet::new(),
            pending: HashSet::new(),
            deferred: HashMap::new(),
            failed: HashSet::new(),
            uploads: VecDeque::new(),
            vols: Vec::new(),
            inst: Vec::new(),
            inst_spare: Vec::new(),
            generation: None,
            levels: (0..=cfg.lod.mid_levels).map(Level::Detail).chain([Level::Far]).collect(),
            scratch: Scratch::default(),
            frame: 0,
            instant: false,
            prim_draws: Vec::new(),
            mesh_draw: None,
            far_count: 0,
            terrain_draws: Vec::new(),
            last: FrameStats::default(),
            cfg,
        })
    }

    /// Switch levels at once instead of cross-fading (offscreen stills).
    pub fn set_instant_transitions(&mut self, instant: bool) {
        self.instant = instant;
    }

    /// The target size changed.
    pub fn resize(&mut self, width: u32, height: u32) {
        self.size = (width.max(1), height.max(1));
        self.depth = depth_view(&self.device, self.size);
    }

    /// Block up to `timeout` until a worker finishes something (offscreen rendering waits; the window never does).
    pub fn wait_for_workers(&mut self, timeout: Duration) {
        if let Some(r) = self.workers.recv_timeout(timeout) {
            self.received.push_back(r);
        }
    }

    /// The statistics of the last update.
    pub fn stats(&self) -> &FrameStats {
        &self.last
    }

    /// Prepare a frame: take finished work, upload within budget, choose levels, build the draw lists (update).
    /// `dt` is the time since the previous frame, seconds (it drives cross-fades).
    pub fn update(&mut self, scene: &Scene, camera: &Camera, dt: f32) -> FrameStats {
        let started = Instant::now();
        self.frame += 1;
        let mut stats = FrameStats::default();
        self.sync_scene(scene);
        self.collect();
        let frame = self.frame;
        self.deferred.retain(|_, at| *at + DEFER_FRAMES > frame);
        self.upload(&mut stats);
        self.select(scene, camera, dt, &mut stats);
        self.write_globals(camera);
        stats.instances = scene.instances.len();
        stats.cache_entries = self.cache.len();
        stats.cache_bytes = self.prim_arena.used() * size_of::<PrimInstance>() as u64
            + self.vert_arena.used() * size_of::<MeshVertex>() as u64
            + self.index_arena.used() * 4;
        stats.cache_capacity = self.prim_buf.size() + self.vert_buf.size() + self.index_buf.size();
        stats.volumes = self.vols.iter().filter(|v| matches!(v, Some(VolState::Ready(_)))).count();
        stats.jobs = self.workers.outstanding() + self.received.len();
        stats.uploads_waiting = self.uploads.len();
        stats.failed = self.failed.len();
        stats.update_ms = started.elapsed().as_secs_f64() * 1e3;
        self.last = stats.clone();
        stats
    }

    fn sync_scene(&mut self, scene: &Scene) {
        let terrain_changed = match &self.terrain {
            Some(t) => !Arc::ptr_eq(&t.source, &scene.terrain),
            None => true,
        };
        if terrain_changed {
            let mesh = TerrainMesh::build(&scene.terrain);
            let vertices = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("terrain vertices"),
                contents: bytemuck::cast_slice(&mesh.vertices),
                usage: wgpu::BufferUsages::VERTEX,
            });
            let indices = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("terrain indices"),
                contents: bytemuck::cast_slice(&mesh.indices),
                usage: wgpu::BufferUsages::INDEX,
            });
            self.terrain = Some(TerrainGpu { source: Arc::clone(&scene.terrain), mesh, vertices, indices });
        }
        if self.generation != Some(scene.generation) || self.inst.len() != scene.instances.len() {
            // Carry states over by id: both lists are sorted by id, so one merge pass (an instance the old list
            // does not have starts afresh).
            let mut old = std::mem::replace(&mut self.inst, std::mem::take(&mut self.inst_spare));
            self.inst.clear();
            let mut j = 0;
            for i in &scene.instances {
                while old.get(j).is_some_and(|s| s.id < i.id) {
                    j += 1;
                }
                self.inst.push(match old.get(j) {
                    Some(s) if s.id == i.id => *s,
                    _ => InstState { id: i.id, ..InstState::default() },
                });
            }
            old.clear();
            self.inst_spare = old;
            self.generation = Some(scene.generation);
        }
        if self.vols.len() < scene.species.len() {
            self.vols.resize(scene.species.len(), None);
        }
        for (id, graph) in scene.species.iter().enumerate() {
            let (Some(graph), None) = (graph, &self.vols[id]) else { continue };
            self.workers.submit(
                Job::Volume {
                    species: id as u16,
                    graph: Arc::clone(graph),
                    given: scene.volumes.get(id).cloned().flatten(),
                    resolution: self.cfg.volume_resolution,
                    budget: self.cfg.amplify_budget,
                    lighting: self.cfg.lighting.clone(),
                },
                f32::MAX,
            );
            self.vols[id] = Some(VolState::Pending);
        }
    }

    fn collect(&mut self) {
        while let Some(r) = self.workers.try_recv() {
            self.received.push_back(r);
        }
        while let Some(r) = self.received.pop_front() {
            match r {
                JobResult::Tree { key, result, .. } => {
                    // A key stays pending until its geometry is uploaded (or given up), so it is not asked for
                    // twice.
                    match result {
                        Ok(geo) if !geo.is_empty() => self.uploads.push_back((key, geo)),
                        Ok(_) => {
                            self.pending.remove(&key);
                            self.failed.insert(key);
                        }
                        Err(e) => {
                            self.pending.remove(&key);
                            tracing::warn!("species {} seed {:#x} detail {}: {e}", key.species, key.seed, key.detail);
                            self.failed.insert(key);
                        }
                    }
                }
                JobResult::Volume { species, result, took } => {
                    let state = match result {
                        Ok(v) => {
                            tracing::debug!("species {species}: far-field volumes in {took:?}");
                            let full = self.add_volume(Arc::new(v.full));
                            let low = self.add_volume(Arc::new(v.low));
                            match (full, low) {
                                (Some((full, center, radius)), Some((low, _, _))) => {
                                    VolState::Ready(SpeciesVol { full, low, center, radius, height: v.height })
                                }
                                _ => {
                                    tracing::warn!("species {species}: the far-field atlas is full");
                                    VolState::Failed
                                }
                            }
                        }
                        Err(e) => {
                            tracing::warn!("species {species}: no far-field volume: {e}");
                            VolState::Failed
                        }
                    };
                    if let Some(slot) = self.vols.get_mut(usize::from(species)) {
                        *slot = Some(state);
                    }
                }
            }
        }
    }

    /// Place a volume in the atlas (growing it if needed); returns its index and bounding sphere.
    fn add_volume(&mut self, v: Arc<FarVolume>) -> Option<(u32, Vec3, f32)> {
        let slot_edge = self.cfg.volume_resolution.next_power_of_two();
        let max3d = self.device.limits().max_texture_dimension_3d;
        if v.dims.iter().any(|&d| d > slot_edge) || slot_edge > max3d {
            return None;
        }
        let per_row = (max3d / slot_edge).clamp(1, 8);
        let max_rows = (max3d / slot_edge).max(1);
        let full = self.atlas.as_ref().is_some_and(|a| a.used >= a.per_row * a.rows);
        if full && self.atlas.as_ref().is_some_and(|a| a.rows * 2 > max_rows) {
            return None;
        }
        if self.atlas.is_none() || full {
            let (rows, old) = match self.atlas.take() {
                None => (1, Vec::new()),
                Some(a) => (a.rows * 2, a.volumes),
            };
            self.atlas = Some(self.make_atlas(slot_edge, per_row, rows, old));
        }
        let atlas = self.atlas.as_mut()?;
        let index = atlas.used;
        atlas.used += 1;
        atlas.volumes.push((index, Arc::clone(&v)));
        let origin = Self::write_volume(&self.queue, atlas, index, &v);
        let info = VolumeInfo {
            atlas: [origin[0], origin[1], origin[2], 0],
            dims: [v.dims[0], v.dims[1], v.dims[2], 0],
            voxel: [
                v.voxel_size[0],
                v.voxel_size[1],
                v.voxel_size[2],
                v.voxel_size[0].min(v.voxel_size[1]).min(v.voxel_size[2]),
            ],
            lo: [v.aabb_min[0], v.aabb_min[1], v.aabb_min[2], v.units],
            hi: [v.aabb_max[0], v.aabb_max[1], v.aabb_max[2], 0.0],
            origin: [v.origin[0], v.origin[1], v.origin[2], 0.0],
        };
        let id = self.volume_infos.len() as u32;
        self.volume_infos.push(info);
        self.volume_buf.write(&self.device, &self.queue, bytemuck::cast_slice(&self.volume_infos));
        self.rebuild_volume_bg();
        let (c, r) = v.bounding_sphere();
        Some((id, Vec3::from(c), r))
    }

    fn make_atlas(&self, slot: u32, per_row: u32, rows: u32, volumes: Vec<(u32, Arc<FarVolume>)>) -> Atlas {
        let texture = self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("far-field atlas"),
            size: wgpu::Extent3d { width: slot * per_row, height: slot, depth_or_array_layers: slot * rows },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D3,
            format: ATLAS_FORMAT,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let mut atlas = Atlas { texture, slot, per_row, rows, used: volumes.len() as u32, volumes };
        for (index, v) in atlas.volumes.clone() {
            Self::write_volume(&self.queue, &mut atlas, index, &v);
        }
        atlas
    }

    fn write_volume(queue: &wgpu::Queue, atlas: &mut Atlas, index: u32, v: &FarVolume) -> [u32; 3] {
        let origin = [(index % atlas.per_row) * atlas.slot, 0, (index / atlas.per_row) * atlas.slot];
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &atlas.texture,
                mip_level: 0,
                origin: wgpu::Origin3d { x: origin[0], y: origin[1], z: origin[2] },
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(&v.texels),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(v.dims[0] * 8),
                rows_per_image: Some(v.dims[1]),
            },
            wgpu::Extent3d { width: v.dims[0], height: v.dims[1], depth_or_array_layers: v.dims[2] },
        );
        origin
    }

    fn rebuild_volume_bg(&mut self) {
        let Some(atlas) = &self.atlas else { return };
        let view = atlas.texture.create_view(&wgpu::TextureViewDescriptor::default());
        self.volume_bg = Some(self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("volumes"),
            layout: &self.p.volume_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(&view) },
                wgpu::BindGroupEntry { binding: 1, resource: self.volume_buf.buffer.as_entire_binding() },
            ],
        }));
    }

    fn evict_one(&mut self) -> bool {
        let Some(&(last, key)) = self.lru.iter().next() else { return false };
        // Never evict what the previous frame drew: this frame most likely draws it again.
        if last + 1 >= self.frame {
            return false;
        }
        self.lru.remove(&(last, key));
        if let Some(e) = self.cache.remove(&key) {
            self.prim_arena.free(e.prims);
            self.vert_arena.free(e.verts);
            self.index_arena.free(e.indices);
        }
        true
    }

    fn upload(&mut self, stats: &mut FrameStats) {
        while let Some((key, geo)) = self.uploads.front() {
            let bytes = geo.gpu_bytes();
            if stats.uploaded_bytes > 0 && stats.uploaded_bytes + bytes > self.cfg.upload_budget {
                break;
            }
            let need = (geo.prims.len() as u64, geo.vertices.len() as u64, geo.indices.len() as u64);
            if need.0 > self.prim_arena.capacity()
                || need.1 > self.vert_arena.capacity()
                || need.2 > self.index_arena.capacity()
            {
                tracing::warn!("species {} seed {:#x}: geometry larger than the cache", key.species, key.seed);
                let key = *key;
                self.pending.remove(&key);
                self.failed.insert(key);
                self.uploads.pop_front();
                continue;
            }
            let ranges = loop {
                let p = self.prim_arena.alloc(need.0);
                let v = p.as_ref().and_then(|_| self.vert_arena.alloc(need.1));
                let i = v.as_ref().and_then(|_| self.index_arena.alloc(need.2));
                match (p, v, i) {
                    (Some(p), Some(v), Some(i)) => break Some((p, v, i)),
                    (p, v, _) => {
                        if let Some(p) = p {
                            self.prim_arena.free(p);
                        }
                        if let Some(v) = v {
                            self.vert_arena.free(v);
                        }
                        if !self.evict_one() {
                            break None;
                        }
                        stats.evicted += 1;
                    }
                }
            };
            let Some((pr, vr, ir)) = ranges else {
                // The cache is full of what the last frames drew: this instance keeps its stand-in for a while
                // (and asks again later), and smaller geometry behind it may still fit.
                let (key, _) = self.uploads.pop_front().expect("front exists");
                self.pending.remove(&key);
                self.deferred.insert(key, self.frame);
                stats.deferred += 1;
                if stats.deferred >= 8 {
                    break;
                }
                continue;
            };
            let (key, geo) = self.uploads.pop_front().expect("front exists");
            self.pending.remove(&key);
            if !geo.prims.is_empty() {
                self.queue.write_buffer(&self.prim_buf, pr.start * 64, bytemuck::cast_slice(&geo.prims));
            }
            if !geo.vertices.is_empty() {
                self.queue.write_buffer(&self.vert_buf, vr.start * 20, bytemuck::cast_slice(&geo.vertices));
            }
            if !geo.indices.is_empty() {
                self.queue.write_buffer(&self.index_buf, ir.start * 4, bytemuck::cast_slice(&geo.indices));
            }
            stats.uploaded_bytes += bytes;
            // A stale duplicate (requested again after an eviction) replaces the old entry.
            if let Some(old) = self.cache.remove(&key) {
                self.lru.remove(&(old.last_used, key));
                self.prim_arena.free(old.prims);
                self.vert_arena.free(old.verts);
                self.index_arena.free(old.indices);
            }
            self.lru.insert((self.frame, key));
            self.cache.insert(
                key,
                CacheEntry {
                    prims: pr,
                    shape_ranges: geo.shape_ranges.clone(),
                    verts: vr,
                    indices: ir,
                    last_used: self.frame,
                },
            );
        }
    }

    fn select(&mut self, scene: &Scene, camera: &Camera, dt: f32, stats: &mut FrameStats) {
        let (w, h) = self.size;
        let aspect = w as f32 / h as f32;
        let vp = camera.view_projection(aspect, self.cfg.near_clip);
        let frustum = Frustum::from_matrix(vp);
        let eye = camera.position;
        let tan_half = camera.tan_half_fov();
        let height_px = h as f32;
        let lod = &self.cfg.lod;
        let progress = if self.instant || lod.fade_seconds <= 0.0 { 1.0 } else { (dt / lod.fade_seconds).max(0.0) };
        let mut s = std::mem::take(&mut self.scratch);
        s.geo_draws.clear();
        s.far.clear();
        s.requests.clear();
        {
            let Renderer { inst, vols, cache, pending, failed, deferred, levels, .. } = self;
            let unavailable = |k: &TreeKey| failed.contains(k) || deferred.contains_key(k);
            for (idx, (si, st)) in scene.instances.iter().zip(inst.iter_mut()).enumerate() {
                let Some(graph) = scene.graph(si.species) else { continue };
                let vs = match vols.get(usize::from(si.species)).copied().flatten() {
                    Some(VolState::Ready(v)) => Some(v),
                    _ => None,
                };
                let scale = match (st.scale, vs) {
                    (Some(s), _) => s,
                    (None, Some(v)) => *st.scale.insert(instance_scale(graph, v.height, si.seed, &si.params)),
                    (None, None) => 1.0,
                };
                let (c_off, radius) = match vs {
                    Some(v) => (v.center * scale, v.radius * scale),
                    None => (Vec3::new(0.0, 6.0, 0.0) * scale, 8.0 * scale),
                };
                let pos = Vec3::from(si.position);
                let center = pos + c_off;
                if !frustum.sphere_visible(center, radius) {
                    continue;
                }
                let dist = (center - eye).length();
                let size = projected_size(radius, dist, tan_half, height_px);
                if size < lod.cull_px {
                    continue;
                }
                stats.in_view += 1;
                let key = |d: u8| TreeKey { species: si.species, seed: si.seed, detail: d };
                let mut wanted = lod.select(st.target, size);
                st.target = Some(wanted);
                if let Level::Detail(d) = wanted
                    && unavailable(&key(d))
                {
                    wanted = Level::Far;
                }
                let ready = |l: Level| match l {
                    Level::Detail(d) => cache.contains_key(&key(d)),
                    Level::Far => vs.is_some(),
                };
                if !ready(wanted) {
                    match wanted {
                        Level::Detail(d) => {
                            let k = key(d);
                            if !pending.contains(&k) {
                                s.requests.push((size, idx, d));
                            }
                            stats.waiting += 1;
                        }
                        Level::Far => {
                            if matches!(vols.get(usize::from(si.species)), Some(Some(VolState::Pending))) {
                                stats.waiting += 1;
                            }
                        }
                    }
                }
                st.lod.step(wanted, progress, &ready, levels);
                match st.lod.shown.map(Level::band) {
                    Some(Band::Near) => stats.near += 1,
                    Some(Band::Mid) => stats.mid += 1,
                    Some(Band::Far) => stats.far += 1,
                    None => stats.hidden += 1,
                }
                for d in st.lod.draws() {
                    match d.level {
                        Level::Detail(det) => s.geo_draws.push((key(det), si.position, d.mask)),
                        Level::Far => {
                            if let Some(v) = vs {
                                let volume = if size < lod.low_res_px { v.low } else { v.full };
                                let fi = FarInstance {
                                    pos_scale: [si.position[0], si.position[1], si.position[2], scale],
                                    volume,
                                    mask: d.mask,
                                };
                                s.far.push((dist, fi));
                            }
                        }
                    }
                }
            }
        }
        // Requests, biggest on screen first, within the job bound.
        s.requests.sort_by(|a, b| b.0.total_cmp(&a.0));
        for &(size, idx, d) in &s.requests {
            if self.workers.outstanding() + self.uploads.len() >= self.cfg.max_jobs {
                break;
            }
            let si = &scene.instances[idx];
            let Some(graph) = scene.graph(si.species) else { continue };
            let key = TreeKey { species: si.species, seed: si.seed, detail: d };
            if !self.pending.insert(key) {
                continue;
            }
            let instance = Instance { seed: si.seed, params: si.params.clone(), detail: d };
            self.workers.submit(
                Job::Tree {
                    key,
                    graph: Arc::clone(graph),
                    instance,
                    mode: self.cfg.near_mode,
                    budget: self.cfg.amplify_budget,
                },
                size,
            );
        }
        // Geometry draw lists: one per (unit shape, tessellation), one for meshes.
        s.lists.iter_mut().flatten().for_each(Vec::clear);
        s.meshes.clear();
        for &(key, pos, mask) in &s.geo_draws {
            let Some(e) = self.cache.get_mut(&key) else { continue };
            if e.last_used != self.frame {
                self.lru.remove(&(e.last_used, key));
                self.lru.insert((self.frame, key));
                e.last_used = self.frame;
            }
            for (k, r) in e.shape_ranges.iter().enumerate() {
                if r.is_empty() {
                    continue;
                }
                s.lists[k][tess(key.detail)].push(Segment {
                    first: 0,
                    base: (e.prims.start + u64::from(r.start)) as u32,
                    vbase: 0,
                    count: r.len() as u32,
                    pos,
                    mask,
                });
            }
            if !e.indices.is_empty() {
                s.meshes.push(Segment {
                    first: 0,
                    base: e.indices.start as u32,
                    vbase: e.verts.start as u32,
                    count: (e.indices.end - e.indices.start) as u32,
                    pos,
                    mask,
                });
            }
        }
        s.all.clear();
        s.uniforms.clear();
        s.uniforms.resize((DRAW_STRIDE * DRAW_SLOTS) as usize, 0);
        let mut slot = 0u32;
        self.prim_draws.clear();
        let put = |u: DrawUniform, slot: u32, uniforms: &mut Vec<u8>| {
            let at = (u64::from(slot) * DRAW_STRIDE) as usize;
            uniforms[at..at + 16].copy_from_slice(bytemuck::bytes_of(&u));
        };
        let append = |list: &mut Vec<Segment>, all: &mut Vec<Segment>| -> (u32, u32, u32) {
            let first = all.len() as u32;
            let mut total = 0u32;
            for s in list.iter_mut() {
                s.first = total;
                total += s.count;
            }
            all.extend_from_slice(list);
            (first, list.len() as u32, total)
        };
        for (shape, per_tess) in s.lists.iter_mut().enumerate() {
            for (t, list) in per_tess.iter_mut().enumerate() {
                if list.is_empty() {
                    continue;
                }
                let (first, count, total) = append(list, &mut s.all);
                put(
                    DrawUniform { seg_first: first, seg_count: count, kind: shape as u32, pad: 0 },
                    slot,
                    &mut s.uniforms,
                );
                self.prim_draws.push(PrimDraw { shape, tess: t, slot, instances: total });
                stats.primitives += u64::from(total);
                slot += 1;
            }
        }
        self.mesh_draw = if s.meshes.is_empty() {
            None
        } else {
            let (first, count, total) = append(&mut s.meshes, &mut s.all);
            put(DrawUniform { seg_first: first, seg_count: count, kind: 0, pad: 0 }, slot, &mut s.uniforms);
            stats.mesh_triangles = u64::from(total / 3);
            Some((slot, total))
        };
        self.queue.write_buffer(&self.draws, 0, &s.uniforms);
        if s.all.is_empty() {
            s.all.push(Segment::zeroed());
        }
        let grew = self.segments.write(&self.device, &self.queue, bytemuck::cast_slice(&s.all));
        if grew || self.prims_bg.is_none() {
            self.prims_bg = Some(self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("prims"),
                layout: &self.p.prims_layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: self.segments.buffer.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: self.prim_buf.as_entire_binding() },
                ],
            }));
            self.mesh_bg = Some(self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("meshes"),
                layout: &self.p.mesh_layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: self.segments.buffer.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: self.vert_buf.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 2, resource: self.index_buf.as_entire_binding() },
                ],
            }));
        }
        // Far instances back to front.
        s.far.sort_unstable_by(|a, b| b.0.total_cmp(&a.0));
        s.far_sorted.clear();
        s.far_sorted.extend(s.far.iter().map(|&(_, f)| f));
        self.far_count = s.far_sorted.len() as u32;
        if !s.far_sorted.is_empty() {
            self.far_buf.write(&self.device, &self.queue, bytemuck::cast_slice(&s.far_sorted));
        }
        self.scratch = s;
        // Terrain chunks.
        self.terrain_draws.clear();
        if let Some(t) = &self.terrain {
            let px_per_m = height_px / (2.0 * tan_half);
            for c in &t.mesh.chunks {
                if !frustum.sphere_visible(c.center, c.radius) {
                    continue;
                }
                let d = ((c.center - eye).length() - c.radius).max(1.0);
                let level = t.mesh.level_for(d, px_per_m, 12.0);
                let r = c.levels[level].clone();
                stats.terrain_triangles += u64::from(r.end - r.start) / 3;
                self.terrain_draws.push(r);
            }
        }
        stats.draw_calls = 1
            + self.terrain_draws.len() as u32
            + self.prim_draws.len() as u32
            + u32::from(self.mesh_draw.is_some())
            + u32::from(self.far_count > 0);
    }

    /// Prepare a frame with nothing but the sky and whatever terrain is loaded (before any scene arrives).
    pub fn update_view(&mut self, camera: &Camera) {
        self.prim_draws.clear();
        self.mesh_draw = None;
        self.far_count = 0;
        self.terrain_draws.clear();
        self.write_globals(camera);
    }

    fn write_globals(&self, camera: &Camera) {
        let (w, h) = self.size;
        let vp: Mat4 = camera.view_projection(w as f32 / h as f32, self.cfg.near_clip);
        let l = &self.cfg.lighting;
        let sun = Vec3::from(l.sun_direction).normalize_or(Vec3::Y);
        let g = Globals {
            view_proj: vp.to_cols_array_2d(),
            inv_view_proj: vp.inverse().to_cols_array_2d(),
            eye: camera.position.extend(0.0).to_array(),
            sun_dir: sun.extend(l.ambient).to_array(),
            sun_color: [l.sun_color[0], l.sun_color[1], l.sun_color[2], l.diffuse],
            sky_zenith: [l.sky_zenith[0], l.sky_zenith[1], l.sky_zenith[2], l.fog_density],
            sky_horizon: [l.sky_horizon[0], l.sky_horizon[1], l.sky_horizon[2], 0.0],
            viewport: [w as f32, h as f32, 1.0 / w as f32, 1.0 / h as f32],
        };
        self.queue.write_buffer(&self.globals, 0, bytemuck::bytes_of(&g));
    }

    /// Encode and submit the frame prepared by [`Renderer::update`] into `view` (render).
    pub fn render(&mut self, view: &wgpu::TextureView) -> wgpu::SubmissionIndex {
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        {
            let hz = self.cfg.lighting.sky_horizon;
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("scene"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color {
                            r: hz[0].into(),
                            g: hz[1].into(),
                            b: hz[2].into(),
                            a: 1.0,
                        }),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &self.depth,
                    depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0.0), store: wgpu::StoreOp::Discard }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_bind_group(0, &self.globals_bg, &[]);
            pass.set_pipeline(&self.p.sky);
            pass.draw(0..3, 0..1);
            if let Some(t) = &self.terrain {
                pass.set_pipeline(&self.p.terrain);
                pass.set_vertex_buffer(0, t.vertices.slice(..));
                pass.set_index_buffer(t.indices.slice(..), wgpu::IndexFormat::Uint32);
                for r in &self.terrain_draws {
                    pass.draw_indexed(r.clone(), 0, 0..1);
                }
            }
            if let (false, Some(bg)) = (self.prim_draws.is_empty(), &self.prims_bg) {
                pass.set_pipeline(&self.p.prims);
                pass.set_bind_group(1, bg, &[]);
                for d in &self.prim_draws {
                    let mesh = match d.shape {
                        0 => &self.p.frusta[d.tess],
                        1 => &self.p.spheres[d.tess],
                        _ => &self.p.cube,
                    };
                    pass.set_bind_group(2, &self.draw_bg, &[(u64::from(d.slot) * DRAW_STRIDE) as u32]);
                    pass.set_vertex_buffer(0, mesh.vertices.slice(..));
                    pass.set_index_buffer(mesh.indices.slice(..), wgpu::IndexFormat::Uint16);
                    pass.draw_indexed(0..mesh.index_count, 0, 0..d.instances);
                }
            }
            if let (Some((slot, count)), Some(bg)) = (self.mesh_draw, &self.mesh_bg) {
                pass.set_pipeline(&self.p.mesh);
                pass.set_bind_group(1, bg, &[]);
                pass.set_bind_group(2, &self.draw_bg, &[(u64::from(slot) * DRAW_STRIDE) as u32]);
                pass.draw(0..count, 0..1);
            }
            if let (true, Some(bg)) = (self.far_count > 0, &self.volume_bg) {
                pass.set_pipeline(&self.p.volume);
                pass.set_bind_group(1, bg, &[]);
                pass.set_vertex_buffer(0, self.far_buf.buffer.slice(..u64::from(self.far_count) * 24));
                pass.draw(0..36, 0..self.far_count);
            }
        }
        self.queue.submit([enc.finish()])
    }
}
