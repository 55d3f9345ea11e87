//! The edit log on NATS JetStream, for real: a 3-node cluster started by `scripts/cluster.sh` on loopback and
//! stateless edges over it (each its own `NatsEditStore`, `LiveStore` and writer). An edit made through one edge
//! reaches the clients of another; edges racing for one cell's versions never take one twice (the engine's
//! compare-and-set, the writer's retry); a new edge starts with nothing and serves the same world. (A node killed
//! mid-run is not in this test yet: edits go on being acknowledged, but an edge's watch of a cell can take longer
//! than the test's bound to recover — see docs/edits.md.)

mod support;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use canopy_client::state::ClientState;
use canopy_protocol::CellCoord;
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_server::nats::{NatsConfig, NatsEditStore};
use support::*;

fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/cluster.sh")
}

/// A cluster for one test, taken down (and its directory removed) when dropped.
struct Cluster {
    dir: tempfile::TempDir,
    port: u16,
}

impl Cluster {
    fn run(&self, args: &[&str]) -> String {
        let o = Command::new("bash")
            .arg(script())
            .args(args)
            .env("CLUSTER_DIR", self.dir.path().join("c"))
            .env("NATS_PORT", self.port.to_string())
            .env("READY_S", "30")
            .output()
            .expect("bash runs scripts/cluster.sh");
        let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
        assert!(o.status.success(), "scripts/cluster.sh {args:?} failed:\n{text}");
        text
    }

    fn up() -> Cluster {
        // Client ports PORT..PORT+2, routes +100, monitoring +200: a block of this process's own.
        let port = 20_000 + (std::process::id() % 2_000) as u16 * 10;
        let c = Cluster { dir: tempfile::tempdir().unwrap(), port };
        c.run(&["up", "0"]);
        c
    }

    fn urls(&self) -> Vec<String> {
        (0..3).map(|i| format!("nats://127.0.0.1:{}", self.port + i)).collect()
    }

    /// A new edge of `world` over the cluster.
    fn edge(&self, world: &str) -> World {
        let cfg = NatsConfig { servers: self.urls(), world: world.into(), replicas: 3 };
        world_over(Arc::new(NatsEditStore::connect(cfg).expect("connecting to the cluster")))
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = Command::new("bash")
            .arg(script())
            .arg("down")
            .env("CLUSTER_DIR", self.dir.path().join("c"))
            .env("NATS_PORT", self.port.to_string())
            .output();
    }
}

fn cell_version(p: &Pair, c: CellCoord) -> u32 {
    p.client.cells().get(&c).map_or(0, |h| h.version)
}

#[test]
fn edges_over_jetstream_share_the_edits_and_their_versions() {
    let cluster = Cluster::up();
    let world = format!("edits-test-{}", std::process::id());
    let (ea, eb) = (cluster.edge(&world), cluster.edge(&world));
    let mut a = Pair::connect(&ea, ClientState::new(), Some(ALICE), 1);
    let mut b = Pair::connect(&eb, ClientState::new(), Some(BOB), 2);
    settle_each(&mut [(&ea, &mut a), (&eb, &mut b)]);

    // An edit through edge A reaches B's client (B watches the cell: its overlay is cached).
    let c = CellCoord::new(1, 1);
    let plant = a.edit(EditOp::Plant { species: 1, x: 36.0, z: 40.0, params: vec![(0, 2.5)] });
    let fell = a.edit(EditOp::Fell { id: canopy_protocol::InstanceId::new(c, 0).unwrap() });
    settle_until(&mut [(&ea, &mut a), (&eb, &mut b)], |p| cell_version(p[1].1, c) == 2);
    assert!(matches!(a.results[&plant], EditOutcome::Ok { version: 1, .. }));
    assert!(matches!(a.results[&fell], EditOutcome::Ok { version: 2, .. }));
    assert_eq!(sorted(b.client.instances(&|_, _| 0.0).collect()), sorted(a.client.instances(&|_, _| 0.0).collect()));

    // Both edges race for one cell's versions: each version is taken once, every edit answered.
    let race = CellCoord::new(2, 2);
    let mut asked = Vec::new();
    for i in 0..8 {
        let z = 70.0 + i as f32;
        asked.push((0, a.edit(EditOp::Plant { species: 0, x: 66.0, z, params: vec![] })));
        asked.push((1, b.edit(EditOp::Plant { species: 0, x: 90.0, z, params: vec![] })));
        a.step(&ea);
        b.step(&eb);
    }
    settle_until(&mut [(&ea, &mut a), (&eb, &mut b)], |p| p[0].1.results.len() == 10 && p[1].1.results.len() == 8);
    let mut versions: Vec<u32> = asked
        .iter()
        .filter_map(|(who, r)| {
            let p = if *who == 0 { &a } else { &b };
            match &p.results[r] {
                EditOutcome::Ok { version, .. } => Some(*version),
                EditOutcome::Conflict => None,
                other => panic!("{other:?}"),
            }
        })
        .collect();
    versions.sort_unstable();
    assert_eq!(versions, (1..=versions.len() as u32).collect::<Vec<_>>(), "versions 1..n, none twice");
    let log = ea.edits.load(race).unwrap();
    assert_eq!(log.len(), versions.len(), "exactly the acknowledged edits are stored");
    settle_until(&mut [(&ea, &mut a), (&eb, &mut b)], |p| {
        cell_version(p[0].1, race) == versions.len() as u32 && cell_version(p[1].1, race) == versions.len() as u32
    });
    assert_eq!(sorted(b.client.instances(&|_, _| 0.0).collect()), sorted(a.client.instances(&|_, _| 0.0).collect()));

    // A new edge holds nothing of its own: it serves the same world, edits included.
    let ec = cluster.edge(&world);
    assert_eq!(expected(&ec), sorted(a.client.instances(&|_, _| 0.0).collect()));
    assert_eq!(ec.edits.count().unwrap(), 2 + versions.len() as u64);
}
