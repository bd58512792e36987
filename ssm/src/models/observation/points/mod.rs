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
//! This file (`mod.rs`) owns the model type, its parameters (the network layout and the
//! output scalings), the per-state [`EdgeMixture`] and the sampler; the model's
//! evaluation paths live beside it:
//!
//! * `kernels`: the filter's hot loop ([`ObservationModel::log_likelihood`]) and the
//!   per-point f64 path (AOTLL, [`ObservationModel::log_density_items`]) through the
//!   same kernel;
//! * `tape`: the tape path ([`ObservationModel::log_likelihood_rows`]) as one
//!   *fused* node of exact value and gradient;
//! * `clutter`: the [`Clutter`] extension on all three paths and in the sampler.
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

mod clutter;
mod kernels;
mod tape;

pub use clutter::Clutter;

use autodiff::nn::{Activation, BoundParams, Mlp, ParamStore};
use autodiff::{Float, Var};
use rand::Rng;

use super::edges::{
    edge_lengths, edge_point, from_box_frame, sample_laplace, sample_soft_uniform, DEFAULT_SOFT_SCALE, NUM_EDGES,
};
use super::features::NUM_FEATURES;
use super::{check_item_outputs, needs_kernels, net, ObsContext, ObservationModel, PosesRef, RowVars, Scratch};
use crate::data::{Dataset, ObservationKind, Pose};
use kernels::{block_log_likelihood, Block, PointConsts, BLOCK};

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
        net::forward_plain(&self.mlp, params, ctx, PosesRef::one(&pose), &mut scratch);
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
        if !needs_kernels("PointObservationModel::log_likelihood", n, items.len(), out) {
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
        check_item_outputs(items.len(), out.len());
        if items.is_empty() {
            return;
        }
        let mut scratch = Scratch::new();
        self.block_densities(params, ctx, PosesRef::one(&pose), items, &mut scratch, |_, j, lg| out[j] = lg[0]);
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
