//! The `sefi` binary end to end: help, and the quick demo writing its results.

use std::process::Command;

fn sefi() -> Command {
    Command::new(env!("CARGO_BIN_EXE_sefi"))
}

#[test]
fn help_lists_the_subcommands() {
    let out = sefi().arg("--help").output().expect("runs");
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("demo"), "{text}");
}

/// The user's commands come first in `sefi --help`; the research instruments
/// follow under their own heading, and every command name still runs.
#[test]
fn help_lists_the_instruments_after_the_commands() {
    let out = sefi().arg("--help").output().expect("runs");
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    let heading = text.find("Research instruments").unwrap_or_else(|| panic!("no instruments heading: {text}"));
    for command in ["demo", "import-kitti", "generate", "eval", "track", "train", "reproduce", "diagnose", "params"] {
        let at = text.find(&format!("\n  {command} ")).unwrap_or_else(|| panic!("`{command}` not listed: {text}"));
        assert!(at < heading, "`{command}` is listed among the instruments: {text}");
    }
    for instrument in ["power-study", "stability", "score-check", "score-at", "precision"] {
        let at =
            text.find(&format!("\n  {instrument} ")).unwrap_or_else(|| panic!("`{instrument}` not listed: {text}"));
        assert!(at > heading, "`{instrument}` is listed among the user's commands: {text}");
        let sub = sefi().args([instrument, "--help"]).output().expect("runs");
        assert!(sub.status.success(), "`sefi {instrument} --help`: {}", String::from_utf8_lossy(&sub.stderr));
    }
}

#[test]
fn quick_demo_writes_its_results() {
    let dir = std::env::temp_dir().join(format!("sefi-demo-{}", std::process::id()));
    let out = sefi().args(["demo", "--quick", "--out"]).arg(&dir).output().expect("runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("demo_summary.json")).unwrap()).unwrap();
    let engine = &summary["engine"];
    assert!(engine["gradient_check"]["max_rel_error"].as_f64().unwrap() < 1e-6);
    // The fit must have learned something: the NLL falls.
    assert!(engine["final_nll"].as_f64().unwrap() < engine["initial_nll"].as_f64().unwrap());
    // The model stage filtered the generated scene at each particle count, with finite metrics.
    let rows = summary["model"]["metrics_by_particles"].as_array().unwrap();
    assert_eq!(rows.len(), 2);
    for r in rows {
        for key in ["mll", "ade_smoothed", "ade_filtered", "aotll", "aptll"] {
            assert!(r[key].as_f64().is_some_and(f64::is_finite), "{key}: {r}");
        }
    }
    assert!(std::fs::read_to_string(dir.join("demo_birdseye.svg")).unwrap().contains("<svg"));
    assert!(std::fs::read_to_string(dir.join("demo_metrics.csv")).unwrap().lines().count() == 3);
    assert!(std::fs::read_to_string(dir.join("demo_loss.svg")).unwrap().contains("<svg"));
    let csv = std::fs::read_to_string(dir.join("demo_loss.csv")).unwrap();
    assert!(csv.starts_with("step,nll\n") && csv.lines().count() > 100);
    // The learning stage trained PF-SEFI and PF from observations alone, each with a
    // finite test-MLL curve, beside a finite TRUE.
    let learning = &summary["learning"];
    assert!(learning["true_test_mll"].as_f64().is_some_and(f64::is_finite));
    let methods: Vec<&str> =
        learning["methods"].as_array().unwrap().iter().map(|m| m["method"].as_str().unwrap()).collect();
    assert_eq!(methods, ["pf-sefi", "pf"]);
    for m in learning["methods"].as_array().unwrap() {
        let curve = m["test_mll"].as_array().unwrap();
        assert!(curve.len() >= 2 && curve.iter().all(|p| p[1].as_f64().is_some_and(f64::is_finite)), "{m}");
    }
    assert!(std::fs::read_to_string(dir.join("demo_learning.svg")).unwrap().contains("<svg"));
    // The criticism stage diagnosed the hidden-lag data and wrote its report.
    let stdout = String::from_utf8_lossy(&out.stdout);
    let cause = summary["criticism"]["cause"].as_str().unwrap();
    assert!(stdout.contains(&format!("cause: {cause}")), "{stdout}");
    assert!(dir.join("criticism/report.json").is_file() && dir.join("criticism/report.md").is_file());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn unknown_subcommand_fails_with_a_message() {
    let out = sefi().arg("frobnicate").output().expect("runs");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("frobnicate"));
}

#[test]
fn import_kitti_writes_readable_train_and_val_datasets() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/kitti-tracking");
    if !root.exists() {
        eprintln!("skipped: {} not present", root.display());
        return;
    }
    let dir = std::env::temp_dir().join(format!("sefi-kitti-{}", std::process::id()));
    let out = sefi().arg("import-kitti").arg(&root).arg("--out").arg(&dir).output().expect("runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for split in ["train", "val"] {
        let d = ssm::data::Dataset::read(dir.join(split)).unwrap_or_else(|e| panic!("{split}: {e}"));
        assert!(d.objects().len() > 100, "{split}: {} objects", d.objects().len());
        assert!(d.boxes().is_some() && d.states().is_some());
    }
    assert!(std::fs::read_to_string(dir.join("import_report.md")).unwrap().contains("association rate"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn import_kitti_from_a_missing_folder_names_it() {
    let out = sefi().args(["import-kitti", "/nonexistent/kitti", "--out"]).arg(std::env::temp_dir()).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/kitti"));
}
