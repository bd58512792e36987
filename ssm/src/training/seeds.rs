//! The seeds and batch orders of a run, each a fixed function of the run's seed
//! (through [`crate::util::seed::splitmix64`]), so a resumed run repeats an
//! uninterrupted one.

use crate::util::seed::splitmix64;

/// Stream tags, so the step seeds, evaluation seeds and batch orders of one run
/// are unrelated.
const STEP_STREAM: u64 = 0x5354_4550; // "STEP"
const EVAL_STREAM: u64 = 0x4556_414c; // "EVAL"
const ORDER_STREAM: u64 = 0x4f52_4452; // "ORDR"

fn derive_seed(seed: u64, stream: u64, index: u64) -> u64 {
    splitmix64(splitmix64(seed ^ splitmix64(stream)) ^ index)
}

/// The seed [`train`](super::train) passes to [`Objective::estimate`](super::Objective::estimate) at step `step` (from 1): a
/// fixed function of the run's seed and the step.
///
/// ```
/// use ssm::training::step_seed;
/// assert_eq!(step_seed(7, 3), step_seed(7, 3));
/// assert_ne!(step_seed(7, 3), step_seed(7, 4));
/// assert_ne!(step_seed(7, 3), step_seed(8, 3));
/// ```
pub fn step_seed(seed: u64, step: usize) -> u64 {
    derive_seed(seed, STEP_STREAM, step as u64)
}

/// The seed [`train`](super::train) passes to [`Objective::evaluate`](super::Objective::evaluate) at every
/// evaluation of a run: the same after every step (common random numbers), so
/// that the differences between a run's evaluations, the ranking
/// [`TrainConfig::keep_best`](super::TrainConfig::keep_best) makes, are the
/// parameters' and not the evaluating filter's Monte Carlo noise.
///
/// ```
/// use ssm::training::{eval_seed, step_seed};
/// assert_ne!(eval_seed(7), eval_seed(8));
/// assert_ne!(eval_seed(7), step_seed(7, 0));
/// ```
pub fn eval_seed(seed: u64) -> u64 {
    derive_seed(seed, EVAL_STREAM, 0)
}

/// The order in which epoch `epoch` visits batches `0..batches`: a permutation
/// drawn from `(seed, epoch)` (Fisher–Yates on a SplitMix64 stream, independent of
/// the `rand` crate's version), or `0..batches` without shuffling.
///
/// ```
/// use ssm::training::epoch_order;
/// let mut o = epoch_order(1, 0, 10, true);
/// assert_ne!(o, epoch_order(1, 1, 10, true));
/// o.sort();
/// assert_eq!(o, (0..10).collect::<Vec<_>>());
/// assert_eq!(epoch_order(1, 0, 3, false), vec![0, 1, 2]);
/// ```
pub fn epoch_order(seed: u64, epoch: usize, batches: usize, shuffle: bool) -> Vec<usize> {
    let mut order: Vec<usize> = (0..batches).collect();
    if shuffle {
        let mut state = derive_seed(seed, ORDER_STREAM, epoch as u64);
        for i in (1..batches).rev() {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            // Multiply-shift: uniform on 0..=i up to a bias below (i + 1) / 2^64.
            let j = ((splitmix64(state) as u128 * (i as u128 + 1)) >> 64) as usize;
            order.swap(i, j);
        }
    }
    order
}
