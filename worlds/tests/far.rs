//! Far-view summaries (issue 15): the hierarchy aggregates exactly, nodes do not depend on the order or blocks they
//! are computed in, the leaf expectation is close to the exact expansion (counts, heights, coverage), bare rock
//! summarises to nothing, the Poisson-disk packing constant is what the process measures, and a memo corrected by
//! a cell's edits counts them in the cell's leaf and every ancestor.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use canopy_protocol::CellCoord;
use canopy_protocol::edit::{CellDelta, Planted};
use canopy_protocol::record::{InstanceRecord, PackedF32};
use canopy_protocol::summary::{MAX_NODE_SPECIES, NodeKey, NodeSummary, SpeciesCover};
use canopy_test_support::{forest, highlands};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::world::{
    CellKey, LeafEdit, MAX_CORRECTED_CELLS, PACKING, POSITION_STEPS, Placement, Summaries, World, aggregate,
    summary_bytes,
};

fn parse(text: &str) -> World {
    World::parse(&SourceFile::new("t.world", text), None).unwrap_or_else(|d| panic!("{d}"))
}

fn key(level: u8, x: i32, z: i32) -> NodeKey {
    NodeKey { level, x, z }
}

fn cell(x: i32, z: i32) -> CellKey {
    CellKey { x, z }
}

/// Nodes of both worlds at several levels: forest, tree line, meadows, valley, far corners.
fn sample_nodes() -> Vec<(&'static World, NodeKey)> {
    let f = forest();
    let h = highlands();
    vec![
        (f, key(1, -1, 2)),
        (f, key(2, -2, -3)),
        (f, key(3, 0, -2)),
        (f, key(4, -1, -1)),
        (f, key(5, -1, 0)),
        (h, key(1, -179, 145)),
        (h, key(2, -151, 99)),
        (h, key(3, -75, 47)),
        (h, key(4, -20, 24)),
        (h, key(5, 3, 3)),
        (h, key(3, 99, 99)),
        (h, key(4, -50, -50)),
    ]
}

#[test]
fn a_parent_is_the_exact_aggregate_of_its_children() {
    for (w, k) in sample_nodes() {
        let parent = w.node_summary(k);
        let children = k.children().expect("level ≥ 1").map(|c| w.node_summary(c));
        assert_eq!(parent, aggregate(k, [&children[0], &children[1], &children[2], &children[3]]), "{k:?}");
        parent.validate().expect("valid");
        assert!(parent.species.len() <= MAX_NODE_SPECIES);
        // Counts are the exact sums of the children's (fewer than 32 species: nothing truncated).
        let ids: BTreeSet<u16> = children.iter().flat_map(|c| c.species.iter().map(|s| s.species)).collect();
        assert_eq!(ids.len(), parent.species.len(), "{k:?}");
        for s in &parent.species {
            let sum: u32 = children
                .iter()
                .flat_map(|c| c.species.iter())
                .filter(|c| c.species == s.species)
                .map(|c| c.count)
                .sum();
            assert_eq!(s.count, sum, "{k:?} species {}", s.species);
            assert!(s.cover != 0, "a positive count has a non-empty mask");
            let heights = children.iter().flat_map(|c| c.species.iter()).filter(|c| c.species == s.species);
            let (lo, hi) = heights.fold((u16::MAX, 0), |(lo, hi), c| (lo.min(c.height_dm), hi.max(c.height_dm)));
            assert!((lo..=hi).contains(&s.height_dm), "{k:?}: a mean lies between the children's");
        }
        let expected = if parent.species.is_empty() { 0.0 } else { w.cell_size * (1 << k.level) as f32 / 8.0 };
        assert_eq!(parent.error, expected, "{k:?}");
        assert!(summary_bytes(&parent) <= canopy_protocol::summary::MAX_NODE_BYTES);
    }
    // The sample is not all empty.
    assert!(sample_nodes().iter().filter(|(w, k)| w.node_summary(*k).total() > 1000).count() >= 8);
}

