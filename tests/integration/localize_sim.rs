//! Localization of a simulated run against the baked map of another run of the same
//! site, over IPC with real processes: accuracy, client/server agreement, gravity.

use crate::common;

use std::path::Path;
use std::process::{Command, Stdio};

use common::{
    Prefix, Server, assert_nees, bake_dataset, kfmap_bin, map_from_input, pose_errors,
    rms_and_max_m, simulate, temp_dir,
};
use kfmap_bake::dataset::{dataset_poses, find_scans};
use kfmap_bake::gravity::read_imu;
use kfmap_client::{Client, ClientOptions};
use kfmap_geometry::geometry::{Pose, pose_from_xyz_quat};
use kfmap_geometry::gravity::{GravityParams, ImuWindow, LiveGravity};
use kfmap_geometry::io::{
    CloudFormat, PcdData, ReadOptions, read_cloud, read_trajectory, write_cloud,
};
use kfmap_sim::gravity_in_map;

/// One scan of `kfmap localize --json-lines`: what it reported, no error figure of its own.
struct Reported {
    pose: Pose,
    status: String,
}

/// `kfmap localize --json-lines`: each scan's pose and status (the summary dropped).
fn localize_lines(data: &Path, prefix: &str, out: &Path, extra: &[&str]) -> Vec<Reported> {
    let extra = [extra, &["--json-lines"]].concat();
    let stdout = String::from_utf8(run_localize(data, prefix, out, &extra)).unwrap();
    stdout
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v.get("index").is_some())
        .map(|v| {
            let pose: Vec<f64> = serde_json::from_value(v["pose"].clone()).unwrap();
            Reported {
                pose: pose_from_xyz_quat(pose.try_into().unwrap()).unwrap(),
                status: v["status"].as_str().unwrap().to_string(),
            }
        })
        .collect()
}

/// The simulator's poses of `dataset` (`poses_gt.txt`, one per scan) in the frame of the
/// map served as `name`: the oracle of every error below.
fn truth_in_map(dataset: &Path, name: &str, prefix: &Prefix) -> Vec<Pose> {
    let map_from_input = map_from_input(name, &prefix.0);
    read_trajectory(&dataset.join("poses_gt.txt"))
        .unwrap()
        .poses
        .iter()
        .map(|p| map_from_input * p)
        .collect()
}

/// `kfmap localize --json-lines` against a running server from the dataset's reference
/// start: the summary and each scan's line.
fn localize_with_lines(
    data: &Path,
    prefix: &str,
    out: &Path,
    extra: &[&str],
) -> (serde_json::Value, Vec<serde_json::Value>) {
    let extra = [extra, &["--json-lines"]].concat();
    let stdout = String::from_utf8(run_localize(data, prefix, out, &extra)).unwrap();
    let (scans, summary): (Vec<_>, Vec<_>) = stdout
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .partition(|v| v.get("index").is_some());
    assert_eq!(summary.len(), 1);
    (summary.into_iter().next().unwrap(), scans)
}

fn run_localize(data: &Path, prefix: &str, out: &Path, extra: &[&str]) -> Vec<u8> {
    let mut command = Command::new(kfmap_bin());
    command
        .args([
            "localize",
            "--initial-from-ground-truth",
            "--map-name",
            "campus",
        ])
        .arg("--dataset")
        .arg(data)
        .args(["--rate", "0", "--json", "--iceoryx-prefix", prefix, "--out"])
        .arg(out)
        .args(extra)
        .stderr(Stdio::piped());
    common::succeeded(&mut command).stdout
}

