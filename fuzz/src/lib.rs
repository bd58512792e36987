//! Shared pieces of the fuzz targets: a scratch directory per process for the
//! readers that take a directory, the splitting of one input into the files
//! of a dataset, and the fixed KITTI sequence the KITTI targets vary one file of.

use std::path::{Path, PathBuf};

/// A directory of this process, emptied of the names it is asked to write;
/// in `/dev/shm` when there is one (no disk traffic per execution).
pub fn scratch(name: &str) -> PathBuf {
    let base = Path::new("/dev/shm");
    let base = if base.is_dir() { base.to_path_buf() } else { std::env::temp_dir() };
    let dir = base.join(format!("ssm-fuzz-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("scratch directory");
    dir
}

/// The dataset files of a fuzz input, in this order, separated by NUL bytes;
/// an empty section is an absent file.
pub const DATASET_FILES: [&str; 7] =
    ["meta.json", "av.csv", "objects.csv", "points.csv", "boxes.csv", "states.csv", "actions.csv"];

/// Writes the sections of `data` (see [`DATASET_FILES`]) into `dir`, removing
/// the files of empty or missing sections.
pub fn write_dataset_files(dir: &Path, data: &[u8]) {
    let mut sections = data.split(|&b| b == 0);
    for name in DATASET_FILES {
        let path = dir.join(name);
        match sections.next() {
            Some(s) if !s.is_empty() => std::fs::write(&path, s).expect("write scratch file"),
            _ => {
                let _ = std::fs::remove_file(&path);
            }
        }
    }
}

/// The four files of a KITTI sequence, relative to the KITTI root, for sequence 0.
pub const KITTI_FILES: [&str; 4] =
    ["label_02/0000.txt", "det_pointrcnn/Car/0000.txt", "ego_pose_orbslam3/0000.txt", "calib/0000.txt"];

/// The first 20 frames of KITTI sequence 0000 (labels, detections, poses,
/// calibration), the fixed files of the KITTI targets.
pub const KITTI_BASE: [&str; 4] = [
    include_str!("../kitti-base/label_02/0000.txt"),
    include_str!("../kitti-base/det_pointrcnn/Car/0000.txt"),
    include_str!("../kitti-base/ego_pose_orbslam3/0000.txt"),
    include_str!("../kitti-base/calib/0000.txt"),
];

/// Imports the KITTI sequence whose file `which` (an index into
/// [`KITTI_FILES`]) is `data` and whose other files are [`KITTI_BASE`], with
/// short windows (so the 20 frames make scenes) at two strides.
pub fn kitti_one_file(which: usize, data: &[u8]) {
    let root = scratch("kitti");
    for (i, name) in KITTI_FILES.iter().enumerate() {
        let path = root.join(name);
        std::fs::create_dir_all(path.parent().expect("has a folder")).expect("scratch folder");
        let bytes = if i == which { data } else { KITTI_BASE[i].as_bytes() };
        std::fs::write(path, bytes).expect("write scratch file");
    }
    for (steps, stride, align) in [(5, 1, 1), (3, 2, 2)] {
        let options = ssm::data::KittiOptions {
            steps,
            stride,
            align,
            sequences: Some(vec![0]),
            val_sequences: Some(vec![]),
            ..ssm::data::KittiOptions::default()
        };
        if let Ok(import) = ssm::data::import_kitti(&root, &options) {
            // What the importer builds is a valid dataset: it writes and reads back.
            let out = root.join("out");
            import.train.write(&out).expect("an imported dataset writes");
            let back = ssm::data::Dataset::read(&out).expect("an imported dataset reads back");
            assert_eq!(back, import.train);
        }
    }
}

/// The first bytes of every file `autodiff::nn::write_versioned` writes.
const MAGIC: &[u8; 8] = b"PFSEFI\x00\x01";

/// A versioned file from a fuzz input: if the first byte is even, the rest
/// as it is; if odd, the rest as the payload behind a valid header of
/// `version` with its checksum (FNV-1a, as `write_versioned` computes it), so
/// that mutations reach the decoder rather than stop at the checksum.
pub fn as_versioned_file(data: &[u8], version: u32) -> Vec<u8> {
    let Some((&first, rest)) = data.split_first() else { return Vec::new() };
    if first & 1 == 0 {
        return rest.to_vec();
    }
    let sum = rest.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3));
    let mut bytes = Vec::with_capacity(rest.len() + 20);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&version.to_le_bytes());
    bytes.extend_from_slice(&sum.to_le_bytes());
    bytes.extend_from_slice(rest);
    bytes
}
