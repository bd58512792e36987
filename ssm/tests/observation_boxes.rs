//! Box-detection observation model (SPEC §3): plain kernels against an independent
//! f64 reference (the wrapped Laplace as an explicit sum over windings), f32 against
//! f64, the tape against the plain path, gradients against finite differences,
//! invariance to whole turns, finiteness at extreme inputs, normalisation, and the
//! sampler against the density.

use std::f64::consts::{PI, TAU};

use crate::common::{
    assert_finite_at, assert_plain_matches_reference, assert_tape_rows_match_plain, check_row_gradients, poses, soa,
    to32, Rows,
};
use autodiff::nn::ParamStore;
use autodiff::Tape;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::data::{BoxDetection, Pose};
use ssm::models::observation::{BoxObservationModel, ObsContext, ObservationModel, PosesRef, RowVars, Scratch};
use ssm::util::angles::wrap_angle;

fn model(seed: u64) -> (BoxObservationModel, ParamStore<f64>) {
    let mut store = ParamStore::new();
    let m = BoxObservationModel::init_params(&mut store, "boxes", &mut StdRng::seed_from_u64(seed));
    (m, store)
}

fn ctx() -> ObsContext {
    ObsContext::new(Pose { x: -15.0, y: 8.0, yaw: 0.3 }, 4.4, 1.9)
}

/// Unit line of sight from the AV to the pose (exact normalisation).
fn los(c: &ObsContext, pose: Pose) -> (f64, f64) {
    let (dx, dy) = (pose.x - c.av.x, pose.y - c.av.y);
    let r = dx.hypot(dy);
    (dx / r, dy / r)
}

/// The detection with offsets `(along, across, dyaw)` from `pose`.
fn detection(c: &ObsContext, pose: Pose, along: f64, across: f64, dyaw: f64) -> BoxDetection {
    let (lx, ly) = los(c, pose);
    BoxDetection {
        x: pose.x + along * lx - across * ly,
        y: pose.y + along * ly + across * lx,
        yaw: pose.yaw + dyaw,
        length: 4.0,
        width: 2.0,
        score: 0.5,
    }
}

/// `(along, across, wrapped yaw offset)` of a detection.
fn offsets(c: &ObsContext, pose: Pose, d: &BoxDetection) -> (f64, f64, f64) {
    let (lx, ly) = los(c, pose);
    let (ddx, ddy) = (d.x - pose.x, d.y - pose.y);
    (ddx * lx + ddy * ly, ddy * lx - ddx * ly, wrap_angle(d.yaw - pose.yaw))
}

fn laplace(x: f64, mu: f64, b: f64) -> f64 {
    -(x - mu).abs() / b - (2.0 * b).ln()
}

/// Independent reference: the network's distribution, the wrapped Laplace as the
/// sum of Laplace densities over 200 windings.
fn reference(
    model: &BoxObservationModel,
    store: &ParamStore<f64>,
    c: &ObsContext,
    pose: Pose,
    d: &BoxDetection,
) -> f64 {
    let p = model.distribution(store, c, pose);
    let (a, x, y) = offsets(c, pose, d);
    let wrapped: f64 = (-100..=100).map(|k| laplace(y + TAU * k as f64, p.mu_yaw, p.b_yaw).exp()).sum();
    laplace(a, p.mu_along, p.b_along) + laplace(x, p.mu_across, p.b_across) + wrapped.ln()
}

#[test]
fn plain_kernel_matches_reference_in_f64_and_f32() {
    let (model, store) = model(1);
    let c = ctx();
    let mut rng = StdRng::seed_from_u64(2);
    let ps = poses(29, &mut rng);
    let mut dets = Vec::new();
    model.sample(&store, &c, ps[0], 3, &mut rng, &mut dets);
    dets.push(detection(&c, ps[0], 1.5, -0.7, 3.0)); // a near-flipped heading
    let (xs, ys, yaws) = soa(&ps);
    let mut out = vec![0.0; ps.len()];
    model.log_likelihood(&store, &c, PosesRef::new(&xs, &ys, &yaws), &dets, &mut Scratch::new(), &mut out);
    assert_plain_matches_reference(&model, &store, &c, &ps, &dets, &out, 1e-9, |p, d| {
        reference(&model, &store, &c, p, d)
    });
    // f32: position rounding (~2e-6 m) over scales >= 0.02 m and heading rounding
    // (~5e-7 rad) over yaw scales >= 0.005 rad give <= 2e-4 per detection.
    let s32 = store.cast::<f32>();
    let mut out32 = vec![0.0f32; ps.len()];
    model.log_likelihood(
        &s32,
        &c,
        PosesRef::new(&to32(&xs), &to32(&ys), &to32(&yaws)),
        &dets,
        &mut Scratch::new(),
        &mut out32,
    );
    for i in 0..ps.len() {
        assert!((out32[i] as f64 - out[i]).abs() < 2e-4 * dets.len() as f64 + 1e-6 * out[i].abs());
    }
}

