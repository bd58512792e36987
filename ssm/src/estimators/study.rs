//! Estimators against the exact score: on the linear-Gaussian model the Kalman
//! filter gives `log p(y_{0:T})` and its gradient exactly, so the bias, standard
//! deviation and root-mean-square error of every estimator can be measured over
//! repeated runs on one observation sequence.

use rayon::prelude::*;
use serde::Serialize;

use super::{Estimator, EstimatorConfig, ScoreEstimator};
use crate::models::linear_gaussian::kalman::Lgssm;
use crate::models::linear_gaussian::particles::LgssmBatch;

/// Names of the score components, in the order of [`crate::models::linear_gaussian::kalman::LgssmTheta::to_array`].
pub const COMPONENTS: [&str; 3] = ["phi", "log_sv", "log_sw"];

/// One estimator's error on one score component.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ScoreStudyRow {
    /// `T` (the sequence has `T + 1` observations).
    pub transitions: usize,
    /// The estimator's name (with its lag or alpha).
    pub estimator: String,
    /// The component (`phi`, `log_sv`, `log_sw`).
    pub component: String,
    /// The exact score.
    pub exact: f64,
    /// Mean of the estimates.
    pub mean: f64,
    /// `mean - exact`.
    pub bias: f64,
    /// Standard deviation of the estimates.
    pub sd: f64,
    /// Standard error of the mean (`sd / sqrt(runs)`).
    pub se: f64,
    /// Root-mean-square error against the exact score.
    pub rmse: f64,
    /// Runs.
    pub runs: usize,
}

impl ScoreStudyRow {
    /// `bias / se`: how many standard errors the mean is from the exact score.
    pub fn z(&self) -> f64 {
        self.bias / self.se
    }
}

/// A label for an estimator with its setting (`pf-sefi L=10`, `pfnet a=0.8`).
pub fn label(estimator: &Estimator) -> String {
    match estimator {
        Estimator::PfSefi(e) => format!("pf-sefi L={}", e.lag),
        Estimator::ThroughFilter(t) => match t.kind {
            super::ThroughFilterKind::Pfnet { alpha } => format!("pfnet a={alpha}"),
            _ => estimator.name(),
        },
    }
}

/// Runs each estimator `runs` times (seeds `seed..seed + runs`) on the sequence
/// `ys` under `model` and compares with the exact score: one row per estimator
/// and component.
pub fn score_study(
    model: &Lgssm,
    ys: &[f64],
    estimators: &[Estimator],
    config: &EstimatorConfig,
    runs: usize,
    seed: u64,
) -> Vec<ScoreStudyRow> {
    assert!(runs >= 2 && !ys.is_empty(), "score_study: need two runs and one observation");
    let (_, exact) = model.score(ys);
    let data = LgssmBatch::new(model.clone(), vec![ys.to_vec()]).expect("one non-empty sequence");
    let mut rows = Vec::new();
    for estimator in estimators {
        let estimates: Vec<[f64; 3]> = (0..runs as u64)
            .into_par_iter()
            .map(|r| {
                let e = estimator.estimate(&data, config, seed.wrapping_add(r));
                let g = e.gradient[0].data();
                [g[0], g[1], g[2]]
            })
            .collect();
        for (k, name) in COMPONENTS.iter().enumerate() {
            let xs: Vec<f64> = estimates.iter().map(|e| e[k]).collect();
            let n = xs.len() as f64;
            let mean = xs.iter().sum::<f64>() / n;
            let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
            let mse = xs.iter().map(|x| (x - exact[k]).powi(2)).sum::<f64>() / n;
            rows.push(ScoreStudyRow {
                transitions: ys.len() - 1,
                estimator: label(estimator),
                component: name.to_string(),
                exact: exact[k],
                mean,
                bias: mean - exact[k],
                sd: var.sqrt(),
                se: (var / n).sqrt(),
                rmse: mse.sqrt(),
                runs,
            });
        }
    }
    rows
}
