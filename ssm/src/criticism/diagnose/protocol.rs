//! The protocol as data: every version of the diagnosis's rules that a
//! committed report or study was made with, each named once with what sets it
//! apart ([`PROTOCOLS`]). A diagnosis runs under one of them
//! ([`Protocol::apply`]); a stored report reads back under the one it was made
//! with ([`Protocol::of`]). The current default is [`DEFAULT_PROTOCOL`], frozen:
//! a change of a rule is a new version, not an edit of an old one.

use super::config::DiagnoseConfig;

/// How the extensions no check flagged are treated.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Screen {
    /// Only the extensions a check flags are fitted.
    Checks,
    /// Every extension that applies to the data is fitted
    /// ([`DiagnoseConfig::fit_all`]); only a flagged one can be the cause.
    FitAll,
    /// The likelihood screen of their starts ([`DiagnoseConfig::likelihood_screen`]).
    Likelihood,
    /// The fitted screen ([`DiagnoseConfig::fitted_screen`]).
    Fitted,
}

impl Screen {
    /// The screen a configuration's three switches select (`None` where more
    /// than one is on, which [`DiagnoseConfig::validate`] refuses).
    pub fn of(config: &DiagnoseConfig) -> Option<Screen> {
        match (config.fit_all, config.likelihood_screen, config.fitted_screen) {
            (false, false, false) => Some(Screen::Checks),
            (true, false, false) => Some(Screen::FitAll),
            (false, true, false) => Some(Screen::Likelihood),
            (false, false, true) => Some(Screen::Fitted),
            _ => None,
        }
    }

    /// Sets a configuration's three switches to this screen.
    pub fn apply_to(self, config: &mut DiagnoseConfig) {
        config.fit_all = self == Screen::FitAll;
        config.likelihood_screen = self == Screen::Likelihood;
        config.fitted_screen = self == Screen::Fitted;
    }
}

/// One named version of the diagnosis's rules: the settings that studies
/// switched, fixed together. Scale (steps, particles, draws) is not part of it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Protocol {
    /// Its name on the command line (`--protocol NAME`).
    pub name: &'static str,
    /// What it is, in a phrase.
    pub summary: &'static str,
    /// [`DiagnoseConfig::refit`].
    pub refit: bool,
    /// [`DiagnoseConfig::refit_noise`].
    pub refit_noise: bool,
    /// [`DiagnoseConfig::candidate_lr`].
    pub candidate_lr: f64,
    /// [`DiagnoseConfig::refit_base_lr`].
    pub refit_base_lr: Option<f64>,
    /// [`DiagnoseConfig::keep_best_every`].
    pub keep_best_every: usize,
    /// [`DiagnoseConfig::average_tail`].
    pub average_tail: f64,
    /// What is fitted of the extensions no check flagged.
    pub screen: Screen,
    /// [`DiagnoseConfig::screen_futility`] (read only by the fitted screen).
    pub screen_futility: f64,
    /// [`DiagnoseConfig::nesting_from_nested`].
    pub nesting_from_nested: bool,
    /// [`DiagnoseConfig::scoped_refits`].
    pub scoped_refits: bool,
    /// [`DiagnoseConfig::set_aside_unmeasured`].
    pub set_aside_unmeasured: bool,
    /// [`DiagnoseConfig::refine_factor`] (read only with `set_aside_unmeasured`).
    pub refine_factor: usize,
}

/// The name of the default protocol, frozen.
pub const DEFAULT_PROTOCOL: &str = "v7";

/// The fitted screen's futility stop of every protocol but one: a third of a refit's steps.
const FUTILITY: f64 = 1.0 / 3.0;

/// The first version: the extensions learned on top of the fixed base.
const V1: Protocol = Protocol {
    name: "v1",
    summary: "extensions learned on the fixed base, which is the reference",
    refit: false,
    refit_noise: false,
    candidate_lr: 0.02,
    refit_base_lr: None,
    keep_best_every: 0,
    average_tail: 0.0,
    screen: Screen::Checks,
    screen_futility: FUTILITY,
    nesting_from_nested: false,
    scoped_refits: false,
    set_aside_unmeasured: false,
    refine_factor: 1,
};
/// The base refitted with each extension and alone (the reference).
const V2: Protocol = Protocol {
    name: "v2",
    summary: "every parameter refitted; the base refitted alone is the reference",
    refit: true,
    candidate_lr: 0.01,
    ..V1
};
/// A reseeded refit of the base measures the refits' own noise (rule (b)).
const V3: Protocol = Protocol { name: "v3", summary: "v2 and the reseeded refit of rule (b)", refit_noise: true, ..V2 };
/// Every fit keeps its best evaluation on the check part.
const V4: Protocol = Protocol {
    name: "v4",
    summary: "v3 and every fit keeps its best check-part evaluation",
    keep_best_every: 25,
    ..V3
};
/// A nesting extension's fit starts where its nested one's ended.
const V5: Protocol = Protocol {
    name: "v5",
    summary: "v4 and a nesting fit starts where its nested fit ended",
    nesting_from_nested: true,
    ..V4
};
/// Each candidate is refitted within its extension's refit scope.
const V6: Protocol =
    Protocol { name: "v6", summary: "v5 and refits within each extension's scope", scoped_refits: true, ..V5 };
