//! The point model's fused tape rows (the differentiable path): the network on
//! the tape, per-row sums of `log g` and their partials in plain code, and one
//! precomputed node.

use autodiff::nn::BoundParams;
use autodiff::{Float, Parallelism, Tape, Tensor, Var};
use rayon::prelude::*;

use super::{clutter::*, kernels::*};
use super::{PointObservationModel, POINT_MIN_SCALE, POINT_OFFSET_SCALE, POINT_SCALE_SCALE};
use crate::data::Pose;
use crate::models::observation::edges::{SoftConsts, NUM_EDGES};
use crate::models::observation::features::av_features_on_tape;
use crate::models::observation::RowVars;

/// Number of per-row values the fused tape kernel produces: the row's log-density,
/// 12 partials with respect to `(ln phi, mu, b)`, and 5 with respect to
/// `(x, y, yaw, l, w)`.
pub(super) const ROW_OUT: usize = 1 + 3 * NUM_EDGES + 5;
/// Per-row values the fused kernel adds with clutter: the partials with respect to
/// the clutter's logit fraction `lambda` and log scale `sigma`.
pub(super) const CLUTTER_OUT: usize = 2;
/// Rows per parallel task of the fused kernel (fixed: results never depend on threads).
pub(super) const ROWS_PER_TASK: usize = 64;
/// Rows per tile of the fused kernel: rows that share their points and box are
/// processed this many at a time, vectorised across rows (a multiple of the f32
/// vector width).
pub(super) const TILE_ROWS: usize = 64;
/// Below this many (row, point) pairs the fused kernel stays on one thread.
pub(super) const PAR_MIN_PAIRS: usize = 1 << 14;

impl PointObservationModel {
    /// [`ObservationModel::log_likelihood_rows`] and, with `clutter = Some([lambda,
    /// sigma])`, [`Self::log_likelihood_rows_with_clutter`]: the network on the tape,
    /// the fused kernel, and one [`autodiff::Tape::precomputed`] node holding the
    /// rows' values and their partials.
    #[track_caller]
    pub(super) fn rows_log_likelihood<'t, F: Float>(
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
        let head = RowsHead::new(tape, o.value().data(), r);
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
}

/// One edge's contribution to one point: the upper bound `ub` of its log-term and
/// the factor `fac` in `(0, 1]` with `log term = ub + ln fac`; plus what the
/// gradient kernel needs.
#[derive(Clone, Copy)]
pub(super) struct EdgeTerm<F> {
    ub: F,
    fac: F,
    inside: bool,
    e_near: F,
    e_far: F,
}

/// `k` is `ln phi - ln(2 b) - ln L`; the soft uniform adds `ln fac` inside the edge
/// and `m / s + tail` outside it (`m` the signed distance to the nearer end).
/// `FAR = false` when `e^{-L/s}` is flushed to 0 for both edge lengths (see
/// `SoftConsts`): `e_far` is then 0 and costs no division.
#[inline(always)]
pub(super) fn edge_term<F: Float, const FAR: bool>(
    alpha: F,
    beta: F,
    k: F,
    mu: F,
    invb: F,
    sc: &SoftConsts<F>,
) -> EdgeTerm<F> {
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
pub(super) struct BoxConsts<F> {
    hl: F,
    hw: F,
    /// Soft-uniform constants of the width edges (0, 2) and the length edges (1, 3).
    sw: SoftConsts<F>,
    sl: SoftConsts<F>,
}

impl<F: Float> BoxConsts<F> {
    pub(super) fn new(length: f64, width: f64, scale: f64) -> Self {
        BoxConsts {
            hl: F::from_f64(0.5 * length),
            hw: F::from_f64(0.5 * width),
            sw: SoftConsts::new(width, scale),
            sl: SoftConsts::new(length, scale),
        }
    }
}

/// Values per row in the fused kernel's output, with or without clutter.
pub(super) fn row_stride(clutter: bool) -> usize {
    if clutter {
        ROW_OUT + CLUTTER_OUT
    } else {
        ROW_OUT
    }
}

/// Partials of one edge's term: d/dalpha and d/dL of `log U_soft`, and the sign and
/// size of `beta - mu`.
#[inline(always)]
pub(super) fn edge_partials<F: Float>(t: &EdgeTerm<F>, alpha: F, beta: F, mu: F, sc: &SoftConsts<F>) -> (F, F, F, F) {
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
pub(super) struct RowsHead<F> {
    /// `(ln phi, mu, b)`: `ln phi = log_softmax(o[0..4])`, `mu = POINT_OFFSET_SCALE
    /// o[4..8]`, `b = POINT_SCALE_SCALE softplus(o[8..12]) + POINT_MIN_SCALE`.
    head: Vec<F>,
    /// `phi` (4 columns), then `d b / d o = POINT_SCALE_SCALE sigmoid(o[8..12])` (4).
    slopes: Vec<F>,
}

impl<F: Float> RowsHead<F> {
    /// From the outputs `o` (`[R, 12]`, row-major) of `r` rows, in buffers of `tape`.
    #[allow(clippy::needless_range_loop)] // index loops over resliced columns vectorise
    pub(super) fn new(tape: &Tape<F>, o: &[F], r: usize) -> Self {
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
            *v *= mu_scale;
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
    pub(super) fn chain(&self, tape: &Tape<F>, k: &[f64], stride: usize) -> Vec<F> {
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
pub(super) struct Tile<F> {
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
    pub(super) fn new() -> Box<Self> {
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
    pub(super) fn load(&mut self, bc: &BoxConsts<F>, rows: &RowSlices<'_, F>, first: usize, m: usize, used: usize) {
        let (one, two) = (F::ONE, F::from_f64(2.0));
        let lens = [&bc.sw, &bc.sl, &bc.sw, &bc.sl];
        let (n, rows_m) = (rows.x.len(), first..first + m);
        let h = |j: usize| &rows.head[j * n..(j + 1) * n][rows_m.clone()];
        #[allow(clippy::needless_range_loop)] // `e` indexes the head columns and four per-edge arrays together
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
    pub(super) fn accumulate(&mut self, used: usize, m: usize) {
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
pub(super) fn tile_point<F: Float, const GRAD: bool, const CLUTTER: bool>(
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
pub(super) struct RowSlices<'a, F> {
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
    pub(super) fn same_group(&self, a: usize, b: usize) -> bool {
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
pub(super) fn rows_kernel<F: Float>(
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
