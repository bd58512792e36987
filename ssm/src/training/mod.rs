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
//!   from `estimate` skips the step (counted, marked in the log, and its reason
//!   written to [`SKIP_LOG`]); any other error aborts training with the step named.
//! * **Clipping.** With `clip` set the global norm of the score is clipped before
//!   the update; the log records the norm before clipping.
//! * **Keeping the best.** With [`TrainConfig::keep_best`] naming an evaluation
//!   metric, the run returns the parameters of its best evaluation rather than its
//!   last ([`TrainOutcome::kept`] says where and how far the run fell after it).
//! * **Averaging the tail.** With [`TrainConfig::average_tail`] the run keeps the
//!   running mean of its last iterates (Polyak–Ruppert averaging), evaluates that
//!   mean from the tail's first step on and returns it (or keep-best's choice).
//! * **Files in `out_dir`.** [`TRAIN_LOG`] (one row per step, header
//!   [`TRAIN_LOG_HEADER`]) and [`EVAL_LOG`] (`step` then the objective's metric
//!   names; a row at step 0, every `eval_every` steps and at the end) are appended
//!   and flushed row by row, so a crash loses at most the row being written.
//!   [`CHECKPOINT_FILE`] (a [`Checkpoint`], versioned, checksummed, written
//!   atomically) and [`PARAMS_FILE`] (the store alone, for `sefi eval --params`) are
//!   written at step 0, every `checkpoint_every` steps and at the end; with
//!   [`TrainConfig::keep_best`], [`PARAMS_FILE`] finally holds the kept parameters,
//!   with [`TrainConfig::average_tail`] alone the tail's mean (the checkpoint holds
//!   the last iterate and the running mean, to resume from).
//! * **Resuming** reads the checkpoint, refuses a different config, drops the log
//!   rows written after it and carries on. Starting afresh in a directory that holds
//!   a run is refused rather than overwriting it.
//!
//! The loop lives here; its settings ([`TrainConfig`], `config.rs`), its errors
//! (`error.rs`), its seeds and batch orders (`seeds.rs`) and its files
//! ([`Checkpoint`] and the CSV logs, `checkpoint.rs`) each have their own file.
//! Two learners stand on it: [`objective`], the road-user model of a dataset
//! learned through a score estimator, and [`supervised`], an observation network
//! fitted to a dataset's labelled states.
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

mod checkpoint;
mod config;
mod error;
pub mod objective;
mod seeds;
pub mod supervised;

pub use checkpoint::Checkpoint;
use checkpoint::{num, truncate_log, CsvLog};
pub use config::TrainConfig;
pub use error::{non_finite, EstimateError, TrainError};
pub use seeds::{epoch_order, eval_seed, step_seed};

use std::path::Path;
use std::time::Instant;

use autodiff::nn::ParamStore;
use autodiff::optim::{clip_global_norm, global_norm, Adam, StepError};
use autodiff::Tensor;
use serde::{Deserialize, Serialize};

/// The per-step log, one row per step.
pub const TRAIN_LOG: &str = "train.csv";
/// The evaluation log: `step`, then the objective's metric names.
pub const EVAL_LOG: &str = "eval.csv";
/// The resumable training state (a [`Checkpoint`]).
pub const CHECKPOINT_FILE: &str = "checkpoint.bin";
/// The parameter store alone, as [`ParamStore::save`] writes it.
pub const PARAMS_FILE: &str = "params.bin";
/// Format version of [`CHECKPOINT_FILE`] (checked by [`autodiff::nn::read_versioned`]).
pub const CHECKPOINT_VERSION: u32 = 4;
/// Why each skipped step was skipped: one row per skip (header
/// [`SKIP_LOG_HEADER`]), created with the train log, cut back on resume as it is.
pub const SKIP_LOG: &str = "skipped.csv";

/// Columns of [`SKIP_LOG`]: the step, its batch and the reason in words (e.g.
/// `gradient not finite in policy.0.w, policy.2.b`).
pub const SKIP_LOG_HEADER: [&str; 3] = ["step", "batch", "reason"];

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
    fn estimate(&mut self, params: &ParamStore<f64>, batch: usize, seed: u64) -> Result<BatchEstimate, EstimateError>;

    /// Test metrics, e.g. `[("test_mll", -1.5)]`; the names are the columns of
    /// [`EVAL_LOG`] and must be the same, in the same order, on every call.
    fn evaluate(&mut self, params: &ParamStore<f64>, seed: u64) -> Result<Vec<(String, f64)>, String>;

    /// Multiples of the learning rate at which each of `params`' tensors moves,
    /// in store order (`None`, the default: every tensor at the rate). A refit
    /// can so continue fitted parameters slowly while new ones learn at the rate.
    fn rate_factors(&self, _params: &ParamStore<f64>) -> Option<Vec<f64>> {
        None
    }

    /// Whether this process writes the run's files: true but on the processes
    /// other than the first of a distributed job, which train alongside it (the
    /// same steps, the same updates) and write nothing.
    fn is_root(&self) -> bool {
        true
    }
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

