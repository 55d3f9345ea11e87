//! `canopy world stats [MANIFEST]`: load a world manifest — or the embedded default world, `worlds/forest` — and
//! print its content summary and how long loading took. A world too large to expand whole is estimated from a
//! sample of its cells; `--cells X0,Z0,X1,Z1` expands a rectangle of cells exactly. `canopy world plant|fell|set|
//! cell` edit and read a running server's world ([`super::edit`]).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use canopy_harness::numbers::percentile;
use canopy_worlds::world::{CellKey, World};
use clap::Subcommand;

#[derive(Subcommand, Debug)]
pub(super) enum WorldCommand {
    /// Load a world and print its summary (area, cells, terrain, species, instances per species) and load time.
    Stats {
        /// A world manifest (`.world`); without one, the embedded default world.
        manifest: Option<PathBuf>,
        /// Loads to time; the fastest is reported with the median.
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100))]
        repeat: u32,
        /// Cells to sample for the estimate of a world expanded on demand.
        #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=65_536))]
        samples: u32,
        /// Expand the cells X0,Z0 ..= X1,Z1 exactly and print what they hold (cell coordinates, inclusive).
        #[arg(long, value_parser = parse_cells, allow_hyphen_values = true)]
        cells: Option<[i32; 4]>,
    },
    /// Plant an instance of SPECIES (a name or number) at world X Z on a running server (an editor token needed).
    Plant {
        /// The species: its name, or its number in the world's table.
        species: String,
        /// World X and Z, metres.
        #[arg(long, num_args = 2, value_names = ["X", "Z"], allow_hyphen_values = true, required = true)]
        at: Vec<f32>,
        /// A parameter value that differs from the species' default (`NAME=VALUE`; repeat for more).
        #[arg(long = "param", value_parser = super::edit::parse_param)]
        params: Vec<(String, f32)>,
        #[command(flatten)]
        server: super::edit::ServerArgs,
    },
    /// Fell (remove) instance ID (the number printed, or X:Z:INDEX) on a running server.
    Fell {
        /// The instance.
        #[arg(value_parser = super::edit::parse_id, allow_hyphen_values = true)]
        id: canopy_protocol::InstanceId,
        #[command(flatten)]
        server: super::edit::ServerArgs,
    },
    /// Give instance ID new parameter values (`NAME=VALUE …`) on a running server.
    Set {
        /// The instance.
        #[arg(value_parser = super::edit::parse_id, allow_hyphen_values = true)]
        id: canopy_protocol::InstanceId,
        /// `NAME=VALUE` pairs.
        #[arg(value_parser = super::edit::parse_param, required = true)]
        params: Vec<(String, f32)>,
        #[command(flatten)]
        server: super::edit::ServerArgs,
    },
    /// Write the world with the edits a server stored in DIR folded into a new manifest (`fell`, `set` and
    /// `instance` lines after the source manifest).
    Bake {
        /// The world's manifest (`.world`) or an embedded world's name; without one, the embedded default world.
        manifest: Option<PathBuf>,
        /// The server's data directory (its `edits.sqlite`).
        #[arg(long)]
        data: PathBuf,
        /// The manifest to write.
        #[arg(short, long)]
        out: PathBuf,
    },
    /// Print the instances of the cell at world X Z as a client receives them (id, species, position,
    /// parameters) and the cell's version.
    Cell {
        /// World X, metres.
        #[arg(allow_hyphen_values = true)]
        x: f32,
        /// World Z, metres.
        #[arg(allow_hyphen_values = true)]
        z: f32,
        #[command(flatten)]
        server: super::edit::ServerArgs,
    },
}

/// Run a `canopy world` command.
pub(super) fn run(cmd: WorldCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        WorldCommand::Stats { manifest, repeat, samples, cells } => Ok(stats(manifest, repeat, samples, cells)),
        WorldCommand::Plant { species, at, params, server } => {
            super::edit::plant(&server, &species, [at[0], at[1]], &params)
        }
        WorldCommand::Fell { id, server } => super::edit::fell(&server, id),
        WorldCommand::Set { id, params, server } => super::edit::set(&server, id, &params),
        WorldCommand::Cell { x, z, server } => super::edit::cell(&server, [x, z]),
        WorldCommand::Bake { manifest, data, out } => super::edit::bake(manifest.as_deref(), &data, &out),
    }
}

/// Most cells `--cells` expands.
const MAX_REGION_CELLS: u64 = 1 << 20;

