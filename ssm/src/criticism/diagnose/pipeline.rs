//! Steps 2–6 of the diagnosis on its three parts ([`run`]).

use super::heldout::sign_flip_p;
use super::heldout::{differences, gain_monte_carlo_sd, gain_of, top_two_share, EvalLikelihoods};
use super::replicated::ModelChecks;

use std::path::Path;
use std::sync::Arc;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use autodiff::nn::ParamStore;

use crate::criticism::checks::{calibrate, checks_for, CheckDef, CheckResult};
use crate::data::ObservationKind;
use crate::filter::{stream_seed, FilterPurpose, Tempering};
use crate::models::extended::{Extension, RefitScope};
use crate::models::params::{AnyPolicy, Models};
use crate::models::vehicle::NeuralPolicy;
use crate::util::reduce::Collective;

use super::config::DiagnoseConfig;
use super::dispatch::{check_model, eval_likelihoods};
use super::fits::{fit, learned, natural_params, start_from_nested, FitSchedule, Fitted, TRAINING_RUN_DIRS};
use super::judge::gain_bar;
use super::progress::Stage;
use super::references::{Reference, ReferenceFit};
use super::report::{
    CandidateReport, CheckReport, ImpreciseObject, NotAdmitted, Report, ReseededReport, REPORT_FORMAT_VERSION,
};
use super::rules::{
    beats_reseeded, choose, nested_comparisons, outcome_without_cause, reference_tests, FITTED_SCREEN_PERMUTATIONS,
};
use super::screen::{to_evaluate, LikelihoodScreen};
use super::split::Parts;
use super::unmeasured::refine_unmeasured;

/// A fitted extension before the fitted screen's verdict.
pub(super) struct Trained {
    pub(super) extension: Extension,
    pub(super) flagged_by: Vec<String>,
    /// Whether a screen (not a check) made it plausible.
    pub(super) screened_in: bool,
    pub(super) check_part_gain: Option<f64>,
    pub(super) check_part_p: Option<f64>,
    pub(super) run: Fitted,
}

impl Trained {
    /// Whether the futility stop ended its fit ([`DiagnoseConfig::screen_futility`]).
    pub(super) fn stopped(&self) -> bool {
        self.run.paused_at.is_some()
    }
}

/// A fitted candidate before the decision.
pub(super) struct Fit {
    pub(super) extension: Extension,
    pub(super) flagged_by: Vec<String>,
    pub(super) check_part_gain: Option<f64>,
    pub(super) check_part_p: Option<f64>,
    pub(super) run: Fitted,
    pub(super) checks: ModelChecks,
    pub(super) eval: EvalLikelihoods,
}

/// Steps 2–6 of the diagnosis on `parts`, stage by stage.
pub(super) fn run(
    parts: Parts<'_>,
    config: &DiagnoseConfig,
    out_dir: &Path,
    comm: &Arc<dyn Collective>,
    progress: &mut dyn FnMut(&Stage),
) -> Result<Report, String> {
    let started = std::time::Instant::now();
    let config = &with_filters_resolved(config, parts.fit.kind());
    let mut run = Run { parts, config, out_dir, comm, progress };
    // 2. The base, from the network's own initialisation.
    let base = run.fit_base()?;
    // 3. Checks of the base on the check part.
    let (base_checks, before) = run.check_base(&base)?;
    // 4. The plausible extensions, started from the check part and fitted; the
    // references they are compared with; the screens' verdicts; the candidates
    // checked again and evaluated; the refits' own noise.
    let discrepancies: Vec<(&str, f64)> = before.iter().map(|c| (c.name.as_str(), c.measured - c.replicated)).collect();
    let starts = Starts { base: &base.params, discrepancies: &discrepancies };
    let Plausible { not_fitted, plausible, screens, base_on_check } = run.plausible_extensions(&before, &starts)?;
    let mut trained = run.fit_plausible(&base, &starts, plausible)?;
    let mut references = run.fit_references(&base, &before, &trained, base_on_check)?;
    run.screen_by_check_part(&mut trained, &references)?;
    let (mut fits, not_admitted) = run.evaluate_admitted(trained, &references)?;
    run.fit_reseeded(&base, &mut references, &fits)?;
    // 5. The decision on the evaluation part, each candidate against the
    // reference of its scope, over the objects every model measures.
    let (eval_imprecise, set_aside) = run.set_aside_unmeasured(&base, &mut references, &mut fits)?;
    let candidates = run.judge(&fits, &references)?;
    let winner = choose(&candidates, |_, c| c.qualifies);
    // 6. The outcome, and the checks after.
    let decided = Decided { candidates, winner, not_fitted, screens, not_admitted, eval_imprecise, set_aside };
    Ok(run.report(&base, &base_checks, &before, &fits, &references, decided, started))
}

