//! Core library of kfmap: geometry, point clouds, surfels, per-point covariances,
//! KD-trees, the keyframe map, registration, the pose graph, gravity, tracking, place
//! search and the baked archive; point-cloud and trajectory I/O and configuration types.
//! Nothing here talks to other processes (that is `kfmap-protocol`) or knows about tests.
//!
//! ```
//! use kfmap_shared::cloud::PointCloud;
//! use kfmap_shared::cov::{estimate_covariances, CovOptions};
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

pub mod archive;
pub mod cloud;
pub mod cov;
pub mod covis;
pub mod eigen;
pub mod geometry;
pub mod gravity;
pub mod imu;
pub mod io;
pub mod map;
pub mod motion;
pub mod neighbourhoods;
pub mod options;
pub mod percentile;
pub mod place;
pub mod pose_graph;
pub mod refine;
pub mod registration;
pub mod select;
pub mod sparse_blocks;
pub mod spatial;
pub mod surfel;
pub mod tiles;
pub mod tracking;
pub mod trajectory_error;
