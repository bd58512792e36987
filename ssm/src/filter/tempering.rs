//! Tempering within a step (resample-move SMC from the prediction to the
//! posterior) for observations much sharper than the particles' spread.
//!
//! A bootstrap filter weights the predicted particles by `g(y_t | x_t)` in one go.
//! When the observation pins the state far more tightly than the prediction does
//! — at `t = 0`, where a broad prior meets ten points with centimetre scales, or
//! after a manoeuvre in the policy's tail — almost every weight vanishes and the
//! effective sample size falls to about one. The tempered step instead moves
//! through the targets `p(x_t | x_{t-1}) g(y_t | x_t)^beta`, `0 = beta_0 < beta_1
//! < ... < beta_K = 1`:
//!
//! 1. each increment `beta_{k+1} - beta_k` is the largest that keeps the
//!    conditional effective sample size (Zhou, Johansen and Aston 2016) of the
//!    incremental weights `g^(beta_{k+1} - beta_k)` at [`Tempering::ess_fraction`]
//!    of `N`; if the whole remaining exponent already does, the step ends there
//!    (a step the bootstrap filter handles well costs what it costs there);
//! 2. the log-likelihood increment is the sum over stages of
//!    `ln sum_i W^i g(y_t | x_t^i)^(beta_{k+1} - beta_k)`, an unbiased estimate of
//!    `p(y_t | y_{0:t-1})` in the likelihood itself;
//! 3. between stages the particles are resampled and moved by
//!    [`Tempering::moves`] random-walk Metropolis sweeps that leave the
//!    intermediate target invariant. The moves act on the standard-normal noise
//!    that drives the model's draws ([`ParticleModel::noise_dims`]): the prior
//!    (`t = 0`) or the transition from the particle's parent, whichever the step
//!    draws, is `N(0, I)` there for every model, so the acceptance ratio is
//!    `beta (ln g' - ln g) - (|z'|^2 - |z|^2) / 2` and the proposal's scales come
//!    from the particle cloud itself (each noise component's sd times a factor
//!    tuned by the acceptance rate).
//!
//! A move changes `x_t` and the action that reached it, never the parent, so the
//! genealogy stays a genealogy: the filter composes the within-step resampling
//! into each particle's parent index, and fixed-lag smoothing and PF-SEFI read the
//! particles, parents and actions as they would from the bootstrap filter. The
//! through-filter baselines replay the bootstrap filter and cannot use this one.

use rand::rngs::SmallRng;
use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use super::resample::Resampling;
use crate::model::{NoiseDims, ParticleModel};

/// Settings of the tempered filter (see the module documentation).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tempering {
    /// Each stage's increment keeps the conditional ESS of its incremental weights
    /// at this fraction of `N` (in `(0, 1)`).
    pub ess_fraction: f64,
    /// Metropolis sweeps over every particle after each intermediate resampling.
    pub moves: usize,
    /// Most stages per step; the last takes whatever exponent is left.
    pub max_stages: usize,
}

impl Default for Tempering {
    /// Half the particles' worth of ESS per stage (the usual choice in adaptive
    /// SMC samplers), two sweeps of moves, at most 64 stages.
    fn default() -> Self {
        Tempering { ess_fraction: 0.5, moves: 2, max_stages: 64 }
    }
}

impl Tempering {
    /// Checks the settings; the message names the bad one.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.ess_fraction > 0.0 && self.ess_fraction < 1.0) {
            return Err(format!("tempering: ess_fraction must be in (0, 1), got {}", self.ess_fraction));
        }
        if self.max_stages == 0 {
            return Err("tempering: max_stages must be at least 1".into());
        }
        Ok(())
    }
}

