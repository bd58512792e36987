//! The report of a diagnosis ([`Report`]) and its parts, as `report.json` holds them.

use serde::{Deserialize, Serialize};

use crate::criticism::checks::CheckResult;
use crate::data::ObservationKind;
use crate::models::extended::RefitScope;
use crate::training::KeptBest;

use super::config::DiagnoseConfig;
use super::judge::not_admitted_clause;
use super::rules::NestedComparison;
use super::screen::LikelihoodScreen;

/// One check before and after the extension, on the check part.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CheckReport {
    /// The statistic.
    pub name: String,
    /// What it measures.
    pub description: String,
    /// The extension it can reveal, if any.
    pub suggests: Option<String>,
    /// Its z-score on the base model (`before.z`).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub z: f64,
    /// Its Holm-adjusted p-value on the base model (`before.p_adjusted`).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub p: f64,
    /// Calibrated on the base model.
    pub before: CheckResult,
    /// Calibrated on the chosen extension (none without a cause).
    pub after: Option<CheckResult>,
    /// Per draw, the statistic on measured and on replicated data (base model;
    /// NaN where a draw had nothing to measure).
    #[serde(deserialize_with = "crate::stats::pairs_nan_from_null")]
    pub draws_before: Vec<(f64, f64)>,
    /// The same on the extended model.
    #[serde(deserialize_with = "crate::stats::pairs_nan_from_null")]
    pub draws_after: Vec<(f64, f64)>,
}

/// An extension the fitted screen fitted and did not admit
/// ([`DiagnoseConfig::fitted_screen`]): no check flagged it, and its fitted
/// model did not raise the check part's likelihood over its scope's reference
/// with a one-sided sign-flip p below [`DiagnoseConfig::plausible_p`]. No rule
/// of step 5 reads anything else of it, so it is neither checked again nor
/// evaluated (unless an admitted candidate nests it: rule (e) compares them,
/// and it stays a candidate outside the Holm family).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NotAdmitted {
    /// The extension's id.
    pub cause: String,
    /// Its fitted model's log-likelihood on the check part over its scope's
    /// reference's (nats per observed unit, the same filter seeds).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub check_part_gain: f64,
    /// That gain's one-sided sign-flip p over the check objects.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub check_part_p: f64,
    /// The refit it was compared with.
    pub refit_scope: RefitScope,
    /// The learned parameters in physical units: `(name, value, unit)`.
    pub params: Vec<(String, f64, String)>,
    /// The learned parameters in a sentence.
    pub description: String,
    /// Training steps skipped (non-finite estimates).
    pub skipped_steps: usize,
    /// Training time (s).
    pub train_seconds: f64,
    /// The evaluation on the check part whose parameters the fit kept.
    #[serde(default)]
    pub kept: Option<KeptBest>,
    /// The step its fit was stopped at by the futility stop
    /// ([`DiagnoseConfig::screen_futility`]): its best evaluation on the check
    /// part by then was not above the base's, so it was not continued and
    /// not tested (`check_part_gain` and `check_part_p` NaN). `None` for a fit
    /// run to its end.
    #[serde(default)]
    pub stopped_at: Option<usize>,
}

impl NotAdmitted {
    /// Why the fitted screen turned it away, in a clause: the futility stop
    /// (the step it was stopped at), or its check-part gain and p.
    pub fn why(&self) -> String {
        match self.stopped_at {
            Some(step) => format!(
                "stopped at step {step} by the fitted screen's futility stop: its check-part evaluation had not \
                 risen above the base's"
            ),
            None => not_admitted_clause(self.check_part_gain, Some(self.check_part_p)),
        }
    }
}

