//! A model written in Python: vectorised callbacks over particles, with the
//! particle filter, resampling, fixed-lag smoothing and PF-SEFI's weights onto
//! distinct ancestors run in Rust.
//!
//! The model object supplies (arrays are float64, one row per particle):
//!
//! * `state_dim`, and optionally `prior_noise_dim` and `transition_noise_dim`
//!   (default `state_dim`);
//! * `prior(theta, z) -> x0`: `z` standard normal `(n, prior_noise_dim)`, `x0` `(n, d)`;
//! * `transition(theta, t, x_prev, z) -> x`: `z` standard normal
//!   `(n, transition_noise_dim)`;
//! * `log_observation(theta, t, y_t, x) -> (n,)`: `log g(y_t | x)`;
//! * for the score, `grad_log_density(theta, t, y, x_prev, x, w) -> (p,)`: the
//!   gradient in `theta` of `sum_i w_i [log g(y_i | x_i) + log f(x_i | x_prev_i)]`
//!   over a batch of rows (`t`, `y` `(R, q)`, `x_prev` and `x` `(R, d)`, `w` `(R,)`);
//!   `x_prev` is `None` for the rows at `t = 0`, where the transition's term is the
//!   prior's `log p(x_0)` (its gradient is zero for a prior free of `theta`).
//!
//! Rust draws every standard-normal `z` from the same per-object streams the
//! built-in models use, so a Python model that maps noise to states as a built-in
//! model does gets the built-in model's particles and log-likelihood on the same seed.
//!
//! The filter is the crate's [`filter_object`]; a callback's exception or a wrong
//! return value is kept, the remaining callbacks of the run are skipped, and it is
//! raised after the filter returns, with the callback, object and step named.

use std::sync::Mutex;

use numpy::ndarray::Array2;
use numpy::{PyArray1, PyArray2, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rand::rngs::SmallRng;
use rand::Rng;
use rand_distr::StandardNormal;

use ssm::filter::{filter_object, FilterConfig, LagView, Observer, StepView};
use ssm::models::{Batch, Drawn, ParticleModel};

use crate::convert::{check, float_array, guard};
use crate::sampling::sampling;

pyo3::create_exception!(
    pfsefi,
    CallbackError,
    pyo3::exceptions::PyRuntimeError,
    "A callback of a Python-defined model raised an exception (its `__cause__`)."
);

/// A Python model object with its parameters and one batch of observations.
struct PyModel {
    obj: Py<PyAny>,
    theta: Py<PyAny>,
    /// Observations per object, `steps * q` row-major.
    ys: Vec<Vec<f64>>,
    steps: usize,
    q: usize,
    d: usize,
    prior_noise: usize,
    transition_noise: usize,
    /// The first failure of a callback; later callbacks are skipped.
    error: Mutex<Option<PyErr>>,
}

/// Row-major `(rows, cols)` values into a float64 NumPy array.
fn matrix<'py>(py: Python<'py>, rows: usize, cols: usize, v: Vec<f64>) -> Bound<'py, PyArray2<f64>> {
    PyArray2::from_owned_array(py, Array2::from_shape_vec((rows, cols), v).expect("rows * cols values"))
}

impl PyModel {
    fn failed(&self) -> bool {
        self.error.lock().map(|e| e.is_some()).unwrap_or(true)
    }

    fn fail(&self, err: PyErr) {
        if let Ok(mut slot) = self.error.lock() {
            if slot.is_none() {
                *slot = Some(err);
            }
        }
    }

