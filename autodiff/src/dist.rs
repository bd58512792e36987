//! Log-densities of common distributions as differentiable expressions on the tape
//! (broadcasting over batches), shared by every model that scores observations or
//! actions.

use crate::float::Float;
use crate::tape::Var;

/// ln(2 pi).
pub const LN_2PI: f64 = 1.837_877_066_409_345_5;
/// ln(2 pi) / 2.
pub const HALF_LN_2PI: f64 = 0.918_938_533_204_672_8;

/// log N(x; mu, exp(log_sd)^2), element-wise with broadcasting.
pub fn normal_logpdf<'t, F: Float>(x: Var<'t, F>, mu: Var<'t, F>, log_sd: Var<'t, F>) -> Var<'t, F> {
    let z = (x - mu) / log_sd.exp();
    z.square().mul_scalar(-0.5) - log_sd - HALF_LN_2PI
}

/// log Laplace(x; mu, exp(log_b)) = -|x - mu| / b - ln(2 b), element-wise with broadcasting.
pub fn laplace_logpdf<'t, F: Float>(x: Var<'t, F>, mu: Var<'t, F>, log_b: Var<'t, F>) -> Var<'t, F> {
    (x - mu).abs() / log_b.exp().neg() - log_b - std::f64::consts::LN_2
}

/// log sum_k softmax(logits)_k p_k given component log-densities `log_p` (same shape
/// as `logits`, components along `axis`): a mixture's log-density, stable in log space.
pub fn mixture_logpdf<'t, F: Float>(logits: Var<'t, F>, log_p: Var<'t, F>, axis: usize) -> Var<'t, F> {
    (logits.log_softmax(axis) + log_p).logsumexp(axis, false)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Tape, Tensor};

    #[test]
    fn densities_match_closed_forms() {
        let tape = Tape::<f64>::new();
        let c = |v: f64| tape.scalar(v);
        let n = normal_logpdf(c(1.3), c(0.5), c(0.2f64.ln())).item();
        let exact = -0.5 * ((1.3f64 - 0.5) / 0.2).powi(2) - 0.2f64.ln() - 0.5 * (2.0 * std::f64::consts::PI).ln();
        assert!((n - exact).abs() < 1e-12);
        let l = laplace_logpdf(c(-0.4), c(0.1), c(0.3f64.ln())).item();
        assert!((l - (-(0.5f64 / 0.3) - (0.6f64).ln())).abs() < 1e-12);
        // A mixture of one component is that component.
        let lp = tape.constant(Tensor::new(&[1, 1], vec![-2.5]));
        let lg = tape.constant(Tensor::new(&[1, 1], vec![3.0]));
        assert!((mixture_logpdf(lg, lp, 1).item() + 2.5).abs() < 1e-12);
    }
}
