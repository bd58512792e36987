//! The `sefi` program's tests, run against the binary this package builds: one
//! module per file of this directory, built as one test binary (`cargo test -p
//! experiments --test integration [module::]`), which links once instead of once
//! per file. The MPI tests (`mpi.rs`) are their own binary, built only with the
//! `mpi` feature.

mod cli;
mod common;
mod diagnose;
mod eval;
mod experiment_c;
mod generate;
mod stability;
mod train;
