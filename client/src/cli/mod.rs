//! The `canopy` command line: argument definitions and dispatch.

mod bandwidth;
mod bots;
mod demo;
mod edit;
mod far;
mod hypertree;
mod render;
mod species;
mod walk;
mod walk_edit;
mod world;

use std::path::Path;
use std::process::ExitCode;

use anyhow::Context;
use canopy_worlds::diag::Diagnostics;
use canopy_worlds::world::World;
use clap::{Parser, Subcommand};

/// Canopy: procedural outdoor worlds — species are programs, trees are a few bytes.
#[derive(Parser, Debug)]
#[command(name = "canopy", version, about, long_about = None)]
pub(crate) struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Species tools: check, stats, amplify, export, nearfield, render, list, edit, demo.
    #[command(subcommand)]
    Species(species::SpeciesCommand),
    /// Hypertrees (far-field volumes): list, check, generate, render, stats, reduce, union, clear, set, voxelise,
    /// bench.
    #[command(subcommand)]
    Hypertree(hypertree::HypertreeCommand),
    /// Worlds: stats, plant, fell, set, bake, cell (manifests, and edits on a running server).
    #[command(subcommand)]
    World(world::WorldCommand),
    /// Bandwidth harness: procedural streaming against explicit geometry over emulated links; writes a report.
    Bandwidth(bandwidth::BandwidthArgs),
    /// Headless walkthrough bots against a running canopy-server, with progress and a summary.
    Bots(bots::BotsArgs),
    /// The streaming demo: canopy-server on the default world (or `--world`) in-process, a few bots, a live summary.
    Demo(demo::DemoArgs),
    /// Render a world offscreen to a PNG (works without a GPU on Mesa lavapipe), with frame times.
    Render(render::RenderArgs),
    /// The walkthrough window: fly or walk through a world streamed from a canopy-server.
    Walk(walk::WalkArgs),
}

/// Run a parsed command line.
pub(crate) fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Species(cmd) => species::run(cmd),
        Command::Hypertree(cmd) => hypertree::run(cmd),
        Command::World(cmd) => world::run(cmd),
        Command::Bandwidth(args) => bandwidth::run(args),
        Command::Bots(args) => bots::run(args),
        Command::Demo(args) => demo::run(args),
        Command::Render(args) => render::run(args),
        Command::Walk(args) => walk::run(args),
    }
}

/// Which server a client command connects to and how it trusts the server's certificate: one set of flags for
/// `walk`, `bots`, `world plant|fell|set|cell` and `bandwidth`.
#[derive(clap::Args, Debug, Clone, Default)]
pub(crate) struct ConnectArgs {
    /// The server's UDP address, or the edges of one world comma-separated (`HOST:PORT,HOST:PORT`: a client whose
    /// edge dies or closes resumes on another). Without it, `walk` and `bandwidth` start a server in this process,
    /// and the other commands connect to 127.0.0.1:4433.
    #[arg(long, value_name = "HOST:PORT[,…]")]
    pub server: Option<canopy_client::net::Edges>,
    /// Pin the server's certificate by its SHA-256 fingerprint (as `canopy-server` prints it).
    #[arg(long, conflicts_with = "insecure")]
    pub cert_fingerprint: Option<String>,
    /// Accept any server certificate (local use only).
    #[arg(long)]
    pub insecure: bool,
    /// Take every cell's instance records from the server, instead of expanding cells here from the world function
    /// (the default where the server offers one).
    #[arg(long)]
    pub records: bool,
    /// Speak WebTransport (HTTP/3, as a browser does) instead of native QUIC; `--cert-fingerprint` then pins the
    /// server's WebTransport certificate (`canopy-server` prints both).
    #[arg(long)]
    pub web_transport: bool,
}

impl ConnectArgs {
    /// The address `canopy-server` listens on by default.
    pub(crate) const DEFAULT_SERVER: &str = "127.0.0.1:4433";

    /// The server's edges, or the default server's.
    pub(crate) fn edges(&self) -> canopy_client::net::Edges {
        self.server.clone().unwrap_or_else(|| Self::DEFAULT_SERVER.parse().expect("the default address parses"))
    }

    /// How to trust the server's certificate (one of the two flags is needed).
    pub(crate) fn trust(&self) -> anyhow::Result<canopy_client::Trust> {
        Ok(canopy_client::Trust::from_flags(self.cert_fingerprint.as_deref(), self.insecure)?)
    }

    /// Where cells are expanded: a pool with a worker per core and the default cache, shared by every connection
    /// of the process; `None` with `--records`.
    pub(crate) fn expander(&self) -> Option<std::sync::Arc<canopy_client::expand::Expander>> {
        (!self.records).then(canopy_client::expand::Expander::default_pool)
    }

    /// The connection configuration for `edges` with `trust`, over WebTransport with `--web-transport`.
    pub(crate) fn config(
        &self,
        edges: &canopy_client::net::Edges,
        trust: canopy_client::Trust,
    ) -> canopy_client::ConnectConfig {
        let mut cfg = canopy_client::ConnectConfig::new_edges(edges, trust);
        if self.web_transport {
            cfg.web = Some(canopy_server::WEB_PATH.to_owned());
        }
        cfg
    }

    /// Whether any flag was given (the commands with a server in process refuse trust flags without `--server`).
    pub(crate) fn trust_given(&self) -> bool {
        self.cert_fingerprint.is_some() || self.insecure
    }
}

/// A `value_parser` for a library enum that names its values (`NAMES`) and parses them (`FromStr`): `--help` lists
/// the names, and the libraries need no clap.
fn named<T>(names: &'static [(&'static str, T)]) -> impl clap::builder::TypedValueParser<Value = T>
where
    T: std::str::FromStr<Err = String> + Clone + Send + Sync + 'static,
{
    use clap::builder::TypedValueParser;
    clap::builder::PossibleValuesParser::new(names.iter().map(|(n, _)| *n)).try_map(|s| s.parse::<T>())
}

/// A world manifest, an embedded world by name, or the embedded default world without one.
fn load_world(manifest: Option<&Path>) -> Result<World, Diagnostics> {
    match manifest {
        // A name that is no file but an embedded world's (`--world highlands`) is that world.
        Some(path) => match path.to_str().filter(|_| !path.exists()).and_then(World::embedded) {
            Some(world) => Ok(world),
            None => World::load(path),
        },
        None => Ok(World::default_world()),
    }
}

/// A world named on the command line: a manifest file if one is at that path, else an embedded world by name
/// (`forest`, `highlands`).
fn world_arg(arg: &str) -> anyhow::Result<World> {
    if Path::new(arg).is_file() {
        return World::load(Path::new(arg)).map_err(|d| anyhow::anyhow!("{d}"));
    }
    World::embedded(arg).ok_or_else(|| {
        let names: Vec<&str> = canopy_worlds::world::EMBEDDED_WORLDS.iter().map(|(n, _)| *n).collect();
        anyhow::anyhow!("no world manifest `{arg}`, and no embedded world of that name ({})", names.join(", "))
    })
}

/// Write a file, creating its parent directory first.
fn write_file(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    std::fs::write(path, bytes).with_context(|| format!("cannot write {}", path.display()))
}
