//! Configuration files: the error every option validation returns (which option, what
//! value, what is allowed), and the TOML file type the server and bake configurations share.

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;

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

/// A configuration file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    // The OS's words are in the message, not a `source`: printed as a chain, they
    // would appear twice.
    #[error("{}: {reason}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        reason: std::io::Error,
    },
    /// Not valid TOML, an unknown key, or a value of the wrong type.
    #[error("{}: {message}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's message: line, column and key.
        message: String,
    },
    /// A value outside its allowed range.
    #[error("{}: [{section}] {reason}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// The section holding the key.
        section: &'static str,
        /// Which key, what value, what is allowed.
        reason: InvalidOption,
    },
}

/// A configuration file type: parsed from TOML, then validated section by section.
pub trait ConfigFile: DeserializeOwned + Default {
    /// The shipped defaults (the file in `config/`).
    const DEFAULT_TOML: &'static str;

    /// Checks every value; the error names the section and key.
    fn validate(&self) -> Result<(), (&'static str, InvalidOption)>;

    /// Parses and validates TOML text; `path` only names the source in errors.
    fn from_toml(text: &str, path: &Path) -> Result<Self, ConfigError> {
        let config: Self = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: path.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        config
            .validate()
            .map_err(|(section, reason)| ConfigError::Invalid {
                path: path.to_path_buf(),
                section,
                reason,
            })?;
        Ok(config)
    }

    /// Loads `path`, or the built-in defaults when `None`.
    fn load(path: Option<&Path>) -> Result<Self, ConfigError> {
        match path {
            None => Ok(Self::default()),
            Some(path) => {
                let text = std::fs::read_to_string(path).map_err(|reason| ConfigError::Read {
                    path: path.to_path_buf(),
                    reason,
                })?;
                Self::from_toml(&text, path)
            }
        }
    }
}
