//! `canopy species check|stats|amplify|export|list|edit` and `canopy demo`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, bail};
use canopy_harness::numbers::group;
use canopy_protocol::SpeciesGraph;
use canopy_worlds::amplify::{Budget, Instance, amplify, resolve_params};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::gltf::{MAX_GLB_BYTES, SizeCheck, glb};
use canopy_worlds::library;
use canopy_worlds::load::{CHECK_SEED, check_file, load, read_source};
use canopy_worlds::lsystem::LSystem;
use canopy_worlds::mesh::{Mesh, MeshOptions, explicit_bytes, mesh};
use canopy_worlds::primitive::PrimitiveStream;
use clap::{Args, Subcommand};

#[path = "export.rs"]
mod export;
#[path = "nearfield.rs"]
mod nearfield;

#[derive(Subcommand, Debug)]
pub(super) enum SpeciesCommand {
    /// Validate species files (.species, .lsys); print every diagnostic with file:line:col. Each species that
    /// parses is also amplified once (seed 0, default parameters, default budget): one that cannot finish fails.
    Check {
        /// Files to check; all are checked even if one fails.
        #[arg(required = true)]
        files: Vec<PathBuf>,
    },
    /// Amplify one instance and report counts by kind, traversal time and sizes (encoded vs explicit geometry).
    Stats {
        #[command(flatten)]
        instance: InstanceArgs,
        /// Traversals to time (the median is reported).
        #[arg(long, default_value_t = 11)]
        repeat: u32,
    },
    /// Amplify one instance and print (or write) its primitive stream and golden hashes.
    Amplify {
        #[command(flatten)]
        instance: InstanceArgs,
        /// Write the primitive stream here, one primitive per line (`-` for stdout).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Export one instance, or a grove of instances, as glTF 2.0 binary (.glb), streamed: each instance is made
    /// twice (to lay the file out, then to write it), so memory holds one instance's meshes whatever the grove.
    Export {
        #[command(flatten)]
        instance: InstanceArgs,
        /// Output file.
        #[arg(long, short)]
        out: PathBuf,
        /// Instances on a square grid (seeds seed, seed+1, …).
        #[arg(long, default_value_t = 1)]
        grove: u32,
        /// Grid spacing of the grove, metres.
        #[arg(long, default_value_t = 8.0)]
        spacing: f32,
        /// Refuse to write a file over this many bytes (checked before writing; at most and by default 4294967295,
        /// the GLB limit: its lengths are u32).
        #[arg(long, default_value_t = MAX_GLB_BYTES)]
        max_bytes: u64,
        /// Mesh every instance to check the size exactly, instead of refusing at once a grove that the first
        /// instance's size times --grove puts more than 10% over the limit (the trees of a grove differ in size).
        #[arg(long)]
        no_estimate: bool,
        #[command(flatten)]
        near: nearfield::NearFieldArgs,
    },
    /// Near-field numbers of one instance: seed 004's Table 1 (continuous mesh triangles at contour resolutions
    /// 5, 9, 12, 15, direct against refined junctions) and the LOD chain's reduction at an error bound.
    Nearfield {
        #[command(flatten)]
        instance: InstanceArgs,
        /// LOD levels.
        #[arg(long, default_value_t = 4)]
        levels: u32,
        /// Error bound of the last LOD level, metres.
        #[arg(long, default_value_t = 0.02)]
        error: f32,
    },
    /// Render one instance to a PNG with the software rasteriser (near-field meshing as for export).
    Render {
        #[command(flatten)]
        instance: InstanceArgs,
        /// Output file (.png).
        #[arg(long, short)]
        out: PathBuf,
        /// What to frame.
        #[arg(long, value_enum, default_value_t = nearfield::View::Tree)]
        view: nearfield::View,
        /// Image width in pixels.
        #[arg(long, default_value_t = 960)]
        width: u32,
        /// Image height in pixels.
        #[arg(long, default_value_t = 720)]
        height: u32,
        /// Camera azimuth in degrees about +Y.
        #[arg(long, default_value_t = 30.0, allow_negative_numbers = true)]
        azimuth: f64,
        /// Camera elevation in degrees.
        #[arg(long, default_value_t = 20.0, allow_negative_numbers = true)]
        elevation: f64,
        /// Zoom: 1 frames the view's box, more comes closer.
        #[arg(long, default_value_t = 1.0)]
        zoom: f64,
        #[command(flatten)]
        near: nearfield::NearFieldArgs,
    },
    /// List the embedded species library.
    List,
    /// The species editor: the source with diagnostics, a live 3D preview, parameter sliders, a grove and the
    /// far field; `.hyp` hypertree definitions too (docs/editor.md).
    Edit(EditArgs),
    /// Amplify every species of the embedded library, print its numbers and export a grove (.glb).
    Demo(DemoArgs),
}

/// Which instance to amplify, and under what budget.
#[derive(Args, Debug, Clone)]
pub(super) struct InstanceArgs {
    /// A species file (.species or .lsys) or the name of an embedded library species (`canopy species list`).
    species: String,
    /// Instance seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Detail level: 0 is full detail; higher selects LOD substitutes and lowers recursion depth.
    #[arg(long, default_value_t = 0)]
    detail: u8,
    /// Override a parameter: `--param height=12` (repeatable).
    #[arg(long = "param", value_parser = parse_setting)]
    params: Vec<(String, f32)>,
    /// Most primitives one instance may emit.
    #[arg(long, default_value_t = Budget::default().max_primitives)]
    max_primitives: u32,
    /// Most traversal steps one instance may take.
    #[arg(long, default_value_t = Budget::default().max_steps)]
    max_steps: u64,
}

fn parse_setting(s: &str) -> Result<(String, f32), String> {
    let (k, v) = s.split_once('=').ok_or_else(|| format!("expected NAME=VALUE, got `{s}`"))?;
    let v: f32 = v.trim().parse().map_err(|_| format!("`{v}` is not a number"))?;
    if !v.is_finite() {
        return Err(format!("`{v}` is not finite"));
    }
    Ok((k.trim().to_string(), v))
}

/// An instance request validated against its species: the config the library calls take.
pub(super) struct InstanceConfig {
    pub(super) graph: SpeciesGraph,
    pub(super) instance: Instance,
    pub(super) budget: Budget,
    /// The L-system the graph was compiled from, when it was one: its errors are reported in its own terms.
    lsystem: Option<LSystem>,
}

impl InstanceConfig {
    /// Amplify `instance` of the species under the budget; an L-system that derives too deep says so with its
    /// derivation depth and production.
    pub(super) fn amplify(&self, instance: &Instance) -> anyhow::Result<PrimitiveStream> {
        Ok(match &self.lsystem {
            Some(l) => l.amplify(instance, &self.budget)?,
            None => amplify(&self.graph, instance, &self.budget)?,
        })
    }
}

/// The L-system a species argument names (a `.lsys` file, or a library entry written as one), if it does.
fn lsystem_of(name_or_path: &str) -> Option<LSystem> {
    let src = if Path::new(name_or_path).is_file() {
        read_source(Path::new(name_or_path)).ok()?
    } else {
        let entry = library::find(name_or_path)?;
        SourceFile::new(entry.file, entry.text)
    };
    src.name.ends_with(".lsys").then(|| LSystem::parse(&src).0).flatten()
}

impl InstanceArgs {
    pub(super) fn config(&self) -> anyhow::Result<InstanceConfig> {
        // An L-system is parsed once and its graph taken from it; `load` reports what does not parse.
        let lsystem = lsystem_of(&self.species);
        let graph = match &lsystem {
            Some(l) => l.graph.clone(),
            None => load(&self.species).map_err(|d| anyhow::anyhow!("{d}"))?,
        };
        let params = resolve_params(&graph, &self.params).map_err(anyhow::Error::msg)?;
        let budget = Budget { max_primitives: self.max_primitives, max_steps: self.max_steps, ..Budget::default() };
        Ok(InstanceConfig {
            graph,
            instance: Instance { seed: self.seed, params, detail: self.detail },
            budget,
            lsystem,
        })
    }
}

/// `canopy species edit [FILE] [--screenshot out.png | --exit-after SECONDS]`.
#[derive(Args, Debug)]
pub(super) struct EditArgs {
    /// A `.species`, `.lsys` or `.hyp` file (created on save if it does not exist), or an embedded library species;
    /// none starts a new species.
    file: Option<PathBuf>,
    /// Render the editor window once into this PNG (offscreen) and exit.
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// Override a parameter: `--param height=12` (repeatable).
    #[arg(long = "param", value_parser = parse_setting)]
    params: Vec<(String, f32)>,
    /// The previewed seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// The detail level.
    #[arg(long, default_value_t = 0)]
    detail: u8,
    /// The view to start in.
    #[arg(long, value_parser = super::named(&canopy_editor::ui::View::NAMES), default_value_t = canopy_editor::ui::View::Tree)]
    view: canopy_editor::ui::View,
    /// Window (and screenshot) width, pixels.
    #[arg(long, default_value_t = 1280)]
    width: u32,
    /// Window (and screenshot) height, pixels.
    #[arg(long, default_value_t = 800)]
    height: u32,
    /// Close the window by itself after this many seconds (prints the frames presented; tests, demos).
    #[arg(long, value_name = "SECONDS", conflicts_with = "screenshot")]
    exit_after: Option<f64>,
}

fn edit(args: EditArgs) -> anyhow::Result<ExitCode> {
    if !(320..=8192).contains(&args.width) || !(240..=8192).contains(&args.height) {
        bail!("--width must be 320..=8192 and --height 240..=8192, got {}×{}", args.width, args.height);
    }
    let exit_after = match args.exit_after {
        Some(s) if s.is_finite() && (0.0..=86_400.0).contains(&s) => Some(std::time::Duration::from_secs_f64(s)),
        Some(s) => bail!("--exit-after must be 0..=86400 seconds, got {s}"),
        None => None,
    };
    let cfg = canopy_editor::EditConfig {
        file: args.file,
        params: args.params,
        seed: args.seed,
        detail: args.detail,
        screenshot: args.screenshot.clone(),
        size: (args.width, args.height),
        view: args.view,
        exit_after,
        last_good: canopy_editor::last_good::LastGood::from_env(),
    };
    canopy_editor::run(&cfg)?;
    if let Some(out) = args.screenshot {
        println!("wrote {}", out.display());
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(Args, Debug)]
pub(super) struct DemoArgs {
    /// Where to write the grove.
    #[arg(long, default_value = "out/demo-grove.glb")]
    out: PathBuf,
    /// Instances of each species in the grove.
    #[arg(long, default_value_t = 3)]
    per_species: u32,
}

pub(super) fn run(cmd: SpeciesCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        SpeciesCommand::Check { files } => Ok(check(&files)),
        SpeciesCommand::Stats { instance, repeat } => stats(&instance.config()?, repeat.max(1)),
        SpeciesCommand::Amplify { instance, out } => amplify_cmd(&instance.config()?, out),
        SpeciesCommand::Export { instance, out, grove, spacing, max_bytes, no_estimate, near } => {
            let check = if no_estimate { SizeCheck::Exact } else { SizeCheck::Estimate };
            export::export(&instance.config()?, &out, grove, spacing, max_bytes, check, &near)
        }
        SpeciesCommand::Nearfield { instance, levels, error } => {
            let cfg = instance.config()?;
            nearfield::table(&cfg.graph, &cfg.instance, &cfg.budget, levels, error)
        }
        SpeciesCommand::Render { instance, out, view, width, height, azimuth, elevation, zoom, near } => {
            let cfg = instance.config()?;
            let plan = near.plan(&cfg.graph, &cfg.instance)?;
            nearfield::render_png(
                &cfg.graph,
                &cfg.instance,
                &cfg.budget,
                &plan,
                view,
                &out,
                (width, height),
                (azimuth, elevation, zoom),
            )
        }
        SpeciesCommand::Demo(args) => demo(args),
        SpeciesCommand::Edit(args) => edit(args),
        SpeciesCommand::List => {
            for e in library::SPECIES {
                let g = e.load().map_err(|d| anyhow::anyhow!("{d}"))?;
                println!(
                    "{:<14} {:<22} {:>5} nodes {:>6} bytes  {}",
                    e.name(),
                    e.file,
                    g.nodes.len(),
                    g.encode().len(),
                    g.name
                );
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}

fn check(files: &[PathBuf]) -> ExitCode {
    let mut failed = 0;
    for f in files {
        let (checked, diags) = check_file(f, &Budget::default());
        for d in &diags {
            println!("{d}\n");
        }
        match checked {
            Some(c) => println!(
                "ok      {} — species `{}`: {} nodes, {} parameters, {} bytes encoded; seed {CHECK_SEED} with default \
                 parameters: {} primitives",
                f.display(),
                c.graph.name,
                c.graph.nodes.len(),
                c.graph.params.len(),
                c.graph.encode().len(),
                group(c.primitives as u64)
            ),
            None => {
                failed += 1;
                println!("failed  {} — {} error(s)", f.display(), diags.len());
            }
        }
    }
    println!("{} file(s) checked, {} failed", files.len(), failed);
    if failed == 0 { ExitCode::SUCCESS } else { ExitCode::FAILURE }
}

fn stats(cfg: &InstanceConfig, repeat: u32) -> anyhow::Result<ExitCode> {
    // One measurement for this command and the editor's stats panel.
    let species = canopy_editor::species::Species::new(cfg.graph.clone(), cfg.lsystem.clone());
    let (stats, _) = canopy_editor::stats::measure(&species, &cfg.instance, &cfg.budget, repeat)?;
    for line in stats.lines() {
        println!("{line}");
    }
    Ok(ExitCode::SUCCESS)
}

fn amplify_cmd(cfg: &InstanceConfig, out: Option<PathBuf>) -> anyhow::Result<ExitCode> {
    let stream = cfg.amplify(&cfg.instance)?;
    let m = mesh(&stream, &MeshOptions::for_detail(cfg.instance.detail));
    println!("species     {}", cfg.graph.name);
    println!(
        "primitives  {}  ({})",
        group(stream.primitives.len() as u64),
        canopy_editor::stats::counts_line(&stream.counts())
    );
    println!("stream hash {:016x}", stream.hash());
    println!("mesh hash   {:016x} ({} triangles)", m.hash(), group(m.triangle_count() as u64));
    if let Some(path) = out {
        let mut w: Box<dyn Write> = if path.as_os_str() == "-" {
            Box::new(std::io::stdout().lock())
        } else {
            Box::new(std::io::BufWriter::new(
                std::fs::File::create(&path).with_context(|| format!("cannot create {}", path.display()))?,
            ))
        };
        write_stream(&mut w, &stream)?;
        w.flush()?;
    }
    Ok(ExitCode::SUCCESS)
}

/// One line per primitive: kind, sizes, the 12 transform entries, the colour; leaf points after `|`.
fn write_stream(w: &mut dyn Write, s: &PrimitiveStream) -> std::io::Result<()> {
    writeln!(w, "# kind sizes... | transform m00..m23 | r g b [| leaf points x y z ...]")?;
    for p in &s.primitives {
        let (sizes, n) = p.shape.sizes();
        let f = |v: &[f32]| v.iter().map(|x| format!("{x}")).collect::<Vec<_>>().join(" ");
        write!(w, "{} {} | {} | {}", p.shape.kind().name(), f(&sizes[..n]), f(&p.transform.m), f(&p.color))?;
        let pts = s.leaf(p);
        if !pts.is_empty() {
            write!(w, " | {}", f(&pts.concat()))?;
        }
        writeln!(w)?;
    }
    Ok(())
}

fn write_glb(out: &Path, meshes: &[(String, Mesh, [f32; 3])]) -> anyhow::Result<()> {
    let refs: Vec<(String, &Mesh, [f32; 3])> = meshes.iter().map(|(n, m, t)| (n.clone(), m, *t)).collect();
    super::write_file(out, &glb(&refs)?)
}

pub(super) fn demo(args: DemoArgs) -> anyhow::Result<ExitCode> {
    println!("Canopy species demo: every embedded species, amplified deterministically from its seed.\n");
    println!(
        "{:<16} {:>6} {:>8} {:>9} {:>11} {:>7} {:>9} {:>9}",
        "species", "nodes", "encoded", "prims", "explicit", "ratio", "ms/tree", "Mprim/s"
    );
    let mut meshes: Vec<(String, Mesh, [f32; 3])> = Vec::new();
    let mut x = 0.0f32;
    for entry in library::SPECIES {
        let g = entry.load().map_err(|d| anyhow::anyhow!("{d}"))?;
        let budget = Budget::default();
        let (mut prims, mut explicit, mut secs) = (0usize, 0usize, 0.0f64);
        let mut width = 0.0f32;
        for i in 0..args.per_species {
            let inst = Instance::new(1 + u64::from(i));
            let t = Instant::now();
            let s = amplify(&g, &inst, &budget)?;
            secs += t.elapsed().as_secs_f64();
            prims += s.primitives.len();
            explicit += explicit_bytes(&s);
            let m = mesh(&s, &MeshOptions::default());
            let (lo, hi) = m.bounds();
            let w = (hi[0] - lo[0]).max(hi[2] - lo[2]).clamp(1.0, 400.0);
            width = width.max(w);
            meshes.push((format!("{}-{}", g.name, inst.seed), m, [x - lo[0], 0.0, i as f32 * w * 1.2]));
        }
        x += width * 1.3;
        let n = args.per_species.max(1) as f64;
        let encoded = g.encode().len();
        println!(
            "{:<16} {:>6} {:>8} {:>9} {:>11} {:>6}× {:>9.3} {:>9.2}",
            entry.name(),
            g.nodes.len(),
            encoded,
            group((prims as f64 / n) as u64),
            group((explicit as f64 / n) as u64),
            canopy_editor::stats::ratio(explicit as f64 / n / encoded as f64),
            secs * 1e3 / n,
            prims as f64 / secs / 1e6
        );
    }
    write_glb(&args.out, &meshes)?;
    println!("\nencoded: the species graph as sent over the wire (postcard); explicit: its instance as geometry,");
    println!("counted as seed 001 §7 counts it. Grove of {} instances written to {}", meshes.len(), args.out.display());
    Ok(ExitCode::SUCCESS)
}