/// `config` with the filters of the checks, the evaluation and training
/// resolved for data of `kind` where it leaves them to the data.
fn with_filters_resolved(config: &DiagnoseConfig, kind: ObservationKind) -> DiagnoseConfig {
    DiagnoseConfig {
        tempering: Some(
            config.tempering.unwrap_or_else(|| Tempering::for_observations(kind, FilterPurpose::Evaluation)),
        ),
        train_tempering: Some(
            config.train_tempering.unwrap_or_else(|| Tempering::for_observations(kind, FilterPurpose::Training)),
        ),
        ..config.clone()
    }
}

/// What every stage of one diagnosis reads: its parts, settings, run
/// directory, the processes that share its fits and its progress.
struct Run<'a, 'p> {
    parts: Parts<'a>,
    config: &'a DiagnoseConfig,
    out_dir: &'a Path,
    comm: &'a Arc<dyn Collective>,
    progress: &'p mut dyn FnMut(&Stage),
}

/// Where each extension's fit starts: the base's parameters with the
/// extension's values from the check part's discrepancies.
struct Starts<'a> {
    base: &'a ParamStore<f64>,
    discrepancies: &'a [(&'a str, f64)],
}

impl Starts<'_> {
    fn of(&self, extension: Extension) -> ParamStore<f64> {
        let mut start = self.base.clone();
        start.add(&extension.param_name(), extension.initial_from_checks(self.discrepancies));
        start
    }
}

/// The extensions the checks and the screens made plausible, and what was
/// learned choosing them.
struct Plausible {
    /// Those neither a check nor a screen made plausible.
    not_fitted: Vec<String>,
    /// Each plausible extension with the checks that flagged it and whether
    /// a screen made it plausible.
    plausible: Vec<(Extension, Vec<String>, bool)>,
    /// The likelihood screen of each extension no check flagged.
    screens: Vec<LikelihoodScreen>,
    /// The base on the check part, where the likelihood screen filtered it.
    base_on_check: Option<EvalLikelihoods>,
}

/// How the references of a diagnosis with `config` on `parts` are fitted
/// from `base`, checked with `defs`.
fn reference_fit<'b>(
    parts: Parts<'b>,
    config: &'b DiagnoseConfig,
    base: &'b Fitted,
    defs: &'b [&'static CheckDef],
) -> ReferenceFit<'b> {
    ReferenceFit { parts, base: &base.params, schedule: FitSchedule::refit(config), defs, config }
}

/// The decision and what the report lists beside it.
struct Decided {
    candidates: Vec<CandidateReport>,
    winner: Option<usize>,
    not_fitted: Vec<String>,
    screens: Vec<LikelihoodScreen>,
    not_admitted: Vec<NotAdmitted>,
    eval_imprecise: Vec<ImpreciseObject>,
    set_aside: Vec<usize>,
}

impl Run<'_, '_> {
    /// The scope `extension` is refitted within.
    fn scope_of(&self, extension: Extension) -> RefitScope {
        if self.config.scoped_refits {
            extension.refit_scope()
        } else {
            RefitScope::All
        }
    }

    /// Step 2: the base, from the network's own initialisation.
    fn fit_base(&mut self) -> Result<Fitted, String> {
        let initial = {
            let mut rng = StdRng::seed_from_u64(self.config.seed);
            let policy = NeuralPolicy::new(&mut rng);
            Models::initial(self.parts.fit.kind(), AnyPolicy::Neural(policy), rng.random()).to_store()
        };
        let dir = self.out_dir.join(TRAINING_RUN_DIRS[0]);
        let schedule = FitSchedule::base(self.config);
        fit(self.parts, None, initial, schedule, &[], self.config, &dir, self.comm, &mut *self.progress)
    }