/// The map: 10 s of the campus at 10 Hz with 64 beams, baked at its true poses. The
/// run localized: the same drive recorded at 7 Hz, so every scan is a new viewpoint.
/// Issue target: under 5 cm from the simulator's truth (here every scan's own error in
/// the map frame, RMS, computed by the test from the written trajectories); client-side
/// and server-side GICP within 1 mm and 0.01 deg of each other. The gravity correction from the IMU windows sent over IPC
/// (world tilted 2 / -3 deg, the simulator's accelerometer bias on) equals the
/// in-process pool's on the same windows, poses and stamps, every member
/// motion-compensated, and is within 0.1 deg of the simulator's tilt.
#[test]
fn campus_run_localizes_against_the_map_of_another_run() {
    let dir = temp_dir("campus");
    let (mapped, replayed) = (dir.join("mapped"), dir.join("replayed"));
    let tilt = ["--tilt-deg", "2,-3"];
    simulate(&mapped, "campus", "10", "64", &tilt);
    simulate(
        &replayed,
        "campus",
        "10",
        "64",
        &["--lidar-rate", "7", tilt[0], tilt[1]],
    );
    let map = dir.join("campus.kfmap");
    // Shipped settings: the map is levelled by the IMU's gravity, and `kfmap localize`
    // moves the replayed run's ground truth into that frame (T_map_input from Status).
    bake_dataset(&mapped, &map);
    let prefix = Prefix::new("campus");
    let _server = Server::start(&map, "campus", &prefix.0, &[]);
    let (client_tum, server_tum) = (dir.join("client.tum"), dir.join("server.tum"));
    let (client_side, client_scans) = localize_with_lines(&replayed, &prefix.0, &client_tum, &[]);
    let (server_side, server_scans) =
        localize_with_lines(&replayed, &prefix.0, &server_tum, &["--server-side"]);
    println!("client-side: {client_side}\nserver-side: {server_side}");
    let a = read_trajectory(&client_tum).unwrap().poses;
    let b = read_trajectory(&server_tum).unwrap().poses;
    assert_eq!(a.len(), 70);
    let truth = truth_in_map(&replayed, "campus", &prefix);
    // The levelling a user reads (`kfmap status --json`, `kfmap inspect --json`) is the
    // one the truth was moved by, and it undoes the simulator's 2 / -3 deg tilt.
    let levelling = map_from_input("campus", &prefix.0);
    for printed in [
        common::json(&common::kfmap(&[
            "status",
            "--map-name",
            "campus",
            "--json",
            "--iceoryx-prefix",
            &prefix.0,
        ])),
        common::json(&common::kfmap(&[
            "inspect",
            map.to_str().unwrap(),
            "--json",
        ])),
    ] {
        let v: Vec<f64> = serde_json::from_value(printed["map_from_input"].clone()).unwrap();
        let printed = pose_from_xyz_quat(v.try_into().unwrap()).unwrap();
        assert!((printed.inverse() * levelling).rotation.angle() < 1e-12);
    }
    let (roll, pitch, yaw) = levelling.rotation.euler_angles();
    assert!(
        (roll.to_degrees() - 2.0).abs() < 0.1
            && (pitch.to_degrees() + 3.0).abs() < 0.1
            && yaw.abs() < 1e-9,
        "levelling roll {roll}, pitch {pitch}, yaw {yaw} rad"
    );
    for (side, s, poses) in [("client", &client_side, &a), ("server", &server_side, &b)] {
        assert_eq!(s["failed"], 0);
        let (rms, max) = rms_and_max_m(&pose_errors(poses, &truth));
        println!("{side}-side: RMS {rms:.4} m, max {max:.4} m from the simulator's truth");
        assert!(rms < 0.05, "{side}-side: RMS {rms} m");
    }
    for (i, (p, q)) in a.iter().zip(&b).enumerate() {
        let d = p.inverse() * q;
        assert!(
            d.translation.vector.norm() < 1e-3 && d.rotation.angle().to_degrees() < 0.01,
            "scan {i}: {d}"
        );
    }
    // The published covariance is calibrated: the errors' NEES against it is near 3
    // per group (DESIGN #covariance; measured 5.11 rotation, 4.76 position here,
    // rotation 3.41 while the heading was floored at 0.01 deg, the heading erring 5.8 mdeg
    // RMS against a sandwich of 4.1 on this drive, along with its along-track; the
    // registration's Hessian alone gave 17 000 and 330 on a like campus run). Client
    // and server publish the same covariance.
    let trace = |scan: &serde_json::Value| -> f64 {
        let c: Vec<f64> = serde_json::from_value(scan["covariance"].clone()).unwrap();
        (0..6).map(|i| c[i * 7]).sum()
    };
    let apart = client_scans
        .iter()
        .zip(&server_scans)
        .map(|(c, s)| (trace(c) / trace(s) - 1.0).abs())
        .fold(0.0, f64::max);
    println!("client- and server-side covariance traces at most {apart:.4} apart (relative)");
    assert!(apart < 0.02, "{apart}");
    for (side, scans) in [("client", &client_scans), ("server", &server_scans)] {
        assert_nees(
            &format!("{side}-side"),
            scans,
            &truth,
            60,
            3.5..7.0,
            3.3..6.5,
        );
    }

    // Oracle for the served gravity: the same pool fed in process with the same
    // windows (as they cross the wire), poses (the client's, read back from its
    // trajectory file) and stamps; and the simulator's tilt, in the levelled map.
    let scans = find_scans(&replayed).unwrap();
    let stamps = dataset_poses(&replayed, &scans).unwrap().unwrap().stamps;
    let imu = read_imu(&replayed.join("imu.csv")).unwrap();
    let mut live = LiveGravity::new(GravityParams::default()).unwrap();
    for (i, &t) in stamps.iter().enumerate() {
        let start = if i == 0 {
            f64::NEG_INFINITY
        } else {
            stamps[i - 1]
        };
        let window: Vec<_> = imu
            .iter()
            .filter(|s| s.t > start && s.t <= t)
            .copied()
            .collect();
        if !window.is_empty() {
            // Samples cross the wire as f32 offsets from the window's first time.
            let t0 = window[0].t;
            let sent = window
                .iter()
                .map(|s| kfmap_geometry::imu::ImuSample {
                    t: t0 + (s.t - t0) as f32 as f64,
                    acc: s.acc.map(|x| x as f32 as f64),
                    gyro: s.gyro.map(|x| x as f32 as f64),
                })
                .collect();
            live.add_window(i as u64, ImuWindow::new(sent), a[i], Some(t));
        }
    }
    let expected = live.answer();
    let expected_g = expected.correction.unwrap().estimate.g;
    let got = &client_side["gravity"];
    let served: Vec<f64> = serde_json::from_value(got["vector"].clone()).unwrap();
    let served = nalgebra::Vector3::new(served[0], served[1], served[2]);
    let map_from_input = map_from_input("campus", &prefix.0);
    let true_up = map_from_input.rotation * -gravity_in_map(2f64.to_radians(), -3f64.to_radians());
    let residual = served.angle(&true_up).to_degrees();
    println!(
        "gravity over IPC {} deg from the in-process pool, {residual:.4} deg from the truth; {got}",
        served.angle(&expected_g).to_degrees()
    );
    // The trajectory file rounds poses to 1e-9 m and 1e-12 in the quaternion.
    assert!(served.angle(&expected_g).to_degrees() < 1e-6);
    assert_eq!(got["members"], expected.members);
    assert_eq!(got["compensated"], true, "every member motion-compensated");
    assert_eq!(got["compensated_members"], expected.members);
    assert!(residual < 0.1, "{residual} deg");
    assert!(got["accel_bias_mps2"].is_array());

    // `kfmap status` lists each session's pool: this process's windows, as it was told.
    let mut client = Client::connect("campus", client_options(&prefix)).unwrap();
    let mut last = None;
    for (i, &t) in stamps.iter().enumerate().skip(1) {
        let window: Vec<_> = imu
            .iter()
            .filter(|s| s.t > stamps[i - 1] && s.t <= t)
            .copied()
            .collect();
        last = Some(
            client
                .push_imu_window(i as u64, &a[i], Some(t), &window)
                .unwrap(),
        );
    }
    let last = last.unwrap();
    let status = client.status().unwrap();
    let mine: Vec<_> = status
        .session_gravity
        .iter()
        .filter(|g| g.pool.members == last.members && g.pool.gravity.is_some())
        .collect();
    println!("status: {:?}", status.session_gravity);
    assert_eq!(mine.len(), 1, "{:?}", status.session_gravity);
    // The status record carries no sigma; its correction is rebuilt from roll and pitch.
    let listed = mine[0].pool;
    assert_eq!(
        listed,
        kfmap_client::GravityAnswer {
            accel_bias_sigma_mps2: None,
            correction: listed.correction,
            ..last
        }
    );
    let quaternion = |q: [f64; 4]| {
        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2]))
    };
    assert!(quaternion(listed.correction).angle_to(&quaternion(last.correction)) < 1e-9);
}

