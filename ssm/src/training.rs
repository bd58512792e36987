//! The training loop (SPEC §6): Adam ascent on a score estimate per batch, with
//! non-finite steps skipped, crash-safe CSV logs and resumable checkpoints.
//!
//! The loop knows nothing about estimators: an [`Objective`] hands it, for one batch
//! (a scene) and a seed, a [`BatchEstimate`] — the log-likelihood estimate and the
//! **score**, its gradient with respect to every parameter of the store. [`train`]
//! **ascends** the score: it passes the negated score to Adam, which minimises.
//!
//! * **Steps.** One step is one batch; an epoch visits every batch once, in order
//!   or shuffled per epoch ([`epoch_order`]). Steps are numbered from 1; step `k`
//!   uses batch slot `(k - 1) % batches` of epoch `(k - 1) / batches` and the seed
//!   [`step_seed`]`(config.seed, k)`, so the whole run is a function of the config
//!   and a resumed run repeats exactly what an uninterrupted one would have done.
//! * **Non-finite estimates never reach the parameters.** A gradient holding NaN or
//!   an infinity, a non-finite log-likelihood, or an [`EstimateError::NonFinite`]
//!   from `estimate` skips the step (counted, marked in the log); any other error
//!   aborts training with the step named.
//! * **Clipping.** With `clip` set the global norm of the score is clipped before
//!   the update; the log records the norm before clipping.
//! * **Files in `out_dir`.** [`TRAIN_LOG`] (one row per step, header
//!   [`TRAIN_LOG_HEADER`]) and [`EVAL_LOG`] (`step` then the objective's metric
//!   names; a row at step 0, every `eval_every` steps and at the end) are appended
//!   and flushed row by row, so a crash loses at most the row being written.
//!   [`CHECKPOINT_FILE`] (a [`Checkpoint`], versioned, checksummed, written
//!   atomically) and [`PARAMS_FILE`] (the store alone, for `sefi eval --params`) are
//!   written at step 0, every `checkpoint_every` steps and at the end.
//! * **Resuming** reads the checkpoint, refuses a different config, drops the log
//!   rows written after it and carries on. Starting afresh in a directory that holds
//!   a run is refused rather than overwriting it.
//!
//! ```
//! use autodiff::nn::ParamStore;
//! use autodiff::Tensor;
//! use ssm::training::{train, BatchEstimate, EstimateError, Objective, TrainConfig};
//!
//! /// Log-likelihood -(x - 3)^2 on every batch: its maximiser is x = 3.
//! struct Quadratic;
//! impl Objective for Quadratic {
//!     fn batches(&self) -> usize {
//!         2
//!     }
//!     fn estimate(&mut self, p: &ParamStore<f64>, _: usize, _: u64) -> Result<BatchEstimate, EstimateError> {
//!         let x = p.values()[0].item();
//!         Ok(BatchEstimate {
//!             log_likelihood: -(x - 3.0) * (x - 3.0),
//!             observed_units: 1,
//!             gradient: vec![Tensor::from_vec(vec![-2.0 * (x - 3.0)])],
//!             collapsed_steps: 0,
//!         })
//!     }
//!     fn evaluate(&mut self, p: &ParamStore<f64>, _seed: u64) -> Result<Vec<(String, f64)>, String> {
//!         Ok(vec![("x".to_string(), p.values()[0].item())])
//!     }
//! }
//!
//! let dir = tempfile::tempdir().unwrap();
//! let mut store = ParamStore::new();
//! store.add("x", Tensor::from_vec(vec![0.0]));
//! let config = TrainConfig { lr: 0.1, epochs: 200, ..TrainConfig::default() };
//! let out = train(&mut Quadratic, store, &config, dir.path(), false, &mut |_| {}).unwrap();
//! assert_eq!(out.steps, 400);
//! assert!((out.params.values()[0].item() - 3.0).abs() < 0.05);
//! assert_eq!(out.final_eval[0].0, "x");
//! // The directory now holds a run: starting afresh there is refused.
//! assert!(train(&mut Quadratic, ParamStore::new(), &config, dir.path(), false, &mut |_| {}).is_err());
//! ```

use std::fmt;
use std::fs::{File, OpenOptions};
use std::path::{Path, PathBuf};
use std::time::Instant;

