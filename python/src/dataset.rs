//! Datasets from Python: the project's dataset format (SPEC §4; a directory of
//! CSV files and `meta.json`) read and written, built from NumPy tables whose
//! columns are those of the CSV files, generated (experiments A and B, hidden
//! effects) and imported from KITTI; each object's observations and ground truth
//! as arrays.
//!
//! A bad data file is a [`DataError`] exception (a `ValueError`) whose message
//! and `file`, `line` and `column` attributes say where; a missing file is a
//! `FileNotFoundError`, any other I/O failure an `OSError`.

use std::collections::HashMap;
use std::path::PathBuf;

use numpy::{PyArray, PyArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rand::rngs::StdRng;
use rand::SeedableRng;

use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
use ssm::data::{
    self, import_kitti, Action, BoxDetection, Dataset, Meta, Object, ObservationKind, Observations, Pose, Prior, State,
    ACTION_COLUMNS, AV_COLUMNS, BOX_COLUMNS, OBJECT_COLUMNS, POINT_COLUMNS, STATE_COLUMNS,
};
use ssm::simulation::synthetic::{generate_experiment, Experiment, ExperimentConfig};

use crate::convert::{check, finite, float_array, guard};

create_exception!(
    pfsefi,
    DataError,
    PyValueError,
    "A dataset file or table is invalid: the message, and the attributes `file`, `line` (1-based, \
     None for a table built in memory) and `column`, say where."
);

/// A dataset error as a Python exception: `FileNotFoundError` for a missing
/// file or directory, `OSError` for other I/O failures, [`DataError`] (with
/// `file`, `line`, `column` set, each None when unknown) for contents.
pub fn data_error(py: Python<'_>, e: data::DataError) -> PyErr {
    let message = e.to_string();
    match &e {
        data::DataError::MissingFile { .. } => return PyFileNotFoundError::new_err(message),
        data::DataError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            return PyFileNotFoundError::new_err(message)
        }
        data::DataError::Io { .. } => return PyOSError::new_err(message),
        _ => {}
    }
    let err = DataError::new_err(message);
    let value = err.value(py);
    let set = |name: &str, v: Py<PyAny>| value.setattr(name, v);
    let (file, line, column) = (e.file(), e.line(), e.column().map(str::to_string));
    // Setting attributes on a fresh exception instance cannot fail in practice;
    // were it to, the message still says where.
    let _ = set("file", file.into_pyobject(py).map(|o| o.into_any().unbind()).unwrap_or_else(|_| py.None()));
    let _ = set("line", line.into_pyobject(py).map(|o| o.into_any().unbind()).unwrap_or_else(|_| py.None()));
    let _ = set("column", column.into_pyobject(py).map(|o| o.into_any().unbind()).unwrap_or_else(|_| py.None()));
    err
}

/// A dataset in memory: scenes (the AV's pose at every step), objects (size and
/// prior of the initial state), their observations (point sets or box
/// detections) and, when known, their true states and actions. Always valid:
/// every constructor runs the format's checks.
#[pyclass(module = "pfsefi", name = "Dataset", frozen)]
#[derive(Clone)]
pub struct PyDataset {
    /// The dataset.
    pub data: Dataset,
}

fn kind_name(kind: ObservationKind) -> &'static str {
    match kind {
        ObservationKind::Points => "points",
        ObservationKind::Boxes => "boxes",
    }
}

/// The column names of every table, by table name.
pub fn columns<'py>(py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
    let out = PyDict::new(py);
    for (name, cols) in [
        ("av", &AV_COLUMNS[..]),
        ("objects", &OBJECT_COLUMNS[..]),
        ("points", &POINT_COLUMNS[..]),
        ("boxes", &BOX_COLUMNS[..]),
        ("states", &STATE_COLUMNS[..]),
        ("actions", &ACTION_COLUMNS[..]),
    ] {
        out.set_item(name, cols.to_vec())?;
    }
    Ok(out)
}

/// A 2-D table read from Python: rows of `columns.len()` floats.
struct Table {
    name: &'static str,
    columns: &'static [&'static str],
    data: Vec<f64>,
}

