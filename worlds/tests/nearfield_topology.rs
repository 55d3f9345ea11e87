//! The continuous mesh as a welding tool (trimesh, a glTF viewer) sees it: vertices at bit-identical positions
//! welded ([`Weld::Exact`]), then one body, no open, non-manifold or misoriented edges and no degenerate
//! triangles — for every species of the library and the fig, five seeds each, direct and refined junctions, with and without
//! the bark's subdivision. The LOD levels are checked in `nearfield_lod.rs` (they need meshoptimizer).
//!
//! Two stated exceptions, each with its reason checked here too:
//! - `terrain` draws no cones, cylinders or trunk bases: there is no continuous mesh (empty, zero roots).
//! - `conifer` at detail 0 draws its twigs as needle tufts along an axis nothing draws, so each tuft is a branch
//!   system of its own: the mesh is one closed, manifold body per root of the skeleton, and
//!   [`ContinuousMesh::why_not_one_body`] says so (`canopy species export` prints it). At details 1–3 the twigs
//!   are cones on the branches, and the conifer is one body like the others.

use canopy_protocol::SpeciesGraph;
use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::library::SPECIES;
use canopy_worlds::load::parse_source;
use canopy_worlds::nearfield::continuous::{ContinuousMesh, ContinuousOptions, continuous_mesh};
use canopy_worlds::nearfield::skeleton::Skeleton;
use canopy_worlds::nearfield::topology::{Topology, Weld, check_mesh};

const SEEDS: [u64; 5] = [1, 2, 3, 4, 5];

/// The detail level each species is checked at: the full tree, except where detail 0 is far too large for a
/// debug-build test (monopodial: about a million triangles) or is the stated exception (conifer, see above).
fn detail_of(name: &str) -> u8 {
    match name {
        "monopodial" => 2,
        "conifer" => 1,
        _ => 0,
    }
}

/// Species that draw no branches at all.
const NO_BRANCHES: [&str; 1] = ["terrain"];

/// The library's species and the fig (`worlds/species/fig.species`, the near-field example, not embedded).
fn species_names() -> Vec<&'static str> {
    SPECIES.iter().map(|e| e.name()).chain(["fig"]).collect()
}

fn graph(name: &str) -> SpeciesGraph {
    if name == "fig" {
        let (g, d) = parse_source(&SourceFile::new("fig.species", include_str!("../species/fig.species")));
        assert!(d.is_empty(), "{d:?}");
        return g.unwrap();
    }
    canopy_worlds::library::find(name).unwrap().load().unwrap()
}

fn mesh_of(name: &str, seed: u64, detail: u8, opts: &ContinuousOptions) -> ContinuousMesh {
    let g = graph(name);
    let s = amplify(&g, &Instance::new(seed).with_detail(detail), &Budget::default()).unwrap();
    continuous_mesh(&s, opts).unwrap()
}

fn closed_and_manifold(t: &Topology) -> bool {
    t.is_watertight() && t.misoriented_edges == 0 && t.degenerate == 0
}

#[test]
fn every_library_species_is_one_closed_manifold_body() {
    let mut checked = 0;
    for name in species_names() {
        let detail = detail_of(name);
        for seed in SEEDS {
            for refine in [false, true] {
                // The bark's subdivision on every other seed; contour resolutions 5 and 9 alternate likewise.
                let (subdivide, contour) = if seed % 2 == 0 { (true, 5) } else { (false, 9) };
                let opts = ContinuousOptions { contour, refine, subdivide, ..ContinuousOptions::default() };
                let cm = mesh_of(name, seed, detail, &opts);
                let what = format!("{name} seed {seed} detail {detail} refine {refine} contour {contour}");
                if NO_BRANCHES.contains(&name) {
                    assert!(cm.mesh.is_empty() && cm.roots == 0, "{what}: expected no branches");
                    assert!(cm.why_not_one_body().is_some_and(|w| w.contains("no cones")), "{what}");
                    continue;
                }
                let t = check_mesh(&cm.mesh, Weld::Exact);
                assert!(t.is_one_closed_body(), "{what}: {t}");
                assert_eq!(t.euler, 2, "{what}: a sphere's topology: {t}");
                assert_eq!((cm.roots, cm.why_not_one_body()), (1, None), "{what}");
                checked += 1;
            }
        }
    }
    assert!(checked >= 70, "{checked} meshes checked");
}

#[test]
fn conifer_needle_tufts_are_closed_bodies_apart() {
    for seed in [1, 2] {
        for refine in [false, true] {
            let opts = ContinuousOptions { contour: 4, refine, ..ContinuousOptions::default() };
            let cm = mesh_of("conifer", seed, 0, &opts);
            let t = check_mesh(&cm.mesh, Weld::Exact);
            let what = format!("conifer seed {seed} detail 0 refine {refine}: {t}");
            assert!(closed_and_manifold(&t), "{what}");
            // One body per branch system, and the skeleton agrees that they touch nothing: no piece of one starts
            // on another.
            assert!(t.bodies > 1000, "{what}");
            assert_eq!(t.bodies, cm.roots, "{what}");
            let g = canopy_worlds::library::find("conifer").unwrap().load().unwrap();
            let sk = Skeleton::from_stream(&amplify(&g, &Instance::new(seed), &Budget::default()).unwrap());
            assert_eq!(sk.roots.len(), cm.roots);
            assert_eq!(t.euler, 2 * t.bodies as i64, "every body a sphere: {what}");
            let why = cm.why_not_one_body().expect("a reason");
            assert!(why.contains(&format!("{} branch systems", cm.roots)), "{why}");
        }
    }
}
