//! The limits every request is checked against: fixed protocol bounds and the
//! per-server limits of `server.toml`.

use kfmap_geometry::cov::CovOptions;
use kfmap_geometry::tracking::TrackingParams;
use kfmap_map::place::RelocalizeParams;
use kfmap_protocol::{Cov2CovMode, WirePairing};

use crate::config::ServerConfig;

/// Largest `k` of a `Nearest` request.
pub const MAX_K: u32 = 64;

/// Most keyframes a `Nearest` request may ask to search (`keyframes`): as many as a
/// map's active set may hold.
pub const MAX_KEYFRAMES: u32 = kfmap_map::select::MAX_KEYFRAMES as u32;

/// Bytes of one answer pairing.
pub const PAIRING_BYTES: u64 = std::mem::size_of::<WirePairing>() as u64;

/// Largest radius of a `Radius` request and bound of a `Nearest` request, metres.
pub const MAX_RADIUS: f32 = 20.0;

/// Largest pairing distance of `Cov2Cov` / `Localize`, metres.
pub const MAX_PAIR_DIST: f32 = 50.0;

/// Most iterations of a `Localize` request.
pub const MAX_ITERATIONS: u32 = 100;

/// Largest `max_correction` of a `Localize` request, metres.
pub const MAX_CORRECTION: f32 = 1000.0;

/// Request limits from `server.toml`.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Points per scan, at most.
    pub max_points: usize,
    /// Map points one `Radius` query point may find, at most.
    pub max_radius_points: usize,
    /// Bytes of pairings one answer may hold.
    pub max_answer_bytes: u64,
    /// Covariances estimated for scans sent without them.
    pub scan_covariance: CovOptions,
    /// Checks and retry ladder of `Localize`.
    pub tracking: TrackingParams,
    /// Search and verdict of `Relocalize`.
    pub relocalize: RelocalizeParams,
    /// What `Cov2CovMode::MapDefault` requests get (`server.toml`); `MapDefault` here
    /// means the map's own choice (`bake.toml`).
    pub cov2cov_mode: Cov2CovMode,
}

impl Limits {
    /// The limits `server.toml` sets.
    pub fn of(config: &ServerConfig) -> Self {
        Self {
            max_points: config.server.max_points_per_request,
            max_radius_points: config.server.max_radius_points as usize,
            max_answer_bytes: config.server.max_answer_bytes,
            scan_covariance: config.covariance,
            tracking: config.tracking,
            relocalize: config.relocalize,
            cov2cov_mode: config.server.cov2cov_mode,
        }
    }
}

impl Default for Limits {
    /// The shipped `server.toml`'s.
    fn default() -> Self {
        Self::of(&ServerConfig::default())
    }
}
