//! Maps built from simulated drives' raw scans (`build_trajectory`), against the
//! simulator's ground truth: a car's lap of the campus closed by loops, and courtyard
//! drives deskewed and turned by the gyro.
//!
//! Integration tests rather than the crate's unit tests: in one binary with the other
//! integration tests, the lap (one core for most of its half minute) overlaps them
//! instead of finishing alone; the module sorts first so that it starts first.

use crate::TestError;
use kfmap_bake::mapping::{BuildParams, build_trajectory};
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::motion::DeskewMode;
use kfmap_geometry::trajectory_error::absolute_trajectory_error;
use kfmap_sim::{LidarParams, Preset, SimConfig, Simulation};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, OnceLock};

/// Where the run comes back to its start: the scan in the second half nearest to the
/// first scan's true position.
fn lap_closing_scan(truth: &[Pose]) -> usize {
    let start = truth[0].translation.vector;
    (truth.len() / 2..truth.len())
        .min_by(|&a, &b| {
            let d = |i: usize| (truth[i].translation.vector - start).norm();
            d(a).total_cmp(&d(b))
        })
        .expect("a run of at least two scans")
}

/// Translation error of the pose of scan `end` relative to the first scan, metres.
fn end_to_start_drift(estimate: &[Pose], truth: &[Pose], end: usize) -> f64 {
    let e = estimate[0].inverse() * estimate[end];
    let t = truth[0].inverse() * truth[end];
    (e.inverse() * t).translation.vector.norm()
}

struct LapFigures {
    ate: f64,
    ate_odometry: f64,
    drift: f64,
    drift_odometry: f64,
    loops: usize,
}

/// Builds the trajectory of a simulated run (`seconds` of `preset` at `cruise` m/s, a
/// LiDAR of `beams`) from its raw scans alone and compares it with the simulator's
/// ground truth.
fn lap(preset: Preset, seconds: f64, cruise: f64, beams: u32) -> LapFigures {
    let sim = Simulation::new(SimConfig {
        preset,
        seconds,
        lidar: LidarParams {
            beams,
            horizontal_resolution_deg: 0.4,
            ..LidarParams::default()
        },
        cruise_speed: Some(cruise),
        ..SimConfig::default()
    })
    .unwrap();
    let count = sim.config().scan_count();
    let started = std::time::Instant::now();
    let stamps: Vec<f64> = (0..count)
        .map(|i| i as f64 / sim.config().lidar.rate_hz)
        .collect();
    let built = build_trajectory::<TestError>(
        &stamps,
        Vec::new(),
        |i| Ok(sim.scan(i).cloud),
        &BuildParams::default(),
        |_| {},
    )
    .unwrap();
    let truth: Vec<Pose> = (0..count).map(|i| sim.scan_pose(i)).collect();
    let kf =
        |poses: &[Pose]| -> Vec<Pose> { built.keyframe_scans.iter().map(|&i| poses[i]).collect() };
    let closing = lap_closing_scan(&truth);
    let figures = LapFigures {
        ate: absolute_trajectory_error(&kf(&built.poses), &kf(&truth)),
        ate_odometry: absolute_trajectory_error(&kf(&built.odometry), &kf(&truth)),
        drift: end_to_start_drift(&built.poses, &truth, closing),
        drift_odometry: end_to_start_drift(&built.odometry, &truth, closing),
        loops: built.loops_accepted().len(),
    };
    println!(
        "{preset:?} {seconds} s, {beams} beams, {count} scans, {} keyframes in {:.1} s: loops {} \
         found / {} accepted; graph error {:.3} -> {:.3}; keyframe ATE {:.3} m (odometry alone \
         {:.3} m); end-to-start drift at scan {closing} {:.3} m (odometry alone {:.3} m)",
        built.keyframe_scans.len(),
        started.elapsed().as_secs_f64(),
        built.loops_found,
        figures.loops,
        built.graph.initial_error,
        built.graph.final_error,
        figures.ate,
        figures.ate_odometry,
        figures.drift,
        figures.drift_odometry
    );
    figures
}

