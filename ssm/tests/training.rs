//! The training loop on a real objective — the linear-Gaussian model with its exact
//! Kalman score — and on wrappers that crash, return non-finite estimates or fail:
//! convergence to the maximum-likelihood estimate, bitwise-exact resumption,
//! skipped steps, refusals, and clipping.

use std::path::Path;

use autodiff::nn::ParamStore;
use autodiff::optim::{clip_global_norm, Adam};
use autodiff::Tensor;
use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmTheta};
use ssm::training::{
    eval_seed, non_finite, train, train_until, BatchEstimate, Checkpoint, EstimateError, Objective, TrainConfig,
    TrainError, TrainEvent, CHECKPOINT_FILE, EVAL_LOG, PARAMS_FILE, SKIP_LOG, TRAIN_LOG, TRAIN_LOG_HEADER,
};

/// The data's parameters: `(phi, ln s_v, ln s_w)`.
const TRUTH: [f64; 3] = [0.8, -0.5, -0.9];
/// A poor start: weak dynamics, too much noise in both places.
const START: [f64; 3] = [0.2, 0.4, 0.3];

fn theta_of(params: &ParamStore<f64>) -> LgssmTheta {
    let d = params.values()[0].data();
    LgssmTheta::from_array([d[0], d[1], d[2]])
}

fn store(theta: [f64; 3]) -> ParamStore<f64> {
    let mut s = ParamStore::new();
    s.add("theta", Tensor::from_vec(theta.to_vec()));
    s
}

/// Linear-Gaussian sequences as batches; the exact score as the estimate; the
/// held-out log-likelihood per observation as the test metric.
struct LgssmObjective {
    prior: Lgssm,
    train: Vec<Vec<f64>>,
    test: Vec<Vec<f64>>,
}

impl LgssmObjective {
    fn new(batches: usize, len: usize, seed: u64) -> Self {
        let prior = Lgssm::new(0.0, 1.0, LgssmTheta::from_array(TRUTH)).unwrap();
        let mut rng = StdRng::seed_from_u64(seed);
        let train = (0..batches).map(|_| prior.simulate(len, &mut rng).ys).collect();
        let test = (0..2).map(|_| prior.simulate(len, &mut rng).ys).collect();
        LgssmObjective { prior, train, test }
    }

    fn model(&self, theta: LgssmTheta) -> Result<Lgssm, String> {
        self.prior.with_theta(theta).map_err(|e| e.to_string())
    }

    /// Exact training log-likelihood and score summed over all batches.
    fn total_score(&self, theta: [f64; 3]) -> (f64, [f64; 3]) {
        let m = self.model(LgssmTheta::from_array(theta)).unwrap();
        self.train
            .iter()
            .map(|ys| m.score(ys))
            .fold((0.0, [0.0; 3]), |(l, g), (li, gi)| (l + li, [g[0] + gi[0], g[1] + gi[1], g[2] + gi[2]]))
    }

    /// The exact maximum-likelihood estimate of the training data: damped Newton
    /// steps from the truth, with the Hessian from central differences of the exact
    /// score (h = 1e-5: truncation error ~h^2, rounding ~1e-16 / h, both far below
    /// the 1e-6 gradient tolerance the caller checks).
    fn mle(&self) -> [f64; 3] {
        let h = 1e-5;
        let mut theta = TRUTH;
        let (mut ll, mut g) = self.total_score(theta);
        for _ in 0..50 {
            if g.iter().all(|x| x.abs() < 1e-9) {
                break;
            }
            let mut hess = [[0.0; 3]; 3];
            for j in 0..3 {
                let (mut up, mut down) = (theta, theta);
                up[j] += h;
                down[j] -= h;
                let (gu, gd) = (self.total_score(up).1, self.total_score(down).1);
                for i in 0..3 {
                    hess[i][j] = (gu[i] - gd[i]) / (2.0 * h);
                }
            }
            let step = solve3(hess, g);
            let mut t = 1.0;
            loop {
                let trial = [theta[0] - t * step[0], theta[1] - t * step[1], theta[2] - t * step[2]];
                let (ll_t, g_t) = self.total_score(trial);
                if ll_t >= ll || t < 1e-6 {
                    (theta, ll, g) = (trial, ll_t, g_t);
                    break;
                }
                t *= 0.5;
            }
        }
        theta
    }
}

/// Solves the 3 x 3 system `a x = b` (Cramer's rule).
fn solve3(a: [[f64; 3]; 3], b: [f64; 3]) -> [f64; 3] {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(a);
    let mut x = [0.0; 3];
    for (k, xk) in x.iter_mut().enumerate() {
        let mut m = a;
        for i in 0..3 {
            m[i][k] = b[i];
        }
        *xk = det(m) / d;
    }
    x
}

impl Objective for LgssmObjective {
    fn batches(&self) -> usize {
        self.train.len()
    }

    fn estimate(&mut self, params: &ParamStore<f64>, batch: usize, _seed: u64) -> Result<BatchEstimate, EstimateError> {
        let ys = &self.train[batch];
        let (ll, g) = self.model(theta_of(params))?.score(ys);
        Ok(BatchEstimate {
            log_likelihood: ll,
            observed_units: ys.len(),
            gradient: vec![Tensor::from_vec(g.to_vec())],
            collapsed_steps: 0,
        })
    }

    fn evaluate(&mut self, params: &ParamStore<f64>, _seed: u64) -> Result<Vec<(String, f64)>, String> {
        let m = self.model(theta_of(params))?;
        let ll: f64 = self.test.iter().map(|ys| m.log_likelihood(ys)).sum();
        let n: usize = self.test.iter().map(|ys| ys.len()).sum();
        Ok(vec![("test_mll".into(), ll / n as f64), ("phi".into(), theta_of(params).phi)])
    }
}

