//! The built-in linear-Gaussian model from Python: simulation, the exact Kalman
//! log-likelihood and score, and every particle estimator's score.
//!
//! `x_0 ~ N(m0, P0)`, `x_t = phi x_{t-1} + s_v e_t`, `y_t = x_t + s_w u_t`; the
//! parameter vector is `theta = [phi, ln s_v, ln s_w]`.

use numpy::{PyArray1, PyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rand::rngs::SmallRng;
use rand::SeedableRng;

use ssm::estimators::{Estimator, EstimatorConfig, Precision, ScoreEstimator};
use ssm::filter::stream_seed;
use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmTheta};
use ssm::models::linear_gaussian::particles::LgssmBatch;

use crate::convert::{check, finite, float_array, guard};
use crate::sampling::sampling;

/// Observation sequences `y` as `(objects, steps)`: a 1-d array is one object.
pub fn sequences(py: Python<'_>, y: &Bound<'_, PyAny>) -> PyResult<Vec<Vec<f64>>> {
    let a = float_array(py, y, "y")?;
    match a.shape.len() {
        1 => Ok(vec![a.data]),
        2 => Ok(a.data.chunks(a.shape[1]).map(|c| c.to_vec()).collect()),
        n => Err(PyValueError::new_err(format!(
            "y: expected shape (steps,) or (objects, steps), got {n} dimensions {:?}",
            a.shape
        ))),
    }
}

/// Two arrays returned together (`(x, y)`, `(mean, var)`).
type Pair<'py, A> = (Bound<'py, A>, Bound<'py, A>);

/// The scalar linear-Gaussian state-space model
/// `x_0 ~ N(m0, P0)`, `x_t = phi x_{t-1} + sv e_t`, `y_t = x_t + sw u_t`.
///
/// Without `m0` and `p0` the prior is the stationary law `N(0, sv^2 / (1 - phi^2))`
/// (which needs `|phi| < 1`). Its parameter vector, the one every score is taken
/// with respect to, is `theta = [phi, ln sv, ln sw]`.
#[pyclass(module = "pfsefi", name = "LinearGaussian", frozen)]
pub struct LinearGaussian {
    model: Lgssm,
}

fn build(phi: f64, sv: f64, sw: f64, m0: Option<f64>, p0: Option<f64>) -> PyResult<Lgssm> {
    finite("phi", phi)?;
    check(finite("sv", sv)? > 0.0, "sv", || format!("must be > 0, got {sv}"))?;
    check(finite("sw", sw)? > 0.0, "sw", || format!("must be > 0, got {sw}"))?;
    let theta = LgssmTheta::new(phi, sv, sw);
    let model = match (m0, p0) {
        (None, None) => Lgssm::stationary(theta),
        (Some(m0), Some(p0)) => Lgssm::new(finite("m0", m0)?, finite("p0", p0)?, theta),
        _ => return Err(PyValueError::new_err("m0 and p0: give both or neither (neither: the stationary prior)")),
    };
    model.map_err(|e| PyValueError::new_err(format!("LinearGaussian: {e}")))
}

#[pymethods]
impl LinearGaussian {
    #[new]
    #[pyo3(signature = (phi, sv, sw, m0 = None, p0 = None))]
    fn new(phi: f64, sv: f64, sw: f64, m0: Option<f64>, p0: Option<f64>) -> PyResult<Self> {
        Ok(LinearGaussian { model: build(phi, sv, sw, m0, p0)? })
    }

    /// The model with parameter vector `theta = [phi, ln sv, ln sw]` and the same
    /// prior (`m0`, `p0`) as this one.
    fn with_theta(&self, py: Python<'_>, theta: &Bound<'_, PyAny>) -> PyResult<Self> {
        let t = float_array(py, theta, "theta")?;
        check(t.shape == [3], "theta", || format!("expected shape (3,) = [phi, ln sv, ln sw], got {:?}", t.shape))?;
        let theta = LgssmTheta::from_array([t.data[0], t.data[1], t.data[2]]);
        let model = self.model.with_theta(theta).map_err(|e| PyValueError::new_err(format!("theta: {e}")))?;
        Ok(LinearGaussian { model })
    }

