//! End-to-end tests of the `kfmap` binary: real processes, real files, exit codes.

use crate::common;

use std::path::PathBuf;
use std::process::Command;

use common::{TestDir, json, kfmap, stderr, temp_dir};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::{CloudFormat, PcdData, write_cloud};
use kfmap_testdata::require_test_data;

#[test]
fn inspect_cloud_json_on_a_written_pcd() {
    // A 30 x 30 grid at 0.2 m on z = 0 plus 5 points at the origin the filter drops.
    let mut points: Vec<[f32; 3]> = (0..900)
        .map(|i| [1.0 + (i % 30) as f32 * 0.2, (i / 30) as f32 * 0.2, 0.0])
        .collect();
    points.extend([[0.0; 3]; 5]);
    let dir = temp_dir("grid");
    let path = dir.join("grid.pcd");
    write_cloud(
        &path,
        &PointCloud::from_points(points),
        CloudFormat::Pcd(PcdData::BinaryCompressed),
    )
    .unwrap();
    let report = json(&kfmap(&["inspect-cloud", path.to_str().unwrap(), "--json"]));
    assert_eq!(report["format"], "pcd-binary-compressed");
    assert_eq!(report["points"], 900);
    assert_eq!(report["points_in_file"], 905);
    assert_eq!(report["filter"]["at_origin"], 5);
    assert_eq!(report["fields"], serde_json::json!(["x", "y", "z"]));
    assert_eq!(report["bbox_min"], serde_json::json!([1.0, 0.0, 0.0]));
    let max = report["bbox_max"].as_array().unwrap();
    assert!(
        (max[0].as_f64().unwrap() - 6.8).abs() < 1e-5
            && (max[1].as_f64().unwrap() - 5.8).abs() < 1e-5
    );
    assert!((report["median_nn_spacing_m"].as_f64().unwrap() - 0.2).abs() < 1e-5);
    // numpy on the same grid (k = 20, r = 1 m): mean planarity 0.842, the exact value
    // depending on how ties among equidistant grid neighbours are broken.
    let planarity = report["mean_planarity"].as_f64().unwrap();
    assert!((0.80..0.90).contains(&planarity), "{planarity}");
}

#[test]
fn inspect_cloud_json_on_real_scan() {
    let Some(path) = require_test_data("small_gicp/target.ply", "inspect_cloud_json_on_real_scan")
    else {
        return;
    };
    let report = json(&kfmap(&["inspect-cloud", path.to_str().unwrap(), "--json"]));
    assert_eq!(report["format"], "ply-binary-le");
    // 69 088 points in the header, 5 032 of them at (0,0,0) (numpy count).
    assert_eq!(report["points_in_file"], 69_088);
    assert_eq!(report["points"], 69_088 - 5_032);
    assert_eq!(
        report["fields"],
        serde_json::json!(["x", "y", "z", "scalar_intensity"])
    );
    let min = report["bbox_min"].as_array().unwrap();
    assert!((min[1].as_f64().unwrap() - -74.6816).abs() < 1e-3);
}

