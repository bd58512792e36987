//! The pitfalls of SPEC §2, each pinned by a test that would fail if the score
//! estimators fell into it: PF-SEFI's marginalise-before-differentiating against a
//! per-particle brute force (every lag, with the t = 0 term and the flush of the
//! last L steps; and T = 0); PFNET at `alpha = 1` collapsing to PF, and soft
//! resampling keeping `l_hat` unbiased; results that do not depend on the thread
//! count or the chunking; ESS-triggered resampling; steps where every particle,
//! or only some, are impossible; the naive DPF-SGR accumulation (a sum of prefix
//! scores); and the identities again on the vehicle model.

use std::collections::HashSet;

use autodiff::{Float, Tape, Tensor, Var};
use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::estimators::{Estimator, EstimatorConfig, Precision, ScoreEstimate, ScoreEstimator};
use ssm::filter::{filter_object, run_filter, FilterConfig, ObjectSummary, Observer, Resampling, Sampling, StepView};
use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmTheta};
use ssm::models::linear_gaussian::particles::LgssmBatch;
use ssm::models::{Batch, Drawn, ParticleModel};
use ssm::models::{Block, DifferentiableModel};

// ---------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------

fn lgssm() -> Lgssm {
    Lgssm::stationary(LgssmTheta::new(0.9, 0.7, 1.0)).unwrap()
}

/// `objects` independent sequences of `len` observations (`T = len - 1`).
fn batch(len: usize, objects: usize, seed: u64) -> LgssmBatch {
    let model = lgssm();
    let mut rng = StdRng::seed_from_u64(seed);
    let seqs = (0..objects).map(|_| model.simulate(len, &mut rng).ys).collect();
    LgssmBatch::new(model, seqs).unwrap()
}

fn config(n: usize, precision: Precision) -> EstimatorConfig {
    EstimatorConfig { sampling: Sampling::new(n, None), precision, chunk_objects: 2 }
}

/// `cfg` with another resampling scheme and ESS threshold.
fn with_sampling(cfg: EstimatorConfig, resampling: Resampling, ess_threshold: Option<f64>) -> EstimatorConfig {
    EstimatorConfig { sampling: Sampling { resampling, ess_threshold, ..cfg.sampling }, ..cfg }
}

/// The filter settings an estimator uses.
fn filter_config(cfg: &EstimatorConfig, seed: u64, lag: usize, soft: Option<f64>) -> FilterConfig {
    cfg.filter(seed, lag, soft)
}

/// Every step of one object's filter, as the filter handed it over.
#[derive(Default)]
struct Recorded {
    states: Vec<Vec<f32>>,
    actions: Vec<Vec<f32>>,
    parents: Vec<Vec<usize>>,
    log_weights: Vec<Vec<f64>>,
    resampled: Vec<bool>,
    used: Vec<bool>,
}

impl Observer for Recorded {
    fn step(&mut self, v: &StepView<'_>) {
        assert_eq!(v.t, self.states.len(), "steps arrive in order, once each");
        self.states.push(v.states.to_vec());
        self.actions.push(v.actions.to_vec());
        self.parents.push(v.parents.to_vec());
        self.log_weights.push(v.log_weights.to_vec());
        self.resampled.push(v.resampled);
        self.used.push(v.observation_used);
    }
}

fn record<M: ParticleModel>(model: &M, fc: &FilterConfig, object: usize) -> (ObjectSummary, Recorded) {
    let mut rec = Recorded::default();
    let (summary, _) = filter_object(model, fc, object, &mut model.new_scratch(), &mut rec);
    (summary, rec)
}

/// All gradient entries, flattened in parameter order.
fn flat(e: &ScoreEstimate) -> Vec<f64> {
    e.gradient.iter().flat_map(|g| g.data().iter().copied()).collect()
}

/// PF-SEFI at three lags (filter marginals, a short lag, full paths for sequences of
/// `len` steps) and every baseline.
fn every_estimator(len: usize) -> [Estimator; 7] {
    [
        Estimator::pf_sefi(0),
        Estimator::pf_sefi(3),
        Estimator::pf_sefi(len + 5),
        Estimator::pf(),
        Estimator::dpf_sgr(),
        Estimator::dpf_sgr_stopped(),
        Estimator::pfnet(0.8),
    ]
}

/// DPF-SGR with stopped particles gives full-path PF-SEFI's gradient on the same
/// draws, to the f32 rounding of the filter's weights.
fn assert_full_path_identity<M: DifferentiableModel>(
    data: &M,
    cfg: &EstimatorConfig,
    seed: u64,
    len: usize,
    what: &str,
) {
    let sefi = Estimator::pf_sefi(len).estimate(data, cfg, seed);
    let dpf = Estimator::dpf_sgr_stopped().estimate(data, cfg, seed);
    for (a, b) in flat(&sefi).iter().zip(flat(&dpf)) {
        assert!((a - b).abs() <= 2e-6 * (1.0 + a.abs()), "{what}: {a} vs {b}");
    }
}