/// What a training run produced (finished, or paused by [`train_until`]).
#[derive(Clone, Debug, PartialEq)]
pub struct TrainOutcome {
    /// The trained parameters: the last ones (the mean of the tail's iterates
    /// with [`TrainConfig::average_tail`]), or with [`TrainConfig::keep_best`]
    /// those of the best evaluation ([`TrainOutcome::kept`]).
    pub params: ParamStore<f64>,
    /// Steps of the whole run, skipped ones included (`epochs * batches`).
    pub steps: usize,
    /// Steps skipped because the estimate was not finite.
    pub skipped_steps: usize,
    /// Steps this call ran (fewer than `steps` after a resume).
    pub steps_run: usize,
    /// The objective's metrics at the trained parameters.
    pub final_eval: Vec<(String, f64)>,
    /// Wall-clock seconds of the run, summed over sessions (work redone after a
    /// resume counts once).
    pub seconds: f64,
    /// With [`TrainConfig::keep_best`]: the evaluation whose parameters
    /// [`TrainOutcome::params`] are, and the last one.
    pub kept: Option<KeptBest>,
    /// The step the run paused after ([`train_until`]), before its end; `None`
    /// for a finished run.
    pub paused_at: Option<usize>,
}

/// Which parameters a run with [`TrainConfig::keep_best`] returned.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KeptBest {
    /// The metric maximised.
    pub metric: String,
    /// The step of the best evaluation (0: the initial parameters).
    pub step: usize,
    /// Its value.
    pub value: f64,
    /// The value at the last evaluation (the end of the run; NaN when not finite).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub last: f64,
}

impl KeptBest {
    /// How far the last evaluation fell below the best (0 when the run ended at its best).
    pub fn fall(&self) -> f64 {
        self.value - self.last
    }
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
    /// With [`TrainConfig::keep_best`]: the best evaluation so far (step, value, parameters).
    best: Option<(usize, f64, ParamStore<f64>)>,
    /// With [`TrainConfig::average_tail`], once the tail has begun: the iterates
    /// averaged so far and their mean.
    average: Option<(usize, ParamStore<f64>)>,
    /// The first step of the tail average ([`TrainConfig::average_start`]).
    average_start: Option<usize>,
    prior_seconds: f64,
    started: Instant,
    /// Created after the initial evaluation of a fresh run (never on a process
    /// that writes no files).
    train_log: Option<CsvLog>,
    eval_log: Option<CsvLog>,
    skip_log: Option<CsvLog>,
    /// Whether this process writes the run's files ([`Objective::is_root`]).
    writes: bool,
    /// Each tensor's multiple of the rate ([`Objective::rate_factors`]), asked
    /// once: the store's tensors do not change during a run.
    rates: Option<Vec<f64>>,
}