use autodiff::nn::{read_versioned, write_versioned, ParamError, ParamStore};
use autodiff::optim::{clip_global_norm, global_norm, Adam, StepError};
use autodiff::Tensor;
use serde::{Deserialize, Serialize};

use crate::seed::splitmix64;

/// The per-step log, one row per step.
pub const TRAIN_LOG: &str = "train.csv";
/// The evaluation log: `step`, then the objective's metric names.
pub const EVAL_LOG: &str = "eval.csv";
/// The resumable training state (a [`Checkpoint`]).
pub const CHECKPOINT_FILE: &str = "checkpoint.bin";
/// The parameter store alone, as [`ParamStore::save`] writes it.
pub const PARAMS_FILE: &str = "params.bin";
/// Format version of [`CHECKPOINT_FILE`] (checked by [`read_versioned`]).
pub const CHECKPOINT_VERSION: u32 = 2;
/// Columns of [`TRAIN_LOG`].
///
/// `step` counts from 1; `epoch` counts from 0; `batch` is the objective's batch
/// index; `ll_per_unit` is `log_likelihood / observed_units` (NaN without units);
/// `grad_norm` is the global norm of the score before clipping; `clipped` and
/// `skipped` are 0 or 1; `seconds` is the wall time of the step (estimate and update).
/// Unknown values (the estimate of a step skipped on a non-finite error) are `NaN`.
pub const TRAIN_LOG_HEADER: [&str; 11] = [
    "step",
    "epoch",
    "batch",
    "log_likelihood",
    "observed_units",
    "ll_per_unit",
    "grad_norm",
    "clipped",
    "skipped",
    "collapsed_steps",
    "seconds",
];
/// Why [`Objective::estimate`] returned no estimate. [`train`] skips the step on
/// [`EstimateError::NonFinite`] and stops on [`EstimateError::Failed`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum EstimateError {
    /// The estimate is not finite (e.g. every particle impossible): the step is
    /// skipped, not fatal. What was not finite, and where.
    NonFinite(String),
    /// Anything else: training stops with the step named. What went wrong.
    Failed(String),
}

impl EstimateError {
    /// Whether the step is skipped rather than fatal.
    pub fn is_non_finite(&self) -> bool {
        matches!(self, EstimateError::NonFinite(_))
    }
}

/// A non-finite estimate error (the step is skipped): `detail` says what was not
/// finite and where.
///
/// ```
/// let e = ssm::training::non_finite("log-weights all -inf at t = 7");
/// assert!(e.is_non_finite());
/// assert_eq!(e.to_string(), "non-finite estimate: log-weights all -inf at t = 7");
/// assert!(!ssm::training::EstimateError::from("data file missing").is_non_finite());
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

impl From<&str> for EstimateError {
    fn from(message: &str) -> Self {
        EstimateError::Failed(message.to_string())
    }
}

/// What one gradient estimate returned for one batch (a scene).
#[derive(Clone, Debug, PartialEq)]
pub struct BatchEstimate {
    /// The log-likelihood estimate `l_hat`, summed over the batch's objects.
    pub log_likelihood: f64,
    /// Points or detections that entered it (the MLL normaliser).
    pub observed_units: usize,
    /// The score: the gradient of the log-likelihood (not of a loss), one tensor per
    /// store parameter, in the order and shapes of [`ParamStore::values`]. The
    /// trainer ascends it.
    pub gradient: Vec<Tensor<f64>>,
    /// Filter steps at which the particle system collapsed (reported, not acted on).
    pub collapsed_steps: usize,
}

/// A learning problem: batches of training data, a score estimate per batch, a test
/// evaluation.
pub trait Objective {
    /// Batches per epoch (training scenes).
    fn batches(&self) -> usize;

    /// The log-likelihood and score estimate of batch `batch` (`0..batches()`) at
    /// `params`; all randomness must come from `seed`, so that a resumed run repeats
    /// an uninterrupted one. [`EstimateError::NonFinite`] skips the step; any other
    /// error aborts training.
    fn estimate(&mut self, params: &ParamStore<f64>, batch: usize, seed: u64)
        -> Result<BatchEstimate, EstimateError>;

