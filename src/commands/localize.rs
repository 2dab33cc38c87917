//! `kfmap localize`: replay a dataset against a running server and localize every scan.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use kfmap_bake::config::BakeConfig;
use kfmap_bake::dataset::{load_raw_scan, scan_poses};
use kfmap_bake::gravity::POSE_FILES;
use kfmap_bake::pipeline::{load_timed, settle_deskew};
use kfmap_bake::scan_range::ScanRange;
use kfmap_bake::source::ScanList;
use kfmap_client::{
    Client, GravityAnswer, HypothesisParams, LocalizeOptions, TrackedScan, Tracker, TrackerOptions,
    TrustParams,
};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::{Pose, pose_to_xyz_quat, rotation_distance, translation_distance};
use kfmap_geometry::gravity::ImuWindow;
use kfmap_geometry::imu::ImuSample;
use kfmap_geometry::io::{Trajectory, format_tum, write_atomic};
use kfmap_geometry::motion::DeskewMode;
use kfmap_geometry::motion::{Gyro, GyroParams};
use kfmap_geometry::options::ConfigFile;
use kfmap_geometry::percentile::percentile;
use kfmap_geometry::tracking::TrackingStatus;
use kfmap_geometry::trajectory_error::{absolute_trajectory_error, relative_pose_error};
use kfmap_protocol::Cov2CovMode;
use kfmap_service::config::ServerConfig;
use serde_json::json;

use super::connect_arg::ConnectArgs;
use super::source_arg::SourceArgs;
use kfmap_geometry::percentile::p99_label;

