//! `sefi demo`: a quick end-to-end run on built-in generated data.
//!
//! Stage one of the demo exercises the engine: it checks a mixture-density network's
//! gradient against finite differences, then fits it with Adam on the f32 tape and
//! writes the loss curve (CSV + SVG) and a JSON summary.

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
    let (n, steps) = if quick { (512, 150) } else { (8192, 1500) };
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
    write_json(
        &out.join("demo_summary.json"),
        &json!({
            "gradient_check": {"comparisons": check.comparisons, "max_rel_error": check.max_rel_error},
            "points": n, "steps": steps, "seconds": seconds,
            "initial_nll": curve[0][1], "final_nll": final_nll, "skipped_steps": skipped,
        }),
    )?;
    println!("wrote {}", out.display());
    Ok(())
}
