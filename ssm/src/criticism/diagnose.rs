//! The diagnosis (SPEC §7): fit the base model, show what its simulation gets
//! wrong, name the cause among the catalogue's extensions, and measure the gain.
//!
//! 1. **Split** the objects, seeded, into a training and a held-out part.
//! 2. **Fit the base** (neural policy and the observation network of the data's
//!    kind, from a standard initialisation) with PF-SEFI on the training part.
//! 3. **Check it** on the held-out part ([`posterior_predictive_checks`]): the
//!    filter's genealogy gives paths drawn from the particle smoother; along each
//!    path the model simulates replicated observations and actions; every
//!    statistic of [`super::checks`] is computed on the measured and the
//!    replicated data and calibrated over the draws (z, p, Holm correction).
//! 4. **Fit the plausible extensions**, each warm-started from the base, with
//!    PF-SEFI: an extension is plausible when a check that suggests it has an
//!    uncorrected p below [`DiagnoseConfig::plausible_p`] (or always, with
//!    [`DiagnoseConfig::fit_all`]).
//! 5. **Choose by held-out log-likelihood**: per held-out object, the filter's
//!    log-likelihood under the extended minus the base model; the gain is their
//!    sum per observed unit, its standard error from the spread over objects. The
//!    cause is the extension with the largest gain among those whose gain exceeds
//!    [`DiagnoseConfig::significance`] standard errors, else none.
//!
//!    Each object's likelihood is the mean of [`DiagnoseConfig::eval_runs`]
//!    filter estimates; objects whose runs disagree get more particles
//!    ([`refine_imprecise`]). The evaluation filters with a defensive proposal
//!    for the actions ([`DiagnoseConfig::proposal`]; training too with
//!    [`DiagnoseConfig::train_with_proposal`]), so that an acceleration in a
//!    model's tail does not make its estimate collapse: the comparison is
//!    between models, not between how well a bootstrap filter follows them.
//! 6. **Re-check** the winner: the same checks on the extended model.
//!
//! Every training run writes its logs and checkpoints under the output
//! directory, and a finished or interrupted run is resumed rather than redone.

use std::path::Path;

use autodiff::nn::ParamStore;
use rand::rngs::{SmallRng, StdRng};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::checks::{calibrate, checks_for, statistics, CheckResult};
use super::extensions::{state_at, DefensiveProposal, ExtendedSsm, ExtensibleObservation, Extension};
use super::{ObjectObservations, ObjectSample};
use crate::data::{Action, Dataset, ObservationKind, State};
use crate::estimators::{Estimator, EstimatorConfig};
use crate::filter::{filter_object, run_filter, stream_seed, FilterConfig, Observer, StepView};
use crate::model::ParticleModel;
use crate::objective::{ObjectiveConfig, SceneObjective};
use crate::params::{AnyPolicy, ModelVisitor, Models};
use crate::stats::{log_sum_exp, sd};
use crate::training::{train, TrainConfig, TrainEvent, CHECKPOINT_FILE};
use crate::vehicle::NeuralPolicy;
use crate::vehicle_ssm::VehicleSsm;

/// The base policy starts with this accel sd (m/s²): a road user's typical
/// acceleration, rather than the network's default.
pub const INITIAL_SD_ACCEL: f64 = 0.5;
/// The base policy starts with this pinch sd (1/(m s)).
pub const INITIAL_SD_PINCH: f64 = 0.02;

/// Settings of a diagnosis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DiagnoseConfig {
    /// Fraction of the objects held out (at least one object on each side).
    pub heldout_fraction: f64,
    /// Seed of the split, the initialisation, training and the checks.
    pub seed: u64,
    /// PF-SEFI steps of the base fit.
    pub base_steps: usize,
    /// PF-SEFI steps of each extension's fit (warm-started from the base).
    pub candidate_steps: usize,
    /// Training particles.
    pub particles: usize,
    /// Particles of the held-out evaluation and of the smoother draws.
    pub eval_particles: usize,
    /// Fixed lag of PF-SEFI.
    pub lag: usize,
    /// Adam learning rate of the base fit.
    pub lr: f64,
    /// Adam learning rate of the extensions' parameters (their stored values are
    /// scaled, see [`super::extensions`]).
    pub candidate_lr: f64,
    /// Global gradient-norm clipping.
    pub clip: Option<f64>,
    /// Scenes per training step.
    pub scenes_per_step: usize,
    /// Paths drawn from the smoother per held-out object (the checks' replicates).
    pub draws: usize,
    /// Filter runs (seeds) whose likelihood estimates are averaged for each held-out
    /// object (at least 2: their spread measures the estimate's precision).
    pub eval_runs: usize,
    /// A held-out object's runs are redone with twice the particles while their
    /// log-likelihoods have an sd above this (nats)...
    pub eval_tolerance: f64,
    /// ... up to this many particles (see [`refine_imprecise`]).
    pub max_eval_particles: usize,
    /// The held-out filter's proposal for the actions (the transition if none): a
    /// few wide draws let every model's filter follow an action in its tail, so
    /// that its likelihood estimate does not collapse there.
    pub proposal: Option<DefensiveProposal>,
    /// Train (PF-SEFI) with the same proposal too, so that the smoother shows the
    /// fit what lies in the model's tails.
    pub train_with_proposal: bool,
    /// Family-wise level of the checks (Holm-corrected).
    pub alpha: f64,
    /// An extension is fitted when a check that suggests it has an uncorrected p
    /// below this.
    pub plausible_p: f64,
    /// Fit every extension that applies to the data, plausible or not.
    pub fit_all: bool,
    /// The cause's gain must exceed this many standard errors.
    pub significance: f64,
}

