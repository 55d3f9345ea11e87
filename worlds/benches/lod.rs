//! Criterion benchmarks of the near-field LOD chain (seed 004 §4–5): `lod_chain` (4 levels, 2 cm) over the
//! continuous mesh of three library species at seed 1, most of whose time is `measure` (every level's candidate
//! measured against the full mesh's vertices), and `measure` alone for the chain's last level.
//!
//! `cargo bench -p canopy-worlds --features meshopt --bench lod`.

use std::hint::black_box;
use std::time::Duration;

use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::nearfield::continuous::{ContinuousOptions, continuous_mesh};
use canopy_worlds::nearfield::lod::{LodOptions, lod_chain, measure};
use criterion::{Criterion, criterion_group, criterion_main};

fn chains(c: &mut Criterion) {
    let opts = LodOptions { levels: 4, error: 0.02 };
    for (name, detail) in [("sympodial", 0), ("conifer", 1), ("monopodial", 2)] {
        let entry = canopy_worlds::library::SPECIES.iter().find(|e| e.name() == name).expect("a library species");
        let g = entry.load().expect("parses");
        let s = amplify(&g, &Instance::new(1).with_detail(detail), &Budget::default()).expect("amplifies");
        let cm = continuous_mesh(&s, &ContinuousOptions { contour: 6, ..ContinuousOptions::default() }).expect("mesh");
        eprintln!("{name}: {} triangles", cm.mesh.triangle_count());
        let mut g = c.benchmark_group("lod_chain");
        g.sample_size(10).measurement_time(Duration::from_secs(5));
        g.bench_function(name, |b| b.iter(|| black_box(lod_chain(black_box(&cm), &opts).expect("a chain").len())));
        g.finish();
        let last = lod_chain(&cm, &opts).expect("a chain").pop().expect("a level");
        let points: Vec<[f64; 3]> = cm.mesh.positions.iter().map(|p| p.map(f64::from)).collect();
        let mut g = c.benchmark_group("measure");
        g.sample_size(10).measurement_time(Duration::from_secs(5));
        g.bench_function(name, |b| {
            b.iter(|| {
                black_box(measure(&points, &last.mesh.positions, &last.mesh.indices, f64::from(last.bound)).error)
            })
        });
        g.finish();
    }
}

criterion_group!(benches, chains);
criterion_main!(benches);
