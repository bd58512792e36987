//! The precomputed-gradients node (`Tape::precomputed`): fused functions built from
//! a value and analytic partials, in both layouts (element-wise with broadcasting —
//! a `[1]`, a column `[R, 1]` and a row `[K]` — and row-wise `[R] <- [R, K]`), checked against finite differences in f64 and
//! against the same function composed from primitive ops; then its `-inf` guard,
//! its behaviour with untracked inputs and its shape checks.

use crate::common::*;
use autodiff::dist::{normal_logpdf, HALF_LN_2PI};
use autodiff::{Tape, Tensor, Var};

/// Rows of the checked inputs.
const ROWS: usize = 7;
/// Trailing length of the row-wise input.
const K: usize = 5;

/// `log N(x; mu, e^{2 log_sd})` as one fused node: `x: [R]`, `mu: [1]` (broadcast),
/// `log_sd: [R]`.
fn fused_normal<'t>(tape: &'t Tape<f64>, x: Var<'t, f64>, mu: Var<'t, f64>, log_sd: Var<'t, f64>) -> Var<'t, f64> {
    let (xv, m, ls) = (x.to_tensor(), mu.item(), log_sd.to_tensor());
    let z: Vec<f64> = xv.data().iter().zip(ls.data()).map(|(&x, &l)| (x - m) / l.exp()).collect();
    let inv_sd: Vec<f64> = ls.data().iter().map(|&l| (-l).exp()).collect();
    let value = z.iter().zip(ls.data()).map(|(&z, &l)| -0.5 * z * z - l - HALF_LN_2PI).collect();
    let dx: Vec<f64> = z.iter().zip(&inv_sd).map(|(&z, &i)| -z * i).collect();
    let dmu: Vec<f64> = dx.iter().map(|&d| -d).collect();
    let dls: Vec<f64> = z.iter().map(|&z| z * z - 1.0).collect();
    tape.precomputed(
        Tensor::from_vec(value),
        vec![(x, Tensor::from_vec(dx)), (mu, Tensor::from_vec(dmu)), (log_sd, Tensor::from_vec(dls))],
    )
}

/// `ln sum_k e^{a_ik} + c_i` as one node: `a: [R, K]` row-wise (partials: the
/// softmax of each row), `c: [R]` element-wise.
fn fused_row_lse<'t>(tape: &'t Tape<f64>, a: Var<'t, f64>, c: Var<'t, f64>) -> Var<'t, f64> {
    let (av, cv) = (a.to_tensor(), c.to_tensor());
    let mut value = Vec::new();
    let mut da = Vec::new();
    for (row, &ci) in av.data().chunks(K).zip(cv.data()) {
        let m = row.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let s: f64 = row.iter().map(|&v| (v - m).exp()).sum();
        let lse = m + s.ln();
        value.push(lse + ci);
        da.extend(row.iter().map(|&v| (v - lse).exp()));
    }
    tape.precomputed(
        Tensor::from_vec(value),
        vec![(a, Tensor::new(&[ROWS, K], da)), (c, Tensor::from_vec(vec![1.0; ROWS]))],
    )
}

/// Checks the fused node `fused` against finite differences, then its value and
/// gradients against the same function `composed` from primitive ops: the values
/// within `value_tol` (relative, floor 1), each gradient with the input's shape and
/// within `grad_tol` (relative, floor `grad_floor`).
#[track_caller]
fn assert_fused_matches_composed<Fused, Composed>(
    name: &str,
    fused: Fused,
    composed: Composed,
    inputs: &[Tensor<f64>],
    value_tol: f64,
    grad_tol: f64,
    grad_floor: f64,
) where
    Fused: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
    Composed: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
{
    check(name, &fused, inputs);
    let (fused, fused_grads) = grads(&fused, inputs);
    let (composed, composed_grads) = grads(composed, inputs);
    assert_close("value", fused.data(), composed.data(), value_tol, 1.0);
    for (i, (f, c)) in fused_grads.iter().zip(&composed_grads).enumerate() {
        assert_eq!(f.shape(), c.shape(), "gradient {i}: the broadcast input keeps its shape");
        assert_close(&format!("gradient {i}"), f.data(), c.data(), grad_tol, grad_floor);
    }
}

#[test]
fn element_wise_layout_matches_finite_differences_and_the_composed_density() {
    let mut r = rng(11);
    let x = normal(&mut r, &[ROWS]);
    let mu = normal(&mut r, &[1]);
    let log_sd = uniform(&mut r, &[ROWS], -0.5, 0.5);
    assert_fused_matches_composed(
        "fused normal",
        |tape, v| fused_normal(tape, v[0], v[1], v[2]),
        |_, v| normal_logpdf(v[0], v[1], v[2]),
        &[x, mu, log_sd],
        1e-14,
        1e-13,
        1.0,
    );
}

#[test]
fn row_wise_layout_matches_finite_differences_and_logsumexp() {
    let mut r = rng(12);
    let a = normal(&mut r, &[ROWS, K]);
    let c = normal(&mut r, &[ROWS]);
    assert_fused_matches_composed(
        "fused row logsumexp",
        |tape, v| fused_row_lse(tape, v[0], v[1]),
        |_, v| v[0].logsumexp(1, false) + v[1],
        &[a, c],
        1e-14,
        1e-13,
        1e-300,
    );
}

