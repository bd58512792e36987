//! Discrepancy statistics for posterior predictive checks (SPEC §7), and their
//! calibration.
//!
//! A statistic `T` maps a set of [`ObjectSample`]s — drawn state paths with their
//! actions and observations — to one number. `diagnose` evaluates every statistic
//! twice per draw `k`: on the drawn path with the *measured* observations (and the
//! path's own actions), and on the same path with observations and actions
//! *replicated* from the fitted model. A model that explains the data gives
//! differences `D_k = T(measured_k) - T(replicated_k)` centred at zero;
//! [`calibrate`] turns them into z-scores and Holm-adjusted p-values.
//!
//! Geometry: the box frame of a state has `u` along its heading and `v'` to its
//! left, origin at the box centre ([`to_box_frame`]). Every statistic is one
//! function over a view of the samples, which holds each observed object-step
//! in its state's box frame; a statistic without enough data is NaN.

use std::f64::consts::FRAC_PI_2;

use serde::{Deserialize, Serialize};

use super::{ObjectObservations, ObjectSample};
use crate::data::{Dataset, ObservationKind, Pose};
use crate::models::observation::edges::to_box_frame;
use crate::stats::{mean, normal_cdf, sd};
use crate::util::angles::wrap_angle;

/// Fewest points of an object-step for its extents to count (`*_extent_ratio`).
pub const MIN_EXTENT_POINTS: usize = 4;
/// Objects whose prior speed is below this (m/s) have no `initial_lag`.
pub const MIN_LAG_SPEED: f64 = 1.0;
/// Fewest draws with finite statistics for a calibrated z-score.
pub const MIN_CALIBRATION_DRAWS: usize = 3;
/// Guard of the line-of-sight normalisation (m), as in the box observation model.
const LOS_EPS: f64 = 1e-6;

/// A discrepancy statistic.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CheckDef {
    /// Identifier (snake case), unique among the checks of a kind.
    pub name: &'static str,
    /// One sentence a person reads, with units.
    pub description: &'static str,
    /// The observation kinds it applies to.
    pub kinds: &'static [ObservationKind],
    /// The catalogue extension a discrepancy can reveal, and which way; `None` for
    /// a general check.
    pub suggests: Option<Suggestion>,
}

/// A catalogue extension a check can reveal, and the sign of the discrepancy it
/// gives that check: the screen that makes the extension plausible is one-sided
/// in that direction ([`CheckResult::screen_p`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Suggestion {
    /// The extension's id (`"latency"`, `"clutter"`, `"size_bias"`,
    /// `"heavy_tailed_accel"`, `"heading_flip"`, `"persistent_flip"`).
    pub extension: &'static str,
    /// The sign of measured minus replicated under that extension.
    pub direction: Direction,
}

/// The sign of the discrepancy, measured minus replicated, that an extension
/// produces in the check that suggests it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    /// The measured statistic is higher than the model's replicates (clutter's far
    /// points, heading flips' reversals, persistent flips' runs of them, heavy
    /// tails' kurtosis).
    Higher,
    /// The measured statistic is lower (a sensor lag's negative slope and initial
    /// offset, heavy tails' lower Geary ratio).
    Lower,
    /// Either sign (extents under- or over-reported).
    Either,
}

impl Direction {
    /// The p-value of a calibrated `z` in this direction: `1 - Phi(z)` for
    /// [`Direction::Higher`], `Phi(z)` for [`Direction::Lower`], two-sided
    /// `2 (1 - Phi(|z|))` for [`Direction::Either`]; 1 when `z` is 0 (no spread).
    pub fn p_value(self, z: f64) -> f64 {
        if z == 0.0 {
            return 1.0;
        }
        match self {
            Direction::Higher => normal_cdf(-z),
            Direction::Lower => normal_cdf(z),
            Direction::Either => (2.0 * normal_cdf(-z.abs())).min(1.0),
        }
    }
}

/// A definition with the function that computes it.
struct Check {
    def: CheckDef,
    stat: fn(&View) -> f64,
}

