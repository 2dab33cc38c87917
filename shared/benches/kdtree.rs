//! The map's KD-tree against kiddo 6.3 (its best layout: flat leaves of 16) and the
//! small_gicp anchor, on KITTI 00 frame 0 (tree) and frame 1 moved into frame 0 by the
//! true poses (queries), one thread, plain loops.
//! Run: `cargo bench -p kfmap-shared --bench kdtree`; the small_gicp anchor is
//! `tools/anchors/small_gicp_knn.py`.

use std::num::NonZeroUsize;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use kfmap_shared::datasets::require_test_data;
use kfmap_shared::geometry::{to_point, transform_point};
use kfmap_shared::io::{ReadOptions, read_cloud, read_trajectory};
use kfmap_shared::spatial::{LEAF_SIZE, build_tree_with_leaf, morton_order};
use kiddo::Eytzinger;
use kiddo::SquaredEuclidean;
use kiddo::kd_tree::KdTree;
use kiddo::leaf_strategy::FlatVec;

type KiddoFlat16 = KdTree<f32, u32, Eytzinger, FlatVec<f32, u32, 3, 16>, 3, 16>;

fn bench_kdtree(c: &mut Criterion) {
    let Some(dir) = require_test_data("kitti00", "kdtree bench") else {
        return;
    };
    let read = |i: usize| {
        read_cloud(&dir.join(format!("{i:06}.bin")), &ReadOptions::default())
            .expect("scan")
            .cloud
            .points
    };
    let poses = read_trajectory(&dir.join("poses_velo_kitti.txt"))
        .expect("poses")
        .poses;
    let target = read(0);
    let relative = poses[0].inverse() * poses[1];
    let queries: Vec<[f32; 3]> = read(1)
        .iter()
        .map(|p| to_point(&transform_point(&relative, p)))
        .collect();
    let sorted: Vec<[f32; 3]> = morton_order(&queries)
        .iter()
        .map(|&i| queries[i as usize])
        .collect();
    let k20 = NonZeroUsize::new(20).expect("k");
    // Rayon's global pool would build on two threads; the comparison is single-threaded.
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");

    let mut group = c.benchmark_group("kitti00_frame0_vs_frame1");
    group.sample_size(10);
    for leaf in [8, LEAF_SIZE, 32] {
        group.bench_function(format!("build_leaf{leaf}"), |b| {
            b.iter(|| one.install(|| build_tree_with_leaf(&target, leaf).expect("tree").len()))
        });
    }
    group.bench_function("build_kiddo_flat16", |b| {
        b.iter(|| KiddoFlat16::new_from_slice(&target).expect("tree").size())
    });

    group.throughput(Throughput::Elements(queries.len() as u64));
    for leaf in [8, LEAF_SIZE, 32] {
        let tree = build_tree_with_leaf(&target, leaf).expect("tree");
        let tree = tree.view();
        let nn = |qs: &[[f32; 3]]| qs.iter().map(|q| tree.nearest_one(q).1).sum::<f32>();
        group.bench_function(format!("nn_leaf{leaf}_scan_order"), |b| {
            b.iter(|| nn(&queries))
        });
        if leaf == LEAF_SIZE {
            group.bench_function(format!("nn_leaf{leaf}_morton_order"), |b| {
                b.iter(|| nn(&sorted))
            });
            group.bench_function(format!("nn_leaf{leaf}_gated_1m"), |b| {
                b.iter(|| {
                    queries
                        .iter()
                        .filter_map(|q| tree.nearest_one_within(q, 1.0))
                        .count()
                })
            });
            group.bench_function(format!("k20_leaf{leaf}_scan_order"), |b| {
                b.iter(|| {
                    queries
                        .iter()
                        .map(|q| tree.nearest_n(q, k20).len())
                        .sum::<usize>()
                })
            });
        }
    }
    let kiddo = KiddoFlat16::new_from_slice(&target).expect("tree");
    group.bench_function("nn_kiddo_flat16_scan_order", |b| {
        b.iter(|| {
            queries
                .iter()
                .map(|q| {
                    kiddo
                        .query(q)
                        .nearest_one::<SquaredEuclidean<f32>>()
                        .execute()
                        .distance
                })
                .sum::<f32>()
        })
    });
    group.bench_function("k20_kiddo_flat16_scan_order", |b| {
        b.iter(|| {
            queries
                .iter()
                .map(|q| {
                    kiddo
                        .query(q)
                        .nearest_n::<SquaredEuclidean<f32>>(k20)
                        .unsorted()
                        .execute()
                        .len()
                })
                .sum::<usize>()
        })
    });
    group.finish();
}

criterion_group!(benches, bench_kdtree);
criterion_main!(benches);