/// Replay a dataset's scans (and IMU) against a running `kfmap serve` and localize
/// every scan, tracking it: each scan is localized from the pose a constant-velocity
/// model predicts from the scans before (its rotation integrated from the gyro when the
/// dataset has an IMU log and timestamped poses). The first scan is localized from
/// --initial, or with --initial-from-ground-truth from the dataset's reference pose of
/// the first replayed scan; without either, the server relocalizes it (finds where it
/// is in the map with no guess, as `kfmap relocalize`), and relocalizes again every
/// scan the tracker reports lost, restarting tracking where it finds one place.
/// Ground truth is taken to be in the frame of the dataset the map was baked from; the
/// rotation bake applied (gravity levelling) is read from the server.
///
/// Every scan gets a health: status ok / degraded / lost, fitness (inlier ratio), RMSE,
/// degeneracy, the 6x6 pose covariance (calibrated so that an EKF may fuse `ok` poses
/// with it: mean NEES near 3 per group; widened along a direction a 0.5 m slide finds
/// weakly held; docs/DESIGN.md#covariance). A correction larger than the motion model
/// allows (the gate adapts to how wrong predictions have been) is retried from wider
/// hypotheses (a coarser scan with a larger pairing distance, then yaw hypotheses) and
/// adopted only when consistent; otherwise the scan is lost, its pose is the prediction,
/// and tracking keeps predicting until scans agree again.
///
/// Scans are read (PCD, PLY, KITTI .bin), invalid returns dropped, downsampled with
/// --voxel, deskewed when they carry per-point times (the simulator's --raw output,
/// Ouster/Velodyne t or time fields: moved into the sensor frame at mid-scan by the
/// motion model, tracked there and reported at the scan's stamp) and sent over
/// iceoryx2 shared memory. By default this process runs the
/// checks and the GICP solver over the server's cov2cov pairings (client-side);
/// --server-side asks the server to run them (thin client). With an IMU log
/// (imu.csv/imu.txt) and timestamped poses, each scan's IMU window goes to the server's
/// gravity pool with the scan's pose and stamp (the server removes the platform's own
/// acceleration and estimates the accelerometer bias) and the final gravity correction
/// is reported. With ground truth, ATE
/// (aligned, RMS), RPE (RMS of consecutive-motion errors) and each scan's error against
/// its reference pose are reported. A scan whose request fails (e.g. the server died)
/// keeps the prediction and is counted in "failed".
///
/// --json-lines prints one JSON object per scan and then the summary object, one per
/// line. A scan's object: index (in the dataset), t (s), pose [x,y,z,qx,qy,qz,qw]
/// (map frame), status (ok, degraded, lost; failed when the request failed), fitness
/// (inlier ratio), rmse_m, latency_ms, reasons, degenerate, constraint (rotation and
/// translation eigenvalue ratios), covariance (36 values row-major, rotation first,
/// rad and m, sensor frame; null when unknown), correction_m and max_correction_m
/// (translation plus the chord at 10 m), registrations, iterations, converged, and
/// error_m / error_deg against the reference pose when the dataset has one.
///
/// Examples:
///   kfmap localize --map-name site --dataset runs/site-2 --out site-2.tum
///   kfmap localize --map-name site --dataset runs/site-2 --rate 0 --server-side --json
///   kfmap localize --map-name site --dataset runs/site-2 --scans 116..177 \
///       --initial-from-ground-truth --rate 0 --json-lines --mode approximate
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    #[command(flatten)]
    server: ConnectArgs,
    #[command(flatten)]
    source: SourceArgs,
    /// Reference poses (TUM or KITTI) for the errors; default: the dataset folder's
    /// pose file (a bag has none: one pose per cloud, in order).
    #[arg(long, value_name = "FILE")]
    poses: Option<PathBuf>,
    /// Replay only scans A..B of the dataset: a half-open range of indices in its
    /// sorted scan list (e.g. 116..177; "A.." to the end).
    #[arg(long, value_name = "A..B")]
    scans: Option<ScanRange>,
    /// Scans per second to replay at; 0 sends each scan as soon as the last is done.
    #[arg(long, default_value_t = 10.0)]
    rate: f64,
    /// First pose guess "x y z roll pitch yaw" (metres, degrees) or a 4x4 matrix file.
    /// A guess starting with a minus sign is a value, not a flag: --initial "-1 2 0 0 0 30".
    #[arg(
        long,
        conflicts_with = "initial_from_ground_truth",
        allow_hyphen_values = true
    )]
    initial: Option<String>,
    /// Start at the dataset's reference pose of the first replayed scan (an error when
    /// the dataset has no pose file).
    #[arg(long)]
    initial_from_ground_truth: bool,
    /// Write the trajectory here (TUM: t x y z qx qy qz qw).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Let the server solve the pose (thin client) instead of solving here.
    #[arg(long)]
    server_side: bool,
    /// Cov2cov mode: map-default (the server's choice: server.toml, else the map's
    /// bake.toml), approximate (never rebuilds) or exact (a merged submap per active
    /// set, built inside the query).
    #[arg(long, value_enum, default_value_t = ModeArg::MapDefault)]
    mode: ModeArg,
    /// Voxel size applied to each scan before sending, metres (0 sends every point).
    #[arg(long, default_value_t = 0.25)]
    voxel: f64,
    #[command(flatten)]
    sensor: super::sensor_arg::SensorArgs,
    /// Largest pairing distance, metres.
    #[arg(long, default_value_t = 1.0)]
    max_pair_dist: f32,
    /// Iterations per registration at most.
    #[arg(long, default_value_t = 30)]
    max_iterations: u32,
    /// server.toml whose [tracking] section (checks and retry ladder) client-side
    /// localization uses; pass the server's own file so both decide alike
    /// (--server-side uses the server's).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Do not use the dataset's IMU log (no gravity windows, no gyro).
    #[arg(long)]
    no_imu: bool,
    /// The IMU's orientation in the LiDAR frame, "roll pitch yaw" degrees (about fixed
    /// X, then Y, then Z), for the gyro.
    #[arg(long, value_name = "R P Y", default_value = "0 0 0")]
    imu_rpy_deg: String,
    /// Which scans are deskewed (with the motion model's twist, into the mid-scan
    /// frame): auto (scans with per-point times; KITTI velodyne .bin by azimuth, as
    /// `kfmap bake`), per-point, azimuth (scans without per-point times are timed by
    /// their azimuths: --bake-config's [build.odometry.sweep], by default a sensor
    /// sweeping clockwise from behind in 0.1 s, stamped facing forward, as KITTI's
    /// HDL-64E) or off. Default: --bake-config's [build.odometry] deskew, "auto".
    /// kitti00_drive's raw scans on its map: 0.130 m RMS without times, 0.054 m with
    /// `azimuth`.
    #[arg(long, value_name = "MODE", value_parser = super::bake::parse_deskew)]
    deskew: Option<DeskewMode>,
    /// A scan is `ok` only when the map explains at least this share of its structure
    /// (points 1 m above their column's floor, paired within --tight-distance); below,
    /// `degraded` (low-fitness). Raise it where much of the world stays as mapped.
    #[arg(long, default_value_t = TrustParams::default().ok_explained)]
    ok_explained: f64,
    /// A point is explained when a map point lies within this fraction of
    /// --max-pair-dist of it.
    #[arg(long, default_value_t = TrustParams::default().tight_distance)]
    tight_distance: f64,
    /// The explained share is measured in this many keyframes around the pose (nearest
    /// by position), so that a look-alike place, which explains what the few keyframes
    /// at it saw, is told from the right one by the map beyond them (0: only the
    /// registration's active keyframes).
    #[arg(long, default_value_t = TrustParams::default().explained_keyframes)]
    explained_keyframes: u32,
    /// A scan is `ok` only when sliding its pose 0.5 m (either way) along its least
    /// constrained horizontal direction costs at least this share of the structure
    /// explained; below, `degraded` (unpinned: a street it could slide along). -1 turns
    /// the check off.
    #[arg(long, default_value_t = TrustParams::default().ok_pinned, allow_hyphen_values = true)]
    ok_pinned: f64,
    /// After this many scans in a row that do not pin the pose (unpinned, degenerate),
    /// a pinned scan is `ok` only when relocalizing it finds the tracked place itself:
    /// a slide along a street ends somewhere unknown (0: no check).
    #[arg(long, default_value_t = TrustParams::default().confirm_after_unpinned)]
    confirm_after_unpinned: usize,
    /// A place decided among places in doubt (not the one tracked before, unless that
    /// one was itself so decided and is not yet confirmed) is `ok` only once a
    /// relocalization of a pinned scan finds it itself or a scan pins it at least this
    /// well (the slide loss of --ok-pinned): a look-alike along a street is held loosely
    /// and stays ambiguous (2: only a relocalization lifts the doubt).
    #[arg(long, default_value_t = TrustParams::default().ok_pinned_after_doubt, allow_hyphen_values = true)]
    ok_pinned_after_doubt: f64,
    /// A pose farther from the motion model's prediction than 0.5 m plus what this
    /// acceleration (m/s^2) moves the sensor since the last adopted scan is `lost`
    /// (implausible): a slide onto a look-alike, not motion (0: no check). With an IMU
    /// log the acceleration it measured (plus 1 m/s^2, and 0.5 m/s of velocity error)
    /// bounds it tighter when that is less. A pose that far off, and every scan after a
    /// refused one, is also judged against the scans' own motion, registered scan to scan
    /// from the last adopted scan (0.5 m, plus per step 2 % of it and how far it lay from
    /// the step before; scans at most 0.25 s apart, however long the chain).
    #[arg(long, default_value_t = TrustParams::default().max_acceleration)]
    max_acceleration: f64,
    /// Every this many adopted scans the scan is also relocalized, so that a look-alike
    /// place elsewhere becomes a hypothesis beside the tracked one (0: never).
    #[arg(long, default_value_t = TrustParams::default().check_every)]
    check_every: usize,
    /// Adopted scans in a row that do not fit the map after which the tracker says
    /// `lost` (unfit-streak) and, with no start pose, relocalizes.
    #[arg(long, default_value_t = TrustParams::default().lost_after_unfit)]
    lost_after_unfit: usize,
    /// Scans in a row adopted after `lost` before the status is `ok` again.
    #[arg(long, default_value_t = TrustParams::default().recover_after)]
    recover_after: usize,
    /// Places a relocalization scored within this of its best are kept as hypotheses
    /// (share of the scan paired) and told apart on the scans that follow.
    #[arg(long, default_value_t = HypothesisParams::default().margin)]
    hypothesis_margin: f64,
    /// Hypotheses kept at most.
    #[arg(long, default_value_t = HypothesisParams::default().max)]
    hypothesis_max: usize,
    /// Two places are one hypothesis when closer than this, metres...
    #[arg(long, default_value_t = HypothesisParams::default().distinct_m)]
    hypothesis_distinct_m: f64,
    /// ... and turned less than this, degrees.
    #[arg(long, default_value_t = HypothesisParams::default().distinct_deg)]
    hypothesis_distinct_deg: f64,
    /// A place is dropped when the best explains at least this much more of the scans'
    /// structure on average...
    #[arg(long, default_value_t = HypothesisParams::default().min_effect)]
    hypothesis_min_effect: f64,
    /// ... and that mean stands this many standard errors above zero...
    #[arg(long, default_value_t = HypothesisParams::default().z)]
    hypothesis_z: f64,
    /// ... after this many scans, on the differences' own spread...
    #[arg(long, default_value_t = HypothesisParams::default().min_scans)]
    hypothesis_min_scans: usize,
    /// ... or sooner, on the scans since the places were proposed, with each scan's
    /// spread taken as at least this (one scan decides at --hypothesis-z times it; 1:
    /// never early).
    #[arg(long, default_value_t = HypothesisParams::default().early_spread)]
    hypothesis_early_spread: f64,
    /// The tracked place, when a check puts it in doubt, is not dropped for explaining
    /// less while it explains at least this share of the scans on average.
    #[arg(long, default_value_t = HypothesisParams::default().hold_explained)]
    hypothesis_hold_explained: f64,
    /// A place lost this many scans in a row is dropped.
    #[arg(long, default_value_t = HypothesisParams::default().drop_after_lost)]
    hypothesis_drop_after_lost: usize,
    /// Places are compared over their last this many scans (at least --hypothesis-min-scans).
    #[arg(long, default_value_t = HypothesisParams::default().window)]
    hypothesis_window: usize,
    /// A place the scans do not pin (a 0.5 m slide along its weakest direction loses
    /// less than --ok-pinned of its explained structure: a corridor or street it could
    /// slide along) is dropped beside one they pin that explains more, once this many
    /// scans in a row (the proposing one included) showed both so; 0: never.
    #[arg(long, default_value_t = HypothesisParams::default().slide_scans)]
    hypothesis_slide_scans: usize,
    /// Print a JSON summary (scans, ok, degraded, lost, failed, ate_m, p50_ms, ...).
    #[arg(long)]
    json: bool,
    /// Print one JSON object per scan, then the summary on one line.
    #[arg(long)]
    json_lines: bool,
}

