//! The paper's synthetic data (SPEC §4): scenes with an AV and objects around it
//! that follow the hand-crafted policy and the exact motion model, observed as
//! point sets drawn from a "true" observation network.
//!
//! # How the data are made
//!
//! 1. **The true observation network** is obtained as the paper did: the point
//!    network ([`PointObservationModel`]) is fitted by maximum AOTLL
//!    ([`fit_network`]) to labelled examples of the physically motivated
//!    [`PointGenerator`] ([`random_point_examples`]). Its quality is reported as
//!    the AOTLL of held-out generator examples ([`fit_true_model`]).
//! 2. **The AV** starts at the origin heading along +x and drives straight at a
//!    constant speed ([`SceneConfig::av_speed`], 5 m/s by default; 0 parks it).
//!    Its pose at every step is known (`av.csv`).
//! 3. **Each object** gets a length and width drawn uniformly (car-sized) and a
//!    diagonal Gaussian prior `mu` of its initial state: the mean's position is at
//!    a uniform range in [`SceneConfig::range`] (5–50 m) and uniform bearing from
//!    the AV's initial position, with a uniform heading, a speed uniform in
//!    [`SceneConfig::speed`] (4–12 m/s) and a curvature uniform in
//!    `±`[`SceneConfig::max_kappa`] (0.02 1/m, a 50 m radius at most); the sds are
//!    [`SceneConfig::prior_sd`] (0.5 m, 0.5 m, 0.1 rad, 1 m/s, 0.01 1/m). The true
//!    `x_0` is drawn from that prior.
//! 4. **Dynamics**: for `t = 1..=T` the action `a_t` is drawn from the
//!    [`HandCraftedPolicy`] at its true parameters (sds 0.5 m/s² and 0.02
//!    1/(m s)) given `x_{t-1}`, and `x_t` is the exact [`MotionModel`] step
//!    (cubic yaw, 8-node Gauss–Legendre), `dt = 1/3 s`.
//! 5. **Observations**: at every step `t = 0..=T` the number of points is drawn
//!    from the generator's count model — Poisson with mean
//!    [`PointGenerator::mean_count`] at the object's range from the AV (300 / r,
//!    capped at 40), so it decreases with range — and the points themselves are
//!    drawn from the *true network* with [`ObservationModel::sample`].
//!
//! Nothing is clipped. The prior mean speeds (>= 4 m/s, sd 1 m/s) and the policy
//! (mean acceleration +1.45 m/s² at standstill) make negative speeds very rare;
//! should the policy drive a speed below zero, the vehicle reverses as the motion
//! model says, and [`SyntheticSummary::negative_speeds`] counts such states.
//! Objects move freely (random headings): over `T` steps many leave the 5–50 m
//! ring, are seen from further away, and receive fewer points; the true network is
//! therefore fitted over a wider range of ranges ([`TruthConfig::ranges`], 2–250 m)
//! than the initial ring. Objects do not avoid each other or the AV: one may pass
//! through the AV's position (ranges below 1 m occur; the count is then capped at
//! 40).
//!
//! # Reproducibility
//!
//! Everything is drawn from the caller's random number generator in a fixed order;
//! each scene draws from its own [`StdRng`] seeded from that generator, so the same
//! seed gives the same data, bit for bit, regardless of thread count.
//!
//! ```
//! use rand::{rngs::StdRng, SeedableRng};
//! use ssm::simulation::synthetic::{generate_experiment, Experiment, ExperimentConfig};
//!
//! let config = ExperimentConfig::quick(Experiment::A);
//! let data = generate_experiment(&config, &mut StdRng::seed_from_u64(7), &mut |_| {}).unwrap();
//! assert_eq!(data.train.scenes().len(), config.train_scenes);
//! assert_eq!(data.train.steps(), config.scene.steps);
//! assert!(data.train.states().unwrap().is_complete());
//! ```

use std::f64::consts::TAU;
use std::fmt;
use std::path::Path;
use std::str::FromStr;

use autodiff::nn::{ParamError, ParamStore};
use autodiff::Tensor;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Poisson, StandardNormal};

