//! Policies (SPEC §3): the [`GaussianPolicy`] trait — a bivariate Gaussian over
//! `(accel, pinch)` given a state's speed and curvature, with mean `mu` and
//! lower-triangular Cholesky factor `L` (positive diagonal) — the batched Gaussians
//! it produces (sampling, reparameterised actions `a = mu + L eps`, log-densities,
//! plain and on the tape), and the [`HandCraftedPolicy`] of the synthetic data.
//!
//! A policy sees only speed and curvature, as both of SPEC's policies do. The
//! neural policy ((v, kappa) -> 32 ReLU -> 32 ReLU -> 5 outputs: two means, `L11`,
//! `L21`, `L22`) implements the same trait: its plain and tape methods fill the
//! same [`ActionGaussians`] / [`ActionGaussianVars`].

use std::fmt;

use autodiff::dist::LN_2PI;
use autodiff::{Float, Tape, Tensor, Var};
use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use super::state::{ActionVars, ActionsMut, ActionsRef};

/// A batch of bivariate Gaussians over actions: one per object, with mean
/// `(mean_accel, mean_pinch)` and covariance `L L^T`,
/// `L = [[l11, 0], [l21, l22]]`, `l11, l22 > 0`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ActionGaussians<F> {
    /// Mean acceleration.
    pub mean_accel: Vec<F>,
    /// Mean pinch.
    pub mean_pinch: Vec<F>,
    /// Cholesky factor, (1, 1) entry: the sd of accel.
    pub l11: Vec<F>,
    /// Cholesky factor, (2, 1) entry: the covariance of accel and pinch over `l11`.
    pub l21: Vec<F>,
    /// Cholesky factor, (2, 2) entry: the conditional sd of pinch given accel.
    pub l22: Vec<F>,
}

impl<F: Float> ActionGaussians<F> {
    /// Number of distributions.
    pub fn len(&self) -> usize {
        self.mean_accel.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.mean_accel.is_empty()
    }

    /// Resizes every component to `n` (no allocation within capacity).
    pub fn resize(&mut self, n: usize) {
        for c in [&mut self.mean_accel, &mut self.mean_pinch, &mut self.l11, &mut self.l21, &mut self.l22] {
            c.resize(n, F::ZERO);
        }
    }

    /// Reparameterised actions `a = mu + L eps` from standard-normal noise.
    #[track_caller]
    pub fn actions_from_noise(&self, eps_accel: &[F], eps_pinch: &[F], out: ActionsMut<'_, F>) {
        let n = self.len();
        assert!(
            eps_accel.len() == n && eps_pinch.len() == n && out.len() == n,
            "ActionGaussians::actions_from_noise: {n} distributions, {} + {} noise values, \
             room for {} actions",
            eps_accel.len(),
            eps_pinch.len(),
            out.len()
        );
        let (e1, e2) = (&eps_accel[..n], &eps_pinch[..n]);
        let (m1, m2) = (&self.mean_accel[..n], &self.mean_pinch[..n]);
        let (l11, l21, l22) = (&self.l11[..n], &self.l21[..n], &self.l22[..n]);
        let (acc, pin) = (&mut out.accel[..n], &mut out.pinch[..n]);
        for i in 0..n {
            acc[i] = m1[i] + l11[i] * e1[i];
            pin[i] = m2[i] + l21[i] * e1[i] + l22[i] * e2[i];
        }
    }

    /// The noise that [`ActionGaussians::actions_from_noise`] maps to `actions`:
    /// `eps = L^{-1} (a - mu)`.
    #[track_caller]
    pub fn standardise(&self, actions: ActionsRef<'_, F>, eps_accel: &mut [F], eps_pinch: &mut [F]) {
        let n = self.len();
        assert!(
            actions.len() == n && eps_accel.len() == n && eps_pinch.len() == n,
            "ActionGaussians::standardise: {n} distributions, {} actions, room for {} + {}",
            actions.len(),
            eps_accel.len(),
            eps_pinch.len()
        );
        for (i, (e1, e2)) in eps_accel.iter_mut().zip(eps_pinch.iter_mut()).enumerate() {
            let z1 = (actions.accel[i] - self.mean_accel[i]) / self.l11[i];
            *e1 = z1;
            *e2 = (actions.pinch[i] - self.mean_pinch[i] - self.l21[i] * z1) / self.l22[i];
        }
    }

