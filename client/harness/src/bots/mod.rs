//! Headless walkthrough clients: bots that connect, walk scripted paths (line, circle, random walk, teleports) or
//! fly (straight legs and turns at an altitude: [`walker`]) at a given speed, keep their area of interest streamed,
//! and at the end stop, wait for a complete area of interest and check what they hold against the world itself
//! ([`verify`]: against the world's cells as a function, so on worlds never materialised too).
//!
//! A flight asks for the radius [`AoiParams::flight_radius`] gives for its altitude and speed under the server's
//! rules (the welcome's), instead of `radius`.
//!
//! Each bot measures its "area of interest change → complete" latencies: from the first viewpoint that left its
//! area of interest incomplete to the moment every cell of the (then current) area of interest is held in full. The
//! first area of interest, filled from nothing, is "connect → first complete" instead, not a change.
//!
//! With an [`EditPlan`] the first bots also edit the world while they walk ([`edits`]: plants near them, fells of
//! their own plants), and every bot measures how soon the others' edits reach it; the check against the world then
//! compares edited cells only as far as the world's function still decides them, and compares them between bots.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

use canopy_protocol::CellCoord;
use canopy_protocol::aoi::{AoiParams, Viewpoint};
use canopy_protocol::edit::EditOp;
use canopy_protocol::messages::{ByKind, ServerMsgKind};
use canopy_protocol::summary::FarView;
use canopy_protocol::sync::Locked;
use canopy_worlds::world::World;
use quinn::Endpoint;

use canopy_client::cache::{CacheLimits, SpeciesCache};
use canopy_client::net::{ClientError, ConnectConfig, Connection};
use canopy_client::state::{Event, viewpoint_due};

pub mod edits;
pub mod ledger;
mod summary;
mod verify;
pub mod walker;

pub use canopy_client::fit::LinkFit;
pub use edits::{Acknowledged, EditPlan, EditStats, EditsSummary, FanOut, FanOutReport};
pub use ledger::{EditLedger, check_ledger};
pub use summary::{BotsSummary, Shard};
pub use verify::{VerifySummary, expected_cells, verify, verify_with};
pub(crate) use walker::Rng;
pub use walker::{PathKind, Walker, grid_rect};

/// How a group of bots runs.
#[derive(Clone, Debug)]
pub struct BotsConfig {
    /// How many bots.
    pub count: usize,
    /// The first bot's id: this group runs bots `first_id..first_id + count` of a larger run (`canopy bots
    /// --processes`: a group a process). The id is the bot's everywhere: its path's seed, its name, whether it is
    /// one of the first bots that expand ([`BotsConfig::expanding`]) or edit ([`EditPlan::editors`]), so the groups
    /// together run exactly the bots one group of them all would.
    pub first_id: usize,
    /// Their path.
    pub path: PathKind,
    /// Walking speed, metres per second.
    pub speed: f32,
    /// How long they walk.
    pub duration: Duration,
    /// The area-of-interest radius they ask for, metres (a flight asks for [`AoiParams::flight_radius`] instead).
    pub radius: f32,
    /// How high a flight flies above the terrain, metres (walkers walk on the ground).
    pub altitude: f32,
    /// Where to connect and how to trust the server.
    pub connect: ConnectConfig,
    /// Seeds the paths (bot `id` uses `seed + id`).
    pub seed: u64,
    /// New connections per second while ramping up.
    pub connect_rate: f64,
    /// A species cache directory shared by the bots (`None`: no cache; each bot starts with no species, like a
    /// fresh client).
    pub cache_dir: Option<PathBuf>,
    /// How long a bot waits at the end for a complete area of interest.
    pub settle: Duration,
    /// Client UDP sockets the bots are spread over.
    pub endpoints: usize,
    /// How often a bot moves and, if it moved enough, sends a viewpoint.
    pub tick: Duration,
    /// The world to check the bots' final state against (`None`: no check).
    pub verify: Option<Arc<World>>,
    /// Where bots expand cells (`connect.expander`): only the first this many do; the others take grants and
    /// expand nothing (`ConnectConfig::grants_only`: the server sees the same traffic, the bots' machine none of
    /// the work) and are not checked against the world. `None`: every bot.
    pub expanding: Option<usize>,
    /// Set to `true` to stop walking early (the bots then settle and check as at the end of `duration`).
    pub stop: tokio::sync::watch::Receiver<bool>,
    /// Keep every walk inside a square of this side, metres, around the middle of the world (`None`: the whole
    /// world): many bots holding the same cells.
    pub spread: Option<f32>,
    /// How the first bots edit the world while they walk (`None`: no edits).
    pub edits: Option<EditPlan>,
    /// The far view the bots ask for (summary nodes beyond the records; `None`: none). A flight's altitude
    /// replaces the one given here.
    pub far: Option<FarView>,
    /// Fit the radius to a link while moving ([`LinkFit`]; `None`: the radius of the walk).
    pub fit: Option<LinkFit>,
}

