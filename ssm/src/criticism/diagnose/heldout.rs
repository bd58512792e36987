//! Held-out evaluation: each model's per-object log-likelihoods on the
//! evaluation part, and the paired comparison of two models' (the gain per unit,
//! its standard error, the sign-flip permutation p-value, how much of the gain
//! two objects carry).

use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use super::config::Evaluation;
use crate::filter::run_filter;
use crate::models::ParticleModel;
use crate::stats::{log_sum_exp, sd};

/// One model's log-likelihoods on the evaluation part.
pub(super) struct EvalLikelihoods {
    /// Per object: the log of the mean of the runs' likelihood estimates.
    pub(super) object_ll: Vec<f64>,
    /// Per object: the Monte Carlo sd of `object_ll` ([`monte_carlo_sd`]).
    pub(super) object_mc_sd: Vec<f64>,
    /// Observed units (points, detections).
    pub(super) units: usize,
}

impl EvalLikelihoods {
    /// The same likelihoods without the objects `set_aside` (indices in
    /// ascending order), whose observed units `object_units` gives per object.
    pub(super) fn without(&self, set_aside: &[usize], object_units: &[usize]) -> EvalLikelihoods {
        let keep = |i: &usize| set_aside.binary_search(i).is_err();
        let kept = |v: &[f64]| v.iter().enumerate().filter(|(i, _)| keep(i)).map(|(_, x)| *x).collect();
        EvalLikelihoods {
            object_ll: kept(&self.object_ll),
            object_mc_sd: kept(&self.object_mc_sd),
            units: self.units - set_aside.iter().map(|&i| object_units[i]).sum::<usize>(),
        }
    }

    /// Puts the likelihoods of `refined`, one model's estimates of the objects
    /// `objects` alone (in that order), in place of this model's.
    pub(super) fn replace(&mut self, objects: &[usize], refined: &EvalLikelihoods) {
        assert_eq!(objects.len(), refined.object_ll.len(), "one refined estimate per object");
        for (k, &o) in objects.iter().enumerate() {
            self.object_ll[o] = refined.object_ll[k];
            self.object_mc_sd[o] = refined.object_mc_sd[k];
        }
    }
}

/// The evaluation objects on which the models of `models` cannot be compared,
/// in ascending order: those whose log-likelihood has a Monte Carlo sd
/// ([`monte_carlo_sd`]) above `bar` nats under at least one model, so that
/// any difference with that model is its filter's noise. Under *every* model
/// would not do: two runs can agree where both are far off (measured: an
/// object whose estimate under the base 32768 particles do not pin to 200
/// nats had its two runs 31 nats apart under one candidate, and 4,311 nats
/// below its reference's estimate). Decided from the runs' spreads alone, the same
/// under any exchange of two models, so a paired sign-flip test over the other
/// objects keeps its level. An sd that is not a number (one run) counts as
/// measured.
pub(super) fn unmeasured_objects(models: &[&EvalLikelihoods], bar: f64) -> Vec<usize> {
    let Some(first) = models.first() else { return Vec::new() };
    (0..first.object_mc_sd.len()).filter(|&o| models.iter().any(|m| m.object_mc_sd[o] > bar)).collect()
}

/// The log-likelihoods of `model` on its data: each object's likelihood
/// estimates of [`Evaluation::runs`] filter runs, averaged.
pub(super) fn likelihoods<M: ParticleModel>(model: &M, eval: &Evaluation) -> Result<EvalLikelihoods, String> {
    let mut per_object: Vec<Vec<f64>> = Vec::new();
    let mut units = 0;
    for r in 0..eval.runs {
        let run = run_filter(model, &eval.filter(r), |_| ());
        if r == 0 {
            per_object = vec![Vec::with_capacity(eval.runs); run.objects.len()];
            units = run.observed_units();
        }
        per_object.iter_mut().zip(&run.objects).for_each(|(l, o)| l.push(o.log_likelihood));
    }
    let object_ll: Vec<f64> = per_object.iter().map(|l| log_sum_exp(l) - (l.len() as f64).ln()).collect();
    if let Some(bad) = object_ll.iter().position(|l| !l.is_finite()) {
        return Err(format!("the log-likelihood of evaluated object {bad} is not finite"));
    }
    let object_mc_sd = per_object.iter().map(|l| monte_carlo_sd(l)).collect();
    Ok(EvalLikelihoods { object_ll, object_mc_sd, units })
}

