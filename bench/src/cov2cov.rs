//! The table's cov2cov rows: one scan's pairings against an active set of keyframes,
//! approximate, exact on a new active set, and exact on the cached submap.

use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::cov::{CovOptions, estimate_covariances};
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::read_trajectory;
use kfmap_map::map::{KeyframeMap, KeyframeMapOptions};

use super::fixtures::{data_file, keyframe_pose, read, synthetic_cloud};
use super::table::Table;

/// Measures the cov2cov rows on KITTI 00 (synthetic scans without it).
pub(super) fn measure(table: &mut Table, data: Option<&Path>) -> anyhow::Result<()> {
    table.stage("cov2cov per scan");
    let (keyframes, query, at, label) = match data_file(data, "kitti00") {
        Some(dir) => kitti_scans(&dir)?,
        None => synthetic_scans(),
    };
    let covariances = estimate_covariances(&query.points, &CovOptions::default()).values;
    for approximate in [true, false] {
        let mut map = KeyframeMap::new(KeyframeMapOptions {
            approximate_cov: approximate,
            ..KeyframeMapOptions::default()
        })?;
        for (i, (cloud, pose)) in keyframes.iter().enumerate() {
            map.insert(cloud.clone(), *pose, i as f64)?;
        }
        if !approximate {
            // A new active set: the merged submap, its tree and covariances, built once.
            let one = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
            let started = Instant::now();
            one.install(|| -> anyhow::Result<()> {
                let active = map.activate(&at)?;
                active.cov2cov(&query, &at, 1.0, Some(&covariances))?;
                Ok(())
            })?;
            let ms = started.elapsed().as_secs_f64() * 1e3;
            table.push(
                "cov2cov per scan, exact, new active set",
                &label,
                1,
                ms,
                "ms",
            );
        }
        let active = map.activate(&at)?;
        let ms = table.time_ms(1, || active.cov2cov(&query, &at, 1.0, Some(&covariances)))?;
        let name = if approximate {
            "cov2cov per scan, approximate"
        } else {
            "cov2cov per scan, exact, cached submap"
        };
        table.push(name, &label, 1, ms, "ms");
    }
    Ok(())
}

/// Keyframes (cloud, pose), the query scan, its pose and the rows' data label.
type Scans = (Vec<(PointCloud, Pose)>, PointCloud, Pose, String);

/// KITTI 00 frames 0, 2 and 4 as keyframes; frame 3 thinned to about 10 000 points as
/// the query.
fn kitti_scans(dir: &Path) -> anyhow::Result<Scans> {
    let poses = read_trajectory(&dir.join("poses_velo_kitti.txt"))?.poses;
    let frames = [0, 2, 4]
        .iter()
        .map(|i| Ok((read(&dir.join(format!("{i:06}.bin")))?, poses[*i])))
        .collect::<anyhow::Result<Vec<_>>>()?;
    // The smallest voxel giving at most ~10 000 points, as the criterion bench.
    let frame = read(&dir.join("000003.bin"))?;
    let query = (1..40)
        .map(|k| frame.voxel_downsample(0.05 * k as f64))
        .find(|c| c.as_ref().map_or(true, |c| c.len() <= 10_500))
        .context("no voxel size thins KITTI 00 frame 3 to 10 000 points")??;
    let label = format!(
        "KITTI 00: frames 0, 2, 4 as keyframes, frame 3 ({} points)",
        query.len()
    );
    Ok((frames, query, poses[3], label))
}

/// Three synthetic keyframes and a synthetic 10 000-point query scan.
fn synthetic_scans() -> Scans {
    let frames = (0..3)
        .map(|i| (synthetic_cloud(i, 120_000), keyframe_pose(2 * i as usize)))
        .collect();
    let query = synthetic_cloud(99, 10_000);
    let label = format!("synthetic: 3 keyframes, scan of {} points", query.len());
    (frames, query, keyframe_pose(3), label)
}
