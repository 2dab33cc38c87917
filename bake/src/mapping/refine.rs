//! The joint refinement of every built scan pose (docs/DESIGN.md#joint-refinement): the
//! scans' finer samples and poses handed to `kfmap_graph::refine` in their cloud frames
//! (mid-scan when deskewed), and the result carried back to the scans' stamps.

use kfmap_geometry::geometry::Pose;
use kfmap_graph::refine::{
    Consistency, RefineParams, RefineReport, RefineScan, consistency, refine_poses,
};

/// Every scan's points as the refinement sees them.
#[derive(Debug, Clone)]
pub struct RefineClouds {
    /// Points in each scan's cloud frame (deskewed), on the refinement's voxel grid and
    /// thinned to its point budget.
    clouds: Vec<Vec<[f32; 3]>>,
    /// Every scan's `T_scan_cloud` (identity when the scans were not deskewed).
    scan_from_cloud: Vec<Pose>,
}

impl RefineClouds {
    /// Keeps at most `max-points-per-scan` of each cloud (an even stride).
    pub fn new(
        clouds: Vec<Vec<[f32; 3]>>,
        scan_from_cloud: Vec<Pose>,
        params: &RefineParams,
    ) -> Self {
        let max = params.max_points_per_scan;
        let clouds = clouds
            .into_iter()
            .map(|points| {
                if points.len() <= max {
                    points
                } else {
                    (0..max).map(|k| points[k * points.len() / max]).collect()
                }
            })
            .collect();
        Self {
            clouds,
            scan_from_cloud,
        }
    }

    /// The map consistency of the scans `measured` at `poses` (`T_map_scan`).
    pub fn consistency_at(&self, poses: &[Pose], measured: &[usize]) -> Consistency {
        let clouds: Vec<&[[f32; 3]]> = self.clouds.iter().map(Vec::as_slice).collect();
        consistency(&clouds, &self.cloud_poses(poses), measured)
    }

    fn cloud_poses(&self, poses: &[Pose]) -> Vec<Pose> {
        poses
            .iter()
            .zip(&self.scan_from_cloud)
            .map(|(p, from_cloud)| p * from_cloud)
            .collect()
    }
}

/// Refines `poses` (`T_map_scan`, one per scan; scan 0 stays) in place and reports.
/// `odometry` (`T_odom_scan` per scan, or empty) gives the priors; `measured` names the
/// scans the consistency figures are taken over (the keyframes).
pub fn refine_trajectory(
    clouds: &RefineClouds,
    poses: &mut [Pose],
    odometry: &[Pose],
    measured: &[usize],
    params: &RefineParams,
    progress: impl FnMut(usize, usize),
) -> RefineReport {
    let scans: Vec<RefineScan> = clouds
        .clouds
        .iter()
        .zip(clouds.cloud_poses(poses))
        .map(|(points, pose)| RefineScan {
            points: points.as_slice(),
            pose,
        })
        .collect();
    let odometry = if odometry.len() == poses.len() {
        clouds.cloud_poses(odometry)
    } else {
        Vec::new()
    };
    let (refined, report) = refine_poses(&scans, &odometry, measured, params, progress);
    for ((pose, cloud_pose), from_cloud) in
        poses.iter_mut().zip(refined).zip(&clouds.scan_from_cloud)
    {
        *pose = cloud_pose * from_cloud.inverse();
    }
    report
}
