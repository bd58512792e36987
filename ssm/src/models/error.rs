//! Why a model could not be built from its data, parameters and settings
//! ([`ModelError`]): the one error of the models floor's constructors.

use std::fmt;

use crate::data::ObservationKind;
use crate::models::extended::Extension;
use crate::models::vehicle::motion::MotionError;
use crate::util::setting::SettingError;

/// Why a model could not be built.
#[derive(Clone, Debug, PartialEq)]
pub enum ModelError {
    /// The dataset holds observations of another kind than the model reads.
    KindMismatch {
        /// What the dataset holds.
        data: ObservationKind,
        /// What the observation model reads.
        model: ObservationKind,
    },
    /// The dataset's time step is not one the motion model can take.
    Motion(MotionError),
    /// The extension does not apply to this kind of data.
    ExtensionNotApplicable {
        /// The extension.
        extension: Extension,
        /// The data's kind.
        kind: ObservationKind,
    },
    /// An extension's stored parameter has the wrong length or is not finite.
    ExtensionValues {
        /// The parameter tensor's name in a store (`ext.<id>`).
        param: String,
        /// How many values it needs.
        expected: usize,
        /// The values found.
        got: Vec<f64>,
    },
    /// A detector drift ([`crate::models::drift`]) on a model it does not fit:
    /// data other than box detections, or with an extension that also moves
    /// the pose the sensor sees (`latency`).
    DriftNotApplicable {
        /// Why.
        reason: String,
    },
    /// The linear-Gaussian model's sequences are empty or of unequal lengths.
    UnequalSequences,
    /// A setting of the model (a defensive proposal's) is out of range.
    Setting(SettingError),
}

impl fmt::Display for ModelError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ModelError::KindMismatch { data, model } => {
                write!(f, "the dataset holds {data:?} observations; the model reads {model:?}")
            }
            ModelError::Motion(e) => e.fmt(f),
            ModelError::ExtensionNotApplicable { extension, kind } => {
                write!(f, "the `{}` extension does not apply to {kind:?} data", extension.id())
            }
            ModelError::ExtensionValues { param, expected, got } => {
                write!(f, "parameter `{param}` needs {expected} finite values, got {got:?}")
            }
            ModelError::DriftNotApplicable { reason } => write!(f, "a detector drift does not apply: {reason}"),
            ModelError::UnequalSequences => f.write_str("LgssmBatch: sequences must be non-empty and of equal length"),
            ModelError::Setting(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for ModelError {}

impl From<MotionError> for ModelError {
    fn from(e: MotionError) -> Self {
        ModelError::Motion(e)
    }
}

impl From<SettingError> for ModelError {
    fn from(e: SettingError) -> Self {
        ModelError::Setting(e)
    }
}

impl From<ModelError> for String {
    fn from(e: ModelError) -> String {
        e.to_string()
    }
}
