//! The decision rules of step 5, (a)–(e), and the choice of the cause among the candidates
//! that pass them (step 6 without one: `unexplained` or `none`).

use super::heldout::sign_flip_p;
use super::heldout::{differences, gain_of};
use super::{NO_CAUSE, UNEXPLAINED};

use serde::{Deserialize, Serialize};

use crate::criticism::checks::{format_z, holm_within, CheckResult};
use crate::filter::stream_seed;
use crate::models::extended::Extension;

use super::config::DiagnoseConfig;
use super::report::CandidateReport;
use super::screen::admitted;

/// A candidate against the catalogue entry it nests, both fitted: rule (e).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NestedComparison {
    /// The nested extension's id.
    pub nested: String,
    /// The candidate's held-out gain over it (nats per observed unit, paired
    /// over the evaluation objects).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain: f64,
    /// That gain's one-sided sign-flip p (one comparison per nesting
    /// candidate, and a further condition on a cause: no adjustment).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub p: f64,
}

impl NestedComparison {
    /// Whether the larger extension earns its extra parameters: a gain over
    /// the nested one of at least `min_gain` with p below `cause_level`.
    pub fn beats_nested(&self, min_gain: f64, cause_level: f64) -> bool {
        clears_bar(self.gain, self.p, min_gain, cause_level)
    }
}

/// Rule (e)'s comparisons: per candidate `ids[i]` that nests another fitted
/// candidate, its per-object gains minus that one's (both over the
/// reference), summed per observed unit, with the one-sided sign-flip p.
pub fn nested_comparisons(
    ids: &[Extension],
    object_gains: &[&[f64]],
    units: usize,
    config: &DiagnoseConfig,
) -> Vec<Option<NestedComparison>> {
    ids.iter()
        .enumerate()
        .map(|(i, ext)| {
            let j = ids.iter().position(|other| Some(*other) == ext.nests())?;
            let d = differences(object_gains[i], object_gains[j]);
            let p = sign_flip_p(&d, config.permutations, stream_seed(config.seed ^ NESTED_PERMUTATIONS, i as u64));
            Some(NestedComparison { nested: ids[j].id().to_string(), gain: gain_of(&d, units).0, p })
        })
        .collect()
}

impl CandidateReport {
    /// What a qualifying candidate is ranked by to be the cause: its
    /// evaluation log-likelihood, or in reports written before it was recorded
    /// (where every candidate had one reference) its gain over the reference.
    pub(super) fn rank(&self) -> f64 {
        if self.mll.is_finite() {
            self.mll
        } else {
            self.gain
        }
    }

    /// Rule (d) against the reference's checks: a candidate that checks
    /// flagged improves one of them ([`improves_flagged_checks`]); one the
    /// likelihood screen admitted instead raises the check part's likelihood
    /// over the reference's ([`CandidateReport::check_part_gain`] positive):
    /// what made it plausible, judged again after the fit on the same
    /// objects. A report without the candidates' checks keeps its recorded
    /// verdict.
    pub fn improves_what_flagged_it(&self, reference: &[CheckResult], plausible_p: f64) -> bool {
        match self.screened_gain() {
            Some(gain) => gain > 0.0 && admitted(self.check_part_p, plausible_p),
            None if self.checks_after.is_empty() => self.checks_improved,
            None => improves_flagged_checks(&self.flagged_by, reference, &self.checks_after, plausible_p),
        }
    }

    /// The check-part gain of a candidate the likelihood screen admitted and
    /// no check flagged: the one whose rule (d) it decides. `None` for every
    /// other candidate.
    pub(super) fn screened_gain(&self) -> Option<f64> {
        self.check_part_gain.filter(|_| self.flagged_by.is_empty())
    }

