//! `sefi`: the command-line program of the PF-SEFI workspace. It parses arguments,
//! shows progress and writes files and plots; the mathematics lives in the
//! `autodiff` and `ssm` libraries.

mod demo;
mod output;
mod plot;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// Particle-filter score estimation with Fisher's identity (PF-SEFI), in Rust.
#[derive(Parser)]
#[command(name = "sefi", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// A quick end-to-end demonstration on built-in generated data.
    Demo {
        /// Directory for the results (CSV, JSON, SVG).
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
        /// Random seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Smaller sizes, for tests.
        #[arg(long)]
        quick: bool,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Demo { out, seed, quick } => demo::run(&out, seed, quick),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
