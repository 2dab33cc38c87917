//! `kfmap demo`: the main job on built-in defaults, end to end: a dataset (simulated, or
//! the real handheld sequence with `--real`), a map built from its raw scans and baked,
//! the map served by `kfmap serve` as a child process, a second pass localized against
//! it by `kfmap localize` as another process, and pictures of both. Progress goes to
//! stderr; stdout gets one table, also written to the output folder as `report.md`.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::commands::cloud_summary::summarize;
use anyhow::{Context, bail};
use kfmap_bake::config::BakeConfig;
use kfmap_bake::dataset::scan_poses;
use kfmap_bake::pipeline::{BakeInput, BakeOutput, bake};
use kfmap_bake::scan_range::ScanRange;
use kfmap_bake::source::{BagSource, Source};
use kfmap_bench::data_dir::shared_data_dir;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::gravity::{GravityCorrection, roll_pitch_from_gravity};
use kfmap_geometry::io::{
    ReadOptions, Trajectory, format_tum, read_cloud, read_trajectory, write_atomic,
};
use kfmap_map::archive::{OpenOptions, open_map};
use kfmap_sim::{LidarParams, Preset, SimConfig, gravity_in_map, write_dataset};

use super::localize::LocalizeLog;
use kfmap_bench::json_number;
use kfmap_bench::server_child::{ServerChild, run_localize};
use kfmap_geometry::percentile::p99_label;
use kfmap_plot::{MapPlotOptions, TrajectoryPlotInputs, render_map, render_trajectory};

/// Run the kfmap pipeline end to end on built-in defaults and draw the result.
///
/// Simulated (default; about a minute on 2 cores):
///   1. simulates 52 s (a lap) of a 32-beam LiDAR and an IMU driving around a courtyard
///      whose world is tilted roll 2 deg / pitch -3 deg against the map frame, and the
///      covariances of one scan;
///   2. builds the poses from the raw scans (GICP odometry, loop closure, pose graph)
///      and bakes the map file, levelled by the gravity the IMU shows;
///   3. reopens it by mmap (nothing rebuilt);
///   4. starts `kfmap serve` on it (a child process, its own iceoryx2 prefix) and runs
///      `kfmap localize` (another process) on a second drive recorded at 7 Hz, sending
///      its IMU windows for a gravity correction;
///   5. draws map.png (the map from above) and trajectory.png (the second drive against
///      the simulator's ground truth, error as colour).
///
/// --real: the same pipeline on the real handheld sequence balm_os0 from the shared
/// data beside the checkout (or $KFMAP_DATA_DIR): the map from scans 0-115 (poses
/// built from the scans), scans 116-176 (a revisit) localized against it, the first one
/// placed by relocalization with no pose guess; errors against the dataset's reference
/// poses.
///
/// Written to --out DIR (default ./kfmap-demo; files of an earlier demo overwritten):
///   report.md        the table printed on stdout
///   map.kfmap        the baked map            map.png         the map from above
///   map_poses.tum    every mapped scan's built pose, map frame
///   localized.tum    the localized pass       reference.tum   its reference, map frame
///   localize.jsonl   one line per localized scan (status, fitness, error, latency)
///   trajectory.png   localized against reference, error as colour, lost scans marked
///
/// Examples:
///   cargo run --release -- demo
///   kfmap demo --real --out /tmp/balm-demo
///   kfmap demo --bag run.mcap --points-topic /ouster/points --imu-topic /ouster/imu \
///       --poses run_reference.tum --map-scans ..400 --localize-scans 300..
///
/// --bag: the same pipeline on your own bag (MCAP, rosbag2 sqlite3 or ROS 1; see
/// `kfmap inspect-bag`): the map built from the clouds of --map-scans (default all),
/// then --localize-scans (default all) localized against it from no pose guess, errors
/// against --poses (one reference pose per cloud, in order).
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// Output folder (created when absent).
    #[arg(long, default_value = "kfmap-demo")]
    out: PathBuf,
    /// Run on the real sequence balm_os0 of the shared data instead of the simulator.
    #[arg(long, conflicts_with = "bag")]
    real: bool,
    /// Run on a bag instead of the simulator (with --points-topic and --poses).
    #[arg(long, value_name = "PATH", requires_all = ["points_topic", "poses"])]
    bag: Option<PathBuf>,
    /// With --bag: the sensor_msgs/PointCloud2 topic.
    #[arg(long, value_name = "TOPIC", requires = "bag")]
    points_topic: Option<String>,
    /// With --bag: the sensor_msgs/Imu topic (gravity levelling, gyro).
    #[arg(long, value_name = "TOPIC", requires = "bag")]
    imu_topic: Option<String>,
    /// With --bag: reference poses, one per cloud in order (TUM or KITTI).
    #[arg(long, value_name = "FILE", requires = "bag")]
    poses: Option<PathBuf>,
    /// With --bag: the clouds the map is built from (A..B, counting the topic's clouds).
    #[arg(long, value_name = "A..B", requires = "bag")]
    map_scans: Option<ScanRange>,
    /// With --bag: the clouds localized against the map.
    #[arg(long, value_name = "A..B", requires = "bag")]
    localize_scans: Option<ScanRange>,
    /// Keep the simulated datasets in OUT/dataset and OUT/second-drive (they must not
    /// exist yet).
    #[arg(long, conflicts_with_all = ["real", "bag"])]
    keep_dataset: bool,
}

