//! What a localizer publishes, read back from a recorded run:
//! `geometry_msgs/PoseWithCovarianceStamped` (the pose and its 6x6 covariance) and
//! `diagnostic_msgs/DiagnosticArray` (its health), so `kfmap plot --bag` can draw a run
//! of `kfmap-ros2` (or of any localizer that publishes them).

use super::reader::Reader;
use super::{DecodeError, Stamp};
use crate::Encoding;

/// A decoded `geometry_msgs/PoseWithCovarianceStamped`.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseWithCovarianceMessage {
    /// Header stamp.
    pub stamp: Stamp,
    /// Header frame (the frame the pose is in, e.g. `map`).
    pub frame_id: String,
    /// Position `x y z`, metres.
    pub position: [f64; 3],
    /// Orientation quaternion `x y z w`.
    pub orientation: [f64; 4],
    /// Row-major 6x6 covariance of `x y z` and the rotation about the fixed `x y z`
    /// axes (m^2, rad^2).
    pub covariance: [f64; 36],
}

/// Decodes a `geometry_msgs/PoseWithCovarianceStamped`.
pub fn decode_pose_with_covariance(
    bytes: &[u8],
    encoding: Encoding,
) -> Result<PoseWithCovarianceMessage, DecodeError> {
    let mut r = Reader::new(bytes, encoding)?;
    let (stamp, frame_id) = r.header()?;
    Ok(PoseWithCovarianceMessage {
        stamp,
        frame_id,
        position: r.f64s("pose.position")?,
        orientation: r.f64s("pose.orientation")?,
        covariance: r.f64s("covariance")?,
    })
}

/// One `diagnostic_msgs/DiagnosticStatus`.
#[derive(Debug, Clone, PartialEq)]
pub struct DiagnosticStatusMessage {
    /// 0 OK, 1 WARN, 2 ERROR, 3 STALE.
    pub level: u8,
    /// The component's name.
    pub name: String,
    /// A one-line description.
    pub message: String,
    /// The hardware it is about.
    pub hardware_id: String,
    /// Key-value pairs, in order.
    pub values: Vec<(String, String)>,
}

