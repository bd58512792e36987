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
//!   node in the manner of Stan ([`autodiff::Tape::precomputed`]): the network runs
//!   on the tape; the sum over a row's points of `log g` and its partial derivatives
//!   with respect to the row's 12 mixture quantities `(ln phi, mu, b)` and its
//!   `(x, y, yaw, l, w)` are computed in plain code, vectorised across the rows
//!   that share an observation (the particles of one object at one step), and
//!   enter the tape as one node — exact value, exact gradient, and a tape of
//!   `O(R)` rather than `O(points x edges)` elements;
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
use autodiff::{Float, Parallelism, Tape, Tensor, Var};
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
/// Rows per parallel task of the fused kernel (fixed: results never depend on threads).
const ROWS_PER_TASK: usize = 64;
/// Rows per tile of the fused kernel: rows that share their points and box are
/// processed this many at a time, vectorised across rows (a multiple of the f32
/// vector width).
const TILE_ROWS: usize = 64;
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
/// use ssm::models::observation::points::Clutter;
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
        Self::new(-lambda.softplus(), -(-lambda).softplus(), sigma)
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
    /// use ssm::models::observation::{ObsContext, ObservationModel, PointObservationModel, RowVars};
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
    /// the fused kernel, and one [`autodiff::Tape::precomputed`] node holding the
    /// rows' values and their partials.
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
        let head = RowsHead::new(tape, &o.value().data(), r);
        let row_vars = [rows.x, rows.y, rows.yaw, rows.length, rows.width];
        let clutter_vars = clutter.as_ref().map_or(&[][..], |c| &c[..]);
        let grad =
            tape.is_recording() && (o.is_tracked() || row_vars.iter().chain(clutter_vars).any(|v| v.is_tracked()));
        let stride = row_stride(cc.is_some());
        let mut k = vec![0.0f64; r * stride];
        {
            let vals: Vec<_> = row_vars.iter().map(|v| v.value()).collect();
            let slices = RowSlices {
                head: &head.head,
                x: vals[0].data(),
                y: vals[1].data(),
                yaw: vals[2].data(),
                length: vals[3].data(),
                width: vals[4].data(),
                items,
            };
            rows_kernel(&slices, self.soft_scale, cc.as_ref(), grad, tape.parallelism(), &mut k);
        }
        let column = |j: usize| {
            let mut c = tape.buffer(r);
            for (c, k) in c.iter_mut().zip(k.chunks(stride)) {
                *c = F::from_f64(k[j]);
            }
            Tensor::from_vec(c)
        };
        if !grad {
            return tape.constant(column(0));
        }
        let mut partials = Vec::new();
        if o.is_tracked() {
            let g = head.chain(tape, &k, stride);
            partials.push((o, Tensor::new(&[r, 3 * NUM_EDGES], g)));
        }
        // Row variables have shape [R]; the clutter's shape [1] broadcasts over rows.
        let tracked = row_vars.iter().enumerate().map(|(j, v)| (1 + 3 * NUM_EDGES + j, v));
        let tracked = tracked.chain(clutter_vars.iter().enumerate().map(|(j, v)| (ROW_OUT + j, v)));
        for (j, v) in tracked {
            if v.is_tracked() {
                partials.push((*v, column(j)));
            }
        }
        tape.precomputed(column(0), partials)
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

/// The mixture quantities of tape rows computed from the network's outputs, with
/// what the chain rule back to the outputs needs, all feature-major (`[k * R + r]`).
struct RowsHead<F> {
    /// `(ln phi, mu, b)`: `ln phi = log_softmax(o[0..4])`, `mu = POINT_OFFSET_SCALE
    /// o[4..8]`, `b = POINT_SCALE_SCALE softplus(o[8..12]) + POINT_MIN_SCALE`.
    head: Vec<F>,
    /// `phi` (4 columns), then `d b / d o = POINT_SCALE_SCALE sigmoid(o[8..12])` (4).
    slopes: Vec<F>,
}

