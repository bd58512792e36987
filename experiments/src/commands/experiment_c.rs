//! `sefi experiment-c`: the paper's experiment C on the real KITTI tracking data.
//!
//! 1. Imports the KITTI sequences (default `../shared/data/kitti-tracking`) into
//!    `OUT/data/train` (AB3DMOT's train sequences) and `OUT/data/val` (its val
//!    sequences) with the importer's defaults — 20-step windows at dt = 0.1 s
//!    (`--steps`, `--stride` change them), box detections, labelled states — or
//!    reuses an earlier import there (if it has those windows).
//! 2. Trains PF-SEFI (L = 15), DPF-SGR, PFNET (alpha = 0.8) and PF with the neural
//!    policy and the box-detection observation network, Adam (lr 0.01) with global
//!    gradient-norm clipping at 0.5 (SPEC §6 for measured data), all from the same
//!    initialisation, each in `OUT/runs/<method>` (a `sefi train` directory; an
//!    interrupted experiment resumes every unfinished run from its checkpoint).
//!    The test MLL during training is measured on val.
//! 3. Fits the **supervised** observation network: the same network, from the same
//!    initial weights, fitted by maximum AOTLL to the labelled train states
//!    ([`ssm::training::supervised`]). It is paired with the policy PF-SEFI learned (the
//!    first trained method's if PF-SEFI is not run), so that its MLL, ADE and AYE
//!    can be measured too; the comparison the paper makes is the AOTLL.
//!    Written to `OUT/supervised/params.bin`.
//! 4. Evaluates on val the untrained initial model (INIT), every learned model
//!    and the supervised one — MLL, AOTLL, APTLL, smoothed (lag L) and filtered ADE
//!    and AYE, median and IQR over repeated filter runs with common seeds — and
//!    writes `OUT/table.md`, `OUT/table.csv`, `OUT/curves.svg` (test MLL against
//!    training step) and `OUT/experiment_c.json` (everything, per run).
//!
//! **Scenes per step.** The importer cuts each labelled track into its own
//! 20-step windows, so a KITTI scene holds about one object (664 objects in 554
//! train scenes) where a synthetic scene holds 100. One scene per step (SPEC §6)
//! would make each step's score an average over ~19 detections of one car: very
//! noisy, and dominated by per-step overhead. The default takes 16 scenes per
//! step (~19 objects, ~330 detections): the per-detection score is averaged over
//! enough cars for clipped Adam to make steady progress, while an epoch still
//! has 35 steps, so a run takes several hundred optimiser steps within the time
//! budget. `--scenes-per-step` changes it.
//!
//! Scales:
//!
//! * `--quick`: 12 train and 6 val scenes, 32 / 64 particles, 2 epochs — about a
//!   second after the import; for tests.
//! * the default: all scenes, 1,024 training and 4,096 evaluation particles, 20
//!   epochs (700 steps per run), 3 evaluation runs. Measured on the 2-core
//!   machine (while shared): a step of 16 scenes takes about 0.2 s for PF-SEFI,
//!   0.4 s for DPF-SGR and 0.65–0.7 s for PFNET and PF, a val evaluation at 4,096
//!   particles about 6 s, so the four methods with their evaluations take roughly
//!   half an hour.
//! * `--paper`: the paper's protocol for KITTI: 4,096 training and evaluation
//!   particles, L = 15, gradient clipping 0.5, 15 epochs (525 steps of 16 scenes).
//!
//! `--particles`, `--eval-particles`, `--epochs`, `--scenes-per-step` and `--runs`
//! override a scale's value.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use autodiff::nn::ParamStore;
use serde::Serialize;
use serde_json::json;
use ssm::data::kitti::KITTI_FRAME_DT;
use ssm::data::{Dataset, KittiOptions, ObservationKind};
use ssm::evaluation::metrics::{BoxAotllTerms, Metrics};
use ssm::filter::{FilterConfig, Sampling};
use ssm::models::drift::{drift_from_labels, DetectorDrift};
use ssm::models::extended::Extension;
use ssm::models::observation::boxes::DetectionOffsets;
use ssm::models::observation::{BoxObservationModel, FitConfig};
use ssm::models::params::{FittedExtension, Models};
use ssm::stats::Summary;
use ssm::training::supervised::{fit_observation, fit_observation_with_flips, SupervisedReport};
use ssm::training::{PARAMS_FILE, SKIP_LOG, TRAIN_LOG};

use crate::args::check_method;
use crate::cluster::Cluster;
use crate::commands::evaluate::{aotll_by_part_table, aotll_terms, metric_runs};
use crate::commands::import;
use crate::commands::train::{self, read_eval_curve, RunScale, TrainArgs};
use crate::output::{ensure_dir, write_atomic, write_json};
use crate::plot::{line_chart, Curve, Series};
use crate::table::{csv_row, header, metric_cells, TableArgs, CSV_HEADER};

