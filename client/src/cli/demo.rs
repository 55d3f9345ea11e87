//! `canopy demo`: the streaming demo. Starts `canopy-server` in-process on the embedded default world (or any world:
//! `--world highlands`, a manifest path; its cells expanded on demand into the server's cell cache), runs a few
//! bots against it over real QUIC on loopback (certificate pinned), and prints a live summary — clients, records
//! per second, bytes by message class, area-of-interest completeness — until `--duration` passes or Ctrl-C; then
//! the bots stop, settle, and are checked against the world.
//!
//! Where there is a display (`DISPLAY` or `WAYLAND_DISPLAY` set) it also opens the walkthrough window
//! (`canopy walk`) on the same in-process server; it closes after `--duration` (0: when you close it), and the bots
//! walk until it does. `--no-window` keeps the demo headless.

use std::net::SocketAddr;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use anyhow::Context;
use canopy_client::{ConnectConfig, Trust};
use canopy_harness::bots::{self, BotsConfig, BotsSummary, PathKind, Progress};
use canopy_harness::numbers::kib;
use canopy_protocol::messages::ServerMsgKind;
use canopy_server::{CellCacheConfig, Cells, Metrics, ServeOptions, ServerConfig, serve};
use canopy_worlds::world::World;
use clap::Args;

/// Options of `canopy demo`.
#[derive(Args, Debug)]
pub(super) struct DemoArgs {
    /// How many bots.
    #[arg(long, default_value_t = 8)]
    bots: usize,
    /// How long the bots walk, seconds (0: until Ctrl-C, or until the window is closed).
    #[arg(long, default_value_t = 30.0)]
    duration: f64,
    /// Their path.
    #[arg(long, value_parser = super::named(&PathKind::NAMES), default_value_t = PathKind::Random)]
    path: PathKind,
    /// Walking (or flying) speed, metres per second.
    #[arg(long, default_value_t = 8.0)]
    speed: f32,
    /// `--path flight`: height above the terrain, metres (the radius then follows from altitude and speed).
    #[arg(long, default_value_t = 1500.0)]
    altitude: f32,
    /// Area-of-interest radius, metres (walkers).
    #[arg(long, default_value_t = 200.0)]
    radius: f32,
    /// The world to serve: an embedded world's name (`forest`, `highlands`) or a manifest path (default: the
    /// embedded default world).
    #[arg(long)]
    world: Option<String>,
    /// The in-process server's largest area-of-interest radius, metres (what a flight asks for is capped to it).
    #[arg(long, default_value_t = canopy_protocol::aoi::AoiParams::default().max_radius)]
    max_radius: f32,
    /// The in-process server's cap on each client's bytes a second (default: the server's default).
    #[arg(long)]
    bandwidth: Option<u64>,
    /// The in-process server's cell cache, MiB.
    #[arg(long, default_value_t = 256)]
    cell_cache_mib: usize,
    /// UDP address of the in-process server.
    #[arg(long, default_value = "127.0.0.1:0")]
    listen: SocketAddr,
    /// TCP address of its metrics endpoint.
    #[arg(long, default_value = "127.0.0.1:0")]
    metrics: SocketAddr,
    /// Do not open the walkthrough window even where there is a display.
    #[arg(long)]
    no_window: bool,
    /// The bots and the window take every cell's records from the server instead of expanding cells themselves.
    #[arg(long)]
    records: bool,
}

/// Whether a window can be opened here.
fn display_present() -> bool {
    ["DISPLAY", "WAYLAND_DISPLAY"].iter().any(|v| std::env::var_os(v).is_some_and(|s| !s.is_empty()))
}

/// `canopy walk`'s options with their defaults (the demo sets the server and its certificate).
#[derive(clap::Parser, Debug)]
struct WalkCli {
    #[command(flatten)]
    walk: super::walk::WalkArgs,
}