fn cover(species: u16, count: u32, height_dm: u16, spread_dm: u16, bits: &[(u32, u32)]) -> SpeciesCover {
    let cover = bits.iter().fold(0u64, |m, &(i, j)| m | 1 << (j * 8 + i));
    SpeciesCover { species, count, height_dm, spread_dm, cover }
}

#[test]
fn aggregation_rounds_heights_in_integers_and_keeps_mostly_covered_bits() {
    let k = key(3, 4, -2);
    let [k0, k1, k2, k3] = k.children().expect("children");
    let node = |key, species| NodeSummary { key, error: 16.0, species };
    // Species 1: child 0 covers the 2 × 2 block under parent bit (0, 0) fully and only one bit under (1, 0);
    // child 3 one bit under parent (4, 4). Species 2: only one bit anywhere (the densest then stays).
    let a =
        node(k0, vec![cover(1, 3, 100, 0, &[(0, 0), (1, 0), (0, 1), (1, 1), (2, 0)]), cover(2, 1, 0, 0, &[(7, 7)])]);
    let b = node(k1, vec![]);
    let c = node(k2, vec![cover(3, 2, 50, 10, &[(3, 3), (2, 3)])]);
    let d = node(k3, vec![cover(1, 2, 105, 20, &[(0, 0)])]);
    let p = aggregate(k, [&a, &b, &c, &d]);
    assert_eq!(p.error, 32.0);
    assert_eq!(p.species.iter().map(|s| (s.species, s.count)).collect::<Vec<_>>(), [(1, 5), (2, 1), (3, 2)]);
    let s1 = &p.species[0];
    // (3·100 + 2·105) / 5 = 102; spread √(5·(3·100² + 2·(20² + 105²)) − 510²) / 5 = √(5·(30000 + 22850) − 260100)/5.
    assert_eq!(s1.height_dm, 102);
    let spread = ((5.0f64 * (30_000.0 + 2.0 * (400.0 + 11_025.0)) - 510.0 * 510.0).sqrt() / 5.0 + 0.5).floor();
    assert_eq!(f64::from(s1.spread_dm), spread);
    assert_eq!(s1.cover, 1, "only (0, 0) has 2 of its 4 child bits set");
    assert_eq!(p.species[1].cover, 1 << (3 * 8 + 3), "the densest sub-square is kept");
    assert_eq!(p.species[2].cover, 1 << (5 * 8 + 1), "two child bits under (1, 5)");
    // Rounding half up: (1·11 + 1·12) / 2 = 11.5 → 12.
    let h = |dm, key| node(key, vec![cover(0, 1, dm, 0, &[(0, 0), (1, 0)])]);
    let p = aggregate(k, [&h(11, k0), &h(12, k1), &node(k2, vec![]), &node(k3, vec![])]);
    assert_eq!(p.species[0].height_dm, 12);
    // The most numerous MAX_NODE_SPECIES species are kept, ties by lower id.
    let many: Vec<SpeciesCover> = (0..40u16).map(|s| cover(s, 1 + u32::from(s % 3), 0, 0, &[(0, 0)])).collect();
    let p = aggregate(k, [&node(k0, many), &node(k1, vec![]), &node(k2, vec![]), &node(k3, vec![])]);
    assert_eq!(p.species.len(), MAX_NODE_SPECIES);
    p.validate().expect("valid");
    let kept: Vec<u16> = p.species.iter().map(|s| s.species).collect();
    let mut want: Vec<u16> = (0..40u16).filter(|s| s % 3 != 0).collect();
    want.extend((0..40u16).filter(|s| s % 3 == 0).take(MAX_NODE_SPECIES - want.len()));
    want.sort_unstable();
    assert_eq!(kept, want);
    // Nothing in, nothing out.
    let e = node(k0, vec![]);
    assert_eq!(aggregate(k, [&e, &e, &e, &e]), NodeSummary { key: k, error: 0.0, species: vec![] });
}

