//! Exact sums across blocks of objects, threads and processes: the one place
//! where a step's partial results become the step's result.
//!
//! A training step's gradient is a sum over independent objects. Floating-point
//! addition is not associative, so a sum that depends on how the objects were
//! split (between rayon workers, or between the ranks of an MPI job) would make
//! the parameters depend on the machine. Here the objects of a batch are cut into
//! fixed *blocks* (consecutive objects, the same cut on every layout); each block is
//! summed in a fixed order by whoever owns it, and the block sums are then added
//! **exactly**:
//!
//! 1. per component, the largest magnitude over all blocks, `m` (a MAX reduction);
//! 2. every block's value is put on the grid `2^-s`, with `s` chosen from `m` and an
//!    upper bound on the number of blocks so that the sum of all of them fits in an
//!    `i64` (at least 62 - log2(blocks) significant bits for the largest block);
//! 3. the integers are added (a SUM reduction, exact and order-free) and scaled
//!    back.
//!
//! Steps 1–3 give the same bits whatever the number of processes or threads and
//! whichever blocks each holds; the rounding onto the grid depends only on a
//! block's own value and the global `m`. A component with a non-finite block is
//! NaN (the trainer then skips the step, as for any non-finite estimate).
//!
//! [`Collective`] is the communication these steps need: [`SingleProcess`] for
//! one process, and the `sefi` binary's MPI communicator (cargo feature `mpi`).

/// The two reductions an exact sum needs, over every process of a job. Every
/// process must call them in the same order with slices of the same length.
pub trait Collective: Send + Sync {
    /// This process's index in `0..size()`.
    fn rank(&self) -> usize;
    /// Number of processes.
    fn size(&self) -> usize;
    /// Element-wise maximum over processes, in place.
    fn max_f64(&self, values: &mut [f64]);
    /// Element-wise sum over processes, in place (exact: integer addition).
    fn sum_i64(&self, values: &mut [i64]);
    /// Bytes this process has sent through the reductions so far.
    fn bytes_sent(&self) -> u64 {
        0
    }
    /// Gives every process the first process's `values`, exactly (NaN and
    /// infinities included), through one [`Collective::max_f64`] of twice the
    /// length: the first sends each value (NaN as 0) and a NaN flag, the others
    /// `-inf`, which never wins a maximum.
    fn share_first(&self, values: &mut [f64]) {
        if self.size() <= 1 {
            return;
        }
        let n = values.len();
        let mut sent = vec![f64::NEG_INFINITY; 2 * n];
        if self.rank() == 0 {
            for (i, v) in values.iter().enumerate() {
                (sent[i], sent[n + i]) = if v.is_nan() { (0.0, 1.0) } else { (*v, 0.0) };
            }
        }
        self.max_f64(&mut sent);
        for (i, v) in values.iter_mut().enumerate() {
            *v = if sent[n + i] > 0.0 { f64::NAN } else { sent[i] };
        }
    }
}

/// One process: both reductions are the identity.
#[derive(Clone, Copy, Debug, Default)]
pub struct SingleProcess;

impl Collective for SingleProcess {
    fn rank(&self) -> usize {
        0
    }
    fn size(&self) -> usize {
        1
    }
    fn max_f64(&self, _: &mut [f64]) {}
    fn sum_i64(&self, _: &mut [i64]) {}
}

/// A job of `size` processes simulated by the threads of one process: each
/// thread holds one [`ThreadGroup::member`] and makes the collective calls as
/// an MPI process would. What tests of data-parallel code run on, without MPI.
pub struct ThreadGroup {
    size: usize,
    slots: std::sync::Mutex<Vec<Vec<u64>>>,
    barrier: std::sync::Barrier,
}

impl ThreadGroup {
    /// A group of `size` (at least 1) members.
    pub fn new(size: usize) -> std::sync::Arc<Self> {
        let size = size.max(1);
        std::sync::Arc::new(ThreadGroup {
            size,
            slots: std::sync::Mutex::new(vec![Vec::new(); size]),
            barrier: std::sync::Barrier::new(size),
        })
    }

    /// Member `rank` of the group, for the thread that plays that process.
    ///
    /// # Panics
    /// If `rank` is not below the group's size.
    pub fn member(self: &std::sync::Arc<Self>, rank: usize) -> ThreadMember {
        assert!(rank < self.size, "ThreadGroup::member: rank {rank} of {}", self.size);
        ThreadMember { group: self.clone(), rank }
    }
}

/// One member of a [`ThreadGroup`].
pub struct ThreadMember {
    group: std::sync::Arc<ThreadGroup>,
    rank: usize,
}

impl ThreadMember {
    /// Posts this member's values (as bits), waits for every member, and
    /// combines all members' values in rank order with `op`.
    fn combine<T: Copy>(&self, values: &mut [T], to: fn(T) -> u64, from: fn(u64) -> T, op: fn(T, T) -> T) {
        let g = &self.group;
        g.slots.lock().unwrap_or_else(|e| e.into_inner())[self.rank] = values.iter().map(|&v| to(v)).collect();
        g.barrier.wait();
        let all = g.slots.lock().unwrap_or_else(|e| e.into_inner()).clone();
        g.barrier.wait();
        for (j, v) in values.iter_mut().enumerate() {
            *v = all.iter().map(|a| from(a[j])).reduce(op).expect("size >= 1");
        }
    }
}

