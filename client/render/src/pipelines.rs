//! Shader modules, bind group layouts, render pipelines and the unit meshes of instanced primitives.

use bytemuck::{Pod, Zeroable};
use wgpu::util::DeviceExt;

use super::geometry::MeshVertex;

/// Depth buffer format (reversed Z: cleared to 0, `Greater` passes).
pub(crate) const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// Format of the far-field atlas texels.
pub(crate) const ATLAS_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;

/// Format of the far field's accumulation target (premultiplied colour and opacity, composited front to back).
pub(crate) const ACCUM_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;

/// The fragment shaders' attribute forcing depth tests before them (where the device has
/// [`wgpu::Features::SHADER_EARLY_DEPTH_TEST`]; without it the attribute is left out, and fragments the scene hides
/// are shaded and then dropped: the same picture, more work).
const EARLY_DEPTH_TEST: &str = "@early_depth_test(force)";

/// Radial segments of cones and cylinders, and latitude bands of spheres, by detail level (as
/// [`canopy_worlds::mesh::MeshOptions::for_detail`]).
pub(crate) const FRUSTUM_SEGMENTS: [u32; 4] = [8, 6, 4, 3];
/// Sphere latitude bands by detail level.
pub(crate) const SPHERE_RINGS: [u32; 4] = [6, 4, 2, 2];

const COMMON: &str = include_str!("../shaders/common.wgsl");
/// The far-field volumes' infos and atlas bindings, shared by the volume and forest shaders.
const VOLUME_INFO: &str = include_str!("../shaders/volume_info.wgsl");
const SEGMENT: &str = include_str!("../shaders/segment.wgsl");
/// The sun's shadow maps, read by what receives shadows (terrain, primitives, meshes).
const SHADOW: &str = include_str!("../shaders/shadow.wgsl");
/// The far field's per-pixel opacity, shared by the volume and forest shaders.
const FAR_ACCUM: &str = include_str!("../shaders/far_accum.wgsl");
const VOLUME: &str = include_str!("../shaders/volume.wgsl");
const FOREST: &str = include_str!("../shaders/forest.wgsl");
/// The parts of the primitives' shader, in order.
pub(crate) const PRIMS_PARTS: [&str; 4] = [COMMON, SHADOW, include_str!("../shaders/prims.wgsl"), SEGMENT];
/// The parts of the meshes' shader, in order.
pub(crate) const MESH_PARTS: [&str; 4] = [COMMON, SHADOW, include_str!("../shaders/mesh.wgsl"), SEGMENT];

/// How a render pipeline uses its pass's samples.
#[derive(Clone, Copy)]
struct Sampling {
    /// Samples a pixel.
    samples: u32,
    /// The fragment's alpha becomes the share of the samples covered (the leaf cards' margins).
    alpha_to_coverage: bool,
    /// The shader's dithered cross-fade keeps samples, not whole pixels (`segment.wgsl` `dither_samples`).
    dithered: bool,
}

impl Sampling {
    /// One sample a pixel (the far field's passes).
    const SINGLE: Sampling = Sampling { samples: 1, alpha_to_coverage: false, dithered: false };
}

/// The forest shader's source: its parts with the canopy tile's layout as the shader reads it, from the constants
/// that bake it.
pub(crate) fn forest_source() -> String {
    [COMMON, VOLUME_INFO, FAR_ACCUM, &tile_consts(), FOREST].concat()
}

fn tile_consts() -> String {
    format!(
        "const CLASSES: f32 = {}.0;\nconst BANDS: f32 = {}.0;\nconst TILE_MIPS: u32 = {}u;\n",
        super::tile::DENSITY_CLASSES,
        super::tile::PROFILE_BANDS,
        super::tile::TILE_MIPS
    )
}

/// A vertex of a unit mesh: `p` (position, or for frusta `(cos, 0|1, sin, cap)`) and a face normal.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(crate) struct UnitVertex {
    p: [f32; 4],
    n: [f32; 4],
}

/// One unit mesh on the GPU.
#[derive(Debug)]
pub(crate) struct UnitMesh {
    pub vertices: wgpu::Buffer,
    pub indices: wgpu::Buffer,
    pub index_count: u32,
}

