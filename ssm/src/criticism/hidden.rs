//! Generated datasets with one hidden effect each (SPEC §7): the test bed of the
//! diagnosis. This file owns the [`HiddenEffect`] vocabulary (the catalogue's
//! effects with their sizes), the [`BoxGenerator`] that makes box detections of
//! known quality, and [`generate_hidden`], which simulates scenes like the paper's
//! synthetic data and hides one effect in them.
//!
//! # How the data are made
//!
//! * **Scenes** as in [`crate::simulation::synthetic`] ([`SceneConfig::paper`]: the AV drives
//!   along +x at 5 m/s, car-sized objects with their priors), but with
//!   [`HiddenConfig::objects_per_scene`] objects placed at 5–35 m so that point sets
//!   are plentiful ([`HiddenConfig::scene_config`]).
//! * **Dynamics**: the true [`HandCraftedPolicy`] and the exact motion model, by the
//!   same code as the paper's data ([`simulate_object`]); only the acceleration
//!   innovation changes under [`HiddenEffect::HeavyTailedAccel`] ([`ScaleMixture`])
//!   and [`HiddenEffect::StudentTAccel`] ([`StandardStudentT`]), whose sizes are
//!   compared by [`HiddenEffect::kl_per_innovation`].
//! * **Points** come from the physically motivated [`PointGenerator`] (its default),
//!   not from a fitted network: nothing is fitted, so generation is fast.
//! * **Boxes** come from [`BoxGenerator`] (its default).
//!
//! The ground truth (`states.csv`, `actions.csv`) is always the true motion; the
//! effect changes only what is observed (or, for heavy tails, how the actions are
//! drawn). The objects' stated length and width are the ones drawn for the scene.
//!
//! # Reproducibility
//!
//! Every draw comes from a [`StdRng`] seeded with [`HiddenConfig::seed`]: one `u64`
//! per scene is drawn from it, and each scene draws from its own [`StdRng`] seeded
//! with that value, object after object (placement and dynamics, then the
//! observations of every step). The same configuration gives the same dataset.
//!
//! ```
//! use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
//! use ssm::data::ObservationKind;
//!
//! let effect = HiddenEffect::by_id("latency").unwrap();
//! assert_eq!(effect, HiddenEffect::Latency { delay: 0.15 });
//! let config = HiddenConfig::quick(ObservationKind::Points, effect, 7);
//! let data = generate_hidden(&config).unwrap();
//! assert_eq!(data.objects().len(), config.scenes * config.objects_per_scene);
//! assert!(data.states().unwrap().is_complete());
//!
//! // Clutter is a points-only effect.
//! let boxes = HiddenConfig::quick(ObservationKind::Boxes, HiddenEffect::by_id("clutter").unwrap(), 7);
//! assert!(generate_hidden(&boxes).is_err());
//! ```

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::data::{BoxDetection, Dataset, Meta, ObservationKind, Pose, State};
use crate::models::extended::lagged_pose;
use crate::models::flip_chain::FlipChain;
use crate::models::observation::edges::sample_laplace;
use crate::models::observation::{ObsContext, PointGenerator};
use crate::models::vehicle::HandCraftedPolicy;
use crate::simulation::synthetic::{
    build_dataset, ground_truth_builder, scene_motion, simulate_object, SceneConfig, SimulatedObject, SyntheticError,
    SyntheticScene,
};
use crate::stats::log_sum_exp;
use crate::util::angles::{reversed_heading, wrap_angle};

/// The ids of the hidden effects, in catalogue order (`none` first), then the
/// effects that no catalogue extension models (`student_t_accel`, another tail
/// family than the catalogue's, is meant to be named `heavy_tailed_accel`;
/// `ego_pose_noise` is meant to be named by none).
pub const HIDDEN_EFFECT_IDS: [&str; 9] = [
    "none",
    "latency",
    "clutter",
    "size_bias",
    "heavy_tailed_accel",
    "student_t_accel",
    "heading_flip",
    "persistent_flip",
    "ego_pose_noise",
];

/// Lag-one correlation of the hidden `persistent_flip` at every strength (runs
/// of reversed detections last `1 / ((1 - p) 0.2)` steps on average, about 6 at
/// the default fraction).
pub const HIDDEN_FLIP_PERSISTENCE: f64 = 0.8;

/// Range of the objects' prior mean positions from the AV (m): nearer than the
/// paper's 5–50 m, so that every object receives plenty of points.
pub const HIDDEN_RANGE: (f64, f64) = (5.0, 35.0);

/// Sd of the prior of the initial position (m): a tracker's handover, tighter than
/// the paper's 0.5 m, so that the prior says where an object is at `t = 0` well
/// enough for observations lagging behind it to show.
pub const HIDDEN_PRIOR_SD_POSITION: f64 = 0.2;

