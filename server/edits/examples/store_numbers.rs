//! Numbers for the SQLite edit store: durable edits per second (one fsync per edit, and group commit), and with
//! `--edits N` above a million, the restart cost of a store holding N edits (open time, RSS, load latency, file size).
//!
//! ```text
//! cargo run --release -p canopy-edits --example store_numbers -- [--edits N] [--dir D]
//! ```
//!
//! Without `--dir` the stores go in a temporary directory that is removed afterwards; with it, in fresh
//! subdirectories of `D` (removed afterwards too). The restart is measured in a fresh process (this program run
//! again with `--restart DIR`), so the RSS is the reopened store's, not the fill's leftovers. The file is in the OS
//! page cache then (it was just written): the load latencies are those of a warm restart.

use canopy_protocol::xorshift::XorShift64;
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use canopy_edits::{CellEdit, EditStore, SqliteEditStore, StoredEdit};
use canopy_protocol::{CellCoord, InstanceRecord};

const SEED: u64 = 0x5eed_cafe_f00d_0001;
/// Cells the throughput runs spread their edits over.
const THROUGHPUT_CELLS: usize = 10_000;
/// Cells the large fill spreads its edits over.
const FILL_CELLS: usize = 100_000;
/// Edits per append in the large fill.
const FILL_GROUP: usize = 10_000;
/// Above this, `--edits` asks for the fill and restart measurement rather than throughput.
const FILL_THRESHOLD: u64 = 1_000_000;
/// Cells loaded after the restart.
const RESTART_LOADS: usize = 1_000;

/// The project's seeded test generator, with a bounded draw.
struct Rng(XorShift64);

impl Rng {
    fn new(seed: u64) -> Rng {
        Rng(XorShift64::new(seed))
    }

    fn next(&mut self) -> u64 {
        self.0.next()
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// `n` distinct cells in a 4,000 × 4,000 region around the origin (negative coordinates included), the same for a
/// seed.
fn cells(n: usize, seed: u64) -> Vec<CellCoord> {
    let mut rng = Rng::new(seed);
    let mut seen = HashSet::with_capacity(n);
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let cell = CellCoord::new(rng.below(4000) as i32 - 2000, rng.below(4000) as i32 - 2000);
        if seen.insert(cell) {
            out.push(cell);
        }
    }
    out
}

/// Edits as editors make them: random cells, each cell's versions consecutive; 60% plants with one or two
/// parameters, 25% fells, 15% sets.
struct Workload {
    cells: Vec<CellCoord>,
    next: Vec<u32>,
    rng: Rng,
}

impl Workload {
    fn new(cells: Vec<CellCoord>, seed: u64) -> Workload {
        let next = vec![1; cells.len()];
        Workload { cells, next, rng: Rng::new(seed) }
    }

    fn edit(&mut self) -> StoredEdit {
        let rng = &mut self.rng;
        let i = rng.below(self.cells.len() as u64) as usize;
        let version = self.next[i];
        self.next[i] += 1;
        let index = (rng.below(2000)) as u16;
        let op = match rng.below(20) {
            0..12 => {
                let first = rng.below(6) as u16;
                let mut params = vec![(first, rng.below(4000) as f32 * 0.01)];
                if rng.below(2) == 0 {
                    params.push((first + 1 + rng.below(3) as u16, rng.below(100) as f32 * 0.1));
                }
                let record = InstanceRecord::new(rng.below(40) as u8, rng.below(4096) as u16, rng.below(4096) as u16);
                CellEdit::Plant { index, record, params }
            }
            12..17 => CellEdit::Fell { index },
            _ => CellEdit::Set { index, params: vec![(rng.below(6) as u16, rng.below(4000) as f32 * 0.01)] },
        };
        StoredEdit { cell: self.cells[i], version, op }
    }

