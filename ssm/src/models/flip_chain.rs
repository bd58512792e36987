//! Heading reversals that persist: the `persistent_flip` extension's per-object
//! two-state Markov chain `b_t` (1: the detector reports the heading reversed
//! by pi at `t`), part of the state.
//!
//! KITTI's reversed detections are not independent (README, "KITTI's reversed
//! headings persist"): a car that is reported backwards once tends to be
//! reported backwards for many frames. Independent flips can only mimic such
//! runs with a track that itself turns around; the chain says it directly.
//!
//! The chain is stationary with reversed fraction `p` and lag-one correlation
//! (persistence) `lambda`:
//!
//! ```text
//! P(b_0 = 1) = p,   P(b_t = 1 | b_{t-1} = 0) = p (1 - lambda),   P(b_t = 1 | b_{t-1} = 1) = 1 - (1 - p)(1 - lambda),
//! ```
//!
//! so `lambda = 0` is the independent flips of `heading_flip` and `lambda -> 1`
//! a flip that, once there, stays for the whole track. A reversed run lasts
//! `1 / ((1 - p)(1 - lambda))` steps on average.
//!
//! Both parameters get their score from the chain's own law (its transition
//! and, since `p` is its initial law, its prior): a detection's density given
//! the state `b_t` does not depend on them.

use autodiff::{Float, Var};

/// Stored logits are multiplied by this: a fraction is `sigmoid(LOGIT_SCALE r)`
/// (the chain's two probabilities here, and every other fraction of the
/// catalogue's extensions, [`crate::models::extended`]).
pub(crate) const LOGIT_SCALE: f64 = 8.0;

/// Probabilities are kept in `[GUARD, 1 - GUARD]` on the plain paths.
const GUARD: f64 = 1e-12;

/// The chain's values in natural units (see the [module docs](self)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlipChain {
    /// Stationary fraction `p` of reversed detections.
    pub fraction: f64,
    /// Lag-one correlation `lambda` of the reversal indicators, in `[0, 1)`.
    pub persistence: f64,
}

impl FlipChain {
    /// `P(b_t = 1 | b_{t-1})`, or `P(b_0 = 1)` for `prev = None`.
    pub fn reversed_probability(&self, prev: Option<bool>) -> f64 {
        let (p, l) = (self.fraction, self.persistence);
        let q = match prev {
            None => p,
            Some(false) => p * (1.0 - l),
            Some(true) => 1.0 - (1.0 - p) * (1.0 - l),
        };
        q.clamp(GUARD, 1.0 - GUARD)
    }

    /// Mean length (steps) of a run of reversed detections.
    pub fn mean_run(&self) -> f64 {
        1.0 / (1.0 - self.reversed_probability(Some(true)))
    }

    /// A path of `steps` indicators from the chain's stationary start.
    pub fn sample_path<R: rand::Rng + ?Sized>(&self, steps: usize, rng: &mut R) -> Vec<bool> {
        let mut path: Vec<bool> = Vec::with_capacity(steps);
        for _ in 0..steps {
            let q = self.reversed_probability(path.last().copied());
            path.push(rng.random::<f64>() < q);
        }
        path
    }
}

/// Whether a stored indicator (0.0 or 1.0 in an f32 state column) is set.
#[inline]
pub fn is_reversed(b: f32) -> bool {
    b > 0.5
}

/// The chain's terms on a tape, from its stored parameter tensor `[r_p, r_lambda]`
/// with `p = sigmoid(LOGIT_SCALE r_p)` and `lambda = sigmoid(LOGIT_SCALE r_lambda)`.
pub(crate) struct FlipChainVars<'t, F: Float> {
    /// `ln P(b_0 = 1)` and `ln P(b_0 = 0)`.
    ln_p: Var<'t, F>,
    ln_not_p: Var<'t, F>,
    /// `ln P(b_t = j | b_{t-1} = i)` as `ln_ij`.
    ln_01: Var<'t, F>,
    ln_00: Var<'t, F>,
    ln_11: Var<'t, F>,
    ln_10: Var<'t, F>,
}

impl<'t, F: Float> FlipChainVars<'t, F> {
    pub(crate) fn new(theta: Var<'t, F>) -> Self {
        let lp = theta.slice(0, 0, 1).mul_scalar(LOGIT_SCALE);
        let ll = theta.slice(0, 1, 1).mul_scalar(LOGIT_SCALE);
        // ln p = -softplus(-lp), ln(1 - p) = -softplus(lp); the same for lambda.
        let (ln_p, ln_not_p) = (lp.neg().softplus().neg(), lp.softplus().neg());
        let ln_not_l = ll.softplus().neg();
        // 0 -> 1: p (1 - lambda); 1 -> 0: (1 - p)(1 - lambda).
        let ln_01 = ln_p + ln_not_l;
        let ln_10 = ln_not_p + ln_not_l;
        let one_minus = |ln_q: Var<'t, F>| ln_q.exp().neg().add_scalar(1.0).ln();
        FlipChainVars { ln_p, ln_not_p, ln_01, ln_00: one_minus(ln_01), ln_11: one_minus(ln_10), ln_10 }
    }