const POINTS: &[ObservationKind] = &[ObservationKind::Points];
const BOXES: &[ObservationKind] = &[ObservationKind::Boxes];
const BOTH: &[ObservationKind] = &[ObservationKind::Points, ObservationKind::Boxes];

/// A general check: it suggests no extension.
const fn check(
    name: &'static str,
    description: &'static str,
    kinds: &'static [ObservationKind],
    stat: fn(&View) -> f64,
) -> Check {
    Check { def: CheckDef { name, description, kinds, suggests: None }, stat }
}

/// A check that can reveal `extension`, which moves it in `direction`.
const fn revealing(
    name: &'static str,
    description: &'static str,
    kinds: &'static [ObservationKind],
    extension: &'static str,
    direction: Direction,
    stat: fn(&View) -> f64,
) -> Check {
    Check { def: CheckDef { name, description, kinds, suggests: Some(Suggestion { extension, direction }) }, stat }
}

/// Every check, in the order [`checks_for`] and [`statistics`] use.
static CHECKS: [Check; 17] = [
    revealing(
        "along_offset_vs_speed",
        "Least-squares slope, over observed object-steps, of the observation's mean offset along the heading \
         (points' mean u, or the detection centre's u; m) on the state's speed (m/s), in seconds; \
         a sensor lag of delta seconds makes it about -delta.",
        BOTH,
        "latency",
        Direction::Lower,
        along_offset_vs_speed,
    ),
    revealing(
        "initial_lag",
        "Mean over objects of the initial state's offset from the prior mean along the prior heading, divided by \
         the prior speed (s; objects slower than 1 m/s left out): the smoother's initial states against draws from \
         the prior. Observations that lag the state by delta seconds pull the path about delta behind the prior.",
        BOTH,
        "latency",
        Direction::Lower,
        initial_lag,
    ),
    revealing(
        "far_point_fraction",
        "Fraction of points farther outside the object's box than the box is wide: a distance in the object's own \
         size, not a fixed one (unitless).",
        POINTS,
        "clutter",
        Direction::Higher,
        far_point_fraction,
    ),
    revealing(
        "yaw_reversal_fraction",
        "Fraction of detections whose heading differs from the state's by more than pi/2 rad (unitless).",
        BOXES,
        "heading_flip",
        Direction::Higher,
        yaw_reversal_fraction,
    ),
    revealing(
        "yaw_reversal_persistence",
        "Lag-one correlation (phi coefficient) of the reversal indicators (heading more than pi/2 rad from the \
         state's) over pairs of detections of one object at consecutive steps (unitless; 0 for reversals \
         independent from step to step, and when no detection or every one is reversed; lambda for a two-state \
         chain with lag-one correlation lambda).",
        BOXES,
        "persistent_flip",
        Direction::Higher,
        yaw_reversal_persistence,
    ),
    revealing(
        "length_extent_ratio",
        "Mean, over object-steps with at least 4 points, of the points' extent along the heading divided by \
         the object's length (unitless).",
        POINTS,
        "size_bias",
        Direction::Either,
        length_extent_ratio,
    ),
    revealing(
        "width_extent_ratio",
        "Mean, over object-steps with at least 4 points, of the points' extent across the heading divided by \
         the object's width (unitless).",
        POINTS,
        "size_bias",
        Direction::Either,
        width_extent_ratio,
    ),
    revealing(
        "accel_kurtosis",
        "Sample excess kurtosis of the accelerations' innovations standardised by the fitted policy's mean and sd \
         at each state (the raw accelerations when the policy is not known), pooled over objects and steps \
         (unitless; 0 for a Gaussian).",
        BOTH,
        "heavy_tailed_accel",
        Direction::Higher,
        accel_kurtosis,
    ),
    revealing(
        "accel_peakedness",
        "Geary's ratio, mean |x| / sqrt(mean x^2), of the same standardised acceleration innovations (unitless; \
         sqrt(2/pi) = 0.798 for a Gaussian, lower for heavier tails). Set by the bulk of the innovations, not by \
         the few largest, which a smoother under a Gaussian policy spreads over neighbouring steps.",
        BOTH,
        "heavy_tailed_accel",
        Direction::Lower,
        accel_peakedness,
    ),
    check(
        "pinch_kurtosis",
        "Sample excess kurtosis of the pinches (rates of change of curvature), pooled over objects and steps \
         (unitless; 0 for a Gaussian).",
        BOTH,
        pinch_kurtosis,
    ),
    check(
        "edge_residual_sd",
        "Standard deviation of each point's signed distance to the nearest edge of its box, positive outside (m).",
        POINTS,
        edge_residual_sd,
    ),
    check(
        "across_offset_vs_speed",
        "Least-squares slope, over object-steps with points, of the points' mean offset to the left of the \
         heading (m) on the state's speed (m/s), in seconds.",
        POINTS,
        across_offset_vs_speed,
    ),
    check(
        "points_near_side_fraction",
        "Fraction of points on the half of the box facing the AV (split by the line through the box centre \
         perpendicular to the direction to the AV; unitless).",
        POINTS,
        points_near_side_fraction,
    ),
    check(
        "speed_change_sd",
        "Standard deviation of the speed change per step, acceleration times dt (m/s).",
        POINTS,
        speed_change_sd,
    ),
    check(
        "los_along_residual_sd",
        "Standard deviation of the detection centre's offset from the state's position along the line of sight \
         from the AV (m).",
        BOXES,
        los_along_residual_sd,
    ),
    check(
        "los_across_residual_sd",
        "Standard deviation of the detection centre's offset from the state's position across the line of \
         sight from the AV (m).",
        BOXES,
        los_across_residual_sd,
    ),
    check(
        "yaw_residual_sd",
        "Standard deviation of the wrapped heading residual (detection minus state) over detections within \
         pi/2 of the state's heading (rad).",
        BOXES,
        yaw_residual_sd,
    ),
];

