//! The metrics of SPEC §5 on hand-made cases with known answers, and the
//! parameter-file convention of `ssm::models::params`.

use std::f64::consts::PI;

use crate::common::with_csv_rows_rewritten;
use autodiff::nn::ParamStore;
use autodiff::Tensor;
use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::data::{Action, Dataset, DatasetBuilder, Meta, Object, ObservationKind, Pose, Prior, State};
use ssm::evaluation::metrics::{
    aotll, aptll, box_aotll_terms, evaluate, mll, state_errors, summarise_runs, track, wrapped_abs_diff, MeanOver,
};
use ssm::filter::{FilterConfig, Sampling};
use ssm::models::observation::{labelled_steps, OBS_PREFIX};
use ssm::models::observation::{
    BoxObservationModel, ObsContext, ObservationModel, PointObservationModel, PosesRef, Scratch,
};
use ssm::models::params::{AnyObservation, AnyPolicy, ModelAdditions, Models, ParamsError, HAND_CRAFTED_PARAM};
use ssm::models::vehicle::{
    Action as VAction, ActionGaussians, ActionsMut, GaussianPolicy, HandCraftedPolicy, MotionModel, NeuralPolicy,
    VehicleState,
};
use ssm::stats::{iqr, median, quantile, Summary};

const DT: f64 = 1.0 / 3.0;

/// A parameter store with the true hand-crafted policy and a freshly initialised
/// observation network of `kind`.
fn store_for(kind: ObservationKind, seed: u64) -> ParamStore<f64> {
    let mut store = ParamStore::new();
    let mut rng = StdRng::seed_from_u64(seed);
    AnyObservation::init(kind, &mut store, &mut rng);
    AnyPolicy::HandCrafted(HandCraftedPolicy::truth()).add_to_store(&mut store);
    store
}

/// A tiny dataset simulated from `models`: one scene, an AV driving along x at
/// 5 m/s, `n` objects over `steps` steps with true states and actions, 4 points (or
/// one detection) per step, except object 0 at step 2 (unobserved) and object 1
/// at step 3 (no true state).
fn tiny(kind: ObservationKind, models: &Models, n: usize, steps: usize, seed: u64) -> Dataset {
    let mut rng = StdRng::seed_from_u64(seed);
    let av: Vec<Pose> = (0..steps).map(|t| Pose { x: 5.0 * DT * t as f64, y: 0.0, yaw: 0.0 }).collect();
    let mut b = Dataset::builder(Meta::new(DT, steps), kind);
    b.scene(1, &av);
    let motion = MotionModel::new(DT, Default::default()).unwrap();
    let mut g = ActionGaussians::default();
    for i in 0..n {
        let id = 10 + i as i64;
        let x0 = State { x: 12.0 + 6.0 * i as f64, y: 4.0 - 3.0 * i as f64, yaw: 0.3 * i as f64, v: 6.0, kappa: 0.01 };
        let sd = State { x: 0.5, y: 0.5, yaw: 0.05, v: 0.5, kappa: 0.005 };
        let obj = Object { scene: 1, id, length: 4.5, width: 1.8, prior: Prior { mean: x0, sd } };
        b.object(obj);
        let mut s = VehicleState::new(x0.x, x0.y, x0.yaw, x0.v, x0.kappa);
        for (t, &av_t) in av.iter().enumerate() {
            if t > 0 {
                let (mut a, mut p) = ([0.0], [0.0]);
                models.policy.sample_actions(
                    &[s.v],
                    &[s.kappa],
                    &mut rng,
                    &mut g,
                    ActionsMut { accel: &mut a, pinch: &mut p },
                );
                s = motion.step(&s, &VAction::new(a[0], p[0]));
                b.action(1, id, t, Action { accel: a[0], pinch: p[0] });
            }
            let state = State { x: s.x, y: s.y, yaw: s.yaw, v: s.v, kappa: s.kappa };
            if !(i == 1 && t == 3) {
                b.state(1, id, t, state);
            }
            if i == 0 && t == 2 {
                continue;
            }
            let ctx = ObsContext::of_object(av_t, &obj);
            let pose = Pose { x: s.x, y: s.y, yaw: s.yaw };
            match &models.observation {
                AnyObservation::Points(m) => {
                    let mut pts = Vec::new();
                    m.sample(&models.observation_params, &ctx, pose, 4, &mut rng, &mut pts);
                    for p in pts {
                        b.point(1, id, t, p);
                    }
                }
                AnyObservation::Boxes(m) => {
                    let mut dets = Vec::new();
                    m.sample(&models.observation_params, &ctx, pose, 1, &mut rng, &mut dets);
                    b.detection(1, id, t, dets[0]);
                }
            }
        }
    }
    b.build().unwrap()
}

