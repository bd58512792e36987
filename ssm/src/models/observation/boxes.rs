//! The box-detection observation model (SPEC §3): each observation is at most one
//! detected box (centre and yaw; its length, width and score are not modelled).
//! Given the state, the detection's centre offset from the state's position,
//! expressed along and across the line of sight from the AV, and its wrapped yaw
//! offset are independent:
//!
//! ```text
//! g(det | x) = Laplace(along; mu_a, b_a) Laplace(across; mu_c, b_c) WL(wrap(yaw_det - yaw - mu_y); b_y)
//! ```
//!
//! with the 6 parameters the outputs `o` of a network `7 -> 16 tanh x 2 -> 6` over
//! the AV-relative features: `mu_a = BOX_OFFSET_SCALE o0`, `mu_c = BOX_OFFSET_SCALE o1`,
//! `b_a, b_c = BOX_SCALE_SCALE softplus(o2, o3) + BOX_MIN_SCALE`,
//! `mu_y = BOX_YAW_OFFSET_SCALE o4`, `b_y = BOX_YAW_SCALE_SCALE softplus(o5) + BOX_MIN_YAW_SCALE`.
//!
//! A **centred** model ([`DetectionOffsets::Zero`], a network `7 -> 16 tanh x 2 -> 4`
//! without the outputs `o0, o1`) fixes `mu_a = mu_c = 0`: the detector is taken to be
//! unbiased in position. With learned offsets, shifting every state of a track by a
//! constant along and across the line of sight and the offsets by the opposite leaves
//! every detection's density unchanged, so from detections alone the offsets are
//! pinned only by the prior on `x_0`; centring removes that direction. The layout
//! tells the two apart in a parameter file (the last layer's width).
//!
//! `WL` is the wrapped Laplace on `(-pi, pi]`, in closed form
//! `WL(d; b) = cosh((pi - |d|) / b) / (2 b sinh(pi / b))`, computed as
//! `-|d|/b - ln(2b) + ln(1 + e^{-2(pi - |d|)/b}) - ln(1 - e^{-2 pi / b})` (a Laplace for
//! small `b`, uniform for large `b`, finite everywhere).
//!
//! The line of sight is the unit vector from the AV to the state's position
//! (normalised with a 1e-6 m guard, so an object at the AV gives a finite density).
//!
//! Both plain paths and the sampler live here; the tape path is composed from
//! engine ops over the (row, detection) pairs with `gather` and `scatter_add` (a
//! row has at most one detection, so the tape stays `O(R)`).

use std::f64::consts::{PI, TAU};

use autodiff::nn::{Activation, BoundParams, Mlp, ParamStore};
use autodiff::{Float, Tensor, Var};
use rand::Rng;
use serde::{Deserialize, Serialize};

use super::edges::sample_laplace;
use super::features::{av_features_on_tape, NUM_FEATURES};
use super::{detection_items, fit_len, net, ObsContext, ObservationModel, PosesRef, RowVars, Scratch};
use crate::data::{BoxDetection, Dataset, ObservationKind, Pose};
use crate::util::angles::wrap_angle;

/// Widths of the box network, input first.
pub const BOX_NET_LAYERS: [usize; 4] = [NUM_FEATURES, 16, 16, 6];
/// Widths of the centred box network ([`DetectionOffsets::Zero`]): no offset outputs.
pub const CENTRED_BOX_NET_LAYERS: [usize; 4] = [NUM_FEATURES, 16, 16, 4];

/// Whether the box model learns the detection centre's mean offset from the state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DetectionOffsets {
    /// Mean offsets along and across the line of sight from the network (the paper's model).
    #[default]
    Learned,
    /// Mean offsets fixed at zero: the detection is centred on the state (see the module docs).
    Zero,
}
/// Centre-offset means are `BOX_OFFSET_SCALE * o` (m).
pub const BOX_OFFSET_SCALE: f64 = 0.5;
/// Centre-offset scales are `BOX_SCALE_SCALE * softplus(o) + BOX_MIN_SCALE` (m).
pub const BOX_SCALE_SCALE: f64 = 0.5;
/// Floor of the centre-offset scales (m).
pub const BOX_MIN_SCALE: f64 = 0.02;
/// The yaw-offset mean is `BOX_YAW_OFFSET_SCALE * o4` (rad).
pub const BOX_YAW_OFFSET_SCALE: f64 = 0.1;
/// The yaw-offset scale is `BOX_YAW_SCALE_SCALE * softplus(o5) + BOX_MIN_YAW_SCALE` (rad).
pub const BOX_YAW_SCALE_SCALE: f64 = 0.1;
/// Floor of the yaw-offset scale (rad).
pub const BOX_MIN_YAW_SCALE: f64 = 0.005;
/// Guard of the line-of-sight normalisation (m).
pub(crate) const LOS_EPS: f64 = 1e-6;
/// Rows of the per-particle head in the plain path: `mu_a, mu_c, 1/b_a, 1/b_c, mu_y,
/// 1/b_y` and the constant part of the log-density.
const HEAD_ROWS: usize = 7;

