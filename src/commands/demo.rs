//! `kfmap demo`: the main job on built-in defaults. It simulates a small courtyard
//! (LiDAR + IMU with ground truth), loads a simulated scan back through the readers,
//! downsamples it and estimates its covariances, bakes a map file and reopens it by
//! mmap, starts `kfmap serve` on it as a child process and localizes a second simulated
//! run against it with `kfmap localize` as another process; with the real data beside
//! the checkout it analyzes a real Velodyne scan too.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use kfmap_service::bake::{BakeInput, BakeOutput, bake};
use kfmap_service::config::BakeConfig;
use kfmap_shared::archive::{OpenOptions, open_map};
use kfmap_shared::datasets::shared_data_dir;
use kfmap_shared::geometry::Pose;
use kfmap_shared::gravity::roll_pitch_from_gravity;
use kfmap_shared::io::{ReadOptions, read_cloud, read_trajectory};
use kfmap_shared::protocol::transport::{iceoryx_config, remove_prefix_files};
use kfmap_shared::sim::{LidarParams, Preset, SimConfig, gravity_in_map, write_dataset};
use kfmap_shared::summary::summarize;
use nalgebra::Vector3;

use super::report::print_summary;

/// Run the kfmap pipeline end to end on built-in defaults.
///
/// 1. Simulates 10 s of a 32-beam LiDAR and an IMU driving around the courtyard preset,
///    in a world tilted by roll 2 deg and pitch -3 deg against the map frame (into a
///    temporary folder, or --out DIR to keep it).
/// 2. Reads a simulated scan back, downsamples it, estimates per-point covariances.
///    Bakes the simulated scans at their true poses into a .kfmap file (keyframes, trees,
///    covariances, covisibility, gravity pool), levelling the map by the gravity the IMU
///    shows (recovered tilt printed next to the true one), reopens it by mmap and pairs
///    the last scan against it (cov2cov, approximate and exact mode).
/// 3. Starts `kfmap serve` on the map (a child process, its own iceoryx2 prefix) and
///    runs `kfmap localize` (another process) on a second drive of the courtyard
///    recorded at 7 Hz: prints its ATE, per-scan latency and the gravity correction its
///    IMU windows gave over IPC, then stops the server.
/// 4. When ../shared/data is beside the checkout (or $KFMAP_DATA_DIR names it), does the
///    same on a real Velodyne HDL-64E scan (kitti00/000000.bin), or on --scan FILE.
///
/// Example: cargo run --release -- demo
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// Keep the simulated dataset in this folder (must be empty or absent).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Also analyze this cloud file instead of the default real scan.
    #[arg(long)]
    scan: Option<PathBuf>,
}

/// Tilt of the simulated world against the map frame, roll and pitch in degrees: the
/// bake recovers it from the IMU.
const DEMO_TILT_DEG: [f64; 2] = [2.0, -3.0];

/// Removes the temporary dataset folder when the demo ends, however it ends.
struct TempDir(PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let config = BakeConfig::default();
    let (dataset, _cleanup) = match args.out {
        Some(dir) => (dir, None),
        None => {
            let dir = std::env::temp_dir().join(format!("kfmap-demo-{}", std::process::id()));
            (dir.clone(), Some(TempDir(dir)))
        }
    };

    let sim = SimConfig {
        preset: Preset::Courtyard,
        seconds: 10.0,
        tilt_deg: DEMO_TILT_DEG,
        lidar: LidarParams {
            beams: 32,
            ..LidarParams::default()
        },
        ..SimConfig::default()
    };
    println!(
        "kfmap demo: simulating {} s of the courtyard ({} beams, seed {}) into {}",
        sim.seconds,
        sim.lidar.beams,
        sim.seed,
        dataset.display()
    );
    let started = Instant::now();
    let summary = write_dataset(sim.clone(), &dataset, false, &|_, _| {})?;
    println!(
        "  {} scans, {} points, {} IMU samples, {:.1} m driven in {:.2} s",
        summary.scans,
        summary.points,
        summary.imu_samples,
        summary.distance_m,
        started.elapsed().as_secs_f64()
    );
    let truth = read_trajectory(&dataset.join("poses_gt.txt"))?;
    println!(
        "  ground truth: {} poses in poses_gt.txt",
        truth.poses.len()
    );
    analyze(&dataset.join("scans/000010.pcd"), &config)?;
    // The built map's frame is the first scan's: the simulated tilt, seen from it.
    let up_map = -gravity_in_map(sim.tilt_deg[0].to_radians(), sim.tilt_deg[1].to_radians());
    let up_built = truth.poses[0].rotation.inverse() * up_map;
    let level = baked_map_stage(&dataset, &truth, &sim, &up_built)?;
    serve_and_localize(&dataset, &sim, &level, &(level.rotation * up_built))?;

    let real = args.scan.or_else(|| {
        shared_data_dir()
            .map(|d| d.join("kitti00/000000.bin"))
            .filter(|p| p.is_file())
    });
    match real {
        Some(path) => analyze(&path, &config)?,
        None => {
            println!("(no real scan: put the shared data beside the checkout or pass --scan FILE)")
        }
    }
    println!("done.");
    Ok(())
}