/// One hidden effect and its size (or none), as the catalogue of model extensions
/// ([`crate::models::extended`]) defines it. Serialised with the catalogue ids as tags,
/// e.g. `{"latency":{"delay":0.15}}` or `"none"`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HiddenEffect {
    /// No effect: the data follow the base model's assumptions.
    None,
    /// Observations lag the state: each step's observation is generated from
    /// [`lagged_pose`]`(state, delay)`.
    Latency {
        /// The lag (s, finite, >= 0).
        delay: f64,
    },
    /// Each point (points data only) is with probability `fraction` replaced by a
    /// clutter point drawn from an isotropic Gaussian of sd `scale` around the box
    /// centre (the true position).
    Clutter {
        /// Probability that a point is clutter (in `[0, 1]`).
        fraction: f64,
        /// Sd of a clutter point around the box centre (m, positive).
        scale: f64,
    },
    /// The true extents are `length_factor * length` and `width_factor * width`
    /// while the dataset states the unscaled length and width (points data only).
    SizeBias {
        /// True length over stated length (positive).
        length_factor: f64,
        /// True width over stated width (positive).
        width_factor: f64,
    },
    /// The acceleration innovation of the hand-crafted policy is a scale mixture:
    /// with probability `fraction` its sd is `ratio` times larger
    /// (`accel = mean + sd z`, `z ~ (1 - f) N(0, 1) + f N(0, ratio^2)`; see
    /// [`ScaleMixture`]).
    HeavyTailedAccel {
        /// Probability of the wide component (in `[0, 1]`).
        fraction: f64,
        /// Sd of the wide component over the policy's sd (positive).
        ratio: f64,
    },
    /// Heavy tails of another family than the catalogue's two-normal mixture: the
    /// acceleration innovation is Student-t with `dof` degrees of freedom at unit
    /// scale (`accel = mean + sd z`; see [`StandardStudentT`]): its bulk is as wide
    /// as the policy's, like the mixture's narrow component, and its tails heavier.
    /// The catalogue's `heavy_tailed_accel` is the extension that should explain it.
    StudentTAccel {
        /// Degrees of freedom (finite, > 2).
        dof: f64,
    },
    /// With probability `fraction` a detection's yaw is reversed by pi (wrapped to
    /// `(-pi, pi]`) (box data only).
    HeadingFlip {
        /// Probability that a detection is flipped (in `[0, 1]`).
        fraction: f64,
    },
    /// Detections' yaws reversed by pi in runs: whether an object's detection
    /// at `t` is reversed follows a stationary two-state Markov chain per object
    /// ([`crate::models::flip_chain::FlipChain`]) with reversed fraction
    /// `fraction` and lag-one correlation `persistence` (box data only).
    PersistentFlip {
        /// Stationary fraction of reversed detections (in `[0, 1]`).
        fraction: f64,
        /// Lag-one correlation of the reversals (in `[0, 1)`).
        persistence: f64,
    },
    /// An effect outside the catalogue: the observer's own pose is noisy. At each
    /// step of a scene the sensor sits at the stated AV pose moved by Gaussian
    /// errors (`position_sd` in x and y, `yaw_sd` in heading), and every object's
    /// observations of that step are recorded as if it sat at the stated pose: one
    /// rigid shift of the whole scene, larger far away (range times the yaw error).
    /// No catalogue extension models it; a diagnosis should call it `unexplained`
    /// (or `none` when too weak to see), never a catalogue cause.
    EgoPoseNoise {
        /// Sd of the sensor's position error, per axis (m, finite, >= 0).
        position_sd: f64,
        /// Sd of its heading error (rad, finite, >= 0).
        yaw_sd: f64,
    },
}

fn config_err(m: impl Into<String>) -> SyntheticError {
    SyntheticError::Config(m.into())
}

fn check_fraction(what: &str, f: f64) -> Result<(), SyntheticError> {
    if (0.0..=1.0).contains(&f) {
        Ok(())
    } else {
        Err(config_err(format!("{what} must be in [0, 1], got {f}")))
    }
}

fn check_positive(what: &str, v: f64) -> Result<(), SyntheticError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(config_err(format!("{what} must be finite and positive, got {v}")))
    }
}