    /// Test metrics, e.g. `[("test_mll", -1.5)]`; the names are the columns of
    /// [`EVAL_LOG`] and must be the same, in the same order, on every call.
    fn evaluate(&mut self, params: &ParamStore<f64>, seed: u64) -> Result<Vec<(String, f64)>, String>;
}

/// Settings of [`train`]. A resumed run must use the same settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrainConfig {
    /// Adam learning rate (default 0.01).
    pub lr: f64,
    /// If set, the learning rate falls linearly from `lr` at the first step to
    /// this at the last (default none: constant), so the final parameters are
    /// not a noisy snapshot of a still-moving run.
    pub final_lr: Option<f64>,
    /// Global gradient-norm clipping, if any (default none; SPEC §6 uses 0.5 on
    /// measured data).
    pub clip: Option<f64>,
    /// Passes over the batches (default 100, the paper's A/B setting).
    pub epochs: usize,
    /// Evaluate every this many steps; 0 evaluates only at the start and the end
    /// (default 0).
    pub eval_every: usize,
    /// Checkpoint every this many steps; 0 only at the start and the end (default 10).
    pub checkpoint_every: usize,
    /// Seed of the per-step seeds and the batch order (default 0).
    pub seed: u64,
    /// Visit the batches in a fresh random order each epoch (seeded from
    /// `(seed, epoch)`) rather than `0..batches` (default true).
    pub shuffle: bool,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            lr: 0.01,
            final_lr: None,
            clip: None,
            epochs: 100,
            eval_every: 0,
            checkpoint_every: 10,
            seed: 0,
            shuffle: true,
        }
    }
}

impl TrainConfig {
    /// The settings in which `self` differs from `other`, as `name: self vs other`.
    pub fn differences(&self, other: &TrainConfig) -> Vec<String> {
        let mut out = Vec::new();
        let mut cmp = |name: &str, a: String, b: String| {
            if a != b {
                out.push(format!("{name}: {a} vs {b}"));
            }
        };
        // `{:?}` of a float is its shortest round-trip text: distinct values print
        // differently.
        cmp("lr", format!("{:?}", self.lr), format!("{:?}", other.lr));
        cmp("final_lr", format!("{:?}", self.final_lr), format!("{:?}", other.final_lr));
        cmp("clip", format!("{:?}", self.clip), format!("{:?}", other.clip));
        cmp("epochs", self.epochs.to_string(), other.epochs.to_string());
        cmp("eval_every", self.eval_every.to_string(), other.eval_every.to_string());
        cmp("checkpoint_every", self.checkpoint_every.to_string(), other.checkpoint_every.to_string());
        cmp("seed", self.seed.to_string(), other.seed.to_string());
        cmp("shuffle", self.shuffle.to_string(), other.shuffle.to_string());
        out
    }

    fn validate(&self) -> Result<(), TrainError> {
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return Err(TrainError::Config(format!("learning rate must be positive and finite, got {}", self.lr)));
        }
        if let Some(end) = self.final_lr {
            if !(end.is_finite() && end > 0.0) {
                return Err(TrainError::Config(format!("final learning rate must be positive and finite, got {end}")));
            }
        }
        if let Some(c) = self.clip {
            if !(c.is_finite() && c > 0.0) {
                return Err(TrainError::Config(format!("clip must be positive and finite, got {c}")));
            }
        }
        Ok(())
    }

    /// The learning rate of step `step` (from 1) of `total`.
    pub fn lr_at(&self, step: usize, total: usize) -> f64 {
        match self.final_lr {
            Some(end) if total > 1 => {
                let f = (step.saturating_sub(1) as f64 / (total - 1) as f64).min(1.0);
                self.lr + (end - self.lr) * f
            }
            _ => self.lr,
        }
    }

    fn eval_due(&self, step: usize, total: usize) -> bool {
        step == 0 || step == total || every(step, self.eval_every)
    }

    fn checkpoint_due(&self, step: usize, total: usize) -> bool {
        step == 0 || step == total || every(step, self.checkpoint_every)
    }
}

/// Whether `step` is a positive multiple of `period` (never, for period 0).
#[allow(clippy::manual_is_multiple_of)] // `is_multiple_of` needs Rust 1.87; the workspace supports 1.82.
fn every(step: usize, period: usize) -> bool {
    period > 0 && step % period == 0
}

