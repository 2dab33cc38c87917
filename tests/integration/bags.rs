//! Bags as datasets, through the commands a user runs: bags written by an independent
//! writer (the PyPI package `rosbags`, via tests/support/dataset_to_bag.py) bake to the
//! same map and poses as the folders they were written from, an Imu topic gives the
//! same gravity as the IMU log, every driver's per-point time deskews as the PCD `time`
//! field does, and bad bags are refused by name with nothing written.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use common::{json, kfmap, stderr, temp_dir};
use kfmap_geometry::geometry::{Pose, translation_distance};
use kfmap_geometry::io::read_trajectory;
use kfmap_testdata::{require_capability, require_test_data};

/// The interpreter with `rosbags` (tests/support/bag_venv.sh), or `None` after a skip
/// (locally) when there is none; under CI=true its absence fails the test.
fn bag_python(test: &str) -> Option<PathBuf> {
    static PYTHON: OnceLock<Option<PathBuf>> = OnceLock::new();
    let found = PYTHON.get_or_init(|| {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/support/bag_venv.sh");
        let out = Command::new(script).output().ok()?;
        if !out.status.success() {
            eprintln!("bag_venv.sh: {}", String::from_utf8_lossy(&out.stderr));
            return None;
        }
        Some(PathBuf::from(String::from_utf8_lossy(&out.stdout).trim()))
    });
    require_capability(
        found.is_some(),
        "no Python with rosbags (tests/support/bag_venv.sh; or set KFMAP_BAG_PYTHON)",
        test,
    )?;
    found.clone()
}

/// Writes `dataset` as a bag at `out` with the independent writer; `extra` are its flags.
fn write_bag(python: &Path, dataset: &Path, out: &Path, container: &str, extra: &[&str]) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/support/dataset_to_bag.py");
    let result = Command::new(python)
        .arg(script)
        .arg(dataset)
        .arg(out)
        .args(["--container", container])
        .args(extra)
        .output()
        .expect("run the bag writer");
    assert!(
        result.status.success(),
        "dataset_to_bag.py {}: {}",
        dataset.display(),
        String::from_utf8_lossy(&result.stderr)
    );
}

