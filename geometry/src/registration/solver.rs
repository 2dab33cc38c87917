//! One Gauss-Newton / Levenberg-Marquardt pose solver over correspondences with
//! information matrices: GICP, point-to-point and point-to-plane ICP, and the map
//! server's localization all reduce to it.

use nalgebra::{Matrix3, Matrix6, SymmetricEigen, Vector3, Vector6};
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use serde::{Deserialize, Serialize};

use super::RobustKernel;
use crate::geometry::Pose;

/// One residual `r = target - T source` weighted by `information` (`r^T W r`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correspondence {
    /// The source point, source frame.
    pub source: Vector3<f64>,
    /// The matched target point, target frame.
    pub target: Vector3<f64>,
    /// `W`, e.g. `(C_t + R C_s R^T)^-1` for GICP.
    pub information: Matrix3<f64>,
}

/// The normal equations of one linearization, with the weighted cost.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Linearized {
    /// `sum J^T w W J` (6x6; rotation first, then translation).
    pub hessian: Matrix6<f64>,
    /// `sum J^T w W r`.
    pub gradient: Vector6<f64>,
    /// `sum w r^T W r`.
    pub cost: f64,
    /// Correspondences summed.
    pub count: usize,
}

impl Linearized {
    fn zero() -> Self {
        Self {
            hessian: Matrix6::zeros(),
            gradient: Vector6::zeros(),
            cost: 0.0,
            count: 0,
        }
    }

    fn add(mut self, other: &Self) -> Self {
        self.hessian += other.hessian;
        self.gradient += other.gradient;
        self.cost += other.cost;
        self.count += other.count;
        self
    }
}

/// Correspondences summed per parallel task: fixed, so the floating-point sum is the
/// same for any thread count.
const CHUNK: usize = 512;

/// Linearizes at `pose` with the right perturbation `T exp(d)`, `d = (omega, v)`:
/// `d(T s)/d(d) = R [-[s]x, I]`, so `J = [R [s]x, -R]` for `r = t - T s`.
pub fn linearize(
    correspondences: &[Correspondence],
    pose: &Pose,
    kernel: &RobustKernel,
) -> Linearized {
    let rotation = pose.rotation.to_rotation_matrix().into_inner();
    let partial: Vec<Linearized> = correspondences
        .par_chunks(CHUNK)
        .map(|chunk| {
            // Summed with `J' = [[R s]x, -I]` (`J = J' diag(R, R)`): the rotation is
            // applied once to the sums below instead of to every term.
            let mut sum = Linearized::zero();
            for c in chunk {
                let rotated = rotation * c.source;
                let r = c.target - (rotated + pose.translation.vector);
                let weighted_r = c.information * r;
                let e2 = r.dot(&weighted_r);
                let w = kernel.weight(e2);
                let info = c.information * w;
                let qx = rotated.cross_matrix();
                let qx_t_info = qx.transpose() * info;
                let mut h = sum.hessian.fixed_view_mut::<3, 3>(0, 0);
                h += qx_t_info * qx;
                let mut h = sum.hessian.fixed_view_mut::<3, 3>(0, 3);
                h -= qx_t_info;
                let mut h = sum.hessian.fixed_view_mut::<3, 3>(3, 3);
                h += info;
                let mut g = sum.gradient.fixed_rows_mut::<3>(0);
                g += qx_t_info * r;
                let mut g = sum.gradient.fixed_rows_mut::<3>(3);
                g -= weighted_r * w;
                sum.cost += w * e2;
                sum.count += 1;
            }
            sum
        })
        .collect();
    let mut total = partial.iter().fold(Linearized::zero(), |a, b| a.add(b));
    let top_right = total.hessian.fixed_view::<3, 3>(0, 3).into_owned();
    total
        .hessian
        .fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&top_right.transpose());
    let mut rotate = Matrix6::zeros();
    rotate.fixed_view_mut::<3, 3>(0, 0).copy_from(&rotation);
    rotate.fixed_view_mut::<3, 3>(3, 3).copy_from(&rotation);
    total.hessian = rotate.transpose() * total.hessian * rotate;
    total.gradient = rotate.transpose() * total.gradient;
    total
}

