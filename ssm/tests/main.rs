//! The `ssm` crate's integration tests: one module per file of this directory,
//! built as one test binary (`cargo test -p ssm --test integration [module::]`).
//! One binary instead of one per file links once and compiles the library's
//! generic code (filters, models, estimators) once, not once per file: most of a
//! cold build of the test suite was those copies.

mod committed_reports;
mod common;
mod criticism_checks;
mod criticism_extensions;
mod data_format;
mod data_kitti;
mod detector_drift;
mod distributed;
mod estimators_lgssm;
mod estimators_pitfalls;
mod filter_lgssm;
mod filter_tempered;
mod fitted_extension;
mod floors;
mod hidden_effects;
mod lgssm;
mod metrics;
mod observation_boxes;
mod observation_clutter;
mod observation_features;
mod observation_fit;
mod observation_points;
mod observation_timing;
mod score_at_truth;
mod supervised;
mod synthetic;
mod training;
mod vehicle_motion;
mod vehicle_policy;
