//! The shortest use of the library: a model, a filter, the PF-SEFI score and a
//! few steps of gradient ascent, judged by the exact Kalman log-likelihood.
//!
//! `cargo run --release --example quickstart`
use autodiff::{nn::ParamStore, optim::Adam};
use rand::{rngs::StdRng, SeedableRng};
use ssm::estimators::{EstimatorConfig, PfSefi, ScoreEstimator};
use ssm::filter::Sampling;
use ssm::models::linear_gaussian::{
    kalman::{Lgssm, LgssmTheta},
    particles::LgssmBatch,
};

/// Learns theta = (phi, ln s_v, ln s_w) of a linear-Gaussian model from `len`
/// simulated observations in `steps` steps; returns the exact log-likelihood
/// per observation at the start, at the learned and at the true parameters.
fn quickstart(len: usize, steps: usize) -> [f64; 3] {
    // x_t = phi x_{t-1} + s_v e_t,  y_t = x_t + s_w n_t;  x_0 ~ N(0, 1).
    let truth = Lgssm::new(0.0, 1.0, LgssmTheta::new(0.9, 0.5, 0.8)).unwrap();
    let ys = truth.simulate(len, &mut StdRng::seed_from_u64(0)).ys;
    let start = truth.with_theta(LgssmTheta::new(0.3, 1.5, 0.3)).unwrap();
    let mut store = ParamStore::new();
    store.add("theta", autodiff::Tensor::from_f64s(&[3], &start.theta().to_array()));
    let (config, mut adam) = (EstimatorConfig::new(Sampling::new(256, None)), Adam::new(0.05));
    for step in 0..steps {
        let theta = LgssmTheta::from_array(store.values()[0].data().try_into().unwrap());
        let data = LgssmBatch::new(truth.with_theta(theta).unwrap(), vec![ys.clone()]).unwrap();
        // The PF-SEFI score (lag 10) from one filter run with seed `step`.
        let estimate = PfSefi { lag: 10 }.estimate(&data, &config, step as u64);
        // Adam minimises: hand it minus the score per observation.
        adam.step(&mut store, &[estimate.gradient[0].map(|g| -g / len as f64)]).unwrap();
    }
    let learned = LgssmTheta::from_array(store.values()[0].data().try_into().unwrap());
    let ll = |m: &Lgssm| m.log_likelihood(&ys) / len as f64;
    println!("phi, s_v, s_w  true 0.900 0.500 0.800  start 0.300 1.500 0.300");
    println!("learned {:.3} {:.3} {:.3} in {steps} steps", learned.phi, learned.sv(), learned.sw());
    let lls = [ll(&start), ll(&truth.with_theta(learned).unwrap()), ll(&truth)];
    println!("exact log-likelihood per observation: start {:.3}  learned {:.3}  true {:.3}", lls[0], lls[1], lls[2]);
    lls
}

fn main() {
    quickstart(1000, 200);
}

#[cfg(test)]
mod tests {
    /// Learning moves the exact log-likelihood from the start most of the way to
    /// the truth's (the start is about 1 nat per observation below it).
    #[test]
    fn learns_most_of_the_way_to_the_truth() {
        let [start, learned, truth] = super::quickstart(200, 80);
        assert!(truth - learned < 0.2 * (truth - start), "start {start}, learned {learned}, truth {truth}");
    }
}
