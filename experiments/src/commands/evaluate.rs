//! `sefi eval` and `sefi track`: load a dataset and a parameter file, run the
//! particle filter and write the metrics (SPEC §5) or the estimated states.
//!
//! The parameter file is a [`ParamStore`] laid out as [`ssm::models::params`] describes:
//! the policy under `policy` (`policy.log_sd` for the hand-crafted policy,
//! otherwise the neural network `policy.0.w`, ...), the observation network under
//! `obs`. The observation model follows the dataset: points -> point model,
//! boxes -> box-detection model.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use autodiff::nn::ParamStore;
use serde_json::{json, Value};
use ssm::data::{Dataset, ObservationKind, State, STATE_COLUMNS};
use ssm::evaluation::metrics::{self, Metrics, EVAL_LAG, EVAL_PARTICLES};
use ssm::filter::{FilterConfig, Sampling};
use ssm::models::drift::DetectorDrift;
use ssm::models::params::{AnyObservation, Models};

use crate::args::FilterArgs;
use crate::birdseye;
use crate::output::{ensure_dir, write_atomic, write_json};

/// Arguments of `sefi eval`.
#[derive(clap::Args)]
pub struct EvalArgs {
    /// Dataset directory.
    #[arg(long)]
    pub data: PathBuf,
    /// Parameter file (a saved ParamStore: policy under `policy`, observation network under `obs`).
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Particles per object.
    #[arg(long, default_value_t = EVAL_PARTICLES)]
    pub particles: usize,
    /// Fixed lag of the smoothed means (steps).
    #[arg(long, default_value_t = EVAL_LAG)]
    pub lag: usize,
    /// Seed of the filter (run r uses seed + r).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Repeated filter runs (different seeds); metrics are summarised by median and IQR.
    #[arg(long, default_value_t = 1)]
    pub runs: usize,
    /// Output directory (metrics.json, metrics.csv).
    #[arg(long, default_value = "out/eval")]
    pub out: PathBuf,
    #[command(flatten)]
    pub filter: FilterArgs,
}

/// Arguments of `sefi track`.
#[derive(clap::Args)]
pub struct TrackArgs {
    /// Dataset directory.
    #[arg(long)]
    pub data: PathBuf,
    /// Parameter file (a saved ParamStore: policy under `policy`, observation network under `obs`).
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Output directory (smoothed.csv, filtered.csv, track.json, the bird's-eye SVG).
    #[arg(long)]
    pub out: PathBuf,
    /// Fixed lag of the smoothed means (steps).
    #[arg(long, default_value_t = EVAL_LAG)]
    pub lag: usize,
    /// Particles per object.
    #[arg(long, default_value_t = EVAL_PARTICLES)]
    pub particles: usize,
    /// Seed of the filter.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Scene (id as in the files) drawn in the bird's-eye plot; default: the first.
    #[arg(long)]
    pub plot_scene: Option<i64>,
    #[command(flatten)]
    pub filter: FilterArgs,
}

/// Reads the dataset and the models of the parameter file.
fn load(data: &Path, params: Option<&Path>) -> Result<(Dataset, Models), String> {
    let params = params.ok_or_else(|| {
        "--params FILE is required: a parameter file (ParamStore) with the policy under `policy` \
         (`policy.log_sd` or a neural network) and the observation network under `obs`"
            .to_string()
    })?;
    if !params.is_file() {
        return Err(format!("parameter file {} does not exist or is not a file", params.display()));
    }
    let dataset = Dataset::read(data).map_err(|e| format!("dataset {}: {e}", data.display()))?;
    let store = ParamStore::<f64>::load(params).map_err(|e| format!("parameter file {}: {e}", params.display()))?;
    let models =
        Models::from_store(&store, dataset.kind()).map_err(|e| format!("parameter file {}: {e}", params.display()))?;
    Ok((dataset, models))
}

fn check_particles(particles: usize) -> Result<(), String> {
    if particles == 0 {
        return Err("--particles must be at least 1".into());
    }
    Ok(())
}

fn kind_name(kind: ObservationKind) -> &'static str {
    match kind {
        ObservationKind::Points => "points",
        ObservationKind::Boxes => "boxes",
    }
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map_or_else(|| "-".into(), |v| format!("{v:.4}"))
}

fn csv_num(v: Option<f64>) -> String {
    v.map_or_else(String::new, |v| v.to_string())
}

/// The metrics of `runs` filter runs of `models` on `data` with the filter
/// `filter` (run `r` with seed `filter.seed + r`).
pub fn metric_runs(
    data: &Dataset,
    models: &Models,
    filter: &FilterConfig,
    runs: usize,
) -> Result<Vec<Metrics>, String> {
    let mut out = Vec::with_capacity(runs);
    for r in 0..runs {
        let config = FilterConfig { seed: filter.seed.wrapping_add(r as u64), ..filter.clone() };
        let tracks = metrics::track_models(data, models, &config)?;
        out.push(metrics::models_metrics_of(data, models, &tracks, &config));
    }
    Ok(out)
}

