//! The neural policy of the measured data (SPEC §3): an MLP
//! `(v, kappa) -> 32 ReLU -> 32 ReLU -> 5` whose outputs are the two action means
//! and the lower-triangular Cholesky factor of their covariance (positive diagonal
//! through a softplus). 1,317 parameters, held in an [`autodiff::nn::ParamStore`].
//!
//! The network is written twice: on the tape for the estimators, and on the plain
//! path the filter runs, `models::plain_mlp`'s block kernel (the same
//! operations in the same order, the layers' sums accumulated in another order: the
//! two agree to rounding, which a test checks).

use autodiff::nn::{Activation, Mlp, ParamStore};
use autodiff::{Float, Tensor, Var};
use rand::Rng;

use crate::models::plain_mlp::forward_feature_major;

use super::policy::{check_parameters, ActionGaussianVars, ActionGaussians, GaussianPolicy, PolicyError};

/// Widths of the network, input first.
pub const NEURAL_POLICY_LAYERS: [usize; 4] = [2, 32, 32, 5];
/// Speed is fed to the network as `v * SPEED_INPUT_SCALE` (order one over 0–40 m/s).
pub const SPEED_INPUT_SCALE: f64 = 0.1;
/// Curvature is fed as `kappa * CURVATURE_INPUT_SCALE` (order one over |kappa| <= 0.2).
pub const CURVATURE_INPUT_SCALE: f64 = 10.0;
/// The network sees speeds clamped to `[-INPUT_SPEED_LIMIT, INPUT_SPEED_LIMIT]` (m/s)
/// and curvatures clamped to `[-INPUT_CURVATURE_LIMIT, INPUT_CURVATURE_LIMIT]` (1/m):
/// beyond any road user's range its outputs stay those at the boundary. Without the
/// clamp a ReLU network extrapolates linearly, and a mean acceleration that grows
/// with speed makes particles' speeds grow geometrically over the steps of a scene
/// until they overflow (training then diverges).
pub const INPUT_SPEED_LIMIT: f64 = 60.0;
/// See [`INPUT_SPEED_LIMIT`].
pub const INPUT_CURVATURE_LIMIT: f64 = 0.5;
/// Output 1 times this is the mean pinch: pinch is two orders smaller than accel, so
/// order-one outputs cover it.
pub const PINCH_OUTPUT_SCALE: f64 = 0.1;
/// Smallest accel sd (m/s^2), added to `softplus(output 2)`.
pub const MIN_SD_ACCEL: f64 = 1e-3;
/// Smallest conditional pinch sd (1/(m s)), added to `PINCH_OUTPUT_SCALE * softplus(output 4)`.
pub const MIN_SD_PINCH: f64 = 1e-4;

/// The neural policy: an MLP from `(v, kappa)` to a bivariate Gaussian over actions.
///
/// Outputs `o` map to `mean_accel = o0`, `mean_pinch = s o1`,
/// `l11 = softplus(o2) + 1e-3`, `l21 = s o3`, `l22 = s softplus(o4) + 1e-4` with
/// `s = 0.1` ([`PINCH_OUTPUT_SCALE`]).
///
/// ```
/// use rand::SeedableRng;
/// use ssm::models::vehicle::{ActionGaussians, GaussianPolicy, NeuralPolicy};
/// let policy = NeuralPolicy::new(&mut rand::rngs::StdRng::seed_from_u64(0));
/// assert_eq!(policy.num_parameters(), 1317);
/// let mut g = ActionGaussians::default();
/// policy.gaussians(&[10.0f32, 3.0], &[0.01, -0.05], &mut g);
/// assert!(g.l11.iter().chain(&g.l22).all(|&s| s > 0.0));
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct NeuralPolicy {
    store: ParamStore<f64>,
    mlp: Mlp,
}

impl NeuralPolicy {
    /// A freshly initialised network (He-scaled ReLU layers, Glorot output, zero
    /// biases), its parameters named `policy.0.w`, `policy.0.b`, ...
    pub fn new<R: Rng + ?Sized>(rng: &mut R) -> Self {
        let mut store = ParamStore::new();
        let mut rng = rng;
        let mlp =
            Mlp::new(&mut store, "policy", &NEURAL_POLICY_LAYERS, Activation::Relu, Activation::Identity, &mut rng);
        NeuralPolicy { store, mlp }
    }

    /// The same network with the output biases set so that, where the hidden
    /// layers' contribution is small, the accel sd is about `sd_accel` (m/s²) and
    /// the pinch's conditional sd about `sd_pinch` (1/(m s)): a start at physical
    /// scales rather than at the network's default (accel sd 0.69, pinch 0.069).
    /// Panics unless both exceed their floors ([`MIN_SD_ACCEL`], [`MIN_SD_PINCH`]).
    #[track_caller]
    pub fn with_initial_sds(mut self, sd_accel: f64, sd_pinch: f64) -> Self {
        assert!(
            sd_accel > MIN_SD_ACCEL && sd_pinch > MIN_SD_PINCH,
            "NeuralPolicy::with_initial_sds: sds must exceed their floors, got {sd_accel}, {sd_pinch}"
        );
        // softplus^{-1}(y) = ln(e^y - 1).
        let inverse_softplus = |y: f64| y.exp_m1().ln();
        let bias = self.mlp.layers.last().expect("the network has layers").b;
        let b = self.store.get_mut(bias).data_mut();
        b[2] = inverse_softplus(sd_accel - MIN_SD_ACCEL);
        b[4] = inverse_softplus((sd_pinch - MIN_SD_PINCH) / PINCH_OUTPUT_SCALE);
        self
    }

