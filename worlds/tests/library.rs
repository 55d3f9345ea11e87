//! The species library of seeds 001 and 003: every file parses and amplifies, and each model has the shape, size
//! and level-of-detail behaviour its paper describes.
//! `cargo test -p canopy-worlds --test worlds library:: -- --nocapture` prints the counts per kind and the encoded sizes that `counts_by_kind_and_detail_level` checks.

use std::collections::HashMap;

use canopy_protocol::{Node, Op, SpeciesGraph};
use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::primitive::{PrimitiveStream, Shape};
use canopy_worlds::species_text::parse_species;

const LIBRARY: [(&str, &str); 5] = [
    ("worm.species", include_str!("../species/worm.species")),
    ("monopodial.species", include_str!("../species/monopodial.species")),
    ("conifer.species", include_str!("../species/conifer.species")),
    ("terrain.species", include_str!("../species/terrain.species")),
    ("morpho.species", include_str!("../species/morpho.species")),
];

/// Index of each kind in [`PrimitiveStream::counts`].
const CONE: usize = 0;
const CYLINDER: usize = 1;
const LEAF: usize = 4;

fn load(name: &str) -> SpeciesGraph {
    let (_, text) = LIBRARY.iter().find(|(n, _)| *n == name).expect("in the library");
    let (g, d) = parse_species(&SourceFile::new(name, *text));
    assert!(d.is_empty(), "{}", d.iter().map(|d| d.to_string()).collect::<Vec<_>>().join("\n"));
    g.expect("no diagnostics, so a graph")
}

/// Amplify with named parameter overrides.
fn run(g: &SpeciesGraph, seed: u64, detail: u8, params: &[(&str, f32)]) -> PrimitiveStream {
    let params = params
        .iter()
        .map(|(n, v)| (g.param_slot(n).unwrap_or_else(|| panic!("`{}` has no parameter `{n}`", g.name)), *v))
        .collect();
    amplify(g, &Instance { seed, params, detail }, &Budget::default())
        .unwrap_or_else(|e| panic!("{} seed {seed} detail {detail}: {e}", g.name))
}

fn total(c: [usize; 5]) -> usize {
    c.iter().sum()
}

fn origin(m: &[f32; 12]) -> [f32; 3] {
    [m[3], m[7], m[11]]
}

/// Angle in degrees between a primitive's axis (local +Y, the transform's Y column) and world +Y.
fn tilt(m: &[f32; 12]) -> f64 {
    let (x, y, z) = (f64::from(m[1]), f64::from(m[5]), f64::from(m[9]));
    (y / (x * x + y * y + z * z).sqrt()).clamp(-1.0, 1.0).acos().to_degrees()
}

/// The counts by kind and the encoded sizes (`-- --nocapture` prints the table), and what they must show: every
/// species encodes to a few KB (seed 001 §7), the counts by kind account for every primitive, and the detail
/// level works as seed 001 §5 says: a coarser level never adds primitives, a species with LOD nodes or `detail`
/// in its expressions has fewer at detail 3 than at full detail, and one without them is the same at every level.
#[test]
fn counts_by_kind_and_detail_level() {
    for (name, _) in LIBRARY {
        let g = load(name);
        let bytes = g.encode().len();
        assert!(bytes <= 4096, "{name} encodes to {bytes} bytes, more than a few KB");
        let uses_detail = g.nodes.iter().any(|n| {
            matches!(n, Node::Lod(_)) || n.exprs().iter().any(|e| e.ops.iter().any(|op| matches!(op, Op::Detail)))
        }) || g.params.iter().any(|p| p.default.ops.iter().any(|op| matches!(op, Op::Detail)));
        let mut streams = Vec::new();
        for detail in 0..4u8 {
            let s = run(&g, 1, detail, &[]);
            let c = s.counts();
            println!(
                "{name:19} {bytes:5} B  detail {detail}: cone {:6} cylinder {:4} sphere {:4} box {} leaf {:6}  total {:6}",
                c[0],
                c[1],
                c[2],
                c[3],
                c[4],
                total(c)
            );
            assert_eq!(total(c), s.primitives.len(), "{name} detail {detail}: counts by kind {c:?}");
            streams.push(s);
        }
        let totals: Vec<usize> = streams.iter().map(|s| s.primitives.len()).collect();
        assert!(totals.windows(2).all(|w| w[1] <= w[0]), "{name}: a coarser level adds primitives: {totals:?}");
        if uses_detail {
            assert!(totals[3] < totals[0], "{name} has LOD but detail 3 is no smaller: {totals:?}");
        } else {
            assert!(streams.iter().all(|s| s.hash() == streams[0].hash()), "{name} has no LOD but detail changes it");
        }
    }
}

