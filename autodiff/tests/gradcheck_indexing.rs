//! Data-movement ops: gather / index_select and scatter_add along every axis (with
//! repeated indices), concat of three parts along every axis, slice, reshape,
//! transpose, broadcast_to and select. Values against index-by-index references,
//! gradients against finite differences in f64 and, where exact, against their
//! closed form (a repeated gather index receives the sum of its cotangents).

use crate::common::*;
use autodiff::{Tape, Tensor};

const SHAPE: [usize; 3] = [3, 4, 5];

/// Gather indices for an axis of length 3, 4, 5: repeats, and (for 5) an omission.
fn gather_indices(n: usize) -> Vec<usize> {
    match n {
        3 => vec![2, 0, 2, 2, 1],
        4 => vec![3, 3, 0, 1, 3, 2],
        5 => vec![4, 1, 1, 0, 4, 4, 2],
        _ => unreachable!(),
    }
}

/// Scatter targets for the `n` slices of an axis of length 3, 4, 5 into an axis of
/// length `n + 1`: repeated targets, and targets that receive nothing.
fn scatter_indices(n: usize) -> Vec<usize> {
    match n {
        3 => vec![2, 0, 2],
        4 => vec![1, 4, 1, 1],
        5 => vec![0, 5, 3, 0, 3],
        _ => unreachable!(),
    }
}

#[test]
fn gather_and_index_select_every_axis_with_repeats() {
    let mut r = rng(30);
    for axis in 0..3 {
        let n = SHAPE[axis];
        let idx = gather_indices(n);
        let x = normal(&mut r, &SHAPE);
        let tape = Tape::<f64>::new();
        let y = tape.constant(x.clone()).gather(axis, &idx).to_tensor();
        let mut out_shape = SHAPE.to_vec();
        out_shape[axis] = idx.len();
        assert_eq!(y.shape(), &out_shape[..]);
        for i in 0..y.numel() {
            let mut at = unravel(i, &out_shape);
            at[axis] = idx[at[axis]];
            assert_eq!(y.data()[i], x.at(&at), "gather axis {axis} element {i}");
        }
        let sel = tape.constant(x.clone()).index_select(axis, &idx).to_tensor();
        assert_eq!(sel, y, "index_select is gather");

        let name = format!("gather axis {axis}");
        check(&name, |_, v| v[0].gather(axis, &idx), std::slice::from_ref(&x));
        check(&format!("index_select axis {axis}"), |_, v| v[0].index_select(axis, &idx), std::slice::from_ref(&x));
        // The gradient of a sum counts how often each position was picked.
        let (_, g) = grads(|_, v| v[0].gather(axis, &idx), std::slice::from_ref(&x));
        for i in 0..x.numel() {
            let pos = unravel(i, &SHAPE)[axis];
            let count = idx.iter().filter(|&&j| j == pos).count() as f64;
            assert_eq!(g[0].data()[i], count, "{name}: position {pos}");
        }
    }
}

#[test]
fn gather_all_from_one_position_sums_the_cotangent() {
    // Resampling every particle from ancestor 2: the ancestor's gradient is the sum.
    let x = Tensor::new(&[4, 2], vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]);
    let tape = Tape::<f64>::new();
    let xv = tape.param(x);
    let y = xv.gather(0, &[2, 2, 2, 2, 2]);
    let cot = Tensor::new(&[5, 2], (0..10).map(|i| i as f64).collect());
    let g = tape.vjp(y, cot).wrt(xv);
    assert_eq!(
        g.data(),
        &[0.0, 0.0, 0.0, 0.0, 20.0, 25.0, 0.0, 0.0],
        "rows 0, 2, 4, 6, 8 and 1, 3, 5, 7, 9 summed into ancestor 2"
    );
}