#[test]
fn bad_input_exits_2_with_a_message_naming_the_problem() {
    let dir = temp_dir("bad");
    let truncated = dir.join("cut.pcd");
    std::fs::write(
        &truncated,
        b"FIELDS x y z\nPOINTS 10\nDATA binary\n\x01\x02",
    )
    .unwrap();
    let bad_config = dir.join("bake.toml");
    std::fs::write(&bad_config, "[covariance]\nk-correspondences-for-cov = 1\n").unwrap();
    let empty = dir.join("empty.ply");
    std::fs::write(&empty, b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n").unwrap();
    // Bad tracker flags are refused before any dataset is read or server asked.
    let localize_with = |flags: &[&'static str]| {
        let mut args = vec![
            "localize",
            "--map-name",
            "none",
            "--dataset",
            "/nonexistent",
        ];
        args.extend_from_slice(flags);
        args
    };
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec!["inspect-cloud", "/nonexistent/scan.pcd"], "scan.pcd"),
        (
            vec!["inspect-cloud", truncated.to_str().unwrap()],
            "truncated",
        ),
        (vec!["inspect-cloud", empty.to_str().unwrap()], "empty.ply"),
        (
            vec![
                "inspect-cloud",
                truncated.to_str().unwrap(),
                "--config",
                bad_config.to_str().unwrap(),
            ],
            "k-correspondences-for-cov",
        ),
        (
            vec![
                "inspect-cloud",
                truncated.to_str().unwrap(),
                "--bin-layout",
                "xyzw",
            ],
            "xyzw",
        ),
        (
            vec![
                "inspect-cloud",
                truncated.to_str().unwrap(),
                "--min-range=-3",
            ],
            "--min-range",
        ),
        (vec!["no-such-command"], "no-such-command"),
        (
            vec![
                "relocalize",
                "--map-name",
                "none",
                "--tilt-deg",
                "3",
                "a.pcd",
            ],
            "--tilt-deg",
        ),
        (
            vec![
                "relocalize",
                "--map-name",
                "none",
                "--tilt-deg=95,0",
                "a.pcd",
            ],
            "below 90",
        ),
        (localize_with(&["--ok-pinned", "3"]), "--ok-pinned"),
        (
            localize_with(&["--ok-pinned-after-doubt", "3"]),
            "ok-pinned-after-doubt",
        ),
        (
            localize_with(&["--max-acceleration=-1"]),
            "--max-acceleration",
        ),
        (
            localize_with(&["--vertical-angle-offset-deg", "-9"]),
            "--vertical-angle-offset-deg: option `vertical-angle-offset-deg` = -9 is invalid",
        ),
        (
            localize_with(&["--confirm-after-unpinned", "5000"]),
            "--confirm-after-unpinned",
        ),
        (
            localize_with(&["--lost-after-unfit", "0"]),
            "--lost-after-unfit",
        ),
        (
            localize_with(&["--hypothesis-early-spread", "0"]),
            "--hypothesis-early-spread",
        ),
        (
            localize_with(&["--hypothesis-window", "3"]),
            "--hypothesis-window",
        ),
        (
            localize_with(&["--hypothesis-slide-scans", "11"]),
            "--hypothesis-slide-scans",
        ),
        // A guess starting with a minus sign is read as the guess, not as a flag: the
        // error is the next problem, the missing dataset.
        (
            localize_with(&["--initial", "-1 2 0 0 0 30"]),
            "/nonexistent",
        ),
        (
            vec![
                "register",
                "/nonexistent/a.pcd",
                "/nonexistent/b.pcd",
                "--initial",
                "-1 2 0 0 0 30",
            ],
            "a.pcd",
        ),
    ];
    for (args, expect) in cases {
        let out = kfmap(&args);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {}", stderr(&out));
        assert!(stderr(&out).contains(expect), "{args:?}: {}", stderr(&out));
    }
}