impl Table {
    fn read(
        py: Python<'_>,
        obj: &Bound<'_, PyAny>,
        name: &'static str,
        columns: &'static [&'static str],
    ) -> PyResult<Self> {
        let a = float_array(py, obj, name)?;
        check(a.shape.len() == 2 && a.shape[1] == columns.len(), name, || {
            format!("expected shape (rows, {}) with columns {columns:?}, got {:?}", columns.len(), a.shape)
        })?;
        Ok(Table { name, columns, data: a.data })
    }

    fn rows(&self) -> impl Iterator<Item = (usize, &[f64])> {
        self.data.chunks(self.columns.len()).enumerate()
    }

    /// Column `c` of row `r` as an integer (ids and steps), or a `ValueError`
    /// naming the table, row and column.
    fn int(&self, r: usize, row: &[f64], c: usize) -> PyResult<i64> {
        let v = row[c];
        check(v.fract() == 0.0 && v.abs() < 9.0e15, self.name, || {
            format!("row {r}, column `{}`: expected an integer, got {v}", self.columns[c])
        })?;
        Ok(v as i64)
    }

    /// Column `c` of row `r` as a step index (a non-negative integer).
    fn step(&self, r: usize, row: &[f64], c: usize) -> PyResult<usize> {
        let t = self.int(r, row, c)?;
        check(t >= 0, self.name, || {
            format!("row {r}, column `{}`: a step must be at least 0, got {t}", self.columns[c])
        })?;
        Ok(t as usize)
    }
}

fn table_opt(
    py: Python<'_>,
    obj: Option<&Bound<'_, PyAny>>,
    name: &'static str,
    columns: &'static [&'static str],
) -> PyResult<Option<Table>> {
    match obj {
        Some(o) if !o.is_none() => Ok(Some(Table::read(py, o, name, columns)?)),
        _ => Ok(None),
    }
}

/// A 2-D float64 array of `rows` rows.
fn array2<'py>(py: Python<'py>, data: Vec<f64>, cols: usize) -> PyResult<Bound<'py, PyAny>> {
    let rows = data.len() / cols;
    Ok(PyArray::from_vec(py, data).reshape(vec![rows, cols])?.into_any())
}

fn state_row(s: &State) -> [f64; 5] {
    s.to_array()
}

fn box_row(b: &BoxDetection) -> [f64; 6] {
    [b.x, b.y, b.yaw, b.length, b.width, b.score]
}

impl PyDataset {
    fn check_object(&self, object: usize) -> PyResult<()> {
        let n = self.data.objects().len();
        check(object < n, "object", || format!("index {object} out of range (the dataset has {n} objects)"))
    }

    fn from_tables(py: Python<'_>, dt: f64, prior_from_detection: bool, t: Tables) -> PyResult<Self> {
        let kind = if t.points.is_some() { ObservationKind::Points } else { ObservationKind::Boxes };
        // Every scene's poses, by id in order of first appearance.
        let mut order: Vec<i64> = Vec::new();
        let mut poses: HashMap<i64, Vec<(usize, usize, Pose)>> = HashMap::new();
        let mut steps = 0;
        for (r, row) in t.av.rows() {
            let (scene, step) = (t.av.int(r, row, 0)?, t.av.step(r, row, 1)?);
            steps = steps.max(step + 1);
            let list = poses.entry(scene).or_insert_with(|| {
                order.push(scene);
                Vec::new()
            });
            list.push((r, step, Pose { x: row[2], y: row[3], yaw: row[4] }));
        }
        let mut builder = Dataset::builder(Meta { prior_from_detection, ..Meta::new(dt, steps) }, kind);
        for id in &order {
            let mut av: Vec<Option<Pose>> = vec![None; steps];
            for &(r, step, pose) in &poses[id] {
                check(av[step].is_none(), "av", || format!("row {r}: scene {id} has a second pose at t = {step}"))?;
                av[step] = Some(pose);
            }
            let av: Vec<Pose> = av
                .into_iter()
                .enumerate()
                .map(|(step, p)| {
                    p.ok_or_else(|| {
                        PyValueError::new_err(format!(
                            "av: scene {id} has no pose at t = {step} (every scene needs one at each of the {steps} steps)"
                        ))
                    })
                })
                .collect::<PyResult<_>>()?;
            builder.scene(*id, &av);
        }
        for (r, row) in t.objects.rows() {
            let state = |o: usize| State::from_array([row[o], row[o + 1], row[o + 2], row[o + 3], row[o + 4]]);
            builder.object(Object {
                scene: t.objects.int(r, row, 0)?,
                id: t.objects.int(r, row, 1)?,
                length: row[2],
                width: row[3],
                prior: Prior { mean: state(4), sd: state(9) },
            });
        }
        if let Some(p) = &t.points {
            for (r, row) in p.rows() {
                builder.point(p.int(r, row, 0)?, p.int(r, row, 1)?, p.step(r, row, 2)?, [row[3], row[4]]);
            }
        }
        if let Some(b) = &t.boxes {
            for (r, row) in b.rows() {
                let d =
                    BoxDetection { x: row[3], y: row[4], yaw: row[5], length: row[6], width: row[7], score: row[8] };
                builder.detection(b.int(r, row, 0)?, b.int(r, row, 1)?, b.step(r, row, 2)?, d);
            }
        }
        if let Some(s) = &t.states {
            builder.with_states();
            for (r, row) in s.rows() {
                let state = State::from_array([row[3], row[4], row[5], row[6], row[7]]);
                builder.state(s.int(r, row, 0)?, s.int(r, row, 1)?, s.step(r, row, 2)?, state);
            }
        }
        if let Some(a) = &t.actions {
            builder.with_actions();
            for (r, row) in a.rows() {
                let action = Action { accel: row[3], pinch: row[4] };
                builder.action(a.int(r, row, 0)?, a.int(r, row, 1)?, a.step(r, row, 2)?, action);
            }
        }
        let data =
            py.detach(|| guard("Dataset.from_arrays", || Ok(builder.build())))?.map_err(|e| data_error(py, e))?;
        Ok(PyDataset { data })
    }
}

