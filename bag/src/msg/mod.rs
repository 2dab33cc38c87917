//! The messages kfmap reads from bags: `sensor_msgs/PointCloud2` and `sensor_msgs/Imu`
//! (the sensors), `geometry_msgs/PoseWithCovarianceStamped` and
//! `diagnostic_msgs/DiagnosticArray` (a localizer's recorded outputs), in ROS 2 CDR or
//! ROS 1 serialization, decoded without copying the point data.

mod imu;
mod localization;
mod point_cloud2;
mod reader;

pub use imu::{ImuMessage, decode_imu};
pub use localization::{
    DiagnosticArrayMessage, DiagnosticStatusMessage, PoseWithCovarianceMessage,
    decode_diagnostic_array, decode_pose_with_covariance,
};
pub use point_cloud2::{
    PointCloud2, PointField, TimeField, TimeUnit, datatype_name, decode_point_cloud2,
};

/// A message's header stamp.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Stamp {
    /// Whole seconds (ROS 2 `int32 sec`; ROS 1 `uint32 secs`, widened).
    pub sec: i64,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl Stamp {
    /// Seconds since the epoch.
    pub fn seconds(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }

    /// Nanoseconds since the epoch.
    pub fn nanos(&self) -> i64 {
        self.sec * 1_000_000_000 + self.nanosec as i64
    }
}

/// A message that does not decode as its type: what is wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct DecodeError(pub String);
