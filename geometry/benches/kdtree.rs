//! The map's KD-tree against kiddo 6.3 (its best layout: flat leaves of 16) and the
//! small_gicp anchor, on KITTI 00 frame 0 (tree) and frame 1 moved into frame 0 by the
//! true poses (queries), one thread, plain loops.
//! Run: `cargo bench -p kfmap-geometry --bench kdtree`; the small_gicp anchor is
//! `tools/anchors/small_gicp_knn.py`.

use std::num::NonZeroUsize;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use kfmap_geometry::geometry::{to_point, transform_point};
use kfmap_geometry::io::{ReadOptions, read_cloud, read_trajectory};
use kfmap_geometry::spatial::{
    LANES, LEAF_SIZE, NodeWords, PointBlock, TreeRef, build_tree_with_leaf, morton_order,
};
use kfmap_testdata::require_test_data;
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

    let tree16 = build_tree_with_leaf(&target, LEAF_SIZE).expect("tree");
    print_search_cost(tree16.view(), &queries, &sorted);

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
            for (order, qs) in [("scan", &queries), ("morton", &sorted)] {
                group.bench_function(format!("k20_leaf{leaf}_{order}_order"), |b| {
                    b.iter(|| {
                        qs.iter()
                            .map(|q| tree.nearest_n(q, k20).len())
                            .sum::<usize>()
                    })
                });
            }
        }
    }
    bench_floors(&mut group, tree16.view(), &queries);

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

/// Floors of the 1-NN scan-order benchmark (see docs/BENCHMARKS.md): its distance
/// evaluations alone, computed over blocks read in order, and its bytes alone (the
/// nodes and blocks the searches read), streamed from a tree-sized buffer that stays
/// in cache like the tree does.
fn bench_floors(
    group: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>,
    tree: TreeRef<'_>,
    queries: &[[f32; 3]],
) {
    let (_, blocks, bytes) = search_cost(tree, queries);
    let all = tree.blocks();
    group.bench_function("nn_floor_distances_scan_order", |b| {
        b.iter(|| {
            let mut nearest = 0.0f32;
            for (j, q) in queries.iter().enumerate() {
                // Query j's share of the counted blocks, taken in order from the tree.
                let from = j * blocks / queries.len();
                let to = (j + 1) * blocks / queries.len();
                let mut best = f32::INFINITY;
                for block in from..to {
                    let [xs, ys, zs] = &all[block % all.len()];
                    for lane in 0..LANES {
                        let (dx, dy, dz) = (xs[lane] - q[0], ys[lane] - q[1], zs[lane] - q[2]);
                        let d = dx * dx + dy * dy + dz * dz;
                        best = if d < best { d } else { best };
                    }
                }
                nearest += best;
            }
            nearest
        })
    });
    let footprint = size_of_val(all) + size_of_val(tree.nodes());
    let buffer: Vec<u64> = (0..footprint / 8).map(|i| i as u64).collect();
    group.bench_function("nn_floor_bytes_scan_order", |b| {
        b.iter(|| {
            let mut sum = 0u64;
            let mut left = bytes / 8;
            while left > 0 {
                let take = left.min(buffer.len());
                sum = buffer[..take].iter().fold(sum, |s, &x| s.wrapping_add(x));
                left -= take;
            }
            sum
        })
    });
}

/// Nodes read, blocks of points scanned and bytes read by the 1-NN searches of
/// `queries`.
fn search_cost(tree: TreeRef<'_>, queries: &[[f32; 3]]) -> (usize, usize, usize) {
    let (nodes, blocks) = queries.iter().fold((0, 0), |(n, b), q| {
        let cost = tree.nearest_one_cost(q);
        (n + cost.nodes, b + cost.blocks)
    });
    let bytes = nodes * size_of::<NodeWords>() + blocks * size_of::<PointBlock>();
    (nodes, blocks, bytes)
}

/// The work behind the 1-NN figures, for the physical-limit estimate in
/// docs/BENCHMARKS.md.
fn print_search_cost(tree: TreeRef<'_>, queries: &[[f32; 3]], sorted: &[[f32; 3]]) {
    for (order, qs) in [("scan", queries), ("morton", sorted)] {
        let (nodes, blocks, bytes) = search_cost(tree, qs);
        let per = |x: usize| x as f64 / qs.len() as f64;
        println!(
            "nn {order}: {:.1} nodes and {:.1} blocks of {LANES} points ({:.1} distances, {:.0} bytes) \
             per query; {} nodes and {} blocks in the tree",
            per(nodes),
            per(blocks),
            per(blocks * LANES),
            per(bytes),
            tree.nodes().len(),
            tree.blocks().len()
        );
    }
}

criterion_group!(benches, bench_kdtree);
criterion_main!(benches);
