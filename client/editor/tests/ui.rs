//! The editor's UI logic without a window (egui_kittest drives the egui UI with synthetic input through its
//! accessibility tree): typing re-parses and updates the diagnostics (gutter and list), a broken edit keeps the
//! previous model, a parameter slider changes the amplified stream's hash and nothing else, and the stats are
//! measured off the UI thread for the current model only.

use canopy_editor::{Editor, EditorUi};
use egui::accesskit::Role;
use egui_kittest::Harness;
use egui_kittest::kittest::Queryable;

/// The worm, one statement per line so an edit at the start of a line breaks exactly that line.
const WORM: &str = "species Worm\nparam c = 4\nparam unused = 2\n\ndef Worm select(c > 0) {\n  separator {\n    \
                    material(0.9, 0.5, 0.2)\n    rotz(-90)\n    cone(0.5, 0, 1)\n  }\n  separator {\n    \
                    material(0.3, 0.7, 0.3)\n    sphere(0.5)\n    translate(1, 0, 0)\n    calc { c = c - 1 }\n    \
                    recurse { use Worm }\n  }\n}\n";

/// Put the text cursor at the start of the text (up past every line, then home).
fn to_text_start(h: &mut Harness<'static, EditorUi>) {
    for _ in 0..WORM.lines().count() {
        h.key_press(egui::Key::ArrowUp);
    }
    h.key_press(egui::Key::Home);
    h.run();
}

fn harness() -> Harness<'static, EditorUi> {
    let model = Editor::from_source("worm.species", WORM).expect("a species name");
    assert!(model.diagnostics().is_empty(), "{:?}", model.diagnostics());
    Harness::builder()
        .with_size(egui::vec2(1200.0, 800.0))
        .build_ui_state(|ui, state: &mut EditorUi| state.show(ui, None), EditorUi::new(model))
}

#[test]
fn typing_reparses_updates_diagnostics_and_a_broken_edit_keeps_the_model() {
    let mut h = harness();
    h.run();
    let hash = h.state().model.amplified().expect("amplified").hash;
    let revision = h.state().model.revision();
    assert!(h.query_by_label("no problems").is_some());

    // Type at the start of the text: `species Worm` becomes `oops species Worm`.
    h.get_by_role(Role::MultilineTextInput).click();
    h.run();
    to_text_start(&mut h);
    h.get_by_role(Role::MultilineTextInput).type_text("oops ");
    h.run();
    h.run_steps(4); // past the debounce
    let state = h.state();
    assert!(state.model.text().starts_with("oops species Worm"), "{:?}", &state.model.text()[..20]);
    let d = state.model.diagnostics();
    assert!(!d.is_empty(), "a broken edit is reported");
    assert_eq!((d[0].line, d[0].col), (1, 1), "{d:?}");
    assert_eq!(state.model.amplified().expect("kept").hash, hash, "the last good model stays");
    assert_eq!(state.model.revision(), revision, "the preview is not asked to change");
    assert!(h.query_by_label_contains("problem(s)").is_some(), "the list shows it");
    assert!(h.query_by_label_contains("1:1: ").is_some(), "listed at line:col");
    assert!(h.query_by_label("showing the last good model").is_some());

    // Delete it again: the text parses, the diagnostics clear, the same tree is back.
    for _ in 0.."oops ".len() {
        h.key_press(egui::Key::Backspace);
    }
    h.run_steps(4);
    let state = h.state();
    assert_eq!(state.model.text(), WORM);
    assert!(state.model.diagnostics().is_empty(), "{:?}", state.model.diagnostics());
    assert_eq!(state.model.amplified().expect("amplified").hash, hash);
    assert!(h.query_by_label("no problems").is_some());

    // A real change to the model re-amplifies: `param c = 4` → `param c = 49` is a longer worm.
    h.get_by_role(Role::MultilineTextInput).click();
    h.run();
    to_text_start(&mut h);
    h.key_press(egui::Key::ArrowDown);
    h.key_press(egui::Key::End);
    h.get_by_role(Role::MultilineTextInput).type_text("9");
    h.run_steps(4);
    let state = h.state();
    assert!(state.model.text().contains("param c = 49"), "{}", state.model.text());
    assert!(state.model.diagnostics().is_empty());
    let a = state.model.amplified().expect("amplified");
    assert_ne!(a.hash, hash);
    assert_eq!(a.stream.primitives.len(), 50, "49 spheres and a cone");
}