use crate::data::{Action, DataError, Dataset, DatasetBuilder, Meta, Object, ObservationKind, Pose, Prior, State};
use crate::models::observation::{
    aotll, fit_network, random_point_examples, FitConfig, FitReport, ObsContext, ObservationModel, PointGenerator,
    PointObservationModel, SceneRanges, OBS_PREFIX,
};
use crate::models::vehicle::{
    Action as VAction, ActionGaussians, GaussianPolicy, HandCraftedPolicy, MotionModel, Quadrature, VehicleState,
    DEFAULT_DT,
};

/// Name of the hand-crafted policy's parameter (shape `[2]`: log sd of accel,
/// log sd of pinch) in a [`TrueModel`]'s store.
pub const POLICY_LOG_SD: &str = "policy.log_sd";

/// Why a configuration or a generation was rejected.
#[derive(Debug)]
pub enum SyntheticError {
    /// A setting is out of range (which, and why).
    Config(String),
    /// The generated records did not form a valid dataset (a bug if it happens).
    Data(DataError),
    /// A true-parameter file could not be read or does not hold a true model.
    Params(String),
}

impl fmt::Display for SyntheticError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SyntheticError::Config(m) => write!(f, "synthetic data settings: {m}"),
            SyntheticError::Data(e) => write!(f, "synthetic data: {e}"),
            SyntheticError::Params(m) => write!(f, "true parameters: {m}"),
        }
    }
}

impl std::error::Error for SyntheticError {}

impl From<DataError> for SyntheticError {
    fn from(e: DataError) -> Self {
        SyntheticError::Data(e)
    }
}

impl From<ParamError> for SyntheticError {
    fn from(e: ParamError) -> Self {
        SyntheticError::Params(e.to_string())
    }
}

fn config_err(m: impl Into<String>) -> SyntheticError {
    SyntheticError::Config(m.into())
}

fn check_interval(name: &str, (lo, hi): (f64, f64), positive: bool) -> Result<(), SyntheticError> {
    if !(lo.is_finite() && hi.is_finite() && lo <= hi) || (positive && lo <= 0.0) {
        let need = if positive { "0 < lo <= hi" } else { "lo <= hi" };
        return Err(config_err(format!("{name} must be a finite interval with {need}, got ({lo}, {hi})")));
    }
    Ok(())
}

/// The paper's two synthetic experiments.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Experiment {
    /// `T = 25` transitions (26 observed steps, `t = 0..=25`).
    A,
    /// `T = 50` transitions (51 observed steps).
    B,
}

impl Experiment {
    /// Number of transitions `T` ("25 steps" in the paper means `T = 25`; a
    /// dataset then holds `T + 1` steps, `meta.steps = 26`).
    pub fn transitions(self) -> usize {
        match self {
            Experiment::A => 25,
            Experiment::B => 50,
        }
    }

    /// Its name, `"A"` or `"B"`.
    pub fn name(self) -> &'static str {
        match self {
            Experiment::A => "A",
            Experiment::B => "B",
        }
    }
}

impl FromStr for Experiment {
    type Err = SyntheticError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_uppercase().as_str() {
            "A" => Ok(Experiment::A),
            "B" => Ok(Experiment::B),
            _ => Err(config_err(format!("unknown experiment `{s}` (expected A or B)"))),
        }
    }
}

/// How scenes are made (see the [module docs](self)).
#[derive(Clone, Debug, PartialEq)]
pub struct SceneConfig {
    /// Steps per scene, `T + 1` (at least 1).
    pub steps: usize,
    /// Time between steps (s).
    pub dt: f64,
    /// Objects per scene.
    pub objects: usize,
    /// Range of the prior mean position from the AV's initial position (m).
    pub range: (f64, f64),
    /// Constant speed of the AV, driving straight along +x from the origin (m/s).
    pub av_speed: f64,
    /// Range of the prior mean speed (m/s), uniform.
    pub speed: (f64, f64),
    /// Prior mean curvatures are uniform in `[-max_kappa, max_kappa]` (1/m).
    pub max_kappa: f64,
    /// Object lengths (m), uniform.
    pub length: (f64, f64),
    /// Object widths (m), uniform.
    pub width: (f64, f64),
    /// Sds of every object's prior (all positive).
    pub prior_sd: State,
    /// The count model of the points per step ([`PointGenerator::mean_count`]).
    pub counts: PointGenerator,
}

