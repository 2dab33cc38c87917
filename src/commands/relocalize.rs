//! `kfmap relocalize`: where each scan was taken in a served map, with no pose guess.

use std::path::PathBuf;
use std::time::Instant;

use kfmap_client::RelocalizeOptions;
use kfmap_geometry::geometry::pose_to_xyz_quat;
use kfmap_protocol::ScanPayload;
use nalgebra::UnitQuaternion;
use serde_json::json;

use super::connect_arg::ConnectArgs;

/// Find where each scan file was taken in the map a running server serves, with no
/// initial pose: the server searches its baked place grid over every yaw and position
/// near the map's keyframes, verifies the best places by registration and answers
/// `found`, `ambiguous` (two places fit almost equally, e.g. a symmetric corridor) or
/// `not-found` (the scan is from elsewhere or sees too little of the map). Up is found
/// from the scan's floor-like planes, unless --tilt-deg gives the sensor's roll and
/// pitch against the map's z (e.g. from an IMU's gravity, the map levelled on gravity
/// as `kfmap bake` levels maps with an IMU log): on rolling or sloping ground a scan's
/// own floor is degrees off, and a known tilt makes the search far more certain.
/// (`kfmap localize` passes each scan's tilt from the dataset's IMU log itself.)
///
/// Examples:
///   kfmap relocalize --map-name site scan.pcd
///   kfmap relocalize --map-name site scans/*.pcd --json > places.jsonl
///   kfmap relocalize --map-name site --tilt-deg 1.5,-4.0 scan.pcd
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    #[command(flatten)]
    server: ConnectArgs,
    /// Scan files, sensor frame (PCD, PLY, KITTI .bin, raw xyz .bin).
    #[arg(required = true)]
    scans: Vec<PathBuf>,
    /// Voxel size applied to each scan before sending, metres (0 sends every point).
    #[arg(long, default_value_t = 0.25)]
    voxel: f64,
    #[command(flatten)]
    sensor: super::sensor_arg::SensorArgs,
    /// Largest pairing distance of the verifying registrations, metres.
    #[arg(long, default_value_t = 1.0)]
    max_pair_dist: f32,
    /// The sensor's tilt, "ROLL,PITCH" in degrees (about x, then y; R = Ry(pitch)
    /// Rx(roll), yaw unknown) against the map's z, for every scan given.
    #[arg(long, value_name = "ROLL,PITCH", allow_hyphen_values = true)]
    tilt_deg: Option<String>,
    /// One JSON object per scan: scan, status, pose [x,y,z,qx,qy,qz,qw] (map frame,
    /// null when not-found), fitness (inlier ratio), rmse_m, score and runner_up (the
    /// verification scores of the best and the best other place), runner_up_pose (that
    /// other place, null when none), places (every place scored, {pose, score}, best
    /// first), candidates, latency_ms, server_ms.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let options = RelocalizeOptions {
        max_pair_dist: args.max_pair_dist,
        tilt: args.tilt_deg.as_deref().map(parse_tilt).transpose()?,
        ..RelocalizeOptions::default()
    };
    if !(options.max_pair_dist.is_finite() && options.max_pair_dist > 0.0) {
        anyhow::bail!(
            "--max-pair-dist must be a positive distance, got {}",
            options.max_pair_dist
        );
    }
    if !(args.voxel.is_finite() && args.voxel >= 0.0) {
        anyhow::bail!(
            "--voxel must be a size >= 0 m (0 sends every point), got {}",
            args.voxel
        );
    }
    let config = args.sensor.scan_config()?;
    let mut client = args.server.connect()?;
    for path in &args.scans {
        let cloud = super::localize::load_scan(path, &config, args.voxel)?;
        let scan = ScanPayload {
            points: &cloud.points,
            view_dirs: cloud.view_dirs.as_deref(),
            covariances: None,
        };
        let started = Instant::now();
        let place = client.relocalize(&scan, &options)?;
        let latency_ms = started.elapsed().as_secs_f64() * 1e3;
        let pose = place.pose.map(|p| pose_to_xyz_quat(&p));
        // The place the runner-up's score is of: what an `ambiguous` scan may also be.
        let runner_up = (place.pose.is_some() && place.runner_up > 0.0)
            .then(|| {
                place
                    .places
                    .iter()
                    .skip(1)
                    .find(|p| p.score == place.runner_up)
            })
            .flatten()
            .map(|p| pose_to_xyz_quat(&p.pose));
        if args.json {
            let places: Vec<_> = place
                .places
                .iter()
                .map(|p| json!({ "pose": pose_to_xyz_quat(&p.pose), "score": p.score }))
                .collect();
            println!(
                "{}",
                json!({
                    "scan": path.display().to_string(),
                    "status": place.status.name(),
                    "pose": pose,
                    "fitness": place.inlier_ratio,
                    "rmse_m": place.rmse,
                    "tight_fitness": place.tight_inlier_ratio,
                    "score": place.score,
                    "runner_up": place.runner_up,
                    "runner_up_pose": runner_up,
                    "places": places,
                    "candidates": place.candidates,
                    "latency_ms": latency_ms,
                    "server_ms": place.server_us / 1e3,
                })
            );
        } else {
            let at = pose.map_or("-".to_string(), |p| {
                format!(
                    "x {:.2} y {:.2} z {:.2} (q {:.3} {:.3} {:.3} {:.3})",
                    p[0], p[1], p[2], p[3], p[4], p[5], p[6]
                )
            });
            let other = runner_up.map_or(String::new(), |p| {
                format!(" at x {:.2} y {:.2} z {:.2}", p[0], p[1], p[2])
            });
            println!(
                "{}: {} at {at}; fitness {:.2}, score {:.2} vs runner-up {:.2}{other}, {:.0} ms",
                path.display(),
                place.status.name(),
                place.inlier_ratio,
                place.score,
                place.runner_up,
                latency_ms
            );
        }
    }
    Ok(())
}

/// `--tilt-deg ROLL,PITCH` as `R_map_sensor` with no yaw.
fn parse_tilt(text: &str) -> anyhow::Result<UnitQuaternion<f64>> {
    let angles: Vec<f64> = text
        .split(',')
        .map(|a| a.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .ok()
        .filter(|a: &Vec<f64>| a.len() == 2 && a.iter().all(|v| v.is_finite() && v.abs() < 90.0))
        .ok_or_else(|| {
            anyhow::anyhow!(
                "--tilt-deg {text:?}: expected \"ROLL,PITCH\", two angles in degrees below 90 in size, e.g. 1.5,-4"
            )
        })?;
    Ok(UnitQuaternion::from_euler_angles(
        angles[0].to_radians(),
        angles[1].to_radians(),
        0.0,
    ))
}
