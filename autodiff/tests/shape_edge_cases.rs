//! Degenerate shapes and programmer errors: empty axes and inner dimensions give the
//! mathematically right values (an empty sum is 0, an empty log-sum-exp is -inf, a
//! product over k = 0 is zero), and shape or tape mismatches panic with a message
//! naming the op.

use autodiff::{Tape, Tensor};

#[test]
fn reductions_over_an_empty_axis() {
    let tape = Tape::<f64>::new();
    let x = tape.param(Tensor::zeros(&[3, 0, 2]));
    let s = x.sum_axis(1, false);
    assert_eq!(s.shape(), vec![3, 2]);
    assert_eq!(s.to_tensor().data(), &[0.0; 6]);
    // ln of an empty sum of exponentials.
    let l = x.logsumexp(1, true);
    assert_eq!(l.shape(), vec![3, 1, 2]);
    assert_eq!(l.to_tensor().data(), &[f64::NEG_INFINITY; 6]);
    let e = Tape::<f64>::new();
    let y = e.constant(Tensor::zeros(&[4, 0])).logsumexp(1, false);
    assert_eq!(y.to_tensor().data(), &[f64::NEG_INFINITY; 4]);
    // Softmax over an empty axis is empty; the gradients have the input's shape.
    let sm = x.softmax(1);
    assert_eq!(sm.numel(), 0);
    let g = tape.backward((l.sum_axis(1, false) + s).sum());
    assert_eq!(g.wrt(x).shape(), &[3, 0, 2]);
}

#[test]
fn matmul_and_affine_with_an_empty_inner_dimension() {
    let tape = Tape::<f64>::new();
    let x = tape.param(Tensor::zeros(&[5, 0]));
    let w = tape.param(Tensor::zeros(&[0, 3]));
    let b = tape.param(Tensor::new(&[3], vec![1.0, 2.0, 3.0]));
    let y = x.matmul(w);
    assert_eq!(y.shape(), vec![5, 3]);
    assert_eq!(y.to_tensor().data(), &[0.0; 15]);
    let a = x.affine(w, b);
    assert_eq!(a.to_tensor().data()[..6], [1.0, 2.0, 3.0, 1.0, 2.0, 3.0]);
    let g = tape.backward((y + a).sum());
    assert_eq!(g.wrt(b).data(), &[5.0, 5.0, 5.0]);
    assert_eq!(g.wrt(x).shape(), &[5, 0]);
    assert_eq!(g.wrt(w).shape(), &[0, 3]);
    // A 3-D lhs with an empty batch dimension.
    let z = tape.constant(Tensor::zeros(&[0, 4, 2]));
    let w2 = tape.constant(Tensor::ones(&[2, 3]));
    assert_eq!(z.matmul(w2).shape(), vec![0, 4, 3]);
}

#[test]
#[should_panic(expected = "concat: inputs live on another tape")]
fn concat_rejects_a_part_from_another_tape() {
    let a = Tape::<f64>::new();
    let b = Tape::<f64>::new();
    let x = a.constant(Tensor::ones(&[2, 2]));
    let y = b.constant(Tensor::ones(&[2, 2]));
    let _ = a.concat(&[x, y], 0);
}

#[test]
#[should_panic(expected = "concat: inputs live on another tape")]
fn concat_rejects_parts_all_from_another_tape() {
    let a = Tape::<f64>::new();
    let b = Tape::<f64>::new();
    let x = b.constant(Tensor::ones(&[2, 2]));
    let _ = a.concat(&[x, x], 0);
}

#[test]
#[should_panic(expected = "Add: shapes [3, 4] and [3] do not broadcast")]
fn mismatched_broadcast_names_the_op_and_shapes() {
    let tape = Tape::<f64>::new();
    let _ = tape.constant(Tensor::zeros(&[3, 4])) + tape.constant(Tensor::zeros(&[3]));
}

#[test]
#[should_panic(expected = "matmul: shapes [3, 4] and [3, 2] do not chain")]
fn mismatched_matmul_names_the_shapes() {
    let tape = Tape::<f64>::new();
    let _ = tape.constant(Tensor::zeros(&[3, 4])).matmul(tape.constant(Tensor::zeros(&[3, 2])));
}

#[test]
#[should_panic(expected = "gather: index 3 out of range for axis of length 3")]
fn gather_out_of_range_panics() {
    let tape = Tape::<f64>::new();
    let _ = tape.constant(Tensor::zeros(&[3, 2])).gather(0, &[0, 3]);
}

#[test]
#[should_panic(expected = "vjp: cotangent shape must equal output shape")]
fn vjp_checks_the_cotangent_shape() {
    let tape = Tape::<f64>::new();
    let x = tape.param(Tensor::zeros(&[3, 2]));
    let _ = tape.vjp(x.exp(), Tensor::zeros(&[2, 3]));
}

#[test]
#[should_panic(expected = "backward: output must be a scalar")]
fn backward_needs_a_scalar() {
    let tape = Tape::<f64>::new();
    let x = tape.param(Tensor::zeros(&[3]));
    let _ = tape.backward(x.exp());
}