    /// Step 3: the base's checks on the check part, calibrated.
    fn check_base(&mut self, base: &Fitted) -> Result<(ModelChecks, Vec<CheckResult>), String> {
        (self.progress)(&Stage::Checking { model: "base".into() });
        let base_checks = check_model(self.parts.check, &base.params, None, self.config)?;
        let defs = checks_for(self.parts.fit.kind());
        let before = calibrate(&defs, &base_checks.measured, &base_checks.replicated, self.config.alpha);
        Ok((base_checks, before))
    }

    /// Step 4's choice: each extension of the catalogue that a check flags
    /// (uncorrected directional p below the plausibility level), or that a
    /// screen admits, or every one under `fit_all`.
    fn plausible_extensions(&mut self, before: &[CheckResult], starts: &Starts<'_>) -> Result<Plausible, String> {
        let (parts, config) = (self.parts, self.config);
        let mut chosen =
            Plausible { not_fitted: Vec::new(), plausible: Vec::new(), screens: Vec::new(), base_on_check: None };
        for extension in Extension::for_kind(parts.fit.kind()) {
            let flagged_by: Vec<String> = before
                .iter()
                .filter(|c| {
                    c.suggests.as_deref() == Some(extension.id()) && c.screen_p.is_some_and(|p| p < config.plausible_p)
                })
                .map(|c| c.name.clone())
                .collect();
            let screened_in = if flagged_by.is_empty() && config.likelihood_screen {
                (self.progress)(&Stage::Evaluating { model: format!("{} at its start (check part)", extension.id()) });
                let base_ll = match &chosen.base_on_check {
                    Some(l) => l,
                    None => chosen.base_on_check.insert(eval_likelihoods(parts.check, starts.base, None, config)?),
                };
                let start_ll = eval_likelihoods(parts.check, &starts.of(extension), Some(extension), config)?;
                let d = differences(&start_ll.object_ll, &base_ll.object_ll);
                let screen = LikelihoodScreen::judge(extension.id(), &d, base_ll.units, config, chosen.screens.len());
                let admitted = screen.admitted;
                chosen.screens.push(screen);
                admitted
            } else {
                // The fitted screen fits every extension no check flagged; its check-part likelihood decides later.
                flagged_by.is_empty() && config.fitted_screen
            };
            if flagged_by.is_empty() && !config.fit_all && !screened_in {
                chosen.not_fitted.push(extension.id().to_string());
            } else {
                chosen.plausible.push((extension, flagged_by, screened_in));
            }
        }
        Ok(chosen)
    }

