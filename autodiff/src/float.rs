//! The element type of tensors: a small float trait implemented for `f32` and `f64`.
//!
//! `f64` uses `std`'s correctly rounded functions (gradient checks run in f64);
//! `f32` is the hot-path type and uses the vectorisable kernels of [`crate::fastmath`].

use std::fmt::{Debug, Display};
use std::iter::Sum;
use std::ops::{Add, AddAssign, Div, DivAssign, Mul, MulAssign, Neg, Sub, SubAssign};

use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::fastmath;

/// A floating-point element type: `f32` (fast) or `f64` (exact checks).
pub trait Float:
    Copy
    + Send
    + Sync
    + Default
    + Debug
    + Display
    + PartialEq
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + SubAssign
    + MulAssign
    + DivAssign
    + Sum
    + Serialize
    + DeserializeOwned
    + 'static
{
    /// 0.
    const ZERO: Self;
    /// 1.
    const ONE: Self;
    /// +infinity.
    const INFINITY: Self;
    /// -infinity.
    const NEG_INFINITY: Self;
    /// Machine epsilon.
    const EPSILON: Self;
    /// Name of the type, for messages.
    const NAME: &'static str;

    /// Converts from f64 (rounding for f32).
    fn from_f64(x: f64) -> Self;
    /// Converts to f64 (exactly).
    fn to_f64(self) -> f64;
    /// Converts from usize.
    fn from_usize(n: usize) -> Self {
        Self::from_f64(n as f64)
    }

    /// e^x.
    fn exp(self) -> Self;
    /// e^x for `x <= 0` (and `-inf`), for log-sum-exp kernels whose arguments are
    /// shifted by their maximum: cheaper than [`Float::exp`] for f32
    /// ([`fastmath::exp_nonpos_f32`]: exactly 0 below -88, subnormal results just
    /// above); `exp` itself for f64. Positive `x` give unspecified values.
    fn exp_nonpos(self) -> Self;
    /// `self * a + b`, fused (one instruction, one rounding) when the build targets
    /// FMA, else a multiply and an add ([`fastmath::mul_add_f32`]): for speed,
    /// results differ between the two at rounding level.
    fn mul_add(self, a: Self, b: Self) -> Self;
    /// Natural logarithm.
    fn ln(self) -> Self;
    /// ln(1 + x), accurate near 0.
    fn ln_1p(self) -> Self;
    /// Hyperbolic tangent.
    fn tanh(self) -> Self;
    /// ln(1 + e^x), stable for large |x|.
    fn softplus(self) -> Self;
    /// 1 / (1 + e^-x), stable for large |x|.
    fn sigmoid(self) -> Self;
    /// Sine.
    fn sin(self) -> Self;
    /// Cosine.
    fn cos(self) -> Self;
    /// Square root.
    fn sqrt(self) -> Self;
    /// Absolute value.
    fn abs(self) -> Self;
    /// x^p.
    fn powf(self, p: Self) -> Self;
    /// Four-quadrant arctangent of self (y) and x.
    fn atan2(self, x: Self) -> Self;
    /// Larger of two values (NaN-ignoring as `f64::max`).
    fn max(self, other: Self) -> Self;
    /// Smaller of two values.
    fn min(self, other: Self) -> Self;
    /// Whether the value is neither infinite nor NaN.
    fn is_finite(self) -> bool;
    /// Whether the value is NaN.
    fn is_nan(self) -> bool;

    /// General matrix multiply `C = alpha A B + beta C` with arbitrary strides
    /// (single-threaded; callers split rows across threads).
    ///
    /// # Safety
    /// The pointers and strides must describe valid `m x k`, `k x n` and `m x n`
    /// matrices; `c` must not alias `a` or `b`.
    #[allow(clippy::too_many_arguments)]
    unsafe fn gemm(
        m: usize,
        k: usize,
        n: usize,
        alpha: Self,
        a: *const Self,
        rsa: isize,
        csa: isize,
        b: *const Self,
        rsb: isize,
        csb: isize,
        beta: Self,
        c: *mut Self,
        rsc: isize,
        csc: isize,
    );
}

