//! Fast, branch-free f32 transcendentals that the compiler can vectorise.
//!
//! The particle filter evaluates about 1e9 transcendentals per step, so `std`'s
//! scalar `tanh`/`exp`/`ln` (which do not vectorise) dominate run time. These are
//! the classic Cephes / Eigen polynomial and rational approximations, written
//! without branches (selects only) so that a loop over a slice compiles to SIMD.
//! Accuracy (checked in tests against `std` in f64): `exp` and `ln` within
//! 2 ulp-ish relative error (< 3e-7), `tanh` within 1e-6 absolute, `softplus`
//! within 1e-6 relative (also far into its exponential tail).

/// log2(e).
const LOG2E: f32 = std::f32::consts::LOG2_E;
/// ln(2) split in a high part exactly representable with few bits and a low correction.
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// Largest argument whose exp is finite in f32.
const EXP_HI: f32 = 88.376_26;
/// Below this exp underflows to (nearly) zero; we return exactly zero.
const EXP_LO: f32 = -87.336_55;
/// Adding and subtracting 1.5 * 2^23 rounds an f32 to the nearest integer.
const ROUND_MAGIC: f32 = 12_582_912.0;

/// The integer `n` held by `n + ROUND_MAGIC` (for |n| < 2^22), read from the bits.
/// Unlike a saturating `as i32` cast this vectorises, and it is defined for every
/// input (NaN and out-of-range values give garbage, never undefined behaviour).
#[inline(always)]
fn round_to_int(shifted: f32) -> i32 {
    (shifted.to_bits() as i32).wrapping_sub(ROUND_MAGIC.to_bits() as i32)
}

/// exp(x) for f32: range reduction to [-ln2/2, ln2/2] and a degree-6 polynomial (Cephes expf).
///
/// Returns exactly 0 for x < -87.3 (including -inf), +inf above 88.37, NaN for NaN.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    let xc = x.clamp(EXP_LO, EXP_HI);
    // n = round(x / ln 2)
    let shifted = xc * LOG2E + ROUND_MAGIC;
    let n = shifted - ROUND_MAGIC;
    let r = xc - n * LN2_HI - n * LN2_LO;
    let r2 = r * r;
    let p = ((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r + 1.666_666_5e-1)
        * r
        + 5.000_000_1e-1;
    let y = p * r2 + r + 1.0;
    // Scale by 2^n through the exponent bits; n is in [-126, 128).
    let scale = f32::from_bits(((round_to_int(shifted) + 127) as u32) << 23);
    let mut out = y * scale;
    out = if x < EXP_LO { 0.0 } else { out };
    out = if x > EXP_HI { f32::INFINITY } else { out };
    if x.is_nan() {
        f32::NAN
    } else {
        out
    }
}

/// ln(x) for f32 (Cephes logf): exponent extraction and a degree-8 polynomial.
///
/// Returns -inf for 0, NaN for negative inputs, +inf for +inf.
#[inline(always)]
pub fn ln_f32(x: f32) -> f32 {
    const SQRT_HALF: f32 = std::f32::consts::FRAC_1_SQRT_2;
    // Subnormals: scale up by 2^23 first so the exponent field is meaningful.
    let tiny = x < f32::MIN_POSITIVE;
    let xs = if tiny { x * 8_388_608.0 } else { x };
    let bits = xs.to_bits();
    let mut e = ((bits >> 23) & 0xff) as i32 - 126;
    // Mantissa in [0.5, 1).
    let mut m = f32::from_bits((bits & 0x007f_ffff) | 0x3f00_0000);
    let small = m < SQRT_HALF;
    e = if small { e - 1 } else { e };
    m = if small { m + m - 1.0 } else { m - 1.0 };
    let z = m * m;
    let mut y = ((((((((7.037_683_6e-2 * m - 1.151_461e-1) * m + 1.167_699_9e-1) * m - 1.242_014_1e-1) * m
        + 1.424_932_3e-1)
        * m
        - 1.666_805_8e-1)
        * m
        + 2.000_071_4e-1)
        * m
        - 2.499_999_4e-1)
        * m
        + 3.333_333_1e-1)
        * m
        * z;
    let ef = e as f32 - if tiny { 23.0 } else { 0.0 };
    y += LN2_LO * ef;
    y += -0.5 * z;
    let mut out = m + y + LN2_HI * ef;
    out = if x == 0.0 { f32::NEG_INFINITY } else { out };
    out = if x == f32::INFINITY { f32::INFINITY } else { out };
    if x < 0.0 || x.is_nan() {
        f32::NAN
    } else {
        out
    }
}