/// Bakes the simulated scans (poses built from the scans) into a map file, reopens it
/// by mmap and pairs the last scan against it (cov2cov), in approximate and exact mode.
/// Returns the levelling rotation the bake applied to the built poses.
fn baked_map_stage(
    dataset: &Path,
    truth: &kfmap_shared::io::Trajectory,
    sim: &SimConfig,
    up_built: &Vector3<f64>,
) -> anyhow::Result<Pose> {
    let config = BakeConfig::default();
    let map_path = dataset.join("courtyard.kfmap");
    // The poses are built from the raw scans; poses_gt.txt only measures them.
    let input = BakeInput {
        build_poses: true,
        ..BakeInput::dataset(dataset)
    };
    let report = bake(&input, &config, &BakeOutput::map(&map_path), |_| {})?;
    println!(
        "baked {}: {} keyframes, {} points ({} m voxels), {:.1} MB in {:.2} s ({:.2} M points/s)",
        map_path.display(),
        report.written.keyframes,
        report.written.points,
        config.keyframes.voxel_size,
        report.written.bytes as f64 / 1e6,
        report.seconds,
        report.points_per_second() / 1e6
    );
    let mapping = report
        .mapping
        .as_ref()
        .context("the demo builds its poses from the scans")?;
    println!(
        "  poses built from the raw scans (GICP odometry, {} graph keyframes, loops {} found / {} accepted): keyframe ATE {:.3} m against poses_gt.txt (odometry alone {:.3} m)",
        mapping.keyframes,
        mapping.loops_found,
        mapping.loops_accepted(),
        mapping.ate.unwrap_or(f64::NAN),
        mapping.ate_odometry.unwrap_or(f64::NAN)
    );
    // The baked poses are levelled: the query pose gets the same rotation.
    let mut level = Pose::identity();
    match report.gravity.as_ref().and_then(|g| g.correction.as_ref()) {
        Some(c) => {
            let (roll, pitch) = roll_pitch_from_gravity(up_built, 1e-9);
            println!(
                "  gravity: recovered roll {:.2}°, pitch {:.2}° from {} keyframes' IMU windows; true {:.2}°, {:.2}° (the simulated {:.0}°/{:.0}° world tilt seen from the first scan's frame); map levelled",
                c.roll_deg(),
                c.pitch_deg(),
                c.estimate.health.members,
                roll.to_degrees(),
                pitch.to_degrees(),
                sim.tilt_deg[0],
                sim.tilt_deg[1]
            );
            level = Pose::from_parts(Default::default(), c.rotation.into());
        }
        None => println!("  gravity: too few keyframes with IMU samples for an estimate"),
    }
    let started = Instant::now();
    let mut map = open_map(&map_path, OpenOptions::default())?.map;
    println!(
        "  reopened by mmap in {:.2} ms (no tree or covariance rebuilt)",
        started.elapsed().as_secs_f64() * 1e3
    );
    let last = truth.poses.len() - 1;
    let scan = read_cloud(
        &dataset.join(format!("scans/{last:06}.pcd")),
        &ReadOptions::default(),
    )?
    .cloud
    .voxel_downsample(0.5)?;
    let at = level * mapping.poses[last];
    for approximate in [true, false] {
        map.set_approximate_cov(approximate);
        let started = Instant::now();
        let active = map.activate(&at)?;
        let pairs = active.cov2cov(&scan, &at, 1.0, None)?;
        let mean = pairs.iter().map(|p| (p.dist_sq as f64).sqrt()).sum::<f64>()
            / pairs.len().max(1) as f64;
        println!(
            "  scan {last} ({} points at 0.5 m) vs keyframes {:?}, {} mode: {} pairings ({:.1} %), mean distance {:.3} m, {:.1} ms",
            scan.len(),
            active.ids(),
            if approximate { "approximate" } else { "exact" },
            pairs.len(),
            100.0 * pairs.len() as f64 / scan.len() as f64,
            mean,
            started.elapsed().as_secs_f64() * 1e3
        );
    }
    Ok(level)
}

/// The `kfmap serve` child: SIGTERM and its shared-memory files removed when dropped.
struct ServerChild {
    child: std::process::Child,
    prefix: String,
}

impl Drop for ServerChild {
    fn drop(&mut self) {
        // SAFETY: kill(2) on our own child.
        unsafe {
            libc::kill(self.child.id() as i32, libc::SIGTERM);
        }
        let _ = self.child.wait();
        if let Ok(config) = iceoryx_config(Some(&self.prefix)) {
            remove_prefix_files(&config, &self.prefix);
        }
    }
}

