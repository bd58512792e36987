//! The plain (no-tape) forward pass of a multilayer perceptron over a batch of
//! particles, feature-major in and out (`[k * n + i]`): what the filter runs for
//! the observation networks and the neural policy, whose tape versions
//! ([`autodiff::nn::Mlp::forward`] and the policy's `gaussians_on_tape`) the
//! estimators differentiate.
//!
//! The particles go through the whole network in blocks of [`NET_BLOCK`]: each
//! layer's output `j` for a block is accumulated in registers (`NET_BLOCK / LANES`
//! vectors: 8 of AVX2, 4 of AVX-512) over the layer's inputs, one broadcast weight and one fused multiply-add
//! per vector and input, and activated there; a block's layers stay in L1. For the
//! point network (7 -> 16 x 4 -> 12, 1,072 multiply-adds per particle) this replaced
//! one GEMM call per layer (matrixmultiply, whose packing and 8 x 8 tiles with 16
//! products each cost about three times the multiply-adds themselves, and which
//! allocated its packing buffer on every call) and a separate bias-and-activation
//! pass over memory; for the policy (2 -> 32 -> 32 -> 5) it replaced the same GEMM
//! calls on a non-recording tape.

use autodiff::nn::{Activation, Mlp};
use autodiff::{Float, Tensor};

/// Particles per block of the forward pass: a layer's input rows for a block stay
/// in L1 (a 32-wide layer is 8 KiB of f32) while its outputs are accumulated.
pub(crate) const NET_BLOCK: usize = 64;

/// Runs `mlp` on the feature-major `input` (`inputs * n`), writing the outputs
/// feature-major into `out` (resized to `outputs * n`); `params` are the network's
/// parameters indexed by their [`autodiff::nn::ParamId`]s (a store's values);
/// `hidden` holds one block's layers.
#[track_caller]
pub(crate) fn forward_feature_major<F: Float>(
    mlp: &Mlp,
    params: &[Tensor<F>],
    n: usize,
    input: &[F],
    hidden: &mut [Vec<F>; 2],
    out: &mut Vec<F>,
) {
    let layers = &mlp.layers;
    assert!(!layers.is_empty(), "observation network without layers");
    assert_eq!(input.len(), layers[0].inputs * n, "observation network input size");
    for (l, layer) in layers.iter().enumerate() {
        let (w, b) = (&params[layer.w.0], &params[layer.b.0]);
        assert!(
            w.numel() == layer.inputs * layer.outputs && b.numel() == layer.outputs,
            "observation network: parameter shapes do not match layer {l} ({} -> {})",
            layer.inputs,
            layer.outputs
        );
        assert!(l == 0 || layer.inputs == layers[l - 1].outputs, "observation network: layer {l} does not chain");
    }
    let (k_in, k_out) = (layers[0].inputs, layers[layers.len() - 1].outputs);
    let widest = layers.iter().map(|l| l.inputs.max(l.outputs)).max().unwrap_or(0);
    out.resize(k_out * n, F::ZERO);
    let [h0, h1] = hidden;
    h0.resize(widest * NET_BLOCK, F::ZERO);
    h1.resize(widest * NET_BLOCK, F::ZERO);
    for start in (0..n).step_by(NET_BLOCK) {
        let len = NET_BLOCK.min(n - start);
        // The block's inputs, zero-padded to a whole block.
        for k in 0..k_in {
            let row = &mut h0[k * NET_BLOCK..(k + 1) * NET_BLOCK];
            row[..len].copy_from_slice(&input[k * n + start..k * n + start + len]);
            row[len..].fill(F::ZERO);
        }
        // Ping-pong between the two block buffers: layer l reads h0 when l is even.
        for (l, layer) in layers.iter().enumerate() {
            let (w, b) = (params[layer.w.0].data(), params[layer.b.0].data());
            let (src, dst) = if l % 2 == 0 { (&*h0, &mut *h1) } else { (&*h1, &mut *h0) };
            dense_block(w, b, layer.act, layer.inputs, layer.outputs, src, dst);
        }
        let last = if layers.len().is_multiple_of(2) { &*h0 } else { &*h1 };
        for j in 0..k_out {
            out[j * n + start..j * n + start + len].copy_from_slice(&last[j * NET_BLOCK..j * NET_BLOCK + len]);
        }
    }
}

