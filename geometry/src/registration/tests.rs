use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};
use proptest::prelude::*;

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

/// `solve_pose` with fixed settings over pairs from `pairs_at`.
fn solve(
    initial: &Pose,
    optimizer: Optimizer,
    source_len: usize,
    mut pairs_at: impl FnMut(&Pose) -> Vec<Correspondence>,
) -> RegistrationResult {
    let params = RegistrationParams {
        optimizer,
        max_iterations: 50,
        ..RegistrationParams::default()
    };
    solve_pose(initial, &params, source_len, |pose| {
        Ok::<_, RegistrationError>(pairs_at(pose))
    })
    .unwrap()
}

#[test]
fn points_on_a_line_are_moved_across_it_only() {
    // Source points on the line `t d` through the source origin, paired with the target
    // line `tau + t d` by point-to-line weights `I - d d^T`: translation along the line
    // and rotation about it are unobservable.
    let d = Vector3::<f64>::new(1.0, 2.0, 2.0) / 3.0;
    let across = Vector3::new(0.2, -0.1, 0.0);
    assert!(across.dot(&d).abs() < 1e-15);
    let tau = d * 0.3 + across;
    let information = Matrix3::identity() - d * d.transpose();
    let pairs: Vec<Correspondence> = (0..50)
        .map(|i| {
            let source = d * (i as f64 * 0.2 - 4.0);
            Correspondence {
                source,
                target: source + tau,
                information,
            }
        })
        .collect();
    let along = d * 0.5;
    for optimizer in [Optimizer::GaussNewton, Optimizer::LevenbergMarquardt] {
        let result = solve(
            &Pose::new(along, Vector3::zeros()),
            optimizer,
            pairs.len(),
            |_| pairs.clone(),
        );
        // Closed form: the across-line offset is corrected, the start along the line
        // (0.5 m, not the 0.3 m of `tau`) is kept, and nothing rotates.
        let off = result.pose.translation.vector - (along + across);
        assert!(
            off.norm() < 1e-9 && result.pose.rotation.angle() < 1e-9,
            "{optimizer:?}: {:?}",
            result.pose
        );
        assert!(result.converged && result.degenerate, "{optimizer:?}");
        assert_eq!(result.unobservable, 2, "{optimizer:?}");
    }
}

/// A corridor infinite along x: floor `z = 0`, walls `y = 0` and `y = 4` (target frame).
/// Returns sample points of its surfaces and their unit normals.
fn corridor() -> Vec<(Vector3<f64>, Vector3<f64>)> {
    let mut surfaces = Vec::new();
    for i in 0..41 {
        let x = i as f64 * 0.5 - 10.0;
        for j in 1..8 {
            let s = j as f64 * 0.5;
            surfaces.push((Vector3::new(x, s, 0.0), Vector3::z()));
            surfaces.push((Vector3::new(x, 0.0, s * 0.5), Vector3::y()));
            surfaces.push((Vector3::new(x, 4.0, s * 0.5), Vector3::y()));
        }
    }
    surfaces
}

#[test]
fn a_corridor_is_aligned_across_and_left_alone_along_its_axis() {
    let offset = Vector3::new(0.4, -0.15, 0.1);
    let surfaces = corridor();
    // Source = the corridor seen from `offset`, so T_target_source = offset.
    let sources: Vec<Vector3<f64>> = surfaces.iter().map(|(p, _)| p - offset).collect();
    // Nearest point of an infinite surface: the foot of the perpendicular on it, with
    // point-to-plane weights `n n^T`.
    let pairs_at = |pose: &Pose| -> Vec<Correspondence> {
        sources
            .iter()
            .zip(&surfaces)
            .map(|(s, (p, n))| {
                let moved = pose * nalgebra::Point3::from(*s);
                Correspondence {
                    source: *s,
                    target: moved.coords - n * n.dot(&(moved.coords - p)),
                    information: n * n.transpose(),
                }
            })
            .collect()
    };
    for optimizer in [Optimizer::GaussNewton, Optimizer::LevenbergMarquardt] {
        let result = solve(&Pose::identity(), optimizer, sources.len(), pairs_at);
        // dy and dz are recovered; dx is unobservable and stays at the guess (0).
        let expected = Vector3::new(0.0, offset.y, offset.z);
        let off = result.pose.translation.vector - expected;
        assert!(
            off.norm() < 1e-9 && result.pose.rotation.angle() < 1e-9,
            "{optimizer:?}: {:?}",
            result.pose
        );
        assert!(result.converged && result.degenerate, "{optimizer:?}");
        assert_eq!(result.unobservable, 1, "{optimizer:?}");
    }
}