fn unit_mesh(device: &wgpu::Device, label: &str, v: &[UnitVertex], i: &[u16]) -> UnitMesh {
    UnitMesh {
        vertices: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytemuck::cast_slice(v),
            usage: wgpu::BufferUsages::VERTEX,
        }),
        indices: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytemuck::cast_slice(i),
            usage: wgpu::BufferUsages::INDEX,
        }),
        index_count: i.len() as u32,
    }
}

/// A frustum along +Y with `n` segments and both caps, counter-clockwise from outside.
pub(crate) fn frustum(n: u32) -> (Vec<UnitVertex>, Vec<u16>) {
    let mut v = Vec::new();
    let mut idx = Vec::new();
    let ring = |k: u32| {
        let t = std::f32::consts::TAU * (k % n) as f32 / n as f32;
        (t.cos(), t.sin())
    };
    let u = |p: [f32; 4]| UnitVertex { p, n: [0.0; 4] };
    for k in 0..n {
        let (c, s) = ring(k);
        v.push(u([c, 0.0, s, 0.0]));
        v.push(u([c, 1.0, s, 0.0]));
    }
    for k in 0..n {
        let (b0, t0, b1, t1) = (2 * k, 2 * k + 1, 2 * ((k + 1) % n), 2 * ((k + 1) % n) + 1);
        idx.extend([b0, t0, t1, b0, t1, b1].map(|x| x as u16));
    }
    for top in [0.0f32, 1.0] {
        let center = v.len() as u16;
        v.push(u([0.0, top, 0.0, 1.0]));
        for k in 0..n {
            let (c, s) = ring(k);
            v.push(u([c, top, s, 1.0]));
        }
        for k in 0..n {
            let (a, b) = (center + 1 + k as u16, center + 1 + ((k + 1) % n) as u16);
            if top > 0.5 {
                idx.extend([center, b, a]);
            } else {
                idx.extend([center, a, b]);
            }
        }
    }
    (v, idx)
}

/// A unit sphere with `rings` latitude bands and `2 · rings` longitude segments.
pub(crate) fn sphere(rings: u32) -> (Vec<UnitVertex>, Vec<u16>) {
    let segs = 2 * rings;
    let mut v = Vec::new();
    for r in 0..=rings {
        let phi = -std::f32::consts::FRAC_PI_2 + std::f32::consts::PI * r as f32 / rings as f32;
        for s in 0..=segs {
            let th = std::f32::consts::TAU * s as f32 / segs as f32;
            let p = [phi.cos() * th.cos(), phi.sin(), phi.cos() * th.sin()];
            v.push(UnitVertex { p: [p[0], p[1], p[2], 0.0], n: [p[0], p[1], p[2], 0.0] });
        }
    }
    let at = |r: u32, s: u32| (r * (segs + 1) + s) as u16;
    let mut idx = Vec::new();
    for r in 0..rings {
        for s in 0..segs {
            idx.extend([at(r, s), at(r + 1, s), at(r + 1, s + 1), at(r, s), at(r + 1, s + 1), at(r, s + 1)]);
        }
    }
    (v, idx)
}

/// A unit cube centred on the origin, four vertices per face.
pub(crate) fn cube() -> (Vec<UnitVertex>, Vec<u16>) {
    let faces: [([f32; 3], [f32; 3], [f32; 3]); 6] = [
        ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]),
        ([-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]),
        ([0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]),
        ([0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
        ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
        ([0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]),
    ];
    let mut v = Vec::new();
    let mut idx = Vec::new();
    for (n, a, b) in faces {
        let base = v.len() as u16;
        for (su, sv) in [(-1.0f32, -1.0f32), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            let p: [f32; 3] = std::array::from_fn(|i| 0.5 * (n[i] + su * a[i] + sv * b[i]));
            v.push(UnitVertex { p: [p[0], p[1], p[2], 0.0], n: [n[0], n[1], n[2], 0.0] });
        }
        idx.extend([base, base + 1, base + 2, base, base + 2, base + 3]);
    }
    (v, idx)
}

