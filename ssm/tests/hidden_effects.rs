//! Each hidden effect of `ssm::criticism::hidden` is present in the generated data,
//! with the size asked for, measured against the ground truth in `states.csv` /
//! `actions.csv`; without an effect the same statistic shows nothing. Also: the box
//! generator's noise is as documented, bad configurations are errors, and
//! generation is deterministic.

use std::f64::consts::{FRAC_PI_2, PI};

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use ssm::criticism::hidden::{generate_hidden, BoxGenerator, HiddenConfig, HiddenEffect, HIDDEN_EFFECT_IDS};
use ssm::data::{Dataset, ObservationKind, Pose, State};
use ssm::evaluation::metrics::wrapped_abs_diff;
use ssm::models::observation::{ObsContext, PointGenerator};
use ssm::models::vehicle::{GaussianPolicy, HandCraftedPolicy};

/// Statistical checks allow 4 standard errors: with the fixed seeds below a false
/// failure cannot happen, and with any seed it has probability ~6e-5 per check.
const Z: f64 = 4.0;

const POINTS: ObservationKind = ObservationKind::Points;
const BOXES: ObservationKind = ObservationKind::Boxes;

fn data(kind: ObservationKind, effect: HiddenEffect, seed: u64) -> Dataset {
    generate_hidden(&HiddenConfig::quick(kind, effect, seed)).unwrap()
}

fn effect(id: &str) -> HiddenEffect {
    HiddenEffect::by_id(id).unwrap()
}

/// The true state of object `o` at step `t`.
fn truth(d: &Dataset, o: usize, t: usize) -> State {
    *d.states().unwrap().get(o, t).unwrap()
}

/// The AV's pose when object `o` is observed at step `t`.
fn av(d: &Dataset, o: usize, t: usize) -> Pose {
    d.scenes()[d.object_scene(o)].av[t]
}

/// `p - x` in the frame of the state `x`: (along its heading, to its left).
fn box_frame(x: &State, p: [f64; 2]) -> (f64, f64) {
    let (dx, dy) = (p[0] - x.x, p[1] - x.y);
    let (c, s) = (x.yaw.cos(), x.yaw.sin());
    (c * dx + s * dy, c * dy - s * dx)
}

/// Least-squares slope of `y` on `x` and its standard error.
fn slope(xy: &[(f64, f64)]) -> (f64, f64) {
    let n = xy.len() as f64;
    let (mx, my) = (xy.iter().map(|p| p.0).sum::<f64>() / n, xy.iter().map(|p| p.1).sum::<f64>() / n);
    let sxx: f64 = xy.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = xy.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let b = sxy / sxx;
    let rss: f64 = xy.iter().map(|p| (p.1 - my - b * (p.0 - mx)).powi(2)).sum();
    (b, (rss / (n - 2.0) / sxx).sqrt())
}

/// Where the generator's points of a box at `pose` fall on average, in the box's
/// frame: the midpoint of each visible edge weighted by the edge's probability
/// (positions along an edge are uniform, the noise has mean zero).
fn expected_point_offset(ctx: &ObsContext, pose: Pose) -> (f64, f64) {
    let w = PointGenerator::default().edge_weights(ctx, pose);
    let (hl, hw) = (0.5 * ctx.length, 0.5 * ctx.width);
    let mids = [(hl, 0.0), (0.0, hw), (-hl, 0.0), (0.0, -hw)];
    (0..4).fold((0.0, 0.0), |(u, v), e| (u + w[e] * mids[e].0, v + w[e] * mids[e].1))
}

/// Per observed (object, step) of a point dataset: the true speed and the offset
/// along the true heading of the points' centroid from where the generator puts it
/// on average for the true state (so the geometry of which edges are seen drops out).
fn point_centroid_offsets(d: &Dataset) -> Vec<(f64, f64)> {
    let points = d.points().unwrap();
    let mut out = Vec::new();
    for o in 0..d.objects().len() {
        for t in 0..d.steps() {
            let pts = points.get(o, t);
            if pts.is_empty() {
                continue;
            }
            let x = truth(d, o, t);
            let ctx = ObsContext::of_object(av(d, o, t), &d.objects()[o]);
            let (eu, _) = expected_point_offset(&ctx, Pose { x: x.x, y: x.y, yaw: x.yaw });
            let mean_u = pts.iter().map(|&p| box_frame(&x, p).0).sum::<f64>() / pts.len() as f64;
            out.push((x.v, mean_u - eu));
        }
    }
    out
}

