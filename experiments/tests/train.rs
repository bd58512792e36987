//! `sefi train`, `sefi reproduce --quick` and `sefi score-check` end to end: the
//! files they promise, refusals that protect earlier work, and resuming.

use std::path::PathBuf;
use std::process::Command;

use crate::common::{ok, rows, s, sefi};

fn temp(name: &str) -> PathBuf {
    crate::common::temp("train", name)
}

#[test]
fn train_writes_logs_and_parameters_refuses_to_overwrite_and_resumes() {
    let dir = temp("run");
    let data = dir.join("data");
    ok(&sefi(&["generate", "--quick", "--exp", "A", "--out", s(&data)]));
    let (train, test, out) = (data.join("train"), data.join("test"), dir.join("pf-sefi"));
    let args = |epochs: &str| {
        vec![
            "train",
            "--data",
            s(&train),
            "--test",
            s(&test),
            "--out",
            s(&out),
            "--epochs",
            epochs,
            "--particles",
            "32",
            "--eval-particles",
            "64",
            "--eval-every",
            "2",
            "--checkpoint-every",
            "2",
        ]
        .into_iter()
        .map(String::from)
        .collect::<Vec<_>>()
    };
    let run = |a: Vec<String>| Command::new(env!("CARGO_BIN_EXE_sefi")).args(&a).output().unwrap();
    ok(&run(args("2")));
    // 2 training scenes x 2 epochs = 4 steps; evaluations at 0, 2, 4.
    assert_eq!(rows(&out.join("train.csv")), 4);
    assert_eq!(rows(&out.join("eval.csv")), 3);
    for f in ["params.bin", "checkpoint.bin", "run.json", "curve.svg"] {
        assert!(out.join(f).is_file(), "{f}");
    }
    let before = std::fs::read(out.join("params.bin")).unwrap();

    // Starting again in the same directory is refused and changes nothing.
    let again = run(args("2"));
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("--resume"));
    assert_eq!(std::fs::read(out.join("params.bin")).unwrap(), before);

    // Resuming with other settings is refused.
    let mut other = args("2");
    other.extend(["--resume".into(), "--lr".into(), "0.5".into()]);
    assert!(!run(other).status.success());

    // Resuming a finished run does no more steps and keeps its result.
    let mut same = args("2");
    same.push("--resume".into());
    ok(&run(same));
    assert_eq!(rows(&out.join("train.csv")), 4);
    assert_eq!(std::fs::read(out.join("params.bin")).unwrap(), before);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn reproduce_quick_writes_the_table_curves_and_every_method() {
    let dir = temp("reproduce");
    let stdout = ok(&sefi(&["reproduce", "--exp", "A", "--quick", "--out", s(&dir)]));
    assert!(stdout.contains("| TRUE |"));
    for f in ["table.md", "table.csv", "curves.svg", "reproduce.json"] {
        assert!(dir.join(f).is_file(), "{f}");
    }
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("reproduce.json")).unwrap()).unwrap();
    let methods: Vec<&str> = doc["methods"].as_array().unwrap().iter().map(|m| m["method"].as_str().unwrap()).collect();
    assert_eq!(methods, ["TRUE", "pf-sefi", "dpf-sgr", "pfnet", "pf", "pf-sefi-tempered"]);
    for m in doc["methods"].as_array().unwrap() {
        for run in m["runs"].as_array().unwrap() {
            assert!(run["mll"].as_f64().unwrap().is_finite(), "{}", m["method"]);
        }
    }
    // Every learned method reports its learned sds, moved from the initial (1.0, 0.1).
    for m in &doc["methods"].as_array().unwrap()[1..] {
        let sds = m["learned_sds"].as_array().unwrap();
        assert_eq!(sds.len(), 2, "{}", m["method"]);
        for sd in sds {
            let (a, p) = (sd[0].as_f64().unwrap(), sd[1].as_f64().unwrap());
            assert!(a > 0.0 && p > 0.0 && (a, p) != (1.0, 0.1), "{}: {sd}", m["method"]);
        }
    }
    let csv = std::fs::read_to_string(dir.join("table.csv")).unwrap();
    assert!(csv.lines().any(|l| l.starts_with("pf-sefi,mll,")));
    // A second call reuses data and finished runs.
    let again = sefi(&["reproduce", "--exp", "A", "--quick", "--out", s(&dir)]);
    ok(&again);
    assert!(String::from_utf8_lossy(&again.stderr).contains("reusing"));
    // A call for one method and seed keeps every finished run in the table.
    ok(&sefi(&["reproduce", "--exp", "A", "--quick", "--methods", "pf", "--seeds", "1", "--out", s(&dir)]));
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("reproduce.json")).unwrap()).unwrap();
    let methods: Vec<&str> = doc["methods"].as_array().unwrap().iter().map(|m| m["method"].as_str().unwrap()).collect();
    assert_eq!(methods, ["TRUE", "pf-sefi", "dpf-sgr", "pfnet", "pf", "pf-sefi-tempered"]);
    assert!(doc["methods"].as_array().unwrap()[1..].iter().all(|m| m["runs"].as_array().unwrap().len() == 2));
    let _ = std::fs::remove_dir_all(&dir);
}

