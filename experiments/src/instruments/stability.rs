//! `sefi stability`: whether a diagnosis's finding hinges on its held-out set.
//! It reads the `report.json` of several diagnoses of one kind of data, each
//! evaluated on a different held-out set (KITTI fitted on one half of its
//! sequences and evaluated on the other, and the reverse; the shared train /
//! val split both ways), and sets side by side each set's outcome under the
//! current decision rules, every candidate's gain with the first rule it fails,
//! and the gain of each extension that is a cause somewhere split by part of
//! every held-out set (KITTI sequence or scene): `stability.md`,
//! `stability.json` and a forest plot of those gains, `stability.svg`.

use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use clap::Args;
use plotters::prelude::*;
use serde::Serialize;
use ssm::criticism::diagnose::{EvalPart, GroupGain, Report};

use crate::output::{ensure_dir, write_atomic, write_json};
use crate::plot::write_svg;

/// Arguments of `sefi stability`.
#[derive(Args, Debug)]
pub struct StabilityArgs {
    /// Diagnosis output directories (each holding the `report.json` of `sefi diagnose`), one per held-out set.
    #[arg(required = true, num_args = 1..)]
    reports: Vec<PathBuf>,
    /// Names of the held-out sets, comma-separated, one per directory [default: each directory's name].
    #[arg(long, value_delimiter = ',')]
    labels: Vec<String>,
    /// Output directory (stability.md, stability.json, stability.svg).
    #[arg(long, default_value = "out/stability")]
    out: PathBuf,
}

/// One diagnosis of the comparison: its held-out set and what it found.
#[derive(Debug, Serialize)]
pub struct HeldOutSet {
    /// The set's name.
    pub label: String,
    /// The diagnosis's `report.json`.
    pub report: PathBuf,
    /// Objects that fitted the models.
    pub train_objects: usize,
    /// Objects that measured the gains (those set aside excluded).
    pub eval_objects: usize,
    /// Their observed units.
    pub eval_units: usize,
    /// The outcome under the current rules ([`Report::decided`]): an extension,
    /// `unexplained` or `none`.
    pub outcome: String,
    /// The outcome the report recorded, where the current rules decide otherwise.
    pub recorded: Option<String>,
    /// For `unexplained`, the failing checks; for a cause, what it learned.
    pub finding: String,
    /// How the held-out set is split into parts.
    pub part: EvalPart,
    /// The level a candidate's Holm-adjusted p must be under (rule (a)).
    pub cause_level: f64,
    /// Every fitted candidate.
    pub candidates: Vec<CandidateOnSet>,
    /// The extensions the fitted screen fitted and turned away (neither
    /// candidates nor evaluated), each with why.
    pub not_admitted: Vec<ScreenedOut>,
    /// The extension whose gain by part is shown ([`Report::shown_candidate`]
    /// of the outcome); `None` without candidates.
    pub shown: Option<String>,
}

/// One candidate extension on one held-out set.
#[derive(Debug, Serialize)]
pub struct CandidateOnSet {
    /// The extension's id.
    pub cause: String,
    /// What it learned, in a sentence.
    pub description: String,
    /// Its held-out gain over its reference (nats per observed unit) and SE.
    pub gain: f64,
    /// See `gain`.
    pub gain_se: f64,
    /// The gain's sign-flip p, Holm-adjusted over the candidates.
    pub p_adjusted: f64,
    /// The first rule of the decision it fails (`None`: it qualifies).
    pub fails: Option<String>,
    /// Its gain by part of the held-out set (empty in reports without a
    /// per-object record).
    pub parts: Vec<GroupGain>,
}

/// An extension the fitted screen fitted on one held-out set and did not admit.
#[derive(Debug, Serialize)]
pub struct ScreenedOut {
    /// The extension's id.
    pub cause: String,
    /// Why ([`ssm::criticism::diagnose::NotAdmitted::why`]).
    pub why: String,
}

