//! The error type of dataset reading, validation, writing and importing.

use std::fmt;
use std::io;
use std::path::PathBuf;

/// Where a bad record sits: a line of a file, or a record added through a
/// [`DatasetBuilder`](super::DatasetBuilder).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Place {
    /// A 1-based line number of a text file (the header is line 1).
    Line(usize),
    /// The 0-based index of a record of one kind added in memory (for example
    /// the third object given to the builder is record 2 of `objects.csv`).
    Record(usize),
}

impl fmt::Display for Place {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Place::Line(n) => write!(f, "line {n}"),
            Place::Record(n) => write!(f, "record {n} (built in memory)"),
        }
    }
}

/// What is wrong with one field (or one row) of a file.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum Problem {
    /// The header line differs from the one the format prescribes.
    Header {
        /// The header the format prescribes (comma-separated).
        expected: String,
        /// The header found (comma-separated).
        found: String,
    },
    /// The row has too few or too many fields.
    FieldCount {
        /// Number of fields the format prescribes.
        expected: usize,
        /// Number of fields found.
        found: usize,
    },
    /// A field is not a number (or not an integer where one is required).
    Malformed {
        /// The text of the field.
        text: String,
        /// What was expected ("a number", "an integer").
        expected: &'static str,
    },
    /// A field is NaN or infinite.
    NonFinite {
        /// The text of the field.
        text: String,
    },
    /// A size, or a prior standard deviation, is zero or negative.
    NonPositive {
        /// The value found.
        value: f64,
    },
    /// A value lies outside its admissible range.
    OutOfRange {
        /// The value found.
        value: f64,
        /// A description of the admissible range.
        allowed: String,
    },
    /// A scene id that has no AV rows in `av.csv`.
    UnknownScene {
        /// The scene id.
        scene: i64,
    },
    /// An object id that `objects.csv` does not list for its scene.
    UnknownObject {
        /// The scene id.
        scene: i64,
        /// The object id.
        object: i64,
    },
    /// The same key appears twice.
    Duplicate {
        /// The key, spelled out (for example `scene 3, object 7, t 4`).
        key: String,
        /// Where the first occurrence is.
        first: Place,
    },
    /// A step index outside its admissible range.
    StepOutOfRange {
        /// The step found.
        t: i64,
        /// The smallest admissible step.
        lo: usize,
        /// One past the largest admissible step.
        hi: usize,
    },
    /// A scene has no AV pose for a step.
    MissingStep {
        /// The scene id.
        scene: i64,
        /// The first step without a pose.
        t: usize,
    },
    /// A record of a kind the dataset does not hold (a point given to a
    /// dataset of box detections, or the reverse).
    WrongKind {
        /// The kind the dataset holds.
        dataset: &'static str,
    },
    /// Anything else, described in words.
    Other(String),
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Problem::Header { expected, found } => {
                write!(f, "bad header: expected `{expected}`, found `{found}`")
            }
            Problem::FieldCount { expected, found } => {
                write!(f, "expected {expected} fields, found {found}")
            }
            Problem::Malformed { text, expected } => {
                write!(f, "malformed value `{text}`: expected {expected}")
            }
            Problem::NonFinite { text } => write!(f, "non-finite value `{text}`"),
            Problem::NonPositive { value } => {
                write!(f, "must be positive, found {value}")
            }
            Problem::OutOfRange { value, allowed } => {
                write!(f, "value {value} out of range: must be {allowed}")
            }
            Problem::UnknownScene { scene } => {
                write!(f, "unknown scene {scene} (it has no rows in av.csv)")
            }
            Problem::UnknownObject { scene, object } => {
                write!(f, "unknown object {object} in scene {scene} (not listed in objects.csv)")
            }
            Problem::Duplicate { key, first } => {
                write!(f, "duplicate row for {key} (first at {first})")
            }
            Problem::StepOutOfRange { t, lo, hi } => {
                write!(f, "step {t} out of range {lo}..{hi}")
            }
            Problem::MissingStep { scene, t } => {
                write!(f, "scene {scene} has no AV pose for step {t} (every step needs one; scene first seen here)")
            }
            Problem::WrongKind { dataset } => {
                write!(f, "this dataset holds {dataset}, not this kind of observation")
            }
            Problem::Other(s) => f.write_str(s),
        }
    }
}