impl SceneConfig {
    /// The paper's scenes with `steps = T + 1`: 100 objects at 5–50 m, AV at 5 m/s.
    pub fn paper(steps: usize) -> Self {
        let cars = SceneRanges::default();
        SceneConfig {
            steps,
            dt: DEFAULT_DT,
            objects: 100,
            range: (5.0, 50.0),
            av_speed: 5.0,
            speed: (4.0, 12.0),
            max_kappa: 0.02,
            length: cars.length,
            width: cars.width,
            prior_sd: State { x: 0.5, y: 0.5, yaw: 0.1, v: 1.0, kappa: 0.01 },
            counts: PointGenerator::default(),
        }
    }

    /// Checks every setting.
    pub fn validate(&self) -> Result<(), SyntheticError> {
        if self.steps == 0 {
            return Err(config_err("steps must be at least 1"));
        }
        if !(self.dt.is_finite() && self.dt > 0.0) {
            return Err(config_err(format!("dt must be positive, got {}", self.dt)));
        }
        check_interval("range", self.range, true)?;
        check_interval("speed", self.speed, false)?;
        check_interval("length", self.length, true)?;
        check_interval("width", self.width, true)?;
        if !self.av_speed.is_finite() {
            return Err(config_err(format!("av_speed must be finite, got {}", self.av_speed)));
        }
        if !(self.max_kappa.is_finite() && self.max_kappa >= 0.0) {
            return Err(config_err(format!("max_kappa must be finite and >= 0, got {}", self.max_kappa)));
        }
        if !self.prior_sd.to_array().iter().all(|&s| s.is_finite() && s > 0.0) {
            return Err(config_err(format!("prior sds must be positive, got {:?}", self.prior_sd)));
        }
        let c = &self.counts;
        if !(c.count_scale.is_finite()
            && c.count_scale >= 0.0
            && c.max_mean_count.is_finite()
            && c.max_mean_count >= 0.0)
        {
            return Err(config_err("point counts: count_scale and max_mean_count must be finite and >= 0"));
        }
        Ok(())
    }

    /// The AV's pose at step `t`.
    pub fn av_pose(&self, t: usize) -> Pose {
        Pose { x: self.av_speed * self.dt * t as f64, y: 0.0, yaw: 0.0 }
    }
}

/// How the true observation network is fitted.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthConfig {
    /// The physically motivated generator the network imitates.
    pub generator: PointGenerator,
    /// Where the labelled examples are drawn. Wider than the scenes' initial
    /// ring because objects drive away from the AV.
    pub ranges: SceneRanges,
    /// Labelled training examples (object states with their generated points).
    pub examples: usize,
    /// Held-out examples for the reported AOTLL.
    pub heldout: usize,
    /// Optimiser settings (its `seed` is replaced by a draw from the caller's rng).
    pub fit: FitConfig,
}

impl TruthConfig {
    /// The full-size fit.
    pub fn paper() -> Self {
        TruthConfig {
            generator: PointGenerator::default(),
            ranges: SceneRanges { range: (2.0, 250.0), ..SceneRanges::default() },
            examples: 20000,
            heldout: 5000,
            fit: FitConfig { steps: 6000, batch: 256, lr: 0.01, clip: None, seed: 0 },
        }
    }

    /// A tiny fit for tests (well under a second).
    pub fn quick() -> Self {
        TruthConfig {
            examples: 300,
            heldout: 100,
            fit: FitConfig { steps: 40, batch: 32, lr: 0.01, clip: None, seed: 0 },
            ..Self::paper()
        }
    }

    /// Checks every setting.
    pub fn validate(&self) -> Result<(), SyntheticError> {
        check_interval("truth ranges.range", self.ranges.range, true)?;
        check_interval("truth ranges.length", self.ranges.length, true)?;
        check_interval("truth ranges.width", self.ranges.width, true)?;
        if self.examples == 0 || self.heldout == 0 {
            return Err(config_err("the truth fit needs at least one training and one held-out example"));
        }
        Ok(())
    }
}

