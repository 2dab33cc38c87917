//! `ros2.toml`: the node's configuration, validated (each key is explained in the
//! shipped file, `config/ros2.toml`).

use kfmap_client::{HypothesisParams, TrustParams};
use kfmap_geometry::cloud::ensure_vertical_angle_offset;
use kfmap_geometry::options::{ConfigFile, InvalidOption, ensure};
use serde::{Deserialize, Serialize};

/// The default `config/ros2.toml`, as shipped.
pub const DEFAULT_ROS2_TOML: &str = include_str!("../../config/ros2.toml");

/// `[node]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct NodeSection {
    pub name: String,
    pub namespace: String,
    pub domain_id: u16,
}

impl Default for NodeSection {
    fn default() -> Self {
        Self {
            name: "kfmap_localizer".into(),
            namespace: "/".into(),
            domain_id: 0,
        }
    }
}

/// Cov2cov mode, as `kfmap localize --mode` names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ModeName {
    #[default]
    MapDefault,
    Approximate,
    Exact,
}

/// `[server]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct ServerSection {
    pub map_name: String,
    pub iceoryx_prefix: String,
    pub server_side: bool,
    pub mode: ModeName,
    pub timeout_s: f64,
}

impl Default for ServerSection {
    fn default() -> Self {
        Self {
            map_name: "map".into(),
            iceoryx_prefix: String::new(),
            server_side: false,
            mode: ModeName::MapDefault,
            timeout_s: 5.0,
        }
    }
}

/// `[topics]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct TopicsSection {
    pub points: String,
    pub imu: String,
    pub initial_pose: String,
    pub pose: String,
    pub odometry: String,
    pub diagnostics: String,
    pub map_cloud: String,
    pub gravity: String,
    pub tf: String,
    pub tf_static: String,
}

impl Default for TopicsSection {
    fn default() -> Self {
        Self {
            points: "/points".into(),
            imu: String::new(),
            initial_pose: "/initialpose".into(),
            pose: "/kfmap/pose".into(),
            odometry: "/kfmap/odometry".into(),
            diagnostics: "/diagnostics".into(),
            map_cloud: "/kfmap/map_cloud".into(),
            gravity: "/kfmap/gravity".into(),
            tf: "/tf".into(),
            tf_static: "/tf_static".into(),
        }
    }
}

impl TopicsSection {
    /// Every topic with its key, `""` (off) included.
    fn named(&self) -> [(&'static str, &str); 10] {
        [
            ("points", &self.points),
            ("imu", &self.imu),
            ("initial-pose", &self.initial_pose),
            ("pose", &self.pose),
            ("odometry", &self.odometry),
            ("diagnostics", &self.diagnostics),
            ("map-cloud", &self.map_cloud),
            ("gravity", &self.gravity),
            ("tf", &self.tf),
            ("tf-static", &self.tf_static),
        ]
    }
}

/// `[frames]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct FramesSection {
    pub map: String,
    pub odom: String,
    pub base: String,
    pub sensor_mounting: String,
    pub publish_tf: bool,
}

impl Default for FramesSection {
    fn default() -> Self {
        Self {
            map: "map".into(),
            odom: "odom".into(),
            base: "base_link".into(),
            sensor_mounting: String::new(),
            publish_tf: true,
        }
    }
}

/// `[qos]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct QosSection {
    pub points_depth: usize,
    pub imu_depth: usize,
}

impl Default for QosSection {
    fn default() -> Self {
        Self {
            points_depth: 5,
            imu_depth: 400,
        }
    }
}

/// `[scans]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct ScansSection {
    pub voxel: f64,
    pub deskew: bool,
    pub vertical_angle_offset_deg: f64,
}

impl Default for ScansSection {
    fn default() -> Self {
        Self {
            voxel: 0.25,
            deskew: true,
            vertical_angle_offset_deg: 0.0,
        }
    }
}

/// `[imu]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct ImuSection {
    pub gyro: bool,
    pub lidar_from_imu_rpy_deg: [f64; 3],
    pub keep_s: f64,
}

impl Default for ImuSection {
    fn default() -> Self {
        Self {
            gyro: true,
            lidar_from_imu_rpy_deg: [0.0; 3],
            keep_s: 20.0,
        }
    }
}

