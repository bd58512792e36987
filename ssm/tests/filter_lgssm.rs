//! The particle filter against the Kalman filter on the linear-Gaussian model: the
//! likelihood estimate is unbiased (in the exp domain), filtering and smoothed means
//! converge to the exact ones as N grows, results do not depend on the thread count,
//! and collapsed steps are handled without NaN.

use rand::rngs::{SmallRng, StdRng};
use rand::SeedableRng;
use ssm::filter::{run_filter, FilterConfig, LagView, Moments, Observer, Resampling, Sampling};
use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmTheta};
use ssm::models::linear_gaussian::particles::LgssmBatch;
use ssm::models::{Batch, Drawn, ParticleModel};

fn model() -> Lgssm {
    Lgssm::stationary(LgssmTheta::new(0.9, 0.5, 0.7)).unwrap()
}

fn sequence(len: usize, seed: u64) -> Vec<f64> {
    model().simulate(len, &mut StdRng::seed_from_u64(seed)).ys
}

/// `objects` copies of one sequence: independent filter runs on the same data.
fn replicated(ys: &[f64], objects: usize) -> LgssmBatch {
    LgssmBatch::new(model(), vec![ys.to_vec(); objects]).unwrap()
}

fn config(n: usize, lag: usize, resampling: Resampling, ess: Option<f64>) -> FilterConfig {
    FilterConfig::new(Sampling { particles: n, resampling, ess_threshold: ess, tempering: None }, lag, 17)
}

/// mean of exp(l_hat - l) over runs and its standard error.
fn ratio_stats(batch: &LgssmBatch, cfg: &FilterConfig, exact: f64) -> (f64, f64) {
    let run = run_filter(batch, cfg, |_| ());
    let r: Vec<f64> = run.objects.iter().map(|o| (o.log_likelihood - exact).exp()).collect();
    let m = r.iter().sum::<f64>() / r.len() as f64;
    let var = r.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (r.len() - 1) as f64;
    (m, (var / r.len() as f64).sqrt())
}

#[test]
fn likelihood_estimate_is_unbiased_for_every_resampling_scheme() {
    let ys = sequence(26, 1);
    let exact = model().log_likelihood(&ys);
    for (scheme, ess) in [
        (Resampling::Systematic, None),
        (Resampling::Multinomial, None),
        (Resampling::Systematic, Some(0.5)),
        (Resampling::Multinomial, Some(0.5)),
    ] {
        let (m, se) = ratio_stats(&replicated(&ys, 400), &config(128, 0, scheme, ess), exact);
        // exp(l_hat) is unbiased: the mean ratio is 1 within 4 standard errors (plus
        // 1% for the heavy right tail of a ratio of likelihoods at 400 runs).
        assert!((m - 1.0).abs() < 4.0 * se + 0.01, "{scheme:?} ess {ess:?}: mean ratio {m} +- {se}");
        assert!(se < 0.1, "the check must have power: se {se}");
    }
}

#[test]
fn likelihood_bias_in_log_domain_is_about_half_the_variance() {
    // l_hat is biased low by about var(l_hat) / 2: it is reported, not differentiated.
    let ys = sequence(26, 2);
    let exact = model().log_likelihood(&ys);
    let run = run_filter(&replicated(&ys, 400), &config(64, 0, Resampling::Systematic, None), |_| ());
    let l: Vec<f64> = run.objects.iter().map(|o| o.log_likelihood - exact).collect();
    let m = l.iter().sum::<f64>() / l.len() as f64;
    let var = l.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (l.len() - 1) as f64;
    assert!(m < 0.0 && (m + var / 2.0).abs() < 0.5 * var + 3.0 * (var / 400.0).sqrt(), "bias {m}, var {var}");
}

fn mean_errors(n: usize, lag: usize) -> (f64, f64) {
    let ys = sequence(40, 3);
    let exact_f = model().filter(&ys);
    let exact_s = model().smooth(&ys);
    let batch = replicated(&ys, 8);
    let run = run_filter(&batch, &config(n, lag, Resampling::Systematic, None), |_| Moments::new(1, &[]));
    let (mut ef, mut es) = (0.0, 0.0);
    for m in &run.observers {
        assert_eq!(m.smoothed.len(), ys.len(), "every step smoothed exactly once");
        for t in 0..ys.len() {
            ef += (m.filtered[t][0] - exact_f.mean[t]).powi(2);
            // Fixed lag L >= T reaches the full smoother's conditioning set.
            es += (m.smoothed[t][0] - exact_s.mean[t]).powi(2);
        }
    }
    let k = (8 * ys.len()) as f64;
    ((ef / k).sqrt(), (es / k).sqrt())
}

#[test]
fn filtering_and_smoothed_means_converge_to_kalman() {
    let (f_small, s_small) = mean_errors(64, 39);
    let (f_big, s_big) = mean_errors(2048, 39);
    // Monte-Carlo error shrinks like 1/sqrt(N): 32 times more particles, ~5.7x less error.
    assert!(f_big < f_small / 2.5 && s_big < s_small / 2.0, "filter {f_small}->{f_big}, smoother {s_small}->{s_big}");
    // Posterior sds are ~0.5: at N = 2048 the means are within a few hundredths.
    assert!(f_big < 0.03 && s_big < 0.06, "filter {f_big}, smoother {s_big}");
}