#[test]
fn every_species_parses_and_amplifies_within_the_default_budget() {
    for (name, _) in LIBRARY {
        let g = load(name);
        assert_eq!(SpeciesGraph::decode(&g.encode()).as_ref(), Ok(&g), "{name} round-trips");
        for seed in 0..8 {
            for detail in 0..4 {
                let s = run(&g, seed, detail, &[]);
                assert!(!s.primitives.is_empty(), "{name} seed {seed} detail {detail} is empty");
                for p in &s.primitives {
                    assert!(p.transform.m.iter().chain(&p.color).all(|v| v.is_finite()), "{name}: non-finite state");
                }
            }
        }
        // Same seed, same stream.
        assert_eq!(run(&g, 5, 0, &[]).hash(), run(&g, 5, 0, &[]).hash(), "{name} is deterministic");
    }
}

// ---- monopodial tree (seed 001 Figure 8) ----

#[test]
fn monopodial_is_compact_and_on_the_scale_of_figure_8() {
    let g = load("monopodial.species");
    let bytes = g.encode().len();
    assert!(bytes <= 2048, "monopodial encodes to {bytes} bytes");
    for p in ["height", "branch_length", "branching"] {
        assert!(g.param_slot(p).is_some(), "parameter `{p}`");
    }
    let mut hashes = Vec::new();
    for seed in 0..8 {
        let s = run(&g, seed, 0, &[]);
        let c = s.counts();
        let axes = c[CONE] + c[CYLINDER];
        assert!((20_000..=45_000).contains(&axes), "seed {seed}: {axes} cones and cylinders ({c:?})");
        assert!(c[LEAF] > 0, "seed {seed} has leaves");
        for p in s.primitives.iter().filter(|p| matches!(p.shape, Shape::Leaf { .. })) {
            assert_eq!(s.leaf(p).len(), 4, "leaves are triangle strips of length 4");
        }
        // Levels of detail: strictly fewer primitives at each coarser level.
        let mut last = total(c);
        for detail in 1..4 {
            let n = total(run(&g, seed, detail, &[]).counts());
            assert!(n < last, "seed {seed}: detail {detail} has {n} primitives, detail {} had {last}", detail - 1);
            last = n;
        }
        hashes.push(s.hash());
    }
    hashes.sort_unstable();
    hashes.dedup();
    assert_eq!(hashes.len(), 8, "every seed grows a different tree");
}

/// Highest primitive origin.
fn top(s: &PrimitiveStream) -> f32 {
    s.primitives.iter().map(|p| origin(&p.transform.m)[1]).fold(f32::MIN, f32::max)
}

#[test]
fn monopodial_parameters_shape_the_tree() {
    let g = load("monopodial.species");
    for seed in 0..4 {
        let base = run(&g, seed, 0, &[]);
        let tall = run(&g, seed, 0, &[("height", 30.0)]);
        let short = run(&g, seed, 0, &[("height", 12.0)]);
        let (b, t, s) = (top(&base), top(&tall), top(&short));
        assert!(t > b + 5.0 && s < b - 4.0, "seed {seed}: tops {s} < {b} < {t}");
        // The trunk is the tallest axis: the tree's top is near `height`.
        assert!((b - 20.0).abs() < 3.0, "seed {seed}: a 20 m tree tops out at {b}");
        // Branching frequency and branch length change the crown.
        let sparse = total(run(&g, seed, 0, &[("branching", 1.2)]).counts());
        assert!(sparse < total(base.counts()), "fewer branches per metre, fewer primitives");
        let spread = |s: &PrimitiveStream| {
            s.primitives
                .iter()
                .map(|p| {
                    let o = origin(&p.transform.m);
                    o[0].hypot(o[2])
                })
                .fold(0.0f32, f32::max)
        };
        let long = run(&g, seed, 0, &[("branch_length", 8.0)]);
        assert!(spread(&long) > spread(&base), "longer branches, wider crown");
    }
}