/// `--mode`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum ModeArg {
    MapDefault,
    Approximate,
    Exact,
}

impl From<ModeArg> for Cov2CovMode {
    fn from(mode: ModeArg) -> Self {
        match mode {
            ModeArg::MapDefault => Cov2CovMode::MapDefault,
            ModeArg::Approximate => Cov2CovMode::Approximate,
            ModeArg::Exact => Cov2CovMode::Exact,
        }
    }
}

/// Per-scan IMU windows: samples in `(previous scan's time, this scan's time]`.
fn imu_windows(samples: &[ImuSample], stamps: &[f64]) -> Vec<ImuWindow> {
    let stream = ImuWindow::new(samples.to_vec());
    stamps
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
        .collect()
}

/// The tracker's gyro over the IMU log at `path`, with `--imu-rpy-deg`.
fn gyro_from(path: &Path, samples: &[ImuSample], rpy: &str) -> anyhow::Result<Gyro> {
    let angles: Vec<f64> = rpy
        .split_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .ok()
        .filter(|a: &Vec<f64>| a.len() == 3)
        .ok_or_else(|| {
            anyhow::anyhow!(
                "--imu-rpy-deg {rpy:?}: expected three angles in degrees, e.g. \"0 0 90\""
            )
        })?;
    let params = GyroParams {
        lidar_from_imu_rpy_deg: [angles[0], angles[1], angles[2]],
        ..GyroParams::default()
    };
    Gyro::new(samples.to_vec(), params)
        .with_context(|| format!("{}: cannot drive the gyro", path.display()))
}

