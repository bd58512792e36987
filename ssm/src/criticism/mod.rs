//! Model criticism (SPEC §7): what the fitted simulation gets wrong, which
//! catalogue extension explains it, and how much it gains.
//!
//! * [`extensions`](crate::models::extended): the catalogue — latency, clutter, size bias, heavy-tailed
//!   acceleration, heading flips, heading flips in runs — each a model component with learnable
//!   parameters ([`ExtendedSsm`](crate::models::extended::ExtendedSsm)) that PF-SEFI trains like the base.
//! * [`checks`]: discrepancy statistics of drawn paths and their observations,
//!   computed alike on measured and replicated data (posterior predictive checks).
//! * [`hidden`]: generated datasets with one hidden effect each, to test that the
//!   diagnosis finds it.
//! * [`diagnose`]: the procedure — fit the base, check it, fit the plausible
//!   extensions, choose by held-out log-likelihood, re-check.

pub mod checks;
pub mod diagnose;
pub mod hidden;

use crate::data::{Action, State};
use crate::models::extended::ObjectObservations;

/// A path of one object with observations: what a discrepancy statistic looks at.
/// For the measured data the observations are the dataset's and the path a draw
/// from the smoother; for a replicate the same path's observations and actions
/// are simulated from the fitted model.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectSample {
    /// Index of the object in its dataset ([`crate::data::Dataset::objects`]).
    pub object: usize,
    /// States `x_0..x_T`.
    pub states: Vec<State>,
    /// Actions `a_1..a_T` (`actions[t - 1]` leads from `x_{t-1}` to `x_t`).
    pub actions: Vec<Action>,
    /// Observations `y_0..y_T`.
    pub observations: ObjectObservations,
    /// The accelerations' innovations standardised by the checked model's
    /// Gaussian policy, `(accel - mean(x_{t-1})) / sd(x_{t-1})`, one per action;
    /// empty when unknown (the checks then use the raw accelerations).
    pub accel_innovations: Vec<f64>,
}
