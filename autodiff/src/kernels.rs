//! Array kernels shared by forward and backward passes: parallel element-wise maps,
//! broadcast binary maps, reductions to a broadcast shape, fixed-order sums, axis
//! reductions and a row-parallel GEMM.
//!
//! Every parallel kernel splits work into chunks whose boundaries depend only on the
//! sizes, never on the thread count, and combines partial results in chunk order,
//! so results are bitwise identical whatever the number of threads.

use rayon::prelude::*;

use crate::float::Float;
use crate::tensor::broadcast_strides;

/// How an op may use threads. Passed explicitly (held by the tape), never ambient.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Parallelism {
    /// Everything on the calling thread (use inside an outer parallel loop).
    Serial,
    /// Large ops split across rayon's thread pool.
    #[default]
    Rayon,
}

/// Element count below which an element-wise op stays serial: rayon costs ~15 µs
/// per split, which a cheap op over fewer elements does not repay.
pub(crate) const PAR_MIN_ELEMS: usize = 1 << 15;
/// Elements per parallel task (and per partial sum in fixed-order reductions).
pub(crate) const CHUNK_ELEMS: usize = 1 << 13;
/// Multiply-adds below which a GEMM stays on one thread.
const PAR_MIN_GEMM_FLOPS: usize = 1 << 18;
/// Rows per partial product when a GEMM reduces over a long dimension (weight
/// gradients `X^T G`): fixed so the summation order never depends on threads.
const GEMM_REDUCE_ROWS: usize = 4096;

impl Parallelism {
    #[inline]
    pub(crate) fn split(self, elems: usize) -> bool {
        self == Parallelism::Rayon && elems >= PAR_MIN_ELEMS
    }
}

/// `f(&mut dst[i], src[i])` for every `i`: the loop, split into chunks, of
/// [`map`] and [`add_assign`].
fn update<F: Float>(par: Parallelism, dst: &mut [F], src: &[F], f: impl Fn(&mut F, F) + Sync) {
    let body = |d: &mut [F], s: &[F]| {
        for (o, &x) in d.iter_mut().zip(s) {
            f(o, x);
        }
    };
    if par.split(dst.len()) {
        dst.par_chunks_mut(CHUNK_ELEMS).zip(src.par_chunks(CHUNK_ELEMS)).for_each(|(d, s)| body(d, s));
    } else {
        body(dst, src);
    }
}

/// `dst[i] = f(src[i])`.
pub(crate) fn map<F: Float>(par: Parallelism, src: &[F], dst: &mut [F], f: impl Fn(F) -> F + Sync) {
    debug_assert_eq!(src.len(), dst.len());
    update(par, dst, src, |o, x| *o = f(x));
}

/// `dst[i] = f(a[i], b[i])`.
pub(crate) fn zip<F: Float>(par: Parallelism, a: &[F], b: &[F], dst: &mut [F], f: impl Fn(F, F) -> F + Sync) {
    debug_assert!(a.len() == dst.len() && b.len() == dst.len());
    let body = |d: &mut [F], a: &[F], b: &[F]| {
        for ((o, &x), &y) in d.iter_mut().zip(a).zip(b) {
            *o = f(x, y);
        }
    };
    if par.split(dst.len()) {
        dst.par_chunks_mut(CHUNK_ELEMS)
            .zip(a.par_chunks(CHUNK_ELEMS))
            .zip(b.par_chunks(CHUNK_ELEMS))
            .for_each(|((d, a), b)| body(d, a, b));
    } else {
        body(dst, a, b);
    }
}