/// Progress of [`train`], for a progress bar or a console log.
#[derive(Clone, Debug, PartialEq)]
pub enum TrainEvent {
    /// Training is about to run steps `first_step..=total_steps` (`first_step` is 1
    /// for a fresh run, one past the checkpoint's step after a resume, and
    /// `total_steps + 1` when a resumed run had already finished).
    Started {
        /// Steps of the whole run: `epochs * batches`.
        total_steps: usize,
        /// The first step this call runs.
        first_step: usize,
    },
    /// A step was taken or skipped.
    Step {
        /// The step (from 1).
        step: usize,
        /// Log-likelihood per observed unit (NaN without units or when unknown).
        ll_per_unit: f64,
        /// Global norm of the score before clipping.
        grad_norm: f64,
        /// Whether the step was skipped (non-finite estimate).
        skipped: bool,
    },
    /// The parameters were evaluated after `step` steps.
    Evaluated {
        /// Steps taken (0 for the initial parameters).
        step: usize,
        /// The objective's metrics.
        metrics: Vec<(String, f64)>,
    },
    /// A checkpoint and the parameter file were written after `step` steps.
    Checkpointed {
        /// Steps taken.
        step: usize,
    },
}

/// What a finished training run produced.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainOutcome {
    /// The trained parameters.
    pub params: ParamStore<f64>,
    /// Steps of the whole run, skipped ones included (`epochs * batches`).
    pub steps: usize,
    /// Steps skipped because the estimate was not finite.
    pub skipped_steps: usize,
    /// The objective's metrics at the trained parameters.
    pub final_eval: Vec<(String, f64)>,
    /// Wall-clock seconds of the run, summed over sessions (work redone after a
    /// resume counts once).
    pub seconds: f64,
}

/// The resumable state of a run, as stored in [`CHECKPOINT_FILE`] (format version
/// [`CHECKPOINT_VERSION`] in the file header).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    /// Steps taken.
    pub step: usize,
    /// The parameters after `step` steps.
    pub params: ParamStore<f64>,
    /// The optimiser's state.
    pub adam: Adam,
    /// Steps skipped so far.
    pub skipped_steps: usize,
    /// The run's settings (a resume must use the same).
    pub config: TrainConfig,
    /// The objective's batches per epoch (a resume must see the same).
    pub batches: usize,
    /// The objective's metric names, the columns of [`EVAL_LOG`] after `step`.
    pub eval_names: Vec<String>,
    /// The latest evaluation: its step and values.
    pub last_eval: (usize, Vec<f64>),
    /// Wall-clock seconds of the run so far.
    pub seconds: f64,
}

