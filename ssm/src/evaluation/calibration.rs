//! Calibration at given parameters: is an estimator's score centred where it
//! must be, and how precise is the filter's likelihood estimate?
//!
//! * [`score_at`]: at the true parameters of data generated from the model the
//!   expected score is zero (for every object, whatever its observations), so
//!   the mean of an estimator's score over filter runs and objects, with its
//!   standard error, measures the estimator's bias there. Each object's score is
//!   averaged over the runs first and the spread is taken over objects, which are
//!   independent, so the standard error counts the data's variability as well as
//!   the filter's.
//! * [`likelihood_precision`]: the spread of one object's log-likelihood estimate
//!   across filter runs and the effective sample size per step.
//!
//! Both read the models from a parameter store the way training does
//! ([`crate::models::params::Models`]).

use std::time::Instant;

use autodiff::nn::ParamStore;
use rayon::prelude::*;
use serde::Serialize;

use crate::data::Dataset;
use crate::estimators::{Estimator, EstimatorConfig, ScoreEstimator};
use crate::filter::{effective_sample_size, run_filter, FilterConfig, Observer, StepView};
use crate::models::extended::ExtensibleObservation;
use crate::models::params::{AnyPolicy, ModelAdditions, ModelVisitor, Models};
use crate::models::road_user::VehicleSsm;
use crate::models::DifferentiableModel;
use crate::models::ParticleModel;
use crate::stats::{normal_cdf, quantile};
use crate::training::objective::gradient_in_store_order;

/// One entry of a parameter tensor's mean score.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EntryScore {
    /// Mean over objects of the per-object score (each averaged over runs).
    pub mean: f64,
    /// Its standard error (sd over objects / sqrt(objects)).
    pub se: f64,
    /// `mean / se`.
    pub z: f64,
    /// The sd over objects of the per-object score: what one object's estimate spreads by.
    pub sd: f64,
}

/// A parameter tensor's mean score.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TensorScore {
    /// The tensor's name in the store.
    pub name: String,
    /// One per entry.
    pub entries: Vec<EntryScore>,
    /// The largest `|z|` over the entries.
    pub max_abs_z: f64,
    /// Two-sided p-value of `max_abs_z`, Bonferroni-corrected over the entries.
    pub p: f64,
}

/// The mean score at given parameters.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ScoreAt {
    /// The estimator's name.
    pub estimator: String,
    /// Objects (the units of the standard error).
    pub objects: usize,
    /// Filter runs per object.
    pub runs: usize,
    /// Per tensor, in store order.
    pub tensors: Vec<TensorScore>,
    /// How large one object's score is: its global norm over every parameter,
    /// spread over objects (heavy tails here are what clipping meets in training).
    pub object_norms: NormSpread,
    /// Steps at which every particle of an object was impossible, summed.
    pub collapsed_steps: usize,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// The spread over objects of the global norm of each object's score.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct NormSpread {
    /// Median over objects.
    pub median: f64,
    /// 90th percentile over objects.
    pub q90: f64,
    /// The largest.
    pub max: f64,
    /// The objects (indices into the dataset's objects) with the largest norms,
    /// largest first, at most five.
    pub largest: Vec<(usize, f64)>,
}

/// The [`NormSpread`] of one score per object (tensors in store order).
fn norm_spread(per_object: &[Vec<autodiff::Tensor<f64>>]) -> NormSpread {
    let norms: Vec<f64> =
        per_object.iter().map(|g| g.iter().flat_map(|t| t.data()).map(|x| x * x).sum::<f64>().sqrt()).collect();
    let at = |q: f64| quantile(&norms, q).unwrap_or(f64::NAN);
    let mut largest: Vec<(usize, f64)> = norms.iter().copied().enumerate().collect();
    largest.sort_by(|a, b| b.1.total_cmp(&a.1));
    largest.truncate(5);
    NormSpread { median: at(0.5), q90: at(0.9), max: at(1.0), largest }
}

struct ObjectScore<'a> {
    estimator: &'a Estimator,
    config: &'a EstimatorConfig,
    runs: usize,
    seed: u64,
    /// The extension and drift of the parameters, scored with the base model's.
    additions: ModelAdditions<'a>,
}

