//! The parameter-file reader ([`ParamStore::from_bytes`]) and what reads a
//! model out of a store ([`Models::from_store`], for both observation kinds).
//! The first byte chooses how the rest becomes a file: as it is (so the magic,
//! version and checksum checks are exercised), or behind a valid header with
//! its checksum (so the fuzzer reaches the decoding of the payload).
#![no_main]
use autodiff::nn::ParamStore;
use libfuzzer_sys::fuzz_target;
use ssm::data::ObservationKind;
use ssm::models::params::Models;

fuzz_target!(|data: &[u8]| {
    let bytes = ssm_fuzz::as_versioned_file(data, autodiff::nn::PARAM_FORMAT_VERSION);
    let Ok(store) = ParamStore::<f64>::from_bytes(&bytes) else { return };
    // What `sefi` does with a parameter file.
    for kind in [ObservationKind::Points, ObservationKind::Boxes] {
        if let Ok(models) = Models::from_store(&store, kind) {
            let again = Models::from_store(&models.to_store(), kind).expect("a store read reads back");
            assert_eq!(again.policy, models.policy);
        }
    }
    let _ = ssm::simulation::synthetic::TrueModel::from_store(store.clone());
    let _ = store.num_scalars();
    let _ = store.cast::<f32>();
});
