//! Seed derivation: the SplitMix64 mixer, the one home of every derived random
//! stream (the filter's per-object streams, training's step, evaluation and batch
//! order seeds).

/// SplitMix64's output function: a bijective 64-bit mixer.
///
/// ```
/// use ssm::util::seed::splitmix64;
/// assert_eq!(splitmix64(0), 0xe220_a839_7b1d_cdaf);
/// assert_ne!(splitmix64(1), splitmix64(2));
/// ```
pub fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}
