//! The catalogue of model extensions (SPEC §7): each is a hypothesis about what
//! the base vehicle model gets wrong, made a model component with learnable
//! parameters, so PF-SEFI fits it exactly as it fits the base.
//!
//! | id | what it adds | parameters (physical) |
//! |---|---|---|
//! | `latency` | the observation at `t` is of the pose [`lagged_pose`] a delay earlier | delay (s) |
//! | `clutter` | a fraction of points are not on the box: an isotropic Gaussian around its centre | fraction, sd (m) |
//! | `size_bias` | the true extents are the given ones times learnable factors | length and width factors |
//! | `heavy_tailed_accel` | the acceleration's innovation is a unit-variance scale mixture of two normals | fraction, sd ratio |
//! | `heading_flip` | a fraction of detections report the heading reversed by pi | fraction |
//! | `persistent_flip` | the same, in runs: a per-object two-state Markov chain ([`FlipChain`]) | fraction, persistence |
//!
//! [`ExtendedSsm`] wraps a [`VehicleSsm`] with at most one extension: it is a
//! [`ParticleModel`] (the filter), a [`DifferentiableModel`] (the estimators) and
//! a simulator of replicated observations and actions (the checks). With no
//! extension it is the base model, value for value.
//!
//! `persistent_flip` puts the chain's indicator and the probability it was
//! predicted with in the state, after the drift's offsets (if any); the
//! filters weight by the mixture over the indicator and draw it from its
//! posterior (`ExtendedSsm::flip_dims`). Its prior is the chain's stationary
//! law, whose score [`DifferentiableModel::prior_log_density`] gives.
//!
//! `heading_flip` (and `persistent_flip`) also changes the prior where the data's priors were read from
//! each object's first detection ([`crate::data::Meta::prior_from_detection`],
//! KITTI's import): a model that says a detection's heading may be reversed
//! cannot take the prior built from one at its word, so `x_0`'s heading is the
//! prior's or its reverse, each with probability 1/2 (an axial prior). The first
//! detection is scored by the likelihood as every other one, so the two
//! directions leave `t = 0` weighted `1 - p` and `p`, which is what that
//! detection says under the model; a fixed 1/2 keeps the prior free of the
//! model's parameters (its score is zero). Without it a track whose first
//! detection is reversed starts reversed, follows the car with a negative speed
//! and calls every later detection a flip.
//!
//! The extension's parameters live in the parameter store under
//! [`Extension::param_name`] (`ext.<id>`), after the base model's. They are stored
//! *scaled*: a stored value `r` means a natural value through a fixed map (for
//! instance fraction `sigmoid(8 r)`), chosen so that Adam's steps of the base
//! model's learning rate move each extension across its plausible range in tens
//! of steps rather than hundreds.
//!
//! A [`DetectorDrift`] (box detections only) may come with or without an
//! extension ([`ExtendedSsm::with_drift`]): its three standardised offsets are
//! appended to the state (dimensions `STATE_DIM..STATE_DIM + DRIFT_DIMS`), its
//! parameter tensor ([`DRIFT_PARAM`]) follows the extension's, and every
//! observation is scored at the pose the drifting detector sees.
//!
//! The reparameterised transition ([`DifferentiableModel::propagate_on_tape`],
//! used only by the through-filter baselines) is the base one: the heavy-tailed
//! component's mixture parameters get their gradient through the transition
//! log-density, which is what PF-SEFI differentiates.

use autodiff::dist::LN_2PI;
use autodiff::nn::{BoundParams, ParamStore};
use autodiff::{Float, Tensor, Var};
use rand::rngs::SmallRng;
use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use crate::data::{Action, BoxDetection, Dataset, ObservationKind, Pose, State};
use crate::models::drift::{DetectorDrift, DriftVars, DRIFT_DIMS, DRIFT_PARAM};
use crate::models::flip_chain::{is_reversed, FlipChain, FlipChainVars, LOGIT_SCALE};
use crate::models::observation::points::Clutter;
use crate::models::observation::{
    BoxObservationModel, ObsContext, ObservationModel, PointObservationModel, PosesRef, RowVars, Scratch, OBS_PREFIX,
};
use crate::models::road_user::{states_mut, states_ref, VehicleScratch, VehicleSsm, YAW};
use crate::models::vehicle::policy::{ActionGaussians, GaussianPolicy};
use crate::models::vehicle::state::{ActionVars, ActionsMut, STATE_DIM};
use crate::models::{Batch, Block, DifferentiableModel, Drawn, ModelError, NoiseDims, ParticleModel};
use crate::stats::{bisect_increasing, log_sum_exp, normal_cdf};
use crate::util::angles::reversed_heading;
use crate::util::setting::SettingError;

/// One object's observations, per step `t = 0..T`, of either kind.
#[derive(Clone, Debug, PartialEq)]
pub enum ObjectObservations {
    /// Point sets (possibly empty) per step.
    Points(Vec<Vec<[f64; 2]>>),
    /// At most one detection per step.
    Boxes(Vec<Option<BoxDetection>>),
}

/// The pose seen by a sensor whose observations lag the state by `delay` seconds:
/// the state extrapolated back along its own motion at constant speed and
/// curvature, `x - delay v cos(yaw)`, `y - delay v sin(yaw)`, `yaw - delay v kappa`
/// (first order in the delay; the `latency` extension and its generator share it).
pub fn lagged_pose(state: &State, delay: f64) -> Pose {
    let d = delay * state.v;
    Pose { x: state.x - d * state.yaw.cos(), y: state.y - d * state.yaw.sin(), yaw: state.yaw - d * state.kappa }
}

/// Name prefix of the extensions' parameters.
pub const EXTENSION_PREFIX: &str = "ext";

/// Stored log-scales are multiplied by this: a positive quantity is `exp(LOG_SCALE r)`.
const LOG_SCALE: f64 = 2.0;
/// A delay is `softplus(DELAY_SHARPNESS r) / DELAY_SHARPNESS` seconds: never
/// negative (observations cannot lead the state), about `r` once above a few
/// hundredths of a second.
const DELAY_SHARPNESS: f64 = 20.0;
/// Initial delay (s).
const INITIAL_DELAY: f64 = 0.01;
/// Largest delay a check may suggest as a start (s).
const MAX_INITIAL_DELAY: f64 = 1.0;
/// Initial fraction of the mixture components (clutter, heavy tails, flips).
const INITIAL_FRACTION: f64 = 0.02;
/// Initial persistence of `persistent_flip`: halfway between independent flips
/// (0) and a flip that stays for the whole track (1), a stated rule.
const INITIAL_PERSISTENCE: f64 = 0.5;
/// Range of the persistence a check may suggest as a start: clear of both
/// ends of the logit, where its gradient vanishes.
const MIN_INITIAL_PERSISTENCE: f64 = 0.05;
const MAX_INITIAL_PERSISTENCE: f64 = 0.95;
/// Least persistence for `persistent_flip` to be a material change over
/// independent flips (`heading_flip`, persistence 0).
const MATERIAL_PERSISTENCE: f64 = 0.1;
/// Initial sd of the clutter Gaussian (m).
const INITIAL_CLUTTER_SD: f64 = 2.0;
/// Initial sd ratio of the heavy-tailed acceleration component when no check
/// measured a kurtosis: a component three times as wide, clearly heavier without
/// claiming any particular tail.
const INITIAL_TAIL_RATIO: f64 = 3.0;
/// Fraction of the heavy-tailed component when its start comes from the measured
/// kurtosis (see [`Extension::initial_from_checks`]).
const KURTOSIS_START_FRACTION: f64 = 0.05;
/// Widest start of the heavy-tailed component's sd ratio.
const MAX_INITIAL_TAIL_RATIO: f64 = 20.0;

/// Mixture fractions are kept in `[FRACTION_GUARD, 1 - FRACTION_GUARD]` on the plain paths.
const FRACTION_GUARD: f64 = 1e-12;

/// Which of the base's parameters a refit moves beside an extension's own
/// ([`Extension::refit_scope`]). A refit lets the base give back what it bent
/// to absorb an effect it lacked; parameters the effect could not have bent
/// are held at the base's fit, since moving them again from a converged fit
/// only adds the noise of the refit (measured on point sets: refitted from the
/// base, the observation network lowers the check objects' likelihood by up to
/// 0.03 nats per point as it keeps fitting the fit objects, where the policy
/// refitted alone leaves it within 0.002; README, "Refits that hold the
/// observation network").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RefitScope {
    /// Every parameter of the base (the policy and the observation network).
    #[default]
    All,
    /// The policy's parameters; the observation network (`obs.*`) is held.
    Dynamics,
}

impl RefitScope {
    /// Both scopes, in the order a diagnosis fits their references.
    pub const ALL: [RefitScope; 2] = [RefitScope::All, RefitScope::Dynamics];

    /// The names of `store`'s parameters a refit of this scope holds at their
    /// values (none for [`RefitScope::All`]; the observation model's,
    /// `obs.*`, for [`RefitScope::Dynamics`]).
    pub fn held(self, store: &ParamStore<f64>) -> Vec<String> {
        match self {
            RefitScope::All => Vec::new(),
            RefitScope::Dynamics => {
                let prefix = format!("{OBS_PREFIX}.");
                store.iter().map(|(name, _)| name).filter(|n| n.starts_with(&prefix)).map(String::from).collect()
            }
        }
    }
}