/// The scaled metric the step is least-length in (`solve_step`'s own scaling).
use super::solver::scaling as documented_scaling;

/// A normal-equation system with Hessian `h` and gradient `g`.
fn system(hessian: Matrix6<f64>, gradient: Vector6<f64>) -> Linearized {
    Linearized {
        hessian,
        gradient,
        cost: 0.0,
        count: 1,
    }
}

fn matrix(entries: &[f64]) -> Matrix6<f64> {
    Matrix6::from_row_slice(&entries[..36])
}

/// Rotation rows and columns scaled by `lever` (metres), as point clouds of that size do.
fn with_lever(m: &Matrix6<f64>, lever: f64) -> Matrix6<f64> {
    let d = Matrix6::from_diagonal(&Vector6::new(lever, lever, lever, 1.0, 1.0, 1.0));
    d * m * d
}

proptest! {
    #[test]
    fn a_well_conditioned_step_is_the_plain_solve(
        entries in prop::collection::vec(-1.0f64..1.0, 42),
        lever in 0.1f64..100.0,
        lambda in prop_oneof![Just(0.0), Just(1e-4), 0.0f64..10.0],
    ) {
        let a = matrix(&entries);
        let h = with_lever(&(a.transpose() * a + Matrix6::identity() * 0.1), lever);
        let g = Vector6::from_column_slice(&entries[36..]);
        let step = solve_step(&system(h, g), lambda).unwrap();
        // An independent factorization of the same system.
        let expected = (h + Matrix6::identity() * lambda).lu().solve(&(-g)).unwrap();
        prop_assert_eq!(step.unobservable, 0);
        prop_assert!(
            (step.delta - expected).norm() <= 1e-9 * expected.norm(),
            "{} vs {}", step.delta, expected
        );
    }

    #[test]
    fn a_rank_deficient_step_is_the_least_squares_step_of_least_scaled_length(
        entries in prop::collection::vec(-1.0f64..1.0, 48),
        eigenvalues in prop::collection::vec(0.5f64..2.0, 6),
        rank in 0usize..6,
        lever in 0.5f64..5.0,
        lambda in prop_oneof![Just(0.0), Just(1e-4), 0.0f64..10.0],
    ) {
        // H = D V diag(mu) V^T D with 6 - rank zero eigenvalues; g in its range.
        let v = matrix(&entries).qr().q();
        let mu = Vector6::from_fn(|i, _| if i < rank { eigenvalues[i] } else { 0.0 });
        let h = with_lever(&(v * Matrix6::from_diagonal(&mu) * v.transpose()), lever);
        let h = (h + h.transpose()) * 0.5;
        let g = h * Vector6::from_column_slice(&entries[36..42]);
        let step = solve_step(&system(h, g), lambda).unwrap();
        prop_assert_eq!(step.unobservable, 6 - rank);
        let s = documented_scaling(&h);
        let s2 = s * s;
        let s2_inverse = s2.try_inverse().unwrap();
        let scale = h.norm() * step.delta.norm() + g.norm();
        // Null directions of H: D^-1 times the zero-eigenvalue columns of V.
        let d_inverse = Matrix6::from_diagonal(&Vector6::new(
            1.0 / lever, 1.0 / lever, 1.0 / lever, 1.0, 1.0, 1.0,
        ));
        for i in rank..6 {
            let null = d_inverse * v.column(i);
            // No component along an unobservable direction (in the scaled metric).
            let along = (s2_inverse * step.delta).dot(&null);
            prop_assert!(
                along.abs() <= 1e-9 * (s2_inverse * step.delta).norm() * null.norm(),
                "component {} along null direction {}", along, i
            );
        }
        // Optimal over the observable directions: the damped residual, mapped by S^2,
        // has nothing in H's range.
        let residual = (h + Matrix6::identity() * lambda) * step.delta + g;
        prop_assert!((h * s2 * residual).norm() <= 1e-9 * h.norm() * s2.norm() * scale);
        if lambda == 0.0 {
            // g is in H's range: the step solves the system exactly.
            prop_assert!(residual.norm() <= 1e-9 * scale, "{}", residual);
        }
    }
}