impl HiddenEffect {
    /// Catalogue id: `"none"`, `"latency"`, `"clutter"`, `"size_bias"`,
    /// `"heavy_tailed_accel"` or `"heading_flip"` (see [`HIDDEN_EFFECT_IDS`]).
    pub fn id(&self) -> &'static str {
        match self {
            HiddenEffect::None => "none",
            HiddenEffect::Latency { .. } => "latency",
            HiddenEffect::Clutter { .. } => "clutter",
            HiddenEffect::SizeBias { .. } => "size_bias",
            HiddenEffect::HeavyTailedAccel { .. } => "heavy_tailed_accel",
            HiddenEffect::StudentTAccel { .. } => "student_t_accel",
            HiddenEffect::HeadingFlip { .. } => "heading_flip",
            HiddenEffect::PersistentFlip { .. } => "persistent_flip",
            HiddenEffect::EgoPoseNoise { .. } => "ego_pose_noise",
        }
    }

    /// The effect with a clearly noticeable default size, by catalogue id: latency
    /// 0.15 s; clutter 15 % of points at 2.5 m; size bias 1.25 (length) x 1.15
    /// (width); heavy-tailed acceleration 10 % of innovations 10 times wider (5 m/s² with the true 0.5); heading
    /// flips of 20 % of detections. An unknown id is an error that lists the known
    /// ones.
    ///
    /// ```
    /// use ssm::criticism::hidden::{HiddenEffect, HIDDEN_EFFECT_IDS};
    /// for id in HIDDEN_EFFECT_IDS {
    ///     assert_eq!(HiddenEffect::by_id(id).unwrap().id(), id);
    /// }
    /// assert!(HiddenEffect::by_id("gremlins").unwrap_err().to_string().contains("heading_flip"));
    /// ```
    pub fn by_id(id: &str) -> Result<HiddenEffect, SyntheticError> {
        HiddenEffect::at_strength(id, 1.0)
    }

    /// The effect `id` at `strength` times its default size (1 = [`HiddenEffect::by_id`]):
    /// a delay of `0.15 s` times it; a clutter fraction of `0.15` times it (at most
    /// 0.9); extents off by `25%` and `15%` times it; a wide component of `10%` of
    /// the accelerations whose sd ratio exceeds 1 by `9` times it; Student-t whose
    /// degrees of freedom put it as far from a Gaussian as that mixture at the same
    /// strength (equal [`HiddenEffect::kl_per_innovation`]: about 2.56, 2.19 and 2.06
    /// degrees of freedom at 0.5, 1 and 2), so that the two tail families are
    /// compared at the same size; a flip
    /// fraction of `0.2` times it (at most 0.5), independent or in runs of
    /// persistence [`HIDDEN_FLIP_PERSISTENCE`]; the observer's pose off by `0.2 m`
    /// and `0.02 rad` (sds) times it (0.4 m at 20 m from the AV). Fails for an
    /// unknown id or a strength that is not positive and finite.
    ///
    /// ```
    /// use ssm::criticism::hidden::HiddenEffect;
    /// let weak = HiddenEffect::at_strength("latency", 0.5).unwrap();
    /// assert_eq!(weak, HiddenEffect::Latency { delay: 0.075 });
    /// assert!(HiddenEffect::at_strength("latency", 0.0).is_err());
    /// ```
    pub fn at_strength(id: &str, strength: f64) -> Result<HiddenEffect, SyntheticError> {
        if !(strength.is_finite() && strength > 0.0) {
            return Err(config_err(format!("a hidden effect's strength must be positive and finite, got {strength}")));
        }
        let s = strength;
        Ok(match id {
            "none" => HiddenEffect::None,
            "latency" => HiddenEffect::Latency { delay: 0.15 * s },
            "clutter" => HiddenEffect::Clutter { fraction: (0.15 * s).min(0.9), scale: 2.5 },
            "size_bias" => HiddenEffect::SizeBias { length_factor: 1.0 + 0.25 * s, width_factor: 1.0 + 0.15 * s },
            "heavy_tailed_accel" => HiddenEffect::HeavyTailedAccel { fraction: 0.1, ratio: 1.0 + 9.0 * s },
            "student_t_accel" => {
                let mixture = HiddenEffect::at_strength("heavy_tailed_accel", s)?;
                let target = mixture.kl_per_innovation().expect("the mixture's divergence is defined");
                HiddenEffect::StudentTAccel { dof: student_t_dof_with_kl(target) }
            }
            "heading_flip" => HiddenEffect::HeadingFlip { fraction: (0.2 * s).min(0.5) },
            "persistent_flip" => {
                HiddenEffect::PersistentFlip { fraction: (0.2 * s).min(0.5), persistence: HIDDEN_FLIP_PERSISTENCE }
            }
            "ego_pose_noise" => HiddenEffect::EgoPoseNoise { position_sd: 0.2 * s, yaw_sd: 0.02 * s },
            _ => {
                return Err(config_err(format!(
                    "unknown hidden effect `{id}` (known: {})",
                    HIDDEN_EFFECT_IDS.join(", ")
                )))
            }
        })
    }

    /// Which observation kind it applies to (`None` = both).
    pub fn applies_to(&self) -> Option<ObservationKind> {
        match self {
            HiddenEffect::None
            | HiddenEffect::Latency { .. }
            | HiddenEffect::HeavyTailedAccel { .. }
            | HiddenEffect::StudentTAccel { .. }
            | HiddenEffect::EgoPoseNoise { .. } => None,
            HiddenEffect::Clutter { .. } | HiddenEffect::SizeBias { .. } => Some(ObservationKind::Points),
            HiddenEffect::HeadingFlip { .. } | HiddenEffect::PersistentFlip { .. } => Some(ObservationKind::Boxes),
        }
    }

    /// Checks the effect's size (finite; fractions in `[0, 1]`; scales, factors and
    /// ratios positive; a delay `>= 0`).
    pub fn validate(&self) -> Result<(), SyntheticError> {
        match *self {
            HiddenEffect::None => Ok(()),
            HiddenEffect::Latency { delay } => {
                if delay.is_finite() && delay >= 0.0 {
                    Ok(())
                } else {
                    Err(config_err(format!("latency: delay must be finite and >= 0, got {delay}")))
                }
            }
            HiddenEffect::Clutter { fraction, scale } => {
                check_fraction("clutter: fraction", fraction)?;
                check_positive("clutter: scale", scale)
            }
            HiddenEffect::SizeBias { length_factor, width_factor } => {
                check_positive("size_bias: length_factor", length_factor)?;
                check_positive("size_bias: width_factor", width_factor)
            }
            HiddenEffect::HeavyTailedAccel { fraction, ratio } => {
                check_fraction("heavy_tailed_accel: fraction", fraction)?;
                check_positive("heavy_tailed_accel: ratio", ratio)
            }
            HiddenEffect::StudentTAccel { dof } => {
                if dof.is_finite() && dof > 2.0 {
                    Ok(())
                } else {
                    Err(config_err(format!("student_t_accel: dof must be finite and > 2, got {dof}")))
                }
            }
            HiddenEffect::HeadingFlip { fraction } => check_fraction("heading_flip: fraction", fraction),
            HiddenEffect::PersistentFlip { fraction, persistence } => {
                check_fraction("persistent_flip: fraction", fraction)?;
                if (0.0..1.0).contains(&persistence) {
                    Ok(())
                } else {
                    Err(config_err(format!("persistent_flip: persistence must be in [0, 1), got {persistence}")))
                }
            }
            HiddenEffect::EgoPoseNoise { position_sd, yaw_sd } => {
                for (what, v) in [("position_sd", position_sd), ("yaw_sd", yaw_sd)] {
                    if !(v.is_finite() && v >= 0.0) {
                        return Err(config_err(format!("ego_pose_noise: {what} must be finite and >= 0, got {v}")));
                    }
                }
                Ok(())
            }
        }
    }

    /// How far a heavy-tail effect's acceleration innovation is from a Gaussian:
    /// the KL divergence (nats per innovation) from its distribution to the
    /// Gaussian of the same variance, which is what the true model gains per
    /// action over the best Gaussian policy when the actions are seen. `None`
    /// for the other effects.
    ///
    /// ```
    /// use ssm::criticism::hidden::HiddenEffect;
    /// let mixture = HiddenEffect::HeavyTailedAccel { fraction: 0.1, ratio: 10.0 };
    /// assert!((mixture.kl_per_innovation().unwrap() - 0.7405).abs() < 1e-3);
    /// let t5 = HiddenEffect::StudentTAccel { dof: 5.0 };
    /// assert!((t5.kl_per_innovation().unwrap() - 0.0468).abs() < 1e-3);
    /// assert_eq!(HiddenEffect::None.kl_per_innovation(), None);
    /// ```
    pub fn kl_per_innovation(&self) -> Option<f64> {
        match *self {
            HiddenEffect::HeavyTailedAccel { fraction, ratio } => {
                let (log_narrow, log_wide) = ((1.0 - fraction).ln(), fraction.ln() - ratio.ln());
                let log_density =
                    |x: f64| log_sum_exp(&[log_narrow - 0.5 * x * x, log_wide - 0.5 * (x / ratio).powi(2)]);
                Some(kl_to_gaussian(log_density, (1.0 - fraction) + fraction * ratio * ratio))
            }
            HiddenEffect::StudentTAccel { dof } => Some(student_t_kl(dof)),
            _ => None,
        }
    }
}

