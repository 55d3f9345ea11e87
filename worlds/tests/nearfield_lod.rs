//! The near-field LOD chain (seed 004 §4–5; needs the `meshopt` feature, which `cargo test --workspace` turns
//! on through the `canopy` client; `required-features` in `worlds/Cargo.toml`, so without it this target is not
//! built rather than built empty): decimation keeps its error bound, thin branches go first, the trunk last, and
//! every level of every library species (and the fig) is one closed manifold body after welding.

use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::load::parse_source;
use canopy_worlds::nearfield::NearFieldError;
use canopy_worlds::nearfield::continuous::{ContinuousOptions, continuous_mesh};
use canopy_worlds::nearfield::lod::{LodOptions, Measure, hausdorff, lod_chain, measure, point_triangle};
use canopy_worlds::nearfield::topology::{Weld, check_mesh};

fn fig_mesh(contour: u32) -> canopy_worlds::nearfield::continuous::ContinuousMesh {
    let (g, d) = parse_source(&SourceFile::new("fig.species", include_str!("../species/fig.species")));
    assert!(d.is_empty(), "{d:?}");
    let s = amplify(&g.unwrap(), &Instance::new(1), &Budget::default()).unwrap();
    continuous_mesh(&s, &ContinuousOptions { contour, ..ContinuousOptions::default() }).unwrap()
}

#[test]
fn decimation_keeps_its_error_bound_thin_branches_first() {
    let cm = fig_mesh(12);
    let full = cm.mesh.triangle_count();
    let chain = lod_chain(&cm, &LodOptions { levels: 4, error: 0.03 }).unwrap();
    assert_eq!(chain.len(), 4);
    let originals: Vec<[f64; 3]> = cm.mesh.positions.iter().map(|p| p.map(f64::from)).collect();
    let mut previous = full;
    for (k, level) in chain.iter().enumerate() {
        let t = level.mesh.triangle_count();
        assert!(t <= previous, "level {k}: {t} triangles after {previous}");
        previous = t;
        // The bound holds, measured independently against the full mesh's vertices.
        assert!(level.error <= level.bound, "level {k}: error {} > bound {}", level.error, level.bound);
        let measured = hausdorff(&originals, &level.mesh.positions, &level.mesh.indices, f64::from(level.bound));
        assert!(measured <= f64::from(level.bound), "level {k}: measured {measured}");
        // Locked (thicker) contours are untouched: every full-mesh vertex thicker than the level's radius is still
        // a vertex of the level.
        let kept: std::collections::BTreeSet<[u32; 3]> =
            level.mesh.positions.iter().map(|p| p.map(f32::to_bits)).collect();
        for (p, &r) in cm.mesh.positions.iter().zip(&cm.radius) {
            if r > level.max_radius {
                assert!(kept.contains(&p.map(f32::to_bits)), "level {k}: a trunk vertex of radius {r} was removed");
            }
        }
    }
    assert!(chain[0].max_radius < chain[2].max_radius && chain[3].max_radius.is_infinite());
    assert!(previous * 2 < full, "the last level halves the mesh at least: {previous} of {full}");
    // Deterministic on one platform.
    assert_eq!(chain, lod_chain(&cm, &LodOptions { levels: 4, error: 0.03 }).unwrap());
}

#[test]
fn the_measure_is_what_measuring_every_point_against_every_triangle_gives() {
    let cm = fig_mesh(6);
    let chain = lod_chain(&cm, &LodOptions { levels: 3, error: 0.03 }).unwrap();
    // The full mesh's vertices, and points pushed off them (some beyond the bounds, one far away).
    let mut points: Vec<[f64; 3]> = cm.mesh.positions.iter().map(|p| p.map(f64::from)).collect();
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    let mut unit = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    for i in 0..400 {
        let p = points[i * 7 % cm.mesh.positions.len()];
        let size = [0.002, 0.02, 0.2][i % 3];
        points.push([p[0] + unit() * size, p[1] + unit() * size, p[2] + unit() * size]);
    }
    points.push([50.0, 50.0, 50.0]);
    for level in &chain {
        let (pos, idx) = (&level.mesh.positions, &level.mesh.indices);
        let tris: Vec<[[f64; 3]; 3]> =
            idx.chunks_exact(3).map(|t| [0, 1, 2].map(|k| pos[t[k] as usize].map(f64::from))).collect();
        let exact: Vec<f64> =
            points.iter().map(|&p| tris.iter().map(|t| point_triangle(p, t)).fold(f64::INFINITY, f64::min)).collect();
        for bound in [0.005, f64::from(level.bound), 0.5, 1e3] {
            let far: Vec<usize> = (0..points.len()).filter(|&i| exact[i] > bound).collect();
            let error = if far.is_empty() { exact.iter().fold(0.0, |a: f64, &d| a.max(d)) } else { f64::INFINITY };
            let Measure { error: e, far: f } = measure(&points, pos, idx, bound);
            assert_eq!((e.to_bits(), &f), (error.to_bits(), &far), "bound {bound}");
            // Without the far points, the largest distance is measured exactly.
            let near: Vec<[f64; 3]> = (0..points.len()).filter(|i| !far.contains(i)).map(|i| points[i]).collect();
            let largest = (0..points.len()).filter(|i| !far.contains(i)).map(|i| exact[i]).fold(0.0, f64::max);
            assert_eq!(hausdorff(&near, pos, idx, bound).to_bits(), largest.to_bits(), "bound {bound}");
        }
    }
}

