//! The closed vocabulary of operations and their forward passes.
//!
//! Every op is a variant of [`Op`]; its vector-Jacobian product lives in
//! `backward.rs`, in one exhaustive `match`, so adding an op without its
//! gradient does not compile. Shape errors are programmer errors: they panic
//! (with `#[track_caller]`) naming the op and the shapes involved.
//!
//! Subgradient conventions at kinks: `relu'(0) = 0`, `abs'(0) = 0`; `clamp` passes
//! the gradient on the closed interval `[lo, hi]`; `minimum`/`maximum` send the
//! whole gradient to the first argument on ties. `logsumexp` of a lane that is all
//! `-inf` is `-inf` with zero gradient; `softmax`/`log_softmax` of such a lane are
//! `0`/`-inf` with zero gradient. `+inf` inputs to these are not supported. An
//! element of a [`Tape::precomputed`] node that is `-inf` passes no gradient.

use std::ops::{Add, Div, Mul, Neg, Sub};
use std::sync::Arc;

use crate::float::Float;
use crate::kernels::{self, MatRef, Parallelism};
use crate::tape::{NodeId, Tape, Var};
use crate::tensor::{axis_split, broadcast_shapes, Tensor};

/// Element-wise unary operations (constants are stored as f64).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Unary {
    Neg,
    Exp,
    Log,
    Log1p,
    Tanh,
    Relu,
    Softplus,
    Sigmoid,
    Sin,
    Cos,
    Abs,
    Sqrt,
    Square,
    Powf(f64),
    AddScalar(f64),
    MulScalar(f64),
    Clamp(f64, f64),
}

/// Element-wise binary operations with numpy-style broadcasting.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Binary {
    Add,
    Sub,
    Mul,
    Div,
    /// `atan2(a, b)`: the angle of the point (b, a).
    Atan2,
    Min,
    Max,
}

/// One recorded operation: its inputs and whatever its VJP needs beyond their values.
#[derive(Clone, Debug)]
pub(crate) enum Op {
    /// A parameter (tracked) or constant; also every node of a non-recording tape.
    Leaf,
    Unary(Unary, NodeId),
    Binary(Binary, NodeId, NodeId),
    /// `[.., k] x [k, n] -> [.., n]`.
    Matmul(NodeId, NodeId),
    /// `x w + b`: `[.., k] x [k, n] + [n]`.
    Affine(NodeId, NodeId, NodeId),
    /// Sum of all elements (to a scalar).
    Sum(NodeId),
    SumAxis(NodeId, usize),
    LogSumExp(NodeId, usize),
    Softmax(NodeId, usize),
    LogSoftmax(NodeId, usize),
    Gather(NodeId, usize, Arc<[usize]>),
    ScatterAdd(NodeId, usize, Arc<[usize]>),
    Concat(Vec<NodeId>, usize),
    /// Input, axis, start (the length is the output's).
    Slice(NodeId, usize, usize),
    Reshape(NodeId),
    Transpose(NodeId),
    BroadcastTo(NodeId),
    /// Pick from the first input where the mask is true, else the second.
    Where(Arc<[bool]>, NodeId, NodeId),
    /// A value whose partials were computed with it ([`Tape::precomputed`]): per
    /// input, the (constant) node holding `d out / d input`.
    Precomputed(Vec<(NodeId, NodeId)>),
}

fn unary_forward<F: Float>(op: Unary, par: Parallelism, x: &[F], out: &mut [F]) {
    use kernels::map;
    match op {
        Unary::Neg => map(par, x, out, |v| -v),
        Unary::Exp => map(par, x, out, |v| v.exp()),
        Unary::Log => map(par, x, out, |v| v.ln()),
        Unary::Log1p => map(par, x, out, |v| v.ln_1p()),
        Unary::Tanh => map(par, x, out, |v| v.tanh()),
        Unary::Relu => map(par, x, out, |v| if v > F::ZERO { v } else { F::ZERO }),
        Unary::Softplus => map(par, x, out, |v| v.softplus()),
        Unary::Sigmoid => map(par, x, out, |v| v.sigmoid()),
        Unary::Sin => map(par, x, out, |v| v.sin()),
        Unary::Cos => map(par, x, out, |v| v.cos()),
        Unary::Abs => map(par, x, out, |v| v.abs()),
        Unary::Sqrt => map(par, x, out, |v| v.sqrt()),
        Unary::Square => map(par, x, out, |v| v * v),
        Unary::Powf(p) => {
            let p = F::from_f64(p);
            map(par, x, out, |v| v.powf(p))
        }
        Unary::AddScalar(c) => {
            let c = F::from_f64(c);
            map(par, x, out, |v| v + c)
        }
        Unary::MulScalar(c) => {
            let c = F::from_f64(c);
            map(par, x, out, |v| v * c)
        }
        Unary::Clamp(lo, hi) => {
            let (lo, hi) = (F::from_f64(lo), F::from_f64(hi));
            map(par, x, out, |v| v.max(lo).min(hi))
        }
    }
}

