//! `sefi reproduce --exp A|B`: the paper's synthetic experiments end to end.
//!
//! 1. Generates the experiment's data into `OUT/data` (or reuses it).
//! 2. Evaluates TRUE (the generating parameters) on the test scenes.
//! 3. Trains PF-SEFI, DPF-SGR, PFNET and PF from the same initialisation per seed
//!    (`OUT/runs/<method>-seed<k>`, each a `sefi train` directory; an interrupted
//!    reproduce resumes every unfinished run from its checkpoint). Each run is
//!    claimed while it trains, so several `reproduce` commands on one `OUT` (one
//!    per core, say) share the runs: each skips the runs another is training.
//! 4. Evaluates each learned model on the test scenes and writes the table of SPEC
//!    §5 metrics (median and interquartile range over seeds) as `OUT/table.csv`
//!    and `OUT/table.md`, the test-MLL curves as `OUT/curves.svg`, and everything
//!    (per-run metrics, learned policy sds, timings) as `OUT/reproduce.json`.
//!
//! Scales: `--quick` (tiny data, a few minutes: for tests), the default (paper-size
//! data, fewer particles and epochs: about two hours for A on two cores) and
//! `--paper` (the paper's settings: 1024 training / 4096 evaluation particles,
//! 100 epochs, L = 8, alpha = 0.8).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use autodiff::nn::ParamStore;
use serde::Serialize;
use serde_json::json;
use ssm::data::Dataset;
use ssm::evaluation::metrics::Metrics;
use ssm::filter::{FilterConfig, Sampling};
use ssm::models::params::{AnyPolicy, Models};
use ssm::models::vehicle::{GaussianPolicy, HandCraftedPolicy};
use ssm::stats::Summary;
use ssm::training::PARAMS_FILE;

use crate::args::check_method;
use crate::cluster::Cluster;
use crate::commands::evaluate::metric_runs;
use crate::commands::generate::{self, GenerateArgs};
use crate::commands::train::{self, read_eval_curve, RunScale, TrainArgs};
use crate::output::{claim_dir, claim_or_refuse, ensure_dir, write_atomic, write_json, Claim};
use crate::plot::{line_chart, Curve, Series};
use crate::table::{csv_row, header, metric_cells, summary_cell, TableArgs, CSV_HEADER, DEFAULT_METHODS};

/// Arguments of `sefi reproduce`.
#[derive(clap::Args)]
pub struct ReproduceArgs {
    /// Experiment: A (25 steps) or B (50 steps).
    #[arg(long, default_value = "A")]
    pub exp: String,
    /// Output directory (default: `results/reproduce-<exp>-paper` with --paper, whose
    /// small files are meant to be committed so that runs accumulate; otherwise
    /// `out/reproduce-<exp>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Scale (`--paper`: 1024 / 4096 particles, 100 epochs), methods and filters.
    #[command(flatten)]
    pub table: TableArgs,
    /// Seeds per method (default: 2 quick, 3 otherwise).
    #[arg(long)]
    pub seeds: Option<usize>,
    /// Train nothing: rebuild the table, curves and plots from the finished runs.
    #[arg(long)]
    pub table_only: bool,
}

/// The sizes of a reproduction.
#[derive(Clone, Debug, Serialize)]
struct Scale {
    name: &'static str,
    particles: usize,
    eval_particles: usize,
    epochs: usize,
    seeds: usize,
    eval_every: usize,
    lag: usize,
    alpha: f64,
}

impl Scale {
    fn of(args: &ReproduceArgs) -> Scale {
        let mut s = if args.table.quick {
            Scale {
                name: "quick",
                particles: 64,
                eval_particles: 256,
                epochs: 4,
                seeds: 2,
                eval_every: 2,
                lag: 8,
                alpha: 0.8,
            }
        } else if args.table.paper {
            Scale {
                name: "paper",
                particles: 1024,
                eval_particles: 4096,
                epochs: 100,
                seeds: 3,
                eval_every: 50,
                lag: 8,
                alpha: 0.8,
            }
        } else {
            Scale {
                name: "default",
                particles: 256,
                eval_particles: 4096,
                epochs: 10,
                seeds: 3,
                eval_every: 10,
                lag: 8,
                alpha: 0.8,
            }
        };
        if let Some(k) = args.seeds {
            s.seeds = k.max(1);
        }
        if let Some(e) = args.table.epochs {
            s.epochs = e.max(1);
        }
        if let Some(n) = args.table.particles {
            s.particles = n.max(1);
        }
        s
    }
}

