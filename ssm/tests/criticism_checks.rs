//! Discrepancy statistics of posterior predictive checks (SPEC §7): each statistic
//! on hand-built samples whose observations give it a known value, NaN (not a
//! panic) without data, and the calibration — z, p, Holm adjustment, NaN draws.

use std::f64::consts::{FRAC_PI_2, PI};

use rand::rngs::SmallRng;
use rand::SeedableRng;

use ssm::criticism::checks::{
    calibrate, checks_for, format_z, holm, holm_within, statistics, CheckDef, Direction, Suggestion,
};
use ssm::criticism::ObjectSample;
use ssm::data::{Action, BoxDetection, Dataset, Meta, Object, ObservationKind, Pose, Prior, State};
use ssm::models::extended::{lagged_pose, ObjectObservations};
use ssm::models::flip_chain::FlipChain;
use ssm::models::observation::edges::from_box_frame;
use ssm::stats::normal_cdf;

const LENGTH: f64 = 4.0;
const WIDTH: f64 = 2.0;
const DT: f64 = 0.5;
const STEPS: usize = 6;

/// One scene, the AV at rest at the origin, `objects` objects of 4 m x 2 m.
fn dataset(kind: ObservationKind, objects: usize) -> Dataset {
    let mut b = Dataset::builder(Meta::new(DT, STEPS), kind);
    b.scene(0, &[Pose::default(); STEPS]);
    for id in 0..objects {
        let mean = State { x: 10.0, ..State::default() };
        let sd = State { x: 1.0, y: 1.0, yaw: 0.1, v: 1.0, kappa: 0.01 };
        b.object(Object { scene: 0, id: id as i64, length: LENGTH, width: WIDTH, prior: Prior { mean, sd } });
    }
    b.build().expect("valid dataset")
}

/// Heading east at `(10 + t, 0)`, speed `1 + t` (varies, so slopes are defined).
fn states() -> Vec<State> {
    (0..STEPS).map(|t| State { x: 10.0 + t as f64, y: 0.0, yaw: 0.0, v: 1.0 + t as f64, kappa: 0.0 }).collect()
}

fn pose(s: &State) -> Pose {
    Pose { x: s.x, y: s.y, yaw: s.yaw }
}

/// Box-frame points `uv` of each state's box (or of `frame(state)`) as world points.
fn points_at(states: &[State], frame: impl Fn(&State) -> Pose, uv: &[(f64, f64)]) -> ObjectObservations {
    ObjectObservations::Points(
        states.iter().map(|s| uv.iter().map(|&(u, v)| from_box_frame(frame(s), u, v)).collect()).collect(),
    )
}

fn sample(object: usize, states: Vec<State>, actions: Vec<Action>, observations: ObjectObservations) -> ObjectSample {
    ObjectSample { object, states, actions, observations, accel_innovations: Vec::new() }
}

/// The value of check `name` in `statistics(data, samples)`.
fn stat(data: &Dataset, samples: &[ObjectSample], name: &str) -> f64 {
    let defs = checks_for(data.kind());
    let values = statistics(data, samples);
    assert_eq!(values.len(), defs.len());
    values[defs.iter().position(|d| d.name == name).unwrap_or_else(|| panic!("no check {name}"))]
}

const CORNERS: [(f64, f64); 4] = [(2.0, 1.0), (2.0, -1.0), (-2.0, 1.0), (-2.0, -1.0)];

