//! The editor window rendered offscreen (what `canopy species edit FILE --screenshot out.png` does) on whatever
//! Vulkan adapter there is — Mesa's lavapipe without a GPU (CI installs `mesa-vulkan-drivers`) — and compared with a
//! committed reference PNG by the renderer's image comparison (`NAME-actual.png` and `NAME-difference.png` are
//! written beside the reference on failure; `CANOPY_BLESS=1` writes a missing reference).

use std::path::PathBuf;

use canopy_editor::EditConfig;
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
    canopy_editor::screenshot::render(&mut ui, cfg.size).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn the_editor_window_matches_its_reference_and_follows_a_parameter() {
    let img = shot(&[("height", 14.0)], View::Tree);
    // The stats panel prints traversal times, which differ run to run: a few hundred pixels of text.
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
