//! Cells as a function of the manifest: the same records whatever the order, thread or neighbourhood a cell is
//! expanded in; Poisson-disk spacing and `avoid` distances across cell borders; densities as the manifest says.

use std::collections::HashMap;

use canopy_test_support::{forest, highlands};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::world::{CellKey, Placement, World};

fn parse(text: &str) -> World {
    World::parse(&SourceFile::new("t.world", text), None).unwrap_or_else(|d| panic!("{d}"))
}

fn key(x: i32, z: i32) -> CellKey {
    CellKey { x, z }
}

/// The materialised world's placements of a cell.
fn stored(w: &World, c: CellKey) -> Vec<Placement> {
    let r = w.cell_instances(c);
    w.instances[r.start as usize..r.end as usize].to_vec()
}

#[test]
fn any_order_any_thread_alone_or_in_blocks_gives_the_same_cells() {
    let w = forest();
    assert!(w.is_materialised());
    let cells: Vec<CellKey> = w.cells().collect();
    let cells = &cells;
    // Alone, in a scrambled order, on two threads.
    let landmarks = [key(0, 0), key(-15, 14), key(-14, 13)].map(|c| cells.iter().position(|&k| k == c).unwrap());
    let mut order: Vec<usize> = (0..cells.len()).step_by(7).chain(landmarks).collect();
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    for i in (1..order.len()).rev() {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        order.swap(i, (state % (i as u64 + 1)) as usize);
    }
    let (a, b) = order.split_at(order.len() / 2);
    std::thread::scope(|s| {
        for half in [a, b] {
            s.spawn(move || {
                for &k in half {
                    let c = cells[k];
                    let alone = w.expand_cells(c, c);
                    assert_eq!(alone.len(), 1);
                    assert_eq!(alone[0].1, stored(w, c), "cell {c:?} alone");
                }
            });
        }
    });
    // In blocks that straddle the world's materialisation bands, past the world's edge, around the cells that
    // hold explicit instances (the landmarks), and the whole world as one block.
    let first = w.first_cell();
    let blocks = [
        (key(first.x + 3, first.z + 13), key(first.x + 7, first.z + 18)),
        (key(12, 12), key(17, 16)),
        (key(-16, 12), key(-13, 15)),
        (key(-1, -1), key(2, 1)),
        (first, key(first.x + 31, first.z + 31)),
    ];
    for (c0, c1) in blocks {
        for (c, list) in w.expand_cells(c0, c1) {
            assert_eq!(list, stored(w, c), "cell {c:?} in block {c0:?}..{c1:?}");
        }
    }
    // A larger world, expanded lazily: a block against its cells alone, in reverse order.
    let h = highlands();
    assert!(!h.is_materialised());
    let block = h.expand_cells(key(-357, 290), key(-354, 293));
    assert_eq!(block.len(), 16);
    assert!(block.iter().map(|(_, l)| l.len()).sum::<usize>() > 1000);
    for (c, list) in block.iter().rev() {
        assert_eq!(&h.expand_cell(*c), list, "highlands cell {c:?}");
    }
}

/// Positions of the placements of one species.
fn of(list: &[Placement], species: u16) -> Vec<[f64; 2]> {
    list.iter().filter(|p| p.species == species).map(|p| [p.x, p.z]).collect()
}

/// The smallest distance between a point of `a` and a different point of `b`.
fn min_distance(a: &[[f64; 2]], b: &[[f64; 2]]) -> f64 {
    let bucket = 8.0;
    let cell = |p: &[f64; 2]| ((p[0] / bucket).floor() as i64, (p[1] / bucket).floor() as i64);
    let mut grid: HashMap<(i64, i64), Vec<[f64; 2]>> = HashMap::new();
    for p in b {
        grid.entry(cell(p)).or_default().push(*p);
    }
    let mut best = f64::INFINITY;
    for p in a {
        let (i, j) = cell(p);
        for q in (-1..=1).flat_map(|dj| (-1..=1).map(move |di| (i + di, j + dj))).filter_map(|k| grid.get(&k)) {
            for q in q {
                let d = ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt();
                if d > 0.0 {
                    best = best.min(d);
                }
            }
        }
    }
    best
}

