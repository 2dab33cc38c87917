//! `sensor_msgs/PointCloud2`: decoding (the point bytes stay borrowed), layout checks,
//! and conversion into kfmap's [`PointCloud`].
//!
//! A PointCloud2 describes its points with `fields` (name, byte offset, datatype,
//! count); each LiDAR driver picks its own. [`PointCloud2::to_cloud`] reads, by name:
//!
//! - `x y z`: FLOAT32 or FLOAT64 (required);
//! - intensity: the first of `intensity`, `i`, `scalar_intensity` (the names kfmap's PCD
//!   reader accepts; Ouster's `reflectivity` is a different, calibrated quantity and is
//!   not used), any numeric datatype;
//! - time: see [`PointCloud2::time_field`].
//!
//! Invalid returns (NaN, or all-zero for drivers that mark "no return" that way) are
//! kept: the caller filters a bag's scans as it filters clouds read from files
//! (`PointCloud::remove_invalid`), so both paths drop the same points.

use kfmap_geometry::cloud::PointCloud;

use super::reader::Reader;
use super::writer::Writer;
use super::{DecodeError, EncodeError, Stamp};
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

impl PointField {
    /// The datatype as ROS names it (`FLOAT32`), or `unknown`.
    pub fn datatype_name(&self) -> &'static str {
        datatype_name(self.datatype)
    }
}

/// The ROS name of a PointField datatype code (`7` is `FLOAT32`); `unknown` for a code
/// outside 1..=8.
pub fn datatype_name(code: u8) -> &'static str {
    Datatype::from_code(code).map_or("unknown", Datatype::name)
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

/// Time field names, most specific first: Livox's `offset_time` wins over the
/// `timestamp` that newer Livox drivers write beside it.
const TIME_NAMES: [&str; 4] = ["offset_time", "t", "time", "timestamp"];
/// Intensity field names, as kfmap's PCD reader accepts them.
const INTENSITY_NAMES: [&str; 3] = ["intensity", "i", "scalar_intensity"];
/// A time reading that puts the first point farther than this from the header stamp
/// is implausible (a scan lasts ~0.1 s; this leaves room for clock offsets).
const PLAUSIBLE_OFFSET_S: f64 = 10.0;

