//! The messages kfmap reads from bags: `sensor_msgs/PointCloud2` and `sensor_msgs/Imu`
//! (the sensors), `geometry_msgs/PoseWithCovarianceStamped` and
//! `diagnostic_msgs/DiagnosticArray` (a localizer's recorded outputs), in ROS 2 CDR or
//! ROS 1 serialization, decoded without copying the point data.

use crate::Encoding;

mod imu;
mod localization;
mod point_cloud2;
mod reader;
mod writer;

pub use imu::{ImuMessage, decode_imu};
pub use localization::{
    DiagnosticArrayMessage, DiagnosticStatusMessage, PoseWithCovarianceMessage,
    decode_diagnostic_array, decode_pose_with_covariance,
};
pub use point_cloud2::{
    PointCloud2, PointField, TimeField, TimeUnit, datatype_name, decode_point_cloud2,
    encode_point_cloud2,
};

/// The `std_msgs/Header` a message starts with (every stamped message does): its stamp
/// and frame, read even when the rest of the message does not decode.
pub fn decode_header(bytes: &[u8], encoding: Encoding) -> Result<(Stamp, String), DecodeError> {
    reader::Reader::new(bytes, encoding)?.header()
}

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

    /// The stamp `seconds` after the epoch, rounded to the nanosecond.
    pub fn from_seconds(seconds: f64) -> Self {
        let whole = seconds.floor();
        let mut nanosec = ((seconds - whole) * 1e9).round() as u32;
        let mut sec = whole as i64;
        if nanosec >= 1_000_000_000 {
            sec += 1;
            nanosec -= 1_000_000_000;
        }
        Self { sec, nanosec }
    }
}

/// `builtin_interfaces/Time` as serde sees it: the ROS 2 node's messages carry the same
/// stamps its decoders read (`int32 sec` on the wire; a stamp past it is an error).
#[derive(serde::Serialize, serde::Deserialize)]
#[serde(rename = "Time")]
struct WireTime {
    sec: i32,
    nanosec: u32,
}

impl serde::Serialize for Stamp {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let sec = i32::try_from(self.sec)
            .map_err(|_| serde::ser::Error::custom(EncodeError::Stamp(self.sec)))?;
        WireTime {
            sec,
            nanosec: self.nanosec,
        }
        .serialize(serializer)
    }
}

impl<'de> serde::Deserialize<'de> for Stamp {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let WireTime { sec, nanosec } = WireTime::deserialize(deserializer)?;
        Ok(Self {
            sec: sec.into(),
            nanosec,
        })
    }
}

/// A message that cannot be encoded: a value past what its wire type holds.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EncodeError {
    /// A stamp's seconds outside ROS 2's `int32 sec`.
    #[error("stamp of {0} s is outside ROS 2's int32 seconds")]
    Stamp(i64),
    /// A string or sequence longer than its `u32` length prefix counts.
    #[error("{what} of {len} elements is longer than a u32 length counts")]
    TooLong { what: &'static str, len: usize },
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_round_trip_to_the_nanosecond() {
        for seconds in [0.0, 1.5, 1_700_000_000.123_456_7, 12.999_999_999_7, -2.25] {
            let t = Stamp::from_seconds(seconds);
            assert!(t.nanosec < 1_000_000_000, "{t:?}");
            assert!(
                (t.seconds() - seconds).abs() < 2e-9 * seconds.abs().max(1.0),
                "{t:?}"
            );
        }
        assert_eq!(
            Stamp::from_seconds(3.25),
            Stamp {
                sec: 3,
                nanosec: 250_000_000
            }
        );
    }

    /// As `builtin_interfaces/Time`: `sec` then `nanosec`, seconds in an `int32`.
    #[test]
    fn stamps_serialize_as_ros2_time_and_refuse_what_int32_cannot_hold() {
        let stamp = Stamp {
            sec: -7,
            nanosec: 5,
        };
        let json = serde_json::to_string(&stamp).unwrap();
        assert_eq!(json, r#"{"sec":-7,"nanosec":5}"#);
        assert_eq!(serde_json::from_str::<Stamp>(&json).unwrap(), stamp);
        let late = Stamp {
            sec: i64::from(i32::MAX) + 1,
            nanosec: 0,
        };
        let err = serde_json::to_string(&late).unwrap_err().to_string();
        assert!(err.contains("int32"), "{err}");
        assert!(serde_json::from_str::<Stamp>(r#"{"sec":2147483648,"nanosec":0}"#).is_err());
    }
}
