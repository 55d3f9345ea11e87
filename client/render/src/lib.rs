//! The renderer: terrain, trees in three distance bands and the hypertree far field, drawn with wgpu (seed 001 §5,
//! seed 000 §8). It consumes a [`Scene`] — species graphs, instances, the terrain and optional hypertree volumes —
//! and knows nothing of the network: `canopy walk` feeds it from the client library, `canopy render` from a world
//! file.
//!
//! Shape (wgpu's examples framework): [`Renderer::new`] (init), [`Renderer::resize`], [`Renderer::update`] (LOD
//! selection, worker results, uploads) and [`Renderer::render`] into any `TextureView`; the winit loop lives apart,
//! in `cli/walk.rs`, and [`offscreen`] renders into a texture and reads it back.
//!
//! Bands, by the projected height of an instance's bounding sphere in pixels ([`lod`]):
//! - **near** (≥ [`LodConfig::near_px`]): the full amplified geometry, detail 0;
//! - **mid**: the species' LOD substitutes, detail 1..=[`LodConfig::mid_levels`], one level per halving of size;
//! - **far** (< [`LodConfig::far_px`]): the species' hypertree volume, raymarched on an instanced proxy box.
//!
//! Beyond the records, the scene's far field ([`SceneFar`]: summary nodes of issue 15) is drawn as forest
//! (`forest.rs`): one raymarched proxy box per node and species, through the species' canopy tile ([`tile`]: its far
//! volume repeated as a stand of trees), on the sub-squares the node covers and neither its held children nor the
//! record cells draw, cross-fading as that changes.
//!
//! Level changes use hysteresis and a dithered cross-fade (both drawn with complementary screen-door masks).
//! Amplification and voxelisation run on worker threads ([`workers`]); results are uploaded under a per-frame byte
//! budget into fixed-size GPU arenas ([`arena`]), which are the memory bound of the geometry cache (least recently
//! used entries are evicted). Rendering never waits for a worker: an instance whose geometry is not resident is
//! drawn at the nearest resident level, or not at all.

mod arena;
mod bins;
mod cache;
pub mod camera;
mod clock;
// Offscreen stills and the image comparison block on the GPU and write files: native only.
#[cfg(not(target_arch = "wasm32"))]
pub mod compare;
mod forest;
mod geometry;
mod gpu;
mod ground;
mod leaf;
mod lod;
#[cfg(not(target_arch = "wasm32"))]
pub mod offscreen;
mod pipelines;
mod renderer;
pub mod scene;
mod select;
mod stats;
mod terrain;
mod tile;
pub mod volume;
mod workers;

pub use camera::{Camera, CameraError};
pub use gpu::{Gpu, GpuError};
pub use lod::{Band, LodConfig};
#[cfg(not(target_arch = "wasm32"))]
pub use offscreen::{OffscreenError, RenderedImage};
pub use renderer::{CullCounts, CulledFrame, FrameStats, Renderer, timing};
pub use scene::{Scene, SceneFar, SceneInstance};

use canopy_worlds::amplify::Budget;
use canopy_worlds::hypertree::render::{Light, RenderOptions, Shading};

/// How near geometry is represented on the GPU (the choice the issue asks to make by measurement; see
/// `docs/renderer.md`). Also the values of `--near-mode`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum NearMode {
    /// Cones, cylinders, spheres and boxes as instances of unit meshes (64 bytes per primitive, shaped in the
    /// vertex shader); leaves and trunk bases as meshes.
    Instanced,
    /// Every primitive meshed on the CPU ([`canopy_worlds::mesh`]) into one merged mesh per tree.
    Merged,
}

