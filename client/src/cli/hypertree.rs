//! `canopy hypertree check|generate|render|stats|reduce|union|clear|set|voxelise|bench`: the far-field volume path
//! of seed 000 (hypertrees) on the command line, with a progress bar on long work.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, bail};
use canopy_harness::numbers::median;
use canopy_worlds::diag::Diagnostics;
use canopy_worlds::hypertree::file::{MAX_VOLUME_BYTES, load as load_volume, save as save_volume};
use canopy_worlds::hypertree::format::{load_forest, load_hypertree};
use canopy_worlds::hypertree::generate::{GenerateOptions, GenerationStats, generate, generate_forest};
use canopy_worlds::hypertree::library::{self, TABLE1};
use canopy_worlds::hypertree::ops::{Unification, clear_region, combine, reduce, set_region};
use canopy_worlds::hypertree::render::{BoundingScheme, RenderOptions, RenderStats, Shading, render};
use canopy_worlds::hypertree::storage::VoxelStore;
use canopy_worlds::hypertree::voxelise::{VoxeliseOptions, voxelise_species};
use canopy_worlds::hypertree::{Hypertree, StorageType, Voxel};
use clap::{Args, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};

use super::{species, write_file};

#[derive(Subcommand, Debug)]
pub(super) enum HypertreeCommand {
    /// Check hypertree (.hyp) and hyperforest (.hyf) files; print every diagnostic with file:line:col.
    Check {
        /// Files to check; all are checked even if one fails.
        #[arg(required = true)]
        files: Vec<PathBuf>,
    },
    /// Generate a hypertree (or hyperforest) and save the volume (.hvol), optionally rendering it.
    Generate {
        #[command(flatten)]
        input: InputArgs,
        /// Where to save the volume.
        #[arg(long, short)]
        out: Option<PathBuf>,
        /// Also render it to this PNG (default view).
        #[arg(long)]
        png: Option<PathBuf>,
    },
    /// Render a hypertree (a .hvol volume, a .hyp definition, a .hyf forest or a library name) to PNG.
    Render {
        #[command(flatten)]
        input: InputArgs,
        #[command(flatten)]
        view: ViewArgs,
        /// The PNG to write.
        #[arg(long, short)]
        out: PathBuf,
    },
    /// Voxel counts, memory per storage structure, level and density histograms, hash.
    Stats {
        #[command(flatten)]
        input: InputArgs,
    },
    /// Level of detail: reduce the resolution by weighted voxel fusion (§9).
    Reduce {
        #[command(flatten)]
        input: InputArgs,
        /// The new resolution: one value or `x,y,z`.
        #[arg(long = "to", value_parser = parse_resolution)]
        to: [u32; 3],
        /// Where to save the reduced volume.
        #[arg(long, short)]
        out: PathBuf,
    },
    /// Unite two hypertrees of the same hypervolume (maximum of densities, or their sum with --add).
    Union {
        /// First hypertree (its storage structure is kept).
        a: String,
        /// Second hypertree.
        b: String,
        /// Add densities instead of taking the maximum.
        #[arg(long)]
        add: bool,
        /// Seed for definitions given as input.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where to save the result.
        #[arg(long, short)]
        out: PathBuf,
    },
    /// Clear every voxel whose centre lies in a box region (trimming, §7).
    Clear {
        #[command(flatten)]
        input: InputArgs,
        #[command(flatten)]
        region: RegionArgs,
        /// Where to save the result.
        #[arg(long, short)]
        out: PathBuf,
    },
    /// Set every voxel whose centre lies in a box region.
    Set {
        #[command(flatten)]
        input: InputArgs,
        #[command(flatten)]
        region: RegionArgs,
        /// Density to set, 1..=255.
        #[arg(long, default_value_t = 255)]
        density: u8,
        /// Level to set.
        #[arg(long, default_value_t = 0)]
        level: u8,
        /// Where to save the result.
        #[arg(long, short)]
        out: PathBuf,
    },
    /// Voxelise an amplified species into a hypertree (the volumetric interpretation of §12).
    Voxelise {
        #[command(flatten)]
        instance: species::InstanceArgs,
        /// Voxels along the longest axis.
        #[arg(long, default_value_t = 200)]
        resolution: u32,
        /// Storage structure.
        #[arg(long, value_enum, default_value_t = StorageArg::Indexbits)]
        storage: StorageArg,
        /// Where to save the volume.
        #[arg(long, short)]
        out: Option<PathBuf>,
        /// Also render it to this PNG.
        #[arg(long)]
        png: Option<PathBuf>,
    },
    /// Reproduce the paper's Table 1 (creation time, render time, memory per storage structure; resolution 100
    /// without supersampling and 300 with s = 2; 300×300 image), on one core.
    Bench {
        /// Timed repetitions per cell (the median is reported).
        #[arg(long, default_value_t = 5)]
        repeat: u32,
        /// Only these trees (A, B, C, D).
        #[arg(long)]
        only: Option<String>,
    },
    /// List the embedded hypertree definitions.
    List,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum StorageArg {
    /// Dense 3D array.
    Dense,
    /// Sorted index list.
    Indexlist,
    /// Index list plus bit array.
    Indexbits,
}

impl From<StorageArg> for StorageType {
    fn from(s: StorageArg) -> StorageType {
        match s {
            StorageArg::Dense => StorageType::Dense,
            StorageArg::Indexlist => StorageType::IndexList,
            StorageArg::Indexbits => StorageType::IndexBits,
        }
    }
}

/// Which hypertree to work on, and how to generate it when it is a definition.
#[derive(Args, Debug, Clone)]
pub(super) struct InputArgs {
    /// A saved volume (.hvol), a definition (.hyp), a hyperforest (.hyf) or a library name (`canopy hypertree list`).
    input: String,
    /// Instance seed (definitions only).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Storage structure (definitions only; a forest names its own).
    #[arg(long, value_enum)]
    storage: Option<StorageArg>,
    /// Keep index lists per first-level subpart.
    #[arg(long)]
    partitioned: bool,
    /// Override the resolution: one value or `x,y,z` (definitions only).
    #[arg(long, value_parser = parse_resolution)]
    resolution: Option<[u32; 3]>,
    /// Override the iteration count (definitions only).
    #[arg(long)]
    iterations: Option<u64>,
}

#[derive(Args, Debug, Clone)]
pub(super) struct ViewArgs {
    /// Image width.
    #[arg(long, default_value_t = 300)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 300)]
    height: u32,
    /// Supersampling factor s (s×s rays per pixel).
    #[arg(long, short = 's', default_value_t = 1)]
    supersample: u32,
    /// Camera azimuth, degrees.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    azimuth: f32,
    /// Camera elevation, degrees.
    #[arg(long, default_value_t = 8.0, allow_hyphen_values = true)]
    elevation: f32,
    /// Bounding volumes for projection rays.
    #[arg(long, value_enum, default_value_t = BoundsArg::Aabb)]
    bounds: BoundsArg,
    /// Shading model.
    #[arg(long, value_enum, default_value_t = ShadingArg::Diffuse)]
    shading: ShadingArg,
    /// Use the projection-ray cache.
    #[arg(long)]
    ray_cache: bool,
    /// No shadow rays.
    #[arg(long)]
    no_shadows: bool,
    /// Do not skip empty bricks.
    #[arg(long)]
    no_skip: bool,
    /// The opacity normalisation coefficient k.
    #[arg(long, default_value_t = 1.0)]
    k: f32,
    /// Distance as a multiple of the distance that just fits the tree.
    #[arg(long, default_value_t = 1.05)]
    zoom_out: f32,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub(super) enum BoundsArg {
    /// The axis-aligned box of the voxels.
    Aabb,
    /// Secondary bounding spheres and the condensation box.
    Spheres,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub(super) enum ShadingArg {
    /// Shadow-attenuated ambient only.
    Ambient,
    /// Attenuated ambient and shadowed diffuse.
    Diffuse,
    /// Ambient, diffuse and specular.
    Specular,
}

impl ViewArgs {
    fn options(&self) -> RenderOptions {
        RenderOptions {
            width: self.width,
            height: self.height,
            supersample: self.supersample,
            azimuth: self.azimuth,
            elevation: self.elevation,
            zoom_out: self.zoom_out,
            bounds: match self.bounds {
                BoundsArg::Aabb => BoundingScheme::Aabb,
                BoundsArg::Spheres => BoundingScheme::Spheres,
            },
            shading: match self.shading {
                ShadingArg::Ambient => Shading::Ambient,
                ShadingArg::Diffuse => Shading::Diffuse,
                ShadingArg::Specular => Shading::Specular,
            },
            ray_cache: self.ray_cache,
            shadows: !self.no_shadows,
            skip_empty: !self.no_skip,
            density_scale: self.k,
            ..RenderOptions::default()
        }
    }
}

/// A box region in hypervolume coordinates.
#[derive(Args, Debug, Clone)]
pub(super) struct RegionArgs {
    /// Lower corner `x,y,z` (hypervolume box coordinates, 0..extent).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    min: [f32; 3],
    /// Upper corner `x,y,z`.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    max: [f32; 3],
}

fn parse_resolution(s: &str) -> Result<[u32; 3], String> {
    let parts: Vec<&str> = s.split(',').collect();
    let nums: Result<Vec<u32>, _> = parts.iter().map(|p| p.trim().parse::<u32>()).collect();
    match nums.map_err(|_| format!("`{s}` is not a resolution (N or X,Y,Z)"))?.as_slice() {
        [n] => Ok([*n; 3]),
        [x, y, z] => Ok([*x, *y, *z]),
        _ => Err(format!("`{s}` is not a resolution (N or X,Y,Z)")),
    }
}

fn parse_vec3(s: &str) -> Result<[f32; 3], String> {
    let v: Result<Vec<f32>, _> = s.split(',').map(|p| p.trim().parse::<f32>()).collect();
    match v.map_err(|_| format!("`{s}` is not x,y,z"))?.as_slice() {
        [x, y, z] if [x, y, z].iter().all(|v| v.is_finite()) => Ok([*x, *y, *z]),
        _ => Err(format!("`{s}` is not x,y,z")),
    }
}

fn bar(len: u64, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template("{msg:>10} [{bar:40}] {percent:>3}% {elapsed_precise}")
            .expect("static template")
            .progress_chars("=> "),
    );
    pb.set_message(what.to_string());
    pb
}

fn diagnostics(d: Vec<canopy_worlds::diag::Diagnostic>) -> anyhow::Error {
    anyhow::anyhow!("{}", Diagnostics(d))
}

impl InputArgs {
    fn generate_options(&self) -> GenerateOptions {
        GenerateOptions {
            storage: self.storage.map_or(StorageType::IndexBits, StorageType::from),
            partitioned: self.partitioned,
            resolution: self.resolution,
            iterations: self.iterations,
        }
    }