/// A pose farther than this from the truth is wrong (as `kfmap localize` counts it),
/// metres.
const WRONG_M: f64 = 0.5;

/// `raw` with every scan's per-point times dropped, as a driver that sends none would
/// deliver it (x y z and view directions kept; the simulator's poses beside it).
fn without_point_times(raw: &Path, out: &Path) {
    std::fs::create_dir_all(out.join("scans")).unwrap();
    for scan in find_scans(raw).unwrap() {
        let mut cloud = read_cloud(&scan, &ReadOptions::default()).unwrap().cloud;
        assert!(cloud.time.take().is_some(), "{} has times", scan.display());
        let name = scan.file_name().unwrap();
        write_cloud(
            &out.join("scans").join(name),
            &cloud,
            CloudFormat::Pcd(PcdData::Binary),
        )
        .unwrap();
    }
    std::fs::copy(raw.join("poses_gt.txt"), out.join("poses_gt.txt")).unwrap();
}

/// Deskew and the gyro in localization: a raw (motion-distorted, per-point times)
/// courtyard drive at 4 m/s and 7 Hz, replayed against the map of a deskewed drive at
/// 10 Hz. The oracle is the simulator's pose at each scan's stamp, every error computed
/// here from the reported poses. Measured 2026-12-03 (2 cores): neither RMS 10.3 m, 19
/// lost and 2 scans over 0.5 m reported ok (the tracker loses the place); deskew alone
/// 0.112 m (max 0.680 m, 2 lost); deskew and gyro 0.016 m (max 0.079 m), none lost. The
/// same scans without their per-point times, timed by azimuth (`--deskew azimuth`, the
/// simulator's sweep given by `--bake-config`), deskew as the recorded times do: 0.112 m,
/// max 0.680 m, as with the recorded times.
#[test]
fn a_raw_drive_is_deskewed_and_turned_by_the_gyro() {
    let dir = temp_dir("raw_drive");
    let (mapped, raw) = (dir.join("mapped"), dir.join("raw"));
    simulate(&mapped, "courtyard", "12", "32", &["--speed", "4"]);
    simulate(
        &raw,
        "courtyard",
        "12",
        "32",
        &["--speed", "4", "--raw", "--lidar-rate", "7", "--seed", "5"],
    );
    let map = dir.join("courtyard.kfmap");
    bake_dataset(&mapped, &map);
    let prefix = Prefix::new("raw_drive");
    let _server = Server::start(&map, "campus", &prefix.0, &[]);
    let out = dir.join("replay.tum");
    let truth = truth_in_map(&raw, "campus", &prefix);
    // (RMS m, max m, lost, wrong poses reported ok)
    let run = |extra: &[&str]| {
        let lines = localize_lines(&raw, &prefix.0, &out, extra);
        let poses: Vec<Pose> = lines.iter().map(|l| l.pose).collect();
        let errors = pose_errors(&poses, &truth);
        let (rms, max) = rms_and_max_m(&errors);
        let lost = lines.iter().filter(|l| l.status == "lost").count();
        let wrong_ok = lines
            .iter()
            .zip(&errors)
            .filter(|(l, e)| l.status == "ok" && e.0 > WRONG_M)
            .count();
        let result = (rms, max, lost, wrong_ok);
        println!("{extra:?}: RMS {rms:.4} m, max {max:.3} m, {lost} lost, {wrong_ok} wrong ok");
        result
    };
    let neither = run(&["--deskew", "off", "--no-imu"]);
    let deskewed = run(&["--no-imu"]);
    let both = run(&[]);
    let server_side = run(&["--server-side"]);
    assert!(deskewed.0 * 2.0 < neither.0, "{deskewed:?} vs {neither:?}");
    // Timeless scans timed by azimuth: the simulator's sensor turns counter-clockwise
    // from +X in one sweep per scan (7 Hz), stamped at the sweep's start.
    let timeless = dir.join("raw-timeless");
    without_point_times(&raw, &timeless);
    let sweep = dir.join("sweep.toml");
    std::fs::write(
        &sweep,
        "[build.odometry.sweep]\nseconds = 0.14285714\ndirection = \"counter-clockwise\"\n\
         start-deg = 0.0\nstamp-deg = 0.0\n",
    )
    .unwrap();
    let lines = localize_lines(
        &timeless,
        &prefix.0,
        &out,
        &[
            "--no-imu",
            "--deskew",
            "azimuth",
            "--bake-config",
            sweep.to_str().unwrap(),
        ],
    );
    let poses: Vec<Pose> = lines.iter().map(|l| l.pose).collect();
    let (azimuth_rms, azimuth_max) = rms_and_max_m(&pose_errors(&poses, &truth));
    println!("timeless, --deskew azimuth: RMS {azimuth_rms:.4} m, max {azimuth_max:.3} m");
    assert!(
        azimuth_rms <= 1.2 * deskewed.0 + 0.01 && azimuth_rms * 2.0 < neither.0,
        "azimuth {azimuth_rms} m, recorded times {deskewed:?}, neither {neither:?}"
    );
    for result in [both, server_side] {
        assert!(
            result.0 < 0.03 && result.0 * 5.0 < deskewed.0 && result.1 < 0.15,
            "{result:?} vs deskew alone {deskewed:?}"
        );
        assert_eq!((result.2, result.3), (0, 0), "none lost, none wrong");
    }
}