/// Arguments of `sefi experiment-c`.
#[derive(clap::Args)]
pub struct ExperimentCArgs {
    /// The KITTI tracking folder (label_02, det_pointrcnn, ego_pose_orbslam3, calib).
    #[arg(long, default_value = "../shared/data/kitti-tracking")]
    pub kitti: PathBuf,
    /// Output directory.
    #[arg(long, default_value = "out/experiment-c")]
    pub out: PathBuf,
    /// Scale (`--quick`: a few scenes, few particles, 2 epochs; `--paper`: 4096
    /// particles, L = 15, 15 epochs), methods and filters.
    #[command(flatten)]
    pub table: TableArgs,
    /// Override the scale's evaluation particles per object.
    #[arg(long)]
    pub eval_particles: Option<usize>,
    /// Override the scale's scenes per training step.
    #[arg(long)]
    pub scenes_per_step: Option<usize>,
    /// Override the scale's repeated filter runs of the final evaluation.
    #[arg(long)]
    pub runs: Option<usize>,
    /// Let Adam's learning rate fall linearly from the scale's (0.01) to this at
    /// each run's last step (default: constant, the paper's).
    #[arg(long)]
    pub final_lr: Option<f64>,
    /// Seed of the initialisation, batch order and filters.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Steps per scene window (T + 1) of the import: longer windows at a coarser
    /// step approach the paper's 60 steps at 0.33 s, but fewer tracks are that long
    /// (see the README's table of objects per stride and window).
    #[arg(long, default_value_t = 20)]
    pub steps: usize,
    /// Keep every k-th KITTI frame in the import (dt = 0.1 s * k).
    #[arg(long, default_value_t = 1)]
    pub stride: usize,
    /// The box network's detection offsets, for every trained run, INIT and the
    /// supervised fit alike: `learned` (the paper's model) or `zero` (centred on the
    /// state, which pins where a track lies).
    #[arg(long, default_value_t = DetectionOffsets::Learned)]
    pub detection_offsets: DetectionOffsets,
    /// A catalogue extension of the box model learned by every trained run
    /// (`sefi train --extension`): `heading_flip` (a learnable fraction of
    /// detections report the heading reversed) or `latency`. INIT starts it at the
    /// catalogue's initial value; the supervised fit observes `heading_flip` in
    /// the labels (the flipped detections turned back, the fraction their share)
    /// and takes another extension's values from the learned run it is paired with.
    #[arg(long)]
    pub extension: Option<String>,
    /// A detector drift learned by every trained run (`sefi train --drift`;
    /// PF-SEFI's methods only). INIT starts it where the runs do; the supervised
    /// fit is the white-noise model, without drift.
    #[arg(long)]
    pub drift: bool,
    /// With --drift: the drift calibrated on the train labels and held there
    /// (`sefi train --drift-from-labels`).
    #[arg(long, requires = "drift")]
    pub drift_from_labels: bool,
}

/// The sizes of the experiment.
#[derive(Clone, Debug, Serialize)]
struct Scale {
    name: &'static str,
    /// Training particles per object.
    particles: usize,
    /// Particles of the periodic test MLL and of the final evaluation.
    eval_particles: usize,
    epochs: usize,
    scenes_per_step: usize,
    /// Test-MLL evaluations per training run (besides the initial one).
    evals_per_run: usize,
    /// Repeated filter runs of the final evaluation.
    eval_runs: usize,
    /// PF-SEFI's fixed lag, also the smoothing lag of ADE / AYE.
    lag: usize,
    alpha: f64,
    lr: f64,
    /// If set, Adam's rate falls linearly from `lr` to this at each run's last step.
    final_lr: Option<f64>,
    clip: f64,
    /// Objects per tape of the through-filter baselines.
    chunk_objects: usize,
    /// Use only this many (evenly spaced) train / val scenes.
    train_scenes: Option<usize>,
    val_scenes: Option<usize>,
    /// Adam steps and minibatch of the supervised fit.
    supervised_steps: usize,
    supervised_batch: usize,
    /// Fits of the supervised network, each from its own seed, whose val AOTLLs
    /// are summarised beside its row ([`supervised_over_seeds`]).
    supervised_seeds: usize,
}

impl Scale {
    fn of(args: &ExperimentCArgs) -> Scale {
        let base = Scale {
            name: "default",
            particles: 1024,
            eval_particles: 4096,
            epochs: 20,
            scenes_per_step: 16,
            evals_per_run: 10,
            eval_runs: 3,
            lag: 15,
            alpha: 0.8,
            lr: 0.01,
            final_lr: None,
            clip: 0.5,
            chunk_objects: 4,
            train_scenes: None,
            val_scenes: None,
            supervised_steps: 3000,
            supervised_batch: 128,
            supervised_seeds: 5,
        };
        let mut s = if args.table.quick {
            Scale {
                name: "quick",
                particles: 32,
                eval_particles: 64,
                epochs: 2,
                scenes_per_step: 4,
                evals_per_run: 2,
                eval_runs: 1,
                train_scenes: Some(12),
                val_scenes: Some(6),
                supervised_steps: 60,
                supervised_batch: 32,
                supervised_seeds: 3,
                ..base
            }
        } else if args.table.paper {
            Scale {
                name: "paper",
                particles: 4096,
                eval_particles: 4096,
                epochs: 15,
                eval_runs: 5,
                evals_per_run: 20,
                supervised_steps: 6000,
                supervised_batch: 256,
                ..base
            }
        } else {
            base
        };
        if let Some(n) = args.table.particles {
            s.particles = n;
        }
        if let Some(n) = args.eval_particles {
            s.eval_particles = n;
        }
        if let Some(n) = args.table.epochs {
            s.epochs = n;
        }
        if let Some(n) = args.scenes_per_step {
            s.scenes_per_step = n;
        }
        if let Some(n) = args.runs {
            s.eval_runs = n;
        }
        s.final_lr = args.final_lr;
        s
    }

