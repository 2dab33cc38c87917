//! `kfmap-ros2`: a ROS 2 localization node over a running `kfmap serve`
//! (docs/DESIGN.md#notes-ros2). It subscribes to a LiDAR's `PointCloud2` (and optionally
//! its IMU, `/initialpose`, `/tf` and `/tf_static`), localizes every cloud with the
//! tracker `kfmap localize` uses, and publishes the pose with its covariance, odometry,
//! the `map -> odom` transform, diagnostics, the served map as a latched cloud and the
//! pooled gravity. It speaks DDS through `ros2-client` (no ROS installation); it lives in
//! a crate of its own so the core build does not carry the DDS stack.

pub mod cloud;
pub mod config;
pub mod frames;
mod keep_last;
pub mod msgs;
pub mod node;
pub mod outputs;
pub mod raw;
