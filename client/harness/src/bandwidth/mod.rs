//! The bandwidth measurement harness (`canopy bandwidth`): procedural streaming against explicit geometry, through
//! the same server, area of interest, pacing, paths and links (seed 001 §4 and §7).
//!
//! A run is a list of [`Scenario`]s — a payload mode ([`PayloadMode`]: procedural, unique meshes, instanced) and a
//! link ([`link::LinkSpec`]: rate cap, latency, loss, emulated by a UDP relay per client) — each run by the same
//! bots on the same scripted paths: a straight walk at a given speed with a teleport half-way. Every bot samples,
//! at a fixed interval, its bytes by class (the transport overhead being what the UDP totals hold beyond the
//! frames, so the classes add up to the wire), and its visible completeness: of the instances within view
//! distance in the world itself ([`measure::GroundTruth`]), the fraction it holds. The [`report`] writes a
//! markdown report, CSV files and SVG plots.

pub mod geometry;
pub mod link;
pub mod measure;
pub mod report;
pub mod sizes;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

use canopy_protocol::messages::{ByKind, GeometryKind};
use canopy_server::session::{GeometrySource, Payload, PayloadMode, SessionConfig};
use canopy_server::{GridStore, Server, ServerConfig, WorldStore};
use canopy_worlds::world::World;
use quinn::Endpoint;

use crate::bots::{self, BotReport, Completion, DriveHooks, DrivePlan, PathKind, Walker};
use canopy_client::net::{ClientError, ConnectConfig, Connection, Trust};
use canopy_client::state::Event;
use geometry::{MeshSource, SourceStats};
use link::{LinkSpec, Relay};
use measure::{Bytes, CompletenessStats, GroundTruth, Sample, SamplePhase};

/// One measured configuration: what the server sends and over which link.
#[derive(Clone, Debug, PartialEq)]
pub struct Scenario {
    /// A short name (file names, tables).
    pub name: String,
    /// What goes out per instance and species.
    pub mode: PayloadMode,
    /// The link every bot is behind.
    pub link: LinkSpec,
}

impl Scenario {
    /// A scenario named after its mode and link rate.
    pub fn new(mode: PayloadMode, link: LinkSpec) -> Scenario {
        let rate = match link.rate {
            None => "unlimited".to_string(),
            Some(r) if r >= 1_000_000 => format!("{}M", r as f64 / 1e6),
            Some(r) => format!("{}k", r as f64 / 1e3),
        };
        let loss = if link.loss > 0.0 { format!("-loss{}", link.loss * 100.0) } else { String::new() };
        Scenario { name: format!("{}-{rate}{loss}", mode.label()), mode, link }
    }
}

/// A server to measure instead of the in-process one (only the payload it serves can be measured).
#[derive(Clone, Debug)]
pub struct External {
    /// Its UDP address.
    pub server: SocketAddr,
    /// How its certificate is trusted.
    pub trust: Trust,
}

/// How a run goes.
#[derive(Clone, Debug)]
pub struct BandwidthConfig {
    /// Bots per scenario.
    pub bots: usize,
    /// How long each bot walks.
    pub duration: Duration,
    /// Walking speed, metres per second.
    pub speed: f32,
    /// Area-of-interest radius the bots ask for, metres.
    pub radius: f32,
    /// View distance for visible completeness, metres.
    pub view: f32,
    /// Teleport half-way through the walk.
    pub teleport: bool,
    /// Seeds the paths (bot `i` uses `seed + i`; the same in every scenario).
    pub seed: u64,
    /// How long a bot waits at the end for a complete area of interest.
    pub settle: Duration,
    /// Sampling interval.
    pub sample: Duration,
    /// The scenarios, in order.
    pub scenarios: Vec<Scenario>,
    /// The output folder.
    pub out: PathBuf,
    /// Measure this server instead of an in-process one.
    pub external: Option<External>,
    /// Server pacing as a fraction of the link rate (the session's token bucket; 0: none).
    pub pace: f64,
    /// Memory bound of the server's cache of encoded instance meshes, bytes.
    pub cache_bytes: usize,
    /// Instances per species for the seed 001 §7 size table (0: no table).
    pub size_seeds: u32,
    /// Instances of the world whose unique meshes are encoded to estimate baseline 1's cost per instance over the
    /// whole world (evenly spaced ids; 0: none). A slow link lets only a few whole trees through in a short walk.
    pub mesh_sample: usize,
    /// Show a progress bar.
    pub progress: bool,
    /// The command line, for the report.
    pub command: String,
}

