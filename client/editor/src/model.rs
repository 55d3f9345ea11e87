//! The editor model, pure of any window or GPU: the source buffer and its file, parsing with diagnostics, the last
//! good model (a broken edit never replaces it), the instance being previewed (seed, parameter overrides, detail)
//! and its amplified stream. The UI feeds it edits and the time; the preview reads `revision` to know when to
//! redraw.

use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use canopy_worlds::amplify::{Budget, Instance, instance_params};
use canopy_worlds::diag::{Diagnostic, SourceFile};
use canopy_worlds::gltf::glb;
use canopy_worlds::library;
use canopy_worlds::load::read_source;
use canopy_worlds::mesh::{MeshOptions, mesh};
use canopy_worlds::primitive::PrimitiveStream;
use canopy_worlds::rng::InstanceRng;

use crate::EditorError;
use crate::hyp::HypertreeModel;
use crate::last_good::LastGood;
use crate::species::Species;

/// How long typing must pause before the text is parsed and amplified again, seconds (times are the UI's clock:
/// egui's `input.time`, so tests drive it).
pub(crate) const DEBOUNCE: f64 = 0.1;

/// What kind of source the editor holds (from the file name's extension).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SourceKind {
    /// The species text format (`.species`).
    Species,
    /// A parametric L-system (`.lsys`).
    LSystem,
    /// A hypertree definition (`.hyp`, seed 000 §10).
    Hypertree,
}

impl SourceKind {
    /// The kind a file name names, if any.
    pub fn of(name: &str) -> Option<SourceKind> {
        if name.ends_with(".species") {
            Some(SourceKind::Species)
        } else if name.ends_with(".lsys") {
            Some(SourceKind::LSystem)
        } else if name.ends_with(".hyp") {
            Some(SourceKind::Hypertree)
        } else {
            None
        }
    }
}

/// One declared parameter as the UI shows it: a slider over `range`.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamControl {
    /// The parameter's slot in the graph.
    pub slot: u16,
    /// Its name.
    pub name: String,
    /// Its declared default for this instance (a random default is drawn with the instance seed).
    pub default: f32,
    /// The value the instance uses (the override, or the default).
    pub value: f32,
    /// The slider's range: around the default, wide enough for any value the default draws over many seeds.
    pub range: RangeInclusive<f32>,
    /// Whether the value is an override.
    pub overridden: bool,
}

/// The last amplification of the previewed instance.
#[derive(Clone, Debug)]
pub struct Amplified {
    /// The primitive stream.
    pub stream: Arc<PrimitiveStream>,
    /// Its hash (the golden-hash function).
    pub hash: u64,
    /// Amplification time, milliseconds.
    pub millis: f64,
}

/// A new species source when no file is given (or the file does not exist yet).
pub(crate) const TEMPLATE: &str = "# A new species: edit, and the preview follows.\n\
species Sapling\n\
param height = 6\n\
separator {\n\
  material(0.42, 0.3, 0.18)\n\
  cone(height * 0.04, height * 0.01, height)\n\
}\n\
separator {\n\
  material(0.25, 0.5, 0.2)\n\
  translate(0, height, 0)\n\
  sphere(height * 0.25)\n\
}\n";

/// The editor model (see the module docs).
#[derive(Debug)]
pub struct Editor {
    name: String,
    path: Option<PathBuf>,
    text: String,
    saved_text: String,
    kind: SourceKind,
    diagnostics: Vec<Diagnostic>,
    species: Option<Species>,
    hypertree: Option<HypertreeModel>,
    /// The previewed instance's seed.
    seed: u64,
    /// The previewed instance's detail level.
    detail: u8,
    overrides: Vec<(String, f32)>,
    amplified: Option<Amplified>,
    amplify_error: Option<String>,
    revision: u64,
    edited_at: Option<f64>,
    budget: Budget,
    /// Where the last good version of the file is kept, if anywhere.
    last_good: Option<LastGood>,
    /// Whether the model shown is the file's last good version, not anything its current text gave.
    from_last_good: bool,
}