    /// Calls `self.obj.<name>(*args)` and reads the result as float64 values of
    /// shape `expected` (`(n, 1)` also taken as `(n,)` and back).
    fn call<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        args: impl pyo3::call::PyCallArgs<'py>,
        expected: &[usize],
        place: &str,
    ) -> PyResult<Vec<f64>> {
        let out = self.obj.bind(py).call_method1(name, args).map_err(|e| {
            let err = CallbackError::new_err(format!("model.{name} raised {} ({place})", describe(py, &e)));
            err.set_cause(py, Some(e));
            err
        })?;
        let arr = match out.extract::<PyReadonlyArrayDyn<'_, f64>>() {
            Ok(a) => a,
            Err(_) => {
                let np = py.import("numpy")?;
                let a = np.call_method1("asarray", (&out,)).map_err(|e| {
                    PyTypeError::new_err(format!("model.{name} returned something that is not an array ({place}): {e}"))
                })?;
                let kind = a.getattr("dtype")?.getattr("kind")?.extract::<String>()?;
                if kind != "f" && kind != "i" && kind != "u" {
                    return Err(PyTypeError::new_err(format!(
                        "model.{name} returned an array of dtype {} ({place}); expected float64",
                        a.getattr("dtype")?.str()?
                    )));
                }
                np.call_method1("ascontiguousarray", (&a, "float64"))?.extract()?
            }
        };
        let shape = arr.shape();
        let total: usize = expected.iter().product();
        let same = shape == expected
            || (expected.len() == 2 && expected[1] == 1 && shape == [expected[0]])
            || (expected.len() == 1 && shape == [expected[0], 1]);
        if !same {
            return Err(PyValueError::new_err(format!(
                "model.{name} returned shape {shape:?} ({place}); expected {expected:?}"
            )));
        }
        let v = match arr.as_slice() {
            Ok(s) => s.to_vec(),
            Err(_) => arr.as_array().iter().copied().collect(),
        };
        debug_assert_eq!(v.len(), total);
        if let Some(i) = v.iter().position(|x| x.is_nan()) {
            return Err(PyValueError::new_err(format!("model.{name} returned NaN at flat index {i} ({place})")));
        }
        Ok(v)
    }

    /// Runs `f` with the GIL unless an earlier callback failed; keeps its error.
    fn with_python(&self, f: impl FnOnce(Python<'_>) -> PyResult<()>) -> bool {
        if self.failed() {
            return false;
        }
        match Python::attach(f) {
            Ok(()) => true,
            Err(e) => {
                self.fail(e);
                false
            }
        }
    }

    fn y_row(&self, object: usize, t: usize) -> &[f64] {
        &self.ys[object][t * self.q..(t + 1) * self.q]
    }
}

/// `TypeName: message` of a Python exception.
fn describe(py: Python<'_>, e: &PyErr) -> String {
    let name = e.get_type(py).name().map(|n| n.to_string()).unwrap_or_else(|_| "an exception".into());
    format!("{name}: {}", e.value(py))
}

/// Dimension-major `d x n` f32 values as row-major `(n, d)` f64.
fn rows_of(dm: &[f32], n: usize, d: usize) -> Vec<f64> {
    let mut v = vec![0.0; n * d];
    for k in 0..d {
        for i in 0..n {
            v[i * d + k] = dm[k * n + i] as f64;
        }
    }
    v
}

/// Row-major `(n, d)` f64 values into dimension-major f32 `out`.
fn store_rows(rows: &[f64], n: usize, d: usize, out: &mut [f32]) {
    for k in 0..d {
        for i in 0..n {
            out[k * n + i] = rows[i * d + k] as f32;
        }
    }
}

impl ParticleModel for PyModel {
    type Scratch = ();

    fn new_scratch(&self) {}

    fn state_dim(&self) -> usize {
        self.d
    }

    fn action_dim(&self) -> usize {
        self.transition_noise
    }

    fn num_objects(&self) -> usize {
        self.ys.len()
    }

    fn num_steps(&self) -> usize {
        self.steps
    }

    fn sample_prior(&self, object: usize, n: usize, rng: &mut SmallRng, states: &mut [f32], _: &mut ()) {
        let z: Vec<f64> = (0..n * self.prior_noise).map(|_| rng.sample::<f64, _>(StandardNormal)).collect();
        let ok = self.with_python(|py| {
            let z = matrix(py, n, self.prior_noise, z);
            let place = format!("object {object}, t = 0");
            let x = self.call(py, "prior", (self.theta.bind(py), z), &[n, self.d], &place)?;
            store_rows(&x, n, self.d, states);
            Ok(())
        });
        if !ok {
            states.fill(0.0);
        }
    }

    fn propagate(&self, at: Batch, prev: &[f32], to: Drawn<'_>, rng: &mut SmallRng, _: &mut ()) {
        let (n, m) = (at.n, self.transition_noise);
        let z: Vec<f32> = (0..n * m).map(|_| rng.sample::<f32, _>(StandardNormal)).collect();
        // The actions are the noise, dimension-major.
        for k in 0..m {
            for i in 0..n {
                to.actions[k * n + i] = z[i * m + k];
            }
        }
        let ok = self.with_python(|py| {
            let zp = matrix(py, n, m, z.iter().map(|&v| v as f64).collect());
            let xp = matrix(py, n, self.d, rows_of(prev, n, self.d));
            let place = format!("object {}, t = {}", at.object, at.t);
            let x = self.call(py, "transition", (self.theta.bind(py), at.t, xp, zp), &[n, self.d], &place)?;
            store_rows(&x, n, self.d, to.next);
            Ok(())
        });
        if !ok {
            to.next.fill(0.0);
        }
    }

