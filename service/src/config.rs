//! `server.toml` and `bake.toml`: one serde struct per section, defaults equal to the
//! files in `config/` (embedded here), unknown keys and out-of-range values rejected
//! with the file, the key and the allowed range.

use std::path::{Path, PathBuf};

use kfmap_shared::cloud::FilterOptions;
use kfmap_shared::cov::CovOptions;
use kfmap_shared::covis::CovisOptions;
use kfmap_shared::gravity::GravityParams;
use kfmap_shared::io::BinLayout;
use kfmap_shared::map::{ActiveSetMode, KeyframeDecider, KeyframeMapOptions};
use kfmap_shared::mapping::BuildParams;
use kfmap_shared::options::{InvalidOption, ensure};
use kfmap_shared::place::RelocalizeParams;
use kfmap_shared::protocol::Cov2CovMode;
use kfmap_shared::protocol::transport::{MAX_CLIENTS, MAX_CLIENTS_PER_PROCESS};
use kfmap_shared::select::SelectionOptions;
use kfmap_shared::tracking::TrackingParams;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// The default `config/server.toml`, as shipped.
pub const DEFAULT_SERVER_TOML: &str = include_str!("../../config/server.toml");
/// The default `config/bake.toml`, as shipped.
pub const DEFAULT_BAKE_TOML: &str = include_str!("../../config/bake.toml");

/// A configuration file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// What the OS said.
        source: std::io::Error,
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
    #[error("{}: [{section}] {source}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// The section holding the key.
        section: &'static str,
        /// Which key, what value, what is allowed.
        source: InvalidOption,
    },
}

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

/// `[input]` of `bake.toml`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct InputSection {
    /// Layout of headerless `.bin` scans.
    pub bin_layout: BinLayout,
}

impl Default for InputSection {
    fn default() -> Self {
        Self {
            bin_layout: BinLayout::Xyzi,
        }
    }
}

/// `[keyframes]` of `bake.toml`: when a scan becomes a keyframe, and its downsampling.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct KeyframeSection {
    /// New keyframe when the nearest one is strictly farther than this, metres.
    pub min_translation: f64,
    /// ... or strictly more than this away in rotation, degrees.
    pub min_rotation_deg: f64,
    /// Voxel grid applied to each keyframe's points, metres; 0 keeps every point.
    pub voxel_size: f64,
}

impl Default for KeyframeSection {
    fn default() -> Self {
        let decider = KeyframeDecider::default();
        Self {
            min_translation: decider.min_translation,
            min_rotation_deg: decider.min_rotation_deg,
            voxel_size: 0.1,
        }
    }
}

impl KeyframeSection {
    fn validate(&self) -> Result<(), InvalidOption> {
        let t = self.min_translation;
        ensure(
            t.is_finite() && t >= 0.0,
            "min-translation",
            t,
            "a finite distance >= 0 m",
        )?;
        let r = self.min_rotation_deg;
        ensure(
            r.is_finite() && r >= 0.0,
            "min-rotation-deg",
            r,
            "a finite angle >= 0 degrees",
        )?;
        let v = self.voxel_size;
        ensure(
            v == 0.0 || (v.is_finite() && v >= 0.001),
            "voxel-size",
            v,
            "0 (off) or a finite size >= 0.001 m",
        )
    }

    /// The keyframe decider these thresholds define.
    pub fn decider(&self) -> KeyframeDecider {
        KeyframeDecider {
            min_translation: self.min_translation,
            min_rotation_deg: self.min_rotation_deg,
        }
    }
}

/// `[map]` of `bake.toml`: what the baked file holds and how it is queried.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct MapSection {
    /// Active-set rule.
    pub active_set: ActiveSetMode,
    /// Reject pairings whose view directions differ by more than the angle below.
    pub use_view_direction_filter: bool,
    /// Degrees; 180 disables the filter.
    pub max_view_angle_deg: f64,
    /// Store KD-trees (else rebuilt when a keyframe is first used).
    pub serialize_kdtrees: bool,
    /// Store covariances (else recomputed when a keyframe is first used).
    pub serialize_covariances: bool,
    /// Rotate every keyframe pose by the gravity correction (IMU log needed) so the
    /// map has +Z up.
    pub align_gravity: bool,
    /// Voxelize keyframes on the map frame's grid and keep each point's raw count, so
    /// exact mode fuses keyframes that see the same place into the voxelization of
    /// their merged scans (no doubled surfaces where keyframes overlap).
    pub fuse_overlapping_keyframes: bool,
    /// How the server answers cov2cov requests that leave the mode to it:
    /// "approximate" (keyframe by keyframe, never rebuilds) or "exact" (a merged
    /// submap built inside the query each time the active set changes).
    pub cov2cov_mode: Cov2CovMode,
}