impl<F: Float> RowsHead<F> {
    /// From the outputs `o` (`[R, 12]`, row-major) of `r` rows, in buffers of `tape`.
    #[allow(clippy::needless_range_loop)] // index loops over resliced columns vectorise
    fn new(tape: &Tape<F>, o: &[F], r: usize) -> Self {
        let f = F::from_f64;
        let (mu_scale, b_scale, b_min) = (f(POINT_OFFSET_SCALE), f(POINT_SCALE_SCALE), f(POINT_MIN_SCALE));
        // Every element of both is written below.
        let mut head = tape.buffer(3 * NUM_EDGES * r);
        for (i, row) in o.chunks(3 * NUM_EDGES).enumerate() {
            for (j, &v) in row.iter().enumerate() {
                head[j * r + i] = v;
            }
        }
        let mut slopes = tape.buffer(2 * NUM_EDGES * r);
        let (logits, rest) = head.split_at_mut(NUM_EDGES * r);
        let (mu, b) = rest.split_at_mut(NUM_EDGES * r);
        let (phi, db) = slopes.split_at_mut(NUM_EDGES * r);
        {
            let (l0, rest) = logits.split_at_mut(r);
            let (l1, rest) = rest.split_at_mut(r);
            let (l2, l3) = rest.split_at_mut(r);
            let (p0, rest) = phi.split_at_mut(r);
            let (p1, rest) = rest.split_at_mut(r);
            let (p2, p3) = rest.split_at_mut(r);
            let (l0, l1, l2, l3) = (&mut l0[..r], &mut l1[..r], &mut l2[..r], &mut l3[..r]);
            let (p0, p1, p2, p3) = (&mut p0[..r], &mut p1[..r], &mut p2[..r], &mut p3[..r]);
            for i in 0..r {
                let m = l0[i].max(l1[i]).max(l2[i].max(l3[i]));
                let (e0, e1, e2, e3) = ((l0[i] - m).exp(), (l1[i] - m).exp(), (l2[i] - m).exp(), (l3[i] - m).exp());
                let total = e0 + e1 + e2 + e3;
                let shift = m + total.ln();
                let inv = F::ONE / total;
                (l0[i], l1[i], l2[i], l3[i]) = (l0[i] - shift, l1[i] - shift, l2[i] - shift, l3[i] - shift);
                (p0[i], p1[i], p2[i], p3[i]) = (e0 * inv, e1 * inv, e2 * inv, e3 * inv);
            }
        }
        for v in mu.iter_mut() {
            *v = *v * mu_scale;
        }
        for (v, d) in b.iter_mut().zip(db.iter_mut()) {
            *d = b_scale * v.sigmoid();
            *v = v.softplus() * b_scale + b_min;
        }
        RowsHead { head, slopes }
    }

    /// The partials of the rows with respect to the outputs `o` (`[R, 12]`,
    /// row-major) from those with respect to `(ln phi, mu, b)` (`k[r * stride +
    /// 1..13]`): `g_logit = g_lnphi - phi sum(g_lnphi)`, `g_o = POINT_OFFSET_SCALE
    /// g_mu` and `(d b / d o) g_b`.
    fn chain(&self, tape: &Tape<F>, k: &[f64], stride: usize) -> Vec<F> {
        let r = k.len() / stride;
        // Every element is written below.
        let mut g = tape.buffer(3 * NUM_EDGES * r);
        for (i, (g, k)) in g.chunks_mut(3 * NUM_EDGES).zip(k.chunks(stride)).enumerate() {
            let gh = &k[1..1 + 3 * NUM_EDGES];
            let total: f64 = gh[..NUM_EDGES].iter().sum();
            for e in 0..NUM_EDGES {
                let (phi, db) = (self.slopes[e * r + i].to_f64(), self.slopes[(NUM_EDGES + e) * r + i].to_f64());
                g[e] = F::from_f64(gh[e] - phi * total);
                g[NUM_EDGES + e] = F::from_f64(POINT_OFFSET_SCALE * gh[NUM_EDGES + e]);
                g[2 * NUM_EDGES + e] = F::from_f64(db * gh[2 * NUM_EDGES + e]);
            }
        }
        g
    }
}

/// Per-row constants of a tile of rows that share their points and box, one array
/// per quantity (structure of arrays: the passes below vectorise across rows), and
/// the tile's work columns.
struct Tile<F> {
    /// `ln phi_e - ln(2 b_e) - ln L_e`, per edge.
    k: [[F; TILE_ROWS]; NUM_EDGES],
    /// Laplace means `mu_e`, per edge.
    mu: [[F; TILE_ROWS]; NUM_EDGES],
    /// `1 / b_e`, per edge.
    ib: [[F; TILE_ROWS]; NUM_EDGES],
    /// Cosine of the heading.
    c: [F; TILE_ROWS],
    /// Sine of the heading.
    s: [F; TILE_ROWS],
    /// Position x.
    x: [F; TILE_ROWS],
    /// Position y.
    y: [F; TILE_ROWS],
    /// One point's outputs, `[output][row]`, in the kernel's type.
    val: [[F; TILE_ROWS]; ROW_OUT + CLUTTER_OUT],
    /// Sums over the points so far of every output, `[output][row]`, in f64.
    acc: [[f64; TILE_ROWS]; ROW_OUT + CLUTTER_OUT],
}