#[test]
fn checks_per_kind_are_fixed_and_name_their_extensions() {
    let names = |k| checks_for(k).iter().map(|d| d.name).collect::<Vec<_>>();
    assert_eq!(
        names(ObservationKind::Points),
        [
            "along_offset_vs_speed",
            "initial_lag",
            "far_point_fraction",
            "length_extent_ratio",
            "width_extent_ratio",
            "accel_kurtosis",
            "accel_peakedness",
            "pinch_kurtosis",
            "edge_residual_sd",
            "across_offset_vs_speed",
            "points_near_side_fraction",
            "speed_change_sd"
        ]
    );
    assert_eq!(
        names(ObservationKind::Boxes),
        [
            "along_offset_vs_speed",
            "initial_lag",
            "yaw_reversal_fraction",
            "yaw_reversal_persistence",
            "accel_kurtosis",
            "accel_peakedness",
            "pinch_kurtosis",
            "los_along_residual_sd",
            "los_across_residual_sd",
            "yaw_residual_sd"
        ]
    );
    let suggests = |k| checks_for(k).iter().filter_map(|d| d.suggests.map(|s| s.extension)).collect::<Vec<_>>();
    assert_eq!(
        suggests(ObservationKind::Points),
        ["latency", "latency", "clutter", "size_bias", "size_bias", "heavy_tailed_accel", "heavy_tailed_accel"]
    );
    assert_eq!(
        suggests(ObservationKind::Boxes),
        ["latency", "latency", "heading_flip", "persistent_flip", "heavy_tailed_accel", "heavy_tailed_accel"]
    );
    for kind in [ObservationKind::Points, ObservationKind::Boxes] {
        for d in checks_for(kind) {
            assert!(d.kinds.contains(&kind), "{} listed for {kind:?}", d.name);
            assert!(d.description.ends_with('.') && d.description.len() > 30, "{}", d.name);
        }
    }
}

#[test]
fn latency_makes_the_along_offset_slope_minus_the_delay() {
    let data = dataset(ObservationKind::Points, 2);
    let delay = 0.3;
    // The corners of the lagged box: mean u = -delay v exactly (kappa = 0).
    let lagged = |delay: f64| {
        let s = states();
        sample(0, s.clone(), vec![], points_at(&s, |x| lagged_pose(x, delay), &CORNERS))
    };
    let along = stat(&data, &[lagged(delay)], "along_offset_vs_speed");
    assert!((along - -delay).abs() < 1e-12, "slope {along}");
    assert!(stat(&data, &[lagged(delay)], "across_offset_vs_speed").abs() < 1e-12);
    assert!(stat(&data, &[lagged(0.0)], "along_offset_vs_speed").abs() < 1e-12);
    // The same points seen from a path heading north (90 degrees left of the lag):
    // the lag now lies to the left of the heading, so across takes the slope.
    let mut turned = lagged(delay);
    turned.states.iter_mut().for_each(|s| s.yaw = FRAC_PI_2);
    let across = stat(&data, std::slice::from_ref(&turned), "across_offset_vs_speed");
    assert!((across - delay).abs() < 1e-12, "slope {across}");
    assert!(stat(&data, &[turned], "along_offset_vs_speed").abs() < 1e-12);
    // Pooled with another object heading elsewhere, every step is on the same line.
    let s2: Vec<State> = states().into_iter().map(|s| State { y: 5.0, yaw: 1.0, v: 2.0 * s.v, ..s }).collect();
    let other = sample(1, s2.clone(), vec![], points_at(&s2, |x| lagged_pose(x, delay), &CORNERS));
    let pooled = stat(&data, &[lagged(delay), other], "along_offset_vs_speed");
    assert!((pooled - -delay).abs() < 1e-12, "slope {pooled}");
}

#[test]
fn extents_span_the_points_relative_to_the_given_size() {
    let data = dataset(ObservationKind::Points, 1);
    let scaled: Vec<(f64, f64)> = CORNERS.iter().map(|&(u, v)| (1.2 * u, 0.9 * v)).collect();
    let s = states();
    let samples = [sample(0, s.clone(), vec![], points_at(&s, pose, &scaled))];
    assert!((stat(&data, &samples, "length_extent_ratio") - 1.2).abs() < 1e-12);
    assert!((stat(&data, &samples, "width_extent_ratio") - 0.9).abs() < 1e-12);
    // Steps with fewer than 4 points do not count; without any, NaN.
    let three = [sample(0, s.clone(), vec![], points_at(&s, pose, &scaled[..3]))];
    assert!(stat(&data, &three, "length_extent_ratio").is_nan());
}

