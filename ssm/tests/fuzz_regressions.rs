//! What fuzzing the readers of outside input found (`fuzz/`, cargo-fuzz), kept
//! as ordinary tests: each minimised input that crashed, hung or exhausted
//! memory now reads as an error; absurd but well-formed input (a line of a
//! gigabyte, a million columns, a length field of a terabyte) is an error
//! without an allocation to match; and whatever the writers produce, the
//! readers read back to equal values, for random datasets, parameter files
//! and checkpoints.

use autodiff::nn::{ParamStore, PARAM_FORMAT_VERSION};
use autodiff::optim::Adam;
use autodiff::Tensor;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::data::{
    import_kitti, Action, BoxDetection, Dataset, KittiOptions, Meta, Object, ObservationKind, Pose, Prior, State,
};
use ssm::models::extended::Extension;
use ssm::models::observation::boxes::DetectionOffsets;
use ssm::models::params::{AnyPolicy, FittedExtension, Models};
use ssm::models::vehicle::{HandCraftedPolicy, NeuralPolicy};
use ssm::training::{Checkpoint, TrainConfig, TrainError, CHECKPOINT_VERSION};
use std::collections::HashSet;
use std::fs;
use std::path::Path;

/// The first bytes of a versioned file (`autodiff::nn::write_versioned`).
const MAGIC: &[u8; 8] = b"PFSEFI\x00\x01";

/// `payload` behind a valid header of `version` with its checksum (FNV-1a), as
/// `write_versioned` frames it: what the fuzz targets do to reach the decoder.
fn framed(version: u32, payload: &[u8]) -> Vec<u8> {
    let sum = payload.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3));
    let mut bytes = MAGIC.to_vec();
    bytes.extend_from_slice(&version.to_le_bytes());
    bytes.extend_from_slice(&sum.to_le_bytes());
    bytes.extend_from_slice(payload);
    bytes
}

/// Little-endian `u64`s and byte strings, the way bincode lays out lengths.
fn le(parts: &[&[u8]]) -> Vec<u8> {
    parts.concat()
}

// ------------------------------------------------------- parameter files

/// A tensor whose shape says more elements than its data holds read as a
/// tensor, and `Models::from_store` then indexed past its data (a panic): the
/// store is now refused as it is decoded.
#[test]
fn a_tensor_shorter_than_its_shape_is_refused() {
    // One parameter `policy.log_sd` of shape [2] holding one number.
    let name = b"policy.log_sd";
    let payload = le(&[
        &1u64.to_le_bytes(),
        &(name.len() as u64).to_le_bytes(),
        name,
        &1u64.to_le_bytes(),
        &1u64.to_le_bytes(),
        &2u64.to_le_bytes(),
        &1u64.to_le_bytes(),
        &0.5f64.to_le_bytes(),
    ]);
    let err = ParamStore::<f64>::from_bytes(&framed(PARAM_FORMAT_VERSION, &payload)).unwrap_err();
    assert!(err.to_string().contains("tensor of shape [2] with 1 elements"), "{err}");
    // The same file with both numbers reads.
    let whole =
        le(&[&payload[..payload.len() - 16], &2u64.to_le_bytes(), &0.5f64.to_le_bytes(), &0.25f64.to_le_bytes()]);
    let store = ParamStore::<f64>::from_bytes(&framed(PARAM_FORMAT_VERSION, &whole)).unwrap();
    assert_eq!(store.values()[0].data(), &[0.5, 0.25]);
}

/// A shape whose element count overflows `usize` is refused, not multiplied.
#[test]
fn a_shape_that_overflows_is_refused() {
    let name = b"obs.0.w";
    let payload = le(&[
        &1u64.to_le_bytes(),
        &(name.len() as u64).to_le_bytes(),
        name,
        &1u64.to_le_bytes(),
        &2u64.to_le_bytes(),
        &(1u64 << 40).to_le_bytes(),
        &(1u64 << 40).to_le_bytes(),
        &0u64.to_le_bytes(),
    ]);
    let err = ParamStore::<f64>::from_bytes(&framed(PARAM_FORMAT_VERSION, &payload)).unwrap_err();
    assert!(err.to_string().contains("tensor of shape"), "{err}");
}