impl<F: Float> Tile<F> {
    /// A zeroed tile on the heap (it holds about 15 KB).
    fn new() -> Box<Self> {
        Box::new(Tile {
            k: [[F::ZERO; TILE_ROWS]; NUM_EDGES],
            mu: [[F::ZERO; TILE_ROWS]; NUM_EDGES],
            ib: [[F::ZERO; TILE_ROWS]; NUM_EDGES],
            c: [F::ZERO; TILE_ROWS],
            s: [F::ZERO; TILE_ROWS],
            x: [F::ZERO; TILE_ROWS],
            y: [F::ZERO; TILE_ROWS],
            val: [[F::ZERO; TILE_ROWS]; ROW_OUT + CLUTTER_OUT],
            acc: [[0.0; TILE_ROWS]; ROW_OUT + CLUTTER_OUT],
        })
    }

    /// Loads the constants of rows `first..first + m` and clears the first `used`
    /// sums.
    #[allow(clippy::too_many_arguments)]
    fn load(&mut self, bc: &BoxConsts<F>, rows: &RowSlices<'_, F>, first: usize, m: usize, used: usize) {
        let (one, two) = (F::ONE, F::from_f64(2.0));
        let lens = [&bc.sw, &bc.sl, &bc.sw, &bc.sl];
        let (n, rows_m) = (rows.x.len(), first..first + m);
        let h = |j: usize| &rows.head[j * n..(j + 1) * n][rows_m.clone()];
        for e in 0..NUM_EDGES {
            let (lnphi, mu, b) = (h(e), h(NUM_EDGES + e), h(2 * NUM_EDGES + e));
            for i in 0..m {
                self.k[e][i] = lnphi[i] - (two * b[i]).ln() - lens[e].ln_len;
                self.mu[e][i] = mu[i];
                self.ib[e][i] = one / b[i];
            }
        }
        let (yaw, x, y) = (&rows.yaw[rows_m.clone()], &rows.x[rows_m.clone()], &rows.y[rows_m]);
        for i in 0..m {
            self.c[i] = yaw[i].cos();
            self.s[i] = yaw[i].sin();
            self.x[i] = x[i];
            self.y[i] = y[i];
        }
        for a in self.acc[..used].iter_mut() {
            a[..m].fill(0.0);
        }
    }

    /// `acc[j][i] += val[j][i]` in f64 for the first `used` outputs and `m` rows.
    /// A pass of its own: mixing the f64 sums into [`tile_point`] keeps the compiler
    /// from vectorising it.
    #[inline(never)]
    fn accumulate(&mut self, used: usize, m: usize) {
        for (a, v) in self.acc[..used].iter_mut().zip(&self.val[..used]) {
            for (a, v) in a[..m].iter_mut().zip(&v[..m]) {
                *a += v.to_f64();
            }
        }
    }
}