#[test]
fn nodes_do_not_depend_on_order_blocks_or_cache() {
    let h = highlands();
    // Leaves across block borders: one rectangle, and each cell alone.
    let (c0, c1) = (cell(-330, 374), cell(-313, 389));
    let block = h.leaf_summaries(c0, c1);
    assert_eq!(block.len(), 18 * 16);
    for (k, leaf) in block.iter().enumerate() {
        let c = cell(c0.x + (k % 18) as i32, c0.z + (k / 18) as i32);
        assert_eq!(leaf.key, key(0, c.x, c.z));
        if k % 7 == 0 {
            assert_eq!(h.leaf_summaries(c, c), std::slice::from_ref(leaf), "cell {c:?}");
        }
    }
    assert!(block.iter().map(NodeSummary::total).sum::<u64>() > 10_000);
    // A memo queried coarse to fine, and a tiny one queried fine to coarse, in another order.
    let world = Arc::clone(h);
    let mut keys = vec![key(6, -6, 5), key(5, -11, 11), key(5, -10, 10), key(4, -21, 22)];
    keys.extend([key(3, -41, 45), key(2, -81, 92), key(1, -163, 184), key(0, -326, 369), key(0, -325, 369)]);
    let mut big = Summaries::new(world.clone());
    let first: Vec<Arc<NodeSummary>> = keys.iter().map(|&k| big.get(k)).collect();
    let mut tiny = Summaries::with_capacity(world, 3);
    let mut order: Vec<usize> = (0..keys.len()).rev().collect();
    order.swap(1, 4);
    for &i in &order {
        assert_eq!(tiny.get(keys[i]), first[i], "{:?}", keys[i]);
        assert!(tiny.len() <= 3);
    }
    for (&k, n) in keys.iter().zip(&first) {
        assert_eq!(**n, h.node_summary(k), "{k:?}");
        assert_eq!(big.get(k), *n, "cached");
    }
}

/// The sampled blocks of 4 × 4 cells: the forest's valley, slopes and ridge; the highlands' tree line, meadows,
/// foothills and conifer slopes.
const FOREST_BLOCKS: [(i32, i32); 4] = [(4, -10), (-8, 0), (8, 4), (-12, -6)];
const HIGHLAND_BLOCKS: [(i32, i32); 4] = [(-358, 290), (-602, 398), (-320, 382), (100, 100)];

/// A placement's height parameter, where it has a known one.
fn height_of(w: &World, p: &Placement) -> Option<f32> {
    let graph = &w.species[usize::from(p.species)].graph;
    let slot = graph.param_slot("height")?;
    let own = p.params.iter().find(|(s, _)| *s == slot).map(|&(_, v)| v);
    own.or_else(|| graph.params[usize::from(slot)].default.as_constant())
}