#[test]
fn scatter_add_every_axis_with_repeats() {
    let mut r = rng(31);
    for axis in 0..3 {
        let n = SHAPE[axis];
        let size = n + 1;
        let idx = scatter_indices(n);
        let x = normal(&mut r, &SHAPE);
        let tape = Tape::<f64>::new();
        let y = tape.constant(x.clone()).scatter_add(axis, &idx, size).to_tensor();
        let mut out_shape = SHAPE.to_vec();
        out_shape[axis] = size;
        assert_eq!(y.shape(), &out_shape[..]);
        let mut expected = Tensor::<f64>::zeros(&out_shape);
        for i in 0..x.numel() {
            let mut at = unravel(i, &SHAPE);
            at[axis] = idx[at[axis]];
            let v = expected.at(&at) + x.data()[i];
            expected.set(&at, v);
        }
        assert_close(&format!("scatter_add axis {axis}"), y.data(), expected.data(), 1e-15, 1.0);
        check(&format!("scatter_add axis {axis}"), |_, v| v[0].scatter_add(axis, &idx, size), &[x]);
    }
}

#[test]
fn scatter_add_is_the_transpose_of_gather() {
    // <gather(x), u> == <x, scatter_add(u)> for any x, u.
    let mut r = rng(32);
    let idx = [1usize, 1, 0, 3, 1];
    let x = normal(&mut r, &[4, 3]);
    let u = normal(&mut r, &[5, 3]);
    let tape = Tape::<f64>::new();
    let gx = tape.constant(x.clone()).gather(0, &idx).to_tensor();
    let su = tape.constant(u.clone()).scatter_add(0, &idx, 4).to_tensor();
    let lhs: f64 = gx.data().iter().zip(u.data()).map(|(a, b)| a * b).sum();
    let rhs: f64 = x.data().iter().zip(su.data()).map(|(a, b)| a * b).sum();
    assert!((lhs - rhs).abs() < 1e-13, "{lhs} vs {rhs}");
}

#[test]
fn concat_three_parts_every_axis() {
    let mut r = rng(33);
    for axis in 0..3 {
        let lens = [1usize, 3, 2];
        let parts: Vec<Tensor<f64>> = lens
            .iter()
            .map(|&l| {
                let mut s = SHAPE.to_vec();
                s[axis] = l;
                normal(&mut r, &s)
            })
            .collect();
        let tape = Tape::<f64>::new();
        let vars: Vec<_> = parts.iter().map(|p| tape.constant(p.clone())).collect();
        let y = tape.concat(&vars, axis).to_tensor();
        let mut out_shape = SHAPE.to_vec();
        out_shape[axis] = 6;
        assert_eq!(y.shape(), &out_shape[..]);
        for i in 0..y.numel() {
            let mut at = unravel(i, &out_shape);
            let (mut p, mut k) = (0, at[axis]);
            while k >= lens[p] {
                k -= lens[p];
                p += 1;
            }
            at[axis] = k;
            assert_eq!(y.data()[i], parts[p].at(&at), "concat axis {axis}");
        }
        check(&format!("concat axis {axis}"), |tape, v| tape.concat(v, axis), &parts);
    }
}

#[test]
fn concat_of_a_value_with_itself_accumulates() {
    let x = normal(&mut rng(34), &[2, 3]);
    check("concat [x, x, x]", |tape, v| tape.concat(&[v[0], v[0].square(), v[0]], 1), std::slice::from_ref(&x));
    let (_, g) = grads(|tape, v| tape.concat(&[v[0], v[0]], 0), &[x]);
    assert!(g[0].data().iter().all(|&v| v == 2.0));
}

