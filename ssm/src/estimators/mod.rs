//! Score estimators (SPEC §2): PF-SEFI and the through-filter baselines (PF,
//! DPF-SGR in two variants, PFNET), behind one trait, [`ScoreEstimator`], over any
//! model that can evaluate its log-densities on a tape
//! ([`DifferentiableModel`], defined with the models in [`crate::models`]).
//!
//! Every estimator runs the same bootstrap particle filter
//! ([`crate::filter::filter_object`]) with the same per-object random streams, so
//! on one seed they see the same draws. They differ in what they differentiate:
//!
//! | estimator | gradient of | time per object | memory |
//! |---|---|---|---|
//! | [`PfSefi`] | the Fisher surrogate over distinct fixed-lag ancestors (one reverse pass) | filter `O(N T)` plus the surrogate over `A` distinct ancestors (`A` is a few per cent of `N T`) | filter ring `O(N L)`, surrogate tape `O(A)` |
//! | [`ThroughFilter`] (PF, DPF-SGR, PFNET) | `l_hat` replayed on a tape through every step | filter plus a tape forward and backward over all `N T` particles | `O(N T)` tape per object in a chunk: `O(C N T)` per thread for chunks of `C` objects |
//!
//! Objects are independent, so all estimators sum per-object gradients; the
//! baselines process objects in chunks of [`EstimatorConfig::chunk_objects`] (one
//! tape per chunk, freed before the next), so their memory grows with `N`, `T` and
//! the chunk size but not with the number of objects. Work is spread over the
//! rayon pool by object (PF-SEFI) or by chunk (baselines). Each estimator returns
//! one partial sum per *block* of [`EstimatorConfig::chunk_objects`] consecutive
//! objects (a [`PartialEstimate`]), and [`PartialEstimate::reduce`] adds the blocks
//! exactly ([`crate::util::reduce`]): the estimate has the same bits for any number of
//! threads, and for any number of processes that each hold some of the blocks.
//!
//! The estimate of each is the gradient of the total log-likelihood of the
//! objects (the sum over objects, not a mean); `l_hat` is reported with it. The
//! PF-SEFI score is not the gradient of `l_hat`.

mod replay;
mod sefi;
pub mod study;

use autodiff::{Float, Tape, Tensor, Var};
use serde::{Deserialize, Serialize};

use crate::filter::{FilterConfig, Sampling};
use crate::models::DifferentiableModel;
use crate::util::reduce::{exact_sum, Collective, SingleProcess};
use crate::util::setting::SettingError;

pub use replay::{ThroughFilter, ThroughFilterKind};
pub use sefi::PfSefi;

/// Floating-point type of the estimators' tapes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum Precision {
    /// Single precision: the fast path for training.
    #[default]
    F32,
    /// Double precision: for checks against exact scores.
    F64,
}

/// Settings shared by every estimator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EstimatorConfig {
    /// The filter's particles, resampling and tempering (the tempered filter for
    /// PF-SEFI only: the through-filter baselines need the bootstrap filter, which
    /// they replay on a tape).
    #[serde(flatten)]
    pub sampling: Sampling,
    /// Objects per tape of the through-filter baselines, and per block of the
    /// exact reduction for every estimator ([`PartialEstimate`]).
    pub chunk_objects: usize,
    /// Tape precision.
    pub precision: Precision,
}

impl Default for EstimatorConfig {
    fn default() -> Self {
        EstimatorConfig { sampling: Sampling::default(), chunk_objects: 4, precision: Precision::F32 }
    }
}

impl EstimatorConfig {
    /// The default settings with `sampling`.
    pub fn new(sampling: Sampling) -> Self {
        EstimatorConfig { sampling, ..EstimatorConfig::default() }
    }

    /// The filter settings for `seed`, lag `lag` and optional soft resampling.
    pub fn filter(&self, seed: u64, lag: usize, soft_resampling: Option<f64>) -> FilterConfig {
        FilterConfig { sampling: self.sampling, lag, seed, soft_resampling }
    }
}

/// A score estimate for a batch of objects.
#[derive(Clone, Debug, PartialEq)]
pub struct ScoreEstimate {
    /// `l_hat`, summed over objects.
    pub log_likelihood: f64,
    /// Observed units (points, detections) that entered `l_hat`.
    pub observed_units: usize,
    /// The estimated score, one tensor per parameter (as
    /// [`DifferentiableModel::parameters`]).
    pub gradient: Vec<Tensor<f64>>,
    /// Steps at which every particle of an object was impossible.
    pub collapsed_steps: usize,
    /// Particle rows the estimator evaluated on the tape (PF-SEFI: distinct
    /// ancestors; the baselines: every particle at every step).
    pub rows_evaluated: usize,
    /// `N x (T + 1) x objects`: the particle slots of the filter.
    pub particle_slots: usize,
}

impl ScoreEstimate {
    /// Whether the log-likelihood and every gradient entry are finite.
    pub fn is_finite(&self) -> bool {
        self.log_likelihood.is_finite() && self.gradient.iter().all(|g| g.all_finite())
    }
}

