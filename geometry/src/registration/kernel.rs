//! Robust kernels: the weight a residual keeps, from its Mahalanobis length.

use serde::{Deserialize, Serialize};

/// How large residuals are down-weighted (IRLS weights on `e = sqrt(r^T W r)`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum RobustKernel {
    /// Plain least squares.
    None,
    /// Quadratic up to `delta`, linear beyond.
    Huber {
        /// Threshold on `e`.
        delta: f64,
    },
    /// `w = 1 / (1 + (e / delta)^2)`.
    Cauchy {
        /// Scale of `e`.
        delta: f64,
    },
    /// `w = (delta^2 / (delta^2 + e^2))^2`: redescending, ignores gross outliers.
    GemanMcClure {
        /// Scale of `e`.
        delta: f64,
    },
}

impl RobustKernel {
    /// The weight of a residual whose squared Mahalanobis length is `e2`.
    #[inline]
    pub fn weight(&self, e2: f64) -> f64 {
        match *self {
            Self::None => 1.0,
            Self::Huber { delta } => {
                let e = e2.sqrt();
                if e <= delta { 1.0 } else { delta / e }
            }
            Self::Cauchy { delta } => 1.0 / (1.0 + e2 / (delta * delta)),
            Self::GemanMcClure { delta } => {
                let d2 = delta * delta;
                (d2 / (d2 + e2)).powi(2)
            }
        }
    }

    /// The robust cost of a residual whose squared length is `e2` (`e2` itself for
    /// least squares; `weight` is its derivative).
    pub fn rho(&self, e2: f64) -> f64 {
        match *self {
            Self::None => e2,
            Self::Huber { delta } => {
                let e = e2.sqrt();
                if e <= delta {
                    e2
                } else {
                    2.0 * delta * e - delta * delta
                }
            }
            Self::Cauchy { delta } => delta * delta * (1.0 + e2 / (delta * delta)).ln(),
            Self::GemanMcClure { delta } => delta * delta * e2 / (delta * delta + e2),
        }
    }

    /// The kernel's scale, if it has one.
    pub fn delta(&self) -> Option<f64> {
        match *self {
            Self::None => None,
            Self::Huber { delta } | Self::Cauchy { delta } | Self::GemanMcClure { delta } => {
                Some(delta)
            }
        }
    }
}
