//! `canopy render`: one offscreen image of a world from a camera with the walkthrough's renderer — on any wgpu
//! adapter, Mesa's lavapipe included (no GPU, no display) — and optionally frame times over more frames.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use canopy_render::camera::{Camera, CameraSpec};
use canopy_render::offscreen::Offscreen;
use canopy_render::{CullPath, FarPath, LodConfig, NearMode, RenderConfig, timing};
use clap::Args;

/// The default view of the default world: above the southern end of the valley, looking north along it.
pub(super) const DEFAULT_VIEW: &str = "position 40 ~28 -760; look-at 0 ~30 -300; fov 60";

/// Renderer options shared by `canopy render` and `canopy walk`.
#[derive(Args, Debug, Clone)]
pub(super) struct RendererArgs {
    /// Projected height in pixels at or above which a tree is drawn at full detail.
    #[arg(long, default_value_t = LodConfig::default().near_px)]
    near_px: f32,
    /// Projected height in pixels below which a tree is drawn as a hypertree volume.
    #[arg(long, default_value_t = LodConfig::default().far_px)]
    far_px: f32,
    /// Mid-band detail levels (LOD substitutes 1..=N).
    #[arg(long, default_value_t = LodConfig::default().mid_levels)]
    mid_levels: u8,
    /// Hysteresis of level changes, a fraction of the threshold.
    #[arg(long, default_value_t = LodConfig::default().hysteresis)]
    hysteresis: f32,
    /// Resolutions far instances are drawn at: 2 (full and halved) to 4 (down to an eighth, for instances a few
    /// pixels tall).
    #[arg(long, default_value_t = LodConfig::default().far_resolutions)]
    far_resolutions: u8,
    /// Cross-fade duration in seconds (0: switch at once).
    #[arg(long, default_value_t = LodConfig::default().fade_seconds)]
    fade: f32,
    /// Near geometry: instanced unit primitives or merged meshes.
    #[arg(long, value_parser = super::named(&NearMode::NAMES), default_value_t = NearMode::Instanced)]
    near_mode: NearMode,
    /// Worker threads for amplification (default: cores − 1).
    #[arg(long)]
    workers: Option<usize>,
    /// GPU memory for cached geometry, MiB (the cache's bound).
    #[arg(long, default_value_t = 192)]
    geometry_mib: u64,
    /// Voxels along the longest axis of far-field volumes.
    #[arg(long, default_value_t = RenderConfig::default().volume_resolution)]
    volume_resolution: u32,
    /// The far view's forest is drawn as a uniform canopy layer where a pixel spans more than this many tree
    /// spacings, and its trees' voxels are marched nearer (0: march everywhere).
    #[arg(long, default_value_t = RenderConfig::default().forest_layer)]
    forest_layer: f32,
    /// How the far field is drawn: marched by a compute pass (GPUs), as rasterised boxes (CPU adapters such as
    /// lavapipe), or `auto` (by the adapter).
    #[arg(long, value_parser = super::named(&FarPath::NAMES), default_value_t = FarPath::Auto)]
    far_path: FarPath,
    /// Where the near and mid trees' primitives are culled: one by one on the GPU (the view, their size on
    /// screen, and the terrain hiding them; drawn indirectly), only tree by tree on the CPU, or `auto` (the GPU on a
    /// GPU, the CPU on a CPU adapter such as lavapipe).
    #[arg(long, value_parser = super::named(&CullPath::NAMES), default_value_t = CullPath::Auto)]
    cull: CullPath,
    /// Where the GPU culls: primitives narrower on screen than this many pixels are not drawn (0: keep them).
    #[arg(long, default_value_t = RenderConfig::default().prim_cull_px)]
    prim_cull_px: f32,
    /// Haze density per metre at height 0 (0: none; default 0.0007). It thins with height (`--haze-height`), so
    /// valleys are hazier than ridges and a view from altitude reaches the horizon.
    #[arg(long)]
    fog: Option<f32>,
    /// The haze's scale height, metres: its density falls as exp(−height / this) (0: the same at every height).
    #[arg(long, default_value_t = RenderConfig::default().lighting.haze_height)]
    haze_height: f32,
    /// Texels along each side of the sun's shadow maps (one a cascade; 0: no shadows).
    #[arg(long, default_value_t = RenderConfig::default().shadows.resolution)]
    shadow_map: u32,
    /// Metres from the eye that sun shadows reach.
    #[arg(long, default_value_t = RenderConfig::default().shadows.distance)]
    shadow_distance: f32,
    /// Wind strength (0: still air; 1: a moderate breeze).
    #[arg(long, default_value_t = RenderConfig::default().wind.strength)]
    wind: f32,
    /// Samples a pixel of terrain and trees: 4 anti-aliases their edges, 1 does not, 0 picks by the adapter (4 on
    /// a GPU, 1 on a CPU adapter such as lavapipe).
    #[arg(long, default_value_t = RenderConfig::default().msaa)]
    msaa: u32,
}