/// tanh(x) for f32: Eigen's 13/6 rational approximation on [-7.9, 7.9].
#[inline(always)]
pub fn tanh_f32(x: f32) -> f32 {
    const CLAMP: f32 = 7.905_311;
    let xc = x.clamp(-CLAMP, CLAMP);
    let x2 = xc * xc;
    let p = ((((((-2.760_768_5e-16 * x2 + 2.000_187_9e-13) * x2 - 8.604_671_5e-11) * x2 + 5.122_297e-8) * x2
        + 1.485_722_4e-5)
        * x2
        + 6.372_619_3e-4)
        * x2
        + 4.893_524_6e-3)
        * xc;
    let q = ((1.198_258_4e-6 * x2 + 1.185_347_1e-4) * x2 + 2.268_434_6e-3) * x2 + 4.893_525e-3;
    let t = p / q;
    if x.abs() < 4e-4 {
        x
    } else {
        t
    }
}

/// ln(1 + exp(x)) for f32, stable for any x: max(x, 0) + ln(1 + exp(-|x|)).
#[inline(always)]
pub fn softplus_f32(x: f32) -> f32 {
    let e = exp_f32(-x.abs());
    // ln(1 + e) to full relative accuracy (softplus(x) ~ e for x << 0). Rounding
    // u = 1 + e loses up to half an ulp of 1, which is 6e-4 of e near e = 1e-4, so
    // ln_f32(u) alone is not enough. Goldberg's correction ln(u) * e / (u - 1) cancels
    // that rounding (u - 1 is exact for e <= 1, and ln_f32 is relatively accurate
    // near 1). For tiny e the series e - e^2/2 is accurate to e^2/3 < 4e-9.
    let u = 1.0 + e;
    let l = if e < 1e-4 { e - 0.5 * e * e } else { ln_f32(u) * (e / (u - 1.0)) };
    x.max(0.0) + l
}

/// The logistic sigmoid 1 / (1 + exp(-x)) for f32, stable for any x.
#[inline(always)]
pub fn sigmoid_f32(x: f32) -> f32 {
    let e = exp_f32(-x.abs());
    let s = 1.0 / (1.0 + e);
    if x >= 0.0 {
        s
    } else {
        e * s
    }
}

/// 2 / pi.
const FRAC_2_PI: f32 = std::f32::consts::FRAC_2_PI;
/// pi / 2 in three parts for Cody–Waite reduction (the first two exact in few bits).
const PIO2_1: f32 = 1.570_312_5;
const PIO2_2: f32 = 4.837_513e-4;
const PIO2_3: f32 = 7.549_79e-8;

/// (sin x, cos x) for f32: reduction by multiples of pi/2 and Cephes' minimax
/// polynomials on [-pi/4, pi/4]. Absolute error below 5e-7 for |x| <= 1e4 (the
/// reduction loses accuracy slowly beyond; vehicle headings stay far inside).
#[inline(always)]
pub fn sin_cos_f32(x: f32) -> (f32, f32) {
    let shifted = x * FRAC_2_PI + ROUND_MAGIC;
    let k = shifted - ROUND_MAGIC;
    let r = ((x - k * PIO2_1) - k * PIO2_2) - k * PIO2_3;
    let z = r * r;
    let s = ((-1.951_529_6e-4 * z + 8.332_161e-3) * z - 1.666_665_5e-1) * z * r + r;
    let c = ((2.443_315_7e-5 * z - 1.388_731_6e-3) * z + 4.166_664_6e-2) * z * z - 0.5 * z + 1.0;
    let q = round_to_int(shifted) & 3;
    let (sin, cos) = (if q & 1 == 0 { s } else { c }, if q & 1 == 0 { c } else { s });
    let sin = if q & 2 == 0 { sin } else { -sin };
    let cos = if (q + 1) & 2 == 0 { cos } else { -cos };
    (sin, cos)
}