impl Default for DiagnoseConfig {
    /// The scale for measured data: 600 base steps, 300 per extension, 512
    /// training and 2048 evaluation particles (2 runs, up to 16384 where they
    /// disagree by more than 2 nats), L = 15, clipping at 0.5.
    fn default() -> Self {
        DiagnoseConfig {
            heldout_fraction: 0.3,
            seed: 0,
            base_steps: 600,
            candidate_steps: 300,
            particles: 512,
            eval_particles: 2048,
            lag: 15,
            lr: 0.01,
            candidate_lr: 0.02,
            clip: Some(0.5),
            scenes_per_step: 16,
            draws: 50,
            eval_runs: 2,
            eval_tolerance: 2.0,
            max_eval_particles: 16384,
            proposal: Some(DefensiveProposal { fraction: 0.1, widening: 8.0 }),
            train_with_proposal: false,
            alpha: 0.05,
            plausible_p: 0.2,
            fit_all: false,
            significance: 2.0,
        }
    }
}

impl DiagnoseConfig {
    /// A small scale that runs in about a minute on generated data (tests, demos).
    pub fn quick() -> Self {
        DiagnoseConfig {
            heldout_fraction: 0.5,
            base_steps: 600,
            candidate_steps: 150,
            particles: 512,
            eval_particles: 16384,
            max_eval_particles: 16384,
            lag: 8,
            draws: 40,
            eval_runs: 3,
            scenes_per_step: 4,
            ..DiagnoseConfig::default()
        }
    }

    /// Checks every setting.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.heldout_fraction > 0.0 && self.heldout_fraction < 1.0) {
            return Err(format!("held-out fraction must be in (0, 1), got {}", self.heldout_fraction));
        }
        if self.particles == 0 || self.eval_particles == 0 || self.eval_runs < 2 || self.draws < 3 {
            return Err("particles and evaluation particles must be positive, evaluation runs at least 2 and draws \
                        at least 3"
                .into());
        }
        if self.max_eval_particles < self.eval_particles || self.eval_tolerance.is_nan() || self.eval_tolerance <= 0.0 {
            return Err(format!(
                "max_eval_particles ({}) must be at least eval_particles ({}) and eval_tolerance positive, got {}",
                self.max_eval_particles, self.eval_particles, self.eval_tolerance
            ));
        }
        if !(self.alpha > 0.0 && self.alpha < 1.0 && self.plausible_p > 0.0 && self.plausible_p <= 1.0) {
            return Err(format!("alpha {} and plausible_p {} must be in (0, 1]", self.alpha, self.plausible_p));
        }
        if let Some(p) = &self.proposal {
            p.validate()?;
        }
        if !(self.lr > 0.0 && self.candidate_lr > 0.0 && self.lr.is_finite() && self.candidate_lr.is_finite()) {
            return Err(format!("learning rates must be positive, got {} and {}", self.lr, self.candidate_lr));
        }
        if !(self.significance.is_finite() && self.significance >= 0.0) {
            return Err(format!("significance must be a non-negative number of SEs, got {}", self.significance));
        }
        Ok(())
    }
}

/// What [`diagnose`] is doing, for a progress display.
#[derive(Clone, Debug, PartialEq)]
pub enum Stage {
    /// A training run (`base` or an extension id) is at `step` of `total`.
    Training {
        /// `base` or the extension's id.
        model: String,
        /// Steps done.
        step: usize,
        /// Steps of the run.
        total: usize,
    },
    /// Evaluating and checking a model on the held-out objects.
    Checking {
        /// `base` or the extension's id.
        model: String,
    },
}

