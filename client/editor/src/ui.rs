//! The editor's egui UI: the source with diagnostics on the left, parameters, stats and actions on the right, the
//! live preview in the middle. It draws the [`Editor`] model and turns input into model calls; the 3D preview is a
//! texture the glue ([`crate::window`], [`crate::screenshot`]) renders with [`crate::preview::Preview`] at the size
//! this UI asks for. UI state (the view, the orbit, the grove size) lives here, apart from rendering.

use std::sync::mpsc::{Receiver, TryRecvError, channel};
use std::time::Duration;

use egui::{Color32, RichText, TextureHandle, TextureId, Ui};

use crate::model::{Editor, SourceKind};
use crate::stats::{SpeciesStats, StatsJob, StatsResult, StatsWorker};
use crate::{EditConfig, EditorError, hyp};

/// What the middle of the window shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum View {
    /// One instance, near geometry.
    Tree,
    /// N × N instances with seeds seed, seed + 1, … (seed 001 Figure 3: the population's variation).
    Grove,
    /// The near geometry beside the species' far field: its voxelised hypertree, raymarched.
    FarField,
}

impl View {
    /// The views with their names (the values of `--view`).
    pub const NAMES: [(&'static str, View); 3] =
        [("tree", View::Tree), ("grove", View::Grove), ("far", View::FarField)];
}

canopy_render::named_values!(View, "view");

/// The preview camera: orbiting a target.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Orbit {
    /// Azimuth, radians.
    pub yaw: f32,
    /// Elevation, radians.
    pub pitch: f32,
    /// Distance from the target, metres.
    pub distance: f32,
    /// The point looked at.
    pub target: [f32; 3],
    /// Frame the model again when it next changes size a lot (until the user moves the camera).
    pub auto_frame: bool,
}

impl Default for Orbit {
    fn default() -> Self {
        Orbit { yaw: 0.6, pitch: 0.25, distance: 30.0, target: [0.0, 8.0, 0.0], auto_frame: true }
    }
}

impl Orbit {
    /// The camera's eye.
    pub fn eye(&self) -> [f32; 3] {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        let t = self.target;
        [t[0] + self.distance * cp * sy, t[1] + self.distance * sp, t[2] + self.distance * cp * cy]
    }

    /// Frame a box: look at its centre from far enough to see it whole with the preview's 45° vertical field of
    /// view in a picture `aspect` (width / height) wide — narrower than tall, the horizontal field is what limits.
    pub fn frame(&mut self, lo: [f32; 3], hi: [f32; 3], aspect: f32) {
        let c = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, (lo[2] + hi[2]) / 2.0];
        let r = ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt() / 2.0;
        let half_v = 22.5f32.to_radians();
        let aspect = if aspect.is_finite() && aspect > 0.0 { aspect } else { 1.0 };
        let half = half_v.min((half_v.tan() * aspect).atan());
        if c.iter().all(|v| v.is_finite()) && r.is_finite() {
            self.target = c;
            self.distance = (r.max(0.5) / half.sin()) * 1.05;
        }
    }

    /// Drag to orbit (primary), pan (secondary or middle), scroll to zoom.
    fn input(&mut self, r: &egui::Response, ui: &Ui) {
        let d = r.drag_delta();
        if r.dragged_by(egui::PointerButton::Primary) && d != egui::Vec2::ZERO {
            self.yaw -= d.x * 0.01;
            self.pitch = (self.pitch + d.y * 0.01).clamp(-1.5, 1.5);
            self.auto_frame = false;
        }
        if (r.dragged_by(egui::PointerButton::Secondary) || r.dragged_by(egui::PointerButton::Middle))
            && d != egui::Vec2::ZERO
        {
            let s = self.distance * 0.0015;
            let (sy, cy) = self.yaw.sin_cos();
            self.target[0] -= (cy * d.x) * s;
            self.target[2] -= (-sy * d.x) * s;
            self.target[1] += d.y * s;
            self.auto_frame = false;
        }
        if r.hovered() {
            let scroll = ui.input(|i| i.smooth_scroll_delta.y);
            if scroll != 0.0 {
                self.distance = (self.distance * (-scroll * 0.002).exp()).clamp(0.2, 5_000.0);
                self.auto_frame = false;
            }
        }
    }
}

/// How long the model must stay unchanged before its stats are measured, seconds of the UI's clock (a slider drag
/// changes it every frame; the worker would only compete with the preview's workers for the CPU).
pub const STATS_DELAY: f64 = 0.25;