/// `max |a - b| / max |a|`: a relative difference that a small component cannot inflate.
fn rel_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = a.iter().fold(0.0f64, |m, x| m.max(x.abs())).max(f64::MIN_POSITIVE);
    a.iter().zip(b).fold(0.0f64, |m, (x, y)| m.max((x - y).abs())) / scale
}

// ---------------------------------------------------------------------------
// 1. Marginalise before differentiating
// ---------------------------------------------------------------------------

/// PF-SEFI's score by brute force, one term per particle per step (no
/// marginalisation): for each `t` and each particle `i` at `s = min(t + L, T)`,
/// `W_s^i` times the closed-form gradient of `log g(y_t | x_t^b) + log f(x_t^b |
/// x_{t-1}^{parent(b)})` at the ancestor `b = b(i, t)`, in f64. Returns the score,
/// the number of distinct `(t, ancestor)` pairs with positive weight and `l_hat`.
fn brute_force_sefi(data: &LgssmBatch, fc: &FilterConfig) -> ([f64; 3], usize, f64) {
    let theta = data.model.theta();
    let (phi, sv2, sw2) = (theta.phi, theta.sv().powi(2), theta.sw().powi(2));
    let last = data.num_steps() - 1;
    let mut grad = [0.0; 3];
    let mut distinct = 0;
    let mut loglik = 0.0;
    for object in 0..data.num_objects() {
        let (summary, rec) = record(data, fc, object);
        loglik += summary.log_likelihood;
        let ys = data.sequence(object);
        for (t, &y) in ys.iter().enumerate() {
            let s = (t + fc.lag).min(last);
            let mut ancestors = HashSet::new();
            for (i, &lw) in rec.log_weights[s].iter().enumerate() {
                let w = lw.exp();
                if w <= 0.0 {
                    continue;
                }
                let mut b = i;
                for k in (t + 1..=s).rev() {
                    b = rec.parents[k][b];
                }
                ancestors.insert(b);
                let x = rec.states[t][b] as f64;
                if rec.used[t] {
                    // d/d ln s_w of log N(y; x, s_w^2).
                    grad[2] += w * ((y - x).powi(2) / sw2 - 1.0);
                }
                if t > 0 {
                    let xp = rec.states[t - 1][rec.parents[t][b]] as f64;
                    let r = x - phi * xp;
                    // d/d phi and d/d ln s_v of log N(x; phi x_prev, s_v^2).
                    grad[0] += w * r * xp / sv2;
                    grad[1] += w * (r * r / sv2 - 1.0);
                }
            }
            distinct += ancestors.len();
        }
    }
    (grad, distinct, loglik)
}

/// PF-SEFI's one-reverse-pass surrogate over distinct ancestors equals the
/// per-particle sum of closed-form gradients (SPEC §2, "marginalise before
/// differentiating"), for filter marginals (L = 0), short lags, and L > T (where
/// the last L steps must be flushed with W_T). This also pins the t = 0 term and
/// the scatter-add push-back; `rows_evaluated` is exactly the number of distinct
/// (t, ancestor) pairs, below the N (T + 1) slots whenever L > 0. Resampling at
/// every step and ESS-triggered (where ancestors are the identity between
/// resampling steps and weights are carried).
#[test]
fn pf_sefi_equals_the_per_particle_brute_force_at_every_lag() {
    let len = 12;
    let data = batch(len, 3, 11);
    let schemes = [
        (Resampling::Systematic, None),
        (Resampling::Multinomial, None),
        (Resampling::Systematic, Some(0.5)),
        (Resampling::Multinomial, Some(0.5)),
    ];
    for (resampling, ess_threshold) in schemes {
        let cfg = with_sampling(config(32, Precision::F64), resampling, ess_threshold);
        for lag in [0, 1, 3, len + 5] {
            for seed in [0, 7] {
                let est = Estimator::pf_sefi(lag).estimate(&data, &cfg, seed);
                let (grad, distinct, loglik) = brute_force_sefi(&data, &filter_config(&cfg, seed, lag, None));
                let d = rel_diff(&grad, &flat(&est));
                let what = format!("{resampling:?} ess {ess_threshold:?} L={lag} seed {seed}");
                assert!(d < 1e-12, "{what}: brute {grad:?} vs {:?} ({d:e})", flat(&est));
                assert_eq!(est.log_likelihood, loglik, "L={lag}: l_hat is the filter's");
                assert_eq!(est.particle_slots, 32 * len * 3);
                assert_eq!(est.rows_evaluated, distinct, "{what}");
                if lag > 0 {
                    assert!(est.rows_evaluated < est.particle_slots, "L={lag}: {} rows", est.rows_evaluated);
                } else {
                    assert_eq!(est.rows_evaluated, est.particle_slots, "L=0 evaluates every particle");
                }
            }
        }
    }
}