impl PointCloud2<'_> {
    /// Points in the cloud (`height * width`).
    pub fn len(&self) -> usize {
        (self.height as usize).saturating_mul(self.width as usize)
    }

    /// True when the cloud has no points.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The first field named `name`.
    pub fn field(&self, name: &str) -> Option<&PointField> {
        self.fields.iter().find(|f| f.name == name)
    }

    /// The laser ring (`ring`, or Livox's `line`), for reporting.
    pub fn ring_field(&self) -> Option<&PointField> {
        self.field("ring").or_else(|| self.field("line"))
    }

    /// The field that gives per-point time, if any, and how it counts.
    ///
    /// The field is the first present of `offset_time`, `t`, `time`, `timestamp`. An
    /// integer `offset_time`, `t` or `time` counts nanoseconds after the header stamp
    /// (Ouster, Livox). A float field, or any `timestamp`, is told by its first finite
    /// non-zero value `v`: `|v| > 1e14` is nanoseconds since the epoch (Livox driver 2),
    /// `|v| > 1e6` seconds since the epoch (Hesai, Robosense), else seconds after the
    /// stamp (Velodyne). Should that reading put `v` more than 10 s from the stamp while
    /// another reading puts it within 10 s, the nearest reading wins: device clocks that
    /// count from power-on (an unsynchronized Livox's nanoseconds) land there. With no
    /// such value (no points, all NaN or zero) it is seconds after the stamp.
    pub fn time_field(&self) -> Option<TimeField> {
        self.time_slot().map(|(field, _, unit)| TimeField {
            name: field.name.clone(),
            unit,
        })
    }

    /// Every point as a [`PointCloud`], row by row (row padding skipped): x y z as
    /// `f32`, intensity when a field gives it, and time in seconds after the header
    /// stamp when [`PointCloud2::time_field`] finds one. Invalid returns (NaN, zero) are
    /// kept; the caller filters them as it filters clouds read from files.
    ///
    /// Fails only for a layout [`decode_point_cloud2`] would have refused (the fields
    /// are public, so a cloud may have been built or edited by hand).
    pub fn to_cloud(&self) -> Result<PointCloud, DecodeError> {
        let xyz = self.check_layout()?;
        let n = self.len();

        let mut points = Vec::with_capacity(n);
        if xyz.iter().all(|s| s.datatype == Datatype::Float32) && !self.is_bigendian {
            // The common case (every driver above): little-endian FLOAT32 coordinates.
            let [ox, oy, oz] = xyz.map(|s| s.offset);
            self.gather(&mut points, |p| {
                [
                    f32::from_le_bytes(value_bytes(p, ox)),
                    f32::from_le_bytes(value_bytes(p, oy)),
                    f32::from_le_bytes(value_bytes(p, oz)),
                ]
            });
        } else {
            let [x, y, z] = xyz.map(|s| (s.offset, scalar_reader(s.datatype, self.is_bigendian)));
            self.gather(&mut points, |p| {
                [x.1(p, x.0) as f32, y.1(p, y.0) as f32, z.1(p, z.0) as f32]
            });
        }

        let intensity = INTENSITY_NAMES
            .iter()
            .find_map(|name| self.slot(name))
            .map(|slot| {
                let mut out = Vec::with_capacity(n);
                if slot.datatype == Datatype::Float32 && !self.is_bigendian {
                    self.gather(&mut out, |p| {
                        f32::from_le_bytes(value_bytes(p, slot.offset))
                    });
                } else {
                    let read = scalar_reader(slot.datatype, self.is_bigendian);
                    self.gather(&mut out, |p| read(p, slot.offset) as f32);
                }
                out
            });

        let time = self.time_slot().map(|(field, datatype, unit)| {
            // Relative seconds = ((v - a) - b) * scale, with the stamp split into whole
            // seconds and nanoseconds so no epoch-sized value is rounded before the
            // subtraction (f64 keeps ~0.2 us at 1.7e9 s, 256 ns at 1.7e18 ns).
            let (sec, nanosec) = (self.stamp.sec as f64, self.stamp.nanosec as f64);
            let (a, b, scale) = match unit {
                TimeUnit::RelativeNanos => (0.0, 0.0, 1e-9),
                TimeUnit::RelativeSeconds => (0.0, 0.0, 1.0),
                TimeUnit::AbsoluteSeconds => (sec, nanosec * 1e-9, 1.0),
                TimeUnit::AbsoluteNanos => (sec * 1e9, nanosec, 1e-9),
            };
            let read = scalar_reader(datatype, self.is_bigendian);
            let offset = field.offset as usize;
            let mut out = Vec::with_capacity(n);
            self.gather(&mut out, |p| (((read(p, offset) - a) - b) * scale) as f32);
            out
        });

        Ok(PointCloud {
            points,
            view_dirs: None,
            intensity,
            time,
        })
    }

    /// Appends `read(point bytes)` for every point, row by row. Call only once
    /// [`Self::check_layout`] passed (so every row lies inside `data`, and with points
    /// `point_step` and `row_step` are not 0).
    fn gather<T>(&self, out: &mut Vec<T>, mut read: impl FnMut(&[u8]) -> T) {
        if self.is_empty() {
            return;
        }
        let step = self.point_step as usize;
        let row_bytes = self.width as usize * step;
        for row in self
            .data
            .chunks(self.row_step as usize)
            .take(self.height as usize)
        {
            out.extend(row[..row_bytes].chunks_exact(step).map(&mut read));
        }
    }

    /// Where the field `name` is and what it holds, if it exists with a known datatype.
    fn slot(&self, name: &str) -> Option<Slot> {
        let field = self.field(name)?;
        Some(Slot {
            offset: field.offset as usize,
            datatype: Datatype::from_code(field.datatype)?,
        })
    }

    /// The time field, its datatype and unit (see [`Self::time_field`]).
    fn time_slot(&self) -> Option<(&PointField, Datatype, TimeUnit)> {
        let field = TIME_NAMES.iter().find_map(|name| self.field(name))?;
        let datatype = Datatype::from_code(field.datatype)?;
        if !datatype.is_float() && field.name != "timestamp" {
            return Some((field, datatype, TimeUnit::RelativeNanos));
        }
        let unit = self
            .first_time_value(field.offset as usize, datatype)
            .map_or(TimeUnit::RelativeSeconds, |v| {
                infer_time_unit(v, self.stamp)
            });
        Some((field, datatype, unit))
    }

    /// The first finite, non-zero value at `offset` (zero is what drivers write for
    /// "no return", so it says nothing about the unit).
    fn first_time_value(&self, offset: usize, datatype: Datatype) -> Option<f64> {
        if self.check_layout().is_err() || self.is_empty() {
            return None;
        }
        let read = scalar_reader(datatype, self.is_bigendian);
        let step = self.point_step as usize;
        let row_bytes = self.width as usize * step;
        self.data
            .chunks(self.row_step as usize)
            .take(self.height as usize)
            .flat_map(|row| row[..row_bytes].chunks_exact(step))
            .map(|p| read(p, offset))
            .find(|v| v.is_finite() && *v != 0.0)
    }

    /// Checks the layout and returns the x y z slots. Every error names the problem.
    fn check_layout(&self) -> Result<[Slot; 3], DecodeError> {
        for f in &self.fields {
            let Some(datatype) = Datatype::from_code(f.datatype) else {
                return Err(DecodeError::Layout(format!(
                    "field '{}' has unknown datatype {} (known: 1 INT8, 2 UINT8, 3 INT16, \
                     4 UINT16, 5 INT32, 6 UINT32, 7 FLOAT32, 8 FLOAT64)",
                    f.name, f.datatype
                )));
            };
            // A count of 0 is read as 1, as PCL does.
            let bytes = datatype.size() as u64 * u64::from(f.count.max(1));
            if u64::from(f.offset) + bytes > u64::from(self.point_step) {
                return Err(DecodeError::Layout(format!(
                    "field '{}' at offset {} ({bytes} bytes) runs past point_step {}",
                    f.name, f.offset, self.point_step
                )));
            }
        }

        let mut xyz = [Slot {
            offset: 0,
            datatype: Datatype::Float32,
        }; 3];
        for (slot, axis) in xyz.iter_mut().zip(["x", "y", "z"]) {
            *slot = self.slot(axis).ok_or_else(|| {
                let names: Vec<&str> = self.fields.iter().map(|f| f.name.as_str()).collect();
                DecodeError::Layout(format!(
                    "cloud has no field '{axis}' (fields: {})",
                    if names.is_empty() {
                        "none".to_string()
                    } else {
                        names.join(" ")
                    }
                ))
            })?;
            if !slot.datatype.is_float() {
                return Err(DecodeError::Layout(format!(
                    "field '{axis}' is {}; x, y and z must be FLOAT32 or FLOAT64",
                    slot.datatype.name()
                )));
            }
        }

        // u32 x u32 always fits u64; the comparison with `data.len()` then bounds
        // every row offset `to_cloud` computes in usize.
        let row_bytes = u64::from(self.width) * u64::from(self.point_step);
        if u64::from(self.row_step) < row_bytes {
            return Err(DecodeError::Layout(format!(
                "row_step {} is less than width {} x point_step {} = {row_bytes}",
                self.row_step, self.width, self.point_step
            )));
        }
        let needed = u64::from(self.height) * u64::from(self.row_step);
        if (self.data.len() as u64) < needed {
            return Err(DecodeError::Layout(format!(
                "data holds {} bytes, fewer than height {} x row_step {} = {needed}",
                self.data.len(),
                self.height,
                self.row_step
            )));
        }
        Ok(xyz)
    }
}

