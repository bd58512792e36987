//! The dataset format of SPEC §4: lossless round trips, and errors that name
//! the file, line and column of every kind of bad input.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::data::{Action, BoxDetection, DataError, Dataset, Meta, Object, ObservationKind, Place, Pose, Prior, State};
use std::collections::HashSet;
use std::fs;
use std::path::Path;

// ---------------------------------------------------------------- round trips

/// Awkward but valid numbers: shortest round-trip forms must survive them.
const AWKWARD: [f64; 8] =
    [1.0 / 3.0, -0.0, 1e-300, -1.7976931348623157e308, std::f64::consts::PI, 0.1 + 0.2, 5e-324, 123_456_789.123_456_79];

fn prior(x: f64, y: f64) -> Prior {
    Prior {
        mean: State { x, y, yaw: AWKWARD[4], v: AWKWARD[5], kappa: AWKWARD[1] },
        sd: State { x: AWKWARD[0], y: 1.0, yaw: AWKWARD[6], v: 2.0, kappa: 0.01 },
    }
}

/// A small synthetic dataset: two scenes (ids out of order, one negative),
/// objects with empty and multi-point cells, partial ground truth.
fn synthetic(kind: ObservationKind) -> Dataset {
    let steps = 5;
    let mut b = Dataset::builder(Meta::new(1.0 / 3.0, steps), kind);
    let av: Vec<Pose> =
        (0..steps).map(|t| Pose { x: t as f64 * AWKWARD[0], y: AWKWARD[(t + 2) % 8], yaw: -AWKWARD[t] }).collect();
    b.scene(9, &av);
    b.scene(-4, &av[..]);
    b.scene(100, &av); // a scene without objects is allowed
    let objects = [(9, 7), (-4, 2), (9, 1), (-4, 3)];
    for (k, &(scene, id)) in objects.iter().enumerate() {
        b.object(Object {
            scene,
            id,
            length: 4.0 + AWKWARD[0] * k as f64,
            width: 1.8,
            prior: prior(AWKWARD[k], -AWKWARD[k + 1]),
        });
    }
    let mut rng = StdRng::seed_from_u64(7);
    for (k, &(scene, id)) in objects.iter().enumerate() {
        for t in 0..steps {
            match kind {
                ObservationKind::Points => {
                    // 0..3 points per cell; object 1 sees nothing at all.
                    let n = if k == 1 { 0 } else { rng.random_range(0..4) };
                    for _ in 0..n {
                        b.point(scene, id, t, [rng.random::<f64>() * 40.0 - 20.0, rng.random()]);
                    }
                }
                ObservationKind::Boxes => {
                    if rng.random_bool(0.7) {
                        b.detection(
                            scene,
                            id,
                            t,
                            BoxDetection {
                                x: rng.random(),
                                y: AWKWARD[t],
                                yaw: rng.random::<f64>() * 6.0 - 3.0,
                                length: 4.0 + rng.random::<f64>(),
                                width: 1.5,
                                score: rng.random::<f64>() * 16.0 - 1.0,
                            },
                        );
                    }
                }
            }
            // Ground truth is partial: object 3 has no state at step 2.
            if !(k == 3 && t == 2) {
                b.state(
                    scene,
                    id,
                    t,
                    State {
                        x: rng.random(),
                        y: rng.random(),
                        yaw: AWKWARD[(k + t) % 8],
                        v: rng.random::<f64>() * 10.0,
                        kappa: AWKWARD[(k * t) % 8] * 1e-3,
                    },
                );
            }
            if t >= 1 {
                b.action(scene, id, t, Action { accel: rng.random(), pinch: AWKWARD[t] });
            }
        }
    }
    b.build().expect("valid synthetic dataset")
}

/// `{:?}` prints every f64 in a form that identifies its bits (including -0.0),
/// so equal debug strings mean a bit-exact round trip.
fn assert_bit_exact(a: &Dataset, b: &Dataset) {
    assert_eq!(format!("{a:?}"), format!("{b:?}"));
    assert_eq!(a, b);
}