/// `y_ik = x_i a_ik + c_k` as one node: `x: [R, 1]` a column broadcast along each
/// row (partials `a`), `a: [R, K]` element-wise (partials `x`), `c: [K]` a row
/// broadcast down the columns (partials 1).
fn fused_outer<'t>(tape: &'t Tape<f64>, x: Var<'t, f64>, a: Var<'t, f64>, c: Var<'t, f64>) -> Var<'t, f64> {
    let (xv, av, cv) = (x.to_tensor(), a.to_tensor(), c.to_tensor());
    let mut value = Vec::new();
    let mut dx = Vec::new();
    for (row, &xi) in av.data().chunks(K).zip(xv.data()) {
        value.extend(row.iter().zip(cv.data()).map(|(&a, &c)| xi * a + c));
        dx.extend(row.iter().copied());
    }
    let da: Vec<f64> = xv.data().iter().flat_map(|&xi| std::iter::repeat_n(xi, K)).collect();
    tape.precomputed(
        Tensor::new(&[ROWS, K], value),
        vec![
            (x, Tensor::new(&[ROWS, K], dx)),
            (a, Tensor::new(&[ROWS, K], da)),
            (c, Tensor::new(&[ROWS, K], vec![1.0; ROWS * K])),
        ],
    )
}

#[test]
fn broadcast_columns_and_rows_sum_their_partials() {
    let mut r = rng(14);
    let inputs = [normal(&mut r, &[ROWS, 1]), normal(&mut r, &[ROWS, K]), normal(&mut r, &[K])];
    assert_fused_matches_composed(
        "fused outer product",
        |tape, v| fused_outer(tape, v[0], v[1], v[2]),
        |_, v| v[0] * v[1] + v[2],
        &inputs,
        1e-15,
        1e-14,
        1.0,
    );
}

#[test]
fn inputs_that_are_intermediates_and_used_twice_accumulate() {
    // The fused node's inputs come from other ops, one of them feeds the node twice
    // (as `x` and as `log_sd`), and its output feeds further ops.
    let mut r = rng(13);
    let w = uniform(&mut r, &[ROWS], -0.4, 0.4);
    let mu = normal(&mut r, &[1]);
    check(
        "fused normal inside a graph",
        |tape, v| {
            let t = v[0].tanh();
            let y = fused_normal(tape, t, v[1], t);
            (y * y).exp() + y
        },
        &[w, mu],
    );
}

#[test]
fn an_impossible_element_passes_no_gradient() {
    let tape = Tape::<f64>::new();
    let x = tape.param(Tensor::from_vec(vec![1.0, 2.0, 3.0]));
    let value = Tensor::from_vec(vec![-1.0, f64::NEG_INFINITY, -2.0]);
    // Garbage partials at the impossible element must not leak into the gradient.
    let y = tape.precomputed(value, vec![(x, Tensor::from_vec(vec![0.5, f64::NAN, -1.5]))]);
    let g = tape.backward(y.logsumexp(0, false));
    let gx = g.wrt(x);
    assert!(gx.all_finite(), "{:?}", gx.data());
    assert_eq!(gx.data()[1], 0.0);
    // The other elements get their share of the log-sum-exp times their partial.
    let lse = ((-1.0f64).exp() + (-2.0f64).exp()).ln();
    let (w0, w2) = ((-1.0 - lse).exp(), (-2.0 - lse).exp());
    assert!((gx.data()[0] - 0.5 * w0).abs() < 1e-15 && (gx.data()[2] + 1.5 * w2).abs() < 1e-15);
}

#[test]
fn untracked_inputs_are_dropped_and_constants_stay_constant() {
    let tape = Tape::<f64>::new();
    let c = tape.constant(Tensor::from_vec(vec![1.0, 2.0]));
    let y = tape.precomputed(Tensor::from_vec(vec![3.0, 4.0]), vec![(c, Tensor::from_vec(vec![1.0, 1.0]))]);
    assert!(!y.is_tracked());
    assert_eq!(y.to_tensor().data(), &[3.0, 4.0]);
    let off = Tape::<f64>::no_record();
    let p = off.param(Tensor::from_vec(vec![1.0]));
    let y = off.precomputed(Tensor::from_vec(vec![2.0]), vec![(p, Tensor::from_vec(vec![5.0]))]);
    assert!(!y.is_tracked());
    // A tracked and an untracked input: only the tracked one receives a gradient.
    let x = tape.param(Tensor::from_vec(vec![1.0, 2.0]));
    let y = tape.precomputed(
        Tensor::from_vec(vec![0.0, 0.0]),
        vec![(c, Tensor::from_vec(vec![9.0, 9.0])), (x, Tensor::from_vec(vec![2.0, 3.0]))],
    );
    let g = tape.backward(y.sum());
    assert_eq!(g.wrt(x).data(), &[2.0, 3.0]);
}

#[test]
#[should_panic(expected = "precomputed: partial of shape [3]")]
fn a_partial_of_the_wrong_shape_is_refused() {
    let tape = Tape::<f64>::new();
    let x = tape.param(Tensor::from_vec(vec![1.0, 2.0]));
    tape.precomputed(Tensor::from_vec(vec![0.0, 0.0]), vec![(x, Tensor::from_vec(vec![1.0, 1.0, 1.0]))]);
}

#[test]
#[should_panic(expected = "precomputed: partial of shape [2, 3]")]
fn a_row_wise_input_must_lead_with_the_value_shape() {
    let tape = Tape::<f64>::new();
    let x = tape.param(Tensor::new(&[2, 3], vec![0.0; 6]));
    tape.precomputed(Tensor::from_vec(vec![0.0, 0.0, 0.0]), vec![(x, Tensor::new(&[2, 3], vec![0.0; 6]))]);
}