impl BotsConfig {
    /// A default group of `count` bots walking lines to `server`.
    pub fn new(count: usize, connect: ConnectConfig) -> BotsConfig {
        BotsConfig {
            count,
            first_id: 0,
            path: PathKind::Line,
            speed: 5.0,
            duration: Duration::from_secs(20),
            radius: 160.0,
            altitude: 1500.0,
            connect,
            seed: 1,
            connect_rate: 200.0,
            cache_dir: None,
            settle: Duration::from_secs(60),
            endpoints: 1,
            tick: Duration::from_millis(100),
            verify: None,
            expanding: None,
            stop: tokio::sync::watch::channel(false).1,
            spread: None,
            edits: None,
            far: None,
            fit: None,
        }
    }
}

/// Live counters of a bots run (read by progress displays).
#[derive(Debug, Default)]
pub struct Progress {
    /// Bots connected now.
    pub connected: AtomicU64,
    /// Bots whose area of interest is complete now.
    pub complete: AtomicU64,
    /// Bots that failed.
    pub failed: AtomicU64,
    /// Bots finished (checked and closed).
    pub finished: AtomicU64,
    /// Instance records received by all bots.
    pub records: AtomicU64,
    /// Edits acknowledged (applied and durable).
    pub edits: AtomicU64,
    /// Sessions resumed on another edge after an edge was lost.
    pub reconnects: AtomicU64,
}

/// What one bot did.
#[derive(Clone, Debug, Default)]
pub struct BotReport {
    /// Bot index.
    pub id: usize,
    /// Why it failed, if it did.
    pub error: Option<String>,
    /// Time from starting to connect to the first complete area of interest.
    pub first_complete: Option<Duration>,
    /// Connect → the last far-view summary node this bot received or computed: for a bot at rest, the time to
    /// its full horizon.
    pub far_settled: Option<Duration>,
    /// Area-of-interest change → complete latencies while walking and at the end (the first fill is
    /// `first_complete`).
    pub latencies: Vec<Duration>,
    /// Whether it ended with a complete area of interest.
    pub complete: bool,
    /// Records received.
    pub records: u64,
    /// Records the bot expanded itself (cells granted to expand).
    pub expanded: u64,
    /// Records held at the end.
    pub held: usize,
    /// All frame bytes received by class (welcome, species, cells, release, geometry).
    pub frame_bytes: ByKind<u64>,
    /// UDP payload bytes received.
    pub udp_bytes: u64,
    /// Species received over the wire.
    pub species_received: u32,
    /// Far-view summary nodes received.
    pub summaries: u64,
    /// Species received twice.
    pub species_duplicates: u32,
    /// Viewpoints sent.
    pub viewpoints: u32,
    /// The check against the world (`None`: not checked).
    pub verify: Option<Result<VerifySummary, String>>,
    /// The area of interest sampled while walking (every [`SAMPLE_EVERY`]), from its first complete area of
    /// interest on (the samples before are only counted).
    pub moving: AoiSamples,
    /// What its edits came to (`None`: it did not edit).
    pub edits: Option<EditStats>,
    /// Cells held at the end that edits changed (version > 0): cell, version, [`edits::cell_digest`].
    pub edited_cells: Vec<(CellCoord, u32, u64)>,
    /// Times it lost its edge and resumed on another ([`Connection::fail_over`]).
    pub reconnects: u32,
    /// How long each fail-over took, from the error that ended the session to the resumed session's welcome.
    pub failovers: Vec<Duration>,
}

/// How often a bot samples its area of interest while walking, on average (the gaps vary: see [`drive`]).
pub const SAMPLE_EVERY: Duration = Duration::from_millis(250);

/// Samples of a moving bot's area of interest: how much of it was held in full.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AoiSamples {
    /// Samples taken.
    pub samples: u64,
    /// Sum over the samples of the fraction of the area of interest's cells held in full.
    pub held_sum: f64,
    /// Samples with the whole area of interest held in full.
    pub complete: u64,
    /// Samples with the cell under the walker held in full.
    pub below: u64,
    /// Samples not taken: the bot was filling its first area of interest.
    pub filling: u64,
}