/// sin x for f32 (see [`sin_cos_f32`]).
#[inline(always)]
pub fn sin_f32(x: f32) -> f32 {
    sin_cos_f32(x).0
}

/// cos x for f32 (see [`sin_cos_f32`]).
#[inline(always)]
pub fn cos_f32(x: f32) -> f32 {
    sin_cos_f32(x).1
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(lo: f32, hi: f32, n: usize) -> impl Iterator<Item = f32> {
        (0..=n).map(move |i| lo + (hi - lo) * i as f32 / n as f32)
    }

    #[test]
    fn exp_matches_std_relative() {
        let mut worst = 0.0f64;
        for x in grid(-87.0, 88.0, 200_000) {
            let exact = (x as f64).exp();
            let rel = ((exp_f32(x) as f64 - exact) / exact).abs();
            worst = worst.max(rel);
        }
        assert!(worst < 3e-7, "worst relative error {worst}");
        assert_eq!(exp_f32(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp_f32(-100.0), 0.0);
        assert_eq!(exp_f32(100.0), f32::INFINITY);
        assert!(exp_f32(f32::NAN).is_nan());
        assert_eq!(exp_f32(0.0), 1.0);
    }

    #[test]
    fn ln_matches_std() {
        let mut worst = 0.0f64;
        // Log-spaced positive inputs across the whole normal and subnormal range.
        for i in 0..200_000 {
            let x = (-100.0f64 + 190.0 * i as f64 / 200_000.0).exp() as f32;
            if x == 0.0 || !x.is_finite() {
                continue;
            }
            let exact = (x as f64).ln();
            let err = (ln_f32(x) as f64 - exact).abs() / exact.abs().max(1.0);
            worst = worst.max(err);
        }
        assert!(worst < 3e-7, "worst error {worst}");
        assert_eq!(ln_f32(0.0), f32::NEG_INFINITY);
        assert!(ln_f32(-1.0).is_nan());
        assert_eq!(ln_f32(f32::INFINITY), f32::INFINITY);
        assert_eq!(ln_f32(1.0), 0.0);
    }

    #[test]
    fn tanh_matches_std() {
        let mut worst = 0.0f64;
        for x in grid(-20.0, 20.0, 400_000) {
            let err = (tanh_f32(x) as f64 - (x as f64).tanh()).abs();
            worst = worst.max(err);
        }
        assert!(worst < 1e-6, "worst absolute error {worst}");
        assert_eq!(tanh_f32(f32::INFINITY), 1.0);
        assert_eq!(tanh_f32(f32::NEG_INFINITY), -1.0);
    }

    #[test]
    fn softplus_and_sigmoid_match_std() {
        for x in grid(-60.0, 60.0, 100_000) {
            let xd = x as f64;
            let sp = xd.max(0.0) + (-xd.abs()).exp().ln_1p();
            // Relative: softplus(x) ~ e^x for x << 0 must keep its leading digits.
            assert!((softplus_f32(x) as f64 - sp).abs() < 1e-6 * sp, "softplus({x})");
            let sg = 1.0 / (1.0 + (-xd).exp());
            assert!((sigmoid_f32(x) as f64 - sg).abs() < 3e-7, "sigmoid({x})");
        }
    }

    #[test]
    fn sin_cos_match_std() {
        let mut worst = 0.0f64;
        for x in grid(-1e4, 1e4, 2_000_000).chain(grid(-7.0, 7.0, 200_000)) {
            let (s, c) = sin_cos_f32(x);
            let xd = x as f64;
            worst = worst.max((s as f64 - xd.sin()).abs()).max((c as f64 - xd.cos()).abs());
        }
        assert!(worst < 5e-7, "worst absolute error {worst}");
        assert_eq!(sin_cos_f32(0.0), (0.0, 1.0));
    }
}
