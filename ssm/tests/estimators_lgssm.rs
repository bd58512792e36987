//! Every score estimator against the exact Kalman score on the linear-Gaussian
//! model: the identities that tie the code paths together, and the statistical
//! properties the method stands on (SPEC §2).

use crate::common::assert_unbiased;
use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::estimators::study::{score_study, ScoreStudyRow};
use ssm::estimators::{Estimator, EstimatorConfig, Precision, ScoreEstimator};
use ssm::filter::{Resampling, Sampling};
use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmTheta};
use ssm::models::linear_gaussian::particles::LgssmBatch;

fn batch(len: usize, objects: usize, seed: u64) -> LgssmBatch {
    let model = Lgssm::stationary(LgssmTheta::new(0.9, 0.7, 1.0)).unwrap();
    let mut rng = StdRng::seed_from_u64(seed);
    let seqs = (0..objects).map(|_| model.simulate(len, &mut rng).ys).collect();
    LgssmBatch::new(model, seqs).unwrap()
}

fn config(n: usize, precision: Precision) -> EstimatorConfig {
    EstimatorConfig { sampling: Sampling::new(n, None), precision, chunk_objects: 2 }
}

#[test]
fn dpf_sgr_with_stopped_particles_equals_full_path_pf_sefi() {
    let data = batch(30, 3, 1);
    for resampling in [Resampling::Systematic, Resampling::Multinomial] {
        let mut cfg = config(64, Precision::F64);
        cfg.sampling.resampling = resampling;
        for seed in 0..3 {
            let sefi = Estimator::pf_sefi(40).estimate(&data, &cfg, seed);
            let dpf = Estimator::dpf_sgr_stopped().estimate(&data, &cfg, seed);
            // Same filter, same draws: the same l_hat exactly.
            assert_eq!(sefi.log_likelihood, dpf.log_likelihood);
            // PF-SEFI weighs by the filter's weights (from f32 log-likelihoods); the
            // replay recomputes them on an f64 tape: equal to single-precision rounding.
            for (a, b) in sefi.gradient[0].data().iter().zip(dpf.gradient[0].data()) {
                assert!((a - b).abs() <= 2e-6 * (1.0 + a.abs()), "{resampling:?} seed {seed}: {a} vs {b}");
            }
        }
    }
}

/// The rows of one estimator.
fn of<'a>(rows: &'a [ScoreStudyRow], label: &str) -> Vec<&'a ScoreStudyRow> {
    let r: Vec<_> = rows.iter().filter(|r| r.estimator == label).collect();
    assert_eq!(r.len(), 3, "{label}");
    r
}

/// 200 runs of N = 512 particles on one sequence of `T + 1` observations.
fn study(transitions: usize, estimators: &[Estimator]) -> Vec<ScoreStudyRow> {
    let model = Lgssm::stationary(LgssmTheta::new(0.9, 0.7, 1.0)).unwrap();
    let ys = model.simulate(transitions + 1, &mut StdRng::seed_from_u64(5)).ys;
    score_study(&model, &ys, estimators, &config(512, Precision::F64), 200, 0)
}

/// PF-SEFI's fixed-lag bias: large with filter marginals (L = 0), gone (within 3
/// standard errors, plus 5% of one run's spread) at L = 10.
#[test]
fn pf_sefi_bias_shrinks_with_the_lag_and_vanishes_at_lag_ten() {
    for transitions in [25, 100] {
        let rows = study(transitions, &[Estimator::pf_sefi(0), Estimator::pf_sefi(10)]);
        let (l0, l10) = (of(&rows, "pf-sefi L=0"), of(&rows, "pf-sefi L=10"));
        let total = |r: &[&ScoreStudyRow]| r.iter().map(|r| r.bias.abs()).sum::<f64>();
        assert!(total(&l10) < 0.2 * total(&l0), "T={transitions}: |bias| L=0 {} vs L=10 {}", total(&l0), total(&l10));
        assert!(l0.iter().any(|r| r.z().abs() > 10.0), "T={transitions}: L=0 should be visibly biased");
        for r in &l10 {
            assert_unbiased(&format!("T={transitions}"), r, 3.0);
        }
    }
}

/// At T = 100, PF-SEFI (L = 10) has the smallest root-mean-square error, and PF's
/// resampling bias is real: its mean is many standard errors from the exact score.
#[test]
fn pf_sefi_beats_every_baseline_at_t_100_and_pf_is_biased() {
    let rows = study(100, &[Estimator::pf_sefi(10), Estimator::pf(), Estimator::dpf_sgr(), Estimator::pfnet(0.8)]);
    let rmse = |label: &str| of(&rows, label).iter().map(|r| r.rmse * r.rmse).sum::<f64>().sqrt();
    let sefi = rmse("pf-sefi L=10");
    for baseline in ["pf", "dpf-sgr", "pfnet a=0.8"] {
        assert!(sefi < rmse(baseline), "rmse: pf-sefi {sefi} vs {baseline} {}", rmse(baseline));
    }
    let pf = of(&rows, "pf");
    assert!(
        pf.iter().any(|r| r.z().abs() > 6.0),
        "PF bias z-scores: {:?}",
        pf.iter().map(|r| r.z()).collect::<Vec<_>>()
    );
}
