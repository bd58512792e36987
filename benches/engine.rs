//! Engine benchmark on the PF-SEFI-shaped workload: an MLP 7 -> 16 -> 16 -> 16 -> 16
//! -> 12 (tanh) over 102,400 rows (1,024 particles x 100 objects), reduced to a
//! weighted scalar, in f32 and f64. Prints medians of forward without a tape,
//! forward with a tape, forward+backward, their ratio (target <= 3), achieved
//! GEMM GFLOP/s against a rough peak, and the speed-up from using both cores.
//!
//! Run: `cargo bench --bench engine` (add `-- --quick` for fewer repetitions, `-- f32`
//! for one element type).

use std::time::Instant;

use autodiff::nn::{Activation, Mlp, ParamStore};
use autodiff::{Float, Tape, Tensor};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

const ROWS: usize = 102_400;
const SIZES: [usize; 6] = [7, 16, 16, 16, 16, 12];
/// Rough peak per core, flops per cycle: 2 AVX-512 FMA units x 16 f32 lanes x 2.
const F32_FLOPS_PER_CYCLE: f64 = 64.0;
/// Nominal clock of this machine (lscpu), GHz.
const CLOCK_GHZ: f64 = 2.3;

struct Workload<F: Float> {
    store: ParamStore<F>,
    mlp: Mlp,
    x: Tensor<F>,
    w: Tensor<F>,
}

fn workload<F: Float>() -> Workload<F> {
    let mut rng = StdRng::seed_from_u64(42);
    let mut store = ParamStore::new();
    let mlp = Mlp::new(&mut store, "obs", &SIZES, Activation::Tanh, Activation::Tanh, &mut rng);
    let x = Tensor::new(
        &[ROWS, SIZES[0]],
        (0..ROWS * SIZES[0]).map(|_| F::from_f64(rng.random_range(-1.0..1.0))).collect(),
    );
    let w = Tensor::new(&[ROWS, 1], (0..ROWS).map(|_| F::from_f64(rng.random_range(0.0..1.0))).collect());
    Workload { store, mlp, x, w }
}

/// Multiply-add flops of the forward GEMMs.
fn forward_flops() -> f64 {
    2.0 * ROWS as f64 * SIZES.windows(2).map(|p| (p[0] * p[1]) as f64).sum::<f64>()
}

/// What a timed run does: the forward pass without a tape, on a recording tape,
/// or on a recording tape followed by the backward pass.
#[derive(Clone, Copy)]
enum Pass {
    Untaped,
    Taped,
    Backward,
}

fn run_once<F: Float>(wl: &Workload<F>, tape: &mut Tape<F>, pass: Pass) -> f64 {
    tape.reset();
    let params = wl.store.bind(tape);
    let x = tape.constant(wl.x.clone());
    let w = tape.constant(wl.w.clone());
    let loss = (wl.mlp.forward(&params, x) * w).sum();
    let v = loss.item().to_f64();
    if let Pass::Backward = pass {
        let g = tape.backward(loss);
        std::hint::black_box(params.gradients(&g));
    }
    v
}

fn median_seconds<F: Float>(wl: &Workload<F>, pass: Pass, reps: usize) -> f64 {
    let mut tape = match pass {
        Pass::Untaped => Tape::no_record(),
        _ => Tape::new(),
    };
    run_once(wl, &mut tape, pass); // warm-up (fills the buffer pool)
    let mut times: Vec<f64> = (0..reps)
        .map(|_| {
            let t = Instant::now();
            std::hint::black_box(run_once(wl, &mut tape, pass));
            t.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(|a, b| a.partial_cmp(b).expect("finite times"));
    times[reps / 2]
}

fn report<F: Float>(reps: usize) {
    let wl = workload::<F>();
    let cores = rayon::current_num_threads();
    let fwd = median_seconds(&wl, Pass::Untaped, reps);
    let fwd_tape = median_seconds(&wl, Pass::Taped, reps);
    let fb = median_seconds(&wl, Pass::Backward, reps);
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("pool");
    let fb1 = one.install(|| median_seconds(&wl, Pass::Backward, reps));
    let fwd1 = one.install(|| median_seconds(&wl, Pass::Untaped, reps));
    // Backward GEMMs: weight gradients for every layer, input gradients for all but the first.
    let ff = forward_flops();
    let bf = 2.0 * ff - 2.0 * ROWS as f64 * (SIZES[0] * SIZES[1]) as f64;
    let lanes_factor = if F::NAME == "f32" { 1.0 } else { 0.5 };
    let peak = cores as f64 * CLOCK_GHZ * F32_FLOPS_PER_CYCLE * lanes_factor;
    println!("\n{} ({} rows, MLP {:?} tanh, weighted sum; median of {reps}, {cores} threads)", F::NAME, ROWS, SIZES);
    println!("  forward, no tape        {:8.2} ms", fwd * 1e3);
    println!("  forward, with tape      {:8.2} ms", fwd_tape * 1e3);
    println!("  forward + backward      {:8.2} ms", fb * 1e3);
    println!("  (fwd+bwd) / fwd no tape {:8.2}   (target <= 3)", fb / fwd);
    println!(
        "  GEMM GFLOP/s (fwd+bwd)  {:8.1}   ({:.1}% of rough peak {:.0} GFLOP/s = {cores} cores x {CLOCK_GHZ} GHz x {} flops/cycle)",
        (ff + bf) / fb / 1e9,
        100.0 * (ff + bf) / fb / 1e9 / peak,
        peak,
        F32_FLOPS_PER_CYCLE * lanes_factor
    );
    println!(
        "  1 thread: fwd {:.2} ms, fwd+bwd {:.2} ms -> speed-up on {cores} threads: fwd {:.2}x, fwd+bwd {:.2}x",
        fwd1 * 1e3,
        fb1 * 1e3,
        fwd1 / fwd,
        fb1 / fb
    );
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let reps = if quick { 5 } else { 21 };
    println!("autodiff engine benchmark: {}", if quick { "quick" } else { "full" });
    // `-- f32` or `-- f64` runs one element type only.
    let only = |name: &str| !std::env::args().any(|a| a == "f32" || a == "f64") || std::env::args().any(|a| a == name);
    if only("f32") {
        report::<f32>(reps);
    }
    if only("f64") {
        report::<f64>(reps);
    }
}
