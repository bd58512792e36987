//! What the reverse pass means beyond smooth VJPs: the documented subgradients at
//! kinks and ties, stop-gradient, accumulation over repeated uses, saturating and
//! near-singular inputs (softplus at +-50, log at 1e-8), and vector-Jacobian products
//! with a non-scalar cotangent.

use crate::common::*;
use autodiff::gradcheck::GradCheck;
use autodiff::{Tape, Tensor, Var};

fn t(data: &[f64]) -> Tensor<f64> {
    Tensor::from_vec(data.to_vec())
}

#[test]
fn relu_and_abs_have_zero_subgradient_at_zero() {
    let x = t(&[-1.5, -0.0, 0.0, 2.0]);
    let (y, g) = grads(|_, v| v[0].relu(), std::slice::from_ref(&x));
    assert_eq!(y.data(), &[0.0, 0.0, 0.0, 2.0]);
    assert_eq!(g[0].data(), &[0.0, 0.0, 0.0, 1.0], "relu'(0) = 0");
    let (y, g) = grads(|_, v| v[0].abs(), &[x]);
    assert_eq!(y.data(), &[1.5, 0.0, 0.0, 2.0]);
    assert_eq!(g[0].data(), &[-1.0, 0.0, 0.0, 1.0], "abs'(0) = 0");
}

#[test]
fn clamp_passes_the_gradient_on_the_closed_interval() {
    let x = t(&[-3.0, -1.0, -0.999, 0.0, 2.0, 2.001, 5.0]);
    let (y, g) = grads(|_, v| v[0].clamp(-1.0, 2.0), &[x]);
    assert_eq!(y.data(), &[-1.0, -1.0, -0.999, 0.0, 2.0, 2.0, 2.0]);
    assert_eq!(g[0].data(), &[0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0]);
}

#[test]
fn minimum_and_maximum_send_ties_to_the_first_argument() {
    let a = t(&[1.0, 2.0, 3.0, -0.5]);
    let b = t(&[1.0, 1.0, 4.0, -0.5]);
    let (y, g) = grads(|_, v| v[0].minimum(v[1]), &[a.clone(), b.clone()]);
    assert_eq!(y.data(), &[1.0, 1.0, 3.0, -0.5]);
    assert_eq!(g[0].data(), &[1.0, 0.0, 1.0, 1.0], "min: ties to a");
    assert_eq!(g[1].data(), &[0.0, 1.0, 0.0, 0.0]);
    let (y, g) = grads(|_, v| v[0].maximum(v[1]), &[a.clone(), b.clone()]);
    assert_eq!(y.data(), &[1.0, 2.0, 4.0, -0.5]);
    assert_eq!(g[0].data(), &[1.0, 1.0, 0.0, 1.0], "max: ties to a");
    assert_eq!(g[1].data(), &[0.0, 0.0, 1.0, 0.0]);
    // Swapping the arguments moves the tie's gradient with the first argument.
    let (_, g) = grads(|_, v| v[1].minimum(v[0]), &[a, b]);
    assert_eq!(g[1].data(), &[1.0, 1.0, 0.0, 1.0]);
    assert_eq!(g[0].data(), &[0.0, 0.0, 1.0, 0.0]);

    // Broadcast against a scalar that ties with some entries: the scalar's gradient
    // counts the positions where it is strictly the minimum.
    let row = Tensor::new(&[2, 3], vec![0.0, 1.0, 2.0, 1.0, 3.0, -1.0]);
    let one = Tensor::scalar(1.0);
    let (y, g) = grads(|_, v| v[0].minimum(v[1]), &[row, one]);
    assert_eq!(y.data(), &[0.0, 1.0, 1.0, 1.0, 1.0, -1.0]);
    assert_eq!(g[0].data(), &[1.0, 1.0, 0.0, 1.0, 0.0, 1.0]);
    assert_eq!(g[1].data(), &[2.0]);
}

#[test]
fn detach_and_stop_gradient_block_the_gradient() {
    let x = t(&[0.5, -2.0, 3.0]);
    // d/dx [stop(x) * x] = stop(x), not 2x.
    let (_, g) = grads(|_, v| v[0].detach() * v[0], std::slice::from_ref(&x));
    assert_eq!(g[0].data(), x.data());
    let (_, g) = grads(|_, v| v[0].stop_gradient() * v[0].exp(), std::slice::from_ref(&x));
    let expected: Vec<f64> = x.data().iter().map(|v| v * v.exp()).collect();
    assert_eq!(g[0].data(), &expected[..]);

    // Nothing but the detached path: the output is untracked and the gradient zero.
    let tape = Tape::<f64>::new();
    let p = tape.param(x.clone());
    let d = p.detach();
    assert!(p.is_tracked() && !d.is_tracked());
    assert_eq!(d.to_tensor(), x);
    let out = d.tanh().sum();
    assert!(!out.is_tracked());
    let g = tape.backward(out);
    assert!(g.get(p).is_none());
    assert_eq!(g.wrt(p).data(), &[0.0, 0.0, 0.0]);
}

#[test]
fn a_value_used_twice_accumulates_both_gradients() {
    let x = t(&[0.3, -1.2, 2.0]);
    // x * x + sin x: 2x + cos x.
    let (_, g) = grads(|_, v| v[0] * v[0] + v[0].sin(), std::slice::from_ref(&x));
    for (gv, xv) in g[0].data().iter().zip(x.data()) {
        assert!((gv - (2.0 * xv + xv.cos())).abs() < 1e-15);
    }
    // Through an intermediate: y = tanh x used three times.
    let (_, g) = grads(
        |_, v| {
            let y = v[0].tanh();
            y * y + y
        },
        std::slice::from_ref(&x),
    );
    for (gv, xv) in g[0].data().iter().zip(x.data()) {
        let y = xv.tanh();
        assert!((gv - (2.0 * y + 1.0) * (1.0 - y * y)).abs() < 1e-15);
    }
    // A row used both broadcast over a matrix and on its own.
    let m = normal(&mut rng(40), &[4, 3]);
    check("row used twice", |_, v| (v[1] * v[0]).sum_axis(0, false) + v[0].exp(), &[x, m]);
}