#[test]
fn whole_turns_do_not_change_the_density() {
    let (model, store) = model(3);
    let c = ctx();
    let pose = Pose { x: 0.3, y: -0.2, yaw: 0.4 };
    let d = detection(&c, pose, 0.3, 0.1, 0.05);
    let base = reference(&model, &store, &c, pose, &d);
    for k in [-3.0, -1.0, 1.0, 5.0] {
        let mut per = [0.0];
        model.log_density_items(&store, &c, pose, &[BoxDetection { yaw: d.yaw + k * TAU, ..d }], &mut per);
        assert!((per[0] - base).abs() < 1e-9, "detection yaw + {k} turns");
        // The state's heading enters the features too (through sin and cos only).
        let turned = Pose { yaw: pose.yaw + k * TAU, ..pose };
        model.log_density_items(&store, &c, turned, &[d], &mut per);
        assert!((per[0] - base).abs() < 1e-9, "state yaw + {k} turns");
    }
}

/// Rows with detections clear of the density's kinks by `margin` (for finite
/// differences): the Laplace modes and a zero wrapped yaw residual.
fn rows(model: &BoxObservationModel, store: &ParamStore<f64>, r: usize, seed: u64, margin: f64) -> Rows<BoxDetection> {
    let mut rng = StdRng::seed_from_u64(seed);
    let ps = poses(r, &mut rng);
    let ctxs: Vec<ObsContext> = (0..r)
        .map(|i| {
            ObsContext::new(
                Pose { x: -15.0 + i as f64, y: 8.0 - i as f64, yaw: 0.3 },
                rng.random_range(3.5..5.0),
                rng.random_range(1.6..2.1),
            )
        })
        .collect();
    let dets = (0..r)
        .map(|i| loop {
            let mut d = Vec::new();
            model.sample(store, &ctxs[i], ps[i], 1, &mut rng, &mut d);
            let p = model.distribution(store, &ctxs[i], ps[i]);
            let (a, x, y) = offsets(&ctxs[i], ps[i], &d[0]);
            let resid = wrap_angle(y - p.mu_yaw);
            if (a - p.mu_along).abs() > margin
                && (x - p.mu_across).abs() > margin
                && resid.abs() > margin
                && resid.abs() < PI - margin
            {
                break d;
            }
        })
        .collect();
    let av = ctxs.iter().map(|c| c.av).collect();
    Rows { poses: ps, ctxs, av, items: dets }
}

#[test]
fn tape_rows_match_plain_path() {
    let (model, store) = model(4);
    let mut b = rows(&model, &store, 5, 5, 0.0);
    b.items[1].clear(); // a step without a detection contributes 0
    let extra = b.items[3][0];
    b.items[3].push(BoxDetection { x: extra.x + 0.2, ..extra }); // two items add
    let out = assert_tape_rows_match_plain(&model, &store, &b, 2e-4);
    assert_eq!(out[1], 0.0);
    // No detection at all: zeros, and a zero gradient.
    let tape = Tape::<f64>::new();
    let params = store.bind(&tape);
    let rv = RowVars::from_poses(&tape, &b.poses[..2], &b.ctxs[..2]);
    let z = model.log_likelihood_rows(&params, &rv, &b.av[..2], &[&[], &[]]);
    assert_eq!(z.to_tensor().data(), &[0.0, 0.0]);
    assert!(params.gradients(&tape.backward(z.sum())).iter().all(|g| g.data().iter().all(|&x| x == 0.0)));
}

