//! Bots that edit (issue: live edits): an in-process server over the highlands with live edits in memory, bots
//! standing together in a 32 m square around the middle, two of them planting and felling. Every edit is answered,
//! reaches every other bot holding its cell (the fan-out record counts each bot and version once), the check against
//! the world passes with edited cells compared only where the world's function still decides them, and bots holding
//! an edited cell at one version hold the same content. A client that planted fails the plain check and passes the
//! one that expects edits; bots that do not edit check a cell the server says is edited as edited. Real QUIC on
//! loopback.

use std::sync::Arc;
use std::time::Duration;

use canopy_client::net::{Connection, endpoint};
use canopy_client::state::Event;
use canopy_harness::bots::{self, BotsConfig, BotsSummary, EditPlan, PathKind, Progress};
use canopy_protocol::aoi::{AoiParams, Viewpoint};
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_server::session::{Editors, SessionConfig, editor_line};
use canopy_server::{CellCacheConfig, Cells, EditService, Edits, ServeOptions, Served, ServerConfig, serve};
use canopy_test_support::{highlands, pinned};

const TOKEN: [u8; 32] = [7; 32];

async fn start_server() -> (Served, Arc<EditService>) {
    let cache = CellCacheConfig { limit_bytes: 16 << 20, workers: 2, ..CellCacheConfig::default() };
    let editors = editor_line("bots", &TOKEN, None, Some(10_000));
    let cfg = ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        metrics: None,
        session: SessionConfig {
            aoi: AoiParams { max_radius: 192.0, hysteresis: 32.0, lookahead_s: 1.0, max_lookahead: 128.0 },
            editors: Some(Arc::new(Editors::parse("editors", &editors).unwrap())),
            ..SessionConfig::default()
        },
        ..ServerConfig::default()
    };
    let opts =
        ServeOptions { server: cfg, cells: Cells::OnDemand(cache), edits: Edits::Memory, overlay_cache_bytes: 1 << 20 };
    let server = serve((**highlands()).clone(), opts).await.expect("server starts");
    let service = Arc::clone(server.edits().expect("a server taking edits"));
    (server, service)
}

/// `count` bots walking slowly at random in a square of side `spread` around the middle, radius 96 m, checked
/// against the highlands.
fn walkers(server: &Served, count: usize, duration: Duration, spread: f32) -> BotsConfig {
    let mut cfg = BotsConfig::new(count, pinned(server));
    cfg.path = PathKind::Random;
    cfg.speed = 1.0;
    cfg.duration = duration;
    cfg.radius = 96.0;
    cfg.spread = Some(spread);
    cfg.verify = Some(Arc::clone(highlands()));
    cfg
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn editing_bots_reach_every_watcher_and_the_checks_hold_with_edits() {
    let (server, service) = start_server().await;
    let mut cfg = walkers(&server, 6, Duration::from_secs(6), 32.0);
    let mut plan = EditPlan::new(10.0, 2, TOKEN.to_vec());
    plan.warmup = Duration::from_secs(1);
    plan.grace = Duration::from_millis(1500);
    let fanout = Arc::clone(&plan.fanout);
    cfg.edits = Some(plan);
    let reports = bots::run(cfg, Arc::new(Progress::default())).await.expect("the bots run");
    let summary = BotsSummary::new(&reports, Duration::ZERO).with_fanout(fanout.report());
    eprintln!("{summary}");
    assert!(summary.ok(), "{summary}");
    assert_eq!(summary.verified, 6, "{summary}");
    let e = summary.edits.as_ref().expect("two bots edited");
    assert_eq!(e.editors, 2);
    let [ok, denied, invalid, conflict] = e.outcomes;
    assert!(ok >= 20 && e.fells > 0, "{summary}");
    assert_eq!((denied, invalid, conflict, e.unanswered), (0, 0, 0, 0), "{summary}");
    assert!(reports[2..].iter().all(|r| r.edits.is_none()), "the others only watch");
    // Every plant lands within 48 m of an editor standing within 45 m of each bot: inside every radius of 96 m.
    let f = summary.fanout.as_ref().unwrap();
    assert_eq!(f.per_edit.len() as u64, ok, "every acknowledged edit reached another bot: {summary}");
    assert_eq!(f.watchers().map(|w| w.1), Some(5), "each reached all five other bots: {summary}");
    assert_eq!(f.samples.len() as u64, 5 * ok, "each (bot, edit) once: {summary}");
    assert_eq!(f.unmatched, 0);
    assert!(summary.edited_checked > 0 && summary.edited_compared > 0, "{summary}");
    server.shutdown(Duration::from_secs(1)).await;
    service.stop();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edited_cell_fails_the_plain_check_and_passes_the_one_expecting_edits() {
    let (server, service) = start_server().await;
    let mut connect = pinned(&server);
    connect.token = Some(TOKEN.to_vec());
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let mut conn = Connection::connect(&ep, &connect, None, |_| Viewpoint::at(0, [10.0, 10.0], 64.0)).await.unwrap();
    conn.wait_complete(Duration::from_secs(60)).await.unwrap();
    let before = bots::verify(conn.state(), highlands()).expect("exact before any edit");
    assert_eq!(before.edited, 0);
    let request = conn.edit(EditOp::Plant { species: 0, x: 12.0, z: 9.0, params: vec![] }).await.unwrap();
    let (mut answered, mut changed) = (false, false);
    while !(answered && changed) {
        match tokio::time::timeout(Duration::from_secs(20), conn.next_event()).await.expect("in time").unwrap() {
            Event::EditResult(r) if r.request == request => {
                assert!(matches!(r.outcome, EditOutcome::Ok { version: 1, .. }), "{r:?}");
                answered = true;
            }
            Event::Changed { version: 1, .. } => changed = true,
            _ => {}
        }
    }
    let state = conn.close_into_state();
    let plain = bots::verify(&state, highlands());
    assert!(plain.is_err(), "an edited cell differs from the world's function");
    let with = bots::verify_with(&state, highlands(), true).expect("edits expected");
    assert_eq!((with.edited, with.instances), (1, before.instances + 1));
    // Bots that do not edit hold the edited cell too: the server says it is edited, and they check it as such.
    let cfg = walkers(&server, 2, Duration::from_secs(2), 16.0);
    let reports = bots::run(cfg, Arc::new(Progress::default())).await.expect("the bots run");
    let summary = BotsSummary::new(&reports, Duration::ZERO);
    assert!(summary.ok() && summary.verified == 2, "{summary}");
    assert!(summary.edited_checked > 0, "the bots held the edited cell: {summary}");
    server.shutdown(Duration::from_secs(1)).await;
    service.stop();
}
