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

use ssm::metrics::{metrics_of, track, Metrics};
use ssm::synthetic::{generate_experiment, Experiment, ExperimentConfig, TruthConfig};

use crate::birdseye;
use crate::output::{ensure_dir, write_csv, write_json, write_with};
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
    write_with(&out.join("demo_loss.svg"), |p| {
        line_chart(p, "Mixture density network fit", "step", "NLL (nats/point)", &series)
    })?;
    let model = model_stage(out, seed, quick)?;
    write_json(
        &out.join("demo_summary.json"),
        &json!({
            "engine": {
                "gradient_check": {"comparisons": check.comparisons, "max_rel_error": check.max_rel_error},
                "points": n, "steps": steps, "seconds": seconds,
                "initial_nll": curve[0][1], "final_nll": final_nll, "skipped_steps": skipped,
            },
            "model": model,
        }),
    )?;
    println!("wrote {}", out.display());
    Ok(())
}

/// Generates a small synthetic experiment, filters its test scene with the true model
/// at increasing particle counts and writes metrics and a bird's-eye plot.
fn model_stage(out: &Path, seed: u64, quick: bool) -> Result<serde_json::Value, String> {
    let mut config = ExperimentConfig::quick(Experiment::A);
    config.train_scenes = 0;
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
        let mut cfg = ssm::metrics::eval_config(ssm::metrics::EVAL_LAG, seed);
        cfg.particles = particles;
        let t = Instant::now();
        let tracks = track(data, &truth.policy, &truth.obs, &truth.params, &cfg)?;
        let m: Metrics = metrics_of(data, &tracks, &truth.policy, &truth.obs, &truth.params, &cfg);
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
    write_with(&plot, |p| birdseye::draw(p, data, 0, &tracks, lag))?;
    println!(
        "at the true parameters: AOTLL {:.3} nats/point, APTLL {:.3} nats/step; bird's-eye view in {}",
        metrics.aotll.mean.unwrap_or(f64::NAN),
        metrics.aptll.mean.unwrap_or(f64::NAN),
        plot.display()
    );
    Ok(json!({
        "objects": data.objects().len(),
        "steps": data.steps(),
        "heldout_aotll_true_network": experiment.truth.heldout_aotll,
        "metrics_by_particles": rows.iter().map(|r| header.iter().zip(r).map(|(h, v)| (h.to_string(), json!(v))).collect::<serde_json::Map<_, _>>()).collect::<Vec<_>>(),
    }))
}