#[test]
fn tape_gradients_match_finite_differences() {
    let (model, store) = model(6);
    let b = rows(&model, &store, 4, 7, 0.02);
    check_row_gradients(&model, &store, &b, &[1.0, -0.6, 0.3, 0.8]);
}

#[test]
fn extreme_inputs_stay_finite() {
    let (model, store) = model(8);
    let c = ctx();
    let pose = Pose { x: 0.3, y: -0.2, yaw: 0.4 };
    let dets = [
        detection(&c, pose, 1e4, 0.0, 0.0),
        detection(&c, pose, 0.0, -1e4, 1e4),
        detection(&c, pose, 0.0, 0.0, PI),
        BoxDetection { x: c.av.x, y: c.av.y, ..detection(&c, pose, 0.0, 0.0, -1e3) },
    ];
    let mut per = [0.0; 4];
    model.log_density_items(&store, &c, pose, &dets, &mut per);
    assert!(per.iter().all(|v| v.is_finite()), "{per:?}");
    // The state at the AV itself, far away, or with a heading of many turns.
    let xs = [c.av.x, 1e4, 0.3];
    let ys = [c.av.y, -1e4, -0.2];
    let yaws = [0.0, 3.0, 1e4];
    assert_finite_at(&model, &store, &c, (&xs, &ys, &yaws), &dets);
}

#[test]
fn density_is_normalised_and_the_sampler_agrees_with_it() {
    let (model, store) = model(9);
    let c = ctx();
    let pose = Pose { x: 2.0, y: 1.0, yaw: -2.8 };
    let p = model.distribution(&store, &c, pose);
    let lg = |a: f64, x: f64, y: f64| {
        let mut v = [0.0];
        model.log_density_items(&store, &c, pose, &[detection(&c, pose, a, x, y)], &mut v);
        v[0]
    };
    // The density factorises over (along, across, yaw offset)...
    let (a0, x0, y0) = (p.mu_along + 0.1, p.mu_across - 0.05, p.mu_yaw + 0.02);
    let mut rng = StdRng::seed_from_u64(10);
    for _ in 0..20 {
        let (a, x, y) = (rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0), rng.random_range(-PI..PI));
        let split = lg(a, x0, y0) + lg(a0, x, y0) + lg(a0, x0, y) - 2.0 * lg(a0, x0, y0);
        assert!((lg(a, x, y) - split).abs() < 1e-9);
    }
    // ... so its integral is a product of three 1-D integrals (trapezoid rule with
    // h = b / 500: the Laplace kinks at the modes cost ~ h^2 / (8 b^2) ~ 1e-6).
    let n = 40_000;
    let integrate = |lo: f64, hi: f64, det: &dyn Fn(f64) -> BoxDetection| {
        let h = (hi - lo) / n as f64;
        let dets: Vec<BoxDetection> = (0..=n).map(|k| det(lo + k as f64 * h)).collect();
        let mut l = vec![0.0; dets.len()];
        model.log_density_items(&store, &c, pose, &dets, &mut l);
        l.iter().enumerate().map(|(k, v)| if k == 0 || k == n { 0.5 } else { 1.0 } * v.exp()).sum::<f64>() * h
    };
    let l0 = lg(a0, x0, y0);
    let ia =
        integrate(p.mu_along - 40.0 * p.b_along, p.mu_along + 40.0 * p.b_along, &|a| detection(&c, pose, a, x0, y0));
    let ix = integrate(p.mu_across - 40.0 * p.b_across, p.mu_across + 40.0 * p.b_across, &|x| {
        detection(&c, pose, a0, x, y0)
    });
    let iy = integrate(-PI, PI, &|y| detection(&c, pose, a0, x0, y));
    let total = ia * ix * iy / l0.exp().powi(2);
    assert!((total - 1.0).abs() < 1e-5, "integral of g: {total}");
    // Sampler against density: for any density q, E_{y ~ g}[q(y) / g(y)] = 1. Each q
    // is a product of normals in the same coordinates (lighter tails than g, so
    // q / g is bounded and the mean has a finite, estimated standard error).
    let n = 100_000;
    let mut dets = Vec::new();
    model.sample(&store, &c, pose, n, &mut rng, &mut dets);
    let mut lgs = vec![0.0; n];
    model.log_density_items(&store, &c, pose, &dets, &mut lgs);
    let normal = |x: f64, m: f64, s: f64| -0.5 * ((x - m) / s).powi(2) - s.ln() - 0.5 * TAU.ln();
    for (shift, widen) in [(0.0, 1.0), (1.0, 1.5), (-0.5, 0.7), (0.3, 2.0)] {
        let ratios: Vec<f64> = dets
            .iter()
            .zip(&lgs)
            .map(|(d, &l)| {
                let (a, x, y) = offsets(&c, pose, d);
                let y = wrap_angle(y - p.mu_yaw); // the yaw normal is centred on the mode, well inside (-pi, pi]
                let q = normal(a, p.mu_along + shift * p.b_along, widen * p.b_along)
                    + normal(x, p.mu_across - shift * p.b_across, widen * p.b_across)
                    + normal(y, shift * p.b_yaw, widen * p.b_yaw);
                (q - l).exp()
            })
            .collect();
        let mean = ratios.iter().sum::<f64>() / n as f64;
        let sd = (ratios.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / n as f64).sqrt();
        let se = sd / (n as f64).sqrt();
        assert!((mean - 1.0).abs() < 5.0 * se, "q (shift {shift}, widen {widen}): E[q/g] = {mean} +- {se}");
    }
    // And the sampled yaw offsets are wrapped into (-pi, pi].
    assert!(dets.iter().all(|d| d.yaw > -PI && d.yaw <= PI));
}

