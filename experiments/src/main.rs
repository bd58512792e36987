//! `sefi`: the command-line program of the PF-SEFI workspace. It parses arguments,
//! shows progress and writes files and plots; the mathematics lives in the
//! `autodiff` and `ssm` libraries.
//!
//! * [`commands`]: what a user runs (demo, import, generate, train, evaluate,
//!   diagnose, the paper's experiments, parameter files).
//! * [`instruments`]: research instruments that study the method itself (the
//!   criticism's power, a diagnosis's stability, the estimators' bias and the
//!   filter's precision); `sefi --help` lists them under their own heading.
//! * Shared by both: [`args`] (options several commands take, declared once),
//!   [`output`] (files), [`plot`], [`birdseye`] and [`table`] (figures and
//!   tables), [`cluster`] (MPI).

mod args;
mod birdseye;
mod cluster;
mod commands;
mod instruments;
mod output;
mod plot;
mod table;

use commands::{demo, diagnose, evaluate, experiment_c, generate, import, params_npz, reproduce, train};

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

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
    /// Turn the KITTI tracking sequences into box-detection datasets (train and val).
    ImportKitti {
        /// The KITTI folder (label_02, det_pointrcnn, ego_pose_orbslam3, calib).
        #[arg(default_value = "../shared/data/kitti-tracking")]
        root: PathBuf,
        /// Output directory: datasets are written to OUT/train and OUT/val.
        #[arg(long, default_value = "out/kitti")]
        out: PathBuf,
        /// Steps per scene window (T + 1).
        #[arg(long, default_value_t = 20)]
        steps: usize,
        /// Keep every k-th frame (dt = 0.1 s * k).
        #[arg(long, default_value_t = 1)]
        stride: usize,
        /// Association gate (m).
        #[arg(long, default_value_t = 2.0)]
        gate: f64,
        /// Discard detections scoring below this.
        #[arg(long)]
        min_score: Option<f64>,
        /// Import only these sequences (comma-separated; default: every one present).
        #[arg(long, value_delimiter = ',')]
        sequences: Option<Vec<u32>>,
        /// The sequences of the val split (comma-separated; default: AB3DMOT's
        /// 1,6,10,12,13,14,16,19). With --sequences, e.g. half of the training
        /// sequences held out against the other half.
        #[arg(long, value_delimiter = ',')]
        val_sequences: Option<Vec<u32>>,
    },
    /// Generate the paper's synthetic datasets (experiment A or B).
    Generate(generate::GenerateArgs),
    /// Filter and smooth a dataset with given parameters and write the metrics.
    Eval(evaluate::EvalArgs),
    /// Smooth a dataset with given parameters and write the estimated states.
    Track(evaluate::TrackArgs),
    /// Learn a dataset's policy and observation network with a score estimator.
    Train(Box<train::TrainArgs>),
    /// Reproduce the paper's synthetic experiment A or B: train every estimator, table and curves.
    Reproduce(reproduce::ReproduceArgs),
    /// The paper's experiment C on KITTI: train every estimator on the train sequences, evaluate on val,
    /// compare with a supervised observation model.
    ExperimentC(experiment_c::ExperimentCArgs),
    /// Model criticism: what the fitted simulation gets wrong, its cause among the catalogue's extensions,
    /// and the held-out gain of the extended model.
    Diagnose(diagnose::DiagnoseArgs),
    /// Parameter files to and from NumPy's `.npz` (`export`, `import`).
    Params(params_npz::ParamsArgs),
    /// The research instruments (listed apart in `--help`).
    #[command(flatten)]
    Instrument(instruments::Instrument),
}

/// The command line: the user's commands in the list of commands, the research
/// instruments (hidden there) under a heading of their own after it, each with
/// its one-line description. Every name parses alike.
fn command_line() -> clap::Command {
    let mut cli = Cli::command();
    let mut listing = String::from("Research instruments (studies of the method itself; `sefi help <NAME>`):\n");
    for name in instruments::Instrument::NAMES {
        let about = cli.find_subcommand(name).and_then(|c| c.get_about()).map(|a| a.to_string()).unwrap_or_default();
        listing.push_str(&format!("  {name:<13} {about}\n"));
        cli = cli.mut_subcommand(name, |c| c.hide(true));
    }
    cli.after_help(listing)
}

fn main() -> ExitCode {
    let cli = Cli::from_arg_matches(&command_line().get_matches()).unwrap_or_else(|e| e.exit());
    let cluster = cluster::Cluster::join();
    let distributed = matches!(
        cli.command,
        Command::Train(_) | Command::Reproduce(_) | Command::ExperimentC(_) | Command::Diagnose(_)
    );
    if cluster.size() > 1 && !distributed {
        if cluster.is_root() {
            eprintln!(
                "error: only `sefi train`, `reproduce`, `experiment-c` and `diagnose` run as an MPI job; start \
                 other commands without mpiexec"
            );
        }
        // Every process refuses alike and ends normally (MPI is finalised when the
        // cluster drops), so no process waits for another. Aborting the job instead
        // could end it before mpiexec had passed the message on (measured: the
        // message lost on one CI run).
        return ExitCode::FAILURE;
    }
    let result = match cli.command {
        Command::Demo { out, seed, quick } => demo::run(&out, seed, quick),
        Command::ImportKitti { root, out, steps, stride, gate, min_score, sequences, val_sequences } => {
            let options = ssm::data::KittiOptions {
                steps,
                stride,
                gate,
                min_score: min_score.unwrap_or(f64::NEG_INFINITY),
                sequences,
                val_sequences,
                ..ssm::data::KittiOptions::default()
            };
            import::kitti(&root, &out, &options)
        }
        Command::Generate(args) => generate::run(&args),
        Command::Eval(args) => evaluate::eval(&args),
        Command::Track(args) => evaluate::track(&args),
        Command::Train(args) => train::run(&args, &cluster),
        Command::Reproduce(args) => reproduce::run(&args, &cluster),
        Command::ExperimentC(args) => experiment_c::run(&args, &cluster),
        Command::Diagnose(args) => diagnose::run(&args, &cluster),
        Command::Params(args) => params_npz::run(&args),
        Command::Instrument(instrument) => instrument.run(),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            cluster.fail(1);
            ExitCode::FAILURE
        }
    }
}