/// One entry of the catalogue.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Extension {
    /// Observations lag the state by a learnable delay.
    Latency,
    /// A learnable fraction of points are clutter, not on the box (points only).
    Clutter,
    /// True extents differ from the given ones by learnable factors (points only).
    SizeBias,
    /// Accelerations are heavier-tailed than Gaussian: the policy's standardised
    /// acceleration innovation is `(1 - p) N(0, c^2) + p N(0, (k c)^2)` with `c` such
    /// that its variance stays 1 (the policy's sd is the overall sd).
    HeavyTailedAccel,
    /// A learnable fraction of detections have their heading reversed (boxes only).
    HeadingFlip,
    /// The same in runs: whether a detection is reversed follows a per-object
    /// two-state Markov chain with a learnable fraction and persistence
    /// ([`FlipChain`]; boxes only).
    PersistentFlip,
}

impl Extension {
    /// The whole catalogue, in a fixed order.
    pub const ALL: [Extension; 6] = [
        Extension::Latency,
        Extension::Clutter,
        Extension::SizeBias,
        Extension::HeavyTailedAccel,
        Extension::HeadingFlip,
        Extension::PersistentFlip,
    ];

    /// The catalogue id (`latency`, `clutter`, `size_bias`, `heavy_tailed_accel`,
    /// `heading_flip`, `persistent_flip`).
    pub fn id(self) -> &'static str {
        match self {
            Extension::Latency => "latency",
            Extension::Clutter => "clutter",
            Extension::SizeBias => "size_bias",
            Extension::HeavyTailedAccel => "heavy_tailed_accel",
            Extension::HeadingFlip => "heading_flip",
            Extension::PersistentFlip => "persistent_flip",
        }
    }

    /// The catalogue entry this one contains as a special case, if any:
    /// `persistent_flip` at persistence 0 is `heading_flip`. A diagnosis names
    /// the larger only where it beats the smaller by object (its extra
    /// parameter must earn its place). The nested entry's values come first
    /// among this one's, stored alike ([`Extension::start_from_nested`]).
    pub fn nests(self) -> Option<Extension> {
        match self {
            Extension::PersistentFlip => Some(Extension::HeadingFlip),
            _ => None,
        }
    }

    /// Which of the base's parameters a refit with this extension moves
    /// beside the extension's own ([`RefitScope`]): the policy alone for an
    /// extension of the dynamics (heavy-tailed accelerations), every parameter
    /// for one of the observations, which the base's observation network and
    /// its policy may both have bent to absorb.
    pub fn refit_scope(self) -> RefitScope {
        match self {
            Extension::HeavyTailedAccel => RefitScope::Dynamics,
            _ => RefitScope::All,
        }
    }

    /// Stored initial values of this extension from the fitted stored values
    /// `nested` of the extension it nests ([`Extension::nests`]) and its own start
    /// `own`: the values the two share from the fit (the nested extension's
    /// stored values are the first of this one's, on the same scale: the chain's
    /// fraction is the independent flips' fraction), the rest (the persistence)
    /// from `own`. `None` where this extension nests none or `nested` is not its
    /// nested extension's values.
    pub fn start_from_nested(self, nested: &[f64], own: &Tensor<f64>) -> Option<Tensor<f64>> {
        let shared = self.nests()?.initial().numel();
        (nested.len() == shared && own.numel() == self.initial().numel()).then(|| {
            let mut raw = own.data().to_vec();
            raw[..shared].copy_from_slice(nested);
            Tensor::from_vec(raw)
        })
    }

    /// The extension with catalogue id `id`.
    pub fn from_id(id: &str) -> Result<Extension, SettingError> {
        Extension::ALL.into_iter().find(|e| e.id() == id).ok_or_else(|| {
            let known: Vec<&str> = Extension::ALL.iter().map(|e| e.id()).collect();
            SettingError::new("extension", id, format!("a model extension: {}", known.join(", ")))
        })
    }

    /// Whether the extension means something for data of `kind`.
    pub fn applies_to(self, kind: ObservationKind) -> bool {
        match self {
            Extension::Latency | Extension::HeavyTailedAccel => true,
            Extension::Clutter | Extension::SizeBias => kind == ObservationKind::Points,
            Extension::HeadingFlip | Extension::PersistentFlip => kind == ObservationKind::Boxes,
        }
    }

    /// The catalogue entries for data of `kind`.
    pub fn for_kind(kind: ObservationKind) -> Vec<Extension> {
        Extension::ALL.into_iter().filter(|e| e.applies_to(kind)).collect()
    }

    /// The name of its parameter tensor in a store: `ext.<id>`.
    pub fn param_name(self) -> String {
        format!("{EXTENSION_PREFIX}.{}", self.id())
    }

    /// The stored initial values: close to the base model (no delay, 2% of a
    /// mixture component, unit factors) but with non-zero gradients.
    pub fn initial(self) -> Tensor<f64> {
        let logit = |p: f64| (p / (1.0 - p)).ln() / LOGIT_SCALE;
        let log = |x: f64| x.ln() / LOG_SCALE;
        Tensor::from_vec(match self {
            Extension::Latency => vec![(DELAY_SHARPNESS * INITIAL_DELAY).exp_m1().ln() / DELAY_SHARPNESS],
            Extension::Clutter => vec![logit(INITIAL_FRACTION), log(INITIAL_CLUTTER_SD)],
            Extension::SizeBias => vec![0.0, 0.0],
            Extension::HeavyTailedAccel => vec![logit(INITIAL_FRACTION), log(INITIAL_TAIL_RATIO - 1.0)],
            Extension::HeadingFlip => vec![logit(INITIAL_FRACTION)],
            Extension::PersistentFlip => vec![logit(INITIAL_FRACTION), logit(INITIAL_PERSISTENCE)],
        })
    }

    /// Stored initial values informed by what the checks measured: for each check
    /// `(name, measured - replicated)`. A sensor lag shows directly in
    /// `initial_lag` (about minus the delay) and reversed headings in
    /// `yaw_reversal_fraction` (the excess fraction), so those extensions start
    /// there, persistent flips with the excess lag-one correlation of the
    /// reversals `yaw_reversal_persistence` measured as their persistence (in
    /// [0.05, 0.95]); heavy tails start at 5% of draws with the sd ratio whose mixture has
    /// the excess kurtosis `accel_kurtosis` measured beyond the replicates (or,
    /// without one, the Geary ratio `accel_peakedness` measured below them). The
    /// others (and these without their check) start at [`Extension::initial`].
    /// Training then takes it from there.
    pub fn initial_from_checks(self, discrepancies: &[(&str, f64)]) -> Tensor<f64> {
        let find = |name: &str| discrepancies.iter().find(|(n, _)| *n == name).map(|d| d.1).filter(|d| d.is_finite());
        let logit = |p: f64| (p / (1.0 - p)).ln() / LOGIT_SCALE;
        match self {
            Extension::Latency => match find("initial_lag") {
                Some(lag) if -lag > INITIAL_DELAY => {
                    let delay = (-lag).min(MAX_INITIAL_DELAY);
                    Tensor::from_vec(vec![(DELAY_SHARPNESS * delay).exp_m1().ln() / DELAY_SHARPNESS])
                }
                _ => self.initial(),
            },
            Extension::HeadingFlip | Extension::PersistentFlip => {
                let mut raw = self.initial().data().to_vec();
                let fraction = match find("yaw_reversal_fraction") {
                    Some(excess) if excess > INITIAL_FRACTION => excess.min(0.5),
                    _ => INITIAL_FRACTION,
                };
                raw[0] = logit(fraction);
                // The chain's persistence is the lag-one correlation of its
                // indicators, which the check measures.
                if let (Extension::PersistentFlip, Some(excess)) = (self, find("yaw_reversal_persistence")) {
                    if excess > 0.0 {
                        raw[1] = logit(excess.clamp(MIN_INITIAL_PERSISTENCE, MAX_INITIAL_PERSISTENCE));
                    }
                }
                Tensor::from_vec(raw)
            }
            Extension::HeavyTailedAccel => {
                let from_kurtosis = find("accel_kurtosis")
                    .filter(|&excess| excess > 0.0)
                    .map(|excess| tail_ratio_for_kurtosis(KURTOSIS_START_FRACTION, excess));
                let from_peakedness = find("accel_peakedness")
                    .filter(|&d| d < 0.0)
                    .map(|d| tail_ratio_for_geary(KURTOSIS_START_FRACTION, GAUSSIAN_GEARY_RATIO + d));
                match from_kurtosis.or(from_peakedness) {
                    Some(ratio) => {
                        Tensor::from_vec(vec![logit(KURTOSIS_START_FRACTION), (ratio - 1.0).ln() / LOG_SCALE])
                    }
                    None => self.initial(),
                }
            }
            _ => self.initial(),
        }
    }

    /// The natural values of stored parameters `raw`: `(name, value, unit)`.
    /// Fails if `raw` has the wrong length or is not finite.
    pub fn natural(self, raw: &[f64]) -> Result<Vec<(&'static str, f64, &'static str)>, ModelError> {
        let expected = self.initial().numel();
        if raw.len() != expected || !raw.iter().all(|x| x.is_finite()) {
            return Err(ModelError::ExtensionValues { param: self.param_name(), expected, got: raw.to_vec() });
        }
        let fraction = |r: f64| (LOGIT_SCALE * r).sigmoid();
        let positive = |r: f64| (LOG_SCALE * r).exp();
        Ok(match self {
            Extension::Latency => vec![("delay", (DELAY_SHARPNESS * raw[0]).softplus() / DELAY_SHARPNESS, "s")],
            Extension::Clutter => vec![("fraction", fraction(raw[0]), ""), ("sd", positive(raw[1]), "m")],
            Extension::SizeBias => {
                vec![("length_factor", positive(raw[0]), ""), ("width_factor", positive(raw[1]), "")]
            }
            Extension::HeavyTailedAccel => {
                vec![("fraction", fraction(raw[0]), ""), ("sd_ratio", 1.0 + positive(raw[1]), "")]
            }
            Extension::HeadingFlip => vec![("fraction", fraction(raw[0]), "")],
            Extension::PersistentFlip => {
                vec![("fraction", fraction(raw[0]), ""), ("persistence", fraction(raw[1]), "")]
            }
        })
    }

    /// The stored values whose [`Extension::natural`] values are `natural` (in
    /// its order and units): the inverse of `natural`. Fails on the wrong number
    /// of values or one outside its range (a fraction in (0, 1), a delay, sd or
    /// factor > 0, an sd ratio > 1).
    pub fn stored(self, natural: &[f64]) -> Result<Vec<f64>, ModelError> {
        let expected = self.initial().numel();
        let logit = |p: f64| (p > 0.0 && p < 1.0).then(|| (p / (1.0 - p)).ln() / LOGIT_SCALE);
        let log = |x: f64| (x > 0.0).then(|| x.ln() / LOG_SCALE);
        let raw: Option<Vec<f64>> = (natural.len() == expected && natural.iter().all(|x| x.is_finite()))
            .then(|| match self {
                Extension::Latency => {
                    let d = natural[0];
                    (d > 0.0).then(|| vec![(DELAY_SHARPNESS * d).exp_m1().ln() / DELAY_SHARPNESS])
                }
                Extension::Clutter => Some(vec![logit(natural[0])?, log(natural[1])?]),
                Extension::SizeBias => Some(vec![log(natural[0])?, log(natural[1])?]),
                Extension::HeavyTailedAccel => Some(vec![logit(natural[0])?, log(natural[1] - 1.0)?]),
                Extension::HeadingFlip => Some(vec![logit(natural[0])?]),
                Extension::PersistentFlip => Some(vec![logit(natural[0])?, logit(natural[1])?]),
            })
            .flatten();
        raw.ok_or_else(|| ModelError::ExtensionValues { param: self.param_name(), expected, got: natural.to_vec() })
    }

    /// Whether stored values `raw` make a material change to the base model: a
    /// delay of at least 30 ms, a mixture fraction of at least 3% (above the 2%
    /// start) with, for heavy tails, an sd ratio of at least 2 and, for
    /// persistent flips, a persistence of at least 0.1 (else they are
    /// `heading_flip`'s independent ones), or an extent off by at least 3%. An extension that stayed at its start cannot be a cause,
    /// whatever the held-out comparison says (two fits differ a little anyway).
    pub fn is_material(self, raw: &[f64]) -> Result<bool, ModelError> {
        let v: Vec<f64> = self.natural(raw)?.iter().map(|p| p.1).collect();
        Ok(match self {
            Extension::Latency => v[0] >= 0.03,
            Extension::Clutter | Extension::HeadingFlip => v[0] >= 0.03,
            Extension::SizeBias => v.iter().any(|f| (f - 1.0).abs() >= 0.03),
            Extension::HeavyTailedAccel => v[0] >= 0.03 && v[1] >= 2.0,
            Extension::PersistentFlip => v[0] >= 0.03 && v[1] >= MATERIAL_PERSISTENCE,
        })
    }

    /// One sentence in physical units, e.g. "observations lag the state by 0.12 s".
    pub fn describe(self, raw: &[f64]) -> Result<String, ModelError> {
        let v: Vec<f64> = self.natural(raw)?.iter().map(|p| p.1).collect();
        Ok(match self {
            Extension::Latency => format!("observations lag the state by {:.3} s", v[0]),
            Extension::Clutter => format!(
                "{:.1}% of points are clutter, scattered with sd {:.2} m around the object's centre",
                100.0 * v[0],
                v[1]
            ),
            Extension::SizeBias => {
                format!("true extents are {:.3} x the given length and {:.3} x the given width", v[0], v[1])
            }
            Extension::HeavyTailedAccel => format!(
                "{:.1}% of accelerations have {:.2} x the sd of the others, at the policy's overall sd (excess \
                 kurtosis {:.2})",
                100.0 * v[0],
                v[1],
                mixture_excess_kurtosis(v[0], v[1])
            ),
            Extension::HeadingFlip => format!("{:.1}% of detections report the heading reversed", 100.0 * v[0]),
            Extension::PersistentFlip => {
                let chain = FlipChain { fraction: v[0], persistence: v[1] };
                format!(
                    "{:.1}% of detections report the heading reversed, in runs (persistence {:.2}: a reversed \
                     detection is followed by another with probability {:.2}, {:.1} steps in a row on average)",
                    100.0 * v[0],
                    v[1],
                    chain.reversed_probability(Some(true)),
                    chain.mean_run()
                )
            }
        })
    }
}