/// The Monte Carlo sd of an object's held-out log-likelihood from its runs'
/// log-likelihood estimates `runs`: their sample sd over `sqrt(runs)` (NaN with
/// fewer than two runs). Taken on the log scale, not by the delta method on the
/// likelihoods, because two runs that disagree by tens of nats say the estimate
/// is that imprecise, where the delta method would cap it near one nat.
pub(super) fn monte_carlo_sd(runs: &[f64]) -> f64 {
    sd(runs.iter().copied()) / (runs.len() as f64).sqrt()
}

/// The Monte Carlo error of the paired gain of model `a` over model `b`, from
/// the filters' own noise: `(sd of the gain per unit, the largest sd of one
/// object's gain in nats)`. Each object's sds under the two models are combined
/// as if independent; the models share their filters' seeds, which correlates
/// their errors positively, so this overstates the error rather than hides it.
pub(super) fn gain_monte_carlo_sd(a: &EvalLikelihoods, b: &EvalLikelihoods) -> (f64, f64) {
    let variances = || a.object_mc_sd.iter().zip(&b.object_mc_sd).map(|(x, y)| x * x + y * y);
    let total = variances().sum::<f64>().sqrt() / b.units.max(1) as f64;
    let worst = variances().fold(f64::NAN, f64::max).sqrt();
    (total, worst)
}

/// `a_i - b_i`.
pub(super) fn differences(a: &[f64], b: &[f64]) -> Vec<f64> {
    a.iter().zip(b).map(|(x, y)| x - y).collect()
}

/// The share of `sum(d)` carried by its two largest entries (NaN unless the sum is positive).
pub(super) fn top_two_share(d: &[f64]) -> f64 {
    let total: f64 = d.iter().sum();
    if total <= 0.0 {
        return f64::NAN;
    }
    let mut sorted = d.to_vec();
    sorted.sort_by(|a, b| b.total_cmp(a));
    sorted.iter().take(2).sum::<f64>() / total
}

/// One-sided sign-flip permutation p-value of `sum(d) > 0`, objects exchangeable
/// under the null of a gain distributed symmetrically about zero:
/// `(1 + #{flips with sum >= observed}) / (1 + permutations)`, the flips drawn
/// from a seeded stream (exact enumeration when `2^n <= permutations`).
pub fn sign_flip_p(d: &[f64], permutations: usize, seed: u64) -> f64 {
    let observed: f64 = d.iter().sum();
    if d.is_empty() || !observed.is_finite() {
        return 1.0;
    }
    // A relative tolerance so that a flip reproducing the observed sum counts
    // despite rounding.
    let tol = 1e-12 * d.iter().map(|x| x.abs()).sum::<f64>();
    let n = d.len();
    if n < 63 && (1usize << n) <= permutations {
        let total = 1usize << n;
        let at_least = (0..total)
            .filter(|mask| {
                let s: f64 = d.iter().enumerate().map(|(i, x)| if mask >> i & 1 == 1 { -x } else { *x }).sum();
                s >= observed - tol
            })
            .count();
        return at_least as f64 / total as f64;
    }
    let mut rng = SmallRng::seed_from_u64(seed);
    let at_least = (0..permutations)
        .filter(|_| {
            let s: f64 = d.iter().map(|x| if rng.random::<bool>() { -x } else { *x }).sum();
            s >= observed - tol
        })
        .count();
    (1 + at_least) as f64 / (1 + permutations) as f64
}

/// `(sum_i (a_i - b_i) / units, sqrt(n var(a - b)) / units)`: the gain per unit
/// and its normal-approximation standard error, objects independent.
pub fn paired_gain(a: &[f64], b: &[f64], units: usize) -> (f64, f64) {
    gain_of(&differences(a, b), units)
}

