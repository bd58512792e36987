//! Learning the vehicle model of a dataset: the [`Objective`] that
//! [`crate::training::train`] climbs, one batch of scenes per step, with a score
//! estimator of [`crate::estimators`] and the test MLL as its evaluation.
//!
//! Parameters live in one [`ParamStore`] under the convention of
//! [`crate::models::params`]; each step rebuilds the models from it
//! ([`Models::from_store`]), estimates the score on the batch's objects and maps
//! the gradient back onto the store by name. The gradient handed to the trainer
//! is the score divided by the batch's observed units (the gradient of the
//! per-point log-likelihood), so learning rates and clipping thresholds do not
//! depend on how many points a scene has.
//!
//! Data-parallel training ([`SceneObjective::with_collective`]): each process of
//! a job holds, of every batch, only the blocks of objects it owns
//! ([`owned_objects`], balanced by [`block_cost`]; read with
//! [`Dataset::read_shard`]), estimates their partial sums, and the exact
//! reduction gives every process the same score, bit for bit, whatever the
//! number of processes. The test evaluation runs on the first process only.

use std::sync::Arc;

use autodiff::nn::ParamStore;
use autodiff::Tensor;
use serde::{Deserialize, Serialize};

use crate::data::{DataLayout, Dataset};
use crate::estimators::{reduction_blocks, Estimator, EstimatorConfig, PartialEstimate, ScoreEstimator};
use crate::filter::{run_filter, FilterConfig, Sampling, Tempering};
use crate::models::extended::{DefensiveProposal, ExtendedSsm, ExtensibleObservation, Extension};
use crate::models::params::{AnyPolicy, ModelVisitor, Models};
use crate::models::road_user::VehicleSsm;
use crate::models::vehicle::GaussianPolicy;
use crate::models::DifferentiableModel;
use crate::training::{BatchEstimate, EstimateError, Objective};
use crate::util::reduce::{assign_blocks, Collective, SingleProcess};

/// How the objective estimates and evaluates.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectiveConfig {
    /// The score estimator.
    pub estimator: Estimator,
    /// Particles, resampling and chunking of the estimator.
    pub estimator_config: EstimatorConfig,
    /// Scenes per training step (SPEC §6: one).
    pub scenes_per_step: usize,
    /// Particles of the test evaluation (SPEC §5: 4096).
    pub eval_particles: usize,
    /// A catalogue extension of the base model to fit along with it
    /// ([`crate::models::extended`]); its parameter is `ext.<id>` in the store.
    #[serde(default)]
    pub extension: Option<Extension>,
    /// With an extension: learn only its parameter, the base model held fixed
    /// (every other parameter's gradient is zero).
    #[serde(default)]
    pub extension_only: bool,
    /// Parameter tensors held at their starting values (their gradients are
    /// zero), by name: a detector drift calibrated on labels, say.
    #[serde(default)]
    pub frozen: Vec<String>,
    /// Every parameter but the extension's moves at this multiple of the
    /// learning rate (`None`: all at the rate): a refit that continues a fitted
    /// base at the rate it ended at while a new extension learns at the full one.
    #[serde(default)]
    pub base_rate_factor: Option<f64>,
    /// The filter's proposal for the actions, if not the transition (PF-SEFI and
    /// the evaluation only: the through-filter baselines replay the transition).
    #[serde(default)]
    pub proposal: Option<DefensiveProposal>,
    /// The test evaluation's filter: tempered ([`crate::filter::Tempering`]) or,
    /// with `None`, the bootstrap filter. Every estimator's learned model is
    /// evaluated alike, whatever filter it was trained with.
    #[serde(default)]
    pub eval_tempering: Option<Tempering>,
}

/// The name of the test MLL among [`SceneObjective`]'s evaluation metrics.
pub const TEST_MLL: &str = "test_mll";

/// Training scenes in batches, test data, and an estimator.
pub struct SceneObjective {
    batches: Vec<Dataset>,
    test: Dataset,
    config: ObjectiveConfig,
    comm: Arc<dyn Collective>,
}

impl SceneObjective {
    /// Batches of `scenes_per_step` consecutive scenes of `train` (the last may be
    /// smaller) and the test data. Fails on an empty dataset or different kinds.
    pub fn new(train: &Dataset, test: Dataset, config: ObjectiveConfig) -> Result<Self, String> {
        if train.scenes().is_empty() || test.scenes().is_empty() {
            return Err("training and test data need at least one scene each".into());
        }
        if train.kind() != test.kind() {
            return Err(format!("training data holds {:?}, test data {:?}", train.kind(), test.kind()));
        }
        let per = config.scenes_per_step.max(1);
        let scenes: Vec<usize> = (0..train.scenes().len()).collect();
        let batches = scenes.chunks(per).map(|c| train.select_scenes(c)).collect();
        Ok(SceneObjective { batches, test, config, comm: Arc::new(SingleProcess) })
    }

