//! Raw (not deskewed) automotive scans without per-point times: KITTI
//! 00 frames 0-5 through `kfmap bake --build-poses` (the function the CLI calls, on a
//! dataset folder like the CLI reads); the simulated street driven raw at 5 Hz with
//! its per-point times stripped, deskewed from the points' azimuths, and at 15 m/s with a
//! 64-beam sensor; and kitti00_drive, when its scans are extracted.
//!
//! KITTI anchor (tools/anchors/kiss_icp_kitti.py, KISS-ICP 1.3.0, voxel 1.0 m, max range
//! 100 m, 2 threads, its KITTI scan correction on), aligned ATE RMS against
//! poses_velo_kitti.txt on the same frames:
//!
//! | frames     | --deskew off (KISS-ICP 1.3's KITTI loader) | kiss (0.x azimuth times) | mid |
//! |------------|-------------------------------------------|--------------------------|-----|
//! | 0,1,..,5   | 0.2355 m                                  | 0.1652 m                 | 0.2204 m |
//! | 0,2,4      | 0.2124 m                                  | 0.1853 m                 | 0.2158 m |
//!
//! `kiss` deskews into the sensor frame at the end of the sweep, and only from the third
//! frame on (no motion known before): its poses jump half a sweep (about 0.35 m) ahead
//! there, which lengthens these short, too short trajectories; deskewed into the
//! mid-sweep frame the ground truth refers to (`mid`) the gain is gone. On these frames no
//! registration recovers more than 80-86 % of the ground truth's forward motion per step,
//! deskewed or not (pairwise GICP with the scans deskewed by the true velocity, either
//! sign, or twice it: the same 0.80-0.86), so the ATE mostly measures that disagreement.

use std::path::{Path, PathBuf};

use crate::TestError;
use kfmap_bake::config::BakeConfig;
use kfmap_bake::mapping::{BuildParams, build_trajectory};
use kfmap_bake::pipeline::{BakeInput, BakeOutput, MappingSummary, bake};
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::{Trajectory, format_tum, read_trajectory};
use kfmap_geometry::motion::{DeskewMode, SpinDirection, SweepParams};
use kfmap_sim::{LidarParams, Preset, SimConfig, Simulation, write_dataset};
use kfmap_testdata::require_test_data;
use nalgebra::{Matrix3, Vector3};

/// Each position's error after the rigid fit (Horn / Umeyama, no scale) of `estimate`'s
/// positions onto `truth`'s, metres (as tools/anchors/ate.py).
fn aligned_errors(estimate: &[Pose], truth: &[Pose]) -> Vec<f64> {
    assert_eq!(estimate.len(), truth.len());
    let e: Vec<Vector3<f64>> = estimate.iter().map(|p| p.translation.vector).collect();
    let r: Vec<Vector3<f64>> = truth.iter().map(|p| p.translation.vector).collect();
    let n = e.len() as f64;
    let (me, mr) = (
        e.iter().sum::<Vector3<f64>>() / n,
        r.iter().sum::<Vector3<f64>>() / n,
    );
    let h: Matrix3<f64> = e
        .iter()
        .zip(&r)
        .map(|(a, b)| (b - mr) * (a - me).transpose())
        .sum();
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u.unwrap(), svd.v_t.unwrap());
    let d = (u * v_t).determinant().signum();
    let rot = u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * v_t;
    let t = mr - rot * me;
    e.iter()
        .zip(&r)
        .map(|(a, b)| (rot * a + t - b).norm())
        .collect()
}

