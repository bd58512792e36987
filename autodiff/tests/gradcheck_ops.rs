//! Element-wise and linear-algebra ops: every VJP against central differences in f64,
//! and every forward value against a direct `std` computation.
//!
//! Inputs are seeded random tensors drawn away from kinks, poles and branch cuts, so
//! that the ops are smooth within a finite-difference step; the subgradient
//! conventions at kinks are asserted separately in `gradient_semantics.rs`.

use crate::common::*;
use autodiff::{broadcast_shapes, Tape, Tensor, Var};

/// Shape of the inputs of the unary checks (60 elements: checked per coordinate).
const SHAPE: [usize; 3] = [3, 4, 5];

type UnaryFn = for<'t> fn(Var<'t, f64>) -> Var<'t, f64>;

/// One unary op: name, the op, its scalar reference, and the input domain `(lo, hi)`
/// together with kinks to keep away from.
struct UnaryCase {
    name: &'static str,
    op: UnaryFn,
    reference: fn(f64) -> f64,
    lo: f64,
    hi: f64,
    kinks: &'static [f64],
}

/// A [`UnaryCase`] as a tuple of its fields, in order: the rows of [`unary_cases`].
type UnaryRow = (&'static str, UnaryFn, fn(f64) -> f64, f64, f64, &'static [f64]);

fn unary_cases() -> Vec<UnaryCase> {
    // The clamp reference is written with `max`/`min` on purpose, independent of the `clamp` under test.
    #[allow(clippy::manual_clamp)]
    let rows: &[UnaryRow] = &[
        ("neg", |x| x.neg(), |x| -x, -3.0, 3.0, &[]),
        ("neg operator", |x| -x, |x| -x, -3.0, 3.0, &[]),
        ("exp", |x| x.exp(), f64::exp, -3.0, 3.0, &[]),
        ("ln", |x| x.ln(), f64::ln, 0.2, 4.0, &[]),
        ("ln_1p", |x| x.ln_1p(), f64::ln_1p, -0.8, 3.0, &[]),
        ("tanh", |x| x.tanh(), f64::tanh, -3.0, 3.0, &[]),
        ("relu", |x| x.relu(), |x| x.max(0.0), -3.0, 3.0, &[0.0]),
        ("softplus", |x| x.softplus(), |x| (1.0 + x.exp()).ln(), -6.0, 6.0, &[]),
        ("sigmoid", |x| x.sigmoid(), |x| 1.0 / (1.0 + (-x).exp()), -6.0, 6.0, &[]),
        ("sin", |x| x.sin(), f64::sin, -4.0, 4.0, &[]),
        ("cos", |x| x.cos(), f64::cos, -4.0, 4.0, &[]),
        ("abs", |x| x.abs(), f64::abs, -3.0, 3.0, &[0.0]),
        ("sqrt", |x| x.sqrt(), f64::sqrt, 0.1, 4.0, &[]),
        ("square", |x| x.square(), |x| x * x, -3.0, 3.0, &[]),
        ("powf(2.5)", |x| x.powf(2.5), |x| x.powf(2.5), 0.1, 3.0, &[]),
        ("powf(-1.5)", |x| x.powf(-1.5), |x| x.powf(-1.5), 0.2, 3.0, &[]),
        ("powf(3) of negatives", |x| x.powf(3.0), |x| x * x * x, -2.0, 2.0, &[]),
        ("powf(1)", |x| x.powf(1.0), |x| x, -2.0, 2.0, &[]),
        ("powf(0)", |x| x.powf(0.0), |_| 1.0, 0.1, 2.0, &[]),
        ("add_scalar", |x| x.add_scalar(0.7), |x| x + 0.7, -3.0, 3.0, &[]),
        ("mul_scalar", |x| x.mul_scalar(-1.3), |x| -1.3 * x, -3.0, 3.0, &[]),
        ("clamp", |x| x.clamp(-0.5, 0.8), |x| x.max(-0.5).min(0.8), -2.0, 2.0, &[-0.5, 0.8]),
        ("mean", |x| x.mean(), |x| x, -3.0, 3.0, &[]),
    ];
    rows.iter().map(|&(name, op, reference, lo, hi, kinks)| UnaryCase { name, op, reference, lo, hi, kinks }).collect()
}

