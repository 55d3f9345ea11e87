//! `canopy bots`: headless walkthrough clients against a running `canopy-server`, with a progress line and a
//! summary (latencies, bytes per record, the check against the world). The exit status says whether every bot
//! ended with a complete area of interest that matched the world.
//!
//! With `--edit-rate` the first `--editors` bots also edit the world as they walk (an editor token is needed), and
//! the summary adds the edits' answers and how soon they reached the other bots (fan-out).
//!
//! With `--processes N` the bots run in N processes of this command ([`processes`]), and the summary is over all.

mod processes;

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use canopy_harness::bots::{
    self, BotReport, BotsConfig, BotsSummary, EditPlan, PathKind, Progress, Shard, check_ledger,
};
use canopy_protocol::aoi::Grid;
use canopy_server::edits::{EditStore, SqliteEditStore};
use canopy_server::session::StoreHead;
use canopy_server::{NatsConfig, NatsEditStore};
use canopy_worlds::world::World;
use clap::Args;

/// Options of `canopy bots`.
// An option given twice takes the last value: `--processes` starts this command again with the parent's options
// and, after them, each process's own (`--count`, `--first-id`, `--connect-rate`, …).
#[derive(Args, Debug)]
#[command(args_override_self = true)]
pub(super) struct BotsArgs {
    /// How many bots.
    #[arg(long, default_value_t = 10)]
    count: usize,
    /// Their path.
    #[arg(long, value_parser = super::named(&PathKind::NAMES), default_value_t = PathKind::Line)]
    path: PathKind,
    /// Walking (or flying) speed, metres per second.
    #[arg(long, default_value_t = 5.0)]
    speed: f32,
    /// `--path flight`: height above the terrain, metres (the area-of-interest radius then follows from altitude
    /// and speed under the server's rules, instead of `--radius`).
    #[arg(long, default_value_t = 1500.0)]
    altitude: f32,
    /// How long they walk, seconds.
    #[arg(long, default_value_t = 20.0)]
    duration: f64,
    #[command(flatten)]
    far: super::far::BotFarArgs,
    /// Where the bots connect (spread over the edges given; the summary counts reconnects).
    #[command(flatten)]
    connect: super::ConnectArgs,
    /// Area-of-interest radius, metres (walkers; a flight's follows from `--altitude` and `--speed`).
    #[arg(long, default_value_t = 160.0)]
    radius: f32,
    /// The bots' link rate (bits a second: `1M`, `500k`): while moving they ask for the radius it carries at their
    /// speed over the records around them, at most the one above (default: not fitted).
    #[arg(long, value_parser = parse_link)]
    link: Option<u64>,
    /// New connections per second while ramping up.
    #[arg(long, default_value_t = 200.0)]
    connect_rate: f64,
    /// A species cache directory shared by the bots (default: none; each bot starts empty).
    #[arg(long)]
    cache_dir: Option<PathBuf>,
    /// How long a bot waits at the end for a complete area of interest, seconds.
    #[arg(long, default_value_t = 120.0)]
    settle: f64,
    /// Client UDP sockets the bots are spread over.
    #[arg(long, default_value_t = 4)]
    endpoints: usize,
    /// Seed of the paths.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Check each bot's final state against this world: a manifest path or an embedded world's name (`forest`,
    /// `highlands`); it must be the world the server serves (default: the embedded default world).
    #[arg(long)]
    world: Option<String>,
    /// Do not check the final state against the world.
    #[arg(long)]
    no_verify: bool,
    /// Only the first N bots expand their cells (and are checked against the world); the others take the cells'
    /// grants and overlays and expand nothing: the server sees the traffic of every bot, this machine does the
    /// work of N (default: every bot expands).
    #[arg(long, value_name = "N", conflicts_with = "records")]
    expanding: Option<usize>,
    /// How often each bot moves and decides whether to send a viewpoint, milliseconds.
    #[arg(long, default_value_t = 100)]
    tick_ms: u64,
    /// Keep every bot inside a square of this side, metres, around the middle of the world (default: the whole
    /// world), so they hold the same cells.
    #[arg(long)]
    spread: Option<f32>,
    /// Edits a second each editing bot makes while it walks: plants of a random species within half its radius,
    /// and every third edit a fell of one of its own plants (0: no edits). Needs `--token`.
    #[arg(long, default_value_t = 0.0)]
    edit_rate: f64,
    /// How many bots edit, the first ones (default: all of them with `--edit-rate`); the others watch.
    #[arg(long)]
    editors: Option<usize>,
    /// The editor token the editing bots connect with (64 hexadecimal digits, as `canopy-server --add-editor`
    /// printed it; the editor's `rate` is shared by all of them); also read from `CANOPY_TOKEN`.
    #[arg(long, env = "CANOPY_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// After the run, read every edit the bots had acknowledged back from the edit store — `nats://HOST:PORT[,…]`
    /// (the edges' JetStream cluster) or a server's data directory (its `edits.sqlite`) — and count those lost or
    /// stored twice; the summary's last line is then `edits acknowledged N, lost L, duplicated D, fan-out p50 … p99
    /// …, reconnects R`, and a lost or duplicated edit fails the run. The world (`--world`) names the stream.
    #[arg(long, value_name = "nats://…|DIR")]
    check_edits: Option<String>,
    /// Run the bots in N processes: this command started again N times, each with its share of the bots (the
    /// same bots, paths and seeds as in one process) and of `--connect-rate`, and one summary over all of them,
    /// its percentiles over every process's samples. At 10,000 bots and more one process is itself the
    /// bottleneck; spread over processes, the server is what is measured. Not with `--edit-rate` or
    /// `--check-edits` (fan-out and the edit ledger are measured within one process).
    #[arg(long, value_name = "N", default_value_t = 1)]
    processes: usize,
    /// The first bot's id: this process runs bots `--first-id` to `--first-id + --count` of a `--processes` run.
    #[arg(long, hide = true, default_value_t = 0)]
    first_id: usize,
    /// Write the bots' raw results (a `Shard`) to standard output for a `--processes` parent, and nothing else;
    /// exit with success whatever the bots did (the parent judges).
    #[arg(long, hide = true)]
    shard_out: bool,
    /// No progress bar (for logs).
    #[arg(long)]
    quiet: bool,
}

