//! The interface between models and the particle filter: a batch of independent
//! objects, each a state-space model with its own observations, under fixed
//! parameters. The filter runs forward only (f32, no tape); estimators evaluate
//! the same model's log-densities on the tape through their own traits.
//!
//! Particle sets are stored dimension-major: for `n` particles of dimension `d`,
//! component `k` of particle `i` is `states[k * n + i]`, so every loop over
//! particles reads contiguous memory.

use rand::rngs::SmallRng;

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
