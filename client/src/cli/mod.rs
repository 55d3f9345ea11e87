//! The `canopy` command line: argument definitions and dispatch.

mod species;
mod world;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// Canopy: procedural outdoor worlds — species are programs, trees are a few bytes.
#[derive(Parser, Debug)]
#[command(name = "canopy", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Species tools: check, stats, amplify, export, list, demo.
    #[command(subcommand)]
    Species(species::SpeciesCommand),
    /// World manifests: stats (the embedded default world, or a manifest file).
    #[command(subcommand)]
    World(world::WorldCommand),
}

/// Run a parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Species(cmd) => species::run(cmd),
        Command::World(cmd) => world::run(cmd),
    }
}
