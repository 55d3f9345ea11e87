//! `canopy bandwidth`: the bandwidth measurement harness — procedural streaming against explicit geometry
//! (unique meshes, instanced meshes) through the same server, paths and emulated links; and, with `--path
//! flight`, bots flying over the highlands with a far view, summary bytes beside record bytes. Writes a markdown
//! report, CSV files and SVG plots (see `canopy_harness::bandwidth` and docs/bandwidth.md).

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use canopy_harness::bandwidth::link::{LinkSpec, parse_rate};
use canopy_harness::bandwidth::{self, BandwidthConfig, External, Scenario, report};
use canopy_harness::bots::PathKind;
use canopy_server::session::PayloadMode;
use canopy_worlds::world::World;
use clap::{Args, ValueEnum};

/// A payload mode on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Mode {
    /// Species programs once, then instance records (Canopy with `--records`).
    Procedural,
    /// Species programs and the world function once, then cell grants: the bots expand cells themselves (Canopy).
    Expanded,
    /// Baseline 1: every instance's own mesh, meshopt-compressed.
    UniqueMesh,
    /// Baseline 2: one meshopt-compressed mesh per species plus per-instance transforms.
    Instanced,
}

/// The bots' path on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Path {
    /// A straight walk from a seeded start, bouncing off the world's edge, with a teleport half-way.
    Line,
    /// Straight legs and turns at `--altitude` above the terrain (procedural only; default world: highlands).
    Flight,
}

impl From<Path> for PathKind {
    fn from(p: Path) -> PathKind {
        match p {
            Path::Line => PathKind::Line,
            Path::Flight => PathKind::Flight,
        }
    }
}

impl Mode {
    /// The scenario of this mode over `link`.
    fn scenario(self, link: LinkSpec) -> Scenario {
        match self {
            Mode::Procedural => Scenario::new(PayloadMode::Procedural, link),
            Mode::Expanded => Scenario::expanded(link),
            Mode::UniqueMesh => Scenario::new(PayloadMode::UniqueMesh, link),
            Mode::Instanced => Scenario::new(PayloadMode::Instanced, link),
        }
    }
}

