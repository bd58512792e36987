//! A catalogue extension learned with the model (`ext.<id>` in a parameter
//! file, [`FittedExtension`]): its stored values invert its natural ones, a store
//! holding it is read back whole and a malformed one is refused by name, the
//! AOTLL under it is the extended model's density at the labels, and the
//! supervised fit observes reversed headings in the labels.

use autodiff::nn::ParamStore;
use autodiff::Tensor;
use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
use ssm::data::{Dataset, ObservationKind};
use ssm::metrics::{aotll, extended_aotll, labelled_steps, model_aotll};
use ssm::models::extended::{ExtendedSsm, Extension};
use ssm::models::observation::{BoxObservationModel, FitConfig, ObservationModel, PointObservationModel};
use ssm::models::params::{AnyObservation, AnyPolicy, FittedExtension, Models, OBS_PREFIX};
use ssm::models::road_user::VehicleSsm;
use ssm::models::vehicle::HandCraftedPolicy;
use ssm::supervised::fit_observation_with_flips;

fn hidden_boxes(effect: HiddenEffect, seed: u64) -> Dataset {
    generate_hidden(&HiddenConfig { scenes: 4, ..HiddenConfig::quick(ObservationKind::Boxes, effect, seed) }).unwrap()
}

fn flips(strength: f64) -> HiddenEffect {
    HiddenEffect::at_strength("heading_flip", strength).unwrap()
}

/// Detections whose heading points away from the label's, counted with cosines
/// (independently of the wrapped-angle rule the library uses).
fn reversed_share(data: &Dataset) -> f64 {
    let (mut reversed, mut all) = (0usize, 0usize);
    for (_, pose, items) in labelled_steps::<BoxObservationModel>(data, data.states().unwrap()) {
        for d in items {
            all += 1;
            reversed += usize::from((d.yaw - pose.yaw).cos() < 0.0);
        }
    }
    reversed as f64 / all as f64
}

#[test]
fn stored_values_invert_natural_ones_and_refuse_values_out_of_range() {
    let cases: [(Extension, &[f64]); 5] = [
        (Extension::Latency, &[0.137]),
        (Extension::Clutter, &[0.08, 1.7]),
        (Extension::SizeBias, &[0.9, 1.25]),
        (Extension::HeavyTailedAccel, &[0.05, 6.0]),
        (Extension::HeadingFlip, &[0.033]),
    ];
    for (e, natural) in cases {
        let raw = e.stored(natural).unwrap();
        let back: Vec<f64> = e.natural(&raw).unwrap().iter().map(|v| v.1).collect();
        for (a, b) in natural.iter().zip(&back) {
            assert!((a - b).abs() < 1e-12 * a.abs().max(1.0), "{}: {natural:?} -> {back:?}", e.id());
        }
    }
    assert!(Extension::HeadingFlip.stored(&[0.0]).is_err(), "a fraction of zero has no stored value");
    assert!(Extension::HeadingFlip.stored(&[1.0]).is_err());
    assert!(Extension::HeavyTailedAccel.stored(&[0.05, 1.0]).is_err(), "an sd ratio must exceed 1");
    assert!(Extension::Clutter.stored(&[0.05]).is_err(), "two values");
}

#[test]
fn a_store_holds_one_extension_for_its_data_kind_and_is_read_back_whole() {
    let mut store = ParamStore::new();
    AnyPolicy::HandCrafted(HandCraftedPolicy::truth()).add_to_store(&mut store);
    BoxObservationModel::init_params(&mut store, OBS_PREFIX, &mut StdRng::seed_from_u64(1));
    let flip = Extension::HeadingFlip;
    let raw = flip.stored(&[0.05]).unwrap();
    let with = |name: &str, value: Vec<f64>| {
        let mut s = store.clone();
        s.add(name, Tensor::from_vec(value));
        s
    };
    let good = with(&flip.param_name(), raw.clone());
    let models = Models::from_store(&good, ObservationKind::Boxes).unwrap();
    assert_eq!(models.extension, Some(FittedExtension { extension: flip, raw: raw.clone() }));
    let again = Models::from_store(&models.to_store(), ObservationKind::Boxes).unwrap();
    assert_eq!(again.extension, models.extension, "to_store keeps the extension");
    assert_eq!(Models::from_store(&store, ObservationKind::Boxes).unwrap().extension, None);

    let refused = |s: &ParamStore<f64>, kind: ObservationKind, says: &str| {
        let err = Models::from_store(s, kind).map(|_| ()).unwrap_err().to_string();
        assert!(err.contains(says), "expected `{says}` in: {err}");
    };
    refused(&with("ext.sensor_noise", vec![0.0]), ObservationKind::Boxes, "ext.sensor_noise");
    refused(&with(&flip.param_name(), vec![0.0, 1.0]), ObservationKind::Boxes, "ext.heading_flip");
    refused(&with(&flip.param_name(), vec![f64::NAN]), ObservationKind::Boxes, "ext.heading_flip");
    let mut two = good.clone();
    two.add(&Extension::Latency.param_name(), Extension::Latency.initial());
    refused(&two, ObservationKind::Boxes, "at most one extension");
    let mut points = ParamStore::new();
    AnyPolicy::HandCrafted(HandCraftedPolicy::truth()).add_to_store(&mut points);
    PointObservationModel::init_params(&mut points, OBS_PREFIX, &mut StdRng::seed_from_u64(1));
    points.add(&flip.param_name(), Tensor::from_vec(raw));
    refused(&points, ObservationKind::Points, "Points");
}

