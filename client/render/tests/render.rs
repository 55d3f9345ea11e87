//! Image tests of the renderer, offscreen on whatever wgpu adapter is present (CI: Mesa lavapipe, no GPU): fixed
//! scenes compared with committed reference PNGs in `tests/reference/` within a tolerance (on failure
//! `NAME-actual.png` and `NAME-difference.png` are written beside them; `CANOPY_BLESS=1` writes missing references),
//! the far field compared with the CPU reference raymarcher of `canopy_worlds::hypertree::render`, and with the
//! near tree it stands for.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use canopy_render::compare::{Tolerance, check_reference, compare};
use canopy_render::offscreen::{RenderedImage, render_still};
use canopy_render::scene::SceneVolume;
use canopy_render::volume::REPRESENTATIVE_SEED;
use canopy_render::{Camera, FarPath, FrameStats, LodConfig, NearMode, RenderConfig, Scene, SceneFar, SceneInstance};
use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::hypertree::generate::{GenerateOptions, generate};
use canopy_worlds::hypertree::render::{ReferenceCamera, RenderOptions, render as cpu_render};
use canopy_worlds::world::{InstanceId, Terrain, World};
use glam::Vec3;

fn reference(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/reference").join(name)
}

fn small_world() -> World {
    let text = r#"
world testgrove
seed 77
bounds -256 -256 256 256
cell 32
terrain terrain {
  tile 256
  depth 5
  param relief = 6
  corners 10 14 18
  corners 8 10 16
  corners 6 8 12
}
species conifer conifer
species broadleaf monopodial
species bush bush
instance broadleaf at 6 30 height=16
instance conifer at -14 52 height=18
scatter conifer {
  spacing 9
  region -256 60 256 256
  param height = 10 .. 20 step 0.5
}
scatter broadleaf {
  spacing 12
  region -256 -256 256 60
  avoid conifer 8
  avoid broadleaf 10
}
scatter bush {
  spacing 7
  density 0.4
  region -60 -60 60 40
  avoid broadleaf 5
  avoid conifer 4
}
"#;
    World::parse(&SourceFile::new("testgrove.world", text), None).unwrap_or_else(|d| panic!("{d}"))
}

fn grove_camera(world: &World) -> Camera {
    let eye = Vec3::new(0.0, world.height(0.0, -10.0) + 9.0, -10.0);
    let target = Vec3::new(0.0, world.height(0.0, 120.0) + 8.0, 120.0);
    Camera::looking_at(eye, target, 60.0)
}

fn grove_config(mode: NearMode) -> RenderConfig {
    RenderConfig {
        // Thresholds for a small image: the nearest trees near, a few mid, the rest far.
        lod: LodConfig { near_px: 150.0, far_px: 30.0, ..LodConfig::default() },
        near_mode: mode,
        workers: 2,
        volume_resolution: 48,
        ..RenderConfig::default()
    }
}

const W: u32 = 320;
const H: u32 = 200;

fn render_grove(cfg: RenderConfig, camera: fn(&World) -> Camera) -> (RenderedImage, canopy_render::FrameStats) {
    let world = small_world();
    let scene = Scene::from_world(&world);
    render_still(cfg, &scene, &camera(&world), W, H, Duration::from_secs(600))
        .unwrap_or_else(|e| panic!("offscreen render failed: {e}"))
}

#[test]
fn grove_with_all_three_bands_matches_its_reference() {
    // The far band both ways: marched by the compute pass over screen tiles, and as rasterised boxes.
    for far_path in [FarPath::Compute, FarPath::Raster] {
        grove_matches_its_reference(RenderConfig { far_path, ..grove_config(NearMode::Instanced) });
    }
}

fn grove_matches_its_reference(cfg: RenderConfig) {
    let (img, stats) = render_grove(cfg, grove_camera);
    assert!(stats.near >= 1, "a tree at full detail: {stats:?}");
    assert!(stats.mid >= 3, "trees with LOD substitutes: {stats:?}");
    assert!(stats.far >= 20, "hypertree volumes in the distance: {stats:?}");
    assert_eq!(stats.waiting, 0);
    assert!(stats.primitives > 1000 && stats.terrain_triangles > 100, "{stats:?}");
    // Sky along the top (between the crowns), ground at the bottom.
    let sky = |p: [u8; 4]| p[2] > p[1] && p[2] > 150;
    let top: Vec<[u8; 4]> = (0..W).map(|x| img.pixel(x, 2)).collect();
    let bottom = img.pixel(W / 2, H - 2);
    assert!(top.iter().filter(|&&p| sky(p)).count() >= W as usize / 10, "sky {top:?}");
    assert!(bottom[1] >= bottom[2], "ground {bottom:?}");
    check_reference(&img, &reference("grove.png"), &Tolerance::default()).unwrap_or_else(|e| panic!("{e}"));
}