    fn group(&mut self, n: usize) -> Vec<StoredEdit> {
        (0..n).map(|_| self.edit()).collect()
    }
}

struct Args {
    edits: u64,
    dir: Option<PathBuf>,
    restart: Option<PathBuf>,
}

fn parse_args() -> Result<Args, String> {
    let mut args = Args { edits: 200_000, dir: None, restart: None };
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        let mut value = || it.next().ok_or(format!("{a} needs a value"));
        match a.as_str() {
            "--edits" => args.edits = value()?.replace('_', "").parse().map_err(|e| format!("--edits: {e}"))?,
            "--dir" => args.dir = Some(PathBuf::from(value()?)),
            "--restart" => args.restart = Some(PathBuf::from(value()?)),
            "-h" | "--help" => {
                return Err("usage: store_numbers [--edits N] [--dir D]  (N above 1,000,000: fill and restart)".into());
            }
            other => return Err(format!("unknown argument {other}")),
        }
    }
    Ok(args)
}

fn main() {
    let args = match parse_args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(2);
        }
    };
    if let Err(e) = run(&args) {
        eprintln!("store_numbers: {e}");
        std::process::exit(1);
    }
}

fn run(args: &Args) -> Result<(), Box<dyn std::error::Error>> {
    if let Some(dir) = &args.restart {
        return restart(dir);
    }
    let _temp;
    let base = match &args.dir {
        Some(d) => {
            std::fs::create_dir_all(d)?;
            d.clone()
        }
        None => {
            _temp = tempfile::tempdir()?;
            _temp.path().to_path_buf()
        }
    };
    println!("store directory: {}", base.display());
    if args.edits > FILL_THRESHOLD { fill_and_restart(&base, args.edits) } else { throughput(&base, args.edits) }
}

