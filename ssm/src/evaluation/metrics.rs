//! The evaluation metrics of SPEC §5, and medians with interquartile ranges over
//! repeated runs.
//!
//! * **MLL**: the particle filter's `l_hat(theta)` (default [`EVAL_PARTICLES`]
//!   particles) divided by the number of observed points or detections — nats per
//!   point ([`mll`]).
//! * **ADE / AYE**: mean position error (m) and mean absolute wrapped yaw error
//!   (rad) of the fixed-lag smoothed means and of the filtering means against the
//!   true states; steps without a true state are skipped ([`state_errors`]).
//! * **AOTLL**: mean `log g(y_t | true x_t)` per observed item ([`aotll`]).
//! * **APTLL**: mean `log pi(true a_t | true x_{t-1})` per step `t >= 1` where the
//!   action and the previous state are known ([`aptll`]).
//! * For box detections, AOTLL split into the reversed headings and the density's
//!   factors ([`box_aotll_terms`]).
//!
//! [`evaluate`] computes all of them with one filter run ([`track`]);
//! [`summarise_runs`] (a [`Summary`] per metric) give the median and interquartile range of each over
//! repeated runs (different seeds).
//!
//! ```
//! use ssm::evaluation::metrics::wrapped_abs_diff;
//! assert!((wrapped_abs_diff(3.1, -3.1) - (2.0 * std::f64::consts::PI - 6.2)).abs() < 1e-12);
//! ```

use std::f64::consts::{PI, TAU};

use autodiff::nn::ParamStore;
use serde::Serialize;

use crate::data::{Dataset, ObservationKind, State, StepTable};
use crate::filter::{run_filter, FilterConfig, Moments, ObjectSummary, Sampling};
use crate::models::drift::DRIFT_DIMS;
use crate::models::extended::{ExtendedSsm, ExtensibleObservation};
use crate::models::observation::boxes::{BoxObservationModel, DetectionDistribution, DetectionTerms};
use crate::models::observation::{labelled_steps, ObservationModel};
use crate::models::params::{ModelAdditions, Models, ObservationVisitor};
use crate::models::road_user::{VehicleSsm, YAW};
use crate::models::vehicle::{ActionGaussians, ActionsRef, GaussianPolicy, STATE_DIM};
use crate::models::{Batch, ParticleModel};
use crate::stats::{log_sum_exp, normal_quantile, quantile_sorted, Summary};

/// Particles of an evaluation run (SPEC §5).
pub const EVAL_PARTICLES: usize = 4096;
/// Default fixed lag of the smoothed means (the paper's synthetic setting).
pub const EVAL_LAG: usize = 8;

/// The filter settings of an evaluation: [`EVAL_PARTICLES`] particles, systematic
/// resampling at every step, the given lag and seed.
pub fn eval_config(lag: usize, seed: u64) -> FilterConfig {
    FilterConfig::new(Sampling::new(EVAL_PARTICLES, None), lag, seed)
}

/// `|a - b|` wrapped to `[0, pi]`: the absolute difference of two angles.
pub fn wrapped_abs_diff(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(TAU);
    if d > PI {
        TAU - d
    } else {
        d
    }
}

/// The marginal log-likelihood per observed unit (nats per point); `None` without
/// observed units.
pub fn mll(log_likelihood: f64, observed_units: usize) -> Option<f64> {
    (observed_units > 0).then(|| log_likelihood / observed_units as f64)
}

/// Mean position and yaw errors of state estimates against the truth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct StateErrors {
    /// Mean Euclidean position error (m); `None` if nothing was compared.
    pub ade: Option<f64>,
    /// Mean absolute wrapped yaw error (rad); `None` if nothing was compared.
    pub aye: Option<f64>,
    /// Number of (object, step) pairs compared.
    pub count: usize,
}