#[test]
fn the_leaf_expectation_is_close_to_the_exact_expansion() {
    for (w, blocks) in [(forest(), FOREST_BLOCKS), (highlands(), HIGHLAND_BLOCKS)] {
        let n = w.species.len();
        let (mut est, mut exact) = (vec![0u64; n], vec![0u64; n]);
        let (mut est_h, mut exact_h, mut exact_known) = (vec![0.0f64; n], vec![0.0f64; n], vec![0u64; n]);
        let (mut inside, mut placed) = (0u64, 0u64);
        for (x, z) in blocks {
            let (c0, c1) = (cell(x, z), cell(x + 3, z + 3));
            let leaves = w.leaf_summaries(c0, c1);
            for (leaf, (c, list)) in leaves.iter().zip(w.expand_cells(c0, c1)) {
                assert_eq!(leaf.key, key(0, c.x, c.z));
                for s in &leaf.species {
                    est[usize::from(s.species)] += u64::from(s.count);
                    est_h[usize::from(s.species)] += f64::from(s.count) * f64::from(s.height_dm) / 10.0;
                }
                for p in &list {
                    let sp = usize::from(p.species);
                    exact[sp] += 1;
                    if let Some(h) = height_of(w, p) {
                        exact_h[sp] += f64::from(h);
                        exact_known[sp] += 1;
                    }
                    // Coverage: where the instances stand.
                    let [ox, oz] = w.cell_origin(c);
                    let sub = f64::from(w.cell_size / 8.0);
                    let (i, j) = (((p.x - f64::from(ox)) / sub) as u32, ((p.z - f64::from(oz)) / sub) as u32);
                    placed += 1;
                    if leaf.species.iter().any(|s| s.species == p.species && s.covers(i, j)) {
                        inside += 1;
                    }
                }
                if list.is_empty() {
                    assert!(leaf.total() <= 1, "an empty cell summarises to (nearly) nothing: {leaf:?}");
                }
            }
        }
        for sp in 0..n {
            let name = &w.species[sp].name;
            if exact[sp] >= 100 {
                let ratio = est[sp] as f64 / exact[sp] as f64;
                eprintln!(
                    "{} {name}: {} estimated, {} placed ({:+.1} %)",
                    w.name,
                    est[sp],
                    exact[sp],
                    (ratio - 1.0) * 100.0
                );
                assert!((0.9..=1.1).contains(&ratio), "{} {name}: {} estimated, {} placed", w.name, est[sp], exact[sp]);
            }
            if exact_known[sp] == exact[sp] && exact[sp] >= 100 {
                let (e, x) = (est_h[sp] / est[sp] as f64, exact_h[sp] / exact[sp] as f64);
                eprintln!("{} {name}: mean height {e:.2} m estimated, {x:.2} m placed", w.name);
                assert!((e - x).abs() < 1.0, "{} {name}: mean height {e} estimated, {x} placed", w.name);
            }
        }
        let share = inside as f64 / placed as f64;
        eprintln!("{}: {:.3} of the instances stand in covered sub-squares", w.name, share);
        assert!(share > 0.8, "{}: {:.3} of the instances stand in covered sub-squares", w.name, share);
    }
}

#[test]
fn bare_rock_above_the_tree_line_summarises_to_nothing() {
    let h = highlands();
    for k in [key(4, 0, 44), key(4, 0, 43), key(4, -1, 43), key(4, 0, 42)] {
        let n = h.node_summary(k);
        assert_eq!((n.error, n.species.len()), (0.0, 0), "{k:?}: {n:?}");
        let c = k.first_cell();
        let cells = h.expand_cells(cell(c.x + 7, c.z + 7), cell(c.x + 8, c.z + 8));
        assert!(cells.iter().all(|(_, l)| l.is_empty()), "the exact expansion is empty too");
        assert!(h.height(c.x as f32 * 64.0, c.z as f32 * 64.0) > 1350.0, "above the weeds' altitude");
    }
    // Outside the bounds too.
    assert_eq!(h.node_summary(key(2, 300, 300)).error, 0.0);
}

#[test]
fn packing_constant_matches_the_poisson_disk_process() {
    // One rule at density 1 on flat open ground, well inside the bounds (no edge effect): darts per spacing².
    let w = parse("seed 7\nbounds -4096 -4096 4096 4096\ncell 64\nspecies a conifer\nscatter a {\n  spacing 4\n}\n");
    let cells = w.expand_cells(cell(-8, -8), cell(7, 7));
    let darts: usize = cells.iter().map(|(_, l)| l.len()).sum();
    let measured = darts as f64 / (1024.0 * 1024.0) * 16.0;
    assert!((measured / PACKING - 1.0).abs() < 0.02, "measured {measured}, PACKING {PACKING}");
    // And the leaves count what the expansion placed.
    let est: u64 = w.leaf_summaries(cell(-8, -8), cell(7, 7)).iter().map(NodeSummary::total).sum();
    assert!((est as f64 / darts as f64 - 1.0).abs() < 0.02, "{est} estimated, {darts} placed");
}