/// Midpoints of the quadrature of [`kl_to_gaussian`] (over `x = tan(theta)`).
const KL_QUADRATURE_POINTS: usize = 1 << 16;

/// KL divergence (nats) from the zero-mean density whose log is `log_density` up
/// to a constant, and whose variance is `variance`, to the Gaussian of that
/// variance: `-H(p) + ln(2 pi variance) / 2 + 1/2`. The normaliser and the
/// entropy come from the midpoint rule over `x = tan(theta)`, which covers the
/// whole line and puts points where the tails are.
fn kl_to_gaussian(log_density: impl Fn(f64) -> f64, variance: f64) -> f64 {
    let h = std::f64::consts::PI / KL_QUADRATURE_POINTS as f64;
    let (mut mass, mut mass_log) = (0.0, 0.0);
    for i in 0..KL_QUADRATURE_POINTS {
        let theta = -std::f64::consts::FRAC_PI_2 + (i as f64 + 0.5) * h;
        let (x, jacobian) = (theta.tan(), h / theta.cos().powi(2));
        let log_p = log_density(x);
        let p = log_p.exp() * jacobian;
        if p > 0.0 {
            mass += p;
            mass_log += p * log_p;
        }
    }
    let negative_entropy = mass_log / mass - mass.ln();
    negative_entropy + 0.5 * (2.0 * std::f64::consts::PI * variance).ln() + 0.5
}

