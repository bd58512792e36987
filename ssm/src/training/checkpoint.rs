//! The files of a run: the resumable [`Checkpoint`] and the CSV logs, appended
//! and flushed row by row and cut back to a checkpoint on resume.

use std::fmt;
use std::fs::{File, OpenOptions};
use std::path::{Path, PathBuf};

use autodiff::nn::{decode_versioned, write_versioned, ParamError, ParamStore};
use autodiff::optim::Adam;
use serde::{Deserialize, Serialize};

use super::{TrainConfig, TrainError, CHECKPOINT_VERSION};

/// The resumable state of a run, as stored in [`CHECKPOINT_FILE`](super::CHECKPOINT_FILE) (format version
/// [`CHECKPOINT_VERSION`] in the file header).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    /// Steps taken.
    pub step: usize,
    /// The parameters after `step` steps.
    pub params: ParamStore<f64>,
    /// The optimiser's state.
    pub adam: Adam,
    /// Steps skipped so far.
    pub skipped_steps: usize,
    /// The run's settings (a resume must use the same).
    pub config: TrainConfig,
    /// The objective's batches per epoch (a resume must see the same).
    pub batches: usize,
    /// The objective's metric names, the columns of [`EVAL_LOG`](super::EVAL_LOG) after `step`.
    pub eval_names: Vec<String>,
    /// The latest evaluation: its step and values.
    pub last_eval: (usize, Vec<f64>),
    /// Wall-clock seconds of the run so far.
    pub seconds: f64,
    /// With [`TrainConfig::keep_best`], the best evaluation so far: its step, its
    /// value and the parameters it evaluated.
    pub best: Option<(usize, f64, ParamStore<f64>)>,
    /// With [`TrainConfig::average_tail`], once the tail has begun: how many
    /// iterates the running mean holds, and the mean.
    pub average: Option<(usize, ParamStore<f64>)>,
}

/// A checkpoint of format version 3, written before
/// [`TrainConfig::average_tail`] and [`Checkpoint::average`] existed; read and
/// carried over as a run without them.
#[derive(Deserialize)]
struct CheckpointV3 {
    step: usize,
    params: ParamStore<f64>,
    adam: Adam,
    skipped_steps: usize,
    config: TrainConfigV3,
    batches: usize,
    eval_names: Vec<String>,
    last_eval: (usize, Vec<f64>),
    seconds: f64,
    best: Option<(usize, f64, ParamStore<f64>)>,
}

/// [`TrainConfig`] as version-3 checkpoints hold it: version 2's fields, then
/// `keep_best` (bincode writes a nested struct's fields in place, so this is
/// the flat layout of the version-3 code).
#[derive(Deserialize)]
struct TrainConfigV3 {
    v2: TrainConfigV2,
    keep_best: Option<String>,
}

impl From<CheckpointV3> for Checkpoint {
    fn from(v3: CheckpointV3) -> Self {
        let TrainConfigV3 { v2: c, keep_best } = v3.config;
        Checkpoint {
            step: v3.step,
            params: v3.params,
            adam: v3.adam,
            skipped_steps: v3.skipped_steps,
            config: TrainConfig {
                lr: c.lr,
                final_lr: c.final_lr,
                clip: c.clip,
                epochs: c.epochs,
                eval_every: c.eval_every,
                checkpoint_every: c.checkpoint_every,
                seed: c.seed,
                shuffle: c.shuffle,
                keep_best,
                average_tail: 0.0,
            },
            batches: v3.batches,
            eval_names: v3.eval_names,
            last_eval: v3.last_eval,
            seconds: v3.seconds,
            best: v3.best,
            average: None,
        }
    }
}

/// A checkpoint of format version 2, written before [`TrainConfig::keep_best`]
/// and [`Checkpoint::best`] existed; read as a version-3 one without them.
#[derive(Deserialize)]
struct CheckpointV2 {
    step: usize,
    params: ParamStore<f64>,
    adam: Adam,
    skipped_steps: usize,
    config: TrainConfigV2,
    batches: usize,
    eval_names: Vec<String>,
    last_eval: (usize, Vec<f64>),
    seconds: f64,
}