/// Options of `canopy bandwidth`. With no options: the default walkthrough (every payload over 1 Mbit/s, records and
/// expanded cells side by side; procedural over 56 kbit/s and over 10 Mbit/s with 1 % loss; 2 bots, 30 s at 10 m/s
/// with a teleport). With `--path flight`: the flight (records and expanded cells over 1 Mbit/s and 10 Mbit/s; 2
/// bots, 30 s at 250 m/s, 1,500 m above the highlands, asking for the far view).
#[derive(Args, Debug)]
pub(super) struct BandwidthArgs {
    /// The bots' path: walk lines (the default walkthrough) or fly (the flight scenario: procedural only, far view
    /// summaries beside records).
    #[arg(long, value_enum, default_value_t = Path::Line)]
    path: Path,
    /// The world: an embedded world's name (`forest`, `highlands`) or a manifest path (default: the embedded
    /// default world walking, `highlands` flying). A world never materialised is served through the server's cell
    /// cache, procedural only.
    #[arg(long)]
    world: Option<String>,
    /// Payload modes to run (comma-separated); with --rate, every mode over every rate.
    #[arg(long, value_enum, value_delimiter = ',')]
    modes: Vec<Mode>,
    /// Link rates (comma-separated: 56k, 1M, 10M, none).
    #[arg(long, value_delimiter = ',')]
    rate: Vec<String>,
    /// One-way link latency, milliseconds (with --modes/--rate).
    #[arg(long, default_value_t = 20)]
    latency_ms: u64,
    /// Packet loss probability per direction, 0..1 (with --modes/--rate).
    #[arg(long, default_value_t = 0.0)]
    loss: f64,
    /// Bots per scenario.
    #[arg(long, default_value_t = 2)]
    bots: usize,
    /// How long each bot walks (or flies), seconds.
    #[arg(long, default_value_t = 30.0)]
    duration: f64,
    /// Walking (or flying) speed, metres per second (default: 10 walking, 250 flying).
    #[arg(long)]
    speed: Option<f32>,
    /// `--path flight`: height above the terrain, metres (the area-of-interest radius then follows from altitude
    /// and speed under the server's rules, instead of `--radius`).
    #[arg(long, default_value_t = 1500.0)]
    altitude: f32,
    /// Area-of-interest radius, metres (walkers; a flight's follows from `--altitude` and `--speed`).
    #[arg(long, default_value_t = 160.0)]
    radius: f32,
    /// View distance for visible completeness, metres (default: the area-of-interest radius asked for).
    #[arg(long)]
    view: Option<f32>,
    #[command(flatten)]
    far: super::far::BotFarArgs,
    /// Walk straight on without the teleport half-way (flights never teleport).
    #[arg(long)]
    no_teleport: bool,
    /// Ask for the same radius however slow the link (flights otherwise fit their radius to each scenario's link
    /// rate while they move, and visible completeness is judged within the radius asked at each sample).
    #[arg(long)]
    fixed_radius: bool,
    /// Path seed (bot `i` uses seed + i; default 1 walking, 6 flying: forest under both bots' flights over the
    /// highlands).
    #[arg(long)]
    seed: Option<u64>,
    /// Longest wait at the end for a complete area of interest, seconds.
    #[arg(long, default_value_t = 10.0)]
    settle: f64,
    /// Sampling interval, milliseconds.
    #[arg(long, default_value_t = 250)]
    sample_ms: u64,
    /// Server pacing (its token bucket) as a fraction of the link rate; 0: off.
    #[arg(long, default_value_t = 0.9)]
    pace: f64,
    /// Memory bound of the server's cache of encoded instance meshes, MiB.
    #[arg(long, default_value_t = 512)]
    cache_mib: usize,
    /// Instances per species for the seed 001 §7 size table (0: no table; default 3 walking, 0 flying).
    #[arg(long)]
    size_seeds: Option<u32>,
    /// Instances of the world whose unique meshes are encoded to estimate baseline 1 per instance (0: none;
    /// default 40 walking, 0 flying).
    #[arg(long)]
    mesh_sample: Option<usize>,
    /// Cells of a world never materialised that the ground truth keeps expanded between samples.
    #[arg(long, default_value_t = canopy_harness::bandwidth::truth::DEFAULT_MEMO_CELLS)]
    truth_cells: usize,
    /// Output folder.
    #[arg(long, default_value = "out/bandwidth")]
    out: PathBuf,
    /// A running canopy-server to measure (procedural scenarios only) instead of one in process; it must serve the
    /// world of `--world` (default: the embedded default world walking, `highlands` flying).
    #[command(flatten)]
    connect: super::ConnectArgs,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

fn config(args: &BandwidthArgs) -> anyhow::Result<BandwidthConfig> {
    let flying = args.path == Path::Flight;
    let mut cfg = if flying { BandwidthConfig::flight_run() } else { BandwidthConfig::default_run() };
    let secs = |v: f64, what: &str| -> anyhow::Result<Duration> {
        if !(v.is_finite() && (0.0..=86_400.0).contains(&v)) {
            bail!("--{what} must be between 0 and 86400 seconds");
        }
        Ok(Duration::from_secs_f64(v))
    };
    if !(0.0..1.0).contains(&args.loss) {
        bail!("--loss must be in 0..1");
    }
    let speed = args.speed.unwrap_or(cfg.speed);
    if !(speed.is_finite() && speed >= 0.0 && args.radius.is_finite() && args.radius > 0.0) {
        bail!("--speed and --radius must be positive numbers");
    }
    if !(args.altitude.is_finite() && args.altitude >= 0.0) || args.view.is_some_and(|v| !(v.is_finite() && v > 0.0)) {
        bail!("--altitude must not be negative, --view must be positive");
    }
    cfg.bots = args.bots;
    cfg.duration = secs(args.duration, "duration")?;
    cfg.settle = secs(args.settle, "settle")?;
    cfg.speed = speed;
    cfg.altitude = if flying { args.altitude } else { 0.0 };
    cfg.radius = args.radius;
    // Walkers measure over their radius by default (a flight over the radius the server's rules give it).
    cfg.view = args.view.or((!flying).then_some(args.radius));
    cfg.far = args.far.view(flying, args.altitude)?;
    cfg.teleport = !args.no_teleport && !flying;
    cfg.fit = flying && !args.fixed_radius;
    cfg.seed = args.seed.unwrap_or(cfg.seed);
    cfg.sample = Duration::from_millis(args.sample_ms.clamp(10, 60_000));
    cfg.pace = args.pace.clamp(0.0, 10.0);
    cfg.cache_bytes = args.cache_mib.saturating_mul(1024 * 1024);
    cfg.size_seeds = args.size_seeds.unwrap_or(cfg.size_seeds);
    cfg.mesh_sample = args.mesh_sample.unwrap_or(cfg.mesh_sample);
    cfg.truth_cells = args.truth_cells.max(1);
    cfg.out = args.out.clone();
    cfg.progress = !args.quiet;
    cfg.command = std::iter::once("canopy".to_string()).chain(std::env::args().skip(1)).collect::<Vec<_>>().join(" ");
    let external = args.connect.server.is_some();
    if !args.modes.is_empty() || !args.rate.is_empty() || external {
        let modes: Vec<Mode> = if args.modes.is_empty() {
            if external || flying {
                vec![Mode::Procedural, Mode::Expanded]
            } else {
                vec![Mode::Procedural, Mode::Expanded, Mode::UniqueMesh, Mode::Instanced]
            }
        } else {
            args.modes.clone()
        };
        let rates: Vec<Option<u64>> = if args.rate.is_empty() {
            vec![Some(1_000_000)]
        } else {
            args.rate.iter().map(|r| parse_rate(r).map_err(anyhow::Error::msg)).collect::<anyhow::Result<_>>()?
        };
        cfg.scenarios = rates
            .iter()
            .flat_map(|&rate| modes.iter().map(move |&m| m.scenario(LinkSpec::new(rate, args.latency_ms, args.loss))))
            .map(|s| if flying { s.prefixed("flight") } else { s })
            .collect();
    }
    cfg.path = args.path.into();
    match &args.connect.server {
        Some(edges) => cfg.external = Some(External { server: edges.first(), trust: args.connect.trust()? }),
        None if args.connect.trust_given() => {
            anyhow::bail!("--cert-fingerprint and --insecure name the trust of a --server")
        }
        None => {}
    }
    Ok(cfg)
}

/// Run `canopy bandwidth`.
pub(super) fn run(args: BandwidthArgs) -> anyhow::Result<ExitCode> {
    let cfg = config(&args)?;
    let loaded = Instant::now();
    let world = Arc::new(match (&args.world, cfg.flying()) {
        (Some(w), _) => super::world_arg(w)?,
        (None, true) => World::embedded("highlands").context("the embedded highlands")?,
        (None, false) => World::default_world(),
    });
    println!(
        "world `{}`: {}, loaded in {:.1} s; {} scenarios × {} bots, {} s {}; report into {}",
        world.name,
        if world.is_materialised() {
            format!("{} instances", world.instances.len())
        } else {
            format!("{} cells expanded on demand", world.cell_count())
        },
        loaded.elapsed().as_secs_f64(),
        cfg.scenarios.len(),
        cfg.bots,
        cfg.duration.as_secs_f64(),
        if cfg.flying() { format!("flights at {} m/s, {} m up", cfg.speed, cfg.altitude) } else { "walks".into() },
        cfg.out.display()
    );
    let outcome = bandwidth::run(&cfg, world)?;
    for c in report::comparisons(&outcome) {
        let n = c[0].records() as f64 / c[0].bots.len().max(1) as f64;
        let [p, u, i] = report::projections(&outcome, c);
        let base = p.as_ref().map_or(1.0, |x| x.bytes(n).max(1.0));
        let ratio =
            |x: &Option<report::Projection>| x.as_ref().map_or("-".into(), |x| format!("{:.0}×", x.bytes(n) / base));
        println!(
            "{}: unique meshes {} the procedural bytes, instanced {} (to deliver the {n:.0} instances per bot procedural delivered)",
            c[0].scenario.link.label(),
            ratio(&u),
            ratio(&i)
        );
    }
    for f in &outcome.files {
        println!("wrote {}", f.display());
    }
    let failed = outcome.scenarios.iter().flat_map(|s| &s.bots).filter(|b| b.bot.error.is_some()).count();
    Ok(if failed == 0 { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}