    /// Draws one action per distribution (accel noise, then pinch noise, object by
    /// object, from `rng`).
    #[track_caller]
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R, out: ActionsMut<'_, F>) {
        self.sample_with(rng, out, |rng| [rng.sample::<f64, _>(StandardNormal), rng.sample::<f64, _>(StandardNormal)]);
    }

    /// Draws one action per distribution as [`ActionGaussians::sample`] does, with
    /// the standardised innovations `[accel, pinch]` drawn by `noise` instead of
    /// two standard normals (a heavier-tailed law for the acceleration, say, or a
    /// filter's proposal).
    #[track_caller]
    pub fn sample_with<R: Rng + ?Sized>(
        &self,
        rng: &mut R,
        out: ActionsMut<'_, F>,
        mut noise: impl FnMut(&mut R) -> [f64; 2],
    ) {
        let n = self.len();
        assert_eq!(out.len(), n, "ActionGaussians::sample: {n} distributions, room for {}", out.len());
        for i in 0..n {
            let [e1, e2] = noise(rng).map(F::from_f64);
            out.accel[i] = self.mean_accel[i] + self.l11[i] * e1;
            out.pinch[i] = self.mean_pinch[i] + self.l21[i] * e1 + self.l22[i] * e2;
        }
    }

    /// `out[i] = log N(actions[i]; mu_i, L_i L_i^T)`.
    #[track_caller]
    #[allow(clippy::needless_range_loop)] // index loops over resliced arrays vectorise
    pub fn log_density(&self, actions: ActionsRef<'_, F>, out: &mut [F]) {
        let n = self.len();
        assert!(
            actions.len() == n && out.len() == n,
            "ActionGaussians::log_density: {n} distributions, {} actions, room for {}",
            actions.len(),
            out.len()
        );
        let half = F::from_f64(0.5);
        let ln2pi = F::from_f64(LN_2PI);
        // Equal-length reslices let the compiler drop the bounds checks.
        let (a1, a2, out) = (&actions.accel[..n], &actions.pinch[..n], &mut out[..n]);
        let (m1, m2) = (&self.mean_accel[..n], &self.mean_pinch[..n]);
        let (l11, l21, l22) = (&self.l11[..n], &self.l21[..n], &self.l22[..n]);
        for i in 0..n {
            let z1 = (a1[i] - m1[i]) / l11[i];
            let z2 = (a2[i] - m2[i] - l21[i] * z1) / l22[i];
            out[i] = -half * (z1 * z1 + z2 * z2) - l11[i].ln() - l22[i].ln() - ln2pi;
        }
    }
}

/// A batch of action Gaussians on a tape. Means have shape `[n]`; the Cholesky
/// entries have shape `[n]` or one that broadcasts to it (`[1]` for a policy whose
/// covariance does not depend on the state). `l21 = None` means a diagonal `L`.
#[derive(Clone, Copy, Debug)]
pub struct ActionGaussianVars<'t, F: Float> {
    /// Mean acceleration.
    pub mean_accel: Var<'t, F>,
    /// Mean pinch.
    pub mean_pinch: Var<'t, F>,
    /// Cholesky factor, (1, 1) entry (positive).
    pub l11: Var<'t, F>,
    /// Cholesky factor, (2, 1) entry, or `None` for zero.
    pub l21: Option<Var<'t, F>>,
    /// Cholesky factor, (2, 2) entry (positive).
    pub l22: Var<'t, F>,
}

