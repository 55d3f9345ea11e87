//! Near-field geometry (issue 5; seeds 002 and 004): the trunk base's curves, the continuous mesh's topology,
//! junctions, bark and the species vocabulary that asks for them.

use std::collections::BTreeMap;

use canopy_protocol::{Node, SpeciesGraph};
use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::load::parse_source;
use canopy_worlds::mesh::{Mesh, MeshOptions, mesh};
use canopy_worlds::nearfield::bark::{BarkOptions, BarkPlace, ChiselMode, outer_bark};
use canopy_worlds::nearfield::continuous::{ContinuousOptions, continuous_mesh};
use canopy_worlds::nearfield::curves::{GeneratorEllipses, astroid_residual, deltoid_residual, hypocycloid, rose};
use canopy_worlds::nearfield::junction::{JunctionKind, JunctionOptions, classify, junction_mesh};
use canopy_worlds::nearfield::options::species_options;
use canopy_worlds::nearfield::skeleton::Skeleton;
use canopy_worlds::nearfield::trunkbase::TrunkBase;
use canopy_worlds::nearfield::{NearFieldError, NearFieldOptions};
use canopy_worlds::primitive::{Primitive, PrimitiveStream, Shape};
use canopy_worlds::transform::Transform;

const FIG: &str = include_str!("../species/fig.species");

fn fig() -> SpeciesGraph {
    let (g, d) = parse_source(&SourceFile::new("fig.species", FIG));
    assert!(d.is_empty(), "{d:?}");
    g.expect("fig parses")
}

fn stream_of(g: &SpeciesGraph, seed: u64) -> PrimitiveStream {
    amplify(g, &Instance::new(seed), &Budget::default()).expect("amplifies")
}

/// Topology of a triangle mesh: every undirected edge in exactly two triangles, every directed edge once (so
/// the winding is consistent), every vertex's triangles forming one fan (vertex-manifold); returns the number of
/// connected components and the Euler characteristic of the used vertices.
fn closed_manifold(m: &Mesh) -> (usize, i64) {
    let mut directed: BTreeMap<(u32, u32), usize> = BTreeMap::new();
    for t in m.indices.chunks_exact(3) {
        assert!(t[0] != t[1] && t[1] != t[2] && t[0] != t[2], "triangle {t:?} repeats a vertex");
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            *directed.entry((a, b)).or_default() += 1;
        }
    }
    for (&(a, b), &c) in &directed {
        assert_eq!(c, 1, "directed edge {a}→{b} used {c} times: winding inconsistent or edge non-manifold");
        assert_eq!(directed.get(&(b, a)), Some(&1), "edge {a}→{b} has no opposite: the surface is open there");
    }
    // Vertex-manifold: the link of each vertex (the opposite edges of its triangles) is one cycle.
    let mut link: BTreeMap<u32, BTreeMap<u32, u32>> = BTreeMap::new();
    for t in m.indices.chunks_exact(3) {
        for k in 0..3 {
            let (v, a, b) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
            assert!(link.entry(v).or_default().insert(a, b).is_none(), "vertex {v} is not manifold");
        }
    }
    for (v, next) in &link {
        let start = *next.keys().next().unwrap();
        let (mut at, mut steps) = (start, 0);
        loop {
            at = next[&at];
            steps += 1;
            if at == start {
                break;
            }
            assert!(steps <= next.len(), "vertex {v}: broken fan");
        }
        assert_eq!(steps, next.len(), "vertex {v}: its triangles form more than one fan");
    }
    // Components (union-find over vertices) and the Euler characteristic.
    let mut parent: BTreeMap<u32, u32> = link.keys().map(|&v| (v, v)).collect();
    fn find(p: &mut BTreeMap<u32, u32>, mut v: u32) -> u32 {
        while p[&v] != v {
            let up = p[&p[&v]];
            p.insert(v, up);
            v = up;
        }
        v
    }
    for t in m.indices.chunks_exact(3) {
        for k in 0..2 {
            let (a, b) = (find(&mut parent, t[k]), find(&mut parent, t[k + 1]));
            if a != b {
                parent.insert(a.max(b), a.min(b));
            }
        }
    }
    let verts: Vec<u32> = link.keys().copied().collect();
    let mut roots: Vec<u32> = verts.iter().map(|&v| find(&mut parent, v)).collect();
    roots.sort_unstable();
    roots.dedup();
    let (v, e, f) = (link.len() as i64, directed.len() as i64 / 2, m.triangle_count() as i64);
    (roots.len(), v - e + f)
}

