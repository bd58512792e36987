//! Importing the KITTI tracking data (labels, PointRCNN detections, ORB-SLAM3
//! ego poses; see `SOURCE.md` in the data folder) as box-detection datasets.
//!
//! # What the importer produces
//!
//! Two datasets, AB3DMOT's split: `val` holds sequences
//! [`KITTI_VAL_SEQUENCES`] (or [`KittiOptions::val_sequences`]), `train` every
//! other sequence imported.
//!
//! * **Frames and units.** Everything is in the world frame of each sequence
//!   (the camera at frame 0, from the ego poses), as a bird's-eye view with
//!   `x` forward (camera `z`) and `y` left (camera `-x`), metres, radians
//!   counter-clockwise. Label and detection positions are the centre of the
//!   box's bottom face. A camera-frame point `p` (rectified reference camera,
//!   the frame of labels and detections) goes to the world as
//!   `R (p + c) + t`, where `[R | t]` is the ego pose `T_world_cam2` of the
//!   frame and `c` the position of the reference camera's origin in the cam2
//!   frame, decomposed exactly from the calibration's `P2 = K [I | c]`
//!   (about `(0.060, -0.0004, 0.0027)` m; SOURCE.md's `(0.0622, 0.0003,
//!   0.0027)` ignores the principal-point term). A heading `rot_y` is the
//!   camera-frame direction `(cos rot_y, 0, -sin rot_y)`, rotated by `R`.
//!   The AV pose is the reference camera's origin and its optical axis.
//! * **Time.** `t` indexes frames, `dt = 0.1 s * stride` (KITTI records at
//!   10 Hz and the files have no timestamps); [`KittiOptions::stride`] keeps
//!   every `stride`-th frame.
//! * **Scenes are per-track windows.** The format has one number of steps
//!   for every scene, while KITTI sequences (78–1059 frames) and tracks
//!   (1–600+ frames) vary. So each labelled Car track is cut into windows of
//!   exactly [`KittiOptions::steps`] steps lying inside one contiguous run of
//!   labelled frames. A window starts at a frame where the track has an
//!   associated detection (so the prior can come from a detection at `t = 0`);
//!   the next window of the same track starts at the first detected frame at
//!   or after the end of the previous one. Windows of one sequence that start
//!   at the same frame form one scene, with the AV poses of those frames:
//!   **scene id = 10000 * sequence + first frame**, **object id = KITTI
//!   track id**. Track parts shorter than a window are dropped (counted in
//!   the report). The §4 format is unchanged.
//! * **Association.** In every frame, PointRCNN Car detections (score at
//!   least [`KittiOptions::min_score`]) are matched one-to-one to the
//!   labelled objects of all classes but `DontCare`, greedily by increasing
//!   bird's-eye centre distance, within [`KittiOptions::gate`] metres
//!   (camera frame, so ego-pose error does not enter). Detections matched to
//!   a Car track become that object's `boxes.csv` rows; detections matched
//!   to other classes (mostly vans) or to nothing are counted, not exported.
//! * **Objects.** Length and width come from the labels (constant within a
//!   track); the prior of `x_0` comes from the window's first detection only:
//!   its position and heading, speed [`KittiOptions::prior_v`] and curvature
//!   0, with standard deviations from the options. Labels never feed the prior
//!   or the observations.
//! * **Ground truth** (`states.csv`, and `actions.csv` if asked): label
//!   position and heading in the world frame; speed and curvature by central
//!   finite differences over ±[`KittiOptions::diff_half_width`] frames of the
//!   labelled run (one-sided at its ends): speed is the displacement along
//!   the labelled heading per second (negative when reversing), curvature the
//!   heading rate over the speed (0 below
//!   [`KittiOptions::min_speed_for_curvature`], clamped to
//!   ±[`KittiOptions::max_curvature`]). Actions are the differences of
//!   consecutive window states: `accel = (v_t - v_{t-1}) / dt`,
//!   `pinch = (kappa_t - kappa_{t-1}) / dt` — noisy, derived quantities.
//!
//! This file holds the options, the reports and the import of a sequence;
//! `files.rs` reads the text files, `frames.rs` the ego poses and calibration,
//! `tracks.rs` associates and differentiates the labelled tracks.

