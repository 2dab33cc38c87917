//! End-to-end tests of the map server: `kfmap serve` and clients as real processes over
//! iceoryx2, each test under its own iceoryx2 prefix (removed at teardown).

use crate::common;

use std::path::Path;
use std::time::{Duration, Instant};

use std::path::PathBuf;

use common::{
    Prefix, Server, TestDir, bake_dataset, json, kfmap, kfmap_bin, map_from_input, pose_errors,
    rms_and_max_m, simulate, temp_dir,
};
use kfmap_bake::config::BakeConfig;
use kfmap_bake::dataset::{dataset_poses, find_scans, load_raw_scan};
use kfmap_client::{Client, ClientError, ClientOptions, LocalizeOptions};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::{Pose, transform_point};
use kfmap_geometry::io::read_trajectory;
use kfmap_protocol::{
    Cov2CovMode, PROTOCOL_VERSION, RequestHeader, RequestKind, ScanPayload, StatusCode,
    WirePairing, pose_to_wire,
};
use kfmap_service::server::ServedMap;
use kfmap_service::server::session::Session;
use kfmap_service::server::{Limits, answer};

fn options(prefix: &Prefix) -> ClientOptions {
    ClientOptions {
        iceoryx_prefix: Some(prefix.0.clone()),
        timeout: Duration::from_secs(20),
        spin: false,
    }
}

/// One test's site: a 3 s courtyard run (16 beams), its baked map and an iceoryx2
/// prefix, all removed when dropped.
struct Site {
    prefix: Prefix,
    data: PathBuf,
    map: PathBuf,
    _dir: TestDir,
}

/// A site and a `kfmap serve` on its map (`server_toml`: a server.toml body, or "").
/// Bind as `let (site, server)`: the server is dropped (killed) before the site.
fn served(test: &str, server_toml: &str) -> (Site, Server) {
    served_with(test, server_toml, &[])
}

/// As [`served`], with more `kfmap serve` arguments.
fn served_with(test: &str, server_toml: &str, extra: &[&str]) -> (Site, Server) {
    let prefix = Prefix::new(test);
    let dir = temp_dir(test);
    let data = dir.join("sim");
    simulate(&data, "courtyard", "3", "16", &[]);
    let map = dir.join("court.kfmap");
    bake_dataset(&data, &map);
    let config = dir.join("server.toml");
    std::fs::write(&config, server_toml).unwrap();
    let args = [&["--config", config.to_str().unwrap()], extra].concat();
    let server = Server::start(&map, "court", &prefix.0, &args);
    let site = Site {
        prefix,
        data,
        map,
        _dir: dir,
    };
    (site, server)
}

/// Scan `i` of a dataset as sent by `kfmap localize` (0.25 m voxels), and its true pose.
fn scan(data: &Path, i: usize) -> (PointCloud, Pose) {
    let scans = find_scans(data).unwrap();
    let truth = dataset_poses(data, &scans).unwrap().unwrap();
    let cloud = load_raw_scan(&scans[i], &BakeConfig::default())
        .unwrap()
        .voxel_downsample(0.25)
        .unwrap();
    (cloud, truth.poses[i])
}

fn in_process(map: &ServedMap, header: &RequestHeader, scan: &ScanPayload) -> Vec<WirePairing> {
    let mut h = *header;
    let payload = scan.encode(&mut h);
    let limits = Limits::default();
    let a = answer(map, &mut Session::new(0), &h, &payload, &limits);
    assert_eq!(a.header.status, 0, "{}", a.header.message());
    a.pairings.into_wire()
}

