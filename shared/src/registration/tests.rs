use nalgebra::{Matrix3, Vector3};

use super::*;
use crate::cloud::PointCloud;
use crate::geometry::{Pose, to_point, transform_point};

/// Three walls and a floor, 10 cm grid.
fn room() -> Vec<[f32; 3]> {
    let mut points = Vec::new();
    for i in 0..40 {
        for j in 0..40 {
            let (a, b) = (i as f32 * 0.1, j as f32 * 0.1);
            points.extend([[a, b, 0.0], [a, 0.0, b], [0.0, a, b], [a, 4.0, b]]);
        }
    }
    points
}

#[test]
fn every_metric_and_optimizer_recovers_a_known_motion() {
    let known = Pose::new(
        Vector3::new(0.12, -0.05, 0.03),
        Vector3::new(0.01, -0.02, 0.03),
    );
    let target = PointCloud::from_points(room());
    // source = known^-1 * target, so T_target_source = known.
    let inverse = known.inverse();
    let source = PointCloud::from_points(
        room()
            .iter()
            .map(|p| to_point(&transform_point(&inverse, p)))
            .collect(),
    );
    for metric in [Metric::Gicp, Metric::PointToPoint, Metric::PointToPlane] {
        for optimizer in [Optimizer::GaussNewton, Optimizer::LevenbergMarquardt] {
            let params = RegistrationParams {
                metric,
                optimizer,
                voxel_size: 0.0,
                max_iterations: 50,
                ..RegistrationParams::default()
            };
            let result = register(&target, &source, &Pose::identity(), &params).unwrap();
            let off = result.pose.inverse() * known;
            assert!(
                off.translation.vector.norm() < 1e-3 && off.rotation.angle() < 1e-3,
                "{metric:?} {optimizer:?}: {off:?}"
            );
        }
    }
}

#[test]
fn cost_is_the_cost_linearize_reports() {
    let pose = Pose::new(Vector3::new(0.3, 0.1, -0.2), Vector3::new(0.05, 0.0, -0.1));
    let pairs: Vec<Correspondence> = room()
        .iter()
        .step_by(7)
        .enumerate()
        .map(|(k, p)| Correspondence {
            source: Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64),
            target: Vector3::new(p[1] as f64, p[0] as f64 + 0.1, k as f64 * 1e-3),
            information: Matrix3::identity() * (1.0 + (k % 3) as f64),
        })
        .collect();
    for kernel in [RobustKernel::None, RobustKernel::Huber { delta: 0.5 }] {
        let full = linearize(&pairs, &pose, &kernel).cost;
        assert!((cost(&pairs, &pose, &kernel) - full).abs() <= 1e-12 * full.max(1.0));
    }
}