mod files;
mod frames;
mod tracks;

use files::{read_detections, read_labels, read_seq_file, Det, Label};
use frames::{cam2_offset, read_poses, CamToWorld};
use tracks::{associate, speed_curvature};

use super::error::{DataError, Place, Problem};
use super::{Action, BoxDetection, Dataset, DatasetBuilder, Meta, Object, ObservationKind, Pose, Prior, State};
use crate::data::{heading_reversals, HeadingReversals};
use std::collections::{BTreeMap, HashSet};
use std::fmt;
use std::fs;
use std::path::Path;

/// AB3DMOT's validation sequences; every other sequence is training data.
pub const KITTI_VAL_SEQUENCES: [u32; 8] = [1, 6, 10, 12, 13, 14, 16, 19];

/// Time between KITTI frames (s): the sensors record at 10 Hz.
pub const KITTI_FRAME_DT: f64 = 0.1;

/// Scene ids are `KITTI_SCENE_ID_BASE * sequence + first frame` (KITTI sequences
/// have fewer frames than this).
pub const KITTI_SCENE_ID_BASE: i64 = 10_000;

/// Largest `steps * stride` accepted (KITTI sequences have at most ~1100 frames).
const MAX_WINDOW_FRAMES: usize = 1_000_000;

/// Options of [`import_kitti`]. `Default` gives the documented defaults.
#[derive(Clone, Debug, PartialEq)]
pub struct KittiOptions {
    /// Steps per scene window (`meta.steps`, `T + 1`). Default 20 (2 s).
    pub steps: usize,
    /// Keep every `stride`-th frame (`dt = 0.1 s * stride`). Default 1.
    pub stride: usize,
    /// Windows start only on frames that are multiples of `align`, so more
    /// tracks share a scene (fewer, larger scenes) at the cost of some
    /// dropped frames. Default 1 (a window may start on any frame).
    pub align: usize,
    /// Association gate: largest bird's-eye distance (m) between a detection's
    /// and a label's centre. Default 2.0.
    pub gate: f64,
    /// Detections with a lower score are discarded before association.
    /// Default `-inf` (keep all; the score is exported with each box).
    pub min_score: f64,
    /// Half-width (frames) of the central differences for speed and
    /// curvature. Default 2 (a 0.4 s baseline, which keeps label jitter of
    /// about 0.1 m to about 0.4 m/s of speed noise).
    pub diff_half_width: usize,
    /// Below this speed (m/s) the curvature is set to 0. Default 1.0.
    pub min_speed_for_curvature: f64,
    /// Curvatures are clamped to `±max_curvature` (1/m). Default 0.2 (a
    /// turning radius of 5 m, about a car's minimum).
    pub max_curvature: f64,
    /// Prior sd of the position (m). Default 1.0.
    pub prior_sd_position: f64,
    /// Prior sd of the heading (rad). Default 0.5.
    pub prior_sd_yaw: f64,
    /// Prior mean of the speed (m/s); one detection says nothing about it.
    /// Default 0.0.
    pub prior_v: f64,
    /// Prior sd of the speed (m/s). Default 10.0 (covers parked to urban speeds).
    pub prior_sd_v: f64,
    /// Prior sd of the curvature (1/m), around a mean of 0. Default 0.05.
    pub prior_sd_kappa: f64,
    /// Also write ground-truth actions (finite differences). Default true.
    pub actions: bool,
    /// Restrict the import to these sequences (None: every sequence present).
    pub sequences: Option<Vec<u32>>,
    /// The sequences of the `val` split (None: [`KITTI_VAL_SEQUENCES`], AB3DMOT's);
    /// every other imported sequence goes to `train`. With
    /// [`KittiOptions::sequences`] this cuts any held-out set, e.g. half of the
    /// training sequences against the other half.
    pub val_sequences: Option<Vec<u32>>,
}

