//! `kfmap query`: one nearest-neighbour, radius or cov2cov query against a running server.

use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::{ReadOptions, read_cloud};
use kfmap_protocol::{Cov2CovMode, ScanPayload, WirePairing};
use kfmap_service::server::MAX_RADIUS;
use serde_json::json;

use super::connect_arg::ConnectArgs;

/// Send the points of a cloud file (sensor frame) at a pose to a running server and
/// print what it found: per point the map point, its keyframe and squared distance
/// (and for cov2cov the information matrix). --out writes one CSV row per answer.
///
/// Examples:
///   kfmap query --map-name site --points scan.pcd --pose "10 2 0 0 0 90"
///   kfmap query --map-name site --points scan.pcd --kind cov2cov --out pairs.csv
///   kfmap query --map-name site --points scan.pcd --kind radius --radius 0.5 --json
///   kfmap query --map-name site --points scan.pcd --max-dist 0.3 --out near.csv
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    #[command(flatten)]
    server: ConnectArgs,
    /// Cloud file with the query points (PCD, PLY, KITTI .bin, raw xyz .bin).
    #[arg(long)]
    points: PathBuf,
    /// Pose of the points "x y z roll pitch yaw" (metres, degrees) or a 4x4 matrix file.
    #[arg(long)]
    pose: Option<String>,
    /// What to ask.
    #[arg(long, value_enum, default_value = "nearest")]
    kind: KindArg,
    /// Neighbours per point (nearest).
    #[arg(long, default_value_t = 1)]
    k: u32,
    /// Search this many keyframes, those nearest the pose by position, instead of the
    /// active set (nearest only; 0: the active set, 1 to 64).
    #[arg(long, default_value_t = 0)]
    keyframes: u32,
    /// Search radius, metres (radius).
    #[arg(long, default_value_t = 0.5)]
    radius: f32,
    /// Only neighbours within this many metres (nearest; up to 20, default: any
    /// distance): points with none that near get no answer.
    #[arg(long)]
    max_dist: Option<f32>,
    /// Largest pairing distance, metres (cov2cov).
    #[arg(long, default_value_t = 1.0)]
    max_pair_dist: f32,
    /// Exact cov2cov (merged submap) instead of the map's default.
    #[arg(long)]
    exact: bool,
    /// Write every answer as CSV here.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print a JSON summary.
    #[arg(long)]
    json: bool,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum KindArg {
    Nearest,
    Radius,
    Cov2cov,
}

fn write_csv(path: &PathBuf, pairings: &[WirePairing]) -> anyhow::Result<()> {
    let file = std::fs::File::create(path).with_context(|| path.display().to_string())?;
    let mut w = std::io::BufWriter::new(file);
    writeln!(
        w,
        "query,keyframe,local_index,x,y,z,dist_sq,ixx,ixy,ixz,iyy,iyz,izz"
    )?;
    for p in pairings {
        let [x, y, z] = p.point;
        let i = p.information;
        writeln!(
            w,
            "{},{},{},{x},{y},{z},{},{},{},{},{},{},{}",
            p.query, p.keyframe, p.local_index, p.dist_sq, i[0], i[1], i[2], i[3], i[4], i[5]
        )?;
    }
    w.flush()?;
    Ok(())
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.keyframes != 0 && !matches!(args.kind, KindArg::Nearest) {
        anyhow::bail!(
            "--keyframes {} applies to --kind nearest only; radius and cov2cov search the active set",
            args.keyframes
        );
    }
    if args.max_dist.is_some() && !matches!(args.kind, KindArg::Nearest) {
        anyhow::bail!(
            "--max-dist applies to --kind nearest only; radius has --radius, cov2cov --max-pair-dist"
        );
    }
    if let Some(d) = args
        .max_dist
        .filter(|d| !(d.is_finite() && *d > 0.0 && *d <= MAX_RADIUS))
    {
        anyhow::bail!("--max-dist {d} must be a distance in (0, {MAX_RADIUS}] m");
    }
    let cloud = read_cloud(&args.points, &ReadOptions::default())?.cloud;
    let pose = match &args.pose {
        Some(text) => super::pose_arg::parse_pose(text)?,
        None => Pose::identity(),
    };
    let mut client = args.server.connect()?;
    let started = Instant::now();
    let pairings = match args.kind {
        KindArg::Nearest => {
            client.nearest_around(&cloud.points, &pose, args.k, args.keyframes, args.max_dist)?
        }
        KindArg::Radius => client.radius(&cloud.points, &pose, args.radius)?,
        KindArg::Cov2cov => {
            let scan = ScanPayload {
                points: &cloud.points,
                view_dirs: cloud.view_dirs.as_deref(),
                covariances: None,
            };
            let mode = if args.exact {
                Cov2CovMode::Exact
            } else {
                Cov2CovMode::MapDefault
            };
            client
                .cov2cov(&scan, &pose, args.max_pair_dist, mode)?
                .pairings
        }
    };
    let ms = started.elapsed().as_secs_f64() * 1e3;
    if let Some(out) = &args.out {
        write_csv(out, &pairings)?;
    }
    let answered = {
        let mut q: Vec<u32> = pairings.iter().map(|p| p.query).collect();
        q.dedup();
        q.len()
    };
    let mean_dist = pairings
        .iter()
        .map(|p| (p.dist_sq as f64).sqrt())
        .sum::<f64>()
        / pairings.len().max(1) as f64;
    if args.json {
        let out = json!({
            "points": cloud.len(), "answers": pairings.len(), "points_answered": answered,
            "mean_distance_m": mean_dist, "round_trip_ms": ms,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "{} points -> {} answers for {answered} points, mean distance {mean_dist:.3} m, {ms:.2} ms round trip",
        cloud.len(),
        pairings.len()
    );
    if args.out.is_none() {
        for p in pairings.iter().take(10) {
            let [x, y, z] = p.point;
            println!(
                "  point {:>6}: keyframe {} [{x:.3}, {y:.3}, {z:.3}] at {:.3} m",
                p.query,
                p.keyframe,
                (p.dist_sq as f64).sqrt()
            );
        }
        if pairings.len() > 10 {
            println!("  ... (--out FILE writes them all)");
        }
    }
    Ok(())
}