impl Editor {
    /// An editor on a source text named `name` (its extension picks the format), with no file behind it.
    pub fn from_source(name: &str, text: &str) -> Result<Editor, EditorError> {
        let kind = SourceKind::of(name).ok_or_else(|| EditorError::Format(name.to_string()))?;
        let mut e = Editor {
            name: name.to_string(),
            path: None,
            text: text.to_string(),
            saved_text: text.to_string(),
            kind,
            diagnostics: Vec::new(),
            species: None,
            hypertree: None,
            seed: 1,
            detail: 0,
            overrides: Vec::new(),
            amplified: None,
            amplify_error: None,
            revision: 0,
            edited_at: None,
            budget: Budget::default(),
            last_good: None,
            from_last_good: false,
        };
        e.reparse();
        Ok(e)
    }

    /// [`Editor::open`], keeping the file's last good version in `last_good`: a file that parses is remembered
    /// there (and again on every save that parses); one that does not shows, beside its diagnostics, the model its
    /// last good version gives, if one was kept.
    pub fn open_keeping(path: &Path, last_good: Option<LastGood>) -> Result<Editor, EditorError> {
        let mut e = Editor::open(path)?;
        e.last_good = last_good;
        if !path.exists() {
            return Ok(e);
        }
        if e.has_model() {
            e.remember();
        } else if let Some(text) = e.last_good.as_ref().and_then(|lg| lg.recall(path)) {
            let old = Editor::from_source(&e.name, &text)?;
            if old.has_model() {
                e.species = old.species;
                e.hypertree = old.hypertree;
                e.amplified = old.amplified;
                e.from_last_good = true;
                e.revision += 1;
            }
        }
        Ok(e)
    }

    /// Whether the current text gave a model (a species that amplifies, or a hypertree definition) with no
    /// diagnostic.
    fn has_model(&self) -> bool {
        self.diagnostics.is_empty() && (self.species.is_some() || self.hypertree.is_some())
    }

    /// Keep the text as the file's last good version (a failure only logged: the edit itself is not at stake).
    fn remember(&self) {
        if let (Some(lg), Some(path)) = (&self.last_good, &self.path)
            && let Err(e) = lg.remember(path, &self.text)
        {
            tracing::warn!("keeping the last good version of {}: {e}", path.display());
        }
    }

    /// Whether the model shown is the file's last good version (kept from an earlier session), because its text
    /// as opened does not parse.
    pub fn showing_last_good(&self) -> bool {
        self.from_last_good
    }

    /// Open a file (read through `canopy_worlds::fsread`: regular files only, bounded); a path that does not exist
    /// yet starts from a template (or from the embedded library species of that name) and is written on save.
    pub fn open(path: &Path) -> Result<Editor, EditorError> {
        let name = path.display().to_string();
        if path.exists() {
            let src = read_source(path).map_err(|reason| EditorError::Read { path: name.clone(), reason })?;
            let mut e = Editor::from_source(&name, &src.text)?;
            e.path = Some(path.to_path_buf());
            return Ok(e);
        }
        let text = match library::find(&name) {
            Some(entry) => return Editor::from_source(entry.file, entry.text),
            None if SourceKind::of(&name) == Some(SourceKind::Hypertree) => crate::hyp::TEMPLATE,
            None => TEMPLATE,
        };
        let mut e = Editor::from_source(&name, text)?;
        e.path = Some(path.to_path_buf());
        e.saved_text = String::new();
        Ok(e)
    }

    /// The source's name (its path, or the library file's name).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The file behind the buffer, if any.
    pub fn path(&self) -> Option<&Path> {
        self.path.as_deref()
    }

    /// The source text.
    pub fn text(&self) -> &str {
        &self.text
    }

    /// The format.
    pub fn kind(&self) -> SourceKind {
        self.kind
    }

    /// Whether the buffer differs from the file.
    pub fn modified(&self) -> bool {
        self.text != self.saved_text
    }

    /// The diagnostics of the current text (empty when it parses and amplifies).
    pub fn diagnostics(&self) -> &[Diagnostic] {
        &self.diagnostics
    }

    /// The last species that parsed and amplified (kept through broken edits).
    pub fn species(&self) -> Option<&Species> {
        self.species.as_ref()
    }

    /// The last hypertree definition that parsed, with the sliders' values.
    pub fn hypertree(&self) -> Option<&HypertreeModel> {
        self.hypertree.as_ref()
    }

    /// The hypertree model, to move its sliders (bumps the revision).
    pub fn hypertree_mut(&mut self) -> Option<&mut HypertreeModel> {
        self.revision += 1;
        self.hypertree.as_mut()
    }

