//! The ROS 2 messages the node reads and writes through ros2-client, as serde structs in
//! the `.msg` files' field order: DDS carries them as CDR, which is positional
//! (docs/ROS2-INTEROP.md). The sensors' messages (`PointCloud2`, `Imu`) and the stamp
//! are `kfmap_bag`'s, read by its decoders (`crate::raw`).

use kfmap_geometry::geometry::Pose;
use nalgebra::{Isometry3, Quaternion as NaQuaternion, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use serde_big_array::BigArray;

pub use kfmap_bag::msg::Stamp;

/// `std_msgs/Header`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Stamp,
    pub frame_id: String,
}

/// `geometry_msgs/Vector3` (also `Point`, whose fields are the same).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Vector3Msg {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl From<Vector3<f64>> for Vector3Msg {
    fn from(v: Vector3<f64>) -> Self {
        Self {
            x: v.x,
            y: v.y,
            z: v.z,
        }
    }
}

impl From<Vector3Msg> for Vector3<f64> {
    fn from(v: Vector3Msg) -> Self {
        Vector3::new(v.x, v.y, v.z)
    }
}

/// `geometry_msgs/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct QuaternionMsg {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for QuaternionMsg {
    fn default() -> Self {
        Self {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

impl From<UnitQuaternion<f64>> for QuaternionMsg {
    fn from(q: UnitQuaternion<f64>) -> Self {
        Self {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        }
    }
}

impl QuaternionMsg {
    /// The rotation, when the four numbers are finite and not all zero (normalized: a
    /// driver's quaternion is seldom exactly unit).
    pub fn rotation(&self) -> Option<UnitQuaternion<f64>> {
        let q = NaQuaternion::new(self.w, self.x, self.y, self.z);
        let norm = q.norm();
        (q.coords.iter().all(|v| v.is_finite()) && norm > 1e-6)
            .then(|| UnitQuaternion::from_quaternion(q / norm))
    }
}

/// `geometry_msgs/Pose`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct PoseMsg {
    pub position: Vector3Msg,
    pub orientation: QuaternionMsg,
}

impl From<&Pose> for PoseMsg {
    fn from(pose: &Pose) -> Self {
        Self {
            position: pose.translation.vector.into(),
            orientation: pose.rotation.into(),
        }
    }
}

impl PoseMsg {
    /// The pose, when finite and its quaternion is a rotation.
    pub fn pose(&self) -> Option<Pose> {
        let t: Vector3<f64> = self.position.into();
        let rotation = self.orientation.rotation()?;
        t.iter()
            .all(|v| v.is_finite())
            .then(|| Isometry3::from_parts(Translation3::from(t), rotation))
    }
}

/// `geometry_msgs/PoseWithCovariance`: covariance row-major over (x, y, z, rotation about
/// x, y, z).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    pub pose: PoseMsg,
    #[serde(with = "BigArray")]
    pub covariance: [f64; 36],
}

impl Default for PoseWithCovariance {
    fn default() -> Self {
        Self {
            pose: PoseMsg::default(),
            covariance: [0.0; 36],
        }
    }
}

/// `geometry_msgs/PoseWithCovarianceStamped`: the node's pose, and `/initialpose`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PoseWithCovarianceStamped {
    pub header: Header,
    pub pose: PoseWithCovariance,
}

/// `geometry_msgs/Twist`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Twist {
    pub linear: Vector3Msg,
    pub angular: Vector3Msg,
}

/// `geometry_msgs/TwistWithCovariance`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    pub twist: Twist,
    #[serde(with = "BigArray")]
    pub covariance: [f64; 36],
}

impl Default for TwistWithCovariance {
    fn default() -> Self {
        Self {
            twist: Twist::default(),
            covariance: [0.0; 36],
        }
    }
}

/// `nav_msgs/Odometry`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    pub pose: PoseWithCovariance,
    pub twist: TwistWithCovariance,
}

/// `geometry_msgs/Transform`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Transform {
    pub translation: Vector3Msg,
    pub rotation: QuaternionMsg,
}

impl From<&Pose> for Transform {
    fn from(pose: &Pose) -> Self {
        Self {
            translation: pose.translation.vector.into(),
            rotation: pose.rotation.into(),
        }
    }
}

impl Transform {
    /// The transform as a pose, when finite and a rotation.
    pub fn pose(&self) -> Option<Pose> {
        PoseMsg {
            position: self.translation,
            orientation: self.rotation,
        }
        .pose()
    }
}

/// `geometry_msgs/TransformStamped`: `T_parent_child`, parent `header.frame_id`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// `tf2_msgs/TFMessage`: `/tf` and `/tf_static`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// `geometry_msgs/Vector3Stamped`: the pooled gravity estimate (m/s^2, map frame, as an
/// accelerometer at rest reads it).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Vector3Stamped {
    pub header: Header,
    pub vector: Vector3Msg,
}

/// `diagnostic_msgs/KeyValue`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}

/// `diagnostic_msgs/DiagnosticStatus` level: ok.
pub const DIAGNOSTIC_OK: u8 = 0;
/// `diagnostic_msgs/DiagnosticStatus` level: warn (degraded).
pub const DIAGNOSTIC_WARN: u8 = 1;
/// `diagnostic_msgs/DiagnosticStatus` level: error (lost, or no server).
pub const DIAGNOSTIC_ERROR: u8 = 2;

/// `diagnostic_msgs/DiagnosticStatus`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<KeyValue>,
}

/// `diagnostic_msgs/DiagnosticArray`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poses_and_transforms_read_back_and_refuse_what_is_not_a_rotation() {
        let pose = Isometry3::from_parts(
            Translation3::new(1.0, -2.0, 0.5),
            UnitQuaternion::from_euler_angles(0.1, -0.2, 2.0),
        );
        let back = PoseMsg::from(&pose).pose().unwrap();
        assert!((back.translation.vector - pose.translation.vector).norm() < 1e-12);
        assert!(back.rotation.angle_to(&pose.rotation) < 1e-12);
        let t = Transform::from(&pose).pose().unwrap();
        assert!(t.rotation.angle_to(&pose.rotation) < 1e-12);
        let zero = QuaternionMsg {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 0.0,
        };
        assert!(zero.rotation().is_none());
        let nan = PoseMsg {
            position: Vector3Msg {
                x: f64::NAN,
                y: 0.0,
                z: 0.0,
            },
            ..PoseMsg::default()
        };
        assert!(nan.pose().is_none());
        // Not unit: normalized, as drivers' quaternions seldom are exactly.
        let scaled = QuaternionMsg {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 2.0,
        };
        assert_eq!(scaled.rotation(), Some(UnitQuaternion::identity()));
    }
}