/// One method's results over seeds.
#[derive(Clone)]
struct MethodResult {
    method: String,
    runs: Vec<Metrics>,
    /// Learned (sd accel, sd pinch) per seed, for the hand-crafted policy.
    sds: Vec<(f64, f64)>,
    /// Test MLL against training step, per seed.
    curves: Vec<Curve>,
    /// The policy's sds (accel, pinch) against training step, per seed.
    sd_curves: Vec<(Curve, Curve)>,
    /// Training seconds, summed over seeds.
    seconds: f64,
}

fn learned_sds(store: &ParamStore<f64>, data: &Dataset) -> Option<(f64, f64)> {
    let models = Models::from_store(store, data.kind()).ok()?;
    match &models.policy {
        AnyPolicy::HandCrafted(_) => {
            let p = models.policy.parameters();
            Some((p[0].data()[0].exp(), p[0].data()[1].exp()))
        }
        AnyPolicy::Neural(_) => None,
    }
}

/// Median over seeds of the curves, at the steps of the first.
fn median_curve(curves: &[Curve]) -> Curve {
    let Some(first) = curves.first() else { return Vec::new() };
    first
        .iter()
        .enumerate()
        .filter_map(|(i, &(x, _))| {
            let ys: Vec<f64> = curves.iter().filter_map(|c| c.get(i)).map(|p| p.1).filter(|y| y.is_finite()).collect();
            ssm::stats::median(&ys).map(|m| (x, m))
        })
        .collect()
}

/// The output directory of `args`.
fn out_dir(args: &ReproduceArgs) -> PathBuf {
    args.out.clone().unwrap_or_else(|| {
        let exp = args.exp.to_uppercase();
        if args.table.paper {
            PathBuf::from(format!("results/reproduce-{exp}-paper"))
        } else {
            PathBuf::from(format!("out/reproduce-{exp}"))
        }
    })
}

/// Where a finished run keeps its final test metrics, with the evaluation's settings.
const FINAL_METRICS: &str = "final_metrics.json";

/// Metrics cached in `path` for the evaluation `key` (`filter` and `runs`), if
/// they are there: the first `runs` of a cache with as many or more runs of the
/// same filter (run `r` is the filter's seed plus `r`, whatever the count).
fn cached_metrics(path: &Path, key: &serde_json::Value) -> Option<Vec<Metrics>> {
    let text = std::fs::read_to_string(path).ok()?;
    let doc: serde_json::Value = serde_json::from_str(&text).ok()?;
    let runs = key.get("runs")?.as_u64()? as usize;
    if doc.get("evaluation")?.get("filter")? != key.get("filter")? {
        return None;
    }
    let metrics: Vec<Metrics> = serde_json::from_value(doc.get("metrics")?.clone()).ok()?;
    (metrics.len() >= runs).then(|| metrics.into_iter().take(runs).collect())
}

/// `metric_runs` of `models`, cached in `path` under the evaluation `key`.
fn evaluate_cached(
    path: &Path,
    key: &serde_json::Value,
    evaluate: impl FnOnce() -> Result<Vec<Metrics>, String>,
) -> Result<Vec<Metrics>, String> {
    if let Some(m) = cached_metrics(path, key) {
        return Ok(m);
    }
    let metrics = evaluate()?;
    write_json(path, &json!({ "evaluation": key, "metrics": metrics }))?;
    Ok(metrics)
}

