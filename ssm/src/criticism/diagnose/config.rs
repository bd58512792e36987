//! The settings of a diagnosis ([`DiagnoseConfig`]): their defaults, the quick scale and their validation.

use serde::{Deserialize, Serialize};

use crate::filter::{FilterConfig, Sampling, Tempering};
use crate::util::setting::SettingError;

/// Settings of a diagnosis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DiagnoseConfig {
    /// Fraction of the objects that fit the models.
    pub fit_fraction: f64,
    /// Fraction of the objects that check the base (and choose and start the
    /// candidates); the rest measure the gain. With a given held-out set
    /// ([`diagnose_split`](crate::criticism::diagnose::diagnose_split)) it is split in the ratio `check : (1 - fit - check)`.
    pub check_fraction: f64,
    /// Seed of the split, the initialisation, training and the checks.
    pub seed: u64,
    /// PF-SEFI steps of the base fit.
    pub base_steps: usize,
    /// PF-SEFI steps of each extension's fit (warm-started from the base), and
    /// of the reference's with [`DiagnoseConfig::refit`].
    pub candidate_steps: usize,
    /// Refit every parameter with each extension's, and compare with the base
    /// refitted alone the same way (the reference); else learn only the
    /// extension's parameters on top of the fixed base. A network that was
    /// fitted without the extension has absorbed part of the effect: held fixed,
    /// it leaves the extension too little to explain (magnitudes biased low) or,
    /// added to what it absorbed, too much (a clutter term on top of a network
    /// that already scatters widely makes the far-point check worse). Reports
    /// written before this setting existed read as `false`.
    #[serde(default)]
    pub refit: bool,
    /// With [`DiagnoseConfig::refit`], refit the base alone a second time with
    /// another training seed (other batches and filter draws) and take its
    /// held-out gain over the reference as the refits' own noise: a cause's gain
    /// must exceed its size as well as [`DiagnoseConfig::min_gain`]. On KITTI
    /// two refits of one network that differ only in an extension that learned
    /// nothing (a latency of 0.001 s) were seen to differ by up to 1 nat per
    /// detection, as much as the effect named. Reports written before this
    /// setting existed read as `false`.
    #[serde(default)]
    pub refit_noise: bool,
    /// Training particles.
    pub particles: usize,
    /// Particles of the evaluation and of the smoother draws.
    pub eval_particles: usize,
    /// Fixed lag of PF-SEFI.
    pub lag: usize,
    /// Adam learning rate of the base fit.
    pub lr: f64,
    /// Adam learning rate of the extensions' fits and of the reference's,
    /// decaying to a tenth (an extension's stored values are scaled, see
    /// [`crate::models::extended`]). The default is the base fit's: a refit at
    /// twice that (0.02) was seen to throw a fitted network off (the reference
    /// of one heavy-tail diagnosis fell from -0.84 to -2.2 nats per point, with
    /// gradient norms of 8e4, while its candidates did not).
    pub candidate_lr: f64,
    /// The rate at which the refits (the references' and the candidates') move
    /// the base's parameters, decaying to a tenth like `candidate_lr`, which
    /// stays the rate of an extension's own parameters; `None` (the default):
    /// every parameter at `candidate_lr`. Refits restarted at the full rate from
    /// a base that ended at a tenth of it move their check MLLs on point data by
    /// more than a heavy tail's gain (README, "Every fit keeps its best
    /// evaluation"); the base's final rate (`lr / 10`) continues it where it ended.
    #[serde(default)]
    pub refit_base_lr: Option<f64>,
    /// Global gradient-norm clipping.
    pub clip: Option<f64>,
    /// Every fit (base, references, candidates) is evaluated on the check part
    /// (with the training filter and particles) every this many
    /// steps, and at its start and end, and keeps the parameters
    /// of its best evaluation (0: keeps its last, as reports written before this
    /// setting existed did). On box detections with reversed headings that no
    /// model explains, a fit was seen to turn its policy sharp on a few spinning
    /// paths and fall by 4–10 nats per detection within tens of steps; a
    /// candidate or a reference measured from there measures the fall. The check
    /// part chooses, so the gain stays out of sample on the evaluation part.
    #[serde(default)]
    pub keep_best_every: usize,
    /// The share of every fit's last steps whose iterates are averaged
    /// ([`TrainConfig::average_tail`](crate::training::TrainConfig::average_tail); 0: none, as reports written before this
    /// setting existed did). The fit then returns (and keep-best evaluates from
    /// the tail's start on) the mean of those iterates rather than the last one.
    #[serde(default)]
    pub average_tail: f64,
    /// Scenes per training step.
    pub scenes_per_step: usize,
    /// Paths drawn from the smoother per checked object (the checks' replicates).
    pub draws: usize,
    /// Filter runs (seeds, the same for every model) whose likelihood estimates
    /// are averaged for each evaluated object.
    pub eval_runs: usize,
    /// The filter of the checks and of the evaluation: tempered within a step,
    /// so that sharp observations do not leave it degenerate; `None` for the
    /// evaluation default of the data's observations
    /// ([`Tempering::for_observations`]: origin moves on box detections). The
    /// report records the one used.
    pub tempering: Option<Tempering>,
    /// Train with the tempered filter too (PF-SEFI on the bootstrap filter is
    /// biased where its weights degenerate; see the README's drift section).
    pub train_tempered: bool,
    /// The tempered filter of training; `None` for the training default of the
    /// data's observations (no origin moves). The report records the one used.
    #[serde(default)]
    pub train_tempering: Option<Tempering>,
    /// Family-wise level of the checks (Holm-corrected).
    pub alpha: f64,
    /// An extension is fitted when a check that suggests it has an uncorrected p
    /// below this, one-sided in the direction the extension moves the check
    /// ([`CheckResult::screen_p`](crate::criticism::checks::CheckResult::screen_p); two-sided for extents, which it moves either way).
    pub plausible_p: f64,
    /// Fit every extension that applies to the data, plausible or not (only a
    /// flagged one can be the cause).
    pub fit_all: bool,
    /// Screen the extensions no check flagged by the likelihood as well
    /// ([`LikelihoodScreen`](crate::criticism::diagnose::LikelihoodScreen)): one that at its start raises the check part's
    /// likelihood over the base's, with a one-sided sign-flip p over the check
    /// objects below [`DiagnoseConfig::plausible_p`], is fitted too. Off by
    /// default (measured on a few cells only; README, "A likelihood screen").
    #[serde(default)]
    pub likelihood_screen: bool,
    /// Screen the extensions no check flagged by the likelihood of their
    /// *fitted* model: every such extension is fitted, and it is a candidate
    /// (tested in step 5's Holm family, rule (d) passed) only when its fitted
    /// model raises the check part's likelihood over its scope's reference
    /// with a one-sided sign-flip p over the check objects below
    /// [`DiagnoseConfig::plausible_p`] ([`CandidateReport::check_part_p`](crate::criticism::diagnose::CandidateReport::check_part_p)).
    /// Plausibility still comes from the check part alone, and the gain from
    /// the evaluation part alone; what it adds over the checks is a screen
    /// that a summary statistic cannot miss, at the cost of fitting every
    /// extension (one it does not admit is not checked again nor evaluated:
    /// [`NotAdmitted`](crate::criticism::diagnose::NotAdmitted)). Off by default; excludes [`DiagnoseConfig::fit_all`] and
    /// [`DiagnoseConfig::likelihood_screen`]; a report written before it reads
    /// `false`.
    #[serde(default)]
    pub fitted_screen: bool,
    /// The fitted screen's futility stop, as a share of a refit's steps (0:
    /// none). An extension the fitted screen fits (no check flagged it) is
    /// paused at the first evaluation at or after this share of its steps
    /// ([`DiagnoseConfig::keep_best_every`]); unless its best evaluation on the
    /// check part so far is above the base's (its reference's start: the same
    /// parameters, filter and seed), it is not continued and not admitted
    /// ([`NotAdmitted::stopped_at`](crate::criticism::diagnose::NotAdmitted::stopped_at)). Otherwise it continues to the end, the
    /// same run as without the stop, and the screen decides as before. An
    /// extension that another nests (`heading_flip`) is always fitted in full,
    /// since rule (e) may compare them; and the reference in the dynamics scope
    /// is fitted only where an extension of that scope was not stopped. A stop
    /// can only turn an extension away, never admit one, so it saves the
    /// screen's fits of extensions that gain nothing without adding a false
    /// cause. 1/3 by default; a report written before it reads 0.
    #[serde(default)]
    pub screen_futility: f64,
    /// Start a nesting extension's fit (`persistent_flip`) where its nested
    /// extension's fit (`heading_flip`) ended, when both are fitted: the base's
    /// parameters as the nested fit left them and the values the two share (the
    /// fraction) from it, the rest (the persistence) from the checks
    /// ([`Extension::start_from_nested`](crate::models::extended::Extension::start_from_nested)). Rule (e) then compares the extra
    /// parameter rather than two optimisations from one start, of which the
    /// larger may stop short (README, "A nesting fit starts where its nested fit
    /// ended"). On by default; a report written before it reads `false`.
    #[serde(default)]
    pub nesting_from_nested: bool,
    /// Refit each candidate within its extension's [`RefitScope`](crate::models::extended::RefitScope) and compare
    /// it with the base refitted alone within the same scope: a dynamics
    /// extension (heavy tails) and its reference move the policy and hold the
    /// observation network at the base's fit; every other extension and its
    /// reference move every parameter. Each scope that has a candidate has its
    /// own reference and reseeded reference. On by default; a report written
    /// before it reads `false` (every refit moved every parameter).
    #[serde(default)]
    pub scoped_refits: bool,
    /// Set aside, before the decision, the evaluation objects on which the
    /// models cannot be compared: those whose held-out log-likelihood has a
    /// Monte Carlo sd (over the [`DiagnoseConfig::eval_runs`] runs) above the
    /// smallest gain that names a cause over the whole evaluation part
    /// ([`DiagnoseConfig::min_gain`] times its observed units) under any model
    /// evaluated: the references, their reseeded twins or a candidate. A
    /// difference with such an object is that filter's noise (and its
    /// estimate's downward bias) rather than the models', and can decide the
    /// sum alone. Decided from the runs' spreads, symmetrically in the models,
    /// so the sign-flip test over the other objects keeps its level; the report
    /// lists them ([`Report::eval_imprecise`](crate::criticism::diagnose::Report::eval_imprecise)). Before that, every model
    /// filters such objects again with [`DiagnoseConfig::refine_factor`] times
    /// the particles (the same seeds for every model, so the pairing holds),
    /// and an object the refined runs bring under the bar stays, with its
    /// refined estimates. On by default (protocol v7): over the power
    /// study's 130 cells it changed no outcome and moved the named gains by
    /// what the objects set aside had inflated (README, "Objects a model does
    /// not measure"). A report written before it reads `false` (every
    /// evaluation object kept).
    #[serde(default)]
    pub set_aside_unmeasured: bool,
    /// How many times the evaluation particles refine an object a model did
    /// not measure ([`DiagnoseConfig::set_aside_unmeasured`]; 1: no
    /// refinement). 8 by default: a filter's log-likelihood sd falls about as
    /// the square root of its particles (measured on one object: 1,035 nats
    /// at 1,024 particles, 386 at 8,192), so an object up to about 2.8 times
    /// over the bar can be brought under it.
    #[serde(default = "one")]
    pub refine_factor: usize,
    /// Family-wise level of the candidates' gain tests (Holm-corrected sign-flip
    /// p-values).
    pub cause_level: f64,
    /// The smallest gain that names a cause (nats per observed unit).
    pub min_gain: f64,
    /// Random sign flips of the permutation test.
    pub permutations: usize,
}

