//! The vehicle model of a dataset and a parameter file from Python: the
//! particle filter and fixed-lag smoother (log-likelihood per object, filtered
//! and smoothed states as arrays), any estimator's score as a dict by parameter
//! name, the evaluation metrics (SPEC §5), training with a progress callback,
//! and the diagnosis with its report as a dict.
//!
//! The filters follow `sefi`'s defaults: the tempered filter for evaluation
//! and for PF-SEFI's training score ([`Tempering::for_observations`]), the
//! bootstrap filter for the through-filter baselines; `filter="bootstrap"`
//! asks for the bootstrap filter everywhere.

use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use autodiff::nn::ParamStore;
use numpy::{PyArray, PyArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyString};

use ssm::criticism::diagnose::{diagnose, diagnose_split, DiagnoseConfig, Protocol};
use ssm::data::{Dataset, ObservationKind, State};
use ssm::estimators::{Estimator, EstimatorConfig, Precision, ScoreEstimate, ScoreEstimator};
use ssm::evaluation::metrics::{self, Tracks, EVAL_LAG, EVAL_PARTICLES};
use ssm::filter::{FilterConfig, FilterPurpose, Sampling, Tempering};
use ssm::models::extended::ExtensibleObservation;
use ssm::models::params::{AnyPolicy, Models, ObservationVisitor};
use ssm::models::road_user::VehicleSsm;
use ssm::models::vehicle::{HandCraftedPolicy, NeuralPolicy};
use ssm::models::DifferentiableModel;
use ssm::training::objective::{ObjectiveConfig, SceneObjective};
use ssm::training::{self, BatchEstimate, EstimateError, Objective, TrainConfig, TrainEvent};
use ssm::util::reduce::{Collective, SingleProcess};

use crate::convert::{check, finite, guard};
use crate::dataset::PyDataset;
use crate::params::{load, save, store_from_dict, store_to_dict};

/// The vehicle model of one dataset: a policy and an observation model (with
/// any extension or detector drift the parameter file holds) and the data it
/// filters.
#[pyclass(module = "pfsefi", name = "VehicleModel", frozen)]
pub struct VehicleModel {
    data: Dataset,
    store: ParamStore<f64>,
    models: Models,
}

/// Which filter: the rule's tempered filter for `purpose`, or the bootstrap one.
fn tempering(filter: &str, kind: ObservationKind, purpose: FilterPurpose) -> PyResult<Option<Tempering>> {
    match filter {
        "tempered" => Ok(Some(Tempering::for_observations(kind, purpose))),
        "bootstrap" => Ok(None),
        other => Err(PyValueError::new_err(format!("filter: expected 'tempered' or 'bootstrap', got {other:?}"))),
    }
}

fn precision(name: &str) -> PyResult<Precision> {
    match name {
        "f64" => Ok(Precision::F64),
        "f32" => Ok(Precision::F32),
        other => Err(PyValueError::new_err(format!("precision: expected 'f64' or 'f32', got {other:?}"))),
    }
}

fn estimator(name: &str, lag: usize, alpha: f64) -> PyResult<Estimator> {
    Estimator::parse(name, lag, finite("alpha", alpha)?).map_err(|e| PyValueError::new_err(format!("estimator: {e}")))
}

fn positive(name: &str, n: usize) -> PyResult<usize> {
    check(n > 0, name, || "must be at least 1".into())?;
    Ok(n)
}

/// Every object's states as one `(objects, steps, 5)` array.
fn states_array<'py>(py: Python<'py>, states: &[Vec<State>], steps: usize) -> PyResult<Bound<'py, PyAny>> {
    let data: Vec<f64> = states.iter().flat_map(|o| o.iter().flat_map(|s| s.to_array())).collect();
    Ok(PyArray::from_vec(py, data).reshape(vec![states.len(), steps, 5])?.into_any())
}

/// A JSON value as a Python object (through `json.loads`).
fn json_to_py<'py>(py: Python<'py>, value: &impl serde::Serialize) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value).map_err(|e| PyRuntimeError::new_err(format!("serialising: {e}")))?;
    py.import("json")?.call_method1("loads", (text,))
}

