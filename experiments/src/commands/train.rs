//! `sefi train`: learns a dataset's policy and observation network with a score
//! estimator (SPEC §6) through [`ssm::training::train`] and
//! [`ssm::training::objective::SceneObjective`].
//!
//! Writes into `--out DIR`: `run.json` (every setting; a resumed run must match
//! it), `train.csv` and `eval.csv` (the logs), `checkpoint.bin` and `params.bin`
//! (resumable state and the learned parameters, for `sefi eval --params`), and
//! `curve.svg` (test MLL against training step).

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use autodiff::nn::ParamStore;
use autodiff::Tensor;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};
use ssm::data::{Dataset, ObservationKind};
use ssm::estimators::{Estimator, EstimatorConfig};
use ssm::filter::Sampling;
use ssm::models::drift::{drift_from_labels, DetectorDrift, DRIFT_PARAM};
use ssm::models::extended::Extension;
use ssm::models::observation::boxes::DetectionOffsets;
use ssm::models::params::{drift_in_store, AnyPolicy, FittedExtension, Models};
use ssm::models::vehicle::{HandCraftedPolicy, NeuralPolicy};
use ssm::training::objective::{owned_objects, ObjectiveConfig, SceneObjective};
use ssm::training::{train, TrainConfig, TrainEvent, TrainOutcome, EVAL_LOG};

use crate::args::{method_settings, FilterArgs, FilterKind};
use crate::cluster::Cluster;
use crate::output::{claim_or_refuse, ensure_dir, write_json};
use crate::plot::{line_chart, Curve, Series};

/// Arguments of `sefi train`.
#[derive(clap::Args, Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct TrainArgs {
    /// Training dataset directory.
    #[arg(long)]
    pub data: PathBuf,
    /// Test dataset directory (evaluated during training).
    #[arg(long)]
    pub test: PathBuf,
    /// Start from these parameters instead of a fresh initialisation.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Policy of a fresh initialisation: `hand-crafted` or `neural`.
    #[arg(long, default_value = "hand-crafted")]
    pub policy: String,
    /// Initial sds `accel,pinch` of a fresh hand-crafted policy.
    #[arg(long, default_value = "1.0,0.1")]
    pub init_sd: String,
    /// Box data, fresh initialisation: the detection centre's mean offset from the
    /// state `learned` (the paper's model) or `zero` (the detector taken as unbiased
    /// in position, which pins where a track lies; README, experiment C).
    #[arg(long, default_value_t = DetectionOffsets::Learned)]
    #[serde(default)]
    pub detection_offsets: DetectionOffsets,
    /// A catalogue extension learned with the model (`sefi diagnose`'s
    /// catalogue: `heading_flip` on box data, `heavy_tailed_accel`, ...): the
    /// filter, the score and the test MLL use the extended model, and the
    /// extension's parameter starts at the catalogue's initial value and is saved
    /// with the others under `ext.<id>`.
    #[arg(long)]
    #[serde(default)]
    pub extension: Option<String>,
    /// Box data: learn a detector drift with the model, a detector error that
    /// persists from frame to frame as offsets in the state (`ssm::models::drift`;
    /// PF-SEFI only). It starts at a stated rule (persistence 1/2, sds at the box
    /// model's floor scales) and is saved under `drift`.
    #[arg(long)]
    #[serde(default)]
    pub drift: bool,
    /// With --drift: calibrate the drift on the training data's labels
    /// (`ssm::models::drift::drift_from_labels`: the AR(1) of the detections'
    /// offsets from their labels) and hold it there; the rest of the model is
    /// learned from the detections alone.
    #[arg(long, requires = "drift")]
    #[serde(default)]
    pub drift_from_labels: bool,
    /// Estimator: pf-sefi, pf, dpf-sgr, dpf-sgr-stopped or pfnet.
    #[arg(long, default_value = "pf-sefi")]
    pub estimator: String,
    /// PF-SEFI's fixed lag L.
    #[arg(long, default_value_t = 8)]
    pub lag: usize,
    /// PF-SEFI's filter (the through-filter baselines always use the bootstrap filter).
    #[command(flatten)]
    #[serde(flatten)]
    pub filter: FilterArgs,
    /// The filter of the test evaluation (the same for every estimator).
    #[arg(long, value_enum, default_value_t = FilterKind::Tempered)]
    pub eval_filter: FilterKind,
    /// PFNET's soft-resampling alpha.
    #[arg(long, default_value_t = 0.8)]
    pub alpha: f64,
    /// Training particles per object.
    #[arg(long, default_value_t = 1024)]
    pub particles: usize,
    /// Evaluation particles per object.
    #[arg(long, default_value_t = 4096)]
    pub eval_particles: usize,
    /// Epochs (passes over the training scenes).
    #[arg(long, default_value_t = 100)]
    pub epochs: usize,
    /// Adam's learning rate.
    #[arg(long, default_value_t = 0.01)]
    pub lr: f64,
    /// If given, the learning rate falls linearly from `--lr` at the first step to
    /// this at the last (default: constant).
    #[arg(long)]
    #[serde(default)]
    pub final_lr: Option<f64>,
    /// Global gradient-norm clipping (of the per-point score).
    #[arg(long)]
    pub clip: Option<f64>,
    /// Evaluate on the test data every this many steps (0: only at the start and end).
    #[arg(long, default_value_t = 10)]
    pub eval_every: usize,
    /// Keep the parameters of the best test evaluation (test MLL, every
    /// `--eval-every` steps, the initial ones included) rather than the last:
    /// `params.bin` holds them at the end. The test data then choose as well as
    /// score, so give them objects that the final comparison does not use.
    #[arg(long)]
    #[serde(default)]
    pub keep_best: bool,
    /// Return the mean of the iterates of the run's last this share of steps
    /// (Polyak–Ruppert tail averaging; 0: the last iterate). Evaluations from
    /// the tail's first step on evaluate that mean.
    #[arg(long, default_value_t = 0.0)]
    #[serde(default)]
    pub average_tail: f64,
    /// Write a checkpoint every this many steps.
    #[arg(long, default_value_t = 10)]
    pub checkpoint_every: usize,
    /// Scenes per training step.
    #[arg(long, default_value_t = 1)]
    pub scenes_per_step: usize,
    /// Objects per tape of the through-filter baselines (memory against speed).
    #[arg(long, default_value_t = 4)]
    pub chunk_objects: usize,
    /// Random seed (initialisation, batch order, filters).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output directory.
    #[arg(long, default_value = "out/train")]
    pub out: PathBuf,
    /// Continue the run in `--out` from its last checkpoint.
    #[arg(long)]
    #[serde(skip)]
    pub resume: bool,
}

