//! `sefi diagnose` on generated data with one hidden effect each, at magnitudes
//! other than the generator's defaults and on other seeds than the development
//! runs', and on controls of both kinds: the diagnosis must name the effect with a
//! gain that passes its permutation test and the minimum effect, must never blame
//! a Student-t tail on an effect other than `heavy_tailed_accel` (the catalogue's
//! heavy-tail extension; how often it is named is the power study's measure), and
//! must name no catalogue cause on a control, nor persistent flips where they
//! are independent. It is told nothing about the
//! data beyond the files. The power study (`sefi power-study`, README) runs the
//! same at three strengths and five seeds each.

use crate::common::{failed, ok, s, sefi, temp};
use autodiff::nn::ParamStore;
use serde_json::Value;
use ssm::criticism::diagnose::{
    beats_reseeded, diagnose as diagnose_data, DiagnoseConfig, Protocol, Report, Screen, REPORT_FORMAT_VERSION,
};
use ssm::data::Dataset;
use ssm::models::extended::RefitScope;
use ssm::training::{Checkpoint, CHECKPOINT_FILE, EVAL_LOG};
use ssm::util::reduce::{Collective, SingleProcess};
use std::path::Path;
use std::sync::Arc;

/// Generates data with `effect` hidden at `strength` (seed `seed`, extra
/// `generate` arguments such as `--boxes --scenes 32`), runs `diagnose --quick`
/// on it and returns the parsed `report.json` with the output directory.
fn diagnose(effect: &str, strength: &str, seed: &str, extra: &[&str]) -> (Value, std::path::PathBuf) {
    let dir = temp("diagnose", &format!("{effect}-{strength}-{seed}"));
    let data = dir.join("data");
    let out = dir.join("out");
    let mut args = vec!["generate", "--hidden", effect, "--strength", strength, "--out", s(&data), "--seed", seed];
    args.extend(extra);
    ok(&sefi(&args));
    let stdout = ok(&sefi(&["diagnose", "--data", s(&data), "--out", s(&out), "--quick", "--seed", seed]));
    let text = std::fs::read_to_string(out.join("report.json")).expect("report.json");
    let report: Value = serde_json::from_str(&text).expect("report.json is JSON");
    // It reads back as the library's report too, non-finite numbers (`null`) and all,
    // as `sefi power-study` does when it resumes.
    let typed: Result<Report, _> = serde_json::from_str(&text);
    let typed = typed.unwrap_or_else(|err| panic!("report.json does not read back as a Report: {err}"));
    assert_eq!(report["format_version"], REPORT_FORMAT_VERSION, "report.json's format version");
    // Deciding again from the report's own candidates and checks (as the power
    // study does with reports of earlier rules) gives the outcome it names.
    let (again, chosen) = typed.decided(true);
    assert_eq!(again, typed.cause, "decided again from the report");
    match chosen {
        Some(c) => assert_eq!((c.cause.as_str(), c.gain), (typed.cause.as_str(), typed.gain), "the chosen candidate"),
        None => assert_eq!(typed.gain, 0.0, "no candidate chosen, no gain"),
    }
    // A report whose candidates lack their comparison with the reseeded refit
    // (written before it) is compared again from the refit's per-object gains,
    // with the same seeds: the same outcome.
    let reseeded: Option<Vec<&[f64]>> = typed
        .candidates
        .iter()
        .map(|c| typed.reference_of(c).and_then(|r| r.reseeded.as_ref()).map(|r| r.object_gains.as_slice()))
        .collect();
    if let Some(reseeded) = reseeded.filter(|r| !r.is_empty()) {
        let gains: Vec<&[f64]> = typed.candidates.iter().map(|c| c.object_gains.as_slice()).collect();
        let family: Vec<bool> = typed.candidates.iter().map(|c| c.admitted(typed.config.plausible_p)).collect();
        let again = beats_reseeded(&gains, &reseeded, typed.eval_units, &family, &typed.config);
        // The same p-values; the gains to rounding (the per-object gains went
        // through JSON's decimal text).
        for ((gain, p), c) in again.into_iter().zip(&typed.candidates) {
            let (stored_gain, stored_p) = c.over_reseeded.expect("the comparison with the reseeded refit");
            assert_eq!(p, stored_p, "{}", c.cause);
            assert!(
                (gain - stored_gain).abs() <= 1e-12 * (1.0 + gain.abs()),
                "{}: {gain} against {stored_gain}",
                c.cause
            );
        }
    }
    let mut uncompared = typed.clone();
    uncompared.candidates.iter_mut().for_each(|c| c.over_reseeded = None);
    assert_eq!(uncompared.decided(true).0, typed.cause, "decided again with the comparison made anew");
    assert!(stdout.contains(&format!("cause: {}", report["cause"].as_str().unwrap())), "stdout: {stdout}");
    // The filters' defaults for the data's observations: origin moves in the
    // checks and evaluations of boxes only, none in training.
    let origin_steps = report["config"]["tempering"]["origin_steps"].as_u64();
    assert_eq!(origin_steps, Some(if extra.contains(&"--boxes") { 8 } else { 0 }), "tempering by the data's kind");
    assert_eq!(report["config"]["train_tempering"]["origin_steps"].as_u64(), Some(0), "training without origin moves");
    // Candidates are compared with the base refitted alone as they were refitted:
    // a reference with its own checks for each refit scope that has a candidate
    // (every parameter; the policy alone for an extension of the dynamics).
    let candidates = report["candidates"].as_array().unwrap();
    assert_eq!((&report["config"]["refit"], &report["config"]["scoped_refits"]), (&true.into(), &true.into()));
    for (scope, field, dir) in
        [("all", "reference", "reference"), ("dynamics", "dynamics_reference", "reference-dynamics")]
    {
        let in_scope = candidates.iter().any(|c| c["refit_scope"] == scope);
        assert_eq!(report[field].is_object(), in_scope, "{}", summary(&report));
        assert_eq!(out.join(dir).join("train.csv").is_file(), in_scope, "{dir}'s training run");
    }
    for c in candidates {
        let scope = if c["cause"] == "heavy_tailed_accel" { "dynamics" } else { "all" };
        assert_eq!(c["refit_scope"], scope, "{}", c["cause"]);
    }
    // A refit in the policy alone holds the observation network at the base's
    // (the parameters it kept, where the refit starts) to its last step, and
    // moves the policy.
    let base = ParamStore::<f64>::load(&out.join("base").join("params.bin")).expect("the base's params.bin");
    let tensor = |p: &ParamStore<f64>, name: &str| p.get(p.id(name).unwrap()).data().to_vec();
    let observation = |p: &ParamStore<f64>| -> Vec<Vec<f64>> {
        p.iter().filter(|(n, _)| n.starts_with("obs.")).map(|(_, v)| v.data().to_vec()).collect()
    };
    let held = [out.join("reference-dynamics"), out.join("candidates").join("heavy_tailed_accel")];
    for dir in held.into_iter().filter(|d| d.is_dir()) {
        let last = Checkpoint::load(&dir.join(CHECKPOINT_FILE)).expect("the refit's checkpoint").params;
        assert!(!observation(&last).is_empty());
        assert_eq!(observation(&last), observation(&base), "{} moved the observation network", dir.display());
        assert_ne!(tensor(&last, "policy.0.w"), tensor(&base, "policy.0.w"), "{} left the policy", dir.display());
    }
    for reference in [report["reference"].as_object(), report["dynamics_reference"].as_object()].into_iter().flatten() {
        let n = report["checks"].as_array().unwrap().len();
        assert_eq!(reference["checks"].as_array().unwrap().len(), n);
        assert!(candidates.iter().all(|c| c["checks_after"].as_array().unwrap().len() == n));
        // The reseeded refit keeps its per-object gains, which sum to its gain.
        let reseeded = &reference["reseeded"];
        let gains = reseeded["object_gains"].as_array().expect("the reseeded refit's object gains");
        assert_eq!(gains.len(), typed.eval_object_keys.len());
        assert_eq!(reseeded["object_mc_sd"].as_array().map(Vec::len), Some(gains.len()));
        let sum: f64 = gains.iter().map(|g| g.as_f64().unwrap()).sum();
        let (gain, units) = (reseeded["gain"].as_f64().unwrap(), report["eval_units"].as_f64().unwrap());
        assert!((sum / units - gain).abs() <= 1e-9 * (1.0 + gain.abs()), "{sum} / {units} against {gain}");
    }
    // Every fit kept the parameters of its best evaluation on the check part:
    // the largest test MLL of its evaluation log, whose last row is the end.
    assert!(report["config"]["keep_best_every"].as_u64().unwrap() > 0);
    let mut fits = vec![(&report["base_kept"], out.join("base"))];
    for (field, dir) in [("reference", "reference"), ("dynamics_reference", "reference-dynamics")] {
        if let Some(reference) = report[field].as_object() {
            fits.push((&reference["kept"], out.join(dir)));
            fits.push((&reference["reseeded"]["kept"], out.join(format!("{dir}-reseeded"))));
        }
    }
    for c in candidates {
        fits.push((&c["kept"], out.join("candidates").join(c["cause"].as_str().unwrap())));
    }
    for (kept, dir) in fits {
        let log = std::fs::read_to_string(dir.join("eval.csv")).expect("a fit's evaluation log");
        let rows: Vec<(u64, f64)> = log
            .lines()
            .skip(1)
            .map(|l| {
                let mut f = l.split(',');
                (f.next().unwrap().parse().unwrap(), f.next().unwrap().parse().unwrap())
            })
            .collect();
        let best = rows.iter().copied().filter(|r| r.1.is_finite()).max_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
        // Equal to rounding: JSON's reader need not round decimal text exactly.
        let close = |x: Option<f64>, y: f64| x.is_some_and(|x| (x - y).abs() <= 1e-12 * y.abs());
        assert_eq!(kept["step"].as_u64(), Some(best.0), "{}", dir.display());
        assert!(close(kept["value"].as_f64(), best.1), "{}: {kept} against {best:?}", dir.display());
        assert!(close(kept["last"].as_f64(), rows.last().unwrap().1), "{}: {kept} against {rows:?}", dir.display());
        assert!(rows.len() >= 3, "evaluated along the way: {rows:?}");
    }
    // The evaluation part's objects are those measured, in the order of every
    // candidate's per-object gains and Monte Carlo sds, and those set aside.
    let set_aside = typed.eval_imprecise.iter().filter(|o| o.set_aside).count();
    assert_eq!(typed.eval_object_keys.len() + set_aside, typed.eval_objects);
    assert_eq!(typed.eval_object_units.len(), typed.eval_object_keys.len());
    let measured_units: usize = typed.eval_object_units.iter().sum();
    assert_eq!(measured_units, typed.eval_units);
    for c in &typed.candidates {
        assert_eq!(
            (c.object_gains.len(), c.object_mc_sd.len()),
            (typed.eval_object_keys.len(), typed.eval_object_keys.len())
        );
    }
    let md = std::fs::read_to_string(out.join("report.md")).expect("report.md");
    assert!(md.contains("## Parameters each fit kept") && md.contains("| base | "), "{md}");
    // The held-out Monte Carlo error comes from the evaluation's own filter runs:
    // two runs with different seeds never agree to the last bit, so with two or
    // more runs per object it is positive for every candidate, and the total
    // (sqrt of the summed per-object variances, per unit) lies between the least
    // precise object's error and sqrt(objects) times it.
    if report["config"]["eval_runs"].as_u64().unwrap() >= 2 {
        let units = report["eval_units"].as_f64().unwrap();
        let objects = typed.eval_object_keys.len() as f64;
        for c in candidates {
            let (total, worst) = (c["gain_mc_sd"].as_f64(), c["worst_object_mc_sd"].as_f64());
            let (Some(total), Some(worst)) = (total, worst) else {
                panic!("MC sd of {}: {}, worst {}", c["cause"], c["gain_mc_sd"], c["worst_object_mc_sd"])
            };
            assert!(total.is_finite() && total > 0.0 && worst.is_finite() && worst > 0.0, "{total} {worst}");
            let summed = total * units;
            assert!(worst * (1.0 - 1e-12) <= summed && summed <= worst * objects.sqrt() * (1.0 + 1e-12), "{c}");
        }
    }
    (report, out)
}