/// `dst[i] = f(a[i], b[i], c[i])`.
pub(crate) fn zip3<F: Float>(
    par: Parallelism,
    a: &[F],
    b: &[F],
    c: &[F],
    dst: &mut [F],
    f: impl Fn(F, F, F) -> F + Sync,
) {
    let body = |d: &mut [F], a: &[F], b: &[F], c: &[F]| {
        for (((o, &x), &y), &z) in d.iter_mut().zip(a).zip(b).zip(c) {
            *o = f(x, y, z);
        }
    };
    if par.split(dst.len()) {
        dst.par_chunks_mut(CHUNK_ELEMS)
            .zip(a.par_chunks(CHUNK_ELEMS))
            .zip(b.par_chunks(CHUNK_ELEMS))
            .zip(c.par_chunks(CHUNK_ELEMS))
            .for_each(|(((d, a), b), c)| body(d, a, b, c));
    } else {
        body(dst, a, b, c);
    }
}

/// `dst[i] += src[i]`.
pub(crate) fn add_assign<F: Float>(par: Parallelism, dst: &mut [F], src: &[F]) {
    update(par, dst, src, |o, x| *o += x);
}

/// Adds `row` to every row of `dst` (a bias): `dst[r, j] += row[j]`.
pub(crate) fn add_rows<F: Float>(par: Parallelism, dst: &mut [F], row: &[F]) {
    let n = row.len().max(1);
    let body = |d: &mut [F]| {
        for r in d.chunks_exact_mut(n) {
            for (o, &b) in r.iter_mut().zip(row) {
                *o += b;
            }
        }
    };
    if par.split(dst.len()) {
        let rows_per_task = (CHUNK_ELEMS / n).max(1);
        dst.par_chunks_mut(rows_per_task * n).for_each(body);
    } else {
        body(dst);
    }
}

/// Sum of all elements, accumulated in f64 over fixed chunks combined in order.
pub(crate) fn sum_f64<F: Float>(par: Parallelism, data: &[F]) -> f64 {
    let chunk_sum = |c: &[F]| c.iter().map(|x| x.to_f64()).sum::<f64>();
    if par.split(data.len()) {
        let partials: Vec<f64> = data.par_chunks(CHUNK_ELEMS).map(chunk_sum).collect();
        partials.iter().sum()
    } else {
        data.chunks(CHUNK_ELEMS).map(chunk_sum).sum()
    }
}

/// Row offsets into two broadcast inputs for output row `row` (a row is the last
/// dimension of `out`); `sa`, `sb` are the broadcast strides.
#[inline]
fn row_offsets(mut row: usize, out: &[usize], sa: &[usize], sb: &[usize]) -> (usize, usize) {
    let (mut oa, mut ob) = (0, 0);
    for d in (0..out.len().saturating_sub(1)).rev() {
        let i = row % out[d];
        row /= out[d];
        oa += i * sa[d];
        ob += i * sb[d];
    }
    (oa, ob)
}

