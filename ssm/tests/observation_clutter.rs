//! Clutter in the point observation model: `g_c = (1 - eps) g + eps N2(centre, s^2 I)`.
//! The plain and tape paths against an f64 reference mixed by hand from the
//! clutter-free per-point densities, tape gradients against finite differences
//! (parameters, rows, and the clutter's logit fraction and log scale), the limits
//! `eps -> 0` and far-away points, finiteness at extreme `eps`, and the sampler
//! against the density.

use crate::common::{assert_finite_with_gradients, ctx, f32_row_params, kink_free_rows, model, poses, soa, to32, Rows};
use autodiff::gradcheck::GradCheck;
use autodiff::nn::{BoundParams, ParamStore};
use autodiff::{Parallelism, Tape, Tensor, Var};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::data::Pose;
use ssm::models::observation::points::Clutter;
use ssm::models::observation::{ObsContext, ObservationModel, PointObservationModel, PosesRef, RowVars, Scratch};

/// `ln(2 pi)`.
const LN_2PI: f64 = 1.837_877_066_409_345_5;

fn softplus(x: f64) -> f64 {
    if x > 0.0 {
        x + (-x).exp().ln_1p()
    } else {
        x.exp().ln_1p()
    }
}

/// `log g_c(p | pose)` mixed by hand from the clutter-free `log g` (which
/// `log_density_items` gives per point), with `eps = sigmoid(lambda)`, `s = exp(sigma)`.
fn reference(
    model: &PointObservationModel,
    store: &ParamStore<f64>,
    ctx: &ObsContext,
    pose: Pose,
    pts: &[[f64; 2]],
    lambda: f64,
    sigma: f64,
) -> f64 {
    let mut lg = vec![0.0; pts.len()];
    model.log_density_items(store, ctx, pose, pts, &mut lg);
    let (ln_keep, ln_eps) = (-softplus(lambda), -softplus(-lambda));
    pts.iter()
        .zip(&lg)
        .map(|(p, &lg)| {
            let d2 = (p[0] - pose.x).powi(2) + (p[1] - pose.y).powi(2);
            let a = ln_keep + lg;
            let b = ln_eps - LN_2PI - 2.0 * sigma - 0.5 * d2 * (-2.0 * sigma).exp();
            let m = a.max(b);
            m + ((a - m).exp() + (b - m).exp()).ln()
        })
        .sum()
}

/// One batch of rows (contexts of varying extents) with point sets drawn with
/// clutter, so both mixture components carry weight.
fn clutter_rows(
    model: &PointObservationModel,
    store: &ParamStore<f64>,
    r: usize,
    per_row: usize,
    seed: u64,
) -> Rows<[f64; 2]> {
    let clutter = Clutter { fraction: 0.3, scale: 2.0 };
    kink_free_rows(model, store, r, per_row, seed, |ctx, pose, rng| {
        let mut cand = Vec::new();
        model.sample_with_clutter(store, ctx, pose, 1, clutter, rng, &mut cand);
        cand[0]
    })
}

/// `log_likelihood_rows_with_clutter` on an f64 tape with constant rows and clutter.
fn tape_rows(
    model: &PointObservationModel,
    store: &ParamStore<f64>,
    poses: &[Pose],
    ctxs: &[ObsContext],
    items: &[&[[f64; 2]]],
    lambda: f64,
    sigma: f64,
) -> Vec<f64> {
    let tape = Tape::<f64>::new();
    let params = store.bind(&tape);
    let rv = RowVars::from_poses(&tape, poses, ctxs);
    let av: Vec<Pose> = ctxs.iter().map(|c| c.av).collect();
    let (l, s) = (tape.constant(Tensor::from_vec(vec![lambda])), tape.constant(Tensor::from_vec(vec![sigma])));
    model.log_likelihood_rows_with_clutter(&params, &rv, &av, items, l, s).to_tensor().data().to_vec()
}