/// The diagnosis of `effect` at `strength` names `cause` ([`assert_names`]).
fn assert_found(effect: &str, strength: &str, seed: &str, extra: &[&str], cause: &str) {
    let (report, out) = diagnose(effect, strength, seed, extra);
    assert_names(&report, &out, cause);
}

/// The report (written to `out`) names `cause`: its gain passes the
/// Holm-adjusted permutation test and the minimum effect, the checks that
/// flagged it improve, and the report's files are there.
fn assert_names(report: &Value, out: &std::path::Path, cause: &str) {
    let summary = summary(report);
    assert_eq!(report["cause"], cause, "{summary}");
    let config = &report["config"];
    let gain = report["gain"].as_f64().unwrap();
    assert!(gain >= config["min_gain"].as_f64().unwrap(), "gain {gain}\n{summary}");
    assert!(report["gain_p"].as_f64().unwrap() < config["cause_level"].as_f64().unwrap(), "{summary}");
    let winner = report["candidates"].as_array().unwrap().iter().find(|c| c["cause"] == cause).expect("candidate");
    assert!(!winner["params"].as_array().unwrap().is_empty(), "learned parameters reported");
    assert!(!winner["flagged_by"].as_array().unwrap().is_empty(), "{summary}");
    assert_eq!(winner["checks_improved"], true, "{summary}");
    let (fit, check, eval) = (&report["train_objects"], &report["check_objects"], &report["eval_objects"]);
    assert!(fit.as_u64().unwrap() > 0 && check.as_u64().unwrap() > 0 && eval.as_u64().unwrap() > 0);
    let checks = report["checks"].as_array().unwrap();
    assert!(checks.iter().all(|c| c["after"].is_object()), "{summary}");
    let md = std::fs::read_to_string(out.join("report.md")).expect("report.md");
    assert!(md.contains(&format!("Cause: `{cause}`")), "{md}");
    assert!(std::fs::read_dir(out).unwrap().any(|e| e.unwrap().file_name().to_string_lossy().ends_with(".svg")));
}

