//! The bootstrap particle filter, batched over objects (in parallel with rayon),
//! with fixed-lag ancestry for smoothing and for PF-SEFI.
//!
//! Each object is filtered independently with its own random stream, seeded from
//! `(seed, object)`, so results do not depend on the number of threads. Log-weights
//! are kept normalised in f64; the log-likelihood increment at step `t` is
//! `ln sum_i W_{t-1}^i g(y_t | x_t^i)` (with `W` uniform after resampling), which is
//! also right under ESS-triggered resampling, where weights are carried.
//!
//! The particle history kept is a ring buffer of `L + 2` steps (states, the actions
//! drawn to reach them and the parent indices), so memory does not grow with `T`.
//! When step `s = t + L` has been weighted, the normalised weights `W_s` are pushed
//! back along the ancestry by scatter-adds to step `t` and handed to an
//! [`Observer`] as the fixed-lag smoothing weights of the particles at `t`; after
//! the last step the remaining `L` steps are flushed with `W_T`.
//!
//! If every particle is impossible at some step (all log-weights `-inf` or NaN) the
//! step's observation is skipped, the previous weights are kept and the step is
//! counted in [`ObjectSummary::collapsed_steps`]: no NaN or `-inf` ever reaches the
//! weights or the likelihood.
//!
//! [`paths`] draws whole paths from an object's genealogy (the smoother's draws).

mod moments;
pub mod paths;
mod resample;
mod tempering;

use crate::stats::log_sum_exp;
use std::time::{Duration, Instant};

use rand::rngs::SmallRng;
use rand::SeedableRng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

pub use moments::Moments;
pub use resample::{effective_sample_size, Resampling};
use tempering::{reweight, ParentStep, StepParticles, Temperer};
pub use tempering::{FilterPurpose, Tempering, BOX_ORIGIN_STEPS};

use crate::models::{Batch, Drawn, ParticleModel};
use crate::util::seed::splitmix64;

/// How a filter draws and resamples its particles: the settings a filter run
/// ([`FilterConfig`]) and a score estimator
/// ([`EstimatorConfig`](crate::estimators::EstimatorConfig)) share. Both embed it
/// flattened, so their serialized forms keep these fields at the top level.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sampling {
    /// Particles per object (`N`).
    pub particles: usize,
    /// Resampling scheme.
    pub resampling: Resampling,
    /// Resample only when the ESS falls below this fraction of `N`; `None` resamples
    /// at every step.
    pub ess_threshold: Option<f64>,
    /// Tempering within a step with MCMC moves ([`Tempering`]) for sharp
    /// observations; `None` is the bootstrap filter. Needs a model with a
    /// noise-driven form; not with soft resampling, and not for the
    /// through-filter baselines (they replay the bootstrap filter on a tape).
    #[serde(default)]
    pub tempering: Option<Tempering>,
}

impl Default for Sampling {
    fn default() -> Self {
        Sampling { particles: 1024, resampling: Resampling::Systematic, ess_threshold: None, tempering: None }
    }
}

impl Sampling {
    /// `particles` per object, tempered by `tempering` (`None`: the bootstrap
    /// filter), resampled systematically at every step.
    pub fn new(particles: usize, tempering: Option<Tempering>) -> Self {
        Sampling { particles, tempering, ..Sampling::default() }
    }
}

/// Settings of a particle-filter run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FilterConfig {
    /// Particles, resampling and tempering.
    #[serde(flatten)]
    pub sampling: Sampling,
    /// Fixed lag `L` of the smoothing weights handed to observers.
    pub lag: usize,
    /// Seed of the random streams.
    pub seed: u64,
    /// PFNET's soft resampling (Karkus et al. 2018): with `Some(alpha)` ancestors are
    /// drawn from `q = alpha W + (1 - alpha) / N` and carry the weights
    /// `W^a / q^a`, normalised. `None` is ordinary resampling.
    #[serde(default)]
    pub soft_resampling: Option<f64>,
}

