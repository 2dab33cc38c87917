//! A deterministic LiDAR + IMU simulator with ground truth: procedural sites, a smooth
//! looping path, a spinning multi-beam LiDAR cast exactly against the scene, and an IMU
//! consistent with the path. Same seed, same bytes.
//!
//! ```
//! use kfmap_sim::{SimConfig, Simulation};
//! let sim = Simulation::new(SimConfig { seconds: 1.0, ..SimConfig::default() }).unwrap();
//! let scan = sim.scan(0);
//! assert!(scan.cloud.len() > 10_000);
//! ```

mod bvh;
mod dataset;
mod imu;
mod lidar;
pub mod noise;
mod presets;
mod scene;
mod shapes;
mod trajectory;

pub use bvh::Bvh;
pub use dataset::{SimConfig, SimError, SimMeta, SimScan, SimSummary, Simulation, write_dataset};
pub use imu::{GRAVITY, ImuParams, gravity_in_map, imu_samples};
pub use lidar::{LidarParams, sweep};
pub use presets::{Preset, Site, build_site};
pub use scene::{Scene, SceneBuilder, Terrain};
pub use shapes::{Bounds, Ray, Shape};
pub use trajectory::{ClosedSpline, SpeedProfile, Trajectory};

#[cfg(test)]
mod tests;
