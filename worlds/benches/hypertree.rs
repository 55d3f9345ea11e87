//! Criterion benchmarks of hypertrees in Table 1's layout (seed 000): for the four Figure 7 trees (A apple, B spruce,
//! C willow, D fork) and each storage structure (index list, index list + bit array, 3D array), creation time and
//! render time at resolution 100 without supersampling and at 300 with s = 2, image 300 × 300, one core.
//!
//! `cargo bench -p canopy-worlds --bench hypertree` (filter with e.g. `-- create/A` or `-- render/.*300`).
//! Memory per structure is printed once per cell before its timings. `canopy hypertree bench` prints the whole
//! table with the paper's values beside it.

use std::hint::black_box;
use std::time::Duration;

use canopy_worlds::hypertree::StorageType;
use canopy_worlds::hypertree::generate::{GenerateOptions, generate};
use canopy_worlds::hypertree::library::{self, TABLE1};
use canopy_worlds::hypertree::render::{RenderOptions, render};
use criterion::{Criterion, criterion_group, criterion_main};

fn table1(c: &mut Criterion) {
    for row in TABLE1 {
        let def = library::find(row.file).expect("embedded").load().expect("parses");
        for storage in StorageType::ALL {
            for (res, s) in [(100u32, 1u32), (300, 2)] {
                let opts = GenerateOptions { storage, resolution: Some([res; 3]), ..GenerateOptions::default() };
                let tree = generate(&def, 1, &opts, &mut |_, _| {}).expect("generates").0;
                let cell = format!("{}/{}/{res}", row.label, storage.name());
                eprintln!("memory {cell}: {} bytes ({} non-empty voxels)", tree.store.memory_bytes(), tree.len());
                let mut g = c.benchmark_group("create");
                g.sample_size(10).measurement_time(Duration::from_secs(4));
                g.bench_function(&cell, |b| {
                    b.iter(|| {
                        black_box(generate(black_box(&def), 1, &opts, &mut |_, _| {}).expect("generates").0.len())
                    })
                });
                g.finish();
                let ropts = RenderOptions { supersample: s, ..RenderOptions::default() };
                let mut g = c.benchmark_group("render");
                g.sample_size(10).measurement_time(Duration::from_secs(4));
                g.bench_function(&cell, |b| {
                    b.iter(|| {
                        black_box(render(black_box(&tree), &ropts, &mut |_, _| {}).expect("renders").0.pixels.len())
                    })
                });
                g.finish();
            }
        }
    }
}

criterion_group!(benches, table1);
criterion_main!(benches);