impl Default for MapSection {
    fn default() -> Self {
        let o = KeyframeMapOptions::default();
        Self {
            active_set: o.active_set,
            use_view_direction_filter: o.use_view_direction_filter,
            max_view_angle_deg: o.max_view_angle_deg,
            serialize_kdtrees: o.serialize_kdtrees,
            serialize_covariances: o.serialize_covariances,
            align_gravity: true,
            fuse_overlapping_keyframes: false,
            cov2cov_mode: Cov2CovMode::Approximate,
        }
    }
}

fn validate_filter(filter: &FilterOptions) -> Result<(), InvalidOption> {
    let r = filter.min_range;
    ensure(
        r.is_finite() && r >= 0.0,
        "min-range",
        r,
        "a finite distance >= 0 m",
    )
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

/// `bake.toml`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct BakeConfig {
    /// How input scans are read.
    pub input: InputSection,
    /// Invalid-return filter applied on load.
    pub filter: FilterOptions,
    /// Per-point covariances baked into the map.
    pub covariance: CovOptions,
    /// Keyframe creation and downsampling.
    pub keyframes: KeyframeSection,
    /// What the file holds; query options stored with the map.
    pub map: MapSection,
    /// Active-set selection stored with the map.
    pub selection: SelectionOptions,
    /// Covisibility graph.
    pub covisibility: CovisOptions,
    /// Gravity from the dataset's IMU log.
    pub gravity: GravityParams,
    /// Building poses from the scans (odometry, loops, pose graph).
    pub build: BuildParams,
}

impl BakeConfig {
    /// The options of the map this configuration bakes.
    pub fn map_options(&self) -> KeyframeMapOptions {
        KeyframeMapOptions {
            covariance: self.covariance,
            selection: self.selection,
            covisibility: self.covisibility,
            active_set: self.map.active_set,
            use_view_direction_filter: self.map.use_view_direction_filter,
            max_view_angle_deg: self.map.max_view_angle_deg,
            serialize_kdtrees: self.map.serialize_kdtrees,
            serialize_covariances: self.map.serialize_covariances,
            serve_exact: self.map.cov2cov_mode == Cov2CovMode::Exact,
            fuse_voxel_size: if self.map.fuse_overlapping_keyframes {
                self.keyframes.voxel_size
            } else {
                0.0
            },
            ..KeyframeMapOptions::default()
        }
    }
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
            .map_err(|(section, source)| ConfigError::Invalid {
                path: path.to_path_buf(),
                section,
                source,
            })?;
        Ok(config)
    }

    /// Loads `path`, or the built-in defaults when `None`.
    fn load(path: Option<&Path>) -> Result<Self, ConfigError> {
        match path {
            None => Ok(Self::default()),
            Some(path) => {
                let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
                    path: path.to_path_buf(),
                    source,
                })?;
                Self::from_toml(&text, path)
            }
        }
    }
}

impl ConfigFile for ServerConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_SERVER_TOML;

    fn validate(&self) -> Result<(), (&'static str, InvalidOption)> {
        self.server.validate().map_err(|e| ("server", e))?;
        validate_filter(&self.filter).map_err(|e| ("filter", e))?;
        self.covariance.validate().map_err(|e| ("covariance", e))?;
        self.tracking.validate().map_err(|e| ("tracking", e))?;
        self.relocalize.validate().map_err(|e| ("relocalize", e))
    }
}

