//! The point observation model (SPEC §3): each observed point is, independently
//! given the state, a mixture over the box's 4 edges of a soft uniform along the
//! edge times a Laplace across it,
//!
//! ```text
//! g(y | x) = sum_e phi_e U_soft(alpha_e; 0, len_e) Laplace(beta_e; mu_e, b_e)
//! ```
//!
//! (edge coordinates in [`super::edges`]), with `phi = softmax(o[0..4])`,
//! `mu_e = POINT_OFFSET_SCALE * o[4 + e]` and
//! `b_e = POINT_SCALE_SCALE * softplus(o[8 + e]) + POINT_MIN_SCALE` the 12 outputs
//! `o` of a network `7 -> 16 tanh x 4 -> 12` over the AV-relative features.
//!
//! This file owns the model's three evaluation kernels and its sampler:
//!
//! * the filter's hot loop ([`ObservationModel::log_likelihood`]): blocks of
//!   particles that stay in L1 while all points are visited, a branch-free loop
//!   over the block that vectorises, two exponentials for the soft uniform (both
//!   edges of a pair share the distance to their nearer end) and four for the
//!   mixture per particle-point, and one logarithm per particle for up to 60
//!   points (the points' mixture sums are multiplied; their range is bounded);
//! * the tape path ([`ObservationModel::log_likelihood_rows`]) as one *fused*
//!   node per row in the manner of Stan: the network runs on the tape; the sum over
//!   a row's points of `log g` and its partial derivatives with respect to the
//!   row's 12 mixture quantities `(ln phi, mu, b)` and its `(x, y, yaw, l, w)` are
//!   computed in plain code, and enter the tape as `v + sum_k g_k (z_k - stop(z_k))`
//!   — exact value, exact gradient, and a tape of `O(R)` rather than
//!   `O(points x edges)` elements;
//! * the per-point f64 path (AOTLL) through the same hot kernel.
//!
//! All work in log space: the mixture is a log-sum-exp whose shift uses an upper
//! bound of each edge's term (the soft uniform inside an edge is at most `1 / L`),
//! so one logarithm per point suffices and no term is ever `-inf` or NaN for
//! finite inputs.
//!
//! # Clutter
//!
//! A model extension ([`Clutter`]) mixes a broad component into every point's
//! density: with probability `eps` a point is not on the box but drawn from an
//! isotropic Gaussian of sd `s` centred on the box centre `(x, y)`,
//!
//! ```text
//! g_c(y | x) = (1 - eps) g(y | x) + eps N2(y; (x, y), s^2 I)
//! ```
//!
//! On the tape `eps = sigmoid(lambda)` and `s = exp(sigma)`
//! ([`PointObservationModel::log_likelihood_rows_with_clutter`]). The clutter paths
//! run the same kernels as the clutter-free ones and then one more pass over the
//! per-point values: a two-term log-sum-exp, and on the tape the partials scaled
//! by the box component's responsibility `r_p` plus the clutter term's own. The
//! clutter-free paths do none of this work.

use autodiff::nn::{Activation, BoundParams, Mlp, ParamStore};
use autodiff::{Float, Parallelism, Tensor, Var};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use super::edges::{
    edge_lengths, edge_point, from_box_frame, sample_laplace, sample_soft_uniform, SoftConsts, DEFAULT_SOFT_SCALE,
    NUM_EDGES,
};
use super::features::{av_features_on_tape, NUM_FEATURES};
use super::{fit_len, net, ObsContext, ObservationModel, PosesRef, RowVars, Scratch};
use crate::data::{Dataset, ObservationKind, Pose};

/// Widths of the point network, input first (SPEC §3: 4 hidden layers of 16 tanh).
pub const POINT_NET_LAYERS: [usize; 6] = [NUM_FEATURES, 16, 16, 16, 16, 3 * NUM_EDGES];
/// `mu_e = POINT_OFFSET_SCALE * o[4 + e]` (m): order-one outputs give offsets of a
/// few tens of centimetres.
pub const POINT_OFFSET_SCALE: f64 = 0.2;
/// `b_e = POINT_SCALE_SCALE * softplus(o[8 + e]) + POINT_MIN_SCALE` (m).
pub const POINT_SCALE_SCALE: f64 = 0.2;
/// Floor of the Laplace scales `b_e` (m).
pub const POINT_MIN_SCALE: f64 = 0.01;

/// Number of per-row values the fused tape kernel produces: the row's log-density,
/// 12 partials with respect to `(ln phi, mu, b)`, and 5 with respect to
/// `(x, y, yaw, l, w)`.
const ROW_OUT: usize = 1 + 3 * NUM_EDGES + 5;
/// Per-row values the fused kernel adds with clutter: the partials with respect to
/// the clutter's logit fraction `lambda` and log scale `sigma`.
const CLUTTER_OUT: usize = 2;
/// Per-point work columns of the fused kernel: its outputs (with clutter's), the
/// box component's responsibilities `r_p` (clutter only), and the points' x and y.
const COLS: usize = ROW_OUT + CLUTTER_OUT + 3;
/// Rows per parallel task of the fused kernel (fixed: results never depend on threads).
const ROWS_PER_TASK: usize = 64;
/// The fused kernel pads each row's points to a multiple of this (the f32 vector
/// width the compiler uses with AVX2/AVX-512 at 256 bits).
const ROW_LANES: usize = 8;
/// Below this many (row, point) pairs the fused kernel stays on one thread.
const PAR_MIN_PAIRS: usize = 1 << 14;
/// Guard of `e_far = e^{-L/s} / e_near`: when `e_near` is below this, `e_far` is
/// negligible anyway (`e_far <= e_near` always, and here `e_far < 1e-30`).
const TINY: f64 = 1e-30;

/// The per-edge mixture of one state: weights, Laplace means and scales across
/// each edge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EdgeMixture {
    /// Mixture weights `phi_e` (sum to 1).
    pub phi: [f64; NUM_EDGES],
    /// Laplace means `mu_e` of the outward offset (m).
    pub mu: [f64; NUM_EDGES],
    /// Laplace scales `b_e` (m).
    pub b: [f64; NUM_EDGES],
}

/// Clutter mixed into every point's density (see the [module docs](self#clutter)):
/// with probability `fraction` a point is drawn from an isotropic 2-D Gaussian of
/// sd `scale` centred on the box centre instead of from the box's edges.
///
/// ```
/// use ssm::observation::points::Clutter;
/// let c = Clutter::from_logits(0.0, 2f64.ln());
/// assert_eq!(c, Clutter { fraction: 0.5, scale: 2.0 });
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Clutter {
    /// Fraction `eps` of clutter points, in `(0, 1)`.
    pub fraction: f64,
    /// Sd `s` of the clutter Gaussian (m, positive).
    pub scale: f64,
}

impl Clutter {
    /// The clutter with `fraction = sigmoid(logit_fraction)` and `scale = exp(log_scale)`
    /// (the tape path's parameterisation).
    pub fn from_logits(logit_fraction: f64, log_scale: f64) -> Self {
        Clutter { fraction: 1.0 / (1.0 + (-logit_fraction).exp()), scale: log_scale.exp() }
    }

    /// Panics unless `0 < fraction < 1` and `scale` is positive and finite.
    #[track_caller]
    fn check(&self, op: &str) {
        assert!(
            self.fraction > 0.0 && self.fraction < 1.0,
            "{op}: clutter fraction must lie in (0, 1), got {}",
            self.fraction
        );
        assert!(
            self.scale > 0.0 && self.scale.is_finite(),
            "{op}: clutter scale must be positive and finite, got {}",
            self.scale
        );
    }
}

