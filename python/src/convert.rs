//! NumPy in and out: every array argument is checked here (type, dtype, shape,
//! finiteness, emptiness) and every failure becomes a Python exception whose
//! message names the argument and what is wrong with it. Also the panic guard:
//! no Rust panic crosses into Python.

use std::panic::{catch_unwind, AssertUnwindSafe};

use numpy::{PyArrayDescrMethods, PyReadonlyArrayDyn, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;

/// A float array taken from Python: values in row-major (C) order and its shape.
#[derive(Clone, Debug)]
pub struct FloatArray {
    /// The values, row-major.
    pub data: Vec<f64>,
    /// The shape.
    pub shape: Vec<usize>,
}

/// Reads `obj` (a NumPy array, or anything `numpy.asarray` takes) as a float64
/// array: `TypeError` unless its dtype is floating point; `ValueError` when it is
/// empty or holds a NaN or an infinity (naming the first such entry).
pub fn float_array(py: Python<'_>, obj: &Bound<'_, PyAny>, name: &str) -> PyResult<FloatArray> {
    let np = py.import("numpy")?;
    let arr = if obj.cast::<PyUntypedArray>().is_ok() {
        obj.clone()
    } else {
        np.call_method1("asarray", (obj,))
            .map_err(|e| PyTypeError::new_err(format!("{name}: cannot be read as an array ({e})")))?
    };
    let untyped =
        arr.cast::<PyUntypedArray>().map_err(|_| PyTypeError::new_err(format!("{name}: expected a NumPy array")))?;
    let dtype = untyped.dtype();
    let kind = dtype.kind();
    if kind != b'f' {
        return Err(PyTypeError::new_err(format!(
            "{name}: expected a floating-point array (float32 or float64), got dtype {}",
            dtype.str()?
        )));
    }
    let shape = untyped.shape().to_vec();
    let f64_contig = np.call_method1("ascontiguousarray", (&arr, "float64"))?;
    let view: PyReadonlyArrayDyn<'_, f64> = f64_contig.extract()?;
    let data = view.as_slice().map_err(|e| PyRuntimeError::new_err(format!("{name}: {e}")))?.to_vec();
    if data.is_empty() {
        return Err(PyValueError::new_err(format!("{name}: the array is empty (shape {shape:?})")));
    }
    if let Some(i) = data.iter().position(|v| !v.is_finite()) {
        return Err(PyValueError::new_err(format!(
            "{name}: entry {:?} is {} (every entry must be finite)",
            unravel(i, &shape),
            data[i]
        )));
    }
    Ok(FloatArray { data, shape })
}

/// The multi-index of flat (row-major) position `i` in `shape`.
pub fn unravel(mut i: usize, shape: &[usize]) -> Vec<usize> {
    let mut idx = vec![0; shape.len()];
    for (k, &s) in shape.iter().enumerate().rev() {
        if s > 0 {
            idx[k] = i % s;
            i /= s;
        }
    }
    idx
}

/// A `ValueError` unless `ok`, saying `what` must hold for `name`.
pub fn check(ok: bool, name: &str, what: impl FnOnce() -> String) -> PyResult<()> {
    if ok {
        Ok(())
    } else {
        Err(PyValueError::new_err(format!("{name}: {}", what())))
    }
}

/// A finite float parameter, or a `ValueError` naming it.
pub fn finite(name: &str, v: f64) -> PyResult<f64> {
    check(v.is_finite(), name, || format!("must be finite, got {v}"))?;
    Ok(v)
}

/// Runs `f`, turning a panic into a `RuntimeError` that names `place` (no panic
/// crosses into Python).
pub fn guard<T>(place: &str, f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            let msg = payload
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(PyRuntimeError::new_err(format!("internal error in {place}: {msg}")))
        }
    }
}
