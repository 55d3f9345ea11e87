//! Criterion benchmarks of amplification: primitives per second for each library species (one core), and meshing.
//!
//! `cargo bench -p canopy-worlds --bench amplify` — throughput is reported in primitives (elements) per second.

use std::hint::black_box;

use canopy_worlds::amplify::{Budget, Instance, amplify_into};
use canopy_worlds::library::SPECIES;
use canopy_worlds::mesh::{Mesh, MeshOptions, mesh_into};
use canopy_worlds::primitive::PrimitiveStream;
use criterion::{Criterion, Throughput, criterion_group, criterion_main};

fn bench_amplify(c: &mut Criterion) {
    let mut group = c.benchmark_group("amplify");
    for entry in SPECIES {
        let g = entry.load().expect("library species parse");
        let inst = Instance::new(1);
        let budget = Budget::default();
        let mut out = PrimitiveStream::default();
        amplify_into(&g, &inst, &budget, &mut out).expect("amplifies");
        group.throughput(Throughput::Elements(out.primitives.len() as u64));
        group.bench_function(entry.name(), |b| {
            b.iter(|| {
                out.primitives.clear();
                out.leaf_points.clear();
                amplify_into(black_box(&g), black_box(&inst), &budget, &mut out).expect("amplifies");
                black_box(out.primitives.len())
            })
        });
    }
    group.finish();

    let mut group = c.benchmark_group("mesh");
    for entry in SPECIES {
        let g = entry.load().expect("library species parse");
        let mut stream = PrimitiveStream::default();
        amplify_into(&g, &Instance::new(1), &Budget::default(), &mut stream).expect("amplifies");
        group.throughput(Throughput::Elements(stream.primitives.len() as u64));
        let opts = MeshOptions::default();
        let mut m = Mesh::default();
        group.bench_function(entry.name(), |b| {
            b.iter(|| {
                m = Mesh::default();
                mesh_into(black_box(&stream), &opts, &mut m);
                black_box(m.indices.len())
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench_amplify);
criterion_main!(benches);