fn live_line(t: Duration, m: &Metrics, p: &Progress, bots: usize, last: &mut (Instant, u64)) -> String {
    let records = m.records.load(Relaxed);
    let now = Instant::now();
    let rate = (records - last.1) as f64 / now.duration_since(last.0).as_secs_f64().max(1e-3);
    *last = (now, records);
    let b = |c: ServerMsgKind| m.bytes[c].load(Relaxed);
    let cells = b(ServerMsgKind::Cells);
    let per = if records > 0 { cells as f64 / records as f64 } else { 0.0 };
    format!(
        "{:>5.1}s  clients {:>3}  AOI complete {}/{}  records {records} ({rate:.0}/s)  grants {}  sent: cells {} ({per:.2} B/record), species {}, releases {}",
        t.as_secs_f64(),
        m.clients.load(Relaxed),
        p.complete.load(Relaxed),
        bots,
        m.messages[ServerMsgKind::Grant].load(Relaxed),
        kib(cells),
        kib(b(ServerMsgKind::Species)),
        kib(b(ServerMsgKind::Release)),
    )
}

/// Run `canopy demo`.
pub(super) fn run(args: DemoArgs) -> anyhow::Result<ExitCode> {
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    if args.no_window || !display_present() {
        return demo(args, None, stop_rx);
    }
    // winit wants the main thread: the server and the bots run on another, the window here.
    let (addr_tx, addr_rx) = std::sync::mpsc::channel();
    let duration = args.duration.max(0.0);
    let records = args.records;
    let started = Instant::now();
    let headless = std::thread::spawn(move || demo(args, Some(addr_tx), stop_rx));
    let walked = match addr_rx.recv() {
        Ok((addr, fingerprint)) => {
            // The window's own defaults, then the in-process server's address and certificate.
            let mut walk = <WalkCli as clap::Parser>::try_parse_from(["walk"])?.walk;
            walk.connect.server = Some(canopy_client::net::Edges::one(addr));
            walk.connect.cert_fingerprint = Some(fingerprint);
            walk.exit_after = duration;
            walk.connect.records = records;
            Some(super::walk::run(walk))
        }
        // The demo failed before its server was up; its error is the one to report.
        Err(_) => None,
    };
    if let Some(Err(e)) = &walked {
        // No window after all (no Vulkan or GL adapter, an unreachable display): the demo goes on headless, for
        // its duration or until Ctrl-C.
        eprintln!("canopy demo: the walkthrough window failed ({e:#}); the bots walk on without it");
        if duration > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(duration).saturating_sub(started.elapsed()));
            let _ = stop_tx.send(true);
        }
    } else {
        let _ = stop_tx.send(true);
    }
    headless.join().map_err(|_| anyhow::anyhow!("the demo thread panicked"))?
}