impl AoiSamples {
    /// Sample a connection's state with the walker at `position`.
    pub fn take(&mut self, conn: &Connection, position: [f32; 2]) {
        let state = conn.state();
        let full = |c: &canopy_protocol::CellCoord| state.cells().get(c).is_some_and(|h| h.is_complete());
        let inner = state.inner_cells();
        let held = inner.iter().filter(|c| full(c)).count();
        self.samples += 1;
        self.held_sum += if inner.is_empty() { 1.0 } else { held as f64 / inner.len() as f64 };
        self.complete += u64::from(held == inner.len());
        self.below += u64::from(full(&conn.welcome().world.grid.cell_of(position[0], position[1])));
    }

    /// Add another bot's samples.
    pub fn add(&mut self, o: &AoiSamples) {
        self.samples += o.samples;
        self.held_sum += o.held_sum;
        self.complete += o.complete;
        self.below += o.below;
        self.filling += o.filling;
    }
}

/// Run one bot to the end (see the module docs).
pub async fn run_bot(
    id: usize,
    endpoint: Endpoint,
    cfg: Arc<BotsConfig>,
    cache: Option<Arc<SpeciesCache>>,
    progress: Arc<Progress>,
) -> BotReport {
    let mut report = BotReport { id, ..BotReport::default() };
    let started = Instant::now();
    match bot_session(&mut report, &endpoint, &cfg, cache, &progress, started).await {
        Ok(()) => {}
        Err(e) => {
            progress.failed.fetch_add(1, Relaxed);
            report.error = Some(e.to_string());
        }
    }
    progress.finished.fetch_add(1, Relaxed);
    report
}

impl BotReport {
    /// Add a session's counters (records received, bytes, species, viewpoints sent) to the bot's, and take the
    /// records it holds: once at the end, and before each fail-over for the session that ended.
    pub fn read(&mut self, conn: &Connection) {
        let state = conn.state();
        let stats = state.stats();
        self.records += stats.records;
        self.expanded += stats.records_expanded;
        self.species_received += stats.species_received;
        self.summaries += stats.summaries;
        self.species_duplicates += stats.species_duplicates;
        self.held = state.record_count();
        for k in ServerMsgKind::ALL {
            self.frame_bytes[k] += conn.frame_bytes_received()[k];
        }
        self.udp_bytes += conn.bytes_received();
        // The ready's viewpoint has `seq` 0, and each one sent after it the next number.
        self.viewpoints += state.viewpoint().map_or(0, |v| v.seq + 1);
    }
}

/// What one bot walks (or flies).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Walk {
    /// The path.
    pub path: PathKind,
    /// Metres per second.
    pub speed: f32,
    /// The area-of-interest radius a walker asks for, metres.
    pub radius: f32,
    /// A flight's height above the terrain, metres.
    pub altitude: f32,
    /// Seeds the path.
    pub seed: u64,
    /// Fit the radius of the first viewpoint to a link ([`LinkFit::first_radius`]; [`DrivePlan::fit`] fits the
    /// later ones).
    pub fit: Option<LinkFit>,
}

impl Walk {
    /// The radius asked for under the server's rules `aoi`: `radius` walking, [`AoiParams::flight_radius`] flying.
    pub fn radius(&self, aoi: &AoiParams) -> f32 {
        match self.path {
            PathKind::Flight => aoi.flight_radius(self.altitude, self.speed),
            _ => self.radius,
        }
    }
}

/// Connect as a walker: the walk is placed inside the welcome's grid (inset by half the radius it asks for,
/// [`Walk::radius`]), and its first viewpoint goes with the ready.
pub async fn connect_walking(
    endpoint: &Endpoint,
    connect: &ConnectConfig,
    cache: Option<Arc<SpeciesCache>>,
    walk: Walk,
) -> Result<(Connection, Walker), ClientError> {
    connect_walking_within(endpoint, connect, cache, walk, None).await
}

