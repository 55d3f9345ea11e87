//! Golden determinism vectors: hashes of the primitive stream and mesh of every library species for fixed seeds
//! and detail levels, committed in `tests/golden/amplify.txt`, and of the cells of 16 blocks of 4 × 4 cells of both
//! embedded worlds (`tests/golden/cells.txt`: cell expansion is held to the same rule as amplification), and of
//! far-view summary nodes of both worlds at levels 0, 2, 4 and 6 (`tests/golden/summaries.txt`). The same test
//! binary runs natively, under qemu for
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

/// Blocks of 4 × 4 cells whose expansion is golden: the default world's corners and centre, the large world's
/// far corners, centre, tree line, meadow edge, valley floor and four blocks between the control heights, and the
/// four corners of the coordinate range (±2^20 cells, [`EDGE`]).
const CELL_BLOCKS: [(&str, i32, i32); 20] = [
    ("forest", -16, -16),
    ("forest", 12, 12),
    ("forest", -2, -2),
    ("forest", -16, 12),
    ("highlands", -800, -800),
    ("highlands", 796, 796),
    ("highlands", -800, 796),
    ("highlands", 796, -800),
    ("highlands", -2, -2),
    ("highlands", -247, 563),
    ("highlands", -358, 290),
    ("highlands", -543, -165),
    ("highlands", -2, -602),
    ("highlands", 398, 198),
    ("highlands", -602, 398),
    ("highlands", 598, -402),
    ("edge", -(1 << 20), -(1 << 20)),
    ("edge", (1 << 20) - 4, (1 << 20) - 4),
    ("edge", -(1 << 20), (1 << 20) - 4),
    ("edge", (1 << 20) - 4, -(1 << 20)),
];

/// A world whose bounds are the whole coordinate range: ±2^20 cells of 64 m (±67,108,864 m, where an f32 holds a
/// position only to 8 m), on a fractal terrain, with a rule that avoids another.
const EDGE: &str = "world edge\nseed 11\nbounds -67108864 -67108864 67108864 67108864\ncell 64\n\
    terrain fractal {\n  tile 65536\n  depth 14\n  param relief = 200\n}\nspecies a worm\nspecies b worm\n\
    scatter a {\n  spacing 6\n  altitude -1000 ..\n  param c = 1 .. 3\n}\nscatter b {\n  spacing 4\n  avoid a 3\n}\n";

/// One line per cell: `world x z count hash` over species, position (its steps in the cell, exact at any distance
/// from the origin) and parameters.
fn cell_vectors() -> Vec<String> {
    use canopy_worlds::primitive::Fnv;
    use canopy_worlds::world::{CellKey, World};
    let edge = World::parse(&canopy_worlds::diag::SourceFile::new("edge.world", EDGE), None).expect("the edge world");
    let worlds = [World::embedded("forest").unwrap(), World::embedded("highlands").unwrap(), edge];
    let mut lines = Vec::new();
    for (name, x, z) in CELL_BLOCKS {
        let w = worlds.iter().find(|w| w.name == name).unwrap();
        for (c, list) in w.expand_cells(CellKey { x, z }, CellKey { x: x + 3, z: z + 3 }) {
            let mut h = Fnv::new();
            for p in &list {
                h.u32(u32::from(p.species));
                let [qx, qz] = w.steps(c, p);
                h.u32(u32::from(qx));
                h.u32(u32::from(qz));
                for &(slot, v) in &p.params {
                    h.u32(u32::from(slot));
                    h.f32s(&[v]);
                }
            }
            lines.push(format!("{name} {} {} {} {:016x}", c.x, c.z, list.len(), h.finish()));
        }
    }
    lines
}