    /// How what flagged this candidate moved, as rule (d) judges it: the
    /// check-part gain of a candidate the likelihood screen admitted, else
    /// [`flagged_check_moves`].
    pub fn flagging_moves(&self, reference: &[CheckResult]) -> String {
        match (self.screened_gain(), self.check_part_p) {
            (Some(gain), Some(p)) => {
                format!("fitted screen: check-part gain over the reference {gain:+.4}, one-sided p {p:.3}")
            }
            (Some(gain), None) => {
                format!("admitted by the likelihood screen; check-part gain over the reference {gain:+.4}")
            }
            (None, _) => flagged_check_moves(&self.flagged_by, reference, &self.checks_after),
        }
    }

    /// Whether the candidate is tested in step 5's Holm family: every
    /// candidate but one the fitted screen fitted and did not admit
    /// ([`CandidateReport::check_part_p`]).
    pub fn admitted(&self, plausible_p: f64) -> bool {
        admitted(self.check_part_p, plausible_p)
    }

    /// Whether the candidate passes the decision's rules on its learned
    /// parameters and its gain — every rule of step 5 but (d), that it lowers a
    /// flagging check's |z| ([`CandidateReport::failed_gain_rule`] finds none
    /// that it fails). `qualifies` is this, on its own comparison, and
    /// `checks_improved`.
    pub fn passes_gain_rules(
        &self,
        gain_bar: f64,
        over_reseeded: Option<(f64, f64)>,
        min_gain: f64,
        cause_level: f64,
    ) -> bool {
        self.failed_gain_rule(gain_bar, over_reseeded, min_gain, cause_level).is_none()
    }

    /// The first rule of step 5 but (d) that the candidate fails, in the order
    /// the rules are listed: (a) a Holm-adjusted p below `cause_level`, (b) a
    /// finite gain of at least `gain_bar` ([`Report::gain_bar`](crate::criticism::diagnose::Report::gain_bar)) and
    /// `beats_refit` on `over_reseeded` (its comparison with the reseeded
    /// refit: its own, or one made since for a report written without it), (c)
    /// material, (e) beating the candidate it nests (`over_nested`). `None`
    /// when it passes them all.
    pub fn failed_gain_rule(
        &self,
        gain_bar: f64,
        over_reseeded: Option<(f64, f64)>,
        min_gain: f64,
        cause_level: f64,
    ) -> Option<FailedRule> {
        // A NaN p fails the level too.
        if self.p_adjusted.partial_cmp(&cause_level) != Some(std::cmp::Ordering::Less) {
            Some(FailedRule::Level)
        } else if !(self.gain.is_finite() && self.gain >= gain_bar) {
            Some(FailedRule::LeastGain)
        } else if !beats_refit(over_reseeded, min_gain, cause_level) {
            Some(FailedRule::Reseeded)
        } else if !self.material {
            Some(FailedRule::NotMaterial)
        } else if !self.over_nested.as_ref().is_none_or(|n| n.beats_nested(min_gain, cause_level)) {
            Some(FailedRule::Nested)
        } else {
            None
        }
    }
}

/// A rule of step 5 that a candidate fails: why it is not the cause.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FailedRule {
    /// (a) Its Holm-adjusted p is not below the cause level.
    Level,
    /// (b) Its gain is under the least gain that names a cause.
    LeastGain,
    /// (b) It does not beat the reseeded refit by that least gain at the level.
    Reseeded,
    /// (c) Its learned parameters do not change the model materially.
    NotMaterial,
    /// (d) It lowers no flagging check's |z| below the reference's.
    Checks,
    /// (e) It does not beat the fitted extension it nests.
    Nested,
}

impl std::fmt::Display for FailedRule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            FailedRule::Level => "(a) p adj. not below the level",
            FailedRule::LeastGain => "(b) under the least gain",
            FailedRule::Reseeded => "(b) not over the reseeded refit",
            FailedRule::NotMaterial => "(c) not material",
            FailedRule::Checks => "(d) no flagging check improved",
            FailedRule::Nested => "(e) not over the nested extension",
        })
    }
}