/// Runs `sefi stability`.
pub fn run(args: &StabilityArgs) -> Result<(), String> {
    if !args.labels.is_empty() && args.labels.len() != args.reports.len() {
        return Err(format!(
            "--labels names {} held-out sets and {} report directories are given: one label per directory",
            args.labels.len(),
            args.reports.len()
        ));
    }
    let mut sets = Vec::with_capacity(args.reports.len());
    for (i, dir) in args.reports.iter().enumerate() {
        let label = match args.labels.get(i) {
            Some(l) => l.clone(),
            None => {
                dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| dir.display().to_string())
            }
        };
        sets.push(held_out_set(&read_report(dir)?, label, dir.join("report.json")));
    }
    if let Some(other) = sets.iter().skip(1).find(|s| s.part != sets[0].part) {
        eprintln!(
            "note: {} is split by {} and {} by {}",
            sets[0].label,
            sets[0].part.label(),
            other.label,
            other.part.label()
        );
    }
    ensure_dir(&args.out)?;
    let value = serde_json::to_value(&sets).map_err(|e| e.to_string())?;
    write_json(&args.out.join("stability.json"), &value)?;
    let shown = shown_extensions(&sets);
    forest_plot(&args.out.join("stability.svg"), &sets, &shown)?;
    write_atomic(&args.out.join("stability.md"), markdown(&sets, &shown).as_bytes())?;
    println!("{}", agreement(&sets));
    println!("wrote {}", args.out.join("stability.md").display());
    Ok(())
}

/// Reads `dir/report.json`, naming the file in any error.
fn read_report(dir: &Path) -> Result<Report, String> {
    let path = dir.join("report.json");
    let text = std::fs::read_to_string(&path)
        .map_err(|e| format!("{}: {e} (is {} a finished `sefi diagnose` output?)", path.display(), dir.display()))?;
    serde_json::from_str(&text).map_err(|e| format!("{}: not a diagnosis report: {e}", path.display()))
}

/// What one report says, decided under the current rules.
pub fn held_out_set(r: &Report, label: String, report: PathBuf) -> HeldOutSet {
    let verdicts = r.verdicts(true);
    let (outcome, chosen) = r.outcome(&verdicts);
    let candidates = r
        .candidates
        .iter()
        .zip(&verdicts)
        .map(|(c, v)| CandidateOnSet {
            cause: c.cause.clone(),
            description: c.description.clone(),
            gain: c.gain,
            gain_se: c.gain_se,
            p_adjusted: c.p_adjusted,
            fails: v.map(|rule| rule.to_string()),
            parts: r.gains_by_part(c).unwrap_or_default(),
        })
        .collect();
    let finding = match chosen {
        Some(c) => c.description.clone(),
        None if outcome == r.cause => r.finding.clone(),
        None => format!("decided again from a recorded `{}`: the report's checks say what fails", r.cause),
    };
    HeldOutSet {
        label,
        report,
        train_objects: r.train_objects,
        eval_objects: r.eval_objects,
        eval_units: r.eval_units,
        recorded: (r.cause != outcome).then(|| r.cause.clone()),
        shown: r.shown_candidate(&outcome).map(|c| c.cause.clone()),
        outcome,
        finding,
        part: r.eval_part(),
        cause_level: r.config.cause_level,
        candidates,
        not_admitted: r.not_admitted.iter().map(|n| ScreenedOut { cause: n.cause.clone(), why: n.why() }).collect(),
    }
}

/// The extensions whose gains by part are shown: each set's
/// [`HeldOutSet::shown`] (its cause, or where it names none its candidate with
/// the largest gain, as `report.md` splits), in order of first appearance.
pub fn shown_extensions(sets: &[HeldOutSet]) -> Vec<String> {
    let mut shown: Vec<String> = Vec::new();
    for e in sets.iter().filter_map(|s| s.shown.as_ref()) {
        if !shown.contains(e) {
            shown.push(e.clone());
        }
    }
    shown
}

/// One line: the outcome of every set, and how many found each.
pub fn agreement(sets: &[HeldOutSet]) -> String {
    let outcomes: BTreeSet<&str> = sets.iter().map(|s| s.outcome.as_str()).collect();
    let counts: Vec<String> = outcomes
        .iter()
        .map(|o| format!("`{o}` on {} of {}", sets.iter().filter(|s| s.outcome == *o).count(), sets.len()))
        .collect();
    format!("held-out sets: {}", counts.join(", "))
}