    fn check(&self) -> Result<(), String> {
        if self.particles == 0 || self.eval_particles == 0 || self.scenes_per_step == 0 || self.eval_runs == 0 {
            return Err("particles, eval particles, scenes per step and runs must all be at least 1".into());
        }
        Ok(())
    }
}

/// One row of the table: a model's metrics on val and how it was made.
#[derive(Serialize)]
struct Row {
    method: String,
    runs: Vec<Metrics>,
    /// AOTLL of the model's observation network on the train split.
    train_aotll: Option<f64>,
    /// Its val AOTLL by part: reversed headings, the density's factors.
    aotll_terms: Option<BoxAotllTerms>,
    /// Training steps, skipped steps and collapsed filter steps summed over training.
    steps: Option<usize>,
    skipped_steps: Option<usize>,
    /// Why steps were skipped: each reason of the run's skip log with its count.
    skip_reasons: Vec<(String, usize)>,
    train_collapsed_steps: Option<usize>,
    /// Wall time of training, summed over resumed sessions (or of the supervised fit).
    train_seconds: Option<f64>,
    /// Wall time of the final evaluation.
    eval_seconds: f64,
    #[serde(skip)]
    curve: Curve,
}

/// Imports KITTI into `OUT/data` unless an import is there, then returns the
/// train and val directories the scale uses (evenly spaced subsets for `--quick`).
fn prepare_data(args: &ExperimentCArgs, scale: &Scale) -> Result<(PathBuf, PathBuf), String> {
    let data_dir = args.out.join("data");
    // The report is written after both datasets: its presence means a finished import.
    let (train, val) = (data_dir.join("train"), data_dir.join("val"));
    if data_dir.join("import_report.md").is_file() {
        // An earlier import is reused only if it has the windows asked for.
        let meta = Dataset::read_layout(&train).map_err(|e| format!("dataset {}: {e}", train.display()))?.meta;
        let dt = KITTI_FRAME_DT * args.stride as f64;
        if meta.steps != args.steps || (meta.dt - dt).abs() > 1e-9 {
            return Err(format!(
                "{} holds an import of {} steps at dt = {} s, but --steps {} --stride {} asks for {} steps at dt = {dt} s: \
                 use another --out (or remove that import)",
                data_dir.display(),
                meta.steps,
                meta.dt,
                args.steps,
                args.stride,
                args.steps
            ));
        }
        if !meta.prior_from_detection && extension_of(args)? == Some(Extension::HeadingFlip) {
            return Err(format!(
                "{} holds an import whose meta.json lacks `prior_from_detection` (made before imports marked \
                 their priors as read from a detection), which --extension heading_flip needs (its prior is \
                 axial there): remove that import, it regenerates",
                data_dir.display()
            ));
        }
        eprintln!("reusing the KITTI import in {}", data_dir.display());
    } else {
        let options = KittiOptions { steps: args.steps, stride: args.stride, ..KittiOptions::default() };
        import::kitti(&args.kitti, &data_dir, &options)?;
    }
    if scale.train_scenes.is_none() && scale.val_scenes.is_none() {
        return Ok((train, val));
    }
    let name = format!("subset-{}-{}", opt_count(scale.train_scenes), opt_count(scale.val_scenes));
    let sub = args.out.join(&name);
    let mut dirs = Vec::new();
    for (split, dir, keep) in [("train", train, scale.train_scenes), ("val", val, scale.val_scenes)] {
        let target = sub.join(split);
        if !target.join("meta.json").is_file() {
            let data = Dataset::read(&dir).map_err(|e| e.to_string())?;
            let picked = evenly_spaced(data.scenes().len(), keep.unwrap_or(usize::MAX));
            data.select_scenes(&picked).write(&target).map_err(|e| e.to_string())?;
        }
        dirs.push(target);
    }
    let val = dirs.pop().expect("two splits");
    Ok((dirs.pop().expect("two splits"), val))
}

fn opt_count(n: Option<usize>) -> String {
    n.map_or_else(|| "all".into(), |n| n.to_string())
}

/// `k` indices spread evenly over `0..n` (all of them if `k >= n`).
fn evenly_spaced(n: usize, k: usize) -> Vec<usize> {
    if k >= n {
        return (0..n).collect();
    }
    (0..k).map(|i| i * n / k).collect()
}

/// The store every training run starts from (what `sefi train --policy neural
/// --seed SEED` builds): the neural policy from `seed`, the box network from
/// `seed + 1`, with `offsets` learned or fixed at zero, and the drift of
/// `--drift` (calibrated on `train_data` with `--drift-from-labels`).
fn initial_models(args: &ExperimentCArgs, train_data: &Dataset) -> Result<Models, String> {
    let mut models = fresh_networks(args, args.seed)?;
    models.drift = match (args.drift, args.drift_from_labels) {
        (false, _) => None,
        (true, false) => Some(DetectorDrift::initial().data().to_vec()),
        (true, true) => Some(drift_from_labels(train_data)?.drift.to_raw()),
    };
    Ok(models)
}