#[test]
fn ipc_answers_equal_in_process_answers_bit_for_bit() {
    let (site, _server) = served("bits", "");
    let (data, map_path, prefix) = (&site.data, &site.map, &site.prefix);
    let mut client = Client::connect("court", options(prefix)).unwrap();
    let served = ServedMap::open(map_path, false, 0).unwrap();
    let (cloud, truth) = scan(data, 17);
    let guess = truth * Pose::translation(0.05, -0.03, 0.02);
    let plain = ScanPayload {
        points: &cloud.points,
        view_dirs: None,
        covariances: None,
    };
    let base = RequestHeader {
        pose: pose_to_wire(&guess),
        ..Default::default()
    };

    let ipc = client.nearest(&cloud.points, &guess, 3).unwrap();
    let local = in_process(
        &served,
        &RequestHeader {
            kind: RequestKind::Nearest as u32,
            k: 3,
            ..base
        },
        &plain,
    );
    assert_eq!(ipc.len(), 3 * cloud.len());
    assert_eq!(ipc, local);

    // Nearest in the keyframes around the pose, as in process and as a brute force over
    // the points of the keyframes whose positions are nearest the guess (whichever way
    // they face; `KeyframeMap::surroundings`, checked against sorted distances in the
    // map's unit tests): all but one of the map's, so the answer must leave the
    // farthest out.
    let count = served.map.len() - 1;
    assert!(count >= 2, "{} keyframes", served.map.len());
    let around = client
        .nearest_around(&cloud.points, &guess, 1, count as u32, None)
        .unwrap();
    // Bounded (as the tracker asks): the unbounded answer's pairs within 0.1 m, the
    // others left out; a bound that is no distance is refused by name.
    let bounded = client
        .nearest_around(&cloud.points, &guess, 1, count as u32, Some(0.1))
        .unwrap();
    let near: Vec<_> = around
        .iter()
        .copied()
        .filter(|p| p.dist_sq <= 0.1f32 * 0.1)
        .collect();
    assert!(!near.is_empty() && near.len() < around.len());
    assert_eq!(bounded, near);
    for bad in [-1.0, f32::NAN, 20.5] {
        let e = client
            .nearest_around(&cloud.points, &guess, 1, 0, Some(bad))
            .unwrap_err();
        assert!(e.to_string().contains("radius"), "{bad}: {e}");
    }
    let local = in_process(
        &served,
        &RequestHeader {
            kind: RequestKind::Nearest as u32,
            keyframes: count as u32,
            ..base
        },
        &plain,
    );
    assert_eq!(around, local);
    let nearest = served.map.surroundings(&guess, count);
    let map_points: Vec<nalgebra::Vector3<f64>> = nearest
        .iter()
        .flat_map(|id| {
            let k = served.map.keyframe(*id).unwrap();
            let local: Vec<[f32; 3]> = k.view().unwrap().points.to_vec();
            local.into_iter().map(move |p| transform_point(&k.pose, &p))
        })
        .collect();
    assert_eq!(around.len(), cloud.len());
    let mut farther_than_in_all = 0;
    for (i, p) in cloud.points.iter().enumerate().step_by(7) {
        let q = transform_point(&guess, p);
        let want = map_points
            .iter()
            .map(|m| (m - q).norm_squared())
            .fold(f64::INFINITY, f64::min);
        let got = &around[i];
        assert_eq!(got.query as usize, i);
        assert!(nearest.contains(&got.keyframe), "point {i}");
        assert!(
            (f64::from(got.dist_sq) - want).abs() <= 1e-4 * want.max(1.0),
            "point {i}: {} against {want}",
            got.dist_sq
        );
        farther_than_in_all += usize::from(f64::from(ipc[3 * i].dist_sq) + 1e-4 < want);
    }
    // The active set (`ipc`) is the whole map here; the farthest keyframe was left out
    // of the surroundings: some points found their nearest there.
    assert_eq!(served.map.select(&guess).len(), served.map.len());
    assert!(farther_than_in_all > 0);

    let ipc = client.radius(&cloud.points, &guess, 0.4).unwrap();
    let local = in_process(
        &served,
        &RequestHeader {
            kind: RequestKind::Radius as u32,
            radius: 0.4,
            ..base
        },
        &plain,
    );
    assert!(!ipc.is_empty());
    assert_eq!(ipc, local);

    for mode in [Cov2CovMode::Approximate, Cov2CovMode::Exact] {
        let ipc = client.cov2cov(&plain, &guess, 1.0, mode).unwrap();
        let local = in_process(
            &served,
            &RequestHeader {
                kind: RequestKind::Cov2Cov as u32,
                max_pair_dist: 1.0,
                mode: mode as u32,
                ..base
            },
            &plain,
        );
        assert!(ipc.pairings.len() > cloud.len() / 2, "{mode:?}");
        assert_eq!(ipc.pairings, local, "{mode:?}");
        assert!(!ipc.active.is_empty());
    }
}

#[test]
fn a_spinning_server_answers_as_the_library_does_and_stops_on_sigterm() {
    let (site, server) = served_with("spin", "", &["--spin"]);
    let spinning = ClientOptions {
        spin: true,
        ..options(&site.prefix)
    };
    let mut client = Client::connect("court", spinning).unwrap();
    let served = ServedMap::open(&site.map, false, 0).unwrap();
    let (cloud, truth) = scan(&site.data, 9);
    let plain = ScanPayload {
        points: &cloud.points,
        view_dirs: None,
        covariances: None,
    };
    let nearest = RequestHeader {
        kind: RequestKind::Nearest as u32,
        k: 2,
        pose: pose_to_wire(&truth),
        ..Default::default()
    };
    // Back to back, so that the spinning leader, not a woken one, takes most of them.
    for _ in 0..20 {
        let ipc = client.nearest(&cloud.points, &truth, 2).unwrap();
        assert_eq!(ipc, in_process(&served, &nearest, &plain));
    }
    drop(client);
    let (status, log) = server.stop();
    assert!(status.success(), "{log}");
    assert!(log.contains("20 requests"), "{log}");
}