/// Excess kurtosis of `(1 - p) N(0, 1) + p N(0, k^2)`.
pub fn mixture_excess_kurtosis(p: f64, k: f64) -> f64 {
    let m2 = 1.0 - p + p * k * k;
    let m4 = 3.0 * (1.0 - p + p * k.powi(4));
    m4 / (m2 * m2) - 3.0
}

/// What an observation model offers the extensions beyond [`ObservationModel`]:
/// clutter (point sets only) and heading reversal (detections only). Implemented by
/// both observation models; an extension that does not apply to a model's kind is
/// refused by [`ExtendedSsm::new`], so a model never runs the other's hooks.
pub trait ExtensibleObservation: ObservationModel {
    /// The item with its heading reversed by pi (items without a heading: unchanged).
    fn reverse_heading(item: &Self::Item) -> Self::Item;

    /// Whether `item` reports the heading of an object at `pose` reversed: more
    /// than pi/2 from it (items without a heading: never).
    fn heading_reversed(item: &Self::Item, pose: Pose) -> bool;

    /// One object's observations from its items per step.
    fn to_observations(per_step: Vec<Vec<Self::Item>>) -> ObjectObservations;

    /// [`ObservationModel::log_likelihood`] with clutter mixed into every item.
    #[allow(clippy::too_many_arguments)]
    fn log_likelihood_with_clutter<F: Float>(
        &self,
        params: &ParamStore<F>,
        ctx: &ObsContext,
        poses: PosesRef<'_, F>,
        items: &[Self::Item],
        clutter: Clutter,
        scratch: &mut Scratch<F>,
        out: &mut [F],
    );

    /// [`ObservationModel::log_likelihood_rows`] with clutter (fraction
    /// `sigmoid(logit_fraction)`, sd `exp(log_scale)`, both of shape `[1]`).
    fn log_likelihood_rows_with_clutter<'t, F: Float>(
        &self,
        params: &BoundParams<'t, F>,
        rows: &RowVars<'t, F>,
        av: &[Pose],
        items: &[&[Self::Item]],
        logit_fraction: Var<'t, F>,
        log_scale: Var<'t, F>,
    ) -> Var<'t, F>;

    /// [`ObservationModel::sample`] with clutter.
    #[allow(clippy::too_many_arguments)]
    fn sample_with_clutter(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        n: usize,
        clutter: Clutter,
        rng: &mut SmallRng,
        out: &mut Vec<Self::Item>,
    );
}

impl ExtensibleObservation for PointObservationModel {
    fn reverse_heading(item: &[f64; 2]) -> [f64; 2] {
        *item
    }

    fn heading_reversed(_item: &[f64; 2], _pose: Pose) -> bool {
        false
    }

    fn to_observations(per_step: Vec<Vec<[f64; 2]>>) -> ObjectObservations {
        ObjectObservations::Points(per_step)
    }

    fn log_likelihood_with_clutter<F: Float>(
        &self,
        params: &ParamStore<F>,
        ctx: &ObsContext,
        poses: PosesRef<'_, F>,
        items: &[[f64; 2]],
        clutter: Clutter,
        scratch: &mut Scratch<F>,
        out: &mut [F],
    ) {
        PointObservationModel::log_likelihood_with_clutter(self, params, ctx, poses, items, clutter, scratch, out)
    }

    fn log_likelihood_rows_with_clutter<'t, F: Float>(
        &self,
        params: &BoundParams<'t, F>,
        rows: &RowVars<'t, F>,
        av: &[Pose],
        items: &[&[[f64; 2]]],
        logit_fraction: Var<'t, F>,
        log_scale: Var<'t, F>,
    ) -> Var<'t, F> {
        PointObservationModel::log_likelihood_rows_with_clutter(
            self,
            params,
            rows,
            av,
            items,
            logit_fraction,
            log_scale,
        )
    }

    fn sample_with_clutter(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        n: usize,
        clutter: Clutter,
        rng: &mut SmallRng,
        out: &mut Vec<[f64; 2]>,
    ) {
        PointObservationModel::sample_with_clutter(self, params, ctx, pose, n, clutter, rng, out)
    }
}

/// Detections have no clutter (at most one per step): the clutter hooks are the
/// plain model, and [`ExtendedSsm::new`] refuses `clutter` for box data.
impl ExtensibleObservation for BoxObservationModel {
    fn reverse_heading(item: &BoxDetection) -> BoxDetection {
        BoxDetection { yaw: reversed_heading(item.yaw), ..*item }
    }

    fn heading_reversed(item: &BoxDetection, pose: Pose) -> bool {
        item.reversed_against(pose)
    }

    fn to_observations(per_step: Vec<Vec<BoxDetection>>) -> ObjectObservations {
        ObjectObservations::Boxes(per_step.into_iter().map(|v| v.first().copied()).collect())
    }

    fn log_likelihood_with_clutter<F: Float>(
        &self,
        params: &ParamStore<F>,
        ctx: &ObsContext,
        poses: PosesRef<'_, F>,
        items: &[BoxDetection],
        _clutter: Clutter,
        scratch: &mut Scratch<F>,
        out: &mut [F],
    ) {
        self.log_likelihood(params, ctx, poses, items, scratch, out)
    }

