//! The split of a diagnosis's objects into its fit, check and evaluation parts.

use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::SeedableRng;

use crate::data::Dataset;

/// Disjoint `(fit, check, evaluate)` object indices, as [`split_objects`] returns them.
pub type ObjectSplit = (Vec<usize>, Vec<usize>, Vec<usize>);

/// Splits `data`'s objects, seeded, into disjoint `(fit, check, evaluate)`
/// object indices, each sorted and non-empty.
pub fn split_objects(data: &Dataset, fit_fraction: f64, check_fraction: f64, seed: u64) -> Result<ObjectSplit, String> {
    let n = data.objects().len();
    if n < 3 {
        return Err(format!("the data hold {n} object(s): a diagnosis needs at least 3 (fit, check, evaluate)"));
    }
    let fit = ((n as f64 * fit_fraction).round() as usize).clamp(1, n - 2);
    let check = ((n as f64 * check_fraction).round() as usize).clamp(1, n - fit - 1);
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut StdRng::seed_from_u64(seed));
    let sorted = |s: &[usize]| {
        let mut v = s.to_vec();
        v.sort_unstable();
        v
    };
    Ok((sorted(&order[..fit]), sorted(&order[fit..fit + check]), sorted(&order[fit + check..])))
}

/// The three disjoint parts of a diagnosis.
#[derive(Clone, Copy)]
pub(super) struct Parts<'a> {
    pub(super) fit: &'a Dataset,
    pub(super) check: &'a Dataset,
    pub(super) eval: &'a Dataset,
}

#[cfg(test)]
mod tests {
    use crate::data::ObservationKind;

    use super::*;

    /// Three disjoint, covering parts with the requested sizes.
    #[test]
    fn split_is_disjoint_and_covering() {
        let data = crate::criticism::hidden::generate_hidden(&crate::criticism::hidden::HiddenConfig::quick(
            ObservationKind::Points,
            crate::criticism::hidden::HiddenEffect::None,
            1,
        ))
        .unwrap();
        let n = data.objects().len();
        let (f, c, e) = split_objects(&data, 0.4, 0.2, 7).unwrap();
        let mut all: Vec<usize> = f.iter().chain(&c).chain(&e).copied().collect();
        all.sort_unstable();
        assert_eq!(all, (0..n).collect::<Vec<_>>());
        assert_eq!(f.len(), (n as f64 * 0.4).round() as usize);
        assert_eq!(c.len(), (n as f64 * 0.2).round() as usize);
    }
}
