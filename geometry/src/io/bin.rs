//! Headerless float32 binary scans: KITTI velodyne (`x y z intensity`, 16 bytes a
//! point) and raw `x y z` triplets (12 bytes a point).

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::error::{IoError, Location};
use crate::cloud::PointCloud;

/// Record layout of a headerless `.bin` file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BinLayout {
    /// KITTI velodyne: float32 `x y z intensity`.
    Xyzi,
    /// Raw float32 `x y z` triplets.
    Xyz,
}

impl BinLayout {
    /// Bytes per point.
    pub fn record_size(self) -> usize {
        match self {
            BinLayout::Xyzi => 16,
            BinLayout::Xyz => 12,
        }
    }

    /// Parses `xyz` or `xyzi` (the sidecar file and CLI spelling).
    pub fn parse(word: &str) -> Option<Self> {
        match word.trim() {
            "xyzi" | "kitti" => Some(BinLayout::Xyzi),
            "xyz" | "raw" => Some(BinLayout::Xyz),
            _ => None,
        }
    }
}

/// Reads a `.bin` scan with the given layout.
pub fn read_bin(path: &Path, bytes: &[u8], layout: BinLayout) -> Result<PointCloud, IoError> {
    let record = layout.record_size();
    if !bytes.len().is_multiple_of(record) {
        let other = match layout {
            BinLayout::Xyzi => {
                "if it holds raw x y z triplets, pass --bin-layout xyz or write 'xyz' into FILE.layout"
            }
            BinLayout::Xyz => "if it is a KITTI x y z intensity file, pass --bin-layout xyzi",
        };
        return Err(IoError::malformed(
            path,
            Location::Byte((bytes.len() - bytes.len() % record) as u64),
            format!(
                "{} bytes is not a whole number of {record}-byte {layout:?} records ({other})",
                bytes.len()
            ),
        ));
    }
    let f = |b: &[u8], k: usize| {
        f32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]])
    };
    let records = bytes.chunks_exact(record);
    let mut cloud = PointCloud::from_points(
        records
            .clone()
            .map(|r| [f(r, 0), f(r, 1), f(r, 2)])
            .collect(),
    );
    if layout == BinLayout::Xyzi {
        cloud.intensity = Some(records.map(|r| f(r, 3)).collect());
    }
    Ok(cloud)
}

/// Writes `cloud` in `layout` (missing intensity is written as 0).
pub fn write_bin(cloud: &PointCloud, layout: BinLayout) -> Vec<u8> {
    let mut out = Vec::with_capacity(cloud.len() * layout.record_size());
    for (i, p) in cloud.points.iter().enumerate() {
        for c in p {
            out.extend_from_slice(&c.to_le_bytes());
        }
        if layout == BinLayout::Xyzi {
            let intensity = cloud.intensity.as_ref().map_or(0.0, |v| v[i]);
            out.extend_from_slice(&intensity.to_le_bytes());
        }
    }
    out
}