/// `ln(1 + e^x)` in f64 without overflow or loss for large `|x|`.
fn softplus64(x: f64) -> f64 {
    if x > 0.0 {
        x + (-x).exp().ln_1p()
    } else {
        x.exp().ln_1p()
    }
}

/// The clutter's constants in the kernels' float type: with `c(d) = eps N2` at
/// distance `d` from the centre, `ln c = ln_peak - half_prec d^2`.
#[derive(Clone, Copy, Debug)]
struct ClutterConsts<F> {
    /// `ln(1 - eps)`.
    ln_keep: F,
    /// `ln eps - ln(2 pi) - 2 ln s`.
    ln_peak: F,
    /// `1 / s^2`.
    prec: F,
    /// `1 / (2 s^2)`.
    half_prec: F,
    /// `eps`.
    eps: F,
}

impl<F: Float> ClutterConsts<F> {
    /// From `ln(1 - eps)`, `ln eps` and `ln s`, computed in f64.
    fn new(ln_keep: f64, ln_eps: f64, ln_s: f64) -> Self {
        let prec = (-2.0 * ln_s).exp();
        let f = F::from_f64;
        ClutterConsts {
            ln_keep: f(ln_keep),
            ln_peak: f(ln_eps - (2.0 * std::f64::consts::PI).ln() - 2.0 * ln_s),
            prec: f(prec),
            half_prec: f(0.5 * prec),
            eps: f(ln_eps.exp()),
        }
    }

    /// Of a validated [`Clutter`].
    #[track_caller]
    fn of(c: Clutter, op: &str) -> Self {
        c.check(op);
        Self::new((-c.fraction).ln_1p(), c.fraction.ln(), c.scale.ln())
    }

    /// Of `eps = sigmoid(lambda)`, `s = exp(sigma)`: `ln eps = -softplus(-lambda)` and
    /// `ln(1 - eps) = -softplus(lambda)` stay accurate however large `|lambda|` is.
    #[track_caller]
    fn from_logits(lambda: f64, sigma: f64, op: &str) -> Self {
        assert!(
            lambda.is_finite() && sigma.is_finite(),
            "{op}: clutter logit fraction {lambda} and log scale {sigma} must be finite"
        );
        Self::new(-softplus64(lambda), -softplus64(-lambda), sigma)
    }
}

/// One point's mixture with clutter: `lg` the log of `g_c`, `q = 1 - r` the clutter
/// term's responsibility, `d2` the squared distance to the box centre.
struct ClutterMix<F> {
    lg: F,
    q: F,
    d2: F,
}

/// `log((1 - eps) e^{lg} + c(d))` for a point at `(dx, dy)` from the box centre whose
/// box log-density is `lg`: a two-term log-sum-exp, finite for finite inputs.
#[inline(always)]
fn clutter_mix<F: Float>(lg: F, dx: F, dy: F, cc: &ClutterConsts<F>) -> ClutterMix<F> {
    let d2 = dx * dx + dy * dy;
    let a = cc.ln_keep + lg;
    let b = cc.ln_peak - cc.half_prec * d2;
    let m = fmax(a, b);
    let (ea, eb) = ((a - m).exp(), (b - m).exp());
    let total = ea + eb;
    ClutterMix { lg: m + total.ln(), q: eb / total, d2 }
}

/// The point observation model: a layout (the network's parameter ids) plus the
/// soft-uniform scale. See the [module docs](self).
#[derive(Clone, Debug, PartialEq)]
pub struct PointObservationModel {
    mlp: Mlp,
    soft_scale: f64,
}

impl PointObservationModel {
    /// The network layout (parameter ids into the store given to
    /// [`ObservationModel::init_params`]).
    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    /// Laplace scale of the soft uniform along edges (m).
    pub fn soft_scale(&self) -> f64 {
        self.soft_scale
    }

    /// The same model with another soft-uniform scale (positive, m).
    #[track_caller]
    pub fn with_soft_scale(mut self, scale: f64) -> Self {
        assert!(scale > 0.0 && scale.is_finite(), "PointObservationModel: soft scale must be positive, got {scale}");
        self.soft_scale = scale;
        self
    }

    /// The mixture over edges at one pose (f64).
    pub fn edge_mixture(&self, params: &ParamStore<f64>, ctx: &ObsContext, pose: Pose) -> EdgeMixture {
        let mut scratch = Scratch::<f64>::new();
        let (x, y, yaw) = ([pose.x], [pose.y], [pose.yaw]);
        net::forward_plain(&self.mlp, params, ctx, PosesRef::new(&x, &y, &yaw), &mut scratch);
        let o = &scratch.outputs;
        let mut m = EdgeMixture { phi: [0.0; 4], mu: [0.0; 4], b: [0.0; 4] };
        let max = o[..4].iter().fold(f64::NEG_INFINITY, |a, &b| a.max(b));
        let total: f64 = o[..4].iter().map(|&l| (l - max).exp()).sum();
        for e in 0..NUM_EDGES {
            m.phi[e] = (o[e] - max).exp() / total;
            m.mu[e] = POINT_OFFSET_SCALE * o[4 + e];
            m.b[e] = POINT_SCALE_SCALE * o[8 + e].softplus() + POINT_MIN_SCALE;
        }
        m
    }

    /// The filter's hot path with clutter: like [`ObservationModel::log_likelihood`],
    /// `out[i] = sum over points of log g_c(point | pose i)`. Each point's box
    /// log-density goes through the same kernel into `scratch`, then is mixed with
    /// the clutter term and added to `out`.
    ///
    /// # Panics
    /// If `out` does not have one value per pose, or `clutter` is invalid
    /// (fraction outside `(0, 1)`, scale not positive).
    #[allow(clippy::too_many_arguments)]
    #[track_caller]
    pub fn log_likelihood_with_clutter<F: Float>(
        &self,
        params: &ParamStore<F>,
        ctx: &ObsContext,
        poses: PosesRef<'_, F>,
        items: &[[f64; 2]],
        clutter: Clutter,
        scratch: &mut Scratch<F>,
        out: &mut [F],
    ) {
        let op = "PointObservationModel::log_likelihood_with_clutter";
        let n = poses.len();
        assert_eq!(out.len(), n, "{op}: {n} poses, room for {}", out.len());
        let cc = ClutterConsts::of(clutter, op);
        if items.is_empty() || n == 0 {
            out.fill(F::ZERO);
            return;
        }
        self.prepare(params, ctx, poses, scratch);
        let pc = PointConsts::new(ctx.length, ctx.width, self.soft_scale);
        let mut lg = [F::ZERO; BLOCK];
        for start in (0..n).step_by(BLOCK) {
            let range = start..n.min(start + BLOCK);
            let blk = Block::new(poses, scratch, n, range.clone());
            let out = &mut out[range];
            let sink = |j: usize, lg: &[F]| {
                let p = items[j];
                if j == 0 {
                    clutter_point_kernel::<F, false>(p, &cc, blk.x, blk.y, lg, out);
                } else {
                    clutter_point_kernel::<F, true>(p, &cc, blk.x, blk.y, lg, out);
                }
            };
            if pc.far {
                block_log_densities::<F, true>(&blk, items, &pc, &mut lg, sink);
            } else {
                block_log_densities::<F, false>(&blk, items, &pc, &mut lg, sink);
            }
        }
    }