#[test]
fn unary_ops_match_std_and_finite_differences() {
    let mut r = rng(1);
    for case in unary_cases() {
        let x = away_from(&mut r, &SHAPE, case.lo, case.hi, case.kinks, KINK_GAP);
        // Forward: f64 uses std's correctly rounded functions, so the values agree
        // to a few ulp (softplus/sigmoid are computed in a stabler form).
        if case.name != "mean" {
            let tape = Tape::<f64>::new();
            let y = (case.op)(tape.constant(x.clone())).to_tensor();
            assert_eq!(y.shape(), &SHAPE, "{}", case.name);
            let expected: Vec<f64> = x.data().iter().map(|&v| (case.reference)(v)).collect();
            assert_close(case.name, y.data(), &expected, 1e-14, 1e-300);
        }
        check(case.name, |_, v| (case.op)(v[0]), &[x]);
    }
}

#[test]
fn mean_is_the_average() {
    let x = normal(&mut rng(2), &SHAPE);
    let tape = Tape::<f64>::new();
    let m = tape.param(x.clone());
    let y = m.mean();
    let expected = x.data().iter().sum::<f64>() / 60.0;
    assert!((y.item() - expected).abs() < 1e-15);
    let g = tape.backward(y);
    assert!(g.wrt(m).data().iter().all(|&v| v == 1.0 / 60.0));
}

/// Broadcast pairs of shapes: same shape, scalar either side, row, column and 3-D.
const BROADCAST_CASES: &[(&str, &[usize], &[usize])] = &[
    ("same shape", &[3, 4], &[3, 4]),
    ("scalar rhs", &[3, 4], &[]),
    ("scalar lhs", &[], &[3, 4]),
    ("one-element rhs", &[3, 4], &[1]),
    ("row rhs", &[3, 4], &[4]),
    ("row lhs", &[4], &[3, 4]),
    ("column rhs", &[3, 4], &[3, 1]),
    ("column lhs", &[3, 1], &[3, 4]),
    ("column x row", &[3, 1], &[1, 4]),
    ("3-D mixed", &[2, 1, 4], &[3, 1]),
    ("3-D mixed reversed", &[3, 1], &[2, 1, 4]),
    ("3-D vs row", &[2, 3, 4], &[4]),
    ("3-D vs middle", &[2, 3, 4], &[3, 1]),
];

/// The element of `t` read at output multi-index `out_idx` under numpy broadcasting.
fn broadcast_read(t: &Tensor<f64>, out_idx: &[usize]) -> f64 {
    let s = t.shape();
    let off = out_idx.len() - s.len();
    let idx: Vec<usize> = s.iter().enumerate().map(|(d, &n)| if n == 1 { 0 } else { out_idx[off + d] }).collect();
    t.at(&idx)
}

/// Reference broadcast binary op, computed index by index.
fn reference_binary(a: &Tensor<f64>, b: &Tensor<f64>, f: fn(f64, f64) -> f64) -> Tensor<f64> {
    let out = broadcast_shapes(a.shape(), b.shape()).expect("broadcastable");
    let n: usize = out.iter().product();
    let data = (0..n)
        .map(|i| {
            let idx = unravel(i, &out);
            f(broadcast_read(a, &idx), broadcast_read(b, &idx))
        })
        .collect();
    Tensor::new(&out, data)
}

type BinaryFn = for<'t> fn(Var<'t, f64>, Var<'t, f64>) -> Var<'t, f64>;

struct BinaryCase {
    name: &'static str,
    op: BinaryFn,
    reference: fn(f64, f64) -> f64,
}

fn binary_cases() -> Vec<BinaryCase> {
    vec![
        BinaryCase { name: "add", op: |a, b| a + b, reference: |a, b| a + b },
        BinaryCase { name: "sub", op: |a, b| a - b, reference: |a, b| a - b },
        BinaryCase { name: "mul", op: |a, b| a * b, reference: |a, b| a * b },
        BinaryCase { name: "div", op: |a, b| a / b, reference: |a, b| a / b },
        BinaryCase { name: "atan2", op: |a, b| a.atan2(b), reference: f64::atan2 },
        BinaryCase { name: "minimum", op: |a, b| a.minimum(b), reference: f64::min },
        BinaryCase { name: "maximum", op: |a, b| a.maximum(b), reference: f64::max },
    ]
}