/// Rule (b) against the reseeded refit: the gain over it (`(gain, Holm p)`
/// from [`beats_reseeded`]) is at least `min_gain` with p below `cause_level`;
/// true without the comparison.
pub(super) fn beats_refit(over_reseeded: Option<(f64, f64)>, min_gain: f64, cause_level: f64) -> bool {
    over_reseeded.is_none_or(|(gain, p)| clears_bar(gain, p, min_gain, cause_level))
}

/// The bar of every paired comparison of the decision (rules (b) and (e)): a
/// gain of at least `min_gain` nats per unit with p below `cause_level`.
pub(super) fn clears_bar(gain: f64, p: f64, min_gain: f64, cause_level: f64) -> bool {
    gain >= min_gain && p < cause_level
}

/// Each candidate's one-sided sign-flip p of its per-object differences `d`,
/// its permutations seeded by the diagnosis seed, `stream` and its index.
pub(super) fn sign_flip_ps(d: &[Vec<f64>], config: &DiagnoseConfig, stream: u64) -> Vec<f64> {
    d.iter()
        .enumerate()
        .map(|(i, d)| sign_flip_p(d, config.permutations, stream_seed(config.seed ^ stream, i as u64)))
        .collect()
}

/// Rule (b)'s comparison with the reseeded refit: per candidate (its
/// `object_gains` over the reference of its refit scope; `reseeded[i]`, that
/// scope's reseeded refit's gains over the same reference), its gain over the
/// refit — per object, its gain minus the refit's, summed per observed unit —
/// and that sum's one-sided sign-flip p, Holm-adjusted over the candidates. A cause must beat
/// both refits of the base: the reference and this one (an intersection–union
/// test, so no further multiplicity control). Paired by object, it is robust to
/// what undid the earlier bar (the size of the refit's mean gain), one refit
/// that lost a few objects, and it turns away a candidate that gains no more
/// than another refit of the base does.
pub fn beats_reseeded(
    object_gains: &[&[f64]],
    reseeded: &[&[f64]],
    units: usize,
    family: &[bool],
    config: &DiagnoseConfig,
) -> Vec<(f64, f64)> {
    assert_eq!(object_gains.len(), reseeded.len(), "one reseeded refit per candidate");
    let over: Vec<Vec<f64>> = object_gains.iter().zip(reseeded).map(|(g, r)| differences(g, r)).collect();
    let adjusted = holm_within(&sign_flip_ps(&over, config, RESEEDED_PERMUTATIONS), family);
    over.iter().zip(adjusted).map(|(d, p)| (gain_of(d, units).0, p)).collect()
}

/// Seeds the sign-flip permutations of the candidates against the reference
/// ([`sign_flip_ps`], with the diagnosis seed and the candidate's index).
pub(super) const REFERENCE_PERMUTATIONS: u64 = 0x5f1b;
/// Seeds those of [`beats_reseeded`].
pub(super) const RESEEDED_PERMUTATIONS: u64 = 0x5f1c;
/// Seeds those of [`nested_comparisons`].
pub(super) const NESTED_PERMUTATIONS: u64 = 0x5f1d;
/// Seeds those of the likelihood screen ([`LikelihoodScreen`]).
pub(super) const SCREEN_PERMUTATIONS: u64 = 0x5f1e;
/// Seeds those of the fitted screen ([`DiagnoseConfig::fitted_screen`]).
pub(super) const FITTED_SCREEN_PERMUTATIONS: u64 = 0x5f1f;

/// Step 5's tests against the references: per candidate (its per-object
/// gains, its fitted-screen p or `None`), the one-sided sign-flip p, that p
/// Holm-adjusted over the tests made (1 for a candidate the fitted screen did
/// not admit), and which tests were made.
pub(super) fn reference_tests(
    object_gains: &[Vec<f64>],
    check_part_ps: &[Option<f64>],
    config: &DiagnoseConfig,
) -> (Vec<f64>, Vec<f64>, Vec<bool>) {
    let p_values = sign_flip_ps(object_gains, config, REFERENCE_PERMUTATIONS);
    let family: Vec<bool> = check_part_ps.iter().map(|&p| admitted(p, config.plausible_p)).collect();
    let adjusted = holm_within(&p_values, &family);
    (p_values, adjusted, family)
}

