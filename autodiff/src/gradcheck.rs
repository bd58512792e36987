//! Finite-difference gradient checks for any model built on a [`Tape`]: one call
//! compares the reverse-mode gradient of a scalar function with central differences.
//!
//! Derivatives are central differences refined by one Richardson extrapolation,
//! `(4 D(h/2) - D(h)) / 3`, whose truncation error is O(h^4): this allows a step
//! large enough (1e-3) that rounding contributes only ~1e-13 relative error, so a
//! tolerance of 1e-6 measures the engine, not the finite differences.
//!
//! Small inputs are checked coordinate by coordinate; inputs with more elements than
//! [`GradCheck::per_coordinate_limit`] are checked along random directions
//! (`<grad, u>` against the directional difference), which costs two evaluations per
//! direction whatever the size.
//!
//! ```
//! use autodiff::gradcheck::GradCheck;
//! use autodiff::Tensor;
//! let x = Tensor::new(&[3], vec![0.3, -1.2, 2.0]);
//! let report = GradCheck::default()
//!     .check(|_, v| (v[0].tanh() * v[0]).sum(), &[x])
//!     .expect("gradient matches finite differences");
//! assert!(report.max_rel_error < 1e-6);
//! ```

use std::fmt;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

use crate::nn::{BoundParams, ParamStore};
use crate::tape::{Tape, Var};
use crate::tensor::Tensor;

/// Settings of a finite-difference gradient check (f64).
#[derive(Clone, Debug)]
pub struct GradCheck {
    /// Central-difference step (the coarser of the two Richardson steps), scaled by
    /// `max(1, |x|)` per coordinate.
    pub step: f64,
    /// Largest accepted relative error `|a - n| / max(|a|, |n|, abs_floor)`.
    pub rel_tol: f64,
    /// Floor of the denominator, so that gradients near zero are compared absolutely.
    pub abs_floor: f64,
    /// Inputs with more elements than this are checked along random directions.
    pub per_coordinate_limit: usize,
    /// Number of random directions for large inputs.
    pub directions: usize,
    /// Seed of the random directions.
    pub seed: u64,
}

impl Default for GradCheck {
    fn default() -> Self {
        GradCheck { step: 1e-3, rel_tol: 1e-6, abs_floor: 1e-6, per_coordinate_limit: 256, directions: 6, seed: 7 }
    }
}

/// What a passing check measured.
#[derive(Clone, Debug, PartialEq)]
pub struct GradCheckReport {
    /// Largest relative error seen.
    pub max_rel_error: f64,
    /// Number of comparisons made (coordinates plus directions).
    pub comparisons: usize,
}

/// Why a gradient check failed.
#[derive(Clone, Debug, PartialEq)]
pub enum GradCheckError {
    /// The function did not return a one-element tensor.
    NotScalar(Vec<usize>),
    /// The function or its gradient was not finite at the check point.
    NonFinite(String),
    /// Analytic and numeric derivatives disagree.
    Mismatch {
        /// Where: `input[i][j]` or `input[i] direction d`.
        at: String,
        /// Reverse-mode value.
        analytic: f64,
        /// Central-difference value.
        numeric: f64,
        /// Their relative error.
        rel_error: f64,
    },
}

impl fmt::Display for GradCheckError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            GradCheckError::NotScalar(s) => {
                write!(f, "gradient check: output has shape {s:?}, not a scalar")
            }
            GradCheckError::NonFinite(w) => write!(f, "gradient check: non-finite {w}"),
            GradCheckError::Mismatch { at, analytic, numeric, rel_error } => write!(
                f,
                "gradient check: at {at} reverse mode gives {analytic:.10e}, finite differences \
                 {numeric:.10e} (relative error {rel_error:.2e})"
            ),
        }
    }
}

impl std::error::Error for GradCheckError {}

impl GradCheck {
    /// Checks a model's gradient with respect to every parameter of `store`: `f`
    /// builds the scalar from the bound parameters, as training code does.
    pub fn check_params<Func>(&self, store: &ParamStore<f64>, f: Func) -> Result<GradCheckReport, GradCheckError>
    where
        Func: for<'t> Fn(&'t Tape<f64>, &BoundParams<'t, f64>) -> Var<'t, f64>,
    {
        self.check(|tape, vars| f(tape, &BoundParams::from_vars(vars.to_vec())), store.values())
    }