#[test]
fn merged_meshes_and_instanced_primitives_draw_the_same_trees() {
    // Merged meshes take several times the memory of primitive instances (and lavapipe binds at most 128 MiB):
    // fewer trees at full detail, and room for all of them.
    let cfg = |mode| RenderConfig {
        lod: LodConfig { near_px: 250.0, ..grove_config(mode).lod },
        mesh_memory: 180 << 20,
        ..grove_config(mode)
    };
    // From further back, so that no tree surrounds the camera.
    let camera = |w: &World| {
        let eye = Vec3::new(10.0, w.height(10.0, -60.0) + 16.0, -60.0);
        Camera::looking_at(eye, Vec3::new(0.0, w.height(0.0, 60.0) + 6.0, 60.0), 60.0)
    };
    let (instanced, a) = render_grove(cfg(NearMode::Instanced), camera);
    let (merged, b) = render_grove(cfg(NearMode::Merged), camera);
    assert!(a.near >= 1 && a.mid >= 10, "{a:?}");
    eprintln!("instanced: {a:?}\nmerged: {b:?}");
    assert_eq!((a.near, a.mid, a.far), (b.near, b.mid, b.far));
    assert!(b.cache_bytes > 3 * a.cache_bytes, "merged meshes take more memory than primitive instances");
    assert_eq!(b.primitives, 0, "merged mode draws meshes only");
    assert!(b.mesh_triangles > a.mesh_triangles);
    // Same tessellation; only normals are quantised differently (computed against snorm8 per vertex).
    let c = compare(&instanced, &merged, 24).unwrap();
    assert!(c.fraction < 0.02 && c.mean < 2.0, "{c:?}");
}

/// A lone hypertree (seed 000's apple, generated at resolution 48) through the far band and through the CPU
/// reference raymarcher, same camera, same lighting, flat background: the images agree.
#[test]
fn far_field_volumes_match_the_cpu_reference_raymarcher() {
    let def = canopy_worlds::hypertree::library::find("apple").expect("apple.hyp").load().expect("parses");
    let opts = GenerateOptions { resolution: Some([48, 48, 48]), ..GenerateOptions::default() };
    let (tree, _) = generate(&def, 3, &opts, &mut |_, _| {}).expect("generates");
    let bg = [0.78f32, 0.85, 0.92];
    let (w, h) = (128u32, 128u32);
    let cpu_opts = RenderOptions {
        width: w,
        height: h,
        background: [bg, bg],
        ..RenderConfig::default().lighting.reference_options()
    };
    let (cpu, _) = cpu_render(&tree, &cpu_opts, &mut |_, _| {}).expect("CPU render");
    let cpu = RenderedImage {
        width: w,
        height: h,
        rgba: cpu.pixels.chunks_exact(3).flat_map(|p| [p[0], p[1], p[2], 255]).collect(),
    };
    // The reference's camera: around the voxels' box, azimuth 0, elevation 8°.
    let rc = ReferenceCamera::new(&tree.aabb().expect("not empty"), &cpu_opts);
    let camera = Camera::looking_at(Vec3::from(rc.eye), Vec3::from(rc.center), cpu_opts.fov);

    // One instance whose species origin is the box origin, so world coordinates are box coordinates; every
    // instance far; no fog; a flat sky of the background colour; the ground far out of view.
    let graph = canopy_worlds::library::find("worm").unwrap().load().unwrap();
    let scene = Scene {
        species: vec![Some(Arc::new(graph))],
        volumes: vec![Some(SceneVolume { tree: Arc::new(tree), origin: [0.0; 3], units: 1.0 })],
        instances: vec![SceneInstance {
            id: InstanceId(0),
            species: 0,
            position: [0.0; 3],
            // Folded, its top byte is 0x88: the species' colours untinted (`common.wgsl` `instance_tint`).
            seed: 0x8800_0000,
            params: Vec::new(),
        }],
        ground: Arc::new(Terrain::flat([1.0e5, 1.0e5], 1.0)).into(),
        cover: None,
        generation: 1,
        far: SceneFar::default(),
    };
    let mut cfg = RenderConfig {
        lod: LodConfig { near_px: 1e7, far_px: 1e7, cull_px: 0.0, low_res_px: 0.0, ..LodConfig::default() },
        volume_resolution: 64,
        workers: 1,
        near_clip: 0.01,
        ..RenderConfig::default()
    };
    cfg.lighting.fog_density = 0.0;
    cfg.lighting.sky_zenith = bg;
    cfg.lighting.sky_horizon = bg;
    for far_path in [FarPath::Compute, FarPath::Raster] {
        let cfg = RenderConfig { far_path, ..cfg.clone() };
        let (gpu, stats) =
            render_still(cfg, &scene, &camera, w, h, Duration::from_secs(120)).unwrap_or_else(|e| panic!("{e}"));
        volume_matches_the_cpu_reference(far_path, &gpu, &stats, &cpu);
    }
}