impl Default for KittiOptions {
    fn default() -> Self {
        KittiOptions {
            steps: 20,
            stride: 1,
            align: 1,
            gate: 2.0,
            min_score: f64::NEG_INFINITY,
            diff_half_width: 2,
            min_speed_for_curvature: 1.0,
            max_curvature: 0.2,
            prior_sd_position: 1.0,
            prior_sd_yaw: 0.5,
            prior_v: 0.0,
            prior_sd_v: 10.0,
            prior_sd_kappa: 0.05,
            actions: true,
            sequences: None,
            val_sequences: None,
        }
    }
}

/// Counts for one split of a KITTI import.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct KittiSplitReport {
    /// Sequences in the split.
    pub sequences: Vec<u32>,
    /// Frames in those sequences.
    pub frames: usize,
    /// Labelled Car tracks.
    pub car_tracks: usize,
    /// Labelled Car rows (track-frames).
    pub car_label_steps: usize,
    /// Labelled Car rows with an associated detection.
    pub car_label_steps_detected: usize,
    /// PointRCNN Car detections considered (score at least `min_score`).
    pub detections: usize,
    /// Detections associated to a labelled Car.
    pub associated_car: usize,
    /// Detections associated to a labelled object of another class (Van, ...).
    pub associated_other: usize,
    /// Detections associated to no label.
    pub unassociated: usize,
    /// Car tracks that gave at least one window (object).
    pub tracks_used: usize,
    /// Car tracks that gave no window (too short, or no detection early enough).
    pub tracks_dropped: usize,
    /// Scenes written.
    pub scenes: usize,
    /// Objects written (track windows).
    pub objects: usize,
    /// Object-steps written (`objects * steps`).
    pub steps: usize,
    /// Box detections written.
    pub boxes: usize,
    /// How the written detections reversed against their labels fall over
    /// objects and steps ([`crate::data::heading_reversals`]; `None` until the
    /// split's dataset is built).
    pub reversals: Option<HeadingReversals>,
}

impl KittiSplitReport {
    /// Fraction of detections associated to a labelled object of any class.
    pub fn association_rate(&self) -> f64 {
        ratio(self.associated_car + self.associated_other, self.detections)
    }

    /// Fraction of labelled Car track-frames with a detection (recall).
    pub fn label_detection_rate(&self) -> f64 {
        ratio(self.car_label_steps_detected, self.car_label_steps)
    }

    /// Fraction of written object-steps with a detection.
    pub fn observed_rate(&self) -> f64 {
        ratio(self.boxes, self.steps)
    }
}

fn ratio(a: usize, b: usize) -> f64 {
    if b == 0 {
        0.0
    } else {
        a as f64 / b as f64
    }
}

/// The report of [`import_kitti`]: the options used and counts per split.
#[derive(Clone, Debug, PartialEq)]
pub struct KittiReport {
    /// The options of the import.
    pub options: KittiOptions,
    /// Counts for the training split.
    pub train: KittiSplitReport,
    /// Counts for the validation split.
    pub val: KittiSplitReport,
}

impl fmt::Display for KittiReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "KITTI import: {} steps per scene, dt {} s, gate {} m",
            self.options.steps,
            KITTI_FRAME_DT * self.options.stride as f64,
            self.options.gate
        )?;
        writeln!(f, "| | train | val |")?;
        writeln!(f, "|---|---|---|")?;
        type Cell = fn(&KittiSplitReport) -> String;
        let rows: [(&str, Cell); 20] = [
            ("sequences", |r| r.sequences.len().to_string()),
            ("frames", |r| r.frames.to_string()),
            ("Car tracks", |r| r.car_tracks.to_string()),
            ("Car label steps", |r| r.car_label_steps.to_string()),
            ("  with a detection", |r| {
                format!("{} ({:.1}%)", r.car_label_steps_detected, 100.0 * r.label_detection_rate())
            }),
            ("detections", |r| r.detections.to_string()),
            ("  associated to Car", |r| r.associated_car.to_string()),
            ("  associated to other classes", |r| r.associated_other.to_string()),
            ("  unassociated", |r| r.unassociated.to_string()),
            ("  association rate", |r| format!("{:.1}%", 100.0 * r.association_rate())),
            ("tracks used", |r| r.tracks_used.to_string()),
            ("tracks dropped", |r| r.tracks_dropped.to_string()),
            ("scenes", |r| r.scenes.to_string()),
            ("objects (track windows)", |r| r.objects.to_string()),
            ("object-steps", |r| r.steps.to_string()),
            ("boxes written", |r| format!("{} ({:.1}%)", r.boxes, 100.0 * r.observed_rate())),
            ("  heading reversed against the label", |r| {
                r.reversals.map_or("-".into(), |v| format!("{} ({:.1}%)", v.reversed, 100.0 * v.rate()))
            }),
            ("  objects with one: seen / if independent", |r| {
                r.reversals.map_or("-".into(), |v| {
                    format!("{} / {:.0} of {}", v.objects_with_any, v.objects_with_any_if_independent, v.objects)
                })
            }),
            ("  their dispersion over objects (1 if independent)", |r| {
                r.reversals.and_then(|v| v.dispersion).map_or("-".into(), |x| format!("{x:.2}"))
            }),
            ("  P(reversed \\| reversed the step before)", |r| {
                r.reversals.and_then(|v| v.persistence).map_or("-".into(), |x| format!("{x:.2}"))
            }),
        ];
        for (name, value) in rows {
            writeln!(f, "| {name} | {} | {} |", value(&self.train), value(&self.val))?;
        }
        Ok(())
    }
}