/// Data with `effect` (a control, or an effect outside the catalogue) name no
/// catalogue cause: `none`, or `unexplained` when a check that no extension
/// speaks to fails (the effect, or the base network's own misfit).
fn assert_no_catalogue_cause(effect: &str, seed: &str, extra: &[&str]) {
    assert_no_false_cause(effect, "1", seed, extra, None);
}

/// Data with `effect` at `strength` name no catalogue cause other than `right`
/// (if any): `right` itself, named as [`assert_names`] asks, or `none` /
/// `unexplained` without a gain.
fn assert_no_false_cause(effect: &str, strength: &str, seed: &str, extra: &[&str], right: Option<&str>) {
    let (report, out) = diagnose(effect, strength, seed, extra);
    let cause = report["cause"].as_str().unwrap();
    if Some(cause) == right {
        return assert_names(&report, &out, cause);
    }
    assert!(cause == "none" || cause == "unexplained", "{}", summary(&report));
    assert_eq!(report["gain"], 0.0);
    let md = std::fs::read_to_string(out.join("report.md")).expect("report.md");
    assert!(md.contains("No cause found") || md.contains("Unexplained"), "{md}");
}

/// The cause, gain and every candidate and significant check, for failure messages.
fn summary(report: &Value) -> String {
    let mut s =
        format!("cause {} gain {} ± {} (p {})\n", report["cause"], report["gain"], report["gain_se"], report["gain_p"]);
    for c in report["candidates"].as_array().unwrap() {
        s += &format!(
            "  candidate {} gain {} ± {} p_adj {} checks improved {} qualifies {}: {}\n",
            c["cause"],
            c["gain"],
            c["gain_se"],
            c["p_adjusted"],
            c["checks_improved"],
            c["qualifies"],
            c["description"]
        );
    }
    for c in report["checks"].as_array().unwrap() {
        s += &format!("  check {} z {} p_adj {}\n", c["name"], c["before"]["z"], c["before"]["p_adjusted"]);
    }
    s
}

