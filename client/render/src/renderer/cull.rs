//! The GPU cull of near and mid primitives (`shaders/cull.wgsl`, `shaders/hiz.wgsl`), for the camera and each sun
//! shadow cascade: the selection culls whole trees on the CPU; here each of their primitives is tested on its own,
//! against the view's frustum (a cascade's: its box), the smallest size drawn
//! ([`crate::RenderConfig::prim_cull_px`], pixels for the camera, shadow-map texels for a cascade) and, for the
//! camera, an occlusion pyramid of the terrain's depth; the kept ones are listed for indirect draws
//! ([`CullPath`](crate::CullPath)).
//!
//! Inputs: each view's primitive draws ([`ViewDraws`]), the camera's terrain chunks, the segments and the primitive
//! arena, the frame's globals. Passes: the terrain drawn depth-only from the camera into the depth buffer, the
//! pyramid built from it, then for each view `cs_cull`, `cs_scan`, `cs_compact`. Outputs: each view's visible list
//! and indirect arguments ([`Culled`]) the scene and shadow passes draw the primitives with (`prims.wgsl`
//! `vs_prim_culled`).
//!
//! The pyramid is the terrain's depth of this frame, not the last frame's scene: nothing lags the camera, and a frame
//! stays a function of the scene, the camera and the time. Trees do not occlude each other here (canopies are not
//! solid); hills, ridges and the ground do. The depth is taken at pixel centres, so a primitive behind a ridge's
//! silhouette may lose a multisample sliver there.

use bytemuck::{Pod, Zeroable};
use wgpu::util::DeviceExt;

use super::passes::GeometryDraws;
use super::{GpuCore, Growable, INITIAL_LIST_BYTES, Pipelines, ViewDraws};
use crate::SHADOW_CASCADES;
use crate::camera::Frustum;
use crate::pipelines::PRIMS_PARTS;
use crate::select::{TESSELLATIONS, UNIT_SHAPES};

/// Primitives a workgroup of `cs_cull` and `cs_compact` tests (a block; `cull.wgsl` `BLOCK`).
const BLOCK: u32 = 256;
/// Bytes of one draw's drawIndexedIndirect arguments (five words).
pub(super) const ARGS_BYTES: u64 = 20;
/// Views culled: the camera, then each shadow cascade.
pub(super) const CULL_VIEWS: usize = 1 + SHADOW_CASCADES;
/// A view's primitive draws at most: one per unit shape and tessellation.
const MAX_DRAWS: usize = UNIT_SHAPES * TESSELLATIONS;
/// Workgroups along a row of a dispatch (WebGPU's least limit per dimension).
const DISPATCH_ROW: u32 = 65_535;
/// Bytes between the pyramid levels' uniforms (the WebGPU minimum for dynamic offsets).
const LEVEL_STRIDE: u64 = 256;

/// One primitive draw as the cull reads it (`cull.wgsl` `CullDraw`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(super) struct CullDraw {
    pub seg_first: u32,
    pub seg_count: u32,
    pub instances: u32,
    pub block_first: u32,
    pub visible_base: u32,
    pub index_count: u32,
    pub kind: u32,
    pub pad: u32,
}

/// The frame's cull parameters (`cull.wgsl` `CullParams`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(super) struct CullParams {
    pub planes: [[f32; 4]; 5],
    pub eye: [f32; 4],
    pub limits: [f32; 4],
    pub counts: [u32; 4],
    pub pyramid_size: [u32; 4],
}

/// What the cull counted over a view's primitives (where asked for: [`super::Renderer::count_culled`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CullCounts {
    /// Primitives tested: every primitive of the view's draws.
    pub tested: u64,
    /// Dropped outside the view frustum.
    pub outside: u64,
    /// Dropped below the smallest size drawn.
    pub small: u64,
    /// Dropped behind the terrain (the camera only).
    pub occluded: u64,
}

/// What the cull counted over a frame: the camera's view, and the shadow cascades' together.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CulledFrame {
    /// The camera's primitives.
    pub camera: CullCounts,
    /// The primitives drawn into the shadow maps, every cascade's summed.
    pub shadows: CullCounts,
}

/// How a view's size test measures a primitive on screen.
#[derive(Clone, Copy, Debug)]
pub(super) enum Scale {
    /// A perspective view from `eye`, `px_per_rad` pixels a radian.
    Perspective { eye: glam::Vec3, px_per_rad: f32 },
    /// A shadow cascade's orthographic view, `px_per_metre` texels a metre.
    Orthographic { px_per_metre: f32 },
}