/// Rule (d) of the decision: the extension improves at least one check that
/// flagged it (`flagged_by`), both calibrated on the check part. A check
/// improves when its |z| falls below the reference's, or when the extension
/// carries it past the measured value without failing it: the reference still
/// showed the discrepancy the extension addresses (screen p below
/// `plausible_p`), the extended model's z has the other sign, and the extended
/// model does not fail that check at the family-wise level. An extension that
/// moves its flagging check further the same way, or that turns a check the
/// reference no longer flagged, or whose overshoot is itself a failure, does
/// not improve it. One check is enough: two checks can flag the same extension
/// (kurtosis and Geary's ratio for heavy tails), and a mixture that explains
/// the kurtosis can leave the Geary ratio's z larger as its replicates' spread
/// narrows (measured: |z| 1.16 -> 0.82 and 0.91 -> 2.42 on one diagnosis).
/// (Earlier forms of this rule asked the mean |z| over the flagging checks to
/// fall, and did not count an overshoot; a stored report is decided again by
/// this one.)
pub fn improves_flagged_checks(
    flagged_by: &[String],
    reference: &[CheckResult],
    extended: &[CheckResult],
    plausible_p: f64,
) -> bool {
    flagged_by.iter().any(|name| match (check_named(reference, name), check_named(extended, name)) {
        (Some(r), Some(e)) => e.z.abs() < r.z.abs() || carries_past_without_failing(r, e, plausible_p),
        _ => false,
    })
}

/// How each check that flagged a candidate (`flagged_by`) moved from the
/// reference to the extended model, as rule (d) judges it: `name z 1.27 → -1.46`
/// per check (`-` where a model lacks it), `, failed` where the extended model
/// fails it at the family-wise level; joined by `; `. A candidate no check
/// flagged (fitted by `fit_all`) says so: it has no check for rule (d) to judge.
pub fn flagged_check_moves(flagged_by: &[String], reference: &[CheckResult], extended: &[CheckResult]) -> String {
    if flagged_by.is_empty() {
        return NO_FLAGGING_CHECK.to_string();
    }
    let z = |c: Option<&CheckResult>| c.map_or("-".to_string(), |c| format_z(c.z, 2));
    let each = flagged_by.iter().map(|name| {
        let after = check_named(extended, name);
        let failed = if after.is_some_and(|c| c.significant) { ", failed" } else { "" };
        format!("{name} z {} → {}{failed}", z(check_named(reference, name)), z(after))
    });
    each.collect::<Vec<_>>().join("; ")
}

/// What [`flagged_check_moves`] says of a candidate no check flagged.
pub const NO_FLAGGING_CHECK: &str = "no check flagged it (fitted by the protocol's screen)";

/// The check called `name` among `results`.
pub(super) fn check_named<'a>(results: &'a [CheckResult], name: &str) -> Option<&'a CheckResult> {
    results.iter().find(|c| c.name == name)
}

/// Rule (d)'s overshoot: the reference still flags the check (screen p below
/// `plausible_p`), the extended model's discrepancy has the other sign and the
/// extended model does not fail the check at the family-wise level.
pub(super) fn carries_past_without_failing(reference: &CheckResult, extended: &CheckResult, plausible_p: f64) -> bool {
    let still_flagged = reference.screen_p.is_some_and(|p| p < plausible_p);
    let other_sign = reference.z * extended.z < 0.0;
    still_flagged && other_sign && !extended.significant
}

/// Step 5's choice: among `candidates`, the index of the one with the largest
/// evaluation log-likelihood (in reports without it, gain) for which
/// `qualifies` holds.
pub(super) fn choose(
    candidates: &[CandidateReport],
    qualifies: impl Fn(usize, &CandidateReport) -> bool,
) -> Option<usize> {
    candidates
        .iter()
        .enumerate()
        .filter(|&(i, c)| qualifies(i, c))
        .max_by(|a, b| a.1.rank().total_cmp(&b.1.rank()))
        .map(|(i, _)| i)
}