/// Aligned ATE: the RMS of [`aligned_errors`], metres.
fn aligned_ate(estimate: &[Pose], truth: &[Pose]) -> f64 {
    let errors = aligned_errors(estimate, truth);
    (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt()
}

/// The largest of [`aligned_errors`], metres.
fn worst_aligned_error(estimate: &[Pose], truth: &[Pose]) -> f64 {
    aligned_errors(estimate, truth)
        .into_iter()
        .fold(0.0, f64::max)
}

/// A KITTI-style dataset folder (`DIR/NNNNNN.bin` linked to kitti00's, `poses.txt` as
/// TUM with times.txt's stamps) of `frames`, as a user would assemble one.
fn kitti_subset(data: &Path, frames: &[usize], name: &str) -> (PathBuf, Vec<Pose>) {
    let dir = std::env::temp_dir().join(format!("kfmap-kitti-raw-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let truth = read_trajectory(&data.join("poses_velo_kitti.txt"))
        .unwrap()
        .poses;
    let times: Vec<f64> = std::fs::read_to_string(data.join("times.txt"))
        .unwrap()
        .split_whitespace()
        .map(|t| t.parse().unwrap())
        .collect();
    for &f in frames {
        let file = format!("{f:06}.bin");
        std::os::unix::fs::symlink(data.join(&file), dir.join(&file)).unwrap();
    }
    let picked: Vec<Pose> = frames.iter().map(|&f| truth[f]).collect();
    let trajectory = Trajectory {
        stamps: Some(frames.iter().map(|&f| times[f]).collect()),
        poses: picked.clone(),
    };
    std::fs::write(dir.join("poses.txt"), format_tum(&trajectory)).unwrap();
    (dir, picked)
}

/// `kfmap bake --dataset DATASET --build-poses --out MAP` with `config` (the function the
/// CLI calls): the built poses and what the mapping reported. `scratch` is removed
/// before a failed bake fails the test.
fn build_poses(dataset: &Path, config: &BakeConfig, map: &Path, scratch: &Path) -> MappingSummary {
    let input = BakeInput {
        build_poses: true,
        ..BakeInput::dataset(dataset)
    };
    let report = bake(&input, config, &BakeOutput::map(map), |_| {});
    if report.is_err() {
        let _ = std::fs::remove_dir_all(scratch);
    }
    report.unwrap().mapping.expect("poses built")
}

/// `kfmap bake --dataset DIR --build-poses` with the default configuration (deskew
/// `auto`, or `deskew`): the built poses' aligned ATE against the frames' truth.
fn bake_kitti(frames: &[usize], name: &str, deskew: DeskewMode) -> Option<f64> {
    let data = require_test_data("kitti00", "kitti_raw")?;
    let (dir, truth) = kitti_subset(&data, frames, name);
    let mut config = BakeConfig::default();
    config.build.odometry.deskew = deskew;
    let mapping = build_poses(&dir, &config, &dir.join("map.kfmap"), &dir);
    let ate = aligned_ate(&mapping.poses, &truth);
    println!(
        "KITTI 00 frames {frames:?}, deskew {deskew} ({}): aligned ATE {ate:.4} m",
        mapping.deskew
    );
    let _ = std::fs::remove_dir_all(&dir);
    Some(ate)
}

/// Every frame (10 Hz, 0.86 m apart) and every second one (~4.8 Hz, 1.7 m apart), raw,
/// deskew `auto` (KITTI .bin: azimuth times). Measured: 0.2471 and 0.2519 m; without
/// deskew 0.2468 and 0.2458 m (the deskew changes nothing measurable here, see the
/// module comment). KISS-ICP as its KITTI pipeline runs (no deskew) measured 0.2355 and
/// 0.2124 m: kfmap is 1.05x and 1.19x of it on these frames, not at or below it. The
/// bounds hold the measured figures (+3 %) so a regression shows.
#[test]
fn kitti00_raw_frames_through_bake() {
    let Some(all) = bake_kitti(&[0, 1, 2, 3, 4, 5], "all", DeskewMode::Auto) else {
        return;
    };
    let every_second = bake_kitti(&[0, 2, 4], "step2", DeskewMode::Auto).unwrap();
    assert!(all <= 0.2471 * 1.03, "frames 0-5: ATE {all} m");
    assert!(
        every_second <= 0.2519 * 1.03,
        "frames 0,2,4: ATE {every_second} m"
    );
}

/// Odometry ATE on the simulated street (10 m/s cruise, 12 m corners) driven with a
/// 16-beam sensor spinning at 5 Hz (2 m per scan), scans raw; `times` keeps their
/// per-point times, else they are stripped like KITTI's .bin and `deskew` decides.
fn street_ate(deskew: DeskewMode, times: bool) -> f64 {
    let sim = Simulation::new(SimConfig {
        preset: Preset::Street,
        seconds: 12.0,
        lidar: LidarParams {
            beams: 16,
            rate_hz: 5.0,
            deskew: false,
            ..LidarParams::default()
        },
        ..SimConfig::default()
    })
    .unwrap();
    let count = sim.config().scan_count();
    let stamps: Vec<f64> = (0..count)
        .map(|i| i as f64 / sim.config().lidar.rate_hz)
        .collect();
    let mut params = BuildParams::default();
    params.odometry.deskew = deskew;
    // The simulator's sensor: counter-clockwise from +X, stamped at the sweep's start.
    params.odometry.sweep = SweepParams {
        seconds: 0.2,
        direction: SpinDirection::CounterClockwise,
        start_deg: 0.0,
        stamp_deg: 0.0,
    };
    let built = build_trajectory::<TestError>(
        &stamps,
        Vec::new(),
        |k| {
            let mut cloud = sim.scan(k).cloud;
            if !times {
                cloud.time = None;
            }
            Ok(cloud)
        },
        &params,
        |_| {},
    )
    .unwrap();
    let truth: Vec<Pose> = (0..count).map(|i| sim.scan_pose(i)).collect();
    aligned_ate(&built.odometry, &truth)
}

/// Azimuth times recover what the recorded per-point times give, and deskewing beats
/// not deskewing, on timeless raw scans at a low frame rate.
#[test]
fn street_raw_at_5hz_deskewed_from_azimuth() {
    let off = street_ate(DeskewMode::Off, false);
    let azimuth = street_ate(DeskewMode::Azimuth, false);
    let recorded = street_ate(DeskewMode::PerPoint, true);
    println!(
        "street raw 5 Hz: ATE {off:.4} m without deskew, {azimuth:.4} m azimuth times, \
         {recorded:.4} m recorded times"
    );
    assert!(azimuth < 0.7 * off, "azimuth {azimuth} m vs off {off} m");
    assert!(
        azimuth <= 1.2 * recorded + 0.01,
        "azimuth {azimuth} m vs recorded times {recorded} m"
    );
}

/// The simulated street driven at 15 m/s (the preset's 10 m/s cruise raised; 1.5 m per
/// sweep), a 64-beam sensor at 10 Hz (0.4 deg azimuth step), sweeps raw (each point at
/// its firing time, the times recorded), with the simulator's IMU: built by `kfmap bake
/// --build-poses` with the defaults (the function the CLI calls, on the folder `kfmap
/// simulate --raw` writes). Its errors are computed here against the simulator's exact
/// poses. Measured 2026-12-03: aligned ATE 0.0085 m (max 0.028 m), KITTI-style drift
/// 0.02 % and 0.011 deg/100 m over 50-200 m segments of the 205 m drive, the joint
/// refinement accepted, no scan poor; the bounds allow about 1.5x of each.
#[test]
fn street_at_15_mps_built_from_raw_sweeps() {
    let dir = std::env::temp_dir().join(format!("kfmap-street15-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let config = SimConfig {
        preset: Preset::Street,
        seconds: 14.0,
        cruise_speed: Some(15.0),
        lidar: LidarParams {
            beams: 64,
            rate_hz: 10.0,
            horizontal_resolution_deg: 0.4,
            deskew: false,
            ..LidarParams::default()
        },
        ..SimConfig::default()
    };
    write_dataset(config, &dir, false, &|_, _| {}).unwrap();
    let mapping = build_poses(&dir, &BakeConfig::default(), &dir.join("map.kfmap"), &dir);
    let truth = read_trajectory(&dir.join("poses_gt.txt")).unwrap().poses;
    let _ = std::fs::remove_dir_all(&dir);
    let ate = aligned_ate(&mapping.poses, &truth);
    let worst = worst_aligned_error(&mapping.poses, &truth);
    let drift = kfmap_geometry::trajectory_error::kitti_drift(&mapping.poses, &truth).unwrap();
    let refine = mapping.refine.as_ref().expect("refinement ran");
    println!(
        "street at 15 m/s, raw: aligned ATE {ate:.4} m (max {worst:.3} m), drift {drift:?}, \
         refinement {:?}, poor {:?}",
        refine.refused, mapping.poor_scans
    );
    assert_eq!(mapping.poses.len(), truth.len());
    assert!(ate <= 0.013, "ATE {ate} m");
    assert!(worst <= 0.045, "worst {worst} m");
    assert!(drift.translation_percent <= 0.03, "{drift:?}");
    assert!(drift.rotation_deg_per_100m <= 0.017, "{drift:?}");
    assert!(refine.accepted(), "{:?}", refine.refused);
    assert!(mapping.poor_scans.is_empty(), "{:?}", mapping.poor_scans);
}

/// kitti00_drive (256 raw HDL-64E key frames, 476 m, RTK reference) built from its scans
/// as `kfmap bake --build-poses --deskew azimuth` with bake.toml's `[input]
/// vertical-angle-offset-deg = 0.205` builds it (the function the CLI calls), once as
/// configured and once with the joint refinement off. The scans are not in the shared
/// data: its `extract.sh` writes them into `kitti00_drive/scans`, and without them this
/// test skips with a reason, under CI as well (CI's shared data has none).
///
/// Measured 2026-12-03: aligned ATE 0.334 m, KITTI-style drift 0.86 % and 0.282 deg/100 m
/// (refinement accepted; 0.325 m, 0.81 %, 0.302 without it), against KISS-ICP 1.3.0's
/// 0.545 m, 1.21 % and 0.504 on the same scans (`tools/anchors/kiss_icp_drive.py`,
/// `kitti_drift.py`). The bounds sit 5 % above kfmap's figures, each below KISS-ICP's.
/// The refinement on this open drive (no loop) must be accepted and must not make the
/// poses worse than the pose graph's: its ATE within 5 % of theirs (the RTK reference is
/// good to 0.1-0.2 m, PROVENANCE), the map's spread lower.
#[test]
fn kitti00_drive_built_from_raw_scans_beats_kiss_icp() {
    let drive = kfmap_testdata::shared_data_dir().map(|d| d.join("kitti00_drive"));
    let Some(drive) = drive.filter(|d| d.join("scans").is_dir()) else {
        println!("skipped: kitti00_drive's scans are not extracted (its extract.sh writes them)");
        return;
    };
    let truth = read_trajectory(&drive.join("poses.txt")).unwrap().poses;
    let build = |refine: bool| {
        let mut config = BakeConfig::default();
        config.build.odometry.deskew = DeskewMode::Azimuth;
        config.input.vertical_angle_offset_deg = 0.205;
        config.build.refine.enabled = refine;
        let dir = std::env::temp_dir().join(format!("kfmap-drive-{}-{refine}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mapping = build_poses(&drive, &config, &dir.join("map.kfmap"), &dir);
        let _ = std::fs::remove_dir_all(&dir);
        mapping
    };
    let refined = build(true);
    let graph = build(false);
    let ate = aligned_ate(&refined.poses, &truth);
    let graph_ate = aligned_ate(&graph.poses, &truth);
    let drift = kfmap_geometry::trajectory_error::kitti_drift(&refined.poses, &truth).unwrap();
    let refine = refined.refine.expect("refinement ran");
    println!(
        "kitti00_drive: aligned ATE {ate:.3} m (pose graph {graph_ate:.3} m), drift {drift:?}, \
         refinement {:?}, spread {:.4} -> {:.4} m",
        refine.refused, refine.consistency_before.mean_spread, refine.consistency_after.mean_spread
    );
    assert!(refine.accepted(), "{:?}", refine.refused);
    assert!(
        ate <= 1.05 * graph_ate,
        "refined {ate} m, pose graph {graph_ate} m"
    );
    assert!(
        refine.consistency_after.mean_spread < refine.consistency_before.mean_spread,
        "{refine:?}"
    );
    assert!(ate <= 0.334 * 1.05, "ATE {ate} m");
    assert!(drift.translation_percent <= 0.86 * 1.05, "{drift:?}");
    assert!(drift.rotation_deg_per_100m <= 0.282 * 1.05, "{drift:?}");
}