    /// Step 4's fits: every plausible extension, in catalogue order (a nested
    /// extension before its nesting one). One the fitted screen fits is paused
    /// at the futility stop and continued only where it has risen above the base.
    fn fit_plausible(
        &mut self,
        base: &Fitted,
        starts: &Starts<'_>,
        plausible: Vec<(Extension, Vec<String>, bool)>,
    ) -> Result<Vec<Trained>, String> {
        let (parts, config) = (self.parts, self.config);
        let refit_schedule = FitSchedule::refit(config);
        // The bar of the futility stop: the base's best check-part evaluation.
        let futility_bar = base.kept.as_ref().map(|kept| kept.value);
        let catalogue = Extension::for_kind(parts.fit.kind());
        let mut trained: Vec<Trained> = Vec::new();
        for (extension, flagged_by, screened_in) in plausible {
            let dir = self.out_dir.join(TRAINING_RUN_DIRS[3]).join(extension.id());
            let nested_fit = extension.nests().and_then(|nested| trained.iter().find(|t| t.extension == nested));
            let start = match nested_fit {
                Some(nested) if config.nesting_from_nested => {
                    start_from_nested(extension, starts.of(extension), &nested.run.params)?
                }
                _ => starts.of(extension),
            };
            let held = if config.refit { self.scope_of(extension).held(&start) } else { Vec::new() };
            let nested_by_another = catalogue.iter().any(|e| e.nests() == Some(extension));
            let futility = match (config.fitted_screen && screened_in && !nested_by_another, futility_bar) {
                (true, Some(bar)) => refit_schedule.at_futility_stop(config).map(|paused| (paused, bar)),
                _ => None,
            };
            let (comm, ext) = (self.comm, Some(extension));
            let run = match futility {
                Some((paused, bar)) => {
                    let run = fit(parts, ext, start.clone(), paused, &held, config, &dir, comm, &mut *self.progress)?;
                    // A run that paused here and has not risen above the base stays
                    // stopped; one already past the stop (resumed) was continued.
                    let futile = run.paused_at == paused.pause_at && run.kept.as_ref().is_none_or(|k| k.value <= bar);
                    if futile {
                        run
                    } else {
                        fit(parts, ext, start, refit_schedule, &held, config, &dir, comm, &mut *self.progress)?
                    }
                }
                None => fit(parts, ext, start, refit_schedule, &held, config, &dir, comm, &mut *self.progress)?,
            };
            trained.push(Trained {
                extension,
                flagged_by,
                screened_in,
                check_part_gain: None,
                check_part_p: None,
                run,
            });
        }
        Ok(trained)
    }

    /// The references the candidates are compared with: per refit scope that
    /// has a candidate, the base refitted alone within that scope exactly as
    /// its candidates are refitted (when any is), else the base. The scope of
    /// every parameter keeps its reference (its checks decide `unexplained`)
    /// even when the futility stop ended all of its extensions; another scope
    /// has one only where an extension of it was not stopped.
    fn fit_references(
        &mut self,
        base: &Fitted,
        before: &[CheckResult],
        trained: &[Trained],
        base_on_check: Option<EvalLikelihoods>,
    ) -> Result<Vec<Reference>, String> {
        let (parts, config) = (self.parts, self.config);
        let defs = checks_for(parts.fit.kind());
        let screened_any = trained.iter().any(|t| t.screened_in && !t.stopped());
        let mut references: Vec<Reference> = Vec::new();
        if config.refit {
            for scope in RefitScope::ALL {
                let in_scope = || trained.iter().filter(|t| self.scope_of(t.extension) == scope);
                if in_scope().any(|t| !t.stopped() || scope == RefitScope::All) {
                    let screened = in_scope().any(|t| t.screened_in && !t.stopped());
                    let fitting = reference_fit(parts, config, base, &defs);
                    let reference = fitting.fit(scope, screened, self.out_dir, self.comm, &mut *self.progress)?;
                    references.push(reference);
                }
            }
        }
        if references.is_empty() {
            (self.progress)(&Stage::Evaluating { model: "base".into() });
            references.push(Reference {
                scope: RefitScope::All,
                run: None,
                checks: before.to_vec(),
                eval: eval_likelihoods(parts.eval, &base.params, None, config)?,
                reseeded_run: None,
                reseeded: None,
                // Rule (d) of a screened candidate: the base on the check part (filtered already by the likelihood
                // screen; filtered now for the fitted screen).
                on_check: match (screened_any, base_on_check) {
                    (false, _) => None,
                    (true, Some(l)) => Some(l),
                    (true, None) => Some(eval_likelihoods(parts.check, &base.params, None, config)?),
                },
            });
        }
        Ok(references)
    }