/// One view to cull: its draws, its frustum, how sizes are measured, and whether the pyramid is tested.
pub(super) struct CullView<'a> {
    pub draws: &'a ViewDraws,
    pub frustum: Frustum,
    pub scale: Scale,
    pub occlusion: bool,
}

impl CullCounts {
    /// Primitives drawn.
    pub fn kept(&self) -> u64 {
        self.tested - self.outside - self.small - self.occluded
    }
}

/// What a pass draws a view's culled primitives with: its group 1 (segments, arena, visible list) and the indirect
/// arguments, five words a draw in the order of the view's [`ViewDraws::prims`].
pub(super) struct Culled<'a> {
    pub bg: wgpu::BindGroup,
    pub args: &'a wgpu::Buffer,
}

/// One level of the occlusion pyramid as `hiz.wgsl` reads it (`Level`): where its source and it lie, their sizes.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub(super) struct HizLevel {
    pub src_offset: u32,
    pub src_w: u32,
    pub src_h: u32,
    pub dst_offset: u32,
    pub dst_w: u32,
    pub dst_h: u32,
    pub pad: [u32; 2],
}

/// The occlusion pyramid (`hiz.wgsl`): its levels one after another in a buffer, each level's uniform in a slot of
/// its own, and the bind group that builds them (the depth buffer, the pyramid, a level's slot).
struct Pyramid {
    base: (u32, u32),
    levels: Vec<HizLevel>,
    buffer: wgpu::Buffer,
    bg: wgpu::BindGroup,
}

/// This frame's cull, once planned.
struct CullFrame {
    blocks: u32,
    /// Bytes of the visible list used.
    kept_bytes: u64,
}

/// One view's lists, arguments, parameters and counters, and its plan for this frame.
struct ViewCull {
    kept: Growable,
    blocks: Growable,
    draws: Growable,
    args: wgpu::Buffer,
    params: wgpu::Buffer,
    counters: wgpu::Buffer,
    counters_read: wgpu::Buffer,
    frame: Option<CullFrame>,
}

impl ViewCull {
    fn new(device: &wgpu::Device) -> ViewCull {
        let storage = wgpu::BufferUsages::STORAGE;
        let buffer = |label, size, usage| {
            device.create_buffer(&wgpu::BufferDescriptor { label: Some(label), size, usage, mapped_at_creation: false })
        };
        let counter_bytes = size_of::<[u32; 4]>() as u64;
        ViewCull {
            kept: Growable::new(device, "visible primitives", INITIAL_LIST_BYTES, storage),
            blocks: Growable::new(device, "cull blocks", INITIAL_LIST_BYTES, storage),
            draws: Growable::new(device, "cull draws", (MAX_DRAWS * size_of::<CullDraw>()) as u64, storage),
            args: buffer(
                "indirect primitive draws",
                MAX_DRAWS as u64 * ARGS_BYTES,
                wgpu::BufferUsages::INDIRECT | storage,
            ),
            params: buffer(
                "cull parameters",
                size_of::<CullParams>() as u64,
                wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            ),
            counters: buffer(
                "cull counters",
                counter_bytes,
                storage | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
            ),
            counters_read: buffer(
                "cull counters read",
                counter_bytes,
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            ),
            frame: None,
        }
    }

    /// Plan the view's cull: its draws' table and parameters written (`params` less the counts), its lists grown to
    /// fit. Nothing is culled (the draws are drawn whole) where there are no primitives, or more than a storage
    /// binding holds.
    fn plan(&mut self, gpu: &GpuCore, draws: &ViewDraws, mut params: CullParams) {
        self.frame = None;
        let mut table = Vec::with_capacity(draws.prims.len());
        let mut blocks = 0u32;
        for d in draws.prims.iter().take(MAX_DRAWS) {
            table.push(CullDraw {
                seg_first: d.seg_first,
                seg_count: d.seg_count,
                instances: d.instances,
                block_first: blocks,
                visible_base: d.visible_base,
                index_count: gpu.p.unit_mesh(d.shape, d.tess).index_count,
                kind: d.shape as u32,
                pad: 0,
            });
            blocks += d.instances.div_ceil(BLOCK);
        }
        let total: u64 = draws.prims.iter().map(|d| u64::from(d.instances)).sum();
        let kept_bytes = total * size_of::<[u32; 2]>() as u64;
        let limit = gpu.device.limits().max_storage_buffer_binding_size;
        if blocks == 0 || draws.prims.len() > MAX_DRAWS || kept_bytes > limit {
            return;
        }
        let (device, queue) = (&gpu.device, &gpu.queue);
        self.draws.write(device, queue, bytemuck::cast_slice(&table));
        self.kept.reserve(device, kept_bytes);
        // Eight mask words and an offset a block, and the total.
        self.blocks.reserve(device, (u64::from(blocks) * 9 + 1) * 4);
        params.counts[0] = table.len() as u32;
        params.counts[1] = blocks;
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        self.frame = Some(CullFrame { blocks, kept_bytes });
    }
}

