//! `canopy-server`: serve a world over QUIC. With no arguments it serves the embedded default world
//! (`worlds/forest`) on 127.0.0.1:4433 with metrics on http://127.0.0.1:9433/metrics, and keeps its certificate in
//! `./canopy-data/`.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;

use anyhow::Context;
use canopy_protocol::aoi::AoiParams;
use canopy_server::session::{Editors, SessionConfig};
use canopy_server::worlds::world::World;
use canopy_server::{
    AdmissionConfig, CellCacheConfig, Cells, Edits, NatsConfig, ServeOptions, ServerConfig, WebConfig, resident_bytes,
    serve,
};
use clap::Parser;
use std::sync::Arc;
use tracing::info;

/// The allocator: jemalloc, whose background threads (turned on in `main`) give pages that sit unused back to the
/// operating system (glibc's malloc keeps what its per-thread arenas freed), so the server's memory goes down when
/// clients leave (issue 14; docs/streaming.md).
#[cfg(not(target_env = "msvc"))]
#[global_allocator]
static ALLOCATOR: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

/// Serve a Canopy world: species once per client, instance records by area of interest, over QUIC.
#[derive(Parser, Debug)]
#[command(name = "canopy-server", version, about)]
struct Args {
    /// A world manifest (`.world`); without one, the embedded default world.
    #[arg(long)]
    world: Option<PathBuf>,
    /// UDP address to listen on.
    #[arg(long, default_value = "127.0.0.1:4433")]
    listen: SocketAddr,
    /// UDP sockets on the listening port, each with its own QUIC endpoint and I/O task (`SO_REUSEPORT`; the kernel
    /// spreads clients over them by address and port); 0: one per core.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u16).range(0..=canopy_server::MAX_ENDPOINTS as i64))]
    endpoints: u16,
    /// Send each connection's datagrams in batches through one system call (GSO): less CPU for bulk senders, a
    /// ~16 KiB buffer kept per connection.
    #[arg(long)]
    gso: bool,
    /// TCP address of the Prometheus metrics endpoint (`GET /metrics`).
    #[arg(long, default_value = "127.0.0.1:9433")]
    metrics: SocketAddr,
    /// Run without the metrics endpoint.
    #[arg(long)]
    no_metrics: bool,
    /// Serve the browser client on this TCP address (HTTP: `http://ADDR/` opens the walkthrough; a secure context
    /// on loopback, behind a TLS proxy elsewhere). Browsers connect over WebTransport to the UDP port either way.
    #[arg(long, value_name = "ADDR")]
    web: Option<SocketAddr>,
    /// With `--web`: the folder of the built page (`scripts/build-web` writes it).
    #[arg(long, default_value = "client/web/dist", requires = "web")]
    web_root: PathBuf,
    /// Where the certificate and the edits (`edits.sqlite`) are kept (the certificate is generated at first start).
    #[arg(long, alias = "data", default_value = "canopy-data")]
    data_dir: PathBuf,
    /// The editors file: who may plant, fell and set (without one, every session is read-only).
    #[arg(long)]
    editors: Option<PathBuf>,
    /// Add an editor of this name to the `--editors` file (created if missing) and print its token once, then
    /// exit.
    #[arg(long, value_name = "NAME", requires = "editors")]
    add_editor: Option<String>,
    /// With `--add-editor`: the world rectangle `X0,Z0,X1,Z1` the editor may change.
    #[arg(long, value_parser = parse_region, allow_hyphen_values = true)]
    region: Option<[f32; 4]>,
    /// With `--add-editor`: edits a second the editor may make.
    #[arg(long)]
    rate: Option<u32>,
    /// Keep the edits in NATS JetStream instead of `DATA/edits.sqlite`: the cluster's servers, comma-separated
    /// (`nats://127.0.0.1:4222,nats://127.0.0.1:4223`). Every edge of one world names the same cluster; edges then
    /// hold nothing that is lost when they die.
    #[arg(long, value_name = "nats://HOST:PORT[,…]")]
    edits: Option<String>,
    /// With `--edits`: replicas of the world's edit stream (3 on a three-node cluster).
    #[arg(long, default_value_t = 3)]
    edit_replicas: usize,
    /// Memory for cells' edit overlays (and edited cells' records), MiB.
    #[arg(long, default_value_t = 64)]
    overlay_cache_mib: usize,
    /// Largest area-of-interest radius a client may ask for, metres.
    #[arg(long, default_value_t = AoiParams::default().max_radius)]
    max_radius: f32,
    /// Hysteresis at the area-of-interest border, metres.
    #[arg(long, default_value_t = AoiParams::default().hysteresis)]
    hysteresis: f32,
    /// Look-ahead along the velocity, seconds.
    #[arg(long, default_value_t = AoiParams::default().lookahead_s)]
    lookahead: f32,
    /// Per-client egress cap, bytes per second (0: none). The default, 4 MB/s (32 Mbit/s), is far above what a
    /// walking or flying client needs and bounds what a viewpoint flood can make the server send.
    #[arg(long, default_value_t = 4_000_000)]
    bandwidth: u64,
    /// Most viewpoints a second a client may send (a burst of twice as many); faster ends its session.
    #[arg(long, default_value_t = SessionConfig::default().viewpoint_rate.0)]
    viewpoint_rate: u32,
    /// Send data queued for clients across all sessions, MiB, beyond which sessions pause instead of queueing more.
    #[arg(long, default_value_t = 256)]
    send_budget_mib: usize,
    /// Memory for expanded cells (quantised records and their encoded batches), MiB: cells are expanded on demand
    /// and the least recently used evicted beyond it.
    #[arg(long, default_value_t = 256)]
    cell_cache_mib: usize,
    /// Memory for far-view summary nodes (encoded once, shared by every session), MiB.
    #[arg(long, default_value_t = 64)]
    summary_cache_mib: usize,
    /// Threads expanding cells (default: the available cores).
    #[arg(long)]
    cell_workers: Option<usize>,
    /// Most clients at once (a client takes a slot when its handshake completes).
    #[arg(long, default_value_t = AdmissionConfig::default().max_clients)]
    max_clients: usize,
    /// Most QUIC handshakes in flight at once.
    #[arg(long, default_value_t = AdmissionConfig::default().max_handshakes)]
    max_handshakes: usize,
    /// Handshakes in flight above which a source must prove its address with a QUIC Retry first (0: always).
    #[arg(long, default_value_t = AdmissionConfig::default().retry_above)]
    retry_above: usize,
    /// Most connections (handshakes included) from one source address.
    #[arg(long, default_value_t = AdmissionConfig::default().max_per_source)]
    max_per_source: usize,
    /// Close a session that sent no viewpoint for this many seconds while the server is near capacity.
    #[arg(long, default_value_t = ServerConfig::default().idle_slot.as_secs())]
    idle_slot: u64,
    /// Log a line with clients, records per second and memory this often, seconds (0: never).
    #[arg(long, default_value_t = 10)]
    stats_every: u64,
    /// Print the certificate fingerprint and exit.
    #[arg(long)]
    print_fingerprint: bool,
}