/// [`connect_walking`], the walk kept inside a square of side `spread` metres around the middle of that rectangle
/// when `spread` is given.
pub async fn connect_walking_within(
    endpoint: &Endpoint,
    connect: &ConnectConfig,
    cache: Option<Arc<SpeciesCache>>,
    walk: Walk,
    spread: Option<f32>,
) -> Result<(Connection, Walker), ClientError> {
    // The first edge that answers places the walk (`connect_any` may try several).
    let walker = std::sync::Mutex::new(None);
    let place = |w: &canopy_protocol::messages::Welcome| {
        let radius = walk.radius(&w.aoi);
        let (mut lo, mut hi) = grid_rect(&w.world.grid, radius * 0.5);
        let radius = walk.fit.map_or(radius, |f| f.first_radius(w, walk.speed, radius));
        if let Some(side) = spread {
            for a in 0..2 {
                let (mid, half) = ((lo[a] + hi[a]) * 0.5, (side * 0.5).min((hi[a] - lo[a]) * 0.5));
                (lo[a], hi[a]) = (mid - half, mid + half);
            }
        }
        let wk = Walker::new(walk.path, walk.speed, lo, hi, walk.seed).with_altitude(walk.altitude);
        let vp = wk.viewpoint(radius);
        *walker.locked() = Some(wk);
        vp
    };
    let conn = Connection::connect_any(endpoint, connect, cache, place).await?;
    let walker = walker.into_inner().unwrap_or_else(|e| e.into_inner()).expect("placed in the handshake");
    Ok((conn, walker))
}

/// How [`drive`] walks a connection.
#[derive(Clone, Debug)]
pub struct DrivePlan {
    /// The area-of-interest radius asked for, metres.
    pub radius: f32,
    /// How often the walker moves and, if a viewpoint is due, sends one.
    pub tick: Duration,
    /// When to stop walking.
    pub walk_until: Instant,
    /// How long to wait at rest for a complete area of interest.
    pub settle: Duration,
    /// How often to call [`DriveHooks::sample`] on average (`None`: never); the gaps vary (see [`drive`]).
    pub sample: Option<Duration>,
    /// Set to `true` to stop walking early.
    pub stop: tokio::sync::watch::Receiver<bool>,
    /// The far view to ask for (its altitude the walker's), sent once streaming and again when it changes enough.
    pub far: Option<FarView>,
    /// Fit the radius to a link while moving (`radius` is then the most it asks for; at rest it asks for `radius`).
    pub fit: Option<LinkFit>,
}

/// What moves a driven connection's viewpoint: a scripted [`Walker`], or a window's camera (`canopy walk`).
pub trait Mover {
    /// Advance `dt` seconds; true when it jumped (a viewpoint goes out at once).
    fn step(&mut self, dt: f32) -> bool;
    /// Where it is on the ground plane (x, z).
    fn position(&self) -> [f32; 2];
    /// Its heading, radians.
    fn yaw(&self) -> f32;
    /// Its velocity on the ground plane, metres a second.
    fn velocity(&self) -> [f32; 2];
    /// Its height above the ground, metres (the far view's altitude).
    fn altitude(&self) -> f32;
    /// The viewpoint of a client here, asking for `radius` metres (`seq` is set when it is sent).
    fn viewpoint(&self, radius: f32) -> Viewpoint {
        Viewpoint { seq: 0, position: self.position(), yaw: self.yaw(), velocity: self.velocity(), radius }
    }
}

/// What a caller of [`drive`] sees along the way, moved by `W` (every method does nothing by default).
pub trait DriveHooks<W: ?Sized = Walker> {
    /// Every event applied, in order.
    fn event(&mut self, _ev: &Event) {}
    /// Every event applied, in order, with the connection's state just after it (by default
    /// [`DriveHooks::event`]).
    fn applied(&mut self, _conn: &Connection, ev: &Event) {
        self.event(ev);
    }
    /// After the state changed: events applied, or a viewpoint sent.
    fn changed(&mut self, _conn: &Connection) {}
    /// After the walker stepped at `now`; may move it (a jump). Returns whether to send a viewpoint now.
    fn stepped(&mut self, _now: Instant, _walker: &mut W) -> bool {
        false
    }
    /// At every sampling tick, while walking and while `settling` at rest.
    fn sample(&mut self, _conn: &Connection, _walker: &W, _settling: bool) {}
    /// How often to ask [`DriveHooks::edit`] for an edit while walking (`None`: never). Asked once, at the start.
    fn edit_every(&self) -> Option<Duration> {
        None
    }
    /// The edit to send now, if any.
    fn edit(&mut self, _now: Instant, _conn: &Connection, _walker: &W) -> Option<EditOp> {
        None
    }
    /// `op` was sent as request `request`; `at` is just before it was written.
    fn edit_sent(&mut self, _request: u32, _op: &EditOp, _at: Instant) {}
}

/// The moments [`drive`] samples at: gaps drawn uniformly from ½ to 1½ times `every`, so that the samples fall at
/// every phase of the walk's tick. Samples on a fixed clock lock to the tick: at 250 ms against a 100-ms tick, every
/// other sample was due with a tick, and half of those came just after the tick sent a viewpoint, before the server
/// could have answered it.
struct Sampler {
    every: Duration,
    next: tokio::time::Instant,
    rng: Rng,
}