/// Without an extension the filter's own density at the labels gives the AOTLL
/// of the plain path (f32 against f64); with reversed headings it is the
/// mixture `(1 - p) g(d) + p g(d reversed)` computed here from the plain density.
#[test]
fn the_aotll_under_an_extension_is_the_extended_density_at_the_labels() {
    for (strength, seed) in [(0.5, 1), (1.5, 2)] {
        let data = hidden_boxes(flips(strength), seed);
        let mut params = ParamStore::new();
        let obs = BoxObservationModel::init_params(&mut params, OBS_PREFIX, &mut StdRng::seed_from_u64(seed));
        let policy = AnyPolicy::HandCrafted(HandCraftedPolicy::truth());
        let base = VehicleSsm::new(&data, &policy, &obs, &params).unwrap();
        let plain = aotll(&data, &obs, &params);
        let of_filter = model_aotll(&data, &ExtendedSsm::new(&base, None, &[]).unwrap());
        assert_eq!(plain.count, of_filter.count);
        let (a, b) = (plain.mean.unwrap(), of_filter.mean.unwrap());
        assert!((a - b).abs() < 1e-4 * a.abs().max(1.0), "strength {strength}: {a} vs {b}");

        let p = 0.15;
        let flip =
            FittedExtension { extension: Extension::HeadingFlip, raw: Extension::HeadingFlip.stored(&[p]).unwrap() };
        let mixed = extended_aotll(&data, &policy, &obs, &params, Some(&flip));
        let (mut sum, mut n) = (0.0, 0usize);
        for (ctx, pose, items) in labelled_steps::<BoxObservationModel>(&data, data.states().unwrap()) {
            let d = obs.distribution(&params, &ctx, pose);
            for det in items {
                let reversed = ssm::data::BoxDetection { yaw: det.yaw + std::f64::consts::PI, ..*det };
                let (g, r) = (
                    d.log_density_terms(&ctx.av, pose, det).total(),
                    d.log_density_terms(&ctx.av, pose, &reversed).total(),
                );
                sum += ((1.0 - p) * g.exp() + p * r.exp()).ln();
                n += 1;
            }
        }
        assert_eq!(mixed.count, n);
        let (want, got) = (sum / n as f64, mixed.mean.unwrap());
        assert!((want - got).abs() < 1e-4 * want.abs().max(1.0), "strength {strength}: mixture {want} vs {got}");
        assert!(got > a, "the mixture scores the reversed detections: {got} vs plain {a}");
    }
}

/// The supervised fit with reversed headings: the fraction is the share of
/// detections reversed against their labels (recounted here with cosines) and
/// close to the hidden share; the network fits the turned-back detections, so
/// its plain density of reversed detections is poor while the mixture's is not.
#[test]
fn the_supervised_fit_observes_reversed_headings_in_the_labels() {
    for (strength, seed) in [(0.5, 3), (1.5, 4)] {
        let data = hidden_boxes(flips(strength), seed);
        let policy = AnyPolicy::HandCrafted(HandCraftedPolicy::truth());
        let mut models = Models::initial(ObservationKind::Boxes, policy, seed);
        let fit = FitConfig { steps: 300, batch: 64, lr: 0.01, clip: None, seed };
        let report = fit_observation_with_flips(&mut models, &data, &fit).unwrap();
        assert!(report.final_aotll > report.initial_aotll);
        let e = models.extension.clone().expect("heading_flip set");
        assert_eq!(e.extension, Extension::HeadingFlip);
        let fraction = e.extension.natural(&e.raw).unwrap()[0].1;
        let share = reversed_share(&data);
        assert!((fraction - share).abs() < 1e-12, "strength {strength}: fraction {fraction}, recounted {share}");
        assert!((fraction - 0.2 * strength).abs() < 0.06, "strength {strength}: {fraction}");
        let AnyObservation::Boxes(obs) = &models.observation else { panic!("a box model") };
        let plain = aotll(&data, obs, &models.observation_params).mean.unwrap();
        let mixed = extended_aotll(&data, &models.policy, obs, &models.observation_params, Some(&e)).mean.unwrap();
        assert!(mixed > plain + 1.0, "strength {strength}: mixture {mixed} vs plain {plain}");
    }
    // Without reversed detections there is no fraction to fit.
    let none = hidden_boxes(HiddenEffect::None, 5);
    let mut models = Models::initial(ObservationKind::Boxes, AnyPolicy::HandCrafted(HandCraftedPolicy::truth()), 5);
    let fit = FitConfig { steps: 10, batch: 64, lr: 0.01, clip: None, seed: 5 };
    assert_eq!(reversed_share(&none), 0.0, "the generator's own yaw noise reverses none here");
    let err = fit_observation_with_flips(&mut models, &none, &fit).unwrap_err();
    assert!(err.contains("nothing to fit"), "{err}");
}