#[test]
fn spacing_and_avoid_distances_hold_across_every_border_of_a_4x4_block() {
    for (w, c0) in [(highlands(), key(-357, 290)), (highlands(), key(-24, -490)), (forest(), key(-3, -3))] {
        // Every cell alone, then together: pairs across each of the block's 24 inner borders are checked.
        let mut all = Vec::new();
        for z in c0.z..c0.z + 4 {
            for x in c0.x..c0.x + 4 {
                all.extend(w.expand_cell(key(x, z)));
            }
        }
        assert!(all.len() > 500, "{} instances", all.len());
        for (n, rule) in w.rules.iter().enumerate() {
            let own = of(&all, rule.species);
            let d = min_distance(&own, &own);
            assert!(d >= f64::from(rule.spacing), "{}: {d} m apart", w.species[usize::from(rule.species)].name);
            // Other species placed by an earlier rule keep the avoid distance (one rule per species here).
            for &(other, distance) in &rule.avoid {
                let earlier = w.rules[..n].iter().any(|r| r.species == other);
                if other != rule.species && earlier {
                    let d = min_distance(&own, &of(&all, other));
                    assert!(d >= f64::from(distance), "rule {n}: {d} m from species {other}");
                }
            }
        }
    }
}

#[test]
fn density_follows_the_manifest_over_a_large_sample() {
    let full = parse("seed 3\nbounds 0 0 1024 1024\ncell 64\nspecies a worm\nscatter a {\n  spacing 4\n}\n");
    let half =
        parse("seed 3\nbounds 0 0 1024 1024\ncell 64\nspecies a worm\nscatter a {\n  spacing 4\n  density 0.5\n}\n");
    let (n, k) = (full.instances.len() as f64, half.instances.len() as f64);
    // The same darts, thinned: each kept with probability 0.5 (about 46,000 darts: a standard deviation of 0.23 %).
    assert!((k / n - 0.5).abs() < 0.015, "{k} of {n}");
    let kept: std::collections::HashSet<(u64, u64)> =
        full.instances.iter().map(|p| (p.x.to_bits(), p.z.to_bits())).collect();
    assert!(half.instances.iter().all(|p| kept.contains(&(p.x.to_bits(), p.z.to_bits()))));
    // A full packing: about 0.63 darts per spacing² (dart throwing to saturation reaches 0.69).
    let per = n * 16.0 / full.bounds.area();
    println!("{per} darts per spacing²");
    assert!((0.58..0.72).contains(&per), "{per} darts per spacing²");
}

#[test]
fn cells_at_the_far_corners_of_the_coordinate_range_expand() {
    // Bounds at ±cell × 2^20 (±67,108,864 m of 64 m cells: 2^42 cells, the most a world may have) on a fractal
    // terrain; an f32 holds a position there only to 4–8 m, so positions are f64.
    let far = 1 << 20;
    let w = parse(
        "seed 11\nbounds -67108864 -67108864 67108864 67108864\ncell 64\nterrain fractal {\n  tile 65536\n  depth 14\n  \
         param relief = 200\n}\nspecies a worm\nspecies b worm\nscatter a {\n  spacing 6\n  altitude -1000 ..\n}\n\
         scatter b {\n  spacing 4\n  avoid a 3\n}\n",
    );
    assert!(!w.is_materialised());
    assert_eq!((w.first_cell(), w.cell_count()), (key(-far, -far), 1u64 << 42));
    let step = f64::from(w.position_step());
    for c in [key(-far, -far), key(far - 2, far - 2), key(-far, far - 2), key(far - 2, -far), key(-1, -1)] {
        // A 2 × 2 block: each cell alone equals the block, and spacing and avoid hold across its borders.
        let block = w.expand_cells(c, key(c.x + 1, c.z + 1));
        let mut all = Vec::new();
        for (k, list) in &block {
            assert!(!list.is_empty(), "cell {k:?}");
            assert_eq!(list, &w.expand_cell(*k), "cell {k:?} alone");
            let [ox, oz] = w.cell_origin(*k).map(f64::from);
            for p in list {
                assert_eq!(w.cell_of(p.x, p.z), *k);
                // On the cell's position grid, exactly: a whole number of steps below POSITION_STEPS.
                let q = [(p.x - ox) / step, (p.z - oz) / step];
                assert!(q.iter().all(|&q| q.fract() == 0.0 && (0.0..4096.0).contains(&q)), "{p:?} in {k:?}");
                all.push(p);
            }
        }
        for (i, p) in all.iter().enumerate() {
            for o in &all[i + 1..] {
                let d = ((p.x - o.x).powi(2) + (p.z - o.z).powi(2)).sqrt();
                let least = match (p.species, o.species) {
                    (0, 0) => 6.0,
                    (1, 1) => 4.0,
                    _ => 3.0,
                };
                assert!(d >= least, "{p:?} and {o:?} are {d} m apart near {c:?}");
            }
        }
    }
    assert!(w.expand_cell(key(far, 0)).is_empty(), "out of bounds");
}
