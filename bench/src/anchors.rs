//! The anchors' figures beside the table's rows: small_gicp 1.0.1 and GTSAM 4.3.0
//! (PyPI) on this project's 2-core machine, by the named scripts (2026-11-24;
//! docs/BENCHMARKS.md). GTSAM runs with its own threading.

/// Covariances: small_gicp's KD-tree build plus `estimate_covariances`, re-measured
/// with the kernels below; 1 and 2 threads.
pub(super) const SMALL_GICP_COV: [f64; 2] = [72.7, 37.7];
/// GICP from raw clouds, 1 and 2 threads.
pub(super) const SMALL_GICP_REGISTER: [f64; 2] = [21.6, 16.0];
/// GICP on preprocessed clouds, 1 and 2 threads.
pub(super) const SMALL_GICP_ALIGN: [f64; 2] = [4.68, 2.42];
/// Pose-graph optimization of parking-garage.g2o.
pub(super) const GTSAM_PARKING_GARAGE_MS: f64 = 69.7;
/// small_gicp 1.0.1 KD-tree on KITTI 00 frame 1 against frame 0, one thread
/// (`small_gicp_knn.py` run before and after the criterion benches by
/// `kernels_side_by_side.sh`, the better run; 2026-11-24): 1-NN and k = 20 in scan
/// order, then in Morton order, then the tree build.
pub(super) const SMALL_GICP_KNN: [f64; 5] = [22.5, 147.2, 22.5, 148.1, 13.5];
/// small_gicp 1.0.1 voxel grid, 0.25 m, target.ply, 1 and 2 threads (`small_gicp_cov.py`).
pub(super) const SMALL_GICP_VOXEL: [f64; 2] = [2.66, 1.59];
/// The script behind the covariance and voxel-grid anchors.
pub(super) const SMALL_GICP_COV_SCRIPT: &str = "tools/anchors/small_gicp_cov.py";
/// small_gicp localizing balm_os0 scans 116-176 against the merged map of scans 0-115
/// (`small_gicp_localize.py --motion-model`, 2 threads): per scan p50, p99, RMS error.
pub(super) const SMALL_GICP_LOCALIZE: [f64; 3] = [24.0, 73.0, 0.183];

/// rosbags 0.11.9 (pure Python) on an MCAP of 40 Ouster-layout PointCloud2 clouds (252
/// MB, page cache warm), GB/s of payload, one thread: raw messages streamed, then each
/// deserialized and its x y z viewed as a numpy array; measured by the script beside
/// `kfmap bench bag-read` on the same file (kfmap 6.33 / 2.84 GB/s in that run).
pub(super) const ROSBAGS_MCAP_READ: [f64; 2] = [1.59, 0.83];
/// The script that measured [`ROSBAGS_MCAP_READ`].
pub(super) const ROSBAGS_MCAP_READ_SCRIPT: &str = "tools/anchors/rosbags_read.py";

/// KISS-ICP 1.3.0 odometry on kitti00_drive's 256 extracted scans (max range 100 m, voxel
/// 1.0 m, no deskew, 2 threads; 2026-12-03): the odometry loop's wall time (s), aligned
/// ATE (m), KITTI-style drift (%, deg/100 m) against the drive's reference.
pub(super) const KISS_ICP_KITTI00_DRIVE: [f64; 4] = [9.3, 0.545, 1.21, 0.504];
/// The scripts behind [`KISS_ICP_KITTI00_DRIVE`] (the errors by `kitti_drift.py`).
pub(super) const KISS_ICP_KITTI00_DRIVE_SCRIPT: &str =
    "tools/anchors/kiss_icp_drive.py + tools/anchors/kitti_drift.py";