/// A whole experiment: the truth fit, scenes, and how many of each split.
#[derive(Clone, Debug, PartialEq)]
pub struct ExperimentConfig {
    /// Which experiment (sets `T`).
    pub experiment: Experiment,
    /// How scenes are made.
    pub scene: SceneConfig,
    /// How the true network is fitted.
    pub truth: TruthConfig,
    /// Training scenes (ids `0..train_scenes`).
    pub train_scenes: usize,
    /// Test scenes (ids `train_scenes..train_scenes + test_scenes`).
    pub test_scenes: usize,
}

impl ExperimentConfig {
    /// The paper's sizes: 10 training and 2 test scenes of 100 objects, `T` of the
    /// experiment.
    pub fn paper(experiment: Experiment) -> Self {
        ExperimentConfig {
            experiment,
            scene: SceneConfig::paper(experiment.transitions() + 1),
            truth: TruthConfig::paper(),
            train_scenes: 10,
            test_scenes: 2,
        }
    }

    /// Test sizes: 2 training and 1 test scene of 10 objects, 6 steps (`T = 5`), a
    /// tiny truth fit.
    pub fn quick(experiment: Experiment) -> Self {
        ExperimentConfig {
            experiment,
            scene: SceneConfig { objects: 10, ..SceneConfig::paper(6) },
            truth: TruthConfig::quick(),
            train_scenes: 2,
            test_scenes: 1,
        }
    }

    /// Checks every setting.
    pub fn validate(&self) -> Result<(), SyntheticError> {
        self.scene.validate()?;
        self.truth.validate()
    }
}

/// The true model of the synthetic data: the hand-crafted policy at its true
/// parameters and the fitted point network. `params` holds the network under
/// [`OBS_PREFIX`] (first, so a store laid out for the network alone shares its
/// ids) and the policy's log sds under [`POLICY_LOG_SD`] (last) — the names of the
/// project's parameter-file convention ([`crate::models::params`]), so a saved true model
/// can be read by [`crate::models::params::Models::from_store`] too.
#[derive(Clone, Debug, PartialEq)]
pub struct TrueModel {
    /// The policy.
    pub policy: HandCraftedPolicy,
    /// The observation model's layout (ids into `params`).
    pub obs: PointObservationModel,
    /// All true parameters.
    pub params: ParamStore<f64>,
}

impl TrueModel {
    /// A true model with a freshly initialised (unfitted) network and the given policy.
    pub fn init<R: Rng + ?Sized>(policy: HandCraftedPolicy, rng: &mut R) -> Self {
        let mut params = ParamStore::new();
        let obs = PointObservationModel::init_params(&mut params, OBS_PREFIX, rng);
        params.add(POLICY_LOG_SD, Tensor::from_vec(vec![policy.log_sd_accel(), policy.log_sd_pinch()]));
        TrueModel { policy, obs, params }
    }

    /// The true model held in `store` (as written by [`TrueModel::save`]): the
    /// names and shapes must be those of [`TrueModel::init`].
    pub fn from_store(store: ParamStore<f64>) -> Result<Self, SyntheticError> {
        let mut layout = TrueModel::init(HandCraftedPolicy::truth(), &mut StdRng::seed_from_u64(0));
        layout.params.check_same_layout(&store)?;
        let id = store.id(POLICY_LOG_SD).expect("layout checked");
        let log_sd = store.get(id).data();
        layout.policy =
            HandCraftedPolicy::new(log_sd[0], log_sd[1]).map_err(|e| SyntheticError::Params(e.to_string()))?;
        layout.params = store;
        Ok(layout)
    }

    /// Writes the parameters (versioned, checksummed, atomic; [`ParamStore::save`]).
    pub fn save(&self, path: &Path) -> Result<(), SyntheticError> {
        Ok(self.params.save(path)?)
    }

    /// Reads a true model written by [`TrueModel::save`].
    pub fn load(path: &Path) -> Result<Self, SyntheticError> {
        Self::from_store(ParamStore::load(path)?)
    }
}

