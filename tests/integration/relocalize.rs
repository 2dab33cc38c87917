//! Global relocalization over IPC with real processes (`kfmap serve`, `kfmap
//! relocalize`, `kfmap localize` without a start), every answer checked against an
//! independent reference: the dataset's pose file (real data) or the simulator's
//! ground truth.
//!
//! - Real data (`../shared/data/balm_os0`, handheld): map of scans 0-115 at their
//!   reference poses, each of scans 116-176 relocalized with no guess; scans of other
//!   places (KITTI, small_gicp's outdoor scans) must all be `not-found`; a replay that
//!   starts with no pose and jumps 10 m and 120 deg (a kidnapped sensor) recovers.
//! - The same revisit scans turned about the sensor's z: as well found at
//!   every turn.
//! - Simulated corridor (a tunnel, repeated structure): no confident wrong answer;
//!   outside the tunnel every scan is found.
//! - Simulated courtyard seen by a 16-ring sensor, relocalized as `kfmap relocalize`
//!   thins it: every scan found.
//! - Simulated campus on rolling ground in a tilted world, relocalized with the
//!   sensor's tilt (`--tilt-deg`, as from an IMU).

use crate::common;

use std::path::{Path, PathBuf};

use common::{
    Prefix, Server, TestDir, bake_dataset, json, kfmap, linked_dataset, simulate, temp_dir,
};
use kfmap_bake::dataset::find_scans;
use kfmap_client::{Client, ClientOptions, Connection, RelocalizeOptions};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::{Pose, pose_from_xyz_quat, rotation_distance, translation_distance};
use kfmap_geometry::io::{
    CloudFormat, PcdData, ReadOptions, read_cloud, read_trajectory, write_cloud,
};
use kfmap_geometry::percentile::{is_maximum, percentile};
use kfmap_map::place::RelocalizeStatus;
use kfmap_protocol::{
    FLAG_FINISH_CHOSEN, FLAG_PLACES_ONLY, FLAG_SCORE_CHOSEN, RequestHeader, RequestKind,
    ResponseHeader, ScanPayload, StatusCode, WirePlace, place_from_wire,
};
use kfmap_sim::gravity_in_map;
use kfmap_testdata::require_test_data;
use nalgebra::{UnitQuaternion, Vector3};

/// The README's figure: revisit scans of balm_os0 relocalized within [`RIGHT_M`] and
/// [`RIGHT_DEG`] with no guess, of 61.
const CLAIMED_FOUND: usize = 61;

/// The bounds: a relocalization within these is a success...
const RIGHT_M: f64 = 0.3;
const RIGHT_DEG: f64 = 3.0;
/// ... and a `found` one beyond these is a confident wrong answer.
const WRONG_M: f64 = 1.0;
const WRONG_DEG: f64 = 5.0;

/// One `kfmap relocalize --json` line.
#[derive(Debug)]
struct Place {
    scan: PathBuf,
    status: String,
    pose: Option<Pose>,
    server_ms: f64,
}

fn relocalize(map_name: &str, prefix: &Prefix, scans: &[PathBuf], extra: &[&str]) -> Vec<Place> {
    let mut args = vec!["relocalize", "--map-name", map_name, "--json"];
    args.extend(["--iceoryx-prefix", &prefix.0, "--timeout", "30"]);
    args.extend(extra);
    let paths: Vec<&str> = scans.iter().map(|p| p.to_str().unwrap()).collect();
    args.extend(&paths);
    let out = kfmap(&args);
    assert!(
        out.status.success(),
        "kfmap relocalize failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|line| {
            let v: serde_json::Value = serde_json::from_str(line).unwrap();
            let pose = v["pose"].as_array().map(|p| {
                let p: Vec<f64> = p.iter().map(|x| x.as_f64().unwrap()).collect();
                pose_from_xyz_quat(p.try_into().unwrap()).unwrap()
            });
            check_places(&v, pose.as_ref());
            Place {
                scan: PathBuf::from(v["scan"].as_str().unwrap()),
                status: v["status"].as_str().unwrap().to_owned(),
                pose,
                server_ms: v["server_ms"].as_f64().unwrap(),
            }
        })
        .collect()
}

