//! Localization that knows when it is wrong, over IPC with real processes: every scan's
//! reported pose is checked against an independent reference (the dataset's pose file,
//! read here), and no wrong pose may be reported `ok`.
//!
//! - Real data (`../shared/data/balm_os0`, handheld, 2 Hz, fast turns up to 48 deg
//!   between scans): the map of scans 0-115 at their reference poses, scans 116-176
//!   replayed by `kfmap localize` client-side and server-side, and every second scan of
//!   them (1 Hz).
//! - Simulated campus: a scan from elsewhere dropped into a drive comes back `lost`
//!   and the tracker recovers; a teleported prediction comes back `lost` from both
//!   sides.

use crate::common;

use std::path::Path;

use common::{Prefix, Server, bake_dataset, kfmap, linked_dataset, simulate, temp_dir};
use kfmap_bake::config::BakeConfig;
use kfmap_bake::dataset::{find_scans, load_raw_scan};
use kfmap_client::{Client, ClientOptions, LocalizeOptions};
use kfmap_geometry::geometry::{Pose, pose_from_xyz_quat, rotation_distance, translation_distance};
use kfmap_geometry::io::read_trajectory;
use kfmap_geometry::tracking::TrackingStatus;
use kfmap_protocol::ScanPayload;
use kfmap_testdata::require_test_data;

/// A pose farther than this from its reference is wrong (the bound), metres.
const WRONG_M: f64 = 0.5;

/// One `--json-lines` scan line.
#[derive(Debug)]
struct Line {
    index: usize,
    pose: Pose,
    status: String,
    fitness: f64,
}

/// `kfmap localize ... --json-lines`: the scan lines and the summary.
fn localize_lines(args: &[&str]) -> (Vec<Line>, serde_json::Value) {
    let (values, summary) = localize_values(args);
    let lines = values
        .iter()
        .map(|v| {
            let pose: Vec<f64> = serde_json::from_value(v["pose"].clone()).unwrap();
            Line {
                index: v["index"].as_u64().unwrap() as usize,
                pose: pose_from_xyz_quat(pose.try_into().unwrap()).unwrap(),
                status: v["status"].as_str().unwrap().to_string(),
                fitness: v["fitness"].as_f64().unwrap(),
            }
        })
        .collect();
    (lines, summary)
}