fn volume_matches_the_cpu_reference(far_path: FarPath, gpu: &RenderedImage, stats: &FrameStats, cpu: &RenderedImage) {
    assert_eq!(stats.far, 1, "{stats:?}");
    let c = compare(gpu, cpu, 8).unwrap();
    eprintln!("GPU ({far_path}) against the CPU reference: {c:?}");
    let covered = cpu.rgba.chunks_exact(4).filter(|p| p[..3] != [199, 217, 235]).count();
    assert!(covered > 2000, "the tree covers the image ({covered} pixels)");
    if !(c.fraction < 0.01 && c.mean < 0.5) {
        let dir = std::env::temp_dir();
        let (g, r) = (dir.join("canopy-far-gpu.png"), dir.join("canopy-far-cpu.png"));
        gpu.save_png(&g).unwrap();
        cpu.save_png(&r).unwrap();
        panic!(
            "GPU raymarch ({far_path}) differs from the CPU reference: {c:?}; see {} and {}",
            g.display(),
            r.display()
        );
    }
    check_reference(gpu, &reference("hypertree-apple.png"), &Tolerance::default()).unwrap_or_else(|e| panic!("{e}"));
}

// The far field matches the near tree where it takes over (issue 35.3): one tree of the library drawn where its
// bounding sphere is `LodConfig::far_px` pixels tall, 8° above the horizon, from four sides, once at full detail and
// once as its hypertree volume (the representative instance, so both are the same tree), each over a black and a
// white sky; the fraction of the image the tree covers and its mean colour are compared.

const SIDE: u32 = 192;
const FOV: f32 = 35.0;
/// The azimuths the tree is seen from, degrees (the opposite sides show the same silhouettes).
const AZIMUTHS: [f32; 4] = [0.0, 45.0, 90.0, 135.0];

/// One instance of `species` (the representative), no ground in view, and its cameras by azimuth: 8° above the
/// horizon, at the distance where the tree's bounding sphere is just under the far threshold.
fn lone_tree(species: &str) -> (Scene, impl Fn(f32) -> Camera) {
    let graph = canopy_worlds::library::find(species).expect("library species").load().expect("parses");
    let stream = amplify(&graph, &Instance::new(REPRESENTATIVE_SEED), &Budget::default()).expect("amplifies");
    let (lo, hi) = stream.bounds();
    let centre = Vec3::from(lo).lerp(Vec3::from(hi), 0.5);
    let radius = 0.5 * (Vec3::from(hi) - Vec3::from(lo)).length();
    // A sphere of radius r at distance d is r·H / (d·tan(fov/2)) pixels tall.
    let px = 0.97 * LodConfig::default().far_px;
    let distance = radius * SIDE as f32 / (px * (FOV.to_radians() / 2.0).tan());
    let scene = Scene::lone(graph, REPRESENTATIVE_SEED, Terrain::flat([1.0e5, 1.0e5], 1.0));
    let camera = move |azimuth: f32| {
        let (el, az) = (8f32.to_radians(), azimuth.to_radians());
        let eye = centre + distance * Vec3::new(az.sin() * el.cos(), el.sin(), az.cos() * el.cos());
        Camera::looking_at(eye, centre, FOV)
    };
    (scene, camera)
}