/// A line's scored places: best score first, the first the best's score; the
/// runner-up's place, when there is one, scored `runner_up` and is another place than
/// the answer (the server's 1 m / 5 deg apart).
fn check_places(line: &serde_json::Value, pose: Option<&Pose>) {
    let pose_of = |v: &serde_json::Value| {
        let p: Vec<f64> = serde_json::from_value(v.clone()).unwrap();
        pose_from_xyz_quat(p.try_into().unwrap()).unwrap()
    };
    let places = line["places"].as_array().unwrap();
    let scores: Vec<f64> = places
        .iter()
        .map(|p| p["score"].as_f64().unwrap())
        .collect();
    assert!(scores.windows(2).all(|w| w[0] >= w[1]), "{line}");
    let runner_up = line["runner_up"].as_f64().unwrap();
    match (&line["runner_up_pose"], pose) {
        (serde_json::Value::Null, _) => assert!(runner_up == 0.0 || pose.is_none(), "{line}"),
        (other, Some(pose)) => {
            assert_eq!(scores[0], line["score"].as_f64().unwrap(), "{line}");
            let other = pose_of(other);
            assert!(
                places
                    .iter()
                    .any(|p| pose_of(&p["pose"]) == other && p["score"].as_f64() == Some(runner_up)),
                "{line}"
            );
            let (m, deg) = gap(&other, pose);
            assert!(m > 1.0 || deg > 5.0, "{line}");
        }
        (_, None) => panic!("a runner-up place without an answer: {line}"),
    }
}

/// Translation (m) and rotation (deg) from the reference.
fn gap(pose: &Pose, reference: &Pose) -> (f64, f64) {
    (
        translation_distance(pose, reference),
        rotation_distance(pose, reference).to_degrees(),
    )
}

fn right(place: &Place, reference: &Pose) -> bool {
    place.status == "found"
        && place.pose.is_some_and(|p| {
            let (m, deg) = gap(&p, reference);
            m <= RIGHT_M && deg <= RIGHT_DEG
        })
}

fn confidently_wrong(place: &Place, reference: &Pose) -> bool {
    place.status == "found"
        && place.pose.is_some_and(|p| {
            let (m, deg) = gap(&p, reference);
            m > WRONG_M || deg > WRONG_DEG
        })
}

fn map_from_input(name: &str, prefix: &Prefix) -> Pose {
    let options = ClientOptions {
        iceoryx_prefix: Some(prefix.0.clone()),
        ..ClientOptions::default()
    };
    Client::connect(name, options)
        .unwrap()
        .status()
        .unwrap()
        .map_from_input
}

/// A simulated site mapped on one drive and served, and the same drive replayed at
/// another lidar rate (other scans than the map's): its scans and their true poses in
/// the simulator's frame and in the map's.
struct ReplayedSite {
    _server: Server,
    prefix: Prefix,
    name: String,
    map: PathBuf,
    scans: Vec<PathBuf>,
    input: Vec<Pose>,
    truth: Vec<Pose>,
    /// Holds the map and the scans: removed last.
    _dir: TestDir,
}

/// Simulates `preset` (`world`: options of both drives) with `beams`, bakes and serves
/// the first drive as `name`, replays it at `lidar_rate` Hz.
fn replayed_site(
    name: &str,
    preset: &str,
    seconds: &str,
    beams: &str,
    world: &[&str],
    lidar_rate: &str,
) -> ReplayedSite {
    let dir = temp_dir(&format!("{name}-relocalize"));
    let (mapped, replayed) = (dir.join("mapped"), dir.join("replayed"));
    simulate(&mapped, preset, seconds, beams, world);
    let replay = [world, &["--lidar-rate", lidar_rate]].concat();
    simulate(&replayed, preset, seconds, beams, &replay);
    let map = dir.join(format!("{name}.kfmap"));
    bake_dataset(&mapped, &map);
    let prefix = Prefix::new(&format!("{name}-reloc"));
    let server = Server::start(&map, name, &prefix.0, &[]);
    let map_from_input = map_from_input(name, &prefix);
    let input = read_trajectory(&replayed.join("poses_gt.txt"))
        .unwrap()
        .poses;
    let truth = input.iter().map(|p| map_from_input * p).collect();
    ReplayedSite {
        _server: server,
        prefix,
        name: name.to_owned(),
        map,
        scans: find_scans(&replayed).unwrap(),
        input,
        truth,
        _dir: dir,
    }
}

