//! Image tests of the sun's shadows, the wind and the crowns' ambient occlusion (issue 33), offscreen on whatever wgpu adapter is present (CI:
//! Mesa lavapipe): one tree on flat ground, compared with committed references, and each with a tolerance that
//! the picture without the effect (no shadow, a frozen wind) fails.

use std::path::{Path, PathBuf};
use std::time::Duration;

use canopy_render::compare::{Tolerance, check_reference, compare};
use canopy_render::offscreen::{Offscreen, RenderedImage};
use canopy_render::volume::REPRESENTATIVE_SEED;
use canopy_render::{Camera, LodConfig, RenderConfig, Scene, Shadows, Wind};
use canopy_worlds::world::Terrain;
use glam::Vec3;

const W: u32 = 256;
const H: u32 = 192;

pub(super) fn reference(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/reference").join(name)
}

/// The representative monopodial tree at the origin of a flat ground.
pub(super) fn tree() -> Scene {
    let graph = canopy_worlds::library::find("monopodial").expect("library species").load().expect("parses");
    Scene::lone(graph, REPRESENTATIVE_SEED, Terrain::flat([-200.0, -200.0], 400.0))
}

/// [`tree`], seen from above and to the side so that its shadow (the sun is the default: up and to −x, +z) falls in
/// view.
fn tree_and_camera() -> (Scene, Camera) {
    let scene = tree();
    let camera = Camera::looking_at(Vec3::new(-14.0, 17.0, -19.0), Vec3::new(3.0, 3.0, -3.0), 55.0);
    (scene, camera)
}

/// The tree at full detail, fog off, with `shadows` and `wind`, at `time` seconds.
fn shoot(shadows: Shadows, wind: Wind, time: f32) -> RenderedImage {
    let (scene, camera) = tree_and_camera();
    let (img, stats) = shoot_sized(&scene, &camera, shadows, wind, time, 4, (W, H));
    assert_eq!((stats.near, stats.waiting), (1, 0), "{stats:?}");
    img
}

fn shoot_sized(
    scene: &Scene,
    camera: &Camera,
    shadows: Shadows,
    wind: Wind,
    time: f32,
    msaa: u32,
    size: (u32, u32),
) -> (RenderedImage, canopy_render::FrameStats) {
    shoot_configured(scene, camera, config(shadows, wind, msaa), time, size)
}

/// The tests' renderer: the tree at full detail from 20 pixels, one worker, fog off.
pub(super) fn config(shadows: Shadows, wind: Wind, msaa: u32) -> RenderConfig {
    let mut cfg = RenderConfig {
        lod: LodConfig { near_px: 20.0, far_px: 5.0, ..LodConfig::default() },
        workers: 1,
        shadows,
        wind,
        msaa,
        ..RenderConfig::default()
    };
    cfg.lighting.fog_density = 0.0;
    cfg
}

pub(super) fn shoot_configured(
    scene: &Scene,
    camera: &Camera,
    cfg: RenderConfig,
    time: f32,
    (w, h): (u32, u32),
) -> (RenderedImage, canopy_render::FrameStats) {
    let mut off = Offscreen::new(cfg, w, h).unwrap_or_else(|e| panic!("{e}"));
    off.renderer.set_time(time);
    let stats = off.settle(scene, camera, Duration::from_secs(300)).unwrap_or_else(|e| panic!("{e}"));
    (off.render().unwrap_or_else(|e| panic!("{e}")), stats)
}

/// Pixels at least `by` darker (summed RGB) in `a` than in `b`, as a fraction of the image.
pub(super) fn darker(a: &RenderedImage, b: &RenderedImage, by: i32) -> f64 {
    let sum = |p: &[u8]| p[..3].iter().map(|&c| i32::from(c)).sum::<i32>();
    let n = a.rgba.chunks_exact(4).zip(b.rgba.chunks_exact(4)).filter(|(p, q)| sum(q) - sum(p) >= by).count();
    n as f64 / f64::from(a.width * a.height)
}