/// With a single observation (T = 0) there is no transition: every estimator's
/// score has exactly zero `phi` and `ln s_v` components, a finite `ln s_w` one, and
/// DPF-SGR with stopped particles equals PF-SEFI (L = 0 is already the full path).
#[test]
fn a_single_observation_has_no_transition_score() {
    let data = batch(1, 3, 13);
    let cfg = config(32, Precision::F64);
    let all = [
        Estimator::pf_sefi(0),
        Estimator::pf(),
        Estimator::dpf_sgr(),
        Estimator::dpf_sgr_stopped(),
        Estimator::pfnet(0.8),
    ];
    for e in &all {
        let est = e.estimate(&data, &cfg, 2);
        let g = flat(&est);
        assert!(est.is_finite(), "{}", e.name());
        assert_eq!((g[0], g[1]), (0.0, 0.0), "{}: {g:?}", e.name());
        assert!(g[2] != 0.0, "{}", e.name());
        assert_eq!(est.particle_slots, 32 * 3);
    }
    let sefi = flat(&Estimator::pf_sefi(0).estimate(&data, &cfg, 2));
    let dpf = flat(&Estimator::dpf_sgr_stopped().estimate(&data, &cfg, 2));
    assert!((sefi[2] - dpf[2]).abs() <= 2e-6 * (1.0 + sefi[2].abs()), "{sefi:?} vs {dpf:?}");
}

// ---------------------------------------------------------------------------
// 2. PFNET with alpha = 1
// ---------------------------------------------------------------------------

/// PFNET's proposal `q = alpha W + (1 - alpha)/N` is `W` at alpha = 1, and the
/// carried weights `W^a / q^a` are uniform: the filter draws the same ancestors
/// as PF's, and PFNET's log-likelihood and gradient are PF's up to rounding.
#[test]
fn pfnet_with_alpha_one_is_pf() {
    let data = batch(15, 3, 2);
    for ess_threshold in [None, Some(0.5)] {
        let cfg = with_sampling(config(64, Precision::F64), Resampling::Systematic, ess_threshold);
        for seed in 0..3 {
            // Same draws: the ancestors of every step agree.
            for object in 0..3 {
                let (_, hard) = record(&data, &filter_config(&cfg, seed, 0, None), object);
                let (_, soft) = record(&data, &filter_config(&cfg, seed, 0, Some(1.0)), object);
                assert_eq!(hard.parents, soft.parents, "{ess_threshold:?} seed {seed} object {object}");
                assert_eq!(hard.resampled, soft.resampled);
            }
            let pf = Estimator::pf().estimate(&data, &cfg, seed);
            let pfnet = Estimator::pfnet(1.0).estimate(&data, &cfg, seed);
            assert!(
                (pf.log_likelihood - pfnet.log_likelihood).abs() <= 1e-12 * pf.log_likelihood.abs(),
                "{ess_threshold:?} seed {seed}: l_hat {} vs {}",
                pf.log_likelihood,
                pfnet.log_likelihood
            );
            let d = rel_diff(&flat(&pf), &flat(&pfnet));
            assert!(d < 1e-12, "{ess_threshold:?} seed {seed}: {:?} vs {:?}", flat(&pf), flat(&pfnet));
            // And alpha < 1 really is different (the test can fail).
            let soft = Estimator::pfnet(0.5).estimate(&data, &cfg, seed);
            assert!(rel_diff(&flat(&pf), &flat(&soft)) > 1e-3);
        }
    }
}

/// PFNET's soft resampling keeps the likelihood estimate unbiased only if each
/// drawn particle carries its own ancestor's `W^a / q^a` (weights re-indexed with
/// their particles): over 1000 independent runs on one sequence, the mean of
/// `exp(l_hat - l)` is 1 within 4 standard errors (plus 1% for the heavy right
/// tail of a likelihood ratio), and the PFNET estimator reports that `l_hat`.
#[test]
fn soft_resampling_keeps_the_likelihood_unbiased() {
    let model = lgssm();
    let ys = model.simulate(21, &mut StdRng::seed_from_u64(14)).ys;
    let exact = model.log_likelihood(&ys);
    let data = LgssmBatch::new(model, vec![ys; 1000]).unwrap();
    for (alpha, ess_threshold) in [(0.5, None), (0.8, None), (0.5, Some(0.5))] {
        let cfg = with_sampling(config(64, Precision::F64), Resampling::Systematic, ess_threshold);
        let run = run_filter(&data, &filter_config(&cfg, 3, 0, Some(alpha)), |_| ());
        let r: Vec<f64> = run.objects.iter().map(|o| (o.log_likelihood - exact).exp()).collect();
        let m = r.iter().sum::<f64>() / r.len() as f64;
        let se = (r.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (r.len() - 1) as f64 / r.len() as f64).sqrt();
        assert!((m - 1.0).abs() < 4.0 * se + 0.01, "alpha {alpha} ess {ess_threshold:?}: mean ratio {m} ± {se}");
        assert!(se < 0.05, "the check must have power: se {se}");
    }
    let small = LgssmBatch::new(lgssm(), (0..3).map(|j| data.sequence(j).to_vec()).collect()).unwrap();
    let cfg = config(64, Precision::F64);
    let run = run_filter(&small, &filter_config(&cfg, 3, 0, Some(0.8)), |_| ());
    assert_eq!(Estimator::pfnet(0.8).estimate(&small, &cfg, 3).log_likelihood, run.log_likelihood());
}