/// Per detection of a box dataset: the true speed and the detection's centre offset
/// along the true heading.
fn box_offsets(d: &Dataset) -> Vec<(f64, f64)> {
    let boxes = d.boxes().unwrap();
    boxes.iter().map(|(o, t, b)| (truth(d, o, t).v, box_frame(&truth(d, o, t), [b.x, b.y]).0)).collect()
}

#[test]
fn latency_shifts_observations_back_along_the_heading_in_proportion_to_speed() {
    // A lag of `delay` puts the observed box `delay * v` behind the true one: the
    // offset along the heading regressed on the speed has slope -delay. The bound is
    // 4 standard errors of the slope plus 0.01 s for the first-order geometry (the
    // lagged box is seen from a slightly different angle).
    let delay = 0.15;
    for kind in [POINTS, BOXES] {
        let lagged = data(kind, HiddenEffect::Latency { delay }, 1);
        let plain = data(kind, HiddenEffect::None, 1);
        let offsets = |d: &Dataset| if kind == POINTS { point_centroid_offsets(d) } else { box_offsets(d) };
        let (b, se) = slope(&offsets(&lagged));
        assert!((b + delay).abs() < Z * se + 0.01, "{kind:?}: slope {b} (se {se}), expected {}", -delay);
        let (b0, se0) = slope(&offsets(&plain));
        assert!(b0.abs() < Z * se0 + 0.01, "{kind:?} without latency: slope {b0} (se {se0})");
    }
}

/// Distance (m) of `p` outside the box of extents `length` x `width` at `x` (0 inside).
fn outside_distance(x: &State, length: f64, width: f64, p: [f64; 2]) -> f64 {
    let (u, v) = box_frame(x, p);
    (u.abs() - 0.5 * length).max(0.0).hypot((v.abs() - 0.5 * width).max(0.0))
}

/// Points farther than this outside the true box count as far (m): 5.5 sds of the
/// generator's noise at 35 m, so the generator itself almost never puts one there.
const FAR: f64 = 1.5;

#[test]
fn clutter_puts_the_asked_fraction_of_points_far_from_the_box() {
    let (fraction, scale) = (0.15, 2.5);
    let cluttered = data(POINTS, HiddenEffect::Clutter { fraction, scale }, 2);
    let plain = data(POINTS, HiddenEffect::None, 2);
    // Probability that a clutter point lands far outside each object's box, by
    // Monte Carlo (isotropic, so the heading does not matter).
    let mut rng = StdRng::seed_from_u64(99);
    const DRAWS: usize = 20_000;
    let p_far: Vec<f64> = cluttered
        .objects()
        .iter()
        .map(|ob| {
            let centre = State::default();
            let far = (0..DRAWS)
                .filter(|_| {
                    let p =
                        [scale * rng.sample::<f64, _>(StandardNormal), scale * rng.sample::<f64, _>(StandardNormal)];
                    outside_distance(&centre, ob.length, ob.width, p) > FAR
                })
                .count();
            far as f64 / DRAWS as f64
        })
        .collect();
    let far_count = |d: &Dataset| {
        let pts = d.points().unwrap();
        let ob = d.objects();
        pts.iter().filter(|&(o, t, p)| outside_distance(&truth(d, o, t), ob[o].length, ob[o].width, p) > FAR).count()
    };
    let pts = cluttered.points().unwrap();
    let expected: f64 = pts.iter().map(|(o, _, _)| fraction * p_far[o]).sum();
    let n = pts.len() as f64;
    let p = expected / n;
    let got = far_count(&cluttered) as f64;
    // Binomial standard error of the count (the Monte Carlo error is far smaller).
    assert!((got - expected).abs() < Z * (n * p * (1.0 - p)).sqrt(), "far points {got}, expected {expected} of {n}");
    let plain_far = far_count(&plain);
    assert!(plain_far as f64 <= 1e-3 * plain.points().unwrap().len() as f64, "far points without clutter: {plain_far}");
}