/// Wraps an objective: fails with a plain error at the `crash_at`-th estimate (a
/// simulated crash), returns a NaN gradient for `nan_batch` and a non-finite error
/// for `error_batch`, and records the parameters, batch and seed of each estimate.
struct Faulty<O> {
    inner: O,
    calls: usize,
    crash_at: Option<usize>,
    nan_batch: Option<usize>,
    error_batch: Option<usize>,
    seen: Vec<Vec<f64>>,
    calls_log: Vec<(usize, u64)>,
}

impl<O> Faulty<O> {
    fn new(inner: O) -> Self {
        Faulty {
            inner,
            calls: 0,
            crash_at: None,
            nan_batch: None,
            error_batch: None,
            seen: Vec::new(),
            calls_log: Vec::new(),
        }
    }
}

impl<O: Objective> Objective for Faulty<O> {
    fn batches(&self) -> usize {
        self.inner.batches()
    }

    fn estimate(&mut self, params: &ParamStore<f64>, batch: usize, seed: u64) -> Result<BatchEstimate, EstimateError> {
        self.calls += 1;
        self.seen.push(params.values()[0].data().to_vec());
        self.calls_log.push((batch, seed));
        if self.crash_at == Some(self.calls) {
            return Err("simulated crash".into());
        }
        if self.error_batch == Some(batch) {
            return Err(non_finite("all log-weights are -inf"));
        }
        let mut est = self.inner.estimate(params, batch, seed)?;
        if self.nan_batch == Some(batch) {
            est.gradient[0].data_mut()[1] = f64::NAN;
        }
        Ok(est)
    }

    fn evaluate(&mut self, params: &ParamStore<f64>, seed: u64) -> Result<Vec<(String, f64)>, String> {
        self.inner.evaluate(params, seed)
    }
}

/// Wraps an objective: from the `turn_at`-th estimate on, returns the negated
/// score, so that the run climbs and then walks away from the maximum.
struct Wandering<O> {
    inner: O,
    calls: usize,
    turn_at: usize,
    crash_at: Option<usize>,
}

impl<O: Objective> Objective for Wandering<O> {
    fn batches(&self) -> usize {
        self.inner.batches()
    }

    fn estimate(&mut self, params: &ParamStore<f64>, batch: usize, seed: u64) -> Result<BatchEstimate, EstimateError> {
        self.calls += 1;
        if self.crash_at == Some(self.calls) {
            return Err("simulated crash".into());
        }
        let mut est = self.inner.estimate(params, batch, seed)?;
        if self.calls >= self.turn_at {
            est.gradient[0].data_mut().iter_mut().for_each(|g| *g = -*g);
        }
        Ok(est)
    }

    fn evaluate(&mut self, params: &ParamStore<f64>, seed: u64) -> Result<Vec<(String, f64)>, String> {
        let mut metrics = self.inner.evaluate(params, seed)?;
        // The parameters evaluated, to check which ones a run kept.
        metrics.extend(params.values()[0].data().iter().enumerate().map(|(i, v)| (format!("theta{i}"), *v)));
        Ok(metrics)
    }
}

/// The rows of a CSV log (header dropped), split into fields.
fn rows(path: &Path) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(path).unwrap();
    text.lines().skip(1).map(|l| l.split(',').map(String::from).collect()).collect()
}

fn column(rows: &[Vec<String>], name: &str) -> Vec<String> {
    let i = TRAIN_LOG_HEADER.iter().position(|&h| h == name).unwrap();
    rows.iter().map(|r| r[i].clone()).collect()
}

fn bits(params: &ParamStore<f64>) -> Vec<u64> {
    params.values().iter().flat_map(|v| v.data().iter().map(|x| x.to_bits())).collect()
}

fn quiet() -> impl FnMut(&TrainEvent) {
    |_| {}
}

#[test]
fn ascent_on_the_exact_score_reaches_the_maximum_likelihood_estimate() {
    let mut obj = LgssmObjective::new(4, 100, 1);
    let mle = obj.mle();
    let (ll_mle, g_mle) = obj.total_score(mle);
    assert!(g_mle.iter().all(|g| g.abs() < 1e-6), "not at a stationary point: {g_mle:?}");

    let dir = tempfile::tempdir().unwrap();
    let config = TrainConfig { lr: 0.02, epochs: 150, eval_every: 200, checkpoint_every: 100, ..Default::default() };
    let mut events = Vec::new();
    let out = train(&mut obj, store(START), &config, dir.path(), false, &mut |e| events.push(e.clone())).unwrap();
    let theta = theta_of(&out.params).to_array();
    let (ll_start, _) = obj.total_score(START);
    let (ll_end, _) = obj.total_score(theta);
    println!("start {ll_start:.2}, trained {ll_end:.2}, MLE {ll_mle:.2}; theta {theta:?}, MLE {mle:?}");
    // A real improvement, and within half a nat (of 400 observations) of the
    // maximum: Adam at a constant rate of 0.02 jitters by about the rate.
    assert!(ll_end - ll_start > 50.0, "{ll_start} -> {ll_end}");
    assert!(ll_mle - ll_end < 0.5, "trained {ll_end}, MLE {ll_mle}");
    for i in 0..3 {
        assert!((theta[i] - mle[i]).abs() < 0.05, "coordinate {i}: trained {theta:?}, MLE {mle:?}");
    }
    assert_eq!((out.steps, out.skipped_steps), (600, 0));

    // One log row per step; evaluations at 0, every 200 steps and at the end.
    let train_rows = rows(&dir.path().join(TRAIN_LOG));
    assert_eq!(column(&train_rows, "step"), (1..=600).map(|s| s.to_string()).collect::<Vec<_>>());
    let eval_rows = rows(&dir.path().join(EVAL_LOG));
    assert_eq!(eval_rows.iter().map(|r| r[0].as_str()).collect::<Vec<_>>(), ["0", "200", "400", "600"]);
    let header = std::fs::read_to_string(dir.path().join(EVAL_LOG)).unwrap();
    assert!(header.starts_with("step,test_mll,phi\n"));
    let test_mll: Vec<f64> = eval_rows.iter().map(|r| r[1].parse().unwrap()).collect();
    assert!(test_mll[3] > test_mll[0] + 0.1, "held-out MLL {test_mll:?}");
    assert_eq!(out.final_eval[0], ("test_mll".to_string(), test_mll[3]));
    // The per-step log-likelihood rises too (first epoch vs last epoch).
    let lpu: Vec<f64> = column(&train_rows, "ll_per_unit").iter().map(|s| s.parse().unwrap()).collect();
    let mean = |s: &[f64]| s.iter().sum::<f64>() / s.len() as f64;
    assert!(mean(&lpu[596..]) > mean(&lpu[..4]) + 0.1);

    // The parameter file holds the trained store; the events tell the story.
    assert_eq!(ParamStore::<f64>::load(&dir.path().join(PARAMS_FILE)).unwrap(), out.params);
    assert_eq!(events[0], TrainEvent::Started { total_steps: 600, first_step: 1 });
    assert_eq!(events.iter().filter(|e| matches!(e, TrainEvent::Step { .. })).count(), 600);
    assert_eq!(events.iter().filter(|e| matches!(e, TrainEvent::Evaluated { .. })).count(), 4);
    // Checkpoints at 0, every 100 steps (600 is also the end).
    assert_eq!(events.iter().filter(|e| matches!(e, TrainEvent::Checkpointed { .. })).count(), 7);
}

