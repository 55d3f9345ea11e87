//! The renderer proper (see the module docs of [`super`]): it drives the workers, the geometry cache
//! ([`super::cache`]) and the per-frame selection ([`super::select`]), and does everything that touches wgpu —
//! buffer writes and bind groups for the plan of each frame, the GPU arenas, the far-field atlas, and the render
//! pass.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use canopy_worlds::amplify::Instance;
use canopy_worlds::world::{Ground, GroundCover, Terrain};
use glam::Mat4;
use wgpu::util::DeviceExt;

use super::cache::{GeometryCache, INDEX_BYTES, Placement};
use super::camera::{Camera, Frustum};
use super::clock::Instant;
use super::geometry::{MeshVertex, PrimInstance, TreeGeometry};
use super::ground::FractalWindow;
use super::pipelines::{ACCUM_FORMAT, DEPTH_FORMAT, Pipelines};
use super::scene::Scene;
use super::select::{
    DRAW_SLOTS, DRAW_STRIDE, DRAW_UNIFORM_BYTES, FarInstance, FrameInputs, FramePlan, LodState, Residency, ShadowView,
    SpeciesVol, View, ViewDraws, VolState,
};
use super::terrain::TerrainMesh;
use super::volume::FarVolume;
use super::workers::{Job, JobResult, Workers};
use super::{RenderConfig, SHADOW_CASCADES};

pub use super::stats::FrameStats;

mod atlas;
mod cull;
mod far_march;
mod forest_gpu;
mod passes;
mod shadow;
pub mod timing;
mod uniforms;
use atlas::Atlas;
use cull::{CULL_VIEWS, CullView, GpuCull, Scale};
pub use cull::{CullCounts, CulledFrame};
use far_march::FarMarch;
use forest_gpu::ForestGpu;
use passes::{GeometryDraws, Msaa, ScenePass};
pub(crate) use shadow::SHADOW_FORMAT;
use shadow::{Cascade, ShadowPass};
use timing::{Part, PassTimer};
use uniforms::{Globals, VolumeInfo};

/// Initial bytes of the segment buffer and of the far-instance buffer (both grow to the next power of two).
const INITIAL_LIST_BYTES: u64 = 64 * 1024;
/// Initial bytes of the volume-info buffer (a few dozen species).
const INITIAL_VOLUME_INFO_BYTES: u64 = 4096;
/// Priority of voxelisation jobs: before any amplification (priorities are projected sizes in pixels).
const VOLUME_PRIORITY: f32 = f32::MAX;
/// Vertices of the sky's full-screen triangle.
const SKY_VERTICES: u32 = 3;
/// Vertices of a far instance's proxy box (12 triangles, no index buffer).
const PROXY_BOX_VERTICES: u32 = 36;

struct TerrainGpu {
    source: Arc<Terrain>,
    /// The cover its colours came from.
    cover: Option<Arc<GroundCover>>,
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

    /// Grow to hold `bytes` (to the next power of two; the contents are lost then).
    fn reserve(&mut self, device: &wgpu::Device, bytes: u64) {
        if bytes > self.buffer.size() {
            self.buffer = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(self.label),
                size: bytes.next_power_of_two(),
                usage: self.usage,
                mapped_at_creation: false,
            });
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

/// The device, the target's size and depth buffer, the pipelines and the frame-wide uniforms.
struct GpuCore {
    device: wgpu::Device,
    queue: wgpu::Queue,
    format: wgpu::TextureFormat,
    size: (u32, u32),
    /// One sample a pixel: the scene's depth as the far field reads it (resolved from `msaa` where there is one).
    depth: wgpu::TextureView,
    /// The multisampled scene targets, where the scene pass is multisampled ([`crate::RenderConfig::msaa`]).
    msaa: Option<Msaa>,
    p: Pipelines,
    globals: wgpu::Buffer,
    globals_bg: wgpu::BindGroup,
    accum: Accumulation,
}

/// The far field's accumulation target (far instances and forest patches composited front to back), the per-pixel
/// opacity beside it (`far_accum.wgsl`), and their bind groups; sized to the target.
struct Accumulation {
    target: wgpu::TextureView,
    opacity: wgpu::Buffer,
    opacity_bg: wgpu::BindGroup,
    composite_bg: wgpu::BindGroup,
}

impl Accumulation {
    /// For a `size` target; `raster`: whether the boxes draw the far field (only they read the opacity buffer).
    fn new(device: &wgpu::Device, p: &Pipelines, (w, h): (u32, u32), raster: bool) -> Accumulation {
        let (w, h) = (w.max(1), h.max(1));
        let usage = wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::STORAGE_BINDING;
        let target = target_view(device, "far-field accumulation", (w, h), ACCUM_FORMAT, usage);
        let opacity = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("far-field opacity"),
            size: if raster { u64::from(w) * u64::from(h) * 4 } else { 4 },
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let opacity_bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("far-field opacity"),
            layout: &p.accum_layout,
            entries: &[wgpu::BindGroupEntry { binding: 0, resource: opacity.as_entire_binding() }],
        });
        let composite_bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("far-field accumulation"),
            layout: &p.composite_layout,
            entries: &[wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(&target) }],
        });
        Accumulation { target, opacity, opacity_bg, composite_bg }
    }
}