/// [`paired_gain`] of the per-object differences `d`.
pub(super) fn gain_of(d: &[f64], units: usize) -> (f64, f64) {
    let n = d.len() as f64;
    let units = units.max(1) as f64;
    if d.len() < 2 {
        return (d.iter().sum::<f64>() / units, f64::INFINITY);
    }
    (d.iter().sum::<f64>() / units, n.sqrt() * sd(d.iter().copied()) / units)
}

/// One group of evaluation objects (a KITTI sequence, a scene) and its part of a
/// candidate's held-out gain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GroupGain {
    /// The group's label (see [`gains_by_group`]).
    pub group: i64,
    /// Evaluation objects in the group.
    pub objects: usize,
    /// Their observed units.
    pub units: usize,
    /// The gain over the group's objects (nats per observed unit) and its
    /// standard error, as [`paired_gain`] computes them.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain: f64,
    /// See `gain`.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain_se: f64,
    /// The share of the group's objects whose gain is positive.
    pub positive: f64,
}

/// A candidate's per-object held-out gains (`object_gains`, nats) split by the
/// group `group` gives each object's scene id (`objects[i].0`), each with its
/// objects' `units`; groups in ascending order. What shows whether a gain is
/// carried by the whole held-out set or by one of its parts.
pub fn gains_by_group(
    object_gains: &[f64],
    objects: &[(i64, i64)],
    units: &[usize],
    group: impl Fn(i64) -> i64,
) -> Vec<GroupGain> {
    let mut members: std::collections::BTreeMap<i64, Vec<usize>> = Default::default();
    for (i, o) in objects.iter().enumerate() {
        members.entry(group(o.0)).or_default().push(i);
    }
    members
        .into_iter()
        .map(|(g, members)| {
            let d: Vec<f64> = members.iter().map(|&i| object_gains[i]).collect();
            let units = members.iter().map(|&i| units[i]).sum();
            let (gain, gain_se) = gain_of(&d, units);
            let positive = d.iter().filter(|&&x| x > 0.0).count() as f64 / d.len() as f64;
            GroupGain { group: g, objects: members.len(), units, gain, gain_se, positive }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn monte_carlo_sd_is_the_runs_spread_on_the_log_scale() {
        // Two runs 200 nats apart: the estimate is uncertain by about 100 nats,
        // not the ~1 nat the delta method on the likelihoods would say.
        assert!((monte_carlo_sd(&[-1000.0, -1200.0]) - 100.0).abs() < 1e-9);
        // Four runs: sample sd 1.291 over 2.
        let s = monte_carlo_sd(&[1.0, 2.0, 3.0, 4.0]);
        assert!((s - (5.0f64 / 3.0).sqrt() / 2.0).abs() < 1e-12, "{s}");
        assert!(monte_carlo_sd(&[-5.0]).is_nan());
    }

    #[test]
    fn an_object_is_set_aside_when_a_model_does_not_measure_it() {
        let ll =
            |sd: Vec<f64>| EvalLikelihoods { object_ll: vec![-1.0, -2.0, -3.0, -4.0], object_mc_sd: sd, units: 40 };
        let a = ll(vec![50.0, 0.1, 30.0, f64::NAN]);
        let b = ll(vec![60.0, 40.0, 0.2, 70.0]);
        // Objects 0 to 3: above 20 nats under both models, under one, under
        // the other, and under one where the other's sd is NaN (measured).
        assert_eq!(unmeasured_objects(&[&a, &b], 20.0), vec![0, 1, 2, 3]);
        assert_eq!(unmeasured_objects(&[&a, &b], 45.0), vec![0, 3]);
        assert_eq!(unmeasured_objects(&[&b, &a], 45.0), vec![0, 3], "the same under an exchange of the models");
        assert_eq!(unmeasured_objects(&[&a], 20.0), vec![0, 2]);
        assert_eq!(unmeasured_objects(&[&a, &b], 100.0), Vec::<usize>::new());
        assert!(unmeasured_objects(&[], 20.0).is_empty());
        let kept = a.without(&[0, 3], &[10, 5, 20, 5]);
        assert_eq!(kept.object_ll, vec![-2.0, -3.0]);
        assert_eq!(kept.object_mc_sd, vec![0.1, 30.0]);
        assert_eq!(kept.units, 25);
        let mut refined = ll(vec![50.0, 0.1, 30.0, 1.0]);
        refined
            .replace(&[0, 2], &EvalLikelihoods { object_ll: vec![-9.0, -8.0], object_mc_sd: vec![2.0, 3.0], units: 7 });
        assert_eq!((refined.object_ll, refined.object_mc_sd), (vec![-9.0, -2.0, -8.0, -4.0], vec![2.0, 0.1, 3.0, 1.0]));
        assert_eq!(refined.units, 40, "the units are the whole part's");
    }

    #[test]
    fn the_gains_monte_carlo_sd_combines_both_models_objects() {
        let a = EvalLikelihoods { object_ll: vec![0.0; 3], object_mc_sd: vec![3.0, 0.0, 1.0], units: 10 };
        let b = EvalLikelihoods { object_ll: vec![0.0; 3], object_mc_sd: vec![4.0, 0.0, 1.0], units: 10 };
        let (per_unit, worst) = gain_monte_carlo_sd(&a, &b);
        assert!((worst - 5.0).abs() < 1e-12);
        assert!((per_unit - (25.0f64 + 2.0).sqrt() / 10.0).abs() < 1e-12);
        let one_run = EvalLikelihoods { object_ll: vec![0.0], object_mc_sd: vec![f64::NAN], units: 1 };
        assert!(gain_monte_carlo_sd(&one_run, &one_run).0.is_nan());
    }

    /// Gains split by group: each group's gain is its objects' differences over
    /// its units, the groups' gains weighted by their units add up to the whole
    /// gain, and the groups come in ascending order with their objects counted.
    #[test]
    fn gains_by_group_split_the_whole_gain() {
        let keys = [(20_003, 1), (10_007, 1), (20_050, 2), (10_007, 4), (30_000, 1)];
        let gains = [1.0, -0.5, 3.0, 0.25, -2.0];
        let units = [10, 5, 20, 5, 8];
        let groups = gains_by_group(&gains, &keys, &units, |scene| scene / 10_000);
        let labels: Vec<i64> = groups.iter().map(|g| g.group).collect();
        assert_eq!(labels, vec![1, 2, 3]);
        assert_eq!(groups[0].objects, 2);
        assert_eq!(groups[0].units, 10);
        assert!((groups[0].gain + 0.025).abs() < 1e-12);
        assert!((groups[0].positive - 0.5).abs() < 1e-12);
        assert!((groups[1].gain - 4.0 / 30.0).abs() < 1e-12);
        assert!(groups[2].gain_se.is_infinite(), "one object has no spread");
        let total: f64 = groups.iter().map(|g| g.gain * g.units as f64).sum();
        let (whole, _) = paired_gain(&gains, &[0.0; 5], units.iter().sum());
        assert!((total / 48.0 - whole).abs() < 1e-12);
    }

    /// The sign-flip p-value: exact enumeration for few objects, uniform-ish
    /// under a symmetric null, small for a clear shift, and not fooled by one
    /// object that carries the whole sum.
    #[test]
    fn sign_flip_p_is_calibrated_and_robust() {
        // Exact: 3 objects, all positive -> only the identity flip reaches the sum.
        assert!((sign_flip_p(&[1.0, 2.0, 3.0], 9999, 0) - 1.0 / 8.0).abs() < 1e-12);
        // A clear shift over 40 objects.
        let shifted: Vec<f64> = (0..40).map(|i| 1.0 + ((i * 37 % 11) as f64 - 5.0) * 0.2).collect();
        assert!(sign_flip_p(&shifted, 9999, 1) < 1e-3);
        // One huge object among many small negative ones: not significant.
        let mut carried = vec![-0.1; 39];
        carried.push(100.0);
        assert!(sign_flip_p(&carried, 9999, 2) > 0.4, "one object cannot carry the decision");
        // Under a symmetric null, p is below 0.05 in about 5% of draws.
        let mut rng = SmallRng::seed_from_u64(3);
        let rejections = (0..400)
            .filter(|&k| {
                let d: Vec<f64> = (0..30).map(|_| rng.random::<f64>() - 0.5).collect();
                sign_flip_p(&d, 999, k) < 0.05
            })
            .count();
        assert!((8..=36).contains(&rejections), "{rejections} of 400 null draws rejected at 5%");
    }
}