/// Everything the renderer draws with.
#[derive(Debug)]
pub(crate) struct Pipelines {
    pub globals_layout: wgpu::BindGroupLayout,
    pub prims_layout: wgpu::BindGroupLayout,
    pub mesh_layout: wgpu::BindGroupLayout,
    pub draw_layout: wgpu::BindGroupLayout,
    pub volume_layout: wgpu::BindGroupLayout,
    /// The forest patches' ground heights (a storage buffer read by the fragment shader).
    pub forest_layout: wgpu::BindGroupLayout,
    /// The far field's per-pixel opacity (group 3 of the volume and forest pipelines).
    pub accum_layout: wgpu::BindGroupLayout,
    /// The accumulation target, read by the composite.
    pub composite_layout: wgpu::BindGroupLayout,
    /// The far field's compute march: scene depth, accumulation target, tile lists, far instances and patches.
    pub march_layout: wgpu::BindGroupLayout,
    /// The sun's shadow maps and their comparison sampler (group 3 of the terrain, primitive and mesh pipelines).
    pub shadow_layout: wgpu::BindGroupLayout,
    /// The multisampled scene depth, read by the depth resolve.
    pub resolve_layout: wgpu::BindGroupLayout,
    /// The multisampled scene depth resolved to one sample a pixel for the far field (`depth_resolve.wgsl`), where
    /// the scene pass is multisampled.
    pub depth_resolve: Option<wgpu::RenderPipeline>,
    pub sky: wgpu::RenderPipeline,
    pub terrain: wgpu::RenderPipeline,
    pub prims: wgpu::RenderPipeline,
    pub mesh: wgpu::RenderPipeline,
    pub volume: wgpu::RenderPipeline,
    /// Summary patches raymarched through canopy tiles ([`super::forest`]).
    pub forest: wgpu::RenderPipeline,
    /// The far field's accumulation laid over the scene.
    pub composite: wgpu::RenderPipeline,
    /// The far field marched per screen tile (`far_march.wgsl`).
    pub far_march: wgpu::ComputePipeline,
    /// The terrain, primitives and meshes drawn depth-only into a shadow map (`renderer/shadow.rs`).
    pub shadow_terrain: wgpu::RenderPipeline,
    pub shadow_prims: wgpu::RenderPipeline,
    pub shadow_mesh: wgpu::RenderPipeline,
    /// Where the GPU culls (`renderer/cull.rs`): the terrain drawn depth-only from the camera (the occlusion
    /// pyramid's source), and the primitives drawn from the cull's visible list (group 1: segments, arena, list),
    /// into the scene and into the shadow maps.
    pub terrain_depth: Option<wgpu::RenderPipeline>,
    pub prims_culled_layout: Option<wgpu::BindGroupLayout>,
    pub prims_culled: Option<wgpu::RenderPipeline>,
    pub shadow_prims_culled: Option<wgpu::RenderPipeline>,
    /// Frusta by detail level.
    pub frusta: Vec<UnitMesh>,
    /// Spheres by detail level.
    pub spheres: Vec<UnitMesh>,
    /// The cube.
    pub cube: UnitMesh,
}

/// A layout entry of `ty` at `binding`, seen by `vis`.
fn entry(binding: u32, vis: wgpu::ShaderStages, ty: wgpu::BindingType) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry { binding, visibility: vis, ty, count: None }
}

/// A read-only storage buffer.
fn storage(binding: u32, vis: wgpu::ShaderStages) -> wgpu::BindGroupLayoutEntry {
    let ty = wgpu::BufferBindingType::Storage { read_only: true };
    entry(binding, vis, wgpu::BindingType::Buffer { ty, has_dynamic_offset: false, min_binding_size: None })
}

/// A texture read with `textureLoad` (no sampler).
fn texture(
    binding: u32,
    vis: wgpu::ShaderStages,
    sample_type: wgpu::TextureSampleType,
    view_dimension: wgpu::TextureViewDimension,
) -> wgpu::BindGroupLayoutEntry {
    entry(binding, vis, wgpu::BindingType::Texture { sample_type, view_dimension, multisampled: false })
}

fn module(device: &wgpu::Device, label: &str, parts: &[&str]) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(parts.concat().into()),
    })
}

fn depth(write: bool, compare: wgpu::CompareFunction) -> Option<wgpu::DepthStencilState> {
    Some(wgpu::DepthStencilState {
        format: DEPTH_FORMAT,
        depth_write_enabled: Some(write),
        depth_compare: Some(compare),
        stencil: wgpu::StencilState::default(),
        bias: wgpu::DepthBiasState::default(),
    })
}