/// The models of `store_for(kind, store_seed)` and a `tiny` dataset of `n` objects
/// over `steps` steps simulated from them with `data_seed`.
fn models_and_data(
    kind: ObservationKind,
    store_seed: u64,
    n: usize,
    steps: usize,
    data_seed: u64,
) -> (Models, Dataset) {
    let models = Models::from_store(&store_for(kind, store_seed), kind).unwrap();
    let data = tiny(kind, &models, n, steps, data_seed);
    (models, data)
}

fn config(particles: usize, lag: usize) -> FilterConfig {
    FilterConfig::new(Sampling::new(particles, None), lag, 3)
}

#[test]
fn yaw_error_wraps() {
    // 3.1 and -3.1 are 2 pi - 6.2 = 0.0832 apart, not 6.2.
    assert!((wrapped_abs_diff(3.1, -3.1) - (2.0 * PI - 6.2)).abs() < 1e-12);
    assert!((wrapped_abs_diff(3.1, -3.1) - 0.083).abs() < 1e-3);
    assert!((wrapped_abs_diff(0.25, -0.5) - 0.75).abs() < 1e-12);
    assert!((wrapped_abs_diff(7.0 * PI, 0.0) - PI).abs() < 1e-9);
    assert!(wrapped_abs_diff(1.0, 1.0 + 4.0 * PI) < 1e-9);
}

#[test]
fn state_errors_of_perfect_and_shifted_estimates() {
    let (_, data) = models_and_data(ObservationKind::Points, 0, 3, 5, 1);
    let truth = data.states().unwrap();
    // Estimates = truth (the missing cell filled with garbage, which must be skipped).
    let perfect: Vec<Vec<State>> = (0..3)
        .map(|o| (0..5).map(|t| truth.get(o, t).copied().unwrap_or(State { x: 1e6, ..State::default() })).collect())
        .collect();
    let e = state_errors(&perfect, truth);
    assert_eq!(e.count, 3 * 5 - 1, "one missing true state is skipped");
    assert_eq!(e.ade, Some(0.0));
    assert_eq!(e.aye, Some(0.0));

    // Shifted by (3, 4) m and rotated by 0.1 rad: ADE 5, AYE 0.1.
    let shifted: Vec<Vec<State>> = perfect
        .iter()
        .map(|r| r.iter().map(|s| State { x: s.x + 3.0, y: s.y - 4.0, yaw: s.yaw + 0.1, ..*s }).collect())
        .collect();
    let e = state_errors(&shifted, truth);
    assert!((e.ade.unwrap() - 5.0).abs() < 1e-9);
    assert!((e.aye.unwrap() - 0.1).abs() < 1e-9);
}

/// A points dataset of `steps` steps under construction: scene 0 with the AV at the
/// origin throughout, and object 0 (4 x 2 m) with prior mean `mean` and unit sds.
fn one_object(steps: usize, mean: State) -> DatasetBuilder {
    let mut b = Dataset::builder(Meta::new(DT, steps), ObservationKind::Points);
    b.scene(0, &vec![Pose::default(); steps]);
    b.object(Object {
        scene: 0,
        id: 0,
        length: 4.0,
        width: 2.0,
        prior: Prior { mean, sd: State { x: 1.0, y: 1.0, yaw: 1.0, v: 1.0, kappa: 1.0 } },
    });
    b
}

