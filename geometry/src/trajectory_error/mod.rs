//! Trajectory error metrics: absolute trajectory error after a rigid alignment (ATE),
//! relative pose error over consecutive poses (RPE), and the alignment itself.

use nalgebra::{Matrix3, Point3, Rotation3, Vector3};

use crate::geometry::Pose;

/// Absolute trajectory error: RMS position difference after the rigid alignment
/// ([`rigid_alignment`]) of `estimate` onto `truth`, metres.
pub fn absolute_trajectory_error(estimate: &[Pose], truth: &[Pose]) -> f64 {
    let n = estimate.len().min(truth.len());
    if n == 0 {
        return 0.0;
    }
    let align = rigid_alignment(&estimate[..n], &truth[..n]);
    let sum_sq: f64 = estimate[..n]
        .iter()
        .zip(&truth[..n])
        .map(|(e, t)| {
            (align * Point3::from(e.translation.vector) - Point3::from(t.translation.vector))
                .norm_squared()
        })
        .sum();
    (sum_sq / n as f64).sqrt()
}

/// The rigid transform (Umeyama/Horn, no scale) that moves the positions of `estimate`
/// closest to those of `truth` in the least-squares sense, pose by pose over the
/// shorter of the two: `T_truth_estimate`. Identity with no pair; the rotation about a
/// straight path's line is left undetermined (positions alone cannot fix it).
pub fn rigid_alignment(estimate: &[Pose], truth: &[Pose]) -> Pose {
    let n = estimate.len().min(truth.len());
    if n == 0 {
        return Pose::identity();
    }
    let p: Vec<Vector3<f64>> = estimate[..n].iter().map(|x| x.translation.vector).collect();
    let q: Vec<Vector3<f64>> = truth[..n].iter().map(|x| x.translation.vector).collect();
    let (mp, mq) = (
        p.iter().sum::<Vector3<f64>>() / n as f64,
        q.iter().sum::<Vector3<f64>>() / n as f64,
    );
    let cross: Matrix3<f64> = p
        .iter()
        .zip(&q)
        .map(|(a, b)| (b - mq) * (a - mp).transpose())
        .sum();
    let svd = cross.svd(true, true);
    let (u, v_t) = (svd.u.expect("u"), svd.v_t.expect("v_t"));
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = Rotation3::from_matrix_unchecked(u * d * v_t);
    Pose::from_parts((mq - r * mp).into(), r.into())
}

/// Relative pose error over consecutive poses: RMS translation error of each step's
/// motion `T_i^-1 T_{i+1}` against the truth's, metres.
pub fn relative_pose_error(estimate: &[Pose], truth: &[Pose]) -> f64 {
    let n = estimate.len().min(truth.len());
    if n < 2 {
        return 0.0;
    }
    let sum_sq: f64 = (0..n - 1)
        .map(|i| {
            let e = estimate[i].inverse() * estimate[i + 1];
            let t = truth[i].inverse() * truth[i + 1];
            (e.inverse() * t).translation.vector.norm_squared()
        })
        .sum();
    (sum_sq / (n - 1) as f64).sqrt()
}

#[cfg(test)]
mod tests;
