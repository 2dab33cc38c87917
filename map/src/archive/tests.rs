use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use proptest::prelude::*;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;
use crate::map::{Keyframe, KeyframeMap, KeyframeMapOptions, MapError};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::Pose;
use kfmap_testdata::Scratch;

fn pose(x: f64, y: f64, yaw: f64) -> Pose {
    Pose::new(Vector3::new(x, y, 0.0), Vector3::new(0.0, 0.0, yaw))
}

/// Random keyframes near the origin; every other one carries view directions.
fn cloud(rng: &mut StdRng, n: usize, with_view: bool) -> PointCloud {
    let points: Vec<[f32; 3]> = (0..n)
        .map(|_| {
            [
                rng.random_range(-5.0..5.0),
                rng.random_range(-5.0..5.0),
                rng.random_range(-1.0..1.0),
            ]
        })
        .collect();
    let mut c = PointCloud::from_points(points);
    if with_view {
        c.view_dirs = Some(
            c.points
                .iter()
                .map(|p| {
                    let n = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt().max(1e-3);
                    [p[0] / n, p[1] / n, p[2] / n]
                })
                .collect(),
        );
    }
    c
}

fn sample_map(options: KeyframeMapOptions) -> KeyframeMap {
    let mut rng = StdRng::seed_from_u64(5);
    let mut map = KeyframeMap::new(options).unwrap();
    for (i, (x, y, yaw)) in [
        (0.0, 0.0, 0.0),
        (2.0, 1.0, 0.4),
        (-1.5, 2.0, -0.7),
        (1.0, -2.0, 2.0),
    ]
    .into_iter()
    .enumerate()
    {
        map.insert(cloud(&mut rng, 1200, i % 2 == 0), pose(x, y, yaw), i as f64)
            .unwrap();
    }
    map
}

fn baked(dir: &Scratch, map: &KeyframeMap) -> PathBuf {
    let path = dir.file("map.kfmap");
    save_map(map, &[], &path).unwrap();
    path
}

/// Every query kind on both maps, at several poses: identical answers.
fn assert_same_answers(heap: &mut KeyframeMap, file: &mut KeyframeMap) {
    let mut rng = StdRng::seed_from_u64(11);
    let scan = cloud(&mut rng, 700, true);
    for at in [
        pose(0.3, 0.2, 0.1),
        pose(1.5, -1.0, 1.7),
        pose(-1.0, 2.0, -0.5),
    ] {
        let a = heap.activate(&at).unwrap();
        let b = file.activate(&at).unwrap();
        assert_eq!(a.ids(), b.ids());
        for _ in 0..300 {
            let q = [
                rng.random_range(-6.0..6.0),
                rng.random_range(-6.0..6.0),
                rng.random_range(-2.0..2.0),
            ];
            assert_eq!(a.nearest_one(&q), b.nearest_one(&q));
            assert_eq!(a.nearest_k(&q, 9), b.nearest_k(&q, 9));
            assert_eq!(a.within_radius(&q, 0.5), b.within_radius(&q, 0.5));
        }
        let pa = a.cov2cov(&scan, &at, 1.0, None).unwrap();
        let pb = b.cov2cov(&scan, &at, 1.0, None).unwrap();
        assert!(pa.len() > 300, "{} pairings", pa.len());
        assert_eq!(pa, pb);
    }
}

#[test]
fn baked_and_heap_maps_answer_identically_in_both_modes() {
    let dir = Scratch::new("archive-identical");
    for approximate in [true, false] {
        let options = KeyframeMapOptions {
            approximate_cov: approximate,
            ..KeyframeMapOptions::default()
        };
        let mut heap = sample_map(options);
        let path = baked(&dir, &heap);
        let open = OpenOptions {
            approximate_cov: approximate,
            ..OpenOptions::default()
        };
        let mut file = open_map(&path, open).unwrap().map;
        assert!(file.keyframes().all(|k| k.is_baked()));
        assert_eq!(file.len(), 4);
        assert_eq!(file.next_id(), 4);
        for (a, b) in heap.keyframes().zip(file.keyframes()) {
            assert_eq!(
                (a.id, a.pose, a.timestamp, a.bbox),
                (b.id, b.pose, b.timestamp, b.bbox)
            );
            let (va, vb) = (a.view().unwrap(), b.view().unwrap());
            assert_eq!(va.points, vb.points);
            assert_eq!(va.view_dirs, vb.view_dirs);
            assert_eq!(va.covariances, vb.covariances);
        }
        assert_eq!(
            heap.covisibility().snapshot(),
            file.covisibility().snapshot()
        );
        assert_same_answers(&mut heap, &mut file);
    }
}

