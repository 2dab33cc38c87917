//! `sensor_msgs/Imu`: a header, the orientation quaternion, angular velocity and linear
//! acceleration, each with its 3x3 covariance (row-major).

use kfmap_geometry::imu::ImuSample;

use super::reader::Reader;
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
    /// Row-major 3x3 covariance of the orientation; element 0 is -1 when the driver
    /// gives no orientation.
    pub orientation_covariance: [f64; 9],
    /// rad/s.
    pub angular_velocity: [f64; 3],
    /// Row-major 3x3 covariance of `angular_velocity`, (rad/s)^2.
    pub angular_velocity_covariance: [f64; 9],
    /// m/s^2 (specific force).
    pub linear_acceleration: [f64; 3],
    /// Row-major 3x3 covariance of `linear_acceleration`, (m/s^2)^2.
    pub linear_acceleration_covariance: [f64; 9],
}

impl ImuMessage {
    /// The sample at the header stamp; `None` when the acceleration or the angular
    /// velocity is not finite (a driver's NaN says nothing, and one such sample would
    /// make the server refuse the whole IMU window it is sent in).
    pub fn sample(&self) -> Option<ImuSample> {
        let sample = ImuSample {
            t: self.stamp.seconds(),
            acc: self.linear_acceleration,
            gyro: self.angular_velocity,
        };
        let finite = sample.acc.iter().chain(&sample.gyro).all(|x| x.is_finite());
        finite.then_some(sample)
    }
}

/// Decodes a `sensor_msgs/Imu`. Bytes after the message (CDR end padding) are ignored.
pub fn decode_imu(bytes: &[u8], encoding: Encoding) -> Result<ImuMessage, DecodeError> {
    let mut r = Reader::new(bytes, encoding)?;
    let (stamp, frame_id) = r.header()?;
    Ok(ImuMessage {
        stamp,
        frame_id,
        orientation: r.f64s("orientation")?,
        orientation_covariance: r.f64s("orientation_covariance")?,
        angular_velocity: r.f64s("angular_velocity")?,
        angular_velocity_covariance: r.f64s("angular_velocity_covariance")?,
        linear_acceleration: r.f64s("linear_acceleration")?,
        linear_acceleration_covariance: r.f64s("linear_acceleration_covariance")?,
    })
}

#[cfg(test)]
mod tests {
    use super::super::writer::Writer;
    use super::*;

    fn imu_bytes(encoding: Encoding, big_endian: bool, frame: &str) -> Vec<u8> {
        let mut w = Writer::new(encoding, big_endian);
        w.header(1_700_000_000, 250_000_000, frame);
        for i in 0..(4 + 9 + 3 + 9 + 3 + 9) {
            w.f64(i as f64 + 0.5);
        }
        w.out
    }

    #[test]
    fn decodes_every_field_in_each_serialization() {
        for (encoding, big_endian) in [
            (Encoding::Cdr, false),
            (Encoding::Cdr, true),
            (Encoding::Ros1, false),
        ] {
            // Frames of each length mod 8 move the doubles' padding around.
            for frame in ["", "i", "imu", "imu_link", "imu_link_9"] {
                let bytes = imu_bytes(encoding, big_endian, frame);
                let m = decode_imu(&bytes, encoding).unwrap();
                assert_eq!(m.frame_id, frame);
                assert_eq!(m.stamp.sec, 1_700_000_000);
                assert_eq!(m.stamp.nanosec, 250_000_000);
                assert_eq!(m.orientation, [0.5, 1.5, 2.5, 3.5]);
                assert_eq!(m.orientation_covariance[8], 12.5);
                assert_eq!(m.angular_velocity, [13.5, 14.5, 15.5]);
                assert_eq!(m.angular_velocity_covariance[0], 16.5);
                assert_eq!(m.linear_acceleration, [25.5, 26.5, 27.5]);
                assert_eq!(m.linear_acceleration_covariance[8], 36.5);
                let s = m.sample().unwrap();
                assert_eq!(s.acc, m.linear_acceleration);
                assert_eq!(s.gyro, m.angular_velocity);
                assert!((s.t - 1_700_000_000.25).abs() < 1e-6);
            }
        }
    }

    /// A NaN or infinite acceleration or angular velocity is no sample; an orientation
    /// the driver does not know (NaN there, as some drivers write it) does not matter.
    #[test]
    fn a_message_is_a_sample_unless_acceleration_or_rate_is_not_finite() {
        let m = decode_imu(&imu_bytes(Encoding::Cdr, false, "imu"), Encoding::Cdr).unwrap();
        let unknown_orientation = ImuMessage {
            orientation: [f64::NAN; 4],
            ..m.clone()
        };
        assert_eq!(unknown_orientation.sample(), m.sample());
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            for axis in 0..3 {
                let mut acc = m.clone();
                acc.linear_acceleration[axis] = bad;
                assert_eq!(acc.sample(), None, "acc {axis} {bad}");
                let mut rate = m.clone();
                rate.angular_velocity[axis] = bad;
                assert_eq!(rate.sample(), None, "gyro {axis} {bad}");
            }
        }
    }

    #[test]
    fn every_truncation_is_an_error() {
        for encoding in [Encoding::Cdr, Encoding::Ros1] {
            let bytes = imu_bytes(encoding, false, "imu");
            for n in 0..bytes.len() {
                assert!(
                    decode_imu(&bytes[..n], encoding).is_err(),
                    "{encoding:?} {n}"
                );
            }
        }
    }
}