/// `kfmap localize ... --json-lines`: each scan's object and the summary.
fn localize_values(args: &[&str]) -> (Vec<serde_json::Value>, serde_json::Value) {
    let mut all = vec!["localize", "--rate", "0", "--json-lines"];
    all.extend_from_slice(args);
    let out = kfmap(&all);
    assert!(
        out.status.success(),
        "kfmap localize failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut values: Vec<serde_json::Value> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).expect("one JSON object per line"))
        .collect();
    let summary = values.pop().expect("a summary line");
    (values, summary)
}

/// Position (m) and rotation (deg) errors of each line against `reference[index]`.
fn errors(lines: &[Line], reference: &[Pose]) -> Vec<(f64, f64)> {
    lines
        .iter()
        .map(|l| {
            let r = &reference[l.index];
            (
                translation_distance(&l.pose, r),
                rotation_distance(&l.pose, r).to_degrees(),
            )
        })
        .collect()
}

/// The targets on one replay; returns the RMS position error.
fn assert_targets(what: &str, lines: &[Line], reference: &[Pose]) -> f64 {
    let errors = errors(lines, reference);
    for (l, (m, deg)) in lines.iter().zip(&errors) {
        println!(
            "{what} scan {}: {:>8} {:.3} m {:.2} deg (fitness {:.3})",
            l.index, l.status, m, deg, l.fitness
        );
    }
    let rms = (errors.iter().map(|e| e.0 * e.0).sum::<f64>() / errors.len() as f64).sqrt();
    let wrong_ok = lines
        .iter()
        .zip(&errors)
        .filter(|(l, e)| e.0 > WRONG_M && l.status == "ok")
        .count();
    println!("{what}: RMS {rms:.4} m, {wrong_ok} wrong poses reported ok");
    assert_eq!(
        wrong_ok, 0,
        "{what}: a pose off by more than {WRONG_M} m reported ok"
    );
    for (l, (m, deg)) in lines.iter().zip(&errors) {
        assert!(
            *m < 0.25 && *deg < 2.0,
            "{what} scan {}: {m} m, {deg} deg from the reference",
            l.index
        );
    }
    rms
}

/// The README's row for the revisit of balm_os0 tracked at 2 Hz: 61 ok, 0 lost (beside
/// RMS 0.060 m, asserted under 0.08 m, the target and 1.33 times the figure).
/// One scan of slack: at least 60 `ok`, none `lost`.
fn assert_claimed_statuses(what: &str, lines: &[Line]) {
    let count = |s: &str| lines.iter().filter(|l| l.status == s).count();
    let (ok, lost) = (count("ok"), count("lost"));
    println!("{what}: {ok} ok, {lost} lost of {}", lines.len());
    assert!(ok >= 60 && lost == 0, "{what}: {ok} ok, {lost} lost");
}

/// Issue targets on balm_os0 (map of scans 0-115 at their reference poses, scans
/// 116-176 replayed from the reference pose of 116): every scan within 0.25 m and 2
/// deg, RMS under 0.08 m (README: 0.060 m), no pose off by more than 0.5 m reported ok,
/// at least 60 of the 61 scans `ok` and none `lost` (README: 61 ok, 0 lost);
/// client-side and server-side alike. Every second scan (1 Hz, turns up to 54 deg
/// between scans) meets the same error bounds. With no start pose from every third
/// scan, no wrong pose is `ok`.
#[test]
fn balm_replay_is_accurate_and_reports_no_wrong_pose_ok() {
    let Some(balm) = require_test_data("balm_os0", "balm_replay") else {
        return;
    };
    let dir = temp_dir("balm-health");
    let scans = find_scans(&balm).unwrap();
    let pose_text = std::fs::read_to_string(balm.join("poses.txt")).unwrap();
    let pose_lines: Vec<&str> = pose_text.lines().collect();
    assert_eq!((scans.len(), pose_lines.len()), (177, 177));
    let map = common::fixtures::balm_first_pass_map(&balm);
    // The independent reference: the dataset's own pose file (no IMU: map frame =
    // dataset frame).
    let reference = read_trajectory(&balm.join("poses.txt")).unwrap().poses;
    let prefix = Prefix::new("balm");
    let _server = Server::start(&map, "balm", &prefix.0, &[]);
    let run = |dataset: &Path, scans: &str, extra: &[&str]| {
        let mut args = vec!["--map-name", "balm", "--iceoryx-prefix", &prefix.0];
        args.extend(["--dataset", dataset.to_str().unwrap(), "--scans", scans]);
        args.push("--initial-from-ground-truth");
        args.extend_from_slice(extra);
        localize_lines(&args)
    };

    let (client, summary) = run(&balm, "116..177", &[]);
    println!("client-side: {summary}");
    assert_eq!(client.len(), 61);
    assert_eq!(client[0].index, 116);
    let rms = assert_targets("client-side", &client, &reference);
    assert!(rms < 0.08, "client-side RMS {rms} m");
    assert_claimed_statuses("client-side", &client);
    let (server, summary) = run(&balm, "116..177", &["--server-side"]);
    println!("server-side: {summary}");
    let rms = assert_targets("server-side", &server, &reference);
    assert!(rms < 0.08, "server-side RMS {rms} m");
    assert_claimed_statuses("server-side", &server);
    // One algorithm on the same pairings: the same decisions, poses within 1 mm.
    for (a, b) in client.iter().zip(&server) {
        assert_eq!(a.status, b.status, "scan {}", a.index);
        assert!(
            translation_distance(&a.pose, &b.pose) < 1e-3,
            "scan {}",
            a.index
        );
    }

    let every_second: Vec<usize> = (116..177).step_by(2).collect();
    let odd = dir.join("every-second");
    linked_dataset(
        &odd,
        &every_second
            .iter()
            .map(|&i| scans[i].clone())
            .collect::<Vec<_>>(),
        &every_second
            .iter()
            .map(|&i| pose_lines[i])
            .collect::<Vec<_>>(),
    );
    let (lines, summary) = run(&odd, "0..", &[]);
    println!("every second scan: {summary}");
    let halved: Vec<Pose> = every_second.iter().map(|&i| reference[i]).collect();
    let rms = assert_targets("every second scan", &lines, &halved);
    assert!(rms < 0.08, "every second scan: RMS {rms} m");

    // No start pose, from every third scan of the revisit and from 141, 147 and 153 (6
    // scans each, as a robot switched on there): no wrong pose is ever `ok` (> 0.5 m or
    // 5 deg from the reference), and every start is `ok` and right within 3 scans
    // (measured: all 61 starts of the revisit but 176, a run of one scan). From 140, 141
    // and 146 a place along a corridor-like stretch, 4.7-15 m from the right one,
    // explains nearly as much of each scan but slides (`slide-scans`): it is dropped
    // at the second scan beside the right place, which the scans pin. From 147 and 153
    // the places are decided at the second scan and the third turns fast: predicted
    // from rest it was `implausible` (3.9 m beyond the 3 m gate) until the first scan
    // after a decision was predicted by scan-to-scan registration.
    let mut quick = 0;
    let starts: Vec<usize> = (116..176).step_by(3).chain([141, 147, 153]).collect();
    for &start in &starts {
        let scans = format!("{start}..{}", (start + 6).min(177));
        let (lines, _) = localize_lines(&[
            "--map-name",
            "balm",
            "--iceoryx-prefix",
            &prefix.0,
            "--dataset",
            balm.to_str().unwrap(),
            "--scans",
            &scans,
        ]);
        let errors = errors(&lines, &reference);
        let right = |k: usize| errors[k].0 <= WRONG_M && errors[k].1 <= 5.0;
        let ok = |k: usize| lines[k].status == "ok";
        let wrong: Vec<usize> = (0..lines.len())
            .filter(|&k| ok(k) && !right(k))
            .map(|k| lines[k].index)
            .collect();
        let first = (0..lines.len()).find(|&k| ok(k) && right(k));
        println!(
            "no start from scan {start}: first right ok at scan {first:?} of the run, wrong ok {wrong:?}"
        );
        assert!(
            wrong.is_empty(),
            "no start from scan {start}: wrong ok at {wrong:?}"
        );
        quick += usize::from(first.is_some_and(|k| k < 3));
    }
    println!(
        "no start: {quick} of {} starts ok and right within 3 scans",
        starts.len()
    );
    assert_eq!(quick, starts.len(), "starts ok and right within 3 scans");
}

/// A campus drive at 7 Hz against the map of another drive, with one scan replaced by
/// a scan from 5 s later (another place): that scan is `lost` (its pose is the
/// prediction, not a wrong registration), and the tracker recovers: the next scan is
/// adopted (`degraded` while recovering) and within 3 scans it is `ok` again. Every
/// other scan is within 5 cm of the ground truth.
#[test]
fn a_scan_from_elsewhere_is_lost_and_tracking_recovers() {
    let dir = temp_dir("elsewhere");
    let (mapped, replayed) = (dir.join("mapped"), dir.join("replayed"));
    simulate(&mapped, "campus", "10", "64", &[]);
    simulate(&replayed, "campus", "10", "64", &["--lidar-rate", "7"]);
    let map = dir.join("campus.kfmap");
    bake_dataset(&mapped, &map);
    let prefix = Prefix::new("elsewhere");
    let _server = Server::start(&map, "elsewhere", &prefix.0, &[]);

    let scans = find_scans(&replayed).unwrap();
    let pose_text = std::fs::read_to_string(replayed.join("poses_gt.txt")).unwrap();
    let pose_lines: Vec<&str> = pose_text.lines().filter(|l| !l.starts_with('#')).collect();
    let (swapped, from) = (30, 65);
    let mut linked = scans.clone();
    linked[swapped] = scans[from].clone();
    let dataset = dir.join("with-a-foreign-scan");
    linked_dataset(&dataset, &linked, &pose_lines);
    let truth = read_trajectory(&replayed.join("poses_gt.txt"))
        .unwrap()
        .poses;
    assert!(
        translation_distance(&truth[swapped], &truth[from]) > 10.0,
        "the foreign scan is from elsewhere"
    );

    let map_from_input = Client::connect("elsewhere", options(&prefix))
        .unwrap()
        .status()
        .unwrap()
        .map_from_input;
    let reference: Vec<Pose> = truth.iter().map(|p| map_from_input * p).collect();
    for side in [&[][..], &["--server-side"][..]] {
        let mut args = vec!["--map-name", "elsewhere", "--iceoryx-prefix", &prefix.0];
        args.extend(["--dataset", dataset.to_str().unwrap()]);
        // Tracking from a known start: the foreign scan must come back `lost` (without a
        // start the tracker would relocalize it, see tests/integration/relocalize.rs).
        args.push("--initial-from-ground-truth");
        args.extend_from_slice(side);
        let (lines, summary) = localize_lines(&args);
        println!("{side:?}: {summary}");
        let errors = errors(&lines, &reference);
        for (l, e) in lines.iter().zip(&errors).skip(swapped - 2).take(8) {
            println!(
                "scan {}: {} {:.3} m (fitness {:.3})",
                l.index, l.status, e.0, l.fitness
            );
        }
        assert_eq!(lines[swapped].status, "lost", "{side:?}: the foreign scan");
        assert_eq!(
            lines[swapped + 1].status,
            "degraded",
            "{side:?}: recovering"
        );
        assert!(
            lines[swapped + 1..=swapped + 3]
                .iter()
                .any(|l| l.status == "ok"),
            "{side:?}: no recovery within 3 scans"
        );
        for (l, e) in lines.iter().zip(&errors) {
            if l.index != swapped {
                assert!(l.status != "lost", "{side:?} scan {}", l.index);
                assert!(e.0 < 0.05, "{side:?} scan {}: {} m", l.index, e.0);
            }
        }
        // The lost scan reports the prediction: close to the truth on a smooth drive,
        // never the foreign scan's registration.
        assert!(
            errors[swapped].0 < WRONG_M,
            "{side:?}: {} m",
            errors[swapped].0
        );
    }

    // The library: a prediction teleported 8 m and 90 deg away, with the fit the
    // scans before had, comes back lost (its pose the prediction) from both sides.
    let mut client = Client::connect("elsewhere", options(&prefix)).unwrap();
    let cloud = load_raw_scan(&scans[10], &BakeConfig::default())
        .unwrap()
        .voxel_downsample(0.25)
        .unwrap();
    let scan = ScanPayload {
        points: &cloud.points,
        view_dirs: None,
        covariances: None,
    };
    let truth_10 = reference[10];
    let good = client
        .localize(&scan, &truth_10, &LocalizeOptions::default())
        .unwrap();
    assert_eq!(good.health.status, TrackingStatus::Ok);
    let teleported = truth_10
        * Pose::new(
            [8.0, 0.0, 0.0].into(),
            [0.0, 0.0, std::f64::consts::FRAC_PI_2].into(),
        );
    let expecting = LocalizeOptions {
        max_correction: Some(2.0),
        expected_inlier_ratio: Some(good.health.inlier_ratio),
        ..LocalizeOptions::default()
    };
    let server = client.localize(&scan, &teleported, &expecting).unwrap();
    let local = client
        .localize_client_side(&scan, &teleported, &expecting)
        .unwrap();
    for found in [&server, &local] {
        assert_eq!(
            found.health.status,
            TrackingStatus::Lost,
            "{:?}",
            found.health
        );
        // The prediction (through the wire's f64 round trip).
        assert!(translation_distance(&found.pose, &teleported) < 1e-9);
        assert!(rotation_distance(&found.pose, &teleported) < 1e-9);
    }
    assert_eq!(server.health.reasons, local.health.reasons);
}

fn options(prefix: &Prefix) -> ClientOptions {
    ClientOptions {
        iceoryx_prefix: Some(prefix.0.clone()),
        ..ClientOptions::default()
    }
}

/// `--scans` out of the dataset's range, or malformed, and
/// `--initial-from-ground-truth` without a pose file, are errors naming the flag (exit
/// code 2), found before any server is contacted.
#[test]
fn bad_scan_ranges_and_missing_ground_truth_are_named() {
    let dir = temp_dir("scan-range");
    let data = dir.join("data");
    simulate(&data, "courtyard", "0.5", "16", &[]);
    let count = find_scans(&data).unwrap().len();
    let run = |extra: &[&str]| {
        let mut args = vec!["localize", "--map-name", "nobody-serves-this"];
        args.extend(["--dataset", data.to_str().unwrap()]);
        args.extend_from_slice(extra);
        let out = kfmap(&args);
        assert_eq!(out.status.code(), Some(2), "{extra:?}");
        String::from_utf8(out.stderr).unwrap()
    };
    let too_far = format!("2..{}", count + 1);
    for bad in [too_far.as_str(), "3..3", "7..2", "1-4", "a..b"] {
        let err = run(&["--scans", bad]);
        assert!(err.contains("--scans"), "{bad}: {err}");
    }
    assert!(run(&["--scans", &too_far]).contains(&format!("has {count} scans")));
    std::fs::remove_file(data.join("poses_gt.txt")).unwrap();
    let err = run(&["--initial-from-ground-truth"]);
    assert!(
        err.contains("--initial-from-ground-truth") && err.contains("no pose file"),
        "{err}"
    );
}

/// The published covariance on a second sensor, hku2_avia (Livox Avia class, handheld,
/// no IMU log: the map frame is the pose file's): its odd scans replayed by `kfmap
/// localize --initial-from-ground-truth` against a map of its even ones, both at the
/// reference `kfmap bake --refine-only` makes of the whole sequence (the plane bundle
/// adjustment over every scan, another estimator than scan-to-map tracking; DESIGN
/// #covariance). The NEES is computed here from that reference. Measured 4.11
/// rotation, 2.91 position over 96 `ok` scans of 133 (3.85 rotation while the heading
/// was floored); the target within 2x of 3; bounds about 1.45x around the
/// figures.
#[test]
fn hku2_covariance_is_within_twice_calibrated_on_a_map_of_its_other_scans() {
    let Some(hku2) = require_test_data("hku2_avia", "hku2_covariance") else {
        return;
    };
    let dir = temp_dir("hku2-covariance");
    let reference = dir.join("reference.tum");
    let out = kfmap(&[
        "bake",
        "--dataset",
        hku2.to_str().unwrap(),
        "--poses",
        hku2.join("poses.txt").to_str().unwrap(),
        "--refine-only",
        "--trajectory-out",
        reference.to_str().unwrap(),
        "--out",
        dir.join("refined.kfmap").to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", common::stderr(&out));
    let reference_text = std::fs::read_to_string(&reference).unwrap();
    let pose_lines: Vec<&str> = reference_text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .collect();
    let scans = find_scans(&hku2).unwrap();
    assert_eq!((scans.len(), pose_lines.len()), (266, 266));
    let half = |parity: usize| -> (Vec<_>, Vec<&str>) {
        (0..scans.len())
            .filter(|i| i % 2 == parity)
            .map(|i| (scans[i].clone(), pose_lines[i]))
            .unzip()
    };
    let (even, odd) = (dir.join("even"), dir.join("odd"));
    for (dataset, parity) in [(&even, 0), (&odd, 1)] {
        let (scans, poses) = half(parity);
        linked_dataset(dataset, &scans, &poses);
    }
    let map = dir.join("even.kfmap");
    bake_dataset(&even, &map);
    let prefix = Prefix::new("hku2-covariance");
    let _server = Server::start(&map, "hku2", &prefix.0, &[]);
    let (values, _) = localize_values(&[
        "--map-name",
        "hku2",
        "--iceoryx-prefix",
        &prefix.0,
        "--dataset",
        odd.to_str().unwrap(),
        "--initial-from-ground-truth",
    ]);
    let truth = read_trajectory(&odd.join("poses.txt")).unwrap().poses;
    common::assert_nees("hku2_avia", &values, &truth, 90, 2.8..6.0, 2.0..4.3);
}