impl ModelVisitor for ObjectScore<'_> {
    type Output = Result<(Vec<autodiff::Tensor<f64>>, Vec<String>, usize), String>;
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) -> Self::Output {
        let model = &self.additions.extend(base)?;
        let mut sum: Option<Vec<autodiff::Tensor<f64>>> = None;
        let mut collapsed = 0;
        for r in 0..self.runs {
            let e = self.estimator.estimate(model, self.config, self.seed.wrapping_add(r as u64));
            collapsed += e.collapsed_steps;
            match &mut sum {
                None => sum = Some(e.gradient),
                Some(s) => {
                    for (a, g) in s.iter_mut().zip(&e.gradient) {
                        a.data_mut().iter_mut().zip(g.data()).for_each(|(x, y)| *x += y);
                    }
                }
            }
        }
        let mut mean = sum.expect("at least one run");
        for t in &mut mean {
            t.data_mut().iter_mut().for_each(|x| *x /= self.runs as f64);
        }
        Ok((mean, model.parameter_names(), collapsed))
    }
}

/// One object's mean score per parameter tensor (in store order) and its number of
/// collapsed filter steps.
type ObjectScoreAt = (Vec<autodiff::Tensor<f64>>, usize);

/// The mean of `estimator`'s score over `runs` filter runs (seeds `seed..`) of
/// every object of `data` under the models of `params` (with their extension
/// and detector drift, if any), per parameter tensor. `progress` is called
/// once per object done.
pub fn score_at(
    data: &Dataset,
    params: &ParamStore<f64>,
    estimator: &Estimator,
    config: &EstimatorConfig,
    runs: usize,
    seed: u64,
    progress: &(dyn Fn() + Sync),
) -> Result<ScoreAt, String> {
    if runs == 0 {
        return Err("score_at: need at least one run".into());
    }
    let objects = data.objects().len();
    if objects < 2 {
        return Err("score_at: need at least two objects for a standard error".into());
    }
    let models = Models::from_store(params, data.kind()).map_err(|e| e.to_string())?;
    let clock = Instant::now();
    let per_object: Vec<Result<ObjectScoreAt, String>> = (0..objects)
        .into_par_iter()
        .map(|o| {
            let one = data.select_objects(&[o]);
            let visit = ObjectScore { estimator, config, runs, seed, additions: models.additions() };
            let (gradient, names, collapsed) = models.visit(&one, visit)??;
            progress();
            Ok((gradient_in_store_order(params, &names, gradient)?, collapsed))
        })
        .collect();
    let per_object: Vec<ObjectScoreAt> = per_object.into_iter().collect::<Result<_, _>>()?;
    let collapsed_steps = per_object.iter().map(|p| p.1).sum();
    let gradients: Vec<Vec<autodiff::Tensor<f64>>> = per_object.into_iter().map(|p| p.0).collect();
    Ok(ScoreAt {
        estimator: crate::estimators::study::label(estimator),
        objects,
        runs,
        tensors: summarise(params, &gradients),
        object_norms: norm_spread(&gradients),
        collapsed_steps,
        seconds: clock.elapsed().as_secs_f64(),
    })
}

/// Mean, standard error and z per entry of every tensor of `params` from one
/// gradient per object (in store order).
fn summarise(params: &ParamStore<f64>, per_object: &[Vec<autodiff::Tensor<f64>>]) -> Vec<TensorScore> {
    let objects = per_object.len();
    params
        .iter()
        .enumerate()
        .map(|(i, (name, value))| {
            let entries: Vec<EntryScore> = (0..value.data().len())
                .map(|j| {
                    let xs = || per_object.iter().map(|g| g[i].data()[j]);
                    let (mean, sd) = (crate::stats::mean(xs()), crate::stats::sd(xs()));
                    let se = sd / (objects as f64).sqrt();
                    EntryScore { mean, se, z: if se > 0.0 { mean / se } else { 0.0 }, sd }
                })
                .collect();
            let max_abs_z = entries.iter().map(|e| e.z.abs()).fold(0.0, f64::max);
            let p = (2.0 * (1.0 - normal_cdf(max_abs_z)) * entries.len() as f64).min(1.0);
            TensorScore { name: name.to_string(), entries, max_abs_z, p }
        })
        .collect()
}

/// One object's complete-data score at the store's parameters.
struct CompleteData {
    object: usize,
}

