//! Timing of the observation models' hot paths (ignored by default; run with
//! `cargo test --release -p ssm --test integration observation_timing -- --ignored --nocapture`).
//! Prints medians: the filter's f32 point log-likelihood for 1024 particles x 20
//! points on one thread (SPEC §10's inner loop), its network part hand-written vs
//! on a non-recording tape with a GEMM, the box model, and the fused tape path.

use std::time::{Duration, Instant};

use autodiff::nn::ParamStore;
use autodiff::{Parallelism, Tape, Tensor};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::data::Pose;
use ssm::models::observation::{
    av_features, BoxObservationModel, ObsContext, ObservationModel, PointObservationModel, PosesRef, RowVars, Scratch,
};

fn median(mut f: impl FnMut(), reps: usize) -> Duration {
    f();
    let mut t: Vec<Duration> = (0..reps)
        .map(|_| {
            let c = Instant::now();
            f();
            c.elapsed()
        })
        .collect();
    t.sort();
    t[reps / 2]
}

fn particles(n: usize, rng: &mut StdRng) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    (
        (0..n).map(|_| 20.0 + rng.random_range(-1.0..1.0f32)).collect(),
        (0..n).map(|_| 5.0 + rng.random_range(-1.0..1.0f32)).collect(),
        (0..n).map(|_| 0.3 + rng.random_range(-0.2..0.2f32)).collect(),
    )
}

#[test]
#[ignore]
fn observation_hot_paths() {
    let mut rng = StdRng::seed_from_u64(0);
    let mut store = ParamStore::new();
    let model = PointObservationModel::init_params(&mut store, "obs", &mut rng);
    let s32 = store.cast::<f32>();
    let ctx = ObsContext::new(Pose { x: 0.0, y: 0.0, yaw: 0.1 }, 4.5, 1.9);
    let n = 1024;
    let (xs, ys, yaws) = particles(n, &mut rng);
    let mut pts = Vec::new();
    model.sample(&store, &ctx, Pose { x: 20.0, y: 5.0, yaw: 0.3 }, 20, &mut rng, &mut pts);
    let poses = PosesRef::new(&xs, &ys, &yaws);
    let mut scratch = Scratch::new();
    let mut out = vec![0.0f32; n];
    let reps = 2001;
    let full = median(|| model.log_likelihood(&s32, &ctx, poses, &pts, &mut scratch, &mut out), reps);
    let one = median(|| model.log_likelihood(&s32, &ctx, poses, &pts[..1], &mut scratch, &mut out), reps);
    let per_point = (full - one) / 19;
    println!("point model, f32, {n} particles x 20 points, 1 thread: {full:?} (network + head ~{:?}, {:?} per point = {:.2} ns per particle-point)",
        one.saturating_sub(per_point), per_point, per_point.as_nanos() as f64 / n as f64);

    // The network alone on a fresh non-recording tape (the alternative to the
    // feature-major GEMM path inside `log_likelihood`).
    let mut feats = vec![0.0f32; 7 * n];
    av_features(&ctx, poses, &mut feats);
    let rows: Vec<f32> = (0..n * 7).map(|k| feats[(k % 7) * n + k / 7]).collect();
    let tape_net = median(
        || {
            let tape = Tape::<f32>::no_record().with_parallelism(Parallelism::Serial);
            let p = s32.bind(&tape);
            let x = tape.constant(Tensor::new(&[n, 7], rows.clone()));
            std::hint::black_box(model.mlp().forward(&p, x).to_tensor());
        },
        reps,
    );
    println!(
        "network 7-16x4-12 alone for {n} particles on a no-record tape: {tape_net:?} (vs network + head + 1 point \
         in log_likelihood: {one:?})"
    );

    // Box model: one detection.
    let mut bstore = ParamStore::new();
    let boxes = BoxObservationModel::init_params(&mut bstore, "boxes", &mut rng);
    let b32 = bstore.cast::<f32>();
    let mut dets = Vec::new();
    boxes.sample(&bstore, &ctx, Pose { x: 20.0, y: 5.0, yaw: 0.3 }, 1, &mut rng, &mut dets);
    let bt = median(|| boxes.log_likelihood(&b32, &ctx, poses, &dets, &mut scratch, &mut out), reps);
    println!("box model, f32, {n} particles x 1 detection, 1 thread: {bt:?}");

    // Fused tape path: R rows x 20 points, forward + backward (f32, one thread), and
    // the network alone on the tape (features -> MLP -> sum, forward + backward) to
    // separate the fused kernel's share.
    let r = 20_000;
    let (rx, ry, ryaw) = particles(r, &mut rng);
    let len = vec![4.5f32; r];
    let wid = vec![1.9f32; r];
    let av = vec![ctx.av; r];
    let items: Vec<&[[f64; 2]]> = vec![&pts[..]; r];
    let serial = || Tape::<f32>::new().with_parallelism(Parallelism::Serial);
    let full = median(
        || {
            let tape = serial();
            let p = s32.bind(&tape);
            let rv = RowVars::constant(&tape, &rx, &ry, &ryaw, &len, &wid);
            let v = model.log_likelihood_rows(&p, &rv, &av, &items);
            std::hint::black_box(p.gradients(&tape.backward(v.sum())));
        },
        11,
    );
    let net_only = median(
        || {
            let tape = serial();
            let p = s32.bind(&tape);
            let rv = RowVars::constant(&tape, &rx, &ry, &ryaw, &len, &wid);
            let o = model.mlp().forward(&p, ssm::models::observation::av_features_on_tape(&rv, &av));
            std::hint::black_box(p.gradients(&tape.backward(o.sum())));
        },
        11,
    );
    let value_only = median(
        || {
            let tape = Tape::<f32>::no_record().with_parallelism(Parallelism::Serial);
            let p = s32.bind(&tape);
            let rv = RowVars::constant(&tape, &rx, &ry, &ryaw, &len, &wid);
            std::hint::black_box(model.log_likelihood_rows(&p, &rv, &av, &items).to_tensor());
        },
        11,
    );
    let per = |d: Duration| d.as_nanos() as f64 / (r * 20) as f64;
    println!(
        "point model rows on the tape, f32, 1 thread, {r} rows x 20 points: forward + backward {full:?} \
         ({:.1} ns per row-point); of which the network on the tape {net_only:?}, so the fused kernel and head \
         ~{:.1} ns per row-point; value only (no-record tape) {value_only:?}",
        per(full),
        per(full.saturating_sub(net_only))
    );
}
