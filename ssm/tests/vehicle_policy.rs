//! Policies: the sampler against the log-density (moments, a Kolmogorov–Smirnov
//! test, the expected log-density, normalisation), plain against tape values, and
//! the tape gradients against finite differences — for the hand-crafted policy, the
//! neural policy, and a correlated test policy that exercises the full Cholesky
//! factor in closed form.

use autodiff::gradcheck::GradCheck;
use autodiff::{Float, Tape, Tensor, Var};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use ssm::models::vehicle::{
    ActionBatch, ActionGaussianVars, ActionGaussians, ActionVars, GaussianPolicy, HandCraftedPolicy, NeuralPolicy,
    PolicyError,
};
use ssm::stats::ks_distance_to_normal;

const LN_2PI: f64 = 1.837_877_066_409_345_5;

/// A state-independent correlated Gaussian with parameters
/// `[mean_accel, mean_pinch, ln l11, l21, ln l22]`: the shape of output the neural
/// policy produces, without the network.
struct CorrelatedPolicy {
    theta: [f64; 5],
}

impl GaussianPolicy for CorrelatedPolicy {
    fn parameters(&self) -> Vec<Tensor<f64>> {
        vec![Tensor::from_vec(self.theta.to_vec())]
    }
    fn parameter_names(&self) -> Vec<String> {
        vec!["policy.theta".into()]
    }
    fn set_parameters(&mut self, params: &[Tensor<f64>]) -> Result<(), PolicyError> {
        ssm::models::vehicle::policy::check_parameters(&self.parameters(), params)?;
        self.theta.copy_from_slice(params[0].data());
        Ok(())
    }
    fn gaussians<F: Float>(&self, v: &[F], _kappa: &[F], out: &mut ActionGaussians<F>) {
        out.resize(v.len());
        let t = self.theta;
        out.mean_accel.fill(F::from_f64(t[0]));
        out.mean_pinch.fill(F::from_f64(t[1]));
        out.l11.fill(F::from_f64(t[2].exp()));
        out.l21.fill(F::from_f64(t[3]));
        out.l22.fill(F::from_f64(t[4].exp()));
    }
    fn gaussians_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        v: Var<'t, F>,
        _kappa: Var<'t, F>,
    ) -> ActionGaussianVars<'t, F> {
        let p = params[0];
        let zeros = v.mul_scalar(0.0);
        ActionGaussianVars {
            mean_accel: zeros + p.slice(0, 0, 1),
            mean_pinch: zeros + p.slice(0, 1, 1),
            l11: p.slice(0, 2, 1).exp(),
            l21: Some(p.slice(0, 3, 1)),
            l22: p.slice(0, 4, 1).exp(),
        }
    }
}

fn mean_var(z: &[f64]) -> (f64, f64) {
    let n = z.len() as f64;
    let m = z.iter().sum::<f64>() / n;
    (m, z.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0))
}

/// States over the synthetic data's range.
fn states(n: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let mut rng = StdRng::seed_from_u64(seed);
    let v = (0..n).map(|_| rng.random_range(0.0..40.0)).collect();
    let k = (0..n).map(|_| rng.random_range(-0.2..0.2)).collect();
    (v, k)
}

#[test]
fn hand_crafted_means_follow_the_spec() {
    for v in [0.0f64, 3.0, 8.0, 12.0, 40.0] {
        let m = HandCraftedPolicy::mean_accel(v);
        assert!((m - 1.5 * ((8.0 - v) / 4.0).tanh()).abs() < 1e-15);
        for k in [-0.2f64, 0.0, 0.07] {
            let p = HandCraftedPolicy::mean_pinch(v, k);
            assert!((p + k * (0.5 + 0.1 * v)).abs() < 1e-15);
        }
    }
    assert!(HandCraftedPolicy::mean_accel(2.0f64) > 1.0 && HandCraftedPolicy::mean_accel(30.0f64) < -1.4);
    let p = HandCraftedPolicy::truth();
    assert!((p.log_sd_accel() - 0.5f64.ln()).abs() < 1e-15);
    assert!((p.log_sd_pinch() - 0.02f64.ln()).abs() < 1e-15);
    assert_eq!(p.num_parameters(), 2);
}

