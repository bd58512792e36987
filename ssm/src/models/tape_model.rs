//! A model written once: [`TapeModel`] is a state-space model whose sampler and
//! log-densities are written a single time, as tape expressions generic over the
//! float type, and [`OnTape`] turns it into both a [`ParticleModel`] (the filter
//! runs the same code on a non-recording `f32` tape) and a
//! [`DifferentiableModel`] (the estimators run it on a recording tape). Neither a
//! hand-written `f32` kernel nor a second copy of a density is needed.
//!
//! The model is noise-driven, as the reparameterised estimators need it:
//!
//! ```text
//! x_0 = m_0(z_0)                  z_0 ~ N(0, I), free of the parameters
//! x_t = m(x_{t-1}, z_t; theta)    z_t ~ N(0, I), t >= 1
//! y_t ~ g(y_t | x_t; theta)       where y_t is observed
//! ```
//!
//! with `ln f(x_t | x_{t-1}; theta)` (the law of `m(x_{t-1}, z_t; theta)`) and
//! `ln g` written on the tape. The draws `z_t` are what the filter records as the
//! particles' actions, so the tempered filter and every estimator of
//! [`crate::estimators`] serve such a model unchanged.
//!
//! What it costs against a hand-written kernel: the filter evaluates a few tape
//! ops per call (each a pass over the particles, with a copy in and out) where a
//! kernel makes one fused loop. `examples/sv_by_hand.rs` measures it on a
//! stochastic-volatility model; docs/bring-your-own-model.md quotes the numbers.

use autodiff::{Float, Parallelism, Tape, Tensor, Var};
use rand::rngs::SmallRng;
use rand::Rng;
use rand_distr::StandardNormal;

use crate::models::{Batch, Block, DifferentiableModel, Drawn, NoiseDims, ParticleModel};

/// A state-space model written once on the tape: what a user implements to get
/// a [`ParticleModel`] and a [`DifferentiableModel`] through [`OnTape`].
///
/// States, noise and observations are dimension-major lists of `Var`s of shape
/// `[R]`, one per component, over `R` rows (particles, or particles of several
/// objects and steps); the parameters are `Var`s in the order of
/// [`TapeModel::parameters`]. Every method must work for any [`Float`] (the
/// filter runs it in `f32`, gradient checks in `f64`).
pub trait TapeModel: Sync {
    /// Dimension of the state `x_t`.
    fn state_dim(&self) -> usize;

    /// Standard-normal draws per particle of one transition (`z_t`); the state's
    /// dimension by default.
    fn noise_dim(&self) -> usize {
        self.state_dim()
    }

    /// Dimension of an observation `y_t`.
    fn observation_dim(&self) -> usize;

    /// Number of independent objects (observation sequences).
    fn num_objects(&self) -> usize;

    /// Number of steps, `T + 1` (steps are `0..=T`), the same for every object.
    fn num_steps(&self) -> usize;

    /// `y_t` of `object` (`observation_dim` values), or `None` when nothing was
    /// observed at `t`.
    fn observation(&self, object: usize, t: usize) -> Option<&[f64]>;

    /// The parameter tensors (an f64 master copy).
    fn parameters(&self) -> Vec<Tensor<f64>>;

    /// A name per parameter tensor.
    fn parameter_names(&self) -> Vec<String>;