fn read_store(py: Python<'_>, params: &Bound<'_, PyAny>) -> PyResult<ParamStore<f64>> {
    if let Ok(dict) = params.cast::<PyDict>() {
        return store_from_dict(py, dict);
    }
    let path: PathBuf = params.extract().map_err(|_| {
        pyo3::exceptions::PyTypeError::new_err("params: expected a dict of arrays by name or a parameter file's path")
    })?;
    py.detach(|| load(&path))
}

impl VehicleModel {
    /// The models `store` describes for `data`, checked by building the model
    /// once (a panic is caught, as everywhere, and raised as `RuntimeError`).
    fn build(data: Dataset, store: ParamStore<f64>) -> PyResult<Self> {
        guard("VehicleModel", || Self::build_unguarded(data, store))
    }

    fn build_unguarded(data: Dataset, store: ParamStore<f64>) -> PyResult<Self> {
        let models =
            Models::from_store(&store, data.kind()).map_err(|e| PyValueError::new_err(format!("params: {e}")))?;
        // Build the model once, so that data the parameters do not fit fail here.
        struct Fits<'a> {
            data: &'a Dataset,
            models: &'a Models,
        }
        impl ObservationVisitor for Fits<'_> {
            type Output = Result<(), String>;
            fn visit<O: ExtensibleObservation>(self, o: &O) -> Self::Output {
                let m = self.models;
                let base = VehicleSsm::new(self.data, &m.policy, o, &m.observation_params)?;
                m.additions().extend(&base).map(|_| ()).map_err(|e| e.to_string())
            }
        }
        models
            .observation
            .visit(Fits { data: &data, models: &models })
            .map_err(|e| PyValueError::new_err(format!("VehicleModel: {e}")))?;
        Ok(VehicleModel { data, store, models })
    }

    fn track(&self, config: &FilterConfig) -> Result<Tracks, String> {
        metrics::track_models(&self.data, &self.models, config)
    }

    fn metrics_of(&self, tracks: &Tracks, config: &FilterConfig) -> metrics::Metrics {
        metrics::models_metrics_of(&self.data, &self.models, tracks, config)
    }

    fn estimate(
        &self,
        estimator: &Estimator,
        config: &EstimatorConfig,
        seed: u64,
    ) -> Result<(ScoreEstimate, Vec<String>), String> {
        struct Score<'a> {
            data: &'a Dataset,
            models: &'a Models,
            estimator: &'a Estimator,
            config: &'a EstimatorConfig,
            seed: u64,
        }
        impl ObservationVisitor for Score<'_> {
            type Output = Result<(ScoreEstimate, Vec<String>), String>;
            fn visit<O: ExtensibleObservation>(self, o: &O) -> Self::Output {
                let m = self.models;
                let base = VehicleSsm::new(self.data, &m.policy, o, &m.observation_params)?;
                let model = m.additions().extend(&base).map_err(|e| e.to_string())?;
                let through_filter = !matches!(self.estimator, Estimator::PfSefi(_));
                if through_filter && (model.drift().is_some() || model.flip_chain().is_some()) {
                    return Err("a detector drift or `persistent_flip` works with PF-SEFI only: the through-filter \
                                baselines would need draws the actions do not record"
                        .into());
                }
                Ok((self.estimator.estimate(&model, self.config, self.seed), model.parameter_names()))
            }
        }
        let visit = Score { data: &self.data, models: &self.models, estimator, config, seed };
        self.models.observation.visit(visit)
    }
}

/// A training objective whose steps stop once the progress callback has raised.
struct Stoppable<'a> {
    inner: SceneObjective,
    failed: &'a RefCell<Option<PyErr>>,
}

impl Objective for Stoppable<'_> {
    fn batches(&self) -> usize {
        self.inner.batches()
    }

    fn estimate(&mut self, params: &ParamStore<f64>, batch: usize, seed: u64) -> Result<BatchEstimate, EstimateError> {
        if self.failed.borrow().is_some() {
            return Err(EstimateError::Failed("the progress callback raised".into()));
        }
        self.inner.estimate(params, batch, seed)
    }

    fn evaluate(&mut self, params: &ParamStore<f64>, seed: u64) -> Result<Vec<(String, f64)>, String> {
        if self.failed.borrow().is_some() {
            return Err("the progress callback raised".into());
        }
        self.inner.evaluate(params, seed)
    }

    fn rate_factors(&self, params: &ParamStore<f64>) -> Option<Vec<f64>> {
        self.inner.rate_factors(params)
    }
}