#[test]
fn state_errors_wrap_yaw_across_pi() {
    let s = State { x: 1.0, y: 2.0, yaw: -3.1, v: 1.0, kappa: 0.0 };
    let mut b = one_object(1, s);
    b.state(0, 0, 0, s);
    let data = b.build().unwrap();
    let e = state_errors(&[vec![State { yaw: 3.1, ..s }]], data.states().unwrap());
    assert!((e.aye.unwrap() - 0.0832).abs() < 1e-4, "aye {:?}", e.aye);
    assert_eq!(e.ade, Some(0.0));
}

#[test]
fn state_errors_without_any_truth_are_none() {
    let s = State { x: 1.0, y: 2.0, yaw: 0.0, v: 1.0, kappa: 0.0 };
    let mut b = one_object(2, s);
    b.with_states();
    let data = b.build().unwrap();
    let e = state_errors(&[vec![s, s]], data.states().unwrap());
    assert_eq!((e.ade, e.aye, e.count), (None, None, 0));
}

#[test]
fn mll_is_loglik_per_point() {
    assert_eq!(mll(-10.0, 4), Some(-2.5));
    assert_eq!(mll(-10.0, 0), None);

    let (models, data) = models_and_data(ObservationKind::Points, 2, 3, 6, 4);
    let AnyObservation::Points(obs) = &models.observation else { unreachable!() };
    let m = evaluate(&data, &models.policy, obs, &models.observation_params, &config(256, 2)).unwrap();
    assert_eq!(m.collapsed_steps, 0);
    // Every point of the dataset enters the likelihood; object 0 misses step 2.
    assert_eq!(m.observed_units, data.points().unwrap().len());
    assert_eq!(m.observed_units, 4 * (3 * 6 - 1));
    let mll = m.mll.unwrap();
    assert!(mll.is_finite());
    assert!((mll * m.observed_units as f64 - m.log_likelihood).abs() < 1e-9 * m.log_likelihood.abs());
    assert_eq!((m.particles, m.lag, m.seed), (256, 2, 3));
    // Every state with a true value was compared, for both estimates.
    assert_eq!(m.smoothed.count, 3 * 6 - 1);
    assert_eq!(m.filtered.count, 3 * 6 - 1);
    assert!(m.smoothed.ade.unwrap().is_finite() && m.filtered.aye.unwrap() <= PI);
}

#[test]
fn aotll_equals_a_direct_computation() {
    let (models, data) = models_and_data(ObservationKind::Points, 5, 2, 5, 6);
    let AnyObservation::Points(obs) = &models.observation else { unreachable!() };
    let got = aotll(&data, obs, &models.observation_params);

    // Direct: the batched plain path, one pose, all of a step's points at once.
    let (truth, points) = (data.states().unwrap(), data.points().unwrap());
    let (mut sum, mut count) = (0.0, 0);
    let mut scratch = Scratch::new();
    for o in 0..2 {
        for t in 0..5 {
            let (Some(s), pts) = (truth.get(o, t), points.get(o, t)) else { continue };
            if pts.is_empty() {
                continue;
            }
            let ctx = ObsContext::of_object(data.scenes()[0].av[t], &data.objects()[o]);
            let mut out = [0.0f64];
            obs.log_likelihood(
                &models.observation_params,
                &ctx,
                PosesRef::new(&[s.x], &[s.y], &[s.yaw]),
                pts,
                &mut scratch,
                &mut out,
            );
            sum += out[0];
            count += pts.len();
        }
    }
    assert_eq!(got.count, count);
    assert_eq!(count, 4 * (2 * 5 - 2), "one step unobserved, one without a true state");
    assert!((got.mean.unwrap() - sum / count as f64).abs() < 1e-10, "{:?} vs {}", got.mean, sum / count as f64);
}

#[test]
fn mean_over_shows_a_mean_carried_by_a_few_items() {
    // 198 items at 1 nat and 2 far in the tail: the mean is negative, the median
    // and the mean without the lowest 1% are the bulk's.
    let mut items = vec![1.0; 198];
    items.insert(17, -100.0);
    items.insert(120, -100.0);
    let m = MeanOver::of(&items);
    assert_eq!(m.count, 200);
    assert!((m.mean.unwrap() - (198.0 - 200.0) / 200.0).abs() < 1e-12);
    assert_eq!(m.median, Some(1.0));
    // Linear interpolation between the 2nd (-100) and 3rd (1) order statistics.
    assert!((m.q01.unwrap() - (-100.0 + 0.99 * 101.0)).abs() < 1e-9, "{:?}", m.q01);
    assert!((m.mean_above_q01.unwrap() - 1.0).abs() < 1e-12);
    let empty = MeanOver::of(&[]);
    assert_eq!((empty.mean, empty.count, empty.median, empty.q01, empty.mean_above_q01), (None, 0, None, None, None));
}

