//! The fits of a diagnosis: their schedules, their run directories and the training run
//! itself (resumed where one is found).

use std::path::Path;
use std::sync::Arc;

use autodiff::nn::ParamStore;

use crate::estimators::{Estimator, EstimatorConfig};
use crate::filter::Sampling;
use crate::models::extended::Extension;
use crate::training::objective::{ObjectiveConfig, SceneObjective};
use crate::training::{train_until, KeptBest, TrainConfig, TrainEvent, CHECKPOINT_FILE};
use crate::util::reduce::Collective;

use super::config::DiagnoseConfig;
use super::progress::Stage;
use super::split::Parts;

/// The sub-directories of a diagnosis's output that hold its training runs
/// (checkpoints, parameters, logs): the base fit, the base refitted alone, and
/// once more with another seed, one run per candidate, and the two refits of
/// the base within the dynamics scope ([`RefitScope::Dynamics`](crate::models::extended::RefitScope::Dynamics)). They serve only to resume an interrupted diagnosis;
/// `report.json` and the plots are what a finished one keeps.
pub const TRAINING_RUN_DIRS: [&str; 6] =
    ["base", "reference", "reference-reseeded", "candidates", "reference-dynamics", "reference-dynamics-reseeded"];

/// The training seed of the reseeded reference ([`DiagnoseConfig::refit_noise`])
/// is the diagnosis's seed with these bits flipped.
pub(super) const RESEED_BITS: u64 = 0x9e37_79b9_7f4a_7c15;

/// The values of `extension`'s own parameter in `params`, a store its fit
/// made (which always holds it).
pub(super) fn learned(params: &ParamStore<f64>, extension: Extension) -> &[f64] {
    params.get(params.id(&extension.param_name()).expect("a fitted extension's store holds its parameter")).data()
}

/// An extension's learned parameters `raw` in physical units, `(name, value, unit)`.
pub(super) fn natural_params(extension: Extension, raw: &[f64]) -> Result<Vec<(String, f64, String)>, String> {
    Ok(extension.natural(raw)?.into_iter().map(|(n, v, u)| (n.to_string(), v, u.to_string())).collect())
}

/// Training runs end at this fraction of the initial learning rate.
pub(super) const FINAL_LR_FRACTION: f64 = 0.1;

/// A finished training run.
pub(super) struct Fitted {
    pub(super) params: ParamStore<f64>,
    pub(super) skipped: usize,
    pub(super) seconds: f64,
    pub(super) kept: Option<KeptBest>,
    /// The step the fit paused after ([`FitSchedule::pause_at`]); `None` once it ended.
    pub(super) paused_at: Option<usize>,
}

/// How long and how fast one fit trains: `steps` at learning rate `lr` decaying
/// to a tenth, the base's parameters at `base_rate_factor` times it, if set;
/// paused after step `pause_at`, if set, to be resumed later on the same
/// schedule.
#[derive(Clone, Copy, Debug)]
pub(super) struct FitSchedule {
    pub(super) steps: usize,
    pub(super) lr: f64,
    pub(super) base_rate_factor: Option<f64>,
    pub(super) pause_at: Option<usize>,
}

impl FitSchedule {
    /// The base fit's, from scratch.
    pub(super) fn base(config: &DiagnoseConfig) -> Self {
        FitSchedule { steps: config.base_steps, lr: config.lr, base_rate_factor: None, pause_at: None }
    }

    /// Every refit's (the references' and the candidates'): the base's parameters
    /// at [`DiagnoseConfig::refit_base_lr`], an extension's at the candidate rate.
    pub(super) fn refit(config: &DiagnoseConfig) -> Self {
        let lr = config.candidate_lr;
        let base_rate_factor = config.refit_base_lr.map(|base| base / lr);
        FitSchedule { steps: config.candidate_steps, lr, base_rate_factor, pause_at: None }
    }