/// Every extension fitted on any set (a candidate, or turned away by the
/// fitted screen), in order of first appearance.
fn fitted_extensions(sets: &[HeldOutSet]) -> Vec<&str> {
    let mut extensions: Vec<&str> = Vec::new();
    for set in sets {
        let fitted =
            set.candidates.iter().map(|c| c.cause.as_str()).chain(set.not_admitted.iter().map(|n| n.cause.as_str()));
        for e in fitted {
            if !extensions.contains(&e) {
                extensions.push(e);
            }
        }
    }
    extensions
}

/// Per extension fitted on any set (in order of first appearance): on how many
/// sets it was fitted (of those, on how many the fitted screen turned it away),
/// gained at a Holm-adjusted p under the set's level, and qualified as a cause.
pub fn consistency(sets: &[HeldOutSet]) -> Vec<String> {
    fitted_extensions(sets)
        .iter()
        .map(|e| {
            let on: Vec<(&HeldOutSet, &CandidateOnSet)> =
                sets.iter().filter_map(|set| set.candidates.iter().find(|c| c.cause == *e).map(|c| (set, c))).collect();
            let significant = on.iter().filter(|(set, c)| c.gain > 0.0 && c.p_adjusted < set.cause_level).count();
            let qualifies = on.iter().filter(|(_, c)| c.fails.is_none()).count();
            let screened_out = sets.iter().filter(|set| set.not_admitted.iter().any(|n| n.cause == *e)).count();
            let turned_away = match screened_out {
                0 => String::new(),
                n => format!(" ({n} turned away by the fitted screen)"),
            };
            format!(
                "`{e}`: fitted on {} of {} sets{turned_away}, a gain at p adj. under the level on {significant}, \
                 qualifies on {qualifies}",
                on.len() + screened_out,
                sets.len()
            )
        })
        .collect()
}

/// `gain ± se` in nats per unit.
fn gain_cell(gain: f64, se: f64) -> String {
    format!("{gain:+.4} ± {se:.4}")
}