/// Decodes a `sensor_msgs/PointCloud2`, checking its layout (x y z present, every field
/// inside `point_step`, the data as long as `height * row_step`). Bytes after the
/// message (CDR end padding) are ignored.
pub fn decode_point_cloud2(
    bytes: &[u8],
    encoding: Encoding,
) -> Result<PointCloud2<'_>, DecodeError> {
    let mut r = Reader::new(bytes, encoding)?;
    let (stamp, frame_id) = r.header()?;
    let height = r.u32("height")?;
    let width = r.u32("width")?;
    // A PointField takes at least 13 bytes (ROS 1, empty name): bounds the allocation.
    let count = r.sequence_len("fields", 13)?;
    let mut fields = Vec::with_capacity(count);
    for _ in 0..count {
        fields.push(PointField {
            name: r.string("a field's name")?,
            offset: r.u32("a field's offset")?,
            datatype: r.u8("a field's datatype")?,
            count: r.u32("a field's count")?,
        });
    }
    let cloud = PointCloud2 {
        stamp,
        frame_id,
        height,
        width,
        fields,
        is_bigendian: r.bool("is_bigendian")?,
        point_step: r.u32("point_step")?,
        row_step: r.u32("row_step")?,
        data: r.byte_sequence("data")?,
        is_dense: r.bool("is_dense")?,
    };
    cloud.check_layout()?;
    Ok(cloud)
}

