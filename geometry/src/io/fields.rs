//! What PCD and PLY share: typed scalar fields, and assembling named fields into a
//! [`PointCloud`].

use crate::cloud::PointCloud;

/// A scalar type of a binary field.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scalar {
    /// Signed 8-bit integer.
    I8,
    /// Unsigned 8-bit integer.
    U8,
    /// Signed 16-bit integer.
    I16,
    /// Unsigned 16-bit integer.
    U16,
    /// Signed 32-bit integer.
    I32,
    /// Unsigned 32-bit integer.
    U32,
    /// Signed 64-bit integer.
    I64,
    /// Unsigned 64-bit integer.
    U64,
    /// 32-bit float.
    F32,
    /// 64-bit float.
    F64,
}

impl Scalar {
    /// Size in bytes.
    pub fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::I64 | Scalar::U64 | Scalar::F64 => 8,
        }
    }

    /// Decodes a little-endian value; `bytes` holds at least `size()` bytes.
    pub fn read_le(self, bytes: &[u8]) -> f64 {
        fn arr<const N: usize>(b: &[u8]) -> [u8; N] {
            std::array::from_fn(|i| b[i])
        }
        match self {
            Scalar::I8 => bytes[0] as i8 as f64,
            Scalar::U8 => bytes[0] as f64,
            Scalar::I16 => i16::from_le_bytes(arr(bytes)) as f64,
            Scalar::U16 => u16::from_le_bytes(arr(bytes)) as f64,
            Scalar::I32 => i32::from_le_bytes(arr(bytes)) as f64,
            Scalar::U32 => u32::from_le_bytes(arr(bytes)) as f64,
            Scalar::I64 => i64::from_le_bytes(arr(bytes)) as f64,
            Scalar::U64 => u64::from_le_bytes(arr(bytes)) as f64,
            Scalar::F32 => f32::from_le_bytes(arr(bytes)) as f64,
            Scalar::F64 => f64::from_le_bytes(arr(bytes)),
        }
    }
}

/// Builds a cloud from records whose fields are known by name. Recognized names:
/// `x y z`, `view_x view_y view_z`, `intensity` (also `i`, `scalar_intensity`) and
/// `time` (also `t`, `timestamp`); other fields are read and ignored.
pub struct Assembler {
    xyz: [usize; 3],
    view: Option<[usize; 3]>,
    intensity: Option<usize>,
    time: Option<usize>,
    cloud: PointCloud,
}

impl Assembler {
    /// Plans the assembly for fields named `names` (one entry per scalar), with room
    /// for `capacity` points. Fails naming the missing coordinate.
    pub fn new(names: &[String], capacity: usize) -> Result<Self, String> {
        let find =
            |candidates: &[&str]| names.iter().position(|n| candidates.contains(&n.as_str()));
        let mut xyz = [0; 3];
        for (slot, axis) in xyz.iter_mut().zip(["x", "y", "z"]) {
            *slot = find(&[axis])
                .ok_or_else(|| format!("no field '{axis}' (fields are: {})", names.join(" ")))?;
        }
        let view = match (find(&["view_x"]), find(&["view_y"]), find(&["view_z"])) {
            (Some(a), Some(b), Some(c)) => Some([a, b, c]),
            _ => None,
        };
        let intensity = find(&["intensity", "i", "scalar_intensity"]);
        let time = find(&["time", "t", "timestamp"]);
        let cloud = PointCloud {
            points: Vec::with_capacity(capacity),
            view_dirs: view.map(|_| Vec::with_capacity(capacity)),
            intensity: intensity.map(|_| Vec::with_capacity(capacity)),
            time: time.map(|_| Vec::with_capacity(capacity)),
        };
        Ok(Self {
            xyz,
            view,
            intensity,
            time,
            cloud,
        })
    }

    /// Appends one point; `value(i)` is the value of scalar field `i`.
    pub fn push(&mut self, value: impl Fn(usize) -> f64) {
        self.cloud.points.push(self.xyz.map(|i| value(i) as f32));
        if let (Some(idx), Some(dst)) = (self.view, &mut self.cloud.view_dirs) {
            dst.push(idx.map(|i| value(i) as f32));
        }
        if let (Some(i), Some(dst)) = (self.intensity, &mut self.cloud.intensity) {
            dst.push(value(i) as f32);
        }
        if let (Some(i), Some(dst)) = (self.time, &mut self.cloud.time) {
            dst.push(value(i) as f32);
        }
    }

    /// The assembled cloud.
    pub fn finish(self) -> PointCloud {
        self.cloud
    }
}

/// Value of output field `field` (a name of [`PointCloud::field_names`]) for point `i`.
pub fn output_value(cloud: &PointCloud, field: &str, i: usize) -> f32 {
    let v = |arr: &Option<Vec<[f32; 3]>>, axis: usize| arr.as_ref().map_or(0.0, |a| a[i][axis]);
    match field {
        "x" => cloud.points[i][0],
        "y" => cloud.points[i][1],
        "z" => cloud.points[i][2],
        "view_x" => v(&cloud.view_dirs, 0),
        "view_y" => v(&cloud.view_dirs, 1),
        "view_z" => v(&cloud.view_dirs, 2),
        "intensity" => cloud.intensity.as_ref().map_or(0.0, |a| a[i]),
        "time" => cloud.time.as_ref().map_or(0.0, |a| a[i]),
        _ => 0.0,
    }
}

/// Appends point `i` as one text line of `fields`, shortest round-trip floats.
pub fn push_ascii_row(out: &mut Vec<u8>, cloud: &PointCloud, fields: &[&str], i: usize) {
    let line: Vec<String> = fields
        .iter()
        .map(|f| output_value(cloud, f, i).to_string())
        .collect();
    out.extend_from_slice(line.join(" ").as_bytes());
    out.push(b'\n');
}

/// Appends point `i` as little-endian `f32` values of `fields`.
pub fn push_binary_row(out: &mut Vec<u8>, cloud: &PointCloud, fields: &[&str], i: usize) {
    for f in fields {
        out.extend_from_slice(&output_value(cloud, f, i).to_le_bytes());
    }
}