/// Six times the signed volume enclosed (positive when the triangles face outward).
fn signed_volume(m: &Mesh) -> f64 {
    m.indices
        .chunks_exact(3)
        .map(|t| {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| m.positions[i as usize].map(f64::from));
            a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) + a[2] * (b[0] * c[1] - b[1] * c[0])
        })
        .sum()
}

#[test]
fn astroid_is_the_envelope_of_generator_ellipses_with_constant_sum() {
    // The astroid of cusp radius 1: every point of the envelope lies on it, the closer the more ellipses.
    let mut worst = Vec::new();
    for count in [16, 64, 256] {
        let family = GeneratorEllipses::new(count, 1.0, 1.0);
        let mut w = 0.0f64;
        for i in 0..720 {
            let theta = std::f64::consts::TAU * f64::from(i) / 720.0;
            let r = family.envelope_radius(theta);
            w = w.max(astroid_residual(r * theta.cos(), r * theta.sin()).abs());
        }
        worst.push(w);
    }
    assert!(worst[2] < 2e-3, "envelope of 256 ellipses is off the astroid by {}", worst[2]);
    assert!(worst[0] > worst[1] && worst[1] > worst[2], "more ellipses, closer envelope: {worst:?}");
    // The generator ellipses really have a constant sum of semi-axes and each touches the astroid.
    let family = GeneratorEllipses::new(9, 2.0, 2.0);
    for &(a, b) in &family.axes {
        assert!((a + b - 2.0).abs() < 1e-12);
        let phi = (a / 2.0).sqrt().acos();
        let p = [2.0 * phi.cos().powi(3), 2.0 * phi.sin().powi(3)];
        assert!((p[0] * p[0] / (a * a) + p[1] * p[1] / (b * b) - 1.0).abs() < 1e-9 || b == 0.0 || a == 0.0);
    }
}

#[test]
fn trunk_base_ground_section_is_an_astroid_and_top_is_a_circle() {
    let tb =
        TrunkBase { spread: 2.0, bottom: 0.5, top: 0.35, ellipses: 256.0, resolution: 200.0, ..TrunkBase::default() };
    let sections = tb.sections().unwrap();
    let c = 2.0 * 0.5; // cusp radius: spread · bottom
    for p in &sections[0].points {
        let res = astroid_residual(p[0] / c, p[2] / c);
        assert!(res.abs() < 3e-3, "ground point {p:?} is {res} off the astroid x^(2/3) + y^(2/3) = 1");
    }
    let top = sections.last().unwrap();
    for p in &top.points {
        let r = ((p[0] - top.centre[0]).powi(2) + (p[2] - top.centre[2]).powi(2)).sqrt();
        assert!((r - 0.35).abs() < 1e-6 && (p[1] - 1.5).abs() < 1e-6, "{p:?}");
    }
    // In between the flares retract: the reach along a cusp shrinks monotonically going up.
    let reach: Vec<f64> = sections.iter().map(|s| s.points[0][0] - s.centre[0]).collect();
    assert!(reach.windows(2).all(|w| w[1] <= w[0] + 1e-12), "{reach:?}");
    assert!((reach[0] - 1.0).abs() < 1e-6);
}