/// The `sefi train` arguments of `method`'s run with `seed`, in `dir`: the
/// command line's defaults (the hand-crafted policy from sds 1.0 and 0.1, Adam at
/// 0.01 without clipping, one scene per step) at the scale's settings, resuming
/// from a checkpoint found in `dir`.
fn run_args(args: &ReproduceArgs, scale: &Scale, data_dir: &Path, method: &str, seed: u64, dir: &Path) -> TrainArgs {
    let run = RunScale::new(scale.lag, scale.alpha, scale.particles, scale.eval_particles, scale.epochs);
    let (train, test) = (data_dir.join("train"), data_dir.join("test"));
    TrainArgs {
        eval_every: scale.eval_every,
        checkpoint_every: scale.eval_every,
        seed,
        ..TrainArgs::for_method(method, &args.table.filter, run, &train, &test, dir)
    }
}

/// Runs `sefi reproduce` as one process of `cluster`. On a job of many processes
/// (`mpiexec`), the first generates the data while the others wait, every
/// process trains every run together (each holding its share of the training
/// objects, [`train::train_run`]), and only the first evaluates and writes the
/// table.
pub fn run(args: &ReproduceArgs, cluster: &Cluster) -> Result<(), String> {
    let started = Instant::now();
    let scale = Scale::of(args);
    let out = out_dir(args);
    for m in &args.table.methods {
        check_method(m, scale.lag, scale.alpha)?;
    }
    let data_dir = out.join("data");
    if !cluster.is_root() {
        cluster.wait_for_first(true);
        return train_runs(args, &scale, &data_dir, cluster);
    }
    ensure_dir(&out)?;
    let generated = if !data_dir.join("generate.json").is_file() {
        generate::run(&GenerateArgs {
            strength: 1.0,
            exp: args.exp.clone(),
            out: data_dir.clone(),
            seed: 0,
            quick: args.table.quick,
            hidden: None,
            boxes: false,
            scenes: 0,
            objects: 0,
            steps: 0,
            like: None,
            params: None,
        })
    } else {
        eprintln!("reusing the data in {} (regenerated bit for bit from its seed when absent)", data_dir.display());
        Ok(())
    };
    cluster.wait_for_first(generated.is_ok());
    generated?;
    let test = Dataset::read(data_dir.join("test")).map_err(|e| e.to_string())?;
    let train_data = Dataset::read(data_dir.join("train")).map_err(|e| e.to_string())?;
    let eval_filter = |seed: u64| -> Result<FilterConfig, String> {
        let tempering = args.table.filter.tempering(test.kind())?;
        Ok(FilterConfig::new(Sampling::new(scale.eval_particles, tempering), scale.lag, seed))
    };
    let eval_key = |seed: u64, runs: usize| -> Result<serde_json::Value, String> {
        Ok(json!({ "filter": eval_filter(seed)?, "runs": runs }))
    };

    // TRUE: the generating parameters, one evaluation per seed.
    let true_path = data_dir.join("true_params.bin");
    let true_store = ParamStore::<f64>::load(&true_path).map_err(|e| format!("{}: {e}", true_path.display()))?;
    let true_models = Models::from_store(&true_store, test.kind()).map_err(|e| e.to_string())?;
    let clock = Instant::now();
    let true_runs = evaluate_cached(&out.join("true_metrics.json"), &eval_key(1000, scale.seeds)?, || {
        eprintln!("evaluating TRUE ({} runs, {} particles)", scale.seeds, scale.eval_particles);
        metric_runs(&test, &true_models, &eval_filter(1000)?, scale.seeds)
    })?;
    let truth = MethodResult {
        method: "TRUE".into(),
        runs: true_runs,
        sds: learned_sds(&true_store, &test).into_iter().collect(),
        curves: Vec::new(),
        sd_curves: Vec::new(),
        seconds: clock.elapsed().as_secs_f64(),
    };
    // Seed-major: after each round every method has one more finished run, so a
    // table with all methods exists early and grows. The table holds every
    // finished run in `out`, whichever command trained it (a run of some
    // methods or seeds leaves the others in the table).
    let steps_per_run = scale.epochs * train_data.scenes().len();
    let evaluate_run = |dir: &Path, seed: u64| -> Result<Vec<Metrics>, String> {
        let store = ParamStore::<f64>::load(&dir.join(PARAMS_FILE)).map_err(|e| e.to_string())?;
        let models = Models::from_store(&store, test.kind()).map_err(|e| e.to_string())?;
        evaluate_cached(&dir.join(FINAL_METRICS), &eval_key(2000 + seed, 1)?, || {
            metric_runs(&test, &models, &eval_filter(2000 + seed)?, 1)
        })
    };
    let rounds = if args.table_only { 1 } else { scale.seeds as u64 };
    for seed in 0..rounds {
        if !args.table_only {
            for method in &args.table.methods {
                let dir = out.join("runs").join(format!("{method}-seed{seed}"));
                // The claim covers training and the final evaluation; a run
                // another `reproduce` holds is left to it (one process) or
                // refused (a job of many, whose processes must train together).
                let _claim = if cluster.size() > 1 {
                    claim_or_refuse(&dir, "trained")?
                } else {
                    match claim_dir(&dir)? {
                        Claim::Held(claim) => claim,
                        Claim::Busy(holder) => {
                            eprintln!(
                                "{method} seed {seed}: skipped, {holder} is training it (the table shows it once finished)"
                            );
                            continue;
                        }
                    }
                };
                let bar = train::bar(&format!("{method} s{seed}"));
                train::train_claimed_run(&run_args(args, &scale, &data_dir, method, seed, &dir), &bar, cluster)?;
                bar.finish_and_clear();
                let m = evaluate_run(&dir, seed)?;
                eprintln!(
                    "{method} seed {seed}: test MLL {:.4} ({} steps)",
                    m.last().and_then(|m| m.mll).unwrap_or(f64::NAN),
                    steps_per_run
                );
            }
        }
        let mut all = vec![truth.clone()];
        for method in table_methods(&args.table.methods) {
            let mut result = MethodResult {
                method: method.clone(),
                runs: Vec::new(),
                sds: Vec::new(),
                curves: Vec::new(),
                sd_curves: Vec::new(),
                seconds: 0.0,
            };
            for (seed, dir) in finished_runs(&out, &method)? {
                let store = ParamStore::<f64>::load(&dir.join(PARAMS_FILE)).map_err(|e| e.to_string())?;
                result.runs.append(&mut evaluate_run(&dir, seed)?);
                result.sds.extend(learned_sds(&store, &test));
                result.curves.push(read_eval_curve(&dir, "test_mll")?);
                if let (Ok(a), Ok(p)) = (read_eval_curve(&dir, "sd_accel"), read_eval_curve(&dir, "sd_pinch")) {
                    result.sd_curves.push((a, p));
                }
                result.seconds += train_seconds(&dir).unwrap_or(0.0);
            }
            if !result.runs.is_empty() {
                all.push(result);
            }
        }
        write_outputs(args, &out, &scale, &all, started.elapsed().as_secs_f64())?;
    }
    cluster.print_traffic();
    Ok(())
}