#[test]
fn far_points_edge_residuals_and_the_near_side() {
    let data = dataset(ObservationKind::Points, 1);
    // Per step 10 points: 6 on the rear edge (facing the AV at the origin), 1 on
    // the front edge and 3 at 3 m beyond the front edge (outside, 3 m from it).
    let mut uv = vec![(-2.0, 0.5); 6];
    uv.push((2.0, 0.0));
    uv.extend([(5.0, 0.0); 3]);
    let s = states();
    let samples = [sample(0, s.clone(), vec![], points_at(&s, pose, &uv))];
    assert!((stat(&data, &samples, "far_point_fraction") - 0.3).abs() < 1e-12);
    assert!((stat(&data, &samples, "points_near_side_fraction") - 0.6).abs() < 1e-12);
    // Signed distances: 7 x 0 and 3 x 3 per step (mean 0.9), sample sd over 60 points.
    let n = 10.0 * STEPS as f64;
    let sum_sq = STEPS as f64 * (7.0 * 0.81 + 3.0 * 2.1 * 2.1);
    let sd = (sum_sq / (n - 1.0)).sqrt();
    assert!((stat(&data, &samples, "edge_residual_sd") - sd).abs() < 1e-9);
    // Inside the box the distance is negative: one point 0.5 m inside the left
    // edge and one 1 m inside the front edge (sd of -0.5 and -1 is sqrt(1/8)).
    let one = [sample(0, s[..1].to_vec(), vec![], points_at(&s[..1], pose, &[(0.0, 0.5), (1.0, 0.0)]))];
    assert!((stat(&data, &one, "edge_residual_sd") - 0.125f64.sqrt()).abs() < 1e-12);
    // A point 2 m past a corner diagonally is 2 sqrt(2) m out: far (2 m past an
    // edge alone would not be).
    let corner = [sample(0, s[..1].to_vec(), vec![], points_at(&s[..1], pose, &[(4.0, 3.0), (2.0, 1.5)]))];
    assert!((stat(&data, &corner, "far_point_fraction") - 0.5).abs() < 1e-12);
}

#[test]
fn accelerations_give_kurtosis_and_speed_change_sd() {
    let data = dataset(ObservationKind::Points, 2);
    let actions = |accels: &[f64]| accels.iter().map(|&a| Action { accel: a, pinch: 0.01 * a }).collect::<Vec<_>>();
    let no_points = ObjectObservations::Points(vec![vec![]; STEPS]);
    // Pooled over two samples: eight zeros and +-10: m2 = 20, m4 = 2000, so 2000/400 - 3 = 2.
    let heavy = [
        sample(0, states(), actions(&[0.0, 0.0, 0.0, 0.0, 10.0]), no_points.clone()),
        sample(1, states(), actions(&[0.0, 0.0, 0.0, 0.0, -10.0]), no_points.clone()),
    ];
    assert!((stat(&data, &heavy, "accel_kurtosis") - 2.0).abs() < 1e-12);
    assert!((stat(&data, &heavy, "pinch_kurtosis") - 2.0).abs() < 1e-9);
    // Geary's ratio: mean |x| = 2, sqrt(m2) = sqrt(20).
    assert!((stat(&data, &heavy, "accel_peakedness") - 2.0 / 20f64.sqrt()).abs() < 1e-12);
    // A two-point distribution has excess kurtosis -2; accel dt = +-0.5, sd sqrt(1/3).
    let light = [sample(0, states(), actions(&[-1.0, 1.0, -1.0, 1.0]), no_points.clone())];
    assert!((stat(&data, &light, "accel_kurtosis") - -2.0).abs() < 1e-12);
    assert!((stat(&data, &light, "accel_peakedness") - 1.0).abs() < 1e-12);
    assert!((stat(&data, &light, "speed_change_sd") - (1.0f64 / 3.0).sqrt()).abs() < 1e-12);
    // Without points every point statistic is NaN, the action ones are not.
    for (d, v) in checks_for(ObservationKind::Points).iter().zip(statistics(&data, &light)) {
        let from_actions =
            ["accel_kurtosis", "accel_peakedness", "pinch_kurtosis", "speed_change_sd"].contains(&d.name);
        assert_eq!(v.is_finite(), from_actions, "{} = {v}", d.name);
    }
}