#[test]
fn plain_and_tape_paths_match_the_hand_mixed_reference() {
    let (model, store) = model(1);
    let mut rng = StdRng::seed_from_u64(2);
    let ps = poses(13, &mut rng);
    let (lambda, sigma) = (-1.2, 0.7);
    let clutter = Clutter::from_logits(lambda, sigma);
    let c = ctx();
    // Box points, clutter points, and a few anywhere within 3 m and 10 m away.
    let mut pts = Vec::new();
    model.sample_with_clutter(&store, &c, ps[0], 20, clutter, &mut rng, &mut pts);
    for _ in 0..3 {
        pts.push([ps[0].x + rng.random_range(-3.0..3.0), ps[0].y + rng.random_range(-3.0..3.0)]);
    }
    pts.push([ps[0].x + 10.0, ps[0].y - 1.0]);
    let want: Vec<f64> = ps.iter().map(|p| reference(&model, &store, &c, *p, &pts, lambda, sigma)).collect();
    // Both components matter for these points: the reference differs from the
    // clutter-free value by more than rounding.
    let (xs, ys, yaws) = soa(&ps);
    let mut base = vec![0.0; ps.len()];
    model.log_likelihood(&store, &c, PosesRef::new(&xs, &ys, &yaws), &pts, &mut Scratch::new(), &mut base);
    assert!((want[0] - base[0]).abs() > 1.0, "clutter {} vs none {}", want[0], base[0]);

    // Plain path, f64.
    let mut out = vec![0.0; ps.len()];
    let mut scratch = Scratch::new();
    model.log_likelihood_with_clutter(
        &store,
        &c,
        PosesRef::new(&xs, &ys, &yaws),
        &pts,
        clutter,
        &mut scratch,
        &mut out,
    );
    for (i, (o, w)) in out.iter().zip(&want).enumerate() {
        assert!((o - w).abs() < 1e-10 * w.abs().max(1.0), "particle {i}: plain {o} vs reference {w}");
    }
    // Plain path, f32: the clutter-free path's budget (per point ~3e-4 from coordinate
    // rounding times the slope of log g, plus ~1e-6 relative); mixing with the
    // clutter term only lowers the slope (responsibilities are at most 1).
    let store32 = store.cast::<f32>();
    let (x32, y32, w32) = (to32(&xs), to32(&ys), to32(&yaws));
    let mut out32 = vec![0.0f32; ps.len()];
    model.log_likelihood_with_clutter(
        &store32,
        &c,
        PosesRef::new(&x32, &y32, &w32),
        &pts,
        clutter,
        &mut Scratch::new(),
        &mut out32,
    );
    for (i, (o, w)) in out32.iter().zip(&want).enumerate() {
        let tol = 3e-4 * pts.len() as f64 + 1e-6 * w.abs();
        assert!((*o as f64 - w).abs() < tol, "particle {i}: f32 {o} vs reference {w}");
    }
    // Tape path, f64 (one row per pose, the same points in every row).
    let items: Vec<&[[f64; 2]]> = vec![&pts[..]; ps.len()];
    let tape = tape_rows(&model, &store, &ps, &vec![c; ps.len()], &items, lambda, sigma);
    for (i, (t, w)) in tape.iter().zip(&want).enumerate() {
        assert!((t - w).abs() < 1e-9 * w.abs().max(1.0), "row {i}: tape {t} vs reference {w}");
    }
    // No points: 0 on both paths.
    let mut empty = vec![1.0; ps.len()];
    model.log_likelihood_with_clutter(
        &store,
        &c,
        PosesRef::new(&xs, &ys, &yaws),
        &[],
        clutter,
        &mut scratch,
        &mut empty,
    );
    assert!(empty.iter().all(|&v| v == 0.0));
    let none: Vec<&[[f64; 2]]> = vec![&[]; 2];
    assert_eq!(tape_rows(&model, &store, &ps[..2], &[c; 2], &none, lambda, sigma), vec![0.0, 0.0]);
}

/// A constant of shape `[1]`.
fn scalar1(tape: &Tape<f64>, x: f64) -> Var<'_, f64> {
    tape.constant(Tensor::from_vec(vec![x]))
}

/// `sum_r w_r out_r`: a scalar that weighs every row differently.
fn weighted<'t>(tape: &'t Tape<f64>, weights: &Tensor<f64>, out: Var<'t, f64>) -> Var<'t, f64> {
    (out * tape.constant(weights.clone())).sum()
}