/// One fitted extension.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CandidateReport {
    /// The extension's id.
    pub cause: String,
    /// Log-likelihood gain over the base on the evaluation part (nats per observed unit).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain: f64,
    /// Its normal-approximation standard error (paired over objects; shown for
    /// scale, the decision uses `p_adjusted`).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain_se: f64,
    /// The gain's Monte Carlo error from the filters' own noise: per object, the
    /// sample sd of the [`DiagnoseConfig::eval_runs`] runs' log-likelihoods over
    /// `sqrt(runs)`, under both models, combined over objects, per unit (NaN with
    /// one run, and in reports written before it was recorded). Where it is
    /// comparable to `gain_se`, the comparison is limited by the filter's
    /// precision rather than by the number of objects: more evaluation particles
    /// or runs would sharpen it.
    #[serde(default = "crate::stats::nan", deserialize_with = "crate::stats::nan_from_null")]
    pub gain_mc_sd: f64,
    /// The largest Monte Carlo sd of one object's gain (nats; as `gain_mc_sd`):
    /// an object whose estimate is that imprecise can sway the sum alone.
    #[serde(default = "crate::stats::nan", deserialize_with = "crate::stats::nan_from_null")]
    pub worst_object_mc_sd: f64,
    /// One-sided sign-flip permutation p-value of the gain.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub p: f64,
    /// `p`, Holm-adjusted over the fitted candidates.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub p_adjusted: f64,
    /// Per evaluated object, its log-likelihood gain (nats).
    #[serde(deserialize_with = "crate::stats::vec_nan_from_null")]
    pub object_gains: Vec<f64>,
    /// Per evaluated object, the Monte Carlo sd of its log-likelihood under
    /// this candidate (nats; empty in reports written before it was kept).
    #[serde(default, deserialize_with = "crate::stats::vec_nan_from_null")]
    pub object_mc_sd: Vec<f64>,
    /// Its log-likelihood on the evaluation part (nats per observed unit; NaN
    /// in reports written before it was recorded): which qualifying candidate
    /// is the cause, where candidates of different refit scopes have gains
    /// over different references.
    #[serde(default = "crate::stats::nan", deserialize_with = "crate::stats::nan_from_null")]
    pub mll: f64,
    /// The refit scope it was fitted in and compared within
    /// ([`DiagnoseConfig::scoped_refits`]; `all` in reports written before it).
    #[serde(default)]
    pub refit_scope: RefitScope,
    /// Its gain over the reseeded refit ([`DiagnoseConfig::refit_noise`]; nats
    /// per observed unit, paired over the evaluation objects) and that gain's
    /// one-sided sign-flip p, Holm-adjusted over the candidates: rule (b)'s
    /// second comparison ([`beats_reseeded`](crate::criticism::diagnose::beats_reseeded)). `None` without the refit, and in
    /// reports written before it was made.
    #[serde(default)]
    pub over_reseeded: Option<(f64, f64)>,
    /// Rule (e), for an extension that nests another fitted candidate
    /// ([`Extension::nests`](crate::models::extended::Extension::nests): `persistent_flip` nests `heading_flip`): its gain
    /// over that candidate, paired by object, and the gain's one-sided
    /// sign-flip p. `None` when it nests none that was fitted, and in reports
    /// written before the rule.
    #[serde(default)]
    pub over_nested: Option<NestedComparison>,
    /// The share of the total gain carried by the two objects with the largest gains.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub top_two_share: f64,
    /// The learned parameters in physical units: `(name, value, unit)`.
    pub params: Vec<(String, f64, String)>,
    /// The learned parameters in a sentence.
    pub description: String,
    /// The checks whose p made it plausible (empty when fitted because of
    /// `fit_all` or the likelihood screen).
    pub flagged_by: Vec<String>,
    /// For a candidate no check flagged that the likelihood screen admitted
    /// ([`LikelihoodScreen`]): the fitted model's log-likelihood on the check
    /// part over the reference's (nats per observed unit, the same filter
    /// seeds), rule (d)'s measure for it. `None` otherwise.
    #[serde(default)]
    pub check_part_gain: Option<f64>,
    /// For a candidate no check flagged that the fitted screen fitted
    /// ([`DiagnoseConfig::fitted_screen`]): the one-sided sign-flip p of
    /// [`CandidateReport::check_part_gain`] over the check objects. Below
    /// [`DiagnoseConfig::plausible_p`] it admits the candidate (into step 5's
    /// Holm family, and rule (d)); above it the extension was fitted and not
    /// admitted, and is a candidate only where an admitted one nests it (in
    /// reports written before the [`NotAdmitted`] list, every such extension was). `None`
    /// otherwise.
    #[serde(default)]
    pub check_part_p: Option<f64>,
    /// Rule (d): whether the extension improves a check that flagged it, or
    /// for one the likelihood screen admitted the check part's likelihood
    /// ([`CandidateReport::improves_what_flagged_it`]; only such an extension
    /// can be the cause).
    pub checks_improved: bool,
    /// Every check calibrated on this extended model (the check part; empty in
    /// reports written before it was recorded).
    #[serde(default)]
    pub checks_after: Vec<CheckResult>,
    /// Whether the learned parameters change the model materially
    /// ([`Extension::is_material`](crate::models::extended::Extension::is_material)); only a material extension can be the cause.
    pub material: bool,
    /// Whether it qualifies as a cause (passes every rule of step 5).
    pub qualifies: bool,
    /// Training steps skipped (non-finite estimates).
    pub skipped_steps: usize,
    /// Training time (s).
    pub train_seconds: f64,
    /// The evaluation on the check part whose parameters the fit kept
    /// ([`DiagnoseConfig::keep_best_every`]; `None` when it kept its last).
    #[serde(default)]
    pub kept: Option<KeptBest>,
}

