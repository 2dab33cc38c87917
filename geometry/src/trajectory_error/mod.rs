//! Trajectory error metrics: absolute trajectory error after a rigid alignment (ATE),
//! relative pose error over consecutive poses (RPE), the alignment itself, and the
//! KITTI odometry benchmark's drift over 50-400 m segments.

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

/// Segment lengths of the KITTI odometry benchmark's drift, metres.
pub const KITTI_SEGMENT_LENGTHS_M: [f64; 8] =
    [50.0, 100.0, 150.0, 200.0, 250.0, 300.0, 350.0, 400.0];

/// Drift as the KITTI odometry benchmark measures it ([`kitti_drift`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Drift {
    /// Mean translation error per segment length, percent.
    pub translation_percent: f64,
    /// Mean rotation error per segment length, degrees per 100 m.
    pub rotation_deg_per_100m: f64,
    /// Segments averaged.
    pub segments: usize,
}

/// The KITTI odometry benchmark's drift of `estimate` against `truth` (pose by pose,
/// over the shorter): from every pose `a`, for each length `L` of
/// [`KITTI_SEGMENT_LENGTHS_M`], the first pose `b` at least `L` further along the true
/// path; the error `(E_a^-1 E_b)^-1 (T_a^-1 T_b)` over `L`, its translation (%) and
/// rotation angle (deg/100 m), averaged over every segment (the devkit starts one at
/// every 10th pose; every pose here, as tools/anchors/kitti_drift.py does by default).
/// `None` when the true path is shorter than 50 m.
pub fn kitti_drift(estimate: &[Pose], truth: &[Pose]) -> Option<Drift> {
    let n = estimate.len().min(truth.len());
    let mut along = Vec::with_capacity(n);
    let mut travelled = 0.0;
    for i in 0..n {
        if i > 0 {
            travelled += (truth[i].translation.vector - truth[i - 1].translation.vector).norm();
        }
        along.push(travelled);
    }
    let (mut translation, mut rotation, mut segments) = (0.0, 0.0, 0usize);
    for a in 0..n {
        for length in KITTI_SEGMENT_LENGTHS_M {
            // `along` never decreases: the first pose at least `length` further.
            let b = a + along[a..].partition_point(|&d| d < along[a] + length);
            if b >= n {
                continue;
            }
            let moved = estimate[a].inverse() * estimate[b];
            let true_motion = truth[a].inverse() * truth[b];
            let error = moved.inverse() * true_motion;
            translation += error.translation.vector.norm() / length;
            rotation += error.rotation.angle() / length;
            segments += 1;
        }
    }
    (segments > 0).then(|| Drift {
        translation_percent: 100.0 * translation / segments as f64,
        rotation_deg_per_100m: 100.0 * (rotation / segments as f64).to_degrees(),
        segments,
    })
}

#[cfg(test)]
mod tests;
