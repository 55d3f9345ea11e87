//! The `canopy` command line: argument definitions and dispatch.

mod species;

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
    /// Species tools: check, stats, amplify, export, list.
    #[command(subcommand)]
    Species(species::SpeciesCommand),
    /// Amplify every species of the embedded library, print its numbers and export a grove (.glb).
    Demo(species::DemoArgs),
}

/// Run a parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Species(cmd) => species::run(cmd),
        Command::Demo(args) => species::demo(args),
    }
}