    /// The tape path with clutter: like [`ObservationModel::log_likelihood_rows`]
    /// (per-row sums of `log g_c`, shape `[R]`), differentiable in the network
    /// parameters, every tracked `Var` of `rows`, and in `logit_fraction`
    /// (`lambda`, `eps = sigmoid(lambda)`) and `log_scale` (`sigma`, `s = exp(sigma)`),
    /// both of shape `[1]` and shared by all rows.
    ///
    /// ```
    /// use autodiff::nn::ParamStore;
    /// use autodiff::{Tape, Tensor};
    /// use rand::SeedableRng;
    /// use ssm::data::Pose;
    /// use ssm::observation::{ObsContext, ObservationModel, PointObservationModel, RowVars};
    ///
    /// let mut rng = rand::rngs::StdRng::seed_from_u64(0);
    /// let mut store = ParamStore::new();
    /// let model = PointObservationModel::init_params(&mut store, "obs", &mut rng);
    /// let ctx = ObsContext::new(Pose::default(), 4.5, 1.8);
    /// let pose = Pose { x: 12.0, y: 3.0, yaw: 0.3 };
    /// let points = [[12.0, 4.0], [40.0, 3.0]]; // the second far from the box
    ///
    /// let tape = Tape::<f64>::new();
    /// let params = store.bind(&tape);
    /// let rows = RowVars::from_poses(&tape, &[pose], &[ctx]);
    /// let lambda = tape.param(Tensor::from_vec(vec![-2.0]));
    /// let sigma = tape.param(Tensor::from_vec(vec![1.0]));
    /// let items: [&[[f64; 2]]; 1] = [&points];
    /// let ll = model.log_likelihood_rows_with_clutter(&params, &rows, &[ctx.av], &items, lambda, sigma);
    /// let grads = tape.backward(ll.sum());
    /// // The far point is clutter: more clutter makes the data likelier.
    /// assert!(grads.wrt(lambda).item() > 0.0);
    /// ```
    ///
    /// # Panics
    /// On the shape mismatches of `log_likelihood_rows`, if `logit_fraction` or
    /// `log_scale` does not have shape `[1]`, or if their values are not finite.
    #[track_caller]
    pub fn log_likelihood_rows_with_clutter<'t, F: Float>(
        &self,
        params: &BoundParams<'t, F>,
        rows: &RowVars<'t, F>,
        av: &[Pose],
        items: &[&[[f64; 2]]],
        logit_fraction: Var<'t, F>,
        log_scale: Var<'t, F>,
    ) -> Var<'t, F> {
        let op = "PointObservationModel::log_likelihood_rows_with_clutter";
        for (name, v) in [("logit_fraction", logit_fraction), ("log_scale", log_scale)] {
            assert!(v.shape() == [1], "{op}: {name} has shape {:?}, expected [1]", v.shape());
        }
        self.rows_log_likelihood(params, rows, av, items, Some([logit_fraction, log_scale]), op)
    }

    /// Appends `n` points drawn independently from `g_c(. | pose)`: each is clutter
    /// with probability `clutter.fraction`, else drawn as by
    /// [`ObservationModel::sample`].
    ///
    /// # Panics
    /// If `clutter` is invalid (fraction outside `(0, 1)`, scale not positive).
    #[allow(clippy::too_many_arguments)]
    #[track_caller]
    pub fn sample_with_clutter<R: Rng + ?Sized>(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        n: usize,
        clutter: Clutter,
        rng: &mut R,
        out: &mut Vec<[f64; 2]>,
    ) {
        clutter.check("PointObservationModel::sample_with_clutter");
        let is_clutter: Vec<bool> = (0..n).map(|_| rng.random::<f64>() < clutter.fraction).collect();
        // The box points in one batch (one network evaluation), interleaved in draw order.
        let mut on_box = Vec::new();
        self.sample(params, ctx, pose, is_clutter.iter().filter(|&&c| !c).count(), rng, &mut on_box);
        let mut on_box = on_box.into_iter();
        out.reserve(n);
        for c in is_clutter {
            let p = if c {
                let (a, b): (f64, f64) = (StandardNormal.sample(rng), StandardNormal.sample(rng));
                [pose.x + clutter.scale * a, pose.y + clutter.scale * b]
            } else {
                on_box.next().expect("one box point per non-clutter draw")
            };
            out.push(p);
        }
    }

    /// [`ObservationModel::log_likelihood_rows`] and, with `clutter = Some([lambda,
    /// sigma])`, [`Self::log_likelihood_rows_with_clutter`]: the network on the tape,
    /// the fused kernel, and the partials entering as `sum_k g_k (z_k - stop(z_k))`.
    #[track_caller]
    fn rows_log_likelihood<'t, F: Float>(
        &self,
        params: &BoundParams<'t, F>,
        rows: &RowVars<'t, F>,
        av: &[Pose],
        items: &[&[[f64; 2]]],
        clutter: Option<[Var<'t, F>; 2]>,
        op: &str,
    ) -> Var<'t, F> {
        let r = rows.check(av.len(), items.len(), op);
        let tape = rows.x.tape();
        let cc = clutter.map(|[l, s]| ClutterConsts::from_logits(l.item().to_f64(), s.item().to_f64(), op));
        let feats = av_features_on_tape(rows, av);
        let o = self.mlp.forward(params, feats);
        let logphi = o.slice(1, 0, NUM_EDGES).log_softmax(1);
        let mu = o.slice(1, NUM_EDGES, NUM_EDGES).mul_scalar(POINT_OFFSET_SCALE);
        let b =
            o.slice(1, 2 * NUM_EDGES, NUM_EDGES).softplus().mul_scalar(POINT_SCALE_SCALE).add_scalar(POINT_MIN_SCALE);
        let head = tape.concat(&[logphi, mu, b], 1);
        let row_vars = [rows.x, rows.y, rows.yaw, rows.length, rows.width];
        let clutter_vars = clutter.as_ref().map_or(&[][..], |c| &c[..]);
        let grad =
            tape.is_recording() && (head.is_tracked() || row_vars.iter().chain(clutter_vars).any(|v| v.is_tracked()));
        let stride = row_stride(cc.is_some());
        let mut k = vec![0.0f64; r * stride];
        {
            let hv = head.value();
            let vals: Vec<Vec<F>> = row_vars.iter().map(|v| v.value().data().to_vec()).collect();
            rows_kernel(
                hv.data(),
                &vals[0],
                &vals[1],
                &vals[2],
                &vals[3],
                &vals[4],
                items,
                self.soft_scale,
                cc.as_ref(),
                grad,
                tape.parallelism(),
                &mut k,
            );
        }
        let column = |j: usize| Tensor::from_vec((0..r).map(|i| F::from_f64(k[i * stride + j])).collect());
        let mut total = tape.constant(column(0));
        if !grad {
            return total;
        }
        if head.is_tracked() {
            let g: Vec<F> = (0..r)
                .flat_map(|i| (1..1 + 3 * NUM_EDGES).map(move |j| (i, j)))
                .map(|(i, j)| F::from_f64(k[i * stride + j]))
                .collect();
            let g = tape.constant(Tensor::new(&[r, 3 * NUM_EDGES], g));
            total = total + ((head - head.detach()) * g).sum_axis(1, false);
        }
        // Row variables have shape [R]; the clutter's shape [1] broadcasts over rows.
        let tracked = row_vars.iter().enumerate().map(|(j, v)| (1 + 3 * NUM_EDGES + j, v));
        let tracked = tracked.chain(clutter_vars.iter().enumerate().map(|(j, v)| (ROW_OUT + j, v)));
        for (j, v) in tracked {
            if v.is_tracked() {
                let g = tape.constant(column(j));
                total = total + (*v - v.detach()) * g;
            }
        }
        total
    }

    /// Network plus head: per particle and edge, the inputs of [`point_terms`] into
    /// `scratch.head` (feature-major, 12 rows): `k_e = ln phi_e - ln(2 b_e) - ln L_e`,
    /// the Laplace's centre `off_e` in the box frame, and `-1 / b_e`.
    #[allow(clippy::needless_range_loop)] // index loops over resliced arrays vectorise
    fn prepare<F: Float>(&self, params: &ParamStore<F>, ctx: &ObsContext, poses: PosesRef<'_, F>, s: &mut Scratch<F>) {
        let n = poses.len();
        net::forward_plain(&self.mlp, params, ctx, poses, s);
        fit_len(&mut s.head, 3 * NUM_EDGES * n);
        let lens = edge_lengths(ctx.length, ctx.width);
        let f = F::from_f64;
        let ln_len: [F; 4] = std::array::from_fn(|e| f(lens[e].ln()));
        // off_e = sign_e (half extent_e + mu_e): the front and rear sit at u = +-hl,
        // the left and right sides at v = +-hw (module table of `edges`).
        let (hl, hw) = (0.5 * ctx.length, 0.5 * ctx.width);
        let centre: [F; 4] = [f(hl), f(hw), f(-hl), f(-hw)];
        let mu_scale: [F; 4] = std::array::from_fn(|e| f(if e < 2 { POINT_OFFSET_SCALE } else { -POINT_OFFSET_SCALE }));
        let (b_scale, b_min, two) = (f(POINT_SCALE_SCALE), f(POINT_MIN_SCALE), f(2.0));
        fit_len(&mut s.tmp, n);
        let Scratch { outputs, head, tmp, .. } = s;
        let o = &outputs[..3 * NUM_EDGES * n];
        let row = |k: usize| &o[k * n..(k + 1) * n];
        // Log-normaliser of each particle's edge logits.
        let lse = &mut tmp[..n];
        let (l0, l1, l2, l3) = (row(0), row(1), row(2), row(3));
        for i in 0..n {
            let mx = fmax(fmax(l0[i], l1[i]), fmax(l2[i], l3[i]));
            let sum = (l0[i] - mx).exp_nonpos()
                + (l1[i] - mx).exp_nonpos()
                + (l2[i] - mx).exp_nonpos()
                + (l3[i] - mx).exp_nonpos();
            lse[i] = mx + sum.ln();
        }
        let (ks, rest) = head.split_at_mut(NUM_EDGES * n);
        let (offs, nibs) = rest.split_at_mut(NUM_EDGES * n);
        for e in 0..NUM_EDGES {
            let (le, me, re) = (row(e), row(4 + e), row(8 + e));
            let (k, off, nib) =
                (&mut ks[e * n..(e + 1) * n], &mut offs[e * n..(e + 1) * n], &mut nibs[e * n..(e + 1) * n]);
            for i in 0..n {
                let b = b_scale * re[i].softplus() + b_min;
                k[i] = le[i] - lse[i] - (two * b).ln() - ln_len[e];
                off[i] = mu_scale[e].mul_add(me[i], centre[e]);
                nib[i] = -F::ONE / b;
            }
        }
    }
}

