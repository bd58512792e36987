//! The geometry of the point model: the box frame, the 4 edges, a point's edge
//! coordinates, and the soft uniform density along an edge.
//!
//! The box frame has `u` along the heading and `v` to the left, origin at the box
//! centre; `hl = length / 2`, `hw = width / 2`. The edges run counter-clockwise:
//!
//! | e | edge | length | `alpha` (along, from its first corner) | `beta` (outward) |
//! |---|---|---|---|---|
//! | 0 | front | `w` | `v + hw` | `u - hl` |
//! | 1 | left | `l` | `hl - u` | `v - hw` |
//! | 2 | rear | `w` | `hw - v` | `-u - hl` |
//! | 3 | right | `l` | `u + hl` | `-v - hw` |
//!
//! Each map `(u, v) -> (alpha_e, beta_e)` is a rigid motion, so a density over
//! `(alpha_e, beta_e)` is a density over the plane.
//!
//! The soft uniform `U_soft(alpha; 0, L)` is `Uniform(0, L)` convolved with a
//! zero-mean Laplace of scale `s`. With `F_s` the Laplace CDF,
//! `U_soft(a) = (F_s(a) - F_s(a - L)) / L`, which gives in closed form
//!
//! ```text
//! a < 0:       U_soft = e^{ a/s}      (1 - e^{-L/s}) / (2L)
//! a > L:       U_soft = e^{-(a-L)/s}  (1 - e^{-L/s}) / (2L)
//! 0 <= a <= L: U_soft = (1 - e^{-a/s}/2 - e^{-(L-a)/s}/2) / L
//! ```
//!
//! Outside the edge the log-density is linear in the distance `m = min(a, L - a)`,
//! `log U_soft = m/s + ln((1 - e^{-L/s})/2) - ln L`, so it is finite for any finite
//! `a` (at `a = 1e4` m it is about `-2e5`); inside, the argument of the log lies in
//! `[(1 - e^{-L/s})/2, 1)`. The two pieces meet with equal values and slopes.

use rand::Rng;
use rand_distr::Exp1;

use crate::data::Pose;

/// Number of edges of a box.
pub const NUM_EDGES: usize = 4;
/// Edge index of the front (length `w`).
pub const FRONT: usize = 0;
/// Edge index of the left side (length `l`).
pub const LEFT: usize = 1;
/// Edge index of the rear (length `w`).
pub const REAR: usize = 2;
/// Edge index of the right side (length `l`).
pub const RIGHT: usize = 3;
/// Default Laplace scale (m) of the soft uniform along an edge (SPEC §3).
pub const DEFAULT_SOFT_SCALE: f64 = 0.05;

/// The lengths of edges 0..4: `[w, l, w, l]`.
pub fn edge_lengths(length: f64, width: f64) -> [f64; NUM_EDGES] {
    [width, length, width, length]
}

/// A world point in the box frame of `pose`: `(u, v)`.
pub fn to_box_frame(pose: Pose, p: [f64; 2]) -> (f64, f64) {
    let (c, s) = (pose.yaw.cos(), pose.yaw.sin());
    let (dx, dy) = (p[0] - pose.x, p[1] - pose.y);
    (c * dx + s * dy, c * dy - s * dx)
}

/// The world point at `(u, v)` in the box frame of `pose`.
pub fn from_box_frame(pose: Pose, u: f64, v: f64) -> [f64; 2] {
    let (c, s) = (pose.yaw.cos(), pose.yaw.sin());
    [pose.x + c * u - s * v, pose.y + s * u + c * v]
}

/// The edge coordinates `(alpha_e, beta_e)` of the box-frame point `(u, v)` for the
/// 4 edges (see the module table).
///
/// ```
/// use ssm::models::observation::edges::{edge_coords, edge_point};
/// let (hl, hw) = (2.0, 1.0);
/// let c = edge_coords(2.5, 0.0, hl, hw);
/// assert_eq!(c[0], (1.0, 0.5)); // half way along the front, 0.5 m out
/// for e in 0..4 {
///     let (u, v) = edge_point(e, c[e].0, c[e].1, hl, hw);
///     assert!((u - 2.5).abs() < 1e-12 && v.abs() < 1e-12);
/// }
/// ```
pub fn edge_coords(u: f64, v: f64, hl: f64, hw: f64) -> [(f64, f64); NUM_EDGES] {
    [(v + hw, u - hl), (hl - u, v - hw), (hw - v, -u - hl), (u + hl, -v - hw)]
}

/// The box-frame point `(u, v)` whose coordinates on edge `e` are `(alpha, beta)`.
#[track_caller]
pub fn edge_point(e: usize, alpha: f64, beta: f64, hl: f64, hw: f64) -> (f64, f64) {
    match e {
        FRONT => (hl + beta, alpha - hw),
        LEFT => (hl - alpha, hw + beta),
        REAR => (-hl - beta, hw - alpha),
        RIGHT => (alpha - hl, -hw - beta),
        _ => panic!("edge_point: edge {e} out of range 0..4"),
    }
}