/// A diverged particle whose heading is far beyond the range where f32 can wrap an
/// angle gets no more density than the worst wrapped offset (pi) allows: the
/// wrapped-Laplace term never rewards it (it once grew with the unwrapped offset).
#[test]
fn huge_headings_get_a_bounded_density() {
    let (m, store) = model(4);
    let c = ctx();
    let pose = Pose { x: 6.0, y: -3.0, yaw: 0.2 };
    let det = detection(&c, pose, 0.1, -0.05, 0.0);
    let store32 = store.cast::<f32>();
    let yaws: Vec<f32> = (0..=64).map(|k| (-PI + TAU * k as f64 / 64.0) as f32).chain([3e8, -7e9, 1e12]).collect();
    let xs = vec![pose.x as f32; yaws.len()];
    let ys = vec![pose.y as f32; yaws.len()];
    let mut out = vec![0.0f32; yaws.len()];
    m.log_likelihood(&store32, &c, PosesRef::new(&xs, &ys, &yaws), &[det], &mut Scratch::new(), &mut out);
    let best = out[..65].iter().copied().fold(f32::MIN, f32::max);
    for (&yaw, &l) in yaws[65..].iter().zip(&out[65..]) {
        assert!(l.is_finite() && l <= best + 1e-3, "yaw {yaw}: {l} above the best wrapped value {best}");
    }
}

/// The centred model (detection offsets fixed at zero, a 4-output network): its
/// distribution has zero mean offsets, the plain kernel matches the reference, the
/// tape matches the plain path with gradients matching finite differences, and a
/// parameter file tells the two layouts apart.
#[test]
fn centred_model_has_zero_offsets_matches_its_reference_and_is_read_back_as_centred() {
    use ssm::data::ObservationKind;
    use ssm::models::observation::boxes::DetectionOffsets;
    use ssm::models::observation::OBS_PREFIX;
    use ssm::models::params::{AnyObservation, AnyPolicy, Models};
    use ssm::models::vehicle::HandCraftedPolicy;

    for seed in [11, 12] {
        let mut store = ParamStore::new();
        let model = BoxObservationModel::init_with_offsets(
            &mut store,
            "boxes",
            DetectionOffsets::Zero,
            &mut StdRng::seed_from_u64(seed),
        );
        assert_eq!(model.offsets(), DetectionOffsets::Zero);
        assert_eq!(model.num_params(), 7 * 16 + 16 + 16 * 16 + 16 + 16 * 4 + 4);
        let c = ctx();
        let mut rng = StdRng::seed_from_u64(seed + 100);
        let ps = poses(17, &mut rng);
        for &p in &ps {
            let d = model.distribution(&store, &c, p);
            assert_eq!((d.mu_along, d.mu_across), (0.0, 0.0));
            assert!(d.b_along > 0.0 && d.b_across > 0.0 && d.b_yaw > 0.0);
        }
        let mut dets = Vec::new();
        model.sample(&store, &c, ps[0], 3, &mut rng, &mut dets);
        let (xs, ys, yaws) = soa(&ps);
        let mut out = vec![0.0; ps.len()];
        model.log_likelihood(&store, &c, PosesRef::new(&xs, &ys, &yaws), &dets, &mut Scratch::new(), &mut out);
        assert_plain_matches_reference(&model, &store, &c, &ps, &dets, &out, 1e-9, |p, d| {
            reference(&model, &store, &c, p, d)
        });
        let b = rows(&model, &store, 4, seed + 200, 0.02);
        assert_tape_rows_match_plain(&model, &store, &b, 2e-4);
        check_row_gradients(&model, &store, &b, &[0.7, -1.1, 0.4, 0.9]);
    }

    // A parameter file: centred models are read back centred, learned ones learned.
    for offsets in [DetectionOffsets::Zero, DetectionOffsets::Learned] {
        let models = Models::initial_with_offsets(
            ObservationKind::Boxes,
            AnyPolicy::HandCrafted(HandCraftedPolicy::truth()),
            3,
            offsets,
        );
        let store = models.to_store();
        assert_eq!(BoxObservationModel::offsets_in_store(&store, OBS_PREFIX), offsets);
        let back = Models::from_store(&store, ObservationKind::Boxes).unwrap();
        match &back.observation {
            AnyObservation::Boxes(m) => assert_eq!(m.offsets(), offsets),
            other => panic!("read back as {:?}", other.kind()),
        }
        assert_eq!(
            back.observation_params.get(autodiff::nn::ParamId(5)),
            models.observation_params.get(autodiff::nn::ParamId(5))
        );
    }
}

