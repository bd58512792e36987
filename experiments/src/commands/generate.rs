//! `sefi generate`: the paper's synthetic datasets (SPEC §4), made by
//! [`ssm::simulation::synthetic::generate_experiment`].
//!
//! Writes into `--out DIR`:
//!
//! * `DIR/train`, `DIR/test`: point datasets with ground-truth `states.csv` and
//!   `actions.csv` (training scene ids `0..10`, test ids `10, 11`);
//! * `DIR/true_params.bin`: the true parameters ([`ssm::simulation::synthetic::TrueModel`]:
//!   the network under `obs.*`, the policy's log sds as `policy.log_sd`);
//! * `DIR/generate.json`: the settings, seed, sizes, the fit's AOTLL (training
//!   examples before/after, held-out generator examples), a summary of each split
//!   (points per object-step, speeds, ranges) and the wall time.
//!
//! The same seed gives byte-identical files; in `generate.json` only the timings
//! (`wall_seconds`, `fit_seconds`) differ between runs.

use std::path::PathBuf;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use rand::rngs::StdRng;
use rand::SeedableRng;
use serde_json::json;
use ssm::models::observation::ObservationModel;
use ssm::simulation::synthetic::{generate_experiment, summarize, Experiment, ExperimentConfig, Progress};

use crate::output::{ensure_dir, write_json};

/// Arguments of `sefi generate`.
#[derive(clap::Args)]
pub struct GenerateArgs {
    /// Experiment: A (25 steps) or B (50 steps).
    #[arg(long, default_value = "A")]
    pub exp: String,
    /// Output directory.
    #[arg(long, default_value = "out/data")]
    pub out: PathBuf,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Small sizes, for tests: 2 training and 1 test scene of 10 objects, 6 steps, a tiny fit.
    #[arg(long)]
    pub quick: bool,
    /// Instead of experiment A/B, one dataset with a hidden effect for `sefi diagnose` to find: none, latency,
    /// clutter, size_bias (points), heavy_tailed_accel, student_t_accel (another tail family) or heading_flip (boxes).
    #[arg(long)]
    pub hidden: Option<String>,
    /// With --hidden: the effect's size as a multiple of its default (see `HiddenEffect::at_strength`).
    #[arg(long, default_value_t = 1.0, requires = "hidden")]
    pub strength: f64,
    /// With --hidden: box detections instead of point sets.
    #[arg(long)]
    pub boxes: bool,
    /// With --hidden: scenes.
    #[arg(long, default_value_t = 8)]
    pub scenes: usize,
    /// With --hidden: objects per scene.
    #[arg(long, default_value_t = 6)]
    pub objects: usize,
    /// With --hidden: steps per scene (T + 1).
    #[arg(long, default_value_t = 16)]
    pub steps: usize,
    /// Instead of experiment A/B: data drawn from a model itself, on the scenes of
    /// this dataset (its AV poses, objects, priors and observation counts), with
    /// ground truth; the parameters are `--params`, or a fresh neural policy and
    /// observation network from `--seed` (written to OUT/true_params.bin).
    #[arg(long)]
    pub like: Option<PathBuf>,
    /// With --like: the parameter file to draw from.
    #[arg(long, requires = "like")]
    pub params: Option<PathBuf>,
}

/// Writes the hidden-effect dataset of `args` into `args.out`.
fn run_hidden(args: &GenerateArgs, effect: &str) -> Result<(), String> {
    use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
    use ssm::data::ObservationKind;
    let effect = HiddenEffect::at_strength(effect, args.strength).map_err(|e| e.to_string())?;
    let kind = if args.boxes { ObservationKind::Boxes } else { ObservationKind::Points };
    let config = HiddenConfig {
        scenes: args.scenes,
        objects_per_scene: args.objects,
        steps: args.steps,
        ..HiddenConfig::quick(kind, effect, args.seed)
    };
    let data = generate_hidden(&config).map_err(|e| e.to_string())?;
    data.write(&args.out).map_err(|e| e.to_string())?;
    println!(
        "wrote {} ({:?}, {} scenes x {} objects, {} steps; hidden effect: {:?})",
        args.out.display(),
        kind,
        args.scenes,
        args.objects,
        args.steps,
        effect
    );
    Ok(())
}

/// Writes data drawn from a model on the scenes of `like` into `args.out`.
fn run_sampled(args: &GenerateArgs, like: &std::path::Path) -> Result<(), String> {
    use autodiff::nn::ParamStore;
    use ssm::models::params::{AnyPolicy, Models};
    use ssm::models::vehicle::NeuralPolicy;
    let skeleton = ssm::data::Dataset::read(like).map_err(|e| format!("dataset {}: {e}", like.display()))?;
    let store = match &args.params {
        Some(p) => ParamStore::<f64>::load(p).map_err(|e| format!("parameter file {}: {e}", p.display()))?,
        None => {
            // The initial sds of a fresh neural policy are those `train` starts from.
            let policy = NeuralPolicy::new(&mut StdRng::seed_from_u64(args.seed));
            Models::initial(skeleton.kind(), AnyPolicy::Neural(policy), args.seed.wrapping_add(1)).to_store()
        }
    };
    let data = ssm::evaluation::calibration::sample_dataset(&skeleton, &store, args.seed)?;
    data.write(&args.out).map_err(|e| e.to_string())?;
    store.save(&args.out.join("true_params.bin")).map_err(|e| e.to_string())?;
    println!(
        "wrote {} ({:?}, {} scenes, {} objects, {} steps, drawn from {}) and its true_params.bin",
        args.out.display(),
        data.kind(),
        data.scenes().len(),
        data.objects().len(),
        data.steps(),
        args.params
            .as_ref()
            .map_or("a fresh neural policy and observation network".into(), |p| p.display().to_string())
    );
    Ok(())
}