/// Encodes `cloud` as ROS 2 CDR, little-endian, its 4-byte encapsulation header first:
/// what [`decode_point_cloud2`] reads back (a DDS writer sends the bytes after the
/// header). A stamp or a length past its wire type is refused, naming it.
pub fn encode_point_cloud2(cloud: &PointCloud2<'_>) -> Result<Vec<u8>, EncodeError> {
    let sec = i32::try_from(cloud.stamp.sec).map_err(|_| EncodeError::Stamp(cloud.stamp.sec))?;
    let counted = |what, len: usize| {
        // A string's prefix counts its NUL too.
        if len < u32::MAX as usize {
            Ok(())
        } else {
            Err(EncodeError::TooLong { what, len })
        }
    };
    counted("data", cloud.data.len())?;
    counted("fields", cloud.fields.len())?;
    counted("frame_id", cloud.frame_id.len())?;
    for field in &cloud.fields {
        counted("a field's name", field.name.len())?;
    }
    let mut w = Writer::new(Encoding::Cdr, false);
    w.out.reserve(cloud.data.len() + 256);
    w.header(sec, cloud.stamp.nanosec, &cloud.frame_id);
    w.u32(cloud.height);
    w.u32(cloud.width);
    w.u32(cloud.fields.len() as u32);
    for field in &cloud.fields {
        w.string(&field.name);
        w.u32(field.offset);
        w.u8(field.datatype);
        w.u32(field.count);
    }
    w.bool(cloud.is_bigendian);
    w.u32(cloud.point_step);
    w.u32(cloud.row_step);
    w.bytes(cloud.data);
    w.bool(cloud.is_dense);
    Ok(w.out)
}

/// A resolved field: where it is in a point and what it holds.
#[derive(Debug, Clone, Copy)]
struct Slot {
    offset: usize,
    datatype: Datatype,
}

/// The PointField datatypes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Datatype {
    Int8,
    Uint8,
    Int16,
    Uint16,
    Int32,
    Uint32,
    Float32,
    Float64,
}