/// A directory for a training run's files that is removed when dropped.
struct ScratchDir(PathBuf);

impl ScratchDir {
    fn new() -> Self {
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
        ScratchDir(std::env::temp_dir().join(format!("pfsefi-train-{}-{nanos}", std::process::id())))
    }
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[pymethods]
impl VehicleModel {
    /// The vehicle model of ``dataset`` under ``params``: a parameter file's path
    /// (``.npz`` or the project's format) or a dict of arrays by name, laid out
    /// as ``sefi train`` writes it (policy under ``policy``, observation network
    /// under ``obs``). The observation model follows the dataset's kind.
    #[new]
    fn new(py: Python<'_>, dataset: &PyDataset, params: &Bound<'_, PyAny>) -> PyResult<Self> {
        let store = read_store(py, params)?;
        Self::build(dataset.data.clone(), store)
    }

    /// Fresh models to learn from, as ``sefi train`` starts them: the
    /// ``hand-crafted`` policy with sds ``init_sd = (accel, pinch)`` or a
    /// ``neural`` policy drawn from ``seed``, and an observation network drawn
    /// from ``seed + 1``.
    #[staticmethod]
    #[pyo3(signature = (dataset, policy = "hand-crafted", init_sd = (1.0, 0.1), seed = 0))]
    fn initial(dataset: &PyDataset, policy: &str, init_sd: (f64, f64), seed: u64) -> PyResult<Self> {
        let policy = match policy {
            "hand-crafted" => {
                let (a, p) = init_sd;
                check(a > 0.0 && p > 0.0 && a.is_finite() && p.is_finite(), "init_sd", || {
                    format!("expected two finite sds > 0, got ({a}, {p})")
                })?;
                AnyPolicy::HandCrafted(
                    HandCraftedPolicy::new(a.ln(), p.ln())
                        .map_err(|e| PyValueError::new_err(format!("init_sd: {e}")))?,
                )
            }
            "neural" => {
                use rand::SeedableRng;
                AnyPolicy::Neural(NeuralPolicy::new(&mut rand::rngs::StdRng::seed_from_u64(seed)))
            }
            other => {
                return Err(PyValueError::new_err(format!(
                    "policy: expected 'hand-crafted' or 'neural', got {other:?}"
                )))
            }
        };
        let models = Models::initial(dataset.data.kind(), policy, seed.wrapping_add(1));
        Self::build(dataset.data.clone(), models.to_store())
    }

    /// The parameters as a dict of float64 arrays by name.
    #[getter]
    fn parameters<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        store_to_dict(py, &self.store)
    }

    /// The dataset the model filters.
    #[getter]
    fn dataset(&self) -> PyDataset {
        PyDataset { data: self.data.clone() }
    }