    /// The hypertree model without marking a change (reading its sliders).
    pub fn hypertree_mut_quiet(&mut self) -> Option<&mut HypertreeModel> {
        self.hypertree.as_mut()
    }

    /// The previewed instance's last amplification.
    pub fn amplified(&self) -> Option<&Amplified> {
        self.amplified.as_ref()
    }

    /// Why the previewed instance could not be amplified with the current settings, if it could not.
    pub fn amplify_error(&self) -> Option<&str> {
        self.amplify_error.as_deref()
    }

    /// Changes whenever what the preview shows changes (the model or the instance settings).
    pub fn revision(&self) -> u64 {
        self.revision
    }

    /// The previewed seed.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The previewed detail level.
    pub fn detail(&self) -> u8 {
        self.detail
    }

    /// The budget every amplification runs under.
    pub fn budget(&self) -> &Budget {
        &self.budget
    }

    /// Replace the text and parse it at once (a file changed on disk, a test).
    pub fn set_text(&mut self, text: &str) {
        self.text = text.to_string();
        self.edited_at = None;
        self.reparse();
    }

    /// The text was typed into: parse it once typing pauses for [`DEBOUNCE`] (see [`Editor::tick`]).
    pub fn edit_text(&mut self, text: String, now: f64) {
        if text != self.text {
            self.text = text;
            self.edited_at = Some(now);
        }
    }

    /// Parse the text if an edit has waited long enough; true when it did.
    pub fn tick(&mut self, now: f64) -> bool {
        match self.edited_at {
            Some(t) if now - t >= DEBOUNCE => {
                self.edited_at = None;
                self.reparse();
                true
            }
            _ => false,
        }
    }

    /// Whether an edit is waiting for the debounce (the UI keeps repainting until it is parsed).
    pub fn pending_edit(&self) -> Option<f64> {
        self.edited_at
    }

    /// Parse the text now. A text that parses (and, for a species, amplifies with the current settings) becomes
    /// the model; one that does not leaves the last good model in place and only changes the diagnostics.
    pub fn reparse(&mut self) {
        let src = SourceFile::new(self.name.clone(), self.text.clone());
        match self.kind {
            SourceKind::Hypertree => {
                let (def, diags) = canopy_worlds::hypertree::format::parse_hypertree(&src);
                self.diagnostics = diags;
                if let Some(def) = def {
                    match &mut self.hypertree {
                        Some(m) => m.replace(def),
                        None => self.hypertree = Some(HypertreeModel::new(def)),
                    }
                    self.from_last_good = false;
                    self.revision += 1;
                }
            }
            SourceKind::Species | SourceKind::LSystem => {
                let (species, mut diags) = Species::parse(&src);
                if let Some(species) = species {
                    match self.amplify(&species) {
                        Ok(a) => {
                            self.amplified = Some(a);
                            self.amplify_error = None;
                            self.species = Some(species);
                            self.from_last_good = false;
                            self.revision += 1;
                        }
                        Err(e) => diags.push(src.diag(
                            0..0,
                            format!(
                                "species `{}` cannot finish (seed {}, detail {}): {e}",
                                species.graph.name, self.seed, self.detail
                            ),
                        )),
                    }
                }
                self.diagnostics = diags;
            }
        }
    }

    /// Amplify the previewed instance of `species`, timed.
    fn amplify(&self, species: &Species) -> Result<Amplified, crate::species::AmplifyFailure> {
        let t = Instant::now();
        let stream = species.amplify(&self.instance_for(species), &self.budget)?;
        let millis = t.elapsed().as_secs_f64() * 1e3;
        Ok(Amplified { hash: stream.hash(), stream: Arc::new(stream), millis })
    }

    /// The overrides that name parameters of `species`, as slots.
    fn instance_for(&self, species: &Species) -> Instance {
        let params = self.overrides.iter().filter_map(|(n, v)| species.graph.param_slot(n).map(|s| (s, *v))).collect();
        Instance { seed: self.seed, params, detail: self.detail }
    }

    /// The previewed instance (seed, overrides of parameters the model has, detail).
    pub fn instance(&self) -> Instance {
        match &self.species {
            Some(s) => self.instance_for(s),
            None => Instance { seed: self.seed, params: Vec::new(), detail: self.detail },
        }
    }