/// The checks that apply to data of `kind`, in a fixed order.
///
/// ```
/// use ssm::criticism::checks::checks_for;
/// use ssm::data::ObservationKind;
/// let names: Vec<_> = checks_for(ObservationKind::Boxes).iter().map(|c| c.name).collect();
/// assert_eq!(names[..3], ["along_offset_vs_speed", "initial_lag", "yaw_reversal_fraction"]);
/// ```
pub fn checks_for(kind: ObservationKind) -> Vec<&'static CheckDef> {
    active(kind).map(|c| &c.def).collect()
}

fn active(kind: ObservationKind) -> impl Iterator<Item = &'static Check> {
    CHECKS.iter().filter(move |c| c.def.kinds.contains(&kind))
}

/// The value of every check of [`checks_for`]`(data.kind())`, in that order, over
/// the samples. `data` gives the AV pose per scene and step, each object's length
/// and width, and `dt`. A statistic with too little data is NaN; a sample whose
/// object index or steps fall outside `data` contributes only what lies inside.
pub fn statistics(data: &Dataset, samples: &[ObjectSample]) -> Vec<f64> {
    let view = View::new(data, samples);
    active(data.kind()).map(|c| (c.stat)(&view)).collect()
}

/// One observed object-step, in the box frame of its state.
struct Step {
    /// The state's speed (m/s).
    speed: f64,
    /// The object's length and width (m).
    length: f64,
    width: f64,
    /// The AV's position in the box frame.
    av: (f64, f64),
    /// The observed points, or the detection centre, in the box frame (never empty).
    items: Vec<(f64, f64)>,
    /// The wrapped heading residual of a detection (box data only).
    yaw_residual: Option<f64>,
}

/// What the statistics look at: observed object-steps, pooled actions and `dt`.
struct View {
    steps: Vec<Step>,
    /// Per object: `(x_0 - prior mean) . prior heading / prior speed` (s).
    initial_lags: Vec<f64>,
    accels: Vec<f64>,
    /// Standardised acceleration innovations (empty when the samples have none).
    innovations: Vec<f64>,
    pinches: Vec<f64>,
    /// Per pair of detections of one object at consecutive steps, whether each
    /// reports the heading reversed (box data only).
    reversal_pairs: Vec<(bool, bool)>,
    dt: f64,
}