/// One check before and after the extension.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CheckReport {
    /// The statistic.
    pub name: String,
    /// What it measures.
    pub description: String,
    /// The extension it can reveal, if any.
    pub suggests: Option<String>,
    /// Its z-score on the base model (`before.z`).
    pub z: f64,
    /// Its Holm-adjusted p-value on the base model (`before.p_adjusted`).
    pub p: f64,
    /// Calibrated on the base model.
    pub before: CheckResult,
    /// Calibrated on the chosen extension (none when the cause is `none`).
    pub after: Option<CheckResult>,
    /// Per draw, the statistic on measured and on replicated data (base model).
    pub draws_before: Vec<(f64, f64)>,
    /// The same on the extended model.
    pub draws_after: Vec<(f64, f64)>,
}

/// One fitted extension.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CandidateReport {
    /// The extension's id.
    pub cause: String,
    /// Held-out log-likelihood gain over the base (nats per observed unit).
    pub gain: f64,
    /// Its standard error (paired over held-out objects).
    pub gain_se: f64,
    /// Per held-out object, its log-likelihood gain (nats).
    pub object_gains: Vec<f64>,
    /// The learned parameters in physical units: `(name, value, unit)`.
    pub params: Vec<(String, f64, String)>,
    /// The learned parameters in a sentence.
    pub description: String,
    /// The checks whose p made it plausible (empty when fitted because of `fit_all`).
    pub flagged_by: Vec<String>,
    /// Whether the learned parameters change the model materially
    /// ([`Extension::is_material`]); only a material extension can be the cause.
    pub material: bool,
    /// Training steps skipped (non-finite estimates).
    pub skipped_steps: usize,
    /// Training time (s).
    pub train_seconds: f64,
    /// How precise its held-out log-likelihoods are.
    pub precision: EvalPrecision,
}

/// The result of [`diagnose`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// The chosen extension's id, or `none`.
    pub cause: String,
    /// Its held-out gain (nats per observed unit; 0 for `none`).
    pub gain: f64,
    /// The gain's standard error.
    pub gain_se: f64,
    /// The chosen extension's learned parameters in a sentence (empty for `none`).
    pub finding: String,
    /// Every check, before and after.
    pub checks: Vec<CheckReport>,
    /// Every fitted extension.
    pub candidates: Vec<CandidateReport>,
    /// Extensions that apply to the data but no check made plausible.
    pub not_fitted: Vec<String>,
    /// The data's kind.
    pub kind: ObservationKind,
    /// Objects in the training part.
    pub train_objects: usize,
    /// Objects in the held-out part.
    pub heldout_objects: usize,
    /// Observed units (points, detections) of the held-out part.
    pub heldout_units: usize,
    /// Held-out log-likelihood of the base (nats per observed unit).
    pub base_mll: f64,
    /// How precise the base's held-out log-likelihoods are.
    pub base_precision: EvalPrecision,
    /// Held-out log-likelihood of the chosen model (the base's for `none`).
    pub chosen_mll: f64,
    /// Training steps of the base skipped (non-finite estimates).
    pub base_skipped_steps: usize,
    /// Training time of the base (s).
    pub base_train_seconds: f64,
    /// The settings.
    pub config: DiagnoseConfig,
}

/// Splits `data`'s objects, seeded: `(train, held-out)` object indices, sorted.
pub fn split_objects(data: &Dataset, heldout_fraction: f64, seed: u64) -> Result<(Vec<usize>, Vec<usize>), String> {
    let n = data.objects().len();
    let held = ((n as f64 * heldout_fraction).round() as usize).clamp(1, n.saturating_sub(1));
    if n < 2 {
        return Err(format!("the data hold {n} object(s): a diagnosis needs at least 2 to hold some out"));
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut StdRng::seed_from_u64(seed));
    let (mut h, mut t) = (order[..held].to_vec(), order[held..].to_vec());
    h.sort_unstable();
    t.sort_unstable();
    Ok((t, h))
}

/// Runs the diagnosis of `data`, writing training runs under `out_dir`
/// (`base/`, `candidates/<id>/`).
pub fn diagnose(
    data: &Dataset,
    config: &DiagnoseConfig,
    out_dir: &Path,
    progress: &mut dyn FnMut(&Stage),
) -> Result<Report, String> {
    config.validate()?;
    let (train_ids, heldout_ids) = split_objects(data, config.heldout_fraction, config.seed)?;
    diagnose_split(&data.select_objects(&train_ids), &data.select_objects(&heldout_ids), config, out_dir, progress)
}

