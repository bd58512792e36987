//! State-space-model learning: particle filters, score estimators (PF-SEFI and
//! the through-filter baselines), training, metrics, datasets and model
//! criticism, over any model that implements two traits. The models it ships
//! are the road user's (vehicle motion, policies, point and box observations)
//! and the linear-Gaussian model, the ground truth of its tests.
//!
//! Data flows one way: dataset -> filter (forward, no tape) -> estimator
//! (surrogate on the tape) -> gradients -> optimiser -> parameters.
//!
//! # Read first
//!
//! 1. [`models::ParticleModel`] and [`models::DifferentiableModel`]: what the
//!    filter and the estimators need of a model; the linear-Gaussian model
//!    ([`models::linear_gaussian`]) implements both and has the exact Kalman
//!    score. To bring a model of your own, write it once on the tape as a
//!    [`models::tape_model::TapeModel`] and wrap it in
//!    [`models::tape_model::OnTape`] (docs/bring-your-own-model.md).
//! 2. [`filter`]: the bootstrap and tempered particle filters
//!    ([`filter::run_filter`], [`filter::Sampling`]).
//! 3. [`estimators`]: [`estimators::PfSefi`] and the baselines behind one
//!    trait, [`estimators::ScoreEstimator`]; an estimate is a
//!    [`estimators::ScoreEstimate`] (the log-likelihood and the score).
//! 4. [`training`]: the Adam loop with logs and checkpoints;
//!    [`training::objective`] learns the road-user model of a [`data::Dataset`].
//! 5. [`criticism`]: checks of a fitted model and the diagnosis
//!    ([`criticism::diagnose::diagnose`]).
//!
//! # Floors
//!
//! The modules stand on one another in this order, bottom to top; a module
//! imports only from its own floor or the floors below it (`ssm/tests/floors.rs`
//! checks the sources):
//!
//! 0. [`util`] and [`stats`]: seeds, the settings error, exact sums across
//!    blocks and processes, `.npz` parameter files, angles; the statistics
//!    helpers (moments, quantiles, the normal law). They know nothing of data
//!    or models.
//! 1. [`data`]: datasets, their file formats and the KITTI import.
//! 2. [`models`]: every model the filter and the estimators run (the model
//!    arithmetic, the parameter-file convention).
//! 3. [`simulation`]: data drawn from the models (the paper's synthetic scenes).
//! 4. [`filter`]: the particle filters.
//! 5. [`estimators`]: the score estimators.
//! 6. [`training`]: the Adam loop, the road-user objective and the supervised
//!    observation fit.
//! 7. [`evaluation`]: metrics of a fitted model and the calibration of an
//!    estimator at given parameters.
//! 8. [`criticism`]: checks of a fitted model and the diagnosis.
//!
//! The examples of the repository (`cargo run --release --example NAME`) run
//! each of these: `quickstart`, `stochastic_volatility`, `kalman_scores`,
//! `diagnose`.
//!
//! # A score in a few lines
//!
//! The PF-SEFI score of a linear-Gaussian model against the exact one:
//!
//! ```
//! use rand::{rngs::StdRng, SeedableRng};
//! use ssm::estimators::{EstimatorConfig, PfSefi, ScoreEstimator};
//! use ssm::filter::Sampling;
//! use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmTheta};
//! use ssm::models::linear_gaussian::particles::LgssmBatch;
//!
//! let model = Lgssm::new(0.0, 1.0, LgssmTheta::new(0.9, 0.5, 0.8)).unwrap();
//! let ys = model.simulate(100, &mut StdRng::seed_from_u64(0)).ys;
//! let (exact_ll, exact_score) = model.score(&ys);
//!
//! let data = LgssmBatch::new(model, vec![ys]).unwrap();
//! let config = EstimatorConfig::new(Sampling::new(512, None));
//! let estimate = PfSefi { lag: 10 }.estimate(&data, &config, 0);
//!
//! // The filter's log-likelihood and the score, [phi, ln s_v, ln s_w].
//! assert!((estimate.log_likelihood - exact_ll).abs() < 2.0);
//! let score = estimate.gradient[0].to_f64_vec();
//! assert!((score[0] - exact_score[0]).abs() < 0.1 * exact_score[0].abs().max(10.0));
//! ```
#![deny(missing_docs)]

pub mod criticism;
pub mod data;
pub mod estimators;
pub mod evaluation;
pub mod filter;
pub mod models;
pub mod simulation;
pub mod stats;
pub mod training;
pub mod util;