/// The result of [`import_kitti`].
#[derive(Clone, Debug)]
pub struct KittiImport {
    /// Training split (AB3DMOT's train sequences).
    pub train: Dataset,
    /// Validation split ([`KITTI_VAL_SEQUENCES`]).
    pub val: Dataset,
    /// Counts and the options used.
    pub report: KittiReport,
}

/// Imports the KITTI tracking folder at `root` (with `label_02/`,
/// `det_pointrcnn/Car/`, `ego_pose_orbslam3/` and `calib/`) as two box
/// datasets; see the [module docs](self) for every convention.
///
/// ```no_run
/// use ssm::data::{import_kitti, KittiOptions};
/// let imp = import_kitti("../shared/data/kitti-tracking".as_ref(), &KittiOptions::default())?;
/// println!("{}", imp.report);
/// imp.train.write("data/kitti-train")?;
/// # Ok::<(), ssm::data::DataError>(())
/// ```
pub fn import_kitti(root: &Path, options: &KittiOptions) -> Result<KittiImport, DataError> {
    check_options(options)?;
    let sequences = match &options.sequences {
        Some(s) => {
            let mut s = s.clone();
            s.sort_unstable();
            s.dedup();
            s
        }
        None => list_sequences(&root.join("label_02"))?,
    };
    let meta = Meta { prior_from_detection: true, ..Meta::new(KITTI_FRAME_DT * options.stride as f64, options.steps) };
    let mut train = Split::new(meta, options.actions);
    let mut val = Split::new(meta, options.actions);
    for seq in sequences {
        let held_out = options.val_sequences.as_deref().unwrap_or(&KITTI_VAL_SEQUENCES).contains(&seq);
        let split = if held_out { &mut val } else { &mut train };
        import_sequence(root, seq, options, split)?;
    }
    let (train_data, val_data) = (train.builder.build()?, val.builder.build()?);
    let (mut train_report, mut val_report) = (train.report, val.report);
    train_report.reversals = heading_reversals(&train_data);
    val_report.reversals = heading_reversals(&val_data);
    let report = KittiReport { options: options.clone(), train: train_report, val: val_report };
    Ok(KittiImport { train: train_data, val: val_data, report })
}

fn option_error(name: &str, message: &str) -> DataError {
    DataError::invalid("KittiOptions", Place::Record(0), name, Problem::Other(message.to_string()))
}