impl NearMode {
    /// The modes with their names (the values of `--near-mode`).
    pub const NAMES: [(&'static str, NearMode); 2] = [("instanced", NearMode::Instanced), ("merged", NearMode::Merged)];
}

/// `Display` and `FromStr` for a type whose values have names in its `NAMES` table (`(name, value)` pairs: the
/// values of a command-line option), `$what` naming the set in the error for an unknown name. The crates that
/// draw need no clap.
#[macro_export]
macro_rules! named_values {
    ($t:ty, $what:literal) => {
        impl std::fmt::Display for $t {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(<$t>::NAMES.iter().find(|(_, v)| v == self).map_or("?", |(n, _)| n))
            }
        }

        impl std::str::FromStr for $t {
            type Err = String;
            fn from_str(s: &str) -> Result<$t, String> {
                <$t>::NAMES.iter().find(|(n, _)| *n == s).map(|(_, v)| *v).ok_or_else(|| format!("no {} `{s}`", $what))
            }
        }
    };
}

named_values!(NearMode, "near mode");

/// Lighting and atmosphere, shared by every band so that they match (and the far field's baked shading matches
/// the CPU reference renderer's defaults).
#[derive(Clone, Debug, PartialEq)]
pub struct Lighting {
    /// Direction toward the sun (normalised when used).
    pub sun_direction: [f32; 3],
    /// Sun colour and intensity.
    pub sun_color: [f32; 3],
    /// Ambient intensity.
    pub ambient: f32,
    /// Diffuse coefficient.
    pub diffuse: f32,
    /// Light from the sky, `sky_light · (½ + ½ n_y)`, on meshes and in the far field's baked shading.
    pub sky_light: f32,
    /// Exponential falloff of ambient light toward a crown's interior (hypertrees, Reeves; 0 = constant).
    pub ambient_falloff: f32,
    /// The opacity coefficient `k` of `α = 1 − (1 − µ)^(k·Δs)` for hypertrees.
    pub density_scale: f32,
    /// Cast shadow rays when baking hypertree shading.
    pub volume_shadows: bool,
    /// Sky colour at the zenith.
    pub sky_zenith: [f32; 3],
    /// Sky colour at the horizon (and the colour of thick haze).
    pub sky_horizon: [f32; 3],
    /// Haze density per metre at height 0 (aerial perspective: `1 − exp(−optical depth)` of a surface's light is
    /// replaced by the haze's); 0 disables the haze.
    pub fog_density: f32,
    /// The haze's scale height, metres: its density falls as `exp(−y / haze_height)`, so valleys are hazier than
    /// ridges and a view from altitude looks down through thin air (0: the same density at every height).
    pub haze_height: f32,
    /// How much brighter the haze and the sky are toward the sun (forward scattering).
    pub sun_glow: f32,
    /// Ambient occlusion inside crowns: the share of the ambient and the sky's light taken away at the centre of a
    /// near or mid tree's crown (its bounding sphere), less toward its surface and in its upper half (0: none).
    pub crown_occlusion: f32,
}

impl Default for Lighting {
    fn default() -> Self {
        // Sun, ambient, diffuse and opacity are the CPU reference renderer's defaults. The far field is lit as the
        // near meshes are, so that a tree does not change where it becomes a volume (issue 35.3): the sky's light
        // of the meshes, its ambient light darkening toward the crown's interior as the meshes' crown occlusion
        // darkens theirs (a falloff of 1.5 matches it best: colour distance at the switch 0.018 for the conifer and
        // 0.010 for the monopodial tree, `render::*_far_field_matches_the_near_tree_at_the_switch`), and no
        // self-shadowing (the meshes' shadow maps reach 300 m).
        let r = RenderOptions::default();
        let sun = r.lights[0];
        Lighting {
            sun_direction: sun.direction,
            sun_color: sun.color,
            ambient: r.ambient,
            diffuse: r.diffuse,
            sky_light: 0.12,
            ambient_falloff: 1.5,
            density_scale: r.density_scale,
            volume_shadows: false,
            sky_zenith: [0.42, 0.6, 0.85],
            sky_horizon: [0.78, 0.85, 0.92],
            fog_density: 0.0007,
            haze_height: 500.0,
            sun_glow: 0.25,
            crown_occlusion: 0.5,
        }
    }
}

impl Lighting {
    /// The unit direction toward the sun.
    pub fn sun(&self) -> glam::Vec3 {
        glam::Vec3::from(self.sun_direction).normalize_or(glam::Vec3::Y)
    }