#[test]
fn fixed_lag_smoother_sits_between_filter_and_full_smoother() {
    // With lag 5 on a model with phi = 0.9 the fixed-lag means are much closer to the
    // full smoother than the filtering means are.
    let ys = sequence(40, 4);
    let exact_f = model().filter(&ys);
    let exact_s = model().smooth(&ys);
    let gap: f64 = (0..40).map(|t| (exact_f.mean[t] - exact_s.mean[t]).powi(2)).sum::<f64>();
    let run = run_filter(&replicated(&ys, 4), &config(4096, 5, Resampling::Systematic, None), |_| Moments::new(1, &[]));
    for m in &run.observers {
        let err: f64 = (0..40).map(|t| (m.smoothed[t][0] - exact_s.mean[t]).powi(2)).sum();
        assert!(err < 0.2 * gap, "fixed-lag error {err} vs filter-smoother gap {gap}");
    }
}

#[test]
fn results_do_not_depend_on_the_thread_count() {
    let ys = sequence(30, 5);
    let batch = replicated(&ys, 16);
    let cfg = config(256, 4, Resampling::Multinomial, Some(0.5));
    let run = || run_filter(&batch, &cfg, |_| Moments::new(1, &[]));
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap().install(run);
    let two = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap().install(run);
    assert_eq!(one.objects, two.objects);
    for (a, b) in one.observers.iter().zip(&two.observers) {
        assert_eq!(a, b);
    }
    // And different objects draw different streams.
    assert_ne!(one.objects[0].log_likelihood, one.objects[1].log_likelihood);
}

/// Records that smoothing weights sum to one and parents index the previous step.
struct WeightAudit {
    steps: Vec<usize>,
}

impl Observer for WeightAudit {
    fn smoothed(&mut self, v: &LagView<'_>) {
        let s: f64 = v.weights.iter().sum();
        assert!((s - 1.0).abs() < 1e-9, "pushed-back weights sum to {s}");
        assert!(v.parents.iter().all(|&p| p < v.n));
        assert_eq!(v.prev_states.is_some(), v.t > 0);
        self.steps.push(v.t);
    }
}

#[test]
fn every_step_is_smoothed_once_in_order_for_any_lag() {
    let ys = sequence(12, 6);
    for lag in [0, 1, 5, 11, 12, 40] {
        let run = run_filter(&replicated(&ys, 2), &config(32, lag, Resampling::Systematic, Some(0.3)), |_| {
            WeightAudit { steps: vec![] }
        });
        for o in &run.observers {
            assert_eq!(o.steps, (0..12).collect::<Vec<_>>(), "lag {lag}");
        }
    }
}

/// The linear-Gaussian model with one step at which every particle is impossible.
struct Collapsing(LgssmBatch);

impl ParticleModel for Collapsing {
    type Scratch = ();
    fn new_scratch(&self) {}
    fn state_dim(&self) -> usize {
        1
    }
    fn action_dim(&self) -> usize {
        1
    }
    fn num_objects(&self) -> usize {
        self.0.num_objects()
    }
    fn num_steps(&self) -> usize {
        self.0.num_steps()
    }
    fn sample_prior(&self, o: usize, n: usize, rng: &mut SmallRng, s: &mut [f32], _: &mut ()) {
        self.0.sample_prior(o, n, rng, s, &mut ())
    }
    fn propagate(&self, at: Batch, p: &[f32], to: Drawn<'_>, r: &mut SmallRng, _: &mut ()) {
        self.0.propagate(at, p, to, r, &mut ())
    }
    fn observation_loglik(&self, at: Batch, s: &[f32], out: &mut [f32], _: &mut ()) -> bool {
        self.0.observation_loglik(at, s, out, &mut ());
        if at.t == 3 {
            out.iter_mut().enumerate().for_each(|(i, v)| *v = if i % 2 == 0 { f32::NEG_INFINITY } else { f32::NAN });
        }
        true
    }
    fn observation_count(&self, _: usize, _: usize) -> usize {
        1
    }
}

#[test]
fn a_collapsed_step_is_skipped_and_counted_never_nan() {
    let ys = sequence(8, 7);
    let run = run_filter(&Collapsing(replicated(&ys, 3)), &config(64, 2, Resampling::Systematic, None), |_| {
        Moments::new(1, &[])
    });
    for (o, m) in run.objects.iter().zip(&run.observers) {
        assert_eq!(o.collapsed_steps, 1);
        assert_eq!(o.observed_units, 7);
        assert!(o.log_likelihood.is_finite());
        assert!(m.filtered.iter().chain(&m.smoothed).all(|r| r[0].is_finite()));
    }
    assert_eq!(run.collapsed_steps(), 3);
}
