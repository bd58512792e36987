//! The dispatch over the models of the data's kind: checks and held-out likelihoods of one
//! parameter store, with or without an extension.

use super::heldout::{likelihoods, EvalLikelihoods};
use super::replicated::{posterior_predictive_checks, ModelChecks};

use autodiff::nn::ParamStore;

use crate::data::Dataset;
use crate::models::extended::{ExtendedSsm, ExtensibleObservation, Extension};
use crate::models::params::{AnyPolicy, ModelVisitor, Models};
use crate::models::road_user::VehicleSsm;

use super::config::DiagnoseConfig;

/// Checks `params` (with `extension`) on `data` (see [`posterior_predictive_checks`]).
pub(super) fn check_model(
    data: &Dataset,
    params: &ParamStore<f64>,
    extension: Option<Extension>,
    config: &DiagnoseConfig,
) -> Result<ModelChecks, String> {
    match with_model(data, params, extension, config, Task::Checks)? {
        TaskOutput::Checks(c) => Ok(c),
        TaskOutput::Likelihoods(_) => unreachable!("a check task returns checks"),
    }
}

/// Filters every object of `data` under `params` (with `extension`)
/// [`DiagnoseConfig::eval_runs`] times with the tempered filter, seeds `seed..`
/// — the same for every model, so that two models' estimates are paired — and
/// averages each object's likelihood estimates (not their logs: each is
/// unbiased, so their mean is an estimate with `runs` times the particles).
pub(super) fn eval_likelihoods(
    data: &Dataset,
    params: &ParamStore<f64>,
    extension: Option<Extension>,
    config: &DiagnoseConfig,
) -> Result<EvalLikelihoods, String> {
    match with_model(data, params, extension, config, Task::Likelihoods)? {
        TaskOutput::Likelihoods(l) => Ok(l),
        TaskOutput::Checks(_) => unreachable!("a likelihood task returns likelihoods"),
    }
}

#[derive(Clone, Copy)]
pub(super) enum Task {
    Checks,
    Likelihoods,
}

pub(super) enum TaskOutput {
    Checks(ModelChecks),
    Likelihoods(EvalLikelihoods),
}

pub(super) fn with_model(
    data: &Dataset,
    params: &ParamStore<f64>,
    extension: Option<Extension>,
    config: &DiagnoseConfig,
    task: Task,
) -> Result<TaskOutput, String> {
    let models = Models::from_store(params, data.kind()).map_err(|e| e.to_string())?;
    models.visit(data, OnModel { params, extension, config, task })?
}

pub(super) struct OnModel<'a> {
    pub(super) params: &'a ParamStore<f64>,
    pub(super) extension: Option<Extension>,
    pub(super) config: &'a DiagnoseConfig,
    pub(super) task: Task,
}

impl ModelVisitor for OnModel<'_> {
    type Output = Result<TaskOutput, String>;
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) -> Self::Output {
        let model = ExtendedSsm::from_store(base, self.extension, self.params)?;
        if model.drift().is_some() {
            // Its replicates are drawn at states, which hold no drift.
            return Err("the criticism does not model a detector drift: diagnose parameters without one".into());
        }
        Ok(match self.task {
            Task::Checks => TaskOutput::Checks(posterior_predictive_checks(&model, &self.config.evaluation())),
            Task::Likelihoods => TaskOutput::Likelihoods(likelihoods(&model, &self.config.evaluation())?),
        })
    }
}

#[cfg(test)]
mod tests {
    use crate::data::ObservationKind;
    use crate::models::vehicle::NeuralPolicy;
    use rand::rngs::StdRng;
    use rand::SeedableRng;

    use super::*;
    use crate::filter::paths::PathRecorder;
    use crate::filter::run_filter;
    use crate::models::ParticleModel;

    /// Paths drawn from the tempered filter's genealogy follow the motion model
    /// step by step: the record of step `t - 1` is revised after the lookback
    /// moves of step `t`, so each path's states and actions agree.
    #[test]
    fn tempered_paths_follow_the_motion_model() {
        let data = crate::criticism::hidden::generate_hidden(&crate::criticism::hidden::HiddenConfig::quick(
            ObservationKind::Points,
            crate::criticism::hidden::HiddenEffect::None,
            2,
        ))
        .unwrap();
        let data = data.select_objects(&[0, 1, 2]);
        let mut rng = StdRng::seed_from_u64(4);
        let policy = AnyPolicy::Neural(NeuralPolicy::new(&mut rng));
        let params = Models::initial(data.kind(), policy, 5).to_store();
        let config = DiagnoseConfig { eval_particles: 128, draws: 5, ..DiagnoseConfig::quick() };
        let checks = check_model(&data, &params, None, &config).unwrap();
        assert_eq!(checks.measured.len(), 5);
        struct Paths<'c>(&'c DiagnoseConfig);
        impl ModelVisitor for Paths<'_> {
            type Output = f64;
            fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) -> f64 {
                let steps = ParticleModel::num_steps(base);
                let run = run_filter(base, &self.0.evaluation().filter(0), |o| PathRecorder::new(steps, 4, o as u64));
                let motion = base.motion();
                let mut worst: f64 = 0.0;
                for rec in &run.observers {
                    for (states, actions) in &rec.paths {
                        for t in 1..states.len() {
                            let (s, a) = (&states[t - 1], &actions[t - 1]);
                            let from = crate::models::vehicle::VehicleState {
                                x: s.x,
                                y: s.y,
                                yaw: s.yaw,
                                v: s.v,
                                kappa: s.kappa,
                            };
                            let action = crate::models::vehicle::Action { accel: a.accel, pinch: a.pinch };
                            let next = motion.step(&from, &action);
                            let to = &states[t];
                            worst =
                                worst.max((next.x - to.x).abs()).max((next.y - to.y).abs()).max((next.v - to.v).abs());
                        }
                    }
                }
                worst
            }
        }
        let models = Models::from_store(&params, data.kind()).unwrap();
        let worst: f64 = models.visit(&data, Paths(&config)).unwrap();
        assert!(worst < 1e-3, "a drawn path leaves the motion model by {worst}");
    }
}