/// The detection distribution at one state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DetectionDistribution {
    /// Mean centre offset along the line of sight (m).
    pub mu_along: f64,
    /// Mean centre offset across the line of sight (m, positive to the left).
    pub mu_across: f64,
    /// Laplace scale along (m).
    pub b_along: f64,
    /// Laplace scale across (m).
    pub b_across: f64,
    /// Mean yaw offset (rad).
    pub mu_yaw: f64,
    /// Wrapped-Laplace scale of the yaw offset (rad).
    pub b_yaw: f64,
}

/// The three independent factors of `log g(det | x)`: the centre offset along and
/// across the line of sight and the wrapped yaw offset (nats; they sum to the
/// model's log-density). AOTLL split into them says which part of a detector's
/// error a network gets wrong.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DetectionTerms {
    /// `log Laplace(along; mu_a, b_a)`.
    pub along: f64,
    /// `log Laplace(across; mu_c, b_c)`.
    pub across: f64,
    /// `log WL(wrap(yaw_det - yaw - mu_y); b_y)`.
    pub yaw: f64,
    /// The offsets from the means: `(along - mu_a, across - mu_c, wrap(yaw_det - yaw - mu_y))`.
    pub residuals: (f64, f64, f64),
}

impl DetectionTerms {
    /// `log g(det | x)`.
    pub fn total(&self) -> f64 {
        self.along + self.across + self.yaw
    }
}

impl DetectionDistribution {
    /// The factors of `log g(det | pose)` for an AV at `av`, this being the
    /// distribution at `pose` ([`BoxObservationModel::distribution`]); the same
    /// closed forms as the filter's kernel.
    pub fn log_density_terms(&self, av: &Pose, pose: Pose, det: &BoxDetection) -> DetectionTerms {
        let (along, across) = los_offsets(pose.x - av.x, pose.y - av.y, det.x - pose.x, det.y - pose.y);
        let laplace = |x: f64, mu: f64, b: f64| -(x - mu).abs() / b - (2.0 * b).ln();
        let dyaw = wrap(det.yaw - pose.yaw - self.mu_yaw);
        let yaw = with_wrapped_laplace_shape(with_wrapped_laplace_norm(0.0, self.b_yaw), dyaw.abs(), 1.0 / self.b_yaw);
        DetectionTerms {
            along: laplace(along, self.mu_along, self.b_along),
            across: laplace(across, self.mu_across, self.b_across),
            yaw,
            residuals: (along - self.mu_along, across - self.mu_across, dyaw),
        }
    }
}

/// `ln(1 - e^{-z})` for `z > 0`, accurate for small `z`.
#[inline(always)]
fn ln_one_minus_exp_neg<F: Float>(z: F) -> F {
    if z < F::from_f64(1e-3) {
        // ln(1 - e^{-z}) = ln z - z/2 + z^2/24 - ...
        z.ln() - F::from_f64(0.5) * z
    } else {
        (F::ONE - (-z).exp()).ln()
    }
}

/// `acc` plus the normalising part of the wrapped Laplace's log-density at scale
/// `b`, `-ln(2b) - ln(1 - e^{-2 pi / b})`, added in that order (the plain kernel's
/// per-particle constant and [`DetectionDistribution::log_density_terms`] share it).
#[inline(always)]
fn with_wrapped_laplace_norm<F: Float>(acc: F, b: F) -> F {
    acc - (F::from_f64(2.0) * b).ln() - ln_one_minus_exp_neg(F::from_f64(TAU) / b)
}

