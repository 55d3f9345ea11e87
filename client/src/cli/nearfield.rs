//! Near-field geometry on the command line (issue 5): the flags of `canopy species export` that ask for the
//! continuous mesh, seed 002's junctions, the double bark and a LOD chain; `canopy species nearfield` (seed 004's
//! Table 1 and the LOD reduction); `canopy species render` (a PNG close-up from the software rasteriser).

use std::path::Path;
use std::process::ExitCode;

use anyhow::bail;
use canopy_protocol::SpeciesGraph;
use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::mesh::{Mesh, MeshOptions, mesh_into_where};
use canopy_worlds::nearfield::bark::{BarkOptions, ChiselMode, outer_bark, trunk_places};
use canopy_worlds::nearfield::continuous::{ContinuousMesh, ContinuousOptions, continuous_mesh};
use canopy_worlds::nearfield::junction::{JunctionOptions, junction_mesh};
use canopy_worlds::nearfield::lod::{LodOptions, lod_chain};
use canopy_worlds::nearfield::options::species_options;
use canopy_worlds::nearfield::raster::{Camera, render};
use canopy_worlds::nearfield::skeleton::Skeleton;
use canopy_worlds::nearfield::{NearFieldOptions, NearParts, species_near_parts};
use canopy_worlds::primitive::{Primitive, PrimitiveStream, Shape};
use clap::{Args, ValueEnum};

/// Near-field flags of `canopy species export` and `canopy species render`; they override what the species'
/// `nearfield(...)` asks for.
#[derive(Args, Debug, Clone, Default)]
pub(crate) struct NearFieldArgs {
    /// Mesh the branches as one continuous surface (seed 004).
    #[arg(long, conflicts_with_all = ["junctions", "primitives"])]
    continuous: bool,
    /// One mesh per branch with seed 002's T, Y and I junctions.
    #[arg(long, conflicts_with = "primitives")]
    junctions: bool,
    /// Plain primitives, ignoring the species' near-field options.
    #[arg(long)]
    primitives: bool,
    /// Contour resolution of the continuous mesh (vertices per contour, 3..=256).
    #[arg(long)]
    contour: Option<u32>,
    /// Stitch junctions directly instead of refining them by intervals.
    #[arg(long)]
    direct: bool,
    /// Add contours along long branch pieces (about square quads; always on with a bark).
    #[arg(long)]
    subdivide: bool,
    /// Bark depth in metres: add the double bark's chiselled outer layer to the trunk (0 removes it).
    #[arg(long)]
    bark: Option<f32>,
    /// Chisel mode of the outer bark.
    #[arg(long, value_enum)]
    chisel: Option<Chisel>,
    /// First chisel factor: how much outer bark triangles shrink (0..=0.95).
    #[arg(long)]
    shrink: Option<f32>,
    /// Second chisel factor: the probability that a run of outer bark triangles is removed (0..=1).
    #[arg(long)]
    removal: Option<f32>,
    /// Also build a LOD chain of this many levels from the continuous mesh (thin branches first, trunk last).
    #[arg(long, default_value_t = 0)]
    lod: u32,
    /// Error bound of the LOD chain's last level, metres (level k of n gets k/n of it).
    #[arg(long, default_value_t = 0.02)]
    lod_error: f32,
}

/// The chisel modes by name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(super) enum Chisel {
    /// Shrink the outer bark's triangles.
    Shrink,
    /// Remove runs of them.
    Remove,
    /// Both.
    Both,
}

/// How one species' instances are meshed, resolved from the species and the flags.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Mode {
    /// One mesh per primitive (the ordinary mesher).
    Primitives,
    /// The continuous mesh.
    Continuous(ContinuousOptions),
    /// Seed 002's junctions.
    Junctions,
}

/// The resolved near-field plan.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Plan {
    /// How the branches are meshed.
    pub mode: Mode,
    /// The outer bark, if any.
    pub bark: Option<BarkOptions>,
    /// The LOD chain, if any.
    pub lod: Option<LodOptions>,
}