impl View {
    fn new(data: &Dataset, samples: &[ObjectSample]) -> View {
        let mut view = View {
            steps: Vec::new(),
            initial_lags: Vec::new(),
            accels: Vec::new(),
            innovations: Vec::new(),
            pinches: Vec::new(),
            reversal_pairs: Vec::new(),
            dt: data.dt(),
        };
        for s in samples {
            view.accels.extend(s.actions.iter().map(|a| a.accel));
            view.innovations.extend(s.accel_innovations.iter().copied());
            view.pinches.extend(s.actions.iter().map(|a| a.pinch));
            let Some(object) = data.objects().get(s.object) else { continue };
            let prior = object.prior.mean;
            if let (Some(x0), true) = (s.states.first(), prior.v.abs() >= MIN_LAG_SPEED) {
                let along = (x0.x - prior.x) * prior.yaw.cos() + (x0.y - prior.y) * prior.yaw.sin();
                view.initial_lags.push(along / prior.v);
            }
            let av = &data.scenes()[data.object_scene(s.object)].av;
            let steps = match &s.observations {
                ObjectObservations::Points(p) => p.len(),
                ObjectObservations::Boxes(b) => b.len(),
            };
            // Whether the previous step's detection is reversed (None: no detection there).
            let mut previous_reversal: Option<bool> = None;
            for t in 0..steps {
                let reversal = previous_reversal.take();
                let (Some(x), Some(a)) = (s.states.get(t), av.get(t)) else { continue };
                let pose = Pose { x: x.x, y: x.y, yaw: x.yaw };
                let (items, yaw_residual) = match &s.observations {
                    ObjectObservations::Points(p) => (p[t].iter().map(|&q| to_box_frame(pose, q)).collect(), None),
                    ObjectObservations::Boxes(b) => match &b[t] {
                        Some(d) => (vec![to_box_frame(pose, [d.x, d.y])], Some(wrap_angle(d.yaw - x.yaw))),
                        None => continue,
                    },
                };
                if let Some(r) = yaw_residual {
                    let reversed = r.abs() > FRAC_PI_2;
                    if let Some(before) = reversal {
                        view.reversal_pairs.push((before, reversed));
                    }
                    previous_reversal = Some(reversed);
                }
                if !items.is_empty() {
                    let av = to_box_frame(pose, [a.x, a.y]);
                    view.steps.push(Step {
                        speed: x.v,
                        length: object.length,
                        width: object.width,
                        av,
                        items,
                        yaw_residual,
                    });
                }
            }
        }
        view
    }

    /// Every observed item (point or detection centre) with its step.
    fn items(&self) -> impl Iterator<Item = (&Step, (f64, f64))> {
        self.steps.iter().flat_map(|s| s.items.iter().map(move |&p| (s, p)))
    }

    /// Every detection's centre offset along and across the line of sight from the
    /// AV to the state's position (the object is at the box-frame origin).
    fn los_residuals(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        self.steps.iter().filter(|s| s.yaw_residual.is_some()).map(|s| {
            let (ax, ay) = s.av;
            let r = (ax * ax + ay * ay + LOS_EPS * LOS_EPS).sqrt();
            let (lx, ly) = (-ax / r, -ay / r);
            let (u, v) = s.items[0];
            (u * lx + v * ly, v * lx - u * ly)
        })
    }
}

// ---------------------------------------------------------------- statistics

fn along_offset_vs_speed(view: &View) -> f64 {
    slope(view.steps.iter().map(|s| (s.speed, mean(s.items.iter().map(|p| p.0)))))
}

fn initial_lag(view: &View) -> f64 {
    mean(view.initial_lags.iter().copied())
}

fn across_offset_vs_speed(view: &View) -> f64 {
    slope(view.steps.iter().map(|s| (s.speed, mean(s.items.iter().map(|p| p.1)))))
}