/// `kfmap ARGS` as a list of strings (paths included).
fn run_json(args: &[String]) -> serde_json::Value {
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    json(&kfmap(&refs))
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// Largest position gap between two trajectories of as many poses, metres.
fn widest_gap(a: &[Pose], b: &[Pose]) -> f64 {
    assert_eq!(a.len(), b.len(), "trajectories of different lengths");
    a.iter()
        .zip(b)
        .map(|(p, q)| translation_distance(p, q))
        .fold(0.0, f64::max)
}

/// A bake from each container equals the bake from the folder: the same map bytes, the
/// same built poses (within 1e-9 m) and stamps.
fn bakes_alike(
    test: &str,
    data: &str,
    scans: &str,
    extra: &[&str],
    containers: &[(&str, &[&str])],
) {
    let Some(python) = bag_python(test) else {
        return;
    };
    let Some(dataset) = require_test_data(data, test) else {
        return;
    };
    let dir = temp_dir(test);
    let poses = dataset.join("poses.txt");
    let bake = |source: Vec<String>, name: &str| {
        let map = dir.join(format!("{name}.kfmap"));
        let tum = dir.join(format!("{name}.tum"));
        let mut args = vec!["bake".to_string()];
        args.extend(source);
        args.extend(
            [
                "--poses",
                &s(&poses),
                "--build-poses",
                "--scans",
                scans,
                "--out",
                &s(&map),
                "--trajectory-out",
                &s(&tum),
                "--json",
            ]
            .map(String::from),
        );
        args.extend(extra.iter().map(|e| e.to_string()));
        let report = run_json(&args);
        (map, read_trajectory(&tum).unwrap(), report)
    };
    let (folder_map, folder_poses, folder_report) =
        bake(vec!["--dataset".into(), s(&dataset)], "folder");
    let folder_bytes = std::fs::read(&folder_map).unwrap();
    for (k, (container, flags)) in containers.iter().enumerate() {
        let bag = dir.join(format!("bag-{k}-{container}"));
        write_bag(&python, &dataset, &bag, container, flags);
        let source = vec![
            "--bag".into(),
            s(&bag),
            "--points-topic".into(),
            "/points".into(),
        ];
        let (map, poses, report) = bake(source, &format!("{k}-{container}"));
        let gap = widest_gap(&poses.poses, &folder_poses.poses);
        assert!(
            gap <= 1e-9,
            "{data} from {container}: poses {gap} m from the folder's"
        );
        assert_eq!(
            poses.stamps, folder_poses.stamps,
            "{data} from {container}: stamps"
        );
        assert!(
            std::fs::read(&map).unwrap() == folder_bytes,
            "{data} from {container}: the map differs from the folder's"
        );
        assert_eq!(report["keyframes"], folder_report["keyframes"]);
        assert_eq!(
            report["mapping"]["ate_m"],
            folder_report["mapping"]["ate_m"]
        );
        assert_eq!(report["dataset_scans"], folder_report["dataset_scans"]);
    }
}

#[test]
fn balm_from_every_container_bakes_as_from_its_folder() {
    bakes_alike(
        "balm_from_every_container_bakes_as_from_its_folder",
        "balm_os0",
        "0..30",
        &[],
        &[("mcap", &[]), ("sqlite3", &[]), ("ros1", &[])],
    );
}

#[test]
fn hku2_from_every_container_bakes_as_from_its_folder() {
    bakes_alike(
        "hku2_from_every_container_bakes_as_from_its_folder",
        "hku2_avia",
        "0..80",
        &[],
        &[
            ("mcap", &[]),
            ("sqlite3", &[]),
            ("ros1", &["--ros1-compression", "bz2"]),
            ("ros1", &["--ros1-compression", "lz4"]),
        ],
    );
}

#[test]
fn an_imu_topic_gives_the_gravity_of_the_imu_log() {
    let test = "an_imu_topic_gives_the_gravity_of_the_imu_log";
    let Some(python) = bag_python(test) else {
        return;
    };
    let Some(data) = require_test_data("imu_real", test) else {
        return;
    };
    let dir = temp_dir(test);
    let traj = s(&data.join("traj.txt"));
    let from_log = json(&kfmap(&["gravity", "--dataset", &s(&data), "--json"]));
    for container in ["mcap", "sqlite3", "ros1"] {
        let bag = dir.join(format!("imu-{container}"));
        let imu = s(&data.join("imu.txt"));
        write_bag(
            &python,
            &data,
            &bag,
            container,
            &["--imu", &imu, "--poses", &traj],
        );
        let from_bag = json(&kfmap(&[
            "gravity",
            "--bag",
            &s(&bag),
            "--imu-topic",
            "/imu",
            "--poses",
            &traj,
            "--json",
        ]));
        assert_eq!(
            from_bag["imu_samples"], from_log["imu_samples"],
            "{container}"
        );
        for (k, (a, b)) in from_bag["gravity"]["vector"]
            .as_array()
            .unwrap()
            .iter()
            .zip(from_log["gravity"]["vector"].as_array().unwrap())
            .enumerate()
        {
            let (a, b) = (a.as_f64().unwrap(), b.as_f64().unwrap());
            assert!(
                (a - b).abs() <= 1e-9,
                "{container}: gravity[{k}] {a} vs {b}"
            );
        }
    }
}

/// The bag writer, a scratch folder and in it a raw (not deskewed) simulated drive
/// with per-point times and its IMU log; `None` after the skip-or-fail without Python.
fn raw_fixture(test: &str) -> Option<(PathBuf, common::TestDir, PathBuf)> {
    let python = bag_python(test)?;
    let dir = temp_dir(test);
    let raw = dir.join("raw");
    common::simulate(&raw, "courtyard", "4", "16", &["--speed", "4", "--raw"]);
    Some((python, dir, raw))
}

#[test]
fn every_drivers_point_times_deskew_as_the_pcd_time_field() {
    let test = "every_drivers_point_times_deskew_as_the_pcd_time_field";
    let Some((python, dir, raw)) = raw_fixture(test) else {
        return;
    };
    let gt = s(&raw.join("poses_gt.txt"));
    let bake = |source: Vec<String>, name: &str, extra: &[&str]| {
        let tum = dir.join(format!("{name}.tum"));
        let mut args = vec!["bake".to_string()];
        args.extend(source);
        args.extend(
            [
                "--build-poses",
                "--out",
                &s(&dir.join(format!("{name}.kfmap"))),
                "--trajectory-out",
                &s(&tum),
                "--json",
            ]
            .map(String::from),
        );
        args.extend(extra.iter().map(|e| e.to_string()));
        run_json(&args);
        read_trajectory(&tum).unwrap().poses
    };
    let folder = bake(vec!["--dataset".into(), s(&raw)], "folder", &[]);
    let bag_source = |layout: &str| {
        let bag = dir.join(format!("raw-{layout}"));
        let imu = s(&raw.join("imu.csv"));
        let flags = [
            "--layout",
            layout,
            "--base-sec",
            "1700000000",
            "--imu",
            &imu,
        ];
        write_bag(&python, &raw, &bag, "mcap", &flags);
        vec![
            "--bag".to_string(),
            s(&bag),
            "--points-topic".into(),
            "/points".into(),
            "--imu-topic".into(),
            "/imu".into(),
            "--poses".into(),
            gt.clone(),
        ]
    };
    // Without deskewing, the drive lands far from the deskewed one (0.19 m): the bound
    // below would catch a layout whose times were ignored. The bag's stamps are
    // absolute (1.7e9 s, read at f64's 0.2 us) where the folder's start at 0, and point
    // times carry their encoding's rounding, so the motion model predicts from
    // marginally different starts and each registration converges within its own
    // tolerance of the other: the bound is that tolerance (translation-eps, 0.1 mm).
    // Measured 7.5e-5 m for every layout.
    let tolerance = kfmap_bake::config::BakeConfig::default()
        .build
        .odometry
        .registration
        .translation_eps;
    let ouster = bag_source("ouster");
    let unskewed = bake(ouster.clone(), "off", &["--deskew", "off"]);
    let off_gap = widest_gap(&unskewed, &folder);
    assert!(
        off_gap > 0.01,
        "deskew off moved the poses only {off_gap} m"
    );
    let mut gaps = Vec::new();
    for layout in [
        "ouster",
        "velodyne",
        "hesai",
        "livox",
        "livox-offset",
        "robosense",
    ] {
        let source = match layout {
            "ouster" => ouster.clone(),
            _ => bag_source(layout),
        };
        let poses = bake(source, layout, &[]);
        let gap = widest_gap(&poses, &folder);
        println!(
            "{layout}: built poses {gap:.2e} m from the PCD path's (deskew off {off_gap:.3} m)"
        );
        gaps.push((layout, gap));
    }
    let over: Vec<_> = gaps.iter().filter(|(_, gap)| *gap > tolerance).collect();
    assert!(
        over.is_empty(),
        "built poses farther from the PCD path's than {tolerance} m: {over:?} (deskew off: \
         {off_gap} m)"
    );
}

#[test]
fn inspect_bag_reports_each_topic_and_the_cloud_layout() {
    let test = "inspect_bag_reports_each_topic_and_the_cloud_layout";
    let Some((python, dir, raw)) = raw_fixture(test) else {
        return;
    };
    let imu = s(&raw.join("imu.csv"));
    let scans = std::fs::read_dir(raw.join("scans")).unwrap().count() as u64;
    let imu_lines = std::fs::read_to_string(raw.join("imu.csv"))
        .unwrap()
        .lines()
        .count() as u64
        - 1;
    for (container, layout, time_field) in [
        ("mcap", "ouster", "t"),
        ("sqlite3", "hesai", "timestamp"),
        ("ros1", "livox-offset", "offset_time"),
    ] {
        let bag = dir.join(format!("inspect-{container}"));
        let flags = [
            "--layout",
            layout,
            "--base-sec",
            "1700000000",
            "--imu",
            &imu,
        ];
        write_bag(&python, &raw, &bag, container, &flags);
        let report = json(&kfmap(&["inspect-bag", &s(&bag), "--json"]));
        let storage = report["storage"].as_str().unwrap();
        assert!(
            storage.contains(container.trim_end_matches('1')),
            "{storage}"
        );
        let topics = report["topics"].as_array().unwrap();
        let topic = |name: &str| topics.iter().find(|t| t["name"] == name).unwrap().clone();
        let points = topic("/points");
        assert_eq!(points["count"].as_u64(), Some(scans), "{container}");
        assert_eq!(
            topic("/imu")["count"].as_u64(),
            Some(imu_lines),
            "{container}"
        );
        let rate = points["rate_hz"].as_f64().unwrap();
        assert!((rate - 10.0).abs() < 0.05, "{container}: {rate} Hz");
        let cloud = &points["point_cloud"];
        assert_eq!(cloud["time"]["field"], time_field, "{container}");
        let fields = cloud["fields"].as_array().unwrap();
        let x = fields.iter().find(|f| f["name"] == "x").unwrap();
        assert_eq!(
            (x["offset"].as_u64(), x["datatype"].as_str()),
            (Some(0), Some("FLOAT32"))
        );
        let first_scan = std::fs::read(raw.join("scans/000000.pcd")).unwrap();
        let width = String::from_utf8_lossy(&first_scan[..400])
            .lines()
            .find_map(|l| {
                l.strip_prefix("WIDTH ")
                    .map(|w| w.trim().parse::<u64>().unwrap())
            })
            .unwrap();
        assert_eq!(cloud["points"].as_u64(), Some(width), "{container}");
        let duration = report["duration_s"].as_f64().unwrap();
        assert!(
            duration > 3.8 && duration < 4.1,
            "{container}: {duration} s"
        );
    }
}

#[test]
fn bad_bags_are_refused_by_name_and_nothing_is_written() {
    let test = "bad_bags_are_refused_by_name_and_nothing_is_written";
    let Some((python, dir, raw)) = raw_fixture(test) else {
        return;
    };
    let imu = s(&raw.join("imu.csv"));
    let good = dir.join("good.bag");
    write_bag(&python, &raw, &good, "ros1", &["--imu", &imu]);
    let broken = dir.join("broken");
    write_bag(&python, &raw, &broken, "mcap", &["--break-cloud", "3"]);
    let bytes = std::fs::read(&good).unwrap();
    let truncated = dir.join("truncated.bag");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let not_a_bag = dir.join("notes.bag");
    std::fs::write(&not_a_bag, "this is not a bag\n").unwrap();
    let out_dir = dir.join("out");
    std::fs::create_dir_all(&out_dir).unwrap();
    let map = s(&out_dir.join("map.kfmap"));
    let cases: [(&Path, &str, &[&str]); 5] = [
        (
            &good,
            "/nope",
            &[
                "no topic '/nope'",
                "/points (sensor_msgs/PointCloud2)",
                "/imu (sensor_msgs/Imu)",
            ],
        ),
        (
            &good,
            "/imu",
            &[
                "'/imu' carries sensor_msgs/Imu",
                "not sensor_msgs/PointCloud2",
                "/points",
            ],
        ),
        (&truncated, "/points", &["truncated.bag", "byte"]),
        (&broken, "/points", &["/points", "message 3", "'z'"]),
        (&not_a_bag, "/points", &["notes.bag", "not a bag"]),
    ];
    for (bag, topic, expected) in cases {
        let out = kfmap(&[
            "bake",
            "--bag",
            &s(bag),
            "--points-topic",
            topic,
            "--poses",
            &s(&raw.join("poses_gt.txt")),
            "--out",
            &map,
        ]);
        let message = stderr(&out);
        assert_eq!(out.status.code(), Some(2), "{}: {message}", bag.display());
        for e in expected {
            assert!(
                message.contains(e),
                "{}: expected '{e}' in: {message}",
                bag.display()
            );
        }
        assert!(!message.contains("panicked"), "{message}");
        let left: Vec<_> = std::fs::read_dir(&out_dir).unwrap().collect();
        assert!(
            left.is_empty(),
            "{}: files left behind: {left:?}",
            bag.display()
        );
    }
}

#[test]
fn a_bag_localizes_as_its_folder() {
    let test = "a_bag_localizes_as_its_folder";
    let Some((python, dir, raw)) = raw_fixture(test) else {
        return;
    };
    let map = dir.join("map.kfmap");
    common::bake_dataset(&raw, &map);
    let bag = dir.join("raw-ouster");
    let imu = s(&raw.join("imu.csv"));
    let flags = [
        "--layout",
        "ouster",
        "--base-sec",
        "1700000000",
        "--imu",
        &imu,
    ];
    write_bag(&python, &raw, &bag, "ros1", &flags);
    let prefix = common::Prefix::new("bagloc");
    let _server = common::Server::start(&map, "bagloc", &prefix.0, &[]);
    let localize = |source: &[String], name: &str| {
        let tum = dir.join(format!("{name}.tum"));
        let mut args: Vec<String> = [
            "localize",
            "--map-name",
            "bagloc",
            "--iceoryx-prefix",
            &prefix.0,
            "--rate",
            "0",
            "--initial-from-ground-truth",
            "--json",
            "--out",
            &s(&tum),
        ]
        .map(String::from)
        .to_vec();
        args.extend(source.iter().cloned());
        let summary = run_json(&args);
        (read_trajectory(&tum).unwrap(), summary)
    };
    let (folder, folder_summary) = localize(&["--dataset".into(), s(&raw)], "folder");
    let bag_args = [
        "--bag",
        &s(&bag),
        "--points-topic",
        "/points",
        "--imu-topic",
        "/imu",
        "--poses",
        &s(&raw.join("poses_gt.txt")),
    ]
    .map(String::from);
    let (from_bag, bag_summary) = localize(&bag_args, "bag");
    assert_eq!(bag_summary["scans"], folder_summary["scans"]);
    assert_eq!(bag_summary["ok"], folder_summary["ok"]);
    let gap = widest_gap(&from_bag.poses, &folder.poses);
    assert!(
        gap <= 1e-3,
        "localized from the bag {gap} m from the folder's poses"
    );
    // The bag's scans are stamped on its own clock (the pose file's plus an epoch).
    let first = from_bag.stamps.as_ref().unwrap()[0] - folder.stamps.as_ref().unwrap()[0];
    assert!((first - 1.7e9).abs() < 1e-3, "bag stamps offset {first} s");
}

#[test]
fn demo_runs_on_a_bag() {
    let test = "demo_runs_on_a_bag";
    let Some((python, dir, raw)) = raw_fixture(test) else {
        return;
    };
    let bag = dir.join("raw-velodyne.mcap");
    let imu = s(&raw.join("imu.csv"));
    let flags = [
        "--layout",
        "velodyne",
        "--base-sec",
        "1700000000",
        "--imu",
        &imu,
    ];
    write_bag(&python, &raw, &bag, "mcap", &flags);
    let out = dir.join("demo");
    let gt = raw.join("poses_gt.txt");
    let result = kfmap(&[
        "demo",
        "--out",
        &s(&out),
        "--bag",
        &s(&bag),
        "--points-topic",
        "/points",
        "--imu-topic",
        "/imu",
        "--poses",
        &s(&gt),
        "--localize-scans",
        "10..",
    ]);
    assert!(result.status.success(), "{}", stderr(&result));
    let report = String::from_utf8(result.stdout).unwrap();
    assert!(report.starts_with("kfmap demo --bag"), "{report}");
    // The simulator's truth is the oracle: the built map's frame is the rigid fit of the
    // mapped scans' true poses onto their built ones.
    let truth = read_trajectory(&gt).unwrap().poses;
    let built = read_trajectory(&out.join("map_poses.tum")).unwrap().poses;
    let map_from_truth = kfmap_geometry::trajectory_error::rigid_alignment(&truth, &built);
    let localized = read_trajectory(&out.join("localized.tum")).unwrap().poses;
    assert_eq!(localized.len(), truth.len() - 10);
    let worst = localized
        .iter()
        .zip(&truth[10..])
        .map(|(l, t)| translation_distance(l, &(map_from_truth * t)))
        .fold(0.0, f64::max);
    // Measured 0.068 m: a 4 s map built from raw 16-beam scans at 4 m/s.
    assert!(worst < 0.1, "worst localized scan {worst} m from the truth");
}
