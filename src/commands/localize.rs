//! `kfmap localize`: replay a dataset against a running server and localize every scan.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use kfmap_client::{GravityAnswer, LocalizeOptions, Localized};
use kfmap_service::bake::{dataset_poses, find_scans, load_raw_scan};
use kfmap_service::config::BakeConfig;
use kfmap_service::gravity::{IMU_FILES, find_in, read_imu};
use kfmap_service::server::percentile;
use kfmap_shared::geometry::Pose;
use kfmap_shared::gravity::ImuWindow;
use kfmap_shared::io::{Trajectory, format_tum, write_atomic};
use kfmap_shared::mapping::{absolute_trajectory_error, relative_pose_error};
use kfmap_shared::protocol::{Cov2CovMode, ScanPayload};
use serde_json::json;

use super::connect_arg::ConnectArgs;

/// Replay a dataset's scans (and IMU) against a running `kfmap serve` and localize
/// every scan, each starting from the previous scan's pose (the first from
/// --initial, in the map frame, else the dataset's first ground-truth pose, else
/// identity). Ground truth is taken to be in the frame of the dataset the map was
/// baked from; the rotation bake applied (gravity levelling) is read from the server.
///
/// Scans are read (PCD, PLY, KITTI .bin), invalid returns dropped, downsampled with
/// --voxel and sent over iceoryx2 shared memory. By default this process runs the GICP
/// solver over the server's cov2cov pairings (client-side); --server-side asks the
/// server to solve (thin client). With an IMU log (imu.csv/imu.txt) and timestamped
/// poses, each scan's IMU window goes to the server's gravity pool and the final
/// gravity correction is reported. With ground truth, ATE (aligned, RMS) and RPE
/// (RMS of consecutive-motion errors) are printed. A scan that fails keeps the
/// previous pose and is counted in "failed".
///
/// Examples:
///   kfmap localize --map-name site --dataset runs/site-2 --out site-2.tum
///   kfmap localize --map-name site --dataset runs/site-2 --rate 0 --server-side --json
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    #[command(flatten)]
    server: ConnectArgs,
    /// Dataset directory (scans/ or scan files, optional pose file and IMU log).
    #[arg(long)]
    dataset: PathBuf,
    /// Scans per second to replay at; 0 sends each scan as soon as the last is done.
    #[arg(long, default_value_t = 10.0)]
    rate: f64,
    /// First pose guess "x y z roll pitch yaw" (metres, degrees) or a 4x4 matrix file.
    #[arg(long)]
    initial: Option<String>,
    /// Write the trajectory here (TUM: t x y z qx qy qz qw).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Let the server solve the pose (thin client) instead of solving here.
    #[arg(long)]
    server_side: bool,
    /// Voxel size applied to each scan before sending, metres (0 sends every point).
    #[arg(long, default_value_t = 0.25)]
    voxel: f64,
    /// Largest pairing distance, metres.
    #[arg(long, default_value_t = 1.0)]
    max_pair_dist: f32,
    /// Iterations per scan at most.
    #[arg(long, default_value_t = 30)]
    max_iterations: u32,
    /// Do not send IMU windows even when the dataset has an IMU log.
    #[arg(long)]
    no_imu: bool,
    /// Print a JSON summary (scans, ate_m, rpe_m, p50_ms, p99_ms, failed, ...).
    #[arg(long)]
    json: bool,
}

