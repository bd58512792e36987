//! A tape-based reverse-mode automatic differentiation engine over tensors.
//!
//! A forward pass records whole-tensor operations on a [`Tape`]; [`Tape::backward`]
//! walks it once in reverse and accumulates vector-Jacobian products into the
//! gradients of the tracked leaves (parameters). The engine knows nothing about
//! particles or vehicles: it serves any batched numerical model.
//!
//! # Read first
//!
//! * [`Tensor`]: shape plus contiguous row-major storage, generic over [`Float`]
//!   (`f64` for exact gradient checks, `f32` with fast vectorised transcendentals
//!   for the hot path).
//! * [`Tape`] / [`Var`]: the recording and its `Copy` handles; arithmetic on
//!   `Var`s (`+ - * /`, [`Var::exp`], [`Var::matmul`], [`Var::sum`], ...) records
//!   an op. A non-recording tape ([`Tape::no_record`]) runs the same model code
//!   forward only.
//! * [`dist`]: log-densities on the tape ([`dist::normal_logpdf`], ...).
//! * [`nn`]: parameter stores ([`nn::ParamStore`]), dense layers and MLPs;
//!   [`optim`]: Adam and global-norm clipping; [`gradcheck`]: finite-difference
//!   checks for any model.
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
//!
//! # One function, two uses
//!
//! Code written over `Var<'t, F>` for any [`Float`] runs on a recording `f64`
//! tape for gradients and on a non-recording `f32` tape for fast values: a model
//! is written once.
//!
//! ```
//! use autodiff::dist::normal_logpdf;
//! use autodiff::{Float, Tape, Tensor, Var};
//!
//! /// ln N(x; mu, 1) summed over x.
//! fn log_density<'t, F: Float>(x: Var<'t, F>, mu: Var<'t, F>) -> Var<'t, F> {
//!     normal_logpdf(x, mu, x.tape().scalar(0.0)).sum()
//! }
//!
//! // Gradient in f64: d/dmu sum_i ln N(x_i; mu, 1) = sum_i (x_i - mu).
//! let tape = Tape::<f64>::new();
//! let mu = tape.param(Tensor::scalar(0.5));
//! let x = tape.constant(Tensor::from_vec(vec![1.0, 2.0, 3.0]));
//! let grads = tape.backward(log_density(x, mu));
//! assert!((grads.wrt(mu).item() - 4.5).abs() < 1e-12);
//!
//! // The same function forward only, in f32, nothing recorded.
//! let fast = Tape::<f32>::no_record();
//! let value = log_density(fast.constant(Tensor::from_vec(vec![1.0, 2.0, 3.0])), fast.scalar(0.5));
//! let expected = -0.5 * (0.25 + 2.25 + 6.25) - 3.0 * autodiff::dist::HALF_LN_2PI;
//! assert!((value.item() as f64 - expected).abs() < 1e-5);
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