    /// `x_0 = m_0(z)` from `state_dim` standard-normal columns `z`; free of the
    /// parameters.
    fn prior<'t, F: Float>(&self, z: &[Var<'t, F>]) -> Vec<Var<'t, F>>;

    /// `x_t = m(x_{t-1}, z_t; theta)` from `noise_dim` standard-normal columns `z`.
    fn transition<'t, F: Float>(&self, params: &[Var<'t, F>], prev: &[Var<'t, F>], z: &[Var<'t, F>])
        -> Vec<Var<'t, F>>;

    /// `ln f(next | prev; theta)` per row, the law of [`TapeModel::transition`],
    /// up to terms free of the parameters.
    fn transition_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        prev: &[Var<'t, F>],
        next: &[Var<'t, F>],
    ) -> Var<'t, F>;

    /// `ln g(y | x; theta)` per row, with `y` the observations (constants,
    /// `observation_dim` columns).
    fn observation_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        y: &[Var<'t, F>],
        x: &[Var<'t, F>],
    ) -> Var<'t, F>;
}

/// A [`TapeModel`] as a [`ParticleModel`] and a [`DifferentiableModel`].
///
/// The parameters are read once, when it is built: build a new one after the
/// parameters change.
pub struct OnTape<M> {
    /// The model.
    pub model: M,
    params_f32: Vec<Tensor<f32>>,
}

impl<M: TapeModel> OnTape<M> {
    /// Wraps `model`, caching its parameters in `f32` for the filter.
    pub fn new(model: M) -> Self {
        let params_f32 = model.parameters().iter().map(|p| p.cast()).collect();
        OnTape { model, params_f32 }
    }

    /// Runs `body` on the scratch tape (reset first) with the parameters bound
    /// as constants, after copying `inputs` (each `dims * n`, dimension-major)
    /// onto it as columns; `body` returns the columns to copy into `out`.
    fn forward(
        &self,
        scratch: &mut OnTapeScratch,
        n: usize,
        inputs: &[&[f32]],
        out: &mut [f32],
        body: impl for<'t> FnOnce(&[Var<'t, f32>], &[Vec<Var<'t, f32>>]) -> Vec<Var<'t, f32>>,
    ) {
        scratch.tape.reset();
        let tape = &scratch.tape;
        let params: Vec<Var<'_, f32>> = self.params_f32.iter().map(|p| tape.constant(p.clone())).collect();
        let columns: Vec<Vec<Var<'_, f32>>> = inputs.iter().map(|values| columns(tape, values, n)).collect();
        let result = body(&params, &columns);
        for (k, column) in result.iter().enumerate() {
            let value = column.value();
            out[k * n..(k + 1) * n].copy_from_slice(column_data(value.data(), n));
        }
    }
}

/// The data of a column, which must have `n` rows (a model's bug otherwise).
#[track_caller]
fn column_data(data: &[f32], n: usize) -> &[f32] {
    assert_eq!(data.len(), n, "OnTape: the model returned a column of {} rows for {n} particles", data.len());
    data
}

/// `values` (`dims * n`, dimension-major) as `dims` constant columns of `tape`.
fn columns<'t, F: Float>(tape: &'t Tape<F>, values: &[f32], n: usize) -> Vec<Var<'t, F>> {
    values
        .chunks(n.max(1))
        .map(|column| {
            let mut buf = tape.buffer(n);
            for (b, &v) in buf.iter_mut().zip(column) {
                *b = F::from_f64(v as f64);
            }
            tape.constant(Tensor::new(&[n], buf))
        })
        .collect()
}

/// The working memory of [`OnTape`] in the filter: a serial non-recording tape
/// (its buffers recycled from call to call) and room for the draws.
pub struct OnTapeScratch {
    tape: Tape<f32>,
    noise: Vec<f32>,
}

impl<M: TapeModel> ParticleModel for OnTape<M> {
    type Scratch = OnTapeScratch;

    fn new_scratch(&self) -> OnTapeScratch {
        OnTapeScratch { tape: Tape::no_record().with_parallelism(Parallelism::Serial), noise: Vec::new() }
    }

    fn state_dim(&self) -> usize {
        self.model.state_dim()
    }

    /// The standard-normal draws `z_t` of the transition.
    fn action_dim(&self) -> usize {
        self.model.noise_dim()
    }

    fn num_objects(&self) -> usize {
        self.model.num_objects()
    }

    fn num_steps(&self) -> usize {
        self.model.num_steps()
    }

    fn sample_prior(
        &self,
        object: usize,
        n: usize,
        rng: &mut SmallRng,
        states: &mut [f32],
        scratch: &mut OnTapeScratch,
    ) {
        let mut noise = std::mem::take(&mut scratch.noise);
        noise.clear();
        noise.extend((0..self.model.state_dim() * n).map(|_| rng.sample::<f32, _>(StandardNormal)));
        self.prior_from_noise(object, n, &noise, states, scratch);
        scratch.noise = noise;
    }

