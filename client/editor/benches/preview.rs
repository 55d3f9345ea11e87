//! Keystroke or slider → updated preview, timed (issue 19's numbers), for the monopodial tree and the conifer. A
//! parameter is set on the model to a value not used before (the UI thread amplifies once, for the hash and the
//! parameters; the renderer's cache cannot help), then, each part timed on its own (medians of 11):
//!
//! - *change → model ready*: the preview's renderer is updated, without drawing, until its workers have amplified
//!   the instance, built its geometry and it is uploaded — what a change costs before the GPU draws it;
//! - *one frame*: a whole window frame (the UI, the 3D preview, egui onto a window-sized target) waited for on the
//!   GPU; *change → updated preview* is the two added;
//! - *window loop*: the change again, drawing whole frames until the preview has settled, as the window does (the
//!   workers run while frames are drawn; on a software rasteriser a frame is the larger part);
//! - *idle frame*: a frame with nothing changed (and, as this bench measured before, the preview drawn and the UI
//!   laid out without drawing the window);
//! - *stats*: the stats panel's measurement (traversals, mesh, LOD levels) on its worker thread, off the UI thread.
//!
//! Run: `XDG_RUNTIME_DIR=/tmp/xdg WGPU_BACKEND=vulkan cargo bench -p canopy-editor --bench preview`.

use std::time::{Duration, Instant};

use canopy_editor::EditConfig;
use canopy_editor::screenshot::Headless;
use canopy_editor::ui::EditorUi;

const TIMEOUT: Duration = Duration::from_secs(120);
const RUNS: usize = 11;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../worlds/species");
    for (file, param, values) in
        [("monopodial.species", "height", [18.0f32, 22.0]), ("conifer.species", "height", [14.0, 16.0])]
    {
        let cfg = EditConfig { file: Some(root.join(file)), size: (1280, 800), ..EditConfig::default() };
        let mut ui = EditorUi::open(&cfg).expect("opens");
        let mut h = Headless::new(cfg.size).expect("a GPU");
        h.settle(&mut ui, TIMEOUT).expect("settles");
        let mut t_model = Vec::new();
        let mut t_ready = Vec::new();
        let mut t_frame = Vec::new();
        let mut t_updated = Vec::new();
        let mut t_loop = Vec::new();
        let mut loop_frames = Vec::new();
        let mut t_idle = Vec::new();
        let mut t_idle_preview = Vec::new();
        let mut t_stats = Vec::new();
        // A value never used before each time: the renderer caches geometry by (species, seed, detail, parameters),
        // and an alternating pair would be drawn from its cache after the first two changes.
        let value = |v: usize| values[v % 2] + v as f32 * 0.01;
        let mut v = 0;
        for _ in 0..RUNS {
            // Change → model ready, then one frame.
            v += 1;
            let t = Instant::now();
            ui.model.set_param(param, value(v)).expect("known parameter");
            t_model.push(ms(t));
            h.update_until_ready(&mut ui, TIMEOUT).expect("ready");
            let ready = ms(t);
            t_ready.push(ready);
            let f = Instant::now();
            h.draw_frame(&mut ui).expect("a frame");
            t_frame.push(ms(f));
            t_updated.push(ms(t));
            // The stats for this model, on the worker (what the panel waits for, never the UI thread).
            ui.wait_for_stats(TIMEOUT);
            t_stats.push(ui.stats_millis().expect("measured"));

            // The window's way: whole frames until the preview has settled.
            v += 1;
            let t = Instant::now();
            ui.model.set_param(param, value(v)).expect("known parameter");
            let mut frames = 0u32;
            loop {
                h.draw_frame(&mut ui).expect("a frame");
                frames += 1;
                if !h.preview.waiting() {
                    break;
                }
                assert!(t.elapsed() < TIMEOUT, "the preview did not settle");
            }
            t_loop.push(ms(t));
            loop_frames.push(f64::from(frames));
            ui.wait_for_stats(TIMEOUT);

            // Nothing changed: the cost of drawing the window.
            let t = Instant::now();
            h.draw_frame(&mut ui).expect("a frame");
            t_idle.push(ms(t));
            // The previous version of this bench's idle frame: the preview drawn and the UI laid out three times,
            // no window drawn.
            let t = Instant::now();
            h.settle_preview(&mut ui, TIMEOUT).expect("settles");
            t_idle_preview.push(ms(t));
        }
        let prims = ui.model.amplified().map_or(0, |a| a.stream.primitives.len());
        println!("{file} ({prims} primitives; adapter {}; medians of {RUNS}):", h.gpu().describe());
        println!("  model amplification on the UI thread (set_param)          {:7.1} ms", median(t_model));
        println!("  change → model ready (worker amplification, upload; no GPU) {:5.1} ms", median(t_ready));
        println!("  one window frame (UI + preview + egui, GPU waited)        {:7.1} ms", median(t_frame));
        println!("  change → updated preview (model ready + one frame)        {:7.1} ms", median(t_updated));
        println!(
            "  change → settled preview, window loop                     {:7.1} ms ({} frames)",
            median(t_loop),
            median(loop_frames)
        );
        println!("  idle frame                                                {:7.1} ms", median(t_idle));
        println!("  idle preview + UI layout, no window drawn (the old measure) {:5.1} ms", median(t_idle_preview));
        println!("  stats measurement on its worker thread (off the UI)       {:7.1} ms", median(t_stats));
    }
}