impl<'t, F: Float> ActionGaussianVars<'t, F> {
    /// Log-densities of `actions` (shape `[n]`), differentiable in everything: one
    /// fused node ([`autodiff::Tape::precomputed`]) with the analytic partials,
    ///
    /// ```text
    /// log pi = -(z1^2 + z2^2) / 2 - ln l11 - ln l22 - ln 2 pi,
    /// z1 = (a1 - m1) / l11,  z2 = (a2 - m2 - l21 z1) / l22,
    /// d/da1 = -z1 / l11 + z2 l21 / (l11 l22) = -d/dm1,  d/da2 = -z2 / l22 = -d/dm2,
    /// d/dl11 = (z1^2 - 1) / l11 - z2 l21 z1 / (l11 l22),
    /// d/dl21 = z1 z2 / l22,  d/dl22 = (z2^2 - 1) / l22.
    /// ```
    ///
    /// # Panics
    /// If the actions do not both have shape `[n]` or a distribution's entry has a
    /// shape other than `[n]` or `[1]`.
    #[track_caller]
    pub fn log_density(&self, actions: &ActionVars<'t, F>) -> Var<'t, F> {
        let n = self.check(actions, "ActionGaussianVars::log_density");
        let tape = actions.accel.tape();
        let f = F::from_f64;
        let (half, ln2pi) = (f(-0.5), f(LN_2PI));
        // Every element of these is written below.
        let mut value = tape.buffer(n);
        let mut d: [Vec<F>; 5] = std::array::from_fn(|_| tape.buffer(n));
        {
            let vals =
                [self.mean_accel, self.mean_pinch, self.l11, self.l22, actions.accel, actions.pinch].map(|v| v.value());
            let l21 = self.l21.map(|v| v.value());
            let [m1, m2, l11, l22, a1, a2] = vals.each_ref().map(|v| v.data());
            let [da1, da2, dl11, dl21, dl22] = &mut d;
            for i in 0..n {
                let (l11, l22) = (at(l11, i), at(l22, i));
                let z1 = (a1[i] - at(m1, i)) / l11;
                let r2 = a2[i] - at(m2, i);
                let (r2, l21) = match &l21 {
                    Some(l) => {
                        let l21 = at(l.data(), i);
                        (r2 - l21 * z1, l21)
                    }
                    None => (r2, F::ZERO),
                };
                let z2 = r2 / l22;
                value[i] = (z1 * z1 + z2 * z2) * half - l11.ln() - l22.ln() - ln2pi;
                let q = z2 * l21 / (l11 * l22);
                da1[i] = -z1 / l11 + q;
                da2[i] = -z2 / l22;
                dl11[i] = (z1 * z1 - F::ONE) / l11 - q * z1;
                dl21[i] = z1 * z2 / l22;
                dl22[i] = (z2 * z2 - F::ONE) / l22;
            }
        }
        let [da1, da2, dl11, dl21, dl22] = d;
        let neg = |g: &[F]| {
            let mut b = tape.buffer(n);
            for (b, &g) in b.iter_mut().zip(g) {
                *b = -g;
            }
            Tensor::from_vec(b)
        };
        let mut inputs = vec![(self.mean_accel, neg(&da1)), (self.mean_pinch, neg(&da2))];
        if let Some(l21) = self.l21 {
            inputs.push((l21, Tensor::from_vec(dl21)));
        }
        inputs.extend([
            (actions.accel, Tensor::from_vec(da1)),
            (actions.pinch, Tensor::from_vec(da2)),
            (self.l11, Tensor::from_vec(dl11)),
            (self.l22, Tensor::from_vec(dl22)),
        ]);
        tape.precomputed(Tensor::from_vec(value), inputs)
    }

    /// The reparameterised transition's actions: `mu + L eps` with the noise `eps =
    /// L^{-1} (a - mu)` of `actions` at the current values held constant, so the
    /// values are those of [`ActionGaussianVars::actions_from_noise`] on the
    /// standardised actions, and the gradient flows to the distribution only (`d
    /// accel / d(mu1, l11) = (1, eps1)`, `d pinch / d(mu2, l21, l22) = (1, eps1,
    /// eps2)`). One fused node per component ([`autodiff::Tape::precomputed`]).
    ///
    /// # Panics
    /// If the actions do not both have shape `[n]` or a distribution's entry has a
    /// shape other than `[n]` or `[1]`.
    #[track_caller]
    pub fn reparameterised(&self, actions: &ActionVars<'t, F>) -> ActionVars<'t, F> {
        let n = self.check(actions, "ActionGaussianVars::reparameterised");
        let tape = actions.accel.tape();
        // Every element of these is written below.
        let [mut accel, mut pinch, mut e1s, mut e2s] = std::array::from_fn(|_| tape.buffer(n));
        {
            let vals =
                [self.mean_accel, self.mean_pinch, self.l11, self.l22, actions.accel, actions.pinch].map(|v| v.value());
            let l21 = self.l21.map(|v| v.value());
            let [m1, m2, l11, l22, a1, a2] = vals.each_ref().map(|v| v.data());
            for i in 0..n {
                let (m1, m2, l11, l22) = (at(m1, i), at(m2, i), at(l11, i), at(l22, i));
                // As `standardise`, then `actions_from_noise`.
                let z1 = (a1[i] - m1) / l11;
                let r2 = a2[i] - m2;
                let l21 = l21.as_ref().map(|l| at(l.data(), i));
                let z2 = match l21 {
                    Some(l21) => (r2 - l21 * z1) / l22,
                    None => r2 / l22,
                };
                accel[i] = m1 + l11 * z1;
                let p = m2 + l22 * z2;
                pinch[i] = match l21 {
                    Some(l21) => p + l21 * z1,
                    None => p,
                };
                (e1s[i], e2s[i]) = (z1, z2);
            }
        }
        let ones = || {
            let mut b = tape.buffer(n);
            b.fill(F::ONE);
            Tensor::from_vec(b)
        };
        let e1 = Tensor::from_vec(e1s);
        let mut pinch_inputs = vec![(self.mean_pinch, ones()), (self.l22, Tensor::from_vec(e2s))];
        if let Some(l21) = self.l21 {
            pinch_inputs.push((l21, e1.clone()));
        }
        ActionVars {
            accel: tape.precomputed(Tensor::from_vec(accel), vec![(self.mean_accel, ones()), (self.l11, e1)]),
            pinch: tape.precomputed(Tensor::from_vec(pinch), pinch_inputs),
        }
    }

    /// The number of actions `n`, after checking the shapes of the distribution's
    /// entries (`[n]` or `[1]`) and of the actions (`[n]`).
    #[track_caller]
    fn check(&self, actions: &ActionVars<'t, F>, op: &str) -> usize {
        let n = actions.accel.numel();
        let ps = actions.pinch.shape();
        assert!(ps == [n], "{op}: {n} accelerations, pinches of shape {ps:?}");
        let parts = [
            ("mean_accel", Some(self.mean_accel)),
            ("mean_pinch", Some(self.mean_pinch)),
            ("l11", Some(self.l11)),
            ("l21", self.l21),
            ("l22", Some(self.l22)),
        ];
        for (name, v) in parts {
            if let Some(v) = v {
                let s = v.shape();
                assert!(s == [n] || s == [1], "{op}: {name} has shape {s:?}, expected [{n}] or [1]");
            }
        }
        n
    }

    /// The noise `eps = L^{-1} (a - mu)` that [`ActionGaussianVars::actions_from_noise`]
    /// maps to `actions`: `(eps_accel, eps_pinch)`, differentiable in both.
    pub fn standardise(&self, actions: &ActionVars<'t, F>) -> (Var<'t, F>, Var<'t, F>) {
        let z1 = (actions.accel - self.mean_accel) / self.l11;
        let r2 = actions.pinch - self.mean_pinch;
        let r2 = match self.l21 {
            Some(l21) => r2 - l21 * z1,
            None => r2,
        };
        (z1, r2 / self.l22)
    }

    /// Reparameterised actions `a = mu + L eps` (shape `[n]`), differentiable in the
    /// distribution and in the noise.
    pub fn actions_from_noise(&self, eps_accel: Var<'t, F>, eps_pinch: Var<'t, F>) -> ActionVars<'t, F> {
        let accel = self.mean_accel + self.l11 * eps_accel;
        let pinch = self.mean_pinch + self.l22 * eps_pinch;
        let pinch = match self.l21 {
            Some(l21) => pinch + l21 * eps_accel,
            None => pinch,
        };
        ActionVars { accel, pinch }
    }
}

/// Element `i` of an `[n]` or `[1]` column (a `[1]` entry is shared by all rows).
#[inline(always)]
fn at<F: Copy>(c: &[F], i: usize) -> F {
    if c.len() == 1 {
        c[0]
    } else {
        c[i]
    }
}

/// Why parameters were rejected.
#[derive(Clone, Debug, PartialEq)]
pub enum PolicyError {
    /// The number of parameter tensors is wrong.
    WrongCount {
        /// Tensors the policy has.
        expected: usize,
        /// Tensors given.
        got: usize,
    },
    /// A parameter tensor has the wrong shape.
    WrongShape {
        /// Which tensor.
        index: usize,
        /// Its shape in the policy.
        expected: Vec<usize>,
        /// The shape given.
        got: Vec<usize>,
    },
    /// A parameter value is NaN or infinite.
    NonFinite {
        /// Which tensor.
        index: usize,
    },
}

impl fmt::Display for PolicyError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PolicyError::WrongCount { expected, got } => {
                write!(f, "policy: expected {expected} parameter tensors, got {got}")
            }
            PolicyError::WrongShape { index, expected, got } => {
                write!(f, "policy: parameter {index} must have shape {expected:?}, got {got:?}")
            }
            PolicyError::NonFinite { index } => {
                write!(f, "policy: parameter {index} holds a non-finite value")
            }
        }
    }
}

