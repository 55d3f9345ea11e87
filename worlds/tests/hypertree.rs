//! Hypertrees (seed 000): the definition format and its diagnostics, the wire encoding, deterministic generation
//! (its golden hashes are in `worlds/golden`), the generation rules, storage structures agreeing voxel for voxel,
//! union/add/clear/set/reduce semantics, saved volumes, rendering invariants and the species voxelisation.

use canopy_protocol::hypertree::{HypertreeDecodeError, HypertreeDef, HypertreeError, MAX_HYPERTREE_BYTES};
use canopy_protocol::xorshift::XorShift64;
use canopy_worlds::amplify::{Budget, Instance};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::hypertree::file::{VolumeFileError, load as load_volume, save as save_volume};
use canopy_worlds::hypertree::format::{load_forest, parse_forest, parse_hypertree};
use canopy_worlds::hypertree::generate::{GenerateError, GenerateOptions, generate, generate_forest};
use canopy_worlds::hypertree::library::{self, HYPERTREES};
use canopy_worlds::hypertree::ops::{OpError, Unification, clear_region, combine, reduce, set_region};
use canopy_worlds::hypertree::render::{BoundingScheme, RenderError, RenderOptions, Shading, render};
use canopy_worlds::hypertree::storage::{DensityClasses, VoxelList, VoxelQuery, VoxelStore};
use canopy_worlds::hypertree::voxelise::{VoxeliseOptions, voxelise_species};
use canopy_worlds::hypertree::{Bounds, Hypertree, Hypervolume, StorageType, Voxel};

fn def(name: &str) -> HypertreeDef {
    library::find(name).unwrap_or_else(|| panic!("no library hypertree {name}")).load().expect("library parses")
}

fn parse(text: &str) -> (Option<HypertreeDef>, Vec<String>) {
    let (d, diags) = parse_hypertree(&SourceFile::new("t.hyp", text));
    (d, diags.iter().map(|d| d.to_string()).collect())
}

fn small(name: &str, storage: StorageType, res: u32, iterations: u64) -> Hypertree {
    let opts =
        GenerateOptions { storage, resolution: Some([res; 3]), iterations: Some(iterations), ..Default::default() };
    generate(&def(name), 1, &opts, &mut |_, _| {}).expect("generates").0
}

const MINIMAL: &str = "RESOLUTION 32\nITERATIONS 2000\nTREEDEPTH 4\nCONDENSATION\n  CONE Y 0 0.3 0.03 0.02\n\
TRANSFORM 1 255\n  SCALE 0.5\n  TRANSLATE 0 0.3 0\n";

// ---------------------------------------------------------------------------------------------------------------
// Format

#[test]
fn library_definitions_parse_and_follow_figure_7() {
    assert!(HYPERTREES.len() >= 4);
    for e in HYPERTREES {
        let d = e.load().unwrap_or_else(|diags| panic!("{}: {diags}", e.file));
        d.validate().expect("valid");
    }
    // A: fruit-coloured deep levels; ten transformations, two of them dummies.
    let a = def("apple");
    assert_eq!(a.transformations.len(), 10);
    assert_eq!(a.transformations.iter().filter(|t| t.dummy_from.is_some()).count(), 2);
    assert!(a.depth_colors.iter().any(|c| c.levels[1] == a.tree_depth - 1 && c.from[0] > 0.7 && c.from[1] < 0.3));
    // B: few transformations and dummies.
    let b = def("spruce");
    assert_eq!(b.transformations.len(), 4);
    assert_eq!(b.transformations.iter().filter(|t| t.dummy_from.is_some()).count(), 2);
    // C: a line-segment generator of length 0.05.
    let c = def("willow");
    match c.generator {
        canopy_protocol::hypertree::Generator::Line { from, to } => {
            let l = ((0..3).map(|i| (to[i] - from[i]).powi(2)).sum::<f32>()).sqrt();
            assert!((l - 0.05).abs() < 1e-6);
        }
        other => panic!("willow has {other:?}"),
    }
    // D: two condensations (dichotomous branching).
    assert_eq!(def("fork").condensations.len(), 2);
}