#[test]
fn the_tree_casts_its_shadow_and_a_missing_shadow_fails() {
    let still = Wind { strength: 0.0, ..Wind::default() };
    let shadows = Shadows { resolution: 1024, distance: 120.0 };
    let lit = shoot(shadows, still, 0.0);
    let unshadowed = shoot(Shadows { resolution: 0, ..shadows }, still, 0.0);
    // The shadow darkens the ground beside the tree and the crown's far side: a good part of the picture.
    let shade = darker(&lit, &unshadowed, 60);
    eprintln!("in shadow: {:.1} % of the pixels", 100.0 * shade);
    assert!(shade > 0.03, "only {:.1} % of the pixels are in shadow", 100.0 * shade);
    assert!(darker(&unshadowed, &lit, 60) < 0.001, "a shadow never brightens");
    let t = Tolerance::default();
    check_reference(&lit, &reference("sun-shadow.png"), &t).unwrap_or_else(|e| panic!("{e}"));
    let missing = compare(&unshadowed, &lit, t.channel).expect("same size");
    eprintln!("without shadows: {missing:?}");
    assert!(!missing.within(&t), "a missing shadow passes the reference's tolerance: {missing:?}");
}

#[test]
fn the_wind_moves_the_tree_and_a_frozen_wind_fails() {
    let shadows = Shadows { resolution: 1024, distance: 120.0 };
    let wind = Wind::default();
    let blown = shoot(shadows, wind, 2.0);
    // A frame is a function of the scene and the time: the same time gives the same picture.
    assert_eq!(blown.rgba, shoot(shadows, wind, 2.0).rgba, "the same time, a different picture");
    let t = Tolerance::default();
    check_reference(&blown, &reference("sun-wind.png"), &t).unwrap_or_else(|e| panic!("{e}"));
    let frozen = compare(&shoot(shadows, wind, 0.0), &blown, t.channel).expect("same size");
    eprintln!("frozen at 0 s against 2 s: {frozen:?}");
    assert!(!frozen.within(&t), "a frozen wind passes the reference's tolerance: {frozen:?}");
    // In still air time changes nothing.
    let still = Wind { strength: 0.0, ..wind };
    assert_eq!(shoot(shadows, still, 0.0).rgba, shoot(shadows, still, 2.0).rgba);
}

#[test]
fn a_tree_out_of_view_still_casts_its_shadow_into_it() {
    let (scene, _) = tree_and_camera();
    // Looking down at the ground where the top of the crown casts its shadow, the tree itself out of view.
    let camera = Camera::looking_at(Vec3::new(14.0, 14.0, -11.5), Vec3::new(14.5, 0.0, -12.0), 30.0);
    let still = Wind { strength: 0.0, ..Wind::default() };
    let shadows = Shadows { resolution: 1024, distance: 120.0 };
    let (lit, stats) = shoot_sized(&scene, &camera, shadows, still, 0.0, 4, (W, H));
    assert_eq!((stats.in_view, stats.shadow_casters), (0, 1), "{stats:?}");
    let (bare, _) = shoot_sized(&scene, &camera, Shadows { resolution: 0, ..shadows }, still, 0.0, 4, (W, H));
    let shade = darker(&lit, &bare, 60);
    eprintln!("out of view, in shadow: {:.1} % of the ground", 100.0 * shade);
    assert!(shade > 0.05, "only {:.1} % of the ground is in shadow", 100.0 * shade);
}

/// The mean absolute difference (RGB, 0..255) of `img` from `big` averaged over `k × k` blocks.
fn off_supersampled(img: &RenderedImage, big: &RenderedImage, k: u32) -> f64 {
    let mut total = 0.0;
    for y in 0..img.height {
        for x in 0..img.width {
            for c in 0..3 {
                let mut sum = 0.0;
                for dy in 0..k {
                    for dx in 0..k {
                        sum += f64::from(big.pixel(x * k + dx, y * k + dy)[c]);
                    }
                }
                total += (sum / f64::from(k * k) - f64::from(img.pixel(x, y)[c])).abs();
            }
        }
    }
    total / f64::from(img.width * img.height * 3)
}