/// The true model with the fit that made its network.
#[derive(Clone, Debug, PartialEq)]
pub struct FittedTruth {
    /// The true model.
    pub model: TrueModel,
    /// What the fit did (AOTLL of the training examples before and after).
    pub report: FitReport,
    /// AOTLL (nats per point) of the fitted network on held-out generator examples.
    pub heldout_aotll: f64,
    /// Points in the training examples.
    pub train_points: usize,
    /// Points in the held-out examples.
    pub heldout_points: usize,
}

/// Fits the true point network to the generator's labelled examples (SPEC §4) and
/// pairs it with the true hand-crafted policy. Draws, in order from `rng`: the
/// network's initial weights, the training examples, the held-out examples and the
/// minibatch seed.
pub fn fit_true_model<R: Rng + ?Sized>(config: &TruthConfig, rng: &mut R) -> Result<FittedTruth, SyntheticError> {
    config.validate()?;
    let mut model = TrueModel::init(HandCraftedPolicy::truth(), rng);
    let train = random_point_examples(&config.generator, &config.ranges, config.examples, rng);
    let heldout = random_point_examples(&config.generator, &config.ranges, config.heldout, rng);
    let fit = FitConfig { seed: rng.random(), ..config.fit.clone() };
    let report = fit_network(&model.obs, &mut model.params, &train, &fit);
    let heldout_aotll = aotll(&model.obs, &model.params, &heldout);
    let points = |ex: &[crate::models::observation::Example<[f64; 2]>]| ex.iter().map(|e| e.items.len()).sum();
    Ok(FittedTruth { heldout_aotll, train_points: points(&train), heldout_points: points(&heldout), model, report })
}

/// One simulated scene, before it becomes part of a [`Dataset`].
#[derive(Clone, Debug, PartialEq)]
pub struct SyntheticScene {
    /// Scene id.
    pub id: i64,
    /// The AV's pose per step.
    pub av: Vec<Pose>,
    /// The objects (ids `0..objects`), with their priors.
    pub objects: Vec<Object>,
    /// True states, `states[object][t]` for `t = 0..steps`.
    pub states: Vec<Vec<State>>,
    /// True actions, `actions[object][t - 1]` for `t = 1..steps` (the action that
    /// leads from step `t - 1` to step `t`).
    pub actions: Vec<Vec<Action>>,
    /// Observed points, `points[object][t]`.
    pub points: Vec<Vec<Vec<[f64; 2]>>>,
}

fn uniform<R: Rng + ?Sized>(rng: &mut R, (lo, hi): (f64, f64)) -> f64 {
    lo + (hi - lo) * rng.random::<f64>()
}

fn to_vehicle(s: State) -> VehicleState<f64> {
    VehicleState::new(s.x, s.y, s.yaw, s.v, s.kappa)
}

fn from_vehicle(s: VehicleState<f64>) -> State {
    State { x: s.x, y: s.y, yaw: s.yaw, v: s.v, kappa: s.kappa }
}

/// One object's placement and true motion (no observations yet).
#[derive(Clone, Debug, PartialEq)]
pub struct SimulatedObject {
    /// Its ids, extents and prior.
    pub object: Object,
    /// True states, `states[t]` for `t = 0..steps`.
    pub states: Vec<State>,
    /// True actions, `actions[t - 1]` for `t = 1..steps`.
    pub actions: Vec<Action>,
}