impl NearFieldArgs {
    /// Resolve the plan for an instance of `graph`: the species' options, then the flags.
    pub(crate) fn plan(&self, graph: &SpeciesGraph, instance: &Instance) -> anyhow::Result<Plan> {
        let asked = species_options(graph, instance)?;
        let mut mesh_opts = asked.map(|o| o.mesh).unwrap_or_default();
        if let Some(c) = self.contour {
            mesh_opts.contour = c;
        }
        if self.direct {
            mesh_opts.refine = false;
        }
        mesh_opts.check()?;
        let mode = if self.primitives {
            Mode::Primitives
        } else if self.junctions {
            Mode::Junctions
        } else if self.continuous || asked.is_some_and(|o| o.continuous) {
            Mode::Continuous(mesh_opts)
        } else {
            Mode::Primitives
        };
        let mut bark = if self.primitives { None } else { asked.and_then(|o| o.bark) };
        if let Some(depth) = self.bark {
            let default =
                BarkOptions { depth, chisel: ChiselMode::Both, shrink: 0.4, removal: 0.1, seed: instance.seed };
            bark = (depth > 0.0).then(|| bark.map_or(default, |b| BarkOptions { depth, ..b }));
        }
        if let Some(b) = bark.as_mut() {
            if let Some(c) = self.chisel {
                b.chisel = match c {
                    Chisel::Shrink => ChiselMode::Shrink,
                    Chisel::Remove => ChiselMode::Remove,
                    Chisel::Both => ChiselMode::Both,
                };
            }
            if let Some(s) = self.shrink {
                b.shrink = s;
            }
            if let Some(r) = self.removal {
                b.removal = r;
            }
            b.seed = instance.seed;
            b.check()?;
        } else if self.chisel.is_some() || self.shrink.is_some() || self.removal.is_some() {
            bail!("--chisel, --shrink and --removal need a bark: --bark DEPTH or `nearfield(bark = …)` in the species");
        }
        // The bark's plates want about square quads along the trunk: contours between the pieces' ends.
        let mode = match mode {
            Mode::Continuous(o) if bark.is_some() || self.subdivide => {
                Mode::Continuous(ContinuousOptions { subdivide: true, ..o })
            }
            m => m,
        };
        let lod = match (self.lod, mode) {
            (0, _) => None,
            (n, Mode::Continuous(_)) => Some(LodOptions { levels: n, error: self.lod_error }),
            _ => bail!("--lod needs the continuous mesh (--continuous or `nearfield(continuous = 1)`)"),
        };
        Ok(Plan { mode, bark, lod })
    }
}

/// The meshes of one instance under a plan.
pub(super) struct InstanceMeshes {
    /// The named meshes: the branches (or all primitives), the outer bark, the LOD levels and the foliage, in that
    /// order; empty ones are left out.
    pub parts: Vec<(String, Mesh)>,
    /// Why the continuous mesh of the branches is not one closed body, when it is not (the species draws pieces
    /// apart, or no branches at all).
    pub not_one_body: Option<String>,
}