/// An error reading, validating, writing or importing a dataset.
///
/// Bad input is always reported through this type (never a panic). Messages
/// name the file, the line (1-based; the header is line 1) and the column.
#[derive(Debug)]
#[non_exhaustive]
pub enum DataError {
    /// An I/O error on a file or directory.
    Io {
        /// The path involved.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// A required file does not exist.
    MissingFile {
        /// The path that was looked for.
        path: PathBuf,
    },
    /// A dataset directory holds both `points.csv` and `boxes.csv`, or neither.
    ObservationFiles {
        /// The dataset directory.
        dir: PathBuf,
        /// True if both files exist, false if neither does.
        both: bool,
    },
    /// `meta.json` is malformed or holds an invalid value.
    Meta {
        /// 1-based line of `meta.json` (or of the value concerned).
        line: usize,
        /// The field concerned (`format`, `dt`, `steps`), or `-` for syntax
        /// errors (whose message then names no field).
        field: String,
        /// What is wrong.
        message: String,
    },
    /// A field or row of a file is invalid.
    Invalid {
        /// The file (its name inside the dataset directory, or a path).
        file: String,
        /// The line (or in-memory record).
        place: Place,
        /// The column name.
        column: String,
        /// What is wrong.
        problem: Problem,
    },
}

impl DataError {
    pub(crate) fn io(path: impl Into<PathBuf>, source: io::Error) -> Self {
        DataError::Io { path: path.into(), source }
    }

    pub(crate) fn invalid(file: impl Into<String>, place: Place, column: impl Into<String>, problem: Problem) -> Self {
        DataError::Invalid { file: file.into(), place, column: column.into(), problem }
    }

    /// The file the error is about, if it is about one file.
    pub fn file(&self) -> Option<String> {
        match self {
            DataError::Io { path, .. } | DataError::MissingFile { path } => Some(path.display().to_string()),
            DataError::ObservationFiles { .. } => None,
            DataError::Meta { .. } => Some(super::META_FILE.to_string()),
            DataError::Invalid { file, .. } => Some(file.clone()),
        }
    }

    /// The 1-based line the error is about, if it has one.
    pub fn line(&self) -> Option<usize> {
        match self {
            DataError::Meta { line, .. } => Some(*line),
            DataError::Invalid { place: Place::Line(n), .. } => Some(*n),
            _ => None,
        }
    }

    /// The column (or `meta.json` field) the error is about, if it has one.
    pub fn column(&self) -> Option<&str> {
        match self {
            DataError::Meta { field, .. } => Some(field),
            DataError::Invalid { column, .. } => Some(column),
            _ => None,
        }
    }
}

impl fmt::Display for DataError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DataError::Io { path, source } => write!(f, "{}: {source}", path.display()),
            DataError::MissingFile { path } => {
                write!(f, "{}: required file not found", path.display())
            }
            DataError::ObservationFiles { dir, both } => {
                if *both {
                    write!(
                        f,
                        "{}: both points.csv and boxes.csv exist; a dataset holds exactly one of them",
                        dir.display()
                    )
                } else {
                    write!(
                        f,
                        "{}: neither points.csv nor boxes.csv exists; a dataset holds exactly one of them",
                        dir.display()
                    )
                }
            }
            DataError::Meta { line, field, message } if field == "-" => write!(f, "meta.json: line {line}: {message}"),
            DataError::Meta { line, field, message } => write!(f, "meta.json: line {line}: field `{field}`: {message}"),
            DataError::Invalid { file, place, column, problem } => {
                write!(f, "{file}: {place}: column `{column}`: {problem}")
            }
        }
    }
}

impl std::error::Error for DataError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            DataError::Io { source, .. } => Some(source),
            _ => None,
        }
    }
}