#[test]
fn aotll_of_box_detections_counts_detections() {
    let (models, data) = models_and_data(ObservationKind::Boxes, 7, 2, 4, 8);
    let AnyObservation::Boxes(obs) = &models.observation else { unreachable!() };
    let got = aotll(&data, obs, &models.observation_params);
    // 2 objects x 4 steps, minus object 0's unobserved step 2 and object 1's step 3 without truth.
    assert_eq!(got.count, 2 * 4 - 1 - 1);
    assert!(got.mean.unwrap().is_finite());
    let m = evaluate(&data, &models.policy, obs, &models.observation_params, &config(128, 1)).unwrap();
    assert_eq!(m.observed_units, 2 * 4 - 1);
}

#[test]
fn aptll_equals_the_gaussian_log_density() {
    let (models, data) = models_and_data(ObservationKind::Points, 9, 3, 6, 10);
    let got = aptll(&data, &models.policy);

    let (states, actions) = (data.states().unwrap(), data.actions().unwrap());
    let normal = |x: f64, m: f64, sd: f64| -0.5 * ((x - m) / sd).powi(2) - sd.ln() - 0.5 * (2.0 * PI).ln();
    let (mut sum, mut count) = (0.0, 0);
    for o in 0..3 {
        for t in 1..6 {
            let (Some(prev), Some(a)) = (states.get(o, t - 1), actions.get(o, t)) else { continue };
            let ma = 1.5 * ((8.0 - prev.v) / 4.0).tanh();
            let mp = -prev.kappa * (0.5 + 0.1 * prev.v);
            sum += normal(a.accel, ma, 0.5) + normal(a.pinch, mp, 0.02);
            count += 1;
        }
    }
    // Object 1 has no true state at step 3, so its action at step 4 is skipped.
    assert_eq!(count, 3 * 5 - 1);
    assert_eq!(got.count, count);
    assert!((got.mean.unwrap() - sum / count as f64).abs() < 1e-9, "{:?} vs {}", got.mean, sum / count as f64);
}

#[test]
fn true_parameters_score_better_than_wrong_ones() {
    // The true policy's APTLL beats a policy with 10x sds (an easy, certain gap:
    // the log-density drops by about ln 100 = 4.6 per step plus the shrunk quadratic).
    let (models, data) = models_and_data(ObservationKind::Points, 11, 4, 8, 12);
    let wide = HandCraftedPolicy::new(5.0f64.ln(), 0.2f64.ln()).unwrap();
    let (good, bad) = (aptll(&data, &models.policy).mean.unwrap(), aptll(&data, &wide).mean.unwrap());
    assert!(good > bad + 3.0, "true {good}, wide {bad}");
}

#[test]
fn tracks_cover_every_object_and_step() {
    let (models, data) = models_and_data(ObservationKind::Points, 13, 3, 7, 14);
    let AnyObservation::Points(obs) = &models.observation else { unreachable!() };
    let tr =
        track(&data, &models.policy, obs, &models.observation_params, ModelAdditions::NONE, &config(128, 3)).unwrap();
    assert_eq!(tr.filtered.len(), 3);
    assert_eq!(tr.smoothed.len(), 3);
    assert!(tr.filtered.iter().chain(&tr.smoothed).all(|r| r.len() == 7));
    assert!(tr.smoothed.iter().flatten().all(|s| s.to_array().iter().all(|v| v.is_finite()) && s.yaw.abs() <= PI));
    // With lag 0 the smoothed means are the filtering means.
    let tr0 =
        track(&data, &models.policy, obs, &models.observation_params, ModelAdditions::NONE, &config(128, 0)).unwrap();
    assert_eq!(tr0.smoothed, tr0.filtered);
    // The wrong kind of model is an error, not a panic.
    let mut s2 = ParamStore::new();
    let boxes = BoxObservationModel::init_params(&mut s2, OBS_PREFIX, &mut StdRng::seed_from_u64(0));
    assert!(track(&data, &models.policy, &boxes, &s2, ModelAdditions::NONE, &config(16, 0)).is_err());
}

