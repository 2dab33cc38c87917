//! One keyframe: pose, timestamp and local bounding box, with its local points, optional
//! view directions, KD-tree and covariances either built in this process (heap) or read
//! in place from a baked map file (memory-mapped).

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::archive::{ArchiveError, BakedKeyframe};
use kfmap_geometry::KeyframeId;
use kfmap_geometry::cloud::{Aabb, PointCloud};
use kfmap_geometry::cov::{CovOptions, estimate_covariances};
use kfmap_geometry::geometry::{
    PackedSym3, Pose, rotation_distance, transform_point, translation_distance,
};
use kfmap_geometry::spatial::{PointTree, TreeError, TreeRef, build_tree};

/// A keyframe of the map.
#[derive(Debug, Clone)]
pub struct Keyframe {
    /// Monotonic id.
    pub id: KeyframeId,
    /// `T_map_keyframe`.
    pub pose: Pose,
    /// Seconds.
    pub timestamp: f64,
    /// Local bounding box.
    pub bbox: Aabb,
    /// Shared: keyframe data is immutable, copies of a keyframe are cheap.
    data: KeyframeData,
}

#[derive(Debug, Clone)]
enum KeyframeData {
    Heap(Arc<HeapKeyframe>),
    Baked(Arc<BakedKeyframe>),
}

/// Keyframe data built in this process.
#[derive(Debug)]
pub struct HeapKeyframe {
    /// Local points.
    pub points: Vec<[f32; 3]>,
    /// Local view directions (unit, from the point towards the sensor), if the scan had them.
    pub view_dirs: Option<Vec<[f32; 3]>>,
    /// Local per-point covariances.
    pub covariances: Vec<PackedSym3>,
    /// Raw points each point stands for (voxel counts), if known.
    pub weights: Option<Vec<u32>>,
    /// KD-tree over `points`.
    pub tree: PointTree,
}

/// A keyframe's local data, wherever it lives: what every map algorithm reads.
#[derive(Clone, Copy)]
pub struct KeyframeView<'a> {
    /// Local points.
    pub points: &'a [[f32; 3]],
    /// Local view directions, if any.
    pub view_dirs: Option<&'a [[f32; 3]]>,
    /// Local per-point covariances.
    pub covariances: &'a [PackedSym3],
    /// Raw points each point stands for, if known (else 1 each).
    pub weights: Option<&'a [u32]>,
    /// KD-tree over `points` (item = index).
    pub tree: TreeRef<'a>,
}

impl Keyframe {
    /// Builds a keyframe and its local caches; the cloud must be non-empty and finite.
    pub fn build(
        id: KeyframeId,
        pose: Pose,
        timestamp: f64,
        cloud: PointCloud,
        cov: &CovOptions,
    ) -> Result<Self, TreeError> {
        Self::build_weighted(id, pose, timestamp, cloud, None, cov)
    }

    /// As [`Keyframe::build`], with how many raw points each point stands for (the
    /// voxel counts of [`PointCloud::voxelize`]; each >= 1), which exact mode's fusion
    /// of overlapping keyframes weighs by.
    pub fn build_weighted(
        id: KeyframeId,
        pose: Pose,
        timestamp: f64,
        cloud: PointCloud,
        weights: Option<Vec<u32>>,
        cov: &CovOptions,
    ) -> Result<Self, TreeError> {
        if cloud.is_empty() {
            return Err(TreeError::Empty);
        }
        if let Some(w) = &weights
            && let Some(problem) = weights_problem(w, cloud.len())
        {
            return Err(TreeError::MismatchedParts(problem));
        }
        let covariances = estimate_covariances(&cloud.points, cov).values;
        Self::assemble(id, pose, timestamp, cloud, covariances, weights)
    }

    /// A keyframe from its parts, with covariances computed elsewhere (one per point);
    /// its tree is built here.
    pub fn from_parts(
        id: KeyframeId,
        pose: Pose,
        timestamp: f64,
        cloud: PointCloud,
        covariances: Vec<PackedSym3>,
    ) -> Result<Self, TreeError> {
        Self::assemble(id, pose, timestamp, cloud, covariances, None)
    }