impl Default for FilterConfig {
    fn default() -> Self {
        FilterConfig { sampling: Sampling::default(), lag: 8, seed: 0, soft_resampling: None }
    }
}

impl FilterConfig {
    /// `sampling` with lag `lag` and seed `seed`, without soft resampling.
    pub fn new(sampling: Sampling, lag: usize, seed: u64) -> Self {
        FilterConfig { sampling, lag, seed, soft_resampling: None }
    }
}

/// The particles at step `t` with their fixed-lag smoothing weights.
pub struct LagView<'a> {
    /// The step.
    pub t: usize,
    /// Number of particles.
    pub n: usize,
    /// `x_t`, dimension-major (`state_dim * n`).
    pub states: &'a [f32],
    /// What was drawn to reach `x_t` (`action_dim * n`; empty at `t = 0`).
    pub actions: &'a [f32],
    /// For each particle, the index of its parent in `prev_states` (empty at `t = 0`).
    pub parents: &'a [usize],
    /// `x_{t-1}` (`None` at `t = 0`).
    pub prev_states: Option<&'a [f32]>,
    /// Smoothing weights `p(x_t^i | y_{0:min(t+L, T)})`, summing to one.
    pub weights: &'a [f64],
}

/// One step of the filter as it happened: what the through-filter estimators
/// record to replay the filter on a tape.
pub struct StepView<'a> {
    /// The step.
    pub t: usize,
    /// Number of particles.
    pub n: usize,
    /// `x_t`, dimension-major (`state_dim * n`).
    pub states: &'a [f32],
    /// What was drawn to reach `x_t` (`action_dim * n`; empty at `t = 0`).
    pub actions: &'a [f32],
    /// The index of each particle's parent at `t - 1` (empty at `t = 0`).
    pub parents: &'a [usize],
    /// Whether the parents were drawn by resampling at this step (otherwise each
    /// particle continues its own path and carries its weight).
    pub resampled: bool,
    /// Whether `y_t` entered the weights (false when there is none, or when every
    /// particle was impossible and the step was skipped).
    pub observation_used: bool,
    /// Normalised log-weights after weighting by `y_t`.
    pub log_weights: &'a [f64],
    /// The tempered filter's step `t - 1` as it stands after step `t` (`None` for
    /// the bootstrap filter and at `t = 0`): re-indexed one-to-one with the
    /// particles of `t` (so `parents` is the identity) and changed by lookback
    /// moves. An observer that keeps the genealogy replaces its record of `t - 1`
    /// with it.
    pub revised_parent: Option<RevisedParent<'a>>,
    /// The steps `0..t-1` before it, as they stand after step `t`, when the
    /// tempered filter's origin moves revised whole paths at `t` (empty
    /// otherwise; see [`Tempering::origin_steps`]): each re-indexed one-to-one
    /// with the particles of `t` like `revised_parent`.
    pub revised_earlier: Vec<RevisedParent<'a>>,
}

/// Step `t - 1` of the tempered filter as revised while filtering step `t` (see
/// [`StepView::revised_parent`]).
#[derive(Clone, Copy, Debug)]
pub struct RevisedParent<'a> {
    /// `x_{t-1}`, dimension-major, one per particle of `t`.
    pub states: &'a [f32],
    /// What was drawn to reach `x_{t-1}` (empty when `t - 1 = 0`).
    pub actions: &'a [f32],
    /// Each one's parent at `t - 2` (empty when `t - 1 = 0`).
    pub parents: &'a [usize],
}