#[test]
fn simulate_writes_a_readable_dataset() {
    let tmp = temp_dir("simulate");
    let dir = tmp.join("out");
    let out = kfmap(&[
        "simulate",
        "--preset",
        "corridor",
        "--seconds",
        "0.3",
        "--beams",
        "16",
        "--tilt-deg",
        "2,-1",
        "--speed",
        "3",
        "--out",
        dir.to_str().unwrap(),
        "--json",
    ]);
    let report = json(&out);
    assert_eq!(report["scans"], 3);
    assert_eq!(report["imu_samples"], 61);
    let meta = std::fs::read_to_string(dir.join("meta.toml")).unwrap();
    assert!(
        meta.contains("preset = \"corridor\"")
            && meta.contains("tilt-deg = [2.0, -1.0]")
            && meta.contains("cruise-speed = 3.0"),
        "{meta}"
    );
    let scan = json(&kfmap(&[
        "inspect-cloud",
        dir.join("scans/000002.pcd").to_str().unwrap(),
        "--json",
    ]));
    // Deskewed sweeps carry no per-point times (they would ask for a second deskew).
    assert_eq!(
        scan["fields"],
        serde_json::json!(["x", "y", "z", "view_x", "view_y", "view_z"])
    );
    // Same folder again: refused, nothing overwritten.
    let again = kfmap(&[
        "simulate",
        "--seconds",
        "0.3",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert_eq!(again.status.code(), Some(2));
    assert!(stderr(&again).contains("not empty"), "{}", stderr(&again));
    for (args, expect) in [
        (
            vec!["simulate", "--preset", "plaza", "--out", "/tmp/x"],
            "plaza",
        ),
        (
            vec!["simulate", "--beams", "40", "--out", "/tmp/kfmap-never"],
            "beams",
        ),
        (
            vec!["simulate", "--tilt-deg", "2", "--out", "/tmp/kfmap-never"],
            "ROLL,PITCH",
        ),
        (
            vec!["simulate", "--seconds", "0", "--out", "/tmp/kfmap-never"],
            "seconds",
        ),
        (
            vec!["simulate", "--speed", "0", "--out", "/tmp/kfmap-never"],
            "speed",
        ),
    ] {
        let out = kfmap(&args);
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        assert!(stderr(&out).contains(expect), "{args:?}: {}", stderr(&out));
    }
}

#[test]
fn every_subcommand_help_has_an_example() {
    for sub in [
        "inspect-cloud",
        "simulate",
        "demo",
        "bake",
        "inspect",
        "bench",
        "register",
        "optimize-graph",
        "plot",
        "gravity",
        "serve",
        "localize",
        "relocalize",
        "query",
        "status",
    ] {
        let out = kfmap(&[sub, "--help"]);
        assert!(out.status.success());
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(
            text.contains("Example:") || text.contains("Examples:"),
            "{sub}"
        );
    }
}

/// `fuse-overlapping-keyframes`: the exact-mode submap of a baked map equals the
/// voxelization of its keyframes' raw scans merged in the map frame (brute force).
#[test]
fn a_fused_bake_serves_the_voxelization_of_the_merged_scans() {
    use kfmap_geometry::geometry::transform_point;
    use kfmap_geometry::io::{ReadOptions, read_cloud};
    use kfmap_map::archive::{OpenOptions, open_map};
    use std::collections::BTreeMap;
    let (_tmp, sim) = simulated("fused");
    let config = sim.parent().unwrap().join("bake.toml");
    std::fs::write(&config, "[map]\nfuse-overlapping-keyframes = true\n").unwrap();
    let path = sim.parent().unwrap().join("fused.kfmap");
    let (sim_arg, path_arg) = (sim.to_str().unwrap(), path.to_str().unwrap());
    let config_arg = config.to_str().unwrap();
    json(&kfmap(&[
        "bake",
        "--dataset",
        sim_arg,
        "--out",
        path_arg,
        "--config",
        config_arg,
        "--json",
    ]));
    let open = OpenOptions {
        approximate_cov: false,
        ..OpenOptions::default()
    };
    let mut map = open_map(&path, open).unwrap().map;
    let voxel = 0.1; // the shipped [keyframes] voxel-size
    assert_eq!(map.options().fuse_voxel_size, voxel);
    let chosen = keyframe_scans(&sim);
    let raw = |id: u64| {
        let scan = sim.join(format!("scans/{:06}.pcd", chosen[id as usize]));
        read_cloud(&scan, &ReadOptions::default()).unwrap().cloud
    };
    for k in map.keyframes() {
        let weights = k.view().unwrap().weights.expect("weights baked");
        let counted: u64 = weights.iter().map(|&w| u64::from(w)).sum();
        assert_eq!(counted, raw(k.id).len() as u64, "keyframe {}", k.id);
    }
    let at = map.keyframes().nth(1).unwrap().pose;
    let active = map.activate(&at).unwrap();
    let ids = active.ids().to_vec();
    assert!(ids.len() > 1, "{ids:?}");
    let mut groups: BTreeMap<[i64; 3], ([f64; 3], usize)> = BTreeMap::new();
    for &id in &ids {
        let pose = map.keyframe(id).unwrap().pose;
        for p in &raw(id).points {
            let q = transform_point(&pose, p);
            let key = q.map(|c| (c / voxel).floor() as i64);
            let entry = groups.entry([key.x, key.y, key.z]).or_default();
            (0..3).for_each(|a| entry.0[a] += q[a]);
            entry.1 += 1;
        }
    }
    let active = map.activate(&at).unwrap();
    let merged = active.merged().unwrap();
    assert_eq!(merged.points.len(), groups.len());
    for (got, (sum, n)) in merged.points.iter().zip(groups.values()) {
        for a in 0..3 {
            let want = sum[a] / *n as f64;
            assert!(
                (got[a] as f64 - want).abs() < 1e-4,
                "{got:?} vs {sum:?} / {n}"
            );
        }
    }
}

/// The scan behind each keyframe `kfmap bake` makes of a dataset: the keyframe decider on
/// its poses, as bake runs it.
fn keyframe_scans(dataset: &std::path::Path) -> Vec<usize> {
    use kfmap_geometry::io::read_trajectory;
    let poses = read_trajectory(&dataset.join("poses_gt.txt"))
        .unwrap()
        .poses;
    choose_keyframes(&poses)
}

/// The keyframe decider (shipped defaults) over `poses`, as bake runs it.
fn choose_keyframes(poses: &[Pose]) -> Vec<usize> {
    use kfmap_map::map::KeyframeDecider;
    let decider = KeyframeDecider::default();
    let mut chosen: Vec<usize> = Vec::new();
    for (i, p) in poses.iter().enumerate() {
        if decider.should_create(chosen.iter().map(|&c| &poses[c]), p) {
            chosen.push(i);
        }
    }
    chosen
}

/// True when two poses agree within `metres` and `metres` radians.
fn close(a: &Pose, b: &Pose, metres: f64) -> bool {
    (a.translation.vector - b.translation.vector).norm() < metres
        && a.rotation.angle_to(&b.rotation) < metres
}

/// A small simulated dataset in a test directory (removed when the first is dropped).
fn simulated(test: &str) -> (TestDir, PathBuf) {
    let tmp = temp_dir(test);
    let dir = tmp.join("sim");
    let out = kfmap(&[
        "simulate",
        "--preset",
        "courtyard",
        "--seconds",
        "3",
        "--beams",
        "16",
        "--out",
        dir.to_str().unwrap(),
        "--json",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    (tmp, dir)
}

#[test]
fn bake_then_inspect_a_simulated_dataset() {
    use kfmap_geometry::io::{ReadOptions, read_cloud, read_trajectory};
    let (_tmp, sim) = simulated("bake");
    let map = sim.parent().unwrap().join("court.kfmap");
    let baked = json(&kfmap(&[
        "bake",
        "--dataset",
        sim.to_str().unwrap(),
        "--out",
        map.to_str().unwrap(),
        "--json",
    ]));
    // Oracle: the decider on the true poses, each chosen scan downsampled at 0.1 m.
    let chosen = keyframe_scans(&sim);
    let poses = read_trajectory(&sim.join("poses_gt.txt")).unwrap().poses;
    let points: usize = chosen
        .iter()
        .map(|i| {
            read_cloud(
                &sim.join(format!("scans/{i:06}.pcd")),
                &ReadOptions::default(),
            )
            .unwrap()
            .cloud
            .voxel_downsample(0.1)
            .unwrap()
            .len()
        })
        .sum();
    assert_eq!(baked["keyframes"], chosen.len());
    assert_eq!(baked["points"], points);
    assert_eq!(baked["scans"], poses.len());
    let size = std::fs::metadata(&map).unwrap().len();
    assert_eq!(baked["bytes"], size);

    let inspected = json(&kfmap(&[
        "inspect",
        map.to_str().unwrap(),
        "--verify",
        "--json",
    ]));
    assert_eq!(inspected["format_version"], 7);
    assert_eq!(inspected["keyframes"], chosen.len());
    assert_eq!(inspected["points"], points);
    assert_eq!(inspected["bytes"], size);
    assert_eq!(inspected["verified"], true);
    let parts = [
        "bytes_points",
        "bytes_covariances",
        "bytes_trees_and_overhead",
        "bytes_index",
        "bytes_place_grid",
    ];
    let sum: u64 = parts.iter().map(|k| inspected[k].as_u64().unwrap()).sum();
    assert!(
        sum <= size && sum + 4096 + 128 * (chosen.len() as u64 + 2) >= size,
        "{sum} vs {size}"
    );
    // 12 bytes a point for positions and 12 for view directions; 24 for covariances.
    assert_eq!(inspected["bytes_points"], 24 * points);
    assert_eq!(inspected["bytes_covariances"], 24 * points);

    // Refuses to overwrite without --force; replaces with it.
    let again = kfmap(&[
        "bake",
        "--dataset",
        sim.to_str().unwrap(),
        "--out",
        map.to_str().unwrap(),
    ]);
    assert_eq!(again.status.code(), Some(2));
    assert!(stderr(&again).contains("--force"), "{}", stderr(&again));
    let _ = std::fs::remove_dir_all(sim.parent().unwrap());
}

#[test]
fn bad_maps_and_datasets_exit_2_naming_the_problem() {
    let (_tmp, sim) = simulated("badmap");
    let dir = sim.parent().unwrap().to_path_buf();
    let map = dir.join("m.kfmap");
    let out = kfmap(&[
        "bake",
        "--dataset",
        sim.to_str().unwrap(),
        "--out",
        map.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let good = std::fs::read(&map).unwrap();
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        p.to_str().unwrap().to_owned()
    };
    let mut flipped = good.clone();
    flipped[40] ^= 1;
    let mut corrupt_keyframe = good.clone();
    corrupt_keyframe[4096 + 64] ^= 1;
    let cases: Vec<(String, &str)> = vec![
        (
            dir.join("missing.kfmap").to_str().unwrap().to_owned(),
            "No such file",
        ),
        (dir.to_str().unwrap().to_owned(), "not a regular file"),
        (write("empty.kfmap", &[]), "empty file"),
        (write("short.kfmap", &good[..good.len() / 2]), "truncated"),
        (write("flipped.kfmap", &flipped), "header is corrupt"),
        (write("text.kfmap", b"# .PCD v0.7\n"), "bad magic"),
    ];
    for (path, message) in cases {
        let out = kfmap(&["inspect", &path]);
        assert_eq!(out.status.code(), Some(2), "{path}");
        assert!(stderr(&out).contains(message), "{path}: {}", stderr(&out));
    }
    // A damaged keyframe opens (only the header and index are read) but fails --verify.
    let damaged = write("damaged.kfmap", &corrupt_keyframe);
    assert!(kfmap(&["inspect", &damaged]).status.success());
    let out = kfmap(&["inspect", &damaged, "--verify"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("corrupt"), "{}", stderr(&out));

    // Datasets: without poses they are built from the scans (no timestamps: no gravity);
    // poses that do not match the scans are refused.
    std::fs::rename(sim.join("poses_gt.txt"), dir.join("poses.tum")).unwrap();
    let built = json(&kfmap(&[
        "bake",
        "--dataset",
        sim.to_str().unwrap(),
        "--out",
        dir.join("built.kfmap").to_str().unwrap(),
        "--json",
    ]));
    assert!(
        built["mapping"]["keyframes"].as_u64().unwrap() >= 1,
        "{built}"
    );
    assert!(built["mapping"]["ate_m"].is_null());
    assert!(built["gravity"].is_null());
    let tum = std::fs::read_to_string(dir.join("poses.tum")).unwrap();
    let short: String = tum.lines().take(5).map(|l| format!("{l}\n")).collect();
    let poses = write("short.tum", short.as_bytes());
    let out = kfmap(&[
        "bake",
        "--dataset",
        sim.to_str().unwrap(),
        "--poses",
        &poses,
        "--out",
        dir.join("x.kfmap").to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("poses for 30 scans"),
        "{}",
        stderr(&out)
    );
    assert!(!dir.join("x.kfmap").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn gravity_and_bake_recover_a_tilted_world() {
    use kfmap_geometry::io::read_trajectory;
    use kfmap_map::archive::{OpenOptions, open_map};
    use nalgebra::Rotation3;
    let tmp = temp_dir("gravity");
    let dir = tmp.join("sim");
    let out = kfmap(&[
        "simulate",
        "--preset",
        "courtyard",
        "--seconds",
        "12",
        "--beams",
        "16",
        "--tilt-deg",
        "2,-3",
        "--no-noise",
        "--out",
        dir.to_str().unwrap(),
        "--json",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    // With noise and bias off only the motion model limits the estimate.
    let g = json(&kfmap(&[
        "gravity",
        "--dataset",
        dir.to_str().unwrap(),
        "--json",
    ]));
    let (roll, pitch) = (
        g["roll_deg"].as_f64().unwrap(),
        g["pitch_deg"].as_f64().unwrap(),
    );
    assert!(
        (roll - 2.0).abs() < 0.02 && (pitch + 3.0).abs() < 0.02,
        "{roll} {pitch}"
    );
    // Keyframes at 0, 1, ..., 11 s: the first one's window ends at the first pose, so no
    // platform acceleration can be removed from it and it is left out.
    assert_eq!(g["members"], 11);
    assert_eq!(g["pool"]["skipped"], 1);
    assert_eq!(g["gravity"]["yaw_deg"], 0.0);

    let map = dir.parent().unwrap().join("tilted.kfmap");
    let baked = json(&kfmap(&[
        "bake",
        "--dataset",
        dir.to_str().unwrap(),
        "--out",
        map.to_str().unwrap(),
        "--json",
    ]));
    assert_eq!(baked["gravity"]["applied"], true);
    // Oracle: every baked pose is the true pose rotated by R_world_map = Ry(-3) Rx(2).
    let world_from_map = Rotation3::from_euler_angles(2f64.to_radians(), -3f64.to_radians(), 0.0);
    let truth = read_trajectory(&dir.join("poses_gt.txt")).unwrap();
    let opened = open_map(&map, OpenOptions::default()).unwrap();
    // Every keyframe but the first (its window ends at the first pose: left out).
    assert_eq!(opened.index.gravity_pool.len(), opened.map.len() - 1);
    assert_eq!(baked["gravity"]["skipped"], 1);
    for k in opened.map.keyframes() {
        let scan = truth
            .stamps
            .as_ref()
            .unwrap()
            .iter()
            .position(|&t| t == k.timestamp)
            .unwrap();
        let applied = k.pose.rotation.to_rotation_matrix()
            * truth.poses[scan].rotation.to_rotation_matrix().inverse();
        let off = (applied * world_from_map.inverse()).angle().to_degrees();
        // Measured 0.052 deg: 12 s of a courtyard barely turn, so the bias and
        // the tilt are hard to tell apart; before, the first keyframe's one raw sample
        // (at rest here, noise off) outweighed the pool and gave 0.004 deg.
        assert!(off < 0.06, "keyframe {}: {off} deg", k.id);
        let moved =
            k.pose.translation.vector - world_from_map * truth.poses[scan].translation.vector;
        // The levelling turns about the map origin: 0.052 deg at 16 m is 0.015 m.
        assert!(moved.norm() < 0.02, "keyframe {}: {moved:?}", k.id);
    }

    // An IMU log on another clock is refused by name.
    let csv = std::fs::read_to_string(dir.join("imu.csv")).unwrap();
    let shifted: String = csv
        .lines()
        .map(|l| match l.split_once(',') {
            Some((t, rest)) if !l.starts_with('t') => {
                format!("{},{rest}\n", t.parse::<f64>().unwrap() + 1000.0)
            }
            _ => format!("{l}\n"),
        })
        .collect();
    std::fs::write(dir.join("imu.csv"), shifted).unwrap();
    let refused = kfmap(&["gravity", "--dataset", dir.to_str().unwrap()]);
    assert_eq!(refused.status.code(), Some(2));
    assert!(
        stderr(&refused).contains("do not overlap"),
        "{}",
        stderr(&refused)
    );
    let _ = std::fs::remove_dir_all(dir.parent().unwrap());
}

/// `--scans A..B` with the dataset's own poses bakes exactly scans A to B-1, each at its
/// pose in the pose file; `--trajectory-out` writes those poses as the map has them
/// (the pose file's, moved by the map's levelling `T_map_input`), stamped with the pose
/// file's times. Built poses over a range start from scan A's frame. Bad ranges and a
/// graph without built poses are refused by name before anything is written.
#[test]
fn bake_a_scan_range_and_write_the_poses_it_used() {
    use kfmap_geometry::geometry::pose_from_xyz_quat;
    use kfmap_geometry::io::{ReadOptions, read_cloud, read_trajectory};
    use kfmap_map::archive::{OpenOptions, open_map};
    let (_tmp, sim) = simulated("scanrange");
    let dir = sim.parent().unwrap();
    let path = |name: &str| dir.join(name).to_str().unwrap().to_owned();
    let (map, tum) = (path("part.kfmap"), path("part.tum"));
    let sim_arg = sim.to_str().unwrap();
    let bake = |extra: &[&str]| {
        let mut args = vec!["bake", "--dataset", sim_arg];
        args.extend(extra);
        kfmap(&args)
    };
    let baked = json(&bake(&[
        "--scans",
        "5..25",
        "--out",
        &map,
        "--trajectory-out",
        &tum,
        "--json",
    ]));
    assert_eq!(baked["scans"], 20);
    assert_eq!(baked["scan_range"], serde_json::json!([5, 25]));
    assert_eq!(baked["dataset_scans"], 30);

    let truth = read_trajectory(&sim.join("poses_gt.txt")).unwrap();
    let true_stamps = &truth.stamps.as_ref().unwrap()[5..25];
    let true_poses = &truth.poses[5..25];
    let opened = open_map(std::path::Path::new(&map), OpenOptions::default()).unwrap();
    let map_from_input = pose_from_xyz_quat(opened.index.map_from_input).unwrap();
    let written = read_trajectory(std::path::Path::new(&tum)).unwrap();
    let stamps = written.stamps.as_ref().unwrap();
    assert_eq!(written.poses.len(), 20);
    for i in 0..20 {
        assert!((stamps[i] - true_stamps[i]).abs() < 1e-9, "line {i}");
        let levelled = map_from_input * true_poses[i];
        assert!(close(&written.poses[i], &levelled, 1e-6), "line {i}");
    }
    // Oracle: the decider over the range's poses, each chosen scan downsampled at 0.1 m.
    let chosen = choose_keyframes(true_poses);
    assert_eq!(opened.map.len(), chosen.len());
    let points: usize = chosen
        .iter()
        .map(|i| {
            let scan = sim.join(format!("scans/{:06}.pcd", 5 + i));
            let cloud = read_cloud(&scan, &ReadOptions::default()).unwrap().cloud;
            cloud.voxel_downsample(0.1).unwrap().len()
        })
        .sum();
    assert_eq!(baked["points"], points);
    for (k, &scan) in opened.map.keyframes().zip(&chosen) {
        assert!((k.timestamp - true_stamps[scan]).abs() < 1e-9, "{}", k.id);
        assert!(close(&k.pose, &written.poses[scan], 1e-6), "{}", k.id);
    }

    // Built poses over a range: the first baked scan is the map origin (levelling only
    // rotates about it), and the map records where the pose file's frame lies in it.
    let built = json(&bake(&[
        "--scans",
        "10..",
        "--build-poses",
        "--out",
        &path("built.kfmap"),
        "--trajectory-out",
        &path("built.tum"),
        "--json",
    ]));
    assert_eq!(built["scan_range"], serde_json::json!([10, 30]));
    let opened = open_map(&dir.join("built.kfmap"), OpenOptions::default()).unwrap();
    let map_from_input = pose_from_xyz_quat(opened.index.map_from_input).unwrap();
    let written = read_trajectory(&dir.join("built.tum")).unwrap();
    assert_eq!(written.poses.len(), 20);
    assert!(written.poses[0].translation.vector.norm() < 1e-9);
    for (i, built) in written.poses.iter().enumerate() {
        let reference = map_from_input * truth.poses[10 + i];
        assert!(close(built, &reference, 0.02), "scan {}", 10 + i);
    }
    assert_eq!(
        written.stamps.unwrap()[0],
        truth.stamps.as_ref().unwrap()[10]
    );

    let refused = path("refused.kfmap");
    for (extra, message) in [
        (
            vec!["--scans", "5..300"],
            "--scans 5..300: the dataset has 30 scans",
        ),
        (
            vec!["--scans", "30.."],
            "--scans 30..: the dataset has 30 scans",
        ),
        (vec!["--scans", "7"], "--scans"),
        (vec!["--scans", "9..3"], "holds no scan"),
        (vec!["--graph-out", "/tmp/never.g2o"], "--build-poses"),
        (
            vec!["--trajectory-out", &tum],
            "part.tum exists; pass --force",
        ),
    ] {
        let mut args = extra.clone();
        args.extend(["--out", &refused]);
        let out = bake(&args);
        assert_eq!(out.status.code(), Some(2), "{extra:?}: {}", stderr(&out));
        assert!(
            stderr(&out).contains(message),
            "{extra:?}: {}",
            stderr(&out)
        );
        assert!(
            stderr(&out).contains(extra[0]),
            "{extra:?}: {}",
            stderr(&out)
        );
        assert!(!dir.join("refused.kfmap").exists(), "{extra:?}");
    }
}

/// Poses built from the scans over a lap (courtyard at 4 m/s): `--graph-out` writes the
/// keyframe pose graph the summary reports (its keyframes, their consecutive edges and
/// the accepted loops), read back by the project's g2o reader at the summary's final
/// error, each vertex (named by its scan) at that scan's pose in `--trajectory-out`,
/// which holds every scan's built pose as the map has it, with the dataset's stamps.
#[test]
fn bake_with_built_poses_writes_its_pose_graph_and_trajectory() {
    use kfmap_geometry::io::read_trajectory;
    use kfmap_graph::pose_graph::read_g2o;
    use kfmap_map::archive::{OpenOptions, open_map};
    let tmp = temp_dir("bakegraph");
    let sim = tmp.join("sim");
    let out = kfmap(&[
        "simulate",
        "--preset",
        "courtyard",
        "--seconds",
        "26",
        "--speed",
        "4",
        "--beams",
        "16",
        "--h-res-deg",
        "0.4",
        "--out",
        sim.to_str().unwrap(),
        "--json",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let (map, tum, g2o) = (
        tmp.join("lap.kfmap"),
        tmp.join("lap.tum"),
        tmp.join("lap.g2o"),
    );
    let baked = json(&kfmap(&[
        "bake",
        "--dataset",
        sim.to_str().unwrap(),
        "--build-poses",
        "--out",
        map.to_str().unwrap(),
        "--trajectory-out",
        tum.to_str().unwrap(),
        "--graph-out",
        g2o.to_str().unwrap(),
        "--json",
    ]));
    let mapping = &baked["mapping"];
    let keyframes = mapping["keyframes"].as_u64().unwrap() as usize;
    let loops = mapping["loops_accepted"].as_u64().unwrap() as usize;
    assert!(loops >= 1, "the lap closes: {mapping}");

    let (graph, fixed) = read_g2o(&g2o).unwrap();
    assert_eq!(graph.len(), keyframes);
    assert_eq!(graph.edges().len(), keyframes - 1 + loops);
    assert_eq!(fixed, Some(graph.ids()[0]));
    assert!(graph.ids().windows(2).all(|w| w[0] < w[1]));
    let rank = |id: u64| graph.ids().iter().position(|&v| v == id).unwrap();
    let consecutive = graph
        .edges()
        .iter()
        .filter(|e| rank(e.to) == rank(e.from) + 1)
        .count();
    assert_eq!(consecutive, keyframes - 1);
    // The vertices are the written (jointly refined) poses, the edges the pose graph's:
    // optimized again from the file, the graph returns to the summary's final error
    // (loop kernels are not in g2o files; at these residuals they are quadratic), and
    // the refined vertices sit no lower than that optimum.
    let final_error = mapping["graph_error_final"].as_f64().unwrap();
    let mut reoptimized = graph.clone();
    let report = reoptimized
        .optimize(&kfmap_graph::pose_graph::GraphParams::default())
        .unwrap();
    assert!(
        (report.final_error - final_error).abs() <= 1e-2 * final_error + 1e-9,
        "{} vs {final_error}",
        report.final_error
    );
    assert!(
        graph.error() >= (1.0 - 1e-2) * final_error,
        "{}",
        graph.error()
    );

    let truth = read_trajectory(&sim.join("poses_gt.txt")).unwrap();
    let written = read_trajectory(&tum).unwrap();
    assert_eq!(written.poses.len(), truth.poses.len());
    assert_eq!(baked["scans"], truth.poses.len());
    let (stamps, true_stamps) = (written.stamps.unwrap(), truth.stamps.unwrap());
    for (a, b) in stamps.iter().zip(&true_stamps) {
        assert!((a - b).abs() < 1e-9);
    }
    for &id in graph.ids() {
        let pose = graph.pose(id).unwrap();
        assert!(
            close(pose, &written.poses[id as usize], 1e-6),
            "vertex {id}"
        );
    }
    let opened = open_map(&map, OpenOptions::default()).unwrap();
    for k in opened.map.keyframes() {
        let scan = true_stamps.iter().position(|&t| t == k.timestamp).unwrap();
        assert!(
            close(&k.pose, &written.poses[scan], 1e-6),
            "keyframe {}",
            k.id
        );
    }
}

/// Output into a closed pipe (`kfmap ... | head`) ends the process quietly
/// (killed by SIGPIPE, status 141 in a shell, or 0), never with a panic.
#[test]
fn a_closed_output_pipe_ends_quietly() {
    use std::os::unix::process::ExitStatusExt;
    use std::process::Stdio;
    let dir = temp_dir("closed_pipe");
    let out_dir = dir.join("sim");
    let mut child = Command::new(common::kfmap_bin())
        .args([
            "simulate",
            "--preset",
            "courtyard",
            "--seconds",
            "0.3",
            "--out",
        ])
        .arg(&out_dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Close the reading end before the child prints its summary.
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(
        out.status.success() || out.status.signal() == Some(libc::SIGPIPE),
        "{:?} {stderr}",
        out.status
    );
}

/// `kfmap bench --quick --json` without the shared data: every row names its data,
/// threads and unit with a positive finite value, synthetic scans carry no anchor (an
/// anchor's figure stands only beside the same data), and the rows that need real data
/// are listed as skipped, not faked.
#[test]
fn bench_table_json_rows_without_data() {
    let out = Command::new(common::kfmap_bin())
        .args(["bench", "--quick", "--json"])
        .env("KFMAP_DATA_DIR", "/nonexistent")
        .output()
        .expect("run kfmap bench");
    let report = json(&out);
    let rows = report["rows"].as_array().unwrap();
    let names: Vec<&str> = rows.iter().map(|r| r["name"].as_str().unwrap()).collect();
    for wanted in [
        "covariances",
        "cov2cov per scan, approximate",
        "GICP from raw clouds",
        "cold start",
        "bake throughput",
        "IPC round trip (echo), 100000 points",
        "cov2cov throughput, 4 client processes",
    ] {
        assert!(
            names.iter().any(|n| n.starts_with(wanted)),
            "{wanted}: {names:?}"
        );
    }
    for row in rows {
        let value = row["value"].as_f64().unwrap();
        assert!(value.is_finite() && value > 0.0, "{row}");
        assert!(row["threads"].as_u64().unwrap() >= 1, "{row}");
        assert!(!row["data"].as_str().unwrap().is_empty(), "{row}");
        assert!(!row["unit"].as_str().unwrap().is_empty(), "{row}");
        assert!(
            row["anchor"].is_null(),
            "an anchor beside synthetic data: {row}"
        );
    }
    let skipped = report["skipped"].as_array().unwrap();
    // The remote rows need a private network namespace: skipped only where the machine
    // has none, never under CI.
    let no_namespace = skipped
        .iter()
        .any(|s| s.as_str().unwrap().starts_with("remote rows"));
    assert!(!(no_namespace && kfmap_testdata::under_ci()), "{skipped:?}");
    if !no_namespace {
        assert!(
            names
                .iter()
                .any(|n| n.starts_with("server-side localize, 20k points, local")),
            "{names:?}"
        );
    }
    // Localization on balm_os0, the parking-garage pose graph, the bake from a bag
    // against balm_os0's files, and the automotive drive (its scans extracted).
    assert_eq!(skipped.len(), 4 + no_namespace as usize, "{skipped:?}");
    assert!(
        skipped
            .iter()
            .any(|s| s.as_str().unwrap().starts_with("automotive drive: needs")),
        "{skipped:?}"
    );
}
