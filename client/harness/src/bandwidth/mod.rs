//! The bandwidth measurement harness (`canopy bandwidth`): procedural streaming against explicit geometry, through
//! the same server, area of interest, pacing, paths and links (seed 001 §4 and §7).
//!
//! A run is a list of [`Scenario`]s — a payload mode ([`PayloadMode`]: procedural, unique meshes, instanced) and a
//! link ([`link::LinkSpec`]: rate cap, latency, loss, emulated by a UDP relay per client) — each run by the same
//! bots on the same scripted paths: a straight walk at a given speed with a teleport half-way, or a flight
//! ([`PathKind::Flight`]: legs and turns at an altitude, the record radius [`AoiParams::flight_radius`] gives,
//! a far view of summary nodes beyond it) over a world never materialised, such as the highlands, which the
//! in-process server then serves through its [`CellCache`]. Every bot samples, at a fixed interval, its bytes by
//! class (the transport overhead being what the UDP totals hold beyond the frames, so the classes add up to the
//! wire), and what it holds within view distance; its visible completeness — of the instances within view
//! distance in the world itself ([`measure::GroundTruth`]), the fraction it held — is computed from those
//! snapshots once the scenario's bots are done. The [`report`] writes a markdown report, CSV files and SVG plots.
//!
//! [`AoiParams::flight_radius`]: canopy_protocol::aoi::AoiParams::flight_radius

mod bot;
pub mod geometry;
pub mod link;
pub mod measure;
pub mod report;
pub mod sizes;
mod tables;
pub mod truth;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use canopy_protocol::messages::ByKind;
use canopy_protocol::summary::FarView;
use canopy_server::session::{GeometrySource, GridStore, Payload, PayloadMode, SessionConfig, WorldStore};
use canopy_server::{CellCacheConfig, ServeError, ServeOptions, Served, ServerConfig, serve, serve_store};
use canopy_worlds::world::World;

use crate::bots::{BotReport, PathKind};
use canopy_client::net::{ClientError, Trust};
use geometry::{MeshSource, SourceStats};
use link::LinkSpec;
use measure::{Bytes, CompletenessStats, GroundTruth, Sample, SamplePhase};
use truth::TruthStats;

/// One measured configuration: what the server sends and over which link.
#[derive(Clone, Debug, PartialEq)]
pub struct Scenario {
    /// A short name (file names, tables).
    pub name: String,
    /// What goes out per instance and species.
    pub mode: PayloadMode,
    /// The link every bot is behind.
    pub link: LinkSpec,
    /// The bots expand cells themselves (procedural only): the server sends grants, not records.
    pub expand: bool,
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
        Scenario { name: format!("{}-{rate}{loss}", mode.label()), mode, link, expand: false }
    }

    /// Procedural over `link`, the bots expanding cells themselves from the world function (`expanded-1M`).
    pub fn expanded(link: LinkSpec) -> Scenario {
        let s = Scenario::new(PayloadMode::Procedural, link);
        Scenario { name: s.name.replacen("procedural", "expanded", 1), expand: true, ..s }
    }

    /// What the bots take: the payload mode's label, or `expanded`.
    pub fn label(&self) -> &'static str {
        if self.expand { "expanded" } else { self.mode.label() }
    }

    /// The same scenario, its name prefixed (`flight-procedural-1M`).
    pub fn prefixed(mut self, prefix: &str) -> Scenario {
        self.name = format!("{prefix}-{}", self.name);
        self
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
    /// How long each bot walks (or flies).
    pub duration: Duration,
    /// The bots' path: [`PathKind::Line`] (a straight walk, bouncing off the world's edge) or
    /// [`PathKind::Flight`] (legs and turns at `altitude`, procedural payload only).
    pub path: PathKind,
    /// Walking (or flying) speed, metres per second.
    pub speed: f32,
    /// A flight's height above the terrain, metres.
    pub altitude: f32,
    /// Area-of-interest radius walkers ask for, metres (a flight asks for [`AoiParams::flight_radius`] of its
    /// altitude and speed under the server's rules instead).
    ///
    /// [`AoiParams::flight_radius`]: canopy_protocol::aoi::AoiParams::flight_radius
    pub radius: f32,
    /// View distance for visible completeness, metres (`None`: the radius the bots ask for).
    pub view: Option<f32>,
    /// The far view the bots ask for (summary nodes beyond the records; `None`: none). The altitude is replaced by
    /// the walker's.
    pub far: Option<FarView>,
    /// Fit each bot's radius to its scenario's link rate while it moves ([`crate::bots::LinkFit`]: what the link
    /// carries at the bot's speed, the far view drawing beyond); with `view` unset, visible completeness is then
    /// judged within the radius asked at each sample.
    pub fit: bool,
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
    /// Cells the ground truth of a world never materialised keeps expanded ([`truth::DEFAULT_MEMO_CELLS`]).
    pub truth_cells: usize,
    /// Show a progress bar.
    pub progress: bool,
    /// The command line, for the report.
    pub command: String,
}