/// Receives what the filter computes for one object, as it computes it.
pub trait Observer: Send {
    /// Every step as it happened, before [`Observer::filtered`] for the same step.
    fn step(&mut self, _view: &StepView<'_>) {}
    /// The particles at `t` with their normalised filtering weights.
    fn filtered(&mut self, _t: usize, _states: &[f32], _weights: &[f64]) {}
    /// The particles at `t` with their fixed-lag smoothing weights (each `t` once, in order).
    fn smoothed(&mut self, _view: &LagView<'_>) {}
}

impl Observer for () {}

/// What the filter measured for one object.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ObjectSummary {
    /// The estimate `l_hat = ln p_hat(y_{0:T})`.
    pub log_likelihood: f64,
    /// Observed units (points, detections) that entered the likelihood.
    pub observed_units: usize,
    /// Steps at which every particle was impossible (their observation was skipped).
    pub collapsed_steps: usize,
    /// Steps at which the particles were resampled.
    pub resampled_steps: usize,
    /// Smallest effective sample size after weighting.
    pub min_ess: f64,
    /// Mean effective sample size after weighting.
    pub mean_ess: f64,
    /// Intermediate stages of the tempered filter (0 for the bootstrap filter, and
    /// for steps it took in one go).
    #[serde(default)]
    pub tempering_stages: usize,
    /// Metropolis moves proposed by the tempered filter.
    #[serde(default)]
    pub moves_proposed: usize,
    /// Metropolis moves accepted.
    #[serde(default)]
    pub moves_accepted: usize,
    /// Evaluations of the observation log-likelihood of all `N` particles: one per
    /// observed step for the bootstrap filter; the tempered filter's cost beyond
    /// that is in its extra evaluations.
    #[serde(default)]
    pub likelihood_evaluations: usize,
}

/// Time spent in each phase, summed over objects (and so over threads).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PhaseTimes {
    /// Drawing from the prior and the transition.
    pub propagate: Duration,
    /// Evaluating observation log-likelihoods.
    pub likelihood: Duration,
    /// Normalising, resampling and gathering parents.
    pub resample: Duration,
    /// Pushing weights back along the ancestry and calling observers.
    pub smoothing: Duration,
}

impl PhaseTimes {
    fn add(&mut self, o: &PhaseTimes) {
        self.propagate += o.propagate;
        self.likelihood += o.likelihood;
        self.resample += o.resample;
        self.smoothing += o.smoothing;
    }
}

/// The result of filtering every object.
pub struct FilterRun<O> {
    /// Per-object summaries, in object order.
    pub objects: Vec<ObjectSummary>,
    /// Per-object observers, in object order.
    pub observers: Vec<O>,
    /// Time per phase, summed over objects.
    pub times: PhaseTimes,
}

impl<O> FilterRun<O> {
    /// Sum of the objects' log-likelihood estimates.
    pub fn log_likelihood(&self) -> f64 {
        self.objects.iter().map(|o| o.log_likelihood).sum()
    }

    /// Total observed units.
    pub fn observed_units(&self) -> usize {
        self.objects.iter().map(|o| o.observed_units).sum()
    }

    /// Total collapsed steps.
    pub fn collapsed_steps(&self) -> usize {
        self.objects.iter().map(|o| o.collapsed_steps).sum()
    }
}

/// The seed of one random stream: SplitMix64 of the seed and the stream's key
/// (an object's [`ParticleModel::stream_key`], or any other index).
pub fn stream_seed(seed: u64, key: u64) -> u64 {
    splitmix64(seed ^ splitmix64(key ^ 0x5eed))
}

/// Filters every object of `model`, in parallel over objects. `make_observer(object)`
/// builds the observer that receives that object's filtering and smoothing output.
pub fn run_filter<M, O>(model: &M, config: &FilterConfig, make_observer: impl Fn(usize) -> O + Sync) -> FilterRun<O>
where
    M: ParticleModel,
    O: Observer,
{
    assert!(config.sampling.particles > 0, "run_filter: need at least one particle");
    let results: Vec<(ObjectSummary, O, PhaseTimes)> = (0..model.num_objects())
        .into_par_iter()
        .map_init(
            || model.new_scratch(),
            |scratch, object| {
                let mut observer = make_observer(object);
                let (summary, times) = filter_object(model, config, object, scratch, &mut observer);
                (summary, observer, times)
            },
        )
        .collect();
    let mut times = PhaseTimes::default();
    let mut objects = Vec::with_capacity(results.len());
    let mut observers = Vec::with_capacity(results.len());
    for (s, o, t) in results {
        times.add(&t);
        objects.push(s);
        observers.push(o);
    }
    FilterRun { objects, observers, times }
}

