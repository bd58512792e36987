//! `sefi power-study`: how often `diagnose` names a hidden effect (SPEC §7, the
//! criticism's power and false-cause rate). For every effect, strength and seed it
//! generates a dataset with that effect hidden ([`ssm::criticism::hidden`]), runs
//! the quick diagnosis under the study's protocol (`--protocol`), and tabulates
//! the share of seeds on which the cause is
//! named, the share of false causes (on the controls, any catalogue cause) and
//! the error of the learned magnitude. Every finished diagnosis keeps its
//! `report.json` and each fit's evaluation log (the rest of its training runs
//! is removed), so an interrupted study resumes
//! where it stopped and a study's state is small enough to commit. Several
//! processes can share a study's directory (each claims the cell it diagnoses);
//! each writes the tables of every finished cell there.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use ssm::criticism::diagnose::{diagnose, DiagnoseConfig, Protocol, Report, NO_CAUSE, TRAINING_RUN_DIRS, UNEXPLAINED};
use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
use ssm::data::ObservationKind;
use ssm::stats::wilson_interval;
use ssm::training::EVAL_LOG;

use crate::cluster::Cluster;
use crate::commands::diagnose::ProtocolArg;
use crate::output::{claim_dir, ensure_dir, write_atomic, write_json, Claim};
use crate::plot::{share_chart, Share, ShareSeries};

/// Arguments of `sefi power-study`.
#[derive(Args, Debug)]
pub struct PowerArgs {
    /// Output directory (one diagnosis per effect, strength and seed; power.csv, power.md).
    #[arg(long, default_value = "out/power")]
    out: PathBuf,
    /// Hidden effects: catalogue effects, `student_t_accel` (to be named `heavy_tailed_accel`), `ego_pose_noise` (outside
    /// the catalogue: to be called `unexplained`), and the controls `none-points`, `none-boxes`.
    #[arg(long, value_delimiter = ',', default_value = STUDY_EFFECTS)]
    effects: Vec<String>,
    /// Strengths, as multiples of each effect's default size (controls run once per seed).
    #[arg(long, value_delimiter = ',', default_value = "0.5,1,2")]
    strengths: Vec<f64>,
    /// Seeds per effect and strength (data and diagnosis).
    #[arg(long, default_value_t = 5)]
    seeds: u64,
    /// Scenes of every effect's data (each has 6 objects), in place of the study's
    /// per-effect setting (8 for points, 16 for heavy tails, 32 for boxes): the power
    /// at another data size. Use a fresh `--out` for it.
    #[arg(long)]
    scenes: Option<usize>,
    #[command(flatten)]
    protocol: ProtocolArg,
    /// Rebuild power.csv and power.md from the finished diagnoses only (run none). The
    /// tables always cover every finished diagnosis under --out, of any effect and
    /// strength, whichever process ran it.
    #[arg(long)]
    table_only: bool,
}

impl PowerArgs {
    /// The study's protocol: every cell's diagnosis runs under it.
    fn protocol(&self) -> Result<&'static Protocol, String> {
        self.protocol.protocol()
    }
}

/// Every effect id of the study, in the order of its tables (and the default of
/// `--effects`).
const STUDY_EFFECTS: &str =
    "latency,clutter,size_bias,heavy_tailed_accel,student_t_accel,heading_flip,persistent_flip,ego_pose_noise,none-points,none-boxes";

/// The study's setting of one effect id: the hidden effect, the data's kind and
/// scene count (boxes carry less information per step, and heavy tails act on a
/// latent quantity: both need more scenes), and the cause that should be named.
pub struct StudyEffect {
    /// The id given on the command line.
    pub id: String,
    /// The effect hidden in the data at strength 1.
    pub effect_id: &'static str,
    /// Points or boxes.
    pub kind: ObservationKind,
    /// Scenes of the data (6 objects of 16 steps each).
    pub scenes: usize,
    /// The cause a correct diagnosis names (`none` for the controls).
    pub expected: &'static str,
}

impl StudyEffect {
    /// The setting of `id`.
    pub fn of(id: &str) -> Result<StudyEffect, String> {
        let (effect_id, kind, scenes, expected) = match id {
            "none-points" => ("none", ObservationKind::Points, 8, NO_CAUSE),
            "none-boxes" => ("none", ObservationKind::Boxes, 32, NO_CAUSE),
            "latency" => ("latency", ObservationKind::Points, 8, "latency"),
            "clutter" => ("clutter", ObservationKind::Points, 8, "clutter"),
            "size_bias" => ("size_bias", ObservationKind::Points, 8, "size_bias"),
            "heavy_tailed_accel" => ("heavy_tailed_accel", ObservationKind::Points, 16, "heavy_tailed_accel"),
            "student_t_accel" => ("student_t_accel", ObservationKind::Points, 16, "heavy_tailed_accel"),
            "heading_flip" => ("heading_flip", ObservationKind::Boxes, 32, "heading_flip"),
            "persistent_flip" => ("persistent_flip", ObservationKind::Boxes, 32, "persistent_flip"),
            // Outside the catalogue: the right answer is that the model is wrong in
            // a way the catalogue does not cover.
            "ego_pose_noise" => ("ego_pose_noise", ObservationKind::Points, 8, UNEXPLAINED),
            _ => return Err(format!("power-study: unknown effect `{id}`")),
        };
        Ok(StudyEffect { id: id.to_string(), effect_id, kind, scenes, expected })
    }

    fn is_control(&self) -> bool {
        self.expected == NO_CAUSE
    }
}

