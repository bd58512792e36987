//! The bottom floor: plumbing that knows nothing of data or models.
//!
//! * [`seed`]: the SplitMix64 mixer every derived random stream goes through.
//! * [`setting`]: [`setting::SettingError`], the one error of every settings check.
//! * [`reduce`]: exact sums across blocks of objects, threads and processes.
//! * [`npz`]: parameter stores as NumPy `.npz` archives.
//! * [`angles`]: wrapping an angle to `(-pi, pi]` and turning a heading around.

pub mod angles;
pub mod npz;
pub mod reduce;
pub mod seed;
pub mod setting;