#[test]
fn weighted_keyframes_and_their_fusion_survive_baking() {
    let dir = Scratch::new("archive-weighted");
    let voxel = 0.4;
    let options = KeyframeMapOptions {
        fuse_voxel_size: voxel,
        ..KeyframeMapOptions::default()
    };
    let mut rng = StdRng::seed_from_u64(8);
    let mut heap = KeyframeMap::new(options).unwrap();
    for (i, at) in [
        pose(0.0, 0.0, 0.0),
        pose(1.0, 0.5, 0.3),
        pose(-0.5, 1.0, -0.4),
    ]
    .into_iter()
    .enumerate()
    {
        let v = cloud(&mut rng, 3000, i % 2 == 0)
            .voxelize(voxel, Some(&at))
            .unwrap();
        let cov = &options.covariance;
        let k = Keyframe::build_weighted(i as u64, at, 0.0, v.cloud, Some(v.counts), cov);
        heap.insert_keyframe(k.unwrap()).unwrap();
    }
    let path = baked(&dir, &heap);
    let open = OpenOptions {
        approximate_cov: false,
        ..OpenOptions::default()
    };
    let mut file = open_map(&path, open).unwrap().map;
    assert_eq!(file.options().fuse_voxel_size, voxel);
    for (a, b) in heap.keyframes().zip(file.keyframes()) {
        let (wa, wb) = (a.view().unwrap().weights, b.view().unwrap().weights);
        assert!(wa.is_some());
        assert_eq!(wa, wb);
    }
    assert_same_answers(&mut heap, &mut file);
    // Overlapping keyframes fused: fewer merged points than keyframe points.
    let at = pose(0.2, 0.3, 0.0);
    let merged = file.activate(&at).unwrap().merged().unwrap().points.len();
    let stacked: usize = file.keyframes().map(|k| k.len()).sum();
    assert!(merged < stacked, "{merged} of {stacked}");
}

#[test]
fn trees_and_covariances_left_out_are_rebuilt_on_first_use() {
    let dir = Scratch::new("archive-rebuilt");
    let options = KeyframeMapOptions {
        serialize_kdtrees: false,
        serialize_covariances: false,
        ..KeyframeMapOptions::default()
    };
    let mut heap = sample_map(options);
    let path = baked(&dir, &heap);
    let full = sample_map(KeyframeMapOptions::default());
    let full_path = dir.file("full.kfmap");
    save_map(&full, &[], &full_path).unwrap();
    let slim = std::fs::metadata(&path).unwrap().len();
    let fat = std::fs::metadata(&full_path).unwrap().len();
    assert!(slim * 2 < fat, "{slim} vs {fat} bytes");
    let mut file = open_map(&path, OpenOptions::default()).unwrap().map;
    heap.set_approximate_cov(true);
    assert_same_answers(&mut heap, &mut file);
}

#[test]
fn a_reopened_map_keeps_growing_like_the_original() {
    let dir = Scratch::new("archive-grow");
    let mut heap = sample_map(KeyframeMapOptions::default());
    let path = baked(&dir, &heap);
    let mut file = open_map(&path, OpenOptions::default()).unwrap().map;
    file.set_approximate_cov(false);
    let mut rng = StdRng::seed_from_u64(3);
    let extra = cloud(&mut rng, 900, false);
    assert_eq!(
        heap.insert(extra.clone(), pose(0.5, 0.5, 0.3), 9.0)
            .unwrap(),
        4
    );
    assert_eq!(file.insert(extra, pose(0.5, 0.5, 0.3), 9.0).unwrap(), 4);
    file.set_pose(1, pose(2.5, 1.0, 0.4)).unwrap();
    heap.set_pose(1, pose(2.5, 1.0, 0.4)).unwrap();
    heap.remove(2).unwrap();
    file.remove(2).unwrap();
    assert_eq!(
        heap.covisibility().snapshot(),
        file.covisibility().snapshot()
    );
    assert_same_answers(&mut heap, &mut file);
    // Saving a map whose keyframes come from a file rebuilds their trees: same answers.
    let again = dir.file("again.kfmap");
    save_map(&file, &[], &again).unwrap();
    let mut reopened = open_map(
        &again,
        OpenOptions {
            approximate_cov: false,
            ..OpenOptions::default()
        },
    )
    .unwrap()
    .map;
    assert_same_answers(&mut heap, &mut reopened);
}