/// Runs `sefi eval`.
pub fn eval(args: &EvalArgs) -> Result<(), String> {
    check_particles(args.particles)?;
    if args.runs == 0 {
        return Err("--runs must be at least 1".into());
    }
    let (data, models) = load(&args.data, args.params.as_deref())?;
    ensure_dir(&args.out)?;
    let extension = extension_described(&models, data.meta().dt)?;
    eprintln!(
        "eval: {} objects x {} steps ({}), {} policy{}, {} particles, lag {}, {} run(s)",
        data.objects().len(),
        data.steps(),
        kind_name(data.kind()),
        models.policy.name(),
        extension.as_ref().map_or_else(String::new, |e| format!(", extended: {e}")),
        args.particles,
        args.lag,
        args.runs
    );
    let filter =
        FilterConfig::new(Sampling::new(args.particles, args.filter.tempering(data.kind())?), args.lag, args.seed);
    let runs = metric_runs(&data, &models, &filter, args.runs)?;
    let summary = metrics::summarise_runs(&runs);

    // Print: a value per metric, or median [q1, q3] over runs.
    let mut text = String::new();
    for (name, s) in &summary {
        match s {
            Some(s) if runs.len() > 1 => {
                let _ = writeln!(text, "{name:>16}  {:.4}  [IQR {:.4} .. {:.4}]", s.median, s.q1, s.q3);
            }
            Some(s) => {
                let _ = writeln!(text, "{name:>16}  {}", fmt_opt(Some(s.median)));
            }
            None => {
                let _ = writeln!(text, "{name:>16}  -");
            }
        }
    }
    let terms = aotll_terms(&data, &models);
    if let Some(terms) = &terms {
        let name = args.params.as_ref().map_or_else(String::new, |p| p.display().to_string());
        let _ = write!(text, "\n{}", aotll_by_part_table("AOTLL by part (labelled detections)", &[(&name, terms)]));
    }
    print!("{text}");

    // metrics.csv: one row per run.
    let names: Vec<&str> = runs[0].scalars().iter().map(|(n, _)| *n).collect();
    let mut csv = format!("run,seed,particles,lag,{}\n", names.join(","));
    for (r, m) in runs.iter().enumerate() {
        let values: Vec<String> = m.scalars().iter().map(|(_, v)| csv_num(*v)).collect();
        let _ = writeln!(csv, "{r},{},{},{},{}", m.seed, m.particles, m.lag, values.join(","));
    }
    write_atomic(&args.out.join("metrics.csv"), csv.as_bytes())?;

    let summary_json: serde_json::Map<String, Value> =
        summary.iter().map(|(n, s)| (n.to_string(), serde_json::to_value(s).unwrap_or(Value::Null))).collect();
    let doc = json!({
        "dataset": args.data.display().to_string(),
        "params": args.params.as_ref().map(|p| p.display().to_string()),
        "observation": kind_name(data.kind()),
        "policy": models.policy.name(),
        "extension": models.extension.as_ref().map(|e| json!({
            "id": e.extension.id(),
            "raw": e.raw,
            "described": extension,
        })),
        "objects": data.objects().len(),
        "steps": data.steps(),
        "particles": args.particles,
        "lag": args.lag,
        "summary": summary_json,
        "aotll_terms": terms,
        "runs": runs,
    });
    write_json(&args.out.join("metrics.json"), &doc)?;
    eprintln!("wrote {} and {}", args.out.join("metrics.json").display(), args.out.join("metrics.csv").display());
    Ok(())
}

/// The catalogue extension `models` were learned with, in one sentence
/// ([`ssm::models::extended::Extension::describe`]); the filter, MLL and AOTLL
/// use it.
fn extension_described(models: &Models, dt: f64) -> Result<Option<String>, String> {
    let extension =
        models.extension.as_ref().map(|e| e.extension.describe(&e.raw).map_err(|err| err.to_string())).transpose()?;
    let drift = models
        .drift
        .as_deref()
        .map(|raw| DetectorDrift::from_raw(raw).map(|d| format!("detector drift ({})", d.describe(dt))))
        .transpose()
        .map_err(|err| err.to_string())?;
    let parts: Vec<String> = extension.into_iter().chain(drift).collect();
    Ok((!parts.is_empty()).then(|| parts.join("; ")))
}

/// AOTLL by part ([`metrics::box_aotll_terms`]) of `models` on `data`: `None`
/// unless the data are labelled box detections.
pub fn aotll_terms(data: &Dataset, models: &Models) -> Option<metrics::BoxAotllTerms> {
    match &models.observation {
        AnyObservation::Boxes(model) => metrics::box_aotll_terms(data, model, &models.observation_params),
        AnyObservation::Points(_) => None,
    }
}