impl std::error::Error for PolicyError {}

/// Checks that `given` matches the shapes of `current` and is finite.
pub fn check_parameters(current: &[Tensor<f64>], given: &[Tensor<f64>]) -> Result<(), PolicyError> {
    if current.len() != given.len() {
        return Err(PolicyError::WrongCount { expected: current.len(), got: given.len() });
    }
    for (index, (c, g)) in current.iter().zip(given).enumerate() {
        if c.shape() != g.shape() {
            return Err(PolicyError::WrongShape { index, expected: c.shape().to_vec(), got: g.shape().to_vec() });
        }
        if !g.all_finite() {
            return Err(PolicyError::NonFinite { index });
        }
    }
    Ok(())
}

/// A policy whose action given a state is a bivariate Gaussian (SPEC §3).
///
/// The parameters are a list of tensors (an f64 master copy); the tape methods take
/// them as `Var`s in the same order, so a caller decides whether they are tracked
/// (the score), constants (the filter) or perturbed (gradient checks).
pub trait GaussianPolicy: Send + Sync {
    /// The learnable parameter tensors, in the order the tape methods expect.
    fn parameters(&self) -> Vec<Tensor<f64>>;

    /// A name per parameter tensor, under the `policy.` prefix of
    /// [`crate::models::params`].
    fn parameter_names(&self) -> Vec<String>;