/// One edge's contribution to one point: the upper bound `ub` of its log-term and
/// the factor `fac` in `(0, 1]` with `log term = ub + ln fac`; plus what the
/// gradient kernel needs.
#[derive(Clone, Copy)]
struct EdgeTerm<F> {
    ub: F,
    fac: F,
    inside: bool,
    e_near: F,
    e_far: F,
}

/// `min(a, b)` as a plain compare-and-select (one `vminps`); `Float::min` also
/// handles NaN, which costs two more instructions per lane. Inputs here are finite.
#[inline(always)]
fn fmin<F: Float>(a: F, b: F) -> F {
    if a < b {
        a
    } else {
        b
    }
}

/// `max(a, b)` as a plain compare-and-select (see [`fmin`]).
#[inline(always)]
fn fmax<F: Float>(a: F, b: F) -> F {
    if a > b {
        a
    } else {
        b
    }
}

/// `k` is `ln phi - ln(2 b) - ln L`; the soft uniform adds `ln fac` inside the edge
/// and `m / s + tail` outside it (`m` the signed distance to the nearer end).
/// `FAR = false` when `e^{-L/s}` is flushed to 0 for both edge lengths (see
/// `SoftConsts`): `e_far` is then 0 and costs no division.
#[inline(always)]
fn edge_term<F: Float, const FAR: bool>(alpha: F, beta: F, k: F, mu: F, invb: F, sc: &SoftConsts<F>) -> EdgeTerm<F> {
    let m = fmin(alpha, sc.len - alpha);
    let inside = m >= F::ZERO;
    let e_near = (-fmax(m, F::ZERO) * sc.inv_s).exp();
    let e_far = if FAR { sc.exp_neg / fmax(e_near, F::from_f64(TINY)) } else { F::ZERO };
    let fac = if inside { F::ONE - F::from_f64(0.5) * (e_near + e_far) } else { F::ONE };
    let soft = if inside { F::ZERO } else { m * sc.inv_s + sc.tail };
    let ub = k - (beta - mu).abs() * invb + soft;
    EdgeTerm { ub, fac, inside, e_near, e_far }
}

/// `log sum_e fac_e e^{ub_e}` over the 4 edges, stable: shift by the largest `ub`.
#[inline(always)]
fn mix4<F: Float>(t: &[EdgeTerm<F>; 4]) -> F {
    let mx = fmax(fmax(t[0].ub, t[1].ub), fmax(t[2].ub, t[3].ub));
    let s = t[0].fac * (t[0].ub - mx).exp()
        + t[1].fac * (t[1].ub - mx).exp()
        + t[2].fac * (t[2].ub - mx).exp()
        + t[3].fac * (t[3].ub - mx).exp();
    mx + s.ln()
}

/// Constants of one object (or row) shared by its points.
#[derive(Clone, Copy)]
struct BoxConsts<F> {
    hl: F,
    hw: F,
    /// Soft-uniform constants of the width edges (0, 2) and the length edges (1, 3).
    sw: SoftConsts<F>,
    sl: SoftConsts<F>,
}

impl<F: Float> BoxConsts<F> {
    fn new(length: f64, width: f64, scale: f64) -> Self {
        BoxConsts {
            hl: F::from_f64(0.5 * length),
            hw: F::from_f64(0.5 * width),
            sw: SoftConsts::new(width, scale),
            sl: SoftConsts::new(length, scale),
        }
    }
}

/// Particles per block of the filter's kernel: a block's 16 per-particle inputs and
/// its two accumulators (4.5 KiB in f32) stay in L1 while all its points are visited.
const BLOCK: usize = 64;
/// The filter's kernel multiplies the points' mixture sums and takes one logarithm
/// of the running product before its binary exponent can leave `[-RANGE, RANGE]`
/// (f32's normal range is `[-126, 127]`).
const PRODUCT_RANGE_LOG2: f64 = 120.0;

/// Constants of one object for the filter's kernel ([`point_terms`]): the soft
/// uniform's, per edge pair, in units of its scale `s` where that saves work.
#[derive(Clone, Copy, Debug)]
struct PointConsts<F> {
    /// `1 / s`.
    inv_s: F,
    /// `-hw / s` and `-hl / s`.
    neg_hw_s: F,
    neg_hl_s: F,
    /// `ln((1 - e^{-L/s}) / 2)` of the width and length edges (added outside them).
    tail_w: F,
    tail_l: F,
    /// `e^{-L/s}` of the width and length edges, flushed to 0 as in `SoftConsts`.
    exp_neg_w: F,
    exp_neg_l: F,
    /// Whether either `e^{-L/s}` is kept (the kernel then adds the far end's term).
    far: bool,
    /// Points whose mixture sums are multiplied before one logarithm is taken.
    points_per_log: usize,
}