    fn propagate(&self, at: Batch, prev: &[f32], to: Drawn<'_>, rng: &mut SmallRng, scratch: &mut OnTapeScratch) {
        for z in to.actions.iter_mut() {
            *z = rng.sample::<f32, _>(StandardNormal);
        }
        let mut noise = std::mem::take(&mut scratch.noise);
        noise.clear();
        noise.extend_from_slice(to.actions);
        self.propagate_from_noise(at, prev, &noise, to, scratch);
        scratch.noise = noise;
    }

    fn noise_dims(&self) -> Option<NoiseDims> {
        Some(NoiseDims { prior: self.model.state_dim(), transition: self.model.noise_dim() })
    }

    fn prior_from_noise(
        &self,
        _object: usize,
        n: usize,
        noise: &[f32],
        states: &mut [f32],
        scratch: &mut OnTapeScratch,
    ) {
        self.forward(scratch, n, &[noise], states, |_, cols| self.model.prior(&cols[0]));
    }

    fn propagate_from_noise(&self, at: Batch, prev: &[f32], z: &[f32], to: Drawn<'_>, scratch: &mut OnTapeScratch) {
        to.actions.copy_from_slice(z);
        self.forward(scratch, at.n, &[prev, z], to.next, |params, cols| {
            self.model.transition(params, &cols[0], &cols[1])
        });
    }

    fn observation_loglik(&self, at: Batch, states: &[f32], out: &mut [f32], scratch: &mut OnTapeScratch) -> bool {
        let Some(y) = self.model.observation(at.object, at.t) else {
            return false;
        };
        let ys: Vec<f32> = y.iter().flat_map(|&v| std::iter::repeat_n(v as f32, at.n)).collect();
        self.forward(scratch, at.n, &[states, &ys], out, |params, cols| {
            vec![self.model.observation_log_density(params, &cols[1], &cols[0])]
        });
        true
    }

    /// One observed unit per step with an observation.
    fn observation_count(&self, object: usize, t: usize) -> usize {
        usize::from(self.model.observation(object, t).is_some())
    }
}

impl<M: TapeModel> DifferentiableModel for OnTape<M> {
    fn parameters(&self) -> Vec<Tensor<f64>> {
        self.model.parameters()
    }

    fn parameter_names(&self) -> Vec<String> {
        self.model.parameter_names()
    }