/// A run held by another process (here the test, through the same operating-system
/// lock `sefi` takes) is skipped by `reproduce`, which trains the rest, and refused
/// by `sefi train`; once released, the next `reproduce` trains it.
#[test]
fn reproduce_skips_a_run_another_process_holds() {
    let dir = temp("claimed");
    let held = dir.join("runs").join("pf-seed0");
    std::fs::create_dir_all(&held).unwrap();
    let lock = std::fs::File::create(held.join(".sefi.lock")).unwrap();
    lock.try_lock().expect("a fresh lock file is free");
    let reproduce = ["reproduce", "--exp", "A", "--quick", "--methods", "pf-sefi,pf", "--seeds", "1", "--out", s(&dir)];
    let first = sefi(&reproduce);
    ok(&first);
    assert!(String::from_utf8_lossy(&first.stderr).contains("pf seed 0: skipped"));
    assert!(dir.join("runs/pf-sefi-seed0/final_metrics.json").is_file(), "the free run trained");
    assert!(!held.join("checkpoint.bin").exists(), "the held run untouched");
    let data = dir.join("data");
    let refused =
        sefi(&["train", "--data", s(&data.join("train")), "--test", s(&data.join("test")), "--out", s(&held)]);
    let stderr = crate::common::failed(&refused);
    assert!(stderr.contains("is being trained by"), "{stderr}");
    drop(lock);
    ok(&sefi(&reproduce));
    assert!(held.join("final_metrics.json").is_file(), "trained once released");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn score_check_prints_the_exact_score_and_names_bad_lines() {
    let dir = temp("score");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("ys.txt");
    std::fs::write(&file, "0.5\n# a comment\n-0.25\n1.5\n").unwrap();
    let stdout = ok(&sefi(&["score-check", "--observations", s(&file), "--params", "0.8,0.5,1.2"]));
    let model = ssm::models::linear_gaussian::kalman::Lgssm::stationary(
        ssm::models::linear_gaussian::kalman::LgssmTheta::new(0.8, 0.5, 1.2),
    )
    .unwrap();
    let (ll, _) = model.score(&[0.5, -0.25, 1.5]);
    assert!(stdout.contains(&format!("exact log-likelihood: {ll:.10}")), "{stdout}");

    std::fs::write(&file, "0.5\nabc\n").unwrap();
    let bad = sefi(&["score-check", "--observations", s(&file)]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("ys.txt:2"), "{}", String::from_utf8_lossy(&bad.stderr));

    // A small table: every estimator appears for each T.
    let out = dir.join("table");
    let stdout = ok(&sefi(&[
        "score-check",
        "--observations",
        s(&file),
        "--simulate",
        "21",
        "--table",
        "--steps",
        "10,20",
        "--runs",
        "4",
        "--particles",
        "32",
        "--out",
        s(&out),
    ]));
    for e in ["pf-sefi L=0", "pf-sefi L=10", "pf-sefi L=20", "pf", "dpf-sgr", "dpf-sgr-stopped", "pfnet a=0.8"] {
        assert!(stdout.contains(&format!("| 20 | {e} |")), "{e}: {stdout}");
    }
    assert!(out.join("score_table.csv").is_file());
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--extension`: the catalogue extension is learned with the model and saved
/// with it. On box data with a fifth of headings reversed the flip fraction
/// rises from its start, on data without reversals it falls (two seeds of
/// data each); an extension that means nothing for the data is refused.
#[test]
fn train_learns_a_catalogue_extension_with_the_model() {
    use autodiff::nn::ParamStore;
    use ssm::models::extended::Extension;
    let dir = temp("extension");
    let flip = Extension::HeadingFlip;
    let start = flip.natural(flip.initial().data()).unwrap()[0].1;
    let train_on = |data: &std::path::Path, out: &std::path::Path, extra: &[&str]| {
        let data = s(data);
        sefi(&[&["train", "--data", data, "--test", data, "--out", s(out)][..], extra].concat())
    };
    let learned = |hidden: &str, seed: &str| -> f64 {
        let data = dir.join(format!("{hidden}-{seed}"));
        let out = dir.join(format!("run-{hidden}-{seed}"));
        ok(&sefi(&[
            "generate",
            "--hidden",
            hidden,
            "--boxes",
            "--scenes",
            "4",
            "--objects",
            "4",
            "--steps",
            "10",
            "--seed",
            seed,
            "--out",
            s(&data),
        ]));
        ok(&train_on(
            &data,
            &out,
            &[
                "--extension",
                "heading_flip",
                "--epochs",
                "6",
                "--particles",
                "128",
                "--eval-particles",
                "128",
                "--eval-every",
                "100",
                "--lr",
                "0.05",
                "--seed",
                seed,
            ],
        ));
        let run: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
        assert_eq!(run["extension"], "heading_flip");
        let store = ParamStore::<f64>::load(&out.join("params.bin")).unwrap();
        let id = store.id(&flip.param_name()).expect("the extension's parameter is saved");
        flip.natural(store.get(id).data()).unwrap()[0].1
    };
    for seed in ["1", "2"] {
        let with = learned("heading_flip", seed);
        let without = learned("none", seed);
        assert!(with > start + 0.02, "seed {seed}: reversed headings, fraction {with} from {start}");
        assert!(without < start, "seed {seed}: no reversals, fraction {without} from {start}");
    }
    let data = dir.join("none-1");
    for (ext, says) in [("clutter", "not an extension of a model of Boxes"), ("flips", "heading_flip")] {
        let err = crate::common::failed(&train_on(&data, &dir.join("refused"), &["--extension", ext]));
        assert!(err.contains(says), "{ext}: {err}");
    }
    // Starting from an extended model without its extension is refused.
    let init = dir.join("run-none-1/params.bin");
    let err = crate::common::failed(&train_on(&data, &dir.join("refused"), &["--init", s(&init)]));
    assert!(err.contains("--extension heading_flip"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--drift`: the detector drift is learned with the model and saved under
/// `drift`; `--drift-from-labels` calibrates it on the training labels and holds
/// it there; point data, a calibration without `--drift` and an `--init` that
/// holds a drift without `--drift` are refused with a message.
#[test]
fn train_learns_a_detector_drift_or_holds_one_calibrated_on_labels() {
    use autodiff::nn::ParamStore;
    use ssm::models::drift::{drift_from_labels, DetectorDrift, DRIFT_PARAM};
    let dir = temp("drift");
    let data = dir.join("boxes");
    let generate = ["generate", "--hidden", "none", "--boxes", "--scenes", "4", "--objects", "4", "--steps", "20"];
    ok(&sefi(&[&generate[..], &["--seed", "3", "--out", s(&data)]].concat()));
    let train_on = |data: &std::path::Path, out: &std::path::Path, extra: &[&str]| {
        let data = s(data);
        let base = ["train", "--data", data, "--test", data, "--out", s(out), "--epochs", "2", "--particles", "64"];
        sefi(&[&base[..], &["--eval-particles", "64", "--eval-every", "100"], extra].concat())
    };
    let saved = |out: &std::path::Path| {
        let store = ParamStore::<f64>::load(&out.join("params.bin")).unwrap();
        store.get(store.id(DRIFT_PARAM).expect("the drift is saved")).data().to_vec()
    };
    let learned = dir.join("learned");
    ok(&train_on(&data, &learned, &["--drift", "--lr", "0.05"]));
    let start = DetectorDrift::initial().data().to_vec();
    assert!(saved(&learned).iter().zip(&start).any(|(a, b)| (a - b).abs() > 1e-3), "the drift was learned");

    let held = dir.join("held");
    ok(&train_on(&data, &held, &["--drift", "--drift-from-labels", "--lr", "0.05"]));
    let labelled = ssm::data::Dataset::read(&data).unwrap();
    let want = drift_from_labels(&labelled).unwrap().drift.to_raw();
    assert_eq!(saved(&held), want, "the calibrated drift is held");

    let points = dir.join("points");
    ok(&sefi(&["generate", "--quick", "--exp", "A", "--out", s(&points)]));
    let err = crate::common::failed(&train_on(&points.join("train"), &dir.join("refused"), &["--drift"]));
    assert!(err.contains("drift") && err.contains("Points"), "{err}");
    let err = crate::common::failed(&train_on(&data, &dir.join("refused"), &["--drift-from-labels"]));
    assert!(err.contains("--drift"), "{err}");
    let init = learned.join("params.bin");
    let err = crate::common::failed(&train_on(&data, &dir.join("refused"), &["--init", s(&init)]));
    assert!(err.contains("--drift"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