    /// `theta = [phi, ln sv, ln sw]` as a float64 array.
    #[getter]
    fn theta<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.model.theta().to_array())
    }

    /// The prior mean `m0`.
    #[getter]
    fn m0(&self) -> f64 {
        self.model.m0()
    }

    /// The prior variance `P0`.
    #[getter]
    fn p0(&self) -> f64 {
        self.model.p0()
    }

    fn __repr__(&self) -> String {
        let t = self.model.theta();
        format!(
            "LinearGaussian(phi={}, sv={}, sw={}, m0={}, p0={})",
            t.phi,
            t.sv(),
            t.sw(),
            self.model.m0(),
            self.model.p0()
        )
    }

    /// Simulates `objects` independent sequences of `steps` steps (`t = 0..steps`).
    /// Returns `(x, y)`, each of shape `(objects, steps)`. Object `k` draws from its
    /// own stream of `seed`, so it does not depend on how many objects are drawn.
    #[pyo3(signature = (steps, objects = 1, seed = 0))]
    fn simulate<'py>(
        &self,
        py: Python<'py>,
        steps: usize,
        objects: usize,
        seed: u64,
    ) -> PyResult<Pair<'py, PyArray2<f64>>> {
        check(steps > 0, "steps", || "must be at least 1".into())?;
        check(objects > 0, "objects", || "must be at least 1".into())?;
        let model = self.model.clone();
        let (xs, ys) = py.detach(move || {
            let mut xs = Vec::with_capacity(objects);
            let mut ys = Vec::with_capacity(objects);
            for k in 0..objects {
                let mut rng = SmallRng::seed_from_u64(stream_seed(seed, k as u64));
                let s = model.simulate(steps, &mut rng);
                xs.push(s.xs);
                ys.push(s.ys);
            }
            (xs, ys)
        });
        Ok((
            PyArray2::from_vec2(py, &xs).expect("rows of equal length"),
            PyArray2::from_vec2(py, &ys).expect("rows of equal length"),
        ))
    }

    /// The exact log-likelihood `log p(y)` by the Kalman filter, summed over objects.
    /// `y`: shape `(steps,)` (one object) or `(objects, steps)`.
    fn kalman_loglik(&self, py: Python<'_>, y: &Bound<'_, PyAny>) -> PyResult<f64> {
        let seqs = sequences(py, y)?;
        let model = self.model.clone();
        py.detach(move || {
            guard("LinearGaussian.kalman_loglik", || Ok(seqs.iter().map(|s| model.log_likelihood(s)).sum()))
        })
    }

    /// The exact log-likelihood and score `d log p(y) / d theta`
    /// (`theta = [phi, ln sv, ln sw]`), summed over objects: `(loglik, score)`.
    fn kalman_score<'py>(&self, py: Python<'py>, y: &Bound<'py, PyAny>) -> PyResult<(f64, Bound<'py, PyArray1<f64>>)> {
        let seqs = sequences(py, y)?;
        let model = self.model.clone();
        let (ll, g) = py.detach(move || {
            guard("LinearGaussian.kalman_score", || {
                let mut ll = 0.0;
                let mut g = [0.0; 3];
                for s in &seqs {
                    let (l, gs) = model.score(s);
                    ll += l;
                    for (a, b) in g.iter_mut().zip(gs) {
                        *a += b;
                    }
                }
                Ok((ll, g))
            })
        })?;
        Ok((ll, PyArray1::from_slice(py, &g)))
    }

    /// The Kalman smoother of one sequence `y` (shape `(steps,)`): the smoothed
    /// means and variances of `x_t`, `(mean, var)`.
    fn kalman_smooth<'py>(&self, py: Python<'py>, y: &Bound<'py, PyAny>) -> PyResult<Pair<'py, PyArray1<f64>>> {
        let seqs = sequences(py, y)?;
        check(seqs.len() == 1, "y", || {
            format!("kalman_smooth takes one sequence (shape (steps,)), got {} objects", seqs.len())
        })?;
        let s = self.model.smooth(&seqs[0]);
        Ok((PyArray1::from_vec(py, s.mean), PyArray1::from_vec(py, s.var)))
    }

    /// A particle estimate of the score of `y` (shape `(steps,)` or
    /// `(objects, steps)`), summed over objects.
    ///
    /// `estimator`: `"pf-sefi"` (fixed lag `lag`), `"pf"`, `"dpf-sgr"`,
    /// `"dpf-sgr-stopped"` or `"pfnet"` (mixing `alpha`). `precision`: `"f64"` or
    /// `"f32"` for the estimator's tape. `resampling`: `"systematic"` or
    /// `"multinomial"`; `ess_threshold` resamples only below that fraction of the
    /// particles. Returns a dict with `loglik` (the filter's estimate), `score`
    /// (float64 array of 3), `rows_evaluated`, `particle_slots`, `collapsed_steps`
    /// and `estimator`.
    #[pyo3(signature = (y, estimator = "pf-sefi", particles = 256, lag = 10, seed = 0, precision = "f64",
                        alpha = 0.5, resampling = "systematic", ess_threshold = None))]
    #[allow(clippy::too_many_arguments)]
    fn score<'py>(
        &self,
        py: Python<'py>,
        y: &Bound<'py, PyAny>,
        estimator: &str,
        particles: usize,
        lag: usize,
        seed: u64,
        precision: &str,
        alpha: f64,
        resampling: &str,
        ess_threshold: Option<f64>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let seqs = sequences(py, y)?;
        let est =
            Estimator::parse(estimator, lag, alpha).map_err(|e| PyValueError::new_err(format!("estimator: {e}")))?;
        let precision = match precision {
            "f64" => Precision::F64,
            "f32" => Precision::F32,
            other => return Err(PyValueError::new_err(format!("precision: expected 'f64' or 'f32', got {other:?}"))),
        };
        let steps = seqs[0].len();
        let batch = LgssmBatch::new(self.model.clone(), seqs)
            .map_err(|e| PyValueError::new_err(format!("y: every sequence must have the same {steps} steps ({e})")))?;
        let config =
            EstimatorConfig { sampling: sampling(particles, resampling, ess_threshold)?, chunk_objects: 4, precision };
        let e = py.detach(move || guard("LinearGaussian.score", || Ok(est.estimate(&batch, &config, seed))))?;
        let out = PyDict::new(py);
        out.set_item("loglik", e.log_likelihood)?;
        out.set_item("score", PyArray1::from_slice(py, e.gradient[0].data()))?;
        out.set_item("rows_evaluated", e.rows_evaluated)?;
        out.set_item("particle_slots", e.particle_slots)?;
        out.set_item("collapsed_steps", e.collapsed_steps)?;
        out.set_item("estimator", est.name())?;
        Ok(out)
    }
}