/// The true magnitudes the learned ones are compared with, `(parameter, value)`,
/// the effect's size first: one for most effects; the flip chain's fraction and
/// its persistence.
fn true_magnitudes(effect: &HiddenEffect) -> Vec<(&'static str, f64)> {
    match *effect {
        HiddenEffect::Latency { delay } => vec![("delay", delay)],
        HiddenEffect::Clutter { fraction, .. } => vec![("fraction", fraction)],
        HiddenEffect::SizeBias { length_factor, .. } => vec![("length_factor", length_factor)],
        HiddenEffect::HeavyTailedAccel { ratio, .. } => vec![("sd_ratio", ratio)],
        HiddenEffect::HeadingFlip { fraction } => vec![("fraction", fraction)],
        HiddenEffect::PersistentFlip { fraction, persistence } => {
            vec![("fraction", fraction), ("persistence", persistence)]
        }
        HiddenEffect::None | HiddenEffect::StudentTAccel { .. } | HiddenEffect::EgoPoseNoise { .. } => Vec::new(),
    }
}

/// The quick diagnosis of one cell of a study under `protocol`, seeded with `seed`.
fn cell_config(protocol: &Protocol, seed: u64) -> DiagnoseConfig {
    let mut config = DiagnoseConfig::quick();
    protocol.apply(&mut config);
    config.seed = seed;
    config
}

/// One diagnosis of the study.
struct Cell {
    effect: String,
    strength: f64,
    seed: u64,
    cause: String,
    named: bool,
    /// Per parameter of [`true_magnitudes`], learned over true minus 1 (NaN
    /// where the cause was not named or the parameter not learned; empty when
    /// the effect has no magnitude to compare).
    relative_errors: Vec<(&'static str, f64)>,
    gain: f64,
    seconds: f64,
    /// The cause the diagnosis would name without rule (d), that an extension
    /// must lower its flagging checks' |z| (the same decision otherwise).
    cause_without_check_rule: String,
    /// Why the expected outcome was not reached ([`Report::why_not`]); `None`
    /// where it was.
    why_missed: Option<String>,
}

/// Runs `sefi power-study`.
pub fn run(args: &PowerArgs) -> Result<(), String> {
    if args.scenes == Some(0) {
        return Err("power-study: --scenes must be at least 1".into());
    }
    let effects = study_effects(args.effects.iter().map(String::as_str), args.scenes)?;
    if args.seeds == 0 || args.strengths.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err("power-study: seeds must be positive and strengths positive and finite".into());
    }
    let protocol = args.protocol()?;
    ensure_dir(&args.out)?;
    let strengths = middle_out(&args.strengths);
    if !args.table_only {
        let plan = plan(&effects, &strengths, args.seeds);
        let bar = ProgressBar::new(plan.len() as u64).with_style(
            ProgressStyle::with_template("{prefix:>12} {bar:30} {pos}/{len} diagnoses ({elapsed}, eta {eta}) {msg}")
                .expect("valid template"),
        );
        bar.set_prefix("power-study");
        for (e, strength, seed) in plan {
            bar.set_message(format!("{} x{strength} seed {seed}", e.id));
            // A finished cell is read (and checked) once, by the tables.
            if cell_dir(&args.out, e, strength, seed).join("report.json").is_file() {
                bar.inc(1);
                continue;
            }
            if run_cell(&args.out, e, strength, seed, protocol, false)?.is_none() {
                continue;
            }
            // The tables so far after every diagnosis: an interrupted study
            // shows what it has.
            write_study_tables(&args.out, &effects, &strengths, args.seeds, args.scenes, protocol)?;
            bar.inc(1);
        }
        bar.finish_and_clear();
    }
    print!("{}", write_study_tables(&args.out, &effects, &strengths, args.seeds, args.scenes, protocol)?);
    println!("wrote {} (power.csv, power.md)", args.out.display());
    Ok(())
}

/// `strengths` from the middle out: the default strength (1) first, then the
/// others by distance from it (on the log scale), without repeats.
fn middle_out(strengths: &[f64]) -> Vec<f64> {
    let mut sorted = strengths.to_vec();
    sorted.sort_by(|a, b| (a.ln().abs()).total_cmp(&b.ln().abs()).then(a.total_cmp(b)));
    sorted.dedup();
    sorted
}

/// The study's cells in the order they run, strength-major over `strengths`
/// as given (from the middle out, [`middle_out`], so that an interrupted study
/// already answers the headline question: the share named at the middle
/// strength and the false causes on controls), the controls once (at strength
/// 1) with the first.
fn plan<'a>(effects: &'a [StudyEffect], strengths: &[f64], seeds: u64) -> Vec<(&'a StudyEffect, f64, u64)> {
    let mut plan = Vec::new();
    for (i, &s) in strengths.iter().enumerate() {
        for e in effects {
            if e.is_control() && i > 0 {
                continue;
            }
            let strength = if e.is_control() { 1.0 } else { s };
            plan.extend((0..seeds).map(|seed| (e, strength, seed)));
        }
    }
    plan
}

/// The settings of effect `ids`, each with `scenes` scenes when given (else
/// the study's own per-effect setting).
fn study_effects<'a>(
    ids: impl IntoIterator<Item = &'a str>,
    scenes: Option<usize>,
) -> Result<Vec<StudyEffect>, String> {
    ids.into_iter()
        .map(|id| {
            let mut e = StudyEffect::of(id)?;
            e.scenes = scenes.unwrap_or(e.scenes);
            Ok(e)
        })
        .collect()
}

