//! The screens of the extensions no check flagged: the likelihood screen of their starts
//! ([`LikelihoodScreen`]) and the fitted screen's admission of their fits.

use super::heldout::gain_of;
use super::heldout::sign_flip_p;

use serde::{Deserialize, Serialize};

use crate::filter::stream_seed;
use crate::models::extended::Extension;

use super::config::DiagnoseConfig;
use super::rules::SCREEN_PERMUTATIONS;

/// The likelihood screen's look at one extension no check flagged
/// ([`DiagnoseConfig::likelihood_screen`]): the extension at its start
/// ([`Extension::initial_from_checks`], on the base's parameters) against the
/// base, both filtered on the check part with the same seeds. A check is a
/// summary statistic that a flexible base can match while its likelihood
/// still falls short (measured: the base's observation network replicates
/// clutter's far points at twice the default clutter, where the clutter
/// extension gains over a nat per point); the likelihood is the screen that
/// such a base cannot match. An extension that starts at the identity (size
/// bias) gains nothing at its start and is never admitted by it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LikelihoodScreen {
    /// The extension's id.
    pub cause: String,
    /// The start's log-likelihood over the base's on the check part (nats
    /// per observed unit).
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub gain: f64,
    /// The gain's one-sided sign-flip p over the check objects.
    #[serde(deserialize_with = "crate::stats::nan_from_null")]
    pub p: f64,
    /// Whether `p` fell below [`DiagnoseConfig::plausible_p`], so the
    /// extension was fitted.
    pub admitted: bool,
}

impl LikelihoodScreen {
    /// The screen's verdict on extension `cause` from `d`, per check object
    /// the start's log-likelihood minus the base's (`units` observed units):
    /// the gain per unit, the one-sided sign-flip p (seeded by the diagnosis
    /// seed and `index`, the extension's place among those screened), and
    /// whether p is below [`DiagnoseConfig::plausible_p`].
    pub(super) fn judge(
        cause: &str,
        d: &[f64],
        units: usize,
        config: &DiagnoseConfig,
        index: usize,
    ) -> LikelihoodScreen {
        let p = sign_flip_p(d, config.permutations, stream_seed(config.seed ^ SCREEN_PERMUTATIONS, index as u64));
        LikelihoodScreen { cause: cause.into(), gain: gain_of(d, units).0, p, admitted: p < config.plausible_p }
    }
}

/// Which fitted extensions (each with its fitted-screen p, `None` where it was
/// not screened so) are checked again and evaluated as candidates: every one
/// admitted at `plausible_p`, and one an admitted extension nests (rule (e)
/// compares them on the evaluation part).
pub(super) fn to_evaluate(fitted: &[(Extension, Option<f64>)], plausible_p: f64) -> Vec<bool> {
    let is_admitted = |&(_, p): &(Extension, Option<f64>)| admitted(p, plausible_p);
    let nested_by_admitted =
        |extension: Extension| fitted.iter().any(|n| is_admitted(n) && n.0.nests() == Some(extension));
    fitted.iter().map(|f| is_admitted(f) || nested_by_admitted(f.0)).collect()
}

/// Whether a candidate whose fitted-screen p is `check_part_p` (`None`: not
/// screened so) is admitted at `plausible_p` ([`CandidateReport::admitted`]).
pub(super) fn admitted(check_part_p: Option<f64>, plausible_p: f64) -> bool {
    check_part_p.is_none_or(|p| p < plausible_p)
}

#[cfg(test)]
mod tests {
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;

    use super::*;
    use crate::criticism::diagnose::testing::wobble;

    /// The screen admits a start that raises the check objects' likelihood
    /// with p below `plausible_p`, gives its gain per unit, and never admits a
    /// start equal to the base (size bias at the identity: every difference 0)
    /// nor one that loses.
    #[test]
    fn the_likelihood_screen_admits_what_raises_the_check_part() {
        let config = DiagnoseConfig { seed: 3, ..DiagnoseConfig::quick() };
        let n = 20;
        let raises: Vec<f64> = (0..n).map(|i| 0.5 + 0.05 * wobble(i)).collect();
        let screen = LikelihoodScreen::judge("clutter", &raises, 4 * n, &config, 0);
        assert_eq!(screen.cause, "clutter");
        assert!(screen.admitted && screen.p < 1e-3, "{screen:?}");
        let total: f64 = raises.iter().sum();
        assert!((screen.gain - total / (4 * n) as f64).abs() < 1e-12, "{screen:?}");
        let identity = LikelihoodScreen::judge("size_bias", &vec![0.0; n], 4 * n, &config, 1);
        assert!(!identity.admitted && identity.p == 1.0 && identity.gain == 0.0, "{identity:?}");
        let loses: Vec<f64> = raises.iter().map(|d| -d).collect();
        assert!(!LikelihoodScreen::judge("latency", &loses, 4 * n, &config, 2).admitted);
        // Starts that change nothing but the filter's noise pass at about the
        // screen's level: a fifth of them.
        let mut rng = StdRng::seed_from_u64(11);
        let looks = 400;
        let admitted = (0..looks)
            .filter(|&k| {
                let d: Vec<f64> = (0..n).map(|_| rng.sample::<f64, _>(StandardNormal) * 0.05).collect();
                LikelihoodScreen::judge("heavy_tailed_accel", &d, 4 * n, &config, k).admitted
            })
            .count();
        let share = admitted as f64 / looks as f64;
        assert!((share - config.plausible_p).abs() < 0.06, "{admitted} of {looks}");
    }

    /// The fitted screen evaluates what it admits, and an extension it did
    /// not admit only where an admitted one nests it (rule (e) needs both).
    /// It is one way of fitting what no check flagged: it excludes `fit_all`
    /// and the likelihood screen.
    #[test]
    fn the_fitted_screen_evaluates_what_it_admits_and_what_that_nests() {
        use Extension::{HeadingFlip, Latency, PersistentFlip};
        let (inside, outside, level) = (Some(0.01), Some(0.5), 0.05);
        assert_eq!(to_evaluate(&[(HeadingFlip, outside), (PersistentFlip, inside)], level), [true, true]);
        assert_eq!(to_evaluate(&[(HeadingFlip, inside), (PersistentFlip, outside)], level), [true, false]);
        assert_eq!(to_evaluate(&[(HeadingFlip, outside), (PersistentFlip, outside)], level), [false, false]);
        // Flagged by a check (no fitted-screen p): always a candidate.
        assert_eq!(to_evaluate(&[(Latency, None), (HeadingFlip, outside)], level), [true, false]);
        assert_eq!(to_evaluate(&[(Latency, Some(level))], level), [false], "p at the level is not below it");
    }

    #[test]
    fn one_screen_of_what_no_check_flagged_at_a_time() {
        let fitted = DiagnoseConfig { fitted_screen: true, ..DiagnoseConfig::quick() };
        assert!(fitted.validate().is_ok());
        for other in [
            DiagnoseConfig { fit_all: true, ..fitted.clone() },
            DiagnoseConfig { likelihood_screen: true, ..fitted.clone() },
        ] {
            let err = other.validate().unwrap_err();
            assert!(err.to_string().contains("fitted_screen"), "{err}");
        }
    }
}