/// [`HiddenEffect::kl_per_innovation`] of a Student-t with `dof > 2` (the same at
/// every scale; computed at unit scale, variance `dof / (dof - 2)`).
fn student_t_kl(dof: f64) -> f64 {
    kl_to_gaussian(|x| -0.5 * (dof + 1.0) * (x * x / dof).ln_1p(), dof / (dof - 2.0))
}

/// The degrees of freedom of the Student-t whose divergence from
/// the Gaussian is `kl` (nats per innovation): the divergence falls from
/// infinity at 2 towards 0 as the degrees of freedom grow, so bisection on
/// `ln(dof - 2)` over `[ln 1e-4, ln 1e4]` finds it (clamped to those ends).
fn student_t_dof_with_kl(kl: f64) -> f64 {
    let (mut lo, mut hi) = (1e-4f64.ln(), 1e4f64.ln());
    for _ in 0..48 {
        let mid = 0.5 * (lo + hi);
        if student_t_kl(2.0 + mid.exp()) > kl {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    2.0 + (0.5 * (lo + hi)).exp()
}

/// A standard normal scale mixture: `z ~ (1 - fraction) N(0, 1) + fraction N(0, ratio^2)`
/// (unit sd with probability `1 - fraction`, sd `ratio` otherwise). Its excess
/// kurtosis is `3 ((1 - f) + f r^4) / ((1 - f) + f r^2)^2 - 3` (22.3 at the default
/// `f = 0.1`, `r = 10`). Each draw takes a uniform (the component) then a standard
/// normal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScaleMixture {
    /// Probability of the wide component.
    pub fraction: f64,
    /// Sd of the wide component.
    pub ratio: f64,
}

impl Distribution<f64> for ScaleMixture {
    fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        let wide = rng.random::<f64>() < self.fraction;
        let z: f64 = rng.sample(StandardNormal);
        if wide {
            self.ratio * z
        } else {
            z
        }
    }
}

/// Student-t with `dof > 2` degrees of freedom at unit scale (the standard t):
/// its bulk is as wide as a standard normal's, like [`ScaleMixture`]'s narrow
/// component, and its variance is `dof / (dof - 2)`. Its excess kurtosis is
/// `6 / (dof - 4)` for `dof > 4` (infinite below).
#[derive(Clone, Copy, Debug)]
pub struct StandardStudentT {
    t: rand_distr::StudentT<f64>,
}

impl StandardStudentT {
    /// Fails unless `dof` is finite and above 2.
    pub fn new(dof: f64) -> Result<Self, SyntheticError> {
        HiddenEffect::StudentTAccel { dof }.validate()?;
        let t = rand_distr::StudentT::new(dof).map_err(|e| config_err(format!("student_t_accel: {e}")))?;
        Ok(StandardStudentT { t })
    }
}

impl Distribution<f64> for StandardStudentT {
    fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        rng.sample(self.t)
    }
}

/// A box detector of known quality, the box counterpart of [`PointGenerator`].
///
/// Given the object's pose and the AV's pose: the detection is missing with
/// probability [`BoxGenerator::miss_probability`]; otherwise its centre is the
/// object's position plus independent Laplace offsets along and across the line
/// of sight from the AV, with zero means and scales growing with range `r`
/// (`along_base + along_per_metre r`, `across_base + across_per_metre r`), and its
/// yaw the object's plus zero-mean Gaussian noise, wrapped to `(-pi, pi]`. Length
/// and width are the context's (the object's stated ones), the score 1.
///
/// ```
/// use rand::{rngs::StdRng, SeedableRng};
/// use ssm::criticism::hidden::BoxGenerator;
/// use ssm::data::Pose;
/// use ssm::models::observation::ObsContext;
///
/// let g = BoxGenerator::default();
/// assert!((g.along_scale(20.0) - 0.35).abs() < 1e-12);
/// let ctx = ObsContext::new(Pose::default(), 4.5, 1.8);
/// let pose = Pose { x: 20.0, y: 0.0, yaw: 1.0 };
/// let mut rng = StdRng::seed_from_u64(1);
/// let dets: Vec<_> = (0..200).filter_map(|_| g.sample(&ctx, pose, &mut rng)).collect();
/// assert!(dets.len() > 150 && dets.len() < 200);
/// assert!(dets.iter().all(|d| d.length == 4.5 && d.score == 1.0));
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoxGenerator {
    /// Laplace scale of the offset along the line of sight at range 0 (m).
    pub along_base: f64,
    /// Its growth per metre of range.
    pub along_per_metre: f64,
    /// Laplace scale of the offset across the line of sight at range 0 (m).
    pub across_base: f64,
    /// Its growth per metre of range.
    pub across_per_metre: f64,
    /// Sd of the yaw noise (rad).
    pub yaw_sd: f64,
    /// Probability that a detection is missing.
    pub miss_probability: f64,
}