#[test]
fn format_reads_every_keyword() {
    let text = "NAME  test tree \nRESOLUTION 64 32 48\nITERATIONS 1234\nTREEDEPTH 7\nBRANCHDEPTH 2\nDENSITYCLASSES 2\n\
DEPTHCOLOR 0 2 0.1 0.2 0.3 0.4 0.5 0.6\nPERTURB 0.01 0.02 0.01 4\nHYPERVOLUME 2 1 2\nDISPLACEMENT 1 0 1\n\
LINEINIT 0 0 0 0 0.1 0\nCONDENSATION 2\n  CONE z -0.1 0.4 0.05 0\n  SHEAR Y 0.1 -0.2 1.5\n\
transform 0.5 3 DUMMY 2   # lower case is fine\n  ROTATE X (10 20 30)\n  SCALE (0.5 0.4) 0.6~0.1 0.7\n  TRANSLATE -1 +2 3e-1\n";
    let (d, errs) = parse(text);
    assert!(errs.is_empty(), "{errs:?}");
    let d = d.unwrap();
    assert_eq!(d.name, "test tree");
    assert_eq!(d.resolution, [64, 32, 48]);
    assert_eq!((d.iterations, d.tree_depth, d.branch_depth, d.density_classes), (1234, 7, 2, 2));
    assert_eq!(d.perturbation.amplitude, [0.01, 0.02, 0.01]);
    assert_eq!(d.perturbation.frequency, 4.0);
    assert_eq!(d.condensations[0].weight, 2.0);
    assert_eq!(d.condensations[0].cone.axis, canopy_protocol::hypertree::Axis::Z);
    let t = &d.transformations[0];
    assert_eq!((t.probability, t.last_level, t.dummy_from), (0.5, 3, Some(2)));
    assert_eq!(d.param_levels(), 3);
    assert_eq!(t.steps.len(), 3);
    // The encoding round-trips.
    assert_eq!(HypertreeDef::decode(&d.encode()).expect("decodes"), d);
}

#[test]
fn bad_definitions_report_every_error_with_file_line_col_and_caret() {
    let text = "RESOLUTION 5000\nTREEDEPTH 4\nBOGUS 1\nSCALE 0.5\nCONDENSATION\n  CONE W 0 1 0 0\n\
TRANSFORM 1 255\n  ROTATE Y (1 2 3 4)\n  SHEAR Y 0 0 99\nDEPTHCOLOR 3 1 0 0 0 0 0 0\nITERATIONS 10 20\n";
    let (d, errs) = parse(text);
    assert!(d.is_none());
    let want = [
        ("t.hyp:1:12: error: resolution 5000 is out of range 1..=1024", "1 | RESOLUTION 5000\n  |            ^^^^"),
        ("t.hyp:3:1: error: unknown keyword `BOGUS`", "3 | BOGUS 1\n  | ^^^^^"),
        ("t.hyp:4:1: error: SCALE outside a CONDENSATION or TRANSFORM block", "^^^^^"),
        ("t.hyp:6:8: error: expected an axis (X, Y or Z), found `W`", "^"),
        ("t.hyp:8:19: error: at most 3 level values", "^"),
        ("t.hyp:9:15: error: a shear exponent 99 is out of range 0..=64", "^^"),
        ("t.hyp:10:12: error: depth colour span runs backwards", "^^^"),
        ("t.hyp:11:15: error: expected end of line, found `20`", "^^"),
    ];
    for (head, caret) in want {
        assert!(
            errs.iter().any(|e| e.starts_with(head) && e.contains(caret)),
            "missing `{head}` in:\n{}",
            errs.join("\n")
        );
    }
    // The condensation without a valid CONE is reported too, at its CONDENSATION line.
    assert!(errs.iter().any(|e| e.starts_with("t.hyp:5:1: error: condensation without a CONE")), "{errs:?}");
}

#[test]
fn structural_errors_are_reported() {
    let cases: &[(&str, &str)] = &[
        ("RESOLUTION 32\n", "a hypertree needs at least one CONDENSATION"),
        ("CONDENSATION\n CONE Y 0 1 0.1 0\n", "a hypertree needs at least one TRANSFORM"),
        ("CONE Y 0 1 0.1 0\n", "CONE outside a CONDENSATION block"),
        ("TREEDEPTH 3\nBRANCHDEPTH 3\n", "branch depth 3 is not below tree depth 3"),
        ("RESOLUTION 32\nRESOLUTION 32\n", "keyword given twice"),
        ("CONDENSATION\n CONE Y 0 1 0.1 0\n SCALE (0.5 0.4)\n", "condensation parameters cannot vary by level"),
        ("CONDENSATION\n CONE Y 0 1 0.1 0\nTRANSFORM 0 255\n SCALE 0.5\n", "transformation probabilities sum to zero"),
        ("TRANSFORM 1 0\n", "last allowed level 0 is out of range 1..=255"),
        ("HYPERVOLUME 1 0 1\n", "a hypervolume extent must be positive"),
        ("ROTATE Y 1e40\n", "is not a finite f32"),
        ("DENSITYCLASSES 200\n", "density classes 200 is out of range 2..=128"),
    ];
    for (text, msg) in cases {
        let (d, errs) = parse(text);
        assert!(d.is_none(), "{text:?} parsed");
        assert!(errs.iter().any(|e| e.contains(msg)), "{text:?}: want `{msg}` in {errs:?}");
    }
    let (d, errs) = parse(MINIMAL);
    assert!(errs.is_empty() && d.is_some(), "{errs:?}");
}

