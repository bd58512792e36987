//! The references a candidate is compared with: the base refitted alone within a refit scope,
//! and its reseeded twin (the refits' own noise).

use super::heldout::{differences, gain_of, EvalLikelihoods};

use std::path::Path;
use std::sync::Arc;

use autodiff::nn::ParamStore;

use crate::criticism::checks::{calibrate, CheckDef, CheckResult};
use crate::models::extended::RefitScope;
use crate::util::reduce::Collective;

use super::config::DiagnoseConfig;
use super::dispatch::{check_model, eval_likelihoods};
use super::fits::{fit, FitSchedule, Fitted, RESEED_BITS, TRAINING_RUN_DIRS};
use super::progress::Stage;
use super::report::{ReferenceReport, ReseededReport};
use super::split::Parts;

impl ReseededReport {
    /// The refit `run`, whose likelihoods are `again`, against the reference's
    /// likelihoods `reference`, paired by object.
    pub(super) fn new(run: &Fitted, again: &EvalLikelihoods, reference: &EvalLikelihoods) -> ReseededReport {
        let object_gains = differences(&again.object_ll, &reference.object_ll);
        let (gain, gain_se) = gain_of(&object_gains, reference.units);
        ReseededReport {
            gain,
            gain_se,
            object_gains,
            object_mc_sd: again.object_mc_sd.clone(),
            train_seconds: run.seconds,
            skipped_steps: run.skipped,
            kept: run.kept.clone(),
        }
    }
}

/// What the candidates of one refit scope are compared with: the base
/// refitted alone within that scope, or the base itself (nothing refitted).
pub(super) struct Reference {
    pub(super) scope: RefitScope,
    /// The refit (`None` where the base is the reference).
    pub(super) run: Option<Fitted>,
    /// Every check calibrated on it (the check part).
    pub(super) checks: Vec<CheckResult>,
    /// Its likelihoods on the evaluation part.
    pub(super) eval: EvalLikelihoods,
    /// The same refit with another training seed ([`DiagnoseConfig::refit_noise`])
    /// and its likelihoods on the evaluation part.
    pub(super) reseeded_run: Option<(Fitted, EvalLikelihoods)>,
    /// Its comparison with this reference, made in step 5 over the objects
    /// kept ([`DiagnoseConfig::set_aside_unmeasured`]).
    pub(super) reseeded: Option<ReseededReport>,
    /// Its likelihoods on the check part, where a candidate of its scope was
    /// admitted by the likelihood screen (rule (d) for it).
    pub(super) on_check: Option<EvalLikelihoods>,
}

impl Reference {
    /// The reference of `scope` among `references` (the first where none is of it).
    pub(super) fn of_scope(references: &[Reference], scope: RefitScope) -> &Reference {
        references.iter().find(|r| r.scope == scope).unwrap_or(&references[0])
    }

    /// Its part of the report (`None` for the base).
    pub(super) fn report(&self) -> Option<ReferenceReport> {
        self.run.as_ref().map(|run| ReferenceReport {
            checks: self.checks.clone(),
            train_seconds: run.seconds,
            skipped_steps: run.skipped,
            kept: run.kept.clone(),
            reseeded: self.reseeded.clone(),
            object_mc_sd: self.eval.object_mc_sd.clone(),
        })
    }
}

/// Refits the base alone within a scope ([`ReferenceFit::fit`]).
pub(super) struct ReferenceFit<'a> {
    pub(super) parts: Parts<'a>,
    pub(super) base: &'a ParamStore<f64>,
    pub(super) schedule: FitSchedule,
    pub(super) defs: &'a [&'static CheckDef],
    pub(super) config: &'a DiagnoseConfig,
}

impl ReferenceFit<'_> {
    /// The base refitted alone within `scope` (in the scope's directory under
    /// `out_dir`, resuming a run found there), checked and evaluated; filtered
    /// on the check part too where a `screened` candidate of the scope needs
    /// it. Its reseeded twin is fitted later, where a candidate of the scope is
    /// evaluated ([`ReferenceFit::fit_reseeded`]).
    pub(super) fn fit(
        &self,
        scope: RefitScope,
        screened: bool,
        out_dir: &Path,
        comm: &Arc<dyn Collective>,
        progress: &mut dyn FnMut(&Stage),
    ) -> Result<Reference, String> {
        let (parts, config) = (self.parts, self.config);
        let dir = reference_dirs(scope)[0];
        let held = scope.held(self.base);
        let run =
            fit(parts, None, self.base.clone(), self.schedule, &held, config, &out_dir.join(dir), comm, progress)?;
        progress(&Stage::Checking { model: dir.into() });
        let checks = check_model(parts.check, &run.params, None, config)?;
        let checks = calibrate(self.defs, &checks.measured, &checks.replicated, config.alpha);
        progress(&Stage::Evaluating { model: dir.into() });
        let eval = eval_likelihoods(parts.eval, &run.params, None, config)?;
        let on_check = if screened { Some(eval_likelihoods(parts.check, &run.params, None, config)?) } else { None };
        Ok(Reference { scope, run: Some(run), checks, eval, reseeded_run: None, reseeded: None, on_check })
    }

    /// The refits' own noise ([`DiagnoseConfig::refit_noise`]): the base
    /// refitted alone within `reference`'s scope once more, with another
    /// training seed (in the scope's reseeded directory, resuming a run found
    /// there), and evaluated, into `reference.reseeded_run`.
    pub(super) fn fit_reseeded(
        &self,
        reference: &mut Reference,
        out_dir: &Path,
        comm: &Arc<dyn Collective>,
        progress: &mut dyn FnMut(&Stage),
    ) -> Result<(), String> {
        let (parts, config) = (self.parts, self.config);
        let reseeded_dir = reference_dirs(reference.scope)[1];
        let held = reference.scope.held(self.base);
        let reseeded_config = DiagnoseConfig { seed: config.seed ^ RESEED_BITS, ..config.clone() };
        let dir = out_dir.join(reseeded_dir);
        let again = fit(parts, None, self.base.clone(), self.schedule, &held, &reseeded_config, &dir, comm, progress)?;
        progress(&Stage::Evaluating { model: reseeded_dir.into() });
        let again_eval = eval_likelihoods(parts.eval, &again.params, None, config)?;
        reference.reseeded_run = Some((again, again_eval));
        Ok(())
    }
}

/// The directories of a scope's reference and reseeded reference: those of
/// [`TRAINING_RUN_DIRS`] for [`RefitScope::All`], `reference-dynamics` and
/// `reference-dynamics-reseeded` for [`RefitScope::Dynamics`].
pub(super) fn reference_dirs(scope: RefitScope) -> [&'static str; 2] {
    match scope {
        RefitScope::All => [TRAINING_RUN_DIRS[1], TRAINING_RUN_DIRS[2]],
        RefitScope::Dynamics => [TRAINING_RUN_DIRS[4], TRAINING_RUN_DIRS[5]],
    }
}
