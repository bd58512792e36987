//! Shared helpers of the diagnosis's unit tests.

use super::*;
use crate::criticism::checks::CheckResult;
use crate::models::extended::RefitScope;

/// A deterministic spread of per-object gains: `i`'s value in [-1, 1]
/// (steps of 0.2), every value about as often.
pub(super) fn wobble(i: usize) -> f64 {
    ((i * 37 % 11) as f64 - 5.0) * 0.2
}

/// A candidate that passes every rule on its own numbers.
pub(super) fn qualifying_candidate() -> CandidateReport {
    CandidateReport {
        cause: "latency".into(),
        gain: 0.2,
        gain_se: 0.01,
        gain_mc_sd: 0.001,
        worst_object_mc_sd: 0.01,
        p: 0.001,
        p_adjusted: 0.001,
        object_gains: vec![],
        object_mc_sd: vec![],
        mll: -1.0,
        refit_scope: RefitScope::All,
        over_reseeded: None,
        over_nested: None,
        top_two_share: 0.1,
        params: vec![],
        description: String::new(),
        flagged_by: vec![],
        check_part_gain: None,
        check_part_p: None,
        checks_improved: true,
        checks_after: vec![],
        material: true,
        qualifies: true,
        skipped_steps: 0,
        train_seconds: 0.0,
        kept: None,
    }
}

pub(super) fn check_with_z(name: &str, z: f64) -> CheckResult {
    CheckResult {
        name: name.into(),
        suggests: Some("heavy_tailed_accel".into()),
        measured: z,
        replicated: 0.0,
        replicated_sd: 1.0,
        z,
        p: 1.0,
        screen_p: Some(1.0),
        p_adjusted: 1.0,
        significant: false,
        draws: 40,
    }
}