#[test]
fn multisampling_brings_edges_toward_the_supersampled_picture() {
    let (scene, camera) = tree_and_camera();
    let (still, shadows) = (Wind { strength: 0.0, ..Wind::default() }, Shadows::default());
    let (one, _) = shoot_sized(&scene, &camera, shadows, still, 0.0, 1, (W, H));
    let (four, _) = shoot_sized(&scene, &camera, shadows, still, 0.0, 4, (W, H));
    // The same view at 4 × 4 samples a pixel, one each, averaged: what an edge should look like.
    let (big, _) = shoot_sized(&scene, &camera, shadows, still, 0.0, 1, (4 * W, 4 * H));
    let (a, b) = (off_supersampled(&one, &big, 4), off_supersampled(&four, &big, 4));
    eprintln!("mean difference from 16 samples a pixel: {a:.2} at 1 sample, {b:.2} at 4");
    assert!(b < 0.8 * a, "{a:.2} → {b:.2}");
}

#[test]
fn a_trunk_close_up_shows_its_bark() {
    let (scene, _) = tree_and_camera();
    // Two metres from the trunk, looking at it level, out of the wind.
    let camera = Camera::looking_at(Vec3::new(-2.0, 2.0, -1.0), Vec3::new(0.0, 2.0, 0.0), 40.0);
    let still = Wind { strength: 0.0, ..Wind::default() };
    let (img, stats) = shoot_sized(&scene, &camera, Shadows::default(), still, 0.0, 4, (W, H));
    assert_eq!(stats.near, 1, "{stats:?}");
    // Across the trunk, fissures: the brightness dips and rises again several times (smooth shading around a
    // cylinder would have one extremum at most).
    let row: Vec<i32> = (0..W).map(|x| img.pixel(x, H / 2)[..3].iter().map(|&c| i32::from(c)).sum()).collect();
    let trunk = &row[W as usize * 2 / 5..W as usize * 3 / 5];
    // A dip: 20 darker than the brightest of the 4 pixels on either side; a run of them is one fissure.
    let dip = |i: usize| {
        let left = trunk[i.saturating_sub(4)..i].iter().max().copied().unwrap_or(0);
        let right = trunk[i + 1..(i + 5).min(trunk.len())].iter().max().copied().unwrap_or(0);
        trunk[i] + 20 <= left && trunk[i] + 20 <= right
    };
    let dips = (1..trunk.len() - 1).filter(|&i| dip(i) && !dip(i - 1)).count();
    eprintln!("fissures across the trunk: {dips}");
    assert!(dips >= 2, "a smooth trunk: {trunk:?}");
    check_reference(&img, &reference("sun-trunk.png"), &Tolerance::default()).unwrap_or_else(|e| panic!("{e}"));
}

#[test]
fn a_crown_is_darker_inside_and_no_occlusion_fails() {
    let (scene, camera) = tree_and_camera();
    let still = Wind { strength: 0.0, ..Wind::default() };
    let shot = |occlusion: f32| {
        let mut cfg = config(Shadows { resolution: 0, ..Shadows::default() }, still, 4);
        cfg.lighting.crown_occlusion = occlusion;
        shoot_configured(&scene, &camera, cfg, 0.0, (W, H)).0
    };
    let (occluded, open) = (shot(RenderConfig::default().lighting.crown_occlusion), shot(0.0));
    // Inside the crown the ambient and sky light is less: a good part of the crown darker, nothing brighter.
    let inner = darker(&occluded, &open, 24);
    eprintln!("darker inside the crown: {:.1} % of the pixels", 100.0 * inner);
    assert!(inner > 0.02, "only {:.1} % of the pixels are darker", 100.0 * inner);
    assert!(darker(&open, &occluded, 6) == 0.0, "occlusion never brightens");
}