#[test]
fn finds_weaker_latency() {
    assert_found("latency", "0.5", "4", &[], "latency");
}

#[test]
fn finds_weaker_clutter() {
    assert_found("clutter", "0.5", "5", &[], "clutter");
}

#[test]
fn finds_weaker_size_bias() {
    assert_found("size_bias", "0.5", "6", &[], "size_bias");
}

/// Heavy tails act on a latent quantity, seen only through the positions of
/// point sets over several steps: 16 scenes, and a stronger tail (10% at 19x).
#[test]
fn finds_stronger_heavy_tailed_accel() {
    assert_found("heavy_tailed_accel", "2", "7", &["--scenes", "16"], "heavy_tailed_accel");
}

/// Another tail family than the catalogue's two-normal mixture: Student-t at
/// unit scale with the mixture's divergence from the Gaussian at double strength
/// (2.06 degrees of freedom, `HiddenEffect::at_strength`) is never blamed on
/// another catalogue effect: it is named `heavy_tailed_accel` or left
/// `unexplained` / `none`. Whether it is named is a rate, measured by the power
/// study (README: at this strength 1 of 5 seeds, at the middle one 3 of 5), not a
/// property of one cell: this cell was named (+0.0130, Holm p 0.0008) by the
/// filter of 2026-11-26, and its Holm p moved to 0.051 when the tempered filter's
/// stage exponents moved by less than 2^-40 (a faster exponent search, 2026-11-27),
/// so asserting the name tested one draw of a noisy decision.
#[test]
fn student_t_accelerations_are_never_blamed_on_another_effect() {
    assert_no_false_cause("student_t_accel", "2", "8", &["--scenes", "16"], Some("heavy_tailed_accel"));
}

/// Independent flips: named `heading_flip`; where the reversal persistence
/// check also makes persistent flips plausible, the chain must not out-gain
/// the independent flips by object.
#[test]
fn finds_stronger_heading_flip() {
    assert_found("heading_flip", "1.5", "9", &["--boxes", "--scenes", "32"], "heading_flip");
}

/// Reversed headings in runs (a flip chain: 20% of detections, persistence
/// 0.8): named `persistent_flip`, which must beat `heading_flip` — fitted too,
/// as the reversal fraction flags it — by object (rule (e)).
#[test]
fn finds_persistent_flip_over_independent_flips() {
    let (report, out) = diagnose("persistent_flip", "1", "31", &["--boxes", "--scenes", "16"]);
    assert_names(&report, &out, "persistent_flip");
    let candidates = report["candidates"].as_array().unwrap();
    let chain = candidates.iter().find(|c| c["cause"] == "persistent_flip").unwrap();
    assert!(candidates.iter().any(|c| c["cause"] == "heading_flip"), "{}", summary(&report));
    let over = &chain["over_nested"];
    assert_eq!(over["nested"], "heading_flip", "{}", summary(&report));
    assert!(over["gain"].as_f64().unwrap() > 0.0 && over["p"].as_f64().unwrap() < 0.05, "{over}");
    assert!(std::fs::read_to_string(out.join("report.md")).unwrap().contains("heading_flip: +"), "over nested");
}

#[test]
fn control_points_names_no_catalogue_cause() {
    assert_no_catalogue_cause("none", "10", &[]);
}

