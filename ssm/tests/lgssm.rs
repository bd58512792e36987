//! The linear-Gaussian SSM: the Kalman log-likelihood, filter and smoother against
//! brute-force joint-Gaussian computations, the tape score against finite
//! differences, the simulator's moments, and the particle-filter pieces (including
//! a small bootstrap filter that must recover the Kalman log-likelihood).

use autodiff::gradcheck::GradCheck;
use autodiff::{Tape, Tensor};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmError, LgssmTheta, ThetaVars};

const LN_2PI: f64 = 1.837_877_066_409_345_5;

/// Lower Cholesky factor of a symmetric positive-definite matrix.
fn cholesky(a: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let n = a.len();
    let mut l = vec![vec![0.0; n]; n];
    for i in 0..n {
        for j in 0..=i {
            let s: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
            l[i][j] = if i == j { (a[i][i] - s).sqrt() } else { (a[i][j] - s) / l[j][j] };
        }
    }
    l
}

/// Solves `A x = b` given the Cholesky factor of `A`.
fn chol_solve(l: &[Vec<f64>], b: &[f64]) -> Vec<f64> {
    let n = b.len();
    let mut z = vec![0.0; n];
    for i in 0..n {
        z[i] = (b[i] - (0..i).map(|k| l[i][k] * z[k]).sum::<f64>()) / l[i][i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        x[i] = (z[i] - (i + 1..n).map(|k| l[k][i] * x[k]).sum::<f64>()) / l[i][i];
    }
    x
}

/// The joint law of `x_{0:T}`: means and covariance.
#[allow(clippy::needless_range_loop)]
fn state_moments(m: &Lgssm, len: usize) -> (Vec<f64>, Vec<Vec<f64>>) {
    let th = m.theta();
    let mut mean = vec![m.m0(); len];
    let mut var = vec![m.p0(); len];
    for t in 1..len {
        mean[t] = th.phi * mean[t - 1];
        var[t] = th.phi * th.phi * var[t - 1] + th.sv().powi(2);
    }
    let mut cov = vec![vec![0.0; len]; len];
    for s in 0..len {
        for t in s..len {
            let c = th.phi.powi((t - s) as i32) * var[s];
            cov[s][t] = c;
            cov[t][s] = c;
        }
    }
    (mean, cov)
}

/// `log p(y)` from the joint Gaussian of `y_{0:T}`.
fn brute_log_likelihood(m: &Lgssm, ys: &[f64]) -> f64 {
    let n = ys.len();
    let (mean, mut cov) = state_moments(m, n);
    for (t, row) in cov.iter_mut().enumerate() {
        row[t] += m.theta().sw().powi(2);
    }
    let l = cholesky(&cov);
    let r: Vec<f64> = ys.iter().zip(&mean).map(|(y, mu)| y - mu).collect();
    let alpha = chol_solve(&l, &r);
    let quad: f64 = r.iter().zip(&alpha).map(|(a, b)| a * b).sum();
    let logdet: f64 = (0..n).map(|i| l[i][i].ln()).sum::<f64>() * 2.0;
    -0.5 * (n as f64 * LN_2PI + logdet + quad)
}

/// `E[x_t | y_{0:T}]` and `Var[x_t | y_{0:T}]` for every t, by Gaussian conditioning.
fn brute_posterior(m: &Lgssm, ys: &[f64]) -> (Vec<f64>, Vec<f64>) {
    let n = ys.len();
    let (mean, cx) = state_moments(m, n);
    let mut cy = cx.clone();
    for (t, row) in cy.iter_mut().enumerate() {
        row[t] += m.theta().sw().powi(2);
    }
    let l = cholesky(&cy);
    let r: Vec<f64> = ys.iter().zip(&mean).map(|(y, mu)| y - mu).collect();
    let alpha = chol_solve(&l, &r);
    let mut pm = vec![0.0; n];
    let mut pv = vec![0.0; n];
    for t in 0..n {
        pm[t] = mean[t] + (0..n).map(|s| cx[t][s] * alpha[s]).sum::<f64>();
        let k = chol_solve(&l, &cx[t]);
        pv[t] = cx[t][t] - (0..n).map(|s| cx[t][s] * k[s]).sum::<f64>();
    }
    (pm, pv)
}

fn models() -> Vec<Lgssm> {
    vec![
        Lgssm::new(0.0, 1.0, LgssmTheta::new(0.9, 0.5, 0.8)).unwrap(),
        Lgssm::new(1.5, 0.3, LgssmTheta::new(-0.6, 1.2, 0.3)).unwrap(),
        Lgssm::new(-2.0, 4.0, LgssmTheta::new(1.05, 0.2, 1.5)).unwrap(),
        Lgssm::stationary(LgssmTheta::new(0.5, 1.0, 1.0)).unwrap(),
    ]
}

#[test]
fn log_likelihood_matches_the_joint_gaussian() {
    let mut rng = StdRng::seed_from_u64(1);
    for m in models() {
        for len in [1, 2, 5, 9] {
            let ys = m.simulate(len, &mut rng).ys;
            let k = m.log_likelihood(&ys);
            let b = brute_log_likelihood(&m, &ys);
            assert!((k - b).abs() < 1e-10 * b.abs().max(1.0), "Kalman {k} vs brute force {b}");
            assert_eq!(m.filter(&ys).log_likelihood, k);
        }
    }
    assert_eq!(models()[0].log_likelihood(&[]), 0.0);
}

#[test]
fn filter_and_smoother_match_gaussian_conditioning() {
    let mut rng = StdRng::seed_from_u64(2);
    for m in models() {
        let ys = m.simulate(8, &mut rng).ys;
        let sm = m.smooth(&ys);
        let (pm, pv) = brute_posterior(&m, &ys);
        for t in 0..ys.len() {
            assert!((sm.mean[t] - pm[t]).abs() < 1e-10, "t = {t}: {} vs {}", sm.mean[t], pm[t]);
            assert!((sm.var[t] - pv[t]).abs() < 1e-10, "t = {t}: {} vs {}", sm.var[t], pv[t]);
        }
        // The filter at t is the smoother of the data up to t.
        let f = m.filter(&ys);
        for t in [0, 3, ys.len() - 1] {
            let (pm, pv) = brute_posterior(&m, &ys[..=t]);
            assert!((f.mean[t] - pm[t]).abs() < 1e-10 && (f.var[t] - pv[t]).abs() < 1e-10);
        }
        assert_eq!(f.pred_mean[0], m.m0());
        assert_eq!(f.pred_var[0], m.p0());
    }
}

#[test]
fn tape_score_matches_finite_differences() {
    let mut rng = StdRng::seed_from_u64(3);
    for m in models() {
        let ys = m.simulate(30, &mut rng).ys;
        GradCheck::default()
            .check(
                |_, v| m.log_likelihood_on_tape(&ThetaVars::from_vector(v[0]), &ys),
                &[Tensor::from_vec(m.theta().to_array().to_vec())],
            )
            .expect("Kalman score");
        // And the convenience score against differences of the plain log-likelihood.
        let (ll, score) = m.score(&ys);
        assert!((ll - m.log_likelihood(&ys)).abs() < 1e-12);
        for (i, &g) in score.iter().enumerate() {
            let h = 1e-6;
            let at = |d: f64| {
                let mut a = m.theta().to_array();
                a[i] += d;
                m.with_theta(LgssmTheta::from_array(a)).unwrap().log_likelihood(&ys)
            };
            let fd = (at(h) - at(-h)) / (2.0 * h);
            assert!((g - fd).abs() < 1e-6 * g.abs().max(1.0), "d/dtheta[{i}]: {g} vs {fd}");
        }
    }
}

#[test]
fn score_is_zero_in_expectation_at_the_truth() {
    // Fisher's identity check of a different kind: E_theta[score] = 0. Each score
    // coordinate over 400 sequences of length 25 has sd ~ sqrt(Fisher information);
    // test the mean against 4 of its standard errors (estimated from the sample).
    let m = Lgssm::stationary(LgssmTheta::new(0.7, 0.6, 0.9)).unwrap();
    let mut rng = StdRng::seed_from_u64(4);
    let scores: Vec<[f64; 3]> = (0..400).map(|_| m.score(&m.simulate(25, &mut rng).ys).1).collect();
    for i in 0..3 {
        let xs: Vec<f64> = scores.iter().map(|s| s[i]).collect();
        let n = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / n;
        let sd = (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        assert!(mean.abs() < 4.0 * sd / n.sqrt(), "score[{i}] mean {mean}, sd {sd}");
    }
}

#[test]
fn simulated_moments_are_right() {
    // Stationary: Var x_t = P0, Var y_t = P0 + sw^2, Cov(y_t, y_{t+1}) = phi P0.
    let theta = LgssmTheta::new(0.8, 0.6, 0.5);
    let m = Lgssm::stationary(theta).unwrap();
    let p0 = m.p0();
    let (reps, len) = (4000, 6);
    let mut rng = StdRng::seed_from_u64(5);
    let sims: Vec<_> = (0..reps).map(|_| m.simulate(len, &mut rng)).collect();
    assert!(sims.iter().all(|s| s.xs.len() == len && s.ys.len() == len));
    let n = reps as f64;
    for t in 0..len - 1 {
        let y: Vec<f64> = sims.iter().map(|s| s.ys[t]).collect();
        let y1: Vec<f64> = sims.iter().map(|s| s.ys[t + 1]).collect();
        let x: Vec<f64> = sims.iter().map(|s| s.xs[t]).collect();
        let vy = p0 + theta.sw().powi(2);
        let mean = y.iter().sum::<f64>() / n;
        let var = y.iter().map(|v| v * v).sum::<f64>() / n;
        let cov = y.iter().zip(&y1).map(|(a, b)| a * b).sum::<f64>() / n;
        let cxy = x.iter().zip(&y).map(|(a, b)| a * b).sum::<f64>() / n;
        // Standard errors under normality: sd/sqrt(n) for the mean,
        // sqrt(2/n) var for a variance, sqrt((s_a^2 s_b^2 + c^2)/n) for a covariance;
        // allow 4.5 of them (18 checks, fixed seed).
        let k = 4.5 / n.sqrt();
        assert!(mean.abs() < k * vy.sqrt(), "t = {t}: mean {mean}");
        assert!((var - vy).abs() < k * 2f64.sqrt() * vy, "t = {t}: var {var} vs {vy}");
        let c = theta.phi * p0;
        assert!((cov - c).abs() < k * (vy * vy + c * c).sqrt(), "t = {t}: cov {cov} vs {c}");
        assert!((cxy - p0).abs() < k * (p0 * vy + p0 * p0).sqrt(), "t = {t}: cov(x, y) {cxy}");
    }
}

#[test]
fn invalid_models_are_rejected() {
    let th = LgssmTheta::new(0.5, 1.0, 1.0);
    assert_eq!(Lgssm::new(0.0, 0.0, th).unwrap_err(), LgssmError::NonPositivePriorVariance(0.0));
    assert!(matches!(Lgssm::new(f64::NAN, 1.0, th), Err(LgssmError::NonFinite("m0"))));
    let e = Lgssm::stationary(LgssmTheta::new(1.0, 1.0, 1.0)).unwrap_err();
    assert!(e.to_string().contains("phi"));
    assert_eq!(LgssmTheta::from_array(th.to_array()), th);
}

#[test]
fn particle_filter_pieces_match_their_formulas_and_tape_versions() {
    let m = Lgssm::new(0.3, 2.0, LgssmTheta::new(0.9, 0.4, 0.7)).unwrap();
    let th = m.theta();
    let prev = [0.5, -1.0, 2.0, 0.0];
    let eps = [0.1, -0.3, 1.2, 2.0];
    let mut next = prev;
    m.propagate_with_noise(&eps, &mut next);
    for i in 0..4 {
        assert!((next[i] - (th.phi * prev[i] + th.sv() * eps[i])).abs() < 1e-15);
    }
    let normal = |x: f64, mu: f64, sd: f64| -0.5 * LN_2PI - sd.ln() - 0.5 * ((x - mu) / sd).powi(2);
    let mut lg = [0.0; 4];
    m.obs_log_density(0.8, &next, &mut lg);
    let mut lf = [0.0; 4];
    m.transition_log_density(&prev, &next, &mut lf);
    let mut lp = [0.0; 4];
    m.prior_log_density(&prev, &mut lp);
    for i in 0..4 {
        assert!((lg[i] - normal(0.8, next[i], th.sw())).abs() < 1e-13);
        assert!((lf[i] - normal(next[i], th.phi * prev[i], th.sv())).abs() < 1e-13);
        assert!((lp[i] - normal(prev[i], m.m0(), m.p0().sqrt())).abs() < 1e-13);
    }
    // Tape versions: same values, gradients in theta and the particles.
    let tape = Tape::<f64>::new();
    let t = ThetaVars::constant(&tape, &th);
    let c = |x: &[f64]| tape.constant(Tensor::from_vec(x.to_vec()));
    let close = |a: &Tensor<f64>, b: &[f64]| a.data().iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-13);
    assert!(close(&t.propagate(c(&prev), c(&eps)).to_tensor(), &next));
    assert!(close(&t.obs_log_density(0.8, c(&next)).to_tensor(), &lg));
    assert!(close(&t.transition_log_density(c(&prev), c(&next)).to_tensor(), &lf));
    GradCheck::default()
        .check(
            |_, v| {
                let t = ThetaVars::from_vector(v[0]);
                let x1 = t.propagate(v[1], v[2]);
                (t.obs_log_density(0.8, x1) + t.transition_log_density(v[1], x1)).sum()
            },
            &[
                Tensor::from_vec(th.to_array().to_vec()),
                Tensor::from_vec(prev.to_vec()),
                Tensor::from_vec(eps.to_vec()),
            ],
        )
        .expect("particle pieces gradient");
}

#[test]
fn bootstrap_filter_from_the_pieces_recovers_the_kalman_likelihood() {
    // A minimal bootstrap filter (multinomial resampling) built from the plain pieces.
    // Its likelihood estimate is unbiased for p(y), so the log estimate is biased by
    // about -sd^2/2 (measured: sd ~0.14 nats at N = 2000, T = 20, bias ~ -0.01).
    // The mean of 20 runs must lie within 4 standard errors (sample sd / sqrt(20))
    // plus that bias of the Kalman value.
    let m = Lgssm::new(0.0, 1.0, LgssmTheta::new(0.8, 0.5, 0.6)).unwrap();
    let mut rng = StdRng::seed_from_u64(6);
    let ys = m.simulate(20, &mut rng).ys;
    let exact = m.log_likelihood(&ys);
    let n = 2000;
    let mut estimates = Vec::new();
    let reps = 20;
    for _ in 0..reps {
        let mut xs = vec![0.0f64; n];
        m.sample_prior(&mut rng, &mut xs);
        let mut lw = vec![0.0; n];
        let mut ll = 0.0;
        for (t, &y) in ys.iter().enumerate() {
            if t > 0 {
                m.propagate(&mut rng, &mut xs);
            }
            m.obs_log_density(y, &xs, &mut lw);
            let max = lw.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            let w: Vec<f64> = lw.iter().map(|l| (l - max).exp()).collect();
            let total: f64 = w.iter().sum();
            ll += max + (total / n as f64).ln();
            // Multinomial resampling by inverse CDF on sorted uniforms.
            let mut u: Vec<f64> = (0..n).map(|_| rng.random::<f64>() * total).collect();
            u.sort_by(|a, b| a.partial_cmp(b).unwrap());
            let mut out = Vec::with_capacity(n);
            let (mut j, mut cum) = (0, w[0]);
            for ui in u {
                while cum < ui && j + 1 < n {
                    j += 1;
                    cum += w[j];
                }
                out.push(xs[j]);
            }
            xs = out;
        }
        estimates.push(ll);
    }
    let k = reps as f64;
    let mean = estimates.iter().sum::<f64>() / k;
    let sd = (estimates.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (k - 1.0)).sqrt();
    assert!(
        (mean - exact).abs() < 4.0 * sd / k.sqrt() + 0.5 * sd * sd,
        "bootstrap filter {mean} (sd {sd}) vs Kalman {exact}"
    );
    assert!(sd < 0.5, "bootstrap filter sd {sd} is implausibly large");
}