/// A fresh directory under `base` (removed when the result is dropped).
fn fresh(base: &Path, name: &str) -> Result<tempfile::TempDir, std::io::Error> {
    tempfile::Builder::new().prefix(name).tempdir_in(base)
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn us(d: Duration) -> String {
    format!("{:.1} us", d.as_secs_f64() * 1e6)
}

fn throughput(base: &Path, edits: u64) -> Result<(), Box<dyn std::error::Error>> {
    // One edit per transaction: one fsync per edit.
    {
        let dir = fresh(base, "single-")?;
        let store = SqliteEditStore::open(dir.path())?;
        let mut load = Workload::new(cells(THROUGHPUT_CELLS, SEED), SEED + 1);
        let n = 2_000.min(edits as usize);
        let mut latencies = Vec::with_capacity(n);
        let start = Instant::now();
        for _ in 0..n {
            let e = load.edit();
            let t = Instant::now();
            store.append(std::slice::from_ref(&e))?;
            latencies.push(t.elapsed());
        }
        let elapsed = start.elapsed();
        latencies.sort();
        println!(
            "one edit per append: {:.0} durable edits/s ({n} edits in {:.2} s)",
            n as f64 / elapsed.as_secs_f64(),
            elapsed.as_secs_f64()
        );
        println!(
            "one edit per append, append latency: p50 {} p99 {} max {}",
            us(percentile(&latencies, 0.5)),
            us(percentile(&latencies, 0.99)),
            us(latencies[n - 1])
        );
    }
    // Group commit: `g` edits per append (a writer thread grouping the requests that queued during the last fsync).
    for g in [1usize, 16, 256, 1024] {
        let dir = fresh(base, "group-")?;
        let store = SqliteEditStore::open(dir.path())?;
        let mut load = Workload::new(cells(THROUGHPUT_CELLS, SEED), SEED + 2);
        // A group of one costs an fsync per edit: keep that run to 2,000 edits per edit of a group.
        let n = (edits as usize).min(2_000 * g).max(g);
        let groups: Vec<Vec<StoredEdit>> = (0..n / g).map(|_| load.group(g)).collect();
        let mut latencies = Vec::with_capacity(groups.len());
        let start = Instant::now();
        for group in &groups {
            let t = Instant::now();
            store.append(group)?;
            latencies.push(t.elapsed());
        }
        let elapsed = start.elapsed();
        latencies.sort();
        let stored = groups.len() * g;
        println!(
            "group commit, {g:>4} edits per append: {:.0} durable edits/s, {:.0} appends/s, append p50 {} p99 {} \
             ({stored} edits in {:.2} s)",
            stored as f64 / elapsed.as_secs_f64(),
            groups.len() as f64 / elapsed.as_secs_f64(),
            us(percentile(&latencies, 0.5)),
            us(percentile(&latencies, 0.99)),
            elapsed.as_secs_f64()
        );
        assert_eq!(store.count()?, stored as u64);
    }
    Ok(())
}

fn fill_and_restart(base: &Path, edits: u64) -> Result<(), Box<dyn std::error::Error>> {
    let dir = fresh(base, "fill-")?;
    let store = SqliteEditStore::open(dir.path())?;
    let mut load = Workload::new(cells(FILL_CELLS, SEED), SEED + 3);
    let start = Instant::now();
    let mut done = 0u64;
    let mut report = 1_000_000u64;
    while done < edits {
        let g = FILL_GROUP.min((edits - done) as usize);
        store.append(&load.group(g))?;
        done += g as u64;
        if done >= report {
            eprintln!("  filled {done} edits, {:.1} s", start.elapsed().as_secs_f64());
            report += 1_000_000;
        }
    }
    let filled = start.elapsed();
    println!(
        "fill: {done} edits over {FILL_CELLS} cells in groups of {FILL_GROUP}: {:.1} s ({:.0} edits/s)",
        filled.as_secs_f64(),
        done as f64 / filled.as_secs_f64()
    );
    let t = Instant::now();
    drop(store);
    println!("close after the fill (last checkpoint): {:.3} s", t.elapsed().as_secs_f64());

    let status = Command::new(std::env::current_exe()?).arg("--restart").arg(dir.path()).status()?;
    if !status.success() {
        return Err(format!("the restart process failed: {status}").into());
    }
    Ok(())
}

/// Resident set size in bytes (`/proc/self/statm`'s second field, in 4 KiB pages).
fn rss() -> u64 {
    std::fs::read_to_string("/proc/self/statm")
        .ok()
        .and_then(|s| s.split_whitespace().nth(1).and_then(|p| p.parse::<u64>().ok()))
        .map_or(0, |pages| pages * 4096)
}

fn mib(bytes: u64) -> String {
    format!("{:.1} MiB", bytes as f64 / (1024.0 * 1024.0))
}

fn file_size(path: &Path) -> u64 {
    std::fs::metadata(path).map_or(0, |m| m.len())
}

/// The restart, in a fresh process: open, RSS, loads of random cells, the cell list, the file size.
fn restart(dir: &Path) -> Result<(), Box<dyn std::error::Error>> {
    let before = rss();
    let t = Instant::now();
    let store = SqliteEditStore::open(dir)?;
    let opened = t.elapsed();
    let after = rss();
    println!("restart: open: {:.3} ms", opened.as_secs_f64() * 1e3);
    println!("restart: RSS before open: {}", mib(before));
    println!("restart: RSS after open: {} (+{})", mib(after), mib(after.saturating_sub(before)));

    let all = cells(FILL_CELLS, SEED);
    let mut rng = Rng::new(SEED + 4);
    let mut latencies = Vec::with_capacity(RESTART_LOADS);
    let mut loaded = 0usize;
    for _ in 0..RESTART_LOADS {
        let cell = all[rng.below(all.len() as u64) as usize];
        let t = Instant::now();
        let edits = store.load(cell)?;
        latencies.push(t.elapsed());
        loaded += edits.len();
    }
    latencies.sort();
    println!(
        "restart: load of {RESTART_LOADS} random cells: p50 {} p99 {} max {} ({:.1} edits per cell)",
        us(percentile(&latencies, 0.5)),
        us(percentile(&latencies, 0.99)),
        us(latencies[RESTART_LOADS - 1]),
        loaded as f64 / RESTART_LOADS as f64
    );
    println!("restart: RSS after the loads: {}", mib(rss()));

    let t = Instant::now();
    let listed = store.cells()?;
    println!("restart: cells(): {} cells in {:.3} s", listed.len(), t.elapsed().as_secs_f64());
    let t = Instant::now();
    let count = store.count()?;
    println!("restart: count(): {count} edits in {:.3} s", t.elapsed().as_secs_f64());
    println!("restart: RSS after cells() and count(): {}", mib(rss()));

    let path = store.path().to_path_buf();
    let db = file_size(&path);
    let wal = file_size(&PathBuf::from(format!("{}-wal", path.display())));
    println!(
        "file size: {} ({db} bytes; {:.1} bytes per edit), WAL {}",
        mib(db),
        db as f64 / count.max(1) as f64,
        mib(wal)
    );
    Ok(())
}