/// The base refitted alone as the candidates are refitted with their extensions:
/// what they are compared with.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReferenceReport {
    /// Every check calibrated on it (the check part): rule (d)'s "before", and
    /// the checks whose failure makes an outcome `unexplained`.
    pub checks: Vec<CheckResult>,
    /// Training time (s).
    pub train_seconds: f64,
    /// Training steps skipped (non-finite estimates).
    pub skipped_steps: usize,
    /// The evaluation on the check part whose parameters the refit kept.
    #[serde(default)]
    pub kept: Option<KeptBest>,
    /// The base refitted alone once more with another training seed
    /// ([`DiagnoseConfig::refit_noise`]); `None` without it.
    #[serde(default)]
    pub reseeded: Option<ReseededReport>,
    /// Per evaluated object, the Monte Carlo sd of its log-likelihood under
    /// this refit (nats; empty in reports written before it was kept).
    #[serde(default, deserialize_with = "crate::stats::vec_nan_from_null")]
    pub object_mc_sd: Vec<f64>,
}

/// An evaluation object that a model did not measure at the evaluation's
/// budget ([`DiagnoseConfig::set_aside_unmeasured`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImpreciseObject {
    /// Its scene id.
    pub scene: i64,
    /// Its object id within the scene.
    pub id: i64,
    /// Its observed units.
    pub units: usize,
    /// The largest Monte Carlo sd of its log-likelihood over the models at
    /// the evaluation's particles (nats).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub mc_sd: f64,
    /// The same after every model filtered it again with
    /// [`DiagnoseConfig::refine_factor`] times the particles (NaN without).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub refined_mc_sd: f64,
    /// Whether it stayed over the bar and was set aside (else the refined
    /// estimates replaced every model's).
    pub set_aside: bool,
}

/// The base refitted alone with another training seed: how far two refits that
/// differ only in their randomness land apart on the evaluation part.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReseededReport {
    /// Its held-out gain over the reference (nats per observed unit, paired
    /// over the evaluation objects like a candidate's); its size is the refits'
    /// noise, the least gain that names a cause.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain: f64,
    /// The gain's standard error over objects.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain_se: f64,
    /// Per evaluated object (in the order of the candidates' `object_gains`),
    /// its log-likelihood gain over the reference (nats): a candidate's gain
    /// over this refit, paired by object, is its `object_gains` minus these
    /// (empty in reports written before they were kept).
    #[serde(default, deserialize_with = "crate::stats::vec_nan_from_null")]
    pub object_gains: Vec<f64>,
    /// Per evaluated object, the Monte Carlo sd of its log-likelihood under
    /// this refit (nats; empty in reports written before it was kept).
    #[serde(default, deserialize_with = "crate::stats::vec_nan_from_null")]
    pub object_mc_sd: Vec<f64>,
    /// Training time (s).
    pub train_seconds: f64,
    /// Training steps skipped (non-finite estimates).
    pub skipped_steps: usize,
    /// The evaluation on the check part whose parameters the refit kept.
    #[serde(default)]
    pub kept: Option<KeptBest>,
}

/// The version of `report.json`'s format that this code writes
/// ([`Report::format_version`]). Reports written before the field existed
/// read back as version 0, with the defaults of the fields they predate.
pub const REPORT_FORMAT_VERSION: u32 = 1;