    /// The CPU reference renderer's options that shade a hypertree as this lighting does (its default diffuse model,
    /// one light: the sun); what the far field bakes per voxel.
    pub fn reference_options(&self) -> RenderOptions {
        RenderOptions {
            lights: vec![Light { direction: self.sun_direction, color: self.sun_color }],
            ambient: self.ambient,
            ambient_falloff: self.ambient_falloff,
            diffuse: self.diffuse,
            sky_light: self.sky_light,
            density_scale: self.density_scale,
            shadows: self.volume_shadows,
            shading: Shading::Diffuse,
            ..RenderOptions::default()
        }
    }
}

/// How the far field (far instances and forest patches) is drawn: marched by a compute pass over screen tiles, or
/// rasterised as proxy boxes whose fragments march (also the values of `--far-path`). Measured in
/// `docs/renderer.md`: on an NVIDIA H200 the compute pass is 20 to 45 times as fast (its graphics stages run on a
/// few of its cores); on Mesa's lavapipe the boxes are 3 to 8 times as fast (a pixel there walks only the boxes
/// that cover it).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum FarPath {
    /// Compute on a GPU, boxes on a CPU adapter (lavapipe).
    Auto,
    /// The compute pass.
    Compute,
    /// Rasterised boxes.
    Raster,
}

