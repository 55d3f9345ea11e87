//! `canopy`: the command-line entry point. Parsing lives in [`cli`]; each subcommand validates its arguments into
//! a config once and calls the libraries.

mod cli;

use clap::Parser;

fn main() -> std::process::ExitCode {
    let args = cli::Cli::parse();
    match cli::run(args) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
