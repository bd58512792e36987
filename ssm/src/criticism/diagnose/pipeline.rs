//! Steps 2–6 of the diagnosis on its three parts ([`run`]).

use super::heldout::sign_flip_p;
use super::heldout::{differences, gain_monte_carlo_sd, gain_of, top_two_share, EvalLikelihoods};
use super::replicated::ModelChecks;

use std::path::Path;
use std::sync::Arc;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::criticism::checks::{calibrate, checks_for};
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
use super::report::{CandidateReport, CheckReport, NotAdmitted, Report, ReseededReport};
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

/// Steps 2–6 of the diagnosis on `parts`.
pub(super) fn run(
    parts: Parts<'_>,
    config: &DiagnoseConfig,
    out_dir: &Path,
    comm: &Arc<dyn Collective>,
    progress: &mut dyn FnMut(&Stage),
) -> Result<Report, String> {
    let started = std::time::Instant::now();
    let kind = parts.fit.kind();
    let config = &DiagnoseConfig {
        tempering: Some(
            config.tempering.unwrap_or_else(|| Tempering::for_observations(kind, FilterPurpose::Evaluation)),
        ),
        train_tempering: Some(
            config.train_tempering.unwrap_or_else(|| Tempering::for_observations(kind, FilterPurpose::Training)),
        ),
        ..config.clone()
    };
    // 2. The base, from the network's own initialisation.
    let initial = {
        let mut rng = StdRng::seed_from_u64(config.seed);
        let policy = NeuralPolicy::new(&mut rng);
        Models::initial(kind, AnyPolicy::Neural(policy), rng.random()).to_store()
    };
    let base = fit(
        parts,
        None,
        initial,
        FitSchedule::base(config),
        &[],
        config,
        &out_dir.join(TRAINING_RUN_DIRS[0]),
        comm,
        progress,
    )?;

    // 3. Checks of the base on the check part.
    progress(&Stage::Checking { model: "base".into() });
    let base_checks = check_model(parts.check, &base.params, None, config)?;
    let defs = checks_for(kind);
    let before = calibrate(&defs, &base_checks.measured, &base_checks.replicated, config.alpha);

    // 4. The plausible extensions, started from the check part.
    let discrepancies: Vec<(&str, f64)> = before.iter().map(|c| (c.name.as_str(), c.measured - c.replicated)).collect();
    let start_of = |extension: Extension| {
        let mut start = base.params.clone();
        start.add(&extension.param_name(), extension.initial_from_checks(&discrepancies));
        start
    };
    let mut not_fitted = Vec::new();
    let mut plausible = Vec::new();
    let mut screens = Vec::new();
    let mut base_on_check: Option<EvalLikelihoods> = None;
    for extension in Extension::for_kind(kind) {
        let flagged_by: Vec<String> = before
            .iter()
            .filter(|c| {
                c.suggests.as_deref() == Some(extension.id()) && c.screen_p.is_some_and(|p| p < config.plausible_p)
            })
            .map(|c| c.name.clone())
            .collect();
        let screened_in = if flagged_by.is_empty() && config.likelihood_screen {
            progress(&Stage::Evaluating { model: format!("{} at its start (check part)", extension.id()) });
            let base_ll = match &base_on_check {
                Some(l) => l,
                None => base_on_check.insert(eval_likelihoods(parts.check, &base.params, None, config)?),
            };
            let start_ll = eval_likelihoods(parts.check, &start_of(extension), Some(extension), config)?;
            let d = differences(&start_ll.object_ll, &base_ll.object_ll);
            let screen = LikelihoodScreen::judge(extension.id(), &d, base_ll.units, config, screens.len());
            let admitted = screen.admitted;
            screens.push(screen);
            admitted
        } else {
            // The fitted screen fits every extension no check flagged; its check-part likelihood decides later.
            flagged_by.is_empty() && config.fitted_screen
        };
        if flagged_by.is_empty() && !config.fit_all && !screened_in {
            not_fitted.push(extension.id().to_string());
        } else {
            plausible.push((extension, flagged_by, screened_in));
        }
    }
    // Every plausible extension is fitted, in catalogue order (a nested
    // extension before its nesting one). One the fitted screen fits is paused
    // at the futility stop and continued only where it has risen above the base.
    let scope_of = |extension: Extension| if config.scoped_refits { extension.refit_scope() } else { RefitScope::All };
    let refit_schedule = FitSchedule::refit(config);
    // The bar of the futility stop: the base's best check-part evaluation.
    let futility_bar = base.kept.as_ref().map(|kept| kept.value);
    let catalogue = Extension::for_kind(kind);
    let mut trained: Vec<Trained> = Vec::new();
    for (extension, flagged_by, screened_in) in plausible {
        let dir = out_dir.join(TRAINING_RUN_DIRS[3]).join(extension.id());
        let nested_fit = extension.nests().and_then(|nested| trained.iter().find(|t| t.extension == nested));
        let start = match nested_fit {
            Some(nested) if config.nesting_from_nested => {
                start_from_nested(extension, start_of(extension), &nested.run.params)?
            }
            _ => start_of(extension),
        };
        let held = if config.refit { scope_of(extension).held(&start) } else { Vec::new() };
        let nested_by_another = catalogue.iter().any(|e| e.nests() == Some(extension));
        let futility = match (config.fitted_screen && screened_in && !nested_by_another, futility_bar) {
            (true, Some(bar)) => refit_schedule.at_futility_stop(config).map(|paused| (paused, bar)),
            _ => None,
        };
        let run = match futility {
            Some((paused, bar)) => {
                let run = fit(parts, Some(extension), start.clone(), paused, &held, config, &dir, comm, progress)?;
                // A run that paused here and has not risen above the base stays
                // stopped; one already past the stop (resumed) was continued.
                let futile = run.paused_at == paused.pause_at && run.kept.as_ref().is_none_or(|k| k.value <= bar);
                if futile {
                    run
                } else {
                    fit(parts, Some(extension), start, refit_schedule, &held, config, &dir, comm, progress)?
                }
            }
            None => fit(parts, Some(extension), start, refit_schedule, &held, config, &dir, comm, progress)?,
        };
        trained.push(Trained { extension, flagged_by, screened_in, check_part_gain: None, check_part_p: None, run });
    }
    // The references the candidates are compared with: per refit scope that
    // has a candidate, the base refitted alone within that scope exactly as
    // its candidates are refitted (when any is), else the base. The scope of
    // every parameter keeps its reference (its checks decide `unexplained`)
    // even when the futility stop ended all of its extensions; another scope
    // has one only where an extension of it was not stopped.
    let screened_any = trained.iter().any(|t| t.screened_in && !t.stopped());
    let mut references: Vec<Reference> = Vec::new();
    let fitting = ReferenceFit { parts, base: &base.params, schedule: refit_schedule, defs: &defs, config };
    if config.refit {
        for scope in RefitScope::ALL {
            let in_scope = || trained.iter().filter(|t| scope_of(t.extension) == scope);
            if in_scope().any(|t| !t.stopped() || scope == RefitScope::All) {
                let screened = in_scope().any(|t| t.screened_in && !t.stopped());
                references.push(fitting.fit(scope, screened, out_dir, comm, progress)?);
            }
        }
    }
    if references.is_empty() {
        progress(&Stage::Evaluating { model: "base".into() });
        references.push(Reference {
            scope: RefitScope::All,
            run: None,
            checks: before.clone(),
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
    // One the fitted screen fitted to its end is admitted by its check-part
    // likelihood over its reference's; one it stopped is not.
    let reference_of = |extension: Extension| Reference::of_scope(&references, scope_of(extension));
    for (slot, t) in trained.iter_mut().enumerate() {
        let (extension, run) = (t.extension, &t.run);
        (t.check_part_gain, t.check_part_p) = match &reference_of(extension).on_check {
            // Stopped: no test, and a p that no level admits.
            _ if t.stopped() => (None, Some(f64::NAN)),
            Some(reference_ll) if t.screened_in => {
                progress(&Stage::Evaluating { model: format!("{} (check part)", extension.id()) });
                let on_check = eval_likelihoods(parts.check, &run.params, Some(extension), config)?;
                let d = differences(&on_check.object_ll, &reference_ll.object_ll);
                let seed = stream_seed(config.seed ^ FITTED_SCREEN_PERMUTATIONS, slot as u64);
                let p = config.fitted_screen.then(|| sign_flip_p(&d, config.permutations, seed));
                (Some(gain_of(&d, reference_ll.units).0), p)
            }
            _ => (None, None),
        };
    }
    // The candidates, checked again and evaluated: every admitted extension,
    // and one an admitted candidate nests (rule (e) compares them); the
    // fitted screen's others are reported as not admitted.
    let screened: Vec<(Extension, Option<f64>)> = trained.iter().map(|t| (t.extension, t.check_part_p)).collect();
    let evaluated = to_evaluate(&screened, config.plausible_p);
    let mut fits: Vec<Fit> = Vec::new();
    let mut not_admitted: Vec<NotAdmitted> = Vec::new();
    for (t, evaluated) in trained.into_iter().zip(evaluated) {
        let stopped = t.stopped();
        let Trained { extension, flagged_by, check_part_gain, check_part_p, run, .. } = t;
        if !evaluated {
            let raw = learned(&run.params, extension);
            not_admitted.push(NotAdmitted {
                cause: extension.id().into(),
                check_part_gain: check_part_gain.unwrap_or(f64::NAN),
                check_part_p: check_part_p.unwrap_or(f64::NAN),
                // A stopped extension was compared with nothing: its own scope.
                refit_scope: if stopped { scope_of(extension) } else { reference_of(extension).scope },
                params: natural_params(extension, raw)?,
                description: extension.describe(raw)?,
                skipped_steps: run.skipped,
                train_seconds: run.seconds,
                kept: run.kept,
                stopped_at: run.paused_at,
            });
            continue;
        }
        progress(&Stage::Checking { model: extension.id().into() });
        let checks = check_model(parts.check, &run.params, Some(extension), config)?;
        progress(&Stage::Evaluating { model: extension.id().into() });
        let eval = eval_likelihoods(parts.eval, &run.params, Some(extension), config)?;
        fits.push(Fit { extension, flagged_by, check_part_gain, check_part_p, run, checks, eval });
    }
    // The refits' own noise, in every scope with a candidate: rule (b).
    if config.refit_noise {
        for reference in references.iter_mut().filter(|r| r.run.is_some()) {
            if fits.iter().any(|f| scope_of(f.extension) == reference.scope) {
                fitting.fit_reseeded(reference, out_dir, comm, progress)?;
            }
        }
    }

    // 5. The decision on the evaluation part, each candidate against the
    // reference of its scope, over the objects every model measures.
    let eval_object_units: Vec<usize> = (0..parts.eval.objects().len()).map(|o| parts.eval.object_units(o)).collect();
    let (eval_imprecise, set_aside) = if config.set_aside_unmeasured {
        refine_unmeasured(parts.eval, &base.params, &mut references, &mut fits, config, progress)?
    } else {
        (Vec::new(), Vec::new())
    };
    if !set_aside.is_empty() {
        for reference in &mut references {
            reference.eval = reference.eval.without(&set_aside, &eval_object_units);
            if let Some((_, again)) = &mut reference.reseeded_run {
                *again = again.without(&set_aside, &eval_object_units);
            }
        }
        for f in &mut fits {
            f.eval = f.eval.without(&set_aside, &eval_object_units);
        }
    }
    // The reseeded refits' gains over the objects kept, refined ones included.
    for reference in &mut references {
        reference.reseeded =
            reference.reseeded_run.as_ref().map(|(run, again)| ReseededReport::new(run, again, &reference.eval));
    }
    let measured = |o: &usize| set_aside.binary_search(o).is_err();
    let reference_of = |extension: Extension| Reference::of_scope(&references, scope_of(extension));
    let reference_eval = &references[0].eval;
    let object_gains: Vec<Vec<f64>> =
        fits.iter().map(|f| differences(&f.eval.object_ll, &reference_of(f.extension).eval.object_ll)).collect();
    let check_part_ps: Vec<Option<f64>> = fits.iter().map(|f| f.check_part_p).collect();
    let (p_values, adjusted, family) = reference_tests(&object_gains, &check_part_ps, config);
    let gains: Vec<&[f64]> = object_gains.iter().map(Vec::as_slice).collect();
    let reseeded_gains: Option<Vec<&[f64]>> =
        fits.iter().map(|f| reference_of(f.extension).reseeded.as_ref().map(|r| r.object_gains.as_slice())).collect();
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
    let winner = choose(&candidates, |_, c| c.qualifies);

    // 6. The outcome, and the checks after.
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
    let units = reference_eval.units.max(1) as f64;
    let base_mll = reference_eval.object_ll.iter().sum::<f64>() / units;
    Ok(Report {
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
        kind,
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
        eval_object_units: eval_object_units.iter().enumerate().filter(|(o, _)| measured(o)).map(|(_, u)| *u).collect(),
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
    })
}
