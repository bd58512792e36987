//! Optimisation: Adam and global-gradient-norm clipping, with the guard that a
//! non-finite gradient never reaches the parameters.

use serde::{Deserialize, Serialize};

use crate::float::Float;
use crate::nn::{ParamId, ParamStore};
use crate::tensor::Tensor;

/// Global L2 norm of a set of gradients (accumulated in f64).
pub fn global_norm<F: Float>(grads: &[Tensor<F>]) -> f64 {
    grads.iter().map(|g| g.sum_squares()).sum::<f64>().sqrt()
}

/// Scales `grads` so their global norm is at most `max_norm`; returns the norm before
/// clipping. Non-finite norms are returned unchanged (and nothing is scaled).
pub fn clip_global_norm<F: Float>(grads: &mut [Tensor<F>], max_norm: f64) -> f64 {
    let norm = global_norm(grads);
    if norm.is_finite() && norm > max_norm && norm > 0.0 {
        let s = F::from_f64(max_norm / norm);
        for g in grads.iter_mut() {
            g.data_mut().iter_mut().for_each(|x| *x *= s);
        }
    }
    norm
}

/// Adam (Kingma & Ba) with bias correction; its state serialises for checkpoints.
///
/// ```
/// use autodiff::optim::Adam;
/// use autodiff::nn::ParamStore;
/// use autodiff::Tensor;
/// let mut store = ParamStore::<f64>::new();
/// let id = store.add("x", Tensor::from_vec(vec![3.0]));
/// let mut adam = Adam::new(0.1);
/// for _ in 0..500 {
///     let x = store.get(id).item();
///     adam.step(&mut store, &[Tensor::from_vec(vec![2.0 * x])]).unwrap(); // minimise x^2
/// }
/// assert!(store.get(id).item().abs() < 1e-2);
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    /// Learning rate.
    pub lr: f64,
    /// Decay of the first-moment estimate.
    pub beta1: f64,
    /// Decay of the second-moment estimate.
    pub beta2: f64,
    /// Denominator offset.
    pub eps: f64,
    /// Steps taken.
    pub t: u64,
    m: Vec<Vec<f64>>,
    v: Vec<Vec<f64>>,
}

/// Why an optimiser step was refused.
#[derive(Clone, Debug, PartialEq)]
pub enum StepError {
    /// A gradient held NaN or infinity; the parameters were left unchanged.
    NonFinite,
    /// The gradients do not match the parameters in number or size.
    Layout(String),
}

impl std::fmt::Display for StepError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StepError::NonFinite => write!(f, "non-finite gradient: step skipped"),
            StepError::Layout(m) => write!(f, "gradients do not match parameters: {m}"),
        }
    }
}

impl std::error::Error for StepError {}

impl Adam {
    /// Adam with learning rate `lr` and the usual defaults (0.9, 0.999, 1e-8).
    pub fn new(lr: f64) -> Self {
        Adam { lr, beta1: 0.9, beta2: 0.999, eps: 1e-8, t: 0, m: Vec::new(), v: Vec::new() }
    }

    /// Checks that the optimiser's moment estimates fit `params` (one per
    /// parameter tensor, of its size; or none yet, before the first step), as
    /// they must for [`Adam::step`] to continue from them: what a resumed run
    /// checks of the state it read.
    pub fn check_layout<F: Float>(&self, params: &ParamStore<F>) -> Result<(), String> {
        if self.m.len() != self.v.len() {
            return Err(format!("{} first moments but {} second moments", self.m.len(), self.v.len()));
        }
        if self.m.is_empty() {
            return Ok(());
        }
        if self.m.len() != params.len() {
            return Err(format!("moments of {} tensors for {} parameters", self.m.len(), params.len()));
        }
        for (i, ((m, v), p)) in self.m.iter().zip(&self.v).zip(params.values()).enumerate() {
            if m.len() != p.numel() || v.len() != p.numel() {
                return Err(format!(
                    "moments of sizes {} and {} for parameter {} of size {}",
                    m.len(),
                    v.len(),
                    params.name(ParamId(i)),
                    p.numel()
                ));
            }
        }
        Ok(())
    }

    /// One update of `params` with `grads` (same order and shapes). A non-finite
    /// gradient leaves parameters and state untouched and returns
    /// [`StepError::NonFinite`].
    pub fn step<F: Float>(&mut self, params: &mut ParamStore<F>, grads: &[Tensor<F>]) -> Result<(), StepError> {
        self.step_with_rates(params, grads, None)
    }

