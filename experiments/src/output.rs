//! Writing results: every file goes to a temporary name in the same directory and
//! is renamed into place, so an interrupted run never leaves a half-written file;
//! a directory one process writes for long (a training run, a diagnosis) is
//! claimed with an exclusive lock, so two processes never write the same one.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

/// The temporary sibling of `path` used while writing it.
pub fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp{}", std::process::id()))
}

/// Writes `bytes` to `path` atomically.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), String> {
    let tmp = temp_path(path);
    std::fs::write(&tmp, bytes).map_err(|e| format!("{}: {e}", tmp.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| format!("{}: {e}", path.display()))
}

/// Writes a CSV with a header row and rows of numbers, atomically.
pub fn write_csv(path: &Path, header: &[&str], rows: &[Vec<f64>]) -> Result<(), String> {
    let mut s = header.join(",");
    s.push('\n');
    for r in rows {
        let line: Vec<String> = r.iter().map(|v| v.to_string()).collect();
        s.push_str(&line.join(","));
        s.push('\n');
    }
    write_atomic(path, s.as_bytes())
}

/// Writes pretty-printed JSON, atomically.
pub fn write_json(path: &Path, value: &serde_json::Value) -> Result<(), String> {
    let text = serde_json::to_string_pretty(value).map_err(|e| e.to_string())?;
    write_atomic(path, text.as_bytes())
}

/// Creates `dir` (and parents) or says why it cannot.
pub fn ensure_dir(dir: &Path) -> Result<(), String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("cannot create {}: {e}", dir.display()))
}

/// The lock file of a claimed directory (holds the claiming process's id).
pub const LOCK_FILE: &str = ".sefi.lock";

/// An exclusive claim on a directory, held until dropped. The operating system
/// releases it when the process ends however it ends, so a killed run leaves no
/// stale claim behind (the file stays; only its lock goes).
#[derive(Debug)]
pub struct DirClaim {
    _file: File,
}

/// The outcome of [`claim_dir`].
#[derive(Debug)]
pub enum Claim {
    /// This process now holds the directory.
    Held(DirClaim),
    /// Another process holds it; the text names that process as it described
    /// itself ("process 1234").
    Busy(String),
}

/// Claims `dir` (creating it) for this process, without waiting.
pub fn claim_dir(dir: &Path) -> Result<Claim, String> {
    ensure_dir(dir)?;
    let path = dir.join(LOCK_FILE);
    let io_error = |e: std::io::Error| format!("{}: {e}", path.display());
    let mut file =
        OpenOptions::new().read(true).write(true).create(true).truncate(false).open(&path).map_err(io_error)?;
    match file.try_lock() {
        Ok(()) => {
            file.set_len(0).map_err(io_error)?;
            write!(file, "process {}", std::process::id()).map_err(io_error)?;
            file.flush().map_err(io_error)?;
            Ok(Claim::Held(DirClaim { _file: file }))
        }
        Err(TryLockError::WouldBlock) => {
            let mut holder = String::new();
            let _ = file.read_to_string(&mut holder);
            let holder = holder.trim();
            Ok(Claim::Busy(if holder.is_empty() { "another process".into() } else { holder.to_string() }))
        }
        Err(TryLockError::Error(e)) => Err(io_error(e)),
    }
}

/// Claims `dir` (creating it), or fails naming the process that holds it
/// while `doing` it ("trained", "diagnosed").
pub fn claim_or_refuse(dir: &Path, doing: &str) -> Result<DirClaim, String> {
    match claim_dir(dir)? {
        Claim::Held(claim) => Ok(claim),
        Claim::Busy(holder) => Err(format!(
            "{} is being {doing} by {holder}: wait for it to finish or choose another --out",
            dir.display()
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A claimed directory is busy for every other claim (here another open of
    /// the lock file in the same process, as a second process would be) and
    /// free again once the claim is dropped; the busy answer names the holder.
    #[test]
    fn a_claimed_directory_is_busy_until_released() {
        let dir = std::env::temp_dir().join(format!("sefi-claim-{}", std::process::id()));
        let Claim::Held(first) = claim_dir(&dir).unwrap() else { panic!("a fresh directory is free") };
        match claim_dir(&dir).unwrap() {
            Claim::Busy(holder) => assert_eq!(holder, format!("process {}", std::process::id())),
            Claim::Held(_) => panic!("a claimed directory was claimed twice"),
        }
        drop(first);
        assert!(matches!(claim_dir(&dir).unwrap(), Claim::Held(_)), "a released directory is free");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