impl Sampler {
    fn new(every: Duration, seed: u64) -> Sampler {
        let mut s = Sampler { every, next: tokio::time::Instant::now(), rng: Rng(seed) };
        let gap = s.gap();
        s.next += gap;
        s
    }

    fn gap(&mut self) -> Duration {
        self.every.mul_f64(0.5 + self.rng.unit_f64())
    }
}

async fn next_sample(sampler: &mut Option<Sampler>) {
    match sampler {
        Some(s) => {
            tokio::time::sleep_until(s.next).await;
            s.next = tokio::time::Instant::now() + s.gap();
        }
        None => std::future::pending().await,
    }
}

async fn next_tick(interval: &mut Option<tokio::time::Interval>) {
    match interval {
        Some(i) => drop(i.tick().await),
        None => std::future::pending().await,
    }
}

/// Walk a connection: apply what arrives, step the walker every tick and send a viewpoint when one is due (it
/// teleported or jumped, moved or turned enough: [`viewpoint_due`]), until `walk_until` or a stop. Then stop: a
/// viewpoint at rest, and wait up to `settle` for the area of interest to fill. Returns whether it did.
///
/// The one streaming loop: bots, the bandwidth harness and the walkthrough window (its camera a [`Mover`]) run it.
pub async fn drive<W: Mover, H: DriveHooks<W>>(
    conn: &mut Connection,
    walker: &mut W,
    plan: DrivePlan,
    hooks: &mut H,
) -> Result<bool, ClientError> {
    let grid = conn.welcome().world.grid;
    let mut tick = tokio::time::interval(plan.tick);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Seeded by where the walk starts, so bots started together sample at different moments.
    let [x, z] = walker.position();
    let mut sample =
        plan.sample.map(|every| Sampler::new(every, u64::from(x.to_bits()) << 32 | u64::from(z.to_bits())));
    // Edits are paced by their own clock, catching up after a late tick (the rate is what is asked for).
    let mut edit_tick = hooks.edit_every().map(|d| tokio::time::interval(d.max(Duration::from_micros(100))));
    let mut last = Instant::now();
    let mut sent_at = last;
    let mut stop = plan.stop;
    // Without a sender (nobody can stop the walk early) `changed` would return at once: listen only while one lives.
    let mut stoppable = stop.has_changed().is_ok();
    let far_view = |walker: &W| plan.far.map(|f| FarView { altitude: walker.altitude().max(2.0), ..f });
    // Fitted, the first viewpoint's radius ([`LinkFit::first_radius`]) is where the fit starts from.
    let mut radius = match plan.fit {
        Some(_) => conn.state().viewpoint().map_or(plan.radius, |v| v.radius),
        None => plan.radius,
    };
    if let Some(f) = far_view(walker) {
        conn.set_far_view(f).await?;
    }
    while Instant::now() < plan.walk_until && !*stop.borrow() {
        tokio::select! {
            r = stop.changed(), if stoppable => stoppable = r.is_ok(),
            ev = conn.next_event() => {
                hooks.applied(conn, &ev?);
                while let Some(ev) = conn.try_next_event() {
                    hooks.applied(conn, &ev?);
                }
                hooks.changed(conn);
            }
            _ = next_tick(&mut edit_tick) => {
                if let Some(op) = hooks.edit(Instant::now(), conn, walker) {
                    let at = Instant::now();
                    let request = conn.edit(op.clone()).await?;
                    hooks.edit_sent(request, &op, at);
                }
            }
            _ = tick.tick() => {
                let now = Instant::now();
                let dt = now.duration_since(last).as_secs_f32();
                last = now;
                let jumped = walker.step(dt) | hooks.stepped(now, walker);
                // A fitted radius changes the area of interest only when it moves by more than a tenth.
                let mut refit = false;
                if let Some(fit) = plan.fit {
                    let r = fit.next(conn, radius, walker.velocity(), plan.radius);
                    refit = r != radius;
                    radius = r;
                }
                // The far view follows the altitude (sent only when it changed enough: `far_view_due`).
                if let Some(f) = far_view(walker) {
                    conn.set_far_view(f).await?;
                }
                let sent = conn.state().viewpoint().expect("a streaming session has a viewpoint");
                if jumped || refit || viewpoint_due(&grid, sent, walker.position(), walker.yaw(), now - sent_at) {
                    conn.set_viewpoint(walker.viewpoint(radius)).await?;
                    sent_at = now;
                    hooks.changed(conn);
                }
            }
            _ = next_sample(&mut sample) => hooks.sample(conn, walker, false),
        }
    }
    // Stop: a viewpoint at rest, then wait for the area of interest to fill.
    let mut rest = walker.viewpoint(plan.radius);
    rest.velocity = [0.0, 0.0];
    conn.set_viewpoint(rest).await?;
    hooks.changed(conn);
    let deadline = tokio::time::Instant::now() + plan.settle;
    while !conn.state().is_complete() {
        tokio::select! {
            ev = conn.next_event() => {
                hooks.applied(conn, &ev?);
                hooks.changed(conn);
            }
            _ = next_sample(&mut sample) => hooks.sample(conn, walker, true),
            _ = tokio::time::sleep_until(deadline) => return Ok(false),
        }
    }
    Ok(true)
}

