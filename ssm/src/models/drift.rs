//! A detector error that persists from frame to frame (*drift*), as part of the
//! state: the box model's white-noise detections scatter around the state plus
//! an offset `d_t` in the sensor's frame — along and across the line of sight
//! from the AV, and in yaw — that follows each object as three independent
//! stationary AR(1) processes,
//!
//! ```text
//! d_t,k = s_k u_t,k,   u_0,k ~ N(0, 1),   u_t,k = rho_k u_{t-1},k + sqrt(1 - rho_k^2) e_t,k,   e ~ N(0, 1),
//! ```
//!
//! so a detection is `g(det | pose + d_t)`, `g` the box model's density. KITTI's
//! PointRCNN boxes need it: most of their error along the line of sight stays
//! with a car for seconds (README, "What the rest of the gap is"), which a
//! white-noise model can only take up by moving the smoothed states.
//!
//! The state holds the *standardised* offsets `u` (non-centred): their law at
//! `t = 0` is `N(0, I)` whatever the parameters, so the prior on `x_0` stays free
//! of them and Fisher's identity needs no prior term. The persistences `rho`
//! get their score from the transition of `u`, the sds `s` from the observation
//! density, which sees `s u`.
//!
//! Parameters (one tensor [`DRIFT_PARAM`] of 6 stored values `r`): persistence
//! `rho_k = sigmoid(PERSISTENCE_SCALE r_k)` per step, sd
//! `s_k = exp(LOG_SD_SCALE r_{3+k})` (m, m, rad), in the order along, across,
//! yaw. The start ([`DetectorDrift::initial`]) is a stated rule, not a
//! magnitude of any data: persistence 1/2 (halfway between white and
//! constant) and sds at the box model's floor scales ([`BOX_MIN_SCALE`],
//! [`BOX_MIN_YAW_SCALE`]), the smallest detection error the model expresses,
//! so that what drift there is comes from the data.

use autodiff::{Float, Tensor, Var};

use crate::data::{Dataset, ObservationKind, Pose};
use crate::models::observation::boxes::{los_offsets, BOX_MIN_SCALE, BOX_MIN_YAW_SCALE, LOS_EPS};
use crate::models::observation::{BoxObservationModel, ObservationModel};
use crate::models::ModelError;
use crate::util::angles::wrap_angle;

/// Name of the drift's parameter tensor in a parameter store.
pub const DRIFT_PARAM: &str = "drift";
/// Offsets per state: along and across the line of sight, yaw.
pub const DRIFT_DIMS: usize = 3;
/// Stored persistences are multiplied by this: `rho = sigmoid(PERSISTENCE_SCALE r)`.
const PERSISTENCE_SCALE: f64 = 4.0;
/// Stored log-sds are multiplied by this: `s = exp(LOG_SD_SCALE r)`.
const LOG_SD_SCALE: f64 = 2.0;
/// Largest persistence the plain paths use: keeps `1 - rho^2` a positive f32.
const MAX_PERSISTENCE: f64 = 1.0 - 1e-6;

/// The drift's values in natural units (see the [module docs](self)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DetectorDrift {
    /// Per-step persistence `rho` of the along, across and yaw offsets.
    pub persistence: [f64; DRIFT_DIMS],
    /// Stationary sd `s` of the along (m), across (m) and yaw (rad) offsets.
    pub sd: [f64; DRIFT_DIMS],
}

impl DetectorDrift {
    /// The stored start: persistence 1/2, sds at the box model's floor scales.
    pub fn initial() -> Tensor<f64> {
        let sd = [BOX_MIN_SCALE, BOX_MIN_SCALE, BOX_MIN_YAW_SCALE];
        let mut raw = vec![0.0; DRIFT_DIMS];
        raw.extend(sd.iter().map(|s| s.ln() / LOG_SD_SCALE));
        Tensor::from_vec(raw)
    }

