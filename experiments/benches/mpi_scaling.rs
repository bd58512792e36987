//! Data-parallel training over MPI: the speed-up of 2 processes over 1 on this
//! machine, and the bytes each process sends per step.
//!
//! Run with `cargo bench -p experiments --features mpi --bench mpi_scaling`
//! (needs `mpiexec`, from Debian's `mpich`). It generates experiment A at its
//! default scale (10 training scenes of 100 objects, T = 25) into a temporary
//! folder, then trains PF-SEFI (N = 1024, L = 8, on the tempered filter, `sefi
//! train`'s default) for one epoch (10 steps) in
//! each layout below, and reads the per-step wall time (estimate and update) from
//! each run's `train.csv`; the median over the steps is reported. Every layout
//! must end with the same parameter file (checked). Layouts:
//!
//! - 1 process without MPI, 1 rayon thread: the baseline;
//! - 1 process without MPI, 2 rayon threads: shared-memory parallelism;
//! - `mpiexec -n 1`, 1 thread; `mpiexec -n 2`, 1 thread each: data parallelism.
//!
//! The machine is shared: run it on an idle machine and compare ratios.

use std::path::Path;
use std::process::Command;

fn sefi() -> Command {
    Command::new(env!("CARGO_BIN_EXE_sefi"))
}

fn check(out: std::process::Output, what: &str) -> String {
    assert!(out.status.success(), "{what} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Median of the `seconds` column of `train.csv`.
fn median_step_seconds(run: &Path) -> f64 {
    let text = std::fs::read_to_string(run.join("train.csv")).expect("train.csv");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col = header.iter().position(|h| *h == "seconds").expect("seconds column");
    let mut v: Vec<f64> = lines.map(|l| l.split(',').nth(col).unwrap().parse().unwrap()).collect();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let dir = std::env::temp_dir().join(format!("sefi-mpi-bench-{}", std::process::id()));
    let data = dir.join("data");
    check(sefi().args(["generate", "--exp", "A", "--out"]).arg(&data).output().unwrap(), "generate");
    let layouts: [(&str, Option<usize>, usize); 4] = [
        ("1 process, 1 thread (no MPI)", None, 1),
        ("1 process, 2 threads (no MPI)", None, 2),
        ("mpiexec -n 1, 1 thread", Some(1), 1),
        ("mpiexec -n 2, 1 thread each", Some(2), 1),
    ];
    println!("PF-SEFI training steps of experiment A (100 objects, T = 25, N = 1024, L = 8), one epoch of 10 steps");
    println!("| layout | median s/step | speed-up over 1 process, 1 thread | bytes sent per step per process |");
    println!("|---|---|---|---|");
    let mut base = None;
    let mut reference: Option<Vec<u8>> = None;
    for (i, (name, processes, threads)) in layouts.iter().enumerate() {
        let out = dir.join(format!("run{i}"));
        let mut c = match processes {
            Some(n) => {
                let mut c = Command::new("mpiexec");
                c.args(["-n", &n.to_string(), env!("CARGO_BIN_EXE_sefi")]);
                c
            }
            None => {
                let mut c = sefi();
                c.env("SEFI_NO_MPI", "1");
                c
            }
        };
        c.env("RAYON_NUM_THREADS", threads.to_string());
        c.arg("train").arg("--data").arg(data.join("train")).arg("--test").arg(data.join("test"));
        c.arg("--out").arg(&out);
        c.args(["--epochs", "1", "--particles", "1024", "--lag", "8", "--eval-particles", "64", "--eval-every", "0"]);
        let stdout = check(c.output().unwrap(), name);
        let bytes = stdout
            .lines()
            .find_map(|l| l.split(" processes; ").nth(1).and_then(|r| r.split(' ').next()).map(String::from))
            .unwrap_or_else(|| "0".into());
        let step = median_step_seconds(&out);
        let base_step = *base.get_or_insert(step);
        println!("| {name} | {step:.3} | {:.2} | {bytes} |", base_step / step);
        let params = std::fs::read(out.join("params.bin")).expect("params.bin");
        match &reference {
            Some(r) => assert_eq!(r, &params, "{name}: parameters differ from the first layout's"),
            None => reference = Some(params),
        }
    }
    println!("every layout ended with the same parameter file");
    let _ = std::fs::remove_dir_all(&dir);
}