#[test]
fn median_and_iqr() {
    let s = Summary::of(&[5.0, 1.0, 4.0, 2.0, 3.0]).unwrap();
    assert_eq!((s.median, s.q1, s.q3, s.iqr, s.n), (3.0, 2.0, 4.0, 2.0, 5));
    // Even count: linear interpolation (NumPy's default).
    let s = Summary::of(&[4.0, 1.0, 3.0, 2.0]).unwrap();
    assert_eq!((s.median, s.q1, s.q3), (2.5, 1.75, 3.25));
    assert_eq!(iqr(&[4.0, 1.0, 3.0, 2.0]), Some(1.5));
    assert_eq!(median(&[7.0]), Some(7.0));
    assert_eq!(Summary::of(&[7.0]).unwrap().iqr, 0.0);
    // Non-finite values are left out; nothing left is None.
    assert_eq!(median(&[f64::NAN, 1.0, 3.0, f64::INFINITY]), Some(2.0));
    assert_eq!(median(&[]), None);
    assert!(Summary::of(&[f64::NAN]).is_none());
    assert_eq!(quantile(&[0.0, 10.0], 0.3), Some(3.0));
}

#[test]
fn summaries_over_repeated_runs() {
    let (models, data) = models_and_data(ObservationKind::Points, 15, 2, 5, 16);
    let AnyObservation::Points(obs) = &models.observation else { unreachable!() };
    let runs: Vec<_> = (0..5)
        .map(|seed| {
            let c = FilterConfig { seed, ..config(64, 2) };
            evaluate(&data, &models.policy, obs, &models.observation_params, &c).unwrap()
        })
        .collect();
    let summary = summarise_runs(&runs);
    let get = |name: &str| summary.iter().find(|(n, _)| *n == name).unwrap().1.unwrap();
    let mlls: Vec<f64> = runs.iter().map(|m| m.mll.unwrap()).collect();
    assert_eq!(get("mll").median, median(&mlls).unwrap());
    assert_eq!(get("mll").n, 5);
    // AOTLL and APTLL do not depend on the filter: zero spread.
    assert_eq!(get("aotll").iqr, 0.0);
    assert_eq!(get("aptll").iqr, 0.0);
    assert!(summarise_runs(&[]).is_empty());
}

#[test]
fn params_round_trip_both_policies() {
    // Hand-crafted.
    let store = store_for(ObservationKind::Points, 17);
    let models = Models::from_store(&store, ObservationKind::Points).unwrap();
    assert_eq!(models.policy, AnyPolicy::HandCrafted(HandCraftedPolicy::truth()));
    assert_eq!(models.observation.kind(), ObservationKind::Points);
    let back = Models::from_store(&models.to_store(), ObservationKind::Points).unwrap();
    assert_eq!(back.policy, models.policy);
    assert_eq!(back.observation_params.values(), models.observation_params.values());

    // Neural, saved to a file and loaded.
    let neural = NeuralPolicy::new(&mut StdRng::seed_from_u64(18));
    let mut store = ParamStore::new();
    AnyPolicy::Neural(neural.clone()).add_to_store(&mut store);
    BoxObservationModel::init_params(&mut store, OBS_PREFIX, &mut StdRng::seed_from_u64(19));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("params.bin");
    store.save(&path).unwrap();
    let loaded = ParamStore::<f64>::load(&path).unwrap();
    let models = Models::from_store(&loaded, ObservationKind::Boxes).unwrap();
    match &models.policy {
        AnyPolicy::Neural(p) => assert_eq!(p.parameters(), neural.parameters()),
        other => panic!("expected the neural policy, got {}", other.name()),
    }
    assert_eq!(models.policy.num_parameters(), 1317);
}