/// Step 6 without a cause: `unexplained` (with the failing checks) when a check
/// of the reference fails at the family-wise level, else `none`.
pub(super) fn outcome_without_cause(reference_checks: &[CheckResult]) -> (String, String) {
    let failing: Vec<String> = reference_checks
        .iter()
        .filter(|c| c.significant)
        .map(|c| format!("{} (z {})", c.name, format_z(c.z, 1)))
        .collect();
    if failing.is_empty() {
        (NO_CAUSE.to_string(), String::new())
    } else {
        (UNEXPLAINED.to_string(), format!("checks fail that no catalogue extension explains: {}", failing.join(", ")))
    }
}

#[cfg(test)]
mod tests {
    use crate::criticism::diagnose::MIN_GAIN;

    use super::*;
    use crate::criticism::diagnose::testing::{check_with_z, qualifying_candidate, wobble};

    /// Rule (b) against the reseeded refit: a candidate that gains what another
    /// refit of the base gains (the same objects up and down) does not beat it,
    /// one that gains more on every object does, and one refit that lost a few
    /// objects badly makes no candidate look like noise; the p-values are
    /// Holm-adjusted over the candidates, and a candidate without the
    /// comparison is judged by the other rules alone.
    #[test]
    fn a_cause_must_beat_the_reseeded_refit_by_object() {
        let config = DiagnoseConfig { seed: 5, ..DiagnoseConfig::quick() };
        let n = 30;
        let reseeded: Vec<f64> = (0..n).map(|i| 0.8 + wobble(i)).collect();
        let like_the_refit: Vec<f64> = (0..n).map(|i| 0.8 + wobble(i) + 0.05 * wobble(i * 7 + 3)).collect();
        let beyond_it: Vec<f64> = (0..n).map(|i| 1.6 + wobble(i) + 0.05 * wobble(i * 7 + 3)).collect();
        let units = 3 * n;
        let over = beats_reseeded(&[&like_the_refit, &beyond_it], &[&reseeded, &reseeded], units, &[true; 2], &config);
        assert!(over[0].1 > 0.05 && over[1].1 < 1e-3, "{over:?}");
        assert!((over[1].0 - 0.8 * n as f64 / units as f64).abs() < 0.02, "{over:?}");
        let alone = beats_reseeded(&[&beyond_it], &[&reseeded], units, &[true], &config);
        assert!(alone[0].1 <= over[1].1, "Holm over two candidates: {} against {}", alone[0].1, over[1].1);
        // Candidates of two refit scopes: each against its own scope's reseeded
        // refit. The second candidate's scope refits as noisily as it gains.
        let noisy_scope: Vec<f64> = beyond_it.iter().map(|g| g - 0.001 * wobble(3)).collect();
        let scoped = beats_reseeded(&[&beyond_it, &beyond_it], &[&reseeded, &noisy_scope], units, &[true; 2], &config);
        assert!(scoped[0].1 < 1e-3 && scoped[1].1 > 0.05, "{scoped:?}");
        assert!(scoped[1].0.abs() < 1e-3, "{scoped:?}");
        // A refit that lost three objects by 50 nats: its mean gain (-5 per
        // object) would have set the old bar above the candidate's gain.
        let mut lost = vec![0.0; n];
        lost[3] = -50.0;
        lost[11] = -50.0;
        lost[20] = -50.0;
        let candidate: Vec<f64> = (0..n).map(|i| 0.6 + 0.1 * wobble(i)).collect();
        let over = beats_reseeded(&[&candidate], &[&lost], units, &[true], &config);
        assert!(over[0].1 < 0.05 && over[0].0 > 0.0, "{over:?}");
        // The rules with and without the comparison.
        let cand = qualifying_candidate();
        assert!(cand.passes_gain_rules(0.003, None, 0.003, 0.05));
        assert!(cand.passes_gain_rules(0.003, Some((0.1, 0.001)), 0.003, 0.05));
        assert!(!cand.passes_gain_rules(0.003, Some((0.1, 0.2)), 0.003, 0.05), "not significantly beyond the refit");
        assert!(
            !cand.passes_gain_rules(0.003, Some((0.001, 0.001)), 0.003, 0.05),
            "beyond it by less than the minimum"
        );
    }