impl Default for DiagnoseConfig {
    /// The scale for measured data: half the objects fit, a fifth check, the
    /// rest evaluate; 600 base steps, 300 per extension (and for the reference),
    /// 512 training and 2048 evaluation particles (2 runs), L = 15, clipping at
    /// 0.5, learning rate 0.01 decaying to a tenth in every fit.
    fn default() -> Self {
        DiagnoseConfig {
            fit_fraction: 0.5,
            check_fraction: 0.2,
            seed: 0,
            base_steps: 600,
            candidate_steps: 300,
            refit: true,
            refit_noise: true,
            particles: 512,
            eval_particles: 2048,
            lag: 15,
            lr: 0.01,
            candidate_lr: 0.01,
            refit_base_lr: None,
            clip: Some(0.5),
            keep_best_every: 25,
            average_tail: 0.0,
            scenes_per_step: 16,
            draws: 50,
            eval_runs: 2,
            tempering: None,
            train_tempered: true,
            train_tempering: None,
            alpha: 0.05,
            plausible_p: 0.2,
            fit_all: false,
            likelihood_screen: false,
            fitted_screen: false,
            screen_futility: 1.0 / 3.0,
            nesting_from_nested: true,
            scoped_refits: true,
            set_aside_unmeasured: true,
            refine_factor: 8,
            cause_level: 0.05,
            min_gain: MIN_GAIN,
            permutations: 9999,
        }
    }
}

