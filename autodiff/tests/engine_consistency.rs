//! Properties of the engine rather than of single VJPs:
//!
//! * every op, forward value and gradient, is bitwise identical on a serial tape and
//!   on a rayon tape (with 2 and 5 threads) at sizes above the parallel threshold, in
//!   f32 and f64: results must not depend on the thread count;
//! * the f32 fast transcendentals agree with f64 to 1e-5 relative through the tape;
//! * a non-recording tape computes exactly the values of a recording one;
//! * `Tape::reset` recycles buffers and the next computation is still exact, and no
//!   op lets the stale contents of a recycled buffer into its results.

use crate::common::*;
use autodiff::{Float, Parallelism, Tape, Tensor, Var};
use rand::rngs::StdRng;
use rand::Rng;

/// ~300k elements: well above the 32k-element threshold of the parallel kernels,
/// so every element-wise kernel splits into ~37 chunks.
const BIG: [usize; 2] = [600, 500];
/// A 3-D tensor of 300k elements for the axis ops.
const CUBE: [usize; 3] = [60, 100, 50];

type OpFn<F> = Box<dyn for<'t> Fn(&'t Tape<F>, &[Var<'t, F>]) -> Var<'t, F> + Send + Sync>;

/// One op on some of the shared input tensors (by index, to keep memory small).
struct Case<F: Float> {
    name: String,
    inputs: Vec<usize>,
    f: OpFn<F>,
}

/// The shared inputs and the cases that use them.
struct Cases<F: Float> {
    tensors: Vec<Tensor<F>>,
    cases: Vec<Case<F>>,
}

impl<F: Float> Cases<F> {
    /// Adds an input tensor, returning its index.
    fn input(&mut self, x: Tensor<f64>) -> usize {
        self.tensors.push(x.cast::<F>());
        self.tensors.len() - 1
    }

    fn add<Func>(&mut self, name: impl Into<String>, inputs: &[usize], f: Func)
    where
        Func: for<'t> Fn(&'t Tape<F>, &[Var<'t, F>]) -> Var<'t, F> + Send + Sync + 'static,
    {
        self.cases.push(Case { name: name.into(), inputs: inputs.to_vec(), f: Box::new(f) });
    }

    /// The element-wise ops and full reductions on `x` (standard normal) and `pos`
    /// (positive): the same cases at every size.
    fn element_wise_ops(&mut self, x: usize, pos: usize) {
        self.add("neg", &[x], |_, v| v[0].neg());
        self.add("exp", &[x], |_, v| v[0].exp());
        self.add("ln", &[pos], |_, v| v[0].ln());
        self.add("ln_1p", &[pos], |_, v| v[0].ln_1p());
        self.add("tanh", &[x], |_, v| v[0].tanh());
        self.add("relu", &[x], |_, v| v[0].relu());
        self.add("softplus", &[x], |_, v| v[0].softplus());
        self.add("sigmoid", &[x], |_, v| v[0].sigmoid());
        self.add("sin", &[x], |_, v| v[0].sin());
        self.add("cos", &[x], |_, v| v[0].cos());
        self.add("abs", &[x], |_, v| v[0].abs());
        self.add("sqrt", &[pos], |_, v| v[0].sqrt());
        self.add("square", &[x], |_, v| v[0].square());
        self.add("powf", &[pos], |_, v| v[0].powf(1.7));
        self.add("add_scalar", &[x], |_, v| v[0].add_scalar(0.3));
        self.add("mul_scalar", &[x], |_, v| v[0].mul_scalar(-1.7));
        self.add("clamp", &[x], |_, v| v[0].clamp(-0.5, 0.5));
        self.add("sum", &[x], |_, v| v[0].sum());
        self.add("mean", &[x], |_, v| v[0].mean());
        self.add("used twice", &[x], |_, v| v[0] * v[0] + v[0].sin());
        self.add("detach", &[x], |_, v| v[0].detach() * v[0]);
        self.add("scalar operators", &[x], |_, v| (2.0 - v[0]) / 3.0 + 1.5 * v[0]);
    }

    /// The broadcasting binary ops for each pattern `(label, lhs shape, rhs shape)`,
    /// on inputs with random signs and magnitudes in `[0.3, 2)` drawn from `r`.
    fn binary_ops<const N: usize>(&mut self, r: &mut StdRng, patterns: [(&str, Vec<usize>, Vec<usize>); N]) {
        for (label, sa, sb) in patterns {
            let a = self.input(signed(r, &sa, 0.3, 2.0));
            let b = self.input(signed(r, &sb, 0.3, 2.0));
            let ab = [a, b];
            self.add(format!("add {label}"), &ab, |_, v| v[0] + v[1]);
            self.add(format!("sub {label}"), &ab, |_, v| v[0] - v[1]);
            self.add(format!("mul {label}"), &ab, |_, v| v[0] * v[1]);
            self.add(format!("div {label}"), &ab, |_, v| v[0] / v[1]);
            self.add(format!("atan2 {label}"), &ab, |_, v| v[0].atan2(v[1]));
            self.add(format!("minimum {label}"), &ab, |_, v| v[0].minimum(v[1]));
            self.add(format!("maximum {label}"), &ab, |_, v| v[0].maximum(v[1]));
        }
    }

    /// The reductions and (log-)softmax along `axis` of `x`, and those that take
    /// -inf along `axis` of `x_inf` (which has -inf entries and all -inf lanes).
    fn lane_ops(&mut self, axis: usize, x: usize, x_inf: usize) {
        for keepdim in [false, true] {
            self.add(format!("sum_axis {axis} {keepdim}"), &[x], move |_, v| v[0].sum_axis(axis, keepdim));
            self.add(format!("logsumexp {axis} {keepdim}"), &[x], move |_, v| v[0].logsumexp(axis, keepdim));
        }
        self.add(format!("mean_axis {axis}"), &[x], move |_, v| v[0].mean_axis(axis, false));
        self.add(format!("softmax {axis}"), &[x], move |_, v| v[0].softmax(axis));
        self.add(format!("log_softmax {axis}"), &[x], move |_, v| v[0].log_softmax(axis));
        self.add(format!("logsumexp with -inf {axis}"), &[x_inf], move |_, v| v[0].logsumexp(axis, false));
        self.add(format!("softmax with -inf {axis}"), &[x_inf], move |_, v| v[0].softmax(axis));
        self.add(format!("log_softmax with -inf {axis}"), &[x_inf], move |_, v| v[0].log_softmax(axis));
    }
}

/// `t` with every 7th entry (from the 4th) set to -inf.
fn with_scattered_neg_inf(mut t: Tensor<f64>) -> Tensor<f64> {
    for (i, v) in t.data_mut().iter_mut().enumerate() {
        if i % 7 == 3 {
            *v = f64::NEG_INFINITY;
        }
    }
    t
}

/// One case per op (and per broadcast pattern / axis), all above the parallel threshold.
fn big_cases<F: Float>() -> Cases<F> {
    let mut r = rng(50);
    let mut cs = Cases { tensors: Vec::new(), cases: Vec::new() };
    let n = cs.input(normal(&mut r, &BIG));
    let pos = cs.input(uniform(&mut r, &BIG, 0.1, 4.0));
    cs.element_wise_ops(n, pos);
    cs.add("reshape", &[n], |_, v| v[0].reshape(&[500, 600]));
    cs.add("transpose", &[n], |_, v| v[0].t());

    let patterns: [(&str, Vec<usize>, Vec<usize>); 5] = [
        ("same", BIG.to_vec(), BIG.to_vec()),
        ("row", BIG.to_vec(), vec![500]),
        ("column lhs", vec![600, 1], BIG.to_vec()),
        ("scalar", BIG.to_vec(), vec![]),
        ("3-D", vec![6, 100, 500], vec![100, 1]),
    ];
    cs.binary_ops(&mut r, patterns);

    // Linear algebra: long m (weight gradients reduced over 4096-row blocks), a 3-D
    // lhs, and a long inner dimension (GEMM depth blocking, multi-threaded rows).
    let x = cs.input(normal(&mut r, &[20_000, 16]));
    let w = cs.input(normal(&mut r, &[16, 16]));
    let b = cs.input(normal(&mut r, &[16]));
    cs.add("matmul long m", &[x, w], |_, v| v[0].matmul(v[1]));
    cs.add("affine long m", &[x, w, b], |_, v| v[0].affine(v[1], v[2]));
    let x3 = cs.input(normal(&mut r, &[100, 200, 16]));
    cs.add("matmul 3-D", &[x3, w], |_, v| v[0].matmul(v[1]));
    let wide = cs.input(normal(&mut r, &[500, 64]));
    cs.add("matmul long k", &[n, wide], |_, v| v[0].matmul(v[1]));

    // Axis ops on a cube, every axis; in a second input, scattered -inf entries and
    // one lane along each axis entirely -inf.
    let cube = normal(&mut r, &CUBE).map(|v| 2.0 * v);
    let mut cube_inf = with_scattered_neg_inf(cube.clone());
    for k in 0..CUBE[0] {
        cube_inf.set(&[k, 4, 9], f64::NEG_INFINITY);
    }
    for k in 0..CUBE[1] {
        cube_inf.set(&[5, k, 9], f64::NEG_INFINITY);
    }
    for k in 0..CUBE[2] {
        cube_inf.set(&[5, 4, k], f64::NEG_INFINITY);
    }
    let c = cs.input(cube);
    let ci = cs.input(cube_inf);
    for axis in 0..3 {
        cs.lane_ops(axis, c, ci);
        cs.add(format!("slice {axis}"), &[c], move |_, v| v[0].slice(axis, 3, 40));
        let len = CUBE[axis];
        let gidx: Vec<usize> = (0..len + 5).map(|_| r.random_range(0..len)).collect();
        cs.add(format!("gather {axis}"), &[c], move |_, v| v[0].gather(axis, &gidx));
        let sidx: Vec<usize> = (0..len).map(|_| r.random_range(0..len / 2)).collect();
        cs.add(format!("scatter_add {axis}"), &[c], move |_, v| v[0].scatter_add(axis, &sidx, len / 2));
        let parts: Vec<usize> = [7, 20, 13]
            .iter()
            .map(|&l| {
                let mut s = CUBE.to_vec();
                s[axis] = l * CUBE[axis] / 40;
                cs.input(normal(&mut r, &s))
            })
            .collect();
        cs.add(format!("concat {axis}"), &parts, move |tape, v| tape.concat(v, axis));
    }
    // Particle-shaped log-weights: many short lanes.
    let lw = cs.input(normal(&mut r, &[4800, 64]));
    cs.add("logsumexp particles", &[lw], |_, v| v[0].logsumexp(1, true));
    cs.add("gather particles", &[lw], |_, v| {
        let idx: Vec<usize> = (0..4800).map(|i| (i * 37) % 4800 / 3).collect();
        v[0].gather(0, &idx)
    });

    let row = cs.input(normal(&mut r, &[500]));
    cs.add("broadcast_to row", &[row], |_, v| v[0].broadcast_to(&BIG));
    let col = cs.input(normal(&mut r, &[600, 1]));
    cs.add("broadcast_to column", &[col], |_, v| v[0].broadcast_to(&BIG));
    let mask: Vec<bool> = (0..300_000).map(|_| r.random::<bool>()).collect();
    let other = cs.input(normal(&mut r, &BIG));
    cs.add("select", &[n, other], move |tape, v| tape.select(&mask, v[0], v[1]));
    cs
}

/// The output value and the VJP of every input on the tape `tape` (see [`run`]).
fn run_on<F: Float>(
    tape: &Tape<F>,
    inputs: &[&Tensor<F>],
    f: &OpFn<F>,
    cot: Option<&Tensor<F>>,
) -> (Vec<Vec<u64>>, Tensor<F>) {
    let vars: Vec<Var<'_, F>> = inputs.iter().map(|&x| tape.param(x.clone())).collect();
    let y = f(tape, &vars);
    let cot = match cot {
        Some(c) => c.clone(),
        None => uniform(&mut rng(51), &y.shape(), -1.0, 1.0).cast::<F>(),
    };
    let mut out = vec![bits(&y.value())];
    let mut g = tape.vjp(y, cot.clone());
    for &v in &vars {
        out.push(bits(&g.take(v)));
    }
    (out, cot)
}

/// The output value and the VJP (for the cotangent `cot`, or a fixed random one if
/// `None`) of every input, as bits, on a fresh tape; and the cotangent used.
fn run<F: Float>(
    inputs: &[&Tensor<F>],
    f: &OpFn<F>,
    par: Parallelism,
    cot: Option<&Tensor<F>>,
) -> (Vec<Vec<u64>>, Tensor<F>) {
    run_on(&Tape::<F>::new().with_parallelism(par), inputs, f, cot)
}

fn bits<F: Float>(t: &Tensor<F>) -> Vec<u64> {
    t.data().iter().map(|x| x.to_f64().to_bits()).collect()
}

#[track_caller]
fn assert_same_bits(name: &str, what: &str, a: &[Vec<u64>], b: &[Vec<u64>]) {
    for (k, (x, y)) in a.iter().zip(b).enumerate() {
        let part = if k == 0 { "value".to_string() } else { format!("gradient of input {}", k - 1) };
        assert_eq!(x.len(), y.len(), "{name} {part}: sizes differ ({what})");
        if let Some(i) = (0..x.len()).find(|&i| x[i] != y[i]) {
            panic!("{name} {part} [{i}]: reference {} vs {what} {}", f64::from_bits(x[i]), f64::from_bits(y[i]));
        }
    }
}

fn serial_and_parallel_agree<F: Float>() {
    let pools: Vec<(String, rayon::ThreadPool)> = [2, 5]
        .iter()
        .map(|&t| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().expect("thread pool");
            (format!("rayon with {t} threads"), pool)
        })
        .collect();
    let cs = big_cases::<F>();
    assert!(cs.cases.len() > 90);
    for c in &cs.cases {
        let name = format!("{} ({})", c.name, F::NAME);
        let inputs: Vec<&Tensor<F>> = c.inputs.iter().map(|&i| &cs.tensors[i]).collect();
        let (serial, cot) = run(&inputs, &c.f, Parallelism::Serial, None);
        assert!(
            serial[1..].iter().any(|g| g.iter().any(|&b| b != 0)),
            "{name}: the gradient must not be trivially zero"
        );
        for (what, pool) in &pools {
            let (par, _) = pool.install(|| run(&inputs, &c.f, Parallelism::Rayon, Some(&cot)));
            assert_same_bits(&name, what, &serial, &par);
        }
    }
}

/// Every op at small sizes (at most 256 elements per buffer), including degenerate
/// shapes: empty axes, empty index lists, an empty inner dimension.
fn small_cases() -> Cases<f64> {
    let mut r = rng(70);
    let mut cs = Cases { tensors: Vec::new(), cases: Vec::new() };
    let x = cs.input(normal(&mut r, &[3, 4, 5]));
    let pos = cs.input(uniform(&mut r, &[3, 4, 5], 0.1, 4.0));
    cs.element_wise_ops(x, pos);
    cs.add("powf(0)", &[pos], |_, v| v[0].powf(0.0));
    cs.add("reshape", &[x], |_, v| v[0].reshape(&[12, 5]));
    cs.add("transpose", &[x], |_, v| v[0].reshape(&[12, 5]).t());
    let patterns: [(&str, Vec<usize>, Vec<usize>); 6] = [
        ("same", vec![3, 4], vec![3, 4]),
        ("row", vec![3, 4], vec![4]),
        ("column lhs", vec![3, 1], vec![3, 4]),
        ("scalar", vec![3, 4], vec![]),
        ("3-D", vec![2, 1, 4], vec![3, 1]),
        ("empty", vec![0, 4], vec![4]),
    ];
    cs.binary_ops(&mut r, patterns);
    let m = cs.input(normal(&mut r, &[5, 3]));
    let m3 = cs.input(normal(&mut r, &[2, 4, 3]));
    let w = cs.input(normal(&mut r, &[3, 4]));
    let b = cs.input(normal(&mut r, &[4]));
    cs.add("matmul", &[m, w], |_, v| v[0].matmul(v[1]));
    cs.add("matmul 3-D", &[m3, w], |_, v| v[0].matmul(v[1]));
    cs.add("affine", &[m, w, b], |_, v| v[0].affine(v[1], v[2]));
    cs.add("affine 3-D", &[m3, w, b], |_, v| v[0].affine(v[1], v[2]));
    let e0 = cs.input(Tensor::zeros(&[5, 0]));
    let w0 = cs.input(Tensor::zeros(&[0, 4]));
    cs.add("matmul k = 0", &[e0, w0], |_, v| v[0].matmul(v[1]));
    cs.add("affine k = 0", &[e0, w0, b], |_, v| v[0].affine(v[1], v[2]));
    let wn0 = cs.input(Tensor::zeros(&[3, 0]));
    cs.add("matmul n = 0", &[m, wn0], |_, v| v[0].matmul(v[1]));

    let mut xi = with_scattered_neg_inf(normal(&mut r, &[3, 4, 5]));
    for k in 0..4 {
        xi.set(&[1, k, 2], f64::NEG_INFINITY);
    }
    let xi = cs.input(xi);
    let empty = cs.input(Tensor::zeros(&[3, 0, 2]));
    for axis in 0..3 {
        cs.lane_ops(axis, x, xi);
        cs.add(format!("sum_axis of empty {axis}"), &[empty], move |_, v| v[0].sum_axis(axis, false));
        cs.add(format!("logsumexp of empty {axis}"), &[empty], move |_, v| v[0].logsumexp(axis, true));
        cs.add(format!("slice {axis}"), &[x], move |_, v| v[0].slice(axis, 1, 2));
        cs.add(format!("empty slice {axis}"), &[x], move |_, v| v[0].slice(axis, 1, 0));
        let len = [3, 4, 5][axis];
        cs.add(format!("gather {axis}"), &[x], move |_, v| v[0].gather(axis, &[len - 1, 0, len - 1, 1]));
        cs.add(format!("gather nothing {axis}"), &[x], move |_, v| v[0].gather(axis, &[]));
        let sidx: Vec<usize> = (0..len).map(|j| (j * 2) % (len + 1)).collect();
        cs.add(format!("scatter_add {axis}"), &[x], move |_, v| v[0].scatter_add(axis, &sidx, len + 1));
        let parts: Vec<usize> = [1, 0, 2]
            .iter()
            .map(|&l| {
                let mut s = vec![3, 4, 5];
                s[axis] = l;
                cs.input(normal(&mut r, &s))
            })
            .collect();
        cs.add(format!("concat {axis}"), &parts, move |tape, v| tape.concat(v, axis));
    }
    let row = cs.input(normal(&mut r, &[5]));
    cs.add("broadcast_to row", &[row], |_, v| v[0].broadcast_to(&[3, 4, 5]));
    let col = cs.input(normal(&mut r, &[4, 1]));
    cs.add("broadcast_to column", &[col], |_, v| v[0].broadcast_to(&[3, 4, 5]));
    let y = cs.input(normal(&mut r, &[3, 4, 5]));
    let mask: Vec<bool> = (0..60).map(|_| r.random::<bool>()).collect();
    cs.add("select", &[x, y], move |tape, v| tape.select(&mask, v[0], v[1]));
    cs
}

#[test]
fn stale_pool_buffers_never_leak_into_results() {
    // Output and scratch buffers come from the tape's pool without being cleared:
    // every op must write its output (and every backward rule its contribution) in
    // full. Fill the pool with NaN buffers of every size an op here can ask for
    // (256 at most), so that anything left unwritten shows up as NaN, and compare
    // with a fresh tape bit for bit.
    let cs = small_cases();
    for c in &cs.cases {
        let inputs: Vec<&Tensor<f64>> = c.inputs.iter().map(|&i| &cs.tensors[i]).collect();
        let (fresh, cot) = run(&inputs, &c.f, Parallelism::Serial, None);
        let mut tape = Tape::<f64>::new().with_parallelism(Parallelism::Serial);
        for len in 0..=256 {
            for _ in 0..6 {
                tape.constant(Tensor::full(&[len], f64::NAN));
            }
        }
        tape.reset();
        let (reused, _) = run_on(&tape, &inputs, &c.f, Some(&cot));
        assert_same_bits(&c.name, "a tape with stale NaN buffers", &fresh, &reused);
    }
}

#[test]
fn every_op_is_bitwise_identical_serial_and_parallel_f32() {
    serial_and_parallel_agree::<f32>();
}

#[test]
fn every_op_is_bitwise_identical_serial_and_parallel_f64() {
    serial_and_parallel_agree::<f64>();
}

/// Evaluates `op` on the f32 and the f64 tape for the same (f32-representable)
/// inputs and returns the worst relative error of the f32 values.
fn f32_vs_f64(
    op: for<'t> fn(Var<'t, f32>) -> Var<'t, f32>,
    op64: for<'t> fn(Var<'t, f64>) -> Var<'t, f64>,
    x: &[f32],
    floor: f64,
) -> (f64, f32) {
    let t32 = Tape::<f32>::new();
    let t64 = Tape::<f64>::new();
    let y32 = op(t32.constant(Tensor::from_vec(x.to_vec()))).to_tensor();
    let x64: Vec<f64> = x.iter().map(|&v| v as f64).collect();
    let y64 = op64(t64.constant(Tensor::from_vec(x64))).to_tensor();
    let mut worst = (0.0, 0.0f32);
    for ((&a, &b), &xi) in y32.data().iter().zip(y64.data()).zip(x) {
        let rel = (a as f64 - b).abs() / b.abs().max(floor);
        if rel > worst.0 {
            worst = (rel, xi);
        }
    }
    worst
}