    fn observation_loglik(&self, at: Batch, states: &[f32], out: &mut [f32], _: &mut ()) -> bool {
        let n = at.n;
        let ok = self.with_python(|py| {
            let y = PyArray1::from_slice(py, self.y_row(at.object, at.t));
            let x = matrix(py, n, self.d, rows_of(states, n, self.d));
            let place = format!("object {}, t = {}", at.object, at.t);
            let lw = self.call(py, "log_observation", (self.theta.bind(py), at.t, y, x), &[n], &place)?;
            for (o, v) in out.iter_mut().zip(lw) {
                *o = v as f32;
            }
            Ok(())
        });
        if !ok {
            out.fill(0.0);
        }
        true
    }

    fn observation_count(&self, _object: usize, _t: usize) -> usize {
        self.q
    }
}

/// The distinct fixed-lag ancestors of one object, row-major, split into the rows
/// at `t = 0` and those at `t >= 1`.
#[derive(Default)]
struct Rows {
    d: usize,
    first_x: Vec<f64>,
    first_w: Vec<f64>,
    t: Vec<i64>,
    prev: Vec<f64>,
    x: Vec<f64>,
    w: Vec<f64>,
    collect: bool,
}

impl Observer for Rows {
    fn step(&mut self, _view: &StepView<'_>) {}

    fn smoothed(&mut self, view: &LagView<'_>) {
        if !self.collect {
            return;
        }
        let (n, d) = (view.n, self.d);
        for (i, &w) in view.weights.iter().enumerate() {
            if w <= 0.0 {
                continue;
            }
            match view.prev_states {
                None => {
                    self.first_w.push(w);
                    self.first_x.extend((0..d).map(|k| view.states[k * n + i] as f64));
                }
                Some(prev) => {
                    let p = view.parents[i];
                    self.t.push(view.t as i64);
                    self.w.push(w);
                    self.x.extend((0..d).map(|k| view.states[k * n + i] as f64));
                    self.prev.extend((0..d).map(|k| prev[k * n + p] as f64));
                }
            }
        }
    }
}

/// What one run returns before it becomes a dict.
struct RunResult {
    loglik: f64,
    score: Vec<f64>,
    rows: usize,
    collapsed: usize,
}

fn run(model: &PyModel, config: &FilterConfig, params: usize, score: bool) -> PyResult<RunResult> {
    let mut result = RunResult { loglik: 0.0, score: vec![0.0; params], rows: 0, collapsed: 0 };
    for object in 0..model.num_objects() {
        let mut rows = Rows { d: model.d, collect: score, ..Rows::default() };
        let (summary, _) = filter_object(model, config, object, &mut (), &mut rows);
        if let Some(e) = model.error.lock().ok().and_then(|mut e| e.take()) {
            return Err(e);
        }
        result.loglik += summary.log_likelihood;
        result.collapsed += summary.collapsed_steps;
        if !score {
            continue;
        }
        result.rows += rows.first_w.len() + rows.w.len();
        Python::attach(|py| -> PyResult<()> {
            let theta = model.theta.bind(py);
            let (d, q) = (model.d, model.q);
            let mut add = |g: Vec<f64>| {
                for (a, b) in result.score.iter_mut().zip(g) {
                    *a += b;
                }
            };
            let r0 = rows.first_w.len();
            if r0 > 0 {
                let t = PyArray1::from_vec(py, vec![0i64; r0]);
                let y = matrix(py, r0, q, (0..r0).flat_map(|_| model.y_row(object, 0).to_vec()).collect());
                let x = matrix(py, r0, d, std::mem::take(&mut rows.first_x));
                let w = PyArray1::from_vec(py, std::mem::take(&mut rows.first_w));
                let place = format!("object {object}, the {r0} rows at t = 0");
                add(model.call(py, "grad_log_density", (theta, t, y, py.None(), x, w), &[params], &place)?);
            }
            let r1 = rows.w.len();
            if r1 > 0 {
                let y =
                    matrix(py, r1, q, rows.t.iter().flat_map(|&t| model.y_row(object, t as usize).to_vec()).collect());
                let t = PyArray1::from_vec(py, std::mem::take(&mut rows.t));
                let prev = matrix(py, r1, d, std::mem::take(&mut rows.prev));
                let x = matrix(py, r1, d, std::mem::take(&mut rows.x));
                let w = PyArray1::from_vec(py, std::mem::take(&mut rows.w));
                let place = format!("object {object}, the {r1} rows at t >= 1");
                add(model.call(py, "grad_log_density", (theta, t, y, prev, x, w), &[params], &place)?);
            }
            Ok(())
        })?;
    }
    Ok(result)
}

/// A non-negative integer attribute of the model object, or `default`.
fn dim_attr(model: &Bound<'_, PyAny>, name: &str, default: Option<usize>) -> PyResult<usize> {
    match model.getattr(name) {
        Ok(v) => {
            let d: usize = v.extract().map_err(|_| {
                PyTypeError::new_err(format!(
                    "model.{name}: expected a positive integer, got {}",
                    v.repr().map(|r| r.to_string()).unwrap_or_default()
                ))
            })?;
            check(d > 0, &format!("model.{name}"), || "must be at least 1".into())?;
            Ok(d)
        }
        Err(_) => default
            .ok_or_else(|| PyTypeError::new_err(format!("model: has no attribute {name:?} (the state's dimension)"))),
    }
}

/// Runs the particle filter on a model written in Python and, with `score=True`,
/// PF-SEFI's score from its distinct fixed-lag ancestors.
///
/// `model`: an object with `state_dim`, `prior`, `transition`, `log_observation`
/// and (for the score) `grad_log_density` (see the module docs and `pfsefi.Model`).
/// `y`: observations of shape `(steps,)`, `(steps, q)` (one object) or
/// `(objects, steps, q)`. `theta`: the parameter vector, shape `(p,)`, handed to
/// every callback. Returns a dict with `loglik` (summed over objects), `score`
/// (shape `(p,)`, with `score=True`), `rows_evaluated` (distinct ancestors) and
/// `collapsed_steps`.
#[pyfunction]
#[pyo3(signature = (model, y, theta, particles = 256, lag = 10, seed = 0, score = true,
                    resampling = "systematic", ess_threshold = None))]