impl Checkpoint {
    /// Reads a checkpoint; a missing file is [`TrainError::NoCheckpoint`], an
    /// unreadable or damaged one [`TrainError::Checkpoint`].
    pub fn load(path: &Path) -> Result<Checkpoint, TrainError> {
        read_versioned(path, CHECKPOINT_VERSION).map_err(|source| match source {
            ParamError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
                TrainError::NoCheckpoint { path: path.to_path_buf() }
            }
            source => TrainError::Checkpoint { path: path.to_path_buf(), source },
        })
    }

    /// Writes the checkpoint atomically (temporary file, then rename).
    pub fn save(&self, path: &Path) -> Result<(), TrainError> {
        write_versioned(path, CHECKPOINT_VERSION, self)
            .map_err(|source| TrainError::Checkpoint { path: path.to_path_buf(), source })
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
    /// [`Objective::estimate`] failed (other than by a non-finite estimate), or
    /// returned gradients that do not match the parameters.
    Estimate {
        /// The step (from 1).
        step: usize,
        /// The batch.
        batch: usize,
        /// The objective's message.
        message: String,
    },
    /// [`Objective::evaluate`] failed or changed its metric names.
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

/// Stream tags, so the step seeds, evaluation seeds and batch orders of one run
/// are unrelated.
const STEP_STREAM: u64 = 0x5354_4550; // "STEP"
const EVAL_STREAM: u64 = 0x4556_414c; // "EVAL"
const ORDER_STREAM: u64 = 0x4f52_4452; // "ORDR"

fn derive_seed(seed: u64, stream: u64, index: u64) -> u64 {
    splitmix64(splitmix64(seed ^ splitmix64(stream)) ^ index)
}

/// The seed [`train`] passes to [`Objective::estimate`] at step `step` (from 1): a
/// fixed function of the run's seed and the step.
///
/// ```
/// use ssm::training::step_seed;
/// assert_eq!(step_seed(7, 3), step_seed(7, 3));
/// assert_ne!(step_seed(7, 3), step_seed(7, 4));
/// assert_ne!(step_seed(7, 3), step_seed(8, 3));
/// ```
pub fn step_seed(seed: u64, step: usize) -> u64 {
    derive_seed(seed, STEP_STREAM, step as u64)
}

/// The seed [`train`] passes to [`Objective::evaluate`] after `step` steps.
pub fn eval_seed(seed: u64, step: usize) -> u64 {
    derive_seed(seed, EVAL_STREAM, step as u64)
}

/// The order in which epoch `epoch` visits batches `0..batches`: a permutation
/// drawn from `(seed, epoch)` (Fisher–Yates on a SplitMix64 stream, independent of
/// the `rand` crate's version), or `0..batches` without shuffling.
///
/// ```
/// use ssm::training::epoch_order;
/// let mut o = epoch_order(1, 0, 10, true);
/// assert_ne!(o, epoch_order(1, 1, 10, true));
/// o.sort();
/// assert_eq!(o, (0..10).collect::<Vec<_>>());
/// assert_eq!(epoch_order(1, 0, 3, false), vec![0, 1, 2]);
/// ```
pub fn epoch_order(seed: u64, epoch: usize, batches: usize, shuffle: bool) -> Vec<usize> {
    let mut order: Vec<usize> = (0..batches).collect();
    if shuffle {
        let mut state = derive_seed(seed, ORDER_STREAM, epoch as u64);
        for i in (1..batches).rev() {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            // Multiply-shift: uniform on 0..=i up to a bias below (i + 1) / 2^64.
            let j = ((splitmix64(state) as u128 * (i as u128 + 1)) >> 64) as usize;
            order.swap(i, j);
        }
    }
    order
}

/// A CSV log appended and flushed row by row.
struct CsvLog {
    path: PathBuf,
    writer: csv::Writer<File>,
}

impl CsvLog {
    /// Creates `path` (which must not exist) holding `header`.
    fn create(path: &Path, header: &[String]) -> Result<Self, TrainError> {
        let file = File::create_new(path).map_err(|source| TrainError::Io { path: path.to_path_buf(), source })?;
        let mut log = CsvLog { path: path.to_path_buf(), writer: csv::WriterBuilder::new().from_writer(file) };
        log.row(header)?;
        Ok(log)
    }

    /// Opens `path` for appending.
    fn append(path: &Path) -> Result<Self, TrainError> {
        let file = OpenOptions::new()
            .append(true)
            .open(path)
            .map_err(|source| TrainError::Io { path: path.to_path_buf(), source })?;
        Ok(CsvLog { path: path.to_path_buf(), writer: csv::WriterBuilder::new().from_writer(file) })
    }

    fn row(&mut self, fields: &[String]) -> Result<(), TrainError> {
        let path = &self.path;
        let err = |e: &dyn fmt::Display| TrainError::Log { path: path.clone(), reason: format!("cannot write: {e}") };
        self.writer.write_record(fields).map_err(|e| err(&e))?;
        self.writer.flush().map_err(|e| err(&e))
    }
}

/// Rewrites the log at `path` keeping its header (which must be `header`) and the
/// complete rows with `step <= last_step`; a missing or empty log is created with
/// the header alone. Then opens it for appending.
fn truncate_log(path: &Path, header: &[String], last_step: usize) -> Result<CsvLog, TrainError> {
    let log_err = |reason: String| TrainError::Log { path: path.to_path_buf(), reason };
    let io_err = |source| TrainError::Io { path: path.to_path_buf(), source };
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(io_err(e)),
    };
    let mut reader = csv::ReaderBuilder::new().has_headers(false).flexible(true).from_reader(bytes.as_slice());
    let mut kept = Vec::new();
    let mut records = reader.byte_records();
    if let Some(head) = records.next() {
        let head = head.map_err(|e| log_err(e.to_string()))?;
        if !head.iter().eq(header.iter().map(|h| h.as_bytes())) {
            let found: Vec<String> = head.iter().map(|f| String::from_utf8_lossy(f).into_owned()).collect();
            return Err(log_err(format!("header {found:?} is not the expected {header:?}")));
        }
        for record in records {
            // A row cut short by a crash has too few fields or a damaged step; any
            // row after the checkpoint is dropped anyway.
            let record = record.map_err(|e| log_err(e.to_string()))?;
            let step = record.get(0).and_then(|f| std::str::from_utf8(f).ok()).and_then(|s| s.parse::<usize>().ok());
            if record.len() == header.len() && step.is_some_and(|s| s <= last_step) {
                kept.push(record);
            }
        }
    }
    let tmp = path.with_extension("csv.tmp");
    {
        let file = File::create(&tmp).map_err(|source| TrainError::Io { path: tmp.clone(), source })?;
        let mut w = csv::WriterBuilder::new().from_writer(file);
        let werr = |e: &dyn fmt::Display| TrainError::Log { path: tmp.clone(), reason: format!("cannot write: {e}") };
        w.write_record(header).map_err(|e| werr(&e))?;
        for r in &kept {
            w.write_byte_record(r).map_err(|e| werr(&e))?;
        }
        w.flush().map_err(|e| werr(&e))?;
    }
    std::fs::rename(&tmp, path).map_err(io_err)?;
    CsvLog::append(path)
}

