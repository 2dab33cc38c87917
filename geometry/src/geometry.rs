//! Pose helpers over `nalgebra::Isometry3<f64>` and packed symmetric 3x3 matrices.
//!
//! Conventions (docs/DESIGN.md#conventions): a pose `T_a_b` maps points expressed in frame
//! `b` into frame `a`; translations are in metres, angles in radians.

use nalgebra::{Isometry3, Matrix3, Quaternion, Translation3, UnitQuaternion, Vector3};

/// A rigid transform `T_a_b` (rotation + translation in metres).
pub type Pose = Isometry3<f64>;

/// `T_a_c = T_a_b * T_b_c`.
pub fn compose(t_a_b: &Pose, t_b_c: &Pose) -> Pose {
    t_a_b * t_b_c
}

/// `T_b_a` from `T_a_b`.
pub fn inverse(t_a_b: &Pose) -> Pose {
    t_a_b.inverse()
}

/// Rotation distance `|| Log_SO3(R_a^T R_b) ||` in radians, in `[0, pi]`.
pub fn rotation_distance(a: &Pose, b: &Pose) -> f64 {
    a.rotation.angle_to(&b.rotation)
}

/// Translation distance `|t_a - t_b|` in metres.
pub fn translation_distance(a: &Pose, b: &Pose) -> f64 {
    (a.translation.vector - b.translation.vector).norm()
}

