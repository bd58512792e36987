//! Every score estimator against the exact score: on a linear-Gaussian model
//! the Kalman filter gives the gradient of `ln p(y_{0:T})` exactly, so each
//! estimator's bias and spread can be measured over repeated filter runs, and
//! how they grow with the length `T` of the sequence.
//!
//! `cargo run --release --example kalman_scores`
//!
//! Per `T`, one simulated sequence and `runs` seeds of each estimator (256
//! particles, f64 tapes). The table shows the `phi` component of the score
//! divided by `T`: the exact value, then each estimator's bias with its
//! standard error and its standard deviation over the runs.
use rand::{rngs::StdRng, SeedableRng};
use ssm::estimators::study::{score_study, ScoreStudyRow};
use ssm::estimators::{Estimator, EstimatorConfig, Precision};
use ssm::filter::Sampling;
use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmTheta};

/// The estimators compared.
fn estimators() -> Vec<Estimator> {
    vec![
        Estimator::pf_sefi(10),
        Estimator::pf(),
        Estimator::dpf_sgr(),
        Estimator::dpf_sgr_stopped(),
        Estimator::pfnet(0.8),
    ]
}

/// Runs the study at each `T` of `lengths` with `runs` seeds; prints the table
/// of the `phi` component and returns every row.
fn kalman_scores(lengths: &[usize], runs: usize) -> Vec<ScoreStudyRow> {
    let model = Lgssm::new(0.0, 1.0, LgssmTheta::new(0.9, 0.5, 0.8)).unwrap();
    let config = EstimatorConfig { precision: Precision::F64, ..EstimatorConfig::new(Sampling::new(256, None)) };
    let mut rows = Vec::new();
    println!("score of phi per transition, {runs} runs of 256 particles: bias (standard error) and sd");
    println!(
        "{:>5} {:>8}  {}",
        "T",
        "exact",
        estimators().iter().map(|e| format!("{:>24}", ssm::estimators::study::label(e))).collect::<String>()
    );
    for &t in lengths {
        let ys = model.simulate(t + 1, &mut StdRng::seed_from_u64(t as u64)).ys;
        let study = score_study(&model, &ys, &estimators(), &config, runs, 1);
        let phi: Vec<&ScoreStudyRow> = study.iter().filter(|r| r.component == "phi").collect();
        let per = |x: f64| x / t as f64;
        let cells: String = phi
            .iter()
            .map(|r| format!("{:>24}", format!("{:+.4} ({:.4}) sd {:.3}", per(r.bias), per(r.se), per(r.sd))))
            .collect();
        println!("{t:>5} {:>8.4}  {cells}", per(phi[0].exact));
        rows.extend(study);
    }
    rows
}

fn main() {
    kalman_scores(&[50, 200, 800], 100);
}

#[cfg(test)]
mod tests {
    /// PF-SEFI's estimate agrees with the exact score within its Monte Carlo
    /// error (|z| < 4 on every component), and PF, which drops the resampling's
    /// score term, is biased on `phi` by many standard errors at this `T`.
    #[test]
    fn pf_sefi_agrees_with_kalman_and_pf_does_not() {
        let rows = super::kalman_scores(&[200], 40);
        let sefi: Vec<_> = rows.iter().filter(|r| r.estimator.starts_with("pf-sefi")).collect();
        assert_eq!(sefi.len(), 3);
        for r in &sefi {
            assert!(r.z().abs() < 4.0, "pf-sefi {}: bias {} se {}", r.component, r.bias, r.se);
        }
        let pf = rows.iter().find(|r| r.estimator == "pf" && r.component == "phi").unwrap();
        assert!(pf.z().abs() > 6.0, "pf phi: bias {} se {}", pf.bias, pf.se);
    }
}
