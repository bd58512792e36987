//! `sefi score-check`: every estimator against the exact score on the
//! linear-Gaussian model (SPEC §2).
//!
//! Prints the exact log-likelihood and score (Kalman filter through the tape) for
//! the given parameters and observation file (one value per line). With
//! `--table`, runs every estimator `--runs` times at `N = --particles` on the
//! first `T + 1` observations for each `T` in `--steps` and writes the bias,
//! standard deviation and RMSE of each score component to `OUT/score_table.csv`
//! and `OUT/score_table.md` (and prints the Markdown).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::estimators::study::{score_study, ScoreStudyRow, COMPONENTS};
use ssm::estimators::{Estimator, EstimatorConfig, Precision};
use ssm::filter::Sampling;
use ssm::models::linear_gaussian::kalman::{Lgssm, LgssmTheta};

use crate::output::{ensure_dir, write_atomic};

/// Arguments of `sefi score-check`.
#[derive(clap::Args)]
pub struct ScoreCheckArgs {
    /// Observation file: one value per line (`#` starts a comment).
    #[arg(long)]
    pub observations: PathBuf,
    /// Parameters `phi,s_v,s_w` (the noise sds, not their logs).
    #[arg(long, default_value = "0.9,0.7,1.0")]
    pub params: String,
    /// Instead of reading the file, simulate this many observations from the
    /// parameters (stationary prior) and write them to it first.
    #[arg(long)]
    pub simulate: Option<usize>,
    /// Also measure every estimator's bias and spread.
    #[arg(long)]
    pub table: bool,
    /// Values of `T` for the table (each needs `T + 1` observations).
    #[arg(long, value_delimiter = ',', default_value = "25,50,100,200")]
    pub steps: Vec<usize>,
    /// Particles per run.
    #[arg(long, default_value_t = 512)]
    pub particles: usize,
    /// Runs per estimator and `T`.
    #[arg(long, default_value_t = 200)]
    pub runs: usize,
    /// Output directory of the table.
    #[arg(long, default_value = "out/score-check")]
    pub out: PathBuf,
    /// Seed of the first run (and of `--simulate`).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Parses `phi,s_v,s_w`.
fn parse_params(text: &str) -> Result<LgssmTheta, String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let values: Result<Vec<f64>, _> = parts.iter().map(|p| p.parse::<f64>()).collect();
    match values {
        Ok(v) if v.len() == 3 && v.iter().all(|x| x.is_finite()) && v[1] > 0.0 && v[2] > 0.0 => {
            Ok(LgssmTheta::new(v[0], v[1], v[2]))
        }
        _ => Err(format!("--params: expected `phi,s_v,s_w` with s_v, s_w > 0, got `{text}`")),
    }
}

/// Reads one finite value per line; blank lines and `#` comments are skipped.
pub fn read_observations(path: &Path) -> Result<Vec<f64>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut ys = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        match line.parse::<f64>() {
            Ok(y) if y.is_finite() => ys.push(y),
            _ => return Err(format!("{}:{}: `{line}` is not a finite number", path.display(), i + 1)),
        }
    }
    if ys.is_empty() {
        return Err(format!("{}: no observations", path.display()));
    }
    Ok(ys)
}

/// The estimators of the table: PF-SEFI at three lags, and every baseline.
fn estimators(transitions: usize) -> Vec<Estimator> {
    vec![
        Estimator::pf_sefi(0),
        Estimator::pf_sefi(10),
        Estimator::pf_sefi(transitions),
        Estimator::pf(),
        Estimator::dpf_sgr(),
        Estimator::dpf_sgr_stopped(),
        Estimator::pfnet(0.8),
    ]
}