/// Runs `sefi generate`.
pub fn run(args: &GenerateArgs) -> Result<(), String> {
    if let Some(effect) = &args.hidden {
        return run_hidden(args, effect);
    }
    if let Some(like) = &args.like {
        return run_sampled(args, like);
    }
    let started = Instant::now();
    let experiment: Experiment =
        args.exp.parse().map_err(|e: ssm::simulation::synthetic::SyntheticError| e.to_string())?;
    let config = if args.quick { ExperimentConfig::quick(experiment) } else { ExperimentConfig::paper(experiment) };
    ensure_dir(&args.out)?;

    let spinner = ProgressBar::new_spinner()
        .with_style(ProgressStyle::with_template("{spinner} {msg} ({elapsed})").expect("valid template"));
    let bar = ProgressBar::hidden();
    let mut fit_started = Instant::now();
    let mut fit_seconds = 0.0;
    let mut rng = StdRng::seed_from_u64(args.seed);
    let data = generate_experiment(&config, &mut rng, &mut |p| match p {
        Progress::FitStarted => {
            fit_started = Instant::now();
            spinner.set_message(format!(
                "fitting the true observation network ({} examples, {} steps)",
                config.truth.examples, config.truth.fit.steps
            ));
            spinner.enable_steady_tick(std::time::Duration::from_millis(120));
        }
        Progress::FitDone => {
            fit_seconds = fit_started.elapsed().as_secs_f64();
            spinner.finish_and_clear();
            bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
            bar.set_length((config.train_scenes + config.test_scenes) as u64);
            bar.set_style(
                ProgressStyle::with_template("simulating scenes [{bar:40}] {pos}/{len}").expect("valid template"),
            );
        }
        Progress::Scene { done, .. } => bar.set_position(done as u64),
    })
    .map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    let truth = &data.truth;
    println!(
        "true observation network: AOTLL {:.3} -> {:.3} nats/point on {} training points, {:.3} on {} held-out \
         points ({} steps, {} skipped, {fit_seconds:.1} s)",
        truth.report.initial_aotll,
        truth.report.final_aotll,
        truth.train_points,
        truth.heldout_aotll,
        truth.heldout_points,
        truth.report.steps,
        truth.report.skipped,
    );

    let (train_dir, test_dir) = (args.out.join("train"), args.out.join("test"));
    data.train.write(&train_dir).map_err(|e| e.to_string())?;
    data.test.write(&test_dir).map_err(|e| e.to_string())?;
    truth.model.save(&args.out.join("true_params.bin")).map_err(|e| e.to_string())?;

    let (train_summary, test_summary) = (summarize(&data.train), summarize(&data.test));
    for (name, s) in [("train", &train_summary), ("test", &test_summary)] {
        println!(
            "{name}: {} scenes x {} objects x {} steps, {} points ({:.1} per object-step, {:.1}% empty), \
             speed {:.1}..{:.1} m/s (mean {:.1}, {} negative), range {:.1}..{:.1} m",
            s.scenes,
            s.objects / s.scenes.max(1),
            s.steps,
            s.points,
            s.points_per_object_step,
            100.0 * s.empty_fraction,
            s.speed_min,
            s.speed_max,
            s.speed_mean,
            s.negative_speeds,
            s.range_min,
            s.range_max,
        );
    }
    let scene = &config.scene;
    let fit = &config.truth;
    let wall_seconds = started.elapsed().as_secs_f64();
    write_json(
        &args.out.join("generate.json"),
        &json!({
            "experiment": experiment.name(),
            "quick": args.quick,
            "seed": args.seed,
            "settings": {
                "steps": scene.steps,
                "transitions": scene.steps - 1,
                "dt": scene.dt,
                "train_scenes": config.train_scenes,
                "test_scenes": config.test_scenes,
                "objects_per_scene": scene.objects,
                "prior_mean_range_m": [scene.range.0, scene.range.1],
                "av": {"start": [0.0, 0.0], "yaw": 0.0, "speed": scene.av_speed},
                "prior_mean_speed": [scene.speed.0, scene.speed.1],
                "prior_mean_max_abs_kappa": scene.max_kappa,
                "length": [scene.length.0, scene.length.1],
                "width": [scene.width.0, scene.width.1],
                "prior_sd": scene.prior_sd,
                "point_count": {"model": "Poisson(min(count_scale / range, max_mean_count))",
                    "count_scale": scene.counts.count_scale, "max_mean_count": scene.counts.max_mean_count},
                "policy": {"log_sd_accel": truth.model.policy.log_sd_accel(),
                    "log_sd_pinch": truth.model.policy.log_sd_pinch()},
                "truth_fit": {
                    "examples": fit.examples,
                    "heldout_examples": fit.heldout,
                    "example_range_m": [fit.ranges.range.0, fit.ranges.range.1],
                    "steps": fit.fit.steps,
                    "batch": fit.fit.batch,
                    "lr": fit.fit.lr,
                },
            },
            "truth": {
                "obs_params": truth.model.obs.num_params(),
                "train_points": truth.train_points,
                "heldout_points": truth.heldout_points,
                "initial_aotll": truth.report.initial_aotll,
                "final_aotll": truth.report.final_aotll,
                "heldout_aotll": truth.heldout_aotll,
                "steps": truth.report.steps,
                "skipped": truth.report.skipped,
            },
            "train": train_summary,
            "test": test_summary,
            "fit_seconds": fit_seconds,
            "wall_seconds": wall_seconds,
        }),
    )?;
    println!("wrote {} in {wall_seconds:.1} s", args.out.display());
    Ok(())
}