/// More names than values (or the reverse) made `ParamStore::get` index past
/// the values; a name given twice broke `ParamStore::id`'s one-to-one lookup.
#[test]
fn a_store_with_unpaired_or_repeated_names_is_refused() {
    let tensor = le(&[&1u64.to_le_bytes(), &1u64.to_le_bytes(), &1u64.to_le_bytes(), &1.0f64.to_le_bytes()]);
    let names = |list: &[&[u8]]| {
        let mut out = (list.len() as u64).to_le_bytes().to_vec();
        for n in list {
            out.extend_from_slice(&(n.len() as u64).to_le_bytes());
            out.extend_from_slice(n);
        }
        out
    };
    let two_names_one_value = le(&[&names(&[b"a", b"b"]), &1u64.to_le_bytes(), &tensor]);
    let err = ParamStore::<f64>::from_bytes(&framed(PARAM_FORMAT_VERSION, &two_names_one_value)).unwrap_err();
    assert!(err.to_string().contains("2 parameter names for 1 values"), "{err}");
    let repeated = le(&[&names(&[b"a", b"a"]), &2u64.to_le_bytes(), &tensor, &tensor]);
    let err = ParamStore::<f64>::from_bytes(&framed(PARAM_FORMAT_VERSION, &repeated)).unwrap_err();
    assert!(err.to_string().contains("\"a\" given twice"), "{err}");
    let fine = le(&[&names(&[b"a", b"b"]), &2u64.to_le_bytes(), &tensor, &tensor]);
    assert_eq!(ParamStore::<f64>::from_bytes(&framed(PARAM_FORMAT_VERSION, &fine)).unwrap().len(), 2);
}

/// A length field of a terabyte is an error, not an allocation of a terabyte
/// (which would abort the test): the decoder reads lengths against the bytes
/// it has.
#[test]
fn huge_length_fields_do_not_allocate() {
    for len in [1u64 << 40, u64::MAX] {
        // As the count of names, as a name's length, as a shape's rank and as
        // the data's length.
        let payloads = [
            le(&[&len.to_le_bytes()]),
            le(&[&1u64.to_le_bytes(), &len.to_le_bytes(), b"abc"]),
            le(&[&0u64.to_le_bytes(), &1u64.to_le_bytes(), &len.to_le_bytes()]),
            le(&[
                &0u64.to_le_bytes(),
                &1u64.to_le_bytes(),
                &1u64.to_le_bytes(),
                &4u64.to_le_bytes(),
                &len.to_le_bytes(),
            ]),
        ];
        for p in &payloads {
            assert!(ParamStore::<f64>::from_bytes(&framed(PARAM_FORMAT_VERSION, p)).is_err());
            assert!(Checkpoint::from_bytes(&framed(CHECKPOINT_VERSION, p)).is_err());
        }
    }
}

/// Bad magic, another version, a wrong checksum and a short file are each
/// named as such.
#[test]
fn header_damage_is_named() {
    let mut store = ParamStore::<f64>::new();
    store.add("x", Tensor::from_vec(vec![1.0, 2.0]));
    let payload = bincode::serialize(&store).unwrap();
    let good = framed(PARAM_FORMAT_VERSION, &payload);
    assert_eq!(ParamStore::<f64>::from_bytes(&good).unwrap(), store);
    let mut magic = good.clone();
    magic[0] ^= 1;
    assert!(ParamStore::<f64>::from_bytes(&magic).unwrap_err().to_string().contains("bad header"));
    let other = framed(PARAM_FORMAT_VERSION + 1, &payload);
    assert!(ParamStore::<f64>::from_bytes(&other).unwrap_err().to_string().contains("format version"));
    let mut flipped = good.clone();
    *flipped.last_mut().unwrap() ^= 0x10;
    assert!(ParamStore::<f64>::from_bytes(&flipped).unwrap_err().to_string().contains("checksum"));
    assert!(ParamStore::<f64>::from_bytes(&good[..19]).is_err());
}

