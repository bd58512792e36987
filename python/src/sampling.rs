//! The particle filter's sampling options from Python keyword arguments.

use pyo3::exceptions::PyValueError;
use pyo3::PyResult;
use ssm::filter::{Resampling, Sampling};

use crate::convert::check;

/// [`Sampling`] from `particles`, a resampling scheme's name and an optional ESS
/// threshold (a fraction of the particles in `(0, 1]`).
pub fn sampling(particles: usize, resampling: &str, ess_threshold: Option<f64>) -> PyResult<Sampling> {
    check(particles > 0, "particles", || "must be at least 1".into())?;
    let resampling = match resampling {
        "systematic" => Resampling::Systematic,
        "multinomial" => Resampling::Multinomial,
        other => {
            return Err(PyValueError::new_err(format!(
                "resampling: expected 'systematic' or 'multinomial', got {other:?}"
            )))
        }
    };
    if let Some(f) = ess_threshold {
        check(f.is_finite() && f > 0.0 && f <= 1.0, "ess_threshold", || format!("must be in (0, 1], got {f}"))?;
    }
    Ok(Sampling { particles, resampling, ess_threshold, tempering: None })
}