/// `max` of a lane and `ln sum exp(x - max)` accumulated in f64; `(-inf, 0)` if all -inf.
#[inline]
pub(crate) fn lane_max_logsum<F: Float>(lane: &[F]) -> (F, f64) {
    let m = lane.iter().fold(F::NEG_INFINITY, |a, &b| a.max(b));
    if m == F::NEG_INFINITY {
        return (m, 0.0);
    }
    let s: f64 = lane.iter().map(|&x| (x - m).exp().to_f64()).sum();
    (m, s.ln())
}

/// Output shape of a reduction over `axis`.
fn reduced_shape(shape: &[usize], axis: usize, keepdim: bool) -> Vec<usize> {
    let mut s = shape.to_vec();
    if keepdim {
        s[axis] = 1;
    } else {
        s.remove(axis);
    }
    s
}

impl<'t, F: Float> Var<'t, F> {
    #[track_caller]
    fn same_tape(self, other: Var<'t, F>, op: &str) {
        assert!(std::ptr::eq(self.tape, other.tape), "{op}: operands live on different tapes");
    }

    /// Runs `compute(input values, output buffer)` and records the result.
    fn record(
        self,
        inputs: &[NodeId],
        shape: Vec<usize>,
        op: impl FnOnce() -> Op,
        compute: impl FnOnce(&[&Tensor<F>], &mut [F], Parallelism),
    ) -> Var<'t, F> {
        let tape = self.tape;
        let numel = shape.iter().product();
        let mut out = tape.alloc(numel);
        let tracked;
        {
            let nodes = tape.nodes();
            let vals: Vec<&Tensor<F>> = inputs.iter().map(|&i| &nodes[i].value).collect();
            compute(&vals, &mut out, tape.parallelism());
            tracked = tape.is_recording() && inputs.iter().any(|&i| nodes[i].tracked);
        }
        let op = if tracked { op() } else { Op::Leaf };
        tape.push_node(Tensor::from_parts(shape, out), op, tracked)
    }

    fn unary(self, u: Unary) -> Var<'t, F> {
        let shape = self.shape();
        self.record(&[self.id], shape, || Op::Unary(u, self.id), |v, out, par| unary_forward(u, par, v[0].data(), out))
    }

    #[track_caller]
    fn binary(self, other: Var<'t, F>, b: Binary) -> Var<'t, F> {
        self.same_tape(other, "binary op");
        let (sa, sb) = (self.shape(), other.shape());
        let Some(shape) = broadcast_shapes(&sa, &sb) else {
            panic!("{b:?}: shapes {sa:?} and {sb:?} do not broadcast");
        };
        let out_shape = shape.clone();
        self.record(
            &[self.id, other.id],
            shape,
            || Op::Binary(b, self.id, other.id),
            |v, out, par| {
                let (a, c) = (v[0], v[1]);
                let z = |f: fn(F, F) -> F, out: &mut [F]| {
                    kernels::broadcast_zip(par, a.data(), a.shape(), c.data(), c.shape(), &out_shape, out, f)
                };
                match b {
                    Binary::Add => z(|x, y| x + y, out),
                    Binary::Sub => z(|x, y| x - y, out),
                    Binary::Mul => z(|x, y| x * y, out),
                    Binary::Div => z(|x, y| x / y, out),
                    Binary::Atan2 => z(|x, y| x.atan2(y), out),
                    Binary::Min => z(|x, y| if y < x { y } else { x }, out),
                    Binary::Max => z(|x, y| if y > x { y } else { x }, out),
                }
            },
        )
    }

    /// Element-wise `-x`.
    // `Var` also implements `std::ops::Neg` (with the same result); this inherent method is public API.
    #[allow(clippy::should_implement_trait)]
    pub fn neg(self) -> Var<'t, F> {
        self.unary(Unary::Neg)
    }
    /// Element-wise `e^x`.
    pub fn exp(self) -> Var<'t, F> {
        self.unary(Unary::Exp)
    }
    /// Element-wise natural log (`-inf` at 0).
    pub fn ln(self) -> Var<'t, F> {
        self.unary(Unary::Log)
    }
    /// Element-wise `ln(1 + x)`.
    pub fn ln_1p(self) -> Var<'t, F> {
        self.unary(Unary::Log1p)
    }
    /// Element-wise hyperbolic tangent.
    pub fn tanh(self) -> Var<'t, F> {
        self.unary(Unary::Tanh)
    }
    /// Element-wise `max(x, 0)` (subgradient 0 at 0).
    pub fn relu(self) -> Var<'t, F> {
        self.unary(Unary::Relu)
    }
    /// Element-wise `ln(1 + e^x)`, stable for large |x|.
    pub fn softplus(self) -> Var<'t, F> {
        self.unary(Unary::Softplus)
    }
    /// Element-wise logistic sigmoid.
    pub fn sigmoid(self) -> Var<'t, F> {
        self.unary(Unary::Sigmoid)
    }
    /// Element-wise sine.
    pub fn sin(self) -> Var<'t, F> {
        self.unary(Unary::Sin)
    }
    /// Element-wise cosine.
    pub fn cos(self) -> Var<'t, F> {
        self.unary(Unary::Cos)
    }
    /// Element-wise absolute value (subgradient 0 at 0).
    pub fn abs(self) -> Var<'t, F> {
        self.unary(Unary::Abs)
    }
    /// Element-wise square root.
    pub fn sqrt(self) -> Var<'t, F> {
        self.unary(Unary::Sqrt)
    }
    /// Element-wise `x^2`.
    pub fn square(self) -> Var<'t, F> {
        self.unary(Unary::Square)
    }
    /// Element-wise `x^p` for a constant `p`.
    pub fn powf(self, p: f64) -> Var<'t, F> {
        self.unary(Unary::Powf(p))
    }
    /// Element-wise `x + c`.
    pub fn add_scalar(self, c: f64) -> Var<'t, F> {
        self.unary(Unary::AddScalar(c))
    }
    /// Element-wise `c x`.
    pub fn mul_scalar(self, c: f64) -> Var<'t, F> {
        self.unary(Unary::MulScalar(c))
    }
    /// Element-wise clamp to `[lo, hi]` (gradient passes on the closed interval).
    pub fn clamp(self, lo: f64, hi: f64) -> Var<'t, F> {
        self.unary(Unary::Clamp(lo, hi))
    }

    /// Element-wise `atan2(self, x)`, broadcasting: the angle of the point `(x, self)`.
    #[track_caller]
    pub fn atan2(self, x: Var<'t, F>) -> Var<'t, F> {
        self.binary(x, Binary::Atan2)
    }
    /// Element-wise minimum, broadcasting (ties send the gradient to `self`).
    #[track_caller]
    pub fn minimum(self, other: Var<'t, F>) -> Var<'t, F> {
        self.binary(other, Binary::Min)
    }
    /// Element-wise maximum, broadcasting (ties send the gradient to `self`).
    #[track_caller]
    pub fn maximum(self, other: Var<'t, F>) -> Var<'t, F> {
        self.binary(other, Binary::Max)
    }

    /// Matrix product `[.., k] x [k, n] -> [.., n]`: every row of `self` (all leading
    /// dimensions flattened) times the matrix `w`.
    #[track_caller]
    pub fn matmul(self, w: Var<'t, F>) -> Var<'t, F> {
        self.same_tape(w, "matmul");
        let (sx, sw) = (self.shape(), w.shape());
        let shape = matmul_shape(&sx, &sw, "matmul");
        self.record(
            &[self.id, w.id],
            shape,
            || Op::Matmul(self.id, w.id),
            |v, out, par| {
                let (m, k, n) = (leading_rows(&sx), sw[0], sw[1]);
                kernels::gemm(par, MatRef::new(v[0].data(), m, k), MatRef::new(v[1].data(), k, n), F::ZERO, out);
            },
        )
    }

    /// Affine map `x w + b`: `[.., k] x [k, n] + [n] -> [.., n]`, fused into one op.
    #[track_caller]
    pub fn affine(self, w: Var<'t, F>, b: Var<'t, F>) -> Var<'t, F> {
        self.same_tape(w, "affine");
        self.same_tape(b, "affine");
        let (sx, sw, sb) = (self.shape(), w.shape(), b.shape());
        let shape = matmul_shape(&sx, &sw, "affine");
        assert!(sb == [sw[1]], "affine: bias shape {sb:?} must be [{}]", sw[1]);
        self.record(
            &[self.id, w.id, b.id],
            shape,
            || Op::Affine(self.id, w.id, b.id),
            |v, out, par| {
                let (m, k, n) = (leading_rows(&sx), sw[0], sw[1]);
                kernels::gemm(par, MatRef::new(v[0].data(), m, k), MatRef::new(v[1].data(), k, n), F::ZERO, out);
                kernels::add_rows(par, out, v[2].data());
            },
        )
    }

    /// Sum of all elements, as a scalar (accumulated in f64).
    pub fn sum(self) -> Var<'t, F> {
        self.record(
            &[self.id],
            vec![],
            || Op::Sum(self.id),
            |v, out, par| {
                out[0] = F::from_f64(kernels::sum_f64(par, v[0].data()));
            },
        )
    }

    /// Mean of all elements, as a scalar.
    pub fn mean(self) -> Var<'t, F> {
        let n = self.numel().max(1);
        self.sum().mul_scalar(1.0 / n as f64)
    }

    /// Sum along `axis` (the axis is kept with length 1 if `keepdim`).
    #[track_caller]
    pub fn sum_axis(self, axis: usize, keepdim: bool) -> Var<'t, F> {
        self.reduce_lanes(axis, keepdim, "sum_axis", Op::SumAxis, |lane| {
            F::from_f64(lane.iter().map(|x| x.to_f64()).sum())
        })
    }

    /// Mean along `axis`.
    #[track_caller]
    pub fn mean_axis(self, axis: usize, keepdim: bool) -> Var<'t, F> {
        let n = self.shape()[axis].max(1);
        self.sum_axis(axis, keepdim).mul_scalar(1.0 / n as f64)
    }

    /// `ln sum exp` along `axis`, fused and stable (a lane of all `-inf` gives `-inf`).
    #[track_caller]
    pub fn logsumexp(self, axis: usize, keepdim: bool) -> Var<'t, F> {
        self.reduce_lanes(axis, keepdim, "logsumexp", Op::LogSumExp, |lane| {
            let (m, ls) = lane_max_logsum(lane);
            if m == F::NEG_INFINITY {
                m
            } else {
                m + F::from_f64(ls)
            }
        })
    }

    /// The forward pass of [`Var::sum_axis`] and [`Var::logsumexp`]: `f` of each lane
    /// along `axis`, recorded as `op(self, axis)`.
    #[track_caller]
    fn reduce_lanes(
        self,
        axis: usize,
        keepdim: bool,
        name: &str,
        op: fn(NodeId, usize) -> Op,
        f: impl Fn(&[F]) -> F + Sync,
    ) -> Var<'t, F> {
        let shape = self.shape();
        let dims = axis_split(&shape, axis, name);
        self.record(
            &[self.id],
            reduced_shape(&shape, axis, keepdim),
            || op(self.id, axis),
            |v, out, par| kernels::reduce_lanes(par, v[0].data(), out, dims, f),
        )
    }

    /// Softmax along `axis`.
    #[track_caller]
    pub fn softmax(self, axis: usize) -> Var<'t, F> {
        self.normalised_lanes(axis, "softmax", Op::Softmax, F::ZERO, |z| z.exp())
    }

    /// Log-softmax along `axis` (normalised log-weights).
    #[track_caller]
    pub fn log_softmax(self, axis: usize) -> Var<'t, F> {
        self.normalised_lanes(axis, "log_softmax", Op::LogSoftmax, F::NEG_INFINITY, |z| z)
    }

    /// The forward pass of [`Var::softmax`] (`f = exp`) and [`Var::log_softmax`]
    /// (`f` the identity): `f(x - shift)` with `shift` the lane's log-sum-exp along
    /// `axis`; `empty` throughout a lane that is all -inf.
    #[track_caller]
    fn normalised_lanes(
        self,
        axis: usize,
        name: &str,
        op: fn(NodeId, usize) -> Op,
        empty: F,
        f: impl Fn(F) -> F + Sync,
    ) -> Var<'t, F> {
        let shape = self.shape();
        let dims = axis_split(&shape, axis, name);
        self.record(
            &[self.id],
            shape,
            || op(self.id, axis),
            |v, out, par| {
                kernels::map_lanes(par, &[v[0].data()], out, dims, |lanes, o| {
                    let (m, ls) = lane_max_logsum(lanes[0]);
                    if m == F::NEG_INFINITY {
                        o.iter_mut().for_each(|y| *y = empty);
                    } else {
                        let shift = m + F::from_f64(ls);
                        for (y, &x) in o.iter_mut().zip(lanes[0]) {
                            *y = f(x - shift);
                        }
                    }
                })
            },
        )
    }

    /// Selects positions `indices` along `axis` (repeats allowed): resampling.
    #[track_caller]
    pub fn gather(self, axis: usize, indices: &[usize]) -> Var<'t, F> {
        let shape = self.shape();
        let dims = axis_split(&shape, axis, "gather");
        let mut out_shape = shape.clone();
        out_shape[axis] = indices.len();
        let idx: Arc<[usize]> = indices.into();
        let idx2 = idx.clone();
        self.record(
            &[self.id],
            out_shape,
            move || Op::Gather(self.id, axis, idx2),
            |v, out, par| kernels::gather_rows(par, v[0].data(), dims, &idx, out),
        )
    }

    /// Alias of [`Var::gather`] (PyTorch's name for a gather of whole slices).
    #[track_caller]
    pub fn index_select(self, axis: usize, indices: &[usize]) -> Var<'t, F> {
        self.gather(axis, indices)
    }

    /// Adds slice `j` along `axis` into position `indices[j]` of a zero tensor whose
    /// `axis` has length `size` (e.g. summing particle weights onto their ancestors).
    #[track_caller]
    pub fn scatter_add(self, axis: usize, indices: &[usize], size: usize) -> Var<'t, F> {
        let shape = self.shape();
        let dims = axis_split(&shape, axis, "scatter_add");
        assert_eq!(
            indices.len(),
            shape[axis],
            "scatter_add: {} indices for axis {axis} of shape {shape:?}",
            indices.len()
        );
        let mut out_shape = shape.clone();
        out_shape[axis] = size;
        let idx: Arc<[usize]> = indices.into();
        let idx2 = idx.clone();
        self.record(
            &[self.id],
            out_shape,
            move || Op::ScatterAdd(self.id, axis, idx2),
            |v, out, par| {
                out.fill(F::ZERO);
                kernels::scatter_add_rows(par, v[0].data(), dims, &idx, size, out)
            },
        )
    }

    /// The sub-range `start..start + len` along `axis`.
    #[track_caller]
    pub fn slice(self, axis: usize, start: usize, len: usize) -> Var<'t, F> {
        let shape = self.shape();
        let dims = axis_split(&shape, axis, "slice");
        assert!(
            start + len <= shape[axis],
            "slice: {start}..{} out of range for axis {axis} of {shape:?}",
            start + len
        );
        let mut out_shape = shape.clone();
        out_shape[axis] = len;
        let out_dims = (dims.0, len, dims.2);
        self.record(
            &[self.id],
            out_shape,
            || Op::Slice(self.id, axis, start),
            |v, out, _| kernels::copy_axis_range(v[0].data(), dims, start, out, out_dims, 0, len, false),
        )
    }

    /// The same data with a new shape of equal size.
    #[track_caller]
    pub fn reshape(self, shape: &[usize]) -> Var<'t, F> {
        let old = self.shape();
        assert_eq!(
            old.iter().product::<usize>(),
            shape.iter().product::<usize>(),
            "reshape: {old:?} -> {shape:?} changes the element count"
        );
        self.record(&[self.id], shape.to_vec(), || Op::Reshape(self.id), |v, out, _| out.copy_from_slice(v[0].data()))
    }

    /// Transpose of a matrix.
    #[track_caller]
    pub fn t(self) -> Var<'t, F> {
        let s = self.shape();
        assert_eq!(s.len(), 2, "t: expected a matrix, got shape {s:?}");
        self.record(
            &[self.id],
            vec![s[1], s[0]],
            || Op::Transpose(self.id),
            |v, out, _| transpose_into(v[0].data(), s[0], s[1], out),
        )
    }

    /// Broadcasts to `shape` (numpy rules).
    #[track_caller]
    pub fn broadcast_to(self, shape: &[usize]) -> Var<'t, F> {
        let s = self.shape();
        assert_eq!(broadcast_shapes(&s, shape).as_deref(), Some(shape), "broadcast_to: {s:?} -> {shape:?}");
        let to = shape.to_vec();
        self.record(
            &[self.id],
            to.clone(),
            || Op::BroadcastTo(self.id),
            |v, out, par| kernels::expand(par, v[0].data(), v[0].shape(), &to, out),
        )
    }
}