/// One block's share of a [`ScoreEstimate`]: its objects' sums, in object order.
#[derive(Clone, Debug, PartialEq)]
pub struct BlockEstimate {
    /// `l_hat` of the block's objects.
    pub log_likelihood: f64,
    /// Their score, flattened in parameter order.
    pub gradient: Vec<f64>,
    /// Observed units.
    pub observed_units: usize,
    /// Collapsed steps.
    pub collapsed_steps: usize,
    /// Particle rows evaluated on the tape.
    pub rows_evaluated: usize,
    /// Particle slots of the filter.
    pub particle_slots: usize,
}

impl BlockEstimate {
    /// A block with nothing in it yet, for `params` parameter values.
    fn zero(params: usize) -> Self {
        BlockEstimate {
            log_likelihood: 0.0,
            gradient: vec![0.0; params],
            observed_units: 0,
            collapsed_steps: 0,
            rows_evaluated: 0,
            particle_slots: 0,
        }
    }

    /// Adds one object's (or one tape's) gradient, tensor by tensor in parameter order.
    fn add_gradient<F: Float>(&mut self, grads: &[Tensor<F>]) {
        let flat = grads.iter().flat_map(|g| g.data().iter());
        for (a, &g) in self.gradient.iter_mut().zip(flat) {
            *a += g.to_f64();
        }
    }

    /// Adds one object's filter summary.
    fn add_summary(&mut self, s: &crate::filter::ObjectSummary) {
        self.log_likelihood += s.log_likelihood;
        self.observed_units += s.observed_units;
        self.collapsed_steps += s.collapsed_steps;
    }
}

/// The blocks of a score estimate that this process computed; [`Self::reduce`]
/// adds them, with those of every other process, into the [`ScoreEstimate`].
#[derive(Clone, Debug, PartialEq)]
pub struct PartialEstimate {
    /// Shapes of the parameter tensors (as [`DifferentiableModel::parameters`]).
    pub shapes: Vec<Vec<usize>>,
    /// Partial sums, one per block of consecutive objects.
    pub blocks: Vec<BlockEstimate>,
}

impl PartialEstimate {
    /// No blocks, for parameters of `shapes`: what a process that owns no object
    /// of a batch contributes.
    pub fn empty(shapes: Vec<Vec<usize>>) -> Self {
        PartialEstimate { shapes, blocks: Vec::new() }
    }

    /// Number of scalar parameter values.
    fn dim(&self) -> usize {
        self.shapes.iter().map(|s| s.iter().product::<usize>()).sum()
    }

    /// The exact sum of every block of every process of `comm` (a collective
    /// call: every process must make it). Counts are summed as integers; `l_hat`
    /// and the score by [`exact_sum`], so the result does not depend on how the
    /// blocks were spread over threads or processes.
    pub fn reduce(self, comm: &dyn Collective) -> ScoreEstimate {
        let dim = self.dim();
        let rows: Vec<Vec<f64>> = self
            .blocks
            .iter()
            .map(|b| std::iter::once(b.log_likelihood).chain(b.gradient.iter().copied()).collect())
            .collect();
        let sum = exact_sum(&rows, dim + 1, comm);
        let mut counts = [0i64; 4];
        for b in &self.blocks {
            for (c, v) in
                counts.iter_mut().zip([b.observed_units, b.collapsed_steps, b.rows_evaluated, b.particle_slots])
            {
                *c += v as i64;
            }
        }
        comm.sum_i64(&mut counts);
        let mut flat = sum[1..].iter().copied();
        let gradient = self
            .shapes
            .iter()
            .map(|shape| Tensor::new(shape, flat.by_ref().take(shape.iter().product()).collect()))
            .collect();
        ScoreEstimate {
            log_likelihood: sum[0],
            observed_units: counts[0] as usize,
            gradient,
            collapsed_steps: counts[1] as usize,
            rows_evaluated: counts[2] as usize,
            particle_slots: counts[3] as usize,
        }
    }
}

/// The blocks of the exact reduction over `objects` objects: consecutive runs of
/// `chunk` (at least 1) objects, the last possibly shorter.
pub fn reduction_blocks(objects: usize, chunk: usize) -> impl Iterator<Item = std::ops::Range<usize>> {
    let chunk = chunk.max(1);
    (0..objects).step_by(chunk).map(move |s| s..objects.min(s + chunk))
}

/// A particle-filter score estimator.
pub trait ScoreEstimator: Send + Sync {
    /// A short name for tables and files (e.g. `pf-sefi`).
    fn name(&self) -> String;

    /// The score of every object of `model` from the filter's draws with `seed`
    /// (the same seed gives the same draws to every estimator), as partial sums
    /// over the blocks of [`reduction_blocks`] with `config.chunk_objects`.
    fn partial<M: DifferentiableModel>(&self, model: &M, config: &EstimatorConfig, seed: u64) -> PartialEstimate;