/// ADE and AYE of `estimates[object][t]` against `truth`, over the cells where
/// both exist (a missing true state, or an estimate row shorter than the truth,
/// is skipped).
#[track_caller]
pub fn state_errors(estimates: &[Vec<State>], truth: &StepTable<State>) -> StateErrors {
    assert_eq!(
        estimates.len(),
        truth.objects(),
        "state_errors: {} estimated objects, {} true objects",
        estimates.len(),
        truth.objects()
    );
    let (mut pos, mut yaw, mut count) = (0.0, 0.0, 0usize);
    for (object, rows) in estimates.iter().enumerate() {
        for (t, est) in rows.iter().enumerate().take(truth.steps()) {
            if let Some(tr) = truth.get(object, t) {
                pos += (est.x - tr.x).hypot(est.y - tr.y);
                yaw += wrapped_abs_diff(est.yaw, tr.yaw);
                count += 1;
            }
        }
    }
    let mean = |s: f64| (count > 0).then(|| s / count as f64);
    StateErrors { ade: mean(pos), aye: mean(yaw), count }
}

/// A mean of per-item values with the number of items and how the items spread:
/// a mean of log-densities can be carried by a few items far in the tail, which
/// the median and the lowest percentile show.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct MeanOver {
    /// The mean; `None` if there was nothing to average.
    pub mean: Option<f64>,
    /// Number of items averaged.
    pub count: usize,
    /// The items' median (`None` when empty, and in files written before it existed).
    #[serde(default)]
    pub median: Option<f64>,
    /// The items' 1% quantile.
    #[serde(default)]
    pub q01: Option<f64>,
    /// The mean without the items below the 1% quantile: how much of the mean
    /// the lowest 1% of items carry.
    #[serde(default)]
    pub mean_above_q01: Option<f64>,
}

impl MeanOver {
    /// The mean and spread of `items` (non-finite items count in the mean only).
    pub fn of(items: &[f64]) -> Self {
        let count = items.len();
        let mean = (count > 0).then(|| items.iter().sum::<f64>() / count as f64);
        // One sorted copy of the finite items serves both quantiles.
        let mut sorted: Vec<f64> = items.iter().copied().filter(|x| x.is_finite()).collect();
        sorted.sort_by(f64::total_cmp);
        let at = |q: f64| (!sorted.is_empty()).then(|| quantile_sorted(&sorted, q));
        let q01 = at(0.01);
        let mean_above_q01 = q01.map(|q| {
            let (sum, kept) = items.iter().filter(|&&x| x >= q).fold((0.0, 0usize), |(s, n), &x| (s + x, n + 1));
            sum / kept as f64
        });
        MeanOver { mean, count, median: at(0.5), q01, mean_above_q01 }
    }
}

/// AOTLL: the mean `log g(y_t | true x_t)` per observed item, over the steps with
/// a true state. `None` mean if the dataset has no true states or no observation
/// at a step with one.
pub fn aotll<O: ObservationModel>(data: &Dataset, model: &O, params: &ParamStore<f64>) -> MeanOver {
    let Some(truth) = data.states() else { return MeanOver::default() };
    if data.kind() != O::KIND {
        return MeanOver::default();
    }
    let mut per_item = Vec::new();
    for (ctx, pose, items) in labelled_steps::<O>(data, truth) {
        let start = per_item.len();
        per_item.resize(start + items.len(), 0.0);
        model.log_density_items(params, &ctx, pose, items, &mut per_item[start..]);
    }
    MeanOver::of(&per_item)
}

/// AOTLL of the observation model with `additions`: [`aotll`] for the base
/// model, [`model_aotll`] of the extended one otherwise (empty if an addition
/// does not apply to the data).
pub fn extended_aotll<P: GaussianPolicy, O: ExtensibleObservation>(
    data: &Dataset,
    policy: &P,
    observation: &O,
    observation_params: &ParamStore<f64>,
    additions: ModelAdditions<'_>,
) -> MeanOver {
    if additions.extension.is_none() && additions.drift.is_none() {
        return aotll(data, observation, observation_params);
    }
    VehicleSsm::new(data, policy, observation, observation_params)
        .and_then(|base| additions.extend(&base).map(|m| model_aotll(data, &m, DRIFT_AOTLL_NODES)))
        .unwrap_or_default()
}