/// Builds a pose from `[x y z qx qy qz qw]` (the TUM order). The quaternion is
/// normalized; `None` if it is zero or any value is not finite.
pub fn pose_from_xyz_quat(v: [f64; 7]) -> Option<Pose> {
    if v.iter().any(|x| !x.is_finite()) {
        return None;
    }
    let mut q = Quaternion::new(v[6], v[3], v[4], v[5]);
    if !q.norm().is_finite() {
        // Entries near 1e200: the norm overflows and would normalize q to zero. Scaled
        // only then, so that ordinary quaternions normalize bit for bit as always.
        q /= q.coords.amax();
    }
    if q.norm() < 1e-12 {
        return None;
    }
    Some(Isometry3::from_parts(
        Translation3::new(v[0], v[1], v[2]),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// `[x y z qx qy qz qw]` of a pose, with `qw >= 0` so that the output is unique.
pub fn pose_to_xyz_quat(p: &Pose) -> [f64; 7] {
    let t = p.translation.vector;
    let mut q = *p.rotation.quaternion();
    if q.w < 0.0 {
        q = -q;
    }
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

/// Builds a pose from a rotation matrix and translation, re-orthonormalizing the
/// rotation (files hold rounded matrices). `None` if the matrix is not close to a rotation.
pub fn pose_from_matrix(r: Matrix3<f64>, t: Vector3<f64>) -> Option<Pose> {
    if r.iter().chain(t.iter()).any(|x| !x.is_finite()) {
        return None;
    }
    let det = r.determinant();
    let orthogonality = (r.transpose() * r - Matrix3::identity()).norm();
    if (det - 1.0).abs() > 1e-3 || orthogonality > 1e-3 {
        return None;
    }
    let rot = nalgebra::Rotation3::from_matrix_unchecked(r);
    let q = UnitQuaternion::from_rotation_matrix(&rot);
    Some(Isometry3::from_parts(Translation3::from(t), q))
}

/// A symmetric 3x3 matrix packed as six `f32`, order `[xx, xy, xz, yy, yz, zz]`.
pub type PackedSym3 = [f32; 6];

// The small conversions below are `#[inline]`: they run once per point in the map
// server's queries in other crates, where without the hint (no cross-crate LTO in the
// release profile) each is a call of its own.

/// Packs the upper triangle of a (symmetric) matrix.
#[inline]
pub fn pack_sym3(m: &Matrix3<f64>) -> PackedSym3 {
    [
        m[(0, 0)] as f32,
        m[(0, 1)] as f32,
        m[(0, 2)] as f32,
        m[(1, 1)] as f32,
        m[(1, 2)] as f32,
        m[(2, 2)] as f32,
    ]
}

/// Unpacks six floats into a full symmetric matrix.
#[inline]
pub fn unpack_sym3(p: &PackedSym3) -> Matrix3<f64> {
    let [xx, xy, xz, yy, yz, zz] = p.map(f64::from);
    Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz)
}

/// Converts a stored `f32` point to an f64 vector for math.
#[inline]
pub fn to_vec3(p: &[f32; 3]) -> Vector3<f64> {
    Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

/// Converts an f64 vector back to a stored `f32` point.
#[inline]
pub fn to_point(v: &Vector3<f64>) -> [f32; 3] {
    [v.x as f32, v.y as f32, v.z as f32]
}

/// A stored `f32` point moved by `pose`, in f64.
#[inline]
pub fn transform_point(pose: &Pose, p: &[f32; 3]) -> Vector3<f64> {
    pose.rotation * to_vec3(p) + pose.translation.vector
}

/// Appends `points` moved by `pose` to `moved_points`, and their covariances rotated with
/// them (`R C R^T`) to `moved_covariances`: a cloud's estimates carried into another
/// frame instead of estimated again there.
pub fn extend_moved(
    pose: &Pose,
    points: &[[f32; 3]],
    covariances: &[PackedSym3],
    moved_points: &mut Vec<[f32; 3]>,
    moved_covariances: &mut Vec<PackedSym3>,
) {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    moved_points.extend(points.iter().map(|p| to_point(&transform_point(pose, p))));
    moved_covariances.extend(
        covariances
            .iter()
            .map(|c| pack_sym3(&(r * unpack_sym3(c) * r.transpose()))),
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Turned 90 degrees about z and shifted: x becomes y, so a covariance of variances
    /// (1, 2, 3) along x, y, z becomes (2, 1, 3) (closed form).
    #[test]
    fn moved_points_carry_their_covariances_rotated() {
        let pose = Pose::new(
            Vector3::new(1.0, 2.0, 3.0),
            Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2),
        );
        let c = pack_sym3(&Matrix3::from_diagonal(&Vector3::new(1.0, 2.0, 3.0)));
        let (mut points, mut covariances) = (Vec::new(), Vec::new());
        extend_moved(
            &pose,
            &[[1.0, 0.0, 0.0]],
            &[c],
            &mut points,
            &mut covariances,
        );
        let p = points[0];
        assert!(
            (p[0] - 1.0).abs() < 1e-6 && (p[1] - 3.0).abs() < 1e-6 && (p[2] - 3.0).abs() < 1e-6
        );
        let want = Matrix3::from_diagonal(&Vector3::new(2.0, 1.0, 3.0));
        assert!(
            (unpack_sym3(&covariances[0]) - want).abs().max() < 1e-6,
            "{covariances:?}"
        );
    }
    use proptest::prelude::*;

    /// Fuzzing (`fuzz/regressions/tum_quaternion_norm_overflow.txt`): a quaternion with
    /// an entry of 1e200 became the zero rotation. Oracle: it is (1, 0, 0, 0) scaled,
    /// a half turn about x.
    #[test]
    fn a_huge_quaternion_is_normalized_not_zeroed() {
        let pose = pose_from_xyz_quat([0.0, 0.0, 0.0, 1e200, 0.0, 0.0, 1.0]).unwrap();
        let q = pose.rotation.quaternion();
        assert!((q.norm() - 1.0).abs() < 1e-12, "{q:?}");
        assert!((q.i.abs() - 1.0).abs() < 1e-12, "{q:?}");
        assert_eq!(pose_from_xyz_quat([0.0; 7]), None);
        assert_eq!(
            pose_from_xyz_quat([0.0, 0.0, 0.0, 1e-300, 0.0, 0.0, 0.0]),
            None
        );
    }

    fn pose_strategy() -> impl Strategy<Value = Pose> {
        (
            prop::array::uniform3(-100.0f64..100.0),
            prop::array::uniform3(-3.2f64..3.2),
        )
            .prop_map(|(t, r)| Isometry3::new(Vector3::from(t), Vector3::from(r)))
    }

    proptest! {
        #[test]
        fn xyz_quat_round_trip(p in pose_strategy()) {
            let back = pose_from_xyz_quat(pose_to_xyz_quat(&p)).unwrap();
            prop_assert!(translation_distance(&p, &back) < 1e-9);
            prop_assert!(rotation_distance(&p, &back) < 1e-9);
        }

        #[test]
        fn compose_with_inverse_is_identity(a in pose_strategy(), b in pose_strategy()) {
            let ab = compose(&a, &b);
            let back = compose(&inverse(&a), &ab);
            prop_assert!(translation_distance(&back, &b) < 1e-9);
            prop_assert!(rotation_distance(&back, &b) < 1e-9);
        }

        #[test]
        fn matrix_round_trip(p in pose_strategy()) {
            let r = p.rotation.to_rotation_matrix().into_inner();
            let back = pose_from_matrix(r, p.translation.vector).unwrap();
            prop_assert!(rotation_distance(&p, &back) < 1e-9);
        }
    }

    #[test]
    fn rotation_distance_matches_closed_form() {
        // A rotation of angle a about any axis is at distance |a| from identity.
        for &a in &[0.0, 0.1, 1.0, 3.0] {
            let axis = Vector3::new(1.0, -2.0, 0.5).normalize();
            let p = Isometry3::new(Vector3::zeros(), axis * a);
            assert!((rotation_distance(&Pose::identity(), &p) - a).abs() < 1e-12);
        }
    }

    #[test]
    fn sym3_round_trip_is_symmetric() {
        let m = Matrix3::new(1.0, 2.0, 3.0, 2.0, 4.0, 5.0, 3.0, 5.0, 6.0);
        let packed = pack_sym3(&m);
        assert_eq!(packed, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        assert_eq!(unpack_sym3(&packed), m);
    }

    #[test]
    fn rejects_degenerate_inputs() {
        assert!(pose_from_xyz_quat([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]).is_none());
        assert!(pose_from_xyz_quat([f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).is_none());
        assert!(pose_from_matrix(Matrix3::identity() * 2.0, Vector3::zeros()).is_none());
    }
}