/// Median over (object, step) cells with at least 3 points of the largest
/// `|offset|` of the points along (`axis = 0`) or across (`axis = 1`) the true
/// heading, over half the stated length or width.
fn median_reach(d: &Dataset, axis: usize) -> f64 {
    let points = d.points().unwrap();
    let mut reach = Vec::new();
    for o in 0..d.objects().len() {
        let half = 0.5 * if axis == 0 { d.objects()[o].length } else { d.objects()[o].width };
        for t in 0..d.steps() {
            let pts = points.get(o, t);
            if pts.len() < 3 {
                continue;
            }
            let x = truth(d, o, t);
            let m = pts
                .iter()
                .map(|&p| {
                    let (u, v) = box_frame(&x, p);
                    if axis == 0 {
                        u.abs()
                    } else {
                        v.abs()
                    }
                })
                .fold(0.0, f64::max);
            reach.push(m / half);
        }
    }
    reach.sort_by(f64::total_cmp);
    reach[reach.len() / 2]
}

#[test]
fn size_bias_makes_points_reach_beyond_the_stated_extents() {
    let (lf, wf) = (1.25, 1.15);
    let biased = data(POINTS, HiddenEffect::SizeBias { length_factor: lf, width_factor: wf }, 3);
    let plain = data(POINTS, HiddenEffect::None, 3);
    // Without bias the points reach the stated extents: ratio ~1, pushed up by the
    // across-edge noise (sd up to ~0.2 m), more for the narrow width than for the
    // length. With it they reach the scaled extents, and the medians' ratio
    // estimates the factor, pulled a little towards 1 because the noise does not
    // scale with the box; 0.06 allows for that.
    for (axis, factor) in [(0, lf), (1, wf)] {
        let (b, p) = (median_reach(&biased, axis), median_reach(&plain, axis));
        assert!(p > 0.95 && p < 1.25, "axis {axis}: unbiased reach {p}");
        assert!((b / p - factor).abs() < 0.06, "axis {axis}: reach {b} vs {p}, factor {factor}");
    }
}

/// Standardised acceleration innovations `(accel - mean) / sd` of the true policy.
fn accel_innovations(d: &Dataset) -> Vec<f64> {
    let (states, actions) = (d.states().unwrap(), d.actions().unwrap());
    let policy = HandCraftedPolicy::truth();
    let mut g = ssm::models::vehicle::ActionGaussians::<f64>::default();
    let mut z = Vec::new();
    for o in 0..d.objects().len() {
        for t in 1..d.steps() {
            let prev = states.get(o, t - 1).unwrap();
            policy.gaussians(&[prev.v], &[prev.kappa], &mut g);
            z.push((actions.get(o, t).unwrap().accel - g.mean_accel[0]) / g.l11[0]);
        }
    }
    z
}

fn excess_kurtosis(z: &[f64]) -> f64 {
    let n = z.len() as f64;
    let m = z.iter().sum::<f64>() / n;
    let m2 = z.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n;
    let m4 = z.iter().map(|x| (x - m).powi(4)).sum::<f64>() / n;
    m4 / (m2 * m2) - 3.0
}