    /// Rule (e): persistent flips are compared with independent flips by
    /// object when both were fitted, and only then; one that gains what the
    /// independent flips gain does not pass, one that gains more on every
    /// object does, by its gain per unit.
    #[test]
    fn a_nesting_extension_must_beat_the_one_it_nests() {
        let config = DiagnoseConfig { seed: 5, ..DiagnoseConfig::quick() };
        let n = 30;
        let units = 3 * n;
        let flips: Vec<f64> = (0..n).map(|i| 1.0 + wobble(i)).collect();
        let like_flips: Vec<f64> = flips.iter().enumerate().map(|(i, g)| g + 0.05 * wobble(i * 7 + 3)).collect();
        let beyond: Vec<f64> = like_flips.iter().map(|g| g + 0.5).collect();
        let ids = [Extension::HeadingFlip, Extension::PersistentFlip, Extension::Latency];
        let compared = nested_comparisons(&ids, &[&flips, &beyond, &flips], units, &config);
        assert!(compared[0].is_none() && compared[2].is_none(), "{compared:?}");
        let over = compared[1].clone().expect("persistent_flip against heading_flip");
        assert_eq!(over.nested, "heading_flip");
        assert!((over.gain - 0.5 * n as f64 / units as f64).abs() < 0.01 && over.p < 1e-3, "{over:?}");
        assert!(over.beats_nested(MIN_GAIN, 0.05));
        let like = nested_comparisons(&ids, &[&flips, &like_flips, &flips], units, &config)[1].clone().unwrap();
        assert!(like.p > 0.05 && !like.beats_nested(MIN_GAIN, 0.05), "{like:?}");
        assert!(nested_comparisons(&ids[1..], &[&beyond, &flips], units, &config)[0].is_none(), "nothing nested");
        let mut cand = qualifying_candidate();
        assert!(cand.passes_gain_rules(MIN_GAIN, None, MIN_GAIN, 0.05));
        cand.over_nested = Some(over);
        assert!(cand.passes_gain_rules(MIN_GAIN, None, MIN_GAIN, 0.05));
        cand.over_nested = Some(like);
        assert!(!cand.passes_gain_rules(MIN_GAIN, None, MIN_GAIN, 0.05), "no better than the nested extension");
    }

    /// A candidate that fails several rules is turned away by the first in the
    /// order they are listed (a, b, c, e), with its numbers; one that fails
    /// none passes, as `passes_gain_rules` says.
    #[test]
    fn the_first_failed_rule_names_why_a_candidate_is_not_the_cause() {
        let (bar, level) = (MIN_GAIN, 0.05);
        let mut cand = qualifying_candidate();
        assert_eq!(cand.failed_gain_rule(bar, None, bar, level), None);
        cand.over_nested = Some(NestedComparison { nested: "heading_flip".into(), gain: 0.0, p: 0.5 });
        assert_eq!(cand.failed_gain_rule(bar, None, bar, level), Some(FailedRule::Nested));
        cand.material = false;
        assert_eq!(cand.failed_gain_rule(bar, None, bar, level), Some(FailedRule::NotMaterial));
        assert_eq!(cand.failed_gain_rule(bar, Some((0.001, 0.001)), bar, level), Some(FailedRule::Reseeded));
        cand.gain = 0.5 * bar;
        assert_eq!(cand.failed_gain_rule(bar, Some((0.001, 0.001)), bar, level), Some(FailedRule::LeastGain));
        cand.gain = f64::NAN;
        assert_eq!(cand.failed_gain_rule(bar, None, bar, level), Some(FailedRule::LeastGain), "a non-finite gain");
        cand.p_adjusted = level;
        assert_eq!(cand.failed_gain_rule(bar, None, bar, level), Some(FailedRule::Level));
        assert!(!cand.passes_gain_rules(bar, None, bar, level));
        assert_eq!(FailedRule::Checks.to_string(), "(d) no flagging check improved");
    }

