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

#[test]
fn quick_demo_writes_its_results() {
    let dir = std::env::temp_dir().join(format!("sefi-demo-{}", std::process::id()));
    let out = sefi().args(["demo", "--quick", "--out"]).arg(&dir).output().expect("runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("demo_summary.json")).unwrap()).unwrap();
    assert!(summary["gradient_check"]["max_rel_error"].as_f64().unwrap() < 1e-6);
    // The fit must have learned something: the NLL falls.
    assert!(summary["final_nll"].as_f64().unwrap() < summary["initial_nll"].as_f64().unwrap());
    assert!(std::fs::read_to_string(dir.join("demo_loss.svg")).unwrap().contains("<svg"));
    let csv = std::fs::read_to_string(dir.join("demo_loss.csv")).unwrap();
    assert!(csv.starts_with("step,nll\n") && csv.lines().count() > 100);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn unknown_subcommand_fails_with_a_message() {
    let out = sefi().arg("frobnicate").output().expect("runs");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("frobnicate"));
}
