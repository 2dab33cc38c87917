//! Reading a dataset: the pose of every scan from its pose file (its scan files and
//! one scan with invalid returns dropped: [`crate::scan_files`], re-exported here).

use std::ops::Range;
use std::path::{Path, PathBuf};

use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::read_trajectory;

use crate::error::BakeError;
use crate::files::{POSE_FILES, find_in};
use crate::source::ScanList;
// Where they were first: callers read scans through `dataset`.
pub use crate::scan_files::{find_scans, load_raw_scan};

/// Every scan's pose and time from the dataset's pose file (the first of
/// [`POSE_FILES`]), or `None` when it has none.
pub fn dataset_poses(dataset: &Path, scans: &[PathBuf]) -> Result<Option<ScanPoses>, BakeError> {
    let scans = ScanList::files(scans.to_vec());
    find_in(dataset, &POSE_FILES)
        .map(|path| scan_poses(&path, &scans))
        .transpose()
}

/// Every scan's pose and time (the pose index when the file has no timestamps).
#[derive(Debug, Clone)]
pub struct ScanPoses {
    /// `T_map_scan` of each scan.
    pub poses: Vec<Pose>,
    /// Each scan's time, seconds.
    pub stamps: Vec<f64>,
    /// True when the stamps come from the pose file.
    pub stamped: bool,
}

impl ScanPoses {
    /// The poses and times of scans `range` only.
    pub fn select(mut self, range: Range<usize>) -> Self {
        self.poses.truncate(range.end);
        self.stamps.truncate(range.end);
        self.poses.drain(..range.start);
        self.stamps.drain(..range.start);
        self
    }
}

/// The pose of every scan: by frame number when every scan is named by one (KITTI
/// `000123.bin`), else one pose per scan in order. Scans from a bag keep their header
/// stamps (the clock their IMU topic shares); a stamped pose file far from them is
/// reported.
pub fn scan_poses(path: &Path, scans: &ScanList) -> Result<ScanPoses, BakeError> {
    let path = path.to_path_buf();
    let trajectory = read_trajectory(&path)?;
    let count_error = || BakeError::PoseCount {
        poses: path.clone(),
        count: trajectory.poses.len(),
        scans: scans.len(),
    };
    let indices: Vec<usize> = match scans.frame_numbers() {
        Some(f) if trajectory.poses.len() != scans.len() => f,
        _ if trajectory.poses.len() == scans.len() => (0..scans.len()).collect(),
        _ => return Err(count_error()),
    };
    if indices.iter().any(|&i| i >= trajectory.poses.len()) {
        return Err(count_error());
    }
    let poses = indices.iter().map(|&i| trajectory.poses[i]).collect();
    let file_stamps: Option<Vec<f64>> = trajectory
        .stamps
        .as_ref()
        .map(|s| indices.iter().map(|&i| s[i]).collect());
    if let (Some(header), Some(file)) = (scans.stamps(), &file_stamps) {
        let (gap, at) = header
            .iter()
            .zip(file)
            .map(|(h, f)| (h - f).abs())
            .enumerate()
            .fold((0.0f64, 0), |w, (i, g)| if g > w.0 { (g, i) } else { w });
        if gap > STAMP_MISMATCH_WARN_S {
            tracing::warn!(
                "{}: pose {at} is stamped {gap:.3} s from its cloud's header stamp; the poses are matched to the clouds in order and the header stamps are used",
                path.display()
            );
        }
    }
    let stamped = file_stamps.is_some() || scans.stamps().is_some();
    let stamps = match (scans.stamps(), file_stamps) {
        (Some(header), _) => header.to_vec(),
        (None, Some(file)) => file,
        (None, None) => indices.iter().map(|&i| i as f64).collect(),
    };
    Ok(ScanPoses {
        poses,
        stamps,
        stamped,
    })
}

/// A stamped pose file this far from its clouds' header stamps is reported (seconds).
const STAMP_MISMATCH_WARN_S: f64 = 0.01;