/// Tilt of the simulated world against the map frame, roll and pitch in degrees: the
/// bake recovers it from the IMU.
const DEMO_TILT_DEG: [f64; 2] = [2.0, -3.0];

/// balm_os0: the scans mapped (the first pass) and the revisit localized against them.
const BALM_MAPPED: std::ops::Range<usize> = 0..116;
const BALM_REPLAYED: std::ops::Range<usize> = 116..177;

/// Removes a temporary folder when the demo ends, however it ends.
struct TempDir(PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The report: one row per step, printed as a table at the end.
#[derive(Default)]
struct Report {
    title: String,
    rows: Vec<ReportRow>,
}

struct ReportRow {
    step: String,
    result: String,
    /// Its duration; none for a line that is not a step of its own.
    seconds: Option<f64>,
}

impl Report {
    /// Runs a step, logs its start and records the line it returns with its duration.
    fn step<T>(
        &mut self,
        name: &str,
        work: impl FnOnce() -> anyhow::Result<(T, String)>,
    ) -> anyhow::Result<T> {
        tracing::info!("{name} ...");
        let started = Instant::now();
        let (value, result) = work().with_context(|| format!("demo step '{name}'"))?;
        self.rows.push(ReportRow {
            step: name.to_string(),
            result,
            seconds: Some(started.elapsed().as_secs_f64()),
        });
        Ok(value)
    }

    /// Records a line that is not a step of its own (no time).
    fn note(&mut self, name: &str, result: String) {
        self.rows.push(ReportRow {
            step: name.to_string(),
            result,
            seconds: None,
        });
    }

    /// A markdown table: readable in a terminal, pasteable into a document.
    fn table(&self) -> String {
        let width = |cell: fn(&ReportRow) -> &str, header: &str| {
            let widest = self.rows.iter().map(|r| cell(r).chars().count()).max();
            widest.unwrap_or(0).max(header.len())
        };
        let (w0, w1) = (width(|r| &r.step, "step"), width(|r| &r.result, "result"));
        let mut out = format!("{}\n\n", self.title);
        out += &format!("| {:w0$} | {:w1$} | {:>7} |\n", "step", "result", "seconds");
        out += &format!(
            "|{}|{}|{}:|\n",
            "-".repeat(w0 + 2),
            "-".repeat(w1 + 2),
            "-".repeat(8)
        );
        for row in &self.rows {
            let seconds = row.seconds.map_or(String::new(), |s| format!("{s:.2}"));
            out += &format!("| {:w0$} | {:w1$} | {seconds:>7} |\n", row.step, row.result);
        }
        out
    }
}

/// A pass of scans to map and a pass to localize against the map, with references.
struct Passes {
    /// Dataset the map is built from, and which of its scans.
    mapped: Source,
    mapped_scans: ScanRange,
    /// Reference poses of a bag (a folder's are found in it).
    reference_file: Option<PathBuf>,
    /// Dataset localized against the map, which of its scans, and their reference poses.
    replayed: Source,
    replayed_scans: ScanRange,
    replayed_reference: Trajectory,
    /// Start the localized pass by relocalization (no pose guess) instead of at the map
    /// frame's origin.
    relocalize_first: bool,
    /// The simulated world's tilt when the map is levelled by a simulated IMU.
    sim_tilt_deg: Option<[f64; 2]>,
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("create the output folder {}", args.out.display()))?;
    let out = args.out.canonicalize()?;
    let mut report = Report::default();
    let temp = std::env::temp_dir().join(format!("kfmap-demo-{}", std::process::id()));
    let _cleanup = TempDir(temp.clone());
    let passes = if let Some(bag) = &args.bag {
        bag_passes(&mut report, &args, bag)?
    } else if args.real {
        real_passes(&mut report)?
    } else {
        let data = if args.keep_dataset { out.clone() } else { temp };
        simulated_passes(&mut report, &data)?
    };
    run_pipeline(&mut report, &passes, &out)?;
    let table = report.table();
    write_atomic(&out.join("report.md"), table.as_bytes())?;
    print!("{table}");
    Ok(())
}

