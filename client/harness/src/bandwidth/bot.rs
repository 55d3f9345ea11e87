//! A measuring bot of the bandwidth harness and one scenario's run of them: each bot connects (through its own
//! emulated link when the scenario shapes one), walks or flies the scripted path through [`bots::drive`], and at
//! every sample records its bytes by class and a [`HeldSnapshot`] of what it held within view distance; visible
//! completeness is computed from the snapshots once the bots are done ([`super::truth::evaluate`]).

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

use canopy_client::net::{ConnectConfig, Connection, Trust};
use canopy_client::state::Event;
use canopy_protocol::aoi::Grid;
use canopy_protocol::messages::GeometryKind;
use canopy_protocol::summary::FarView;
use quinn::Endpoint;

use super::link::{self, Relay};
use super::measure::{Bytes, GroundTruth, HeldSnapshot, Sample, SamplePhase};
use super::{BandwidthConfig, BandwidthError, BotResult, LinkTotals, Scenario};
use crate::bots::{self, BotReport, Completion, DriveHooks, DrivePlan, LinkFit, Mover, PathKind, Walker};

/// Live counters for the progress display.
#[derive(Debug, Default)]
struct Live {
    bytes: AtomicU64,
    records: AtomicU64,
}

/// What every bot of a scenario shares.
struct BotParams {
    duration: Duration,
    path: PathKind,
    speed: f32,
    altitude: f32,
    radius: f32,
    view: Option<f32>,
    far: Option<FarView>,
    fit: Option<LinkFit>,
    teleport: bool,
    seed: u64,
    settle: Duration,
    sample: Duration,
    truth: Arc<GroundTruth>,
    live: Arc<Live>,
    /// When the scenario started (sample times count from here).
    t0: Instant,
}

/// A bot's result and what it held at each of its samples (`held[i]` at `result.samples[i]`).
pub(super) type BotOutput = (BotResult, Vec<HeldSnapshot>);

async fn run_bot(
    id: usize,
    endpoint: Endpoint,
    connect: ConnectConfig,
    relay: Option<Relay>,
    p: Arc<BotParams>,
) -> BotOutput {
    let mut r = BotResult { bot: BotReport { id, ..BotReport::default() }, ..BotResult::default() };
    let mut held = Vec::new();
    if let Err(e) = bot_session(&mut r, &mut held, &endpoint, connect, &p).await {
        r.bot.error = Some(e.to_string());
    }
    if let Some(relay) = relay {
        let s = relay.stats();
        let dir = |d: &link::DirectionStats| {
            [d.packets.load(Relaxed), d.lost.load(Relaxed), d.overflow.load(Relaxed), d.delivered.load(Relaxed)]
        };
        r.link = Some(LinkTotals { down: dir(&s.down), up: dir(&s.up), down_bytes: s.down.bytes.load(Relaxed) });
    }
    (r, held)
}

fn bytes_of(conn: &Connection) -> Bytes {
    Bytes::split(conn.frame_bytes_received(), conn.frame_bytes_sent(), conn.bytes_received(), conn.bytes_sent())
}

/// A measuring bot's hooks into the drive loop: what arrived by kind, its phase, the teleport, samples.
struct Measure<'a> {
    r: &'a mut BotResult,
    held: &'a mut Vec<HeldSnapshot>,
    p: &'a BotParams,
    completion: Completion,
    phase: SamplePhase,
    teleport_at: Option<Instant>,
    teleported: Option<Instant>,
    last_bytes: u64,
    last_records: u64,
}

impl Measure<'_> {
    /// A sample: bytes now, and what is held within view distance (compared with the ground truth later, so
    /// that a sample never waits for the world's cells to be expanded).
    fn take(&mut self, conn: &Connection, phase: SamplePhase, pos: [f32; 2]) {
        let asked = conn.state().viewpoint().map_or(self.r.radius, |v| v.radius);
        let view = self.p.view.unwrap_or(asked);
        self.held.push(HeldSnapshot::take(&self.p.truth, conn.state(), pos, view));
        self.r.samples.push(Sample {
            t: self.p.t0.elapsed().as_secs_f64(),
            phase,
            position: pos,
            view,
            bytes: bytes_of(conn),
            visible: 0,
            held: 0,
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
    held: &mut Vec<HeldSnapshot>,
    endpoint: &Endpoint,
    mut connect: ConnectConfig,
    p: &BotParams,
) -> Result<(), BandwidthError> {
    connect.client_name = format!("bandwidth-{}", r.bot.id);
    let started = Instant::now();
    let seed = p.seed.wrapping_add(r.bot.id as u64);
    let walk = bots::Walk { path: p.path, speed: p.speed, radius: p.radius, altitude: p.altitude, seed, fit: p.fit };
    let (mut conn, mut walker) = bots::connect_walking(endpoint, &connect, None, walk).await?;
    let w = &conn.welcome().world;
    let describe = |name: &str, instances: usize, g: &Grid| {
        format!("`{name}` ({instances} instances, cells {:?} ..= {:?} of {} m)", g.min, g.max, g.cell_size)
    };
    let (server, truth) = (
        describe(&w.name, w.instances as usize, &w.grid),
        describe(&p.truth.world().name, p.truth.len(), p.truth.grid()),
    );
    if server != truth {
        conn.close();
        return Err(BandwidthError::WorldMismatch { server, truth });
    }
    // A walker asks for its radius, a flight for the one its altitude and speed give under the server's rules.
    r.radius = walk.radius(&conn.welcome().aoi);
    let plan = DrivePlan {
        radius: r.radius,
        tick: Duration::from_millis(100),
        walk_until: started + p.duration,
        settle: p.settle,
        sample: Some(p.sample),
        stop: tokio::sync::watch::channel(false).1,
        far: p.far,
        fit: p.fit,
    };
    let mut m = Measure {
        r: &mut *r,
        held,
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
/// results (samples not yet evaluated) and snapshots.
pub(super) async fn run_scenario(
    cfg: &BandwidthConfig,
    scenario: &Scenario,
    server: SocketAddr,
    trust: Trust,
    truth: Arc<GroundTruth>,
    bar: &indicatif::ProgressBar,
) -> Result<Vec<BotOutput>, BandwidthError> {
    let endpoint = canopy_client::net::endpoint(canopy_client::net::loopback_for(server))?;
    let params = Arc::new(BotParams {
        duration: cfg.duration,
        path: cfg.path,
        speed: cfg.speed,
        altitude: cfg.altitude,
        radius: cfg.radius,
        view: cfg.view,
        far: cfg.far,
        fit: scenario.link.rate.filter(|_| cfg.fit).map(|rate| LinkFit { link_bits: rate as f64 }),
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
    let mut base = ConnectConfig::new(server, trust);
    if scenario.expand {
        // The bots of the scenario share one expander, as the bots of a process do.
        base.expander = Some(canopy_client::expand::Expander::default_pool());
    }
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
    let all = bots::join(tasks, |id, error| {
        let bot = BotReport { id, error: Some(error), ..Default::default() };
        (BotResult { bot, ..Default::default() }, Vec::new())
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