#[test]
fn params_errors_are_clear() {
    let points = store_for(ObservationKind::Points, 20);
    // A point network cannot drive a box model, and the message says which model.
    let e = Models::from_store(&points, ObservationKind::Boxes).unwrap_err();
    assert!(e.to_string().contains("box-detection observation model"), "{e}");
    let boxes = store_for(ObservationKind::Boxes, 21);
    let e = Models::from_store(&boxes, ObservationKind::Points).unwrap_err();
    assert!(e.to_string().contains("point observation model"), "{e}");

    // No policy; no observation network.
    let mut only_obs = ParamStore::new();
    PointObservationModel::init_params(&mut only_obs, OBS_PREFIX, &mut StdRng::seed_from_u64(0));
    assert_eq!(Models::from_store(&only_obs, ObservationKind::Points).unwrap_err(), ParamsError::NoPolicy);
    let mut only_policy = ParamStore::new();
    AnyPolicy::HandCrafted(HandCraftedPolicy::truth()).add_to_store(&mut only_policy);
    assert_eq!(Models::from_store(&only_policy, ObservationKind::Points).unwrap_err(), ParamsError::NoObservation);

    // Mixed policies; a bad shape; a NaN.
    let mut mixed = points.clone();
    mixed.add("policy.0.w", Tensor::zeros(&[2, 32]));
    assert!(matches!(Models::from_store(&mixed, ObservationKind::Points), Err(ParamsError::Unexpected { .. })));
    let mut bad = only_obs.clone();
    bad.add(HAND_CRAFTED_PARAM, Tensor::from_vec(vec![0.0, 0.0, 0.0]));
    assert!(matches!(Models::from_store(&bad, ObservationKind::Points), Err(ParamsError::Shape { .. })));
    let mut nan = only_obs.clone();
    nan.add(HAND_CRAFTED_PARAM, Tensor::from_vec(vec![f64::NAN, 0.0]));
    assert!(matches!(Models::from_store(&nan, ObservationKind::Points), Err(ParamsError::NonFinite { .. })));
    // A partial neural policy names the missing layer.
    let mut partial = only_obs.clone();
    for (name, v) in NeuralPolicy::new(&mut StdRng::seed_from_u64(0)).store().iter().take(2) {
        partial.add(name, v.clone());
    }
    let e = Models::from_store(&partial, ObservationKind::Points).unwrap_err();
    assert!(e.to_string().contains("policy.1.w") && e.to_string().contains("missing"), "{e}");
}