/// Simulates the mapping drive and the second drive into `data`.
fn simulated_passes(report: &mut Report, data: &Path) -> anyhow::Result<Passes> {
    let sim = SimConfig {
        preset: Preset::Courtyard,
        seconds: 52.0,
        tilt_deg: DEMO_TILT_DEG,
        lidar: LidarParams {
            beams: 32,
            ..LidarParams::default()
        },
        ..SimConfig::default()
    };
    report.title = format!(
        "kfmap demo: simulated courtyard ({} s of a {}-beam LiDAR + IMU, world tilted roll {} / pitch {} deg, seed {})",
        sim.seconds, sim.lidar.beams, sim.tilt_deg[0], sim.tilt_deg[1], sim.seed
    );
    let mapped = data.join("dataset");
    let summary = report.step("simulate", || {
        let s = write_dataset(sim.clone(), &mapped, false, &|_, _| {})?;
        let line = format!(
            "{} scans at {} Hz, {:.2} M points, {} IMU samples, {:.1} m driven",
            s.scans,
            sim.lidar.rate_hz,
            s.points as f64 / 1e6,
            s.imu_samples,
            s.distance_m
        );
        Ok((s, line))
    })?;
    let scan = mapped.join(format!("scans/{:06}.pcd", summary.scans / 10));
    report.step("covariances", || Ok(((), analyze(&scan)?)))?;
    // The same drive recorded at 7 Hz: every scan a new viewpoint of the mapped site.
    let replayed = data.join("second-drive");
    let replay = SimConfig {
        lidar: LidarParams {
            rate_hz: 7.0,
            ..sim.lidar
        },
        ..sim.clone()
    };
    let replayed_reference = report.step("simulate again", || {
        let s = write_dataset(replay, &replayed, false, &|_, _| {})?;
        let reference = read_trajectory(&replayed.join("poses_gt.txt"))?;
        let line = format!("the same drive at 7 Hz, to localize: {} scans", s.scans);
        Ok((reference, line))
    })?;
    Ok(Passes {
        mapped: Source::Folder(mapped),
        mapped_scans: ScanRange::ALL,
        reference_file: None,
        replayed: Source::Folder(replayed),
        replayed_scans: ScanRange::ALL,
        replayed_reference,
        // Both drives start where the map's frame is: the first scan's pose.
        relocalize_first: false,
        sim_tilt_deg: Some(sim.tilt_deg),
    })
}

/// balm_os0 from the shared data: the first pass mapped, the revisit localized.
fn real_passes(report: &mut Report) -> anyhow::Result<Passes> {
    let balm = shared_data_dir()
        .map(|d| d.join("balm_os0"))
        .filter(|d| d.join("poses.txt").is_file())
        .context(
            "demo --real needs the shared data beside the checkout (../shared/data/balm_os0) or $KFMAP_DATA_DIR naming the data folder",
        )?;
    report.title = format!(
        "kfmap demo --real: balm_os0 (handheld 64-ring LiDAR, 2 Hz, fast turns; {})",
        balm.display()
    );
    let reference = read_trajectory(&balm.join("poses.txt"))?;
    if reference.poses.len() < BALM_REPLAYED.end {
        bail!(
            "{} has {} poses, the demo needs {}",
            balm.join("poses.txt").display(),
            reference.poses.len(),
            BALM_REPLAYED.end
        );
    }
    report.note(
        "dataset",
        format!(
            "{} scans: {}-{} mapped, {}-{} localized (a revisit 2.3-4 m from the first pass)",
            reference.poses.len(),
            BALM_MAPPED.start,
            BALM_MAPPED.end - 1,
            BALM_REPLAYED.start,
            BALM_REPLAYED.end - 1
        ),
    );
    let replayed_reference = Trajectory {
        stamps: reference.stamps.as_ref().map(|s| s[BALM_REPLAYED].to_vec()),
        poses: reference.poses[BALM_REPLAYED].to_vec(),
    };
    Ok(Passes {
        mapped: Source::Folder(balm.clone()),
        mapped_scans: ScanRange {
            start: BALM_MAPPED.start,
            end: Some(BALM_MAPPED.end),
        },
        reference_file: None,
        replayed: Source::Folder(balm),
        replayed_scans: ScanRange {
            start: BALM_REPLAYED.start,
            end: Some(BALM_REPLAYED.end),
        },
        replayed_reference,
        // No pose guess: the first scan is relocalized, as any lost one would be.
        relocalize_first: true,
        sim_tilt_deg: None,
    })
}

