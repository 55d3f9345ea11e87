//! End-to-end test of `canopy bandwidth`'s harness: a few seconds, one bot per scenario, real QUIC on loopback,
//! through the emulated link; checks that the report files exist and that the byte totals are consistent.

use std::sync::Arc;
use std::time::Duration;

use canopy_harness::bandwidth::link::LinkSpec;
use canopy_harness::bandwidth::{self, BandwidthConfig, Scenario};
use canopy_protocol::messages::ServerMsgKind;
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