impl TrainArgs {
    /// The command line's defaults (one source of truth for `sefi train` and every
    /// command that trains) for a run on `data`, evaluated on `test`, written to `out`.
    pub fn with_defaults(data: PathBuf, test: PathBuf, out: PathBuf) -> TrainArgs {
        #[derive(clap::Parser)]
        struct Defaults {
            #[command(flatten)]
            args: TrainArgs,
        }
        let argv: [std::ffi::OsString; 7] =
            ["train".into(), "--data".into(), data.into(), "--test".into(), test.into(), "--out".into(), out.into()];
        <Defaults as clap::Parser>::try_parse_from(argv).expect("the required arguments are given").args
    }

    /// The run of a table's `method` ([`method_settings`]: its estimator and
    /// filter, with the table's `filter` settings, evaluated on the table's
    /// filter) at `scale`, on `data`, evaluated on `test`, in `out`, resuming
    /// from a checkpoint found there; the rest as [`TrainArgs::with_defaults`].
    pub fn for_method(
        method: &str,
        filter: &FilterArgs,
        scale: RunScale,
        data: &Path,
        test: &Path,
        out: &Path,
    ) -> Self {
        let (estimator, kind) = method_settings(method);
        TrainArgs {
            estimator: estimator.to_string(),
            lag: scale.lag,
            filter: FilterArgs { filter: kind, ..filter.clone() },
            eval_filter: filter.filter,
            alpha: scale.alpha,
            particles: scale.particles,
            eval_particles: scale.eval_particles,
            epochs: scale.epochs,
            resume: out.join(ssm::training::CHECKPOINT_FILE).is_file(),
            ..TrainArgs::with_defaults(data.to_path_buf(), test.to_path_buf(), out.to_path_buf())
        }
    }
}

