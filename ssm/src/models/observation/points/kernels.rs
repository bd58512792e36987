//! The filter's kernels of the point model: the network's head for a batch of
//! particles (`prepare`), and blocks of particles against all points.

use autodiff::nn::ParamStore;
use autodiff::Float;

use super::{PointObservationModel, POINT_MIN_SCALE, POINT_OFFSET_SCALE, POINT_SCALE_SCALE};
use crate::models::observation::edges::{edge_lengths, SoftConsts, NUM_EDGES};
use crate::models::observation::{fit_len, net, ObsContext, PosesRef, Scratch};

/// Guard of `e_far = e^{-L/s} / e_near`: when `e_near` is below this, `e_far` is
/// negligible anyway (`e_far <= e_near` always, and here `e_far < 1e-30`).
pub(super) const TINY: f64 = 1e-30;

impl PointObservationModel {
    /// Network plus head: per particle and edge, the inputs of [`point_terms`] into
    /// `scratch.head` (feature-major, 12 rows): `k_e = ln phi_e - ln(2 b_e) - ln L_e`,
    /// the Laplace's centre `off_e` in the box frame, and `-1 / b_e`.
    #[allow(clippy::needless_range_loop)] // index loops over resliced arrays vectorise
    pub(super) fn prepare<F: Float>(
        &self,
        params: &ParamStore<F>,
        ctx: &ObsContext,
        poses: PosesRef<'_, F>,
        s: &mut Scratch<F>,
    ) {
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

/// `min(a, b)` as a plain compare-and-select (one `vminps`); `Float::min` also
/// handles NaN, which costs two more instructions per lane. Inputs here are finite.
#[inline(always)]
pub(super) fn fmin<F: Float>(a: F, b: F) -> F {
    if a < b {
        a
    } else {
        b
    }
}

/// `max(a, b)` as a plain compare-and-select (see [`fmin`]).
#[inline(always)]
pub(super) fn fmax<F: Float>(a: F, b: F) -> F {
    if a > b {
        a
    } else {
        b
    }
}

/// Particles per block of the filter's kernel: a block's 16 per-particle inputs and
/// its two accumulators (4.5 KiB in f32) stay in L1 while all its points are visited.
pub(super) const BLOCK: usize = 64;
/// The filter's kernel multiplies the points' mixture sums and takes one logarithm
/// of the running product before its binary exponent can leave `[-RANGE, RANGE]`
/// (f32's normal range is `[-126, 127]`).
pub(super) const PRODUCT_RANGE_LOG2: f64 = 120.0;

/// Constants of one object for the filter's kernel ([`point_terms`]): the soft
/// uniform's, per edge pair, in units of its scale `s` where that saves work.
#[derive(Clone, Copy, Debug)]
pub(super) struct PointConsts<F> {
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
    pub(super) far: bool,
    /// Points whose mixture sums are multiplied before one logarithm is taken.
    points_per_log: usize,
}

impl<F: Float> PointConsts<F> {
    pub(super) fn new(length: f64, width: f64, scale: f64) -> Self {
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
pub(super) fn point_terms<F: Float, const FAR: bool>(
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
pub(super) struct Block<'a, F> {
    pub(super) x: &'a [F],
    pub(super) y: &'a [F],
    cos: &'a [F],
    sin: &'a [F],
    k: [&'a [F]; NUM_EDGES],
    off: [&'a [F]; NUM_EDGES],
    nib: [&'a [F]; NUM_EDGES],
}

impl<'a, F: Float> Block<'a, F> {
    /// Particles `range` of `n`, from `scratch` after `prepare`.
    pub(super) fn new(
        poses: PosesRef<'a, F>,
        scratch: &'a Scratch<F>,
        n: usize,
        range: std::ops::Range<usize>,
    ) -> Self {
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

    pub(super) fn len(&self) -> usize {
        self.x.len()
    }

    /// `point_terms` of the `P` points `pts` for every particle of the block, handed
    /// to `f(i, [(mx, sum); P])`. Inlined into a loop over the block that vectorises.
    /// With `P = 2` each iteration holds two independent dependency chains (the loop
    /// body is long: one chain alone keeps the core waiting on its latencies) that
    /// share the particle's loads.
    #[inline(always)]
    pub(super) fn for_each_terms<const FAR: bool, const P: usize>(
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
pub(super) fn block_log_likelihood<F: Float, const FAR: bool>(
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
pub(super) fn block_log_densities<F: Float, const FAR: bool>(
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
