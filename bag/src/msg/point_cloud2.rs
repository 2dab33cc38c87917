//! Placeholder: `sensor_msgs/PointCloud2`.

use kfmap_shared::cloud::PointCloud;

use super::{DecodeError, Stamp};
use crate::Encoding;

/// One `sensor_msgs/PointField`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PointField {
    /// Field name (`x`, `intensity`, `t`, ...).
    pub name: String,
    /// Byte offset inside a point.
    pub offset: u32,
    /// ROS datatype code: 1 INT8, 2 UINT8, 3 INT16, 4 UINT16, 5 INT32, 6 UINT32,
    /// 7 FLOAT32, 8 FLOAT64.
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

/// How a per-point time field counts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimeUnit {
    /// Nanoseconds after the header stamp (Ouster `t`, Livox `offset_time`).
    RelativeNanos,
    /// Seconds after the header stamp (Velodyne `time`).
    RelativeSeconds,
    /// Seconds since the epoch (Hesai and Robosense `timestamp`).
    AbsoluteSeconds,
    /// Nanoseconds since the epoch (Livox driver 2 `timestamp`).
    AbsoluteNanos,
}

/// The field that gives each point's time, and how it counts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TimeField {
    /// The field's name.
    pub name: String,
    /// Its unit and origin.
    pub unit: TimeUnit,
}

/// A decoded `sensor_msgs/PointCloud2`; the point bytes are borrowed from the message.
#[derive(Debug, Clone, PartialEq)]
pub struct PointCloud2<'a> {
    /// Header stamp: the scan's time.
    pub stamp: Stamp,
    /// Header frame.
    pub frame_id: String,
    /// Rows (1 for unorganized clouds).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The point layout.
    pub fields: Vec<PointField>,
    /// Multi-byte values are big-endian.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    pub data: &'a [u8],
    /// True when no point is invalid (drivers often say false for organized clouds).
    pub is_dense: bool,
}

impl PointCloud2<'_> {
    /// Points in the cloud (`height * width`).
    pub fn len(&self) -> usize {
        self.height as usize * self.width as usize
    }

    /// True when the cloud has no points.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The field that gives per-point time, if any, and how it counts.
    pub fn time_field(&self) -> Option<TimeField> {
        None
    }

    /// Every point as a [`PointCloud`] (x y z, intensity when present, time relative to
    /// the header stamp in seconds when a time field is present). Invalid returns are
    /// kept: the caller filters as it filters clouds read from files.
    pub fn to_cloud(&self) -> Result<PointCloud, DecodeError> {
        Err(DecodeError("not decoded yet".into()))
    }
}

/// Decodes a `sensor_msgs/PointCloud2`, checking its layout (x y z present, every field
/// inside `point_step`, the data as long as `height * row_step`).
pub fn decode_point_cloud2(
    _bytes: &[u8],
    _encoding: Encoding,
) -> Result<PointCloud2<'_>, DecodeError> {
    Err(DecodeError("not decoded yet".into()))
}

impl PointCloud2<'_> {
    /// Placeholder: the `ring` (or `line`) field.
    pub fn ring_field(&self) -> Option<&PointField> {
        None
    }
}

/// Placeholder: a datatype code's ROS name.
pub fn datatype_name(_code: u8) -> &'static str {
    "?"
}