fn far_point_fraction(view: &View) -> f64 {
    fraction(view.items().map(|(s, p)| edge_distance(s, p) > s.width))
}

fn yaw_reversal_fraction(view: &View) -> f64 {
    fraction(view.steps.iter().filter_map(|s| s.yaw_residual).map(|r| r.abs() > FRAC_PI_2))
}

fn yaw_reversal_persistence(view: &View) -> f64 {
    let pairs = &view.reversal_pairs;
    let both = fraction(pairs.iter().map(|&(a, b)| a && b));
    let (first, second) = (fraction(pairs.iter().map(|p| p.0)), fraction(pairs.iter().map(|p| p.1)));
    let spread = (first * (1.0 - first) * second * (1.0 - second)).sqrt();
    if spread > 0.0 {
        (both - first * second) / spread
    } else if pairs.is_empty() {
        f64::NAN
    } else {
        // No reversal (or nothing but reversals) among the pairs: no runs.
        0.0
    }
}

fn length_extent_ratio(view: &View) -> f64 {
    let extended = view.steps.iter().filter(|s| s.items.len() >= MIN_EXTENT_POINTS);
    mean(extended.map(|s| extent(s.items.iter().map(|p| p.0)) / s.length))
}

fn width_extent_ratio(view: &View) -> f64 {
    let extended = view.steps.iter().filter(|s| s.items.len() >= MIN_EXTENT_POINTS);
    mean(extended.map(|s| extent(s.items.iter().map(|p| p.1)) / s.width))
}

fn accel_kurtosis(view: &View) -> f64 {
    if view.innovations.is_empty() {
        excess_kurtosis(&view.accels)
    } else {
        excess_kurtosis(&view.innovations)
    }
}

fn accel_peakedness(view: &View) -> f64 {
    if view.innovations.is_empty() {
        geary_ratio(&view.accels)
    } else {
        geary_ratio(&view.innovations)
    }
}

fn pinch_kurtosis(view: &View) -> f64 {
    excess_kurtosis(&view.pinches)
}

fn edge_residual_sd(view: &View) -> f64 {
    sd(view.items().map(|(s, p)| edge_distance(s, p)))
}

fn points_near_side_fraction(view: &View) -> f64 {
    fraction(view.items().map(|(s, (u, v))| u * s.av.0 + v * s.av.1 > 0.0))
}

fn speed_change_sd(view: &View) -> f64 {
    sd(view.accels.iter().map(|a| a * view.dt))
}

fn los_along_residual_sd(view: &View) -> f64 {
    sd(view.los_residuals().map(|r| r.0))
}

fn los_across_residual_sd(view: &View) -> f64 {
    sd(view.los_residuals().map(|r| r.1))
}

fn yaw_residual_sd(view: &View) -> f64 {
    sd(view.steps.iter().filter_map(|s| s.yaw_residual).filter(|r| r.abs() < FRAC_PI_2))
}

// ---------------------------------------------------------------- helpers

/// Signed distance (m) of a box-frame point to the nearest edge of the step's
/// box: the Euclidean distance to the box outside, minus the distance to the
/// nearest edge inside.
fn edge_distance(s: &Step, (u, v): (f64, f64)) -> f64 {
    let (du, dv) = (u.abs() - s.length / 2.0, v.abs() - s.width / 2.0);
    if du > 0.0 || dv > 0.0 {
        du.max(0.0).hypot(dv.max(0.0))
    } else {
        du.max(dv)
    }
}

/// Fraction of `true`; NaN when empty.
fn fraction(flags: impl IntoIterator<Item = bool>) -> f64 {
    mean(flags.into_iter().map(|f| f64::from(u8::from(f))))
}

/// `max - min`; NaN when empty.
fn extent(xs: impl IntoIterator<Item = f64>) -> f64 {
    let (lo, hi) = xs.into_iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| (lo.min(x), hi.max(x)));
    if lo <= hi {
        hi - lo
    } else {
        f64::NAN
    }
}

