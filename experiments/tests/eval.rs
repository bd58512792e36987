//! `sefi eval` and `sefi track` end to end on tiny datasets written by the test.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use autodiff::nn::ParamStore;
use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::data::{Action, Dataset, Meta, Object, ObservationKind, Pose, Prior, State};
use ssm::models::observation::{ObsContext, ObservationModel};
use ssm::models::params::{AnyObservation, AnyPolicy, Models};
use ssm::models::vehicle::{
    Action as VAction, ActionGaussians, ActionsMut, GaussianPolicy, HandCraftedPolicy, MotionModel, NeuralPolicy,
    VehicleState,
};

const DT: f64 = 1.0 / 3.0;

/// A fresh directory under the target's temporary directory.
fn workdir(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("sefi-eval-{name}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A parameter store: `policy` (hand-crafted truth, or a fresh neural network) and
/// a fresh observation network of `kind` under `obs`.
fn store_for(kind: ObservationKind, neural: bool, seed: u64) -> ParamStore<f64> {
    let mut store = ParamStore::new();
    let mut rng = StdRng::seed_from_u64(seed);
    AnyObservation::init(kind, &mut store, &mut rng);
    let policy = if neural {
        AnyPolicy::Neural(NeuralPolicy::new(&mut rng))
    } else {
        AnyPolicy::HandCrafted(HandCraftedPolicy::truth())
    };
    policy.add_to_store(&mut store);
    store
}

/// A tiny dataset simulated from `store` (hand-crafted policy): two scenes with an
/// AV driving along x, `n` objects each, true states and actions, 5 points or one
/// detection per step.
fn tiny(kind: ObservationKind, store: &ParamStore<f64>, n: usize, steps: usize, seed: u64) -> Dataset {
    let models = Models::from_store(store, kind).unwrap();
    let policy = HandCraftedPolicy::truth();
    let mut rng = StdRng::seed_from_u64(seed);
    let mut b = Dataset::builder(Meta::new(DT, steps), kind);
    let motion = MotionModel::new(DT, Default::default()).unwrap();
    let mut g = ActionGaussians::default();
    for scene in [3i64, 7] {
        let av: Vec<Pose> =
            (0..steps).map(|t| Pose { x: 6.0 * DT * t as f64, y: 0.5 * scene as f64, yaw: 0.0 }).collect();
        b.scene(scene, &av);
        for i in 0..n {
            let id = i as i64;
            let angle = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
            let r = 10.0 + 4.0 * i as f64;
            let x0 = State { x: r * angle.cos(), y: r * angle.sin(), yaw: angle + 1.2, v: 4.0 + i as f64, kappa: 0.02 };
            let sd = State { x: 0.5, y: 0.5, yaw: 0.05, v: 0.5, kappa: 0.005 };
            let obj = Object { scene, id, length: 4.5, width: 1.9, prior: Prior { mean: x0, sd } };
            b.object(obj);
            let mut s = VehicleState::new(x0.x, x0.y, x0.yaw, x0.v, x0.kappa);
            for (t, &av_t) in av.iter().enumerate() {
                if t > 0 {
                    let (mut a, mut p) = ([0.0], [0.0]);
                    let out = ActionsMut { accel: &mut a, pinch: &mut p };
                    policy.sample_actions(&[s.v], &[s.kappa], &mut rng, &mut g, out);
                    s = motion.step(&s, &VAction::new(a[0], p[0]));
                    b.action(scene, id, t, Action { accel: a[0], pinch: p[0] });
                }
                b.state(scene, id, t, State { x: s.x, y: s.y, yaw: s.yaw, v: s.v, kappa: s.kappa });
                let ctx = ObsContext::of_object(av_t, &obj);
                let pose = Pose { x: s.x, y: s.y, yaw: s.yaw };
                match &models.observation {
                    AnyObservation::Points(m) => {
                        let mut pts = Vec::new();
                        m.sample(&models.observation_params, &ctx, pose, 5, &mut rng, &mut pts);
                        for p in pts {
                            b.point(scene, id, t, p);
                        }
                    }
                    AnyObservation::Boxes(m) => {
                        let mut dets = Vec::new();
                        m.sample(&models.observation_params, &ctx, pose, 1, &mut rng, &mut dets);
                        b.detection(scene, id, t, dets[0]);
                    }
                }
            }
        }
    }
    b.build().unwrap()
}

/// Writes a dataset and its parameter file into `dir` and returns their paths.
fn setup(dir: &Path, kind: ObservationKind, neural: bool) -> (PathBuf, PathBuf) {
    let store = store_for(kind, neural, 1);
    let data = tiny(kind, &store, 4, 8, 2);
    let (data_dir, params) = (dir.join("data"), dir.join("params.bin"));
    data.write(&data_dir).unwrap();
    store.save(&params).unwrap();
    (data_dir, params)
}

fn sefi(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sefi")).args(args).output().expect("run sefi")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn assert_clean_failure(out: &Output, needle: &str) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "expected failure; stderr: {stderr}");
    assert!(!stderr.contains("panicked"), "panicked: {stderr}");
    assert!(stderr.contains(needle), "stderr should mention {needle:?}: {stderr}");
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn eval_writes_metrics_for_points() {
    let dir = workdir("points");
    let (data, params) = setup(&dir, ObservationKind::Points, false);
    let out = dir.join("out");
    let r = sefi(&[
        "eval",
        "--data",
        s(&data),
        "--params",
        s(&params),
        "--particles",
        "128",
        "--lag",
        "2",
        "--runs",
        "3",
        "--out",
        s(&out),
    ]);
    assert!(r.status.success(), "stderr: {}", String::from_utf8_lossy(&r.stderr));
    let doc = json(&out.join("metrics.json"));
    assert_eq!(doc["policy"], "hand-crafted");
    assert_eq!(doc["observation"], "points");
    assert_eq!(doc["runs"].as_array().unwrap().len(), 3);
    let run = &doc["runs"][0];
    let units = run["observed_units"].as_f64().unwrap();
    assert_eq!(units, (2 * 4 * 8 * 5) as f64, "every point enters the likelihood");
    let mll = run["mll"].as_f64().unwrap();
    assert!((mll * units - run["log_likelihood"].as_f64().unwrap()).abs() < 1e-6 * mll.abs() * units);
    for key in ["mll", "ade_smoothed", "aye_smoothed", "ade_filtered", "aye_filtered", "aotll", "aptll"] {
        let s = &doc["summary"][key];
        assert!(s["median"].as_f64().unwrap().is_finite(), "{key}: {s}");
        assert!(s["iqr"].as_f64().unwrap() >= 0.0, "{key}: {s}");
        assert_eq!(s["n"], 3);
    }
    // CSV: a header and one row per run, all numbers.
    let csv = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), 4);
    let header: Vec<&str> = lines[0].split(',').collect();
    assert!(header.contains(&"mll") && header.contains(&"ade_smoothed") && header.contains(&"aptll"));
    for row in &lines[1..] {
        let cells: Vec<&str> = row.split(',').collect();
        assert_eq!(cells.len(), header.len());
        assert!(cells.iter().all(|c| c.parse::<f64>().is_ok()), "{row}");
    }
    // The printed table names the metrics; the box-only split is absent.
    assert!(String::from_utf8_lossy(&r.stdout).contains("mll"));
    assert!(doc["aotll_terms"].is_null());
}

#[test]
fn eval_boxes_with_a_neural_policy() {
    let dir = workdir("boxes-neural");
    let (data, params) = setup(&dir, ObservationKind::Boxes, true);
    let out = dir.join("out");
    let r = sefi(&["eval", "--data", s(&data), "--params", s(&params), "--particles", "64", "--out", s(&out)]);
    assert!(r.status.success(), "stderr: {}", String::from_utf8_lossy(&r.stderr));
    let doc = json(&out.join("metrics.json"));
    assert_eq!(doc["policy"], "neural");
    assert_eq!(doc["observation"], "boxes");
    assert_eq!(doc["runs"][0]["observed_units"], 2 * 4 * 8);
    assert!(doc["runs"][0]["aotll"]["mean"].as_f64().unwrap().is_finite());
    // Box data with labels: AOTLL split into reversed headings and the factors,
    // its counts those of AOTLL, printed and kept.
    let terms = &doc["aotll_terms"];
    let counted = terms["reversed"]["count"].as_u64().unwrap() + terms["others"]["total"]["count"].as_u64().unwrap();
    assert_eq!(counted, doc["runs"][0]["aotll"]["count"].as_u64().unwrap());
    assert!(terms["others"]["along"]["mean"].as_f64().unwrap().is_finite(), "{terms}");
    let split =
        terms["in_line"]["total"]["count"].as_u64().unwrap() + terms["crossing"]["total"]["count"].as_u64().unwrap();
    assert_eq!(split, terms["others"]["total"]["count"].as_u64().unwrap());
    assert!(String::from_utf8_lossy(&r.stdout).contains("AOTLL by part"));
}

#[test]
fn track_writes_states_and_a_birdseye_plot() {
    let dir = workdir("track");
    let (data, params) = setup(&dir, ObservationKind::Points, false);
    let out = dir.join("out");
    let r = sefi(&[
        "track",
        "--data",
        s(&data),
        "--params",
        s(&params),
        "--particles",
        "256",
        "--lag",
        "3",
        "--plot-scene",
        "7",
        "--out",
        s(&out),
    ]);
    assert!(r.status.success(), "stderr: {}", String::from_utf8_lossy(&r.stderr));
    let dataset = Dataset::read(&data).unwrap();
    for name in ["smoothed.csv", "filtered.csv"] {
        let text = std::fs::read_to_string(out.join(name)).unwrap();
        let mut lines = text.lines();
        assert_eq!(lines.next().unwrap(), "scene,object,t,x,y,yaw,v,kappa");
        let rows: Vec<Vec<f64>> =
            lines.map(|l| l.split(',').map(|c| c.parse::<f64>().expect("a number")).collect()).collect();
        assert_eq!(rows.len(), dataset.objects().len() * dataset.steps());
        assert!(rows.iter().all(|r| r.len() == 8 && r.iter().all(|v| v.is_finite())));
        assert!(rows.iter().all(|r| r[5].abs() <= std::f64::consts::PI + 1e-12), "yaw wrapped");
        // Scene and object ids are those of the dataset.
        assert!(rows.iter().all(|r| dataset.find_object(r[0] as i64, r[1] as i64).is_some()));
    }
    let svg = std::fs::read_to_string(out.join("birdseye_scene_7.svg")).unwrap();
    assert!(svg.starts_with("<svg") || svg.contains("<svg"));
    for label in ["true box", "observed points", "smoothed mean", "AV track"] {
        assert!(svg.contains(label), "legend lacks {label:?}");
    }
    let doc = json(&out.join("track.json"));
    assert!(doc["metrics"]["smoothed"]["ade"].as_f64().unwrap().is_finite());
}

#[test]
fn track_draws_box_detections() {
    let dir = workdir("track-boxes");
    let (data, params) = setup(&dir, ObservationKind::Boxes, false);
    let out = dir.join("out");
    let r = sefi(&["track", "--data", s(&data), "--params", s(&params), "--particles", "128", "--out", s(&out)]);
    assert!(r.status.success(), "stderr: {}", String::from_utf8_lossy(&r.stderr));
    let svg = std::fs::read_to_string(out.join("birdseye_scene_3.svg")).unwrap();
    assert!(svg.contains("detected box"));
}

#[test]
fn bad_input_gives_a_clear_error() {
    let dir = workdir("bad");
    let (data, params) = setup(&dir, ObservationKind::Points, false);
    let out = dir.join("out");
    // No --params.
    assert_clean_failure(&sefi(&["eval", "--data", s(&data), "--out", s(&out)]), "--params");
    assert_clean_failure(&sefi(&["track", "--data", s(&data), "--out", s(&out)]), "--params");
    // A params file that does not exist.
    let missing = dir.join("nope.bin");
    assert_clean_failure(&sefi(&["eval", "--data", s(&data), "--params", s(&missing), "--out", s(&out)]), "nope.bin");
    // A file that is not a parameter store.
    let junk = dir.join("junk.bin");
    std::fs::write(&junk, b"not a parameter file").unwrap();
    assert_clean_failure(&sefi(&["eval", "--data", s(&data), "--params", s(&junk), "--out", s(&out)]), "junk.bin");
    // The wrong kind: a box-detection network for a point dataset.
    let boxes = dir.join("boxes.bin");
    store_for(ObservationKind::Boxes, false, 3).save(&boxes).unwrap();
    assert_clean_failure(
        &sefi(&["eval", "--data", s(&data), "--params", s(&boxes), "--out", s(&out)]),
        "point observation model",
    );
    // A dataset directory that does not exist.
    let nodata = dir.join("no-data");
    assert_clean_failure(&sefi(&["eval", "--data", s(&nodata), "--params", s(&params), "--out", s(&out)]), "no-data");
    // A scene that does not exist.
    assert_clean_failure(
        &sefi(&["track", "--data", s(&data), "--params", s(&params), "--plot-scene", "99", "--out", s(&out)]),
        "--plot-scene 99",
    );
    // Zero particles.
    assert_clean_failure(
        &sefi(&["eval", "--data", s(&data), "--params", s(&params), "--particles", "0", "--out", s(&out)]),
        "--particles",
    );
    assert!(!out.join("metrics.json").exists(), "nothing written on failure");
}