#[test]
fn gravity_pool_and_header_round_trip() {
    let dir = Scratch::new("archive-gravity");
    let map = sample_map(KeyframeMapOptions::default());
    let pool = [GravityRecord {
        keyframe: 2,
        mean_acc: [0.1, -0.2, 9.8],
        std: 0.05,
        samples: 40,
    }];
    let path = dir.file("g.kfmap");
    let summary = save_map(&map, &pool, &path).unwrap();
    assert_eq!(summary.bytes, std::fs::metadata(&path).unwrap().len());
    assert_eq!(summary.points, 4800);
    let opened = open_map(&path, OpenOptions::default()).unwrap();
    assert_eq!(opened.index.gravity_pool, pool);
    assert_eq!(opened.header.format_version, FORMAT_VERSION);
    assert!(opened.header.options_toml.contains("max-view-angle-deg"));
    opened.verify_payload().unwrap();
    opened.verify_keyframes(|_| {}).unwrap();
}

fn open_err(path: &Path) -> ArchiveError {
    match open_map(path, OpenOptions::default()) {
        Ok(_) => panic!("{} opened", path.display()),
        Err(e) => e,
    }
}

#[test]
fn bad_files_are_named_errors() {
    let dir = Scratch::new("archive-bad");
    let path = baked(&dir, &sample_map(KeyframeMapOptions::default()));
    let good = std::fs::read(&path).unwrap();
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.file(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };

    assert!(matches!(
        open_err(&dir.file("missing.kfmap")),
        ArchiveError::Io { .. }
    ));
    assert!(matches!(open_err(&dir.0), ArchiveError::NotAFile(_)));
    assert!(matches!(
        open_err(&write("empty", &[])),
        ArchiveError::EmptyFile(_)
    ));
    let truncated = write("truncated", &good[..good.len() - 1000]);
    assert!(matches!(
        open_err(&truncated),
        ArchiveError::Truncated { .. }
    ));
    let mut magic = good.clone();
    magic[0] = b'X';
    assert!(matches!(
        open_err(&write("magic", &magic)),
        ArchiveError::BadMagic
    ));
    let mut newer = good.clone();
    newer[8] = 8;
    assert!(matches!(
        open_err(&write("newer", &newer)),
        ArchiveError::NewerVersion {
            found: 8,
            supported: 7
        }
    ));
    // Version 1 held kiddo trees, version 2 no T_map_input, version 3 no point weights,
    // version 4 no place grid, version 5 unblocked tree leaves, version 6 a dense place
    // grid: such maps are baked again.
    for old in [1u8, 2, 3, 4, 5, 6] {
        let mut older = good.clone();
        older[8] = old;
        let error = open_err(&write("older", &older));
        assert!(error.to_string().contains("format version"), "{error}");
        assert!(matches!(
            error,
            ArchiveError::OldVersion { found, supported: 7 } if found == old as u32
        ));
    }
    let mut wide = good.clone();
    wide[13] = 8; // a 64-bit-pointer build's file
    assert!(matches!(
        open_err(&write("wide", &wide)),
        ArchiveError::PointerWidth { found: 8, .. }
    ));
    let mut narrow = good.clone();
    narrow[13] = 2;
    assert!(matches!(
        open_err(&write("narrow", &narrow)),
        ArchiveError::PointerWidth { found: 2, .. }
    ));
    let mut header = good.clone();
    header[100] ^= 0x01; // inside the options text
    assert!(matches!(
        open_err(&write("header", &header)),
        ArchiveError::HeaderCorrupt
    ));
    let mut index = good.clone();
    let at = index.len() - 20;
    index[at] ^= 0x40;
    assert!(matches!(
        open_err(&write("index", &index)),
        ArchiveError::IndexCorrupt(_)
    ));
    let mut trailing = good.clone();
    trailing.extend_from_slice(b"junk");
    assert!(matches!(
        open_err(&write("trailing", &trailing)),
        ArchiveError::IndexCorrupt(_)
    ));

    // A flipped byte in keyframe 0's points: the file opens (O(1)), the keyframe fails
    // on first use, the others still answer, and both verifications catch it.
    let mut payload = good.clone();
    payload[HEADER_LEN + 200] ^= 0x20;
    let p = write("payload", &payload);
    let opened = open_map(&p, OpenOptions::default()).unwrap();
    assert!(matches!(
        opened.verify_payload(),
        Err(ArchiveError::PayloadCorrupt)
    ));
    assert!(matches!(
        opened.verify_keyframes(|_| {}),
        Err(ArchiveError::KeyframeCorrupt { id: 0, .. })
    ));
    let mut map = opened.map;
    assert!(matches!(
        map.activate_ids(vec![0, 1]).err(),
        Some(MapError::Archive(ArchiveError::KeyframeCorrupt {
            id: 0,
            ..
        }))
    ));
    assert!(map.activate_ids(vec![1, 2]).is_ok());
}