/// One point against the first `m` rows of a tile, vectorised across rows, into
/// `val`: `log g` (`log g_c` with `CLUTTER`) and, with `GRAD`, its partials with
/// respect to `ln phi_e`, `mu_e`, `b_e`, the row's `x, y, yaw, l, w` and, with
/// `CLUTTER`, the clutter's `lambda` and `sigma` (the order of [`ROW_OUT`] and
/// [`CLUTTER_OUT`]). With clutter every partial of the box component is scaled by
/// its responsibility `r`; the position's partials also get the clutter term's
/// `(1 - r) (p - centre) / s^2`, and `lambda`, `sigma` get `1 - r - eps` and
/// `(1 - r) (d^2 / s^2 - 2)`.
#[inline(never)]
#[allow(clippy::needless_range_loop)] // index loops over resliced arrays vectorise
fn tile_point<F: Float, const GRAD: bool, const CLUTTER: bool>(
    t: &mut Tile<F>,
    m: usize,
    bc: &BoxConsts<F>,
    cc: &ClutterConsts<F>,
    px: F,
    py: F,
) {
    let (one, half, two) = (F::ONE, F::from_f64(0.5), F::from_f64(2.0));
    let (hl, hw) = (bc.hl, bc.hw);
    let (sw, sl) = (&bc.sw, &bc.sl);
    let Tile { k, mu, ib, c, s, x, y, val, .. } = t;
    let (k0, k1, k2, k3) = (&k[0][..m], &k[1][..m], &k[2][..m], &k[3][..m]);
    let (mu0, mu1, mu2, mu3) = (&mu[0][..m], &mu[1][..m], &mu[2][..m], &mu[3][..m]);
    let (ib0, ib1, ib2, ib3) = (&ib[0][..m], &ib[1][..m], &ib[2][..m], &ib[3][..m]);
    let (c, s, x, y) = (&c[..m], &s[..m], &x[..m], &y[..m]);
    let [lgs, p0, p1, p2, p3, m0, m1, m2, m3, b0, b1, b2, b3, gxs, gys, gyaw, gl, gw, dlambda, dsigma] = val;
    for i in 0..m {
        let dx = px - x[i];
        let dy = py - y[i];
        let u = c[i] * dx + s[i] * dy;
        let v = c[i] * dy - s[i] * dx;
        let (a0, be0, a1, be1, a2, be2, a3, be3) = (v + hw, u - hl, hl - u, v - hw, hw - v, -u - hl, u + hl, -v - hw);
        let t = [
            edge_term::<F, true>(a0, be0, k0[i], mu0[i], ib0[i], sw),
            edge_term::<F, true>(a1, be1, k1[i], mu1[i], ib1[i], sl),
            edge_term::<F, true>(a2, be2, k2[i], mu2[i], ib2[i], sw),
            edge_term::<F, true>(a3, be3, k3[i], mu3[i], ib3[i], sl),
        ];
        let mx = fmax(fmax(t[0].ub, t[1].ub), fmax(t[2].ub, t[3].ub));
        let e0 = t[0].fac * (t[0].ub - mx).exp();
        let e1 = t[1].fac * (t[1].ub - mx).exp();
        let e2 = t[2].fac * (t[2].ub - mx).exp();
        let e3 = t[3].fac * (t[3].ub - mx).exp();
        let total = e0 + e1 + e2 + e3;
        let lg = mx + total.ln();
        if !GRAD {
            lgs[i] = if CLUTTER { clutter_mix(lg, dx, dy, cc).lg } else { lg };
            continue;
        }
        let inv = one / total;
        // Responsibilities of the edges.
        let (r0, r1, r2, r3) = (e0 * inv, e1 * inv, e2 * inv, e3 * inv);
        let (da0, dl0, s0, ad0) = edge_partials(&t[0], a0, be0, mu0[i], sw);
        let (da1, dl1, s1, ad1) = edge_partials(&t[1], a1, be1, mu1[i], sl);
        let (da2, dl2, s2, ad2) = edge_partials(&t[2], a2, be2, mu2[i], sw);
        let (da3, dl3, s3, ad3) = edge_partials(&t[3], a3, be3, mu3[i], sl);
        // d log g / d mu_e = -d log g / d beta_e.
        let (q0, q1, q2, q3) = (r0 * s0 * ib0[i], r1 * s1 * ib1[i], r2 * s2 * ib2[i], r3 * s3 * ib3[i]);
        // d log g / d alpha_e.
        let (ga0, ga1, ga2, ga3) = (r0 * da0, r1 * da1, r2 * da2, r3 * da3);
        // Chain rule through the edge coordinates (module table of `edges`).
        let gu = ga3 - ga1 - q0 + q2;
        let gv = ga0 - ga2 - q1 + q3;
        let gx = s[i] * gv - c[i] * gu;
        let gy = -s[i] * gu - c[i] * gv;
        // The box component's responsibility `r` (1 without clutter) scales its partials.
        let (lg, r, gx, gy) = if CLUTTER {
            let cm = clutter_mix(lg, dx, dy, cc);
            let r = one - cm.q;
            // d ln c / d(x, y) = (p - centre) / s^2.
            let qp = cm.q * cc.prec;
            dlambda[i] = cm.q - cc.eps;
            dsigma[i] = cm.q * (cm.d2 * cc.prec - two);
            (cm.lg, r, r * gx + qp * dx, r * gy + qp * dy)
        } else {
            (lg, one, gx, gy)
        };
        let sc = |v: F| if CLUTTER { v * r } else { v };
        lgs[i] = lg;
        p0[i] = sc(r0);
        p1[i] = sc(r1);
        p2[i] = sc(r2);
        p3[i] = sc(r3);
        m0[i] = sc(q0);
        m1[i] = sc(q1);
        m2[i] = sc(q2);
        m3[i] = sc(q3);
        b0[i] = sc(r0 * (ad0 * ib0[i] - one) * ib0[i]);
        b1[i] = sc(r1 * (ad1 * ib1[i] - one) * ib1[i]);
        b2[i] = sc(r2 * (ad2 * ib2[i] - one) * ib2[i]);
        b3[i] = sc(r3 * (ad3 * ib3[i] - one) * ib3[i]);
        gxs[i] = gx;
        gys[i] = gy;
        gyaw[i] = sc(v * gu - u * gv);
        gl[i] = sc(half * (ga1 + ga3 + q0 + q2) + r1 * dl1 + r3 * dl3);
        gw[i] = sc(half * (ga0 + ga2 + q1 + q3) + r0 * dl0 + r2 * dl2);
    }
}