/// The tree at the level `lod` forces, over a black and over a white sky, fog off, the default lighting.
fn shoot_lone(scene: &Scene, camera: &Camera, lod: &LodConfig) -> [RenderedImage; 2] {
    [[0.0; 3], [1.0; 3]].map(|sky| {
        let mut cfg =
            RenderConfig { lod: lod.clone(), workers: 1, far_path: FarPath::Compute, ..RenderConfig::default() };
        cfg.lighting.fog_density = 0.0;
        (cfg.lighting.sky_zenith, cfg.lighting.sky_horizon) = (sky, sky);
        let (img, stats) =
            render_still(cfg, scene, camera, SIDE, SIDE, Duration::from_secs(300)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((stats.in_view, stats.waiting), (1, 0), "{stats:?}");
        img
    })
}

/// The summed opacity of the pixels (`1 − (white − black)`: a pixel half covered counts half, whether it is half
/// transparent or half of its samples) and their summed colour over black, 0..1.
fn opacity_and_colour([black, white]: &[RenderedImage; 2]) -> (f64, [f64; 3]) {
    let (mut covered, mut sum) = (0.0f64, [0.0f64; 3]);
    for (b, w) in black.rgba.chunks_exact(4).zip(white.rgba.chunks_exact(4)) {
        let alpha: f64 = (0..3).map(|i| 1.0 - (f64::from(w[i]) - f64::from(b[i])) / 255.0).sum::<f64>() / 3.0;
        covered += alpha.clamp(0.0, 1.0);
        for i in 0..3 {
            sum[i] += f64::from(b[i]) / 255.0;
        }
    }
    (covered, sum)
}

/// Render `species` near and far from every azimuth, print the numbers, and check the far field's coverage (the
/// mean over the views) within `coverage` (relative) of the near tree's, within `one_view` from each side, and the
/// mean colours (opacity-weighted, over every view) within `colour` (Euclidean, RGB in 0..1). On failure the
/// pictures of the view furthest off are written to the temporary directory.
fn far_matches_near(species: &str, coverage: f64, one_view: f64, colour: f64) {
    let near_lod = LodConfig { near_px: 0.0, far_px: 0.0, cull_px: 0.0, ..LodConfig::default() };
    let far_lod = LodConfig { near_px: 1e7, far_px: 1e7, cull_px: 0.0, ..LodConfig::default() };
    let (mut total, mut worst) = ([(0.0f64, [0.0f64; 3]); 2], (0.0f64, 0.0f32, None));
    let mut views = Vec::new();
    let (scene, camera) = lone_tree(species);
    for az in AZIMUTHS {
        let shots = [&near_lod, &far_lod].map(|lod| shoot_lone(&scene, &camera(az), lod));
        let [n, f] = [&shots[0], &shots[1]].map(opacity_and_colour);
        for (t, m) in total.iter_mut().zip([n, f]) {
            t.0 += m.0;
            (0..3).for_each(|i| t.1[i] += m.1[i]);
        }
        let rel = (f.0 - n.0) / n.0.max(1e-9);
        views.push(format!("{az}°: {:+.1} %", 100.0 * rel));
        if rel.abs() >= worst.0 {
            worst = (rel.abs(), az, Some(shots));
        }
    }
    let pixels = f64::from(SIDE * SIDE) * AZIMUTHS.len() as f64;
    let [n, f] = total.map(|(c, s)| (c / pixels, s.map(|v| v / c.max(1e-9))));
    let dc = (0..3).map(|i| (n.1[i] - f.1[i]).powi(2)).sum::<f64>().sqrt();
    let rel = (f.0 - n.0) / n.0.max(1e-9);
    let report = format!(
        "{species}: near coverage {:.4} colour {:.3?}; far coverage {:.4} colour {:.3?}; coverage {:+.1} % ({}), colour distance {dc:.3}",
        n.0,
        n.1,
        f.0,
        f.1,
        100.0 * rel,
        views.join(", ")
    );
    eprintln!("{report}");
    if !(n.0 > 0.005 && rel.abs() <= coverage && worst.0 <= one_view && dc <= colour) {
        let dir = std::env::temp_dir();
        if let (_, az, Some([near, far])) = worst {
            for (name, img) in [("near", &near[1]), ("far", &far[1])] {
                img.save_png(&dir.join(format!("canopy-{species}-{az}-{name}.png"))).unwrap();
            }
        }
        panic!("{report}: the far field does not match the near tree (pictures in {})", dir.display());
    }
}

/// The issue's goal: coverage within ±15 %, mean colour within 0.1; no side more than 25 % off. Measured 2026-11-27
/// on lavapipe: monopodial −8.7 % (sides −7.4 to −9.7 %), 0.011; conifer +12.0 % (+7.5 to +16.7 %), 0.010; before the
/// far field was calibrated, seen from 0°: +87 %, 0.16 and +141 %, 0.165 (dark blobs). A density is the same from every side, a tree's cover and light are not: seen from 45° and 85° above the
/// horizon monopodial's far field covers −10 % and −13 % of the near tree, and the near tree's leaves, lit from
/// above, are brighter than the far field's baked light (colour distance 0.15 and 0.21; conifer −3 %, −8 %, 0.09).
#[test]
fn monopodial_far_field_matches_the_near_tree_at_the_switch() {
    far_matches_near("monopodial", 0.15, 0.25, 0.1);
}

#[test]
fn conifer_far_field_matches_the_near_tree_at_the_switch() {
    far_matches_near("conifer", 0.15, 0.25, 0.1);
}