/// A scan file as clients send it: invalid returns dropped, downsampled at `voxel`
/// metres (0 keeps every point).
pub(super) fn load_scan(
    path: &Path,
    config: &BakeConfig,
    voxel: f64,
) -> anyhow::Result<PointCloud> {
    downsample(load_raw_scan(path, config)?, path, voxel)
}

/// `cloud` downsampled at `voxel` metres (0 keeps every point); `path` names it in errors.
fn downsample(cloud: PointCloud, path: &Path, voxel: f64) -> anyhow::Result<PointCloud> {
    if voxel > 0.0 {
        Ok(cloud
            .voxel_downsample(voxel)
            .with_context(|| path.display().to_string())?)
    } else {
        Ok(cloud)
    }
}

/// One replayed scan's line of `--json-lines`.
fn scan_line(
    index: usize,
    tracked: &TrackedScan,
    latency_ms: f64,
    reference: Option<&Pose>,
    error: Option<&str>,
) -> serde_json::Value {
    let h = &tracked.localized.health;
    let gap = reference.map(|r| {
        (
            translation_distance(&tracked.localized.pose, r),
            rotation_distance(&tracked.localized.pose, r).to_degrees(),
        )
    });
    json!({
        "index": index,
        "t": tracked.t,
        "pose": pose_to_xyz_quat(&tracked.localized.pose),
        "status": if error.is_some() { "failed" } else { h.status.name() },
        "fitness": h.inlier_ratio,
        "rmse_m": h.rmse,
        "latency_ms": latency_ms,
        "reasons": h.reasons.names(),
        "degenerate": h.degenerate,
        "constraint": [h.constraint.rotation_ratio, h.constraint.translation_ratio],
        "covariance": h.covariance.map(|c| c.transpose().as_slice().to_vec()),
        "correction_m": h.correction,
        "max_correction_m": tracked.max_correction,
        "registrations": h.registrations,
        "iterations": h.iterations,
        "converged": h.converged,
        "explained": tracked.explained,
        "slide_loss": tracked.slide_loss,
        "hypotheses": tracked.hypotheses.iter().map(|p| json!({
            "pose": pose_to_xyz_quat(&p.pose),
            "explained": p.mean_explained(),
            "scans": p.explained.len(),
            "error_m": reference.map(|r| translation_distance(&p.pose, r)),
        })).collect::<Vec<_>>(),
        "error_m": gap.map(|g| g.0),
        "error_deg": gap.map(|g| g.1),
        "failure": error,
    })
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    if !(args.rate.is_finite() && args.rate >= 0.0) {
        anyhow::bail!("--rate must be >= 0 scans/s, got {}", args.rate);
    }
    trust(&args)
        .validate()
        .map_err(|e| anyhow::anyhow!("--{}: {e}", e.option))?;
    hypotheses(&args)
        .validate()
        .map_err(|e| anyhow::anyhow!("--hypothesis-{}: {e}", e.option))?;
    let mut scan_config = args.sensor.scan_config()?;
    if let Some(mode) = args.deskew {
        scan_config.build.odometry.deskew = mode;
    }
    let mut dataset = ReplayDataset::read(&args)?;
    let scan_config = settle_deskew(&scan_config, &dataset.scans);
    let deskew = scan_config.build.odometry.deskew.uses_point_times();
    let mut client = args.server.connect()?;
    let truth = dataset.truth_in_map_frame(&mut client)?;
    let mut tracker = start_tracker(&args, truth.as_deref(), dataset.gyro.take(), deskew)?;
    let quiet = args.json || args.json_lines;
    let bar = progress_bar(quiet, dataset.scans.len());
    let replayed = replay_scans(
        &args,
        &scan_config,
        &dataset,
        &mut client,
        &mut tracker,
        truth.as_deref(),
        &bar,
    )?;
    bar.finish_and_clear();
    if let Some(out) = &args.out {
        write_trajectory(out, &dataset.stamps, &replayed.poses)?;
    }
    let summary = Summary::of(&dataset, replayed, truth.as_deref());
    if quiet {
        print_json(&args, &summary)
    } else {
        print_text(&args, &summary);
        Ok(())
    }
}