/// A bag of the user's: the clouds of `--map-scans` mapped, those of `--localize-scans`
/// localized from no guess, against `--poses`.
fn bag_passes(report: &mut Report, args: &Args, bag: &Path) -> anyhow::Result<Passes> {
    let source = Source::Bag(BagSource {
        path: bag.to_path_buf(),
        points_topic: args.points_topic.clone().unwrap_or_default(),
        imu_topic: args.imu_topic.clone(),
    });
    let poses = args.poses.clone().context("--bag needs --poses")?;
    let scans = source.scans(&mut |_, _| {})?;
    let reference = scan_poses(&poses, &scans)?;
    let mapped_scans = args.map_scans.unwrap_or(ScanRange::ALL);
    let replayed_scans = args.localize_scans.unwrap_or(ScanRange::ALL);
    let (mapped, replayed) = (
        mapped_scans.within(scans.len())?,
        replayed_scans.within(scans.len())?,
    );
    report.title = format!("kfmap demo --bag: {}", bag.display());
    report.note(
        "dataset",
        format!(
            "{} clouds on {}: {}-{} mapped, {}-{} localized",
            scans.len(),
            args.points_topic.as_deref().unwrap_or(""),
            mapped.start,
            mapped.end - 1,
            replayed.start,
            replayed.end - 1
        ),
    );
    let replayed_reference = Trajectory {
        stamps: Some(reference.stamps[replayed.clone()].to_vec()),
        poses: reference.poses[replayed].to_vec(),
    };
    Ok(Passes {
        mapped: source.clone(),
        mapped_scans,
        reference_file: Some(poses),
        replayed: source,
        replayed_scans,
        replayed_reference,
        relocalize_first: true,
        sim_tilt_deg: None,
    })
}

/// Map, serve, localize, draw: the same for simulated and real data.
fn run_pipeline(report: &mut Report, passes: &Passes, out: &Path) -> anyhow::Result<()> {
    let map = out.join("map.kfmap");
    let map_poses = out.join("map_poses.tum");
    let baked = report.step("build and bake the map", || {
        build_map(passes, &map, &map_poses)
    })?;
    // The simulator's up (its input frame's) in the built map's frame, levelled.
    let true_up = passes.sim_tilt_deg.map(|tilt| {
        let up_input = -gravity_in_map(tilt[0].to_radians(), tilt[1].to_radians());
        baked.map_from_input.rotation * up_input
    });
    if let Some(up) = true_up {
        note_levelling(report, &baked, &up);
    }
    report.step("reopen by mmap", || reopen(&map))?;
    let reference_path = out.join("reference.tum");
    write_reference(passes, &baked, &reference_path)?;
    let server = report.step("kfmap serve", || start_demo_server(&map))?;
    let localized = out.join("localized.tum");
    let log = out.join("localize.jsonl");
    let summary = report.step("kfmap localize", || {
        localize_pass(passes, &server, &localized, &log)
    })?;
    drop(server);
    note_localization(report, &summary, true_up.as_ref());
    draw_pictures(report, &map, out, &localized, &reference_path, &log)?;
    report.note(
        "files",
        format!(
            "{}/: map.kfmap, map_poses.tum, localized.tum, reference.tum, localize.jsonl, report.md",
            out.display()
        ),
    );
    Ok(())
}