/// The settings a table's scale gives every method's run ([`TrainArgs::for_method`]).
#[derive(Clone, Copy, Debug)]
pub struct RunScale {
    /// Fixed lag L.
    pub lag: usize,
    /// PFNET's alpha.
    pub alpha: f64,
    /// Training particles.
    pub particles: usize,
    /// Evaluation particles.
    pub eval_particles: usize,
    /// Epochs.
    pub epochs: usize,
}

impl RunScale {
    /// The settings, in the order of the fields.
    pub fn new(lag: usize, alpha: f64, particles: usize, eval_particles: usize, epochs: usize) -> Self {
        RunScale { lag, alpha, particles, eval_particles, epochs }
    }
}

/// Parses `a,b` as two positive numbers.
fn parse_sds(text: &str) -> Result<(f64, f64), String> {
    let v: Vec<f64> = text.split(',').filter_map(|p| p.trim().parse().ok()).collect();
    match v[..] {
        [a, b] if a > 0.0 && b > 0.0 && a.is_finite() && b.is_finite() => Ok((a, b)),
        _ => Err(format!("--init-sd: expected `accel,pinch` sds > 0, got `{text}`")),
    }
}

/// The models a fresh run starts from: the policy named `policy` (`hand-crafted`
/// with sds `init_sd` = `accel,pinch`, or `neural` drawn from `seed`) and an
/// observation network for `kind` drawn from `seed + 1` (a box network with
/// `offsets` learned or fixed at zero).
pub fn fresh_models(
    policy: &str,
    init_sd: &str,
    kind: ObservationKind,
    offsets: DetectionOffsets,
    seed: u64,
) -> Result<Models, String> {
    let policy = match policy {
        "hand-crafted" => {
            let (a, p) = parse_sds(init_sd)?;
            AnyPolicy::HandCrafted(HandCraftedPolicy::new(a.ln(), p.ln()).map_err(|e| e.to_string())?)
        }
        "neural" => {
            use rand::SeedableRng;
            AnyPolicy::Neural(NeuralPolicy::new(&mut rand::rngs::StdRng::seed_from_u64(seed)))
        }
        other => return Err(format!("--policy: expected hand-crafted or neural, got `{other}`")),
    };
    Ok(Models::initial_with_offsets(kind, policy, seed.wrapping_add(1), offsets))
}

/// The store training starts from.
fn initial_store(args: &TrainArgs, data: &Dataset) -> Result<ParamStore<f64>, String> {
    if let Some(path) = &args.init {
        let store = ParamStore::load(path).map_err(|e| format!("{}: {e}", path.display()))?;
        Models::from_store(&store, data.kind()).map_err(|e| format!("{}: {e}", path.display()))?;
        return Ok(store);
    }
    Ok(fresh_models(&args.policy, &args.init_sd, data.kind(), args.detection_offsets, args.seed)?.to_store())
}

/// The catalogue extension `id`, refused with the reason where it means nothing
/// for observations of `kind`.
pub fn extension_for(id: &str, kind: ObservationKind) -> Result<Extension, String> {
    let extension = Extension::from_id(id).map_err(|e| format!("--extension: {e}"))?;
    if !extension.applies_to(kind) {
        return Err(format!("--extension {id}: not an extension of a model of {kind:?} observations"));
    }
    Ok(extension)
}

