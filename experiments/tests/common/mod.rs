//! Helpers shared by the `sefi` command-line tests: run the binary, require
//! success or failure, make a fresh temporary directory.
#![allow(dead_code)] // the MPI tests' binary uses only some of them

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Runs `sefi` with `args` and returns what it printed.
pub fn sefi(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sefi")).args(args).output().expect("runs")
}

/// Requires a successful run (showing its stderr otherwise) and returns its stdout.
pub fn ok(out: &Output) -> String {
    assert!(out.status.success(), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Requires a failed run and returns its stderr.
#[track_caller]
pub fn failed(out: &Output) -> String {
    assert!(!out.status.success());
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A fresh (removed if present) temporary directory named after `prefix` and `name`.
pub fn temp(prefix: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sefi-{prefix}-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// A path as a command-line argument.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Data rows of a CSV file (lines after the header).
pub fn rows(path: &Path) -> usize {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).lines().count() - 1
}
