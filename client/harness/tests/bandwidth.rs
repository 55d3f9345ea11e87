//! End-to-end tests of `canopy bandwidth`'s harness: a few seconds, one bot per scenario, real QUIC on loopback,
//! through the emulated link; checks that the report files exist and that the byte totals are consistent — for the
//! walkthrough on the default world, and for a flight over the highlands (never materialised: served through the
//! cell cache, the ground truth expanded cell by cell) with a far view, summaries beside records.

use std::sync::Arc;
use std::time::Duration;

use canopy_harness::bandwidth::link::LinkSpec;
use canopy_harness::bandwidth::{self, BandwidthConfig, BandwidthError, Scenario};
use canopy_protocol::messages::ServerMsgKind;
use canopy_protocol::summary::FarView;
use canopy_server::session::PayloadMode;
use canopy_worlds::world::World;

#[test]
fn short_run_writes_a_consistent_report() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("report");
    let mut cfg = BandwidthConfig::default_run();
    cfg.bots = 1;
    cfg.duration = Duration::from_secs(3);
    cfg.settle = Duration::from_secs(8);
    cfg.sample = Duration::from_millis(200);
    cfg.size_seeds = 0;
    cfg.mesh_sample = 0;
    cfg.progress = false;
    cfg.out = out.clone();
    cfg.scenarios = vec![
        Scenario::new(PayloadMode::Procedural, LinkSpec::default()),
        Scenario::new(PayloadMode::Procedural, LinkSpec::new(Some(1_000_000), 10, 0.01)),
        Scenario::new(PayloadMode::Instanced, LinkSpec::new(Some(10_000_000), 5, 0.0)),
    ];
    let world = Arc::new(World::default_world());
    let o = bandwidth::run(&cfg, world).expect("the run completes");

    for name in ["report.md", "scenarios.csv", "samples.csv", "sizes.csv", "bytes-all.svg"] {
        assert!(out.join(name).is_file(), "{name} written");
    }
    for s in &cfg.scenarios {
        assert!(out.join(format!("bytes-{}.svg", s.name)).is_file());
        assert!(out.join(format!("completeness-{}.svg", s.name)).is_file());
    }
    assert_eq!(o.scenarios.len(), 3);
    for r in &o.scenarios {
        let b = r.bytes();
        assert_eq!(b.class_sum(), b.total(), "{}: classes add up to the wire", r.scenario.name);
        for bot in &r.bots {
            assert!(bot.bot.error.is_none(), "{}: {:?}", r.scenario.name, bot.bot.error);
            let x = &bot.bytes;
            assert_eq!(x.class_sum(), x.total());
            assert!(x.species + x.records + x.geometry <= x.udp_rx, "frames fit in the datagrams");
            assert!(bot.bot.records > 0, "{}: records arrived", r.scenario.name);
            assert!(!bot.samples.is_empty());
            for w in bot.samples.windows(2) {
                assert!(w[0].t <= w[1].t && w[0].bytes.total() <= w[1].bytes.total(), "samples grow");
            }
            assert!(bot.samples.last().unwrap().bytes.total() <= x.total());
            assert!(bot.samples.iter().all(|s| s.held <= s.visible));
        }
        // The server's frames by class bound what the client received.
        let sent = r.server_bytes.expect("in-process server");
        assert!(
            b.species <= sent[ServerMsgKind::Species]
                && b.records <= sent[ServerMsgKind::Cells]
                && b.geometry <= sent[ServerMsgKind::Geometry],
            "{}",
            r.scenario.name
        );
    }
    let [plain, lossy, inst] = [&o.scenarios[0], &o.scenarios[1], &o.scenarios[2]];
    // Procedural on a free link: complete at the end, and then every visible instance is held (the ground truth
    // and the client agree).
    for r in [plain, lossy] {
        let bot = &r.bots[0];
        assert!(bot.bot.complete, "{}: complete at the end", r.scenario.name);
        let last = bot.samples.last().unwrap();
        assert!(last.aoi_complete && last.visible > 0 && last.held == last.visible, "{}: {last:?}", r.scenario.name);
        assert!(bot.first_complete().is_some());
        assert_eq!(r.bytes().geometry, 0);
        assert!(r.bytes().species > 0);
    }
    assert!(lossy.bots[0].link.is_some() && plain.bots[0].link.is_none());
    // Instanced: species meshes instead of programs, transforms with the records.
    let b = inst.bytes();
    assert_eq!(b.species, 0);
    assert!(inst.bots[0].geometry[1] > 0 && b.geometry >= inst.bots[0].geometry.iter().sum::<u64>());

    // The CSV's per-scenario row is the sum of its bots.
    let rows: Vec<csv::StringRecord> =
        csv::Reader::from_path(out.join("scenarios.csv")).unwrap().records().map(Result::unwrap).collect();
    for s in &cfg.scenarios {
        let wire = |bot: &str| -> u64 {
            rows.iter().find(|r| &r[0] == s.name.as_str() && &r[5] == bot).map(|r| r[6].parse().unwrap()).unwrap()
        };
        assert_eq!(wire("all"), wire("0"));
    }
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("| procedural-unlimited |") && report.contains("instanced-10M"));
}