/// The GPU side of near and mid geometry: the arenas' buffers (their bookkeeping is the [`GeometryCache`]), the
/// frame's segments and per-draw uniforms, and their bind groups.
struct GeometryGpu {
    prims: wgpu::Buffer,
    verts: wgpu::Buffer,
    indices: wgpu::Buffer,
    segments: Growable,
    draws: wgpu::Buffer,
    draw_bg: wgpu::BindGroup,
    prims_bg: Option<wgpu::BindGroup>,
    mesh_bg: Option<wgpu::BindGroup>,
}

impl GeometryGpu {
    /// Copy placed geometry into the arenas' buffers.
    fn write(&self, queue: &wgpu::Queue, geo: &TreeGeometry, at: &Placement) {
        if !geo.prims.is_empty() {
            let offset = at.prims.start * size_of::<PrimInstance>() as u64;
            queue.write_buffer(&self.prims, offset, bytemuck::cast_slice(&geo.prims));
        }
        if !geo.vertices.is_empty() {
            let offset = at.verts.start * size_of::<MeshVertex>() as u64;
            queue.write_buffer(&self.verts, offset, bytemuck::cast_slice(&geo.vertices));
        }
        if !geo.indices.is_empty() {
            queue.write_buffer(&self.indices, at.indices.start * INDEX_BYTES, bytemuck::cast_slice(&geo.indices));
        }
    }
}

/// The far field: each species' volumes, the atlas holding them, their infos, and the frame's far instances.
struct FarField {
    /// Volume state by species id (`None`: not asked for yet).
    vols: Vec<Option<VolState>>,
    /// Each species' full-resolution volume once resident (canopy tiles are baked from it).
    sources: Vec<Option<Arc<FarVolume>>>,
    atlas: Option<Atlas>,
    infos: Vec<VolumeInfo>,
    info_buf: Growable,
    bg: Option<wgpu::BindGroup>,
    instances: Growable,
}

/// The renderer (see the module docs of [`super`]).
pub struct Renderer {
    cfg: RenderConfig,
    gpu: GpuCore,
    geometry: GeometryGpu,
    far: FarField,
    /// The summary patches beyond the records.
    forest: ForestGpu,
    /// The far field's tile lists (drawn by the compute pass when `Some`).
    march: Option<FarMarch>,
    /// The GPU cull of the camera's and the shadow cascades' primitives (`Some` where it culls, [`crate::CullPath`]).
    cull: Option<GpuCull>,
    terrain: Option<TerrainGpu>,
    /// The window drawn of a fractal ground.
    window: Option<FractalWindow>,
    /// Which geometry is resident, pending, failed or waiting for upload.
    cache: GeometryCache,
    workers: Workers,
    /// Results taken from the workers and not yet handled.
    received: VecDeque<JobResult>,
    /// Every instance's level-of-detail state.
    lod: LodState,
    /// This frame's plan (kept between frames for its allocations).
    plan: FramePlan,
    frame: u64,
    last: FrameStats,
    /// GPU time per part of the frame, once asked for ([`Renderer::time_parts`]) where the device can.
    timer: Option<PassTimer>,
    /// The sun's shadow maps.
    shadow: ShadowPass,
    /// Seconds of the scene's clock (wind), [`Renderer::set_time`].
    time: f32,
}

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer").field("size", &self.gpu.size).field("frame", &self.frame).finish()
    }
}