    /// Load or generate the hypertree, with a progress bar while generating.
    fn tree(&self) -> anyhow::Result<(Hypertree, Option<(GenerationStats, f64)>)> {
        load_input(&self.input, self.seed, &self.generate_options(), self.storage.map(StorageType::from))
    }
}

fn load_input(
    input: &str,
    seed: u64,
    opts: &GenerateOptions,
    convert: Option<StorageType>,
) -> anyhow::Result<(Hypertree, Option<(GenerationStats, f64)>)> {
    let path = Path::new(input);
    if input.ends_with(".hvol") {
        let bytes = canopy_worlds::fsread::read_bounded(path, MAX_VOLUME_BYTES as u64)
            .with_context(|| format!("reading {input}"))?;
        let mut t = load_volume(&bytes).with_context(|| format!("loading {input}"))?;
        if let Some(ty) = convert.filter(|&ty| ty != t.store.storage_type() || t.store.is_partitioned()) {
            // A saved volume is re-stored only when a structure is asked for explicitly.
            t.store = VoxelStore::from_list(t.store.to_list(), ty, &t.volume);
        }
        return Ok((t, None));
    }
    let pb = bar(1, "generate");
    let mut progress = |done: u64, total: u64| {
        pb.set_length(total);
        pb.set_position(done);
    };
    let start = Instant::now();
    let result = if input.ends_with(".hyf") {
        let (forest, d) = load_forest(path);
        let forest = forest.ok_or_else(|| diagnostics(d))?;
        generate_forest(&forest, &mut progress)?
    } else {
        let def = if input.ends_with(".hyp") {
            let (def, d) = load_hypertree(path);
            def.ok_or_else(|| diagnostics(d))?
        } else {
            match library::find(input) {
                Some(e) => e.load().map_err(|d| anyhow::anyhow!("{d}"))?,
                None => bail!(
                    "`{input}` is not a .hvol, .hyp or .hyf file nor a library hypertree (`canopy hypertree list`)"
                ),
            }
        };
        generate(&def, seed, opts, &mut progress)?
    };
    let ms = start.elapsed().as_secs_f64() * 1e3;
    pb.finish_and_clear();
    Ok((result.0, Some((result.1, ms))))
}

fn render_to(tree: &Hypertree, opts: &RenderOptions, out: &Path) -> anyhow::Result<(RenderStats, f64)> {
    let pb = bar(u64::from(opts.height), "render");
    let start = Instant::now();
    let (img, stats) = render(tree, opts, &mut |done, total| {
        pb.set_length(u64::from(total));
        pb.set_position(u64::from(done));
    })?;
    let ms = start.elapsed().as_secs_f64() * 1e3;
    pb.finish_and_clear();
    write_file(out, &img.encode_png()?)?;
    println!(
        "rendered {} in {ms:.1} ms ({}×{}, s = {}) → {}",
        tree.name,
        opts.width,
        opts.height,
        opts.supersample,
        out.display()
    );
    Ok((stats, ms))
}

fn describe(tree: &Hypertree, generation: Option<&(GenerationStats, f64)>) {
    let v = tree.volume;
    println!(
        "{}: {}×{}×{} voxels, {} non-empty, {} {}, {} bytes, hash {:016x}",
        tree.name,
        v.resolution[0],
        v.resolution[1],
        v.resolution[2],
        tree.len(),
        tree.store.storage_type().name(),
        if tree.store.is_partitioned() { "(partitioned)" } else { "" },
        tree.store.memory_bytes(),
        tree.hash()
    );
    if let Some(b) = tree.aabb() {
        println!(
            "occupies x {:.3}..{:.3}, y {:.3}..{:.3}, z {:.3}..{:.3} of the {:?} hypervolume",
            b.min[0], b.max[0], b.min[1], b.max[1], b.min[2], b.max[2], v.extent
        );
    }
    if let Some((s, ms)) = generation {
        println!(
            "generated in {ms:.1} ms: {} generators in {} cycles, {} dummies, {} hits, {} outside the hypervolume",
            s.generators, s.cycles, s.dummies, s.hits, s.outside
        );
    }
}

/// Run a hypertree subcommand.
pub(super) fn run(cmd: HypertreeCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        HypertreeCommand::Check { files } => Ok(check(&files)),
        HypertreeCommand::List => {
            for e in library::HYPERTREES {
                let d = e.load().map_err(|d| anyhow::anyhow!("{d}"))?;
                println!(
                    "{:<10} {:<14} {:>4}³ {:>9} iterations, depth {:>2}, {:>2} transformations, {} condensation(s), {} bytes encoded",
                    e.name(),
                    e.file,
                    d.resolution[0],
                    d.iterations,
                    d.tree_depth,
                    d.transformations.len(),
                    d.condensations.len(),
                    d.encode().len()
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        HypertreeCommand::Generate { input, out, png } => {
            let (tree, generation) = input.tree()?;
            describe(&tree, generation.as_ref());
            if let Some(out) = out {
                write_file(&out, &save_volume(&tree))?;
                println!("saved {}", out.display());
            }
            if let Some(png) = png {
                render_to(&tree, &RenderOptions::default(), &png)?;
            }
            Ok(ExitCode::SUCCESS)
        }
        HypertreeCommand::Render { input, view, out } => {
            let (tree, generation) = input.tree()?;
            describe(&tree, generation.as_ref());
            let (s, _) = render_to(&tree, &view.options(), &out)?;
            println!(
                "{} rays, {} storage queries ({} from the ray cache), {} voxels shaded, {} shadow samples",
                s.rays, s.samples, s.cache_hits, s.shaded, s.shadow_samples
            );
            Ok(ExitCode::SUCCESS)
        }
        HypertreeCommand::Stats { input } => {
            let (tree, generation) = input.tree()?;
            describe(&tree, generation.as_ref());
            stats(&tree);
            Ok(ExitCode::SUCCESS)
        }
        HypertreeCommand::Reduce { input, to, out } => {
            let (tree, _) = input.tree()?;
            let start = Instant::now();
            let r = reduce(&tree, to)?;
            println!("reduced in {:.1} ms", start.elapsed().as_secs_f64() * 1e3);
            describe(&r, None);
            write_file(&out, &save_volume(&r))?;
            Ok(ExitCode::SUCCESS)
        }
        HypertreeCommand::Union { a, b, add, seed, out } => {
            let opts = GenerateOptions::default();
            let (ta, _) = load_input(&a, seed, &opts, None)?;
            let (tb, _) = load_input(&b, seed.wrapping_add(1), &opts, None)?;
            let how = if add { Unification::Add } else { Unification::Max };
            let u = combine(&ta, &tb, how)?;
            describe(&u, None);
            write_file(&out, &save_volume(&u))?;
            Ok(ExitCode::SUCCESS)
        }
        HypertreeCommand::Clear { input, region, out } => {
            let (tree, _) = input.tree()?;
            let t = clear_region(&tree, region.min, region.max)?;
            describe(&t, None);
            write_file(&out, &save_volume(&t))?;
            Ok(ExitCode::SUCCESS)
        }
        HypertreeCommand::Set { input, region, density, level, out } => {
            let (tree, _) = input.tree()?;
            let t = set_region(&tree, region.min, region.max, Voxel { density, level })?;
            describe(&t, None);
            write_file(&out, &save_volume(&t))?;
            Ok(ExitCode::SUCCESS)
        }
        HypertreeCommand::Voxelise { instance, resolution, storage, out, png } => {
            let cfg = instance.config()?;
            let opts = VoxeliseOptions { resolution, storage: storage.into(), ..VoxeliseOptions::default() };
            let start = Instant::now();
            let tree = voxelise_species(&cfg.graph, &cfg.instance, &cfg.budget, &opts)?;
            println!("voxelised in {:.1} ms", start.elapsed().as_secs_f64() * 1e3);
            describe(&tree, None);
            if let Some(out) = out {
                write_file(&out, &save_volume(&tree))?;
            }
            if let Some(png) = png {
                render_to(&tree, &RenderOptions::default(), &png)?;
            }
            Ok(ExitCode::SUCCESS)
        }
        HypertreeCommand::Bench { repeat, only } => bench(repeat.max(1), only.as_deref()),
    }
}

fn check(files: &[PathBuf]) -> ExitCode {
    let mut failed = 0;
    for f in files {
        let name = f.display().to_string();
        let (ok, diags, summary) = if name.ends_with(".hyf") {
            let (forest, d) = load_forest(f);
            let s = forest.as_ref().map(|x| format!("hyperforest `{}`: {} trees", x.def.name, x.trees.len()));
            (forest.is_some(), d, s)
        } else {
            let (def, d) = load_hypertree(f);
            let s = def.as_ref().map(|x| {
                format!(
                    "hypertree `{}`: {} transformations, {} bytes encoded",
                    x.name,
                    x.transformations.len(),
                    x.encode().len()
                )
            });
            (def.is_some(), d, s)
        };
        for d in &diags {
            println!("{d}\n");
        }
        if ok {
            println!("ok      {name} — {}", summary.unwrap_or_default());
        } else {
            failed += 1;
            println!("failed  {name} — {} error(s)", diags.len());
        }
    }
    println!("{} file(s) checked, {} failed", files.len(), failed);
    if failed == 0 { ExitCode::SUCCESS } else { ExitCode::FAILURE }
}

fn bytes(n: f64) -> String {
    if n >= 1024.0 * 1024.0 { format!("{:.1}M", n / (1024.0 * 1024.0)) } else { format!("{:.0}K", n / 1024.0) }
}

fn stats(tree: &Hypertree) {
    let list = tree.store.to_list();
    let mut levels = [0u64; 256];
    let mut dens = [0u64; 256];
    for k in 0..list.len() {
        levels[list.levels[k] as usize] += 1;
        dens[list.densities[k] as usize] += 1;
    }
    let lv: Vec<String> = levels.iter().enumerate().filter(|(_, n)| **n > 0).map(|(l, n)| format!("{l}:{n}")).collect();
    println!("voxels per level: {}", lv.join(" "));
    let classes = dens.iter().filter(|&&n| n > 0).count();
    println!("distinct densities: {classes} (full density: {} voxels)", dens[255]);
    let dense = tree.volume.voxel_count() as f64;
    for ty in StorageType::ALL {
        let store = VoxelStore::from_list(list.clone(), ty, &tree.volume);
        let m = store.memory_bytes() as f64;
        println!(
            "{:<10} {:>10} bytes  ({:5.2}% of a one-byte-per-voxel array)",
            ty.name(),
            store.memory_bytes(),
            100.0 * m / dense
        );
    }
    println!(
        "occupancy brick map: {} bytes; bounds: {} spheres, {} boxes; {} flows",
        tree.occupancy.memory_bytes(),
        tree.bounds.spheres.len(),
        tree.bounds.boxes.len(),
        tree.flows.len()
    );
}

/// CPU time of the calling thread in seconds, from `CLOCK_THREAD_CPUTIME_ID` (Linux; nanosecond resolution, unlike
/// `/proc/thread-self/schedstat`, which only advances at scheduler ticks), so the benchmark measures the work on
/// one core even when other processes share the machine; `None` elsewhere (wall time is used then).
#[cfg(target_os = "linux")]
fn thread_cpu_seconds() -> Option<f64> {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
    Some(t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9)
}

#[cfg(not(target_os = "linux"))]
fn thread_cpu_seconds() -> Option<f64> {
    None
}

/// Time `f`: thread CPU time where available, wall time otherwise.
fn timed<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let (cpu, wall) = (thread_cpu_seconds(), Instant::now());
    let out = f();
    let t = match (cpu, thread_cpu_seconds()) {
        (Some(a), Some(b)) => b - a,
        _ => wall.elapsed().as_secs_f64(),
    };
    (out, t)
}

/// The Table 1 reproduction (see `docs/hypertrees.md`).
fn bench(repeat: u32, only: Option<&str>) -> anyhow::Result<ExitCode> {
    println!("Table 1 reproduction: creation time (CT), render time (RT), memory (MC) per storage structure;");
    println!(
        "resolution 100, s = 1 (first value) and resolution 300, s = 2 (in parentheses); image 300×300; one core;"
    );
    let clock = if thread_cpu_seconds().is_some() { "thread CPU time" } else { "wall time" };
    println!("median {clock} of {repeat} runs; in brackets the speed-up over the paper's Table 1 (Athlon 1.4 GHz).\n");
    let head: Vec<String> = StorageType::ALL.iter().map(|t| format!("{:^62}", t.name())).collect();
    println!("   {}", head.join(" | "));
    let mut worst = f64::INFINITY;
    for row in TABLE1 {
        if only.is_some_and(|o| !o.contains(row.label)) {
            continue;
        }
        let def =
            library::find(row.file).expect("Table 1 trees are embedded").load().map_err(|d| anyhow::anyhow!("{d}"))?;
        let mut cells = Vec::new();
        for (si, ty) in StorageType::ALL.iter().enumerate() {
            let mut ct = [0.0; 2];
            let mut rt = [0.0; 2];
            let mut mc = [0.0; 2];
            for (ci, (res, s)) in [(100u32, 1u32), (300, 2)].into_iter().enumerate() {
                let opts = GenerateOptions { storage: *ty, resolution: Some([res; 3]), ..GenerateOptions::default() };
                let mut times = Vec::new();
                let mut tree = None;
                for _ in 0..repeat {
                    let (t, secs) = timed(|| generate(&def, 1, &opts, &mut |_, _| {}));
                    times.push(secs);
                    tree = Some(t?.0);
                }
                let tree = tree.expect("at least one run");
                ct[ci] = median(times);
                mc[ci] = tree.store.memory_bytes() as f64;
                let ropts = RenderOptions { supersample: s, ..RenderOptions::default() };
                let mut times = Vec::new();
                for _ in 0..repeat {
                    let (r, secs) = timed(|| render(&tree, &ropts, &mut |_, _| {}));
                    r?;
                    times.push(secs);
                }
                rt[ci] = median(times);
                for (ours, paper) in [(ct[ci], row.creation[si][ci]), (rt[ci], row.render[si][ci])] {
                    worst = worst.min(paper / ours);
                }
            }
            let sp = |ours: f64, paper: f64| format!("{:.0}×", paper / ours);
            cells.push(format!(
                "CT {:>5.1}({:>5.1})ms [{}/{}] RT {:>5.1}({:>6.1})ms [{}/{}] MC {}({})",
                ct[0] * 1e3,
                ct[1] * 1e3,
                sp(ct[0], row.creation[si][0]),
                sp(ct[1], row.creation[si][1]),
                rt[0] * 1e3,
                rt[1] * 1e3,
                sp(rt[0], row.render[si][0]),
                sp(rt[1], row.render[si][1]),
                bytes(mc[0]),
                bytes(mc[1])
            ));
        }
        println!("{}  {}", row.label, cells.join(" | "));
    }
    println!("\nsmallest speed-up over Table 1 in any time cell: {worst:.1}×");
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    //! The subcommands run as a user runs them (parsed from argument lists), on small volumes in a temp folder.

    use super::*;
    use clap::Parser;

    #[derive(Parser, Debug)]
    struct Wrapper {
        #[command(subcommand)]
        command: HypertreeCommand,
    }

    fn run_args(args: &[&str]) -> anyhow::Result<ExitCode> {
        let w = Wrapper::try_parse_from(std::iter::once("hypertree").chain(args.iter().copied()))?;
        run(w.command)
    }

    /// A path in this test process's temporary directory (removed when the process ends).
    fn temp(name: &str) -> PathBuf {
        static DIR: std::sync::OnceLock<tempfile::TempDir> = std::sync::OnceLock::new();
        DIR.get_or_init(|| tempfile::tempdir().expect("temp dir")).path().join(name)
    }

    fn s(p: &Path) -> &str {
        p.to_str().expect("utf-8 temp path")
    }

    #[test]
    fn generate_render_stats_reduce_union_clear_set() {
        let vol = temp("fork.hvol");
        let png = temp("fork.png");
        let small = ["--resolution", "48", "--iterations", "20000"];
        let mut args = vec!["generate", "fork", "--storage", "indexlist", "-o", s(&vol), "--png", s(&png)];
        args.extend(small);
        assert_eq!(run_args(&args).unwrap(), ExitCode::SUCCESS);
        let tree = load_volume(&std::fs::read(&vol).unwrap()).unwrap();
        assert_eq!(tree.volume.resolution, [48; 3]);
        assert_eq!(tree.store.storage_type(), StorageType::IndexList);
        assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));

        let out = temp("r.png");
        let args =
            ["render", s(&vol), "-o", s(&out), "-s", "2", "--width", "64", "--height", "48", "--bounds", "spheres"];
        assert_eq!(run_args(&args).unwrap(), ExitCode::SUCCESS);
        let img = image::open(&out).expect("a PNG").to_rgb8();
        assert_eq!(img.dimensions(), (64, 48));
        assert_eq!(run_args(&["stats", s(&vol), "--storage", "dense"]).unwrap(), ExitCode::SUCCESS);

        let reduced = temp("reduced.hvol");
        assert_eq!(run_args(&["reduce", s(&vol), "--to", "24,30,24", "-o", s(&reduced)]).unwrap(), ExitCode::SUCCESS);
        assert_eq!(load_volume(&std::fs::read(&reduced).unwrap()).unwrap().volume.resolution, [24, 30, 24]);

        let both = temp("both.hvol");
        assert_eq!(run_args(&["union", s(&vol), s(&vol), "-o", s(&both)]).unwrap(), ExitCode::SUCCESS);
        assert_eq!(load_volume(&std::fs::read(&both).unwrap()).unwrap().hash(), tree.hash());

        let cleared = temp("cleared.hvol");
        let ext = tree.volume.extent;
        let max = format!("{},{},{}", ext[0], ext[1], ext[2]);
        let min = format!("0,{},0", ext[1] / 2.0);
        assert_eq!(
            run_args(&["clear", s(&vol), "--min", &min, "--max", &max, "-o", s(&cleared)]).unwrap(),
            ExitCode::SUCCESS
        );
        let c = load_volume(&std::fs::read(&cleared).unwrap()).unwrap();
        assert!(c.len() < tree.len() && c.voxel_box.unwrap().1[1] < 24);

        let set = temp("set.hvol");
        let args = ["set", s(&vol), "--min", "0,0,0", "--max", "0.05,0.05,0.05", "--density", "9", "-o", s(&set)];
        assert_eq!(run_args(&args).unwrap(), ExitCode::SUCCESS);
        assert_eq!(
            load_volume(&std::fs::read(&set).unwrap()).unwrap().voxel([0, 0, 0]),
            Voxel { density: 9, level: 0 }
        );

        // Bad input is a typed error, not a panic.
        assert!(run_args(&["reduce", s(&vol), "--to", "100", "-o", s(&reduced)]).is_err());
        assert!(run_args(&["render", "no-such-tree", "-o", s(&out)]).is_err());
        assert!(run_args(&["clear", s(&vol), "--min", "1,1", "--max", "2,2,2", "-o", s(&set)]).is_err());
    }