/// Settings of the resume tests: 4 epochs of 3 shuffled batches, checkpoints every
/// 5 steps, evaluations every 3, clipping on.
fn resume_config() -> TrainConfig {
    TrainConfig {
        lr: 0.05,
        final_lr: None,
        clip: Some(20.0),
        epochs: 4,
        eval_every: 3,
        checkpoint_every: 5,
        seed: 42,
        shuffle: true,
        keep_best: None,
        average_tail: 0.0,
    }
}

#[test]
fn a_resumed_run_reproduces_the_uninterrupted_run_bitwise() {
    let config = resume_config();
    let whole = tempfile::tempdir().unwrap();
    let mut obj = Faulty::new(LgssmObjective::new(3, 40, 2));
    let full = train(&mut obj, store(START), &config, whole.path(), false, &mut quiet()).unwrap();
    let (full_seen, full_calls) = (obj.seen.clone(), obj.calls_log.clone());

    // Crash at the 9th estimate: rows 1..=8 and the evaluation at 6 are on disk,
    // the last checkpoint is at step 5.
    let broken = tempfile::tempdir().unwrap();
    let mut obj = Faulty::new(LgssmObjective::new(3, 40, 2));
    obj.crash_at = Some(9);
    let err = train(&mut obj, store(START), &config, broken.path(), false, &mut quiet()).unwrap_err();
    assert!(matches!(err, TrainError::Estimate { step: 9, .. }), "{err}");
    assert!(err.to_string().contains("step 9"), "{err}");
    assert_eq!(rows(&broken.path().join(TRAIN_LOG)).len(), 8);
    assert_eq!(Checkpoint::load(&broken.path().join(CHECKPOINT_FILE)).unwrap().step, 5);
    // A row torn by the crash.
    let mut log = std::fs::read_to_string(broken.path().join(TRAIN_LOG)).unwrap();
    log.push_str("9,2,1,-3.1");
    std::fs::write(broken.path().join(TRAIN_LOG), log).unwrap();

    // Resume: the initial store given is ignored (the checkpoint's is used).
    let mut obj = Faulty::new(LgssmObjective::new(3, 40, 2));
    let mut events = Vec::new();
    let resumed =
        train(&mut obj, store([0.0; 3]), &config, broken.path(), true, &mut |e| events.push(e.clone())).unwrap();
    assert_eq!(events[0], TrainEvent::Started { total_steps: 12, first_step: 6 });
    assert_eq!(obj.seen[..], full_seen[5..], "the resumed steps saw other parameters");
    assert_eq!(obj.calls_log[..], full_calls[5..], "the resumed steps used other batches or seeds");
    assert!(full_calls.iter().map(|c| c.1).collect::<std::collections::HashSet<_>>().len() == 12);
    assert_eq!(bits(&resumed.params), bits(&full.params));
    assert_eq!(resumed.final_eval, full.final_eval);
    assert_eq!((resumed.steps, resumed.skipped_steps), (full.steps, full.skipped_steps));
    let ckpt = |d: &Path| Checkpoint::load(&d.join(CHECKPOINT_FILE)).unwrap();
    let (a, b) = (ckpt(whole.path()), ckpt(broken.path()));
    assert_eq!((&a.adam, bits(&a.params), a.step), (&b.adam, bits(&b.params), b.step));

    // Logs: the same rows but for the timing column, each step exactly once, and
    // the same evaluation log.
    let strip = |d: &Path| -> Vec<Vec<String>> {
        rows(&d.join(TRAIN_LOG))
            .into_iter()
            .map(|mut r| {
                assert_eq!(r.len(), TRAIN_LOG_HEADER.len());
                r.pop();
                r
            })
            .collect()
    };
    let (rows_full, rows_resumed) = (strip(whole.path()), strip(broken.path()));
    assert_eq!(rows_full, rows_resumed);
    assert_eq!(column(&rows_resumed, "step"), (1..=12).map(|s| s.to_string()).collect::<Vec<_>>());
    let read = |d: &Path| std::fs::read_to_string(d.join(EVAL_LOG)).unwrap();
    assert_eq!(read(whole.path()), read(broken.path()));
    let eval_steps: Vec<String> = rows(&broken.path().join(EVAL_LOG)).into_iter().map(|r| r[0].clone()).collect();
    assert_eq!(eval_steps, ["0", "3", "6", "9", "12"]);
    // Shuffling happened: some epoch is not in order 0, 1, 2.
    let batches = column(&rows_full, "batch");
    assert!(batches.chunks(3).any(|c| c != ["0", "1", "2"]), "{batches:?}");

    // Resuming a finished run changes nothing.
    let mut obj = Faulty::new(LgssmObjective::new(3, 40, 2));
    let again = train(&mut obj, store(START), &config, broken.path(), true, &mut quiet()).unwrap();
    assert_eq!(obj.calls, 0);
    assert_eq!(bits(&again.params), bits(&full.params));
    assert_eq!(again.final_eval, full.final_eval);
    assert_eq!(strip(broken.path()), rows_full);
}

