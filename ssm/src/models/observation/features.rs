//! The AV-relative network inputs shared by both observation models: the object's
//! box as seen from the AV, scaled to order one. Computed three ways that agree:
//! batched over particles (plain loops, feature-major), for one pose (f64), and on
//! a tape from `Var`s (the through-filter baselines differentiate with respect to
//! the particle states).
//!
//! With `d = (x - x_av, y - y_av)` the object's position relative to the AV,
//! `r = sqrt(|d|^2 + RANGE_EPS^2)` (smoothed so that it is differentiable, and never
//! zero, at `d = 0`), the 7 features are, in order:
//!
//! | # | feature | meaning |
//! |---|---|---|
//! | 0 | `r / RANGE_SCALE` | range (50 m -> 1) |
//! | 1 | `sin(bearing)` = `(d_y cos yaw_av - d_x sin yaw_av) / r` | where the object is, in the AV's frame |
//! | 2 | `cos(bearing)` = `(d_x cos yaw_av + d_y sin yaw_av) / r` | |
//! | 3 | `sin(rel)` = `(d_x sin yaw - d_y cos yaw) / r` | where the AV is, in the object's frame |
//! | 4 | `cos(rel)` = `-(d_x cos yaw + d_y sin yaw) / r` | (`cos(rel) = 1`: AV straight ahead) |
//! | 5 | `length / LENGTH_SCALE` | |
//! | 6 | `width / WIDTH_SCALE` | |
//!
//! No `atan2` is needed: sines and cosines are projections divided by the range.

use autodiff::{Float, Tape, Tensor, Var};

use super::{ObsContext, PosesRef, RowVars};
use crate::data::Pose;

/// Number of network inputs.
pub const NUM_FEATURES: usize = 7;
/// Range is fed as `r / RANGE_SCALE` (objects at 5–50 m give 0.1–1).
pub const RANGE_SCALE: f64 = 50.0;
/// Length is fed as `length / LENGTH_SCALE` (cars ~ 4.5 m give ~ 0.9).
pub const LENGTH_SCALE: f64 = 5.0;
/// Width is fed as `width / WIDTH_SCALE` (cars ~ 1.8 m give ~ 0.9).
pub const WIDTH_SCALE: f64 = 2.0;
/// Smoothing of the range (m): `r = sqrt(|d|^2 + RANGE_EPS^2)`. At the 5 m minimum
/// range of the data it changes `r` by 1e-5 relative.
pub const RANGE_EPS: f64 = 0.01;

/// The features of one pose seen from `ctx.av` (f64).
///
/// ```
/// use ssm::data::Pose;
/// use ssm::models::observation::{av_features_one, ObsContext};
/// // AV at the origin facing +x; a 5 m x 2 m object 10 m ahead, facing away.
/// let ctx = ObsContext::new(Pose { x: 0.0, y: 0.0, yaw: 0.0 }, 5.0, 2.0);
/// let f = av_features_one(&ctx, Pose { x: 10.0, y: 0.0, yaw: 0.0 });
/// assert!((f[0] - 0.2).abs() < 1e-6); // 10 m / 50
/// assert!(f[1].abs() < 1e-12 && (f[2] - 1.0).abs() < 1e-6); // straight ahead of the AV
/// assert!(f[3].abs() < 1e-12 && (f[4] + 1.0).abs() < 1e-6); // the AV is behind the object
/// assert_eq!((f[5], f[6]), (1.0, 1.0));
/// ```
pub fn av_features_one(ctx: &ObsContext, pose: Pose) -> [f64; NUM_FEATURES] {
    let (c, s) = (pose.yaw.cos(), pose.yaw.sin());
    let mut out = [0.0; NUM_FEATURES];
    features_with_trig(ctx, PosesRef::new(&[pose.x], &[pose.y], &[pose.yaw]), &[c], &[s], &mut out);
    out
}

/// The features of `n` poses, feature-major: feature `k` of pose `i` is
/// `out[k * n + i]` (`out` has length `7 n`).
#[track_caller]
pub fn av_features<F: Float>(ctx: &ObsContext, poses: PosesRef<'_, F>, out: &mut [F]) {
    let n = poses.len();
    assert_eq!(out.len(), NUM_FEATURES * n, "av_features: {n} poses need {} outputs, got {}", 7 * n, out.len());
    let cos: Vec<F> = poses.yaw.iter().map(|&a| a.cos()).collect();
    let sin: Vec<F> = poses.yaw.iter().map(|&a| a.sin()).collect();
    features_with_trig(ctx, poses, &cos, &sin, out);
}

/// [`av_features`] with the headings' cosines and sines given (the hot path has them).
#[track_caller]
#[allow(clippy::needless_range_loop)] // index loops over resliced arrays vectorise
pub(crate) fn features_with_trig<F: Float>(
    ctx: &ObsContext,
    poses: PosesRef<'_, F>,
    cos: &[F],
    sin: &[F],
    out: &mut [F],
) {
    let n = poses.len();
    assert!(
        cos.len() == n && sin.len() == n && out.len() == NUM_FEATURES * n,
        "features: {n} poses, {} cosines, {} sines, room for {} features",
        cos.len(),
        sin.len(),
        out.len()
    );
    let f = F::from_f64;
    let (ax, ay) = (f(ctx.av.x), f(ctx.av.y));
    let (ca, sa) = (f(ctx.av.yaw.cos()), f(ctx.av.yaw.sin()));
    let eps2 = f(RANGE_EPS * RANGE_EPS);
    let inv_range_scale = f(1.0 / RANGE_SCALE);
    let lf = f(ctx.length / LENGTH_SCALE);
    let wf = f(ctx.width / WIDTH_SCALE);
    let (xs, ys, cs, ss) = (&poses.x[..n], &poses.y[..n], &cos[..n], &sin[..n]);
    let (o0, rest) = out.split_at_mut(n);
    let (o1, rest) = rest.split_at_mut(n);
    let (o2, rest) = rest.split_at_mut(n);
    let (o3, rest) = rest.split_at_mut(n);
    let (o4, rest) = rest.split_at_mut(n);
    let (o5, o6) = rest.split_at_mut(n);
    for i in 0..n {
        let dx = xs[i] - ax;
        let dy = ys[i] - ay;
        let r = (dx * dx + dy * dy + eps2).sqrt();
        let inv_r = F::ONE / r;
        o0[i] = r * inv_range_scale;
        o1[i] = (dy * ca - dx * sa) * inv_r;
        o2[i] = (dx * ca + dy * sa) * inv_r;
        o3[i] = (dx * ss[i] - dy * cs[i]) * inv_r;
        o4[i] = -(dx * cs[i] + dy * ss[i]) * inv_r;
        o5[i] = lf;
        o6[i] = wf;
    }
}