#[test]
fn tape_gradients_match_finite_differences() {
    let (model, store) = model(7);
    let b = clutter_rows(&model, &store, 3, 7, 8);
    let items = b.item_slices();
    let weights = Tensor::from_vec(vec![1.0, -0.6, 0.3]);
    // A clutter broad enough that both components share most points.
    let (lambda, sigma) = (-0.8, 2f64.ln());
    let clutter_inputs = [Tensor::from_vec(vec![lambda]), Tensor::from_vec(vec![sigma])];

    // Every network parameter (rows and clutter constant).
    let report = GradCheck::default()
        .check_params(&store, |tape, params| {
            let rv = RowVars::from_poses(tape, &b.poses, &b.ctxs);
            let (l, s) = (scalar1(tape, lambda), scalar1(tape, sigma));
            weighted(tape, &weights, model.log_likelihood_rows_with_clutter(params, &rv, &b.av, &items, l, s))
        })
        .unwrap();
    assert!(report.comparisons >= 100, "{report:?}");

    // States, extents and the clutter's logit fraction and log scale.
    let mut inputs = b.inputs();
    inputs.extend(clutter_inputs.iter().cloned());
    let report = GradCheck::default()
        .check(
            |tape, v| {
                let params = store.bind(tape);
                let rv = RowVars { x: v[0], y: v[1], yaw: v[2], length: v[3], width: v[4] };
                weighted(
                    tape,
                    &weights,
                    model.log_likelihood_rows_with_clutter(&params, &rv, &b.av, &items, v[5], v[6]),
                )
            },
            &inputs,
        )
        .unwrap();
    assert_eq!(report.comparisons, 3 * 5 + 2);

    // Only the clutter tracked (network and rows constant): its partials alone
    // decide that the fused kernel computes gradients.
    let report = GradCheck::default()
        .check(
            |tape, v| {
                let params = BoundParams::from_vars(store.values().iter().map(|t| tape.constant(t.clone())).collect());
                let rv = RowVars::from_poses(tape, &b.poses, &b.ctxs);
                weighted(
                    tape,
                    &weights,
                    model.log_likelihood_rows_with_clutter(&params, &rv, &b.av, &items, v[0], v[1]),
                )
            },
            &clutter_inputs,
        )
        .unwrap();
    assert_eq!(report.comparisons, 2);
}

#[test]
fn vanishing_clutter_gives_the_clutter_free_model_and_far_points_are_clutter() {
    let (model, store) = model(3);
    let c = ctx();
    let mut rng = StdRng::seed_from_u64(4);
    let ps = poses(9, &mut rng);
    let (xs, ys, yaws) = soa(&ps);
    let mut pts = Vec::new();
    model.sample(&store, &c, ps[0], 12, &mut rng, &mut pts);
    pts.push([ps[0].x + 2.5, ps[0].y + 1.5]);

    // eps = sigmoid(-30) ~ 1e-13: the mixture changes log g by at most ~eps c / g.
    let (lambda, sigma) = (-30.0, 0.0);
    let tiny = Clutter::from_logits(lambda, sigma);
    let poses_ref = PosesRef::new(&xs, &ys, &yaws);
    let (mut with, mut without) = (vec![0.0; ps.len()], vec![0.0; ps.len()]);
    model.log_likelihood_with_clutter(&store, &c, poses_ref, &pts, tiny, &mut Scratch::new(), &mut with);
    model.log_likelihood(&store, &c, poses_ref, &pts, &mut Scratch::new(), &mut without);
    for (a, b) in with.iter().zip(&without) {
        assert!(a.is_finite() && (a - b).abs() < 1e-9 * b.abs().max(1.0), "eps -> 0: {a} vs {b}");
    }
    let items: Vec<&[[f64; 2]]> = vec![&pts[..]; ps.len()];
    let tape = tape_rows(&model, &store, &ps, &vec![c; ps.len()], &items, lambda, sigma);
    for (a, b) in tape.iter().zip(&without) {
        assert!(a.is_finite() && (a - b).abs() < 1e-9 * b.abs().max(1.0), "tape, eps -> 0: {a} vs {b}");
    }
    // The same in f32 (exp and ln are the fast approximations): finite, and equal up
    // to the f32 path's own rounding.
    let store32 = store.cast::<f32>();
    let (x32, y32, w32) = (to32(&xs), to32(&ys), to32(&yaws));
    let p32 = PosesRef::new(&x32, &y32, &w32);
    let (mut with32, mut without32) = (vec![0.0f32; ps.len()], vec![0.0f32; ps.len()]);
    model.log_likelihood_with_clutter(&store32, &c, p32, &pts, tiny, &mut Scratch::new(), &mut with32);
    model.log_likelihood(&store32, &c, p32, &pts, &mut Scratch::new(), &mut without32);
    for (a, b) in with32.iter().zip(&without32) {
        assert!(a.is_finite() && (a - b).abs() <= 1e-6 * b.abs().max(1.0), "f32, eps -> 0: {a} vs {b}");
    }

    // A point 50 m from the box centre: its box density is negligible next to the
    // clutter's, so log g_c = ln eps + log N2 up to ln(1 + (1 - eps) g / (eps N2)).
    let pose = ps[0];
    let far = [[pose.x + 30.0, pose.y - 40.0]];
    let mut base = [0.0];
    model.log_density_items(&store, &c, pose, &far, &mut base);
    let (eps, s) = (0.1f64, 10.0f64);
    let clutter_term = eps.ln() - LN_2PI - 2.0 * f64::ln(s) - 50.0 * 50.0 / (2.0 * s * s);
    assert!(base[0] < clutter_term - 50.0, "box {} vs clutter {clutter_term}", base[0]);
    let mut lg = [0.0];
    let one = ([pose.x], [pose.y], [pose.yaw]);
    model.log_likelihood_with_clutter(
        &store,
        &c,
        PosesRef::new(&one.0, &one.1, &one.2),
        &far,
        Clutter { fraction: eps, scale: s },
        &mut Scratch::new(),
        &mut lg,
    );
    assert!((lg[0] - clutter_term).abs() < 1e-12, "far point: {} vs {clutter_term}", lg[0]);
    // On the tape too, where the point's gradient in x and y is the Gaussian's alone:
    // d/dx = (px - x) / s^2 = 0.3, d/dy = -0.4.
    let tape = Tape::<f64>::new();
    let params = store.bind(&tape);
    let x = tape.param(Tensor::from_vec(vec![pose.x]));
    let y = tape.param(Tensor::from_vec(vec![pose.y]));
    let k = |v: f64| tape.constant(Tensor::from_vec(vec![v]));
    let rv = RowVars { x, y, yaw: k(pose.yaw), length: k(c.length), width: k(c.width) };
    let (l, sg) = (k((eps / (1.0 - eps)).ln()), k(s.ln()));
    let out = model.log_likelihood_rows_with_clutter(&params, &rv, &[c.av], &[&far[..]], l, sg);
    assert!((out.item() - clutter_term).abs() < 1e-9, "tape far point: {} vs {clutter_term}", out.item());
    let grads = tape.backward(out.sum());
    assert!((grads.wrt(x).item() - 0.3).abs() < 1e-9 && (grads.wrt(y).item() + 0.4).abs() < 1e-9);
}