/// `stability.md`.
fn markdown(sets: &[HeldOutSet], shown: &[String]) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# One diagnosis on {} held-out sets\n", sets.len());
    let _ = writeln!(
        s,
        "Each set's diagnosis fitted its models on other objects and measured every candidate's gain on this set \
         alone; outcomes are decided again under the current rules. Gains in nats per observed unit, ± their \
         standard error over objects; p is the sign-flip p, Holm-adjusted over the set's candidates.\n"
    );
    let _ = writeln!(s, "{}.\n", agreement(sets));
    for line in consistency(sets) {
        let _ = writeln!(s, "- {line}");
    }
    s.push('\n');
    let _ = writeln!(s, "## Outcome per held-out set\n");
    let _ = writeln!(s, "| held-out set | fitted objects | evaluated objects (units) | outcome | learned or failing checks | gain | p adj. |");
    let _ = writeln!(s, "|---|---|---|---|---|---|---|");
    for set in sets {
        let outcome = match &set.recorded {
            Some(recorded) => format!("`{}` (recorded: `{recorded}`)", set.outcome),
            None => format!("`{}`", set.outcome),
        };
        let chosen = set.candidates.iter().find(|c| c.cause == set.outcome);
        let (gain, p) = match chosen {
            Some(c) => (gain_cell(c.gain, c.gain_se), format!("{:.4}", c.p_adjusted)),
            None => ("–".into(), "–".into()),
        };
        let _ = writeln!(
            s,
            "| {} | {} | {} ({}) | {outcome} | {} | {gain} | {p} |",
            set.label, set.train_objects, set.eval_objects, set.eval_units, set.finding
        );
    }
    let _ = writeln!(s, "\n## Every candidate on every set\n");
    let _ = writeln!(
        s,
        "A candidate qualifies when it fails none of the decision's rules; the cause is the qualifying one with the \
         largest evaluation log-likelihood. – : not fitted on that set. An extension the fitted screen fitted \
         and turned away is neither a candidate nor evaluated: its cell says why.\n"
    );
    let extensions = fitted_extensions(sets);
    let header: Vec<&str> = sets.iter().map(|set| set.label.as_str()).collect();
    let _ = writeln!(s, "| extension | {} |", header.join(" | "));
    let _ = writeln!(s, "|---|{}", "---|".repeat(sets.len()));
    for e in &extensions {
        let cells: Vec<String> = sets
            .iter()
            .map(|set| match set.candidates.iter().find(|c| c.cause == *e) {
                Some(c) => format!(
                    "{}, p {:.4}: {}",
                    gain_cell(c.gain, c.gain_se),
                    c.p_adjusted,
                    c.fails.as_deref().unwrap_or("qualifies")
                ),
                None => match set.not_admitted.iter().find(|n| n.cause == *e) {
                    Some(n) => n.why.clone(),
                    None => "–".into(),
                },
            })
            .collect();
        let _ = writeln!(s, "| `{e}` | {} |", cells.join(" | "));
    }
    let _ = writeln!(s, "\n## Gains by part of each held-out set\n");
    let _ = writeln!(
        s,
        "Whether a gain is carried by the whole set or by one of its parts: each set's cause, or where it names \
         none its candidate with the largest gain, on every set where it was fitted, per part ![gains by part]\
         (stability.svg).\n"
    );
    for e in shown {
        let _ = writeln!(s, "### `{e}`\n");
        let _ = writeln!(s, "| held-out set | part | objects | units | gain | objects gaining |");
        let _ = writeln!(s, "|---|---|---|---|---|---|");
        let mut summary = Vec::new();
        for set in sets {
            let Some(c) = set.candidates.iter().find(|c| c.cause == *e) else { continue };
            for g in &c.parts {
                let _ = writeln!(
                    s,
                    "| {} | {} {} | {} | {} | {} | {:.0}% |",
                    set.label,
                    set.part.label(),
                    g.group,
                    g.objects,
                    g.units,
                    gain_cell(g.gain, g.gain_se),
                    100.0 * g.positive
                );
            }
            let positive = c.parts.iter().filter(|g| g.gain > 0.0).count();
            let above = c.parts.iter().filter(|g| g.gain > 2.0 * g.gain_se).count();
            summary.push(format!(
                "{}: positive in {positive} of {} parts, above 2 SE in {above}",
                set.label,
                c.parts.len()
            ));
        }
        let _ = writeln!(s, "\n{}.\n", summary.join("; "));
    }
    s
}

/// One row of the forest plot: a set's whole gain or one of its parts.
struct ForestRow {
    label: String,
    /// Per shown extension, its gain and SE on this row (absent where not fitted).
    gains: Vec<Option<(f64, f64)>>,
    whole: bool,
}

/// The rows of the forest plot: per set, its whole gain then each part.
fn forest_rows(sets: &[HeldOutSet], shown: &[String]) -> Vec<ForestRow> {
    let mut rows = Vec::new();
    for set in sets {
        let of = |e: &String| set.candidates.iter().find(|c| c.cause == *e);
        rows.push(ForestRow {
            label: format!("{}: {}", set.label, set.outcome),
            gains: shown.iter().map(|e| of(e).map(|c| (c.gain, c.gain_se))).collect(),
            whole: true,
        });
        let mut parts: BTreeSet<i64> = BTreeSet::new();
        for e in shown {
            parts.extend(of(e).into_iter().flat_map(|c| c.parts.iter().map(|g| g.group)));
        }
        for part in parts {
            let gains = shown
                .iter()
                .map(|e| of(e).and_then(|c| c.parts.iter().find(|g| g.group == part)).map(|g| (g.gain, g.gain_se)))
                .collect();
            let name = match set.part {
                EvalPart::KittiSequence => format!("seq. {part}"),
                EvalPart::Scene => format!("scene {part}"),
            };
            rows.push(ForestRow { label: format!("  {name}"), gains, whole: false });
        }
    }
    rows
}