    /// Rule (d): one flagging check whose |z| falls is enough; checks that did
    /// not flag the extension, or that a model lacks, do not count. An
    /// overshoot counts only while the reference still flagged the check and
    /// the extended model does not fail it.
    #[test]
    fn rule_d_needs_one_flagging_check_to_improve() {
        let level = 0.2;
        let improves = |flagged: &[String], reference: &[CheckResult], extended: &[CheckResult]| {
            improves_flagged_checks(flagged, reference, extended, level)
        };
        let flagged = vec!["accel_kurtosis".to_string(), "accel_peakedness".to_string()];
        let reference = [check_with_z("accel_kurtosis", 1.16), check_with_z("accel_peakedness", -0.91)];
        // The measured case: kurtosis explained, the Geary ratio's z larger (mean |z| up).
        let one_better = [check_with_z("accel_kurtosis", 0.82), check_with_z("accel_peakedness", -2.42)];
        assert!(improves(&flagged, &reference, &one_better));
        let within = [check_with_z("accel_kurtosis", -0.5), check_with_z("accel_peakedness", 0.3)];
        assert!(improves(&flagged, &reference, &within), "|z| counts, not its sign");
        let both_worse = [check_with_z("accel_kurtosis", 1.5), check_with_z("accel_peakedness", -0.91)];
        assert!(!improves(&flagged, &reference, &both_worse), "an equal |z| is no improvement");
        let only_kurtosis = vec!["accel_kurtosis".to_string()];
        assert!(!improves(&only_kurtosis, &reference, &both_worse));
        assert!(!improves(&only_kurtosis, &reference[1..], &one_better), "missing on the reference");
        assert!(!improves(&[], &reference, &one_better), "fitted without a flag: nothing to improve");

        // Carried past the measured value: the clutter cell of the power study
        // (far-point |z| 1.27 -> 1.46 with the other sign, the reference's screen p 0.10).
        let far = vec!["far_point_fraction".to_string()];
        let flagging =
            |z: f64, screen_p: f64| CheckResult { screen_p: Some(screen_p), ..check_with_z("far_point_fraction", z) };
        let reference = [flagging(1.27, 0.10)];
        let overshoot = [check_with_z("far_point_fraction", -1.46)];
        assert!(improves(&far, &reference, &overshoot));
        let further = [check_with_z("far_point_fraction", 1.46)];
        assert!(!improves(&far, &reference, &further), "further the same way");
        let failing = [CheckResult { significant: true, ..check_with_z("far_point_fraction", -4.0) }];
        assert!(!improves(&far, &reference, &failing), "an overshoot the extended model fails");
        let unflagged = [flagging(0.37, 0.36)];
        assert!(!improves(&far, &unflagged, &overshoot), "the reference no longer flagged it");
        assert!(!improves(&far, &[flagging(1.27, 0.10)], &[]), "missing on the extended model");
        // What a reader is shown: signed z, and whether the extended model fails the check.
        assert_eq!(flagged_check_moves(&far, &reference, &overshoot), "far_point_fraction z 1.27 → -1.46");
        assert_eq!(flagged_check_moves(&far, &reference, &failing), "far_point_fraction z 1.27 → -4.00, failed");
        assert_eq!(flagged_check_moves(&far, &reference, &[]), "far_point_fraction z 1.27 → -");
        assert_eq!(flagged_check_moves(&[], &reference, &failing), NO_FLAGGING_CHECK, "a candidate of the screen");
    }

