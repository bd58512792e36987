//! The diagnosis (SPEC §7): fit the base model, show what its simulation gets
//! wrong, name the cause among the catalogue's extensions, and measure the gain,
//! each on its own objects so that nothing is judged on the data that chose it.
//!
//! 1. **Split** the objects, seeded, into three disjoint parts: the *fit* part
//!    trains every model, the *check* part says what the base gets wrong (and so
//!    which extensions are plausible and where they start), the *evaluation*
//!    part measures the gain. ([`diagnose_split`] takes the fit part as given,
//!    e.g. KITTI's training sequences, and splits the held-out data in two.)
//! 2. **Fit the base** (neural policy and the observation network of the data's
//!    kind, from the network's own initialisation: nothing taken from the data
//!    or a generator) with PF-SEFI.
//! 3. **Check it** on the check part (`check_model`): the tempered filter's
//!    genealogy gives paths drawn from the particle smoother; along each path
//!    the model simulates replicated observations and actions; every statistic
//!    of [`super::checks`] is computed on the measured and the replicated data
//!    and calibrated over the draws (z, p, Holm correction).
//! 4. **Fit the plausible extensions**, each warm-started from the base at the
//!    values the check part's discrepancies suggest
//!    ([`Extension::initial_from_checks`](crate::models::extended::Extension::initial_from_checks)): an extension is plausible when a
//!    check that suggests it has an uncorrected p below
//!    [`DiagnoseConfig::plausible_p`] in the direction the extension moves that
//!    check ([`CheckResult::screen_p`](crate::criticism::checks::CheckResult::screen_p): a lag lowers the offset-speed slope, heavy
//!    tails raise the kurtosis; a discrepancy the other way is no sign of it), or
//!    always, with [`DiagnoseConfig::fit_all`]. With
//!    [`DiagnoseConfig::likelihood_screen`] an extension no check flagged is
//!    plausible too when its start raises the check part's likelihood over the
//!    base's ([`LikelihoodScreen`]); rule (d) below then asks the same of the
//!    fitted extension against the reference.
//!    With [`DiagnoseConfig::fitted_screen`] every extension is fitted, and one
//!    no check flagged is a candidate only when its *fitted* model raises the
//!    check part's likelihood over its reference's (one-sided sign-flip p
//!    below [`DiagnoseConfig::plausible_p`]); the others are reported as not
//!    admitted ([`NotAdmitted`]), neither checked again nor evaluated (unless
//!    an admitted candidate nests one: then it is evaluated for rule (e) and
//!    left out of step 5's Holm families), and cannot be the cause.
//!    A nesting extension's fit starts where its nested extension's fit ended
//!    ([`DiagnoseConfig::nesting_from_nested`]), so that rule (e) below
//!    compares its extra parameter, not two optimisations.
//!    With [`DiagnoseConfig::refit`] (the default) the base's parameters are
//!    refitted with the extension's — the base network gives back what it
//!    absorbed of the effect — within the extension's refit scope
//!    ([`Extension::refit_scope`](crate::models::extended::Extension::refit_scope), [`DiagnoseConfig::scoped_refits`]): every
//!    parameter for an extension of the observations, the policy alone (the
//!    observation network held) for one of the dynamics. The base alone is
//!    refitted the same way, in the same scope, from the same start, with the
//!    same seed and batches: this *reference* of the scope is what each of its
//!    candidates is compared with. Without it, only the extension's parameters
//!    are learned on top of the fixed base, which is the reference. Each fitted
//!    candidate is checked again on the check part. A scope's reseeded refit
//!    (rule (b)) is fitted only where a candidate of the scope is evaluated.
//! 5. **Decide on the evaluation part**: per object, the tempered filter's
//!    log-likelihood under the extended minus its scope's reference model, both
//!    filtered with the same seeds, over the objects every model measures (an
//!    object whose log-likelihood some model estimates with a Monte Carlo sd
//!    over the smallest gain that names a cause is filtered again with more
//!    particles, and set aside if it stays over: [`DiagnoseConfig::set_aside_unmeasured`]).
//!    The gain is their sum per observed unit. Its one-sided
//!    p-value comes from a sign-flip permutation test over objects ([`sign_flip_p`]:
//!    no normality, robust to a few objects carrying the sum), Holm-adjusted over
//!    the fitted candidates. The cause is the extension with the largest
//!    evaluation log-likelihood among those that (a) pass at [`DiagnoseConfig::cause_level`], (b) gain at
//!    least [`DiagnoseConfig::min_gain`] nats per unit and beat the refits' own
//!    noise ([`DiagnoseConfig::refit_noise`]: the base refitted alone in the
//!    scope with another seed; the candidate's gain over that refit, paired by object,
//!    passes the same test and the same minimum, [`beats_reseeded`]), (c) change the model
//!    materially, (d) improve a check that flagged them (its |z| on the check
//!    part falls below the reference's, or the extension carries it past the
//!    measured value without failing it where the reference still flagged it:
//!    [`improves_flagged_checks`]; one the likelihood screen admitted must
//!    raise the check part's likelihood over the reference's) and (e),
//!    for an extension that contains another fitted candidate as a special case
//!    ([`Extension::nests`](crate::models::extended::Extension::nests): persistent flips at persistence 0 are independent
//!    ones), beat that candidate by object with the same test and minimum
//!    ([`nested_comparisons`]): the larger model is named only where its extra
//!    parameter earns its place.
//! 6. **The outcome**: the cause; else `unexplained` when some check of the
//!    reference fails at the family-wise level (the model is wrong in a way the
//!    catalogue does not cover); else `none`.
//!
//! Every training run writes its logs and checkpoints under the output
//! directory, and a finished or interrupted run is resumed rather than redone.
//!
//! One idea a file: this one holds the entry points ([`diagnose`],
//! [`diagnose_split`]); `config.rs` the settings; `split.rs` the object split;
//! `fits.rs` the fit schedules, run directories and training runs;
//! `references.rs` the refits of the base the candidates are compared with;
//! `screen.rs` the screens of what no check flagged; `rules.rs` the decision
//! rules (a)–(e) and the choice of the cause; `pipeline.rs` steps 2–6;
//! `unmeasured.rs` the objects a model does not measure; `dispatch.rs` the
//! dispatch over the data's models; `report.rs` the report's schema;
//! `judge.rs` the reading of a stored report under the current rules;
//! `progress.rs` the progress stages; `protocol.rs` the named versions of
//! the rules; `heldout.rs` the held-out evaluation and
//! the paired comparison of two models, `replicated.rs` the replicated
//! (posterior predictive) checks.
//! The paths the checks draw come from [`crate::filter::paths`].

