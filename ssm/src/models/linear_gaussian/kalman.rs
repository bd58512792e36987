//! A linear-Gaussian state-space model with the exact Kalman log-likelihood and score:
//! the ground truth every score estimator is tested against (SPEC §2).
//!
//! ```text
//! x_0 ~ N(m0, P0)
//! x_t = phi x_{t-1} + s_v e_t        e_t ~ N(0, 1), t >= 1
//! y_t = x_t + s_w n_t                n_t ~ N(0, 1), t >= 0
//! ```
//!
//! with learnable `theta = (phi, ln s_v, ln s_w)`; the prior `(m0, P0)` is fixed.
//! The Kalman recursion is written once, over tape values ([`Var`]): run on a
//! non-recording tape it gives the plain log-likelihood and the filtering moments;
//! run on a recording tape, one reverse pass gives the exact score. The RTS smoother
//! and the pieces a particle filter needs (prior sampling, propagation, observation
//! and transition log-densities, plain and on the tape) complete the model.
//!
//! ```
//! use rand::SeedableRng;
//! use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmTheta};
//! let model = Lgssm::new(0.0, 1.0, LgssmTheta::new(0.9, 0.5, 0.8)).unwrap();
//! let data = model.simulate(20, &mut rand::rngs::StdRng::seed_from_u64(0));
//! let (ll, score) = model.score(&data.ys);
//! assert!((ll - model.log_likelihood(&data.ys)).abs() < 1e-12);
//! assert!(score.iter().all(|g| g.is_finite()));
//! ```

use std::fmt;

use autodiff::dist::normal_logpdf;
use autodiff::dist::LN_2PI;
use autodiff::{Float, Tape, Tensor, Var};
use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

/// The learnable parameters `theta = (phi, ln s_v, ln s_w)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LgssmTheta {
    /// State transition coefficient.
    pub phi: f64,
    /// Log of the state noise sd `s_v`.
    pub log_sv: f64,
    /// Log of the observation noise sd `s_w`.
    pub log_sw: f64,
}

impl LgssmTheta {
    /// Parameters from `phi` and the noise sds (not their logs).
    pub fn new(phi: f64, sv: f64, sw: f64) -> Self {
        LgssmTheta { phi, log_sv: sv.ln(), log_sw: sw.ln() }
    }

    /// `[phi, ln s_v, ln s_w]`: the order of scores and of [`ThetaVars::from_vector`].
    pub fn to_array(&self) -> [f64; 3] {
        [self.phi, self.log_sv, self.log_sw]
    }

    /// The inverse of [`LgssmTheta::to_array`].
    pub fn from_array(a: [f64; 3]) -> Self {
        LgssmTheta { phi: a[0], log_sv: a[1], log_sw: a[2] }
    }

    /// State noise sd.
    pub fn sv(&self) -> f64 {
        self.log_sv.exp()
    }

    /// Observation noise sd.
    pub fn sw(&self) -> f64 {
        self.log_sw.exp()
    }
}

/// Why a model could not be built.
#[derive(Clone, Debug, PartialEq)]
pub enum LgssmError {
    /// A parameter is NaN or infinite.
    NonFinite(&'static str),
    /// The prior variance must be positive.
    NonPositivePriorVariance(f64),
    /// A stationary prior needs `|phi| < 1`.
    NotStationary(f64),
}

impl fmt::Display for LgssmError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LgssmError::NonFinite(what) => write!(f, "lgssm: {what} is not finite"),
            LgssmError::NonPositivePriorVariance(p) => {
                write!(f, "lgssm: prior variance P0 = {p} must be > 0")
            }
            LgssmError::NotStationary(phi) => {
                write!(f, "lgssm: phi = {phi} has no stationary distribution (need |phi| < 1)")
            }
        }
    }
}

impl std::error::Error for LgssmError {}

/// A simulated sequence: states and observations at `t = 0..len`.
#[derive(Clone, Debug, PartialEq)]
pub struct LgssmSample {
    /// Latent states `x_t`.
    pub xs: Vec<f64>,
    /// Observations `y_t`.
    pub ys: Vec<f64>,
}

/// The Kalman filter's output for `y_{0:T}`.
#[derive(Clone, Debug, PartialEq)]
pub struct KalmanFilter {
    /// `log p(y_{0:T})`.
    pub log_likelihood: f64,
    /// Predictive means `E[x_t | y_{0:t-1}]` (the prior mean at `t = 0`).
    pub pred_mean: Vec<f64>,
    /// Predictive variances `Var[x_t | y_{0:t-1}]`.
    pub pred_var: Vec<f64>,
    /// Filtering means `E[x_t | y_{0:t}]`.
    pub mean: Vec<f64>,
    /// Filtering variances `Var[x_t | y_{0:t}]`.
    pub var: Vec<f64>,
}