/// Places one object and drives it (steps 3 and 4 of the [module docs](self)):
/// draws, in order from `rng`, its length and width, its prior mean (range,
/// bearing, heading, speed, curvature; around `start`, the AV's initial pose), its
/// `x_0` from the prior, then for each step the policy's two innovations — the
/// acceleration's from `accel_innovation` (the standardised `z` of
/// `accel = mean + sd z`; [`StandardNormal`] for the paper's data), the pinch's from
/// a standard normal — and moves it with `motion`.
///
/// [`simulate_scene`] and the hidden-effect generator
/// ([`crate::criticism::hidden`]) share it, so both place and drive objects alike.
#[allow(clippy::too_many_arguments)]
pub fn simulate_object<R: Rng + ?Sized, D: Distribution<f64> + ?Sized>(
    config: &SceneConfig,
    policy: &HandCraftedPolicy,
    motion: &MotionModel,
    start: Pose,
    scene: i64,
    id: i64,
    accel_innovation: &D,
    rng: &mut R,
) -> SimulatedObject {
    let length = uniform(rng, config.length);
    let width = uniform(rng, config.width);
    let r = uniform(rng, config.range);
    let bearing = TAU * rng.random::<f64>();
    let mean = State {
        x: start.x + r * bearing.cos(),
        y: start.y + r * bearing.sin(),
        yaw: TAU * rng.random::<f64>(),
        v: uniform(rng, config.speed),
        kappa: uniform(rng, (-config.max_kappa, config.max_kappa)),
    };
    let sd = config.prior_sd;
    let noise: [f64; 5] = std::array::from_fn(|_| rng.sample::<f64, _>(StandardNormal));
    let m = mean.to_array();
    let s = sd.to_array();
    let x0 = State::from_array(std::array::from_fn(|i| m[i] + s[i] * noise[i]));

    // Dynamics: a_t ~ pi(. | x_{t-1}), x_t = f(x_{t-1}, a_t).
    let steps = config.steps;
    let mut gaussians = ActionGaussians::<f64>::default();
    let mut states = Vec::with_capacity(steps);
    let mut actions = Vec::with_capacity(steps.saturating_sub(1));
    states.push(x0);
    for _ in 1..steps {
        let prev = *states.last().expect("x_0 is there");
        policy.gaussians(&[prev.v], &[prev.kappa], &mut gaussians);
        let g = &gaussians;
        let e1: f64 = accel_innovation.sample(rng);
        let e2: f64 = rng.sample(StandardNormal);
        let accel = g.mean_accel[0] + g.l11[0] * e1;
        let pinch = g.mean_pinch[0] + g.l21[0] * e1 + g.l22[0] * e2;
        let next = motion.step(&to_vehicle(prev), &VAction::new(accel, pinch));
        actions.push(Action { accel, pinch });
        states.push(from_vehicle(next));
    }
    let object = Object { scene, id, length, width, prior: Prior { mean, sd } };
    SimulatedObject { object, states, actions }
}

/// The exact motion model of the synthetic data at `config.dt` (8-node Gauss–Legendre).
pub(crate) fn scene_motion(config: &SceneConfig) -> Result<MotionModel, SyntheticError> {
    MotionModel::new(config.dt, Quadrature::default()).map_err(|e| config_err(format!("motion model: {e}")))
}

/// Simulates one scene (see the [module docs](self)). Objects are drawn one after
/// another, each completely (size, prior, `x_0`, actions and states with
/// [`simulate_object`], then points), from `rng`.
pub fn simulate_scene<R: Rng + ?Sized>(
    config: &SceneConfig,
    truth: &TrueModel,
    id: i64,
    rng: &mut R,
) -> Result<SyntheticScene, SyntheticError> {
    config.validate()?;
    let motion = scene_motion(config)?;
    let steps = config.steps;
    let av: Vec<Pose> = (0..steps).map(|t| config.av_pose(t)).collect();
    let start = av[0];
    let mut scene = SyntheticScene {
        id,
        av,
        objects: Vec::with_capacity(config.objects),
        states: Vec::with_capacity(config.objects),
        actions: Vec::with_capacity(config.objects),
        points: Vec::with_capacity(config.objects),
    };
    for k in 0..config.objects {
        let SimulatedObject { object, states, actions } =
            simulate_object(config, &truth.policy, &motion, start, id, k as i64, &StandardNormal, rng);

        // Observations: a Poisson count from the generator's count model, points
        // from the true network.
        let mut points = Vec::with_capacity(steps);
        for (t, x) in states.iter().enumerate() {
            let ctx = ObsContext::of_object(scene.av[t], &object);
            let pose = Pose { x: x.x, y: x.y, yaw: x.yaw };
            let mean_count = config.counts.mean_count((x.x - ctx.av.x).hypot(x.y - ctx.av.y));
            let n = if mean_count > 0.0 {
                let k: f64 = Poisson::new(mean_count).expect("positive finite mean").sample(rng);
                k as usize
            } else {
                0
            };
            let mut pts = Vec::with_capacity(n);
            truth.obs.sample(&truth.params, &ctx, pose, n, rng, &mut pts);
            points.push(pts);
        }
        scene.objects.push(object);
        scene.states.push(states);
        scene.actions.push(actions);
        scene.points.push(points);
    }
    Ok(scene)
}

