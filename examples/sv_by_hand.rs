//! What the written-once model costs: the stochastic-volatility model of
//! `stochastic_volatility.rs` written by hand against the two traits the
//! filter and the estimators use — [`ParticleModel`] with `f32` loops for the
//! filter, and [`DifferentiableModel`] with a second copy of each density on
//! the tape — timed against the same model written once ([`OnTape`]).
//!
//! `cargo run --release --example sv_by_hand`
//!
//! Both draw the same noise in the same order, so they filter alike and give
//! the same scores (checked, to f32 rounding). The table shows the median
//! seconds of each workload over repeated runs and their ratio.
use std::time::Instant;

use autodiff::dist::{normal_logpdf, HALF_LN_2PI};
use autodiff::{Float, Tensor, Var};
use rand::rngs::SmallRng;
use rand::Rng;
use rand_distr::StandardNormal;
use ssm::estimators::{Estimator, EstimatorConfig, ScoreEstimator};
use ssm::filter::{run_filter, FilterConfig, Sampling};
use ssm::models::tape_model::OnTape;
use ssm::models::{Batch, Block, DifferentiableModel, Drawn, NoiseDims, ParticleModel};

#[allow(dead_code)]
#[path = "stochastic_volatility.rs"]
mod written_once;
use written_once::{simulate, Sv};

/// The stochastic-volatility model written by hand: `theta = [phi, ln sigma, ln beta]`.
struct SvByHand<'a> {
    theta: [f64; 3],
    ys: &'a [Vec<f64>],
}

/// The filter's side: plain `f32` loops over the particles, no tape.
impl ParticleModel for SvByHand<'_> {
    type Scratch = ();
    fn new_scratch(&self) {}
    fn state_dim(&self) -> usize {
        1
    }
    /// The standard-normal draw `e_t` of the transition.
    fn action_dim(&self) -> usize {
        1
    }
    fn num_objects(&self) -> usize {
        self.ys.len()
    }
    fn num_steps(&self) -> usize {
        self.ys[0].len()
    }
    fn sample_prior(&self, _object: usize, _n: usize, rng: &mut SmallRng, states: &mut [f32], _: &mut ()) {
        for x in states {
            *x = rng.sample::<f32, _>(StandardNormal);
        }
    }
    fn propagate(&self, at: Batch, prev: &[f32], to: Drawn<'_>, rng: &mut SmallRng, scratch: &mut ()) {
        let mut z = vec![0.0f32; at.n];
        for e in z.iter_mut() {
            *e = rng.sample::<f32, _>(StandardNormal);
        }
        self.propagate_from_noise(at, prev, &z, to, scratch);
    }
    fn noise_dims(&self) -> Option<NoiseDims> {
        Some(NoiseDims { prior: 1, transition: 1 })
    }
    fn prior_from_noise(&self, _object: usize, _n: usize, noise: &[f32], states: &mut [f32], _: &mut ()) {
        states.copy_from_slice(noise);
    }
    fn propagate_from_noise(&self, _at: Batch, prev: &[f32], z: &[f32], to: Drawn<'_>, _: &mut ()) {
        let (phi, sigma) = (self.theta[0] as f32, self.theta[1].exp() as f32);
        to.actions.copy_from_slice(z);
        for ((x, &p), &e) in to.next.iter_mut().zip(prev).zip(z) {
            *x = phi * p + sigma * e;
        }
    }
    fn observation_loglik(&self, at: Batch, states: &[f32], out: &mut [f32], _: &mut ()) -> bool {
        let (y, log_beta) = (self.ys[at.object][at.t] as f32, self.theta[2] as f32);
        for (o, &x) in out.iter_mut().zip(states) {
            let log_sd = log_beta + 0.5 * x;
            let u = y * (-log_sd).exp();
            *o = -0.5 * u * u - log_sd - HALF_LN_2PI as f32;
        }
        true
    }
    fn observation_count(&self, _object: usize, _t: usize) -> usize {
        1
    }
}

/// `theta`'s scalars on the tape.
fn split<'t, F: Float>(theta: Var<'t, F>) -> [Var<'t, F>; 3] {
    [0, 1, 2].map(|i| theta.slice(0, i, 1).reshape(&[]))
}

