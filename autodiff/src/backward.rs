//! Every vector-Jacobian product, in one exhaustive `match` over [`Op`].
//!
//! Rules receive the output cotangent `g` and deliver each input's contribution to a
//! [`GradSink`], which accumulates (a value used twice receives the sum of both
//! gradients). Broadcast inputs receive the sum over the broadcast dimensions.

use crate::float::Float;
use crate::kernels::{self, MatRef};
use crate::ops::{lane_max_logsum, leading_rows, transpose_into, Binary, Op, Unary};
use crate::tape::{GradSink, Node, NodeId};
use crate::tensor::axis_split;

/// Propagates the cotangent `g` of node `id` to its inputs.
pub(crate) fn backward_node<F: Float>(nodes: &[Node<F>], id: NodeId, g: &[F], sink: &mut GradSink<'_, F>) {
    let node = &nodes[id];
    let par = sink.par;
    let val = |i: NodeId| &nodes[i].value;
    let out_shape = node.value.shape();
    match &node.op {
        Op::Leaf => {}
        Op::Unary(u, x) => {
            let x = *x;
            if !sink.wants(x) {
                return;
            }
            let mut gx = sink.alloc(g.len());
            unary_backward(*u, par, g, val(x).data(), node.value.data(), &mut gx);
            sink.add(x, gx);
        }
        Op::Binary(b, a, c) => binary_backward(*b, nodes, id, *a, *c, g, sink),
        Op::Matmul(x, w) => {
            let (x, w) = (*x, *w);
            let (k, n) = (val(w).shape()[0], val(w).shape()[1]);
            let m = leading_rows(val(x).shape());
            matmul_backward(x, w, m, k, n, val(x).data(), val(w).data(), g, sink);
        }
        Op::Affine(x, w, b) => {
            let (x, w, b) = (*x, *w, *b);
            let (k, n) = (val(w).shape()[0], val(w).shape()[1]);
            let m = leading_rows(val(x).shape());
            matmul_backward(x, w, m, k, n, val(x).data(), val(w).data(), g, sink);
            if sink.wants(b) {
                sink.add(b, kernels::sum_to_shape(par, g, &[m, n], &[n]));
            }
        }
        Op::Sum(x) => {
            let x = *x;
            if sink.wants(x) {
                let mut gx = sink.alloc(val(x).numel());
                gx.iter_mut().for_each(|v| *v = g[0]);
                sink.add(x, gx);
            }
        }
        Op::SumAxis(x, axis) => {
            let x = *x;
            if sink.wants(x) {
                let (outer, n, inner) = axis_split(val(x).shape(), *axis, "sum_axis");
                let mut gx = sink.alloc(val(x).numel());
                kernels::expand(par, g, &[outer, 1, inner], &[outer, n, inner], &mut gx);
                sink.add(x, gx);
            }
        }
        Op::LogSumExp(x, axis) => {
            let x = *x;
            if sink.wants(x) {
                // d lse / dx_k = exp(x_k - lse); zero for a lane that is all -inf.
                let (outer, n, inner) = axis_split(val(x).shape(), *axis, "logsumexp");
                let (full, red) = ([outer, n, inner], [outer, 1, inner]);
                let mut w = sink.alloc(val(x).numel());
                kernels::broadcast_zip(par, val(x).data(), &full, node.value.data(), &red, &full, &mut w, |x, l| {
                    if l == F::NEG_INFINITY {
                        F::ZERO
                    } else {
                        (x - l).exp()
                    }
                });
                let mut gx = sink.alloc(val(x).numel());
                kernels::broadcast_zip(par, &w, &full, g, &red, &full, &mut gx, |w, g| w * g);
                sink.add(x, gx);
            }
        }
        Op::Softmax(x, axis) => {
            // gx = y (g - <g, y>)
            lane_backward(*x, *axis, "softmax", &nodes[id], g, sink, |y, g, o| {
                let s: f64 = y.iter().zip(g).map(|(&y, &g)| (y * g).to_f64()).sum();
                let s = F::from_f64(s);
                for ((o, &y), &g) in o.iter_mut().zip(y).zip(g) {
                    *o = y * (g - s);
                }
            });
        }
        Op::LogSoftmax(x, axis) => {
            // gx = g - softmax(x) * sum(g); zero for a lane that is all -inf.
            lane_backward(*x, *axis, "log_softmax", &nodes[id], g, sink, |y, g, o| {
                let (m, _) = lane_max_logsum(y);
                if m == F::NEG_INFINITY {
                    o.iter_mut().for_each(|v| *v = F::ZERO);
                    return;
                }
                let s = F::from_f64(g.iter().map(|v| v.to_f64()).sum());
                for ((o, &y), &g) in o.iter_mut().zip(y).zip(g) {
                    *o = g - y.exp() * s;
                }
            });
        }
        Op::Gather(x, axis, idx) => {
            let x = *x;
            let (outer, n, inner) = axis_split(val(x).shape(), *axis, "gather");
            sink.add_with(x, |gx| kernels::scatter_add_rows(par, g, (outer, idx.len(), inner), idx, n, gx));
        }
        Op::ScatterAdd(x, axis, idx) => {
            let x = *x;
            if sink.wants(x) {
                let (outer, _, inner) = axis_split(val(x).shape(), *axis, "scatter_add");
                let size = out_shape[*axis];
                let mut gx = sink.alloc(val(x).numel());
                kernels::gather_rows(par, g, (outer, size, inner), idx, &mut gx);
                sink.add(x, gx);
            }
        }
        Op::Concat(parts, axis) => {
            let total = out_shape[*axis];
            let mut at = 0;
            for &p in parts {
                let (outer, n, inner) = axis_split(val(p).shape(), *axis, "concat");
                sink.add_with(p, |gp| {
                    kernels::copy_axis_range(g, (outer, total, inner), at, gp, (outer, n, inner), 0, n, true)
                });
                at += n;
            }
        }
        Op::Slice(x, axis, start) => {
            let x = *x;
            let (outer, n, inner) = axis_split(val(x).shape(), *axis, "slice");
            let len = out_shape[*axis];
            sink.add_with(x, |gx| {
                kernels::copy_axis_range(g, (outer, len, inner), 0, gx, (outer, n, inner), *start, len, true)
            });
        }
        Op::Reshape(x) => {
            let x = *x;
            if sink.wants(x) {
                let mut gx = sink.alloc(g.len());
                gx.copy_from_slice(g);
                sink.add(x, gx);
            }
        }
        Op::Transpose(x) => {
            let x = *x;
            if sink.wants(x) {
                let mut gx = sink.alloc(g.len());
                transpose_into(g, out_shape[0], out_shape[1], &mut gx);
                sink.add(x, gx);
            }
        }
        Op::BroadcastTo(x) => {
            let x = *x;
            if sink.wants(x) {
                sink.add(x, kernels::sum_to_shape(par, g, out_shape, val(x).shape()));
            }
        }
        Op::Precomputed(pairs) => {
            for &(x, p) in pairs {
                if !sink.wants(x) {
                    continue;
                }
                let (xs, pv) = (val(x).shape(), val(p));
                if pv.shape() == xs && xs.starts_with(out_shape) {
                    // Row-wise: gx[i, k] = g[i] p[i, k].
                    let mut g_shape = out_shape.to_vec();
                    g_shape.resize(xs.len(), 1);
                    let mut gx = sink.alloc(pv.numel());
                    kernels::broadcast_zip(par, g, &g_shape, pv.data(), xs, xs, &mut gx, |g, p| g * p);
                    sink.add(x, gx);
                } else if let Some(k) = trailing_column(xs, out_shape) {
                    // Element-wise with `x` a column `[.., 1]` of `[.., k]`: a dot product
                    // per row (accumulated in f64, as `sum_to_shape` would).
                    let mut gx = sink.alloc(pv.numel() / k.max(1));
                    for ((o, g), p) in gx.iter_mut().zip(g.chunks(k)).zip(pv.data().chunks(k)) {
                        *o = F::from_f64(g.iter().zip(p).map(|(&g, &p)| (g * p).to_f64()).sum());
                    }
                    sink.add(x, gx);
                } else {
                    // Element-wise: g p, summed over the axes `x` is broadcast along.
                    let mut full = sink.alloc(g.len());
                    kernels::zip(par, g, pv.data(), &mut full, |g, p| g * p);
                    if xs == out_shape {
                        sink.add(x, full);
                    } else {
                        let reduced = kernels::sum_to_shape(par, &full, out_shape, xs);
                        sink.tape_recycle(full);
                        sink.add(x, reduced);
                    }
                }
            }
        }
        Op::Where(mask, a, b) => {
            for (input, pick) in [(*a, true), (*b, false)] {
                if sink.wants(input) {
                    let mut gi = sink.alloc(g.len());
                    for ((o, &gv), &m) in gi.iter_mut().zip(g).zip(mask.iter()) {
                        *o = if m == pick { gv } else { F::ZERO };
                    }
                    sink.add(input, gi);
                }
            }
        }
    }
}