/// A full lap of the simulated campus (778 m, 32 beams) driven at 19 m/s (a car on a
/// main road; 1.9 m between scans, nearly every scan a keyframe), built from the raw
/// scans alone. Loop closure must cut the keyframe ATE and the end-to-start drift:
/// measured ATE 0.2 cm (odometry alone 13.1 cm), drift 0.2 cm (odometry alone 49.7 cm),
/// 14 loops accepted of 66 found; 27 s alone on 2 cores (2026-12-04). The same lap at
/// 9.5 m/s (90 s) showed 0.2 / 2.8 cm and 0.1 / 11.4 cm and took 99 s beside another
/// test, at the preset's walking pace (165 s) 0.3 / 0.8 cm and 1.2 / 3.4 cm.
///
/// Odometry alone was 3.7 cm (drift 14.1 cm) before its local map took each scan's own
/// covariances instead of estimating them over the merged map (docs/DESIGN.md#map-building):
/// on this sparse 32-beam lap at 1.9 m per scan that costs 3.6x in odometry ATE (the old
/// estimate, put back by hand on 2026-12-04: 3.6 cm, drift 14.1 cm, the build 46 s instead
/// of 29 s); on kitti00_drive (64 beams) 0.313 -> 0.325 m for 17.0 -> 9.6 s of odometry.
/// The odometry bound below holds that trade where it stands.
#[test]
fn campus_lap_from_raw_scans() {
    let f = lap(Preset::Campus, 45.0, 19.0, 32);
    // Bounds about 3x the measured figures (the build is deterministic).
    assert!(f.loops >= 5, "{} loops accepted", f.loops);
    assert!(
        f.ate < 0.005 && f.ate * 8.0 < f.ate_odometry,
        "ATE {} (odometry {})",
        f.ate,
        f.ate_odometry
    );
    assert!(
        f.drift * 15.0 <= f.drift_odometry && f.drift < 0.006,
        "{} vs {}",
        f.drift,
        f.drift_odometry
    );
    // Odometry alone, 10 % above its measured 13.1 cm.
    assert!(f.ate_odometry < 0.144, "odometry ATE {}", f.ate_odometry);
}

/// How the courtyard drive is followed.
#[derive(Clone, Copy)]
struct Drive {
    /// Cruise speed, m/s.
    speed: f64,
    /// Deskew the raw scans.
    deskew: bool,
    /// Give odometry the simulated IMU (noise and bias on).
    gyro: bool,
    /// Use every this many scans (1: 10 Hz).
    stride: usize,
}

/// Odometry ATE on a simulated courtyard drive with motion-distorted (raw) scans. The
/// deskew and gyro tests share three drives: each is built once per test run.
fn raw_drive_ate(drive: Drive) -> f64 {
    type Key = (u64, bool, bool, usize);
    static BUILT: Mutex<BTreeMap<Key, Arc<OnceLock<f64>>>> = Mutex::new(BTreeMap::new());
    let key = (
        drive.speed.to_bits(),
        drive.deskew,
        drive.gyro,
        drive.stride,
    );
    let once = Arc::clone(BUILT.lock().unwrap().entry(key).or_default());
    *once.get_or_init(|| build_raw_drive(drive))
}

/// [`raw_drive_ate`] of each pair of drives, the pairs built side by side: the two drive
/// tests would otherwise build theirs one after another on one core once the campus lap
/// is done.
fn raw_drive_ates(pairs: &[[Drive; 2]]) -> Vec<[f64; 2]> {
    use rayon::prelude::*;
    pairs
        .par_iter()
        .map(|pair| pair.map(raw_drive_ate))
        .collect()
}

