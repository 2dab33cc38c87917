//! Why kiddo queries are slower than small_gicp's / nanoflann's, on KITTI 00 frame 0
//! (tree) and frame 1 moved into frame 0 (queries), one thread, plain loops.
//! Run: `cargo bench -p kfmap-shared --bench kdtree`; the small_gicp anchor is
//! `tools/anchors/small_gicp_knn.py`.

use std::num::NonZeroUsize;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use kfmap_shared::datasets::require_test_data;
use kfmap_shared::io::{ReadOptions, read_cloud, read_trajectory};
use kfmap_shared::spatial::{PointTree, build_tree, morton_order};
use kiddo::kd_tree::KdTree;
use kiddo::leaf_strategy::{FlatVec, VecOfArenas};
use kiddo::{Donnelly, Eytzinger, SquaredEuclidean};
use rayon::prelude::*;

type Arenas16 = KdTree<f32, u32, Eytzinger, VecOfArenas<f32, u32, 3, 16>, 3, 16>;
type Arenas32 = KdTree<f32, u32, Eytzinger, VecOfArenas<f32, u32, 3, 32>, 3, 32>;
type Flat16 = KdTree<f32, u32, Eytzinger, FlatVec<f32, u32, 3, 16>, 3, 16>;
type Flat8 = KdTree<f32, u32, Eytzinger, FlatVec<f32, u32, 3, 8>, 3, 8>;
type Flat32 = KdTree<f32, u32, Eytzinger, FlatVec<f32, u32, 3, 32>, 3, 32>;
type DonnellyFlat16 = KdTree<f32, u32, Donnelly<3>, FlatVec<f32, u32, 3, 16>, 3, 16>;
type Donnelly8 = KdTree<f32, u32, Donnelly<3>, VecOfArenas<f32, u32, 3, 8>, 3, 8>;

/// Sum of 1-NN squared distances (keeps the optimizer honest).
macro_rules! nn_sum {
    ($tree:expr, $queries:expr) => {
        $queries
            .iter()
            .map(|q| {
                $tree
                    .query(q)
                    .nearest_one::<SquaredEuclidean<f32>>()
                    .execute()
                    .distance
            })
            .sum::<f32>()
    };
}

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
        .map(|p| {
            let q = relative * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            [q.x as f32, q.y as f32, q.z as f32]
        })
        .collect();
    let sorted: Vec<[f32; 3]> = morton_order(&queries)
        .iter()
        .map(|&i| queries[i as usize])
        .collect();
    let tree: PointTree = build_tree(&target).expect("tree");
    let k20 = NonZeroUsize::new(20).expect("k");

    let mut group = c.benchmark_group("kitti00_frame0_vs_frame1");
    group.sample_size(10);
    group.bench_function("build_leaf8_arenas", |b| {
        b.iter(|| build_tree(&target).expect("tree").size())
    });
    group.bench_function("build_flat16", |b| {
        b.iter(|| Flat16::new_from_slice(&target).expect("tree").size())
    });
    group.throughput(Throughput::Elements(queries.len() as u64));
    group.bench_function("nn_leaf8_scan_order", |b| b.iter(|| nn_sum!(tree, queries)));
    group.bench_function("nn_leaf8_morton_order", |b| {
        b.iter(|| nn_sum!(tree, sorted))
    });
    group.bench_function("morton_sort_itself", |b| {
        b.iter(|| morton_order(&queries).len())
    });
    group.bench_function("nn_leaf8_gated_1m_nearest_n", |b| {
        b.iter(|| {
            sorted
                .iter()
                .map(|q| {
                    tree.query(q)
                        .nearest_n::<SquaredEuclidean<f32>>(NonZeroUsize::MIN)
                        .within(1.0)
                        .execute()
                        .len()
                })
                .sum::<usize>()
        })
    });
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    group.bench_function("nn_leaf8_morton_in_1_thread_rayon_pool", |b| {
        b.iter(|| {
            one.install(|| {
                sorted
                    .par_iter()
                    .map(|q| {
                        tree.query(q)
                            .nearest_one::<SquaredEuclidean<f32>>()
                            .execute()
                            .distance
                    })
                    .sum::<f32>()
            })
        })
    });
    let arenas16 = Arenas16::new_from_slice(&target).expect("tree");
    let arenas32 = Arenas32::new_from_slice(&target).expect("tree");
    let flat16 = Flat16::new_from_slice(&target).expect("tree");
    let donnelly8 = Donnelly8::new_from_slice(&target).expect("tree");
    group.bench_function("nn_leaf16_morton", |b| b.iter(|| nn_sum!(arenas16, sorted)));
    group.bench_function("nn_leaf32_morton", |b| b.iter(|| nn_sum!(arenas32, sorted)));
    group.bench_function("nn_flat16_morton", |b| b.iter(|| nn_sum!(flat16, sorted)));
    let flat8 = Flat8::new_from_slice(&target).expect("tree");
    let flat32 = Flat32::new_from_slice(&target).expect("tree");
    let donnelly_flat16 = DonnellyFlat16::new_from_slice(&target).expect("tree");
    group.bench_function("nn_flat8_morton", |b| b.iter(|| nn_sum!(flat8, sorted)));
    group.bench_function("nn_flat32_morton", |b| b.iter(|| nn_sum!(flat32, sorted)));
    group.bench_function("nn_flat16_scan_order", |b| {
        b.iter(|| nn_sum!(flat16, queries))
    });
    group.bench_function("nn_donnelly_flat16_morton", |b| {
        b.iter(|| nn_sum!(donnelly_flat16, sorted))
    });
    group.bench_function("k20_flat16_scan_order", |b| {
        b.iter(|| {
            queries
                .iter()
                .map(|q| {
                    flat16
                        .query(q)
                        .nearest_n::<SquaredEuclidean<f32>>(k20)
                        .unsorted()
                        .execute()
                        .len()
                })
                .sum::<usize>()
        })
    });
    group.bench_function("nn_donnelly8_morton", |b| {
        b.iter(|| nn_sum!(donnelly8, sorted))
    });

    let knn = |queries: &[[f32; 3]]| {
        queries
            .iter()
            .map(|q| {
                tree.query(q)
                    .nearest_n::<SquaredEuclidean<f32>>(k20)
                    .unsorted()
                    .execute()
                    .len()
            })
            .sum::<usize>()
    };
    group.bench_function("k20_leaf8_scan_order", |b| b.iter(|| knn(&queries)));
    group.bench_function("k20_leaf8_morton_order", |b| b.iter(|| knn(&sorted)));
    group.finish();
}

criterion_group!(benches, bench_kdtree);
criterion_main!(benches);
