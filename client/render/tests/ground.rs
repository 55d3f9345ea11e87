//! The terrain as a function, drawn: the embedded large world `highlands` (a fractal ground, no height grid) seen
//! from altitude, offscreen on whatever wgpu adapter is present (CI: Mesa lavapipe). The renderer builds the
//! window of lattice squares around the camera itself; the picture must show ground, not only sky
//! (`CANOPY_GROUND_PNG=path` saves it).

use std::time::Duration;

use canopy_render::offscreen::render_still;
use canopy_render::{Camera, RenderConfig, Scene};
use canopy_worlds::world::{Ground, World};
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