/// The broadcast binary map `dst = f(a, b)` where `a`, `b` have shapes broadcasting to
/// `out` (the shape of `dst`).
// The two operands, their shapes, the output and the map are all needed by every call site.
#[allow(clippy::too_many_arguments)]
pub(crate) fn broadcast_zip<F: Float>(
    par: Parallelism,
    a: &[F],
    shape_a: &[usize],
    b: &[F],
    shape_b: &[usize],
    out: &[usize],
    dst: &mut [F],
    f: impl Fn(F, F) -> F + Sync,
) {
    if shape_a == out && shape_b == out {
        return zip(par, a, b, dst, f);
    }
    if b.len() == 1 && shape_a == out {
        let y = b[0];
        return map(par, a, dst, |x| f(x, y));
    }
    if a.len() == 1 && shape_b == out {
        let x = a[0];
        return map(par, b, dst, |y| f(x, y));
    }
    let sa = broadcast_strides(shape_a, out);
    let sb = broadcast_strides(shape_b, out);
    let row_len = out.last().copied().unwrap_or(1).max(1);
    let (ia, ib) = (sa.last().copied().unwrap_or(0), sb.last().copied().unwrap_or(0));
    let rows_body = |first_row: usize, d: &mut [F]| {
        for (r, drow) in d.chunks_mut(row_len).enumerate() {
            let (oa, ob) = row_offsets(first_row + r, out, &sa, &sb);
            match (ia, ib) {
                (1, 1) => {
                    for ((o, &x), &y) in drow.iter_mut().zip(&a[oa..oa + row_len]).zip(&b[ob..ob + row_len]) {
                        *o = f(x, y);
                    }
                }
                (1, _) => {
                    let y = b[ob];
                    for (o, &x) in drow.iter_mut().zip(&a[oa..oa + row_len]) {
                        *o = f(x, y);
                    }
                }
                (_, 1) => {
                    let x = a[oa];
                    for (o, &y) in drow.iter_mut().zip(&b[ob..ob + row_len]) {
                        *o = f(x, y);
                    }
                }
                _ => {
                    let v = f(a[oa], b[ob]);
                    drow.iter_mut().for_each(|o| *o = v);
                }
            }
        }
    };
    if out.is_empty() {
        dst[0] = f(a[0], b[0]);
    } else if par.split(dst.len()) {
        let rows_per_task = (CHUNK_ELEMS / row_len).max(1);
        dst.par_chunks_mut(rows_per_task * row_len).enumerate().for_each(|(t, d)| rows_body(t * rows_per_task, d));
    } else {
        rows_body(0, dst);
    }
}

/// Sums `src` (of shape `from`) down to `to`, the shape of an input that was broadcast
/// to `from`: the gradient rule for broadcasting. Accumulates in f64.
pub(crate) fn sum_to_shape<F: Float>(par: Parallelism, src: &[F], from: &[usize], to: &[usize]) -> Vec<F> {
    let numel_to: usize = to.iter().product();
    if from == to {
        return src.to_vec();
    }
    if numel_to == 1 {
        return vec![F::from_f64(sum_f64(par, src))];
    }
    let st = broadcast_strides(to, from);
    let zeros = vec![0; from.len()];
    let row_len = from.last().copied().unwrap_or(1).max(1);
    let it = st.last().copied().unwrap_or(0);
    let rows = src.len() / row_len;
    // Partial sums are accumulated in f64 (gradients of broadcast inputs such as
    // biases sum over every particle) and rounded to F once at the end.
    let rows_body = |first_row: usize, nrows: usize, acc: &mut [f64]| {
        for r in first_row..first_row + nrows {
            let (ot, _) = row_offsets(r, from, &st, &zeros);
            let srow = &src[r * row_len..(r + 1) * row_len];
            if it == 1 {
                for (o, &x) in acc[ot..ot + row_len].iter_mut().zip(srow) {
                    *o += x.to_f64();
                }
            } else {
                acc[ot] += srow.iter().map(|x| x.to_f64()).sum::<f64>();
            }
        }
    };
    // Fixed row blocks, each into its own partial, combined in block order: the same
    // summation order whether the blocks run serially or in parallel.
    let rows_per_task = (CHUNK_ELEMS * 4 / row_len).max(1);
    let tasks = rows.div_ceil(rows_per_task);
    let block = |t: usize| {
        let mut acc = vec![0.0f64; numel_to];
        let first = t * rows_per_task;
        rows_body(first, rows_per_task.min(rows - first), &mut acc);
        acc
    };
    let partials: Vec<Vec<f64>> = if tasks > 1 && par.split(src.len()) {
        (0..tasks).into_par_iter().map(block).collect()
    } else {
        (0..tasks).map(block).collect()
    };
    let mut out = vec![0.0f64; numel_to];
    for p in &partials {
        add_assign(Parallelism::Serial, &mut out, p);
    }
    out.into_iter().map(F::from_f64).collect()
}

/// Axis view of a tensor: `[outer, n, inner]` element counts around one axis.
pub(crate) type AxisDims = (usize, usize, usize);

