//! The KITTI text files of one sequence: reading a file with its name for
//! errors, splitting lines into checked fields, and the label and detection
//! records read from them.

use std::fs;
use std::path::Path;

use crate::data::error::{DataError, Place, Problem};

/// Columns of a `label_02` file (space-separated).
pub(super) const LABEL_COLUMNS: [&str; 17] = [
    "frame",
    "track_id",
    "type",
    "truncated",
    "occluded",
    "alpha",
    "x1",
    "y1",
    "x2",
    "y2",
    "h",
    "w",
    "l",
    "x",
    "y",
    "z",
    "rot_y",
];

/// Columns of a PointRCNN detection file (comma-separated).
pub(super) const DET_COLUMNS: [&str; 15] =
    ["frame", "type", "x1", "y1", "x2", "y2", "score", "h", "w", "l", "x", "y", "z", "rot_y", "alpha"];

/// A text file of a sequence, with its name as shown in errors.
pub(super) struct SeqFile {
    pub(super) name: String,
    pub(super) text: String,
}

/// The largest KITTI text file read, in bytes: the largest of the data
/// (a label file of about 1100 frames) is under 2 MB, so a file past this is
/// refused before it is held in memory.
pub(super) const MAX_FILE_BYTES: u64 = 64 << 20;

pub(super) fn read_seq_file(root: &Path, folder: &str, seq: u32) -> Result<SeqFile, DataError> {
    let name = format!("{folder}/{seq:04}.txt");
    let path = root.join(&name);
    let file = fs::File::open(&path).map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            DataError::MissingFile { path: path.clone() }
        } else {
            DataError::io(&path, e)
        }
    })?;
    let mut text = String::new();
    std::io::Read::read_to_string(&mut std::io::Read::take(file, MAX_FILE_BYTES + 1), &mut text)
        .map_err(|e| DataError::io(&path, e))?;
    if text.len() as u64 > MAX_FILE_BYTES {
        let problem = Problem::Other(format!("file over {MAX_FILE_BYTES} bytes (KITTI files are under 2 MB)"));
        return Err(DataError::invalid(&name, Place::Line(1), "-", problem));
    }
    Ok(SeqFile { name, text })
}

impl SeqFile {
    /// Non-blank lines split into fields, with 1-based line numbers; checks the
    /// field count.
    pub(super) fn rows<'a>(
        &'a self,
        columns: &'a [&'a str],
        sep: Option<char>,
    ) -> impl Iterator<Item = Result<Fields<'a>, DataError>> + 'a {
        self.text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()).map(move |(i, l)| {
            // Fields are counted before they are collected, so a line of a
            // million fields is an error without a vector of a million.
            let found = match sep {
                Some(c) => l.split(c).count(),
                None => l.split_whitespace().count(),
            };
            if found != columns.len() {
                let col = columns
                    .get(found)
                    .map(|c| c.to_string())
                    .unwrap_or_else(|| format!("(extra field {})", columns.len() + 1));
                return Err(DataError::invalid(
                    &self.name,
                    Place::Line(i + 1),
                    col,
                    Problem::FieldCount { expected: columns.len(), found },
                ));
            }
            let fields: Vec<&str> = match sep {
                Some(c) => l.split(c).map(str::trim).collect(),
                None => l.split_whitespace().collect(),
            };
            let f = Fields { file: &self.name, line: i + 1, columns, fields };
            Ok(f)
        })
    }
}

/// The fields of one line of a KITTI file.
pub(super) struct Fields<'a> {
    pub(super) file: &'a str,
    pub(super) line: usize,
    pub(super) columns: &'a [&'a str],
    pub(super) fields: Vec<&'a str>,
}

impl Fields<'_> {
    pub(super) fn error(&self, i: usize, problem: Problem) -> DataError {
        DataError::invalid(self.file, Place::Line(self.line), self.columns[i], problem)
    }

    pub(super) fn num(&self, i: usize) -> Result<f64, DataError> {
        let text = self.fields[i];
        let v: f64 =
            text.parse().map_err(|_| self.error(i, Problem::Malformed { text: text.into(), expected: "a number" }))?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(self.error(i, Problem::NonFinite { text: text.into() }))
        }
    }

    pub(super) fn int(&self, i: usize) -> Result<i64, DataError> {
        let text = self.fields[i];
        text.parse().map_err(|_| self.error(i, Problem::Malformed { text: text.into(), expected: "an integer" }))
    }

    /// A frame index in `0..frames`.
    pub(super) fn frame(&self, i: usize, frames: usize) -> Result<usize, DataError> {
        let f = self.int(i)?;
        if f >= 0 && (f as u64) < frames as u64 {
            Ok(f as usize)
        } else {
            Err(self.error(i, Problem::StepOutOfRange { t: f, lo: 0, hi: frames }))
        }
    }

    /// A positive size.
    pub(super) fn size(&self, i: usize) -> Result<f64, DataError> {
        let v = self.num(i)?;
        if v > 0.0 {
            Ok(v)
        } else {
            Err(self.error(i, Problem::NonPositive { value: v }))
        }
    }
}

/// A labelled (non-DontCare) object in one frame.
pub(super) struct Label {
    pub(super) line: usize,
    pub(super) frame: usize,
    pub(super) track: i64,
    pub(super) car: bool,
    pub(super) length: f64,
    pub(super) width: f64,
    pub(super) p: [f64; 3],
    pub(super) rot_y: f64,
}

/// A detection in one frame.
pub(super) struct Det {
    pub(super) frame: usize,
    pub(super) score: f64,
    pub(super) length: f64,
    pub(super) width: f64,
    pub(super) p: [f64; 3],
    pub(super) rot_y: f64,
}

pub(super) fn read_labels(file: &SeqFile, frames: usize) -> Result<Vec<Label>, DataError> {
    let mut out = Vec::new();
    for row in file.rows(&LABEL_COLUMNS, None) {
        let row = row?;
        let frame = row.frame(0, frames)?;
        let track = row.int(1)?;
        // Every numeric field is checked, even where unused; DontCare rows
        // carry placeholder sizes (-1000) and are then skipped.
        for i in 3..LABEL_COLUMNS.len() {
            if i == 3 || i == 4 {
                row.int(i)?;
            } else {
                row.num(i)?;
            }
        }
        let kind = row.fields[2];
        if kind == "DontCare" {
            continue;
        }
        out.push(Label {
            line: row.line,
            frame,
            track,
            car: kind == "Car",
            width: row.size(11)?,
            length: row.size(12)?,
            p: [row.num(13)?, row.num(14)?, row.num(15)?],
            rot_y: row.num(16)?,
        });
    }
    Ok(out)
}

pub(super) fn read_detections(file: &SeqFile, frames: usize, min_score: f64) -> Result<Vec<Det>, DataError> {
    let mut out = Vec::new();
    for row in file.rows(&DET_COLUMNS, Some(',')) {
        let row = row?;
        let frame = row.frame(0, frames)?;
        row.int(1)?;
        for i in 2..DET_COLUMNS.len() {
            row.num(i)?;
        }
        let score = row.num(6)?;
        let det = Det {
            frame,
            score,
            width: row.size(8)?,
            length: row.size(9)?,
            p: [row.num(10)?, row.num(11)?, row.num(12)?],
            rot_y: row.num(13)?,
        };
        if score >= min_score {
            out.push(det);
        }
    }
    Ok(out)
}