    /// Amplify the previewed instance again after a settings change.
    fn reamplify(&mut self) {
        self.revision += 1;
        let Some(species) = &self.species else { return };
        match self.amplify(species) {
            Ok(a) => {
                self.amplified = Some(a);
                self.amplify_error = None;
            }
            Err(e) => self.amplify_error = Some(e.to_string()),
        }
    }

    /// Override a parameter by name (an unknown name is refused with the parameters the species has).
    pub fn set_param(&mut self, name: &str, value: f32) -> Result<(), EditorError> {
        let Some(species) = &self.species else { return Err(EditorError::NoModel) };
        species.graph.parameter_slot(name).map_err(EditorError::Param)?;
        if !value.is_finite() {
            return Err(EditorError::Param(format!("`{value}` is not finite")));
        }
        match self.overrides.iter_mut().find(|(n, _)| n == name) {
            Some(o) => o.1 = value,
            None => self.overrides.push((name.to_string(), value)),
        }
        self.reamplify();
        Ok(())
    }

    /// Drop a parameter's override (back to its default).
    pub fn reset_param(&mut self, name: &str) {
        self.overrides.retain(|(n, _)| n != name);
        self.reamplify();
    }

    /// The overrides, by name.
    pub fn overrides(&self) -> &[(String, f32)] {
        &self.overrides
    }

    /// Preview another seed.
    pub fn set_seed(&mut self, seed: u64) {
        self.seed = seed;
        if let Some(h) = &mut self.hypertree {
            h.seed = seed;
        }
        self.reamplify();
    }

    /// Preview another detail level.
    pub fn set_detail(&mut self, detail: u8) {
        self.detail = detail;
        self.reamplify();
    }

    /// The sliders: every declared parameter with its default, value and range.
    pub fn params(&self) -> Vec<ParamControl> {
        let Some(species) = &self.species else { return Vec::new() };
        let g = &species.graph;
        let defaults = |seed: u64| {
            let inst = Instance { seed, params: Vec::new(), detail: self.detail };
            instance_params(g, &inst, &mut InstanceRng::new(seed)).map(|(v, _)| v).ok()
        };
        let Some(here) = defaults(self.seed) else { return Vec::new() };
        let values = instance_params(g, &self.instance_for(species), &mut InstanceRng::new(self.seed))
            .map(|(v, _)| v)
            .unwrap_or_else(|_| here.clone());
        // A random default's spread: its values over a few seeds.
        let samples: Vec<Vec<f32>> = (0..8u64).filter_map(|k| defaults(k.wrapping_mul(0x9e37_79b9) + 7)).collect();
        species
            .declared_params()
            .into_iter()
            .map(|(slot, name)| {
                let i = usize::from(slot);
                let default = here[i];
                let (mut lo, mut hi) = around(default);
                for s in &samples {
                    let (a, b) = around(s[i]);
                    lo = lo.min(a);
                    hi = hi.max(b);
                }
                let value = values[i];
                ParamControl {
                    slot,
                    name: name.to_string(),
                    default,
                    value,
                    range: lo.min(value)..=hi.max(value),
                    overridden: self.overrides.iter().any(|(n, _)| n == name),
                }
            })
            .collect()
    }

    /// The species' working values (not sliders: its program computes them) and their values at the start of the
    /// previewed instance, in declaration order.
    pub fn working_values(&self) -> Vec<(String, f32)> {
        let Some(species) = &self.species else { return Vec::new() };
        let rng = &mut InstanceRng::new(self.seed);
        let Ok((values, _)) = instance_params(&species.graph, &self.instance_for(species), rng) else {
            return Vec::new();
        };
        let named = species.working_values().into_iter();
        named.map(|(slot, name)| (name.to_string(), values[usize::from(slot)])).collect()
    }

    /// A world manifest's `instance` line for the previewed instance: the species by its file's stem, at the
    /// origin, with the overridden parameters (a manifest's instances take their seeds from their ids).
    pub fn instance_line(&self) -> String {
        let stem = Path::new(&self.name).file_stem().and_then(|s| s.to_str()).unwrap_or("species").to_string();
        let mut line = format!("instance {stem} at 0 0");
        for (n, v) in &self.overrides {
            if self.species.as_ref().is_some_and(|s| s.graph.param_slot(n).is_some()) {
                line.push_str(&format!(" {n}={v}"));
            }
        }
        line
    }