impl BandwidthConfig {
    /// The default walkthrough: 2 bots, 30 s at 10 m/s with a teleport, AOI and view 160 m; the three payload
    /// modes over 1 Mbit/s with 20 ms latency, and procedural over 56 kbit/s (100 ms) and 10 Mbit/s with 1 % loss.
    pub fn default_run() -> BandwidthConfig {
        let one = LinkSpec::new(Some(1_000_000), 20, 0.0);
        BandwidthConfig {
            bots: 2,
            duration: Duration::from_secs(30),
            speed: 10.0,
            radius: 160.0,
            view: 160.0,
            teleport: true,
            seed: 1,
            settle: Duration::from_secs(10),
            sample: Duration::from_millis(250),
            scenarios: vec![
                Scenario::new(PayloadMode::Procedural, one),
                Scenario::new(PayloadMode::UniqueMesh, one),
                Scenario::new(PayloadMode::Instanced, one),
                Scenario::new(PayloadMode::Procedural, LinkSpec::new(Some(56_000), 100, 0.0)),
                Scenario::new(PayloadMode::Procedural, LinkSpec::new(Some(10_000_000), 20, 0.01)),
            ],
            out: PathBuf::from("out/bandwidth"),
            external: None,
            pace: 0.9,
            cache_bytes: 512 * 1024 * 1024,
            size_seeds: 3,
            mesh_sample: 40,
            progress: true,
            command: "canopy bandwidth".into(),
        }
    }
}

/// Why a run failed.
#[derive(Debug, thiserror::Error)]
pub enum BandwidthError {
    /// The server did not start.
    #[error("starting the server: {0}")]
    Server(#[from] canopy_server::StartError),
    /// The world store could not be built.
    #[error("building the world store: {0}")]
    Store(String),
    /// A socket or file failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The client side failed before any bot ran.
    #[error(transparent)]
    Client(#[from] ClientError),
    /// The configuration is not usable.
    #[error("{0}")]
    Config(String),
    /// The server streams another world than the one the ground truth was computed from.
    #[error("the server's world has {server} instances, the ground truth {truth}: not the same world")]
    WorldMismatch {
        /// Instances in the server's welcome.
        server: u32,
        /// Instances in the ground truth.
        truth: usize,
    },
}

/// The link's counters for one bot at the end.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LinkTotals {
    /// Server → client datagrams offered to the link, and of those lost, dropped at the queue, delivered.
    pub down: [u64; 4],
    /// Client → server, likewise.
    pub up: [u64; 4],
    /// Server → client UDP payload bytes offered to the link.
    pub down_bytes: u64,
}

/// What one bot measured.
#[derive(Clone, Debug, Default)]
pub struct BotResult {
    /// What any bot reports: index, why it stopped early (if it did), records received and held, time to its
    /// first complete area of interest, whether it ended complete.
    pub bot: BotReport,
    /// Its samples, in time order.
    pub samples: Vec<Sample>,
    /// Its bytes at the end.
    pub bytes: Bytes,
    /// Explicit-geometry payload bytes received by kind (instance meshes, species meshes, transforms).
    pub geometry: [u64; 3],
    /// Species received: programs (procedural) or species meshes started (instanced), in arrival order.
    pub species_ids: Vec<u8>,
    /// Instance meshes whose first chunk arrived, and the sum of their sizes as the chunks announce them
    /// (baseline 1: the per-instance cost is known before a whole mesh is through a slow link).
    pub mesh_headers: (u64, u64),
    /// When it teleported (seconds since the scenario started).
    pub teleported_at: Option<f64>,
    /// Seconds from the teleport to the next complete area of interest.
    pub teleport_complete: Option<f64>,
    /// The link's counters (`None`: not behind an emulated link).
    pub link: Option<LinkTotals>,
}

impl BotResult {
    /// Seconds from starting to connect to the first complete area of interest.
    pub fn first_complete(&self) -> Option<f64> {
        self.bot.first_complete.map(|d| d.as_secs_f64())
    }