/// `X0,Z0,X1,Z1` with X0 ≤ X1 and Z0 ≤ Z1, at most [`MAX_REGION_CELLS`] cells.
fn parse_cells(s: &str) -> Result<[i32; 4], String> {
    let v: Vec<i32> =
        s.split(',').map(|p| p.trim().parse::<i32>().map_err(|e| format!("`{p}`: {e}"))).collect::<Result<_, _>>()?;
    let [x0, z0, x1, z1] = v[..] else { return Err(format!("expected X0,Z0,X1,Z1, got {} numbers", v.len())) };
    if x0 > x1 || z0 > z1 {
        return Err("expected X0 ≤ X1 and Z0 ≤ Z1".into());
    }
    let n = (i64::from(x1) - i64::from(x0) + 1) as u64 * (i64::from(z1) - i64::from(z0) + 1) as u64;
    if n > MAX_REGION_CELLS {
        return Err(format!("{n} cells, more than {MAX_REGION_CELLS}"));
    }
    Ok([x0, z0, x1, z1])
}

fn stats(manifest: Option<PathBuf>, repeat: u32, samples: u32, cells: Option<[i32; 4]>) -> ExitCode {
    let load = || super::load_world(manifest.as_deref());
    let mut times: Vec<Duration> = Vec::new();
    let mut world = None;
    for _ in 0..repeat {
        let start = Instant::now();
        match load() {
            Ok(w) => {
                times.push(start.elapsed());
                world = Some(w);
            }
            Err(diags) => {
                for d in &diags.0 {
                    eprintln!("{d}\n");
                }
                eprintln!("failed — {} error(s)", diags.0.len());
                return ExitCode::FAILURE;
            }
        }
    }
    let Some(world) = world else { return ExitCode::FAILURE };
    times.sort_unstable();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    print!("{}", world.content_summary());
    let source = manifest.as_ref().map_or("the embedded default world".to_string(), |p| p.display().to_string());
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    if times.len() == 1 {
        println!("loaded {source} in {:.1} ms ({threads} threads)", ms(times[0]));
    } else {
        println!(
            "loaded {source} in {:.1} ms (fastest of {}; median {:.1} ms; {threads} threads)",
            ms(times[0]),
            times.len(),
            ms(times[times.len() / 2])
        );
    }
    if !world.is_materialised() {
        sample(&world, samples);
    }
    if let Some([x0, z0, x1, z1]) = cells {
        region(&world, CellKey { x: x0, z: z0 }, CellKey { x: x1, z: z1 });
    }
    ExitCode::SUCCESS
}

/// Estimate a world expanded on demand from `n` sampled cells, and time their expansion.
fn sample(world: &World, n: u32) {
    let start = Instant::now();
    let mut times = Vec::new();
    let mut lists = Vec::new();
    let cells = world.sample_cells(n);
    for &c in &cells {
        let t = Instant::now();
        lists.push(world.expand_cell(c));
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    print!("{}", world.estimate(&lists).describe(world));
    let total = start.elapsed().as_secs_f64();
    times.sort_by(f64::total_cmp);
    // Again, with every tile variant those cells touch already computed: what a long-running client or server pays.
    let mut warm: Vec<f64> = cells
        .iter()
        .map(|&c| {
            let t = Instant::now();
            std::hint::black_box(world.expand_cell(c));
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    warm.sort_by(f64::total_cmp);
    println!(
        "sampled {} cells in {total:.2} s: expansion p50 {:.2} ms, p99 {:.2} ms per cell alone (one thread, tile \
         variants computed on first use); again: p50 {:.2} ms, p99 {:.2} ms",
        lists.len(),
        percentile(&times, 0.5).unwrap_or(0.0),
        percentile(&times, 0.99).unwrap_or(0.0),
        percentile(&warm, 0.5).unwrap_or(0.0),
        percentile(&warm, 0.99).unwrap_or(0.0),
    );
}

/// Expand a rectangle of cells exactly and print its instances per species.
fn region(world: &World, c0: CellKey, c1: CellKey) {
    let start = Instant::now();
    let cells = world.expand_cells(c0, c1);
    let elapsed = start.elapsed().as_secs_f64();
    let mut counts = vec![0u64; world.species.len()];
    for (_, list) in &cells {
        for p in list {
            counts[usize::from(p.species)] += 1;
        }
    }
    let total: u64 = counts.iter().sum();
    let most = cells.iter().map(|(_, l)| l.len()).max().unwrap_or(0);
    println!(
        "cells {},{} ..= {},{}: {} cells, {total} instances (max {most} in a cell), expanded in {:.1} ms ({:.2} ms per cell)",
        c0.x,
        c0.z,
        c1.x,
        c1.z,
        cells.len(),
        elapsed * 1e3,
        elapsed * 1e3 / cells.len().max(1) as f64,
    );
    for (sp, n) in world.species.iter().zip(&counts) {
        println!("  {:12} {n:>10}", sp.name);
    }
}
