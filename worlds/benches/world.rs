//! Criterion benchmarks of world loading: the embedded default world (parse, terrain amplification, population
//! expansion, cell index), terrain height lookups, and the large world's cells as a function (load, one cell
//! alone, a 4 × 4 block, fractal heights), and its far-view summaries (a leaf block of 16 × 16 cells, a level-6
//! node of 64 × 64 cells; one core and all of them).
//!
//! `cargo bench -p canopy-worlds --bench world` — load time is a measurement here, never a test assertion.

use std::hint::black_box;

use canopy_protocol::summary::NodeKey;
use canopy_worlds::world::{CellKey, World};
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

    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("highlands/highlands.world");
    let h = World::load(&path).unwrap_or_else(|d| panic!("{d}"));
    let mut group = c.benchmark_group("highlands");
    group.sample_size(10);
    group.bench_function("load", |b| b.iter(|| black_box(World::load(&path).is_ok())));
    // A conifer slope with weeds under the trees (the densest rules), and a valley of broadleaf.
    for (name, cell) in [("cell_conifer", CellKey { x: -319, z: 383 }), ("cell_valley", CellKey { x: -541, z: -163 })] {
        group.throughput(Throughput::Elements(1));
        group.bench_function(name, |b| b.iter(|| black_box(h.expand_cell(black_box(cell))).len()));
    }
    group.throughput(Throughput::Elements(16));
    group.bench_function("block_4x4_conifer", |b| {
        b.iter(|| h.expand_cells(CellKey { x: -320, z: 382 }, CellKey { x: -317, z: 385 }).len())
    });
    let points: Vec<(f32, f32)> =
        (0..4096u32).map(|k| (-50000.0 + (k % 64) as f32 * 1531.7, -50000.0 + (k / 64) as f32 * 1529.9)).collect();
    group.throughput(Throughput::Elements(points.len() as u64));
    group.bench_function("fractal_height", |b| {
        b.iter(|| points.iter().map(|&(x, z)| h.height(black_box(x), black_box(z))).sum::<f32>())
    });
    group.finish();
}

fn bench_summaries(c: &mut Criterion) {
    let h = World::embedded("highlands").expect("embedded");
    let mut group = c.benchmark_group("summaries");
    group.sample_size(10);
    // One aligned block of 16 × 16 cells on the conifer slopes (a fractal patch and 256 leaves), and one of the
    // forest (a height grid).
    let (c0, c1) = (CellKey { x: -320, z: 368 }, CellKey { x: -305, z: 383 });
    group.throughput(Throughput::Elements(256));
    group.bench_function("leaf_block_16x16", |b| b.iter(|| h.leaf_summaries(black_box(c0), black_box(c1)).len()));
    let f = World::default_world();
    let (f0, f1) = (CellKey { x: -8, z: -8 }, CellKey { x: 7, z: 7 });
    group
        .bench_function("leaf_block_16x16_forest", |b| b.iter(|| f.leaf_summaries(black_box(f0), black_box(f1)).len()));
    // A level-6 node: 4,096 leaves in 16 blocks (on the available cores) aggregated up.
    let node = NodeKey { level: 6, x: -5, z: 5 };
    group.throughput(Throughput::Elements(4096));
    group.bench_function("node_level6", |b| b.iter(|| h.node_summary(black_box(node)).species.len()));
    group.finish();
}

criterion_group!(benches, bench_world, bench_summaries);
criterion_main!(benches);
