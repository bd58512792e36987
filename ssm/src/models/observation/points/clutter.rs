//! The clutter extension of the point model: its constants, the filter path,
//! the tape path and the sampler.

use autodiff::nn::{BoundParams, ParamStore};
use autodiff::{Float, Var};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

use super::kernels::*;
use super::PointObservationModel;
use crate::data::Pose;
use crate::models::observation::{ObsContext, ObservationModel, PosesRef, RowVars, Scratch};

/// Clutter mixed into every point's density (see the [module docs](crate::models::observation::points#clutter)):
/// with probability `fraction` a point is drawn from an isotropic 2-D Gaussian of
/// sd `scale` centred on the box centre instead of from the box's edges.
///
/// ```
/// use ssm::models::observation::points::Clutter;
/// let c = Clutter::from_logits(0.0, 2f64.ln());
/// assert_eq!(c, Clutter { fraction: 0.5, scale: 2.0 });
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Clutter {
    /// Fraction `eps` of clutter points, in `(0, 1)`.
    pub fraction: f64,
    /// Sd `s` of the clutter Gaussian (m, positive).
    pub scale: f64,
}

impl Clutter {
    /// The clutter with `fraction = sigmoid(logit_fraction)` and `scale = exp(log_scale)`
    /// (the tape path's parameterisation).
    pub fn from_logits(logit_fraction: f64, log_scale: f64) -> Self {
        Clutter { fraction: 1.0 / (1.0 + (-logit_fraction).exp()), scale: log_scale.exp() }
    }

    /// Panics unless `0 < fraction < 1` and `scale` is positive and finite.
    #[track_caller]
    pub(super) fn check(&self, op: &str) {
        assert!(
            self.fraction > 0.0 && self.fraction < 1.0,
            "{op}: clutter fraction must lie in (0, 1), got {}",
            self.fraction
        );
        assert!(
            self.scale > 0.0 && self.scale.is_finite(),
            "{op}: clutter scale must be positive and finite, got {}",
            self.scale
        );
    }
}

/// The clutter's constants in the kernels' float type: with `c(d) = eps N2` at
/// distance `d` from the centre, `ln c = ln_peak - half_prec d^2`.
#[derive(Clone, Copy, Debug)]
pub(super) struct ClutterConsts<F> {
    /// `ln(1 - eps)`.
    ln_keep: F,
    /// `ln eps - ln(2 pi) - 2 ln s`.
    ln_peak: F,
    /// `1 / s^2`.
    pub(super) prec: F,
    /// `1 / (2 s^2)`.
    half_prec: F,
    /// `eps`.
    pub(super) eps: F,
}

impl<F: Float> ClutterConsts<F> {
    /// From `ln(1 - eps)`, `ln eps` and `ln s`, computed in f64.
    pub(super) fn new(ln_keep: f64, ln_eps: f64, ln_s: f64) -> Self {
        let prec = (-2.0 * ln_s).exp();
        let f = F::from_f64;
        ClutterConsts {
            ln_keep: f(ln_keep),
            ln_peak: f(ln_eps - (2.0 * std::f64::consts::PI).ln() - 2.0 * ln_s),
            prec: f(prec),
            half_prec: f(0.5 * prec),
            eps: f(ln_eps.exp()),
        }
    }

    /// Of a validated [`Clutter`].
    #[track_caller]
    pub(super) fn of(c: Clutter, op: &str) -> Self {
        c.check(op);
        Self::new((-c.fraction).ln_1p(), c.fraction.ln(), c.scale.ln())
    }

    /// Of `eps = sigmoid(lambda)`, `s = exp(sigma)`: `ln eps = -softplus(-lambda)` and
    /// `ln(1 - eps) = -softplus(lambda)` stay accurate however large `|lambda|` is.
    #[track_caller]
    pub(super) fn from_logits(lambda: f64, sigma: f64, op: &str) -> Self {
        assert!(
            lambda.is_finite() && sigma.is_finite(),
            "{op}: clutter logit fraction {lambda} and log scale {sigma} must be finite"
        );
        Self::new(-lambda.softplus(), -(-lambda).softplus(), sigma)
    }
}

