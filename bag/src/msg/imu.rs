//! Placeholder: `sensor_msgs/Imu`.

use kfmap_shared::imu::ImuSample;

use super::{DecodeError, Stamp};
use crate::Encoding;

/// A decoded `sensor_msgs/Imu`.
#[derive(Debug, Clone, PartialEq)]
pub struct ImuMessage {
    /// Header stamp.
    pub stamp: Stamp,
    /// Header frame.
    pub frame_id: String,
    /// Orientation quaternion `x y z w` (all zero or -1 covariance when unknown).
    pub orientation: [f64; 4],
    /// rad/s.
    pub angular_velocity: [f64; 3],
    /// m/s^2 (specific force).
    pub linear_acceleration: [f64; 3],
}

impl ImuMessage {
    /// The sample at the header stamp.
    pub fn sample(&self) -> ImuSample {
        ImuSample {
            t: self.stamp.seconds(),
            acc: self.linear_acceleration,
            gyro: self.angular_velocity,
        }
    }
}

/// Decodes a `sensor_msgs/Imu`.
pub fn decode_imu(_bytes: &[u8], _encoding: Encoding) -> Result<ImuMessage, DecodeError> {
    Err(DecodeError("not decoded yet".into()))
}