/// Reads `eval.csv` in `dir`: the step column and the named metric.
pub fn read_eval_curve(dir: &Path, metric: &str) -> Result<Curve, String> {
    let path = dir.join(EVAL_LOG);
    let mut reader = csv::Reader::from_path(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let headers = reader.headers().map_err(|e| format!("{}: {e}", path.display()))?.clone();
    let col = headers.iter().position(|h| h == metric).ok_or_else(|| format!("{}: no `{metric}`", path.display()))?;
    let mut points = Vec::new();
    for row in reader.records() {
        let row = row.map_err(|e| format!("{}: {e}", path.display()))?;
        let x: f64 = row[0].parse().map_err(|_| format!("{}: bad step `{}`", path.display(), &row[0]))?;
        let y: f64 = row[col].parse().unwrap_or(f64::NAN);
        points.push((x, y));
    }
    Ok(points)
}

/// The training data this process holds and the test data. A job of one reads
/// both whole. On a job of many, each process reads the training data's layout,
/// then only the objects it owns ([`owned_objects`]); only the first process,
/// which evaluates, reads the test objects (the others hold the test scenes
/// without objects).
fn read_data(args: &TrainArgs, config: &ObjectiveConfig, cluster: &Cluster) -> Result<(Dataset, Dataset), String> {
    let read = |dir: &Path| Dataset::read(dir).map_err(|e| e.to_string());
    if cluster.size() == 1 {
        return Ok((read(&args.data)?, read(&args.test)?));
    }
    let layout = Dataset::read_layout(&args.data).map_err(|e| e.to_string())?;
    let owned = owned_objects(&layout, config, cluster.rank(), cluster.size());
    let keep: HashSet<(i64, i64)> = owned.iter().map(|&o| layout.objects[o]).collect();
    let data = Dataset::read_shard(&args.data, &keep).map_err(|e| e.to_string())?;
    let test = if cluster.is_root() {
        read(&args.test)?
    } else {
        Dataset::read_shard(&args.test, &HashSet::new()).map_err(|e| e.to_string())?
    };
    Ok((data, test))
}

/// Whether `args` continue the run described by `before`: the same settings, with
/// the origin moves compared as the filters they give on data of `kind` (a run
/// described before the option existed, or with the default rule, resumes with an
/// explicit count that gives the same filters, and the other way round).
fn same_run(
    before: &TrainArgs,
    args: &TrainArgs,
    estimator: &Estimator,
    kind: ObservationKind,
) -> Result<bool, String> {
    let filters = |a: &TrainArgs| -> Result<_, String> {
        Ok((a.filter.tempering_for(estimator, kind)?, a.filter.tempering_of(a.eval_filter, kind)?))
    };
    let rest = |a: &TrainArgs| TrainArgs {
        resume: false,
        filter: FilterArgs { temper_origin_steps: None, ..a.filter.clone() },
        ..a.clone()
    };
    Ok(rest(before) == rest(args) && filters(before)? == filters(args)?)
}

/// Runs one training run as one process of `cluster` (of one, but for `sefi
/// train` under mpiexec); `bar` shows its progress (hidden for none). Only the
/// first process writes files, and it claims `--out` for the run's length
/// ([`claim_or_refuse`]): a directory another process is training is refused.
pub fn train_run(args: &TrainArgs, bar: &ProgressBar, cluster: &Cluster) -> Result<TrainOutcome, String> {
    let _claim = if cluster.is_root() { Some(claim_or_refuse(&args.out, "trained")?) } else { None };
    train_claimed_run(args, bar, cluster)
}

/// [`train_run`] for a caller that already holds the claim of `args.out` (or
/// is not the job's first process, which never writes).
pub fn train_claimed_run(args: &TrainArgs, bar: &ProgressBar, cluster: &Cluster) -> Result<TrainOutcome, String> {
    let estimator = Estimator::parse(&args.estimator, args.lag, args.alpha)?;
    if args.particles == 0 || args.eval_particles == 0 {
        return Err("--particles and --eval-particles must be at least 1".into());
    }
    ensure_dir(&args.out)?;
    let run_file = args.out.join("run.json");
    let root = cluster.is_root();
    // The filters' tempering depends on the data's observations (origin moves on
    // boxes), set once they are read.
    let mut config = ObjectiveConfig {
        estimator,
        estimator_config: EstimatorConfig {
            sampling: Sampling::new(args.particles, None),
            chunk_objects: args.chunk_objects.max(1),
            ..EstimatorConfig::default()
        },
        scenes_per_step: args.scenes_per_step,
        eval_particles: args.eval_particles,
        extension: None,
        extension_only: false,
        frozen: Vec::new(),
        base_rate_factor: None,
        proposal: None,
        eval_tempering: None,
    };
    let (data, test) = read_data(args, &config, cluster)?;
    config.extension = args.extension.as_deref().map(|id| extension_for(id, data.kind())).transpose()?;
    if args.resume {
        let text = std::fs::read_to_string(&run_file).map_err(|e| format!("{}: {e}", run_file.display()))?;
        let before: TrainArgs =
            serde_json::from_str(&text).map_err(|e| format!("{}: not a run description: {e}", run_file.display()))?;
        if !same_run(&before, args, &estimator, data.kind())? {
            return Err(format!(
                "{}: the run was started with other settings; resume it with the same arguments",
                run_file.display()
            ));
        }
    }
    config.estimator_config.sampling.tempering = args.filter.tempering_for(&estimator, data.kind())?;
    config.eval_tempering = args.filter.tempering_of(args.eval_filter, data.kind())?;
    let mut initial = initial_store(args, &data)?;
    let held = FittedExtension::from_store(&initial, data.kind()).map_err(|e| e.to_string())?.map(|e| e.extension);
    if let Some(h) = held.filter(|h| Some(*h) != config.extension) {
        return Err(format!(
            "--init holds the extension `{}`: pass --extension {} to go on learning it (a model is extended by one)",
            h.id(),
            h.id()
        ));
    }
    if let Some(e) = config.extension {
        if initial.id(&e.param_name()).is_none() {
            initial.add(&e.param_name(), e.initial());
        }
    }
    match (initial.id(DRIFT_PARAM).is_some(), args.drift) {
        (true, false) => return Err("--init holds a detector drift: pass --drift to go on learning it".into()),
        (false, true) => {
            initial.add(DRIFT_PARAM, DetectorDrift::initial());
        }
        _ => {}
    }
    if args.drift_from_labels {
        if cluster.size() > 1 {
            // Each process holds a share of the objects: calibrations would differ.
            return Err("--drift-from-labels: run it as one process (calibrate once, then --init)".into());
        }
        let c = drift_from_labels(&data).map_err(|e| format!("--drift-from-labels: {e}"))?;
        if root {
            eprintln!(
                "detector drift calibrated on {} labelled detections ({} left out): {}",
                c.used,
                c.left_out,
                c.drift.describe(data.meta().dt)
            );
        }
        let id = initial.id(DRIFT_PARAM).expect("added above");
        *initial.get_mut(id) = Tensor::from_vec(c.drift.to_raw());
        config.frozen.push(DRIFT_PARAM.into());
    }
    drift_in_store(&initial, data.kind()).map_err(|e| format!("--drift: {e}"))?;
    let mut objective = SceneObjective::new(&data, test, config)?.with_collective(cluster.collective());
    let train_config = TrainConfig {
        lr: args.lr,
        final_lr: args.final_lr,
        clip: args.clip,
        epochs: args.epochs,
        eval_every: args.eval_every,
        checkpoint_every: args.checkpoint_every.max(1),
        seed: args.seed,
        shuffle: true,
        keep_best: args.keep_best.then(|| ssm::training::objective::TEST_MLL.to_string()),
        average_tail: args.average_tail,
    };
    let description = serde_json::to_value(args).map_err(|e| e.to_string())?;
    if !args.resume && root {
        // Refuse before writing anything if the directory holds a run.
        if args.out.join(ssm::training::CHECKPOINT_FILE).exists() {
            return Err(format!(
                "{} already holds a training run: pass --resume to continue it or choose another --out",
                args.out.display()
            ));
        }
        write_json(&run_file, &description)?;
    }
    let mut last_mll = f64::NAN;
    let mut on_event = |e: &TrainEvent| match e {
        TrainEvent::Started { total_steps, first_step } => {
            bar.set_length(*total_steps as u64);
            bar.set_position(first_step.saturating_sub(1) as u64);
        }
        TrainEvent::Step { step, ll_per_unit, .. } => {
            cluster.inject_failure(*step);
            bar.set_position(*step as u64);
            bar.set_message(format!("train {ll_per_unit:.3} nats/pt, test {last_mll:.3}"));
        }
        TrainEvent::Evaluated { metrics, .. } => {
            if let Some((_, v)) = metrics.iter().find(|(n, _)| n == "test_mll") {
                last_mll = *v;
            }
        }
        TrainEvent::Checkpointed { .. } => {}
    };
    let outcome = train(&mut objective, initial, &train_config, &args.out, args.resume, &mut on_event)
        .map_err(|e| e.to_string())?;
    if !root {
        return Ok(outcome);
    }
    let curve = read_eval_curve(&args.out, "test_mll")?;
    let series = [Series { name: args.estimator.clone(), points: curve }];
    line_chart(
        &args.out.join("curve.svg"),
        "Test MLL during training",
        "training step",
        "test MLL (nats/point)",
        &series,
    )?;
    Ok(outcome)
}

/// A progress bar for training.
pub fn bar(prefix: &str) -> ProgressBar {
    ProgressBar::new(0).with_prefix(prefix.to_string()).with_style(
        ProgressStyle::with_template("{prefix:>16} {bar:30} {pos}/{len} steps ({elapsed}, eta {eta}) {msg}")
            .expect("valid template"),
    )
}

/// Runs `sefi train` as one process of `cluster`.
pub fn run(args: &TrainArgs, cluster: &Cluster) -> Result<(), String> {
    let bar = if cluster.is_root() { bar(&args.estimator) } else { ProgressBar::hidden() };
    let started = std::time::Instant::now();
    let outcome = train_run(args, &bar, cluster)?;
    bar.finish();
    if !cluster.is_root() {
        return Ok(());
    }
    if cluster.size() > 1 {
        let steps = outcome.steps_run.max(1) as f64;
        println!(
            "{} processes; {:.0} bytes sent per step by this process in the reductions; {:.3} s per step",
            cluster.size(),
            cluster.collective().bytes_sent() as f64 / steps,
            started.elapsed().as_secs_f64() / steps
        );
    }
    println!(
        "{} steps ({} skipped) in {:.1} s; final: {}",
        outcome.steps,
        outcome.skipped_steps,
        outcome.seconds,
        outcome.final_eval.iter().map(|(n, v)| format!("{n} {v:.4}")).collect::<Vec<_>>().join(", ")
    );
    println!("parameters: {}", args.out.join(ssm::training::PARAMS_FILE).display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `sefi train` into a directory another process is training stops before
    /// reading or writing anything and names that process.
    #[test]
    fn a_run_another_process_trains_is_refused() {
        let out = std::env::temp_dir().join(format!("sefi-claimed-run-{}", std::process::id()));
        let _holder = claim_or_refuse(&out, "trained").unwrap();
        let args = TrainArgs::with_defaults("no-train-data".into(), "no-test-data".into(), out.clone());
        let err = train_run(&args, &ProgressBar::hidden(), &Cluster::single()).unwrap_err();
        assert!(err.contains("is being trained by process"), "{err}");
        assert_eq!(std::fs::read_dir(&out).unwrap().count(), 1, "only the lock file is there");
        std::fs::remove_dir_all(&out).unwrap();
    }

    /// A run described before `--temper-origin-steps` existed (read as 0) resumes
    /// under the default rule where that rule gives the same filters (point
    /// sets), and not where it does not (box detections are evaluated with origin
    /// moves); any other change of settings still refuses.
    #[test]
    fn a_run_resumes_when_its_filters_are_the_same() {
        let args = TrainArgs::with_defaults("train".into(), "test".into(), "out".into());
        let estimator = Estimator::parse(&args.estimator, args.lag, args.alpha).expect("the default estimator");
        let old =
            TrainArgs { filter: FilterArgs { temper_origin_steps: Some(0), ..args.filter.clone() }, ..args.clone() };
        assert_eq!(args.filter.temper_origin_steps, None);
        assert!(same_run(&old, &args, &estimator, ObservationKind::Points).unwrap());
        assert!(!same_run(&old, &args, &estimator, ObservationKind::Boxes).unwrap());
        let explicit =
            TrainArgs { filter: FilterArgs { temper_origin_steps: Some(8), ..args.filter.clone() }, ..args.clone() };
        assert!(!same_run(&explicit, &args, &estimator, ObservationKind::Points).unwrap());
        let other_lr = TrainArgs { lr: args.lr * 2.0, ..args.clone() };
        assert!(!same_run(&other_lr, &args, &estimator, ObservationKind::Points).unwrap());
        let decaying = TrainArgs { final_lr: Some(args.lr / 10.0), ..args.clone() };
        assert!(!same_run(&decaying, &args, &estimator, ObservationKind::Points).unwrap());
        // A run description written before `final_lr` existed reads as a constant rate.
        let mut old_json = serde_json::to_value(&args).unwrap();
        old_json.as_object_mut().unwrap().remove("final_lr");
        let old_args: TrainArgs = serde_json::from_value(old_json).unwrap();
        assert!(same_run(&old_args, &args, &estimator, ObservationKind::Points).unwrap());
        let resumed = TrainArgs { resume: true, ..args.clone() };
        assert!(same_run(&args, &resumed, &estimator, ObservationKind::Boxes).unwrap());
    }
}