impl ModelVisitor for CompleteData {
    type Output = Result<(Vec<autodiff::Tensor<f64>>, Vec<String>), String>;
    fn visit<O: ExtensibleObservation>(self, model: &VehicleSsm<'_, AnyPolicy, O>) -> Self::Output {
        use crate::models::Block;
        use autodiff::{Tape, Tensor};
        let data = model.data();
        let (states, actions) = match (data.states(), data.actions()) {
            (Some(s), Some(a)) => (s, a),
            _ => return Err("the complete-data score needs the ground truth (states.csv and actions.csv)".into()),
        };
        let o = self.object;
        let truth: Vec<crate::data::State> = (0..data.steps())
            .map(|t| states.get(o, t).copied().ok_or_else(|| format!("object {o} has no true state at step {t}")))
            .collect::<Result<_, _>>()?;
        let acts: Vec<crate::data::Action> = (1..data.steps())
            .map(|t| actions.get(o, t).copied().ok_or_else(|| format!("object {o} has no true action at step {t}")))
            .collect::<Result<_, _>>()?;
        let tape = Tape::<f64>::new();
        let params = model.bind(&tape);
        let column = |v: Vec<f64>| tape.constant(Tensor::from_vec(v));
        let state_columns = |ts: &[usize]| -> Vec<autodiff::Var<'_, f64>> {
            (0..5).map(|k| column(ts.iter().map(|&t| truth[t].to_array()[k]).collect())).collect()
        };
        let observed: Vec<usize> = (0..data.steps()).filter(|&t| model.observation_count(o, t) > 0).collect();
        let mut total = tape.constant(Tensor::from_vec(vec![0.0]));
        if !observed.is_empty() {
            let blocks: Vec<Block> = observed.iter().map(|&t| Block { object: o, t, len: 1 }).collect();
            total = total + model.observation_log_density(&params, &blocks, &state_columns(&observed)).sum();
        }
        if data.steps() > 1 {
            let ts: Vec<usize> = (1..data.steps()).collect();
            let prev: Vec<usize> = ts.iter().map(|t| t - 1).collect();
            let blocks: Vec<Block> = ts.iter().map(|&t| Block { object: o, t, len: 1 }).collect();
            let a =
                vec![column(acts.iter().map(|a| a.accel).collect()), column(acts.iter().map(|a| a.pinch).collect())];
            let density =
                model.transition_log_density(&params, &blocks, &state_columns(&prev), &state_columns(&ts), &a);
            total = total + density.sum();
        }
        let grads = tape.backward(total);
        Ok((params.iter().map(|&p| grads.wrt(p)).collect(), model.parameter_names()))
    }
}

/// The complete-data score `grad ln p(x_{0:T}, y_{0:T})` at the store's
/// parameters, from the ground-truth states and actions of `data`, per parameter
/// tensor (mean, standard error and z over objects). On data sampled from the
/// model at those parameters its expectation is zero: a mean beyond noise means
/// that a sampler and its log-density disagree, whatever the filter does.
pub fn complete_data_score_at(data: &Dataset, params: &ParamStore<f64>) -> Result<ScoreAt, String> {
    let objects = data.objects().len();
    if objects < 2 {
        return Err("complete_data_score_at: need at least two objects for a standard error".into());
    }
    let models = Models::from_store(params, data.kind()).map_err(|e| e.to_string())?;
    let clock = Instant::now();
    let per_object: Vec<Vec<autodiff::Tensor<f64>>> = (0..objects)
        .into_par_iter()
        .map(|o| {
            let (gradient, names) = models.visit(data, CompleteData { object: o })??;
            gradient_in_store_order(params, &names, gradient)
        })
        .collect::<Result<_, _>>()?;
    Ok(ScoreAt {
        estimator: "complete data".into(),
        objects,
        runs: 1,
        tensors: summarise(params, &per_object),
        object_norms: norm_spread(&per_object),
        collapsed_steps: 0,
        seconds: clock.elapsed().as_secs_f64(),
    })
}

/// How precise a filter's likelihood estimate is on a dataset.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LikelihoodPrecision {
    /// Particles per object.
    pub particles: usize,
    /// Runs per object.
    pub runs: usize,
    /// Per object, the sd of `l_hat` over the runs (nats).
    pub object_sd: Vec<f64>,
    /// Median of `object_sd`.
    pub median_sd: f64,
    /// 95th percentile of `object_sd`.
    pub p95_sd: f64,
    /// Per step, the ESS after weighting averaged over objects and runs, as a
    /// fraction of `N`.
    pub ess_per_step: Vec<f64>,
    /// Per step, the smallest ESS fraction over objects and runs.
    pub min_ess_per_step: Vec<f64>,
    /// Observation likelihood evaluations of all `N` particles per observed
    /// object-step (1 for the bootstrap filter): the relative cost.
    pub evaluations_per_step: f64,
    /// Mean `l_hat` per observed unit over objects and runs.
    pub mll: f64,
    /// Collapsed steps, summed over runs.
    pub collapsed_steps: usize,
    /// Wall-clock seconds per run.
    pub seconds_per_run: f64,
}