impl<F: Float> PointConsts<F> {
    fn new(length: f64, width: f64, scale: f64) -> Self {
        let (sw, sl) = (SoftConsts::<F>::new(width, scale), SoftConsts::<F>::new(length, scale));
        // Each point's sum lies in [fac_min, 4]: the largest term's factor is at least
        // the soft uniform's relative value at an edge's end, (1 - e^{-L/s}) / 2.
        let fac_min = [width, length].map(|l| -(-l / scale).exp_m1() / 2.0);
        let log2_range = fac_min.iter().fold(2.0f64, |a, f| a.max(-f.log2()));
        let f = F::from_f64;
        PointConsts {
            inv_s: f(1.0 / scale),
            neg_hw_s: f(-0.5 * width / scale),
            neg_hl_s: f(-0.5 * length / scale),
            tail_w: sw.tail,
            tail_l: sl.tail,
            exp_neg_w: sw.exp_neg,
            exp_neg_l: sl.exp_neg,
            far: sw.exp_neg != F::ZERO || sl.exp_neg != F::ZERO,
            points_per_log: ((PRODUCT_RANGE_LOG2 / log2_range) as usize).max(1),
        }
    }
}

/// One point against one particle, for the filter: `(mx, sum)` with
/// `log g = mx + ln(sum)`, `mx` the largest edge term's upper bound and `sum` in
/// `[fac_min, 4]`. `(u, v)` is the point in the particle's box frame; per edge `e`,
/// `k[e]` is `ln phi_e - ln(2 b_e) - ln L_e`, `off[e]` the centre of its Laplace in
/// the box frame (`hl + mu_0`, `hw + mu_1`, `-(hl + mu_2)`, `-(hw + mu_3)`, along
/// `u` for the front and rear, `v` for the sides) and `nib[e] = -1 / b_e`.
///
/// The two edges of a pair have the same distance to their nearer end (`hw - |v|`
/// for the front and rear, `hl - |u|` for the sides), so the soft uniform costs two
/// exponentials per point, the mixture four, and the logarithm is left to the caller.
#[inline(always)]
fn point_terms<F: Float, const FAR: bool>(
    u: F,
    v: F,
    k: [F; NUM_EDGES],
    off: [F; NUM_EDGES],
    nib: [F; NUM_EDGES],
    pc: &PointConsts<F>,
) -> (F, F) {
    let (zero, one, neg_half) = (F::ZERO, F::ONE, F::from_f64(-0.5));
    // q = minus the distance to the nearer end over s: `(fac, soft)` with the term's
    // log-density `soft + ln fac` (`edge_term`'s split).
    let soft_uniform = |q: F, tail: F, exp_neg: F| -> (F, F) {
        let inside = q <= zero;
        let e_near = fmin(q, zero).exp_nonpos();
        let e = if FAR { e_near + exp_neg / fmax(e_near, F::from_f64(TINY)) } else { e_near };
        let fac = if inside { neg_half.mul_add(e, one) } else { one };
        let soft = if inside { zero } else { tail - q };
        (fac, soft)
    };
    let (fac_w, soft_w) = soft_uniform(v.abs().mul_add(pc.inv_s, pc.neg_hw_s), pc.tail_w, pc.exp_neg_w);
    let (fac_l, soft_l) = soft_uniform(u.abs().mul_add(pc.inv_s, pc.neg_hl_s), pc.tail_l, pc.exp_neg_l);
    let ub = [
        (u - off[0]).abs().mul_add(nib[0], k[0] + soft_w),
        (v - off[1]).abs().mul_add(nib[1], k[1] + soft_l),
        (u - off[2]).abs().mul_add(nib[2], k[2] + soft_w),
        (v - off[3]).abs().mul_add(nib[3], k[3] + soft_l),
    ];
    let mx = fmax(fmax(ub[0], ub[1]), fmax(ub[2], ub[3]));
    let t = ub.map(|b| (b - mx).exp_nonpos());
    (mx, fac_w.mul_add(t[0] + t[2], fac_l * (t[1] + t[3])))
}

/// One block of particles' inputs to the filter's kernel, each sliced to the block:
/// poses, heading trig, and the head rows of [`PointObservationModel::prepare`].
struct Block<'a, F> {
    x: &'a [F],
    y: &'a [F],
    cos: &'a [F],
    sin: &'a [F],
    k: [&'a [F]; NUM_EDGES],
    off: [&'a [F]; NUM_EDGES],
    nib: [&'a [F]; NUM_EDGES],
}

impl<'a, F: Float> Block<'a, F> {
    /// Particles `range` of `n`, from `scratch` after `prepare`.
    fn new(poses: PosesRef<'a, F>, scratch: &'a Scratch<F>, n: usize, range: std::ops::Range<usize>) -> Self {
        let row = |r: usize| &scratch.head[r * n..(r + 1) * n][range.clone()];
        Block {
            x: &poses.x[range.clone()],
            y: &poses.y[range.clone()],
            cos: &scratch.cos[range.clone()],
            sin: &scratch.sin[range.clone()],
            k: std::array::from_fn(row),
            off: std::array::from_fn(|e| row(NUM_EDGES + e)),
            nib: std::array::from_fn(|e| row(2 * NUM_EDGES + e)),
        }
    }

    fn len(&self) -> usize {
        self.x.len()
    }

    /// `point_terms` of the `P` points `pts` for every particle of the block, handed
    /// to `f(i, [(mx, sum); P])`. Inlined into a loop over the block that vectorises.
    /// With `P = 2` each iteration holds two independent dependency chains (the loop
    /// body is long: one chain alone keeps the core waiting on its latencies) that
    /// share the particle's loads.
    #[inline(always)]
    fn for_each_terms<const FAR: bool, const P: usize>(
        &self,
        pts: [[F; 2]; P],
        pc: &PointConsts<F>,
        mut f: impl FnMut(usize, [(F, F); P]),
    ) {
        let b = self.len();
        let (x, y, c, s) = (&self.x[..b], &self.y[..b], &self.cos[..b], &self.sin[..b]);
        let (k, off, nib) = (self.k.map(|r| &r[..b]), self.off.map(|r| &r[..b]), self.nib.map(|r| &r[..b]));
        for i in 0..b {
            let ki = [k[0][i], k[1][i], k[2][i], k[3][i]];
            let offi = [off[0][i], off[1][i], off[2][i], off[3][i]];
            let nibi = [nib[0][i], nib[1][i], nib[2][i], nib[3][i]];
            let mut terms = [(F::ZERO, F::ZERO); P];
            for q in 0..P {
                let (dx, dy) = (pts[q][0] - x[i], pts[q][1] - y[i]);
                let u = c[i].mul_add(dx, s[i] * dy);
                let v = c[i].mul_add(dy, -(s[i] * dx));
                terms[q] = point_terms::<F, FAR>(u, v, ki, offi, nibi, pc);
            }
            f(i, terms);
        }
    }
}

/// The filter's kernel for one block: `out[i] = sum over points of log g(point |
/// particle i)`. The points' sums are multiplied (their range bounds the product,
/// see [`PointConsts`]) and one logarithm taken per `points_per_log` points; the
/// points go through the loop over the block two at a time.
#[inline(never)]
fn block_log_likelihood<F: Float, const FAR: bool>(
    blk: &Block<'_, F>,
    points: &[[f64; 2]],
    pc: &PointConsts<F>,
    out: &mut [F],
) {
    let b = blk.len();
    let (mut total, mut prod) = ([F::ZERO; BLOCK], [F::ONE; BLOCK]);
    let (total, prod) = (&mut total[..b], &mut prod[..b]);
    let to_f = |p: &[f64; 2]| p.map(F::from_f64);
    for chunk in points.chunks(pc.points_per_log) {
        let mut pairs = chunk.chunks_exact(2);
        for pair in pairs.by_ref() {
            blk.for_each_terms::<FAR, 2>([to_f(&pair[0]), to_f(&pair[1])], pc, |i, [(m0, s0), (m1, s1)]| {
                total[i] = total[i] + m0 + m1;
                prod[i] = prod[i] * s0 * s1;
            });
        }
        if let [p] = pairs.remainder() {
            blk.for_each_terms::<FAR, 1>([to_f(p)], pc, |i, [(mx, sum)]| {
                total[i] += mx;
                prod[i] *= sum;
            });
        }
        for (t, p) in total.iter_mut().zip(prod.iter_mut()) {
            *t += p.ln();
            *p = F::ONE;
        }
    }
    out[..b].copy_from_slice(total);
}

/// The filter's kernel for one block, point by point: for each point `j`,
/// `lg[i] = log g(point j | particle i)`, then `sink(j, lg)`.
#[inline(never)]
fn block_log_densities<F: Float, const FAR: bool>(
    blk: &Block<'_, F>,
    points: &[[f64; 2]],
    pc: &PointConsts<F>,
    lg: &mut [F],
    mut sink: impl FnMut(usize, &[F]),
) {
    let lg = &mut lg[..blk.len()];
    for (j, p) in points.iter().enumerate() {
        blk.for_each_terms::<FAR, 1>([p.map(F::from_f64)], pc, |i, [(mx, sum)]| lg[i] = mx + sum.ln());
        sink(j, lg);
    }
}

/// Clutter for one point over a block of particles at `(xs, ys)`: `lg[i]` holds
/// `log g(point | particle i)`; `log g_c` is added to `out` (`ACC`) or written into it.
#[allow(clippy::needless_range_loop)]
#[inline(never)]
fn clutter_point_kernel<F: Float, const ACC: bool>(
    p: [f64; 2],
    cc: &ClutterConsts<F>,
    xs: &[F],
    ys: &[F],
    lg: &[F],
    out: &mut [F],
) {
    let n = out.len();
    let (px, py) = (F::from_f64(p[0]), F::from_f64(p[1]));
    let (xs, ys, lg) = (&xs[..n], &ys[..n], &lg[..n]);
    for i in 0..n {
        let lgc = clutter_mix(lg[i], px - xs[i], py - ys[i], cc).lg;
        out[i] = if ACC { out[i] + lgc } else { lgc };
    }
}

/// Values per row in the fused kernel's output, with or without clutter.
fn row_stride(clutter: bool) -> usize {
    if clutter {
        ROW_OUT + CLUTTER_OUT
    } else {
        ROW_OUT
    }
}

/// Per-row inputs of the fused tape kernel, in the kernel's float type.
struct RowInput<'a, F> {
    /// `(ln phi, mu, b)`, 12 values.
    head: &'a [F],
    x: F,
    y: F,
    yaw: F,
    points: &'a [[f64; 2]],
}

/// Per-row constants of the fused kernel.
struct RowConsts<'a, F> {
    /// `ln phi_e - ln(2 b_e) - ln L_e`.
    k: [F; 4],
    mu: [F; 4],
    /// `1 / b_e`.
    ib: [F; 4],
    /// cos and sin of the row's heading.
    c: F,
    s: F,
    x: F,
    y: F,
    bc: &'a BoxConsts<F>,
}