#[test]
fn a_short_flight_over_the_highlands_reports_summaries_beside_records() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("flight");
    let world = Arc::new(World::embedded("highlands").expect("embedded"));
    assert!(!world.is_materialised());
    let mut cfg = BandwidthConfig::flight_run();
    cfg.bots = 1;
    cfg.duration = Duration::from_secs(5);
    cfg.settle = Duration::from_secs(5);
    // A far view out to 3 km keeps the summaries cheap to compute in a debug build.
    cfg.far = cfg.far.map(|f| FarView { range: 3000.0, ..f });
    cfg.progress = false;
    cfg.out = out.clone();
    cfg.scenarios =
        vec![Scenario::new(PayloadMode::Procedural, LinkSpec::new(Some(10_000_000), 10, 0.0)).prefixed("flight")];

    // The explicit baselines need a materialised world's meshes: a flight refuses them before starting anything.
    let mut explicit = cfg.clone();
    explicit.scenarios.push(Scenario::new(PayloadMode::Instanced, LinkSpec::default()));
    let refused = bandwidth::run(&explicit, Arc::clone(&world)).expect_err("a flight is procedural only");
    assert!(matches!(refused, BandwidthError::ProceduralOnly { mode: "instanced", .. }), "{refused}");
    assert!(!out.exists(), "nothing written");

    let started = std::time::Instant::now();
    let o = bandwidth::run(&cfg, world).expect("the flight completes");
    eprintln!("flight scenario in {:.1} s; ground truth {:?}", started.elapsed().as_secs_f64(), o.truth);
    let r = &o.scenarios[0];
    let bot = &r.bots[0];
    assert!(bot.bot.error.is_none(), "{:?}", bot.bot.error);
    // The radius of a flight at 1,500 m and 250 m/s, capped by the server (512 m by default), is the view distance
    // (10 Mbit/s carries it: the radius fitted to the link stays there at every sample).
    assert_eq!(bot.radius, 512.0);
    assert!(
        bot.samples.iter().all(|s| s.view == 512.0),
        "{:?}",
        bot.samples.iter().map(|s| s.view).collect::<Vec<_>>()
    );
    let b = r.bytes();
    assert_eq!(b.class_sum(), b.total(), "classes add up to the wire");
    assert!(b.summaries > 0 && b.records > 0 && b.species > 0, "{b:?}");
    assert_eq!(b.geometry, 0);
    assert!(bot.bot.summaries > 0 && bot.bot.records > 0);
    assert!(b.species + b.records + b.summaries <= b.udp_rx, "frames fit in the datagrams");
    let sent = r.server_bytes.expect("in-process server");
    assert!(b.summaries <= sent[ServerMsgKind::Summaries] && b.records <= sent[ServerMsgKind::Cells]);
    // Visible completeness measured against the world's function while flying.
    let overall = r.overall();
    assert!(overall.samples >= 10 && overall.visible > 0, "{overall:?}");
    assert!(bot.samples.iter().all(|s| s.held <= s.visible));
    assert!(bot.samples.iter().any(|s| s.held > 0), "records held within view");
    assert!(o.truth.expanded > 0, "{:?}", o.truth);
    let last = bot.samples.last().unwrap();
    if last.aoi_complete {
        // Complete at the end: the ground truth and the client agree on every record within view.
        assert_eq!(last.held, last.visible, "{last:?}");
    }
    // The far view and the summaries column in the report.
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        report.contains("## The far view: summaries beside records") && report.contains("| flight-procedural-10M |")
    );
    let rows: Vec<csv::StringRecord> =
        csv::Reader::from_path(out.join("scenarios.csv")).unwrap().records().map(Result::unwrap).collect();
    let header = csv::Reader::from_path(out.join("scenarios.csv")).unwrap().headers().unwrap().clone();
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    let all = rows.iter().find(|row| &row[col("bot")] == "all").unwrap();
    assert_eq!(all[col("summaries")].parse::<u64>().unwrap(), b.summaries);
    assert!(out.join("bytes-flight-procedural-10M.svg").is_file());
}