/// Records the ESS fraction of every step.
#[derive(Default)]
struct EssRecorder(Vec<f64>);

impl Observer for EssRecorder {
    fn step(&mut self, view: &StepView<'_>) {
        let w: Vec<f64> = view.log_weights.iter().map(|l| l.exp()).collect();
        self.0.push(effective_sample_size(&w) / view.n as f64);
    }
}

struct Precision<'a> {
    config: &'a FilterConfig,
    runs: usize,
}

/// What one filter run of every object measured.
struct RunRecord {
    log_likelihood: Vec<f64>,
    ess: Vec<Vec<f64>>,
    collapsed: usize,
    evaluations: usize,
    observed_steps: usize,
    observed_units: usize,
    seconds: f64,
}

impl ModelVisitor for Precision<'_> {
    type Output = Vec<RunRecord>;
    fn visit<O: ExtensibleObservation>(self, model: &VehicleSsm<'_, AnyPolicy, O>) -> Self::Output {
        (0..self.runs)
            .map(|r| {
                let config = FilterConfig { seed: self.config.seed.wrapping_add(r as u64), ..self.config.clone() };
                let clock = Instant::now();
                let run = run_filter(model, &config, |_| EssRecorder::default());
                let seconds = clock.elapsed().as_secs_f64();
                let observed_steps = (0..model.num_objects())
                    .map(|o| (0..model.num_steps()).filter(|&t| model.observation_count(o, t) > 0).count())
                    .sum();
                RunRecord {
                    log_likelihood: run.objects.iter().map(|o| o.log_likelihood).collect(),
                    evaluations: run.objects.iter().map(|o| o.likelihood_evaluations).sum(),
                    collapsed: run.collapsed_steps(),
                    observed_units: run.observed_units(),
                    ess: run.observers.into_iter().map(|e| e.0).collect(),
                    observed_steps,
                    seconds,
                }
            })
            .collect()
    }
}

/// Filters every object of `data` `runs` times (seeds `config.seed..`) under the
/// models of `params` and measures the spread of each object's log-likelihood
/// estimate and the ESS per step.
pub fn likelihood_precision(
    data: &Dataset,
    params: &ParamStore<f64>,
    config: &FilterConfig,
    runs: usize,
) -> Result<LikelihoodPrecision, String> {
    if runs < 2 {
        return Err("likelihood_precision: need at least two runs for a spread".into());
    }
    let models = Models::from_store(params, data.kind()).map_err(|e| e.to_string())?;
    let records = models.visit(data, Precision { config, runs })?;
    let objects = data.objects().len();
    let object_sd: Vec<f64> =
        (0..objects).map(|o| crate::stats::sd(records.iter().map(|r| r.log_likelihood[o]))).collect();
    let units: usize = records.iter().map(|r| r.observed_units).sum();
    let mll = records.iter().map(|r| r.log_likelihood.iter().sum::<f64>()).sum::<f64>() / units.max(1) as f64;
    let steps = data.steps();
    let at_step = |t: usize| records.iter().flat_map(move |r| r.ess.iter().map(move |e| e[t]));
    let ess_per_step = (0..steps).map(|t| crate::stats::mean(at_step(t))).collect();
    let min_ess_per_step = (0..steps).map(|t| at_step(t).fold(f64::INFINITY, f64::min)).collect();
    let evaluations: usize = records.iter().map(|r| r.evaluations).sum();
    let observed: usize = records.iter().map(|r| r.observed_steps).sum();
    let seconds_per_run = records.iter().map(|r| r.seconds).sum::<f64>() / runs as f64;
    let mut sorted = object_sd.clone();
    sorted.sort_by(f64::total_cmp);
    let quantile = |q: f64| sorted[(q * (sorted.len() - 1) as f64).round() as usize];
    let (median_sd, p95_sd) = (quantile(0.5), quantile(0.95));
    Ok(LikelihoodPrecision {
        particles: config.sampling.particles,
        runs,
        object_sd,
        median_sd,
        p95_sd,
        ess_per_step,
        min_ess_per_step,
        evaluations_per_step: evaluations as f64 / observed.max(1) as f64,
        mll,
        collapsed_steps: records.iter().map(|r| r.collapsed).sum(),
        seconds_per_run,
    })
}