/// The VJP of an op on lanes along `axis` of its input `x` (the softmaxes), whose
/// rule needs only the lanes of the output `node` and of its cotangent `g`:
/// `rule(y, g, gx)` writes a lane of the input's gradient.
fn lane_backward<F: Float>(
    x: NodeId,
    axis: usize,
    name: &str,
    node: &Node<F>,
    g: &[F],
    sink: &mut GradSink<'_, F>,
    rule: impl Fn(&[F], &[F], &mut [F]) + Sync,
) {
    if sink.wants(x) {
        let dims = axis_split(node.value.shape(), axis, name);
        let mut gx = sink.alloc(g.len());
        kernels::map_lanes(sink.par, &[node.value.data(), g], &mut gx, dims, |l, o| rule(l[0], l[1], o));
        sink.add(x, gx);
    }
}

/// `Some(k)` if `x` is `out` with its last axis (of length `k > 1`) reduced to 1.
fn trailing_column(x: &[usize], out: &[usize]) -> Option<usize> {
    match (x.split_last(), out.split_last()) {
        (Some((1, xl)), Some((&k, ol))) if xl == ol && k > 1 => Some(k),
        _ => None,
    }
}

fn unary_backward<F: Float>(u: Unary, par: kernels::Parallelism, g: &[F], x: &[F], y: &[F], gx: &mut [F]) {
    use kernels::zip3;
    let zero = F::ZERO;
    let one = F::ONE;
    match u {
        Unary::Neg => kernels::map(par, g, gx, |g| -g),
        Unary::Exp => zip3(par, g, x, y, gx, |g, _, y| g * y),
        Unary::Log => zip3(par, g, x, y, gx, |g, x, _| g / x),
        Unary::Log1p => zip3(par, g, x, y, gx, |g, x, _| g / (one + x)),
        Unary::Tanh => zip3(par, g, x, y, gx, |g, _, y| g * (one - y * y)),
        Unary::Relu => zip3(par, g, x, y, gx, |g, x, _| if x > zero { g } else { zero }),
        Unary::Softplus => zip3(par, g, x, y, gx, |g, x, _| g * x.sigmoid()),
        Unary::Sigmoid => zip3(par, g, x, y, gx, |g, _, y| g * y * (one - y)),
        Unary::Sin => zip3(par, g, x, y, gx, |g, x, _| g * x.cos()),
        Unary::Cos => zip3(par, g, x, y, gx, |g, x, _| -g * x.sin()),
        Unary::Abs => zip3(par, g, x, y, gx, |g, x, _| {
            if x > zero {
                g
            } else if x < zero {
                -g
            } else {
                zero
            }
        }),
        Unary::Sqrt => zip3(par, g, x, y, gx, |g, _, y| g * F::from_f64(0.5) / y),
        Unary::Square => zip3(par, g, x, y, gx, |g, x, _| g * (x + x)),
        Unary::Powf(p) => {
            let (pf, pm1) = (F::from_f64(p), F::from_f64(p - 1.0));
            if p == 0.0 {
                gx.iter_mut().for_each(|v| *v = zero);
            } else {
                zip3(par, g, x, y, gx, |g, x, _| g * pf * x.powf(pm1))
            }
        }
        Unary::AddScalar(_) => gx.copy_from_slice(g),
        Unary::MulScalar(c) => {
            let c = F::from_f64(c);
            kernels::map(par, g, gx, |g| g * c)
        }
        Unary::Clamp(lo, hi) => {
            let (lo, hi) = (F::from_f64(lo), F::from_f64(hi));
            zip3(par, g, x, y, gx, |g, x, _| if x >= lo && x <= hi { g } else { zero })
        }
    }
}