fn client_options(prefix: &Prefix) -> ClientOptions {
    ClientOptions {
        iceoryx_prefix: Some(prefix.0.clone()),
        ..ClientOptions::default()
    }
}

/// Tracking never wanders, through `kfmap localize` with no start pose as a
/// user runs it: the campus, 20 s at 10 Hz, seed 5, baked at its true poses, and
/// another recording of the same world and route (the LiDAR at 7 Hz: no replayed scan is
/// one the map was built from) replayed against it. Every scan is relocalized or
/// tracked; the test takes the poses from the written trajectory and the statuses from
/// `--json-lines`, and the truth from the simulator (`poses_gt.txt` in the map frame).
/// Measured, client- and server-side: first `ok` at the second scan (0.14 s), every scan
/// from 2 s on within 8 mm, one `degraded` scan (the first), no `ok` scan off the truth.
/// Bounds: first `ok` within 0.5 s, from 2 s on within 0.03 m, at most 3 `degraded`
/// scans in a row, no `ok` scan off by 0.3 m.
#[test]
fn a_run_with_no_start_is_found_and_never_wanders() {
    let dir = temp_dir("no-start");
    let mapped = dir.join("campus-map");
    simulate(&mapped, "campus", "20", "64", &["--seed", "5"]);
    let map = dir.join("campus.kfmap");
    bake_dataset(&mapped, &map);
    // Another recording of the same world and route: the LiDAR at 7 Hz, so no replayed
    // scan is one the map was built from.
    let run = dir.join("campus");
    simulate(
        &run,
        "campus",
        "20",
        "64",
        &["--seed", "5", "--lidar-rate", "7"],
    );
    let prefix = Prefix::new("no-start");
    let _server = Server::start(&map, "nostart", &prefix.0, &[]);
    let truth = truth_in_map(&run, "nostart", &prefix);
    let stamps = read_trajectory(&run.join("poses_gt.txt"))
        .unwrap()
        .stamps
        .unwrap();
    for side in ["client", "server"] {
        let out = dir.join(format!("{side}.tum"));
        let mut extra = vec!["--out", out.to_str().unwrap()];
        if side == "server" {
            extra.push("--server-side");
        }
        let statuses: Vec<String> = replay_json_lines(&run, "nostart", &prefix, &extra)
            .iter()
            .map(|v| v["status"].as_str().unwrap().to_string())
            .collect();
        let poses = read_trajectory(&out).unwrap().poses;
        assert_eq!(poses.len(), truth.len());
        assert_eq!(statuses.len(), truth.len());
        let errors: Vec<f64> = pose_errors(&poses, &truth).iter().map(|e| e.0).collect();
        let since = |k: usize| stamps[k] - stamps[0];
        let first_ok = statuses.iter().position(|s| s == "ok").map(since);
        let late_max = (0..errors.len())
            .filter(|&k| since(k) >= 2.0)
            .map(|k| errors[k])
            .fold(0.0, f64::max);
        let mut longest_degraded = 0;
        let mut run_length = 0;
        for s in &statuses {
            run_length = if s == "degraded" { run_length + 1 } else { 0 };
            longest_degraded = longest_degraded.max(run_length);
        }
        let wrong_ok = (0..errors.len())
            .filter(|&k| statuses[k] == "ok" && errors[k] > 0.3)
            .count();
        println!(
            "{side}-side, no start: first ok at {first_ok:?} s, max error from 2 s {late_max:.3} m, longest degraded run {longest_degraded}, ok scans off the truth {wrong_ok}; statuses {}",
            statuses.iter().map(|s| &s[..1]).collect::<String>()
        );
        assert!(first_ok.is_some_and(|t| t <= 0.5), "{side}: {first_ok:?}");
        assert!(late_max <= 0.03, "{side}: {late_max} m");
        assert!(longest_degraded <= 3, "{side}: {longest_degraded}");
        assert_eq!(wrong_ok, 0, "{side}");
    }
}

