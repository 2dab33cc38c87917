//! Every cloud and trajectory file under `../shared/data` in a supported format, read
//! with the filter off: point counts from PROVENANCE.txt (or the file header) and
//! bounding boxes as computed independently with numpy from the raw bytes.

use kfmap_geometry::cloud::FilterOptions;
use kfmap_geometry::geometry::translation_distance;
use kfmap_geometry::io::{
    BinLayout, CloudFormat, PcdData, PlyEncoding, ReadOptions, read_cloud, read_trajectory,
};
use kfmap_testdata::require_test_data;

type Bbox = ([f32; 3], [f32; 3]);

fn unfiltered(layout: Option<BinLayout>) -> ReadOptions {
    ReadOptions {
        bin_layout: layout,
        filter: FilterOptions {
            enabled: false,
            ..FilterOptions::default()
        },
    }
}

fn check(relative: &str, layout: Option<BinLayout>, format: CloudFormat, count: usize, bbox: Bbox) {
    let Some(path) = require_test_data(relative, "real_data") else {
        return;
    };
    let loaded = read_cloud(&path, &unfiltered(layout)).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(loaded.format, format, "{relative}");
    assert_eq!(loaded.cloud.len(), count, "{relative}");
    let got = loaded.cloud.bounding_box().unwrap();
    for axis in 0..3 {
        assert!(
            (got.min[axis] - bbox.0[axis]).abs() < 1e-4,
            "{relative} min: {:?} vs {:?}",
            got.min,
            bbox.0
        );
        assert!(
            (got.max[axis] - bbox.1[axis]).abs() < 1e-4,
            "{relative} max: {:?} vs {:?}",
            got.max,
            bbox.1
        );
    }
}

const KITTI_SOURCE_BBOX: Bbox = ([-23.759, -52.0011, -3.0213], [18.4799, 6.5079, 9.1728]);
const KITTI_TARGET_BBOX: Bbox = ([-23.3375, -74.6816, -2.9573], [19.0247, 8.9195, 10.7959]);

#[test]
fn small_gicp_ply_scans() {
    let ply = CloudFormat::Ply(PlyEncoding::BinaryLittleEndian);
    check(
        "small_gicp/source.ply",
        None,
        ply,
        69_792,
        KITTI_SOURCE_BBOX,
    );
    check(
        "small_gicp/target.ply",
        None,
        ply,
        69_088,
        KITTI_TARGET_BBOX,
    );
}

#[test]
fn fast_gicp_pcd_scans_match_their_ply_twins() {
    // Same scans as small_gicp/, in another format: the same counts and boxes.
    let pcd = CloudFormat::Pcd(PcdData::Binary);
    check(
        "fast_gicp/251370668.pcd",
        None,
        pcd,
        69_088,
        KITTI_TARGET_BBOX,
    );
    check(
        "fast_gicp/251371071.pcd",
        None,
        pcd,
        69_792,
        KITTI_SOURCE_BBOX,
    );
}

#[test]
fn kitti00_velodyne_scans() {
    let cases: [(usize, Bbox); 6] = [
        (
            124_668,
            ([-78.0874, -55.7234, -11.5565], [77.9673, 44.8786, 2.8253]),
        ),
        (
            124_605,
            ([-79.1606, -54.5851, -11.2955], [79.7415, 51.2191, 2.8168]),
        ),
        (
            124_478,
            ([-79.4611, -53.1331, -11.0305], [78.9743, 44.1329, 2.8398]),
        ),
        (
            124_167,
            ([-79.2710, -43.6613, -10.7554], [79.2312, 46.4681, 2.8519]),
        ),
        (
            123_969,
            ([-79.9997, -43.2709, -10.4854], [78.4343, 44.2865, 2.8685]),
        ),
        (
            123_924,
            ([-77.5486, -41.4301, -10.2024], [78.1254, 44.0041, 2.8815]),
        ),
    ];
    for (i, (count, bbox)) in cases.into_iter().enumerate() {
        let name = format!("kitti00/{i:06}.bin");
        check(&name, None, CloudFormat::Bin(BinLayout::Xyzi), count, bbox);
    }
}

