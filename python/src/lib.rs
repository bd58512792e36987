//! The Python package `pfsefi` (module `pfsefi._native`): PF-SEFI score
//! estimation for NumPy and JAX users.
//!
//! * [`lgssm`]: the built-in linear-Gaussian model (simulation, Kalman
//!   log-likelihood and score, every particle estimator's score);
//! * [`callback`]: a model written in Python as vectorised callbacks, filtered
//!   and scored by PF-SEFI in Rust;
//! * [`vehicle`]: the vehicle model on a synthetic scene (score by parameter name);
//! * [`dataset`]: datasets read, written, built from arrays, generated and
//!   imported from KITTI;
//! * [`model`]: the vehicle model of a dataset and a parameter file (filter,
//!   smoother, score, metrics, training) and the diagnosis;
//! * [`params`]: parameter files (`.npz` and the project's format) as dicts;
//! * [`convert`]: NumPy arguments checked into Rust values, errors into Python
//!   exceptions, panics caught.
//!
//! Every function releases the GIL while Rust computes (a Python model's
//! callbacks take it back for each call).

pub mod callback;
pub mod convert;
pub mod dataset;
pub mod lgssm;
pub mod model;
pub mod params;
pub mod sampling;
pub mod vehicle;

use pyo3::prelude::*;

/// The native module of `pfsefi`.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<lgssm::LinearGaussian>()?;
    m.add_class::<vehicle::SyntheticScene>()?;
    m.add_function(wrap_pyfunction!(callback::particle_filter, m)?)?;
    m.add_function(wrap_pyfunction!(params::read_params, m)?)?;
    m.add_function(wrap_pyfunction!(params::write_params, m)?)?;
    m.add_function(wrap_pyfunction!(params::convert_params, m)?)?;
    m.add_class::<dataset::PyDataset>()?;
    m.add_class::<model::VehicleModel>()?;
    m.add_function(wrap_pyfunction!(dataset::generate_experiment_data, m)?)?;
    m.add_function(wrap_pyfunction!(dataset::generate_hidden_data, m)?)?;
    m.add_function(wrap_pyfunction!(dataset::import_kitti_data, m)?)?;
    m.add_function(wrap_pyfunction!(model::diagnose_dataset, m)?)?;
    m.add("COLUMNS", dataset::columns(m.py())?)?;
    m.add("DataError", m.py().get_type::<dataset::DataError>())?;
    m.add("CallbackError", m.py().get_type::<callback::CallbackError>())?;
    Ok(())
}