fn check_options(o: &KittiOptions) -> Result<(), DataError> {
    if o.steps < 1 {
        return Err(option_error("steps", "must be at least 1"));
    }
    if o.stride < 1 {
        return Err(option_error("stride", "must be at least 1"));
    }
    if o.steps.checked_mul(o.stride).is_none_or(|frames| frames > MAX_WINDOW_FRAMES) {
        return Err(option_error("steps", "steps * stride is larger than any KITTI sequence"));
    }
    if o.align < 1 {
        return Err(option_error("align", "must be at least 1"));
    }
    let positive = [
        ("gate", o.gate),
        ("prior_sd_position", o.prior_sd_position),
        ("prior_sd_yaw", o.prior_sd_yaw),
        ("prior_sd_v", o.prior_sd_v),
        ("prior_sd_kappa", o.prior_sd_kappa),
        ("max_curvature", o.max_curvature),
    ];
    for (name, v) in positive {
        if !(v.is_finite() && v > 0.0) {
            return Err(option_error(name, "must be positive and finite"));
        }
    }
    if !o.prior_v.is_finite() {
        return Err(option_error("prior_v", "must be finite"));
    }
    if o.min_score.is_nan() {
        return Err(option_error("min_score", "must not be NaN"));
    }
    if !(o.min_speed_for_curvature >= 0.0 && o.min_speed_for_curvature.is_finite()) {
        return Err(option_error("min_speed_for_curvature", "must be non-negative and finite"));
    }
    Ok(())
}

/// The sequences with a label file, sorted.
fn list_sequences(dir: &Path) -> Result<Vec<u32>, DataError> {
    let entries = fs::read_dir(dir).map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            DataError::MissingFile { path: dir.to_path_buf() }
        } else {
            DataError::io(dir, e)
        }
    })?;
    let mut seqs = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| DataError::io(dir, e))?;
        let name = entry.file_name();
        let name = name.to_string_lossy();
        if let Some(stem) = name.strip_suffix(".txt") {
            if let Ok(s) = stem.parse::<u32>() {
                seqs.push(s);
            }
        }
    }
    seqs.sort_unstable();
    Ok(seqs)
}

/// One split being built.
struct Split {
    builder: DatasetBuilder,
    report: KittiSplitReport,
    /// The scenes added so far.
    scenes: HashSet<i64>,
}

impl Split {
    fn new(meta: Meta, actions: bool) -> Self {
        let mut builder = Dataset::builder(meta, ObservationKind::Boxes);
        builder.with_states();
        if actions {
            builder.with_actions();
        }
        Split { builder, report: KittiSplitReport::default(), scenes: HashSet::new() }
    }
}

/// A Car track: its id and its size (from its first label).
struct Track {
    id: i64,
    length: f64,
    width: f64,
}

/// One KITTI sequence read and associated: what its windows are cut from.
struct Sequence {
    seq: u32,
    poses: Vec<CamToWorld>,
    /// The reference camera's origin in the cam2 frame.
    offset: [f64; 3],
    labels: Vec<Label>,
    dets: Vec<Det>,
    /// The detection associated with each label, if any.
    label_det: Vec<Option<usize>>,
}

fn import_sequence(root: &Path, seq: u32, o: &KittiOptions, split: &mut Split) -> Result<(), DataError> {
    let sequence = Sequence::read(root, seq, o, &mut split.report)?;
    for (track, idx) in sequence.car_tracks()? {
        let r = &mut split.report;
        r.car_tracks += 1;
        r.car_label_steps += idx.len();
        r.car_label_steps_detected += idx.iter().filter(|&&i| sequence.label_det[i].is_some()).count();
        let first = &sequence.labels[idx[0]];
        let track = Track { id: track, length: first.length, width: first.width };
        let mut windows = 0;
        // The runs of consecutive labelled frames.
        for run in idx.chunk_by(|&a, &b| sequence.labels[b].frame == sequence.labels[a].frame + 1) {
            windows += sequence.cut_windows(&track, run, o, split);
        }
        if windows > 0 {
            split.report.tracks_used += 1;
        } else {
            split.report.tracks_dropped += 1;
        }
    }
    Ok(())
}