#[test]
fn an_abandoned_write_leaves_nothing_behind() {
    let dir = Scratch::new("archive-abandon");
    let map = sample_map(KeyframeMapOptions::default());
    let path = dir.file("map.kfmap");
    std::fs::write(&path, b"previous map").unwrap();
    {
        let mut writer = MapWriter::create(&path, map.options()).unwrap();
        writer.write_keyframe(map.keyframe(0).unwrap()).unwrap();
        // Out-of-order ids are refused; dropping the writer abandons the file.
        assert!(writer.write_keyframe(map.keyframe(0).unwrap()).is_err());
    }
    let names: Vec<_> = std::fs::read_dir(&dir.0)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, vec![std::ffi::OsString::from("map.kfmap")]);
    assert_eq!(std::fs::read(&path).unwrap(), b"previous map");
}

/// A small valid map file, built once for the mutation property.
fn small_file() -> &'static [u8] {
    static BYTES: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    BYTES.get_or_init(|| {
        let dir = Scratch::new("archive-small");
        let mut rng = StdRng::seed_from_u64(8);
        let mut map = KeyframeMap::new(KeyframeMapOptions::default()).unwrap();
        map.insert(cloud(&mut rng, 150, true), pose(0.0, 0.0, 0.0), 0.0)
            .unwrap();
        map.insert(cloud(&mut rng, 150, false), pose(1.5, 0.0, 0.5), 1.0)
            .unwrap();
        std::fs::read(baked(&dir, &map)).unwrap()
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    /// Corrupted or cut files never panic: either a named error, or (when the damage
    /// misses every checked byte, i.e. only padding) a map that answers.
    #[test]
    fn mutated_files_error_or_answer(flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..4),
                                     cut in prop::option::of(any::<prop::sample::Index>()),
                                     trust in any::<bool>()) {
        let mut bytes = small_file().to_vec();
        for (at, mask) in flips {
            let i = at.index(bytes.len());
            bytes[i] ^= mask;
        }
        if let Some(cut) = cut {
            bytes.truncate(cut.index(bytes.len()));
        }
        static CASE: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let case = CASE.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = Scratch::new(&format!("mutated-{case}"));
        let path = dir.file("m.kfmap");
        std::fs::write(&path, &bytes).unwrap();
        if let Ok(opened) = open_map(&path, OpenOptions { trust, ..OpenOptions::default() }) {
            let _ = opened.verify_keyframes(|_| {});
            let mut map = opened.map;
            for id in [0, 1] {
                if let Ok(active) = map.activate_ids(vec![id]) {
                    prop_assert!(active.nearest_one(&[0.0, 0.0, 0.0]).is_some());
                }
            }
        }
    }
}

