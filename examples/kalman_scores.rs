//! Every score estimator against the exact score: on a linear-Gaussian model
//! the Kalman filter gives the gradient of `ln p(y_{0:T})` exactly, so each
//! estimator's bias and spread can be measured over repeated filter runs, and
//! how they grow with the length `T` of the sequence.
//!
//! `cargo run --release --example kalman_scores`
//!
//! Per `T`, one simulated sequence and `runs` seeds of each estimator (256
//! particles, f64 tapes). The table shows the `phi` component of the score
//! divided by `T`: the exact value, each estimator's bias with its standard
//! error, its standard deviation over the runs, and the bias in standard errors.
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
    println!("score of phi per transition over {runs} runs of 256 particles (z = bias / standard error)");
    println!("{:>5} {:<16} {:>8} {:>8} {:>8} {:>8} {:>7}", "T", "estimator", "exact", "bias", "se", "sd", "z");
    for &t in lengths {
        let ys = model.simulate(t + 1, &mut StdRng::seed_from_u64(t as u64)).ys;
        let study = score_study(&model, &ys, &estimators(), &config, runs, 1);
        let per = |x: f64| x / t as f64;
        for r in study.iter().filter(|r| r.component == "phi") {
            let (exact, bias, se, sd) = (per(r.exact), per(r.bias), per(r.se), per(r.sd));
            println!("{t:>5} {:<16} {exact:>8.4} {bias:>+8.4} {se:>8.4} {sd:>8.4} {:>+7.1}", r.estimator, r.z());
        }
        rows.extend(study);
    }
    rows
}

fn main() {
    kalman_scores(&[50, 200, 800], 100);
}

#[cfg(test)]
mod tests {
    /// At T = 200: PF-SEFI's bias (from its fixed lag and the particle
    /// approximation) is under 0.03 per transition on every component (the
    /// exact score of `phi` is about 0.5 per transition), and its spread a
    /// small fraction of DPF-SGR's; PF, which drops the resampling's part of
    /// the score, is biased by many standard errors.
    #[test]
    fn pf_sefi_is_close_and_precise_and_pf_is_biased() {
        let rows = super::kalman_scores(&[200], 40);
        let find = |e: &str, c: &str| rows.iter().find(|r| r.estimator == e && r.component == c).unwrap();
        for c in ["phi", "log_sv", "log_sw"] {
            let sefi = find("pf-sefi L=10", c);
            assert!(sefi.bias.abs() / 200.0 < 0.03, "pf-sefi {c}: {sefi:?}");
        }
        // On phi, PF-SEFI's spread is about a twentieth of DPF-SGR's (the printed table).
        let (sefi, dpf) = (find("pf-sefi L=10", "phi"), find("dpf-sgr", "phi"));
        assert!(sefi.sd < dpf.sd / 4.0, "pf-sefi phi sd {} against dpf-sgr's {}", sefi.sd, dpf.sd);
        let pf = find("pf", "phi");
        assert!(pf.z().abs() > 6.0, "pf phi: bias {} se {}", pf.bias, pf.se);
    }
}