#[test]
fn heavy_tailed_accel_has_heavy_tailed_innovations() {
    // f = 0.1, r = 10: excess kurtosis 22.3 in the population; its sample estimate
    // is very noisy, so require only > 3. Without the effect the sample excess
    // kurtosis of n normals has standard error sqrt(24 / n).
    for kind in [POINTS, BOXES] {
        let heavy = accel_innovations(&data(kind, effect("heavy_tailed_accel"), 4));
        let plain = accel_innovations(&data(kind, HiddenEffect::None, 4));
        let (kh, kp) = (excess_kurtosis(&heavy), excess_kurtosis(&plain));
        assert!(kh > 3.0, "{kind:?}: excess kurtosis {kh}");
        assert!(kp.abs() < Z * (24.0 / plain.len() as f64).sqrt(), "{kind:?} without the effect: {kp}");
        // |z| > 3: probability 0.9 P(|N| > 3) + 0.1 P(|N| > 0.3) = 0.0789 (binomial se).
        let n = heavy.len() as f64;
        let p = 0.9 * 0.0026998 + 0.1 * 0.7641772;
        let tail = heavy.iter().filter(|z| z.abs() > 3.0).count() as f64 / n;
        assert!((tail - p).abs() < Z * (p * (1.0 - p) / n).sqrt(), "{kind:?}: tail fraction {tail}, expected {p}");
    }
}

#[test]
fn student_t_accel_innovations_are_standard_student_t() {
    // At 3 dof and unit scale: P(|t| > 3) = 1 - 2 (atan(sqrt 3) + sqrt(3) / 4) / pi
    // = 0.0577, and P(|t| < 0.765) = 1/2 (the bulk is a standard normal's width).
    let d = data(POINTS, HiddenEffect::StudentTAccel { dof: 3.0 }, 4);
    let z = accel_innovations(&d);
    let n = z.len() as f64;
    for (threshold, p) in [(3.0, 1.0 - 2.0 * (3f64.sqrt().atan() + 3f64.sqrt() / 4.0) / PI), (0.7649, 0.5)] {
        let tail = z.iter().filter(|z| z.abs() > threshold).count() as f64 / n;
        assert!((tail - p).abs() < Z * (p * (1.0 - p) / n).sqrt(), "P(|z| > {threshold}) = {tail}, expected {p}");
    }
}

#[test]
fn student_t_tails_are_as_far_from_gaussian_as_the_mixture_at_each_strength() {
    // Both tail families at strength s carry the same divergence from the
    // Gaussian per innovation, and a stronger effect has fewer degrees of freedom.
    let mut last_dof = f64::INFINITY;
    for s in [0.5, 1.0, 2.0] {
        let mixture = HiddenEffect::at_strength("heavy_tailed_accel", s).unwrap().kl_per_innovation().unwrap();
        let t = HiddenEffect::at_strength("student_t_accel", s).unwrap();
        let HiddenEffect::StudentTAccel { dof } = t else { panic!("{t:?}") };
        let kl = t.kl_per_innovation().unwrap();
        assert!((kl - mixture).abs() < 1e-6 * mixture, "strength {s}: {kl} against the mixture's {mixture}");
        assert!(dof > 2.0 && dof < last_dof, "strength {s}: {dof} dof after {last_dof}");
        last_dof = dof;
    }
    // A Gaussian is at zero, whatever way it is written.
    for gaussian in [
        HiddenEffect::HeavyTailedAccel { fraction: 0.0, ratio: 10.0 },
        HiddenEffect::HeavyTailedAccel { fraction: 0.5, ratio: 1.0 },
    ] {
        assert!(gaussian.kl_per_innovation().unwrap().abs() < 1e-9, "{gaussian:?}");
    }
    // The divergence does not depend on the scale. At 3 dof the unit-variance
    // Student-t density is (2 / pi) (1 + x^2)^-2: its divergence from N(0, 1) by a
    // plain trapezoid rule over [-L, L] (the integrand falls as x^-2, so the rest
    // is about 1 / (pi L)).
    let (l, n) = (2.0e4, 4_000_000);
    let h = 2.0 * l / n as f64;
    let direct: f64 = (0..=n)
        .map(|i| {
            let x = -l + i as f64 * h;
            let p = 2.0 / PI * (1.0 + x * x).powi(-2);
            let w = if i == 0 || i == n { 0.5 } else { 1.0 };
            w * h * p * (p.ln() + 0.5 * (2.0 * PI).ln() + 0.5 * x * x)
        })
        .sum();
    let kl3 = HiddenEffect::StudentTAccel { dof: 3.0 }.kl_per_innovation().unwrap();
    assert!((kl3 - direct).abs() < 1e-3, "{kl3} against a direct {direct}");
}

