//! The GPU cull of primitives (`renderer/cull.rs`), run on whatever adapter is present (CI: lavapipe, where
//! `CullPath::Auto` keeps the CPU path, so these tests ask for the GPU's): it draws what the CPU path draws, less
//! what a hill hides, what is out of view or out of a shadow cascade, and (where asked) what is under the smallest
//! size.

use std::time::Duration;

use canopy_render::compare::compare;
use canopy_render::offscreen::{Offscreen, RenderedImage};
use canopy_render::{
    Camera, CullCounts, CullPath, CulledFrame, FrameStats, LodConfig, RenderConfig, Scene, SceneInstance,
};
use canopy_worlds::world::{InstanceId, Terrain};
use glam::Vec3;

const W: u32 = 256;
const H: u32 = 160;

/// A tree at the origin (the library's `species`), and 40 m south of it a ridge 30 m high, 20 m wide, across the
/// whole ground.
fn tree_behind_a_ridge(species: &str) -> Scene {
    let graph = canopy_worlds::library::find(species).expect("library species").load().expect("parses");
    let (n, spacing) = (40u32, 10.0f32);
    let mut heights = Vec::new();
    for j in 0..=n {
        let z = -200.0 + spacing * j as f32;
        for _ in 0..=n {
            heights.push(if (-50.0..=-30.0).contains(&z) { 30.0 } else { 0.0 });
        }
    }
    let ground = Terrain::from_heights([-200.0, -200.0], spacing, [n, n], heights).expect("a ridge");
    Scene::lone(graph, 7, ground)
}

/// Every tree at full detail; the GPU cull as `cull` asks, dropping nothing for its size unless `min_px` says.
fn config(cull: CullPath, min_px: f32) -> RenderConfig {
    RenderConfig {
        lod: LodConfig { near_px: 0.0, far_px: 0.0, cull_px: 0.0, ..LodConfig::default() },
        workers: 2,
        cull,
        prim_cull_px: min_px,
        msaa: 1,
        ..RenderConfig::default()
    }
}

/// The settled frame, its statistics and what the GPU cull counted of the camera's primitives (`None` on the CPU
/// path).
fn shoot(scene: &Scene, camera: &Camera, cfg: RenderConfig) -> (RenderedImage, FrameStats, Option<CullCounts>) {
    let (image, stats, counts) = shoot_all(scene, camera, cfg);
    (image, stats, counts.map(|c| c.camera))
}

/// The same, with what the cull counted of the shadow maps' primitives.
fn shoot_all(scene: &Scene, camera: &Camera, cfg: RenderConfig) -> (RenderedImage, FrameStats, Option<CulledFrame>) {
    let mut off = Offscreen::new(cfg, W, H).unwrap_or_else(|e| panic!("{e}"));
    let counting = off.renderer.count_culled();
    let stats = off.settle(scene, camera, Duration::from_secs(300)).unwrap_or_else(|e| panic!("{e}"));
    let image = off.render().unwrap_or_else(|e| panic!("{e}"));
    let counts = off.renderer.culled();
    assert_eq!(counting, counts.is_some(), "counted where the GPU culls: {counts:?}");
    (image, stats, counts)
}

#[test]
fn a_ridge_hides_the_tree_behind_it_and_the_gpu_draws_none_of_it() {
    let scene = tree_behind_a_ridge("monopodial");
    // From 2 m above the ground 80 m south of the tree: the ridge between hides it.
    let low = Camera::looking_at(Vec3::new(0.0, 2.0, -80.0), Vec3::new(0.0, 8.0, 0.0), 60.0);
    let (cpu, stats, none) = shoot(&scene, &low, config(CullPath::Cpu, 0.0));
    assert!(none.is_none());
    assert!(stats.near == 1 && stats.primitives > 100, "the CPU draws the tree behind the ridge: {stats:?}");
    let (gpu, _, counts) = shoot(&scene, &low, config(CullPath::Gpu, 0.0));
    let counts = counts.expect("the GPU culls");
    assert_eq!(counts.tested, stats.primitives, "{counts:?}");
    assert_eq!(counts.occluded + counts.outside, counts.tested, "every primitive hidden or out of view: {counts:?}");
    assert!(counts.occluded > counts.tested / 2, "{counts:?}");
    assert_eq!(counts.kept(), 0, "{counts:?}");
    let diff = compare(&cpu, &gpu, 0).expect("same size");
    assert_eq!(diff.differing, 0, "the same picture: {diff:?}");

    // From 150 m up the whole tree stands clear of the ridge: the GPU keeps it, and draws what the CPU draws.
    let high = Camera::looking_at(Vec3::new(0.0, 150.0, -80.0), Vec3::new(0.0, 8.0, 0.0), 60.0);
    let (cpu, stats, _) = shoot(&scene, &high, config(CullPath::Cpu, 0.0));
    let (gpu, _, counts) = shoot(&scene, &high, config(CullPath::Gpu, 0.0));
    let counts = counts.expect("the GPU culls");
    assert_eq!((counts.tested, counts.occluded), (stats.primitives, 0), "{counts:?}");
    assert!(counts.kept() > counts.tested / 2, "{counts:?}");
    let diff = compare(&cpu, &gpu, 0).expect("same size");
    assert_eq!(diff.differing, 0, "the same picture: {diff:?}");

    // From 60 m up the crown shows over the ridge and the trunk's foot does not: the GPU drops the foot alone.
    let half = Camera::looking_at(Vec3::new(0.0, 60.0, -80.0), Vec3::new(0.0, 8.0, 0.0), 60.0);
    let (cpu, stats, _) = shoot(&scene, &half, config(CullPath::Cpu, 0.0));
    let (gpu, _, counts) = shoot(&scene, &half, config(CullPath::Gpu, 0.0));
    let counts = counts.expect("the GPU culls");
    assert!(counts.occluded > 0 && counts.kept() > counts.tested / 2, "{counts:?} of {stats:?}");
    let diff = compare(&cpu, &gpu, 0).expect("same size");
    assert_eq!(diff.differing, 0, "the same picture: {diff:?}");
}