/// Least-squares slope of `y` on `x`; NaN below 2 pairs or when `x` is constant.
fn slope(pairs: impl IntoIterator<Item = (f64, f64)>) -> f64 {
    let pairs: Vec<(f64, f64)> = pairs.into_iter().collect();
    let (mx, my) = (mean(pairs.iter().map(|p| p.0)), mean(pairs.iter().map(|p| p.1)));
    let sxy: f64 = pairs.iter().map(|(x, y)| (x - mx) * (y - my)).sum();
    let sxx: f64 = pairs.iter().map(|(x, _)| (x - mx).powi(2)).sum();
    if pairs.len() < 2 || sxx <= 0.0 {
        f64::NAN
    } else {
        sxy / sxx
    }
}

/// Sample excess kurtosis `m4 / m2^2 - 3` (central moments, denominator `n`); NaN
/// below 4 values or without spread.
fn excess_kurtosis(xs: &[f64]) -> f64 {
    let m = mean(xs.iter().copied());
    let m2 = mean(xs.iter().map(|x| (x - m).powi(2)));
    let m4 = mean(xs.iter().map(|x| (x - m).powi(4)));
    if xs.len() < 4 || m2 <= 0.0 {
        f64::NAN
    } else {
        m4 / (m2 * m2) - 3.0
    }
}

/// Geary's ratio `mean |x - m| / sqrt(mean (x - m)^2)` (denominator `n`):
/// `sqrt(2 / pi)` for a Gaussian, lower for heavier tails. NaN below 4 values
/// or without spread.
pub fn geary_ratio(xs: &[f64]) -> f64 {
    let m = mean(xs.iter().copied());
    let m1 = mean(xs.iter().map(|x| (x - m).abs()));
    let m2 = mean(xs.iter().map(|x| (x - m).powi(2)));
    if xs.len() < 4 || m2 <= 0.0 {
        f64::NAN
    } else {
        m1 / m2.sqrt()
    }
}

// ---------------------------------------------------------------- calibration

/// One calibrated check.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct CheckResult {
    /// The check's name ([`CheckDef::name`]).
    pub name: String,
    /// The extension it can reveal ([`CheckDef::suggests`]).
    pub suggests: Option<String>,
    /// Mean over the usable draws of `T(measured)`.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub measured: f64,
    /// Mean over the usable draws of `T(replicated)`.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub replicated: f64,
    /// Standard deviation over the usable draws of `T(replicated)`.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub replicated_sd: f64,
    /// `mean(D) / sd(D)` of the differences `D = T(measured) - T(replicated)`.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub z: f64,
    /// Two-sided p-value `2 (1 - Phi(|z|))`.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub p: f64,
    /// For a check that suggests an extension, the p-value in the direction that
    /// extension moves it ([`Suggestion::direction`]): the screen that makes the
    /// extension plausible. `None` for a general check (and in reports written
    /// before the screen was one-sided).
    #[serde(default)]
    pub screen_p: Option<f64>,
    /// Holm-adjusted p-value over the checks.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub p_adjusted: f64,
    /// `p_adjusted < alpha`.
    pub significant: bool,
    /// Number of usable draws (both statistics finite).
    pub draws: usize,
}