    /// Replaces the parameters; the count and shapes must match
    /// [`GaussianPolicy::parameters`] and the values be finite.
    fn set_parameters(&mut self, params: &[Tensor<f64>]) -> Result<(), PolicyError>;

    /// The action distributions of states with speeds `v` and curvatures `kappa`
    /// (resizes `out` to their number).
    fn gaussians<F: Float>(&self, v: &[F], kappa: &[F], out: &mut ActionGaussians<F>);

    /// The same distributions on a tape, as functions of the parameter `Var`s (shapes
    /// as [`GaussianPolicy::parameters`]) and of the states (`v`, `kappa`: `[n]`).
    fn gaussians_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        v: Var<'t, F>,
        kappa: Var<'t, F>,
    ) -> ActionGaussianVars<'t, F>;

    /// Total number of scalar parameters.
    fn num_parameters(&self) -> usize {
        self.parameters().iter().map(|p| p.numel()).sum()
    }

    /// The parameters as tracked leaves of `tape` (converted to `F`).
    fn bind_parameters<'t, F: Float>(&self, tape: &'t Tape<F>) -> Vec<Var<'t, F>> {
        self.parameters().iter().map(|p| tape.param(p.cast())).collect()
    }

    /// Reparameterised actions for states `(v, kappa)` from standard-normal noise;
    /// `scratch` holds the distributions afterwards.
    fn actions_from_noise<F: Float>(
        &self,
        v: &[F],
        kappa: &[F],
        eps_accel: &[F],
        eps_pinch: &[F],
        scratch: &mut ActionGaussians<F>,
        out: ActionsMut<'_, F>,
    ) {
        self.gaussians(v, kappa, scratch);
        scratch.actions_from_noise(eps_accel, eps_pinch, out);
    }

    /// Samples actions for states `(v, kappa)`; `scratch` holds the distributions
    /// afterwards.
    fn sample_actions<F: Float, R: Rng + ?Sized>(
        &self,
        v: &[F],
        kappa: &[F],
        rng: &mut R,
        scratch: &mut ActionGaussians<F>,
        out: ActionsMut<'_, F>,
    ) {
        self.gaussians(v, kappa, scratch);
        scratch.sample(rng, out);
    }

    /// `out[i] = log pi(actions[i] | v[i], kappa[i])`; `scratch` holds the
    /// distributions afterwards.
    fn log_density<F: Float>(
        &self,
        v: &[F],
        kappa: &[F],
        actions: ActionsRef<'_, F>,
        scratch: &mut ActionGaussians<F>,
        out: &mut [F],
    ) {
        self.gaussians(v, kappa, scratch);
        scratch.log_density(actions, out);
    }

    /// `log pi(actions | v, kappa)` on a tape (shape `[n]`), differentiable in the
    /// parameters, the states and the actions.
    fn log_density_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        v: Var<'t, F>,
        kappa: Var<'t, F>,
        actions: &ActionVars<'t, F>,
    ) -> Var<'t, F> {
        self.gaussians_on_tape(params, v, kappa).log_density(actions)
    }
}