/// [`diagnose`] with a given split: fit on `train_data`, check and compare on
/// `heldout` (e.g. KITTI's train and val sequences). Both must hold the same kind
/// of observations and time step.
pub fn diagnose_split(
    train_data: &Dataset,
    heldout: &Dataset,
    config: &DiagnoseConfig,
    out_dir: &Path,
    progress: &mut dyn FnMut(&Stage),
) -> Result<Report, String> {
    config.validate()?;
    let kind = train_data.kind();
    if heldout.kind() != kind || heldout.dt() != train_data.dt() || heldout.steps() != train_data.steps() {
        return Err(format!(
            "the held-out data ({:?}, dt {}, {} steps) differ from the training data ({kind:?}, dt {}, {} steps)",
            heldout.kind(),
            heldout.dt(),
            heldout.steps(),
            train_data.dt(),
            train_data.steps()
        ));
    }
    if train_data.objects().is_empty() || heldout.objects().is_empty() {
        return Err("the training and the held-out data need at least one object each".into());
    }

    // 2. The base.
    let initial = {
        let mut rng = StdRng::seed_from_u64(config.seed);
        let policy = NeuralPolicy::new(&mut rng).with_initial_sds(INITIAL_SD_ACCEL, INITIAL_SD_PINCH);
        Models::initial(kind, AnyPolicy::Neural(policy), rng.random()).to_store()
    };
    let base_dir = out_dir.join("base");
    let base = fit(train_data, heldout, None, initial, config.base_steps, config.lr, config, &base_dir, progress)?;

    // 3. Checks of the base.
    progress(&Stage::Checking { model: "base".into() });
    let base_eval = evaluate(heldout, &base.params, None, config)?;
    let defs = checks_for(kind);
    let before = calibrate(&defs, &base_eval.measured, &base_eval.replicated, config.alpha);

    // 4. The plausible extensions, each on top of the base.
    let plausible: Vec<(Extension, Vec<String>)> = Extension::for_kind(kind)
        .into_iter()
        .map(|ext| {
            let flagged_by = before
                .iter()
                .filter(|c| c.suggests.as_deref() == Some(ext.id()) && c.p < config.plausible_p)
                .map(|c| c.name.clone())
                .collect::<Vec<_>>();
            (ext, flagged_by)
        })
        .collect();
    let not_fitted: Vec<String> = plausible
        .iter()
        .filter(|(_, flagged)| flagged.is_empty() && !config.fit_all)
        .map(|(ext, _)| ext.id().to_string())
        .collect();
    let to_fit: Vec<(Extension, Vec<String>)> =
        plausible.into_iter().filter(|(_, flagged)| !flagged.is_empty() || config.fit_all).collect();
    let discrepancies: Vec<(&str, f64)> = before.iter().map(|c| (c.name.as_str(), c.measured - c.replicated)).collect();
    let mut candidates = Vec::new();
    let mut fitted = Vec::new();
    for (ext, flagged_by) in to_fit {
        let mut start = base.params.clone();
        start.add(&ext.param_name(), ext.initial_from_checks(&discrepancies));
        let dir = out_dir.join("candidates").join(ext.id());
        let run = refit(train_data, heldout, Some(ext), start, config, &dir, progress)?;
        progress(&Stage::Checking { model: ext.id().into() });
        let eval = evaluate(heldout, &run.params, Some(ext), config)?;
        let against = &base_eval;
        let (gain, gain_se) = paired_gain(&eval.object_ll, &against.object_ll, against.units);
        let raw = run.params.get(run.params.id(&ext.param_name()).expect("the extension's parameter")).data().to_vec();
        candidates.push(CandidateReport {
            cause: ext.id().into(),
            gain,
            gain_se,
            object_gains: eval.object_ll.iter().zip(&against.object_ll).map(|(a, b)| a - b).collect(),
            params: ext.natural(&raw)?.into_iter().map(|(n, v, u)| (n.to_string(), v, u.to_string())).collect(),
            description: ext.describe(&raw)?,
            material: ext.is_material(&raw)?,
            flagged_by,
            skipped_steps: run.skipped,
            train_seconds: run.seconds,
            precision: eval.precision,
        });
        fitted.push(eval);
    }

    // 5. The cause.
    let winner = candidates
        .iter()
        .enumerate()
        .filter(|(_, c)| c.material && c.gain.is_finite() && c.gain > config.significance * c.gain_se && c.gain > 0.0)
        .max_by(|a, b| a.1.gain.total_cmp(&b.1.gain))
        .map(|(i, _)| i);

    // 6. The checks after.
    let after = winner.map(|i| calibrate(&defs, &fitted[i].measured, &fitted[i].replicated, config.alpha));
    let checks = defs
        .iter()
        .enumerate()
        .map(|(c, def)| CheckReport {
            name: def.name.into(),
            description: def.description.into(),
            suggests: def.suggests.map(str::to_string),
            z: before[c].z,
            p: before[c].p_adjusted,
            before: before[c].clone(),
            after: after.as_ref().map(|a| a[c].clone()),
            draws_before: base_eval.draws_of(c),
            draws_after: winner.map(|i| fitted[i].draws_of(c)).unwrap_or_default(),
        })
        .collect();
    let units = base_eval.units.max(1) as f64;
    let base_mll = base_eval.object_ll.iter().sum::<f64>() / units;
    Ok(Report {
        cause: winner.map_or("none".into(), |i| candidates[i].cause.clone()),
        gain: winner.map_or(0.0, |i| candidates[i].gain),
        gain_se: winner.map_or(0.0, |i| candidates[i].gain_se),
        finding: winner.map_or(String::new(), |i| candidates[i].description.clone()),
        chosen_mll: winner.map_or(base_mll, |i| fitted[i].object_ll.iter().sum::<f64>() / units),
        checks,
        candidates,
        not_fitted,
        kind,
        train_objects: train_data.objects().len(),
        heldout_objects: heldout.objects().len(),
        heldout_units: base_eval.units,
        base_mll,
        base_precision: base_eval.precision,
        base_skipped_steps: base.skipped,
        base_train_seconds: base.seconds,
        config: config.clone(),
    })
}