/// The result of [`diagnose`](fn@crate::criticism::diagnose::diagnose).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// The format of the report as written ([`REPORT_FORMAT_VERSION`]; 0 for
    /// a report written before the field).
    #[serde(default)]
    pub format_version: u32,
    /// The chosen extension's id, [`UNEXPLAINED`](crate::criticism::diagnose::UNEXPLAINED) or [`NO_CAUSE`](crate::criticism::diagnose::NO_CAUSE).
    pub cause: String,
    /// Its gain on the evaluation part (nats per observed unit; 0 without a cause).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain: f64,
    /// The gain's standard error.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain_se: f64,
    /// Its Holm-adjusted permutation p-value (1 without a cause).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain_p: f64,
    /// The chosen extension's learned parameters in a sentence; for
    /// `unexplained`, the failing checks.
    pub finding: String,
    /// Every check, before and after.
    pub checks: Vec<CheckReport>,
    /// Every fitted extension.
    pub candidates: Vec<CandidateReport>,
    /// Extensions that apply to the data but no check made plausible (nor the
    /// likelihood screen, where it ran).
    pub not_fitted: Vec<String>,
    /// The likelihood screen of every extension no check flagged (empty
    /// without [`DiagnoseConfig::likelihood_screen`]).
    #[serde(default)]
    pub likelihood_screen: Vec<LikelihoodScreen>,
    /// The extensions the fitted screen fitted and did not admit
    /// ([`DiagnoseConfig::fitted_screen`]; empty without it, and in reports
    /// written before this list, which kept them among `candidates` with
    /// `p adj.` 1).
    #[serde(default)]
    pub not_admitted: Vec<NotAdmitted>,
    /// The data's kind.
    pub kind: ObservationKind,
    /// Objects that fitted the models.
    pub train_objects: usize,
    /// Objects that checked them.
    pub check_objects: usize,
    /// Objects that measured the gain.
    pub eval_objects: usize,
    /// The evaluation part's objects `(scene id, object id)`, in the order of
    /// every candidate's `object_gains` (empty in reports written before it was
    /// recorded).
    #[serde(default)]
    pub eval_object_keys: Vec<(i64, i64)>,
    /// Each evaluation object's observed units, in the same order.
    #[serde(default)]
    pub eval_object_units: Vec<usize>,
    /// The evaluation objects a model did not measure at the evaluation's
    /// budget ([`DiagnoseConfig::set_aside_unmeasured`]): refined, and set
    /// aside where that did not bring them under the bar. Those set aside are
    /// not among `eval_object_keys`, and neither their units nor their gains count.
    #[serde(default)]
    pub eval_imprecise: Vec<ImpreciseObject>,
    /// Observed units (points, detections) of the evaluation part.
    pub eval_units: usize,
    /// Log-likelihood of the reference on the evaluation part (nats per
    /// observed unit): the refitted base with [`DiagnoseConfig::refit`] when a
    /// candidate was fitted (refitted in every parameter where a candidate of
    /// that scope was fitted, else in the policy), else the base.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub base_mll: f64,
    /// The refitted base, when there is one (see [`DiagnoseConfig::refit`]):
    /// refitted in every parameter, the reference of the candidates of
    /// [`RefitScope::All`].
    #[serde(default)]
    pub reference: Option<ReferenceReport>,
    /// The base refitted in the policy alone, the observation network held,
    /// when a candidate of [`RefitScope::Dynamics`] was fitted
    /// ([`DiagnoseConfig::scoped_refits`]): their reference.
    #[serde(default)]
    pub dynamics_reference: Option<ReferenceReport>,
    /// The same for the chosen model (the base's without a cause).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub chosen_mll: f64,
    /// Training steps of the base skipped (non-finite estimates).
    pub base_skipped_steps: usize,
    /// Training time of the base (s).
    pub base_train_seconds: f64,
    /// The evaluation on the check part whose parameters the base fit kept.
    #[serde(default)]
    pub base_kept: Option<KeptBest>,
    /// Wall time of the whole diagnosis (s; resumed training counts its own time).
    pub seconds: f64,
    /// The settings.
    pub config: DiagnoseConfig,
}

#[cfg(test)]
mod tests {

    use super::*;
    use crate::criticism::diagnose::testing::{check_with_z, qualifying_candidate};

    /// A check none of whose draws had anything to measure (KITTI's
    /// `initial_lag` when no object moves fast enough) is written with `null`s
    /// and read back with NaNs, so that such a report can be read again.
    #[test]
    fn a_check_with_undefined_draws_reads_back() {
        let undefined =
            CheckResult { measured: f64::NAN, replicated: f64::NAN, draws: 0, ..check_with_z("initial_lag", 0.0) };
        let check = CheckReport {
            name: "initial_lag".into(),
            description: String::new(),
            suggests: Some("latency".into()),
            z: f64::NAN,
            p: 1.0,
            before: undefined.clone(),
            after: Some(undefined),
            draws_before: vec![(f64::NAN, 0.5), (f64::NAN, f64::NAN)],
            draws_after: vec![(1.0, f64::NAN)],
        };
        let json = serde_json::to_string(&check).unwrap();
        assert!(json.contains("[null,0.5]"), "{json}");
        let back: CheckReport = serde_json::from_str(&json).unwrap();
        assert!(back.z.is_nan() && back.before.measured.is_nan() && back.after.unwrap().replicated.is_nan());
        let (b, a) = (&back.draws_before, &back.draws_after);
        assert!(b[0].0.is_nan() && b[0].1 == 0.5 && b[1].0.is_nan() && b[1].1.is_nan());
        assert!(a[0].0 == 1.0 && a[0].1.is_nan());
        // One evaluation run leaves each object's Monte Carlo sd undefined.
        let candidate = CandidateReport { object_mc_sd: vec![f64::NAN, 2.0], ..qualifying_candidate() };
        let back: CandidateReport = serde_json::from_str(&serde_json::to_string(&candidate).unwrap()).unwrap();
        assert!(back.object_mc_sd[0].is_nan() && back.object_mc_sd[1] == 2.0);
    }
}