    /// `ln P(b_0)` per row of the indicator column `b` (constants 0 or 1).
    pub(crate) fn prior_log_density(&self, b: Var<'t, F>) -> Var<'t, F> {
        b * self.ln_p + b.neg().add_scalar(1.0) * self.ln_not_p
    }

    /// `ln P(b_t | b_{t-1})` per row of the indicator columns `prev` and `next`.
    pub(crate) fn transition_log_density(&self, prev: Var<'t, F>, next: Var<'t, F>) -> Var<'t, F> {
        let (not_prev, not_next) = (prev.neg().add_scalar(1.0), next.neg().add_scalar(1.0));
        let from_reversed = next * self.ln_11 + not_next * self.ln_10;
        let from_kept = next * self.ln_01 + not_next * self.ln_00;
        prev * from_reversed + not_prev * from_kept
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use autodiff::{Tape, Tensor};
    use rand::rngs::SmallRng;
    use rand::SeedableRng;

    fn chain() -> FlipChain {
        FlipChain { fraction: 0.15, persistence: 0.7 }
    }

    #[test]
    fn the_chain_keeps_its_stationary_fraction_and_persistence() {
        let c = chain();
        // Stationarity: p = (1 - p) q01 + p q11.
        let (q01, q11) = (c.reversed_probability(Some(false)), c.reversed_probability(Some(true)));
        assert!(((1.0 - c.fraction) * q01 + c.fraction * q11 - c.fraction).abs() < 1e-12);
        // Lag-one correlation of a two-state chain: q11 - q01.
        assert!((q11 - q01 - c.persistence).abs() < 1e-12);
        let mut rng = SmallRng::seed_from_u64(3);
        let path = c.sample_path(200_000, &mut rng);
        let rate = path.iter().filter(|&&b| b).count() as f64 / path.len() as f64;
        let both = path.windows(2).filter(|w| w[0] && w[1]).count() as f64 / (path.len() - 1) as f64;
        let corr = (both - rate * rate) / (rate * (1.0 - rate));
        assert!((rate - 0.15).abs() < 0.01, "rate {rate}");
        assert!((corr - 0.7).abs() < 0.02, "lag-one correlation {corr}");
        assert!((c.mean_run() - 1.0 / (0.85 * 0.3)).abs() < 1e-9);
    }

    /// The tape's log-probabilities equal the plain ones, and their gradients
    /// match central finite differences in f64.
    #[test]
    fn tape_log_probabilities_and_their_gradients_are_right() {
        let raw = [(0.15f64 / 0.85).ln() / LOGIT_SCALE, (0.7f64 / 0.3).ln() / LOGIT_SCALE];
        let prev = [0.0, 0.0, 1.0, 1.0];
        let next = [0.0, 1.0, 0.0, 1.0];
        let value = |raw: &[f64]| -> (f64, Vec<f64>) {
            let tape = Tape::<f64>::new();
            let theta = tape.param(Tensor::from_vec(raw.to_vec()));
            let vars = FlipChainVars::new(theta);
            let p = tape.constant(Tensor::from_vec(prev.to_vec()));
            let n = tape.constant(Tensor::from_vec(next.to_vec()));
            let total = (vars.transition_log_density(p, n).sum() + vars.prior_log_density(n).sum()).sum();
            let v = total.value().data()[0];
            let g = tape.backward(total).wrt(theta).data().to_vec();
            (v, g)
        };
        let (v, g) = value(&raw);
        let c = chain();
        let mut plain = 0.0;
        for (&a, &b) in prev.iter().zip(&next) {
            let q = c.reversed_probability(Some(a > 0.5));
            plain += if b > 0.5 { q.ln() } else { (1.0 - q).ln() };
            let q0 = c.reversed_probability(None);
            plain += if b > 0.5 { q0.ln() } else { (1.0 - q0).ln() };
        }
        assert!((v - plain).abs() < 1e-10, "tape {v} against plain {plain}");
        for k in 0..2 {
            let h = 1e-6;
            let (mut up, mut down) = (raw, raw);
            up[k] += h;
            down[k] -= h;
            let fd = (value(&up).0 - value(&down).0) / (2.0 * h);
            assert!((fd - g[k]).abs() < 1e-6 * (1.0 + fd.abs()), "param {k}: tape {} against fd {fd}", g[k]);
        }
    }
}
