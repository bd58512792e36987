//! PF-SEFI: the score by Fisher's identity with fixed-lag smoothing.
//!
//! For each step `t` the filter pushes the normalised weights of step
//! `s = min(t + L, T)` back along the ancestry onto the particles of `t` (a
//! scatter-add, so weights of particles sharing an ancestor are summed first).
//! Only particles with positive smoothed weight, the distinct ancestors, are kept,
//! each with its parent at `t - 1` and the action that led to it. The surrogate
//!
//! ```text
//! S(theta) = sum_t sum_{ancestors i} W^i [ log g(y_t | x_t^i) + log f(x_t^i | x_{t-1}^{parent}) ]
//! ```
//!
//! with particles and weights held constant is built on one tape per object and
//! differentiated by one reverse pass. `L = 0` gives filter marginals; `L >= T`
//! the full-path (degenerate) estimate.

use autodiff::{Float, Parallelism, Tape, Tensor, Var};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::ScoreEstimator;
use super::{by_precision, columns, reduction_blocks, zero_blocks, EstimateIn, EstimatorConfig, PartialEstimate};
use crate::filter::{filter_object, LagView, ObjectSummary, Observer, StepView};
use crate::models::{Block, DifferentiableModel};

/// PF-SEFI with fixed lag `L`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PfSefi {
    /// The fixed lag `L` (`0`: filter marginals; `>= T`: full paths).
    pub lag: usize,
}

impl ScoreEstimator for PfSefi {
    fn name(&self) -> String {
        "pf-sefi".into()
    }

    fn partial<M: DifferentiableModel>(&self, model: &M, config: &EstimatorConfig, seed: u64) -> PartialEstimate {
        by_precision(self, model, config, seed)
    }
}

/// The distinct fixed-lag ancestors of one object, in step order, with their
/// parents, actions and summed weights (dimension-major per component).
struct AncestorRows {
    blocks: Vec<Block>,
    /// Whether `y_t` entered the filter's weights, per step.
    used: Vec<bool>,
    states: Vec<Vec<f32>>,
    prev: Vec<Vec<f32>>,
    actions: Vec<Vec<f32>>,
    weights: Vec<f64>,
}

impl AncestorRows {
    fn new(d: usize, a: usize) -> Self {
        AncestorRows {
            blocks: Vec::new(),
            used: Vec::new(),
            states: vec![Vec::new(); d],
            prev: vec![Vec::new(); d],
            actions: vec![Vec::new(); a],
            weights: Vec::new(),
        }
    }

    fn rows(&self) -> usize {
        self.weights.len()
    }
}

/// Collects the distinct ancestors the filter hands over, for one object.
struct Collector {
    object: usize,
    rows: AncestorRows,
}

impl Observer for Collector {
    fn step(&mut self, view: &StepView<'_>) {
        debug_assert_eq!(self.rows.used.len(), view.t);
        self.rows.used.push(view.observation_used);
    }

    fn smoothed(&mut self, view: &LagView<'_>) {
        let n = view.n;
        let rows = &mut self.rows;
        let mut len = 0;
        for (i, &w) in view.weights.iter().enumerate() {
            if w <= 0.0 {
                continue;
            }
            len += 1;
            rows.weights.push(w);
            for (k, col) in rows.states.iter_mut().enumerate() {
                col.push(view.states[k * n + i]);
            }
            if let Some(prev) = view.prev_states {
                let p = view.parents[i];
                for (k, col) in rows.prev.iter_mut().enumerate() {
                    col.push(prev[k * n + p]);
                }
                for (k, col) in rows.actions.iter_mut().enumerate() {
                    col.push(view.actions[k * n + i]);
                }
            }
        }
        rows.blocks.push(Block { object: self.object, t: view.t, len });
    }
}

/// Constant `[R]` columns of the rows in `ranges` (start, len) of `cols`.
fn gather_columns<'t, F: Float>(tape: &'t Tape<F>, cols: &[Vec<f32>], ranges: &[(usize, usize)]) -> Vec<Var<'t, F>> {
    let total: usize = ranges.iter().map(|r| r.1).sum();
    let mut flat = Vec::with_capacity(cols.len() * total);
    for col in cols {
        for &(start, len) in ranges {
            flat.extend_from_slice(&col[start..start + len]);
        }
    }
    columns(tape, &flat, cols.len(), total)
}

fn gather_weights<'t, F: Float>(tape: &'t Tape<F>, w: &[f64], ranges: &[(usize, usize)]) -> Var<'t, F> {
    let v: Vec<F> = ranges.iter().flat_map(|&(s, l)| w[s..s + l].iter().map(|&x| F::from_f64(x))).collect();
    tape.constant(Tensor::from_vec(v))
}