impl Pipelines {
    /// Build every pipeline for targets of `format`, the scene pass's with `samples` samples a pixel;
    /// `early_depth`: whether the device has [`wgpu::Features::SHADER_EARLY_DEPTH_TEST`]; `culls`: whether the
    /// GPU culls the primitives (its pipelines are built only then).
    pub(crate) fn new(
        device: &wgpu::Device,
        format: wgpu::TextureFormat,
        samples: u32,
        early_depth: bool,
        culls: bool,
    ) -> Pipelines {
        let vs_fs = wgpu::ShaderStages::VERTEX_FRAGMENT;
        let fs_cs = wgpu::ShaderStages::FRAGMENT | wgpu::ShaderStages::COMPUTE;
        let unfiltered = wgpu::TextureSampleType::Float { filterable: false };
        let globals_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("globals"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: vs_fs | wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }],
        });
        let v = wgpu::ShaderStages::VERTEX;
        let prims_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("prims"),
            entries: &[storage(0, v), storage(1, v)],
        });
        let mesh_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("meshes"),
            entries: &[storage(0, v), storage(1, v), storage(2, v)],
        });
        let draw_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("draw"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: v,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: wgpu::BufferSize::new(16),
                },
                count: None,
            }],
        });
        let volume_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("volumes"),
            entries: &[
                texture(0, fs_cs, unfiltered, wgpu::TextureViewDimension::D3),
                storage(1, vs_fs | wgpu::ShaderStages::COMPUTE),
            ],
        });
        let forest_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("forest ground and profiles"),
            entries: &[storage(0, fs_cs), storage(1, fs_cs)],
        });
        let accum_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("far-field opacity"),
            entries: &[entry(
                0,
                wgpu::ShaderStages::FRAGMENT,
                wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: false },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
            )],
        });
        let composite_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("far-field accumulation"),
            entries: &[texture(0, wgpu::ShaderStages::FRAGMENT, unfiltered, wgpu::TextureViewDimension::D2)],
        });
        let cs = wgpu::ShaderStages::COMPUTE;
        let march_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("far-field march"),
            entries: &[
                texture(1, cs, wgpu::TextureSampleType::Depth, wgpu::TextureViewDimension::D2),
                entry(
                    2,
                    cs,
                    wgpu::BindingType::StorageTexture {
                        access: wgpu::StorageTextureAccess::WriteOnly,
                        format: ACCUM_FORMAT,
                        view_dimension: wgpu::TextureViewDimension::D2,
                    },
                ),
                storage(3, cs),
                storage(4, cs),
                storage(5, cs),
                storage(6, cs),
            ],
        });
        let shadow_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("shadow maps"),
            entries: &[
                texture(
                    0,
                    wgpu::ShaderStages::FRAGMENT,
                    wgpu::TextureSampleType::Depth,
                    wgpu::TextureViewDimension::D2Array,
                ),
                entry(
                    1,
                    wgpu::ShaderStages::FRAGMENT,
                    wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Comparison),
                ),
            ],
        });
        let layout = |label: &str, groups: &[Option<&wgpu::BindGroupLayout>]| {
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: groups,
                immediate_size: 0,
            })
        };
        // A far-field shader: its parts, without the early depth attribute where the device lacks it.
        let far_module = |label: &str, parts: &[&str]| {
            let source = parts.concat();
            let source = if early_depth { source } else { source.replace(EARLY_DEPTH_TEST, "") };
            module(device, label, &[&source])
        };
        let opaque = [Some(wgpu::ColorTargetState { format, blend: None, write_mask: wgpu::ColorWrites::ALL })];
        let premultiplied = [Some(wgpu::ColorTargetState {
            format,
            blend: Some(wgpu::BlendState::PREMULTIPLIED_ALPHA_BLENDING),
            write_mask: wgpu::ColorWrites::ALL,
        })];
        // Premultiplied fragments arriving front to back, each composited under what is already there.
        let under = wgpu::BlendComponent {
            src_factor: wgpu::BlendFactor::OneMinusDstAlpha,
            dst_factor: wgpu::BlendFactor::One,
            operation: wgpu::BlendOperation::Add,
        };
        let accumulated = [Some(wgpu::ColorTargetState {
            format: ACCUM_FORMAT,
            blend: Some(wgpu::BlendState { color: under, alpha: under }),
            write_mask: wgpu::ColorWrites::ALL,
        })];
        let pipeline = |label: &str,
                        layout: &wgpu::PipelineLayout,
                        module: &wgpu::ShaderModule,
                        entry: (&str, &str),
                        buffers: &[Option<wgpu::VertexBufferLayout<'_>>],
                        cull: Option<wgpu::Face>,
                        depth_stencil: Option<wgpu::DepthStencilState>,
                        targets: &[Option<wgpu::ColorTargetState>],
                        Sampling { samples, alpha_to_coverage, dithered }: Sampling| {
            // The shader is told (its overrides) whether its alpha becomes the samples covered, and how many samples
            // a pixel its dithered cross-fade spreads over (`segment.wgsl` `dither_samples`).
            let mut constants: Vec<(&str, f64)> = Vec::new();
            if alpha_to_coverage {
                constants.push(("ALPHA_TO_COVERAGE", 1.0));
            }
            if dithered && samples > 1 {
                constants.push(("SAMPLES", f64::from(samples)));
            }
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(label),
                layout: Some(layout),
                vertex: wgpu::VertexState {
                    module,
                    entry_point: Some(entry.0),
                    compilation_options: Default::default(),
                    buffers,
                },
                primitive: wgpu::PrimitiveState { cull_mode: cull, ..Default::default() },
                depth_stencil,
                multisample: wgpu::MultisampleState {
                    count: samples,
                    alpha_to_coverage_enabled: alpha_to_coverage,
                    ..Default::default()
                },
                fragment: Some(wgpu::FragmentState {
                    module,
                    entry_point: Some(entry.1),
                    compilation_options: wgpu::PipelineCompilationOptions {
                        constants: &constants,
                        ..Default::default()
                    },
                    targets,
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        let greater = wgpu::CompareFunction::Greater;
        // What casts a shadow: the vertex stage of a receiver, depth only, nearest the sun kept; no culling (leaves
        // and mirrored primitives are seen from both sides). The slope bias keeps a lit surface out of its own map.
        // A fragment stage only where it cuts something out (the meshes' leaf cards).
        let caster = |label: &str,
                      layout: &wgpu::PipelineLayout,
                      module: &wgpu::ShaderModule,
                      (entry, cut): (&str, Option<&str>),
                      buffers: &[Option<wgpu::VertexBufferLayout<'_>>]| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(label),
                layout: Some(layout),
                vertex: wgpu::VertexState {
                    module,
                    entry_point: Some(entry),
                    compilation_options: Default::default(),
                    buffers,
                },
                primitive: wgpu::PrimitiveState::default(),
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: super::renderer::SHADOW_FORMAT,
                    depth_write_enabled: Some(true),
                    depth_compare: Some(wgpu::CompareFunction::Less),
                    stencil: wgpu::StencilState::default(),
                    bias: wgpu::DepthBiasState { constant: 0, slope_scale: 2.0, clamp: 0.0 },
                }),
                multisample: wgpu::MultisampleState::default(),
                fragment: cut.map(|cut| wgpu::FragmentState {
                    module,
                    entry_point: Some(cut),
                    compilation_options: Default::default(),
                    targets: &[],
                }),
                multiview_mask: None,
                cache: None,
            })
        };

        let sky_mod = module(device, "sky", &[COMMON, include_str!("../shaders/sky.wgsl")]);
        let sky = pipeline(
            "sky",
            &layout("sky", &[Some(&globals_layout)]),
            &sky_mod,
            ("vs_sky", "fs_sky"),
            &[],
            None,
            depth(false, wgpu::CompareFunction::Always),
            &opaque,
            Sampling { samples, alpha_to_coverage: false, dithered: false },
        );

        let terrain_mod = module(device, "terrain", &[COMMON, SHADOW, include_str!("../shaders/terrain.wgsl")]);
        let terrain_attrs = wgpu::vertex_attr_array![0 => Float32x3, 1 => Uint32, 2 => Uint32];
        let terrain_buffers = [Some(wgpu::VertexBufferLayout {
            array_stride: size_of::<MeshVertex>() as u64,
            step_mode: wgpu::VertexStepMode::Vertex,
            attributes: &terrain_attrs,
        })];
        let terrain = pipeline(
            "terrain",
            &layout("terrain", &[Some(&globals_layout), None, None, Some(&shadow_layout)]),
            &terrain_mod,
            ("vs_terrain", "fs_terrain"),
            &terrain_buffers,
            None,
            depth(true, greater),
            &opaque,
            Sampling { samples, alpha_to_coverage: false, dithered: false },
        );
        let shadow_terrain = caster(
            "terrain shadow",
            &layout("terrain shadow", &[Some(&globals_layout)]),
            &terrain_mod,
            ("vs_terrain", None),
            &terrain_buffers,
        );

        let prims_mod = module(device, "prims", &PRIMS_PARTS);
        let unit_attrs = wgpu::vertex_attr_array![0 => Float32x4, 1 => Float32x4];
        let unit_buffers = [Some(wgpu::VertexBufferLayout {
            array_stride: size_of::<UnitVertex>() as u64,
            step_mode: wgpu::VertexStepMode::Vertex,
            attributes: &unit_attrs,
        })];
        // No culling: a mirroring transform flips a primitive's winding.
        let prims = pipeline(
            "prims",
            &layout("prims", &[Some(&globals_layout), Some(&prims_layout), Some(&draw_layout), Some(&shadow_layout)]),
            &prims_mod,
            ("vs_prim", "fs_prim"),
            &unit_buffers,
            None,
            depth(true, greater),
            &opaque,
            Sampling { samples, alpha_to_coverage: false, dithered: true },
        );
        let prims_culled_layout = culls.then(|| {
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("culled prims"),
                entries: &[storage(0, v), storage(1, v), storage(2, v)],
            })
        });
        let prims_culled = prims_culled_layout.as_ref().map(|culled| {
            pipeline(
                "culled prims",
                &layout(
                    "culled prims",
                    &[Some(&globals_layout), Some(culled), Some(&draw_layout), Some(&shadow_layout)],
                ),
                &prims_mod,
                ("vs_prim_culled", "fs_prim"),
                &unit_buffers,
                None,
                depth(true, greater),
                &opaque,
                Sampling { samples, alpha_to_coverage: false, dithered: true },
            )
        });
        let terrain_depth = culls.then(|| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("terrain depth"),
                layout: Some(&layout("terrain depth", &[Some(&globals_layout)])),
                vertex: wgpu::VertexState {
                    module: &terrain_mod,
                    entry_point: Some("vs_terrain"),
                    compilation_options: Default::default(),
                    buffers: &terrain_buffers,
                },
                primitive: wgpu::PrimitiveState::default(),
                depth_stencil: depth(true, greater),
                multisample: wgpu::MultisampleState::default(),
                fragment: None,
                multiview_mask: None,
                cache: None,
            })
        });
        let shadow_prims = caster(
            "primitive shadow",
            &layout("primitive shadow", &[Some(&globals_layout), Some(&prims_layout), Some(&draw_layout)]),
            &prims_mod,
            ("vs_prim", None),
            &unit_buffers,
        );
        let shadow_prims_culled = prims_culled_layout.as_ref().map(|culled| {
            caster(
                "culled primitive shadow",
                &layout("culled primitive shadow", &[Some(&globals_layout), Some(culled), Some(&draw_layout)]),
                &prims_mod,
                ("vs_prim_culled", None),
                &unit_buffers,
            )
        });

        let mesh_mod = module(device, "meshes", &MESH_PARTS);
        // Multisampled, a leaf card's edge is its coverage (alpha-to-coverage); the alpha written stays the scene's.
        let alpha_to_coverage = samples > 1;
        let mesh_targets = [Some(wgpu::ColorTargetState {
            format,
            blend: None,
            write_mask: if alpha_to_coverage { wgpu::ColorWrites::COLOR } else { wgpu::ColorWrites::ALL },
        })];
        let mesh = pipeline(
            "meshes",
            &layout("meshes", &[Some(&globals_layout), Some(&mesh_layout), Some(&draw_layout), Some(&shadow_layout)]),
            &mesh_mod,
            ("vs_mesh", "fs_mesh"),
            &[],
            None,
            depth(true, greater),
            &mesh_targets,
            Sampling { samples, alpha_to_coverage, dithered: true },
        );
        let shadow_mesh = caster(
            "mesh shadow",
            &layout("mesh shadow", &[Some(&globals_layout), Some(&mesh_layout), Some(&draw_layout)]),
            &mesh_mod,
            ("vs_mesh", Some("fs_mesh_shadow")),
            &[],
        );

        let volume_mod = far_module("volumes", &[COMMON, VOLUME_INFO, FAR_ACCUM, VOLUME]);
        let far_attrs = wgpu::vertex_attr_array![0 => Float32x4, 1 => Uint32, 2 => Float32];
        let volume = pipeline(
            "volumes",
            &layout("volumes", &[Some(&globals_layout), Some(&volume_layout), None, Some(&accum_layout)]),
            &volume_mod,
            ("vs_volume", "fs_volume"),
            &[Some(wgpu::VertexBufferLayout {
                array_stride: 24,
                step_mode: wgpu::VertexStepMode::Instance,
                attributes: &far_attrs,
            })],
            Some(wgpu::Face::Back),
            depth(false, greater),
            &accumulated,
            Sampling::SINGLE,
        );

        let tile_consts = tile_consts();
        let forest_mod = far_module("forest", &[&forest_source()]);
        let patch_attrs = wgpu::vertex_attr_array![
            0 => Float32x4, 1 => Float32x2, 2 => Uint32x2, 3 => Uint32x2, 4 => Uint32, 5 => Uint32,
            6 => Float32, 7 => Float32, 8 => Float32, 9 => Uint32, 10 => Float32, 11 => Float32, 12 => Float32x2,
            13 => Float32x2
        ];
        // Back faces culled: from inside a node's box the vertex shader mirrors it, so its inner faces are drawn.
        let forest = pipeline(
            "forest",
            &layout(
                "forest",
                &[Some(&globals_layout), Some(&volume_layout), Some(&forest_layout), Some(&accum_layout)],
            ),
            &forest_mod,
            ("vs_forest", "fs_forest"),
            &[Some(wgpu::VertexBufferLayout {
                array_stride: size_of::<super::forest::ForestPatch>() as u64,
                step_mode: wgpu::VertexStepMode::Instance,
                attributes: &patch_attrs,
            })],
            Some(wgpu::Face::Back),
            depth(false, greater),
            &accumulated,
            Sampling::SINGLE,
        );

        let bins_consts = format!(
            "const PATCH_BIT: u32 = {}u;\nconst MARCH_TILE: u32 = {}u;\n",
            super::bins::PATCH_BIT,
            super::bins::TILE_PX
        );
        let march_mod = far_module(
            "far-field march",
            &[
                COMMON,
                VOLUME_INFO,
                FAR_ACCUM,
                &tile_consts,
                &bins_consts,
                VOLUME,
                FOREST,
                include_str!("../shaders/far_march.wgsl"),
            ],
        );
        let far_march = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("far-field march"),
            layout: Some(&layout(
                "far-field march",
                &[Some(&globals_layout), Some(&volume_layout), Some(&forest_layout), Some(&march_layout)],
            )),
            module: &march_mod,
            entry_point: Some("cs_far"),
            compilation_options: Default::default(),
            cache: None,
        });

        let resolve_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("scene depth"),
            entries: &[entry(
                0,
                wgpu::ShaderStages::FRAGMENT,
                wgpu::BindingType::Texture {
                    sample_type: wgpu::TextureSampleType::Depth,
                    view_dimension: wgpu::TextureViewDimension::D2,
                    multisampled: true,
                },
            )],
        });
        let depth_resolve = (samples > 1).then(|| {
            let m = module(device, "depth resolve", &[include_str!("../shaders/depth_resolve.wgsl")]);
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("depth resolve"),
                layout: Some(&layout("depth resolve", &[Some(&resolve_layout)])),
                vertex: wgpu::VertexState {
                    module: &m,
                    entry_point: Some("vs_resolve"),
                    compilation_options: Default::default(),
                    buffers: &[],
                },
                primitive: wgpu::PrimitiveState::default(),
                depth_stencil: depth(true, wgpu::CompareFunction::Always),
                multisample: wgpu::MultisampleState::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &m,
                    entry_point: Some("fs_resolve"),
                    compilation_options: Default::default(),
                    targets: &[],
                }),
                multiview_mask: None,
                cache: None,
            })
        });

        let composite_mod = module(device, "far-field composite", &[include_str!("../shaders/composite.wgsl")]);
        let composite = pipeline(
            "far-field composite",
            &layout("far-field composite", &[Some(&composite_layout)]),
            &composite_mod,
            ("vs_composite", "fs_composite"),
            &[],
            None,
            None,
            &premultiplied,
            Sampling::SINGLE,
        );

        let frusta = FRUSTUM_SEGMENTS
            .iter()
            .map(|&n| {
                let (v, i) = frustum(n);
                unit_mesh(device, "unit frustum", &v, &i)
            })
            .collect();
        let spheres = SPHERE_RINGS
            .iter()
            .map(|&r| {
                let (v, i) = sphere(r);
                unit_mesh(device, "unit sphere", &v, &i)
            })
            .collect();
        let (cv, ci) = cube();
        let cube = unit_mesh(device, "unit cube", &cv, &ci);
        Pipelines {
            globals_layout,
            prims_layout,
            mesh_layout,
            draw_layout,
            volume_layout,
            forest_layout,
            accum_layout,
            composite_layout,
            march_layout,
            shadow_layout,
            resolve_layout,
            depth_resolve,
            sky,
            terrain,
            prims,
            mesh,
            volume,
            forest,
            composite,
            far_march,
            shadow_terrain,
            shadow_prims,
            shadow_mesh,
            terrain_depth,
            prims_culled_layout,
            prims_culled,
            shadow_prims_culled,
            frusta,
            spheres,
            cube,
        }
    }
}

