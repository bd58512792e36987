//! The road-user state-space model over a dataset, as a [`ParticleModel`]: each
//! object's known prior, a Gaussian policy with the exact motion model as the
//! transition, and an observation model (points or boxes) seen from the AV.

use autodiff::nn::{BoundParams, ParamStore};
use autodiff::{Float, Tensor, Var};
use rand::rngs::SmallRng;
use rand::Rng;
use rand_distr::StandardNormal;

use crate::data::{Dataset, Pose};
use crate::models::observation::{ObsContext, ObservationModel, PosesRef, RowVars, Scratch};
use crate::models::vehicle::motion::MotionModel;
use crate::models::vehicle::policy::{ActionGaussians, GaussianPolicy};
use crate::models::vehicle::state::{
    ActionVars, ActionsMut, ActionsRef, StateVars, StatesMut, StatesRef, ACTION_DIM, STATE_DIM,
};
use crate::models::{block_rows, Block, DifferentiableModel};
use crate::models::{Batch, Drawn, ModelError, NoiseDims, ParticleModel};

/// Index of the heading among the state components `(x, y, yaw, v, kappa)`.
pub const YAW: usize = 2;

/// A dataset's objects under a policy and an observation model with given parameters.
pub struct VehicleSsm<'a, P: GaussianPolicy, O: ObservationModel> {
    data: &'a Dataset,
    motion: MotionModel,
    policy: &'a P,
    observation: &'a O,
    /// The observation network's parameters in f32, the filter's precision.
    observation_params: ParamStore<f32>,
    /// The same in f64, the master copy the estimators differentiate.
    observation_params64: ParamStore<f64>,
}

/// What the observation log-density of tape rows needs besides the states: per
/// row, the AV's pose, the observation and the object's extents.
pub(crate) struct ObservationRows<'a, I> {
    pub(crate) av: Vec<Pose>,
    pub(crate) items: Vec<&'a [I]>,
    pub(crate) length: Vec<f64>,
    pub(crate) width: Vec<f64>,
}

impl<I> ObservationRows<'_, I> {
    /// The rows' poses from `states` (components `x, y, yaw` tracked as given) with
    /// the extents as constants.
    pub(crate) fn vars<'t, F: Float>(&self, states: &[Var<'t, F>]) -> RowVars<'t, F> {
        let tape = states[0].tape();
        let constant = |v: &[f64]| tape.constant(Tensor::from_vec(v.iter().map(|&x| F::from_f64(x)).collect()));
        RowVars {
            x: states[0],
            y: states[1],
            yaw: states[YAW],
            length: constant(&self.length),
            width: constant(&self.width),
        }
    }
}

/// Per-thread working memory of [`VehicleSsm`].
pub struct VehicleScratch {
    pub(crate) observation: Scratch<f32>,
    pub(crate) gaussians: ActionGaussians<f32>,
}

impl<'a, P: GaussianPolicy, O: ObservationModel> VehicleSsm<'a, P, O> {
    /// The model of `data`'s objects. The motion model's time step is the dataset's.
    ///
    /// Fails if the dataset's observations are not of the kind `O` reads or its time
    /// step is not a valid motion-model step.
    pub fn new(
        data: &'a Dataset,
        policy: &'a P,
        observation: &'a O,
        observation_params: &ParamStore<f64>,
    ) -> Result<Self, ModelError> {
        if data.kind() != O::KIND {
            return Err(ModelError::KindMismatch { data: data.kind(), model: O::KIND });
        }
        let motion = MotionModel::new(data.dt(), Default::default())?;
        Ok(VehicleSsm {
            data,
            motion,
            policy,
            observation,
            observation_params: observation_params.cast(),
            observation_params64: observation_params.clone(),
        })
    }