/// The named meshes of one instance under a plan (see [`InstanceMeshes`]).
pub(super) fn instance_meshes(plan: &Plan, stream: &PrimitiveStream, detail: u8) -> anyhow::Result<InstanceMeshes> {
    let mut out = Vec::new();
    let mut not_one_body = None;
    let bark_of = |cm: &ContinuousMesh, b: &BarkOptions| -> anyhow::Result<Mesh> {
        let place = trunk_places(&cm.tags);
        Ok(outer_bark(&cm.mesh, &place, b)?)
    };
    match plan.mode {
        Mode::Continuous(mesh) => {
            let opts = NearFieldOptions { continuous: true, mesh, bark: plan.bark };
            let NearParts { continuous: cm, bark } = species_near_parts(stream, &opts)?;
            not_one_body = cm.why_not_one_body();
            let lods = match &plan.lod {
                Some(l) => lod_chain(&cm, l)?,
                None => Vec::new(),
            };
            out.push(("branches".to_string(), cm.mesh));
            out.extend(bark.map(|b| ("bark".to_string(), b)));
            for (k, level) in lods.into_iter().enumerate() {
                out.push((format!("lod{}", k + 1), level.mesh));
            }
            out.push(("foliage".to_string(), cm.foliage));
        }
        Mode::Junctions | Mode::Primitives => {
            let junctions = matches!(plan.mode, Mode::Junctions);
            let branches = if junctions { junction_mesh(stream, &JunctionOptions::default()) } else { Mesh::default() };
            // Everything the junction mesher leaves (trunk bases, foliage) or everything, through the ordinary mesher.
            let rest = |_, p: &Primitive| !junctions || !matches!(p.shape, Shape::Cone { .. } | Shape::Cylinder { .. });
            let mut meshed = Mesh::default();
            mesh_into_where(stream, &MeshOptions::for_detail(detail), rest, &mut meshed);
            let mut all = branches;
            all.append(&meshed, [0.0; 3]);
            out.push(("branches".to_string(), all));
            if let Some(b) = &plan.bark {
                // The trunk bases' outer bark: their sections as a continuous mesh of their own.
                let bases = PrimitiveStream {
                    primitives: stream
                        .primitives
                        .iter()
                        .filter(|p| matches!(p.shape, Shape::TrunkBase(_)))
                        .cloned()
                        .collect(),
                    leaf_points: Vec::new(),
                };
                if !bases.primitives.is_empty() {
                    let cm = continuous_mesh(&bases, &ContinuousOptions::default())?;
                    out.push(("bark".to_string(), bark_of(&cm, b)?));
                }
            }
        }
    }
    out.retain(|(_, m)| !m.is_empty());
    Ok(InstanceMeshes { parts: out, not_one_body })
}