/// Calibrates the checks `defs`: `measured[k][c]` and `replicated[k][c]` are
/// statistic `c` for draw `k` (the same drawn path with measured vs replicated
/// observations and actions).
///
/// Per check, over the draws with both values finite, `D_k = measured - replicated`
/// and `z = mean(D) / sd(D)` (the spread of `D` over draws is the reference, as in
/// a posterior predictive p-value; with fewer than [`MIN_CALIBRATION_DRAWS`] draws
/// or `sd(D) = 0`, `z = 0` and `p = 1`); `p = 2 (1 - Phi(|z|))`, Holm-adjusted
/// over the checks, and significant when the adjusted p is below `alpha`.
///
/// Panics if the rows do not all have one value per check, or the two tables have
/// different numbers of draws.
#[track_caller]
pub fn calibrate(defs: &[&CheckDef], measured: &[Vec<f64>], replicated: &[Vec<f64>], alpha: f64) -> Vec<CheckResult> {
    assert_eq!(
        measured.len(),
        replicated.len(),
        "calibrate: {} measured draws but {} replicated",
        measured.len(),
        replicated.len()
    );
    for (k, (m, r)) in measured.iter().zip(replicated).enumerate() {
        assert!(
            m.len() == defs.len() && r.len() == defs.len(),
            "calibrate: draw {k} has {} measured and {} replicated statistics for {} checks",
            m.len(),
            r.len(),
            defs.len()
        );
    }
    let mut results: Vec<CheckResult> = defs
        .iter()
        .enumerate()
        .map(|(c, def)| {
            let pairs: Vec<(f64, f64)> = measured
                .iter()
                .zip(replicated)
                .map(|(m, r)| (m[c], r[c]))
                .filter(|(m, r)| m.is_finite() && r.is_finite())
                .collect();
            let d: Vec<f64> = pairs.iter().map(|(m, r)| m - r).collect();
            let sd_d = sd(d.iter().copied());
            let z = if d.len() >= MIN_CALIBRATION_DRAWS && sd_d > 0.0 { mean(d.iter().copied()) / sd_d } else { 0.0 };
            let p = Direction::Either.p_value(z);
            CheckResult {
                name: def.name.to_string(),
                suggests: def.suggests.map(|s| s.extension.to_string()),
                measured: mean(pairs.iter().map(|p| p.0)),
                replicated: mean(pairs.iter().map(|p| p.1)),
                replicated_sd: sd(pairs.iter().map(|p| p.1)),
                z,
                p,
                screen_p: def.suggests.map(|s| s.direction.p_value(z)),
                p_adjusted: p,
                significant: false,
                draws: pairs.len(),
            }
        })
        .collect();
    let adjusted = holm(&results.iter().map(|r| r.p).collect::<Vec<_>>());
    for (r, p) in results.iter_mut().zip(adjusted) {
        r.p_adjusted = p;
        r.significant = p < alpha;
    }
    results
}

/// Beyond this |z| a check's differences have no spread but rounding: the
/// measured statistic sits off every replicate by the same amount.
pub const UNBOUNDED_Z: f64 = 1e6;

/// The bound a z beyond [`UNBOUNDED_Z`] is written as (a ratio to a rounding
/// error is not a number to print); `None` within it.
pub fn z_bound(z: f64) -> Option<&'static str> {
    if z >= UNBOUNDED_Z {
        Some("> 1e6 (no spread)")
    } else if z <= -UNBOUNDED_Z {
        Some("< -1e6 (no spread)")
    } else {
        None
    }
}

/// A check's z for people, with `digits` decimals, or its bound ([`z_bound`]).
pub fn format_z(z: f64, digits: usize) -> String {
    z_bound(z).map_or_else(|| format!("{z:.digits$}"), str::to_string)
}

/// Holm's step-down adjustment: the `i`-th smallest p-value (from 0) becomes
/// `max over j <= i of min(1, (m - j) p_(j))`.
pub fn holm(p: &[f64]) -> Vec<f64> {
    let m = p.len();
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by(|&a, &b| p[a].total_cmp(&p[b]));
    let mut adjusted = vec![1.0; m];
    let mut running: f64 = 0.0;
    for (i, &k) in order.iter().enumerate() {
        running = running.max(((m - i) as f64 * p[k]).min(1.0));
        adjusted[k] = running;
    }
    adjusted
}

/// [`holm`] over the members of a family (`family[i]`), each adjusted for the
/// family's size only; a p-value outside it is 1, as no test of it is made.
pub fn holm_within(p: &[f64], family: &[bool]) -> Vec<f64> {
    assert_eq!(p.len(), family.len(), "one membership per p-value");
    let members: Vec<f64> = p.iter().zip(family).filter(|(_, &m)| m).map(|(&p, _)| p).collect();
    let mut adjusted = holm(&members).into_iter();
    family.iter().map(|&m| if m { adjusted.next().expect("one per member") } else { 1.0 }).collect()
}