pub(crate) fn transpose_into<F: Float>(src: &[F], rows: usize, cols: usize, dst: &mut [F]) {
    for r in 0..rows {
        for c in 0..cols {
            dst[c * rows + r] = src[r * cols + c];
        }
    }
}

/// Rows of the matrix that a `[.., k]` operand of a matrix product stands for: the
/// product of its leading dimensions (`numel / k` is wrong for `k = 0`).
pub(crate) fn leading_rows(shape: &[usize]) -> usize {
    shape[..shape.len().saturating_sub(1)].iter().product()
}

#[track_caller]
fn matmul_shape(sx: &[usize], sw: &[usize], op: &str) -> Vec<usize> {
    assert!(sw.len() == 2, "{op}: weights must be a matrix, got shape {sw:?}");
    assert!(
        !sx.is_empty() && sx[sx.len() - 1] == sw[0],
        "{op}: shapes {sx:?} and {sw:?} do not chain (last dimension must be {})",
        sw[0]
    );
    let mut shape = sx.to_vec();
    *shape.last_mut().expect("non-empty") = sw[1];
    shape
}

impl<F: Float> Tape<F> {
    /// Concatenation along `axis`; all other dimensions must agree.
    #[track_caller]
    pub fn concat<'t>(&'t self, parts: &[Var<'t, F>], axis: usize) -> Var<'t, F> {
        assert!(!parts.is_empty(), "concat: no inputs");
        let shapes: Vec<Vec<usize>> = parts.iter().map(|p| p.shape()).collect();
        let first = &shapes[0];
        for (s, p) in shapes.iter().zip(parts) {
            assert!(
                s.len() == first.len()
                    && axis < s.len()
                    && s.iter().zip(first).enumerate().all(|(d, (a, b))| d == axis || a == b),
                "concat: shapes {shapes:?} do not agree off axis {axis}"
            );
            assert!(std::ptr::eq(p.tape, self), "concat: inputs live on another tape");
        }
        let total: usize = shapes.iter().map(|s| s[axis]).sum();
        let mut out_shape = first.clone();
        out_shape[axis] = total;
        let ids: Vec<NodeId> = parts.iter().map(|p| p.id).collect();
        let ids2 = ids.clone();
        let (outer, _, inner) = axis_split(first, axis, "concat");
        parts[0].record(
            &ids,
            out_shape,
            move || Op::Concat(ids2, axis),
            |v, out, _| {
                let mut at = 0;
                for t in v {
                    let n = t.shape()[axis];
                    kernels::copy_axis_range(t.data(), (outer, n, inner), 0, out, (outer, total, inner), at, n, false);
                    at += n;
                }
            },
        )
    }

    /// A node whose value and partial derivatives were computed together outside the
    /// tape, in one pass: Stan's precomputed-gradients node. Fused log-densities use
    /// it: one node and one buffer of partials per input instead of a graph of
    /// element-wise temporaries, and one place that guards `-inf`.
    ///
    /// Each `(input, partial)` pair gives `d value / d input` in one of two layouts:
    ///
    /// * **element-wise**: `input`'s shape broadcasts to `value`'s and `partial` has
    ///   `value`'s shape: `d value_i / d input_b(i) = partial_i`, summed over the
    ///   broadcast axes in the reverse pass (a `[1]` parameter shared by all rows);
    /// * **row-wise**: `input`'s shape is `value`'s followed by trailing dimensions
    ///   (`[R] <- [R, K]`) and `partial` has `input`'s shape:
    ///   `d value_i / d input_{i, k} = partial_{i, k}`.
    ///
    /// The two agree when the shapes are equal. An element of `value` that is `-inf`
    /// (an impossible row) passes no gradient, whatever its partials. Untracked
    /// inputs are dropped; with none tracked, or on a non-recording tape, the result
    /// is a constant.
    ///
    /// ```
    /// use autodiff::{Tape, Tensor};
    /// let tape = Tape::<f64>::new();
    /// let x = tape.param(Tensor::from_vec(vec![1.0, -2.0]));
    /// let xv = x.to_tensor();
    /// // y = x^2 with dy/dx = 2x, as one node.
    /// let y = tape.precomputed(xv.map(|v| v * v), vec![(x, xv.map(|v| 2.0 * v))]);
    /// let g = tape.backward(y.sum());
    /// assert_eq!(g.wrt(x).data(), &[2.0, -4.0]);
    /// ```
    ///
    /// # Panics
    /// If an input lives on another tape or a partial's shape fits neither layout.
    #[track_caller]
    pub fn precomputed<'t>(&'t self, value: Tensor<F>, partials: Vec<(Var<'t, F>, Tensor<F>)>) -> Var<'t, F> {
        let out_shape = value.shape().to_vec();
        let mut pairs = Vec::with_capacity(partials.len());
        for (input, mut partial) in partials {
            assert!(std::ptr::eq(input.tape, self), "precomputed: an input lives on another tape");
            let xs = input.shape();
            let ps = partial.shape();
            let row_wise = ps == xs.as_slice() && xs.starts_with(&out_shape);
            let element_wise =
                ps == out_shape.as_slice() && broadcast_shapes(&xs, &out_shape).as_deref() == Some(&out_shape[..]);
            assert!(
                row_wise || element_wise,
                "precomputed: partial of shape {ps:?} for an input of shape {xs:?} and a value of shape {out_shape:?} \
                 (expected the value's shape, with an input that broadcasts to it, or the input's, with the value's \
                 shape leading)"
            );
            if !(self.is_recording() && input.is_tracked()) {
                continue;
            }
            // An impossible element has no slope.
            let per = partial.numel() / value.numel().max(1);
            for (i, &v) in value.data().iter().enumerate() {
                if v == F::NEG_INFINITY {
                    partial.data_mut()[i * per..(i + 1) * per].fill(F::ZERO);
                }
            }
            let p = self.push_node(partial, Op::Leaf, false);
            pairs.push((input.id, p.id));
        }
        let tracked = !pairs.is_empty();
        self.push_node(value, Op::Precomputed(pairs), tracked)
    }

    /// Element-wise choice: `a` where `mask` is true, `b` elsewhere (same shapes).
    #[track_caller]
    pub fn select<'t>(&'t self, mask: &[bool], a: Var<'t, F>, b: Var<'t, F>) -> Var<'t, F> {
        a.same_tape(b, "select");
        let (sa, sb) = (a.shape(), b.shape());
        assert!(
            sa == sb && mask.len() == a.numel(),
            "select: mask of {} elements with shapes {sa:?} and {sb:?}",
            mask.len()
        );
        let m: Arc<[bool]> = mask.into();
        let m2 = m.clone();
        a.record(
            &[a.id, b.id],
            sa,
            move || Op::Where(m2, a.id, b.id),
            |v, out, _| {
                for (((o, &x), &y), &k) in out.iter_mut().zip(v[0].data()).zip(v[1].data()).zip(m.iter()) {
                    *o = if k { x } else { y };
                }
            },
        )
    }
}