/// The particle history of the last `L + 2` steps.
struct Ring {
    slots: usize,
    states: Vec<Vec<f32>>,
    actions: Vec<Vec<f32>>,
    parents: Vec<Vec<usize>>,
}

impl Ring {
    fn new(slots: usize, n: usize, d: usize, a: usize) -> Self {
        Ring {
            slots,
            states: vec![vec![0.0; d * n]; slots],
            actions: vec![vec![0.0; a * n]; slots],
            parents: vec![(0..n).collect(); slots],
        }
    }
    fn slot(&self, t: usize) -> usize {
        t % self.slots
    }

    /// Moves the states and actions of `slot` out (put them back with [`Ring::put`]).
    fn take(&mut self, slot: usize) -> [Vec<f32>; 2] {
        [std::mem::take(&mut self.states[slot]), std::mem::take(&mut self.actions[slot])]
    }

    /// Puts back what [`Ring::take`] moved out.
    fn put(&mut self, slot: usize, [states, actions]: [Vec<f32>; 2]) {
        self.states[slot] = states;
        self.actions[slot] = actions;
    }

    /// Re-indexes every step `0..t-1` by the particles of `t` (each particle's own
    /// path, un-shared: the origin moves change whole paths). Every earlier step
    /// must already be one-to-one with the particles of `t - 1` (this was done at
    /// every step since 1); slot `t - 1`'s states come from `gathered` as in
    /// [`Ring::reindex_parent_step`], and every parent index becomes the identity.
    fn reindex_history(&mut self, t: usize, ancestors: &[usize], gathered: &mut Vec<f32>) {
        let n = ancestors.len();
        let mut buffer = Vec::new();
        for s in 0..t - 1 {
            let slot = self.slot(s);
            for values in [&mut self.states[slot], &mut self.actions[slot]] {
                buffer.clear();
                for column in values.chunks_exact(n) {
                    buffer.extend(ancestors.iter().map(|&i| column[i]));
                }
                std::mem::swap(values, &mut buffer);
            }
        }
        self.reindex_parent_step(t, ancestors, gathered);
        for s in 1..=t {
            let slot = self.slot(s);
            self.parents[slot].iter_mut().enumerate().for_each(|(i, p)| *p = i);
        }
    }

    /// Re-indexes step `t - 1` by the particles of `t` (particle `i` of `t - 1`
    /// becomes the one `ancestors[i]` was): the states come from `gathered`,
    /// which holds them already and receives the old ones; the parents of `t`
    /// become the identity.
    fn reindex_parent_step(&mut self, t: usize, ancestors: &[usize], gathered: &mut Vec<f32>) {
        let (slot, prev) = (self.slot(t), self.slot(t - 1));
        let n = ancestors.len();
        std::mem::swap(&mut self.states[prev], gathered);
        let actions = &mut self.actions[prev];
        let mut buffer = Vec::with_capacity(actions.len());
        for column in actions.chunks_exact(n) {
            buffer.extend(ancestors.iter().map(|&i| column[i]));
        }
        *actions = buffer;
        let reindexed: Vec<usize> = ancestors.iter().map(|&i| self.parents[prev][i]).collect();
        self.parents[prev] = reindexed;
        self.parents[slot].iter_mut().enumerate().for_each(|(i, p)| *p = i);
    }
}