// ---------------------------------------------------------------------------
// 3. Thread count and chunking
// ---------------------------------------------------------------------------

fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(f)
}

/// Results do not depend on the thread count: every estimator gives bitwise the
/// same estimate in a 1-thread and a 2-thread pool, in both precisions; and the
/// baselines' chunking of objects (1 vs 3 per tape) changes the gradient only by
/// the order of a floating-point sum.
#[test]
fn estimates_do_not_depend_on_threads_or_chunks() {
    let data = batch(10, 7, 3);
    let estimators = [
        Estimator::pf_sefi(3),
        Estimator::pf(),
        Estimator::dpf_sgr(),
        Estimator::dpf_sgr_stopped(),
        Estimator::pfnet(0.8),
    ];
    for precision in [Precision::F32, Precision::F64] {
        let cfg = config(64, precision);
        for e in &estimators {
            let one = in_pool(1, || e.estimate(&data, &cfg, 5));
            let two = in_pool(2, || e.estimate(&data, &cfg, 5));
            assert!(one.is_finite());
            assert_eq!(one, two, "{} {precision:?}", e.name());
        }
    }
    let cfg = config(64, Precision::F64);
    for e in &estimators {
        let c1 = e.estimate(&data, &EstimatorConfig { chunk_objects: 1, ..cfg.clone() }, 5);
        let c3 = e.estimate(&data, &EstimatorConfig { chunk_objects: 3, ..cfg.clone() }, 5);
        assert_eq!(c1.log_likelihood, c3.log_likelihood, "{}", e.name());
        let d = rel_diff(&flat(&c1), &flat(&c3));
        assert!(d < 1e-12, "{}: chunks 1 vs 3: {:?} vs {:?} ({d:e})", e.name(), flat(&c1), flat(&c3));
    }
}

// ---------------------------------------------------------------------------
// 4. ESS-triggered resampling
// ---------------------------------------------------------------------------

/// `l_hat` from the recorded steps, recomputed in f64:
/// `sum_t lse_i(log W_{t-1}^i + log g(y_t | x_t^i))` with `W_{t-1}` uniform after
/// resampling and carried otherwise.
fn l_hat_from_steps(data: &LgssmBatch, object: usize, rec: &Recorded) -> f64 {
    let theta = data.model.theta();
    let n = rec.states[0].len();
    let ys = data.sequence(object);
    let mut total = 0.0;
    for (t, &y) in ys.iter().enumerate() {
        let prev: Vec<f64> =
            if t == 0 || rec.resampled[t] { vec![-(n as f64).ln(); n] } else { rec.log_weights[t - 1].clone() };
        let terms: Vec<f64> = prev
            .iter()
            .zip(&rec.states[t])
            .map(|(&lw, &x)| {
                let z = (y - x as f64) / theta.sw();
                lw - 0.5 * z * z - theta.log_sw - 0.5 * (2.0 * std::f64::consts::PI).ln()
            })
            .collect();
        let m = terms.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        total += m + terms.iter().map(|v| (v - m).exp()).sum::<f64>().ln();
    }
    total
}

/// Under ESS-triggered resampling (threshold N/2) weights are carried between
/// resampling steps: DPF-SGR with stopped particles still equals full-path
/// PF-SEFI on the same draws, and the log-likelihood that PF and PF-SEFI report
/// is the filter's `l_hat`, whose increments carry the weights (checked against
/// a recomputation from the recorded steps).
#[test]
fn ess_triggered_resampling_keeps_the_identities() {
    let len = 20;
    let data = batch(len, 3, 4);
    for resampling in [Resampling::Systematic, Resampling::Multinomial] {
        let cfg = with_sampling(config(64, Precision::F64), resampling, Some(0.5));
        for seed in 0..3 {
            let fc = filter_config(&cfg, seed, 0, None);
            let run = run_filter(&data, &fc, |_| ());
            // The threshold matters: some steps resample and some carry their weights.
            for o in &run.objects {
                assert!(o.resampled_steps > 0 && o.resampled_steps < len - 1, "{} resampled", o.resampled_steps);
            }
            let recomputed: f64 = (0..3).map(|j| l_hat_from_steps(&data, j, &record(&data, &fc, j).1)).sum();
            assert!(
                (recomputed - run.log_likelihood()).abs() < 1e-4,
                "{resampling:?} seed {seed}: l_hat {} vs recomputed {recomputed}",
                run.log_likelihood()
            );

            let sefi = Estimator::pf_sefi(len + 1).estimate(&data, &cfg, seed);
            let dpf = Estimator::dpf_sgr_stopped().estimate(&data, &cfg, seed);
            let pf = Estimator::pf().estimate(&data, &cfg, seed);
            for e in [&sefi, &dpf, &pf] {
                assert_eq!(e.log_likelihood, run.log_likelihood());
            }
            // As in estimators_lgssm.rs: PF-SEFI weighs by the f32 filter's weights,
            // the replay recomputes them in f64, so they agree to single precision.
            for (a, b) in flat(&sefi).iter().zip(flat(&dpf)) {
                assert!((a - b).abs() <= 2e-6 * (1.0 + a.abs()), "{resampling:?} seed {seed}: {a} vs {b}");
            }
        }
    }
}