/// `kfmap localize --json-lines` of `dataset` against the map served as `name`, with no
/// start pose unless `extra` (more arguments) gives one: each scan's line, the summary
/// dropped.
fn replay_json_lines(
    dataset: &Path,
    name: &str,
    prefix: &Prefix,
    extra: &[&str],
) -> Vec<serde_json::Value> {
    let mut command = Command::new(kfmap_bin());
    command
        .args([
            "localize",
            "--map-name",
            name,
            "--rate",
            "0",
            "--json-lines",
        ])
        .args(["--timeout", "60", "--iceoryx-prefix", &prefix.0])
        .arg("--dataset")
        .arg(dataset)
        .args(extra)
        .stderr(Stdio::piped());
    String::from_utf8(common::succeeded(&mut command).stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v.get("index").is_some())
        .collect()
}

/// A pose as `--json-lines` writes it (`[x, y, z, qx, qy, qz, qw]`).
fn pose_of(v: &serde_json::Value) -> Pose {
    let pose: Vec<f64> = serde_json::from_value(v.clone()).unwrap();
    pose_from_xyz_quat(pose.try_into().unwrap()).unwrap()
}

/// The map of a later-recording test: 12 s of `preset` at seed 41 (the map's day)
/// baked at its true poses without its IMU log, served as `name` for as long as the
/// returned server lives.
fn serve_the_map_day(dir: &Path, preset: &str, name: &str) -> (Prefix, Server) {
    let mapped = dir.join("map-day");
    simulate(&mapped, preset, "12", "64", &["--seed", "41"]);
    std::fs::remove_file(mapped.join("imu.csv")).unwrap();
    let map = dir.join(format!("{preset}.kfmap"));
    bake_dataset(&mapped, &map);
    let prefix = Prefix::new(name);
    let server = Server::start(&map, name, &prefix.0, &[]);
    (prefix, server)
}

/// Never confidently wrong on a later recording of a mapped site. The map: 12 s of the
/// courtyard (seed 41) baked at its true poses, without its IMU log. The runs: the same
/// walls and route recorded again with the clutter moved (seeds 42 and 43), replayed
/// with no start pose, with their IMU logs and (seed 42) without (and seed 44 from its
/// true start, past the end of the map's route: below), as a user would
/// (`kfmap localize`). The
/// courtyard has a twin turned 90 degrees (the same square of walls; only wall heights,
/// doors and the thin wall differ), which relocalization alone cannot tell apart: the
/// tracker must keep both places and decide on the scans that follow. Oracles: the
/// simulator's poses (`poses_gt.txt` in the map frame); the test computes every error.
/// Targets (measured 0 wrong, 96 % right in each run, the first right `ok` at 0.5 s;
/// with the explained share on the 3 active keyframes instead of the 8 around the
/// place: 72 % / 77 %, 3.3 s / 2.8 s): no `ok` scan off the truth by 0.5 m or 5 deg; at
/// least 90 % of the scans `ok` and right; the first within 1 s; while undecided the
/// right place is among the hypotheses reported.
#[test]
fn a_later_recording_with_moved_clutter_is_never_confidently_wrong() {
    let dir = temp_dir("later-recording");
    let (prefix, _server) = serve_the_map_day(&dir, "courtyard", "later");
    // (seed, with the IMU log): the IMU's tilt changes what relocalization proposes.
    for (seed, imu) in [("42", true), ("42", false), ("43", true)] {
        let recorded = dir.join(format!("run-{seed}"));
        if !recorded.exists() {
            simulate(&recorded, "courtyard", "12", "64", &["--seed", seed]);
        }
        let run = if imu {
            recorded.clone()
        } else {
            // The same scans and stamps without the IMU log beside them.
            let bare = dir.join(format!("run-{seed}-no-imu"));
            std::fs::create_dir_all(&bare).unwrap();
            std::os::unix::fs::symlink(recorded.join("scans"), bare.join("scans")).unwrap();
            std::fs::copy(recorded.join("poses_gt.txt"), bare.join("poses_gt.txt")).unwrap();
            bare
        };
        let seed = format!("{seed}{}", if imu { "" } else { " without IMU" });
        let stamps = read_trajectory(&run.join("poses_gt.txt"))
            .unwrap()
            .stamps
            .unwrap();
        let replayed = replay_against_truth(&run, "later", &prefix, &[]);
        let (scans, truth) = (&replayed.scans, &replayed.truth);
        let wrong_ok = replayed.wrong.len();
        let right_ok = replayed.right_ok.len();
        let first = replayed.right_ok.first().map(|&k| stamps[k] - stamps[0]);
        // Every undecided scan keeps the right place among its hypotheses.
        let mut undecided = 0;
        for (k, scan) in scans.iter().enumerate() {
            let hypotheses = scan["hypotheses"].as_array().unwrap();
            if hypotheses.len() < 2 {
                continue;
            }
            undecided += 1;
            assert_eq!(scan["status"], "lost", "seed {seed} scan {k}");
            assert!(
                scan["reasons"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|r| r == "ambiguous"),
                "seed {seed} scan {k}"
            );
            let nearest = hypotheses
                .iter()
                .map(|h| pose_errors(&[pose_of(&h["pose"])], &truth[k..=k])[0].0)
                .fold(f64::INFINITY, f64::min);
            assert!(
                nearest <= 0.5,
                "seed {seed} scan {k}: nearest hypothesis {nearest} m"
            );
            // ... and the look-alike is the courtyard turned 90 degrees about its centre
            // (the origin): measured in every undecided scan of the three runs
            // (DESIGN, "The courtyard's first 2.4 s").
            let t = truth[k].translation.vector;
            let turned = nalgebra::Vector3::new(-t.y, t.x, t.z);
            assert!(
                hypotheses
                    .iter()
                    .any(|h| (pose_of(&h["pose"]).translation.vector - turned).norm() <= 1.0),
                "seed {seed} scan {k}: no hypothesis at the turned twin"
            );
        }
        let share = right_ok as f64 / scans.len() as f64;
        println!(
            "courtyard seed {seed} on the map of seed 41, no start: {wrong_ok} ok scans wrong, {:.0} % ok and right, first at {first:?} s, {undecided} scans undecided",
            share * 100.0
        );
        // The covariance errs on the careful side on this site (its same world too,
        // 1.52; the moved clutter's pairs account for about a third of it, DESIGN
        // #covariance): measured 1.65-1.77 rotation (1.43-1.56 while the
        // heading was floored at 0.01 deg), 0.81-0.93 position (1.48-1.65,
        // 0.82-1.03 when fewer scans were `ok`); the registration's Hessian alone gave
        // 509 / 55.
        assert_nees(
            &format!("courtyard seed {seed}"),
            scans,
            truth,
            80,
            1.1..2.5,
            0.55..1.45,
        );
        assert_eq!(wrong_ok, 0, "seed {seed}");
        assert!(share >= 0.9, "seed {seed}: {share}");
        assert!(first.is_some_and(|t| t <= 1.0), "seed {seed}: {first:?}");
        assert!(undecided > 0, "seed {seed}: the twin was never in doubt");
    }
    // Seed 44 from its true start for 21.5 s, the last 9.5 s beyond the map's route: the
    // periodic check puts the place in doubt against the twin turned 180 deg, and the
    // places are decided on a scan that does not register at the right one. Before the
    // motion was seeded at a place so decided, the next scan was predicted at the drive's
    // start, and the twin, 27 m off, was tracked `ok` (8 scans here, 69 over 30 s);
    // measured now 0, 92 % `ok` and right.
    let (replayed, share) = replayed_from_true_start(
        &dir,
        ("courtyard", "21.5", "44", "10", true),
        "later",
        &prefix,
    );
    assert!(replayed.wrong.is_empty(), "seed 44: {:?}", replayed.wrong);
    assert!(share >= 0.85, "seed 44: {share}");
}