#[test]
fn hand_crafted_sampler_matches_its_density() {
    let n = 20_000;
    let policy = HandCraftedPolicy::new(0.3f64.ln(), 0.05f64.ln()).unwrap();
    let (v, k) = states(n, 1);
    let mut rng = StdRng::seed_from_u64(2);
    let mut g = ActionGaussians::default();
    let mut actions = ActionBatch::zeros(n);
    policy.sample_actions(&v, &k, &mut rng, &mut g, actions.view_mut());
    // Standardise with the spec's formulas, independently of the library.
    let za: Vec<f64> = (0..n).map(|i| (actions.accel[i] - 1.5 * ((8.0 - v[i]) / 4.0).tanh()) / 0.3).collect();
    let zp: Vec<f64> = (0..n).map(|i| (actions.pinch[i] + k[i] * (0.5 + 0.1 * v[i])) / 0.05).collect();
    // With n = 20000 the standard errors are 1/sqrt(n) = 0.0071 for a mean or a
    // correlation and sqrt(2/n) = 0.010 for a variance: allow 4 of them (a false
    // alarm has probability ~6e-5 per check; the seed is fixed anyway).
    let se = 1.0 / (n as f64).sqrt();
    for z in [&za, &zp] {
        let (m, var) = mean_var(z);
        assert!(m.abs() < 4.0 * se, "mean {m}");
        assert!((var - 1.0).abs() < 4.0 * 2f64.sqrt() * se, "variance {var}");
        // KS at level 0.001: critical distance 1.95 / sqrt(n) = 0.0138.
        let d = ks_distance_to_normal(z.clone());
        assert!(d < 1.95 * se, "KS distance {d}");
    }
    let corr = za.iter().zip(&zp).map(|(a, b)| a * b).sum::<f64>() / n as f64;
    assert!(corr.abs() < 4.0 * se, "accel and pinch correlated: {corr}");

    // The density at the samples: log p = -ln 2pi - ln sd_a - ln sd_p - chi2_2 / 2,
    // so its mean is minus the entropy and its sd is 1.
    let mut lp = vec![0.0; n];
    policy.log_density(&v, &k, actions.view(), &mut g, &mut lp);
    for i in 0..n {
        let want = -LN_2PI - 0.3f64.ln() - 0.05f64.ln() - 0.5 * (za[i] * za[i] + zp[i] * zp[i]);
        assert!((lp[i] - want).abs() < 1e-10, "{} vs {want}", lp[i]);
    }
    let (m, _) = mean_var(&lp);
    let neg_entropy = -LN_2PI - 0.3f64.ln() - 0.05f64.ln() - 1.0;
    assert!((m - neg_entropy).abs() < 4.0 * se, "E log p = {m}, -H = {neg_entropy}");
}

#[test]
fn correlated_sampler_matches_its_covariance_and_density() {
    let n = 20_000;
    let policy = CorrelatedPolicy { theta: [0.4, -0.1, 0.7f64.ln(), 0.3, 0.2f64.ln()] };
    let (v, k) = states(n, 3);
    let mut rng = StdRng::seed_from_u64(4);
    let mut g = ActionGaussians::default();
    let mut a = ActionBatch::zeros(n);
    policy.sample_actions(&v, &k, &mut rng, &mut g, a.view_mut());
    // Sigma = L L^T with L = [[0.7, 0], [0.3, 0.2]].
    let sigma = [[0.49, 0.21], [0.21, 0.13]];
    let (ma, va) = mean_var(&a.accel);
    let (mp, vp) = mean_var(&a.pinch);
    let cov = a.accel.iter().zip(&a.pinch).map(|(x, y)| (x - ma) * (y - mp)).sum::<f64>() / (n as f64 - 1.0);
    let se = 1.0 / (n as f64).sqrt();
    // 4 standard errors of each moment (normal theory).
    assert!((ma - 0.4).abs() < 4.0 * se * 0.7 && (mp + 0.1).abs() < 4.0 * se * 0.13f64.sqrt());
    assert!((va - sigma[0][0]).abs() < 4.0 * se * 2f64.sqrt() * sigma[0][0]);
    assert!((vp - sigma[1][1]).abs() < 4.0 * se * 2f64.sqrt() * sigma[1][1]);
    let cov_se = se * (sigma[0][0] * sigma[1][1] + sigma[0][1] * sigma[0][1]).sqrt();
    assert!((cov - sigma[0][1]).abs() < 4.0 * cov_se, "cov {cov}");
    // Standardised samples are iid N(0, 1).
    let mut e1 = vec![0.0; n];
    let mut e2 = vec![0.0; n];
    g.standardise(a.view(), &mut e1, &mut e2);
    assert!(ks_distance_to_normal(e1) < 1.95 * se && ks_distance_to_normal(e2) < 1.95 * se);

    // The log-density equals the textbook formula with Sigma^{-1} and det Sigma.
    let mut lp = vec![0.0; n];
    g.log_density(a.view(), &mut lp);
    let det = sigma[0][0] * sigma[1][1] - sigma[0][1] * sigma[0][1];
    for (i, l) in lp.iter().enumerate().take(50) {
        let (r1, r2) = (a.accel[i] - 0.4, a.pinch[i] + 0.1);
        let q = (sigma[1][1] * r1 * r1 - 2.0 * sigma[0][1] * r1 * r2 + sigma[0][0] * r2 * r2) / det;
        let want = -LN_2PI - 0.5 * det.ln() - 0.5 * q;
        assert!((l - want).abs() < 1e-12);
    }
}

