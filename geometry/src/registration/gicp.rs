//! Pairwise registration in the small_gicp style: voxel downsampling, per-point
//! covariances, nearest-neighbour correspondences within a distance, and the pose
//! solver iterated until the update is small. GICP by default; point-to-point and
//! point-to-plane ICP share everything but the information matrix.

use std::sync::OnceLock;

use nalgebra::{Matrix3, Matrix6, SymmetricEigen, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::RobustKernel;
use super::solver::{
    Constraint, Correspondence, GradientScatter, Linearized, Optimizer, cost, linearize, retract,
    solve_step,
};
use crate::cloud::PointCloud;
use crate::cov::{CovOptions, estimate_covariances};
use crate::geometry::{PackedSym3, Pose, to_vec3, unpack_sym3};
use crate::options::{InvalidOption, ensure};
use crate::spatial::{PointTree, TreeError, build_tree};

/// Which residual metric pairs are weighted by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Metric {
    /// GICP: `W = (C_t + R C_s R^T)^-1`.
    Gicp,
    /// Point-to-point ICP: `W = I`.
    PointToPoint,
    /// Point-to-plane ICP: `W = n n^T` (target normal), plus a small isotropic term.
    PointToPlane,
}

/// Registration settings (defaults as small_gicp's `align`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct RegistrationParams {
    /// Residual metric.
    pub metric: Metric,
    /// Voxel grid applied to both clouds first, metres; 0 keeps every point.
    pub voxel_size: f64,
    /// Neighbours per point for its covariance.
    pub covariance_neighbours: usize,
    /// Neighbours must be closer than this, metres. small_gicp has no limit; on KITTI
    /// 00 at 0.25 m voxels a 1 m limit left 14.2 cm where small_gicp's 14.1 cm.
    pub covariance_max_distance: f64,
    /// Pairs farther apart than this are not correspondences, metres.
    pub max_correspondence_distance: f64,
    /// Iterations at most.
    pub max_iterations: usize,
    /// Converged when the rotation update is below this, radians...
    pub rotation_eps: f64,
    /// ...and the translation update below this, metres.
    pub translation_eps: f64,
    /// Down-weighting of large residuals.
    pub kernel: RobustKernel,
    /// Step method.
    pub optimizer: Optimizer,
    /// A Hessian block whose min/max eigenvalue ratio is below this is degenerate.
    pub degeneracy_ratio: f64,
    /// When set, the result carries the gradient's scatter over cubes of this side,
    /// metres ([`RegistrationResult::gradient_scatter`], for the sandwich covariance).
    /// Asked by the localizer for the registration it reports; not a config setting.
    #[serde(skip)]
    pub gradient_cluster_m: Option<f64>,
}

impl Default for RegistrationParams {
    fn default() -> Self {
        Self {
            metric: Metric::Gicp,
            voxel_size: 0.25,
            covariance_neighbours: 10,
            covariance_max_distance: 1000.0,
            max_correspondence_distance: 1.0,
            max_iterations: 20,
            rotation_eps: 0.1f64.to_radians(),
            translation_eps: 1e-3,
            kernel: RobustKernel::None,
            optimizer: Optimizer::GaussNewton,
            degeneracy_ratio: 1e-2,
            gradient_cluster_m: None,
        }
    }
}