/// [`TrainConfig`] as version-2 checkpoints hold it.
#[derive(Deserialize)]
struct TrainConfigV2 {
    lr: f64,
    final_lr: Option<f64>,
    clip: Option<f64>,
    epochs: usize,
    eval_every: usize,
    checkpoint_every: usize,
    seed: u64,
    shuffle: bool,
}

impl From<CheckpointV2> for CheckpointV3 {
    fn from(v2: CheckpointV2) -> Self {
        let config = TrainConfigV3 { v2: v2.config, keep_best: None };
        CheckpointV3 {
            step: v2.step,
            params: v2.params,
            adam: v2.adam,
            skipped_steps: v2.skipped_steps,
            config,
            batches: v2.batches,
            eval_names: v2.eval_names,
            last_eval: v2.last_eval,
            seconds: v2.seconds,
            best: None,
        }
    }
}

impl Checkpoint {
    /// Reads a checkpoint (of this format version, or of version 2 or 3, carried
    /// over); a missing file is [`TrainError::NoCheckpoint`], an unreadable or
    /// damaged one [`TrainError::Checkpoint`].
    pub fn load(path: &Path) -> Result<Checkpoint, TrainError> {
        let bytes = std::fs::read(path).map_err(|source| {
            if source.kind() == std::io::ErrorKind::NotFound {
                TrainError::NoCheckpoint { path: path.to_path_buf() }
            } else {
                let source = ParamError::Io { path: path.display().to_string(), source };
                TrainError::Checkpoint { path: path.to_path_buf(), source }
            }
        })?;
        Checkpoint::decode(&bytes, &path.display().to_string())
            .map_err(|source| TrainError::Checkpoint { path: path.to_path_buf(), source })
    }

    /// Decodes the bytes of a checkpoint file (what [`Checkpoint::load`] does
    /// after reading the file); a damaged one is [`TrainError::Checkpoint`]
    /// with the path `<bytes>`.
    pub fn from_bytes(bytes: &[u8]) -> Result<Checkpoint, TrainError> {
        let name = "<bytes>";
        Checkpoint::decode(bytes, name).map_err(|source| TrainError::Checkpoint { path: name.into(), source })
    }

    /// Decodes a checkpoint of this format version, or of version 2 or 3, and
    /// checks that its parts fit together ([`Checkpoint::check_layout`]).
    fn decode(bytes: &[u8], name: &str) -> Result<Checkpoint, ParamError> {
        let ckpt = Checkpoint::decode_any_version(bytes, name)?;
        ckpt.check_layout()
            .map_err(|reason| ParamError::Corrupt { path: name.to_string(), reason: reason.to_string() })?;
        Ok(ckpt)
    }

    /// Checks what a resumed run relies on: the optimiser's moments fit the
    /// parameters, and the best and averaged parameters have their layout.
    fn check_layout(&self) -> Result<(), String> {
        self.adam.check_layout(&self.params).map_err(|e| format!("optimiser state: {e}"))?;
        for (what, store) in
            [("best", self.best.as_ref().map(|b| &b.2)), ("average", self.average.as_ref().map(|a| &a.1))]
        {
            if let Some(store) = store {
                self.params.check_same_layout(store).map_err(|e| format!("{what} parameters: {e}"))?;
            }
        }
        Ok(())
    }

    /// Decodes a checkpoint of this format version, or of version 2 or 3.
    fn decode_any_version(bytes: &[u8], name: &str) -> Result<Checkpoint, ParamError> {
        match decode_versioned(bytes, CHECKPOINT_VERSION, name) {
            Err(ParamError::Version { found: 2, .. }) => {
                decode_versioned::<CheckpointV2>(bytes, 2, name).map(|v2| Checkpoint::from(CheckpointV3::from(v2)))
            }
            Err(ParamError::Version { found: 3, .. }) => {
                decode_versioned::<CheckpointV3>(bytes, 3, name).map(Checkpoint::from)
            }
            read => read,
        }
    }