    fn log_likelihood_rows_with_clutter<'t, F: Float>(
        &self,
        params: &BoundParams<'t, F>,
        rows: &RowVars<'t, F>,
        av: &[Pose],
        items: &[&[BoxDetection]],
        _logit_fraction: Var<'t, F>,
        _log_scale: Var<'t, F>,
    ) -> Var<'t, F> {
        self.log_likelihood_rows(params, rows, av, items)
    }

    fn sample_with_clutter(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        n: usize,
        _clutter: Clutter,
        rng: &mut SmallRng,
        out: &mut Vec<BoxDetection>,
    ) {
        self.sample(params, ctx, pose, n, rng, out)
    }
}

/// An extension with its natural parameter values (f64), as the plain paths use them.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Active {
    None,
    Latency { delay: f64 },
    Clutter(Clutter),
    SizeBias { length: f64, width: f64 },
    HeavyTailedAccel { fraction: f64, ratio: f64 },
    HeadingFlip { fraction: f64 },
    PersistentFlip(FlipChain),
}

/// The base vehicle model with at most one catalogue extension. See the
/// [module docs](self).
pub struct ExtendedSsm<'m, 'a, P: GaussianPolicy, O: ExtensibleObservation> {
    base: &'m VehicleSsm<'a, P, O>,
    extension: Option<Extension>,
    /// Stored (scaled) values of the extension's parameter.
    raw: Vec<f64>,
    active: Active,
    /// The filter's proposal for the acceleration, if not the transition.
    defensive: Option<DefensiveProposal>,
    /// The detector's drift and its stored values, if the model has one.
    drift: Option<(DetectorDrift, Vec<f64>)>,
}

/// A defensive proposal for the action's innovations (Hesterberg 1995): with
/// probability `fraction` a particle's standardised innovations (acceleration and
/// pinch) are drawn `widening` times wider than the policy's, otherwise from the
/// model; the filter weights each
/// particle by transition over proposal, so the likelihood estimate stays unbiased
/// for the same model.
///
/// A bootstrap filter follows only what its transition proposes: where the data
/// hold an acceleration far in the model's tail (a hard brake under a Gaussian
/// policy), no particle follows it and the likelihood estimate collapses by
/// hundreds of nats, differently from run to run. A few wide particles keep every
/// model's estimate near its true value at a cost of `fraction` of the particles
/// elsewhere, and give models with and without heavy tails a like-for-like
/// comparison.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DefensiveProposal {
    /// Probability of a wide draw (in `(0, 1)`).
    pub fraction: f64,
    /// Sd of a wide draw over the model's (at least 1).
    pub widening: f64,
}

impl DefensiveProposal {
    /// Checks the fraction and the widening.
    pub fn validate(&self) -> Result<(), SettingError> {
        let (f, w) = (self.fraction, self.widening);
        SettingError::check(f > 0.0 && f < 1.0, "defensive_proposal.fraction", f, "in (0, 1)")?;
        SettingError::check(
            w >= 1.0 && w.is_finite(),
            "defensive_proposal.widening",
            w,
            "a finite number of at least 1",
        )
    }
}

/// Per-thread working memory of [`ExtendedSsm`].
pub struct ExtendedScratch<I> {
    base: VehicleScratch,
    /// Lagged poses, one value per particle each.
    x: Vec<f32>,
    y: Vec<f32>,
    yaw: Vec<f32>,
    /// The second term of a two-component observation mixture.
    other: Vec<f32>,
    /// Reversed-heading items.
    reversed: Vec<I>,
    /// Standardised acceleration innovations of the last `propagate`.
    innovations: Vec<[f64; 2]>,
    /// Standardised acceleration innovations built from noise (heavy tails).
    accel_eps: Vec<f32>,
    /// The poses a drifting detector sees, one value per particle each.
    seen_x: Vec<f32>,
    seen_y: Vec<f32>,
    seen_yaw: Vec<f32>,
    /// Standard-normal noise of the drift's transition.
    drift_noise: Vec<f32>,
    /// Standard-normal noise of a flip chain's transition.
    flip_noise: Vec<f32>,
    /// Each particle's probability that its indicator is set, given `y_t`.
    flip_posterior: Vec<f64>,
    /// Log-likelihoods of the detection as reported (with `other`: reversed).
    kept: Vec<f32>,
    /// The flips' weights while a chain's indicators are drawn.
    marginal: Vec<f32>,
}

impl<'m, 'a, P: GaussianPolicy, O: ExtensibleObservation> ExtendedSsm<'m, 'a, P, O> {
    /// `base` extended by `extension` with stored parameter values `raw` (the
    /// tensor `ext.<id>` of a store); `None` is the base model itself. Fails if the
    /// extension does not apply to the data's kind or `raw` is malformed.
    pub fn new(base: &'m VehicleSsm<'a, P, O>, extension: Option<Extension>, raw: &[f64]) -> Result<Self, ModelError> {
        let active = match extension {
            None => Active::None,
            Some(ext) => {
                if !ext.applies_to(O::KIND) {
                    return Err(ModelError::ExtensionNotApplicable { extension: ext, kind: O::KIND });
                }
                let v: Vec<f64> = ext.natural(raw)?.iter().map(|p| p.1).collect();
                match ext {
                    Extension::Latency => Active::Latency { delay: v[0] },
                    // A fraction that rounds to 0 or 1 would make a log-weight infinite.
                    Extension::Clutter => Active::Clutter(Clutter {
                        fraction: v[0].clamp(FRACTION_GUARD, 1.0 - FRACTION_GUARD),
                        scale: v[1],
                    }),
                    Extension::SizeBias => Active::SizeBias { length: v[0], width: v[1] },
                    Extension::HeavyTailedAccel => Active::HeavyTailedAccel { fraction: v[0], ratio: v[1] },
                    Extension::HeadingFlip => Active::HeadingFlip { fraction: v[0] },
                    Extension::PersistentFlip => {
                        Active::PersistentFlip(FlipChain { fraction: v[0], persistence: v[1] })
                    }
                }
            }
        };
        Ok(ExtendedSsm { base, extension, raw: raw.to_vec(), active, defensive: None, drift: None })
    }

    /// The same model with the detector drift stored as `raw` ([`DRIFT_PARAM`]),
    /// or without drift (`None`). Fails on data other than box detections, with
    /// `latency` (which also moves the pose the sensor sees) or on a malformed
    /// `raw`.
    pub fn with_drift(self, raw: Option<&[f64]>) -> Result<Self, ModelError> {
        let Some(raw) = raw else { return Ok(ExtendedSsm { drift: None, ..self }) };
        if O::KIND != ObservationKind::Boxes {
            return Err(ModelError::DriftNotApplicable { reason: format!("{:?} data (box detections only)", O::KIND) });
        }
        if self.extension == Some(Extension::Latency) {
            return Err(ModelError::DriftNotApplicable {
                reason: "with the `latency` extension, which also moves the pose the sensor sees".into(),
            });
        }
        let drift = DetectorDrift::from_raw(raw)?;
        Ok(ExtendedSsm { drift: Some((drift, raw.to_vec())), ..self })
    }

    /// The detector drift, if the model has one.
    pub fn drift(&self) -> Option<&DetectorDrift> {
        self.drift.as_ref().map(|d| &d.0)
    }

    /// Offsets the drift appends to the state (0 without drift).
    fn drift_dims(&self) -> usize {
        if self.drift.is_some() {
            DRIFT_DIMS
        } else {
            0
        }
    }

    /// The chain of `persistent_flip`, if that is the extension.
    pub fn flip_chain(&self) -> Option<FlipChain> {
        match self.active {
            Active::PersistentFlip(chain) => Some(chain),
            _ => None,
        }
    }

    /// Components the flip chain appends to the state, after the drift's: its
    /// indicator `b_t` and the probability `q_t = P(b_t = 1 | b_{t-1})` it was
    /// predicted with (2 with a chain, else 0). The filters weight a particle
    /// by the marginal over the indicator, `(1 - q_t) g(y_t | x_t) + q_t g(y_t |
    /// x_t, reversed)`, and draw `b_t` from its posterior given `y_t`
    /// ([`Self::draw_flips`]): every particle can take a reversed detection, as
    /// under `heading_flip`, while the path keeps the indicator the score needs.
    fn flip_dims(&self) -> usize {
        2 * usize::from(self.flip_chain().is_some())
    }

    /// Under `persistent_flip` with an axial prior, `x_0`'s speed is folded to
    /// `|v|` (and its curvature's sign turned with it, so the path's turn is
    /// kept): the axial heading already covers both directions of travel, and
    /// a car that drives backwards with every detection reversed — the mirror
    /// of one driving forwards — would otherwise cost the chain only `ln p`
    /// once, so detections could not identify its fraction (README,
    /// "Persistent flips"). Independent flips pay the mirror per detection
    /// and keep the prior as it is. No-op otherwise.
    fn fold_speeds(&self, n: usize, states: &mut [f32]) {
        if self.flip_chain().is_none() {
            return;
        }
        let s = states_mut(states, n);
        for (v, kappa) in s.v.iter_mut().zip(s.kappa.iter_mut()) {
            if *v < 0.0 {
                (*v, *kappa) = (-*v, -*kappa);
            }
        }
    }

    /// Sets the `n` particles' flip-chain prediction `q` to the chain's
    /// stationary fraction, so that [`ParticleModel::observation_loglik`] gives
    /// a detection's density given the vehicle state alone, the indicator
    /// marginalised as independent flips' is (no-op without a chain).
    pub(crate) fn predict_stationary_flips(&self, n: usize, states: &mut [f32]) {
        if let Some(chain) = self.flip_chain() {
            let k = self.flip_dim() + 1;
            states[k * n..(k + 1) * n].fill(chain.reversed_probability(None) as f32);
        }
    }