impl FarPath {
    /// The paths with their names (the values of `--far-path`).
    pub const NAMES: [(&'static str, FarPath); 3] =
        [("auto", FarPath::Auto), ("compute", FarPath::Compute), ("raster", FarPath::Raster)];

    /// Whether the far field is marched by the compute pass on an adapter of `device_type`.
    pub fn computes(self, device_type: wgpu::DeviceType) -> bool {
        match self {
            FarPath::Auto => device_type != wgpu::DeviceType::Cpu,
            FarPath::Compute => true,
            FarPath::Raster => false,
        }
    }
}

named_values!(FarPath, "far path");

/// Where the camera's near and mid primitives are culled (also the values of `--cull`): one by one on the GPU
/// (`renderer/cull.rs`: the view frustum, [`RenderConfig::prim_cull_px`] and the terrain's occlusion pyramid, the
/// kept ones drawn indirectly), or only tree by tree, as the CPU's selection does either way.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CullPath {
    /// The GPU on a GPU, the CPU on a CPU adapter (lavapipe) and in a browser.
    Auto,
    /// Each primitive on the GPU (compute passes and indirect draws).
    Gpu,
    /// Whole trees on the CPU only.
    Cpu,
}

impl CullPath {
    /// The paths with their names (the values of `--cull`).
    pub const NAMES: [(&'static str, CullPath); 3] =
        [("auto", CullPath::Auto), ("gpu", CullPath::Gpu), ("cpu", CullPath::Cpu)];

    /// Whether the GPU culls on an adapter of `device_type`.
    pub fn on_gpu(self, device_type: wgpu::DeviceType) -> bool {
        match self {
            CullPath::Auto => device_type != wgpu::DeviceType::Cpu,
            CullPath::Gpu => true,
            CullPath::Cpu => false,
        }
    }
}

named_values!(CullPath, "cull path");

/// Everything that configures a renderer. Every threshold is here, none in the shaders.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderConfig {
    /// Distance bands, thresholds, hysteresis and cross-fade.
    pub lod: LodConfig,
    /// Representation of near and mid geometry.
    pub near_mode: NearMode,
    /// Lighting and fog.
    pub lighting: Lighting,
    /// Worker threads for amplification and voxelisation (at least 1).
    pub workers: usize,
    /// Bytes of GPU arena for primitive instances (the near/mid geometry cache's bound, with `mesh_memory`).
    pub prim_memory: u64,
    /// Bytes of GPU arena for mesh vertices and indices (leaves, trunk bases, merged meshes).
    pub mesh_memory: u64,
    /// Bytes of geometry uploaded per frame at most (the rest waits for later frames).
    pub upload_budget: u64,
    /// Amplification jobs queued or running at most.
    pub max_jobs: usize,
    /// Work bound of one instance's amplification (hostile species end in an error, drawn far or not at all).
    pub amplify_budget: Budget,
    /// Voxels along the longest axis of a species' far-field volume; a second, halved resolution is derived by
    /// voxel fusion (seed 000 §9) for the farthest instances.
    pub volume_resolution: u32,
    /// Vertical field of view is the camera's; this is the near clip plane, metres (there is no far plane: the
    /// projection is reversed-Z to infinity).
    pub near_clip: f32,
    /// Lattice squares per edge of the window drawn of a fractal ground ([`ground::FractalWindow`]).
    pub ground_window: u32,
    /// Tree spacings a pixel spans beyond which a summary patch draws its species' canopy as a uniform layer
    /// ([`tile::CanopyProfile`]) instead of marching the canopy tile's voxels; 0: march everywhere. The default,
    /// 0.5 (trees two pixels apart and farther), draws a view from altitude about 1.6 times as fast as 1 and 2.8
    /// times as fast as marching everywhere (frame times in `docs/renderer.md`).
    pub forest_layer: f32,
    /// How the far field is drawn.
    pub far_path: FarPath,
    /// Where the near and mid primitives are culled.
    pub cull: CullPath,
    /// Where the GPU culls: a primitive whose bounding sphere is narrower on screen than this many pixels is not
    /// drawn (0 keeps every one in view).
    pub prim_cull_px: f32,
    /// Sun shadows: cascaded shadow maps cast by the terrain and the near and mid trees.
    pub shadows: Shadows,
    /// Wind bending trees and fluttering leaves in the vertex stage.
    pub wind: Wind,
    /// Samples a pixel of the scene pass (terrain and trees): 4 anti-aliases their edges, 1 does not, 0 picks by
    /// the adapter (4 on a GPU, 1 on a CPU adapter such as lavapipe, where 4 doubles some frames). The far field is
    /// drawn once a pixel either way, against the nearest of the pixel's depths.
    pub msaa: u32,
}

/// Sun shadows (`renderer/shadow.rs`): [`SHADOW_CASCADES`] shadow maps, each fitted to a slice of the view out to
/// `distance`, the slices growing geometrically.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shadows {
    /// Texels along each side of a cascade's map; 0 turns shadows off.
    pub resolution: u32,
    /// Metres from the eye that shadows reach (beyond, the sun is unblocked).
    pub distance: f32,
}

/// Shadow map cascades.
pub const SHADOW_CASCADES: usize = 3;

impl Default for Shadows {
    fn default() -> Self {
        Shadows { resolution: 2048, distance: 300.0 }
    }
}

/// Wind (`shaders/segment.wgsl` `wind_offset`): trunks sway by their height squared and branches and leaves
/// flutter by their distance from the trunk, each tree in its own phase drawn from its instance seed. A frame is a
/// function of the scene and the renderer's time ([`Renderer::set_time`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Wind {
    /// Horizontal direction the wind blows toward, (x, z) (normalised when used).
    pub direction: [f32; 2],
    /// 0 for still air; 1 a moderate breeze (a 20 m crown's top sways about half a metre).
    pub strength: f32,
}

impl Default for Wind {
    fn default() -> Self {
        Wind { direction: [0.8, 0.6], strength: 1.0 }
    }
}

impl Default for RenderConfig {
    fn default() -> Self {
        let workers = std::thread::available_parallelism().map_or(1, |n| n.get().saturating_sub(1).max(1));
        RenderConfig {
            lod: LodConfig::default(),
            near_mode: NearMode::Instanced,
            lighting: Lighting::default(),
            workers,
            prim_memory: 96 << 20,
            mesh_memory: 96 << 20,
            upload_budget: 16 << 20,
            max_jobs: Self::jobs_for(workers),
            amplify_budget: Budget {
                max_primitives: 400_000,
                max_depth: 1_024,
                max_steps: 50_000_000,
                max_pending: 1 << 18,
            },
            volume_resolution: 64,
            near_clip: 0.25,
            ground_window: ground::WINDOW_SQUARES,
            forest_layer: 0.5,
            far_path: FarPath::Auto,
            cull: CullPath::Auto,
            prim_cull_px: 1.0,
            shadows: Shadows::default(),
            wind: Wind::default(),
            msaa: 0,
        }
    }
}

