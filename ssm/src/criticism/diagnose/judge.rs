//! Reading a stored report again: its outcome under the current rules, what a study that
//! expected one outcome reads off it, and the queries its presentation makes.

use super::heldout::{gains_by_group, GroupGain};
use super::{NO_CAUSE, UNEXPLAINED};

use std::borrow::Cow;

use serde::{Deserialize, Serialize};

use crate::criticism::checks::CheckResult;
use crate::data::KITTI_SCENE_ID_BASE;
use crate::models::extended::RefitScope;

use super::report::{CandidateReport, ReferenceReport, Report, ReseededReport};
use super::rules::{beats_reseeded, choose, outcome_without_cause, FailedRule};

/// A candidate's gain over the reseeded refit and that gain's Holm p
/// ([`CandidateReport::over_reseeded`]).
pub(super) type OverReseeded = Option<(f64, f64)>;

/// A report decided for a study that expected one outcome ([`Report::decided_for`]).
#[derive(Clone, Debug, PartialEq)]
pub struct StudyDecision<'a> {
    /// The outcome under the current rules ([`Report::decided`]).
    pub cause: String,
    /// The candidate named, if any.
    pub chosen: Option<&'a CandidateReport>,
    /// The outcome without rule (d).
    pub cause_without_check_rule: String,
    /// Why the outcome is not the expected one ([`Report::why_not`]); `None` when it is.
    pub why_missed: Option<String>,
}

/// The parts a held-out gain is split into ([`Report::gains_by_part`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EvalPart {
    /// KITTI sequences: the importer's scene ids are
    /// [`KITTI_SCENE_ID_BASE`] × sequence + first frame.
    KittiSequence,
    /// Scenes.
    Scene,
}

impl EvalPart {
    /// The part's name in a table's header.
    pub fn label(self) -> &'static str {
        match self {
            EvalPart::KittiSequence => "KITTI sequence",
            EvalPart::Scene => "scene",
        }
    }
}

impl Report {
    /// How this report's evaluation objects are split into parts: by KITTI
    /// sequence when their scene ids span more than one, else by scene.
    pub fn eval_part(&self) -> EvalPart {
        let first = self.eval_object_keys.first().map(|o| o.0 / KITTI_SCENE_ID_BASE);
        if self.eval_object_keys.iter().any(|o| Some(o.0 / KITTI_SCENE_ID_BASE) != first) {
            EvalPart::KittiSequence
        } else {
            EvalPart::Scene
        }
    }

    /// The candidate whose gain a report splits by part: the one named `cause`,
    /// or where none is (no cause, or a cause decided again), the one with the
    /// largest gain; `None` without candidates.
    pub fn shown_candidate(&self, cause: &str) -> Option<&CandidateReport> {
        let named = self.candidates.iter().find(|c| c.cause == cause);
        named.or_else(|| self.candidates.iter().max_by(|a, b| a.gain.total_cmp(&b.gain)))
    }

    /// Candidate `c`'s held-out gain split by [`Report::eval_part`] (groups in
    /// ascending order, each labelled by its sequence or scene): whether the
    /// gain is carried by the whole evaluation part or by one of its parts.
    /// `None` when the report has no per-object record that matches its
    /// evaluation objects (reports written before it was kept).
    pub fn gains_by_part(&self, c: &CandidateReport) -> Option<Vec<GroupGain>> {
        let (keys, units) = (&self.eval_object_keys, &self.eval_object_units);
        if keys.is_empty() || keys.len() != c.object_gains.len() || units.len() != keys.len() {
            return None;
        }
        Some(match self.eval_part() {
            EvalPart::KittiSequence => {
                gains_by_group(&c.object_gains, keys, units, |scene| scene / KITTI_SCENE_ID_BASE)
            }
            EvalPart::Scene => gains_by_group(&c.object_gains, keys, units, |scene| scene),
        })
    }