impl ConfigFile for BakeConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_BAKE_TOML;

    fn validate(&self) -> Result<(), (&'static str, InvalidOption)> {
        validate_filter(&self.filter).map_err(|e| ("filter", e))?;
        self.covariance.validate().map_err(|e| ("covariance", e))?;
        self.keyframes.validate().map_err(|e| ("keyframes", e))?;
        self.selection.validate().map_err(|e| ("selection", e))?;
        self.covisibility
            .validate()
            .map_err(|e| ("covisibility", e))?;
        self.gravity.validate().map_err(|e| ("gravity", e))?;
        self.build.validate()?;
        // The sections above passed, so what can still fail here is a [map] key.
        ensure(
            !self.map.fuse_overlapping_keyframes || self.keyframes.voxel_size > 0.0,
            "fuse-overlapping-keyframes",
            true,
            "false when [keyframes] voxel-size is 0 (fusion needs the voxel grid)",
        )
        .map_err(|e| ("map", e))?;
        ensure(
            self.map.cov2cov_mode != Cov2CovMode::MapDefault,
            "cov2cov-mode",
            "\"map-default\"",
            "\"approximate\" or \"exact\" (the map's own default)",
        )
        .map_err(|e| ("map", e))?;
        self.map_options().validate().map_err(|e| ("map", e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_files_equal_the_code_defaults() {
        let server =
            ServerConfig::from_toml(DEFAULT_SERVER_TOML, Path::new("config/server.toml")).unwrap();
        assert_eq!(server, ServerConfig::default());
        let bake = BakeConfig::from_toml(DEFAULT_BAKE_TOML, Path::new("config/bake.toml")).unwrap();
        assert_eq!(bake, BakeConfig::default());
    }

    #[test]
    fn shipped_files_list_every_option() {
        // Serializing the defaults gives every key; each must appear in the shipped file.
        let check = |serialized: String, file: &str| {
            for line in serialized.lines().filter(|l| l.contains(" = ")) {
                let key = line.split(" = ").next().unwrap();
                assert!(
                    file.lines().any(|l| l.starts_with(&format!("{key} = "))),
                    "{key} missing"
                );
            }
        };
        check(
            toml::to_string(&ServerConfig::default()).unwrap(),
            DEFAULT_SERVER_TOML,
        );
        check(
            toml::to_string(&BakeConfig::default()).unwrap(),
            DEFAULT_BAKE_TOML,
        );
    }

    #[test]
    fn build_section_errors_name_the_section_and_key() {
        let bad = |text: &str| {
            BakeConfig::from_toml(text, Path::new("bake.toml"))
                .unwrap_err()
                .to_string()
        };
        let text = bad("[build.odometry]\nfit-distance = -1.0\n");
        assert!(
            text.contains("build.odometry") && text.contains("fit-distance"),
            "{text}"
        );
        let text = bad("[build.odometry.gyro]\nmax-gap = 0.0\n");
        assert!(
            text.contains("build.odometry.gyro") && text.contains("max-gap"),
            "{text}"
        );
        let text = bad("[build.odometry.registration]\nvoxel-size = -0.5\n");
        assert!(
            text.contains("build.odometry.registration") && text.contains("voxel-size"),
            "{text}"
        );
        let text = bad("[build.loops]\nmax-distanse = 3.0\n");
        assert!(text.contains("max-distanse"), "{text}");
        let ok =
            BakeConfig::from_toml("[build.loops]\nmax-distance = 3.0\n", Path::new("b")).unwrap();
        assert_eq!(ok.build.loops.max_distance, 3.0);
    }

    #[test]
    fn unknown_key_is_named_with_the_file() {
        let err = BakeConfig::from_toml("[covariance]\nk-neighbours = 3\n", Path::new("my.toml"))
            .unwrap_err();
        let text = err.to_string();
        assert!(
            text.contains("my.toml") && text.contains("k-neighbours") && text.contains("line 2"),
            "{text}"
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
        let bake_error = |toml: &str| {
            BakeConfig::from_toml(toml, Path::new("b.toml"))
                .unwrap_err()
                .to_string()
        };
        let err = bake_error("[filter]\nmin-range = -1\n");
        assert!(err.contains("min-range") && err.contains(">= 0"), "{err}");
        let err = bake_error("[input]\nbin-layout = \"xyzrgb\"\n");
        assert!(err.contains("xyzrgb") && err.contains("xyzi"), "{err}");
        let err = bake_error("[map]\ncov2cov-mode = \"map-default\"\n");
        assert!(
            err.contains("[map]") && err.contains("cov2cov-mode") && err.contains("exact"),
            "{err}"
        );
        let err = bake_error("[map]\ncov2cov-mode = \"fast\"\n");
        assert!(err.contains("fast") && err.contains("approximate"), "{err}");
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
        ] {
            let err = ServerConfig::from_toml(text, Path::new("s.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains("[relocalize]") && err.contains(key), "{err}");
        }
        let err =
            bake_error("[keyframes]\nvoxel-size = 0\n[map]\nfuse-overlapping-keyframes = true\n");
        assert!(
            err.contains("[map]") && err.contains("fuse-overlapping-keyframes"),
            "{err}"
        );
    }

    #[test]
    fn missing_file_is_a_read_error() {
        let err = ServerConfig::load(Some(Path::new("/nonexistent/server.toml"))).unwrap_err();
        assert!(matches!(err, ConfigError::Read { .. }));
    }
}
