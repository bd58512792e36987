//! Observation models (SPEC §3): the density `g(y_t | x_t)` of what the AV sees of
//! one object at one step, behind one trait, [`ObservationModel`], so the particle
//! filter, the score estimators, training and diagnostics use either model
//! unchanged.
//!
//! * [`features`]: the AV-relative network inputs shared by both models (range,
//!   bearing, relative bearing, size), plain and on the tape.
//! * [`edges`]: the box edges, edge coordinates of a point and the soft uniform.
//! * [`points`]: the [`PointObservationModel`] — a set of 2-D points around the
//!   box, each a mixture over the 4 edges.
//! * [`boxes`]: the [`BoxObservationModel`] — at most one detected box (centre
//!   and yaw) per step.
//! * [`generator`]: the physically motivated point generator of the synthetic data.
//! * [`fit`]: supervised fitting of an observation network by maximum mean
//!   log-density (AOTLL), which makes the "true" network of the synthetic data.
//!
//! An observation is a slice of *items*, independent given the state: points for
//! the point model, at most one [`BoxDetection`] for the box model. An empty slice
//! (no point, no detection) contributes `log g = 0`.
//!
//! Each model is a *layout*: it adds its network to an
//! [`autodiff::nn::ParamStore`] under a name prefix ([`ObservationModel::init_params`])
//! and keeps the parameter ids. Every method takes the parameters explicitly: a
//! `ParamStore<F>` for the plain paths (the filter casts its f64 master copy to f32
//! once per gradient step) and [`BoundParams`] for the tape path. The four
//! evaluation paths compute the same numbers:
//!
//! | path | use | method |
//! |---|---|---|
//! | plain, batched over particles, reused scratch | the filter's hot loop | [`ObservationModel::log_likelihood`] |
//! | tape, batched over rows | PF-SEFI surrogate, baselines, fitting | [`ObservationModel::log_likelihood_rows`] |
//! | plain, per item, f64 | AOTLL | [`ObservationModel::log_density_items`] |
//! | sampler | synthetic data, posterior predictive checks | [`ObservationModel::sample`] |

pub mod boxes;
pub mod edges;
pub mod features;
pub mod fit;
pub mod generator;
mod net;
pub mod points;

pub use boxes::BoxObservationModel;
pub use features::{av_features, av_features_on_tape, av_features_one, NUM_FEATURES};
pub use fit::{aotll, fit_network, Example, FitConfig, FitReport};
pub use generator::{random_point_examples, PointGenerator, SceneRanges};
pub use points::PointObservationModel;

use autodiff::nn::{BoundParams, ParamStore};
use autodiff::{Float, Tape, Tensor, Var};
use rand::Rng;

use crate::data::{BoxDetection, Dataset, Object, ObservationKind, Pose, State, StepTable};

/// What an observation depends on besides the object's state: the AV's pose and the
/// object's known extents.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ObsContext {
    /// The AV's pose (world frame).
    pub av: Pose,
    /// The object's length along its heading (m, positive).
    pub length: f64,
    /// The object's width (m, positive).
    pub width: f64,
}

impl ObsContext {
    /// A context from its parts.
    pub fn new(av: Pose, length: f64, width: f64) -> Self {
        ObsContext { av, length, width }
    }

    /// The context of `object` seen from `av`.
    pub fn of_object(av: Pose, object: &Object) -> Self {
        ObsContext { av, length: object.length, width: object.width }
    }
}

/// Borrowed struct-of-arrays poses `(x, y, yaw)` of `n` particles (the first three
/// components of a dimension-major particle array).
#[derive(Clone, Copy, Debug)]
pub struct PosesRef<'a, F> {
    /// Positions x (m).
    pub x: &'a [F],
    /// Positions y (m).
    pub y: &'a [F],
    /// Headings (rad).
    pub yaw: &'a [F],
}

impl<'a, F> PosesRef<'a, F> {
    /// Poses from three slices of one length.
    pub fn new(x: &'a [F], y: &'a [F], yaw: &'a [F]) -> Self {
        PosesRef { x, y, yaw }
    }

