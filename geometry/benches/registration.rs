//! GICP on the real scan pair small_gicp/{source,target}.ply (invalid returns filtered)
//! and fast_gicp's copy of it, 1 and 2 threads: preprocessing (0.25 m voxels, k = 10
//! covariances, trees), GICP on the preprocessed clouds, and the whole registration.
//! Anchor: `tools/anchors/small_gicp_reg.py`.

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::{ReadOptions, read_cloud};
use kfmap_geometry::registration::{PreparedCloud, RegistrationParams, align, register};
use kfmap_testdata::require_test_data;

fn read(path: &std::path::Path) -> PointCloud {
    read_cloud(path, &ReadOptions::default())
        .expect("cloud")
        .cloud
}

fn bench_registration(c: &mut Criterion) {
    let Some(dir) = require_test_data("small_gicp", "registration bench") else {
        return;
    };
    let pairs = [(
        "small_gicp",
        read(&dir.join("target.ply")),
        read(&dir.join("source.ply")),
    )]
    .into_iter()
    .chain(
        require_test_data("fast_gicp", "registration bench").map(|d| {
            (
                "fast_gicp",
                read(&d.join("251370668.pcd")),
                read(&d.join("251371071.pcd")),
            )
        }),
    );
    let params = RegistrationParams::default();
    let mut group = c.benchmark_group("registration");
    group.sample_size(20);
    for (name, target, source) in pairs {
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool");
            let prepare = || {
                rayon::join(
                    || PreparedCloud::new(&target, &params, "target").expect("target"),
                    || PreparedCloud::new(&source, &params, "source").expect("source"),
                )
            };
            group.bench_function(
                BenchmarkId::new(format!("{name}_preprocess"), threads),
                |b| b.iter(|| pool.install(prepare)),
            );
            let (t, s) = pool.install(prepare);
            group.bench_function(BenchmarkId::new(format!("{name}_gicp"), threads), |b| {
                b.iter(|| {
                    pool.install(|| align(&t, &s, &Pose::identity(), &params).expect("align"))
                })
            });
            group.bench_function(BenchmarkId::new(format!("{name}_whole"), threads), |b| {
                b.iter(|| {
                    pool.install(|| {
                        register(&target, &source, &Pose::identity(), &params).expect("register")
                    })
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench_registration);
criterion_main!(benches);