#[test]
fn hyperforest_files_parse_and_load_their_trees() {
    let (f, errs) = parse_forest(&SourceFile::new(
        "g.hyf",
        "NAME g\nRESOLUTION 40 20 40\nSTORAGETYPE INDEXLIST PARTITIONED\nHYPERVOLUME 4 2 4\nTREE a.hyp 1 0 1\nTREE b.hyp 3 0 3 SEED 9\n",
    ));
    assert!(errs.is_empty(), "{errs:?}");
    let f = f.unwrap();
    assert_eq!((f.storage, f.partitioned, f.resolution), (StorageType::IndexList, true, [40, 20, 40]));
    assert_eq!(f.trees[1].seed, 9);
    assert_eq!(f.trees[1].origin, [3.0, 0.0, 3.0]);
    let (f, errs) = parse_forest(&SourceFile::new("g.hyf", "STORAGETYPE OCTREE\nTREE\nWHAT 1\n"));
    assert!(f.is_none());
    let errs: Vec<String> = errs.iter().map(|e| e.to_string()).collect();
    assert!(errs.iter().any(|e| e.starts_with("g.hyf:1:13: error: unknown storage type `OCTREE`")), "{errs:?}");
    assert!(errs.iter().any(|e| e.starts_with("g.hyf:2:5: error: expected a hypertree file name")), "{errs:?}");
    assert!(errs.iter().any(|e| e.starts_with("g.hyf:3:1: error: unknown keyword `WHAT`")), "{errs:?}");
    // The shipped grove loads every tree it names.
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("hypertrees/grove.hyf");
    let (forest, errs) = load_forest(&path);
    assert!(errs.is_empty(), "{errs:?}");
    assert_eq!(forest.expect("loads").trees.len(), 3);
}

// ---------------------------------------------------------------------------------------------------------------
// Wire encoding

#[test]
fn encoding_rejects_hostile_bytes_without_panicking() {
    let d = def("apple");
    let bytes = d.encode();
    assert!(bytes.len() < 2048, "a hypertree definition is a few hundred bytes, got {}", bytes.len());
    let mut trailing = bytes.clone();
    trailing.push(0);
    assert_eq!(HypertreeDef::decode(&trailing), Err(HypertreeDecodeError::Trailing(1)));
    assert!(matches!(
        HypertreeDef::decode(&vec![0u8; MAX_HYPERTREE_BYTES + 1]),
        Err(HypertreeDecodeError::TooLarge(_))
    ));
    let mut bad = d.clone();
    bad.resolution = [0, 1, 1];
    assert!(matches!(
        HypertreeDef::decode(&bad.encode()),
        Err(HypertreeDecodeError::Invalid(HypertreeError::Resolution(_)))
    ));
    bad = d.clone();
    bad.transformations[0].steps[0] = canopy_protocol::hypertree::Elementary::Scale([
        canopy_protocol::hypertree::Param(vec![]),
        canopy_protocol::hypertree::Param::fixed(1.0),
        canopy_protocol::hypertree::Param::fixed(1.0),
    ]);
    assert_eq!(bad.validate(), Err(HypertreeError::ParamLevels(0)));
    bad = d.clone();
    bad.perturbation.amplitude[1] = f32::NAN;
    assert!(matches!(bad.validate(), Err(HypertreeError::Number { .. })));
    // Every truncation and many byte flips decode to an error or a valid definition, never a panic.
    for n in 0..bytes.len() {
        let _ = HypertreeDef::decode(&bytes[..n]);
    }
    let mut rng = XorShift64::new(0x2545_f491_4f6c_dd1d);
    for _ in 0..3000 {
        let x = rng.next();
        let mut b = bytes.clone();
        let i = (x % b.len() as u64) as usize;
        b[i] = (x >> 32) as u8;
        if let Ok(d) = HypertreeDef::decode(&b) {
            d.validate().expect("decode returns only valid definitions");
        }
    }
}

// ---------------------------------------------------------------------------------------------------------------
// Generation

#[test]
fn seeds_change_random_parameters_and_iteration() {
    let d = def("apple");
    let opts = GenerateOptions { resolution: Some([48; 3]), iterations: Some(20_000), ..Default::default() };
    let a = generate(&d, 1, &opts, &mut |_, _| {}).unwrap().0;
    let b = generate(&d, 2, &opts, &mut |_, _| {}).unwrap().0;
    assert_ne!(a.hash(), b.hash());
}

