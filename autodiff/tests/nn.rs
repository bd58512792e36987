//! Whole-model checks of the building blocks: an MLP feeding a Gaussian-mixture
//! log-density is differentiated end to end and checked against finite differences;
//! parameter files round-trip and reject corruption; Adam trains a small regression.

use autodiff::dist::{mixture_logpdf, normal_logpdf};
use autodiff::gradcheck::GradCheck;
use autodiff::nn::{Activation, Mlp, ParamError, ParamStore};
use autodiff::optim::{clip_global_norm, Adam};
use autodiff::{Tape, Tensor, Var};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

const COMPONENTS: usize = 3;

/// log p(y | x) of a K-component 1-D Gaussian mixture whose logits, means and log
/// standard deviations come from an MLP, summed over the batch.
fn mixture_nll<'t>(
    mlp: &Mlp,
    params: &autodiff::nn::BoundParams<'t, f64>,
    x: Var<'t, f64>,
    y: Var<'t, f64>,
) -> Var<'t, f64> {
    let out = mlp.forward(params, x); // [B, 3K]
    let logits = out.slice(1, 0, COMPONENTS);
    let mu = out.slice(1, COMPONENTS, COMPONENTS);
    let log_sd = out.slice(1, 2 * COMPONENTS, COMPONENTS);
    // y: [B, 1] broadcasts over the components.
    mixture_logpdf(logits, normal_logpdf(y, mu, log_sd), 1).sum().neg()
}

fn batch(rng: &mut StdRng, b: usize) -> (Tensor<f64>, Tensor<f64>) {
    let x: Vec<f64> = (0..b * 2).map(|_| rng.random_range(-1.0..1.0)).collect();
    let y: Vec<f64> = (0..b).map(|i| (3.0 * x[2 * i]).sin() + 0.5 * x[2 * i + 1]).collect();
    (Tensor::new(&[b, 2], x), Tensor::new(&[b, 1], y))
}

#[test]
fn mlp_mixture_density_gradient_matches_finite_differences() {
    let mut rng = StdRng::seed_from_u64(11);
    let mut store = ParamStore::new();
    let mlp = Mlp::new(&mut store, "net", &[2, 8, 8, 3 * COMPONENTS], Activation::Tanh, Activation::Identity, &mut rng);
    let (x, y) = batch(&mut rng, 16);
    let report = GradCheck::default()
        .check_params(&store, |tape, p| mixture_nll(&mlp, p, tape.constant(x.clone()), tape.constant(y.clone())))
        .unwrap_or_else(|e| panic!("{e}"));
    // Every one of the 179 parameters compared coordinate by coordinate.
    assert_eq!(report.comparisons, store.num_scalars());
    assert!(report.max_rel_error < 1e-6, "max relative error {}", report.max_rel_error);
}

#[test]
fn relu_mlp_gradient_matches_finite_differences() {
    let mut rng = StdRng::seed_from_u64(5);
    let mut store = ParamStore::new();
    let mlp = Mlp::new(&mut store, "pol", &[2, 32, 32, 5], Activation::Relu, Activation::Identity, &mut rng);
    assert_eq!(mlp.num_params(), 2 * 32 + 32 + 32 * 32 + 32 + 32 * 5 + 5);
    let (x, _) = batch(&mut rng, 8);
    // The 32x32 layer exceeds the per-coordinate limit and is checked along random
    // directions. ReLU is piecewise linear: a step must not carry a pre-activation across
    // its kink, so this check uses a small step (pre-activations here are O(0.1..1)).
    let report = GradCheck { step: 1e-6, ..GradCheck::default() }
        .check_params(&store, |tape, p| mlp.forward(p, tape.constant(x.clone())).softplus().sum())
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(report.max_rel_error < 1e-6);
}

#[test]
fn wrong_gradient_is_caught() {
    // A function whose recorded graph is cut (detach) must fail the check.
    let x = Tensor::new(&[2], vec![0.4, -0.3]);
    let err = GradCheck::default().check(|_, v| (v[0].detach() * v[0]).sum(), &[x]);
    assert!(matches!(err, Err(autodiff::gradcheck::GradCheckError::Mismatch { .. })), "{err:?}");
}

#[test]
fn parameter_files_round_trip_and_reject_corruption() {
    let dir = std::env::temp_dir().join(format!("autodiff-nn-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("params.bin");
    let mut rng = StdRng::seed_from_u64(1);
    let mut store = ParamStore::<f32>::new();
    Mlp::new(&mut store, "obs", &[7, 16, 12], Activation::Tanh, Activation::Identity, &mut rng);
    store.save(&path).unwrap();
    assert_eq!(ParamStore::<f32>::load(&path).unwrap(), store);

    // Flip one payload byte: the checksum catches it.
    let mut bytes = std::fs::read(&path).unwrap();
    let last = bytes.len() - 3;
    bytes[last] ^= 0x40;
    std::fs::write(&path, &bytes).unwrap();
    let err = ParamStore::<f32>::load(&path).unwrap_err();
    assert!(matches!(err, ParamError::Corrupt { .. }) && err.to_string().contains("checksum"), "{err}");

    // Truncation and foreign files are named as such, with the path.
    std::fs::write(&path, &bytes[..10]).unwrap();
    let err = ParamStore::<f32>::load(&path).unwrap_err();
    assert!(err.to_string().contains("params.bin") && err.to_string().contains("bad header"), "{err}");
    let err = ParamStore::<f32>::load(&dir.join("missing.bin")).unwrap_err();
    assert!(matches!(err, ParamError::Io { .. }));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn adam_with_clipping_fits_a_regression() {
    let mut rng = StdRng::seed_from_u64(3);
    let mut store = ParamStore::<f64>::new();
    let mlp = Mlp::new(&mut store, "net", &[2, 16, 1], Activation::Tanh, Activation::Identity, &mut rng);
    let (x, y) = batch(&mut rng, 64);
    let loss_at = |store: &ParamStore<f64>| {
        let tape = Tape::no_record();
        let p = store.bind(&tape);
        (mlp.forward(&p, tape.constant(x.clone())) - tape.constant(y.clone())).square().mean().item()
    };
    let initial = loss_at(&store);
    let mut adam = Adam::new(0.02);
    let mut tape = Tape::new();
    for _ in 0..400 {
        let mut grads = {
            let p = store.bind(&tape);
            let loss = (mlp.forward(&p, tape.constant(x.clone())) - tape.constant(y.clone())).square().mean();
            p.gradients(&tape.backward(loss))
        };
        clip_global_norm(&mut grads, 1.0);
        adam.step(&mut store, &grads).unwrap();
        tape.reset();
    }
    let fitted = loss_at(&store);
    // The target is smooth and noise-free: a 16-unit net reduces the error tenfold.
    assert!(fitted < initial / 10.0, "loss {initial} -> {fitted}");
}
