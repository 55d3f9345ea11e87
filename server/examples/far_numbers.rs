//! Numbers for the far view (issue 15): the bytes of the whole far field of a view from altitude, the time to the
//! full horizon over a paced link, cold (the cell cache's workers computing every node) and warm (a second client
//! at the same place), and a flight's far-field completeness over time. The real session core and cell cache run
//! in process; the link is the session's own pacing (a token bucket at the link's rate) with a transport that
//! takes every byte at once, so the times are the pacing's and the computing's, not a network's.
//!
//! ```text
//! cargo run --release -p canopy-server --example far_numbers -- [--world highlands] [--altitude 1500]
//!     [--range 20000] [--error 16] [--rate 10000000] [--speed 250] [--flight 30] [--at X,Z]
//! ```

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_protocol::aoi::{AoiParams, Viewpoint};
use canopy_protocol::messages::ClientStreaming;
use canopy_protocol::messages::ServerMsgKind;
use canopy_protocol::summary::{FarView, NodeKey, Refine};
use canopy_protocol::{ClientMsg, ServerMsg};
use canopy_server::session::{Session, SessionConfig};
use canopy_server::session::{SummaryState, WorldStore};
use canopy_server::{CellCache, CellCacheConfig};
use canopy_worlds::world::World;

struct Args {
    world: String,
    altitude: f32,
    range: f32,
    error: f32,
    rate: u64,
    speed: f32,
    flight: f64,
    at: [f32; 2],
}

fn args() -> Result<Args, String> {
    let mut a = Args {
        world: "highlands".into(),
        altitude: 1500.0,
        range: 20_000.0,
        error: 16.0,
        rate: 10_000_000,
        speed: 250.0,
        flight: 30.0,
        at: [2000.0, -30_000.0],
    };
    let mut it = std::env::args().skip(1);
    while let Some(k) = it.next() {
        let v = it.next().ok_or(format!("{k} needs a value"))?;
        let num = |v: &str| v.parse::<f64>().map_err(|e| format!("{k} {v}: {e}"));
        match k.as_str() {
            "--world" => a.world = v,
            "--altitude" => a.altitude = num(&v)? as f32,
            "--range" => a.range = num(&v)? as f32,
            "--error" => a.error = num(&v)? as f32,
            "--rate" => a.rate = num(&v)? as u64,
            "--speed" => a.speed = num(&v)? as f32,
            "--flight" => a.flight = num(&v)?,
            "--at" => {
                let xz: Vec<f64> = v.split(',').map(num).collect::<Result<_, _>>()?;
                a.at = [*xz.first().ok_or("--at X,Z")? as f32, *xz.get(1).ok_or("--at X,Z")? as f32];
            }
            _ => return Err(format!("unknown option {k}")),
        }
    }
    Ok(a)
}

fn view(a: &Args) -> FarView {
    FarView { error_px: a.error, height_px: 1080, fov_y: 60f32.to_radians(), range: a.range, altitude: a.altitude }
}

/// What the rule wants at `at`, and how much of it `held` covers: (wanted, held of them), with nodes not yet
/// computed counted as wanted and missing (their subtrees unknown).
fn completeness(
    cache: &CellCache,
    view: FarView,
    at: [f32; 2],
    record_radius: f32,
    held: &BTreeSet<NodeKey>,
) -> (usize, usize) {
    let grid = *cache.grid();
    let r = Refine {
        view,
        eye: at,
        origin: grid.origin,
        cell_size: grid.cell_size,
        root_level: cache.summary_root_level(),
        record_radius,
    };
    let reached = r.reach(|k| match cache.summary(k, None) {
        SummaryState::Ready(n) => Some(n.node.error),
        _ => None,
    });
    let known = reached.iter().filter(|(k, _)| !matches!(cache.summary(*k, None), SummaryState::Unavailable));
    let (mut wanted, mut have) = (0, 0);
    for (k, _) in known {
        wanted += 1;
        have += usize::from(held.contains(k));
    }
    (wanted, have)
}

/// A client of the session: what it holds of the far view, and the bytes by class.
#[derive(Default)]
struct Client {
    held: BTreeSet<NodeKey>,
    summary_bytes: u64,
    cell_bytes: u64,
}

impl Client {
    fn take(&mut self, s: &mut Session, now: Instant) {
        while let Some(t) = s.poll_transmit(now) {
            s.on_flushed(t.len());
            match t.class {
                ServerMsgKind::Summaries => {
                    self.summary_bytes += t.len() as u64;
                    let frame = t.frame();
                    if let Ok(ServerMsg::Streaming(canopy_protocol::messages::ServerStreaming::Summaries(b))) =
                        ServerMsg::decode(&frame[4..])
                    {
                        for k in b.released {
                            self.held.remove(&k);
                        }
                        self.held.extend(b.nodes.iter().map(|n| n.key));
                    }
                }
                ServerMsgKind::Cells => self.cell_bytes += t.len() as u64,
                _ => {}
            }
        }
    }
}

fn session(store: &Arc<CellCache>, a: &Args, vp: Viewpoint, now: Instant) -> Session {
    let cfg = SessionConfig { bandwidth: Some(a.rate / 8), burst: 64 * 1024, ..SessionConfig::default() };
    let mut s = Session::new(Arc::clone(store) as Arc<dyn WorldStore>, cfg, now);
    s.handle(now, ClientMsg::hello("far-numbers")).unwrap();
    let w = s.poll_transmit(now).unwrap();
    s.on_flushed(w.len());
    s.handle(now, ClientMsg::ready(vec![], vp)).unwrap();
    s.handle(now, ClientMsg::Streaming(ClientStreaming::FarView(view(a)))).unwrap();
    s
}