#[test]
fn kitti07_raw_keyframes() {
    let cases: [(usize, Bbox); 5] = [
        (
            21_562,
            ([-75.4484, -79.5530, -9.5458], [79.1963, 73.4895, 4.0633]),
        ),
        (
            24_703,
            ([-62.8196, -70.0416, -6.0433], [68.6894, 69.0257, 3.7231]),
        ),
        (
            24_573,
            ([-81.9312, -76.3187, -13.0404], [83.5435, 77.6276, 3.4674]),
        ),
        (
            16_911,
            ([-83.8024, -68.0171, -15.2702], [84.9605, 15.9272, 3.3704]),
        ),
        (
            19_872,
            ([-81.8285, -79.7609, -20.0898], [85.7544, 51.6366, 4.3616]),
        ),
    ];
    for (i, (count, bbox)) in cases.into_iter().enumerate() {
        let name = format!("kitti07/keyframe_{i}.bin");
        check(
            &name,
            Some(BinLayout::Xyz),
            CloudFormat::Bin(BinLayout::Xyz),
            count,
            bbox,
        );
    }
}

#[test]
fn newer_college_raw_and_deskewed_scans() {
    let raw = CloudFormat::Bin(BinLayout::Xyz);
    let cases: [(&str, usize, Bbox); 6] = [
        (
            "raw_00",
            25_109,
            ([-21.9808, -22.2681, -8.0708], [63.0163, 33.5166, 16.2726]),
        ),
        (
            "raw_01",
            20_061,
            ([-18.0814, -18.2448, -15.3810], [56.0789, 35.2171, 18.3143]),
        ),
        (
            "raw_02",
            24_649,
            ([-19.8769, -18.7440, -11.0716], [63.2764, 34.0209, 17.7858]),
        ),
        (
            "deskewed_00",
            25_109,
            ([-63.0301, -33.6661, -7.9878], [22.2376, 22.0689, 16.0231]),
        ),
        (
            "deskewed_01",
            20_061,
            ([-57.4362, -33.1039, -15.5382], [18.1793, 18.1408, 18.0526]),
        ),
        (
            "deskewed_02",
            24_649,
            ([-63.2824, -34.7815, -10.8298], [19.9977, 18.5511, 17.8307]),
        ),
    ];
    for (name, count, bbox) in cases {
        check(
            &format!("newer_college06/{name}.bin"),
            Some(BinLayout::Xyz),
            raw,
            count,
            bbox,
        );
    }
}

#[test]
fn pcl_bunny_ascii_pcd() {
    let bbox = ([-0.0939, 0.0374, -0.0550], [0.0596, 0.1845, 0.0578]);
    check(
        "pcl/bun0.pcd",
        None,
        CloudFormat::Pcd(PcdData::Ascii),
        397,
        bbox,
    );
}

#[test]
fn kitti_bin_without_layout_hint_explains_itself_for_raw_files() {
    let Some(path) = require_test_data("kitti07/keyframe_0.bin", "real_data") else {
        return;
    };
    let err = read_cloud(&path, &unfiltered(None))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("keyframe_0.bin") && err.contains("--bin-layout xyz"),
        "{err}"
    );
}

#[test]
fn invalid_returns_are_filtered_on_load() {
    // PROVENANCE: about 5 000 points at exactly (0,0,0) in each small_gicp scan;
    // numpy counts 5 107 in source.ply and 5 032 in the same target scan.
    for (relative, at_origin, total) in [
        ("small_gicp/source.ply", 5_107, 69_792),
        ("fast_gicp/251370668.pcd", 5_032, 69_088),
    ] {
        let Some(path) = require_test_data(relative, "real_data") else {
            return;
        };
        let loaded = read_cloud(&path, &ReadOptions::default()).unwrap();
        let report = loaded.filter.unwrap();
        assert_eq!(report.at_origin, at_origin, "{relative}");
        assert_eq!(report.non_finite, 0);
        assert_eq!(loaded.cloud.len(), total - at_origin);
    }
}

#[test]
fn trajectories() {
    let Some(dir) = require_test_data("kitti00", "real_data") else {
        return;
    };
    let cam = read_trajectory(&dir.join("poses_cam0_kitti.txt")).unwrap();
    let velo = read_trajectory(&dir.join("poses_velo_kitti.txt")).unwrap();
    assert_eq!((cam.poses.len(), velo.poses.len()), (6, 6));
    // PROVENANCE: about 0.86 m per frame.
    for pair in velo.poses.windows(2) {
        let step = translation_distance(&pair[0], &pair[1]);
        assert!((step - 0.86).abs() < 0.03, "{step}");
    }
    let Some(traj) = require_test_data("imu_real/traj.txt", "real_data") else {
        return;
    };
    let tum = read_trajectory(&traj).unwrap();
    assert_eq!(tum.poses.len(), 2380);
    let stamps = tum.stamps.unwrap();
    assert!((stamps[1] - stamps[0] - 0.1).abs() < 1e-6);
}