    /// Visible completeness while walking with its area of interest filled once (excluding the initial fill and
    /// the refill after the teleport, which the two times to complete measure).
    pub fn walking(&self) -> CompletenessStats {
        CompletenessStats::over(&self.samples, |s| s.phase == SamplePhase::Walking)
    }

    /// Visible completeness over every sample taken before settling.
    pub fn overall(&self) -> CompletenessStats {
        CompletenessStats::over(&self.samples, |s| s.phase != SamplePhase::Settling)
    }
}

/// What one scenario measured.
#[derive(Clone, Debug)]
pub struct ScenarioResult {
    /// The scenario.
    pub scenario: Scenario,
    /// Every bot's result.
    pub bots: Vec<BotResult>,
    /// Wall time.
    pub wall: f64,
    /// What the server's mesh source encoded (explicit modes, in-process server).
    pub source: Option<SourceStats>,
    /// Frame bytes the server sent, by message class (in-process server).
    pub server_bytes: Option<ByKind<u64>>,
}

impl ScenarioResult {
    /// All bots' bytes.
    pub fn bytes(&self) -> Bytes {
        let mut b = Bytes::default();
        for bot in &self.bots {
            b.add(&bot.bytes);
        }
        b
    }

    /// All bots' records received.
    pub fn records(&self) -> u64 {
        self.bots.iter().map(|b| b.bot.records).sum()
    }

    /// Wire bytes per instance record received (all bytes, both directions).
    pub fn bytes_per_instance(&self) -> Option<f64> {
        let r = self.records();
        (r > 0).then(|| self.bytes().total() as f64 / r as f64)
    }

    /// Wire bytes per frame byte (transport overhead and the client's own messages on top of what the server
    /// sent); 1 when nothing arrived.
    pub fn wire_ratio(&self) -> f64 {
        let b = self.bytes();
        let frames = b.species + b.records + b.geometry + b.control;
        if frames == 0 { 1.0 } else { b.total() as f64 / frames as f64 }
    }

    /// Payload bytes per instance received that scale with instances (`None` if none arrived): the records, plus
    /// the transforms when instanced (`with_records: false` leaves the records out of the explicit modes, which
    /// carry them only for the harness's bookkeeping).
    pub fn per_instance_payload(&self, with_records: bool) -> Option<f64> {
        let r = self.records();
        let b = self.bytes();
        let transforms: u64 = self.bots.iter().map(|x| x.geometry[2]).sum();
        let records = if with_records || self.scenario.mode == PayloadMode::Procedural { b.records } else { 0 };
        (r > 0).then(|| (records + transforms) as f64 / r as f64)
    }

    /// Baseline 1 only: the mean size of the instance meshes whose first chunk arrived (as the chunks announce
    /// them), and how many there were.
    pub fn announced_mesh(&self) -> Option<(f64, u64)> {
        let (n, sum) = self.bots.iter().fold((0u64, 0u64), |a, b| (a.0 + b.mesh_headers.0, a.1 + b.mesh_headers.1));
        (self.scenario.mode == PayloadMode::UniqueMesh && n > 0).then(|| (sum as f64 / n as f64, n))
    }

    /// Walking completeness over all bots.
    pub fn walking(&self) -> CompletenessStats {
        let mut c = CompletenessStats { min: 1.0, ..Default::default() };
        for b in &self.bots {
            c.merge(&b.walking());
        }
        c
    }

    /// Overall completeness over all bots.
    pub fn overall(&self) -> CompletenessStats {
        let mut c = CompletenessStats { min: 1.0, ..Default::default() };
        for b in &self.bots {
            c.merge(&b.overall());
        }
        c
    }

    /// The slowest bot's time to its first complete area of interest (`None` if one never got there).
    pub fn first_complete(&self) -> Option<f64> {
        self.bots.iter().map(BotResult::first_complete).try_fold(0.0f64, |m, t| t.map(|t| m.max(t)))
    }

