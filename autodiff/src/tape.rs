//! The tape (a Wengert list of whole-tensor operations), the `Copy` handles that
//! point into it, and the reverse pass that turns a recorded computation into
//! vector-Jacobian products.
//!
//! Values are owned by the tape; a [`Var`] is an index plus a borrow of the tape, so
//! handles are free to copy and cannot outlive the tape or survive a
//! [`Tape::reset`] (which needs `&mut`). Buffers of a reset tape are recycled, so a
//! loop that rebuilds the same computation each step stops allocating after the
//! first one.

use std::cell::{Cell, Ref, RefCell};
use std::collections::BTreeMap;
use std::fmt;

use crate::backward;
use crate::float::Float;
use crate::kernels::{self, Parallelism};
use crate::ops::Op;
use crate::tensor::Tensor;

/// Index of a node on a tape.
pub(crate) type NodeId = usize;

/// Most recycled buffers a tape keeps between resets.
const MAX_POOLED_BUFFERS: usize = 4096;

pub(crate) struct Node<F: Float> {
    pub value: Tensor<F>,
    pub op: Op,
    /// Depends on a tracked leaf (a parameter) through recorded ops.
    pub tracked: bool,
}

/// Recycled buffers keyed by their length. A request takes a buffer of exactly its
/// length if there is one, else the shortest longer one (truncated), so reuse costs
/// no fill; only when none is long enough does it extend a shorter one with room
/// (zero-filling the gap). A computation rebuilt step after step asks for the same
/// lengths again, so exact matches are the rule.
struct Pool<F> {
    by_len: BTreeMap<usize, Vec<Vec<F>>>,
    count: usize,
}

impl<F> Default for Pool<F> {
    fn default() -> Self {
        Pool { by_len: BTreeMap::new(), count: 0 }
    }
}

impl<F> Pool<F> {
    /// Keeps `buf` (dropped if the pool holds [`MAX_POOLED_BUFFERS`] already).
    fn put(&mut self, buf: Vec<F>) {
        if self.count < MAX_POOLED_BUFFERS && buf.capacity() > 0 {
            self.by_len.entry(buf.len()).or_default().push(buf);
            self.count += 1;
        }
    }

    /// A buffer for `len` elements: of length at least `len` (the shortest such),
    /// else a shorter one with room for `len` (which the caller has to extend).
    fn take(&mut self, len: usize) -> Option<Vec<F>> {
        let key = match self.by_len.range(len..).next() {
            Some((&key, _)) => key,
            None => *self.by_len.iter().rev().find(|(_, bufs)| bufs.iter().any(|b| b.capacity() >= len))?.0,
        };
        let bufs = self.by_len.get_mut(&key).expect("a pooled length");
        let at = bufs.iter().position(|b| b.capacity() >= len).expect("a buffer with room");
        let buf = bufs.swap_remove(at);
        if bufs.is_empty() {
            self.by_len.remove(&key);
        }
        self.count -= 1;
        Some(buf)
    }
}

/// A recording of tensor operations, differentiable in reverse mode.
///
/// ```
/// use autodiff::{Tape, Tensor};
/// let tape = Tape::<f64>::new();
/// let x = tape.param(Tensor::from_vec(vec![1.0, 2.0]));
/// let y = (x * x).sum(); // y = x1^2 + x2^2
/// let g = tape.backward(y);
/// assert_eq!(g.wrt(x).data(), &[2.0, 4.0]);
/// ```
pub struct Tape<F: Float = f64> {
    nodes: RefCell<Vec<Node<F>>>,
    pool: RefCell<Pool<F>>,
    recording: Cell<bool>,
    par: Cell<Parallelism>,
}

impl<F: Float> Default for Tape<F> {
    fn default() -> Self {
        Self::new()
    }
}

impl<F: Float> fmt::Debug for Tape<F> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Tape")
            .field("nodes", &self.len())
            .field("recording", &self.recording.get())
            .field("parallelism", &self.par.get())
            .finish()
    }
}

impl<F: Float> Tape<F> {
    /// A recording tape whose large ops use rayon.
    pub fn new() -> Self {
        Tape {
            nodes: RefCell::new(Vec::new()),
            pool: RefCell::new(Pool::default()),
            recording: Cell::new(true),
            par: Cell::new(Parallelism::Rayon),
        }
    }

    /// A tape that does not record: ops compute values only, parameters are bound as
    /// constants and nothing can be differentiated. The same model code runs on it.
    pub fn no_record() -> Self {
        let t = Self::new();
        t.recording.set(false);
        t
    }

    /// Sets how ops on this tape use threads (e.g. `Serial` inside an outer parallel loop).
    pub fn with_parallelism(self, par: Parallelism) -> Self {
        self.par.set(par);
        self
    }

    /// How ops on this tape use threads.
    pub fn parallelism(&self) -> Parallelism {
        self.par.get()
    }

    /// Whether ops are recorded for differentiation.
    pub fn is_recording(&self) -> bool {
        self.recording.get()
    }

    /// Number of nodes on the tape.
    pub fn len(&self) -> usize {
        self.nodes.borrow().len()
    }

