//! A map file larger than 2 GiB (the reach of rkyv's 32-bit relative pointers): written
//! keyframe by keyframe, reopened by mmap, its last keyframe (past 2 GiB) verified and
//! queried. About 2.5 GB under /dev/shm when it has room (the layout is under test,
//! not the disk: 13 s instead of 20 on this VM, most of the difference the writer's
//! fsync), else under $TMPDIR; removed afterwards.

use crate::archive::{HEADER_LEN, MapWriter, OpenOptions, open_map};
use crate::covis::CovisSnapshot;
use crate::map::{Keyframe, KeyframeMapOptions};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::Pose;
use nalgebra::Vector3;

const POINTS: usize = 8 << 20;
const KEYFRAMES: u64 = 6;

/// A jittered 3-D grid: distinct points, deterministic.
fn points() -> Vec<[f32; 3]> {
    (0..POINTS)
        .map(|i| {
            let (x, y, z) = (i % 256, (i / 256) % 256, i / 65536);
            let jitter =
                ((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40) as f32 / (1u64 << 24) as f32;
            [
                x as f32 * 0.1 + jitter * 0.05,
                y as f32 * 0.1,
                z as f32 * 0.1,
            ]
        })
        .collect()
}

#[test]
fn maps_beyond_2_gib_are_written_and_read_in_place() {
    let shm = std::path::Path::new("/dev/shm");
    let scratch = match kfmap_geometry::io::free_bytes(shm) {
        Some(free) if free >= 3 << 30 => kfmap_testdata::Scratch::under(shm, "large-map"),
        _ => kfmap_testdata::Scratch::new("large-map"),
    };
    let path = scratch.file("large.kfmap");

    let cloud = PointCloud::from_points(points());
    let template = Keyframe::from_parts(
        0,
        Pose::identity(),
        0.0,
        cloud,
        vec![[0.01, 0.0, 0.0, 0.01, 0.0, 0.01]; POINTS],
    )
    .unwrap();
    let options = KeyframeMapOptions::default();
    let mut writer = MapWriter::create(&path, &options).unwrap();
    let ids: Vec<u64> = (0..KEYFRAMES).collect();
    // Two at a time, serialized in parallel (the bake's path); the clones share the
    // template's data, so two keyframes' archives are in memory at once.
    for pair in ids.chunks(2) {
        let keyframes: Vec<Keyframe> = pair
            .iter()
            .map(|&id| {
                let mut k = template.clone();
                k.id = id;
                k.pose = Pose::new(Vector3::new(30.0 * id as f64, 0.0, 0.0), Vector3::zeros());
                k
            })
            .collect();
        writer.write_keyframes(&keyframes).unwrap();
    }
    drop(template);
    let summary = writer
        .finish(KEYFRAMES, &CovisSnapshot::default(), &[])
        .unwrap();
    assert!(summary.bytes > 2 << 30, "{} bytes", summary.bytes);

    let opened = open_map(&path, OpenOptions::default()).unwrap();
    let last = opened.index.keyframes.last().unwrap();
    assert!(
        HEADER_LEN as u64 + last.offset > 2 << 30,
        "last segment at {}",
        last.offset
    );
    let mut map = opened.map;
    let active = map.activate_ids(vec![KEYFRAMES - 1]).unwrap();
    let pts = points();
    let offset = 30.0 * (KEYFRAMES - 1) as f32;
    for i in (0..POINTS).step_by(POINTS / 2000) {
        let p = pts[i];
        let hit = active.nearest_one(&[p[0] + offset, p[1], p[2]]).unwrap();
        // The oracle: every point finds itself (up to the f32 round trip through the pose).
        assert_eq!((hit.keyframe, hit.local_index), (KEYFRAMES - 1, i as u32));
        assert!(hit.dist_sq < 1e-8, "{}", hit.dist_sq);
    }
}