    /// The refit's, paused at the fitted screen's futility stop
    /// ([`DiagnoseConfig::screen_futility`]): the first evaluation at or after
    /// that share of its steps. `None` without the stop or where that is the end.
    pub(super) fn at_futility_stop(self, config: &DiagnoseConfig) -> Option<Self> {
        let every = config.keep_best_every;
        if config.screen_futility <= 0.0 || every == 0 {
            return None;
        }
        let share = (config.screen_futility * self.steps as f64).ceil() as usize;
        let step = share.div_ceil(every).max(1) * every;
        (step < self.steps).then_some(FitSchedule { pause_at: Some(step), ..self })
    }
}

/// The start of nesting `extension`'s fit from its nested extension's fit
/// ([`DiagnoseConfig::nesting_from_nested`]): `own_start` (the base and the
/// extension's start from the checks) with every base parameter as that fit left
/// it (`nested_params`), and the extension's own values from
/// [`Extension::start_from_nested`].
pub(super) fn start_from_nested(
    extension: Extension,
    own_start: ParamStore<f64>,
    nested_params: &ParamStore<f64>,
) -> Result<ParamStore<f64>, String> {
    let nested = extension.nests().ok_or_else(|| format!("{} does not nest another extension", extension.id()))?;
    let (own_name, nested_name) = (extension.param_name(), nested.param_name());
    let missing = |name: &str| format!("{}: no parameter `{name}` to start from", extension.id());
    let own = own_start.id(&own_name).ok_or_else(|| missing(&own_name))?;
    let nested_values = nested_params.id(&nested_name).ok_or_else(|| missing(&nested_name))?;
    let values = extension
        .start_from_nested(nested_params.get(nested_values).data(), own_start.get(own))
        .ok_or_else(|| format!("{}: `{nested_name}` is not {}'s values", extension.id(), nested.id()))?;
    let mut start = own_start;
    start.copy_matching(nested_params);
    *start.get_mut(own) = values;
    Ok(start)
}

/// Trains `initial` (with `extension`, if any) by PF-SEFI on `schedule`, the
/// parameters named in `held` kept at their values, in `dir`, resuming a run
/// found there, as one process of `comm` holding its share of the fit part's
/// objects.
#[allow(clippy::too_many_arguments)]
pub(super) fn fit(
    parts: Parts<'_>,
    extension: Option<Extension>,
    initial: ParamStore<f64>,
    schedule: FitSchedule,
    held: &[String],
    config: &DiagnoseConfig,
    dir: &Path,
    comm: &Arc<dyn Collective>,
    progress: &mut dyn FnMut(&Stage),
) -> Result<Fitted, String> {
    let train_tempering = config.train_tempered.then_some(config.train_tempering());
    let objective_config = ObjectiveConfig {
        estimator: Estimator::pf_sefi(config.lag),
        estimator_config: EstimatorConfig::new(Sampling::new(config.particles, train_tempering)),
        scenes_per_step: config.scenes_per_step,
        // The check part's evaluations rank the fit's own steps
        // (`keep_best_every`) by differences as small as an extension's gain:
        // the evaluation filter's particles, with one seed for every step
        // (`training::eval_seed`). At 256 particles and a seed per step, one
        // parameter set's evaluations differed by 0.005 to 0.01 nats per point.
        eval_particles: config.eval_particles,
        extension,
        extension_only: extension.is_some() && !config.refit,
        frozen: held.to_vec(),
        base_rate_factor: schedule.base_rate_factor,
        proposal: None,
        eval_tempering: train_tempering,
    };
    let mut objective = SceneObjective::for_process(parts.fit, parts.check.clone(), objective_config, comm.clone())?;
    let batches = crate::training::Objective::batches(&objective).max(1);
    let train_config = TrainConfig {
        lr: schedule.lr,
        final_lr: Some(schedule.lr * FINAL_LR_FRACTION),
        clip: config.clip,
        epochs: schedule.steps.div_ceil(batches),
        eval_every: config.keep_best_every,
        checkpoint_every: 25,
        seed: config.seed,
        shuffle: true,
        keep_best: (config.keep_best_every > 0).then(|| crate::training::objective::TEST_MLL.to_string()),
        average_tail: config.average_tail,
    };
    // `base`, `reference` or the extension's id: the run's directory names it.
    let model = dir.file_name().map_or_else(|| "base".to_string(), |n| n.to_string_lossy().into_owned());
    let resume = dir.join(CHECKPOINT_FILE).exists();
    let mut total = 0;
    let mut on_event = |e: &TrainEvent| match e {
        TrainEvent::Started { total_steps, .. } => total = *total_steps,
        TrainEvent::Step { step, .. } => progress(&Stage::Training { model: model.clone(), step: *step, total }),
        _ => {}
    };
    let outcome = train_until(&mut objective, initial, &train_config, dir, resume, schedule.pause_at, &mut on_event)
        .map_err(|e| format!("training the {model} model in {}: {e}", dir.display()))?;
    Ok(Fitted {
        params: outcome.params,
        skipped: outcome.skipped_steps,
        seconds: outcome.seconds,
        kept: outcome.kept,
        paused_at: outcome.paused_at,
    })
}