/// A detection with centre `(x, y)` and heading `yaw`.
fn detection(x: f64, y: f64, yaw: f64) -> BoxDetection {
    BoxDetection { x, y, yaw, length: LENGTH, width: WIDTH, score: 1.0 }
}

#[test]
fn box_statistics_see_lag_flips_and_line_of_sight_residuals() {
    let data = dataset(ObservationKind::Boxes, 1);
    // Heading north at (10, 0): the line of sight from the AV is +x, so along is
    // +x and across is +y (to the left of the line of sight).
    let s: Vec<State> =
        (0..4).map(|t| State { x: 10.0, y: 0.0, yaw: FRAC_PI_2, v: 1.0 + t as f64, kappa: 0.0 }).collect();
    let offsets = [(0.5, 0.2), (-0.5, -0.2), (0.5, 0.2), (-0.5, -0.2)];
    let yaws = [0.1, -0.1, PI, 0.0];
    let dets =
        s.iter().zip(offsets).zip(yaws).map(|((x, (dx, dy)), dyaw)| Some(detection(x.x + dx, x.y + dy, x.yaw + dyaw)));
    let mut dets: Vec<Option<BoxDetection>> = dets.collect();
    dets.push(None); // a missed detection is skipped
    let mut s5 = s.clone();
    s5.push(s[0]);
    let samples = [sample(0, s5, vec![], ObjectObservations::Boxes(dets))];
    assert!((stat(&data, &samples, "yaw_reversal_fraction") - 0.25).abs() < 1e-12);
    assert!((stat(&data, &samples, "los_along_residual_sd") - (1.0f64 / 3.0).sqrt()).abs() < 1e-12);
    assert!((stat(&data, &samples, "los_across_residual_sd") - (0.16f64 / 3.0).sqrt()).abs() < 1e-12);
    // Yaw residuals 0.1, -0.1, 0 (the flip is excluded): sd 0.1.
    assert!((stat(&data, &samples, "yaw_residual_sd") - 0.1).abs() < 1e-12);
    // Detections at the lagged centre: slope -delay.
    let delay = 0.25;
    let lagged = s.iter().map(|x| lagged_pose(x, delay)).map(|p| Some(detection(p.x, p.y, p.yaw))).collect();
    let lag = [sample(0, s.clone(), vec![], ObjectObservations::Boxes(lagged))];
    assert!((stat(&data, &lag, "along_offset_vs_speed") - -delay).abs() < 1e-12);
}

/// Detections of one object heading east along `states()`, reversed where
/// `reversed[t]`, missing where `None`.
fn reversal_sample(object: usize, reversed: &[Option<bool>]) -> ObjectSample {
    let s: Vec<State> = states().into_iter().cycle().take(reversed.len()).collect();
    let dets = s.iter().zip(reversed).map(|(x, r)| r.map(|r| detection(x.x, x.y, if r { PI } else { 0.0 })));
    let observations = ObjectObservations::Boxes(dets.collect());
    sample(object, s, vec![], observations)
}

