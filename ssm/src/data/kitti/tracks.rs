//! Tracks: labels associated with detections frame by frame, and the speed and
//! curvature of a labelled run by finite differences.

use std::collections::BTreeMap;

use crate::data::Pose;

use super::files::{Det, Label};
use super::{KittiOptions, KITTI_FRAME_DT};

/// Greedy one-to-one association per frame by increasing bird's-eye distance
/// within the gate. Returns, per label, the index of its detection, and per
/// detection whether it was matched.
pub(super) fn associate(labels: &[Label], dets: &[Det], gate: f64) -> (Vec<Option<usize>>, Vec<bool>) {
    let mut by_frame: BTreeMap<usize, (Vec<usize>, Vec<usize>)> = BTreeMap::new();
    for (i, l) in labels.iter().enumerate() {
        by_frame.entry(l.frame).or_default().0.push(i);
    }
    for (j, d) in dets.iter().enumerate() {
        by_frame.entry(d.frame).or_default().1.push(j);
    }
    let mut label_det = vec![None; labels.len()];
    let mut det_used = vec![false; dets.len()];
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for (ls, ds) in by_frame.values() {
        pairs.clear();
        for &i in ls {
            for &j in ds {
                let (a, b) = (labels[i].p, dets[j].p);
                let dist = (a[0] - b[0]).hypot(a[2] - b[2]);
                if dist <= gate {
                    pairs.push((dist, i, j));
                }
            }
        }
        pairs.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)).then(x.2.cmp(&y.2)));
        for &(_, i, j) in &pairs {
            if label_det[i].is_none() && !det_used[j] {
                label_det[i] = Some(j);
                det_used[j] = true;
            }
        }
    }
    (label_det, det_used)
}

/// Unwraps a sequence of angles so consecutive differences lie in [-pi, pi].
pub(super) fn unwrap_angles(a: &mut [f64]) {
    use std::f64::consts::{PI, TAU};
    for i in 1..a.len() {
        let d = (a[i] - a[i - 1] + PI).rem_euclid(TAU) - PI;
        a[i] = a[i - 1] + d;
    }
}

/// Speed and curvature along one contiguous labelled run (10 Hz frames) by
/// central differences (see the module docs).
pub(super) fn speed_curvature(poses: &[Pose], o: &KittiOptions) -> Vec<(f64, f64)> {
    let n = poses.len();
    let mut yaw: Vec<f64> = poses.iter().map(|p| p.yaw).collect();
    unwrap_angles(&mut yaw);
    (0..n)
        .map(|i| {
            let i0 = i.saturating_sub(o.diff_half_width);
            let i1 = (i + o.diff_half_width).min(n - 1);
            if i1 == i0 {
                return (0.0, 0.0);
            }
            let time = (i1 - i0) as f64 * KITTI_FRAME_DT;
            let (dx, dy) = (poses[i1].x - poses[i0].x, poses[i1].y - poses[i0].y);
            let v = (dx * poses[i].yaw.cos() + dy * poses[i].yaw.sin()) / time;
            let yaw_rate = (yaw[i1] - yaw[i0]) / time;
            let kappa = if v.abs() >= o.min_speed_for_curvature {
                (yaw_rate / v).clamp(-o.max_curvature, o.max_curvature)
            } else {
                0.0
            };
            (v, kappa)
        })
        .collect()
}
