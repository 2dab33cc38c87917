//! Scan-to-local-map odometry: each scan is registered (GICP) against the last few
//! keyframes merged in the odometry frame, starting from the previous scan's pose.

use std::collections::VecDeque;

use crate::cloud::PointCloud;
use crate::geometry::{Pose, to_point, transform_point};
use crate::map::KeyframeDecider;
use crate::registration::{
    PreparedCloud, RegistrationError, RegistrationParams, RegistrationResult, align,
};

/// Odometry settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdometryParams {
    /// Registration of each scan (voxel size, distances, kernel).
    pub registration: RegistrationParams,
    /// When a scan joins the local map.
    pub local_map_decider: KeyframeDecider,
    /// Keyframes the local map holds.
    pub local_map_keyframes: usize,
}

impl Default for OdometryParams {
    fn default() -> Self {
        Self {
            // Converge tightly: every step's residual error stays in the trajectory.
            registration: RegistrationParams {
                voxel_size: 0.5,
                translation_eps: 1e-4,
                rotation_eps: 0.01f64.to_radians(),
                max_iterations: 30,
                ..RegistrationParams::default()
            },
            // About 40 m of map: 8 keyframes 1 m apart left 43.5 cm keyframe ATE on the
            // simulated campus lap, 20 keyframes 2 m apart 2.2 cm (odometry alone).
            local_map_decider: KeyframeDecider {
                min_translation: 2.0,
                min_rotation_deg: 15.0,
            },
            local_map_keyframes: 20,
        }
    }
}

/// Odometry state: the local map and the last pose.
pub struct Odometry {
    params: OdometryParams,
    /// Local-map keyframes: pose and downsampled points (odometry frame).
    keyframes: VecDeque<(Pose, Vec<[f32; 3]>)>,
    local_map: Option<PreparedCloud>,
    last: Option<Pose>,
}

/// One odometry step.
pub struct OdometryStep {
    /// `T_odom_scan`.
    pub pose: Pose,
    /// The registration against the local map (`None` for the first scan).
    pub registration: Option<RegistrationResult>,
    /// The scan as registered (downsampled, covariances, tree), for callers that keep it.
    pub prepared: PreparedCloud,
}

impl Odometry {
    /// Starts at `T_odom_scan0 = identity`.
    pub fn new(params: OdometryParams) -> Self {
        Self {
            params,
            keyframes: VecDeque::new(),
            local_map: None,
            last: None,
        }
    }

    /// Registers the next scan (sensor frame) and returns its pose.
    pub fn push(&mut self, scan: &PointCloud) -> Result<OdometryStep, RegistrationError> {
        let reg = &self.params.registration;
        let prepared = PreparedCloud::new(scan, reg, "scan")?;
        let (pose, registration) = match (&self.local_map, self.last) {
            (Some(map), Some(last)) => {
                // The last pose, not a constant-velocity extrapolation: on the simulated
                // courtyard and campus the extrapolated guess let GICP settle a little past
                // the true pose each step, the error fed the next guess and odometry
                // diverged within 4 s; from the last pose it stayed within 2 mm.
                let result = align(map, &prepared, &last, reg)?;
                (result.pose, Some(result))
            }
            _ => (Pose::identity(), None),
        };
        self.last = Some(pose);
        let decider = &self.params.local_map_decider;
        if decider.should_create(self.keyframes.iter().map(|(p, _)| p), &pose) {
            let moved: Vec<[f32; 3]> = prepared
                .points
                .iter()
                .map(|p| to_point(&transform_point(&pose, p)))
                .collect();
            self.keyframes.push_back((pose, moved));
            while self.keyframes.len() > self.params.local_map_keyframes {
                self.keyframes.pop_front();
            }
            // Keyframe points are voxelized already; a second grid in the odometry frame
            // would average neighbouring surface points into misplaced centroids.
            let merged: Vec<[f32; 3]> = self
                .keyframes
                .iter()
                .flat_map(|(_, pts)| pts.iter().copied())
                .collect();
            self.local_map = Some(PreparedCloud::from_points(merged, reg, "local map")?);
        }
        Ok(OdometryStep {
            pose,
            registration,
            prepared,
        })
    }
}