    /// The policy's name (``hand-crafted`` or ``neural``).
    #[getter]
    fn policy(&self) -> &'static str {
        self.models.policy.name()
    }

    /// The same parameters on another dataset (of the same kind).
    fn on(&self, dataset: &PyDataset) -> PyResult<Self> {
        Self::build(dataset.data.clone(), self.store.clone())
    }

    /// Writes the parameters as a parameter file (``.npz`` for that extension,
    /// the project's format, which ``sefi`` reads, for any other).
    fn save_params(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        py.detach(|| save(&self.store, &path))
    }

    /// Runs the particle filter and fixed-lag smoother over every object, as
    /// ``sefi track`` does: a dict with ``loglik`` (the summed estimate),
    /// ``loglik_per_object``, ``observed_units`` and ``collapsed_steps`` (per
    /// object), ``filtered`` and ``smoothed`` means (shape ``(objects, steps,
    /// 5)``, columns ``x, y, yaw, v, kappa``; yaw averaged on the circle).
    #[pyo3(signature = (particles = EVAL_PARTICLES, lag = EVAL_LAG, seed = 0, filter = "tempered"))]
    fn filter<'py>(
        &self,
        py: Python<'py>,
        particles: usize,
        lag: usize,
        seed: u64,
        filter: &str,
    ) -> PyResult<Bound<'py, PyDict>> {
        let sampling = Sampling::new(
            positive("particles", particles)?,
            tempering(filter, self.data.kind(), FilterPurpose::Evaluation)?,
        );
        let config = FilterConfig::new(sampling, lag, seed);
        let tracks = py
            .detach(|| guard("VehicleModel.filter", || Ok(self.track(&config))))?
            .map_err(|e| PyValueError::new_err(format!("VehicleModel.filter: {e}")))?;
        let out = PyDict::new(py);
        let s = &tracks.summaries;
        out.set_item("loglik", tracks.log_likelihood())?;
        out.set_item("loglik_per_object", PyArray::from_vec(py, s.iter().map(|o| o.log_likelihood).collect()))?;
        out.set_item("observed_units", PyArray::from_vec(py, s.iter().map(|o| o.observed_units as i64).collect()))?;
        out.set_item("collapsed_steps", PyArray::from_vec(py, s.iter().map(|o| o.collapsed_steps as i64).collect()))?;
        out.set_item("min_ess", PyArray::from_vec(py, s.iter().map(|o| o.min_ess).collect()))?;
        out.set_item("filtered", states_array(py, &tracks.filtered, self.data.steps())?)?;
        out.set_item("smoothed", states_array(py, &tracks.smoothed, self.data.steps())?)?;
        Ok(out)
    }

    /// The score (gradient of the log-likelihood) of every object by
    /// ``estimator`` (``pf-sefi``, ``pf``, ``dpf-sgr``, ``dpf-sgr-stopped``,
    /// ``pfnet``): a dict with ``loglik``, ``score`` (a dict of arrays by
    /// parameter name, shaped as the parameters), ``observed_units``,
    /// ``rows_evaluated``, ``particle_slots`` and ``collapsed_steps``.
    #[pyo3(signature = (estimator = "pf-sefi", particles = 1024, lag = 8, seed = 0, alpha = 0.8, precision = "f32", filter = "tempered", chunk_objects = 4))]
    #[allow(clippy::too_many_arguments)]
    fn score<'py>(
        &self,
        py: Python<'py>,
        estimator: &str,
        particles: usize,
        lag: usize,
        seed: u64,
        alpha: f64,
        precision: &str,
        filter: &str,
        chunk_objects: usize,
    ) -> PyResult<Bound<'py, PyDict>> {
        let est = self::estimator(estimator, lag, alpha)?;
        let temper = match est {
            Estimator::PfSefi(_) => tempering(filter, self.data.kind(), FilterPurpose::Training)?,
            Estimator::ThroughFilter(_) => None,
        };
        let config = EstimatorConfig {
            sampling: Sampling::new(positive("particles", particles)?, temper),
            chunk_objects: positive("chunk_objects", chunk_objects)?,
            precision: self::precision(precision)?,
        };
        let (e, names) = py
            .detach(|| guard("VehicleModel.score", || Ok(self.estimate(&est, &config, seed))))?
            .map_err(|e| PyValueError::new_err(format!("VehicleModel.score: {e}")))?;
        let out = PyDict::new(py);
        out.set_item("loglik", e.log_likelihood)?;
        let score = PyDict::new(py);
        for (name, g) in names.iter().zip(&e.gradient) {
            score.set_item(name, PyArray::from_vec(py, g.data().to_vec()).reshape(g.shape().to_vec())?)?;
        }
        out.set_item("score", score)?;
        out.set_item("observed_units", e.observed_units)?;
        out.set_item("rows_evaluated", e.rows_evaluated)?;
        out.set_item("particle_slots", e.particle_slots)?;
        out.set_item("collapsed_steps", e.collapsed_steps)?;
        Ok(out)
    }

    /// The evaluation metrics (SPEC §5) of ``runs`` filter runs (run ``r`` with
    /// seed ``seed + r``), as ``sefi eval``: a dict with ``runs`` (each run's
    /// metrics: ``mll``, ``log_likelihood``, ``observed_units``, ``smoothed``
    /// and ``filtered`` state errors ``{ade, aye, count}``, ``aotll``,
    /// ``aptll``, ...), ``summary`` (median and IQR of each scalar over the
    /// runs) and ``per_object`` (the first run's ``loglik`` and
    /// ``observed_units`` per object, as arrays). Errors against the truth are
    /// None when the dataset has none.
    #[pyo3(signature = (particles = EVAL_PARTICLES, lag = EVAL_LAG, seed = 0, runs = 1, filter = "tempered"))]
    fn evaluate<'py>(
        &self,
        py: Python<'py>,
        particles: usize,
        lag: usize,
        seed: u64,
        runs: usize,
        filter: &str,
    ) -> PyResult<Bound<'py, PyDict>> {
        let sampling = Sampling::new(
            positive("particles", particles)?,
            tempering(filter, self.data.kind(), FilterPurpose::Evaluation)?,
        );
        let base = FilterConfig::new(sampling, lag, seed);
        let runs = positive("runs", runs)?;
        let (all, first) = py
            .detach(|| {
                guard("VehicleModel.evaluate", || {
                    let mut all = Vec::with_capacity(runs);
                    let mut first = None;
                    for r in 0..runs {
                        let config = FilterConfig { seed: seed.wrapping_add(r as u64), ..base.clone() };
                        let tracks = match self.track(&config) {
                            Ok(t) => t,
                            Err(e) => return Ok(Err(e)),
                        };
                        all.push(self.metrics_of(&tracks, &config));
                        first.get_or_insert(tracks);
                    }
                    Ok(Ok((all, first)))
                })
            })?
            .map_err(|e| PyValueError::new_err(format!("VehicleModel.evaluate: {e}")))?;
        let out = PyDict::new(py);
        out.set_item("runs", json_to_py(py, &all)?)?;
        let summary: serde_json::Map<String, serde_json::Value> = metrics::summarise_runs(&all)
            .iter()
            .map(|(n, s)| (n.to_string(), serde_json::to_value(s).unwrap_or(serde_json::Value::Null)))
            .collect();
        out.set_item("summary", json_to_py(py, &summary)?)?;
        if let Some(t) = first {
            let per = PyDict::new(py);
            per.set_item("loglik", PyArray::from_vec(py, t.summaries.iter().map(|o| o.log_likelihood).collect()))?;
            per.set_item(
                "observed_units",
                PyArray::from_vec(py, t.summaries.iter().map(|o| o.observed_units as i64).collect()),
            )?;
            out.set_item("per_object", per)?;
        }
        Ok(out)
    }

    /// Learns the parameters on this model's dataset, as ``sefi train`` does
    /// (Adam, one batch of ``scenes_per_step`` scenes a step, ``epochs`` passes),
    /// evaluating the test MLL on ``test`` at the start, every ``eval_every``
    /// steps and at the end. ``callback(step, loss)``, if given, is called after
    /// every step with the negated log-likelihood per observed unit of that
    /// step's batch; an exception it raises stops training and propagates.
    /// Returns a dict with ``model`` (a ``VehicleModel`` with the trained
    /// parameters), ``final_eval`` (dict), ``evaluations`` (list of ``(step,
    /// dict)``), ``steps``, ``skipped_steps`` and ``seconds``. The run's files
    /// (``train.csv``, ``eval.csv``, checkpoint, ``params.bin``) go to ``out`` if given,
    /// otherwise to a temporary directory that is removed; an ``out`` that
    /// already holds a run is a ``FileExistsError``.
    #[pyo3(signature = (test, epochs = 1, lr = 0.01, estimator = "pf-sefi", particles = 256, eval_particles = 1024,
        lag = 8, alpha = 0.8, seed = 0, scenes_per_step = 1, eval_every = 0, clip = None, final_lr = None,
        filter = "tempered", out = None, callback = None))]
    #[allow(clippy::too_many_arguments)]
    fn train<'py>(
        &self,
        py: Python<'py>,
        test: &PyDataset,
        epochs: usize,
        lr: f64,
        estimator: &str,
        particles: usize,
        eval_particles: usize,
        lag: usize,
        alpha: f64,
        seed: u64,
        scenes_per_step: usize,
        eval_every: usize,
        clip: Option<f64>,
        final_lr: Option<f64>,
        filter: &str,
        out: Option<PathBuf>,
        callback: Option<Py<PyAny>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let est = self::estimator(estimator, lag, alpha)?;
        let kind = self.data.kind();
        let temper = match est {
            Estimator::PfSefi(_) => tempering(filter, kind, FilterPurpose::Training)?,
            Estimator::ThroughFilter(_) => None,
        };
        if let Some(c) = &callback {
            check(c.bind(py).is_callable(), "callback", || "must be callable as callback(step, loss)".into())?;
        }
        let config = ObjectiveConfig {
            estimator: est,
            estimator_config: EstimatorConfig {
                sampling: Sampling::new(positive("particles", particles)?, temper),
                ..EstimatorConfig::default()
            },
            scenes_per_step: positive("scenes_per_step", scenes_per_step)?,
            eval_particles: positive("eval_particles", eval_particles)?,
            extension: self.models.extension.as_ref().map(|e| e.extension),
            extension_only: false,
            frozen: Vec::new(),
            base_rate_factor: None,
            proposal: None,
            eval_tempering: tempering(filter, kind, FilterPurpose::Evaluation)?,
        };
        let train_config = TrainConfig {
            lr: finite("lr", lr)?,
            final_lr: final_lr.map(|v| finite("final_lr", v)).transpose()?,
            clip: clip.map(|v| finite("clip", v)).transpose()?,
            epochs,
            eval_every,
            checkpoint_every: 10,
            seed,
            ..TrainConfig::default()
        };
        let objective = SceneObjective::new(&self.data, test.data.clone(), config)
            .map_err(|e| PyValueError::new_err(format!("VehicleModel.train: {e}")))?;
        let initial = self.store.clone();
        let scratch = out.is_none().then(ScratchDir::new);
        let dir: PathBuf = out.unwrap_or_else(|| scratch.as_ref().map(|s| s.0.clone()).unwrap_or_default());
        let (outcome, evaluations, failed) = py.detach(|| {
            guard("VehicleModel.train", || {
                let failed: RefCell<Option<PyErr>> = RefCell::new(None);
                let mut evaluations: Vec<(usize, Vec<(String, f64)>)> = Vec::new();
                let mut on_event = |e: &TrainEvent| match e {
                    TrainEvent::Step { step, ll_per_unit, .. } => {
                        if failed.borrow().is_some() {
                            return;
                        }
                        let r = Python::attach(|py| -> PyResult<()> {
                            py.check_signals()?;
                            if let Some(cb) = &callback {
                                cb.call1(py, (*step, -*ll_per_unit))?;
                            }
                            Ok(())
                        });
                        if let Err(err) = r {
                            *failed.borrow_mut() = Some(err);
                        }
                    }
                    TrainEvent::Evaluated { step, metrics } => evaluations.push((*step, metrics.clone())),
                    _ => {}
                };
                let mut objective = Stoppable { inner: objective, failed: &failed };
                let outcome = training::train(&mut objective, initial, &train_config, &dir, false, &mut on_event);
                Ok((outcome, evaluations, failed.into_inner()))
            })
        })?;
        drop(scratch);
        if let Some(err) = failed {
            return Err(err);
        }
        let outcome = outcome.map_err(|e| match e {
            training::TrainError::Config(m) => PyValueError::new_err(format!("VehicleModel.train: {m}")),
            e @ training::TrainError::Exists { .. } => {
                pyo3::exceptions::PyFileExistsError::new_err(format!("VehicleModel.train: {e}"))
            }
            e @ training::TrainError::Io { .. } => {
                pyo3::exceptions::PyOSError::new_err(format!("VehicleModel.train: {e}"))
            }
            other => PyRuntimeError::new_err(format!("VehicleModel.train: {other}")),
        })?;
        let metrics = |m: &[(String, f64)]| -> PyResult<Bound<'py, PyDict>> {
            let d = PyDict::new(py);
            for (k, v) in m {
                d.set_item(k, v)?;
            }
            Ok(d)
        };
        let result = PyDict::new(py);
        result.set_item("final_eval", metrics(&outcome.final_eval)?)?;
        let evals = evaluations.iter().map(|(s, m)| Ok((*s, metrics(m)?))).collect::<PyResult<Vec<_>>>()?;
        result.set_item("evaluations", evals)?;
        result.set_item("steps", outcome.steps)?;
        result.set_item("skipped_steps", outcome.skipped_steps)?;
        result.set_item("seconds", outcome.seconds)?;
        let trained = Self::build(self.data.clone(), outcome.params)?;
        result.set_item("model", Py::new(py, trained)?)?;
        Ok(result)
    }

    fn __repr__(&self) -> String {
        format!(
            "VehicleModel({} policy, {} observations, {} objects, {} parameter tensors)",
            self.models.policy.name(),
            match self.data.kind() {
                ObservationKind::Points => "points",
                ObservationKind::Boxes => "boxes",
            },
            self.data.objects().len(),
            self.store.len()
        )
    }
}

