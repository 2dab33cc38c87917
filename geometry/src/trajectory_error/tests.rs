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