#[test]
fn a_parameter_slider_changes_the_stream_hash_and_only_that() {
    let mut h = harness();
    h.run();
    let before = {
        let s = h.state();
        let m = &s.model;
        (
            m.text().to_string(),
            m.diagnostics().to_vec(),
            m.species().expect("species").graph.encode(),
            m.amplified().expect("amplified").hash,
            m.params(),
            m.seed(),
        )
    };
    let c = before.4.iter().find(|p| p.name == "c").expect("c").value;
    assert_eq!(c, 4.0);
    h.get_by_role_and_label(Role::Slider, "c").set_value_accesskit(6.0);
    h.run();
    let s = h.state();
    let m = &s.model;
    assert_eq!(m.text(), before.0, "the text is untouched");
    assert_eq!(m.diagnostics(), &before.1[..]);
    assert_eq!(m.species().expect("species").graph.encode(), before.2, "the species is the same");
    assert_eq!(m.seed(), before.5);
    assert_ne!(m.amplified().expect("amplified").hash, before.3, "the stream changed");
    assert_eq!(m.amplified().expect("amplified").stream.primitives.len(), 7, "6 spheres and a cone");
    let after = m.params();
    for (p, q) in before.4.iter().zip(&after) {
        if p.name == "c" {
            assert_eq!((q.value, q.overridden), (6.0, true));
        } else {
            assert_eq!((p.value, p.overridden), (q.value, q.overridden), "{} moved", p.name);
        }
    }
    assert_eq!(m.instance_line(), "instance worm at 0 0 c=6");
}

#[test]
fn the_stats_panel_measures_off_the_ui_thread_and_drops_stale_results() {
    let mut h = harness();
    h.run();
    h.state_mut().wait_for_stats(std::time::Duration::from_secs(60));
    let (rev, hash) = {
        let s = h.state();
        let (rev, stats) = s.stats().expect("measured");
        assert_eq!(rev, s.model.revision());
        let hash = stats.as_ref().expect("amplifies").stream_hash;
        assert_eq!(hash, s.model.amplified().expect("amplified").hash);
        (rev, hash)
    };
    h.get_by_role_and_label(Role::Slider, "c").set_value_accesskit(9.0);
    // One frame (a `run` could step the UI's clock past the stats delay): it takes the change and does not measure.
    h.step();
    {
        // The panel still holds the old revision's numbers.
        let s = h.state();
        assert!(s.model.revision() > rev);
        assert_eq!(s.stats().expect("the old numbers").0, rev);
        assert!(s.stats_pending());
    }
    assert!(h.query_by_label_contains("measuring…").is_some(), "the panel says the numbers are stale");
    h.state_mut().wait_for_stats(std::time::Duration::from_secs(60));
    let s = h.state();
    let (now, stats) = s.stats().expect("measured");
    assert_eq!(now, s.model.revision());
    let stats = stats.as_ref().expect("amplifies");
    assert_ne!(stats.stream_hash, hash);
    assert_eq!(stats.stream_hash, s.model.amplified().expect("amplified").hash);
    assert_eq!(stats.primitives, 10, "9 spheres and a cone");
    assert!(!s.stats_pending());
}

/// The far view splits the preview in two: the tree is framed again for its half-width picture, so its bounding
/// sphere fits the narrower horizontal field of view (it was cropped, framed for the full width).
#[test]
fn the_split_far_view_frames_the_tree_for_its_narrower_picture() {
    let mut h = harness();
    h.run();
    let full = h.state().orbit.distance;
    h.state_mut().view = canopy_editor::ui::View::FarField;
    h.run();
    let ui = h.state();
    let [w, ht] = ui.preview_px;
    let aspect = w as f32 / ht as f32;
    assert!(aspect < 1.0, "the split picture is narrower than tall here ({w} x {ht})");
    let (lo, hi) = ui.model_bounds().expect("a model");
    let r = (0..3).map(|i| (hi[i] - lo[i]).powi(2)).sum::<f32>().sqrt() / 2.0;
    let half_h = (22.5f32.to_radians().tan() * aspect).atan();
    assert!(r.max(0.5) / ui.orbit.distance <= half_h.sin(), "the sphere fits the horizontal field");
    assert!(ui.orbit.distance > full, "farther than for the full-width picture ({} vs {full})", ui.orbit.distance);
}