/// The methods of the table: every method of the default list, in its order,
/// then any other of `requested`.
fn table_methods(requested: &[String]) -> Vec<String> {
    let mut methods: Vec<String> = DEFAULT_METHODS.split(',').map(str::to_string).collect();
    methods.extend(requested.iter().filter(|m| !DEFAULT_METHODS.split(',').any(|d| d == m.as_str())).cloned());
    methods
}

/// `method`'s finished runs in `out/runs` (those with final metrics), as
/// `(seed, directory)` in the order of their seeds.
fn finished_runs(out: &Path, method: &str) -> Result<Vec<(u64, PathBuf)>, String> {
    let runs = out.join("runs");
    let entries = match std::fs::read_dir(&runs) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(format!("{}: {e}", runs.display())),
    };
    let prefix = format!("{method}-seed");
    let mut found = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| format!("{}: {e}", runs.display()))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(seed) = name.strip_prefix(&prefix).and_then(|k| k.parse::<u64>().ok()) else { continue };
        if entry.path().join(FINAL_METRICS).is_file() {
            found.push((seed, entry.path()));
        }
    }
    found.sort();
    Ok(found)
}

/// What a process other than the first does in `sefi reproduce`: train every
/// run with the first, in the same order (seed-major), holding its share of the
/// objects; the first process evaluates and writes.
fn train_runs(args: &ReproduceArgs, scale: &Scale, data_dir: &Path, cluster: &Cluster) -> Result<(), String> {
    if args.table_only {
        return Ok(());
    }
    let hidden = indicatif::ProgressBar::hidden();
    for seed in 0..scale.seeds as u64 {
        for method in &args.table.methods {
            let dir = out_dir(args).join("runs").join(format!("{method}-seed{seed}"));
            train::train_run(&run_args(args, scale, data_dir, method, seed, &dir), &hidden, cluster)?;
        }
    }
    Ok(())
}