/// The tables of [`PyDataset::from_arrays`], read and shape-checked.
struct Tables {
    av: Table,
    objects: Table,
    points: Option<Table>,
    boxes: Option<Table>,
    states: Option<Table>,
    actions: Option<Table>,
}

#[pymethods]
impl PyDataset {
    /// Reads the dataset directory `path` (``meta.json``, ``av.csv``,
    /// ``objects.csv``, ``points.csv`` or ``boxes.csv``, and optionally
    /// ``states.csv`` and ``actions.csv``).
    #[staticmethod]
    fn read(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let data = py.detach(|| guard("Dataset.read", || Ok(Dataset::read(&path))))?.map_err(|e| data_error(py, e))?;
        Ok(PyDataset { data })
    }

    /// Writes the dataset as the directory `path` (created if needed), in the
    /// format ``Dataset.read`` and the ``sefi`` CLI read.
    fn write(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        py.detach(|| guard("Dataset.write", || Ok(self.data.write(&path))))?.map_err(|e| data_error(py, e))
    }

    /// A dataset from tables: 2-D float arrays whose columns are those of the
    /// CSV files (``pfsefi.COLUMNS``). ``av`` holds one row per scene and step
    /// (the number of steps is one past the largest ``t``); exactly one of
    /// ``points`` and ``boxes`` is given; ``states`` and ``actions`` (ground
    /// truth) are optional. Ids and steps must be integral. A bad record is a
    /// ``DataError`` naming its table (as the file it would be written to), its
    /// row (``record``) and column. ``Dataset.from_arrays(ds.dt, **ds.tables())``
    /// rebuilds ``ds``.
    #[staticmethod]
    #[pyo3(signature = (dt, av, objects, points = None, boxes = None, states = None, actions = None, prior_from_detection = false))]
    #[allow(clippy::too_many_arguments)]
    fn from_arrays(
        py: Python<'_>,
        dt: f64,
        av: &Bound<'_, PyAny>,
        objects: &Bound<'_, PyAny>,
        points: Option<&Bound<'_, PyAny>>,
        boxes: Option<&Bound<'_, PyAny>>,
        states: Option<&Bound<'_, PyAny>>,
        actions: Option<&Bound<'_, PyAny>>,
        prior_from_detection: bool,
    ) -> PyResult<Self> {
        finite("dt", dt)?;
        let tables = Tables {
            av: Table::read(py, av, "av", &AV_COLUMNS)?,
            objects: Table::read(py, objects, "objects", &OBJECT_COLUMNS)?,
            points: table_opt(py, points, "points", &POINT_COLUMNS)?,
            boxes: table_opt(py, boxes, "boxes", &BOX_COLUMNS)?,
            states: table_opt(py, states, "states", &STATE_COLUMNS)?,
            actions: table_opt(py, actions, "actions", &ACTION_COLUMNS)?,
        };
        check(tables.points.is_some() != tables.boxes.is_some(), "points, boxes", || {
            "give exactly one of them (the dataset's observations)".into()
        })?;
        Self::from_tables(py, dt, prior_from_detection, tables)
    }