    /// The objective of one process of the job `comm` on the whole training data
    /// `train` in memory: that process's share ([`owned_objects`], cut with
    /// [`Dataset::shard`]) with [`SceneObjective::with_collective`]. On a job of
    /// one, the objective of [`SceneObjective::new`].
    pub fn for_process(
        train: &Dataset,
        test: Dataset,
        config: ObjectiveConfig,
        comm: Arc<dyn Collective>,
    ) -> Result<Self, String> {
        let share =
            (comm.size() > 1).then(|| train.shard(&owned_objects(&train.layout(), &config, comm.rank(), comm.size())));
        Ok(SceneObjective::new(share.as_ref().unwrap_or(train), test, config)?.with_collective(comm))
    }

    /// The objective of one process of the job `comm`, on `train` holding that
    /// process's share of the training objects ([`owned_objects`]: read with
    /// [`Dataset::read_shard`], or cut from the whole data with
    /// [`Dataset::shard`]) and every scene, so that every process has the same
    /// batches. Every process of the job must build its objective alike and step
    /// together (each estimate is a collective call); on a job of one, `train`
    /// is the whole data.
    pub fn with_collective(mut self, comm: Arc<dyn Collective>) -> Self {
        self.comm = comm;
        self
    }

    /// The models a store describes for this data's kind.
    fn models(&self, params: &ParamStore<f64>) -> Result<Models, String> {
        Models::from_store(params, self.test.kind()).map_err(|e| e.to_string())
    }
}

/// The training objects (indices into [`Dataset::objects`], ascending) that
/// process `rank` of a job of `size` owns: of every batch (runs of
/// `scenes_per_step` scenes, as [`SceneObjective::new`] cuts them), the blocks
/// of `estimator_config.chunk_objects` consecutive objects
/// ([`reduction_blocks`]) that [`assign_blocks`] gives it by their
/// [`block_cost`]. Computed alike on every process from the data's
/// [`DataLayout`], before any object is read.
pub fn owned_objects(layout: &DataLayout, config: &ObjectiveConfig, rank: usize, size: usize) -> Vec<usize> {
    let chunk = config.estimator_config.chunk_objects;
    let mut owned = Vec::new();
    for scenes in layout.scenes.chunks(config.scenes_per_step.max(1)) {
        let first = scenes.first().map_or(0, |r| r.start);
        let last = scenes.last().map_or(0, |r| r.end);
        let blocks: Vec<_> = reduction_blocks(last - first, chunk).map(|r| first + r.start..first + r.end).collect();
        let costs: Vec<f64> = blocks.iter().map(|r| block_cost(layout, r.clone())).collect();
        let owners = assign_blocks(&costs, size);
        owned.extend(blocks.into_iter().zip(owners).filter(|(_, p)| *p == rank).flat_map(|(r, _)| r));
    }
    owned.sort_unstable();
    owned
}

/// Relative cost of a block of objects for the load balance of a distributed
/// job: its observed items plus [`STEP_COST_IN_UNITS`] per object-step.
pub fn block_cost(layout: &DataLayout, objects: std::ops::Range<usize>) -> f64 {
    objects.map(|o| layout.units[o] as f64 + STEP_COST_IN_UNITS * layout.meta.steps as f64).sum()
}

/// The cost of propagating one object's particles through one step, in observed
/// items' likelihoods: in the filter's profile (likelihood 61%, propagation 29%)
/// propagation takes about half the time of the point likelihood at ~9.5 points
/// per object-step, i.e. about as much as 4 to 5 points.
pub const STEP_COST_IN_UNITS: f64 = 4.5;

struct Estimate<'a> {
    estimator: &'a Estimator,
    config: &'a EstimatorConfig,
    extension: Option<Extension>,
    proposal: Option<DefensiveProposal>,
    params: &'a ParamStore<f64>,
    seed: u64,
}

impl ModelVisitor for Estimate<'_> {
    type Output = Result<(PartialEstimate, Vec<String>), String>;
    fn visit<O: ExtensibleObservation>(self, model: &VehicleSsm<'_, AnyPolicy, O>) -> Self::Output {
        let model = ExtendedSsm::from_store(model, self.extension, self.params)?.with_proposal(self.proposal)?;
        if self.proposal.is_some() && !matches!(self.estimator, Estimator::PfSefi(_)) {
            return Err("a filter proposal other than the transition works with PF-SEFI only".into());
        }
        if model.flip_chain().is_some() && !matches!(self.estimator, Estimator::PfSefi(_)) {
            return Err("`persistent_flip` works with PF-SEFI only: the through-filter baselines would need its \
                        chain's draws, which are discrete and not recorded in the actions"
                .into());
        }
        if model.drift().is_some() && !matches!(self.estimator, Estimator::PfSefi(_)) {
            return Err("a detector drift works with PF-SEFI only: the through-filter baselines would need its \
                        offsets' noise, which the actions do not record"
                .into());
        }
        Ok((self.estimator.partial(&model, self.config, self.seed), model.parameter_names()))
    }
}

/// The filter's log-likelihood estimate of a dataset under a model (with an
/// extension, if any): `(l_hat, observed units, collapsed steps)`.
pub struct LogLikelihood<'a> {
    /// The filter's settings.
    pub config: &'a FilterConfig,
    /// The extension, if any.
    pub extension: Option<Extension>,
    /// The store holding the extension's parameter.
    pub params: &'a ParamStore<f64>,
    /// The filter's proposal for the actions, if not the transition.
    pub proposal: Option<DefensiveProposal>,
}