/// Fraction of detections whose yaw is more than pi/2 from the true yaw, and how many.
fn reversed_fraction(d: &Dataset) -> (f64, usize) {
    let boxes = d.boxes().unwrap();
    let n = boxes.count();
    let flipped = boxes.iter().filter(|&(o, t, b)| wrapped_abs_diff(b.yaw, truth(d, o, t).yaw) > FRAC_PI_2).count();
    (flipped as f64 / n as f64, n)
}

#[test]
fn heading_flip_reverses_the_asked_fraction_of_detections() {
    let f = 0.2;
    let (got, n) = reversed_fraction(&data(BOXES, HiddenEffect::HeadingFlip { fraction: f }, 5));
    assert!((got - f).abs() < Z * (f * (1.0 - f) / n as f64).sqrt(), "flipped fraction {got} of {n}");
    let flipped = data(BOXES, HiddenEffect::HeadingFlip { fraction: f }, 5);
    assert!(flipped.boxes().unwrap().iter().all(|(_, _, b)| (-PI..=PI).contains(&b.yaw)), "yaws wrapped");
    let (none, _) = reversed_fraction(&data(BOXES, HiddenEffect::None, 5));
    assert_eq!(none, 0.0, "no flips without the effect");
}

/// Mean over scene-steps of the products of two objects' residuals (detection
/// minus truth: x, y and heading), over every pair of objects seen at the same
/// step of the same scene, with their standard error: what the objects of one
/// step share.
fn shared_residuals(d: &Dataset) -> [(f64, f64); 3] {
    let boxes = d.boxes().unwrap();
    let mut by_step: std::collections::BTreeMap<(usize, usize), Vec<[f64; 3]>> = Default::default();
    for (o, t, b) in boxes.iter() {
        let x = truth(d, o, t);
        let dyaw = ssm::util::angles::wrap_angle(b.yaw - x.yaw);
        by_step.entry((d.object_scene(o), t)).or_default().push([b.x - x.x, b.y - x.y, dyaw]);
    }
    let mut products: [Vec<f64>; 3] = Default::default();
    for residuals in by_step.values() {
        for (i, a) in residuals.iter().enumerate() {
            for b in &residuals[i + 1..] {
                for k in 0..3 {
                    products[k].push(a[k] * b[k]);
                }
            }
        }
    }
    products.map(|p| {
        let n = p.len() as f64;
        let m = p.iter().sum::<f64>() / n;
        let sd = (p.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        (m, sd / n.sqrt())
    })
}

#[test]
fn ego_pose_noise_moves_every_object_of_a_step_together() {
    // Position errors only: the objects of one step share a shift of variance sd^2
    // per axis (the detector's own noise is independent between objects).
    let sd = 0.3;
    let shifted = data(BOXES, HiddenEffect::EgoPoseNoise { position_sd: sd, yaw_sd: 0.0 }, 7);
    let [x, y, yaw] = shared_residuals(&shifted);
    for (axis, (m, se)) in [("x", x), ("y", y)] {
        assert!((m - sd * sd).abs() < Z * se, "{axis}: shared {m} +- {se}, want {}", sd * sd);
    }
    assert!(yaw.0.abs() < Z * yaw.1, "heading: {yaw:?}");
    // A heading error turns every detection's heading by the same angle.
    let yaw_sd = 0.05;
    let turned = data(BOXES, HiddenEffect::EgoPoseNoise { position_sd: 0.0, yaw_sd }, 8);
    let [_, _, yaw] = shared_residuals(&turned);
    assert!((yaw.0 - yaw_sd * yaw_sd).abs() < Z * yaw.1, "heading: shared {yaw:?}, want {}", yaw_sd * yaw_sd);
    // Without the effect the objects share nothing.
    for (m, se) in shared_residuals(&data(BOXES, HiddenEffect::None, 7)) {
        assert!(m.abs() < Z * se, "control: {m} +- {se}");
    }
    // Point data with it are valid data too.
    let points = data(POINTS, effect("ego_pose_noise"), 9);
    assert!(!points.points().unwrap().is_empty());
}

#[test]
fn box_generator_noise_is_as_documented() {
    // Laplace offsets: E|X| = b and sd(|X|) = b, so mean(|offset| / b) is 1 with
    // standard error 1/sqrt(n). Misses are binomial with p = 0.1.
    let g = BoxGenerator::default();
    let d = data(BOXES, HiddenEffect::None, 6);
    let boxes = d.boxes().unwrap();
    let (mut along, mut across, mut yaw) = (Vec::new(), Vec::new(), Vec::new());
    for (o, t, b) in boxes.iter() {
        let x = truth(&d, o, t);
        let a = av(&d, o, t);
        let r = (x.x - a.x).hypot(x.y - a.y);
        let (lx, ly) = ((x.x - a.x) / r, (x.y - a.y) / r);
        let (dx, dy) = (b.x - x.x, b.y - x.y);
        along.push((lx * dx + ly * dy).abs() / g.along_scale(r));
        across.push((lx * dy - ly * dx).abs() / g.across_scale(r));
        yaw.push(wrapped_abs_diff(b.yaw, x.yaw));
        assert_eq!((b.length, b.width, b.score), (d.objects()[o].length, d.objects()[o].width, 1.0));
    }
    let n = boxes.count() as f64;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!((mean(&along) - 1.0).abs() < Z / n.sqrt(), "along: {}", mean(&along));
    assert!((mean(&across) - 1.0).abs() < Z / n.sqrt(), "across: {}", mean(&across));
    // Half-normal: E|yaw noise| = sd sqrt(2/pi), sd of |noise| = sd sqrt(1 - 2/pi).
    let (m, s) = (g.yaw_sd * (2.0 / PI).sqrt(), g.yaw_sd * (1.0 - 2.0 / PI).sqrt());
    assert!((mean(&yaw) - m).abs() < Z * s / n.sqrt(), "yaw: {}", mean(&yaw));
    let cells = (d.objects().len() * d.steps()) as f64;
    let missed = 1.0 - n / cells;
    let p = g.miss_probability;
    assert!((missed - p).abs() < Z * (p * (1.0 - p) / cells).sqrt(), "missed fraction {missed}");
}

#[test]
fn effects_by_id_have_their_defaults_and_unknown_ids_are_errors() {
    for id in HIDDEN_EFFECT_IDS {
        assert_eq!(effect(id).id(), id);
    }
    assert_eq!(effect("clutter"), HiddenEffect::Clutter { fraction: 0.15, scale: 2.5 });
    assert_eq!(effect("size_bias"), HiddenEffect::SizeBias { length_factor: 1.25, width_factor: 1.15 });
    assert_eq!(effect("heavy_tailed_accel"), HiddenEffect::HeavyTailedAccel { fraction: 0.1, ratio: 10.0 });
    assert_eq!(effect("heading_flip"), HiddenEffect::HeadingFlip { fraction: 0.2 });
    assert_eq!(effect("ego_pose_noise"), HiddenEffect::EgoPoseNoise { position_sd: 0.2, yaw_sd: 0.02 });
    let msg = HiddenEffect::by_id("wobble").unwrap_err().to_string();
    assert!(msg.contains("wobble") && HIDDEN_EFFECT_IDS.iter().all(|id| msg.contains(id)), "{msg}");
    assert_eq!(effect("none").applies_to(), None);
    assert_eq!(effect("clutter").applies_to(), Some(POINTS));
    assert_eq!(effect("heading_flip").applies_to(), Some(BOXES));
    // Serialised with the catalogue ids.
    let json = serde_json::to_string(&effect("latency")).unwrap();
    assert_eq!(json, r#"{"latency":{"delay":0.15}}"#);
    assert_eq!(serde_json::from_str::<HiddenEffect>(&json).unwrap(), effect("latency"));
}

#[test]
fn wrong_kinds_and_bad_sizes_are_errors() {
    let quick = |kind, e| HiddenConfig::quick(kind, e, 0);
    for (kind, id) in [(BOXES, "clutter"), (BOXES, "size_bias"), (POINTS, "heading_flip")] {
        let err = generate_hidden(&quick(kind, effect(id))).unwrap_err().to_string();
        assert!(err.contains(id), "{err}");
    }
    let ok = quick(POINTS, HiddenEffect::None);
    let bad = [
        HiddenConfig { scenes: 0, ..ok },
        HiddenConfig { objects_per_scene: 0, ..ok },
        HiddenConfig { steps: 0, ..ok },
        HiddenConfig { effect: HiddenEffect::Clutter { fraction: 1.5, scale: 2.5 }, ..ok },
        HiddenConfig { effect: HiddenEffect::Clutter { fraction: 0.1, scale: 0.0 }, ..ok },
        HiddenConfig { effect: HiddenEffect::Latency { delay: f64::NAN }, ..ok },
        HiddenConfig { effect: HiddenEffect::Latency { delay: -0.1 }, ..ok },
        HiddenConfig { effect: HiddenEffect::SizeBias { length_factor: -1.0, width_factor: 1.0 }, ..ok },
        HiddenConfig { effect: HiddenEffect::HeavyTailedAccel { fraction: 0.1, ratio: f64::INFINITY }, ..ok },
    ];
    for c in bad {
        assert!(generate_hidden(&c).is_err(), "accepted {c:?}");
    }
    // A single step (no transitions) is fine.
    let one = generate_hidden(&HiddenConfig { steps: 1, ..ok }).unwrap();
    assert_eq!(one.steps(), 1);
}

#[test]
fn generation_is_deterministic() {
    for (kind, id) in [(POINTS, "clutter"), (BOXES, "heading_flip"), (POINTS, "heavy_tailed_accel")] {
        let a = data(kind, effect(id), 8);
        assert_eq!(a, data(kind, effect(id), 8), "{id}: same seed");
        assert_ne!(a, data(kind, effect(id), 9), "{id}: another seed");
        assert_eq!(a.kind(), kind);
        assert_eq!((a.scenes().len(), a.objects().len(), a.steps()), (8, 48, 16));
    }
}

/// The hidden `persistent_flip` reverses detections in runs: at two fractions
/// and persistences, the reversed share is the chain's stationary fraction and
/// the chance that a reversed detection follows a reversed one is
/// `1 - (1 - p)(1 - lambda)` (measured by `data::heading_reversals`, which
/// reads reversals against the labels), far above the rate.
#[test]
fn hidden_persistent_flips_come_in_runs_of_the_chains_persistence() {
    use ssm::data::heading_reversals;
    for (fraction, persistence, seed) in [(0.2, 0.8, 31), (0.1, 0.5, 32)] {
        let effect = HiddenEffect::PersistentFlip { fraction, persistence };
        let config = HiddenConfig { scenes: 24, ..HiddenConfig::quick(ObservationKind::Boxes, effect, seed) };
        let r = heading_reversals(&generate_hidden(&config).unwrap()).expect("labelled detections");
        let rate = r.reversed as f64 / r.detections as f64;
        let after = r.persistence.expect("reversals follow reversals");
        let want = 1.0 - (1.0 - fraction) * (1.0 - persistence);
        assert!((rate - fraction).abs() < 0.04, "({fraction}, {persistence}): rate {rate}");
        assert!((after - want).abs() < 0.08, "({fraction}, {persistence}): P(rev | rev) {after} against {want}");
        assert!(r.dispersion.expect("objects") > 1.5, "overdispersed per object");
    }
    assert_eq!(HiddenEffect::by_id("persistent_flip").unwrap().id(), "persistent_flip");
    assert!(HiddenEffect::PersistentFlip { fraction: 0.2, persistence: 1.0 }.validate().is_err());
}