#[test]
fn non_finite_estimates_are_skipped_counted_and_logged() {
    let mut obj = Faulty::new(LgssmObjective::new(4, 40, 3));
    obj.nan_batch = Some(1);
    obj.error_batch = Some(2);
    let dir = tempfile::tempdir().unwrap();
    let config = TrainConfig { lr: 0.05, clip: Some(1.0), epochs: 5, seed: 9, ..Default::default() };
    let mut skipped_events = 0;
    let out = train(&mut obj, store(START), &config, dir.path(), false, &mut |e| {
        if let TrainEvent::Step { skipped: true, .. } = e {
            skipped_events += 1;
        }
    })
    .unwrap();
    assert_eq!((out.steps, out.skipped_steps, skipped_events), (20, 10, 10));
    assert!(out.params.values()[0].all_finite());

    let rows = rows(&dir.path().join(TRAIN_LOG));
    let (batch, skipped) = (column(&rows, "batch"), column(&rows, "skipped"));
    for (k, (b, s)) in batch.iter().zip(&skipped).enumerate() {
        let bad = b == "1" || b == "2";
        assert_eq!(s, if bad { "1" } else { "0" }, "step {}: batch {b}", k + 1);
        if bad {
            // The parameters the next step saw are those this step saw.
            if let Some(next) = obj.seen.get(k + 1) {
                assert_eq!(next, &obj.seen[k], "step {} changed the parameters", k + 1);
            }
            assert_eq!(column(&rows, "clipped")[k], "0");
        }
    }
    // The NaN gradient's norm is logged as NaN; the failed estimate's values as NaN.
    let i = batch.iter().position(|b| b == "1").unwrap();
    assert_eq!(column(&rows, "grad_norm")[i], "NaN");
    assert!(column(&rows, "log_likelihood")[i].parse::<f64>().unwrap().is_finite());
    let j = batch.iter().position(|b| b == "2").unwrap();
    assert_eq!(column(&rows, "log_likelihood")[j], "NaN");
    // Every skip has its reason in the skip log: the parameter whose gradient was
    // not finite, or the estimate's own message.
    let skips = self::rows(&dir.path().join(SKIP_LOG));
    assert_eq!(skips.len(), 10);
    for row in &skips {
        let step: usize = row[0].parse().unwrap();
        assert_eq!(skipped[step - 1], "1", "step {step}");
        assert_eq!(row[1], batch[step - 1]);
        let want = if row[1] == "1" { "gradient not finite in theta" } else { "all log-weights are -inf" };
        assert_eq!(row[2], want, "step {step}");
    }
    // Training still made progress on the healthy batches.
    assert!(obj.inner.total_score(theta_of(&out.params).to_array()).0 > obj.inner.total_score(START).0);
}

