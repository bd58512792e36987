//! The linear-Gaussian model as a [`ParticleModel`]: a batch of independent
//! observation sequences under one [`Lgssm`]. With the Kalman filter's exact
//! likelihood and score it is the ground truth every filter and estimator is
//! tested against.

use autodiff::dist::normal_logpdf;
use autodiff::{Float, Tensor, Var};
use rand::rngs::SmallRng;
use rand::Rng;
use rand_distr::StandardNormal;

use crate::models::linear_gaussian::kalman::{Lgssm, ThetaVars};
use crate::models::{Batch, Drawn, ModelError, NoiseDims, ParticleModel};
use crate::models::{Block, DifferentiableModel};

/// The name of the model's one parameter tensor `[phi, ln s_v, ln s_w]`.
pub const THETA_PARAM: &str = "theta";

/// Independent sequences `y_{0:T}` (one per object) under one linear-Gaussian model.
#[derive(Clone, Debug)]
pub struct LgssmBatch {
    /// The model (prior and parameters).
    pub model: Lgssm,
    sequences: Vec<Vec<f64>>,
}

impl LgssmBatch {
    /// A batch of sequences, which must all have the same (non-zero) length.
    pub fn new(model: Lgssm, sequences: Vec<Vec<f64>>) -> Result<Self, ModelError> {
        let len = sequences.first().map(|s| s.len()).unwrap_or(0);
        if len == 0 || sequences.iter().any(|s| s.len() != len) {
            return Err(ModelError::UnequalSequences);
        }
        Ok(LgssmBatch { model, sequences })
    }

    /// The same sequences under other parameters.
    pub fn with_model(&self, model: Lgssm) -> Self {
        LgssmBatch { model, sequences: self.sequences.clone() }
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

    fn sample_prior(&self, _object: usize, _n: usize, rng: &mut SmallRng, states: &mut [f32], _scratch: &mut ()) {
        self.model.sample_prior(rng, states);
    }

    fn propagate(&self, _at: Batch, prev: &[f32], to: Drawn<'_>, rng: &mut SmallRng, _scratch: &mut ()) {
        for e in to.actions.iter_mut() {
            *e = rng.sample::<f32, _>(StandardNormal);
        }
        to.next.copy_from_slice(prev);
        self.model.propagate_with_noise(to.actions, to.next);
    }

    /// `x_0 = m_0 + sqrt(P_0) z` and `x_t = phi x_{t-1} + s_v z`.
    fn noise_dims(&self) -> Option<NoiseDims> {
        Some(NoiseDims { prior: 1, transition: 1 })
    }

    fn prior_from_noise(&self, _object: usize, _n: usize, noise: &[f32], states: &mut [f32], _scratch: &mut ()) {
        self.model.prior_from_noise(noise, states);
    }

    fn propagate_from_noise(&self, _at: Batch, prev: &[f32], z: &[f32], to: Drawn<'_>, _scratch: &mut ()) {
        to.actions.copy_from_slice(z);
        to.next.copy_from_slice(prev);
        self.model.propagate_with_noise(z, to.next);
    }

    fn observation_loglik(&self, at: Batch, states: &[f32], out: &mut [f32], _scratch: &mut ()) -> bool {
        self.model.obs_log_density(self.sequences[at.object][at.t], states, out);
        true
    }

    fn observation_count(&self, _object: usize, _t: usize) -> usize {
        1
    }
}

impl DifferentiableModel for LgssmBatch {
    /// One tensor `[phi, ln s_v, ln s_w]` (shape `[3]`).
    fn parameters(&self) -> Vec<Tensor<f64>> {
        vec![Tensor::from_f64s(&[3], &self.model.theta().to_array())]
    }

    fn parameter_names(&self) -> Vec<String> {
        vec![THETA_PARAM.to_string()]
    }

    fn observation_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        states: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let theta = ThetaVars::from_vector(params[0]);
        let ys: Vec<F> = blocks
            .iter()
            .flat_map(|b| std::iter::repeat_n(F::from_f64(self.sequences[b.object][b.t]), b.len))
            .collect();
        let tape = states[0].tape();
        normal_logpdf(states[0], tape.constant(Tensor::from_vec(ys)), theta.log_sw)
    }

    fn transition_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        _blocks: &[Block],
        prev: &[Var<'t, F>],
        next: &[Var<'t, F>],
        _actions: &[Var<'t, F>],
    ) -> Var<'t, F> {
        ThetaVars::from_vector(params[0]).transition_log_density(prev[0], next[0])
    }

    /// `x_t = phi x_{t-1} + s_v e_t` with the recorded noise `e_t` (the action).
    fn propagate_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        _blocks: &[Block],
        prev: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Vec<Var<'t, F>> {
        vec![ThetaVars::from_vector(params[0]).propagate(prev[0], actions[0])]
    }
}
