//! Registration (docs/DESIGN.md#registration): pairwise GICP / ICP on a shared pose solver.
//!
//! ```
//! use kfmap_geometry::cloud::PointCloud;
//! use kfmap_geometry::geometry::Pose;
//! use kfmap_geometry::registration::{RegistrationParams, register};
//!
//! // Three walls and a floor, and the same scene moved by 10 cm along x.
//! let mut points = Vec::new();
//! for i in 0..40 {
//!     for j in 0..40 {
//!         let (a, b) = (i as f32 * 0.1, j as f32 * 0.1);
//!         points.extend([[a, b, 0.0], [a, 0.0, b], [0.0, a, b], [a, 4.0, b]]);
//!     }
//! }
//! let target = PointCloud::from_points(points.clone());
//! let source = PointCloud::from_points(points.iter().map(|p| [p[0] - 0.1, p[1], p[2]]).collect());
//! let params = RegistrationParams { voxel_size: 0.0, ..RegistrationParams::default() };
//! let result = register(&target, &source, &Pose::identity(), &params).unwrap();
//! assert!((result.pose.translation.vector.x - 0.1).abs() < 1e-3);
//! ```

mod gicp;
mod kernel;
mod overlap;
mod solver;
#[cfg(test)]
mod tests;

pub use gicp::{
    Fitness, Metric, PreparedCloud, RegistrationError, RegistrationParams, RegistrationResult,
    align, correspondences, register, solve_pose,
};
pub use kernel::RobustKernel;
pub use overlap::overlap;
pub use solver::{
    Constraint, Correspondence, GradientScatter, Linearized, Optimizer, Step, UNOBSERVABLE_RATIO,
    cost, linearize, retract, solve_step,
};
