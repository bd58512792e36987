//! The user's commands: one file per command (or pair of commands), each with
//! its arguments and its `run`.
//!
//! * [`demo`]: `sefi demo`, a quick end-to-end run on generated data.
//! * [`import`]: `sefi import-kitti`, the KITTI sequences as datasets.
//! * [`generate`]: `sefi generate`, the paper's synthetic datasets.
//! * [`train`]: `sefi train`, learning a dataset's model.
//! * [`evaluate`]: `sefi eval` and `sefi track`, metrics and smoothed states.
//! * [`reproduce`]: `sefi reproduce`, the paper's experiments A and B.
//! * [`experiment_c`]: `sefi experiment-c`, the paper's experiment C on KITTI.
//! * [`diagnose`]: `sefi diagnose`, model criticism.
//! * [`params_npz`]: `sefi params export|import`, parameter files and `.npz`.

pub mod demo;
pub mod diagnose;
pub mod evaluate;
pub mod experiment_c;
pub mod generate;
pub mod import;
pub mod params_npz;
pub mod reproduce;
pub mod train;