/// Writes the tables of the whole study under `out` and returns `power.md`'s
/// text: the cells of `effects` x `strengths` x `seeds` and every other
/// finished cell found there. Several processes can share a study, each
/// running some of its effects or strengths; each writes the tables of all of
/// it, not only of what it ran.
fn write_study_tables(
    out: &Path,
    effects: &[StudyEffect],
    strengths: &[f64],
    seeds: u64,
    scenes: Option<usize>,
    protocol: &'static Protocol,
) -> Result<String, String> {
    let mut ids: Vec<String> = effects.iter().map(|e| e.id.clone()).collect();
    let (mut strengths, mut seeds) = (strengths.to_vec(), seeds);
    for (id, strength, seed) in finished_cells(out)? {
        if !ids.contains(&id) {
            ids.push(id);
        }
        if !strengths.contains(&strength) {
            strengths.push(strength);
        }
        seeds = seeds.max(seed + 1);
    }
    // The study's own order of effects and strengths, whatever the order found.
    ids.sort_by_key(|id| STUDY_EFFECTS.split(',').position(|known| known == id));
    let strengths = middle_out(&strengths);
    let effects = study_effects(ids.iter().map(String::as_str), scenes)?;
    let mut cells = Vec::new();
    for (e, strength, seed) in plan(&effects, &strengths, seeds) {
        cells.extend(run_cell(out, e, strength, seed, protocol, true)?);
    }
    write_tables(out, &effects, &strengths, &cells)
}

/// `(effect id, strength, seed)` of every finished cell under `out`
/// (`<effect>/x<strength>/seed<seed>/report.json`, a known effect id).
fn finished_cells(out: &Path) -> Result<Vec<(String, f64, u64)>, String> {
    let entries = |dir: &Path| -> Result<Vec<(String, PathBuf)>, String> {
        let read = std::fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        Ok(read
            .flatten()
            .filter(|e| e.path().is_dir())
            .map(|e| (e.file_name().to_string_lossy().into_owned(), e.path()))
            .collect())
    };
    let mut found = Vec::new();
    for (id, effect_dir) in entries(out)? {
        if StudyEffect::of(&id).is_err() {
            continue;
        }
        for (name, strength_dir) in entries(&effect_dir)? {
            let Some(strength) = name.strip_prefix('x').and_then(|s| s.parse::<f64>().ok()) else { continue };
            for (name, seed_dir) in entries(&strength_dir)? {
                let Some(seed) = name.strip_prefix("seed").and_then(|s| s.parse::<u64>().ok()) else { continue };
                if seed_dir.join("report.json").is_file() {
                    found.push((id.clone(), strength, seed));
                }
            }
        }
    }
    Ok(found)
}

/// Writes `power.csv` (one row per finished diagnosis), `power.md` and
/// `power.svg` into `out`, and returns `power.md`'s text.
fn write_tables(out: &Path, effects: &[StudyEffect], strengths: &[f64], cells: &[Cell]) -> Result<String, String> {
    let mut csv = csv::Writer::from_writer(Vec::new());
    let header = [
        "effect",
        "strength",
        "seed",
        "cause",
        "named",
        "relative_error",
        "gain",
        "seconds",
        "cause_without_check_rule",
        "other_relative_errors",
        "why_missed",
    ];
    let mut write = |record: &[String]| csv.write_record(record).map_err(|e| format!("power.csv: {e}"));
    write(&header.map(str::to_string))?;
    for c in cells {
        // The effect's size in `relative_error` (as before); any further
        // parameter as `name:error` pairs joined by `;`.
        let size = c.relative_errors.first().map_or(f64::NAN, |e| e.1);
        let others: Vec<String> = c.relative_errors.iter().skip(1).map(|(n, e)| format!("{n}:{e}")).collect();
        write(&[
            c.effect.clone(),
            c.strength.to_string(),
            c.seed.to_string(),
            c.cause.clone(),
            c.named.to_string(),
            size.to_string(),
            c.gain.to_string(),
            format!("{:.1}", c.seconds),
            c.cause_without_check_rule.clone(),
            others.join(";"),
            c.why_missed.clone().unwrap_or_default(),
        ])?;
    }
    let csv = csv.into_inner().map_err(|e| format!("power.csv: {e}"))?;
    write_atomic(&out.join("power.csv"), &csv)?;
    let table = summarise(effects, strengths, cells);
    write_atomic(&out.join("power.md"), table.as_bytes())?;
    write_power_chart(out, effects, strengths, cells)?;
    Ok(table)
}

/// The directory of one cell of the study under `out`.
fn cell_dir(out: &Path, e: &StudyEffect, strength: f64, seed: u64) -> PathBuf {
    out.join(&e.id).join(format!("x{strength}")).join(format!("seed{seed}"))
}

/// Removes a finished cell's training runs except each fit's evaluation log
/// ([`EVAL_LOG`]: its check-part likelihood every few steps, a few hundred
/// bytes, which shows how the fit climbed and where it was kept). The
/// checkpoints, parameters and step logs only served to resume an interrupted
/// diagnosis; the report and these logs are what the study keeps. A file that
/// cannot be removed is left: the cell's report is already written.
fn prune_training_runs(cell: &Path) {
    fn prune(dir: &Path) {
        let Ok(entries) = std::fs::read_dir(dir) else { return };
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() {
                prune(&path);
                // Empty once nothing in it was an evaluation log.
                let _ = std::fs::remove_dir(&path);
            } else if path.file_name().is_none_or(|name| name != EVAL_LOG) {
                let _ = std::fs::remove_file(&path);
            }
        }
    }
    for run in TRAINING_RUN_DIRS {
        let dir = cell.join(run);
        prune(&dir);
        let _ = std::fs::remove_dir(&dir);
    }
}