    /// The poses of a dimension-major particle array (`states[k * n + i]`, with
    /// `x, y, yaw` the components 0, 1, 2) of `n` particles.
    #[track_caller]
    pub fn from_dim_major(states: &'a [F], n: usize) -> Self {
        assert!(states.len() >= 3 * n, "PosesRef::from_dim_major: {} values for {n} particles", states.len());
        PosesRef { x: &states[..n], y: &states[n..2 * n], yaw: &states[2 * n..3 * n] }
    }

    /// Number of poses; panics if the slices differ in length.
    #[track_caller]
    pub fn len(&self) -> usize {
        let n = self.x.len();
        assert!(
            self.y.len() == n && self.yaw.len() == n,
            "PosesRef: component lengths differ (x {n}, y {}, yaw {})",
            self.y.len(),
            self.yaw.len()
        );
        n
    }

    /// Whether there are no poses.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
}

impl<'a, F: Float> From<crate::models::vehicle::StatesRef<'a, F>> for PosesRef<'a, F> {
    fn from(s: crate::models::vehicle::StatesRef<'a, F>) -> Self {
        PosesRef { x: s.x, y: s.y, yaw: s.yaw }
    }
}

/// Rows on a tape for [`ObservationModel::log_likelihood_rows`]: row `r` is an
/// object state `(x, y, yaw)` with the object's extents. Every `Var` has shape `[R]`.
/// Any of them may be tracked: gradients flow to states (the through-filter
/// baselines) and extents (a size-bias model extension) as well as to parameters.
#[derive(Clone, Copy, Debug)]
pub struct RowVars<'t, F: Float> {
    /// Positions x (m).
    pub x: Var<'t, F>,
    /// Positions y (m).
    pub y: Var<'t, F>,
    /// Headings (rad).
    pub yaw: Var<'t, F>,
    /// Lengths (m).
    pub length: Var<'t, F>,
    /// Widths (m).
    pub width: Var<'t, F>,
}

impl<'t, F: Float> RowVars<'t, F> {
    /// Rows of constants on `tape` (all slices of one length).
    #[track_caller]
    pub fn constant(tape: &'t Tape<F>, x: &[F], y: &[F], yaw: &[F], length: &[F], width: &[F]) -> Self {
        let r = x.len();
        assert!(
            [y.len(), yaw.len(), length.len(), width.len()].iter().all(|&m| m == r),
            "RowVars::constant: lengths differ (x {r}, y {}, yaw {}, length {}, width {})",
            y.len(),
            yaw.len(),
            length.len(),
            width.len()
        );
        let c = |s: &[F]| tape.constant(Tensor::from_vec(s.to_vec()));
        RowVars { x: c(x), y: c(y), yaw: c(yaw), length: c(length), width: c(width) }
    }

    /// Rows of constants from per-row poses and contexts (the AV poses of the
    /// contexts are what [`ObservationModel::log_likelihood_rows`] takes as `av`).
    #[track_caller]
    pub fn from_poses(tape: &'t Tape<F>, poses: &[Pose], contexts: &[ObsContext]) -> Self {
        assert_eq!(
            poses.len(),
            contexts.len(),
            "RowVars::from_poses: {} poses, {} contexts",
            poses.len(),
            contexts.len()
        );
        let c = |f: &dyn Fn(usize) -> f64| {
            tape.constant(Tensor::from_vec((0..poses.len()).map(|i| F::from_f64(f(i))).collect()))
        };
        RowVars {
            x: c(&|i| poses[i].x),
            y: c(&|i| poses[i].y),
            yaw: c(&|i| poses[i].yaw),
            length: c(&|i| contexts[i].length),
            width: c(&|i| contexts[i].width),
        }
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.x.numel()
    }

    /// Whether there are no rows.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    #[track_caller]
    pub(crate) fn check(&self, av: usize, items: usize, op: &str) -> usize {
        let r = self.len();
        for (name, v) in [("y", self.y), ("yaw", self.yaw), ("length", self.length), ("width", self.width)] {
            assert!(v.shape() == [r], "{op}: rows.{name} has shape {:?}, expected [{r}]", v.shape());
        }
        assert!(self.x.shape() == [r], "{op}: rows.x has shape {:?}, expected [{r}]", self.x.shape());
        assert!(av == r && items == r, "{op}: {r} rows, {av} AV poses, {items} observations");
        r
    }
}

