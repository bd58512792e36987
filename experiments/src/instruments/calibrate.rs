//! `sefi score-at` and `sefi precision`: an estimator's mean score at given
//! parameters (zero within noise at the truth of generated data) and the
//! precision of the filter's likelihood estimate.

use std::path::{Path, PathBuf};

use autodiff::nn::ParamStore;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;
use ssm::data::Dataset;
use ssm::estimators::{Estimator, EstimatorConfig};
use ssm::evaluation::calibration::{
    complete_data_score_at, likelihood_precision, score_at, LikelihoodPrecision, ScoreAt,
};
use ssm::filter::{FilterConfig, Sampling};

use crate::args::{FilterArgs, FilterKind};
use crate::output::{ensure_dir, write_json};

/// Arguments of `sefi score-at`.
#[derive(clap::Args)]
pub struct ScoreAtArgs {
    /// Dataset directory.
    #[arg(long)]
    pub data: PathBuf,
    /// Parameter file (the truth of generated data: `true_params.bin`).
    #[arg(long)]
    pub params: PathBuf,
    /// Estimator: pf-sefi, pf, dpf-sgr, dpf-sgr-stopped or pfnet; or `complete-data`,
    /// the score of the ground-truth states and actions (no filter): the reference.
    #[arg(long, default_value = "pf-sefi")]
    pub estimator: String,
    /// PF-SEFI's fixed lag.
    #[arg(long, default_value_t = 8)]
    pub lag: usize,
    /// PFNET's mixing alpha.
    #[arg(long, default_value_t = 0.8)]
    pub alpha: f64,
    /// Particles per object.
    #[arg(long, default_value_t = 1024)]
    pub particles: usize,
    /// Filter runs per object (seeds seed..seed+runs).
    #[arg(long, default_value_t = 4)]
    pub runs: usize,
    /// First filter seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Use only the first K scenes.
    #[arg(long)]
    pub scenes: Option<usize>,
    #[command(flatten)]
    pub filter: FilterArgs,
    /// Write score_at.json here.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Arguments of `sefi precision`.
#[derive(clap::Args)]
pub struct PrecisionArgs {
    /// Dataset directory.
    #[arg(long)]
    pub data: PathBuf,
    /// Parameter file.
    #[arg(long)]
    pub params: PathBuf,
    /// Particle counts to compare, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1024,4096")]
    pub particles: Vec<usize>,
    /// Filter runs per object (seeds seed..seed+runs).
    #[arg(long, default_value_t = 8)]
    pub runs: usize,
    /// First filter seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Use only the first K scenes.
    #[arg(long)]
    pub scenes: Option<usize>,
    /// Compare both filters (bootstrap and tempered) instead of the one chosen by --filter.
    #[arg(long)]
    pub both: bool,
    #[command(flatten)]
    pub filter: FilterArgs,
    /// Write precision.json here.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

fn load(data: &Path, params: &Path, scenes: Option<usize>) -> Result<(Dataset, ParamStore<f64>), String> {
    let dataset = Dataset::read(data).map_err(|e| format!("dataset {}: {e}", data.display()))?;
    let dataset = match scenes {
        Some(0) => return Err("--scenes must be at least 1".into()),
        Some(k) if k < dataset.scenes().len() => dataset.select_scenes(&(0..k).collect::<Vec<_>>()),
        _ => dataset,
    };
    if !params.is_file() {
        return Err(format!("parameter file {} does not exist or is not a file", params.display()));
    }
    let store = ParamStore::<f64>::load(params).map_err(|e| format!("parameter file {}: {e}", params.display()))?;
    Ok((dataset, store))
}

fn progress(len: usize, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len as u64);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} ({eta})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

/// Prints one line per small tensor entry, one summary line per large tensor,
/// and the spread of one object's score norm over objects.
fn print_score(s: &ScoreAt, data: &Dataset, filter: &str) {
    println!(
        "{} ({filter} filter), {} objects x {} runs, {:.1} s, collapsed steps {}",
        s.estimator, s.objects, s.runs, s.seconds, s.collapsed_steps
    );
    println!("{:<28} {:>12} {:>12} {:>8} {:>12}", "parameter", "mean", "se", "z", "sd/object");
    for t in &s.tensors {
        if t.entries.len() <= 4 {
            for (j, e) in t.entries.iter().enumerate() {
                let name = format!("{}[{j}]", t.name);
                println!("{name:<28} {:>12.4e} {:>12.4e} {:>8.2} {:>12.4e}", e.mean, e.se, e.z, e.sd);
            }
        } else {
            println!(
                "{:<28} {:>12} entries, max |z| {:>6.2}, Bonferroni p {:.3}",
                t.name,
                t.entries.len(),
                t.max_abs_z,
                t.p
            );
        }
    }
    let n = &s.object_norms;
    let largest: Vec<String> = n
        .largest
        .iter()
        .map(|&(o, norm)| {
            let object = &data.objects()[o];
            format!("scene {} object {}: {norm:.3e}", object.scene, object.id)
        })
        .collect();
    println!(
        "one object's score norm over objects: median {:.3e}, 90% {:.3e}, max {:.3e} (largest: {})",
        n.median,
        n.q90,
        n.max,
        largest.join("; ")
    );
}

/// `sefi score-at`.
pub fn run_score_at(args: &ScoreAtArgs) -> Result<(), String> {
    let (data, store) = load(&args.data, &args.params, args.scenes)?;
    if args.estimator == "complete-data" {
        let s = complete_data_score_at(&data, &store)?;
        print_score(&s, &data, "no");
        if let Some(out) = &args.out {
            ensure_dir(out)?;
            write_json(&out.join("score_at.json"), &json!({ "filter": "none", "result": s }))?;
        }
        return Ok(());
    }
    let estimator = Estimator::parse(&args.estimator, args.lag, args.alpha)?;
    if args.particles == 0 {
        return Err("--particles must be at least 1".into());
    }
    let config =
        EstimatorConfig::new(Sampling::new(args.particles, args.filter.tempering_for(&estimator, data.kind())?));
    let filter = if config.sampling.tempering.is_some() { "tempered" } else { "bootstrap" };
    let bar = progress(data.objects().len(), "objects");
    let s = score_at(&data, &store, &estimator, &config, args.runs, args.seed, &|| bar.inc(1))?;
    bar.finish_and_clear();
    print_score(&s, &data, filter);
    if let Some(out) = &args.out {
        ensure_dir(out)?;
        write_json(&out.join("score_at.json"), &json!({ "filter": filter, "particles": args.particles, "result": s }))?;
    }
    Ok(())
}

/// `sefi precision`.
pub fn run_precision(args: &PrecisionArgs) -> Result<(), String> {
    let (data, store) = load(&args.data, &args.params, args.scenes)?;
    let filters: Vec<FilterArgs> = if args.both {
        [FilterKind::Bootstrap, FilterKind::Tempered]
            .map(|filter| FilterArgs { filter, ..args.filter.clone() })
            .to_vec()
    } else {
        vec![args.filter.clone()]
    };
    if args.particles.is_empty() || args.particles.contains(&0) {
        return Err("--particles: give positive particle counts".into());
    }
    println!(
        "{:<10} {:>6} {:>10} {:>10} {:>10} {:>10} {:>10} {:>9} {:>8} {:>9}",
        "filter", "N", "sd median", "sd p95", "ESS mean", "ESS t=0", "ESS min", "evals/st", "MLL", "s/run"
    );
    let mut rows = Vec::new();
    for f in &filters {
        for &n in &args.particles {
            let config = FilterConfig::new(Sampling::new(n, f.tempering(data.kind())?), 0, args.seed);
            let p: LikelihoodPrecision = likelihood_precision(&data, &store, &config, args.runs)?;
            let mean_ess = p.ess_per_step.iter().sum::<f64>() / p.ess_per_step.len() as f64;
            let min_ess = p.min_ess_per_step.iter().copied().fold(f64::INFINITY, f64::min);
            println!(
                "{:<10} {:>6} {:>10.3} {:>10.3} {:>10.3} {:>10.3} {:>10.4} {:>9.2} {:>8.4} {:>9.2}",
                f.name(),
                n,
                p.median_sd,
                p.p95_sd,
                mean_ess,
                p.ess_per_step[0],
                min_ess,
                p.evaluations_per_step,
                p.mll,
                p.seconds_per_run
            );
            rows.push(json!({ "filter": f.name(), "result": p }));
        }
    }
    if let Some(out) = &args.out {
        ensure_dir(out)?;
        write_json(&out.join("precision.json"), &json!(rows))?;
    }
    Ok(())
}