/// Runs `body(first_outer, src_block, dst_block)` over blocks of whole outer slices,
/// in parallel when large. `src_per`/`dst_per` are the elements per outer index.
fn outer_blocks<F: Float>(
    par: Parallelism,
    outer: usize,
    srcs: &[&[F]],
    src_per: usize,
    dst: &mut [F],
    dst_per: usize,
    body: impl Fn(&[&[F]], &mut [F]) + Sync,
) {
    if outer == 0 || dst_per == 0 {
        return;
    }
    let work = outer * src_per.max(dst_per);
    if par.split(work) && outer > 1 {
        let per_task = (CHUNK_ELEMS / src_per.max(dst_per).max(1)).max(1);
        dst.par_chunks_mut(per_task * dst_per).enumerate().for_each(|(t, d)| {
            let o0 = t * per_task;
            let no = d.len() / dst_per;
            let blocks: Vec<&[F]> = srcs.iter().map(|s| &s[o0 * src_per..(o0 + no) * src_per]).collect();
            body(&blocks, d);
        });
    } else {
        body(srcs, dst);
    }
}

/// Gathers lane `j` (stride `inner`) of an `[n, inner]` block into `buf`.
#[inline]
fn load_lane<F: Float>(block: &[F], n: usize, inner: usize, j: usize, buf: &mut Vec<F>) {
    buf.clear();
    buf.extend((0..n).map(|k| block[k * inner + j]));
}

/// Reduces each lane along an axis: `dst[o, j] = f(lane)`, with `src` viewed as
/// `[outer, n, inner]` and `dst` as `[outer, inner]`. Lanes are contiguous slices when
/// `inner == 1`; otherwise they are copied into a scratch buffer first.
pub(crate) fn reduce_lanes<F: Float>(
    par: Parallelism,
    src: &[F],
    dst: &mut [F],
    (outer, n, inner): AxisDims,
    f: impl Fn(&[F]) -> F + Sync,
) {
    debug_assert_eq!(dst.len(), outer * inner);
    if n == 0 {
        // Empty lanes: the reduction of nothing (0 for a sum, -inf for a log-sum-exp).
        // Written explicitly: output buffers are not zero-filled.
        let empty = f(&[]);
        dst.iter_mut().for_each(|o| *o = empty);
        return;
    }
    outer_blocks(par, outer, &[src], n * inner, dst, inner, |s, d| {
        let s = s[0];
        if inner == 1 {
            for (o, lane) in d.iter_mut().zip(s.chunks(n.max(1))) {
                *o = f(if n == 0 { &[] } else { lane });
            }
        } else {
            let mut buf = Vec::with_capacity(n);
            for (ob, sb) in d.chunks_mut(inner).zip(s.chunks((n * inner).max(1))) {
                for (j, o) in ob.iter_mut().enumerate() {
                    load_lane(sb, n, inner, j, &mut buf);
                    *o = f(&buf);
                }
            }
        }
    });
}

/// Most source arrays a lane map reads at once.
const MAX_LANE_SOURCES: usize = 4;