/// `ln((1/n) sum_i e^{x_i})`, stable.
fn log_mean_exp(x: &[f64]) -> f64 {
    log_sum_exp(x) - (x.len() as f64).ln()
}

/// How precise a model's held-out log-likelihoods are (see [`refine_imprecise`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EvalPrecision {
    /// Objects re-estimated with more particles because their runs disagreed.
    pub refined_objects: usize,
    /// Objects whose runs still disagreed by more than the tolerance at the cap.
    pub imprecise_objects: usize,
    /// The most particles any object needed.
    pub max_particles: usize,
    /// The largest sd (nats) of an object's runs' log-likelihoods, after refining.
    pub max_run_sd: f64,
}

/// Sample sd of one object's runs (0 for a single run).
fn run_sd(x: &[f64]) -> f64 {
    if x.len() < 2 {
        0.0
    } else {
        sd(x.iter().copied())
    }
}

/// Redoes, with twice the particles each round up to `max_particles`, the runs of
/// every object whose runs' log-likelihoods (`per_run[object]`, one per seed of
/// `filter.seed..`) have an sd above `tolerance` nats.
///
/// A bootstrap filter's log-likelihood estimate has a long lower tail when the
/// observations are sharp and the model rarely proposes what they show (a jump
/// in the acceleration, say): one such object can differ by hundreds of nats
/// between runs and swamp a paired comparison of two models, although its
/// estimate is unbiased. More particles for the few objects whose runs disagree
/// is the remedy (as in choosing the particle count for a target variance of the
/// log-likelihood, Pitt et al. 2012); every model gets the same rule and seeds.
fn refine_imprecise<M: ParticleModel>(
    model: &M,
    filter: &FilterConfig,
    per_run: &mut [Vec<f64>],
    max_particles: usize,
    tolerance: f64,
) -> EvalPrecision {
    let mut precision = EvalPrecision { max_particles: filter.particles, ..EvalPrecision::default() };
    let mut particles = filter.particles;
    let mut refined = vec![false; per_run.len()];
    loop {
        let imprecise: Vec<usize> = (0..per_run.len()).filter(|&o| run_sd(&per_run[o]) > tolerance).collect();
        if imprecise.is_empty() || particles.saturating_mul(2) > max_particles {
            precision.imprecise_objects = imprecise.len();
            break;
        }
        particles *= 2;
        let runs = per_run.first().map_or(0, Vec::len);
        let redone: Vec<Vec<f64>> = imprecise
            .par_iter()
            .map_init(
                || model.new_scratch(),
                |scratch, &object| {
                    (0..runs)
                        .map(|r| {
                            let config = FilterConfig { particles, seed: filter.seed + r as u64, ..filter.clone() };
                            filter_object(model, &config, object, scratch, &mut ()).0.log_likelihood
                        })
                        .collect()
                },
            )
            .collect();
        for (&object, lls) in imprecise.iter().zip(redone) {
            per_run[object] = lls;
            refined[object] = true;
        }
        precision.max_particles = particles;
    }
    precision.refined_objects = refined.iter().filter(|&&r| r).count();
    precision.max_run_sd = per_run.iter().map(|l| run_sd(l)).fold(0.0, f64::max);
    precision
}

/// `(sum_i (a_i - b_i) / units, sqrt(n var(a - b)) / units)`: the gain per unit
/// and its standard error, objects independent.
pub fn paired_gain(a: &[f64], b: &[f64], units: usize) -> (f64, f64) {
    let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    let n = d.len() as f64;
    let units = units.max(1) as f64;
    if d.len() < 2 {
        return (d.iter().sum::<f64>() / units, f64::INFINITY);
    }
    (d.iter().sum::<f64>() / units, n.sqrt() * sd(d.iter().copied()) / units)
}

