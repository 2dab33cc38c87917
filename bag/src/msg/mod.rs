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

/// A message that does not decode as its type: what is wrong, by kind (a reader may
/// skip a truncated message but refuse a layout it cannot read at all).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DecodeError {
    /// The message ends before a field.
    #[error("message truncated reading {what}: needs {needed} bytes at byte {at}, {left} left")]
    Truncated {
        what: String,
        needed: usize,
        at: usize,
        left: usize,
    },
    /// A CDR message too short for its 4-byte encapsulation header.
    #[error("a CDR message of {0} bytes, shorter than its 4-byte encapsulation header")]
    NoEncapsulation(usize),
    /// A CDR representation other than plain CDR.
    #[error(
        "CDR representation 0x{id:04x} ({name}) is not read; only plain CDR (0x0000 big-endian, 0x0001 little-endian) is, as rmw implementations write by default"
    )]
    Representation { id: u16, name: &'static str },
    /// A value out of its type's range (a bool of 2).
    #[error("{what} is {value}, not {expected}")]
    BadValue {
        what: String,
        value: String,
        expected: &'static str,
    },
    /// A sequence whose count the bytes left cannot hold.
    #[error("{what} claims {count} elements, more than the {left} bytes left can hold")]
    BadCount {
        what: String,
        count: usize,
        left: usize,
    },
    /// A cloud whose layout cannot be read (the message names the field or size).
    #[error("{0}")]
    Layout(String),
}