#[test]
fn other_estimate_errors_abort_naming_the_step() {
    struct Broken;
    impl Objective for Broken {
        fn batches(&self) -> usize {
            2
        }
        fn estimate(&mut self, _: &ParamStore<f64>, batch: usize, _: u64) -> Result<BatchEstimate, EstimateError> {
            Err(format!("scene {batch} unreadable").into())
        }
        fn evaluate(&mut self, _: &ParamStore<f64>, _: u64) -> Result<Vec<(String, f64)>, String> {
            Ok(vec![])
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let config = TrainConfig { shuffle: false, ..Default::default() };
    let err = train(&mut Broken, store(START), &config, dir.path(), false, &mut quiet()).unwrap_err();
    assert_eq!(err.to_string(), "step 1 (batch 0): gradient estimate failed: scene 0 unreadable");

    // A gradient of the wrong shape is an error, not a skipped step.
    struct WrongShape;
    impl Objective for WrongShape {
        fn batches(&self) -> usize {
            1
        }
        fn estimate(&mut self, _: &ParamStore<f64>, _: usize, _: u64) -> Result<BatchEstimate, EstimateError> {
            Ok(BatchEstimate {
                log_likelihood: 0.0,
                observed_units: 1,
                gradient: vec![Tensor::from_vec(vec![f64::NAN; 2])],
                collapsed_steps: 0,
            })
        }
        fn evaluate(&mut self, _: &ParamStore<f64>, _: u64) -> Result<Vec<(String, f64)>, String> {
            Ok(vec![])
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let err = train(&mut WrongShape, store(START), &config, dir.path(), false, &mut quiet()).unwrap_err();
    assert!(err.to_string().contains("`theta` has shape [2]"), "{err}");
}

#[test]
fn refuses_to_overwrite_to_resume_with_other_settings_and_to_read_a_damaged_checkpoint() {
    let config = resume_config();
    let dir = tempfile::tempdir().unwrap();
    let obj = || LgssmObjective::new(3, 20, 4);

    // Nothing to resume from.
    let err = train(&mut obj(), store(START), &config, dir.path(), true, &mut quiet()).unwrap_err();
    assert!(matches!(err, TrainError::NoCheckpoint { .. }), "{err}");
    assert!(err.to_string().contains(CHECKPOINT_FILE), "{err}");

    train(&mut obj(), store(START), &config, dir.path(), false, &mut quiet()).unwrap();
    let before = std::fs::read(dir.path().join(TRAIN_LOG)).unwrap();

    // A second fresh run in the same directory is refused and touches nothing.
    let err = train(&mut obj(), store(START), &config, dir.path(), false, &mut quiet()).unwrap_err();
    assert!(matches!(err, TrainError::Exists { .. }), "{err}");
    let msg = err.to_string();
    assert!(msg.contains("--resume") && msg.contains(&dir.path().display().to_string()), "{msg}");
    assert_eq!(std::fs::read(dir.path().join(TRAIN_LOG)).unwrap(), before);

    // Resuming with other settings is refused, naming each difference.
    let changed = TrainConfig { lr: 0.01, epochs: 5, ..config.clone() };
    let err = train(&mut obj(), store(START), &changed, dir.path(), true, &mut quiet()).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, TrainError::ConfigChanged { .. }), "{msg}");
    assert!(msg.contains("lr: 0.05") && msg.contains("epochs: 4 vs 5") && !msg.contains("seed"), "{msg}");
    // ... as is another objective (batch count) or parameter layout.
    let err = train(&mut LgssmObjective::new(2, 20, 4), store(START), &config, dir.path(), true, &mut quiet());
    assert!(matches!(err, Err(TrainError::Incompatible { .. })));
    let mut other = store(START);
    other.add("extra", Tensor::from_vec(vec![1.0]));
    let err = train(&mut obj(), other, &config, dir.path(), true, &mut quiet());
    assert!(matches!(err, Err(TrainError::Incompatible { .. })));

    // A flipped byte is caught by the checksum and the error names the file.
    let path = dir.path().join(CHECKPOINT_FILE);
    let mut bytes = std::fs::read(&path).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x10;
    std::fs::write(&path, bytes).unwrap();
    let err = train(&mut obj(), store(START), &config, dir.path(), true, &mut quiet()).unwrap_err();
    assert!(matches!(err, TrainError::Checkpoint { .. }), "{err}");
    assert!(err.to_string().contains(&path.display().to_string()), "{err}");
    assert!(err.to_string().contains("checksum"), "{err}");

    // Invalid settings are refused up front.
    let bad = TrainConfig { clip: Some(0.0), ..config };
    let other_dir = tempfile::tempdir().unwrap();
    let err = train(&mut obj(), store(START), &bad, other_dir.path(), false, &mut quiet()).unwrap_err();
    assert!(matches!(err, TrainError::Config(_)), "{err}");
}

#[test]
fn clipping_logs_the_norm_before_clipping_and_adam_sees_the_clipped_score() {
    let obj = LgssmObjective::new(3, 60, 5);
    let clip = 0.5;
    let config = TrainConfig { lr: 0.05, clip: Some(clip), epochs: 3, shuffle: false, ..Default::default() };
    let dir = tempfile::tempdir().unwrap();
    let mut run_obj = LgssmObjective { prior: obj.prior.clone(), train: obj.train.clone(), test: obj.test.clone() };
    let out = train(&mut run_obj, store(START), &config, dir.path(), false, &mut quiet()).unwrap();

    // Replay by hand: the exact score, clipped to norm 0.5, negated, into Adam.
    let log = rows(&dir.path().join(TRAIN_LOG));
    let (norms, clipped) = (column(&log, "grad_norm"), column(&log, "clipped"));
    let mut params = store(START);
    let mut adam = Adam::new(config.lr);
    for step in 0..9 {
        let m = obj.prior.with_theta(theta_of(&params)).unwrap();
        let (_, g) = m.score(&obj.train[step % 3]);
        let mut grads = vec![Tensor::from_vec(g.to_vec())];
        let norm = clip_global_norm(&mut grads, clip);
        assert!(norm > clip, "step {}: norm {norm} does not exercise clipping", step + 1);
        assert_eq!(norms[step].parse::<f64>().unwrap().to_bits(), norm.to_bits(), "step {}", step + 1);
        assert_eq!(clipped[step], "1");
        let clipped_norm: f64 = grads[0].data().iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!(clipped_norm <= clip * (1.0 + 1e-12));
        grads[0].data_mut().iter_mut().for_each(|x| *x = -*x);
        let before = params.values()[0].data().to_vec();
        adam.step(&mut params, &grads).unwrap();
        // Adam's step is bounded by a few learning rates per coordinate.
        for (a, b) in before.iter().zip(params.values()[0].data()) {
            assert!((a - b).abs() <= 3.0 * config.lr, "step {}: moved {}", step + 1, (a - b).abs());
        }
    }
    assert_eq!(bits(&out.params), bits(&params));
    let ckpt = Checkpoint::load(&dir.path().join(CHECKPOINT_FILE)).unwrap();
    assert_eq!(ckpt.adam, adam);

    // Without clipping the same run ends elsewhere: the clip changed the updates.
    let dir2 = tempfile::tempdir().unwrap();
    let unclipped = TrainConfig { clip: None, ..config };
    let out2 = train(&mut run_obj, store(START), &unclipped, dir2.path(), false, &mut quiet()).unwrap();
    assert_ne!(bits(&out2.params), bits(&out.params));
    assert!(column(&rows(&dir2.path().join(TRAIN_LOG)), "clipped").iter().all(|c| c == "0"));
}

#[test]
fn a_run_that_fails_at_once_leaves_no_files_and_metric_names_must_not_change() {
    /// Evaluation fails while `fail_eval`; otherwise its metric names change after
    /// the first call.
    struct Fickle {
        fail_eval: bool,
        evals: usize,
    }
    impl Objective for Fickle {
        fn batches(&self) -> usize {
            1
        }
        fn estimate(&mut self, _: &ParamStore<f64>, _: usize, _: u64) -> Result<BatchEstimate, EstimateError> {
            Ok(BatchEstimate {
                log_likelihood: -1.0,
                observed_units: 2,
                gradient: vec![Tensor::from_vec(vec![0.1, 0.2, 0.3])],
                collapsed_steps: 1,
            })
        }
        fn evaluate(&mut self, _: &ParamStore<f64>, _: u64) -> Result<Vec<(String, f64)>, String> {
            if self.fail_eval {
                return Err("test data missing".into());
            }
            self.evals += 1;
            Ok(vec![(if self.evals == 1 { "a" } else { "b" }.to_string(), 0.0)])
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let config = TrainConfig { epochs: 3, eval_every: 2, ..Default::default() };
    let err = train(&mut Fickle { fail_eval: true, evals: 0 }, store(START), &config, dir.path(), false, &mut quiet())
        .unwrap_err();
    assert_eq!(err.to_string(), "evaluation after step 0 failed: test data missing");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);

    // Now the start succeeds; the renamed metric at step 2 is an error.
    let err = train(&mut Fickle { fail_eval: false, evals: 0 }, store(START), &config, dir.path(), false, &mut quiet())
        .unwrap_err();
    assert!(matches!(err, TrainError::Evaluate { step: 2, .. }), "{err}");
    assert!(err.to_string().contains("[\"a\"] to [\"b\"]"), "{err}");
    let log = rows(&dir.path().join(TRAIN_LOG));
    assert_eq!(log.len(), 2);
    assert_eq!(&log[0][..10], ["1", "0", "0", "-1", "2", "-0.5", &(0.14f64.sqrt()).to_string(), "0", "0", "1"]);
}

#[test]
fn keep_best_returns_the_best_evaluation_and_survives_a_resume() {
    // 10 epochs of 3 batches, evaluated every 2 steps: the score turns at the
    // 13th estimate, so the test MLL rises, then falls for 18 steps.
    let config = TrainConfig { eval_every: 2, epochs: 10, keep_best: Some("test_mll".into()), ..resume_config() };
    let wandering = |crash_at| Wandering { inner: LgssmObjective::new(3, 40, 2), calls: 0, turn_at: 13, crash_at };
    let whole = tempfile::tempdir().unwrap();
    let full = train(&mut wandering(None), store(START), &config, whole.path(), false, &mut quiet()).unwrap();

    let evals = rows(&whole.path().join(EVAL_LOG));
    let value = |r: &Vec<String>| r[1].parse::<f64>().unwrap();
    let best = evals.iter().max_by(|a, b| value(a).total_cmp(&value(b))).unwrap();
    let last = evals.last().unwrap();
    let kept = full.kept.clone().expect("a finite evaluation was made");
    assert_eq!(kept.metric, "test_mll");
    assert_eq!(kept.step.to_string(), best[0]);
    assert!(kept.step > 0 && kept.step < 30, "the run climbed, then fell: kept step {}", kept.step);
    assert_eq!((kept.value, kept.last), (value(best), value(last)));
    assert!(kept.fall() > 0.0, "{kept:?}");
    // The parameters returned and written are those of that evaluation; the
    // checkpoint holds the last, to resume from.
    let theta: Vec<f64> = best[3..6].iter().map(|v| v.parse().unwrap()).collect();
    assert_eq!(full.params.values()[0].data(), &theta[..]);
    assert_eq!(ParamStore::<f64>::load(&whole.path().join(PARAMS_FILE)).unwrap(), full.params);
    let ckpt = Checkpoint::load(&whole.path().join(CHECKPOINT_FILE)).unwrap();
    let last_theta: Vec<f64> = last[3..6].iter().map(|v| v.parse().unwrap()).collect();
    assert_eq!(ckpt.params.values()[0].data(), &last_theta[..]);
    assert_eq!(ckpt.best.as_ref().map(|b| b.0), Some(kept.step));

    // Without the setting, the same run returns its last parameters.
    let plain = TrainConfig { keep_best: None, ..config.clone() };
    let dir = tempfile::tempdir().unwrap();
    let out = train(&mut wandering(None), store(START), &plain, dir.path(), false, &mut quiet()).unwrap();
    assert_eq!((out.params.values()[0].data(), out.kept), (&last_theta[..], None));

    // Interrupted after its best and resumed, it keeps the same parameters.
    let broken = tempfile::tempdir().unwrap();
    let crash_at = kept.step + 8;
    assert!(crash_at < 30);
    assert!(train(&mut wandering(Some(crash_at)), store(START), &config, broken.path(), false, &mut quiet()).is_err());
    // The resumed run's wrapper counts its estimates from the checkpoint on.
    let ckpt_step = Checkpoint::load(&broken.path().join(CHECKPOINT_FILE)).unwrap().step;
    let mut resumed_obj = wandering(None);
    resumed_obj.calls = ckpt_step;
    let resumed = train(&mut resumed_obj, store(START), &config, broken.path(), true, &mut quiet()).unwrap();
    assert_eq!(bits(&resumed.params), bits(&full.params));
    assert_eq!(resumed.kept, full.kept);

    // A metric the objective does not report is an error naming it.
    let wrong = TrainConfig { keep_best: Some("val_mll".into()), ..config };
    let dir = tempfile::tempdir().unwrap();
    let err = train(&mut wandering(None), store(START), &wrong, dir.path(), false, &mut quiet()).unwrap_err();
    assert!(err.to_string().contains("val_mll"), "{err}");
}

/// A run paused by `train_until` returns its best evaluation so far and, resumed,
/// ends exactly where the uninterrupted run ends: the pause is between two
/// checkpoints, and a second call at or before the checkpoint takes no step.
#[test]
fn a_paused_run_keeps_its_best_so_far_and_resumes_to_the_uninterrupted_run() {
    let config = TrainConfig { eval_every: 2, epochs: 10, keep_best: Some("test_mll".into()), ..resume_config() };
    let wandering = |calls| Wandering { inner: LgssmObjective::new(3, 40, 2), calls, turn_at: 13, crash_at: None };
    let whole = tempfile::tempdir().unwrap();
    let full = train(&mut wandering(0), store(START), &config, whole.path(), false, &mut quiet()).unwrap();
    assert_eq!(full.paused_at, None);
    let evals: Vec<(usize, f64)> =
        rows(&whole.path().join(EVAL_LOG)).iter().map(|r| (r[0].parse().unwrap(), r[1].parse().unwrap())).collect();

    // Paused after step 8 (an evaluation, between the checkpoints at 5 and 10).
    let dir = tempfile::tempdir().unwrap();
    let paused =
        train_until(&mut wandering(0), store(START), &config, dir.path(), false, Some(8), &mut quiet()).unwrap();
    assert_eq!((paused.paused_at, paused.steps_run, paused.steps), (Some(8), 8, 30));
    let best_so_far = evals.iter().filter(|e| e.0 <= 8).max_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
    let kept = paused.kept.clone().unwrap();
    assert_eq!((kept.step, kept.value, kept.last), (best_so_far.0, best_so_far.1, evals[4].1));
    assert_eq!(Checkpoint::load(&dir.path().join(CHECKPOINT_FILE)).unwrap().step, 8);
    // Asked again to pause there (or before), it takes no step.
    let again = train_until(&mut wandering(8), store(START), &config, dir.path(), true, Some(4), &mut quiet()).unwrap();
    assert_eq!((again.paused_at, again.steps_run, again.kept), (Some(8), 0, paused.kept));

    // Resumed to the end: the uninterrupted run, to the bit.
    let resumed = train(&mut wandering(8), store(START), &config, dir.path(), true, &mut quiet()).unwrap();
    assert_eq!((resumed.paused_at, resumed.steps_run), (None, 22));
    assert_eq!(bits(&resumed.params), bits(&full.params));
    assert_eq!(resumed.kept, full.kept);
    let read = |d: &Path| std::fs::read_to_string(d.join(EVAL_LOG)).unwrap();
    assert_eq!(read(whole.path()), read(dir.path()));
    // A finished run asked to pause takes no step and says it finished.
    let done = train_until(&mut wandering(30), store(START), &config, dir.path(), true, Some(8), &mut quiet()).unwrap();
    assert_eq!((done.paused_at, done.steps_run, done.kept), (None, 0, full.kept));
}

#[test]
fn a_version_2_checkpoint_is_read_as_a_run_without_keep_best() {
    // A checkpoint written by the version-2 code (commit 985dab9: PF on the
    // paper's experiment A, seed 0, at its last step), not a layout mirrored here.
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/checkpoint-v2.bin");
    let bytes = std::fs::read(&fixture).unwrap();
    assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 2, "a version-2 file");
    let read = Checkpoint::load(&fixture).unwrap();
    let expected = TrainConfig {
        lr: 0.01,
        final_lr: None,
        clip: None,
        epochs: 100,
        eval_every: 50,
        checkpoint_every: 50,
        seed: 0,
        shuffle: true,
        keep_best: None,
        average_tail: 0.0,
    };
    assert_eq!((read.step, read.batches), (1000, 10));
    assert_eq!((&read.config, &read.best), (&expected, &None));
    assert_eq!((read.last_eval.0, read.eval_names[0].as_str()), (1000, "test_mll"));
    assert!(!read.params.is_empty() && read.seconds > 0.0);
    // Saved again, it is a checkpoint of the current version that reads back the same.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(CHECKPOINT_FILE);
    read.save(&path).unwrap();
    assert_eq!(Checkpoint::load(&path).unwrap(), read);
    // Another version is refused, naming the version found.
    let mut v1 = bytes;
    v1[8..12].copy_from_slice(&1u32.to_le_bytes());
    std::fs::write(&path, v1).unwrap();
    let err = Checkpoint::load(&path).unwrap_err();
    assert!(err.to_string().contains('1'), "{err}");
}

#[test]
fn every_evaluation_of_a_run_uses_one_seed() {
    // Keep-best ranks a run's evaluations by their differences: with one filter
    // seed for all (common random numbers) those are the parameters', not the
    // evaluating filter's noise. A run of another seed evaluates with another.
    struct Recording {
        inner: LgssmObjective,
        seeds: Vec<u64>,
    }
    impl Objective for Recording {
        fn batches(&self) -> usize {
            self.inner.batches()
        }
        fn estimate(
            &mut self,
            params: &ParamStore<f64>,
            batch: usize,
            seed: u64,
        ) -> Result<BatchEstimate, EstimateError> {
            self.inner.estimate(params, batch, seed)
        }
        fn evaluate(&mut self, params: &ParamStore<f64>, seed: u64) -> Result<Vec<(String, f64)>, String> {
            self.seeds.push(seed);
            self.inner.evaluate(params, seed)
        }
    }
    let seeds_of = |seed: u64| {
        let config = TrainConfig { eval_every: 2, epochs: 3, seed, ..resume_config() };
        let mut objective = Recording { inner: LgssmObjective::new(3, 20, 2), seeds: Vec::new() };
        let dir = tempfile::tempdir().unwrap();
        train(&mut objective, store(START), &config, dir.path(), false, &mut quiet()).unwrap();
        objective.seeds
    };
    let seeds = seeds_of(42);
    // At step 0, every 2 steps and at the last (9).
    assert_eq!(seeds.len(), 6, "{seeds:?}");
    assert!(seeds.iter().all(|&s| s == eval_seed(42)), "{seeds:?}");
    assert!(seeds_of(43).iter().all(|&s| s == eval_seed(43) && s != eval_seed(42)));
}

#[test]
fn tail_averaging_returns_the_mean_of_the_last_iterates_and_survives_a_resume() {
    // 12 steps (4 epochs of 3 batches), the last half averaged: steps 7..=12.
    let plain = resume_config();
    let config = TrainConfig { average_tail: 0.5, ..plain.clone() };
    assert_eq!(config.average_start(12), Some(7));
    assert_eq!(
        (plain.average_start(12), TrainConfig { average_tail: 0.01, ..plain.clone() }.average_start(12)),
        (None, Some(12))
    );

    // The iterates of the plain run: `seen[k]` is the iterate after step k.
    let mut obj = Faulty::new(LgssmObjective::new(3, 40, 2));
    let dir = tempfile::tempdir().unwrap();
    let last = train(&mut obj, store(START), &plain, dir.path(), false, &mut quiet()).unwrap().params;
    let mut iterates = obj.seen[1..].to_vec();
    iterates.push(last.values()[0].data().to_vec());
    assert_eq!(iterates.len(), 12);
    let mean_of = |from: usize, to: usize| -> Vec<f64> {
        (0..3).map(|j| iterates[from - 1..to].iter().map(|it| it[j]).sum::<f64>() / (to + 1 - from) as f64).collect()
    };

    // The averaged run takes the same steps and returns the tail's mean.
    let whole = tempfile::tempdir().unwrap();
    let mut obj = Faulty::new(LgssmObjective::new(3, 40, 2));
    let averaged = train(&mut obj, store(START), &config, whole.path(), false, &mut quiet()).unwrap();
    assert_eq!(obj.seen[1..], iterates[..11], "averaging changed the trajectory");
    let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12);
    assert!(close(averaged.params.values()[0].data(), &mean_of(7, 12)), "{:?}", averaged.params.values());
    assert!(!close(averaged.params.values()[0].data(), &iterates[11]), "the mean is not the last iterate");
    assert_eq!(ParamStore::<f64>::load(&whole.path().join(PARAMS_FILE)).unwrap(), averaged.params);
    // Evaluations in the tail evaluate the running mean (phi is the last column):
    // at step 9 the mean of steps 7..=9, at 12 of 7..=12; at 6, the iterate.
    let evals = rows(&whole.path().join(EVAL_LOG));
    let phi_at = |step: &str| evals.iter().find(|r| r[0] == step).unwrap()[2].parse::<f64>().unwrap();
    let phi_of = |v: &[f64]| LgssmTheta::from_array([v[0], v[1], v[2]]).phi;
    assert!((phi_at("6") - phi_of(&iterates[5])).abs() < 1e-12);
    assert!((phi_at("9") - phi_of(&mean_of(7, 9))).abs() < 1e-12);
    assert!((phi_at("12") - phi_of(&mean_of(7, 12))).abs() < 1e-12);

    // Interrupted inside the tail (the last checkpoint at step 10) and resumed,
    // it returns the same mean to the bit.
    let broken = tempfile::tempdir().unwrap();
    let mut obj = Faulty::new(LgssmObjective::new(3, 40, 2));
    obj.crash_at = Some(11);
    assert!(train(&mut obj, store(START), &config, broken.path(), false, &mut quiet()).is_err());
    let ckpt = Checkpoint::load(&broken.path().join(CHECKPOINT_FILE)).unwrap();
    assert_eq!((ckpt.step, ckpt.average.as_ref().map(|a| a.0)), (10, Some(4)));
    let resumed = train(
        &mut Faulty::new(LgssmObjective::new(3, 40, 2)),
        store(START),
        &config,
        broken.path(),
        true,
        &mut quiet(),
    )
    .unwrap();
    assert_eq!(bits(&resumed.params), bits(&averaged.params));
    // A run that averages cannot resume one that did not.
    let err =
        train(&mut Faulty::new(LgssmObjective::new(3, 40, 2)), store(START), &config, dir.path(), true, &mut quiet())
            .unwrap_err();
    assert!(err.to_string().contains("average_tail"), "{err}");
    // A share outside [0, 1] is refused by name.
    let bad = TrainConfig { average_tail: 1.5, ..plain };
    let err = train(
        &mut Faulty::new(LgssmObjective::new(3, 40, 2)),
        store(START),
        &bad,
        tempfile::tempdir().unwrap().path(),
        false,
        &mut quiet(),
    )
    .unwrap_err();
    assert!(err.to_string().contains("average_tail"), "{err}");
}

#[test]
fn a_version_3_checkpoint_is_read_as_a_run_without_tail_averaging() {
    // A checkpoint written by the version-3 code (commit 10ff114: `sefi train
    // --policy hand-crafted --particles 16 --epochs 1 --eval-every 1
    // --keep-best` on two generated scenes, at its last step), not a layout
    // mirrored here: its keep-best state is carried over.
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/checkpoint-v3.bin");
    let bytes = std::fs::read(&fixture).unwrap();
    assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 3, "a version-3 file");
    let read = Checkpoint::load(&fixture).unwrap();
    let expected = TrainConfig {
        lr: 0.01,
        final_lr: None,
        clip: None,
        epochs: 1,
        eval_every: 1,
        checkpoint_every: 10,
        seed: 0,
        shuffle: true,
        keep_best: Some("test_mll".into()),
        average_tail: 0.0,
    };
    assert_eq!((read.step, read.batches, &read.config), (2, 2, &expected));
    let best = read.best.as_ref().expect("the keep-best state");
    assert_eq!((best.0, best.1), (2, -1.6480245532773865));
    assert_eq!(read.average, None);
    assert_eq!(read.eval_names[0], "test_mll");
    // Saved again, it is a checkpoint of the current version that reads back the same.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(CHECKPOINT_FILE);
    read.save(&path).unwrap();
    assert_eq!(Checkpoint::load(&path).unwrap(), read);
}