/// The dataset side of a replay: which scans, their stamps, reference poses and IMU.
struct ReplayDataset {
    /// Indices of the replayed scans in the dataset's sorted scan list.
    range: Range<usize>,
    /// The replayed scans.
    scans: ScanList,
    /// Their stamps, s (from the pose file, else at `--rate`).
    stamps: Vec<f64>,
    /// The replayed scans' reference poses, in the baked dataset's frame.
    truth: Option<Vec<Pose>>,
    /// Every dataset scan's IMU window (by index in the dataset), with an IMU log.
    windows: Option<Vec<ImuWindow>>,
    /// The tracker's gyro over the IMU log.
    gyro: Option<Gyro>,
}

impl ReplayDataset {
    /// Finds the scans of `--dataset` within `--scans`, their reference poses and
    /// stamps, and (with timestamped poses, unless `--no-imu`) the IMU log.
    fn read(args: &Args) -> anyhow::Result<Self> {
        let source = args.source.source();
        let all_scans = source.scans(&mut |_, _| {})?;
        let range = args
            .scans
            .unwrap_or(ScanRange::ALL)
            .within(all_scans.len())?;
        let pose_file = args.poses.clone().or_else(|| source.pose_file());
        let truth = pose_file
            .map(|path| scan_poses(&path, &all_scans))
            .transpose()?;
        if args.initial_from_ground_truth && truth.is_none() {
            anyhow::bail!(
                "--initial-from-ground-truth: {} has no pose file ({}; or pass --poses)",
                source.path().display(),
                POSE_FILES.join(", ")
            );
        }
        let all_stamps: Vec<f64> = match (&truth, all_scans.stamps()) {
            (Some(t), _) => t.stamps.clone(),
            (None, Some(header)) => header.to_vec(),
            (None, None) => (0..all_scans.len())
                .map(|i| i as f64 / args.rate.max(1.0))
                .collect(),
        };
        let stamped = truth.as_ref().is_some_and(|t| t.stamped) || all_scans.stamps().is_some();
        let imu = match source.imu() {
            Some(imu) if stamped && !args.no_imu => Some((imu.label(), imu.read()?)),
            _ => None,
        };
        let windows = imu
            .as_ref()
            .map(|(_, samples)| imu_windows(samples, &all_stamps));
        let gyro = imu
            .as_ref()
            .map(|(path, samples)| gyro_from(path, samples, &args.imu_rpy_deg))
            .transpose()?;
        Ok(Self {
            scans: all_scans.select(range.clone()),
            stamps: all_stamps[range.clone()].to_vec(),
            truth: truth.map(|t| t.poses[range.clone()].to_vec()),
            range,
            windows,
            gyro,
        })
    }