/// `acc` plus the part of the wrapped Laplace's log-density that depends on the
/// wrapped offset `a = |d|`, `-a/b + softplus(2 (a - pi) / b)`, with `inv_b = 1/b`.
#[inline(always)]
fn with_wrapped_laplace_shape<F: Float>(acc: F, a: F, inv_b: F) -> F {
    acc - a * inv_b + (F::from_f64(2.0) * (a - F::from_f64(PI)) * inv_b).softplus()
}

/// `x` rounded to the nearest integer (|x| < 2^22 for f32), without branches: adding
/// and subtracting 1.5 / epsilon rounds in the float's own precision.
#[inline(always)]
fn round_nearest<F: Float>(x: F) -> F {
    let magic = F::from_f64(1.5) / F::EPSILON;
    (x + magic) - magic
}

/// `a` wrapped to `[-pi, pi]`. Beyond the range where [`round_nearest`] is exact
/// (|a| > 2^22 * 2 pi in f32, where the angle has no meaningful residue anyway) the
/// result is clamped, so the density stays bounded for diverged states.
#[inline(always)]
fn wrap<F: Float>(a: F) -> F {
    let pi = F::from_f64(PI);
    (a - F::from_f64(TAU) * round_nearest(a * F::from_f64(1.0 / TAU))).max(-pi).min(pi)
}

/// Along- and across-line-of-sight offsets of `(ddx, ddy)` for an object at
/// `(dx, dy)` from the AV.
#[inline(always)]
pub(crate) fn los_offsets<F: Float>(dx: F, dy: F, ddx: F, ddy: F) -> (F, F) {
    let inv = F::ONE / (dx * dx + dy * dy + F::from_f64(LOS_EPS * LOS_EPS)).sqrt();
    let (lx, ly) = (dx * inv, dy * inv);
    (ddx * lx + ddy * ly, ddy * lx - ddx * ly)
}

/// The box-detection observation model: a layout (the network's parameter ids).
/// See the [module docs](self).
#[derive(Clone, Debug, PartialEq)]
pub struct BoxObservationModel {
    mlp: Mlp,
    offsets: DetectionOffsets,
}

impl std::fmt::Display for DetectionOffsets {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            DetectionOffsets::Learned => "learned",
            DetectionOffsets::Zero => "zero",
        })
    }
}

impl std::str::FromStr for DetectionOffsets {
    type Err = String;
    /// `learned` or `zero`.
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "learned" => Ok(DetectionOffsets::Learned),
            "zero" => Ok(DetectionOffsets::Zero),
            other => Err(format!("detection offsets: expected `learned` or `zero`, got `{other}`")),
        }
    }
}

/// The network output of each head parameter, `mu_a, mu_c, b_a, b_c, mu_y, b_y` in
/// that order (`None`: fixed at zero, the centred model's offsets).
type OutputRows = [Option<usize>; 6];
const LEARNED_ROWS: OutputRows = [Some(0), Some(1), Some(2), Some(3), Some(4), Some(5)];
const CENTRED_ROWS: OutputRows = [None, None, Some(0), Some(1), Some(2), Some(3)];

impl BoxObservationModel {
    /// The largest value `log g(det | x)` can take, whatever the parameters: both
    /// centre offsets and the yaw offset at their means with the floored scales. An
    /// MLL per detection above it is not a likelihood but a numerical artefact.
    pub fn max_log_density() -> f64 {
        let b = BOX_MIN_YAW_SCALE;
        -2.0 * (2.0 * BOX_MIN_SCALE).ln() - (2.0 * b).ln() + (-TAU / b).exp().ln_1p() - (-(-TAU / b).exp()).ln_1p()
    }

    /// The network layout.
    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    /// A fresh model with `offsets` learned or fixed at zero, its network added to
    /// `store` under `prefix` with standard initialisation drawn from `rng`.
    pub fn init_with_offsets<R: Rng + ?Sized>(
        store: &mut ParamStore<f64>,
        prefix: &str,
        offsets: DetectionOffsets,
        rng: &mut R,
    ) -> Self {
        let mut rng = rng;
        let layers = match offsets {
            DetectionOffsets::Learned => &BOX_NET_LAYERS,
            DetectionOffsets::Zero => &CENTRED_BOX_NET_LAYERS,
        };
        let mlp = Mlp::new(store, prefix, layers, Activation::Tanh, Activation::Identity, &mut rng);
        BoxObservationModel { mlp, offsets }
    }

    /// Whether the offsets are learned or fixed at zero.
    pub fn offsets(&self) -> DetectionOffsets {
        self.offsets
    }

