//! Reductions and the fused log-sum-exp family: sum, mean, sum_axis, mean_axis,
//! logsumexp, softmax and log_softmax along every axis of a 3-D tensor (keepdim both
//! ways), checked against finite differences in f64 and against direct computation;
//! then their behaviour on `-inf` entries and on lanes that are entirely `-inf`.

use crate::common::*;
use autodiff::{Tape, Tensor};

const SHAPE: [usize; 3] = [3, 4, 5];
const NEG_INF: f64 = f64::NEG_INFINITY;

/// Reference reduction of `x` along `axis` with `f(lane)`, in row-major output order.
fn reduce_ref(x: &Tensor<f64>, axis: usize, f: impl Fn(&[f64]) -> f64) -> Vec<f64> {
    let s = x.shape();
    let outer: usize = s[..axis].iter().product();
    let inner: usize = s[axis + 1..].iter().product();
    let n = s[axis];
    let mut out = Vec::with_capacity(outer * inner);
    for o in 0..outer {
        for j in 0..inner {
            let lane: Vec<f64> = (0..n).map(|k| x.data()[(o * n + k) * inner + j]).collect();
            out.push(f(&lane));
        }
    }
    out
}

/// Reference lane map (softmax-like) of `x` along `axis`.
fn map_ref(x: &Tensor<f64>, axis: usize, f: impl Fn(&[f64]) -> Vec<f64>) -> Vec<f64> {
    let s = x.shape();
    let outer: usize = s[..axis].iter().product();
    let inner: usize = s[axis + 1..].iter().product();
    let n = s[axis];
    let mut out = vec![0.0; x.numel()];
    for o in 0..outer {
        for j in 0..inner {
            let lane: Vec<f64> = (0..n).map(|k| x.data()[(o * n + k) * inner + j]).collect();
            for (k, v) in f(&lane).into_iter().enumerate() {
                out[(o * n + k) * inner + j] = v;
            }
        }
    }
    out
}

fn naive_lse(lane: &[f64]) -> f64 {
    lane.iter().map(|v| v.exp()).sum::<f64>().ln()
}

fn reduced_shape(axis: usize, keepdim: bool) -> Vec<usize> {
    let mut s = SHAPE.to_vec();
    if keepdim {
        s[axis] = 1;
    } else {
        s.remove(axis);
    }
    s
}

#[test]
fn sum_and_mean_of_everything() {
    let x = normal(&mut rng(20), &SHAPE);
    let tape = Tape::<f64>::new();
    let v = tape.constant(x.clone());
    let total: f64 = x.data().iter().sum();
    assert_eq!(v.sum().shape(), Vec::<usize>::new());
    assert!((v.sum().item() - total).abs() < 1e-14);
    assert!((v.mean().item() - total / 60.0).abs() < 1e-15);
    check("sum", |_, v| v[0].sum(), std::slice::from_ref(&x));
    check("mean", |_, v| v[0].mean(), std::slice::from_ref(&x));
    // d sum / dx = 1 and d mean / dx = 1/n exactly.
    let (_, g) = grads(|_, v| v[0].sum(), std::slice::from_ref(&x));
    assert!(g[0].data().iter().all(|&v| v == 1.0));
}

#[test]
fn sum_axis_and_mean_axis_every_axis_and_keepdim() {
    let mut r = rng(21);
    for (axis, &len) in SHAPE.iter().enumerate() {
        for keepdim in [false, true] {
            let x = normal(&mut r, &SHAPE);
            let tape = Tape::<f64>::new();
            let s = tape.constant(x.clone()).sum_axis(axis, keepdim);
            let m = tape.constant(x.clone()).mean_axis(axis, keepdim);
            assert_eq!(s.shape(), reduced_shape(axis, keepdim));
            assert_eq!(m.shape(), reduced_shape(axis, keepdim));
            let n = len as f64;
            let es = reduce_ref(&x, axis, |l| l.iter().sum());
            let em: Vec<f64> = es.iter().map(|v| v / n).collect();
            assert_close("sum_axis", s.to_tensor().data(), &es, 1e-15, 1.0);
            assert_close("mean_axis", m.to_tensor().data(), &em, 1e-15, 1.0);
            let label = format!("axis {axis} keepdim {keepdim}");
            check(&format!("sum_axis {label}"), |_, v| v[0].sum_axis(axis, keepdim), std::slice::from_ref(&x));
            check(&format!("mean_axis {label}"), |_, v| v[0].mean_axis(axis, keepdim), &[x]);
        }
    }
}