/// The hand-crafted policy's one parameter in a store: `[log sd accel, log sd
/// pinch]` (see [`crate::models::params`]).
pub const HAND_CRAFTED_PARAM: &str = "policy.log_sd";

/// The hand-crafted policy of the synthetic data (SPEC §3): independent Gaussian
/// accel and pinch with
///
/// ```text
/// mean accel = 1.5 tanh((8 - v) / 4)        (speeds up when slow, slows when fast)
/// mean pinch = -kappa (0.5 + 0.1 v)         (straightens out, harder at speed)
/// ```
///
/// and two learnable parameters, one tensor of shape `[2]`: the log sds of accel
/// (true `ln 0.5`) and of pinch (true `ln 0.02`).
///
/// ```
/// use ssm::models::vehicle::{ActionGaussians, GaussianPolicy, HandCraftedPolicy};
/// let p = HandCraftedPolicy::truth();
/// let mut g = ActionGaussians::default();
/// p.gaussians(&[8.0f64], &[0.1], &mut g);
/// assert_eq!(g.mean_accel[0], 0.0);
/// assert!((g.mean_pinch[0] + 0.1 * 1.3).abs() < 1e-15);
/// assert!((g.l11[0] - 0.5).abs() < 1e-15 && (g.l22[0] - 0.02).abs() < 1e-15);
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HandCraftedPolicy {
    log_sd_accel: f64,
    log_sd_pinch: f64,
}

impl Default for HandCraftedPolicy {
    fn default() -> Self {
        Self::truth()
    }
}

impl HandCraftedPolicy {
    /// Largest mean acceleration (m/s^2).
    pub const ACCEL_GAIN: f64 = 1.5;
    /// Speed the mean acceleration steers towards (m/s).
    pub const TARGET_SPEED: f64 = 8.0;
    /// Speed difference over which the mean acceleration saturates (m/s).
    pub const SPEED_SCALE: f64 = 4.0;
    /// Straightening rate at standstill (1/s).
    pub const PINCH_BASE: f64 = 0.5;
    /// Increase of the straightening rate per unit speed (1/m).
    pub const PINCH_PER_SPEED: f64 = 0.1;
    /// True sd of accel (m/s^2).
    pub const TRUE_SD_ACCEL: f64 = 0.5;
    /// True sd of pinch (1/(m s)).
    pub const TRUE_SD_PINCH: f64 = 0.02;