/// Open the edit store `--check-edits` names, for the world `world`.
fn open_store(at: &str, world: &World) -> anyhow::Result<Arc<dyn EditStore>> {
    if at.starts_with("nats://") {
        let cfg = NatsConfig {
            servers: at.split(',').map(|s| s.trim().to_owned()).filter(|s| !s.is_empty()).collect(),
            world: world.name.clone(),
            replicas: 1,
        };
        return Ok(Arc::new(NatsEditStore::connect(cfg).with_context(|| format!("--check-edits {at}"))?));
    }
    let dir = PathBuf::from(at);
    if !dir.join("edits.sqlite").is_file() {
        bail!("--check-edits {at}: no edits.sqlite there (expected nats://… or a server's data directory)");
    }
    Ok(Arc::new(SqliteEditStore::open(&dir).with_context(|| format!("--check-edits {at}"))?))
}

/// Run `canopy bots`.
// Negated comparisons are deliberate: NaN is rejected too.
#[allow(clippy::neg_cmp_op_on_partial_ord, clippy::nonminimal_bool)]
pub(super) fn run(args: BotsArgs) -> anyhow::Result<ExitCode> {
    if args.count == 0
        || !(args.speed.is_finite() && args.speed >= 0.0)
        || !(args.duration >= 0.0)
        || !(args.settle >= 0.0)
        || !(args.altitude.is_finite() && args.altitude >= 0.0)
    {
        bail!("--count must be positive, --speed, --duration, --settle and --altitude not negative");
    }
    if !(args.edit_rate.is_finite() && (0.0..=10_000.0).contains(&args.edit_rate)) {
        bail!("--edit-rate is edits a second per bot, 0 to 10000");
    }
    if args.spread.is_some_and(|s| !(s.is_finite() && s > 0.0)) {
        bail!("--spread must be a positive number of metres");
    }
    if args.processes == 0 {
        bail!("--processes must be at least 1");
    }
    if (args.processes > 1 || args.shard_out) && (args.edit_rate > 0.0 || args.check_edits.is_some()) {
        bail!(
            "--processes runs the bots in several processes: not with --edit-rate or --check-edits (fan-out and the \
             edit ledger are measured within one process)"
        );
    }
    if args.processes > 1 {
        // What would fail in every process fails once, here; the world is loaded where it is checked against.
        args.connect.trust()?;
        args.far.view(args.path == PathKind::Flight, args.altitude)?;
        let summary = processes::run(args.count, args.processes, args.connect_rate)?;
        print!("{summary}");
        return Ok(if summary.ok() { ExitCode::SUCCESS } else { ExitCode::FAILURE });
    }
    let edits = if args.edit_rate > 0.0 {
        let Some(token) = &args.token else {
            bail!(
                "--edit-rate needs an editor token: --token HEX or CANOPY_TOKEN (as `canopy-server --editors FILE \
                 --add-editor NAME` prints it)"
            );
        };
        let token = canopy_server::session::unhex(token.trim()).context("--token: expected hexadecimal digits")?;
        let editors = args.editors.unwrap_or(args.count).min(args.count);
        Some(EditPlan::new(args.edit_rate, editors, token))
    } else {
        None
    };
    let trust = args.connect.trust()?;
    let world = if args.no_verify && args.check_edits.is_none() {
        None
    } else {
        Some(Arc::new(match &args.world {
            Some(w) => super::world_arg(w)?,
            None => World::default_world(),
        }))
    };
    let ledger = match (&args.check_edits, &world) {
        (Some(at), Some(w)) => Some((open_store(at, w)?, StoreHead::of_world(w)?.world().grid)),
        _ => None,
    };
    let verify = if args.no_verify { None } else { world };
    let mut connect = args.connect.config(&args.connect.edges(), trust);
    // One expander for every bot of the process: they share its cache, as they would share a world's cells.
    connect.expander = args.connect.expander();
    let mut cfg = BotsConfig::new(args.count, connect);
    cfg.first_id = args.first_id;
    cfg.expanding = args.expanding;
    cfg.path = args.path;
    cfg.speed = args.speed;
    cfg.altitude = args.altitude;
    cfg.duration = Duration::from_secs_f64(args.duration);
    cfg.radius = args.radius;
    cfg.fit = args.link.map(|rate| canopy_harness::bots::LinkFit { link_bits: rate as f64 });
    cfg.connect_rate = args.connect_rate;
    cfg.cache_dir = args.cache_dir.clone();
    cfg.settle = Duration::from_secs_f64(args.settle);
    cfg.endpoints = args.endpoints;
    cfg.seed = args.seed;
    cfg.tick = Duration::from_millis(args.tick_ms.max(1));
    cfg.verify = verify;
    cfg.spread = args.spread;
    cfg.edits = edits;
    cfg.far = args.far.view(args.path == PathKind::Flight, args.altitude)?;
    if args.shard_out {
        let (reports, _) = walk_bots(cfg, true)?;
        let mut out = std::io::stdout().lock();
        out.write_all(&Shard::new(&reports).encode()).and_then(|()| out.flush()).context("writing the shard")?;
        return Ok(ExitCode::SUCCESS);
    }
    let summary = run_bots(cfg, args.quiet, ledger)?;
    print!("{summary}");
    Ok(if summary.ok() { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}

/// Run bots on a fresh runtime with a progress display; returns the summary, with the acknowledged edits checked
/// against `ledger`'s store (on its world's grid) when given.
pub(super) fn run_bots(
    cfg: BotsConfig,
    quiet: bool,
    ledger: Option<(Arc<dyn EditStore>, Grid)>,
) -> anyhow::Result<BotsSummary> {
    let fanout = cfg.edits.as_ref().map(|e| Arc::clone(&e.fanout));
    let (reports, wall) = walk_bots(cfg, quiet)?;
    let summary = BotsSummary::new(&reports, wall);
    let summary = match fanout {
        Some(f) => summary.with_fanout(f.report()),
        None => summary,
    };
    Ok(match ledger {
        Some((store, grid)) => {
            let checked = check_ledger(store.as_ref(), &grid, BotsSummary::acknowledged(&reports))
                .context("reading the acknowledged edits back from the store")?;
            summary.with_ledger(checked)
        }
        None => summary,
    })
}

/// Run bots on a fresh runtime with a progress display (none when `quiet`); returns every bot's report and the
/// wall time of the run.
fn walk_bots(cfg: BotsConfig, quiet: bool) -> anyhow::Result<(Vec<BotReport>, Duration)> {
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    let progress = Arc::new(Progress::default());
    let total = cfg.count as u64;
    let started = Instant::now();
    let reports = rt.block_on(async {
        let show = {
            let progress = Arc::clone(&progress);
            tokio::spawn(async move {
                let bar = if quiet { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(total) };
                bar.set_style(
                    indicatif::ProgressStyle::with_template("{elapsed:>4} [{bar:30}] {pos}/{len} finished  {msg}")
                        .expect("a valid template")
                        .progress_chars("=> "),
                );
                let mut last = (Instant::now(), 0u64);
                loop {
                    tokio::time::sleep(Duration::from_millis(500)).await;
                    let records = progress.records.load(Relaxed);
                    let now = Instant::now();
                    let rate = (records - last.1) as f64 / now.duration_since(last.0).as_secs_f64();
                    last = (now, records);
                    bar.set_position(progress.finished.load(Relaxed));
                    let edits = match progress.edits.load(Relaxed) {
                        0 => String::new(),
                        n => format!(" · edits {n}"),
                    };
                    let edits = match progress.reconnects.load(Relaxed) {
                        0 => edits,
                        n => format!("{edits} · reconnects {n}"),
                    };
                    bar.set_message(format!(
                        "connected {} · AOI complete {} · failed {} · records {records} ({rate:.0}/s){edits}",
                        progress.connected.load(Relaxed),
                        progress.complete.load(Relaxed),
                        progress.failed.load(Relaxed),
                    ));
                    if progress.finished.load(Relaxed) >= total {
                        bar.finish();
                        return;
                    }
                }
            })
        };
        let reports = bots::run(cfg, Arc::clone(&progress)).await;
        if reports.is_err() {
            show.abort();
        }
        let _ = show.await;
        reports
    })?;
    Ok((reports, started.elapsed()))
}

/// A link rate for `--link`: a number of bits a second, not "unlimited".
pub(crate) fn parse_link(s: &str) -> Result<u64, String> {
    canopy_harness::bandwidth::link::parse_rate(s)?.ok_or_else(|| format!("`{s}`: give a rate, e.g. 1M"))
}