/// AOTLL split for box detections: on generated data with a known share of
/// reversed headings (the hidden `heading_flip` effect, two strengths, two seeds;
/// none without it), the split counts about that share as reversed, its parts
/// add up to `aotll` itself, and the other detections' factors add up to their mean.
#[test]
fn box_aotll_terms_count_reversed_headings_and_add_up_to_aotll() {
    use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
    for (strength, seed) in [(0.0, 1), (0.5, 2), (1.5, 3)] {
        let effect = if strength > 0.0 {
            HiddenEffect::at_strength("heading_flip", strength).unwrap()
        } else {
            HiddenEffect::None
        };
        let config = HiddenConfig { scenes: 6, ..HiddenConfig::quick(ObservationKind::Boxes, effect, seed) };
        let data = generate_hidden(&config).unwrap();
        let mut store = ParamStore::new();
        let model = BoxObservationModel::init_params(&mut store, OBS_PREFIX, &mut StdRng::seed_from_u64(seed));
        let terms = box_aotll_terms(&data, &model, &store).expect("labelled box detections");
        let whole = aotll(&data, &model, &store);
        let total = terms.reversed.count + terms.others.total.count;
        assert_eq!(total, whole.count);
        let share = terms.reversed.count as f64 / total as f64;
        let expected = 0.2 * strength;
        // Binomial sd over ~500 detections is <= 0.02; the generator's own yaw
        // noise reverses almost none.
        assert!((share - expected).abs() < 0.06, "strength {strength}: {share} reversed, expected {expected}");
        let others = terms.others.total.mean.unwrap();
        let recombined = terms.reversed_contribution + others * terms.others.total.count as f64 / total as f64;
        assert!((recombined - whole.mean.unwrap()).abs() < 1e-9, "{recombined} vs {:?}", whole.mean);
        let g = &terms.others;
        let parts = g.along.mean.unwrap() + g.across.mean.unwrap() + g.yaw.mean.unwrap();
        assert!((parts - others).abs() < 1e-9, "{parts} vs {others}");
        let (ba, bc, by) = g.mean_scales;
        let (oa, oc, oy) = g.mean_abs_offsets;
        assert!([ba, bc, by, oa, oc, oy].iter().all(|v| v.is_finite() && *v > 0.0));
        // The cars along and across the line of sight split the others.
        let (a, c) = (&terms.in_line.total, &terms.crossing.total);
        assert_eq!(a.count + c.count, g.total.count);
        let pooled = a.mean.unwrap_or(0.0) * a.count as f64 + c.mean.unwrap_or(0.0) * c.count as f64;
        assert!((pooled / g.total.count as f64 - others).abs() < 1e-9);
        // Recounted from the labels another way (cosines rather than wrapped
        // angles): a detection is reversed when its heading's cosine with the
        // label's is negative; a car is within 45 degrees of the line of sight when
        // |cos(heading - bearing)| >= cos 45 degrees.
        let (mut reversed, mut in_line) = (0, 0);
        for (ctx, pose, items) in labelled_steps::<BoxObservationModel>(&data, data.states().unwrap()) {
            let bearing = (pose.y - ctx.av.y).atan2(pose.x - ctx.av.x);
            let along_line = (pose.yaw - bearing).cos().abs() >= std::f64::consts::FRAC_1_SQRT_2;
            for det in items {
                if (det.yaw - pose.yaw).cos() < 0.0 {
                    reversed += 1;
                } else if along_line {
                    in_line += 1;
                }
            }
        }
        assert_eq!((terms.reversed.count, terms.in_line.total.count), (reversed, in_line), "strength {strength}");
        assert!(in_line > 0 && terms.crossing.total.count > 0, "both groups occur in generated scenes");
    }
    // Point data have no box factors.
    let (_, points) = models_and_data(ObservationKind::Points, 0, 2, 4, 0);
    let mut store = ParamStore::new();
    let model = BoxObservationModel::init_params(&mut store, OBS_PREFIX, &mut StdRng::seed_from_u64(0));
    assert!(box_aotll_terms(&points, &model, &store).is_none());
}