/// Working memory of the plain (no-tape) paths, reused across calls: after the
/// first call for a given number of particles the point and box models' plain
/// paths allocate nothing. One per thread.
#[derive(Clone, Debug, Default)]
pub struct Scratch<F> {
    /// Network inputs then outputs, feature-major (`[k * n + i]`).
    pub(crate) feats: Vec<F>,
    pub(crate) hidden: [Vec<F>; 2],
    pub(crate) outputs: Vec<F>,
    /// cos and sin of the particles' headings.
    pub(crate) cos: Vec<F>,
    pub(crate) sin: Vec<F>,
    /// Per-particle model quantities (feature-major), filled by each model's head.
    pub(crate) head: Vec<F>,
    /// One value per particle.
    pub(crate) tmp: Vec<F>,
}

impl<F: Float> Scratch<F> {
    /// Empty working memory.
    pub fn new() -> Self {
        Scratch {
            feats: Vec::new(),
            hidden: [Vec::new(), Vec::new()],
            outputs: Vec::new(),
            cos: Vec::new(),
            sin: Vec::new(),
            head: Vec::new(),
            tmp: Vec::new(),
        }
    }
}

/// Resizes `v` to `n` (values unspecified; no allocation within capacity).
#[inline]
pub(crate) fn fit_len<F: Float>(v: &mut Vec<F>, n: usize) {
    if v.len() != n {
        v.resize(n, F::ZERO);
    }
}

/// An observation model `g(y | x)` (SPEC §3): the density of one step's
/// observation of one object — a slice of items independent given the state — as
/// a function of the object's pose `(x, y, yaw)`, its extents and the AV's pose,
/// through a network over AV-relative features whose parameters live in a
/// [`ParamStore`].
///
/// Implemented by [`PointObservationModel`] and [`BoxObservationModel`].
///
/// ```
/// use autodiff::nn::ParamStore;
/// use rand::SeedableRng;
/// use ssm::data::Pose;
/// use ssm::models::observation::{ObsContext, ObservationModel, PointObservationModel, PosesRef, Scratch};
///
/// let mut rng = rand::rngs::StdRng::seed_from_u64(0);
/// let mut store = ParamStore::new();
/// let model = PointObservationModel::init_params(&mut store, "obs", &mut rng);
/// let ctx = ObsContext::new(Pose { x: 0.0, y: 0.0, yaw: 0.0 }, 4.5, 1.8);
/// let pose = Pose { x: 12.0, y: 3.0, yaw: 0.3 };
/// let mut points = Vec::new();
/// model.sample(&store, &ctx, pose, 5, &mut rng, &mut points);
///
/// // The filter's path: f32, batched over particles, reusable scratch.
/// let store32 = store.cast::<f32>();
/// let (xs, ys, yaws) = ([12.0f32, 12.5], [3.0f32, 2.0], [0.3f32, 0.0]);
/// let mut out = [0.0f32; 2];
/// let mut scratch = Scratch::new();
/// model.log_likelihood(&store32, &ctx, PosesRef::new(&xs, &ys, &yaws), &points, &mut scratch, &mut out);
///
/// // AOTLL's path: per item, f64.
/// let mut per_point = vec![0.0; points.len()];
/// model.log_density_items(&store, &ctx, pose, &points, &mut per_point);
/// let total: f64 = per_point.iter().sum();
/// assert!((total - out[0] as f64).abs() < 1e-3 * total.abs().max(1.0));
/// ```
pub trait ObservationModel: Clone + Send + Sync {
    /// One observed item: a point `[x, y]` or a [`BoxDetection`].
    type Item: Copy + std::fmt::Debug + Send + Sync;

    /// The kind of dataset this model reads.
    const KIND: ObservationKind;

    /// Adds the model's parameters to `store` under `prefix` (names
    /// `{prefix}.0.w`, `{prefix}.0.b`, ...) with standard initialisation, and returns
    /// the model that refers to them.
    fn init_params<R: Rng + ?Sized>(store: &mut ParamStore<f64>, prefix: &str, rng: &mut R) -> Self
    where
        Self: Sized;

