//! The research instruments: commands that study the method itself rather than
//! a user's data. `sefi --help` lists them after the user's commands.
//!
//! * [`power`]: `sefi power-study`, how often the diagnosis names a hidden effect.
//! * [`stability`]: `sefi stability`, whether a finding hinges on its held-out set.
//! * [`score_check`]: `sefi score-check`, the estimators against the exact
//!   linear-Gaussian score.
//! * [`calibrate`]: `sefi score-at` and `sefi precision`, an estimator's score at
//!   given parameters and the filter's likelihood precision.

pub mod calibrate;
pub mod power;
pub mod score_check;
pub mod stability;

use clap::Subcommand;

/// The instruments' subcommands (flattened into `sefi`'s).
#[derive(Subcommand)]
pub enum Instrument {
    /// How often `diagnose` names a hidden effect: effects x strengths x seeds of generated data (the criticism's
    /// power and false-cause rate).
    PowerStudy(power::PowerArgs),
    /// Whether a diagnosis's finding hinges on its held-out set: several diagnoses' outcomes, candidates and
    /// gains by part (KITTI sequence or scene) side by side, with a forest plot.
    Stability(stability::StabilityArgs),
    /// Exact linear-Gaussian log-likelihood and score, and every estimator's bias and spread.
    ScoreCheck(score_check::ScoreCheckArgs),
    /// An estimator's mean score at given parameters over filter runs and objects, with its standard
    /// error and z per parameter (zero within noise at the truth of generated data).
    ScoreAt(calibrate::ScoreAtArgs),
    /// The precision of the filter's likelihood estimate: each object's spread across runs, and the
    /// effective sample size per step.
    Precision(calibrate::PrecisionArgs),
}

impl Instrument {
    /// The instruments' command names, in the order `--help` lists them.
    pub const NAMES: [&'static str; 5] = ["power-study", "stability", "score-check", "score-at", "precision"];

    /// Runs the instrument.
    pub fn run(self) -> Result<(), String> {
        match self {
            Instrument::PowerStudy(args) => power::run(&args),
            Instrument::Stability(args) => stability::run(&args),
            Instrument::ScoreCheck(args) => score_check::run(&args),
            Instrument::ScoreAt(args) => calibrate::run_score_at(&args),
            Instrument::Precision(args) => calibrate::run_precision(&args),
        }
    }
}
