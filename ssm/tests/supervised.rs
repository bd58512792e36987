//! The supervised observation model (`ssm::training::supervised`): fitting a network to
//! labelled states by maximum AOTLL raises the AOTLL of the training data and of
//! held-out data, for points and for box detections, reports what
//! `ssm::evaluation::metrics::aotll` measures, and refuses data it cannot fit.

use autodiff::nn::ParamStore;
use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::data::{Dataset, ObservationKind, Pose};
use ssm::evaluation::metrics::aotll;
use ssm::models::observation::OBS_PREFIX;
use ssm::models::observation::{BoxObservationModel, FitConfig, ObsContext, ObservationModel, PointObservationModel};
use ssm::models::params::{AnyObservation, AnyPolicy, Models};
use ssm::models::vehicle::HandCraftedPolicy;
use ssm::simulation::synthetic::{generate_experiment, Experiment, ExperimentConfig, SyntheticExperiment};
use ssm::training::supervised::{
    fit_observation, fit_supervised, labelled_examples, SupervisedConfig, SupervisedError, SupervisedReport,
};

/// The quick synthetic experiment (2 train and 1 test scene, 6 steps) with
/// `objects` objects per scene: point observations with labelled states.
fn quick_data(objects: usize, seed: u64) -> SyntheticExperiment {
    let mut config = ExperimentConfig::quick(Experiment::A);
    config.scene.objects = objects;
    generate_experiment(&config, &mut StdRng::seed_from_u64(seed), &mut |_| {}).expect("quick data")
}

#[test]
fn supervised_point_network_raises_train_and_heldout_aotll() {
    let data = quick_data(10, 1);
    let config = SupervisedConfig {
        fit: FitConfig { steps: 150, batch: 32, lr: 0.01, clip: None, seed: 5 },
        // Not the truth's initialisation: a random network, fitted from scratch.
        init_seed: 77,
    };
    let fitted = fit_supervised::<PointObservationModel>(&data.train, &config).unwrap();
    let r = &fitted.report;
    let cells = data.train.objects().len() * data.train.steps();
    assert!(r.examples > cells / 2 && r.examples <= cells, "{} examples of {cells} cells", r.examples);
    assert_eq!(r.items, data.train.observations().count());
    assert_eq!((r.steps, r.skipped), (150, 0));
    assert!(fitted.params.iter().all(|(n, _)| n.starts_with("obs.")));

    // The report's AOTLLs are the ones the metrics compute on the same data.
    let mut init = ParamStore::new();
    let model = PointObservationModel::init_params(&mut init, OBS_PREFIX, &mut StdRng::seed_from_u64(77));
    let metric_before = aotll(&data.train, &model, &init).mean.unwrap();
    let metric_after = aotll(&data.train, &fitted.model, &fitted.params).mean.unwrap();
    assert!((metric_before - r.initial_aotll).abs() < 1e-9, "{metric_before} vs {}", r.initial_aotll);
    assert!((metric_after - r.final_aotll).abs() < 1e-9, "{metric_after} vs {}", r.final_aotll);

    // Fitting from a random network gains about 1.2 nats per point on the train
    // scenes here. The held-out scene's objects were never seen: that its AOTLL
    // closes most of the gap to the network that generated the points (about 90%
    // here; no network beats the generator on average, up to the sampling noise
    // of ~1,000 points, hence the 0.1 nats of slack) shows the fit generalises.
    let held_before = aotll(&data.test, &model, &init).mean.unwrap();
    let held_after = aotll(&data.test, &fitted.model, &fitted.params).mean.unwrap();
    let held_truth = aotll(&data.test, &data.truth.model.obs, &data.truth.model.params).mean.unwrap();
    assert_fit_generalises("points", r, (held_before, held_after, held_truth), 0.25);
}

/// Prints the AOTLLs of the fit of `kind` that `r` reports and those held out
/// (before and after the fit, and of the generating network), and asserts that the
/// fit gained more than 0.5 nats on the train and the held-out data, that the gap to
/// the generating network shrank below `gap_left` of what it was, and that the fit
/// does not beat the generating network by more than 0.1 nats.
#[track_caller]
fn assert_fit_generalises(
    kind: &str,
    r: &SupervisedReport,
    (held_before, held_after, held_truth): (f64, f64, f64),
    gap_left: f64,
) {
    eprintln!(
        "{kind}: train {:.3} -> {:.3}; held-out {held_before:.3} -> {held_after:.3} (truth {held_truth:.3})",
        r.initial_aotll, r.final_aotll
    );
    assert!(r.final_aotll > r.initial_aotll + 0.5, "train AOTLL {} -> {}", r.initial_aotll, r.final_aotll);
    assert!(held_after > held_before + 0.5, "held-out AOTLL {held_before} -> {held_after}");
    assert!(
        held_truth - held_after < gap_left * (held_truth - held_before),
        "{held_before} -> {held_after} vs {held_truth}"
    );
    assert!(held_after < held_truth + 0.1, "held-out {held_after} beats the generating network {held_truth}");
}