/// The table as Markdown: one row per `T` and estimator, bias ± sd per component.
pub fn markdown(rows: &[ScoreStudyRow]) -> String {
    let mut s = String::from("| T | estimator |");
    for c in COMPONENTS {
        let _ = write!(s, " {c}: bias (sd) |");
    }
    s.push_str(" RMSE (all) |\n|---|---|");
    for _ in COMPONENTS {
        s.push_str("---|");
    }
    s.push_str("---|\n");
    for group in rows.chunks(COMPONENTS.len()) {
        let _ = write!(s, "| {} | {} |", group[0].transitions, group[0].estimator);
        for r in group {
            let _ = write!(s, " {:+.3} ({:.3}) |", r.bias, r.sd);
        }
        let rmse = group.iter().map(|r| r.rmse * r.rmse).sum::<f64>().sqrt();
        let _ = writeln!(s, " {rmse:.3} |");
    }
    s
}

/// Runs `sefi score-check`.
pub fn run(args: &ScoreCheckArgs) -> Result<(), String> {
    let theta = parse_params(&args.params)?;
    let model = Lgssm::stationary(theta).map_err(|e| e.to_string())?;
    if let Some(len) = args.simulate {
        if len == 0 {
            return Err("--simulate: need at least one observation".into());
        }
        let ys = model.simulate(len, &mut StdRng::seed_from_u64(args.seed)).ys;
        if let Some(dir) = args.observations.parent().filter(|d| !d.as_os_str().is_empty()) {
            ensure_dir(dir)?;
        }
        let text: String = ys.iter().map(|y| format!("{y}\n")).collect();
        write_atomic(&args.observations, text.as_bytes())?;
        println!("wrote {len} simulated observations to {}", args.observations.display());
    }
    let ys = read_observations(&args.observations)?;
    let (ll, score) = model.score(&ys);
    println!("observations: {} (T = {})", ys.len(), ys.len() - 1);
    println!("parameters: phi = {}, s_v = {}, s_w = {}", theta.phi, theta.sv(), theta.sw());
    println!("exact log-likelihood: {ll:.10}");
    for (name, g) in COMPONENTS.iter().zip(score) {
        println!("exact score d/d{name}: {g:.10}");
    }
    if !args.table {
        return Ok(());
    }
    if args.runs < 2 || args.particles == 0 {
        return Err("--table needs --runs >= 2 and --particles >= 1".into());
    }
    if let Some(&t) = args.steps.iter().find(|&&t| t + 1 > ys.len()) {
        return Err(format!(
            "--steps {t} needs {} observations; {} has {} (use --simulate {})",
            t + 1,
            args.observations.display(),
            ys.len(),
            t + 1
        ));
    }
    ensure_dir(&args.out)?;
    let config =
        EstimatorConfig { precision: Precision::F64, ..EstimatorConfig::new(Sampling::new(args.particles, None)) };
    let bar = ProgressBar::new(args.steps.len() as u64).with_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} T values ({elapsed}) {msg}").expect("valid template"),
    );
    let started = Instant::now();
    let mut rows = Vec::new();
    for &t in &args.steps {
        bar.set_message(format!("T = {t}"));
        rows.extend(score_study(&model, &ys[..=t], &estimators(t), &config, args.runs, args.seed));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let mut csv = String::from("T,estimator,component,exact,mean,bias,sd,se,z,rmse,runs\n");
    for r in &rows {
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{},{},{}",
            r.transitions,
            r.estimator,
            r.component,
            r.exact,
            r.mean,
            r.bias,
            r.sd,
            r.se,
            r.z(),
            r.rmse,
            r.runs
        );
    }
    write_atomic(&args.out.join("score_table.csv"), csv.as_bytes())?;
    let md = markdown(&rows);
    write_atomic(&args.out.join("score_table.md"), md.as_bytes())?;
    println!(
        "\n{} runs per cell, N = {}, f64 tapes, {:.1} s; bias = mean - exact, sd over runs:\n",
        args.runs,
        args.particles,
        started.elapsed().as_secs_f64()
    );
    println!("{md}");
    println!("wrote {} and score_table.md", args.out.join("score_table.csv").display());
    Ok(())
}
