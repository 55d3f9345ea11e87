//! Hypertrees in the editor (seed 000 §10: "the framework … allowing the user to adjust the parameters before the
//! hypertree generation begins"): a `.hyp` definition with sliders for the resolution, the iterations and every
//! per-level transformation value, generated and raymarched (the CPU reference renderer) on change; and the far
//! field of a species — its instance voxelised into a hypervolume (seed 000 §12) and raymarched the same way.

use canopy_protocol::hypertree::{Elementary, HypertreeDef, Param};
use canopy_worlds::amplify::{Budget, Instance};
use canopy_worlds::hypertree::Hypertree;
use canopy_worlds::hypertree::generate::{GenerateOptions, generate};
use canopy_worlds::hypertree::render::{Image, RenderOptions, render};
use canopy_worlds::hypertree::voxelise::{VoxeliseOptions, voxelise};

use crate::species::Species;

/// A new hypertree when the file does not exist yet: a trunk and four branch transformations.
pub(crate) const TEMPLATE: &str = "# A new hypertree (seed 000 §10): edit, and the raymarched preview follows.\n\
NAME sapling\n\
RESOLUTION 128\n\
ITERATIONS 200000\n\
TREEDEPTH 6\n\
BRANCHDEPTH 2\n\
DENSITYCLASSES 64\n\
DEPTHCOLOR 0 2 0.30 0.21 0.13 0.36 0.27 0.16\n\
DEPTHCOLOR 3 5 0.12 0.32 0.10 0.40 0.56 0.16\n\
HYPERVOLUME 0.8 0.8 0.8\n\
DISPLACEMENT 0.4 0.005 0.4\n\
POINTINIT 0 0 0\n\
CONDENSATION 1\n\
  CONE Y 0 0.36 0.032 0.016\n\
TRANSFORM 0.25 255\n\
  SCALE 0.55\n\
  ROTATE Z (-35 -25)\n\
  ROTATE Y 90\n\
  TRANSLATE 0 0.36 0\n\
TRANSFORM 0.25 255\n\
  SCALE 0.55\n\
  ROTATE Z (35 25)\n\
  ROTATE Y -90\n\
  TRANSLATE 0 0.33 0\n\
TRANSFORM 0.25 255\n\
  SCALE 0.5\n\
  ROTATE X (40 30)\n\
  TRANSLATE 0 0.28 0\n\
TRANSFORM 0.25 255\n\
  SCALE 0.5\n\
  ROTATE X (-40 -30)\n\
  TRANSLATE 0 0.24 0\n";

/// Voxels along the longest axis of the preview's generation at most (the definition's own resolution is used up
/// to this; the slider goes higher).
pub(crate) const PREVIEW_RESOLUTION: u32 = 160;
/// Iterations of the preview's generation at most by default.
pub(crate) const PREVIEW_ITERATIONS: u64 = 400_000;

/// A hypertree definition with the editor's slider values.
#[derive(Clone, Debug)]
pub struct HypertreeModel {
    /// The definition as parsed from the text.
    pub parsed: HypertreeDef,
    /// The definition generated: the parsed one with the sliders' transformation values.
    pub def: HypertreeDef,
    /// Voxels along the longest axis.
    pub resolution: u32,
    /// Generators to produce.
    pub iterations: u64,
    /// The tree's seed (random values are drawn once per tree).
    pub seed: u64,
}

/// One slider over a transformation value at one level.
#[derive(Debug)]
pub struct LevelValue<'a> {
    /// `T2 rotate Z, level 1` and the like.
    pub label: String,
    /// The value's mean (its spread is kept).
    pub value: &'a mut f32,
}

impl HypertreeModel {
    /// The model of a parsed definition: preview resolution and iterations capped for interactivity.
    pub fn new(def: HypertreeDef) -> HypertreeModel {
        let longest = def.resolution.iter().copied().max().unwrap_or(1);
        HypertreeModel {
            resolution: longest.min(PREVIEW_RESOLUTION),
            iterations: def.iterations.min(PREVIEW_ITERATIONS),
            parsed: def.clone(),
            def,
            seed: 1,
        }
    }