/// The objects a model does not measure are refined and set aside.
const V7: Protocol = Protocol {
    name: "v7",
    summary: "v6 and the objects a model does not measure refined, then set aside (the default)",
    set_aside_unmeasured: true,
    refine_factor: 8,
    ..V6
};

/// Every protocol, in order of version; a variant of a version follows it.
pub const PROTOCOLS: &[Protocol] = &[
    V1,
    V2,
    V3,
    V4,
    Protocol { name: "v4-fit-all", summary: "v4, every extension fitted", screen: Screen::FitAll, ..V4 },
    Protocol {
        name: "v4-likelihood-screen",
        summary: "v4 with the likelihood screen",
        screen: Screen::Likelihood,
        ..V4
    },
    Protocol {
        name: "v4-base-rate-0.001",
        summary: "v4, the base's parameters refitted at 0.001",
        refit_base_lr: Some(0.001),
        ..V4
    },
    Protocol { name: "v4-refit-rate-0.001", summary: "v4, every refit at 0.001", candidate_lr: 0.001, ..V4 },
    V5,
    Protocol {
        name: "v5-average-tail",
        summary: "v5, each fit's last half of iterates averaged",
        average_tail: 0.5,
        ..V5
    },
    V6,
    V7,
    Protocol {
        name: "v7-fitted-screen",
        summary: "v7 with the fitted screen and its futility stop",
        screen: Screen::Fitted,
        ..V7
    },
    Protocol {
        name: "v7-fitted-screen-full",
        summary: "v7 with the fitted screen, every screened extension fitted to its end",
        screen: Screen::Fitted,
        screen_futility: 0.0,
        ..V7
    },
];

impl Protocol {
    /// The protocol called `name`.
    pub fn named(name: &str) -> Result<&'static Protocol, String> {
        PROTOCOLS.iter().find(|p| p.name == name).ok_or_else(|| {
            let names: Vec<&str> = PROTOCOLS.iter().map(|p| p.name).collect();
            format!("no protocol `{name}`: the protocols are {}", names.join(", "))
        })
    }

    /// The default protocol ([`DEFAULT_PROTOCOL`]).
    pub fn default_protocol() -> &'static Protocol {
        Protocol::named(DEFAULT_PROTOCOL).expect("the default protocol is in the table")
    }

    /// Sets `config`'s rules to this protocol's (its scale and seed stay).
    pub fn apply(&self, config: &mut DiagnoseConfig) {
        config.refit = self.refit;
        config.refit_noise = self.refit_noise;
        config.candidate_lr = self.candidate_lr;
        config.refit_base_lr = self.refit_base_lr;
        config.keep_best_every = self.keep_best_every;
        config.average_tail = self.average_tail;
        self.screen.apply_to(config);
        config.screen_futility = self.screen_futility;
        config.nesting_from_nested = self.nesting_from_nested;
        config.scoped_refits = self.scoped_refits;
        config.set_aside_unmeasured = self.set_aside_unmeasured;
        config.refine_factor = self.refine_factor;
    }

    /// The protocol a diagnosis with `config` ran under (a stored report's,
    /// read with the defaults of settings it predates): the one whose rules it
    /// has. A setting no rule reads under the others is not compared (the
    /// futility stop without the fitted screen, the refinement without the
    /// set-aside). `None` for rules no protocol has.
    pub fn of(config: &DiagnoseConfig) -> Option<&'static Protocol> {
        let screen = Screen::of(config)?;
        PROTOCOLS.iter().find(|p| {
            p.refit == config.refit
                && p.refit_noise == config.refit_noise
                && p.candidate_lr == config.candidate_lr
                && p.refit_base_lr == config.refit_base_lr
                && p.keep_best_every == config.keep_best_every
                && p.average_tail == config.average_tail
                && p.screen == screen
                && (screen != Screen::Fitted || p.screen_futility == config.screen_futility)
                && p.nesting_from_nested == config.nesting_from_nested
                && p.scoped_refits == config.scoped_refits
                && p.set_aside_unmeasured == config.set_aside_unmeasured
                && (!config.set_aside_unmeasured || p.refine_factor == config.refine_factor)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The default configuration is the default protocol's, and every
    /// protocol applied to it reads back as itself: no two protocols share
    /// their rules.
    #[test]
    fn every_protocol_reads_back_as_itself() {
        let default = DiagnoseConfig::default();
        assert_eq!(Protocol::of(&default).map(|p| p.name), Some(DEFAULT_PROTOCOL));
        let mut applied = default.clone();
        Protocol::default_protocol().apply(&mut applied);
        assert_eq!(applied, default, "the default protocol sets the default's rules");
        for p in PROTOCOLS {
            let mut config = DiagnoseConfig::quick();
            p.apply(&mut config);
            assert!(config.validate().is_ok(), "{}", p.name);
            assert_eq!(Protocol::of(&config).map(|q| q.name), Some(p.name));
        }
        assert!(Protocol::named("v0").unwrap_err().contains(DEFAULT_PROTOCOL));
    }
}
