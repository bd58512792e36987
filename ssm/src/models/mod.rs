//! The models floor: every model the filter and the estimators run, and nothing
//! that runs them. Above it come the filter, the estimators, training and
//! criticism; below it only the data.
//!
//! * [`traits`]: [`ParticleModel`] (what the filter needs) and
//!   [`DifferentiableModel`] with [`Block`] (what the score estimators need).
//! * [`vehicle`]: the vehicle's state, exact motion model and policies.
//! * [`observation`]: the point and box observation models and their networks.
//! * [`road_user`]: [`road_user::VehicleSsm`], the road-user state-space model of
//!   a dataset (vehicle, policy and observation model together).
//! * [`extended`]: [`extended::ExtendedSsm`], the road-user model with at most one
//!   catalogue extension, and the defensive proposal.
//! * [`drift`]: [`drift::DetectorDrift`], a detector error that persists from
//!   frame to frame, as offsets in the state of [`extended::ExtendedSsm`].
//! * [`linear_gaussian`]: the linear-Gaussian model with its exact Kalman
//!   likelihood and score, and as a particle model.
//! * [`tape_model`]: [`tape_model::TapeModel`], a user's model written once on
//!   the tape, and [`tape_model::OnTape`], which makes it a particle model and a
//!   differentiable model.
//! * [`params`]: the parameter-file convention ([`params::Models`]).
//! * `plain_mlp`: the tape-free block kernel that runs the networks in the filter.
//! * [`error`]: [`ModelError`], why a model could not be built.

pub mod drift;
pub mod error;
pub mod extended;
pub mod flip_chain;
pub mod linear_gaussian;
pub mod observation;
pub mod params;
pub(crate) mod plain_mlp;
pub mod road_user;
pub mod tape_model;
pub mod traits;
pub mod vehicle;

pub use error::ModelError;
pub use traits::{block_rows, Batch, Block, DifferentiableModel, Drawn, NoiseDims, ParticleModel};