    /// The reference poses in the map frame: ground truth is in the baked dataset's
    /// frame, and the map may be levelled from it (the server says how).
    fn truth_in_map_frame(&self, client: &mut Client) -> anyhow::Result<Option<Vec<Pose>>> {
        let map_from_input = client.status()?.map_from_input;
        Ok(self
            .truth
            .as_ref()
            .map(|t| t.iter().map(|p| map_from_input * *p).collect()))
    }

    /// The IMU window of dataset scan `index`, when it has samples.
    fn window(&self, index: usize) -> Option<&ImuWindow> {
        self.windows
            .as_ref()
            .map(|w| &w[index])
            .filter(|w| !w.is_empty())
    }
}

/// The tracker's trust rules from the command line.
fn trust(args: &Args) -> TrustParams {
    TrustParams {
        recover_after: args.recover_after,
        lost_after_unfit: args.lost_after_unfit,
        check_every: args.check_every,
        ok_explained: args.ok_explained,
        tight_distance: args.tight_distance,
        ok_pinned: args.ok_pinned,
        confirm_after_unpinned: args.confirm_after_unpinned,
        ok_pinned_after_doubt: args.ok_pinned_after_doubt,
        explained_keyframes: args.explained_keyframes,
        max_acceleration: args.max_acceleration,
    }
}

/// How the tracker keeps and drops places in doubt, from the command line.
fn hypotheses(args: &Args) -> HypothesisParams {
    HypothesisParams {
        margin: args.hypothesis_margin,
        max: args.hypothesis_max,
        distinct_m: args.hypothesis_distinct_m,
        distinct_deg: args.hypothesis_distinct_deg,
        min_effect: args.hypothesis_min_effect,
        z: args.hypothesis_z,
        min_scans: args.hypothesis_min_scans,
        early_spread: args.hypothesis_early_spread,
        hold_explained: args.hypothesis_hold_explained,
        drop_after_lost: args.hypothesis_drop_after_lost,
        window: args.hypothesis_window,
        slide_scans: args.hypothesis_slide_scans,
    }
}

/// The tracker: from `--initial`, the reference pose (`--initial-from-ground-truth`) or
/// relocalizing, with the `--config` checks, the solver options and the gyro.
fn start_tracker(
    args: &Args,
    truth: Option<&[Pose]>,
    gyro: Option<Gyro>,
    deskew: bool,
) -> anyhow::Result<Tracker> {
    let initial = match (&args.initial, truth) {
        (Some(text), _) => Some(super::pose_arg::parse_pose(text)?),
        (None, Some(t)) if args.initial_from_ground_truth => Some(t[0]),
        _ => None,
    };
    let tracking = ServerConfig::load(args.config.as_deref())?.tracking;
    let options = TrackerOptions {
        localize: LocalizeOptions {
            max_iterations: args.max_iterations,
            max_pair_dist: args.max_pair_dist,
            mode: args.mode.into(),
            tracking,
            ..LocalizeOptions::default()
        },
        server_side: args.server_side,
        deskew,
        trust: trust(args),
        hypotheses: hypotheses(args),
        ..TrackerOptions::default()
    };
    let mut tracker = match initial {
        Some(pose) => Tracker::new(pose, options),
        None => Tracker::relocalizing(options),
    };
    if let Some(gyro) = gyro {
        tracker = tracker.with_gyro(gyro);
    }
    Ok(tracker)
}

/// The progress bar over `scans` scans (hidden when printing JSON).
fn progress_bar(quiet: bool, scans: usize) -> ProgressBar {
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(scans as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("localizing {bar:30} {pos}/{len} scans, {msg} ({eta})")
            .expect("valid template"),
    );
    bar
}

/// What the replay produced, scan by scan.
struct Replayed {
    /// Each scan's pose (the prediction when its request failed).
    poses: Vec<Pose>,
    /// Each scan's request latency, ms.
    latencies: Vec<f64>,
    /// Each scan's status; `None` when its request failed.
    statuses: Vec<Option<TrackingStatus>>,
    /// Scans whose request failed.
    failed: usize,
    /// GICP iterations over all scans.
    iterations: u64,
    /// The server's last answer to an IMU window.
    gravity: Option<GravityAnswer>,
}