/// [`extended_aotll`] of a whole set of `models`: its observation network (points
/// or boxes) with its extension and drift.
pub fn models_aotll(data: &Dataset, models: &Models) -> MeanOver {
    struct Aotll<'a>(&'a Dataset, &'a Models);
    impl ObservationVisitor for Aotll<'_> {
        type Output = MeanOver;
        fn visit<O: ExtensibleObservation>(self, o: &O) -> MeanOver {
            let m = self.1;
            extended_aotll(self.0, &m.policy, o, &m.observation_params, m.additions())
        }
    }
    models.observation.visit(Aotll(data, models))
}

/// Nodes per offset of the finer of the two grids over which [`model_aotll`]
/// integrates a detector drift out (`24^3` and `12^3` per labelled step).
pub const DRIFT_AOTLL_NODES: usize = 24;

/// AOTLL under `model`'s observation density exactly as its filter weighs
/// particles (in f32, with any catalogue extension, e.g. a heading-flip mixture):
/// every labelled object-step's log-density of its items at the true state,
/// shared evenly among its items (so the mean over items is [`aotll`]'s for a
/// model whose items are independent given the state).
///
/// With a detector drift the density at the true state is the marginal over the
/// drift's stationary law, `E_u g(y | x + d(u))` with `u ~ N(0, I)`: a
/// detection's density given the state alone, as a white-noise model's is. It
/// is integrated on product grids of `nodes` and `nodes / 2` standard-normal
/// quantiles per offset (midpoints of equal-probability bins), whose error
/// falls as the square of the spacing at the density's kinks; the two are
/// combined by Richardson's rule, `L_n + (L_n - L_{n/2}) / 3` per step
/// (README, experiment C, measures what is left against a grid of 48).
pub fn model_aotll<P: GaussianPolicy, O: ExtensibleObservation>(
    data: &Dataset,
    model: &ExtendedSsm<'_, '_, P, O>,
    nodes: usize,
) -> MeanOver {
    let Some(fine) = grid_log_marginals(data, model, nodes) else { return MeanOver::default() };
    let steps = match model.drift() {
        Some(_) if nodes >= 2 => {
            let coarse = grid_log_marginals(data, model, nodes / 2).expect("the same labels");
            fine.iter().zip(&coarse).map(|(&(f, items), &(c, _))| (f + (f - c) / 3.0, items)).collect()
        }
        _ => fine,
    };
    let mut per_item = Vec::new();
    for (log_density, items) in steps {
        per_item.extend(std::iter::repeat_n(log_density / items as f64, items));
    }
    MeanOver::of(&per_item)
}

