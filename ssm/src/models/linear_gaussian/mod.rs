//! The linear-Gaussian model, the ground truth of every filter and estimator test.
//!
//! * [`kalman`]: [`kalman::Lgssm`], the scalar model with the exact Kalman
//!   log-likelihood and score.
//! * [`particles`]: [`particles::LgssmBatch`], a batch of observation sequences
//!   under one `Lgssm` as a [`crate::models::ParticleModel`].

pub mod kalman;
pub mod particles;
