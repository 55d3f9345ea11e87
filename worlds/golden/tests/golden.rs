//! Golden determinism vectors: hashes of the primitive stream and mesh of every library species for fixed seeds
//! and detail levels (`vectors/amplify.txt`), of the cells of 16 blocks of 4 × 4 cells of both embedded worlds
//! (`vectors/cells.txt`: cell expansion is held to the same rule as amplification), of far-view summary nodes of
//! both worlds at levels 0, 2, 4 and 6 (`vectors/summaries.txt`), and of hypertree generation and rendering. The
//! same test binary runs natively, under qemu for aarch64 and under node's WASI for wasm32 in CI
//! (`.ci/cross-determinism`), so a change in any platform's floating point, libm or RNG path shows up as a mismatch
//! here. It lives in a package of its own, `canopy-golden`, whose only dependencies are canopy-worlds,
//! canopy-protocol and postcard: the cross-platform builds compile those and not canopy-worlds' dev-dependencies.
//!
//! To re-bless after an intended change: `CANOPY_BLESS=1 cargo test -p canopy-golden` and review the diff of the
//! vector files (the hypertree hashes are constants below; their tests print the new values).

use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::hypertree::generate::{GenerateOptions, generate};
use canopy_worlds::hypertree::render::{RenderOptions, render};
use canopy_worlds::hypertree::{Hypertree, StorageType};
use canopy_worlds::library::SPECIES;
use canopy_worlds::mesh::{MeshOptions, mesh};

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

/// Checks `got` against a committed vector file's lines (`#` starts a comment line), first difference first. Only
/// `CANOPY_BLESS=1` rewrites the file instead (any other value, `0` or empty, checks) and gives `None`.
fn check_vectors(file: &str, committed: &'static str, got: &[String], what: &str) -> Option<Vec<&'static str>> {
    if std::env::var_os("CANOPY_BLESS").is_some_and(|v| v == "1") {
        std::fs::write(format!("{}/vectors/{file}", env!("CARGO_MANIFEST_DIR")), got.join("\n") + "\n").unwrap();
        return None;
    }
    let want: Vec<&str> = committed.lines().filter(|l| !l.starts_with('#')).collect();
    for (g, w) in got.iter().zip(&want) {
        assert_eq!(g, w, "{what} differs from the golden vector");
    }
    assert_eq!(got.len(), want.len(), "number of golden vectors in {file}");
    Some(want)
}

#[test]
fn amplification_matches_golden_vectors() {
    let committed = include_str!("../vectors/amplify.txt");
    check_vectors("amplify.txt", committed, &vectors(), "amplification (species seed detail count stream mesh)");
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
    let cells = include_str!("../vectors/cells.txt");
    if let Some(want) = check_vectors("cells.txt", cells, &cell_vectors(), "cell expansion (world x z count hash)") {
        assert!(want.iter().filter(|l| !l.contains(" 0 ")).count() > 100, "the golden cells hold instances");
    }
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
    let nodes = include_str!("../vectors/summaries.txt");
    let what = "a summary node (world level x z species total hash)";
    if let Some(want) = check_vectors("summaries.txt", nodes, &summary_vectors(), what) {
        assert!(want.iter().filter(|l| !l.contains(" 0 0 ")).count() > 40, "the golden nodes hold instances");
    }
}

// ---------------------------------------------------------------------------------------------------------------
// Hypertrees (seed 000): generation and rendering

fn hypertree(name: &str, storage: StorageType, res: u32, iterations: u64) -> Hypertree {
    let def = canopy_worlds::hypertree::library::find(name)
        .unwrap_or_else(|| panic!("no library hypertree {name}"))
        .load()
        .expect("library parses");
    let opts =
        GenerateOptions { storage, resolution: Some([res; 3]), iterations: Some(iterations), ..Default::default() };
    generate(&def, 1, &opts, &mut |_, _| {}).expect("generates").0
}

/// Golden hashes: resolution 64, 30 000 iterations, seed 1, index list. Any change to the RNG addressing, the
/// pipelines, the density classes or the voxel mapping changes them.
const HYPERTREES: [(&str, u64, usize); 5] = [
    ("apple", 0xee04c5d588274a7d, 10783),
    ("spruce", 0xd76a14611ecb1086, 1522),
    ("willow", 0xf05132875e89ce07, 18924),
    ("fork", 0xa872258fc6fff22a, 7505),
    ("perturbed", 0x869b076f71d3f80e, 6103),
];

#[test]
fn generation_is_deterministic_golden() {
    let mut report = Vec::new();
    for (name, hash, voxels) in HYPERTREES {
        let t = hypertree(name, StorageType::IndexList, 64, 30_000);
        let again = hypertree(name, StorageType::IndexList, 64, 30_000);
        assert_eq!(t.hash(), again.hash(), "{name} is not deterministic");
        report.push(format!("(\"{name}\", 0x{:016x}, {}),", t.hash(), t.len()));
        if hash != 0 {
            assert_eq!((t.hash(), t.len()), (hash, voxels), "{name} changed; now {}", report.last().expect("pushed"));
        }
    }
    assert!(HYPERTREES.iter().all(|g| g.1 != 0), "pin the golden values:\n{}", report.join("\n"));
}

#[test]
fn render_golden_and_png() {
    let t = hypertree("apple", StorageType::IndexBits, 64, 30_000);
    let (img, stats) = render(
        &t,
        &RenderOptions { width: 64, height: 64, supersample: 2, ..RenderOptions::default() },
        &mut |_, _| {},
    )
    .unwrap();
    assert!(stats.rays > 0);
    let again = render(
        &t,
        &RenderOptions { width: 64, height: 64, supersample: 2, ..RenderOptions::default() },
        &mut |_, _| {},
    )
    .unwrap()
    .0;
    assert_eq!(img.hash(), again.hash());
    // The tree covers the middle of the image and leaves the corners to the sky.
    let sky = img.pixel(0, 0);
    let centre = img.pixel(32, 30);
    assert_ne!(sky, centre);
    assert!(centre[1] >= centre[2], "foliage is greener than it is blue: {centre:?}");
    let png = img.encode_png().unwrap();
    assert_eq!(&png[1..4], b"PNG");
    const GOLDEN_RENDER: u64 = 0x8f39_f0cb_3183_bba2;
    assert_eq!(img.hash(), GOLDEN_RENDER, "render changed: now 0x{:016x}", img.hash());
}
