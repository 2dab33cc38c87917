//! Keyframe-map queries on real KITTI data: frames 0, 2 and 4 of sequence 00 as keyframes
//! at their true poses, frame 3 downsampled to about 10 000 points as the query at its
//! true pose, one thread. Run: `cargo bench -p kfmap-map --bench map`.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::cov::estimate_covariances;
use kfmap_geometry::geometry::{PackedSym3, to_point, transform_point};
use kfmap_geometry::io::{ReadOptions, read_cloud, read_trajectory};
use kfmap_map::archive::{OpenOptions, open_map, save_map};
use kfmap_map::map::{ActiveSet, KeyframeMap, KeyframeMapOptions};
use kfmap_testdata::require_test_data;
use kiddo::kd_tree::KdTree;
use kiddo::leaf_strategy::FlatVec;
use kiddo::{Eytzinger, SquaredEuclidean};

type KiddoFlat16 = KdTree<f32, u32, Eytzinger, FlatVec<f32, u32, 3, 16>, 3, 16>;

fn build(
    frames: &[PointCloud],
    poses: &[kfmap_geometry::geometry::Pose],
    approximate: bool,
) -> KeyframeMap {
    let options = KeyframeMapOptions {
        approximate_cov: approximate,
        ..KeyframeMapOptions::default()
    };
    let mut map = KeyframeMap::new(options).expect("options");
    for i in [0, 2, 4] {
        map.insert(frames[i].clone(), poses[i], i as f64)
            .expect("keyframe");
    }
    map
}

fn bench_map(c: &mut Criterion) {
    let Some(dir) = require_test_data("kitti00", "map bench") else {
        return;
    };
    let frames: Vec<PointCloud> = (0..5)
        .map(|i| {
            read_cloud(&dir.join(format!("{i:06}.bin")), &ReadOptions::default())
                .expect("scan")
                .cloud
        })
        .collect();
    let poses = read_trajectory(&dir.join("poses_velo_kitti.txt"))
        .expect("poses")
        .poses;
    // The smallest voxel giving at most ~10 000 points.
    let query = (1..40)
        .map(|k| frames[3].voxel_downsample(0.05 * k as f64).expect("voxel"))
        .find(|c| c.len() <= 10_500)
        .expect("downsample");
    let query_covs =
        estimate_covariances(&query.points, &KeyframeMapOptions::default().covariance).values;
    let at = poses[3];
    println!(
        "query: {} points; keyframes: {} points each",
        query.len(),
        frames[0].len()
    );
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let mut group = c.benchmark_group("kitti00");
    group.sample_size(10);
    group.throughput(Throughput::Elements(query.len() as u64));

    let mut exact = build(&frames, &poses, false);
    group.bench_function("exact_cov2cov_new_active_set", |b| {
        b.iter(|| {
            one.install(|| {
                exact.set_pose(0, poses[0]).expect("pose"); // Invalidates the merged submap.
                let active = exact.activate(&at).expect("active");
                active
                    .cov2cov(&query, &at, 1.0, Some(&query_covs))
                    .expect("pairs")
                    .len()
            })
        })
    });
    let moved: Vec<[f32; 3]> = query
        .points
        .iter()
        .map(|p| to_point(&transform_point(&at, p)))
        .collect();
    let pairs = |active: &ActiveSet, covs: Option<&[PackedSym3]>| {
        one.install(|| active.cov2cov(&query, &at, 1.0, covs).expect("pairs").len())
    };
    let nearest = |active: &ActiveSet| {
        moved
            .iter()
            .map(|p| active.nearest_one(p).expect("hit").dist_sq)
            .sum::<f32>()
    };

    let active = exact.activate(&at).expect("active");
    group.bench_function("exact_cov2cov_cached", |b| {
        b.iter(|| pairs(&active, Some(&query_covs)))
    });
    group.bench_function("exact_cov2cov_cached_estimating_query_covariances", |b| {
        b.iter(|| pairs(&active, None))
    });
    group.bench_function("exact_nearest_one", |b| b.iter(|| nearest(&active)));
    let merged = active.merged().expect("exact mode");
    group.bench_function("raw_tree_nearest_one", |b| {
        let tree = merged.tree.view();
        b.iter(|| moved.iter().map(|p| tree.nearest_one(p).1).sum::<f32>())
    });
    // The same merged points in kiddo 6.3 (flat leaves of 16), for reference.
    let kiddo = KiddoFlat16::new_from_slice(&merged.points).expect("tree");
    group.bench_function("raw_kiddo_nearest_one", |b| {
        b.iter(|| {
            moved
                .iter()
                .map(|p| {
                    kiddo
                        .query(p)
                        .nearest_one::<SquaredEuclidean<f32>>()
                        .execute()
                        .distance
                })
                .sum::<f32>()
        })
    });

    let mut approx = build(&frames, &poses, true);
    let active = approx.activate(&at).expect("active");
    group.bench_function("approximate_cov2cov", |b| {
        b.iter(|| pairs(&active, Some(&query_covs)))
    });
    group.bench_function("approximate_nearest_one", |b| b.iter(|| nearest(&active)));

    // The same map baked to a file and memory-mapped: queries read it in place.
    let path = std::env::temp_dir().join(format!("kfmap-map-bench-{}.kfmap", std::process::id()));
    save_map(&approx, &[], &path).expect("bake");
    let mut baked = open_map(&path, OpenOptions::default()).expect("open").map;
    let active = baked.activate(&at).expect("active");
    group.bench_function("baked_approximate_cov2cov", |b| {
        b.iter(|| pairs(&active, Some(&query_covs)))
    });
    group.bench_function("baked_approximate_nearest_one", |b| {
        b.iter(|| nearest(&active))
    });
    group.finish();
    let _ = std::fs::remove_file(&path);
}

criterion_group!(benches, bench_map);
criterion_main!(benches);