/// Bisection steps for an increment: the bracket shrinks to `2^-40` of the
/// remaining exponent, far below what changes an ESS.
const BISECTION_STEPS: usize = 40;
/// The random-walk factor starts at the classic `2.38 / sqrt(dim)` (Roberts,
/// Gelman and Gilks 1997) and is tuned towards an acceptance rate in this band.
const ACCEPT_LOW: f64 = 0.15;
/// Upper end of the acceptance band.
const ACCEPT_HIGH: f64 = 0.45;
/// Factor by which the random walk shrinks (or, inverted, grows) when the
/// acceptance rate leaves the band.
const STEP_ADAPT: f64 = 0.6;
/// Smallest proposal scale per noise component (noise is standard normal, so this
/// is a thousandth of the prior's or transition's own spread): a cloud that has
/// collapsed onto one value in a component still moves.
const MIN_NOISE_SCALE: f64 = 1e-3;

/// The particles of one step that a tempered weighting resamples and moves.
pub(super) struct StepParticles<'a> {
    /// `x_t`, dimension-major.
    pub states: &'a mut Vec<f32>,
    /// The actions that reached `x_t` (empty at `t = 0`).
    pub actions: &'a mut Vec<f32>,
    /// Each particle's parent at `t - 1` (empty at `t = 0`).
    pub parents: &'a mut Vec<usize>,
    /// Each particle's parent state `x_{t-1}`, dimension-major (empty at `t = 0`).
    pub parent_states: &'a mut Vec<f32>,
}

/// What one tempered weighting did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct Weighing {
    /// Whether there was an observation at the step.
    pub observed: bool,
    /// `ln p_hat(y_t | y_{0:t-1})`, or `None` when every particle was impossible.
    pub increment: Option<f64>,
    /// Intermediate stages (0 when the whole observation was taken in one go).
    pub stages: usize,
    /// Metropolis proposals made and accepted.
    pub proposed: usize,
    /// Accepted proposals.
    pub accepted: usize,
    /// Observation log-likelihood evaluations of all `N` particles.
    pub evaluations: usize,
}

/// Working memory of the tempered filter for one object at a time.
pub(super) struct Temperer {
    config: Tempering,
    dims: NoiseDims,
    /// The noise of the current particles (dimension-major).
    noise: Vec<f32>,
    proposal_noise: Vec<f32>,
    proposal_states: Vec<f32>,
    proposal_actions: Vec<f32>,
    /// `ln g(y_t | x_t^i)` of the current particles (NaN read as `-inf`).
    loglik: Vec<f64>,
    proposal_loglik: Vec<f32>,
    weights: Vec<f64>,
    ancestors: Vec<usize>,
    resample_scratch: Vec<f64>,
    gather_f32: Vec<f32>,
    gather_f64: Vec<f64>,
    gather_usize: Vec<usize>,
}

impl Temperer {
    /// Working memory for `model`, which must have a noise-driven form.
    #[track_caller]
    pub(super) fn new<M: ParticleModel>(model: &M, config: Tempering) -> Self {
        let dims = model.noise_dims().unwrap_or_else(|| {
            panic!("tempered filter: the model has no noise-driven form (ParticleModel::noise_dims is None)")
        });
        Temperer {
            config,
            dims,
            noise: Vec::new(),
            proposal_noise: Vec::new(),
            proposal_states: Vec::new(),
            proposal_actions: Vec::new(),
            loglik: Vec::new(),
            proposal_loglik: Vec::new(),
            weights: Vec::new(),
            ancestors: Vec::new(),
            resample_scratch: Vec::new(),
            gather_f32: Vec::new(),
            gather_f64: Vec::new(),
            gather_usize: Vec::new(),
        }
    }

    fn noise_dim(&self, t: usize) -> usize {
        if t == 0 {
            self.dims.prior
        } else {
            self.dims.transition
        }
    }

