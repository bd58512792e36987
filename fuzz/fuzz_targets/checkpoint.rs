//! The checkpoint reader ([`Checkpoint::from_bytes`], this format version and
//! the two it carries over). The first byte chooses how the rest becomes a
//! file, as in the `params` target; the version is this one or an older.
#![no_main]
use libfuzzer_sys::fuzz_target;
use ssm::training::{Checkpoint, CHECKPOINT_VERSION};

fuzz_target!(|data: &[u8]| {
    let version = match data.first().map(|b| b >> 6) {
        Some(1) => 2,
        Some(2) => 3,
        _ => CHECKPOINT_VERSION,
    };
    let bytes = ssm_fuzz::as_versioned_file(data, version);
    let Ok(ckpt) = Checkpoint::from_bytes(&bytes) else { return };
    let _ = ckpt.config.differences(&ssm::training::TrainConfig::default());
    let _ = ckpt.params.check_same_layout(&ckpt.params);
    // What a resumed run does first: an optimiser step from the saved state.
    let mut params = ckpt.params.clone();
    let grads: Vec<_> = params.values().iter().map(|v| autodiff::Tensor::zeros(v.shape())).collect();
    let _ = ckpt.adam.clone().step(&mut params, &grads);
});