    /// Whether the tape holds no nodes.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Clears every node, keeping their buffers for reuse by the next computation.
    pub fn reset(&mut self) {
        let nodes = std::mem::take(self.nodes.get_mut());
        let pool = self.pool.get_mut();
        for node in nodes {
            pool.put(node.value.into_parts().1);
        }
    }

    /// A tracked leaf: gradients flow to it (a constant on a non-recording tape).
    pub fn param(&self, value: Tensor<F>) -> Var<'_, F> {
        let tracked = self.is_recording();
        self.push_node(value, Op::Leaf, tracked)
    }

    /// An untracked leaf: a constant input.
    pub fn constant(&self, value: Tensor<F>) -> Var<'_, F> {
        self.push_node(value, Op::Leaf, false)
    }

    /// A scalar constant.
    pub fn scalar(&self, x: f64) -> Var<'_, F> {
        self.constant(Tensor::scalar(F::from_f64(x)))
    }

    /// A buffer of `len` elements with unspecified (but initialised) contents, recycled
    /// from earlier steps when possible. For outputs that are written in full.
    pub(crate) fn alloc(&self, len: usize) -> Vec<F> {
        let buf = self.pool.borrow_mut().take(len);
        match buf {
            Some(mut buf) => {
                // Within the buffer's length no fill is needed; beyond it, zeros.
                buf.resize(len, F::ZERO);
                buf
            }
            None => vec![F::ZERO; len],
        }
    }

    /// A buffer of `len` elements recycled from earlier computations on this tape when
    /// possible (see [`Tape::reset`]): its contents are unspecified (stale values),
    /// so write every element. For code that builds a node's value or partials
    /// outside the tape ([`Tape::precomputed`]) without fresh allocations.
    pub fn buffer(&self, len: usize) -> Vec<F> {
        self.alloc(len)
    }

    /// A zero-filled buffer of `len` elements (for outputs that are accumulated into).
    pub(crate) fn alloc_zeroed(&self, len: usize) -> Vec<F> {
        let mut buf = self.alloc(len);
        buf.fill(F::ZERO);
        buf
    }

    /// Returns a no-longer-needed buffer to the pool.
    pub(crate) fn recycle(&self, buf: Vec<F>) {
        self.pool.borrow_mut().put(buf);
    }

    pub(crate) fn push_node(&self, value: Tensor<F>, op: Op, tracked: bool) -> Var<'_, F> {
        let mut nodes = self.nodes.borrow_mut();
        let (op, tracked) = if tracked && self.is_recording() { (op, true) } else { (Op::Leaf, false) };
        nodes.push(Node { value, op, tracked });
        Var { tape: self, id: nodes.len() - 1 }
    }

    pub(crate) fn nodes(&self) -> Ref<'_, Vec<Node<F>>> {
        self.nodes.borrow()
    }

    pub(crate) fn is_tracked(&self, id: NodeId) -> bool {
        self.nodes.borrow()[id].tracked
    }

    /// Reverse pass from a scalar: the gradient of `output` with respect to every
    /// tracked leaf.
    #[track_caller]
    pub fn backward(&self, output: Var<'_, F>) -> Gradients<F> {
        let shape = output.shape();
        assert!(
            shape.iter().product::<usize>() == 1,
            "backward: output must be a scalar, got shape {shape:?} (use vjp for a cotangent)"
        );
        self.vjp(output, Tensor::ones(&shape))
    }

    /// Vector-Jacobian product: `cotangent^T d output / d leaf` for every tracked leaf,
    /// in one reverse walk of the tape.
    #[track_caller]
    pub fn vjp(&self, output: Var<'_, F>, cotangent: Tensor<F>) -> Gradients<F> {
        assert!(std::ptr::eq(output.tape, self), "vjp: output belongs to another tape");
        let nodes = self.nodes.borrow();
        let out_shape = nodes[output.id].value.shape();
        assert_eq!(out_shape, cotangent.shape(), "vjp: cotangent shape must equal output shape");
        let mut grads: Vec<Option<Vec<F>>> = Vec::new();
        grads.resize_with(output.id + 1, || None);
        if nodes[output.id].tracked {
            grads[output.id] = Some(cotangent.into_data());
        }
        let par = self.par.get();
        let mut leaf_grads: Vec<Option<Tensor<F>>> = Vec::new();
        leaf_grads.resize_with(output.id + 1, || None);
        for id in (0..=output.id).rev() {
            let Some(g) = grads[id].take() else { continue };
            let node = &nodes[id];
            if let Op::Leaf = node.op {
                leaf_grads[id] = Some(Tensor::from_parts(node.value.shape().to_vec(), g));
                continue;
            }
            let mut sink = GradSink { nodes: &nodes, grads: &mut grads, par, tape: self };
            backward::backward_node(&nodes, id, &g, &mut sink);
            self.recycle(g);
        }
        Gradients { grads: leaf_grads }
    }
}

/// Where backward rules deliver the gradient contributions for their inputs.
pub(crate) struct GradSink<'a, F: Float> {
    nodes: &'a [Node<F>],
    grads: &'a mut Vec<Option<Vec<F>>>,
    pub par: Parallelism,
    tape: &'a Tape<F>,
}