/// Every labelled object-step's log-density of its items at the true state,
/// with its number of items; a drift integrated out on a product grid of
/// `nodes` quantiles per offset (see [`model_aotll`]). `None` without labels.
fn grid_log_marginals<P: GaussianPolicy, O: ExtensibleObservation>(
    data: &Dataset,
    model: &ExtendedSsm<'_, '_, P, O>,
    nodes: usize,
) -> Option<Vec<(f64, usize)>> {
    let truth = data.states()?;
    let grid: Vec<[f32; DRIFT_DIMS]> = match model.drift() {
        Some(_) => {
            let q: Vec<f32> = (0..nodes).map(|j| normal_quantile((j as f64 + 0.5) / nodes as f64) as f32).collect();
            let mut g = Vec::with_capacity(nodes.pow(3));
            for &a in &q {
                for &c in &q {
                    g.extend(q.iter().map(|&y| [a, c, y]));
                }
            }
            g
        }
        None => vec![[0.0; DRIFT_DIMS]],
    };
    let (n, dim) = (grid.len(), model.state_dim());
    let mut scratch = model.new_scratch();
    let (mut states, mut out) = (vec![0.0f32; dim * n], vec![0.0f32; n]);
    let drift_dims = if model.drift().is_some() { DRIFT_DIMS } else { 0 };
    for (k, column) in states.chunks_mut(n).enumerate().skip(STATE_DIM).take(drift_dims) {
        column.iter_mut().zip(&grid).for_each(|(x, g)| *x = g[k - STATE_DIM]);
    }
    model.predict_stationary_flips(n, &mut states);
    let mut steps = Vec::new();
    for object in 0..data.objects().len() {
        for t in 0..data.steps() {
            let (Some(state), items) = (truth.get(object, t), model.observation_count(object, t)) else { continue };
            if items == 0 {
                continue;
            }
            for (column, v) in states.chunks_mut(n).zip(state.to_array()) {
                column.fill(v as f32);
            }
            if model.observation_loglik(Batch { object, t, n }, &states, &mut out, &mut scratch) {
                let logs: Vec<f64> = out.iter().map(|&v| v as f64).collect();
                steps.push((log_sum_exp(&logs) - (n as f64).ln(), items));
            }
        }
    }
    Some(steps)
}

/// A box-detection model's AOTLL split by what it gets wrong ([`box_aotll_terms`]):
/// the detections whose heading is reversed against the label, and the others by
/// the density's factors — all of them, and apart for the cars moving along the
/// line of sight and across it (for a crossing car, along the line of sight is its
/// sideways direction).
#[derive(Clone, Debug, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct BoxAotllTerms {
    /// `log g` of the detections whose heading is more than pi/2 from the label's.
    pub reversed: MeanOver,
    /// What they carry of the AOTLL: their sum over every detection's count.
    pub reversed_contribution: f64,
    /// The other detections.
    pub others: FactorTerms,
    /// Those of them whose car's labelled heading is within 45 degrees of the line
    /// of sight (either way).
    pub in_line: FactorTerms,
    /// Those whose car's heading is more than 45 degrees from it: crossing it.
    pub crossing: FactorTerms,
}

/// The factors of `log g` over a group of detections ([`BoxAotllTerms`]), with the
/// network's scales beside the offsets the labels show.
#[derive(Clone, Debug, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct FactorTerms {
    /// `log g` of the group's detections.
    pub total: MeanOver,
    /// The along-line-of-sight factor.
    pub along: MeanOver,
    /// The across-line-of-sight factor.
    pub across: MeanOver,
    /// The yaw factor.
    pub yaw: MeanOver,
    /// Mean learned scales `(b_along, b_across, b_yaw)` (m, m, rad).
    pub mean_scales: (f64, f64, f64),
    /// Mean absolute offsets from the learned means (along, across, yaw): the
    /// Laplace scales that the labels alone would give at those means.
    pub mean_abs_offsets: (f64, f64, f64),
}

/// The running sums of one [`FactorTerms`] group.
#[derive(Default)]
struct FactorSums {
    total: Vec<f64>,
    along: Vec<f64>,
    across: Vec<f64>,
    yaw: Vec<f64>,
    scales: [f64; 3],
    offsets: [f64; 3],
}

impl FactorSums {
    fn push(&mut self, d: &DetectionDistribution, terms: &DetectionTerms) {
        self.total.push(terms.total());
        self.along.push(terms.along);
        self.across.push(terms.across);
        self.yaw.push(terms.yaw);
        let (ra, rc, ry) = terms.residuals;
        for (k, (b, r)) in [(d.b_along, ra), (d.b_across, rc), (d.b_yaw, ry)].into_iter().enumerate() {
            self.scales[k] += b;
            self.offsets[k] += r.abs();
        }
    }