#[test]
fn a_stand_whose_crowns_show_over_the_ridge_is_drawn_as_the_cpu_draws_it() {
    // 36 trees behind the ridge, near and mid levels of every size, their crowns cut by the ridge's line: the
    // pyramid is read at every level in one dispatch (a texture's mip levels read this way came out wrong on
    // lavapipe; the pyramid is a buffer for that).
    let mut scene = tree_behind_a_ridge("monopodial");
    let first = scene.instances[0].clone();
    scene.instances = (0..36u64)
        .map(|k| SceneInstance {
            id: InstanceId(k),
            position: [-50.0 + 20.0 * (k % 6) as f32, 0.0, 10.0 * (k / 6) as f32],
            seed: 100 + k,
            ..first.clone()
        })
        .collect();
    let camera = Camera::looking_at(Vec3::new(5.0, 40.0, -75.0), Vec3::new(0.0, 14.0, 30.0), 60.0);
    let lod = LodConfig { near_px: 38.0, far_px: 2.0, cull_px: 0.0, ..LodConfig::default() };
    let (cpu, stats, _) = shoot(&scene, &camera, RenderConfig { lod: lod.clone(), ..config(CullPath::Cpu, 0.0) });
    let (gpu, _, counts) = shoot(&scene, &camera, RenderConfig { lod, ..config(CullPath::Gpu, 0.0) });
    let counts = counts.expect("the GPU culls");
    assert!(stats.near >= 1 && stats.mid >= 10, "{stats:?}");
    assert!(counts.occluded > counts.tested / 10 && counts.kept() > counts.tested / 10, "{counts:?}");
    let diff = compare(&cpu, &gpu, 0).expect("same size");
    assert_eq!(diff.differing, 0, "the same picture: {diff:?}");
}

#[test]
fn primitives_out_of_view_and_under_the_smallest_size_are_dropped_from_the_view_and_the_shadow_maps() {
    let scene = tree_behind_a_ridge("monopodial");
    // Close to the trunk, looking up past it: much of the crown is out of view.
    let near = Camera::looking_at(Vec3::new(3.0, 2.0, -4.0), Vec3::new(8.0, 9.0, 4.0), 60.0);
    let (cpu, stats, _) = shoot(&scene, &near, config(CullPath::Cpu, 0.0));
    let (gpu, _, frame) = shoot_all(&scene, &near, config(CullPath::Gpu, 0.0));
    let CulledFrame { camera: counts, shadows } = frame.expect("the GPU culls");
    assert_eq!(counts.tested, stats.primitives);
    assert_eq!(shadows.tested, stats.shadow_primitives, "{shadows:?}");
    assert!(counts.outside > counts.tested / 10 && counts.kept() > 0, "{counts:?}");
    assert_eq!(counts.small, 0, "{counts:?}");
    let diff = compare(&cpu, &gpu, 0).expect("same size");
    assert_eq!(diff.differing, 0, "dropping what is out of view changes nothing: {diff:?}");

    // From 150 m the tree straddles two shadow cascades: each draws only the primitives in its box, and the
    // shadows are the same.
    let far = Camera::looking_at(Vec3::new(0.0, 40.0, 150.0), Vec3::new(0.0, 8.0, 0.0), 60.0);
    let (cpu, stats, _) = shoot(&scene, &far, config(CullPath::Cpu, 0.0));
    let (gpu, _, frame) = shoot_all(&scene, &far, config(CullPath::Gpu, 0.0));
    let shadows = frame.expect("the GPU culls").shadows;
    assert_eq!(shadows.tested, stats.shadow_primitives, "{shadows:?}");
    assert!(shadows.outside > 0 && shadows.kept() > shadows.tested / 2 && shadows.small == 0, "{shadows:?}");
    let diff = compare(&cpu, &gpu, 0).expect("same size");
    assert_eq!(diff.differing, 0, "the same picture: {diff:?}");

    // And there the twigs are under a pixel: dropped, with the picture about the same; into the shadow maps, those
    // under a texel of their cascade.
    let (gpu, _, frame) = shoot_all(&scene, &far, config(CullPath::Gpu, RenderConfig::default().prim_cull_px));
    let CulledFrame { camera: counts, shadows } = frame.expect("the GPU culls");
    assert!(counts.small > counts.tested / 10, "{counts:?}");
    assert!(shadows.small > 0, "{shadows:?}");
    let diff = compare(&cpu, &gpu, 24).expect("same size");
    eprintln!("{counts:?}, shadows {shadows:?}; {diff:?}");
    assert!(diff.mean < 0.5 && diff.fraction < 0.01, "{diff:?}");
}