#[test]
fn client_and_server_side_localization_agree() {
    client_and_server_side_agree("agree", "");
}

/// A server whose `[covariance]` is not the default: the client must estimate its scan
/// covariances with the server's options (from the status report), or the two sides
/// register different scans and land on different poses.
#[test]
fn client_and_server_side_agree_with_a_non_default_covariance_section() {
    client_and_server_side_agree(
        "agree-cov",
        "[covariance]\nk-correspondences-for-cov = 10\nmin-correspondences-for-cov = 4\nlambda = 0.01\nmax-distance-for-cov = 0.6\n",
    );
}

/// Server-side and client-side localization of one scan against a server configured by
/// `server_toml`: the same pose and health.
fn client_and_server_side_agree(test: &str, server_toml: &str) {
    let (site, _server) = served(test, server_toml);
    let (data, prefix) = (&site.data, &site.prefix);
    let mut client = Client::connect("court", options(prefix)).unwrap();
    let (cloud, truth) = scan(data, 12);
    let guess = truth * Pose::new([0.3, -0.2, 0.05].into(), [0.0, 0.0, 0.03].into());
    let scan = ScanPayload {
        points: &cloud.points,
        view_dirs: None,
        covariances: None,
    };
    let opts = LocalizeOptions::default();
    let server = client.localize(&scan, &guess, &opts).unwrap();
    let local = client.localize_client_side(&scan, &guess, &opts).unwrap();
    // Same loop, same pairings; poses differ only by the wire's rounding of the guess.
    let gap = server.pose.inverse() * local.pose;
    assert!(gap.translation.vector.norm() < 1e-6, "{gap}");
    assert!(gap.rotation.angle().to_degrees() < 1e-6, "{gap}");
    assert_eq!(server.health, local.health);
    let error = (truth.inverse() * server.pose).translation.vector.norm();
    assert!(error < 0.02, "{error} m from the true pose");
    assert!(server.health.converged && server.health.inlier_ratio > 0.5);
}

#[test]
fn bad_requests_get_a_named_error_and_change_nothing() {
    let (site, _server) = served("garbage", "[server]\nmax-points-per-request = 5000\n");
    let (data, prefix) = (&site.data, &site.prefix);
    let mut client = Client::connect("court", options(prefix)).unwrap();
    let (cloud, truth) = scan(data, 5);
    let before = client.nearest(&cloud.points[..1000], &truth, 1).unwrap();

    let mut nan = cloud.points[..1000].to_vec();
    nan[321][1] = f32::NAN;
    let e = client.nearest(&nan, &truth, 1).unwrap_err();
    assert_eq!(e.status(), Some(StatusCode::NonFinitePoint));
    assert!(e.to_string().contains("point 321"), "{e}");

    let e = client.nearest(&[], &truth, 1).unwrap_err();
    assert_eq!(e.status(), Some(StatusCode::EmptyScan));

    let big = vec![[1.0f32, 2.0, 3.0]; 5001];
    let e = client.nearest(&big, &truth, 1).unwrap_err();
    assert_eq!(e.status(), Some(StatusCode::TooManyPoints));
    assert!(e.to_string().contains("5000"), "{e}");

    let e = client.nearest(&cloud.points[..10], &truth, 0).unwrap_err();
    assert_eq!(e.status(), Some(StatusCode::BadRequest));
    let e = client
        .nearest_around(&cloud.points[..10], &truth, 1, 65, None)
        .unwrap_err();
    assert_eq!(e.status(), Some(StatusCode::BadRequest));
    assert!(e.to_string().contains("keyframes = 65"), "{e}");

    let header = RequestHeader {
        version: PROTOCOL_VERSION + 7,
        kind: RequestKind::Nearest as u32,
        ..Default::default()
    };
    let e = client
        .connection()
        .call_raw(header, 3, |h, out| {
            h.point_count = 1;
            out.copy_from_slice(&[0.0, 0.0, 0.0]);
        })
        .unwrap_err();
    assert_eq!(e.status(), Some(StatusCode::VersionMismatch));
    assert!(e.to_string().contains("protocol"), "{e}");

    let header = RequestHeader {
        kind: 42,
        ..Default::default()
    };
    let e = client.connection().call(header, 0, |_, _| {}).unwrap_err();
    assert_eq!(e.status(), Some(StatusCode::UnknownKind));

    // A payload shorter than its header says.
    let header = RequestHeader {
        kind: RequestKind::Nearest as u32,
        k: 1,
        ..Default::default()
    };
    let e = client
        .connection()
        .call(header, 6, |h, _| h.point_count = 100)
        .unwrap_err();
    assert_eq!(e.status(), Some(StatusCode::BadRequest));

    let after = client.nearest(&cloud.points[..1000], &truth, 1).unwrap();
    assert_eq!(before, after);
}