impl Default for BoxGenerator {
    /// Along 0.15 + 0.01 r m (0.35 m at 20 m), across 0.08 + 0.004 r m (0.16 m at
    /// 20 m): depth is harder to measure than bearing. Yaw sd 0.04 rad; 10 % missed.
    fn default() -> Self {
        BoxGenerator {
            along_base: 0.15,
            along_per_metre: 0.01,
            across_base: 0.08,
            across_per_metre: 0.004,
            yaw_sd: 0.04,
            miss_probability: 0.1,
        }
    }
}

/// Guard of the line-of-sight normalisation (m): an object at the AV gets the
/// +x axis as its line of sight.
const LOS_EPS: f64 = 1e-6;

impl BoxGenerator {
    /// Laplace scale of the offset along the line of sight at `range` (m).
    pub fn along_scale(&self, range: f64) -> f64 {
        self.along_base + self.along_per_metre * range
    }

    /// Laplace scale of the offset across the line of sight at `range` (m).
    pub fn across_scale(&self, range: f64) -> f64 {
        self.across_base + self.across_per_metre * range
    }

    /// Checks every setting (scales and sd finite and positive at range 0 and not
    /// shrinking with range; the miss probability in `[0, 1]`).
    pub fn validate(&self) -> Result<(), SyntheticError> {
        check_positive("box generator: along_base", self.along_base)?;
        check_positive("box generator: across_base", self.across_base)?;
        check_positive("box generator: yaw_sd", self.yaw_sd)?;
        for (what, v) in [("along_per_metre", self.along_per_metre), ("across_per_metre", self.across_per_metre)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(config_err(format!("box generator: {what} must be finite and >= 0, got {v}")));
            }
        }
        check_fraction("box generator: miss_probability", self.miss_probability)
    }

    /// The detection of an object at `pose` seen from `ctx.av`, or `None` when it is
    /// missed. Draws a uniform (missed or not), then, if detected, the along and
    /// across offsets and the yaw noise.
    ///
    /// # Panics
    /// If [`BoxGenerator::yaw_sd`] is negative or NaN (see [`BoxGenerator::validate`]).
    #[track_caller]
    pub fn sample<R: Rng + ?Sized>(&self, ctx: &ObsContext, pose: Pose, rng: &mut R) -> Option<BoxDetection> {
        if rng.random::<f64>() < self.miss_probability {
            return None;
        }
        let (dx, dy) = (pose.x - ctx.av.x, pose.y - ctx.av.y);
        let r = dx.hypot(dy);
        let (lx, ly) = if r > LOS_EPS { (dx / r, dy / r) } else { (1.0, 0.0) };
        let along = sample_laplace(0.0, self.along_scale(r), rng);
        let across = sample_laplace(0.0, self.across_scale(r), rng);
        let dyaw = Normal::new(0.0, self.yaw_sd).expect("validated sd").sample(rng);
        Some(BoxDetection {
            x: pose.x + along * lx - across * ly,
            y: pose.y + along * ly + across * lx,
            yaw: wrap_angle(pose.yaw + dyaw),
            length: ctx.length,
            width: ctx.width,
            score: 1.0,
        })
    }
}

/// Size and seed of a hidden-effect dataset.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HiddenConfig {
    /// Which observations the dataset holds.
    pub kind: ObservationKind,
    /// The hidden effect.
    pub effect: HiddenEffect,
    /// Number of scenes (ids `0..scenes`, at least 1).
    pub scenes: usize,
    /// Objects per scene (at least 1).
    pub objects_per_scene: usize,
    /// Steps per scene, `T + 1` (at least 1).
    pub steps: usize,
    /// Seed of every random draw.
    pub seed: u64,
}

impl HiddenConfig {
    /// A small size for tests: 8 scenes of 6 objects, 16 steps (`T = 15`).
    pub fn quick(kind: ObservationKind, effect: HiddenEffect, seed: u64) -> Self {
        HiddenConfig { kind, effect, scenes: 8, objects_per_scene: 6, steps: 16, seed }
    }

    /// The scene settings used: the paper's ([`SceneConfig::paper`]) with
    /// [`HiddenConfig::objects_per_scene`] objects at [`HIDDEN_RANGE`] and prior
    /// position sds of [`HIDDEN_PRIOR_SD_POSITION`].
    pub fn scene_config(&self) -> SceneConfig {
        let paper = SceneConfig::paper(self.steps);
        let prior_sd = State { x: HIDDEN_PRIOR_SD_POSITION, y: HIDDEN_PRIOR_SD_POSITION, ..paper.prior_sd };
        SceneConfig { objects: self.objects_per_scene, range: HIDDEN_RANGE, prior_sd, ..paper }
    }

