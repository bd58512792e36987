//! An [`Observer`] that records weighted means of the particles per step: filtering
//! means and fixed-lag smoothed means, with angular components averaged on the
//! circle (the angle of the weighted mean of unit vectors).

use super::{LagView, Observer};

/// Per-step filtering and smoothed means of one object's state.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Moments {
    dim: usize,
    angular: Vec<usize>,
    /// Filtering means `E[x_t | y_{0:t}]`, one row of `dim` values per step.
    pub filtered: Vec<Vec<f64>>,
    /// Fixed-lag smoothed means `E[x_t | y_{0:min(t+L,T)}]`, one row per step.
    pub smoothed: Vec<Vec<f64>>,
}

impl Moments {
    /// Records means of `dim`-dimensional states whose `angular` components are angles.
    pub fn new(dim: usize, angular: &[usize]) -> Self {
        Moments { dim, angular: angular.to_vec(), filtered: Vec::new(), smoothed: Vec::new() }
    }

    fn mean(&self, states: &[f32], weights: &[f64]) -> Vec<f64> {
        let n = weights.len();
        (0..self.dim)
            .map(|k| {
                let xs = &states[k * n..(k + 1) * n];
                if self.angular.contains(&k) {
                    let (mut s, mut c) = (0.0, 0.0);
                    for (&x, &w) in xs.iter().zip(weights) {
                        s += w * (x as f64).sin();
                        c += w * (x as f64).cos();
                    }
                    s.atan2(c)
                } else {
                    xs.iter().zip(weights).map(|(&x, &w)| w * x as f64).sum()
                }
            })
            .collect()
    }
}

impl Observer for Moments {
    fn filtered(&mut self, _t: usize, states: &[f32], weights: &[f64]) {
        let m = self.mean(states, weights);
        self.filtered.push(m);
    }

    fn smoothed(&mut self, view: &LagView<'_>) {
        let m = self.mean(view.states, view.weights);
        self.smoothed.push(m);
    }
}