impl RegistrationParams {
    /// Checks every value; the error names the option.
    pub fn validate(&self) -> Result<(), InvalidOption> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        ensure(
            self.voxel_size.is_finite() && self.voxel_size >= 0.0,
            "voxel-size",
            self.voxel_size,
            "a finite size >= 0 m",
        )?;
        ensure(
            self.covariance_neighbours >= 3,
            "covariance-neighbours",
            self.covariance_neighbours,
            "at least 3",
        )?;
        ensure(
            positive(self.covariance_max_distance),
            "covariance-max-distance",
            self.covariance_max_distance,
            "a finite distance > 0 m",
        )?;
        ensure(
            positive(self.max_correspondence_distance),
            "max-correspondence-distance",
            self.max_correspondence_distance,
            "a finite distance > 0 m",
        )?;
        ensure(
            self.max_iterations >= 1,
            "max-iterations",
            self.max_iterations,
            "at least 1",
        )?;
        ensure(
            positive(self.rotation_eps),
            "rotation-eps",
            self.rotation_eps,
            "> 0 rad",
        )?;
        ensure(
            positive(self.translation_eps),
            "translation-eps",
            self.translation_eps,
            "> 0 m",
        )?;
        if let Some(delta) = self.kernel.delta() {
            ensure(positive(delta), "kernel.delta", delta, "> 0")?;
        }
        ensure(
            (0.0..1.0).contains(&self.degeneracy_ratio),
            "degeneracy-ratio",
            self.degeneracy_ratio,
            "0 to 1",
        )
    }

    /// The covariance options registration uses.
    pub fn covariance(&self) -> CovOptions {
        CovOptions {
            k_correspondences_for_cov: self.covariance_neighbours,
            min_correspondences_for_cov: self.covariance_neighbours.min(5),
            max_distance_for_cov: self.covariance_max_distance,
            ..CovOptions::default()
        }
    }
}

/// Why registration could not run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RegistrationError {
    /// A parameter is out of range.
    #[error(transparent)]
    Invalid(#[from] InvalidOption),
    /// A cloud is empty (after downsampling) or holds a non-finite point.
    #[error("{which} cloud: {source}")]
    Cloud {
        /// "source" or "target".
        which: &'static str,
        /// What is wrong.
        source: TreeError,
    },
    /// The voxel grid refused the cloud (e.g. a grid too fine for its extent).
    #[error("{which} cloud: {message}")]
    Downsample {
        /// "source" or "target".
        which: &'static str,
        /// What the voxel grid said.
        message: String,
    },
    /// A scan's per-point times could not deskew it.
    #[error("scan: {0}")]
    Deskew(#[from] crate::cloud::DeskewError),
    /// The IMU log cannot drive the odometry's motion model.
    #[error("IMU: {0}")]
    Imu(#[from] crate::motion::GyroError),
    /// No source point has a target point within the correspondence distance.
    #[error(
        "no correspondences within {max_distance} m at the initial pose; the guess is too far off or the clouds do not overlap"
    )]
    NoCorrespondences {
        /// The distance used.
        max_distance: f64,
    },
}

/// A cloud ready for registration: downsampled points, their covariances, a tree.
pub struct PreparedCloud {
    /// Points (after the voxel grid).
    pub points: Vec<[f32; 3]>,
    /// Per-point covariances.
    pub covariances: Vec<PackedSym3>,
    /// KD-tree over `points`.
    pub tree: PointTree,
    normals: OnceLock<Vec<Vector3<f64>>>,
}

impl PreparedCloud {
    /// Downsamples `cloud` (params' voxel size), estimates covariances, builds the tree.
    pub fn new(
        cloud: &PointCloud,
        params: &RegistrationParams,
        which: &'static str,
    ) -> Result<Self, RegistrationError> {
        let points = if params.voxel_size > 0.0 {
            cloud
                .voxel_downsample(params.voxel_size)
                .map_err(|e| RegistrationError::Downsample {
                    which,
                    message: e.to_string(),
                })?
                .points
        } else {
            cloud.points.clone()
        };
        Self::from_points(points, params, which)
    }

    /// As [`PreparedCloud::new`] on points already downsampled.
    pub fn from_points(
        points: Vec<[f32; 3]>,
        params: &RegistrationParams,
        which: &'static str,
    ) -> Result<Self, RegistrationError> {
        let tree =
            build_tree(&points).map_err(|source| RegistrationError::Cloud { which, source })?;
        let covariances = estimate_covariances(&points, &params.covariance()).values;
        Ok(Self {
            points,
            covariances,
            tree,
            normals: OnceLock::new(),
        })
    }