    /// The slowest bot's time from teleport to complete (`None` if one never got there or none teleported).
    pub fn teleport_complete(&self) -> Option<f64> {
        if self.bots.iter().all(|b| b.teleported_at.is_none()) {
            return None;
        }
        self.bots
            .iter()
            .filter(|b| b.teleported_at.is_some())
            .map(|b| b.teleport_complete)
            .try_fold(0.0f64, |m, t| t.map(|t| m.max(t)))
    }
}

/// Everything a run measured.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// Per scenario.
    pub scenarios: Vec<ScenarioResult>,
    /// The seed 001 §7 size table.
    pub sizes: Vec<sizes::SizeRow>,
    /// Baseline 1's unique meshes over an even sample of the world's instances.
    pub mesh_sample: Option<MeshSample>,
    /// Baseline 2's species meshes: compressed bytes by species id (in-process runs).
    pub species_meshes: Vec<u64>,
    /// Files written.
    pub files: Vec<PathBuf>,
    /// Wall time of the whole run.
    pub wall: f64,
}

/// Unique-mesh sizes over an even sample of the world's instances (ids `(2i + 1) · N / 2k`; ids run cell by cell,
/// so the sample is spread over the world and follows its species mix).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshSample {
    /// Instances encoded.
    pub count: usize,
    /// Their compressed mesh bytes in total.
    pub bytes: u64,
    /// Per species: name, instances, compressed bytes.
    pub by_species: Vec<(String, usize, u64)>,
    /// Seconds it took.
    pub seconds: f64,
}

impl MeshSample {
    /// Take the sample through `source` (meshes encoded by a baseline scenario are reused from its cache).
    pub fn take(world: &World, source: &MeshSource, k: usize) -> MeshSample {
        let t = Instant::now();
        let n = world.instances.len();
        let k = k.min(n);
        let mut by: Vec<(String, usize, u64)> = world.species.iter().map(|s| (s.name.clone(), 0, 0)).collect();
        let mut bytes = 0u64;
        for i in 0..k {
            let index = ((2 * i + 1) * n / (2 * k)) as u32;
            let b = source.instance_mesh(world.instance_id(index)).len() as u64;
            let s = &mut by[usize::from(world.instances[index as usize].species)];
            s.1 += 1;
            s.2 += b;
            bytes += b;
        }
        by.retain(|s| s.1 > 0);
        MeshSample { count: k, bytes, by_species: by, seconds: t.elapsed().as_secs_f64() }
    }

    /// Mean compressed mesh bytes per instance.
    pub fn mean(&self) -> Option<f64> {
        (self.count > 0).then(|| self.bytes as f64 / self.count as f64)
    }
}

/// Live counters for the progress display.
#[derive(Debug, Default)]
struct Live {
    bytes: AtomicU64,
    records: AtomicU64,
}

struct BotParams {
    duration: Duration,
    speed: f32,
    radius: f32,
    view: f32,
    teleport: bool,
    seed: u64,
    settle: Duration,
    sample: Duration,
    truth: Arc<GroundTruth>,
    live: Arc<Live>,
    /// When the scenario started (sample times count from here).
    t0: Instant,
}

async fn run_bot(
    id: usize,
    endpoint: Endpoint,
    connect: ConnectConfig,
    relay: Option<Relay>,
    p: Arc<BotParams>,
) -> BotResult {
    let mut r = BotResult { bot: BotReport { id, ..BotReport::default() }, ..BotResult::default() };
    if let Err(e) = bot_session(&mut r, &endpoint, connect, &p).await {
        r.bot.error = Some(e.to_string());
    }
    if let Some(relay) = relay {
        let s = relay.stats();
        let dir = |d: &link::DirectionStats| {
            [d.packets.load(Relaxed), d.lost.load(Relaxed), d.overflow.load(Relaxed), d.delivered.load(Relaxed)]
        };
        r.link = Some(LinkTotals { down: dir(&s.down), up: dir(&s.up), down_bytes: s.down.bytes.load(Relaxed) });
    }
    r
}

fn bytes_of(conn: &Connection) -> Bytes {
    Bytes::split(conn.frame_bytes_received(), conn.frame_bytes_sent(), conn.bytes_received(), conn.bytes_sent())
}

/// A measuring bot's hooks into the drive loop: what arrived by kind, its phase, the teleport, samples.
struct Measure<'a> {
    r: &'a mut BotResult,
    p: &'a BotParams,
    completion: Completion,
    phase: SamplePhase,
    teleport_at: Option<Instant>,
    teleported: Option<Instant>,
    last_bytes: u64,
    last_records: u64,
}