/// Sends every scan at `--rate` and tracks it, printing each scan's line with
/// `--json-lines` and pushing its IMU window to the server's gravity pool.
fn replay_scans(
    args: &Args,
    scan_config: &BakeConfig,
    dataset: &ReplayDataset,
    client: &mut Client,
    tracker: &mut Tracker,
    truth: Option<&[Pose]>,
    bar: &ProgressBar,
) -> anyhow::Result<Replayed> {
    let n = dataset.scans.len();
    let mut out = Replayed {
        poses: Vec::with_capacity(n),
        latencies: Vec::with_capacity(n),
        statuses: Vec::with_capacity(n),
        failed: 0,
        iterations: 0,
        gravity: None,
    };
    let period = (args.rate > 0.0).then(|| Duration::from_secs_f64(1.0 / args.rate));
    for k in 0..n {
        let index = dataset.range.start + k;
        let tick = Instant::now();
        let path = dataset.scans.name(k);
        let cloud = downsample(
            load_timed(&dataset.scans, k, scan_config)?,
            &path,
            args.voxel,
        )?;
        let t = dataset.stamps[k];
        let sent = Instant::now();
        let result = tracker.track_cloud(client, &cloud, t);
        let latency = sent.elapsed().as_secs_f64() * 1e3;
        out.latencies.push(latency);
        let (tracked, error) = match result {
            Ok(tracked) => (tracked, None),
            Err(e) => {
                out.failed += 1;
                bar.suspend(|| eprintln!("scan {}: {e}", path.display()));
                (tracker.unanswered(t), Some(e.to_string()))
            }
        };
        let health = &tracked.localized.health;
        out.iterations += health.iterations as u64;
        out.statuses.push(error.is_none().then_some(health.status));
        if args.json_lines {
            let reference = truth.map(|t| &t[k]);
            let line = scan_line(index, &tracked, latency, reference, error.as_deref());
            println!("{line}");
        }
        let pose = tracked.localized.pose;
        out.poses.push(pose);
        if let Some(w) = dataset.window(index) {
            // The window ends at this scan's stamp; the pose there goes with it.
            match client.push_imu_window(index as u64, &pose, Some(t), w.samples()) {
                Ok(g) => out.gravity = Some(g),
                Err(e) => bar.suspend(|| eprintln!("IMU window of scan {index}: {e}")),
            }
        }
        bar.set_message(format!("last {latency:.1} ms"));
        bar.inc(1);
        if let Some(period) = period {
            std::thread::sleep(period.saturating_sub(tick.elapsed()));
        }
    }
    Ok(out)
}

/// Writes the replayed trajectory to `out` (TUM).
fn write_trajectory(out: &Path, stamps: &[f64], poses: &[Pose]) -> anyhow::Result<()> {
    let trajectory = Trajectory {
        stamps: Some(stamps.to_vec()),
        poses: poses.to_vec(),
    };
    write_atomic(out, format_tum(&trajectory).as_bytes())?;
    Ok(())
}

/// The replay's figures, as printed.
struct Summary {
    scans: usize,
    first_scan: usize,
    ok: usize,
    degraded: usize,
    lost: usize,
    failed: usize,
    /// Latency per scan, ms.
    p50: f64,
    p99: f64,
    mean_iterations: f64,
    /// Against the reference poses, when the dataset has them.
    errors: Option<ReferenceErrors>,
    /// The server's gravity estimate, when it made one.
    gravity: Option<GravityAnswer>,
}

impl Summary {
    /// Counts, latency percentiles and errors against `truth` of the replay.
    fn of(dataset: &ReplayDataset, replayed: Replayed, truth: Option<&[Pose]>) -> Self {
        let mut sorted = replayed.latencies;
        sorted.sort_by(f64::total_cmp);
        let statuses = &replayed.statuses;
        let count = |s: TrackingStatus| statuses.iter().filter(|x| **x == Some(s)).count();
        let scans = dataset.scans.len();
        Self {
            scans,
            first_scan: dataset.range.start,
            ok: count(TrackingStatus::Ok),
            degraded: count(TrackingStatus::Degraded),
            lost: count(TrackingStatus::Lost),
            failed: replayed.failed,
            p50: percentile(&sorted, 0.5),
            p99: percentile(&sorted, 0.99),
            mean_iterations: replayed.iterations as f64 / scans.max(1) as f64,
            errors: truth.map(|t| ReferenceErrors::of(&replayed.poses, t, statuses)),
            gravity: replayed.gravity.filter(|g| g.gravity.is_some()),
        }
    }
}