#[test]
fn densities_integrate_to_one() {
    // Midpoint rule over +-9 sd on a 600 x 600 grid: the Gaussian tails beyond are
    // ~1e-18 and the midpoint rule on a smooth, rapidly decaying integrand is
    // spectrally accurate, so 1e-9 is a safe bound.
    let correlated = CorrelatedPolicy { theta: [0.4, -0.1, 0.7f64.ln(), 0.3, 0.2f64.ln()] };
    // Each case fills one distribution and gives its marginal (mean, sd) pairs.
    type Case<'a> = (&'a dyn Fn(&mut ActionGaussians<f64>), [f64; 4]);
    let cases: [Case; 2] = [
        (
            &|g| HandCraftedPolicy::truth().gaussians(&[5.0], &[0.05], g),
            [HandCraftedPolicy::mean_accel(5.0), 0.5, HandCraftedPolicy::mean_pinch(5.0, 0.05), 0.02],
        ),
        // Marginal sds of the correlated case: 0.7 and sqrt(0.13).
        (&|g| correlated.gaussians(&[1.0], &[0.0], g), [0.4, 0.7, -0.1, 0.13f64.sqrt()]),
    ];
    for (fill, [ma, sa, mp, sp]) in cases {
        let mut g = ActionGaussians::default();
        fill(&mut g);
        let m = 600;
        let (ha, hp) = (18.0 * sa / m as f64, 18.0 * sp / m as f64);
        let mut acc = vec![0.0; m * m];
        let mut pin = vec![0.0; m * m];
        for i in 0..m {
            for j in 0..m {
                acc[i * m + j] = ma - 9.0 * sa + (i as f64 + 0.5) * ha;
                pin[i * m + j] = mp - 9.0 * sp + (j as f64 + 0.5) * hp;
            }
        }
        // The same distribution at every grid point.
        let big = ActionGaussians {
            mean_accel: vec![g.mean_accel[0]; m * m],
            mean_pinch: vec![g.mean_pinch[0]; m * m],
            l11: vec![g.l11[0]; m * m],
            l21: vec![g.l21[0]; m * m],
            l22: vec![g.l22[0]; m * m],
        };
        let mut lp = vec![0.0; m * m];
        big.log_density(ssm::models::vehicle::ActionsRef { accel: &acc, pinch: &pin }, &mut lp);
        let total: f64 = lp.iter().map(|l| l.exp()).sum::<f64>() * ha * hp;
        assert!((total - 1.0).abs() < 1e-9, "density integrates to {total}");
    }
}

#[test]
fn parameters_are_validated() {
    let mut p = HandCraftedPolicy::truth();
    assert!(matches!(p.set_parameters(&[]), Err(PolicyError::WrongCount { expected: 1, got: 0 })));
    let e = p.set_parameters(&[Tensor::from_vec(vec![0.0, 1.0, 2.0])]).unwrap_err();
    assert!(matches!(e, PolicyError::WrongShape { index: 0, .. }));
    assert!(e.to_string().contains("[2]"));
    assert!(matches!(HandCraftedPolicy::new(f64::NAN, 0.0), Err(PolicyError::NonFinite { index: 0 })));
    p.set_parameters(&[Tensor::from_vec(vec![-1.0, -2.0])]).unwrap();
    assert_eq!((p.log_sd_accel(), p.log_sd_pinch()), (-1.0, -2.0));
    // Binding makes tracked leaves with the same values.
    let tape = Tape::<f32>::new();
    let vars = p.bind_parameters(&tape);
    assert!(vars[0].is_tracked());
    assert_eq!(vars[0].to_tensor().data(), &[-1.0f32, -2.0]);
}

