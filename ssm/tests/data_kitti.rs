//! The KITTI importer on the real data in `/work/shared/data/kitti-tracking`
//! (the tests are skipped, with a message, where that folder is absent).

use ssm::data::{import_kitti, Dataset, KittiImport, KittiOptions, KITTI_SCENE_ID_BASE, KITTI_VAL_SEQUENCES};
use std::f64::consts::PI;
use std::path::PathBuf;
use std::sync::OnceLock;

fn root() -> Option<PathBuf> {
    let candidates = [
        std::env::var("KITTI_TRACKING_DIR").ok().map(PathBuf::from),
        Some(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/kitti-tracking")),
        Some(PathBuf::from("/work/shared/data/kitti-tracking")),
    ];
    candidates.into_iter().flatten().find(|p| p.join("label_02").is_dir())
}

/// The default import, shared by the tests of this file.
fn import() -> Option<&'static KittiImport> {
    static IMPORT: OnceLock<Option<KittiImport>> = OnceLock::new();
    IMPORT
        .get_or_init(|| {
            let root = root()?;
            Some(import_kitti(&root, &KittiOptions::default()).expect("KITTI import"))
        })
        .as_ref()
}

macro_rules! kitti_or_skip {
    () => {
        match import() {
            Some(i) => i,
            None => {
                eprintln!("KITTI data not found; test skipped");
                return;
            }
        }
    };
}