/// `yaw_reversal_persistence` pairs detections of one object at consecutive
/// steps only (a missed detection breaks the pair; objects are never paired),
/// and is the lag-one correlation (phi) of the reversal indicators: about the
/// chain's `lambda` over paths of a flip chain at any fraction, about 0 for
/// independent flips, 0 without reversals.
#[test]
fn reversal_persistence_is_the_lag_one_correlation_of_consecutive_detections() {
    let data = dataset(ObservationKind::Boxes, 2);
    let (t, f) = (Some(true), Some(false));
    // Pairs (f,t), (t,t), (t,f) and, across the gap, none; object 1: (f,f), (f,t).
    let samples = [reversal_sample(0, &[f, t, t, f, None, t]), reversal_sample(1, &[f, f, t])];
    // Both 1/5, first reversed 2/5, second reversed 3/5: phi = (0.2 - 0.24) / 0.24.
    let want = (1.0 / 5.0 - (2.0 / 5.0) * (3.0 / 5.0)) / 0.24;
    assert!((stat(&data, &samples, "yaw_reversal_persistence") - want).abs() < 1e-12);
    assert!(stat(&data, &[reversal_sample(0, &[t, None, t])], "yaw_reversal_persistence").is_nan(), "no pair");
    assert_eq!(stat(&data, &[reversal_sample(0, &[f, f, f])], "yaw_reversal_persistence"), 0.0, "no reversal");
    let steps = 400;
    let data = Dataset::builder(Meta::new(DT, steps), ObservationKind::Boxes);
    let data = {
        let mut b = data;
        b.scene(0, &vec![Pose::default(); steps]);
        for id in 0..50 {
            let prior = Prior { mean: State::default(), sd: State { x: 1.0, y: 1.0, yaw: 0.1, v: 1.0, kappa: 0.01 } };
            b.object(Object { scene: 0, id, length: LENGTH, width: WIDTH, prior });
        }
        b.build().expect("valid dataset")
    };
    let mut rng = SmallRng::seed_from_u64(3);
    for (p, lambda) in [(0.2, 0.8), (0.05, 0.4), (0.2, 0.0), (0.02, 0.6)] {
        let chain = FlipChain { fraction: p, persistence: lambda };
        let samples: Vec<ObjectSample> = (0..50)
            .map(|o| {
                let path: Vec<Option<bool>> = chain.sample_path(steps, &mut rng).into_iter().map(Some).collect();
                reversal_sample(o, &path)
            })
            .collect();
        let got = stat(&data, &samples, "yaw_reversal_persistence");
        assert!((got - lambda).abs() < 0.05, "p {p}, lambda {lambda}: {got}");
    }
}

#[test]
fn too_little_data_is_nan_never_a_panic() {
    for kind in [ObservationKind::Points, ObservationKind::Boxes] {
        let data = dataset(kind, 1);
        let empty = statistics(&data, &[]);
        assert_eq!(empty.len(), checks_for(kind).len());
        assert!(empty.iter().all(|v| v.is_nan()), "{kind:?}: {empty:?}");
        // An unknown object, more observation steps than states or AV poses.
        let obs = match kind {
            ObservationKind::Points => ObjectObservations::Points(vec![vec![[11.0, 0.0]]; STEPS + 3]),
            ObservationKind::Boxes => ObjectObservations::Boxes(vec![Some(detection(11.0, 0.0, 0.0)); STEPS + 3]),
        };
        let odd = [sample(7, states(), vec![], obs.clone()), sample(0, states()[..2].to_vec(), vec![], obs)];
        assert_eq!(statistics(&data, &odd).len(), checks_for(kind).len());
    }
}

// ---------------------------------------------------------------- calibration

const A: CheckDef = CheckDef {
    name: "a",
    description: "A.",
    kinds: &[ObservationKind::Points],
    suggests: Some(Suggestion { extension: "clutter", direction: Direction::Higher }),
};
const B: CheckDef = CheckDef { name: "b", description: "B.", kinds: &[ObservationKind::Points], suggests: None };
const C: CheckDef = CheckDef { name: "c", description: "C.", kinds: &[ObservationKind::Points], suggests: None };

/// Draw tables from per-check columns of (measured, replicated).
fn tables(columns: &[Vec<(f64, f64)>]) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    let draws = columns[0].len();
    let m = (0..draws).map(|k| columns.iter().map(|c| c[k].0).collect()).collect();
    let r = (0..draws).map(|k| columns.iter().map(|c| c[k].1).collect()).collect();
    (m, r)
}