#[allow(clippy::too_many_arguments)]
pub fn particle_filter<'py>(
    py: Python<'py>,
    model: &Bound<'py, PyAny>,
    y: &Bound<'py, PyAny>,
    theta: &Bound<'py, PyAny>,
    particles: usize,
    lag: usize,
    seed: u64,
    score: bool,
    resampling: &str,
    ess_threshold: Option<f64>,
) -> PyResult<Bound<'py, PyDict>> {
    let sampling = sampling(particles, resampling, ess_threshold)?;
    let d = dim_attr(model, "state_dim", None)?;
    let prior_noise = dim_attr(model, "prior_noise_dim", Some(d))?;
    let transition_noise = dim_attr(model, "transition_noise_dim", Some(d))?;
    for name in
        ["prior", "transition", "log_observation"].iter().chain(if score { &["grad_log_density"][..] } else { &[] })
    {
        let ok = model.getattr(*name).map(|f| f.is_callable()).unwrap_or(false);
        if !ok {
            return Err(PyTypeError::new_err(format!("model: has no method {name:?}")));
        }
    }
    let ya = float_array(py, y, "y")?;
    let (objects, steps, q) = match ya.shape[..] {
        [s] => (1, s, 1),
        [s, q] => (1, s, q),
        [k, s, q] => (k, s, q),
        _ => {
            return Err(PyValueError::new_err(format!(
                "y: expected shape (steps,), (steps, q) or (objects, steps, q), got {:?}",
                ya.shape
            )))
        }
    };
    let th = float_array(py, theta, "theta")?;
    check(th.shape.len() == 1, "theta", || format!("expected a vector (p,), got shape {:?}", th.shape))?;
    let params = th.data.len();
    let theta_arr = PyArray1::from_vec(py, th.data);
    theta_arr.readwrite().make_nonwriteable();
    let ys: Vec<Vec<f64>> = ya.data.chunks(steps * q).map(|c| c.to_vec()).collect();
    let pm = PyModel {
        obj: model.clone().unbind(),
        theta: theta_arr.into_any().unbind(),
        ys,
        steps,
        q,
        d,
        prior_noise,
        transition_noise,
        error: Mutex::new(None),
    };
    debug_assert_eq!(pm.ys.len(), objects);
    let config = FilterConfig::new(sampling, lag, seed);
    let r = py.detach(|| guard("particle_filter", || run(&pm, &config, params, score)))?;
    let out = PyDict::new(py);
    out.set_item("loglik", r.loglik)?;
    if score {
        out.set_item("score", PyArray1::from_vec(py, r.score))?;
        out.set_item("rows_evaluated", r.rows)?;
    }
    out.set_item("collapsed_steps", r.collapsed)?;
    Ok(out)
}