/// The diagnosis's settings: the scale, the protocol's rules, the seed, then
/// every override by field name (through JSON, so that an unknown name or a
/// value of the wrong type is refused with serde's message).
fn diagnose_config(
    py: Python<'_>,
    quick: bool,
    protocol: Option<&str>,
    seed: u64,
    settings: Option<&Bound<'_, PyDict>>,
) -> PyResult<DiagnoseConfig> {
    let mut c = if quick { DiagnoseConfig::quick() } else { DiagnoseConfig::default() };
    match protocol {
        Some(name) => Protocol::named(name).map_err(|e| PyValueError::new_err(format!("protocol: {e}")))?.apply(&mut c),
        None => Protocol::default_protocol().apply(&mut c),
    }
    c.seed = seed;
    let Some(settings) = settings else { return Ok(c) };
    let mut value = serde_json::to_value(&c).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    let object = value.as_object_mut().ok_or_else(|| PyRuntimeError::new_err("settings are not a JSON object"))?;
    let json = py.import("json")?;
    for (k, v) in settings.iter() {
        let name: String = k.extract()?;
        check(object.contains_key(&name), "settings", || {
            let mut names: Vec<&String> = object.keys().collect();
            names.sort();
            format!("no setting named {name:?} (the settings are {names:?})")
        })?;
        let text: String = json.call_method1("dumps", (v,))?.cast::<PyString>()?.to_string();
        let parsed: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| PyValueError::new_err(format!("settings[{name:?}]: {e}")))?;
        object.insert(name, parsed);
    }
    let c: DiagnoseConfig =
        serde_json::from_value(value).map_err(|e| PyValueError::new_err(format!("settings: {e}")))?;
    c.validate().map_err(|e| PyValueError::new_err(format!("settings: {e}")))?;
    Ok(c)
}

