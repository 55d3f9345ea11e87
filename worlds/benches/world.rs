//! Criterion benchmarks of world loading: the embedded default world (parse, terrain amplification, population
//! expansion, cell index), and terrain height lookups.
//!
//! `cargo bench -p canopy-worlds --bench world` — load time is a measurement here, never a test assertion.

use std::hint::black_box;

use canopy_worlds::world::World;
use criterion::{Criterion, Throughput, criterion_group, criterion_main};

fn bench_world(c: &mut Criterion) {
    let mut group = c.benchmark_group("world");
    group.sample_size(10);
    let w = World::default_world();
    group.throughput(Throughput::Elements(w.instances.len() as u64));
    group.bench_function("load_default", |b| b.iter(|| black_box(World::default_world()).instances.len()));
    group.finish();

    let mut group = c.benchmark_group("terrain");
    let points: Vec<(f32, f32)> =
        (0..4096u32).map(|k| (-1024.0 + (k % 64) as f32 * 31.7, -1024.0 + (k / 64) as f32 * 31.9)).collect();
    group.throughput(Throughput::Elements(points.len() as u64));
    group.bench_function("height", |b| {
        b.iter(|| points.iter().map(|&(x, z)| w.height(black_box(x), black_box(z))).sum::<f32>())
    });
    group.bench_function("height_and_slope", |b| {
        b.iter(|| points.iter().map(|&(x, z)| w.terrain.height_and_slope(black_box(x), black_box(z)).1).sum::<f32>())
    });
    group.finish();
}

criterion_group!(benches, bench_world);
criterion_main!(benches);