/// The diagnosis of one effect, strength and seed: read back if already done,
/// else run (or, with `table_only`, `None`).
fn run_cell(
    out: &Path,
    e: &StudyEffect,
    strength: f64,
    seed: u64,
    protocol: &'static Protocol,
    table_only: bool,
) -> Result<Option<Cell>, String> {
    let effect = HiddenEffect::at_strength(e.effect_id, strength).map_err(|err| err.to_string())?;
    let config = HiddenConfig { scenes: e.scenes, ..HiddenConfig::quick(e.kind, effect, seed) };
    let dir = cell_dir(out, e, strength, seed);
    let report_path = dir.join("report.json");
    let report: Report = match std::fs::read_to_string(&report_path) {
        Ok(text) => serde_json::from_str(&text).map_err(|err| format!("{}: {err}", report_path.display()))?,
        Err(_) if table_only => return Ok(None),
        Err(_) => {
            // A cell another `power-study` on the same `--out` is diagnosing is
            // left to it: several processes share a study's cells.
            let _claim = match claim_dir(&dir)? {
                Claim::Held(claim) => claim,
                Claim::Busy(holder) => {
                    eprintln!("{} x{strength} seed {seed}: skipped, {holder} is diagnosing it", e.id);
                    return Ok(None);
                }
            };
            if report_path.is_file() {
                // Finished by another process between the read and the claim.
                return run_cell(out, e, strength, seed, protocol, table_only);
            }
            let data = generate_hidden(&config).map_err(|err| err.to_string())?;
            let diagnose_config = cell_config(protocol, seed);
            let report = diagnose(&data, &diagnose_config, &dir, &Cluster::single().collective(), &mut |_| {})?;
            let value = serde_json::to_value(&report).map_err(|err| err.to_string())?;
            write_json(&report_path, &value)?;
            prune_training_runs(&dir);
            report
        }
    };
    // A study's directory holds one data size: a report of another (an `--out`
    // reused with another `--scenes`) is refused rather than mixed in.
    let objects = report.train_objects + report.check_objects + report.eval_objects;
    if objects != config.scenes * config.objects_per_scene {
        return Err(format!(
            "{}: a diagnosis of {objects} objects, where this study's {} data have {} scenes of {} (another --scenes? use another --out)",
            report_path.display(),
            e.id,
            config.scenes,
            config.objects_per_scene
        ));
    }
    // Nor is a report of another protocol (an `--out` reused with another `--protocol`).
    let found = Protocol::of(&report.config);
    if found.map(|p| p.name) != Some(protocol.name) {
        let found =
            found.map_or("rules no protocol has".to_string(), |p| format!("protocol {} ({})", p.name, p.summary));
        return Err(format!(
            "{}: a diagnosis under {found}, where this study's is protocol {} ({}) (another --protocol? use another \
             --out)",
            report_path.display(),
            protocol.name,
            protocol.summary,
        ));
    }
    // Decided again under the current rules: cells diagnosed under an earlier
    // rule (d) count as the protocol would decide them now.
    let decision = report.decided_for(e.expected);
    let (cause, chosen) = (decision.cause, decision.chosen);
    let named = cause == e.expected;
    let relative_errors = true_magnitudes(&effect)
        .into_iter()
        .map(|(name, truth)| {
            let learned = chosen.filter(|_| named).and_then(|c| c.params.iter().find(|p| p.0 == name));
            (name, learned.map_or(f64::NAN, |p| p.1 / truth - 1.0))
        })
        .collect();
    Ok(Some(Cell {
        cause_without_check_rule: decision.cause_without_check_rule,
        why_missed: decision.why_missed,
        effect: e.id.clone(),
        strength,
        seed,
        cause,
        named,
        relative_errors,
        gain: chosen.map_or(0.0, |c| c.gain),
        seconds: report.seconds,
    }))
}

/// The median |relative error| of each learned magnitude over `group`'s cells
/// that learned it (`-` where none did): `12%` for an effect of one magnitude,
/// `fraction 12%, persistence 3%` for more.
fn median_errors(group: &[&Cell]) -> String {
    let names: Vec<&str> = group.first().map_or(Vec::new(), |c| c.relative_errors.iter().map(|e| e.0).collect());
    let medians: Vec<(&str, String)> = names
        .iter()
        .enumerate()
        .map(|(i, &name)| {
            let mut errors: Vec<f64> = group
                .iter()
                .filter_map(|c| c.relative_errors.get(i))
                .map(|e| e.1.abs())
                .filter(|x| x.is_finite())
                .collect();
            errors.sort_by(f64::total_cmp);
            (name, errors.get(errors.len() / 2).map_or("-".to_string(), |m| format!("{:.0}%", 100.0 * m)))
        })
        .collect();
    match medians.as_slice() {
        [] => "-".to_string(),
        [(_, one)] => one.clone(),
        many => many.iter().map(|(n, m)| format!("{n} {m}")).collect::<Vec<_>>().join(", "),
    }
}

