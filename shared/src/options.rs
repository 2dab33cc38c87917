//! The error every option validation returns: which option, what value, what is allowed.

/// An option value outside its allowed range.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("option `{option}` = {value} is invalid: allowed {allowed}")]
pub struct InvalidOption {
    /// Option name as written in the config files (kebab-case).
    pub option: &'static str,
    /// The value given, formatted.
    pub value: String,
    /// The allowed range or set, in words.
    pub allowed: String,
}

impl InvalidOption {
    /// Builds the error for `option` holding `value`.
    pub fn new(
        option: &'static str,
        value: impl std::fmt::Display,
        allowed: impl Into<String>,
    ) -> Self {
        Self {
            option,
            value: value.to_string(),
            allowed: allowed.into(),
        }
    }
}

/// Fails with [`InvalidOption`] unless `ok`.
pub fn ensure(
    ok: bool,
    option: &'static str,
    value: impl std::fmt::Display,
    allowed: &str,
) -> Result<(), InvalidOption> {
    if ok {
        Ok(())
    } else {
        Err(InvalidOption::new(option, value, allowed))
    }
}

/// Fails unless `value` is a finite distance > 0 m.
pub fn ensure_distance(option: &'static str, value: f64) -> Result<(), InvalidOption> {
    ensure(
        value.is_finite() && value > 0.0,
        option,
        value,
        "a finite distance > 0 m",
    )
}

/// Fails unless `value` is a share from 0 to 1.
pub fn ensure_ratio(option: &'static str, value: f64) -> Result<(), InvalidOption> {
    ensure((0.0..=1.0).contains(&value), option, value, "0 to 1")
}
