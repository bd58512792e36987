//! Shared helpers of the engine's test suite: seeded random tensors and a gradient
//! check that contracts an op's (possibly non-scalar) output with fixed random weights.

use autodiff::gradcheck::{GradCheck, GradCheckReport};
use autodiff::{Tape, Tensor, Var};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

/// Largest accepted relative error of a smooth op's VJP against central differences.
/// Any wrong rule (a missing factor, a sign, a broadcast axis not summed) shows up as
/// an O(1) relative error; 1e-6 is far above the finite-difference noise at the
/// settings of [`smooth_check`] (see there).
pub const SMOOTH_TOL: f64 = 1e-6;

/// A seeded generator (rand 0.9).
pub fn rng(seed: u64) -> StdRng {
    StdRng::seed_from_u64(seed)
}

fn numel(shape: &[usize]) -> usize {
    shape.iter().product()
}

/// Multi-index of flat position `i` in `shape` (row-major).
pub fn unravel(mut i: usize, shape: &[usize]) -> Vec<usize> {
    let mut idx = vec![0; shape.len()];
    for d in (0..shape.len()).rev() {
        idx[d] = i % shape[d];
        i /= shape[d];
    }
    idx
}

/// Standard normal entries.
pub fn normal(rng: &mut StdRng, shape: &[usize]) -> Tensor<f64> {
    let data = (0..numel(shape)).map(|_| rng.sample::<f64, _>(StandardNormal)).collect();
    Tensor::new(shape, data)
}

/// Uniform entries in `[lo, hi)`.
pub fn uniform(rng: &mut StdRng, shape: &[usize], lo: f64, hi: f64) -> Tensor<f64> {
    let data = (0..numel(shape)).map(|_| rng.random_range(lo..hi)).collect();
    Tensor::new(shape, data)
}

/// Entries with magnitude uniform in `[lo, hi)` and a random sign (away from zero).
pub fn signed(rng: &mut StdRng, shape: &[usize], lo: f64, hi: f64) -> Tensor<f64> {
    let data = (0..numel(shape))
        .map(|_| {
            let m = rng.random_range(lo..hi);
            if rng.random::<bool>() {
                m
            } else {
                -m
            }
        })
        .collect();
    Tensor::new(shape, data)
}

/// Uniform entries in `[lo, hi)` at least `gap` away from every point of `kinks`, so
/// that a central difference of step 1e-6 never straddles a kink.
pub fn away_from(rng: &mut StdRng, shape: &[usize], lo: f64, hi: f64, kinks: &[f64], gap: f64) -> Tensor<f64> {
    let data = (0..numel(shape))
        .map(|_| loop {
            let x = rng.random_range(lo..hi);
            if kinks.iter().all(|k| (x - k).abs() >= gap) {
                break x;
            }
        })
        .collect();
    Tensor::new(shape, data)
}

/// The shape of `f`'s output on `inputs` (computed on a non-recording tape).
pub fn output_shape<Func>(f: &Func, inputs: &[Tensor<f64>]) -> Vec<usize>
where
    Func: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
{
    let tape = Tape::no_record();
    let vars: Vec<Var<'_, f64>> = inputs.iter().map(|x| tape.constant(x.clone())).collect();
    f(&tape, &vars).shape()
}

