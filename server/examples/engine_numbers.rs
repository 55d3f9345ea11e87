//! Numbers for the edit log on NATS JetStream (issue 17): durable edits per second at the stream's replication, the
//! time of one append, and — while `scripts/cluster.sh kill nats I` runs beside it — how long appends fail or stall
//! after a node dies and when they are acknowledged again.
//!
//! ```text
//! scripts/cluster.sh up
//! cargo run --release -p canopy-server --example engine_numbers -- --nats nats://127.0.0.1:14222,… [--seconds 20]
//!     [--group 64] [--cells 1000] [--writers 1]
//! ```
//!
//! Each writer appends groups of `--group` edits, each to a random one of `--cells` cells of a fresh world (its own
//! stream), one group at a time, as an edge's writer does. Every 500 ms a line: groups acknowledged, edits a second,
//! failed calls, the longest call. At the end: edits a second overall, call time p50/p99/max, and the longest gap
//! between two acknowledged groups (the recovery time when a node was killed).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

use canopy_edits::{CellEdit, EditStore, Overlay, StoredEdit};
use canopy_protocol::xorshift::XorShift64;
use canopy_protocol::{CellCoord, InstanceRecord};
use canopy_server::{NatsConfig, NatsEditStore};

struct Args {
    nats: Vec<String>,
    seconds: f64,
    group: usize,
    cells: u64,
    writers: usize,
    replicas: usize,
}

fn args() -> Result<Args, String> {
    let mut a = Args { nats: vec![], seconds: 20.0, group: 64, cells: 1000, writers: 1, replicas: 3 };
    let mut it = std::env::args().skip(1);
    while let Some(k) = it.next() {
        let mut v = || it.next().ok_or(format!("{k} needs a value"));
        match k.as_str() {
            "--nats" => a.nats = v()?.split(',').map(str::to_owned).collect(),
            "--seconds" => a.seconds = v()?.parse().map_err(|e| format!("--seconds: {e}"))?,
            "--group" => a.group = v()?.parse().map_err(|e| format!("--group: {e}"))?,
            "--cells" => a.cells = v()?.parse().map_err(|e| format!("--cells: {e}"))?,
            "--writers" => a.writers = v()?.parse().map_err(|e| format!("--writers: {e}"))?,
            "--replicas" => a.replicas = v()?.parse().map_err(|e| format!("--replicas: {e}"))?,
            _ => return Err(format!("unknown argument {k}")),
        }
    }
    if a.nats.is_empty() || a.group == 0 || a.cells == 0 || a.writers == 0 {
        return Err("usage: engine_numbers --nats nats://HOST:PORT[,…] [--seconds S] [--group N] [--cells N] \
                    [--writers N] [--replicas N]"
            .into());
    }
    Ok(a)
}

#[derive(Default)]
struct Counts {
    groups: AtomicU64,
    edits: AtomicU64,
    failed: AtomicU64,
    longest_us: AtomicU64,
}