// ---------------------------------------------------------------------------
// 5. Every particle impossible
// ---------------------------------------------------------------------------

/// An [`LgssmBatch`] whose observations at the `missing` `(object, t)` are absent,
/// and whose observation at each gated `(object, t, c)` also says `x_t <= c`: a
/// particle above `c` is impossible (log-density `-inf`).
struct Edited {
    inner: LgssmBatch,
    missing: Vec<(usize, usize)>,
    gates: Vec<(usize, usize, f64)>,
}

impl Edited {
    fn gate(&self, object: usize, t: usize) -> Option<f64> {
        self.gates.iter().find(|g| (g.0, g.1) == (object, t)).map(|g| g.2)
    }
}

impl ParticleModel for Edited {
    type Scratch = ();
    fn new_scratch(&self) {}
    fn state_dim(&self) -> usize {
        1
    }
    fn action_dim(&self) -> usize {
        1
    }
    fn num_objects(&self) -> usize {
        self.inner.num_objects()
    }
    fn num_steps(&self) -> usize {
        self.inner.num_steps()
    }
    fn sample_prior(&self, object: usize, n: usize, rng: &mut rand::rngs::SmallRng, states: &mut [f32], s: &mut ()) {
        self.inner.sample_prior(object, n, rng, states, s)
    }
    fn propagate(&self, at: Batch, prev: &[f32], to: Drawn<'_>, rng: &mut rand::rngs::SmallRng, scratch: &mut ()) {
        self.inner.propagate(at, prev, to, rng, scratch)
    }
    fn observation_loglik(&self, at: Batch, states: &[f32], out: &mut [f32], scratch: &mut ()) -> bool {
        if self.missing.contains(&(at.object, at.t)) {
            return false;
        }
        let observed = self.inner.observation_loglik(at, states, out, scratch);
        if let Some(c) = self.gate(at.object, at.t) {
            for (o, &x) in out.iter_mut().zip(states) {
                if x as f64 > c {
                    *o = f32::NEG_INFINITY;
                }
            }
        }
        observed
    }
    fn observation_count(&self, object: usize, t: usize) -> usize {
        self.inner.observation_count(object, t)
    }
}

impl DifferentiableModel for Edited {
    fn parameters(&self) -> Vec<Tensor<f64>> {
        self.inner.parameters()
    }
    fn parameter_names(&self) -> Vec<String> {
        self.inner.parameter_names()
    }
    fn observation_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        states: &[Var<'t, F>],
    ) -> Var<'t, F> {
        assert!(blocks.iter().all(|b| !self.missing.contains(&(b.object, b.t))), "a missing observation was scored");
        let x = states[0].value().data().iter().map(|v| v.to_f64()).collect::<Vec<f64>>();
        let mut row = 0;
        let mut gate = Vec::with_capacity(x.len());
        for b in blocks {
            let c = self.gate(b.object, b.t).unwrap_or(f64::INFINITY);
            gate.extend(x[row..row + b.len].iter().map(|&v| F::from_f64(if v > c { f64::NEG_INFINITY } else { 0.0 })));
            row += b.len;
        }
        self.inner.observation_log_density(params, blocks, states) + states[0].tape().constant(Tensor::from_vec(gate))
    }
    fn transition_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        prev: &[Var<'t, F>],
        next: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Var<'t, F> {
        self.inner.transition_log_density(params, blocks, prev, next, actions)
    }
    fn propagate_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        prev: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Vec<Var<'t, F>> {
        self.inner.propagate_on_tape(params, blocks, prev, actions)
    }
}