/// Inputs for a binary op: magnitudes in [0.3, 2] with random signs (no division by
/// ~0, atan2 away from the origin and its branch cut), and for min/max no pair of
/// broadcast-aligned elements closer than [`KINK_GAP`] (away from the kink).
fn binary_inputs(r: &mut rand::rngs::StdRng, sa: &[usize], sb: &[usize]) -> (Tensor<f64>, Tensor<f64>) {
    loop {
        let a = signed(r, sa, 0.3, 2.0);
        let b = signed(r, sb, 0.3, 2.0);
        let gap = reference_binary(&a, &b, |x, y| (x - y).abs());
        if gap.data().iter().all(|&d| d > KINK_GAP) {
            return (a, b);
        }
    }
}

#[test]
fn broadcast_binary_ops_match_reference_and_finite_differences() {
    let mut r = rng(3);
    for case in binary_cases() {
        for &(label, sa, sb) in BROADCAST_CASES {
            let name = format!("{} ({label}: {sa:?} with {sb:?})", case.name);
            let (a, b) = binary_inputs(&mut r, sa, sb);
            let tape = Tape::<f64>::new();
            let y = (case.op)(tape.constant(a.clone()), tape.constant(b.clone()));
            let expected = reference_binary(&a, &b, case.reference);
            assert_eq!(y.shape(), expected.shape(), "{name}");
            // Same arithmetic as the reference, element by element: exact.
            assert_eq!(y.to_tensor().data(), expected.data(), "{name}");
            check(&name, |_, v| (case.op)(v[0], v[1]), &[a, b]);
        }
    }
}

#[test]
fn atan2_covers_all_four_quadrants() {
    use std::f64::consts::{FRAC_PI_4, PI};
    // Values: the angle of (x, y) in each quadrant and on the axes.
    let y = Tensor::new(&[6], vec![1.0, 1.0, -1.0, -1.0, 2.0, -2.0]);
    let x = Tensor::new(&[6], vec![1.0, -1.0, -1.0, 1.0, 0.0, 0.0]);
    let tape = Tape::<f64>::new();
    let a = tape.constant(y.clone()).atan2(tape.constant(x.clone()));
    let expected = [FRAC_PI_4, 3.0 * FRAC_PI_4, -3.0 * FRAC_PI_4, -FRAC_PI_4, PI / 2.0, -PI / 2.0];
    assert_close("atan2 angles", a.to_tensor().data(), &expected, 1e-15, 1.0);
    // Gradients in each quadrant, with points kept off the negative x axis (the cut).
    let mut r = rng(4);
    for (qy, qx) in [(1.0, 1.0), (1.0, -1.0), (-1.0, -1.0), (-1.0, 1.0)] {
        let ys = uniform(&mut r, &[8], 0.2, 2.0).map(|v| qy * v);
        let xs = uniform(&mut r, &[8], 0.2, 2.0).map(|v| qx * v);
        let (_, g) = grads(|_, v| v[0].atan2(v[1]), &[ys.clone(), xs.clone()]);
        for i in 0..8 {
            let (yi, xi) = (ys.data()[i], xs.data()[i]);
            let r2 = xi * xi + yi * yi;
            assert!((g[0].data()[i] - xi / r2).abs() < 1e-15);
            assert!((g[1].data()[i] + yi / r2).abs() < 1e-15);
        }
        check(&format!("atan2 quadrant ({qy}, {qx})"), |_, v| v[0].atan2(v[1]), &[ys, xs]);
    }
}