/// The server and the bots with the live summary; with `window`, the server's address and fingerprint go there
/// and the bots walk until `stop` (the window closed).
fn demo(
    args: DemoArgs,
    window: Option<std::sync::mpsc::Sender<(SocketAddr, String)>>,
    stop_rx: tokio::sync::watch::Receiver<bool>,
) -> anyhow::Result<ExitCode> {
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    rt.block_on(async move {
        let loaded = Instant::now();
        let world = Arc::new(match &args.world {
            Some(w) => super::world_arg(w)?,
            None => World::default_world(),
        });
        // As `canopy-server` serves it: cells expanded on demand into a byte-bounded cache.
        let cache = CellCacheConfig { limit_bytes: args.cell_cache_mib.saturating_mul(1 << 20), ..CellCacheConfig::default() };
        print!("{}", world.content_summary());
        println!("world loaded in {:.1} s", loaded.elapsed().as_secs_f64());
        let mut cfg = ServerConfig { listen: args.listen, metrics: Some(args.metrics), ..ServerConfig::default() };
        cfg.session.aoi.max_radius = args.max_radius;
        if let Some(b) = args.bandwidth {
            cfg.session.bandwidth = Some(b);
        }
        cfg.session.aoi.validate().context("--max-radius")?;
        let server_aoi = cfg.session.aoi;
        let opts = ServeOptions { server: cfg, cells: Cells::OnDemand(cache), ..ServeOptions::default() };
        let server = serve((*world).clone(), opts).await?;
        println!("canopy-server (in-process) on {} — fingerprint {}", server.local_addr(), server.fingerprint());
        if let Some(m) = server.metrics_addr() {
            println!("metrics: http://{m}/metrics");
        }
        let (stop_tx, bots_stop) = tokio::sync::watch::channel(false);
        let mut window_closed = stop_rx.clone();
        let windowed = window.is_some();
        if let Some(tx) = window {
            let _ = tx.send((server.local_addr(), server.fingerprint().to_string()));
        }
        let trust = Trust::pinned(server.fingerprint()).context("the server's fingerprint")?;
        let mut connect = ConnectConfig::new(server.local_addr(), trust);
        connect.expander = (!args.records).then(canopy_client::expand::Expander::default_pool);
        let mut cfg = BotsConfig::new(args.bots, connect);
        cfg.path = args.path;
        cfg.speed = args.speed;
        cfg.altitude = args.altitude;
        cfg.radius = args.radius;
        cfg.duration = if args.duration > 0.0 && !windowed { Duration::from_secs_f64(args.duration) } else { Duration::from_secs(u64::MAX / 4) };
        cfg.connect_rate = 50.0;
        cfg.verify = Some(Arc::clone(&world));
        cfg.stop = bots_stop;
        // Flying bots ask for the far view (summary nodes to the horizon), as `canopy bots` does.
        cfg.far = super::far::BotFarArgs::default().view(args.path == PathKind::Flight, args.altitude)?;
        let forever = args.duration <= 0.0 || windowed;
        let walk =
            bots::Walk { path: args.path, speed: args.speed, radius: args.radius, altitude: args.altitude, seed: 0, fit: None };
        let height = if args.path == PathKind::Flight { format!(", {} m above the terrain", args.altitude) } else { String::new() };
        println!(
            "{} bots {} ({}, {} m/s{height}, AOI radius {} m) {}",
            args.bots,
            if args.path == PathKind::Flight { "flying" } else { "walking" },
            args.path,
            args.speed,
            walk.radius(&server_aoi),
            if windowed {
                "until the window closes".to_string()
            } else if forever { "until Ctrl-C".to_string() } else { format!("for {} s (Ctrl-C stops early)", args.duration) }
        );
        let progress = Arc::new(Progress::default());
        let started = Instant::now();
        let mut run = tokio::spawn(bots::run(cfg, Arc::clone(&progress)));
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        tick.tick().await;
        let mut last = (Instant::now(), 0u64);
        let mut ctrl_c = std::pin::pin!(tokio::signal::ctrl_c());
        let mut stopping = false;
        let reports = loop {
            tokio::select! {
                r = &mut run => break r??,
                _ = tick.tick() => println!("{}", live_line(started.elapsed(), server.metrics(), &progress, args.bots, &mut last)),
                _ = &mut ctrl_c, if !stopping => {
                    println!("stopping: the bots stop walking, settle and are checked");
                    stopping = true;
                    let _ = stop_tx.send(true);
                }
                _ = window_closed.wait_for(|closed| *closed), if windowed && !stopping => {
                    println!("stopping (the window closed, or the time is up): the bots stop walking, settle and are checked");
                    stopping = true;
                    let _ = stop_tx.send(true);
                }
            }
        };
        println!("{}", live_line(started.elapsed(), server.metrics(), &progress, args.bots, &mut last));
        let summary = BotsSummary::new(&reports, started.elapsed());
        print!("{summary}");
        let m = server.metrics();
        let sent: u64 = m.bytes.iter().map(|(_, b)| b.load(Relaxed)).sum();
        println!(
            "server sent {} in {} messages; {} records; species sent {} times to {} bots",
            kib(sent),
            m.messages.iter().map(|(_, n)| n.load(Relaxed)).sum::<u64>(),
            m.records.load(Relaxed),
            m.messages[ServerMsgKind::Species].load(Relaxed),
            args.bots
        );
        server.shutdown(Duration::from_secs(1)).await;
        anyhow::Ok(if summary.ok() { ExitCode::SUCCESS } else { ExitCode::FAILURE })
    })
}