    /// Draws `x_t` for `n` particles through the model's noise (the prior at
    /// `t = 0`, else the transition from `parent_states`) and keeps the noise.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn draw<M: ParticleModel>(
        &mut self,
        model: &M,
        object: usize,
        t: usize,
        n: usize,
        parent_states: &[f32],
        states: &mut [f32],
        actions: &mut [f32],
        rng: &mut SmallRng,
        scratch: &mut M::Scratch,
    ) {
        let dim = self.noise_dim(t);
        self.noise.clear();
        self.noise.extend((0..dim * n).map(|_| rng.sample::<f32, _>(StandardNormal)));
        map_noise(model, object, t, n, parent_states, &self.noise, states, actions, scratch);
    }

    /// Weights the particles of step `t` by `y_t` (if there is one) through
    /// tempered stages, moving them between stages. `log_w` holds the normalised
    /// log-weights before `y_t` and receives them after. Returns what it did; on
    /// `increment: None` (no observation, or every particle impossible) `log_w` is
    /// unchanged.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn weigh<M: ParticleModel>(
        &mut self,
        model: &M,
        object: usize,
        t: usize,
        n: usize,
        particles: StepParticles<'_>,
        log_w: &mut [f64],
        resampling: Resampling,
        rng: &mut SmallRng,
        scratch: &mut M::Scratch,
    ) -> Weighing {
        let mut out = Weighing { evaluations: 1, ..Weighing::default() };
        self.proposal_loglik.resize(n, 0.0);
        out.observed = model.observation_loglik(object, t, n, particles.states, &mut self.proposal_loglik, scratch);
        if !out.observed {
            return out;
        }
        self.loglik.clear();
        self.loglik.extend(self.proposal_loglik.iter().map(|&l| if l.is_nan() { f64::NEG_INFINITY } else { l as f64 }));
        let StepParticles { states, actions, parents, parent_states } = particles;

        let mut beta = 0.0;
        let mut total = 0.0;
        let mut step = 2.38 / (self.noise_dim(t).max(1) as f64).sqrt();
        loop {
            let remaining = 1.0 - beta;
            let last = out.stages + 1 >= self.config.max_stages;
            let delta = if last { remaining } else { self.increment(log_w, remaining, n) };
            let Some(inc) = reweight(log_w, &self.loglik, delta) else {
                debug_assert_eq!(out.stages, 0, "particles that survived a stage cannot all become impossible");
                return out;
            };
            total += inc;
            if delta >= remaining {
                break;
            }
            beta += delta;
            out.stages += 1;

            // Resample within the step; the genealogy composes.
            self.weights.clear();
            self.weights.extend(log_w.iter().map(|&lw| lw.exp()));
            self.ancestors.resize(n, 0);
            resampling.draw(&self.weights, rng, &mut self.ancestors, &mut self.resample_scratch);
            let idx = &self.ancestors;
            gather(states, &mut self.gather_f32, idx, n);
            gather(&mut self.noise, &mut self.gather_f32, idx, n);
            gather(&mut self.loglik, &mut self.gather_f64, idx, n);
            if t > 0 {
                gather(actions, &mut self.gather_f32, idx, n);
                gather(parent_states, &mut self.gather_f32, idx, n);
                gather(parents, &mut self.gather_usize, idx, n);
            }
            log_w.fill(-(n as f64).ln());

            for _ in 0..self.config.moves {
                let accepted =
                    self.sweep(model, object, t, n, beta, step, states, actions, parent_states, rng, scratch);
                out.evaluations += 1;
                out.proposed += n;
                out.accepted += accepted;
                let rate = accepted as f64 / n as f64;
                if rate < ACCEPT_LOW {
                    step *= STEP_ADAPT;
                } else if rate > ACCEPT_HIGH {
                    step /= STEP_ADAPT;
                }
            }
        }
        out.increment = Some(total);
        out
    }

    /// The largest increment in `(0, remaining]` whose incremental weights keep
    /// the conditional ESS at the target (the whole `remaining` if it does).
    fn increment(&self, log_w: &[f64], remaining: f64, n: usize) -> f64 {
        let target = self.config.ess_fraction * n as f64;
        let cess = |delta: f64| conditional_ess(log_w, &self.loglik, delta);
        if cess(remaining) >= target {
            return remaining;
        }
        let (mut lo, mut hi) = (0.0, remaining);
        for _ in 0..BISECTION_STEPS {
            let mid = 0.5 * (lo + hi);
            if cess(mid) >= target {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        // When impossible particles hold more than the target's share of the
        // weight no increment reaches it: the smallest bracket still kills them.
        if lo > 0.0 {
            lo
        } else {
            hi
        }
    }

    /// One random-walk Metropolis sweep over every particle at exponent `beta`;
    /// returns the number of accepted moves.
    #[allow(clippy::too_many_arguments)]
    fn sweep<M: ParticleModel>(
        &mut self,
        model: &M,
        object: usize,
        t: usize,
        n: usize,
        beta: f64,
        step: f64,
        states: &mut [f32],
        actions: &mut [f32],
        parent_states: &[f32],
        rng: &mut SmallRng,
        scratch: &mut M::Scratch,
    ) -> usize {
        let dim = self.noise_dim(t);
        self.proposal_noise.resize(dim * n, 0.0);
        for k in 0..dim {
            let z = &self.noise[k * n..(k + 1) * n];
            let scale = (step * spread(z).max(MIN_NOISE_SCALE)) as f32;
            for (p, &z) in self.proposal_noise[k * n..(k + 1) * n].iter_mut().zip(z) {
                *p = z + scale * rng.sample::<f32, _>(StandardNormal);
            }
        }
        self.proposal_states.resize(states.len(), 0.0);
        self.proposal_actions.resize(actions.len(), 0.0);
        map_noise(
            model,
            object,
            t,
            n,
            parent_states,
            &self.proposal_noise,
            &mut self.proposal_states,
            &mut self.proposal_actions,
            scratch,
        );
        model.observation_loglik(object, t, n, &self.proposal_states, &mut self.proposal_loglik, scratch);
        let (d, a) = (states.len() / n, actions.len() / n);
        let mut accepted = 0;
        for i in 0..n {
            let l_new = self.proposal_loglik[i];
            if l_new.is_nan() || l_new == f32::NEG_INFINITY {
                continue;
            }
            let l_new = l_new as f64;
            let mut log_ratio = beta * (l_new - self.loglik[i]);
            for k in 0..dim {
                let (z, z_new) = (self.noise[k * n + i] as f64, self.proposal_noise[k * n + i] as f64);
                log_ratio -= 0.5 * (z_new * z_new - z * z);
            }
            if log_ratio >= 0.0 || rng.random::<f64>().ln() < log_ratio {
                accepted += 1;
                self.loglik[i] = l_new;
                for k in 0..dim {
                    self.noise[k * n + i] = self.proposal_noise[k * n + i];
                }
                for k in 0..d {
                    states[k * n + i] = self.proposal_states[k * n + i];
                }
                for k in 0..a {
                    actions[k * n + i] = self.proposal_actions[k * n + i];
                }
            }
        }
        accepted
    }
}

/// The model's noise-driven draw: the prior at `t = 0`, else the transition.
#[allow(clippy::too_many_arguments)]
fn map_noise<M: ParticleModel>(
    model: &M,
    object: usize,
    t: usize,
    n: usize,
    parent_states: &[f32],
    noise: &[f32],
    states: &mut [f32],
    actions: &mut [f32],
    scratch: &mut M::Scratch,
) {
    if t == 0 {
        model.prior_from_noise(object, n, noise, states);
    } else {
        model.propagate_from_noise(object, t, n, parent_states, noise, states, actions, scratch);
    }
}

/// `log_w += delta * loglik`, normalised; returns `ln sum_i W^i g_i^delta`, or
/// `None` (and `log_w` unchanged) when every particle is impossible.
pub(super) fn reweight(log_w: &mut [f64], loglik: &[f64], delta: f64) -> Option<f64> {
    let scaled = |lw: f64, l: f64| if l == f64::NEG_INFINITY { f64::NEG_INFINITY } else { lw + delta * l };
    let max = log_w.iter().zip(loglik).map(|(&lw, &l)| scaled(lw, l)).fold(f64::NEG_INFINITY, f64::max);
    if max == f64::NEG_INFINITY || max.is_nan() {
        return None;
    }
    let total: f64 = log_w.iter().zip(loglik).map(|(&lw, &l)| (scaled(lw, l) - max).exp()).sum();
    let lse = max + total.ln();
    for (lw, &l) in log_w.iter_mut().zip(loglik) {
        *lw = scaled(*lw, l) - lse;
    }
    Some(lse)
}

/// The conditional ESS `N (sum W w)^2 / sum W w^2` of incremental weights
/// `w = g^delta` under normalised log-weights `log_w` (Zhou, Johansen and Aston
/// 2016); `N` for uniform increments, the ESS of the new weights when `W` is uniform.
fn conditional_ess(log_w: &[f64], loglik: &[f64], delta: f64) -> f64 {
    let max = loglik
        .iter()
        .zip(log_w)
        .filter(|(_, &lw)| lw > f64::NEG_INFINITY)
        .map(|(&l, _)| delta * l)
        .fold(f64::NEG_INFINITY, f64::max);
    if max == f64::NEG_INFINITY || max.is_nan() {
        return 0.0;
    }
    let (mut first, mut second) = (0.0, 0.0);
    for (&lw, &l) in log_w.iter().zip(loglik) {
        if l == f64::NEG_INFINITY || lw == f64::NEG_INFINITY {
            continue;
        }
        let w = (delta * l - max).exp();
        let big_w = lw.exp();
        first += big_w * w;
        second += big_w * w * w;
    }
    log_w.len() as f64 * first * first / second
}

/// The sd of standard-normal-scale values (one pass; no allocation).
fn spread(z: &[f32]) -> f64 {
    let n = z.len() as f64;
    let (sum, sum_sq) = z.iter().fold((0.0, 0.0), |(s, q), &v| (s + v as f64, q + (v as f64) * (v as f64)));
    let mean = sum / n;
    ((sum_sq - n * mean * mean) / (n - 1.0).max(1.0)).max(0.0).sqrt()
}

/// Reorders the dimension-major `values` (components of `n` particles) by `idx`
/// through `buffer`.
fn gather<T: Copy>(values: &mut Vec<T>, buffer: &mut Vec<T>, idx: &[usize], n: usize) {
    buffer.clear();
    for column in values.chunks_exact(n) {
        buffer.extend(idx.iter().map(|&i| column[i]));
    }
    std::mem::swap(values, buffer);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reweight_matches_a_direct_log_sum_exp_and_keeps_impossible_particles_out() {
        let mut log_w = vec![(0.5f64).ln(), (0.25f64).ln(), (0.25f64).ln()];
        let loglik = [-1.0, f64::NEG_INFINITY, 2.0];
        let inc = reweight(&mut log_w, &loglik, 0.5).unwrap();
        let direct = (0.5 * (-0.5f64).exp() + 0.25 * 1.0f64.exp()).ln();
        assert!((inc - direct).abs() < 1e-14);
        assert_eq!(log_w[1], f64::NEG_INFINITY);
        let sum: f64 = log_w.iter().map(|l| l.exp()).sum();
        assert!((sum - 1.0).abs() < 1e-14);
        let mut none = vec![0.0; 2];
        assert_eq!(reweight(&mut none, &[f64::NEG_INFINITY, f64::NAN], 1.0), None);
    }

    #[test]
    fn conditional_ess_is_the_ess_under_uniform_weights() {
        let n = 4;
        let log_w = vec![-(n as f64).ln(); n];
        let loglik = [0.0, 1.0, 2.0, 3.0];
        let w: Vec<f64> = loglik.iter().map(|&l: &f64| (0.7 * l).exp()).collect();
        let s: f64 = w.iter().sum();
        let ess = 1.0 / w.iter().map(|x| (x / s).powi(2)).sum::<f64>();
        assert!((conditional_ess(&log_w, &loglik, 0.7) - ess).abs() < 1e-12);
        assert!((conditional_ess(&log_w, &loglik, 0.0) - n as f64).abs() < 1e-12);
    }

    #[test]
    fn gather_reorders_every_component() {
        let mut v = vec![0, 1, 2, 10, 11, 12];
        gather(&mut v, &mut Vec::new(), &[2, 2, 0], 3);
        assert_eq!(v, vec![2, 2, 0, 12, 12, 10]);
    }
}