/// Checks the VJP of `f` (any output shape) against central differences with `gc`:
/// the checked scalar is `sum(f(inputs) * w)` for fixed standard-normal weights `w`,
/// so every output element carries a different cotangent (a plain sum would hide
/// errors, e.g. softmax's gradient of a sum is identically zero). With the environment
/// variable `GRADCHECK_VERBOSE` set, prints each check's largest relative error.
#[track_caller]
pub fn check_with<Func>(gc: &GradCheck, name: &str, f: Func, inputs: &[Tensor<f64>]) -> GradCheckReport
where
    Func: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
{
    let shape = output_shape(&f, inputs);
    let mut r = rng(0x5EF1 ^ name.len() as u64);
    let w = normal(&mut r, &shape);
    let report = gc
        .check(
            |tape, v| {
                let y = f(tape, v);
                (y * tape.constant(w.clone())).sum()
            },
            inputs,
        )
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    let coords: usize =
        inputs.iter().map(|x| if x.numel() <= gc.per_coordinate_limit { x.numel() } else { gc.directions }).sum();
    assert_eq!(report.comparisons, coords, "{name}: every coordinate must be compared");
    assert!(report.max_rel_error < gc.rel_tol, "{name}: relative error {}", report.max_rel_error);
    if std::env::var_os("GRADCHECK_VERBOSE").is_some() {
        eprintln!("{name}: max relative error {:.2e}", report.max_rel_error);
    }
    report
}

/// The finite-difference settings for smooth ops. `GradCheck` refines central
/// differences by Richardson extrapolation (steps `h` and `h / 2`, truncation error
/// about `h^4 |f^(5)| / 480`).
///
/// * Step 1e-3 (times `max(1, |x|)`): the truncation error is below 1e-9 relative on
///   the input domains used (the worst, `x^-1.5` at 0.2 with `|f^(5)| ~ 1e7`, gives
///   ~2e-8 absolute against a derivative of 84), and the rounding error
///   `eps |f| / (h / 2)` is ~4e-12 absolute for the O(10) contracted outputs.
/// * `abs_floor` 1e-4: gradient entries below 1e-4 are compared absolutely at
///   `1e-6 * 1e-4 = 1e-10`, 25 times that rounding noise; a relative error of a tiny
///   entry would measure the noise, not the VJP.
///
/// Inputs of ops with kinks are drawn at least [`KINK_GAP`] away from them.
pub fn smooth_check() -> GradCheck {
    GradCheck { step: 1e-3, rel_tol: SMOOTH_TOL, abs_floor: 1e-4, ..GradCheck::default() }
}

/// Least distance of a random input from a kink (relu/abs at 0, clamp's bounds, a
/// min/max tie): the finite-difference points `x +- h` with `h <= 1e-3 max(1, |x|)`
/// (<= 3e-3 on the domains used) then stay on one side.
pub const KINK_GAP: f64 = 1e-2;

/// [`check_with`] at the [`smooth_check`] settings.
#[track_caller]
pub fn check<Func>(name: &str, f: Func, inputs: &[Tensor<f64>]) -> GradCheckReport
where
    Func: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
{
    check_with(&smooth_check(), name, f, inputs)
}

/// Asserts `|a - b| <= tol * max(|b|, floor)` element-wise, naming the first failure.
#[track_caller]
pub fn assert_close(what: &str, a: &[f64], b: &[f64], tol: f64, floor: f64) {
    assert_eq!(a.len(), b.len(), "{what}: lengths differ");
    for (i, (&x, &y)) in a.iter().zip(b).enumerate() {
        let ok = if y.is_infinite() { x == y } else { (x - y).abs() <= tol * y.abs().max(floor) };
        assert!(ok, "{what}[{i}]: got {x:e}, expected {y:e} (tol {tol:e})");
    }
}

/// The value of `f` and its VJP with a cotangent of ones (the gradient of the sum of
/// its outputs) with respect to each input, on a fresh recording tape.
pub fn grads<Func>(f: Func, inputs: &[Tensor<f64>]) -> (Tensor<f64>, Vec<Tensor<f64>>)
where
    Func: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
{
    let tape = Tape::new();
    let vars: Vec<Var<'_, f64>> = inputs.iter().map(|x| tape.param(x.clone())).collect();
    let y = f(&tape, &vars);
    let value = y.to_tensor();
    let cot = Tensor::ones(value.shape());
    let g = tape.vjp(y, cot);
    (value, vars.iter().map(|&v| g.wrt(v)).collect())
}