#[test]
fn storage_structures_agree_voxel_for_voxel() {
    for name in ["apple", "fork", "willow"] {
        let d = def(name);
        let mut trees = Vec::new();
        for (storage, partitioned) in [
            (StorageType::Dense, false),
            (StorageType::IndexList, false),
            (StorageType::IndexBits, false),
            (StorageType::IndexList, true),
            (StorageType::IndexBits, true),
        ] {
            let opts =
                GenerateOptions { storage, partitioned, resolution: Some([40, 44, 36]), iterations: Some(20_000) };
            trees.push(generate(&d, 7, &opts, &mut |_, _| {}).expect("generates").0);
        }
        let reference = &trees[0];
        assert!(reference.len() > 500, "{name}: {} voxels", reference.len());
        for t in &trees[1..] {
            assert_eq!(t.len(), reference.len(), "{name}: {:?}", t.store.storage_type());
            assert_eq!(t.hash(), reference.hash());
            assert_eq!(t.voxel_box, reference.voxel_box);
            for i in 0..reference.volume.voxel_count() as u32 + 10 {
                assert_eq!(
                    t.store.voxel(i),
                    reference.store.voxel(i),
                    "{name} voxel {i} in {:?}",
                    t.store.storage_type()
                );
            }
        }
        // Memory: the index list is far smaller than the dense array (packed: a low index byte and a palette
        // code a voxel, plus block tables); the bit array (over the plain list) adds to it.
        let m: Vec<usize> = trees.iter().map(|t| t.store.memory_bytes()).collect();
        assert_eq!(m[0], 2 * 40 * 48 * 40, "two bytes a voxel, bricks of 8³ pad 44 to 48 and 36 to 40");
        assert!(m[1] < m[2] && m[1] < 4 * reference.len(), "{name}: {} bytes for {} voxels", m[1], reference.len());
    }
}

#[test]
fn density_classes_equalise_the_histogram() {
    // Exponential hit-count distribution (Figure 3): many voxels hit once, few hit often.
    let mut h = [0u64; 256];
    for (n, slot) in h.iter_mut().enumerate().skip(1) {
        *slot = (100_000.0 * 0.8f64.powi(n as i32)) as u64;
    }
    let dc = DensityClasses::equalise(&h, 9);
    let mut per_class = [0u64; 9];
    for n in 1..256 {
        per_class[dc.class[n] as usize] += h[n];
        assert!(n == 1 || dc.class[n] >= dc.class[n - 1], "monotone");
    }
    assert_eq!(per_class[0], 0);
    let total: u64 = per_class.iter().sum();
    // No class holds much more than its eighth (a single hit count cannot be split), and most classes are used.
    for (c, &n) in per_class.iter().enumerate() {
        assert!((n as f64) < 0.22 * total as f64, "class {c}: {n} of {total}");
    }
    assert!(per_class.iter().filter(|&&n| n > 0).count() >= 6, "{per_class:?}");
    // The voxels hit once (20 %) are not left transparent as a linear mapping would (§4: "almost bare of leaves").
    assert!(dc.density[1] >= 60, "{}", dc.density[1]);
    assert_eq!(dc.density[255], 255);
    // Binary hypertree: every hit voxel at full density.
    let bin = DensityClasses::equalise(&h, 2);
    assert!((1..256).all(|n| bin.density[n] == 255));
}

#[test]
fn branch_voxels_get_full_density_and_levels_stay_in_range() {
    let d = def("fork");
    let t = small("fork", StorageType::IndexList, 64, 30_000);
    let list = t.store.to_list();
    let mut seen = [false; 256];
    for k in 0..list.len() {
        let level = list.levels[k];
        assert!(level < d.tree_depth);
        seen[level as usize] = true;
        if level <= d.branch_depth {
            assert_eq!(list.densities[k], 255, "branch voxel below full density");
        }
    }
    assert!(seen[0] && seen[usize::from(d.tree_depth) - 1], "levels 0 and k−1 present");
    assert!(list.densities.iter().any(|&x| x < 255), "leaves have lower densities");
}

#[test]
fn dummies_and_last_allowed_levels_limit_their_subparts() {
    // Subpart j + 1 holds what transformation j made as the outermost (first-level) transformation.
    let text = "RESOLUTION 48\nITERATIONS 40000\nTREEDEPTH 6\nBRANCHDEPTH 0\nHYPERVOLUME 1.2 1.2 1.2\nDISPLACEMENT 0.6 0 0.6\n\
CONDENSATION\n CONE Y 0 0.3 0.02 0.01\nTRANSFORM 1 255\n SCALE 0.6\n ROTATE Y 90\n TRANSLATE 0 0.3 0\n\
TRANSFORM 1 2\n SCALE 0.5\n ROTATE Z 50\n TRANSLATE 0 0.2 0\nTRANSFORM 1 255 DUMMY 3\n SCALE 0.5\n ROTATE Z -50\n TRANSLATE 0 0.25 0\n\
TRANSFORM 1 255 DUMMY\n SCALE 0.9\n ROTATE Y 45\n";
    let (d, errs) = parse(text);
    assert!(errs.is_empty(), "{errs:?}");
    let d = d.unwrap();
    let opts = GenerateOptions { storage: StorageType::IndexList, partitioned: true, ..Default::default() };
    let (t, stats) = generate(&d, 3, &opts, &mut |_, _| {}).unwrap();
    let VoxelStore::Partitioned(p) = &t.store else { panic!("partitioned") };
    let levels_of = |sub: u8| -> Vec<u8> {
        p.parts.iter().find(|x| x.subpart == sub).map(|x| x.store.voxels().levels.clone()).unwrap_or_default()
    };
    assert!(levels_of(0).iter().all(|&l| l == 0), "the stem part holds the condensation");
    let l1 = levels_of(1);
    assert!(l1.iter().any(|&l| l >= 4), "an unrestricted transformation reaches deep levels");
    let l2 = levels_of(2);
    assert!(!l2.is_empty() && l2.iter().all(|&l| l <= 2), "last allowed level 2: {l2:?}");
    let l3 = levels_of(3);
    assert!(!l3.is_empty() && l3.iter().all(|&l| l < 3), "dummy from level 3: {:?}", l3.iter().max());
    assert!(levels_of(4).is_empty(), "a dummy from level 1 never records");
    assert!(stats.dummies > 0);
    assert_eq!(stats.generators, 40_000);
}

