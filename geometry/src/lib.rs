//! kfmap's ground floor: geometry and SE(3), point clouds and their I/O, per-point
//! covariances, KD-trees and neighbourhoods, surfels, IMU samples and gravity, and
//! registration with the motion model and tracking health built on it. Everything
//! above (the keyframe map and place search in `kfmap-map`, the pose graph and joint
//! refinement in `kfmap-graph`) builds on these types. Nothing here talks to other
//! processes (that is `kfmap-protocol`) or knows about tests.
//!
//! ```
//! use kfmap_geometry::cloud::PointCloud;
//! use kfmap_geometry::cov::{estimate_covariances, CovOptions};
//!
//! // A 20 x 20 grid on the ground plane, 10 cm apart.
//! let points: Vec<[f32; 3]> = (0..400).map(|i| [(i % 20) as f32 * 0.1, (i / 20) as f32 * 0.1, 0.0]).collect();
//! let cloud = PointCloud::from_points(points);
//! let covs = estimate_covariances(&cloud.points, &CovOptions::default());
//! // Planar neighbourhoods: the zz variance is the regularized 1e-3 m^2.
//! assert!((covs.values[210][5] - 1e-3).abs() < 1e-6);
//! ```
#![warn(missing_docs)]

/// Identifier of a keyframe: monotonic, never reused.
pub type KeyframeId = u64;

pub mod cloud;
pub mod cov;
pub mod eigen;
pub mod geometry;
pub mod gravity;
pub mod imu;
pub mod io;
pub mod motion;
pub mod neighbourhoods;
pub mod options;
pub mod percentile;
pub mod registration;
pub mod se3;
pub mod spatial;
pub mod surfel;
pub mod tracking;
pub mod trajectory_error;