impl ModelVisitor for LogLikelihood<'_> {
    type Output = Result<(f64, usize, usize), String>;
    fn visit<O: ExtensibleObservation>(self, model: &VehicleSsm<'_, AnyPolicy, O>) -> Self::Output {
        let model = ExtendedSsm::from_store(model, self.extension, self.params)?.with_proposal(self.proposal)?;
        let run = run_filter(&model, self.config, |_| ());
        Ok((run.log_likelihood(), run.observed_units(), run.collapsed_steps()))
    }
}

/// Places per-tensor gradients named `names` into the order of `store`; names
/// the model does not have get zeros. Fails if a model name is not in the store.
pub fn gradient_in_store_order(
    store: &ParamStore<f64>,
    names: &[String],
    gradient: Vec<Tensor<f64>>,
) -> Result<Vec<Tensor<f64>>, String> {
    let mut out: Vec<Tensor<f64>> = store.values().iter().map(|v| Tensor::zeros(v.shape())).collect();
    for (name, g) in names.iter().zip(gradient) {
        let id = store.id(name).ok_or_else(|| format!("the model's parameter `{name}` is not in the store"))?;
        out[id.0] = g;
    }
    Ok(out)
}

impl Objective for SceneObjective {
    fn batches(&self) -> usize {
        self.batches.len()
    }

    fn is_root(&self) -> bool {
        self.comm.rank() == 0
    }

    fn rate_factors(&self, params: &ParamStore<f64>) -> Option<Vec<f64>> {
        let factor = self.config.base_rate_factor?;
        let extension = self.config.extension.map(|e| e.param_name());
        let is_extension = |name: &str| extension.as_deref() == Some(name);
        Some(params.iter().map(|(name, _)| if is_extension(name) { 1.0 } else { factor }).collect())
    }

    fn estimate(&mut self, params: &ParamStore<f64>, batch: usize, seed: u64) -> Result<BatchEstimate, EstimateError> {
        let models = self.models(params)?;
        let visit = Estimate {
            estimator: &self.config.estimator,
            config: &self.config.estimator_config,
            extension: self.config.extension,
            proposal: self.config.proposal,
            params,
            seed,
        };
        let (partial, names) = models.visit(&self.batches[batch], visit)??;
        // A non-finite estimate goes to the trainer as it is: it skips the step
        // and records which parameters' gradients were not finite.
        let estimate = partial.reduce(&*self.comm);
        let units = estimate.observed_units.max(1) as f64;
        let mut gradient = gradient_in_store_order(params, &names, estimate.gradient)?;
        let learned = self.config.extension.filter(|_| self.config.extension_only).map(|e| e.param_name());
        for (i, g) in gradient.iter_mut().enumerate() {
            let name = params.name(autodiff::nn::ParamId(i));
            let frozen = learned.as_ref().is_some_and(|l| name != l) || self.config.frozen.iter().any(|f| f == name);
            g.data_mut().iter_mut().for_each(|x| *x = if frozen { 0.0 } else { *x / units });
        }
        Ok(BatchEstimate {
            log_likelihood: estimate.log_likelihood,
            observed_units: estimate.observed_units,
            gradient,
            collapsed_steps: estimate.collapsed_steps,
        })
    }

    /// `test_mll` (nats per point, one filter run with `eval_particles`), the
    /// test's collapsed steps and, for the hand-crafted policy, its sds. In a
    /// distributed job only the first process runs the filter; the others receive
    /// its two metrics ([`crate::util::reduce::Collective::share_first`]).
    fn evaluate(&mut self, params: &ParamStore<f64>, seed: u64) -> Result<Vec<(String, f64)>, String> {
        let models = self.models(params)?;
        let (ll, units, collapsed): (f64, usize, Option<usize>) = if self.is_root() {
            let sampling = Sampling::new(self.config.eval_particles, self.config.eval_tempering);
            let config = FilterConfig::new(sampling, 0, seed);
            let visit = LogLikelihood {
                config: &config,
                extension: self.config.extension,
                params,
                proposal: self.config.proposal,
            };
            let (ll, units, collapsed) = models.visit(&self.test, visit)??;
            (ll, units, Some(collapsed))
        } else {
            (f64::NAN, 0, None)
        };
        // Every process gets the first's values, so that a choice made on them
        // (`TrainConfig::keep_best`) is the same on all.
        let mut shared =
            [if units > 0 { ll / units as f64 } else { f64::NAN }, collapsed.map_or(f64::NAN, |c| c as f64)];
        self.comm.share_first(&mut shared);
        let mut metrics = vec![(TEST_MLL.to_string(), shared[0]), ("test_collapsed_steps".to_string(), shared[1])];
        if let AnyPolicy::HandCrafted(_) = &models.policy {
            let p = models.policy.parameters();
            metrics.push(("sd_accel".into(), p[0].data()[0].exp()));
            metrics.push(("sd_pinch".into(), p[0].data()[1].exp()));
        }
        Ok(metrics)
    }
}