mod config;
mod dispatch;
mod fits;
mod heldout;
mod judge;
mod pipeline;
mod progress;
mod protocol;
mod references;
mod replicated;
mod report;
mod rules;
mod screen;
mod split;
#[cfg(test)]
mod testing;
mod unmeasured;

pub use config::{DiagnoseConfig, MIN_GAIN};
pub use fits::TRAINING_RUN_DIRS;
pub use heldout::{gains_by_group, paired_gain, sign_flip_p, GroupGain};
pub use judge::{EvalPart, StudyDecision};
pub use progress::Stage;
pub use protocol::{Protocol, Screen, DEFAULT_PROTOCOL, PROTOCOLS};
pub use report::{
    CandidateReport, CheckReport, ImpreciseObject, NotAdmitted, ReferenceReport, Report, ReseededReport,
    REPORT_FORMAT_VERSION,
};
pub use rules::{
    beats_reseeded, flagged_check_moves, improves_flagged_checks, nested_comparisons, FailedRule, NestedComparison,
    NO_FLAGGING_CHECK,
};
pub use screen::LikelihoodScreen;
pub use split::{split_objects, ObjectSplit};

use std::path::Path;
use std::sync::Arc;

use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::SeedableRng;

use crate::data::Dataset;
use crate::util::reduce::Collective;

use pipeline::run;
use split::Parts;

/// The outcome when no extension qualifies but some check fails at the
/// family-wise level: the model is wrong in a way the catalogue does not cover.
pub const UNEXPLAINED: &str = "unexplained";
/// The outcome when no extension qualifies and no check fails.
pub const NO_CAUSE: &str = "none";

/// Runs the diagnosis of `data`, writing training runs under `out_dir`
/// (`base/`, `candidates/<id>/`), as one process of the job `comm`
/// ([`SingleProcess`](crate::util::reduce::SingleProcess) alone). In a job of many,
/// every process runs the whole diagnosis on the whole data; each fit's
/// training steps are shared between the processes (each holds its share of
/// the fit part's objects, [`SceneObjective::for_process`](crate::training::objective::SceneObjective::for_process)), the checks and held-out
/// evaluations are repeated on every process (they are deterministic, so every
/// process takes the same decisions), and only the first writes files.
pub fn diagnose(
    data: &Dataset,
    config: &DiagnoseConfig,
    out_dir: &Path,
    comm: &Arc<dyn Collective>,
    progress: &mut dyn FnMut(&Stage),
) -> Result<Report, String> {
    config.validate()?;
    let (fit, check, eval) = split_objects(data, config.fit_fraction, config.check_fraction, config.seed)?;
    let parts = Parts {
        fit: &data.select_objects(&fit),
        check: &data.select_objects(&check),
        eval: &data.select_objects(&eval),
    };
    run(parts, config, out_dir, comm, progress)
}

/// [`diagnose`] with a given fit part, `train_data` (e.g. KITTI's training
/// sequences); `heldout` is split, seeded, into the check and the evaluation
/// parts. Both must hold the same kind of observations and time step.
pub fn diagnose_split(
    train_data: &Dataset,
    heldout: &Dataset,
    config: &DiagnoseConfig,
    out_dir: &Path,
    comm: &Arc<dyn Collective>,
    progress: &mut dyn FnMut(&Stage),
) -> Result<Report, String> {
    config.validate()?;
    let kind = train_data.kind();
    if heldout.kind() != kind || heldout.dt() != train_data.dt() || heldout.steps() != train_data.steps() {
        return Err(format!(
            "the held-out data ({:?}, dt {}, {} steps) differ from the training data ({kind:?}, dt {}, {} steps)",
            heldout.kind(),
            heldout.dt(),
            heldout.steps(),
            train_data.dt(),
            train_data.steps()
        ));
    }
    let n = heldout.objects().len();
    if train_data.objects().is_empty() || n < 2 {
        return Err(format!(
            "the training data need at least one object and the held-out data two (check, evaluate); got {} and {n}",
            train_data.objects().len()
        ));
    }
    let share = config.check_fraction / (1.0 - config.fit_fraction);
    let check_n = ((n as f64 * share).round() as usize).clamp(1, n - 1);
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut StdRng::seed_from_u64(config.seed));
    let (mut check, mut eval) = (order[..check_n].to_vec(), order[check_n..].to_vec());
    check.sort_unstable();
    eval.sort_unstable();
    let parts = Parts { fit: train_data, check: &heldout.select_objects(&check), eval: &heldout.select_objects(&eval) };
    run(parts, config, out_dir, comm, progress)
}