/// Diagnoses ``dataset`` as ``sefi diagnose`` does: fits the base model and
/// the catalogue's extensions the checks make plausible on a seeded part of
/// the objects, compares them on held-out objects and names the hidden effect,
/// if any. Returns the report as a dict (what ``report.json`` holds); the
/// training runs go under ``out``. ``quick`` is ``sefi diagnose --quick``'s
/// scale; ``settings`` overrides any field of the configuration by name (e.g.
/// ``{"base_steps": 20}``); with ``heldout``, the model is fitted on
/// ``dataset`` and checked and compared on ``heldout``.
#[pyfunction(name = "diagnose")]
#[pyo3(signature = (dataset, out, quick = true, seed = 0, protocol = None, settings = None, heldout = None))]
#[allow(clippy::too_many_arguments)]
pub fn diagnose_dataset<'py>(
    py: Python<'py>,
    dataset: &PyDataset,
    out: PathBuf,
    quick: bool,
    seed: u64,
    protocol: Option<&str>,
    settings: Option<&Bound<'_, PyDict>>,
    heldout: Option<&PyDataset>,
) -> PyResult<Bound<'py, PyAny>> {
    let config = diagnose_config(py, quick, protocol, seed, settings)?;
    let held = heldout.map(|h| h.data.clone());
    let report = py.detach(|| {
        guard("diagnose", || {
            let comm: Arc<dyn Collective> = Arc::new(SingleProcess);
            std::fs::create_dir_all(&out)
                .map_err(|e| pyo3::exceptions::PyOSError::new_err(format!("{}: {e}", out.display())))?;
            let dir: &Path = &out;
            let r = match &held {
                Some(h) => diagnose_split(&dataset.data, h, &config, dir, &comm, &mut |_| {}),
                None => diagnose(&dataset.data, &config, dir, &comm, &mut |_| {}),
            };
            r.map_err(|e| PyValueError::new_err(format!("diagnose: {e}")))
        })
    })?;
    json_to_py(py, &report)
}