    #[test]
    fn check_reports_diagnostics_and_fails() {
        let bad = temp("bad.hyp");
        std::fs::write(&bad, "RESOLUTION 0\nTRANSFORM 1 255\n  SHEAR Q 1 1 1\n").unwrap();
        let good = concat!(env!("CARGO_MANIFEST_DIR"), "/../worlds/hypertrees/apple.hyp");
        let forest = concat!(env!("CARGO_MANIFEST_DIR"), "/../worlds/hypertrees/grove.hyf");
        assert_eq!(run_args(&["check", s(&bad), good, forest]).unwrap(), ExitCode::FAILURE);
        assert_eq!(run_args(&["check", good, forest]).unwrap(), ExitCode::SUCCESS);
        let (_, diags) = load_hypertree(&bad);
        let text: Vec<String> = diags.iter().map(|d| d.to_string()).collect();
        assert!(
            text.iter().any(|d| d.starts_with(&format!("{}:1:12: error: resolution 0", bad.display()))),
            "{text:?}"
        );
        assert!(text.iter().any(|d| d.contains(":3:9: error: expected an axis")), "{text:?}");
    }

    #[test]
    fn voxelise_a_species_and_list() {
        let vol = temp("mono.hvol");
        let args = ["voxelise", "monopodial", "--seed", "2", "--resolution", "48", "-o", s(&vol)];
        assert_eq!(run_args(&args).unwrap(), ExitCode::SUCCESS);
        let t = load_volume(&std::fs::read(&vol).unwrap()).unwrap();
        assert!(!t.is_empty() && t.volume.resolution.iter().max() == Some(&48));
        assert_eq!(run_args(&["list"]).unwrap(), ExitCode::SUCCESS);
    }
}