    /// The parameter store (f64 master copy).
    pub fn store(&self) -> &ParamStore<f64> {
        &self.store
    }

    /// The parameter store, mutable (e.g. for an optimiser step).
    pub fn store_mut(&mut self) -> &mut ParamStore<f64> {
        &mut self.store
    }

    /// The network's layout (parameter ids index [`GaussianPolicy::parameters`]).
    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    /// The network on a tape: parameters as `Var`s in store order, states `[n]`.
    fn forward<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        v: Var<'t, F>,
        kappa: Var<'t, F>,
    ) -> ActionGaussianVars<'t, F> {
        let n = v.numel();
        let tape = v.tape();
        let x = tape.concat(
            &[
                v.clamp(-INPUT_SPEED_LIMIT, INPUT_SPEED_LIMIT).reshape(&[n, 1]).mul_scalar(SPEED_INPUT_SCALE),
                kappa
                    .clamp(-INPUT_CURVATURE_LIMIT, INPUT_CURVATURE_LIMIT)
                    .reshape(&[n, 1])
                    .mul_scalar(CURVATURE_INPUT_SCALE),
            ],
            1,
        );
        let o =
            self.mlp.layers.iter().fold(x, |h, layer| layer.act.apply(h.affine(params[layer.w.0], params[layer.b.0])));
        let col = |j: usize| o.slice(1, j, 1).reshape(&[n]);
        ActionGaussianVars {
            mean_accel: col(0),
            mean_pinch: col(1).mul_scalar(PINCH_OUTPUT_SCALE),
            l11: col(2).softplus().add_scalar(MIN_SD_ACCEL),
            l21: Some(col(3).mul_scalar(PINCH_OUTPUT_SCALE)),
            l22: col(4).softplus().mul_scalar(PINCH_OUTPUT_SCALE).add_scalar(MIN_SD_PINCH),
        }
    }
}

impl GaussianPolicy for NeuralPolicy {
    fn parameters(&self) -> Vec<Tensor<f64>> {
        self.store.values().to_vec()
    }

    fn parameter_names(&self) -> Vec<String> {
        self.store.iter().map(|(name, _)| name.to_string()).collect()
    }

    fn set_parameters(&mut self, params: &[Tensor<f64>]) -> Result<(), PolicyError> {
        check_parameters(self.store.values(), params)?;
        self.store.values_mut().clone_from_slice(params);
        Ok(())
    }

    #[track_caller]
    fn gaussians<F: Float>(&self, v: &[F], kappa: &[F], out: &mut ActionGaussians<F>) {
        let n = v.len();
        assert_eq!(kappa.len(), n, "NeuralPolicy::gaussians: {n} speeds, {} curvatures", kappa.len());
        out.resize(n);
        if n == 0 {
            return;
        }
        // The tape version's operations in its order (clamp, scale; the layers; the
        // heads), on the block kernel of the filter's networks.
        let f = F::from_f64;
        let (v_lim, k_lim) = (f(INPUT_SPEED_LIMIT), f(INPUT_CURVATURE_LIMIT));
        let (v_scale, k_scale) = (f(SPEED_INPUT_SCALE), f(CURVATURE_INPUT_SCALE));
        let mut input = Vec::with_capacity(2 * n);
        input.extend(v.iter().map(|&x| x.max(-v_lim).min(v_lim) * v_scale));
        input.extend(kappa.iter().map(|&x| x.max(-k_lim).min(k_lim) * k_scale));
        let weights: Vec<Tensor<F>> = self.store.values().iter().map(|p| p.cast()).collect();
        let (mut hidden, mut o) = ([Vec::new(), Vec::new()], Vec::new());
        forward_feature_major(&self.mlp, &weights, n, &input, &mut hidden, &mut o);
        let col = |j: usize| &o[j * n..(j + 1) * n];
        let (pinch_scale, min_accel, min_pinch) = (f(PINCH_OUTPUT_SCALE), f(MIN_SD_ACCEL), f(MIN_SD_PINCH));
        out.mean_accel.copy_from_slice(col(0));
        for (dst, &o1) in out.mean_pinch.iter_mut().zip(col(1)) {
            *dst = o1 * pinch_scale;
        }
        for (dst, &o2) in out.l11.iter_mut().zip(col(2)) {
            *dst = o2.softplus() + min_accel;
        }
        for (dst, &o3) in out.l21.iter_mut().zip(col(3)) {
            *dst = o3 * pinch_scale;
        }
        for (dst, &o4) in out.l22.iter_mut().zip(col(4)) {
            *dst = o4.softplus() * pinch_scale + min_pinch;
        }
    }

    #[track_caller]
    fn gaussians_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        v: Var<'t, F>,
        kappa: Var<'t, F>,
    ) -> ActionGaussianVars<'t, F> {
        let shapes: Vec<Vec<usize>> = params.iter().map(|p| p.shape()).collect();
        let want: Vec<&[usize]> = self.store.values().iter().map(|p| p.shape()).collect();
        assert!(
            shapes.len() == want.len() && shapes.iter().zip(&want).all(|(a, b)| a == b),
            "NeuralPolicy::gaussians_on_tape: parameter shapes {shapes:?}, expected {want:?}"
        );
        self.forward(params, v, kappa)
    }
}