/// A bot's "area of interest change → complete" latencies: from the first change that left the area of interest
/// incomplete to the moment it is complete again. The first fill, from the start of the walk, is the report's
/// `first_complete` (from the start of connecting), not one of them.
#[derive(Clone, Copy, Debug)]
pub struct Completion {
    started: Instant,
    pending: Option<Instant>,
    complete: bool,
}

impl Completion {
    /// Start measuring now; `started` is when the bot started to connect.
    pub fn new(started: Instant) -> Completion {
        Completion { started, pending: Some(Instant::now()), complete: false }
    }

    /// Time since the bot started to connect.
    pub fn since_start(&self) -> Duration {
        self.started.elapsed()
    }

    /// Note the connection's state into `report` (latencies, first complete). Returns whether the area of
    /// interest became complete (`Some(true)`) or incomplete (`Some(false)`).
    pub fn note(&mut self, conn: &Connection, report: &mut BotReport) -> Option<bool> {
        let now_complete = conn.state().is_complete();
        let changed = (now_complete != self.complete).then_some(now_complete);
        self.complete = now_complete;
        match (now_complete, self.pending) {
            (true, Some(t0)) => {
                match report.first_complete {
                    Some(_) => report.latencies.push(t0.elapsed()),
                    None => report.first_complete = Some(self.started.elapsed()),
                }
                self.pending = None;
            }
            (false, None) => self.pending = Some(Instant::now()),
            _ => {}
        }
        changed
    }
}

struct BotHooks<'a> {
    report: &'a mut BotReport,
    progress: &'a Progress,
    completion: Completion,
    /// With edits on: the shared record, and the versions of the cells held.
    fanout: Option<(Arc<FanOut>, edits::HeldVersions)>,
    /// An editing bot's edits, made from `edit_window.0` until `edit_window.1`.
    editing: Option<edits::Editing>,
    edit_window: (Instant, Instant),
    edit_every: Option<Duration>,
}

impl DriveHooks for BotHooks<'_> {
    fn applied(&mut self, conn: &Connection, ev: &Event) {
        let now = Instant::now();
        match ev {
            Event::Records { count, .. } => drop(self.progress.records.fetch_add(*count as u64, Relaxed)),
            Event::Summaries { added, .. } if *added > 0 => {
                self.report.far_settled = Some(self.completion.since_start())
            }
            Event::EditResult(r) => {
                if let Some(e) = &mut self.editing {
                    let ok = e.stats.outcomes[0];
                    e.answered(r, now);
                    self.progress.edits.fetch_add(e.stats.outcomes[0] - ok, Relaxed);
                }
            }
            _ => {}
        }
        if let Some((fanout, versions)) = &mut self.fanout
            && let Some(covered) = versions.apply(ev, |c| conn.state().cells().get(&c).map(|h| h.version))
            && let Event::Changed { cell, .. } = ev
        {
            fanout.seen(self.report.id, *cell, covered, now);
        }
    }

    fn changed(&mut self, conn: &Connection) {
        match self.completion.note(conn, self.report) {
            Some(true) => drop(self.progress.complete.fetch_add(1, Relaxed)),
            Some(false) => drop(self.progress.complete.fetch_sub(1, Relaxed)),
            None => {}
        }
    }

    fn sample(&mut self, conn: &Connection, walker: &Walker, settling: bool) {
        match (settling, self.report.first_complete) {
            (true, _) => {}
            // Filling the first area of interest: what `first_complete` measures, not the walk.
            (false, None) => self.report.moving.filling += 1,
            (false, Some(_)) => self.report.moving.take(conn, walker.position()),
        }
    }

    fn edit_every(&self) -> Option<Duration> {
        self.edit_every
    }

    fn edit(&mut self, now: Instant, conn: &Connection, walker: &Walker) -> Option<EditOp> {
        let e = self.editing.as_mut()?;
        let (from, until) = self.edit_window;
        (from..until).contains(&now).then(|| e.next_op(walker.position(), &conn.welcome().world.grid))
    }

    fn edit_sent(&mut self, request: u32, op: &EditOp, at: Instant) {
        if let Some(e) = &mut self.editing {
            e.sent(request, op, at);
        }
    }
}