/// `r = t - T s` and its squared Mahalanobis length.
#[inline]
fn residual(c: &Correspondence, rotation: &Matrix3<f64>, pose: &Pose) -> (Vector3<f64>, f64) {
    let r = c.target - (rotation * c.source + pose.translation.vector);
    (r, r.dot(&(c.information * r)))
}

/// The weighted cost `linearize` would report at `pose`, without the derivatives (for
/// accepting or rejecting a damped step).
pub fn cost(correspondences: &[Correspondence], pose: &Pose, kernel: &RobustKernel) -> f64 {
    let rotation = pose.rotation.to_rotation_matrix().into_inner();
    let partial: Vec<f64> = correspondences
        .par_chunks(CHUNK)
        .map(|chunk| {
            chunk
                .iter()
                .map(|c| {
                    let e2 = residual(c, &rotation, pose).1;
                    kernel.weight(e2) * e2
                })
                .sum()
        })
        .collect();
    partial.iter().sum()
}

/// The step method.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Optimizer {
    /// Plain Gauss-Newton steps.
    GaussNewton,
    /// Damped steps (`H + lambda I`), accepted only when the cost drops.
    LevenbergMarquardt,
}

/// The pose update `T exp(d)` (rotation by `omega`, then translation `v` in the body).
pub fn retract(pose: &Pose, step: &Vector6<f64>) -> Pose {
    let omega = Vector3::new(step[0], step[1], step[2]);
    let v = Vector3::new(step[3], step[4], step[5]);
    pose * Pose::new(v, omega)
}

/// A solved step and the directions it could not move along.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step {
    /// `d = (omega, v)` for [`retract`]: rotation in radians, then translation in
    /// metres, both in the body (source) frame.
    pub delta: Vector6<f64>,
    /// How many directions of `d` the Hessian does not constrain (0 to 6); `delta` has
    /// no component along them, so the pose keeps its guess there.
    pub unobservable: usize,
}

/// Eigenvalues of the scaled Hessian below this fraction of the largest are
/// unobservable directions: their information is rounding noise, and a step along
/// them would amplify it by the inverse ratio.
pub const UNOBSERVABLE_RATIO: f64 = 1e-9;

/// Solves `(H + lambda I) d = -g` over the directions `H` observes.
///
/// Observability is decided on `S H S` with `S = diag(I / L, I)`, where
/// `L = sqrt(tr H_rr / tr H_tt)` metres (the RMS lever arm of the constraints) turns
/// rotations into displacements comparable with translations: eigen-directions whose
/// eigenvalue is at most [`UNOBSERVABLE_RATIO`] times the largest are unobservable.
/// When none is, this is the plain Cholesky solve. Otherwise the system is solved on
/// the observable eigen-directions only (with `lambda = 0`: the least-squares step
/// of least scaled length, the observable-directions update of Zhang, Kaess and Singh,
/// "On degeneracy of optimization-based state estimation problems", ICRA 2016).
/// `None` only for a non-finite system or a negative or non-finite `lambda`.
pub fn solve_step(lin: &Linearized, lambda: f64) -> Option<Step> {
    let finite = lin
        .hessian
        .iter()
        .chain(lin.gradient.iter())
        .all(|v| v.is_finite());
    if !finite || !lambda.is_finite() || lambda < 0.0 {
        return None;
    }
    let damped = lin.hessian + Matrix6::identity() * lambda;
    let scale = scaling(&lin.hessian);
    let eigen = SymmetricEigen::new(scale * lin.hessian * scale);
    let largest = eigen.eigenvalues.max();
    let observable = eigen
        .eigenvalues
        .map(|e| largest > 0.0 && e > UNOBSERVABLE_RATIO * largest);
    let unobservable = observable.iter().filter(|&&o| !o).count();
    if unobservable == 0
        && let Some(cholesky) = damped.cholesky()
    {
        return Some(Step {
            delta: cholesky.solve(&(-lin.gradient)),
            unobservable,
        });
    }
    // `d = B z` over the observable columns of `B = S V`; the other columns are zero
    // and their unknowns pinned to 0 by a unit diagonal.
    let mut basis = Matrix6::zeros();
    for (i, _) in observable.iter().enumerate().filter(|(_, o)| **o) {
        basis.set_column(i, &(scale * eigen.eigenvectors.column(i)));
    }
    let mut reduced = basis.transpose() * damped * basis;
    for (i, _) in observable.iter().enumerate().filter(|(_, o)| !**o) {
        reduced[(i, i)] = 1.0;
    }
    let z = reduced
        .cholesky()?
        .solve(&(-basis.transpose() * lin.gradient));
    Some(Step {
        delta: basis * z,
        unobservable,
    })
}