    /// The policy with the true sds.
    pub fn truth() -> Self {
        HandCraftedPolicy { log_sd_accel: Self::TRUE_SD_ACCEL.ln(), log_sd_pinch: Self::TRUE_SD_PINCH.ln() }
    }

    /// The policy with the given log sds (finite).
    pub fn new(log_sd_accel: f64, log_sd_pinch: f64) -> Result<Self, PolicyError> {
        let mut p = Self::truth();
        p.set_parameters(&[Tensor::from_vec(vec![log_sd_accel, log_sd_pinch])])?;
        Ok(p)
    }

    /// Log sd of accel.
    pub fn log_sd_accel(&self) -> f64 {
        self.log_sd_accel
    }

    /// Log sd of pinch.
    pub fn log_sd_pinch(&self) -> f64 {
        self.log_sd_pinch
    }

    /// Mean acceleration at speed `v`.
    #[inline]
    pub fn mean_accel<F: Float>(v: F) -> F {
        // (8 - v) / 4 written as 2 - v / 4, as on the tape.
        let u = v * F::from_f64(-1.0 / Self::SPEED_SCALE) + F::from_f64(Self::TARGET_SPEED / Self::SPEED_SCALE);
        u.tanh() * F::from_f64(Self::ACCEL_GAIN)
    }

    /// Mean pinch at speed `v` and curvature `kappa`.
    #[inline]
    pub fn mean_pinch<F: Float>(v: F, kappa: F) -> F {
        kappa * (v * F::from_f64(-Self::PINCH_PER_SPEED) + F::from_f64(-Self::PINCH_BASE))
    }
}

impl GaussianPolicy for HandCraftedPolicy {
    fn parameters(&self) -> Vec<Tensor<f64>> {
        vec![Tensor::from_vec(vec![self.log_sd_accel, self.log_sd_pinch])]
    }

    fn parameter_names(&self) -> Vec<String> {
        vec![HAND_CRAFTED_PARAM.to_string()]
    }

    fn set_parameters(&mut self, params: &[Tensor<f64>]) -> Result<(), PolicyError> {
        check_parameters(&self.parameters(), params)?;
        self.log_sd_accel = params[0].data()[0];
        self.log_sd_pinch = params[0].data()[1];
        Ok(())
    }

    #[track_caller]
    fn gaussians<F: Float>(&self, v: &[F], kappa: &[F], out: &mut ActionGaussians<F>) {
        let n = v.len();
        assert_eq!(kappa.len(), n, "HandCraftedPolicy::gaussians: {n} speeds, {} curvatures", kappa.len());
        out.resize(n);
        let sd_a = F::from_f64(self.log_sd_accel.exp());
        let sd_p = F::from_f64(self.log_sd_pinch.exp());
        let (v, kappa) = (&v[..n], &kappa[..n]);
        for i in 0..n {
            out.mean_accel[i] = Self::mean_accel(v[i]);
            out.mean_pinch[i] = Self::mean_pinch(v[i], kappa[i]);
        }
        out.l11.fill(sd_a);
        out.l21.fill(F::ZERO);
        out.l22.fill(sd_p);
    }

    #[track_caller]
    fn gaussians_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        v: Var<'t, F>,
        kappa: Var<'t, F>,
    ) -> ActionGaussianVars<'t, F> {
        assert!(
            params.len() == 1 && params[0].shape() == [2],
            "HandCraftedPolicy::gaussians_on_tape: expected one parameter of shape [2], got {:?}",
            params.iter().map(|p| p.shape()).collect::<Vec<_>>()
        );
        let log_sd = params[0];
        let mean_accel = v
            .mul_scalar(-1.0 / Self::SPEED_SCALE)
            .add_scalar(Self::TARGET_SPEED / Self::SPEED_SCALE)
            .tanh()
            .mul_scalar(Self::ACCEL_GAIN);
        let mean_pinch = kappa * v.mul_scalar(-Self::PINCH_PER_SPEED).add_scalar(-Self::PINCH_BASE);
        ActionGaussianVars {
            mean_accel,
            mean_pinch,
            l11: log_sd.slice(0, 0, 1).exp(),
            l21: None,
            l22: log_sd.slice(0, 1, 1).exp(),
        }
    }
}
