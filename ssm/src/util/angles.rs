//! Angles: wrapping to `(-pi, pi]` and turning a heading around, shared by the
//! data (heading reversals against labels), the observation models and the
//! checks.

use std::f64::consts::{PI, TAU};

/// An angle wrapped to `(-pi, pi]`.
///
/// ```
/// use ssm::util::angles::wrap_angle;
/// assert!((wrap_angle(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
/// assert!((wrap_angle(-0.5) + 0.5).abs() < 1e-15);
/// ```
pub fn wrap_angle(a: f64) -> f64 {
    let w = a - TAU * (a / TAU).round();
    if w <= -PI {
        w + TAU
    } else {
        w
    }
}

/// The heading `yaw` turned around, wrapped to `(-pi, pi]`: how a detector that
/// reverses a box reports it, and how a reversed state or prior draw is turned.
pub fn reversed_heading(yaw: f64) -> f64 {
    wrap_angle(yaw + PI)
}