// ------------------------------------------------------------ checkpoints

/// A checkpoint written by a run, for the damage tests.
fn checkpoint(rng: &mut StdRng) -> Checkpoint {
    let params = random_store(rng, false);
    let mut adam = Adam::new(0.01);
    let mut stepped = params.clone();
    let grads: Vec<Tensor<f64>> = params
        .values()
        .iter()
        .map(|v| Tensor::new(v.shape(), v.data().iter().map(|_| rng.random()).collect()))
        .collect();
    adam.step(&mut stepped, &grads).unwrap();
    Checkpoint {
        step: rng.random_range(0..1000),
        params: stepped.clone(),
        adam,
        skipped_steps: rng.random_range(0..5),
        config: TrainConfig { lr: rng.random(), epochs: rng.random_range(1..50), ..TrainConfig::default() },
        batches: rng.random_range(1..10),
        eval_names: vec!["aotll".into(), "ll".into()],
        last_eval: (rng.random_range(0..100), vec![rng.random(), -rng.random::<f64>()]),
        seconds: rng.random::<f64>() * 100.0,
        best: rng.random_bool(0.5).then(|| (3, rng.random(), stepped.clone())),
        average: rng.random_bool(0.5).then(|| (2, params.clone())),
    }
}

/// An optimiser state whose moments do not fit the parameters read as a
/// checkpoint, and the resumed run's first step indexed past them (a panic);
/// best or averaged parameters of another layout likewise. Each is now
/// refused as the checkpoint is decoded.
#[test]
fn a_checkpoint_whose_parts_do_not_fit_is_refused() {
    let mut rng = StdRng::seed_from_u64(11);
    let mut ckpt = checkpoint(&mut rng);
    while ckpt.params.is_empty() {
        ckpt = checkpoint(&mut rng);
    }
    let bytes = |c: &Checkpoint| framed(CHECKPOINT_VERSION, &bincode::serialize(c).unwrap());
    assert_eq!(Checkpoint::from_bytes(&bytes(&ckpt)).unwrap(), ckpt);

    // Moments of the right count whose sizes differ: the parameters' first
    // tensor grows by one element.
    let mut grown = ckpt.clone();
    let first = grown.params.values()[0].clone();
    let mut data = first.data().to_vec();
    data.push(0.0);
    grown.params.values_mut()[0] = Tensor::from_vec(data);
    grown.best = None;
    grown.average = None;
    let err = Checkpoint::from_bytes(&bytes(&grown)).unwrap_err();
    assert!(matches!(err, TrainError::Checkpoint { .. }) && err.to_string().contains("optimiser state"), "{err}");

    let mut other_best = ckpt.clone();
    let mut store = ParamStore::new();
    store.add("elsewhere", Tensor::from_vec(vec![1.0]));
    other_best.best = Some((1, 0.0, store.clone()));
    assert!(Checkpoint::from_bytes(&bytes(&other_best)).unwrap_err().to_string().contains("best parameters"));
    let mut other_average = ckpt.clone();
    other_average.average = Some((1, store));
    assert!(Checkpoint::from_bytes(&bytes(&other_average)).unwrap_err().to_string().contains("average parameters"));
}

// ---------------------------------------------------------------- datasets

/// A valid two-step point dataset's files, with `av.csv` replaced by `av`.
fn dataset_with_av(dir: &Path, av: &[u8]) {
    fs::write(dir.join("meta.json"), "{\"format\": 1, \"dt\": 0.5, \"steps\": 2}").unwrap();
    fs::write(dir.join("av.csv"), av).unwrap();
    fs::write(
        dir.join("objects.csv"),
        "scene,object,length,width,prior_x,prior_y,prior_yaw,prior_v,prior_kappa,sd_x,sd_y,sd_yaw,sd_v,sd_kappa\n",
    )
    .unwrap();
    fs::write(dir.join("points.csv"), "scene,object,t,x,y\n").unwrap();
}