/// The fused kernel for one row: `out[0]` the sum over its points of `log g` (of
/// `log g_c` with `clutter`), and (if `GRAD`) `out[1..13]` its partials with respect
/// to `(ln phi, mu, b)`, `out[13..18]` with respect to `(x, y, yaw, l, w)` and, with
/// clutter, `out[18..20]` with respect to the clutter's `(lambda, sigma)`.
///
/// One branch-free pass over the row's points (vectorised across points) writes
/// each point's contributions into columns of `cols`; with clutter a second pass
/// mixes in the clutter term; the columns are then summed in f64, in point order.
fn row_kernel<F: Float, const GRAD: bool>(
    row: &RowInput<'_, F>,
    bc: &BoxConsts<F>,
    clutter: Option<&ClutterConsts<F>>,
    cols: &mut [Vec<F>; COLS],
    out: &mut [f64],
) {
    out.iter_mut().for_each(|o| *o = 0.0);
    let np = row.points.len();
    if np == 0 {
        return;
    }
    let used = if GRAD { row_stride(clutter.is_some()) } else { 1 };
    // Rows are short (tens of points): pad to whole vectors by repeating the last
    // point, so no point takes the scalar remainder loop; padding is not summed.
    let padded = np.div_ceil(ROW_LANES) * ROW_LANES;
    let (outs, rest) = cols.split_at_mut(ROW_OUT + CLUTTER_OUT);
    let [resp, px, py] = rest else { unreachable!("responsibility and point columns") };
    for c in outs[..used].iter_mut().chain([&mut *px, &mut *py]) {
        fit_len(c, padded);
    }
    // The points as two contiguous columns in the kernel's type (an interleaved f64
    // input keeps the passes below from vectorising).
    for (k, (x, y)) in px.iter_mut().zip(py.iter_mut()).enumerate() {
        let p = row.points[k.min(np - 1)];
        *x = F::from_f64(p[0]);
        *y = F::from_f64(p[1]);
    }
    let (one, two) = (F::ONE, F::from_f64(2.0));
    let h = row.head;
    let lens = [&bc.sw, &bc.sl, &bc.sw, &bc.sl];
    let rc = RowConsts {
        k: std::array::from_fn(|e| h[e] - (two * h[8 + e]).ln() - lens[e].ln_len),
        mu: std::array::from_fn(|e| h[4 + e]),
        ib: std::array::from_fn(|e| one / h[8 + e]),
        c: row.yaw.cos(),
        s: row.yaw.sin(),
        x: row.x,
        y: row.y,
        bc,
    };
    if GRAD {
        let (base, extra) = outs.split_at_mut(ROW_OUT);
        let [lg, p0, p1, p2, p3, m0, m1, m2, m3, b0, b1, b2, b3, gx, gy, gyaw, gl, gw] = base else {
            unreachable!("{ROW_OUT} output columns")
        };
        row_grad_pass(&rc, px, py, lg, p0, p1, p2, p3, m0, m1, m2, m3, b0, b1, b2, b3, gx, gy, gyaw, gl, gw);
        if let Some(cc) = clutter {
            let [dlambda, dsigma] = extra else { unreachable!("{CLUTTER_OUT} clutter columns") };
            fit_len(resp, padded);
            clutter_grad_pass(cc, rc.x, rc.y, px, py, lg, resp, gx, gy, dlambda, dsigma);
            for c in [p0, p1, p2, p3, m0, m1, m2, m3, b0, b1, b2, b3, gyaw, gl, gw] {
                scale_by(c, resp);
            }
        }
    } else {
        row_value_pass(&rc, px, py, &mut outs[0]);
        if let Some(cc) = clutter {
            clutter_value_pass(cc, rc.x, rc.y, px, py, &mut outs[0]);
        }
    }
    for (o, column) in out[..used].iter_mut().zip(outs.iter()) {
        *o = column[..np].iter().map(|v| v.to_f64()).sum();
    }
}

/// `lg[p] <- log g_c(point p | row)` from `lg[p] = log g(point p | row)`, for a row
/// centred at `(x, y)`.
#[inline(never)]
#[allow(clippy::needless_range_loop)]
fn clutter_value_pass<F: Float>(cc: &ClutterConsts<F>, x: F, y: F, px: &[F], py: &[F], lg: &mut [F]) {
    let n = px.len();
    let (px, py, lg) = (&px[..n], &py[..n], &mut lg[..n]);
    for p in 0..n {
        lg[p] = clutter_mix(lg[p], px[p] - x, py[p] - y, cc).lg;
    }
}