/// One point's mixture with clutter: `lg` the log of `g_c`, `q = 1 - r` the clutter
/// term's responsibility, `d2` the squared distance to the box centre.
pub(super) struct ClutterMix<F> {
    pub(super) lg: F,
    pub(super) q: F,
    pub(super) d2: F,
}

/// `log((1 - eps) e^{lg} + c(d))` for a point at `(dx, dy)` from the box centre whose
/// box log-density is `lg`: a two-term log-sum-exp, finite for finite inputs.
#[inline(always)]
pub(super) fn clutter_mix<F: Float>(lg: F, dx: F, dy: F, cc: &ClutterConsts<F>) -> ClutterMix<F> {
    let d2 = dx * dx + dy * dy;
    let a = cc.ln_keep + lg;
    let b = cc.ln_peak - cc.half_prec * d2;
    let m = fmax(a, b);
    let (ea, eb) = ((a - m).exp(), (b - m).exp());
    let total = ea + eb;
    ClutterMix { lg: m + total.ln(), q: eb / total, d2 }
}

impl PointObservationModel {
    /// The filter's hot path with clutter: like [`ObservationModel::log_likelihood`],
    /// `out[i] = sum over points of log g_c(point | pose i)`. Each point's box
    /// log-density goes through the same kernel into `scratch`, then is mixed with
    /// the clutter term and added to `out`.
    ///
    /// # Panics
    /// If `out` does not have one value per pose, or `clutter` is invalid
    /// (fraction outside `(0, 1)`, scale not positive).
    #[allow(clippy::too_many_arguments)]
    #[track_caller]
    pub fn log_likelihood_with_clutter<F: Float>(
        &self,
        params: &ParamStore<F>,
        ctx: &ObsContext,
        poses: PosesRef<'_, F>,
        items: &[[f64; 2]],
        clutter: Clutter,
        scratch: &mut Scratch<F>,
        out: &mut [F],
    ) {
        let op = "PointObservationModel::log_likelihood_with_clutter";
        let n = poses.len();
        assert_eq!(out.len(), n, "{op}: {n} poses, room for {}", out.len());
        let cc = ClutterConsts::of(clutter, op);
        if items.is_empty() || n == 0 {
            out.fill(F::ZERO);
            return;
        }
        self.prepare(params, ctx, poses, scratch);
        let pc = PointConsts::new(ctx.length, ctx.width, self.soft_scale);
        let mut lg = [F::ZERO; BLOCK];
        for start in (0..n).step_by(BLOCK) {
            let range = start..n.min(start + BLOCK);
            let blk = Block::new(poses, scratch, n, range.clone());
            let out = &mut out[range];
            let sink = |j: usize, lg: &[F]| {
                let p = items[j];
                if j == 0 {
                    clutter_point_kernel::<F, false>(p, &cc, blk.x, blk.y, lg, out);
                } else {
                    clutter_point_kernel::<F, true>(p, &cc, blk.x, blk.y, lg, out);
                }
            };
            if pc.far {
                block_log_densities::<F, true>(&blk, items, &pc, &mut lg, sink);
            } else {
                block_log_densities::<F, false>(&blk, items, &pc, &mut lg, sink);
            }
        }
    }