/// A CSV line of a gigabyte (a sparse file: no disk is used) is an error
/// after the first megabyte, on the header line and on a data line.
#[test]
fn a_line_of_a_gigabyte_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    dataset_with_av(dir.path(), b"");
    let huge = |path: &Path, prefix: &[u8]| {
        fs::write(path, prefix).unwrap();
        fs::OpenOptions::new().write(true).open(path).unwrap().set_len(1 << 30).unwrap();
    };
    huge(&dir.path().join("av.csv"), b"");
    let err = Dataset::read(dir.path()).unwrap_err();
    assert_eq!((err.file().as_deref(), err.line()), (Some("av.csv"), Some(1)), "{err}");
    assert!(err.to_string().contains("line longer than"), "{err}");
    huge(&dir.path().join("av.csv"), b"scene,t,x,y,yaw\n0,0,1");
    let err = Dataset::read(dir.path()).unwrap_err();
    assert_eq!(err.line(), Some(2), "{err}");
    assert!(Dataset::read_layout(dir.path()).is_err());
    // meta.json of a gigabyte.
    dataset_with_av(dir.path(), b"scene,t,x,y,yaw\n0,0,0,0,0\n0,1,0,0,0\n");
    assert!(Dataset::read(dir.path()).is_ok());
    huge(&dir.path().join("meta.json"), b"{\"format\": 1, ");
    let err = Dataset::read(dir.path()).unwrap_err();
    assert!(err.to_string().contains("over 1048576 bytes"), "{err}");
}

/// A header or a row of half a million columns is a field-count or header
/// error; the reader counts the fields without keeping them.
#[test]
fn half_a_million_columns_are_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let wide = "1,".repeat(500_000);
    dataset_with_av(dir.path(), format!("scene,t,x,y,yaw\n0,0,0,0,{wide}0\n").as_bytes());
    let err = Dataset::read(dir.path()).unwrap_err();
    assert_eq!((err.line(), err.column()), (Some(2), Some("(extra field 6)")), "{err}");
    assert!(err.to_string().contains("found 500005"), "{err}");
    dataset_with_av(dir.path(), format!("scene,t,x,y,yaw,{wide}\n").as_bytes());
    let err = Dataset::read(dir.path()).unwrap_err();
    assert_eq!(err.line(), Some(1), "{err}");
}

/// A `steps` of 10^18 in `meta.json` allocates nothing per step: the scenes'
/// rows show the steps do not exist.
#[test]
fn a_huge_step_count_is_an_error_without_allocation() {
    let dir = tempfile::tempdir().unwrap();
    dataset_with_av(dir.path(), b"scene,t,x,y,yaw\n0,0,0,0,0\n0,1,0,0,0\n");
    fs::write(dir.path().join("meta.json"), "{\"format\": 1, \"dt\": 0.5, \"steps\": 1000000000000000000}").unwrap();
    let err = Dataset::read(dir.path()).unwrap_err();
    assert_eq!((err.file().as_deref(), err.column()), (Some("av.csv"), Some("t")), "{err}");
}

// ------------------------------------------------------------------- KITTI

/// The four files of a tiny KITTI sequence 0 under `root`, `which` of them
/// (an index into labels, detections, poses, calibration) replaced by `bytes`.
fn kitti_sequence(root: &Path, which: usize, bytes: &[u8]) {
    let label = "0 1 Car 0 0 -1.5 0 0 10 10 1.5 1.8 4.5 0.0 1.6 10.0 -1.57\n";
    let labels: String = (0..6).map(|f| label.replacen('0', &f.to_string(), 1)).collect();
    let det = "0,2,0,0,10,10,5.0,1.5,1.8,4.5,0.0,1.6,10.0,-1.57,-1.5\n";
    let dets: String = (0..6).map(|f| det.replacen('0', &f.to_string(), 1)).collect();
    let poses = "1 0 0 0 0 1 0 0 0 0 1 0\n".repeat(6);
    let calib = "P2: 721.5 0 609.6 44.9 0 721.5 172.9 0.2 0 0 1 0.003\n";
    let files = ["label_02", "det_pointrcnn/Car", "ego_pose_orbslam3", "calib"];
    for (i, (folder, text)) in files.iter().zip([labels, dets, poses.clone(), calib.to_string()]).enumerate() {
        let path = root.join(folder).join("0000.txt");
        fs::create_dir_all(path.parent().unwrap()).unwrap();
        if i == which {
            fs::write(&path, bytes).unwrap();
        } else {
            fs::write(&path, text).unwrap();
        }
    }
}