/// An observation that every particle finds impossible (f32 log-weights all
/// `-inf` from overflow, or NaN) makes the filter skip the step: every estimator,
/// in both precisions, with and without ESS-triggered resampling and with the
/// collapsed object sharing a tape with healthy ones, returns a finite estimate,
/// counts the collapsed steps, and gives exactly the estimate of the same data
/// with those observations missing. The identity DPF-SGR-stopped = full-path
/// PF-SEFI survives the collapse.
#[test]
fn collapsed_steps_are_skipped_by_every_estimator() {
    let len = 10;
    let healthy = batch(len, 4, 6);
    // Overflow to -inf at the last step, overflow at a middle step, NaN at t = 0.
    let absurd = [(0, len - 1, f64::INFINITY), (1, 4, 1e25), (2, 0, f64::NAN)];
    let mut seqs: Vec<Vec<f64>> = (0..4).map(|j| healthy.sequence(j).to_vec()).collect();
    for &(j, t, y) in &absurd {
        seqs[j][t] = y;
    }
    let data = LgssmBatch::new(lgssm(), seqs).unwrap();
    let masked =
        Edited { inner: healthy.clone(), missing: absurd.iter().map(|&(j, t, _)| (j, t)).collect(), gates: vec![] };
    let estimators = every_estimator(len);
    for precision in [Precision::F32, Precision::F64] {
        for ess_threshold in [None, Some(0.5)] {
            let cfg = EstimatorConfig {
                chunk_objects: 4,
                ..with_sampling(config(32, precision), Resampling::Systematic, ess_threshold)
            };
            for e in &estimators {
                let got = e.estimate(&data, &cfg, 9);
                let what = format!("{} {precision:?} ess {ess_threshold:?}", e.name());
                assert!(got.is_finite(), "{what}: l_hat {} gradient {:?}", got.log_likelihood, flat(&got));
                assert_eq!(got.collapsed_steps, 3, "{what}");
                assert_eq!(got.observed_units, 4 * len - 3, "{what}");
                let missing = e.estimate(&masked, &cfg, 9);
                assert_eq!(missing.collapsed_steps, 0);
                assert_eq!(got.log_likelihood, missing.log_likelihood, "{what}");
                assert_eq!(got.gradient, missing.gradient, "{what}: a collapsed step is a missing observation");
            }
            if precision == Precision::F64 {
                assert_full_path_identity(&data, &cfg, 9, len, &format!("ess {ess_threshold:?}"));
            }
        }
    }
}

/// Some (not all) particles impossible: a gated observation gives `-inf` to every
/// particle above a threshold, at several steps of every object. The impossible
/// particles get zero weight and never resampled (PFNET's proposal does draw them,
/// and they must stay impossible): every estimator, in both precisions, with and
/// without ESS-triggered resampling, returns a finite estimate with nothing
/// counted as collapsed, and DPF-SGR with stopped particles still equals
/// full-path PF-SEFI.
#[test]
fn partly_impossible_particles_never_give_nan() {
    let len = 10;
    let inner = batch(len, 3, 12);
    // Gate at the observation itself: about half the particles are impossible.
    let gates = (0..3).flat_map(|j| [0, 3, 4, len - 1].map(|t| (j, t, inner.sequence(j)[t]))).collect();
    let data = Edited { inner, missing: vec![], gates };
    let estimators = every_estimator(len);
    for precision in [Precision::F32, Precision::F64] {
        for ess_threshold in [None, Some(0.5)] {
            let cfg = EstimatorConfig {
                chunk_objects: 3,
                ..with_sampling(config(32, precision), Resampling::Systematic, ess_threshold)
            };
            for e in &estimators {
                let got = e.estimate(&data, &cfg, 4);
                let what = format!("{} {precision:?} ess {ess_threshold:?}", e.name());
                assert!(got.is_finite(), "{what}: l_hat {} gradient {:?}", got.log_likelihood, flat(&got));
                assert_eq!(got.collapsed_steps, 0, "{what}");
            }
            if precision == Precision::F64 {
                assert_full_path_identity(&data, &cfg, 4, len, &format!("ess {ess_threshold:?}"));
            }
        }
    }
}

// ---------------------------------------------------------------------------
// 6. The naive DPF-SGR accumulation
// ---------------------------------------------------------------------------