async fn bot_session(
    report: &mut BotReport,
    endpoint: &Endpoint,
    cfg: &BotsConfig,
    cache: Option<Arc<SpeciesCache>>,
    progress: &Progress,
    started: Instant,
) -> Result<(), ClientError> {
    let mut connect = cfg.connect.clone();
    connect.client_name = format!("bot-{}", report.id);
    let thin = connect.expander.is_some() && cfg.expanding.is_some_and(|n| report.id >= n);
    if thin {
        connect.expander = None;
        connect.grants_only = true;
    }
    spread_over_edges(&mut connect, report.id);
    let editor = cfg.edits.as_ref().filter(|e| report.id < e.editors && e.rate > 0.0);
    // Editors connect with the token; the other bots watch, read-only.
    connect.token = editor.map(|e| e.token.clone());
    let seed = cfg.seed.wrapping_add(report.id as u64);
    let walk =
        Walk { path: cfg.path, speed: cfg.speed, radius: cfg.radius, altitude: cfg.altitude, seed, fit: cfg.fit };
    let (mut conn, mut walker) = connect_walking_within(endpoint, &connect, cache, walk, cfg.spread).await?;
    progress.connected.fetch_add(1, Relaxed);
    let plan = DrivePlan {
        radius: walk.radius(&conn.welcome().aoi),
        tick: cfg.tick,
        walk_until: Instant::now() + cfg.duration,
        settle: cfg.settle,
        sample: Some(SAMPLE_EVERY),
        stop: cfg.stop.clone(),
        far: cfg.far,
        fit: cfg.fit,
    };
    // Edits start once the last bot of the ramp has had `warmup` to connect and fill its area of interest, and stop
    // `grace` before the walk ends.
    let ramp_left = (cfg.count - (report.id - cfg.first_id) - 1) as f64 / cfg.connect_rate.max(0.001);
    let edit_window = match editor {
        Some(e) => (started + Duration::from_secs_f64(ramp_left) + e.warmup, plan.walk_until - e.grace),
        None => (started, started),
    };
    let species = conn.welcome().species.len().min(usize::from(u8::MAX)) as u8;
    let id = report.id;
    let mut hooks = BotHooks {
        report: &mut *report,
        progress,
        completion: Completion::new(started),
        fanout: cfg.edits.as_ref().map(|e| (Arc::clone(&e.fanout), edits::HeldVersions::default())),
        editing: editor.map(|e| edits::Editing::new(id, seed, species, plan.radius * 0.5, Arc::clone(&e.fanout))),
        edit_window,
        edit_every: editor.map(|e| Duration::from_secs_f64(1.0 / e.rate)),
    };
    let driven = loop {
        match drive(&mut conn, &mut walker, plan.clone(), &mut hooks).await {
            // The edge is gone: resume on another with what this session held, where the walker is now.
            Err(e) if e.edge_lost() && connect.edges.len() > 1 => {
                hooks.report.read(&conn);
                let lost_at = Instant::now();
                match conn.fail_over(endpoint, &connect, walker.viewpoint(plan.radius)).await {
                    Ok(c) => conn = c,
                    Err(e) => {
                        // No edge took the session: what was measured so far stays in the report.
                        report.edits = hooks.editing.take().map(edits::Editing::finish);
                        progress.connected.fetch_sub(1, Relaxed);
                        return Err(e);
                    }
                }
                hooks.report.reconnects += 1;
                hooks.report.failovers.push(lost_at.elapsed());
                progress.reconnects.fetch_add(1, Relaxed);
            }
            r => break r,
        }
    };
    report.edits = hooks.editing.take().map(edits::Editing::finish);
    let result = match driven {
        Ok(true) => {
            report.complete = true;
            Ok(())
        }
        Ok(false) => Err(ClientError::Timeout("waiting for a complete area of interest at the end")),
        Err(e) => Err(e),
    };
    progress.connected.fetch_sub(1, Relaxed);
    report.read(&conn);
    let state = conn.close_into_state();
    if cfg.edits.is_some() {
        report.edited_cells = state
            .cells()
            .iter()
            .filter(|(_, h)| h.version > 0 && h.is_complete())
            .map(|(c, h)| (*c, h.version, edits::cell_digest(h)))
            .collect();
    }
    let thin = cfg.connect.expander.is_some() && cfg.expanding.is_some_and(|n| report.id >= n);
    if result.is_ok()
        && !thin
        && let Some(world) = &cfg.verify
    {
        // Checking thousands of records is CPU work: keep it off the runtime's workers, which carry the other
        // bots' connections.
        static CHECKS: tokio::sync::Semaphore = tokio::sync::Semaphore::const_new(2);
        let world = Arc::clone(world);
        let _permit = CHECKS.acquire().await.expect("the semaphore is never closed");
        // A cell the server holds at a version past 0 was edited, by these bots or anyone else: it is checked as far as
        // the world's function still decides it (a bot cannot know what others planted).
        let checked = tokio::task::spawn_blocking(move || verify_with(&state, &world, true)).await;
        report.verify = Some(checked.unwrap_or_else(|e| Err(format!("check task: {e}"))));
    }
    result
}

