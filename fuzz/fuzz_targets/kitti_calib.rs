//! The KITTI importer with arbitrary bytes as the calib file of a sequence
//! whose other files are valid (`ssm_fuzz::KITTI_BASE`).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    ssm_fuzz::kitti_one_file(3, data);
});