    /// Every block must be at a step with an observation.
    fn observation_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        blocks: &[Block],
        states: &[Var<'t, F>],
    ) -> Var<'t, F> {
        let tape = states[0].tape();
        let dims = self.model.observation_dim();
        let mut ys: Vec<Vec<F>> = vec![Vec::new(); dims];
        for b in blocks {
            let y = self.model.observation(b.object, b.t).unwrap_or_else(|| {
                panic!("OnTape::observation_log_density: object {} has no observation at step {}", b.object, b.t)
            });
            for (column, &v) in ys.iter_mut().zip(y) {
                column.extend(std::iter::repeat_n(F::from_f64(v), b.len));
            }
        }
        let ys: Vec<Var<'t, F>> = ys.into_iter().map(|c| tape.constant(Tensor::from_vec(c))).collect();
        self.model.observation_log_density(params, &ys, states)
    }

    fn transition_log_density<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        _blocks: &[Block],
        prev: &[Var<'t, F>],
        next: &[Var<'t, F>],
        _actions: &[Var<'t, F>],
    ) -> Var<'t, F> {
        self.model.transition_log_density(params, prev, next)
    }

    /// `m(prev, z; theta)` with the recorded draws `z` (free of the parameters,
    /// so they need no standardising).
    fn propagate_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        _blocks: &[Block],
        prev: &[Var<'t, F>],
        actions: &[Var<'t, F>],
    ) -> Vec<Var<'t, F>> {
        self.model.transition(params, prev, actions)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimators::{Estimator, EstimatorConfig, Precision, ScoreEstimator};
    use crate::filter::{run_filter, FilterConfig, Sampling};
    use crate::models::linear_gaussian::kalman::{Lgssm, LgssmTheta, ThetaVars};
    use crate::models::linear_gaussian::particles::LgssmBatch;
    use autodiff::dist::normal_logpdf;
    use rand::SeedableRng;

    /// The linear-Gaussian model written once (prior `N(0, 1)`).
    struct Lg {
        theta: LgssmTheta,
        ys: Vec<Vec<f64>>,
    }

    impl TapeModel for Lg {
        fn state_dim(&self) -> usize {
            1
        }
        fn observation_dim(&self) -> usize {
            1
        }
        fn num_objects(&self) -> usize {
            self.ys.len()
        }
        fn num_steps(&self) -> usize {
            self.ys[0].len()
        }
        fn observation(&self, object: usize, t: usize) -> Option<&[f64]> {
            Some(std::slice::from_ref(&self.ys[object][t]))
        }
        fn parameters(&self) -> Vec<Tensor<f64>> {
            vec![Tensor::from_f64s(&[3], &self.theta.to_array())]
        }
        fn parameter_names(&self) -> Vec<String> {
            vec!["theta".into()]
        }
        fn prior<'t, F: Float>(&self, z: &[Var<'t, F>]) -> Vec<Var<'t, F>> {
            z.to_vec()
        }
        fn transition<'t, F: Float>(&self, p: &[Var<'t, F>], prev: &[Var<'t, F>], z: &[Var<'t, F>]) -> Vec<Var<'t, F>> {
            vec![ThetaVars::from_vector(p[0]).propagate(prev[0], z[0])]
        }
        fn transition_log_density<'t, F: Float>(
            &self,
            p: &[Var<'t, F>],
            prev: &[Var<'t, F>],
            next: &[Var<'t, F>],
        ) -> Var<'t, F> {
            ThetaVars::from_vector(p[0]).transition_log_density(prev[0], next[0])
        }
        fn observation_log_density<'t, F: Float>(
            &self,
            p: &[Var<'t, F>],
            y: &[Var<'t, F>],
            x: &[Var<'t, F>],
        ) -> Var<'t, F> {
            normal_logpdf(x[0], y[0], ThetaVars::from_vector(p[0]).log_sw)
        }
    }

    fn both() -> (OnTape<Lg>, LgssmBatch) {
        let theta = LgssmTheta::new(0.8, 0.6, 0.7);
        let model = Lgssm::new(0.0, 1.0, theta).unwrap();
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let ys: Vec<Vec<f64>> = (0..3).map(|_| model.simulate(30, &mut rng).ys).collect();
        (OnTape::new(Lg { theta, ys: ys.clone() }), LgssmBatch::new(model, ys).unwrap())
    }

    /// The filter draws the same noise in the same order from both, so the
    /// written-once model and the hand-written one give the same likelihood and
    /// the same scores up to f32 rounding of the two evaluation orders.
    #[test]
    fn written_once_matches_the_hand_written_linear_gaussian_model() {
        let (once, hand) = both();
        let config = FilterConfig::new(Sampling::new(128, None), 5, 11);
        let a = run_filter(&once, &config, |_| ());
        let b = run_filter(&hand, &config, |_| ());
        for (x, y) in a.objects.iter().zip(&b.objects) {
            assert!((x.log_likelihood - y.log_likelihood).abs() < 1e-3, "{} vs {}", x.log_likelihood, y.log_likelihood);
        }
        let config = EstimatorConfig { precision: Precision::F64, ..EstimatorConfig::new(Sampling::new(128, None)) };
        for estimator in [Estimator::pf_sefi(5), Estimator::dpf_sgr()] {
            let g1 = estimator.estimate(&once, &config, 7).gradient[0].to_f64_vec();
            let g2 = estimator.estimate(&hand, &config, 7).gradient[0].to_f64_vec();
            for (x, y) in g1.iter().zip(&g2) {
                assert!((x - y).abs() < 1e-3 * (1.0 + y.abs()), "{}: {g1:?} vs {g2:?}", estimator.name());
            }
        }
    }

    /// The tempered filter (which needs the noise-driven form) runs on it.
    #[test]
    fn the_tempered_filter_runs_on_a_written_once_model() {
        let (once, _) = both();
        let sampling = Sampling::new(64, Some(crate::filter::Tempering::default()));
        let run = run_filter(&once, &FilterConfig::new(sampling, 3, 1), |_| ());
        assert!(run.objects.iter().all(|s| s.log_likelihood.is_finite()));
    }
}