    /// Writes the checkpoint atomically (temporary file, then rename).
    pub fn save(&self, path: &Path) -> Result<(), TrainError> {
        write_versioned(path, CHECKPOINT_VERSION, self)
            .map_err(|source| TrainError::Checkpoint { path: path.to_path_buf(), source })
    }
}

/// A CSV log appended and flushed row by row.
pub(super) struct CsvLog {
    path: PathBuf,
    writer: csv::Writer<File>,
}

impl CsvLog {
    /// Creates `path` (which must not exist) holding `header`.
    pub(super) fn create(path: &Path, header: &[String]) -> Result<Self, TrainError> {
        let file = File::create_new(path).map_err(|source| TrainError::Io { path: path.to_path_buf(), source })?;
        let mut log = CsvLog { path: path.to_path_buf(), writer: csv::WriterBuilder::new().from_writer(file) };
        log.row(header)?;
        Ok(log)
    }

    /// Opens `path` for appending.
    pub(super) fn append(path: &Path) -> Result<Self, TrainError> {
        let file = OpenOptions::new()
            .append(true)
            .open(path)
            .map_err(|source| TrainError::Io { path: path.to_path_buf(), source })?;
        Ok(CsvLog { path: path.to_path_buf(), writer: csv::WriterBuilder::new().from_writer(file) })
    }

    pub(super) fn row(&mut self, fields: &[String]) -> Result<(), TrainError> {
        let path = &self.path;
        let err = |e: &dyn fmt::Display| TrainError::Log { path: path.clone(), reason: format!("cannot write: {e}") };
        self.writer.write_record(fields).map_err(|e| err(&e))?;
        self.writer.flush().map_err(|e| err(&e))
    }
}

/// Rewrites the log at `path` keeping its header (which must be `header`) and the
/// complete rows with `step <= last_step`; a missing or empty log is created with
/// the header alone. Then opens it for appending.
pub(super) fn truncate_log(path: &Path, header: &[String], last_step: usize) -> Result<CsvLog, TrainError> {
    let log_err = |reason: String| TrainError::Log { path: path.to_path_buf(), reason };
    let io_err = |source| TrainError::Io { path: path.to_path_buf(), source };
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(io_err(e)),
    };
    let mut reader = csv::ReaderBuilder::new().has_headers(false).flexible(true).from_reader(bytes.as_slice());
    let mut kept = Vec::new();
    let mut records = reader.byte_records();
    if let Some(head) = records.next() {
        let head = head.map_err(|e| log_err(e.to_string()))?;
        if !head.iter().eq(header.iter().map(|h| h.as_bytes())) {
            let found: Vec<String> = head.iter().map(|f| String::from_utf8_lossy(f).into_owned()).collect();
            return Err(log_err(format!("header {found:?} is not the expected {header:?}")));
        }
        for record in records {
            // A row cut short by a crash has too few fields or a damaged step; any
            // row after the checkpoint is dropped anyway.
            let record = record.map_err(|e| log_err(e.to_string()))?;
            let step = record.get(0).and_then(|f| std::str::from_utf8(f).ok()).and_then(|s| s.parse::<usize>().ok());
            if record.len() == header.len() && step.is_some_and(|s| s <= last_step) {
                kept.push(record);
            }
        }
    }
    let tmp = path.with_extension("csv.tmp");
    {
        let file = File::create(&tmp).map_err(|source| TrainError::Io { path: tmp.clone(), source })?;
        let mut w = csv::WriterBuilder::new().from_writer(file);
        let werr = |e: &dyn fmt::Display| TrainError::Log { path: tmp.clone(), reason: format!("cannot write: {e}") };
        w.write_record(header).map_err(|e| werr(&e))?;
        for r in &kept {
            w.write_byte_record(r).map_err(|e| werr(&e))?;
        }
        w.flush().map_err(|e| werr(&e))?;
    }
    std::fs::rename(&tmp, path).map_err(io_err)?;
    CsvLog::append(path)
}

/// Shortest round-trip text of a float (`NaN`, `inf` and `-inf` included).
pub(super) fn num(x: f64) -> String {
    format!("{x}")
}
