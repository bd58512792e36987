//! The vehicle model on a synthetic scene from Python: the PF-SEFI (or any
//! estimator's) score as a dict by parameter name, and the same call timed inside
//! Rust, so a benchmark can state what the Python call adds.

use std::time::Instant;

use numpy::{PyArray, PyArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rand::rngs::StdRng;
use rand::SeedableRng;

use ssm::data::Dataset;
use ssm::estimators::{Estimator, EstimatorConfig, Precision, ScoreEstimate, ScoreEstimator};
use ssm::models::road_user::VehicleSsm;
use ssm::models::vehicle::policy::HandCraftedPolicy;
use ssm::models::DifferentiableModel;
use ssm::simulation::synthetic::{generate_dataset, SceneConfig, TrueModel};

use crate::convert::{check, guard};
use crate::sampling::sampling;

/// One synthetic scene of the paper's setting (point observations of vehicles)
/// with the true model that drives it: the hand-crafted policy and an unfitted
/// observation network (as the estimator benchmark builds its sizes A and B).
#[pyclass(module = "pfsefi", name = "SyntheticScene", frozen)]
pub struct SyntheticScene {
    truth: TrueModel,
    data: Dataset,
}

struct Settings {
    estimator: Estimator,
    config: EstimatorConfig,
    seed: u64,
}

impl SyntheticScene {
    fn run(&self, s: &Settings) -> PyResult<(ScoreEstimate, Vec<String>, f64)> {
        let t0 = Instant::now();
        let model = VehicleSsm::new(&self.data, &self.truth.policy, &self.truth.obs, &self.truth.params)
            .map_err(|e| PyValueError::new_err(format!("SyntheticScene: model: {e}")))?;
        let e = s.estimator.estimate(&model, &s.config, s.seed);
        let secs = t0.elapsed().as_secs_f64();
        Ok((e, model.parameter_names(), secs))
    }
}

fn settings(
    estimator: &str,
    particles: usize,
    lag: usize,
    seed: u64,
    precision: &str,
    alpha: f64,
) -> PyResult<Settings> {
    let estimator =
        Estimator::parse(estimator, lag, alpha).map_err(|e| PyValueError::new_err(format!("estimator: {e}")))?;
    let precision = match precision {
        "f64" => Precision::F64,
        "f32" => Precision::F32,
        other => return Err(PyValueError::new_err(format!("precision: expected 'f64' or 'f32', got {other:?}"))),
    };
    let config = EstimatorConfig { sampling: sampling(particles, "systematic", None)?, chunk_objects: 4, precision };
    Ok(Settings { estimator, config, seed })
}

fn to_dict<'py>(py: Python<'py>, e: &ScoreEstimate, names: &[String]) -> PyResult<Bound<'py, PyDict>> {
    let out = PyDict::new(py);
    out.set_item("loglik", e.log_likelihood)?;
    let score = PyDict::new(py);
    for (name, g) in names.iter().zip(&e.gradient) {
        let arr = PyArray::from_vec(py, g.data().to_vec()).reshape(g.shape().to_vec())?;
        score.set_item(name, arr)?;
    }
    out.set_item("score", score)?;
    out.set_item("observed_units", e.observed_units)?;
    out.set_item("rows_evaluated", e.rows_evaluated)?;
    out.set_item("particle_slots", e.particle_slots)?;
    out.set_item("collapsed_steps", e.collapsed_steps)?;
    Ok(out)
}

#[pymethods]
impl SyntheticScene {
    /// A scene of `transitions` steps (`T`; the benchmark's size A is 25, B 50)
    /// drawn with `seed` (the benchmark's is 3).
    #[new]
    #[pyo3(signature = (transitions = 25, seed = 3))]
    fn new(py: Python<'_>, transitions: usize, seed: u64) -> PyResult<Self> {
        check(transitions > 0, "transitions", || "must be at least 1".into())?;
        py.detach(move || {
            guard("SyntheticScene", || {
                let mut rng = StdRng::seed_from_u64(seed);
                let truth = TrueModel::init(HandCraftedPolicy::truth(), &mut rng);
                let scene = SceneConfig::paper(transitions + 1);
                let data = generate_dataset(&scene, &truth, &[0], &mut rng)
                    .map_err(|e| PyValueError::new_err(format!("SyntheticScene: {e}")))?;
                Ok(SyntheticScene { truth, data })
            })
        })
    }

    /// The true parameters as a dict of float64 arrays by name.
    #[getter]
    fn parameters<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let out = PyDict::new(py);
        for (name, t) in self.truth.params.iter() {
            out.set_item(name, PyArray::from_vec(py, t.data().to_vec()).reshape(t.shape().to_vec())?)?;
        }
        Ok(out)
    }

    /// Number of objects (vehicles) in the scene.
    #[getter]
    fn num_objects(&self) -> usize {
        self.data.objects().len()
    }

    /// The score of every object under the true parameters: a dict with `loglik`,
    /// `score` (a dict of arrays by parameter name), `observed_units`,
    /// `rows_evaluated`, `particle_slots` and `collapsed_steps`.
    #[pyo3(signature = (estimator = "pf-sefi", particles = 1024, lag = 8, seed = 1, precision = "f32", alpha = 0.8))]
    #[allow(clippy::too_many_arguments)]
    fn score<'py>(
        &self,
        py: Python<'py>,
        estimator: &str,
        particles: usize,
        lag: usize,
        seed: u64,
        precision: &str,
        alpha: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        let s = settings(estimator, particles, lag, seed, precision, alpha)?;
        let (e, names, _) = py.detach(|| guard("SyntheticScene.score", || self.run(&s)))?;
        to_dict(py, &e, &names)
    }

    /// As `score`, and the seconds the estimate took inside Rust (model built,
    /// estimated; no Python objects made): `(result, rust_seconds)`.
    #[pyo3(signature = (estimator = "pf-sefi", particles = 1024, lag = 8, seed = 1, precision = "f32", alpha = 0.8))]
    #[allow(clippy::too_many_arguments)]
    fn score_timed<'py>(
        &self,
        py: Python<'py>,
        estimator: &str,
        particles: usize,
        lag: usize,
        seed: u64,
        precision: &str,
        alpha: f64,
    ) -> PyResult<(Bound<'py, PyDict>, f64)> {
        let s = settings(estimator, particles, lag, seed, precision, alpha)?;
        let (e, names, secs) = py.detach(|| guard("SyntheticScene.score_timed", || self.run(&s)))?;
        Ok((to_dict(py, &e, &names)?, secs))
    }

    /// Writes the true parameters as a project parameter file (bincode, as the
    /// `sefi` CLI reads).
    fn save_params(&self, path: std::path::PathBuf) -> PyResult<()> {
        self.truth.params.save(&path).map_err(crate::params::param_error)
    }
}