#[test]
fn an_avoiding_rule_is_estimated_within_tolerance() {
    // Flat ground, pairs and triples of rules like the embedded worlds' (weeds under trees, bushes between them).
    let configs = [
        "species b conifer\nspecies a conifer\nscatter b {\n spacing 2.6\n}\nscatter a {\n spacing 3\n density 0.8\n avoid b 2\n}\n",
        "species b conifer\nspecies a conifer\nscatter b {\n spacing 6.5\n density 0.6\n}\nscatter a {\n spacing 6\n avoid b 5\n}\n",
        "species b conifer\nspecies a conifer\nscatter b {\n spacing 4\n density 0.5\n}\nscatter a {\n spacing 5\n avoid b 4\n}\n",
        "species b conifer\nspecies c conifer\nspecies a conifer\nscatter b {\n spacing 6.5\n}\nscatter c {\n spacing 6\n avoid b 5\n}\nscatter a {\n spacing 5\n density 0.8\n avoid b 3\n avoid c 3\n}\n",
    ];
    for text in configs {
        let w = parse(&format!("seed 7\nbounds -4096 -4096 4096 4096\ncell 64\n{text}"));
        let (c0, c1) = (cell(-4, -4), cell(3, 3));
        let mut est = vec![0u64; w.species.len()];
        for n in w.leaf_summaries(c0, c1) {
            n.species.iter().for_each(|s| est[usize::from(s.species)] += u64::from(s.count));
        }
        let mut exact = vec![0u64; w.species.len()];
        for (_, l) in w.expand_cells(c0, c1) {
            l.iter().for_each(|p| exact[usize::from(p.species)] += 1);
        }
        for (e, x) in est.iter().zip(&exact) {
            eprintln!("{e} estimated, {x} placed ({:+.1} %)", (*e as f64 / *x as f64 - 1.0) * 100.0);
            assert!((*e as f64 / *x as f64 - 1.0).abs() < 0.08, "{e} estimated, {x} placed:\n{text}");
        }
    }
}

/// Counts by species.
fn counts(n: &NodeSummary) -> BTreeMap<u16, u32> {
    n.species.iter().map(|s| (s.species, s.count)).collect()
}

/// The node of `level` holding cell `c`.
fn holding(c: CellKey, level: u8) -> NodeKey {
    NodeKey::of_cell(CellCoord::new(c.x, c.z), level)
}

/// A cell's edits from version 0, as a delta carries them (checked as its receiver checks it).
fn delta(
    c: CellKey,
    total: usize,
    adds: Vec<Planted>,
    removes: Vec<u16>,
    updates: Vec<(u16, Vec<(u16, PackedF32)>)>,
) -> CellDelta {
    let total = u16::try_from(total).expect("a cell's records fit a u16");
    let d = CellDelta {
        cell: CellCoord::new(c.x, c.z),
        grant: 1,
        from_version: 0,
        to_version: 1,
        total,
        adds,
        removes,
        updates,
    };
    d.validate().expect("a valid delta");
    d
}

#[test]
fn felling_a_cell_takes_its_instances_from_its_leaf_and_its_ancestors() {
    let w = forest();
    let c = cell(4, -10);
    let (leaf_key, top_key, next_key) = (holding(c, 0), holding(c, 4), key(0, c.x + 1, c.z));
    let base = w.expand_cell(c);
    let mut felled: BTreeMap<u16, u32> = BTreeMap::new();
    base.iter().for_each(|p| *felled.entry(p.species).or_default() += 1);
    let d = delta(c, base.len(), vec![], (0..base.len() as u16).collect(), vec![]);
    let edits = w.leaf_edits(c, &base, &d);
    assert_eq!(edits.len(), base.len());
    assert!(edits.iter().zip(&base).all(|(e, p)| (e.species, e.x, e.z, e.sign) == (p.species, p.x, p.z, -1)));
    let mut memo = Summaries::new(Arc::clone(w));
    let (leaf, top, next) = (memo.get(leaf_key), memo.get(top_key), memo.get(next_key));
    assert_eq!(*leaf, w.leaf_summaries(c, c)[0], "without edits, the world function's leaf");
    assert!(memo.correct(c, Some(edits.into())));
    assert_eq!(memo.corrected_cells(), 1);
    let (before, after) = (counts(&leaf), counts(&memo.get(leaf_key)));
    for (s, &n) in &before {
        let want = n.saturating_sub(felled.get(s).copied().unwrap_or(0));
        assert_eq!(after.get(s).copied().unwrap_or(0), want, "species {s}: {n} less the {:?} felled", felled.get(s));
    }
    assert!(after.keys().all(|s| before.contains_key(s)), "felling adds no species");
    let dropped: u32 = before.values().sum::<u32>() - after.values().sum::<u32>();
    assert!(dropped > 100, "the cell held instances to fell: {before:?} → {after:?}");
    // The ancestor drops by what the leaf dropped, species by species.
    let top_after = counts(&memo.get(top_key));
    for (s, &n) in &counts(&top) {
        let drop = before.get(s).copied().unwrap_or(0) - after.get(s).copied().unwrap_or(0);
        assert_eq!(top_after.get(s).copied().unwrap_or(0), n - drop, "species {s}");
    }
    assert_eq!(memo.get(next_key), next, "a neighbouring cell's leaf is unchanged");
    assert_eq!(*next, w.leaf_summaries(cell(c.x + 1, c.z), cell(c.x + 1, c.z))[0]);
}

