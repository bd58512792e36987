//! The vehicle model (SPEC §3): state and action types, the exact motion model and
//! the policies that choose actions.
//!
//! * [`state`]: one object's [`VehicleState`] and [`Action`], struct-of-arrays
//!   batches for the filter's loops, and their counterparts on a tape.
//! * [`motion`]: the deterministic, differentiable [`MotionModel`] (cubic yaw,
//!   Gauss–Legendre positions), the paper's closed form and a reference integrator.
//! * [`policy`]: the [`GaussianPolicy`] trait and the [`HandCraftedPolicy`] of the
//!   synthetic data.
//! * [`neural`]: the [`NeuralPolicy`] of the measured data.

pub mod motion;
pub mod neural;
pub mod policy;
pub mod state;

pub use motion::{MotionError, MotionModel, Quadrature, DEFAULT_DT};
pub use neural::NeuralPolicy;
pub use policy::{ActionGaussianVars, ActionGaussians, GaussianPolicy, HandCraftedPolicy, PolicyError};
pub use state::{
    Action, ActionBatch, ActionVars, ActionsMut, ActionsRef, StateBatch, StateVars, StatesMut, StatesRef, VehicleState,
    ACTION_DIM, STATE_DIM,
};
