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

/// Implements `Float` methods of the form `fn name(self) -> Self` by calling a
/// function of one argument: `unary_float_fns!(exp => f64::exp, ...)`.
macro_rules! unary_float_fns {
    ($($name:ident => $f:expr),* $(,)?) => {
        $(
            #[inline(always)]
            fn $name(self) -> Self {
                $f(self)
            }
        )*
    };
}

/// `unary_float_fns` for methods of the form `fn name(self, other: Self) -> Self`.
macro_rules! binary_float_fns {
    ($($name:ident => $f:expr),* $(,)?) => {
        $(
            #[inline(always)]
            fn $name(self, other: Self) -> Self {
                $f(self, other)
            }
        )*
    };
}

/// The `Float` items that `f32` and `f64` implement alike: constants, `std`'s exact
/// functions, `mul_add` by `$mul_add` and the GEMM `$gemm`.
macro_rules! common_float_impl {
    ($t:ty, $gemm:path, $mul_add:path) => {
        const ZERO: Self = 0.0;
        const ONE: Self = 1.0;
        const INFINITY: Self = <$t>::INFINITY;
        const NEG_INFINITY: Self = <$t>::NEG_INFINITY;
        const EPSILON: Self = <$t>::EPSILON;
        const NAME: &'static str = stringify!($t);

        unary_float_fns!(ln_1p => <$t>::ln_1p, sqrt => <$t>::sqrt, abs => <$t>::abs);
        binary_float_fns!(powf => <$t>::powf, atan2 => <$t>::atan2, max => <$t>::max, min => <$t>::min);

        #[inline(always)]
        fn mul_add(self, a: Self, b: Self) -> Self {
            $mul_add(self, a, b)
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
    common_float_impl!(f64, matrixmultiply::dgemm, fastmath::mul_add_f64);
    unary_float_fns!(
        exp => f64::exp,
        exp_nonpos => f64::exp,
        ln => f64::ln,
        tanh => f64::tanh,
        sin => f64::sin,
        cos => f64::cos,
    );

    #[inline(always)]
    fn from_f64(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
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
    common_float_impl!(f32, matrixmultiply::sgemm, fastmath::mul_add_f32);
    unary_float_fns!(
        exp => fastmath::exp_f32,
        exp_nonpos => fastmath::exp_nonpos_f32,
        ln => fastmath::ln_f32,
        tanh => fastmath::tanh_f32,
        sin => fastmath::sin_f32,
        cos => fastmath::cos_f32,
        softplus => fastmath::softplus_f32,
        sigmoid => fastmath::sigmoid_f32,
    );

    #[inline(always)]
    fn from_f64(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self as f64
    }
}