/// The per-row inputs of the fused kernel, in its float type: `head` is `(ln phi,
/// mu, b)` feature-major (`[k * R + r]`, 12 columns), the rest `[R]`; `items[r]`
/// are row `r`'s points.
struct RowSlices<'a, F> {
    head: &'a [F],
    x: &'a [F],
    y: &'a [F],
    yaw: &'a [F],
    length: &'a [F],
    width: &'a [F],
    items: &'a [&'a [[f64; 2]]],
}

impl<F: Float> RowSlices<'_, F> {
    /// Whether rows `a` and `b` share their points (the same slice) and box.
    #[inline]
    fn same_group(&self, a: usize, b: usize) -> bool {
        std::ptr::eq(self.items[a], self.items[b]) && self.length[a] == self.length[b] && self.width[a] == self.width[b]
    }
}

/// The fused kernel over all rows, into `out` (`row_stride(clutter)` values per
/// row): `out[0]` the sum over the row's points of `log g` (of `log g_c` with
/// `clutter`) and, if `grad`, `out[1..]` its partials (the order of [`ROW_OUT`] and
/// [`CLUTTER_OUT`]).
///
/// Consecutive rows that share their points and box (one object at one step: the
/// particles of a filter, the distinct ancestors of PF-SEFI) form tiles of up to
/// [`TILE_ROWS`] rows; each point is one vectorised pass over a tile. Every
/// row's sums run over its points in order, in f64, so a row's result does not
/// depend on how rows are tiled or split between threads.
fn rows_kernel<F: Float>(
    rows: &RowSlices<'_, F>,
    scale: f64,
    clutter: Option<&ClutterConsts<F>>,
    grad: bool,
    par: Parallelism,
    out: &mut [f64],
) {
    let stride = row_stride(clutter.is_some());
    let used = if grad { stride } else { 1 };
    // Unused without clutter (the passes that read it are not instantiated).
    let no_clutter = ClutterConsts::new(0.0, f64::NEG_INFINITY, 0.0);
    let cc = clutter.unwrap_or(&no_clutter);
    let task = |first: usize, chunk: &mut [f64]| {
        let mut tile = Tile::<F>::new();
        let n = chunk.len() / stride;
        let mut start = 0;
        while start < n {
            let r0 = first + start;
            let mut m = 1;
            while m < TILE_ROWS && start + m < n && rows.same_group(r0, r0 + m) {
                m += 1;
            }
            let bc = BoxConsts::new(rows.length[r0].to_f64(), rows.width[r0].to_f64(), scale);
            tile.load(&bc, rows, r0, m, used);
            for p in rows.items[r0] {
                let (px, py) = (F::from_f64(p[0]), F::from_f64(p[1]));
                match (grad, clutter.is_some()) {
                    (false, false) => tile_point::<F, false, false>(&mut tile, m, &bc, cc, px, py),
                    (false, true) => tile_point::<F, false, true>(&mut tile, m, &bc, cc, px, py),
                    (true, false) => tile_point::<F, true, false>(&mut tile, m, &bc, cc, px, py),
                    (true, true) => tile_point::<F, true, true>(&mut tile, m, &bc, cc, px, py),
                }
                tile.accumulate(used, m);
            }
            for (i, o) in chunk[start * stride..(start + m) * stride].chunks_mut(stride).enumerate() {
                o.fill(0.0);
                for (o, a) in o[..used].iter_mut().zip(&tile.acc) {
                    *o = a[i];
                }
            }
            start += m;
        }
    };
    let pairs: usize = rows.items.iter().map(|p| p.len()).sum();
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