impl Measure<'_> {
    fn take(&mut self, conn: &Connection, phase: SamplePhase, pos: [f32; 2]) {
        let truth = &*self.p.truth;
        let (visible, held) =
            measure::completeness(truth, pos, self.p.view, |c| measure::held_indices(conn.state(), c));
        self.r.samples.push(Sample {
            t: self.p.t0.elapsed().as_secs_f64(),
            phase,
            position: pos,
            bytes: bytes_of(conn),
            visible,
            held,
            aoi_complete: conn.state().is_complete(),
        });
        let b = conn.bytes_received() + conn.bytes_sent();
        let rec = conn.state().stats().records;
        self.p.live.bytes.fetch_add(b.saturating_sub(self.last_bytes), Relaxed);
        self.p.live.records.fetch_add(rec.saturating_sub(self.last_records), Relaxed);
        self.last_bytes = b;
        self.last_records = rec;
    }
}

impl DriveHooks for Measure<'_> {
    fn event(&mut self, ev: &Event) {
        let species_ids = &mut self.r.species_ids;
        if let Event::Species { id, .. } = ev
            && !species_ids.contains(id)
        {
            species_ids.push(*id);
        }
        if let Event::Geometry { kind: GeometryKind::SpeciesMesh, id, offset: 0, .. } = ev {
            let id = u8::try_from(*id).unwrap_or(u8::MAX);
            if !species_ids.contains(&id) {
                species_ids.push(id);
            }
        }
        if let Event::Geometry { kind: GeometryKind::InstanceMesh, offset: 0, total, .. } = ev {
            self.r.mesh_headers.0 += 1;
            self.r.mesh_headers.1 += u64::from(*total);
        }
    }

    fn changed(&mut self, conn: &Connection) {
        self.completion.note(conn, &mut self.r.bot);
        if !conn.state().is_complete() {
            return;
        }
        match self.phase {
            SamplePhase::Start => self.phase = SamplePhase::Walking,
            SamplePhase::Teleported => {
                self.r.teleport_complete = self.teleported.map(|t| t.elapsed().as_secs_f64());
                self.phase = SamplePhase::Walking;
            }
            _ => {}
        }
    }

    fn stepped(&mut self, now: Instant, walker: &mut Walker) -> bool {
        let due = self.teleported.is_none() && self.teleport_at.is_some_and(|t| now >= t);
        if !due {
            return false;
        }
        // Jump to another walk: a new start and heading, same speed.
        walker.jump();
        self.teleported = Some(now);
        self.r.teleported_at = Some(self.p.t0.elapsed().as_secs_f64());
        self.phase = SamplePhase::Teleported;
        true
    }

    fn sample(&mut self, conn: &Connection, walker: &Walker, settling: bool) {
        let phase = if settling { SamplePhase::Settling } else { self.phase };
        self.take(conn, phase, walker.position());
    }
}

async fn bot_session(
    r: &mut BotResult,
    endpoint: &Endpoint,
    mut connect: ConnectConfig,
    p: &BotParams,
) -> Result<(), BandwidthError> {
    connect.client_name = format!("bandwidth-{}", r.bot.id);
    let started = Instant::now();
    let seed = p.seed.wrapping_add(r.bot.id as u64);
    let walk = bots::Walk { path: PathKind::Line, speed: p.speed, radius: p.radius, altitude: 0.0, seed };
    let (mut conn, mut walker) = bots::connect_walking(endpoint, &connect, None, walk).await?;
    if conn.welcome().world.instances as usize != p.truth.len() {
        let server = conn.welcome().world.instances;
        conn.close();
        return Err(BandwidthError::WorldMismatch { server, truth: p.truth.len() });
    }
    let plan = DrivePlan {
        radius: p.radius,
        tick: Duration::from_millis(100),
        walk_until: started + p.duration,
        settle: p.settle,
        sample: Some(p.sample),
        stop: tokio::sync::watch::channel(false).1,
        far: None,
    };
    let mut m = Measure {
        r: &mut *r,
        p,
        completion: Completion::new(started),
        phase: SamplePhase::Start,
        teleport_at: p.teleport.then(|| started + p.duration / 2),
        teleported: None,
        last_bytes: 0,
        last_records: 0,
    };
    let result = bots::drive(&mut conn, &mut walker, plan, &mut m).await;
    if result.is_ok() {
        // The last sample, at rest, whether or not the area of interest filled.
        m.take(&conn, SamplePhase::Settling, walker.position());
    }
    r.geometry = conn.state().stats().geometry_bytes;
    r.bot.read(&conn);
    r.bot.complete = conn.state().is_complete();
    r.bytes = bytes_of(&conn);
    conn.close();
    result.map(|_| ()).map_err(BandwidthError::from)
}