/// The features of tape rows (`[R, 7]`), differentiable in the rows' `x, y, yaw,
/// length, width`, with the AV pose of each row in `av` (constants): one fused
/// node ([`Tape::precomputed`]) whose values are those of the features composed
/// from element-wise tape ops (`inv_r` as `q^-1/2`, `r` as `sqrt(q)`, `q = |d|^2 +
/// RANGE_EPS^2`) and whose partials are computed with them.
#[track_caller]
pub fn av_features_on_tape<'t, F: Float>(rows: &RowVars<'t, F>, av: &[Pose]) -> Var<'t, F> {
    let r = rows.check(av.len(), av.len(), "av_features_on_tape");
    let tape: &'t Tape<F> = rows.x.tape();
    let f = F::from_f64;
    let (eps2, inv_range_scale, minus_half) = (f(RANGE_EPS * RANGE_EPS), f(1.0 / RANGE_SCALE), f(-0.5));
    // Every element is written below.
    let mut value = tape.buffer(r * NUM_FEATURES);
    // d value / d (x, y, yaw), row-major like the value.
    let mut partials: [Vec<F>; 3] = std::array::from_fn(|_| tape.buffer(r * NUM_FEATURES));
    {
        let (xs, ys, yaws) = (rows.x.value(), rows.y.value(), rows.yaw.value());
        let (ls, ws) = (rows.length.value(), rows.width.value());
        let [gx, gy, gyaw] = &mut partials;
        for (i, p) in av.iter().enumerate() {
            let (ca, sa) = (f(p.yaw.cos()), f(p.yaw.sin()));
            let dx = xs.data()[i] - f(p.x);
            let dy = ys.data()[i] - f(p.y);
            let q = dx * dx + dy * dy + eps2;
            let inv_r = q.powf(minus_half);
            let (cy, sy) = (yaws.data()[i].cos(), yaws.data()[i].sin());
            let u = [dy * ca - dx * sa, dx * ca + dy * sa, dx * sy - dy * cy, dx * cy + dy * sy];
            let row = i * NUM_FEATURES..(i + 1) * NUM_FEATURES;
            value[row.clone()].copy_from_slice(&[
                q.sqrt() * inv_range_scale,
                u[0] * inv_r,
                u[1] * inv_r,
                u[2] * inv_r,
                -(u[3] * inv_r),
                ls.data()[i] * f(1.0 / LENGTH_SCALE),
                ws.data()[i] * f(1.0 / WIDTH_SCALE),
            ]);
            // d inv_r / d(dx, dy) = -(dx, dy) inv_r^3.
            let ir3 = inv_r * inv_r * inv_r;
            let (ex, ey) = (dx * ir3, dy * ir3);
            gx[row.clone()].copy_from_slice(&[
                dx * inv_r * inv_range_scale,
                -sa * inv_r - u[0] * ex,
                ca * inv_r - u[1] * ex,
                sy * inv_r - u[2] * ex,
                -(cy * inv_r - u[3] * ex),
                F::ZERO,
                F::ZERO,
            ]);
            gy[row.clone()].copy_from_slice(&[
                dy * inv_r * inv_range_scale,
                ca * inv_r - u[0] * ey,
                sa * inv_r - u[1] * ey,
                -cy * inv_r - u[2] * ey,
                -(sy * inv_r - u[3] * ey),
                F::ZERO,
                F::ZERO,
            ]);
            gyaw[row].copy_from_slice(&[F::ZERO, F::ZERO, F::ZERO, u[3] * inv_r, u[2] * inv_r, F::ZERO, F::ZERO]);
        }
    }
    // Each row's inputs as a column [R, 1]: it broadcasts along the row's features.
    let column = |v: Var<'t, F>| v.reshape(&[r, 1]);
    let shape = [r, NUM_FEATURES];
    let [gx, gy, gyaw] = partials;
    let mut inputs = vec![
        (column(rows.x), Tensor::new(&shape, gx)),
        (column(rows.y), Tensor::new(&shape, gy)),
        (column(rows.yaw), Tensor::new(&shape, gyaw)),
    ];
    for (v, k, scale) in [(rows.length, 5, LENGTH_SCALE), (rows.width, 6, WIDTH_SCALE)] {
        if v.is_tracked() {
            let mut g = tape.buffer(r * NUM_FEATURES);
            g.fill(F::ZERO);
            g.iter_mut().skip(k).step_by(NUM_FEATURES).for_each(|g| *g = f(1.0 / scale));
            inputs.push((column(v), Tensor::new(&shape, g)));
        }
    }
    tape.precomputed(Tensor::new(&shape, value), inputs)
}
