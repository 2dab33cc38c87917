use nalgebra::Vector3;

use super::*;

#[test]
fn relative_pose_error_of_a_stretched_straight_line() {
    // Closed form: every 1 m step is estimated as 1.1 m, so each step is 0.1 m off.
    let at = |x: f64| Pose::translation(x, 0.0, 0.0);
    let truth: Vec<Pose> = (0..10).map(|i| at(i as f64)).collect();
    let estimate: Vec<Pose> = (0..10).map(|i| at(1.1 * i as f64)).collect();
    assert!((relative_pose_error(&estimate, &truth) - 0.1).abs() < 1e-12);
    assert_eq!(relative_pose_error(&truth, &truth), 0.0);
    assert_eq!(relative_pose_error(&truth[..1], &truth[..1]), 0.0);
}

#[test]
fn rigid_alignment_recovers_a_known_transform_of_a_trajectory() {
    // A non-planar path moved by a known transform: the alignment is that transform,
    // and the ATE of the moved path against the original is zero.
    let truth: Vec<Pose> = (0..30)
        .map(|i| {
            let t = i as f64 * 0.3;
            Pose::new(
                Vector3::new(5.0 * t.cos(), 3.0 * t.sin(), 0.2 * t),
                Vector3::new(0.0, 0.0, t),
            )
        })
        .collect();
    let moved_by = Pose::new(Vector3::new(1.0, -2.0, 0.5), Vector3::new(0.1, -0.2, 1.3));
    let estimate: Vec<Pose> = truth.iter().map(|p| moved_by * p).collect();
    let align = rigid_alignment(&estimate, &truth);
    let expected = moved_by.inverse();
    assert!((align.translation.vector - expected.translation.vector).norm() < 1e-9);
    assert!(align.rotation.angle_to(&expected.rotation) < 1e-9);
    assert!(absolute_trajectory_error(&estimate, &truth) < 1e-9);
    assert_eq!(rigid_alignment(&[], &truth), Pose::identity());
}

#[test]
fn kitti_drift_of_a_stretched_line_and_a_steady_turn_error() {
    // Closed forms on a straight 600 m line, a pose every metre.
    let truth: Vec<Pose> = (0..=600)
        .map(|i| Pose::translation(i as f64, 0.0, 0.0))
        .collect();
    // Every metre estimated as 1.01 m: each segment of L m is 0.01 L off, 1 %.
    let stretched: Vec<Pose> = (0..=600)
        .map(|i| Pose::translation(1.01 * i as f64, 0.0, 0.0))
        .collect();
    let drift = kitti_drift(&stretched, &truth).unwrap();
    assert!((drift.translation_percent - 1.0).abs() < 1e-9, "{drift:?}");
    assert!(drift.rotation_deg_per_100m.abs() < 1e-9);
    // Segments from every pose with 50-400 m ahead: 551 + 501 + ... + 201.
    assert_eq!(drift.segments, (1..=8).map(|k| 601 - 50 * k).sum::<usize>());
    // The heading estimated 0.01 deg too far per metre (positions true): each segment's
    // rotation error is 0.01 deg per metre, 1 deg/100 m.
    let turned: Vec<Pose> = (0..=600)
        .map(|i| {
            let yaw = (0.01 * i as f64).to_radians();
            Pose::new(
                Vector3::new(i as f64, 0.0, 0.0),
                Vector3::new(0.0, 0.0, yaw),
            )
        })
        .collect();
    let drift = kitti_drift(&turned, &truth).unwrap();
    assert!(
        (drift.rotation_deg_per_100m - 1.0).abs() < 1e-9,
        "{drift:?}"
    );
    // Shorter than the shortest segment: no figure.
    assert_eq!(kitti_drift(&truth[..50], &truth[..50]), None);
    assert_eq!(kitti_drift(&truth[..51], &truth[..51]).unwrap().segments, 1);
}
