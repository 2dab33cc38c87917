//! The offline pipeline of kfmap (`kfmap bake`): reading a dataset (scans, poses, IMU
//! log), building poses from raw scans (odometry, loops, pose graph), the gravity pool
//! from the IMU, and baking the map file; with its configuration file `bake.toml`.
//!
//! ```
//! let config = kfmap_bake::config::BakeConfig::default();
//! assert!(config.keyframes.voxel_size > 0.0);
//! ```
#![warn(missing_docs)]

pub mod config;
pub mod dataset;
pub mod error;
pub mod files;
pub mod gravity;
pub mod mapping;
pub mod pipeline;
pub mod scan_files;
pub mod scan_range;
pub mod source;
pub mod tiling;