#[test]
fn line_generators_hit_several_voxels_and_perturbation_is_seeded() {
    let (_, stats) = generate(
        &def("willow"),
        1,
        &GenerateOptions { resolution: Some([100; 3]), iterations: Some(5_000), ..Default::default() },
        &mut |_, _| {},
    )
    .unwrap();
    // A segment of length 0.05 in a 1.4-wide box at resolution 100 crosses about 4 voxels.
    assert!(stats.hits > 3 * stats.generators, "{stats:?}");
    let mut d = def("perturbed");
    let a = small("perturbed", StorageType::IndexList, 64, 20_000);
    d.perturbation.amplitude = [0.0; 3];
    let opts = GenerateOptions { resolution: Some([64; 3]), iterations: Some(20_000), ..Default::default() };
    let b = generate(&d, 1, &opts, &mut |_, _| {}).unwrap().0;
    assert_ne!(a.hash(), b.hash(), "perturbation moves voxels");
}

#[test]
fn bounds_of_generation_are_conservative() {
    for name in ["apple", "spruce", "willow", "fork", "perturbed"] {
        let t = small(name, StorageType::IndexBits, 56, 20_000);
        assert!(!t.bounds.spheres.is_empty(), "{name}");
        let list = t.store.to_list();
        for &i in &list.indices {
            let c = t.volume.center(t.volume.coords(i));
            let in_sphere = t.bounds.spheres.iter().any(|s| {
                let d: f32 = (0..3).map(|k| (c[k] - s.center[k]).powi(2)).sum();
                d.sqrt() <= s.radius
            });
            let in_box = t.bounds.boxes.iter().any(|b| (0..3).all(|k| c[k] >= b.min[k] && c[k] <= b.max[k]));
            assert!(in_sphere || in_box, "{name}: voxel {i} at {c:?} outside every bounding volume");
        }
    }
}

#[test]
fn generation_rejects_oversized_requests() {
    let d = def("apple");
    let go = |o: GenerateOptions| generate(&d, 1, &o, &mut |_, _| {}).map(|_| ());
    assert!(matches!(
        go(GenerateOptions { resolution: Some([2000, 10, 10]), ..Default::default() }),
        Err(GenerateError::Resolution(_))
    ));
    assert!(matches!(
        go(GenerateOptions { storage: StorageType::Dense, resolution: Some([1024; 3]), ..Default::default() }),
        Err(GenerateError::DenseTooLarge(_))
    ));
    assert!(matches!(
        go(GenerateOptions { iterations: Some(0), ..Default::default() }),
        Err(GenerateError::Iterations(0))
    ));
    assert!(matches!(
        go(GenerateOptions { storage: StorageType::Dense, partitioned: true, ..Default::default() }),
        Err(GenerateError::PartitionedDense)
    ));
}

#[test]
fn forest_generates_every_tree_into_one_volume() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("hypertrees/grove.hyf");
    let (forest, _) = load_forest(&path);
    let mut forest = forest.expect("loads");
    for t in &mut forest.trees {
        t.iterations = 20_000;
    }
    forest.def.resolution = [72, 24, 48];
    let (t, stats) = generate_forest(&forest, &mut |_, _| {}).unwrap();
    let (t2, _) = generate_forest(&forest, &mut |_, _| {}).unwrap();
    assert_eq!(t.hash(), t2.hash());
    assert_eq!(stats.generators, 60_000);
    // Every third of the forest's width holds a tree.
    let list = t.store.to_list();
    let mut thirds = [0usize; 3];
    for &i in &list.indices {
        thirds[(t.volume.coords(i)[0] / 24) as usize] += 1;
    }
    assert!(thirds.iter().all(|&n| n > 100), "{thirds:?}");
}