#[cfg(test)]
mod tests {
    use autodiff::Tensor;

    use super::*;

    /// A nesting extension started from its nested fit: every base parameter
    /// and the fraction as that fit left them, the persistence its own start;
    /// an extension that does not nest the other is refused.
    #[test]
    fn a_nesting_fit_starts_where_its_nested_fit_ended() {
        let (chain, flips) = (Extension::PersistentFlip, Extension::HeadingFlip);
        let mut own = ParamStore::new();
        own.add("policy.0.w", Tensor::from_vec(vec![1.0, 2.0]));
        own.add(&chain.param_name(), chain.stored(&[0.1, 0.7]).map(Tensor::from_vec).unwrap());
        let mut nested = ParamStore::new();
        nested.add("policy.0.w", Tensor::from_vec(vec![3.0, 4.0]));
        nested.add(&flips.param_name(), flips.stored(&[0.4]).map(Tensor::from_vec).unwrap());
        let start = start_from_nested(chain, own.clone(), &nested).unwrap();
        assert_eq!(start.get(start.id("policy.0.w").unwrap()).data(), [3.0, 4.0]);
        assert!(start.id(&flips.param_name()).is_none(), "only the nesting extension's own values");
        let values = chain.natural(start.get(start.id(&chain.param_name()).unwrap()).data()).unwrap();
        assert!((values[0].1 - 0.4).abs() < 1e-9 && (values[1].1 - 0.7).abs() < 1e-9, "{values:?}");
        assert!(start_from_nested(flips, nested.clone(), &own).unwrap_err().contains("does not nest"));
    }

    /// The futility stop falls on the first evaluation at or after its share
    /// of a refit's steps, and not at all where that is the end, without
    /// evaluations or with a share of 0.
    #[test]
    fn the_futility_stop_falls_on_an_evaluation_before_the_end() {
        let stop = |futility: f64, steps: usize, every: usize| {
            let config = DiagnoseConfig {
                screen_futility: futility,
                candidate_steps: steps,
                keep_best_every: every,
                ..DiagnoseConfig::quick()
            };
            FitSchedule::refit(&config).at_futility_stop(&config).and_then(|s| s.pause_at)
        };
        assert_eq!(DiagnoseConfig::quick().screen_futility, 1.0 / 3.0);
        assert_eq!(stop(1.0 / 3.0, 150, 25), Some(50));
        assert_eq!(stop(1.0 / 3.0, 300, 25), Some(100));
        assert_eq!(stop(0.3, 12, 2), Some(4));
        assert_eq!(stop(0.01, 150, 25), Some(25));
        assert_eq!(stop(0.9, 150, 25), None);
        assert_eq!(stop(0.0, 150, 25), None);
        assert_eq!(stop(1.0 / 3.0, 150, 0), None);
        let bad = DiagnoseConfig { screen_futility: 1.0, ..DiagnoseConfig::quick() };
        assert!(bad.validate().unwrap_err().to_string().contains("screen_futility"));
        let blind = DiagnoseConfig { fitted_screen: true, keep_best_every: 0, ..DiagnoseConfig::quick() };
        assert!(blind.validate().unwrap_err().to_string().contains("keep_best_every"));
        assert!(DiagnoseConfig { screen_futility: 0.0, ..blind }.validate().is_ok());
    }
}
