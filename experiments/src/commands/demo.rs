//! `sefi demo`: a quick end-to-end run on built-in generated data.
//!
//! 1. The engine: a mixture-density network's gradient is checked against finite
//!    differences, then the network is fitted with Adam on the f32 tape (loss curve
//!    as CSV + SVG).
//! 2. The model: a small synthetic experiment is generated as the paper's (true
//!    point network fitted to a physical generator, hand-crafted policy, exact
//!    motion); its test scene is filtered and smoothed with the true model at
//!    several particle counts, and the metrics (MLL, ADE, AYE, AOTLL, APTLL) are
//!    written with a bird's-eye plot of the scene.
//! 3. Learning: the policy's sds and the observation network are learned from
//!    the experiment's observations alone, by PF-SEFI (on the tempered filter)
//!    and by the PF baseline (through the bootstrap filter), from the same start;
//!    their test MLL against training step is plotted beside TRUE's.
//! 4. Criticism: a small dataset with a hidden sensor lag is diagnosed
//!    ([`ssm::criticism::diagnose`]), and what it found is printed.

use std::path::Path;
use std::time::Instant;

use autodiff::dist::{mixture_logpdf, normal_logpdf};
use autodiff::gradcheck::GradCheck;
use autodiff::nn::{Activation, BoundParams, Mlp, ParamStore};
use autodiff::optim::{clip_global_norm, Adam};
use autodiff::{Float, Tape, Tensor, Var};
use indicatif::{ProgressBar, ProgressStyle};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde_json::json;

use ssm::criticism::diagnose::{diagnose, DiagnoseConfig};
use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
use ssm::data::{Dataset, ObservationKind};
use ssm::evaluation::metrics::{metrics_of, track, Metrics};
use ssm::filter::{FilterConfig, FilterPurpose, Sampling, Tempering};
use ssm::models::params::{ModelAdditions, Models};
use ssm::simulation::synthetic::{generate_experiment, Experiment, ExperimentConfig, SyntheticExperiment, TruthConfig};

use crate::args::{FilterArgs, FilterKind};
use crate::birdseye;
use crate::cluster::Cluster;
use crate::commands::evaluate::metric_runs;
use crate::commands::train::{read_eval_curve, train_run, TrainArgs};
use crate::output::{ensure_dir, write_csv, write_json};
use crate::plot::{line_chart, Series};

const COMPONENTS: usize = 2;

/// Negative mean log-likelihood of `y` under the network's Gaussian mixture.
fn mixture_nll<'t, F: Float>(mlp: &Mlp, p: &BoundParams<'t, F>, x: Var<'t, F>, y: Var<'t, F>) -> Var<'t, F> {
    let out = mlp.forward(p, x);
    let logits = out.slice(1, 0, COMPONENTS);
    let mu = out.slice(1, COMPONENTS, COMPONENTS);
    let log_sd = out.slice(1, 2 * COMPONENTS, COMPONENTS);
    mixture_logpdf(logits, normal_logpdf(y, mu, log_sd), 1).mean().neg()
}

/// A bimodal regression: y = ±sin(3x) + noise, the sign a fair coin.
fn generate(rng: &mut StdRng, n: usize) -> (Tensor<f64>, Tensor<f64>) {
    let x: Vec<f64> = (0..n).map(|_| rng.random_range(-1.5..1.5)).collect();
    let y: Vec<f64> = x
        .iter()
        .map(|&x| {
            let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
            sign * (3.0 * x).sin() + 0.1 * (rng.random::<f64>() - 0.5)
        })
        .collect();
    (Tensor::new(&[n, 1], x), Tensor::new(&[n, 1], y))
}