    fn assemble(
        id: KeyframeId,
        pose: Pose,
        timestamp: f64,
        cloud: PointCloud,
        covariances: Vec<PackedSym3>,
        weights: Option<Vec<u32>>,
    ) -> Result<Self, TreeError> {
        if covariances.len() != cloud.len() {
            return Err(TreeError::MismatchedParts(format!(
                "{} covariances for {} points",
                covariances.len(),
                cloud.len()
            )));
        }
        let tree = build_tree(&cloud.points)?;
        let bbox = cloud.bounding_box().ok_or(TreeError::Empty)?;
        let heap = HeapKeyframe {
            points: cloud.points,
            view_dirs: cloud.view_dirs,
            covariances,
            weights,
            tree,
        };
        Ok(Self {
            id,
            pose,
            timestamp,
            bbox,
            data: KeyframeData::Heap(Arc::new(heap)),
        })
    }

    /// A keyframe whose data stays in a baked map file.
    pub(crate) fn baked(
        id: KeyframeId,
        pose: Pose,
        timestamp: f64,
        bbox: Aabb,
        data: BakedKeyframe,
    ) -> Self {
        Self {
            id,
            pose,
            timestamp,
            bbox,
            data: KeyframeData::Baked(Arc::new(data)),
        }
    }

    /// Number of points (known without reading a baked keyframe's data).
    pub fn len(&self) -> usize {
        match &self.data {
            KeyframeData::Heap(h) => h.points.len(),
            KeyframeData::Baked(b) => b.len(),
        }
    }

    /// True for a keyframe without points (never built: keyframes are non-empty).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// True when the data is read from a baked map file.
    pub fn is_baked(&self) -> bool {
        matches!(self.data, KeyframeData::Baked(_))
    }

    /// The local data. A baked keyframe is verified (checksum, archive layout) the
    /// first time, and its tree or covariances rebuilt if the file does not hold them.
    pub fn view(&self) -> Result<KeyframeView<'_>, ArchiveError> {
        match &self.data {
            KeyframeData::Heap(h) => Ok(KeyframeView {
                points: &h.points,
                view_dirs: h.view_dirs.as_deref(),
                covariances: &h.covariances,
                weights: h.weights.as_deref(),
                tree: h.tree.view(),
            }),
            KeyframeData::Baked(b) => b.view(),
        }
    }

    /// Points in the map frame, f64.
    pub fn map_points(&self) -> Result<Vec<[f64; 3]>, ArchiveError> {
        Ok(self
            .view()?
            .points
            .iter()
            .map(|p| transform_point(&self.pose, p).into())
            .collect())
    }
}

/// What is wrong with per-point weights for `points` points, if anything.
pub(crate) fn weights_problem(weights: &[u32], points: usize) -> Option<String> {
    if weights.len() != points {
        Some(format!("{} weights for {points} points", weights.len()))
    } else {
        weights
            .iter()
            .position(|&w| w == 0)
            .map(|i| format!("point {i} has weight 0 (each stands for >= 1 raw point)"))
    }
}

/// When to create a keyframe (as MOLA's KeyframeDecider): the first one, or when the
/// keyframe closest in translation is strictly farther than `min_translation` metres or
/// strictly more than `min_rotation_deg` degrees away in rotation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct KeyframeDecider {
    /// Metres.
    pub min_translation: f64,
    /// Degrees.
    pub min_rotation_deg: f64,
}

impl Default for KeyframeDecider {
    fn default() -> Self {
        Self {
            min_translation: 1.0,
            min_rotation_deg: 30.0,
        }
    }
}

impl KeyframeDecider {
    /// Checks both thresholds; the error names the option.
    pub fn validate(&self) -> Result<(), kfmap_geometry::options::InvalidOption> {
        kfmap_geometry::options::ensure(
            self.min_translation.is_finite() && self.min_translation >= 0.0,
            "min-translation",
            self.min_translation,
            "a finite distance >= 0 m",
        )?;
        kfmap_geometry::options::ensure(
            self.min_rotation_deg.is_finite() && self.min_rotation_deg >= 0.0,
            "min-rotation-deg",
            self.min_rotation_deg,
            "a finite angle >= 0 degrees",
        )
    }

    /// Whether a keyframe should be created at `pose` given the existing poses.
    pub fn should_create<'a>(
        &self,
        existing: impl IntoIterator<Item = &'a Pose>,
        pose: &Pose,
    ) -> bool {
        let closest = existing
            .into_iter()
            .map(|p| (translation_distance(p, pose), p))
            .min_by(|a, b| a.0.total_cmp(&b.0));
        match closest {
            None => true,
            Some((dist, p)) => {
                dist > self.min_translation
                    || rotation_distance(p, pose).to_degrees() > self.min_rotation_deg
            }
        }
    }
}