    /// The bar of [`DiagnoseConfig::set_aside_unmeasured`](crate::criticism::diagnose::DiagnoseConfig::set_aside_unmeasured) on this report's
    /// evaluation part, its objects set aside included.
    pub fn unmeasured_bar(&self) -> f64 {
        let set_aside: usize = self.eval_imprecise.iter().filter(|o| o.set_aside).map(|o| o.units).sum();
        self.config.unmeasured_bar(self.eval_units + set_aside)
    }

    /// The least gain (nats per observed unit) that names a cause, rule (b):
    /// [`DiagnoseConfig::min_gain`](crate::criticism::diagnose::DiagnoseConfig::min_gain), or the size of the refits' own noise when
    /// it was measured and is larger.
    pub fn gain_bar(&self) -> f64 {
        gain_bar(self.config.min_gain, self.first_reference().and_then(|r| r.reseeded.as_ref()))
    }

    /// The least gain of candidate `c`, as [`Report::gain_bar`] with its own
    /// scope's reseeded refit.
    pub(super) fn gain_bar_of(&self, c: &CandidateReport) -> f64 {
        gain_bar(self.config.min_gain, self.reference_of(c).and_then(|r| r.reseeded.as_ref()))
    }

    /// The refit of the base in `scope` ([`Report::reference`] or
    /// [`Report::dynamics_reference`]).
    pub fn reference_in(&self, scope: RefitScope) -> Option<&ReferenceReport> {
        match scope {
            RefitScope::All => self.reference.as_ref(),
            RefitScope::Dynamics => self.dynamics_reference.as_ref(),
        }
    }

    /// What candidate `c` was compared with: the refit of its scope.
    pub fn reference_of(&self, c: &CandidateReport) -> Option<&ReferenceReport> {
        self.reference_in(c.refit_scope)
    }

    /// The first refit of the base: in every parameter where there is one, else in the policy.
    pub fn first_reference(&self) -> Option<&ReferenceReport> {
        self.reference.as_ref().or(self.dynamics_reference.as_ref())
    }