    /// Number of scalar parameters.
    fn num_params(&self) -> usize;

    /// The items of `object` at step `t` of `data` (possibly none).
    ///
    /// # Panics
    /// If `data` holds the other kind of observation (check [`Dataset::kind`]
    /// against [`ObservationModel::KIND`] first) or the indices are out of range.
    fn items(data: &Dataset, object: usize, t: usize) -> &[Self::Item];

    /// The filter's hot path: `out[i] = sum_items log g(item | pose i)` for the `n`
    /// poses (`out` has length `n`). No tape; `scratch` is reused (see [`Scratch`]);
    /// single-threaded (the filter parallelises over objects). With no items the
    /// network is not run and `out` is all 0.
    fn log_likelihood<F: Float>(
        &self,
        params: &ParamStore<F>,
        ctx: &ObsContext,
        poses: PosesRef<'_, F>,
        items: &[Self::Item],
        scratch: &mut Scratch<F>,
        out: &mut [F],
    );

    /// The same on a tape, batched over rows: row `r` has state and extents from
    /// `rows`, AV pose `av[r]` and observation `items[r]`. Returns the per-row sums
    /// `sum_items log g` (shape `[R]`), differentiable in the parameters and in
    /// every tracked `Var` of `rows`. Large batches use the tape's parallelism;
    /// results never depend on the thread count.
    fn log_likelihood_rows<'t, F: Float>(
        &self,
        params: &BoundParams<'t, F>,
        rows: &RowVars<'t, F>,
        av: &[Pose],
        items: &[&[Self::Item]],
    ) -> Var<'t, F>;

    /// Per-item log-densities `out[k] = log g(items[k] | pose)` in f64 (AOTLL).
    #[track_caller]
    fn log_density_items(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        items: &[Self::Item],
        out: &mut [f64],
    ) {
        assert_eq!(out.len(), items.len(), "log_density_items: {} items, room for {}", items.len(), out.len());
        let mut scratch = Scratch::new();
        let (x, y, yaw) = ([pose.x], [pose.y], [pose.yaw]);
        for (o, item) in out.iter_mut().zip(items) {
            let mut v = [0.0];
            self.log_likelihood(
                params,
                ctx,
                PosesRef::new(&x, &y, &yaw),
                std::slice::from_ref(item),
                &mut scratch,
                &mut v,
            );
            *o = v[0];
        }
    }

    /// Appends `n` items drawn independently from `g(. | pose)` to `out`.
    #[allow(clippy::too_many_arguments)]
    fn sample<R: Rng + ?Sized>(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        n: usize,
        rng: &mut R,
        out: &mut Vec<Self::Item>,
    );
}

/// A detection's items: the detection, if any, as a slice of length 0 or 1.
/// Every object-step of `data` with a true state (from `truth`) and observations
/// (of `O`'s kind), object by object and step by step: the observation context,
/// the true pose and the observed items.
pub fn labelled_steps<'d, O: ObservationModel<Item: 'd>>(
    data: &'d Dataset,
    truth: &'d StepTable<State>,
) -> impl Iterator<Item = (ObsContext, Pose, &'d [O::Item])> + 'd {
    data.objects().iter().enumerate().flat_map(move |(object, obj)| {
        let scene = &data.scenes()[data.object_scene(object)];
        (0..data.steps()).filter_map(move |t| {
            let s = truth.get(object, t)?;
            let items = O::items(data, object, t);
            (!items.is_empty())
                .then(|| (ObsContext::of_object(scene.av[t], obj), Pose { x: s.x, y: s.y, yaw: s.yaw }, items))
        })
    })
}

/// Name prefix of the observation network's parameters in a parameter store
/// (`obs.0.w`, `obs.0.b`, ...; the convention of [`crate::models::params`]).
pub const OBS_PREFIX: &str = "obs";

pub(crate) fn detection_items(d: Option<&BoxDetection>) -> &[BoxDetection] {
    match d {
        Some(d) => std::slice::from_ref(d),
        None => &[],
    }
}