fn kitti_options() -> KittiOptions {
    KittiOptions { steps: 3, sequences: Some(vec![0]), val_sequences: Some(vec![]), ..KittiOptions::default() }
}

/// A KITTI file of a gigabyte is refused before it is read into memory, and
/// a line of half a million fields is a field-count error.
#[test]
fn kitti_files_of_absurd_size_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    kitti_sequence(dir.path(), 9, b"");
    let import = import_kitti(dir.path(), &kitti_options()).unwrap();
    assert!(!import.train.objects().is_empty(), "the tiny sequence imports");
    for which in 0..4 {
        kitti_sequence(dir.path(), 9, b"");
        let path =
            dir.path().join(["label_02", "det_pointrcnn/Car", "ego_pose_orbslam3", "calib"][which]).join("0000.txt");
        fs::OpenOptions::new().write(true).open(&path).unwrap().set_len(1 << 30).unwrap();
        let err = import_kitti(dir.path(), &kitti_options()).unwrap_err();
        assert!(err.to_string().contains("file over"), "{which}: {err}");
    }
    let wide = format!("0 {}\n", "1 ".repeat(500_000));
    for which in 0..3 {
        kitti_sequence(dir.path(), which, wide.as_bytes());
        let err = import_kitti(dir.path(), &kitti_options()).unwrap_err();
        assert!(err.to_string().contains("fields, found"), "{which}: {err}");
    }
    kitti_sequence(dir.path(), 3, format!("P2: {wide}").as_bytes());
    let err = import_kitti(dir.path(), &kitti_options()).unwrap_err();
    assert!(err.to_string().contains("expected 12 fields, found 500001"), "{err}");
}

// -------------------------------------------------------------- round trips

/// A value for a CSV cell: mostly ordinary, sometimes awkward (signed zero,
/// subnormal, extremes, values with long shortest forms).
fn value(rng: &mut StdRng) -> f64 {
    const AWKWARD: [f64; 8] = [-0.0, 5e-324, 1e-300, 1.7976931348623157e308, -1.0 / 3.0, 0.1 + 0.2, 1e21, 123.456];
    if rng.random_bool(0.2) {
        AWKWARD[rng.random_range(0..AWKWARD.len())]
    } else {
        (rng.random::<f64>() - 0.5) * 10f64.powi(rng.random_range(-6..7))
    }
}

fn positive(rng: &mut StdRng) -> f64 {
    let v = value(rng).abs();
    if v > 0.0 {
        v
    } else {
        1.5
    }
}