#[test]
fn points_round_trip_is_lossless() {
    let ds = synthetic(ObservationKind::Points);
    let dir = tempfile::tempdir().unwrap();
    ds.write(dir.path()).unwrap();
    let back = Dataset::read(dir.path()).unwrap();
    assert_bit_exact(&ds, &back);
    // Writing what was read gives identical files.
    let dir2 = tempfile::tempdir().unwrap();
    back.write(dir2.path()).unwrap();
    for f in ["meta.json", "av.csv", "objects.csv", "points.csv", "states.csv", "actions.csv"] {
        assert_eq!(fs::read(dir.path().join(f)).unwrap(), fs::read(dir2.path().join(f)).unwrap(), "{f}");
    }
    // No temporary files are left behind.
    let names: Vec<String> =
        fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert!(names.iter().all(|n| !n.starts_with('.')), "{names:?}");
}

#[test]
fn boxes_round_trip_is_lossless_and_replaces_points() {
    let dir = tempfile::tempdir().unwrap();
    synthetic(ObservationKind::Points).write(dir.path()).unwrap();
    let ds = synthetic(ObservationKind::Boxes);
    ds.write(dir.path()).unwrap();
    assert!(!dir.path().join("points.csv").exists());
    assert_bit_exact(&ds, &Dataset::read(dir.path()).unwrap());
}

#[test]
fn layout_serves_the_filter() {
    let ds = synthetic(ObservationKind::Points);
    let ids: Vec<i64> = ds.scenes().iter().map(|s| s.id).collect();
    assert_eq!(ids, vec![-4, 9, 100]);
    let keys: Vec<(i64, i64)> = ds.objects().iter().map(|o| (o.scene, o.id)).collect();
    assert_eq!(keys, vec![(-4, 2), (-4, 3), (9, 1), (9, 7)]);
    assert_eq!(ds.scenes()[0].objects, 0..2);
    assert_eq!(ds.scenes()[2].objects, 4..4);
    assert_eq!(ds.scene_objects(1).len(), 2);
    assert_eq!(ds.object_scene(3), 1);
    assert_eq!(ds.find_object(9, 7), Some(3));
    assert_eq!(ds.find_object(9, 2), None);
    assert_eq!(ds.find_scene(100), Some(2));
    let pts = ds.points().unwrap();
    // Object (-4, 2) saw nothing; one object's cells are one contiguous slice.
    assert!((0..5).all(|t| pts.get(0, t).is_empty()));
    let off = pts.object_offsets(2);
    assert_eq!(off.len(), 6);
    for t in 0..5 {
        assert_eq!(pts.get(2, t), &pts.xy()[off[t]..off[t + 1]]);
    }
    assert_eq!(ds.observations().count(), pts.len());
    let states = ds.states().unwrap();
    assert!(states.get(1, 2).is_none() && !states.is_complete());
    assert!(ds.actions().unwrap().get(0, 0).is_none());

    let sub = ds.select_scenes(&[1, 0]);
    assert_eq!(sub.scenes().len(), 2);
    assert_eq!(sub.objects(), &ds.objects()[..4]);
    assert_eq!(sub.points().unwrap().get(3, 2), pts.get(3, 2));
    let dir = tempfile::tempdir().unwrap();
    sub.write(dir.path()).unwrap();
    assert_bit_exact(&sub, &Dataset::read(dir.path()).unwrap());
}

// ---------------------------------------------------------------- sharded reads