/// The cells of effect `e` at each strength of `strengths` (a control's at 1
/// only), weakest first, leaving out strengths without a finished cell.
fn strength_groups<'a>(e: &StudyEffect, strengths: &[f64], cells: &'a [Cell]) -> Vec<(f64, Vec<&'a Cell>)> {
    let mut list = if e.is_control() { vec![1.0] } else { strengths.to_vec() };
    list.sort_by(f64::total_cmp);
    list.into_iter()
        .map(|st| (st, cells.iter().filter(|c| c.effect == e.id && c.strength == st).collect::<Vec<_>>()))
        .filter(|(_, group)| !group.is_empty())
        .collect()
}

/// The share of `group`'s seeds (the cells at strength `x`) that reached the
/// expected outcome, with its 95% Wilson interval.
fn named_share(x: f64, group: &[&Cell]) -> Share {
    let named = group.iter().filter(|c| c.named).count();
    let (low, high) = wilson_interval(named, group.len(), 0.95);
    Share { x, share: named as f64 / group.len() as f64, low, high }
}

/// Draws `power.svg` into `out`: for every hidden effect (not the controls),
/// the share of seeds named at each strength with its 95% interval, against
/// the goal of 90%. Nothing is drawn before a cell of an effect has finished.
fn write_power_chart(out: &Path, effects: &[StudyEffect], strengths: &[f64], cells: &[Cell]) -> Result<(), String> {
    let series: Vec<ShareSeries> = effects
        .iter()
        .filter(|e| !e.is_control())
        .map(|e| {
            let shares =
                strength_groups(e, strengths, cells).into_iter().map(|(x, group)| named_share(x, &group)).collect();
            ShareSeries { name: format!("{} ({} scenes)", e.id, e.scenes), shares }
        })
        .filter(|s| !s.shares.is_empty())
        .collect();
    if series.is_empty() {
        return Ok(());
    }
    share_chart(
        &out.join("power.svg"),
        "Share of seeds on which the diagnosis names the hidden effect",
        "strength (x the generator's default)",
        "named (95% interval)",
        &series,
        Some(0.9),
    )
}