    /// The drift stored as `raw` ([`DRIFT_PARAM`]). Fails on a wrong length or a
    /// value that is not finite.
    pub fn from_raw(raw: &[f64]) -> Result<Self, ModelError> {
        if raw.len() != 2 * DRIFT_DIMS || raw.iter().any(|v| !v.is_finite()) {
            return Err(ModelError::ExtensionValues {
                param: DRIFT_PARAM.into(),
                expected: 2 * DRIFT_DIMS,
                got: raw.to_vec(),
            });
        }
        let rho = |r: f64| (1.0 / (1.0 + (-PERSISTENCE_SCALE * r).exp())).min(MAX_PERSISTENCE);
        Ok(DetectorDrift {
            persistence: [rho(raw[0]), rho(raw[1]), rho(raw[2])],
            sd: [3, 4, 5].map(|k| (LOG_SD_SCALE * raw[k]).exp()),
        })
    }

    /// The stored values of this drift (what [`DetectorDrift::from_raw`] reads).
    pub fn to_raw(&self) -> Vec<f64> {
        let logit = |p: f64| (p / (1.0 - p)).ln() / PERSISTENCE_SCALE;
        let mut raw: Vec<f64> = self.persistence.iter().map(|&p| logit(p.clamp(1e-6, MAX_PERSISTENCE))).collect();
        raw.extend(self.sd.iter().map(|s| s.ln() / LOG_SD_SCALE));
        raw
    }

    /// One line for reports: each offset's sd and persistence.
    pub fn describe(&self, dt: f64) -> String {
        let part = |k: usize, unit: &str| {
            let rho = self.persistence[k];
            format!("sd {:.3} {unit}, persistence {rho:.3} per step ({:.2} s)", self.sd[k], persistence_time(rho, dt))
        };
        format!("along: {}; across: {}; yaw: {}", part(0, "m"), part(1, "m"), part(2, "rad"))
    }

    /// `x_t`'s standardised offsets from `x_{t-1}`'s (`prev`, dimension-major,
    /// `DRIFT_DIMS * n`) and standard-normal noise `e` (same layout), into `next`.
    pub fn propagate(&self, n: usize, prev: &[f32], e: &[f32], next: &mut [f32]) {
        for k in 0..DRIFT_DIMS {
            let rho = self.persistence[k];
            let (a, b) = (rho as f32, (1.0 - rho * rho).sqrt() as f32);
            let range = k * n..(k + 1) * n;
            for ((x, &p), &z) in next[range.clone()].iter_mut().zip(&prev[range.clone()]).zip(&e[range]) {
                *x = a * p + b * z;
            }
        }
    }

    /// The poses the detector sees, `pose + d`, for an AV at `av`: each
    /// particle's position moved by `s_a u_a` along and `s_c u_c` across the line
    /// of sight from the AV to it, its yaw by `s_y u_y`. `x`, `y`, `yaw` hold the
    /// states' poses on entry and the seen poses on return; `u` is the drift's
    /// `DRIFT_DIMS * n` dimension-major block.
    pub fn shift_poses<F: Float>(&self, av: &Pose, u: &[F], x: &mut [F], y: &mut [F], yaw: &mut [F]) {
        let n = x.len();
        let [sa, sc, sy] = self.sd.map(F::from_f64);
        let (ax, ay, eps) = (F::from_f64(av.x), F::from_f64(av.y), F::from_f64(LOS_EPS * LOS_EPS));
        for i in 0..n {
            let (dx, dy) = (x[i] - ax, y[i] - ay);
            let inv = F::ONE / (dx * dx + dy * dy + eps).sqrt();
            let (lx, ly) = (dx * inv, dy * inv);
            let (a, c) = (sa * u[i], sc * u[n + i]);
            x[i] = x[i] + a * lx - c * ly;
            y[i] = y[i] + a * ly + c * lx;
            yaw[i] += sy * u[2 * n + i];
        }
    }