/// The quick experiment's states, AV poses and objects, observed by box
/// detections drawn from `truth` (one per step; every fourth step missing).
fn box_dataset(points: &Dataset, truth: &BoxObservationModel, params: &ParamStore<f64>, seed: u64) -> Dataset {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut b = Dataset::builder(points.meta(), ObservationKind::Boxes);
    b.with_states();
    let states = points.states().unwrap();
    for scene in points.scenes() {
        b.scene(scene.id, &scene.av);
    }
    for (k, o) in points.objects().iter().enumerate() {
        b.object(*o);
        let av = &points.scenes()[points.object_scene(k)].av;
        for (t, av_t) in av.iter().enumerate() {
            let s = *states.get(k, t).unwrap();
            b.state(o.scene, o.id, t, s);
            if (k + t) % 4 == 3 {
                continue;
            }
            let mut det = Vec::new();
            let pose = Pose { x: s.x, y: s.y, yaw: s.yaw };
            truth.sample(params, &ObsContext::of_object(*av_t, o), pose, 1, &mut rng, &mut det);
            b.detection(o.scene, o.id, t, det[0]);
        }
    }
    b.build().unwrap()
}

#[test]
fn supervised_box_network_approaches_the_generating_one() {
    let data = quick_data(30, 2);
    let mut truth_params = ParamStore::new();
    let truth = BoxObservationModel::init_params(&mut truth_params, OBS_PREFIX, &mut StdRng::seed_from_u64(3));
    let train = box_dataset(&data.train, &truth, &truth_params, 10);
    let test = box_dataset(&data.test, &truth, &truth_params, 11);

    // Through `Models` (as a command does): a fresh network beside some policy.
    let policy = AnyPolicy::HandCrafted(HandCraftedPolicy::truth());
    let mut models = Models::initial(ObservationKind::Boxes, policy.clone(), 4);
    let AnyObservation::Boxes(model) = models.observation.clone() else { panic!("a box model") };
    let held_before = aotll(&test, &model, &models.observation_params).mean.unwrap();
    let fit = FitConfig { steps: 300, batch: 64, lr: 0.01, clip: None, seed: 6 };
    let r = fit_observation(&mut models, &train, &fit).unwrap();
    assert_eq!(models.policy, policy, "the policy is untouched");
    assert_eq!(r.items, train.observations().count());
    assert_eq!(r.examples, r.items, "one detection per example");
    let held_after = aotll(&test, &model, &models.observation_params).mean.unwrap();
    let held_truth = aotll(&test, &truth, &truth_params).mean.unwrap();
    // Held out, the fit closes most of the gap to the network that drew the
    // detections (about 85% here; no network beats it on average, 0.1 nats of
    // slack for the sampling noise of ~130 detections).
    assert_fit_generalises("boxes", &r, (held_before, held_after, held_truth), 0.5);
}

#[test]
fn labelled_examples_are_the_observed_labelled_cells() {
    let data = quick_data(5, 3);
    let examples = labelled_examples::<PointObservationModel>(&data.train).unwrap();
    let points = data.train.points().unwrap();
    let nonempty = (0..data.train.objects().len())
        .flat_map(|o| (0..data.train.steps()).map(move |t| (o, t)))
        .filter(|&(o, t)| !points.get(o, t).is_empty())
        .count();
    assert_eq!(examples.len(), nonempty);
    let first = &examples[0];
    let s = data.train.states().unwrap().get(0, 0).unwrap();
    if !points.get(0, 0).is_empty() {
        assert_eq!((first.pose.x, first.pose.y, first.pose.yaw), (s.x, s.y, s.yaw));
        assert_eq!(first.items, points.get(0, 0));
        assert_eq!(first.ctx.av, data.train.scenes()[0].av[0]);
    }
}

#[test]
fn refuses_data_it_cannot_fit() {
    let data = quick_data(3, 4);
    let config = SupervisedConfig::default();
    // Points cannot train a box network.
    let err = fit_supervised::<BoxObservationModel>(&data.train, &config).unwrap_err();
    assert_eq!(err, SupervisedError::Kind { data: ObservationKind::Points, model: ObservationKind::Boxes });
    assert!(err.to_string().contains("Points"));
    // Without states there is nothing to supervise with.
    let mut b = Dataset::builder(data.train.meta(), ObservationKind::Points);
    for scene in data.train.scenes() {
        b.scene(scene.id, &scene.av);
    }
    for o in data.train.objects() {
        b.object(*o);
    }
    for (o, t, p) in data.train.points().unwrap().iter() {
        let obj = data.train.objects()[o];
        b.point(obj.scene, obj.id, t, p);
    }
    let unlabelled = b.build().unwrap();
    let err = fit_supervised::<PointObservationModel>(&unlabelled, &config).unwrap_err();
    assert_eq!(err, SupervisedError::NoStates);
    assert!(err.to_string().contains("states.csv"));
}