    /// Write the buffer to its file (through a temporary file renamed over it: [`crate::save`]).
    pub fn save(&mut self) -> Result<PathBuf, EditorError> {
        let path = self.path.clone().ok_or(EditorError::NoPath)?;
        crate::save::write_file(&path, self.text.as_bytes())?;
        self.saved_text = self.text.clone();
        if self.edited_at.is_none() && self.has_model() {
            self.remember();
        }
        Ok(path)
    }

    /// The file changed on disk: take its text if it differs from the buffer. Returns whether it did.
    pub fn reload(&mut self) -> Result<bool, EditorError> {
        let path = self.path.clone().ok_or(EditorError::NoPath)?;
        let src =
            read_source(&path).map_err(|reason| EditorError::Read { path: path.display().to_string(), reason })?;
        if src.text == self.text {
            return Ok(false);
        }
        self.saved_text = src.text.clone();
        self.set_text(&src.text);
        Ok(true)
    }

    /// The previewed instance as glTF binary (its triangle mesh at its detail level).
    pub fn glb(&self) -> Result<Vec<u8>, EditorError> {
        let (Some(species), Some(a)) = (&self.species, &self.amplified) else { return Err(EditorError::NoModel) };
        let m = mesh(&a.stream, &MeshOptions::for_detail(self.detail));
        let name = format!("{}-{}", species.graph.name, self.seed);
        glb(&[(name, &m, [0.0; 3])]).map_err(|e| EditorError::Export(e.to_string()))
    }

    /// Write the previewed instance as a `.glb` file (as [`Editor::save`] writes).
    pub fn export_glb(&self, path: &Path) -> Result<(), EditorError> {
        let bytes = self.glb()?;
        crate::save::write_file(path, &bytes)
    }
}