#[test]
fn logsumexp_every_axis_and_keepdim() {
    let mut r = rng(22);
    for axis in 0..3 {
        for keepdim in [false, true] {
            // Spread 3 so that lanes are dominated by different elements.
            let x = normal(&mut r, &SHAPE).map(|v| 3.0 * v);
            let tape = Tape::<f64>::new();
            let y = tape.constant(x.clone()).logsumexp(axis, keepdim);
            assert_eq!(y.shape(), reduced_shape(axis, keepdim));
            assert_close("logsumexp", y.to_tensor().data(), &reduce_ref(&x, axis, naive_lse), 1e-14, 1.0);
            check(&format!("logsumexp axis {axis} keepdim {keepdim}"), |_, v| v[0].logsumexp(axis, keepdim), &[x]);
        }
    }
}

#[test]
fn logsumexp_is_stable_for_large_inputs() {
    // Naive exp overflows at 1000; the fused op subtracts the lane maximum.
    let x = Tensor::new(&[2, 3], vec![1000.0, 999.0, 998.0, -1000.0, -1001.0, -1002.0]);
    let tape = Tape::<f64>::new();
    let y = tape.constant(x.clone()).logsumexp(1, false).to_tensor();
    let tail = (1.0 + (-1.0f64).exp() + (-2.0f64).exp()).ln();
    assert_close("stable lse", y.data(), &[1000.0 + tail, -1000.0 + tail], 1e-15, 1.0);
    // GradCheck scales its step by max(1, |x|): step 1e-6 keeps h at 1e-3 here, as
    // for inputs of order one (rounding error eps * 1000 / (h / 2) ~ 4e-10).
    let gc = autodiff::gradcheck::GradCheck { step: 1e-6, ..smooth_check() };
    check_with(&gc, "stable lse", |_, v| v[0].logsumexp(1, false), &[x]);
}

fn softmax_ref(lane: &[f64]) -> Vec<f64> {
    let z: f64 = lane.iter().map(|v| v.exp()).sum();
    lane.iter().map(|v| v.exp() / z).collect()
}

#[test]
fn softmax_and_log_softmax_every_axis() {
    let mut r = rng(23);
    for axis in 0..3 {
        let x = normal(&mut r, &SHAPE).map(|v| 2.0 * v);
        let tape = Tape::<f64>::new();
        let s = tape.constant(x.clone()).softmax(axis);
        let l = tape.constant(x.clone()).log_softmax(axis);
        assert_eq!(s.shape(), SHAPE.to_vec());
        let es = map_ref(&x, axis, softmax_ref);
        let el = map_ref(&x, axis, |lane| {
            let lse = naive_lse(lane);
            lane.iter().map(|v| v - lse).collect()
        });
        assert_close("softmax", s.to_tensor().data(), &es, 1e-14, 1e-300);
        assert_close("log_softmax", l.to_tensor().data(), &el, 1e-14, 1.0);
        // Every lane of the softmax sums to one.
        let sums = reduce_ref(&s.to_tensor(), axis, |l| l.iter().sum());
        assert!(sums.iter().all(|v| (v - 1.0).abs() < 1e-15));
        check(&format!("softmax axis {axis}"), |_, v| v[0].softmax(axis), std::slice::from_ref(&x));
        check(&format!("log_softmax axis {axis}"), |_, v| v[0].log_softmax(axis), &[x]);
    }
}

/// A [3, 4] matrix whose lanes along axis 1 contain some `-inf` entries (row 0: one,
/// row 1: three of four) and row 2 none.
fn partially_infinite() -> Tensor<f64> {
    Tensor::new(
        &[3, 4],
        vec![
            0.5, NEG_INF, -1.0, 2.0, //
            NEG_INF, NEG_INF, 0.3, NEG_INF, //
            1.0, -2.0, 0.0, 0.7,
        ],
    )
}

