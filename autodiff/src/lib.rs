//! A tape-based reverse-mode automatic differentiation engine over tensors.
//!
//! A forward pass records whole-tensor operations on a [`Tape`]; [`Tape::backward`]
//! walks it once in reverse and accumulates vector-Jacobian products into the
//! gradients of the tracked leaves (parameters). The engine knows nothing about
//! particles or vehicles: it serves any batched numerical model.
//!
//! * [`Tensor`]: shape plus contiguous row-major storage, generic over [`Float`]
//!   (`f64` for exact gradient checks, `f32` with fast vectorised transcendentals
//!   for the hot path).
//! * [`Tape`] / [`Var`]: the recording and its `Copy` handles; a non-recording tape
//!   ([`Tape::no_record`]) runs the same model code forward only.
//! * [`nn`]: parameter stores, dense layers and MLPs; [`optim`]: Adam and
//!   global-norm clipping; [`gradcheck`]: finite-difference checks for any model.
//!
//! ```
//! use autodiff::{Tape, Tensor};
//! let tape = Tape::<f64>::new();
//! let w = tape.param(Tensor::new(&[2, 1], vec![0.5, -1.0]));
//! let x = tape.constant(Tensor::new(&[3, 2], vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]));
//! let loss = x.matmul(w).tanh().sum();
//! let grads = tape.backward(loss);
//! assert_eq!(grads.wrt(w).shape(), &[2, 1]);
//! ```
#![deny(missing_docs)]

mod backward;
pub mod dist;
pub mod fastmath;
mod float;
pub mod gradcheck;
mod kernels;
pub mod nn;
mod ops;
pub mod optim;
mod tape;
mod tensor;

pub use float::Float;
pub use kernels::Parallelism;
pub use tape::{Gradients, Tape, Var};
pub use tensor::{broadcast_shapes, Tensor};
