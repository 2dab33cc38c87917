//! `bake.toml`: how `kfmap bake` reads a dataset, builds poses and what the baked map
//! holds, validated section by section.

use kfmap_geometry::cloud::FilterOptions;
use kfmap_geometry::cloud::ensure_vertical_angle_offset;
use kfmap_geometry::cov::CovOptions;
use kfmap_geometry::gravity::GravityParams;
use kfmap_geometry::io::BinLayout;
use kfmap_geometry::options::{ConfigFile, InvalidOption, ensure};
use kfmap_map::covis::CovisOptions;
use kfmap_map::map::{ActiveSetMode, Cov2CovMode, KeyframeDecider, KeyframeMapOptions};
use kfmap_map::select::SelectionOptions;
use serde::{Deserialize, Serialize};

use crate::mapping::BuildParams;

/// The default `config/bake.toml`, as shipped.
pub const DEFAULT_BAKE_TOML: &str = include_str!("../../config/bake.toml");

/// `[input]` of `bake.toml`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct InputSection {
    /// Layout of headerless `.bin` scans.
    pub bin_layout: BinLayout,
    /// Every return's elevation raised by this on load, degrees (a spinning sensor's
    /// vertical-angle calibration error; 0 leaves the scans as they are).
    pub vertical_angle_offset_deg: f64,
}

impl Default for InputSection {
    fn default() -> Self {
        Self {
            bin_layout: BinLayout::Xyzi,
            vertical_angle_offset_deg: 0.0,
        }
    }
}

impl InputSection {
    /// Checks `vertical-angle-offset-deg`; the error names it.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        ensure_vertical_angle_offset(self.vertical_angle_offset_deg)
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

impl ConfigFile for BakeConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_BAKE_TOML;

    fn validate(&self) -> Result<(), (&'static str, InvalidOption)> {
        self.filter.validate().map_err(|e| ("filter", e))?;
        self.covariance.validate().map_err(|e| ("covariance", e))?;
        self.input.validate().map_err(|e| ("input", e))?;
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
    use std::path::Path;

    use super::*;

    #[test]
    fn shipped_file_equals_the_code_defaults() {
        let bake = BakeConfig::from_toml(DEFAULT_BAKE_TOML, Path::new("config/bake.toml")).unwrap();
        assert_eq!(bake, BakeConfig::default());
    }

    #[test]
    fn shipped_file_lists_every_option() {
        kfmap_testdata::assert_lists_every_option(
            &toml::to_string(&BakeConfig::default()).unwrap(),
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
        let text = bad("[build.odometry.sweep]\nseconds = 0.0\n");
        assert!(
            text.contains("build.odometry.sweep") && text.contains("seconds"),
            "{text}"
        );
        let text = bad("[build.odometry.sweep]\ndirection = \"left\"\n");
        assert!(
            text.contains("left") && text.contains("clockwise"),
            "{text}"
        );
        let text = bad("[build.odometry]\ndeskew = \"kiss\"\n");
        assert!(text.contains("kiss") && text.contains("azimuth"), "{text}");
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
        let err =
            bake_error("[keyframes]\nvoxel-size = 0\n[map]\nfuse-overlapping-keyframes = true\n");
        assert!(
            err.contains("[map]") && err.contains("fuse-overlapping-keyframes"),
            "{err}"
        );
    }
}