    /// The screens' verdicts: one the fitted screen fitted to its end is
    /// admitted by its check-part likelihood over its reference's; one it
    /// stopped is not.
    fn screen_by_check_part(&mut self, trained: &mut [Trained], references: &[Reference]) -> Result<(), String> {
        let (parts, config) = (self.parts, self.config);
        for (slot, t) in trained.iter_mut().enumerate() {
            let (extension, run) = (t.extension, &t.run);
            (t.check_part_gain, t.check_part_p) =
                match &Reference::of_scope(references, self.scope_of(extension)).on_check {
                    // Stopped: no test, and a p that no level admits.
                    _ if t.stopped() => (None, Some(f64::NAN)),
                    Some(reference_ll) if t.screened_in => {
                        (self.progress)(&Stage::Evaluating { model: format!("{} (check part)", extension.id()) });
                        let on_check = eval_likelihoods(parts.check, &run.params, Some(extension), config)?;
                        let d = differences(&on_check.object_ll, &reference_ll.object_ll);
                        let seed = stream_seed(config.seed ^ FITTED_SCREEN_PERMUTATIONS, slot as u64);
                        let p = config.fitted_screen.then(|| sign_flip_p(&d, config.permutations, seed));
                        (Some(gain_of(&d, reference_ll.units).0), p)
                    }
                    _ => (None, None),
                };
        }
        Ok(())
    }

    /// The candidates, checked again and evaluated: every admitted extension,
    /// and one an admitted candidate nests (rule (e) compares them); the
    /// fitted screen's others are reported as not admitted.
    fn evaluate_admitted(
        &mut self,
        trained: Vec<Trained>,
        references: &[Reference],
    ) -> Result<(Vec<Fit>, Vec<NotAdmitted>), String> {
        let (parts, config) = (self.parts, self.config);
        let screened: Vec<(Extension, Option<f64>)> = trained.iter().map(|t| (t.extension, t.check_part_p)).collect();
        let evaluated = to_evaluate(&screened, config.plausible_p);
        let mut fits: Vec<Fit> = Vec::new();
        let mut not_admitted: Vec<NotAdmitted> = Vec::new();
        for (t, evaluated) in trained.into_iter().zip(evaluated) {
            let stopped = t.stopped();
            let Trained { extension, flagged_by, check_part_gain, check_part_p, run, .. } = t;
            if !evaluated {
                let raw = learned(&run.params, extension);
                let compared = Reference::of_scope(references, self.scope_of(extension)).scope;
                not_admitted.push(NotAdmitted {
                    cause: extension.id().into(),
                    check_part_gain: check_part_gain.unwrap_or(f64::NAN),
                    check_part_p: check_part_p.unwrap_or(f64::NAN),
                    // A stopped extension was compared with nothing: its own scope.
                    refit_scope: if stopped { self.scope_of(extension) } else { compared },
                    params: natural_params(extension, raw)?,
                    description: extension.describe(raw)?,
                    skipped_steps: run.skipped,
                    train_seconds: run.seconds,
                    kept: run.kept,
                    stopped_at: run.paused_at,
                });
                continue;
            }
            (self.progress)(&Stage::Checking { model: extension.id().into() });
            let checks = check_model(parts.check, &run.params, Some(extension), config)?;
            (self.progress)(&Stage::Evaluating { model: extension.id().into() });
            let eval = eval_likelihoods(parts.eval, &run.params, Some(extension), config)?;
            fits.push(Fit { extension, flagged_by, check_part_gain, check_part_p, run, checks, eval });
        }
        Ok((fits, not_admitted))
    }

    /// The refits' own noise, in every scope with a candidate: rule (b).
    fn fit_reseeded(&mut self, base: &Fitted, references: &mut [Reference], fits: &[Fit]) -> Result<(), String> {
        let (parts, config) = (self.parts, self.config);
        if !config.refit_noise {
            return Ok(());
        }
        let defs = checks_for(parts.fit.kind());
        for reference in references.iter_mut().filter(|r| r.run.is_some()) {
            if fits.iter().any(|f| self.scope_of(f.extension) == reference.scope) {
                let fitting = reference_fit(parts, config, base, &defs);
                fitting.fit_reseeded(reference, self.out_dir, self.comm, &mut *self.progress)?;
            }
        }
        Ok(())
    }