impl Sequence {
    /// Reads sequence `seq`'s files, associates its detections with its labels
    /// and counts both in `r`.
    fn read(root: &Path, seq: u32, o: &KittiOptions, r: &mut KittiSplitReport) -> Result<Self, DataError> {
        let pose_file = read_seq_file(root, "ego_pose_orbslam3", seq)?;
        let poses = read_poses(&pose_file)?;
        let frames = poses.len();
        let offset = cam2_offset(&read_seq_file(root, "calib", seq)?)?;
        let labels = read_labels(&read_seq_file(root, "label_02", seq)?, frames)?;
        let dets = read_detections(&read_seq_file(root, "det_pointrcnn/Car", seq)?, frames, o.min_score)?;

        let (label_det, det_used) = associate(&labels, &dets, o.gate);
        r.sequences.push(seq);
        r.frames += frames;
        r.detections += dets.len();
        for (i, l) in labels.iter().enumerate() {
            if let Some(j) = label_det[i] {
                debug_assert!(det_used[j]);
                if l.car {
                    r.associated_car += 1;
                } else {
                    r.associated_other += 1;
                }
            }
        }
        r.unassociated += det_used.iter().filter(|u| !**u).count();
        Ok(Sequence { seq, poses, offset, labels, dets, label_det })
    }

    /// The Car tracks by id, each its label indices sorted by frame; fails on a
    /// track labelled twice in one frame.
    fn car_tracks(&self) -> Result<BTreeMap<i64, Vec<usize>>, DataError> {
        let labels = &self.labels;
        let mut tracks: BTreeMap<i64, Vec<usize>> = BTreeMap::new();
        for (i, l) in labels.iter().enumerate() {
            if l.car {
                tracks.entry(l.track).or_default().push(i);
            }
        }
        for (&track, idx) in &mut tracks {
            idx.sort_by_key(|&i| labels[i].frame);
            if let Some(w) = idx.windows(2).find(|w| labels[w[0]].frame == labels[w[1]].frame) {
                let (a, b) = (&labels[w[0]], &labels[w[1]]);
                let (first, second) = if a.line < b.line { (a, b) } else { (b, a) };
                return Err(DataError::invalid(
                    format!("label_02/{:04}.txt", self.seq),
                    Place::Line(second.line),
                    "track_id",
                    Problem::Duplicate {
                        key: format!("frame {}, track {track}", second.frame),
                        first: Place::Line(first.line),
                    },
                ));
            }
        }
        Ok(tracks)
    }

    /// Cuts one run of `track` into windows of `o.steps` steps, each starting at
    /// a detected frame, into `split`'s dataset; returns how many.
    fn cut_windows(&self, track: &Track, run: &[usize], o: &KittiOptions, split: &mut Split) -> usize {
        let (labels, poses, offset) = (&self.labels, &self.poses, self.offset);
        let span = (o.steps - 1) * o.stride;
        let world: Vec<Pose> = run
            .iter()
            .map(|&i| {
                let l = &labels[i];
                poses[l.frame].bev(l.p, offset, l.rot_y)
            })
            .collect();
        let vk = speed_curvature(&world, o);
        let run_first = labels[run[0]].frame;
        let run_last = labels[run[run.len() - 1]].frame;
        let mut windows = 0;
        let mut k = 0; // index into run of the earliest allowed start
        while run_first + k + span <= run_last {
            // First detected frame at or after k that leaves room for a window.
            let Some(k0) = (k..=(run_last - run_first - span))
                .find(|&k0| self.label_det[run[k0]].is_some() && (run_first + k0) % o.align == 0)
            else {
                break;
            };
            let track_states: Vec<State> = (0..o.steps)
                .map(|s| {
                    let kk = k0 + s * o.stride;
                    let p = world[kk];
                    State { x: p.x, y: p.y, yaw: p.yaw, v: vk[kk].0, kappa: vk[kk].1 }
                })
                .collect();
            self.add_window(track, run, k0, &track_states, o, split);
            windows += 1;
            k = k0 + span + o.stride;
        }
        windows
    }