/// Run one scenario against a server at `server`: a relay per bot when the link is shaped, the bots, their
/// results.
async fn run_scenario(
    cfg: &BandwidthConfig,
    scenario: &Scenario,
    server: SocketAddr,
    trust: Trust,
    truth: Arc<GroundTruth>,
    bar: &indicatif::ProgressBar,
) -> Result<Vec<BotResult>, BandwidthError> {
    let endpoint = canopy_client::net::endpoint(canopy_client::net::loopback_for(server))?;
    let params = Arc::new(BotParams {
        duration: cfg.duration,
        speed: cfg.speed,
        radius: cfg.radius,
        view: cfg.view,
        teleport: cfg.teleport,
        seed: cfg.seed,
        settle: cfg.settle,
        sample: cfg.sample,
        truth,
        live: Arc::new(Live::default()),
        t0: Instant::now(),
    });
    let live = Arc::clone(&params.live);
    let t0 = params.t0;
    // One TLS configuration for all the bots: each one's clone only changes the address (its relay's).
    let base = ConnectConfig::new(server, trust);
    let mut tasks = Vec::new();
    for id in 0..cfg.bots {
        let (relay, addr) = if scenario.link.is_shaped() {
            let relay =
                Relay::start(server, scenario.link, cfg.seed.wrapping_mul(1000).wrapping_add(id as u64)).await?;
            let addr = relay.addr();
            (Some(relay), addr)
        } else {
            (None, server)
        };
        let mut connect = base.clone();
        connect.server = addr;
        tasks.push(tokio::spawn(run_bot(id, endpoint.clone(), connect, relay, Arc::clone(&params))));
    }
    let total = (cfg.duration + cfg.settle).as_secs_f64();
    let mut ticker = tokio::time::interval(Duration::from_millis(200));
    let results;
    let all = bots::join(tasks, |id, error| BotResult {
        bot: BotReport { id, error: Some(error), ..Default::default() },
        ..Default::default()
    });
    tokio::pin!(all);
    loop {
        tokio::select! {
            r = &mut all => { results = r; break; }
            _ = ticker.tick() => {
                let t = t0.elapsed().as_secs_f64();
                bar.set_position(((t / total).min(1.0) * 1000.0) as u64);
                bar.set_message(format!(
                    "{}: {:.1} MB, {} records",
                    scenario.name,
                    live.bytes.load(Relaxed) as f64 / 1e6,
                    live.records.load(Relaxed)
                ));
            }
        }
    }
    endpoint.close(0u32.into(), b"done");
    let _ = tokio::time::timeout(Duration::from_secs(2), endpoint.wait_idle()).await;
    Ok(results)
}

