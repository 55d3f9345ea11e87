//! Image tests of the level-of-detail cross-fade (issue 33, item 5), offscreen on lavapipe: a tree half-way from
//! full detail to its first substitute, against the mean of the two levels drawn alone from the same place. With one
//! sample a pixel the fade is a checkerboard of whole pixels, each one level or the other; multisampled, each pixel
//! keeps half its samples of either level and is resolved to their mean. A dither cut a whole pixel at a time under
//! multisampling fails.

use std::time::Duration;

use canopy_render::offscreen::{Offscreen, RenderedImage};
use canopy_render::{Camera, LodConfig, RenderConfig, Shadows, Wind};
use glam::Vec3;

use super::sun::{config, tree};

const SIZE: (u32, u32) = (256, 192);
const SETTLE: Duration = Duration::from_secs(300);

/// Looking at the tree from `distance` metres, always from the same side.
fn camera(distance: f32) -> Camera {
    let target = Vec3::new(0.0, 5.0, 0.0);
    let from = target + Vec3::new(-0.55, 0.35, -0.76).normalize() * distance;
    Camera::looking_at(from, target, 40.0)
}

/// The tests' renderer with full detail from `near_px` pixels up: `msaa` samples a pixel, no shadow, still air.
fn renderer(near_px: f32, msaa: u32) -> Offscreen {
    let still = Wind { strength: 0.0, ..Wind::default() };
    let mut cfg: RenderConfig = config(Shadows { resolution: 0, ..Shadows::default() }, still, msaa);
    cfg.lod = LodConfig { near_px, far_px: near_px.min(10.0) / 2.0, ..cfg.lod };
    Offscreen::new(cfg, SIZE.0, SIZE.1).unwrap_or_else(|e| panic!("{e}"))
}

/// The tree from far away (`FAR`) at full detail, at its substitute, and half-way through the fade from the first
/// to the second as the camera moves there from near (`NEAR`).
fn pictures(msaa: u32) -> [RenderedImage; 3] {
    const NEAR: f32 = 20.0;
    const FAR: f32 = 60.0;
    // Full detail from 200 px: the tree is well above it from 20 m and well below from 60 m.
    const NEAR_PX: f32 = 200.0;
    let scene = tree();
    let settled = |near_px: f32, level: fn(&canopy_render::FrameStats) -> usize| {
        let mut off = renderer(near_px, msaa);
        let stats = off.settle(&scene, &camera(FAR), SETTLE).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(level(&stats), 1, "{stats:?}");
        off.render().unwrap_or_else(|e| panic!("{e}"))
    };
    let detail = settled(1.0, |s| s.near);
    let substitute = settled(NEAR_PX, |s| s.mid);

    let mut off = renderer(NEAR_PX, msaa);
    // Both levels built first, so the fade starts as soon as the level wanted changes.
    off.settle(&scene, &camera(FAR), SETTLE).unwrap_or_else(|e| panic!("{e}"));
    let near = off.settle(&scene, &camera(NEAR), SETTLE).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(near.near, 1, "{near:?}");
    off.renderer.set_instant_transitions(false);
    let fade = LodConfig::default().fade_seconds;
    let stats = off.renderer.update(&scene, &camera(FAR), 0.5 * fade);
    // The substitute is the level shown; full detail, fading out, is drawn too.
    assert_eq!((stats.near, stats.mid), (0, 1), "{stats:?}");
    assert!(stats.primitives > near.primitives && stats.mesh_triangles >= near.mesh_triangles, "{stats:?}");
    let fading = off.render().unwrap_or_else(|e| panic!("{e}"));
    [detail, substitute, fading]
}

/// The mean absolute difference (RGB, 0..255) of `fading` from the mean of `a` and `b`, over the pixels where `a`
/// and `b` differ by at least 60 (summed RGB); and how many those are.
fn off_the_mean(a: &RenderedImage, b: &RenderedImage, fading: &RenderedImage) -> (f64, usize) {
    let (mut total, mut n) = (0.0, 0);
    for ((p, q), f) in a.rgba.chunks_exact(4).zip(b.rgba.chunks_exact(4)).zip(fading.rgba.chunks_exact(4)) {
        let apart: i32 = (0..3).map(|c| (i32::from(p[c]) - i32::from(q[c])).abs()).sum();
        if apart < 60 {
            continue;
        }
        for c in 0..3 {
            total += ((f64::from(p[c]) + f64::from(q[c])) / 2.0 - f64::from(f[c])).abs();
        }
        n += 1;
    }
    (total / (3 * n.max(1)) as f64, n)
}

#[test]
fn multisampled_a_cross_fade_blends_each_pixel() {
    let [a, b, one] = pictures(1);
    let (e1, n) = off_the_mean(&a, &b, &one);
    let [a, b, four] = pictures(4);
    let (e4, n4) = off_the_mean(&a, &b, &four);
    eprintln!(
        "half-way through the fade, where the levels differ ({n} and {n4} pixels): off their mean by {e1:.1} at 1 sample, {e4:.1} at 4"
    );
    assert!(n > 300 && n4 > 300, "the two levels differ in only {n} and {n4} pixels");
    // One sample a pixel: each of those pixels is one level or the other, half their difference off the mean.
    assert!(e1 > 15.0, "{e1:.1}");
    // Four: half the samples of each level, their mean.
    assert!(e4 < 0.4 * e1, "{e1:.1} → {e4:.1}");
}