/// A builder holding the scenes' AV poses, objects and ground truth (states and
/// actions) but no observations: [`build_dataset`] adds points, the hidden-effect
/// generator box detections.
pub(crate) fn ground_truth_builder(meta: Meta, kind: ObservationKind, scenes: &[SyntheticScene]) -> DatasetBuilder {
    let mut b = Dataset::builder(meta, kind);
    b.with_states().with_actions();
    for s in scenes {
        b.scene(s.id, &s.av);
        for (k, o) in s.objects.iter().enumerate() {
            b.object(*o);
            for (t, x) in s.states[k].iter().enumerate() {
                b.state(s.id, o.id, t, *x);
            }
            for (t, a) in s.actions[k].iter().enumerate() {
                b.action(s.id, o.id, t + 1, *a);
            }
        }
    }
    b
}

/// Assembles simulated scenes into a validated point [`Dataset`] with ground-truth
/// states and actions.
pub fn build_dataset(config: &SceneConfig, scenes: &[SyntheticScene]) -> Result<Dataset, SyntheticError> {
    let meta = Meta::new(config.dt, config.steps);
    let mut b = ground_truth_builder(meta, ObservationKind::Points, scenes);
    for s in scenes {
        for (o, points) in s.objects.iter().zip(&s.points) {
            for (t, pts) in points.iter().enumerate() {
                for p in pts {
                    b.point(s.id, o.id, t, *p);
                }
            }
        }
    }
    Ok(b.build()?)
}

/// Simulates the scenes `ids` and assembles them into a dataset. Each scene draws
/// from its own [`StdRng`] seeded by one `u64` from `rng` (in the order of `ids`).
pub fn generate_dataset<R: Rng + ?Sized>(
    config: &SceneConfig,
    truth: &TrueModel,
    ids: &[i64],
    rng: &mut R,
) -> Result<Dataset, SyntheticError> {
    let scenes = ids
        .iter()
        .map(|&id| simulate_scene(config, truth, id, &mut StdRng::seed_from_u64(rng.random())))
        .collect::<Result<Vec<_>, _>>()?;
    build_dataset(config, &scenes)
}

/// Progress of [`generate_experiment`], for a caller's progress display.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Progress {
    /// The truth fit is starting.
    FitStarted,
    /// The truth fit is done.
    FitDone,
    /// Scene `done` of `total` (train and test together) has been simulated.
    Scene {
        /// Scenes simulated so far.
        done: usize,
        /// Scenes in all.
        total: usize,
    },
}

/// A generated experiment: the true model and its fit, and the two datasets.
#[derive(Clone, Debug, PartialEq)]
pub struct SyntheticExperiment {
    /// The true model and how its network was fitted.
    pub truth: FittedTruth,
    /// Training scenes (ids `0..train_scenes`).
    pub train: Dataset,
    /// Test scenes (ids following the training ones).
    pub test: Dataset,
}

/// Generates a whole experiment: fits the true network ([`fit_true_model`]), then
/// simulates the training scenes and the test scenes, each scene from its own
/// [`StdRng`] seeded by a draw from `rng` (training scenes first). `progress` is
/// told what is happening.
pub fn generate_experiment<R: Rng + ?Sized>(
    config: &ExperimentConfig,
    rng: &mut R,
    progress: &mut dyn FnMut(Progress),
) -> Result<SyntheticExperiment, SyntheticError> {
    config.validate()?;
    progress(Progress::FitStarted);
    let truth = fit_true_model(&config.truth, rng)?;
    progress(Progress::FitDone);
    let total = config.train_scenes + config.test_scenes;
    let seeds: Vec<u64> = (0..total).map(|_| rng.random()).collect();
    let mut scenes = Vec::with_capacity(total);
    for (k, &seed) in seeds.iter().enumerate() {
        scenes.push(simulate_scene(&config.scene, &truth.model, k as i64, &mut StdRng::seed_from_u64(seed))?);
        progress(Progress::Scene { done: k + 1, total });
    }
    let test = build_dataset(&config.scene, &scenes[config.train_scenes..])?;
    let train = build_dataset(&config.scene, &scenes[..config.train_scenes])?;
    Ok(SyntheticExperiment { truth, train, test })
}