/// Spread bots over the edges: bot `id` starts at edge `id mod n`, and every other round of bots lists the other
/// edges backwards, so the bots of a lost edge fail over to both its neighbours.
fn spread_over_edges(connect: &mut ConnectConfig, id: usize) {
    let n = connect.edges.len();
    if n > 1 {
        connect.edges.rotate_left(id % n);
        if (id / n) % 2 == 1 {
            connect.edges[1..].reverse();
        }
        connect.server = connect.edges[0];
    }
}

/// Wait for every bot's task, in order; a task that panicked or was cancelled becomes `failed(index, why)`.
pub async fn join<T>(tasks: Vec<tokio::task::JoinHandle<T>>, failed: impl Fn(usize, String) -> T) -> Vec<T> {
    let mut out = Vec::with_capacity(tasks.len());
    for (id, t) in tasks.into_iter().enumerate() {
        out.push(t.await.unwrap_or_else(|e| failed(id, format!("bot task: {e}"))));
    }
    out
}

/// Run a group of bots to the end: ramp up at `connect_rate`, walk, settle, check. Returns every bot's report, in
/// the order of their ids (`first_id` on).
pub async fn run(cfg: BotsConfig, progress: Arc<Progress>) -> Result<Vec<BotReport>, ClientError> {
    let bind = canopy_client::net::loopback_for(cfg.connect.server);
    let endpoints: Vec<Endpoint> =
        (0..cfg.endpoints.max(1)).map(|_| canopy_client::net::endpoint(bind)).collect::<Result<_, _>>()?;
    let cache = match &cfg.cache_dir {
        Some(dir) => Some(Arc::new(SpeciesCache::open(dir, CacheLimits::default())?)),
        None => None,
    };
    let cfg = Arc::new(cfg);
    let mut tasks = Vec::with_capacity(cfg.count);
    let start = tokio::time::Instant::now();
    for i in 0..cfg.count {
        let (id, at) = (cfg.first_id + i, start + Duration::from_secs_f64(i as f64 / cfg.connect_rate.max(0.001)));
        let (endpoint, cfg, cache, progress) =
            (endpoints[i % endpoints.len()].clone(), Arc::clone(&cfg), cache.clone(), Arc::clone(&progress));
        tasks.push(tokio::spawn(async move {
            tokio::time::sleep_until(at).await;
            run_bot(id, endpoint, cfg, cache, progress).await
        }));
    }
    let first = cfg.first_id;
    let reports = join(tasks, |i, error| BotReport { id: first + i, error: Some(error), ..Default::default() }).await;
    for e in &endpoints {
        e.wait_idle().await;
    }
    Ok(reports)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The gaps between samples stay within ½ to 1½ times the mean, and the samples fall at every phase of a
    /// 100-ms tick (on a fixed 250-ms clock they would fall at two phases only).
    #[test]
    fn samples_fall_at_every_phase_of_the_tick() {
        let mut s = Sampler::new(SAMPLE_EVERY, 7);
        let (mut at, mut bins) = (Duration::ZERO, [0u32; 10]);
        for _ in 0..2000 {
            let gap = s.gap();
            assert!(gap >= SAMPLE_EVERY / 2 && gap < SAMPLE_EVERY * 3 / 2, "{gap:?}");
            at += gap;
            bins[(at.as_micros() % 100_000 / 10_000) as usize] += 1;
        }
        assert!(bins.iter().all(|&n| n >= 150), "each tenth of the tick holds about a tenth of the samples: {bins:?}");
    }
}