/// The clutter's part of the fused kernel's gradient pass, per point: `lg[p]` from
/// `log g` to `log g_c`; `resp[p]` the box component's responsibility `r`;
/// `gx`, `gy` from the box's partials to `r g + (1 - r) (p - centre) / s^2`; and
/// the partials with respect to `lambda` (`1 - r - eps`) and `sigma`
/// (`(1 - r) (d^2 / s^2 - 2)`). The other partials still need scaling by `r`
/// ([`scale_by`]).
#[inline(never)]
#[allow(clippy::too_many_arguments, clippy::needless_range_loop)]
fn clutter_grad_pass<F: Float>(
    cc: &ClutterConsts<F>,
    x: F,
    y: F,
    px: &[F],
    py: &[F],
    lg: &mut [F],
    resp: &mut [F],
    gx: &mut [F],
    gy: &mut [F],
    dlambda: &mut [F],
    dsigma: &mut [F],
) {
    let n = px.len();
    let (px, py, lg, resp) = (&px[..n], &py[..n], &mut lg[..n], &mut resp[..n]);
    let (gx, gy, dlambda, dsigma) = (&mut gx[..n], &mut gy[..n], &mut dlambda[..n], &mut dsigma[..n]);
    let two = F::from_f64(2.0);
    for p in 0..n {
        let (dx, dy) = (px[p] - x, py[p] - y);
        let m = clutter_mix(lg[p], dx, dy, cc);
        let r = F::ONE - m.q;
        lg[p] = m.lg;
        resp[p] = r;
        // d ln c / d(x, y) = (p - centre) / s^2.
        let qp = m.q * cc.prec;
        gx[p] = r * gx[p] + qp * dx;
        gy[p] = r * gy[p] + qp * dy;
        dlambda[p] = m.q - cc.eps;
        dsigma[p] = m.q * (m.d2 * cc.prec - two);
    }
}

/// `col[p] *= r[p]` over `col`'s length.
#[inline(never)]
fn scale_by<F: Float>(col: &mut [F], r: &[F]) {
    let n = col.len();
    for (c, &r) in col.iter_mut().zip(&r[..n]) {
        *c *= r;
    }
}

/// `lg[p] = log g(point p | row)`.
#[inline(never)]
#[allow(clippy::needless_range_loop)]
fn row_value_pass<F: Float>(rc: &RowConsts<'_, F>, px: &[F], py: &[F], lg: &mut [F]) {
    let n = px.len();
    let (px, py, lg) = (&px[..n], &py[..n], &mut lg[..n]);
    let (bc, k, mu, ib) = (rc.bc, &rc.k, &rc.mu, &rc.ib);
    let (hl, hw, c, s) = (bc.hl, bc.hw, rc.c, rc.s);
    for p in 0..n {
        let dx = px[p] - rc.x;
        let dy = py[p] - rc.y;
        let u = c * dx + s * dy;
        let v = c * dy - s * dx;
        let t = [
            edge_term::<F, true>(v + hw, u - hl, k[0], mu[0], ib[0], &bc.sw),
            edge_term::<F, true>(hl - u, v - hw, k[1], mu[1], ib[1], &bc.sl),
            edge_term::<F, true>(hw - v, -u - hl, k[2], mu[2], ib[2], &bc.sw),
            edge_term::<F, true>(u + hl, -v - hw, k[3], mu[3], ib[3], &bc.sl),
        ];
        lg[p] = mix4(&t);
    }
}

/// Partials of one edge's term: d/dalpha and d/dL of `log U_soft`, and the sign and
/// size of `beta - mu`.
#[inline(always)]
fn edge_partials<F: Float>(t: &EdgeTerm<F>, alpha: F, beta: F, mu: F, sc: &SoftConsts<F>) -> (F, F, F, F) {
    let (one, half) = (F::ONE, F::from_f64(0.5));
    let near_start = alpha <= sc.len - alpha;
    let dir = if near_start { one } else { -one };
    let e2 = if near_start { t.e_far } else { t.e_near };
    let q = half * sc.inv_s / t.fac;
    let da = if t.inside { q * dir * (t.e_near - t.e_far) } else { dir * sc.inv_s };
    let above = if near_start { F::ZERO } else { sc.inv_s };
    let dl = if t.inside { q * e2 - sc.inv_len } else { above + sc.dtail_dlen - sc.inv_len };
    let diff = beta - mu;
    let sgn = if diff > F::ZERO {
        one
    } else if diff < F::ZERO {
        -one
    } else {
        F::ZERO
    };
    (da, dl, sgn, diff.abs())
}

/// Per point: `log g` and its partials with respect to `ln phi_e` (`p_e`), `mu_e`
/// (`m_e`), `b_e` (`b_e`) and the row's `x, y, yaw, l, w`. Every output is its own
/// argument, so the compiler knows they do not alias and vectorises across points.
#[inline(never)]
#[allow(clippy::too_many_arguments, clippy::needless_range_loop)]
fn row_grad_pass<F: Float>(
    rc: &RowConsts<'_, F>,
    px: &[F],
    py: &[F],
    lg: &mut [F],
    p0: &mut [F],
    p1: &mut [F],
    p2: &mut [F],
    p3: &mut [F],
    m0: &mut [F],
    m1: &mut [F],
    m2: &mut [F],
    m3: &mut [F],
    b0: &mut [F],
    b1: &mut [F],
    b2: &mut [F],
    b3: &mut [F],
    gx: &mut [F],
    gy: &mut [F],
    gyaw: &mut [F],
    gl: &mut [F],
    gw: &mut [F],
) {
    let n = px.len();
    let (px, py) = (&px[..n], &py[..n]);
    let (lg, p0, p1, p2, p3) = (&mut lg[..n], &mut p0[..n], &mut p1[..n], &mut p2[..n], &mut p3[..n]);
    let (m0, m1, m2, m3) = (&mut m0[..n], &mut m1[..n], &mut m2[..n], &mut m3[..n]);
    let (b0, b1, b2, b3) = (&mut b0[..n], &mut b1[..n], &mut b2[..n], &mut b3[..n]);
    let (gx, gy, gyaw, gl, gw) = (&mut gx[..n], &mut gy[..n], &mut gyaw[..n], &mut gl[..n], &mut gw[..n]);
    let (bc, k, mu, ib) = (rc.bc, &rc.k, &rc.mu, &rc.ib);
    let (hl, hw, c, s) = (bc.hl, bc.hw, rc.c, rc.s);
    let (one, half) = (F::ONE, F::from_f64(0.5));
    let (sw, sl) = (&bc.sw, &bc.sl);
    for p in 0..n {
        let dx = px[p] - rc.x;
        let dy = py[p] - rc.y;
        let u = c * dx + s * dy;
        let v = c * dy - s * dx;
        let (a0, be0, a1, be1, a2, be2, a3, be3) = (v + hw, u - hl, hl - u, v - hw, hw - v, -u - hl, u + hl, -v - hw);
        let t = [
            edge_term::<F, true>(a0, be0, k[0], mu[0], ib[0], sw),
            edge_term::<F, true>(a1, be1, k[1], mu[1], ib[1], sl),
            edge_term::<F, true>(a2, be2, k[2], mu[2], ib[2], sw),
            edge_term::<F, true>(a3, be3, k[3], mu[3], ib[3], sl),
        ];
        let mx = fmax(fmax(t[0].ub, t[1].ub), fmax(t[2].ub, t[3].ub));
        let e0 = t[0].fac * (t[0].ub - mx).exp();
        let e1 = t[1].fac * (t[1].ub - mx).exp();
        let e2 = t[2].fac * (t[2].ub - mx).exp();
        let e3 = t[3].fac * (t[3].ub - mx).exp();
        let total = e0 + e1 + e2 + e3;
        lg[p] = mx + total.ln();
        let inv = one / total;
        // Responsibilities of the edges.
        let (r0, r1, r2, r3) = (e0 * inv, e1 * inv, e2 * inv, e3 * inv);
        let (da0, dl0, s0, ad0) = edge_partials(&t[0], a0, be0, mu[0], sw);
        let (da1, dl1, s1, ad1) = edge_partials(&t[1], a1, be1, mu[1], sl);
        let (da2, dl2, s2, ad2) = edge_partials(&t[2], a2, be2, mu[2], sw);
        let (da3, dl3, s3, ad3) = edge_partials(&t[3], a3, be3, mu[3], sl);
        p0[p] = r0;
        p1[p] = r1;
        p2[p] = r2;
        p3[p] = r3;
        // d log g / d mu_e = -d log g / d beta_e.
        let (q0, q1, q2, q3) = (r0 * s0 * ib[0], r1 * s1 * ib[1], r2 * s2 * ib[2], r3 * s3 * ib[3]);
        m0[p] = q0;
        m1[p] = q1;
        m2[p] = q2;
        m3[p] = q3;
        b0[p] = r0 * (ad0 * ib[0] - one) * ib[0];
        b1[p] = r1 * (ad1 * ib[1] - one) * ib[1];
        b2[p] = r2 * (ad2 * ib[2] - one) * ib[2];
        b3[p] = r3 * (ad3 * ib[3] - one) * ib[3];
        // d log g / d alpha_e.
        let (ga0, ga1, ga2, ga3) = (r0 * da0, r1 * da1, r2 * da2, r3 * da3);
        // Chain rule through the edge coordinates (module table of `edges`).
        let gu = ga3 - ga1 - q0 + q2;
        let gv = ga0 - ga2 - q1 + q3;
        gx[p] = s * gv - c * gu;
        gy[p] = -s * gu - c * gv;
        gyaw[p] = v * gu - u * gv;
        gl[p] = half * (ga1 + ga3 + q0 + q2) + r1 * dl1 + r3 * dl3;
        gw[p] = half * (ga0 + ga2 + q1 + q3) + r0 * dl0 + r2 * dl2;
    }
}