/// An effect outside the catalogue — the observer's own pose off by 0.2 m and
/// 0.02 rad (sds) at each step — must not be blamed on a catalogue extension.
#[test]
fn effect_outside_the_catalogue_names_no_catalogue_cause() {
    assert_no_catalogue_cause("ego_pose_noise", "15", &[]);
}

#[test]
fn control_boxes_names_no_catalogue_cause() {
    assert_no_catalogue_cause("none", "11", &["--boxes", "--scenes", "32"]);
}

#[test]
fn bad_input_is_a_clear_error() {
    let dir = temp("diagnose", "bad");
    let out = sefi(&["diagnose", "--data", s(&dir.join("missing")), "--out", s(&dir.join("out"))]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("missing"), "{err}");
    let out = sefi(&["generate", "--hidden", "heading_flip", "--out", s(&dir.join("d"))]);
    assert!(!out.status.success(), "heading_flip on point data is refused");
    assert!(String::from_utf8_lossy(&out.stderr).contains("heading_flip"));
    let out = sefi(&["generate", "--hidden", "latency", "--strength", "0", "--out", s(&dir.join("d"))]);
    assert!(!out.status.success(), "a strength of zero is refused");
    assert!(String::from_utf8_lossy(&out.stderr).contains("strength"));
}

/// `sefi power-study --protocol` reaches every cell: a table rebuilt over a
/// committed cell of the first study (protocol v3) is refused under the
/// default protocol, naming both, and rebuilt under v3.
#[test]
fn power_study_protocol_sets_the_study_protocol() {
    let out = temp("power", "protocol");
    let cell = out.join("latency/x1/seed0");
    std::fs::create_dir_all(&cell).unwrap();
    let committed =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../results/power-study/latency/x1/seed0/report.json");
    std::fs::copy(committed, cell.join("report.json")).unwrap();
    let table = ["power-study", "--table-only", "--effects", "latency", "--strengths", "1", "--seeds", "1"];
    let table = [table.as_slice(), &["--out", s(&out)]].concat();
    let err = failed(&sefi(&table));
    assert!(err.contains("under protocol v3 (") && err.contains("this study's is protocol v7 ("), "{err}");
    ok(&sefi(&[table.as_slice(), &["--protocol", "v3"]].concat()));
    assert!(std::fs::read_to_string(out.join("power.csv")).unwrap().contains("latency,1,0,"));
    std::fs::remove_dir_all(&out).unwrap();
}

/// The options of `sefi diagnose` are what a user sets: the study switches are
/// gone (a study names a protocol), and no help text cites a date.
#[test]
fn diagnose_shows_only_the_options_a_user_sets() {
    let help = ok(&sefi(&["diagnose", "--help"]));
    // An option's line starts at the second column (`-h, --help`) or the sixth (`--data <DATA>`); a
    // description's continuation is indented further.
    let mut options: Vec<&str> = help
        .lines()
        .filter_map(|l| l.strip_prefix("  -h, ").or_else(|| l.strip_prefix("      ")))
        .filter_map(|l| l.strip_prefix("--"))
        .map(|l| l.split([' ', '<']).next().unwrap())
        .collect();
    options.sort_unstable();
    let expected = [
        "base-steps",
        "candidate-steps",
        "data",
        "eval-particles",
        "eval-runs",
        "heldout",
        "help",
        "out",
        "particles",
        "protocol",
        "quick",
        "seed",
    ];
    assert_eq!(options, expected, "{help}");
    // A date in the form YYYY-MM-DD: `20`, two digits and a dash.
    let dated = |text: &str| {
        text.as_bytes()
            .windows(5)
            .any(|w| w.starts_with(b"20") && w[2..4].iter().all(u8::is_ascii_digit) && w[4] == b'-')
    };
    for command in [["diagnose", "--help"], ["power-study", "--help"]] {
        let help = ok(&sefi(&command));
        assert!(!help.contains("session") && !dated(&help), "{help}");
    }
    for switch in ["--fit-all", "--fitted-screen", "--keep-unmeasured", "--refine-factor", "--min-gain"] {
        let err = failed(&sefi(&["diagnose", "--data", "missing", switch]));
        assert!(err.contains(&format!("unexpected argument '{switch}'")), "{err}");
    }
}

/// Diagnoses the data in `data` into `out` in this process, under `config`,
/// as `sefi diagnose` does (its fits resume from `out`). For the tests whose
/// settings no protocol names (a scale small enough for a test, a bar set
/// from a first run's numbers).
fn diagnose_in_process(data: &Path, out: &Path, config: &DiagnoseConfig) -> Report {
    let data = Dataset::read(data).unwrap();
    let comm: Arc<dyn Collective> = Arc::new(SingleProcess);
    diagnose_data(&data, config, out, &comm, &mut |_| {}).unwrap()
}

