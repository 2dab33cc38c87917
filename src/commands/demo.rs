//! `kfmap demo`: the main job on built-in defaults. For now it loads a real scan
//! (or builds a synthetic one), filters it, downsamples it, estimates per-point
//! covariances and prints statistics and timings. Later stages (simulate, bake, serve,
//! localize) join it as they land.

use std::path::PathBuf;
use std::time::Instant;

use kfmap_service::config::BakeConfig;
use kfmap_shared::cloud::PointCloud;
use kfmap_shared::datasets::shared_data_dir;
use kfmap_shared::io::{ReadOptions, read_cloud};
use kfmap_shared::summary::summarize;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::report::print_summary;

/// Run the kfmap pipeline end to end on built-in defaults.
///
/// Uses ../shared/data/kitti00/000000.bin (a real Velodyne HDL-64E scan) when the
/// shared data folder is beside the checkout (or named by $KFMAP_DATA_DIR), else a
/// built-in synthetic scan of ground, walls and poles.
///
/// Example: cargo run --release -- demo
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// Use this cloud file instead of the default scan.
    #[arg(long)]
    scan: Option<PathBuf>,
    /// Use the built-in synthetic scan even when real data is present.
    #[arg(long, conflicts_with = "scan")]
    synthetic: bool,
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let config = BakeConfig::default();
    let default_scan = || {
        shared_data_dir()
            .map(|d| d.join("kitti00/000000.bin"))
            .filter(|p| p.is_file())
    };
    let scan_path = if args.synthetic {
        None
    } else {
        args.scan.or_else(default_scan)
    };

    let started = Instant::now();
    let (label, cloud) = match &scan_path {
        Some(path) => {
            let options = ReadOptions {
                bin_layout: None,
                filter: config.filter,
            };
            let loaded = read_cloud(path, &options)?;
            let dropped = loaded.filter.map_or(0, |f| f.dropped());
            let label = format!(
                "{} ({}, {} invalid returns dropped)",
                path.display(),
                loaded.format,
                dropped
            );
            (label, loaded.cloud)
        }
        None => (
            "built-in synthetic scan (ground, walls, poles; seed 7)".to_string(),
            synthetic_scan(7),
        ),
    };
    println!("kfmap demo: {label}");
    println!(
        "  loaded in {:.1} ms",
        started.elapsed().as_secs_f64() * 1e3
    );
    cloud.validate()?;

    let started = Instant::now();
    let downsampled = cloud.voxel_downsample(0.25)?;
    println!(
        "  voxel 0.25 m:     {} -> {} points in {:.1} ms",
        cloud.len(),
        downsampled.len(),
        started.elapsed().as_secs_f64() * 1e3
    );
    println!(
        "full-resolution scan, covariances k = {}, r = {} m:",
        config.covariance.k_correspondences_for_cov, config.covariance.max_distance_for_cov
    );
    print_summary(&summarize(&cloud, &config.covariance)?);
    println!("done: simulate, bake, serve and localize join this demo as they land (see README).");
    Ok(())
}

/// A LiDAR-like scan around a sensor 1.7 m above flat ground: a ground disc, four
/// walls and a ring of poles, with 1 cm range noise; about 40 000 points.
fn synthetic_scan(seed: u64) -> PointCloud {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut points = Vec::new();
    let noise = |rng: &mut StdRng| rng.random_range(-0.01f32..0.01);
    for _ in 0..20_000 {
        let (r, a) = (
            rng.random_range(2.0f32..30.0),
            rng.random_range(0.0..std::f32::consts::TAU),
        );
        points.push([r * a.cos(), r * a.sin(), -1.7 + noise(&mut rng)]);
    }
    for wall in 0..4 {
        for _ in 0..4_000 {
            let (along, up) = (
                rng.random_range(-20.0f32..20.0),
                rng.random_range(-1.7f32..4.0),
            );
            let off = 20.0 + noise(&mut rng);
            points.push(match wall {
                0 => [off, along, up],
                1 => [-off, along, up],
                2 => [along, off, up],
                _ => [along, -off, up],
            });
        }
    }
    for pole in 0..12 {
        let centre = (pole as f32 * 0.52).sin_cos();
        for _ in 0..300 {
            let a = rng.random_range(0.0..std::f32::consts::TAU);
            let (x, y) = (
                centre.0 * 10.0 + 0.15 * a.cos(),
                centre.1 * 10.0 + 0.15 * a.sin(),
            );
            points.push([x, y, rng.random_range(-1.7f32..3.0)]);
        }
    }
    PointCloud::from_points(points)
}
