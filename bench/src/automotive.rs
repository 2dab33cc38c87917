//! The table's automotive row: kitti00_drive (a car on Karlsruhe streets, raw HDL-64E key
//! frames about 1.8 m apart, RTK reference) built from its scans by `kfmap bake
//! --build-poses --deskew azimuth` with the sensor's vertical-angle offset (bake.toml's
//! `[input] vertical-angle-offset-deg = 0.205`), its aligned ATE and KITTI-style drift beside
//! KISS-ICP's on the same scans. The scans are not in the shared data (its
//! `extract.sh` writes them from a public repository): without them the row is skipped.

use std::path::Path;
use std::time::Instant;

use kfmap_bake::config::BakeConfig;
use kfmap_bake::dataset::find_scans;
use kfmap_bake::pipeline::{BakeInput, BakeOutput, bake, scan_check_sidecar};
use kfmap_geometry::io::read_trajectory;
use kfmap_geometry::motion::DeskewMode;
use kfmap_geometry::trajectory_error::{absolute_trajectory_error, kitti_drift};

use super::anchors::{KISS_ICP_KITTI00_DRIVE, KISS_ICP_KITTI00_DRIVE_SCRIPT};
use super::table::{Table, anchor};

/// Scans of the drive once extracted.
const DRIVE_SCANS: usize = 256;
/// The vertical-angle correction of KITTI's HDL-64E, degrees (KISS-ICP's for KITTI).
const KITTI_HDL64_VERTICAL_OFFSET_DEG: f64 = 0.205;

/// Measures the automotive rows (skipped without the extracted scans).
pub(super) fn measure(table: &mut Table, data: Option<&Path>, dir: &Path) -> anyhow::Result<()> {
    let drive = data.map(|d| d.join("kitti00_drive"));
    let extracted = drive
        .as_deref()
        .filter(|d| find_scans(d).is_ok_and(|s| s.len() == DRIVE_SCANS));
    let Some(drive) = extracted else {
        table.skip(
            "automotive drive: needs kitti00_drive's 256 scans (its extract.sh writes them \
             from the repository its PROVENANCE entry names)",
        );
        return Ok(());
    };
    table.stage("automotive drive (bake --build-poses)");
    let map = dir.join(format!("kfmap-bench-drive-{}.kfmap", std::process::id()));
    let built = dir.join(format!("kfmap-bench-drive-{}.tum", std::process::id()));
    let input = BakeInput {
        build_poses: true,
        ..BakeInput::dataset(drive)
    };
    let mut config = BakeConfig::default();
    // The scans are raw and carry no per-point times: timed by azimuth (documented in
    // `kfmap bake --help`), as a user bakes them; and KITTI's HDL-64E beams sit 0.205 deg
    // below their nominal angles (`[input] vertical-angle-offset-deg`, config/bake.toml).
    config.build.odometry.deskew = DeskewMode::Azimuth;
    config.input.vertical_angle_offset_deg = KITTI_HDL64_VERTICAL_OFFSET_DEG;
    let output = BakeOutput {
        trajectory: Some(built.clone()),
        ..BakeOutput::map(&map)
    };
    let started = Instant::now();
    let baked = bake(&input, &config, &output, |_| {});
    let seconds = started.elapsed().as_secs_f64();
    let _ = std::fs::remove_file(&map);
    let estimate = read_trajectory(&built).map(|t| t.poses);
    let _ = std::fs::remove_file(&built);
    let _ = std::fs::remove_file(scan_check_sidecar(&built));
    baked?;
    let estimate = estimate?;
    let reference = read_trajectory(&drive.join("poses.txt"))?.poses;
    anyhow::ensure!(
        estimate.len() == reference.len(),
        "{} built poses for {} reference poses",
        estimate.len(),
        reference.len()
    );
    let drift = kitti_drift(&estimate, &reference)
        .ok_or_else(|| anyhow::anyhow!("kitti00_drive's reference path is under 50 m"))?;
    let label = "kitti00_drive: 256 raw HDL-64E key frames, 476 m, RTK reference";
    let threads = rayon::current_num_threads();
    let rows = [
        (
            "automotive drive: bake --build-poses wall time",
            seconds,
            "s",
        ),
        (
            "automotive drive: aligned ATE",
            absolute_trajectory_error(&estimate, &reference),
            "m",
        ),
        (
            "automotive drive: drift, translation (50-400 m)",
            drift.translation_percent,
            "%",
        ),
        (
            "automotive drive: drift, rotation (50-400 m)",
            drift.rotation_deg_per_100m,
            "deg/100 m",
        ),
    ];
    for ((name, value, unit), anchor_value) in rows.into_iter().zip(KISS_ICP_KITTI00_DRIVE) {
        table.push(name, label, threads, value, unit);
        table.anchored(anchor(
            "KISS-ICP 1.3.0 (voxel 1.0 m)",
            anchor_value,
            KISS_ICP_KITTI00_DRIVE_SCRIPT,
        ));
    }
    Ok(())
}