/// [`raw_drive_ate`], built.
fn build_raw_drive(drive: Drive) -> f64 {
    let sim = Simulation::new(SimConfig {
        preset: Preset::Courtyard,
        seconds: 12.0,
        cruise_speed: Some(drive.speed),
        lidar: LidarParams {
            beams: 16,
            deskew: false,
            ..LidarParams::default()
        },
        ..SimConfig::default()
    })
    .unwrap();
    let picked: Vec<usize> = (0..sim.config().scan_count())
        .step_by(drive.stride)
        .collect();
    let stamps: Vec<f64> = picked
        .iter()
        .map(|&i| i as f64 / sim.config().lidar.rate_hz)
        .collect();
    let mut params = BuildParams::default();
    params.odometry.deskew = if drive.deskew {
        DeskewMode::PerPoint
    } else {
        DeskewMode::Off
    };
    let imu = if drive.gyro { sim.imu() } else { Vec::new() };
    let built = build_trajectory::<TestError>(
        &stamps,
        imu,
        |k| Ok(sim.scan(picked[k]).cloud),
        &params,
        |_| {},
    )
    .unwrap();
    assert_eq!(built.gyro_bias.is_some(), drive.gyro);
    let truth: Vec<Pose> = picked.iter().map(|&i| sim.scan_pose(i)).collect();
    absolute_trajectory_error(&built.odometry, &truth)
}

/// Deskewing raw scans with the motion model's twist: never worse, and clearly better
/// at 4 m/s. Measured odometry ATE without / with: 1 m/s 1.5 / 0.3 cm, 2 m/s 5.5 / 1.5
/// cm, 4 m/s 16.2 / 11.7 cm (the 4 m/s error comes from one sharp corner, deskewed or
/// not).
#[test]
fn deskewing_raw_scans_lowers_the_odometry_error() {
    let drive = |speed, deskew| Drive {
        speed,
        deskew,
        gyro: false,
        stride: 1,
    };
    let speeds = [1.0, 2.0, 4.0];
    let pairs = speeds.map(|v| [drive(v, false), drive(v, true)]);
    for (speed, [raw, deskewed]) in speeds.into_iter().zip(raw_drive_ates(&pairs)) {
        println!(
            "raw courtyard at {speed} m/s: ATE {raw:.4} m without deskew, {deskewed:.4} m with"
        );
        assert!(
            deskewed <= raw * 1.05 + 1e-3,
            "{speed} m/s: {deskewed} vs {raw}"
        );
        if speed >= 4.0 {
            assert!(deskewed < raw * 0.8, "{speed} m/s: {deskewed} vs {raw}");
        }
    }
}

/// The gyro in the motion model on the fast-turn drives (noisy, biased simulated IMU):
/// at 4 m/s, and with every second or third scan (5 and 3.3 Hz), where constant
/// velocity mispredicts the turns most. The oracle is the simulator's trajectory.
#[test]
fn the_gyro_keeps_fast_turns_on_track() {
    let runs = [(4.0, 1), (4.0, 2), (4.0, 3), (2.0, 1), (1.0, 1)];
    let drive = |(speed, stride): (f64, usize), gyro| Drive {
        speed,
        deskew: true,
        gyro,
        stride,
    };
    let pairs = runs.map(|run| [drive(run, false), drive(run, true)]);
    for ((speed, stride), [without, with]) in runs.into_iter().zip(raw_drive_ates(&pairs)) {
        println!(
            "raw courtyard at {speed} m/s, every {stride} scans: ATE {without:.4} m constant velocity, {with:.4} m with the gyro"
        );
        // Measured at 4 m/s: 11.7 / 9.8 / 30.6 cm without, 0.7 / 0.8 / 1.0 cm with; at
        // 2 and 1 m/s 1.5 / 0.2 and 0.3 / 0.1 cm.
        let gain = if speed >= 4.0 { 3.0 } else { 1.0 };
        assert!(
            with < 0.02 && with * gain < without,
            "{speed} m/s every {stride}: {with} with the gyro vs {without}"
        );
    }
}
