//! `canopy world stats [MANIFEST]`: load a world manifest — or the embedded default world, `worlds/forest` — and
//! print its content summary and how long loading took (parsing, terrain and population expansion).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::Subcommand;

#[derive(Subcommand, Debug)]
pub enum WorldCommand {
    /// Load a world and print its summary (area, cells, terrain, species, instances per species) and load time.
    Stats {
        /// A world manifest (`.world`); without one, the embedded default world.
        manifest: Option<PathBuf>,
        /// Loads to time; the fastest is reported with the median.
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100))]
        repeat: u32,
    },
}

/// Run a `canopy world` command.
pub fn run(cmd: WorldCommand) -> anyhow::Result<ExitCode> {
    match cmd {
        WorldCommand::Stats { manifest, repeat } => Ok(stats(manifest, repeat)),
    }
}

fn stats(manifest: Option<PathBuf>, repeat: u32) -> ExitCode {
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
    ExitCode::SUCCESS
}
