//! `sefi import-kitti`: writes the KITTI tracking sequences as box-detection
//! datasets (train and val split) and prints the import report.

use std::path::Path;

use ssm::data::{import_kitti, KittiOptions};

use crate::output::{ensure_dir, write_atomic};

/// Imports `root` with `options` into `out/train` and `out/val`, and writes
/// `out/import_report.md`.
pub fn kitti(root: &Path, out: &Path, options: &KittiOptions) -> Result<(), String> {
    let import = import_kitti(root, options).map_err(|e| e.to_string())?;
    ensure_dir(out)?;
    for (name, dataset) in [("train", &import.train), ("val", &import.val)] {
        let dir = out.join(name);
        dataset.write(&dir).map_err(|e| e.to_string())?;
        println!(
            "{name}: {} scenes, {} objects, {} steps each -> {}",
            dataset.scenes().len(),
            dataset.objects().len(),
            dataset.steps(),
            dir.display()
        );
    }
    let report = import.report.to_string();
    println!("{report}");
    write_atomic(&out.join("import_report.md"), report.as_bytes())
}