/// `ln((1 - e^{-L/s}) / 2)`: the log-density offset just outside an edge (without
/// the `-ln L`), accurate for small `L/s`.
fn tail_offset(len: f64, scale: f64) -> f64 {
    (-(-len / scale).exp_m1()).ln() - std::f64::consts::LN_2
}

/// `log U_soft(alpha; 0, len)` with Laplace scale `scale`, in f64 (the reference
/// that the fast kernels are tested against). Finite for every finite `alpha` and
/// positive `len`, `scale`.
///
/// ```
/// use ssm::models::observation::edges::log_soft_uniform;
/// // Deep inside an edge it is the uniform density 1 / len.
/// assert!((log_soft_uniform(2.0, 4.0, 0.05) + 4.0f64.ln()).abs() < 1e-12);
/// // Far outside it is linear in the distance, never -inf.
/// assert!((log_soft_uniform(-1e4, 4.0, 0.05) + 2e5).abs() < 10.0);
/// ```
pub fn log_soft_uniform(alpha: f64, len: f64, scale: f64) -> f64 {
    let m = alpha.min(len - alpha);
    if m < 0.0 {
        m / scale + tail_offset(len, scale) - len.ln()
    } else {
        let inside = 1.0 - 0.5 * (-alpha / scale).exp() - 0.5 * (-(len - alpha) / scale).exp();
        inside.ln() - len.ln()
    }
}

/// Draws from `U_soft(.; 0, len)` with Laplace scale `scale`: a uniform position
/// plus Laplace noise (a difference of two exponentials).
pub fn sample_soft_uniform<R: Rng + ?Sized>(len: f64, scale: f64, rng: &mut R) -> f64 {
    let e1: f64 = rng.sample(Exp1);
    let e2: f64 = rng.sample(Exp1);
    rng.random::<f64>() * len + scale * (e1 - e2)
}

/// Draws from `Laplace(mu, b)`.
pub fn sample_laplace<R: Rng + ?Sized>(mu: f64, b: f64, rng: &mut R) -> f64 {
    let e1: f64 = rng.sample(Exp1);
    let e2: f64 = rng.sample(Exp1);
    mu + b * (e1 - e2)
}

/// Per-edge-length constants of the soft uniform used by the kernels (computed in
/// f64, stored in the kernel's float type).
#[derive(Clone, Copy, Debug)]
pub(crate) struct SoftConsts<F> {
    /// `L`.
    pub len: F,
    /// `1 / s`.
    pub inv_s: F,
    /// `e^{-L/s}`, flushed to 0 below [`FLUSH_EXP_NEG`].
    pub exp_neg: F,
    /// `ln((1 - e^{-L/s}) / 2)`: added to `m / s` outside the edge.
    pub tail: F,
    /// `ln L`.
    pub ln_len: F,
    /// `d tail / dL = e^{-L/s} / (s (1 - e^{-L/s}))`.
    pub dtail_dlen: F,
    /// `1 / L`.
    pub inv_len: F,
}

/// `e^{-L/s}` is stored as 0 when it is below `FLUSH_EXP_NEG` or `epsilon^2` of the
/// kernel's float type. The kernels use `e_far = e^{-L/s} / e_near` only inside the
/// edge, where `e_far <= sqrt(e^{-L/s})` (the far end is at least `L/2` away) and it
/// enters `U_soft` through `1 - (e_near + e_far)/2 >= 1/2`: flushing changes
/// `U_soft` by less than one rounding error. For f32 this drops `e_far` for every
/// edge longer than `32 s` (1.6 m at the default scale), so the hot kernel runs
/// without divisions; and it keeps subnormals (`e^{-88}` for a 4.4 m edge), which
/// cost a microcode assist per operation, out of the kernels.
pub(crate) const FLUSH_EXP_NEG: f64 = 1e-30;

impl<F: autodiff::Float> SoftConsts<F> {
    pub fn new(len: f64, scale: f64) -> Self {
        let e = (-len / scale).exp();
        let eps = F::EPSILON.to_f64();
        let e_flushed = if e < FLUSH_EXP_NEG.max(eps * eps) { 0.0 } else { e };
        let one_minus = -(-len / scale).exp_m1();
        let f = F::from_f64;
        SoftConsts {
            len: f(len),
            inv_s: f(1.0 / scale),
            exp_neg: f(e_flushed),
            tail: f(tail_offset(len, scale)),
            ln_len: f(len.ln()),
            dtail_dlen: f(e / (scale * one_minus)),
            inv_len: f(1.0 / len),
        }
    }
}