/// Maps lanes to lanes: `f(lanes of each source, out lane)`, all of shape
/// `[outer, n, inner]` (at most [`MAX_LANE_SOURCES`] sources).
pub(crate) fn map_lanes<F: Float>(
    par: Parallelism,
    srcs: &[&[F]],
    dst: &mut [F],
    (outer, n, inner): AxisDims,
    f: impl Fn(&[&[F]], &mut [F]) + Sync,
) {
    assert!(srcs.len() <= MAX_LANE_SOURCES);
    let block = n * inner;
    if block == 0 {
        return;
    }
    outer_blocks(par, outer, srcs, block, dst, block, |s, d| {
        if inner == 1 {
            let mut lanes: [&[F]; MAX_LANE_SOURCES] = [&[]; MAX_LANE_SOURCES];
            for (o, out) in d.chunks_mut(n).enumerate() {
                for (lane, x) in lanes.iter_mut().zip(s) {
                    *lane = &x[o * n..(o + 1) * n];
                }
                f(&lanes[..s.len()], out);
            }
        } else {
            let mut bufs: Vec<Vec<F>> = vec![Vec::with_capacity(n); s.len()];
            let mut out = vec![F::ZERO; n];
            for (ob, db) in d.chunks_mut(block).enumerate() {
                for j in 0..inner {
                    for (buf, x) in bufs.iter_mut().zip(s) {
                        load_lane(&x[ob * block..(ob + 1) * block], n, inner, j, buf);
                    }
                    let mut lanes: [&[F]; MAX_LANE_SOURCES] = [&[]; MAX_LANE_SOURCES];
                    for (lane, b) in lanes.iter_mut().zip(&bufs) {
                        *lane = b.as_slice();
                    }
                    f(&lanes[..s.len()], &mut out);
                    for (k, &v) in out.iter().enumerate() {
                        db[k * inner + j] = v;
                    }
                }
            }
        }
    });
}

/// `dst` (shape `to`) filled with `src` (shape `from`) broadcast to `to`.
pub(crate) fn expand<F: Float>(par: Parallelism, src: &[F], from: &[usize], to: &[usize], dst: &mut [F]) {
    broadcast_zip(par, src, from, &[F::ZERO], &[], to, dst, |x, _| x);
}

/// Gathers rows along an axis: with `src` viewed as `[outer, n, inner]`, row `(o, j)`
/// of `dst` (`[outer, idx.len(), inner]`) is row `(o, idx[j])` of `src`.
/// Panics if an index is out of range.
#[track_caller]
pub(crate) fn gather_rows<F: Float>(
    par: Parallelism,
    src: &[F],
    (outer, n, inner): AxisDims,
    idx: &[usize],
    dst: &mut [F],
) {
    if let Some(&bad) = idx.iter().find(|&&i| i >= n) {
        panic!("gather: index {bad} out of range for axis of length {n}");
    }
    let m = idx.len();
    debug_assert_eq!(dst.len(), outer * m * inner);
    if inner == 0 || m == 0 {
        return;
    }
    let body = |first_row: usize, d: &mut [F]| {
        for (r, drow) in d.chunks_mut(inner).enumerate() {
            let row = first_row + r;
            let (o, j) = (row / m, row % m);
            let s = (o * n + idx[j]) * inner;
            drow.copy_from_slice(&src[s..s + inner]);
        }
    };
    if par.split(dst.len()) {
        let rows_per_task = (CHUNK_ELEMS / inner).max(1);
        dst.par_chunks_mut(rows_per_task * inner).enumerate().for_each(|(t, d)| body(t * rows_per_task, d));
    } else {
        body(0, dst);
    }
}

/// Scatter-adds rows along an axis (the transpose of [`gather_rows`]): with `src` viewed
/// as `[outer, idx.len(), inner]`, row `(o, j)` is added into row `(o, idx[j])` of `dst`
/// (`[outer, size, inner]`). Parallel over `outer` only, so sums keep a fixed order.
#[track_caller]
pub(crate) fn scatter_add_rows<F: Float>(
    par: Parallelism,
    src: &[F],
    (outer, m, inner): AxisDims,
    idx: &[usize],
    size: usize,
    dst: &mut [F],
) {
    if let Some(&bad) = idx.iter().find(|&&i| i >= size) {
        panic!("scatter_add: index {bad} out of range for output axis of length {size}");
    }
    debug_assert_eq!(idx.len(), m);
    let block_in = m * inner;
    let block_out = size * inner;
    if block_out == 0 || outer == 0 {
        return;
    }
    let body = |s: &[F], d: &mut [F]| {
        for (j, &i) in idx.iter().enumerate() {
            let srow = &s[j * inner..(j + 1) * inner];
            for (o, &x) in d[i * inner..(i + 1) * inner].iter_mut().zip(srow) {
                *o += x;
            }
        }
    };
    if par.split(src.len()) && outer > 1 {
        dst.par_chunks_mut(block_out).zip(src.par_chunks(block_in.max(1))).for_each(|(d, s)| body(s, d));
    } else {
        for (d, s) in dst.chunks_mut(block_out).zip(src.chunks(block_in.max(1))) {
            body(s, d);
        }
    }
}