// ---------------------------------------------------------------------------------------------------------------
// Operations

fn tree_from(volume: Hypervolume, voxels: &[(u32, Voxel)], storage: StorageType) -> Hypertree {
    let mut list = VoxelList::default();
    for &(i, v) in voxels {
        list.push(i, v);
    }
    let store = VoxelStore::from_list(list, storage, &volume);
    Hypertree::new("t".into(), volume, store, Vec::new(), 4, 1, Bounds::default(), Vec::new())
}

#[test]
fn union_takes_the_maximum_and_addition_the_sum() {
    let vol = Hypervolume { resolution: [4, 4, 4], extent: [1.0; 3] };
    let v = |density, level| Voxel { density, level };
    let a = tree_from(vol, &[(1, v(100, 3)), (5, v(200, 2)), (9, v(50, 1))], StorageType::IndexList);
    let b = tree_from(vol, &[(5, v(120, 1)), (9, v(50, 0)), (20, v(255, 2))], StorageType::Dense);
    let u = combine(&a, &b, Unification::Max).unwrap();
    assert_eq!(u.store.storage_type(), StorageType::IndexList, "the first operand's structure");
    let got: Vec<(u32, Voxel)> = (0..64).map(|i| (i, u.store.voxel(i))).filter(|x| x.1.density > 0).collect();
    assert_eq!(got, vec![(1, v(100, 3)), (5, v(200, 2)), (9, v(50, 0)), (20, v(255, 2))]);
    let s = combine(&a, &b, Unification::Add).unwrap();
    assert_eq!(s.store.voxel(5), v(255, 1), "saturating sum, shallower level");
    assert_eq!(s.store.voxel(9), v(100, 0));
    // A tree united with itself is itself.
    let t = small("fork", StorageType::IndexBits, 40, 10_000);
    assert_eq!(combine(&t, &t, Unification::Max).unwrap().hash(), t.hash());
    let other = Hypervolume { resolution: [4, 4, 5], extent: [1.0; 3] };
    let c = tree_from(other, &[], StorageType::IndexList);
    assert!(matches!(combine(&a, &c, Unification::Max), Err(OpError::VolumeMismatch(..))));
}

#[test]
fn clear_and_set_act_on_voxel_centres_in_the_region() {
    let t = small("apple", StorageType::IndexBits, 40, 20_000);
    let ext = t.volume.extent;
    // Clear the top half (Figure 9, right).
    let cleared = clear_region(&t, [0.0, 0.5 * ext[1], 0.0], ext).unwrap();
    assert!(cleared.len() < t.len() && !cleared.is_empty());
    let list = t.store.to_list();
    for &i in &list.indices {
        let y = t.volume.coords(i)[1];
        let want = if y >= 20 { Voxel::EMPTY } else { t.store.voxel(i) };
        assert_eq!(cleared.store.voxel(i), want, "voxel {i}");
    }
    assert!(cleared.voxel_box.unwrap().1[1] < 20);
    let v = Voxel { density: 77, level: 2 };
    // A region reaching 2.6 voxel sides holds the voxels whose centres (0.5, 1.5, 2.5 sides) lie inside it.
    let vs = t.volume.voxel_size();
    let set = set_region(&t, [0.0; 3], vs.map(|s| 2.6 * s), v).unwrap();
    for x in 0..3u32 {
        assert_eq!(set.voxel([x, x, x]), v);
    }
    assert_eq!(set.voxel([3, 3, 3]), t.voxel([3, 3, 3]));
    assert!(set.bounds.boxes.len() > t.bounds.boxes.len(), "a set region joins the bounds");
    assert!(matches!(set_region(&t, [0.0; 3], [1.0; 3], Voxel::EMPTY), Err(OpError::ZeroDensity)));
    assert!(matches!(clear_region(&t, [1.0; 3], [0.0; 3]), Err(OpError::Region(..))));
    assert!(matches!(clear_region(&t, [f32::NAN; 3], [1.0; 3]), Err(OpError::Region(..))));
}