#[test]
fn identical_data_is_not_significant_and_a_shift_is() {
    let noise = |k: usize, phase: f64| (k as f64 * 1.7 + phase).sin();
    let same: Vec<(f64, f64)> = (0..50).map(|k| (noise(k, 0.0), noise(k, 0.0))).collect();
    let shifted: Vec<(f64, f64)> = (0..50).map(|k| (3.0 + noise(k, 0.3), noise(k, 1.1))).collect();
    let (m, r) = tables(&[same, shifted]);
    let res = calibrate(&[&A, &B], &m, &r, 0.05);
    assert_eq!((res[0].name.as_str(), res[0].suggests.as_deref()), ("a", Some("clutter")));
    assert_eq!((res[0].z, res[0].p, res[0].p_adjusted, res[0].significant), (0.0, 1.0, 1.0, false));
    assert_eq!(res[0].draws, 50);
    // D = 3 + (sin - sin) has sd about 1, so z is about 3 / 1 and far from 0.
    assert!(res[1].z > 2.5, "z {}", res[1].z);
    assert!(res[1].significant && res[1].p < 0.01 && res[1].p_adjusted >= res[1].p);
    assert_eq!(res[1].name, "b");
    assert!((res[1].measured - res[1].replicated - 3.0).abs() < 0.3);
    assert!((res[1].replicated_sd - 0.7).abs() < 0.1, "sd of sin over many phases ~ 1/sqrt(2)");
    // The sign of z follows the shift.
    let res = calibrate(&[&A, &B], &r, &m, 0.05);
    assert!(res[1].z < -2.5 && res[1].significant);
}

#[test]
fn the_screen_is_one_sided_in_the_direction_the_extension_moves_the_check() {
    // D = [z - 1, z, z + 1] has mean z and sd 1, so z is exact.
    let column = |z: f64| vec![(z - 1.0, 0.0), (z, 0.0), (z + 1.0, 0.0)];
    for z in [1.0, -1.0, 2.3, -2.3] {
        let (m, r) = tables(&[column(z), column(z)]);
        let res = calibrate(&[&A, &B], &m, &r, 0.05);
        // A suggests clutter, which raises it: only a positive z screens it in.
        let screen = res[0].screen_p.expect("a check that suggests an extension has a screen p");
        assert!((screen - normal_cdf(-z)).abs() < 1e-12, "z {z}: screen p {screen}");
        assert!((res[0].p - 2.0 * normal_cdf(-z.abs())).abs() < 1e-12, "the reported p stays two-sided");
        assert_eq!(res[1].screen_p, None, "a general check screens nothing");
    }
    // At the same level the one-sided screen passes |z| > 0.84 the predicted way
    // (the two-sided one needed |z| > 1.28) and never the other way.
    assert!(Direction::Higher.p_value(0.9) < 0.2 && Direction::Either.p_value(0.9) > 0.2);
    assert!(Direction::Lower.p_value(-0.9) < 0.2 && Direction::Lower.p_value(5.0) > 0.99);
    assert_eq!(Direction::Higher.p_value(0.0), 1.0, "no spread, no evidence");
}

#[test]
fn every_revealing_check_states_the_direction_its_extension_moves_it() {
    use ssm::criticism::checks::Direction::{Either, Higher, Lower};
    for kind in [ObservationKind::Points, ObservationKind::Boxes] {
        for def in checks_for(kind) {
            let Some(Suggestion { extension, direction }) = def.suggests else { continue };
            let expected = match (extension, def.name) {
                // A lag puts observations behind the state: a negative slope and offset.
                ("latency", _) => Lower,
                ("clutter" | "heading_flip", _) => Higher,
                // Runs of reversals raise the indicators' lag-one correlation.
                ("persistent_flip", _) => Higher,
                // The extent factors can be below or above 1.
                ("size_bias", _) => Either,
                ("heavy_tailed_accel", "accel_kurtosis") => Higher,
                ("heavy_tailed_accel", "accel_peakedness") => Lower,
                (other, name) => panic!("{name} suggests {other}, which this test does not know"),
            };
            assert_eq!(direction, expected, "{}", def.name);
        }
    }
}