/// Issue targets on balm_os0: the 61 revisit scans relocalized within 0.3 m and 3 deg
/// as the README claims (58 of 61; at least 57 here, the floor was 90 %, 55),
/// no confident wrong answer, every foreign scan `not-found`. Then a
/// replay with no start and a jump: the first scan and the scan after the jump are
/// relocalized, every adopted pose is right, and the tracker is `ok` again within 3
/// scans of each relocalization.
#[test]
fn balm_scans_are_relocalized_and_foreign_scans_are_not_found() {
    let test = "balm_relocalize";
    let Some(balm) = require_test_data("balm_os0", test) else {
        return;
    };
    // The foreign scans, needed as much as balm's (under CI=true a missing one fails).
    let (Some(kitti00), Some(small_gicp)) = (
        require_test_data("kitti00", test),
        require_test_data("small_gicp", test),
    ) else {
        return;
    };
    let dir = temp_dir("balm-relocalize");
    let scans = find_scans(&balm).unwrap();
    let pose_text = std::fs::read_to_string(balm.join("poses.txt")).unwrap();
    let pose_lines: Vec<&str> = pose_text.lines().collect();
    let map = common::fixtures::balm_first_pass_map(&balm);
    let reference = read_trajectory(&balm.join("poses.txt")).unwrap().poses;
    let prefix = Prefix::new("balm-reloc");
    let _server = Server::start(&map, "balm", &prefix.0, &[]);
    let map_from_input = map_from_input("balm", &prefix);
    let reference: Vec<Pose> = reference.iter().map(|p| map_from_input * p).collect();

    let places = relocalize("balm", &prefix, &scans[116..], &[]);
    assert_eq!(places.len(), 61);
    let count = |status: &str| places.iter().filter(|p| p.status == status).count();
    let success = places
        .iter()
        .zip(&reference[116..])
        .filter(|(p, r)| right(p, r))
        .count();
    let wrong: Vec<&Path> = places
        .iter()
        .zip(&reference[116..])
        .filter(|(p, r)| confidently_wrong(p, r))
        .map(|(p, _)| p.scan.as_path())
        .collect();
    let mut ms: Vec<f64> = places.iter().map(|p| p.server_ms).collect();
    ms.sort_by(f64::total_cmp);
    println!(
        "balm revisit: {success} of 61 within {RIGHT_M} m / {RIGHT_DEG} deg; found {}, ambiguous {}, not-found {}, confident wrong {}; server p50 {:.1} ms, p99 {:.1} ms{}",
        count("found"),
        count("ambiguous"),
        count("not-found"),
        wrong.len(),
        percentile(&ms, 0.5),
        percentile(&ms, 0.99),
        if is_maximum(ms.len(), 0.99) {
            format!(" (over {} scans the p99 is the slowest)", ms.len())
        } else {
            String::new()
        }
    );
    assert!(wrong.is_empty(), "confident wrong answers: {wrong:?}");
    // README and DESIGN.md: 61 of 61 (58 before a place that only slides along a
    // corridor-like stretch stopped being a rival, `pinned-share`); the target is 60.
    assert!(success >= CLAIMED_FOUND - 1, "{success} of 61");

    let mut foreign: Vec<PathBuf> = find_scans(&kitti00).unwrap();
    foreign.extend(["source.ply", "target.ply"].map(|f| small_gicp.join(f)));
    let places = relocalize("balm", &prefix, &foreign, &[]);
    for place in &places {
        println!("foreign {}: {}", place.scan.display(), place.status);
    }
    assert_eq!(places.len(), 8);
    assert!(places.iter().all(|p| p.status == "not-found"));

    // A replay with no start that jumps from scan 130 to 150 (10 m, 120 deg).
    let jump: Vec<usize> = (116..=130)
        .step_by(2)
        .chain((150..177).step_by(2))
        .collect();
    let jumped = dir.join("jumped");
    linked_dataset(
        &jumped,
        &jump.iter().map(|&i| scans[i].clone()).collect::<Vec<_>>(),
        &jump.iter().map(|&i| pose_lines[i]).collect::<Vec<_>>(),
    );
    let out = kfmap(&[
        "localize",
        "--map-name",
        "balm",
        "--iceoryx-prefix",
        &prefix.0,
        "--dataset",
        jumped.to_str().unwrap(),
        "--rate",
        "0",
        "--json-lines",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<serde_json::Value> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .filter(|v: &serde_json::Value| v.get("index").is_some())
        .collect();
    assert_eq!(lines.len(), jump.len());
    let mut relocalized = Vec::new();
    for (k, line) in lines.iter().enumerate() {
        let status = line["status"].as_str().unwrap();
        let reasons: Vec<&str> = line["reasons"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r.as_str().unwrap())
            .collect();
        println!("jumped scan {}: {status} {reasons:?}", jump[k]);
        if reasons.contains(&"relocalized") {
            relocalized.push(k);
        }
        if status != "lost" {
            let p: Vec<f64> = line["pose"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            let pose = pose_from_xyz_quat(p.try_into().unwrap()).unwrap();
            let (m, deg) = gap(&pose, &reference[jump[k]]);
            assert!(
                m <= RIGHT_M && deg <= RIGHT_DEG,
                "scan {}: {m} m, {deg} deg",
                jump[k]
            );
        }
    }
    let after_jump = jump.iter().position(|&i| i == 150).unwrap();
    assert_eq!(
        relocalized.first(),
        Some(&0),
        "the first scan is relocalized"
    );
    assert!(
        relocalized
            .iter()
            .any(|&k| (after_jump..after_jump + 3).contains(&k)),
        "relocalized within 3 scans of the jump: {relocalized:?}"
    );
    for &k in &relocalized {
        let ok_again = lines[k..(k + 4).min(lines.len())]
            .iter()
            .any(|l| l["status"] == "ok");
        assert!(ok_again, "not ok within 3 scans of scan {}", jump[k]);
    }
}

/// The balm_os0 revisit scans turned about the sensor's z by 37, 143, 180 and
/// 250 deg (a copy holds `Rz(turn) p`, so its reference is `T_ref Rz(-turn)`) are
/// relocalized as well as the scans as recorded: at every turn at least 56 of 61 within
/// 0.3 m / 3 deg of `poses.txt` and `found`, none `found` more than 1 m or 5 deg off.
#[test]
fn turned_balm_scans_are_found_at_any_heading() {
    let Some(balm) = require_test_data("balm_os0", "balm_turned_relocalize") else {
        return;
    };
    let dir = temp_dir("balm-turned");
    let scans = find_scans(&balm).unwrap();
    let map = common::fixtures::balm_first_pass_map(&balm);
    let prefix = Prefix::new("balm-turned");
    let _server = Server::start(&map, "balm-turned", &prefix.0, &[]);
    let map_from_input = map_from_input("balm-turned", &prefix);
    let reference = read_trajectory(&balm.join("poses.txt")).unwrap().poses;
    let mut outcomes = Vec::new();
    for turn_deg in [37.0_f64, 143.0, 180.0, 250.0] {
        let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), turn_deg.to_radians());
        let turned_dir = dir.join(format!("turned-{turn_deg}"));
        std::fs::create_dir_all(&turned_dir).unwrap();
        let turned: Vec<PathBuf> = scans[116..]
            .iter()
            .map(|path| {
                let points = read_cloud(path, &ReadOptions::default())
                    .unwrap()
                    .cloud
                    .points
                    .iter()
                    .map(|p| {
                        let v = turn.cast::<f32>() * Vector3::new(p[0], p[1], p[2]);
                        [v.x, v.y, v.z]
                    })
                    .collect();
                let out = turned_dir.join(path.file_name().unwrap());
                let cloud = PointCloud::from_points(points);
                write_cloud(&out, &cloud, CloudFormat::Pcd(PcdData::Binary)).unwrap();
                out
            })
            .collect();
        let places = relocalize("balm-turned", &prefix, &turned, &[]);
        assert_eq!(places.len(), 61);
        let unturn = Pose::from_parts(Default::default(), turn.inverse());
        let references: Vec<Pose> = reference[116..]
            .iter()
            .map(|r| map_from_input * r * unturn)
            .collect();
        let success = places
            .iter()
            .zip(&references)
            .filter(|(p, r)| right(p, r))
            .count();
        let wrong: Vec<usize> = (0..61)
            .filter(|&k| confidently_wrong(&places[k], &references[k]))
            .map(|k| 116 + k)
            .collect();
        let mut ms: Vec<f64> = places.iter().map(|p| p.server_ms).collect();
        ms.sort_by(f64::total_cmp);
        println!(
            "balm turned {turn_deg} deg: {success} of 61 within {RIGHT_M} m / {RIGHT_DEG} deg and found, confident wrong {wrong:?}; server p50 {:.1} ms",
            percentile(&ms, 0.5)
        );
        outcomes.push((turn_deg, success, wrong));
    }
    for (turn_deg, success, wrong) in outcomes {
        assert!(
            wrong.is_empty(),
            "{turn_deg} deg: confident wrong {wrong:?}"
        );
        // README: 61 / 61 / 61 / 61 at 37 / 143 / 180 / 250 deg, also with `final-points`
        // (60 at 37 deg with half the scan before the share's noise allowance;
        // 61 / 61 / 61 / 60 before `explained-lead` 0 and `settle-points` 1100,
        // 59 / 59 / 58 / 58 before `pinned-share`); the target, 60 of 61 at any heading.
        assert!(success >= 60, "{turn_deg} deg: {success} of 61");
    }
}

/// The simulated campus (rolling ground, world tilted 2 / -3 deg), mapped
/// over 30 s at 10 Hz and baked with its IMU; every 5th scan of the same drive at 3 Hz
/// relocalized with `kfmap relocalize --tilt-deg R,P`, R and P the sensor's true tilt
/// (the simulator's gravity seen through `poses_gt.txt`): at least 16 of 18 within
/// 0.3 m / 3 deg of the truth and `found`, none `found` more than 1 m or 5 deg off.
#[test]
fn a_tilted_campus_is_relocalized_with_the_imu_tilt() {
    let world = ["--seed", "7", "--tilt-deg", "2.0,-3.0"];
    let site = replayed_site("campus", "campus", "30", "64", &world, "3");
    let (scans, input) = (&site.scans, &site.input);
    // Up in the simulator's frame (its world is tilted), from its gravity.
    let up = -gravity_in_map(2f64.to_radians(), -3f64.to_radians()).normalize();
    let (mut success, mut wrong) = (0, Vec::new());
    let chosen: Vec<usize> = (0..scans.len()).step_by(5).collect();
    assert_eq!(chosen.len(), 18);
    for &i in &chosen {
        // The sensor's up as roll and pitch of R = Ry(pitch) Rx(roll), whose z row
        // is (-sin pitch, sin roll cos pitch, cos roll cos pitch).
        let sensor_up = input[i].rotation.inverse() * up;
        let (roll, pitch) = (sensor_up.y.atan2(sensor_up.z), (-sensor_up.x).asin());
        let tilt = UnitQuaternion::from_euler_angles(roll, pitch, 0.0);
        assert!((tilt.inverse() * Vector3::z()).angle(&sensor_up) < 1e-9);
        let tilt_deg = format!("{},{}", roll.to_degrees(), pitch.to_degrees());
        let place = relocalize(
            &site.name,
            &site.prefix,
            &[scans[i].clone()],
            &["--tilt-deg", &tilt_deg],
        )
        .remove(0);
        let truth = site.truth[i];
        println!(
            "campus scan {i} (tilt {tilt_deg} deg): {} {:?}, {:.0} ms",
            place.status,
            place.pose.map(|p| gap(&p, &truth)),
            place.server_ms
        );
        success += usize::from(right(&place, &truth));
        if confidently_wrong(&place, &truth) {
            wrong.push(i);
        }
    }
    println!("tilted campus: {success} of 18 found right, confident wrong {wrong:?}");
    assert!(wrong.is_empty(), "confident wrong: {wrong:?}");
    assert!(success >= 16, "{success} of 18");
}

/// The simulator's corridor: a 4 m wide, 80 m long tunnel (repeated structure) on a
/// loop over open ground, mapped at 10 Hz and replayed at 1.1 Hz, of which every second scan
/// is relocalized (one every 1.8 s: new viewpoints, but for one in eleven that falls on
/// a map scan's time). No scan gets a confident
/// wrong answer; every scan outside the tunnel is found within 0.3 m and 3 deg; inside
/// it the answers are `ambiguous` or right.
#[test]
fn a_corridor_is_never_answered_with_a_confident_wrong_place() {
    // The simulator's slowest rate is 1 Hz; a 3 Hz replay of which one scan in six was
    // used simulated 270 scans for 45.
    let site = replayed_site("corridor", "corridor", "90", "32", &[], "1.1");
    let (scans, input, truth) = (&site.scans, &site.input, &site.truth);
    let chosen: Vec<usize> = (0..scans.len()).step_by(2).collect();
    let places = relocalize(
        &site.name,
        &site.prefix,
        &chosen.iter().map(|&i| scans[i].clone()).collect::<Vec<_>>(),
        &[],
    );
    let json_summary = json(&kfmap(&["inspect", site.map.to_str().unwrap(), "--json"]));
    println!("place grid: {}", json_summary["place_grid"]);
    let (mut outside, mut outside_found, mut inside, mut inside_ambiguous) = (0, 0, 0, 0);
    for (place, &i) in places.iter().zip(&chosen) {
        // In the simulator's frame the tunnel spans x in [-40, 40] at y = 0.
        let t = input[i].translation.vector;
        let in_tunnel = t.x.abs() < 38.0 && t.y.abs() < 2.0;
        let open = t.x.abs() > 45.0 || t.y.abs() > 5.0;
        println!(
            "scan {i} at x {:.1} y {:.1}: {} {:?}",
            t.x,
            t.y,
            place.status,
            place.pose.map(|p| gap(&p, &truth[i]))
        );
        assert!(!confidently_wrong(place, &truth[i]), "scan {i}");
        if open {
            outside += 1;
            outside_found += usize::from(right(place, &truth[i]));
        }
        if in_tunnel {
            inside += 1;
            inside_ambiguous += usize::from(place.status == "ambiguous");
        }
    }
    println!(
        "corridor: outside the tunnel {outside_found} of {outside} found; inside {inside_ambiguous} of {inside} ambiguous"
    );
    assert!(outside >= 20 && inside >= 10, "{outside} / {inside} scans");
    assert_eq!(outside_found, outside);
    let sample: Vec<&PathBuf> = chosen.iter().step_by(4).map(|&i| &scans[i]).collect();
    three_phases_answer_as_one(&site.name, &site.prefix, &sample);
}

/// A sparse sensor through the command a user types: a 16-ring courtyard drive, mapped,
/// then replayed at another frame rate (other scans than the map's) and relocalized by
/// `kfmap relocalize` with its default thinning (0.25 m voxels leave a ring's arc alone
/// in most 1 m voxels: up used to be found in 2 of 15 such scans, and none was placed).
/// Every scan is `found` within 0.3 m / 3 deg of the simulator's truth; none wrong.
#[test]
fn a_sparse_sixteen_ring_scan_is_relocalized_as_sent() {
    let world = ["--speed", "8"];
    let site = replayed_site("courtyard", "courtyard", "36", "16", &world, "7");
    let chosen: Vec<usize> = (0..site.scans.len()).step_by(9).collect();
    let places = relocalize(
        &site.name,
        &site.prefix,
        &chosen
            .iter()
            .map(|&i| site.scans[i].clone())
            .collect::<Vec<_>>(),
        &[],
    );
    assert_eq!(places.len(), chosen.len());
    let mut worst: f64 = 0.0;
    for (place, &i) in places.iter().zip(&chosen) {
        let truth = site.truth[i];
        let gap = place.pose.map(|p| gap(&p, &truth));
        println!("scan {i}: {} {gap:?}", place.status);
        assert!(right(place, &truth), "scan {i}: {} {gap:?}", place.status);
        worst = worst.max(gap.map_or(f64::INFINITY, |g| g.0));
    }
    println!(
        "sparse courtyard: {} of {} scans found, worst {worst:.3} m from the truth",
        places.len(),
        chosen.len()
    );
    assert!(chosen.len() >= 20, "{} scans", chosen.len());
}

/// The phases a relocalization over a tile set runs on each tile (`FLAG_PLACES_ONLY`,
/// `FLAG_SCORE_CHOSEN` with every place chosen, `FLAG_FINISH_CHOSEN` of the best score)
/// reach the answer of one relocalization: the same pose, fit and scores, with the
/// runner-up and verdict judged here over the scored places; with the session's places
/// and scores, and in a fresh session that runs the steps again.
fn three_phases_answer_as_one(map_name: &str, prefix: &Prefix, scans: &[&PathBuf]) {
    let connect = || {
        let options = ClientOptions {
            iceoryx_prefix: Some(prefix.0.clone()),
            ..Default::default()
        };
        Connection::connect(map_name, options).unwrap()
    };
    let (mut connection, mut fresh) = (connect(), connect());
    let defaults = RelocalizeOptions::default();
    let ask = |connection: &mut Connection, points: &[[f32; 3]], flags: u32, ranks: u64| {
        let mut header = RequestHeader {
            kind: RequestKind::Relocalize as u32,
            flags,
            keyframe_or_scan_id: ranks,
            max_pair_dist: defaults.max_pair_dist,
            max_iterations: defaults.max_iterations,
            ..Default::default()
        };
        let scan = ScanPayload {
            points,
            view_dirs: None,
            covariances: None,
        };
        let payload = scan.encode(&mut header);
        let (h, slots) = connection
            .forward(header, &payload, |h, slots| (*h, slots.to_vec()))
            .unwrap();
        let places: Vec<WirePlace> = slots.into_iter().map(WirePlace::from_slot).collect();
        (h, places)
    };
    let mut compared = 0;
    for path in scans {
        let points = read_cloud(path, &ReadOptions::default())
            .unwrap()
            .cloud
            .points;
        let (one, _) = ask(&mut connection, &points, 0, 0);
        assert_eq!(one.status, StatusCode::Ok as u32, "{}", one.message());
        let (proposed, places) = ask(&mut connection, &points, FLAG_PLACES_ONLY, 0);
        assert_eq!(
            proposed.status,
            StatusCode::Ok as u32,
            "{}",
            proposed.message()
        );
        assert_eq!(places.len(), one.candidates as usize);
        assert!(places.windows(2).all(|w| w[0].score >= w[1].score));
        assert!(places.iter().all(|p| place_from_wire(p).is_some()));
        if places.is_empty() {
            continue;
        }
        let every = u64::MAX >> (64 - places.len());
        let (_, scored) = ask(&mut connection, &points, FLAG_SCORE_CHOSEN, every);
        assert!(scored.windows(2).all(|w| w[0].rank < w[1].rank));
        // The first of equal best scores, in rank order.
        let Some(best) = scored
            .iter()
            .fold(None::<&WirePlace>, |b, p| match b {
                Some(b) if b.score >= p.score => Some(b),
                _ => Some(p),
            })
            .copied()
        else {
            assert_eq!(one.relocalization, RelocalizeStatus::NotFound as u32);
            continue;
        };
        let (finished, _) = ask(&mut connection, &points, FLAG_FINISH_CHOSEN, 1 << best.rank);
        let (again, _) = ask(&mut fresh, &points, FLAG_FINISH_CHOSEN, 1 << best.rank);
        let fit = |h: &ResponseHeader| (h.pose, h.fitness, h.tight_fitness, h.place_scores[0]);
        assert_eq!(fit(&finished), fit(&one), "{}", path.display());
        assert_eq!(
            fit(&again),
            fit(&one),
            "{} (steps run again)",
            path.display()
        );
        let status = RelocalizeStatus::from_code(one.relocalization).unwrap();
        if finished.relocalization == RelocalizeStatus::NotFound as u32 {
            assert_eq!(status, RelocalizeStatus::NotFound);
            continue;
        }
        let settled = pose_from_xyz_quat(finished.pose).unwrap();
        let runner_up = scored
            .iter()
            .filter(|p| p.rank != best.rank)
            .filter(|p| {
                let pose = place_from_wire(p).unwrap();
                translation_distance(&pose, &settled) > 1.0
                    || rotation_distance(&pose, &settled).to_degrees() > 5.0
            })
            .map(|p| p.score)
            .fold(0.0, f64::max);
        assert_eq!(one.place_scores[1], runner_up, "{}", path.display());
        let expected = if runner_up + 0.05 >= best.score {
            RelocalizeStatus::Ambiguous
        } else {
            RelocalizeStatus::Found
        };
        assert_eq!(status, expected, "{}", path.display());
        compared += 1;
    }
    assert!(
        compared >= 3,
        "only {compared} scans had a place that fitted"
    );
    let points = read_cloud(scans[0], &ReadOptions::default())
        .unwrap()
        .cloud
        .points;
    let (places, _) = ask(&mut connection, &points, FLAG_PLACES_ONLY, 0);
    let beyond = 1u64 << places.candidates;
    for (flags, ranks, says) in [
        (FLAG_PLACES_ONLY | FLAG_SCORE_CHOSEN, 1, "one at a time"),
        (FLAG_SCORE_CHOSEN, 0, "no place chosen"),
        (FLAG_FINISH_CHOSEN, 0b11, "exactly one bit"),
        (FLAG_SCORE_CHOSEN, beyond, "proposed"),
    ] {
        let (refused, _) = ask(&mut connection, &points, flags, ranks);
        assert_eq!(
            refused.status,
            StatusCode::BadRequest as u32,
            "flags {flags}"
        );
        assert!(refused.message().contains(says), "{}", refused.message());
    }
}
