//! Bots that fly (issue 18): 250 m/s over the highlands, a 102.4 km world that exists only cell by cell (the
//! server's cell cache expands what the flights ask for), across cell borders, 2 km region borders and a terrain
//! tile border, ending exact against the world's function: `verify` compares every held cell with
//! `World::expand_cell`; and receiving the far view's summary nodes at altitude (issue 15). Real QUIC on loopback,
//! in process.

use std::collections::HashSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_client::net::{Connection, endpoint};
use canopy_harness::bots::{self, BotsConfig, BotsSummary, DriveHooks, DrivePlan, Mover, PathKind, Progress, Walker};
use canopy_protocol::aoi::AoiParams;
use canopy_protocol::summary::FarView;
use canopy_server::session::SessionConfig;
use canopy_server::{CellCacheConfig, Cells, ServeOptions, Served, ServerConfig, serve};
use canopy_test_support::{highlands, pinned};
use canopy_worlds::world::REGION_BLOCK;

/// The server's rules for these flights: a radius capped at 192 m (what a flight at 1500 m asks for is capped to
/// it), a second of look-ahead led at most 128 m (so `flight_radius` adds the rest of 250 m to the radius, up to
/// the cap).
const AOI: AoiParams = AoiParams { max_radius: 192.0, hysteresis: 32.0, lookahead_s: 1.0, max_lookahead: 128.0 };

async fn start_server() -> Served {
    let cache = CellCacheConfig { limit_bytes: 16 << 20, workers: 2, ..CellCacheConfig::default() };
    let cfg = ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        metrics: None,
        session: SessionConfig { aoi: AOI, ..SessionConfig::default() },
        ..ServerConfig::default()
    };
    let opts = ServeOptions { server: cfg, cells: Cells::OnDemand(cache), ..ServeOptions::default() };
    serve((**highlands()).clone(), opts).await.expect("server starts")
}

/// Where the flight went.
#[derive(Default)]
struct Track {
    cells: HashSet<(i32, i32)>,
    regions: HashSet<(i32, i32)>,
    tiles: HashSet<(i32, i32)>,
    viewpoints: usize,
}

impl DriveHooks for Track {
    fn stepped(&mut self, _now: Instant, walker: &mut Walker) -> bool {
        let world = highlands();
        let [x, z] = walker.position();
        let c = world.cell_of(x.into(), z.into());
        self.cells.insert((c.x, c.z));
        let region = world.cell_size * REGION_BLOCK as f32;
        self.regions.insert(((x / region).floor() as i32, (z / region).floor() as i32));
        // Terrain tiles of 12.8 km from the world's corner: x = 0 and z = 0 are tile borders.
        self.tiles.insert((((x + 51_200.0) / 12_800.0).floor() as i32, ((z + 51_200.0) / 12_800.0).floor() as i32));
        false
    }