/// What a generated point dataset looks like.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SyntheticSummary {
    /// Scenes.
    pub scenes: usize,
    /// Objects.
    pub objects: usize,
    /// Steps per scene (`T + 1`).
    pub steps: usize,
    /// Observed points.
    pub points: usize,
    /// Mean points per (object, step).
    pub points_per_object_step: f64,
    /// Fraction of (object, step) cells without a point.
    pub empty_fraction: f64,
    /// Mean points per (object, step) by range from the AV: bins `[0, 10)`,
    /// `[10, 25)`, `[25, 50)`, `[50, 100)`, `[100, inf)` m (NaN for an empty bin).
    pub points_by_range: [f64; 5],
    /// Smallest true speed (m/s).
    pub speed_min: f64,
    /// Mean true speed (m/s).
    pub speed_mean: f64,
    /// Largest true speed (m/s).
    pub speed_max: f64,
    /// True states with a negative speed (reversing; never clipped).
    pub negative_speeds: usize,
    /// Largest absolute true curvature (1/m).
    pub kappa_abs_max: f64,
    /// Smallest range of an object from the AV (m).
    pub range_min: f64,
    /// Mean range (m).
    pub range_mean: f64,
    /// Largest range (m).
    pub range_max: f64,
}

/// Upper edges of the range bins of [`SyntheticSummary::points_by_range`] (m).
pub const RANGE_BINS: [f64; 4] = [10.0, 25.0, 50.0, 100.0];

/// Summarises a point dataset with ground-truth states (counts, speeds, ranges).
///
/// # Panics
/// If the dataset has no point observations or no complete states.
#[track_caller]
pub fn summarize(data: &Dataset) -> SyntheticSummary {
    let points = data.points().expect("summarize: a point dataset");
    let states = data.states().expect("summarize: a dataset with true states");
    let (mut cells, mut empty) = (0usize, 0usize);
    let mut bin_points = [0usize; 5];
    let mut bin_cells = [0usize; 5];
    let (mut vmin, mut vmax, mut vsum, mut neg) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0usize);
    let (mut rmin, mut rmax, mut rsum) = (f64::INFINITY, f64::NEG_INFINITY, 0.0);
    let mut kmax: f64 = 0.0;
    for o in 0..data.objects().len() {
        let av = &data.scenes()[data.object_scene(o)].av;
        for (t, pose) in av.iter().enumerate() {
            let x = states.get(o, t).expect("summarize: complete states");
            let n = points.get(o, t).len();
            let r = (x.x - pose.x).hypot(x.y - pose.y);
            let bin = RANGE_BINS.iter().position(|&edge| r < edge).unwrap_or(RANGE_BINS.len());
            bin_points[bin] += n;
            bin_cells[bin] += 1;
            cells += 1;
            empty += usize::from(n == 0);
            vmin = vmin.min(x.v);
            vmax = vmax.max(x.v);
            vsum += x.v;
            neg += usize::from(x.v < 0.0);
            kmax = kmax.max(x.kappa.abs());
            rmin = rmin.min(r);
            rmax = rmax.max(r);
            rsum += r;
        }
    }
    let c = cells.max(1) as f64;
    SyntheticSummary {
        scenes: data.scenes().len(),
        objects: data.objects().len(),
        steps: data.steps(),
        points: points.len(),
        points_per_object_step: points.len() as f64 / c,
        empty_fraction: empty as f64 / c,
        points_by_range: std::array::from_fn(|b| {
            if bin_cells[b] == 0 {
                f64::NAN
            } else {
                bin_points[b] as f64 / bin_cells[b] as f64
            }
        }),
        speed_min: vmin,
        speed_mean: vsum / c,
        speed_max: vmax,
        negative_speeds: neg,
        kappa_abs_max: kmax,
        range_min: rmin,
        range_mean: rsum / c,
        range_max: rmax,
    }
}