/// A markdown table of AOTLL by part, one row per `(name, terms)` under `title`
/// (`sefi eval` and `sefi experiment-c` both print it): what the detections with
/// reversed headings carry, and the others' mean with its factors, for every car,
/// cars along the line of sight and cars crossing it, each with the network's mean
/// scales beside the labels' mean absolute offsets.
pub fn aotll_by_part_table(title: &str, rows: &[(&str, &metrics::BoxAotllTerms)]) -> String {
    let mut md = format!(
        "{title}: the detections whose heading is more than pi/2 from the label's (mean, and what they carry of \
         AOTLL), and the others' mean with its along / across / yaw factors (they sum to it); beside each group of \
         the others, its mean and the network's mean scales (along m / across m / yaw rad) against the labels' mean \
         absolute offsets from the network's means.\n\n| model | reversed: mean (carried) | others: mean (along / \
         across / yaw) | cars within 45 deg of the line of sight: mean, scales (labels) | cars crossing it: mean, \
         scales (labels) |\n|---|---|---|---|---|\n",
    );
    let num = |m: &metrics::MeanOver| m.mean.map_or_else(|| "-".into(), |v| format!("{v:.3}"));
    let group = |g: &metrics::FactorTerms| {
        let (b, o) = (g.mean_scales, g.mean_abs_offsets);
        format!(
            "{} ({} detections), {:.3} / {:.3} / {:.3} ({:.3} / {:.3} / {:.3})",
            num(&g.total),
            g.total.count,
            b.0,
            b.1,
            b.2,
            o.0,
            o.1,
            o.2
        )
    };
    for (name, t) in rows {
        let _ = writeln!(
            md,
            "| {name} | {} ({:.3}; {} detections) | {} ({} / {} / {}) | {} | {} |",
            num(&t.reversed),
            t.reversed_contribution,
            t.reversed.count,
            num(&t.others.total),
            num(&t.others.along),
            num(&t.others.across),
            num(&t.others.yaw),
            group(&t.in_line),
            group(&t.crossing)
        );
    }
    md
}

/// The estimates as a `states.csv` table (`scene,object,t,x,y,yaw,v,kappa`).
fn states_csv(data: &Dataset, estimates: &[Vec<State>]) -> String {
    let mut s = STATE_COLUMNS.join(",");
    s.push('\n');
    for (object, rows) in estimates.iter().enumerate() {
        let o = &data.objects()[object];
        for (t, e) in rows.iter().enumerate() {
            let _ = writeln!(s, "{},{},{t},{},{},{},{},{}", o.scene, o.id, e.x, e.y, e.yaw, e.v, e.kappa);
        }
    }
    s
}

/// Runs `sefi track`.
pub fn track(args: &TrackArgs) -> Result<(), String> {
    check_particles(args.particles)?;
    let (data, models) = load(&args.data, args.params.as_deref())?;
    let scene = match args.plot_scene {
        Some(id) => data.find_scene(id).ok_or_else(|| {
            let ids: Vec<String> = data.scenes().iter().take(10).map(|s| s.id.to_string()).collect();
            format!("--plot-scene {id}: no such scene in {} (scenes: {} ...)", args.data.display(), ids.join(", "))
        })?,
        None => 0,
    };
    ensure_dir(&args.out)?;
    let config =
        FilterConfig::new(Sampling::new(args.particles, args.filter.tempering(data.kind())?), args.lag, args.seed);
    eprintln!(
        "track: {} objects x {} steps ({}), {} policy, {} particles, lag {}",
        data.objects().len(),
        data.steps(),
        kind_name(data.kind()),
        models.policy.name(),
        args.particles,
        args.lag
    );
    let tracks = metrics::track_models(&data, &models, &config)?;
    write_atomic(&args.out.join("smoothed.csv"), states_csv(&data, &tracks.smoothed).as_bytes())?;
    write_atomic(&args.out.join("filtered.csv"), states_csv(&data, &tracks.filtered).as_bytes())?;
    let m = metrics::models_metrics_of(&data, &models, &tracks, &config);
    let scene_id = data.scenes()[scene].id;
    let svg = args.out.join(format!("birdseye_scene_{scene_id}.svg"));
    birdseye::draw(&svg, &data, scene, &tracks, args.lag)?;
    let doc = json!({
        "dataset": args.data.display().to_string(),
        "observation": kind_name(data.kind()),
        "policy": models.policy.name(),
        "particles": args.particles,
        "lag": args.lag,
        "seed": args.seed,
        "metrics": m,
        "files": {
            "smoothed": "smoothed.csv",
            "filtered": "filtered.csv",
            "birdseye": svg.file_name().map(|n| n.to_string_lossy().into_owned()),
        },
    });
    write_json(&args.out.join("track.json"), &doc)?;
    println!(
        "mll {}  ade smoothed {}  ade filtered {}",
        fmt_opt(m.mll),
        fmt_opt(m.smoothed.ade),
        fmt_opt(m.filtered.ade)
    );
    eprintln!("wrote smoothed.csv, filtered.csv, track.json and {} to {}", svg.display(), args.out.display());
    Ok(())
}
