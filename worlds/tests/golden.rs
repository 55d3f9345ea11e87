//! Golden determinism vectors: hashes of the primitive stream and mesh of every library species for fixed seeds
//! and detail levels, committed in `tests/golden/amplify.txt`. The same test binary runs natively, under qemu for
//! aarch64 and under node's WASI for wasm32 in CI (`.ci/cross-determinism`), so a change in any platform's
//! floating point, libm or RNG path shows up as a mismatch here.
//!
//! To re-bless after an intended change: `CANOPY_BLESS=1 cargo test -p canopy-worlds --test golden` and review
//! the diff of the golden file.

use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::library::SPECIES;
use canopy_worlds::mesh::{MeshOptions, mesh};

const GOLDEN: &str = include_str!("golden/amplify.txt");
const SEEDS: [u64; 3] = [0, 1, 0xdead_beef];
const DETAILS: [u8; 3] = [0, 1, 2];

fn vectors() -> Vec<String> {
    let mut lines = Vec::new();
    for entry in SPECIES {
        let g = entry.load().unwrap_or_else(|d| panic!("{d}"));
        for seed in SEEDS {
            for detail in DETAILS {
                let s = amplify(&g, &Instance::new(seed).with_detail(detail), &Budget::default()).unwrap();
                let m = mesh(&s, &MeshOptions::for_detail(detail));
                lines.push(format!(
                    "{} {seed} {detail} {} {:016x} {:016x}",
                    entry.name(),
                    s.primitives.len(),
                    s.hash(),
                    m.hash()
                ));
            }
        }
    }
    lines
}

#[test]
fn amplification_matches_golden_vectors() {
    let got = vectors().join("\n") + "\n";
    // Only `CANOPY_BLESS=1` rewrites the vectors; any other value (`0`, empty) checks them.
    if std::env::var_os("CANOPY_BLESS").is_some_and(|v| v == "1") {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/golden/amplify.txt");
        std::fs::write(path, &got).unwrap();
        return;
    }
    let want: Vec<&str> = GOLDEN.lines().filter(|l| !l.starts_with('#')).collect();
    let got: Vec<&str> = got.lines().collect();
    for (g, w) in got.iter().zip(&want) {
        assert_eq!(g, w, "amplification differs from the golden vector (species seed detail count stream mesh)");
    }
    assert_eq!(got.len(), want.len(), "number of golden vectors");
}

// wasm32-wasip1 has no threads; the native and aarch64 runs cover this.
#[cfg(not(target_family = "wasm"))]
#[test]
fn thread_count_does_not_change_results() {
    let serial = vectors();
    let parallel: Vec<Vec<String>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..4).map(|_| s.spawn(vectors)).collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for p in parallel {
        assert_eq!(p, serial);
    }
}