/// A random valid dataset: 0–3 scenes of 1–5 steps with ids anywhere in
/// `i64`, 0–3 objects each, points or boxes with empty cells, optional states
/// and actions.
fn random_dataset(rng: &mut StdRng) -> Dataset {
    let steps = rng.random_range(1..6);
    let kind = if rng.random_bool(0.5) { ObservationKind::Points } else { ObservationKind::Boxes };
    let meta = Meta { prior_from_detection: rng.random_bool(0.3), ..Meta::new(positive(rng), steps) };
    let mut b = Dataset::builder(meta, kind);
    let (states, actions) = (rng.random_bool(0.5), rng.random_bool(0.5));
    if states {
        b.with_states();
    }
    if actions {
        b.with_actions();
    }
    let mut scene_ids = HashSet::new();
    for _ in 0..rng.random_range(0..4) {
        let scene: i64 = if rng.random_bool(0.2) { rng.random() } else { rng.random_range(-5..20) };
        if !scene_ids.insert(scene) {
            continue;
        }
        let av: Vec<Pose> = (0..steps).map(|_| Pose { x: value(rng), y: value(rng), yaw: value(rng) }).collect();
        b.scene(scene, &av);
        let mut ids = HashSet::new();
        for _ in 0..rng.random_range(0..4) {
            let id: i64 = if rng.random_bool(0.2) { rng.random() } else { rng.random_range(-3..10) };
            if !ids.insert(id) {
                continue;
            }
            let state = |rng: &mut StdRng| State {
                x: value(rng),
                y: value(rng),
                yaw: value(rng),
                v: value(rng),
                kappa: value(rng),
            };
            let sd = State {
                x: positive(rng),
                y: positive(rng),
                yaw: positive(rng),
                v: positive(rng),
                kappa: positive(rng),
            };
            let prior = Prior { mean: state(rng), sd };
            b.object(Object { scene, id, length: positive(rng), width: positive(rng), prior });
            for t in 0..steps {
                match kind {
                    ObservationKind::Points => {
                        for _ in 0..rng.random_range(0..3) {
                            b.point(scene, id, t, [value(rng), value(rng)]);
                        }
                    }
                    ObservationKind::Boxes => {
                        if rng.random_bool(0.7) {
                            let d = BoxDetection {
                                x: value(rng),
                                y: value(rng),
                                yaw: value(rng),
                                length: positive(rng),
                                width: positive(rng),
                                score: value(rng),
                            };
                            b.detection(scene, id, t, d);
                        }
                    }
                }
                if states && rng.random_bool(0.8) {
                    b.state(scene, id, t, state(rng));
                }
                if actions && t >= 1 && rng.random_bool(0.8) {
                    b.action(scene, id, t, Action { accel: value(rng), pinch: value(rng) });
                }
            }
        }
    }
    b.build().expect("a random dataset is valid")
}

/// Whatever `Dataset::write` produces, `Dataset::read` reads back bit for bit
/// (`{:?}` tells -0.0 from 0.0), and the layout and shard readers agree with
/// the dataset read whole: 300 random datasets. With `SSM_FUZZ_SEED_DIR` set,
/// the first few are also written there as seeds of the `dataset` fuzz target.
#[test]
fn random_datasets_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let seeds = std::env::var_os("SSM_FUZZ_SEED_DIR");
    let mut rng = StdRng::seed_from_u64(77);
    let mut nonempty = 0;
    for case in 0..300 {
        let ds = random_dataset(&mut rng);
        let path = dir.path().join(format!("case{case}"));
        ds.write(&path).unwrap();
        let back = Dataset::read(&path).unwrap();
        assert_eq!(format!("{back:?}"), format!("{ds:?}"), "case {case}");
        assert_eq!(Dataset::read_layout(&path).unwrap(), ds.layout(), "case {case}");
        let picked: Vec<usize> = (0..ds.objects().len()).filter(|o| o % 2 == case % 2).collect();
        let keep: HashSet<(i64, i64)> = picked.iter().map(|&o| (ds.objects()[o].scene, ds.objects()[o].id)).collect();
        assert_eq!(Dataset::read_shard(&path, &keep).unwrap(), ds.shard(&picked), "case {case}");
        nonempty += usize::from(ds.objects().len() > 1);
        if let (Some(seeds), true) = (&seeds, case < 12) {
            ds.write(Path::new(seeds).join(format!("random-{case}"))).unwrap();
        }
        fs::remove_dir_all(&path).unwrap();
    }
    // The property is not vacuous: most cases have several objects.
    assert!(nonempty > 100, "{nonempty} cases with several objects");
}

/// A random store: 0–5 tensors of rank 0–3 with dimensions 0–4, names of any
/// characters; with `any_bits`, values of any bits (NaN payloads included).
fn random_store(rng: &mut StdRng, any_bits: bool) -> ParamStore<f64> {
    let mut store = ParamStore::new();
    for i in 0..rng.random_range(0..6) {
        let rank = rng.random_range(0..4);
        let shape: Vec<usize> = (0..rank).map(|_| rng.random_range(0..5)).collect();
        let n: usize = shape.iter().product();
        let data: Vec<f64> = (0..n).map(|_| if any_bits { f64::from_bits(rng.random()) } else { value(rng) }).collect();
        let name: String = (0..rng.random_range(0..8)).map(|_| rng.random::<char>()).collect();
        store.add(&format!("{i}{name}"), Tensor::new(&shape, data));
    }
    store
}