impl Pipelines {
    /// The unit mesh of a unit shape (frustum, sphere, box) at a tessellation.
    pub(crate) fn unit_mesh(&self, shape: usize, tess: usize) -> &UnitMesh {
        match shape {
            0 => &self.frusta[tess],
            1 => &self.spheres[tess],
            _ => &self.cube,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn outward(v: &[UnitVertex], idx: &[u16], centre_of: impl Fn([f32; 3]) -> [f32; 3]) {
        for t in idx.chunks_exact(3) {
            let p = |k: usize| {
                let q = v[t[k] as usize].p;
                [q[0], q[1], q[2]]
            };
            let (a, b, c) = (p(0), p(1), p(2));
            let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
            let m: [f32; 3] = std::array::from_fn(|i| (a[i] + b[i] + c[i]) / 3.0);
            let o = centre_of(m);
            let out = [m[0] - o[0], m[1] - o[1], m[2] - o[2]];
            let d = n[0] * out[0] + n[1] * out[1] + n[2] * out[2];
            assert!(d > 0.0, "triangle {t:?} faces inward");
        }
    }

    #[test]
    fn unit_meshes_wind_counter_clockwise_from_outside() {
        for n in FRUSTUM_SEGMENTS {
            let (v, i) = frustum(n);
            assert_eq!(i.len() as u32, 3 * 4 * n);
            // The axis point at the triangle's height is inside (caps: a point just inside the cap).
            outward(&v, &i, |m| [0.0, if m[1] == 1.0 || m[1] == 0.0 { 0.5 } else { m[1] }, 0.0]);
        }
        for r in SPHERE_RINGS {
            let (v, i) = sphere(r);
            let (vv, ii): (Vec<UnitVertex>, Vec<u16>) = (v, i);
            // Degenerate triangles at the poles have no orientation; skip zero-area ones.
            let good: Vec<u16> = ii
                .chunks_exact(3)
                .filter(|t| {
                    let p = |k: usize| vv[t[k] as usize].p;
                    let (a, b, c) = (p(0), p(1), p(2));
                    let d = |x: [f32; 4], y: [f32; 4]| (0..3).map(|i| (x[i] - y[i]).abs()).sum::<f32>() > 1e-6;
                    d(a, b) && d(b, c) && d(a, c)
                })
                .flatten()
                .copied()
                .collect();
            outward(&vv, &good, |_| [0.0; 3]);
        }
        let (v, i) = cube();
        outward(&v, &i, |_| [0.0; 3]);
    }
}