impl EstimateIn for PfSefi {
    fn run<M: DifferentiableModel, F: Float>(&self, model: &M, config: &EstimatorConfig, seed: u64) -> PartialEstimate {
        let filter = config.filter(seed, self.lag, None);
        let (d, a) = (model.state_dim(), model.action_dim());
        let per_object: Vec<(ObjectSummary, Vec<Tensor<F>>, usize)> = (0..model.num_objects())
            .into_par_iter()
            .map_init(
                || (model.new_scratch(), Tape::<F>::new().with_parallelism(Parallelism::Serial)),
                |(scratch, tape), object| {
                    let mut collector = Collector { object, rows: AncestorRows::new(d, a) };
                    let (summary, _) = filter_object(model, &filter, object, scratch, &mut collector);
                    tape.reset();
                    let rows = collector.rows;
                    let grads = surrogate_gradient(model, tape, &rows);
                    (summary, grads, rows.rows())
                },
            )
            .collect();

        let mut partial = zero_blocks(model, config);
        let slots = config.sampling.particles * model.num_steps();
        for (block, range) in partial.blocks.iter_mut().zip(reduction_blocks(model.num_objects(), config.chunk_objects))
        {
            for (summary, grads, rows) in &per_object[range] {
                block.add_gradient(grads);
                block.add_summary(summary);
                block.rows_evaluated += rows;
                block.particle_slots += slots;
            }
        }
        partial
    }
}

/// The gradient of one object's surrogate: one forward over its distinct
/// ancestors and one reverse pass.
fn surrogate_gradient<M: DifferentiableModel, F: Float>(
    model: &M,
    tape: &Tape<F>,
    rows: &AncestorRows,
) -> Vec<Tensor<F>> {
    let params = model.bind(tape);
    // Row ranges of the blocks with a used observation, of those at t >= 1 and
    // of those at t = 0 (the prior's term, for a model whose prior has one).
    let mut obs_blocks = Vec::new();
    let mut obs_ranges = Vec::new();
    let mut trans_blocks = Vec::new();
    let mut trans_ranges = Vec::new();
    let mut prior_blocks = Vec::new();
    let mut prior_ranges = Vec::new();
    let mut start = 0;
    for b in &rows.blocks {
        if b.len > 0 && rows.used[b.t] {
            obs_blocks.push(*b);
            obs_ranges.push((start, b.len));
        }
        if b.t == 0 && b.len > 0 && model.has_prior_term() {
            prior_blocks.push(*b);
            prior_ranges.push((start, b.len));
        }
        if b.t > 0 && b.len > 0 {
            trans_blocks.push(*b);
            trans_ranges.push((start, b.len));
        }
        start += b.len;
    }
    let mut terms = Vec::new();
    if !obs_blocks.is_empty() {
        let states = gather_columns(tape, &rows.states, &obs_ranges);
        let w = gather_weights(tape, &rows.weights, &obs_ranges);
        terms.push((model.observation_log_density(&params, &obs_blocks, &states) * w).sum());
    }
    if !prior_blocks.is_empty() {
        let states = gather_columns(tape, &rows.states, &prior_ranges);
        if let Some(prior) = model.prior_log_density(&params, &prior_blocks, &states) {
            let w = gather_weights(tape, &rows.weights, &prior_ranges);
            terms.push((prior * w).sum());
        }
    }
    if !trans_blocks.is_empty() {
        let states = gather_columns(tape, &rows.states, &trans_ranges);
        // prev and actions hold only rows at t >= 1: shift the ranges by the t = 0 rows.
        let offset = rows.blocks.iter().filter(|b| b.t == 0).map(|b| b.len).sum::<usize>();
        let shifted: Vec<(usize, usize)> = trans_ranges.iter().map(|&(s, l)| (s - offset, l)).collect();
        let prev = gather_columns(tape, &rows.prev, &shifted);
        let actions = gather_columns(tape, &rows.actions, &shifted);
        let w = gather_weights(tape, &rows.weights, &trans_ranges);
        terms.push((model.transition_log_density(&params, &trans_blocks, &prev, &states, &actions) * w).sum());
    }
    let Some(&first) = terms.first() else {
        return params.iter().map(|p| Tensor::zeros(&p.shape())).collect();
    };
    let surrogate = terms[1..].iter().fold(first, |acc, &t| acc + t);
    let grads = tape.backward(surrogate);
    params.iter().map(|&p| grads.wrt(p)).collect()
}