/// The forest plot: per row, each shown extension's gain with a bar of ± 2 SE
/// (a filled marker for a set's whole gain), and the zero line.
fn forest_plot(path: &Path, sets: &[HeldOutSet], shown: &[String]) -> Result<(), String> {
    let rows = forest_rows(sets, shown);
    let spans = rows.iter().flat_map(|r| r.gains.iter().flatten()).map(|&(g, se)| (g - 2.0 * se, g + 2.0 * se));
    let (mut x0, mut x1) = (0.0f64, 0.0f64);
    for (lo, hi) in spans.filter(|(lo, hi)| lo.is_finite() && hi.is_finite()) {
        x0 = x0.min(lo);
        x1 = x1.max(hi);
    }
    let pad = ((x1 - x0) * 0.05).max(1e-6);
    let (x0, x1) = (x0 - pad, x1 + pad);
    let n = rows.len().max(1) as f64;
    let height = (90 + 20 * rows.len()) as u32;
    let label_width = 250u32;
    write_svg(path, (950, height.max(240)), |root, err| {
        let area = root.titled("Held-out gain by set and part (± 2 SE)", ("sans-serif", 20)).map_err(|e| err(&e))?;
        let mut chart = ChartBuilder::on(&area)
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(label_width)
            .right_y_label_area_size(0)
            .build_cartesian_2d(x0..x1, -n..0.0)
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .y_labels(0)
            .x_desc("gain (nats per observed unit)")
            .draw()
            .map_err(|e| err(&e))?;
        chart
            .draw_series(std::iter::once(PathElement::new(vec![(0.0, -n), (0.0, 0.0)], BLACK.stroke_width(1))))
            .map_err(|e| err(&e))?;
        let k = shown.len().max(1) as f64;
        for (e, name) in shown.iter().enumerate() {
            let color = Palette99::pick(e).to_rgba();
            let y = |i: usize| -(i as f64) - 0.5 - 0.5 * ((e as f64 + 0.5) / k - 0.5);
            let points = rows.iter().enumerate().filter_map(|(i, r)| r.gains[e].map(|g| (i, r.whole, g)));
            let mut first = true;
            for (i, whole, (g, se)) in points {
                if !(g.is_finite() && se.is_finite()) {
                    continue;
                }
                chart
                    .draw_series(std::iter::once(PathElement::new(
                        vec![(g - 2.0 * se, y(i)), (g + 2.0 * se, y(i))],
                        color.stroke_width(if whole { 3 } else { 1 }),
                    )))
                    .map_err(|e| err(&e))?;
                let marker = if whole { color.filled() } else { color.stroke_width(1) };
                let drawn = chart
                    .draw_series(std::iter::once(Circle::new((g, y(i)), if whole { 5 } else { 3 }, marker)))
                    .map_err(|e| err(&e))?;
                if first {
                    drawn.label(name.clone()).legend(move |(x, y)| Circle::new((x + 10, y), 4, color.filled()));
                    first = false;
                }
            }
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| err(&e))?;
        for (i, r) in rows.iter().enumerate() {
            let (_, py) = chart.backend_coord(&(x0, -(i as f64) - 0.5));
            let style = if r.whole {
                ("sans-serif", 13).into_font().style(FontStyle::Bold)
            } else {
                ("sans-serif", 12).into_font()
            };
            root.draw(&Text::new(r.label.clone(), (14, py - 6), style)).map_err(|e| err(&e))?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ssm::criticism::diagnose::{NO_CAUSE, UNEXPLAINED};

    fn candidate(cause: &str, gain: f64, parts: &[(i64, f64)]) -> CandidateOnSet {
        CandidateOnSet {
            cause: cause.into(),
            description: String::new(),
            gain,
            gain_se: 0.1,
            p_adjusted: 0.01,
            fails: None,
            parts: parts
                .iter()
                .map(|&(group, gain)| GroupGain { group, objects: 3, units: 30, gain, gain_se: 0.2, positive: 1.0 })
                .collect(),
        }
    }

    /// A set with outcome `outcome` whose gains by part show `shown` (what
    /// [`Report::shown_candidate`] chooses is tested on committed reports in
    /// `diagnose.rs`).
    fn set(label: &str, outcome: &str, shown: Option<&str>, candidates: Vec<CandidateOnSet>) -> HeldOutSet {
        HeldOutSet {
            shown: shown.map(str::to_owned),
            label: label.into(),
            report: PathBuf::new(),
            train_objects: 10,
            eval_objects: 6,
            eval_units: 60,
            outcome: outcome.into(),
            recorded: None,
            finding: String::new(),
            part: EvalPart::KittiSequence,
            cause_level: 0.05,
            candidates,
            not_admitted: vec![],
        }
    }

    /// A committed diagnosis under the fitted screen whose screen turned two
    /// extensions away, one at its futility stop and one fitted to its end
    /// (the Student-t at the default scale, seed 2): each is listed with why,
    /// and neither is a candidate.
    #[test]
    fn the_extensions_the_fitted_screen_turned_away_are_listed_with_why() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../results/diagnose-student-t-default/seed2");
        let set = held_out_set(&read_report(&dir).unwrap(), "seed 2".into(), dir.join("report.json"));
        let why: Vec<(&str, &str)> = set.not_admitted.iter().map(|n| (n.cause.as_str(), n.why.as_str())).collect();
        assert_eq!(
            why,
            [
                ("clutter", "not admitted by the fitted screen: check-part gain +0.0001, p 0.475"),
                (
                    "heavy_tailed_accel",
                    "stopped at step 100 by the fitted screen's futility stop: its check-part evaluation had not risen \
                     above the base's"
                ),
            ]
        );
        assert!(set.candidates.iter().all(|c| c.cause != "clutter" && c.cause != "heavy_tailed_accel"));
        assert_eq!(
            fitted_extensions(std::slice::from_ref(&set)),
            ["latency", "size_bias", "clutter", "heavy_tailed_accel"]
        );
    }

    /// The shown extensions are the sets' own, each once; the forest plot has a whole row per set then one per part any of them has.
    #[test]
    fn the_forest_rows_hold_every_set_and_part_of_the_shown_extensions() {
        let mut sets = [
            set(
                "a",
                "heading_flip",
                Some("heading_flip"),
                vec![candidate("latency", 0.9, &[]), candidate("heading_flip", 0.4, &[(1, 0.3), (4, 0.5)])],
            ),
            set(
                "b",
                UNEXPLAINED,
                Some("persistent_flip"),
                vec![
                    candidate("heading_flip", 0.2, &[(2, 0.1)]),
                    candidate("persistent_flip", 0.3, &[(2, 0.4), (7, -0.1)]),
                ],
            ),
            set("c", NO_CAUSE, None, vec![]),
        ];
        let why = "stopped at step 100 by the fitted screen's futility stop";
        sets[2].not_admitted.push(ScreenedOut { cause: "heading_flip".into(), why: why.into() });
        let shown = shown_extensions(&sets);
        assert_eq!(shown, ["heading_flip", "persistent_flip"]);
        let rows = forest_rows(&sets, &shown);
        let labels: Vec<&str> = rows.iter().map(|r| r.label.trim()).collect();
        assert_eq!(labels, ["a: heading_flip", "seq. 1", "seq. 4", "b: unexplained", "seq. 2", "seq. 7", "c: none"]);
        // Set b, sequence 7: persistent flips only.
        assert_eq!(rows[5].gains, [None, Some((-0.1, 0.2))]);
        assert_eq!(rows[3].gains, [Some((0.2, 0.1)), Some((0.3, 0.1))]);
        assert!(rows[6].gains.iter().all(Option::is_none));
        assert_eq!(
            agreement(&sets),
            "held-out sets: `heading_flip` on 1 of 3, `none` on 1 of 3, `unexplained` on 1 of 3"
        );
        let md = markdown(&sets, &shown);
        assert!(md.contains("| `latency` | +0.9000 ± 0.1000, p 0.0100: qualifies | – | – |"), "{md}");
        assert!(md.contains(&format!("p 0.0100: qualifies | {why} |")), "the screened-out fit says why: {md}");
        assert!(md.contains("b: positive in 1 of 2 parts, above 2 SE in 0"), "{md}");
        assert_eq!(
            consistency(&sets)[1],
            "`heading_flip`: fitted on 3 of 3 sets (1 turned away by the fitted screen), a gain at p adj. under the \
             level on 2, qualifies on 2"
        );
    }
}
