//! The editor window rendered offscreen (what `canopy species edit FILE --screenshot out.png` does) on whatever
//! Vulkan adapter there is — Mesa's lavapipe without a GPU (CI installs `mesa-vulkan-drivers`) — and compared with a
//! committed reference PNG by the renderer's image comparison (`NAME-actual.png` and `NAME-difference.png` are
//! written beside the reference on failure; `CANOPY_BLESS=1` writes a missing reference). Also on that adapter: the
//! ground grid is drawn, and a `nearfield(…)` species is drawn as its continuous mesh or as primitives by the toggle.

use std::path::PathBuf;

use canopy_editor::EditConfig;
use canopy_editor::grid::GridLayout;
use canopy_editor::preview::has_nearfield;
use canopy_editor::screenshot::{Headless, SETTLE};
use canopy_editor::ui::{EditorUi, View};
use canopy_render::compare::{Tolerance, check_reference, compare};

fn reference(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/reference").join(name)
}

fn shot(params: &[(&str, f32)], view: View) -> canopy_render::RenderedImage {
    let cfg = EditConfig {
        file: Some(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../worlds/species/monopodial.species")),
        params: params.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
        seed: 3,
        size: (960, 600),
        view,
        ..EditConfig::default()
    };
    let mut ui = EditorUi::open(&cfg).expect("opens");
    // Times measured differ run to run (and under load): dashes in their place.
    ui.show_times = false;
    canopy_editor::screenshot::render(&mut ui, cfg.size).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn the_editor_window_matches_its_reference_and_follows_a_parameter() {
    let img = shot(&[("height", 14.0)], View::Tree);
    let t = Tolerance { max_fraction: 0.01, ..Tolerance::default() };
    check_reference(&img, &reference("monopodial-window.png"), &t).unwrap_or_else(|e| panic!("{e}"));
    // The preview really draws the tree: a taller one changes the picture well beyond the tolerance.
    let taller = shot(&[("height", 24.0)], View::Tree);
    let c = compare(&img, &taller, t.channel).expect("same size");
    assert!(c.fraction > 0.03, "a taller tree looks the same: {c:?}");
}

#[test]
fn the_far_field_view_matches_its_reference() {
    let img = shot(&[("height", 14.0)], View::FarField);
    let t = Tolerance { max_fraction: 0.01, ..Tolerance::default() };
    check_reference(&img, &reference("monopodial-far.png"), &t).unwrap_or_else(|e| panic!("{e}"));
}

/// The preview of `ui` settled on a fresh headless GPU: the renderer's statistics of its last frame.
fn settled_stats(ui: &mut EditorUi) -> canopy_render::FrameStats {
    let mut h = Headless::new((640, 400)).unwrap_or_else(|e| panic!("{e}"));
    h.settle(ui, SETTLE).unwrap_or_else(|e| panic!("{e}"));
    h.preview.stats.clone()
}

#[test]
fn the_ground_grid_is_drawn_and_the_near_field_toggle_switches_mesh_and_primitives() {
    let cfg = EditConfig {
        file: Some(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../worlds/species/fig.species")),
        size: (640, 400),
        ..EditConfig::default()
    };
    let mut ui = EditorUi::open(&cfg).expect("opens");
    let species = ui.model.species().expect("fig parses").clone();
    assert!(has_nearfield(&species.graph), "fig declares nearfield(…)");
    let prims = ui.model.amplified().expect("amplified").stream.primitives.len() as u64;
    let (lo, hi) = ui.model_bounds().expect("bounds");
    let grid = GridLayout::around(lo, hi);
    let grid_boxes = 2 * (u64::from(grid.n) + 1);

    // Near-field mode (the default): the tree is one continuous mesh; the only primitive instances are the grid's.
    assert!(ui.near_field);
    let mesh = settled_stats(&mut ui);
    assert_eq!(mesh.primitives, grid_boxes, "{mesh:?}");
    assert!(mesh.mesh_triangles > 10_000, "{mesh:?}");

    // Primitives: the tree's cones and spheres are instanced (its trunk base is still a mesh), the grid as before.
    ui.near_field = false;
    let direct = settled_stats(&mut ui);
    assert!(direct.primitives > grid_boxes + prims / 2, "{direct:?}");
    assert!(direct.primitives <= grid_boxes + prims, "{direct:?}");
    assert!(direct.mesh_triangles < mesh.mesh_triangles, "{direct:?} vs {mesh:?}");
    // The model itself did not change: the same stream either way.
    assert_eq!(ui.model.species().expect("species").graph.encode(), species.graph.encode());

    // A species without nearfield(…) offers no toggle and is drawn the same either way.
    let mut plain = EditorUi::open(&EditConfig {
        file: Some(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../worlds/species/conifer.species")),
        ..cfg
    })
    .expect("opens");
    assert!(!has_nearfield(&plain.model.species().expect("conifer").graph));
    let a = settled_stats(&mut plain);
    plain.near_field = false;
    let b = settled_stats(&mut plain);
    assert_eq!((a.primitives, a.mesh_triangles), (b.primitives, b.mesh_triangles));
}