/// Traversals the stats panel times.
pub const STATS_REPEAT: u32 = 3;

/// The stats panel's state: the numbers shown (of some revision) and the measurement asked of the worker.
struct StatsPanel {
    worker: Result<StatsWorker, String>,
    shown: Option<StatsResult>,
    /// The revision asked for and not yet back.
    asked: Option<u64>,
    /// The revision last seen and when (UI clock) it was first seen.
    seen: Option<(u64, f64)>,
}

/// A raymarched volume image and the model revision it shows.
struct VolumeImage {
    revision: u64,
    texture: TextureHandle,
}

/// The editor UI's state (see the module docs).
pub struct EditorUi {
    /// The model.
    pub model: Editor,
    /// The view.
    pub view: View,
    /// Instances per side of the grove.
    pub grove: u32,
    /// The preview camera.
    pub orbit: Orbit,
    /// The last message for the status line.
    pub status: String,
    /// The preview's size in pixels, as the last frame laid it out (the glue renders at this size).
    pub preview_px: [u32; 2],
    /// Where `Export .glb` writes.
    pub export_path: String,
    /// Near-field mode: a species that declares `nearfield(…)` is drawn with its continuous mesh (true) or its
    /// primitives (false); see [`crate::preview`].
    pub near_field: bool,
    /// Whether measured times are shown (the stats panel, the raymarch's status line); off, a dash stands in for
    /// them, so a screenshot is the same run to run.
    pub show_times: bool,
    stats: StatsPanel,
    volume: Option<VolumeImage>,
    volume_job: Option<(u64, Receiver<Result<hyp::VolumeImage, String>>)>,
    volume_error: Option<String>,
    /// The azimuth of the raymarched views, degrees.
    pub volume_azimuth: f32,
}

impl EditorUi {
    /// The UI on a model.
    pub fn new(model: Editor) -> EditorUi {
        // Beside the working directory, named after the source (a path there would make screenshots differ by
        // checkout).
        let stem = std::path::Path::new(model.name()).file_stem().and_then(|s| s.to_str()).unwrap_or("species");
        let export_path = format!("{stem}.glb");
        let mut ui = EditorUi {
            model,
            view: View::Tree,
            grove: 3,
            orbit: Orbit::default(),
            status: String::new(),
            preview_px: [640, 480],
            export_path,
            near_field: true,
            show_times: true,
            stats: StatsPanel {
                worker: StatsWorker::new().map_err(|e| format!("starting the stats thread: {e}")),
                shown: None,
                asked: None,
                seen: None,
            },
            volume: None,
            volume_job: None,
            volume_error: None,
            volume_azimuth: 0.0,
        };
        ui.frame_model();
        ui
    }

    /// Open what the configuration names, with its settings applied.
    pub fn open(cfg: &EditConfig) -> Result<EditorUi, EditorError> {
        let mut model = match &cfg.file {
            Some(f) => Editor::open_keeping(f, cfg.last_good.clone())?,
            None => Editor::from_source("new.species", crate::model::TEMPLATE)?,
        };
        model.set_seed(cfg.seed);
        model.set_detail(cfg.detail);
        for (k, v) in &cfg.params {
            model.set_param(k, *v)?;
        }
        let mut ui = EditorUi::new(model);
        ui.view = cfg.view;
        ui.frame_model();
        Ok(ui)
    }

    /// Point the camera at the model (the whole grove in the grove view).
    pub fn frame_model(&mut self) {
        if let Some((lo, hi)) = self.model_bounds() {
            let [w, h] = self.preview_px;
            self.orbit.frame(lo, hi, w as f32 / h.max(1) as f32);
        }
    }