/// Runs the demo, writing into `out`.
pub fn run(out: &Path, seed: u64, quick: bool) -> Result<(), String> {
    ensure_dir(out)?;
    let mut rng = StdRng::seed_from_u64(seed);
    let (n, steps) = if quick { (512, 150) } else { (4096, 600) };
    let mut store = ParamStore::<f64>::new();
    let mlp =
        Mlp::new(&mut store, "mdn", &[1, 32, 32, 3 * COMPONENTS], Activation::Tanh, Activation::Identity, &mut rng);
    let (x, y) = generate(&mut rng, n);

    // 1. The engine's gradient of this model agrees with finite differences (f64).
    let (xs, ys) = (x.clone().reshape(&[n, 1]), y.clone());
    let small = |t: &Tensor<f64>| Tensor::new(&[32, 1], t.data()[..32].to_vec());
    let (xc, yc) = (small(&xs), small(&ys));
    let check = GradCheck::default()
        .check_params(&store, |tape, p| mixture_nll(&mlp, p, tape.constant(xc.clone()), tape.constant(yc.clone())))
        .map_err(|e| e.to_string())?;
    println!("gradient check: {} comparisons, max relative error {:.2e}", check.comparisons, check.max_rel_error);

    // 2. Fit on the f32 tape with Adam and global-norm clipping.
    let (x32, y32) = (x.cast::<f32>(), y.cast::<f32>());
    let mut adam = Adam::new(0.01);
    let mut tape = Tape::<f32>::new();
    let bar = ProgressBar::new(steps as u64)
        .with_style(ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} ({eta})").expect("valid template"));
    bar.set_message("fitting");
    let started = Instant::now();
    let mut curve = Vec::with_capacity(steps);
    let mut skipped = 0usize;
    for step in 0..steps {
        tape.reset();
        let params32 = store.cast::<f32>();
        let (loss, grads) = {
            let p = params32.bind(&tape);
            let loss = mixture_nll(&mlp, &p, tape.constant(x32.clone()), tape.constant(y32.clone()));
            let g = p.gradients(&tape.backward(loss));
            (loss.item() as f64, g)
        };
        let mut grads: Vec<Tensor<f64>> = grads.iter().map(|g| g.cast()).collect();
        clip_global_norm(&mut grads, 5.0);
        if adam.step(&mut store, &grads).is_err() {
            skipped += 1;
        }
        curve.push(vec![step as f64, loss]);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    let final_nll = curve.last().map(|r| r[1]).unwrap_or(f64::NAN);
    println!(
        "fitted a {}-parameter mixture density network on {n} points in {steps} steps ({seconds:.2} s): \
         NLL {:.3} -> {:.3} nats/point ({skipped} steps skipped)",
        store.num_scalars(),
        curve[0][1],
        final_nll
    );

    write_csv(&out.join("demo_loss.csv"), &["step", "nll"], &curve)?;
    let series = [Series { name: "training NLL".into(), points: curve.iter().map(|r| (r[0], r[1])).collect() }];
    line_chart(&out.join("demo_loss.svg"), "Mixture density network fit", "step", "NLL (nats/point)", &series)?;
    let (model, experiment) = model_stage(out, seed, quick)?;
    let learning = learning_stage(out, &experiment, seed, quick)?;
    let criticism = criticism_stage(out, seed, quick)?;
    write_json(
        &out.join("demo_summary.json"),
        &json!({
            "engine": {
                "gradient_check": {"comparisons": check.comparisons, "max_rel_error": check.max_rel_error},
                "points": n, "steps": steps, "seconds": seconds,
                "initial_nll": curve[0][1], "final_nll": final_nll, "skipped_steps": skipped,
            },
            "model": model,
            "learning": learning,
            "criticism": criticism,
        }),
    )?;
    println!("wrote {}", out.display());
    Ok(())
}

/// Generates a small synthetic experiment, filters its test scene with the true model
/// at increasing particle counts and writes metrics and a bird's-eye plot; returns
/// them with the experiment (its training scenes serve the learning stage).
fn model_stage(out: &Path, seed: u64, quick: bool) -> Result<(serde_json::Value, SyntheticExperiment), String> {
    let mut config = ExperimentConfig::quick(Experiment::A);
    config.train_scenes = if quick { 1 } else { LEARNING_SCENES };
    config.test_scenes = 1;
    if !quick {
        config.truth = TruthConfig::paper();
        config.scene.objects = 20;
        config.scene.steps = Experiment::A.transitions() + 1;
    }
    let started = Instant::now();
    let mut rng = StdRng::seed_from_u64(seed);
    let experiment = generate_experiment(&config, &mut rng, &mut |_| {}).map_err(|e| e.to_string())?;
    let (data, truth) = (&experiment.test, &experiment.truth.model);
    println!(
        "generated a test scene: {} objects, {} steps, {} points (true network held-out AOTLL {:.3} nats/point) in {:.1} s",
        data.objects().len(),
        data.steps(),
        data.points().map(|p| p.len()).unwrap_or(0),
        experiment.truth.heldout_aotll,
        started.elapsed().as_secs_f64()
    );
    let particle_counts: &[usize] = if quick { &[64, 512] } else { &[64, 512, 4096] };
    let mut rows = Vec::new();
    let mut last = None;
    println!(
        "{:>9} {:>10} {:>13} {:>13} {:>13} {:>13} {:>8}",
        "particles", "MLL", "ADE smooth", "ADE filter", "AYE smooth", "AYE filter", "seconds"
    );
    for &particles in particle_counts {
        let mut cfg = ssm::evaluation::metrics::eval_config(ssm::evaluation::metrics::EVAL_LAG, seed);
        cfg.sampling.particles = particles;
        let t = Instant::now();
        let tracks = track(data, &truth.policy, &truth.obs, &truth.params, ModelAdditions::NONE, &cfg)?;
        let m: Metrics =
            metrics_of(data, &tracks, &truth.policy, &truth.obs, &truth.params, ModelAdditions::NONE, &cfg);
        let secs = t.elapsed().as_secs_f64();
        let f = |v: Option<f64>| v.unwrap_or(f64::NAN);
        println!(
            "{particles:>9} {:>10.4} {:>11.3} m {:>11.3} m {:>9.4} rad {:>9.4} rad {secs:>8.2}",
            f(m.mll),
            f(m.smoothed.ade),
            f(m.filtered.ade),
            f(m.smoothed.aye),
            f(m.filtered.aye)
        );
        rows.push(vec![
            particles as f64,
            f(m.mll),
            f(m.smoothed.ade),
            f(m.filtered.ade),
            f(m.smoothed.aye),
            f(m.filtered.aye),
            f(m.aotll.mean),
            f(m.aptll.mean),
            secs,
        ]);
        last = Some((tracks, m, cfg.lag));
    }
    let header = [
        "particles",
        "mll",
        "ade_smoothed",
        "ade_filtered",
        "aye_smoothed",
        "aye_filtered",
        "aotll",
        "aptll",
        "seconds",
    ];
    write_csv(&out.join("demo_metrics.csv"), &header, &rows)?;
    let (tracks, metrics, lag) = last.expect("at least one particle count");
    let plot = out.join("demo_birdseye.svg");
    birdseye::draw(&plot, data, 0, &tracks, lag)?;
    println!(
        "at the true parameters: AOTLL {:.3} nats/point, APTLL {:.3} nats/step; bird's-eye view in {}",
        metrics.aotll.mean.unwrap_or(f64::NAN),
        metrics.aptll.mean.unwrap_or(f64::NAN),
        plot.display()
    );
    let summary = json!({
        "objects": data.objects().len(),
        "steps": data.steps(),
        "heldout_aotll_true_network": experiment.truth.heldout_aotll,
        "metrics_by_particles": rows.iter().map(|r| header.iter().zip(r).map(|(h, v)| (h.to_string(), json!(v))).collect::<serde_json::Map<_, _>>()).collect::<Vec<_>>(),
    });
    Ok((summary, experiment))
}

/// Training scenes of the learning stage (of 20 objects each, besides the test scene).
const LEARNING_SCENES: usize = 4;

/// The methods the learning stage trains: `(name, estimator, training filter)`.
const LEARNING_METHODS: [(&str, &str, FilterKind); 2] =
    [("pf-sefi", "pf-sefi", FilterKind::Tempered), ("pf", "pf", FilterKind::Bootstrap)];

/// Learns the experiment's policy sds and observation network from its training
/// scenes' observations alone, by PF-SEFI and by the PF baseline from the same
/// start (hand-crafted policy at sds 1.0 and 0.1, a fresh network), and plots
/// their test MLL against training step beside TRUE's (`demo_learning.svg`).
fn learning_stage(
    out: &Path,
    experiment: &SyntheticExperiment,
    seed: u64,
    quick: bool,
) -> Result<serde_json::Value, String> {
    let dir = out.join("learning");
    let _ = std::fs::remove_dir_all(&dir);
    let (train_dir, test_dir) = (dir.join("data/train"), dir.join("data/test"));
    experiment.train.write(&train_dir).map_err(|e| e.to_string())?;
    experiment.test.write(&test_dir).map_err(|e| e.to_string())?;
    let (particles, eval_particles, epochs, eval_every) = if quick { (32, 64, 2, 1) } else { (256, 1024, 12, 8) };
    // TRUE, evaluated as every run's test MLL is: the tempered filter at `eval_particles`.
    let truth =
        Models::from_store(&experiment.truth.model.params, ObservationKind::Points).map_err(|e| e.to_string())?;
    let eval_filter = FilterConfig::new(
        Sampling::new(
            eval_particles,
            Some(Tempering::for_observations(ObservationKind::Points, FilterPurpose::Evaluation)),
        ),
        0,
        seed.wrapping_add(7),
    );
    let true_mll = metric_runs(&experiment.test, &truth, &eval_filter, 1)?[0].mll.unwrap_or(f64::NAN);
    println!(
        "learning from observations alone ({} training scenes of {} objects; TRUE test MLL {true_mll:.3} nats/point):",
        experiment.train.scenes().len(),
        experiment.train.objects().len() / experiment.train.scenes().len().max(1)
    );
    let mut series = Vec::new();
    let mut methods = Vec::new();
    for (name, estimator, filter) in LEARNING_METHODS {
        // The command line's defaults (hand-crafted policy from sds 1.0 and 0.1,
        // PF-SEFI's lag 8, the tempered evaluation filter) at a small scale.
        let defaults = TrainArgs::with_defaults(train_dir.clone(), test_dir.clone(), dir.join(name));
        let args = TrainArgs {
            estimator: estimator.into(),
            filter: FilterArgs { filter, ..defaults.filter.clone() },
            particles,
            eval_particles,
            epochs,
            lr: 0.02,
            eval_every,
            checkpoint_every: eval_every,
            seed,
            ..defaults
        };
        let bar = crate::commands::train::bar(name);
        let outcome = train_run(&args, &bar, &Cluster::single())?;
        bar.finish_and_clear();
        let curve = read_eval_curve(&args.out, "test_mll")?;
        let sds = (read_eval_curve(&args.out, "sd_accel")?, read_eval_curve(&args.out, "sd_pinch")?);
        let (first, last) = (curve.first().map_or(f64::NAN, |p| p.1), curve.last().map_or(f64::NAN, |p| p.1));
        let learned = (sds.0.last().map_or(f64::NAN, |p| p.1), sds.1.last().map_or(f64::NAN, |p| p.1));
        println!(
            "  {name:<8} test MLL {first:.3} -> {last:.3} in {} steps ({:.1} s); policy sds {:.3}, {:.4} (true {:.3}, {:.4})",
            outcome.steps,
            outcome.seconds,
            learned.0,
            learned.1,
            experiment.truth.model.policy.log_sd_accel().exp(),
            experiment.truth.model.policy.log_sd_pinch().exp(),
        );
        methods.push(json!({
            "method": name, "steps": outcome.steps, "seconds": outcome.seconds, "skipped_steps": outcome.skipped_steps,
            "test_mll": curve, "learned_sds": [learned.0, learned.1],
        }));
        series.push(Series { name: name.to_string(), points: curve });
    }
    let span = series.iter().flat_map(|s| s.points.iter().map(|p| p.0)).fold(0.0, f64::max);
    series.push(Series { name: "TRUE".into(), points: vec![(0.0, true_mll), (span, true_mll)] });
    let plot = out.join("demo_learning.svg");
    line_chart(&plot, "Learning from observations alone", "training step", "test MLL (nats/point)", &series)?;
    println!("  curves: {}", plot.display());
    Ok(json!({ "true_test_mll": true_mll, "methods": methods }))
}

/// Generates a small point dataset with a hidden sensor lag (observations of the
/// pose 0.15 s ago) and diagnoses it, told nothing but the data.
fn criticism_stage(out: &Path, seed: u64, quick: bool) -> Result<serde_json::Value, String> {
    let dir = out.join("criticism");
    let _ = std::fs::remove_dir_all(&dir);
    let effect = HiddenEffect::at_strength("latency", 1.0).map_err(|e| e.to_string())?;
    let mut hidden = HiddenConfig::quick(ObservationKind::Points, effect, seed);
    let config = if quick {
        hidden.scenes = 3;
        hidden.steps = 6;
        DiagnoseConfig {
            base_steps: 4,
            candidate_steps: 2,
            particles: 32,
            eval_particles: 64,
            draws: 5,
            permutations: 99,
            seed,
            ..DiagnoseConfig::quick()
        }
    } else {
        // The quick scale with shorter fits, so that the whole demo stays within a
        // few minutes; `sefi diagnose --quick` runs the full quick scale.
        DiagnoseConfig { base_steps: 150, candidate_steps: 60, seed, ..DiagnoseConfig::quick() }
    };
    let data: Dataset = generate_hidden(&hidden).map_err(|e| e.to_string())?;
    let data_dir = dir.join("data");
    data.write(&data_dir).map_err(|e| e.to_string())?;
    println!(
        "criticising {} objects of point data with a hidden sensor lag of 0.15 s (the diagnosis is told nothing of it):",
        data.objects().len()
    );
    let bar = crate::commands::train::bar("diagnose");
    let report = diagnose(
        &data,
        &config,
        &dir.join("runs"),
        &Cluster::single().collective(),
        &mut crate::commands::diagnose::stage_progress(&bar),
    )?;
    bar.finish_and_clear();
    crate::commands::diagnose::write_report(&dir, &report, &data_dir)?;
    crate::commands::diagnose::print_outcome(&report, &dir);
    Ok(json!({
        "hidden": "latency 0.15 s", "cause": report.cause, "finding": report.finding,
        "gain": report.gain, "gain_se": report.gain_se, "gain_p": report.gain_p, "seconds": report.seconds,
    }))
}