/// Hover at `at` until the far field is complete (every wanted node held and nothing queued), in wall time.
fn hover(cache: &Arc<CellCache>, a: &Args, label: &str) {
    let radius = AoiParams::default().flight_radius(a.altitude, 0.0).min(AoiParams::default().max_radius);
    let vp = Viewpoint { seq: 0, position: a.at, yaw: 0.0, velocity: [0.0, 0.0], radius };
    let t0 = Instant::now();
    let mut s = session(cache, a, vp, t0);
    let mut c = Client::default();
    let mut records_done = None;
    let mut checked = None;
    loop {
        c.take(&mut s, Instant::now());
        if records_done.is_none() && s.is_complete() {
            records_done = Some(t0.elapsed());
        }
        // The far field can only have become complete with a summaries message and with nothing left queued:
        // walking the rule's tree costs the cores the workers use, so it is walked only then.
        if checked == Some(c.summary_bytes) || s.far().is_none_or(|f| f.queued() > 0) {
            std::thread::sleep(Duration::from_millis(5));
            continue;
        }
        checked = Some(c.summary_bytes);
        let (wanted, have) = completeness(cache, view(a), a.at, radius, &c.held);
        if wanted > 0 && have == wanted {
            let took = t0.elapsed();
            println!(
                "{label}: full far field of {wanted} nodes in {:.2} s: {:.1} KiB of summaries ({:.1} B a node), {:.1} KiB of cell batches meanwhile",
                took.as_secs_f64(),
                c.summary_bytes as f64 / 1024.0,
                c.summary_bytes as f64 / wanted as f64,
                c.cell_bytes as f64 / 1024.0
            );
            let levels: Vec<usize> = (0..=8).map(|l| c.held.iter().filter(|k| k.level == l).count()).collect();
            println!("{label}: nodes held by level 0..8: {levels:?}");
            if let Some(r) = records_done {
                println!(
                    "{label}: the records of the {radius} m area of interest were complete after {:.2} s",
                    r.as_secs_f64()
                );
            }
            return;
        }
        if t0.elapsed() > Duration::from_secs(600) {
            println!("{label}: not complete after 600 s: {have} of {wanted}");
            return;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Fly east at `speed` for `flight` seconds, a viewpoint every 100 ms; completeness every second.
fn fly(cache: &Arc<CellCache>, a: &Args) {
    let radius = AoiParams::default().flight_radius(a.altitude, a.speed).min(AoiParams::default().max_radius);
    let start = [a.at[0] - 30_000.0, a.at[1] + 20_000.0];
    let at = |t: f32| [start[0] + a.speed * t, start[1]];
    let vp =
        |seq, t| Viewpoint { seq, position: at(t), yaw: std::f32::consts::FRAC_PI_2, velocity: [a.speed, 0.0], radius };
    let t0 = Instant::now();
    let mut s = session(cache, a, vp(0, 0.0), t0);
    let mut c = Client::default();
    let mut seq = 0;
    let mut next_vp = 0.1f32;
    let mut next_report = 1.0f32;
    let mut samples = vec![];
    while t0.elapsed().as_secs_f64() < a.flight {
        let t = t0.elapsed().as_secs_f32();
        if t >= next_vp {
            seq += 1;
            s.handle(Instant::now(), ClientMsg::viewpoint(vp(seq, t))).unwrap();
            next_vp += 0.1;
        }
        c.take(&mut s, Instant::now());
        if t >= next_report {
            let (wanted, have) = completeness(cache, view(a), at(t), radius, &c.held);
            let pc = 100.0 * have as f64 / wanted.max(1) as f64;
            samples.push(pc);
            println!(
                "flight t={t:>5.1} s: far field {have} of {wanted} nodes ({pc:.1} %), {:.0} KiB of summaries so far",
                c.summary_bytes as f64 / 1024.0
            );
            next_report += 1.0;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let mut sorted = samples.clone();
    sorted.sort_by(f64::total_cmp);
    if !sorted.is_empty() {
        let mean = sorted.iter().sum::<f64>() / sorted.len() as f64;
        println!(
            "flight: far-field completeness mean {mean:.1} %, min {:.1} %, after the first 5 s min {:.1} %; {:.0} KiB of summaries, {:.0} KiB of cell batches",
            sorted[0],
            samples.iter().skip(5).copied().fold(100.0, f64::min),
            c.summary_bytes as f64 / 1024.0,
            c.cell_bytes as f64 / 1024.0
        );
    }
}

fn main() {
    let a = match args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("far_numbers: {e}");
            std::process::exit(2);
        }
    };
    let world = World::embedded(&a.world)
        .or_else(|| World::load(std::path::Path::new(&a.world)).ok())
        .unwrap_or_else(|| panic!("no world {}", a.world));
    let cfg = CellCacheConfig { summary_limit_bytes: 256 << 20, ..CellCacheConfig::default() };
    let cache = Arc::new(CellCache::new(world, cfg).expect("a store"));
    println!(
        "world {}, far view {} px over {} m from {} m up, link {} Mbit/s, {} cache workers",
        a.world,
        a.error,
        a.range,
        a.altitude,
        a.rate as f64 / 1e6,
        cache.config().workers
    );
    hover(&cache, &a, "cold");
    hover(&cache, &a, "warm");
    let (nodes, bytes) = cache.summaries_cached();
    println!("summary cache: {nodes} nodes, {:.1} MiB", bytes as f64 / 1048576.0);
    if a.flight > 0.0 {
        fly(&cache, &a);
    }
}