    fn changed(&mut self, conn: &Connection) {
        self.viewpoints = conn.state().viewpoint().map_or(0, |v| v.seq as usize);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn flights_over_the_highlands_cross_borders_and_end_exact_against_the_function() {
    let world = highlands();
    assert!(!world.is_materialised() && world.instances.is_empty(), "the highlands exist only as a function");
    let server = start_server().await;

    // Two bots through the runner, flying wherever their seeds put them in the 102.4 km square.
    let mut cfg = BotsConfig::new(2, pinned(&server));
    cfg.path = PathKind::Flight;
    cfg.speed = 250.0;
    cfg.altitude = 1500.0;
    cfg.duration = Duration::from_secs(4);
    cfg.settle = Duration::from_secs(60);
    cfg.seed = 18;
    cfg.verify = Some(Arc::clone(world));
    let runner = tokio::spawn(bots::run(cfg, Arc::new(Progress::default())));

    // One flight placed in a 600 m square around (0, 0), where cells, 2 km regions and 12.8 km terrain tiles all
    // meet: 1 km of flight there crosses them.
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let radius = AOI.flight_radius(1500.0, 250.0);
    assert_eq!(radius, 192.0, "the server's cap");
    let mut walker = Walker::new(PathKind::Flight, 250.0, [-300.0, -300.0], [300.0, 300.0], 5).with_altitude(1500.0);
    let first = walker.viewpoint(radius);
    let mut conn = Connection::connect(&ep, &pinned(&server), None, |_| first).await.expect("connects");
    let mut track = Track::default();
    let plan = DrivePlan {
        radius,
        tick: Duration::from_millis(100),
        walk_until: Instant::now() + Duration::from_secs(4),
        settle: Duration::from_secs(60),
        sample: None,
        stop: tokio::sync::watch::channel(false).1,
        // The far view beyond the records (issue 15): summary nodes out to 3 km.
        far: Some(FarView { error_px: 16.0, height_px: 1080, fov_y: 1.0, range: 3000.0, altitude: 0.0 }),
        fit: None,
    };
    let complete = bots::drive(&mut conn, &mut walker, plan, &mut track).await.expect("flies");
    assert!(complete, "the area of interest filled at the end");
    // At altitude the bot asked for the far view and received summary nodes, none of them finer than the rule
    // allows from 1,500 m up (a level-0 node's error, 8 m, projects to under 16 px from there).
    let far = conn.state().summaries();
    assert!(conn.state().stats().summaries > 0 && !far.is_empty(), "summaries arrived");
    assert_eq!(conn.state().far_view().map(|f| f.altitude), Some(1500.0), "the far view carries the altitude");
    assert!(far.keys().all(|k| k.level >= 1), "{:?}", far.keys().next());
    let state = conn.close_into_state();
    let checked = tokio::task::spawn_blocking(move || bots::verify(&state, highlands())).await.unwrap();
    let summary = checked.expect("exact against World::expand_cell");
    assert!(summary.instances > 0 && summary.cells >= 20, "{summary:?}");
    assert!(track.cells.len() >= 10, "{} cells flown over", track.cells.len());
    assert!(track.regions.len() >= 2, "crossed a region border: {:?}", track.regions);
    assert!(track.tiles.len() >= 2, "crossed a terrain tile border: {:?}", track.tiles);
    assert!(track.viewpoints >= 10, "{} viewpoints", track.viewpoints);

    let reports = runner.await.unwrap().expect("the bots run");
    let summary = BotsSummary::new(&reports, Duration::ZERO);
    assert!(summary.ok(), "{summary}");
    assert_eq!(summary.checked, 2, "{summary}");
    assert!(reports.iter().all(|r| r.viewpoints >= 10), "they moved: {summary}");
    assert!(summary.moving.samples >= 8, "sampled while flying: {summary}");
    eprintln!("{summary}");
    server.shutdown(Duration::from_secs(1)).await;
}

/// The radii a bot asked for, viewpoint by viewpoint.
#[derive(Default)]
struct Radii(Vec<(u32, f32)>);

impl DriveHooks for Radii {
    fn changed(&mut self, conn: &Connection) {
        if let Some(v) = conn.state().viewpoint()
            && self.0.last().is_none_or(|&(seq, _)| seq != v.seq)
        {
            self.0.push((v.seq, v.radius));
        }
    }
}

/// A flight on a slow link asks, while it moves, for the radius the link carries at its speed
/// (`AoiParams::link_radius` over the records around it), not the flight radius; at rest it asks for the flight
/// radius again, and what it holds is exact against the world's function.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flight_on_a_slow_link_asks_for_the_radius_the_link_carries() {
    let server = start_server().await;
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let radius = AOI.flight_radius(1500.0, 250.0);
    let mut walker = Walker::new(PathKind::Flight, 250.0, [-300.0, -300.0], [300.0, 300.0], 5).with_altitude(1500.0);
    let first = walker.viewpoint(radius);
    let mut conn = Connection::connect(&ep, &pinned(&server), None, |_| first).await.expect("connects");
    // 100 kbit/s: 0.6 · 12,500 B/s over 2 · 250 m/s · 0.05 records/m² (the forest near (0, 0)) · ~7.5 B is
    // ~40 m, well under the 192 m cap.
    let fit = bots::LinkFit { link_bits: 100_000.0 };
    let plan = DrivePlan {
        radius,
        tick: Duration::from_millis(100),
        walk_until: Instant::now() + Duration::from_secs(3),
        settle: Duration::from_secs(60),
        sample: None,
        stop: tokio::sync::watch::channel(false).1,
        far: None,
        fit: Some(fit),
    };
    let mut radii = Radii::default();
    let complete = bots::drive(&mut conn, &mut walker, plan, &mut radii).await.expect("flies");
    assert!(complete, "the area of interest filled at the end");
    let (moving, rest) = radii.0.split_at(radii.0.len() - 1);
    assert_eq!(rest[0].1, radius, "at rest: the flight radius again");
    let fitted: Vec<f32> = moving.iter().map(|&(_, r)| r).filter(|&r| r < radius).collect();
    assert!(!fitted.is_empty(), "a fitted radius was asked for while moving: {:?}", radii.0);
    assert!(
        fitted.iter().all(|&r| (canopy_protocol::aoi::LINK_MIN_RADIUS..=120.0).contains(&r)),
        "what 100 kbit/s carries at 250 m/s: {:?}",
        radii.0
    );
    // The density the fit read is the records' around the bot.
    let density = conn.state().record_density().expect("cells held");
    assert!((0.01..1.0).contains(&density), "{density} records a m²");
    let state = conn.close_into_state();
    let checked = tokio::task::spawn_blocking(move || bots::verify(&state, highlands())).await.unwrap();
    let summary = checked.expect("exact against World::expand_cell");
    assert!(summary.instances > 0, "{summary:?}");
    server.shutdown(Duration::from_secs(1)).await;
}