impl<F: Float> GradSink<'_, F> {
    /// Whether input `id` wants a gradient at all (so rules can skip work).
    pub fn wants(&self, id: NodeId) -> bool {
        self.nodes[id].tracked
    }

    /// Returns a scratch buffer to the tape's pool.
    pub fn tape_recycle(&self, buf: Vec<F>) {
        self.tape.recycle(buf);
    }

    /// A scratch buffer from the tape's pool, contents unspecified (write it in full).
    pub fn alloc(&self, len: usize) -> Vec<F> {
        self.tape.alloc(len)
    }

    /// A zero-filled scratch buffer from the tape's pool.
    pub fn alloc_zeroed(&self, len: usize) -> Vec<F> {
        self.tape.alloc_zeroed(len)
    }

    /// Adds `contrib` (with the input's shape) to the gradient of input `id`.
    pub fn add(&mut self, id: NodeId, contrib: Vec<F>) {
        if !self.nodes[id].tracked {
            self.tape.recycle(contrib);
            return;
        }
        debug_assert_eq!(contrib.len(), self.nodes[id].value.numel(), "gradient size for node {id}");
        match &mut self.grads[id] {
            Some(g) => {
                kernels::add_assign(self.par, g, &contrib);
                self.tape.recycle(contrib);
            }
            slot @ None => *slot = Some(contrib),
        }
    }

    /// Adds `f(i)` to element `i` of input `id`'s gradient for every `i`, creating it
    /// zeroed if needed (for sparse rules such as gather and slice).
    pub fn add_with(&mut self, id: NodeId, f: impl FnOnce(&mut [F])) {
        if !self.nodes[id].tracked {
            return;
        }
        let n = self.nodes[id].value.numel();
        if self.grads[id].is_none() {
            self.grads[id] = Some(self.tape.alloc_zeroed(n));
        }
        f(self.grads[id].as_mut().expect("just set"));
    }
}

/// Gradients of one reverse pass, for the tracked leaves it reached.
#[derive(Debug)]
pub struct Gradients<F: Float> {
    grads: Vec<Option<Tensor<F>>>,
}

impl<F: Float> Gradients<F> {
    /// The gradient for `leaf`, or `None` if the output does not depend on it.
    pub fn get(&self, leaf: Var<'_, F>) -> Option<&Tensor<F>> {
        self.grads.get(leaf.id).and_then(|g| g.as_ref())
    }

    /// The gradient for `leaf` (zeros if the output does not depend on it).
    pub fn wrt(&self, leaf: Var<'_, F>) -> Tensor<F> {
        match self.get(leaf) {
            Some(g) => g.clone(),
            None => Tensor::zeros(&leaf.shape()),
        }
    }

    /// Takes the gradient for `leaf` out without copying (zeros if absent).
    pub fn take(&mut self, leaf: Var<'_, F>) -> Tensor<F> {
        match self.grads.get_mut(leaf.id).and_then(|g| g.take()) {
            Some(g) => g,
            None => Tensor::zeros(&leaf.shape()),
        }
    }
}

/// A handle to a value on a [`Tape`]: cheap to copy, valid while the tape is borrowed.
///
/// Arithmetic operators (`+ - * /`, unary `-`) work between handles (with
/// broadcasting) and with `f64` scalars.
pub struct Var<'t, F: Float = f64> {
    pub(crate) tape: &'t Tape<F>,
    pub(crate) id: NodeId,
}

impl<F: Float> Clone for Var<'_, F> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<F: Float> Copy for Var<'_, F> {}

impl<F: Float> fmt::Debug for Var<'_, F> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Var#{}{:?}", self.id, self.shape())
    }
}

impl<'t, F: Float> Var<'t, F> {
    /// The tape this value lives on.
    pub fn tape(&self) -> &'t Tape<F> {
        self.tape
    }

    /// The value (borrowed from the tape).
    pub fn value(&self) -> Ref<'t, Tensor<F>> {
        Ref::map(self.tape.nodes.borrow(), |n| &n[self.id].value)
    }

    /// A copy of the value.
    pub fn to_tensor(&self) -> Tensor<F> {
        self.value().clone()
    }

    /// The shape.
    pub fn shape(&self) -> Vec<usize> {
        self.value().shape().to_vec()
    }

    /// Number of elements.
    pub fn numel(&self) -> usize {
        self.value().numel()
    }

    /// The value of a one-element tensor.
    pub fn item(&self) -> F {
        self.value().item()
    }

    /// Whether gradients flow through this value.
    pub fn is_tracked(&self) -> bool {
        self.tape.is_tracked(self.id)
    }

    /// The same value as a constant: no gradient flows back through it.
    pub fn detach(self) -> Var<'t, F> {
        let v = self.to_tensor();
        self.tape.constant(v)
    }

    /// Alias of [`Var::detach`] in the vocabulary of the estimators.
    pub fn stop_gradient(self) -> Var<'t, F> {
        self.detach()
    }
}