#[test]
fn logsumexp_with_neg_inf_entries_is_the_finite_lse_with_softmax_gradient() {
    let x = partially_infinite();
    let finite = |r: usize| -> Vec<f64> { (0..4).map(|c| x.at(&[r, c])).filter(|v| v.is_finite()).collect() };
    let (y, g) = grads(|_, v| v[0].logsumexp(1, false), std::slice::from_ref(&x));
    for r in 0..3 {
        assert!((y.data()[r] - naive_lse(&finite(r))).abs() < 1e-15);
    }
    // Row 1 has a single finite entry: the lse is that entry exactly.
    assert_eq!(y.data()[1], 0.3);
    assert!(g[0].all_finite(), "gradient {:?}", g[0]);
    // The gradient is the softmax of the row: exactly zero at -inf entries.
    let tape = Tape::<f64>::new();
    let sm = tape.constant(x.clone()).softmax(1).to_tensor();
    assert_close("lse gradient", g[0].data(), sm.data(), 1e-15, 1e-300);
    for (gv, xv) in g[0].data().iter().zip(x.data()) {
        if *xv == NEG_INF {
            assert_eq!(*gv, 0.0);
        }
    }
    // Along axis 0, column 1 has two -inf entries of three.
    let (y0, g0) = grads(|_, v| v[0].logsumexp(0, true), std::slice::from_ref(&x));
    assert_eq!(y0.shape(), &[1, 4]);
    assert!((y0.data()[1] - (-2.0f64)).abs() < 1e-15);
    assert!(g0[0].all_finite());
    assert_eq!(g0[0].at(&[2, 1]), 1.0);
}

#[test]
fn logsumexp_of_an_all_neg_inf_lane_is_neg_inf_with_zero_gradient() {
    // Row 1 along axis 1, and column 2 along axis 0, are entirely -inf.
    let mut x = normal(&mut rng(24), &[3, 4]);
    for c in 0..4 {
        x.set(&[1, c], NEG_INF);
    }
    for r in 0..3 {
        x.set(&[r, 2], NEG_INF);
    }
    for (axis, dead) in [(1usize, 1usize), (0, 2)] {
        for keepdim in [false, true] {
            let (y, g) = grads(|_, v| v[0].logsumexp(axis, keepdim), &[x.clone()]);
            for (i, &v) in y.data().iter().enumerate() {
                if i == dead {
                    assert_eq!(v, NEG_INF, "axis {axis}: the dead lane");
                } else {
                    assert!(v.is_finite(), "axis {axis} lane {i}: {v}");
                }
            }
            assert!(!g[0].data().iter().any(|v| v.is_nan()), "NaN gradient");
            assert!(g[0].all_finite());
            let dead_grads: Vec<f64> = (0..x.numel())
                .filter(|&i| if axis == 1 { i / 4 == dead } else { i % 4 == dead })
                .map(|i| g[0].data()[i])
                .collect();
            assert!(dead_grads.iter().all(|&v| v == 0.0), "{dead_grads:?}");
            // Lanes with some finite entries still get their softmax (sums to one).
            let live: f64 = (0..4).filter(|&c| c != 2).map(|c| g[0].at(&[0, c])).sum();
            if axis == 1 {
                assert!((live - 1.0).abs() < 1e-15);
            }
        }
    }
}

#[test]
fn softmax_family_on_neg_inf_entries_and_dead_lanes() {
    // Documented: softmax of an all -inf lane is 0 and log_softmax is -inf, both
    // with zero gradient; -inf entries of a live lane get probability 0.
    let mut x = partially_infinite();
    for c in 0..4 {
        x.set(&[1, c], NEG_INF); // row 1 now dead
    }
    let tape = Tape::<f64>::new();
    let xs = tape.param(x.clone());
    let s = xs.softmax(1);
    let l = xs.log_softmax(1);
    let sv = s.to_tensor();
    let lv = l.to_tensor();
    for c in 0..4 {
        assert_eq!(sv.at(&[1, c]), 0.0);
        assert_eq!(lv.at(&[1, c]), NEG_INF);
    }
    assert_eq!(sv.at(&[0, 1]), 0.0);
    assert_eq!(lv.at(&[0, 1]), NEG_INF);
    let row0: f64 = (0..4).map(|c| sv.at(&[0, c])).sum();
    assert!((row0 - 1.0).abs() < 1e-15);
    assert!(!sv.data().iter().any(|v| v.is_nan()));
    assert!(!lv.data().iter().any(|v| v.is_nan()));

    let w = normal(&mut rng(25), &[3, 4]);
    let gs = tape.vjp(s, w.clone());
    let gl = tape.vjp(l, w.clone());
    for g in [gs.wrt(xs), gl.wrt(xs)] {
        assert!(g.all_finite(), "{g:?}");
        for c in 0..4 {
            assert_eq!(g.at(&[1, c]), 0.0, "dead lane gradient");
        }
    }
    // Live lanes: the softmax VJP y (w - <w, y>) and log-softmax VJP w - y sum(w),
    // with y = 0 at -inf entries.
    let (gs, gl) = (gs.wrt(xs), gl.wrt(xs));
    for r in [0, 2] {
        let y: Vec<f64> = (0..4).map(|c| sv.at(&[r, c])).collect();
        let wr: Vec<f64> = (0..4).map(|c| w.at(&[r, c])).collect();
        let dot: f64 = y.iter().zip(&wr).map(|(a, b)| a * b).sum();
        let tot: f64 = wr.iter().sum();
        for c in 0..4 {
            assert!((gs.at(&[r, c]) - y[c] * (wr[c] - dot)).abs() < 1e-14);
            assert!((gl.at(&[r, c]) - (wr[c] - y[c] * tot)).abs() < 1e-14);
        }
    }
}