#[test]
fn monopodial_lod_keeps_the_skeleton() {
    // The draws of the orders kept at a coarser detail do not depend on detail: every frustum of a coarse tree
    // (the trunk, and each finest kept axis collapsed to one frustum) starts exactly where, in the same direction
    // and with the same radius as a frustum of the full tree.
    let g = load("monopodial.species");
    let frusta = |seed: u64, detail: u8| -> Vec<([u32; 12], u32)> {
        run(&g, seed, detail, &[])
            .primitives
            .iter()
            .filter_map(|p| match p.shape {
                Shape::Cone { bottom, .. } => Some((p.transform.m.map(f32::to_bits), bottom.to_bits())),
                _ => None,
            })
            .collect()
    };
    for seed in 0..3 {
        let mut fine = frusta(seed, 0);
        fine.sort_unstable();
        for detail in 1..4 {
            let coarse = frusta(seed, detail);
            assert!(
                coarse.iter().all(|f| fine.binary_search(f).is_ok()),
                "seed {seed} detail {detail}: a frustum that the full tree does not have"
            );
        }
    }
}

// ---- conifer (seed 001 Figure 7) ----

#[test]
fn conifer_has_figure_7_counts_and_hand_made_levels_of_detail() {
    let g = load("conifer.species");
    for seed in 0..8 {
        let counts: Vec<[usize; 5]> = (0..4).map(|d| run(&g, seed, d, &[]).counts()).collect();
        let c = counts[0];
        assert!((12_000..=19_000).contains(&c[CONE]), "seed {seed}: {} needle cones", c[CONE]);
        assert!((120..=300).contains(&c[CYLINDER]), "seed {seed}: {} trunk and branch cylinders", c[CYLINDER]);
        for d in 1..4 {
            assert!(total(counts[d]) < total(counts[d - 1]), "seed {seed}: {counts:?}");
        }
        // Detail 1: each twig is one flat green cone, trunk and branches unchanged.
        assert_eq!(counts[1][CYLINDER], c[CYLINDER]);
        assert!(counts[1][CONE] < c[CONE] / 10);
        // Detail 3: one crown cone on the trunk.
        assert!(total(counts[3]) <= 20, "seed {seed}: detail 3 has {:?}", counts[3]);
    }
}

#[test]
fn conifer_substitutes_sit_where_the_sub_graphs_were() {
    // Branch and twig sub-graphs have their own random contexts, so a substitute does not shift the draws around
    // it: the trunk and branch cylinders are the same at detail 0 and 1, and at detail 2 each branch's flat cone
    // stands exactly where the branch's first cylinder stood (same origin and axis).
    let g = load("conifer.species");
    for seed in 0..4 {
        let streams: Vec<PrimitiveStream> = (0..3).map(|d| run(&g, seed, d, &[])).collect();
        let of_kind = |s: &PrimitiveStream, cylinder: bool| -> Vec<[f32; 12]> {
            s.primitives
                .iter()
                .filter(|p| matches!(p.shape, Shape::Cylinder { .. }) == cylinder)
                .map(|p| p.transform.m)
                .collect()
        };
        assert_eq!(of_kind(&streams[0], true), of_kind(&streams[1], true), "seed {seed}: cylinders at detail 1");
        let branch_bases = |ms: Vec<[f32; 12]>| -> Vec<([f32; 3], [f32; 3])> {
            ms.iter()
                .filter(|m| {
                    let o = origin(m);
                    o[0] == 0.0 && o[2] == 0.0 && tilt(m) > 1.0
                })
                .map(|m| (origin(m), [m[1], m[5], m[9]]))
                .collect()
        };
        let fine = branch_bases(of_kind(&streams[0], true));
        assert!(fine.len() > 40, "seed {seed}: {} branches", fine.len());
        assert_eq!(fine, branch_bases(of_kind(&streams[2], false)), "seed {seed}: branch cones at detail 2");
    }
}

// ---- fractal terrain tile (seed 001 §7) ----

/// Every leaf vertex in world space.
fn vertices(s: &PrimitiveStream) -> Vec<[f32; 3]> {
    s.primitives.iter().flat_map(|p| s.leaf(p).iter().map(|&q| p.transform.point(q))).collect()
}

/// Heights by the bit patterns of (x, z); panics on a crack (one (x, z) with two heights).
fn height_map(s: &PrimitiveStream) -> HashMap<(u32, u32), f32> {
    let mut map: HashMap<(u32, u32), f32> = HashMap::new();
    for v in vertices(s) {
        let h = *map.entry((v[0].to_bits(), v[2].to_bits())).or_insert(v[1]);
        assert_eq!(h.to_bits(), v[1].to_bits(), "crack at ({}, {}): heights {h} and {}", v[0], v[2], v[1]);
    }
    map
}