/// f32 lanes of the widest vector the build targets (16 with AVX-512, else 8 of
/// AVX2): the unit of the block kernel's register tiles. The results are the same
/// bits either way (each lane accumulates its inputs in the same order); on the
/// 2-core AVX-512 machine 16 lanes made a default diagnosis's base fit about 1%
/// faster than 8 (0.334 and 0.341 against 0.338 and 0.344 s per step, alternating
/// runs on the same data).
const LANES: usize = if cfg!(target_feature = "avx512f") { 16 } else { 8 };
/// Outputs per register tile of [`dense_block`].
const TILE_OUTPUTS: usize = 4;
/// Vectors of particles per register tile: `TILE_OUTPUTS x TILE_VECTORS` accumulators
/// (8 of the 16 AVX2 or 32 AVX-512 registers), each input vector loaded once per
/// tile and each weight broadcast once per tile (4 vectors of 16 lanes per tile was
/// 11% slower than 2).
const TILE_VECTORS: usize = 2;
const _: () = assert!(NET_BLOCK.is_multiple_of(TILE_VECTORS * LANES), "a block is whole tiles");

/// One layer `y = act(x W + b)` for one block: `x` holds `k_in` rows of
/// [`NET_BLOCK`] values, `y` receives `k_out` rows; `W` is `k_in x k_out`, row-major.
/// Register tiles of `TILE_OUTPUTS` outputs (single outputs for a remainder) by
/// `TILE_VECTORS x LANES` particles are accumulated over the inputs and stored; then
/// one activation pass covers the layer.
fn dense_block<F: Float>(w: &[F], b: &[F], act: Activation, k_in: usize, k_out: usize, x: &[F], y: &mut [F]) {
    let layer = Layer { w: &w[..k_in * k_out], b: &b[..k_out], k_out, x: &x[..k_in * NET_BLOCK] };
    let y = &mut y[..k_out * NET_BLOCK];
    let mut j0 = 0;
    while j0 + TILE_OUTPUTS <= k_out {
        layer.tile::<TILE_OUTPUTS>(j0, y);
        j0 += TILE_OUTPUTS;
    }
    for j in j0..k_out {
        layer.tile::<1>(j, y);
    }
    activate(act, y);
}

/// One layer's parameters and one block's inputs (see [`dense_block`]).
struct Layer<'a, F> {
    w: &'a [F],
    b: &'a [F],
    k_out: usize,
    x: &'a [F],
}

impl<F: Float> Layer<'_, F> {
    /// Outputs `j0..j0 + J` of the block into `y`.
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // index loops over fixed-size arrays vectorise
    fn tile<const J: usize>(&self, j0: usize, y: &mut [F]) {
        const SPAN: usize = TILE_VECTORS * LANES;
        let bias: &[F; J] = self.b[j0..j0 + J].try_into().expect("J outputs");
        for p0 in (0..NET_BLOCK).step_by(SPAN) {
            let mut acc: [[F; SPAN]; J] = std::array::from_fn(|t| [bias[t]; SPAN]);
            for k in 0..self.x.len() / NET_BLOCK {
                let (xs, ws) = (k * NET_BLOCK + p0, k * self.k_out + j0);
                let xk: &[F; SPAN] = self.x[xs..xs + SPAN].try_into().expect("SPAN particles");
                let wt: &[F; J] = self.w[ws..ws + J].try_into().expect("J outputs");
                for t in 0..J {
                    for l in 0..SPAN {
                        acc[t][l] = xk[l].mul_add(wt[t], acc[t][l]);
                    }
                }
            }
            for (t, a) in acc.iter().enumerate() {
                let row = (j0 + t) * NET_BLOCK + p0;
                y[row..row + SPAN].copy_from_slice(a);
            }
        }
    }
}

/// `y = act(y)` elementwise, over a whole layer of a block at once.
fn activate<F: Float>(act: Activation, y: &mut [F]) {
    match act {
        Activation::Identity => {}
        Activation::Tanh => y.iter_mut().for_each(|v| *v = v.tanh()),
        Activation::Relu => y.iter_mut().for_each(|v| *v = v.max(F::ZERO)),
        Activation::Softplus => y.iter_mut().for_each(|v| *v = v.softplus()),
        Activation::Sigmoid => y.iter_mut().for_each(|v| *v = v.sigmoid()),
    }
}