/// Shortest round-trip text of a float (`NaN`, `inf` and `-inf` included).
fn num(x: f64) -> String {
    format!("{x}")
}

/// Per-unit log-likelihood, NaN without units.
fn per_unit(ll: f64, units: usize) -> f64 {
    if units > 0 {
        ll / units as f64
    } else {
        f64::NAN
    }
}

/// The mutable state of a run between steps.
struct Run<'a, O: Objective + ?Sized> {
    objective: &'a mut O,
    config: &'a TrainConfig,
    batches: usize,
    dir: &'a Path,
    params: ParamStore<f64>,
    adam: Adam,
    skipped: usize,
    eval_names: Option<Vec<String>>,
    last_eval: (usize, Vec<f64>),
    prior_seconds: f64,
    started: Instant,
    /// Created after the initial evaluation of a fresh run.
    train_log: Option<CsvLog>,
    eval_log: Option<CsvLog>,
}

impl<O: Objective + ?Sized> Run<'_, O> {
    fn seconds(&self) -> f64 {
        self.prior_seconds + self.started.elapsed().as_secs_f64()
    }

    /// One step: estimate, guard, clip, update, log.
    fn step(&mut self, step: usize, batch: usize, epoch: usize) -> Result<TrainEvent, TrainError> {
        let t0 = Instant::now();
        let estimate_err = |message: String| TrainError::Estimate { step, batch, message };
        let seed = step_seed(self.config.seed, step);
        let (ll, units, collapsed, grad_norm, clipped, skipped) =
            match self.objective.estimate(&self.params, batch, seed) {
                Ok(est) => {
                    let mut grad = est.gradient;
                    if grad.len() != self.params.len() {
                        return Err(estimate_err(format!(
                            "{} gradients for {} parameters",
                            grad.len(),
                            self.params.len()
                        )));
                    }
                    for ((name, p), g) in self.params.iter().zip(&grad) {
                        if g.shape() != p.shape() {
                            return Err(estimate_err(format!(
                                "gradient of `{name}` has shape {:?}, the parameter {:?}",
                                g.shape(),
                                p.shape()
                            )));
                        }
                    }
                    // Checked before clipping: scaling by a NaN norm would poison
                    // every coordinate.
                    let finite = est.log_likelihood.is_finite() && grad.iter().all(|g| g.all_finite());
                    let norm = match self.config.clip {
                        Some(c) if finite => clip_global_norm(&mut grad, c),
                        _ => global_norm(&grad),
                    };
                    let clipped = finite && self.config.clip.is_some_and(|c| norm > c);
                    let mut skipped = !finite;
                    if finite {
                        // Adam minimises; the score is ascended.
                        for g in grad.iter_mut() {
                            g.data_mut().iter_mut().for_each(|x| *x = -*x);
                        }
                        self.adam.lr = self.config.lr_at(step, self.config.epochs * self.batches);
                        match self.adam.step(&mut self.params, &grad) {
                            Ok(()) => {}
                            Err(StepError::NonFinite) => skipped = true,
                            Err(e @ StepError::Layout(_)) => return Err(estimate_err(e.to_string())),
                        }
                    }
                    (est.log_likelihood, est.observed_units, est.collapsed_steps, norm, clipped, skipped)
                }
                Err(EstimateError::NonFinite(_)) => (f64::NAN, 0, 0, f64::NAN, false, true),
                Err(EstimateError::Failed(message)) => return Err(estimate_err(message)),
            };
        if skipped {
            self.skipped += 1;
        }
        let ll_per_unit = per_unit(ll, units);
        let flag = |b: bool| if b { "1" } else { "0" }.to_string();
        self.train_log.as_mut().expect("created before the first step").row(&[
            step.to_string(),
            epoch.to_string(),
            batch.to_string(),
            num(ll),
            units.to_string(),
            num(ll_per_unit),
            num(grad_norm),
            flag(clipped),
            flag(skipped),
            collapsed.to_string(),
            num(t0.elapsed().as_secs_f64()),
        ])?;
        Ok(TrainEvent::Step { step, ll_per_unit, grad_norm, skipped })
    }

    /// Evaluates after `step` steps and logs the row (creating the log at the first
    /// evaluation of a fresh run).
    fn evaluate(&mut self, step: usize) -> Result<TrainEvent, TrainError> {
        let metrics = self
            .objective
            .evaluate(&self.params, eval_seed(self.config.seed, step))
            .map_err(|message| TrainError::Evaluate { step, message })?;
        let names: Vec<String> = metrics.iter().map(|(n, _)| n.clone()).collect();
        match &self.eval_names {
            Some(expected) if *expected != names => {
                return Err(TrainError::Evaluate {
                    step,
                    message: format!("metric names changed from {expected:?} to {names:?}"),
                })
            }
            Some(_) => {}
            None => self.eval_names = Some(names.clone()),
        }
        if self.eval_log.is_none() {
            let header: Vec<String> = std::iter::once("step".to_string()).chain(names).collect();
            self.eval_log = Some(CsvLog::create(&self.dir.join(EVAL_LOG), &header)?);
        }
        let row: Vec<String> = std::iter::once(step.to_string()).chain(metrics.iter().map(|(_, v)| num(*v))).collect();
        self.eval_log.as_mut().expect("created above").row(&row)?;
        self.last_eval = (step, metrics.iter().map(|(_, v)| *v).collect());
        Ok(TrainEvent::Evaluated { step, metrics })
    }

    /// Writes the checkpoint, then the parameter file.
    fn checkpoint(&mut self, step: usize) -> Result<TrainEvent, TrainError> {
        let ckpt = Checkpoint {
            step,
            params: self.params.clone(),
            adam: self.adam.clone(),
            skipped_steps: self.skipped,
            config: self.config.clone(),
            batches: self.batches,
            eval_names: self.eval_names.clone().unwrap_or_default(),
            last_eval: self.last_eval.clone(),
            seconds: self.seconds(),
        };
        ckpt.save(&self.dir.join(CHECKPOINT_FILE))?;
        let path = self.dir.join(PARAMS_FILE);
        self.params.save(&path).map_err(|source| TrainError::Checkpoint { path, source })?;
        Ok(TrainEvent::Checkpointed { step })
    }

    fn final_eval(&self) -> Vec<(String, f64)> {
        let names = self.eval_names.clone().unwrap_or_default();
        names.into_iter().zip(self.last_eval.1.iter().copied()).collect()
    }
}