    /// The bounds of what the preview draws.
    pub fn model_bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        let a = self.model.amplified()?;
        if a.stream.primitives.is_empty() {
            return None;
        }
        let (lo, mut hi) = a.stream.bounds();
        if self.view == View::Grove {
            let step = self.grove_spacing();
            let span = step * (self.grove.max(1) - 1) as f32;
            hi[0] += span;
            hi[2] += span;
        }
        Some((lo, hi))
    }

    /// Metres between grove instances: the tree's width and a fifth.
    pub fn grove_spacing(&self) -> f32 {
        self.model.amplified().map_or(8.0, |a| {
            let (lo, hi) = a.stream.bounds();
            ((hi[0] - lo[0]).max(hi[2] - lo[2]) * 1.2).clamp(1.0, 500.0)
        })
    }

    /// Whether something is still being computed for the picture (a debounced edit, a raymarch).
    pub fn busy(&self) -> bool {
        self.model.pending_edit().is_some() || self.volume_job.is_some()
    }

    /// Whether the stats shown are not yet those of the current model (a measurement waits or runs).
    pub fn stats_pending(&self) -> bool {
        self.model.kind() != SourceKind::Hypertree
            && self.model.species().is_some()
            && self.stats.worker.is_ok()
            && self.stats.shown.as_ref().is_none_or(|r| r.revision != self.model.revision())
    }

    /// The stats shown: the revision they were measured for and the numbers (or why there are none).
    pub fn stats(&self) -> Option<(u64, &Result<SpeciesStats, String>)> {
        self.stats.shown.as_ref().map(|r| (r.revision, &r.stats))
    }

    /// Milliseconds the worker took for the stats shown.
    pub fn stats_millis(&self) -> Option<f64> {
        self.stats.shown.as_ref().map(|r| r.millis)
    }

    fn stats_job(&self) -> Option<StatsJob> {
        Some(StatsJob {
            revision: self.model.revision(),
            species: self.model.species()?.clone(),
            instance: self.model.instance(),
            budget: *self.model.budget(),
            repeat: STATS_REPEAT,
        })
    }

    /// Take what the stats worker sent back (a stale result is dropped) and ask it for the current revision once
    /// that has stood still for [`STATS_DELAY`] (or at once with `now_please`). Never measures on this thread.
    fn poll_stats(&mut self, now: f64, now_please: bool) {
        let rev = self.model.revision();
        let arrived = match &self.stats.worker {
            Ok(w) => w.try_result(),
            Err(_) => return,
        };
        if let Some(r) = arrived {
            if self.stats.asked == Some(r.revision) {
                self.stats.asked = None;
            }
            if r.revision == rev {
                self.stats.shown = Some(r);
            }
        }
        if !self.stats_pending() || self.stats.asked == Some(rev) {
            return;
        }
        let since = match self.stats.seen {
            Some((r, t)) if r == rev => t,
            _ => {
                self.stats.seen = Some((rev, now));
                now
            }
        };
        if !(now_please || now - since >= STATS_DELAY || self.stats.shown.is_none()) {
            return;
        }
        let Some(job) = self.stats_job() else { return };
        let sent = self.stats.worker.as_ref().is_ok_and(|w| w.request(job));
        if sent {
            self.stats.asked = Some(rev);
        } else {
            self.stats.worker = Err("the stats thread stopped".into());
        }
    }

    /// Wait up to `timeout` for the stats of the current model (screenshots, benchmarks).
    pub fn wait_for_stats(&mut self, timeout: Duration) {
        if !self.stats_pending() {
            return;
        }
        self.poll_stats(0.0, true);
        // The result may have arrived just now (taken by `poll_stats`): then there is nothing to wait for.
        if !self.stats_pending() {
            return;
        }
        let rev = self.model.revision();
        if let Ok(w) = &self.stats.worker
            && let Some(r) = w.wait_for(rev, timeout)
        {
            self.stats.asked = None;
            self.stats.shown = Some(r);
        }
    }

    /// Wait for a running raymarch (screenshots).
    pub fn wait_for_volume(&mut self, ctx: &egui::Context, timeout: Duration) {
        if let Some((rev, rx)) = self.volume_job.take() {
            match rx.recv_timeout(timeout) {
                Ok(r) => self.volume_done(ctx, rev, r),
                Err(_) => self.volume_job = Some((rev, rx)),
            }
        }
    }

    fn wants_volume(&self) -> bool {
        self.model.kind() == SourceKind::Hypertree || self.view == View::FarField
    }

    fn volume_done(&mut self, ctx: &egui::Context, revision: u64, r: Result<hyp::VolumeImage, String>) {
        match r {
            Ok(img) => {
                let image = egui::ColorImage::from_rgb(
                    [img.image.width as usize, img.image.height as usize],
                    &img.image.pixels,
                );
                let texture = ctx.load_texture("volume", image, egui::TextureOptions::LINEAR);
                self.volume = Some(VolumeImage { revision, texture });
                self.volume_error = None;
                self.status = if self.show_times { img.summary } else { img.untimed };
            }
            Err(e) => self.volume_error = Some(e),
        }
    }

    /// Start (or collect) the raymarch of the current model when the view needs one.
    fn poll_volume(&mut self, ctx: &egui::Context) {
        if let Some((rev, rx)) = self.volume_job.take() {
            match rx.try_recv() {
                Ok(r) => self.volume_done(ctx, rev, r),
                Err(TryRecvError::Empty) => {
                    self.volume_job = Some((rev, rx));
                    ctx.request_repaint_after(Duration::from_millis(30));
                    return;
                }
                Err(TryRecvError::Disconnected) => self.volume_error = Some("the raymarch stopped".into()),
            }
        }
        let rev = self.model.revision();
        if !self.wants_volume() || self.volume.as_ref().is_some_and(|v| v.revision == rev) {
            return;
        }
        if self.volume_error.is_some()
            && self.volume_job.is_none()
            && self.volume.as_ref().is_none_or(|v| v.revision == rev)
        {
            return;
        }
        let job = hyp::VolumeJob::of(&self.model, self.volume_azimuth);
        let Some(job) = job else { return };
        let (tx, rx) = channel();
        let spawned = std::thread::Builder::new().name("raymarch".into()).spawn(move || {
            let _ = tx.send(job.run());
        });
        match spawned {
            Ok(_) => {
                self.volume_job = Some((rev, rx));
                ctx.request_repaint_after(Duration::from_millis(30));
            }
            Err(e) => self.volume_error = Some(format!("starting the raymarch: {e}")),
        }
    }

    /// One frame of the UI. `preview` is the texture holding the last 3D preview, if the glue has one.
    pub fn show(&mut self, ui: &mut Ui, preview: Option<TextureId>) {
        let ctx = ui.ctx().clone();
        let now = ctx.input(|i| i.time);
        if self.model.tick(now) && self.orbit.auto_frame {
            self.frame_model();
        }
        if let Some(t) = self.model.pending_edit() {
            ctx.request_repaint_after(Duration::from_secs_f64((t + crate::model::DEBOUNCE - now).max(0.0)));
        }
        self.poll_volume(&ctx);
        if self.model.kind() != SourceKind::Hypertree {
            self.poll_stats(now, false);
            if self.stats_pending() {
                // Wake to send the job once the model stands still, and to collect the result.
                ctx.request_repaint_after(Duration::from_millis(50));
            }
        }
        egui::Panel::top("bar").show(ui, |ui| self.top_bar(ui));
        egui::Panel::bottom("status").show(ui, |ui| {
            ui.horizontal(|ui| {
                ui.label(RichText::new(&self.status).small());
            })
        });
        // The problems under everything else, as tall as the user drags them (they are what an author reads first
        // when the tree does not come).
        egui::Panel::bottom("problems")
            .resizable(true)
            .default_size(120.0)
            .min_size(40.0)
            .show(ui, |ui| self.problems(ui));
        egui::Panel::left("source").default_size(ui.available_width() * 0.36).resizable(true).show(ui, |ui| {
            let mut text = self.model.text().to_string();
            if crate::ui_source::show(ui, &mut text, self.model.diagnostics()) {
                self.model.edit_text(text, now);
                ctx.request_repaint_after(Duration::from_secs_f64(crate::model::DEBOUNCE));
            }
        });
        egui::Panel::right("side").default_size(300.0).resizable(true).show(ui, |ui| {
            egui::ScrollArea::vertical().id_salt("side-scroll").show(ui, |ui| self.side(ui));
        });
        egui::CentralPanel::default().show(ui, |ui| self.middle(ui, preview));
    }

    fn top_bar(&mut self, ui: &mut Ui) {
        ui.horizontal(|ui| {
            let star = if self.model.modified() { " *" } else { "" };
            let name = std::path::Path::new(self.model.name()).file_name().and_then(|s| s.to_str());
            ui.strong(format!("{}{star}", name.unwrap_or(self.model.name()))).on_hover_text(self.model.name());
            ui.separator();
            if ui.add_enabled(self.model.path().is_some(), egui::Button::new("Save")).clicked() {
                self.status = match self.model.save() {
                    Ok(p) => format!("saved {}", p.display()),
                    Err(e) => e.to_string(),
                };
            }
            let species = self.model.kind() != SourceKind::Hypertree;
            if species {
                let to = ui.label("to").id;
                ui.add(egui::TextEdit::singleline(&mut self.export_path).desired_width(140.0)).labelled_by(to);
                if ui.button("Export .glb").clicked() {
                    let path = std::path::PathBuf::from(&self.export_path);
                    self.status = match self.model.export_glb(&path) {
                        Ok(()) => format!("wrote {}", path.display()),
                        Err(e) => e.to_string(),
                    };
                }
                if ui.button("Copy instance line").clicked() {
                    let line = self.model.instance_line();
                    ui.ctx().copy_text(line.clone());
                    self.status = format!("copied: {line}");
                }
                ui.separator();
                for (name, v) in View::NAMES {
                    if ui.selectable_label(self.view == v, name).clicked() && self.view != v {
                        self.view = v;
                        self.frame_model();
                    }
                }
                if self.view == View::Grove {
                    ui.add(egui::Slider::new(&mut self.grove, 1..=8).text("N"));
                }
                if self.model.species().is_some_and(|s| crate::preview::has_nearfield(&s.graph)) {
                    ui.checkbox(&mut self.near_field, "near-field mesh").on_hover_text(
                        "the species declares nearfield(…): at detail 0 draw its continuous mesh (on) or its \
                         primitives (off)",
                    );
                }
                if ui.button("Frame").clicked() {
                    self.orbit.auto_frame = true;
                    self.frame_model();
                }
            }
        });
    }

    fn side(&mut self, ui: &mut Ui) {
        match self.model.kind() {
            SourceKind::Hypertree => self.hyp_controls(ui),
            _ => self.species_controls(ui),
        }
    }

    /// The problem list: one line a diagnostic (`line:col: message`, the whole diagnostic with its caret on hover),
    /// and what the preview shows meanwhile.
    fn problems(&mut self, ui: &mut Ui) {
        let n = self.model.diagnostics().len();
        let has_model = self.model.species().is_some() || self.model.hypertree().is_some();
        ui.horizontal(|ui| {
            let heading = if n == 0 { "no problems".to_string() } else { format!("{n} problem(s)") };
            let colour = if n == 0 { Color32::GRAY } else { crate::ui_source::ERROR };
            ui.label(RichText::new(heading).strong().color(colour));
            let showing = match (n, has_model, self.model.showing_last_good()) {
                (0, _, _) => None,
                (_, true, true) => Some("showing the file's last good version, as the editor kept it"),
                (_, true, false) => Some("showing the last good model"),
                (_, false, _) => Some("nothing to show until the file parses"),
            };
            if let Some(s) = showing {
                ui.label(RichText::new(s).italics());
            }
        });
        egui::ScrollArea::vertical().id_salt("problems-scroll").auto_shrink([false, false]).show(ui, |ui| {
            for d in self.model.diagnostics() {
                ui.label(RichText::new(format!("{}:{}: {}", d.line, d.col, d.message)).monospace())
                    .on_hover_text(RichText::new(d.to_string()).monospace());
            }
        });
    }

    fn species_controls(&mut self, ui: &mut Ui) {
        ui.heading("Instance");
        let mut seed = self.model.seed();
        if ui.add(egui::DragValue::new(&mut seed).prefix("seed ")).changed() {
            self.model.set_seed(seed);
        }
        let mut detail = self.model.detail();
        if ui.add(egui::Slider::new(&mut detail, 0..=6).text("detail")).changed() {
            self.model.set_detail(detail);
        }
        ui.heading("Parameters");
        for p in self.model.params() {
            ui.horizontal(|ui| {
                let mut v = p.value;
                let r = ui.add(
                    egui::Slider::new(&mut v, p.range.clone()).text(&p.name).clamping(egui::SliderClamping::Never),
                );
                if r.changed()
                    && v.is_finite()
                    && let Err(e) = self.model.set_param(&p.name, v)
                {
                    self.status = e.to_string();
                }
                if p.overridden && ui.small_button("reset").on_hover_text(format!("default {}", p.default)).clicked() {
                    self.model.reset_param(&p.name);
                }
            });
        }
        // Counted every frame; evaluated (the instance's parameters) only while the section is open.
        let working = self.model.species().map_or(0, |s| s.working_values().len());
        if working > 0 {
            egui::CollapsingHeader::new(format!("Working values ({working})")).default_open(false).show(ui, |ui| {
                ui.label(RichText::new("the program's own, at the start of this instance").italics().small());
                for (name, v) in self.model.working_values() {
                    ui.label(RichText::new(format!("{name} = {v}")).monospace().small());
                }
            });
        }
        if let Some(e) = self.model.amplify_error() {
            ui.colored_label(crate::ui_source::ERROR, e);
        }
        ui.heading("Stats");
        let stale = self.stats_pending();
        if let Err(e) = &self.stats.worker {
            ui.colored_label(crate::ui_source::ERROR, e);
        }
        match &self.stats.shown {
            Some(StatsResult { stats: Ok(s), .. }) => {
                if stale {
                    ui.label(RichText::new("measuring… (the numbers below are of an earlier model)").italics().small());
                }
                for line in s.lines_timed(self.show_times) {
                    ui.label(RichText::new(line).monospace().small());
                }
                ui.label(RichText::new(format!("stream hash {:016x}", s.stream_hash)).monospace().small());
            }
            Some(StatsResult { stats: Err(e), .. }) => {
                ui.colored_label(crate::ui_source::ERROR, e);
            }
            None if self.model.species().is_some() => {
                ui.label(RichText::new("measuring…").italics());
            }
            None => {
                ui.label("no species yet");
            }
        }
    }

    fn hyp_controls(&mut self, ui: &mut Ui) {
        ui.heading("Hypertree");
        let mut seed = self.model.seed();
        if ui.add(egui::DragValue::new(&mut seed).prefix("seed ")).changed() {
            self.model.set_seed(seed);
        }
        let Some(h) = self.model.hypertree() else {
            ui.label("no definition has parsed yet");
            return;
        };
        let (mut res, mut it) = (h.resolution, h.iterations);
        let r1 = ui.add(egui::Slider::new(&mut res, 16..=512).text("resolution"));
        let r2 = ui.add(egui::Slider::new(&mut it, 1_000..=4_000_000).logarithmic(true).text("iterations"));
        if (r1.changed() || r2.changed())
            && let Some(h) = self.model.hypertree_mut()
        {
            h.resolution = res;
            h.iterations = it;
        }
        ui.label(RichText::new("per-level transformation values").strong());
        let mut values: Vec<(String, f32)> = match self.model.hypertree_mut_quiet() {
            Some(h) => h.level_values().into_iter().map(|v| (v.label, *v.value)).collect(),
            None => Vec::new(),
        };
        let mut changed = None;
        for (i, (label, v)) in values.iter_mut().enumerate() {
            let span = v.abs().max(1.0) * 2.0;
            if ui.add(egui::Slider::new(v, -span..=span).text(label.as_str())).changed() {
                changed = Some((i, *v));
            }
        }
        // Only a moved slider marks the model changed (a new generation and raymarch).
        if let Some((i, v)) = changed
            && let Some(h) = self.model.hypertree_mut()
            && let Some(slot) = h.level_values().into_iter().nth(i)
        {
            *slot.value = v;
        }
        if let Some(e) = &self.volume_error {
            ui.colored_label(crate::ui_source::ERROR, e);
        }
    }

    fn middle(&mut self, ui: &mut Ui, preview: Option<TextureId>) {
        let size = ui.available_size();
        let hyp = self.model.kind() == SourceKind::Hypertree;
        let split = self.view == View::FarField || hyp;
        let near_w = if hyp {
            0.0
        } else if split {
            size.x / 2.0
        } else {
            size.x
        };
        if !hyp {
            let px = ui.ctx().pixels_per_point();
            let was = std::mem::replace(
                &mut self.preview_px,
                [((near_w * px) as u32).max(16), ((size.y * px) as u32).max(16)],
            );
            // The picture changed shape (a split view, a resized window): framed again for it, unless the user has
            // moved the camera.
            if was != self.preview_px && self.orbit.auto_frame {
                self.frame_model();
            }
        }
        ui.horizontal(|ui| {
            if !hyp {
                let rect_size = egui::vec2(near_w, size.y);
                let r = match preview {
                    Some(id) if self.model.species().is_some() => {
                        ui.add(egui::Image::from_texture((id, rect_size)).sense(egui::Sense::click_and_drag()))
                    }
                    _ => ui.allocate_response(rect_size, egui::Sense::click_and_drag()),
                };
                if self.model.species().is_none() {
                    // No tree yet (the file has never parsed here): say so instead of an empty scene.
                    let n = self.model.diagnostics().len();
                    ui.painter().text(
                        r.rect.center(),
                        egui::Align2::CENTER_CENTER,
                        format!("no tree: {n} problem(s) in the file, listed below"),
                        egui::FontId::proportional(18.0),
                        crate::ui_source::ERROR,
                    );
                }
                self.orbit.input(&r, ui);
            }
            if split {
                let w = size.x - near_w;
                match &self.volume {
                    Some(v) => {
                        let side = w.min(size.y);
                        ui.add(egui::Image::from_texture((v.texture.id(), egui::vec2(side, side))));
                    }
                    None => {
                        ui.label(if self.volume_job.is_some() { "raymarching…" } else { "no volume yet" });
                    }
                }
            }
        });
    }
}
