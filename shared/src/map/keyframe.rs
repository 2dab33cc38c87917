//! One keyframe: local points, optional view directions, pose, timestamp, and the
//! caches built at insertion (local bounding box, KD-tree, covariances).

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::KeyframeId;
use crate::cloud::{Aabb, PointCloud};
use crate::cov::{CovOptions, estimate_covariances};
use crate::geometry::{PackedSym3, Pose, rotation_distance, translation_distance};
use crate::spatial::{PointTree, TreeError, build_tree};

/// A keyframe of the map.
#[derive(Debug, Clone)]
pub struct Keyframe {
    /// Monotonic id.
    pub id: KeyframeId,
    /// `T_map_keyframe`.
    pub pose: Pose,
    /// Seconds.
    pub timestamp: f64,
    /// Points in the keyframe-local frame (view directions local too).
    pub cloud: PointCloud,
    /// Local bounding box.
    pub bbox: Aabb,
    /// KD-tree over the local points (shared: trees are immutable, copies are cheap).
    pub tree: Arc<PointTree>,
    /// Local per-point covariances.
    pub covariances: Vec<PackedSym3>,
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
        let tree = Arc::new(build_tree(&cloud.points)?);
        let bbox = cloud.bounding_box().ok_or(TreeError::Empty)?;
        let covariances = estimate_covariances(&cloud.points, cov).values;
        Ok(Self {
            id,
            pose,
            timestamp,
            cloud,
            bbox,
            tree,
            covariances,
        })
    }

    /// Points in the map frame, f64.
    pub fn map_points(&self) -> impl Iterator<Item = [f64; 3]> + '_ {
        self.cloud.points.iter().map(|p| {
            let q = self.pose * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            [q.x, q.y, q.z]
        })
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
