//! The supervised observation model: an observation network fitted to a dataset's
//! **labelled states** rather than learned from the observations alone.
//!
//! The fit maximises the AOTLL of SPEC §5 — the mean `log g(y_t | true x_t)` per
//! observed item — over the training data: every (object, step) with a true state
//! and at least one observed item becomes an [`Example`] (the true pose, the AV's
//! pose and the object's extents, the items), and [`fit_network`] climbs the mean
//! log-density per item with Adam on minibatches of them. This is the reference
//! the paper compares the unsupervised learners' observation models with on
//! measured data: the best AOTLL a network of this shape reaches when the states
//! are known. It works for any [`ObservationModel`] (points or box detections).
//!
//! * [`labelled_examples`]: the examples of a dataset.
//! * [`fit_supervised`]: a fresh network (standard initialisation under
//!   [`OBS_PREFIX`]) fitted to a dataset; returns the model, its parameter store
//!   and a [`SupervisedReport`].
//! * [`fit_observation`]: the same for the observation part of [`Models`] of
//!   either kind, in place (warm-started from its current parameters), so a
//!   supervised observation network can be paired with any policy.
//! * [`fit_observation_with_flips`]: the supervised fit of the box model
//!   extended by reversed headings (the catalogue's `heading_flip`). With the
//!   states labelled, which detections are flipped is observed (their heading
//!   is more than pi/2 from the label's), so the complete-data maximum-likelihood
//!   fit is the network fitted to every detection with the flipped ones turned
//!   back, and the flip fraction is their share.
//!
//! The AOTLL reported is the one [`crate::evaluation::metrics::aotll`] computes on the same
//! dataset (the same items, the same per-item densities).
//!
//! ```
//! use rand::{rngs::StdRng, SeedableRng};
//! use ssm::models::observation::PointObservationModel;
//! use ssm::training::supervised::{fit_supervised, SupervisedConfig};
//! use ssm::simulation::synthetic::{generate_experiment, Experiment, ExperimentConfig};
//!
//! let data = generate_experiment(&ExperimentConfig::quick(Experiment::A), &mut StdRng::seed_from_u64(0), &mut |_| {})
//!     .unwrap();
//! let mut config = SupervisedConfig::default();
//! config.fit.steps = 50;
//! let fitted = fit_supervised::<PointObservationModel>(&data.train, &config).unwrap();
//! assert!(fitted.report.final_aotll > fitted.report.initial_aotll);
//! assert!(fitted.params.iter().all(|(name, _)| name.starts_with("obs.")));
//! ```

use std::fmt;

use autodiff::nn::ParamStore;
use rand::rngs::StdRng;
use rand::SeedableRng;
use serde::Serialize;

use crate::data::{Dataset, ObservationKind};
use crate::models::extended::{ExtensibleObservation, Extension};
use crate::models::observation::{fit_network, labelled_steps, Example, FitConfig, ObservationModel, OBS_PREFIX};
use crate::models::params::{FittedExtension, Models, ObservationVisitor};

/// Why a supervised fit cannot run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SupervisedError {
    /// The dataset has no `states.csv`: there is nothing to supervise with.
    NoStates,
    /// The dataset holds the other kind of observation.
    Kind {
        /// What the dataset holds.
        data: ObservationKind,
        /// What the model reads.
        model: ObservationKind,
    },
    /// No (object, step) has both a true state and an observed item.
    NoExamples,
}

impl fmt::Display for SupervisedError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SupervisedError::NoStates => {
                write!(f, "supervised fitting needs labelled states (states.csv); the dataset has none")
            }
            SupervisedError::Kind { data, model } => {
                write!(f, "the dataset holds {data:?} observations; the observation model reads {model:?}")
            }
            SupervisedError::NoExamples => {
                write!(f, "no object step has both a labelled state and an observation: nothing to fit")
            }
        }
    }
}

impl std::error::Error for SupervisedError {}