/// Runs the fused kernel over all rows (in parallel for large batches) into
/// `out` (`ROW_OUT` values per row, `ROW_OUT + CLUTTER_OUT` with clutter).
#[allow(clippy::too_many_arguments)]
fn rows_kernel<F: Float>(
    head: &[F],
    x: &[F],
    y: &[F],
    yaw: &[F],
    length: &[F],
    width: &[F],
    items: &[&[[f64; 2]]],
    scale: f64,
    clutter: Option<&ClutterConsts<F>>,
    grad: bool,
    par: Parallelism,
    out: &mut [f64],
) {
    let stride = row_stride(clutter.is_some());
    let task = |first: usize, chunk: &mut [f64]| {
        let mut cols: [Vec<F>; COLS] = std::array::from_fn(|_| Vec::new());
        let mut cached: Option<(F, F, BoxConsts<F>)> = None;
        for (j, o) in chunk.chunks_mut(stride).enumerate() {
            let r = first + j;
            let bc = match cached {
                Some((l, w, bc)) if l == length[r] && w == width[r] => bc,
                _ => {
                    let bc = BoxConsts::new(length[r].to_f64(), width[r].to_f64(), scale);
                    cached = Some((length[r], width[r], bc));
                    bc
                }
            };
            let row = RowInput {
                head: &head[r * 3 * NUM_EDGES..(r + 1) * 3 * NUM_EDGES],
                x: x[r],
                y: y[r],
                yaw: yaw[r],
                points: items[r],
            };
            if grad {
                row_kernel::<F, true>(&row, &bc, clutter, &mut cols, o);
            } else {
                row_kernel::<F, false>(&row, &bc, clutter, &mut cols, o);
            }
        }
    };
    let pairs: usize = items.iter().map(|p| p.len()).sum();
    if par == Parallelism::Rayon && pairs >= PAR_MIN_PAIRS {
        out.par_chunks_mut(stride * ROWS_PER_TASK).enumerate().for_each(|(c, chunk)| task(c * ROWS_PER_TASK, chunk));
    } else {
        task(0, out);
    }
}

impl ObservationModel for PointObservationModel {
    type Item = [f64; 2];
    const KIND: ObservationKind = ObservationKind::Points;

    fn init_params<R: Rng + ?Sized>(store: &mut ParamStore<f64>, prefix: &str, rng: &mut R) -> Self {
        let mut rng = rng;
        let mlp = Mlp::new(store, prefix, &POINT_NET_LAYERS, Activation::Tanh, Activation::Identity, &mut rng);
        PointObservationModel { mlp, soft_scale: DEFAULT_SOFT_SCALE }
    }

    fn num_params(&self) -> usize {
        self.mlp.num_params()
    }

    #[track_caller]
    fn items(data: &Dataset, object: usize, t: usize) -> &[[f64; 2]] {
        match data.points() {
            Some(p) => p.get(object, t),
            None => panic!("PointObservationModel::items: the dataset holds box detections, not points"),
        }
    }

    #[track_caller]
    fn log_likelihood<F: Float>(
        &self,
        params: &ParamStore<F>,
        ctx: &ObsContext,
        poses: PosesRef<'_, F>,
        items: &[[f64; 2]],
        scratch: &mut Scratch<F>,
        out: &mut [F],
    ) {
        let n = poses.len();
        assert_eq!(out.len(), n, "PointObservationModel::log_likelihood: {n} poses, room for {}", out.len());
        if items.is_empty() || n == 0 {
            out.fill(F::ZERO);
            return;
        }
        self.prepare(params, ctx, poses, scratch);
        let pc = PointConsts::new(ctx.length, ctx.width, self.soft_scale);
        for start in (0..n).step_by(BLOCK) {
            let range = start..n.min(start + BLOCK);
            let blk = Block::new(poses, scratch, n, range.clone());
            if pc.far {
                block_log_likelihood::<F, true>(&blk, items, &pc, &mut out[range]);
            } else {
                block_log_likelihood::<F, false>(&blk, items, &pc, &mut out[range]);
            }
        }
    }

    #[track_caller]
    fn log_density_items(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        items: &[[f64; 2]],
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
        let pc = PointConsts::new(ctx.length, ctx.width, self.soft_scale);
        let blk = Block::new(poses, &scratch, 1, 0..1);
        let sink = |j: usize, lg: &[f64]| out[j] = lg[0];
        let mut lg = [0.0];
        if pc.far {
            block_log_densities::<f64, true>(&blk, items, &pc, &mut lg, sink);
        } else {
            block_log_densities::<f64, false>(&blk, items, &pc, &mut lg, sink);
        }
    }

    #[track_caller]
    fn log_likelihood_rows<'t, F: Float>(
        &self,
        params: &BoundParams<'t, F>,
        rows: &RowVars<'t, F>,
        av: &[Pose],
        items: &[&[[f64; 2]]],
    ) -> Var<'t, F> {
        self.rows_log_likelihood(params, rows, av, items, None, "PointObservationModel::log_likelihood_rows")
    }

    fn sample<R: Rng + ?Sized>(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        n: usize,
        rng: &mut R,
        out: &mut Vec<[f64; 2]>,
    ) {
        let m = self.edge_mixture(params, ctx, pose);
        let lens = edge_lengths(ctx.length, ctx.width);
        let (hl, hw) = (0.5 * ctx.length, 0.5 * ctx.width);
        out.reserve(n);
        for _ in 0..n {
            let mut u: f64 = rng.random();
            let mut e = NUM_EDGES - 1;
            for (k, &p) in m.phi.iter().enumerate() {
                if u < p {
                    e = k;
                    break;
                }
                u -= p;
            }
            let alpha = sample_soft_uniform(lens[e], self.soft_scale, rng);
            let beta = sample_laplace(m.mu[e], m.b[e], rng);
            let (bu, bv) = edge_point(e, alpha, beta, hl, hw);
            out.push(from_box_frame(pose, bu, bv));
        }
    }
}
