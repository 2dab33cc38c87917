//! The point cloud type: points in one frame plus optional per-point attributes.

mod deskew;
mod elevation;
mod filter;
mod voxel;

pub use deskew::{DeskewError, DeskewOutcome, Twist, deskew};
pub use elevation::ensure_vertical_angle_offset;
pub use filter::{FilterOptions, FilterReport};
pub use voxel::Voxelized;
pub use voxel::{grid_position, unit_or_zero, voxel_groups};

/// Why a cloud is not usable as it is.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CloudError {
    /// A coordinate is NaN or infinite.
    #[error("point {index} has a non-finite coordinate ({value:?})")]
    NonFinite {
        /// Index of the first bad point.
        index: usize,
        /// Its coordinates as read.
        value: [f32; 3],
    },
    /// An attribute array does not have one entry per point.
    #[error("attribute '{attribute}' has {len} entries but the cloud has {points} points")]
    LengthMismatch {
        /// Name of the attribute (`view_dirs`, `intensity`, `time`).
        attribute: &'static str,
        /// Entries in the attribute array.
        len: usize,
        /// Points in the cloud.
        points: usize,
    },
    /// A voxel size that is not a positive finite number of metres.
    #[error("voxel size must be a positive finite number of metres, got {0}")]
    BadVoxelSize(f64),
    /// The cloud spans more voxels per axis than the grid can index (2^21).
    #[error(
        "voxel size {voxel_size} m is too fine for this cloud: {cells} cells on one axis, at most 2097152; use a larger voxel"
    )]
    VoxelGridTooFine {
        /// The voxel size asked for, metres.
        voxel_size: f64,
        /// Cells needed on the longest axis.
        cells: i64,
    },
}

/// Points of one scan or keyframe, all in one frame (sensor or keyframe-local).
///
/// Every optional attribute, when present, has exactly one entry per point;
/// [`PointCloud::validate`] checks that.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    /// Point coordinates in metres.
    pub points: Vec<[f32; 3]>,
    /// Unit vectors from each point toward the sensor, in the cloud's frame.
    pub view_dirs: Option<Vec<[f32; 3]>>,
    /// Return intensity, sensor-specific units.
    pub intensity: Option<Vec<f32>>,
    /// Time of each point, seconds relative to the scan stamp.
    pub time: Option<Vec<f32>>,
}

/// An axis-aligned bounding box in the cloud's frame, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    /// Smallest coordinate on each axis.
    pub min: [f32; 3],
    /// Largest coordinate on each axis.
    pub max: [f32; 3],
}

impl Aabb {
    /// Edge lengths in metres.
    pub fn extent(&self) -> [f32; 3] {
        std::array::from_fn(|i| self.max[i] - self.min[i])
    }

    /// Volume in cubic metres.
    pub fn volume(&self) -> f64 {
        self.extent().iter().map(|&e| e as f64).product()
    }

    /// Squared distance from `p` to the box (0 inside), m^2. Inlined: once per query
    /// and keyframe in approximate cov2cov, from another crate.
    #[inline]
    pub fn dist_sq(&self, p: &[f32; 3]) -> f32 {
        (0..3)
            .map(|a| {
                let gap = (self.min[a] - p[a]).max(p[a] - self.max[a]).max(0.0);
                gap * gap
            })
            .sum()
    }
}

impl PointCloud {
    /// A cloud of bare points.
    pub fn from_points(points: Vec<[f32; 3]>) -> Self {
        Self {
            points,
            ..Self::default()
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True when the cloud has no points.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Names of the fields present, e.g. `["x", "y", "z", "intensity"]`.
    pub fn field_names(&self) -> Vec<&'static str> {
        let mut names = vec!["x", "y", "z"];
        if self.view_dirs.is_some() {
            names.extend(["view_x", "view_y", "view_z"]);
        }
        if self.intensity.is_some() {
            names.push("intensity");
        }
        if self.time.is_some() {
            names.push("time");
        }
        names
    }

    /// Checks attribute lengths and that every coordinate is finite; the error names
    /// the first bad point.
    pub fn validate(&self) -> Result<(), CloudError> {
        let n = self.points.len();
        let lengths = [
            ("view_dirs", self.view_dirs.as_ref().map(Vec::len)),
            ("intensity", self.intensity.as_ref().map(Vec::len)),
            ("time", self.time.as_ref().map(Vec::len)),
        ];
        for (attribute, len) in lengths {
            if let Some(len) = len.filter(|&len| len != n) {
                return Err(CloudError::LengthMismatch {
                    attribute,
                    len,
                    points: n,
                });
            }
        }
        match self
            .points
            .iter()
            .position(|p| p.iter().any(|c| !c.is_finite()))
        {
            Some(index) => Err(CloudError::NonFinite {
                index,
                value: self.points[index],
            }),
            None => Ok(()),
        }
    }

    /// The bounding box of the finite points; `None` when there are none.
    pub fn bounding_box(&self) -> Option<Aabb> {
        let mut finite = self
            .points
            .iter()
            .filter(|p| p.iter().all(|c| c.is_finite()));
        let first = *finite.next()?;
        let mut bbox = Aabb {
            min: first,
            max: first,
        };
        for p in finite {
            bbox.min = std::array::from_fn(|i| bbox.min[i].min(p[i]));
            bbox.max = std::array::from_fn(|i| bbox.max[i].max(p[i]));
        }
        Some(bbox)
    }

    /// A new cloud holding the points at `indices`, with their attributes, in that order.
    pub fn select(&self, indices: &[usize]) -> PointCloud {
        let pick3 = |v: &Vec<[f32; 3]>| indices.iter().map(|&i| v[i]).collect();
        let pick1 = |v: &Vec<f32>| indices.iter().map(|&i| v[i]).collect();
        PointCloud {
            points: indices.iter().map(|&i| self.points[i]).collect(),
            view_dirs: self.view_dirs.as_ref().map(pick3),
            intensity: self.intensity.as_ref().map(pick1),
            time: self.time.as_ref().map(pick1),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_names_first_bad_point() {
        let cloud = PointCloud::from_points(vec![
            [0.0, 0.0, 1.0],
            [1.0, f32::NAN, 0.0],
            [f32::INFINITY, 0.0, 0.0],
        ]);
        match cloud.validate() {
            Err(CloudError::NonFinite { index, .. }) => assert_eq!(index, 1),
            other => panic!("expected NonFinite, got {other:?}"),
        }
    }

    #[test]
    fn validate_catches_attribute_length_mismatch() {
        let mut cloud = PointCloud::from_points(vec![[1.0, 2.0, 3.0]; 3]);
        cloud.intensity = Some(vec![1.0; 2]);
        assert!(matches!(
            cloud.validate(),
            Err(CloudError::LengthMismatch {
                attribute: "intensity",
                len: 2,
                points: 3
            })
        ));
    }

    #[test]
    fn bounding_box_skips_non_finite() {
        let cloud = PointCloud::from_points(vec![
            [1.0, -2.0, 3.0],
            [f32::NAN, 100.0, 0.0],
            [-1.0, 5.0, 0.5],
        ]);
        let bbox = cloud.bounding_box().unwrap();
        assert_eq!(bbox.min, [-1.0, -2.0, 0.5]);
        assert_eq!(bbox.max, [1.0, 5.0, 3.0]);
        assert!(PointCloud::default().bounding_box().is_none());
    }
}
