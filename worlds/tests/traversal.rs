//! Traversal semantics: what each node kind does to the state and the primitive stream, and the budgets.

use canopy_protocol::SpeciesGraph;
use canopy_worlds::amplify::{AmplifyError, Budget, Instance, amplify};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::primitive::{PrimitiveStream, Shape};
use canopy_worlds::species_text::parse_species;

fn species(text: &str) -> SpeciesGraph {
    let (g, d) = parse_species(&SourceFile::new("test.species", text));
    assert!(d.is_empty(), "{}", d.iter().map(|d| d.to_string()).collect::<Vec<_>>().join("\n"));
    g.unwrap()
}

fn run(text: &str) -> PrimitiveStream {
    amplify(&species(text), &Instance::new(1), &Budget::default()).unwrap()
}

fn origin(s: &PrimitiveStream, i: usize) -> [f32; 3] {
    let m = s.primitives[i].transform.m;
    [m[3], m[7], m[11]]
}

#[test]
fn worm_of_seed_001_is_four_spheres_then_a_cone() {
    let g = species(include_str!("../species/worm.species"));
    let s = amplify(&g, &Instance::new(0), &Budget::default()).unwrap();
    let kinds: Vec<&str> = s.primitives.iter().map(|p| p.shape.kind().name()).collect();
    assert_eq!(kinds, ["sphere", "sphere", "sphere", "sphere", "cone"]);
    for i in 0..5 {
        assert_eq!(origin(&s, i), [i as f32, 0.0, 0.0]);
    }
    // Worm(c) for another c, as an instance parameter.
    let c = g.param_slot("c").unwrap();
    let s = amplify(&g, &Instance { seed: 0, params: vec![(c, 9.0)], detail: 0 }, &Budget::default()).unwrap();
    assert_eq!(s.primitives.len(), 10);
}

#[test]
fn separator_restores_transform_material_and_parameters() {
    let s =
        run("param r = 1\nseparator { translate(5, 0, 0) material(1, 0, 0) calc { r = 2 } sphere(r) }\nsphere(r)\n");
    assert_eq!(origin(&s, 1), [0.0, 0.0, 0.0]);
    assert_eq!(s.primitives[1].color, [0.8, 0.8, 0.8]);
    assert_eq!(s.primitives[1].shape, Shape::Sphere { radius: 1.0 });
    assert_eq!(s.primitives[0].shape, Shape::Sphere { radius: 2.0 });
}

#[test]
fn group_lets_state_flow_to_later_siblings() {
    let s = run("param r = 1\ngroup { translate(5, 0, 0) calc { r = 2 } }\nsphere(r)\n");
    assert_eq!(origin(&s, 0), [5.0, 0.0, 0.0]);
    assert_eq!(s.primitives[0].shape, Shape::Sphere { radius: 2.0 });
}

#[test]
fn recursion_separator_restores_locals_but_not_transform_or_turtle_state() {
    let s = run("param r = 1\nstate w = 1\nrecurse { translate(0, 3, 0) calc { r = 2, w = 5 } }\ncone(r, w, 1)\n");
    assert_eq!(origin(&s, 0), [0.0, 3.0, 0.0]);
    assert_eq!(s.primitives[0].shape, Shape::Cone { bottom: 1.0, top: 5.0, height: 1.0 });
}

#[test]
fn calculation_assigns_simultaneously() {
    let s = run("param a = 1\nparam b = 2\ncalc { a = b, b = a }\ncylinder(a, b)\n");
    assert_eq!(s.primitives[0].shape, Shape::Cylinder { radius: 2.0, height: 1.0 });
}

#[test]
fn selection_truncates_and_clamps_and_lod_follows_detail() {
    let s = run(
        "select(1.9) { sphere(0) sphere(1) sphere(2) }\nselect(-4) { sphere(10) sphere(11) }\nselect(99) { sphere(20) sphere(21) }\n",
    );
    let radii: Vec<Shape> = s.primitives.iter().map(|p| p.shape.clone()).collect();
    assert_eq!(radii, [1.0, 10.0, 21.0].map(|radius| Shape::Sphere { radius }));
    let g = species("lod { sphere(0) sphere(1) }\nsphere(detail)\n");
    for detail in [0u8, 1, 5] {
        let s = amplify(&g, &Instance::new(0).with_detail(detail), &Budget::default()).unwrap();
        assert_eq!(s.primitives[0].shape, Shape::Sphere { radius: f32::from(detail.min(1)) });
        assert_eq!(s.primitives[1].shape, Shape::Sphere { radius: f32::from(detail) });
    }
}