/// Bits of every value, for comparisons that NaN would defeat.
fn bits(store: &ParamStore<f64>) -> Vec<(String, Vec<usize>, Vec<u64>)> {
    store
        .iter()
        .map(|(n, v)| (n.to_string(), v.shape().to_vec(), v.data().iter().map(|x| x.to_bits()).collect()))
        .collect()
}

/// Whatever `ParamStore::save` writes, `ParamStore::load` reads back bit for
/// bit, and so do `from_bytes` of the same bytes: 300 random stores.
#[test]
fn random_parameter_files_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("params.bin");
    let mut rng = StdRng::seed_from_u64(78);
    for case in 0..300 {
        let store = random_store(&mut rng, true);
        store.save(&path).unwrap();
        assert_eq!(bits(&ParamStore::load(&path).unwrap()), bits(&store), "case {case}");
        assert_eq!(bits(&ParamStore::from_bytes(&fs::read(&path).unwrap()).unwrap()), bits(&store), "case {case}");
    }
}

/// Models written to a parameter file read back as the same models, for
/// random policies (hand-crafted or neural), both observation kinds, both box
/// offsets, and a random extension and drift where they apply: 60 cases.
#[test]
fn random_models_round_trip_through_a_parameter_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("params.bin");
    let mut rng = StdRng::seed_from_u64(79);
    for case in 0..60 {
        let kind = if rng.random_bool(0.5) { ObservationKind::Points } else { ObservationKind::Boxes };
        let policy = if rng.random_bool(0.5) {
            AnyPolicy::HandCrafted(HandCraftedPolicy::new(value(&mut rng), value(&mut rng)).unwrap())
        } else {
            AnyPolicy::Neural(NeuralPolicy::new(&mut rng))
        };
        let offsets = if rng.random_bool(0.5) { DetectionOffsets::Learned } else { DetectionOffsets::Zero };
        let mut models = Models::initial_with_offsets(kind, policy, rng.random(), offsets);
        let extensions = Extension::for_kind(kind);
        if rng.random_bool(0.6) && !extensions.is_empty() {
            let extension = extensions[rng.random_range(0..extensions.len())];
            let raw = extension.initial().data().iter().map(|_| value(&mut rng)).collect();
            models.extension = Some(FittedExtension { extension, raw });
        }
        if kind == ObservationKind::Boxes && rng.random_bool(0.5) {
            let n = ssm::models::drift::DetectorDrift::initial().numel();
            models.drift = Some((0..n).map(|_| value(&mut rng)).collect());
        }
        models.to_store().save(&path).unwrap();
        let back = Models::from_store(&ParamStore::load(&path).unwrap(), kind).unwrap();
        assert_eq!(back.policy, models.policy, "case {case}");
        assert_eq!(back.observation, models.observation, "case {case}");
        assert_eq!(back.observation_params, models.observation_params, "case {case}");
        assert_eq!(back.extension, models.extension, "case {case}");
        assert_eq!(back.drift, models.drift, "case {case}");
    }
}

/// Whatever `Checkpoint::save` writes, `Checkpoint::load` reads back equal:
/// 100 random checkpoints (random stores, optimiser states, settings, best
/// and averaged parameters).
#[test]
fn random_checkpoints_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("checkpoint.bin");
    let mut rng = StdRng::seed_from_u64(80);
    for case in 0..100 {
        let ckpt = checkpoint(&mut rng);
        ckpt.save(&path).unwrap();
        assert_eq!(Checkpoint::load(&path).unwrap(), ckpt, "case {case}");
    }
}

// ------------------------------------------------- minimised fuzz inputs

/// The minimised inputs the fuzz targets of `fuzz/` stopped on, one folder
/// per target, each fed through what its target does (`fuzz/fuzz_targets/`).
fn fuzz_inputs(target: &str) -> Vec<(String, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_inputs").join(target);
    let mut out: Vec<(String, Vec<u8>)> = fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| {
            let path = e.unwrap().path();
            (path.file_name().unwrap().to_string_lossy().into_owned(), fs::read(&path).unwrap())
        })
        .collect();
    out.sort();
    assert!(!out.is_empty(), "no inputs in {}", dir.display());
    out
}