    /// Every table as a 2-D float64 array with the columns of its CSV file
    /// (``pfsefi.COLUMNS``): ``av``, ``objects``, ``points`` or ``boxes``, and
    /// ``states`` and ``actions`` when the dataset has ground truth.
    fn tables<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = &self.data;
        let out = PyDict::new(py);
        let mut av = Vec::new();
        for s in d.scenes() {
            for (t, p) in s.av.iter().enumerate() {
                av.extend([s.id as f64, t as f64, p.x, p.y, p.yaw]);
            }
        }
        out.set_item("av", array2(py, av, AV_COLUMNS.len())?)?;
        let mut objects = Vec::new();
        for o in d.objects() {
            objects.extend([o.scene as f64, o.id as f64, o.length, o.width]);
            objects.extend(o.prior.mean.to_array());
            objects.extend(o.prior.sd.to_array());
        }
        out.set_item("objects", array2(py, objects, OBJECT_COLUMNS.len())?)?;
        let ids = |i: usize| (d.objects()[i].scene as f64, d.objects()[i].id as f64);
        match d.observations() {
            Observations::Points(p) => {
                let mut rows = Vec::new();
                for (i, t, xy) in p.iter() {
                    let (s, o) = ids(i);
                    rows.extend([s, o, t as f64, xy[0], xy[1]]);
                }
                out.set_item("points", array2(py, rows, POINT_COLUMNS.len())?)?;
            }
            Observations::Boxes(b) => {
                let mut rows = Vec::new();
                for (i, t, det) in b.iter() {
                    let (s, o) = ids(i);
                    rows.extend([s, o, t as f64]);
                    rows.extend(box_row(det));
                }
                out.set_item("boxes", array2(py, rows, BOX_COLUMNS.len())?)?;
            }
        }
        if let Some(states) = d.states() {
            let mut rows = Vec::new();
            for (i, t, s) in states.iter() {
                let (sc, o) = ids(i);
                rows.extend([sc, o, t as f64]);
                rows.extend(state_row(s));
            }
            out.set_item("states", array2(py, rows, STATE_COLUMNS.len())?)?;
        }
        if let Some(actions) = d.actions() {
            let mut rows = Vec::new();
            for (i, t, a) in actions.iter() {
                let (s, o) = ids(i);
                rows.extend([s, o, t as f64, a.accel, a.pinch]);
            }
            out.set_item("actions", array2(py, rows, ACTION_COLUMNS.len())?)?;
        }
        Ok(out)
    }

    /// ``"points"`` or ``"boxes"``.
    #[getter]
    fn kind(&self) -> &'static str {
        kind_name(self.data.kind())
    }

    /// Seconds between steps.
    #[getter]
    fn dt(&self) -> f64 {
        self.data.dt()
    }

    /// Steps per scene (``T + 1``).
    #[getter]
    fn steps(&self) -> usize {
        self.data.steps()
    }

    /// Whether each object's prior was read from its first detection (KITTI).
    #[getter]
    fn prior_from_detection(&self) -> bool {
        self.data.meta().prior_from_detection
    }

    /// Number of scenes.
    #[getter]
    fn num_scenes(&self) -> usize {
        self.data.scenes().len()
    }

    /// Number of objects.
    #[getter]
    fn num_objects(&self) -> usize {
        self.data.objects().len()
    }

    /// Whether the dataset holds true states (``states.csv``).
    #[getter]
    fn has_truth(&self) -> bool {
        self.data.states().is_some()
    }

    /// Number of observed items (points, or box detections).
    #[getter]
    fn num_observations(&self) -> usize {
        self.data.observations().count()
    }

    /// The ``(scene id, object id)`` of every object, shape ``(objects, 2)`` int64.
    #[getter]
    fn object_ids<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let ids: Vec<i64> = self.data.objects().iter().flat_map(|o| [o.scene, o.id]).collect();
        let n = self.data.objects().len();
        Ok(PyArray::from_vec(py, ids).reshape(vec![n, 2])?.into_any())
    }

    /// Object ``object``'s observations: for points, one row ``(t, x, y)`` per
    /// point, shape ``(m, 3)``; for boxes, one row ``(x, y, yaw, length, width,
    /// score)`` per step, shape ``(steps, 6)``, NaN where nothing was detected.
    fn observations<'py>(&self, py: Python<'py>, object: usize) -> PyResult<Bound<'py, PyAny>> {
        self.check_object(object)?;
        let steps = self.data.steps();
        match self.data.observations() {
            Observations::Points(p) => {
                let mut rows = Vec::new();
                for t in 0..steps {
                    for xy in p.get(object, t) {
                        rows.extend([t as f64, xy[0], xy[1]]);
                    }
                }
                array2(py, rows, 3)
            }
            Observations::Boxes(b) => {
                let mut rows = Vec::with_capacity(steps * 6);
                for t in 0..steps {
                    rows.extend(b.get(object, t).map_or([f64::NAN; 6], box_row));
                }
                array2(py, rows, 6)
            }
        }
    }

    /// Object ``object``'s true states ``(x, y, yaw, v, kappa)``, shape
    /// ``(steps, 5)`` (NaN where unknown), or None without ground truth.
    fn truth<'py>(&self, py: Python<'py>, object: usize) -> PyResult<Option<Bound<'py, PyAny>>> {
        self.check_object(object)?;
        let Some(states) = self.data.states() else { return Ok(None) };
        let rows: Vec<f64> =
            states.object(object).iter().flat_map(|s| s.map_or([f64::NAN; 5], |s| state_row(&s))).collect();
        Ok(Some(array2(py, rows, 5)?))
    }

    /// Object ``object``'s true actions ``(accel, pinch)``, shape ``(steps, 2)``
    /// (row ``t`` is the action between steps ``t - 1`` and ``t``; NaN where
    /// unknown, always at ``t = 0``), or None without them.
    fn actions<'py>(&self, py: Python<'py>, object: usize) -> PyResult<Option<Bound<'py, PyAny>>> {
        self.check_object(object)?;
        let Some(actions) = self.data.actions() else { return Ok(None) };
        let rows: Vec<f64> =
            actions.object(object).iter().flat_map(|a| a.map_or([f64::NAN; 2], |a| [a.accel, a.pinch])).collect();
        Ok(Some(array2(py, rows, 2)?))
    }

    /// The dataset of the scenes at positions ``scenes`` (0-based, in this order).
    fn select_scenes(&self, scenes: Vec<usize>) -> PyResult<Self> {
        let n = self.data.scenes().len();
        if let Some(&bad) = scenes.iter().find(|&&s| s >= n) {
            return Err(PyValueError::new_err(format!(
                "scenes: index {bad} out of range (the dataset has {n} scenes)"
            )));
        }
        Ok(PyDataset { data: self.data.select_scenes(&scenes) })
    }

    /// The dataset of the objects at positions ``objects`` (0-based) with their scenes.
    fn select_objects(&self, objects: Vec<usize>) -> PyResult<Self> {
        let n = self.data.objects().len();
        if let Some(&bad) = objects.iter().find(|&&o| o >= n) {
            return Err(PyValueError::new_err(format!(
                "objects: index {bad} out of range (the dataset has {n} objects)"
            )));
        }
        check(!objects.is_empty(), "objects", || "select at least one object".into())?;
        Ok(PyDataset { data: self.data.select_objects(&objects) })
    }

    fn __eq__(&self, other: &Bound<'_, PyAny>) -> bool {
        other.cast::<PyDataset>().is_ok_and(|o| o.get().data == self.data)
    }

    fn __repr__(&self) -> String {
        format!(
            "Dataset({}, {} scenes, {} objects, {} steps, dt {}{})",
            self.kind(),
            self.num_scenes(),
            self.num_objects(),
            self.steps(),
            self.dt(),
            if self.has_truth() { ", with truth" } else { "" }
        )
    }
}