    /// The pose a drifting detector sees of `pose` with standardised offsets `u`
    /// for an AV at `av` (one pose of [`DetectorDrift::shift_poses`]).
    pub fn seen_pose(&self, av: &Pose, pose: Pose, u: [f64; DRIFT_DIMS]) -> Pose {
        let (mut x, mut y, mut yaw) = ([pose.x], [pose.y], [pose.yaw]);
        self.shift_poses(av, &u, &mut x, &mut y, &mut yaw);
        Pose { x: x[0], y: y[0], yaw: yaw[0] }
    }

    /// A path of standardised offsets over `steps` steps from `rng`: `u_0` from
    /// N(0, I), then the AR(1) (what the filter's [`DetectorDrift::propagate`] draws).
    pub fn sample_path<R: rand::Rng + ?Sized>(&self, steps: usize, rng: &mut R) -> Vec<[f64; DRIFT_DIMS]> {
        use rand_distr::{Distribution, StandardNormal};
        let mut path: Vec<[f64; DRIFT_DIMS]> = Vec::with_capacity(steps);
        for t in 0..steps {
            let mut u = [0.0; DRIFT_DIMS];
            for (k, u) in u.iter_mut().enumerate() {
                let e: f64 = StandardNormal.sample(rng);
                *u = match t {
                    0 => e,
                    _ => {
                        let rho = self.persistence[k];
                        rho * path[t - 1][k] + (1.0 - rho * rho).sqrt() * e
                    }
                };
            }
            path.push(u);
        }
        path
    }
}

/// Steps after which an AR(1) of persistence `rho` keeps `1/e` of its
/// correlation, times `dt`: the offset's memory in seconds.
pub fn persistence_time(rho: f64, dt: f64) -> f64 {
    if rho <= 0.0 {
        0.0
    } else {
        -dt / rho.ln()
    }
}

/// The drift's terms on a tape: its stored parameter `theta` (shape `[6]`).
pub struct DriftVars<'t, F: Float> {
    theta: Var<'t, F>,
}

impl<'t, F: Float> DriftVars<'t, F> {
    /// The drift of stored parameter `theta`.
    pub fn new(theta: Var<'t, F>) -> Self {
        DriftVars { theta }
    }