/// The study's table: per effect and strength, the share named, false causes,
/// `unexplained`, and the median |relative error| of the learned magnitude.
fn summarise(effects: &[StudyEffect], strengths: &[f64], cells: &[Cell]) -> String {
    let mut s = String::from(
        "| effect | scenes | strength | seeds | named | named: 95% interval | false cause | unexplained | median abs. error of the magnitude | mean time (s) | without rule (d): named | without rule (d): false cause |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for e in effects {
        for (st, group) in strength_groups(e, strengths, cells) {
            let n = group.len() as f64;
            let Share { share: named, low, high, .. } = named_share(st, &group);
            let catalogue = |c: &&Cell| c.cause != NO_CAUSE && c.cause != UNEXPLAINED;
            let false_cause = group.iter().filter(|c| catalogue(c) && !c.named).count() as f64 / n;
            let unexplained = group.iter().filter(|c| c.cause == UNEXPLAINED).count() as f64 / n;
            let error = median_errors(&group);
            let time = group.iter().map(|c| c.seconds).sum::<f64>() / n;
            let loose = |c: &&&Cell| c.cause_without_check_rule == e.expected;
            let named_loose = group.iter().filter(loose).count() as f64 / n;
            let false_loose = group
                .iter()
                .filter(|c| {
                    let cause = &c.cause_without_check_rule;
                    cause != NO_CAUSE && cause != UNEXPLAINED && cause != e.expected
                })
                .count() as f64
                / n;
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.0}% | {:.0}–{:.0}% | {:.0}% | {:.0}% | {error} | {time:.0} | {:.0}% | {:.0}% |",
                e.id,
                e.scenes,
                if e.is_control() { "-".to_string() } else { format!("{st}") },
                group.len(),
                100.0 * named,
                100.0 * low,
                100.0 * high,
                100.0 * false_cause,
                100.0 * unexplained,
                100.0 * named_loose,
                100.0 * false_loose
            );
        }
    }
    s.push_str(
        "\n`named`: the expected outcome — the hidden effect's catalogue cause (`heavy_tailed_accel` for Student-t \
         tails), `unexplained` for `ego_pose_noise` (outside the catalogue), `none` for the controls; its 95% \
         interval is Wilson's over the seeds (5 of 5 is 57–100%). `false cause`: a catalogue cause other than the \
         expected one. `power.svg` draws the share named against the strength.\n",
    );
    let missed: Vec<(&Cell, &str)> = cells.iter().filter_map(|c| Some((c, c.why_missed.as_deref()?))).collect();
    if !missed.is_empty() {
        s.push_str("\nSeeds that missed, and why (the outcome; then the first rule the expected cause fails, with its numbers):\n\n");
        for (c, why) in missed {
            let control = effects.iter().any(|e| e.id == c.effect && e.is_control());
            let strength = if control { String::new() } else { format!(" × {}", c.strength) };
            let _ = writeln!(s, "- {}{strength}, seed {}: {why}", c.effect, c.seed);
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use ssm::criticism::diagnose::PROTOCOLS;
    use ssm::criticism::hidden::HIDDEN_FLIP_PERSISTENCE;

    /// Copies the reports of `cells` (`effect/xS/seedN`) of the committed study
    /// `results/<study>` into the same cells under `out`.
    fn copy_committed_cells(out: &Path, study: &str, cells: &[&str]) {
        let committed = Path::new(env!("CARGO_MANIFEST_DIR")).join("../results").join(study);
        for cell in cells {
            std::fs::create_dir_all(out.join(cell)).unwrap();
            std::fs::copy(committed.join(cell).join("report.json"), out.join(cell).join("report.json")).unwrap();
        }
    }

    /// The protocol called `name`.
    fn named(name: &str) -> &'static Protocol {
        Protocol::named(name).unwrap()
    }

    /// A finished cell is read back and decided again under the study's
    /// protocol; a report of another data size or protocol in the same study
    /// directory (an `--out` reused with another `--scenes` or `--protocol`) is
    /// refused with its path and both protocols, not mixed into the table; and
    /// each cell is diagnosed at the quick scale under the study's protocol.
    #[test]
    fn a_report_of_another_data_size_or_protocol_is_refused() {
        let out = std::env::temp_dir().join(format!("sefi-power-scenes-{}", std::process::id()));
        // A report of the committed study (protocol v3): 16 scenes of 6 objects.
        copy_committed_cells(&out, "power-study", &["heavy_tailed_accel/x1/seed0"]);
        let mut effect = StudyEffect::of("heavy_tailed_accel").unwrap();
        let v3 = named("v3");
        let read = run_cell(&out, &effect, 1.0, 0, v3, true).unwrap().expect("the finished cell is read back");
        assert_eq!((read.effect.as_str(), read.seed), ("heavy_tailed_accel", 0));
        for other in PROTOCOLS.iter().filter(|p| p.name != v3.name) {
            let err = run_cell(&out, &effect, 1.0, 0, other, true).err().expect(other.name);
            assert!(err.contains("report.json") && err.contains("a diagnosis under protocol v3 ("), "{err}");
            assert!(err.contains(&format!("this study's is protocol {} ({})", other.name, other.summary)), "{err}");
        }
        let quick = DiagnoseConfig::quick();
        for p in PROTOCOLS {
            let cell = cell_config(p, 4);
            assert_eq!(Protocol::of(&cell).map(|q| q.name), Some(p.name));
            assert_eq!((cell.seed, cell.base_steps, cell.particles), (4, quick.base_steps, quick.particles));
        }
        effect.scenes = 32;
        let err = run_cell(&out, &effect, 1.0, 0, v3, true).err().expect("a 16-scene report in a 32-scene study");
        assert!(err.contains("report.json") && err.contains("96 objects") && err.contains("32 scenes"), "{err}");
        std::fs::remove_dir_all(&out).unwrap();
    }

    /// A finished cell keeps each fit's evaluation log and nothing else of its
    /// training runs; the report and files outside the runs stay.
    #[test]
    fn a_finished_cell_keeps_only_its_fits_evaluation_logs() {
        let cell = std::env::temp_dir().join(format!("sefi-power-prune-{}", std::process::id()));
        let runs = ["base", "reference", "candidates/latency", "candidates/clutter", "reference-dynamics"];
        for run in runs {
            std::fs::create_dir_all(cell.join(run)).unwrap();
            for file in ["checkpoint.bin", "params.bin", "train.csv", "skipped.csv", EVAL_LOG] {
                std::fs::write(cell.join(run).join(file), run).unwrap();
            }
        }
        // A run stopped before its first evaluation has no log: its directory goes.
        std::fs::create_dir_all(cell.join("reference-reseeded")).unwrap();
        std::fs::write(cell.join("reference-reseeded/checkpoint.bin"), "x").unwrap();
        std::fs::write(cell.join("report.json"), "{}").unwrap();
        prune_training_runs(&cell);
        for run in runs {
            let left: Vec<String> = std::fs::read_dir(cell.join(run))
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            assert_eq!(left, [EVAL_LOG], "{run}");
            assert_eq!(std::fs::read_to_string(cell.join(run).join(EVAL_LOG)).unwrap(), run);
        }
        assert!(!cell.join("reference-reseeded").exists());
        assert!(cell.join("report.json").is_file());
        std::fs::remove_dir_all(&cell).unwrap();
    }

    /// A fitted-screen study's reports record the futility stop they ran with:
    /// those of the study without it (every screened fit run to its end,
    /// protocol v7-fitted-screen-full) are read back by a study under that
    /// protocol and refused by one with the stop (v7-fitted-screen).
    #[test]
    fn a_fitted_screen_report_without_the_futility_stop_is_refused_by_a_study_with_it() {
        let out = std::env::temp_dir().join(format!("sefi-power-futility-{}", std::process::id()));
        copy_committed_cells(&out, "power-study-fitted-screen", &["none-points/x1/seed0"]);
        let effect = StudyEffect::of("none-points").unwrap();
        let whole = named("v7-fitted-screen-full");
        assert!(run_cell(&out, &effect, 1.0, 0, whole, true).unwrap().is_some());
        let stopped = named("v7-fitted-screen");
        let err = run_cell(&out, &effect, 1.0, 0, stopped, true).err().expect("a report without the stop");
        assert!(
            err.contains("under protocol v7-fitted-screen-full (") && err.contains("is protocol v7-fitted-screen (")
        );
        assert_eq!((cell_config(stopped, 2).screen_futility, cell_config(whole, 2).screen_futility), (1.0 / 3.0, 0.0));
        std::fs::remove_dir_all(&out).unwrap();
    }

    /// A process that ran one effect at one strength writes the tables of every
    /// finished cell of the study, whichever process diagnosed it, in the
    /// study's order.
    #[test]
    fn the_tables_cover_every_finished_cell_of_the_study() {
        let out = std::env::temp_dir().join(format!("sefi-power-tables-{}", std::process::id()));
        let cells = ["latency/x1/seed0", "latency/x2/seed1", "heavy_tailed_accel/x1/seed0", "none-points/x1/seed0"];
        copy_committed_cells(&out, "power-study", &cells);
        // Neither an unknown effect's directory nor a cell without its report counts.
        std::fs::create_dir_all(out.join("not_an_effect/x1/seed0")).unwrap();
        std::fs::create_dir_all(out.join("clutter/x1/seed0")).unwrap();
        // Every id of the study's order is a known effect.
        assert!(STUDY_EFFECTS.split(',').all(|id| StudyEffect::of(id).is_ok()));
        let latency = vec![StudyEffect::of("latency").unwrap()];
        let table = write_study_tables(&out, &latency, &[1.0], 1, None, named("v3")).unwrap();
        let rows: Vec<&str> = table.lines().filter(|l| l.starts_with("| ") && !l.starts_with("| effect")).collect();
        let lead: Vec<String> = rows.iter().map(|r| r.split(" | ").take(3).collect::<Vec<_>>().join(" | ")).collect();
        assert_eq!(
            lead,
            ["| latency | 8 | 1", "| latency | 8 | 2", "| heavy_tailed_accel | 16 | 1", "| none-points | 8 | -"]
        );
        let csv = std::fs::read_to_string(out.join("power.csv")).unwrap();
        let cells: Vec<&str> = csv.lines().skip(1).map(|l| l.splitn(4, ',').take(3).last().unwrap()).collect();
        assert_eq!(csv.lines().count(), 5, "{csv}");
        assert_eq!(cells, ["0", "0", "0", "1"], "the middle strength and the controls first, then x2");
        assert_eq!(std::fs::read_to_string(out.join("power.md")).unwrap(), table);
        // Each row's 95% interval of the share named: latency x1 seed 0 named
        // (1 of 1: 21–100%).
        assert!(table.contains("| latency | 8 | 1 | 1 | 100% | 21–100% |"), "{table}");
        // The chart draws the hidden effects, not the controls.
        let svg = std::fs::read_to_string(out.join("power.svg")).unwrap();
        assert!(svg.contains("latency (8 scenes)") && svg.contains("heavy_tailed_accel (16 scenes)"));
        assert!(!svg.contains("none-points") && svg.contains("goal (90%)"));
        std::fs::remove_dir_all(&out).unwrap();
    }

    /// Every cell that missed says why, in `power.csv` and under the table:
    /// the outcome, then the first rule its expected cause fails with the
    /// numbers that failed it, or that it was not fitted; a control, the checks
    /// that fail. Cells that named what they should say nothing.
    #[test]
    fn each_missed_cell_says_why() {
        let out = std::env::temp_dir().join(format!("sefi-power-why-{}", std::process::id()));
        let cells = [
            "heavy_tailed_accel/x1/seed0",
            "heavy_tailed_accel/x1/seed2",
            "heavy_tailed_accel/x1/seed3",
            "latency/x1/seed0",
            "none-points/x1/seed3",
        ];
        copy_committed_cells(&out, "power-study-eval-crn", &cells);
        let effects = study_effects(["heavy_tailed_accel", "latency", "none-points"], None).unwrap();
        let table = write_study_tables(&out, &effects, &[1.0], 5, None, named("v4")).unwrap();
        let mut reader = csv::Reader::from_path(out.join("power.csv")).unwrap();
        let rows: Vec<csv::StringRecord> = reader.records().map(Result::unwrap).collect();
        let why = |effect: &str, seed: &str| {
            let row = rows.iter().find(|r| &r[0] == effect && &r[2] == seed).unwrap();
            row[10].to_string()
        };
        // The same reports, read directly: what each holds.
        let report = |cell: &str| -> Report {
            serde_json::from_str(&std::fs::read_to_string(out.join(cell).join("report.json")).unwrap()).unwrap()
        };
        let seed3 = report(cells[2]);
        let tails = seed3.candidates.iter().find(|c| c.cause == "heavy_tailed_accel").unwrap();
        let reference_z = seed3.reference_checks().iter().find(|c| c.name == "accel_kurtosis").unwrap().z;
        let after = tails.checks_after.iter().find(|c| c.name == "accel_kurtosis").unwrap();
        assert!(
            after.z > reference_z && reference_z > 0.0 && !after.significant,
            "the committed report fails rule (d), further the same way: {reference_z} -> {}",
            after.z
        );
        let expected = format!(
            "`unexplained`: `heavy_tailed_accel` fails (d) no flagging check improved: accel_kurtosis z {reference_z:.2} → {:.2}",
            after.z
        );
        assert_eq!(why("heavy_tailed_accel", "3"), expected);
        // Without rule (d), from the same judging: what deciding again without it gives.
        let decision = seed3.decided_for("heavy_tailed_accel");
        assert_eq!(decision.cause_without_check_rule, "heavy_tailed_accel");
        assert_eq!(decision.cause_without_check_rule, seed3.decided(false).0);
        assert_eq!((decision.cause.as_str(), decision.why_missed.as_deref()), ("unexplained", Some(expected.as_str())));
        assert!(report(cells[1]).candidates.iter().all(|c| c.cause != "heavy_tailed_accel"));
        assert_eq!(why("heavy_tailed_accel", "2"), "`unexplained`: `heavy_tailed_accel` not fitted");
        let seed0 = report(cells[0]);
        let (over, p) =
            seed0.candidates.iter().find(|c| c.cause == "heavy_tailed_accel").unwrap().over_reseeded.unwrap();
        assert!(over < seed0.config.min_gain || p >= seed0.config.cause_level);
        assert!(why("heavy_tailed_accel", "0")
            .contains(&format!("fails (b) not over the reseeded refit: over it {over:+.4}")));
        assert_eq!(why("latency", "0"), "", "named: nothing to explain");
        let control = why("none-points", "3");
        assert!(
            control.starts_with("`unexplained`: checks fail") && control.contains("length_extent_ratio"),
            "{control}"
        );
        // Under the table, one line per missed cell, in the table's order.
        let listed: Vec<&str> = table.lines().filter(|l| l.starts_with("- ")).collect();
        assert_eq!(listed.len(), 4, "{table}");
        assert_eq!(listed[2], format!("- heavy_tailed_accel × 1, seed 3: {expected}"));
        assert!(listed[3].starts_with("- none-points, seed 3: "), "a control without a strength: {}", listed[3]);
        std::fs::remove_dir_all(&out).unwrap();
    }

    /// The two answers of `why_not` no committed miss holds: a control on which
    /// a cause is named says which, with its gain and p; a cause that qualifies
    /// but is not chosen says what gained more. Built on a committed report that
    /// names the mixture, with one candidate added (a copy, gaining less).
    #[test]
    fn a_miss_names_the_false_cause_or_the_larger_gain() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../results/power-study-eval-crn-32-scenes/heavy_tailed_accel/x1/seed0/report.json");
        let mut report: Report = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let (cause, chosen) = report.decided(true);
        assert_eq!(cause, "heavy_tailed_accel");
        let (gain, p) = (chosen.unwrap().gain, chosen.unwrap().p_adjusted);
        assert_eq!(report.why_not("heavy_tailed_accel"), None);
        let named = format!("`heavy_tailed_accel`: `heavy_tailed_accel` named (gain {gain:+.4}, p adj. {p:.4})");
        assert_eq!(report.why_not(NO_CAUSE).as_deref(), Some(named.as_str()), "a control");
        assert_eq!(report.why_not(UNEXPLAINED).as_deref(), Some(named.as_str()));
        assert_eq!(
            report.why_not("clutter").as_deref(),
            Some("`heavy_tailed_accel`: `clutter` not fitted"),
            "a cause without a candidate"
        );
        let mut runner_up = chosen.unwrap().clone();
        runner_up.cause = "clutter".into();
        runner_up.gain *= 0.9;
        report.candidates.push(runner_up);
        assert_eq!(report.verdicts(true).last(), Some(&None), "the copy passes every rule");
        assert_eq!(report.decided(true).0, "heavy_tailed_accel", "the larger gain is chosen");
        assert_eq!(
            report.why_not("clutter").as_deref(),
            Some("`heavy_tailed_accel`: `clutter` qualifies, but `heavy_tailed_accel` gains more")
        );
    }

    /// The flip chain's cell compares both learned magnitudes with the truth:
    /// the fraction in `relative_error`, the persistence beside it, and the
    /// table's medians name each.
    #[test]
    fn the_flip_chain_reports_the_error_of_its_fraction_and_its_persistence() {
        let out = std::env::temp_dir().join(format!("sefi-power-chain-{}", std::process::id()));
        let cell = "persistent_flip/x1/seed0";
        copy_committed_cells(&out, "power-study-persistent-flip", &[cell]);
        let effect = StudyEffect::of("persistent_flip").unwrap();
        let read = run_cell(&out, &effect, 1.0, 0, named("v4"), true).unwrap().unwrap();
        assert!(read.named);
        let names: Vec<&str> = read.relative_errors.iter().map(|e| e.0).collect();
        assert_eq!(names, ["fraction", "persistence"]);
        // The report's learned values, against the generator's 20% at persistence 0.8.
        let report: Report =
            serde_json::from_str(&std::fs::read_to_string(out.join(cell).join("report.json")).unwrap()).unwrap();
        let chain = report.candidates.iter().find(|c| c.cause == "persistent_flip").unwrap();
        let learned = |name: &str| chain.params.iter().find(|p| p.0 == name).unwrap().1;
        assert!((read.relative_errors[0].1 - (learned("fraction") / 0.2 - 1.0)).abs() < 1e-12);
        assert!((read.relative_errors[1].1 - (learned("persistence") / HIDDEN_FLIP_PERSISTENCE - 1.0)).abs() < 1e-12);
        let table = write_study_tables(&out, &[effect], &[1.0], 1, None, named("v4")).unwrap();
        let row = table.lines().find(|l| l.starts_with("| persistent_flip")).unwrap();
        assert!(row.contains("| fraction ") && row.contains(", persistence "), "{row}");
        // One cell: each median is that cell's |error|.
        let (fraction, persistence) = (read.relative_errors[0].1, read.relative_errors[1].1);
        let medians =
            format!("| fraction {:.0}%, persistence {:.0}% |", 100.0 * fraction.abs(), 100.0 * persistence.abs());
        assert!(row.contains(&medians), "{row} lacks {medians}");
        let csv = std::fs::read_to_string(out.join("power.csv")).unwrap();
        assert!(csv.lines().nth(1).unwrap().contains(",persistence:"), "{csv}");
        let columns: Vec<&str> = csv.lines().nth(1).unwrap().split(',').collect();
        assert_eq!(columns[5].parse::<f64>().unwrap(), fraction, "relative_error is the fraction's");
        assert_eq!(columns[9], format!("persistence:{persistence}"));
        std::fs::remove_dir_all(&out).unwrap();
    }
}