/// `[map-cloud]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct MapCloudSection {
    pub voxel: f64,
}

impl Default for MapCloudSection {
    fn default() -> Self {
        Self { voxel: 1.0 }
    }
}

/// The whole `ros2.toml`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct Ros2Config {
    pub node: NodeSection,
    pub server: ServerSection,
    pub topics: TopicsSection,
    pub frames: FramesSection,
    pub qos: QosSection,
    pub scans: ScansSection,
    pub imu: ImuSection,
    pub map_cloud: MapCloudSection,
    /// When a pose is `ok` and when the tracker gives up on its place, as
    /// `kfmap localize`'s flags of the same names.
    pub tracker: TrustParams,
    /// How the tracker keeps and drops places in doubt, as `kfmap localize`'s
    /// `--hypothesis-<key>` flags.
    pub hypotheses: HypothesisParams,
}

/// True for a ROS 2 name: `/`-separated tokens of letters, digits and `_`, none starting
/// with a digit (a leading `/` allowed).
fn ros_name(name: &str) -> bool {
    let body = name.strip_prefix('/').unwrap_or(name);
    !body.is_empty()
        && body.split('/').all(|token| {
            token
                .chars()
                .next()
                .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
                && token.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        })
}

/// True for a frame id: non-empty, printable, no whitespace.
fn frame_id(name: &str) -> bool {
    !name.is_empty() && name.chars().all(|c| c.is_ascii_graphic())
}

impl ConfigFile for Ros2Config {
    const DEFAULT_TOML: &'static str = DEFAULT_ROS2_TOML;