/// Reversed headings over objects and steps: generated data whose detections
/// are reversed independently (the hidden `heading_flip`, two strengths and
/// seeds) look independent — dispersion near 1, the chance after a reversal near
/// the rate, objects with one near the independent count — while generated data
/// without flips whose every detection of every k-th object is reversed (k = 4
/// and 3, written and read back) look persistent. The counts agree with a
/// recount by cosines, and point data have none.
#[test]
fn heading_reversals_tell_independent_flips_from_persistent_ones() {
    use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
    use ssm::data::heading_reversals;
    let recount = |data: &Dataset| -> usize {
        labelled_steps::<BoxObservationModel>(data, data.states().unwrap())
            .map(|(_, pose, items)| items.iter().filter(|d| (d.yaw - pose.yaw).cos() < 0.0).count())
            .sum()
    };
    for (strength, seed) in [(0.5, 2), (1.5, 3)] {
        let effect = HiddenEffect::at_strength("heading_flip", strength).unwrap();
        let config = HiddenConfig { scenes: 10, ..HiddenConfig::quick(ObservationKind::Boxes, effect, seed) };
        let data = generate_hidden(&config).unwrap();
        let r = heading_reversals(&data).expect("labelled box detections");
        assert_eq!(r.reversed, recount(&data), "strength {strength}");
        assert!((r.rate() - 0.2 * strength).abs() < 0.06, "strength {strength}: rate {}", r.rate());
        let dispersion = r.dispersion.unwrap();
        assert!((0.4..1.8).contains(&dispersion), "strength {strength}: independent flips, dispersion {dispersion}");
        let after = r.persistence.unwrap();
        assert!((after - r.rate()).abs() < 0.12, "strength {strength}: {after} after a reversal, rate {}", r.rate());
        let expected_any = r.objects_with_any_if_independent;
        assert!((r.objects_with_any as f64 - expected_any).abs() < 0.25 * expected_any, "{r:?}");
    }
    for (every, seed) in [(4, 2), (3, 3)] {
        let config =
            HiddenConfig { scenes: 10, ..HiddenConfig::quick(ObservationKind::Boxes, HiddenEffect::None, seed) };
        let data = generate_hidden(&config).unwrap();
        assert_eq!(heading_reversals(&data).unwrap().reversed, 0, "the generator reverses none by itself");
        let mut order: Vec<(String, String)> = Vec::new();
        let reversed = with_csv_rows_rewritten(&data, "boxes.csv", &format!("reversals-{seed}"), |col, fields| {
            let key = (fields[col("scene")].clone(), fields[col("object")].clone());
            let index = order.iter().position(|k| *k == key).unwrap_or_else(|| {
                order.push(key);
                order.len() - 1
            });
            if index % every == 0 {
                let yaw = col("yaw");
                fields[yaw] = (fields[yaw].parse::<f64>().unwrap() + PI).to_string();
            }
        });
        let r = heading_reversals(&reversed).unwrap();
        assert_eq!(r.reversed, recount(&reversed));
        assert_eq!(r.objects_with_any, order.len().div_ceil(every), "{r:?}");
        assert!(r.objects_with_any_if_independent > 0.9 * r.objects as f64, "{r:?}");
        assert!(r.dispersion.unwrap() > 5.0, "{r:?}");
        // With whole objects reversed and none else, a reversed object's term is
        // n (1 - rate) / rate and another's n rate / (1 - rate); summed over the
        // objects they make rate N (1 - rate) / rate + (1 - rate) N rate / (1 - rate)
        // = N, so the dispersion is exactly the detections per object.
        let per_object = r.detections as f64 / r.objects as f64;
        assert!((r.dispersion.unwrap() - per_object).abs() < 1e-9, "{r:?}: {per_object} detections per object");
        assert_eq!(r.persistence, Some(1.0), "{r:?}");
    }
    let (_, points) = models_and_data(ObservationKind::Points, 0, 2, 4, 0);
    assert!(heading_reversals(&points).is_none());
}

/// A persistent flip's AOTLL is a detection's density given the state alone,
/// its indicator marginalised over the chain's stationary law: exactly
/// independent flips' at the same fraction, whatever the persistence (two
/// fractions, two persistences, data with reversed headings).
#[test]
fn persistent_flips_have_the_aotll_of_independent_flips_at_their_fraction() {
    use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
    use ssm::evaluation::metrics::models_aotll;
    use ssm::models::extended::Extension;
    use ssm::models::params::FittedExtension;
    let effect = HiddenEffect::at_strength("heading_flip", 1.0).unwrap();
    let data =
        generate_hidden(&HiddenConfig { scenes: 3, ..HiddenConfig::quick(ObservationKind::Boxes, effect, 4) }).unwrap();
    let policy = NeuralPolicy::new(&mut StdRng::seed_from_u64(4)).with_initial_sds(0.5, 0.02);
    let models = Models::initial(ObservationKind::Boxes, AnyPolicy::Neural(policy), 5);
    let base = models_aotll(&data, &models).mean.unwrap();
    for fraction in [0.05, 0.2] {
        let with = |extension: Extension, natural: &[f64]| {
            let raw = extension.stored(natural).unwrap();
            let mut m = models.clone();
            m.extension = Some(FittedExtension { extension, raw });
            models_aotll(&data, &m).mean.unwrap()
        };
        let independent = with(Extension::HeadingFlip, &[fraction]);
        assert!(independent > base + 0.1, "flips explain the reversed detections: {independent} vs {base}");
        for persistence in [0.3, 0.9] {
            let persistent = with(Extension::PersistentFlip, &[fraction, persistence]);
            assert!(
                (persistent - independent).abs() < 1e-4 * independent.abs().max(1.0),
                "fraction {fraction}, persistence {persistence}: {persistent} vs {independent}"
            );
        }
    }
}