/// The networks of [`initial_models`] with their initial weights drawn from
/// `seed`, and `--extension` at its initial value; no drift.
fn fresh_networks(args: &ExperimentCArgs, seed: u64) -> Result<Models, String> {
    let mut models = train::fresh_models("neural", "", ObservationKind::Boxes, args.detection_offsets, seed)
        .expect("the neural policy needs no settings");
    models.extension =
        extension_of(args)?.map(|extension| FittedExtension { extension, raw: extension.initial().data().to_vec() });
    Ok(models)
}

/// The catalogue extension of `--extension`, refused where it means nothing for
/// box detections.
fn extension_of(args: &ExperimentCArgs) -> Result<Option<Extension>, String> {
    args.extension.as_deref().map(|id| train::extension_for(id, ObservationKind::Boxes)).transpose()
}

/// AOTLL of `models`' observation network on `data`.
fn aotll_on(data: &Dataset, models: &Models) -> Option<f64> {
    ssm::evaluation::metrics::models_aotll(data, models).mean
}

/// Sums of the `skipped` and `collapsed_steps` columns of a run's `train.csv`.
fn train_log_totals(dir: &Path) -> Result<(usize, usize), String> {
    let path = dir.join(TRAIN_LOG);
    let mut reader = csv::Reader::from_path(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let headers = reader.headers().map_err(|e| format!("{}: {e}", path.display()))?.clone();
    let col = |name: &str| headers.iter().position(|h| h == name).ok_or(format!("{}: no `{name}`", path.display()));
    let (skipped, collapsed) = (col("skipped")?, col("collapsed_steps")?);
    let (mut s, mut c) = (0usize, 0usize);
    for row in reader.records() {
        let row = row.map_err(|e| format!("{}: {e}", path.display()))?;
        // A skipped step may log NaN for what it never measured: count what parses.
        s += row[skipped].parse::<f64>().ok().filter(|v| v.is_finite()).unwrap_or(0.0) as usize;
        c += row[collapsed].parse::<f64>().ok().filter(|v| v.is_finite()).unwrap_or(0.0) as usize;
    }
    Ok((s, c))
}

/// Each reason of a run's skip log with the number of steps it skipped, most
/// frequent first (none for a run without the log, written before it existed).
fn skip_reasons(dir: &Path) -> Result<Vec<(String, usize)>, String> {
    let path = dir.join(SKIP_LOG);
    if !path.is_file() {
        return Ok(Vec::new());
    }
    let mut reader = csv::Reader::from_path(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut counts: Vec<(String, usize)> = Vec::new();
    for row in reader.records() {
        let row = row.map_err(|e| format!("{}: {e}", path.display()))?;
        let reason = row.get(2).unwrap_or("").to_string();
        match counts.iter_mut().find(|(r, _)| *r == reason) {
            Some((_, n)) => *n += 1,
            None => counts.push((reason, 1)),
        }
    }
    counts.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    Ok(counts)
}

/// The training data's batches per epoch and the steps between evaluations.
fn schedule(scale: &Scale, train_scenes: usize) -> (usize, usize) {
    let batches = train_scenes.div_ceil(scale.scenes_per_step);
    (batches, (scale.epochs * batches / scale.evals_per_run.max(1)).max(1))
}

/// The `sefi train` arguments of `method`'s run in `dir`, resuming from a
/// checkpoint found there.
fn run_args(
    args: &ExperimentCArgs,
    scale: &Scale,
    data: (&Path, &Path),
    eval_every: usize,
    method: &str,
    dir: &Path,
) -> TrainArgs {
    let run = RunScale::new(scale.lag, scale.alpha, scale.particles, scale.eval_particles, scale.epochs);
    TrainArgs {
        policy: "neural".into(),
        lr: scale.lr,
        final_lr: scale.final_lr,
        clip: Some(scale.clip),
        eval_every,
        checkpoint_every: eval_every,
        scenes_per_step: scale.scenes_per_step,
        chunk_objects: scale.chunk_objects,
        seed: args.seed,
        detection_offsets: args.detection_offsets,
        extension: args.extension.clone(),
        drift: args.drift,
        drift_from_labels: args.drift_from_labels,
        ..TrainArgs::for_method(method, &args.table.filter, run, data.0, data.1, dir)
    }
}

/// Runs `sefi experiment-c` as one process of `cluster`. On a job of many
/// processes (`mpiexec`), the first imports the data while the others wait,
/// every process trains every method's run together (each holding its share of
/// the training objects, [`train::train_run`]), and only the first evaluates,
/// fits the supervised model and writes the table.
pub fn run(args: &ExperimentCArgs, cluster: &Cluster) -> Result<(), String> {
    let started = Instant::now();
    let scale = Scale::of(args);
    scale.check()?;
    extension_of(args)?;
    for m in &args.table.methods {
        check_method(m, scale.lag, scale.alpha)?;
        if args.drift && !m.starts_with("pf-sefi") {
            return Err(format!("--drift: `{m}` cannot learn a detector drift (PF-SEFI's methods only)"));
        }
    }
    if !cluster.is_root() {
        // Wait for the first process's import, then find it where it was written.
        cluster.wait_for_first(true);
        let (train_dir, val_dir) = prepare_data(args, &scale)?;
        let scenes = Dataset::read_layout(&train_dir).map_err(|e| e.to_string())?.scenes.len();
        let (_, eval_every) = schedule(&scale, scenes);
        let hidden = indicatif::ProgressBar::hidden();
        for method in &args.table.methods {
            let dir = args.out.join("runs").join(method);
            let run = run_args(args, &scale, (&train_dir, &val_dir), eval_every, method, &dir);
            train::train_run(&run, &hidden, cluster)?;
        }
        return Ok(());
    }
    let prepared = ensure_dir(&args.out).and_then(|_| prepare_data(args, &scale));
    cluster.wait_for_first(prepared.is_ok());
    let (train_dir, val_dir) = prepared?;
    let train_data = Dataset::read(&train_dir).map_err(|e| e.to_string())?;
    let val = Dataset::read(&val_dir).map_err(|e| e.to_string())?;
    if train_data.kind() != ObservationKind::Boxes || train_data.states().is_none() {
        return Err(format!("{}: expected box detections with labelled states", train_dir.display()));
    }
    let (batches, eval_every) = schedule(&scale, train_data.scenes().len());
    let total_steps = scale.epochs * batches;
    eprintln!(
        "experiment C ({} scale): train {} scenes / {} objects, val {} scenes / {} objects; {} steps per run \
         ({} epochs x {batches}), {} particles, {} scenes per step",
        scale.name,
        train_data.scenes().len(),
        train_data.objects().len(),
        val.scenes().len(),
        val.objects().len(),
        total_steps,
        scale.epochs,
        scale.particles,
        scale.scenes_per_step,
    );
    let eval_seed = 1000 + args.seed;
    let sampling = Sampling::new(scale.eval_particles, args.table.filter.tempering(val.kind())?);
    let eval_filter = FilterConfig::new(sampling, scale.lag, eval_seed);
    let evaluate = |models: &Models| metric_runs(&val, models, &eval_filter, scale.eval_runs);

    // INIT: where every run starts.
    let clock = Instant::now();
    let init = initial_models(args, &train_data)?;
    let init_runs = evaluate(&init)?;
    let mut rows = vec![Row {
        method: "INIT".into(),
        runs: init_runs,
        train_aotll: aotll_on(&train_data, &init),
        aotll_terms: aotll_terms(&val, &init),
        steps: None,
        skipped_steps: None,
        skip_reasons: Vec::new(),
        train_collapsed_steps: None,
        train_seconds: None,
        eval_seconds: clock.elapsed().as_secs_f64(),
        curve: Vec::new(),
    }];

    let mut learned: Vec<(String, Models)> = Vec::new();
    for method in &args.table.methods {
        let dir = args.out.join("runs").join(method);
        let train_args = run_args(args, &scale, (&train_dir, &val_dir), eval_every, method, &dir);
        let bar = train::bar(method);
        let outcome = train::train_run(&train_args, &bar, cluster)?;
        bar.finish_and_clear();
        let store = ParamStore::<f64>::load(&dir.join(PARAMS_FILE)).map_err(|e| e.to_string())?;
        let models = Models::from_store(&store, val.kind()).map_err(|e| e.to_string())?;
        let (skipped, collapsed) = train_log_totals(&dir)?;
        let clock = Instant::now();
        let runs = evaluate(&models)?;
        eprintln!(
            "{method}: val MLL {:.4}, AOTLL {:.4} ({} steps, {} skipped, {} collapsed filter steps in training)",
            runs[0].mll.unwrap_or(f64::NAN),
            runs[0].aotll.mean.unwrap_or(f64::NAN),
            outcome.steps,
            skipped,
            collapsed
        );
        rows.push(Row {
            method: method.clone(),
            runs,
            train_aotll: aotll_on(&train_data, &models),
            aotll_terms: aotll_terms(&val, &models),
            steps: Some(outcome.steps),
            skipped_steps: Some(outcome.skipped_steps),
            skip_reasons: skip_reasons(&dir)?,
            train_collapsed_steps: Some(collapsed),
            train_seconds: Some(outcome.seconds),
            eval_seconds: clock.elapsed().as_secs_f64(),
            curve: read_eval_curve(&dir, "test_mll")?,
        });
        learned.push((method.clone(), models));
    }

    // SUPERVISED: the observation network fitted to the labelled train states, from
    // the same initial weights, beside PF-SEFI's learned policy.
    let clock = Instant::now();
    let (policy_from, paired) = match learned.iter().find(|(m, _)| m == "pf-sefi").or(learned.first()) {
        Some((m, models)) => (m.clone(), models),
        None => ("INIT".to_string(), &init),
    };
    let (supervised, report) = fit_supervised(args, &scale, &train_data, paired, args.seed)?;
    let sup_dir = args.out.join("supervised");
    ensure_dir(&sup_dir)?;
    supervised.to_store().save(&sup_dir.join(PARAMS_FILE)).map_err(|e| e.to_string())?;
    eprintln!(
        "supervised observation network: train AOTLL {:.4} -> {:.4} ({} examples, {} steps, {} skipped)",
        report.initial_aotll, report.final_aotll, report.examples, report.steps, report.skipped
    );
    let fit_seconds = clock.elapsed().as_secs_f64();
    let clock = Instant::now();
    let sup_runs = evaluate(&supervised)?;
    rows.push(Row {
        method: format!("SUPERVISED obs + {policy_from} policy"),
        runs: sup_runs,
        train_aotll: aotll_on(&train_data, &supervised),
        aotll_terms: aotll_terms(&val, &supervised),
        steps: Some(report.steps),
        skipped_steps: Some(report.skipped),
        skip_reasons: Vec::new(),
        train_collapsed_steps: None,
        train_seconds: Some(fit_seconds),
        eval_seconds: clock.elapsed().as_secs_f64(),
        curve: Vec::new(),
    });
    let row = rows.last().expect("the supervised row");
    let first = SupervisedSeed {
        seed: args.seed,
        val_aotll: row.runs.first().and_then(|m| m.aotll.mean),
        train_aotll: row.train_aotll,
    };
    let supervised_seeds = supervised_over_seeds(args, &scale, (&train_data, &val), paired, first)?;

    let context = Context {
        args,
        scale: &scale,
        train: &train_data,
        val: &val,
        batches,
        eval_every,
        supervised: &report,
        supervised_seconds: fit_seconds,
        supervised_seeds: &supervised_seeds,
        supervised_extension: match &supervised.extension {
            None => None,
            Some(e) => {
                let described = e.extension.describe(&e.raw).map_err(|err| err.to_string())?;
                Some(match e.extension {
                    Extension::HeadingFlip => format!(
                        "{described}, observed in the labels (the flipped detections turned back for the fit; the \
                         train AOTLLs are theirs)"
                    ),
                    _ => format!("{described}, as the {policy_from} run learned it"),
                })
            }
        },
        policy_from: &policy_from,
    };
    write_outputs(&context, &rows, started.elapsed().as_secs_f64())?;
    cluster.print_traffic();
    Ok(())
}

/// The supervised observation network fitted to `train`'s labelled states from
/// the initial weights of `seed` (its minibatches drawn from it too), beside
/// `paired`'s policy and extension, without a drift: with `heading_flip`, the
/// flips observed in the labels ([`fit_observation_with_flips`]).
fn fit_supervised(
    args: &ExperimentCArgs,
    scale: &Scale,
    train: &Dataset,
    paired: &Models,
    seed: u64,
) -> Result<(Models, SupervisedReport), String> {
    let mut supervised =
        Models { policy: paired.policy.clone(), extension: paired.extension.clone(), ..fresh_networks(args, seed)? };
    let fit =
        FitConfig { steps: scale.supervised_steps, batch: scale.supervised_batch, lr: scale.lr, clip: None, seed };
    let report = match extension_of(args)? {
        Some(Extension::HeadingFlip) => fit_observation_with_flips(&mut supervised, train, &fit)?,
        _ => fit_observation(&mut supervised, train, &fit).map_err(|e| e.to_string())?,
    };
    Ok((supervised, report))
}

/// One supervised fit of [`supervised_over_seeds`]: its seed and AOTLLs.
#[derive(Clone, Debug, Serialize)]
struct SupervisedSeed {
    seed: u64,
    val_aotll: Option<f64>,
    train_aotll: Option<f64>,
}

/// The supervised row's network refitted from [`Scale::supervised_seeds`] seeds
/// (the run's seed, whose AOTLLs `first` the supervised row already has, and
/// the next ones):
/// how much of the comparison with the self-supervised rows is the supervised
/// fit's own randomness (initial weights, minibatches). AOTLL needs no filter,
/// so each fit costs seconds.
fn supervised_over_seeds(
    args: &ExperimentCArgs,
    scale: &Scale,
    (train, val): (&Dataset, &Dataset),
    paired: &Models,
    first: SupervisedSeed,
) -> Result<Vec<SupervisedSeed>, String> {
    let mut seeds = vec![first];
    for k in 1..scale.supervised_seeds as u64 {
        let seed = args.seed + k;
        let (models, _) = fit_supervised(args, scale, train, paired, seed)?;
        seeds.push(SupervisedSeed { seed, val_aotll: aotll_on(val, &models), train_aotll: aotll_on(train, &models) });
    }
    Ok(seeds)
}

/// What the outputs describe besides the rows.
struct Context<'a> {
    args: &'a ExperimentCArgs,
    scale: &'a Scale,
    train: &'a Dataset,
    val: &'a Dataset,
    batches: usize,
    eval_every: usize,
    supervised: &'a SupervisedReport,
    supervised_seconds: f64,
    /// The supervised network's val AOTLL over fit seeds.
    supervised_seeds: &'a [SupervisedSeed],
    policy_from: &'a str,
    /// The supervised model's extension in words, if any.
    supervised_extension: Option<String>,
}

/// Notes on rows whose numbers are not what they seem: non-finite state estimates
/// (the model diverged) and MLLs above what the density allows.
fn validity_notes(rows: &[Row]) -> String {
    let mut notes = String::new();
    let bound = BoxObservationModel::max_log_density();
    for r in rows {
        if !r.skip_reasons.is_empty() {
            let reasons: Vec<String> = r.skip_reasons.iter().map(|(why, n)| format!("{n}: {why}")).collect();
            let _ = writeln!(
                notes,
                "\n{}: {} training steps skipped, each before it reached the parameters ({}).",
                r.method,
                r.skip_reasons.iter().map(|x| x.1).sum::<usize>(),
                reasons.join("; ")
            );
        }
        let bad_states = r.runs.iter().any(|m| m.smoothed.ade.is_some_and(|a| !a.is_finite()));
        let over: Vec<f64> = r.runs.iter().filter_map(|m| m.mll).filter(|&v| v > bound).collect();
        if bad_states {
            let _ = writeln!(
                notes,
                "\n{}: some smoothed state estimates are not finite (ADE shown as `-`): the learned model \
                 diverged.",
                r.method
            );
        }
        if !over.is_empty() {
            let _ = writeln!(
                notes,
                "\n{}: MLL {} in {} of {} runs exceeds {bound:.2} nats, the largest log-density one detection can \
                 have under the box model: a numerical artefact, not a likelihood.",
                r.method,
                over.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>().join(", "),
                over.len(),
                r.runs.len()
            );
        }
    }
    notes
}

/// The table's line on the supervised network refitted over seeds: its val
/// AOTLLs, their median and range (empty for a single seed).
fn supervised_seeds_line(seeds: &[SupervisedSeed]) -> String {
    if seeds.len() < 2 {
        return String::new();
    }
    let vals: Vec<f64> = seeds.iter().filter_map(|s| s.val_aotll).collect();
    let listed: Vec<String> = seeds
        .iter()
        .map(|s| format!("{}: {}", s.seed, s.val_aotll.map_or_else(|| "-".into(), |v| format!("{v:.3}"))))
        .collect();
    let summary =
        Summary::of(&vals).map_or_else(String::new, |m| format!(", median {:.3} [{:.3}, {:.3}]", m.median, m.q1, m.q3));
    format!(
        "The same fit from {} seeds (initial weights and minibatches; the row above is seed {}): val AOTLL \
         {}{summary} — how far the supervised row moves by its fit's randomness alone.\n",
        seeds.len(),
        seeds[0].seed,
        listed.join(", ")
    )
}

/// A count's median \[IQR\] over runs, as whole numbers.
fn count_summary_cell(s: Option<&Summary>) -> String {
    match s {
        Some(s) if s.n > 1 && s.iqr > 0.0 => format!("{:.0} [{:.0}, {:.0}]", s.median, s.q1, s.q3),
        Some(s) => format!("{:.0}", s.median),
        None => "-".into(),
    }
}

fn count_cell(n: Option<usize>) -> String {
    n.map_or_else(|| "-".into(), |n| n.to_string())
}

fn write_outputs(c: &Context<'_>, rows: &[Row], seconds: f64) -> Result<(), String> {
    let s = c.scale;
    let detections = |d: &Dataset| d.observations().count();
    let mut md = format!(
        "Experiment C on KITTI ({} scale: {} training / {} evaluation particles, {} epochs of {} steps \
         ({} scenes per step), L = {}, PFNET alpha = {}, Adam lr {}{} with global-norm clipping {}, neural \
         policy, box-detection observation network{}; this session took {:.0} s).\n\
         Train: {} scenes, {} objects, {} detections. Val: {} scenes, {} objects, {} detections.\n\
         Metrics on val, median [IQR] over {} filter runs ({} particles, smoothing lag {}); AOTLL median and AOTLL \
         without lowest 1% are the median of val's per-detection log-densities and their mean without the \
         lowest 1% (a mean of log-densities can be carried by a few detections far from the labelled state); \
         AOTLL train is the observation network's AOTLL on the train split.\n\n",
        s.name,
        s.particles,
        s.eval_particles,
        s.epochs,
        c.batches,
        s.scenes_per_step,
        s.lag,
        s.alpha,
        s.lr,
        s.final_lr.map_or_else(String::new, |end| format!(" falling linearly to {end}")),
        s.clip,
        c.args.extension.as_ref().map_or_else(String::new, |e| format!(
            " extended by `{e}` (every row: MLL and AOTLL under the extended model; AOTLL by part: the base network)"
        )) + match (c.args.drift, c.args.drift_from_labels) {
            (false, _) => "",
            (true, false) => " with a detector drift learned (AOTLL integrates it out; the supervised row has none)",
            (true, true) => {
                " with a detector drift calibrated on the train labels and held (AOTLL integrates it out; the \
                 supervised row has none)"
            }
        },
        seconds,
        c.train.scenes().len(),
        c.train.objects().len(),
        detections(c.train),
        c.val.scenes().len(),
        c.val.objects().len(),
        detections(c.val),
        s.eval_runs,
        s.eval_particles,
        s.lag,
    );
    let mut csv = String::from(CSV_HEADER);
    md.push_str(&header(&[
        "AOTLL median",
        "AOTLL without lowest 1%",
        "AOTLL train",
        "steps",
        "skipped",
        "collapsed (train)",
        "collapsed (val)",
        "train (s)",
        "eval (s)",
    ]));
    for r in rows {
        let summary = metric_cells(&r.method, &r.runs, &mut md, &mut csv);
        let val_collapsed = summary.iter().find(|(n, _)| *n == "collapsed_steps").and_then(|(_, s)| s.as_ref());
        // AOTLL does not depend on the filter: every run has the same per-detection values.
        let val_aotll = r.runs.first().map(|m| m.aotll).unwrap_or_default();
        let cell = |v: Option<f64>| v.map_or_else(|| "-".into(), |v| format!("{v:.3}"));
        let _ = writeln!(
            md,
            " {} | {} | {} | {} | {} | {} | {} | {} | {:.0} |",
            cell(val_aotll.median),
            cell(val_aotll.mean_above_q01),
            cell(r.train_aotll),
            count_cell(r.steps),
            count_cell(r.skipped_steps),
            count_cell(r.train_collapsed_steps),
            count_summary_cell(val_collapsed),
            r.train_seconds.map_or_else(|| "-".into(), |v| format!("{v:.0}")),
            r.eval_seconds
        );
        if let Some(v) = r.train_aotll {
            let _ = writeln!(csv, "{},train_aotll,{v},{v},{v},1", r.method);
        }
        if let Some(v) = val_collapsed {
            csv_row(&mut csv, &r.method, "collapsed_steps", v);
        }
    }
    let rep = c.supervised;
    let _ = writeln!(
        md,
        "\nSupervised observation network: fitted by maximum AOTLL to {} labelled train object-steps ({} \
         detections), {} Adam steps of {} (skipped {}); train AOTLL {:.4} -> {:.4}; paired with the {} policy{} \
         ({:.1} s).",
        rep.examples,
        rep.items,
        rep.steps,
        s.supervised_batch,
        rep.skipped,
        rep.initial_aotll,
        rep.final_aotll,
        c.policy_from,
        c.supervised_extension.as_ref().map_or_else(String::new, |e| format!("; extended: {e}")),
        c.supervised_seconds
    );
    md.push_str(&supervised_seeds_line(c.supervised_seeds));
    let by_part: Vec<(&str, &BoxAotllTerms)> =
        rows.iter().filter_map(|r| r.aotll_terms.as_ref().map(|t| (r.method.as_str(), t))).collect();
    md.push('\n');
    md.push_str(&aotll_by_part_table("Val AOTLL by part", &by_part));
    md.push_str(&validity_notes(rows));
    write_atomic(&c.args.out.join("table.md"), md.as_bytes())?;
    write_atomic(&c.args.out.join("table.csv"), csv.as_bytes())?;

    // A diverged run's curve swings by thousands of nats (and above what the
    // density allows): plot only the plausible range, from 10 nats below the
    // initial MLL up to the density's bound, and say how many points were left out.
    let bound = BoxObservationModel::max_log_density();
    let floor = rows.iter().flat_map(|r| r.curve.first()).map(|p| p.1).fold(f64::INFINITY, f64::min) - 10.0;
    let mut omitted = 0usize;
    let mut series: Vec<Series> = rows
        .iter()
        .filter(|r| !r.curve.is_empty())
        .map(|r| {
            let points: Curve =
                r.curve.iter().copied().filter(|p| p.1.is_finite() && p.1 >= floor && p.1 <= bound).collect();
            omitted += r.curve.len() - points.len();
            Series { name: r.method.clone(), points }
        })
        .collect();
    let last = rows.iter().flat_map(|r| r.curve.last()).map(|p| p.0).fold(1.0, f64::max);
    if let Some(sup) = rows.last() {
        let mlls: Vec<f64> = sup.runs.iter().filter_map(|m| m.mll).collect();
        if let Some(m) = ssm::stats::median(&mlls) {
            series.push(Series { name: sup.method.clone(), points: vec![(0.0, m), (last, m)] });
        }
    }
    if series.iter().any(|s| !s.points.is_empty()) {
        let title = if omitted > 0 {
            format!("Experiment C (KITTI): val MLL during training ({omitted} points outside [{floor:.1}, {bound:.1}] omitted)")
        } else {
            "Experiment C (KITTI): val MLL during training".to_string()
        };
        line_chart(&c.args.out.join("curves.svg"), &title, "training step", "val MLL (nats/detection)", &series)?;
    }

    let doc = json!({
        "experiment": "C",
        "data": {
            "kitti": c.args.kitti.display().to_string(),
            "train": {"scenes": c.train.scenes().len(), "objects": c.train.objects().len(), "detections": detections(c.train)},
            "val": {"scenes": c.val.scenes().len(), "objects": c.val.objects().len(), "detections": detections(c.val)},
        },
        "scale": s,
        "seed": c.args.seed,
        "steps_per_epoch": c.batches,
        "eval_every": c.eval_every,
        "session_seconds": seconds,
        "rows": rows,
        "supervised": {
            "report": rep,
            "policy_from": c.policy_from,
            "batch": s.supervised_batch,
            "seconds": c.supervised_seconds,
            "params": "supervised/params.bin",
            "seeds": c.supervised_seeds,
        },
    });
    write_json(&c.args.out.join("experiment_c.json"), &doc)?;
    println!("{md}");
    println!("wrote {} (table.md, table.csv, curves.svg, experiment_c.json)", c.args.out.display());
    Ok(())
}
