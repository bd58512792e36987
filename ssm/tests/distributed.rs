//! Data-parallel training steps, with the processes of a job simulated by
//! threads ([`ThreadGroup`]): whatever the number of processes, every process
//! gets the score one process computes on the whole data, bit for bit, for
//! PF-SEFI and a through-filter baseline, on point and box data; and the
//! processes' shares ([`owned_objects`]) split the training objects exactly.

use std::sync::Arc;

use autodiff::nn::ParamStore;
use rand::SeedableRng;
use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
use ssm::data::{Dataset, ObservationKind};
use ssm::estimators::{Estimator, EstimatorConfig};
use ssm::filter::Sampling;
use ssm::models::params::{AnyPolicy, Models};
use ssm::models::vehicle::{HandCraftedPolicy, NeuralPolicy};
use ssm::training::objective::{owned_objects, ObjectiveConfig, SceneObjective};
use ssm::training::Objective;
use ssm::util::reduce::ThreadGroup;

/// Every batch's log-likelihood and score, as bits, for one process of a job.
fn step_bits(objective: &mut SceneObjective, params: &ParamStore<f64>) -> Vec<Vec<u64>> {
    (0..objective.batches())
        .map(|b| {
            let e = objective.estimate(params, b, 11 + b as u64).expect("finite estimate");
            let mut bits = vec![e.log_likelihood.to_bits(), e.observed_units as u64];
            bits.extend(e.gradient.iter().flat_map(|g| g.data().iter().map(|x| x.to_bits())));
            bits
        })
        .collect()
}

fn config(estimator: Estimator, chunk_objects: usize, scenes_per_step: usize) -> ObjectiveConfig {
    ObjectiveConfig {
        estimator,
        estimator_config: EstimatorConfig {
            sampling: Sampling::new(24, None),
            chunk_objects,
            ..EstimatorConfig::default()
        },
        scenes_per_step,
        eval_particles: 16,
        extension: None,
        extension_only: false,
        frozen: Vec::new(),
        base_rate_factor: None,
        proposal: None,
        eval_tempering: None,
    }
}

/// Checks that the processes' shares split the objects, then runs every batch on
/// `size` simulated processes, each holding its share
/// ([`SceneObjective::for_process`]), and checks that every process gets
/// `expected`.
fn check_processes(data: &Dataset, params: &ParamStore<f64>, config: &ObjectiveConfig, expected: &[Vec<u64>]) {
    let layout = data.layout();
    for size in [2, 3, 5] {
        let shares: Vec<Vec<usize>> = (0..size).map(|rank| owned_objects(&layout, config, rank, size)).collect();
        let mut all: Vec<usize> = shares.concat();
        all.sort_unstable();
        assert_eq!(all, (0..data.objects().len()).collect::<Vec<_>>(), "{size} processes split the objects");
        let group = ThreadGroup::new(size);
        let answers: Vec<Vec<Vec<u64>>> = std::thread::scope(|scope| {
            let handles: Vec<_> = (0..size)
                .map(|rank| {
                    let comm = Arc::new(group.member(rank));
                    let config = config.clone();
                    scope.spawn(move || {
                        let mut objective = SceneObjective::for_process(data, data.clone(), config, comm).unwrap();
                        step_bits(&mut objective, params)
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for (rank, a) in answers.iter().enumerate() {
            assert!(a == expected, "{:?}, {size} processes: process {rank} differs", config.estimator);
        }
    }
}

#[test]
fn any_number_of_processes_gives_the_bits_of_one() {
    for (kind, seed) in [(ObservationKind::Points, 3), (ObservationKind::Boxes, 4)] {
        let data = generate_hidden(&HiddenConfig {
            scenes: 3,
            objects_per_scene: 5,
            steps: 5,
            ..HiddenConfig::quick(kind, HiddenEffect::None, seed)
        })
        .unwrap();
        let policy = match kind {
            ObservationKind::Points => AnyPolicy::HandCrafted(HandCraftedPolicy::new(0.0, 0.1f64.ln()).unwrap()),
            ObservationKind::Boxes => {
                AnyPolicy::Neural(NeuralPolicy::new(&mut rand::rngs::StdRng::seed_from_u64(seed)))
            }
        };
        let params = Models::initial(kind, policy, seed).to_store();
        for (estimator, chunk, per_step) in [(Estimator::pf_sefi(2), 2, 2), (Estimator::dpf_sgr(), 3, 1)] {
            let config = config(estimator, chunk, per_step);
            let mut whole = SceneObjective::new(&data, data.clone(), config.clone()).unwrap();
            let expected = step_bits(&mut whole, &params);
            check_processes(&data, &params, &config, &expected);
        }
    }
}