fn wrap(a: f64) -> f64 {
    (a + PI).rem_euclid(2.0 * PI) - PI
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[test]
fn report_counts_are_plausible() {
    let imp = kitti_or_skip!();
    println!("{}", imp.report);
    for (name, r, ds) in [("train", &imp.report.train, &imp.train), ("val", &imp.report.val, &imp.val)] {
        assert!(r.tracks_used > 0 && r.objects > 0, "{name}: no objects");
        assert_eq!(r.objects, ds.objects().len(), "{name}");
        assert_eq!(r.scenes, ds.scenes().len(), "{name}");
        assert_eq!(r.boxes, ds.boxes().unwrap().count(), "{name}");
        assert_eq!(r.steps, ds.objects().len() * ds.steps(), "{name}");
        assert_eq!(r.detections, r.associated_car + r.associated_other + r.unassociated, "{name}");
        assert_eq!(r.car_tracks, r.tracks_used + r.tracks_dropped, "{name}");
        // PointRCNN finds most labelled cars (about 89% of label rows fall
        // within 2 m of a detection; far and occluded cars are missed).
        assert!(r.label_detection_rate() > 0.8, "{name}: recall {}", r.label_detection_rate());
        // Windows start on a detection and keep to long tracks, so most of
        // their steps are observed.
        assert!(r.observed_rate() > 0.85, "{name}: observed {}", r.observed_rate());
        // Without a score threshold half the raw detections are low-score
        // clutter, but nearly all associated ones are cars or vans.
        assert!(r.association_rate() > 0.4, "{name}");
        // The reversal counts are those of the written dataset, and KITTI's
        // detector reverses cars in bursts: fewer cars with a reversal than
        // independent reversals would give, and over-dispersed counts.
        let reversals = r.reversals.expect("labelled box detections");
        assert_eq!(Some(reversals), ssm::data::heading_reversals(ds), "{name}");
        assert_eq!(reversals.detections, r.boxes, "{name}: every written box has a label");
        assert!((reversals.objects_with_any as f64) < 0.7 * reversals.objects_with_any_if_independent, "{name}");
        assert!(reversals.dispersion.unwrap() > 2.0, "{name}: {reversals:?}");
    }
    let report = imp.report.to_string();
    assert!(report.contains("heading reversed against the label") && report.contains("reversed the step before"));
    assert_eq!(imp.train.meta().dt, 0.1);
    // Each prior is read from the object's first detection, and the data say so.
    assert!(imp.train.meta().prior_from_detection && imp.val.meta().prior_from_detection);
    assert_eq!(imp.report.val.sequences, KITTI_VAL_SEQUENCES.to_vec());
    assert!(imp.report.train.sequences.iter().all(|s| !KITTI_VAL_SEQUENCES.contains(s)));
}

#[test]
fn scenes_come_from_their_split() {
    let imp = kitti_or_skip!();
    for s in imp.val.scenes() {
        let seq = (s.id / KITTI_SCENE_ID_BASE) as u32;
        assert!(KITTI_VAL_SEQUENCES.contains(&seq));
        assert!(!s.objects.is_empty());
    }
    for s in imp.train.scenes() {
        let seq = (s.id / KITTI_SCENE_ID_BASE) as u32;
        assert!(!KITTI_VAL_SEQUENCES.contains(&seq));
    }
}

/// Checks on the ground truth, detections and priors of one split.
fn check_world_frame(name: &str, ds: &Dataset) {
    let states = ds.states().expect("states");
    let boxes = ds.boxes().expect("boxes");
    assert!(states.is_complete(), "{name}: every step has ground truth");
    let dt = ds.dt();
    let mut prior_err = Vec::new();
    let mut det_err = Vec::new();
    let mut yaw_err = Vec::new();
    let mut speeds = Vec::new();
    for (i, obj) in ds.objects().iter().enumerate() {
        let x = states.object(i);
        let s0 = x[0].unwrap();
        // The prior is the first detection, which is at step 0 and near the label.
        let b0 = boxes.get(i, 0).expect("windows start on a detection");
        assert_eq!((obj.prior.mean.x, obj.prior.mean.y), (b0.x, b0.y));
        prior_err.push((obj.prior.mean.x - s0.x).hypot(obj.prior.mean.y - s0.y));
        // Within the 2 m gate (applied in the camera frame; ego pitch and the
        // height difference can add a little in the world bird's-eye view).
        assert!(*prior_err.last().unwrap() < 2.5, "{name}: gate");
        for t in 0..ds.steps() {
            let s = x[t].unwrap();
            speeds.push(s.v.abs());
            if let Some(b) = boxes.get(i, t) {
                det_err.push((b.x - s.x).hypot(b.y - s.y));
                yaw_err.push(wrap(b.yaw - s.yaw).abs());
            }
            if t > 0 {
                let p = x[t - 1].unwrap();
                let step_speed = (s.x - p.x).hypot(s.y - p.y) / dt;
                assert!(step_speed < 40.0, "{name}: object {i} t {t}: {step_speed} m/s");
            }
        }
        assert!(obj.length > 2.0 && obj.length < 7.0, "{name}: car length {}", obj.length);
        assert!(obj.width > 1.0 && obj.width < 3.0, "{name}: car width {}", obj.width);
    }
    // Parked cars stay put in the world frame while the AV drives past them
    // (a wrong ego transform would give them the AV's motion), and moving
    // cars move along their labelled heading (a mirrored yaw convention
    // would not).
    let (mut still, mut passing) = (0usize, 0usize);
    let (mut forward, mut moving) = (0usize, 0usize);
    for (si, s) in ds.scenes().iter().enumerate() {
        let (a, b) = (s.av[0], s.av[s.av.len() - 1]);
        let av_moves = (b.x - a.x).hypot(b.y - a.y) > 5.0;
        for i in s.objects.clone() {
            assert_eq!(ds.object_scene(i), si);
            let x = states.object(i);
            let (p, q) = (x[0].unwrap(), x[ds.steps() - 1].unwrap());
            let moved = (q.x - p.x).hypot(q.y - p.y);
            if av_moves {
                passing += 1;
                still += usize::from(moved < 1.0);
            }
            if moved / (dt * (ds.steps() - 1) as f64) > 3.0 {
                moving += 1;
                let heading = (q.y - p.y).atan2(q.x - p.x);
                forward += usize::from(wrap(heading - p.yaw).abs() < 0.5);
            }
        }
    }
    println!("{name}: {still} of {passing} objects still while the AV moves; {forward} of {moving} moving objects drive forward");
    assert!(still as f64 > 0.2 * passing as f64, "{name}");
    assert!(forward as f64 > 0.9 * moving as f64, "{name}");
    for s in ds.scenes() {
        for w in s.av.windows(2) {
            let v = (w[1].x - w[0].x).hypot(w[1].y - w[0].y) / dt;
            assert!(v < 40.0, "{name}: AV speed {v} in scene {}", s.id);
        }
    }
    let max_speed = speeds.iter().cloned().fold(0.0, f64::max);
    println!(
        "{name}: median |prior - label| {:.3} m, median |det - label| {:.3} m, median yaw err {:.4} rad, \
         flipped {:.2}%, median speed {:.2} m/s, max {:.1} m/s",
        median(prior_err.clone()),
        median(det_err.clone()),
        median(yaw_err.clone()),
        100.0 * yaw_err.iter().filter(|e| **e > PI / 2.0).count() as f64 / yaw_err.len() as f64,
        median(speeds.clone()),
        max_speed
    );
    assert!(max_speed < 40.0, "{name}: label speed {max_speed} m/s");
    assert!(median(prior_err) < 0.5, "{name}");
    assert!(median(det_err) < 0.5, "{name}");
    // Detections and labels agree on the heading in the world frame (a few
    // percent of detections are flipped by pi, which the median ignores).
    assert!(median(yaw_err) < 0.1, "{name}");
}

#[test]
fn world_frame_is_consistent() {
    let imp = kitti_or_skip!();
    check_world_frame("train", &imp.train);
    check_world_frame("val", &imp.val);
}

#[test]
fn import_round_trips_through_files() {
    let imp = kitti_or_skip!();
    let dir = tempfile::tempdir().unwrap();
    imp.val.write(dir.path()).unwrap();
    let back = Dataset::read(dir.path()).unwrap();
    assert_eq!(back, imp.val);
    assert!(dir.path().join("actions.csv").exists());
}

#[test]
fn options_change_the_windows() {
    let Some(root) = root() else {
        eprintln!("KITTI data not found; test skipped");
        return;
    };
    let opts = KittiOptions {
        steps: 10,
        stride: 3,
        min_score: 2.0,
        actions: false,
        sequences: Some(vec![1, 2]),
        ..KittiOptions::default()
    };
    let imp = import_kitti(&root, &opts).unwrap();
    assert!((imp.train.dt() - 0.3).abs() < 1e-12);
    assert_eq!(imp.train.steps(), 10);
    assert!(imp.train.actions().is_none());
    assert_eq!(imp.report.train.sequences, vec![2]);
    assert_eq!(imp.report.val.sequences, vec![1]);
    // Any held-out set: two training sequences, one held out against the other.
    let swapped = KittiOptions { sequences: Some(vec![0, 2]), val_sequences: Some(vec![2]), ..opts.clone() };
    let imp2 = import_kitti(&root, &swapped).unwrap();
    assert_eq!(imp2.report.train.sequences, vec![0]);
    assert_eq!(imp2.report.val.sequences, vec![2]);
    let seq =
        |d: &Dataset| d.scenes().iter().map(|s| s.id / KITTI_SCENE_ID_BASE).collect::<std::collections::BTreeSet<_>>();
    assert_eq!(seq(&imp2.val), [2].into());
    assert_eq!(seq(&imp2.train), [0].into());
    assert_eq!(imp2.val.objects().len(), imp.train.objects().len(), "sequence 2 alone, as before");
    // With a score threshold most surviving detections belong to labels.
    assert!(imp.report.val.association_rate() > 0.75);
    let bad = KittiOptions { steps: 0, ..KittiOptions::default() };
    let e = import_kitti(&root, &bad).unwrap_err();
    assert!(e.to_string().contains("steps"), "{e}");
    let missing = KittiOptions { sequences: Some(vec![8]), ..KittiOptions::default() };
    let e = import_kitti(&root, &missing).unwrap_err();
    assert!(e.to_string().contains("0008.txt"), "{e}");
}

#[test]
fn bad_kitti_files_are_reported() {
    let Some(root) = root() else {
        eprintln!("KITTI data not found; test skipped");
        return;
    };
    // A copy of sequence 0012 (78 frames) to spoil.
    let copy = |dir: &std::path::Path| {
        for folder in ["label_02", "calib", "ego_pose_orbslam3", "det_pointrcnn/Car"] {
            std::fs::create_dir_all(dir.join(folder)).unwrap();
            std::fs::copy(root.join(folder).join("0012.txt"), dir.join(folder).join("0012.txt")).unwrap();
        }
    };
    let opts = KittiOptions { sequences: Some(vec![12]), ..KittiOptions::default() };
    let spoil = |file: &str, line: usize, f: &dyn Fn(&str) -> String| -> String {
        let dir = tempfile::tempdir().unwrap();
        copy(dir.path());
        let ok = import_kitti(dir.path(), &opts).unwrap();
        assert!(!ok.val.objects().is_empty());
        let path = dir.path().join(file);
        let text = std::fs::read_to_string(&path).unwrap();
        let mut lines: Vec<String> = text.lines().map(String::from).collect();
        lines[line - 1] = f(&lines[line - 1]);
        std::fs::write(&path, lines.join("\n")).unwrap();
        import_kitti(dir.path(), &opts).unwrap_err().to_string()
    };
    let replace_field = |i: usize, v: &'static str, sep: char| {
        move |l: &str| {
            let mut f: Vec<String> = l.split(sep).map(String::from).collect();
            f[i] = v.to_string();
            f.join(&sep.to_string())
        }
    };
    let msg = spoil("label_02/0012.txt", 5, &replace_field(13, "abc", ' '));
    assert!(msg.starts_with("label_02/0012.txt: line 5: column `x`: malformed"), "{msg}");
    let msg = spoil("label_02/0012.txt", 7, &replace_field(0, "78", ' '));
    assert!(msg.starts_with("label_02/0012.txt: line 7: column `frame`: step 78 out of range 0..78"), "{msg}");
    let msg = spoil("label_02/0012.txt", 3, &replace_field(12, "-4.1", ' '));
    assert!(msg.starts_with("label_02/0012.txt: line 3: column `l`: must be positive"), "{msg}");
    let msg = spoil("det_pointrcnn/Car/0012.txt", 4, &replace_field(6, "nan", ','));
    assert!(msg.starts_with("det_pointrcnn/Car/0012.txt: line 4: column `score`: non-finite"), "{msg}");
    let msg = spoil("ego_pose_orbslam3/0012.txt", 10, &|l: &str| l.split(' ').take(11).collect::<Vec<_>>().join(" "));
    assert!(msg.starts_with("ego_pose_orbslam3/0012.txt: line 10: column `t2`: expected 12 fields"), "{msg}");
    // A track labelled twice in one frame.
    let dir = tempfile::tempdir().unwrap();
    copy(dir.path());
    let path = dir.path().join("label_02/0012.txt");
    let text = std::fs::read_to_string(&path).unwrap();
    let car = text.lines().find(|l| l.split(' ').nth(2) == Some("Car")).unwrap().to_string();
    std::fs::write(&path, format!("{text}{car}\n")).unwrap();
    let msg = import_kitti(dir.path(), &opts).unwrap_err().to_string();
    assert!(msg.contains("label_02/0012.txt: line") && msg.contains("column `track_id`: duplicate"), "{msg}");
}