impl<O: Objective + ?Sized> Run<'_, O> {
    fn seconds(&self) -> f64 {
        self.prior_seconds + self.started.elapsed().as_secs_f64()
    }

    /// The parameters the run would return now: the tail's mean once it has
    /// begun ([`TrainConfig::average_tail`]), else the current iterate.
    fn current(&self) -> &ParamStore<f64> {
        self.average.as_ref().map_or(&self.params, |(_, mean)| mean)
    }

    /// Adds the iterate after `step` to the tail's running mean, if the tail has begun.
    fn accumulate(&mut self, step: usize) {
        if self.average_start.is_none_or(|start| step < start) {
            return;
        }
        match self.average.as_mut() {
            None => self.average = Some((1, self.params.clone())),
            Some((count, mean)) => {
                *count += 1;
                let w = 1.0 / *count as f64;
                for (m, p) in mean.values_mut().iter_mut().zip(self.params.values()) {
                    for (a, &b) in m.data_mut().iter_mut().zip(p.data()) {
                        *a += w * (b - *a);
                    }
                }
            }
        }
    }

    /// One step: estimate, guard, clip, update, log.
    fn step(&mut self, step: usize, batch: usize, epoch: usize) -> Result<TrainEvent, TrainError> {
        let t0 = Instant::now();
        let estimate_err = |message: String| TrainError::Estimate { step, batch, message };
        let seed = step_seed(self.config.seed, step);
        let mut skip_reason = None;
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
                    if !finite {
                        skip_reason = Some(non_finite_reason(est.log_likelihood, &self.params, &grad));
                    }
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
                        match self.adam.step_with_rates(&mut self.params, &grad, self.rates.as_deref()) {
                            Ok(()) => {}
                            Err(StepError::NonFinite) => {
                                skipped = true;
                                skip_reason = Some("update not finite".to_string());
                            }
                            Err(e @ StepError::Layout(_)) => return Err(estimate_err(e.to_string())),
                        }
                    }
                    (est.log_likelihood, est.observed_units, est.collapsed_steps, norm, clipped, skipped)
                }
                Err(EstimateError::NonFinite(detail)) => {
                    skip_reason = Some(detail);
                    (f64::NAN, 0, 0, f64::NAN, false, true)
                }
                Err(EstimateError::Failed(message)) => return Err(estimate_err(message)),
            };
        if skipped {
            self.skipped += 1;
            if let Some(log) = self.skip_log.as_mut() {
                let reason = skip_reason.unwrap_or_else(|| "not finite".to_string());
                log.row(&[step.to_string(), batch.to_string(), reason])?;
            }
        }
        let ll_per_unit = per_unit(ll, units);
        let flag = |b: bool| if b { "1" } else { "0" }.to_string();
        if let Some(log) = self.train_log.as_mut() {
            log.row(&[
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
        }
        Ok(TrainEvent::Step { step, ll_per_unit, grad_norm, skipped })
    }

    /// Evaluates after `step` steps and logs the row (creating the log at the first
    /// evaluation of a fresh run).
    fn evaluate(&mut self, step: usize) -> Result<TrainEvent, TrainError> {
        let evaluated = self.average.as_ref().map_or(&self.params, |(_, mean)| mean);
        let metrics = self
            .objective
            .evaluate(evaluated, eval_seed(self.config.seed))
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
        self.last_eval = (step, metrics.iter().map(|(_, v)| *v).collect());
        if let Some(name) = &self.config.keep_best {
            let value = metrics.iter().find(|(n, _)| n == name).map(|(_, v)| *v).ok_or_else(|| {
                TrainError::Evaluate { step, message: format!("no metric {name:?} to keep the best by in {names:?}") }
            })?;
            // A non-finite evaluation is never the best; the first finite one is.
            let better = value.is_finite() && self.best.as_ref().is_none_or(|(_, b, _)| value > *b);
            if better {
                self.best = Some((step, value, self.current().clone()));
            }
        }
        if !self.writes {
            return Ok(TrainEvent::Evaluated { step, metrics });
        }
        if self.eval_log.is_none() {
            let header: Vec<String> = std::iter::once("step".to_string()).chain(names).collect();
            self.eval_log = Some(CsvLog::create(&self.dir.join(EVAL_LOG), &header)?);
        }
        let row: Vec<String> = std::iter::once(step.to_string()).chain(metrics.iter().map(|(_, v)| num(*v))).collect();
        self.eval_log.as_mut().expect("created above").row(&row)?;
        Ok(TrainEvent::Evaluated { step, metrics })
    }

    /// Writes the checkpoint, then the parameter file (on the writing process).
    fn checkpoint(&mut self, step: usize) -> Result<TrainEvent, TrainError> {
        if !self.writes {
            return Ok(TrainEvent::Checkpointed { step });
        }
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
            best: self.best.clone(),
            average: self.average.clone(),
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
    train_until(objective, initial, config, out_dir, resume, None, on_event)
}

/// [`train`], paused after step `until` when that comes before the run's end:
/// the run checkpoints there and returns what it would return if it ended
/// then (the best evaluation so far with [`TrainConfig::keep_best`], among
/// those at or before `until`), with [`TrainOutcome::paused_at`] set. A later
/// call with `resume` continues it from there exactly as if it had not paused:
/// the schedule is the whole run's. A run whose checkpoint is already at or past
/// `until` takes no step and is returned as its checkpoint left it (paused
/// there, or finished).
pub fn train_until(
    objective: &mut (impl Objective + ?Sized),
    initial: ParamStore<f64>,
    config: &TrainConfig,
    out_dir: &Path,
    resume: bool,
    until: Option<usize>,
    on_event: &mut dyn FnMut(&TrainEvent),
) -> Result<TrainOutcome, TrainError> {
    config.validate()?;
    let batches = objective.batches();
    if batches == 0 && config.epochs > 0 {
        return Err(TrainError::Config("the objective has no batches to train on".into()));
    }
    let total = config.epochs * batches;
    let writes = objective.is_root();
    std::fs::create_dir_all(out_dir).map_err(|source| TrainError::Io { path: out_dir.to_path_buf(), source })?;
    let started = Instant::now();
    let ckpt_path = out_dir.join(CHECKPOINT_FILE);
    let train_header: Vec<String> = TRAIN_LOG_HEADER.iter().map(|s| s.to_string()).collect();
    let skip_header: Vec<String> = SKIP_LOG_HEADER.iter().map(|s| s.to_string()).collect();

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
        let (train_log, eval_log, skip_log) = if writes {
            (
                Some(truncate_log(&out_dir.join(TRAIN_LOG), &train_header, ckpt.step)?),
                Some(truncate_log(&out_dir.join(EVAL_LOG), &eval_header, ckpt.step)?),
                // Runs written before the skip log existed get one from here on.
                Some(truncate_log(&out_dir.join(SKIP_LOG), &skip_header, ckpt.step)?),
            )
        } else {
            (None, None, None)
        };
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
            best: ckpt.best,
            average: ckpt.average,
            average_start: config.average_start(total),
            prior_seconds: ckpt.seconds,
            started,
            train_log,
            eval_log,
            skip_log,
            writes,
            rates: None,
        };
        (run, ckpt.step)
    } else {
        for name in [CHECKPOINT_FILE, TRAIN_LOG, EVAL_LOG, SKIP_LOG, PARAMS_FILE] {
            let path = out_dir.join(name);
            if writes && path.exists() {
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
            best: None,
            average: None,
            average_start: config.average_start(total),
            prior_seconds: 0.0,
            started,
            train_log: None,
            eval_log: None,
            skip_log: None,
            writes,
            rates: None,
        };
        (run, 0)
    };

    run.rates = run.objective.rate_factors(&run.params);
    on_event(&TrainEvent::Started { total_steps: total, first_step: done + 1 });
    if !resume {
        // Nothing is written before the objective has evaluated the initial
        // parameters, so a run that fails at once leaves no files to refuse later.
        on_event(&run.evaluate(0)?);
        if writes {
            run.train_log = Some(CsvLog::create(&out_dir.join(TRAIN_LOG), &train_header)?);
            run.skip_log = Some(CsvLog::create(&out_dir.join(SKIP_LOG), &skip_header)?);
        }
        on_event(&run.checkpoint(0)?);
    }
    // The last step this call takes: the run's last, or the pause.
    let stop = until.map_or(total, |until| until.min(total)).max(done);
    let mut order = Vec::new();
    let mut order_epoch = usize::MAX;
    for step in done + 1..=stop {
        let epoch = (step - 1) / batches;
        if epoch != order_epoch {
            order = epoch_order(config.seed, epoch, batches, config.shuffle);
            order_epoch = epoch;
        }
        let batch = order[(step - 1) % batches];
        on_event(&run.step(step, batch, epoch)?);
        run.accumulate(step);
        if config.eval_due(step, total) {
            on_event(&run.evaluate(step)?);
        }
        if config.checkpoint_due(step, total) {
            on_event(&run.checkpoint(step)?);
        }
    }
    if stop > done && !config.checkpoint_due(stop, total) {
        // A pause between checkpoints: the resumed run starts here.
        on_event(&run.checkpoint(stop)?);
    }
    let final_eval = run.final_eval();
    let (seconds, skipped_steps) = (run.seconds(), run.skipped);
    let (params, kept) = match (&config.keep_best, run.best) {
        (Some(metric), Some((step, value, params))) => {
            let last = final_eval.iter().find(|(n, _)| n == metric).map_or(f64::NAN, |(_, v)| *v);
            if writes {
                let path = out_dir.join(PARAMS_FILE);
                params.save(&path).map_err(|source| TrainError::Checkpoint { path, source })?;
            }
            (params, Some(KeptBest { metric: metric.clone(), step, value, last }))
        }
        // No finite evaluation at all: the last parameters (or the tail's mean),
        // as without the setting.
        _ => {
            let params = match run.average {
                Some((_, mean)) => {
                    if writes {
                        let path = out_dir.join(PARAMS_FILE);
                        mean.save(&path).map_err(|source| TrainError::Checkpoint { path, source })?;
                    }
                    mean
                }
                None => run.params,
            };
            (params, None)
        }
    };
    let paused_at = (stop < total).then_some(stop);
    Ok(TrainOutcome {
        final_eval,
        seconds,
        steps: total,
        skipped_steps,
        steps_run: stop - done,
        params,
        kept,
        paused_at,
    })
}

/// Why an estimate is not finite, in words: the log-likelihood's value and the
/// parameters whose gradient holds NaN or an infinity.
fn non_finite_reason(log_likelihood: f64, params: &ParamStore<f64>, grad: &[Tensor<f64>]) -> String {
    let mut parts = Vec::new();
    if !log_likelihood.is_finite() {
        parts.push(format!("log-likelihood {log_likelihood}"));
    }
    let names: Vec<&str> =
        params.iter().zip(grad).filter(|(_, g)| !g.all_finite()).map(|((name, _), _)| name).collect();
    if !names.is_empty() {
        parts.push(format!("gradient not finite in {}", names.join(", ")));
    }
    parts.join("; ")
}