    /// Rule (d) of a candidate the likelihood screen admitted (no check
    /// flagged it) asks what admitted it: the fitted model's likelihood on the
    /// check part over the reference's. A flagged candidate is judged by its
    /// checks whatever its check-part gain, and one fitted by --fit-all alone
    /// still has nothing to improve.
    #[test]
    fn rule_d_of_a_screened_candidate_is_its_check_part_gain() {
        let reference = [CheckResult { screen_p: Some(0.1), ..check_with_z("far_point_fraction", 1.27) }];
        let after = vec![check_with_z("far_point_fraction", 2.0)];
        let screened = |gain: f64| CandidateReport {
            check_part_gain: Some(gain),
            checks_after: after.clone(),
            ..qualifying_candidate()
        };
        assert!(screened(0.12).improves_what_flagged_it(&reference, 0.2));
        assert!(!screened(-0.01).improves_what_flagged_it(&reference, 0.2));
        assert!(!screened(0.0).improves_what_flagged_it(&reference, 0.2), "no better than the reference");
        assert_eq!(
            screened(0.1234).flagging_moves(&reference),
            "admitted by the likelihood screen; check-part gain over the reference +0.1234"
        );
        // Flagged by a check it moves further the same way: its checks decide.
        let flagged = CandidateReport { flagged_by: vec!["far_point_fraction".into()], ..screened(0.12) };
        assert!(!flagged.improves_what_flagged_it(&reference, 0.2));
        assert_eq!(flagged.flagging_moves(&reference), "far_point_fraction z 1.27 → 2.00");
        let fit_all = CandidateReport { check_part_gain: None, ..screened(0.12) };
        assert!(!fit_all.improves_what_flagged_it(&reference, 0.2));
        assert_eq!(fit_all.flagging_moves(&reference), NO_FLAGGING_CHECK);
        // The fitted screen: the same gain, admitted only below the screen's level.
        let fitted = |gain: f64, p: f64| CandidateReport { check_part_p: Some(p), ..screened(gain) };
        assert!(fitted(0.12, 0.05).improves_what_flagged_it(&reference, 0.2) && fitted(0.12, 0.05).admitted(0.2));
        assert!(!fitted(0.12, 0.3).improves_what_flagged_it(&reference, 0.2) && !fitted(0.12, 0.3).admitted(0.2));
        assert!(!fitted(-0.01, 0.05).improves_what_flagged_it(&reference, 0.2));
        assert!(screened(0.12).admitted(0.2) && flagged.admitted(0.2), "only the fitted screen leaves a candidate out");
        assert_eq!(
            fitted(0.1234, 0.0412).flagging_moves(&reference),
            "fitted screen: check-part gain over the reference +0.1234, one-sided p 0.041"
        );
    }

    /// Step 5's tests leave out the candidate the fitted screen did not admit
    /// (adjusted p 1) and adjust the others for the tests made only.
    #[test]
    fn the_reference_tests_are_made_of_the_admitted_candidates_only() {
        let config = DiagnoseConfig { permutations: 999, ..DiagnoseConfig::quick() };
        // Three candidates whose p-values differ (more objects lose as k grows),
        // so a family read out of order would not pass.
        let gains: Vec<Vec<f64>> = (0..3)
            .map(|k| (0..30).map(|i| if i % 10 < 2 * k { -1.0 } else { 0.2 + 0.1 * ((i * 7) % 5) as f64 }).collect())
            .collect();
        let (p, adjusted, family) = reference_tests(&gains, &[None, Some(0.5), Some(0.01)], &config);
        assert!(p[0] < p[1] && p[1] < p[2], "{p:?}");
        assert_eq!(family, [true, false, true]);
        assert_eq!(adjusted[1], 1.0);
        let within = crate::criticism::checks::holm(&[p[0], p[2]]);
        assert_eq!((adjusted[0], adjusted[2]), (within[0], within[1]));
        let (_, whole, _) = reference_tests(&gains, &[None; 3], &config);
        assert_eq!(whole, crate::criticism::checks::holm(&p), "without the screen, Holm over every candidate");
    }
}