/// A slider range around a value: 0 to twice it (or twice it to 0), and −1 to 1 around zero.
fn around(v: f32) -> (f32, f32) {
    if v > 0.0 {
        (0.0, 2.0 * v)
    } else if v < 0.0 {
        (2.0 * v, 0.0)
    } else {
        (-1.0, 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Only a species' parameters are sliders: its working values (`let`) and an L-system's module arguments are
    /// listed apart, and cannot be set.
    #[test]
    fn only_parameters_are_sliders() {
        let cases: [(&str, &[&str]); 4] = [
            ("monopodial", &["height", "branch_length", "branching"]),
            ("conifer", &["height", "spread", "radius"]),
            ("worm", &["c"]),
            ("bush", &["angle", "len", "leaf"]),
        ];
        for (name, want) in cases {
            let e = library::find(name).expect("library");
            let ed = Editor::from_source(e.file, e.text).expect("format");
            let names: Vec<String> = ed.params().into_iter().map(|p| p.name).collect();
            assert_eq!(names, want, "{name}");
        }
        let mut ed = monopodial();
        let working: Vec<String> = ed.working_values().into_iter().map(|(n, _)| n).collect();
        assert_eq!(working.join(" "), "n s r c w m t u d p g h e k");
        let err = ed.set_param("m", 1.0).unwrap_err().to_string();
        assert!(err.contains("`m` is a working value of species `monopodial`"), "{err}");
        assert!(ed.set_param("height", 12.0).is_ok());
    }

    /// A file broken when it is opened shows its last good version (kept when it was last opened or saved whole)
    /// beside its diagnostics; without one it shows nothing, and a later good parse replaces the kept model.
    #[test]
    fn a_broken_file_opens_on_its_last_good_version() {
        let dir = tempfile::tempdir().unwrap();
        let lg = LastGood::in_dir(dir.path().join("state"));
        let path = dir.path().join("tree.species");
        let good = library::find("worm").expect("library").text;
        std::fs::write(&path, good).unwrap();
        let opened = Editor::open_keeping(&path, Some(lg.clone())).unwrap();
        assert!(opened.species().is_some() && !opened.showing_last_good());
        assert_eq!(lg.recall(&path).as_deref(), Some(good), "a file that parses is remembered");

        let broken = good.replacen("cone(", "cnoe(", 1);
        std::fs::write(&path, &broken).unwrap();
        let mut ed = Editor::open_keeping(&path, Some(lg.clone())).unwrap();
        assert_eq!(ed.diagnostics().len(), 1, "{:?}", ed.diagnostics());
        assert!(ed.species().is_some(), "the last good tree is shown");
        assert!(ed.showing_last_good());
        assert_eq!(ed.text(), broken, "the buffer is the file as it is");
        assert_eq!(lg.recall(&path).as_deref(), Some(good), "a broken file is not remembered");
        // Saving it broken keeps the good copy; fixing and saving replaces it.
        ed.save().unwrap();
        assert_eq!(lg.recall(&path).as_deref(), Some(good));
        let fixed = good.replacen("sphere(0.5)", "sphere(0.6)", 1);
        ed.set_text(&fixed);
        assert!(ed.diagnostics().is_empty() && !ed.showing_last_good());
        ed.save().unwrap();
        assert_eq!(lg.recall(&path).as_deref(), Some(fixed.as_str()));

        // No kept version: nothing to show.
        let other = dir.path().join("other.species");
        std::fs::write(&other, &broken).unwrap();
        let ed = Editor::open_keeping(&other, Some(lg)).unwrap();
        assert!(ed.species().is_none() && !ed.showing_last_good());
        assert_eq!(ed.diagnostics().len(), 1);
    }

    fn monopodial() -> Editor {
        let e = library::find("monopodial").expect("library");
        Editor::from_source(e.file, e.text).expect("format")
    }

    #[test]
    fn a_broken_edit_keeps_the_last_good_model_and_reports_where() {
        let mut ed = monopodial();
        assert!(ed.diagnostics().is_empty(), "{:?}", ed.diagnostics());
        let (hash, rev) = (ed.amplified().expect("amplified").hash, ed.revision());
        let good = ed.text().to_string();
        ed.set_text(&good.replacen("param height = 20", "param height = 20 +", 1));
        assert!(!ed.diagnostics().is_empty());
        assert_eq!(ed.amplified().expect("kept").hash, hash);
        assert_eq!(ed.revision(), rev, "the preview does not change");
        let line = good.lines().position(|l| l.starts_with("param height")).expect("declared") + 1;
        assert!(ed.diagnostics().iter().any(|d| d.line == line || d.line == line + 1), "{:?}", ed.diagnostics());
        ed.set_text(&good.replacen("param height = 20", "param height = 21", 1));
        assert!(ed.diagnostics().is_empty());
        assert_ne!(ed.amplified().expect("new").hash, hash);
    }

    #[test]
    fn debounce_waits_for_a_pause() {
        let mut ed = monopodial();
        let t0 = 10.0;
        let text = ed.text().replacen("param height = 20", "param height = 22", 1);
        let before = ed.revision();
        ed.edit_text(text, t0);
        assert!(!ed.tick(t0 + DEBOUNCE / 2.0));
        assert_eq!(ed.revision(), before, "not parsed while typing");
        assert!(ed.tick(t0 + DEBOUNCE * 1.5));
        assert!(ed.revision() > before);
        assert!(!ed.tick(t0 + DEBOUNCE * 3.0));
    }

    #[test]
    fn sliders_cover_declared_parameters_and_the_instance_line_names_overrides() {
        let mut ed = monopodial();
        let p = ed.params();
        let h = p.iter().find(|c| c.name == "height").expect("height");
        assert_eq!((h.default, h.value, h.overridden), (20.0, 20.0, false));
        assert!(h.range.contains(&0.0) && h.range.contains(&40.0));
        ed.set_param("height", 12.5).expect("known");
        assert!(ed.params().iter().any(|c| c.name == "height" && c.value == 12.5 && c.overridden));
        assert_eq!(ed.instance_line(), "instance monopodial at 0 0 height=12.5");
        assert!(matches!(ed.set_param("nope", 1.0), Err(EditorError::Param(_))));
    }

    #[test]
    fn the_template_is_a_species() {
        let ed = Editor::from_source("new.species", TEMPLATE).expect("format");
        assert!(ed.diagnostics().is_empty(), "{:?}", ed.diagnostics());
        assert!(ed.amplified().is_some_and(|a| a.stream.primitives.len() == 2));
    }

    #[test]
    fn an_lsystem_hides_its_internal_parameters() {
        let e = library::find("bush").expect("library");
        let ed = Editor::from_source(e.file, e.text).expect("format");
        assert!(ed.diagnostics().is_empty(), "{:?}", ed.diagnostics());
        assert!(ed.params().iter().all(|p| !p.name.starts_with('_')));
    }
}