#[test]
fn reduction_fuses_voxels_by_their_shares() {
    let vol = Hypervolume { resolution: [4, 4, 4], extent: [1.0; 3] };
    let full: Vec<(u32, Voxel)> = (0..64).map(|i| (i, Voxel { density: 200, level: 1 })).collect();
    let r = reduce(&tree_from(vol, &full, StorageType::IndexList), [2, 2, 2]).unwrap();
    assert_eq!(r.len(), 8);
    assert!((0..8).all(|i| r.store.voxel(i) == Voxel { density: 200, level: 1 }));
    // One voxel at a reduction factor of 2 shares an eighth of the new voxel.
    let one = tree_from(vol, &[(0, Voxel { density: 240, level: 3 })], StorageType::Dense);
    let r = reduce(&one, [2, 2, 2]).unwrap();
    assert_eq!(r.store.voxel(0), Voxel { density: 30, level: 3 });
    assert_eq!(r.store.storage_type(), StorageType::Dense);
    // Factor 4/3 along x: old voxel 1, [1, 2), lies 1/3 in new voxel 0, [0, 4/3), and 2/3 in new voxel 1 (Figure 5
    // along one axis).
    let vol = Hypervolume { resolution: [4, 1, 1], extent: [1.0; 3] };
    let t = tree_from(vol, &[(1, Voxel { density: 240, level: 0 })], StorageType::IndexList);
    let r = reduce(&t, [3, 1, 1]).unwrap();
    assert_eq!(r.store.voxel(0).density, 60); // 240 · (1/3) / (4/3)
    assert_eq!(r.store.voxel(1).density, 120); // 240 · (2/3) / (4/3)
    // Depth is the most represented one.
    let t = tree_from(
        vol,
        &[
            (0, Voxel { density: 10, level: 5 }),
            (1, Voxel { density: 250, level: 2 }),
            (2, Voxel { density: 10, level: 5 }),
            (3, Voxel { density: 10, level: 5 }),
        ],
        StorageType::IndexList,
    );
    assert_eq!(reduce(&t, [1, 1, 1]).unwrap().store.voxel(0), Voxel { density: 70, level: 5 });
    // Same resolution: identity; larger: refused.
    let g = small("willow", StorageType::IndexList, 36, 5_000);
    assert_eq!(reduce(&g, g.volume.resolution).unwrap().hash(), g.hash());
    assert!(matches!(reduce(&g, [37, 36, 36]), Err(OpError::Resolution { .. })));
    // Reducing a real tree keeps its mass approximately: total density scales with the voxel volume ratio.
    let big = small("apple", StorageType::IndexList, 60, 20_000);
    let r = reduce(&big, [40, 40, 40]).unwrap();
    let mass = |t: &Hypertree| t.store.to_list().densities.iter().map(|&d| f64::from(d)).sum::<f64>();
    let ratio = mass(&r) * 2.25 * 1.5 / mass(&big);
    assert!((0.9..1.1).contains(&ratio), "mass ratio {ratio}");
}

// ---------------------------------------------------------------------------------------------------------------
// Saved volumes

#[test]
fn volumes_round_trip_and_reject_corruption() {
    for (storage, partitioned) in
        [(StorageType::Dense, false), (StorageType::IndexBits, true), (StorageType::IndexList, false)]
    {
        let opts = GenerateOptions { storage, partitioned, resolution: Some([40; 3]), iterations: Some(10_000) };
        let t = generate(&def("fork"), 5, &opts, &mut |_, _| {}).unwrap().0;
        let bytes = save_volume(&t);
        let back = load_volume(&bytes).expect("loads");
        assert_eq!(back.hash(), t.hash());
        assert_eq!(back.store.storage_type(), storage);
        assert_eq!(back.store.is_partitioned(), partitioned);
        assert_eq!(back.bounds, t.bounds);
        assert_eq!(back.flows, t.flows);
        assert_eq!(back.voxel_box, t.voxel_box);
        for n in (0..bytes.len()).step_by(97) {
            assert!(load_volume(&bytes[..n]).is_err());
        }
    }
    assert_eq!(load_volume(b"not a volume").map(|_| ()), Err(VolumeFileError::Magic));
    let t = small("fork", StorageType::IndexList, 32, 3_000);
    let bytes = save_volume(&t);
    let mut rng = XorShift64::new(0x9e37_79b9_7f4a_7c15);
    for _ in 0..2000 {
        let x = rng.next();
        let mut b = bytes.clone();
        let i = 9 + (x % (b.len() as u64 - 9)) as usize;
        b[i] ^= (x >> 40) as u8 | 1;
        if let Ok(t) = load_volume(&b) {
            // Whatever decodes is internally consistent.
            let l = t.store.to_list();
            assert!(l.indices.windows(2).all(|w| w[0] < w[1]));
            assert!(l.indices.iter().all(|&i| u64::from(i) < t.volume.voxel_count()));
        }
    }
}

// ---------------------------------------------------------------------------------------------------------------
// Rendering

fn quick_view() -> RenderOptions {
    RenderOptions { width: 48, height: 48, ..RenderOptions::default() }
}