    fn at(&self, k: usize) -> Var<'t, F> {
        self.theta.slice(0, k, 1)
    }

    /// `ln N(u_t; rho u_{t-1}, 1 - rho^2)` summed over the three offsets, per row
    /// (`prev`, `next`: the three standardised offsets' rows), without the
    /// constant `-3/2 ln 2 pi`.
    pub fn transition_log_density(&self, prev: &[Var<'t, F>], next: &[Var<'t, F>]) -> Var<'t, F> {
        let mut total: Option<Var<'t, F>> = None;
        for k in 0..DRIFT_DIMS {
            let rho = self.at(k).mul_scalar(PERSISTENCE_SCALE).sigmoid();
            let var = (rho * rho).neg().add_scalar(1.0);
            let r = next[k] - prev[k] * rho;
            let term = (r * r / var).mul_scalar(-0.5) - var.ln().mul_scalar(0.5);
            total = Some(match total {
                Some(t) => t + term,
                None => term,
            });
        }
        total.expect("the drift has offsets")
    }

    /// The seen poses `pose + d` on the tape (see [`DetectorDrift::shift_poses`]):
    /// `(x, y, yaw)` of the states, `u` the three standardised offsets' rows and
    /// `av_x`, `av_y` the rows' AV positions (constants).
    pub fn shift_poses(
        &self,
        [x, y, yaw]: [Var<'t, F>; 3],
        u: &[Var<'t, F>],
        av_x: Var<'t, F>,
        av_y: Var<'t, F>,
    ) -> [Var<'t, F>; 3] {
        let sd = |k: usize| self.at(DRIFT_DIMS + k).mul_scalar(LOG_SD_SCALE).exp();
        let (dx, dy) = (x - av_x, y - av_y);
        let inv = (dx.square() + dy.square()).add_scalar(LOS_EPS * LOS_EPS).powf(-0.5);
        let (lx, ly) = (dx * inv, dy * inv);
        let (a, c) = (u[0] * sd(0), u[1] * sd(1));
        [x + a * lx - c * ly, y + a * ly + c * lx, yaw + u[2] * sd(2)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_start_is_half_persistent_at_the_floor_scales() {
        let d = DetectorDrift::from_raw(DetectorDrift::initial().data()).unwrap();
        assert_eq!(d.persistence, [0.5; 3]);
        for (s, want) in d.sd.iter().zip([BOX_MIN_SCALE, BOX_MIN_SCALE, BOX_MIN_YAW_SCALE]) {
            assert!((s - want).abs() < 1e-12);
        }
    }

    #[test]
    fn a_malformed_parameter_is_refused() {
        assert!(DetectorDrift::from_raw(&[0.0; 5]).is_err());
        assert!(DetectorDrift::from_raw(&[0.0, 0.0, f64::NAN, 0.0, 0.0, 0.0]).is_err());
    }

    #[test]
    fn the_shift_moves_along_and_across_the_line_of_sight() {
        let d = DetectorDrift { persistence: [0.5; 3], sd: [2.0, 3.0, 0.5] };
        // An object straight ahead of the AV along +x: along is +x, across is +y.
        let av = Pose { x: 1.0, y: 0.0, yaw: 0.0 };
        let (mut x, mut y, mut yaw) = ([11.0f32], [0.0f32], [0.1f32]);
        d.shift_poses(&av, &[0.5, -1.0, 2.0], &mut x, &mut y, &mut yaw);
        assert!((x[0] - 12.0).abs() < 1e-5 && (y[0] + 3.0).abs() < 1e-5 && (yaw[0] - 1.1).abs() < 1e-5);
    }

    #[test]
    fn the_offsets_keep_their_stationary_law() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let d = DetectorDrift { persistence: [0.9, 0.3, 0.0], sd: [1.0; 3] };
        let n = 20_000;
        let mut rng = rand::rngs::SmallRng::seed_from_u64(3);
        let mut normal = || -> Vec<f32> { (0..3 * n).map(|_| StandardNormal.sample(&mut rng)).collect() };
        let (u0, e) = (normal(), normal());
        let mut u1 = vec![0.0; 3 * n];
        d.propagate(n, &u0, &e, &mut u1);
        for k in 0..3 {
            let r = k * n..(k + 1) * n;
            let var = u1[r.clone()].iter().map(|v| (v * v) as f64).sum::<f64>() / n as f64;
            let cov = u1[r.clone()].iter().zip(&u0[r]).map(|(a, b)| (a * b) as f64).sum::<f64>() / n as f64;
            assert!((var - 1.0).abs() < 0.04, "offset {k}: variance {var}");
            assert!((cov - d.persistence[k]).abs() < 0.03, "offset {k}: lag-1 covariance {cov}");
        }
    }
}

/// Lags (steps) of the autocovariances [`drift_from_labels`] fits its AR(1)
/// through: the next step and ten steps on (1 s at KITTI's 0.1 s).
pub const CALIBRATION_LAGS: (usize, usize) = (1, 10);
/// Detections farther than this from their label along or across the line of
/// sight (m) are left out of the calibration: association failures, not drift.
const CALIBRATION_MAX_OFFSET: f64 = 1.0;
/// Detections whose yaw is farther than this from the label's (rad) are left
/// out: reversed headings (the flips), not drift.
const CALIBRATION_MAX_YAW: f64 = 0.5;

/// A detector drift calibrated on labels ([`drift_from_labels`]).
#[derive(Clone, Debug, PartialEq)]
pub struct DriftCalibration {
    /// The AR(1) drift.
    pub drift: DetectorDrift,
    /// Per offset (along, across, yaw): the detections' mean square offset from
    /// their labels and the autocovariances at the two [`CALIBRATION_LAGS`].
    pub autocovariance: [[f64; 3]; DRIFT_DIMS],
    /// Labelled detections used, and left out by the offset guards.
    pub used: usize,
    /// Labelled detections left out.
    pub left_out: usize,
}

/// Calibrates a detector drift on labelled box data (`states.csv` beside the
/// detections): each detection's offset from its label along and across the
/// line of sight and in yaw, and per offset the AR(1) through the
/// autocovariances of those offsets at lags `k1 < k2` ([`CALIBRATION_LAGS`]),
/// pooled over the pairs within objects: `rho = (c_k2 / c_k1)^(1 / (k2 - k1))`,
/// `s^2 = c_k1 / rho^k1`, capped at the offsets' mean square. What persists from
/// step to step is the drift; the rest is the white noise the box network
/// learns. Offsets beyond `CALIBRATION_MAX_OFFSET` or a yaw beyond
/// `CALIBRATION_MAX_YAW` are left out (and break the pairs through them).
/// Fails on data without labels or of points.
pub fn drift_from_labels(data: &Dataset) -> Result<DriftCalibration, String> {
    if data.kind() != ObservationKind::Boxes {
        return Err("a detector drift is calibrated on box detections".into());
    }
    let truth = data.states().ok_or("calibrating a detector drift needs labels (states.csv)")?;
    let (k1, k2) = CALIBRATION_LAGS;
    let lags = [0, k1, k2];
    // Sums of products and pair counts per offset and lag.
    let mut sums = [[0.0; 3]; DRIFT_DIMS];
    let mut pairs = [[0usize; 3]; DRIFT_DIMS];
    let (mut used, mut left_out) = (0, 0);
    for object in 0..data.objects().len() {
        let av = &data.scenes()[data.object_scene(object)].av;
        let offsets: Vec<Option<[f64; DRIFT_DIMS]>> = (0..data.steps())
            .map(|t| {
                let (label, det) = (truth.get(object, t)?, BoxObservationModel::items(data, object, t).first()?);
                let (dx, dy) = (label.x - av[t].x, label.y - av[t].y);
                let (along, across) = los_offsets(dx, dy, det.x - label.x, det.y - label.y);
                let o = [along, across, wrap_angle(det.yaw - label.yaw)];
                let kept = o[0].abs() <= CALIBRATION_MAX_OFFSET
                    && o[1].abs() <= CALIBRATION_MAX_OFFSET
                    && o[2].abs() <= CALIBRATION_MAX_YAW;
                if kept {
                    used += 1;
                } else {
                    left_out += 1;
                }
                kept.then_some(o)
            })
            .collect();
        for (j, &lag) in lags.iter().enumerate() {
            for t in lag..offsets.len() {
                if let (Some(a), Some(b)) = (offsets[t - lag], offsets[t]) {
                    for k in 0..DRIFT_DIMS {
                        sums[k][j] += a[k] * b[k];
                        pairs[k][j] += 1;
                    }
                }
            }
        }
    }
    let mut autocovariance = [[0.0; 3]; DRIFT_DIMS];
    let (mut persistence, mut sd) = ([0.0; DRIFT_DIMS], [0.0; DRIFT_DIMS]);
    let floors = [BOX_MIN_SCALE, BOX_MIN_SCALE, BOX_MIN_YAW_SCALE];
    for k in 0..DRIFT_DIMS {
        if pairs[k].contains(&0) {
            return Err(format!("too few labelled detections {k2} steps apart to calibrate a drift"));
        }
        let c = [0, 1, 2].map(|j| sums[k][j] / pairs[k][j] as f64);
        autocovariance[k] = c;
        let (rho, var) = if c[1] > 0.0 && c[2] > 0.0 {
            let rho = (c[2] / c[1]).powf(1.0 / (k2 - k1) as f64).min(MAX_PERSISTENCE);
            (rho, (c[1] / rho.powi(k1 as i32)).min(c[0]))
        } else {
            // Nothing persists: the least drift the model holds.
            (0.5, floors[k] * floors[k])
        };
        persistence[k] = rho;
        sd[k] = var.sqrt().max(floors[k]);
    }
    Ok(DriftCalibration { drift: DetectorDrift { persistence, sd }, autocovariance, used, left_out })
}