impl Collective for ThreadMember {
    fn rank(&self) -> usize {
        self.rank
    }
    fn size(&self) -> usize {
        self.group.size
    }
    fn max_f64(&self, values: &mut [f64]) {
        self.combine(values, f64::to_bits, f64::from_bits, f64::max);
    }
    fn sum_i64(&self, values: &mut [i64]) {
        self.combine(values, |v| v as u64, |b| b as i64, i64::wrapping_add);
    }
}

/// The owner of each block of a batch among `size` processes, balancing the
/// blocks' `costs`: longest first, each to the least-loaded process (ties: the
/// lower block index, the lower rank). Deterministic; which process holds a block
/// never changes the sum, only how long the step takes.
///
/// ```
/// use ssm::util::reduce::assign_blocks;
/// // 5 -> 0, 4 -> 1, 2 -> 1 (4 < 5), 1 -> 0 (5 < 6)
/// assert_eq!(assign_blocks(&[5.0, 1.0, 4.0, 2.0], 2), vec![0, 0, 1, 1]);
/// assert_eq!(assign_blocks(&[1.0, 1.0, 1.0], 1), vec![0, 0, 0]);
/// ```
pub fn assign_blocks(costs: &[f64], size: usize) -> Vec<usize> {
    let size = size.max(1);
    let mut order: Vec<usize> = (0..costs.len()).collect();
    order.sort_by(|&a, &b| costs[b].total_cmp(&costs[a]).then(a.cmp(&b)));
    let mut load = vec![0.0f64; size];
    let mut owner = vec![0; costs.len()];
    for b in order {
        let p = (0..size).min_by(|&x, &y| load[x].total_cmp(&load[y]).then(x.cmp(&y))).expect("size >= 1");
        owner[b] = p;
        load[p] += costs[b];
    }
    owner
}

/// `x * 2^e`, exact whenever the result is a normal number (the scaling is split
/// so that no intermediate power of two overflows).
fn scale_pow2(x: f64, e: i32) -> f64 {
    let mut x = x;
    let mut e = e;
    while e != 0 {
        let step = e.clamp(-1000, 1000);
        x *= 2f64.powi(step);
        e -= step;
    }
    x
}

/// The exact sum, over every block of every process, of `blocks` (this process's
/// blocks, each of length `dim`): the same bits for any split of the blocks
/// between processes (see the [module docs](self)). Every process must call it
/// with the same `dim`.
///
/// ```
/// use ssm::util::reduce::{exact_sum, SingleProcess};
/// let blocks = vec![vec![1e16, 1.0], vec![1.0, -3.0], vec![-1e16, 0.5]];
/// let fwd = exact_sum(&blocks, 2, &SingleProcess);
/// let rev: Vec<Vec<f64>> = blocks.iter().rev().cloned().collect();
/// assert_eq!(fwd, exact_sum(&rev, 2, &SingleProcess));
/// assert_eq!(fwd, vec![1.0, -1.5]); // naive left-to-right gives 0.0 for the first
/// ```
///
/// # Panics
/// If a block does not have length `dim`.
pub fn exact_sum(blocks: &[Vec<f64>], dim: usize, comm: &dyn Collective) -> Vec<f64> {
    // The largest magnitude per component (non-finite as +inf), and in the last
    // slot the largest block count of any process (a bound on the total: size x max).
    let mut max = vec![0.0f64; dim + 1];
    for b in blocks {
        assert_eq!(b.len(), dim, "exact_sum: a block of {} values, expected {dim}", b.len());
        for (m, &x) in max.iter_mut().zip(b) {
            let a = if x.is_finite() { x.abs() } else { f64::INFINITY };
            if a > *m {
                *m = a;
            }
        }
    }
    max[dim] = blocks.len() as f64;
    comm.max_f64(&mut max);
    let total_blocks = (max[dim] as u64).saturating_mul(comm.size().max(1) as u64).max(1);
    // Headroom for the sum: 2^headroom >= total blocks.
    let headroom = 64 - (total_blocks - 1).leading_zeros() as i32;
    // Per component: the grid exponent `s` with every scaled block below 2^(62 - headroom).
    let exps: Vec<Option<i32>> = max[..dim]
        .iter()
        .map(|&m| {
            if m.is_finite() && m > 0.0 {
                // m < 2^(exp), with exp = floor(log2 m) + 1.
                let (_, exp) = frexp(m);
                Some(62 - headroom - exp)
            } else {
                None
            }
        })
        .collect();
    let mut sums = vec![0i64; dim];
    for b in blocks {
        for ((s, &x), e) in sums.iter_mut().zip(b).zip(&exps) {
            if let Some(e) = e {
                *s += scale_pow2(x, *e).round() as i64;
            }
        }
    }
    comm.sum_i64(&mut sums);
    sums.iter()
        .zip(&exps)
        .zip(&max[..dim])
        .map(|((&s, e), &m)| match e {
            Some(e) => scale_pow2(s as f64, -e),
            None if m == 0.0 => 0.0,
            None => f64::NAN,
        })
        .collect()
}

