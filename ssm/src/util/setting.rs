//! The one error of every settings check ([`SettingError`]): a filter's
//! tempering, a defensive proposal, an estimator's name, a diagnosis's
//! configuration. It names the setting, the value given and what was expected,
//! so a command-line program can point at the flag or the config field.

use std::fmt;

/// A setting outside what it may be.
///
/// ```
/// use ssm::util::setting::SettingError;
/// let e = SettingError::new("tempering.ess_fraction", 1.5, "in (0, 1)");
/// assert_eq!(e.setting, "tempering.ess_fraction");
/// assert_eq!(e.to_string(), "tempering.ess_fraction = 1.5: expected in (0, 1)");
/// ```
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SettingError {
    /// The setting, as its config field or flag is named (`tempering.max_stages`).
    pub setting: String,
    /// The value given, as written.
    pub value: String,
    /// What it must be.
    pub expected: String,
}

impl SettingError {
    /// `setting` was `value`, which is not `expected`.
    pub fn new(setting: impl Into<String>, value: impl fmt::Display, expected: impl Into<String>) -> Self {
        SettingError { setting: setting.into(), value: value.to_string(), expected: expected.into() }
    }

    /// Fails with this error unless `ok`.
    pub fn check(
        ok: bool,
        setting: impl Into<String>,
        value: impl fmt::Display,
        expected: impl Into<String>,
    ) -> Result<(), Self> {
        if ok {
            Ok(())
        } else {
            Err(SettingError::new(setting, value, expected))
        }
    }
}

impl fmt::Display for SettingError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} = {}: expected {}", self.setting, self.value, self.expected)
    }
}

impl std::error::Error for SettingError {}

impl From<SettingError> for String {
    fn from(e: SettingError) -> String {
        e.to_string()
    }
}
