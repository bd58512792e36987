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
//! This module owns the model (its parameters, the [`EdgeMixture`] of a state, the
//! sampler) and, one file each, its three evaluation kernels and the clutter term:
//!
//! * `kernels.rs`, the filter's hot loop ([`ObservationModel::log_likelihood`]): blocks of
//!   particles that stay in L1 while all points are visited, a branch-free loop
//!   over the block that vectorises, two exponentials for the soft uniform (both
//!   edges of a pair share the distance to their nearer end) and four for the
//!   mixture per particle-point, and one logarithm per particle for up to 60
//!   points (the points' mixture sums are multiplied; their range is bounded);
//! * `tape.rs`, the tape path ([`ObservationModel::log_likelihood_rows`]) as one *fused*
//!   node in the manner of Stan ([`autodiff::Tape::precomputed`]): the network runs
//!   on the tape; the sum over a row's points of `log g` and its partial derivatives
//!   with respect to the row's 12 mixture quantities `(ln phi, mu, b)` and its
//!   `(x, y, yaw, l, w)` are computed in plain code, vectorised across the rows
//!   that share an observation (the particles of one object at one step), and
//!   enter the tape as one node — exact value, exact gradient, and a tape of
//!   `O(R)` rather than `O(points x edges)` elements;
//! * the per-point f64 path (AOTLL) through the same hot kernel;
//! * `clutter.rs`, the [`Clutter`] extension on all three paths (below).
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
use autodiff::{Float, Var};
use rand::Rng;

use super::edges::{
    edge_lengths, edge_point, from_box_frame, sample_laplace, sample_soft_uniform, DEFAULT_SOFT_SCALE, NUM_EDGES,
};
use super::features::NUM_FEATURES;
use super::{net, ObsContext, ObservationModel, PosesRef, RowVars, Scratch};
use crate::data::{Dataset, ObservationKind, Pose};

mod clutter;
mod kernels;
mod tape;

pub use clutter::Clutter;
use kernels::{block_log_densities, block_log_likelihood, Block, PointConsts, BLOCK};

/// Widths of the point network, input first (SPEC §3: 4 hidden layers of 16 tanh).
pub const POINT_NET_LAYERS: [usize; 6] = [NUM_FEATURES, 16, 16, 16, 16, 3 * NUM_EDGES];
/// `mu_e = POINT_OFFSET_SCALE * o[4 + e]` (m): order-one outputs give offsets of a
/// few tens of centimetres.
pub const POINT_OFFSET_SCALE: f64 = 0.2;
/// `b_e = POINT_SCALE_SCALE * softplus(o[8 + e]) + POINT_MIN_SCALE` (m).
pub const POINT_SCALE_SCALE: f64 = 0.2;
/// Floor of the Laplace scales `b_e` (m).
pub const POINT_MIN_SCALE: f64 = 0.01;

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