/// The cull's pipelines, pyramid, and each view's buffers.
pub(super) struct GpuCull {
    hiz_depth: wgpu::ComputePipeline,
    hiz_level: wgpu::ComputePipeline,
    cull: wgpu::ComputePipeline,
    scan: wgpu::ComputePipeline,
    compact: wgpu::ComputePipeline,
    hiz_layout: wgpu::BindGroupLayout,
    arena_layout: wgpu::BindGroupLayout,
    cull_layout: wgpu::BindGroupLayout,
    pyramid: Pyramid,
    /// The camera's, then each cascade's.
    views: [ViewCull; CULL_VIEWS],
    /// Copy the counters out each frame ([`GpuCull::read_counts`]).
    pub count: bool,
    counted: bool,
    min_px: f32,
}

/// A storage buffer entry of a compute layout.
fn buffer_entry(binding: u32, ty: wgpu::BufferBindingType) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer { ty, has_dynamic_offset: false, min_binding_size: None },
        count: None,
    }
}

/// The depth buffer, read by the pyramid's first level.
fn depth_entry(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Texture {
            sample_type: wgpu::TextureSampleType::Depth,
            view_dimension: wgpu::TextureViewDimension::D2,
            multisampled: false,
        },
        count: None,
    }
}

impl GpuCull {
    /// The cull for targets of `size` whose depth buffer is `depth`, dropping primitives smaller than `min_px`.
    pub(super) fn new(
        device: &wgpu::Device,
        p: &Pipelines,
        depth: &wgpu::TextureView,
        size: (u32, u32),
        min_px: f32,
    ) -> GpuCull {
        let ro = wgpu::BufferBindingType::Storage { read_only: true };
        let rw = wgpu::BufferBindingType::Storage { read_only: false };
        let layout = |label, entries: &[wgpu::BindGroupLayoutEntry]| {
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor { label: Some(label), entries })
        };
        let level = wgpu::BindGroupLayoutEntry {
            binding: 2,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: true,
                min_binding_size: wgpu::BufferSize::new(size_of::<HizLevel>() as u64),
            },
            count: None,
        };
        let hiz_layout = layout("occlusion pyramid", &[depth_entry(0), buffer_entry(1, rw), level]);
        let arena_layout = layout("cull arena", &[buffer_entry(0, ro), buffer_entry(1, ro)]);
        let cull_layout = layout(
            "cull",
            &[
                buffer_entry(1, rw),
                buffer_entry(2, ro),
                buffer_entry(3, rw),
                buffer_entry(4, rw),
                buffer_entry(5, wgpu::BufferBindingType::Uniform),
                buffer_entry(6, rw),
                buffer_entry(7, ro),
            ],
        );
        let compute = |label, module: &wgpu::ShaderModule, entry, groups: &[Option<&wgpu::BindGroupLayout>]| {
            let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: groups,
                immediate_size: 0,
            });
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: Some(&layout),
                module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let hiz_mod = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("occlusion pyramid"),
            source: wgpu::ShaderSource::Wgsl(include_str!("../../shaders/hiz.wgsl").into()),
        });
        let cull_mod = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("cull"),
            source: wgpu::ShaderSource::Wgsl(cull_source().into()),
        });
        let groups = [Some(&p.globals_layout), Some(&arena_layout), Some(&cull_layout)];
        GpuCull {
            hiz_depth: compute("pyramid from depth", &hiz_mod, "cs_hiz_depth", &[Some(&hiz_layout)]),
            hiz_level: compute("pyramid level", &hiz_mod, "cs_hiz_level", &[Some(&hiz_layout)]),
            cull: compute("cull", &cull_mod, "cs_cull", &groups),
            scan: compute("cull scan", &cull_mod, "cs_scan", &groups),
            compact: compute("cull compact", &cull_mod, "cs_compact", &groups),
            pyramid: Pyramid::new(device, &hiz_layout, depth, size),
            hiz_layout,
            arena_layout,
            cull_layout,
            views: std::array::from_fn(|_| ViewCull::new(device)),
            count: false,
            counted: false,
            min_px,
        }
    }

    /// The target (and its depth buffer `depth`) is now `size`: a new pyramid.
    pub(super) fn resize(&mut self, device: &wgpu::Device, depth: &wgpu::TextureView, size: (u32, u32)) {
        self.pyramid = Pyramid::new(device, &self.hiz_layout, depth, size);
    }

    /// Plan this frame's cull of each view (the camera, then each cascade).
    pub(super) fn plan(&mut self, gpu: &GpuCore, views: [CullView<'_>; CULL_VIEWS]) {
        for (v, view) in self.views.iter_mut().zip(views) {
            let (eye, px_per_metre) = match view.scale {
                Scale::Perspective { eye, px_per_rad } => (eye.extend(px_per_rad), 0.0),
                Scale::Orthographic { px_per_metre } => (glam::Vec4::ZERO, px_per_metre),
            };
            let params = CullParams {
                planes: view.frustum.planes().map(|p| p.to_array()),
                eye: eye.to_array(),
                limits: [self.min_px, if view.occlusion { 1.0 } else { 0.0 }, px_per_metre, 0.0],
                counts: [0, 0, DISPATCH_ROW, self.pyramid.levels.len() as u32],
                pyramid_size: [self.pyramid.base.0, self.pyramid.base.1, 0, 0],
            };
            v.plan(gpu, view.draws, params);
        }
    }

    /// Encode the frame's cull: the terrain's depth and the pyramid (where the camera culls), then each view's three
    /// passes; what each view's pass draws with, or `None` for a view where nothing was planned (its primitives are
    /// drawn whole).
    pub(super) fn encode<'a>(
        &'a self,
        gpu: &GpuCore,
        camera: &GeometryDraws<'_>,
        enc: &mut wgpu::CommandEncoder,
    ) -> [Option<Culled<'a>>; CULL_VIEWS] {
        let none = || std::array::from_fn(|_| None);
        let (Some(prepass), Some(culled_layout)) = (&gpu.p.terrain_depth, &gpu.p.prims_culled_layout) else {
            return none();
        };
        if self.views.iter().all(|v| v.frame.is_none()) {
            return none();
        }
        let device = &gpu.device;
        if self.views[0].frame.is_some() {
            let mut pass = super::passes::depth_pass(enc, &gpu.depth, "terrain depth for the cull");
            pass.set_bind_group(0, &gpu.globals_bg, &[]);
            camera.terrain(&mut pass, prepass);
            drop(pass);
            // A pass a level: each reads the level beneath.
            for (k, l) in self.pyramid.levels.iter().enumerate() {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("pyramid"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(if k == 0 { &self.hiz_depth } else { &self.hiz_level });
                pass.set_bind_group(0, &self.pyramid.bg, &[(k as u64 * LEVEL_STRIDE) as u32]);
                pass.dispatch_workgroups(l.dst_w.div_ceil(8), l.dst_h.div_ceil(8), 1);
            }
        }
        let geometry = camera.geometry;
        let arena = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("cull arena"),
            layout: &self.arena_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: geometry.segments.buffer.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: geometry.prims.as_entire_binding() },
            ],
        });
        let mut out = none();
        for (v, slot) in self.views.iter().zip(&mut out) {
            let Some(frame) = &v.frame else { continue };
            enc.clear_buffer(&v.counters, 0, None);
            let kept = wgpu::BufferBinding {
                buffer: &v.kept.buffer,
                offset: 0,
                size: wgpu::BufferSize::new(frame.kept_bytes),
            };
            let lists = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("cull"),
                layout: &self.cull_layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::Buffer(kept.clone()) },
                    wgpu::BindGroupEntry { binding: 2, resource: v.draws.buffer.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 3, resource: v.blocks.buffer.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 4, resource: v.args.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 5, resource: v.params.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 6, resource: v.counters.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 7, resource: self.pyramid.buffer.as_entire_binding() },
                ],
            });
            let mut pass =
                enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("cull"), timestamp_writes: None });
            pass.set_bind_group(0, &gpu.globals_bg, &[]);
            pass.set_bind_group(1, &arena, &[]);
            pass.set_bind_group(2, &lists, &[]);
            let (x, y) = (frame.blocks.min(DISPATCH_ROW), frame.blocks.div_ceil(DISPATCH_ROW));
            pass.set_pipeline(&self.cull);
            pass.dispatch_workgroups(x, y, 1);
            pass.set_pipeline(&self.scan);
            pass.dispatch_workgroups(1, 1, 1);
            pass.set_pipeline(&self.compact);
            pass.dispatch_workgroups(x, y, 1);
            drop(pass);
            if self.count {
                enc.copy_buffer_to_buffer(&v.counters, 0, &v.counters_read, 0, v.counters.size());
            }
            let bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("culled primitives"),
                layout: culled_layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: geometry.segments.buffer.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: geometry.prims.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 2, resource: wgpu::BindingResource::Buffer(kept) },
                ],
            });
            *slot = Some(Culled { bg, args: &v.args });
        }
        out
    }

    /// Cull nothing this frame (it draws no trees).
    pub(super) fn skip(&mut self) {
        self.views.iter_mut().for_each(|v| v.frame = None);
    }

    /// Note that the frame just encoded copied its counters out (where [`GpuCull::count`] is on and it culled).
    pub(super) fn encoded(&mut self) {
        self.counted = self.count && self.views.iter().any(|v| v.frame.is_some());
    }

    /// The counters of the last frame culled, once the GPU finished it (blocks until then); `None` if no frame was
    /// counted since the last read.
    pub(super) fn read_counts(&mut self, device: &wgpu::Device) -> Option<CulledFrame> {
        if !std::mem::take(&mut self.counted) {
            return None;
        }
        let mut frame = CulledFrame::default();
        for (k, v) in self.views.iter().enumerate() {
            if v.frame.is_none() {
                continue;
            }
            let words: Vec<u64> = super::timing::read_mapped(device, &v.counters_read)?
                .chunks_exact(4)
                .map(|b| u64::from(u32::from_le_bytes(b.try_into().expect("4 bytes"))))
                .collect();
            let into = if k == 0 { &mut frame.camera } else { &mut frame.shadows };
            into.tested += words[0];
            into.outside += words[1];
            into.small += words[2];
            into.occluded += words[3];
        }
        Some(frame)
    }
}