/// The density's factors (`DetectionTerms`, which split AOTLL by what a network
/// gets wrong) sum to the independent reference and to the filter's kernel, and
/// their residuals are the detection's offsets from the distribution's means.
#[test]
fn density_terms_sum_to_the_density_and_give_the_offsets() {
    for seed in [3, 4] {
        let (model, store) = model(seed);
        let c = ctx();
        let mut rng = StdRng::seed_from_u64(seed);
        for pose in poses(5, &mut rng) {
            let mut dets = Vec::new();
            model.sample(&store, &c, pose, 3, &mut rng, &mut dets);
            dets.push(detection(&c, pose, 0.8, -0.4, PI - 0.05)); // a reversed heading
            let mut kernel = vec![0.0; dets.len()];
            model.log_density_items(&store, &c, pose, &dets, &mut kernel);
            let dist = model.distribution(&store, &c, pose);
            for (d, k) in dets.iter().zip(&kernel) {
                let terms = dist.log_density_terms(&c.av, pose, d);
                let reference = reference(&model, &store, &c, pose, d);
                assert!((terms.total() - reference).abs() < 1e-9, "{} vs {reference}", terms.total());
                assert!((terms.total() - k).abs() < 1e-9, "{} vs kernel {k}", terms.total());
                let (a, x, y) = offsets(&c, pose, d);
                let (ra, rc, ry) = terms.residuals;
                assert!((ra - (a - dist.mu_along)).abs() < 1e-9 && (rc - (x - dist.mu_across)).abs() < 1e-9);
                assert!((ry - wrap_angle(y - dist.mu_yaw)).abs() < 1e-9, "{ry} vs {y}");
                assert!((terms.along - laplace(a, dist.mu_along, dist.b_along)).abs() < 1e-9);
            }
        }
    }
}

/// A reversed heading stays in `(-pi, pi]`, is pi from the heading, and turned
/// around again is the heading itself; at the wrap's edges too.
#[test]
fn reversed_heading_turns_around_within_the_wrapped_range() {
    use ssm::util::angles::reversed_heading;
    for &yaw in &[0.0, 0.3, -0.3, 3.0, -3.0, std::f64::consts::PI, -std::f64::consts::PI + 1e-12, 1e-15] {
        let r = reversed_heading(yaw);
        assert!(r > -std::f64::consts::PI && r <= std::f64::consts::PI, "{yaw} -> {r}");
        assert!((wrap_angle(r - yaw).abs() - std::f64::consts::PI).abs() < 1e-12, "{yaw} -> {r}");
        assert!(wrap_angle(reversed_heading(r) - wrap_angle(yaw)).abs() < 1e-12, "{yaw} -> {r}");
    }
}