    /// Checks the sizes, the effect's size, and that the effect applies to the kind.
    pub fn validate(&self) -> Result<(), SyntheticError> {
        if self.scenes == 0 {
            return Err(config_err("hidden-effect data: scenes must be at least 1"));
        }
        if self.objects_per_scene == 0 {
            return Err(config_err("hidden-effect data: objects_per_scene must be at least 1"));
        }
        if self.steps == 0 {
            return Err(config_err("hidden-effect data: steps must be at least 1"));
        }
        if i64::try_from(self.scenes).is_err() || i64::try_from(self.objects_per_scene).is_err() {
            return Err(config_err("hidden-effect data: too many scenes or objects"));
        }
        self.effect.validate()?;
        if let Some(kind) = self.effect.applies_to() {
            if kind != self.kind {
                return Err(config_err(format!(
                    "hidden effect `{}` applies to {kind:?} data only, not to {:?} data",
                    self.effect.id(),
                    self.kind
                )));
            }
        }
        self.scene_config().validate()
    }
}

/// Generates the dataset (with `states.csv` / `actions.csv` ground truth) of
/// `config`: see the [module docs](self). Rejects bad sizes and an effect that
/// does not apply to the kind with [`SyntheticError::Config`]; never panics.
pub fn generate_hidden(config: &HiddenConfig) -> Result<Dataset, SyntheticError> {
    config.validate()?;
    let scene_config = config.scene_config();
    let mut rng = StdRng::seed_from_u64(config.seed);
    let seeds: Vec<u64> = (0..config.scenes).map(|_| rng.random()).collect();
    let mut scenes = Vec::with_capacity(config.scenes);
    let mut boxes = Vec::with_capacity(config.scenes);
    for (k, &seed) in seeds.iter().enumerate() {
        let (scene, dets) = simulate_hidden_scene(config, &scene_config, k as i64, &mut StdRng::seed_from_u64(seed))?;
        scenes.push(scene);
        boxes.push(dets);
    }
    match config.kind {
        ObservationKind::Points => build_dataset(&scene_config, &scenes),
        ObservationKind::Boxes => {
            let meta = Meta::new(scene_config.dt, scene_config.steps);
            let mut b = ground_truth_builder(meta, ObservationKind::Boxes, &scenes);
            for (s, dets) in scenes.iter().zip(&boxes) {
                for (o, per_step) in s.objects.iter().zip(dets) {
                    for (t, d) in per_step.iter().enumerate() {
                        if let Some(d) = d {
                            b.detection(s.id, o.id, t, *d);
                        }
                    }
                }
            }
            Ok(b.build()?)
        }
    }
}

/// Box detections of one scene, `detections[object][t]`.
type SceneDetections = Vec<Vec<Option<BoxDetection>>>;

/// One scene: the truth and, for points data, the points (in the scene); for box
/// data the detections (returned beside it; the scene's point sets stay empty).
fn simulate_hidden_scene(
    config: &HiddenConfig,
    scene_config: &SceneConfig,
    id: i64,
    rng: &mut StdRng,
) -> Result<(SyntheticScene, SceneDetections), SyntheticError> {
    let motion = scene_motion(scene_config)?;
    let policy = HandCraftedPolicy::truth();
    let steps = scene_config.steps;
    let av: Vec<Pose> = (0..steps).map(|t| scene_config.av_pose(t)).collect();
    let n = scene_config.objects;
    let mut scene = SyntheticScene {
        id,
        av,
        objects: Vec::with_capacity(n),
        states: Vec::with_capacity(n),
        actions: Vec::with_capacity(n),
        points: Vec::with_capacity(n),
    };
    let mut detections = Vec::with_capacity(n);
    let points = PointGenerator::default();
    let boxes = BoxGenerator::default();
    // The sensor's pose errors, one per step, shared by every object of the scene
    // (drawn only for that effect, so other datasets' draws are unchanged).
    let ego: Vec<EgoError> = match config.effect {
        HiddenEffect::EgoPoseNoise { position_sd, yaw_sd } => {
            (0..steps).map(|_| EgoError::draw(position_sd, yaw_sd, rng)).collect()
        }
        _ => Vec::new(),
    };
    for k in 0..n {
        let (start, k) = (scene.av[0], k as i64);
        let SimulatedObject { object, states, actions } = match config.effect {
            HiddenEffect::HeavyTailedAccel { fraction, ratio } => {
                simulate_object(scene_config, &policy, &motion, start, id, k, &ScaleMixture { fraction, ratio }, rng)
            }
            HiddenEffect::StudentTAccel { dof } => {
                simulate_object(scene_config, &policy, &motion, start, id, k, &StandardStudentT::new(dof)?, rng)
            }
            _ => simulate_object(scene_config, &policy, &motion, start, id, k, &StandardNormal, rng),
        };
        let ctx_of = |t: usize| {
            let ctx = ObsContext::of_object(scene.av[t], &object);
            match config.effect {
                HiddenEffect::SizeBias { length_factor, width_factor } => {
                    ObsContext { length: ctx.length * length_factor, width: ctx.width * width_factor, ..ctx }
                }
                _ => ctx,
            }
        };
        match config.kind {
            ObservationKind::Points => {
                let per_step = states.iter().enumerate().map(|(t, x)| {
                    let mut pts = hidden_points(&points, config.effect, &ctx_of(t), x, rng);
                    if let Some(e) = ego.get(t) {
                        pts.iter_mut().for_each(|p| *p = e.recorded(scene.av[t], *p));
                    }
                    pts
                });
                scene.points.push(per_step.collect());
            }
            ObservationKind::Boxes => {
                let runs = match config.effect {
                    HiddenEffect::PersistentFlip { fraction, persistence } => {
                        FlipChain { fraction, persistence }.sample_path(states.len(), rng)
                    }
                    _ => Vec::new(),
                };
                let per_step = states.iter().enumerate().map(|(t, x)| {
                    let mut d = hidden_box(&boxes, config.effect, &ctx_of(t), x, rng);
                    if let (true, Some(d)) = (runs.get(t).copied().unwrap_or(false), d.as_mut()) {
                        d.yaw = reversed_heading(d.yaw);
                    }
                    if let (Some(e), Some(d)) = (ego.get(t), d.as_mut()) {
                        [d.x, d.y] = e.recorded(scene.av[t], [d.x, d.y]);
                        d.yaw = wrap_angle(d.yaw - e.yaw);
                    }
                    d
                });
                detections.push(per_step.collect());
                scene.points.push(vec![Vec::new(); steps]);
            }
        }
        scene.objects.push(object);
        scene.states.push(states);
        scene.actions.push(actions);
    }
    Ok((scene, detections))
}