/// Training runs end at this fraction of the initial learning rate.
const FINAL_LR_FRACTION: f64 = 0.1;

/// A candidate's fit: the extension's parameter of `initial` trained for
/// [`DiagnoseConfig::candidate_steps`], the base held fixed.
fn refit(
    train_data: &Dataset,
    heldout: &Dataset,
    extension: Option<Extension>,
    initial: ParamStore<f64>,
    config: &DiagnoseConfig,
    dir: &Path,
    progress: &mut dyn FnMut(&Stage),
) -> Result<Fitted, String> {
    let steps = config.candidate_steps;
    fit(train_data, heldout, extension, initial, steps, config.candidate_lr, config, dir, progress)
}

/// A finished training run.
struct Fitted {
    params: ParamStore<f64>,
    skipped: usize,
    seconds: f64,
}

/// Trains `initial` (with `extension`, if any) by PF-SEFI for `steps` at learning
/// rate `lr` decaying to a tenth, in `dir`, resuming a run found there.
#[allow(clippy::too_many_arguments)]
fn fit(
    train_data: &Dataset,
    heldout: &Dataset,
    extension: Option<Extension>,
    initial: ParamStore<f64>,
    steps: usize,
    lr: f64,
    config: &DiagnoseConfig,
    dir: &Path,
    progress: &mut dyn FnMut(&Stage),
) -> Result<Fitted, String> {
    let objective_config = ObjectiveConfig {
        estimator: Estimator::pf_sefi(config.lag),
        estimator_config: EstimatorConfig { particles: config.particles, ..EstimatorConfig::default() },
        scenes_per_step: config.scenes_per_step,
        eval_particles: config.eval_particles,
        extension,
        extension_only: extension.is_some(),
        proposal: config.proposal.filter(|_| config.train_with_proposal),
        eval_tempering: None,
    };
    let mut objective = SceneObjective::new(train_data, heldout.clone(), objective_config)?;
    let batches = crate::training::Objective::batches(&objective).max(1);
    let train_config = TrainConfig {
        lr,
        final_lr: Some(lr * FINAL_LR_FRACTION),
        clip: config.clip,
        epochs: steps.div_ceil(batches),
        eval_every: 0,
        checkpoint_every: 25,
        seed: config.seed,
        shuffle: true,
    };
    let model = extension.map_or("base".to_string(), |e| e.id().to_string());
    let resume = dir.join(CHECKPOINT_FILE).exists();
    let mut total = 0;
    let mut on_event = |e: &TrainEvent| match e {
        TrainEvent::Started { total_steps, .. } => total = *total_steps,
        TrainEvent::Step { step, .. } => progress(&Stage::Training { model: model.clone(), step: *step, total }),
        _ => {}
    };
    let outcome = train(&mut objective, initial, &train_config, dir, resume, &mut on_event)
        .map_err(|e| format!("training the {model} model in {}: {e}", dir.display()))?;
    Ok(Fitted { params: outcome.params, skipped: outcome.skipped_steps, seconds: outcome.seconds })
}

/// A model on the held-out objects: per-object log-likelihoods and the checks'
/// statistics per draw.
struct HeldOutEval {
    object_ll: Vec<f64>,
    units: usize,
    precision: EvalPrecision,
    /// `measured[k][c]`: statistic `c` of draw `k` on the measured data.
    measured: Vec<Vec<f64>>,
    /// `replicated[k][c]`: the same on replicated data.
    replicated: Vec<Vec<f64>>,
}

impl HeldOutEval {
    fn draws_of(&self, c: usize) -> Vec<(f64, f64)> {
        self.measured.iter().zip(&self.replicated).map(|(m, r)| (m[c], r[c])).collect()
    }
}

fn evaluate(
    heldout: &Dataset,
    params: &ParamStore<f64>,
    extension: Option<Extension>,
    config: &DiagnoseConfig,
) -> Result<HeldOutEval, String> {
    let models = Models::from_store(params, heldout.kind()).map_err(|e| e.to_string())?;
    models.visit(heldout, Evaluate { params, extension, config })?
}

struct Evaluate<'a> {
    params: &'a ParamStore<f64>,
    extension: Option<Extension>,
    config: &'a DiagnoseConfig,
}

impl ModelVisitor for Evaluate<'_> {
    type Output = Result<HeldOutEval, String>;
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) -> Self::Output {
        let model = ExtendedSsm::from_store(base, self.extension, self.params)?.with_proposal(self.config.proposal)?;
        posterior_predictive_checks(&model, self.config)
    }
}