impl RendererArgs {
    /// The validated renderer configuration.
    pub(super) fn config(&self) -> anyhow::Result<RenderConfig> {
        let mut cfg = RenderConfig {
            lod: LodConfig {
                near_px: self.near_px,
                far_px: self.far_px,
                mid_levels: self.mid_levels,
                hysteresis: self.hysteresis,
                fade_seconds: self.fade,
                far_resolutions: self.far_resolutions,
                ..LodConfig::default()
            },
            near_mode: self.near_mode,
            ..RenderConfig::default()
        };
        if let Some(w) = self.workers {
            cfg.workers = w;
            cfg.max_jobs = RenderConfig::jobs_for(w);
        }
        let bytes = self.geometry_mib.saturating_mul(1 << 20);
        cfg.prim_memory = bytes / 2;
        cfg.mesh_memory = bytes / 2;
        cfg.volume_resolution = self.volume_resolution;
        cfg.forest_layer = self.forest_layer;
        cfg.far_path = self.far_path;
        cfg.cull = self.cull;
        cfg.prim_cull_px = self.prim_cull_px;
        cfg.shadows.resolution = self.shadow_map;
        cfg.shadows.distance = self.shadow_distance;
        cfg.wind.strength = self.wind;
        cfg.msaa = self.msaa;
        if let Some(fog) = self.fog {
            cfg.lighting.fog_density = fog;
        }
        cfg.lighting.haze_height = self.haze_height;
        cfg.validate().context("renderer options")?;
        Ok(cfg)
    }
}

/// Options of `canopy render`.
#[derive(Args, Debug)]
pub(super) struct RenderArgs {
    /// World manifest, or an embedded world by name (`highlands`; default: the embedded default world).
    #[arg(long)]
    world: Option<PathBuf>,
    /// Camera file, or camera statements inline separated by `;` (default: the default view,
    /// "position 40 ~28 -760; look-at 0 ~30 -300; fov 60").
    #[arg(long)]
    camera: Option<String>,
    /// Output PNG.
    #[arg(long, default_value = "shot.png")]
    out: PathBuf,
    /// Image width, pixels.
    #[arg(long, default_value_t = 1280)]
    width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = 720)]
    height: u32,
    /// Seconds on the scene's clock for the still (what the wind blows by); timed frames go on from it at 60 a
    /// second.
    #[arg(long, default_value_t = 0.0)]
    time: f32,
    /// After the still, render this many more frames and report frame times.
    #[arg(long, default_value_t = 0)]
    frames: u32,
    /// Seconds to wait for the view's geometry.
    #[arg(long, default_value_t = 600.0)]
    timeout: f64,
    /// A world expanded cell by cell (`highlands`): records are drawn for the cells within this radius of the camera,
    /// metres; beyond it the far view's summary nodes.
    #[arg(long, default_value_t = 512.0)]
    record_radius: f32,
    #[command(flatten)]
    far: super::far::FarArgs,
    #[command(flatten)]
    renderer: RendererArgs,
}

/// The camera of a `--camera` argument: a file if one exists at that path, else inline statements.
pub(super) fn camera_spec(arg: Option<&str>) -> anyhow::Result<CameraSpec> {
    match arg {
        None => Ok(CameraSpec::parse(DEFAULT_VIEW)?),
        Some(a) if std::path::Path::new(a).is_file() => Ok(CameraSpec::load(std::path::Path::new(a))?),
        Some(a) if a.contains(' ') => CameraSpec::parse(a).with_context(|| format!("camera `{a}`")),
        Some(a) => {
            anyhow::bail!("camera file {a} does not exist (inline cameras look like \"position 0 ~30 0; yaw 90\")")
        }
    }
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    canopy_harness::numbers::percentile(sorted, q).unwrap_or(0.0)
}