    /// The objects a model did not measure, refined and set aside
    /// ([`DiagnoseConfig::set_aside_unmeasured`]): every model's evaluation
    /// without them, and the reseeded refits' gains over those kept.
    fn set_aside_unmeasured(
        &mut self,
        base: &Fitted,
        references: &mut [Reference],
        fits: &mut [Fit],
    ) -> Result<(Vec<ImpreciseObject>, Vec<usize>), String> {
        let (parts, config) = (self.parts, self.config);
        let eval_object_units: Vec<usize> =
            (0..parts.eval.objects().len()).map(|o| parts.eval.object_units(o)).collect();
        let (eval_imprecise, set_aside) = if config.set_aside_unmeasured {
            refine_unmeasured(parts.eval, &base.params, references, fits, config, &mut *self.progress)?
        } else {
            (Vec::new(), Vec::new())
        };
        if !set_aside.is_empty() {
            for reference in references.iter_mut() {
                reference.eval = reference.eval.without(&set_aside, &eval_object_units);
                if let Some((_, again)) = &mut reference.reseeded_run {
                    *again = again.without(&set_aside, &eval_object_units);
                }
            }
            for f in fits.iter_mut() {
                f.eval = f.eval.without(&set_aside, &eval_object_units);
            }
        }
        // The reseeded refits' gains over the objects kept, refined ones included.
        for reference in references.iter_mut() {
            reference.reseeded =
                reference.reseeded_run.as_ref().map(|(run, again)| ReseededReport::new(run, again, &reference.eval));
        }
        Ok((eval_imprecise, set_aside))
    }

    /// Step 5: each candidate's gain over its scope's reference, its tests and
    /// the rules (a)–(e) it passes.
    fn judge(&self, fits: &[Fit], references: &[Reference]) -> Result<Vec<CandidateReport>, String> {
        let config = self.config;
        let defs = checks_for(self.parts.fit.kind());
        let reference_of = |extension: Extension| Reference::of_scope(references, self.scope_of(extension));
        let reference_eval = &references[0].eval;
        let object_gains: Vec<Vec<f64>> =
            fits.iter().map(|f| differences(&f.eval.object_ll, &reference_of(f.extension).eval.object_ll)).collect();
        let check_part_ps: Vec<Option<f64>> = fits.iter().map(|f| f.check_part_p).collect();
        let (p_values, adjusted, family) = reference_tests(&object_gains, &check_part_ps, config);
        let gains: Vec<&[f64]> = object_gains.iter().map(Vec::as_slice).collect();
        let reseeded_gains: Option<Vec<&[f64]>> = fits
            .iter()
            .map(|f| reference_of(f.extension).reseeded.as_ref().map(|r| r.object_gains.as_slice()))
            .collect();
        let over_reseeded: Vec<Option<(f64, f64)>> = match &reseeded_gains {
            Some(reseeded) if !fits.is_empty() => {
                beats_reseeded(&gains, reseeded, reference_eval.units, &family, config).into_iter().map(Some).collect()
            }
            _ => vec![None; fits.len()],
        };
        let ids: Vec<Extension> = fits.iter().map(|f| f.extension).collect();
        let over_nested = nested_comparisons(&ids, &gains, reference_eval.units, config);
        let mut candidates = Vec::new();
        for (i, (f, d)) in fits.iter().zip(object_gains).enumerate() {
            let ext = f.extension;
            let reference = reference_of(ext);
            let (gain, gain_se) = gain_of(&d, reference_eval.units);
            let (gain_mc_sd, worst_object_mc_sd) = gain_monte_carlo_sd(&f.eval, &reference.eval);
            let after = calibrate(&defs, &f.checks.measured, &f.checks.replicated, config.alpha);
            let raw = learned(&f.run.params, ext).to_vec();
            let material = ext.is_material(&raw)?;
            let mut candidate = CandidateReport {
                cause: ext.id().into(),
                gain,
                gain_se,
                gain_mc_sd,
                worst_object_mc_sd,
                p: p_values[i],
                p_adjusted: adjusted[i],
                top_two_share: top_two_share(&d),
                object_gains: d,
                object_mc_sd: f.eval.object_mc_sd.clone(),
                mll: f.eval.object_ll.iter().sum::<f64>() / reference_eval.units.max(1) as f64,
                refit_scope: reference.scope,
                over_reseeded: over_reseeded[i],
                over_nested: over_nested[i].clone(),
                params: natural_params(ext, &raw)?,
                description: ext.describe(&raw)?,
                flagged_by: f.flagged_by.clone(),
                check_part_gain: f.check_part_gain,
                check_part_p: f.check_part_p,
                checks_improved: false,
                checks_after: after,
                material,
                qualifies: false,
                skipped_steps: f.run.skipped,
                train_seconds: f.run.seconds,
                kept: f.run.kept.clone(),
            };
            candidate.checks_improved = candidate.improves_what_flagged_it(&reference.checks, config.plausible_p);
            let gain_bar = gain_bar(config.min_gain, reference.reseeded.as_ref());
            candidate.qualifies = candidate.checks_improved
                && candidate.passes_gain_rules(gain_bar, candidate.over_reseeded, config.min_gain, config.cause_level);
            candidates.push(candidate);
        }
        Ok(candidates)
    }

