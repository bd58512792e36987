//! Options that several commands share, each declared once and flattened into
//! the commands that take it: the particle filter's settings ([`FilterArgs`]) and
//! the table methods' names ([`method_settings`], [`check_method`]).

use ssm::data::ObservationKind;
use ssm::estimators::Estimator;
use ssm::filter::{FilterPurpose, Tempering};

/// Which particle filter to run.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FilterKind {
    /// Tempering within a step with Metropolis moves: precise when sharp
    /// observations meet a broad prediction (the default).
    Tempered,
    /// The bootstrap filter (the paper's, and what the through-filter baselines need).
    Bootstrap,
}

/// The particle filter's settings on the command line.
#[derive(clap::Args, Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FilterArgs {
    /// Particle filter: `tempered` (tempering within a step, Metropolis moves) or
    /// `bootstrap` (the paper's; the through-filter baselines always use it).
    #[arg(long, value_enum, default_value_t = FilterKind::Tempered)]
    pub filter: FilterKind,
    /// Tempered filter: each stage keeps the conditional ESS at this fraction of N.
    #[arg(long, default_value_t = Tempering::default().ess_fraction)]
    pub temper_ess: f64,
    /// Tempered filter: Metropolis sweeps after each intermediate resampling.
    #[arg(long, default_value_t = Tempering::default().moves)]
    pub temper_moves: usize,
    /// Tempered filter: origin moves (the prior's noise, whole paths re-propagated)
    /// at every step up to this one, in training and evaluation; 0 for none.
    /// Default: by the data's observations and the filter's use (8 in evaluating
    /// box detections; none in training, or on point sets).
    #[arg(long)]
    #[serde(default = "no_origin_moves")]
    pub temper_origin_steps: Option<usize>,
}

impl FilterArgs {
    /// The evaluation filter `filter` with these parameters on observations of
    /// `kind`, validated.
    pub fn tempering_of(&self, filter: FilterKind, kind: ObservationKind) -> Result<Option<Tempering>, String> {
        FilterArgs { filter, ..self.clone() }.tempering(kind)
    }

    /// The tempering settings of the evaluation filter (`None` for the bootstrap
    /// filter) on observations of `kind`, validated.
    pub fn tempering(&self, kind: ObservationKind) -> Result<Option<Tempering>, String> {
        self.tempering_with(Tempering::for_observations(kind, FilterPurpose::Evaluation))
    }

    /// The tempering settings of `estimator`'s training filter on observations
    /// of `kind`: the through-filter baselines replay the bootstrap filter, so
    /// they get `None` whatever was asked.
    pub fn tempering_for(&self, estimator: &Estimator, kind: ObservationKind) -> Result<Option<Tempering>, String> {
        match estimator {
            Estimator::PfSefi(_) => self.tempering_with(Tempering::for_observations(kind, FilterPurpose::Training)),
            Estimator::ThroughFilter(_) => Ok(None),
        }
    }

    /// These settings over `default` (the rule's filter for the data and use).
    fn tempering_with(&self, default: Tempering) -> Result<Option<Tempering>, String> {
        match self.filter {
            FilterKind::Bootstrap => Ok(None),
            FilterKind::Tempered => {
                let t = Tempering {
                    ess_fraction: self.temper_ess,
                    moves: self.temper_moves,
                    origin_steps: self.temper_origin_steps.unwrap_or(default.origin_steps),
                    ..default
                };
                t.validate()?;
                Ok(Some(t))
            }
        }
    }

    /// A short name of the filter for tables (`tempered`, `bootstrap`).
    pub fn name(&self) -> &'static str {
        match self.filter {
            FilterKind::Tempered => "tempered",
            FilterKind::Bootstrap => "bootstrap",
        }
    }
}

/// What a run configuration written before origin moves existed meant: none.
fn no_origin_moves() -> Option<usize> {
    Some(0)
}

/// The suffix of a table's method that trains PF-SEFI on the tempered filter.
pub const TEMPERED_SUFFIX: &str = "-tempered";

/// A table method's estimator name and training filter: `<estimator>` on the
/// bootstrap filter (the paper's setting), `pf-sefi-tempered` on the tempered one.
pub fn method_settings(method: &str) -> (&str, FilterKind) {
    match method.strip_suffix(TEMPERED_SUFFIX) {
        Some(estimator) => (estimator, FilterKind::Tempered),
        None => (method, FilterKind::Bootstrap),
    }
}

/// Checks a table's method name (see [`method_settings`]).
pub fn check_method(method: &str, lag: usize, alpha: f64) -> Result<(), String> {
    let (estimator, filter) = method_settings(method);
    let parsed = Estimator::parse(estimator, lag, alpha)?;
    if filter == FilterKind::Tempered && !matches!(parsed, Estimator::PfSefi(_)) {
        return Err(format!("method `{method}`: only PF-SEFI runs on the tempered filter"));
    }
    Ok(())
}