/// The naive DPF-SGR of SPEC §2, with particles stopped, replayed on an f64 tape
/// from a recorded filter (resampling at every step): unnormalised carried
/// log-weights `lw_t = [lw_{t-1}^a - stopgrad(lw_{t-1}^a)] + [log f - stopgrad(log
/// f)] + log g_t`, and `sum_t log mean_i exp(lw_t^i)`. Returns its value and gradient.
fn naive_dpf_sgr(data: &LgssmBatch, rec: &Recorded) -> (f64, [f64; 3]) {
    let tape = Tape::<f64>::new();
    let params = data.bind(&tape);
    let n = rec.states[0].len();
    let col = |v: &[f32]| tape.constant(Tensor::from_vec(v.iter().map(|&x| x as f64).collect()));
    let mut lw: Option<Var<'_, f64>> = None;
    let mut total: Option<Var<'_, f64>> = None;
    for t in 0..rec.states.len() {
        assert!(t == 0 || rec.resampled[t], "the naive replay assumes resampling at every step");
        let block = [Block { object: 0, t, len: n }];
        let x = col(&rec.states[t]);
        let carried = match lw {
            None => tape.constant(Tensor::zeros(&[n])),
            Some(prev) => {
                let lw_a = prev.gather(0, &rec.parents[t]);
                let x_prev = col(&rec.states[t - 1]).gather(0, &rec.parents[t]);
                let a = col(&rec.actions[t]);
                let trans = data.transition_log_density(&params, &block, &[x_prev], &[x], &[a]);
                (lw_a - lw_a.stop_gradient()) + (trans - trans.stop_gradient())
            }
        };
        let w = carried + data.observation_log_density(&params, &block, &[x]);
        let log_mean = w.logsumexp(0, false).add_scalar(-(n as f64).ln()).sum();
        total = Some(match total {
            None => log_mean,
            Some(s) => s + log_mean,
        });
        lw = Some(w);
    }
    let total = total.unwrap();
    let g = tape.backward(total).wrt(params[0]);
    (total.item(), [g.data()[0], g.data()[1], g.data()[2]])
}

/// Mean and standard error of each component.
fn mean_se(xs: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let n = xs.len() as f64;
    let mean: [f64; 3] = std::array::from_fn(|k| xs.iter().map(|x| x[k]).sum::<f64>() / n);
    let se = std::array::from_fn(|k| {
        let var = xs.iter().map(|x| (x[k] - mean[k]).powi(2)).sum::<f64>() / (n - 1.0);
        (var / n).sqrt()
    });
    (mean, se)
}

/// The naive DPF-SGR accumulation has the right value (`l_hat`) but the wrong
/// gradient: over 100 runs its mean is the sum of the prefix scores
/// `sum_t grad log p(y_{0:t})` (exact, by Kalman), many standard errors from the
/// score, while our DPF-SGR (normalised carried weights), with particles stopped
/// or reparameterised, averages to the exact score. Tolerances: 4 standard
/// errors, plus 5% of one run's spread for the O(1/N) bias of full-path estimates
/// at N = 256. (Measured: naive -43.4 ± 0.5 against the prefix sum -43.5 for
/// `phi`, whose exact score is -7.22; z = 73.)
#[test]
fn naive_dpf_sgr_accumulation_sums_prefix_scores() {
    let len = 11; // T = 10
    let model = lgssm();
    let ys = model.simulate(len, &mut StdRng::seed_from_u64(21)).ys;
    let data = LgssmBatch::new(model.clone(), vec![ys.clone()]).unwrap();
    let (_, exact) = model.score(&ys);
    let mut prefix_sum = [0.0; 3];
    for t in 0..len {
        let (_, s) = model.score(&ys[..=t]);
        (0..3).for_each(|k| prefix_sum[k] += s[k]);
    }
    let cfg = config(256, Precision::F64);
    let runs = 100;
    let (mut stopped, mut reparam, mut naive) = (Vec::new(), Vec::new(), Vec::new());
    let score = |e: &ScoreEstimate| std::array::from_fn::<f64, 3, _>(|k| e.gradient[0].data()[k]);
    for seed in 0..runs {
        let (summary, rec) = record(&data, &filter_config(&cfg, seed, 0, None), 0);
        let (value, g) = naive_dpf_sgr(&data, &rec);
        // The value is right: l_hat (f32 filter weights vs the f64 tape).
        assert!((value - summary.log_likelihood).abs() < 1e-4, "{value} vs {}", summary.log_likelihood);
        naive.push(g);
        stopped.push(score(&Estimator::dpf_sgr_stopped().estimate(&data, &cfg, seed)));
        reparam.push(score(&Estimator::dpf_sgr().estimate(&data, &cfg, seed)));
    }
    let sd = |se: f64| se * (runs as f64).sqrt();
    let close = |xs: &[[f64; 3]], target: [f64; 3], what: &str| {
        let (m, se) = mean_se(xs);
        for k in 0..3 {
            assert!(
                (m[k] - target[k]).abs() <= 4.0 * se[k] + 0.05 * sd(se[k]),
                "component {k}: {what} mean {} ± {} vs {}",
                m[k],
                se[k],
                target[k]
            );
        }
    };
    close(&stopped, exact, "DPF-SGR (stopped particles) against the exact score");
    close(&reparam, exact, "DPF-SGR against the exact score");
    close(&naive, prefix_sum, "naive DPF-SGR against the sum of prefix scores");
    let (m_naive, se_naive) = mean_se(&naive);
    let z = (0..3).map(|k| ((m_naive[k] - exact[k]) / se_naive[k]).abs()).fold(0.0, f64::max);
    assert!(z > 10.0, "naive mean {m_naive:?} should be far from the exact score {exact:?} (z = {z})");
}

// ---------------------------------------------------------------------------
// 7. The vehicle model
// ---------------------------------------------------------------------------