/// Filters every object of `model`'s data with `config.eval_particles`,
/// `config.eval_runs` times with seeds `seed..seed + runs` (each object's
/// log-likelihood is that of the mean of the runs' likelihood estimates, refined
/// by [`refine_imprecise`] where the runs disagree), draws `config.draws` paths
/// per object from the first run's smoother (the filter's genealogy), and
/// evaluates the checks' statistics on measured and replicated data per draw.
fn posterior_predictive_checks<P: crate::vehicle::GaussianPolicy, O: ExtensibleObservation>(
    model: &ExtendedSsm<'_, '_, P, O>,
    config: &DiagnoseConfig,
) -> Result<HeldOutEval, String> {
    let (draws, seed) = (config.draws, config.seed);
    let steps = ParticleModel::num_steps(model);
    let filter = FilterConfig { particles: config.eval_particles, lag: 0, seed, ..FilterConfig::default() };
    let run = run_filter(model, &filter, |object| PathRecorder::new(steps, draws, stream_seed(seed ^ 0xd1a6, object)));
    let data = model.data();
    // Per object, the runs' likelihood estimates are averaged (not their logs):
    // each is unbiased, so their mean is an estimate with `runs` times the
    // particles, and one run that missed the likelihood's peak does not drag the
    // object's value down (log p_hat has a long lower tail).
    let mut per_run: Vec<Vec<f64>> = run.objects.iter().map(|o| vec![o.log_likelihood]).collect();
    for r in 1..config.eval_runs {
        let again = run_filter(model, &FilterConfig { seed: seed + r as u64, ..filter.clone() }, |_| ());
        per_run.iter_mut().zip(&again.objects).for_each(|(l, o)| l.push(o.log_likelihood));
    }
    let precision = refine_imprecise(model, &filter, &mut per_run, config.max_eval_particles, config.eval_tolerance);
    let object_ll: Vec<f64> = per_run.iter().map(|l| log_mean_exp(l)).collect();
    if let Some(bad) = object_ll.iter().position(|l| !l.is_finite()) {
        return Err(format!("the held-out log-likelihood of object {bad} is not finite"));
    }
    let mut measured = Vec::with_capacity(draws);
    let mut replicated = Vec::with_capacity(draws);
    for k in 0..draws {
        let mut rng = SmallRng::seed_from_u64(stream_seed(seed ^ 0x7e71, k));
        let real: Vec<ObjectSample> = run
            .observers
            .iter()
            .enumerate()
            .map(|(o, rec)| {
                let (states, actions) = &rec.paths[k];
                ObjectSample {
                    object: o,
                    states: states.clone(),
                    actions: actions.clone(),
                    observations: measured_observations::<O>(data, o),
                    accel_innovations: innovations(model, states, actions),
                }
            })
            .collect();
        let rep: Vec<ObjectSample> = real.iter().map(|s| replicate(model, s, &mut rng)).collect();
        measured.push(statistics(data, &real));
        replicated.push(statistics(data, &rep));
    }
    Ok(HeldOutEval { object_ll, units: run.observed_units(), precision, measured, replicated })
}

/// The dataset's observations of `object`.
fn measured_observations<O: ExtensibleObservation>(data: &Dataset, object: usize) -> ObjectObservations {
    O::to_observations((0..data.steps()).map(|t| O::items(data, object, t).to_vec()).collect())
}

/// A replicate of `sample` from `model`: actions drawn from the policy at the
/// path's states, observations drawn at the path's states — except at `t = 0`,
/// where the state is drawn from the object's prior (the `initial_lag` check
/// compares the smoother's initial states with the prior's) and the observation
/// at that state.
fn replicate<P: crate::vehicle::GaussianPolicy, O: ExtensibleObservation>(
    model: &ExtendedSsm<'_, '_, P, O>,
    sample: &ObjectSample,
    rng: &mut SmallRng,
) -> ObjectSample {
    let actions: Vec<Action> =
        sample.states[..sample.states.len() - 1].iter().map(|s| model.sample_action(s, rng)).collect();
    let mut states = sample.states.clone();
    states[0] = model.sample_initial_state(sample.object, rng);
    let mut items = Vec::new();
    let mut per_step: Vec<Vec<O::Item>> = Vec::with_capacity(states.len());
    for (t, s) in states.iter().enumerate() {
        items.clear();
        model.sample_observation(sample.object, t, s, rng, &mut items);
        per_step.push(items.clone());
    }
    let accel_innovations = innovations(model, &sample.states, &actions);
    ObjectSample {
        object: sample.object,
        states,
        actions,
        observations: O::to_observations(per_step),
        accel_innovations,
    }
}