#[test]
fn tighter_bounds_keep_more_triangles() {
    let cm = fig_mesh(9);
    let loose = lod_chain(&cm, &LodOptions { levels: 1, error: 0.05 }).unwrap();
    let tight = lod_chain(&cm, &LodOptions { levels: 1, error: 0.002 }).unwrap();
    assert!(tight[0].mesh.triangle_count() > loose[0].mesh.triangle_count());
    assert!(tight[0].error <= 0.002 && loose[0].error <= 0.05);
    assert!(matches!(lod_chain(&cm, &LodOptions { levels: 0, error: 0.01 }), Err(NearFieldError::Option { .. })));
    assert!(matches!(lod_chain(&cm, &LodOptions { levels: 2, error: -1.0 }), Err(NearFieldError::Option { .. })));
    let mut broken = cm.clone();
    broken.mesh.indices[4] = u32::MAX;
    assert_eq!(lod_chain(&broken, &LodOptions::default()), Err(NearFieldError::Malformed("index out of range")));
    let mut broken = cm.clone();
    broken.radius.pop();
    assert!(matches!(lod_chain(&broken, &LodOptions::default()), Err(NearFieldError::Malformed(_))));
}

#[test]
fn point_to_triangle_distance() {
    let t = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    assert!((point_triangle([0.2, 0.2, 0.5], &t) - 0.5).abs() < 1e-12, "above the face");
    assert!((point_triangle([-1.0, 0.0, 0.0], &t) - 1.0).abs() < 1e-12, "beyond a vertex");
    assert!((point_triangle([1.0, 1.0, 0.0], &t) - 0.5f64.sqrt()).abs() < 1e-12, "beyond the hypotenuse");
    assert!((point_triangle([0.5, -2.0, 0.0], &t) - 2.0).abs() < 1e-12, "beyond an edge");
}

#[test]
fn every_level_of_every_library_species_is_one_closed_body() {
    let library = canopy_worlds::library::SPECIES.iter().map(|e| (e.name(), e.load().unwrap()));
    let (fig, d) = parse_source(&SourceFile::new("fig.species", include_str!("../species/fig.species")));
    assert!(d.is_empty(), "{d:?}");
    let check = |name: &str, g: canopy_protocol::SpeciesGraph| -> usize {
        // As in `nearfield_topology.rs`: terrain draws no branches, the conifer is one body from detail 1 (its
        // needle tufts at detail 0 are bodies apart); the large trees at a coarser detail, so the chains (each
        // level measured against the full mesh) stay quick in a debug build.
        let detail = match name {
            "terrain" => return 0,
            "monopodial" => 2,
            "conifer" | "bush" | "stochastic_weed" => 1,
            _ => 0,
        };
        let mut decimated = 0;
        let mut levels_checked = 0;
        for seed in 1..=5u64 {
            let s = amplify(&g, &Instance::new(seed).with_detail(detail), &Budget::default()).unwrap();
            let refine = seed % 2 == 1;
            let cm =
                continuous_mesh(&s, &ContinuousOptions { contour: 6, refine, ..ContinuousOptions::default() }).unwrap();
            let full = check_mesh(&cm.mesh, Weld::Exact);
            assert!(full.is_one_closed_body(), "{name} seed {seed}: {full}");
            let chain = lod_chain(&cm, &LodOptions { levels: 4, error: 0.02 }).unwrap();
            for (k, level) in chain.iter().enumerate() {
                let t = check_mesh(&level.mesh, Weld::Exact);
                assert!(t.is_one_closed_body(), "{name} seed {seed} level {}: {t}", k + 1);
                assert_eq!(t.euler, 2, "{name} seed {seed} level {}: {t}", k + 1);
                levels_checked += 1;
            }
            let last = chain.last().unwrap().mesh.triangle_count();
            decimated += usize::from(last < cm.mesh.triangle_count());
        }
        // The checks do not hold by giving up everywhere: most seeds' chains still decimate. (A level that cannot
        // keep both its error bound and the topology keeps the previous level's triangles: two of the
        // stochastic_weed's five chains at detail 1 keep all of them; the other species decimate on every seed.)
        let least = if name == "stochastic_weed" { 3 } else { 5 };
        assert!(decimated >= least, "{name}: {decimated} of 5 chains decimate");
        levels_checked
    };
    // A species a thread (the checks are independent; a failing one fails the test when joined).
    let levels_checked: usize = std::thread::scope(|s| {
        let threads: Vec<_> =
            library.chain([("fig", fig.unwrap())]).map(|(name, g)| s.spawn(move || check(name, g))).collect();
        threads.into_iter().map(|t| t.join().unwrap()).sum()
    });
    assert!(levels_checked >= 100, "{levels_checked} levels checked");
}