/// The quick diagnosis under protocol `protocol` with `screen`, seed `seed`,
/// at a test's scale: `base_steps` and `candidate_steps`, 32 particles.
fn small(protocol: &str, screen: Screen, seed: u64, base_steps: usize, candidate_steps: usize) -> DiagnoseConfig {
    let mut config = DiagnoseConfig::quick();
    Protocol::named(protocol).unwrap().apply(&mut config);
    screen.apply_to(&mut config);
    config.seed = seed;
    (config.base_steps, config.candidate_steps) = (base_steps, candidate_steps);
    (config.particles, config.eval_particles) = (32, 32);
    config
}

/// Setting aside the objects no model measures (the default), at a small scale
/// with every extension fitted (so that every model compared is in the
/// report): a first diagnosis under protocol v6 (every object kept) gives every
/// model's per-object Monte Carlo sds; a second, under v7 and resumed from the
/// same fits with the bar set between two of the objects' largest sds, flags
/// exactly the objects over it (the evaluation is deterministic), refilters
/// them at 4 times the particles and sets aside exactly those
/// that stay over it; the objects set aside leave the evaluation part's keys,
/// units and every gain, and every model's estimates of the others are the
/// first run's, refined ones excepted.
#[test]
fn objects_a_model_does_not_measure_are_refined_then_set_aside() {
    let dir = temp("diagnose", "set-aside");
    let (data, out) = (dir.join("data"), dir.join("out"));
    ok(&sefi(&["generate", "--hidden", "latency", "--scenes", "4", "--out", s(&data), "--seed", "3"]));
    // Protocol v6 keeps every object; v7, the default, sets aside the unmeasured ones.
    let first = diagnose_in_process(&data, &out, &small("v6", Screen::FitAll, 3, 12, 6));
    assert!(!first.config.set_aside_unmeasured, "protocol v6 keeps every object");
    assert!(first.eval_imprecise.is_empty() && first.eval_object_keys.len() == first.eval_objects);
    let every_model = |r: &Report| -> Vec<Vec<f64>> {
        let mut sds: Vec<Vec<f64>> = r.candidates.iter().map(|c| c.object_mc_sd.clone()).collect();
        for reference in r.reference.iter().chain(&r.dynamics_reference) {
            sds.push(reference.object_mc_sd.clone());
            sds.extend(reference.reseeded.iter().map(|r| r.object_mc_sd.clone()));
        }
        sds
    };
    let sds = every_model(&first);
    assert!(sds.len() >= 4, "every extension and the references compared");
    let worst: Vec<f64> = (0..first.eval_objects).map(|o| sds.iter().map(|m| m[o]).fold(f64::NAN, f64::max)).collect();
    let mut sorted = worst.clone();
    sorted.sort_by(f64::total_cmp);
    let bar = 0.5 * (sorted[sorted.len() / 2] + sorted[sorted.len() / 2 + 1]);
    assert!(sorted[sorted.len() / 2 + 1] > sorted[sorted.len() / 2], "two objects' sds apart: {sorted:?}");
    let mut config = small("v7", Screen::FitAll, 3, 12, 6);
    (config.refine_factor, config.min_gain) = (4, bar / first.eval_units as f64);
    let second = diagnose_in_process(&data, &out, &config);
    assert!(second.config.set_aside_unmeasured && second.config.refine_factor == 4);
    let flagged: Vec<(i64, i64)> = second.eval_imprecise.iter().map(|o| (o.scene, o.id)).collect();
    let over: Vec<(i64, i64)> =
        first.eval_object_keys.iter().zip(&worst).filter(|(_, &w)| w > bar).map(|(k, _)| *k).collect();
    assert_eq!(flagged, over, "the objects over {bar} nats under some model");
    for o in &second.eval_imprecise {
        assert!(o.refined_mc_sd.is_finite() && o.set_aside == (o.refined_mc_sd > bar), "{o:?} against {bar}");
        assert_eq!(second.eval_object_keys.contains(&(o.scene, o.id)), !o.set_aside, "{o:?}");
    }
    let set_aside: Vec<_> = second.eval_imprecise.iter().filter(|o| o.set_aside).collect();
    assert_eq!(second.eval_object_keys.len() + set_aside.len(), second.eval_objects);
    assert_eq!(second.eval_object_units.iter().sum::<usize>(), second.eval_units);
    assert_eq!(second.eval_units + set_aside.iter().map(|o| o.units).sum::<usize>(), first.eval_units);
    // Per model, the kept objects' sds: the first run's where never flagged,
    // and under the bar everywhere.
    for (before, after) in sds.iter().zip(every_model(&second)) {
        assert_eq!(after.len(), second.eval_object_keys.len());
        for (key, sd) in second.eval_object_keys.iter().zip(&after) {
            assert!(*sd <= bar, "{key:?}: {sd} over {bar}");
            if !flagged.contains(key) {
                let o = first.eval_object_keys.iter().position(|k| k == key).unwrap();
                assert_eq!(*sd, before[o], "{key:?}");
            }
        }
    }
    for c in &second.candidates {
        assert_eq!(c.object_gains.len(), second.eval_object_keys.len(), "{}", c.cause);
    }
    // The report's bar is the one the objects were flagged against, its set-aside units included.
    assert!((second.unmeasured_bar() - bar).abs() <= 1e-9 * bar, "{} against {bar}", second.unmeasured_bar());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The fitted screen at a small scale, resumed from a diagnosis that fits every extension, of
/// the same data (the same fits, every extension evaluated): every extension is
/// fitted; those no check flagged and the screen did not admit are reported as
/// not admitted (check-part p at or over the plausibility level) and are
/// neither candidates nor evaluated; every candidate's per-object gains are
/// the fit-all diagnosis's, to the bit (the same fits and filter seeds, every
/// object kept); a scope's reseeded refit is fitted only where it has a
/// candidate; and the outcome decided again from the report is the one named.
#[test]
fn the_fitted_screen_evaluates_only_what_it_admits() {
    let dir = temp("diagnose", "fitted-screen");
    let (data, out) = (dir.join("data"), dir.join("out"));
    ok(&sefi(&["generate", "--hidden", "latency", "--scenes", "4", "--out", s(&data), "--seed", "1"]));
    // Protocol v6 keeps every object, so that the two diagnoses evaluate the same ones.
    let every = diagnose_in_process(&data, &out, &small("v6", Screen::FitAll, 1, 12, 6));
    let screened = diagnose_in_process(&data, &out, &small("v6", Screen::Fitted, 1, 12, 6));
    let plausible_p = screened.config.plausible_p;
    assert!(screened.config.fitted_screen && screened.not_fitted.is_empty());
    // The data exercise a screen that turns extensions away, in one scope all of them.
    assert!(!screened.not_admitted.is_empty(), "nothing turned away");
    let without_reseeded = |scope| screened.reference_in(scope).is_some_and(|r| r.reseeded.is_none());
    assert!(RefitScope::ALL.into_iter().any(without_reseeded), "no scope left without a candidate");
    let mut fitted: Vec<&str> = screened.candidates.iter().map(|c| c.cause.as_str()).collect();
    fitted.extend(screened.not_admitted.iter().map(|n| n.cause.as_str()));
    fitted.sort_unstable();
    let mut all: Vec<&str> = every.candidates.iter().map(|c| c.cause.as_str()).collect();
    all.sort_unstable();
    assert_eq!(fitted, all, "every extension fitted once");
    for n in &screened.not_admitted {
        assert!(n.check_part_p >= plausible_p && n.check_part_gain.is_finite(), "{n:?}");
        assert!(out.join("candidates").join(&n.cause).join("train.csv").is_file(), "{}'s fit", n.cause);
    }
    for c in &screened.candidates {
        if c.flagged_by.is_empty() {
            assert!(c.admitted(plausible_p), "{}: not admitted, and no admitted candidate nests it", c.cause);
        }
        let full = every.candidates.iter().find(|f| f.cause == c.cause).unwrap();
        assert_eq!(c.object_gains, full.object_gains, "{}: the fit-all diagnosis's gains", c.cause);
    }
    for scope in RefitScope::ALL {
        let in_scope = screened.candidates.iter().any(|c| c.refit_scope == scope);
        let reseeded = screened.reference_in(scope).is_some_and(|r| r.reseeded.is_some());
        assert_eq!(reseeded, in_scope, "the reseeded refit of scope {scope:?}");
    }
    assert_eq!(screened.decided(true).0, screened.cause, "decided again from the report");
    for expected in screened.not_admitted.iter().map(|n| n.cause.as_str()).filter(|&id| id != screened.cause) {
        let why = screened.why_not(expected).unwrap();
        assert!(why.contains(&format!("`{expected}` fitted, not admitted by the fitted screen")), "{why}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The fitted screen's futility stop: a screened
/// extension whose best check-part evaluation by the stop is not above the
/// base's is stopped there (its checkpoint at that step, listed as not
/// admitted with the step, not tested); every other fit is the same run as
/// without the stop, so each candidate's per-object gains are the unstopped
/// diagnosis's to the bit; the reference in the dynamics scope is fitted only
/// where an extension of that scope went on; and a stop never admits what the
/// unstopped screen turned away. Two data sets exercise both sides of the
/// dynamics rule: the mixture's (its heavy-tail extension is flagged, so it
/// goes on) and a sensor lag's (the screened heavy-tail extension is stopped,
/// so no dynamics reference is fitted).
#[test]
fn the_futility_stop_ends_only_fits_that_have_not_risen_above_the_base() {
    let mixture = futility_stop_on("heavy_tailed_accel", "2");
    let lag = futility_stop_on("latency", "3");
    assert!(mixture.dynamics_reference && !mixture.dynamics_stopped, "the mixture's data: {mixture:?}");
    assert!(!lag.dynamics_reference && lag.dynamics_stopped, "the lag's data: {lag:?}");
}

/// What one data set showed of the dynamics scope under the futility stop.
#[derive(Debug)]
struct DynamicsUnderTheStop {
    /// The stopped diagnosis fitted a reference in the dynamics scope.
    dynamics_reference: bool,
    /// An extension of the dynamics was stopped.
    dynamics_stopped: bool,
}

/// Diagnoses generated data (4 scenes of `effect`, seed `seed`) with the
/// fitted screen with and without the futility stop, asserts what
/// `the_futility_stop_ends_only_fits_that_have_not_risen_above_the_base`
/// states, and says what happened in the dynamics scope.
fn futility_stop_on(effect: &str, seed: &str) -> DynamicsUnderTheStop {
    let dir = temp("diagnose", &format!("screen-futility-{effect}-{seed}"));
    let data = dir.join("data");
    ok(&sefi(&["generate", "--hidden", effect, "--scenes", "4", "--out", s(&data), "--seed", seed]));
    // Protocol v6 keeps every object; every fit keeps its best of an evaluation every 2 steps, so that
    // the stop falls within a test's short fits.
    let run = |name: &str, futility: f64| -> (Report, std::path::PathBuf) {
        let out = dir.join(name);
        let mut config = small("v6", Screen::Fitted, seed.parse().unwrap(), 40, 12);
        (config.keep_best_every, config.screen_futility) = (2, futility);
        (diagnose_in_process(&data, &out, &config), out)
    };
    let (whole, _) = run("whole", 0.0);
    let (stopped, out) = run("stopped", 0.3);
    // 30% of 12 steps is 3.6: the first evaluation after it is at step 4.
    let stop_step = 4;
    let base_value = stopped.base_kept.as_ref().unwrap().value;
    assert_eq!(Some(base_value), whole.base_kept.as_ref().map(|k| k.value), "the same base");
    let stops: Vec<&str> =
        stopped.not_admitted.iter().filter(|n| n.stopped_at.is_some()).map(|n| n.cause.as_str()).collect();
    assert!(!stops.is_empty(), "the data exercise a stop");
    let evaluations = |cause: &str| -> Vec<(usize, f64)> {
        let text = std::fs::read_to_string(out.join("candidates").join(cause).join(EVAL_LOG)).unwrap();
        text.lines()
            .skip(1)
            .map(|l| l.split(',').collect::<Vec<_>>())
            .map(|f| (f[0].parse().unwrap(), f[1].parse().unwrap()))
            .collect()
    };
    let best_by_stop = |cause: &str| {
        evaluations(cause).iter().filter(|e| e.0 <= stop_step).map(|e| e.1).fold(f64::NEG_INFINITY, f64::max)
    };
    for n in &stopped.not_admitted {
        match n.stopped_at {
            Some(step) => {
                assert_eq!(step, stop_step, "{}", n.cause);
                assert!(n.check_part_p.is_nan() && n.check_part_gain.is_nan(), "{n:?}: not tested");
                assert!(best_by_stop(&n.cause) <= base_value, "{}: stopped above the base", n.cause);
                assert_eq!(evaluations(&n.cause).last().unwrap().0, stop_step, "{}: fitted past the stop", n.cause);
                let why = stopped.why_not(&n.cause).unwrap();
                assert!(why.contains(&format!("stopped at step {stop_step}")), "{why}");
                // What the stop turned away, the unstopped screen did not admit either here.
                let full = whole.not_admitted.iter().find(|w| w.cause == n.cause);
                assert!(full.is_some(), "{}: admitted without the stop", n.cause);
            }
            None => assert!(best_by_stop(&n.cause) > base_value, "{}: went on from below the base", n.cause),
        }
    }
    for c in &stopped.candidates {
        if c.flagged_by.is_empty() {
            assert!(best_by_stop(&c.cause) > base_value, "{}: went on from below the base", c.cause);
        }
        let full = whole.candidates.iter().find(|f| f.cause == c.cause).expect("a candidate without the stop too");
        assert_eq!(c.object_gains, full.object_gains, "{}: the unstopped diagnosis's gains", c.cause);
        assert_eq!(c.kept, full.kept, "{}: the same fit", c.cause);
    }
    let went_on_in = |scope: RefitScope| {
        stopped.candidates.iter().any(|c| c.refit_scope == scope)
            || stopped.not_admitted.iter().any(|n| n.refit_scope == scope && n.stopped_at.is_none())
    };
    let dynamics_reference = stopped.reference_in(RefitScope::Dynamics).is_some();
    assert_eq!(dynamics_reference, went_on_in(RefitScope::Dynamics), "{effect}: the dynamics reference");
    assert!(whole.reference_in(RefitScope::Dynamics).is_some(), "{effect}: without the stop every extension goes on");
    assert_eq!(stopped.cause, whole.cause, "the same outcome");
    std::fs::remove_dir_all(&dir).unwrap();
    let dynamics_stopped =
        stopped.not_admitted.iter().any(|n| n.refit_scope == RefitScope::Dynamics && n.stopped_at.is_some());
    DynamicsUnderTheStop { dynamics_reference, dynamics_stopped }
}