mod vehicle {
    use super::*;
    use ssm::models::observation::PointGenerator;
    use ssm::models::params::{AnyObservation, Models};
    use ssm::models::road_user::VehicleSsm;
    use ssm::simulation::synthetic::{fit_true_model, generate_dataset, SceneConfig, TruthConfig};

    /// On the vehicle model (hand-crafted policy, fitted point network, 3 objects,
    /// T = 11, N = 64): every estimator gives a finite gradient with one tensor per
    /// parameter, shaped like it; DPF-SGR with stopped particles equals full-path
    /// PF-SEFI on the same draws, per tensor to 2e-5 relative; PF-SEFI with the
    /// paper's lag evaluates a small fraction of the particle slots.
    ///
    /// The tolerance is set by the filter, not the tape: PF-SEFI weighs by the f32
    /// filter's weights (fast polynomial tanh/exp, ~4e-7 per point), the replay
    /// recomputes them on its tape. Measured over 8 seeds: at most 1.5e-6 on f32
    /// tapes and 1.6e-6 on f64 tapes, so f64 tapes are no tighter.
    #[test]
    fn estimators_on_the_vehicle_model() {
        let mut rng = StdRng::seed_from_u64(8);
        let truth = fit_true_model(&TruthConfig::quick(), &mut rng).unwrap().model;
        // Sparse points (a mean of 40 / range per step, ~1-8 at 5-50 m), so that some
        // steps have none and the replay's partial-observation path is exercised.
        let counts = PointGenerator { count_scale: 40.0, ..PointGenerator::default() };
        let scene = SceneConfig { objects: 3, counts, ..SceneConfig::paper(12) };
        let data = generate_dataset(&scene, &truth, &[0], &mut rng).unwrap();
        let models = Models::from_store(&truth.params, data.kind()).unwrap();
        let AnyObservation::Points(obs) = &models.observation else { panic!("a point model") };
        let model = VehicleSsm::new(&data, &models.policy, obs, &models.observation_params).unwrap();
        let params = model.parameters();
        let steps = data.steps();
        let names = model.parameter_names();
        assert_eq!(names.len(), params.len());
        assert_eq!(names[0], ssm::models::params::HAND_CRAFTED_PARAM);
        let empty =
            (0..3).flat_map(|j| (0..steps).map(move |t| (j, t))).filter(|&(j, t)| model.observation_count(j, t) == 0);
        let empty = empty.count();
        assert!(empty > 0 && empty < 3 * steps / 2, "{empty} empty steps");

        // The vehicle model's per-thread scratch does not leak into results.
        for e in [Estimator::pf_sefi(8), Estimator::dpf_sgr()] {
            let cfg = config(64, Precision::F32);
            assert_eq!(in_pool(1, || e.estimate(&model, &cfg, 3)), in_pool(2, || e.estimate(&model, &cfg, 3)));
        }

        for precision in [Precision::F32, Precision::F64] {
            let cfg = config(64, precision);
            for e in [Estimator::pf_sefi(8), Estimator::pf(), Estimator::dpf_sgr(), Estimator::pfnet(0.8)] {
                let est = e.estimate(&model, &cfg, 1);
                assert!(est.is_finite(), "{} {precision:?}", e.name());
                assert_eq!(est.gradient.len(), params.len());
                for (g, p) in est.gradient.iter().zip(&params) {
                    assert_eq!(g.shape(), p.shape(), "{}", e.name());
                }
                for (g, name) in est.gradient.iter().zip(&names) {
                    assert!(g.sum_squares() > 0.0, "{}: no gradient for {name}", e.name());
                }
                assert_eq!(est.particle_slots, 64 * steps * 3);
                if let Estimator::PfSefi(_) = e {
                    let frac = est.rows_evaluated as f64 / est.particle_slots as f64;
                    // Measured: 13% (SPEC §10: about 7% at experiment A's N = 1024, T = 25).
                    assert!(frac < 0.25, "pf-sefi L=8 evaluates {:.1}% of the slots", 100.0 * frac);
                }
            }
            for (ess_threshold, seed) in [(None, 0), (None, 1), (Some(0.5), 2), (Some(0.5), 3)] {
                let cfg = with_sampling(cfg.clone(), cfg.sampling.resampling, ess_threshold);
                let sefi = Estimator::pf_sefi(steps).estimate(&model, &cfg, seed);
                let dpf = Estimator::dpf_sgr_stopped().estimate(&model, &cfg, seed);
                assert_eq!(sefi.log_likelihood, dpf.log_likelihood);
                for ((a, b), name) in sefi.gradient.iter().zip(&dpf.gradient).zip(&names) {
                    let d = rel_diff(a.data(), b.data());
                    assert!(
                        d < 2e-5,
                        "{precision:?} ess {ess_threshold:?} seed {seed} {name}: relative difference {d:e}"
                    );
                }
            }
        }
    }
}
