//! How well a registered cloud lies on its target at a chosen distance, independent of
//! the distance the registration itself paired points within (a wide search distance
//! accepts loose pairs, so its own inlier ratio cannot tell a wrong minimum).

use rayon::prelude::*;

use super::{Fitness, PreparedCloud};
use crate::geometry::{Pose, to_vec3};

/// Share of `source` points (moved by `pose`, `T_target_source`) with a `target` point
/// within `max_distance` metres, and the RMS distance of those pairs.
pub fn overlap(
    target: &PreparedCloud,
    source: &PreparedCloud,
    pose: &Pose,
    max_distance: f64,
) -> Fitness {
    let max_sq = (max_distance * max_distance) as f32;
    let rotation = pose.rotation.to_rotation_matrix().into_inner();
    let tree = target.tree.view();
    let (count, sum_sq) = source
        .points
        .par_iter()
        .filter_map(|p| {
            let moved = rotation * to_vec3(p) + pose.translation.vector;
            let query = [moved.x as f32, moved.y as f32, moved.z as f32];
            tree.nearest_one_within(&query, max_sq)
        })
        .map(|(_, d_sq)| (1usize, d_sq as f64))
        .reduce(|| (0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
    Fitness {
        inlier_ratio: count as f64 / source.points.len().max(1) as f64,
        rmse: if count > 0 {
            (sum_sq / count as f64).sqrt()
        } else {
            f64::INFINITY
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::registration::RegistrationParams;

    #[test]
    fn overlap_counts_points_within_the_distance_as_brute_force_does() {
        let params = RegistrationParams {
            voxel_size: 0.0,
            ..RegistrationParams::default()
        };
        let grid: Vec<[f32; 3]> = (0..400)
            .map(|i| [(i % 20) as f32 * 0.1, (i / 20) as f32 * 0.1, 0.0])
            .collect();
        let target = PreparedCloud::from_points(grid.clone(), &params, "target").unwrap();
        let source = PreparedCloud::from_points(grid, &params, "source").unwrap();
        // Lifted 0.3 m: every point is 0.3 m from its partner.
        let lifted = Pose::translation(0.0, 0.0, 0.3);
        let within = overlap(&target, &source, &lifted, 0.35);
        assert_eq!(within.inlier_ratio, 1.0);
        assert!((within.rmse - 0.3).abs() < 1e-6);
        assert_eq!(overlap(&target, &source, &lifted, 0.25).inlier_ratio, 0.0);
        // Shifted 1 m along x: the 10 columns past the edge lose their partners... as a
        // brute-force count does.
        let shifted = Pose::translation(1.05, 0.0, 0.0);
        let brute = source
            .points
            .iter()
            .filter(|p| {
                target.points.iter().any(|q| {
                    let d = [p[0] + 1.05 - q[0], p[1] - q[1], p[2] - q[2]];
                    d.iter().map(|c| c * c).sum::<f32>() < 0.2 * 0.2
                })
            })
            .count();
        let got = overlap(&target, &source, &shifted, 0.2).inlier_ratio;
        assert_eq!(got, brute as f64 / 400.0);
        assert!(got > 0.0 && got < 1.0);
    }
}
