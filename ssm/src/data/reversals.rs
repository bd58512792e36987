//! Heading reversals of a labelled box dataset: how often, and how persistently,
//! the detector reports an object's heading turned around against its label.
//! The KITTI import reports them ([`super::kitti::KittiSplitReport`]).

use serde::Serialize;

use crate::data::{BoxDetection, Dataset, Pose};
use crate::util::angles::wrap_angle;

impl BoxDetection {
    /// Whether this detection reports the heading of an object at `pose`
    /// reversed: more than pi/2 from it.
    ///
    /// ```
    /// use ssm::data::{BoxDetection, Pose};
    /// let d = BoxDetection { x: 0.0, y: 0.0, yaw: 3.0, length: 4.0, width: 2.0, score: 1.0 };
    /// assert!(d.reversed_against(Pose { x: 0.0, y: 0.0, yaw: 0.0 }));
    /// assert!(!d.reversed_against(Pose { x: 0.0, y: 0.0, yaw: 2.0 }));
    /// ```
    pub fn reversed_against(&self, pose: Pose) -> bool {
        wrap_angle(self.yaw - pose.yaw).abs() > std::f64::consts::FRAC_PI_2
    }
}

/// How the detections of a labelled box dataset that report their heading
/// reversed against the label (more than pi/2 from it, the rule of
/// [`BoxDetection::reversed_against`]) fall over objects and steps, beside
/// what independent reversals at the same rate would give. The catalogue's
/// `heading_flip` reverses each detection independently; a detector that
/// reverses some cars for many frames shows as `objects_with_any` well below
/// `objects_with_any_if_independent`, a `dispersion` above 1 and a
/// `persistence` above the rate.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct HeadingReversals {
    /// Detections at labelled steps.
    pub detections: usize,
    /// Of those, reversed against the label.
    pub reversed: usize,
    /// Objects with a labelled detection.
    pub objects: usize,
    /// Of those, objects with a reversed detection.
    pub objects_with_any: usize,
    /// Their expected number if every detection were reversed independently at
    /// the data's rate: the sum over objects of `1 - (1 - rate)^n`.
    pub objects_with_any_if_independent: f64,
    /// The dispersion index of the per-object counts, the mean over objects of
    /// `(k - n rate)^2 / (n rate (1 - rate))`: about 1 for independent
    /// reversals (`None` at a rate of 0 or 1).
    pub dispersion: Option<f64>,
    /// The share of steps with a reversed detection among the steps whose
    /// previous step had one (same object; a step is reversed if any of its
    /// detections is): the rate for independent reversals (`None` without such
    /// pairs).
    pub persistence: Option<f64>,
    /// Steps that count towards `persistence`.
    pub persistence_pairs: usize,
}

impl HeadingReversals {
    /// The share of detections reversed.
    pub fn rate(&self) -> f64 {
        self.reversed as f64 / self.detections.max(1) as f64
    }
}

/// [`HeadingReversals`] of `data`; `None` without labels or box detections.
pub fn heading_reversals(data: &Dataset) -> Option<HeadingReversals> {
    let truth = data.states()?;
    let boxes = data.boxes()?;
    // Per object with a labelled detection: (detections, reversed).
    let mut counts: Vec<(usize, usize)> = Vec::new();
    let (mut pairs, mut pairs_reversed) = (0usize, 0usize);
    for object in 0..data.objects().len() {
        let (mut n, mut k) = (0usize, 0usize);
        let mut previous_reversed = false;
        for t in 0..data.steps() {
            let labelled = truth.get(object, t).zip(boxes.get(object, t));
            let Some((s, detection)) = labelled else {
                previous_reversed = false;
                continue;
            };
            let pose = Pose { x: s.x, y: s.y, yaw: s.yaw };
            let reversed = usize::from(detection.reversed_against(pose));
            if previous_reversed {
                pairs += 1;
                pairs_reversed += usize::from(reversed > 0);
            }
            previous_reversed = reversed > 0;
            n += 1;
            k += reversed;
        }
        if n > 0 {
            counts.push((n, k));
        }
    }
    let detections: usize = counts.iter().map(|c| c.0).sum();
    let reversed: usize = counts.iter().map(|c| c.1).sum();
    let rate = reversed as f64 / detections.max(1) as f64;
    let dispersion = (rate > 0.0 && rate < 1.0).then(|| {
        let chi2: f64 =
            counts.iter().map(|&(n, k)| (k as f64 - n as f64 * rate).powi(2) / (n as f64 * rate * (1.0 - rate))).sum();
        chi2 / counts.len() as f64
    });
    Some(HeadingReversals {
        detections,
        reversed,
        objects: counts.len(),
        objects_with_any: counts.iter().filter(|c| c.1 > 0).count(),
        objects_with_any_if_independent: counts.iter().map(|&(n, _)| 1.0 - (1.0 - rate).powi(n as i32)).sum(),
        dispersion,
        persistence: (pairs > 0).then(|| pairs_reversed as f64 / pairs as f64),
        persistence_pairs: pairs,
    })
}