    fn finish(&self) -> FactorTerms {
        let n = self.total.len().max(1) as f64;
        FactorTerms {
            total: MeanOver::of(&self.total),
            along: MeanOver::of(&self.along),
            across: MeanOver::of(&self.across),
            yaw: MeanOver::of(&self.yaw),
            mean_scales: (self.scales[0] / n, self.scales[1] / n, self.scales[2] / n),
            mean_abs_offsets: (self.offsets[0] / n, self.offsets[1] / n, self.offsets[2] / n),
        }
    }
}

/// [`BoxAotllTerms`] of `model` on `data`'s labelled steps; `None` without labels
/// or box detections.
pub fn box_aotll_terms(data: &Dataset, model: &BoxObservationModel, params: &ParamStore<f64>) -> Option<BoxAotllTerms> {
    let truth = data.states()?;
    if data.kind() != ObservationKind::Boxes {
        return None;
    }
    let mut reversed = Vec::new();
    let (mut others, mut in_line, mut crossing) = (FactorSums::default(), FactorSums::default(), FactorSums::default());
    for (ctx, pose, items) in labelled_steps::<BoxObservationModel>(data, truth) {
        let d = model.distribution(params, &ctx, pose);
        let bearing = (pose.y - ctx.av.y).atan2(pose.x - ctx.av.x);
        // The heading's angle to the line of sight, folded to [0, pi/2].
        let off_line = wrapped_abs_diff(pose.yaw, bearing).min(PI - wrapped_abs_diff(pose.yaw, bearing));
        let group = if off_line <= PI / 4.0 { &mut in_line } else { &mut crossing };
        for det in items {
            let terms = d.log_density_terms(&ctx.av, pose, det);
            if BoxObservationModel::heading_reversed(det, pose) {
                reversed.push(terms.total());
            } else {
                others.push(&d, &terms);
                group.push(&d, &terms);
            }
        }
    }
    let count = (reversed.len() + others.total.len()).max(1) as f64;
    Some(BoxAotllTerms {
        reversed_contribution: reversed.iter().sum::<f64>() / count,
        reversed: MeanOver::of(&reversed),
        others: others.finish(),
        in_line: in_line.finish(),
        crossing: crossing.finish(),
    })
}

/// APTLL: the mean `log pi(true a_t | true x_{t-1})` over the steps `t >= 1` with a
/// true action and a true previous state.
pub fn aptll<P: GaussianPolicy>(data: &Dataset, policy: &P) -> MeanOver {
    let (Some(states), Some(actions)) = (data.states(), data.actions()) else { return MeanOver::default() };
    let (mut v, mut kappa, mut accel, mut pinch) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for object in 0..data.objects().len() {
        for t in 1..data.steps() {
            if let (Some(prev), Some(a)) = (states.get(object, t - 1), actions.get(object, t)) {
                v.push(prev.v);
                kappa.push(prev.kappa);
                accel.push(a.accel);
                pinch.push(a.pinch);
            }
        }
    }
    let mut out = vec![0.0; v.len()];
    if !v.is_empty() {
        let mut scratch = ActionGaussians::default();
        policy.log_density(&v, &kappa, ActionsRef { accel: &accel, pinch: &pinch }, &mut scratch, &mut out);
    }
    MeanOver::of(&out)
}

/// The filter's estimates of every object's states.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Tracks {
    /// Filtering means `E[x_t | y_{0:t}]`, `[object][t]`.
    pub filtered: Vec<Vec<State>>,
    /// Fixed-lag smoothed means `E[x_t | y_{0:min(t+L,T)}]`, `[object][t]`.
    pub smoothed: Vec<Vec<State>>,
    /// The filter's per-object summaries (log-likelihood, observed units, ESS).
    pub summaries: Vec<ObjectSummary>,
}

impl Tracks {
    /// The summed log-likelihood estimate `l_hat`.
    pub fn log_likelihood(&self) -> f64 {
        self.summaries.iter().map(|s| s.log_likelihood).sum()
    }