/// A street tracked from its true start on a later recording in which every building
/// changed width and height (the facades' line, the kerb poles and the route stay):
/// where the scans pin the pose only weakly along the street, the tracker must not call
/// a slide `ok`. The map: 12 s of the street (seed 41) baked at its true poses, without
/// its IMU log; the runs: seeds 43, 42 and 44, `kfmap localize --initial-from-ground-truth`.
/// Oracles: the simulator's poses, every error computed here. Before the slide check
/// (`unpinned`), seed 43 had 2 `ok` scans 90-97 m off and seed 42 had 5 (a slide to
/// 0.64 m, then 8-75 m on look-alikes), and seed 42 one at 34 m while the hypotheses
/// jumped to a place 25 m along that explains the changed street better than the right
/// one; measured now 0 and 0 (the tracked place holds), with 28 % and 41 % of the scans
/// `ok` and right. Seed 42 replayed with no start: before `confirm-after-unpinned`, 3
/// scans `ok` 25 m off (a look-alike decided, then a slide that ended on a locally
/// pinned scan); now 0. Seed 44: a look-alike 2.2-2.5 m along the road; seed 47 with
/// no start: one 104 m along; seed 45 with no start and no IMU log: one 121 m along
/// (below).
#[test]
fn a_street_whose_buildings_changed_is_not_called_ok_while_sliding_along_it() {
    let dir = temp_dir("street-later");
    let (prefix, _server) = serve_the_map_day(&dir, "street", "street");
    // (seed, wrong `ok` scans at most, share `ok` and right at least, position NEES)
    for (seed, max_wrong, min_right, position_nees) in
        [("43", 0, 0.18, 0.7..1.6), ("42", 0, 0.40, 2.3..4.8)]
    {
        let (replayed, share) =
            replayed_from_true_start(&dir, ("street", "12", seed, "10", true), "street", &prefix);
        let (scans, wrong) = (&replayed.scans, &replayed.wrong);
        // Along the road the registration cannot see how far the changed buildings'
        // ends pull the pose; the slide probe widens the covariance there (DESIGN
        // #covariance). Measured NEES 1.10 / 3.40 position, 1.06 / 1.26 rotation
        // (seeds 43 / 42; 1.37 / 0.90 position for seed 43 before its slides were refused
        // as jumps; rotation 0.69 / 0.55 while the heading was floored at 0.01 deg, which
        // the rotation's lower bound catches); 28 position without the widening.
        assert!(wrong.len() <= max_wrong, "seed {seed}: {wrong:?}");
        assert!(share >= min_right, "seed {seed}: {share}");
        assert_nees(
            &format!("street seed {seed}"),
            scans,
            &replayed.truth,
            20,
            0.8..1.8,
            position_nees,
        );
        // The checks engaged: a changed street is not pinned everywhere (seed 43's
        // slides are now refused jumps, before they were unpinned scans).
        let weak = with_reason(scans, "degraded", "unpinned") + refused_jumps(scans);
        assert!(weak > 0, "seed {seed}");
    }
    // Seed 44's street holds a place 2.0-2.5 m along the road that the registration
    // slides to from the right prediction every few scans, and fits as well (better,
    // after scan 58). Before the acceleration bound (`--max-acceleration`) the
    // correction gate learned from the first jump and let the next ones through: in
    // its first 4 s 18 scans `ok` 2.5-6.4 m off. With 1 g as the bound, 4 scans of its
    // 12 s were still `ok` 2.2-2.3 m off, adopted after six refused scans, when 0.6 s
    // of 1 g reaches the look-alike; with the acceleration its IMU log measured
    // (docs/DESIGN.md#tracking) measured now 0, 17 % `ok` and right (the same 20 scans).
    let (replayed, share) =
        replayed_from_true_start(&dir, ("street", "12", "44", "10", true), "street", &prefix);
    let refused = refused_jumps(&replayed.scans);
    println!("street seed 44: {refused} jumps refused");
    assert!(replayed.wrong.is_empty(), "seed 44: {:?}", replayed.wrong);
    assert!(share >= 0.15, "seed 44: {share}");
    assert!(refused > 0, "seed 44: no jump refused");
    // Without its IMU log only 1 g bounds the jump, which let the look-alike through
    // after 0.6 s (8 scans `ok` 2.2-2.5 m off); the scans' own motion, registered scan
    // to scan while the map's answers are refused, keeps it out (measured 0, 17 %).
    std::fs::remove_file(dir.join("run-44").join("imu.csv")).unwrap();
    let without_imu = replay_against_truth(
        &dir.join("run-44"),
        "street",
        &prefix,
        &["--initial-from-ground-truth"],
    );
    let share = without_imu.share_right();
    println!(
        "street seed 44 without its IMU log: wrong ok {:?}, {:.0} % ok and right",
        without_imu.wrong,
        share * 100.0
    );
    assert!(
        without_imu.wrong.is_empty(),
        "seed 44 without IMU: {:?}",
        without_imu.wrong
    );
    assert!(share >= 0.15, "seed 44 without IMU: {share}");
    let wrong = replay_against_truth(&dir.join("run-42"), "street", &prefix, &[]).wrong;
    println!("street seed 42 on the map of seed 41, no start: wrong ok {wrong:?}");
    assert!(wrong.is_empty(), "seed 42 with no start: {wrong:?}");
    // Seed 47 with no start (its first 4 s) starts at the map's end of the street,
    // which scores below look-alikes in its middle: no relocalization proposes the
    // right place, and the places in doubt came down to one 104 m along, `ok` for 7
    // scans (slide loss 0.056-0.075, the right place's 0.15-0.24) before a place
    // decided from doubt had to be pinned well (`ok-pinned-after-doubt`); measured
    // now 0, the look-alike `degraded` (`unpinned`).
    let run = dir.join("run-47");
    simulate(&run, "street", "4", "64", &["--seed", "47"]);
    let replayed = replay_against_truth(&run, "street", &prefix, &[]);
    println!(
        "street seed 47, no start, 4 s: wrong ok {:?}",
        replayed.wrong
    );
    assert!(
        replayed.wrong.is_empty(),
        "seed 47 with no start: {:?}",
        replayed.wrong
    );
    // The rule's premise, against the truth: where the adopted pose is the look-alike
    // (over 0.5 m off), the scans hold it loosely (measured 0.005-0.072, the right
    // place 0.13-0.24 from the true start).
    let poses: Vec<Pose> = replayed.scans.iter().map(|s| pose_of(&s["pose"])).collect();
    let errors = pose_errors(&poses, &replayed.truth);
    let loose: Vec<f64> = (0..poses.len())
        .filter(|&k| errors[k].0 > 0.5)
        .filter_map(|k| replayed.scans[k]["slide_loss"].as_f64())
        .collect();
    println!("street seed 47: slide losses off the truth {loose:?}");
    assert!(
        !loose.is_empty(),
        "seed 47: the look-alike was never adopted"
    );
    assert!(loose.iter().all(|&l| l < 0.1), "seed 47: {loose:?}");
    // Seed 45's first 4 s with no start and without its IMU log: the places in doubt are
    // decided for a look-alike 121 m along (the map's far end), still doubted; the
    // periodic check then doubts it against the right place, and when the scans turn
    // back to the look-alike (the place the tracker held), that place kept the standing
    // of a confirmed one: one scan `ok` 121 m off. It keeps its doubt now (measured 0
    // wrong).
    let run = dir.join("run-45");
    simulate(&run, "street", "4", "64", &["--seed", "45"]);
    std::fs::remove_file(run.join("imu.csv")).unwrap();
    let wrong = replay_against_truth(&run, "street", &prefix, &[]).wrong;
    println!("street seed 45, no start, no IMU log, 4 s: wrong ok {wrong:?}");
    assert!(wrong.is_empty(), "seed 45 with no start: {wrong:?}");
    // Seed 52's first 5 s from the true start without its IMU log: its changed
    // buildings pull the map's best fit 1.06 m along the road from 2.8 s on, where the
    // slide probe and relocalization both accept it; only the scans' own motion
    // refuses it. The chain's allowance grew by 5 % of the distance reckoned, so after
    // 14 m it reached the look-alike (3 scans `ok` 1.08 m off); now it grows by what
    // each step may have got wrong (2 % of it and how far it lay from its guess), and
    // each scan of a chain is judged (measured 0 wrong, 26 of 50 `ok` and right).
    let (replayed, share) =
        replayed_from_true_start(&dir, ("street", "5", "52", "10", false), "street", &prefix);
    assert!(replayed.wrong.is_empty(), "seed 52: {:?}", replayed.wrong);
    assert!(share >= 0.45, "seed 52: {share}");
    // Seed 56's first 6 s at 7 Hz from the true start, with its IMU log: from 2.3 s on
    // the map's best fit slides 2-6 m along the road and the scans' own motion refuses
    // it, right (the reckoned poses 0.01-0.03 m off). A chain lived 3 s past the last
    // adopted scan; then the acceleration bound alone judged, about 25 m wide, and
    // let a registration 9.8 m along through: `ok` at 5.4 s. A chain now lives while
    // its scans register (measured 0 wrong, 16 of 42 `ok` and right; before 1 wrong).
    let (replayed, share) =
        replayed_from_true_start(&dir, ("street", "6", "56", "7", true), "street", &prefix);
    assert!(replayed.wrong.is_empty(), "seed 56: {:?}", replayed.wrong);
    assert!(share >= 0.35, "seed 56: {share}");
}

