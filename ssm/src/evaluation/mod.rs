//! The evaluation floor: how good a fitted model is, above the filter, the
//! estimators and training, and below criticism.
//!
//! * [`metrics`]: the paper's metrics (test MLL, AOTLL, APTLL, state errors) and
//!   the median and IQR of repeated runs.
//! * [`calibration`]: an estimator's score and the filter's likelihood at given
//!   parameters (is the score centred at the truth, how precise is the estimate).

pub mod calibration;
pub mod metrics;