fn main() {
    let a = match args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(2);
        }
    };
    let world = format!("engine-numbers-{}", std::process::id());
    let cfg = NatsConfig { servers: a.nats.clone(), world, replicas: a.replicas };
    let store = Arc::new(NatsEditStore::connect(cfg).unwrap_or_else(|e| panic!("connecting: {e}")));
    let counts = Arc::new(Counts::default());
    let started = Instant::now();
    let until = started + Duration::from_secs_f64(a.seconds);
    let writers: Vec<_> = (0..a.writers)
        .map(|w| {
            let (store, counts) = (Arc::clone(&store), Arc::clone(&counts));
            let (group, cells) = (a.group, a.cells);
            std::thread::spawn(move || writer(w, &*store, &counts, group, cells, until))
        })
        .collect();
    let mut last = (0, 0, 0);
    while Instant::now() < until {
        std::thread::sleep(Duration::from_millis(500));
        let (g, e, f) = (counts.groups.load(Relaxed), counts.edits.load(Relaxed), counts.failed.load(Relaxed));
        println!(
            "{:6.1} s: {:5} groups acknowledged, {:7.0} edits/s, {} failed calls, longest call {:.1} ms",
            started.elapsed().as_secs_f64(),
            g - last.0,
            (e - last.1) as f64 * 2.0,
            f - last.2,
            counts.longest_us.swap(0, Relaxed) as f64 / 1e3
        );
        last = (g, e, f);
    }
    let mut times: Vec<Duration> = Vec::new();
    let mut gap = Duration::ZERO;
    for w in writers {
        let (t, g) = w.join().expect("a writer thread");
        times.extend(t);
        gap = gap.max(g);
    }
    times.sort_unstable();
    let at = |q: f64| times.get(((times.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or_default();
    let wall = started.elapsed().as_secs_f64();
    println!(
        "{} edits in {} groups of {} acknowledged at R{} by {} writer(s) in {wall:.1} s: {:.0} edits/s; call p50 {:.2} \
         ms p99 {:.2} ms max {:.1} ms; {} failed calls; longest gap between acknowledged groups {:.2} s",
        counts.edits.load(Relaxed),
        counts.groups.load(Relaxed),
        a.group,
        a.replicas,
        a.writers,
        counts.edits.load(Relaxed) as f64 / wall,
        at(0.5).as_secs_f64() * 1e3,
        at(0.99).as_secs_f64() * 1e3,
        at(1.0).as_secs_f64() * 1e3,
        counts.failed.load(Relaxed),
        gap.as_secs_f64()
    );
}

/// One writer: groups of plants on its own cells (writer `w` owns cells `w, w + writers, …` in effect, by its own
/// overlays), each group appended at the next versions its overlays know; a failed append reloads the cells it
/// touched (as the edge's writer does). Returns every call's time and the longest gap between acknowledgements.
fn writer(
    w: usize,
    store: &dyn EditStore,
    counts: &Counts,
    group: usize,
    cells: u64,
    until: Instant,
) -> (Vec<Duration>, Duration) {
    let mut rng = XorShift64::new(0x5eed ^ w as u64);
    let mut overlays: std::collections::BTreeMap<CellCoord, Overlay> = Default::default();
    let mut times = Vec::new();
    let (mut last_ack, mut gap) = (Instant::now(), Duration::ZERO);
    while Instant::now() < until {
        let mut edits = Vec::with_capacity(group);
        for _ in 0..group {
            let n = rng.next() % cells;
            let cell = CellCoord::new((n % 1000) as i32 * 16 + w as i32, (n / 1000) as i32);
            let o = overlays.entry(cell).or_insert_with(|| Overlay::new(0));
            let record = InstanceRecord::new(0, (rng.next() % 4096) as u16, (rng.next() % 4096) as u16);
            let e = StoredEdit {
                cell,
                version: o.version() + 1,
                op: CellEdit::Plant { index: o.total(), record, params: vec![] },
            };
            o.apply(&e).expect("the next version of a plant applies");
            edits.push(e);
        }
        let t0 = Instant::now();
        let r = store.append(&edits);
        let took = t0.elapsed();
        times.push(took);
        counts.longest_us.fetch_max(took.as_micros() as u64, Relaxed);
        match r {
            Ok(()) => {
                counts.groups.fetch_add(1, Relaxed);
                counts.edits.fetch_add(edits.len() as u64, Relaxed);
                gap = gap.max(last_ack.elapsed());
                last_ack = Instant::now();
            }
            Err(_) => {
                counts.failed.fetch_add(1, Relaxed);
                // Read back what the cells hold: some of the group may be stored.
                for e in &edits {
                    if let Ok(log) = store.load(e.cell) {
                        let mut o = Overlay::new(0);
                        for s in &log {
                            let _ = o.apply(s);
                        }
                        overlays.insert(e.cell, o);
                    }
                }
            }
        }
    }
    (times, gap)
}