fn linspace(lo: f64, hi: f64, n: usize) -> Vec<f32> {
    (0..=n).map(|i| (lo + (hi - lo) * i as f64 / n as f64) as f32).collect()
}

fn logspace(lo: f64, hi: f64, n: usize) -> Vec<f32> {
    let (a, b) = (lo.ln(), hi.ln());
    (0..=n).map(|i| (a + (b - a) * i as f64 / n as f64).exp() as f32).collect()
}

#[test]
fn f32_fast_transcendentals_agree_with_f64() {
    // The polynomial kernels are accurate to ~3e-7 relative (exp, ln, sigmoid,
    // softplus) and tanh to ~5e-7 relative; storing the result in f32 adds 6e-8.
    // 1e-5 is a loose bound that still catches any loss of relative accuracy, such
    // as the cancellation in a naive ln(1 + e^x) (which reaches 6e-4).
    const TOL: f64 = 1e-5;
    // Only the exact-zero results (ln 1) need a floor; relative everywhere else.
    const FLOOR: f64 = 1e-300;
    let mut near_one = linspace(0.5, 2.0, 20_000);
    near_one.extend(logspace(1e-37, 1e38, 20_000));
    let mut small = linspace(-10.0, 10.0, 20_000);
    small.extend(logspace(1e-7, 0.1, 5_000));
    small.extend(logspace(1e-7, 0.1, 5_000).iter().map(|v| -v));
    type Pair =
        (&'static str, for<'t> fn(Var<'t, f32>) -> Var<'t, f32>, for<'t> fn(Var<'t, f64>) -> Var<'t, f64>, Vec<f32>);
    let cases: Vec<Pair> = vec![
        ("exp", |x| x.exp(), |x| x.exp(), linspace(-87.0, 88.3, 50_000)),
        ("ln", |x| x.ln(), |x| x.ln(), near_one),
        ("tanh", |x| x.tanh(), |x| x.tanh(), small),
        ("softplus", |x| x.softplus(), |x| x.softplus(), linspace(-80.0, 80.0, 50_000)),
        ("sigmoid", |x| x.sigmoid(), |x| x.sigmoid(), linspace(-80.0, 80.0, 50_000)),
    ];
    for (name, op32, op64, xs) in cases {
        let (worst, at) = f32_vs_f64(op32, op64, &xs, FLOOR);
        assert!(worst < TOL, "{name}: f32 relative error {worst:e} at x = {at}");
    }
}

#[test]
fn f32_fused_log_sum_exp_family_agrees_with_f64() {
    // Lane sums are accumulated in f64 in both cases; what differs is the f32 exp and
    // the f32 rounding of inputs and outputs. Log-domain values are compared with a
    // floor of 1 (their absolute error is what matters, ~1e-6 for |x| ~ 10).
    let x = normal(&mut rng(52), &[50, 64]).map(|v| 3.0 * v);
    let x32 = x.cast::<f32>();
    let x64 = x32.cast::<f64>();
    let t32 = Tape::<f32>::new();
    let t64 = Tape::<f64>::new();
    for axis in 0..2 {
        let a = t32.constant(x32.clone());
        let b = t64.constant(x64.clone());
        let pairs = [
            ("logsumexp", a.logsumexp(axis, false), b.logsumexp(axis, false), 1.0),
            ("log_softmax", a.log_softmax(axis), b.log_softmax(axis), 1.0),
            // Probabilities: relative to themselves, down to 1e-30.
            ("softmax", a.softmax(axis), b.softmax(axis), 1e-30),
        ];
        for (name, y32, y64, floor) in pairs {
            let y32 = y32.to_tensor().cast::<f64>();
            assert_close(&format!("{name} axis {axis} f32 vs f64"), y32.data(), y64.to_tensor().data(), 1e-5, floor);
        }
    }
}

/// Buffer addresses of a computation's nodes: op outputs, and leaves.
struct Buffers {
    ops: Vec<usize>,
    leaves: Vec<usize>,
}

fn addresses<F: Float>(vars: &[Var<'_, F>]) -> Vec<usize> {
    vars.iter().map(|v| v.value().data().as_ptr() as usize).collect()
}

/// A small model touching most ops: the value of every op it records, and the
/// addresses of the buffers of all its nodes (every op output is named here).
fn model<F: Float>(tape: &Tape<F>, inputs: &[Tensor<f64>; 3]) -> (Vec<Tensor<F>>, Buffers) {
    let x = tape.param(inputs[0].cast::<F>());
    let w = tape.param(inputs[1].cast::<F>());
    let b = tape.param(inputs[2].cast::<F>());
    let half_c = tape.scalar(0.5);
    let one_c = tape.scalar(1.0);
    let a = x.affine(w, b);
    let h = a.tanh();
    let lw = h.log_softmax(1);
    let lse = h.logsumexp(1, true);
    let anc = lw.gather(0, &[3, 3, 1, 0, 2, 5, 4, 4]);
    let sp = anc.softplus();
    let wide = lse.broadcast_to(&[8, 4]);
    let sg = wide.sigmoid();
    let mix = tape.concat(&[sp, sg], 1);
    let part = mix.slice(1, 2, 5);
    let half = part * half_c;
    let col = h.slice(1, 0, 1);
    let diff = half - col;
    let other = h.slice(1, 1, 1);
    let mag = other.abs();
    let den = mag + one_c;
    let y = diff.atan2(den);
    let sq = y.square();
    let sq_rows = sq.sum_axis(0, false);
    let sq_mean = sq_rows.mul_scalar(1.0 / 8.0);
    let msq = sq_mean.sum();
    let yt = y.t();
    let gram = yt.matmul(y);
    let gsum = gram.sum_axis(0, false);
    let gtot = gsum.sum();
    let loss = msq + gtot;
    let ops = [
        a, h, lw, lse, anc, sp, wide, sg, mix, part, half, col, diff, other, mag, den, y, sq, sq_rows, sq_mean, msq,
        yt, gram, gsum, gtot, loss,
    ];
    let values = ops.iter().map(|v| v.to_tensor()).collect();
    let buffers = Buffers { ops: addresses(&ops), leaves: addresses(&[x, w, b, half_c, one_c]) };
    (values, buffers)
}

/// The loss of a small model and its gradient with respect to its three inputs.
fn model_grads<F: Float>(tape: &Tape<F>, inputs: &[Tensor<f64>; 3]) -> Vec<Tensor<F>> {
    let x = tape.param(inputs[0].cast::<F>());
    let w = tape.param(inputs[1].cast::<F>());
    let b = tape.param(inputs[2].cast::<F>());
    let h = x.affine(w, b).tanh();
    let lw = h.log_softmax(1).gather(0, &[3, 3, 1, 0, 2, 5, 4, 4]);
    let loss = (lw.softplus() * h).sum() + h.logsumexp(0, false).square().sum();
    let g = tape.backward(loss);
    vec![loss.to_tensor(), g.wrt(x), g.wrt(w), g.wrt(b)]
}

fn model_inputs(seed: u64) -> [Tensor<f64>; 3] {
    let mut r = rng(seed);
    [normal(&mut r, &[8, 3]), normal(&mut r, &[3, 4]), normal(&mut r, &[4])]
}

#[test]
fn a_non_recording_tape_computes_the_same_values() {
    let inputs = model_inputs(53);
    let rec = Tape::<f64>::new();
    let fwd = Tape::<f64>::no_record();
    assert!(rec.is_recording() && !fwd.is_recording());
    let (a, _) = model(&rec, &inputs);
    let (c, _) = model(&fwd, &inputs);
    assert_eq!(a, c);
    assert!(a.iter().all(|t| t.all_finite()));
    let rec32 = Tape::<f32>::new();
    let fwd32 = Tape::<f32>::no_record();
    assert_eq!(model(&rec32, &inputs).0, model(&fwd32, &inputs).0);
    // Nothing on a non-recording tape is tracked, so nothing has a gradient.
    let p = fwd.param(inputs[0].clone());
    let out = p.exp().sum();
    assert!(!p.is_tracked() && !out.is_tracked());
    assert!(fwd.backward(out).get(p).is_none());
}

#[test]
fn reset_recycles_buffers_and_stays_correct() {
    let steps: Vec<[Tensor<f64>; 3]> = (0..3).map(|i| model_inputs(60 + i)).collect();
    let fresh_values = |i: usize| model(&Tape::<f64>::new(), &steps[i]).0;
    let fresh_grads = |i: usize| model_grads(&Tape::<f64>::new(), &steps[i]);

    // A forward-only tape reused across steps: after a reset, every op output of the
    // same computation lands in a recycled buffer of an earlier step (the tape holds
    // no other buffers, since nothing runs backward).
    let mut tape = Tape::<f64>::no_record();
    let mut previous: Vec<usize> = Vec::new();
    for (i, inputs) in steps.iter().enumerate() {
        let (values, buffers) = model(&tape, inputs);
        assert_eq!(values, fresh_values(i), "step {i}: values after reset");
        if i > 0 {
            let new: Vec<usize> = (0..buffers.ops.len()).filter(|&k| !previous.contains(&buffers.ops[k])).collect();
            assert!(new.is_empty(), "step {i}: op outputs {new:?} of {} were newly allocated", buffers.ops.len());
        }
        // Buffers left over in the pool from earlier steps stay candidates.
        previous.extend(buffers.ops);
        previous.extend(buffers.leaves);
        tape.reset();
        assert!(tape.is_empty());
    }

    // A recording tape reused across steps (including backward passes, whose scratch
    // buffers also go back to the pool): values and gradients match a fresh tape.
    let mut tape = Tape::<f64>::new();
    for i in [0, 1, 2, 1, 0] {
        let (values, _) = model(&tape, &steps[i]);
        assert_eq!(values, fresh_values(i), "step {i}: values after reset");
        tape.reset();
        assert_eq!(model_grads(&tape, &steps[i]), fresh_grads(i), "step {i}: gradients after reset");
        tape.reset();
    }
}