    /// [`Adam::step`] with parameter tensor `i` moved at `rate_factors[i]` times
    /// the learning rate (`None`: every tensor at the rate). The moment estimates
    /// are the same either way; only the size of each tensor's update changes.
    /// A factor list of the wrong length is a [`StepError::Layout`].
    pub fn step_with_rates<F: Float>(
        &mut self,
        params: &mut ParamStore<F>,
        grads: &[Tensor<F>],
        rate_factors: Option<&[f64]>,
    ) -> Result<(), StepError> {
        if let Some(f) = rate_factors.filter(|f| f.len() != params.len()) {
            return Err(StepError::Layout(format!("{} rate factors for {} parameters", f.len(), params.len())));
        }
        if grads.len() != params.len() {
            return Err(StepError::Layout(format!("{} gradients for {} parameters", grads.len(), params.len())));
        }
        for (g, p) in grads.iter().zip(params.values()) {
            if g.shape() != p.shape() {
                return Err(StepError::Layout(format!("gradient {:?} for parameter {:?}", g.shape(), p.shape())));
            }
        }
        if !grads.iter().all(|g| g.all_finite()) {
            return Err(StepError::NonFinite);
        }
        if self.m.len() != grads.len() {
            self.m = grads.iter().map(|g| vec![0.0; g.numel()]).collect();
            self.v = grads.iter().map(|g| vec![0.0; g.numel()]).collect();
        }
        // A step count read from a file may be anything: it saturates rather
        // than wraps, and past i32::MAX the bias corrections are 1 to the
        // last bit, so the exponent saturates too.
        self.t = self.t.saturating_add(1);
        let t = i32::try_from(self.t).unwrap_or(i32::MAX);
        let c1 = 1.0 - self.beta1.powi(t);
        let c2 = 1.0 - self.beta2.powi(t);
        for (i, (p, g)) in params.values_mut().iter_mut().zip(grads).enumerate() {
            let lr = self.lr * rate_factors.map_or(1.0, |f| f[i]);
            for (j, (x, &gj)) in p.data_mut().iter_mut().zip(g.data()).enumerate() {
                let gj = gj.to_f64();
                let m = &mut self.m[i][j];
                let v = &mut self.v[i][j];
                *m = self.beta1 * *m + (1.0 - self.beta1) * gj;
                *v = self.beta2 * *v + (1.0 - self.beta2) * gj * gj;
                let update = lr * (*m / c1) / ((*v / c2).sqrt() + self.eps);
                *x = F::from_f64(x.to_f64() - update);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clipping_bounds_the_norm_and_keeps_direction() {
        let mut g = vec![Tensor::from_vec(vec![3.0f64, 0.0]), Tensor::from_vec(vec![4.0])];
        let before = clip_global_norm(&mut g, 1.0);
        assert_eq!(before, 5.0);
        assert!((global_norm(&g) - 1.0).abs() < 1e-12);
        assert!((g[0].data()[0] - 0.6).abs() < 1e-12 && (g[1].data()[0] - 0.8).abs() < 1e-12);
        // Below the limit nothing changes.
        let mut h = vec![Tensor::from_vec(vec![0.1f64])];
        clip_global_norm(&mut h, 1.0);
        assert_eq!(h[0].data(), &[0.1]);
    }

    #[test]
    fn non_finite_gradient_is_refused_and_changes_nothing() {
        let mut store = ParamStore::<f64>::new();
        store.add("a", Tensor::from_vec(vec![1.0, 2.0]));
        let mut adam = Adam::new(0.1);
        let before = store.clone();
        let err = adam.step(&mut store, &[Tensor::from_vec(vec![f64::NAN, 1.0])]);
        assert_eq!(err, Err(StepError::NonFinite));
        assert_eq!(store, before);
        assert_eq!(adam.t, 0);
    }

    #[test]
    fn first_adam_step_moves_each_coordinate_by_lr() {
        // With bias correction the first step is lr * sign(g) (up to eps).
        let mut store = ParamStore::<f64>::new();
        store.add("a", Tensor::from_vec(vec![0.0, 0.0]));
        let mut adam = Adam::new(0.01);
        adam.step(&mut store, &[Tensor::from_vec(vec![5.0, -0.001])]).unwrap();
        let d = store.values()[0].data();
        assert!((d[0] + 0.01).abs() < 1e-8 && (d[1] - 0.01).abs() < 1e-6, "{d:?}");
    }

    /// A tensor's rate factor scales its update and nothing else: the same
    /// moments, so factor 1 is a plain step, 0.1 a tenth of it and 0 none.
    #[test]
    fn rate_factors_scale_each_tensors_update() {
        let mut plain = ParamStore::<f64>::new();
        plain.add("base", Tensor::from_vec(vec![1.0, -1.0]));
        plain.add("ext", Tensor::from_vec(vec![0.5]));
        let (mut scaled, mut frozen) = (plain.clone(), plain.clone());
        let grads = [Tensor::from_vec(vec![2.0, -3.0]), Tensor::from_vec(vec![0.7])];
        let (mut a, mut b, mut c) = (Adam::new(0.01), Adam::new(0.01), Adam::new(0.01));
        for _ in 0..3 {
            a.step(&mut plain, &grads).unwrap();
            b.step_with_rates(&mut scaled, &grads, Some(&[0.1, 1.0])).unwrap();
            c.step_with_rates(&mut frozen, &grads, Some(&[0.0, 1.0])).unwrap();
        }
        for j in 0..2 {
            let (start, moved) = ([1.0, -1.0][j], plain.values()[0].data()[j]);
            assert!(((scaled.values()[0].data()[j] - start) - 0.1 * (moved - start)).abs() < 1e-15);
            assert_eq!(frozen.values()[0].data()[j], start);
        }
        assert_eq!(scaled.values()[1].data(), plain.values()[1].data());
        assert_eq!(frozen.values()[1].data(), plain.values()[1].data());
        let err = a.step_with_rates(&mut plain, &grads, Some(&[1.0]));
        assert!(matches!(err, Err(StepError::Layout(m)) if m.contains("1 rate factors for 2 parameters")));
    }
}
