//! What several benchmarks measure on: synthetic scans, keyframe poses and maps, and the
//! files of the shared data when they are there.

use std::path::{Path, PathBuf};
use std::time::Instant;

use indicatif::ProgressBar;
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::{ReadOptions, read_cloud};
use kfmap_map::archive::MapWriter;
use kfmap_map::covis::CovisSnapshot;
use kfmap_map::map::{Keyframe, KeyframeMapOptions};
use nalgebra::Vector3;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

/// A synthetic scan: ground, two walls and scattered posts around the keyframe.
pub(super) fn synthetic_cloud(seed: u64, n: usize) -> PointCloud {
    let mut rng = SmallRng::seed_from_u64(seed);
    let points = (0..n)
        .map(|i| match i % 10 {
            0..4 => [
                rng.random_range(-30.0..30.0),
                rng.random_range(-30.0..30.0),
                rng.random_range(-0.02..0.02),
            ],
            4..7 => [
                rng.random_range(-30.0..30.0),
                if i % 2 == 0 { -8.0 } else { 9.0 },
                rng.random_range(0.0..4.0),
            ],
            _ => {
                let post = rng.random_range(0..40) as f32;
                [
                    post * 1.5 - 30.0,
                    (post * 7.3) % 16.0 - 8.0 + rng.random_range(-0.1..0.1),
                    rng.random_range(0.0..3.0),
                ]
            }
        })
        .collect();
    PointCloud::from_points(points)
}

/// The pose of synthetic keyframe `i`: 2 m apart along x, turning a little.
pub(super) fn keyframe_pose(i: usize) -> Pose {
    Pose::new(
        Vector3::new(2.0 * i as f64, 0.0, 0.0),
        Vector3::new(0.0, 0.0, 0.05 * (i % 7) as f64),
    )
}

/// Builds and writes `count` synthetic keyframes; returns seconds spent (generation of
/// the raw points excluded).
pub(super) fn bake_synthetic(
    path: &Path,
    count: usize,
    points: usize,
    bar: &ProgressBar,
) -> anyhow::Result<f64> {
    bake_synthetic_at(path, count, points, keyframe_pose, bar)
}

/// As [`bake_synthetic`], keyframe `i` at `pose_of(i)`.
pub(super) fn bake_synthetic_at(
    path: &Path,
    count: usize,
    points: usize,
    pose_of: impl Fn(usize) -> Pose + Sync,
    bar: &ProgressBar,
) -> anyhow::Result<f64> {
    let options = KeyframeMapOptions::default();
    let mut writer = MapWriter::create(path, &options)?;
    let seconds = build_synthetic(count, points, pose_of, bar, |keyframes| {
        Ok(writer.write_keyframes(keyframes)?)
    })?;
    let started = Instant::now();
    writer.finish(count as u64, &CovisSnapshot::default(), &[])?;
    Ok(seconds + started.elapsed().as_secs_f64())
}

/// Builds `count` synthetic keyframes of `points` points, keyframe `i` at `pose_of(i)`,
/// a chunk at a time handed to `write`; returns seconds spent building and writing
/// (generation of the raw points excluded).
pub(super) fn build_synthetic(
    count: usize,
    points: usize,
    pose_of: impl Fn(usize) -> Pose + Sync,
    bar: &ProgressBar,
    mut write: impl FnMut(&[Keyframe]) -> anyhow::Result<()> + Send,
) -> anyhow::Result<f64> {
    let options = KeyframeMapOptions::default();
    let chunk = 2 * rayon::current_num_threads();
    let mut seconds = 0.0;
    let build = |start: usize, clouds: Vec<PointCloud>| -> anyhow::Result<Vec<Keyframe>> {
        Ok(clouds
            .into_par_iter()
            .enumerate()
            .map(|(j, c)| {
                let i = start + j;
                Keyframe::build(i as u64, pose_of(i), i as f64, c, &options.covariance)
            })
            .collect::<Result<_, _>>()?)
    };
    let mut write = |keyframes: &[Keyframe]| -> anyhow::Result<()> {
        write(keyframes)?;
        bar.inc(keyframes.len() as u64);
        Ok(())
    };
    // A chunk is written while the next one is built, as `kfmap bake` does.
    let mut built: Option<Vec<Keyframe>> = None;
    for start in (0..count).step_by(chunk) {
        let clouds: Vec<PointCloud> = (start..(start + chunk).min(count))
            .into_par_iter()
            .map(|i| synthetic_cloud(i as u64, points))
            .collect();
        let started = Instant::now();
        let (next, wrote) = rayon::join(
            || build(start, clouds),
            || built.take().map_or(Ok(()), |k| write(&k)),
        );
        wrote?;
        built = Some(next?);
        seconds += started.elapsed().as_secs_f64();
    }
    let started = Instant::now();
    if let Some(keyframes) = built {
        write(&keyframes)?;
    }
    Ok(seconds + started.elapsed().as_secs_f64())
}

/// Bakes the small synthetic map the server benchmarks (ipc, soak) serve: 12 keyframes
/// x 40 000 points.
pub(super) fn bake_served_map(path: &Path) -> anyhow::Result<()> {
    bake_synthetic(path, 12, 40_000, &ProgressBar::hidden()).map(|_| ())
}

/// The real file `relative` of the shared data, when it is there.
pub(super) fn data_file(data: Option<&Path>, relative: &str) -> Option<PathBuf> {
    data.map(|d| d.join(relative)).filter(|p| p.exists())
}

/// A point cloud file of the shared data.
pub(super) fn read(path: &Path) -> anyhow::Result<PointCloud> {
    Ok(read_cloud(path, &ReadOptions::default())?.cloud)
}
