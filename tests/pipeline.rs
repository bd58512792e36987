//! The whole pipeline on generated data: a synthetic experiment is written to disk
//! and read back, filtered and smoothed with the true model, and scored. More
//! particles must give a higher likelihood estimate and better tracks; smoothing
//! must beat filtering; the same seed must give the same numbers.

use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::data::Dataset;
use ssm::evaluation::metrics::{eval_config, evaluate, Metrics};
use ssm::simulation::synthetic::{generate_experiment, Experiment, ExperimentConfig, TrueModel};

fn metrics(data: &Dataset, truth: &TrueModel, particles: usize, seed: u64) -> Metrics {
    let mut cfg = eval_config(4, seed);
    cfg.sampling.particles = particles;
    evaluate(data, &truth.policy, &truth.obs, &truth.params, &cfg).expect("evaluates")
}

#[test]
fn generated_data_round_trips_and_the_true_model_tracks_it() {
    let mut config = ExperimentConfig::quick(Experiment::A);
    config.train_scenes = 0;
    config.test_scenes = 1;
    config.scene.objects = 24;
    config.scene.steps = 16;
    let exp = generate_experiment(&config, &mut StdRng::seed_from_u64(21), &mut |_| {}).expect("generates");

    let dir = std::env::temp_dir().join(format!("pf-sefi-pipeline-{}", std::process::id()));
    exp.test.write(&dir).expect("writes");
    let data = Dataset::read(&dir).expect("reads back");
    assert_eq!(data, exp.test);
    std::fs::remove_dir_all(&dir).ok();

    let truth = &exp.truth.model;
    let few = metrics(&data, truth, 32, 1);
    let many = metrics(&data, truth, 1024, 1);
    let (mll_few, mll_many) = (few.mll.unwrap(), many.mll.unwrap());
    // l_hat is biased low by about half its variance, which shrinks with N: at 32
    // particles and ~10 sharp points per step the gap is several nats per point.
    assert!(mll_many > mll_few + 0.5, "MLL {mll_few} (N=32) vs {mll_many} (N=1024)");
    let (ade_s, ade_f) = (many.smoothed.ade.unwrap(), many.filtered.ade.unwrap());
    assert!(ade_s < ade_f, "smoothed ADE {ade_s} must beat filtered {ade_f}");
    assert!(ade_s < 0.5, "smoothed ADE {ade_s} m with the true model");
    assert!(few.smoothed.ade.unwrap() > ade_s, "32 particles track worse than 1024");
    assert_eq!(many.collapsed_steps, 0);
    // Reproducible: same seed, same numbers.
    assert_eq!(metrics(&data, truth, 1024, 1).mll, many.mll);
}
