//! Small statistical helpers shared by the filter, tests and diagnostics: the
//! sample mean and sd, a stable log-sum-exp, the standard normal CDF and the
//! Kolmogorov–Smirnov distance of a sample from N(0, 1), and the Wilson interval
//! of a binomial share.

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