/// Experiment ``"A"`` (25 steps) or ``"B"`` (50 steps) of the paper, as ``sefi
/// generate`` makes it from ``seed``: ``(train, test, true_params)`` with the
/// true parameters as a dict of arrays by name. ``quick`` gives the small sizes
/// of ``sefi generate --quick`` (2 training and 1 test scene of 10 objects, 6
/// steps, a tiny fit of the true observation network).
#[pyfunction(name = "generate_experiment")]
#[pyo3(signature = (experiment = "A", seed = 0, quick = false))]
pub fn generate_experiment_data<'py>(
    py: Python<'py>,
    experiment: &str,
    seed: u64,
    quick: bool,
) -> PyResult<(PyDataset, PyDataset, Bound<'py, PyDict>)> {
    let experiment: Experiment = experiment
        .parse()
        .map_err(|e: ssm::simulation::synthetic::SyntheticError| PyValueError::new_err(format!("experiment: {e}")))?;
    let config = if quick { ExperimentConfig::quick(experiment) } else { ExperimentConfig::paper(experiment) };
    let data = py.detach(|| {
        guard("generate_experiment", || {
            let mut rng = StdRng::seed_from_u64(seed);
            generate_experiment(&config, &mut rng, &mut |_| {})
                .map_err(|e| PyValueError::new_err(format!("generate_experiment: {e}")))
        })
    })?;
    let params = crate::params::store_to_dict(py, &data.truth.model.params)?;
    Ok((PyDataset { data: data.train }, PyDataset { data: data.test }, params))
}

