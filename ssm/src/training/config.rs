//! The settings of a training run ([`TrainConfig`]): learning rate and its
//! schedule, clipping, epochs, evaluation and checkpoint periods, seed.

use serde::{Deserialize, Serialize};

use super::TrainError;

/// Settings of [`train`](super::train). A resumed run must use the same settings.
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
    /// If set, the name of an evaluation metric to maximise: the run keeps the
    /// parameters of its best evaluation (the initial ones included) and returns
    /// them rather than the last ones (default none: the last). Evaluations come
    /// every `eval_every` steps, so that period is the resolution of the choice.
    /// A fit that wanders off (a sharp policy on a few paths, SPEC §6) then
    /// returns where it was best on the evaluation data, and the outcome says
    /// how far the last evaluation fell below it ([`super::KeptBest`]).
    pub keep_best: Option<String>,
    /// The share of the run's last steps whose iterates are averaged
    /// (Polyak–Ruppert tail averaging; default 0: none). From
    /// [`TrainConfig::average_start`] on, the run keeps the running mean of the
    /// parameters after each step; evaluations from then on evaluate that mean,
    /// and the run returns it (or, with [`TrainConfig::keep_best`], whichever
    /// evaluation was best). A stochastic-gradient run whose rate has not reached
    /// zero ends at one noisy draw around where it settled; the mean of its last
    /// iterates has a fraction of that spread, so two runs that differ only in
    /// their seeds end closer together.
    pub average_tail: f64,
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
            keep_best: None,
            average_tail: 0.0,
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
        cmp("keep_best", format!("{:?}", self.keep_best), format!("{:?}", other.keep_best));
        cmp("average_tail", format!("{:?}", self.average_tail), format!("{:?}", other.average_tail));
        out
    }

    pub(super) fn validate(&self) -> Result<(), TrainError> {
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return Err(TrainError::Config(format!("learning rate must be positive and finite, got {}", self.lr)));
        }
        if let Some(end) = self.final_lr {
            if !(end.is_finite() && end > 0.0) {
                return Err(TrainError::Config(format!("final learning rate must be positive and finite, got {end}")));
            }
        }
        if !(self.average_tail.is_finite() && (0.0..=1.0).contains(&self.average_tail)) {
            return Err(TrainError::Config(format!("average_tail must be in [0, 1], got {}", self.average_tail)));
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

    /// The first step (from 1) of `total` whose iterate enters the tail average
    /// ([`TrainConfig::average_tail`]): the last `round(average_tail * total)`
    /// steps, at least one; `None` without averaging or steps.
    pub fn average_start(&self, total: usize) -> Option<usize> {
        if self.average_tail <= 0.0 || total == 0 {
            return None;
        }
        let averaged = ((self.average_tail * total as f64).round() as usize).clamp(1, total);
        Some(total - averaged + 1)
    }

    pub(super) fn eval_due(&self, step: usize, total: usize) -> bool {
        step == 0 || step == total || every(step, self.eval_every)
    }

    pub(super) fn checkpoint_due(&self, step: usize, total: usize) -> bool {
        step == 0 || step == total || every(step, self.checkpoint_every)
    }
}

/// Whether `step` is a positive multiple of `period` (never, for period 0).
fn every(step: usize, period: usize) -> bool {
    period > 0 && step.is_multiple_of(period)
}