    /// The state component of the flip chain's indicator `b_t` (with a chain);
    /// its predictive probability `q_t` is the next one.
    fn flip_dim(&self) -> usize {
        STATE_DIM + self.drift_dims()
    }

    /// `base` extended by `extension`, reading its parameter from `store` (the
    /// extension's initial values if the store has none), with the detector
    /// drift the store holds ([`DRIFT_PARAM`]), if any.
    pub fn from_store(
        base: &'m VehicleSsm<'a, P, O>,
        extension: Option<Extension>,
        store: &ParamStore<f64>,
    ) -> Result<Self, ModelError> {
        let raw = match extension {
            None => Vec::new(),
            Some(ext) => match store.id(&ext.param_name()) {
                Some(id) => store.get(id).data().to_vec(),
                None => ext.initial().data().to_vec(),
            },
        };
        let drift = store.id(DRIFT_PARAM).map(|id| store.get(id).data());
        ExtendedSsm::new(base, extension, &raw)?.with_drift(drift)
    }

    /// The same model, filtered with a defensive proposal for the actions (see
    /// [`DefensiveProposal`]) or, with `None`, with the transition: the filter's
    /// estimates are for the same model either way. Fails on a bad proposal.
    pub fn with_proposal(self, proposal: Option<DefensiveProposal>) -> Result<Self, ModelError> {
        if let Some(p) = &proposal {
            p.validate()?;
        }
        Ok(ExtendedSsm { defensive: proposal, ..self })
    }

    /// The extension, if any.
    pub fn extension(&self) -> Option<Extension> {
        self.extension
    }

    /// The base model.
    pub fn base(&self) -> &'m VehicleSsm<'a, P, O> {
        self.base
    }

    /// The dataset.
    pub fn data(&self) -> &'a Dataset {
        self.base.data()
    }

    /// The observation context of `object` at `t` under the extension (scaled
    /// extents for `size_bias`).
    fn context(&self, object: usize, t: usize) -> ObsContext {
        let mut ctx = self.base.context(object, t);
        if let Active::SizeBias { length, width } = self.active {
            ctx.length *= length;
            ctx.width *= width;
        }
        ctx
    }

    /// Draws an initial state of `object` from its prior (axial under
    /// `heading_flip` on priors read from a detection; module docs).
    pub fn sample_initial_state(&self, object: usize, rng: &mut SmallRng) -> State {
        let mut x = vec![0.0f32; self.state_dim()];
        self.sample_prior(object, 1, rng, &mut x, &mut self.new_scratch());
        state_at(&x, 1, 0)
    }

    /// Whether `x_0`'s heading is axial: `heading_flip` on data whose priors were
    /// read from a detection (module docs).
    pub fn axial_prior(&self) -> bool {
        matches!(self.active, Active::HeadingFlip { .. } | Active::PersistentFlip(_))
            && self.data().meta().prior_from_detection
    }

    /// Draws an action at `state` from the policy (with the extension's heavy
    /// tails, if any).
    pub fn sample_action(&self, state: &State, rng: &mut SmallRng) -> Action {
        let mut g = ActionGaussians::<f64>::default();
        self.base.policy().gaussians(&[state.v], &[state.kappa], &mut g);
        let (mut accel, mut pinch) = ([0.0], [0.0]);
        let out = ActionsMut { accel: &mut accel, pinch: &mut pinch };
        g.sample_with(rng, out, |rng| [self.accel_innovation(rng), rng.sample(StandardNormal)]);
        Action { accel: accel[0], pinch: pinch[0] }
    }

    /// The innovation of `action`'s acceleration at `state` standardised by the
    /// policy's Gaussian: `(accel - mean) / sd`.
    pub fn accel_innovation_of(&self, state: &State, action: &Action) -> f64 {
        let mut g = ActionGaussians::<f64>::default();
        self.base.policy().gaussians(&[state.v], &[state.kappa], &mut g);
        (action.accel - g.mean_accel[0]) / g.l11[0]
    }

    /// `ln` of the density of a standardised acceleration innovation `z`: normal,
    /// or the heavy-tailed mixture of unit variance (what [`Self::accel_innovation`]
    /// draws).
    fn accel_innovation_log_density(&self, z: f64) -> f64 {
        match self.active {
            Active::HeavyTailedAccel { fraction, ratio } => {
                let core = 1.0 / (1.0 + fraction * (ratio * ratio - 1.0)).sqrt();
                let f = fraction.clamp(FRACTION_GUARD, 1.0 - FRACTION_GUARD);
                log_sum_exp(&[
                    (1.0 - f).ln() + normal_log_density(z, core),
                    f.ln() + normal_log_density(z, ratio * core),
                ])
            }
            _ => normal_log_density(z, 1.0),
        }
    }

    /// A standardised acceleration innovation: normal, or the heavy-tailed mixture
    /// of unit variance.
    fn accel_innovation(&self, rng: &mut SmallRng) -> f64 {
        let z: f64 = rng.sample(StandardNormal);
        match self.active {
            Active::HeavyTailedAccel { fraction, ratio } => {
                let core = 1.0 / (1.0 + fraction * (ratio * ratio - 1.0)).sqrt();
                if rng.random::<f64>() < fraction {
                    ratio * core * z
                } else {
                    core * z
                }
            }
            _ => z,
        }
    }

    /// Appends to `out` a replicate of the observation of `object` at `t` (as many
    /// items as the data hold there) drawn from the model at `state`.
    /// Without drift: a drift's offsets are not part of a [`State`]; see
    /// [`Self::sample_drifted_observation`].
    pub fn sample_observation(
        &self,
        object: usize,
        t: usize,
        state: &State,
        rng: &mut SmallRng,
        out: &mut Vec<O::Item>,
    ) {
        let pose = match self.active {
            Active::Latency { delay } => lagged_pose(state, delay),
            _ => Pose { x: state.x, y: state.y, yaw: state.yaw },
        };
        self.sample_observation_of_pose(object, t, pose, rng, out);
    }

    /// A replicate of every observation of `object` along the path `states`
    /// (one state per step from `t = 0`): the detector's own processes — a
    /// drift's offsets, a persistent flip's chain — drawn afresh from their
    /// laws, then each step's observation as [`Self::sample_observation`] draws
    /// it (through the drift, reversed where the chain says so).
    pub fn sample_observations_along(&self, object: usize, states: &[State], rng: &mut SmallRng) -> Vec<Vec<O::Item>> {
        let drift = self.drift().map(|d| d.sample_path(states.len(), rng));
        let flips = self.flip_chain().map(|c| c.sample_path(states.len(), rng));
        states
            .iter()
            .enumerate()
            .map(|(t, s)| {
                let mut items = Vec::new();
                match &drift {
                    Some(path) => self.sample_drifted_observation(object, t, s, path[t], rng, &mut items),
                    None => self.sample_observation(object, t, s, rng, &mut items),
                }
                if flips.as_ref().is_some_and(|f| f[t]) {
                    items.iter_mut().for_each(|item| *item = O::reverse_heading(item));
                }
                items
            })
            .collect()
    }

    /// [`Self::sample_observation`] through the drift's standardised offsets
    /// `u` at `t` (a path from [`DetectorDrift::sample_path`]); `u` is ignored
    /// without drift.
    pub fn sample_drifted_observation(
        &self,
        object: usize,
        t: usize,
        state: &State,
        u: [f64; DRIFT_DIMS],
        rng: &mut SmallRng,
        out: &mut Vec<O::Item>,
    ) {
        let Some(drift) = self.drift() else { return self.sample_observation(object, t, state, rng, out) };
        let pose = Pose { x: state.x, y: state.y, yaw: state.yaw };
        let seen = drift.seen_pose(&self.base.context(object, t).av, pose, u);
        self.sample_observation_of_pose(object, t, seen, rng, out);
    }

    /// Appends to `out` a replicate of the observation of `object` at `t` as the
    /// sensor sees `pose`.
    fn sample_observation_of_pose(
        &self,
        object: usize,
        t: usize,
        pose: Pose,
        rng: &mut SmallRng,
        out: &mut Vec<O::Item>,
    ) {
        let n = O::items(self.data(), object, t).len();
        if n == 0 {
            return;
        }
        let ctx = self.context(object, t);
        let params = self.base.observation_params();
        let obs = self.base.observation();
        let start = out.len();
        match self.active {
            Active::Clutter(c) => obs.sample_with_clutter(params, &ctx, pose, n, c, rng, out),
            _ => obs.sample(params, &ctx, pose, n, rng, out),
        }
        if let Active::HeadingFlip { fraction } = self.active {
            for item in &mut out[start..] {
                if rng.random::<f64>() < fraction {
                    *item = O::reverse_heading(item);
                }
            }
        }
    }

    /// The stored extension parameter as a `Var` among the bound `params` (the
    /// base model's, the extension's, then the drift's).
    fn extension_var<'t, F: Float>(&self, params: &[Var<'t, F>]) -> Var<'t, F> {
        params[params.len() - 1 - usize::from(self.drift.is_some())]
    }

    /// The drift's terms on the tape, if the model has a drift.
    fn drift_vars<'t, F: Float>(&self, params: &[Var<'t, F>]) -> Option<DriftVars<'t, F>> {
        self.drift.as_ref().map(|_| DriftVars::new(params[params.len() - 1]))
    }

    /// Writes into the scratch's seen poses the poses the drifting detector sees
    /// for the `n` particles `states` of `object` at `t`.
    fn seen_poses(
        &self,
        drift: &DetectorDrift,
        object: usize,
        t: usize,
        states: &[f32],
        n: usize,
        scratch: &mut ExtendedScratch<O::Item>,
    ) {
        let s5 = states_ref(states, n);
        for (buf, from) in [(&mut scratch.seen_x, s5.x), (&mut scratch.seen_y, s5.y), (&mut scratch.seen_yaw, s5.yaw)] {
            buf.clear();
            buf.extend_from_slice(from);
        }
        let av = self.base.context(object, t).av;
        let u = &states[STATE_DIM * n..(STATE_DIM + DRIFT_DIMS) * n];
        drift.shift_poses(&av, u, &mut scratch.seen_x, &mut scratch.seen_y, &mut scratch.seen_yaw);
    }

    /// Draws the drift's offsets at `t` from those at `t - 1` for `n` particles
    /// (no-op without drift).
    fn propagate_drift(&self, n: usize, prev: &[f32], next: &mut [f32], rng: &mut SmallRng, noise: &mut Vec<f32>) {
        if self.drift.is_none() {
            return;
        }
        noise.clear();
        noise.extend((0..DRIFT_DIMS * n).map(|_| rng.sample::<f32, _>(StandardNormal)));
        self.drift_from_noise(n, prev, noise, next);
    }

    /// The flip chain's components at `at.t` for `n` particles whose vehicle
    /// (and drift) components `states` already hold: the predictive probability
    /// `q = P(b_t = 1 | b_{t-1})` (from `prev`'s indicators; `None` at `t = 0`:
    /// the stationary fraction), then the indicator drawn from standard-normal
    /// `z` by its posterior given the observation at `t`,
    /// `q g(y | x, reversed) / ((1 - q) g(y | x) + q g(y | x, reversed))` (`q`
    /// without one). Weighted by that denominator
    /// ([`ParticleModel::observation_loglik`]), the particles target the model's
    /// posterior over both. No-op without a chain.
    fn draw_flips(
        &self,
        at: Batch,
        prev: Option<&[f32]>,
        z: &[f32],
        states: &mut [f32],
        scratch: &mut ExtendedScratch<O::Item>,
    ) {
        let Some(chain) = self.flip_chain() else { return };
        let n = at.n;
        let (kb, kq) = (self.flip_dim(), self.flip_dim() + 1);
        for i in 0..n {
            let before = prev.map(|p| is_reversed(p[kb * n + i]));
            states[kq * n + i] = chain.reversed_probability(before) as f32;
        }
        let mut posterior = std::mem::take(&mut scratch.flip_posterior);
        posterior.clear();
        posterior.extend(states[kq * n..(kq + 1) * n].iter().map(|&q| f64::from(q)));
        let mut marginal = std::mem::take(&mut scratch.marginal);
        marginal.resize(n, 0.0);
        // The weight leaves each particle's densities as reported and reversed
        // in the scratch.
        if self.observation_loglik(at, states, &mut marginal, scratch) {
            for ((post, &kept), &reversed) in posterior.iter_mut().zip(&scratch.kept).zip(&scratch.other) {
                let log_odds = post.ln() - (1.0 - *post).ln() + f64::from(reversed) - f64::from(kept);
                *post = if log_odds.is_nan() { *post } else { 1.0 / (1.0 + (-log_odds).exp()) };
            }
        }
        for ((b, &post), &z) in states[kb * n..(kb + 1) * n].iter_mut().zip(&posterior).zip(z) {
            *b = f32::from(u8::from(normal_cdf(f64::from(z)) < post));
        }
        scratch.flip_posterior = posterior;
        scratch.marginal = marginal;
    }

    /// [`ParticleModel::propagate_from_noise`] without a flip chain's
    /// component (its noise `z` stops before the chain's).
    fn propagate_unchained_from_noise(
        &self,
        at: Batch,
        prev: &[f32],
        z: &[f32],
        to: Drawn<'_>,
        scratch: &mut ExtendedScratch<O::Item>,
    ) {
        let n = at.n;
        let (z, drift_z) = z.split_at(z.len() - self.drift_dims() * n);
        self.drift_from_noise(n, prev, drift_z, to.next);
        let Active::HeavyTailedAccel { fraction, ratio } = self.active else {
            return self.base.propagate_from_noise(at, prev, z, to, &mut scratch.base);
        };
        let core = 1.0 / (1.0 + fraction * (ratio * ratio - 1.0)).sqrt();
        let (narrow, wide) = (core as f32, (ratio * core) as f32);
        let (z_accel, rest) = z.split_at(n);
        let (z_pinch, z_pick) = rest.split_at(n);
        let eps = &mut scratch.accel_eps;
        eps.clear();
        eps.extend(z_accel.iter().zip(&z_pick[..n]).map(|(&z, &pick)| {
            let scale = if normal_cdf(pick as f64) < fraction { wide } else { narrow };
            scale * z
        }));
        self.base.propagate_with_innovations(n, prev, [eps, &z_pinch[..n]], to, &mut scratch.base);
    }

    /// [`ParticleModel::propagate`] without a flip chain's component.
    fn propagate_unchained(
        &self,
        at: Batch,
        prev: &[f32],
        to: Drawn<'_>,
        rng: &mut SmallRng,
        scratch: &mut ExtendedScratch<O::Item>,
    ) {
        self.propagate_drift(at.n, prev, to.next, rng, &mut scratch.drift_noise);
        if !matches!(self.active, Active::HeavyTailedAccel { .. }) && self.defensive.is_none() {
            return self.base.propagate(at, prev, to, rng, &mut scratch.base);
        }
        let innovations = &mut scratch.innovations;
        innovations.clear();
        let wide = self.defensive.map_or((0.0, 1.0), |d| (d.fraction, d.widening));
        self.base.propagate_by(at.n, prev, to, &mut scratch.base.gaussians, |g, actions| {
            g.sample_with(rng, actions, |rng| {
                let z = if wide.0 > 0.0 && rng.random::<f64>() < wide.0 {
                    let mut normal = || wide.1 * rng.sample::<f64, _>(StandardNormal);
                    [normal(), normal()]
                } else {
                    [self.accel_innovation(rng), rng.sample(StandardNormal)]
                };
                if wide.0 > 0.0 {
                    innovations.push(z); // for the proposal's weights
                }
                z
            })
        });
    }

    /// The drift's offsets at `t` from those at `t - 1` (in `prev`'s and
    /// `next`'s drift dimensions) and standard-normal noise `e` (no-op without
    /// drift).
    fn drift_from_noise(&self, n: usize, prev: &[f32], e: &[f32], next: &mut [f32]) {
        if let Some((drift, _)) = &self.drift {
            let r = STATE_DIM * n..(STATE_DIM + DRIFT_DIMS) * n;
            drift.propagate(n, &prev[r.clone()], e, &mut next[r]);
        }
    }
}

