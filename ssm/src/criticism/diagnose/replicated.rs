//! Replicated checks: paths drawn from a fitted model's smoother, their measured
//! observations beside observations and actions replicated from the model, and
//! the discrepancy statistics of both (posterior predictive checks).

use rand::rngs::SmallRng;
use rand::SeedableRng;

use super::config::Evaluation;
use crate::criticism::checks::statistics;
use crate::criticism::ObjectSample;
use crate::data::{Action, Dataset, State};
use crate::filter::paths::PathRecorder;
use crate::filter::{run_filter, stream_seed};
use crate::models::extended::{ExtendedSsm, ExtensibleObservation, ObjectObservations};
use crate::models::vehicle::GaussianPolicy;
use crate::models::ParticleModel;

/// What one model's checks measured on the check part.
pub(super) struct ModelChecks {
    /// `measured[k][c]`: statistic `c` of draw `k` on the measured data.
    pub(super) measured: Vec<Vec<f64>>,
    /// `replicated[k][c]`: the same on replicated data.
    pub(super) replicated: Vec<Vec<f64>>,
}

impl ModelChecks {
    pub(super) fn draws_of(&self, c: usize) -> Vec<(f64, f64)> {
        self.measured.iter().zip(&self.replicated).map(|(m, r)| (m[c], r[c])).collect()
    }
}

/// Filters every object of `model`'s data once with the tempered filter, draws
/// [`Evaluation::draws`] paths per object from its smoother (the filter's genealogy),
/// and evaluates the checks' statistics on measured and replicated data per draw.
pub(super) fn posterior_predictive_checks<P: GaussianPolicy, O: ExtensibleObservation>(
    model: &ExtendedSsm<'_, '_, P, O>,
    eval: &Evaluation,
) -> ModelChecks {
    let (draws, seed) = (eval.draws, eval.seed);
    let steps = ParticleModel::num_steps(model);
    let run = run_filter(model, &eval.filter(0), |object| {
        PathRecorder::new(steps, draws, stream_seed(seed ^ 0xd1a6, object as u64))
    });
    let data = model.data();
    let mut measured = Vec::with_capacity(draws);
    let mut replicated = Vec::with_capacity(draws);
    for k in 0..draws {
        let mut rng = SmallRng::seed_from_u64(stream_seed(seed ^ 0x7e71, k as u64));
        let real: Vec<ObjectSample> = run
            .observers
            .iter()
            .enumerate()
            .map(|(o, rec)| {
                let (states, actions) = &rec.paths[k];
                ObjectSample {
                    object: o,
                    states: states.clone(),
                    actions: actions.clone(),
                    observations: measured_observations::<O>(data, o),
                    accel_innovations: innovations(model, states, actions),
                }
            })
            .collect();
        let rep: Vec<ObjectSample> = real.iter().map(|s| replicate(model, s, &mut rng)).collect();
        measured.push(statistics(data, &real));
        replicated.push(statistics(data, &rep));
    }
    ModelChecks { measured, replicated }
}

/// The dataset's observations of `object`.
pub(super) fn measured_observations<O: ExtensibleObservation>(data: &Dataset, object: usize) -> ObjectObservations {
    O::to_observations((0..data.steps()).map(|t| O::items(data, object, t).to_vec()).collect())
}

/// A replicate of `sample` from `model`: actions drawn from the policy at the
/// path's states, observations drawn at the path's states — except at `t = 0`,
/// where the state is drawn from the object's prior (the `initial_lag` check
/// compares the smoother's initial states with the prior's) and the observation
/// at that state.
pub(super) fn replicate<P: GaussianPolicy, O: ExtensibleObservation>(
    model: &ExtendedSsm<'_, '_, P, O>,
    sample: &ObjectSample,
    rng: &mut SmallRng,
) -> ObjectSample {
    let actions: Vec<Action> =
        sample.states[..sample.states.len() - 1].iter().map(|s| model.sample_action(s, rng)).collect();
    let mut states = sample.states.clone();
    states[0] = model.sample_initial_state(sample.object, rng);
    let per_step = model.sample_observations_along(sample.object, &states, rng);
    let accel_innovations = innovations(model, &sample.states, &actions);
    ObjectSample {
        object: sample.object,
        states,
        actions,
        observations: O::to_observations(per_step),
        accel_innovations,
    }
}

/// The standardised acceleration innovations of a path's actions.
pub(super) fn innovations<P: GaussianPolicy, O: ExtensibleObservation>(
    model: &ExtendedSsm<'_, '_, P, O>,
    states: &[State],
    actions: &[Action],
) -> Vec<f64> {
    states.iter().zip(actions).map(|(s, a)| model.accel_innovation_of(s, a)).collect()
}