    /// The layout a parameter store holds under `prefix`: centred when its last
    /// layer has the centred network's width, else learned (whose layout the
    /// caller then checks in full).
    pub fn offsets_in_store(store: &ParamStore<f64>, prefix: &str) -> DetectionOffsets {
        let last = format!("{prefix}.{}.b", CENTRED_BOX_NET_LAYERS.len() - 2);
        match store.id(&last) {
            Some(id) if store.get(id).shape() == [CENTRED_BOX_NET_LAYERS[3]] => DetectionOffsets::Zero,
            _ => DetectionOffsets::Learned,
        }
    }

    fn rows(&self) -> OutputRows {
        match self.offsets {
            DetectionOffsets::Learned => LEARNED_ROWS,
            DetectionOffsets::Zero => CENTRED_ROWS,
        }
    }

    /// The detection distribution at one state (f64).
    pub fn distribution(&self, params: &ParamStore<f64>, ctx: &ObsContext, pose: Pose) -> DetectionDistribution {
        let mut s = Scratch::<f64>::new();
        let (x, y, yaw) = ([pose.x], [pose.y], [pose.yaw]);
        net::forward_plain(&self.mlp, params, ctx, PosesRef::new(&x, &y, &yaw), &mut s);
        let rows = self.rows();
        let o = |k: usize| rows[k].map_or(0.0, |r| s.outputs[r]);
        DetectionDistribution {
            mu_along: BOX_OFFSET_SCALE * o(0),
            mu_across: BOX_OFFSET_SCALE * o(1),
            b_along: BOX_SCALE_SCALE * o(2).softplus() + BOX_MIN_SCALE,
            b_across: BOX_SCALE_SCALE * o(3).softplus() + BOX_MIN_SCALE,
            mu_yaw: BOX_YAW_OFFSET_SCALE * o(4),
            b_yaw: BOX_YAW_SCALE_SCALE * o(5).softplus() + BOX_MIN_YAW_SCALE,
        }
    }

    /// Network plus head into `s.head` (`HEAD_ROWS` feature-major rows).
    #[allow(clippy::needless_range_loop)] // index loops over resliced arrays vectorise
    fn prepare<F: Float>(&self, params: &ParamStore<F>, ctx: &ObsContext, poses: PosesRef<'_, F>, s: &mut Scratch<F>) {
        let n = poses.len();
        net::forward_plain(&self.mlp, params, ctx, poses, s);
        fit_len(&mut s.head, HEAD_ROWS * n);
        let f = F::from_f64;
        let (off, sc, mn) = (f(BOX_OFFSET_SCALE), f(BOX_SCALE_SCALE), f(BOX_MIN_SCALE));
        let (yoff, ysc, ymn) = (f(BOX_YAW_OFFSET_SCALE), f(BOX_YAW_SCALE_SCALE), f(BOX_MIN_YAW_SCALE));
        let two = f(2.0);
        let rows = self.rows();
        let outputs = rows.iter().flatten().count();
        let o = &s.outputs[..outputs * n];
        let row = |k: usize| rows[k].map(|r| &o[r * n..(r + 1) * n]);
        let (o2, o3, o4, o5) = (row(2).unwrap(), row(3).unwrap(), row(4).unwrap(), row(5).unwrap());
        let offset = |k: usize, i: usize| row(k).map_or(F::ZERO, |o| off * o[i]);
        let (h, rest) = s.head.split_at_mut(n);
        let (h1, rest) = rest.split_at_mut(n);
        let (h2, rest) = rest.split_at_mut(n);
        let (h3, rest) = rest.split_at_mut(n);
        let (h4, rest) = rest.split_at_mut(n);
        let (h5, h6) = rest.split_at_mut(n);
        for i in 0..n {
            let ba = sc * o2[i].softplus() + mn;
            let bc = sc * o3[i].softplus() + mn;
            let by = ysc * o5[i].softplus() + ymn;
            h[i] = offset(0, i);
            h1[i] = offset(1, i);
            h2[i] = F::ONE / ba;
            h3[i] = F::ONE / bc;
            h4[i] = yoff * o4[i];
            h5[i] = F::ONE / by;
            h6[i] = with_wrapped_laplace_norm(-(two * ba).ln() - (two * bc).ln(), by);
        }
    }
}