    /// A cloud from points and their covariances, both already computed (e.g. prepared
    /// clouds merged, their covariances moved with their points): builds only the tree.
    ///
    /// # Panics
    ///
    /// When `covariances` does not have one entry per point.
    pub fn from_parts(
        points: Vec<[f32; 3]>,
        covariances: Vec<PackedSym3>,
        which: &'static str,
    ) -> Result<Self, RegistrationError> {
        assert_eq!(points.len(), covariances.len(), "one covariance per point");
        let tree =
            build_tree(&points).map_err(|source| RegistrationError::Cloud { which, source })?;
        Ok(Self {
            points,
            covariances,
            tree,
            normals: OnceLock::new(),
        })
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True without points (never, once built).
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Unit normals: the covariances' least-spread directions (computed once).
    pub fn normals(&self) -> &[Vector3<f64>] {
        self.normals.get_or_init(|| {
            self.covariances
                .par_iter()
                .map(|c| {
                    let eig = SymmetricEigen::new(unpack_sym3(c));
                    eig.eigenvectors.column(eig.eigenvalues.imin()).into_owned()
                })
                .collect()
        })
    }
}

/// How much of the source found a partner, and how close.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Fitness {
    /// Source points with a correspondence, over all source points.
    pub inlier_ratio: f64,
    /// RMS Euclidean distance of the correspondences, metres.
    pub rmse: f64,
}

/// The outcome of a registration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegistrationResult {
    /// `T_target_source`.
    pub pose: Pose,
    /// The 6x6 Hessian at the solution (rotation first): the pose's information.
    pub hessian: Matrix6<f64>,
    /// Overlap and residual size at the solution.
    pub fitness: Fitness,
    /// Iterations run.
    pub iterations: usize,
    /// True when the last update was below both thresholds.
    pub converged: bool,
    /// How well the scene constrains rotation and translation.
    pub constraint: Constraint,
    /// Directions of the pose update (rotation and translation) the last Hessian does
    /// not constrain at all (0 to 6, see [`solve_step`]): the last step left the pose
    /// at its guess along them, e.g. 1 along a corridor seen as infinite.
    pub unobservable: usize,
    /// True when a block is below the degeneracy ratio or a direction is unobservable:
    /// the pose is not trustworthy along some direction (e.g. a featureless corridor).
    pub degenerate: bool,
    /// The weighted cost `sum w r^T W r` of the last linearization (the one `hessian`
    /// comes from), dimensionless (residuals whitened by the information matrices).
    pub cost: f64,
    /// Correspondences of the last linearization.
    pub pairs: usize,
    /// The last pairs' gradient scatter over spatial clusters at the solution, when
    /// [`RegistrationParams::gradient_cluster_m`] asked for it.
    pub gradient_scatter: Option<GradientScatter>,
}

/// The correspondences of `source` moved by `pose` (source order).
pub fn correspondences(
    target: &PreparedCloud,
    source: &PreparedCloud,
    pose: &Pose,
    params: &RegistrationParams,
) -> Vec<Correspondence> {
    let max_sq = (params.max_correspondence_distance * params.max_correspondence_distance) as f32;
    let rotation = pose.rotation.to_rotation_matrix().into_inner();
    let normals = (params.metric == Metric::PointToPlane).then(|| target.normals());
    let tree = target.tree.view();
    source
        .points
        .par_iter()
        .enumerate()
        .filter_map(|(i, p)| {
            let s = to_vec3(p);
            let moved = rotation * s + pose.translation.vector;
            let query = [moved.x as f32, moved.y as f32, moved.z as f32];
            let (j, _) = tree.nearest_one_within(&query, max_sq)?;
            let j = j as usize;
            let information = match params.metric {
                Metric::Gicp => {
                    let combined = unpack_sym3(&target.covariances[j])
                        + rotation * unpack_sym3(&source.covariances[i]) * rotation.transpose();
                    combined.try_inverse()?
                }
                Metric::PointToPoint => Matrix3::identity(),
                Metric::PointToPlane => {
                    let n = normals.expect("computed above")[j];
                    n * n.transpose() + Matrix3::identity() * 1e-3
                }
            };
            Some(Correspondence {
                source: s,
                target: to_vec3(&target.points[j]),
                information,
            })
        })
        .collect()
}

/// Registers `source` onto `target` from `initial` (`T_target_source`).
pub fn align(
    target: &PreparedCloud,
    source: &PreparedCloud,
    initial: &Pose,
    params: &RegistrationParams,
) -> Result<RegistrationResult, RegistrationError> {
    solve_pose(initial, params, source.len(), |pose| {
        Ok(correspondences(target, source, pose, params))
    })
}