/// Notes the roll and pitch the bake's levelling recovered against the simulator's
/// true `up` (in the map frame).
fn note_levelling(report: &mut Report, baked: &Baked, up: &nalgebra::Vector3<f64>) {
    let line = match &baked.level {
        Some(c) => {
            // What the levelling had to undo: the true up before it.
            let (roll, pitch) = roll_pitch_from_gravity(&(c.rotation.inverse() * up), 1e-9);
            format!(
                "recovered roll {:.2} deg, pitch {:.2} deg from the IMU; truth {:.2} / {:.2} deg; map levelled",
                c.roll_deg(),
                c.pitch_deg(),
                roll.to_degrees(),
                pitch.to_degrees()
            )
        }
        None => "too few keyframes with IMU samples for an estimate".into(),
    };
    report.note("level by gravity", line);
}

/// Writes the replayed pass's reference poses in the map frame, as the server reports
/// it, to `path` (TUM).
fn write_reference(passes: &Passes, baked: &Baked, path: &Path) -> anyhow::Result<()> {
    let reference = Trajectory {
        stamps: passes.replayed_reference.stamps.clone(),
        poses: passes
            .replayed_reference
            .poses
            .iter()
            .map(|p| baked.map_from_input * p)
            .collect(),
    };
    write_atomic(path, format_tum(&reference).as_bytes())?;
    Ok(())
}

/// Starts `kfmap serve` on `map` as a child process; the report's line about it.
fn start_demo_server(map: &Path) -> anyhow::Result<(ServerChild, String)> {
    let id = std::process::id();
    let server = ServerChild::start(map, &format!("demo{id}"), &format!("kfdemo{id}_"), &[])?;
    let ready = server.ready.trim_start_matches("ready: ");
    let line = format!("child process {}, {ready}", server.pid());
    Ok((server, line))
}

/// Runs `kfmap localize --json-lines` on the replayed pass against `server`, writing
/// the trajectory to `localized` and the log to `log`: its summary and the report's
/// line.
fn localize_pass(
    passes: &Passes,
    server: &ServerChild,
    localized: &Path,
    log: &Path,
) -> anyhow::Result<(serde_json::Value, String)> {
    // Without a guess the first scan is relocalized, as any lost one would be.
    let start: &[&str] = if passes.relocalize_first {
        &[]
    } else {
        &["--initial-from-ground-truth"]
    };
    let scans = passes.replayed_scans;
    let range = format!(
        "{}..{}",
        scans.start,
        scans.end.map_or(String::new(), |e| e.to_string())
    );
    let mut args: Vec<&std::ffi::OsStr> = vec!["--scans".as_ref(), range.as_ref()];
    args.extend([
        "--json-lines".as_ref(),
        "--out".as_ref(),
        localized.as_os_str(),
    ]);
    args.extend(start.iter().map(OsStr::new));
    if let Some(poses) = &passes.reference_file {
        args.extend(["--poses".as_ref(), poses.as_os_str()]);
    }
    let lines = run_localize(server, &passes.replayed, &args)?;
    write_atomic(log, lines.as_bytes())?;
    let s = LocalizeLog::parse(&lines)?;
    let relocalized = s.scans_with_reason("relocalized");
    let v = &s.summary;
    let line = format!(
        "{} scans: {} ok / {} degraded / {} lost / {} failed{}; per scan p50 {:.1} ms, {} {:.1} ms",
        v["scans"],
        v["ok"],
        v["degraded"],
        v["lost"],
        v["failed"],
        match relocalized {
            0 => String::new(),
            n => format!(", {n} relocalized with no guess"),
        },
        json_number(&v["p50_ms"]),
        p99_label(v["scans"].as_u64().unwrap_or(0) as usize),
        json_number(&v["p99_ms"]),
    );
    Ok((s.summary, line))
}

/// Notes the localized pass's error against its reference and, with the simulator's
/// true `up`, the gravity the server estimated over IPC against it.
fn note_localization(
    report: &mut Report,
    summary: &serde_json::Value,
    true_up: Option<&nalgebra::Vector3<f64>>,
) {
    report.note(
        "error vs reference",
        format!(
            "in the map frame: RMS {:.3} m, max {:.3} m / {:.2} deg, {} scans over 0.5 m reported ok; aligned on itself (ATE) {:.3} m",
            json_number(&summary["rms_error_m"]),
            json_number(&summary["max_error_m"]),
            json_number(&summary["max_error_deg"]),
            summary["wrong_ok"],
            json_number(&summary["ate_m"]),
        ),
    );
    if let (Some(g), Some(up)) = (summary["gravity"].as_object(), true_up) {
        let (roll, pitch) = (json_number(&g["roll_deg"]), json_number(&g["pitch_deg"]));
        let (true_roll, true_pitch) = roll_pitch_from_gravity(up, 1e-9);
        report.note(
            "gravity over IPC",
            format!(
                "{} IMU windows: roll {roll:.3} / pitch {pitch:.3} deg left in the levelled map; residual against the truth {:.3} / {:.3} deg",
                g["members"],
                roll - true_roll.to_degrees(),
                pitch - true_pitch.to_degrees()
            ),
        );
    }
}