/// A fuzz input as the `params` and `checkpoint` targets turn it into a file
/// (`ssm_fuzz::as_versioned_file`): an even first byte, the rest as it is; an
/// odd one, the rest framed as a file of `version` with its checksum.
fn as_versioned_file(data: &[u8], version: u32) -> Vec<u8> {
    match data.split_first() {
        None => Vec::new(),
        Some((first, rest)) if first & 1 == 0 => rest.to_vec(),
        Some((_, rest)) => framed(version, rest),
    }
}

/// What the `params` target does with an input: the store, then the models
/// for either kind and the synthetic data's true model.
fn params_target(data: &[u8]) -> Result<ParamStore<f64>, String> {
    let store =
        ParamStore::<f64>::from_bytes(&as_versioned_file(data, PARAM_FORMAT_VERSION)).map_err(|e| e.to_string())?;
    for kind in [ObservationKind::Points, ObservationKind::Boxes] {
        if let Ok(models) = Models::from_store(&store, kind) {
            let again = Models::from_store(&models.to_store(), kind).unwrap();
            assert_eq!(again.policy, models.policy);
        }
    }
    let _ = ssm::simulation::synthetic::TrueModel::from_store(store.clone());
    Ok(store)
}

/// What the `checkpoint` target does: the checkpoint, then a resumed run's
/// first optimiser step from it, whose step count must not wrap.
fn checkpoint_target(data: &[u8]) -> Result<Checkpoint, String> {
    let version = match data.first().map(|b| b >> 6) {
        Some(1) => 2,
        Some(2) => 3,
        _ => CHECKPOINT_VERSION,
    };
    let ckpt = Checkpoint::from_bytes(&as_versioned_file(data, version)).map_err(|e| e.to_string())?;
    let mut params = ckpt.params.clone();
    let grads: Vec<_> = params.values().iter().map(|v| Tensor::zeros(v.shape())).collect();
    let mut adam = ckpt.adam.clone();
    adam.step(&mut params, &grads).unwrap();
    assert!(adam.t >= ckpt.adam.t, "the step count wrapped from {} to {}", ckpt.adam.t, adam.t);
    Ok(ckpt)
}

/// The `params` target's crash: a store of more names than values, whose
/// `Models::from_store` indexed past the values.
#[test]
fn fuzz_params_inputs_are_errors() {
    for (name, data) in fuzz_inputs("params") {
        // The minimised input also holds a tensor of shape [2, 32] without
        // data, which the decoder now meets first.
        let err = params_target(&data).expect_err(&name);
        assert!(err.contains("parameter names for") || err.contains("tensor of shape"), "{name}: {err}");
    }
}

/// The `checkpoint` target's crashes: a step count of `u64::MAX`
/// (`step-overflow`: its increment overflowed, a panic with overflow checks,
/// without them a wrap to step 0, a bias correction of 0 and NaN parameters),
/// now read and stepped without a wrap; and two refused as they are decoded:
/// moments that did not fit the parameters (`moments`: the resumed run's first
/// step indexed past them; the minimised input's tensors also disagree with
/// their shapes, which the decoder now meets first, so the moments check is
/// tested on its own in `a_checkpoint_whose_parts_do_not_fit_is_refused`), and
/// a tensor of 10^19 elements by its shape without data (`shape-overflow`:
/// a buffer sized by the shape overflowed its capacity).
#[test]
fn fuzz_checkpoint_inputs_are_errors_or_resume() {
    for (name, data) in fuzz_inputs("checkpoint") {
        let read = checkpoint_target(&data);
        if name.starts_with("step-overflow") {
            assert_eq!(read.expect(&name).adam.t, u64::MAX, "{name}");
            continue;
        }
        let err = read.expect_err(&name);
        assert!(err.contains("corrupt") && err.contains("tensor of shape"), "{name}: {err}");
    }
}