fn binary_backward<F: Float>(
    b: Binary,
    nodes: &[Node<F>],
    id: NodeId,
    a: NodeId,
    c: NodeId,
    g: &[F],
    sink: &mut GradSink<'_, F>,
) {
    let par = sink.par;
    let out = nodes[id].value.shape();
    let (va, vc) = (&nodes[a].value, &nodes[c].value);
    let (sa, sc) = (va.shape(), vc.shape());
    let n = g.len();
    // Full-size contribution for one input, then summed down to its shape.
    let deliver = |sink: &mut GradSink<'_, F>, input: NodeId, shape: &[usize], full: Vec<F>| {
        if shape == out {
            sink.add(input, full);
        } else {
            let reduced = kernels::sum_to_shape(par, &full, out, shape);
            sink.add(input, reduced);
        }
    };
    let (wa, wc) = (sink.wants(a), sink.wants(c));
    match b {
        Binary::Add | Binary::Sub => {
            if wa {
                let mut ga = sink.alloc(n);
                ga.copy_from_slice(g);
                deliver(sink, a, sa, ga);
            }
            if wc {
                let mut gc = sink.alloc(n);
                if b == Binary::Add {
                    gc.copy_from_slice(g);
                } else {
                    kernels::map(par, g, &mut gc, |v| -v);
                }
                deliver(sink, c, sc, gc);
            }
        }
        Binary::Mul => {
            if wa {
                let mut ga = sink.alloc(n);
                kernels::broadcast_zip(par, g, out, vc.data(), sc, out, &mut ga, |g, y| g * y);
                deliver(sink, a, sa, ga);
            }
            if wc {
                let mut gc = sink.alloc(n);
                kernels::broadcast_zip(par, g, out, va.data(), sa, out, &mut gc, |g, x| g * x);
                deliver(sink, c, sc, gc);
            }
        }
        Binary::Div => {
            if wa {
                let mut ga = sink.alloc(n);
                kernels::broadcast_zip(par, g, out, vc.data(), sc, out, &mut ga, |g, y| g / y);
                deliver(sink, a, sa, ga);
            }
            if wc {
                // d(a/c)/dc = -z / c, with z the output.
                let mut gz = sink.alloc(n);
                kernels::zip(par, g, nodes[id].value.data(), &mut gz, |g, z| g * z);
                let mut gc = sink.alloc(n);
                kernels::broadcast_zip(par, &gz, out, vc.data(), sc, out, &mut gc, |t, y| -t / y);
                sink.tape_recycle(gz);
                deliver(sink, c, sc, gc);
            }
        }
        Binary::Atan2 | Binary::Min | Binary::Max => {
            // These need both operands at every output position: materialise them.
            let full = |sink: &GradSink<'_, F>, v: &[F], s: &[usize]| {
                let mut f = sink.alloc(n);
                kernels::expand(par, v, s, out, &mut f);
                f
            };
            let (fa, fc) = (full(sink, va.data(), sa), full(sink, vc.data(), sc));
            let d = |da: bool, fa: &[F], fc: &[F], dst: &mut [F]| match (b, da) {
                // atan2(y, x): d/dy = x / r^2, d/dx = -y / r^2.
                (Binary::Atan2, true) => kernels::zip3(par, g, fa, fc, dst, |g, y, x| g * x / (x * x + y * y)),
                (Binary::Atan2, false) => kernels::zip3(par, g, fa, fc, dst, |g, y, x| -g * y / (x * x + y * y)),
                (Binary::Min, true) => kernels::zip3(par, g, fa, fc, dst, |g, x, y| if x <= y { g } else { F::ZERO }),
                (Binary::Min, false) => kernels::zip3(par, g, fa, fc, dst, |g, x, y| if x <= y { F::ZERO } else { g }),
                (Binary::Max, true) => kernels::zip3(par, g, fa, fc, dst, |g, x, y| if x >= y { g } else { F::ZERO }),
                (Binary::Max, false) => kernels::zip3(par, g, fa, fc, dst, |g, x, y| if x >= y { F::ZERO } else { g }),
                _ => unreachable!("only atan2, min and max reach here"),
            };
            if wa {
                let mut ga = sink.alloc(n);
                d(true, &fa, &fc, &mut ga);
                deliver(sink, a, sa, ga);
            }
            if wc {
                let mut gc = sink.alloc(n);
                d(false, &fa, &fc, &mut gc);
                deliver(sink, c, sc, gc);
            }
            sink.tape_recycle(fa);
            sink.tape_recycle(fc);
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn matmul_backward<F: Float>(
    x: NodeId,
    w: NodeId,
    m: usize,
    k: usize,
    n: usize,
    xv: &[F],
    wv: &[F],
    g: &[F],
    sink: &mut GradSink<'_, F>,
) {
    let par = sink.par;
    if sink.wants(x) {
        // gx = g w^T
        let mut gx = sink.alloc(m * k);
        kernels::gemm(par, MatRef::new(g, m, n), MatRef::t(wv, k, n), F::ZERO, &mut gx);
        sink.add(x, gx);
    }
    if sink.wants(w) {
        // gw = x^T g, reduced over the long dimension in fixed blocks.
        let mut gw = sink.alloc_zeroed(k * n);
        kernels::gemm_at_b_acc(par, xv, g, m, k, n, &mut gw);
        sink.add(w, gw);
    }
}
