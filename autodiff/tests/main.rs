//! The `autodiff` crate's integration tests: one module per file of this
//! directory, built as one test binary (`cargo test -p autodiff --test
//! integration [module::]`): one link and one copy of the engine's generic code
//! instead of one per file.

mod common;
mod engine_consistency;
mod gradcheck_indexing;
mod gradcheck_ops;
mod gradcheck_precomputed;
mod gradcheck_reductions;
mod gradient_semantics;
mod nn;
mod shape_edge_cases;