/// Every subset of the synthetic dataset's objects, read as one process's share,
/// equals the same share cut from the whole dataset in memory, on both kinds;
/// the layout read without values equals the whole dataset's.
#[test]
fn a_shard_read_from_files_equals_the_shard_cut_in_memory() {
    for kind in [ObservationKind::Points, ObservationKind::Boxes] {
        let ds = synthetic(kind);
        let dir = tempfile::tempdir().unwrap();
        ds.write(dir.path()).unwrap();
        let layout = Dataset::read_layout(dir.path()).unwrap();
        assert_eq!(layout, ds.layout());
        assert_eq!(layout.scenes, vec![0..2, 2..4, 4..4]);
        assert_eq!(layout.units.iter().sum::<usize>(), ds.observations().count());
        let n = ds.objects().len();
        for mask in 0..1u32 << n {
            let picked: Vec<usize> = (0..n).filter(|o| mask >> o & 1 == 1).collect();
            let keep: HashSet<(i64, i64)> = picked.iter().map(|&o| layout.objects[o]).collect();
            let shard = Dataset::read_shard(dir.path(), &keep).unwrap();
            assert_bit_exact(&shard, &ds.shard(&picked));
            // Every scene stays, with its AV poses, even without objects.
            assert_eq!(shard.scenes().len(), ds.scenes().len());
            assert_eq!(shard.objects().len(), picked.len());
        }
    }
}

/// A process validates the rows it keeps and skips the values of the others;
/// rows of an object no file lists are an error for every process.
#[test]
fn a_shard_read_validates_its_own_rows_and_rejects_unknown_objects() {
    let dir = tempfile::tempdir().unwrap();
    base(dir.path(), false);
    edit(dir.path(), "points.csv", &Edit::Replace(5, "2,10,1,-10,oops"));
    let mine: HashSet<(i64, i64)> = [(2, 10)].into();
    let others: HashSet<(i64, i64)> = [(1, 10), (1, 11)].into();
    let err = Dataset::read_shard(dir.path(), &mine).expect_err("the owner sees the bad value");
    assert_eq!((err.line(), err.column()), (Some(5), Some("y")), "{err}");
    let shard = Dataset::read_shard(dir.path(), &others).expect("the bad row is another process's");
    assert_eq!(shard.objects().len(), 2);
    // The layout counts rows without parsing values.
    assert_eq!(Dataset::read_layout(dir.path()).unwrap().units, vec![3, 0, 1]);

    base(dir.path(), false);
    edit(dir.path(), "points.csv", &Edit::Append("1,99,0,1,1"));
    for keep in [&mine, &others] {
        let err = Dataset::read_shard(dir.path(), keep).expect_err("an unknown object is an error");
        assert!(err.to_string().contains("99"), "{err}");
    }
    base(dir.path(), false);
    edit(dir.path(), "objects.csv", &Edit::Append("7,1,4.5,1.8,10,0,0,5,0,1,1,0.1,1,0.01"));
    let err = Dataset::read_layout(dir.path()).expect_err("an object of an unknown scene");
    assert_eq!((err.line(), err.column()), (Some(5), Some("scene")), "{err}");
}

// ---------------------------------------------------------------- bad input

const META: &str = "{\"format\": 1, \"dt\": 0.5, \"steps\": 3}\n";
const AV: &str = "scene,t,x,y,yaw
1,0,0,0,0
1,1,1,0,0
1,2,2,0,0
2,0,0,0,0
2,1,0,1,1.5
2,2,0,2,1.5
";
const OBJECTS: &str =
    "scene,object,length,width,prior_x,prior_y,prior_yaw,prior_v,prior_kappa,sd_x,sd_y,sd_yaw,sd_v,sd_kappa
1,10,4.5,1.8,10,0,0,5,0,1,1,0.1,1,0.01
1,11,4.0,1.7,20,5,0,5,0,1,1,0.1,1,0.01
2,10,4.2,1.9,-10,0,3.1,2,0,1,1,0.1,1,0.01
";
const POINTS: &str = "scene,object,t,x,y
1,10,0,9,0.5
1,10,0,9.5,-0.5
1,10,2,10,0
2,10,1,-10,1
";
const BOXES: &str = "scene,object,t,x,y,yaw,length,width,score
1,10,0,9,0.5,0.1,4.4,1.7,9.5
1,11,2,21,5,0,4.1,1.6,3
";
const STATES: &str = "scene,object,t,x,y,yaw,v,kappa
1,10,0,10,0,0,5,0
1,10,1,12.5,0,0,5,0
";
const ACTIONS: &str = "scene,object,t,accel,pinch
1,10,1,0,0
1,10,2,0.5,-0.01
";

