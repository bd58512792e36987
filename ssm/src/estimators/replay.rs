//! The through-filter baselines: PF, DPF-SGR (two variants) and PFNET.
//!
//! Each object is filtered forward once (f32, no tape), recording every step's
//! particles, actions, ancestors, whether it resampled and whether its
//! observation was used. The filter is then replayed on a tape with the recorded
//! ancestors and noise held constant, which is exactly differentiating the filter
//! with resampling indices treated as constants:
//!
//! - **PF**: weights after resampling are the constant `1/N`; particles are
//!   reparameterised (`x_t` depends on `theta` through the policy and `x_{t-1}`).
//! - **DPF-SGR** (Scibior & Wood 2021): after resampling each particle carries
//!   `log W^a - stopgrad(log W^a) - log N` (value `-log N`, gradient of `log W^a`).
//!   The likelihood is accumulated as SPEC §2 requires: the carried log-weights
//!   are normalised (`log W_t = log_softmax(L_t)`) and each step adds the
//!   log-sum-exp of the next carried-plus-observation log-weights.
//! - **DPF-SGR, particles stopped**: as DPF-SGR with every particle constant; the
//!   transition enters the weight as `log f - stopgrad(log f)`. Its gradient is
//!   PF-SEFI's with `L >= T` on the same draws.
//! - **PFNET** (Karkus et al. 2018): ancestors drawn from
//!   `q = alpha W + (1 - alpha)/N` carry `W^a / q^a`, normalised, differentiable.
//!
//! Objects are processed in chunks of [`EstimatorConfig::chunk_objects`]: a tape
//! holds the whole filter of a chunk's objects (`O(C N T)` memory) and is reset
//! before the next chunk (one tape per worker, so its buffers are recycled); chunks
//! run in parallel on the rayon pool.

use autodiff::{Float, Parallelism, Tape, Tensor, Var};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::ScoreEstimator;
use super::{by_precision, columns, reduction_blocks, zero_blocks, EstimateIn, EstimatorConfig, PartialEstimate};
use crate::filter::{filter_object, ObjectSummary, Observer, StepView};
use crate::models::{Block, DifferentiableModel};

/// Which baseline.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum ThroughFilterKind {
    /// `l_hat` through the filter; post-resampling weights constant.
    Pf,
    /// DPF-SGR as in the paper: stop-gradient on the post-resampling weights only.
    DpfSgr,
    /// DPF-SGR with the particles stopped too.
    DpfSgrStopped,
    /// PFNET soft resampling with mixing `alpha` in `(0, 1]`.
    Pfnet {
        /// Weight of the filter's weights in the proposal `q`.
        alpha: f64,
    },
}

/// A baseline that differentiates the filter itself.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThroughFilter {
    /// Which baseline.
    pub kind: ThroughFilterKind,
}

impl ScoreEstimator for ThroughFilter {
    fn name(&self) -> String {
        match self.kind {
            ThroughFilterKind::Pf => "pf",
            ThroughFilterKind::DpfSgr => "dpf-sgr",
            ThroughFilterKind::DpfSgrStopped => "dpf-sgr-stopped",
            ThroughFilterKind::Pfnet { .. } => "pfnet",
        }
        .into()
    }

    fn partial<M: DifferentiableModel>(&self, model: &M, config: &EstimatorConfig, seed: u64) -> PartialEstimate {
        by_precision(self, model, config, seed)
    }
}

/// One object's filter, step by step.
#[derive(Default)]
struct Record {
    states: Vec<Vec<f32>>,
    actions: Vec<Vec<f32>>,
    parents: Vec<Vec<usize>>,
    resampled: Vec<bool>,
    used: Vec<bool>,
}

impl Observer for Record {
    fn step(&mut self, view: &StepView<'_>) {
        self.states.push(view.states.to_vec());
        self.actions.push(view.actions.to_vec());
        self.parents.push(view.parents.to_vec());
        self.resampled.push(view.resampled);
        self.used.push(view.observation_used);
    }
}

impl EstimateIn for ThroughFilter {
    fn run<M: DifferentiableModel, F: Float>(&self, model: &M, config: &EstimatorConfig, seed: u64) -> PartialEstimate {
        let soft = match self.kind {
            ThroughFilterKind::Pfnet { alpha } => Some(alpha),
            _ => None,
        };
        // The replay needs every step: the lag only sizes the filter's ring.
        let filter = config.filter(seed, 0, soft);
        assert!(
            filter.sampling.tempering.is_none(),
            "{}: the through-filter baselines replay the bootstrap filter; tempering is for PF-SEFI",
            self.name()
        );
        // The tapes' chunks are the blocks of the exact reduction.
        let objects: Vec<usize> = (0..model.num_objects()).collect();
        let chunks: Vec<&[usize]> =
            reduction_blocks(objects.len(), config.chunk_objects).map(|r| &objects[r]).collect();
        let per_chunk: Vec<(Vec<ObjectSummary>, Vec<Tensor<F>>)> = chunks
            .par_iter()
            .map_init(
                || (model.new_scratch(), Tape::<F>::new().with_parallelism(Parallelism::Serial)),
                |(scratch, tape), chunk| {
                    let mut summaries = Vec::with_capacity(chunk.len());
                    let mut records = Vec::with_capacity(chunk.len());
                    for &object in chunk.iter() {
                        let mut record = Record::default();
                        let (summary, _) = filter_object(model, &filter, object, scratch, &mut record);
                        summaries.push(summary);
                        records.push(record);
                    }
                    // One tape per worker, reset per chunk: its buffers are recycled.
                    tape.reset();
                    let grads = replay_gradient(model, tape, self.kind, config.sampling.particles, chunk, &records);
                    (summaries, grads)
                },
            )
            .collect();

        let mut partial = zero_blocks(model, config);
        let slots = config.sampling.particles * model.num_steps();
        for (block, (summaries, grads)) in partial.blocks.iter_mut().zip(&per_chunk) {
            block.add_gradient(grads);
            for s in summaries {
                block.add_summary(s);
            }
            block.rows_evaluated = slots * summaries.len();
            block.particle_slots = slots * summaries.len();
        }
        partial
    }
}