impl BandwidthConfig {
    /// The default walkthrough: 2 bots, 30 s at 10 m/s with a teleport, AOI and view 160 m; the three payload
    /// modes and the bots expanding cells themselves over 1 Mbit/s with 20 ms latency, and procedural over 56
    /// kbit/s (100 ms) and 10 Mbit/s with 1 % loss.
    pub fn default_run() -> BandwidthConfig {
        let one = LinkSpec::new(Some(1_000_000), 20, 0.0);
        BandwidthConfig {
            bots: 2,
            duration: Duration::from_secs(30),
            path: PathKind::Line,
            speed: 10.0,
            altitude: 0.0,
            radius: 160.0,
            view: Some(160.0),
            far: None,
            fit: false,
            teleport: true,
            seed: 1,
            settle: Duration::from_secs(10),
            sample: Duration::from_millis(250),
            scenarios: vec![
                Scenario::new(PayloadMode::Procedural, one),
                Scenario::expanded(one),
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
            truth_cells: truth::DEFAULT_MEMO_CELLS,
            progress: true,
            command: "canopy bandwidth".into(),
        }
    }

    /// The default flight (issues 15 and 18): 2 bots flying 30 s at 250 m/s, 1,500 m above the terrain, without a
    /// teleport, asking for the radius their altitude and speed give (capped by the server) and for the far view
    /// (16 px on a 1080-pixel 60° view, 20 km), the view distance that radius; records and expanded cells over 1
    /// Mbit/s and over 10 Mbit/s (20 ms). Meant for a world never materialised (`highlands`); no size table, no mesh sample. Seed
    /// 6: over the highlands, bots 0 and 1 fly over forest nearly all the way (seeds 1 and 2 cross bare rock above
    /// the tree line, where there are no records to measure).
    pub fn flight_run() -> BandwidthConfig {
        let link = |rate| LinkSpec::new(Some(rate), 20, 0.0);
        BandwidthConfig {
            path: PathKind::Flight,
            speed: 250.0,
            altitude: 1500.0,
            view: None,
            far: Some(FarView {
                error_px: 16.0,
                height_px: 1080,
                fov_y: 60f32.to_radians(),
                range: 20_000.0,
                altitude: 1500.0,
            }),
            fit: true,
            teleport: false,
            seed: 6,
            scenarios: [1_000_000, 10_000_000]
                .into_iter()
                .flat_map(|rate| [Scenario::new(PayloadMode::Procedural, link(rate)), Scenario::expanded(link(rate))])
                .map(|s| s.prefixed("flight"))
                .collect(),
            size_seeds: 0,
            mesh_sample: 0,
            command: "canopy bandwidth --path flight".into(),
            ..BandwidthConfig::default_run()
        }
    }

    /// Whether the bots fly.
    pub fn flying(&self) -> bool {
        self.path == PathKind::Flight
    }
}

/// Why a run failed.
#[derive(Debug, thiserror::Error)]
pub enum BandwidthError {
    /// The server did not start.
    #[error("starting the server: {0}")]
    Server(#[from] ServeError),
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
    #[error("the server streams {server}, the ground truth is {truth}: not the same world")]
    WorldMismatch {
        /// The server's world as its welcome describes it: name, instances, grid.
        server: String,
        /// The ground truth's world, likewise.
        truth: String,
    },
    /// An explicit-geometry payload asked of a run that can only be procedural: its meshes come from the instances
    /// of a world materialised at load.
    #[error(
        "{mode} needs the meshes of a world materialised at load, and {why}: run it with --modes procedural \
         (the explicit baselines run on the default walkthrough)"
    )]
    ProceduralOnly {
        /// The payload mode refused.
        mode: &'static str,
        /// Why the run is procedural only.
        why: String,
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
    /// What any bot reports: index, why it stopped early (if it did), records received and held, summary nodes
    /// received, time to its first complete area of interest, whether it ended complete.
    pub bot: BotReport,
    /// The area-of-interest radius it asked for, metres (a flight's from its altitude and speed; fitted to the link,
    /// the most it asked for). Each sample carries the view distance it is judged within ([`Sample::view`]).
    pub radius: f32,
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

    /// Instance records the bots obtained: received, or expanded themselves from grants.
    pub fn records(&self) -> u64 {
        self.bots.iter().map(|b| b.bot.records + b.bot.expanded).sum()
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
    /// The world's name.
    pub world: String,
    /// Per scenario.
    pub scenarios: Vec<ScenarioResult>,
    /// The seed 001 §7 size table.
    pub sizes: Vec<sizes::SizeRow>,
    /// Baseline 1's unique meshes over an even sample of the world's instances.
    pub mesh_sample: Option<MeshSample>,
    /// Baseline 2's species meshes: compressed bytes by species id (in-process runs).
    pub species_meshes: Vec<u64>,
    /// What the ground truth expanded of a world never materialised (zeros for a materialised one).
    pub truth: TruthStats,
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

/// Refuse what cannot run: no bots or scenarios, a path other than a line or a flight, an unusable far view, and
/// explicit geometry against an external server, in a flight, or on a world never materialised.
fn check(cfg: &BandwidthConfig, world: &World) -> Result<(), BandwidthError> {
    if cfg.bots == 0 || cfg.scenarios.is_empty() {
        return Err(BandwidthError::Config("nothing to run: no bots or no scenarios".into()));
    }
    if !matches!(cfg.path, PathKind::Line | PathKind::Flight) {
        return Err(BandwidthError::Config(format!("the bots walk lines or fly, not `{}`", cfg.path)));
    }
    if let Some(far) = &cfg.far {
        far.validate().map_err(|e| BandwidthError::Config(format!("the far view: {e}")))?;
    }
    let Some(explicit) = cfg.scenarios.iter().find(|s| s.mode != PayloadMode::Procedural) else { return Ok(()) };
    if cfg.external.is_some() {
        return Err(BandwidthError::Config(
            "an external server serves its own payload: only procedural scenarios can run against it".into(),
        ));
    }
    let why = if cfg.flying() {
        format!("a flight is procedural only (over `{}`)", world.name)
    } else if !world.is_materialised() {
        format!("`{}` is never materialised (its cells are expanded on demand)", world.name)
    } else {
        return Ok(());
    };
    Err(BandwidthError::ProceduralOnly { mode: explicit.mode.label(), why })
}

/// Where the in-process server's cells come from.
enum Cells {
    /// Every cell up front, shared by the scenarios (a world materialised at load).
    Grid(Arc<dyn WorldStore>),
    /// Cells expanded on demand, as `canopy-server` serves any world: a cold cache per scenario.
    Cache(Arc<World>),
}

impl Cells {
    /// A server for one scenario, as `canopy-server` would serve these cells.
    async fn serve(&self, session: SessionConfig) -> Result<Served, ServeError> {
        let batch_records = session.batch_records;
        let server = ServerConfig { listen: SocketAddr::from(([127, 0, 0, 1], 0)), session, ..ServerConfig::default() };
        let opts = ServeOptions { server, ..ServeOptions::default() };
        match self {
            Cells::Grid(store) => serve_store(Arc::clone(store), opts).await,
            Cells::Cache(world) => {
                let cells =
                    canopy_server::Cells::OnDemand(CellCacheConfig { batch_records, ..CellCacheConfig::default() });
                serve((**world).clone(), ServeOptions { cells, ..opts }).await
            }
        }
    }
}

/// Run every scenario of `cfg` on `world` (the in-process server's world and the ground truth; with an external
/// server it must be the world that server serves), write the report, and return what was measured.
///
/// A world materialised at load is served from a [`GridStore`] shared by the scenarios; any other through a
/// [`canopy_server::CellCache`], cold in each scenario (a flight's cells are expanded as it asks for them, as by
/// `canopy-server`). Visible completeness is computed after each scenario's bots are done and its server is shut
/// down, from what each bot held at each sample, so that expanding the ground truth's cells neither delays the
/// bots nor takes CPU from the server.
pub fn run(cfg: &BandwidthConfig, world: Arc<World>) -> Result<Outcome, BandwidthError> {
    check(cfg, &world)?;
    let started = Instant::now();
    let truth = Arc::new(if world.is_materialised() {
        GroundTruth::new(Arc::clone(&world))
    } else {
        GroundTruth::from_function(Arc::clone(&world), cfg.truth_cells)
    });
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    // The server and the bots run on separate runtimes, so that a server encoding meshes (baseline 1) does not
    // delay the bots' clocks, samples and acknowledgements.
    let server_rt =
        tokio::runtime::Builder::new_multi_thread().worker_threads(2).thread_name("bw-server").enable_all().build()?;
    let bots_rt =
        tokio::runtime::Builder::new_multi_thread().worker_threads(2).thread_name("bw-bots").enable_all().build()?;
    let cells = match (&cfg.external, world.is_materialised()) {
        (Some(_), _) => None,
        (None, true) => {
            Some(Cells::Grid(GridStore::from_world(&world).map_err(|e| BandwidthError::Store(e.to_string()))?.shared()))
        }
        (None, false) => Some(Cells::Cache(Arc::clone(&world))),
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
        let (server, addr, trust) = match (&cfg.external, &cells) {
            (Some(e), _) => (None, e.server, e.trust.clone()),
            (None, Some(cells)) => {
                let mut session = SessionConfig::default();
                if let (Some(rate), true) = (scenario.link.rate, cfg.pace > 0.0) {
                    session.bandwidth = Some(((rate as f64 / 8.0) * cfg.pace).max(1.0) as u64);
                }
                session.payload = Payload::new(scenario.mode, Arc::clone(&source) as Arc<dyn GeometrySource>);
                let server = server_rt.block_on(cells.serve(session))?;
                let trust = Trust::pinned(server.fingerprint())
                    .ok_or_else(|| BandwidthError::Config("the server's fingerprint is not pinnable".into()))?;
                let addr = server.local_addr();
                (Some(server), addr, trust)
            }
            (None, None) => unreachable!("an in-process run has a store"),
        };
        let bots = bots_rt.block_on(bot::run_scenario(cfg, scenario, addr, trust, Arc::clone(&truth), &bar));
        let server_bytes = server.as_ref().map(|s| {
            let m = s.metrics();
            m.bytes.map(|b| b.load(Relaxed))
        });
        if let Some(s) = server {
            server_rt.block_on(s.shutdown(Duration::from_secs(1)));
        }
        let wall = t.elapsed().as_secs_f64();
        bar.set_message(format!("{}: visible completeness against the world", scenario.name));
        let bots: Vec<BotResult> = bots?
            .into_iter()
            .map(|(mut bot, held)| {
                truth::evaluate(&truth, &mut bot.samples, &held, threads);
                bot
            })
            .collect();
        let after = source.stats();
        let source_stats = (scenario.mode != PayloadMode::Procedural && cfg.external.is_none()).then(|| SourceStats {
            instance_meshes: after.instance_meshes - before.instance_meshes,
            instance_bytes: after.instance_bytes - before.instance_bytes,
            instance_vertices: after.instance_vertices - before.instance_vertices,
            hits: after.hits - before.hits,
            encode_seconds: after.encode_seconds - before.encode_seconds,
        });
        let result = ScenarioResult { scenario: scenario.clone(), bots, wall, source: source_stats, server_bytes };
        if !bar.is_hidden() {
            bar.println(report::scenario_line(&result));
        } else {
            println!("{}", report::scenario_line(&result));
        }
        results.push(result);
    }
    bar.finish_and_clear();
    let sizes = if cfg.size_seeds > 0 { sizes::table(&world, cfg.size_seeds) } else { Vec::new() };
    let mesh_sample =
        (cfg.mesh_sample > 0 && world.is_materialised()).then(|| MeshSample::take(&world, &source, cfg.mesh_sample));
    // Baseline 2's species meshes, for the comparison (which needs an explicit scenario beside procedural).
    let explicit = cfg.scenarios.iter().any(|s| s.mode != PayloadMode::Procedural);
    let species_meshes = match cfg.external {
        Some(_) => Vec::new(),
        None if !explicit => Vec::new(),
        None => (0..world.species.len().min(256)).map(|i| source.species_mesh(i as u8).len() as u64).collect(),
    };
    let mut outcome = Outcome {
        world: world.name.clone(),
        scenarios: results,
        sizes,
        mesh_sample,
        species_meshes,
        truth: truth.stats(),
        files: Vec::new(),
        wall: 0.0,
    };
    outcome.wall = started.elapsed().as_secs_f64();
    outcome.files = report::write(cfg, &outcome)?;
    Ok(outcome)
}
