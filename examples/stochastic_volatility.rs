//! A model the project does not ship, learned by PF-SEFI and by DPF-SGR: the
//! stochastic-volatility model
//!
//! ```text
//! x_0 ~ N(0, 1)
//! x_t = phi x_{t-1} + sigma e_t        e_t ~ N(0, 1)
//! y_t = beta exp(x_t / 2) u_t          u_t ~ N(0, 1)
//! ```
//!
//! with `theta = (phi, ln sigma, ln beta)`. The model is written once, as tape
//! expressions generic over the float type ([`TapeModel`]); [`OnTape`] serves
//! it to the particle filter (forward, `f32`, no tape) and to the score
//! estimators (on a tape). Data are simulated at the true `theta`; both
//! estimators start from the same wrong `theta` and climb the score with Adam.
//! docs/bring-your-own-model.md walks through this file.
//!
//! `cargo run --release --example stochastic_volatility`
use std::time::Instant;

use autodiff::dist::normal_logpdf;
use autodiff::{nn::ParamStore, optim::Adam, Float, Tensor, Var};
use rand::{rngs::StdRng, Rng, SeedableRng};
use rand_distr::StandardNormal;
use ssm::estimators::{Estimator, EstimatorConfig, ScoreEstimator};
use ssm::filter::{run_filter, FilterConfig, Sampling};
use ssm::models::tape_model::{OnTape, TapeModel};

/// The stochastic-volatility model over some observation sequences.
pub struct Sv<'a> {
    /// `[phi, ln sigma, ln beta]`.
    pub theta: [f64; 3],
    /// One sequence `y_{0:T}` per object.
    pub ys: &'a [Vec<f64>],
}

/// `theta`'s three scalars on the tape, split from the one `[3]` parameter
/// (gradients flow back into it).
fn split<'t, F: Float>(theta: Var<'t, F>) -> [Var<'t, F>; 3] {
    [0, 1, 2].map(|i| theta.slice(0, i, 1).reshape(&[]))
}