/// Flat indices of lane `(o, j)` along `axis` of `SHAPE` (outer index `o`, inner `j`).
fn lane_indices(axis: usize, o: usize, j: usize) -> Vec<usize> {
    let n = SHAPE[axis];
    let inner: usize = SHAPE[axis + 1..].iter().product();
    (0..n).map(|k| (o * n + k) * inner + j).collect()
}

#[test]
fn dead_lanes_along_every_axis_of_a_3d_tensor() {
    // For each axis: one lane entirely -inf, and scattered -inf entries elsewhere
    // (no other lane entirely -inf). Documented: logsumexp -inf with zero gradient;
    // softmax 0 and log_softmax -inf, both with zero gradient; never NaN.
    let mut r = rng(27);
    for axis in 0..3 {
        let mut x = normal(&mut r, &SHAPE);
        let inner: usize = SHAPE[axis + 1..].iter().product();
        let outer: usize = SHAPE[..axis].iter().product();
        let (o, j) = (outer - 1, inner / 2);
        let dead = lane_indices(axis, o, j);
        for &i in &dead {
            x.data_mut()[i] = NEG_INF;
        }
        for i in (0..60).step_by(11) {
            x.data_mut()[i] = NEG_INF;
        }
        for &i in &dead {
            assert_eq!(x.data()[i], NEG_INF);
        }
        let w = normal(&mut r, &SHAPE);

        let tape = Tape::<f64>::new();
        let xv = tape.param(x.clone());
        let lse = xv.logsumexp(axis, false);
        let lv = lse.to_tensor();
        let expected = reduce_ref(&x, axis, |lane| {
            let finite: Vec<f64> = lane.iter().copied().filter(|v| v.is_finite()).collect();
            if finite.is_empty() {
                NEG_INF
            } else {
                naive_lse(&finite)
            }
        });
        assert_close(&format!("lse axis {axis}"), lv.data(), &expected, 1e-14, 1.0);
        assert_eq!(lv.data()[o * inner + j], NEG_INF);
        let cot = normal(&mut r, lv.shape());
        let g = tape.vjp(lse, cot).wrt(xv);
        assert!(g.all_finite(), "lse axis {axis}: {g:?}");
        assert!(dead.iter().all(|&i| g.data()[i] == 0.0));

        let sm = xv.softmax(axis);
        let ls = xv.log_softmax(axis);
        let (sv, lsv) = (sm.to_tensor(), ls.to_tensor());
        assert!(!sv.data().iter().chain(lsv.data()).any(|v| v.is_nan()), "axis {axis}: NaN");
        for &i in &dead {
            assert_eq!(sv.data()[i], 0.0);
            assert_eq!(lsv.data()[i], NEG_INF);
        }
        // Live lanes still sum to one.
        let sums = reduce_ref(&sv, axis, |l| l.iter().sum());
        for (k, s) in sums.iter().enumerate() {
            let want = if k == o * inner + j { 0.0 } else { 1.0 };
            assert!((s - want).abs() < 1e-15, "axis {axis} lane {k}: {s}");
        }
        for y in [sm, ls] {
            let g = tape.vjp(y, w.clone()).wrt(xv);
            assert!(g.all_finite(), "axis {axis}: {g:?}");
            assert!(dead.iter().all(|&i| g.data()[i] == 0.0));
        }
    }
}

#[test]
fn log_softmax_lse_identity_on_live_lanes() {
    // log_softmax(x) + logsumexp(x) == x, with both fused ops on one tape.
    let x = normal(&mut rng(26), &SHAPE).map(|v| 4.0 * v);
    for axis in 0..3 {
        check(
            &format!("log_softmax + lse axis {axis}"),
            |_, v| v[0].log_softmax(axis) + v[0].logsumexp(axis, true),
            std::slice::from_ref(&x),
        );
        let (y, g) = grads(|_, v| v[0].log_softmax(axis) + v[0].logsumexp(axis, true), std::slice::from_ref(&x));
        assert_close("identity", y.data(), x.data(), 1e-14, 1.0);
        assert_close("identity grad", g[0].data(), &vec![1.0; 60], 1e-14, 1.0);
    }
}