/// Per-scan IMU windows: samples in `(previous scan's time, this scan's time]`.
fn imu_windows(dataset: &Path, stamps: &[f64]) -> anyhow::Result<Option<Vec<ImuWindow>>> {
    let Some(path) = find_in(dataset, &IMU_FILES) else {
        return Ok(None);
    };
    let stream = ImuWindow::new(read_imu(&path)?);
    let windows = stamps
        .iter()
        .enumerate()
        .map(|(i, &t)| {
            let start = if i == 0 {
                f64::NEG_INFINITY
            } else {
                stamps[i - 1]
            };
            ImuWindow::cut(stream.samples(), start, t)
        })
        .collect();
    Ok(Some(windows))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if !(args.rate.is_finite() && args.rate >= 0.0) {
        anyhow::bail!("--rate must be >= 0 scans/s, got {}", args.rate);
    }
    let scans = find_scans(&args.dataset)?;
    let truth = dataset_poses(&args.dataset, &scans)?;
    let stamps: Vec<f64> = match &truth {
        Some(t) => t.stamps.clone(),
        None => (0..scans.len())
            .map(|i| i as f64 / args.rate.max(1.0))
            .collect(),
    };
    let windows = match &truth {
        Some(t) if t.stamped && !args.no_imu => imu_windows(&args.dataset, &stamps)?,
        _ => None,
    };
    let mut client = args.server.connect()?;
    // Ground truth is in the baked dataset's frame; the map may be levelled from it.
    let map_from_input = client.status()?.map_from_input;
    let truth = truth.map(|mut t| {
        t.poses.iter_mut().for_each(|p| *p = map_from_input * *p);
        t
    });
    let initial = match (&args.initial, &truth) {
        (Some(text), _) => super::pose_arg::parse_pose(text)?,
        (None, Some(t)) => t.poses[0],
        (None, None) => Pose::identity(),
    };
    let options = LocalizeOptions {
        max_iterations: args.max_iterations,
        max_pair_dist: args.max_pair_dist,
        mode: Cov2CovMode::MapDefault,
    };
    let bar = if args.json {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(scans.len() as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("localizing {bar:30} {pos}/{len} scans, {msg} ({eta})")
            .expect("valid template"),
    );
    let config = BakeConfig::default();
    let period = (args.rate > 0.0).then(|| Duration::from_secs_f64(1.0 / args.rate));
    let mut poses = Vec::with_capacity(scans.len());
    let mut latencies = Vec::with_capacity(scans.len());
    let mut failed = 0usize;
    let mut iterations = 0u64;
    let mut gravity: Option<GravityAnswer> = None;
    let mut guess = initial;
    for (i, path) in scans.iter().enumerate() {
        let tick = Instant::now();
        let cloud = load_raw_scan(path, &config)?;
        let cloud = if args.voxel > 0.0 {
            cloud
                .voxel_downsample(args.voxel)
                .with_context(|| path.display().to_string())?
        } else {
            cloud
        };
        let scan = ScanPayload {
            points: &cloud.points,
            view_dirs: None,
            covariances: None,
        };
        let sent = Instant::now();
        let result: Result<Localized, _> = if args.server_side {
            client.localize(&scan, &guess, &options)
        } else {
            client.localize_client_side(&scan, &guess, &options)
        };
        latencies.push(sent.elapsed().as_secs_f64() * 1e3);
        match result {
            Ok(found) => {
                guess = found.pose;
                iterations += found.iterations as u64;
            }
            Err(e) => {
                failed += 1;
                bar.suspend(|| eprintln!("scan {}: {e}", path.display()));
            }
        }
        poses.push(guess);
        if let Some(w) = windows.as_ref().map(|w| &w[i]).filter(|w| !w.is_empty()) {
            match client.push_imu_window(i as u64, &guess, w.samples()) {
                Ok(g) => gravity = Some(g),
                Err(e) => bar.suspend(|| eprintln!("IMU window of scan {i}: {e}")),
            }
        }
        bar.set_message(format!("last {:.1} ms", latencies[i]));
        bar.inc(1);
        if let Some(period) = period {
            std::thread::sleep(period.saturating_sub(tick.elapsed()));
        }
    }
    bar.finish_and_clear();
    if let Some(out) = &args.out {
        let trajectory = Trajectory {
            stamps: Some(stamps.clone()),
            poses: poses.clone(),
        };
        write_atomic(out, format_tum(&trajectory).as_bytes())?;
    }
    let mut sorted = latencies.clone();
    sorted.sort_by(f64::total_cmp);
    let (p50, p99) = (percentile(&sorted, 0.5), percentile(&sorted, 0.99));
    let errors = truth.as_ref().map(|t| {
        (
            absolute_trajectory_error(&poses, &t.poses),
            relative_pose_error(&poses, &t.poses),
        )
    });
    let tilt = gravity.filter(|g| g.gravity.is_some()).map(|g| {
        (
            g.roll_pitch[0].to_degrees(),
            g.roll_pitch[1].to_degrees(),
            g.members,
        )
    });
    if args.json {
        let out = json!({
            "scans": scans.len(),
            "failed": failed,
            "ate_m": errors.map(|e| e.0),
            "rpe_m": errors.map(|e| e.1),
            "p50_ms": p50,
            "p99_ms": p99,
            "mean_iterations": iterations as f64 / (scans.len() - failed).max(1) as f64,
            "server_side": args.server_side,
            "gravity": tilt.map(|(r, p, n)| json!({"roll_deg": r, "pitch_deg": p, "members": n})),
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "{} scans localized against map {} ({}), {failed} failed",
        scans.len(),
        args.server.map_name,
        if args.server_side {
            "server-side GICP"
        } else {
            "client-side GICP"
        }
    );
    println!("  latency per scan: p50 {p50:.2} ms, p99 {p99:.2} ms");
    if let Some((ate, rpe)) = errors {
        println!("  ATE {ate:.4} m, RPE {rpe:.4} m per scan");
    }
    if let Some((roll, pitch, members)) = tilt {
        println!(
            "  gravity over IPC: roll {roll:.3} deg, pitch {pitch:.3} deg ({members} keyframes)"
        );
    }
    if let Some(out) = &args.out {
        println!("  trajectory: {}", out.display());
    }
    Ok(())
}