#[test]
fn holm_adjusts_in_order_and_stays_monotone() {
    // D = [z - 1, z, z + 1] has mean z and sd 1, so z is exact.
    let column = |z: f64| vec![(z - 1.0, 0.0), (z, 0.0), (z + 1.0, 0.0)];
    let (m, r) = tables(&[column(2.3), column(0.0), column(2.4)]);
    let res = calibrate(&[&A, &B, &C], &m, &r, 0.05);
    let p = |z: f64| 2.0 * normal_cdf(-z);
    let zs: Vec<f64> = res.iter().map(|r| r.z).collect();
    assert!((zs[0] - 2.3).abs() < 1e-12 && zs[1] == 0.0 && (zs[2] - 2.4).abs() < 1e-12, "{zs:?}");
    assert!((res[0].p - p(2.3)).abs() < 1e-12 && res[1].p == 1.0 && (res[2].p - p(2.4)).abs() < 1e-12);
    // Smallest p (z 2.4) times 3 = 0.049; next times 2 = 0.043 would be below it, so
    // the step-down takes the running maximum; the last is min(1, 1 * 1).
    assert!((res[2].p_adjusted - 3.0 * p(2.4)).abs() < 1e-12);
    assert!(2.0 * p(2.3) < 3.0 * p(2.4));
    assert_eq!(res[0].p_adjusted, res[2].p_adjusted);
    assert_eq!(res[1].p_adjusted, 1.0);
    assert_eq!(res.iter().map(|r| r.significant).collect::<Vec<_>>(), [true, false, true]);
    let strict = calibrate(&[&A, &B, &C], &m, &r, 0.04);
    assert!(strict.iter().all(|r| !r.significant));
}

#[test]
fn non_finite_draws_are_ignored() {
    let clean = vec![(1.0, 0.0), (2.0, 0.0), (3.0, 0.0), (2.5, 0.5)];
    let mut dirty = clean.clone();
    dirty.insert(1, (f64::NAN, 0.0));
    dirty.push((5.0, f64::INFINITY));
    let (mc, rc) = tables(&[clean]);
    let (md, rd) = tables(&[dirty]);
    let (c, d) = (&calibrate(&[&A], &mc, &rc, 0.05)[0], &calibrate(&[&A], &md, &rd, 0.05)[0]);
    assert_eq!((c.draws, d.draws), (4, 4));
    assert_eq!(c, d);
    // D = [1, 2, 3, 2]: mean 2, sd sqrt(2/3).
    assert!((d.z - 2.0 / (2.0f64 / 3.0).sqrt()).abs() < 1e-12 && d.measured == 2.125 && d.replicated == 0.125);
    // Fewer than 3 usable draws: no evidence.
    let two = calibrate(&[&A], &[vec![1.0], vec![5.0], vec![f64::NAN]], &[vec![0.0], vec![0.0], vec![0.0]], 0.05);
    assert_eq!((two[0].z, two[0].p, two[0].draws), (0.0, 1.0, 2));
    // No draws at all: NaN summaries, p = 1.
    let none = calibrate(&[&A], &[], &[], 0.05);
    assert_eq!((none[0].p, none[0].draws, none[0].significant), (1.0, 0, false));
    assert!(none[0].measured.is_nan());
}

#[test]
#[should_panic(expected = "calibrate: draw 1")]
fn a_row_of_the_wrong_length_panics() {
    calibrate(&[&A, &B], &[vec![0.0, 0.0], vec![0.0]], &[vec![0.0, 0.0], vec![0.0, 0.0]], 0.05);
}

#[test]
fn initial_lag_is_the_initial_offset_from_the_prior_over_the_prior_speed() {
    // Two objects with prior speeds 8 and 4 m/s heading north; their initial states
    // lie 0.15 s of travel behind the prior means.
    let mut b = Dataset::builder(Meta::new(DT, STEPS), ObservationKind::Points);
    b.scene(0, &[Pose::default(); STEPS]);
    let sd = State { x: 1.0, y: 1.0, yaw: 0.1, v: 1.0, kappa: 0.01 };
    for (id, v) in [(0, 8.0), (1, 4.0), (2, 0.5)] {
        let mean = State { x: 10.0, y: 5.0, yaw: FRAC_PI_2, v, kappa: 0.0 };
        b.object(Object { scene: 0, id, length: LENGTH, width: WIDTH, prior: Prior { mean, sd } });
    }
    let data = b.build().expect("valid dataset");
    let behind = |o: usize| {
        let prior = data.objects()[o].prior.mean;
        let p = lagged_pose(&prior, 0.15);
        vec![State { x: p.x, y: p.y, ..prior }; STEPS]
    };
    let no_points = || ObjectObservations::Points(vec![vec![]; STEPS]);
    let samples: Vec<ObjectSample> = (0..2).map(|o| sample(o, behind(o), vec![], no_points())).collect();
    assert!((stat(&data, &samples, "initial_lag") + 0.15).abs() < 1e-12);
    // The slow object (0.5 m/s) is left out whatever its offset.
    let slow = [sample(2, vec![State { x: 0.0, ..data.objects()[2].prior.mean }; STEPS], vec![], no_points())];
    assert!(stat(&data, &slow, "initial_lag").is_nan());
}

