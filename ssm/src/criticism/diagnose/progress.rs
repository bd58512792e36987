//! What a diagnosis reports of its progress ([`Stage`]).

/// What [`diagnose`](fn@crate::criticism::diagnose::diagnose) is doing, for a progress display.
#[derive(Clone, Debug, PartialEq)]
pub enum Stage {
    /// A training run (`base`, `reference` or an extension id) is at `step` of `total`.
    Training {
        /// `base`, `reference` or the extension's id.
        model: String,
        /// Steps done.
        step: usize,
        /// Steps of the run.
        total: usize,
    },
    /// Checking a model on the check part.
    Checking {
        /// `base`, `reference` or the extension's id.
        model: String,
    },
    /// Filtering the evaluation part with a model.
    Evaluating {
        /// `base`, `reference` or the extension's id.
        model: String,
    },
}