#[test]
fn deltoid_and_quadrifolium_are_the_papers_curves() {
    for i in 0..200 {
        let t = std::f64::consts::TAU * f64::from(i) / 200.0;
        let p = hypocycloid(3, t);
        assert!(deltoid_residual(p[0], p[1]).abs() < 1e-12, "deltoid point {p:?}");
        // The quadrifolium r = cos 2θ rotated by 2π/8: (x² + y²)³ = 4x²y².
        let (r, a) = (rose(2.0, t), t + std::f64::consts::PI / 4.0);
        let (x, y) = (r * a.cos(), r * a.sin());
        assert!(((x * x + y * y).powi(3) - 4.0 * x * x * y * y).abs() < 1e-12);
    }
    // The folium transition's ground section: wherever a root flare stands out of the trunk it is the deltoid.
    let tb =
        TrunkBase { spread: 2.5, lobes: 3.0, transition: 1.0, resolution: 240.0, bottom: 0.4, ..TrunkBase::default() };
    let ground = &tb.sections().unwrap()[0];
    let cusp = 2.5 * f64::from(0.4f32);
    let mut on_curve = 0;
    for p in &ground.points {
        let r = (p[0] * p[0] + p[2] * p[2]).sqrt();
        if r > f64::from(0.4f32) + 1e-6 {
            // Points are (r cos θ, −r sin θ): the deltoid's y is −z.
            assert!(deltoid_residual(p[0] / cusp, -p[2] / cusp).abs() < 1e-7, "{p:?}");
            on_curve += 1;
        }
    }
    assert!(on_curve > 60, "{on_curve} points on the deltoid's flares");
}