/// Settings of [`fit_supervised`].
#[derive(Clone, Debug, PartialEq)]
pub struct SupervisedConfig {
    /// The optimiser: Adam steps, minibatch size, learning rate, clipping, and the
    /// seed of the minibatch draws.
    pub fit: FitConfig,
    /// Seed of the network's initial weights.
    pub init_seed: u64,
}

impl Default for SupervisedConfig {
    /// [`FitConfig::default`] (2,000 Adam steps of 128 examples, learning rate
    /// 0.01, no clipping) and initial weights from seed 0.
    fn default() -> Self {
        SupervisedConfig { fit: FitConfig::default(), init_seed: 0 }
    }
}

/// What a supervised fit did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SupervisedReport {
    /// Examples: (object, step) cells with a true state and at least one item.
    pub examples: usize,
    /// Observed items (points, detections) in the examples: the AOTLL's normaliser.
    pub items: usize,
    /// AOTLL (nats per item) of the training data before fitting.
    pub initial_aotll: f64,
    /// AOTLL of the training data after fitting.
    pub final_aotll: f64,
    /// Adam steps taken.
    pub steps: usize,
    /// Steps skipped because the gradient was not finite.
    pub skipped: usize,
}

/// A fitted network: the model (a layout), its parameters under [`OBS_PREFIX`]
/// and what the fit did.
#[derive(Clone, Debug, PartialEq)]
pub struct Supervised<O> {
    /// The observation model, referring to `params`.
    pub model: O,
    /// The fitted network's parameters (names `obs.0.w`, `obs.0.b`, ...).
    pub params: ParamStore<f64>,
    /// What the fit did.
    pub report: SupervisedReport,
}

/// The labelled examples of `data`: one per (object, step) with a true state and at
/// least one observed item, in object-major order. Fails if `data` has no states or
/// holds the other kind of observation.
pub fn labelled_examples<O: ObservationModel>(data: &Dataset) -> Result<Vec<Example<O::Item>>, SupervisedError> {
    if data.kind() != O::KIND {
        return Err(SupervisedError::Kind { data: data.kind(), model: O::KIND });
    }
    let truth = data.states().ok_or(SupervisedError::NoStates)?;
    Ok(labelled_steps::<O>(data, truth)
        .map(|(ctx, pose, items)| Example { ctx, pose, items: items.to_vec() })
        .collect())
}

/// Fits `model`'s parameters in `params` (from their current values) to the
/// labelled states of `data` by maximum AOTLL with [`fit_network`]. Parameters of
/// `params` the model does not use are left unchanged.
pub fn fit_supervised_params<O: ObservationModel>(
    model: &O,
    params: &mut ParamStore<f64>,
    data: &Dataset,
    fit: &FitConfig,
) -> Result<SupervisedReport, SupervisedError> {
    fit_params_on(model, params, &labelled_examples::<O>(data)?, fit)
}

/// [`fit_network`] on `examples`, reported.
fn fit_params_on<O: ObservationModel>(
    model: &O,
    params: &mut ParamStore<f64>,
    examples: &[Example<O::Item>],
    fit: &FitConfig,
) -> Result<SupervisedReport, SupervisedError> {
    if examples.is_empty() {
        return Err(SupervisedError::NoExamples);
    }
    let report = fit_network(model, params, examples, fit);
    Ok(SupervisedReport {
        examples: examples.len(),
        items: examples.iter().map(|e| e.items.len()).sum(),
        initial_aotll: report.initial_aotll,
        final_aotll: report.final_aotll,
        steps: report.steps,
        skipped: report.skipped,
    })
}