#[test]
fn operators_with_f64_on_either_side() {
    let mut r = rng(5);
    let x = signed(&mut r, &[3, 4], 0.3, 2.0);
    type Case = (&'static str, UnaryFn, fn(f64) -> f64);
    let cases: [Case; 8] = [
        ("x + c", |x| x + 2.5, |x| x + 2.5),
        ("c + x", |x| 2.5 + x, |x| 2.5 + x),
        ("x - c", |x| x - 2.5, |x| x - 2.5),
        ("c - x", |x| 2.5 - x, |x| 2.5 - x),
        ("x * c", |x| x * 2.5, |x| x * 2.5),
        ("c * x", |x| 2.5 * x, |x| 2.5 * x),
        ("x / c", |x| x / 2.5, |x| x / 2.5),
        ("c / x", |x| 2.5 / x, |x| 2.5 / x),
    ];
    for (name, op, reference) in cases {
        let tape = Tape::<f64>::new();
        let y = op(tape.constant(x.clone()));
        let expected: Vec<f64> = x.data().iter().map(|&v| reference(v)).collect();
        assert_eq!(y.to_tensor().data(), &expected[..], "{name}");
        check(name, |_, v| op(v[0]), std::slice::from_ref(&x));
    }
    // The derivative of the scalar-on-the-left forms is exact: d(c - x)/dx = -1,
    // d(c / x)/dx = -c / x^2.
    let (_, g) = grads(|_, v| 2.5 - v[0], std::slice::from_ref(&x));
    assert!(g[0].data().iter().all(|&v| v == -1.0));
    let (_, g) = grads(|_, v| 2.5 / v[0], std::slice::from_ref(&x));
    for (gv, xv) in g[0].data().iter().zip(x.data()) {
        assert!((gv + 2.5 / (xv * xv)).abs() <= 1e-14 * gv.abs());
    }
}

/// Naive `[.., k] x [k, n]`.
fn reference_matmul(x: &Tensor<f64>, w: &Tensor<f64>) -> Vec<f64> {
    let (k, n) = (w.shape()[0], w.shape()[1]);
    let m = x.numel() / k;
    let mut out = vec![0.0; m * n];
    for i in 0..m {
        for j in 0..n {
            out[i * n + j] = (0..k).map(|l| x.data()[i * k + l] * w.data()[l * n + j]).sum();
        }
    }
    out
}

#[test]
fn matmul_2d_3d_and_vector_lhs() {
    let mut r = rng(6);
    for (label, sx) in
        [("2-D", vec![5, 3]), ("3-D lhs", vec![2, 3, 4]), ("vector lhs", vec![4]), ("single column", vec![6, 1])]
    {
        let k = *sx.last().unwrap();
        let x = normal(&mut r, &sx);
        let w = normal(&mut r, &[k, 5]);
        let tape = Tape::<f64>::new();
        let y = tape.constant(x.clone()).matmul(tape.constant(w.clone()));
        let mut expected_shape = sx.clone();
        *expected_shape.last_mut().unwrap() = 5;
        assert_eq!(y.shape(), expected_shape, "matmul {label}");
        // Summation order differs from the GEMM kernel's: agree to rounding.
        assert_close(&format!("matmul {label}"), y.to_tensor().data(), &reference_matmul(&x, &w), 1e-13, 1.0);
        check(&format!("matmul {label}"), |_, v| v[0].matmul(v[1]), &[x, w]);
    }
}

#[test]
fn matmul_with_long_inner_dimension() {
    // k above the GEMM kernel's depth blocking, so C is accumulated over k-blocks;
    // 600 x 3 inputs are checked along random directions.
    let mut r = rng(7);
    let x = normal(&mut r, &[3, 600]);
    let w = normal(&mut r, &[600, 2]).map(|v| v * 0.05);
    let tape = Tape::<f64>::new();
    let y = tape.constant(x.clone()).matmul(tape.constant(w.clone()));
    assert_close("long matmul", y.to_tensor().data(), &reference_matmul(&x, &w), 1e-12, 1.0);
    check("long matmul", |_, v| v[0].matmul(v[1]), &[x, w]);
}

#[test]
fn affine_2d_and_3d() {
    let mut r = rng(8);
    for (label, sx) in [("2-D", vec![5, 3]), ("3-D", vec![2, 4, 3])] {
        let x = normal(&mut r, &sx);
        let w = normal(&mut r, &[3, 4]);
        let b = normal(&mut r, &[4]);
        let tape = Tape::<f64>::new();
        let y = tape.constant(x.clone()).affine(tape.constant(w.clone()), tape.constant(b.clone()));
        let expected: Vec<f64> =
            reference_matmul(&x, &w).iter().enumerate().map(|(i, v)| v + b.data()[i % 4]).collect();
        assert_close(&format!("affine {label}"), y.to_tensor().data(), &expected, 1e-13, 1.0);
        check(&format!("affine {label}"), |_, v| v[0].affine(v[1], v[2]), &[x, w, b]);
    }
}

#[test]
fn composite_of_broadcast_ops_checks_out() {
    // A small "layer": tanh(x w + b) * s / (1 + c^2), with s a row and c a column.
    let mut r = rng(9);
    let x = normal(&mut r, &[4, 3]);
    let w = normal(&mut r, &[3, 5]);
    let b = normal(&mut r, &[5]);
    let s = normal(&mut r, &[5]);
    let c = normal(&mut r, &[4, 1]);
    check("composite", |_, v| (v[0].affine(v[1], v[2]).tanh() * v[3]) / (v[4].square() + 1.0), &[x, w, b, s, c]);
}