/// `1`: [`DiagnoseConfig::refine_factor`] of a report written before it existed.
pub(super) fn one() -> usize {
    1
}

/// The default [`DiagnoseConfig::min_gain`]: 0.003 nats per observed unit, about
/// 0.03 nats per object-step at ten points a step — a model that is that much
/// better predicts a 100-step track `e^3` times better.
pub const MIN_GAIN: f64 = 0.003;

impl DiagnoseConfig {
    /// A small scale for generated data (tests, demos): 300 base steps, 40% of the objects fit,
    /// 20% check, 40% evaluate.
    pub fn quick() -> Self {
        DiagnoseConfig {
            fit_fraction: 0.4,
            check_fraction: 0.2,
            base_steps: 300,
            candidate_steps: 150,
            particles: 256,
            eval_particles: 1024,
            lag: 8,
            draws: 40,
            eval_runs: 2,
            scenes_per_step: 4,
            ..DiagnoseConfig::default()
        }
    }

    /// Checks every setting.
    pub fn validate(&self) -> Result<(), SettingError> {
        let (f, c) = (self.fit_fraction, self.check_fraction);
        let fraction = |x: f64| x > 0.0 && x < 1.0;
        SettingError::check(fraction(f), "fit_fraction", f, "in (0, 1)")?;
        SettingError::check(fraction(c), "check_fraction", c, "in (0, 1)")?;
        SettingError::check(
            f + c < 1.0,
            "fit_fraction + check_fraction",
            f + c,
            "below 1, to leave objects to evaluate the gain",
        )?;
        SettingError::check(self.particles > 0, "particles", self.particles, "at least 1")?;
        SettingError::check(self.eval_particles > 0, "eval_particles", self.eval_particles, "at least 1")?;
        SettingError::check(self.eval_runs > 0, "eval_runs", self.eval_runs, "at least 1")?;
        SettingError::check(self.refine_factor > 0, "refine_factor", self.refine_factor, "at least 1")?;
        SettingError::check(self.draws >= 3, "draws", self.draws, "at least 3")?;
        SettingError::check(fraction(self.alpha), "alpha", self.alpha, "in (0, 1)")?;
        let p = self.plausible_p;
        SettingError::check(p > 0.0 && p <= 1.0, "plausible_p", p, "in (0, 1]")?;
        SettingError::check(fraction(self.cause_level), "cause_level", self.cause_level, "in (0, 1)")?;
        SettingError::check(self.permutations >= 99, "permutations", self.permutations, "at least 99")?;
        let g = self.min_gain;
        SettingError::check(g.is_finite() && g >= 0.0, "min_gain", g, "a non-negative number of nats per unit")?;
        let t = self.average_tail;
        SettingError::check((0.0..=1.0).contains(&t), "average_tail", t, "in [0, 1]")?;
        let u = self.screen_futility;
        SettingError::check((0.0..1.0).contains(&u), "screen_futility", u, "in [0, 1)")?;
        SettingError::check(
            !(self.fitted_screen && u > 0.0) || self.keep_best_every > 0,
            "keep_best_every",
            self.keep_best_every,
            "at least 1 for the fitted screen's futility stop (it reads the fits' evaluations); or screen_futility 0",
        )?;
        let screens = [self.fit_all, self.likelihood_screen, self.fitted_screen].into_iter().filter(|&on| on).count();
        SettingError::check(
            screens <= 1,
            "fit_all + likelihood_screen + fitted_screen",
            screens,
            "at most one of them on",
        )?;
        for tempering in self.tempering.iter().chain(&self.train_tempering) {
            tempering.validate()?;
        }
        let refit_base_lr = self.refit_base_lr.unwrap_or(self.candidate_lr);
        for (setting, lr) in [("lr", self.lr), ("candidate_lr", self.candidate_lr), ("refit_base_lr", refit_base_lr)] {
            SettingError::check(lr > 0.0 && lr.is_finite(), setting, lr, "positive and finite")?;
        }
        Ok(())
    }