/// `log g(det | particle i)` for every particle, added to `out` (`ACC`) or written.
#[allow(clippy::needless_range_loop)]
fn detection_kernel<F: Float, const ACC: bool>(
    det: &BoxDetection,
    av: &Pose,
    poses: PosesRef<'_, F>,
    head: &[F],
    out: &mut [F],
) {
    let n = out.len();
    let f = F::from_f64;
    let (ax, ay) = (f(av.x), f(av.y));
    let (qx, qy, qyaw) = (f(det.x), f(det.y), f(det.yaw));
    let (xs, ys, yaws) = (&poses.x[..n], &poses.y[..n], &poses.yaw[..n]);
    let h = |k: usize| &head[k * n..(k + 1) * n];
    let (mua, muc, iba, ibc, muy, iby, cst) = (h(0), h(1), h(2), h(3), h(4), h(5), h(6));
    for i in 0..n {
        let (along, across) = los_offsets(xs[i] - ax, ys[i] - ay, qx - xs[i], qy - ys[i]);
        let a = wrap(qyaw - yaws[i] - muy[i]).abs();
        let lg = with_wrapped_laplace_shape(
            cst[i] - (along - mua[i]).abs() * iba[i] - (across - muc[i]).abs() * ibc[i],
            a,
            iby[i],
        );
        out[i] = if ACC { out[i] + lg } else { lg };
    }
}

impl ObservationModel for BoxObservationModel {
    type Item = BoxDetection;
    const KIND: ObservationKind = ObservationKind::Boxes;

    fn init_params<R: Rng + ?Sized>(store: &mut ParamStore<f64>, prefix: &str, rng: &mut R) -> Self {
        BoxObservationModel::init_with_offsets(store, prefix, DetectionOffsets::Learned, rng)
    }

    fn num_params(&self) -> usize {
        self.mlp.num_params()
    }

    #[track_caller]
    fn items(data: &Dataset, object: usize, t: usize) -> &[BoxDetection] {
        match data.boxes() {
            Some(b) => detection_items(b.get(object, t)),
            None => panic!("BoxObservationModel::items: the dataset holds points, not box detections"),
        }
    }

    #[track_caller]
    fn log_likelihood<F: Float>(
        &self,
        params: &ParamStore<F>,
        ctx: &ObsContext,
        poses: PosesRef<'_, F>,
        items: &[BoxDetection],
        scratch: &mut Scratch<F>,
        out: &mut [F],
    ) {
        let n = poses.len();
        assert_eq!(out.len(), n, "BoxObservationModel::log_likelihood: {n} poses, room for {}", out.len());
        if items.is_empty() || n == 0 {
            out.fill(F::ZERO);
            return;
        }
        self.prepare(params, ctx, poses, scratch);
        for (j, det) in items.iter().enumerate() {
            if j == 0 {
                detection_kernel::<F, false>(det, &ctx.av, poses, &scratch.head, out);
            } else {
                detection_kernel::<F, true>(det, &ctx.av, poses, &scratch.head, out);
            }
        }
    }

    #[track_caller]
    fn log_density_items(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        items: &[BoxDetection],
        out: &mut [f64],
    ) {
        assert_eq!(out.len(), items.len(), "log_density_items: {} items, room for {}", items.len(), out.len());
        if items.is_empty() {
            return;
        }
        let mut scratch = Scratch::new();
        let (x, y, yaw) = ([pose.x], [pose.y], [pose.yaw]);
        let poses = PosesRef::new(&x, &y, &yaw);
        self.prepare(params, ctx, poses, &mut scratch);
        for (o, det) in out.iter_mut().zip(items) {
            let mut v = [0.0];
            detection_kernel::<f64, false>(det, &ctx.av, poses, &scratch.head, &mut v);
            *o = v[0];
        }
    }