/// The cull shader's source: the primitives' shader (its structs, segments and wind) and the cull's passes.
pub(crate) fn cull_source() -> String {
    [PRIMS_PARTS.concat().as_str(), include_str!("../../shaders/cull.wgsl")].concat()
}

impl Pyramid {
    /// The pyramid over a depth buffer `depth` of `size`: level 0 half its size rounded up to powers of two, every
    /// level down to 1 × 1.
    fn new(
        device: &wgpu::Device,
        layout: &wgpu::BindGroupLayout,
        depth: &wgpu::TextureView,
        (w, h): (u32, u32),
    ) -> Pyramid {
        let base = (w.max(1).div_ceil(2).next_power_of_two(), h.max(1).div_ceil(2).next_power_of_two());
        let mut levels: Vec<HizLevel> = Vec::new();
        let mut size = base;
        let mut offset = 0;
        loop {
            let below = levels.last().copied().unwrap_or_default();
            levels.push(HizLevel {
                src_offset: below.dst_offset,
                src_w: below.dst_w,
                src_h: below.dst_h,
                dst_offset: offset,
                dst_w: size.0,
                dst_h: size.1,
                pad: [0; 2],
            });
            offset += size.0 * size.1;
            if size == (1, 1) {
                break;
            }
            size = ((size.0 / 2).max(1), (size.1 / 2).max(1));
        }
        let buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("occlusion pyramid"),
            size: u64::from(offset) * 4,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        });
        let mut slots = vec![0u8; levels.len() * LEVEL_STRIDE as usize];
        for (k, l) in levels.iter().enumerate() {
            let at = k * LEVEL_STRIDE as usize;
            slots[at..at + size_of::<HizLevel>()].copy_from_slice(bytemuck::bytes_of(l));
        }
        let uniforms = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("occlusion pyramid levels"),
            contents: &slots,
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("occlusion pyramid"),
            layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(depth) },
                wgpu::BindGroupEntry { binding: 1, resource: buffer.as_entire_binding() },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &uniforms,
                        offset: 0,
                        size: wgpu::BufferSize::new(size_of::<HizLevel>() as u64),
                    }),
                },
            ],
        });
        Pyramid { base, levels, buffer, bg }
    }
}