macro_rules! binary_operator {
    ($trait:ident, $method:ident, $variant:ident) => {
        impl<'t, F: Float> $trait<Var<'t, F>> for Var<'t, F> {
            type Output = Var<'t, F>;
            #[track_caller]
            fn $method(self, rhs: Var<'t, F>) -> Var<'t, F> {
                self.binary(rhs, Binary::$variant)
            }
        }
        impl<'t, F: Float> $trait<f64> for Var<'t, F> {
            type Output = Var<'t, F>;
            fn $method(self, rhs: f64) -> Var<'t, F> {
                let c = self.tape.scalar(rhs);
                self.binary(c, Binary::$variant)
            }
        }
        impl<'t, F: Float> $trait<Var<'t, F>> for f64 {
            type Output = Var<'t, F>;
            fn $method(self, rhs: Var<'t, F>) -> Var<'t, F> {
                let c = rhs.tape.scalar(self);
                c.binary(rhs, Binary::$variant)
            }
        }
    };
}

binary_operator!(Add, add, Add);
binary_operator!(Sub, sub, Sub);
binary_operator!(Mul, mul, Mul);
binary_operator!(Div, div, Div);

impl<'t, F: Float> Neg for Var<'t, F> {
    type Output = Var<'t, F>;
    fn neg(self) -> Var<'t, F> {
        self.unary(Unary::Neg)
    }
}