/// The error of the sensor's pose at one step ([`HiddenEffect::EgoPoseNoise`]):
/// the sensor sits at the stated AV pose moved by `(dx, dy)` and turned by `yaw`.
#[derive(Clone, Copy, Debug)]
struct EgoError {
    dx: f64,
    dy: f64,
    yaw: f64,
}

impl EgoError {
    /// Draws the position errors, then the heading error.
    fn draw(position_sd: f64, yaw_sd: f64, rng: &mut StdRng) -> EgoError {
        let mut normal = || rng.sample::<f64, _>(StandardNormal);
        let (dx, dy) = (position_sd * normal(), position_sd * normal());
        EgoError { dx, dy, yaw: yaw_sd * normal() }
    }

    /// Where a world point `p` is recorded: the sensor measures it from its true
    /// pose (the stated `av` moved by this error), and the measurement is put back
    /// into the world from the stated pose.
    fn recorded(&self, av: Pose, p: [f64; 2]) -> [f64; 2] {
        let true_yaw = av.yaw + self.yaw;
        let (tx, ty) = (av.x + self.dx, av.y + self.dy);
        // In the true sensor frame.
        let (rx, ry) = (p[0] - tx, p[1] - ty);
        let (c, s) = (true_yaw.cos(), true_yaw.sin());
        let (u, v) = (c * rx + s * ry, -s * rx + c * ry);
        // Back to the world from the stated pose.
        let (c0, s0) = (av.yaw.cos(), av.yaw.sin());
        [av.x + c0 * u - s0 * v, av.y + s0 * u + c0 * v]
    }
}

/// The pose the sensor sees of the true state `x` under `effect`.
fn observed_pose(effect: HiddenEffect, x: &State) -> Pose {
    match effect {
        HiddenEffect::Latency { delay } => lagged_pose(x, delay),
        _ => Pose { x: x.x, y: x.y, yaw: x.yaw },
    }
}

/// One step's points of the true state `x`: the generator's, at the observed pose
/// and with the (possibly scaled) extents of `ctx`, then clutter replacement.
fn hidden_points(
    generator: &PointGenerator,
    effect: HiddenEffect,
    ctx: &ObsContext,
    x: &State,
    rng: &mut StdRng,
) -> Vec<[f64; 2]> {
    let mut pts = Vec::new();
    generator.sample(ctx, observed_pose(effect, x), rng, &mut pts);
    if let HiddenEffect::Clutter { fraction, scale } = effect {
        for p in &mut pts {
            if rng.random::<f64>() < fraction {
                let (u, v): (f64, f64) = (rng.sample(StandardNormal), rng.sample(StandardNormal));
                *p = [x.x + scale * u, x.y + scale * v];
            }
        }
    }
    pts
}

/// One step's detection of the true state `x` (if any), at the observed pose, with
/// its yaw reversed with the heading-flip probability.
fn hidden_box(
    generator: &BoxGenerator,
    effect: HiddenEffect,
    ctx: &ObsContext,
    x: &State,
    rng: &mut StdRng,
) -> Option<BoxDetection> {
    let mut d = generator.sample(ctx, observed_pose(effect, x), rng)?;
    if let HiddenEffect::HeadingFlip { fraction } = effect {
        if rng.random::<f64>() < fraction {
            d.yaw = reversed_heading(d.yaw);
        }
    }
    Some(d)
}