/// A fresh observation network of type `O` (standard initialisation from
/// `config.init_seed`, parameters under [`OBS_PREFIX`]) fitted to the labelled
/// states of `data` by maximum AOTLL.
pub fn fit_supervised<O: ObservationModel>(
    data: &Dataset,
    config: &SupervisedConfig,
) -> Result<Supervised<O>, SupervisedError> {
    let mut params = ParamStore::new();
    let model = O::init_params(&mut params, OBS_PREFIX, &mut StdRng::seed_from_u64(config.init_seed));
    let report = fit_supervised_params(&model, &mut params, data, &config.fit)?;
    Ok(Supervised { model, params, report })
}

/// Fits the observation network of `models` (points or boxes, from its current
/// parameters) to the labelled states of `data` in place; the policy is untouched.
/// With [`Models::initial`] this is a fresh supervised network beside any policy.
pub fn fit_observation(
    models: &mut Models,
    data: &Dataset,
    fit: &FitConfig,
) -> Result<SupervisedReport, SupervisedError> {
    let fitted = Fit { params: &mut models.observation_params, data, fit, turn_back_flips: false };
    models.observation.visit(fitted).map(|(report, _)| report)
}

/// The supervised fit of the visited observation model to `data`'s labelled
/// examples, with the items reversed against their labels turned back if
/// `turn_back_flips`: its report and the share of items turned back.
struct Fit<'a> {
    params: &'a mut ParamStore<f64>,
    data: &'a Dataset,
    fit: &'a FitConfig,
    turn_back_flips: bool,
}

impl ObservationVisitor for Fit<'_> {
    type Output = Result<(SupervisedReport, f64), SupervisedError>;
    fn visit<O: ExtensibleObservation>(self, o: &O) -> Self::Output {
        let TurnedBack { examples, flipped } = if self.turn_back_flips {
            examples_with_flips_turned_back::<O>(self.data)?
        } else {
            TurnedBack { examples: labelled_examples::<O>(self.data)?, flipped: 0 }
        };
        let report = fit_params_on(o, self.params, &examples, self.fit)?;
        let fraction = flipped as f64 / report.items.max(1) as f64;
        Ok((report, fraction))
    }
}

/// Labelled examples with the items reversed against their labels turned back
/// ([`examples_with_flips_turned_back`]).
pub struct TurnedBack<I> {
    /// The examples, every item's heading within pi/2 of its label's.
    pub examples: Vec<Example<I>>,
    /// How many items were turned back.
    pub flipped: usize,
}

/// The labelled examples of `data` ([`labelled_examples`]) with every item whose
/// heading is reversed against its label turned back, and how many items were.
pub fn examples_with_flips_turned_back<O: ExtensibleObservation>(
    data: &Dataset,
) -> Result<TurnedBack<O::Item>, SupervisedError> {
    let mut examples = labelled_examples::<O>(data)?;
    let mut flipped = 0;
    for e in &mut examples {
        for item in &mut e.items {
            if O::heading_reversed(item, e.pose) {
                *item = O::reverse_heading(item);
                flipped += 1;
            }
        }
    }
    Ok(TurnedBack { examples, flipped })
}

/// The supervised fit of `models`' observation network extended by reversed
/// headings, in place (see the module documentation): the network fitted to the
/// labelled detections of `data` with the flipped ones turned back, and
/// [`Models::extension`] set to `heading_flip` at their share of the detections.
/// The report's AOTLLs are the network's on the turned-back detections. Fails on
/// data without flipped detections (a fraction of zero has no stored value) or
/// as [`fit_observation`].
pub fn fit_observation_with_flips(
    models: &mut Models,
    data: &Dataset,
    fit: &FitConfig,
) -> Result<SupervisedReport, String> {
    let fitted = Fit { params: &mut models.observation_params, data, fit, turn_back_flips: true };
    let (report, fraction) = models.observation.visit(fitted).map_err(|e| e.to_string())?;
    let flip = Extension::HeadingFlip;
    let raw = flip.stored(&[fraction]).map_err(|_| {
        format!("no detection of the data reports its heading reversed (fraction {fraction}): nothing to fit")
    })?;
    models.extension = Some(FittedExtension { extension: flip, raw });
    Ok(report)
}