    #[track_caller]
    fn log_likelihood_rows<'t, F: Float>(
        &self,
        params: &BoundParams<'t, F>,
        rows: &RowVars<'t, F>,
        av: &[Pose],
        items: &[&[BoxDetection]],
    ) -> Var<'t, F> {
        let r = rows.check(av.len(), items.len(), "BoxObservationModel::log_likelihood_rows");
        let tape = rows.x.tape();
        let mut idx: Vec<usize> = Vec::new();
        for (i, d) in items.iter().enumerate() {
            idx.extend(d.iter().map(|_| i));
        }
        let q = idx.len();
        if q == 0 {
            return tape.constant(Tensor::zeros(&[r]));
        }
        let dets: Vec<&BoxDetection> = items.iter().flat_map(|d| d.iter()).collect();
        let c = |g: &dyn Fn(usize) -> f64| tape.constant(Tensor::from_vec((0..q).map(|k| F::from_f64(g(k))).collect()));
        let feats = av_features_on_tape(rows, av);
        let o = self.mlp.forward(params, feats).gather(0, &idx);
        let outputs = self.rows();
        let col = |k: usize| outputs[k].map(|j| o.slice(1, j, 1).reshape(&[q]));
        let mean_offset = |k: usize| match col(k) {
            Some(v) => v.mul_scalar(BOX_OFFSET_SCALE),
            None => tape.constant(Tensor::zeros(&[q])),
        };
        let col = |k: usize| col(k).expect("every scale and the yaw offset have an output");
        let (x, y, yaw) = (rows.x.gather(0, &idx), rows.y.gather(0, &idx), rows.yaw.gather(0, &idx));
        let dx = x - c(&|k| av[idx[k]].x);
        let dy = y - c(&|k| av[idx[k]].y);
        let inv = (dx.square() + dy.square()).add_scalar(LOS_EPS * LOS_EPS).powf(-0.5);
        let (lx, ly) = (dx * inv, dy * inv);
        let ddx = c(&|k| dets[k].x) - x;
        let ddy = c(&|k| dets[k].y) - y;
        let along = ddx * lx + ddy * ly;
        let across = ddy * lx - ddx * ly;
        let laplace = |z: Var<'t, F>, mu: Var<'t, F>, b: Var<'t, F>| -((z - mu).abs() / b) - b.mul_scalar(2.0).ln();
        let b_along = col(2).softplus().mul_scalar(BOX_SCALE_SCALE).add_scalar(BOX_MIN_SCALE);
        let b_across = col(3).softplus().mul_scalar(BOX_SCALE_SCALE).add_scalar(BOX_MIN_SCALE);
        let b_yaw = col(5).softplus().mul_scalar(BOX_YAW_SCALE_SCALE).add_scalar(BOX_MIN_YAW_SCALE);
        let d = c(&|k| dets[k].yaw) - yaw - col(4).mul_scalar(BOX_YAW_OFFSET_SCALE);
        let turns: Vec<f64> = d.value().data().iter().map(|v| (v.to_f64() / TAU).round()).collect();
        let a = (d - c(&|k| TAU * turns[k])).abs().clamp(0.0, PI);
        let inv_by = b_yaw.powf(-1.0);
        let z = inv_by.mul_scalar(TAU);
        let wrapped = -(a * inv_by) - b_yaw.mul_scalar(2.0).ln()
            + (a.add_scalar(-PI) * inv_by).mul_scalar(2.0).softplus()
            - z.neg().exp().neg().add_scalar(1.0).ln();
        let lq = laplace(along, mean_offset(0), b_along) + laplace(across, mean_offset(1), b_across) + wrapped;
        lq.scatter_add(0, &idx, r)
    }

    fn sample<R: Rng + ?Sized>(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        n: usize,
        rng: &mut R,
        out: &mut Vec<BoxDetection>,
    ) {
        let d = self.distribution(params, ctx, pose);
        let (dx, dy) = (pose.x - ctx.av.x, pose.y - ctx.av.y);
        let inv = 1.0 / (dx * dx + dy * dy + LOS_EPS * LOS_EPS).sqrt();
        let (lx, ly) = (dx * inv, dy * inv);
        // Inverse of (ddx, ddy) -> (along, across): the rows (lx, ly), (-ly, lx) have
        // determinant lx^2 + ly^2 (1 up to the guard).
        let det = lx * lx + ly * ly;
        out.reserve(n);
        for _ in 0..n {
            let along = sample_laplace(d.mu_along, d.b_along, rng);
            let across = sample_laplace(d.mu_across, d.b_across, rng);
            let dyaw = sample_laplace(d.mu_yaw, d.b_yaw, rng);
            out.push(BoxDetection {
                x: pose.x + (along * lx - across * ly) / det,
                y: pose.y + (along * ly + across * lx) / det,
                yaw: wrap_angle(pose.yaw + dyaw),
                length: ctx.length,
                width: ctx.width,
                score: 1.0,
            });
        }
    }
}