/// Dimension-major values of every object of a chunk at one step, as constant columns.
fn chunk_columns<'t, F: Float>(tape: &'t Tape<F>, per_object: &[&[f32]], dims: usize, n: usize) -> Vec<Var<'t, F>> {
    let c = per_object.len();
    let mut flat = Vec::with_capacity(dims * c * n);
    for k in 0..dims {
        for values in per_object {
            flat.extend_from_slice(&values[k * n..(k + 1) * n]);
        }
    }
    columns(tape, &flat, dims, c * n)
}

/// Replays the filter of a chunk of objects on `tape` and returns the gradient of
/// the baseline's objective (the sum of the objects' `l_hat`).
fn replay_gradient<M: DifferentiableModel, F: Float>(
    model: &M,
    tape: &Tape<F>,
    kind: ThroughFilterKind,
    n: usize,
    objects: &[usize],
    records: &[Record],
) -> Vec<Tensor<F>> {
    let params = model.bind(tape);
    let (d, a) = (model.state_dim(), model.action_dim());
    let c = objects.len();
    let r = c * n;
    let ln_n = (n as f64).ln();
    let uniform = || tape.constant(Tensor::full(&[c, n], F::from_f64(-ln_n)));
    let stopped = kind == ThroughFilterKind::DpfSgrStopped;

    let mut x = chunk_columns(tape, &records.iter().map(|rec| &rec.states[0][..]).collect::<Vec<_>>(), d, n);
    let mut log_w: Option<Var<'_, F>> = None;
    let mut total: Option<Var<'_, F>> = None;
    for t in 0..model.num_steps() {
        let blocks: Vec<Block> = objects.iter().map(|&object| Block { object, t, len: n }).collect();
        let mut carried = if t == 0 {
            uniform()
        } else {
            let anc: Vec<usize> = records
                .iter()
                .enumerate()
                .flat_map(|(j, rec)| rec.parents[t].iter().map(move |&p| j * n + p))
                .collect();
            let prev: Vec<Var<'_, F>> = x.iter().map(|v| v.gather(0, &anc)).collect();
            let lw_prev = log_w.expect("weights of the previous step");
            let lw_a = lw_prev.reshape(&[r]).gather(0, &anc).reshape(&[c, n]);
            let resampled: Vec<bool> = records.iter().map(|rec| rec.resampled[t]).collect();
            let carried = if resampled.iter().any(|&s| s) {
                let after = match kind {
                    ThroughFilterKind::Pf => uniform(),
                    ThroughFilterKind::DpfSgr | ThroughFilterKind::DpfSgrStopped => {
                        let carried = (lw_a - lw_a.stop_gradient()).add_scalar(-ln_n);
                        // A lane that is impossible stays impossible (and never NaN).
                        let finite: Vec<bool> = lw_a.value().data().iter().map(|v| v.is_finite()).collect();
                        if finite.iter().all(|&f| f) {
                            carried
                        } else {
                            tape.select(&finite, carried, lw_a)
                        }
                    }
                    ThroughFilterKind::Pfnet { alpha } => {
                        let log_q = lw_a.exp().mul_scalar(alpha).add_scalar((1.0 - alpha) / n as f64).ln();
                        (lw_a - log_q).log_softmax(1)
                    }
                };
                if resampled.iter().all(|&s| s) {
                    after
                } else {
                    let mask: Vec<bool> = resampled.iter().flat_map(|&s| std::iter::repeat_n(s, n)).collect();
                    tape.select(&mask, after, lw_a)
                }
            } else {
                lw_a
            };
            let actions = chunk_columns(tape, &records.iter().map(|rec| &rec.actions[t][..]).collect::<Vec<_>>(), a, n);
            if stopped {
                x = chunk_columns(tape, &records.iter().map(|rec| &rec.states[t][..]).collect::<Vec<_>>(), d, n);
                let trans = model.transition_log_density(&params, &blocks, &prev, &x, &actions);
                carried + (trans - trans.stop_gradient()).reshape(&[c, n])
            } else {
                x = model.propagate_on_tape(&params, &blocks, &prev, &actions);
                carried
            }
        };

        // Weight by the observations that the filter used.
        let used: Vec<usize> = (0..c).filter(|&j| records[j].used[t]).collect();
        if !used.is_empty() {
            let lg = if used.len() == c {
                model.observation_log_density(&params, &blocks, &x)
            } else {
                let rows: Vec<usize> = used.iter().flat_map(|&j| j * n..(j + 1) * n).collect();
                let states: Vec<Var<'_, F>> = x.iter().map(|v| v.gather(0, &rows)).collect();
                let used_blocks: Vec<Block> = used.iter().map(|&j| blocks[j]).collect();
                model.observation_log_density(&params, &used_blocks, &states).scatter_add(0, &rows, r)
            };
            carried = carried + lg.reshape(&[c, n]);
        }
        let increment = carried.logsumexp(1, true);
        total = Some(match total {
            None => increment.sum(),
            Some(s) => s + increment.sum(),
        });
        log_w = Some(carried - increment);
    }
    let total = total.expect("at least one step");
    let grads = tape.backward(total);
    params.iter().map(|&p| grads.wrt(p)).collect()
}