    fn validate(&self) -> Result<(), (&'static str, InvalidOption)> {
        let n = &self.node;
        ensure(
            ros_name(&n.name) && !n.name.contains('/'),
            "name",
            &n.name,
            "a ROS 2 node name: letters, digits and _",
        )
        .and_then(|()| {
            ensure(
                n.namespace == "/" || (n.namespace.starts_with('/') && ros_name(&n.namespace)),
                "namespace",
                &n.namespace,
                "/ or an absolute ROS 2 name such as /robot1",
            )
        })
        .and_then(|()| ensure(n.domain_id <= 232, "domain-id", n.domain_id, "0 to 232"))
        .map_err(|e| ("node", e))?;
        let s = &self.server;
        ensure(
            !s.map_name.is_empty(),
            "map-name",
            &s.map_name,
            "the name `kfmap serve --map-name` announces",
        )
        .and_then(|()| {
            ensure(
                s.timeout_s.is_finite() && s.timeout_s > 0.0 && s.timeout_s <= 600.0,
                "timeout-s",
                s.timeout_s,
                "seconds > 0, at most 600",
            )
        })
        .map_err(|e| ("server", e))?;
        for (key, topic) in self.topics.named() {
            let optional = matches!(key, "imu" | "initial-pose" | "map-cloud" | "gravity");
            ensure(
                (optional && topic.is_empty()) || ros_name(topic),
                key,
                topic,
                if optional {
                    "a ROS 2 topic name such as /points, or \"\" (off)"
                } else {
                    "a ROS 2 topic name such as /points"
                },
            )
            .map_err(|e| ("topics", e))?;
        }
        let f = &self.frames;
        for (key, frame) in [("map", &f.map), ("odom", &f.odom), ("base", &f.base)] {
            ensure(
                frame_id(frame),
                key,
                frame,
                "a frame id: printable, no spaces",
            )
            .map_err(|e| ("frames", e))?;
        }
        ensure(
            f.sensor_mounting.is_empty()
                || crate::frames::parse_mounting(&f.sensor_mounting).is_some(),
            "sensor-mounting",
            &f.sensor_mounting,
            "\"x y z roll pitch yaw\" (metres, degrees) or \"\"",
        )
        .map_err(|e| ("frames", e))?;
        let q = &self.qos;
        ensure(
            (1..=1000).contains(&q.points_depth),
            "points-depth",
            q.points_depth,
            "1 to 1000",
        )
        .and_then(|()| {
            ensure(
                (1..=100_000).contains(&q.imu_depth),
                "imu-depth",
                q.imu_depth,
                "1 to 100000",
            )
        })
        .map_err(|e| ("qos", e))?;
        ensure(
            self.scans.voxel.is_finite() && (0.0..=10.0).contains(&self.scans.voxel),
            "voxel",
            self.scans.voxel,
            "0 (every point) to 10 m",
        )
        .and_then(|()| ensure_vertical_angle_offset(self.scans.vertical_angle_offset_deg))
        .map_err(|e| ("scans", e))?;
        let i = &self.imu;
        ensure(
            i.lidar_from_imu_rpy_deg
                .iter()
                .all(|a| a.is_finite() && a.abs() <= 360.0),
            "lidar-from-imu-rpy-deg",
            format!("{:?}", i.lidar_from_imu_rpy_deg),
            "three finite angles within +-360 deg",
        )
        .and_then(|()| {
            ensure(
                i.keep_s.is_finite() && (1.0..=600.0).contains(&i.keep_s),
                "keep-s",
                i.keep_s,
                "1 to 600 s",
            )
        })
        .map_err(|e| ("imu", e))?;
        ensure(
            self.map_cloud.voxel.is_finite()
                && (self.map_cloud.voxel == 0.0 || (0.05..=100.0).contains(&self.map_cloud.voxel)),
            "voxel",
            self.map_cloud.voxel,
            "0 (off) or 0.05 to 100 m",
        )
        .map_err(|e| ("map-cloud", e))?;
        self.tracker.validate().map_err(|e| ("tracker", e))?;
        self.hypotheses.validate().map_err(|e| ("hypotheses", e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn the_shipped_file_is_the_defaults() {
        let shipped = Ros2Config::from_toml(DEFAULT_ROS2_TOML, Path::new("ros2.toml")).unwrap();
        assert_eq!(shipped, Ros2Config::default());
    }

    #[test]
    fn bad_values_name_their_section_and_key() {
        for (text, key) in [
            ("[node]\nname = \"9lives\"", "name"),
            ("[node]\nnamespace = \"robot\"", "namespace"),
            ("[node]\ndomain-id = 300", "domain-id"),
            ("[server]\ntimeout-s = 0.0", "timeout-s"),
            ("[topics]\npoints = \"\"", "points"),
            ("[topics]\npose = \"/a b\"", "pose"),
            ("[frames]\nbase = \"\"", "base"),
            ("[frames]\nsensor-mounting = \"1 2 3\"", "sensor-mounting"),
            ("[qos]\npoints-depth = 0", "points-depth"),
            ("[scans]\nvoxel = -1.0", "voxel"),
            (
                "[scans]\nvertical-angle-offset-deg = 9.0",
                "vertical-angle-offset-deg",
            ),
            ("[map-cloud]\nvoxel = 0.01", "voxel"),
            ("[server]\nmode = \"fast\"", "mode"),
            ("[topics]\nlidar = \"/x\"", "lidar"),
            ("[tracker]\nok-pinned = 3.0", "ok-pinned"),
            (
                "[tracker]\nok-pinned-after-doubt = 3.0",
                "ok-pinned-after-doubt",
            ),
            ("[tracker]\nmax-acceleration = -1.0", "max-acceleration"),
            (
                "[tracker]\nconfirm-after-unpinned = 5000",
                "confirm-after-unpinned",
            ),
            ("[tracker]\nok-explained = 1.5", "ok-explained"),
            ("[tracker]\nexplained-keyframes = 65", "explained-keyframes"),
            ("[tracker]\ntight-distance = 0.0", "tight-distance"),
            ("[tracker]\nlost-after-unfit = 0", "lost-after-unfit"),
            ("[tracker]\nrecover-after = 0", "recover-after"),
            ("[tracker]\nslide = 1", "slide"),
            ("[hypotheses]\nearly-spread = 0.0", "early-spread"),
            ("[hypotheses]\nhold-explained = 1.5", "hold-explained"),
            ("[hypotheses]\nwindow = 3", "window"),
            ("[hypotheses]\ncount = 3", "count"),
        ] {
            let err = Ros2Config::from_toml(text, Path::new("r.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains(key), "{text}: {err}");
        }
        // Optional topics may be off.
        let off =
            Ros2Config::from_toml("[topics]\nimu = \"\"\ngravity = \"\"", Path::new("r.toml"));
        assert!(off.is_ok());
    }
}