/// The registration loop over any source of correspondences: `pairs_at(pose)` gives
/// the pairings at a pose (e.g. a local tree, or a map server's cov2cov answer), and
/// the pose is iterated from `initial` until the update is small. `source_len` is the
/// number of source points, for the inlier ratio.
pub fn solve_pose<E: From<RegistrationError>>(
    initial: &Pose,
    params: &RegistrationParams,
    source_len: usize,
    mut pairs_at: impl FnMut(&Pose) -> Result<Vec<Correspondence>, E>,
) -> Result<RegistrationResult, E> {
    params.validate().map_err(RegistrationError::from)?;
    let no_pairs = || RegistrationError::NoCorrespondences {
        max_distance: params.max_correspondence_distance,
    };
    let mut pose = *initial;
    let mut lambda = 1e-4;
    let mut converged = false;
    let mut iterations = 0;
    let mut unobservable = 0;
    // The last linearization and the pose it was taken at: its Hessian and pairs are
    // the result's (as small_gicp), so no extra correspondence search after the loop.
    let mut last: Option<(Vec<Correspondence>, Linearized, Pose)> = None;
    while iterations < params.max_iterations && !converged {
        iterations += 1;
        let pairs = pairs_at(&pose)?;
        if pairs.is_empty() {
            return Err(no_pairs().into());
        }
        let lin = linearize(&pairs, &pose, &params.kernel);
        let step = match params.optimizer {
            Optimizer::GaussNewton => solve_step(&lin, 0.0).inspect(|s| {
                unobservable = s.unobservable;
            }),
            Optimizer::LevenbergMarquardt => {
                // Damp until the cost over these correspondences drops.
                let mut accepted = None;
                for _ in 0..10 {
                    // `unobservable` is a property of H alone, whatever the damping.
                    if let Some(step) = solve_step(&lin, lambda).inspect(|s| {
                        unobservable = s.unobservable;
                    }) && cost(&pairs, &retract(&pose, &step.delta), &params.kernel) <= lin.cost
                    {
                        lambda = (lambda / 10.0).max(1e-10);
                        accepted = Some(step);
                        break;
                    }
                    lambda *= 10.0;
                }
                accepted
            }
        };
        last = Some((pairs, lin, pose));
        let Some(step) = step.map(|s| s.delta) else {
            break;
        };
        pose = retract(&pose, &step);
        let rotation_step = Vector3::new(step[0], step[1], step[2]).norm();
        let translation_step = Vector3::new(step[3], step[4], step[5]).norm();
        converged =
            rotation_step < params.rotation_eps && translation_step < params.translation_eps;
    }
    let (pairs, lin, linearized_at) = last.expect("max-iterations >= 1 was validated");
    let rotation = linearized_at.rotation.to_rotation_matrix().into_inner();
    let mean_sq = pairs
        .iter()
        .map(|c| {
            (c.target - (rotation * c.source + linearized_at.translation.vector)).norm_squared()
        })
        .sum::<f64>()
        / pairs.len() as f64;
    let constraint = Constraint::of(&lin.hessian);
    let gradient_scatter = params
        .gradient_cluster_m
        .map(|side| GradientScatter::of(&pairs, &pose, &params.kernel, side));
    Ok(RegistrationResult {
        pose,
        hessian: lin.hessian,
        fitness: Fitness {
            inlier_ratio: pairs.len() as f64 / source_len.max(1) as f64,
            rmse: mean_sq.sqrt(),
        },
        iterations,
        converged,
        constraint,
        unobservable,
        degenerate: constraint.rotation_ratio < params.degeneracy_ratio
            || constraint.translation_ratio < params.degeneracy_ratio
            || unobservable > 0,
        cost: lin.cost,
        pairs: pairs.len(),
        gradient_scatter,
    })
}

/// Prepares both clouds (in parallel) and aligns them.
pub fn register(
    target: &PointCloud,
    source: &PointCloud,
    initial: &Pose,
    params: &RegistrationParams,
) -> Result<RegistrationResult, RegistrationError> {
    params.validate()?;
    let (t, s) = rayon::join(
        || PreparedCloud::new(target, params, "target"),
        || PreparedCloud::new(source, params, "source"),
    );
    align(&t?, &s?, initial, params)
}
