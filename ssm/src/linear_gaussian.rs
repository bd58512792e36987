//! The linear-Gaussian model as a [`ParticleModel`]: a batch of independent
//! observation sequences under one [`Lgssm`]. With the Kalman filter's exact
//! likelihood and score it is the ground truth every filter and estimator is
//! tested against.

use rand::rngs::SmallRng;
use rand::Rng;
use rand_distr::StandardNormal;

use crate::lgssm::Lgssm;
use crate::model::ParticleModel;

/// Independent sequences `y_{0:T}` (one per object) under one linear-Gaussian model.
#[derive(Clone, Debug)]
pub struct LgssmBatch {
    /// The model (prior and parameters).
    pub model: Lgssm,
    sequences: Vec<Vec<f64>>,
}

impl LgssmBatch {
    /// A batch of sequences, which must all have the same (non-zero) length.
    pub fn new(model: Lgssm, sequences: Vec<Vec<f64>>) -> Result<Self, String> {
        let len = sequences.first().map(|s| s.len()).unwrap_or(0);
        if len == 0 || sequences.iter().any(|s| s.len() != len) {
            return Err("LgssmBatch: sequences must be non-empty and of equal length".into());
        }
        Ok(LgssmBatch { model, sequences })
    }

    /// The observations of one object.
    pub fn sequence(&self, object: usize) -> &[f64] {
        &self.sequences[object]
    }
}

impl ParticleModel for LgssmBatch {
    type Scratch = ();

    fn new_scratch(&self) {}

    fn state_dim(&self) -> usize {
        1
    }

    /// The standard-normal process noise `e_t` of `x_t = phi x_{t-1} + s_v e_t`.
    fn action_dim(&self) -> usize {
        1
    }

    fn num_objects(&self) -> usize {
        self.sequences.len()
    }

    fn num_steps(&self) -> usize {
        self.sequences[0].len()
    }

    fn sample_prior(&self, _object: usize, _n: usize, rng: &mut SmallRng, states: &mut [f32]) {
        self.model.sample_prior(rng, states);
    }

    fn propagate(
        &self,
        _object: usize,
        _t: usize,
        _n: usize,
        prev: &[f32],
        next: &mut [f32],
        actions: &mut [f32],
        rng: &mut SmallRng,
        _scratch: &mut (),
    ) {
        for e in actions.iter_mut() {
            *e = rng.sample::<f32, _>(StandardNormal);
        }
        next.copy_from_slice(prev);
        self.model.propagate_with_noise(actions, next);
    }

    fn observation_loglik(
        &self,
        object: usize,
        t: usize,
        _n: usize,
        states: &[f32],
        out: &mut [f32],
        _scratch: &mut (),
    ) -> bool {
        self.model.obs_log_density(self.sequences[object][t], states, out);
        true
    }

    fn observation_count(&self, _object: usize, _t: usize) -> usize {
        1
    }
}