/// Seconds of training a run's log records (the sum of its steps' times).
fn train_seconds(dir: &Path) -> Option<f64> {
    let mut reader = csv::Reader::from_path(dir.join(ssm::training::TRAIN_LOG)).ok()?;
    let col = reader.headers().ok()?.iter().position(|h| h == "seconds")?;
    Some(reader.records().filter_map(|r| r.ok()?.get(col)?.parse::<f64>().ok()).sum())
}

fn write_outputs(
    args: &ReproduceArgs,
    out: &Path,
    scale: &Scale,
    results: &[MethodResult],
    seconds: f64,
) -> Result<(), String> {
    let truth = HandCraftedPolicy::truth();
    let (true_sd_a, true_sd_p) = (truth.log_sd_accel().exp(), truth.log_sd_pinch().exp());
    let mut md = format!(
        "Experiment {} ({} scale: {} training / {} evaluation particles, {} epochs, L = {}, alpha = {}, {} seeds \
         asked; {:.0} s in this command). Median [IQR] over the finished seeds of each method (`seeds`).\n\n",
        args.exp.to_uppercase(),
        scale.name,
        scale.particles,
        scale.eval_particles,
        scale.epochs,
        scale.lag,
        scale.alpha,
        scale.seeds,
        seconds
    );
    let mut csv = String::from(CSV_HEADER);
    md.push_str(&header(&["sd accel", "sd pinch", "seeds", "train time per run (s)"]));
    for r in results {
        metric_cells(&r.method, &r.runs, &mut md, &mut csv);
        let sd = |f: fn(&(f64, f64)) -> f64| {
            let v: Vec<f64> = r.sds.iter().map(f).collect();
            summary_cell(Summary::of(&v).as_ref())
        };
        // TRUE is not trained: one evaluation per seed, and its seconds are
        // those of its evaluation.
        let (seeds, per_run) = if r.curves.is_empty() {
            (r.runs.len(), "-".to_string())
        } else {
            (r.curves.len(), format!("{:.0}", r.seconds / r.curves.len() as f64))
        };
        let _ = writeln!(md, " {} | {} | {seeds} | {per_run} |", sd(|s| s.0), sd(|s| s.1));
        for (name, f) in [("sd_accel", (|s: &(f64, f64)| s.0) as fn(&(f64, f64)) -> f64), ("sd_pinch", |s| s.1)] {
            let v: Vec<f64> = r.sds.iter().map(f).collect();
            if let Some(s) = Summary::of(&v) {
                csv_row(&mut csv, &r.method, name, &s);
            }
        }
    }
    let _ = writeln!(md, "\nTrue policy sds: accel {true_sd_a}, pinch {true_sd_p}.");
    write_atomic(&out.join("table.md"), md.as_bytes())?;
    write_atomic(&out.join("table.csv"), csv.as_bytes())?;

    let series: Vec<Series> = results
        .iter()
        .filter(|r| !r.curves.is_empty())
        .map(|r| Series { name: r.method.clone(), points: median_curve(&r.curves) })
        .collect();
    let true_mll = results[0].runs.iter().filter_map(|m| m.mll).reduce(f64::max);
    training_chart(
        &out.join("curves.svg"),
        &format!("Experiment {}: test MLL during training (median over seeds)", args.exp.to_uppercase()),
        "test MLL (nats/point)",
        series,
        true_mll.map(|y| ("TRUE", y)),
    )?;

    // The learned sds relative to the truth (1 is the truth).
    let mut sd_series = Vec::new();
    for r in results.iter().filter(|r| !r.sd_curves.is_empty()) {
        for (label, pick, truth) in [("accel", 0, true_sd_a), ("pinch", 1, true_sd_p)] {
            let curves: Vec<Curve> = r
                .sd_curves
                .iter()
                .map(|c| if pick == 0 { &c.0 } else { &c.1 })
                .map(|c| c.iter().map(|&(x, y)| (x, y / truth)).collect())
                .collect();
            sd_series.push(Series { name: format!("{} {label}", r.method), points: median_curve(&curves) });
        }
    }
    if !sd_series.is_empty() {
        training_chart(
            &out.join("sds.svg"),
            &format!("Experiment {}: learned policy sds / true sds (median over seeds)", args.exp.to_uppercase()),
            "learned sd / true sd",
            sd_series,
            Some(("truth", 1.0)),
        )?;
    }

    let doc = json!({
        "experiment": args.exp.to_uppercase(),
        "scale": scale,
        "seconds": seconds,
        "true_sds": [true_sd_a, true_sd_p],
        "methods": results.iter().map(|r| json!({
            "method": r.method,
            "runs": r.runs,
            "learned_sds": r.sds,
            "seconds": r.seconds,
        })).collect::<Vec<_>>(),
    });
    write_json(&out.join("reproduce.json"), &doc)?;
    println!("{md}");
    println!("wrote {} (table.csv, table.md, curves.svg, sds.svg, reproduce.json)", display(out));
    Ok(())
}

