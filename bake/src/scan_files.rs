//! A dataset folder's scan files, and one scan read with invalid returns dropped: what
//! both a folder [`crate::source::Source`] and the pose matching of [`crate::dataset`]
//! need, so it depends on neither.

use std::path::{Path, PathBuf};

use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::io::{IoError, ReadOptions, read_cloud};

use crate::config::BakeConfig;
use crate::error::BakeError;

/// Scan file extensions a dataset may hold.
const SCAN_EXTENSIONS: [&str; 3] = ["pcd", "ply", "bin"];

/// Scan files of a dataset, sorted by name: `DIR/scans/` if it exists, else `DIR`.
pub fn find_scans(dataset: &Path) -> Result<Vec<PathBuf>, BakeError> {
    let dir = if dataset.join("scans").is_dir() {
        dataset.join("scans")
    } else {
        dataset.to_path_buf()
    };
    let entries = std::fs::read_dir(&dir).map_err(|e| IoError::os(&dir, e))?;
    let mut scans: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| SCAN_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    scans.sort();
    if scans.is_empty() {
        return Err(BakeError::NoScans(dataset.to_path_buf()));
    }
    Ok(scans)
}

/// Reads one scan and drops invalid returns (the bake configuration's filter).
pub fn load_raw_scan(path: &Path, config: &BakeConfig) -> Result<PointCloud, BakeError> {
    let sidecar = path.with_extension("bin.layout").is_file();
    let options = ReadOptions {
        bin_layout: (!sidecar).then_some(config.input.bin_layout),
        filter: config.filter,
    };
    let mut cloud = read_cloud(path, &options)?.cloud;
    cloud.raise_elevation(config.input.vertical_angle_offset_deg);
    Ok(cloud)
}
