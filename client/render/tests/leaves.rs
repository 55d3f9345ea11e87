//! Image tests of leaf cards (issue 33, item 3), offscreen on lavapipe: one large leaf lying flat above flat ground,
//! seen from straight above, the sun low in −x so that its shadow falls beside it, a copy moved along x. The leaf
//! and its shadow both show the procedural silhouette's teeth; the leaf drawn as its polygon, or a shadow cast by
//! the whole card, has straight margins and fails.

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
    let (graph, diagnostics) = parse_species(&SourceFile::new("leaf.species", LEAF));
    let graph = graph.unwrap_or_else(|| panic!("{diagnostics:?}"));
    let scene = Scene::lone(graph, 1, Terrain::flat([-50.0, -50.0], 100.0));
    // Straight down from 7 m over the middle of the leaf and its shadow (2.5 m to +x).
    let camera = Camera::looking_at(Vec3::new(1.25, 7.0, -0.01), Vec3::new(1.25, 0.0, 0.0), 40.0);
    let mut cfg = config(shadows, Wind { strength: 0.0, ..Wind::default() }, 1);
    cfg.lighting.sun_direction = [-1.0, 0.6, 0.0];
    shoot_configured(&scene, &camera, cfg, 0.0, SIZE).0
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
