//! The simulation floor: data drawn from the models, above the models and below
//! the filter.
//!
//! * [`synthetic`]: the paper's synthetic scenes (SPEC §4) and their true model.

pub mod synthetic;