    /// The dataset.
    pub fn data(&self) -> &'a Dataset {
        self.data
    }

    /// The context of `object`'s observation at step `t`: the AV's pose and the size.
    pub fn context(&self, object: usize, t: usize) -> ObsContext {
        let scene = &self.data.scenes()[self.data.object_scene(object)];
        ObsContext::of_object(scene.av[t], &self.data.objects()[object])
    }

    /// The motion model.
    pub fn motion(&self) -> &MotionModel {
        &self.motion
    }

    /// The policy.
    pub fn policy(&self) -> &'a P {
        self.policy
    }

    /// The observation model (a layout over [`VehicleSsm::observation_params`]).
    pub fn observation(&self) -> &'a O {
        self.observation
    }

    /// The observation network's parameters (f64 master copy).
    pub fn observation_params(&self) -> &ParamStore<f64> {
        &self.observation_params64
    }

    /// The same in f32, as the filter reads them.
    pub(crate) fn observation_params32(&self) -> &ParamStore<f32> {
        &self.observation_params
    }

    /// How many of [`DifferentiableModel::parameters`] are the policy's (they come first).
    pub fn policy_param_count(&self) -> usize {
        self.policy.parameters().len()
    }

    /// The observation network's parameters among the bound `params` of the tape methods.
    pub(crate) fn observation_params_on_tape<'t, F: Float>(&self, params: &[Var<'t, F>]) -> BoundParams<'t, F> {
        let np = self.policy_param_count();
        BoundParams::from_vars(params[np..np + self.observation_params64.len()].to_vec())
    }

    /// Per-row AV poses, observations and extents of `blocks`.
    pub(crate) fn observation_rows(&self, blocks: &[Block]) -> ObservationRows<'a, O::Item> {
        let rows = block_rows(blocks);
        let mut out = ObservationRows {
            av: Vec::with_capacity(rows),
            items: Vec::with_capacity(rows),
            length: Vec::with_capacity(rows),
            width: Vec::with_capacity(rows),
        };
        for b in blocks {
            let ctx = self.context(b.object, b.t);
            let its = O::items(self.data, b.object, b.t);
            for _ in 0..b.len {
                out.av.push(ctx.av);
                out.items.push(its);
                out.length.push(ctx.length);
                out.width.push(ctx.width);
            }
        }
        out
    }
}

impl<P: GaussianPolicy, O: ObservationModel> VehicleSsm<'_, P, O> {
    /// `x_t` from `x_{t-1}` (`prev`) by the actions `a = mu + L eps` of the policy
    /// at `prev`, with given standardised innovations `eps` (the acceleration's may
    /// come from a heavier-tailed law): writes `to`.
    pub(crate) fn propagate_with_innovations(
        &self,
        n: usize,
        prev: &[f32],
        [eps_accel, eps_pinch]: [&[f32]; 2],
        to: Drawn<'_>,
        scratch: &mut VehicleScratch,
    ) {
        self.propagate_by(n, prev, to, &mut scratch.gaussians, |g, actions| {
            g.actions_from_noise(eps_accel, eps_pinch, actions)
        });
    }

    /// `x_t` from `x_{t-1}` (`prev`) for `n` particles by actions that `draw`
    /// writes from the policy's Gaussians at `prev` (kept in `gaussians`); writes
    /// `to`. The one place
    /// the transition puts the policy and the motion model together.
    pub(crate) fn propagate_by(
        &self,
        n: usize,
        prev: &[f32],
        to: Drawn<'_>,
        gaussians: &mut ActionGaussians<f32>,
        draw: impl FnOnce(&ActionGaussians<f32>, ActionsMut<'_, f32>),
    ) {
        let from = states_ref(prev, n);
        gaussians.resize(n);
        self.policy.gaussians(from.v, from.kappa, gaussians);
        let (accel, pinch) = to.actions.split_at_mut(n);
        draw(gaussians, ActionsMut { accel, pinch: &mut pinch[..n] });
        let acts = ActionsRef { accel: &to.actions[..n], pinch: &to.actions[n..2 * n] };
        self.motion.propagate(from, acts, states_mut(to.next, n));
    }
}

pub(crate) fn states_ref(s: &[f32], n: usize) -> StatesRef<'_, f32> {
    StatesRef { x: &s[..n], y: &s[n..2 * n], yaw: &s[2 * n..3 * n], v: &s[3 * n..4 * n], kappa: &s[4 * n..5 * n] }
}

pub(crate) fn states_mut(s: &mut [f32], n: usize) -> StatesMut<'_, f32> {
    let (x, rest) = s.split_at_mut(n);
    let (y, rest) = rest.split_at_mut(n);
    let (yaw, rest) = rest.split_at_mut(n);
    let (v, kappa) = rest.split_at_mut(n);
    StatesMut { x, y, yaw, v, kappa: &mut kappa[..n] }
}

