//! The interface between models and the particle filter: a batch of independent
//! objects, each a state-space model with its own observations, under fixed
//! parameters. The filter runs forward only (f32, no tape); estimators evaluate
//! the same model's log-densities on the tape through their own traits.
//!
//! Particle sets are stored dimension-major: for `n` particles of dimension `d`,
//! component `k` of particle `i` is `states[k * n + i]`, so every loop over
//! particles reads contiguous memory.

use rand::rngs::SmallRng;

/// Dimensions of the standard-normal noise that drives a model's draws (see
/// [`ParticleModel::noise_dims`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NoiseDims {
    /// Noise per particle of the initial state `x_0`.
    pub prior: usize,
    /// Noise per particle of one transition.
    pub transition: usize,
}

/// A batch of objects whose states a particle filter can track.
pub trait ParticleModel: Sync {
    /// Per-thread working memory (buffers, a non-recording tape), created once per
    /// worker and reused across objects and steps.
    type Scratch: Send;

    /// Fresh working memory.
    fn new_scratch(&self) -> Self::Scratch;

    /// Dimension of the state.
    fn state_dim(&self) -> usize;

    /// Dimension of what `propagate` records per particle (the vehicle's action; the
    /// linear-Gaussian model's process noise). May be 0.
    fn action_dim(&self) -> usize;

    /// State components that are angles (averaged as circular quantities).
    fn angular_dims(&self) -> &[usize] {
        &[]
    }

    /// Number of objects.
    fn num_objects(&self) -> usize;

    /// Number of steps, `T + 1` (steps are `0..=T`).
    fn num_steps(&self) -> usize;

    /// Draws `n` particles of `x_0` for `object` into `states` (`state_dim * n`).
    fn sample_prior(&self, object: usize, n: usize, rng: &mut SmallRng, states: &mut [f32]);

    /// Draws `x_t` given `x_{t-1}` for `n` particles: writes `next` (`state_dim * n`)
    /// and what was drawn into `actions` (`action_dim * n`).
    #[allow(clippy::too_many_arguments)]
    fn propagate(
        &self,
        object: usize,
        t: usize,
        n: usize,
        prev: &[f32],
        next: &mut [f32],
        actions: &mut [f32],
        rng: &mut SmallRng,
        scratch: &mut Self::Scratch,
    );

    /// For a model whose [`ParticleModel::propagate`] draws from a proposal `q`
    /// other than its transition `f` (to reach what the transition rarely does):
    /// writes `ln f(x_t | x_{t-1}) - ln q(x_t | x_{t-1})` for the `n` particles the
    /// last `propagate` with this `scratch` drew into `out` and returns `true`; the
    /// filter multiplies the weights by it. The default, for a `propagate` that
    /// draws from the transition, returns `false` and leaves `out` alone.
    fn proposal_log_weights(&self, n: usize, out: &mut [f32], scratch: &mut Self::Scratch) -> bool {
        let _ = (n, out, scratch);
        false
    }

    /// The noise-driven form of the model, if it has one: `x_0 = m_0(z_0)` and
    /// `x_t = m_t(x_{t-1}, z_t)` with `z` standard normal of these dimensions
    /// ([`ParticleModel::prior_from_noise`], [`ParticleModel::propagate_from_noise`]).
    /// A filter that moves particles by MCMC within a step (the tempered filter of
    /// [`crate::filter`]) works in this noise, where the prior and the transition are
    /// a standard normal whatever the model. `None` (the default): no such form.
    fn noise_dims(&self) -> Option<NoiseDims> {
        None
    }

    /// `x_0 = m_0(z)` for `n` particles from standard-normal `noise`
    /// (`noise_dims().prior * n`, dimension-major) into `states`: the same law as
    /// [`ParticleModel::sample_prior`].
    fn prior_from_noise(&self, object: usize, n: usize, noise: &[f32], states: &mut [f32]) {
        let _ = (object, n, noise, states);
        unimplemented!("prior_from_noise: this model has no noise-driven form (noise_dims is None)")
    }

    /// `x_t = m_t(x_{t-1}, z)` for `n` particles from standard-normal `noise`
    /// (`noise_dims().transition * n`, dimension-major): writes `next` and `actions`
    /// as [`ParticleModel::propagate`] does, with the same law (the transition,
    /// never a proposal).
    #[allow(clippy::too_many_arguments)]
    fn propagate_from_noise(
        &self,
        object: usize,
        t: usize,
        n: usize,
        prev: &[f32],
        noise: &[f32],
        next: &mut [f32],
        actions: &mut [f32],
        scratch: &mut Self::Scratch,
    ) {
        let _ = (object, t, n, prev, noise, next, actions, scratch);
        unimplemented!("propagate_from_noise: this model has no noise-driven form (noise_dims is None)")
    }

    /// Writes `log g(y_t | x_t^i)` for `n` particles into `out` and returns `true`, or
    /// returns `false` (leaving `out` alone) when there is no observation at `t`.
    fn observation_loglik(
        &self,
        object: usize,
        t: usize,
        n: usize,
        states: &[f32],
        out: &mut [f32],
        scratch: &mut Self::Scratch,
    ) -> bool;

    /// How many observed units (points, detections, scalars) `y_t` holds: the
    /// normaliser of per-point metrics.
    fn observation_count(&self, object: usize, t: usize) -> usize;
}
