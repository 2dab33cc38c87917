//! Localization over IPC on real LiDAR data (`../shared/data`): maps baked from some
//! scans at their reference poses, the others localized against a running server.
//! Skipped with a printed reason when the data is missing (failing under CI=true).

use crate::common;

use std::time::Duration;

use common::{Prefix, Server, bake_map_with, temp_dir};
use kfmap_client::{Client, ClientOptions, LocalizeOptions, Localized};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::cov::CovOptions;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::read_keyframe_graph;
use kfmap_geometry::io::{BinLayout, ReadOptions, read_cloud, read_trajectory};
use kfmap_map::map::KeyframeMapOptions;
use kfmap_map::select::SelectionOptions;
use kfmap_protocol::{Cov2CovMode, ScanPayload};
use kfmap_testdata::require_test_data;
use nalgebra::{UnitQuaternion, Vector3};

fn read_bin(path: &std::path::Path, layout: BinLayout) -> PointCloud {
    let options = ReadOptions {
        bin_layout: Some(layout),
        ..ReadOptions::default()
    };
    read_cloud(path, &options).expect("cloud").cloud
}

/// Translation (m) and rotation (deg) between two poses.
fn gap(a: &Pose, b: &Pose) -> (f64, f64) {
    let d = a.inverse() * b;
    (d.translation.vector.norm(), d.rotation.angle().to_degrees())
}

fn localize(
    client: &mut Client,
    cloud: &PointCloud,
    guess: &Pose,
    max_iterations: u32,
    mode: Cov2CovMode,
) -> Localized {
    let scan = cloud.voxel_downsample(0.25).unwrap();
    let payload = ScanPayload {
        points: &scan.points,
        view_dirs: None,
        covariances: None,
    };
    let options = LocalizeOptions {
        max_iterations,
        max_pair_dist: 1.0,
        mode,
        ..LocalizeOptions::default()
    };
    client
        .localize(&payload, guess, &options)
        .expect("localize")
}

fn client(prefix: &Prefix, name: &str) -> Client {
    Client::connect(
        name,
        ClientOptions {
            iceoryx_prefix: Some(prefix.0.clone()),
            timeout: Duration::from_secs(60),
            spin: false,
        },
    )
    .unwrap()
}

/// Bake four of the five KITTI 07 keyframes at their `graph.txt` poses, localize the
/// fifth from its pose perturbed by 0.5 m and 3 deg. Issue target: within 3 cm and
/// 0.15 deg of `graph.txt` for every held-out choice (GICP agrees with it to 0.9-2.7
/// cm). The map answers from the two nearest keyframes (`max_search_keyframes` 2, no
/// diverse slot): 0.62 / 0.72 / 1.38 / 1.53 / 2.92 cm, 0.020-0.141 deg, the same within
/// 0.1 cm for map voxels of 0-0.25 m. With MOLA's default (3 keyframes, 1 for heading
/// diversity) the end keyframe 4 also gets keyframe 0, 28 m away, and lands 3.22 cm off;
/// small_gicp 1.0.1 against the same keyframes merged shows the same (2.81 cm with the
/// two nearest, 3.13 cm with three).
#[test]
fn kitti07_held_out_keyframes_localize_over_ipc() {
    let Some(dir) = require_test_data("kitti07", "kitti07_held_out_keyframes_localize_over_ipc")
    else {
        return;
    };
    let poses = read_keyframe_graph(&dir.join("graph.txt")).unwrap();
    let clouds: Vec<PointCloud> = (0..5)
        .map(|i| read_bin(&dir.join(format!("keyframe_{i}.bin")), BinLayout::Xyz))
        .collect();
    let work = temp_dir("kitti07");
    let prefix = Prefix::new("kitti07");
    let offset = Pose::from_parts(
        Vector3::new(0.3, -0.3, 0.2828).into(),
        UnitQuaternion::from_euler_angles(0.0, 0.0, 3f64.to_radians()),
    );
    // The two nearest keyframes answer; see the doc comment.
    let two_nearest = KeyframeMapOptions {
        selection: SelectionOptions {
            max_search_keyframes: 2,
            num_diverse_keyframes: 0,
            ..SelectionOptions::default()
        },
        ..KeyframeMapOptions::default()
    };
    for held_out in 0..5 {
        let keyframes: Vec<(PointCloud, Pose)> = (0..5)
            .filter(|&i| i != held_out)
            .map(|i| (clouds[i].clone(), poses[i]))
            .collect();
        let map = work.join(format!("without{held_out}.kfmap"));
        bake_map_with(&map, &keyframes, 0.1, two_nearest);
        let name = format!("kitti07-{held_out}");
        let _server = Server::start(&map, &name, &prefix.0, &[]);
        let mut client = client(&prefix, &name);
        let guess = poses[held_out] * offset;
        let found = localize(
            &mut client,
            &clouds[held_out],
            &guess,
            50,
            Cov2CovMode::MapDefault,
        );
        let (t, r) = gap(&found.pose, &poses[held_out]);
        println!(
            "kitti07 keyframe {held_out} held out: {:.2} cm, {:.3} deg from graph.txt ({} iterations, inliers {:.2})",
            t * 100.0,
            r,
            found.health.iterations,
            found.health.inlier_ratio
        );
        assert!(t < 0.03 && r < 0.15, "keyframe {held_out}: {t} m, {r} deg");
        assert!(found.health.converged);
    }
}