/// Copies the blocks of a `[outer, n, inner]` array into (or out of) a sub-range of
/// axis positions `start..start + n` of a `[outer, total, inner]` array.
// Source and destination each need their slice, dims and start; bundling them would only move the count.
#[allow(clippy::too_many_arguments)]
pub(crate) fn copy_axis_range<F: Float>(
    src: &[F],
    src_dims: AxisDims,
    src_start: usize,
    dst: &mut [F],
    dst_dims: AxisDims,
    dst_start: usize,
    len: usize,
    accumulate: bool,
) {
    let (outer, ns, inner) = src_dims;
    let (_, nd, _) = dst_dims;
    for o in 0..outer {
        let s = &src[(o * ns + src_start) * inner..(o * ns + src_start + len) * inner];
        let d = &mut dst[(o * nd + dst_start) * inner..(o * nd + dst_start + len) * inner];
        if accumulate {
            for (x, &y) in d.iter_mut().zip(s) {
                *x += y;
            }
        } else {
            d.copy_from_slice(s);
        }
    }
}

/// Row-major matrix operand: data plus whether it is read transposed.
#[derive(Clone, Copy)]
pub(crate) struct MatRef<'a, F> {
    pub data: &'a [F],
    pub rows: usize,
    pub cols: usize,
    /// Read as the transpose of the stored `cols x rows` row-major matrix.
    pub transposed: bool,
}

impl<'a, F> MatRef<'a, F> {
    pub fn new(data: &'a [F], rows: usize, cols: usize) -> Self {
        MatRef { data, rows, cols, transposed: false }
    }
    /// The transpose of a stored `rows x cols` matrix, seen as `cols x rows`.
    pub fn t(data: &'a [F], rows: usize, cols: usize) -> Self {
        MatRef { data, rows: cols, cols: rows, transposed: true }
    }
    fn strides(&self) -> (isize, isize) {
        if self.transposed {
            (1, self.rows as isize)
        } else {
            (self.cols as isize, 1)
        }
    }
    /// The sub-matrix of rows `r0..r0 + nr`.
    fn row_block(&self, r0: usize, nr: usize) -> (*const F, usize) {
        let (rs, _) = self.strides();
        // SAFETY of the caller: r0 + nr <= rows.
        (unsafe { self.data.as_ptr().offset(r0 as isize * rs) }, nr)
    }
}

/// `c = a b + beta c` for row-major `c` (`a.rows x b.cols`), splitting rows of `a`
/// across threads (each call to the single-threaded kernel owns its rows).
pub(crate) fn gemm<F: Float>(par: Parallelism, a: MatRef<F>, b: MatRef<F>, beta: F, c: &mut [F]) {
    let (m, k, n) = (a.rows, a.cols, b.cols);
    assert_eq!(k, b.rows, "gemm: inner dimensions {k} and {}", b.rows);
    assert_eq!(c.len(), m * n);
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        // Empty inner dimension: C = beta C, where beta = 0 must not read C (it may
        // hold stale values, as the GEMM kernel's contract allows).
        if beta == F::ZERO {
            c.fill(F::ZERO);
        } else {
            c.iter_mut().for_each(|x| *x *= beta);
        }
        return;
    }
    let (rsa, csa) = a.strides();
    let (rsb, csb) = b.strides();
    let run = |r0: usize, nr: usize, cblock: &mut [F]| {
        let (pa, _) = a.row_block(r0, nr);
        // SAFETY: strides describe the valid matrices built by MatRef; c does not alias.
        unsafe {
            F::gemm(nr, k, n, F::ONE, pa, rsa, csa, b.data.as_ptr(), rsb, csb, beta, cblock.as_mut_ptr(), n as isize, 1)
        }
    };
    let flops = m * k * n;
    if par == Parallelism::Rayon && flops >= PAR_MIN_GEMM_FLOPS && m >= 16 {
        let threads = rayon::current_num_threads().max(1);
        // Several tasks per thread for balance, but each large enough for the kernel.
        let rows_per_task = m.div_ceil(threads * 4).max(64).min(m);
        c.par_chunks_mut(rows_per_task * n).enumerate().for_each(|(t, cb)| {
            let r0 = t * rows_per_task;
            run(r0, cb.len() / n, cb);
        });
    } else {
        run(0, m, c);
    }
}