/// Writes the base dataset (points or boxes, with states and actions).
fn base(dir: &Path, boxes: bool) {
    fs::write(dir.join("meta.json"), META).unwrap();
    fs::write(dir.join("av.csv"), AV).unwrap();
    fs::write(dir.join("objects.csv"), OBJECTS).unwrap();
    if boxes {
        fs::write(dir.join("boxes.csv"), BOXES).unwrap();
    } else {
        fs::write(dir.join("points.csv"), POINTS).unwrap();
    }
    fs::write(dir.join("states.csv"), STATES).unwrap();
    fs::write(dir.join("actions.csv"), ACTIONS).unwrap();
}

/// How to spoil a file.
enum Edit {
    /// Replace the 1-based line with this text.
    Replace(usize, &'static str),
    /// Append this line.
    Append(&'static str),
    /// Delete the 1-based line.
    Delete(usize),
}

fn edit(dir: &Path, file: &str, e: &Edit) {
    let path = dir.join(file);
    let text = fs::read_to_string(&path).unwrap();
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    match e {
        Edit::Replace(n, s) => lines[n - 1] = s.to_string(),
        Edit::Append(s) => lines.push(s.to_string()),
        Edit::Delete(n) => {
            lines.remove(n - 1);
        }
    }
    fs::write(&path, lines.join("\n") + "\n").unwrap();
}

/// Spoils one file of the base dataset and checks that reading fails with a
/// message naming `file`, `line` and `column` and containing `words`.
#[track_caller]
fn expect_error(boxes: bool, file: &str, e: Edit, line: usize, column: &str, words: &str) -> DataError {
    let dir = tempfile::tempdir().unwrap();
    base(dir.path(), boxes);
    Dataset::read(dir.path()).expect("the base dataset is valid");
    edit(dir.path(), file, &e);
    let err = Dataset::read(dir.path()).expect_err("spoiled dataset must be rejected");
    let msg = err.to_string();
    let place = format!("{file}: line {line}: column `{column}`");
    assert!(msg.starts_with(&place), "expected `{place}` in: {msg}");
    assert!(msg.contains(words), "expected `{words}` in: {msg}");
    assert_eq!(err.line(), Some(line), "{msg}");
    assert_eq!(err.column(), Some(column), "{msg}");
    err
}

#[test]
fn malformed_numbers() {
    use Edit::*;
    expect_error(false, "av.csv", Replace(3, "1,1,1.0.0,0,0"), 3, "x", "malformed value `1.0.0`");
    expect_error(false, "av.csv", Replace(4, "1,2,2,0,"), 4, "yaw", "malformed value ``");
    expect_error(false, "av.csv", Replace(2, "1,0.5,0,0,0"), 2, "t", "expected an integer");
    expect_error(false, "av.csv", Replace(2, "x1,0,0,0,0"), 2, "scene", "expected an integer");
    expect_error(false, "objects.csv", Replace(3, "1,11,4.0,1.7,20,5,0,5,0,1,1,0.1,1m,0.01"), 3, "sd_v", "malformed");
    expect_error(false, "points.csv", Replace(5, "2,10,1,-10,1e"), 5, "y", "malformed");
    expect_error(true, "boxes.csv", Replace(2, "1,10,0,9,0.5,0.1,4.4,1.7,high"), 2, "score", "malformed");
    expect_error(false, "states.csv", Replace(3, "1,10,1,12.5,0,0,five,0"), 3, "v", "malformed");
    expect_error(false, "actions.csv", Replace(2, "1,10,1,0,--1"), 2, "pinch", "malformed");
}

#[test]
fn non_finite_values() {
    use Edit::*;
    expect_error(false, "av.csv", Replace(6, "2,1,NaN,1,1.5"), 6, "x", "non-finite value `NaN`");
    expect_error(
        false,
        "objects.csv",
        Replace(4, "2,10,4.2,1.9,-10,0,inf,2,0,1,1,0.1,1,0.01"),
        4,
        "prior_yaw",
        "non-finite",
    );
    expect_error(false, "points.csv", Replace(2, "1,10,0,-inf,0.5"), 2, "x", "non-finite");
    expect_error(false, "states.csv", Replace(2, "1,10,0,10,0,0,5,nan"), 2, "kappa", "non-finite");
    expect_error(true, "boxes.csv", Replace(3, "1,11,2,21,5,infinity,4.1,1.6,3"), 3, "yaw", "non-finite");
}

#[test]
fn unknown_ids() {
    use Edit::*;
    // An object whose scene has no AV rows.
    expect_error(false, "objects.csv", Append("3,10,4.5,1.8,10,0,0,5,0,1,1,0.1,1,0.01"), 5, "scene", "unknown scene 3");
    // A point for an object not in objects.csv, and for an unknown scene.
    expect_error(false, "points.csv", Append("2,11,0,1,1"), 6, "object", "unknown object 11 in scene 2");
    expect_error(false, "points.csv", Replace(3, "7,10,0,9.5,-0.5"), 3, "scene", "unknown scene 7");
    expect_error(true, "boxes.csv", Replace(3, "1,12,2,21,5,0,4.1,1.6,3"), 3, "object", "unknown object 12");
    expect_error(false, "states.csv", Append("2,11,0,1,1,1,1,1"), 4, "object", "unknown object");
    expect_error(false, "actions.csv", Replace(3, "0,10,2,0.5,-0.01"), 3, "scene", "unknown scene 0");
}

#[test]
fn non_positive_sizes_and_sds() {
    use Edit::*;
    let obj = |line: &'static str, col: &str, words: &str| {
        expect_error(false, "objects.csv", Replace(2, line), 2, col, words);
    };
    obj("1,10,0,1.8,10,0,0,5,0,1,1,0.1,1,0.01", "length", "must be positive, found 0");
    obj("1,10,4.5,-1.8,10,0,0,5,0,1,1,0.1,1,0.01", "width", "must be positive, found -1.8");
    obj("1,10,4.5,1.8,10,0,0,5,0,0,1,0.1,1,0.01", "sd_x", "must be positive");
    obj("1,10,4.5,1.8,10,0,0,5,0,1,-1,0.1,1,0.01", "sd_y", "must be positive");
    obj("1,10,4.5,1.8,10,0,0,5,0,1,1,-0.0,1,0.01", "sd_yaw", "must be positive");
    obj("1,10,4.5,1.8,10,0,0,5,0,1,1,0.1,0,0.01", "sd_v", "must be positive");
    obj("1,10,4.5,1.8,10,0,0,5,0,1,1,0.1,1,-0.01", "sd_kappa", "must be positive");
    expect_error(true, "boxes.csv", Replace(2, "1,10,0,9,0.5,0.1,4.4,0,9.5"), 2, "width", "must be positive");
}

#[test]
fn duplicate_rows() {
    use Edit::*;
    expect_error(false, "av.csv", Append("1,2,5,5,5"), 8, "t", "duplicate row for scene 1, t 2 (first at line 4)");
    expect_error(
        false,
        "objects.csv",
        Append("1,11,4.0,1.7,20,5,0,5,0,1,1,0.1,1,0.01"),
        5,
        "object",
        "duplicate row for scene 1, object 11 (first at line 3)",
    );
    expect_error(true, "boxes.csv", Append("1,10,0,1,1,1,1,1,1"), 4, "t", "duplicate row for scene 1, object 10, t 0");
    expect_error(false, "states.csv", Append("1,10,1,0,0,0,0,0"), 4, "t", "first at line 3");
    expect_error(false, "actions.csv", Append("1,10,1,0,0"), 4, "t", "duplicate");
    // Several points of one object and step are not duplicates.
    let dir = tempfile::tempdir().unwrap();
    base(dir.path(), false);
    edit(dir.path(), "points.csv", &Append("1,10,0,9,0.5"));
    let ds = Dataset::read(dir.path()).unwrap();
    assert_eq!(ds.points().unwrap().get(0, 0).len(), 3);
}

#[test]
fn steps_out_of_range() {
    use Edit::*;
    expect_error(false, "av.csv", Append("2,3,0,0,0"), 8, "t", "step 3 out of range 0..3");
    expect_error(false, "points.csv", Replace(4, "1,10,-1,10,0"), 4, "t", "step -1 out of range 0..3");
    expect_error(true, "boxes.csv", Replace(3, "1,11,3,21,5,0,4.1,1.6,3"), 3, "t", "out of range");
    expect_error(false, "states.csv", Append("1,11,7,1,1,1,1,1"), 4, "t", "step 7 out of range");
    // Actions start at t = 1.
    expect_error(false, "actions.csv", Replace(2, "1,10,0,0,0"), 2, "t", "step 0 out of range 1..3");
}

#[test]
fn missing_av_pose() {
    use Edit::*;
    // Scene 2 loses its pose at t = 1: reported at the scene's first line.
    let err = expect_error(false, "av.csv", Delete(6), 5, "t", "scene 2 has no AV pose for step 1");
    assert!(matches!(err, DataError::Invalid { place: Place::Line(5), .. }));

    // A huge `steps` is caught as missing poses, without allocating per step.
    let dir = tempfile::tempdir().unwrap();
    base(dir.path(), false);
    fs::write(dir.path().join("meta.json"), "{\"format\": 1, \"dt\": 0.5, \"steps\": 1000000000000}").unwrap();
    let msg = Dataset::read(dir.path()).unwrap_err().to_string();
    assert!(msg.starts_with("av.csv: line 2: column `t`: scene 1 has no AV pose for step 3"), "{msg}");
}

#[test]
fn headers_are_required_and_exact() {
    use Edit::*;
    expect_error(false, "av.csv", Replace(1, "scene,t,x,y"), 1, "yaw", "bad header");
    expect_error(false, "av.csv", Replace(1, "scene,t,x,y,yaw,z"), 1, "z", "bad header");
    expect_error(false, "points.csv", Replace(1, "scene,object,t,y,x"), 1, "x", "bad header");
    // A file without its header: the first data row is not a header.
    expect_error(false, "states.csv", Delete(1), 1, "scene", "bad header");
    let dir = tempfile::tempdir().unwrap();
    base(dir.path(), true);
    fs::write(dir.path().join("boxes.csv"), "").unwrap();
    let msg = Dataset::read(dir.path()).unwrap_err().to_string();
    assert!(msg.starts_with("boxes.csv: line 1: column `scene`"), "{msg}");
}

#[test]
fn wrong_field_counts() {
    use Edit::*;
    expect_error(false, "av.csv", Replace(3, "1,1,1,0"), 3, "yaw", "expected 5 fields, found 4");
    expect_error(false, "points.csv", Replace(2, "1,10,0,9,0.5,3"), 2, "(extra field 6)", "found 6");
}

#[test]
fn tolerated_formatting() {
    // Windows line ends, spaces around fields, blank lines, a final line
    // without newline, and a byte-order mark are all fine.
    let dir = tempfile::tempdir().unwrap();
    base(dir.path(), false);
    fs::write(dir.path().join("points.csv"), "\u{feff}scene, object ,t,x,y\r\n1, 10,0,9,0.5\r\n\r\n2,10,1,-10,1")
        .unwrap();
    let ds = Dataset::read(dir.path()).unwrap();
    assert_eq!(ds.points().unwrap().len(), 2);
    // Row order in files does not matter.
    let av_reversed: String = {
        let mut lines: Vec<&str> = AV.lines().collect();
        lines[1..].reverse();
        lines.join("\n")
    };
    fs::write(dir.path().join("av.csv"), av_reversed).unwrap();
    assert_eq!(Dataset::read(dir.path()).unwrap(), ds);
}

#[test]
fn observation_files_exactly_one() {
    let dir = tempfile::tempdir().unwrap();
    base(dir.path(), false);
    fs::write(dir.path().join("boxes.csv"), BOXES).unwrap();
    let msg = Dataset::read(dir.path()).unwrap_err().to_string();
    assert!(msg.contains("both points.csv and boxes.csv"), "{msg}");
    fs::remove_file(dir.path().join("boxes.csv")).unwrap();
    fs::remove_file(dir.path().join("points.csv")).unwrap();
    let msg = Dataset::read(dir.path()).unwrap_err().to_string();
    assert!(msg.contains("neither points.csv nor boxes.csv"), "{msg}");
}

#[test]
fn missing_required_files() {
    for f in ["meta.json", "av.csv", "objects.csv"] {
        let dir = tempfile::tempdir().unwrap();
        base(dir.path(), false);
        fs::remove_file(dir.path().join(f)).unwrap();
        let err = Dataset::read(dir.path()).unwrap_err();
        assert!(matches!(err, DataError::MissingFile { .. }), "{err}");
        assert!(err.to_string().contains(f), "{err}");
    }
    // states.csv and actions.csv are optional.
    let dir = tempfile::tempdir().unwrap();
    base(dir.path(), false);
    fs::remove_file(dir.path().join("states.csv")).unwrap();
    fs::remove_file(dir.path().join("actions.csv")).unwrap();
    let ds = Dataset::read(dir.path()).unwrap();
    assert!(ds.states().is_none() && ds.actions().is_none());
}

#[test]
fn malformed_meta() {
    let cases = [
        ("{\"format\": 2, \"dt\": 0.5, \"steps\": 3}", 1, "format", "unsupported format version 2"),
        ("{\n  \"format\": 1,\n  \"dt\": 0,\n  \"steps\": 3\n}", 3, "dt", "must be a positive"),
        ("{\"format\": 1, \"dt\": -0.1, \"steps\": 3}", 1, "dt", "must be a positive"),
        ("{\"format\": 1, \"dt\": 0.5,\n \"steps\": 0}", 2, "steps", "must be at least 1"),
        ("{\"format\": 1, \"dt\": 0.5, \"steps\": 2.5}", 1, "steps", "integer"),
        ("{\"format\": 1, \"dt\": \"0.5\", \"steps\": 3}", 1, "dt", "expected a number"),
        ("{\"format\": 1, \"dt\": 0.5}", 1, "steps", "missing field"),
        ("{\"format\": 1, \"dt\": 0.5, \"steps\": 3, \"seed\": 4}", 1, "seed", "unknown field"),
        ("{\"format\": 1, \"dt\": 0.5,\n\n \"steps\": 3", 3, "-", "syntax error"),
        ("[1, 0.5, 3]", 1, "-", "syntax error"),
    ];
    for (text, line, field, words) in cases {
        let dir = tempfile::tempdir().unwrap();
        base(dir.path(), false);
        fs::write(dir.path().join("meta.json"), text).unwrap();
        let err = Dataset::read(dir.path()).unwrap_err();
        let msg = err.to_string();
        let place = if field == "-" {
            format!("meta.json: line {line}: syntax error")
        } else {
            format!("meta.json: line {line}: field `{field}`")
        };
        assert!(msg.starts_with(&place), "expected `{place}` in: {msg}");
        assert!(msg.contains(words), "expected `{words}` in: {msg}");
    }
}

#[test]
fn builder_errors_name_the_record() {
    let meta = Meta::new(0.1, 2);
    let pose = [Pose::default(); 2];
    let obj = |scene, id, length| Object { scene, id, length, width: 2.0, prior: prior(0.0, 0.0) };

    let mut b = Dataset::builder(meta, ObservationKind::Points);
    b.scene(1, &pose).object(obj(1, 1, 4.0)).object(obj(1, 2, -4.0));
    let msg = b.build().unwrap_err().to_string();
    assert!(msg.starts_with("objects.csv: record 1 (built in memory): column `length`"), "{msg}");

    let mut b = Dataset::builder(meta, ObservationKind::Points);
    b.scene(1, &pose[..1]);
    let msg = b.build().unwrap_err().to_string();
    assert!(msg.contains("av.csv") && msg.contains("no AV pose for step 1"), "{msg}");

    let mut b = Dataset::builder(meta, ObservationKind::Points);
    b.scene(1, &pose).object(obj(1, 1, 4.0));
    b.detection(1, 1, 0, BoxDetection { x: 0.0, y: 0.0, yaw: 0.0, length: 1.0, width: 1.0, score: 0.0 });
    let msg = b.build().unwrap_err().to_string();
    assert!(msg.contains("boxes.csv") && msg.contains("holds point observations"), "{msg}");

    let mut b = Dataset::builder(meta, ObservationKind::Boxes);
    b.scene(1, &pose).object(obj(1, 1, 4.0));
    b.point(1, 1, 0, [0.0, 0.0]);
    assert!(b.build().is_err());

    let mut b = Dataset::builder(Meta::new(f64::NAN, 2), ObservationKind::Boxes);
    b.scene(1, &pose);
    let msg = b.build().unwrap_err().to_string();
    assert!(msg.contains("`dt`"), "{msg}");

    let mut b = Dataset::builder(meta, ObservationKind::Points);
    b.scene(1, &pose).object(obj(1, 1, 4.0));
    b.point(1, 1, 0, [f64::INFINITY, 0.0]);
    let msg = b.build().unwrap_err().to_string();
    assert!(msg.starts_with("points.csv: record 0 (built in memory): column `x`: non-finite"), "{msg}");
}

#[test]
fn write_failure_keeps_existing_files() {
    let dir = tempfile::tempdir().unwrap();
    let ds = synthetic(ObservationKind::Points);
    ds.write(dir.path()).unwrap();
    let before = fs::read(dir.path().join("av.csv")).unwrap();
    // A directory in the way of a file makes the rename of objects.csv fail
    // after av.csv was replaced; every complete file survives.
    fs::remove_file(dir.path().join("objects.csv")).unwrap();
    fs::create_dir(dir.path().join("objects.csv")).unwrap();
    fs::write(dir.path().join("objects.csv").join("keep"), "x").unwrap();
    let err = synthetic(ObservationKind::Boxes).write(dir.path()).unwrap_err();
    assert!(err.to_string().contains("objects.csv"), "{err}");
    assert_eq!(fs::read(dir.path().join("av.csv")).unwrap(), before);
    assert!(dir.path().join("points.csv").exists());
    let leftovers: Vec<_> = fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn random_corruption_never_panics() {
    // Flip, delete and insert bytes at random in each file of a valid
    // dataset: reading must return Ok or Err, never panic.
    let src = tempfile::tempdir().unwrap();
    synthetic(ObservationKind::Boxes).write(src.path()).unwrap();
    let files = ["meta.json", "av.csv", "objects.csv", "boxes.csv", "states.csv", "actions.csv"];
    let originals: Vec<Vec<u8>> = files.iter().map(|f| fs::read(src.path().join(f)).unwrap()).collect();
    let mut rng = StdRng::seed_from_u64(11);
    let alphabet = b"0123456789,.-e\nNa \"{}:x";
    let (mut ok, mut rejected) = (0, 0);
    for _ in 0..250 {
        let dir = tempfile::tempdir().unwrap();
        let k = rng.random_range(0..files.len());
        for (i, f) in files.iter().enumerate() {
            let mut bytes = originals[i].clone();
            if i == k {
                for _ in 0..rng.random_range(1..4) {
                    let pos = rng.random_range(0..bytes.len());
                    let c = alphabet[rng.random_range(0..alphabet.len())];
                    match rng.random_range(0..3) {
                        0 => bytes[pos] = c,
                        1 => {
                            bytes.remove(pos);
                        }
                        _ => bytes.insert(pos, c),
                    }
                }
            }
            fs::write(dir.path().join(f), bytes).unwrap();
        }
        match Dataset::read(dir.path()) {
            Ok(_) => ok += 1,
            Err(e) => {
                // Every rejection says which file.
                assert!(files.iter().any(|f| e.to_string().contains(f)), "{e}");
                rejected += 1;
            }
        }
    }
    assert!(rejected > 125, "{ok} accepted, {rejected} rejected");
}