/// The place grid is baked beside the keyframes: its map points' voxels are marked
/// (each point within half a half-resolution voxel's diagonal of one), and a damaged
/// grid segment is refused by name when first used, while the map still opens and
/// serves its keyframes.
#[test]
fn the_place_grid_is_baked_and_a_damaged_one_is_named() {
    let dir = Scratch::new("archive-place");
    let map = sample_map(KeyframeMapOptions::default());
    let path = baked(&dir, &map);
    let opened = open_map(&path, OpenOptions::default()).unwrap();
    let view = opened.place.as_ref().expect("a place grid").view().unwrap();
    for keyframe in map.keyframes() {
        for p in keyframe.map_points().unwrap().iter().step_by(7) {
            assert!(crate::place::tests::marked_near(&view, p), "{p:?}");
        }
    }
    let entry = opened.index.place.unwrap();
    let mut bytes = std::fs::read(&path).unwrap();
    bytes[HEADER_LEN + entry.offset as usize + entry.len as usize / 2] ^= 0x10;
    let damaged = dir.file("damaged.kfmap");
    std::fs::write(&damaged, &bytes).unwrap();
    let opened = open_map(&damaged, OpenOptions::default()).unwrap();
    let error = opened.place.as_ref().unwrap().view().unwrap_err();
    assert!(error.to_string().contains("place grid"), "{error}");
    assert!(opened.map.keyframes().all(|k| k.view().is_ok()));
}

/// The place grid read back from a reopened file is the grid the writer built: same
/// frame, extent and bytes, and the same answer at every level for every voxel of the
/// grid and a margin around it.
#[test]
fn the_place_grid_round_trips_through_a_file() {
    let dir = Scratch::new("archive-place-trip");
    let map = sample_map(KeyframeMapOptions::default());
    let path = baked(&dir, &map);
    let params = crate::place::GridParams::default();
    let mut builder = crate::place::GridBuilder::new(&params);
    for keyframe in map.keyframes() {
        builder.add_anchor(keyframe.pose.translation.vector.into());
        builder.add_points(keyframe.map_points().unwrap());
    }
    let built = builder.finish(&params).unwrap();
    let expected = built.view();
    let opened = open_map(&path, OpenOptions::default()).unwrap();
    let view = opened.place.as_ref().unwrap().view().unwrap();
    assert_eq!(view.dims(), expected.dims());
    assert_eq!(view.origin(), expected.origin());
    assert_eq!(view.levels(), expected.levels());
    assert_eq!(view.bytes(), expected.bytes());
    assert_eq!(view.level_blocks(), expected.level_blocks());
    assert_eq!(view.region(), expected.region());
    let [nx, ny, nz] = view.dims();
    let mut marked = 0;
    for level in 0..view.levels() {
        for z in -3..nz + 3 {
            for y in -3..ny + 3 {
                for x in -3..nx + 3 {
                    let answer = view.marked(level, [x, y, z]);
                    assert_eq!(answer, expected.marked(level, [x, y, z]));
                    marked += usize::from(answer);
                }
            }
        }
    }
    assert!(marked > 0);
}

/// Keyframes written in a batch (serialized and their grid parts found in parallel)
/// make the file one-by-one writing makes, byte for byte.
#[test]
fn a_batch_of_keyframes_is_written_as_one_by_one() {
    let dir = Scratch::new("archive-batch");
    let map = sample_map(KeyframeMapOptions::default());
    let one_by_one = baked(&dir, &map);
    let batch = dir.file("batch.kfmap");
    let mut writer = MapWriter::create(&batch, map.options()).unwrap();
    let keyframes: Vec<Keyframe> = map.keyframes().cloned().collect();
    writer.write_keyframes(&keyframes[..1]).unwrap();
    writer.write_keyframes(&keyframes[1..]).unwrap();
    // Ids must still ascend across batches.
    assert!(writer.write_keyframes(&keyframes[..1]).is_err());
    writer
        .finish(map.next_id(), &map.covisibility().snapshot(), &[])
        .unwrap();
    let (a, b) = (
        std::fs::read(&one_by_one).unwrap(),
        std::fs::read(&batch).unwrap(),
    );
    assert!(a.len() > 10_000);
    assert!(a == b, "the files differ");
}