    /// The tape path with clutter: like [`ObservationModel::log_likelihood_rows`]
    /// (per-row sums of `log g_c`, shape `[R]`), differentiable in the network
    /// parameters, every tracked `Var` of `rows`, and in `logit_fraction`
    /// (`lambda`, `eps = sigmoid(lambda)`) and `log_scale` (`sigma`, `s = exp(sigma)`),
    /// both of shape `[1]` and shared by all rows.
    ///
    /// ```
    /// use autodiff::nn::ParamStore;
    /// use autodiff::{Tape, Tensor};
    /// use rand::SeedableRng;
    /// use ssm::data::Pose;
    /// use ssm::models::observation::{ObsContext, ObservationModel, PointObservationModel, RowVars};
    ///
    /// let mut rng = rand::rngs::StdRng::seed_from_u64(0);
    /// let mut store = ParamStore::new();
    /// let model = PointObservationModel::init_params(&mut store, "obs", &mut rng);
    /// let ctx = ObsContext::new(Pose::default(), 4.5, 1.8);
    /// let pose = Pose { x: 12.0, y: 3.0, yaw: 0.3 };
    /// let points = [[12.0, 4.0], [40.0, 3.0]]; // the second far from the box
    ///
    /// let tape = Tape::<f64>::new();
    /// let params = store.bind(&tape);
    /// let rows = RowVars::from_poses(&tape, &[pose], &[ctx]);
    /// let lambda = tape.param(Tensor::from_vec(vec![-2.0]));
    /// let sigma = tape.param(Tensor::from_vec(vec![1.0]));
    /// let items: [&[[f64; 2]]; 1] = [&points];
    /// let ll = model.log_likelihood_rows_with_clutter(&params, &rows, &[ctx.av], &items, lambda, sigma);
    /// let grads = tape.backward(ll.sum());
    /// // The far point is clutter: more clutter makes the data likelier.
    /// assert!(grads.wrt(lambda).item() > 0.0);
    /// ```
    ///
    /// # Panics
    /// On the shape mismatches of `log_likelihood_rows`, if `logit_fraction` or
    /// `log_scale` does not have shape `[1]`, or if their values are not finite.
    #[track_caller]
    pub fn log_likelihood_rows_with_clutter<'t, F: Float>(
        &self,
        params: &BoundParams<'t, F>,
        rows: &RowVars<'t, F>,
        av: &[Pose],
        items: &[&[[f64; 2]]],
        logit_fraction: Var<'t, F>,
        log_scale: Var<'t, F>,
    ) -> Var<'t, F> {
        let op = "PointObservationModel::log_likelihood_rows_with_clutter";
        for (name, v) in [("logit_fraction", logit_fraction), ("log_scale", log_scale)] {
            assert!(v.shape() == [1], "{op}: {name} has shape {:?}, expected [1]", v.shape());
        }
        self.rows_log_likelihood(params, rows, av, items, Some([logit_fraction, log_scale]), op)
    }

    /// Appends `n` points drawn independently from `g_c(. | pose)`: each is clutter
    /// with probability `clutter.fraction`, else drawn as by
    /// [`ObservationModel::sample`].
    ///
    /// # Panics
    /// If `clutter` is invalid (fraction outside `(0, 1)`, scale not positive).
    #[allow(clippy::too_many_arguments)]
    #[track_caller]
    pub fn sample_with_clutter<R: Rng + ?Sized>(
        &self,
        params: &ParamStore<f64>,
        ctx: &ObsContext,
        pose: Pose,
        n: usize,
        clutter: Clutter,
        rng: &mut R,
        out: &mut Vec<[f64; 2]>,
    ) {
        clutter.check("PointObservationModel::sample_with_clutter");
        let is_clutter: Vec<bool> = (0..n).map(|_| rng.random::<f64>() < clutter.fraction).collect();
        // The box points in one batch (one network evaluation), interleaved in draw order.
        let mut on_box = Vec::new();
        self.sample(params, ctx, pose, is_clutter.iter().filter(|&&c| !c).count(), rng, &mut on_box);
        let mut on_box = on_box.into_iter();
        out.reserve(n);
        for c in is_clutter {
            let p = if c {
                let (a, b): (f64, f64) = (StandardNormal.sample(rng), StandardNormal.sample(rng));
                [pose.x + clutter.scale * a, pose.y + clutter.scale * b]
            } else {
                on_box.next().expect("one box point per non-clutter draw")
            };
            out.push(p);
        }
    }
}

/// Clutter for one point over a block of particles at `(xs, ys)`: `lg[i]` holds
/// `log g(point | particle i)`; `log g_c` is added to `out` (`ACC`) or written into it.
#[allow(clippy::needless_range_loop)]
#[inline(never)]
pub(super) fn clutter_point_kernel<F: Float, const ACC: bool>(
    p: [f64; 2],
    cc: &ClutterConsts<F>,
    xs: &[F],
    ys: &[F],
    lg: &[F],
    out: &mut [F],
) {
    let n = out.len();
    let (px, py) = (F::from_f64(p[0]), F::from_f64(p[1]));
    let (xs, ys, lg) = (&xs[..n], &ys[..n], &lg[..n]);
    for i in 0..n {
        let lgc = clutter_mix(lg[i], px - xs[i], py - ys[i], cc).lg;
        out[i] = if ACC { out[i] + lgc } else { lgc };
    }
}