#[test]
fn f32_gaussians_track_f64() {
    let (v, k) = states(500, 8);
    let v32: Vec<f32> = v.iter().map(|&x| x as f32).collect();
    let k32: Vec<f32> = k.iter().map(|&x| x as f32).collect();
    let p = HandCraftedPolicy::truth();
    let (mut g64, mut g32) = (ActionGaussians::default(), ActionGaussians::default());
    p.gaussians(&v, &k, &mut g64);
    p.gaussians(&v32, &k32, &mut g32);
    for i in 0..v.len() {
        // The f32 tanh kernel is within 1e-6 absolute; the inputs carry 6e-8 relative.
        assert!((g64.mean_accel[i] - g32.mean_accel[i] as f64).abs() < 5e-6);
        assert!((g64.mean_pinch[i] - g32.mean_pinch[i] as f64).abs() < 1e-6);
    }
}

/// Plain and tape values of every policy agree, and the tape gradient in the
/// parameters, states and actions matches finite differences with settings `fd`.
fn check_tape<P: GaussianPolicy>(policy: &P, seed: u64, fd: &GradCheck) {
    let n = 7;
    let (v, k) = states(n, seed);
    let mut rng = StdRng::seed_from_u64(seed + 1);
    let mut g = ActionGaussians::default();
    let mut a = ActionBatch::zeros(n);
    policy.sample_actions(&v, &k, &mut rng, &mut g, a.view_mut());
    let mut lp = vec![0.0; n];
    g.log_density(a.view(), &mut lp);

    let tape = Tape::<f64>::new();
    let params = policy.bind_parameters(&tape);
    let c = |x: &[f64]| tape.constant(Tensor::from_vec(x.to_vec()));
    let actions = ActionVars { accel: c(&a.accel), pinch: c(&a.pinch) };
    let lp_tape = policy.log_density_on_tape(&params, c(&v), c(&k), &actions);
    for (x, y) in lp_tape.to_tensor().data().iter().zip(&lp) {
        assert!((x - y).abs() < 1e-12, "tape {x} vs plain {y}");
    }
    // Reparameterised actions on the tape from the same noise.
    let mut e1 = vec![0.0; n];
    let mut e2 = vec![0.0; n];
    g.standardise(a.view(), &mut e1, &mut e2);
    let rep = policy.gaussians_on_tape(&params, c(&v), c(&k)).actions_from_noise(c(&e1), c(&e2));
    for (x, y) in rep.accel.to_tensor().data().iter().zip(&a.accel) {
        assert!((x - y).abs() < 1e-12);
    }
    for (x, y) in rep.pinch.to_tensor().data().iter().zip(&a.pinch) {
        assert!((x - y).abs() < 1e-12);
    }

    // The score of the summed log-density: in the parameters (what PF-SEFI uses),
    // in the states and actions (what the through-filter baselines use).
    let mut inputs = policy.parameters();
    let np = inputs.len();
    for x in [&v, &k, &a.accel, &a.pinch] {
        inputs.push(Tensor::from_vec(x.to_vec()));
    }
    let w: Vec<f64> = (0..n).map(|_| rng.random_range(0.5..1.5)).collect();
    fd.check(
        |tape, x| {
            let actions = ActionVars { accel: x[np + 2], pinch: x[np + 3] };
            let lp = policy.log_density_on_tape(&x[..np], x[np], x[np + 1], &actions);
            (lp * tape.constant(Tensor::from_vec(w.clone()))).sum()
        },
        &inputs,
    )
    .expect("log-density gradient");
    // Reparameterised actions: gradient in parameters, states and noise.
    let mut inputs = policy.parameters();
    for x in [&v, &k, &e1, &e2] {
        inputs.push(Tensor::from_vec(x.to_vec()));
    }
    let noise: Vec<f64> = (0..2 * n).map(|_| rng.sample(StandardNormal)).collect();
    fd.check(
        |tape, x| {
            let act = policy.gaussians_on_tape(&x[..np], x[np], x[np + 1]).actions_from_noise(x[np + 2], x[np + 3]);
            let u = tape.constant(Tensor::from_vec(noise[..n].to_vec()));
            let r = tape.constant(Tensor::from_vec(noise[n..].to_vec()));
            (act.accel * u).sum() + (act.pinch * r).sum()
        },
        &inputs,
    )
    .expect("reparameterised action gradient");
    // The fused reparameterisation of recorded actions (the through-filter
    // baselines' transition): the same values, and the gradient of
    // `actions_from_noise` with the standardised noise held constant.
    let u = Tensor::from_vec(noise[..n].to_vec());
    let r = Tensor::from_vec(noise[n..].to_vec());
    let grads_of = |fused: bool| {
        let tape = Tape::<f64>::new();
        let params = policy.bind_parameters(&tape);
        let (vv, kv) = (tape.param(Tensor::from_vec(v.clone())), tape.param(Tensor::from_vec(k.clone())));
        let g = policy.gaussians_on_tape(&params, vv, kv);
        let c = |x: &[f64]| tape.constant(Tensor::from_vec(x.to_vec()));
        let act = if fused {
            g.reparameterised(&ActionVars { accel: c(&a.accel), pinch: c(&a.pinch) })
        } else {
            g.actions_from_noise(c(&e1), c(&e2))
        };
        let values = [act.accel.to_tensor(), act.pinch.to_tensor()];
        let total = (act.accel * tape.constant(u.clone())).sum() + (act.pinch * tape.constant(r.clone())).sum();
        let grads = tape.backward(total);
        let mut out: Vec<Tensor<f64>> = params.iter().map(|&p| grads.wrt(p)).collect();
        out.extend([grads.wrt(vv), grads.wrt(kv)]);
        (values, out)
    };
    let ((fused_values, fused), (composed_values, composed)) = (grads_of(true), grads_of(false));
    for (x, y) in fused_values.iter().zip(&composed_values) {
        for (x, y) in x.data().iter().zip(y.data()) {
            assert!((x - y).abs() < 1e-12, "reparameterised {x} vs actions_from_noise {y}");
        }
    }
    for (x, y) in fused.iter().zip(&composed) {
        for (x, y) in x.data().iter().zip(y.data()) {
            assert!((x - y).abs() <= 1e-12 * y.abs().max(1.0), "reparameterised gradient {x} vs composed {y}");
        }
    }
}