    /// The score of every object of `model`: [`Self::partial`] reduced
    /// in this process.
    fn estimate<M: DifferentiableModel>(&self, model: &M, config: &EstimatorConfig, seed: u64) -> ScoreEstimate {
        self.partial(model, config, seed).reduce(&SingleProcess)
    }
}

/// Any of the estimators, chosen at run time (by a config or a command line).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Estimator {
    /// PF-SEFI with fixed lag `L`.
    PfSefi(PfSefi),
    /// A through-filter baseline.
    ThroughFilter(ThroughFilter),
}

impl Estimator {
    /// PF-SEFI with lag `lag`.
    pub fn pf_sefi(lag: usize) -> Self {
        Estimator::PfSefi(PfSefi { lag })
    }

    /// PF: `l_hat` differentiated through the filter.
    pub fn pf() -> Self {
        Estimator::ThroughFilter(ThroughFilter { kind: ThroughFilterKind::Pf })
    }

    /// DPF-SGR as in the paper (stop-gradient on the post-resampling weights).
    pub fn dpf_sgr() -> Self {
        Estimator::ThroughFilter(ThroughFilter { kind: ThroughFilterKind::DpfSgr })
    }

    /// DPF-SGR with the particles stopped too.
    pub fn dpf_sgr_stopped() -> Self {
        Estimator::ThroughFilter(ThroughFilter { kind: ThroughFilterKind::DpfSgrStopped })
    }

    /// PFNET's soft resampling with mixing `alpha`.
    pub fn pfnet(alpha: f64) -> Self {
        Estimator::ThroughFilter(ThroughFilter { kind: ThroughFilterKind::Pfnet { alpha } })
    }

    /// Parses a name as written by [`ScoreEstimator::name`]: `pf-sefi`, `pf`,
    /// `dpf-sgr`, `dpf-sgr-stopped`, `pfnet`; `lag` and `alpha` fill in the settings.
    pub fn parse(name: &str, lag: usize, alpha: f64) -> Result<Self, SettingError> {
        match name {
            "pf-sefi" | "sefi" => Ok(Self::pf_sefi(lag)),
            "pf" => Ok(Self::pf()),
            "dpf-sgr" | "dpf" => Ok(Self::dpf_sgr()),
            "dpf-sgr-stopped" => Ok(Self::dpf_sgr_stopped()),
            "pfnet" => {
                SettingError::check(alpha > 0.0 && alpha <= 1.0, "pfnet.alpha", alpha, "in (0, 1]")?;
                Ok(Self::pfnet(alpha))
            }
            other => Err(SettingError::new("estimator", other, "pf-sefi, pf, dpf-sgr, dpf-sgr-stopped or pfnet")),
        }
    }
}

impl ScoreEstimator for Estimator {
    fn name(&self) -> String {
        match self {
            Estimator::PfSefi(e) => e.name(),
            Estimator::ThroughFilter(e) => e.name(),
        }
    }

    fn partial<M: DifferentiableModel>(&self, model: &M, config: &EstimatorConfig, seed: u64) -> PartialEstimate {
        match self {
            Estimator::PfSefi(e) => e.partial(model, config, seed),
            Estimator::ThroughFilter(e) => e.partial(model, config, seed),
        }
    }
}

/// An estimator's work in one float type of its tapes.
pub(crate) trait EstimateIn {
    /// [`ScoreEstimator::partial`] with tapes of `F`.
    fn run<M: DifferentiableModel, F: Float>(&self, model: &M, config: &EstimatorConfig, seed: u64) -> PartialEstimate;
}

/// [`EstimateIn::run`] in the float type `config.precision` names.
pub(crate) fn by_precision<E: EstimateIn, M: DifferentiableModel>(
    estimator: &E,
    model: &M,
    config: &EstimatorConfig,
    seed: u64,
) -> PartialEstimate {
    match config.precision {
        Precision::F32 => estimator.run::<M, f32>(model, config, seed),
        Precision::F64 => estimator.run::<M, f64>(model, config, seed),
    }
}

/// An empty partial estimate for `model`'s parameters with one zero block per
/// block of [`reduction_blocks`].
pub(crate) fn zero_blocks<M: DifferentiableModel>(model: &M, config: &EstimatorConfig) -> PartialEstimate {
    let shapes: Vec<Vec<usize>> = model.parameters().iter().map(|p| p.shape().to_vec()).collect();
    let mut partial = PartialEstimate::empty(shapes);
    let dim = partial.dim();
    partial.blocks =
        reduction_blocks(model.num_objects(), config.chunk_objects).map(|_| BlockEstimate::zero(dim)).collect();
    partial
}

/// A constant `[R]` column per component from dimension-major values
/// (`values[k * rows + r]`).
pub(crate) fn columns<'t, F: Float>(tape: &'t Tape<F>, values: &[f32], dims: usize, rows: usize) -> Vec<Var<'t, F>> {
    (0..dims)
        .map(|k| {
            let col: Vec<F> = values[k * rows..(k + 1) * rows].iter().map(|&v| F::from_f64(v as f64)).collect();
            tape.constant(Tensor::from_vec(col))
        })
        .collect()
}
