//! SE(3) exponential, logarithm and adjoint in `(omega, v)` order (rotation first), as
//! GTSAM's `Pose3` uses them.

use nalgebra::{Matrix3, Matrix6, UnitQuaternion, Vector3, Vector6};

use crate::geometry::Pose;

fn split(xi: &Vector6<f64>) -> (Vector3<f64>, Vector3<f64>) {
    (
        xi.fixed_rows::<3>(0).into_owned(),
        xi.fixed_rows::<3>(3).into_owned(),
    )
}

/// `(A, B, C)` of the SE(3) series: `sin t / t`, `(1 - cos t) / t^2`, `(1 - A) / t^2`.
fn coefficients(theta: f64) -> (f64, f64, f64) {
    if theta < 1e-4 {
        let t2 = theta * theta;
        (1.0 - t2 / 6.0, 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0)
    } else {
        let (s, c) = theta.sin_cos();
        let a = s / theta;
        (a, (1.0 - c) / (theta * theta), (1.0 - a) / (theta * theta))
    }
}

/// `Exp(xi)`: rotation `exp(omega)`, translation `V v`.
pub fn exp(xi: &Vector6<f64>) -> Pose {
    let (omega, v) = split(xi);
    let (_, b, c) = coefficients(omega.norm());
    let w = omega.cross_matrix();
    let t = (Matrix3::identity() + w * b + w * w * c) * v;
    Pose::from_parts(t.into(), UnitQuaternion::from_scaled_axis(omega))
}

/// `Log(T)`: `(omega, V^-1 t)`.
pub fn log(pose: &Pose) -> Vector6<f64> {
    let omega = pose.rotation.scaled_axis();
    let theta = omega.norm();
    let w = omega.cross_matrix();
    let (a, b, _) = coefficients(theta);
    // V^-1 = I - W/2 + (1 - A / (2B)) / theta^2 W^2; the factor tends to 1/12.
    let factor = if theta < 1e-4 {
        1.0 / 12.0 + theta * theta / 720.0
    } else {
        (1.0 - a / (2.0 * b)) / (theta * theta)
    };
    let v = (Matrix3::identity() - w * 0.5 + w * w * factor) * pose.translation.vector;
    Vector6::new(omega.x, omega.y, omega.z, v.x, v.y, v.z)
}

/// `Ad(T)`, so that `T Exp(xi) = Exp(Ad(T) xi) T`.
pub fn adjoint(pose: &Pose) -> Matrix6<f64> {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let mut ad = Matrix6::zeros();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    ad.fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&(pose.translation.vector.cross_matrix() * r));
    ad
}

/// First-order inverse right Jacobian `I + ad(xi) / 2`: how `Log(T Exp(d))` moves with
/// `d` near `T = Exp(xi)`.
pub fn right_jacobian_inverse(xi: &Vector6<f64>) -> Matrix6<f64> {
    let (omega, v) = split(xi);
    let mut ad = Matrix6::zeros();
    let w = omega.cross_matrix();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&w);
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&w);
    ad.fixed_view_mut::<3, 3>(3, 0).copy_from(&v.cross_matrix());
    Matrix6::identity() + ad * 0.5
}
