//! AV-relative features: known geometry, invariance to moving and turning the whole
//! scene, the batched (f32, f64), single-pose and tape computations against each
//! other, and the tape's gradients against finite differences.

use autodiff::gradcheck::GradCheck;
use autodiff::{Tape, Tensor};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::data::Pose;
use ssm::models::observation::{av_features, av_features_on_tape, av_features_one, ObsContext, PosesRef, RowVars};

fn random_case(rng: &mut StdRng) -> (ObsContext, Pose) {
    let av =
        Pose { x: rng.random_range(-50.0..50.0), y: rng.random_range(-50.0..50.0), yaw: rng.random_range(-4.0..4.0) };
    let r = rng.random_range(5.0..50.0);
    let b: f64 = rng.random_range(-4.0..4.0);
    let pose = Pose { x: av.x + r * b.cos(), y: av.y + r * b.sin(), yaw: rng.random_range(-7.0..7.0) };
    (ObsContext::new(av, rng.random_range(3.0..6.0), rng.random_range(1.5..2.5)), pose)
}

#[test]
fn known_geometry() {
    let ctx = ObsContext::new(Pose { x: 1.0, y: 2.0, yaw: std::f64::consts::FRAC_PI_2 }, 4.0, 2.0);
    // Object 20 m to the AV's left (world +x is the AV's right when it faces +y),
    // facing the AV: world direction of the AV from the object is -x... place it at
    // world (1, 22): straight ahead of an AV facing +y.
    let f = av_features_one(&ctx, Pose { x: 1.0, y: 22.0, yaw: 0.0 });
    let close = |a: f64, b: f64| (a - b).abs() < 1e-6;
    assert!(close(f[0], 20.0 / 50.0), "{f:?}");
    assert!(close(f[1], 0.0) && close(f[2], 1.0), "ahead of the AV: {f:?}");
    // The object faces +x; the AV is at world -y from it, i.e. to its right.
    assert!(close(f[3], -1.0) && close(f[4], 0.0), "AV to the object's right: {f:?}");
    assert!(close(f[5], 0.8) && close(f[6], 1.0));
    // Object to the AV's left (world -x of an AV facing +y), facing the AV.
    let f = av_features_one(&ctx, Pose { x: -9.0, y: 2.0, yaw: 0.0 });
    assert!(close(f[1], 1.0) && close(f[2], 0.0), "left of the AV: {f:?}");
    assert!(close(f[3], 0.0) && close(f[4], 1.0), "AV straight ahead of the object: {f:?}");
}

#[test]
fn invariant_to_moving_and_turning_the_scene() {
    let mut rng = StdRng::seed_from_u64(1);
    for _ in 0..50 {
        let (ctx, pose) = random_case(&mut rng);
        let f = av_features_one(&ctx, pose);
        let (tx, ty, rot) =
            (rng.random_range(-100.0..100.0), rng.random_range(-100.0..100.0), rng.random_range(-3.0..3.0f64));
        let move_pose = |p: Pose| Pose {
            x: tx + rot.cos() * p.x - rot.sin() * p.y,
            y: ty + rot.sin() * p.x + rot.cos() * p.y,
            yaw: p.yaw + rot,
        };
        let ctx2 = ObsContext { av: move_pose(ctx.av), ..ctx };
        let g = av_features_one(&ctx2, move_pose(pose));
        for k in 0..7 {
            assert!((f[k] - g[k]).abs() < 1e-9, "feature {k}: {} vs {}", f[k], g[k]);
        }
        // Unit vectors up to the range smoothing: |.|^2 = 1 - RANGE_EPS^2 / r^2 >= 1 - 4e-6 at 5 m.
        assert!((f[1] * f[1] + f[2] * f[2] - 1.0).abs() < 5e-6 && (f[3] * f[3] + f[4] * f[4] - 1.0).abs() < 5e-6);
    }
}

#[test]
fn batched_single_and_tape_agree() {
    let mut rng = StdRng::seed_from_u64(2);
    let (ctx, _) = random_case(&mut rng);
    let n = 33;
    let poses: Vec<Pose> = (0..n).map(|_| random_case(&mut rng).1).collect();
    let xs: Vec<f64> = poses.iter().map(|p| p.x).collect();
    let ys: Vec<f64> = poses.iter().map(|p| p.y).collect();
    let yaws: Vec<f64> = poses.iter().map(|p| p.yaw).collect();
    let mut batched = vec![0.0; 7 * n];
    av_features(&ctx, PosesRef::new(&xs, &ys, &yaws), &mut batched);
    let (x32, y32, w32): (Vec<f32>, Vec<f32>, Vec<f32>) = (
        xs.iter().map(|&v| v as f32).collect(),
        ys.iter().map(|&v| v as f32).collect(),
        yaws.iter().map(|&v| v as f32).collect(),
    );
    let mut batched32 = vec![0.0f32; 7 * n];
    av_features(&ctx, PosesRef::new(&x32, &y32, &w32), &mut batched32);
    let tape = Tape::<f64>::new();
    let ctxs = vec![ctx; n];
    let rows = RowVars::from_poses(&tape, &poses, &ctxs);
    let av: Vec<Pose> = ctxs.iter().map(|c| c.av).collect();
    let on_tape = av_features_on_tape(&rows, &av).to_tensor();
    assert_eq!(on_tape.shape(), &[n, 7]);
    for (i, p) in poses.iter().enumerate() {
        let single = av_features_one(&ctx, *p);
        for k in 0..7 {
            let b = batched[k * n + i];
            assert!((single[k] - b).abs() < 1e-12, "batched vs single");
            assert!((on_tape.at(&[i, k]) - b).abs() < 1e-12, "tape vs batched");
            // f32: inputs rounded to ~4e-6 m at 50 m, over ranges >= 5 m.
            assert!((batched32[k * n + i] as f64 - b).abs() < 2e-6, "f32 feature {k}: {} vs {b}", batched32[k * n + i]);
        }
    }
}

#[test]
fn tape_gradients_match_finite_differences() {
    let mut rng = StdRng::seed_from_u64(3);
    let n = 5;
    let cases: Vec<(ObsContext, Pose)> = (0..n).map(|_| random_case(&mut rng)).collect();
    let av: Vec<Pose> = cases.iter().map(|c| c.0.av).collect();
    let col = |f: &dyn Fn(&(ObsContext, Pose)) -> f64| Tensor::from_vec(cases.iter().map(f).collect::<Vec<f64>>());
    let inputs = [col(&|c| c.1.x), col(&|c| c.1.y), col(&|c| c.1.yaw), col(&|c| c.0.length), col(&|c| c.0.width)];
    let weights = Tensor::new(&[n, 7], (0..7 * n).map(|_| rng.random_range(-1.0..1.0)).collect());
    let report = GradCheck::default()
        .check(
            |tape, v| {
                let rows = RowVars { x: v[0], y: v[1], yaw: v[2], length: v[3], width: v[4] };
                (av_features_on_tape(&rows, &av) * tape.constant(weights.clone())).sum()
            },
            &inputs,
        )
        .unwrap();
    assert!(report.comparisons == 25, "{report:?}");
}
