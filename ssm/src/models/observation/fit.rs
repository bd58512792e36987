//! Supervised fitting of an observation network to labelled examples (state, AV
//! pose, extents, observed items) by maximum mean log-density per item — the AOTLL
//! of SPEC §5 — with Adam. This is how the synthetic data's "true" point network is
//! made from the [`super::generator`]'s examples (SPEC §4); it works for any
//! [`ObservationModel`].

use autodiff::nn::ParamStore;
use autodiff::optim::{clip_global_norm, Adam, StepError};
use autodiff::{Parallelism, Tape, Tensor};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::{ObsContext, ObservationModel, RowVars};
use crate::data::Pose;

/// One labelled example: an object's true pose, its context and what was observed.
#[derive(Clone, Debug, PartialEq)]
pub struct Example<I> {
    /// The AV's pose and the object's extents.
    pub ctx: ObsContext,
    /// The object's true pose.
    pub pose: Pose,
    /// The observed items (possibly none).
    pub items: Vec<I>,
}

/// Settings of [`fit_network`].
#[derive(Clone, Debug, PartialEq)]
pub struct FitConfig {
    /// Adam steps.
    pub steps: usize,
    /// Examples per step (drawn uniformly with replacement).
    pub batch: usize,
    /// Adam learning rate.
    pub lr: f64,
    /// Global gradient-norm clipping, if any.
    pub clip: Option<f64>,
    /// Seed of the minibatch draws.
    pub seed: u64,
}

impl Default for FitConfig {
    fn default() -> Self {
        FitConfig { steps: 2000, batch: 128, lr: 0.01, clip: None, seed: 0 }
    }
}

/// What a fit did.
#[derive(Clone, Debug, PartialEq)]
pub struct FitReport {
    /// AOTLL (nats per item) of the examples before fitting.
    pub initial_aotll: f64,
    /// AOTLL of the examples after fitting.
    pub final_aotll: f64,
    /// Optimiser steps taken.
    pub steps: usize,
    /// Steps skipped because the gradient was not finite.
    pub skipped: usize,
}

/// AOTLL: the mean over all items of all examples of `log g(item | true pose)`
/// (nats per item), in f64. NaN if there are no items.
pub fn aotll<M: ObservationModel>(model: &M, params: &ParamStore<f64>, examples: &[Example<M::Item>]) -> f64 {
    let mut total = 0.0;
    let mut count = 0usize;
    let mut buf = Vec::new();
    for ex in examples {
        buf.resize(ex.items.len(), 0.0);
        model.log_density_items(params, &ex.ctx, ex.pose, &ex.items, &mut buf);
        total += buf.iter().sum::<f64>();
        count += ex.items.len();
    }
    if count == 0 {
        f64::NAN
    } else {
        total / count as f64
    }
}

/// Fits `model`'s parameters in `params` to `examples` by maximising the mean
/// log-density per item with Adam (f32 tape, one minibatch per step). Parameters
/// of `params` that the model does not use are left unchanged. A step whose
/// gradient is not finite is skipped and counted.
pub fn fit_network<M: ObservationModel>(
    model: &M,
    params: &mut ParamStore<f64>,
    examples: &[Example<M::Item>],
    config: &FitConfig,
) -> FitReport {
    let initial_aotll = aotll(model, params, examples);
    let mut adam = Adam::new(config.lr);
    let mut rng = StdRng::seed_from_u64(config.seed);
    let mut skipped = 0;
    let mut steps = 0;
    if !examples.is_empty() && config.batch > 0 {
        let mut batch: Vec<&Example<M::Item>> = Vec::with_capacity(config.batch);
        for _ in 0..config.steps {
            batch.clear();
            batch.extend((0..config.batch).map(|_| &examples[rng.random_range(0..examples.len())]));
            let count: usize = batch.iter().map(|e| e.items.len()).sum();
            if count == 0 {
                continue;
            }
            let p32 = params.cast::<f32>();
            let tape = Tape::<f32>::new().with_parallelism(Parallelism::Serial);
            let bound = p32.bind(&tape);
            let poses: Vec<Pose> = batch.iter().map(|e| e.pose).collect();
            let ctxs: Vec<ObsContext> = batch.iter().map(|e| e.ctx).collect();
            let av: Vec<Pose> = ctxs.iter().map(|c| c.av).collect();
            let items: Vec<&[M::Item]> = batch.iter().map(|e| e.items.as_slice()).collect();
            let rows = RowVars::from_poses(&tape, &poses, &ctxs);
            let ll = model.log_likelihood_rows(&bound, &rows, &av, &items);
            let loss = ll.sum().mul_scalar(-1.0 / count as f64);
            let grads = bound.gradients(&tape.backward(loss));
            let mut grads: Vec<Tensor<f64>> = grads.iter().map(|g| g.cast()).collect();
            if let Some(c) = config.clip {
                clip_global_norm(&mut grads, c);
            }
            match adam.step(params, &grads) {
                Ok(()) => steps += 1,
                Err(StepError::NonFinite) => skipped += 1,
                Err(e) => panic!("fit_network: {e}"),
            }
        }
    }
    FitReport { initial_aotll, final_aotll: aotll(model, params, examples), steps, skipped }
}