#[test]
fn accel_kurtosis_uses_standardised_innovations_when_given() {
    let data = dataset(ObservationKind::Points, 1);
    let no_points = ObjectObservations::Points(vec![vec![]; STEPS]);
    // Raw accelerations are a two-point distribution (kurtosis -2); the innovations
    // given are eight zeros and +-10 (kurtosis 2): the check uses the innovations.
    let accels = [1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0];
    let actions: Vec<Action> = accels.iter().map(|&a| Action { accel: a, pinch: 0.0 }).collect();
    let mut innovations = vec![0.0; 8];
    innovations.extend([10.0, -10.0]);
    let raw = [sample(0, states(), actions.clone(), no_points.clone())];
    assert!((stat(&data, &raw, "accel_kurtosis") + 2.0).abs() < 1e-12);
    let with = [ObjectSample { accel_innovations: innovations, ..sample(0, states(), actions, no_points) }];
    assert!((stat(&data, &with, "accel_kurtosis") - 2.0).abs() < 1e-12);
}

/// Differences equal up to rounding (the measured statistic off every replicate
/// by the same amount) give a z that is a ratio to a rounding error; it is
/// printed as a bound, with its sign, and ordinary z as numbers.
#[test]
fn a_z_without_spread_is_printed_as_a_bound() {
    let offset = 0.054;
    let rounding = [offset, offset + 1e-17, offset - 1e-17, offset, offset + 2e-17];
    let column: Vec<(f64, f64)> = rounding.iter().map(|&m| (m, 0.0)).collect();
    let (m, r) = tables(&[column]);
    let z = calibrate(&[&A], &m, &r, 0.05)[0].z;
    assert!(z > 1e12, "z {z}");
    assert_eq!(format_z(z, 1), "> 1e6 (no spread)");
    assert_eq!(format_z(-z, 1), "< -1e6 (no spread)");
    assert_eq!(format_z(-3.27, 1), "-3.3");
    assert_eq!(format_z(2.345, 2), "2.35");
}

/// A check without usable draws has non-finite statistics, which JSON holds as
/// `null`; the result is read back with NaN there (a report must be readable
/// again, e.g. when `sefi power-study` resumes).
#[test]
fn a_check_with_non_finite_statistics_survives_a_json_round_trip() {
    let (m, r) = tables(&[vec![(f64::NAN, 0.0), (f64::NAN, 1.0), (f64::NAN, 2.0)]]);
    let result = calibrate(&[&A], &m, &r, 0.05).remove(0);
    assert!(result.measured.is_nan() && result.draws == 0, "{result:?}");
    let text = serde_json::to_string(&result).unwrap();
    assert!(text.contains("\"measured\":null"), "{text}");
    let back: ssm::criticism::checks::CheckResult = serde_json::from_str(&text).unwrap();
    assert!(back.measured.is_nan() && back.replicated.is_nan());
    assert_eq!((back.z, back.p, back.draws), (result.z, result.p, result.draws));
}

#[test]
fn holm_within_a_family_adjusts_for_its_members_only() {
    let p = [0.01, 0.3, 0.02, 0.04];
    // The whole family: Holm over four.
    assert_eq!(holm_within(&p, &[true; 4]), holm(&p));
    // Two members: each adjusted for two tests; the others are not tested.
    let within = holm_within(&p, &[true, false, true, false]);
    assert!((within[0] - 0.02).abs() < 1e-15 && (within[2] - 0.02).abs() < 1e-15, "{within:?}");
    assert_eq!((within[1], within[3]), (1.0, 1.0));
    assert_eq!(holm_within(&p, &[false; 4]), vec![1.0; 4]);
}