impl DiagnosticStatusMessage {
    /// The value of `key`, if present.
    pub fn value(&self, key: &str) -> Option<&str> {
        self.values
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

/// A decoded `diagnostic_msgs/DiagnosticArray`.
#[derive(Debug, Clone, PartialEq)]
pub struct DiagnosticArrayMessage {
    /// Header stamp.
    pub stamp: Stamp,
    /// The statuses.
    pub status: Vec<DiagnosticStatusMessage>,
}

/// The fewest bytes a `DiagnosticStatus` takes: its level and four length prefixes.
const MIN_STATUS_BYTES: usize = 1 + 4 * 4;
/// The fewest bytes a `KeyValue` takes: two length prefixes.
const MIN_KEY_VALUE_BYTES: usize = 2 * 4;

/// Decodes a `diagnostic_msgs/DiagnosticArray`.
pub fn decode_diagnostic_array(
    bytes: &[u8],
    encoding: Encoding,
) -> Result<DiagnosticArrayMessage, DecodeError> {
    let mut r = Reader::new(bytes, encoding)?;
    let (stamp, _frame) = r.header()?;
    let count = r.sequence_len("status", MIN_STATUS_BYTES)?;
    let mut status = Vec::with_capacity(count);
    for _ in 0..count {
        let level = r.u8("status.level")?;
        let name = r.string("status.name")?;
        let message = r.string("status.message")?;
        let hardware_id = r.string("status.hardware_id")?;
        let pairs = r.sequence_len("status.values", MIN_KEY_VALUE_BYTES)?;
        let mut values = Vec::with_capacity(pairs);
        for _ in 0..pairs {
            values.push((r.string("values.key")?, r.string("values.value")?));
        }
        status.push(DiagnosticStatusMessage {
            level,
            name,
            message,
            hardware_id,
            values,
        });
    }
    Ok(DiagnosticArrayMessage { stamp, status })
}

#[cfg(test)]
mod tests {
    use super::super::writer::Writer;
    use super::*;

    fn pose_bytes(encoding: Encoding, big_endian: bool, frame: &str) -> Vec<u8> {
        let mut w = Writer::new(encoding, big_endian);
        w.header(1_700_000_000, 500, frame);
        for i in 0..(3 + 4 + 36) {
            w.f64(i as f64 * 0.25);
        }
        w.out
    }

    fn diagnostics_bytes(encoding: Encoding, big_endian: bool, name: &str) -> Vec<u8> {
        let mut w = Writer::new(encoding, big_endian);
        w.header(12, 34, "");
        w.u32(2);
        for (level, pairs) in [(1u8, 2u32), (2, 0)] {
            w.u8(level);
            w.string(name);
            w.string("degraded: few matches");
            w.string("lidar");
            w.u32(pairs);
            for k in 0..pairs {
                w.string(&format!("key{k}"));
                w.string(&format!("value {k}"));
            }
        }
        w.out
    }

    #[test]
    fn a_pose_decodes_in_each_serialization() {
        for (encoding, big_endian) in [
            (Encoding::Cdr, false),
            (Encoding::Cdr, true),
            (Encoding::Ros1, false),
        ] {
            // Frames of each length mod 8 move the doubles' padding around.
            for frame in ["", "m", "map", "map_2", "earth_map"] {
                let m =
                    decode_pose_with_covariance(&pose_bytes(encoding, big_endian, frame), encoding)
                        .unwrap();
                assert_eq!(
                    (m.frame_id.as_str(), m.stamp.sec, m.stamp.nanosec),
                    (frame, 1_700_000_000, 500)
                );
                assert_eq!(m.position, [0.0, 0.25, 0.5]);
                assert_eq!(m.orientation, [0.75, 1.0, 1.25, 1.5]);
                assert_eq!((m.covariance[0], m.covariance[35]), (1.75, 10.5));
            }
        }
    }

    #[test]
    fn diagnostics_decode_in_each_serialization() {
        for (encoding, big_endian) in [
            (Encoding::Cdr, false),
            (Encoding::Cdr, true),
            (Encoding::Ros1, false),
        ] {
            for name in ["k", "kfmap", "kfmap_localizer"] {
                let m = decode_diagnostic_array(
                    &diagnostics_bytes(encoding, big_endian, name),
                    encoding,
                )
                .unwrap();
                assert_eq!((m.stamp.sec, m.stamp.nanosec), (12, 34));
                assert_eq!(m.status.len(), 2);
                let s = &m.status[0];
                assert_eq!((s.level, s.name.as_str()), (1, name));
                assert_eq!(s.message, "degraded: few matches");
                assert_eq!(s.hardware_id, "lidar");
                assert_eq!(s.value("key1"), Some("value 1"));
                assert_eq!(s.value("key2"), None);
                assert_eq!((m.status[1].level, m.status[1].values.len()), (2, 0));
            }
        }
    }

    #[test]
    fn every_truncation_is_an_error_and_a_huge_count_allocates_nothing() {
        for encoding in [Encoding::Cdr, Encoding::Ros1] {
            let pose = pose_bytes(encoding, false, "map");
            let diagnostics = diagnostics_bytes(encoding, false, "kfmap");
            for n in 0..pose.len() {
                assert!(decode_pose_with_covariance(&pose[..n], encoding).is_err());
            }
            for n in 0..diagnostics.len() {
                assert!(decode_diagnostic_array(&diagnostics[..n], encoding).is_err());
            }
        }
        let mut w = Writer::new(Encoding::Cdr, false);
        w.header(0, 0, "");
        w.u32(u32::MAX);
        let err = decode_diagnostic_array(&w.out, Encoding::Cdr).unwrap_err();
        assert!(
            matches!(&err, DecodeError::BadCount { what, .. } if what == "status"),
            "{err:?}"
        );
    }
}