#[test]
fn extreme_clutter_stays_finite() {
    let (model, store) = model(13);
    let c = ctx();
    let s32 = store.cast::<f32>();
    let pose = Pose { x: 0.3, y: -0.2, yaw: 0.4 };
    let pts = [[0.3, -0.2], [2.5, 0.8], [1e4, -1e4], [0.3 + 1e3, -0.2]];
    let (xs, ys, yaws) = ([0.3f32, 1e4, -2e4], [-0.2f32, -1e4, 1e4], [0.4f32, -1e3, 7.0]);
    // eps from ~1e-13 to ~1 - 1e-13, s from 1 cm to 1 km.
    for (lambda, sigma) in [(-30.0, 0.0), (30.0, 0.0), (0.0, -4.6), (-30.0, 6.9), (30.0, -4.6)] {
        let mut out = [0.0f32; 3];
        let clutter = Clutter::from_logits(lambda, sigma);
        model.log_likelihood_with_clutter(
            &s32,
            &c,
            PosesRef::new(&xs, &ys, &yaws),
            &pts,
            clutter,
            &mut Scratch::new(),
            &mut out,
        );
        assert!(out.iter().all(|v| v.is_finite()), "plain f32, lambda {lambda}, sigma {sigma}: {out:?}");
        let tape = Tape::<f32>::new();
        let params = s32.bind(&tape);
        let rv = f32_row_params(&tape, &xs, &ys, &yaws, 4.4, 1.9);
        let l = tape.param(Tensor::from_vec(vec![lambda as f32]));
        let sg = tape.param(Tensor::from_vec(vec![sigma as f32]));
        let items: Vec<&[[f64; 2]]> = vec![&pts[..]; 3];
        let out = model.log_likelihood_rows_with_clutter(&params, &rv, &[c.av; 3], &items, l, sg);
        let inputs = [rv.x, rv.y, rv.yaw, rv.length, rv.width, l, sg];
        assert_finite_with_gradients(
            &format!("tape f32, lambda {lambda}, sigma {sigma}"),
            &tape,
            &params,
            out,
            &inputs,
        );
    }
    // The near-certain clutter (lambda = 30) at the box centre is the Gaussian's peak.
    let mut lg = [0.0];
    let one = ([pose.x], [pose.y], [pose.yaw]);
    let clutter = Clutter::from_logits(30.0, 0.0);
    model.log_likelihood_with_clutter(
        &store,
        &c,
        PosesRef::new(&one.0, &one.1, &one.2),
        &pts[..1],
        clutter,
        &mut Scratch::new(),
        &mut lg,
    );
    assert!((lg[0] + LN_2PI).abs() < 1e-9, "{}", lg[0]);
}