#[test]
fn terrain_resolution_is_the_recursion_depth() {
    let g = load("terrain.species");
    for detail in 0..4u8 {
        let depth = 7 - u32::from(detail);
        let s = run(&g, 0, detail, &[]);
        assert_eq!(s.counts(), [0, 0, 0, 0, 2 * 4usize.pow(depth)], "detail {detail}");
        assert!(s.primitives.iter().all(|p| s.leaf(p).len() == 3), "two triangles per cell");
    }
    for depth in 0..5u32 {
        let s = run(&g, 0, 0, &[("depth", depth as f32)]);
        assert_eq!(s.counts()[LEAF], 2 * 4usize.pow(depth), "depth {depth}");
        assert_eq!(height_map(&s).len(), (2usize.pow(depth) + 1).pow(2), "a full grid of vertices");
    }
}

#[test]
fn terrain_is_crack_free_and_honours_its_corners() {
    let g = load("terrain.species");
    let corners = [("h00", 3.0), ("h10", -7.5), ("h01", 12.25), ("h11", 40.0)];
    for seed in 0..8 {
        for (size, dimension) in [(256.0, 2.2), (100.0, 2.7), (1000.0, 2.05)] {
            let mut params = corners.to_vec();
            params.extend([("size", size), ("dimension", dimension)]);
            let s = run(&g, seed, 1, &params);
            let map = height_map(&s);
            assert_eq!(map.len(), 65 * 65);
            for (x, z, h) in [(0.0f32, 0.0f32, 3.0), (size, 0.0, -7.5), (0.0, size, 12.25), (size, size, 40.0)] {
                assert_eq!(map.get(&(x.to_bits(), z.to_bits())), Some(&h), "corner ({x}, {z})");
            }
            // Triangles face up.
            for p in &s.primitives {
                let q: Vec<[f32; 3]> = s.leaf(p).iter().map(|&q| p.transform.point(q)).collect();
                let (a, b) = ([q[1][0] - q[0][0], q[1][2] - q[0][2]], [q[2][0] - q[0][0], q[2][2] - q[0][2]]);
                assert!(a[1] * b[0] - a[0] * b[1] > 0.0, "triangle faces down");
            }
        }
    }
}

#[test]
fn terrain_levels_of_detail_and_neighbouring_tiles_agree() {
    let g = load("terrain.species");
    // A coarser depth has exactly the vertices of the finer one at its grid points.
    let fine = height_map(&run(&g, 4, 0, &[]));
    for detail in 1..4 {
        let coarse = height_map(&run(&g, 4, detail, &[]));
        for (k, h) in &coarse {
            assert_eq!(fine.get(k), Some(h), "detail {detail} vertex not on the fine surface");
        }
    }
    // Two tiles side by side (same seed, shared corner heights, offsets = world position) share their edge.
    let left = [("h00", 0.0), ("h10", 10.0), ("h01", 5.0), ("h11", -5.0)];
    let right = [("h00", 10.0), ("h10", 20.0), ("h01", -5.0), ("h11", 0.0), ("ox", 256.0)];
    let a = vertices(&run(&g, 9, 1, &left));
    let b = vertices(&run(&g, 9, 1, &right));
    let edge = |v: &[[f32; 3]], x: f32| {
        let mut e: Vec<(u32, u32)> = v.iter().filter(|p| p[0] == x).map(|p| (p[2].to_bits(), p[1].to_bits())).collect();
        e.sort_unstable();
        e.dedup();
        e
    };
    assert_eq!(edge(&a, 256.0), edge(&b, 0.0));
    assert_eq!(edge(&a, 256.0).len(), 65);
}

/// Mean absolute height difference along the triangle edges.
fn roughness(s: &PrimitiveStream) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for p in &s.primitives {
        let q = s.leaf(p);
        for i in 0..q.len() {
            sum += f64::from((q[i][1] - q[(i + 1) % q.len()][1]).abs());
            n += 1;
        }
    }
    sum / n as f64
}

#[test]
fn terrain_higher_dimension_is_rougher() {
    let g = load("terrain.species");
    let mean = |dimension: f32| {
        (0..8).map(|seed| roughness(&run(&g, seed, 1, &[("dimension", dimension)]))).sum::<f64>() / 8.0
    };
    let (smooth, default, rough) = (mean(2.05), mean(2.2), mean(2.8));
    assert!(smooth < default && default < rough, "roughness {smooth} {default} {rough}");
}

// ---- morphological tree (seed 003) ----

