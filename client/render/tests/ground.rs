//! The terrain as a function, drawn: the embedded large world `highlands` (a fractal ground, no height grid) seen
//! from altitude, offscreen on whatever wgpu adapter is present (CI: Mesa lavapipe). The renderer builds the
//! window of lattice squares around the camera itself; the picture must show ground, not only sky
//! (`CANOPY_GROUND_PNG=path` saves it). The land reads from the air: the world's cover colours it (rock past the
//! tree line, snow on the heights; `CANOPY_COVER_PNG=dir` saves those views), and the haze thins with height.

use std::sync::Arc;
use std::time::Duration;

use canopy_render::offscreen::render_still;
use canopy_render::{Camera, RenderConfig, RenderedImage, Scene};
use canopy_worlds::world::{Ground, Terrain, World};
use glam::Vec3;

#[test]
fn highlands_from_altitude_shows_fractal_ground() {
    let world = World::embedded("highlands").expect("embedded");
    let scene = Scene::from_world(&world);
    assert!(matches!(scene.ground, Ground::Fractal(_)), "the highlands' ground is its fractal");
    let (x, z) = (2_000.0, -30_000.0);
    let eye = Vec3::new(x, world.height(x, z) + 3_000.0, z);
    let target = Vec3::new(x + 200.0, world.height(x + 200.0, z + 8_000.0), z + 8_000.0);
    let camera = Camera::looking_at(eye, target, 60.0);
    let mut cfg = RenderConfig { workers: 1, ..RenderConfig::default() };
    cfg.lighting.fog_density = 0.0;
    let (image, stats) = render_still(cfg, &scene, &camera, 160, 100, Duration::from_secs(300))
        .unwrap_or_else(|e| panic!("offscreen render failed: {e}"));
    if let Some(path) = std::env::var_os("CANOPY_GROUND_PNG") {
        image.save_png(std::path::Path::new(&path)).expect("saved");
    }
    assert!(stats.terrain_triangles > 0, "{stats:?}");
    // Ground is green to grey (green above blue); the sky is blue above green.
    let ground = |p: [u8; 4]| i32::from(p[1]) > i32::from(p[2]) + 8;
    let mut count = 0;
    for y in 0..image.height {
        for x in 0..image.width {
            count += u32::from(ground(image.pixel(x, y)));
        }
    }
    let total = image.width * image.height;
    assert!(count > total / 4, "{count} of {total} pixels are ground");
    let bottom = (0..image.width).filter(|&x| ground(image.pixel(x, image.height - 1))).count();
    assert!(bottom as u32 > image.width * 9 / 10, "the bottom row looks down on the ground: {bottom}");
}

/// The highlands' world, drawn with its ground's cover and without, from `eye` toward `target` (heights above the
/// ground there), 160 × 100; saved as `NAME.png` and `NAME-uncovered.png` in `CANOPY_COVER_PNG=dir`.
fn highlands_cover_shots(name: &str, eye: [f32; 3], target: [f32; 3]) -> (RenderedImage, RenderedImage) {
    let world = World::embedded("highlands").expect("embedded");
    let at = |p: [f32; 3]| Vec3::new(p[0], world.height(p[0], p[2]) + p[1], p[2]);
    let camera = Camera::looking_at(at(eye), at(target), 60.0);
    let cfg = RenderConfig { workers: 1, ..RenderConfig::default() };
    let shot = |scene: &Scene| {
        render_still(cfg.clone(), scene, &camera, 160, 100, Duration::from_secs(300))
            .unwrap_or_else(|e| panic!("offscreen render failed: {e}"))
            .0
    };
    let covered = Scene::from_world(&world);
    assert!(covered.cover.is_some(), "a world's scene carries its cover");
    let bare = Scene { cover: None, ..covered.clone() };
    let (covered, bare) = (shot(&covered), shot(&bare));
    if let Some(dir) = std::env::var_os("CANOPY_COVER_PNG") {
        let dir = std::path::Path::new(&dir);
        covered.save_png(&dir.join(format!("{name}.png"))).expect("saved");
        bare.save_png(&dir.join(format!("{name}-uncovered.png"))).expect("saved");
    }
    (covered, bare)
}

