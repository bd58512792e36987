//! Why training, or one of its gradient estimates, failed: [`EstimateError`]
//! (the objective's, which decides whether a step is skipped) and [`TrainError`]
//! (the loop's, naming the file or step).

use std::fmt;
use std::path::PathBuf;

use autodiff::nn::ParamError;

use crate::models::ModelError;

/// Why [`Objective::estimate`](super::Objective::estimate) returned no estimate. [`train`](super::train) skips the step on
/// [`EstimateError::NonFinite`] and stops on [`EstimateError::Failed`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum EstimateError {
    /// The estimate is not finite (e.g. every particle impossible): the step is
    /// skipped, not fatal. What was not finite, and where.
    NonFinite(String),
    /// Anything else: training stops with the step named. What went wrong.
    Failed(String),
}

/// A non-finite estimate error (the step is skipped): `detail` says what was not
/// finite and where.
///
/// ```
/// let e = ssm::training::non_finite("log-weights all -inf at t = 7");
/// assert!(matches!(e, ssm::training::EstimateError::NonFinite(_)));
/// assert_eq!(e.to_string(), "non-finite estimate: log-weights all -inf at t = 7");
/// assert!(matches!(ssm::training::EstimateError::from("data file missing"), ssm::training::EstimateError::Failed(_)));
/// ```
pub fn non_finite(detail: impl fmt::Display) -> EstimateError {
    EstimateError::NonFinite(detail.to_string())
}

impl fmt::Display for EstimateError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            EstimateError::NonFinite(detail) => write!(f, "non-finite estimate: {detail}"),
            EstimateError::Failed(message) => f.write_str(message),
        }
    }
}

impl std::error::Error for EstimateError {}

impl From<String> for EstimateError {
    fn from(message: String) -> Self {
        EstimateError::Failed(message)
    }
}

impl From<ModelError> for EstimateError {
    fn from(e: ModelError) -> Self {
        EstimateError::Failed(e.to_string())
    }
}

impl From<&str> for EstimateError {
    fn from(message: &str) -> Self {
        EstimateError::Failed(message.to_string())
    }
}

/// Why training failed.
#[derive(Debug)]
pub enum TrainError {
    /// The settings or the objective cannot be trained.
    Config(String),
    /// `out_dir` already holds a run and `resume` was not asked for.
    Exists {
        /// The file found.
        path: PathBuf,
    },
    /// `resume` was asked for but there is no checkpoint.
    NoCheckpoint {
        /// The checkpoint expected.
        path: PathBuf,
    },
    /// A checkpoint or parameter file could not be read or written, or is damaged.
    Checkpoint {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        source: ParamError,
    },
    /// The checkpoint was written with other settings.
    ConfigChanged {
        /// The checkpoint.
        path: PathBuf,
        /// Each difference, `name: checkpoint vs now`.
        differences: Vec<String>,
    },
    /// The checkpoint does not fit this objective or parameter store.
    Incompatible {
        /// The checkpoint.
        path: PathBuf,
        /// What differs.
        reason: String,
    },
    /// A log file could not be read, written or understood.
    Log {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
    /// A file or directory operation failed.
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// [`Objective::estimate`](super::Objective::estimate) failed (other than by a non-finite estimate), or
    /// returned gradients that do not match the parameters.
    Estimate {
        /// The step (from 1).
        step: usize,
        /// The batch.
        batch: usize,
        /// The objective's message.
        message: String,
    },
    /// [`Objective::evaluate`](super::Objective::evaluate) failed or changed its metric names.
    Evaluate {
        /// Steps taken when it was called.
        step: usize,
        /// What went wrong.
        message: String,
    },
}

impl fmt::Display for TrainError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TrainError::Config(m) => write!(f, "training settings: {m}"),
            TrainError::Exists { path } => write!(
                f,
                "{} exists: the directory already holds a training run; pass --resume to continue it, \
                 or choose another output directory (or delete it)",
                path.display()
            ),
            TrainError::NoCheckpoint { path } => {
                write!(f, "{}: no checkpoint to resume from (start without --resume)", path.display())
            }
            TrainError::Checkpoint { path, source } => {
                write!(f, "checkpoint {}: {source}", path.display())
            }
            TrainError::ConfigChanged { path, differences } => write!(
                f,
                "{}: cannot resume with different settings (checkpoint vs now): {}",
                path.display(),
                differences.join("; ")
            ),
            TrainError::Incompatible { path, reason } => {
                write!(f, "{}: cannot resume: {reason}", path.display())
            }
            TrainError::Log { path, reason } => write!(f, "log {}: {reason}", path.display()),
            TrainError::Io { path, source } => write!(f, "{}: {source}", path.display()),
            TrainError::Estimate { step, batch, message } => {
                write!(f, "step {step} (batch {batch}): gradient estimate failed: {message}")
            }
            TrainError::Evaluate { step, message } => write!(f, "evaluation after step {step} failed: {message}"),
        }
    }
}

impl std::error::Error for TrainError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            TrainError::Checkpoint { source, .. } => Some(source),
            TrainError::Io { source, .. } => Some(source),
            _ => None,
        }
    }
}