/// A chart of curves against the training step, with a horizontal reference
/// line `(name, y)` (TRUE's metric, the truth) across their steps.
fn training_chart(
    path: &Path,
    title: &str,
    y_label: &str,
    mut series: Vec<Series>,
    reference: Option<(&str, f64)>,
) -> Result<(), String> {
    if let Some((name, y)) = reference {
        let last = series.iter().flat_map(|s| s.points.last()).map(|p| p.0).fold(1.0, f64::max);
        series.push(Series { name: name.into(), points: vec![(0.0, y), (last, y)] });
    }
    line_chart(path, title, "training step", y_label, &series)
}

fn display(p: &Path) -> String {
    p.display().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn metrics(seed: u64) -> Metrics {
        Metrics {
            mll: Some(-1.0 - seed as f64),
            log_likelihood: -10.0,
            observed_units: 10,
            smoothed: Default::default(),
            filtered: Default::default(),
            aotll: Default::default(),
            aptll: Default::default(),
            collapsed_steps: 0,
            particles: 8,
            lag: 0,
            seed,
        }
    }

    /// A cache of three runs serves requests for one to three runs (their
    /// first runs) of the same filter, and nothing for four runs or another filter.
    #[test]
    fn cached_metrics_serve_a_prefix_of_the_same_filter() {
        let dir = std::env::temp_dir().join(format!("sefi-cache-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("true_metrics.json");
        let key = |filter: &str, runs: usize| json!({ "filter": filter, "runs": runs });
        let three: Vec<Metrics> = (0..3).map(metrics).collect();
        let computed = evaluate_cached(&path, &key("a", 3), || Ok(three.clone())).unwrap();
        assert_eq!(computed, three);
        for runs in 1..=3 {
            assert_eq!(cached_metrics(&path, &key("a", runs)), Some(three[..runs].to_vec()), "{runs} runs");
        }
        assert_eq!(cached_metrics(&path, &key("a", 4)), None);
        assert_eq!(cached_metrics(&path, &key("b", 1)), None);
        // A smaller request never replaces the larger cache.
        let one = evaluate_cached(&path, &key("a", 1), || Err("evaluated again".into())).unwrap();
        assert_eq!(one, three[..1].to_vec());
        assert_eq!(cached_metrics(&path, &key("a", 3)), Some(three));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