/// First-level branches: frustums standing on the trunk axis (x = z = 0) but tilted. Valid with `jitter` 0, when
/// the trunk is straight.
fn first_level_branches(s: &PrimitiveStream) -> Vec<&[f32; 12]> {
    s.primitives
        .iter()
        .filter(|p| matches!(p.shape, Shape::Cone { .. }))
        .map(|p| &p.transform.m)
        .filter(|m| {
            let o = origin(m);
            o[0].abs() < 1e-6 && o[2].abs() < 1e-6 && tilt(m) > 1.0
        })
        .collect()
}

#[test]
fn morpho_follows_the_golden_rules() {
    let g = load("morpho.species");
    let mut seen = [false; 2];
    for seed in 0..8 {
        for branches in [6.0f32, 7.0, 3.0] {
            let s = run(&g, seed, 0, &[("jitter", 0.0), ("branches", branches)]);
            let first = first_level_branches(&s);
            assert_eq!(first.len(), branches as usize, "seed {seed}: primary branches");
            let mut last_azimuth: Option<f64> = None;
            for m in first {
                let t = tilt(m);
                let golden = [34.4, 55.6].iter().position(|a| (t - a).abs() < 1e-3);
                assert!(golden.is_some(), "seed {seed}: branch angle {t}");
                seen[golden.unwrap()] = true;
                // Neighbouring branches are 225 degrees apart in azimuth.
                let azimuth = f64::from(m[1]).atan2(f64::from(m[9])).to_degrees();
                if let Some(prev) = last_azimuth {
                    let step: f64 = (azimuth - prev).rem_euclid(360.0);
                    assert!((step - 225.0).abs() < 1e-3, "azimuth step {step}");
                }
                last_azimuth = Some(azimuth);
            }
        }
    }
    assert_eq!(seen, [true, true], "both golden angles occur");
}

#[test]
fn morpho_counts_follow_levels_branches_and_leaves() {
    let g = load("morpho.species");
    for (levels, branches, leaves) in [(3, 6, 8), (3, 7, 8), (2, 5, 4), (1, 4, 10), (0, 6, 8)] {
        for (seed, jitter) in [(0, 0.0), (1, 1.0), (2, 1.0)] {
            let s = run(
                &g,
                seed,
                0,
                &[
                    ("levels", levels as f32),
                    ("branches", branches as f32),
                    ("leaves", leaves as f32),
                    ("jitter", jitter),
                ],
            );
            let c = s.counts();
            let last_level = branches_pow(branches, levels);
            assert_eq!(c[LEAF], last_level * leaves, "{levels} levels, {branches} branches, {leaves} leaves");
            // Every axis is a base element plus one element per child (branch or leaf).
            let inner: usize = (0..levels).map(|l| branches_pow(branches, l)).sum();
            assert_eq!(c[CONE], inner * (1 + branches) + last_level * (1 + leaves));
            for p in s.primitives.iter().filter(|p| matches!(p.shape, Shape::Leaf { .. })) {
                assert_eq!(s.leaf(p).len(), 4, "leaves are quadrilaterals");
            }
        }
    }
}

fn branches_pow(b: usize, l: usize) -> usize {
    b.pow(l as u32)
}

#[test]
fn morpho_attenuates_from_the_parent() {
    let g = load("morpho.species");
    let s = run(&g, 0, 0, &[("jitter", 0.0), ("base_radius", 0.4)]);
    // The first trunk element starts at base_radius; primary branches start at 0.45 times it.
    assert_eq!(s.primitives[0].shape, Shape::Cone { bottom: 0.4, top: 0.4 + (0.12 - 0.4) * 0.35, height: 8.0 * 0.35 });
    for m in first_level_branches(&s) {
        let p = s.primitives.iter().find(|p| &p.transform.m == m).unwrap();
        let Shape::Cone { bottom, .. } = p.shape else { unreachable!() };
        assert!((bottom - 0.18).abs() < 1e-6, "primary branch base radius {bottom}");
    }
}

#[test]
fn morpho_lod_replaces_leaves_and_keeps_the_branches() {
    let g = load("morpho.species");
    let axes = |s: &PrimitiveStream| -> Vec<(Shape, [f32; 12])> {
        s.primitives
            .iter()
            .filter(|p| matches!(p.shape, Shape::Cone { .. }))
            .map(|p| (p.shape.clone(), p.transform.m))
            .collect()
    };
    let fine = run(&g, 2, 0, &[]);
    let coarse = run(&g, 2, 1, &[]);
    assert_eq!(axes(&fine), axes(&coarse), "the same branches at both levels");
    assert_eq!(coarse.counts()[LEAF], 0);
    assert_eq!(coarse.counts()[2], 6 * 6 * 6, "one foliage ellipsoid per last-level branch");
}