/// `(mantissa, exponent)` with `x = mantissa * 2^exponent` and `0.5 <= |mantissa| < 1`,
/// for finite nonzero `x`.
fn frexp(x: f64) -> (f64, i32) {
    let bits = x.to_bits();
    let biased = ((bits >> 52) & 0x7ff) as i32;
    if biased == 0 {
        // Subnormal: normalise first.
        let (m, e) = frexp(x * 2f64.powi(64));
        return (m, e - 64);
    }
    let e = biased - 1022;
    let m = f64::from_bits((bits & !(0x7ff << 52)) | (1022u64 << 52));
    (m, e)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn frexp_matches_the_definition() {
        for x in [1.0, 0.75, 3.0, -1e300, 1e-310, 5e-324, 123456.789] {
            let (m, e) = frexp(x);
            assert!((0.5..1.0).contains(&m.abs()), "{x}: mantissa {m}");
            assert_eq!(scale_pow2(m, e), x);
        }
    }

    /// The exact sum of `blocks` dealt round-robin to `size` simulated processes;
    /// every process must get the same answer, which is returned.
    fn split_sum(blocks: &[Vec<f64>], dim: usize, size: usize) -> Vec<f64> {
        let group = ThreadGroup::new(size);
        let answers: Vec<Vec<f64>> = std::thread::scope(|scope| {
            let handles: Vec<_> = (0..size)
                .map(|rank| {
                    let comm = group.member(rank);
                    let owners = assign_blocks(&vec![1.0; blocks.len()], size);
                    let mine: Vec<Vec<f64>> =
                        blocks.iter().enumerate().filter(|(b, _)| owners[*b] == rank).map(|(_, v)| v.clone()).collect();
                    scope.spawn(move || exact_sum(&mine, dim, &comm))
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for a in &answers[1..] {
            assert_eq!(to_bits(a), to_bits(&answers[0]), "processes disagree");
        }
        answers[0].clone()
    }

    fn to_bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    #[test]
    fn share_first_gives_every_process_the_first_ones_values_exactly() {
        let first = [1.5, f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -0.0, -2.25e-300];
        for size in [1, 2, 3] {
            let group = ThreadGroup::new(size);
            let answers: Vec<Vec<f64>> = std::thread::scope(|scope| {
                let handles: Vec<_> = (0..size)
                    .map(|rank| {
                        let comm = group.member(rank);
                        // The others hold values larger than the first's.
                        let mut mine = if rank == 0 { first.to_vec() } else { vec![f64::MAX; first.len()] };
                        scope.spawn(move || {
                            comm.share_first(&mut mine);
                            mine
                        })
                    })
                    .collect();
                handles.into_iter().map(|h| h.join().unwrap()).collect()
            });
            for a in &answers {
                assert_eq!(to_bits(a), to_bits(&first), "{size} processes");
            }
        }
    }

    #[test]
    fn any_split_and_order_gives_the_same_bits() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for magnitude in [1e-300, 1e-3, 1.0, 1e8, 1e300] {
            let dim = 5;
            let blocks: Vec<Vec<f64>> = (0..37)
                .map(|_| {
                    (0..dim)
                        .map(|_| magnitude * (rng.random::<f64>() - 0.5) * 10f64.powi(rng.random_range(-6..6)))
                        .collect()
                })
                .collect();
            let reference = exact_sum(&blocks, dim, &SingleProcess);
            let mut shuffled = blocks.clone();
            for i in (1..shuffled.len()).rev() {
                let j = rng.random_range(0..=i);
                shuffled.swap(i, j);
            }
            assert_eq!(reference, exact_sum(&shuffled, dim, &SingleProcess));
            for size in [1, 2, 3, 5] {
                assert_eq!(to_bits(&reference), to_bits(&split_sum(&shuffled, dim, size)), "{size} processes");
            }
            // Close to the correctly rounded sum (within the grid's resolution).
            for c in 0..dim {
                let naive: f64 = blocks.iter().map(|b| b[c]).sum();
                let scale = blocks.iter().map(|b| b[c].abs()).fold(0.0, f64::max);
                assert!((reference[c] - naive).abs() <= 1e-12 * scale, "{c}: {} vs {naive}", reference[c]);
            }
        }
    }

    #[test]
    fn non_finite_blocks_give_nan_and_zeros_give_zero() {
        let blocks = vec![vec![1.0, 0.0, f64::INFINITY], vec![2.0, 0.0, 1.0]];
        let s = exact_sum(&blocks, 3, &SingleProcess);
        assert_eq!(s[0], 3.0);
        assert_eq!(s[1], 0.0);
        assert!(s[2].is_nan());
        let nan = exact_sum(&[vec![f64::NAN]], 1, &SingleProcess);
        assert!(nan[0].is_nan());
        assert_eq!(exact_sum(&[], 2, &SingleProcess), vec![0.0, 0.0]);
    }
}