/// The standardised acceleration innovations of a path's actions.
fn innovations<P: crate::vehicle::GaussianPolicy, O: ExtensibleObservation>(
    model: &ExtendedSsm<'_, '_, P, O>,
    states: &[State],
    actions: &[Action],
) -> Vec<f64> {
    states.iter().zip(actions).map(|(s, a)| model.accel_innovation_of(s, a)).collect()
}

/// Records one object's filter steps and, at the last, draws paths from the
/// genealogy with the final weights (the particle approximation of the smoother).
struct PathRecorder {
    steps: usize,
    draws: usize,
    seed: u64,
    states: Vec<Vec<f32>>,
    actions: Vec<Vec<f32>>,
    parents: Vec<Vec<usize>>,
    /// The drawn paths: states `x_0..x_T` and actions `a_1..a_T`.
    paths: Vec<(Vec<State>, Vec<Action>)>,
}

impl PathRecorder {
    fn new(steps: usize, draws: usize, seed: u64) -> Self {
        PathRecorder {
            steps,
            draws,
            seed,
            states: Vec::with_capacity(steps),
            actions: Vec::with_capacity(steps),
            parents: Vec::with_capacity(steps),
            paths: Vec::new(),
        }
    }
}

impl Observer for PathRecorder {
    fn step(&mut self, view: &StepView<'_>) {
        self.states.push(view.states.to_vec());
        self.actions.push(view.actions.to_vec());
        self.parents.push(view.parents.to_vec());
        if view.t + 1 < self.steps {
            return;
        }
        let n = view.n;
        let weights: Vec<f64> = view.log_weights.iter().map(|l| l.exp()).collect();
        let total: f64 = weights.iter().sum();
        let mut rng = SmallRng::seed_from_u64(self.seed);
        for _ in 0..self.draws {
            let mut u = rng.random::<f64>() * total;
            let mut i = n - 1;
            for (j, w) in weights.iter().enumerate() {
                if u < *w {
                    i = j;
                    break;
                }
                u -= w;
            }
            let mut states = vec![State::default(); self.steps];
            let mut actions = vec![Action::default(); self.steps - 1];
            for t in (0..self.steps).rev() {
                states[t] = state_at(&self.states[t], n, i);
                if t > 0 {
                    let a = &self.actions[t];
                    actions[t - 1] = Action { accel: a[i] as f64, pinch: a[n + i] as f64 };
                    i = self.parents[t][i];
                }
            }
            self.paths.push((states, actions));
        }
        // The genealogy is no longer needed: free it.
        self.states = Vec::new();
        self.actions = Vec::new();
        self.parents = Vec::new();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lgssm::{Lgssm, LgssmTheta};
    use crate::linear_gaussian::LgssmBatch;

    /// An object whose runs disagree is re-run with more particles, until they
    /// agree; the others keep their runs; without room to double, nothing changes.
    #[test]
    fn refine_imprecise_reruns_only_disagreeing_objects() {
        let model = Lgssm::new(0.0, 1.0, LgssmTheta::new(0.9, 0.5, 0.7)).unwrap();
        let ys: Vec<Vec<f64>> =
            (0..3).map(|o| (0..20).map(|t| ((t * 7 + o * 3) % 11) as f64 * 0.2 - 1.0).collect()).collect();
        let batch = LgssmBatch::new(model.clone(), ys.clone()).unwrap();
        let filter = FilterConfig { particles: 256, lag: 0, seed: 9, ..FilterConfig::default() };
        let fake = vec![vec![-100.0, -10.0, -50.0], vec![-5.0, -5.1, -5.05], vec![-7.0, -7.2, -7.1]];

        let mut stuck = fake.clone();
        let none = refine_imprecise(&batch, &filter, &mut stuck, 256, 2.0);
        assert_eq!(stuck, fake, "no room to double: the runs stay");
        assert_eq!((none.refined_objects, none.imprecise_objects, none.max_particles), (0, 1, 256));

        let mut per_run = fake.clone();
        let p = refine_imprecise(&batch, &filter, &mut per_run, 4096, 2.0);
        assert_eq!(&per_run[1..], &fake[1..], "precise objects keep their runs");
        assert_eq!((p.refined_objects, p.imprecise_objects), (1, 0));
        assert!(p.max_particles >= 512 && p.max_particles <= 4096);
        assert!(p.max_run_sd <= 2.0 && run_sd(&per_run[0]) <= 2.0);
        let exact = model.log_likelihood(&ys[0]);
        for ll in &per_run[0] {
            assert!((ll - exact).abs() < 2.0, "re-run estimate {ll} vs Kalman {exact}");
        }
    }
}
