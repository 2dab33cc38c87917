//! Simulator speed: one 64-beam sweep (0.2 deg, ~115 000 rays) per site, on one thread.
//! Target: at least 20 sweeps/s on one core. Run: `cargo bench -p kfmap-sim --bench sim`.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use kfmap_sim::{Preset, SimConfig, Simulation};

fn bench_sweeps(c: &mut Criterion) {
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let mut group = c.benchmark_group("sweep_64_beams");
    group.sample_size(20);
    for preset in Preset::ALL {
        let sim = Simulation::new(SimConfig {
            preset,
            seconds: 30.0,
            ..SimConfig::default()
        })
        .expect("config");
        let points = sim.scan(100).cloud.len();
        println!(
            "{}: {points} points per sweep, {} shapes",
            preset.name(),
            sim.site().scene.shape_count()
        );
        group.throughput(Throughput::Elements(1));
        group.bench_function(BenchmarkId::from_parameter(preset.name()), |b| {
            b.iter(|| one.install(|| sim.scan(100)))
        });
    }
    group.finish();
}

criterion_group!(benches, bench_sweeps);
criterion_main!(benches);
