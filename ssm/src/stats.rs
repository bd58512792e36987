//! The one home of the statistical helpers shared by the filter, the metrics,
//! the calibration and the diagnosis: the sample mean and sd, quantiles, the
//! median and the interquartile range ([`Summary`]), a stable log-sum-exp, the
//! standard normal CDF and quantile, the Kolmogorov–Smirnov distance of a sample
//! from N(0, 1), the Wilson interval of a binomial share, and the serde helpers
//! that read `null` as NaN.
//!
//! ```
//! use ssm::stats::Summary;
//! let s = Summary::of(&[1.0, 2.0, 3.0, 4.0, 5.0]).unwrap();
//! assert_eq!((s.median, s.q1, s.q3, s.iqr), (3.0, 2.0, 4.0, 2.0));
//! ```

use serde::Serialize;

/// Mean; NaN when empty.
pub fn mean(xs: impl IntoIterator<Item = f64>) -> f64 {
    let (n, sum) = xs.into_iter().fold((0usize, 0.0), |(n, s), x| (n + 1, s + x));
    sum / n as f64
}

/// Sample standard deviation (denominator `n - 1`); NaN below 2 values.
pub fn sd(xs: impl IntoIterator<Item = f64>) -> f64 {
    let xs: Vec<f64> = xs.into_iter().collect();
    if xs.len() < 2 {
        return f64::NAN;
    }
    let m = mean(xs.iter().copied());
    (xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (xs.len() - 1) as f64).sqrt()
}

/// `ln sum_i exp(x_i)` in f64, stable (`-inf` for an empty or all `-inf` slice).
#[inline]
pub fn log_sum_exp(x: &[f64]) -> f64 {
    let max = x.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if max == f64::NEG_INFINITY {
        return max;
    }
    max + x.iter().map(|&v| (v - max).exp()).sum::<f64>().ln()
}

/// The standard normal CDF, via the Numerical Recipes `erfc` (relative error of
/// `erfc` below 1.2e-7).
///
/// ```
/// let p = ssm::stats::normal_cdf(1.96);
/// assert!((p - 0.975).abs() < 1e-4);
/// assert!((ssm::stats::normal_cdf(0.0) - 0.5).abs() < 1e-7);
/// ```
pub fn normal_cdf(x: f64) -> f64 {
    let z = x.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98 + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let erfc = t * poly.exp();
    if x >= 0.0 {
        1.0 - 0.5 * erfc
    } else {
        0.5 * erfc
    }
}

/// The standard normal quantile `Phi^{-1}(p)` for `p` in `(0, 1)`, by bisection
/// on [`normal_cdf`] (to its accuracy).
///
/// ```
/// assert!((ssm::stats::normal_quantile(0.975) - 1.96).abs() < 1e-3);
/// ```
pub fn normal_quantile(p: f64) -> f64 {
    bisect_increasing(normal_cdf, p, (-10.0, 10.0), 64)
}