/// `seconds` of `preset` at `seed` (64 beams, `rate_hz` LiDAR rate) simulated under
/// `dir` (its IMU log removed unless `with_imu`) and replayed from its true start
/// against the map served as `name`, with the share of its scans `ok` and right.
fn replayed_from_true_start(
    dir: &Path,
    (preset, seconds, seed, rate_hz, with_imu): (&str, &str, &str, &str, bool),
    name: &str,
    prefix: &Prefix,
) -> (Replayed, f64) {
    let run = dir.join(format!("run-{seed}"));
    simulate(
        &run,
        preset,
        seconds,
        "64",
        &["--seed", seed, "--lidar-rate", rate_hz],
    );
    if !with_imu {
        std::fs::remove_file(run.join("imu.csv")).unwrap();
    }
    let replayed = replay_against_truth(&run, name, prefix, &["--initial-from-ground-truth"]);
    let share = replayed.share_right();
    println!(
        "{preset} seed {seed} on the map of seed 41 from its true start, {seconds} s at {rate_hz} Hz{}: wrong ok {:?}, {:.0} % ok and right",
        if with_imu { "" } else { ", no IMU log" },
        replayed.wrong,
        share * 100.0
    );
    (replayed, share)
}

/// The scans of `status` whose reasons hold `reason`.
fn with_reason(scans: &[serde_json::Value], status: &str, reason: &str) -> usize {
    scans
        .iter()
        .filter(|s| {
            s["status"] == status && s["reasons"].as_array().unwrap().iter().any(|r| r == reason)
        })
        .count()
}