/// Filters one object; the core loop of [`run_filter`].
pub fn filter_object<M: ParticleModel, O: Observer>(
    model: &M,
    config: &FilterConfig,
    object: usize,
    scratch: &mut M::Scratch,
    observer: &mut O,
) -> (ObjectSummary, PhaseTimes) {
    let n = config.sampling.particles;
    let (d, a) = (model.state_dim(), model.action_dim());
    let steps = model.num_steps();
    let lag = config.lag;
    let mut rng = SmallRng::seed_from_u64(stream_seed(config.seed, model.stream_key(object)));
    // The tempered filter's lookback moves reach back to x_{t-2}, its origin moves
    // to x_0 up to step `origin_steps`.
    let slots = match config.sampling.tempering {
        Some(c) => (lag + 2).max(3).max(c.origin_steps + 1),
        None => lag + 2,
    };
    let mut ring = Ring::new(slots, n, d, a);
    let mut times = PhaseTimes::default();
    let mut summary = ObjectSummary { min_ess: f64::INFINITY, ..Default::default() };

    let uniform = -(n as f64).ln();
    let mut log_w = vec![uniform; n]; // normalised log-weights
    let mut soft_log_w = vec![uniform; n];
    let mut weights = vec![1.0 / n as f64; n];
    let mut loglik = vec![0.0f32; n];
    let mut log_lik64 = Vec::with_capacity(n);
    let mut gathered = vec![0.0f32; d * n];
    let mut ancestors: Vec<usize> = (0..n).collect();
    let mut resample_scratch = Vec::with_capacity(n);
    let mut push = (vec![0.0f64; n], vec![0.0f64; n]);
    let mut ess_sum = 0.0;
    let mut soft_q = Vec::with_capacity(if config.soft_resampling.is_some() { n } else { 0 });
    let mut resampled = false;
    assert!(
        config.sampling.tempering.is_none() || config.soft_resampling.is_none(),
        "filter: tempering and soft resampling do not combine (soft resampling is PFNET's, a through-filter baseline)"
    );
    let mut temperer = config.sampling.tempering.map(|c| Temperer::new(model, c));

    for t in 0..steps {
        let slot = ring.slot(t);
        let mut proposed = false;
        let clock = Instant::now();
        if t == 0 {
            match &mut temperer {
                Some(tm) => {
                    let to = Drawn { next: &mut ring.states[slot], actions: &mut [] };
                    tm.draw(model, Batch { object, t: 0, n }, &[], to, &mut rng, scratch)
                }
                None => model.sample_prior(object, n, &mut rng, &mut ring.states[slot], scratch),
            }
            times.propagate += clock.elapsed();
        } else {
            let prev = ring.slot(t - 1);
            let resample_now = match config.sampling.ess_threshold {
                None => true,
                Some(frac) => effective_sample_size(&weights) < frac * n as f64,
            };
            if let (true, Some(alpha)) = (resample_now, config.soft_resampling) {
                // Draw from q = alpha W + (1 - alpha) / N; carry W^a / q^a, normalised.
                let floor = (1.0 - alpha) / n as f64;
                soft_q.clear();
                soft_q.extend(weights.iter().map(|&w| alpha * w + floor));
                config.sampling.resampling.draw(&soft_q, &mut rng, &mut ancestors, &mut resample_scratch);
                for (lw, &p) in soft_log_w.iter_mut().zip(&ancestors) {
                    *lw = log_w[p] - soft_q[p].ln();
                }
                let lse = log_sum_exp(&soft_log_w);
                log_w.iter_mut().zip(&soft_log_w).for_each(|(lw, &b)| *lw = b - lse);
                summary.resampled_steps += 1;
            } else if resample_now {
                config.sampling.resampling.draw(&weights, &mut rng, &mut ancestors, &mut resample_scratch);
                log_w.fill(uniform);
                summary.resampled_steps += 1;
            } else {
                ancestors.iter_mut().enumerate().for_each(|(i, p)| *p = i);
            }
            resampled = resample_now;
            for k in 0..d {
                let src = &ring.states[prev][k * n..(k + 1) * n];
                for (g, &p) in gathered[k * n..(k + 1) * n].iter_mut().zip(&ancestors) {
                    *g = src[p];
                }
            }
            ring.parents[slot].copy_from_slice(&ancestors);
            if let Some(tm) = &mut temperer {
                // One parent per particle: slot t - 1 re-indexed by the particles
                // of t, so that a lookback move changes one particle's parent
                // (every earlier step too while origin moves change whole paths).
                if tm.origin_at(t) {
                    ring.reindex_history(t, &ancestors, &mut gathered);
                } else {
                    ring.reindex_parent_step(t, &ancestors, &mut gathered);
                }
                tm.carry(t, &ancestors);
            }
            let mid = Instant::now();
            times.resample += mid - clock;
            if let Some(tm) = &mut temperer {
                let [mut states, mut actions] = ring.take(slot);
                let parent_states = &ring.states[prev];
                let to = Drawn { next: &mut states[..], actions: &mut actions[..] };
                tm.draw(model, Batch { object, t, n }, parent_states, to, &mut rng, scratch);
                ring.put(slot, [states, actions]);
            } else {
                let to = Drawn { next: &mut ring.states[slot], actions: &mut ring.actions[slot] };
                model.propagate(Batch { object, t, n }, &gathered, to, &mut rng, scratch);
            }
            if temperer.is_none() && model.proposal_log_weights(n, &mut loglik, scratch) {
                // Drawn from a proposal: weight by transition over proposal. The
                // weights' sum then estimates 1 and enters the likelihood below.
                for (lw, &c) in log_w.iter_mut().zip(&loglik) {
                    *lw += if c.is_nan() { f64::NEG_INFINITY } else { c as f64 };
                }
                proposed = true;
            }
            times.propagate += mid.elapsed();
        }

        // Weight by the observation (if any): in one go, or through tempered stages.
        let clock = Instant::now();
        let (mut observed, increment) = match &mut temperer {
            Some(tm) => {
                let [mut states, mut actions] = ring.take(slot);
                let parent_slot = ring.slot(t.wrapping_sub(1));
                let [mut p_states, mut p_actions] = if t > 0 { ring.take(parent_slot) } else { Default::default() };
                let mut p_parents = if t > 0 { std::mem::take(&mut ring.parents[parent_slot]) } else { Vec::new() };
                let origin = t >= 2 && tm.origin_at(t);
                let mut history: Vec<[Vec<f32>; 2]> =
                    if origin { (0..t - 1).map(|s| ring.take(ring.slot(s))).collect() } else { Vec::new() };
                let grandparents = (t >= 2 && !origin).then(|| &ring.states[ring.slot(t - 2)][..]);
                let parent = (t > 0).then_some(ParentStep {
                    states: &mut p_states,
                    actions: &mut p_actions,
                    parents: &mut p_parents,
                    grandparents,
                });
                let particles = StepParticles { states: &mut states, actions: &mut actions, parent };
                let w = tm.weigh(
                    model,
                    Batch { object, t, n },
                    particles,
                    origin.then_some(&mut history[..]),
                    &mut log_w,
                    config.sampling.resampling,
                    &mut rng,
                    scratch,
                );
                ring.put(slot, [states, actions]);
                if t > 0 {
                    ring.put(parent_slot, [p_states, p_actions]);
                    ring.parents[parent_slot] = p_parents;
                }
                for (s, step) in history.into_iter().enumerate() {
                    ring.put(ring.slot(s), step);
                }
                summary.tempering_stages += w.stages;
                summary.moves_proposed += w.proposed;
                summary.moves_accepted += w.accepted;
                summary.likelihood_evaluations += if w.observed { w.evaluations } else { 0 };
                (w.observed, w.increment)
            }
            None => {
                let observed =
                    model.observation_loglik(Batch { object, t, n }, &ring.states[slot], &mut loglik, scratch);
                let mut increment = None;
                if observed {
                    summary.likelihood_evaluations += 1;
                    log_lik64.clear();
                    log_lik64.extend(loglik.iter().map(|&l| if l.is_nan() { f64::NEG_INFINITY } else { l as f64 }));
                    increment = reweight(&mut log_w, &log_lik64, 1.0);
                }
                (observed, increment)
            }
        };
        let mid = Instant::now();
        times.likelihood += mid - clock;
        if observed {
            match increment {
                Some(lse) => {
                    summary.log_likelihood += lse;
                    summary.observed_units += model.observation_count(object, t);
                }
                None => {
                    // Every particle impossible: the previous weights are kept and
                    // this observation is skipped.
                    summary.collapsed_steps += 1;
                    observed = false;
                }
            }
        }
        if proposed && !observed {
            let lse = log_sum_exp(&log_w);
            if lse.is_finite() {
                summary.log_likelihood += lse;
                log_w.iter_mut().for_each(|lw| *lw -= lse);
            } else {
                summary.collapsed_steps += 1;
                log_w.fill(uniform);
            }
        }
        for (w, &lw) in weights.iter_mut().zip(&log_w) {
            *w = lw.exp();
        }
        let ess = effective_sample_size(&weights);
        ess_sum += ess;
        summary.min_ess = summary.min_ess.min(ess);
        times.resample += mid.elapsed();

        let clock = Instant::now();
        observer.step(&StepView {
            t,
            n,
            states: &ring.states[slot],
            actions: if t == 0 { &[] } else { &ring.actions[slot] },
            parents: if t == 0 { &[] } else { &ring.parents[slot] },
            resampled: t > 0 && resampled,
            observation_used: observed,
            log_weights: &log_w,
            revised_parent: (temperer.is_some() && t > 0).then(|| {
                let prev = ring.slot(t - 1);
                RevisedParent {
                    states: &ring.states[prev],
                    actions: if t == 1 { &[] } else { &ring.actions[prev] },
                    parents: if t == 1 { &[] } else { &ring.parents[prev] },
                }
            }),
            revised_earlier: match &temperer {
                Some(tm) if t >= 2 && tm.origin_at(t) => (0..t - 1)
                    .map(|s| {
                        let slot = ring.slot(s);
                        RevisedParent {
                            states: &ring.states[slot],
                            actions: if s == 0 { &[] } else { &ring.actions[slot] },
                            parents: if s == 0 { &[] } else { &ring.parents[slot] },
                        }
                    })
                    .collect(),
                _ => Vec::new(),
            },
        });
        observer.filtered(t, &ring.states[slot], &weights);
        if t >= lag {
            emit_smoothed(&ring, t - lag, t, n, &weights, &mut push, observer);
        }
        times.smoothing += clock.elapsed();
    }
    // Flush the last L steps with the final weights.
    let clock = Instant::now();
    let last = steps - 1;
    let first_unflushed = if last >= lag { last - lag + 1 } else { 0 };
    for u in first_unflushed..steps {
        emit_smoothed(&ring, u, last, n, &weights, &mut push, observer);
    }
    times.smoothing += clock.elapsed();
    summary.mean_ess = ess_sum / steps as f64;
    (summary, times)
}

/// Pushes the weights of step `s` back along the ancestry to step `u` (scatter-adds
/// over parents) and hands the particles of `u` to the observer.
fn emit_smoothed<O: Observer>(
    ring: &Ring,
    u: usize,
    s: usize,
    n: usize,
    weights_s: &[f64],
    push: &mut (Vec<f64>, Vec<f64>),
    observer: &mut O,
) {
    let (cur, next) = push;
    cur.copy_from_slice(weights_s);
    for k in (u + 1..=s).rev() {
        next.fill(0.0);
        for (&p, &w) in ring.parents[ring.slot(k)].iter().zip(cur.iter()) {
            next[p] += w;
        }
        std::mem::swap(cur, next);
    }
    let slot = ring.slot(u);
    let view = LagView {
        t: u,
        n,
        states: &ring.states[slot],
        actions: if u == 0 { &[] } else { &ring.actions[slot] },
        parents: if u == 0 { &[] } else { &ring.parents[slot] },
        prev_states: if u == 0 { None } else { Some(&ring.states[ring.slot(u - 1)]) },
        weights: cur,
    };
    observer.smoothed(&view);
}