/// `ln(e^a + e^b)` per element, stable: `a + softplus(b - a)`.
fn log_add_exp<'t, F: Float>(a: Var<'t, F>, b: Var<'t, F>) -> Var<'t, F> {
    a + (b - a).softplus()
}

/// Turns around each heading in `yaws` whose `reversed` is true
/// ([`reversed_heading`], as a detection's heading is reversed).
fn reverse_headings(yaws: &mut [f32], reversed: impl Iterator<Item = bool>) {
    for (yaw, r) in yaws.iter_mut().zip(reversed) {
        if r {
            *yaw = reversed_heading(f64::from(*yaw)) as f32;
        }
    }
}

/// `ln N(z; 0, sd^2)`.
fn normal_log_density(z: f64, sd: f64) -> f64 {
    -0.5 * (z / sd).powi(2) - sd.ln() - 0.5 * LN_2PI
}

/// `ln((1 - p) e^a + p e^b)` per element with `p = sigmoid(logit)` (plain).
#[inline]
fn mix_plain(a: f32, b: f32, ln_keep: f32, ln_p: f32) -> f32 {
    let (u, v) = (ln_keep + a, ln_p + b);
    let m = u.max(v);
    m + ((u - m).exp() + (v - m).exp()).ln()
}

impl<P: GaussianPolicy, O: ExtensibleObservation> ParticleModel for ExtendedSsm<'_, '_, P, O> {
    type Scratch = ExtendedScratch<O::Item>;

    fn new_scratch(&self) -> Self::Scratch {
        ExtendedScratch {
            base: self.base.new_scratch(),
            x: Vec::new(),
            y: Vec::new(),
            yaw: Vec::new(),
            other: Vec::new(),
            reversed: Vec::new(),
            innovations: Vec::new(),
            accel_eps: Vec::new(),
            seen_x: Vec::new(),
            seen_y: Vec::new(),
            seen_yaw: Vec::new(),
            drift_noise: Vec::new(),
            flip_noise: Vec::new(),
            flip_posterior: Vec::new(),
            kept: Vec::new(),
            marginal: Vec::new(),
        }
    }

    fn state_dim(&self) -> usize {
        self.base.state_dim() + self.drift_dims() + self.flip_dims()
    }

    fn action_dim(&self) -> usize {
        self.base.action_dim()
    }

    fn angular_dims(&self) -> &[usize] {
        self.base.angular_dims()
    }

    fn num_objects(&self) -> usize {
        self.base.num_objects()
    }

    fn stream_key(&self, object: usize) -> u64 {
        self.base.stream_key(object)
    }

    fn num_steps(&self) -> usize {
        self.base.num_steps()
    }