#[test]
fn transforms_accumulate_by_post_multiplication() {
    let s = run("translate(1, 0, 0)\nrotz(90)\ntranslate(1, 0, 0)\nsphere(1)\n");
    let o = origin(&s, 0);
    assert!((o[0] - 1.0).abs() < 1e-6 && (o[1] - 1.0).abs() < 1e-6, "{o:?}");
}

#[test]
fn random_parameters_vary_by_seed_and_are_reproducible() {
    let g = species("param h = uniform(8, 12)\ncylinder(1, h)\n");
    let h = |seed| match amplify(&g, &Instance::new(seed), &Budget::default()).unwrap().primitives[0].shape {
        Shape::Cylinder { height, .. } => height,
        _ => unreachable!(),
    };
    assert_eq!(h(7), h(7));
    let all: Vec<f32> = (0..50).map(h).collect();
    assert!(all.iter().all(|&v| (8.0..12.0).contains(&v)));
    assert!(all.windows(2).any(|w| w[0] != w[1]));
}

#[test]
fn overriding_a_parameter_does_not_reshuffle_the_others() {
    let g = species("param a = rand()\nparam b = rand()\nsphere(a)\nsphere(b)\n");
    let slot = g.param_slot("a").unwrap();
    let base = amplify(&g, &Instance::new(3), &Budget::default()).unwrap();
    let over = amplify(&g, &Instance { seed: 3, params: vec![(slot, 0.5)], detail: 0 }, &Budget::default()).unwrap();
    assert_eq!(over.primitives[0].shape, Shape::Sphere { radius: 0.5 });
    assert_eq!(over.primitives[1].shape, base.primitives[1].shape);
}

#[test]
fn hostile_graphs_end_in_typed_errors_within_budget() {
    let budget = Budget { max_primitives: 10_000, max_depth: 64, max_steps: 1_000_000, max_pending: 10_000 };
    let cases = [
        // Infinite recursion through separators: depth.
        ("def A separator { sphere(1) use A }", AmplifyError::Depth(64)),
        // Infinite loop through groups, no state growth: steps.
        ("def A group { use A }", AmplifyError::Steps(1_000_000)),
        // Exponential fan-out without separators: pending tasks.
        ("def A group { use A use A }", AmplifyError::Pending(10_000)),
        // Exponential recursion with a terminating counter, but 2^40 leaves: primitives.
        (
            "param n = 40\ndef A select(n > 0) { sphere(1) recurse { calc { n = n - 1 } use A use A } }",
            AmplifyError::Primitives(10_000),
        ),
        // Exponential recursion without primitives: steps.
        (
            "param n = 40\ndef A select(n > 0) { group {} recurse { calc { n = n - 1 } use A use A } }",
            AmplifyError::Steps(1_000_000),
        ),
    ];
    for (text, want) in cases {
        let g = species(text);
        assert_eq!(amplify(&g, &Instance::new(0), &budget), Err(want), "{text}");
    }
}

#[test]
fn parameter_defaults_see_earlier_overrides() {
    let g = species("param height = 10\nparam s = height / 4\ncylinder(1, s)\n");
    let slot = g.param_slot("height").unwrap();
    let s = amplify(&g, &Instance { seed: 0, params: vec![(slot, 20.0)], detail: 0 }, &Budget::default()).unwrap();
    assert_eq!(s.primitives[0].shape, Shape::Cylinder { radius: 1.0, height: 5.0 });
}

#[test]
fn lod_substitutes_do_not_shift_draws_outside_them() {
    // The full child draws three times, the substitute none; the sphere after the LOD node must not care.
    let g = species(
        "param r = 1\nlod { group { calc { r = rand() + rand() + rand() } } group {} }\nsphere(rand())\nsphere(r)\n",
    );
    let at = |detail| amplify(&g, &Instance::new(11).with_detail(detail), &Budget::default()).unwrap();
    let (full, coarse) = (at(0), at(1));
    assert_eq!(full.primitives[0].shape, coarse.primitives[0].shape);
    assert_eq!(full.primitives[1].shape, Shape::Sphere { radius: 1.0 }, "locals set inside a substitute stay inside");
}

#[test]
fn defs_blocks_are_not_traversed_in_place() {
    let s = run("defs { def Twig cylinder(0.1, 1) }\nsphere(1)\nuse Twig\n");
    let kinds: Vec<&str> = s.primitives.iter().map(|p| p.shape.kind().name()).collect();
    assert_eq!(kinds, ["sphere", "cylinder"]);
}