    /// Observed units (points, detections) that entered the likelihood.
    pub fn observed_units(&self) -> usize {
        self.summaries.iter().map(|s| s.observed_units).sum()
    }

    /// Steps at which every particle was impossible.
    pub fn collapsed_steps(&self) -> usize {
        self.summaries.iter().map(|s| s.collapsed_steps).sum()
    }
}

fn to_states(rows: Vec<Vec<f64>>) -> Vec<State> {
    rows.into_iter()
        .map(|r| {
            let mut a = [0.0; STATE_DIM];
            a.copy_from_slice(&r[..STATE_DIM]);
            State::from_array(a)
        })
        .collect()
}

/// Runs the particle filter over every object of `data` and returns the filtering
/// and fixed-lag smoothed means (yaw averaged on the circle) with the filter's
/// summaries. Fails if the dataset's kind is not the one `observation` reads.
pub fn track<P: GaussianPolicy, O: ExtensibleObservation>(
    data: &Dataset,
    policy: &P,
    observation: &O,
    observation_params: &ParamStore<f64>,
    additions: ModelAdditions<'_>,
    config: &FilterConfig,
) -> Result<Tracks, String> {
    let base = VehicleSsm::new(data, policy, observation, observation_params)?;
    let model = additions.extend(&base).map_err(|e| e.to_string())?;
    let run = run_filter(&model, config, |_| Moments::new(model.state_dim(), &[YAW]));
    let mut tracks = Tracks { summaries: run.objects, ..Tracks::default() };
    for m in run.observers {
        tracks.filtered.push(to_states(m.filtered));
        tracks.smoothed.push(to_states(m.smoothed));
    }
    Ok(tracks)
}

/// Every metric of SPEC §5 for one run.
#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct Metrics {
    /// `l_hat / observed_units` (nats per point).
    pub mll: Option<f64>,
    /// The filter's `l_hat` summed over objects.
    pub log_likelihood: f64,
    /// Observed units (points or detections) in `l_hat`.
    pub observed_units: usize,
    /// Position and yaw errors of the fixed-lag smoothed means.
    pub smoothed: StateErrors,
    /// Position and yaw errors of the filtering means.
    pub filtered: StateErrors,
    /// Mean observation log-density at the true states, per item.
    pub aotll: MeanOver,
    /// Mean policy log-density of the true actions, per step.
    pub aptll: MeanOver,
    /// Steps at which every particle was impossible (observation skipped).
    pub collapsed_steps: usize,
    /// Particles per object.
    pub particles: usize,
    /// Fixed lag of the smoothed means.
    pub lag: usize,
    /// Seed of the filter.
    pub seed: u64,
}

impl Metrics {
    /// The scalar metrics by name (`mll`, `ade_smoothed`, `aye_smoothed`,
    /// `ade_filtered`, `aye_filtered`, `aotll`, `aptll`, `log_likelihood`,
    /// `observed_units`, `collapsed_steps`); missing values are `None`.
    pub fn scalars(&self) -> Vec<(&'static str, Option<f64>)> {
        vec![
            ("mll", self.mll),
            ("ade_smoothed", self.smoothed.ade),
            ("aye_smoothed", self.smoothed.aye),
            ("ade_filtered", self.filtered.ade),
            ("aye_filtered", self.filtered.aye),
            ("aotll", self.aotll.mean),
            ("aptll", self.aptll.mean),
            ("log_likelihood", Some(self.log_likelihood)),
            ("observed_units", Some(self.observed_units as f64)),
            ("collapsed_steps", Some(self.collapsed_steps as f64)),
        ]
    }
}