/// Bake KITTI 00 frames 0, 2, 4 at their ground-truth poses; localize frames 1, 3, 5
/// from the previous frame's true pose. small_gicp 1.0.1 (0.25 m voxels, k = 20
/// without a radius limit, against frames 0, 2, 4 merged, 20 iterations) lands 14, 41
/// and 40 cm (0.09, 0.19, 0.35 deg) from ground truth on these unskewed scans; the
/// issue's target is no worse, frame by frame (its figures are rounded: 0.5 cm and
/// 0.005 deg of slack). small_gicp voxelizes the merged raw scans; a map of keyframes
/// each voxelized on its own stacks their surfaces where they overlap (73 k points
/// instead of 53 k), and lands 15.5, 41.3, 37.2 cm. So the map fuses overlapping
/// keyframes (`fuse_voxel_size`, bake's `fuse-overlapping-keyframes`): keyframes
/// voxelized on the map's grid with their counts, fused in exact mode into exactly the
/// voxelization of the merged scans: 14.3, 41.2, 37.4 cm (0.085, 0.187, 0.348 deg).
#[test]
fn kitti00_frames_localize_no_worse_than_small_gicp() {
    let Some(dir) = require_test_data(
        "kitti00",
        "kitti00_frames_localize_no_worse_than_small_gicp",
    ) else {
        return;
    };
    let truth = read_trajectory(&dir.join("poses_velo_kitti.txt"))
        .unwrap()
        .poses;
    let cloud = |i: usize| read_bin(&dir.join(format!("{i:06}.bin")), BinLayout::Xyzi);
    let work = temp_dir("kitti00");
    let prefix = Prefix::new("kitti00");
    let map = work.join("kitti00.kfmap");
    let unlimited = CovOptions {
        k_correspondences_for_cov: 20,
        max_distance_for_cov: 1000.0,
        ..CovOptions::default()
    };
    bake_map_with(
        &map,
        &[0, 2, 4].map(|i| (cloud(i), truth[i])),
        0.25,
        KeyframeMapOptions {
            covariance: unlimited,
            fuse_voxel_size: 0.25,
            ..KeyframeMapOptions::default()
        },
    );
    let config = work.join("server.toml");
    std::fs::write(
        &config,
        "[covariance]\nk-correspondences-for-cov = 20\nmax-distance-for-cov = 1000.0\n",
    )
    .unwrap();
    let _server = Server::start(
        &map,
        "kitti00",
        &prefix.0,
        &["--config", config.to_str().unwrap()],
    );
    let mut client = client(&prefix, "kitti00");
    // (frame, small_gicp m, small_gicp deg)
    let small_gicp = [(1, 0.14, 0.09), (3, 0.41, 0.19), (5, 0.40, 0.35)];
    for (frame, m_bound, deg_bound) in small_gicp {
        let found = localize(
            &mut client,
            &cloud(frame),
            &truth[frame - 1],
            20,
            Cov2CovMode::Exact,
        );
        let (t, r) = gap(&found.pose, &truth[frame]);
        println!(
            "kitti00 frame {frame}: {:.1} cm, {:.3} deg from ground truth (small_gicp {:.0} cm, {:.2} deg)",
            t * 100.0,
            r,
            m_bound * 100.0,
            deg_bound
        );
        assert!(t <= m_bound + 0.005, "frame {frame}: {t} m");
        assert!(r <= deg_bound + 0.005, "frame {frame}: {r} deg");
    }
}
