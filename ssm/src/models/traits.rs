//! The model traits: what the particle filter needs of a model
//! ([`ParticleModel`]: a batch of independent objects, each a state-space model
//! with its own observations, under fixed parameters, run forward only in f32
//! without a tape) and what the score estimators need of it
//! ([`DifferentiableModel`]: the same model's log-densities on a tape, over rows
//! laid out in [`Block`]s).
//!
//! Particle sets are stored dimension-major: for `n` particles of dimension `d`,
//! component `k` of particle `i` is `states[k * n + i]`, so every loop over
//! particles reads contiguous memory.

use autodiff::{Float, Tape, Tensor, Var};
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

/// The `n` particles of `object` at step `t` that one [`ParticleModel`] call is
/// about.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Batch {
    /// The object.
    pub object: usize,
    /// The step.
    pub t: usize,
    /// Number of particles.
    pub n: usize,
}

/// Where a transition writes, both dimension-major: the states it reaches, `next`
/// (`state_dim * n`), and what it drew, `actions` (`action_dim * n`).
pub struct Drawn<'a> {
    /// The states `x_t`.
    pub next: &'a mut [f32],
    /// The actions (or process noise) that took `x_{t-1}` to `x_t`.
    pub actions: &'a mut [f32],
}

impl Drawn<'_> {
    /// The same buffers, borrowed again (to hand on to another model and keep).
    pub fn reborrow(&mut self) -> Drawn<'_> {
        Drawn { next: self.next, actions: self.actions }
    }
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

    /// The key of `object`'s random stream in the filter (with the filter's seed):
    /// its index by default. Models over a dataset key by the object's identity
    /// (scene and object id), so that an object gets the same draws in any subset
    /// of the data, whichever process or position holds it.
    fn stream_key(&self, object: usize) -> u64 {
        object as u64
    }

    /// Number of steps, `T + 1` (steps are `0..=T`).
    fn num_steps(&self) -> usize;

    /// Draws `n` particles of `x_0` for `object` into `states` (`state_dim * n`),
    /// with the same working memory as the transitions (a prior that looks at
    /// `y_0`, as a persistent flip's indicator does, needs it).
    fn sample_prior(
        &self,
        object: usize,
        n: usize,
        rng: &mut SmallRng,
        states: &mut [f32],
        scratch: &mut Self::Scratch,
    );

    /// Draws `x_t` given `x_{t-1}` (`prev`) for the `n` particles of `at`, into `to`.
    fn propagate(&self, at: Batch, prev: &[f32], to: Drawn<'_>, rng: &mut SmallRng, scratch: &mut Self::Scratch);

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
    fn prior_from_noise(
        &self,
        object: usize,
        n: usize,
        noise: &[f32],
        states: &mut [f32],
        scratch: &mut Self::Scratch,
    ) {
        let _ = (object, n, noise, states, scratch);
        unimplemented!("prior_from_noise: this model has no noise-driven form (noise_dims is None)")
    }

    /// `x_t = m_t(x_{t-1}, z)` for the `n` particles of `at` from standard-normal
    /// noise `z` (`noise_dims().transition * n`, dimension-major): writes `to` as
    /// [`ParticleModel::propagate`] does, with the same law (the transition, never a
    /// proposal).
    fn propagate_from_noise(&self, at: Batch, prev: &[f32], z: &[f32], to: Drawn<'_>, scratch: &mut Self::Scratch) {
        let _ = (at, prev, z, to, scratch);
        unimplemented!("propagate_from_noise: this model has no noise-driven form (noise_dims is None)")
    }

    /// Writes `log g(y_t | x_t^i)` for the `n` particles of `at` into `out` and
    /// returns `true`, or returns `false` (leaving `out` alone) when there is no
    /// observation at `t`.
    fn observation_loglik(&self, at: Batch, states: &[f32], out: &mut [f32], scratch: &mut Self::Scratch) -> bool;

    /// How many observed units (points, detections, scalars) `y_t` holds: the
    /// normaliser of per-point metrics.
    fn observation_count(&self, object: usize, t: usize) -> usize;
}

/// A run of consecutive rows on a tape that all belong to one object at one step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Block {
    /// The object.
    pub object: usize,
    /// The step.
    pub t: usize,
    /// Number of rows.
    pub len: usize,
}

/// Total rows of `blocks`.
pub fn block_rows(blocks: &[Block]) -> usize {
    blocks.iter().map(|b| b.len).sum()
}

/// A [`ParticleModel`] whose log-densities and transition can be evaluated on a
/// tape as functions of its parameters `theta`.
///
/// States and actions on the tape are dimension-major lists of `Var`s of shape
/// `[R]` (one per component) whose rows are laid out by `blocks`. The parameters
/// are a list of tensors ([`DifferentiableModel::parameters`]); the tape methods
/// take them as `Var`s in the same order, bound by the caller, so the caller
/// decides what is tracked.
pub trait DifferentiableModel: ParticleModel {
    /// The parameter tensors (an f64 master copy), in the order of the tape methods.
    fn parameters(&self) -> Vec<Tensor<f64>>;

    /// A name per parameter tensor (the names of a [`autodiff::nn::ParamStore`]).
    fn parameter_names(&self) -> Vec<String>;

    /// The parameters as tracked leaves of `tape`.
    fn bind<'t, F: Float>(&self, tape: &'t Tape<F>) -> Vec<Var<'t, F>> {
        self.parameters().iter().map(|p| tape.param(p.cast())).collect()
    }

    /// `log g(y_t | x)` per row (shape `[R]`). Every block must be at a step with an
    /// observation (`observation_count > 0`).
    fn observation_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        states: &[Var<'t, F>],
    ) -> Var<'t, F>;

    /// Whether the prior depends on the parameters, so that the score has a
    /// term at `t = 0` ([`DifferentiableModel::prior_log_density`]); `false`
    /// (the default) for a prior free of them, and the estimators then gather
    /// nothing for it.
    fn has_prior_term(&self) -> bool {
        false
    }

    /// `log p(x_0)` per row (shape `[R]`, blocks at `t = 0`), up to terms that
    /// do not depend on the parameters, for a model with
    /// [`DifferentiableModel::has_prior_term`]; `None` (the default) otherwise.
    fn prior_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        states: &[Var<'t, F>],
    ) -> Option<Var<'t, F>> {
        let _ = (params, blocks, states);
        None
    }

    /// The transition's log-density per row (shape `[R]`, blocks at `t >= 1`), up
    /// to terms that do not depend on the parameters: `log f(next | prev)`, or, for
    /// a deterministic injective motion model driven by actions, `log pi(a | prev)`
    /// (the paper's Lemma: same gradient).
    fn transition_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        prev: &[Var<'t, F>],
        next: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Var<'t, F>;

    /// The reparameterised transition: the states reached from `prev` by the
    /// recorded `actions` (constants), as functions of the parameters and of
    /// `prev`. The noise is the recorded actions standardised at the current
    /// values, held constant, so the values equal the filter's.
    fn propagate_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        prev: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Vec<Var<'t, F>>;
}