#[test]
fn trunk_base_surface_is_closed_and_faces_out() {
    for tb in [
        TrunkBase::default(),
        TrunkBase { randomiser: 0.8, seed: 0.25, tilt: 12.0, lobes: 5.0, ..TrunkBase::default() },
        TrunkBase { transition: 1.0, lobes: 3.0, spread: 2.6, ..TrunkBase::default() },
    ] {
        let s = tb.surface().unwrap();
        assert_eq!(s.triangle_count(), tb.triangle_count());
        let m = s.to_mesh([0.5; 3]);
        assert!(signed_volume(&m) > 0.0, "{tb:?} faces inward");
        // Sides share vertices with neither cap, so check the sides plus caps as one shell by welding positions.
        let welded = weld(&m);
        let (components, euler) = closed_manifold(&welded);
        assert_eq!((components, euler), (1, 2), "{tb:?}");
        // Normals are unit length.
        assert!(s.normals.iter().all(|n| ((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt() - 1.0).abs() < 1e-5));
    }
    // A different seed gives different roots; the same seed the same ones.
    let a = TrunkBase { randomiser: 0.5, seed: 0.1, ..TrunkBase::default() }.surface().unwrap();
    let b = TrunkBase { randomiser: 0.5, seed: 0.7, ..TrunkBase::default() }.surface().unwrap();
    let c = TrunkBase { randomiser: 0.5, seed: 0.1, ..TrunkBase::default() }.surface().unwrap();
    assert_ne!(a, b);
    assert_eq!(a, c);
}

#[test]
fn bad_trunk_bases_are_typed_errors() {
    let bad = [
        TrunkBase { height: 0.0, ..TrunkBase::default() },
        TrunkBase { bottom: f32::NAN, ..TrunkBase::default() },
        TrunkBase { spread: 0.5, ..TrunkBase::default() },
        TrunkBase { tilt: 75.0, ..TrunkBase::default() },
        TrunkBase { randomiser: 2.0, ..TrunkBase::default() },
    ];
    for tb in bad {
        assert!(matches!(tb.surface(), Err(NearFieldError::TrunkBase { .. })), "{tb:?}");
        // The ordinary mesher skips it.
        let s = PrimitiveStream {
            primitives: vec![Primitive {
                shape: Shape::TrunkBase(tb),
                transform: Transform::IDENTITY,
                color: [0.5; 3],
            }],
            leaf_points: vec![],
        };
        assert!(mesh(&s, &MeshOptions::default()).is_empty());
    }
}

/// Merge vertices at bit-identical positions (the trunk base's caps have their own rim vertices).
fn weld(m: &Mesh) -> Mesh {
    let mut first: BTreeMap<[u32; 3], u32> = BTreeMap::new();
    let map: Vec<u32> =
        m.positions.iter().enumerate().map(|(i, p)| *first.entry(p.map(f32::to_bits)).or_insert(i as u32)).collect();
    Mesh { indices: m.indices.iter().map(|&i| map[i as usize]).collect(), ..m.clone() }
}

#[test]
fn the_species_near_mesh_is_branches_bark_and_foliage() {
    let g = fig();
    let s = stream_of(&g, 3);
    let opts = species_options(&g, &Instance::new(3)).unwrap().unwrap();
    let all = canopy_worlds::nearfield::species_near_mesh(&s, &opts).unwrap();
    let cm = continuous_mesh(&s, &ContinuousOptions { subdivide: true, ..opts.mesh }).unwrap();
    let bark =
        outer_bark(&cm.mesh, &canopy_worlds::nearfield::bark::trunk_places(&cm.tags), &opts.bark.unwrap()).unwrap();
    assert!(bark.triangle_count() > 0 && cm.foliage.triangle_count() > 0);
    assert_eq!(all.triangle_count(), cm.mesh.triangle_count() + bark.triangle_count() + cm.foliage.triangle_count());
    // Without a bark the branches are not subdivided: fewer triangles than the bark-carrying mesh.
    let bare = canopy_worlds::nearfield::species_near_mesh(&s, &NearFieldOptions { bark: None, ..opts }).unwrap();
    assert!(bare.triangle_count() < cm.mesh.triangle_count() + cm.foliage.triangle_count());
    assert_eq!(all, canopy_worlds::nearfield::species_near_mesh(&s, &opts).unwrap(), "deterministic");
}

#[test]
fn species_file_asks_for_trunk_base_bark_and_continuous_mesh() {
    let g = fig();
    assert!(g.nodes.iter().any(|n| matches!(n, Node::TrunkBase(_))));
    // The new nodes survive the wire.
    assert_eq!(SpeciesGraph::decode(&g.encode()).unwrap(), g);
    let opts = species_options(&g, &Instance::new(3)).unwrap().expect("fig asks for near-field options");
    assert!(opts.continuous && opts.mesh.refine);
    assert_eq!(opts.mesh.contour, 12);
    let bark = opts.bark.expect("double bark");
    assert_eq!((bark.depth, bark.chisel), (0.02, ChiselMode::Both));
    let s = stream_of(&g, 3);
    assert!(matches!(s.primitives[0].shape, Shape::TrunkBase(tb) if tb.spread == 2.0 && tb.bottom == 0.32));
    // The per-instance seed is drawn: two instances get different roots.
    let t = stream_of(&g, 4);
    assert_ne!(s.primitives[0].shape, t.primitives[0].shape);
    // Named arguments: unknown or repeated names are errors with positions.
    let (_, d) = parse_source(&SourceFile::new("t.species", "trunkbase(spread = 2, hieght = 1)\n"));
    assert!(d[0].message.contains("`trunkbase` has no argument `hieght`"), "{d:?}");
    let (_, d) = parse_source(&SourceFile::new("t.species", "nearfield(bark = 1, bark = 2)\n"));
    assert!(d[0].message.contains("given twice"), "{d:?}");
    let (g2, d) = parse_source(&SourceFile::new("t.species", "trunkbase(1.5, 2, 0.3, 0.2, lobes = 3)\n"));
    assert!(d.is_empty(), "{d:?}");
    assert!(matches!(&g2.unwrap().nodes[0], Node::TrunkBase(b) if b.lobes.as_constant() == Some(3.0)));
}

#[test]
fn continuous_mesh_is_one_closed_manifold_surface() {
    let g = fig();
    for seed in [1, 2, 3] {
        let s = stream_of(&g, seed);
        for refine in [false, true] {
            for contour in [5, 9, 12, 15] {
                let cm = continuous_mesh(&s, &ContinuousOptions { contour, refine, ..ContinuousOptions::default() })
                    .unwrap();
                let (components, euler) = closed_manifold(&cm.mesh);
                assert_eq!(components, 1, "seed {seed} refine {refine} contour {contour}");
                assert_eq!(euler, 2, "a closed surface of genus 0: seed {seed} refine {refine} contour {contour}");
                assert!(signed_volume(&cm.mesh) > 0.0, "faces outward");
                assert_eq!(cm.tags.len(), cm.mesh.triangle_count());
                assert!(!cm.foliage.is_empty(), "the tips' foliage is meshed apart");
            }
        }
    }
}

#[test]
fn refining_by_intervals_adds_contours_at_junctions() {
    let s = stream_of(&fig(), 1);
    let mut counts = Vec::new();
    for contour in [5, 9, 12, 15] {
        let direct = continuous_mesh(&s, &ContinuousOptions { contour, refine: false, ..ContinuousOptions::default() })
            .unwrap()
            .mesh
            .triangle_count();
        let refined = continuous_mesh(&s, &ContinuousOptions { contour, refine: true, ..ContinuousOptions::default() })
            .unwrap()
            .mesh
            .triangle_count();
        assert!(refined > direct, "contour {contour}: refined {refined} vs direct {direct}");
        counts.push((direct, refined));
    }
    assert!(counts.windows(2).all(|w| w[1].0 > w[0].0 && w[1].1 > w[0].1), "{counts:?}");
    // Deterministic.
    let a = continuous_mesh(&s, &ContinuousOptions::default()).unwrap();
    let b = continuous_mesh(&s, &ContinuousOptions::default()).unwrap();
    assert_eq!(a.mesh.hash(), b.mesh.hash());
}

#[test]
fn continuous_mesh_of_library_species_is_manifold() {
    for name in ["monopodial", "morpho", "bush"] {
        let g = canopy_worlds::library::find(name).unwrap().load().unwrap();
        let s =
            amplify(&g, &Instance::new(7).with_detail(if name == "monopodial" { 2 } else { 0 }), &Budget::default())
                .unwrap();
        let sk = Skeleton::from_stream(&s);
        for refine in [false, true] {
            let cm =
                continuous_mesh(&s, &ContinuousOptions { contour: 6, refine, ..ContinuousOptions::default() }).unwrap();
            let (components, _) = closed_manifold(&cm.mesh);
            assert_eq!(components, sk.roots.len(), "{name}: one surface per root of the skeleton");
        }
    }
}

#[test]
fn options_are_checked() {
    let s = stream_of(&fig(), 1);
    for o in [
        ContinuousOptions { contour: 2, ..ContinuousOptions::default() },
        ContinuousOptions { interval: 0.0, ..ContinuousOptions::default() },
    ] {
        assert!(matches!(continuous_mesh(&s, &o), Err(NearFieldError::Option { .. })));
    }
    let small = ContinuousOptions { max_triangles: 100, ..ContinuousOptions::default() };
    assert_eq!(continuous_mesh(&s, &small).unwrap_err(), NearFieldError::TooLarge(100));
}

/// A parent cylinder with a continuation, a lateral in its middle and a fork of two at the top of the lateral.
fn junction_stream() -> PrimitiveStream {
    let mut s = PrimitiveStream::default();
    let mut push = |shape, transform| s.primitives.push(Primitive { shape, transform, color: [0.4, 0.3, 0.2] });
    let trunk = Transform::IDENTITY;
    push(Shape::Cylinder { radius: 0.3, height: 3.0 }, trunk);
    let up = trunk.translated(0.0, 3.0, 0.0).mul(&Transform::rotation([1.0, 0.0, 0.0], 10.0));
    push(Shape::Cone { bottom: 0.3, top: 0.2, height: 2.0 }, up);
    let side = trunk.translated(0.0, 1.5, 0.0).mul(&Transform::rotation([0.0, 0.0, 1.0], 60.0));
    push(Shape::Cone { bottom: 0.15, top: 0.12, height: 1.5 }, side);
    let fork = side.translated(0.0, 1.5, 0.0);
    push(Shape::Cone { bottom: 0.12, top: 0.05, height: 1.0 }, fork.mul(&Transform::rotation([1.0, 0.0, 0.0], 30.0)));
    push(Shape::Cone { bottom: 0.12, top: 0.05, height: 1.0 }, fork.mul(&Transform::rotation([1.0, 0.0, 0.0], -30.0)));
    s
}

#[test]
fn junctions_are_classified_t_y_and_i_and_embedded() {
    let s = junction_stream();
    let sk = Skeleton::from_stream(&s);
    let kinds: Vec<JunctionKind> = classify(&sk).into_iter().map(|(k, _)| k).collect();
    assert_eq!(kinds, [JunctionKind::Root, JunctionKind::I, JunctionKind::T, JunctionKind::Y, JunctionKind::Y]);
    let m = junction_mesh(&s, &JunctionOptions::default());
    assert!(m.triangle_count() > 0);
    // The lateral's base is embedded: its lowest ring's points are inside the trunk's cylinder (radius 0.3).
    let n = JunctionOptions::default().radial as usize;
    // The trunk (two rings and its base cap's centre) and its continuation (two rings and its top cap's centre)
    // come first.
    let before = 2 * (2 * n + 1);
    let lateral_base = &m.positions[before..before + n];
    let inside = lateral_base.iter().filter(|p| (p[0] * p[0] + p[2] * p[2]).sqrt() < 0.3).count();
    assert_eq!(inside, n, "every base point of the T lateral is embedded in the parent: {lateral_base:?}");
    // Its base follows the parent: the base points are at different heights along the lateral (sinusoidal).
    let along: Vec<f32> =
        lateral_base.iter().map(|p| p[1] * 60f32.to_radians().cos() - p[0] * 60f32.to_radians().sin()).collect();
    let spread = along.iter().cloned().fold(f32::MIN, f32::max) - along.iter().cloned().fold(f32::MAX, f32::min);
    assert!(spread > 0.05, "sinusoidal base spread {spread}");
    // The continuous mesh of the same stream is closed.
    for refine in [false, true] {
        let cm = continuous_mesh(&s, &ContinuousOptions { refine, ..ContinuousOptions::default() }).unwrap();
        assert_eq!(closed_manifold(&cm.mesh), (1, 2));
    }
}

#[test]
fn double_bark_is_offset_shrunk_and_chiselled() {
    let tb = TrunkBase { resolution: 32.0, ..TrunkBase::default() };
    let s = PrimitiveStream {
        primitives: vec![Primitive { shape: Shape::TrunkBase(tb), transform: Transform::IDENTITY, color: [0.5; 3] }],
        leaf_points: vec![],
    };
    let cm = continuous_mesh(&s, &ContinuousOptions::default()).unwrap();
    let place: Vec<Option<BarkPlace>> = cm
        .tags
        .iter()
        .map(|t| Some(BarkPlace { piece: t.piece, column: t.column, ring: t.ring, up: t.axis }))
        .collect();
    let opts = |chisel, shrink, removal| BarkOptions { depth: 0.03, chisel, shrink, removal, seed: 9 };
    let plain = outer_bark(&cm.mesh, &place, &opts(ChiselMode::Shrink, 0.0, 0.5)).unwrap();
    assert_eq!(plain.triangle_count(), cm.mesh.triangle_count(), "shrink mode removes nothing");
    // Without shrinking, each plate's corners stand exactly the bark depth off the inner vertices.
    for (k, t) in cm.mesh.indices.iter().enumerate() {
        let (p, q) = (cm.mesh.positions[*t as usize], plain.positions[k]);
        let d = ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) + (q[2] - p[2]).powi(2)).sqrt();
        assert!((d - 0.03).abs() < 1e-5, "{d}");
    }
    let removed = outer_bark(&cm.mesh, &place, &opts(ChiselMode::Remove, 0.0, 0.3)).unwrap();
    let kept = removed.triangle_count() as f64 / cm.mesh.triangle_count() as f64;
    assert!(kept > 0.5 && kept < 0.9, "about 70% kept, got {kept}");
    let shrunk = outer_bark(&cm.mesh, &place, &opts(ChiselMode::Both, 0.5, 0.3)).unwrap();
    let area = |m: &Mesh| -> f64 {
        m.indices
            .chunks_exact(3)
            .map(|t| {
                let [a, b, c] = [t[0], t[1], t[2]].map(|i| m.positions[i as usize].map(f64::from));
                let (u, v) = ([b[0] - a[0], b[1] - a[1], b[2] - a[2]], [c[0] - a[0], c[1] - a[1], c[2] - a[2]]);
                let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
                0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
            })
            .sum()
    };
    assert!(area(&shrunk) < 0.9 * area(&removed), "shrunk plates cover less");
    // Same seed, same bark; a bad depth is an error.
    assert_eq!(shrunk, outer_bark(&cm.mesh, &place, &opts(ChiselMode::Both, 0.5, 0.3)).unwrap());
    let bad = BarkOptions { depth: -1.0, ..opts(ChiselMode::Both, 0.5, 0.3) };
    assert!(outer_bark(&cm.mesh, &place, &bad).is_err());
}
