//! `sefi train` as an MPI job (cargo feature `mpi`; needs `mpiexec` on the path,
//! from Debian's `mpich`): the same parameter file, bit for bit, on 1, 2 and 3
//! processes and without MPI; a process that fails ends the job promptly with a
//! clear error, and the run resumed on another number of processes ends where an
//! uninterrupted one does. Built only with the feature (`required-features` in
//! Cargo.toml).

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

mod common;

use common::{ok, rows, s, sefi};

fn temp(name: &str) -> PathBuf {
    common::temp("mpi", name)
}

/// Runs `command`, killing it if it has not ended within `limit` (a job that
/// hangs in a collective must fail the test, not stall it).
fn run_with_limit(mut command: Command, limit: Duration) -> Output {
    let mut child = command.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().expect("starts");
    let started = Instant::now();
    loop {
        if child.try_wait().expect("waits").is_some() {
            return child.wait_with_output().expect("collects");
        }
        if started.elapsed() > limit {
            child.kill().ok();
            let out = child.wait_with_output().expect("collects");
            panic!("still running after {limit:?}; stderr:\n{}", String::from_utf8_lossy(&out.stderr));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// `sefi train` on `processes` MPI processes (`None`: one process without MPI,
/// the rayon path), with `extra` arguments and environment.
fn train(processes: Option<usize>, args: &[String], env: &[(&str, &str)]) -> Output {
    let mut all = vec!["train".to_string()];
    all.extend_from_slice(args);
    job(processes, &all, env)
}

/// The `sefi` command `args` on `processes` MPI processes (`None`: one process
/// without MPI), with the environment `env`.
fn job(processes: Option<usize>, args: &[String], env: &[(&str, &str)]) -> Output {
    let mut command = match processes {
        Some(n) => {
            let mut c = Command::new("mpiexec");
            c.args(["-n", &n.to_string(), env!("CARGO_BIN_EXE_sefi")]);
            // One rayon thread per process: the processes share the machine's cores.
            c.env("RAYON_NUM_THREADS", "1");
            c
        }
        None => {
            let mut c = Command::new(env!("CARGO_BIN_EXE_sefi"));
            c.env("SEFI_NO_MPI", "1");
            c
        }
    };
    command.args(args);
    for (k, v) in env {
        command.env(k, v);
    }
    run_with_limit(command, Duration::from_secs(300))
}

fn train_args(data: &Path, out: &Path, estimator: &str) -> Vec<String> {
    let (train, test) = (data.join("train"), data.join("test"));
    [
        "--data",
        s(&train),
        "--test",
        s(&test),
        "--out",
        s(out),
        "--estimator",
        estimator,
        "--epochs",
        "2",
        "--particles",
        "24",
        "--eval-particles",
        "32",
        "--eval-every",
        "2",
        "--checkpoint-every",
        "1",
        "--chunk-objects",
        "2",
    ]
    .into_iter()
    .map(String::from)
    .collect()
}

/// A fresh folder `name` holding generated quick data in `data/`.
fn generated(name: &str) -> (PathBuf, PathBuf) {
    let dir = temp(name);
    let data = dir.join("data");
    ok(&sefi(&["generate", "--quick", "--exp", "A", "--out", s(&data)]));
    (dir, data)
}

fn params(out: &Path) -> Vec<u8> {
    std::fs::read(out.join("params.bin")).unwrap_or_else(|e| panic!("{}: {e}", out.display()))
}

#[test]
fn any_number_of_processes_learns_the_same_bits_as_one() {
    let (dir, data) = generated("ranks");
    for estimator in ["pf-sefi", "dpf-sgr"] {
        let reference = dir.join(format!("{estimator}-rayon"));
        ok(&train(None, &train_args(&data, &reference, estimator), &[]));
        let expected = params(&reference);
        for n in 1..=3 {
            let out = dir.join(format!("{estimator}-{n}"));
            let stdout = ok(&train(Some(n), &train_args(&data, &out, estimator), &[]));
            assert_eq!(params(&out), expected, "{estimator} on {n} processes differs from one process without MPI");
            // Only the first process writes: one row per step, one per evaluation.
            assert_eq!(rows(&out.join("train.csv")), rows(&reference.join("train.csv")), "{estimator}, {n}");
            assert_eq!(rows(&out.join("eval.csv")), rows(&reference.join("eval.csv")), "{estimator}, {n}");
            if n > 1 {
                let bytes: f64 = stdout
                    .lines()
                    .find_map(|l| l.split(" processes; ").nth(1)?.split(' ').next()?.parse().ok())
                    .unwrap_or_else(|| panic!("no bytes-per-step line in {stdout}"));
                assert!(bytes > 0.0, "{estimator} on {n} processes sent no bytes");
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_failed_process_ends_the_job_and_the_run_resumes_on_other_processes() {
    let (dir, data) = generated("failure");
    let whole = dir.join("whole");
    ok(&train(Some(2), &train_args(&data, &whole, "pf-sefi"), &[]));

    let out = dir.join("interrupted");
    let args = train_args(&data, &out, "pf-sefi");
    let started = Instant::now();
    let failed = train(Some(2), &args, &[("SEFI_FAIL_AT_STEP", "2"), ("SEFI_FAIL_RANK", "1")]);
    assert!(!failed.status.success(), "the job must fail");
    let stderr = String::from_utf8_lossy(&failed.stderr);
    assert!(stderr.contains("injected failure at step 2 on process 1"), "{stderr}");
    assert!(started.elapsed() < Duration::from_secs(120), "the job took {:?} to end", started.elapsed());
    // The checkpoint of step 1 survived; resume on three processes.
    assert!(out.join("checkpoint.bin").is_file());
    let mut resume = args.clone();
    resume.push("--resume".into());
    ok(&train(Some(3), &resume, &[]));
    assert_eq!(params(&out), params(&whole), "the resumed run must end where the uninterrupted one did");
    assert_eq!(rows(&out.join("train.csv")), rows(&whole.join("train.csv")));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_killed_process_ends_the_job() {
    let (dir, data) = generated("killed");
    let out = dir.join("run");
    let started = Instant::now();
    let env = [("SEFI_FAIL_AT_STEP", "2"), ("SEFI_FAIL_RANK", "2"), ("SEFI_FAIL_HOW", "abort")];
    let killed = train(Some(3), &train_args(&data, &out, "pf-sefi"), &env);
    assert!(!killed.status.success(), "the job must fail");
    assert!(started.elapsed() < Duration::from_secs(120), "the job took {:?} to end", started.elapsed());
    let stderr = String::from_utf8_lossy(&killed.stderr);
    assert!(stderr.contains("injected abort at step 2 on process 2"), "{stderr}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn commands_that_do_not_train_refuse_to_run_as_a_job() {
    let dir = temp("refuse");
    let mut c = Command::new("mpiexec");
    c.args(["-n", "2", env!("CARGO_BIN_EXE_sefi"), "generate", "--quick", "--exp", "A", "--out", s(&dir)]);
    let out = run_with_limit(c, Duration::from_secs(120));
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("`diagnose` run as an MPI job"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// `value` without the fields that time the run.
fn untimed(value: &mut serde_json::Value) {
    match value {
        serde_json::Value::Object(map) => {
            map.retain(|k, _| !k.contains("seconds"));
            map.values_mut().for_each(untimed);
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(untimed),
        _ => {}
    }
}

fn json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    untimed(&mut value);
    value
}

/// Every parameter file under `dir`, by path relative to it.
fn parameter_files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut found = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap().map(Result::unwrap) {
            let path = entry.path();
            if path.is_dir() {
                stack.push(path);
            } else if path.file_name().is_some_and(|n| n == "params.bin") {
                found.push((path.strip_prefix(dir).unwrap().to_path_buf(), std::fs::read(&path).unwrap()));
            }
        }
    }
    found.sort();
    found
}

/// On a job of many processes, that the command's training steps went through
/// the job's reductions: identical files alone would also come from every
/// process doing all the work by itself. A lone barrier sends 8 bytes; a
/// training step sends two reductions of one value per parameter.
fn shared_training(stdout: &str, processes: Option<usize>, command: &str) {
    if processes.is_none() {
        return;
    }
    let bytes: u64 = stdout
        .lines()
        .find_map(|l| l.split(" processes; ").nth(1)?.split(' ').next()?.parse().ok())
        .unwrap_or_else(|| panic!("{command}: no traffic line in {stdout}"));
    assert!(bytes > 10_000, "{command}: the first process sent only {bytes} bytes");
}

#[test]
fn reproduce_diagnose_and_experiment_c_as_a_job_write_what_one_process_writes() {
    let (dir, data) = generated("commands");
    let kitti = Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/kitti-tracking"))
        .filter(|p| p.join("label_02").is_dir());
    let one = dir.join("one");
    let two = dir.join("two");
    for (out, processes) in [(&one, None), (&two, Some(2))] {
        let reproduce = ["reproduce", "--exp", "A", "--quick", "--methods", "pf-sefi,dpf-sgr", "--seeds", "1"];
        let mut args: Vec<String> = reproduce.iter().map(|a| a.to_string()).collect();
        args.extend(["--out".to_string(), out.join("reproduce").display().to_string()]);
        shared_training(&ok(&job(processes, &args, &[])), processes, "reproduce");
        let (train_data, report) = (data.join("train"), out.join("diagnose"));
        let diagnose = ["diagnose", "--quick", "--data", s(&train_data), "--out", s(&report)];
        shared_training(&ok(&job(processes, &diagnose.map(String::from), &[])), processes, "diagnose");
        if let Some(kitti) = &kitti {
            let c = out.join("experiment-c");
            let args = ["experiment-c", "--quick", "--kitti", s(kitti), "--methods", "pf-sefi,dpf-sgr", "--out", s(&c)];
            shared_training(&ok(&job(processes, &args.map(String::from), &[])), processes, "experiment-c");
        }
    }
    let mut parts = vec!["reproduce", "diagnose"];
    if kitti.is_some() {
        parts.push("experiment-c");
        assert_eq!(
            json(&two.join("experiment-c/experiment_c.json")),
            json(&one.join("experiment-c/experiment_c.json"))
        );
    } else {
        eprintln!("experiment-c not checked: the KITTI data (../shared/data/kitti-tracking) is not present");
    }
    for part in parts {
        let expected = parameter_files(&one.join(part));
        assert!(expected.len() >= 2, "{part}: {expected:?}");
        assert!(parameter_files(&two.join(part)) == expected, "{part}: the parameters differ");
    }
    assert_eq!(json(&two.join("reproduce/reproduce.json")), json(&one.join("reproduce/reproduce.json")));
    assert_eq!(json(&two.join("diagnose/report.json")), json(&one.join("diagnose/report.json")));
    let _ = std::fs::remove_dir_all(&dir);
}