    /// The tempering of the checks and evaluations ([`DiagnoseConfig::tempering`],
    /// resolved for the data by [`run`] before anything is filtered).
    pub(super) fn tempering(&self) -> Tempering {
        self.tempering.unwrap_or_default()
    }

    /// The tempering of training ([`DiagnoseConfig::train_tempering`], resolved
    /// likewise).
    pub(super) fn train_tempering(&self) -> Tempering {
        self.train_tempering.unwrap_or_default()
    }

    /// The Monte Carlo sd (nats) above which an evaluation object of a part
    /// with `units` observed units counts as unmeasured
    /// ([`DiagnoseConfig::set_aside_unmeasured`]): the smallest gain that names
    /// a cause over the whole part.
    pub fn unmeasured_bar(&self, units: usize) -> f64 {
        self.min_gain * units as f64
    }

    /// What the checks and the evaluation filter with ([`Evaluation`]).
    pub(super) fn evaluation(&self) -> Evaluation {
        Evaluation {
            particles: self.eval_particles,
            runs: self.eval_runs,
            tempering: self.tempering(),
            seed: self.seed,
            draws: self.draws,
        }
    }
}

/// The part of a [`DiagnoseConfig`] that the checks' replicates and the
/// held-out likelihoods read: their filter and how often it runs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Evaluation {
    /// Particles of each filter run ([`DiagnoseConfig::eval_particles`]).
    pub(super) particles: usize,
    /// Filter runs whose likelihood estimates are averaged per object
    /// ([`DiagnoseConfig::eval_runs`]); run `r` is seeded `seed + r`.
    pub(super) runs: usize,
    /// The filter's tempering ([`DiagnoseConfig::tempering`], resolved).
    pub(super) tempering: Tempering,
    /// The seed of the first run and of the smoother draws.
    pub(super) seed: u64,
    /// Paths drawn from the smoother per checked object ([`DiagnoseConfig::draws`]).
    pub(super) draws: usize,
}

impl Evaluation {
    /// The filter of run `run`.
    pub(super) fn filter(&self, run: usize) -> FilterConfig {
        FilterConfig::new(Sampling::new(self.particles, Some(self.tempering)), 0, self.seed + run as u64)
    }
}