/// The RTS smoother's output: `E[x_t | y_{0:T}]` and `Var[x_t | y_{0:T}]`.
#[derive(Clone, Debug, PartialEq)]
pub struct KalmanSmoother {
    /// Smoothing means.
    pub mean: Vec<f64>,
    /// Smoothing variances.
    pub var: Vec<f64>,
}

/// `theta` on a tape: three scalar `Var`s (shape `[]`).
#[derive(Clone, Copy, Debug)]
pub struct ThetaVars<'t, F: Float = f64> {
    /// `phi`.
    pub phi: Var<'t, F>,
    /// `ln s_v`.
    pub log_sv: Var<'t, F>,
    /// `ln s_w`.
    pub log_sw: Var<'t, F>,
}

impl<'t, F: Float> ThetaVars<'t, F> {
    /// Splits a `[3]` vector `[phi, ln s_v, ln s_w]` into scalars (gradients flow
    /// back into the vector).
    #[track_caller]
    pub fn from_vector(theta: Var<'t, F>) -> Self {
        assert_eq!(theta.shape(), [3], "ThetaVars::from_vector: expected shape [3], got {:?}", theta.shape());
        let part = |i| theta.slice(0, i, 1).reshape(&[]);
        ThetaVars { phi: part(0), log_sv: part(1), log_sw: part(2) }
    }

    /// `theta` as a tracked `[3]` leaf of `tape` and its scalar parts.
    pub fn bind(tape: &'t Tape<F>, theta: &LgssmTheta) -> (Var<'t, F>, Self) {
        let v = tape.param(Tensor::from_f64s(&[3], &theta.to_array()));
        (v, Self::from_vector(v))
    }

    /// `theta` as constants on `tape`.
    pub fn constant(tape: &'t Tape<F>, theta: &LgssmTheta) -> Self {
        let c = |x: f64| tape.scalar(x);
        ThetaVars { phi: c(theta.phi), log_sv: c(theta.log_sv), log_sw: c(theta.log_sw) }
    }

    /// `log g(y | x) = log N(y; x, s_w^2)` element-wise over particles `x`.
    pub fn obs_log_density(&self, y: f64, x: Var<'t, F>) -> Var<'t, F> {
        normal_logpdf(x, x.tape().scalar(y), self.log_sw)
    }

    /// `log f(next | prev) = log N(next; phi prev, s_v^2)` element-wise.
    pub fn transition_log_density(&self, prev: Var<'t, F>, next: Var<'t, F>) -> Var<'t, F> {
        normal_logpdf(next, self.phi * prev, self.log_sv)
    }

    /// Reparameterised propagation `phi prev + s_v eps`.
    pub fn propagate(&self, prev: Var<'t, F>, eps: Var<'t, F>) -> Var<'t, F> {
        self.phi * prev + self.log_sv.exp() * eps
    }
}

/// The model: a fixed prior and the learnable `theta`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Lgssm {
    m0: f64,
    p0: f64,
    theta: LgssmTheta,
}

/// One step of the Kalman recursion, as tape values.
struct KalmanStep<'t, F: Float> {
    pred_mean: Var<'t, F>,
    pred_var: Var<'t, F>,
    mean: Var<'t, F>,
    var: Var<'t, F>,
}

impl Lgssm {
    /// A model with prior `N(m0, p0)` and parameters `theta`.
    pub fn new(m0: f64, p0: f64, theta: LgssmTheta) -> Result<Self, LgssmError> {
        for (name, v) in
            [("m0", m0), ("P0", p0), ("phi", theta.phi), ("ln s_v", theta.log_sv), ("ln s_w", theta.log_sw)]
        {
            if !v.is_finite() {
                return Err(LgssmError::NonFinite(name));
            }
        }
        if p0 <= 0.0 {
            return Err(LgssmError::NonPositivePriorVariance(p0));
        }
        Ok(Lgssm { m0, p0, theta })
    }

    /// The model started in its stationary distribution `N(0, s_v^2 / (1 - phi^2))`.
    pub fn stationary(theta: LgssmTheta) -> Result<Self, LgssmError> {
        if theta.phi.is_nan() || theta.phi.abs() >= 1.0 {
            return Err(LgssmError::NotStationary(theta.phi));
        }
        let p0 = theta.sv().powi(2) / (1.0 - theta.phi * theta.phi);
        Self::new(0.0, p0, theta)
    }

    /// The same prior with other parameters.
    pub fn with_theta(&self, theta: LgssmTheta) -> Result<Self, LgssmError> {
        Self::new(self.m0, self.p0, theta)
    }

