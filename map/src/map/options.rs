//! `KeyframeMapOptions`: every option of docs/DESIGN.md#keyframe-map (MOLA
//! `TCreationOptions` names and defaults), grouped by concern.

use serde::{Deserialize, Serialize};

use crate::covis::CovisOptions;
use crate::select::SelectionOptions;
use kfmap_geometry::cov::CovOptions;
use kfmap_geometry::options::{InvalidOption, ensure};

/// How the active keyframes are chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ActiveSetMode {
    /// Nearest by the translation + rotation metric, plus diverse slots.
    Distance,
    /// The nearest keyframe plus its best covisible neighbours.
    Covisibility,
}

/// Options of a keyframe map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct KeyframeMapOptions {
    /// Per-point covariances (k, min, max distance, lambda, centre, plane gate).
    pub covariance: CovOptions,
    /// Active-set size, diverse slots and the rotation weight of the metric.
    pub selection: SelectionOptions,
    /// Covisibility voxel size and thresholds.
    pub covisibility: CovisOptions,
    /// Active-set rule.
    pub active_set: ActiveSetMode,
    /// Reject pairings whose view directions differ by more than `max_view_angle_deg`.
    pub use_view_direction_filter: bool,
    /// Largest angle between query and map view directions, degrees (180 disables).
    pub max_view_angle_deg: f64,
    /// Store KD-trees in baked maps (else they are rebuilt on load).
    pub serialize_kdtrees: bool,
    /// Store covariances in baked maps (else they are recomputed on load).
    pub serialize_covariances: bool,
    /// Per-keyframe lookups without a merged submap (zero rebuild cost).
    pub approximate_cov: bool,
    /// Baked maps: the map server answers cov2cov requests in exact mode by default,
    /// building a merged submap inside the query each time the active set changes;
    /// false (the default) serves approximate mode, which never rebuilds. Queries in
    /// this process follow `approximate_cov` instead.
    pub serve_exact: bool,
    /// Inserting at pose p first evicts keyframes farther than this (metres); 0 = off.
    pub remove_frames_farther_than: f64,
    /// Exact mode: fuse the merged submap's points that share a map-frame voxel of this
    /// edge (metres) into their centroid weighted by the keyframes' point weights; 0 =
    /// off (plain concatenation, docs/DESIGN.md#keyframe-map).
    pub fuse_voxel_size: f64,
}

impl Default for KeyframeMapOptions {
    fn default() -> Self {
        Self {
            covariance: CovOptions::default(),
            selection: SelectionOptions::default(),
            covisibility: CovisOptions::default(),
            active_set: ActiveSetMode::Distance,
            use_view_direction_filter: true,
            max_view_angle_deg: 120.0,
            serialize_kdtrees: true,
            serialize_covariances: true,
            approximate_cov: false,
            serve_exact: false,
            remove_frames_farther_than: 0.0,
            fuse_voxel_size: 0.0,
        }
    }
}

impl KeyframeMapOptions {
    /// Checks every option; the error names the first bad one.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        self.covariance.validate()?;
        self.selection.validate()?;
        self.covisibility.validate()?;
        let a = self.max_view_angle_deg;
        ensure(
            a.is_finite() && a > 0.0 && a <= 180.0,
            "max-view-angle-deg",
            a,
            "more than 0 and at most 180 degrees",
        )?;
        let r = self.remove_frames_farther_than;
        ensure(
            r.is_finite() && r >= 0.0,
            "remove-frames-farther-than",
            r,
            "a finite distance >= 0 m (0 = off)",
        )?;
        let f = self.fuse_voxel_size;
        ensure(
            f.is_finite() && f >= 0.0,
            "fuse-voxel-size",
            f,
            "a finite voxel edge >= 0 m (0 = off)",
        )
    }

    /// True when the view-direction filter can reject pairs at all.
    pub fn view_filter_active(&self) -> bool {
        self.use_view_direction_filter && self.max_view_angle_deg < 180.0
    }
}

/// Cov2cov search mode of a request or a map (in config files: "map-default",
/// "approximate", "exact"; on the wire its `u32` code).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
#[repr(u32)]
pub enum Cov2CovMode {
    /// The map's own setting.
    MapDefault = 0,
    /// Keyframe by keyframe (no merged submap).
    Approximate = 1,
    /// In the merged submap of the active set (built once per set and session).
    Exact = 2,
}

impl Cov2CovMode {
    /// The mode of a wire code.
    pub fn from_code(code: u32) -> Option<Self> {
        [Self::MapDefault, Self::Approximate, Self::Exact]
            .into_iter()
            .find(|m| *m as u32 == code)
    }

    /// Lower-case name, as in config files.
    pub fn name(self) -> &'static str {
        match self {
            Self::MapDefault => "map-default",
            Self::Approximate => "approximate",
            Self::Exact => "exact",
        }
    }
}
