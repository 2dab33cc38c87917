//! The ROS 2 messages the node reads and writes, as serde structs in the `.msg` files'
//! field order: DDS carries them as CDR, which is positional (docs/ROS2-INTEROP.md).
//! Only the node's own messages live here; `kfmap_bag` decodes the point layouts.

use kfmap_geometry::geometry::Pose;
use nalgebra::{Isometry3, Quaternion as NaQuaternion, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use serde_big_array::BigArray;

/// `builtin_interfaces/Time`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// Seconds since the epoch.
    pub fn seconds(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }

    /// The time `seconds` after the epoch (rounded to the nanosecond).
    pub fn from_seconds(seconds: f64) -> Self {
        let whole = seconds.floor();
        let mut nanosec = ((seconds - whole) * 1e9).round() as u32;
        let mut sec = whole as i32;
        if nanosec >= 1_000_000_000 {
            sec += 1;
            nanosec -= 1_000_000_000;
        }
        Self { sec, nanosec }
    }
}

/// `std_msgs/Header`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `sensor_msgs/PointField`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct PointField {
    pub name: String,
    pub offset: u32,
    pub datatype: u8,
    pub count: u32,
}

/// `sensor_msgs/PointCloud2`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PointCloud2 {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub fields: Vec<PointField>,
    pub is_bigendian: bool,
    pub point_step: u32,
    pub row_step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    pub is_dense: bool,
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

/// `sensor_msgs/Imu`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Imu {
    pub header: Header,
    pub orientation: QuaternionMsg,
    pub orientation_covariance: [f64; 9],
    pub angular_velocity: Vector3Msg,
    pub angular_velocity_covariance: [f64; 9],
    pub linear_acceleration: Vector3Msg,
    pub linear_acceleration_covariance: [f64; 9],
}

impl Imu {
    /// The sample at the header stamp (as `kfmap_bag`'s `ImuMessage::sample` reads a
    /// bag's), `None` when a value is not finite.
    pub fn sample(&self) -> Option<kfmap_geometry::imu::ImuSample> {
        let v = |m: &Vector3Msg| [m.x, m.y, m.z];
        let sample = kfmap_geometry::imu::ImuSample {
            t: self.header.stamp.seconds(),
            acc: v(&self.linear_acceleration),
            gyro: v(&self.angular_velocity),
        };
        let finite = sample.acc.iter().chain(&sample.gyro).all(|x| x.is_finite());
        (finite && sample.t.is_finite()).then_some(sample)
    }
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
    fn times_round_trip_to_the_nanosecond() {
        for seconds in [0.0, 1.5, 1_700_000_000.123_456_7, 12.999_999_999_7] {
            let t = Time::from_seconds(seconds);
            assert!(t.nanosec < 1_000_000_000, "{t:?}");
            assert!(
                (t.seconds() - seconds).abs() < 2e-9 * seconds.max(1.0),
                "{t:?}"
            );
        }
        assert_eq!(
            Time::from_seconds(3.25),
            Time {
                sec: 3,
                nanosec: 250_000_000
            }
        );
    }

    #[test]
    fn an_imu_message_is_a_sample_unless_a_value_is_not_finite() {
        let mut imu = Imu {
            header: Header {
                stamp: Time::from_seconds(2.5),
                frame_id: "imu".into(),
            },
            linear_acceleration: Vector3Msg {
                x: 0.1,
                y: 0.2,
                z: 9.8,
            },
            angular_velocity: Vector3Msg {
                x: 0.01,
                y: 0.0,
                z: -0.3,
            },
            ..Imu::default()
        };
        let sample = imu.sample().unwrap();
        assert_eq!(
            (sample.t, sample.acc, sample.gyro),
            (2.5, [0.1, 0.2, 9.8], [0.01, 0.0, -0.3])
        );
        imu.angular_velocity.y = f64::NAN;
        assert!(imu.sample().is_none());
    }

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