/// Serves the baked map from a child process and localizes a second drive against it
/// from another process.
/// `true_up`: the simulator's up in the levelled map, what the served correction is
/// checked against.
fn serve_and_localize(
    dataset: &Path,
    sim: &SimConfig,
    level: &Pose,
    true_up: &Vector3<f64>,
) -> anyhow::Result<()> {
    use std::io::BufRead;
    use std::process::{Command, Stdio};
    let exe = std::env::current_exe()?;
    let map = dataset.join("courtyard.kfmap");
    let prefix = format!("kfdemo{}_", std::process::id());
    let name = format!("demo{}", std::process::id());
    let mut child = Command::new(&exe)
        .args(["serve", "--map"])
        .arg(&map)
        .args(["--map-name", &name, "--iceoryx-prefix", &prefix])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .context("start kfmap serve")?;
    let stdout = child.stdout.take().context("server stdout")?;
    let server = ServerChild { child, prefix };
    let mut ready = String::new();
    std::io::BufReader::new(stdout).read_line(&mut ready)?;
    anyhow::ensure!(
        ready.starts_with("ready:"),
        "kfmap serve did not start: {ready:?}"
    );
    println!(
        "kfmap serve (child process {}): {}",
        server.child.id(),
        ready.trim()
    );

    // The same drive recorded at 7 Hz: every scan a new viewpoint of the mapped site.
    let second = dataset.join("second-drive");
    let replay = SimConfig {
        lidar: LidarParams {
            rate_hz: 7.0,
            ..sim.lidar
        },
        ..sim.clone()
    };
    write_dataset(replay, &second, false, &|_, _| {})?;
    // The built map's frame is the first scan's, levelled; both drives start there.
    let initial = second.join("initial.txt");
    let m = level.to_homogeneous();
    let rows: Vec<String> = (0..4)
        .map(|r| {
            (0..4)
                .map(|c| m[(r, c)].to_string())
                .collect::<Vec<_>>()
                .join(" ")
        })
        .collect();
    std::fs::write(&initial, rows.join("\n"))?;
    let started = Instant::now();
    let out = Command::new(&exe)
        .args(["localize", "--map-name", &name, "--dataset"])
        .arg(&second)
        .args([
            "--rate",
            "0",
            "--json",
            "--iceoryx-prefix",
            &server.prefix,
            "--initial",
        ])
        .arg(&initial)
        .output()
        .context("run kfmap localize")?;
    anyhow::ensure!(
        out.status.success(),
        "kfmap localize failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let s: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    println!(
        "kfmap localize (child process) on a second drive ({} scans at 7 Hz) in {:.1} s: ATE {:.4} m, RPE {:.4} m, {} ok / {} degraded / {} lost, {} failed; latency per scan p50 {:.1} ms, p99 {:.1} ms ({:.1} GICP iterations on average)",
        s["scans"],
        started.elapsed().as_secs_f64(),
        s["ate_m"].as_f64().unwrap_or(f64::NAN),
        s["rpe_m"].as_f64().unwrap_or(f64::NAN),
        s["ok"],
        s["degraded"],
        s["lost"],
        s["failed"],
        s["p50_ms"].as_f64().unwrap_or(f64::NAN),
        s["p99_ms"].as_f64().unwrap_or(f64::NAN),
        s["mean_iterations"].as_f64().unwrap_or(f64::NAN)
    );
    match s["gravity"].as_object() {
        Some(g) => {
            let number = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
            let (roll, pitch) = (number(&g["roll_deg"]), number(&g["pitch_deg"]));
            let (true_roll, true_pitch) = roll_pitch_from_gravity(true_up, 1e-9);
            let bias: Vec<f64> = g["accel_bias_mps2"]
                .as_array()
                .map(|b| b.iter().map(number).collect())
                .unwrap_or_default();
            println!(
                "  gravity over IPC from {} IMU windows ({} motion-compensated): roll {roll:.3}°, pitch {pitch:.3}° left in the levelled map; the truth {:.3}°, {:.3}°: residual {:.3}° / {:.3}°; accelerometer bias {bias:.3?} m/s^2",
                g["members"],
                g["compensated_members"],
                true_roll.to_degrees(),
                true_pitch.to_degrees(),
                roll - true_roll.to_degrees(),
                pitch - true_pitch.to_degrees(),
            )
        }
        None => println!("  gravity over IPC: too few IMU windows for an estimate"),
    }
    drop(server);
    println!("kfmap serve stopped; its shared memory removed");
    Ok(())
}

/// Loads `path`, downsamples it and prints its covariance statistics.
fn analyze(path: &Path, config: &BakeConfig) -> anyhow::Result<()> {
    let started = Instant::now();
    let loaded = read_cloud(
        path,
        &ReadOptions {
            bin_layout: None,
            filter: config.filter,
        },
    )?;
    let dropped = loaded.filter.map_or(0, |f| f.dropped());
    println!(
        "{} ({}, {} invalid returns dropped, read in {:.1} ms)",
        path.display(),
        loaded.format,
        dropped,
        started.elapsed().as_secs_f64() * 1e3
    );
    let cloud = loaded.cloud;
    cloud
        .validate()
        .with_context(|| path.display().to_string())?;
    let started = Instant::now();
    let downsampled = cloud.voxel_downsample(0.25)?;
    println!(
        "  voxel 0.25 m:     {} -> {} points in {:.1} ms",
        cloud.len(),
        downsampled.len(),
        started.elapsed().as_secs_f64() * 1e3
    );
    print_summary(&summarize(&cloud, &config.covariance)?);
    Ok(())
}