/// Localizes a dataset with `kfmap localize --json`, writing the trajectory to `out`.
fn localize_process(
    name: &str,
    data: &Path,
    prefix: &str,
    out: &Path,
    extra: &[&str],
) -> std::process::Child {
    std::process::Command::new(kfmap_bin())
        .args([
            "localize",
            "--map-name",
            name,
            "--dataset",
            data.to_str().unwrap(),
        ])
        .args(["--rate", "0", "--json", "--iceoryx-prefix", prefix])
        .args([
            "--out",
            out.to_str().unwrap(),
            "--initial-from-ground-truth",
        ])
        .args(extra)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

fn summary(child: std::process::Child) -> serde_json::Value {
    json(&child.wait_with_output().unwrap())
}

#[test]
fn four_client_processes_at_once_get_their_own_answers() {
    let (site, _server) = served("four", "");
    let (data, prefix) = (&site.data, &site.prefix);
    let dir = site.map.parent().unwrap().to_path_buf();
    // Oracle: one client alone.
    let alone = dir.join("alone.tum");
    let reference = summary(localize_process("court", data, &prefix.0, &alone, &[]));
    assert_eq!(reference["failed"], 0);
    // Its error against the simulator's truth, computed here from the trajectory file.
    let map_from_input = map_from_input("court", &prefix.0);
    let truth: Vec<Pose> = dataset_poses(data, &find_scans(data).unwrap())
        .unwrap()
        .unwrap()
        .poses
        .iter()
        .map(|p| map_from_input * p)
        .collect();
    let poses = read_trajectory(&alone).unwrap().poses;
    let (rms, max) = rms_and_max_m(&pose_errors(&poses, &truth));
    println!("one client alone: RMS {rms:.4} m, max {max:.4} m from the simulator's truth");
    assert!(rms < 0.02, "RMS {rms} m");
    let children: Vec<_> = (0..4)
        .map(|i| {
            let side: &[&str] = if i % 2 == 0 { &[] } else { &["--server-side"] };
            let out = dir.join(format!("client{i}.tum"));
            (
                out.clone(),
                localize_process("court", data, &prefix.0, &out, side),
            )
        })
        .collect();
    let expected = std::fs::read(&alone).unwrap();
    for (out, child) in children {
        let s = summary(child);
        assert_eq!(s["failed"], 0, "{s}");
        // Same answers as alone, to the last digit: no cross-talk between sessions.
        assert_eq!(std::fs::read(&out).unwrap(), expected, "{}", out.display());
    }
}

/// Every raw point of scan `i`, `copies` times over (jittered by 1 cm steps): a
/// request that keeps the server busy for a while in exact mode.
fn heavy_cloud(data: &Path, i: usize, copies: usize) -> PointCloud {
    let raw = load_raw_scan(&find_scans(data).unwrap()[i], &BakeConfig::default()).unwrap();
    let points: Vec<[f32; 3]> = (0..copies)
        .flat_map(|k| {
            raw.points
                .iter()
                .map(move |p| [p[0] + 0.01 * k as f32, p[1], p[2]])
        })
        .collect();
    PointCloud::from_points(points)
}

#[test]
fn a_client_killed_mid_request_is_reclaimed_and_others_keep_being_served() {
    use kfmap_geometry::io::{CloudFormat, PcdData, write_cloud};
    let (site, _server) = served("killc", "");
    let (data, prefix) = (&site.data, &site.prefix);
    let dir = site.map.parent().unwrap().to_path_buf();
    let mut watcher = Client::connect("court", options(prefix)).unwrap();
    let (cloud, truth) = scan(data, 3);
    let before = watcher.nearest(&cloud.points, &truth, 1).unwrap();
    let heavy = dir.join("heavy.pcd");
    write_cloud(
        &heavy,
        &heavy_cloud(data, 6, 12),
        CloudFormat::Pcd(PcdData::Binary),
    )
    .unwrap();
    // Exact cov2cov with every covariance estimated by the server: seconds of work.
    let mut victim = std::process::Command::new(kfmap_bin())
        .args(["query", "--map-name", "court", "--points"])
        .arg(&heavy)
        .args(["--kind", "cov2cov", "--exact", "--max-pair-dist", "5"])
        .args(["--timeout", "300", "--iceoryx-prefix", &prefix.0])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let started = Instant::now();
    loop {
        let status = watcher.status().unwrap();
        if status.sessions == 2 && status.in_flight == 1 {
            break;
        }
        assert!(
            victim.try_wait().unwrap().is_none(),
            "the victim ended before the server took its request"
        );
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the server never took the victim's request"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    victim.kill().unwrap();
    victim.wait().unwrap();
    let killed = Instant::now();
    // Killed mid-request: the server is still answering it.
    assert_eq!(watcher.status().unwrap().in_flight, 1);
    // Another client is answered meanwhile, the same as before.
    let asked = Instant::now();
    assert_eq!(watcher.nearest(&cloud.points, &truth, 1).unwrap(), before);
    println!(
        "answered beside the dead client's request in {:.0} ms",
        asked.elapsed().as_secs_f64() * 1e3
    );
    // The orphaned request ends (its answer has nowhere to go) and the session is reclaimed.
    let started = Instant::now();
    loop {
        let status = watcher.status().unwrap();
        if status.sessions == 1 && status.in_flight == 0 {
            println!(
                "the orphaned request ended and the session was reclaimed {:.0} ms after the kill",
                killed.elapsed().as_secs_f64() * 1e3
            );
            let cov2cov = status
                .kinds
                .iter()
                .find(|k| k.0 == RequestKind::Cov2Cov)
                .map(|k| k.1);
            assert_eq!(cov2cov, Some(1), "{:?}", status.kinds);
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "session never reclaimed: {status:?}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(watcher.nearest(&cloud.points, &truth, 1).unwrap(), before);
}

#[test]
fn a_killed_and_restarted_server_is_found_again() {
    let (site, server) = served("kills", "");
    let (data, map_path, prefix) = (&site.data, &site.map, &site.prefix);
    let mut client = Client::connect(
        "court",
        ClientOptions {
            timeout: Duration::from_millis(1500),
            ..options(prefix)
        },
    )
    .unwrap();
    let (cloud, truth) = scan(data, 8);
    let first = client.nearest(&cloud.points, &truth, 1).unwrap();
    server.kill();
    let e = client.nearest(&cloud.points, &truth, 1).unwrap_err();
    assert!(matches!(e, ClientError::Timeout { .. }), "{e}");
    // The dead server's port is cleaned up by whoever comes next.
    let _again = Server::start(map_path, "court", &prefix.0, &[]);
    let second = client.nearest(&cloud.points, &truth, 1).unwrap();
    assert_eq!(first, second);
}

#[test]
fn a_second_server_for_the_same_map_name_refuses_to_start() {
    let (site, server) = served("twice", "");
    let (map_path, prefix) = (&site.map, &site.prefix);
    let out = kfmap(&[
        "serve",
        "--map",
        map_path.to_str().unwrap(),
        "--map-name",
        "court",
        "--iceoryx-prefix",
        &prefix.0,
    ]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("already serves map \"court\""), "{err}");
    let (status, log) = server.stop();
    assert!(status.success(), "{log}");
    assert!(log.contains("stopped after"), "{log}");
}

#[test]
fn status_and_reload_report_the_map_and_the_counters() {
    let (site, _server) = served("status", "");
    let (data, map_path, prefix) = (&site.data, &site.map, &site.prefix);
    let mut client = Client::connect("court", options(prefix)).unwrap();
    let (cloud, truth) = scan(data, 2);
    let before = client.nearest(&cloud.points, &truth, 1).unwrap();
    for _ in 0..2 {
        client.nearest(&cloud.points, &truth, 1).unwrap();
    }
    // Oracle for the map's size: `kfmap inspect`, another reader of the file.
    let inspected = kfmap(&["inspect", map_path.to_str().unwrap(), "--json"]);
    let inspected: serde_json::Value = serde_json::from_slice(&inspected.stdout).unwrap();
    let out = kfmap(&[
        "status",
        "--map-name",
        "court",
        "--json",
        "--iceoryx-prefix",
        &prefix.0,
    ]);
    let s = json(&out);
    assert_eq!(s["keyframes"], inspected["keyframes"]);
    assert_eq!(s["points"], inspected["points"]);
    assert_eq!(s["requests"]["nearest"]["count"], 3);
    assert!(s["requests"]["nearest"]["p99_us"].as_f64().unwrap() > 0.0);
    let message = client.reload().unwrap();
    assert!(message.contains("generation 1"), "{message}");
    // A file that is no map replaces the map (atomically, as bake writes): the reload
    // fails by name and the old map keeps answering from its own mapping.
    let junk = map_path.with_extension("junk");
    std::fs::write(&junk, b"not a map").unwrap();
    std::fs::rename(&junk, map_path).unwrap();
    let e = client.reload().unwrap_err();
    assert_eq!(e.status(), Some(StatusCode::Internal));
    assert!(
        e.to_string().contains("still serving the previous map"),
        "{e}"
    );
    let out = kfmap(&[
        "status",
        "--map-name",
        "nobody",
        "--iceoryx-prefix",
        &prefix.0,
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no kfmap server serves map"));
    assert_eq!(client.nearest(&cloud.points, &truth, 1).unwrap(), before);
}

#[test]
fn query_prints_and_writes_every_answer() {
    use kfmap_geometry::io::{CloudFormat, PcdData, write_cloud};
    let (site, _server) = served("query", "");
    let (data, map_path, prefix) = (&site.data, &site.map, &site.prefix);
    let (cloud, truth) = scan(data, 9);
    // The query file holds the scan already moved into the map frame (identity pose).
    let moved: Vec<[f32; 3]> = cloud
        .points
        .iter()
        .take(2000)
        .map(|p| {
            kfmap_geometry::geometry::to_point(&kfmap_geometry::geometry::transform_point(
                &truth, p,
            ))
        })
        .collect();
    let file = map_path.with_file_name("query.pcd");
    write_cloud(
        &file,
        &PointCloud::from_points(moved.clone()),
        CloudFormat::Pcd(PcdData::Binary),
    )
    .unwrap();
    let csv = map_path.with_file_name("answers.csv");
    let out = kfmap(&[
        "query",
        "--map-name",
        "court",
        "--points",
        file.to_str().unwrap(),
        "--k",
        "2",
        "--out",
        csv.to_str().unwrap(),
        "--json",
        "--iceoryx-prefix",
        &prefix.0,
    ]);
    let s = json(&out);
    assert_eq!(s["points"], 2000);
    assert_eq!(s["answers"], 4000);
    // Oracle: the library over IPC with the same points at the identity pose.
    let mut client = Client::connect("court", options(prefix)).unwrap();
    let direct = client.nearest(&moved, &Pose::identity(), 2).unwrap();
    let text = std::fs::read_to_string(&csv).unwrap();
    let rows: Vec<&str> = text.lines().skip(1).collect();
    assert_eq!(rows.len(), direct.len());
    for (row, p) in rows.iter().zip(&direct) {
        let cols: Vec<&str> = row.split(',').collect();
        assert_eq!(cols[0].parse::<u32>().unwrap(), p.query);
        assert_eq!(cols[1].parse::<u64>().unwrap(), p.keyframe);
        assert_eq!(cols[6].parse::<f32>().unwrap(), p.dist_sq);
    }
}

#[test]
fn sighup_reloads_the_map_and_sigterm_stops_cleanly() {
    let (site, server) = served("hup", "");
    let (data, prefix) = (&site.data, &site.prefix);
    let mut client = Client::connect("court", options(prefix)).unwrap();
    let (cloud, truth) = scan(data, 4);
    let before = client.nearest(&cloud.points, &truth, 1).unwrap();
    common::signal(&server.child, libc::SIGHUP);
    // The reload happens on the next housekeeping tick (250 ms).
    std::thread::sleep(Duration::from_millis(800));
    let after = client.nearest(&cloud.points, &truth, 1).unwrap();
    assert_eq!(before, after);
    let (status, log) = server.stop();
    assert!(status.success(), "{log}");
    assert!(
        log.contains("reloaded") && log.contains("generation 1"),
        "{log}"
    );
    assert!(
        log.contains("nearest") && log.contains("2 requests"),
        "{log}"
    );
    // With the client gone too, only iceoryx2's per-prefix management segment is left.
    drop(client);
    let left: Vec<String> = std::fs::read_dir("/dev/shm")
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(&prefix.0))
        .collect();
    assert!(left.iter().all(|n| n.ends_with("global_mgmt")), "{left:?}");
}

/// A server sent SIGSTOP then SIGCONT shut down, taking the WaitSet's
/// interrupt (any signal) for a stop request. After SIGSTOP, SIGCONT and SIGWINCH it
/// must keep serving; only SIGINT/SIGTERM stop it.
#[test]
fn job_control_signals_do_not_stop_the_server() {
    let (site, server) = served("jobctl", "");
    let (data, prefix) = (&site.data, &site.prefix);
    let mut client = Client::connect("court", options(prefix)).unwrap();
    let (cloud, truth) = scan(data, 4);
    let before = client.nearest(&cloud.points, &truth, 1).unwrap();
    common::signal(&server.child, libc::SIGSTOP);
    std::thread::sleep(Duration::from_millis(300));
    common::signal(&server.child, libc::SIGCONT);
    common::signal(&server.child, libc::SIGWINCH);
    std::thread::sleep(Duration::from_millis(500));
    let after = client.nearest(&cloud.points, &truth, 1).unwrap();
    assert_eq!(
        before, after,
        "still serving after SIGSTOP / SIGCONT / SIGWINCH"
    );
    let (status, log) = server.stop();
    assert!(status.success(), "{log}");
    assert!(
        log.contains("nearest") && log.contains("2 requests"),
        "{log}"
    );
}

/// A server whose stdout and stderr readers are gone (closed pipes) must
/// still serve and stop cleanly, not panic on its ready line or its summary.
#[test]
fn a_server_with_closed_output_pipes_serves_and_stops_cleanly() {
    // A second server, on the same map and prefix under another name.
    let (site, _server) = served("pipes", "");
    let mut child = std::process::Command::new(common::kfmap_bin())
        .args([
            "serve",
            "--map",
            site.map.to_str().unwrap(),
            "--map-name",
            "piped",
        ])
        .args(["--iceoryx-prefix", &site.prefix.0])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    drop(child.stderr.take());
    // No ready line to wait for: ask until it answers.
    let started = Instant::now();
    let status = loop {
        let answer = Client::connect("piped", options(&site.prefix)).and_then(|mut c| c.status());
        match answer {
            Ok(status) => break status,
            Err(e) if started.elapsed() > Duration::from_secs(30) => {
                panic!("the server never answered: {e}")
            }
            Err(_) => std::thread::sleep(Duration::from_millis(100)),
        }
    };
    assert_eq!(status.map_name, "piped");
    common::signal(&child, libc::SIGTERM);
    let exit = child.wait().unwrap();
    assert!(exit.success(), "{exit:?}");
}

#[test]
fn sigterm_answers_queued_requests_with_shutting_down() {
    let (site, server) = served("term", "[server]\nworker-threads = 1\n");
    let (data, prefix) = (&site.data, &site.prefix);
    let (_, truth) = scan(data, 6);
    // Heavy requests (every raw point, thirty times over, jittered) from three clients on
    // one worker: one runs, two wait in the queue. The running one must outlast the wait
    // below (at twelve copies it once finished before the signal). A stopping server
    // waits for its clients to read their last answers (a CI run once saw both refusals
    // lost when the server exited first).
    let cloud = heavy_cloud(data, 6, 30);
    let guess = truth * Pose::translation(0.3, 0.0, 0.0);
    let heavy = LocalizeOptions {
        max_iterations: 100,
        max_pair_dist: 5.0,
        mode: Cov2CovMode::Exact,
        ..LocalizeOptions::default()
    };
    // Connected first, so the signal below can only meet requests sent or running. The
    // running request may take long on a loaded machine: wait for it, up to 5 minutes.
    let patient = ClientOptions {
        timeout: Duration::from_secs(300),
        ..options(prefix)
    };
    let clients: Vec<Client> = (0..3)
        .map(|_| Client::connect("court", patient.clone()).unwrap())
        .collect();
    let results: Vec<_> = std::thread::scope(|scope| {
        let handles: Vec<_> = clients
            .into_iter()
            .map(|mut c| {
                let cloud = &cloud;
                scope.spawn(move || {
                    let scan = ScanPayload {
                        points: &cloud.points,
                        view_dirs: None,
                        covariances: None,
                    };
                    c.localize(&scan, &guess, &heavy).map(|_| ())
                })
            })
            .collect();
        // Time for all three to send, also on a loaded machine (the running one takes
        // seconds; at 300 ms a CI run once signalled before any request arrived).
        std::thread::sleep(Duration::from_millis(1000));
        common::signal(&server.child, libc::SIGTERM);
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let refused = results
        .iter()
        .filter(|r| matches!(r, Err(e) if e.status() == Some(StatusCode::ShuttingDown)))
        .count();
    // Every request got an answer (no timeout): finished, refused by name, or (sent
    // after the server stopped looking) told at once that the server is gone.
    for r in &results {
        assert!(
            r.is_ok()
                || matches!(r, Err(e) if e.status().is_some())
                || matches!(r, Err(ClientError::Disconnected(_))),
            "{r:?}"
        );
    }
    let (status, log) = server.stop();
    assert!(refused >= 1, "{results:?}\n{log}");
    assert!(status.success(), "{log}");
    assert!(log.contains("queued requests refused at shutdown"), "{log}");
}

#[test]
fn serve_names_a_bad_map_file_once_and_exits_2() {
    let dir = temp_dir("badmap");
    let junk = dir.join("junk.kfmap");
    std::fs::write(&junk, b"definitely not a map").unwrap();
    for (path, expected) in [
        (junk.to_str().unwrap(), "not a kfmap map file"),
        ("/nonexistent/site.kfmap", "No such file"),
    ] {
        let out = kfmap(&["serve", "--map", path, "--iceoryx-prefix", "kfmt_badmap_"]);
        assert_eq!(out.status.code(), Some(2));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(expected), "{err}");
        assert_eq!(err.matches(path).count(), 1, "{err}");
    }
}

/// Which cov2cov mode requests that leave it to the server get: approximate for a
/// shipped bake; exact for a map baked with `[map] cov2cov-mode = "exact"`; server.toml's
/// `[server] cov2cov-mode` overrides the map's either way. A map-default request then
/// answers exactly as an explicit request of that mode, and the ready line says which.
#[test]
fn the_default_cov2cov_mode_comes_from_the_server_then_the_map() {
    let prefix = Prefix::new("modes");
    let dir = temp_dir("modes");
    let data = dir.join("sim");
    simulate(&data, "courtyard", "3", "16", &[]);
    let approximate_map = dir.join("approximate.kfmap");
    bake_dataset(&data, &approximate_map);
    let exact_map = dir.join("exact.kfmap");
    let bake_toml = dir.join("bake.toml");
    std::fs::write(&bake_toml, "[map]\ncov2cov-mode = \"exact\"\n").unwrap();
    json(&kfmap(&[
        "bake",
        "--dataset",
        data.to_str().unwrap(),
        "--out",
        exact_map.to_str().unwrap(),
        "--config",
        bake_toml.to_str().unwrap(),
        "--json",
    ]));
    let (cloud, truth) = scan(&data, 11);
    let guess = truth * Pose::translation(0.1, 0.05, 0.0);
    let plain = ScanPayload {
        points: &cloud.points,
        view_dirs: None,
        covariances: None,
    };
    let cases = [
        (&approximate_map, "", false),
        (&exact_map, "", true),
        (
            &exact_map,
            "[server]\ncov2cov-mode = \"approximate\"\n",
            false,
        ),
        (
            &approximate_map,
            "[server]\ncov2cov-mode = \"exact\"\n",
            true,
        ),
    ];
    for (i, (map, server_toml, exact)) in cases.into_iter().enumerate() {
        let config = dir.join(format!("server{i}.toml"));
        std::fs::write(&config, server_toml).unwrap();
        let name = format!("modes{i}");
        let server = Server::start(
            map,
            &name,
            &prefix.0,
            &["--config", config.to_str().unwrap()],
        );
        let said = if exact { "exact" } else { "approximate" };
        assert!(
            server
                .ready_line
                .contains(&format!("{said} cov2cov by default")),
            "case {i}: {}",
            server.ready_line
        );
        let mut client = Client::connect(&name, options(&prefix)).unwrap();
        let (same, other) = if exact {
            (Cov2CovMode::Exact, Cov2CovMode::Approximate)
        } else {
            (Cov2CovMode::Approximate, Cov2CovMode::Exact)
        };
        let mut ask = |mode| client.cov2cov(&plain, &guess, 1.0, mode).unwrap().pairings;
        let default = ask(Cov2CovMode::MapDefault);
        assert_eq!(default, ask(same), "case {i}");
        assert_ne!(default, ask(other), "case {i}");
    }
}

/// A test run killed before its drops leaves its iceoryx2 files; the next run removes
/// those of processes that are gone and leaves a live run's alone. The dead run's pid
/// is one past `pid_max` (no process can have it), the live one this process's.
#[test]
fn a_killed_test_runs_shared_memory_is_swept_by_the_next_run() {
    let pid_max: u64 = std::fs::read_to_string("/proc/sys/kernel/pid_max")
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    let dead = PathBuf::from(format!("/dev/shm/kfmt_swept_{}_abc.data", pid_max + 1));
    let live = PathBuf::from(format!(
        "/dev/shm/kfmt_kept_{}_abc.data",
        std::process::id()
    ));
    std::fs::write(&dead, b"left by a killed run").unwrap();
    std::fs::write(&live, b"a live run's").unwrap();
    common::remove_dead_runs_shared_memory();
    let (dead_left, live_left) = (dead.exists(), live.exists());
    let _ = std::fs::remove_file(&live);
    assert!(!dead_left, "{} was not swept", dead.display());
    assert!(live_left, "{} of a live run was removed", live.display());
}