#[test]
fn hand_crafted_tape_values_and_gradients() {
    check_tape(&HandCraftedPolicy::new(-0.4, -3.5).unwrap(), 10, &GradCheck::default());
}

#[test]
fn correlated_tape_values_and_gradients() {
    let policy = CorrelatedPolicy { theta: [0.4, -0.1, 0.7f64.ln(), 0.3, 0.2f64.ln()] };
    check_tape(&policy, 20, &GradCheck::default());
}

#[test]
fn neural_tape_values_and_gradients() {
    let policy = NeuralPolicy::new(&mut StdRng::seed_from_u64(30));
    // A ReLU network is piecewise smooth: the default step (1e-3, with Richardson
    // extrapolation) moves the scaled inputs by 1e-2 and crosses kinks; 1e-6 does
    // not here. Its rounding error is ~1e-16 |f| / 1e-6 ~ 1e-10 absolute, so
    // gradients below 1e-3 are compared absolutely (to 1e-9) rather than relatively.
    let fd = GradCheck { step: 1e-6, abs_floor: 1e-3, ..GradCheck::default() };
    check_tape(&policy, 30, &fd);
}

#[test]
fn neural_policy_layout_parameters_and_precision() {
    let mut rng = StdRng::seed_from_u64(31);
    let mut policy = NeuralPolicy::new(&mut rng);
    // SPEC §3: (2 -> 32) + (32 -> 32) + (32 -> 5) weights and biases.
    assert_eq!(policy.num_parameters(), 2 * 32 + 32 + 32 * 32 + 32 + 32 * 5 + 5);
    assert_eq!(policy.num_parameters(), 1317);
    let mut params = policy.parameters();
    assert!(matches!(policy.set_parameters(&params[1..]), Err(PolicyError::WrongCount { .. })));
    params[2] = Tensor::zeros(&[32, 31]);
    assert!(matches!(policy.set_parameters(&params), Err(PolicyError::WrongShape { index: 2, .. })));
    // New parameters change the output; f32 tracks f64.
    let mut params = policy.parameters();
    for p in params.iter_mut() {
        for x in p.data_mut() {
            *x += rng.random_range(-0.05..0.05);
        }
    }
    let (v, k) = states(300, 32);
    let mut before = ActionGaussians::default();
    policy.gaussians(&v, &k, &mut before);
    policy.set_parameters(&params).unwrap();
    assert_eq!(policy.parameters(), params);
    let mut g64 = ActionGaussians::default();
    policy.gaussians(&v, &k, &mut g64);
    assert_ne!(before, g64);
    let v32: Vec<f32> = v.iter().map(|&x| x as f32).collect();
    let k32: Vec<f32> = k.iter().map(|&x| x as f32).collect();
    let mut g32 = ActionGaussians::default();
    policy.gaussians(&v32, &k32, &mut g32);
    // Order-one activations through three f32 layers: ~1e-6 relative each.
    let close = |a: &[f64], b: &[f32]| a.iter().zip(b).all(|(x, &y)| (x - y as f64).abs() < 1e-4 * x.abs().max(1.0));
    assert!(close(&g64.mean_accel, &g32.mean_accel) && close(&g64.mean_pinch, &g32.mean_pinch));
    assert!(close(&g64.l11, &g32.l11) && close(&g64.l21, &g32.l21) && close(&g64.l22, &g32.l22));
    assert!(g64.l11.iter().chain(&g64.l22).all(|&s| s > 0.0));
}

