//! `server.toml`: the map server's configuration, validated section by section.

use kfmap_geometry::cloud::FilterOptions;
use kfmap_geometry::cov::CovOptions;
use kfmap_geometry::options::{ConfigFile, InvalidOption, ensure};
use kfmap_geometry::tracking::TrackingParams;
use kfmap_map::place::RelocalizeParams;
use kfmap_protocol::Cov2CovMode;
use kfmap_protocol::transport::{MAX_CLIENTS, MAX_CLIENTS_PER_PROCESS};
use serde::{Deserialize, Serialize};

/// The default `config/server.toml`, as shipped.
pub const DEFAULT_SERVER_TOML: &str = include_str!("../../config/server.toml");

/// `[server]` of `server.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct ServerSection {
    /// Map name used in service names; empty means the map file's stem.
    pub map_name: String,
    /// Worker threads; 0 means one per core.
    pub worker_threads: usize,
    /// Largest scan a client may send, in points.
    pub max_points_per_request: usize,
    /// Cov2cov mode of requests that leave it to the server: "map-default" (what the
    /// map was baked with, `[map] cov2cov-mode`), "approximate" or "exact".
    pub cov2cov_mode: Cov2CovMode,
    /// Largest answer, bytes of pairings: a request whose worst case is larger is
    /// refused before any work.
    pub max_answer_bytes: u64,
    /// Most map points one `Radius` query point may find; a point finding more stops
    /// the request with a status naming this limit.
    pub max_radius_points: u32,
    /// Memory one client process's requests in flight (worst case from each request's
    /// header: answer, its shared-memory copy and scratch) and its unread answers may
    /// hold at once, bytes.
    pub client_memory_budget: u64,
    /// Memory every client's requests in flight and unread answers may hold at once,
    /// bytes.
    pub memory_budget: u64,
    /// Requests one process (all its clients together) may have queued or in flight.
    pub max_requests_per_process: u32,
    /// Client ports of one process served at once; requests through its further
    /// ports are refused (Busy) until some close.
    pub max_clients_per_process: usize,
}

impl Default for ServerSection {
    fn default() -> Self {
        Self {
            map_name: String::new(),
            worker_threads: 0,
            max_points_per_request: 1 << 20,
            cov2cov_mode: Cov2CovMode::MapDefault,
            max_answer_bytes: 256 << 20,
            max_radius_points: 4096,
            client_memory_budget: 1 << 30,
            memory_budget: 2 << 30,
            max_requests_per_process: 16,
            max_clients_per_process: MAX_CLIENTS_PER_PROCESS,
        }
    }
}

impl ServerSection {
    fn validate(&self) -> Result<(), InvalidOption> {
        let name_ok = self
            .map_name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c));
        ensure(
            name_ok,
            "map-name",
            format!("{:?}", self.map_name),
            "letters, digits, '-', '_' and '.' only",
        )?;
        ensure(
            self.worker_threads <= 1024,
            "worker-threads",
            self.worker_threads,
            "0 (one per core) to 1024",
        )?;
        let max = self.max_points_per_request;
        ensure(
            (1..=1 << 26).contains(&max),
            "max-points-per-request",
            max,
            "1 to 67108864 points",
        )?;
        ensure(
            (1 << 20..=1 << 40).contains(&self.max_answer_bytes),
            "max-answer-bytes",
            self.max_answer_bytes,
            "1 MiB (1048576) to 1 TiB",
        )?;
        ensure(
            (1..=1 << 24).contains(&self.max_radius_points),
            "max-radius-points",
            self.max_radius_points,
            "1 to 16777216",
        )?;
        ensure(
            self.client_memory_budget >= 2 * self.max_answer_bytes,
            "client-memory-budget",
            self.client_memory_budget,
            "at least twice max-answer-bytes (an answer and its shared-memory copy)",
        )?;
        ensure(
            self.memory_budget >= self.client_memory_budget,
            "memory-budget",
            self.memory_budget,
            "at least client-memory-budget",
        )?;
        ensure(
            (1..=4096).contains(&self.max_requests_per_process),
            "max-requests-per-process",
            self.max_requests_per_process,
            "1 to 4096",
        )?;
        ensure(
            (1..=MAX_CLIENTS).contains(&self.max_clients_per_process),
            "max-clients-per-process",
            self.max_clients_per_process,
            &format!("1 to {MAX_CLIENTS} (the map's client port table)"),
        )
    }
}

/// `server.toml`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct ServerConfig {
    /// Process-level settings.
    pub server: ServerSection,
    /// Invalid-return filter for incoming scans.
    pub filter: FilterOptions,
    /// Covariances of incoming scans.
    pub covariance: CovOptions,
    /// Checks and retry ladder of server-side localization.
    pub tracking: TrackingParams,
    /// Global relocalization: the place search and the verdict's thresholds.
    pub relocalize: RelocalizeParams,
}

impl ConfigFile for ServerConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_SERVER_TOML;

    fn validate(&self) -> Result<(), (&'static str, InvalidOption)> {
        self.server.validate().map_err(|e| ("server", e))?;
        self.filter.validate().map_err(|e| ("filter", e))?;
        self.covariance.validate().map_err(|e| ("covariance", e))?;
        self.tracking.validate().map_err(|e| ("tracking", e))?;
        self.relocalize.validate().map_err(|e| ("relocalize", e))
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use kfmap_geometry::options::ConfigError;

    use super::*;

    #[test]
    fn shipped_file_equals_the_code_defaults() {
        let server =
            ServerConfig::from_toml(DEFAULT_SERVER_TOML, Path::new("config/server.toml")).unwrap();
        assert_eq!(server, ServerConfig::default());
    }

    #[test]
    fn shipped_file_lists_every_option() {
        kfmap_testdata::assert_lists_every_option(
            &toml::to_string(&ServerConfig::default()).unwrap(),
            DEFAULT_SERVER_TOML,
        );
    }

    #[test]
    fn out_of_range_value_names_key_and_range() {
        let err = ServerConfig::from_toml(
            "[covariance]\nmin-correspondences-for-cov = 50\n",
            Path::new("s.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("s.toml") && err.contains("[covariance]"),
            "{err}"
        );
        assert!(
            err.contains("min-correspondences-for-cov")
                && err.contains("[3, k-correspondences-for-cov = 20]"),
            "{err}"
        );
        let err = ServerConfig::from_toml("[tracking]\ncoarse-voxel = 0\n", Path::new("s.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("[tracking]") && err.contains("coarse-voxel"),
            "{err}"
        );
        for (text, key) in [
            ("[relocalize]\nfound-tight-ratio = 2\n", "found-tight-ratio"),
            ("[relocalize]\nmin-range = 40\n", "min-range"),
            ("[relocalize.search]\ncandidates = 0\n", "candidates"),
            ("[filter]\nmin-range = -1\n", "min-range"),
        ] {
            let err = ServerConfig::from_toml(text, Path::new("s.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains(key), "{err}");
        }
    }

    #[test]
    fn missing_file_is_a_read_error() {
        let err = ServerConfig::load(Some(Path::new("/nonexistent/server.toml"))).unwrap_err();
        assert!(matches!(err, ConfigError::Read { .. }));
    }
}