    /// Step 6: the outcome, the checks before and after, and the report.
    #[allow(clippy::too_many_arguments)]
    fn report(
        &self,
        base: &Fitted,
        base_checks: &ModelChecks,
        before: &[CheckResult],
        fits: &[Fit],
        references: &[Reference],
        decided: Decided,
        started: std::time::Instant,
    ) -> Report {
        let (parts, config) = (self.parts, self.config);
        let Decided { candidates, winner, not_fitted, screens, not_admitted, eval_imprecise, set_aside } = decided;
        let defs = checks_for(parts.fit.kind());
        let checks: Vec<CheckReport> = defs
            .iter()
            .enumerate()
            .map(|(c, def)| CheckReport {
                name: def.name.into(),
                description: def.description.into(),
                suggests: def.suggests.map(|s| s.extension.to_string()),
                z: before[c].z,
                p: before[c].p_adjusted,
                before: before[c].clone(),
                after: winner.map(|i| candidates[i].checks_after[c].clone()),
                draws_before: base_checks.draws_of(c),
                draws_after: winner.map(|i| fits[i].checks.draws_of(c)).unwrap_or_default(),
            })
            .collect();
        let (cause, finding) = match winner {
            Some(i) => (candidates[i].cause.clone(), candidates[i].description.clone()),
            None => outcome_without_cause(&references[0].checks),
        };
        let measured = |o: &usize| set_aside.binary_search(o).is_err();
        let eval_object_units: Vec<usize> =
            (0..parts.eval.objects().len()).map(|o| parts.eval.object_units(o)).collect();
        let reference_eval = &references[0].eval;
        let units = reference_eval.units.max(1) as f64;
        let base_mll = reference_eval.object_ll.iter().sum::<f64>() / units;
        Report {
            format_version: REPORT_FORMAT_VERSION,
            cause,
            gain: winner.map_or(0.0, |i| candidates[i].gain),
            gain_se: winner.map_or(0.0, |i| candidates[i].gain_se),
            gain_p: winner.map_or(1.0, |i| candidates[i].p_adjusted),
            finding,
            chosen_mll: winner.map_or(base_mll, |i| fits[i].eval.object_ll.iter().sum::<f64>() / units),
            checks,
            candidates,
            not_fitted,
            likelihood_screen: screens,
            not_admitted,
            kind: parts.fit.kind(),
            train_objects: parts.fit.objects().len(),
            check_objects: parts.check.objects().len(),
            eval_objects: parts.eval.objects().len(),
            eval_object_keys: parts
                .eval
                .objects()
                .iter()
                .enumerate()
                .filter(|(o, _)| measured(o))
                .map(|(_, o)| (o.scene, o.id))
                .collect(),
            eval_object_units: eval_object_units
                .iter()
                .enumerate()
                .filter(|(o, _)| measured(o))
                .map(|(_, u)| *u)
                .collect(),
            eval_imprecise,
            eval_units: reference_eval.units,
            base_mll,
            reference: references.iter().find(|r| r.scope == RefitScope::All).and_then(Reference::report),
            dynamics_reference: references.iter().find(|r| r.scope == RefitScope::Dynamics).and_then(Reference::report),
            base_skipped_steps: base.skipped,
            base_train_seconds: base.seconds,
            base_kept: base.kept.clone(),
            seconds: started.elapsed().as_secs_f64(),
            config: config.clone(),
        }
    }
}