#[test]
fn planting_adds_one_to_its_species_and_covers_its_sub_square() {
    let w = forest();
    let c = cell(-8, 0);
    let leaf_key = holding(c, 0);
    let mut memo = Summaries::new(Arc::clone(w));
    let before = memo.get(leaf_key);
    // A species of the leaf, and the first sub-square it does not cover.
    let (species, k) = before
        .species
        .iter()
        .find_map(|s| (0..64u32).find(|k| s.cover >> k & 1 == 0).map(|k| (s.species, k)))
        .expect("a sub-square some species does not cover");
    let (i, j) = (k % 8, k / 8);
    let steps = POSITION_STEPS / 8;
    let at = |v: u32| u16::try_from(v * steps + steps / 2).expect("a step within the cell");
    let record = InstanceRecord::new(u8::try_from(species).expect("a species id"), at(i), at(j));
    let base = w.expand_cell(c);
    let plant = Planted { record, params: vec![] };
    let edits = w.leaf_edits(c, &base, &delta(c, base.len() + 1, vec![plant.clone()], vec![], vec![]));
    assert_eq!(edits.len(), 1);
    let e = edits[0];
    let ([ox, oz], sub) = (w.cell_origin(c), f64::from(w.cell_size) / 8.0);
    let sub_of = |v: f64, o: f32| ((v - f64::from(o)) / sub).floor() as u32;
    assert_eq!((e.species, e.sign, sub_of(e.x, ox), sub_of(e.z, oz)), (species, 1, i, j), "{e:?}");
    assert!(memo.correct(c, Some(edits.into())));
    let after = memo.get(leaf_key);
    let mut want = counts(&before);
    *want.get_mut(&species).expect("listed") += 1;
    assert_eq!(counts(&after), want, "exactly one more of its species");
    let s = after.species.iter().find(|s| s.species == species).expect("listed");
    assert!(s.covers(i, j), "the sub-square it stands in is covered");
    // Planted and felled in the same delta: nothing.
    let d = delta(c, base.len() + 1, vec![plant], vec![base.len() as u16], vec![]);
    assert!(w.leaf_edits(c, &base, &d).is_empty());
}