/// Trains `initial` on `objective` with Adam, writing logs and checkpoints into
/// `out_dir` (created if needed) and reporting progress through `on_event`.
///
/// With `resume`, the run continues from `out_dir`'s checkpoint (whose parameters
/// replace `initial`, which must have the same layout) after dropping the log rows
/// written after it; the config and the objective's batch count and metric names
/// must be those of the checkpoint. Without `resume`, a directory that already holds
/// a run is refused. See the [module documentation](self) for the schedule, the
/// files and the handling of non-finite estimates.
pub fn train(
    objective: &mut (impl Objective + ?Sized),
    initial: ParamStore<f64>,
    config: &TrainConfig,
    out_dir: &Path,
    resume: bool,
    on_event: &mut dyn FnMut(&TrainEvent),
) -> Result<TrainOutcome, TrainError> {
    config.validate()?;
    let batches = objective.batches();
    if batches == 0 && config.epochs > 0 {
        return Err(TrainError::Config("the objective has no batches to train on".into()));
    }
    let total = config.epochs * batches;
    std::fs::create_dir_all(out_dir).map_err(|source| TrainError::Io { path: out_dir.to_path_buf(), source })?;
    let started = Instant::now();
    let ckpt_path = out_dir.join(CHECKPOINT_FILE);
    let train_header: Vec<String> = TRAIN_LOG_HEADER.iter().map(|s| s.to_string()).collect();

    let (mut run, done) = if resume {
        let ckpt = Checkpoint::load(&ckpt_path)?;
        let differences = ckpt.config.differences(config);
        if !differences.is_empty() {
            return Err(TrainError::ConfigChanged { path: ckpt_path, differences });
        }
        if ckpt.batches != batches {
            return Err(TrainError::Incompatible {
                path: ckpt_path,
                reason: format!(
                    "the checkpoint was written for {} batches per epoch, the objective has {batches}",
                    ckpt.batches
                ),
            });
        }
        if let Err(e) = ckpt.params.check_same_layout(&initial) {
            return Err(TrainError::Incompatible { path: ckpt_path, reason: e.to_string() });
        }
        if ckpt.step > total {
            return Err(TrainError::Incompatible {
                path: ckpt_path,
                reason: format!("the checkpoint is at step {}, past the run's {total} steps", ckpt.step),
            });
        }
        let eval_header: Vec<String> = std::iter::once("step".to_string()).chain(ckpt.eval_names.clone()).collect();
        let train_log = truncate_log(&out_dir.join(TRAIN_LOG), &train_header, ckpt.step)?;
        let eval_log = truncate_log(&out_dir.join(EVAL_LOG), &eval_header, ckpt.step)?;
        let run = Run {
            objective,
            config,
            batches,
            dir: out_dir,
            params: ckpt.params,
            adam: ckpt.adam,
            skipped: ckpt.skipped_steps,
            eval_names: Some(ckpt.eval_names),
            last_eval: ckpt.last_eval,
            prior_seconds: ckpt.seconds,
            started,
            train_log: Some(train_log),
            eval_log: Some(eval_log),
        };
        (run, ckpt.step)
    } else {
        for name in [CHECKPOINT_FILE, TRAIN_LOG, EVAL_LOG, PARAMS_FILE] {
            let path = out_dir.join(name);
            if path.exists() {
                return Err(TrainError::Exists { path });
            }
        }
        let run = Run {
            objective,
            config,
            batches,
            dir: out_dir,
            params: initial,
            adam: Adam::new(config.lr),
            skipped: 0,
            eval_names: None,
            last_eval: (0, Vec::new()),
            prior_seconds: 0.0,
            started,
            train_log: None,
            eval_log: None,
        };
        (run, 0)
    };

    on_event(&TrainEvent::Started { total_steps: total, first_step: done + 1 });
    if !resume {
        // Nothing is written before the objective has evaluated the initial
        // parameters, so a run that fails at once leaves no files to refuse later.
        on_event(&run.evaluate(0)?);
        run.train_log = Some(CsvLog::create(&out_dir.join(TRAIN_LOG), &train_header)?);
        on_event(&run.checkpoint(0)?);
    }
    let mut order = Vec::new();
    let mut order_epoch = usize::MAX;
    for step in done + 1..=total {
        let epoch = (step - 1) / batches;
        if epoch != order_epoch {
            order = epoch_order(config.seed, epoch, batches, config.shuffle);
            order_epoch = epoch;
        }
        let batch = order[(step - 1) % batches];
        on_event(&run.step(step, batch, epoch)?);
        if config.eval_due(step, total) {
            on_event(&run.evaluate(step)?);
        }
        if config.checkpoint_due(step, total) {
            on_event(&run.checkpoint(step)?);
        }
    }
    Ok(TrainOutcome {
        final_eval: run.final_eval(),
        seconds: run.seconds(),
        steps: total,
        skipped_steps: run.skipped,
        params: run.params,
    })
}
