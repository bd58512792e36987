//! Parameter files from Python: the project's versioned bincode files and `.npz`
//! archives (`ssm::util::npz`), both read into and written from a dict of float64
//! arrays by parameter name. The format follows the file's extension.

use std::path::Path;

use autodiff::nn::{ParamError, ParamStore};
use autodiff::Tensor;
use numpy::{PyArray, PyArrayMethods};
use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use ssm::util::npz::{self, NpzError};

use crate::convert::{check, float_array};

/// A parameter-file error as a Python exception: `FileNotFoundError` for a
/// missing file, `OSError` for other file-system failures,
/// `ValueError` for contents; the message names the file.
pub fn param_error(e: ParamError) -> PyErr {
    match e {
        ParamError::Io { ref source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(e.to_string())
        }
        ParamError::Io { .. } => PyOSError::new_err(e.to_string()),
        _ => PyValueError::new_err(e.to_string()),
    }
}

fn npz_error(e: NpzError) -> PyErr {
    match e {
        NpzError::Io { ref source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(e.to_string())
        }
        NpzError::Io { .. } => PyOSError::new_err(e.to_string()),
        NpzError::Format { .. } => PyValueError::new_err(e.to_string()),
    }
}

fn is_npz(path: &Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("npz"))
}

/// Reads a parameter file: `.npz`, or the project's format for any other extension.
pub fn load(path: &Path) -> PyResult<ParamStore<f64>> {
    if is_npz(path) {
        npz::read_params(path, None).map_err(npz_error)
    } else {
        ParamStore::load(path).map_err(param_error)
    }
}

/// Reads a parameter file (`.npz`, or the project's bincode format for any other
/// extension) into a dict of float64 arrays by name, in the file's order.
#[pyfunction]
pub fn read_params<'py>(py: Python<'py>, path: std::path::PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let store = py.detach(|| load(&path))?;
    store_to_dict(py, &store)
}

/// A store as a dict of float64 arrays by name, in the store's order.
pub fn store_to_dict<'py>(py: Python<'py>, store: &ParamStore<f64>) -> PyResult<Bound<'py, PyDict>> {
    let out = PyDict::new(py);
    for (name, t) in store.iter() {
        out.set_item(name, PyArray::from_vec(py, t.data().to_vec()).reshape(t.shape().to_vec())?)?;
    }
    Ok(out)
}

/// A store from a dict of float arrays by name (in the dict's order).
pub fn store_from_dict(py: Python<'_>, params: &Bound<'_, PyDict>) -> PyResult<ParamStore<f64>> {
    if params.is_empty() {
        return Err(PyValueError::new_err("params: the dict is empty"));
    }
    let mut store = ParamStore::new();
    for (k, v) in params.iter() {
        let name: String = k.extract().map_err(|_| PyTypeError::new_err(format!("params: key {k} is not a string")))?;
        check(store.id(&name).is_none(), "params", || format!("the name {name:?} appears twice"))?;
        let a = float_array(py, &v, &format!("params[{name:?}]"))?;
        store.add(&name, Tensor::new(&a.shape, a.data));
    }
    Ok(store)
}

/// Writes `store` as a parameter file: `.npz` for that extension, the project's
/// format for any other.
pub fn save(store: &ParamStore<f64>, path: &Path) -> PyResult<()> {
    if is_npz(path) {
        npz::write_params(store, path).map_err(npz_error)
    } else {
        store.save(path).map_err(param_error)
    }
}

/// Writes a dict of float arrays by name as a parameter file: `.npz` for that
/// extension, the project's bincode format (read by `sefi`) for any other.
#[pyfunction]
pub fn write_params(py: Python<'_>, params: &Bound<'_, PyDict>, path: std::path::PathBuf) -> PyResult<()> {
    let store = store_from_dict(py, params)?;
    py.detach(|| save(&store, &path))
}

/// Converts a parameter file between formats by extension (`.npz` <-> the
/// project's bincode). With `like`, a parameter file whose names and shapes the
/// result must have.
#[pyfunction]
#[pyo3(signature = (src, dst, like = None))]
pub fn convert_params(
    py: Python<'_>,
    src: std::path::PathBuf,
    dst: std::path::PathBuf,
    like: Option<std::path::PathBuf>,
) -> PyResult<()> {
    py.detach(|| {
        let store = load(&src)?;
        if let Some(like) = like {
            load(&like)?
                .check_same_layout(&store)
                .map_err(|e| PyValueError::new_err(format!("{}: {e}", src.display())))?;
        }
        if is_npz(&dst) {
            npz::write_params(&store, &dst).map_err(npz_error)
        } else {
            store.save(&dst).map_err(param_error)
        }
    })
}