/// Run `canopy render`.
pub(super) fn run(args: RenderArgs) -> anyhow::Result<ExitCode> {
    let spec = camera_spec(args.camera.as_deref())?;
    let loaded = Instant::now();
    let world = Arc::new(super::load_world(args.world.as_deref()).map_err(|d| anyhow::anyhow!("{d}"))?);
    let camera: Camera = spec.resolve(&|x, z| world.height(x, z));
    println!(
        "world {}: {} instances of {} species, loaded in {:.2} s",
        world.name,
        world.instances.len(),
        world.species.len(),
        loaded.elapsed().as_secs_f64()
    );
    // Records near the camera (every instance of a world materialised at load), the far view's summaries beyond.
    let altitude = camera.position.y - world.height(camera.position.x, camera.position.z);
    let cfg = args.renderer.config()?;
    let mut off = Offscreen::new(cfg, args.width, args.height)?;
    off.renderer.set_time(args.time);
    let culls = off.renderer.count_culled();
    println!("adapter: {}", off.gpu.describe());
    let far = args.far.view(args.height, camera.fov_y, altitude)?;
    if !(args.record_radius.is_finite() && args.record_radius >= 0.0) {
        anyhow::bail!("--record-radius must be a distance in metres");
    }
    let built = Instant::now();
    let eye = [camera.position.x, camera.position.y, camera.position.z];
    let scene = super::far::scene_around(&world, eye, args.record_radius, far);
    println!(
        "scene: {} records, {} summary nodes{}, built in {:.2} s",
        scene.instances.len(),
        scene.far.nodes.len(),
        if far.is_some() { "" } else { " (--no-summaries)" },
        built.elapsed().as_secs_f64()
    );
    let settle = Instant::now();
    let stats = off.settle(&scene, &camera, Duration::from_secs_f64(args.timeout.max(0.0)))?;
    println!(
        "settled in {:.2} s: {} in view — near {}, mid {}, far {}; far view {} nodes drawn as {} forest patches ({:.0} trees' worth); {} primitives ({} into the shadow maps, {} trees out of view among their casters), {} mesh triangles, {} terrain triangles, {} draw calls; cache {} entries, {:.1} of {:.0} MiB",
        settle.elapsed().as_secs_f64(),
        stats.in_view,
        stats.near,
        stats.mid,
        stats.far,
        stats.forest_nodes,
        stats.forest_patches,
        stats.forest_trees,
        stats.primitives,
        stats.shadow_primitives,
        stats.shadow_casters,
        stats.mesh_triangles,
        stats.terrain_triangles,
        stats.draw_calls,
        stats.cache_entries,
        stats.cache_bytes as f64 / 1048576.0,
        stats.cache_capacity as f64 / 1048576.0,
    );
    let image = off.render()?;
    let px = args.renderer.prim_cull_px;
    match off.renderer.culled() {
        Some(c) => println!(
            "GPU cull: {} of {} primitives drawn; dropped {} out of view, {} under {px} px, {} behind the terrain; into the shadow maps {} of {} (dropped {} outside their cascades, {} under {px} texels)",
            c.camera.kept(),
            c.camera.tested,
            c.camera.outside,
            c.camera.small,
            c.camera.occluded,
            c.shadows.kept(),
            c.shadows.tested,
            c.shadows.outside,
            c.shadows.small,
        ),
        None if culls => println!("GPU cull: no primitives this frame"),
        None => println!("GPU cull: off (trees culled whole on the CPU; --cull gpu culls each primitive)"),
    }
    image.save_png(&args.out)?;
    println!("wrote {} ({}×{})", args.out.display(), image.width, image.height);
    if args.frames > 0 {
        let mut times = Vec::new();
        let mut update = Vec::new();
        let timed = off.renderer.time_parts();
        let mut parts: Vec<Vec<f64>> = vec![Vec::new(); timing::PARTS.len()];
        // As in the window: while the GPU draws a frame the CPU prepares the next, so a frame takes the longer of
        // the two (from one submission to the next, once the GPU finished it).
        let mut next = off.renderer.update(&scene, &camera, 1.0 / 60.0);
        for k in 0..args.frames {
            let t = Instant::now();
            let index = off.submit();
            update.push(next.update_ms);
            if k + 1 < args.frames {
                off.renderer.set_time(args.time + (k + 1) as f32 / 60.0);
                next = off.renderer.update(&scene, &camera, 1.0 / 60.0);
            }
            off.wait(index)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
            for (part, ms) in parts.iter_mut().zip(off.renderer.part_times().unwrap_or_default()) {
                part.push(ms);
            }
        }
        times.sort_by(f64::total_cmp);
        update.sort_by(f64::total_cmp);
        let mean = times.iter().sum::<f64>() / times.len() as f64;
        println!(
            "frame time over {} frames at {}×{} (the next frame prepared while the GPU draws): mean {:.1} ms ({:.1} fps), median {:.1} ms, p95 {:.1} ms, min {:.1} ms; CPU update median {:.1} ms",
            times.len(),
            args.width,
            args.height,
            mean,
            1e3 / mean,
            percentile(&times, 0.5),
            percentile(&times, 0.95),
            times[0],
            percentile(&update, 0.5),
        );
        if timed {
            let mut line = String::from("GPU time median per part:");
            let mut total = 0.0;
            for (name, mut ms) in timing::PARTS.iter().zip(parts) {
                ms.sort_by(f64::total_cmp);
                let m = percentile(&ms, 0.5);
                total += m;
                line += &format!(" {name} {m:.2} ms,");
            }
            println!("{line} together {total:.2} ms");
        } else {
            println!("GPU time per part: the adapter has no timestamp queries inside passes");
        }
    }
    Ok(ExitCode::SUCCESS)
}