impl<P: GaussianPolicy, O: ObservationModel> ParticleModel for VehicleSsm<'_, P, O> {
    type Scratch = VehicleScratch;

    fn new_scratch(&self) -> VehicleScratch {
        VehicleScratch { observation: Scratch::new(), gaussians: ActionGaussians::default() }
    }

    fn state_dim(&self) -> usize {
        STATE_DIM
    }

    fn action_dim(&self) -> usize {
        ACTION_DIM
    }

    fn angular_dims(&self) -> &[usize] {
        &[YAW]
    }

    fn num_objects(&self) -> usize {
        self.data.objects().len()
    }

    fn stream_key(&self, object: usize) -> u64 {
        let o = &self.data.objects()[object];
        crate::util::seed::splitmix64(o.scene as u64 ^ 0x5ce4_e1d5) ^ o.id as u64
    }

    fn num_steps(&self) -> usize {
        self.data.steps()
    }

    fn sample_prior(&self, object: usize, n: usize, rng: &mut SmallRng, states: &mut [f32], _: &mut VehicleScratch) {
        let prior = self.data.objects()[object].prior;
        let (mean, sd) = (prior.mean.to_array(), prior.sd.to_array());
        for k in 0..STATE_DIM {
            for x in &mut states[k * n..(k + 1) * n] {
                *x = (mean[k] + sd[k] * rng.sample::<f64, _>(StandardNormal)) as f32;
            }
        }
    }

    fn propagate(&self, at: Batch, prev: &[f32], to: Drawn<'_>, rng: &mut SmallRng, scratch: &mut VehicleScratch) {
        self.propagate_by(at.n, prev, to, &mut scratch.gaussians, |g, actions| g.sample(rng, actions));
    }

    /// `x_0 = mu_0 + sd_0 z` per component; the action `a = mu + L z` of the policy.
    fn noise_dims(&self) -> Option<NoiseDims> {
        Some(NoiseDims { prior: STATE_DIM, transition: ACTION_DIM })
    }

    fn prior_from_noise(&self, object: usize, n: usize, noise: &[f32], states: &mut [f32], _: &mut VehicleScratch) {
        let prior = self.data.objects()[object].prior;
        let (mean, sd) = (prior.mean.to_array(), prior.sd.to_array());
        for k in 0..STATE_DIM {
            let z = &noise[k * n..(k + 1) * n];
            for (x, &z) in states[k * n..(k + 1) * n].iter_mut().zip(z) {
                *x = (mean[k] + sd[k] * z as f64) as f32;
            }
        }
    }

    fn propagate_from_noise(&self, at: Batch, prev: &[f32], z: &[f32], to: Drawn<'_>, scratch: &mut VehicleScratch) {
        let n = at.n;
        self.propagate_with_innovations(n, prev, [&z[..n], &z[n..2 * n]], to, scratch);
    }

    fn observation_loglik(&self, at: Batch, states: &[f32], out: &mut [f32], scratch: &mut VehicleScratch) -> bool {
        let items = O::items(self.data, at.object, at.t);
        if items.is_empty() {
            return false;
        }
        let ctx = self.context(at.object, at.t);
        let poses = PosesRef::from_dim_major(states, at.n);
        self.observation.log_likelihood(&self.observation_params, &ctx, poses, items, &mut scratch.observation, out);
        true
    }

    fn observation_count(&self, object: usize, t: usize) -> usize {
        O::items(self.data, object, t).len()
    }
}

impl<P: GaussianPolicy, O: ObservationModel> DifferentiableModel for VehicleSsm<'_, P, O> {
    /// The policy's parameters, then the observation network's (store order).
    fn parameters(&self) -> Vec<Tensor<f64>> {
        let mut p = self.policy.parameters();
        p.extend(self.observation_params64.values().iter().cloned());
        p
    }

    fn parameter_names(&self) -> Vec<String> {
        let mut names = self.policy.parameter_names();
        names.extend(self.observation_params64.iter().map(|(n, _)| n.to_string()));
        names
    }

    fn observation_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        states: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let obs = self.observation_params_on_tape(params);
        let rows = self.observation_rows(blocks);
        self.observation.log_likelihood_rows(&obs, &rows.vars(states), &rows.av, &rows.items)
    }

    /// `log pi(a | x_{t-1})`: the motion model is deterministic and injective in
    /// the action, so this has the transition density's gradient.
    fn transition_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        _blocks: &[Block],
        prev: &[Var<'t, F>],
        _next: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let np = self.policy.parameters().len();
        let a = ActionVars { accel: actions[0], pinch: actions[1] };
        self.policy.log_density_on_tape(&params[..np], prev[3], prev[4], &a)
    }

    fn propagate_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        _blocks: &[Block],
        prev: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Vec<Var<'t, F>> {
        let np = self.policy.parameters().len();
        let g = self.policy.gaussians_on_tape(&params[..np], prev[3], prev[4]);
        // The recorded actions standardised at the current values, held constant.
        let a = g.reparameterised(&ActionVars { accel: actions[0], pinch: actions[1] });
        let s = StateVars { x: prev[0], y: prev[1], yaw: prev[YAW], v: prev[3], kappa: prev[4] };
        let next = self.motion.propagate_on_tape(&s, &a);
        vec![next.x, next.y, next.yaw, next.v, next.kappa]
    }
}
