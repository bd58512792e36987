//! Frames: the ego poses of a sequence as camera-to-world transforms, the
//! reference camera's offset from the calibration, and the bird's-eye pose of a
//! camera-frame box.

use crate::data::error::{DataError, Place, Problem};
use crate::data::Pose;

use super::files::SeqFile;

/// A camera-to-world transform: `p_world = R (p + c) + t`.
#[derive(Clone, Copy, Debug)]
pub(super) struct CamToWorld {
    pub(super) r: [[f64; 3]; 3],
    pub(super) t: [f64; 3],
}

impl CamToWorld {
    pub(super) fn point(&self, p: [f64; 3]) -> [f64; 3] {
        let mut out = self.t;
        for (i, o) in out.iter_mut().enumerate() {
            *o += self.r[i][0] * p[0] + self.r[i][1] * p[1] + self.r[i][2] * p[2];
        }
        out
    }

    pub(super) fn dir(&self, d: [f64; 3]) -> [f64; 3] {
        let mut out = [0.0; 3];
        for (i, o) in out.iter_mut().enumerate() {
            *o = self.r[i][0] * d[0] + self.r[i][1] * d[1] + self.r[i][2] * d[2];
        }
        out
    }

    /// Bird's-eye world pose of a camera-frame point and `rot_y` heading.
    pub(super) fn bev(&self, p_ref: [f64; 3], offset: [f64; 3], rot_y: f64) -> Pose {
        let p = self.point([p_ref[0] + offset[0], p_ref[1] + offset[1], p_ref[2] + offset[2]]);
        let d = self.dir([rot_y.cos(), 0.0, -rot_y.sin()]);
        Pose { x: p[2], y: -p[0], yaw: (-d[0]).atan2(d[2]) }
    }

    /// Bird's-eye world pose of the reference camera (position, optical axis).
    pub(super) fn camera(&self, offset: [f64; 3]) -> Pose {
        let p = self.point(offset);
        let d = self.dir([0.0, 0.0, 1.0]);
        Pose { x: p[2], y: -p[0], yaw: (-d[0]).atan2(d[2]) }
    }
}

/// The reference camera's origin in the cam2 frame, from `P2 = K [I | c]`.
pub(super) fn cam2_offset(file: &SeqFile) -> Result<[f64; 3], DataError> {
    for (i, line) in file.text.lines().enumerate() {
        if let Some(rest) = line.trim_start().strip_prefix("P2:") {
            let bad = |problem| DataError::invalid(&file.name, Place::Line(i + 1), "P2", problem);
            // Counted before collected: a line of a million fields allocates nothing.
            let found = rest.split_whitespace().count();
            if found != 12 {
                return Err(bad(Problem::FieldCount { expected: 12, found }));
            }
            let v: Vec<&str> = rest.split_whitespace().collect();
            let mut p = [0.0; 12];
            for (x, t) in p.iter_mut().zip(&v) {
                *x = t
                    .parse()
                    .ok()
                    .filter(|x: &f64| x.is_finite())
                    .ok_or_else(|| bad(Problem::Malformed { text: t.to_string(), expected: "a finite number" }))?;
            }
            let (fx, cx, fy, cy) = (p[0], p[2], p[5], p[6]);
            if fx.abs() < 1e-9 || fy.abs() < 1e-9 {
                return Err(bad(Problem::Other("zero focal length".into())));
            }
            let cz = p[11];
            return Ok([(p[3] - cx * cz) / fx, (p[7] - cy * cz) / fy, cz]);
        }
    }
    Err(DataError::invalid(&file.name, Place::Line(1), "P2", Problem::Other("no `P2:` line".into())))
}

/// The ego poses, one per frame.
pub(super) fn read_poses(file: &SeqFile) -> Result<Vec<CamToWorld>, DataError> {
    const COLS: [&str; 12] = ["r00", "r01", "r02", "t0", "r10", "r11", "r12", "t1", "r20", "r21", "r22", "t2"];
    let mut poses = Vec::new();
    for row in file.rows(&COLS, None) {
        let row = row?;
        let mut m = [0.0; 12];
        for (i, x) in m.iter_mut().enumerate() {
            *x = row.num(i)?;
        }
        poses.push(CamToWorld {
            r: [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]],
            t: [m[3], m[7], m[11]],
        });
    }
    Ok(poses)
}