/// The neural policy's plain path (the block kernel the filter runs) against its tape
/// version, at states inside and beyond the inputs' clamps, over several networks and
/// batch sizes that are and are not whole blocks: f64 to rounding, f32 to f32's.
#[test]
fn neural_plain_path_matches_the_tape() {
    for seed in [40u64, 41, 42] {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut policy = NeuralPolicy::new(&mut rng);
        // Perturbed biases and weights, so no unit sits at a ReLU's kink by construction.
        let mut params = policy.parameters();
        for p in params.iter_mut() {
            p.data_mut().iter_mut().for_each(|x| *x += rng.random_range(-0.1..0.1));
        }
        policy.set_parameters(&params).unwrap();
        for n in [1usize, 63, 64, 65, 200] {
            let v: Vec<f64> = (0..n).map(|_| rng.random_range(-80.0..80.0)).collect();
            let k: Vec<f64> = (0..n).map(|_| rng.random_range(-0.8..0.8)).collect();
            let mut plain = ActionGaussians::default();
            policy.gaussians(&v, &k, &mut plain);
            let tape = Tape::<f64>::new();
            let bound = policy.bind_parameters(&tape);
            let c = |x: &[f64]| tape.constant(Tensor::from_vec(x.to_vec()));
            let on_tape = policy.gaussians_on_tape(&bound, c(&v), c(&k));
            let l21 = on_tape.l21.expect("full Cholesky factor");
            for (name, a, b) in [
                ("mean_accel", &plain.mean_accel, on_tape.mean_accel),
                ("mean_pinch", &plain.mean_pinch, on_tape.mean_pinch),
                ("l11", &plain.l11, on_tape.l11),
                ("l21", &plain.l21, l21),
                ("l22", &plain.l22, on_tape.l22),
            ] {
                for (i, (x, y)) in a.iter().zip(b.to_tensor().data()).enumerate() {
                    assert!((x - y).abs() <= 1e-12 * y.abs().max(1.0), "seed {seed}, n {n}, {name}[{i}]: {x} vs {y}");
                }
            }
            let v32: Vec<f32> = v.iter().map(|&x| x as f32).collect();
            let k32: Vec<f32> = k.iter().map(|&x| x as f32).collect();
            let mut plain32 = ActionGaussians::default();
            policy.gaussians(&v32, &k32, &mut plain32);
            for (a, b) in
                [(&plain32.mean_accel, &plain.mean_accel), (&plain32.l11, &plain.l11), (&plain32.l22, &plain.l22)]
            {
                for (x, y) in a.iter().zip(b) {
                    assert!((*x as f64 - y).abs() <= 1e-4 * y.abs().max(1.0), "seed {seed}, n {n}: f32 {x} vs f64 {y}");
                }
            }
        }
    }
}