/// Draws map.png and trajectory.png (the localized pass against its reference, its
/// scan log marked) into `out`.
fn draw_pictures(
    report: &mut Report,
    map: &Path,
    out: &Path,
    localized: &Path,
    reference: &Path,
    log: &Path,
) -> anyhow::Result<()> {
    let map_png = out.join("map.png");
    report.step("picture of the map", || {
        render_map(map, &map_png, &MapPlotOptions::default())?;
        Ok(((), map_png.display().to_string()))
    })?;
    let trajectory_png = out.join("trajectory.png");
    report.step("picture of the trajectory", || {
        let inputs = TrajectoryPlotInputs {
            estimate: localized,
            reference,
            scan_log: Some(log),
            title: Some("localized pass against its reference (map frame)"),
        };
        render_trajectory(&inputs, &trajectory_png, 1600, 1200)?;
        Ok(((), trajectory_png.display().to_string()))
    })?;
    Ok(())
}

/// What baking the demo's map gave the later steps.
struct Baked {
    /// The levelling the gravity stage applied, when there was an IMU log.
    level: Option<GravityCorrection>,
    /// The dataset's reference frame seen from the map's.
    map_from_input: Pose,
}

/// Builds the poses from the raw scans and bakes the map.
fn build_map(passes: &Passes, map: &Path, map_poses: &Path) -> anyhow::Result<(Baked, String)> {
    let input = BakeInput {
        source: passes.mapped.clone(),
        poses: passes.reference_file.clone(),
        build_poses: true,
        scans: passes.mapped_scans,
        refine_only: false,
    };
    let output = BakeOutput {
        trajectory: Some(map_poses.to_path_buf()),
        ..BakeOutput::map(map)
    };
    let r = bake(&input, &BakeConfig::default(), &output, |_| {})?;
    let mapping = r
        .mapping
        .as_ref()
        .context("the demo builds its poses from the scans")?;
    let line = format!(
        "{} scans -> {} keyframes, {:.2} M points, {:.0} MB; {} of {} loops accepted; keyframe ATE {:.3} m (odometry alone {:.3} m)",
        r.scans.len(),
        r.written.keyframes,
        r.written.points as f64 / 1e6,
        r.written.bytes as f64 / 1e6,
        mapping.loops_accepted(),
        mapping.loops_found,
        mapping.ate.unwrap_or(f64::NAN),
        mapping.ate_odometry.unwrap_or(f64::NAN),
    );
    let baked = Baked {
        level: r.gravity.filter(|g| g.applied).and_then(|g| g.correction),
        map_from_input: r.map_from_input,
    };
    Ok((baked, line))
}

/// Reopens the map by mmap and times it.
fn reopen(map: &Path) -> anyhow::Result<((), String)> {
    let started = Instant::now();
    let opened = open_map(map, OpenOptions::default())?;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    Ok((
        (),
        format!(
            "{} keyframes ready in {ms:.2} ms: trees and covariances read in place, none rebuilt",
            opened.map.len()
        ),
    ))
}

/// Covariance statistics of one scan.
fn analyze(path: &Path) -> anyhow::Result<String> {
    let config = BakeConfig::default();
    let cloud = read_cloud(
        path,
        &ReadOptions {
            bin_layout: None,
            filter: config.filter,
        },
    )?
    .cloud;
    cloud
        .validate()
        .with_context(|| path.display().to_string())?;
    let s = summarize(&cloud, &config.covariance)?;
    Ok(format!(
        "one scan, {} points: covariances in {:.1} ms on {} threads, {:.1} % isotropic fallback, mean planarity {:.2}",
        s.points,
        s.covariances_ms,
        s.threads,
        100.0 * s.fallback_fraction,
        s.mean_planarity.unwrap_or(f64::NAN)
    ))
}
