//! Keystroke or slider → updated preview, timed (issue 19's numbers): for the monopodial tree and the conifer, a
//! parameter change is applied to the model (amplification on the UI thread for the stats and hash) and the preview
//! is drawn until it settles (the renderer's workers amplify, the geometry is uploaded, the frame rendered and
//! waited for). Run: `cargo bench -p canopy-editor --bench preview` (prints medians; set WGPU_BACKEND=vulkan for
//! lavapipe).

use std::time::{Duration, Instant};

use canopy_editor::EditConfig;
use canopy_editor::screenshot::Headless;
use canopy_editor::ui::EditorUi;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../worlds/species");
    for (file, param, values) in
        [("monopodial.species", "height", [18.0f32, 22.0]), ("conifer.species", "height", [14.0, 16.0])]
    {
        let cfg = EditConfig { file: Some(root.join(file)), size: (1280, 800), ..EditConfig::default() };
        let mut ui = EditorUi::open(&cfg).expect("opens");
        let mut h = Headless::new(cfg.size).expect("a GPU");
        h.settle(&mut ui, Duration::from_secs(120)).expect("settles");
        let (mut model_ms, mut total_ms, mut frames_ms) = (Vec::new(), Vec::new(), Vec::new());
        for i in 0..11 {
            let t = Instant::now();
            ui.model.set_param(param, values[i % 2]).expect("known parameter");
            let m = t.elapsed().as_secs_f64() * 1e3;
            h.settle(&mut ui, Duration::from_secs(120)).expect("settles");
            total_ms.push(t.elapsed().as_secs_f64() * 1e3);
            model_ms.push(m);
            // A frame with nothing to change: the render cost alone.
            let t = Instant::now();
            h.settle(&mut ui, Duration::from_secs(120)).expect("settles");
            frames_ms.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let prims = ui.model.amplified().map_or(0, |a| a.stream.primitives.len());
        println!(
            "{file:<20} {prims:>7} primitives: change → settled preview {:.1} ms median of 11 (model amplification {:.1} ms); an idle update + frame {:.1} ms; adapter {}",
            median(total_ms),
            median(model_ms),
            median(frames_ms),
            h.gpu().describe()
        );
    }
}