/// Run every scenario of `cfg` on `world` (the in-process server's world and the ground truth; with an external
/// server it must be the world that server serves), write the report, and return what was measured.
pub fn run(cfg: &BandwidthConfig, world: Arc<World>) -> Result<Outcome, BandwidthError> {
    if cfg.bots == 0 || cfg.scenarios.is_empty() {
        return Err(BandwidthError::Config("nothing to run: no bots or no scenarios".into()));
    }
    if cfg.external.is_some() && cfg.scenarios.iter().any(|s| s.mode != PayloadMode::Procedural) {
        return Err(BandwidthError::Config(
            "an external server serves its own payload: only procedural scenarios can run against it".into(),
        ));
    }
    let started = Instant::now();
    let truth = Arc::new(GroundTruth::new(Arc::clone(&world)));
    // The server and the bots run on separate runtimes, so that a server encoding meshes (baseline 1) does not
    // delay the bots' clocks, samples and acknowledgements.
    let server_rt =
        tokio::runtime::Builder::new_multi_thread().worker_threads(2).thread_name("bw-server").enable_all().build()?;
    let bots_rt =
        tokio::runtime::Builder::new_multi_thread().worker_threads(2).thread_name("bw-bots").enable_all().build()?;
    let store: Option<Arc<dyn WorldStore>> = match &cfg.external {
        Some(_) => None,
        None => Some(GridStore::from_world(&world).map_err(|e| BandwidthError::Store(e.to_string()))?.shared()),
    };
    let source = Arc::new(MeshSource::new(Arc::clone(&world), cfg.cache_bytes));
    let bar = if cfg.progress {
        let b = indicatif::ProgressBar::new(1000);
        b.set_style(
            indicatif::ProgressStyle::with_template("{prefix:>24} [{bar:30}] {elapsed:>4} {msg}")
                .map_err(|e| BandwidthError::Config(e.to_string()))?
                .progress_chars("=> "),
        );
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let mut results = Vec::new();
    for (i, scenario) in cfg.scenarios.iter().enumerate() {
        bar.set_prefix(format!("{}/{} {}", i + 1, cfg.scenarios.len(), scenario.name));
        bar.set_position(0);
        let t = Instant::now();
        let before = source.stats();
        let (server, addr, trust) = match (&cfg.external, &store) {
            (Some(e), _) => (None, e.server, e.trust.clone()),
            (None, Some(store)) => {
                let mut session = SessionConfig::default();
                if let (Some(rate), true) = (scenario.link.rate, cfg.pace > 0.0) {
                    session.bandwidth = Some(((rate as f64 / 8.0) * cfg.pace).max(1.0) as u64);
                }
                session.payload = Payload::new(scenario.mode, Arc::clone(&source) as Arc<dyn GeometrySource>);
                let server_cfg =
                    ServerConfig { listen: SocketAddr::from(([127, 0, 0, 1], 0)), session, ..ServerConfig::default() };
                let server = server_rt.block_on(Server::start(Arc::clone(store), server_cfg))?;
                let trust = Trust::pinned(server.fingerprint())
                    .ok_or_else(|| BandwidthError::Config("the server's fingerprint is not pinnable".into()))?;
                let addr = server.local_addr();
                (Some(server), addr, trust)
            }
            (None, None) => unreachable!("an in-process run has a store"),
        };
        let bots = bots_rt.block_on(run_scenario(cfg, scenario, addr, trust, Arc::clone(&truth), &bar));
        let server_bytes = server.as_ref().map(|s| {
            let m = s.metrics();
            m.bytes.map(|b| b.load(Relaxed))
        });
        if let Some(s) = server {
            server_rt.block_on(s.shutdown(Duration::from_secs(1)));
        }
        let bots = bots?;
        let after = source.stats();
        let source_stats = (scenario.mode != PayloadMode::Procedural && cfg.external.is_none()).then(|| SourceStats {
            instance_meshes: after.instance_meshes - before.instance_meshes,
            instance_bytes: after.instance_bytes - before.instance_bytes,
            instance_vertices: after.instance_vertices - before.instance_vertices,
            hits: after.hits - before.hits,
            encode_seconds: after.encode_seconds - before.encode_seconds,
        });
        let result = ScenarioResult {
            scenario: scenario.clone(),
            bots,
            wall: t.elapsed().as_secs_f64(),
            source: source_stats,
            server_bytes,
        };
        if !bar.is_hidden() {
            bar.println(report::scenario_line(&result));
        } else {
            println!("{}", report::scenario_line(&result));
        }
        results.push(result);
    }
    bar.finish_and_clear();
    let sizes = if cfg.size_seeds > 0 { sizes::table(&world, cfg.size_seeds) } else { Vec::new() };
    let mesh_sample = (cfg.mesh_sample > 0).then(|| MeshSample::take(&world, &source, cfg.mesh_sample));
    let species_meshes = match cfg.external {
        Some(_) => Vec::new(),
        None => (0..world.species.len().min(256)).map(|i| source.species_mesh(i as u8).len() as u64).collect(),
    };
    let mut outcome = Outcome { scenarios: results, sizes, mesh_sample, species_meshes, files: Vec::new(), wall: 0.0 };
    outcome.wall = started.elapsed().as_secs_f64();
    outcome.files = report::write(cfg, &outcome)?;
    Ok(outcome)
}