    /// The text changed: its definition replaces the slider values (the text wins); resolution and iterations stay.
    pub fn replace(&mut self, def: HypertreeDef) {
        self.parsed = def.clone();
        self.def = def;
    }

    /// The resolution per axis: the definition's proportions with `resolution` voxels along the longest.
    pub fn resolution3(&self) -> [u32; 3] {
        let r = self.def.resolution;
        let longest = r.iter().copied().max().unwrap_or(1).max(1);
        r.map(|v| ((u64::from(v) * u64::from(self.resolution)) / u64::from(longest)).max(1) as u32)
    }

    /// Every per-level value of every transformation (and condensation), for sliders.
    pub fn level_values(&mut self) -> Vec<LevelValue<'_>> {
        let mut out = Vec::new();
        for (j, t) in self.def.transformations.iter_mut().enumerate() {
            for step in t.steps.iter_mut() {
                push_step(&format!("T{}", j + 1), step, &mut out);
            }
        }
        for (j, c) in self.def.condensations.iter_mut().enumerate() {
            for step in c.then.iter_mut() {
                push_step(&format!("C{}", j + 1), step, &mut out);
            }
        }
        out
    }

    /// Generate the hypertree (the sliders' definition, resolution and iterations).
    pub fn generate(&self) -> Result<Hypertree, String> {
        let opts = GenerateOptions {
            resolution: Some(self.resolution3()),
            iterations: Some(self.iterations),
            ..GenerateOptions::default()
        };
        generate(&self.def, self.seed, &opts, &mut |_, _| {}).map(|(t, _)| t).map_err(|e| e.to_string())
    }
}

fn push_param<'a>(label: String, p: &'a mut Param, out: &mut Vec<LevelValue<'a>>) {
    let levels = p.0.len();
    for (k, v) in p.0.iter_mut().enumerate() {
        let label = if levels > 1 { format!("{label}, level {}", k + 1) } else { label.clone() };
        out.push(LevelValue { label, value: &mut v.mean });
    }
}

fn push_step<'a>(owner: &str, step: &'a mut Elementary, out: &mut Vec<LevelValue<'a>>) {
    const XYZ: [&str; 3] = ["x", "y", "z"];
    match step {
        Elementary::Translate(v) => {
            for (p, a) in v.iter_mut().zip(XYZ) {
                push_param(format!("{owner} translate {a}"), p, out);
            }
        }
        Elementary::Scale(v) => {
            for (p, a) in v.iter_mut().zip(XYZ) {
                push_param(format!("{owner} scale {a}"), p, out);
            }
        }
        Elementary::Rotate { axis, angle } => push_param(format!("{owner} rotate {axis:?}"), angle, out),
        Elementary::Shear { axis, max, exponent } => {
            let [a, b] = max;
            push_param(format!("{owner} shear {axis:?} d1"), a, out);
            push_param(format!("{owner} shear {axis:?} d2"), b, out);
            push_param(format!("{owner} shear {axis:?} exponent"), exponent, out);
        }
    }
}

/// Raymarch a hypertree with the CPU reference renderer (seed 000 §8) into a `width × height` image, seen from
/// `azimuth` degrees, lit as `lit` says.
pub(crate) fn raymarch(
    tree: &Hypertree,
    lit: &RenderOptions,
    width: u32,
    height: u32,
    azimuth: f32,
) -> Result<Image, String> {
    let opts = RenderOptions { width, height, azimuth, ..lit.clone() };
    render(tree, &opts, &mut |_, _| {}).map(|(img, _)| img).map_err(|e| e.to_string())
}

/// The far field of a species instance: its amplified stream voxelised into a hypervolume (`resolution` voxels
/// along the longest axis).
pub(crate) fn species_volume(
    species: &Species,
    instance: &Instance,
    budget: &Budget,
    resolution: u32,
) -> Result<Hypertree, String> {
    let stream = species.amplify(instance, budget).map_err(|e| e.to_string())?;
    let opts = VoxeliseOptions { resolution, ..VoxeliseOptions::default() };
    voxelise(&stream, &species.graph.name, &opts).map_err(|e| e.to_string())
}