    /// Prior mean.
    pub fn m0(&self) -> f64 {
        self.m0
    }

    /// Prior variance.
    pub fn p0(&self) -> f64 {
        self.p0
    }

    /// The parameters.
    pub fn theta(&self) -> LgssmTheta {
        self.theta
    }

    /// Simulates states and observations at `t = 0..len` (so `T = len - 1`).
    pub fn simulate<R: Rng + ?Sized>(&self, len: usize, rng: &mut R) -> LgssmSample {
        let (phi, sv, sw) = (self.theta.phi, self.theta.sv(), self.theta.sw());
        let mut xs = Vec::with_capacity(len);
        let mut ys = Vec::with_capacity(len);
        let mut x = self.m0 + self.p0.sqrt() * rng.sample::<f64, _>(StandardNormal);
        for t in 0..len {
            if t > 0 {
                x = phi * x + sv * rng.sample::<f64, _>(StandardNormal);
            }
            xs.push(x);
            ys.push(x + sw * rng.sample::<f64, _>(StandardNormal));
        }
        LgssmSample { xs, ys }
    }

    /// The Kalman recursion over `ys` on `tape`, as a function of `theta`: returns
    /// `log p(y_{0:T})` and hands every step's moments to `on_step`. The only
    /// implementation of the recursion.
    fn kalman<'t, F: Float>(
        &self,
        theta: &ThetaVars<'t, F>,
        ys: &[f64],
        mut on_step: impl FnMut(&KalmanStep<'t, F>),
    ) -> Var<'t, F> {
        let tape = theta.phi.tape();
        let sv2 = theta.log_sv.mul_scalar(2.0).exp();
        let sw2 = theta.log_sw.mul_scalar(2.0).exp();
        let mut m = tape.scalar(self.m0);
        let mut p = tape.scalar(self.p0);
        let mut ll = tape.scalar(0.0);
        for (t, &y) in ys.iter().enumerate() {
            if t > 0 {
                m = theta.phi * m;
                p = theta.phi.square() * p + sv2;
            }
            let s = p + sw2;
            let r = y - m;
            ll = ll + (s.ln() + r.square() / s + LN_2PI).mul_scalar(-0.5);
            let k = p / s;
            let step = KalmanStep { pred_mean: m, pred_var: p, mean: m + k * r, var: p * sw2 / s };
            on_step(&step);
            m = step.mean;
            p = step.var;
        }
        ll
    }

    /// `log p(y_{0:T})` as a function of `theta` on a tape (a scalar): call
    /// `backward` on it for the exact score.
    pub fn log_likelihood_on_tape<'t, F: Float>(&self, theta: &ThetaVars<'t, F>, ys: &[f64]) -> Var<'t, F> {
        self.kalman(theta, ys, |_| {})
    }

    /// The exact `log p(y_{0:T})` (Kalman filter, f64; 0 for no observations).
    pub fn log_likelihood(&self, ys: &[f64]) -> f64 {
        let tape = Tape::<f64>::no_record();
        let theta = ThetaVars::constant(&tape, &self.theta);
        self.log_likelihood_on_tape(&theta, ys).item()
    }

    /// The exact log-likelihood and score `d log p(y_{0:T}) / d theta`, in the order
    /// `[phi, ln s_v, ln s_w]`, by one reverse pass through the Kalman recursion.
    pub fn score(&self, ys: &[f64]) -> (f64, [f64; 3]) {
        let tape = Tape::<f64>::new();
        let (v, theta) = ThetaVars::bind(&tape, &self.theta);
        let ll = self.log_likelihood_on_tape(&theta, ys);
        let g = tape.backward(ll).wrt(v);
        (ll.item(), [g.data()[0], g.data()[1], g.data()[2]])
    }

    /// The Kalman filter: log-likelihood, predictive and filtering moments.
    pub fn filter(&self, ys: &[f64]) -> KalmanFilter {
        let tape = Tape::<f64>::no_record();
        let theta = ThetaVars::constant(&tape, &self.theta);
        let n = ys.len();
        let mut out = KalmanFilter {
            log_likelihood: 0.0,
            pred_mean: Vec::with_capacity(n),
            pred_var: Vec::with_capacity(n),
            mean: Vec::with_capacity(n),
            var: Vec::with_capacity(n),
        };
        let ll = self.kalman(&theta, ys, |s| {
            out.pred_mean.push(s.pred_mean.item());
            out.pred_var.push(s.pred_var.item());
            out.mean.push(s.mean.item());
            out.var.push(s.var.item());
        });
        out.log_likelihood = ll.item();
        out
    }

    /// The Rauch–Tung–Striebel smoother: `E[x_t | y_{0:T}]` and `Var[x_t | y_{0:T}]`.
    pub fn smooth(&self, ys: &[f64]) -> KalmanSmoother {
        let f = self.filter(ys);
        let mut mean = f.mean.clone();
        let mut var = f.var.clone();
        let phi = self.theta.phi;
        for t in (0..ys.len().saturating_sub(1)).rev() {
            let gain = f.var[t] * phi / f.pred_var[t + 1];
            mean[t] = f.mean[t] + gain * (mean[t + 1] - f.pred_mean[t + 1]);
            var[t] = f.var[t] + gain * gain * (var[t + 1] - f.pred_var[t + 1]);
        }
        KalmanSmoother { mean, var }
    }

    /// Draws particles from the prior `N(m0, P0)`.
    pub fn sample_prior<F: Float, R: Rng + ?Sized>(&self, rng: &mut R, out: &mut [F]) {
        let sd = self.p0.sqrt();
        for x in out {
            *x = F::from_f64(self.m0 + sd * rng.sample::<f64, _>(StandardNormal));
        }
    }

    /// Particles of the prior from standard-normal noise: `x = m0 + sqrt(P0) z`.
    #[track_caller]
    pub fn prior_from_noise<F: Float>(&self, noise: &[F], out: &mut [F]) {
        assert_eq!(noise.len(), out.len(), "Lgssm::prior_from_noise: lengths differ");
        let sd = self.p0.sqrt();
        for (x, &z) in out.iter_mut().zip(noise) {
            *x = F::from_f64(self.m0 + sd * z.to_f64());
        }
    }

    /// `out[i] = log N(xs[i]; m0, P0)`.
    #[track_caller]
    pub fn prior_log_density<F: Float>(&self, xs: &[F], out: &mut [F]) {
        assert_eq!(xs.len(), out.len(), "Lgssm::prior_log_density: lengths differ");
        let (m0, p0) = (self.m0, self.p0);
        for (o, &x) in out.iter_mut().zip(xs) {
            let r = x.to_f64() - m0;
            *o = F::from_f64(-0.5 * (LN_2PI + p0.ln() + r * r / p0));
        }
    }

    /// Propagates particles in place: `x <- phi x + s_v eps`, `eps` drawn from `rng`.
    pub fn propagate<F: Float, R: Rng + ?Sized>(&self, rng: &mut R, xs: &mut [F]) {
        let (phi, sv) = (F::from_f64(self.theta.phi), F::from_f64(self.theta.sv()));
        for x in xs {
            *x = phi * *x + sv * F::from_f64(rng.sample::<f64, _>(StandardNormal));
        }
    }

    /// Propagates particles in place with given standard-normal noise.
    #[track_caller]
    pub fn propagate_with_noise<F: Float>(&self, eps: &[F], xs: &mut [F]) {
        assert_eq!(eps.len(), xs.len(), "Lgssm::propagate_with_noise: lengths differ");
        let (phi, sv) = (F::from_f64(self.theta.phi), F::from_f64(self.theta.sv()));
        for (x, &e) in xs.iter_mut().zip(eps) {
            *x = phi * *x + sv * e;
        }
    }

    /// `out[i] = log g(y | xs[i]) = log N(y; xs[i], s_w^2)`.
    #[track_caller]
    pub fn obs_log_density<F: Float>(&self, y: f64, xs: &[F], out: &mut [F]) {
        assert_eq!(xs.len(), out.len(), "Lgssm::obs_log_density: lengths differ");
        let log_sw = self.theta.log_sw;
        let inv = (-log_sw).exp();
        let c = F::from_f64(-0.5 * LN_2PI - log_sw);
        let (y, inv, half) = (F::from_f64(y), F::from_f64(inv), F::from_f64(0.5));
        for (o, &x) in out.iter_mut().zip(xs) {
            let z = (x - y) * inv;
            *o = c - half * z * z;
        }
    }

    /// `out[i] = log f(next[i] | prev[i]) = log N(next[i]; phi prev[i], s_v^2)`.
    #[track_caller]
    pub fn transition_log_density<F: Float>(&self, prev: &[F], next: &[F], out: &mut [F]) {
        assert!(prev.len() == next.len() && next.len() == out.len(), "Lgssm::transition_log_density: lengths differ");
        let log_sv = self.theta.log_sv;
        let c = F::from_f64(-0.5 * LN_2PI - log_sv);
        let (phi, inv, half) = (F::from_f64(self.theta.phi), F::from_f64((-log_sv).exp()), F::from_f64(0.5));
        for ((o, &a), &b) in out.iter_mut().zip(prev).zip(next) {
            let z = (b - phi * a) * inv;
            *o = c - half * z * z;
        }
    }
}
