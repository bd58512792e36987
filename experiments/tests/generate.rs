//! `sefi generate --quick`: writes the train/test datasets, the true parameters and
//! a summary, and the same seed gives byte-identical files.

use std::path::{Path, PathBuf};
use std::process::Command;

use ssm::data::Dataset;
use ssm::simulation::synthetic::TrueModel;

fn generate(dir: &Path, seed: u64) {
    let out = Command::new(env!("CARGO_BIN_EXE_sefi"))
        .args(["generate", "--quick", "--exp", "B", "--seed", &seed.to_string(), "--out"])
        .arg(dir)
        .output()
        .expect("runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

fn temp(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("sefi-generate-{name}-{}", std::process::id()))
}

/// Every file under `dir` (relative paths, sorted).
fn files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for sub in ["", "train", "test"] {
        for entry in std::fs::read_dir(dir.join(sub)).unwrap() {
            let path = entry.unwrap().path();
            if path.is_file() {
                out.push(path.strip_prefix(dir).unwrap().to_path_buf());
            }
        }
    }
    out.sort();
    out
}

/// `generate.json` without its timings.
fn summary(dir: &Path) -> serde_json::Value {
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("generate.json")).unwrap()).unwrap();
    let obj = v.as_object_mut().unwrap();
    assert!(obj.remove("wall_seconds").unwrap().as_f64().unwrap() > 0.0);
    assert!(obj.remove("fit_seconds").unwrap().as_f64().unwrap() >= 0.0);
    v
}

#[test]
fn quick_generation_writes_datasets_and_is_reproducible() {
    let (a, b, c) = (temp("a"), temp("b"), temp("c"));
    generate(&a, 5);
    generate(&b, 5);
    generate(&c, 6);

    let listed = files(&a);
    for f in [
        "generate.json",
        "true_params.bin",
        "train/meta.json",
        "train/av.csv",
        "train/objects.csv",
        "train/points.csv",
        "train/states.csv",
        "train/actions.csv",
        "test/points.csv",
        "test/states.csv",
        "test/actions.csv",
    ] {
        assert!(listed.contains(&PathBuf::from(f)), "{f} missing from {listed:?}");
    }
    assert_eq!(listed, files(&b));
    for f in &listed {
        if f != Path::new("generate.json") {
            assert!(std::fs::read(a.join(f)).unwrap() == std::fs::read(b.join(f)).unwrap(), "{} differs", f.display());
        }
    }
    assert_eq!(summary(&a), summary(&b));
    assert_ne!(std::fs::read(a.join("train/points.csv")).unwrap(), std::fs::read(c.join("train/points.csv")).unwrap());

    let train = Dataset::read(a.join("train")).unwrap();
    let test = Dataset::read(a.join("test")).unwrap();
    assert_eq!((train.scenes().len(), test.scenes().len()), (2, 1));
    assert_eq!(train.steps(), 6);
    assert!(train.states().unwrap().is_complete());
    let truth = TrueModel::load(&a.join("true_params.bin")).unwrap();
    assert_eq!(truth.policy, ssm::models::vehicle::HandCraftedPolicy::truth());
    let s = summary(&a);
    assert_eq!(s["experiment"], "B");
    assert_eq!(s["seed"], 5);
    assert_eq!(s["train"]["points"].as_u64().unwrap() as usize, train.points().unwrap().len());
    assert!(s["truth"]["heldout_aotll"].as_f64().unwrap().is_finite());
    for d in [a, b, c] {
        std::fs::remove_dir_all(d).ok();
    }
}

#[test]
fn unknown_experiment_is_an_error() {
    let dir = temp("bad");
    let out = Command::new(env!("CARGO_BIN_EXE_sefi"))
        .args(["generate", "--quick", "--exp", "C", "--out"])
        .arg(&dir)
        .output()
        .expect("runs");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown experiment"));
    std::fs::remove_dir_all(dir).ok();
}