#[test]
fn a_cell_given_back_its_world_function_summarises_as_before() {
    let w = highlands();
    let c = cell(-318, 384);
    let keys = [holding(c, 0), holding(c, 5)];
    let mut memo = Summaries::new(Arc::clone(w));
    let original: Vec<Arc<NodeSummary>> = keys.iter().map(|&k| memo.get(k)).collect();
    let base = w.expand_cell(c);
    // A `set` of an instance's height: the count stays, the height moves.
    let (index, p) =
        base.iter().enumerate().find(|(_, p)| height_of(w, p).is_some()).expect("an instance with a height");
    let slot = w.species[usize::from(p.species)].graph.param_slot("height").expect("a height");
    let raised = height_of(w, p).expect("a height") + 60.0;
    let set = delta(c, base.len(), vec![], vec![], vec![(index as u16, vec![(slot, PackedF32(raised))])]);
    let edits = w.leaf_edits(c, &base, &set);
    let h = |e: &LeafEdit| (e.sign, e.height);
    assert_eq!(edits.iter().map(h).collect::<Vec<_>>(), [(-1, height_of(w, p)), (1, Some(raised))]);
    assert!(memo.correct(c, Some(edits.into())));
    let raised_leaf = memo.get(keys[0]);
    assert_eq!(counts(&raised_leaf), counts(&original[0]), "a set changes no count");
    let height = |n: &NodeSummary| n.species.iter().find(|s| s.species == p.species).expect("listed").height_dm;
    assert!(height(&raised_leaf) > height(&original[0]), "the mean height rises");
    // Felled, planted and set at once, then given back.
    let plant = Planted { record: InstanceRecord::new(0, 100, 200), params: vec![] };
    let mixed = delta(c, base.len() + 1, vec![plant], (0..base.len() as u16).step_by(2).collect(), set.updates.clone());
    assert!(memo.correct(c, Some(w.leaf_edits(c, &base, &mixed).into())));
    for (&k, n) in keys.iter().zip(&original) {
        assert_ne!(memo.get(k), *n, "{k:?} is corrected");
    }
    assert!(memo.correct(c, None));
    assert!(!memo.correct(c, None), "nothing changed");
    assert!(!memo.correct(c, Some(Arc::new([]))), "no edits are the world function too");
    assert_eq!(memo.corrected_cells(), 0);
    for (&k, n) in keys.iter().zip(&original) {
        assert_eq!(memo.get(k), *n, "{k:?}: bit-identical");
        assert_eq!(**n, w.node_summary(k), "{k:?}");
    }
}

#[test]
fn a_correction_drops_every_cached_node_holding_the_cell() {
    let w = forest();
    let c = cell(3, -9);
    let keys: Vec<NodeKey> = (0..=6).map(|level| holding(c, level)).collect();
    let other = [key(0, c.x + 1, c.z), key(4, 1, -1)];
    let mut memo = Summaries::new(Arc::clone(w));
    let old: Vec<Arc<NodeSummary>> = keys.iter().map(|&k| memo.get(k)).collect();
    other.iter().for_each(|&k| drop(memo.get(k)));
    assert!(keys.iter().chain(&other).all(|&k| memo.peek(k).is_some()), "cached");
    let p = w.expand_cell(c)[0].clone();
    let one: Arc<[LeafEdit]> =
        Arc::new([LeafEdit { species: p.species, x: p.x, z: p.z, height: height_of(w, &p), sign: -1 }]);
    assert!(memo.correct(c, Some(one.clone())));
    assert!(keys.iter().all(|&k| memo.peek(k).is_none()), "the leaf and every ancestor are dropped");
    assert!(other.iter().all(|&k| memo.peek(k).is_some()), "nodes not holding the cell are kept");
    for (&k, n) in keys.iter().zip(&old) {
        let species = |n: &NodeSummary| n.species.iter().find(|s| s.species == p.species).map_or(0, |s| s.count);
        assert_eq!(species(&memo.get(k)) + 1, species(n), "{k:?}: not served from the cache");
    }
    assert!(!memo.correct(c, Some(one.clone())), "the same edits again change nothing");
    assert!(keys.iter().all(|&k| memo.peek(k).is_some()), "and drop nothing");
    // At most MAX_CORRECTED_CELLS cells: a new one past it is refused, a known one still corrected or given back.
    for n in 1..MAX_CORRECTED_CELLS as i32 {
        assert!(memo.correct(cell(1000 + n % 64, n / 64), Some(one.clone())));
    }
    assert_eq!(memo.corrected_cells(), MAX_CORRECTED_CELLS);
    assert!(!memo.correct(cell(-1000, 0), Some(one.clone())), "refused past the bound");
    assert_eq!(memo.corrected_cells(), MAX_CORRECTED_CELLS);
    assert!(memo.correct(c, None));
    assert!(memo.correct(cell(-1000, 0), Some(one)), "room again");
}