/// Pixels of the rows `from..` (of 100) that `f` counts.
fn count_below(img: &RenderedImage, from: u32, f: impl Fn([u8; 4]) -> bool) -> u32 {
    (from..img.height).flat_map(|y| (0..img.width).map(move |x| (x, y))).filter(|&(x, y)| f(img.pixel(x, y))).count()
        as u32
}

/// Grey ground: rock and scree (no channel leads by much; green and sky blue do).
fn grey(p: [u8; 4]) -> bool {
    let (r, g, b) = (i32::from(p[0]), i32::from(p[1]), i32::from(p[2]));
    (g - b).abs() < 16 && (r - g).abs() < 16 && g < 200
}

/// Snow: white.
fn white(p: [u8; 4]) -> bool {
    p[..3].iter().all(|&c| c > 200) && p[..3].iter().max().unwrap() - p[..3].iter().min().unwrap() < 24
}

#[test]
fn past_the_tree_line_the_highlands_are_rock_and_on_the_heights_snow() {
    // Toward the southern massif from 1,500 m: forest below the tree line (1,280 m), rock and scree above.
    let (covered, bare) = highlands_cover_shots("rock", [2_000.0, 1_500.0, -30_000.0], [1_000.0, 0.0, -40_000.0]);
    let (rock, rock_without) = (count_below(&covered, 45, grey), count_below(&bare, 45, grey));
    assert!(rock > 800 && rock_without < 50, "rock pixels: {rock} with the cover, {rock_without} without");
    // Up on the northern heights (1,600 m and more, above the snow line at 1,500 m): snow.
    let (snowy, green) = highlands_cover_shots("snow", [0.0, 300.0, 33_500.0], [0.0, 0.0, 38_400.0]);
    let (snow, snow_without) = (count_below(&snowy, 60, white), count_below(&green, 60, white));
    assert!(snow > 2_000 && snow_without < 50, "snow pixels: {snow} with the cover, {snow_without} without");
}

/// A flat plateau 8 km across at `height`, seen from 300 m above it toward a point 3 km away, with the haze's scale
/// height `haze_height`: the colour at the image's centre (the plateau's ground).
fn plateau(height: f32, haze_height: f32) -> [u8; 4] {
    let heights = vec![height; 25];
    let ground = Terrain::from_heights([-4_000.0, -4_000.0], 2_000.0, [4, 4], heights).expect("a plateau");
    let scene = Scene::empty(Arc::new(ground));
    let camera = Camera::looking_at(Vec3::new(0.0, height + 300.0, -2_000.0), Vec3::new(0.0, height, 1_000.0), 60.0);
    let mut cfg = RenderConfig { workers: 1, ..RenderConfig::default() };
    cfg.lighting.haze_height = haze_height;
    let (image, _) = render_still(cfg, &scene, &camera, 64, 40, Duration::from_secs(300))
        .unwrap_or_else(|e| panic!("offscreen render failed: {e}"));
    image.pixel(32, 20)
}

#[test]
fn the_haze_thins_with_height_so_valleys_are_hazier_than_ridges() {
    let haze = RenderConfig::default().lighting.sky_horizon.map(|c| (c.powf(1.0 / 2.2) * 255.0) as i32);
    // How far a pixel is from the colour of thick haze (the horizon's): more haze, nearer.
    let clear = |p: [u8; 4]| (0..3).map(|i| (i32::from(p[i]) - haze[i]).abs()).sum::<i32>();
    let h = RenderConfig::default().lighting.haze_height;
    assert!(h > 0.0, "the default haze thins with height");
    let (low, high) = (plateau(0.0, h), plateau(1_500.0, h));
    assert!(clear(high) > clear(low) + 30, "at 1,500 m {high:?} is clearer than at sea level {low:?}");
    // Where the haze is the same at every height the two look alike.
    let (low, high) = (plateau(0.0, 0.0), plateau(1_500.0, 0.0));
    assert!((clear(high) - clear(low)).abs() <= 6, "uniform haze: {high:?} and {low:?}");
}