#[test]
fn softplus_sigmoid_and_tanh_saturate_cleanly() {
    let x = t(&[-1000.0, -50.0, 50.0, 1000.0]);
    let e50 = (-50.0f64).exp();
    let (y, g) = grads(|_, v| v[0].softplus(), std::slice::from_ref(&x));
    assert_close("softplus(+-50)", y.data(), &[0.0, e50, 50.0, 1000.0], 1e-15, 1e-300);
    // d softplus = sigmoid: e^-50 / (1 + e^-50) ~ 1.93e-22 at -50, 1 at +50.
    assert_close("softplus'(+-50)", g[0].data(), &[0.0, e50 / (1.0 + e50), 1.0, 1.0], 1e-15, 1e-300);
    let (y, g) = grads(|_, v| v[0].sigmoid(), std::slice::from_ref(&x));
    assert!(y.all_finite() && g[0].all_finite());
    assert_eq!(y.data()[3], 1.0);
    assert_eq!(y.data()[0], 0.0);
    let (y, g) = grads(|_, v| v[0].tanh(), std::slice::from_ref(&x));
    assert_eq!(y.data(), &[-1.0, -1.0, 1.0, 1.0]);
    assert!(g[0].all_finite());

    // f32: the same values through the fast kernels, still finite.
    let tape = Tape::<f32>::new();
    let xv = tape.param(x.cast::<f32>());
    let sp = xv.softplus();
    let v = sp.to_tensor();
    assert_eq!(v.data()[0], 0.0);
    assert!(((v.data()[1] as f64) - e50).abs() < 1e-6 * e50);
    assert_eq!(v.data()[2], 50.0);
    assert_eq!(v.data()[3], 1000.0);
    let g = tape.backward(sp.sum()).wrt(xv);
    assert!(g.all_finite());
    assert!(((g.data()[1] as f64) - e50).abs() < 1e-6 * e50);
    assert_eq!(g.data()[2], 1.0);
    assert_eq!(g.data()[3], 1.0);
}

#[test]
fn log_near_zero_is_accurate() {
    let x = t(&[1e-8, 2.5e-8]);
    let (y, g) = grads(|_, v| v[0].ln(), std::slice::from_ref(&x));
    assert_close("ln(1e-8)", y.data(), &[(1e-8f64).ln(), (2.5e-8f64).ln()], 1e-15, 1.0);
    assert_close("d ln(1e-8)", g[0].data(), &[1e8, 4e7], 1e-15, 1.0);
    // Finite differences need a step below x itself: h = 1e-12 perturbs x by 1e-4
    // relative, so the truncation error h^2 / (3 x^2) is ~3e-9 relative and the
    // rounding error eps * 18 / h ~ 4e-3 is 4e-11 of the 1e8 gradient.
    let gc = GradCheck { step: 1e-12, ..smooth_check() };
    check_with(&gc, "ln near 0", |_, v| v[0].ln(), std::slice::from_ref(&x));

    // f32 at 1e-8 (a normal f32): the fast log keeps full relative accuracy.
    let tape = Tape::<f32>::new();
    let xv = tape.param(x.cast::<f32>());
    let y = xv.ln();
    let exact = ((1e-8f32) as f64).ln();
    assert!((y.to_tensor().data()[0] as f64 - exact).abs() < 1e-6 * exact.abs());
    let g = tape.backward(y.sum()).wrt(xv);
    assert!(((g.data()[0] as f64) - 1e8).abs() < 1e-6 * 1e8);
}

#[test]
fn vjp_with_a_non_scalar_cotangent_is_the_gradient_of_the_contraction() {
    let mut r = rng(41);
    let x = normal(&mut r, &[4, 3]);
    let w = normal(&mut r, &[3, 2]);
    let c = normal(&mut r, &[4, 2]);
    fn model<'t>(xv: Var<'t, f64>, wv: Var<'t, f64>) -> Var<'t, f64> {
        xv.matmul(wv).tanh() + xv.sum_axis(1, true).sin()
    }
    let tape = Tape::<f64>::new();
    let (xv, wv) = (tape.param(x.clone()), tape.param(w.clone()));
    let y = model(xv, wv);
    assert_eq!(y.shape(), vec![4, 2]);
    let by_vjp = tape.vjp(y, c.clone());
    let contraction = (y * tape.constant(c.clone())).sum();
    let by_backward = tape.backward(contraction);
    // The cotangent reaching y is c either way (1 * c is exact), so the two reverse
    // passes perform identical arithmetic.
    assert_eq!(by_vjp.wrt(xv), by_backward.wrt(xv));
    assert_eq!(by_vjp.wrt(wv), by_backward.wrt(wv));
    // And it is right: finite differences of the contraction.
    check_with(
        &smooth_check(),
        "vjp contraction",
        |tape, v| (model(v[0], v[1]) * tape.constant(c.clone())).sum(),
        &[x, w],
    );
    // A leaf's own VJP is the cotangent; a second reverse pass repeats the first.
    let u = normal(&mut r, &[4, 3]);
    assert_eq!(tape.vjp(xv, u.clone()).wrt(xv), u);
    assert_eq!(tape.vjp(y, c.clone()).wrt(wv), by_vjp.wrt(wv));
}