/// Why a renderer configuration is not usable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    /// A number is not finite or out of its range.
    #[error("{0} is out of range")]
    Range(&'static str),
}

impl RenderConfig {
    /// The job bound for `workers` worker threads: four jobs each, plus a few (the default `max_jobs`).
    pub fn jobs_for(workers: usize) -> usize {
        4 * workers + 8
    }

    /// The scene pass's samples a pixel on an adapter of `device_type` ([`RenderConfig::msaa`]).
    pub fn samples(&self, device_type: wgpu::DeviceType) -> u32 {
        match self.msaa {
            0 if device_type == wgpu::DeviceType::Cpu => 1,
            0 => 4,
            n => n,
        }
    }

    /// Bytes of the mesh arena for vertices: two thirds of `mesh_memory`.
    pub fn vertex_memory(&self) -> u64 {
        self.mesh_memory * 2 / 3
    }

    /// Bytes of the mesh arena for indices: a third of `mesh_memory`.
    pub fn index_memory(&self) -> u64 {
        self.mesh_memory / 3
    }

    /// Check every number (the CLI validates once, the renderer trusts a checked config).
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.lod.validate()?;
        let l = &self.lighting;
        let fin = |v: &[f32]| v.iter().all(|x| x.is_finite());
        let checks = [
            (fin(&l.sun_direction) && l.sun_direction.iter().any(|v| *v != 0.0), "sun direction"),
            (fin(&l.sun_color) && l.sun_color.iter().all(|v| (0.0..=100.0).contains(v)), "sun colour"),
            ((0.0..=100.0).contains(&l.ambient), "ambient"),
            ((0.0..=100.0).contains(&l.diffuse), "diffuse"),
            ((0.0..=100.0).contains(&l.ambient_falloff), "ambient falloff"),
            ((0.0..=100.0).contains(&l.sky_light), "sky light"),
            ((0.0..=1000.0).contains(&l.density_scale), "density scale"),
            (fin(&l.sky_zenith) && fin(&l.sky_horizon), "sky colour"),
            ((0.0..=1.0).contains(&l.fog_density), "fog density"),
            ((0.0..=100_000.0).contains(&l.haze_height), "haze height"),
            ((0.0..=10.0).contains(&l.sun_glow), "sun glow"),
            ((0.0..=1.0).contains(&l.crown_occlusion), "crown occlusion"),
            ((1..=64).contains(&self.workers), "worker count"),
            ((1 << 20..=2 << 30).contains(&self.prim_memory), "primitive memory"),
            ((1 << 20..=2 << 30).contains(&self.mesh_memory), "mesh memory"),
            (self.upload_budget >= 1 << 16, "upload budget"),
            ((1..=4096).contains(&self.max_jobs), "job count"),
            ((8..=volume::MAX_SLOT).contains(&self.volume_resolution), "volume resolution"),
            (self.near_clip > 0.0 && self.near_clip.is_finite(), "near clip plane"),
            ((0.0..=1000.0).contains(&self.forest_layer), "forest layer"),
            ((0.0..=64.0).contains(&self.prim_cull_px), "primitive cull size"),
            (self.shadows.resolution <= 8192, "shadow map resolution"),
            ((1.0..=100_000.0).contains(&self.shadows.distance), "shadow distance"),
            (fin(&self.wind.direction) && self.wind.direction.iter().any(|v| *v != 0.0), "wind direction"),
            ((0.0..=100.0).contains(&self.wind.strength), "wind strength"),
            (matches!(self.msaa, 0 | 1 | 4), "samples a pixel (0, 1 or 4)"),
        ];
        match checks.iter().find(|c| !c.0) {
            Some((_, what)) => Err(ConfigError::Range(what)),
            None => Ok(()),
        }
    }
}