impl Datatype {
    fn from_code(code: u8) -> Option<Self> {
        use Datatype::*;
        Some(match code {
            1 => Int8,
            2 => Uint8,
            3 => Int16,
            4 => Uint16,
            5 => Int32,
            6 => Uint32,
            7 => Float32,
            8 => Float64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        use Datatype::*;
        match self {
            Int8 | Uint8 => 1,
            Int16 | Uint16 => 2,
            Int32 | Uint32 | Float32 => 4,
            Float64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Datatype::Float32 | Datatype::Float64)
    }

    fn name(self) -> &'static str {
        use Datatype::*;
        match self {
            Int8 => "INT8",
            Uint8 => "UINT8",
            Int16 => "INT16",
            Uint16 => "UINT16",
            Int32 => "INT32",
            Uint32 => "UINT32",
            Float32 => "FLOAT32",
            Float64 => "FLOAT64",
        }
    }
}

/// The `N` bytes at `offset` of one point. The layout check keeps every field inside
/// `point_step`, so the zero fallback never happens; it keeps this panic-free.
#[inline(always)]
fn value_bytes<const N: usize>(point: &[u8], offset: usize) -> [u8; N] {
    point
        .get(offset..)
        .and_then(<[u8]>::first_chunk)
        .copied()
        .unwrap_or([0; N])
}

/// A reader of one value of `datatype` (at a byte offset in a point) as `f64`, chosen
/// once per field so the per-point loop does not branch on the type.
fn scalar_reader(datatype: Datatype, big_endian: bool) -> fn(&[u8], usize) -> f64 {
    use Datatype::*;
    match (datatype, big_endian) {
        (Int8, _) => |p, o| i8::from_le_bytes(value_bytes(p, o)).into(),
        (Uint8, _) => |p, o| u8::from_le_bytes(value_bytes(p, o)).into(),
        (Int16, false) => |p, o| i16::from_le_bytes(value_bytes(p, o)).into(),
        (Int16, true) => |p, o| i16::from_be_bytes(value_bytes(p, o)).into(),
        (Uint16, false) => |p, o| u16::from_le_bytes(value_bytes(p, o)).into(),
        (Uint16, true) => |p, o| u16::from_be_bytes(value_bytes(p, o)).into(),
        (Int32, false) => |p, o| i32::from_le_bytes(value_bytes(p, o)).into(),
        (Int32, true) => |p, o| i32::from_be_bytes(value_bytes(p, o)).into(),
        (Uint32, false) => |p, o| u32::from_le_bytes(value_bytes(p, o)).into(),
        (Uint32, true) => |p, o| u32::from_be_bytes(value_bytes(p, o)).into(),
        (Float32, false) => |p, o| f32::from_le_bytes(value_bytes(p, o)).into(),
        (Float32, true) => |p, o| f32::from_be_bytes(value_bytes(p, o)).into(),
        (Float64, false) => |p, o| f64::from_le_bytes(value_bytes(p, o)),
        (Float64, true) => |p, o| f64::from_be_bytes(value_bytes(p, o)),
    }
}

/// The unit of a time value `v` (see [`PointCloud2::time_field`]): by magnitude, unless
/// that reading is implausibly far from the stamp and another is near it.
fn infer_time_unit(v: f64, stamp: Stamp) -> TimeUnit {
    use TimeUnit::*;
    let by_magnitude = if v.abs() > 1e14 {
        AbsoluteNanos
    } else if v.abs() > 1e6 {
        AbsoluteSeconds
    } else {
        RelativeSeconds
    };
    let offset = |unit: TimeUnit| {
        let (sec, nanosec) = (stamp.sec as f64, stamp.nanosec as f64);
        match unit {
            AbsoluteNanos => ((v - sec * 1e9) - nanosec) * 1e-9,
            AbsoluteSeconds => (v - sec) - nanosec * 1e-9,
            RelativeSeconds | RelativeNanos => v,
        }
        .abs()
    };
    if offset(by_magnitude) <= PLAUSIBLE_OFFSET_S {
        return by_magnitude;
    }
    [AbsoluteNanos, AbsoluteSeconds, RelativeSeconds]
        .into_iter()
        .filter(|&unit| offset(unit) <= PLAUSIBLE_OFFSET_S)
        .min_by(|&a, &b| offset(a).total_cmp(&offset(b)))
        .unwrap_or(by_magnitude)
}

#[cfg(test)]
mod tests;