impl TapeModel for Sv<'_> {
    fn state_dim(&self) -> usize {
        1
    }
    fn observation_dim(&self) -> usize {
        1
    }
    fn num_objects(&self) -> usize {
        self.ys.len()
    }
    fn num_steps(&self) -> usize {
        self.ys[0].len()
    }
    fn observation(&self, object: usize, t: usize) -> Option<&[f64]> {
        Some(std::slice::from_ref(&self.ys[object][t]))
    }
    fn parameters(&self) -> Vec<Tensor<f64>> {
        vec![Tensor::from_f64s(&[3], &self.theta)]
    }
    fn parameter_names(&self) -> Vec<String> {
        vec!["theta".to_string()]
    }
    /// `x_0 = z`: the prior `N(0, 1)`.
    fn prior<'t, F: Float>(&self, z: &[Var<'t, F>]) -> Vec<Var<'t, F>> {
        z.to_vec()
    }
    /// `x_t = phi x_{t-1} + sigma z`.
    fn transition<'t, F: Float>(&self, p: &[Var<'t, F>], prev: &[Var<'t, F>], z: &[Var<'t, F>]) -> Vec<Var<'t, F>> {
        let [phi, log_sigma, _] = split(p[0]);
        vec![phi * prev[0] + log_sigma.exp() * z[0]]
    }
    /// `ln N(x_t; phi x_{t-1}, sigma^2)`.
    fn transition_log_density<'t, F: Float>(
        &self,
        p: &[Var<'t, F>],
        prev: &[Var<'t, F>],
        next: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let [phi, log_sigma, _] = split(p[0]);
        normal_logpdf(next[0], phi * prev[0], log_sigma)
    }
    /// `ln N(y_t; 0, beta^2 exp(x_t))`: the sd's log is `ln beta + x_t / 2`.
    fn observation_log_density<'t, F: Float>(
        &self,
        p: &[Var<'t, F>],
        y: &[Var<'t, F>],
        x: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let [_, _, log_beta] = split(p[0]);
        normal_logpdf(y[0], y[0].tape().scalar(0.0), log_beta + x[0].mul_scalar(0.5))
    }
}

/// `objects` sequences of `len` observations at `theta = [phi, ln sigma, ln beta]`.
pub fn simulate(theta: [f64; 3], objects: usize, len: usize, seed: u64) -> Vec<Vec<f64>> {
    let [phi, sigma, beta] = [theta[0], theta[1].exp(), theta[2].exp()];
    let mut rng = StdRng::seed_from_u64(seed);
    let mut normal = move || rng.sample::<f64, _>(StandardNormal);
    (0..objects)
        .map(|_| {
            let mut x = normal();
            (0..len)
                .map(|t| {
                    if t > 0 {
                        x = phi * x + sigma * normal();
                    }
                    beta * (x / 2.0).exp() * normal()
                })
                .collect()
        })
        .collect()
}

/// `steps` Adam steps on the score `estimator` gives, from `start`: the learned
/// `theta` and the seconds taken.
fn learn(estimator: Estimator, ys: &[Vec<f64>], start: [f64; 3], steps: usize) -> ([f64; 3], f64) {
    let clock = Instant::now();
    let units: usize = ys.iter().map(Vec::len).sum();
    let config = EstimatorConfig::new(Sampling::new(256, None));
    let mut store = ParamStore::new();
    store.add("theta", Tensor::from_f64s(&[3], &start));
    let mut adam = Adam::new(0.02);
    for step in 0..steps {
        let theta: [f64; 3] = store.values()[0].to_f64_vec().try_into().unwrap();
        let estimate = estimator.estimate(&OnTape::new(Sv { theta, ys }), &config, step as u64);
        // Adam minimises: minus the score per observation.
        let _ = adam.step(&mut store, &[estimate.gradient[0].map(|g| -g / units as f64)]);
    }
    (store.values()[0].to_f64_vec().try_into().unwrap(), clock.elapsed().as_secs_f64())
}

/// The particle filter's log-likelihood per observation at `theta` (4096
/// particles, one seed for every `theta`).
fn log_likelihood(ys: &[Vec<f64>], theta: [f64; 3]) -> f64 {
    let config = FilterConfig::new(Sampling::new(4096, None), 0, 99);
    let run = run_filter(&OnTape::new(Sv { theta, ys }), &config, |_| ());
    let units: usize = ys.iter().map(Vec::len).sum();
    run.objects.iter().map(|o| o.log_likelihood).sum::<f64>() / units as f64
}

/// What one run found: the truth, the start, and each estimator's learned
/// `theta` with its seconds.
#[cfg_attr(not(test), allow(dead_code))]
struct Outcome {
    truth: [f64; 3],
    start: [f64; 3],
    learned: Vec<(&'static str, [f64; 3], f64)>,
}

/// Simulates `objects` sequences of `len` observations, learns `theta` with
/// PF-SEFI and DPF-SGR in `steps` steps each and prints the table.
fn stochastic_volatility(objects: usize, len: usize, steps: usize) -> Outcome {
    let natural = |t: [f64; 3]| [t[0], t[1].exp(), t[2].exp()];
    let truth = [0.95, 0.25f64.ln(), 0.6f64.ln()];
    let start = [0.5, 1.0f64.ln(), 2.0f64.ln()];
    let ys = simulate(truth, objects, len, 7);
    let learned = vec![("PF-SEFI L=10", Estimator::pf_sefi(10)), ("DPF-SGR", Estimator::dpf_sgr())]
        .into_iter()
        .map(|(name, e)| {
            let (theta, seconds) = learn(e, &ys, start, steps);
            (name, theta, seconds)
        })
        .collect::<Vec<_>>();
    println!("{objects} sequences of {len} observations, {steps} Adam steps, 256 particles");
    println!("{:<14} {:>7} {:>7} {:>7} {:>12} {:>9}", "", "phi", "sigma", "beta", "l_hat/obs", "seconds");
    let row = |name: &str, t: [f64; 3], seconds: &str| {
        let [phi, sigma, beta] = natural(t);
        println!("{name:<14} {phi:>7.3} {sigma:>7.3} {beta:>7.3} {:>12.4} {seconds:>9}", log_likelihood(&ys, t));
    };
    row("truth", truth, "");
    row("start", start, "");
    for (name, theta, seconds) in &learned {
        row(name, *theta, &format!("{seconds:.1}"));
    }
    Outcome { truth, start, learned }
}

fn main() {
    stochastic_volatility(4, 1000, 300);
}

#[cfg(test)]
mod tests {
    /// Both estimators end far closer to the truth than they started: each
    /// learned `theta` is within a third of the start's distance from the truth
    /// (in `(phi, ln sigma, ln beta)`).
    #[test]
    fn both_estimators_learn_towards_the_truth() {
        let out = super::stochastic_volatility(2, 300, 150);
        let distance = |t: [f64; 3]| t.iter().zip(&out.truth).map(|(a, b)| (a - b).powi(2)).sum::<f64>().sqrt();
        for (name, theta, _) in &out.learned {
            assert!(distance(*theta) < distance(out.start) / 3.0, "{name}: {theta:?} from {:?}", out.start);
        }
    }
}