    /// Checks `f`'s reverse-mode gradient with respect to every input against central
    /// differences. `f` receives a fresh tape and the inputs as tracked leaves and
    /// must return a scalar.
    pub fn check<Func>(&self, f: Func, inputs: &[Tensor<f64>]) -> Result<GradCheckReport, GradCheckError>
    where
        Func: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
    {
        let eval = |xs: &[Tensor<f64>]| -> f64 {
            let tape = Tape::no_record();
            let vars: Vec<Var<'_, f64>> = xs.iter().map(|x| tape.constant(x.clone())).collect();
            f(&tape, &vars).item()
        };
        // Analytic gradients.
        let tape = Tape::new();
        let vars: Vec<Var<'_, f64>> = inputs.iter().map(|x| tape.param(x.clone())).collect();
        let out = f(&tape, &vars);
        let shape = out.shape();
        if shape.iter().product::<usize>() != 1 {
            return Err(GradCheckError::NotScalar(shape));
        }
        if !out.item().is_finite() {
            return Err(GradCheckError::NonFinite(format!("output {}", out.item())));
        }
        let grads = tape.backward(out);
        let analytic: Vec<Tensor<f64>> = vars.iter().map(|&v| grads.wrt(v)).collect();
        for (i, g) in analytic.iter().enumerate() {
            if !g.all_finite() {
                return Err(GradCheckError::NonFinite(format!("gradient of input {i}")));
            }
        }

        let mut report = GradCheckReport { max_rel_error: 0.0, comparisons: 0 };
        let mut compare = |at: String, a: f64, n: f64| -> Result<(), GradCheckError> {
            let rel = (a - n).abs() / a.abs().max(n.abs()).max(self.abs_floor);
            report.max_rel_error = report.max_rel_error.max(rel);
            report.comparisons += 1;
            if rel > self.rel_tol || !n.is_finite() {
                return Err(GradCheckError::Mismatch { at, analytic: a, numeric: n, rel_error: rel });
            }
            Ok(())
        };
        let mut xs: Vec<Tensor<f64>> = inputs.to_vec();
        let mut rng = StdRng::seed_from_u64(self.seed);
        for i in 0..inputs.len() {
            let n = inputs[i].numel();
            if n <= self.per_coordinate_limit {
                for j in 0..n {
                    let x0 = inputs[i].data()[j];
                    let h = self.step * x0.abs().max(1.0);
                    let numeric = richardson(h, |t| {
                        xs[i].data_mut()[j] = x0 + t;
                        let f = eval(&xs);
                        xs[i].data_mut()[j] = x0;
                        f
                    });
                    compare(format!("input[{i}][{j}]"), analytic[i].data()[j], numeric)?;
                }
            } else {
                let scale = inputs[i].data().iter().fold(1.0f64, |m, x| m.max(x.abs()));
                for d in 0..self.directions {
                    let u: Vec<f64> = (0..n).map(|_| rng.sample(StandardNormal)).collect();
                    let norm = u.iter().map(|v| v * v).sum::<f64>().sqrt();
                    let h = self.step * scale;
                    let numeric = richardson(h, |t| {
                        let mut ys = xs.clone();
                        for (y, uj) in ys[i].data_mut().iter_mut().zip(&u) {
                            *y += t * uj / norm;
                        }
                        eval(&ys)
                    });
                    let a: f64 = analytic[i].data().iter().zip(&u).map(|(g, uj)| g * uj / norm).sum();
                    compare(format!("input[{i}] direction {d}"), a, numeric)?;
                }
            }
        }
        Ok(report)
    }
}

/// The derivative at 0 of `f(t)` from central differences with steps `h` and `h / 2`
/// combined by Richardson extrapolation (truncation error O(h^4)).
fn richardson(h: f64, mut f: impl FnMut(f64) -> f64) -> f64 {
    let mut central = |s: f64| (f(s) - f(-s)) / (2.0 * s);
    let coarse = central(h);
    let fine = central(h / 2.0);
    (4.0 * fine - coarse) / 3.0
}