/// Prints the summary as JSON: pretty, or on one line after the scans' lines with
/// `--json-lines`.
fn print_json(args: &Args, s: &Summary) -> anyhow::Result<()> {
    let errors = s.errors.as_ref();
    let out = json!({
        "scans": s.scans,
        "first_scan": s.first_scan,
        "ok": s.ok,
        "degraded": s.degraded,
        "lost": s.lost,
        "failed": s.failed,
        "ate_m": errors.map(|e| e.ate),
        "rpe_m": errors.map(|e| e.rpe),
        "rms_error_m": errors.map(|e| e.rms),
        "max_error_m": errors.map(|e| e.max_m),
        "max_error_deg": errors.map(|e| e.max_deg),
        "wrong_ok": errors.map(|e| e.wrong_ok),
        "p50_ms": s.p50,
        "p99_ms": s.p99,
        "mean_iterations": s.mean_iterations,
        "server_side": args.server_side,
        "mode": Cov2CovMode::from(args.mode).name(),
        "gravity": s.gravity.as_ref().map(super::gravity::served_json),
    });
    if args.json_lines {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    Ok(())
}

/// Prints the summary for people.
fn print_text(args: &Args, s: &Summary) {
    println!(
        "{} scans localized against map {} ({}): {} ok, {} degraded, {} lost, {} failed",
        s.scans,
        args.server.map_name,
        if args.server_side {
            "server-side GICP"
        } else {
            "client-side GICP"
        },
        s.ok,
        s.degraded,
        s.lost,
        s.failed
    );
    // Every scan's request is timed, failed ones too.
    println!(
        "  latency per scan: p50 {:.2} ms, {} {:.2} ms",
        s.p50,
        p99_label(s.scans),
        s.p99
    );
    if let Some(e) = &s.errors {
        println!(
            "  ATE {:.4} m, RPE {:.4} m per scan; against the reference poses: RMS {:.4} m, max {:.3} m / {:.2} deg, {} scans off by more than {WRONG_M} m reported ok",
            e.ate, e.rpe, e.rms, e.max_m, e.max_deg, e.wrong_ok
        );
    }
    if let Some(g) = &s.gravity {
        println!("  gravity over IPC: {}", super::gravity::served_line(g));
    }
    if let Some(out) = &args.out {
        println!("  trajectory: {}", out.display());
    }
}

/// A pose farther than this from its reference is wrong, metres.
const WRONG_M: f64 = 0.5;

/// The replayed poses against the dataset's reference poses (map frame).
struct ReferenceErrors {
    /// Aligned ATE (RMS), metres.
    ate: f64,
    /// RPE (RMS of consecutive-motion errors), metres.
    rpe: f64,
    /// RMS of the unaligned position errors, metres.
    rms: f64,
    /// Largest position error, metres.
    max_m: f64,
    /// Largest rotation error, degrees.
    max_deg: f64,
    /// Scans farther than [`WRONG_M`] from their reference but reported `ok`.
    wrong_ok: usize,
}

impl ReferenceErrors {
    fn of(poses: &[Pose], truth: &[Pose], statuses: &[Option<TrackingStatus>]) -> Self {
        let gaps: Vec<(f64, f64)> = poses
            .iter()
            .zip(truth)
            .map(|(p, t)| {
                (
                    translation_distance(p, t),
                    rotation_distance(p, t).to_degrees(),
                )
            })
            .collect();
        let n = gaps.len().max(1) as f64;
        Self {
            ate: absolute_trajectory_error(poses, truth),
            rpe: relative_pose_error(poses, truth),
            rms: (gaps.iter().map(|g| g.0 * g.0).sum::<f64>() / n).sqrt(),
            max_m: gaps.iter().map(|g| g.0).fold(0.0, f64::max),
            max_deg: gaps.iter().map(|g| g.1).fold(0.0, f64::max),
            wrong_ok: gaps
                .iter()
                .zip(statuses)
                .filter(|(g, s)| g.0 > WRONG_M && **s == Some(TrackingStatus::Ok))
                .count(),
        }
    }
}

/// What `kfmap localize --json-lines` printed: one object per scan, then the summary.
pub struct LocalizeLog {
    pub scans: Vec<serde_json::Value>,
    pub summary: serde_json::Value,
}

impl LocalizeLog {
    /// Parses the printed lines.
    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let mut scans = text
            .lines()
            .map(serde_json::from_str)
            .collect::<Result<Vec<serde_json::Value>, _>>()
            .context("kfmap localize --json-lines printed a line that is not JSON")?;
        let summary = scans.pop().context("kfmap localize printed nothing")?;
        Ok(Self { scans, summary })
    }

    /// Scans whose health names `reason`.
    pub fn scans_with_reason(&self, reason: &str) -> usize {
        self.scans
            .iter()
            .filter(|scan| {
                scan["reasons"]
                    .as_array()
                    .is_some_and(|r| r.iter().any(|x| x == reason))
            })
            .count()
    }
}
