//! The dataset reader with arbitrary bytes as a dataset folder's files
//! (`meta.json` and each CSV, split by NUL bytes: `ssm_fuzz::DATASET_FILES`).
//! Beyond not panicking, a dataset that reads must also read as the same
//! layout ([`Dataset::read_layout`]), as the same shard ([`Dataset::read_shard`]),
//! and back after a write.
#![no_main]
use libfuzzer_sys::fuzz_target;
use ssm::data::Dataset;
use std::collections::HashSet;

fuzz_target!(|data: &[u8]| {
    let dir = ssm_fuzz::scratch("dataset");
    ssm_fuzz::write_dataset_files(&dir, data);
    let read = Dataset::read(&dir);
    let layout = Dataset::read_layout(&dir);
    let Ok(ds) = read else { return };
    assert_eq!(layout.expect("a dataset that reads has a layout"), ds.layout());
    // Every other object: one process's share of a two-process job.
    let picked: Vec<usize> = (0..ds.objects().len()).step_by(2).collect();
    let keep: HashSet<(i64, i64)> = picked.iter().map(|&o| (ds.objects()[o].scene, ds.objects()[o].id)).collect();
    let shard = Dataset::read_shard(&dir, &keep).expect("a dataset that reads reads in shards");
    assert_eq!(shard, ds.shard(&picked));
    let out = dir.join("out");
    ds.write(&out).expect("a dataset that reads writes");
    assert_eq!(Dataset::read(&out).expect("a written dataset reads back"), ds);
});