    fn sample_prior(
        &self,
        object: usize,
        n: usize,
        rng: &mut SmallRng,
        states: &mut [f32],
        scratch: &mut Self::Scratch,
    ) {
        self.base.sample_prior(object, n, rng, states, &mut scratch.base);
        if self.axial_prior() {
            reverse_headings(&mut states[YAW * n..(YAW + 1) * n], std::iter::repeat_with(|| rng.random::<bool>()));
            self.fold_speeds(n, states);
        }
        // The drift's standardised offsets start in their stationary law, N(0, 1).
        let drift = STATE_DIM * n..(STATE_DIM + self.drift_dims()) * n;
        states[drift].iter_mut().for_each(|u| *u = rng.sample(StandardNormal));
        // A persistent flip's indicator: from the stationary law, given y_0.
        if self.flip_chain().is_some() {
            let mut z = std::mem::take(&mut scratch.flip_noise);
            z.clear();
            z.extend((0..n).map(|_| rng.sample::<f32, _>(StandardNormal)));
            self.draw_flips(Batch { object, t: 0, n }, None, &z, states, scratch);
            scratch.flip_noise = z;
        }
    }

    /// The base model's noise; heavy-tailed accelerations add a third transition
    /// component whose normal CDF picks the mixture's wide component, an axial
    /// prior a last prior component whose sign picks the direction; a drift
    /// puts its offsets' noise after all of those, in the prior's noise and in
    /// the transition's, and a persistent flip one component after that, whose
    /// normal CDF, against the indicator's posterior given `y_t`, picks it.
    /// The noise form draws from the transition: a defensive
    /// proposal does not apply to it.
    fn noise_dims(&self) -> Option<NoiseDims> {
        let base = self.base.noise_dims()?;
        let extra = usize::from(matches!(self.active, Active::HeavyTailedAccel { .. }));
        let drift = self.drift_dims();
        let chain = usize::from(self.flip_chain().is_some());
        Some(NoiseDims {
            prior: base.prior + usize::from(self.axial_prior()) + drift + chain,
            transition: base.transition + extra + drift + chain,
        })
    }

    fn prior_from_noise(
        &self,
        object: usize,
        n: usize,
        noise: &[f32],
        states: &mut [f32],
        scratch: &mut Self::Scratch,
    ) {
        let chain_noise = usize::from(self.flip_chain().is_some()) * n;
        let (noise, flip_z) = noise.split_at(noise.len() - chain_noise);
        let (noise, drift) = noise.split_at(noise.len() - self.drift_dims() * n);
        states[STATE_DIM * n..(STATE_DIM + self.drift_dims()) * n].copy_from_slice(drift);
        if self.axial_prior() {
            let (base, pick) = noise.split_at(noise.len() - n);
            self.base.prior_from_noise(object, n, base, states, &mut scratch.base);
            reverse_headings(&mut states[YAW * n..(YAW + 1) * n], pick.iter().map(|&z| z < 0.0));
            self.fold_speeds(n, states);
        } else {
            self.base.prior_from_noise(object, n, noise, states, &mut scratch.base);
        }
        self.draw_flips(Batch { object, t: 0, n }, None, flip_z, states, scratch);
    }

    fn propagate_from_noise(&self, at: Batch, prev: &[f32], z: &[f32], to: Drawn<'_>, scratch: &mut Self::Scratch) {
        let chain_noise = usize::from(self.flip_chain().is_some()) * at.n;
        let (z, flip_z) = z.split_at(z.len() - chain_noise);
        let mut to = to;
        self.propagate_unchained_from_noise(at, prev, z, to.reborrow(), scratch);
        self.draw_flips(at, Some(prev), flip_z, to.next, scratch);
    }

    fn propagate(&self, at: Batch, prev: &[f32], to: Drawn<'_>, rng: &mut SmallRng, scratch: &mut Self::Scratch) {
        if self.flip_chain().is_none() {
            return self.propagate_unchained(at, prev, to, rng, scratch);
        }
        let mut noise = std::mem::take(&mut scratch.flip_noise);
        noise.clear();
        noise.extend((0..at.n).map(|_| rng.sample::<f32, _>(StandardNormal)));
        let mut to = to;
        self.propagate_unchained(at, prev, to.reborrow(), rng, scratch);
        self.draw_flips(at, Some(prev), &noise, to.next, scratch);
        scratch.flip_noise = noise;
    }

    fn proposal_log_weights(&self, n: usize, out: &mut [f32], scratch: &mut Self::Scratch) -> bool {
        let Some(DefensiveProposal { fraction, widening }) = self.defensive else {
            return false;
        };
        // ln f - ln q with q = (1 - e) f + e N(0, w^2 I): -ln((1 - e) + e N(z; 0, w^2 I) / f(z)).
        for (o, &[z1, z2]) in out[..n].iter_mut().zip(&scratch.innovations) {
            let wide = normal_log_density(z1, widening) + normal_log_density(z2, widening);
            let log_ratio = wide - self.accel_innovation_log_density(z1) - normal_log_density(z2, 1.0);
            *o = -log_sum_exp(&[(1.0 - fraction).ln(), fraction.ln() + log_ratio]) as f32;
        }
        true
    }

    fn observation_loglik(&self, at: Batch, states: &[f32], out: &mut [f32], scratch: &mut Self::Scratch) -> bool {
        let Batch { object, t, n } = at;
        let items = O::items(self.data(), object, t);
        if items.is_empty() {
            return false;
        }
        let ctx = self.context(object, t);
        let params = self.base.observation_params32();
        let obs = self.base.observation();
        if let Some((drift, _)) = &self.drift {
            self.seen_poses(drift, object, t, states, n, scratch);
        }
        let poses = match self.drift {
            Some(_) => PosesRef::new(&scratch.seen_x[..n], &scratch.seen_y[..n], &scratch.seen_yaw[..n]),
            None => PosesRef::from_dim_major(states, n),
        };
        let s = &mut scratch.base.observation;
        match self.active {
            Active::Latency { delay } => {
                let s5 = states_ref(states, n);
                for buf in [&mut scratch.x, &mut scratch.y, &mut scratch.yaw] {
                    buf.resize(n, 0.0);
                }
                let d = delay as f32;
                for i in 0..n {
                    let dv = d * s5.v[i];
                    let (sin, cos) = s5.yaw[i].sin_cos();
                    scratch.x[i] = s5.x[i] - dv * cos;
                    scratch.y[i] = s5.y[i] - dv * sin;
                    scratch.yaw[i] = s5.yaw[i] - dv * s5.kappa[i];
                }
                let lagged = PosesRef::new(&scratch.x[..n], &scratch.y[..n], &scratch.yaw[..n]);
                obs.log_likelihood(params, &ctx, lagged, items, s, out);
            }
            Active::Clutter(c) => obs.log_likelihood_with_clutter(params, &ctx, poses, items, c, s, out),
            Active::HeadingFlip { .. } | Active::PersistentFlip(_) => {
                // `ln((1 - p) g(y | x) + p g(y | x, reversed))` at `heading_flip`'s
                // fraction or a persistent flip's predictive probability `q_t`
                // (see `flip_dims`); both densities stay in the scratch.
                scratch.kept.resize(n, 0.0);
                scratch.other.resize(n, 0.0);
                obs.log_likelihood(params, &ctx, poses, items, s, &mut scratch.kept[..n]);
                scratch.reversed.clear();
                scratch.reversed.extend(items.iter().map(O::reverse_heading));
                obs.log_likelihood(params, &ctx, poses, &scratch.reversed, s, &mut scratch.other[..n]);
                let pairs = out[..n].iter_mut().zip(&scratch.kept[..n]).zip(&scratch.other[..n]);
                match self.active {
                    Active::HeadingFlip { fraction } => {
                        let (ln_keep, ln_p) = ((1.0 - fraction).ln() as f32, fraction.ln() as f32);
                        pairs.for_each(|((o, &a), &b)| *o = mix_plain(a, b, ln_keep, ln_p));
                    }
                    _ => {
                        let k = self.flip_dim() + 1;
                        for (((o, &a), &b), &q) in pairs.zip(&states[k * n..(k + 1) * n]) {
                            *o = mix_plain(a, b, (1.0 - q).ln(), q.ln());
                        }
                    }
                }
            }
            Active::None | Active::SizeBias { .. } | Active::HeavyTailedAccel { .. } => {
                obs.log_likelihood(params, &ctx, poses, items, s, out)
            }
        }
        true
    }

    fn observation_count(&self, object: usize, t: usize) -> usize {
        self.base.observation_count(object, t)
    }
}

impl<P: GaussianPolicy, O: ExtensibleObservation> DifferentiableModel for ExtendedSsm<'_, '_, P, O> {
    /// The base model's parameters, then the extension's (if any).
    fn parameters(&self) -> Vec<Tensor<f64>> {
        let mut p = self.base.parameters();
        if self.extension.is_some() {
            p.push(Tensor::from_vec(self.raw.clone()));
        }
        if let Some((_, raw)) = &self.drift {
            p.push(Tensor::from_vec(raw.clone()));
        }
        p
    }

    fn parameter_names(&self) -> Vec<String> {
        let mut names = self.base.parameter_names();
        if let Some(ext) = self.extension {
            names.push(ext.param_name());
        }
        if self.drift.is_some() {
            names.push(DRIFT_PARAM.into());
        }
        names
    }