/// Voxels along the longest axis of a species' far-field volume in the editor.
pub(crate) const FAR_RESOLUTION: u32 = 96;
/// Side of the raymarched images, pixels.
pub(crate) const IMAGE_SIDE: u32 = 384;

/// A raymarched image and a line saying what it took.
#[derive(Clone, Debug)]
pub(crate) struct VolumeImage {
    /// The image.
    pub image: Image,
    /// `generated 64×64×64 voxels in 80 ms, raymarched in 120 ms` and the like.
    pub summary: String,
    /// The same without the times (`generated 64×64×64 voxels, raymarched`).
    pub untimed: String,
}

/// The work behind a raymarched view, taken from the model so it can run on another thread.
#[derive(Clone, Debug)]
pub(crate) enum VolumeJob {
    /// Generate a `.hyp` and raymarch it.
    Hypertree(Box<HypertreeModel>, f32),
    /// Voxelise a species instance and raymarch it.
    Species(Species, Instance, Budget, f32),
}

impl VolumeJob {
    /// The job for the model's current state, if it has something to show.
    pub(crate) fn of(model: &crate::model::Editor, azimuth: f32) -> Option<VolumeJob> {
        if let Some(h) = model.hypertree() {
            return Some(VolumeJob::Hypertree(Box::new(h.clone()), azimuth));
        }
        let s = model.species()?;
        Some(VolumeJob::Species(s.clone(), model.instance(), *model.budget(), azimuth))
    }

    /// Generate (or voxelise) and raymarch.
    pub(crate) fn run(&self) -> Result<VolumeImage, String> {
        let t = std::time::Instant::now();
        // A `.hyp` in the paper's shading model; a species' far field as the walkthrough shades it.
        let (tree, lit, azimuth, what) = match self {
            VolumeJob::Hypertree(h, a) => (h.generate()?, RenderOptions::default(), *a, "generated"),
            VolumeJob::Species(s, i, b, a) => (
                species_volume(s, i, b, FAR_RESOLUTION)?,
                canopy_render::Lighting::default().reference_options(),
                *a,
                "voxelised",
            ),
        };
        let made = t.elapsed().as_secs_f64() * 1e3;
        let t = std::time::Instant::now();
        let image = raymarch(&tree, &lit, IMAGE_SIDE, IMAGE_SIDE, azimuth)?;
        let marched = t.elapsed().as_secs_f64() * 1e3;
        let r = tree.volume.resolution;
        Ok(VolumeImage {
            image,
            summary: format!("{what} {}×{}×{} voxels in {made:.0} ms, raymarched in {marched:.0} ms", r[0], r[1], r[2]),
            untimed: format!("{what} {}×{}×{} voxels, raymarched", r[0], r[1], r[2]),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_worlds::diag::SourceFile;
    use canopy_worlds::hypertree::format::parse_hypertree;

    #[test]
    fn the_template_parses_generates_and_its_sliders_change_the_tree() {
        let (def, diags) = parse_hypertree(&SourceFile::new("new.hyp", TEMPLATE));
        assert!(diags.is_empty(), "{diags:?}");
        let mut m = HypertreeModel::new(def.expect("parses"));
        m.resolution = 48;
        m.iterations = 20_000;
        let a = m.generate().expect("generates");
        let labels: Vec<String> = m.level_values().iter().map(|v| v.label.clone()).collect();
        assert!(labels.iter().any(|l| l == "T1 rotate Z, level 2"), "{labels:?}");
        let mut values = m.level_values();
        let v = values.iter_mut().find(|v| v.label == "T1 rotate Z, level 1").expect("slider");
        *v.value = 10.0;
        let b = m.generate().expect("generates");
        assert_ne!(a.hash(), b.hash(), "a slider changes the tree");
        let img = raymarch(&b, &RenderOptions::default(), 32, 32, 0.0).expect("renders");
        assert_eq!(img.pixels.len(), 32 * 32 * 3);
    }
}