/// A view of a new `size` 2D texture that frames render into.
fn target_view(
    device: &wgpu::Device,
    label: &str,
    (w, h): (u32, u32),
    format: wgpu::TextureFormat,
    usage: wgpu::TextureUsages,
) -> wgpu::TextureView {
    device
        .create_texture(&wgpu::TextureDescriptor {
            label: Some(label),
            size: wgpu::Extent3d { width: w.max(1), height: h.max(1), depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | usage,
            view_formats: &[],
        })
        .create_view(&wgpu::TextureViewDescriptor::default())
}

/// The depth buffer (read by the far field's march).
fn depth_view(device: &wgpu::Device, size: (u32, u32)) -> wgpu::TextureView {
    target_view(device, "depth", size, DEPTH_FORMAT, wgpu::TextureUsages::TEXTURE_BINDING)
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
        let device_type = device.adapter_info().device_type;
        let samples = cfg.samples(device_type);
        let culls = cfg.cull.on_gpu(device_type);
        let p = Pipelines::new(
            device,
            format,
            samples,
            device.features().contains(wgpu::Features::SHADER_EARLY_DEPTH_TEST),
            culls,
        );
        let (globals, globals_bg) = uniforms::globals_binding(device, &p.globals_layout, "globals");
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let prim_units = cfg.prim_memory / size_of::<PrimInstance>() as u64;
        let vert_units = cfg.vertex_memory() / size_of::<MeshVertex>() as u64;
        let index_units = cfg.index_memory() / INDEX_BYTES;
        let buf = |label: &str, bytes: u64| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage: storage,
                mapped_at_creation: false,
            })
        };
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
                    size: wgpu::BufferSize::new(DRAW_UNIFORM_BYTES as u64),
                }),
            }],
        });
        let geometry = GeometryGpu {
            prims: buf("primitive arena", prim_units * size_of::<PrimInstance>() as u64),
            verts: buf("vertex arena", vert_units * size_of::<MeshVertex>() as u64),
            indices: buf("index arena", index_units * INDEX_BYTES),
            segments: Growable::new(device, "segments", INITIAL_LIST_BYTES, wgpu::BufferUsages::STORAGE),
            draws,
            draw_bg,
            prims_bg: None,
            mesh_bg: None,
        };
        let far = FarField {
            vols: Vec::new(),
            sources: Vec::new(),
            atlas: None,
            infos: Vec::new(),
            info_buf: Growable::new(device, "volume infos", INITIAL_VOLUME_INFO_BYTES, wgpu::BufferUsages::STORAGE),
            bg: None,
            instances: Growable::new(
                device,
                "far instances",
                INITIAL_LIST_BYTES,
                wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::STORAGE,
            ),
        };
        // A browser page has no threads: amplification runs there on the page's thread, `Renderer::run_jobs`.
        #[cfg(not(target_arch = "wasm32"))]
        let workers = Workers::new(cfg.workers)?;
        #[cfg(target_arch = "wasm32")]
        let workers = Workers::inline();
        let march = cfg.far_path.computes(device.adapter_info().device_type).then(|| FarMarch::new(device));
        let shadow = ShadowPass::new(device, &p, &cfg.shadows);
        let depth = depth_view(device, size);
        let cull = culls.then(|| GpuCull::new(device, &p, &depth, size, cfg.prim_cull_px));
        Ok(Renderer {
            gpu: GpuCore {
                depth,
                msaa: (samples > 1).then(|| Msaa::new(device, &p, format, size, samples)),
                format,
                accum: Accumulation::new(device, &p, size, march.is_none()),
                device: device.clone(),
                queue: queue.clone(),
                size,
                p,
                globals,
                globals_bg,
            },
            geometry,
            far,
            forest: ForestGpu::new(device),
            shadow,
            march,
            cull,
            terrain: None,
            window: None,
            cache: GeometryCache::new(prim_units, vert_units, index_units),
            workers,
            received: VecDeque::new(),
            lod: LodState::new(&cfg.lod),
            plan: FramePlan::default(),
            frame: 0,
            last: FrameStats::default(),
            timer: None,
            time: 0.0,
            cfg,
        })
    }

    /// Time each part of every frame on the GPU from now on ([`timing::PARTS`]); false where the device lacks
    /// timestamp queries inside passes ([`timing::FEATURES`]).
    pub fn time_parts(&mut self) -> bool {
        if self.timer.is_none() {
            self.timer = PassTimer::new(&self.gpu.device, &self.gpu.queue);
        }
        self.timer.is_some()
    }

    /// Milliseconds of GPU time of each part of the last frame rendered ([`timing::PARTS`]), waiting for the GPU to
    /// finish it; `None` unless [`Renderer::time_parts`] is on and a frame was rendered since the last call.
    pub fn part_times(&mut self) -> Option<[f64; timing::PARTS.len()]> {
        self.timer.as_mut()?.read(&self.gpu.device)
    }

    /// Count what the GPU cull drops in every frame from now on; false where the GPU does not cull
    /// ([`crate::CullPath`]).
    pub fn count_culled(&mut self) -> bool {
        self.cull.as_mut().map(|c| c.count = true).is_some()
    }

    /// What the GPU cull kept and dropped of the last frame's primitives, the camera's and the shadow maps', waiting
    /// for the GPU to finish it; `None` unless [`Renderer::count_culled`] is on and a frame was culled since the last
    /// call.
    pub fn culled(&mut self) -> Option<CulledFrame> {
        self.cull.as_mut()?.read_counts(&self.gpu.device)
    }

    /// Set the scene's clock, seconds: what the wind blows by. A frame is a function of the scene, the camera and
    /// this time (the window sets it from the wall clock; stills keep 0 unless asked).
    pub fn set_time(&mut self, seconds: f32) {
        self.time = if seconds.is_finite() { seconds } else { 0.0 };
    }

    /// Switch levels at once instead of cross-fading (offscreen stills).
    pub fn set_instant_transitions(&mut self, instant: bool) {
        self.lod.instant = instant;
    }

    /// The target size changed.
    pub fn resize(&mut self, width: u32, height: u32) {
        self.gpu.size = (width.max(1), height.max(1));
        self.gpu.depth = depth_view(&self.gpu.device, self.gpu.size);
        if let Some(c) = &mut self.cull {
            c.resize(&self.gpu.device, &self.gpu.depth, self.gpu.size);
        }
        let samples = self.cfg.samples(self.gpu.device.adapter_info().device_type);
        if samples > 1 {
            self.gpu.msaa = Some(Msaa::new(&self.gpu.device, &self.gpu.p, self.gpu.format, self.gpu.size, samples));
        }
        self.gpu.accum = Accumulation::new(&self.gpu.device, &self.gpu.p, self.gpu.size, self.march.is_none());
    }

    /// Block up to `timeout` until a worker finishes something (offscreen rendering waits; the window never does).
    pub fn wait_for_workers(&mut self, timeout: Duration) {
        if let Some(r) = self.workers.recv_timeout(timeout) {
            self.received.push_back(r);
        }
    }

    /// Where there are no worker threads (wasm32): run queued amplification, voxelisation and baking jobs on this
    /// thread, most urgent first, while `more()` says so (asked before each job); how many ran. A page calls it
    /// each frame with its time budget, before [`Renderer::update`]. With worker threads it does nothing.
    pub fn run_jobs(&mut self, more: &mut dyn FnMut() -> bool) -> usize {
        self.workers.run_inline(more)
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
        self.sync_scene(scene, camera);
        self.collect();
        self.cache.expire_deferred(self.frame);
        let (gpu, geometry) = (&self.gpu, &self.geometry);
        self.cache
            .upload(self.frame, self.cfg.upload_budget, &mut stats, &mut |geo, at| geometry.write(&gpu.queue, geo, at));
        let cascades = self.cascades(camera);
        self.select(scene, camera, &cascades, dt, &mut stats);
        self.plan_forest(scene, camera, dt, &mut stats);
        self.write_globals(camera, &cascades);
        let (w, h) = self.gpu.size;
        let vp = camera.view_projection(w as f32 / h as f32, self.cfg.near_clip);
        if let Some(c) = &mut self.cull {
            let px_per_rad = h as f32 / (2.0 * camera.tan_half_fov());
            let views: [CullView<'_>; CULL_VIEWS] = std::array::from_fn(|k| match k {
                0 => CullView {
                    draws: &self.plan.camera,
                    frustum: Frustum::from_matrix(vp),
                    scale: Scale::Perspective { eye: camera.position, px_per_rad },
                    occlusion: true,
                },
                k => CullView {
                    draws: &self.plan.cascades[k - 1],
                    frustum: Frustum::from_matrix(cascades[k - 1].view_proj),
                    scale: Scale::Orthographic { px_per_metre: 1.0 / cascades[k - 1].texel },
                    occlusion: false,
                },
            });
            c.plan(&self.gpu, views);
        }
        if self.march.is_some() {
            self.bin_far_field(&vp);
        }
        stats.instances = scene.instances.len();
        stats.cache_entries = self.cache.len();
        stats.cache_bytes = self.cache.bytes_used();
        stats.cache_capacity = self.geometry.prims.size() + self.geometry.verts.size() + self.geometry.indices.size();
        stats.volumes = self.far.vols.iter().filter(|v| matches!(v, Some(VolState::Ready(_)))).count();
        stats.jobs = self.workers.outstanding() + self.received.len();
        stats.uploads_waiting = self.cache.uploads_waiting();
        stats.failed = self.cache.failed();
        stats.update_ms = started.elapsed().as_secs_f64() * 1e3;
        self.last = stats.clone();
        stats
    }

    /// The height grid to draw: the scene's grid, or the window of its fractal around the camera (re-centred and
    /// re-leveled as the camera moves: a new `Arc` then).
    fn ground_grid(&mut self, scene: &Scene, camera: &Camera) -> Arc<Terrain> {
        match &scene.ground {
            Ground::Grid(t) => {
                self.window = None;
                Arc::clone(t)
            }
            Ground::Fractal(f) => match &mut self.window {
                Some(w) if Arc::ptr_eq(w.fractal(), f) => {
                    w.update(camera.position);
                    Arc::clone(w.terrain())
                }
                _ => {
                    let w = FractalWindow::new(Arc::clone(f), self.cfg.ground_window, camera.position);
                    let t = Arc::clone(w.terrain());
                    self.window = Some(w);
                    t
                }
            },
        }
    }

    fn sync_scene(&mut self, scene: &Scene, camera: &Camera) {
        let grid = self.ground_grid(scene, camera);
        let cover_ptr = |c: &Option<Arc<GroundCover>>| c.as_ref().map(Arc::as_ptr);
        let terrain_changed = match &self.terrain {
            Some(t) => !Arc::ptr_eq(&t.source, &grid) || cover_ptr(&t.cover) != cover_ptr(&scene.cover),
            None => true,
        };
        if terrain_changed {
            let mesh = TerrainMesh::build(&grid, scene.cover.as_deref());
            let vertices = self.gpu.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("terrain vertices"),
                contents: bytemuck::cast_slice(&mesh.vertices),
                usage: wgpu::BufferUsages::VERTEX,
            });
            let indices = self.gpu.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("terrain indices"),
                contents: bytemuck::cast_slice(&mesh.indices),
                usage: wgpu::BufferUsages::INDEX,
            });
            self.terrain = Some(TerrainGpu { source: grid, cover: scene.cover.clone(), mesh, vertices, indices });
        }
        self.lod.sync(scene.generation, &scene.instances);
        let vols = &mut self.far.vols;
        if vols.len() < scene.species.len() {
            vols.resize(scene.species.len(), None);
        }
        for (id, graph) in scene.species.iter().enumerate() {
            let (Some(graph), None) = (graph, &vols[id]) else { continue };
            self.workers.submit(
                Job::Volume {
                    species: id as u16,
                    graph: Arc::clone(graph),
                    given: scene.volumes.get(id).cloned().flatten(),
                    resolution: self.cfg.volume_resolution,
                    budget: self.cfg.amplify_budget,
                    lighting: self.cfg.lighting.clone(),
                },
                VOLUME_PRIORITY,
            );
            vols[id] = Some(VolState::Pending);
        }
    }

    fn collect(&mut self) {
        while let Some(r) = self.workers.try_recv() {
            self.received.push_back(r);
        }
        while let Some(r) = self.received.pop_front() {
            match r {
                JobResult::Tree { key, result, .. } => self.cache.finished(key, result),
                JobResult::Volume { species, result, took } => {
                    let state = match result {
                        Ok(v) => {
                            tracing::debug!("species {species}: far-field volumes in {took:?}");
                            // Canopy tiles are baked from the halved resolution: what the far band draws at
                            // the sizes summaries are seen at.
                            let source = Arc::new(v.low);
                            let full = self.add_volume(Arc::new(v.full));
                            let sources = &mut self.far.sources;
                            if sources.len() <= usize::from(species) {
                                sources.resize(usize::from(species) + 1, None);
                            }
                            sources[usize::from(species)] = Some(Arc::clone(&source));
                            let coarser = v.coarser.len() as u32;
                            let lower = self.add_lower_volumes(source, v.coarser);
                            match (full, lower) {
                                (Some((full, center, radius)), Some(low)) => {
                                    // Full, halved, then the coarser ones after the halved (the coarsest repeated).
                                    let levels = std::array::from_fn(|k| match k {
                                        0 => full,
                                        k => low + (k as u32 - 1).min(coarser),
                                    });
                                    VolState::Ready(SpeciesVol { levels, center, radius, height: v.height })
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
                    if let Some(slot) = self.far.vols.get_mut(usize::from(species)) {
                        *slot = Some(state);
                    }
                }
                JobResult::Tile { species, result, took } => self.tile_finished(species, result.map(|t| *t), took),
            }
        }
    }

    /// Plan the frame ([`FramePlan::plan`]), submit its jobs, mark what it draws as used, and write its lists.
    fn select(
        &mut self,
        scene: &Scene,
        camera: &Camera,
        cascades: &[Cascade; SHADOW_CASCADES],
        dt: f32,
        stats: &mut FrameStats,
    ) {
        let mut view = View::new(camera, self.gpu.size, self.cfg.near_clip, &self.cfg.lod, dt, self.lod.instant);
        view.shadows = (self.cfg.shadows.resolution > 0).then(|| ShadowView {
            sun: self.cfg.lighting.sun(),
            reach: self.cfg.shadows.distance,
            cascades: cascades.map(|c| Frustum::from_matrix(c.view_proj)),
        });
        let room = self.cfg.max_jobs.saturating_sub(self.workers.outstanding() + self.cache.uploads_waiting());
        let input = FrameInputs {
            scene,
            residency: Residency { cache: &self.cache, volumes: &self.far.vols },
            lod: &self.cfg.lod,
            view,
            terrain: self.terrain.as_ref().map(|t| &t.mesh),
            job_room: room,
        };
        self.plan.plan(&input, &mut self.lod, stats);
        for j in &self.plan.jobs {
            let si = &scene.instances[j.instance];
            let Some(graph) = scene.graph(si.species) else { continue };
            if !self.cache.mark_pending(j.key) {
                continue;
            }
            let instance = Instance { seed: si.seed, params: si.params.clone(), detail: j.key.detail };
            let job = Job::Tree {
                key: j.key,
                graph: Arc::clone(graph),
                instance,
                mode: self.cfg.near_mode,
                budget: self.cfg.amplify_budget,
            };
            self.workers.submit(job, j.priority);
        }
        for g in &self.plan.geo_draws {
            self.cache.touch(g.key, self.frame);
        }
        let (gpu, geo, far) = (&self.gpu, &mut self.geometry, &mut self.far);
        gpu.queue.write_buffer(&geo.draws, 0, &self.plan.uniforms);
        let grew = geo.segments.write(&gpu.device, &gpu.queue, bytemuck::cast_slice(&self.plan.segments));
        if grew || geo.prims_bg.is_none() {
            geo.prims_bg = Some(gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("prims"),
                layout: &gpu.p.prims_layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: geo.segments.buffer.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: geo.prims.as_entire_binding() },
                ],
            }));
            geo.mesh_bg = Some(gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("meshes"),
                layout: &gpu.p.mesh_layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: geo.segments.buffer.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: geo.verts.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 2, resource: geo.indices.as_entire_binding() },
                ],
            }));
        }
        if !self.plan.far_sorted.is_empty() {
            far.instances.write(&gpu.device, &gpu.queue, bytemuck::cast_slice(&self.plan.far_sorted));
        }
    }

    /// Prepare a frame with nothing but the sky and whatever terrain is loaded (before any scene arrives).
    pub fn update_view(&mut self, camera: &Camera) {
        self.plan.clear();
        self.forest.clear();
        if let Some(c) = &mut self.cull {
            c.skip();
        }
        let cascades = self.cascades(camera);
        self.write_globals(camera, &cascades);
    }

    /// The sun's shadow cascades for `camera` (fitted once a frame: the selection plans their draws, the globals
    /// carry their matrices).
    fn cascades(&self, camera: &Camera) -> [Cascade; SHADOW_CASCADES] {
        let (w, h) = self.gpu.size;
        let aspect = w as f32 / h as f32;
        shadow::fit_cascades(camera, aspect, self.cfg.near_clip, self.cfg.lighting.sun(), &self.cfg.shadows)
    }

    fn write_globals(&mut self, camera: &Camera, cascades: &[Cascade; SHADOW_CASCADES]) {
        let (w, h) = self.gpu.size;
        let aspect = w as f32 / h as f32;
        let vp: Mat4 = camera.view_projection(aspect, self.cfg.near_clip);
        let l = &self.cfg.lighting;
        let sun = l.sun();
        let wind = &self.cfg.wind;
        let wind_dir = glam::Vec2::from(wind.direction).normalize_or(glam::Vec2::X);
        let mut g = Globals {
            view_proj: vp.to_cols_array_2d(),
            inv_view_proj: vp.inverse().to_cols_array_2d(),
            eye: camera.position.extend(0.0).to_array(),
            sun_dir: sun.extend(l.ambient).to_array(),
            sun_color: [l.sun_color[0], l.sun_color[1], l.sun_color[2], l.diffuse],
            sky_zenith: [l.sky_zenith[0], l.sky_zenith[1], l.sky_zenith[2], l.fog_density],
            sky_horizon: [l.sky_horizon[0], l.sky_horizon[1], l.sky_horizon[2], l.sky_light],
            viewport: [w as f32, h as f32, 1.0 / w as f32, 1.0 / h as f32],
            wind: [wind_dir.x, wind_dir.y, wind.strength, self.time],
            shadow_split: [0.0; 4],
            shadow_texel: [0.0; 4],
            haze: [l.haze_height, l.sun_glow, l.crown_occlusion, 0.0],
            shadow: [[[0.0; 4]; 4]; SHADOW_CASCADES],
        };
        self.shadow.write(&self.gpu.queue, &mut g, cascades);
        self.gpu.queue.write_buffer(&self.gpu.globals, 0, bytemuck::bytes_of(&g));
    }

    /// Encode and submit the frame prepared by [`Renderer::update`] into `view` (render): the scene pass (sky,
    /// terrain, near and mid geometry), then, where there is a far field, its instances and forest patches front to
    /// back into the accumulation target — by the compute pass over screen tiles, or as boxes whose fragments stop
    /// behind an opaque pixel ([`crate::FarPath`]) — and that laid over the scene.
    pub fn render(&mut self, view: &wgpu::TextureView) -> wgpu::SubmissionIndex {
        let far_count = self.plan.far_count();
        // Both ways need the volumes' bind group (there are far instances or patches only once a volume is resident)
        // and the forest's (made by the first frame's plan).
        let far_field = (far_count > 0 || !self.forest.patches().is_empty())
            && self.far.bg.is_some()
            && self.forest.bind_group().is_some();
        let gpu = &self.gpu;
        let timer = self.timer.as_ref();
        let mut enc = gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        if let Some(t) = timer {
            t.start(&mut enc);
        }
        let view_draws =
            |draws, culled| GeometryDraws { draws, geometry: &self.geometry, terrain: self.terrain.as_ref(), culled };
        let culled = match &self.cull {
            Some(c) => c.encode(gpu, &view_draws(&self.plan.camera, None), &mut enc),
            None => std::array::from_fn(|_| None),
        };
        if let Some(t) = timer {
            t.done_between(&mut enc, Part::Cull);
        }
        let cascades: [GeometryDraws<'_>; SHADOW_CASCADES] =
            std::array::from_fn(|k| view_draws(&self.plan.cascades[k], culled[1 + k].as_ref()));
        self.shadow.encode(&mut enc, &gpu.p, &cascades);
        if let Some(t) = timer {
            t.done_between(&mut enc, Part::Shadows);
        }
        let scene = ScenePass {
            gpu,
            target: view,
            draws: view_draws(&self.plan.camera, culled[0].as_ref()),
            shadows: self.shadow.receive(),
            sky: self.cfg.lighting.sky_horizon,
            keep_depth: far_field,
        };
        scene.encode(&mut enc, timer);
        if far_field {
            passes::resolve_depth(gpu, &mut enc);
            match &self.march {
                Some(march) => {
                    self.march_far_field(march, &mut enc);
                    if let Some(t) = timer {
                        t.done_between(&mut enc, Part::FarField);
                    }
                }
                None => self.raster_far_field(&mut enc, far_count),
            }
            passes::composite(gpu, view, &mut enc, timer);
        }
        drop(culled);
        if let Some(c) = &mut self.cull {
            c.encoded();
        }
        if let Some(t) = &mut self.timer {
            t.resolve(&mut enc);
        }
        self.gpu.queue.submit([enc.finish()])
    }
}