fn parse_region(s: &str) -> Result<[f32; 4], String> {
    let v: Vec<f32> =
        s.split(',').map(|x| x.trim().parse::<f32>().map_err(|e| format!("{x:?}: {e}"))).collect::<Result<_, _>>()?;
    match v[..] {
        [x0, z0, x1, z1] if x0 <= x1 && z0 <= z1 && v.iter().all(|x| x.is_finite()) => Ok([x0, z0, x1, z1]),
        _ => Err("expected X0,Z0,X1,Z1 with X0 ≤ X1 and Z0 ≤ Z1".into()),
    }
}

/// Append an editor with a new token to the editors file (created with mode 600 if missing) and print the token.
fn add_editor(file: &std::path::Path, name: &str, region: Option<[f32; 4]>, rate: Option<u32>) -> anyhow::Result<()> {
    use std::io::Write;
    if name.is_empty() || name.chars().any(|c| c.is_whitespace() || c == '#') {
        anyhow::bail!("an editor's name is one word without '#'");
    }
    // Check the file parses before adding to it, so a broken file is not made worse.
    if file.exists() {
        Editors::load(file)?;
    }
    let token = canopy_server::session::new_token()?;
    let line = canopy_server::session::editor_line(name, &token, region, rate);
    // The line must parse on its own before it is written (a rate of 0, an empty region).
    Editors::parse("the new editor's line", &line)?;
    let mut options = std::fs::OpenOptions::new();
    options.create(true).append(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut f = options.open(file).with_context(|| format!("opening {}", file.display()))?;
    writeln!(f, "{line}")?;
    f.sync_all()?;
    Editors::load(file)?;
    eprintln!("added editor {name} to {} (the file keeps only the token's hash)", file.display());
    println!("{}", canopy_server::session::hex(&token));
    Ok(())
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    // jemalloc's background threads purge dirty pages of idle arenas (after its decay time, 10 s by default).
    #[cfg(not(target_env = "msvc"))]
    if let Err(e) = tikv_jemalloc_ctl::background_thread::write(true) {
        tracing::warn!("jemalloc background threads: {e}; freed memory is given back only as arenas are used");
    }
    let args = Args::parse();
    if let (Some(name), Some(file)) = (&args.add_editor, &args.editors) {
        return add_editor(file, name, args.region, args.rate);
    }
    let editors = match &args.editors {
        Some(path) => Editors::load(path)?,
        None => Editors::none(),
    };
    if args.print_fingerprint {
        let id = canopy_server::Identity::load_or_generate(&args.data_dir)?;
        println!("{}", id.fingerprint());
        return Ok(());
    }
    let world = match &args.world {
        Some(path) => World::load(path).map_err(|d| anyhow::anyhow!("{d}"))?,
        None => World::default_world(),
    };
    // A world too large to materialise is summarised from its manifest alone: its instances exist only cell by cell.
    let summary = if world.is_materialised() {
        world.content_summary()
    } else {
        let [w, d] = world.cell_dims();
        format!(
            "world {}: {} species, {w} × {d} cells of {} m, expanded on demand\n",
            world.name,
            world.species.len(),
            world.cell_size
        )
    };
    let session_editors = editors.len();
    let session = SessionConfig {
        aoi: AoiParams {
            max_radius: args.max_radius,
            hysteresis: args.hysteresis,
            lookahead_s: args.lookahead,
            ..AoiParams::default()
        },
        bandwidth: (args.bandwidth > 0).then_some(args.bandwidth),
        viewpoint_rate: (args.viewpoint_rate.max(1), args.viewpoint_rate.max(1).saturating_mul(2)),
        editors: Some(Arc::new(editors)),
        ..SessionConfig::default()
    };
    session.aoi.validate().context("area-of-interest options")?;
    let cells = CellCacheConfig {
        limit_bytes: args.cell_cache_mib.saturating_mul(1 << 20),
        workers: args.cell_workers.unwrap_or(CellCacheConfig::default().workers).max(1),
        batch_records: session.batch_records,
        summary_limit_bytes: args.summary_cache_mib.saturating_mul(1 << 20),
    };
    // Edits are kept in the data directory (or the NATS cluster) and read cell by cell when a cell is first needed.
    let edits = match &args.edits {
        Some(servers) => Edits::Nats(NatsConfig {
            servers: servers.split(',').map(|s| s.trim().to_owned()).filter(|s| !s.is_empty()).collect(),
            world: world.name.clone(),
            replicas: args.edit_replicas,
        }),
        None => Edits::Sqlite(args.data_dir.clone()),
    };
    let opts = ServeOptions {
        server: ServerConfig {
            listen: args.listen,
            metrics: (!args.no_metrics).then_some(args.metrics),
            web: args.web.map(|listen| WebConfig { listen, root: args.web_root.clone() }),
            data_dir: Some(args.data_dir.clone()),
            session,
            admission: AdmissionConfig {
                max_clients: args.max_clients,
                max_handshakes: args.max_handshakes,
                retry_above: args.retry_above,
                max_per_source: args.max_per_source,
            },
            idle_slot: Duration::from_secs(args.idle_slot),
            send_budget: Some(args.send_budget_mib.saturating_mul(1 << 20)),
            endpoints: usize::from(args.endpoints),
            segmentation_offload: args.gso,
            ..ServerConfig::default()
        },
        // The cache expands the world's cells on demand, however small the world: what a served world needs.
        cells: Cells::OnDemand(cells),
        edits,
        overlay_cache_bytes: args.overlay_cache_mib.saturating_mul(1 << 20),
    };
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    rt.block_on(async move {
        let rss_before = resident_bytes();
        let server = serve(world, opts).await?;
        print!("{summary}");
        println!("{}", server.cells());
        println!("listening on {} (QUIC, ALPN canopy/1; {} endpoints)", server.local_addr(), server.endpoints());
        if let Some(m) = server.metrics_addr() {
            println!("metrics on http://{m}/metrics");
        }
        let how = if server.identity_generated() { "generated" } else { "loaded" };
        println!("certificate {how} in {}", args.data_dir.display());
        let editors_n = session_editors;
        println!("{} edits stored in {}; {editors_n} editors", server.edit_count(), server.edits_at());
        println!("fingerprint {}", server.fingerprint());
        let days = canopy_server::WEB_CERT_VALIDITY.as_secs() / 86_400;
        println!(
            "WebTransport (ALPN h3, path {}) fingerprint {} (valid {days} days, renewed while running)",
            canopy_server::WEB_PATH,
            server.web_fingerprint()
        );
        if let Some(web) = server.web_addr() {
            if !args.web_root.join("index.html").is_file() {
                tracing::warn!("{} has no index.html: build the page with scripts/build-web", args.web_root.display());
            }
            println!("browser client on http://{web}/");
        }
        let (r, s) = server.socket_buffers();
        println!("socket buffers: receive {r} B, send {s} B");
        let metrics = std::sync::Arc::clone(server.metrics());
        let every = Duration::from_secs(args.stats_every.max(1));
        let stats = tokio::spawn(async move {
            if args.stats_every == 0 {
                return;
            }
            let mut tick = tokio::time::interval(every);
            tick.tick().await;
            loop {
                tick.tick().await;
                let clients = metrics.clients.load(Relaxed);
                let rss = resident_bytes().unwrap_or(0);
                let per_client = match (rss_before, clients) {
                    (Some(b), c) if c > 0 => format!("{:.1} KiB", rss.saturating_sub(b) as f64 / 1024.0 / c as f64),
                    _ => "-".into(),
                };
                let (cache_kib, expansions) =
                    metrics.cells().map_or((0, 0), |c| (c.bytes.load(Relaxed) / 1024, c.expansions.load(Relaxed)));
                info!(
                    clients,
                    cache_kib,
                    expansions,
                    records_per_s = metrics.records_per_second.load(Relaxed),
                    records = metrics.records.load(Relaxed),
                    rss_mib = rss / (1 << 20),
                    per_client = %per_client,
                    "stats"
                );
            }
        });
        tokio::signal::ctrl_c().await.context("waiting for Ctrl-C")?;
        println!("shutting down");
        stats.abort();
        server.shutdown(Duration::from_secs(2)).await;
        anyhow::Ok(())
    })
}