    fn observation_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        states: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let drift = self.drift_vars(params);
        if self.extension.is_none() && drift.is_none() {
            return self.base.observation_log_density(params, blocks, states);
        }
        let obs_params = self.base.observation_params_on_tape(params);
        let rows = self.base.observation_rows(blocks);
        let mut vars = rows.vars(states);
        let model = self.base.observation();
        if let Some(d) = drift {
            let tape = states[0].tape();
            let av = |f: fn(&Pose) -> f64| {
                tape.constant(Tensor::from_vec(rows.av.iter().map(|p| F::from_f64(f(p))).collect()))
            };
            let u = &states[STATE_DIM..STATE_DIM + DRIFT_DIMS];
            [vars.x, vars.y, vars.yaw] = d.shift_poses([vars.x, vars.y, vars.yaw], u, av(|p| p.x), av(|p| p.y));
        }
        let Some(ext) = self.extension else {
            return model.log_likelihood_rows(&obs_params, &vars, &rows.av, &rows.items);
        };
        let theta = self.extension_var(params);
        let at = |k: usize| theta.slice(0, k, 1);
        match ext {
            Extension::Latency => {
                let d = at(0).mul_scalar(DELAY_SHARPNESS).softplus().mul_scalar(1.0 / DELAY_SHARPNESS) * states[3];
                vars.x = states[0] - d * states[YAW].cos();
                vars.y = states[1] - d * states[YAW].sin();
                vars.yaw = states[YAW] - d * states[4];
                model.log_likelihood_rows(&obs_params, &vars, &rows.av, &rows.items)
            }
            Extension::SizeBias => {
                vars.length = vars.length * at(0).mul_scalar(LOG_SCALE).exp();
                vars.width = vars.width * at(1).mul_scalar(LOG_SCALE).exp();
                model.log_likelihood_rows(&obs_params, &vars, &rows.av, &rows.items)
            }
            Extension::Clutter => model.log_likelihood_rows_with_clutter(
                &obs_params,
                &vars,
                &rows.av,
                &rows.items,
                at(0).mul_scalar(LOGIT_SCALE),
                at(1).mul_scalar(LOG_SCALE),
            ),
            Extension::HeadingFlip => {
                let kept = model.log_likelihood_rows(&obs_params, &vars, &rows.av, &rows.items);
                let reversed: Vec<Vec<O::Item>> =
                    rows.items.iter().map(|its| its.iter().map(O::reverse_heading).collect()).collect();
                let reversed: Vec<&[O::Item]> = reversed.iter().map(|v| v.as_slice()).collect();
                let flipped = model.log_likelihood_rows(&obs_params, &vars, &rows.av, &reversed);
                let logit = at(0).mul_scalar(LOGIT_SCALE);
                // ln(1 - p) = -softplus(logit), ln p = -softplus(-logit).
                log_add_exp(kept - logit.softplus(), flipped - logit.neg().softplus())
            }
            Extension::PersistentFlip => {
                // Each row's items as the detector reported them: reversed where
                // the row's indicator is set. The chain's parameters enter
                // through its prior and transition, not here.
                let bits: Vec<bool> =
                    states[self.flip_dim()].value().data().iter().map(|b| is_reversed(b.to_f64() as f32)).collect();
                let reversed: Vec<Vec<O::Item>> = rows
                    .items
                    .iter()
                    .zip(&bits)
                    .map(|(its, &r)| if r { its.iter().map(O::reverse_heading).collect() } else { Vec::new() })
                    .collect();
                let items: Vec<&[O::Item]> = rows
                    .items
                    .iter()
                    .zip(&reversed)
                    .zip(&bits)
                    .map(|((its, rev), &r)| if r { rev.as_slice() } else { *its })
                    .collect();
                model.log_likelihood_rows(&obs_params, &vars, &rows.av, &items)
            }
            Extension::HeavyTailedAccel => model.log_likelihood_rows(&obs_params, &vars, &rows.av, &rows.items),
        }
    }

    fn transition_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        prev: &[Var<'t, F>],
        next: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let vehicle = self.vehicle_transition_log_density(params, blocks, prev, next, actions);
        let with_drift = match self.drift_vars(params) {
            Some(d) => {
                let drift = STATE_DIM..STATE_DIM + DRIFT_DIMS;
                vehicle + d.transition_log_density(&prev[drift.clone()], &next[drift])
            }
            None => vehicle,
        };
        match self.flip_chain() {
            Some(_) => {
                let k = self.flip_dim();
                let chain = FlipChainVars::new(self.extension_var(params));
                with_drift + chain.transition_log_density(prev[k], next[k])
            }
            None => with_drift,
        }
    }

    /// `persistent_flip`'s: its chain starts in its stationary law, whose
    /// fraction is a parameter. The axial prior's 1/2 and the drift's standard
    /// normal are free of the parameters.
    fn has_prior_term(&self) -> bool {
        self.flip_chain().is_some()
    }

    /// The flip chain's initial law for `persistent_flip`; no term otherwise.
    fn prior_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        _blocks: &[Block],
        states: &[Var<'t, F>],
    ) -> Option<Var<'t, F>> {
        self.flip_chain()?;
        Some(FlipChainVars::new(self.extension_var(params)).prior_log_density(states[self.flip_dim()]))
    }

    /// The base model's reparameterised transition. A drift's offsets and a
    /// flip chain's indicator are held where they were: their noise is not
    /// recorded in the actions, so the through-filter baselines, the only users,
    /// refuse a drifting model and a persistent flip ([`crate::training::objective`]).
    fn propagate_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        prev: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Vec<Var<'t, F>> {
        let mut next = self.base.propagate_on_tape(params, blocks, prev, actions);
        next.extend_from_slice(&prev[STATE_DIM..STATE_DIM + self.drift_dims() + self.flip_dims()]);
        next
    }
}

impl<P: GaussianPolicy, O: ExtensibleObservation> ExtendedSsm<'_, '_, P, O> {
    /// The vehicle's part of the transition's log-density per row: the base
    /// model's, or with the heavy-tailed acceleration's mixture.
    fn vehicle_transition_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        prev: &[Var<'t, F>],
        next: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Var<'t, F> {
        if self.extension != Some(Extension::HeavyTailedAccel) {
            return self.base.transition_log_density(params, blocks, prev, next, actions);
        }
        let np = self.base.policy_param_count();
        let g = self.base.policy().gaussians_on_tape(&params[..np], prev[3], prev[4]);
        let (z1, z2) = g.standardise(&ActionVars { accel: actions[0], pinch: actions[1] });
        let theta = self.extension_var(params);
        let logit = theta.slice(0, 0, 1).mul_scalar(LOGIT_SCALE);
        let ratio = theta.slice(0, 1, 1).mul_scalar(LOG_SCALE).exp().add_scalar(1.0);
        let half_sq = |z: Var<'t, F>| (z * z).mul_scalar(-0.5);
        // (1 - p) N(z1; 0, c^2) + p N(z1; 0, (k c)^2) with c^2 = 1 / m2 and
        // m2 = 1 + p (k^2 - 1): unit variance, in log space.
        let m2 = (ratio * ratio).add_scalar(-1.0) * logit.sigmoid();
        let m2 = m2.add_scalar(1.0);
        let half_ln_m2 = m2.ln().mul_scalar(0.5);
        let z1_scaled = z1 * m2.sqrt();
        let narrow = half_sq(z1_scaled) + half_ln_m2 - logit.softplus();
        let wide = half_sq(z1_scaled / ratio) + half_ln_m2 - ratio.ln() - logit.neg().softplus();
        let accel = log_add_exp(narrow, wide);
        (accel + half_sq(z2) - g.l11.ln() - g.l22.ln()).add_scalar(-LN_2PI)
    }
}

/// The stored state of one object's particle as a [`State`].
pub(crate) fn state_at(states: &[f32], n: usize, i: usize) -> State {
    let c = |k: usize| states[k * n + i] as f64;
    debug_assert!(states.len() >= STATE_DIM * n);
    State { x: c(0), y: c(1), yaw: c(YAW), v: c(3), kappa: c(4) }
}

/// Geary's ratio `E|x| / sqrt(E x^2)` of a Gaussian: `sqrt(2 / pi)`.
pub const GAUSSIAN_GEARY_RATIO: f64 = 0.797_884_560_802_865_4;

/// The sd ratio `r` at which a scale mixture of two centred normals, fraction
/// `p` at `r` times the sd of the rest, has Geary's ratio `target`:
/// `sqrt(2/pi) ((1-p) + p r) / sqrt((1-p) + p r^2)`, which falls from the
/// Gaussian's as `r` grows (for `p` below one half).
fn tail_ratio_for_geary(p: f64, target: f64) -> f64 {
    // Solved for its negative, which rises with r.
    tail_ratio_where(|r| -GAUSSIAN_GEARY_RATIO * ((1.0 - p) + p * r) / ((1.0 - p) + p * r * r).sqrt(), -target)
}

/// The sd ratio `r` for which a scale mixture of normals, `1 - p` at sd 1 and `p`
/// at sd `r`, has excess kurtosis `excess`:
/// `3 ((1 - p) + p r^4) / ((1 - p) + p r^2)^2 - 3`, increasing in `r`.
fn tail_ratio_for_kurtosis(p: f64, excess: f64) -> f64 {
    tail_ratio_where(
        |r| {
            let r2 = r * r;
            3.0 * ((1.0 - p) + p * r2 * r2) / ((1.0 - p) + p * r2).powi(2) - 3.0
        },
        excess,
    )
}

/// The `r` in `[1, MAX_INITIAL_TAIL_RATIO]` where `f`, increasing, reaches
/// `target`, by bisection: the upper end when `f` stays below it, and at least
/// a hair above 1 (a ratio of exactly 1 is no tail at all).
fn tail_ratio_where(f: impl Fn(f64) -> f64, target: f64) -> f64 {
    if f(MAX_INITIAL_TAIL_RATIO) <= target {
        return MAX_INITIAL_TAIL_RATIO;
    }
    bisect_increasing(f, target, (1.0, MAX_INITIAL_TAIL_RATIO), 60).max(1.0 + 1e-3)
}