/// `c += a^T b` where `a` is row-major `m x k` and `b` row-major `m x n` with `m` long
/// (the weight-gradient product). Partial products over fixed blocks of
/// [`GEMM_REDUCE_ROWS`] rows are summed in block order.
pub(crate) fn gemm_at_b_acc<F: Float>(par: Parallelism, a: &[F], b: &[F], m: usize, k: usize, n: usize, c: &mut [F]) {
    assert_eq!(a.len(), m * k);
    assert_eq!(b.len(), m * n);
    assert_eq!(c.len(), k * n);
    let blocks = m.div_ceil(GEMM_REDUCE_ROWS);
    let partial = |blk: usize, out: &mut [F], beta: F| {
        let r0 = blk * GEMM_REDUCE_ROWS;
        let nr = GEMM_REDUCE_ROWS.min(m - r0);
        let at = MatRef::t(&a[r0 * k..(r0 + nr) * k], nr, k);
        let bb = MatRef::new(&b[r0 * n..(r0 + nr) * n], nr, n);
        gemm(Parallelism::Serial, at, bb, beta, out);
    };
    if blocks <= 1 {
        if m > 0 {
            partial(0, c, F::ONE);
        }
        return;
    }
    let parts: Vec<Vec<F>> = if par == Parallelism::Rayon {
        (0..blocks)
            .into_par_iter()
            .map(|blk| {
                let mut p = vec![F::ZERO; k * n];
                partial(blk, &mut p, F::ZERO);
                p
            })
            .collect()
    } else {
        (0..blocks)
            .map(|blk| {
                let mut p = vec![F::ZERO; k * n];
                partial(blk, &mut p, F::ZERO);
                p
            })
            .collect()
    };
    for p in &parts {
        add_assign(Parallelism::Serial, c, p);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `gemm` on narrow and wide shapes against the naive product, with either
    /// operand transposed, `beta` 0 and not, serial and split across threads.
    #[test]
    fn narrow_and_wide_products_match_the_naive_product() {
        for &(m, k, n) in &[
            (1, 1, 1),
            (37, 5, 3),
            (130, 16, 12),
            (67, 7, 16),
            (9, 64, 33),
            (300, 16, 17),
            (70, 65, 20),
            (50, 12, 80),
            (2000, 16, 16),
        ] {
            for (ta, tb) in [(false, false), (true, false), (false, true), (true, true)] {
                for beta in [0.0, 0.5] {
                    let a: Vec<f64> = (0..m * k).map(|i| (i as f64 * 0.37).sin()).collect();
                    let b: Vec<f64> = (0..k * n).map(|i| (i as f64 * 0.11).cos()).collect();
                    let av = if ta { MatRef::t(&a, k, m) } else { MatRef::new(&a, m, k) };
                    let bv = if tb { MatRef::t(&b, n, k) } else { MatRef::new(&b, k, n) };
                    let get = |v: &MatRef<f64>, i: usize, j: usize| {
                        let (rs, cs) = v.strides();
                        v.data[i * rs as usize + j * cs as usize]
                    };
                    let c0: Vec<f64> = (0..m * n).map(|i| (i as f64 * 0.05).cos()).collect();
                    for par in [Parallelism::Serial, Parallelism::Rayon] {
                        let mut c = c0.clone();
                        gemm(par, av, bv, beta, &mut c);
                        for i in 0..m {
                            for j in 0..n {
                                let e: f64 =
                                    (0..k).map(|l| get(&av, i, l) * get(&bv, l, j)).sum::<f64>() + beta * c0[i * n + j];
                                let got = c[i * n + j];
                                assert!(
                                    (got - e).abs() < 1e-12 * (1.0 + e.abs()),
                                    "{m}x{k}x{n} {ta} {tb} {beta}: {got} vs {e}"
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    /// The weight-gradient product `c += a^T b` on narrow and wide shapes, over one
    /// and several reduction blocks, against the naive sum.
    #[test]
    fn weight_gradient_products_match_the_naive_sum() {
        for &(m, k, n) in &[(1, 1, 1), (37, 5, 3), (9000, 16, 12), (5000, 7, 16), (300, 65, 9), (4100, 3, 70)] {
            let a: Vec<f64> = (0..m * k).map(|i| (i as f64 * 0.37).sin()).collect();
            let b: Vec<f64> = (0..m * n).map(|i| (i as f64 * 0.11).cos()).collect();
            let c0: Vec<f64> = (0..k * n).map(|i| i as f64 * 0.01).collect();
            for par in [Parallelism::Serial, Parallelism::Rayon] {
                let mut c = c0.clone();
                gemm_at_b_acc(par, &a, &b, m, k, n, &mut c);
                for p in 0..k {
                    for j in 0..n {
                        let e: f64 = (0..m).map(|i| a[i * k + p] * b[i * n + j]).sum::<f64>() + c0[p * n + j];
                        let got = c[p * n + j];
                        assert!((got - e).abs() < 1e-10 * (1.0 + e.abs()), "{m}x{k}x{n}: {got} vs {e}");
                    }
                }
            }
        }
    }

    #[test]
    fn gemm_matches_naive_with_transposes() {
        let (m, k, n) = (37, 5, 3);
        let a: Vec<f64> = (0..m * k).map(|i| (i as f64 * 0.37).sin()).collect();
        let b: Vec<f64> = (0..k * n).map(|i| (i as f64 * 0.11).cos()).collect();
        let mut c = vec![0.0; m * n];
        gemm(Parallelism::Rayon, MatRef::new(&a, m, k), MatRef::new(&b, k, n), 0.0, &mut c);
        for i in 0..m {
            for j in 0..n {
                let e: f64 = (0..k).map(|l| a[i * k + l] * b[l * n + j]).sum();
                assert!((c[i * n + j] - e).abs() < 1e-12);
            }
        }
        // a^T c via the reducing kernel equals the naive product.
        let mut g = vec![0.0; k * n];
        gemm_at_b_acc(Parallelism::Rayon, &a, &c, m, k, n, &mut g);
        for i in 0..k {
            for j in 0..n {
                let e: f64 = (0..m).map(|l| a[l * k + i] * c[l * n + j]).sum();
                assert!((g[i * n + j] - e).abs() < 1e-10);
            }
        }
    }

    #[test]
    fn sums_do_not_depend_on_parallelism() {
        let data: Vec<f32> = (0..300_001).map(|i| ((i as f32) * 0.001).sin()).collect();
        assert_eq!(sum_f64(Parallelism::Serial, &data), sum_f64(Parallelism::Rayon, &data));
        let from = [3000, 100];
        let s = sum_to_shape(Parallelism::Serial, &data[..300_000], &from, &[100]);
        let p = sum_to_shape(Parallelism::Rayon, &data[..300_000], &from, &[100]);
        assert_eq!(s, p);
    }
}
