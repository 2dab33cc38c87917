//! Pose-graph optimization of parking-garage.g2o (1661 poses, 6275 edges), Gauss-Newton,
//! one thread; anchor: GTSAM 4.3 via `tools/anchors/gtsam_pose_graph.py`.

use criterion::{Criterion, criterion_group, criterion_main};
use kfmap_graph::pose_graph::{GraphParams, read_g2o};
use kfmap_testdata::require_test_data;

fn bench_pose_graph(c: &mut Criterion) {
    let Some(path) = require_test_data("g2o/parking-garage.g2o", "pose_graph bench") else {
        return;
    };
    let (graph, fixed) = read_g2o(&path).expect("g2o");
    let params = GraphParams {
        fixed,
        ..GraphParams::default()
    };
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let mut group = c.benchmark_group("pose_graph");
    group.sample_size(10);
    group.bench_function("parking_garage_gauss_newton_1_thread", |b| {
        b.iter(|| {
            one.install(|| {
                graph
                    .clone()
                    .optimize(&params)
                    .expect("optimize")
                    .final_error
            })
        })
    });
    group.bench_function("parking_garage_gauss_newton_2_threads", |b| {
        b.iter(|| {
            graph
                .clone()
                .optimize(&params)
                .expect("optimize")
                .final_error
        })
    });
    group.finish();
}

criterion_group!(benches, bench_pose_graph);
criterion_main!(benches);