/// A dataset with a hidden effect for the diagnosis to find, as ``sefi
/// generate --hidden EFFECT`` makes it: ``effect`` is ``none``, ``latency``,
/// ``clutter``, ``size_bias`` (points), ``heavy_tailed_accel``,
/// ``student_t_accel`` or ``heading_flip`` (boxes); ``strength`` a multiple of
/// its default size.
#[pyfunction(name = "generate_hidden")]
#[pyo3(signature = (effect, strength = 1.0, boxes = false, scenes = 8, objects = 6, steps = 16, seed = 0))]
#[allow(clippy::too_many_arguments)]
pub fn generate_hidden_data(
    py: Python<'_>,
    effect: &str,
    strength: f64,
    boxes: bool,
    scenes: usize,
    objects: usize,
    steps: usize,
    seed: u64,
) -> PyResult<PyDataset> {
    finite("strength", strength)?;
    check(scenes > 0 && objects > 0, "scenes, objects", || "must be at least 1".into())?;
    check(steps >= 2, "steps", || format!("must be at least 2, got {steps}"))?;
    let effect =
        HiddenEffect::at_strength(effect, strength).map_err(|e| PyValueError::new_err(format!("effect: {e}")))?;
    let kind = if boxes { ObservationKind::Boxes } else { ObservationKind::Points };
    let config = HiddenConfig { scenes, objects_per_scene: objects, steps, ..HiddenConfig::quick(kind, effect, seed) };
    let data = py.detach(|| {
        guard("generate_hidden", || {
            generate_hidden(&config).map_err(|e| PyValueError::new_err(format!("generate_hidden: {e}")))
        })
    })?;
    Ok(PyDataset { data })
}

/// Imports the KITTI tracking folder ``root`` (with ``label_02/``,
/// ``det_pointrcnn/Car/``, ``ego_pose_orbslam3/`` and ``calib/``) as two box
/// datasets, as ``sefi import-kitti`` does: ``(train, val, report)`` with the
/// import report as Markdown. ``sequences`` restricts the import;
/// ``val_sequences`` (default AB3DMOT's) go to ``val``.
#[pyfunction(name = "import_kitti")]
#[pyo3(signature = (root, steps = 20, stride = 1, align = 1, gate = 2.0, sequences = None, val_sequences = None))]
#[allow(clippy::too_many_arguments)]
pub fn import_kitti_data(
    py: Python<'_>,
    root: PathBuf,
    steps: usize,
    stride: usize,
    align: usize,
    gate: f64,
    sequences: Option<Vec<u32>>,
    val_sequences: Option<Vec<u32>>,
) -> PyResult<(PyDataset, PyDataset, String)> {
    let options = data::KittiOptions {
        steps,
        stride,
        align,
        gate: finite("gate", gate)?,
        sequences,
        val_sequences,
        ..data::KittiOptions::default()
    };
    let import =
        py.detach(|| guard("import_kitti", || Ok(import_kitti(&root, &options))))?.map_err(|e| data_error(py, e))?;
    Ok((PyDataset { data: import.train }, PyDataset { data: import.val }, import.report.to_string()))
}