/// The scans whose registration moved them farther than the motion allows, not adopted
/// (`lost`, `implausible`).
fn refused_jumps(scans: &[serde_json::Value]) -> usize {
    with_reason(scans, "lost", "implausible")
}

/// A later recording replayed against a served map, judged against the simulator's
/// truth (every error computed here).
struct Replayed {
    /// Each scan's `--json-lines` object.
    scans: Vec<serde_json::Value>,
    /// The simulator's poses in the map frame.
    truth: Vec<Pose>,
    /// The `ok` scans more than 0.5 m or 5 deg off the truth: (index, metres off).
    wrong: Vec<(usize, f64)>,
    /// The `ok` scans within both, in order.
    right_ok: Vec<usize>,
}

impl Replayed {
    /// The share of the scans `ok` and right.
    fn share_right(&self) -> f64 {
        self.right_ok.len() as f64 / self.scans.len() as f64
    }
}

/// Replays `run` against the map served as `name` with `extra` flags ([`Replayed`]).
fn replay_against_truth(run: &Path, name: &str, prefix: &Prefix, extra: &[&str]) -> Replayed {
    let truth = truth_in_map(run, name, prefix);
    let scans = replay_json_lines(run, name, prefix, extra);
    assert_eq!(scans.len(), truth.len());
    let poses: Vec<Pose> = scans.iter().map(|s| pose_of(&s["pose"])).collect();
    let errors = pose_errors(&poses, &truth);
    let right = |k: usize| errors[k].0 <= 0.5 && errors[k].1 <= 5.0;
    let ok: Vec<usize> = (0..scans.len())
        .filter(|&k| scans[k]["status"] == "ok")
        .collect();
    let wrong = ok
        .iter()
        .filter(|&&k| !right(k))
        .map(|&k| (k, errors[k].0))
        .collect();
    let right_ok = ok.into_iter().filter(|&k| right(k)).collect();
    Replayed {
        scans,
        truth,
        wrong,
        right_ok,
    }
}