#[test]
fn time_saving_options_leave_the_image_bit_identical() {
    for name in ["apple", "fork", "willow"] {
        let t = small(name, StorageType::IndexList, 48, 15_000);
        let base = render(&t, &quick_view(), &mut |_, _| {}).unwrap().0;
        for o in [
            RenderOptions { bounds: BoundingScheme::Spheres, ..quick_view() },
            RenderOptions { skip_empty: false, ..quick_view() },
            RenderOptions { ray_cache: true, ..quick_view() },
            RenderOptions { ray_cache: true, bounds: BoundingScheme::Spheres, skip_empty: false, ..quick_view() },
        ] {
            let img = render(&t, &o, &mut |_, _| {}).unwrap().0;
            assert_eq!(img, base, "{name}: {:?} {:?} {} {}", o.bounds, o.shading, o.skip_empty, o.ray_cache);
        }
        // So do the other storage structures.
        for storage in [StorageType::Dense, StorageType::IndexBits] {
            let u = small(name, storage, 48, 15_000);
            assert_eq!(render(&u, &quick_view(), &mut |_, _| {}).unwrap().0, base, "{name} {storage:?}");
        }
    }
}

#[test]
fn shading_models_and_shadows_change_the_image() {
    let t = small("fork", StorageType::IndexBits, 48, 15_000);
    let base = render(&t, &quick_view(), &mut |_, _| {}).unwrap().0;
    for o in [
        RenderOptions { shading: Shading::Ambient, ..quick_view() },
        RenderOptions { shading: Shading::Specular, ..quick_view() },
        RenderOptions { shadows: false, ..quick_view() },
        RenderOptions { supersample: 2, ..quick_view() },
    ] {
        assert_ne!(render(&t, &o, &mut |_, _| {}).unwrap().0, base, "{:?} {}", o.shading, o.shadows);
    }
    // Without shadows everything is at least as bright.
    let lit = render(&t, &RenderOptions { shadows: false, ..quick_view() }, &mut |_, _| {}).unwrap().0;
    let sum = |img: &canopy_worlds::hypertree::render::Image| img.pixels.iter().map(|&p| u64::from(p)).sum::<u64>();
    assert!(sum(&lit) > sum(&base));
}

#[test]
fn render_rejects_bad_options() {
    let t = small("fork", StorageType::IndexList, 24, 2_000);
    let r = |o: RenderOptions| render(&t, &o, &mut |_, _| {}).map(|_| ());
    assert!(matches!(r(RenderOptions { width: 0, ..quick_view() }), Err(RenderError::Size(0, 48))));
    assert!(matches!(r(RenderOptions { width: 100_000, ..quick_view() }), Err(RenderError::Size(..))));
    assert!(matches!(r(RenderOptions { supersample: 9, ..quick_view() }), Err(RenderError::Supersample(9))));
    assert!(matches!(r(RenderOptions { fov: f32::NAN, ..quick_view() }), Err(RenderError::Parameter(_))));
    // An empty hypertree renders as background.
    let empty = clear_region(&t, [0.0; 3], t.volume.extent).unwrap();
    let img = render(&empty, &quick_view(), &mut |_, _| {}).unwrap().0;
    assert_eq!(img.pixel(0, 10), img.pixel(40, 10));
}

// ---------------------------------------------------------------------------------------------------------------
// Voxelised species

#[test]
fn species_voxelise_deterministically_with_depth_colours() {
    let graph = canopy_worlds::library::find("monopodial").expect("library species").load().expect("parses");
    let opts = VoxeliseOptions { resolution: 64, ..VoxeliseOptions::default() };
    let a = voxelise_species(&graph, &Instance::new(3), &Budget::default(), &opts).unwrap();
    let b = voxelise_species(&graph, &Instance::new(3), &Budget::default(), &opts).unwrap();
    assert_eq!(a.hash(), b.hash());
    assert!(a.len() > 1000, "{} voxels", a.len());
    let c = voxelise_species(&graph, &Instance::new(4), &Budget::default(), &opts).unwrap();
    assert_ne!(a.hash(), c.hash(), "another seed, another tree");
    let l = a.store.to_list();
    assert!(l.levels.contains(&0), "the trunk is level 0");
    assert!(l.levels.iter().all(|&x| x <= opts.branch_depth + 1));
    assert!(!a.depth_colors.is_empty() && !a.flows.is_empty());
    assert_eq!(a.volume.resolution.iter().max(), Some(&64));
    let img = render(&a, &quick_view(), &mut |_, _| {}).unwrap().0;
    assert_ne!(img.pixel(24, 24), img.pixel(0, 0));
    assert!(
        voxelise_species(&graph, &Instance::new(3), &Budget::default(), &VoxeliseOptions { resolution: 0, ..opts })
            .is_err()
    );
    assert!(matches!(
        voxelise_species(&graph, &Instance::new(3), &Budget::default(), &VoxeliseOptions { max_samples: 10, ..opts }),
        Err(canopy_worlds::hypertree::voxelise::VoxeliseError::Samples(10))
    ));
    assert!(matches!(
        voxelise_species(&graph, &Instance::new(3), &Budget::default(), &VoxeliseOptions { max_covered: 100, ..opts }),
        Err(canopy_worlds::hypertree::voxelise::VoxeliseError::Covered(100))
    ));
}
