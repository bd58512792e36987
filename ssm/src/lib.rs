//! State-space-model learning for road users: the vehicle motion model, policies,
//! observation models, the particle filter and fixed-lag smoother, score
//! estimators (PF-SEFI and the through-filter baselines), training, metrics,
//! datasets and model criticism.
//!
//! Data flows one way: dataset -> filter (forward, no tape) -> estimator
//! (surrogate on the tape) -> gradients -> optimiser -> parameters.
#![deny(missing_docs)]

pub mod calibration;
pub mod criticism;
pub mod data;
pub mod estimators;
pub mod filter;
pub mod metrics;
pub mod models;
pub mod npz;
pub mod objective;
pub mod reduce;
pub mod seed;
pub mod setting;
pub mod stats;
pub mod supervised;
pub mod synthetic;
pub mod training;
