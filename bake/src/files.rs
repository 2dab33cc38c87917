//! Which files a dataset folder's poses and IMU log are looked for in (no dependency on
//! the rest of the crate: the dataset, its sources and gravity all look them up).

use std::path::{Path, PathBuf};

/// IMU logs looked for in a dataset folder, in order.
pub const IMU_FILES: [&str; 2] = ["imu.csv", "imu.txt"];
/// Pose files looked for in a dataset folder, in order.
pub const POSE_FILES: [&str; 4] = [
    "poses_gt.txt",
    "poses.txt",
    "traj.txt",
    "poses_velo_kitti.txt",
];

/// The first of `names` present in `dir`.
pub fn find_in(dir: &Path, names: &[&str]) -> Option<PathBuf> {
    names.iter().map(|n| dir.join(n)).find(|p| p.is_file())
}