/// The estimators' side: the same densities again, on the tape, over rows
/// laid out in blocks.
impl DifferentiableModel for SvByHand<'_> {
    fn parameters(&self) -> Vec<Tensor<f64>> {
        vec![Tensor::from_f64s(&[3], &self.theta)]
    }
    fn parameter_names(&self) -> Vec<String> {
        vec!["theta".to_string()]
    }
    fn observation_log_density<'t, F: Float>(
        &self,
        p: &[Var<'t, F>],
        blocks: &[Block],
        x: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let [_, _, log_beta] = split(p[0]);
        let ys: Vec<F> =
            blocks.iter().flat_map(|b| std::iter::repeat_n(F::from_f64(self.ys[b.object][b.t]), b.len)).collect();
        let tape = x[0].tape();
        normal_logpdf(tape.constant(Tensor::from_vec(ys)), tape.scalar(0.0), log_beta + x[0].mul_scalar(0.5))
    }
    fn transition_log_density<'t, F: Float>(
        &self,
        p: &[Var<'t, F>],
        _blocks: &[Block],
        prev: &[Var<'t, F>],
        next: &[Var<'t, F>],
        _actions: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let [phi, log_sigma, _] = split(p[0]);
        normal_logpdf(next[0], phi * prev[0], log_sigma)
    }
    fn propagate_on_tape<'t, F: Float>(
        &self,
        p: &[Var<'t, F>],
        _blocks: &[Block],
        prev: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Vec<Var<'t, F>> {
        let [phi, log_sigma, _] = split(p[0]);
        vec![phi * prev[0] + log_sigma.exp() * actions[0]]
    }
}

/// Median seconds of `repeats` runs of `work`.
fn median_seconds(repeats: usize, mut work: impl FnMut()) -> f64 {
    let mut times: Vec<f64> = (0..repeats)
        .map(|_| {
            let clock = Instant::now();
            work();
            clock.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[repeats / 2]
}

/// One workload's result under both models: `(hand, once)` of the
/// log-likelihood and score, and the median seconds of each.
struct Compared {
    name: &'static str,
    hand: (f64, Vec<f64>),
    once: (f64, Vec<f64>),
    seconds: (f64, f64),
}

/// Times the filter, PF-SEFI and DPF-SGR on `objects` sequences of `len`
/// observations with `particles` particles under both models, `repeats` times
/// each, and prints the table.
fn sv_by_hand(objects: usize, len: usize, particles: usize, repeats: usize) -> Vec<Compared> {
    let theta = [0.95, 0.25f64.ln(), 0.6f64.ln()];
    let ys = simulate(theta, objects, len, 7);
    let hand = SvByHand { theta, ys: &ys };
    let once = OnTape::new(Sv { theta, ys: &ys });
    let filter = FilterConfig::new(Sampling::new(particles, None), 0, 5);
    let config = EstimatorConfig::new(Sampling::new(particles, None));
    let ll = |m: &dyn Fn() -> f64| m();
    let mut out = Vec::new();
    let run_hand = || run_filter(&hand, &filter, |_| ()).objects.iter().map(|o| o.log_likelihood).sum::<f64>();
    let run_once = || run_filter(&once, &filter, |_| ()).objects.iter().map(|o| o.log_likelihood).sum::<f64>();
    out.push(Compared {
        name: "filter",
        hand: (ll(&run_hand), vec![]),
        once: (ll(&run_once), vec![]),
        seconds: (
            median_seconds(repeats, || {
                std::hint::black_box(run_hand());
            }),
            median_seconds(repeats, || {
                std::hint::black_box(run_once());
            }),
        ),
    });
    for (name, estimator) in [("PF-SEFI L=10", Estimator::pf_sefi(10)), ("DPF-SGR", Estimator::dpf_sgr())] {
        let estimate = |m: &dyn Fn() -> ssm::estimators::ScoreEstimate| {
            let e = m();
            (e.log_likelihood, e.gradient[0].to_f64_vec())
        };
        let run_hand = || estimator.estimate(&hand, &config, 3);
        let run_once = || estimator.estimate(&once, &config, 3);
        out.push(Compared {
            name,
            hand: estimate(&run_hand),
            once: estimate(&run_once),
            seconds: (
                median_seconds(repeats, || {
                    std::hint::black_box(run_hand());
                }),
                median_seconds(repeats, || {
                    std::hint::black_box(run_once());
                }),
            ),
        });
    }
    println!("{objects} sequences of {len} observations, {particles} particles, median of {repeats} runs");
    println!(
        "{:<14} {:>10} {:>13} {:>7}  {:>12} {:>12}",
        "workload", "by hand s", "written once", "ratio", "l_hat hand", "l_hat once"
    );
    for c in &out {
        println!(
            "{:<14} {:>10.4} {:>13.4} {:>7.2}  {:>12.3} {:>12.3}",
            c.name,
            c.seconds.0,
            c.seconds.1,
            c.seconds.1 / c.seconds.0,
            c.hand.0,
            c.once.0
        );
    }
    out
}

fn main() {
    sv_by_hand(4, 1000, 1024, 7);
}

#[cfg(test)]
mod tests {
    /// The two versions are the same model: the same likelihood and scores from
    /// the same draws, up to f32 rounding (the two compute `phi x + sigma e` and
    /// the densities in different orders).
    #[test]
    fn by_hand_and_written_once_agree() {
        for c in super::sv_by_hand(2, 100, 128, 1) {
            let (a, b) = (&c.hand, &c.once);
            assert!((a.0 - b.0).abs() < 1e-3 * (1.0 + a.0.abs()), "{}: l_hat {} vs {}", c.name, a.0, b.0);
            for (x, y) in a.1.iter().zip(&b.1) {
                assert!((x - y).abs() < 1e-2 * (1.0 + x.abs()), "{}: score {:?} vs {:?}", c.name, a.1, b.1);
            }
        }
    }
}
