use nalgebra::{Matrix3, Point3, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;
use kfmap_geometry::geometry::{PackedSym3, pack_sym3, to_point, to_vec3, unpack_sym3};

fn pose(x: f64, y: f64, yaw: f64) -> Pose {
    Pose::new(Vector3::new(x, y, 0.0), Vector3::new(0.0, 0.0, yaw))
}

fn random_cloud(rng: &mut StdRng, n: usize) -> PointCloud {
    PointCloud::from_points(
        (0..n)
            .map(|_| {
                [
                    rng.random_range(-5.0..5.0),
                    rng.random_range(-5.0..5.0),
                    rng.random_range(-1.0..1.0),
                ]
            })
            .collect(),
    )
}

/// A map of 4 random keyframes near the origin, in exact or approximate mode.
fn random_map(seed: u64, approximate: bool) -> KeyframeMap {
    let mut rng = StdRng::seed_from_u64(seed);
    let options = KeyframeMapOptions {
        approximate_cov: approximate,
        ..KeyframeMapOptions::default()
    };
    let mut map = KeyframeMap::new(options).unwrap();
    for (i, (x, y, yaw)) in [
        (0.0, 0.0, 0.0),
        (2.0, 1.0, 0.4),
        (-1.5, 2.0, -0.7),
        (30.0, 0.0, 0.0),
    ]
    .into_iter()
    .enumerate()
    {
        map.insert(random_cloud(&mut rng, 1500), pose(x, y, yaw), i as f64)
            .unwrap();
    }
    map
}

fn sq(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    let (dx, dy, dz) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    dx * dx + dy * dy + dz * dz
}

/// Oracle: every active point as a candidate, exactly as each mode defines it
/// (exact: map-frame f32 points; approximate: the query moved into each keyframe).
fn linear_scan(
    map: &KeyframeMap,
    ids: &[KeyframeId],
    q: &[f32; 3],
    approximate: bool,
) -> Vec<MapHit> {
    let mut all = Vec::new();
    for &id in ids {
        let k = map.keyframe(id).unwrap();
        let local_q = to_point(&(k.pose.inverse() * Point3::from(to_vec3(q))).coords);
        for (i, p) in k.view().unwrap().points.iter().enumerate() {
            let global = to_point(&(k.pose * Point3::from(to_vec3(p))).coords);
            let dist_sq = if approximate {
                sq(p, &local_q)
            } else {
                sq(&global, q)
            };
            all.push(MapHit {
                point: global,
                dist_sq,
                keyframe: id,
                local_index: i as u32,
            });
        }
    }
    all.sort_by(|a, b| {
        a.dist_sq
            .total_cmp(&b.dist_sq)
            .then(a.keyframe.cmp(&b.keyframe))
            .then(a.local_index.cmp(&b.local_index))
    });
    all
}

#[test]
fn nearest_queries_match_a_linear_scan_in_both_modes() {
    for approximate in [false, true] {
        let mut map = random_map(1, approximate);
        let mut rng = StdRng::seed_from_u64(2);
        let ids = map.select(&pose(0.5, 0.5, 0.1));
        assert_eq!(ids, vec![0, 1, 2]);
        let oracle_map = map.clone();
        let active = map.activate(&pose(0.5, 0.5, 0.1)).unwrap();
        for i in 0..10_000 {
            let q = [
                rng.random_range(-6.0..6.0),
                rng.random_range(-6.0..6.0),
                rng.random_range(-2.0..2.0),
            ];
            let want = linear_scan(&oracle_map, &ids, &q, approximate);
            assert_eq!(active.nearest_one(&q).unwrap(), want[0], "query {i}");
            assert_eq!(active.nearest_k(&q, 1), want[..1].to_vec(), "query {i}");
            // Bounded: the nearest when it lies within the bound (inclusive), else none.
            for bound in [0.05f32, 0.2, want[0].dist_sq] {
                let near = want[..1].iter().copied().filter(|h| h.dist_sq <= bound);
                assert_eq!(
                    active.nearest_k_within(&q, 1, bound),
                    near.collect::<Vec<_>>(),
                    "query {i} within {bound}"
                );
            }
            if i % 10 == 0 {
                assert_eq!(active.nearest_k(&q, 7), want[..7].to_vec());
                let r2 = (0.6f64 * 0.6) as f32;
                let within: Vec<MapHit> =
                    want.iter().copied().filter(|h| h.dist_sq <= r2).collect();
                assert_eq!(active.within_radius(&q, 0.6), within);
                let near: Vec<MapHit> = within.iter().copied().take(7).collect();
                assert_eq!(active.nearest_k_within(&q, 7, r2), near);
            }
        }
    }
}

/// Oracle for cov2cov: merged cloud, brute-force covariances, brute-force nearest.
fn brute_cov2cov(
    map: &KeyframeMap,
    ids: &[KeyframeId],
    scan: &PointCloud,
    at: &Pose,
    max_dist: f64,
) -> Vec<Pairing> {
    let options = map.options().covariance;
    let mut points = Vec::new();
    let mut origins = Vec::new();
    for &id in ids {
        let k = map.keyframe(id).unwrap();
        for (i, p) in k.view().unwrap().points.iter().enumerate() {
            points.push(to_point(&(k.pose * Point3::from(to_vec3(p))).coords));
            origins.push((id, i as u32));
        }
    }
    let map_covs = kfmap_geometry::cov::oracle::brute_force(&points, &options);
    let scan_covs = kfmap_geometry::cov::oracle::brute_force(&scan.points, &options);
    let r = at.rotation.to_rotation_matrix().into_inner();
    let mut out = Vec::new();
    for (i, sp) in scan.points.iter().enumerate() {
        let q = to_point(&(at * Point3::from(to_vec3(sp))).coords);
        let (j, d2) = points
            .iter()
            .enumerate()
            .map(|(j, p)| (j, sq(p, &q)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        if d2 > (max_dist * max_dist) as f32 {
            continue;
        }
        let info: Matrix3<f64> = (unpack_sym3(&map_covs[j])
            + r * unpack_sym3(&scan_covs[i]) * r.transpose())
        .try_inverse()
        .unwrap();
        out.push(Pairing {
            query_index: i as u32,
            keyframe: origins[j].0,
            local_index: origins[j].1,
            map_point: points[j],
            dist_sq: d2,
            information: pack_sym3(&info),
        });
    }
    out
}

fn assert_information_close(a: &PackedSym3, b: &PackedSym3, rel: f32) {
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() <= rel * y.abs().max(1.0), "{a:?} vs {b:?}");
    }
}

#[test]
fn exact_cov2cov_matches_brute_force() {
    let mut map = random_map(3, false);
    let mut rng = StdRng::seed_from_u64(4);
    let scan = random_cloud(&mut rng, 400);
    let at = pose(0.3, -0.2, 0.2);
    let ids = map.select(&at);
    let want = brute_cov2cov(&map.clone(), &ids, &scan, &at, 0.5);
    let got = map
        .activate(&at)
        .unwrap()
        .cov2cov(&scan, &at, 0.5, None)
        .unwrap();
    assert_eq!(got.len(), want.len());
    assert!(got.len() > 100, "{}", got.len());
    for (g, w) in got.iter().zip(&want) {
        assert_eq!(
            (
                g.query_index,
                g.keyframe,
                g.local_index,
                g.map_point,
                g.dist_sq
            ),
            (
                w.query_index,
                w.keyframe,
                w.local_index,
                w.map_point,
                w.dist_sq
            )
        );
        assert_information_close(&g.information, &w.information, 1e-4);
    }
}

#[test]
fn approximate_and_exact_agree_on_a_single_keyframe() {
    let mut rng = StdRng::seed_from_u64(6);
    let cloud = random_cloud(&mut rng, 3000);
    let scan = random_cloud(&mut rng, 500);
    let at = pose(0.1, 0.2, 0.05);
    let mut results = Vec::new();
    for approximate in [false, true] {
        let mut map = KeyframeMap::new(KeyframeMapOptions {
            approximate_cov: approximate,
            ..KeyframeMapOptions::default()
        })
        .unwrap();
        map.insert(cloud.clone(), pose(1.0, -1.0, 0.7), 0.0)
            .unwrap();
        results.push(
            map.activate(&at)
                .unwrap()
                .cov2cov(&scan, &at, 1.0, None)
                .unwrap(),
        );
    }
    assert_eq!(results[0].len(), results[1].len());
    for (e, a) in results[0].iter().zip(&results[1]) {
        assert_eq!(
            (e.query_index, e.local_index),
            (a.query_index, a.local_index)
        );
        assert_information_close(&a.information, &e.information, 1e-3);
    }
}

/// A memo's pairings are exactly a search's, and most of a converging registration's
/// iterations are recalled: the iterations of one registration (moves shrinking from
/// 5 cm to none), a jump, another active set, another scan size, another pairing
/// distance (a relocalization settles a place at the coarse one and scores it at the
/// fine one with the same memo), two keyframes holding the same points (ties, never a
/// lead to recall by), each compared bit for bit with
/// `cov2cov` without a memo (which `nearest_queries_match_a_linear_scan_in_both_modes`
/// checks against a linear scan).
#[test]
fn remembered_pairings_are_exactly_the_searched_ones() {
    let mut rng = StdRng::seed_from_u64(21);
    let mut map = KeyframeMap::new(KeyframeMapOptions {
        approximate_cov: true,
        ..KeyframeMapOptions::default()
    })
    .unwrap();
    let twin = random_cloud(&mut rng, 4000);
    map.insert(twin.clone(), pose(0.0, 0.0, 0.0), 0.0).unwrap();
    map.insert(twin, pose(0.0, 0.0, 0.0), 1.0).unwrap();
    map.insert(random_cloud(&mut rng, 4000), pose(1.5, 0.5, 0.3), 2.0)
        .unwrap();
    map.insert(random_cloud(&mut rng, 4000), pose(30.0, 0.0, 0.0), 3.0)
        .unwrap();
    let scan = random_cloud(&mut rng, 3000);
    let coarse = random_cloud(&mut rng, 700);
    let mut memo = NearestMemo::default();
    let mut x = 0.2;
    let mut steps: Vec<(Pose, &PointCloud, Vec<KeyframeId>, f64)> = Vec::new();
    for step in [0.05, 0.02, 0.005, 0.001, 1e-4, 0.0] {
        x += step;
        steps.push((pose(x, 0.1, 0.05 + step), &scan, vec![0, 1, 2], 1.0));
    }
    steps.push((pose(x + 0.6, 0.1, 0.05), &scan, vec![0, 1, 2], 1.0));
    steps.push((pose(x + 0.6, 0.1, 0.05), &coarse, vec![0, 1, 2], 1.0));
    steps.push((pose(x + 0.6, 0.1, 0.05), &scan, vec![1, 2], 1.0));
    steps.push((pose(29.5, 0.0, 0.0), &scan, vec![2, 3], 1.0));
    steps.push((pose(29.5, 0.0, 0.0), &scan, vec![2, 3], 1.0));
    // Pairs beyond the new distance are dropped, those a shorter search never saw found.
    steps.push((pose(29.5, 0.0, 0.001), &scan, vec![2, 3], 0.05));
    steps.push((pose(29.5, 0.0, 0.002), &scan, vec![2, 3], 2.0));
    let mut recalled = Vec::new();
    for (k, (at, cloud, ids, max_pair_dist)) in steps.iter().enumerate() {
        let active = map.activate_ids(ids.clone()).unwrap();
        let searched = active.cov2cov(cloud, at, *max_pair_dist, None).unwrap();
        let remembered = active
            .cov2cov_remembering(cloud, at, *max_pair_dist, None, Some(&mut memo))
            .unwrap();
        assert!(
            searched.len() > cloud.len() / 2 || *max_pair_dist < 1.0,
            "step {k}"
        );
        assert_eq!(remembered, searched, "step {k}");
        recalled.push(memo.recalled() as f64 / cloud.len() as f64);
    }
    println!("recalled per step: {recalled:.2?}");
    // A first search recalls nothing; then, as the moves shrink, nearly everything
    // (the points whose nearest lies in both twin keyframes never).
    assert_eq!(recalled[0], 0.0);
    assert!(
        recalled[1..6].windows(2).all(|w| w[1] >= w[0]),
        "{recalled:?}"
    );
    assert!(recalled[5] > 0.3, "{recalled:?}");
    // Moved 0.6 m: searched again. Another scan size or active set forgets.
    assert!(recalled[6] < recalled[5], "{recalled:?}");
    assert_eq!(recalled[8], 0.0, "{recalled:?}");
    assert_eq!(recalled[9], 0.0, "{recalled:?}");
    assert!(recalled[10] > 0.9, "{recalled:?}");
    // Moved 1 mm: recalled where the nearest still leads, whatever the pairing distance.
    assert!(recalled[11] > 0.5 && recalled[12] > 0.5, "{recalled:?}");
}

/// A session's memos: one per scan size, the two sizes last paired kept, none for
/// scans too large to remember.
#[test]
fn memos_are_kept_per_scan_size_for_the_two_last_sizes() {
    let mut map = random_map(23, true);
    let active = map.activate(&pose(0.5, 0.5, 0.1)).unwrap();
    let mut rng = StdRng::seed_from_u64(24);
    let (fine, coarse, other) = (
        random_cloud(&mut rng, 900),
        random_cloud(&mut rng, 200),
        random_cloud(&mut rng, 300),
    );
    let at = pose(0.5, 0.5, 0.1);
    let mut memos = NearestMemos::default();
    let pair = |cloud: &PointCloud, memos: &mut NearestMemos| {
        let memo = memos.for_points(cloud.len()).unwrap();
        active
            .cov2cov_remembering(cloud, &at, 1.0, None, Some(&mut *memo))
            .unwrap();
        memo.recalled()
    };
    assert_eq!(pair(&fine, &mut memos), 0);
    assert_eq!(pair(&coarse, &mut memos), 0);
    // Both kept: the same scans at the same pose are recalled, all but the points
    // whose two nearest lie within the rounding margin of each other.
    let whole = |cloud: &PointCloud, recalled: usize| {
        recalled <= cloud.len() && recalled as f64 >= 0.99 * cloud.len() as f64
    };
    assert!(whole(&fine, pair(&fine, &mut memos)));
    assert!(whole(&coarse, pair(&coarse, &mut memos)));
    // A third size replaces the least recently used (the fine one).
    assert_eq!(pair(&other, &mut memos), 0);
    assert!(whole(&coarse, pair(&coarse, &mut memos)));
    assert_eq!(pair(&fine, &mut memos), 0);
    assert!(memos.for_points(NearestMemos::MAX_POINTS + 1).is_none());
}

#[test]
fn unchanged_active_set_rebuilds_nothing() {
    let mut map = random_map(7, false);
    map.activate(&pose(0.0, 0.0, 0.0)).unwrap();
    map.activate(&pose(0.1, 0.0, 0.0)).unwrap();
    assert_eq!(map.merged_rebuilds(), 1);
    // Moving a keyframe outside the active set keeps the cache; inside drops it.
    map.set_pose(3, pose(31.0, 0.0, 0.0)).unwrap();
    map.activate(&pose(0.1, 0.0, 0.0)).unwrap();
    assert_eq!(map.merged_rebuilds(), 1);
    map.set_pose(1, pose(2.1, 1.0, 0.4)).unwrap();
    map.activate(&pose(0.1, 0.0, 0.0)).unwrap();
    assert_eq!(map.merged_rebuilds(), 2);
    // The local caches of a moved keyframe are kept (same tree object).
    let before = map.keyframe(1).unwrap().view().unwrap().points.as_ptr();
    map.set_pose(1, pose(2.2, 1.0, 0.4)).unwrap();
    assert_eq!(
        map.keyframe(1).unwrap().view().unwrap().points.as_ptr(),
        before
    );
}

/// A vertical wall in the plane x = 0, points with view directions `toward_x`.
fn wall(toward_x: f32) -> PointCloud {
    let points: Vec<[f32; 3]> = (0..40)
        .flat_map(|i| (0..20).map(move |j| [0.0, i as f32 * 0.1 - 2.0, j as f32 * 0.1]))
        .collect();
    let n = points.len();
    PointCloud {
        view_dirs: Some(vec![[toward_x, 0.0, 0.0]; n]),
        ..PointCloud::from_points(points)
    }
}

#[test]
fn view_direction_filter_separates_the_two_sides_of_a_thin_wall() {
    for (filter, expect_pairs) in [(false, true), (true, false)] {
        let options = KeyframeMapOptions {
            use_view_direction_filter: filter,
            ..KeyframeMapOptions::default()
        };
        let mut map = KeyframeMap::new(options).unwrap();
        map.insert(wall(-1.0), Pose::identity(), 0.0).unwrap(); // seen from x < 0
        let scan = wall(1.0); // the same wall seen from x > 0
        let pairs = map
            .activate(&Pose::identity())
            .unwrap()
            .cov2cov(&scan, &Pose::identity(), 0.5, None)
            .unwrap();
        assert_eq!(
            !pairs.is_empty(),
            expect_pairs,
            "filter {filter}: {} pairs",
            pairs.len()
        );
    }
    // The 120 deg boundary: 119 deg passes, 121 deg is rejected.
    let mut map = KeyframeMap::new(KeyframeMapOptions::default()).unwrap();
    map.insert(wall(1.0), Pose::identity(), 0.0).unwrap();
    for (deg, expect) in [(119.0f32, true), (121.0, false)] {
        let mut scan = wall(1.0);
        let (s, c) = deg.to_radians().sin_cos();
        scan.view_dirs = Some(vec![[c, s, 0.0]; scan.len()]);
        let pairs = map
            .activate(&Pose::identity())
            .unwrap()
            .cov2cov(&scan, &Pose::identity(), 0.5, None)
            .unwrap();
        assert_eq!(pairs.len() == scan.len(), expect, "{deg} deg");
    }
    // A missing vector never rejects.
    let mut scan = wall(-1.0);
    scan.view_dirs = Some(vec![[0.0; 3]; scan.len()]);
    let pairs = map
        .activate(&Pose::identity())
        .unwrap()
        .cov2cov(&scan, &Pose::identity(), 0.5, None)
        .unwrap();
    assert_eq!(pairs.len(), scan.len());
}

#[test]
fn eviction_and_monotonic_ids() {
    let options = KeyframeMapOptions {
        remove_frames_farther_than: 5.0,
        ..KeyframeMapOptions::default()
    };
    let mut map = KeyframeMap::new(options).unwrap();
    let mut rng = StdRng::seed_from_u64(8);
    let ids: Vec<KeyframeId> = [0.0, 3.0, 6.0]
        .iter()
        .map(|&x| {
            map.insert(random_cloud(&mut rng, 200), pose(x, 0.0, 0.0), 0.0)
                .unwrap()
        })
        .collect();
    assert_eq!(ids, vec![0, 1, 2]);
    // At x = 10: 0 (10 m) and 1 (7 m) are evicted, 2 (4 m) stays; exactly 5 m stays too.
    let id = map
        .insert(random_cloud(&mut rng, 200), pose(10.0, 0.0, 0.0), 0.0)
        .unwrap();
    assert_eq!(id, 3);
    assert_eq!(map.drain_evicted(), vec![0, 1]);
    assert!(map.drain_evicted().is_empty());
    map.insert(random_cloud(&mut rng, 200), pose(11.0, 0.0, 0.0), 0.0)
        .unwrap();
    assert_eq!(
        map.keyframes().map(|k| k.id).collect::<Vec<_>>(),
        vec![2, 3, 4]
    );
    map.remove(4).unwrap();
    assert_eq!(
        map.insert(random_cloud(&mut rng, 200), pose(11.0, 0.0, 0.0), 0.0)
            .unwrap(),
        5
    );
    assert!(matches!(map.remove(0), Err(MapError::UnknownKeyframe(0))));
}

#[test]
fn keyframe_decider_thresholds_are_strict() {
    let decider = KeyframeDecider::default();
    let existing = [Pose::identity()];
    assert!(decider.should_create([], &Pose::identity()));
    assert!(!decider.should_create(&existing, &pose(1.0, 0.0, 0.0)));
    assert!(decider.should_create(&existing, &pose(1.001, 0.0, 0.0)));
    assert!(!decider.should_create(&existing, &pose(0.0, 0.0, 30f64.to_radians() - 1e-9)));
    assert!(decider.should_create(&existing, &pose(0.0, 0.0, 30.01f64.to_radians())));
}

#[test]
fn transform_all_and_merge() {
    let map = random_map(9, false);
    let t = pose(5.0, -3.0, 1.0);
    let mut moved = map.clone();
    moved.transform_all(&t).unwrap();
    for (a, b) in map.keyframes().zip(moved.keyframes()) {
        assert!(((t * a.pose).translation.vector - b.pose.translation.vector).norm() < 1e-12);
    }
    let mut merged = map.clone();
    let new_ids = merged.merge(&map, &t).unwrap();
    assert_eq!(new_ids, vec![4, 5, 6, 7]);
    assert_eq!(merged.len(), 8);
    assert!(
        (merged.keyframe(4).unwrap().pose.translation.vector - t.translation.vector).norm() < 1e-12
    );
}

#[test]
fn covisibility_active_set_is_the_nearest_plus_its_best_covisible() {
    let options = KeyframeMapOptions {
        active_set: ActiveSetMode::Covisibility,
        ..KeyframeMapOptions::default()
    };
    let mut map = KeyframeMap::new(options).unwrap();
    let mut rng = StdRng::seed_from_u64(10);
    for x in [0.0, 1.0, 2.0, 3.0, 50.0] {
        map.insert(random_cloud(&mut rng, 2000), pose(x, 0.0, 0.0), 0.0)
            .unwrap();
    }
    let nearest = 3; // at x = 3
    let want: Vec<KeyframeId> = {
        let mut ids = vec![nearest];
        ids.extend(map.covisibility().best_covisible(nearest, 2));
        ids.sort_unstable();
        ids
    };
    assert_eq!(map.select(&pose(3.2, 0.0, 0.0)), want);
    assert!(!want.contains(&4));
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let mut map = KeyframeMap::new(KeyframeMapOptions::default()).unwrap();
    assert!(matches!(
        map.insert(PointCloud::default(), Pose::identity(), 0.0),
        Err(MapError::Tree(_))
    ));
    let nan = PointCloud::from_points(vec![[0.0, f32::NAN, 0.0]]);
    assert!(matches!(
        map.insert(nan.clone(), Pose::identity(), 0.0),
        Err(MapError::Cloud(_))
    ));
    assert!(matches!(
        map.activate(&Pose::identity()),
        Err(MapError::Empty)
    ));
    map.insert(wall(1.0), Pose::identity(), 0.0).unwrap();
    let active = map.activate(&Pose::identity()).unwrap();
    assert!(matches!(
        active.cov2cov(&nan, &Pose::identity(), 1.0, None),
        Err(MapError::Cloud(_))
    ));
    let scan = wall(1.0);
    assert!(matches!(
        active.cov2cov(
            &scan,
            &Pose::identity(),
            1.0,
            Some(&[[1.0, 0.0, 0.0, 1.0, 0.0, 1.0]])
        ),
        Err(MapError::CovarianceCount { .. })
    ));
    let bad = KeyframeMapOptions {
        max_view_angle_deg: 200.0,
        ..KeyframeMapOptions::default()
    };
    assert!(
        matches!(KeyframeMap::new(bad), Err(MapError::Options(e)) if e.option == "max-view-angle-deg")
    );
    let bad = KeyframeMapOptions {
        fuse_voxel_size: -0.1,
        ..KeyframeMapOptions::default()
    };
    assert!(
        matches!(KeyframeMap::new(bad), Err(MapError::Options(e)) if e.option == "fuse-voxel-size")
    );
    let cov = kfmap_geometry::cov::CovOptions::default();
    for (weights, named) in [
        (vec![1, 2], "2 weights for 3 points"),
        (vec![1, 0, 4], "point 1 has weight 0"),
    ] {
        let built = Keyframe::build_weighted(
            9,
            Pose::identity(),
            0.0,
            wall(1.0).select(&[0, 1, 2]),
            Some(weights),
            &cov,
        );
        assert!(matches!(built, Err(TreeError::MismatchedParts(m)) if m.contains(named)));
    }
}

#[test]
fn fused_exact_submap_is_the_voxelization_of_the_merged_raw_clouds() {
    let mut rng = StdRng::seed_from_u64(11);
    let voxel = 0.5;
    let poses = [
        pose(0.0, 0.0, 0.0),
        pose(1.0, 0.5, 0.3),
        pose(-0.5, 1.0, -0.4),
    ];
    let raw: Vec<PointCloud> = poses.iter().map(|_| random_cloud(&mut rng, 4000)).collect();
    let options = KeyframeMapOptions {
        fuse_voxel_size: voxel,
        ..KeyframeMapOptions::default()
    };
    let mut map = KeyframeMap::new(options).unwrap();
    for (i, (cloud, at)) in raw.iter().zip(&poses).enumerate() {
        let v = cloud.voxelize(voxel, Some(at)).unwrap();
        assert_eq!(v.counts.iter().sum::<u32>() as usize, cloud.len());
        let k = Keyframe::build_weighted(
            i as u64,
            *at,
            0.0,
            v.cloud,
            Some(v.counts),
            &options.covariance,
        );
        map.insert_keyframe(k.unwrap()).unwrap();
    }
    // Oracle: every raw point in the map frame, grouped by voxel, averaged in f64.
    let mut groups: std::collections::BTreeMap<[i64; 3], (Vector3<f64>, usize)> =
        Default::default();
    for (cloud, at) in raw.iter().zip(&poses) {
        for p in &cloud.points {
            let q = at * Point3::from(to_vec3(p));
            let key = q.coords.map(|c| (c / voxel).floor() as i64);
            let entry = groups.entry([key.x, key.y, key.z]).or_default();
            entry.0 += q.coords;
            entry.1 += 1;
        }
    }
    let locals: Vec<Vec<[f32; 3]>> = (0..3)
        .map(|id| map.keyframe(id).unwrap().view().unwrap().points.to_vec())
        .collect();
    let active = map.activate(&pose(0.2, 0.3, 0.0)).unwrap();
    assert_eq!(active.ids(), &[0, 1, 2]);
    let merged = active.merged().unwrap();
    assert_eq!(merged.points.len(), groups.len());
    for (i, (got, (sum, n))) in merged.points.iter().zip(groups.values()).enumerate() {
        let want = sum / *n as f64;
        assert!(
            (to_vec3(got) - want).norm() < 1e-5,
            "voxel {i}: {got:?} vs {want}"
        );
        // The fused point names a keyframe point of the same voxel.
        let slot = merged.origin_keyframe[i] as usize;
        let local = locals[slot][merged.origin_index[i] as usize];
        let origin = poses[slot] * Point3::from(to_vec3(&local));
        assert!(origin.coords.map(|c| (c / voxel).floor()) == want.map(|c| (c / voxel).floor()));
    }
}

#[test]
fn surroundings_are_the_keyframes_nearest_by_position_whichever_way_they_face() {
    let map = random_map(3, true);
    let mut rng = StdRng::seed_from_u64(4);
    for _ in 0..200 {
        let at = pose(
            rng.random_range(-3.0..5.0),
            rng.random_range(-3.0..4.0),
            rng.random_range(-3.1..3.1),
        );
        let count = rng.random_range(1..=5);
        // Oracle: every keyframe sorted by its distance to the query's position.
        let mut by_distance: Vec<(f64, KeyframeId)> = map
            .keyframes()
            .map(|k| {
                (
                    (k.pose.translation.vector - at.translation.vector).norm(),
                    k.id,
                )
            })
            .collect();
        by_distance.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut want: Vec<KeyframeId> = by_distance.iter().take(count).map(|d| d.1).collect();
        want.sort_unstable();
        assert_eq!(map.surroundings(&at, count), want, "{at:?}, {count}");
    }
    // The active set weighs heading; the surroundings do not: at (0.3, 1.8), facing as
    // keyframe 1 faced, keyframes 2 and 0 are nearest (1.81 m, 1.82 m) but a 2-keyframe
    // selection by the map's metric takes keyframe 1 (1.88 m, no turn) for 2.
    let facing_one = pose(0.3, 1.8, 0.4);
    assert_eq!(map.surroundings(&facing_one, 2), vec![0, 2]);
    let heading_weighed = SelectionOptions {
        max_search_keyframes: 2,
        num_diverse_keyframes: 0,
        ..SelectionOptions::default()
    };
    assert_eq!(map.select_with(&facing_one, &heading_weighed), vec![0, 1]);
}
