//! Image tests of leaf cards (issue 33, item 3), offscreen on lavapipe: one large leaf lying flat above flat ground,
//! seen from straight above, the sun low in −x so that its shadow falls beside it, a copy moved along x. The leaf
//! and its shadow both show the procedural silhouette's teeth; the leaf drawn as its polygon, or a shadow cast by
//! the whole card, has straight margins and fails. Multisampled, the margins are the blade's coverage of each pixel
//! (alpha-to-coverage), near a supersampled picture; a cut a whole pixel at a time fails.

use canopy_render::offscreen::RenderedImage;
use canopy_render::{Camera, Scene, Shadows, Wind};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::species_text::parse_species;
use canopy_worlds::world::Terrain;
use glam::Vec3;

use canopy_render::compare::{Tolerance, check_reference};

use super::sun::{config, darker, reference, shoot_configured};

/// One red leaf, 2.4 m long and 1.8 m wide (the bush's leaf shape), lying flat 1.5 m above the ground, its tip
/// toward +z.
const LEAF: &str = "species Leaf
material(0.8, 0.12, 0.1)
translate(0, 1.5, -1.2)
leaf((0, 0, 0), (0.8, 0, 0.6), (0.9, 0, 1.5), (0, 0, 2.4), (-0.9, 0, 1.5), (-0.8, 0, 0.6))
";

const SIZE: (u32, u32) = (320, 240);

fn shot(shadows: Shadows) -> RenderedImage {
    shot_sampled(shadows, 1, SIZE)
}

/// The leaf with `msaa` samples a pixel, at `size`.
fn shot_sampled(shadows: Shadows, msaa: u32, size: (u32, u32)) -> RenderedImage {
    let (graph, diagnostics) = parse_species(&SourceFile::new("leaf.species", LEAF));
    let graph = graph.unwrap_or_else(|| panic!("{diagnostics:?}"));
    let scene = Scene::lone(graph, 1, Terrain::flat([-50.0, -50.0], 100.0));
    // Straight down from 7 m over the middle of the leaf and its shadow (2.5 m to +x).
    let camera = Camera::looking_at(Vec3::new(1.25, 7.0, -0.01), Vec3::new(1.25, 0.0, 0.0), 40.0);
    let mut cfg = config(shadows, Wind { strength: 0.0, ..Wind::default() }, msaa);
    cfg.lighting.sun_direction = [-1.0, 0.6, 0.0];
    shoot_configured(&scene, &camera, cfg, 0.0, size).0
}

/// Teeth along a shape's margins: rows where its width (pixels of `mask` in the row) changes by `jump` or more
/// from the row before, both rows inside the shape. A polygon's straight margins change it a few pixels a row.
fn teeth(mask: impl Fn(u32, u32) -> bool, jump: i32) -> (usize, Vec<i32>) {
    let widths: Vec<i32> = (0..SIZE.1).map(|y| (0..SIZE.0).filter(|&x| mask(x, y)).count() as i32).collect();
    let n = widths.windows(2).filter(|w| w[0] > 0 && w[1] > 0 && (w[1] - w[0]).abs() >= jump).count();
    (n, widths)
}

#[test]
fn a_leaf_card_and_its_shadow_show_the_toothed_silhouette() {
    let shadows = Shadows { resolution: 2048, distance: 40.0 };
    let (lit, bare) = (shot(shadows), shot(Shadows { resolution: 0, ..shadows }));
    let red = |p: &[u8]| i32::from(p[0]) > 100 && i32::from(p[0]) > i32::from(p[1]) + 50;
    let (leaf, widths) = teeth(|x, y| red(&lit.pixel(x, y)), 6);
    eprintln!("leaf: {leaf} teeth, widths {widths:?}");
    let sum = |p: &[u8]| p[..3].iter().map(|&c| i32::from(c)).sum::<i32>();
    let shade = |x: u32, y: u32| sum(&bare.pixel(x, y)) - sum(&lit.pixel(x, y)) >= 60;
    let (shadow, widths) = teeth(shade, 6);
    eprintln!("shadow: {shadow} teeth, widths {widths:?}");
    assert!(darker(&bare, &lit, 60) < 0.001, "a shadow never brightens");
    assert!(leaf >= 4, "the leaf's margins are straight: {leaf} teeth");
    assert!(shadow >= 4, "the shadow's margins are straight: {shadow} teeth");
    check_reference(&lit, &reference("leaf-card.png"), &Tolerance::default()).unwrap_or_else(|e| panic!("{e}"));
}

/// The mean absolute difference (RGB, 0..255) of `img` from `big` averaged over `k × k` blocks, over the pixels
/// whose block is part leaf and part ground (the margin).
fn off_at_margin(img: &RenderedImage, big: &RenderedImage, k: u32, leaf: impl Fn(&[u8]) -> bool) -> (f64, usize) {
    let (mut total, mut n) = (0.0, 0);
    for y in 0..img.height {
        for x in 0..img.width {
            let block: Vec<[u8; 4]> =
                (0..k * k).map(|i| big.pixel(x * k + i % k, y * k + i / k)).map(|p| [p[0], p[1], p[2], p[3]]).collect();
            let on = block.iter().filter(|p| leaf(&p[..])).count();
            if on == 0 || on == block.len() {
                continue;
            }
            for c in 0..3 {
                let mean = block.iter().map(|p| f64::from(p[c])).sum::<f64>() / block.len() as f64;
                total += (mean - f64::from(img.pixel(x, y)[c])).abs();
            }
            n += 1;
        }
    }
    (total / (3 * n.max(1)) as f64, n)
}

#[test]
fn multisampled_a_leaf_cards_edge_is_its_coverage() {
    // No shadow (its edges are the shadow map's, alike at any sample count): the leaf's margins are the only edges,
    // all of them cut by the fragment shader, none a triangle's.
    let shadows = Shadows { resolution: 0, distance: 40.0 };
    let (one, four) = (shot_sampled(shadows, 1, SIZE), shot_sampled(shadows, 4, SIZE));
    let big = shot_sampled(shadows, 1, (4 * SIZE.0, 4 * SIZE.1));
    let red = |p: &[u8]| i32::from(p[0]) > 100 && i32::from(p[0]) > i32::from(p[1]) + 50;
    let ((a, n), (b, _)) = (off_at_margin(&one, &big, 4, red), off_at_margin(&four, &big, 4, red));
    eprintln!("at the margin ({n} pixels), mean difference from 16 samples a pixel: {a:.1} at 1 sample, {b:.1} at 4");
    assert!(n > 200, "{n} pixels at the margin");
    // A cut a whole pixel at a time is as far from the supersampled margin at 4 samples as at 1.
    assert!(b < 0.75 * a, "{a:.1} → {b:.1}");
}