struct SampleFromModel<'a> {
    seed: u64,
    /// The extension and drift the data are drawn with.
    additions: ModelAdditions<'a>,
    builder: &'a mut crate::data::DatasetBuilder,
}

impl ModelVisitor for SampleFromModel<'_> {
    type Output = Result<(), String>;
    fn visit<O: ExtensibleObservation>(self, model: &VehicleSsm<'_, AnyPolicy, O>) -> Self::Output {
        use crate::models::extended::ObjectObservations;
        use crate::models::vehicle::state::{Action as VAction, VehicleState};
        use rand::SeedableRng;

        let data = model.data();
        let sampler = self.additions.extend(model)?;
        let b = self.builder;
        b.with_states().with_actions();
        for scene in data.scenes() {
            b.scene(scene.id, &scene.av);
        }
        for (o, object) in data.objects().iter().enumerate() {
            let mut rng = rand::rngs::SmallRng::seed_from_u64(crate::filter::stream_seed(self.seed, o as u64));
            let mut states = vec![sampler.sample_initial_state(o, &mut rng)];
            let mut actions = Vec::with_capacity(data.steps());
            for _ in 1..data.steps() {
                let s = *states.last().expect("x_0 is there");
                let a = sampler.sample_action(&s, &mut rng);
                let next = model
                    .motion()
                    .step(&VehicleState::new(s.x, s.y, s.yaw, s.v, s.kappa), &VAction::new(a.accel, a.pinch));
                actions.push(a);
                states.push(crate::data::State { x: next.x, y: next.y, yaw: next.yaw, v: next.v, kappa: next.kappa });
            }
            b.object(*object);
            let (scene, id) = (object.scene, object.id);
            let per_step = sampler.sample_observations_along(o, &states, &mut rng);
            match O::to_observations(per_step) {
                ObjectObservations::Points(steps) => {
                    for (t, pts) in steps.into_iter().enumerate() {
                        pts.into_iter().for_each(|p| {
                            b.point(scene, id, t, p);
                        });
                    }
                }
                ObjectObservations::Boxes(steps) => {
                    for (t, det) in steps.into_iter().enumerate() {
                        if let Some(d) = det {
                            b.detection(scene, id, t, d);
                        }
                    }
                }
            }
            for (t, s) in states.into_iter().enumerate() {
                b.state(scene, id, t, s);
            }
            for (t, a) in actions.into_iter().enumerate() {
                b.action(scene, id, t + 1, a);
            }
        }
        Ok(())
    }
}

/// Data drawn from the models of `params` themselves on the scenes of
/// `skeleton` (its AV poses, objects with their sizes and priors, and how many
/// points or detections each object has at each step): per object, `x_0` from
/// its prior, actions from the policy, states by the motion model, observations
/// from the observation model (with the catalogue extension and the detector
/// drift `params` hold, if any), with ground-truth states and actions. At
/// `params` the expected score of these data is exactly zero, which makes them
/// the test bed of [`score_at`] for any model family (a neural policy and box
/// detections as in experiment C, say). Object `o` draws from the stream
/// `stream_seed(seed, o)`.
pub fn sample_dataset(skeleton: &Dataset, params: &ParamStore<f64>, seed: u64) -> Result<Dataset, String> {
    let models = Models::from_store(params, skeleton.kind()).map_err(|e| e.to_string())?;
    let mut builder = Dataset::builder(skeleton.meta(), skeleton.kind());
    models.visit(skeleton, SampleFromModel { seed, additions: models.additions(), builder: &mut builder })??;
    builder.build().map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use autodiff::Tensor;

    #[test]
    fn norm_spread_ranks_objects_by_their_score_norm() {
        // Object i's score is (3k, 4k) split over two tensors, norm 5k, with
        // k = 7i mod 11: the norms are 0, 5, ..., 50 in an order unlike the objects'.
        let k = |i: usize| (7 * i % 11) as f64;
        let per_object: Vec<Vec<Tensor<f64>>> =
            (0..11).map(|i| vec![Tensor::from_vec(vec![3.0 * k(i)]), Tensor::from_vec(vec![4.0 * k(i)])]).collect();
        let s = norm_spread(&per_object);
        assert_eq!(s.median, 25.0);
        assert_eq!(s.q90, 45.0);
        assert_eq!(s.max, 50.0);
        // k(i) = 10, 9, 8, 7, 6 at i = 3, 6, 9, 1, 4.
        assert_eq!(s.largest, vec![(3, 50.0), (6, 45.0), (9, 40.0), (1, 35.0), (4, 30.0)]);
    }
}