/// `canopy species nearfield`: seed 004's Table 1 (triangles of the continuous mesh at contour resolutions 5, 9,
/// 12 and 15, direct against refined) and the LOD chain's reduction at an error bound.
pub(super) fn table(
    graph: &SpeciesGraph,
    instance: &Instance,
    budget: &Budget,
    levels: u32,
    error: f32,
) -> anyhow::Result<ExitCode> {
    let stream = amplify(graph, instance, budget)?;
    let sk = Skeleton::from_stream(&stream);
    let (lo, hi) = stream.bounds();
    println!(
        "species {} seed {}: {} primitives, {} branch segments, {} junction pieces, height {:.2} m",
        graph.name,
        instance.seed,
        stream.primitives.len(),
        sk.segments.len(),
        sk.pieces.len(),
        hi[1] - lo[1]
    );
    println!("\nTriangles of the continuous mesh (seed 004 Table 1):");
    println!("{:>18} {:>14} {:>18} {:>8}", "contour resolution", "direct method", "interval refining", "ratio");
    for contour in [5, 9, 12, 15] {
        let count = |refine| -> anyhow::Result<usize> {
            let o = ContinuousOptions { contour, refine, ..ContinuousOptions::default() };
            Ok(continuous_mesh(&stream, &o)?.mesh.triangle_count())
        };
        let (d, r) = (count(false)?, count(true)?);
        println!("{contour:>18} {d:>14} {r:>18} {:>7.2}×", r as f64 / d as f64);
    }
    let o = ContinuousOptions { contour: 12, refine: true, ..ContinuousOptions::default() };
    let cm = continuous_mesh(&stream, &o)?;
    let full = cm.mesh.triangle_count();
    println!(
        "\nLOD chain of the refined mesh at contour resolution 12 (meshoptimizer; thin branches first, trunk last):"
    );
    println!(
        "{:>6} {:>14} {:>12} {:>14} {:>10} {:>10}",
        "level", "radius ≤ (m)", "bound (m)", "error (m)", "triangles", "reduction"
    );
    println!("{:>6} {:>14} {:>12} {:>14} {:>10} {:>10}", 0, "-", "-", "-", full, "0.0%");
    for (k, l) in lod_chain(&cm, &LodOptions { levels, error })?.iter().enumerate() {
        let radius = if l.max_radius.is_finite() { format!("{:.4}", l.max_radius) } else { "all".to_string() };
        let t = l.mesh.triangle_count();
        println!(
            "{:>6} {:>14} {:>12.4} {:>14.5} {:>10} {:>9.1}%",
            k + 1,
            radius,
            l.bound,
            l.error,
            t,
            100.0 * (1.0 - t as f64 / full as f64)
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// What `canopy species render` frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum View {
    /// The whole tree.
    Tree,
    /// The trunk base (the lowest part of the tree, widened to the root flares).
    Base,
    /// The first junction with several children, close up.
    Junction,
}

/// Render one instance under a plan to a PNG.
#[allow(clippy::too_many_arguments)]
pub(super) fn render_png(
    graph: &SpeciesGraph,
    instance: &Instance,
    budget: &Budget,
    plan: &Plan,
    view: View,
    out: &Path,
    size: (u32, u32),
    angles: (f64, f64, f64),
) -> anyhow::Result<ExitCode> {
    let stream = amplify(graph, instance, budget)?;
    let parts = instance_meshes(&Plan { lod: None, ..*plan }, &stream, instance.detail)?.parts;
    let meshes: Vec<&Mesh> = parts.iter().map(|(_, m)| m).collect();
    let all = parts.iter().fold(Mesh::default(), |mut acc, (_, m)| {
        acc.append(m, [0.0; 3]);
        acc
    });
    if all.is_empty() {
        bail!("species `{}` has no geometry to render", graph.name);
    }
    let (lo, hi) = match view {
        View::Tree => all.bounds(),
        View::Base => {
            let (lo, hi) = all.bounds();
            let sk = Skeleton::from_stream(&stream);
            let top = sk
                .segments
                .iter()
                .find(|s| s.sections.is_some())
                .map(|s| s.top_centre()[1] as f32)
                .unwrap_or(lo[1] + 0.15 * (hi[1] - lo[1]));
            let near: Vec<[f32; 3]> = all.positions.iter().filter(|p| p[1] <= top * 1.15).copied().collect();
            bounds_of(&near).unwrap_or((lo, hi))
        }
        View::Junction => {
            let sk = Skeleton::from_stream(&stream);
            let Some(id) = sk.pieces.iter().position(|p| p.children.len() > 1) else {
                bail!("species `{}` has no junction with several branches", graph.name);
            };
            let s = sk.segment(id);
            let o = s.at(sk.pieces[id].t1).map(|x| x as f32);
            let r = (s.radius(sk.pieces[id].t1) as f32).max(1e-3) * 5.0;
            ([o[0] - r, o[1] - 0.6 * r, o[2] - r], [o[0] + r, o[1] + 1.4 * r, o[2] + r])
        }
    };
    let camera = Camera::framing(lo, hi, angles.0, angles.1, angles.2);
    // A patch of ground under the trunk base.
    let ground = (view == View::Base).then(|| ground_disc(lo, hi));
    let mut meshes = meshes;
    if let Some(g) = &ground {
        meshes.push(g);
    }
    let image = render(&meshes, &camera, size.0, size.1);
    crate::cli::write_file(out, &image.png()?)?;
    let tris: usize = meshes.iter().map(|m| m.triangle_count()).sum();
    println!("wrote {} ({}×{}, {} triangles)", out.display(), image.width, image.height, tris);
    Ok(ExitCode::SUCCESS)
}

/// A flat disc at the lowest point of the box, wider than the box, earth-coloured.
fn ground_disc(lo: [f32; 3], hi: [f32; 3]) -> Mesh {
    let c = [0.5 * (lo[0] + hi[0]), lo[1], 0.5 * (lo[2] + hi[2])];
    let r = 1.5 * (hi[0] - lo[0]).max(hi[2] - lo[2]).max(1e-3);
    let n = 64u32;
    let mut m = Mesh::default();
    m.positions.push(c);
    for k in 0..n {
        let a = std::f32::consts::TAU * k as f32 / n as f32;
        m.positions.push([c[0] + r * a.cos(), c[1], c[2] - r * a.sin()]);
    }
    m.normals = vec![[0.0, 1.0, 0.0]; m.positions.len()];
    m.colors = vec![[0.33, 0.30, 0.22]; m.positions.len()];
    for k in 0..n {
        m.indices.extend_from_slice(&[0, 1 + k, 1 + (k + 1) % n]);
    }
    m
}

fn bounds_of(points: &[[f32; 3]]) -> Option<([f32; 3], [f32; 3])> {
    let first = *points.first()?;
    Some(points.iter().fold((first, first), |(mut lo, mut hi), p| {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
        (lo, hi)
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_worlds::diag::SourceFile;
    use canopy_worlds::load::parse_source;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        near: NearFieldArgs,
    }

    fn args(list: &[&str]) -> NearFieldArgs {
        Cli::try_parse_from(std::iter::once("t").chain(list.iter().copied())).expect("flags parse").near
    }

    fn fig() -> SpeciesGraph {
        let text = include_str!("../../../worlds/species/fig.species");
        parse_source(&SourceFile::new("fig.species", text)).0.expect("fig parses")
    }

    #[test]
    fn species_options_then_flags() {
        let (g, inst) = (fig(), Instance::new(2));
        let p = args(&[]).plan(&g, &inst).unwrap();
        let Mode::Continuous(o) = p.mode else { panic!("fig asks for the continuous mesh") };
        assert!(o.refine && o.subdivide && o.contour == 12);
        assert_eq!(p.bark.map(|b| (b.depth, b.seed)), Some((0.02, 2)));
        let p = args(&["--direct", "--contour", "5", "--bark", "0", "--lod", "3"]).plan(&g, &inst).unwrap();
        let Mode::Continuous(o) = p.mode else { panic!("still continuous") };
        assert!(!o.refine && !o.subdivide && o.contour == 5 && p.bark.is_none());
        assert_eq!(p.lod.map(|l| l.levels), Some(3));
        let p = args(&["--primitives"]).plan(&g, &inst).unwrap();
        assert!(matches!(p.mode, Mode::Primitives) && p.bark.is_none());
        let p = args(&["--junctions", "--chisel", "remove", "--removal", "0.5"]).plan(&g, &inst).unwrap();
        assert!(matches!(p.mode, Mode::Junctions));
        assert_eq!(p.bark.map(|b| (b.chisel, b.removal)), Some((ChiselMode::Remove, 0.5)));
    }

    #[test]
    fn bad_flag_combinations_are_errors() {
        let (g, inst) = (fig(), Instance::new(1));
        let worm = canopy_worlds::library::find("worm").unwrap().load().unwrap();
        assert!(args(&["--lod", "2"]).plan(&worm, &inst).is_err(), "a LOD chain needs the continuous mesh");
        assert!(args(&["--shrink", "0.3"]).plan(&worm, &inst).is_err(), "chisel factors need a bark");
        assert!(args(&["--contour", "2"]).plan(&g, &inst).is_err());
        assert!(args(&["--bark", "0.01", "--removal", "3"]).plan(&g, &inst).is_err());
        assert!(Cli::try_parse_from(["t", "--continuous", "--junctions"]).is_err());
    }

    #[test]
    fn instance_meshes_name_their_parts() {
        let (g, inst) = (fig(), Instance::new(1));
        let stream = amplify(&g, &inst, &Budget::default()).unwrap();
        let plan = args(&["--lod", "2"]).plan(&g, &inst).unwrap();
        let names: Vec<String> =
            instance_meshes(&plan, &stream, 0).unwrap().parts.into_iter().map(|(n, _)| n).collect();
        assert_eq!(names, ["branches", "bark", "lod1", "lod2", "foliage"]);
        let plan = args(&["--junctions"]).plan(&g, &inst).unwrap();
        let names: Vec<String> =
            instance_meshes(&plan, &stream, 0).unwrap().parts.into_iter().map(|(n, _)| n).collect();
        assert_eq!(names, ["branches", "bark"]);
        assert_eq!(instance_meshes(&plan, &stream, 0).unwrap().not_one_body, None, "no continuous mesh asked for");
        // The fig is one body; conifer needle tufts (detail 0) are drawn apart from any branch, and the export
        // says so.
        let plan = args(&[]).plan(&g, &inst).unwrap();
        assert_eq!(instance_meshes(&plan, &stream, 0).unwrap().not_one_body, None);
        let conifer = canopy_worlds::library::find("conifer").unwrap().load().unwrap();
        let stream = amplify(&conifer, &inst, &Budget::default()).unwrap();
        let plan = args(&["--continuous", "--contour", "3"]).plan(&conifer, &inst).unwrap();
        let why = instance_meshes(&plan, &stream, 0).unwrap().not_one_body.expect("needle tufts apart");
        assert!(why.contains("branch systems that touch no other"), "{why}");
    }
}