    /// Adds the window of `track` starting at index `k0` of `run` (a detected
    /// frame) with ground-truth `states`: its scene (if new), the object with
    /// its prior from the first detection, the states, the actions (if asked)
    /// and the detections.
    fn add_window(
        &self,
        track: &Track,
        run: &[usize],
        k0: usize,
        states: &[State],
        o: &KittiOptions,
        split: &mut Split,
    ) {
        let (poses, offset, dets) = (&self.poses, self.offset, &self.dets);
        let r = &mut split.report;
        let run_first = self.labels[run[0]].frame;
        let f0 = run_first + k0;
        let scene = KITTI_SCENE_ID_BASE * i64::from(self.seq) + f0 as i64;
        if split.scenes.insert(scene) {
            let av: Vec<Pose> = (0..o.steps).map(|s| poses[f0 + s * o.stride].camera(offset)).collect();
            split.builder.scene(scene, &av);
            r.scenes += 1;
        }
        let first_det = &dets[self.label_det[run[k0]].expect("start is detected")];
        let d0 = poses[f0].bev(first_det.p, offset, first_det.rot_y);
        split.builder.object(Object {
            scene,
            id: track.id,
            length: track.length,
            width: track.width,
            prior: Prior {
                mean: State { x: d0.x, y: d0.y, yaw: d0.yaw, v: o.prior_v, kappa: 0.0 },
                sd: State {
                    x: o.prior_sd_position,
                    y: o.prior_sd_position,
                    yaw: o.prior_sd_yaw,
                    v: o.prior_sd_v,
                    kappa: o.prior_sd_kappa,
                },
            },
        });
        let dt = KITTI_FRAME_DT * o.stride as f64;
        for (s, &state) in states.iter().enumerate() {
            split.builder.state(scene, track.id, s, state);
            if let (true, Some(prev)) = (o.actions, s.checked_sub(1).map(|p| states[p])) {
                let action = Action { accel: (state.v - prev.v) / dt, pinch: (state.kappa - prev.kappa) / dt };
                split.builder.action(scene, track.id, s, action);
            }
            let kk = k0 + s * o.stride;
            if let Some(j) = self.label_det[run[kk]] {
                let d = &dets[j];
                let b = poses[run_first + kk].bev(d.p, offset, d.rot_y);
                let detection =
                    BoxDetection { x: b.x, y: b.y, yaw: b.yaw, length: d.length, width: d.width, score: d.score };
                split.builder.detection(scene, track.id, s, detection);
                r.boxes += 1;
            }
        }
        r.objects += 1;
        r.steps += o.steps;
    }
}

#[cfg(test)]
mod tests {
    use super::tracks::unwrap_angles;
    use super::*;

    #[test]
    fn heading_conventions() {
        // Identity pose: rot_y = -pi/2 faces forward (world +x), rot_y = 0 faces
        // the camera's right (world -y).
        let id = CamToWorld { r: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], t: [0.0; 3] };
        let p = id.bev([2.0, 1.5, 10.0], [0.0; 3], -std::f64::consts::FRAC_PI_2);
        assert!((p.x - 10.0).abs() < 1e-12 && (p.y + 2.0).abs() < 1e-12);
        assert!(p.yaw.abs() < 1e-12);
        let p = id.bev([0.0; 3], [0.0; 3], 0.0);
        assert!((p.yaw + std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        // A camera turned 90 degrees left (about -y, the up axis): its forward
        // axis is the world's left, so the AV yaw is +pi/2.
        let (c, s) = (0.0f64, 1.0f64);
        let left = CamToWorld {
            // Rotation about y by -90 degrees: z_cam -> -x_world.
            r: [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]],
            t: [0.0; 3],
        };
        let av = left.camera([0.0; 3]);
        assert!((av.yaw - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        // And an object facing the camera's forward faces the same way.
        let p = left.bev([0.0; 3], [0.0; 3], -std::f64::consts::FRAC_PI_2);
        assert!((p.yaw - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn unwrap_and_differences() {
        let mut a = [3.1, -3.1, -3.0];
        unwrap_angles(&mut a);
        assert!((a[1] - (2.0 * std::f64::consts::PI - 3.1)).abs() < 1e-12);
        // Straight line at 10 m/s along yaw 0.3.
        let poses: Vec<Pose> = (0..10)
            .map(|i| {
                let s = i as f64;
                Pose { x: s * 0.3f64.cos(), y: s * 0.3f64.sin(), yaw: 0.3 }
            })
            .collect();
        let vk = speed_curvature(&poses, &KittiOptions::default());
        for (v, k) in vk {
            assert!((v - 10.0).abs() < 1e-9 && k.abs() < 1e-12);
        }
    }
}