    /// Every check calibrated on what the candidates were compared with: the
    /// reference's (refitted in every parameter where there is one, else in
    /// the policy), or the base's when the base is the reference
    /// (`--no-refit`, or nothing fitted). A check that fails on it, with no
    /// qualifying cause, makes the outcome `unexplained`.
    pub fn reference_checks(&self) -> Cow<'_, [CheckResult]> {
        self.checks_of(self.first_reference())
    }

    /// The reference checks of candidate `c`: those of its scope's refit (rule
    /// (d)'s "before"), or [`Report::reference_checks`] without one.
    pub fn reference_checks_of(&self, c: &CandidateReport) -> Cow<'_, [CheckResult]> {
        self.checks_of(self.reference_of(c).or(self.first_reference()))
    }

    pub(super) fn checks_of<'a>(&'a self, reference: Option<&'a ReferenceReport>) -> Cow<'a, [CheckResult]> {
        match reference {
            Some(r) => Cow::Borrowed(&r.checks),
            None => Cow::Owned(self.checks.iter().map(|c| c.before.clone()).collect()),
        }
    }

    /// The outcome the current decision rules give on this report's candidates
    /// and reference checks, and the chosen candidate: reports written under an
    /// earlier rule (d) are decided again (those without the candidates' checks
    /// keep their recorded `checks_improved`). Without `check_rule`, rule (d) is
    /// left out (what the outcome would be if extensions did not have to improve
    /// their checks). A report without candidates keeps its outcome.
    pub fn decided(&self, check_rule: bool) -> (String, Option<&CandidateReport>) {
        self.outcome(&self.verdicts(check_rule))
    }

    /// The outcome of candidates judged `verdicts` ([`Report::verdicts`]):
    /// the qualifying one with the largest gain, else `unexplained` or `none`
    /// by the reference's checks; without candidates, the recorded outcome.
    /// [`Report::decided`] is this of [`Report::verdicts`]; a caller that needs
    /// both judges the candidates once.
    pub fn outcome(&self, verdicts: &[Option<FailedRule>]) -> (String, Option<&CandidateReport>) {
        if self.candidates.is_empty() {
            return (self.cause.clone(), None);
        }
        match choose(&self.candidates, |i, _| verdicts[i].is_none()) {
            Some(i) => (self.candidates[i].cause.clone(), Some(&self.candidates[i])),
            None => (outcome_without_cause(&self.reference_checks()).0, None),
        }
    }

    /// Per candidate, the first rule of step 5 it fails under the current
    /// rules (`None`: it qualifies), as [`Report::decided`] judges them; rule
    /// (d) only with `check_rule`.
    pub fn verdicts(&self, check_rule: bool) -> Vec<Option<FailedRule>> {
        self.judged(check_rule).0
    }

    /// [`Report::verdicts`], with the comparisons with the reseeded refit
    /// they were judged on ([`Report::over_reseeded`]).
    pub(super) fn judged(&self, check_rule: bool) -> (Vec<Option<FailedRule>>, Vec<OverReseeded>) {
        let improved =
            |c: &CandidateReport| c.improves_what_flagged_it(&self.reference_checks_of(c), self.config.plausible_p);
        let over = self.over_reseeded();
        let (min_gain, level) = (self.config.min_gain, self.config.cause_level);
        let verdicts = self
            .candidates
            .iter()
            .enumerate()
            .map(|(i, c)| {
                c.failed_gain_rule(self.gain_bar_of(c), over[i], min_gain, level)
                    .or_else(|| (check_rule && !improved(c)).then_some(FailedRule::Checks))
            })
            .collect();
        (verdicts, over)
    }

    /// Why the outcome is not `expected` (a cause, `none` or `unexplained`),
    /// in a phrase for a table; `None` when it is. For an expected cause: not
    /// fitted, the rule it fails with the numbers that failed it, or the cause
    /// that gained more; else the cause named, or the failing checks.
    pub fn why_not(&self, expected: &str) -> Option<String> {
        self.decided_for(expected).why_missed
    }

    /// What a study that expected `expected` reads off this report, from one
    /// judging of its candidates (on reports written before the paired rule
    /// (b), the comparisons with the reseeded refit are permutation tests):
    /// [`Report::decided`] with and without rule (d), and [`Report::why_not`].
    pub fn decided_for(&self, expected: &str) -> StudyDecision<'_> {
        let (verdicts, over) = self.judged(true);
        // Rule (d) is judged last, so leaving it out frees exactly the
        // candidates it alone turned away.
        let without_check_rule: Vec<_> = verdicts.iter().map(|v| v.filter(|r| *r != FailedRule::Checks)).collect();
        let (cause, chosen) = self.outcome(&verdicts);
        let why_missed = (cause != expected).then(|| {
            let candidate = self.candidates.iter().position(|c| c.cause == expected);
            let not_admitted = self.not_admitted.iter().find(|n| n.cause == expected);
            let why = match (candidate, chosen, not_admitted) {
                (Some(i), _, _) if !self.candidates[i].admitted(self.config.plausible_p) => {
                    let c = &self.candidates[i];
                    format!(
                        "`{expected}` fitted, {}",
                        not_admitted_clause(c.check_part_gain.unwrap_or(f64::NAN), c.check_part_p)
                    )
                }
                (Some(i), _, _) => match verdicts[i] {
                    Some(rule) => format!(
                        "`{expected}` fails {rule}: {}",
                        self.failure_numbers(&self.candidates[i], over[i], rule)
                    ),
                    None => format!("`{expected}` qualifies, but `{cause}` gains more"),
                },
                (None, _, Some(n)) => format!("`{expected}` fitted, {}", n.why()),
                (None, _, None) if expected != NO_CAUSE && expected != UNEXPLAINED => {
                    match self.likelihood_screen.iter().find(|s| s.cause == expected) {
                        Some(s) => format!(
                            "`{expected}` not fitted: no check flagged it, nor did the likelihood screen admit it \
                             (start gain {:+.4}, p {:.3})",
                            s.gain, s.p
                        ),
                        None => format!("`{expected}` not fitted"),
                    }
                }
                (None, Some(c), _) => format!("`{}` named (gain {:+.4}, p adj. {:.4})", c.cause, c.gain, c.p_adjusted),
                (None, None, _) => match outcome_without_cause(&self.reference_checks()).1 {
                    failing if failing.is_empty() => {
                        "no check of the reference fails at the family-wise level".to_string()
                    }
                    failing => failing,
                },
            };
            format!("`{cause}`: {why}")
        });
        StudyDecision { cause_without_check_rule: self.outcome(&without_check_rule).0, cause, chosen, why_missed }
    }

    /// The numbers by which candidate `c` (its gain over the reseeded refit
    /// `over_reseeded`) fails `rule`.
    pub(super) fn failure_numbers(
        &self,
        c: &CandidateReport,
        over_reseeded: Option<(f64, f64)>,
        rule: FailedRule,
    ) -> String {
        match rule {
            FailedRule::Level => format!("gain {:+.4}, p adj. {:.4}", c.gain, c.p_adjusted),
            FailedRule::LeastGain => format!("gain {:+.4} under {:.4}", c.gain, self.gain_bar_of(c)),
            FailedRule::Reseeded => {
                over_reseeded.map_or(String::new(), |(gain, p)| format!("over it {gain:+.4}, p adj. {p:.4}"))
            }
            FailedRule::NotMaterial => c.description.clone(),
            FailedRule::Checks => c.flagging_moves(&self.reference_checks_of(c)),
            FailedRule::Nested => c
                .over_nested
                .as_ref()
                .map_or(String::new(), |n| format!("over `{}` {:+.4}, p {:.4}", n.nested, n.gain, n.p)),
        }
    }

    /// Per candidate, its gain over the reseeded refit and the gain's Holm p:
    /// as recorded, or, in reports whose candidates were not compared with it
    /// (written before that comparison) but that kept its per-object gains,
    /// compared now.
    pub(super) fn over_reseeded(&self) -> Vec<OverReseeded> {
        let reseeded_gains = |c: &CandidateReport| {
            let reseeded = self.reference_of(c).and_then(|r| r.reseeded.as_ref());
            reseeded.filter(|r| !r.object_gains.is_empty()).map(|r| r.object_gains.as_slice())
        };
        let reseeded: Option<Vec<&[f64]>> = self.candidates.iter().map(reseeded_gains).collect();
        match reseeded {
            Some(r) if self.candidates.iter().any(|c| c.over_reseeded.is_none()) => {
                let gains: Vec<&[f64]> = self.candidates.iter().map(|c| c.object_gains.as_slice()).collect();
                let family: Vec<bool> = self.candidates.iter().map(|c| c.admitted(self.config.plausible_p)).collect();
                beats_reseeded(&gains, &r, self.eval_units, &family, &self.config).into_iter().map(Some).collect()
            }
            _ => self.candidates.iter().map(|c| c.over_reseeded).collect(),
        }
    }
}

/// Why the fitted screen did not admit an extension it fitted to its end: its
/// check-part gain and p.
pub(super) fn not_admitted_clause(check_part_gain: f64, check_part_p: Option<f64>) -> String {
    format!(
        "not admitted by the fitted screen: check-part gain {check_part_gain:+.4}, p {:.3}",
        check_part_p.unwrap_or(f64::NAN)
    )
}

/// Rule (b)'s least gain over the reference: `min_gain`; in reports whose
/// reseeded refit did not keep its per-object gains (so no
/// candidate could be compared with it by object), the size of its gain when
/// that is larger.
pub(super) fn gain_bar(min_gain: f64, reseeded: Option<&ReseededReport>) -> f64 {
    let earlier_bar = reseeded.filter(|r| r.object_gains.is_empty()).map_or(0.0, |r| r.gain.abs());
    min_gain.max(earlier_bar)
}