/// `S = diag(I / L, I)` of [`solve_step`] (identity when a block carries nothing).
pub(super) fn scaling(hessian: &Matrix6<f64>) -> Matrix6<f64> {
    let rotation = hessian.fixed_view::<3, 3>(0, 0).trace();
    let translation = hessian.fixed_view::<3, 3>(3, 3).trace();
    let per_radian = if rotation > 0.0 && translation > 0.0 {
        (translation / rotation).sqrt()
    } else {
        1.0
    };
    Matrix6::from_diagonal(&Vector6::new(
        per_radian, per_radian, per_radian, 1.0, 1.0, 1.0,
    ))
}

/// How well the Hessian constrains each block: the smallest over the largest
/// eigenvalue of its rotation and translation 3x3 blocks (1 = isotropic, near 0 = a
/// direction the scene does not constrain, e.g. along a corridor).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Constraint {
    /// Rotation block min/max eigenvalue ratio.
    pub rotation_ratio: f64,
    /// Translation block min/max eigenvalue ratio.
    pub translation_ratio: f64,
}

impl Constraint {
    /// Of a 6x6 Hessian (rotation first).
    pub fn of(hessian: &Matrix6<f64>) -> Self {
        let ratio = |m: Matrix3<f64>| {
            let e = SymmetricEigen::new(m).eigenvalues;
            let max = e.max();
            if max > 0.0 {
                (e.min() / max).max(0.0)
            } else {
                0.0
            }
        };
        Self {
            rotation_ratio: ratio(hessian.fixed_view::<3, 3>(0, 0).into_owned()),
            translation_ratio: ratio(hessian.fixed_view::<3, 3>(3, 3).into_owned()),
        }
    }
}

/// The scatter of the cost's gradient over spatial clusters at a solution: the "meat"
/// `M = sum_c g_c g_c^T` of the cluster-robust sandwich covariance `H^-1 M H^-1`, with
/// `g_c = sum_{i in c} J_i^T w_i W_i r_i` (body frame, rotation first). Pairs are
/// clustered by the cube their target point falls in, so residuals that err together
/// (one wall seen a little off) count as one draw, not as hundreds of independent ones.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GradientScatter {
    /// `M`, about the clusters' mean gradient (zero at an exact optimum).
    pub matrix: Matrix6<f64>,
    /// Clusters summed.
    pub clusters: usize,
}

impl GradientScatter {
    /// Of `correspondences` at `pose`, in cubes of side `cluster_m` metres.
    pub fn of(
        correspondences: &[Correspondence],
        pose: &Pose,
        kernel: &RobustKernel,
        cluster_m: f64,
    ) -> Self {
        let rotation = pose.rotation.to_rotation_matrix().into_inner();
        // Fx: a few thousand small integer keys per scan, where SipHash would dominate.
        let mut clusters: FxHashMap<[i64; 3], Vector6<f64>> = FxHashMap::default();
        for c in correspondences {
            let (r, e2) = residual(c, &rotation, pose);
            // `J^T w W r` with `J = [R [s]x, -R]`, as `linearize` sums it.
            let u = rotation.transpose() * (c.information * r * kernel.weight(e2));
            let turn = u.cross(&c.source);
            let cube = c.target.map(|v| (v / cluster_m).floor() as i64);
            *clusters
                .entry([cube.x, cube.y, cube.z])
                .or_insert_with(Vector6::zeros) +=
                Vector6::new(turn.x, turn.y, turn.z, -u.x, -u.y, -u.z);
        }
        let mean = clusters.values().sum::<Vector6<f64>>() / clusters.len().max(1) as f64;
        Self {
            matrix: clusters
                .values()
                .map(|g| (g - mean) * (g - mean).transpose())
                .sum(),
            clusters: clusters.len(),
        }
    }
}
