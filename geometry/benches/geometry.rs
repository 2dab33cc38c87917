//! Kernels on the largest real scan: KD-tree build, per-point covariances (k = 20,
//! r = 1 m) on one thread and on all threads, voxel downsampling at 0.25 m.
//! Run: `cargo bench -p kfmap-geometry --bench geometry`. Compare with small_gicp via
//! `tools/anchors/small_gicp_cov.py`.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use kfmap_geometry::cov::{CovOptions, estimate_covariances};
use kfmap_geometry::io::{ReadOptions, read_cloud};
use kfmap_geometry::spatial::build_tree;
use kfmap_testdata::require_test_data;

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool")
}

fn bench_kernels(c: &mut Criterion) {
    let Some(path) = require_test_data("small_gicp/target.ply", "geometry bench") else {
        return;
    };
    // The invalid-return filter is on, as in every kfmap load path.
    let cloud = read_cloud(&path, &ReadOptions::default())
        .expect("target.ply")
        .cloud;
    let points = &cloud.points;
    let n = points.len() as u64;
    let all = std::thread::available_parallelism().map_or(1, |t| t.get());
    let options = CovOptions::default();

    let mut group = c.benchmark_group("target.ply");
    group.throughput(Throughput::Elements(n));
    group.sample_size(20);
    for threads in [1, all] {
        let pool = pool(threads);
        group.bench_function(BenchmarkId::new("kdtree_build", threads), |b| {
            b.iter(|| pool.install(|| build_tree(points).expect("tree")))
        });
        group.bench_function(BenchmarkId::new("covariances_k20", threads), |b| {
            b.iter(|| pool.install(|| estimate_covariances(points, &options)))
        });
        group.bench_function(BenchmarkId::new("voxel_downsample_0.25", threads), |b| {
            b.iter(|| pool.install(|| cloud.voxel_downsample(0.25).expect("voxel")))
        });
    }
    group.finish();
}

criterion_group!(benches, bench_kernels);
criterion_main!(benches);