/// Where the increasing `f` reaches `target` in `[lo, hi]`, by `iterations`
/// halvings of the bracket (its midpoint; an end when `f` stays on one side).
pub fn bisect_increasing(f: impl Fn(f64) -> f64, target: f64, (mut lo, mut hi): (f64, f64), iterations: usize) -> f64 {
    for _ in 0..iterations {
        let mid = 0.5 * (lo + hi);
        if f(mid) < target {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// The Wilson score interval of a binomial share: `successes` of `trials` at the
/// two-sided `level` (0.95 for 95%). Unlike the normal approximation it stays in
/// [0, 1] and is not empty at 0 or `trials` successes, which is where a study of
/// five seeds lives: 5 of 5 has a 95% lower bound of 0.57. `(NaN, NaN)` for no
/// trials.
///
/// ```
/// let (low, high) = ssm::stats::wilson_interval(5, 5, 0.95);
/// assert!((low - 0.5655).abs() < 1e-3 && (high - 1.0).abs() < 1e-12);
/// let (low, high) = ssm::stats::wilson_interval(4, 5, 0.95);
/// assert!((low - 0.3755).abs() < 1e-3 && (high - 0.9638).abs() < 1e-3);
/// assert_eq!(ssm::stats::wilson_interval(0, 5, 0.95).0, 0.0);
/// ```
pub fn wilson_interval(successes: usize, trials: usize, level: f64) -> (f64, f64) {
    if trials == 0 {
        return (f64::NAN, f64::NAN);
    }
    let n = trials as f64;
    let share = successes.min(trials) as f64 / n;
    let z2 = normal_quantile(0.5 + 0.5 * level).powi(2);
    let scale = 1.0 + z2 / n;
    let centre = (share + z2 / (2.0 * n)) / scale;
    let half = (z2 * (share * (1.0 - share) / n + z2 / (4.0 * n * n))).sqrt() / scale;
    ((centre - half).max(0.0), (centre + half).min(1.0))
}

/// The Kolmogorov–Smirnov distance `sup |F_n - Phi|` of a sample from N(0, 1).
/// Under the null its scale is `1 / sqrt(n)` (5% critical value ~1.36 / sqrt(n)).
pub fn ks_distance_to_normal(mut z: Vec<f64>) -> f64 {
    z.sort_by(f64::total_cmp);
    let n = z.len() as f64;
    z.iter()
        .enumerate()
        .map(|(i, &x)| {
            let f = normal_cdf(x);
            (f - i as f64 / n).abs().max(((i + 1) as f64 / n - f).abs())
        })
        .fold(0.0, f64::max)
}

/// Reads a number that JSON may hold as `null`: serde_json writes a non-finite
/// `f64` (a NaN share, an undefined z) as `null`, and this reads it back as NaN,
/// so a report written with one can be read again (`#[serde(deserialize_with =
/// "crate::stats::nan_from_null")]`).
pub fn nan_from_null<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    use serde::Deserialize;
    Ok(Option::<f64>::deserialize(deserializer)?.unwrap_or(f64::NAN))
}

/// [`nan_from_null`] for a list of numbers (per-object gains and Monte Carlo
/// sds, NaN where one run left an sd undefined).
pub fn vec_nan_from_null<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<Vec<f64>, D::Error> {
    use serde::Deserialize;
    Ok(Vec::<Option<f64>>::deserialize(deserializer)?.into_iter().map(|x| x.unwrap_or(f64::NAN)).collect())
}

/// [`nan_from_null`] for a list of pairs of numbers (a check's per-draw
/// statistics, NaN where a draw had nothing to measure).
pub fn pairs_nan_from_null<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<Vec<(f64, f64)>, D::Error> {
    use serde::Deserialize;
    let pairs = Vec::<(Option<f64>, Option<f64>)>::deserialize(deserializer)?;
    Ok(pairs.into_iter().map(|(a, b)| (a.unwrap_or(f64::NAN), b.unwrap_or(f64::NAN))).collect())
}

/// NaN: the serde default of a number a report written before it existed lacks
/// (`#[serde(default = "crate::stats::nan")]`).
pub fn nan() -> f64 {
    f64::NAN
}

/// Median and interquartile range of repeated measurements. Quartiles are by
/// linear interpolation between order statistics (NumPy's default, "type 7").
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Summary {
    /// The median.
    pub median: f64,
    /// The first quartile (25th percentile).
    pub q1: f64,
    /// The third quartile (75th percentile).
    pub q3: f64,
    /// `q3 - q1`.
    pub iqr: f64,
    /// Number of values summarised.
    pub n: usize,
}

impl Summary {
    /// The summary of the finite values of `values`; `None` if there are none.
    pub fn of(values: &[f64]) -> Option<Summary> {
        let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        let (q1, median, q3) = (quantile_sorted(&v, 0.25), quantile_sorted(&v, 0.5), quantile_sorted(&v, 0.75));
        Some(Summary { median, q1, q3, iqr: q3 - q1, n: v.len() })
    }
}

/// The `q`-quantile (`0 <= q <= 1`) of sorted, non-empty values by linear
/// interpolation (the caller sorts once for several quantiles; [`quantile`]
/// takes any values).
#[track_caller]
pub fn quantile_sorted(v: &[f64], q: f64) -> f64 {
    let h = q * (v.len() - 1) as f64;
    let (lo, hi) = (h.floor() as usize, h.ceil() as usize);
    v[lo] + (h - lo as f64) * (v[hi] - v[lo])
}

/// The `q`-quantile of the finite values (linear interpolation); `None` if there
/// are none. Panics unless `0 <= q <= 1`.
#[track_caller]
pub fn quantile(values: &[f64], q: f64) -> Option<f64> {
    assert!((0.0..=1.0).contains(&q), "quantile: q = {q} is outside [0, 1]");
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(quantile_sorted(&v, q))
}

/// The median of the finite values; `None` if there are none.
pub fn median(values: &[f64]) -> Option<f64> {
    quantile(values, 0.5)
}

/// The interquartile range of the finite values; `None` if there are none.
pub fn iqr(values: &[f64]) -> Option<f64> {
    Summary::of(values).map(|s| s.iqr)
}