#[test]
fn slice_every_axis() {
    let mut r = rng(35);
    for axis in 0..3 {
        let n = SHAPE[axis];
        for (start, len) in [(0, 1), (1, n - 1), (n / 2, n - n / 2), (0, n)] {
            let x = normal(&mut r, &SHAPE);
            let tape = Tape::<f64>::new();
            let y = tape.constant(x.clone()).slice(axis, start, len).to_tensor();
            let mut out_shape = SHAPE.to_vec();
            out_shape[axis] = len;
            assert_eq!(y.shape(), &out_shape[..]);
            for i in 0..y.numel() {
                let mut at = unravel(i, &out_shape);
                at[axis] += start;
                assert_eq!(y.data()[i], x.at(&at));
            }
            check(&format!("slice axis {axis} {start}..{}", start + len), |_, v| v[0].slice(axis, start, len), &[x]);
        }
    }
    // Two overlapping slices of one value: gradients add where they overlap.
    let x = normal(&mut r, &[6, 2]);
    let (_, g) = grads(|_, v| v[0].slice(0, 0, 4) + v[0].slice(0, 2, 4), std::slice::from_ref(&x));
    let expected: Vec<f64> = (0..12).map(|i| if (4..8).contains(&i) { 2.0 } else { 1.0 }).collect();
    assert_eq!(g[0].data(), &expected[..]);
}

#[test]
fn reshape_transpose_and_broadcast_to() {
    let mut r = rng(36);
    let x = normal(&mut r, &SHAPE);
    let tape = Tape::<f64>::new();
    let y = tape.constant(x.clone()).reshape(&[12, 5]).to_tensor();
    assert_eq!(y.shape(), &[12, 5]);
    assert_eq!(y.data(), x.data());
    check("reshape", |_, v| v[0].reshape(&[5, 12]).tanh().reshape(&[60]), &[x]);

    let m = normal(&mut r, &[3, 5]);
    let t = tape.constant(m.clone()).t().to_tensor();
    assert_eq!(t.shape(), &[5, 3]);
    for i in 0..3 {
        for j in 0..5 {
            assert_eq!(t.at(&[j, i]), m.at(&[i, j]));
        }
    }
    check("transpose", |_, v| v[0].t(), std::slice::from_ref(&m));
    check("x^T x", |_, v| v[0].t().matmul(v[0]), &[m]);

    for (from, to) in [
        (vec![3, 1], vec![2, 3, 4]),
        (vec![4], vec![3, 4]),
        (vec![], vec![2, 2]),
        (vec![1, 4], vec![3, 4]),
        (vec![2, 1, 4], vec![2, 3, 4]),
        (vec![3, 4], vec![3, 4]),
    ] {
        let x = normal(&mut r, &from);
        let y = tape.constant(x.clone()).broadcast_to(&to).to_tensor();
        assert_eq!(y.shape(), &to[..]);
        for i in 0..y.numel() {
            let at = unravel(i, &to);
            let off = to.len() - from.len();
            let src: Vec<usize> = from.iter().enumerate().map(|(d, &n)| if n == 1 { 0 } else { at[off + d] }).collect();
            assert_eq!(y.data()[i], x.at(&src));
        }
        check(&format!("broadcast_to {from:?} -> {to:?}"), |_, v| v[0].broadcast_to(&to), &[x]);
    }
}

#[test]
fn select_with_a_constant_mask() {
    let mut r = rng(37);
    let a = normal(&mut r, &[3, 4]);
    let b = normal(&mut r, &[3, 4]);
    let mask: Vec<bool> = (0..12).map(|i| i % 3 != 1).collect();
    let tape = Tape::<f64>::new();
    let y = tape.select(&mask, tape.constant(a.clone()), tape.constant(b.clone())).to_tensor();
    for (i, &m) in mask.iter().enumerate() {
        let e = if m { a.data()[i] } else { b.data()[i] };
        assert_eq!(y.data()[i], e);
    }
    check("select", |tape, v| tape.select(&mask, v[0], v[1]), &[a.clone(), b.clone()]);
    let (_, g) = grads(|tape, v| tape.select(&mask, v[0], v[1]), &[a, b]);
    for (i, &m) in mask.iter().enumerate() {
        assert_eq!(g[0].data()[i], if m { 1.0 } else { 0.0 });
        assert_eq!(g[1].data()[i], if m { 0.0 } else { 1.0 });
    }
    // Both branches from one value: the gradient is one everywhere.
    let x = normal(&mut r, &[3, 4]);
    let (_, g) = grads(|tape, v| tape.select(&mask, v[0], v[0]), &[x]);
    assert!(g[0].data().iter().all(|&v| v == 1.0));
}