#[test]
fn parallel_rows_with_clutter_do_not_change_results() {
    let (model, store) = model(11);
    // 600 rows x 28 points: above the fused kernel's parallel threshold (16384 pairs).
    let mut rng = StdRng::seed_from_u64(12);
    let ps = poses(600, &mut rng);
    let c = ctx();
    let (ctxs, av) = (vec![c; 600], vec![c.av; 600]);
    let mut pts = Vec::new();
    model.sample_with_clutter(&store, &c, ps[0], 28, Clutter { fraction: 0.3, scale: 2.0 }, &mut rng, &mut pts);
    let items: Vec<&[[f64; 2]]> = vec![&pts[..]; 600];
    let run = |par: Parallelism| {
        let tape = Tape::<f32>::new().with_parallelism(par);
        let s32 = store.cast::<f32>();
        let params = s32.bind(&tape);
        let rv = RowVars::from_poses(&tape, &ps, &ctxs);
        let l = tape.param(Tensor::from_vec(vec![-1.0f32]));
        let sg = tape.param(Tensor::from_vec(vec![0.5f32]));
        let out = model.log_likelihood_rows_with_clutter(&params, &rv, &av, &items, l, sg);
        let grads = tape.backward(out.sum());
        let mut g = params.gradients(&grads);
        g.extend([grads.wrt(l), grads.wrt(sg)]);
        (out.to_tensor(), g)
    };
    let (serial, rayon) = (run(Parallelism::Serial), run(Parallelism::Rayon));
    assert!(serial.1.last().unwrap().item() != 0.0, "the clutter's scale has a gradient");
    assert_eq!(serial, rayon);
}

#[test]
fn sampler_agrees_with_the_density_beyond_a_radius() {
    let (model, store) = model(15);
    let c = ctx();
    let pose = Pose { x: 2.0, y: 1.0, yaw: 0.3 };
    let clutter = Clutter { fraction: 0.3, scale: 3.0 };
    let n = 40_000;
    let mut rng = StdRng::seed_from_u64(16);
    let mut mixed = Vec::new();
    model.sample_with_clutter(&store, &c, pose, n, clutter, &mut rng, &mut mixed);
    assert_eq!(mixed.len(), n);
    // The box component's tail, estimated from an independent base sample.
    let mut base = Vec::new();
    model.sample(&store, &c, pose, n, &mut rng, &mut base);
    let beyond = |pts: &[[f64; 2]], r: f64| {
        pts.iter().filter(|p| (p[0] - pose.x).hypot(p[1] - pose.y) > r).count() as f64 / pts.len() as f64
    };
    for r in [2.5, 6.0] {
        let (got, f_box) = (beyond(&mixed, r), beyond(&base, r));
        // The distance of an isotropic 2-D Gaussian point is Rayleigh: P(d > r) = e^{-r^2 / (2 s^2)}.
        let f_clutter = (-r * r / (2.0 * clutter.scale.powi(2))).exp();
        let want = clutter.fraction * f_clutter + (1.0 - clutter.fraction) * f_box;
        // Standard error of the difference: binomial for the mixed sample plus the base
        // estimate's, scaled by (1 - eps); 4.5 of them (a false alarm ~1e-5 per check).
        let se = (want * (1.0 - want) / n as f64 + (1.0 - clutter.fraction).powi(2) * f_box * (1.0 - f_box) / n as f64)
            .sqrt();
        assert!((got - want).abs() < 4.5 * se, "beyond {r} m: sampled {got:.4}, density {want:.4} (se {se:.4})");
        // The check has power: without clutter the fraction would be far off.
        assert!((f_box - want).abs() > 10.0 * se, "beyond {r} m: box alone {f_box:.4} vs {want:.4}");
    }
}