#[test]
fn cell_expansion_matches_golden_vectors() {
    const CELLS: &str = include_str!("golden/cells.txt");
    let got = cell_vectors().join("\n") + "\n";
    if std::env::var_os("CANOPY_BLESS").is_some_and(|v| v == "1") {
        std::fs::write(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/golden/cells.txt"), &got).unwrap();
        return;
    }
    let want: Vec<&str> = CELLS.lines().filter(|l| !l.starts_with('#')).collect();
    let got: Vec<&str> = got.lines().collect();
    for (g, w) in got.iter().zip(&want) {
        assert_eq!(g, w, "cell expansion differs from the golden vector (world x z count hash)");
    }
    assert_eq!(got.len(), want.len(), "number of golden cells");
    assert!(want.iter().filter(|l| !l.contains(" 0 ")).count() > 100, "the golden cells hold instances");
}

/// Far-view summary nodes whose encoding is golden, `(world, level, x, z)`: the default world's cells, quadrants
/// and whole quarters; the large world's far corners, tree line, bare rock, meadow edge, valley floor and conifer
/// slopes (levels 0, 2, 4 and 6: a level-6 node is 4,096 leaves, so few of them, for wasm32's sake).
const SUMMARY_NODES: [(&str, u8, i32, i32); 64] = [
    ("forest", 0, -16, -16),
    ("forest", 0, 15, 15),
    ("forest", 0, 0, 0),
    ("forest", 0, -1, -1),
    ("forest", 0, 4, -10),
    ("forest", 0, -8, 0),
    ("forest", 0, 8, 4),
    ("forest", 0, -12, -6),
    ("forest", 0, -15, 14),
    ("forest", 0, 13, -3),
    ("forest", 0, -5, 9),
    ("forest", 0, 16, 0),
    ("forest", 2, -4, -4),
    ("forest", 2, 3, 3),
    ("forest", 2, 0, 0),
    ("forest", 2, 1, -3),
    ("forest", 2, -2, 0),
    ("forest", 2, 2, 1),
    ("forest", 2, -3, -2),
    ("forest", 2, -4, 3),
    ("forest", 4, -1, -1),
    ("forest", 4, 0, 0),
    ("forest", 4, -1, 0),
    ("forest", 4, 0, -1),
    ("forest", 4, 1, 0),
    ("forest", 6, -1, -1),
    ("forest", 6, 0, 0),
    ("highlands", 0, -800, -800),
    ("highlands", 0, 799, 799),
    ("highlands", 0, -800, 799),
    ("highlands", 0, 799, -800),
    ("highlands", 0, 0, 0),
    ("highlands", 0, -247, 563),
    ("highlands", 0, -358, 290),
    ("highlands", 0, -543, -165),
    ("highlands", 0, -320, 382),
    ("highlands", 0, -602, 398),
    ("highlands", 0, 100, 100),
    ("highlands", 0, 0, -600),
    ("highlands", 2, -62, 140),
    ("highlands", 2, -90, 72),
    ("highlands", 2, -136, -42),
    ("highlands", 2, -80, 95),
    ("highlands", 2, -151, 99),
    ("highlands", 2, 25, 25),
    ("highlands", 2, -200, -200),
    ("highlands", 2, 199, 199),
    ("highlands", 2, 0, 176),
    ("highlands", 2, 149, -101),
    ("highlands", 2, -1, -151),
    ("highlands", 4, -16, 35),
    ("highlands", 4, -23, 18),
    ("highlands", 4, -34, -11),
    ("highlands", 4, 0, 44),
    ("highlands", 4, -50, -50),
    ("highlands", 4, 49, 49),
    ("highlands", 4, -50, 49),
    ("highlands", 4, 49, -50),
    ("highlands", 4, -20, 23),
    ("highlands", 4, 6, 6),
    ("highlands", 6, -6, 5),
    ("highlands", 6, -4, 8),
    ("highlands", 6, -13, -13),
    ("highlands", 6, 12, 12),
];

/// One line per node: `world level x z species total hash` with FNV-1a over the node's postcard encoding.
fn summary_vectors() -> Vec<String> {
    use canopy_protocol::summary::NodeKey;
    use canopy_worlds::primitive::Fnv;
    use canopy_worlds::world::World;
    let worlds = [World::embedded("forest").unwrap(), World::embedded("highlands").unwrap()];
    let mut lines = Vec::new();
    for (name, level, x, z) in SUMMARY_NODES {
        let w = worlds.iter().find(|w| w.name == name).unwrap();
        let node = w.node_summary(NodeKey { level, x, z });
        let mut h = Fnv::new();
        h.bytes(&postcard::to_allocvec(&node).unwrap());
        lines.push(format!("{name} {level} {x} {z} {} {} {:016x}", node.species.len(), node.total(), h.finish()));
    }
    lines
}

#[test]
fn summaries_match_golden_vectors() {
    const SUMMARIES: &str = include_str!("golden/summaries.txt");
    let got = summary_vectors().join("\n") + "\n";
    if std::env::var_os("CANOPY_BLESS").is_some_and(|v| v == "1") {
        std::fs::write(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/golden/summaries.txt"), &got).unwrap();
        return;
    }
    let want: Vec<&str> = SUMMARIES.lines().filter(|l| !l.starts_with('#')).collect();
    let got: Vec<&str> = got.lines().collect();
    for (g, w) in got.iter().zip(&want) {
        assert_eq!(g, w, "a summary node differs from the golden vector (world level x z species total hash)");
    }
    assert_eq!(got.len(), want.len(), "number of golden summary nodes");
    assert!(want.iter().filter(|l| !l.contains(" 0 0 ")).count() > 40, "the golden nodes hold instances");
}