/// Computes every metric: one filter run with `config` (MLL, ADE/AYE of smoothed
/// and filtering means) plus AOTLL and APTLL at the true states and actions (which
/// need no filter). Fails if the dataset's kind is not the one `observation` reads.
pub fn evaluate<P: GaussianPolicy, O: ExtensibleObservation>(
    data: &Dataset,
    policy: &P,
    observation: &O,
    observation_params: &ParamStore<f64>,
    config: &FilterConfig,
) -> Result<Metrics, String> {
    let tracks = track(data, policy, observation, observation_params, ModelAdditions::NONE, config)?;
    Ok(metrics_of(data, &tracks, policy, observation, observation_params, ModelAdditions::NONE, config))
}

/// [`track`] with the policy, observation model and additions that `models` holds.
pub fn track_models(data: &Dataset, models: &Models, config: &FilterConfig) -> Result<Tracks, String> {
    struct Track<'a> {
        data: &'a Dataset,
        models: &'a Models,
        config: &'a FilterConfig,
    }
    impl ObservationVisitor for Track<'_> {
        type Output = Result<Tracks, String>;
        fn visit<O: ExtensibleObservation>(self, o: &O) -> Self::Output {
            let m = self.models;
            track(self.data, &m.policy, o, &m.observation_params, m.additions(), self.config)
        }
    }
    models.observation.visit(Track { data, models, config })
}

/// [`metrics_of`] with the policy, observation model and additions that `models` holds.
pub fn models_metrics_of(data: &Dataset, models: &Models, tracks: &Tracks, config: &FilterConfig) -> Metrics {
    struct Of<'a> {
        data: &'a Dataset,
        models: &'a Models,
        tracks: &'a Tracks,
        config: &'a FilterConfig,
    }
    impl ObservationVisitor for Of<'_> {
        type Output = Metrics;
        fn visit<O: ExtensibleObservation>(self, o: &O) -> Metrics {
            let m = self.models;
            metrics_of(self.data, self.tracks, &m.policy, o, &m.observation_params, m.additions(), self.config)
        }
    }
    models.observation.visit(Of { data, models, tracks, config })
}

/// The metrics of an existing filter run `tracks` (made with `config`) on `data`.
pub fn metrics_of<P: GaussianPolicy, O: ExtensibleObservation>(
    data: &Dataset,
    tracks: &Tracks,
    policy: &P,
    observation: &O,
    observation_params: &ParamStore<f64>,
    additions: ModelAdditions<'_>,
    config: &FilterConfig,
) -> Metrics {
    let aotll = extended_aotll(data, policy, observation, observation_params, additions);
    let (smoothed, filtered) = match data.states() {
        Some(truth) => (state_errors(&tracks.smoothed, truth), state_errors(&tracks.filtered, truth)),
        None => (StateErrors::default(), StateErrors::default()),
    };
    Metrics {
        mll: mll(tracks.log_likelihood(), tracks.observed_units()),
        log_likelihood: tracks.log_likelihood(),
        observed_units: tracks.observed_units(),
        smoothed,
        filtered,
        aotll,
        aptll: aptll(data, policy),
        collapsed_steps: tracks.collapsed_steps(),
        particles: config.sampling.particles,
        lag: config.lag,
        seed: config.seed,
    }
}

/// Median and IQR of each scalar metric ([`Metrics::scalars`]) over repeated runs,
/// in the order of [`Metrics::scalars`]; a metric missing from every run is `None`.
pub fn summarise_runs(runs: &[Metrics]) -> Vec<(&'static str, Option<Summary>)> {
    let Some(first) = runs.first() else { return Vec::new() };
    let names: Vec<&'static str> = first.scalars().into_iter().map(|(n, _)| n).collect();
    let table: Vec<Vec<(&'static str, Option<f64>)>> = runs.iter().map(|m| m.scalars()).collect();
    names
        .iter()
        .enumerate()
        .map(|(k, &name)| {
            let values: Vec<f64> = table.iter().filter_map(|row| row[k].1).collect();
            (name, Summary::of(&values))
        })
        .collect()
}
