//! Resampling: ancestor indices from normalised weights, multinomial (the paper's)
//! and systematic, both O(N) by merging sorted uniforms with the weights' running
//! sum. Indices never pass `N - 1`, even when rounding leaves the weights summing
//! to slightly under one.

use rand::Rng;
use rand_distr::Exp1;
use serde::{Deserialize, Serialize};

/// How ancestors are drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Resampling {
    /// Independent draws from the weights (the paper's choice).
    Multinomial,
    /// One uniform offset, `N` evenly spaced points: lower variance (default).
    Systematic,
}

impl Resampling {
    /// Writes `out.len()` ancestor indices drawn from `weights` (normalised to sum 1).
    /// `scratch` is working memory reused across calls.
    pub fn draw<R: Rng + ?Sized>(self, weights: &[f64], rng: &mut R, out: &mut [usize], scratch: &mut Vec<f64>) {
        match self {
            Resampling::Systematic => {
                let n = out.len() as f64;
                let u: f64 = rng.random::<f64>();
                merge_sorted(weights, out, |i| (u + i as f64) / n);
            }
            Resampling::Multinomial => {
                // Sorted uniforms from normalised cumulative sums of N + 1 exponentials.
                let m = out.len();
                let mut acc = 0.0;
                let cum = scratch;
                cum.clear();
                for _ in 0..m {
                    acc += rng.sample::<f64, _>(Exp1);
                    cum.push(acc);
                }
                let total = acc + rng.sample::<f64, _>(Exp1);
                merge_sorted(weights, out, |i| cum[i] / total);
            }
        }
    }
}

/// For increasing positions `pos(0) <= pos(1) <= ...` in [0, 1), writes the index of
/// the weight whose cumulative interval holds each position.
fn merge_sorted(weights: &[f64], out: &mut [usize], pos: impl Fn(usize) -> f64) {
    let last = weights.len() - 1;
    let mut j = 0;
    let mut cum = weights[0];
    for (i, o) in out.iter_mut().enumerate() {
        let p = pos(i);
        while p >= cum && j < last {
            j += 1;
            cum += weights[j];
        }
        *o = j;
    }
}

/// Effective sample size `1 / sum W_i^2` of normalised weights.
pub fn effective_sample_size(weights: &[f64]) -> f64 {
    1.0 / weights.iter().map(|w| w * w).sum::<f64>()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::SmallRng;
    use rand::SeedableRng;

    #[test]
    fn weights_summing_under_one_never_index_past_the_end() {
        // Rounding can leave the sum below the largest position: the last index absorbs it.
        let w = vec![0.25, 0.25, 0.25, 0.25 - 1e-12];
        let mut out = vec![0; 4];
        merge_sorted(&w, &mut out, |i| [0.1, 0.5, 0.9, 1.0 - 1e-15][i]);
        assert_eq!(out, vec![0, 2, 3, 3]);
    }

    #[test]
    fn counts_match_weights() {
        let w = [0.1, 0.0, 0.6, 0.3];
        let mut rng = SmallRng::seed_from_u64(1);
        for scheme in [Resampling::Systematic, Resampling::Multinomial] {
            let mut counts = [0usize; 4];
            let mut out = vec![0; 1000];
            for _ in 0..100 {
                scheme.draw(&w, &mut rng, &mut out, &mut Vec::new());
                for &i in &out {
                    counts[i] += 1;
                }
            }
            // 100,000 draws: multinomial sd of a count is at most sqrt(n p (1-p)) < 160.
            for (c, p) in counts.iter().zip(w) {
                assert!((*c as f64 - 1e5 * p).abs() < 800.0, "{scheme:?}: {counts:?}");
            }
            assert_eq!(counts[1], 0, "a zero weight is never drawn");
        }
    }

    #[test]
    fn systematic_is_within_one_of_expected_count() {
        let w = [0.123, 0.377, 0.2, 0.3];
        let mut out = vec![0; 50];
        Resampling::Systematic.draw(&w, &mut SmallRng::seed_from_u64(9), &mut out, &mut Vec::new());
        for (k, p) in w.iter().enumerate() {
            let c = out.iter().filter(|&&i| i == k).count() as f64;
            assert!((c - 50.0 * p).abs() < 1.0 + 1e-9);
        }
    }
}
