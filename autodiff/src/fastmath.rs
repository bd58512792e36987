//! Fast, branch-free f32 transcendentals that the compiler can vectorise.
//!
//! The particle filter evaluates about 1e9 transcendentals per step, so `std`'s
//! scalar `tanh`/`exp`/`ln` (which do not vectorise) dominate run time. These are
//! the classic Cephes / Eigen polynomial and rational approximations, written
//! without branches (selects only) so that a loop over a slice compiles to SIMD.
//! Accuracy (checked in tests against `std` in f64): `exp`, `exp_nonpos` and `ln`
//! within 2 ulp-ish relative error (< 3e-7), `tanh` within 1e-6 absolute, `softplus`
//! within 1e-6 relative (also far into its exponential tail).
//!
//! Polynomials are evaluated with [`mul_add_f32`]: fused multiply-adds where the
//! build targets FMA (one instruction, one rounding), separate operations elsewhere.

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

/// `a * b + c`: one fused multiply-add (one rounding) when the build targets FMA
/// (`-C target-cpu` or `-C target-feature=+fma`), else a multiply and an add. Never
/// the software `fmaf` that `f32::mul_add` falls back to, which is ~50 times slower.
#[inline(always)]
pub fn mul_add_f32(a: f32, b: f32, c: f32) -> f32 {
    if cfg!(target_feature = "fma") {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// `a * b + c` in f64, fused where the build targets FMA (see [`mul_add_f32`]).
#[inline(always)]
pub fn mul_add_f64(a: f64, b: f64, c: f64) -> f64 {
    if cfg!(target_feature = "fma") {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// Below this [`exp_nonpos_f32`] returns exactly 0: the scale `2^n` of its range
/// reduction is then `2^-127`, whose exponent field is 0 (the bits of +0.0).
const EXP_NONPOS_LO: f32 = -88.0;

/// e^x for f32 and `x <= 0` (also `-inf`): [`exp_f32`]'s reduction and polynomial
/// with one clamp and none of its underflow and overflow fix-ups (15 vector
/// operations instead of 20), for the log-sum-exp kernels whose arguments are
/// shifted by their maximum.
///
/// Relative error below 3e-7 down to `e^-87.3` (the smallest normal f32); between
/// `-88` and `-87.3` the results are subnormal; below `-88` exactly 0. NaN gives NaN.
/// Positive `x` give unspecified values (the caller's contract).
///
/// ```
/// use autodiff::fastmath::exp_nonpos_f32;
/// assert_eq!(exp_nonpos_f32(0.0), 1.0);
/// assert!((exp_nonpos_f32(-1.0) - (-1.0f32).exp()).abs() < 1e-7);
/// assert_eq!(exp_nonpos_f32(f32::NEG_INFINITY), 0.0);
/// ```
#[inline(always)]
pub fn exp_nonpos_f32(x: f32) -> f32 {
    // A clamp that keeps NaN (the comparison is false for it).
    exp_clamped(if x < EXP_NONPOS_LO { EXP_NONPOS_LO } else { x })
}

/// `e^xc` for `xc` in `[-88, 88.38]` (NaN gives NaN): `n = round(xc / ln 2)`, `r =
/// xc - n ln 2` in `[-ln2/2, ln2/2]` (Cody–Waite, fused), `e^r` by Cephes expf's
/// polynomial, and `2^n` from the bits; `n = -127` gives 0, `n = 128` infinity.
#[inline(always)]
fn exp_clamped(xc: f32) -> f32 {
    let shifted = mul_add_f32(xc, LOG2E, ROUND_MAGIC);
    let n = shifted - ROUND_MAGIC;
    let r = mul_add_f32(n, -LN2_LO, mul_add_f32(n, -LN2_HI, xc));
    let y = mul_add_f32(exp_poly(r), r * r, r) + 1.0;
    // 2^n: `shifted` holds ROUND_MAGIC + n, whose low 9 bits are those of n (the
    // magic number's are 0), so the biased exponent n + 127 is the low 9 bits of
    // bits + 127; the shift drops the rest.
    y * f32::from_bits(shifted.to_bits().wrapping_add(EXP_BIAS) << 23)
}

/// The exponent bias of f32.
const EXP_BIAS: u32 = 127;

/// Cephes expf's polynomial: `e^r = 1 + r + r^2 exp_poly(r)` on `[-ln2/2, ln2/2]`.
#[inline(always)]
fn exp_poly(r: f32) -> f32 {
    let p = mul_add_f32(1.987_569_1e-4, r, 1.398_199_9e-3);
    let p = mul_add_f32(p, r, 8.333_452e-3);
    let p = mul_add_f32(p, r, 4.166_579_6e-2);
    let p = mul_add_f32(p, r, 1.666_666_5e-1);
    mul_add_f32(p, r, 5e-1)
}

/// exp(x) for f32: range reduction to [-ln2/2, ln2/2] and a degree-6 polynomial (Cephes expf).
///
/// Returns exactly 0 for x < -87.3 (including -inf), +inf above 88.37, NaN for NaN.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    // `f32::clamp` keeps NaN, and so does the rest.
    let out = exp_clamped(x.clamp(EXP_LO, EXP_HI));
    let out = if x < EXP_LO { 0.0 } else { out };
    if x > EXP_HI {
        f32::INFINITY
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
    let mut y = mul_add_f32(7.037_683_6e-2, m, -1.151_461e-1);
    for c in [1.167_699_9e-1, -1.242_014_1e-1, 1.424_932_3e-1, -1.666_805_8e-1, 2.000_071_4e-1, -2.499_999_4e-1] {
        y = mul_add_f32(y, m, c);
    }
    let mut y = mul_add_f32(y, m, 3.333_333e-1) * m * z;
    let ef = e as f32 - if tiny { 23.0 } else { 0.0 };
    y = mul_add_f32(LN2_LO, ef, y);
    y = mul_add_f32(-0.5, z, y);
    let mut out = mul_add_f32(LN2_HI, ef, m + y);
    out = if x == 0.0 { f32::NEG_INFINITY } else { out };
    out = if x == f32::INFINITY { f32::INFINITY } else { out };
    if x < 0.0 || x.is_nan() {
        f32::NAN
    } else {
        out
    }
}

/// tanh(x) for f32: Eigen's 13/6 rational approximation on [-7.9, 7.9], in fused
/// multiply-adds.
///
/// Eigen returns `x` itself below `|x| < 4e-4`; here the rational is used throughout
/// (its relative error there is below 1e-7: `p / q -> x (1 - 8e-8)`, for
/// `|x| > 1e-30`; below ~1e-36 the numerator is subnormal). The select
/// cost three operations per vector, and in an in-place loop LLVM turned it into a
/// masked store (`vmaskmovps`), which is slow on AMD.
#[inline(always)]
pub fn tanh_f32(x: f32) -> f32 {
    // Where the rational first reaches exactly 1 (it stays below 1 before): Eigen's
    // 7.905311 for separate multiplies and adds; with fused ones it gets there later.
    const CLAMP: f32 = if cfg!(target_feature = "fma") { 8.005_163 } else { 7.905_311 };
    let xc = x.clamp(-CLAMP, CLAMP);
    let x2 = xc * xc;
    let p = mul_add_f32(-2.760_768_5e-16, x2, 2.000_188e-13);
    let p = mul_add_f32(p, x2, -8.604_672e-11);
    let p = mul_add_f32(p, x2, 5.122_297e-8);
    let p = mul_add_f32(p, x2, 1.485_722_4e-5);
    let p = mul_add_f32(p, x2, 6.372_619_3e-4);
    let p = mul_add_f32(p, x2, 4.893_524_6e-3) * xc;
    let q = mul_add_f32(1.198_258_4e-6, x2, 1.185_347_1e-4);
    let q = mul_add_f32(q, x2, 2.268_434_6e-3);
    let q = mul_add_f32(q, x2, 4.893_525e-3);
    p / q
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
    let shifted = mul_add_f32(x, FRAC_2_PI, ROUND_MAGIC);
    let k = shifted - ROUND_MAGIC;
    let r = mul_add_f32(k, -PIO2_3, mul_add_f32(k, -PIO2_2, mul_add_f32(k, -PIO2_1, x)));
    let z = r * r;
    let ps = mul_add_f32(mul_add_f32(-1.951_529_6e-4, z, 8.332_161e-3), z, -1.666_665_5e-1);
    let s = mul_add_f32(ps * z, r, r);
    let pc = mul_add_f32(mul_add_f32(2.443_315_7e-5, z, -1.388_731_6e-3), z, 4.166_664_6e-2);
    let c = mul_add_f32(pc * z, z, mul_add_f32(-0.5, z, 1.0));
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
    fn exp_nonpos_matches_std_relative() {
        // Over the whole range of normal results, and finely near 0 where the
        // reduction's n changes sign.
        let mut worst = 0.0f64;
        for x in grid(-87.3, 0.0, 400_000).chain(grid(-1.0, 0.0, 100_000)) {
            let exact = (x as f64).exp();
            let rel = ((exp_nonpos_f32(x) as f64 - exact) / exact).abs();
            worst = worst.max(rel);
        }
        assert!(worst < 3e-7, "worst relative error {worst}");
        // Subnormal results just below, and exactly 0 beyond.
        for x in grid(-87.99, -87.34, 1000) {
            let (got, exact) = (exp_nonpos_f32(x) as f64, (x as f64).exp());
            assert!((got - exact).abs() < 2.0 * f32::MIN_POSITIVE as f64, "exp_nonpos({x}) = {got}");
        }
        for x in [-88.0, -88.5, -100.0, -1e30, f32::MIN, f32::NEG_INFINITY] {
            assert_eq!(exp_nonpos_f32(x), 0.0, "exp_nonpos({x})");
        }
        assert!(exp_nonpos_f32(f32::NAN).is_nan());
        assert_eq!(exp_nonpos_f32(0.0), 1.0);
        assert_eq!(exp_nonpos_f32(-0.0), 1.0);
    }

    #[test]
    fn mul_add_is_exact_or_fused() {
        // 1 + 2^-23 squared is 1 + 2^-22 + 2^-46: fused keeps the 2^-46 after
        // subtracting 1 + 2^-22, two roundings lose it. Either is a valid result.
        let a = 1.0 + f32::EPSILON;
        let got = mul_add_f32(a, a, -(1.0 + 2.0 * f32::EPSILON));
        let fused = 2f32.powi(-46);
        assert!(got == fused || got == 0.0, "{got}");
        assert_eq!(got == fused, cfg!(target_feature = "fma"));
        assert_eq!(mul_add_f64(3.0, 4.0, 5.0), 17.0);
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
            assert!(tanh_f32(x).abs() <= 1.0, "|tanh({x})| > 1");
        }
        assert!(worst < 1e-6, "worst absolute error {worst}");
        // Relative accuracy near 0 (log-spaced from 0.1 down to 1e-31; below ~1e-36
        // the numerator is subnormal and only the absolute error stays tiny), and signs.
        let mut worst_rel = 0.0f64;
        for i in 0..6_000 {
            let x = (-0.0115f64 * i as f64).exp() as f32 * 0.1;
            for x in [x, -x] {
                let exact = (x as f64).tanh();
                worst_rel = worst_rel.max(((tanh_f32(x) as f64 - exact) / exact).abs());
            }
        }
        assert!(worst_rel < 3e-7, "worst relative error near 0: {worst_rel}");
        assert_eq!(tanh_f32(0.0), 0.0);
        assert!(tanh_f32(-0.0) == 0.0 && tanh_f32(-0.0).is_sign_negative());
        assert!(tanh_f32(f32::NAN).is_nan());
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