macro_rules! common_float_impl {
    ($t:ty, $gemm:path) => {
        const ZERO: Self = 0.0;
        const ONE: Self = 1.0;
        const INFINITY: Self = <$t>::INFINITY;
        const NEG_INFINITY: Self = <$t>::NEG_INFINITY;
        const EPSILON: Self = <$t>::EPSILON;
        const NAME: &'static str = stringify!($t);

        #[inline(always)]
        fn ln_1p(self) -> Self {
            <$t>::ln_1p(self)
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            <$t>::sqrt(self)
        }
        #[inline(always)]
        fn abs(self) -> Self {
            <$t>::abs(self)
        }
        #[inline(always)]
        fn powf(self, p: Self) -> Self {
            <$t>::powf(self, p)
        }
        #[inline(always)]
        fn atan2(self, x: Self) -> Self {
            <$t>::atan2(self, x)
        }
        #[inline(always)]
        fn max(self, other: Self) -> Self {
            <$t>::max(self, other)
        }
        #[inline(always)]
        fn min(self, other: Self) -> Self {
            <$t>::min(self, other)
        }
        #[inline(always)]
        fn is_finite(self) -> bool {
            <$t>::is_finite(self)
        }
        #[inline(always)]
        fn is_nan(self) -> bool {
            <$t>::is_nan(self)
        }
        #[inline(always)]
        unsafe fn gemm(
            m: usize,
            k: usize,
            n: usize,
            alpha: Self,
            a: *const Self,
            rsa: isize,
            csa: isize,
            b: *const Self,
            rsb: isize,
            csb: isize,
            beta: Self,
            c: *mut Self,
            rsc: isize,
            csc: isize,
        ) {
            $gemm(m, k, n, alpha, a, rsa, csa, b, rsb, csb, beta, c, rsc, csc)
        }
    };
}

impl Float for f64 {
    common_float_impl!(f64, matrixmultiply::dgemm);

    #[inline(always)]
    fn from_f64(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
    }
    #[inline(always)]
    fn exp(self) -> Self {
        f64::exp(self)
    }
    #[inline(always)]
    fn exp_nonpos(self) -> Self {
        f64::exp(self)
    }
    #[inline(always)]
    fn mul_add(self, a: Self, b: Self) -> Self {
        fastmath::mul_add_f64(self, a, b)
    }
    #[inline(always)]
    fn ln(self) -> Self {
        f64::ln(self)
    }
    #[inline(always)]
    fn tanh(self) -> Self {
        f64::tanh(self)
    }
    #[inline(always)]
    fn sin(self) -> Self {
        f64::sin(self)
    }
    #[inline(always)]
    fn cos(self) -> Self {
        f64::cos(self)
    }
    #[inline(always)]
    fn softplus(self) -> Self {
        self.max(0.0) + (-self.abs()).exp().ln_1p()
    }
    #[inline(always)]
    fn sigmoid(self) -> Self {
        let e = (-self.abs()).exp();
        let s = 1.0 / (1.0 + e);
        if self >= 0.0 {
            s
        } else {
            e * s
        }
    }
}

impl Float for f32 {
    common_float_impl!(f32, matrixmultiply::sgemm);

    #[inline(always)]
    fn from_f64(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline(always)]
    fn exp(self) -> Self {
        fastmath::exp_f32(self)
    }
    #[inline(always)]
    fn exp_nonpos(self) -> Self {
        fastmath::exp_nonpos_f32(self)
    }
    #[inline(always)]
    fn mul_add(self, a: Self, b: Self) -> Self {
        fastmath::mul_add_f32(self, a, b)
    }
    #[inline(always)]
    fn ln(self) -> Self {
        fastmath::ln_f32(self)
    }
    #[inline(always)]
    fn tanh(self) -> Self {
        fastmath::tanh_f32(self)
    }
    #[inline(always)]
    fn sin(self) -> Self {
        fastmath::sin_f32(self)
    }
    #[inline(always)]
    fn cos(self) -> Self {
        fastmath::cos_f32(self)
    }
    #[inline(always)]
    fn softplus(self) -> Self {
        fastmath::softplus_f32(self)
    }
    #[inline(always)]
    fn sigmoid(self) -> Self {
        fastmath::sigmoid_f32(self)
    }
}
