//! CPU side of near and mid geometry: one instance amplified at a detail level and turned into what the GPU draws —
//! primitive instances of unit shapes (cone/cylinder frusta, spheres, boxes) and a mesh for everything else
//! (leaves, trunk bases), or one merged mesh ([`NearMode::Merged`]). Pure and deterministic; runs on workers.

use std::ops::Range;

use bytemuck::{Pod, Zeroable};
use canopy_protocol::SpeciesGraph;
use canopy_worlds::amplify::{AmplifyError, Budget, Instance, amplify};
use canopy_worlds::mesh::{Mesh, MeshOptions, mesh_into_where};
use canopy_worlds::nearfield::options::species_options;
use canopy_worlds::nearfield::species_near_mesh;
use canopy_worlds::primitive::{Primitive, PrimitiveStream, Shape};

use super::NearMode;
use super::leaf::{Card, NOT_A_CARD, card_of};

/// The unit shapes drawn by instancing, in draw order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(crate) enum UnitShape {
    /// A frustum on the origin along +Y: cones and cylinders (`shape = [bottom, top, height]`).
    Frustum = 0,
    /// A sphere on the origin (`shape = [radius, radius, radius]`).
    Sphere = 1,
    /// A box centred on the origin (`shape = edge lengths`).
    Box = 2,
}

/// One primitive instance as the shaders read it (64 bytes): the species-space transform's three rows, the shape's
/// size and the linear RGB colour packed as unorm8×4.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub(crate) struct PrimInstance {
    /// Rows of the 3×4 affine transform.
    pub rows: [[f32; 4]; 3],
    /// Size parameters (see [`UnitShape`]).
    pub shape: [f32; 3],
    /// Colour, unorm8×4 little-endian (r in the low byte).
    pub color: u32,
}

/// One mesh vertex as the shaders read it (20 bytes): position, normal snorm8×4, colour unorm8×4.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub(crate) struct MeshVertex {
    /// Species-space position.
    pub position: [f32; 3],
    /// Unit normal, snorm8×4; w is 1 for a leaf (thin: lit through from behind), 0 otherwise.
    pub normal: u32,
    /// Linear RGB colour, unorm8×3; the alpha byte places a leaf card's corner (`leaf.rs`), 255 elsewhere.
    pub color: u32,
}

/// The GPU-ready geometry of one (species, seed, detail).
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct TreeGeometry {
    /// Primitive instances, grouped by [`UnitShape`] (empty in merged mode).
    pub prims: Vec<PrimInstance>,
    /// The range of each [`UnitShape`] in `prims`.
    pub shape_ranges: [Range<u32>; 3],
    /// Mesh vertices.
    pub vertices: Vec<MeshVertex>,
    /// Mesh triangle indices into `vertices`.
    pub indices: Vec<u32>,
    /// Primitives amplified.
    pub primitives: usize,
}

impl TreeGeometry {
    /// Bytes this geometry takes on the GPU.
    pub(crate) fn gpu_bytes(&self) -> u64 {
        (self.prims.len() * size_of::<PrimInstance>()
            + self.vertices.len() * size_of::<MeshVertex>()
            + self.indices.len() * 4) as u64
    }

    /// Whether there is nothing to draw.
    pub(crate) fn is_empty(&self) -> bool {
        self.prims.is_empty() && self.indices.is_empty()
    }
}

/// Pack a linear colour as unorm8×4.
pub(crate) fn pack_unorm(c: [f32; 3]) -> u32 {
    let q = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u32;
    q(c[0]) | q(c[1]) << 8 | q(c[2]) << 16 | 255 << 24
}

/// Pack a unit vector as snorm8×4 (w = 0).
pub(crate) fn pack_snorm(n: [f32; 3]) -> u32 {
    pack_snorm4(n, 0.0)
}

/// Pack a unit vector and `w` as snorm8×4.
fn pack_snorm4(n: [f32; 3], w: f32) -> u32 {
    let q = |v: f32| ((v.clamp(-1.0, 1.0) * 127.0).round() as i32 as u32) & 0xff;
    q(n[0]) | q(n[1]) << 8 | q(n[2]) << 16 | q(w) << 24
}

fn finite_positive(v: &[f32]) -> bool {
    v.iter().all(|x| x.is_finite() && *x > 0.0)
}

/// The unit-shape instance of a primitive, or `None` for leaves, trunk bases and degenerate primitives.
fn unit_instance(p: &Primitive) -> Option<(UnitShape, [f32; 3])> {
    let (shape, size) = match p.shape {
        Shape::Cone { bottom, top, height } => {
            let ok = bottom.is_finite() && top.is_finite() && bottom >= 0.0 && top >= 0.0 && bottom + top > 0.0;
            if !ok || !finite_positive(&[height]) {
                return None;
            }
            (UnitShape::Frustum, [bottom, top, height])
        }
        Shape::Cylinder { radius, height } => {
            if !finite_positive(&[radius, height]) {
                return None;
            }
            (UnitShape::Frustum, [radius, radius, height])
        }
        Shape::Sphere { radius } => {
            if !finite_positive(&[radius]) {
                return None;
            }
            (UnitShape::Sphere, [radius; 3])
        }
        Shape::Box { size } => {
            if !finite_positive(&size) {
                return None;
            }
            (UnitShape::Box, size)
        }
        Shape::Leaf { .. } | Shape::TrunkBase(_) => return None,
    };
    if !p.transform.m.iter().all(|v| v.is_finite()) || p.transform.determinant().abs() < 1e-24 {
        return None;
    }
    Some((shape, size))
}

/// Amplify `instance` of `graph` (its `detail` selects the LOD substitutes) and build its geometry.
pub(crate) fn build_tree(
    graph: &SpeciesGraph,
    instance: &Instance,
    mode: NearMode,
    budget: &Budget,
) -> Result<TreeGeometry, AmplifyError> {
    let stream = amplify(graph, instance, budget)?;
    // Full detail of a species that asks for near-field meshing (`nearfield(continuous = 1, …)`): its continuous
    // mesh with bark and foliage, as `canopy species export` writes it.
    if instance.detail == 0
        && let Some(o) = species_options(graph, instance)?.filter(|o| o.continuous)
    {
        match species_near_mesh(&stream, &o) {
            Ok(m) => {
                let mut out = TreeGeometry { primitives: stream.primitives.len(), ..Default::default() };
                set_mesh(&mut out, m, &[]);
                return Ok(out);
            }
            Err(e) => tracing::warn!("{}: near-field mesh failed ({e}); drawing its primitives", graph.name),
        }
    }
    Ok(geometry_of(&stream, instance.detail, mode))
}

/// Build the geometry of an amplified stream (see [`build_tree`]).
pub(crate) fn geometry_of(stream: &PrimitiveStream, detail: u8, mode: NearMode) -> TreeGeometry {
    let opts = MeshOptions::for_detail(detail);
    let mut out = TreeGeometry { primitives: stream.primitives.len(), ..Default::default() };
    let mut mesh = Mesh::new();
    // Meshed: leaves first (thin, lit through), then the rest merged, or only the trunk bases (never unit shapes)
    // where the rest are instanced.
    // Flat leaves as cards (`leaf.rs`), the others as their polygons.
    let leaf = |p: &Primitive| matches!(p.shape, Shape::Leaf { .. });
    let rest = |_, p: &Primitive| !leaf(p) && (mode == NearMode::Merged || matches!(p.shape, Shape::TrunkBase(_)));
    let mut tags = Vec::new();
    // Each leaf's card made once; the leaves without one are meshed as polygons after.
    let mut polygons = vec![false; stream.primitives.len()];
    for (i, p) in stream.primitives.iter().enumerate().filter(|(_, p)| leaf(p)) {
        let Some(c) = card_of(stream, p) else {
            polygons[i] = true;
            continue;
        };
        let first = mesh.positions.len() as u32;
        for (corner, tag) in c.corners.iter().zip(c.tags) {
            mesh.positions.push(corner.to_array());
            mesh.normals.push(c.normal.to_array());
            mesh.colors.push(p.color);
            tags.push(tag);
        }
        mesh.indices.extend(Card::TRIANGLES.iter().map(|i| first + i));
    }
    if polygons.contains(&true) {
        mesh_into_where(stream, &opts, |i, _| polygons[i], &mut mesh);
    }
    let thin = mesh.positions.len();
    tags.resize(thin, NOT_A_CARD);
    if stream.primitives.iter().any(|p| rest(0, p)) {
        mesh_into_where(stream, &opts, rest, &mut mesh);
    }
    if mode == NearMode::Instanced {
        let mut by_shape: [Vec<PrimInstance>; 3] = Default::default();
        for p in &stream.primitives {
            if let Some((shape, size)) = unit_instance(p) {
                let m = &p.transform.m;
                by_shape[shape as usize].push(PrimInstance {
                    rows: [[m[0], m[1], m[2], m[3]], [m[4], m[5], m[6], m[7]], [m[8], m[9], m[10], m[11]]],
                    shape: size,
                    color: pack_unorm(p.color),
                });
            }
        }
        let mut start = 0u32;
        for (k, v) in by_shape.iter_mut().enumerate() {
            out.shape_ranges[k] = start..start + v.len() as u32;
            start += v.len() as u32;
            out.prims.append(v);
        }
    }
    set_mesh(&mut out, mesh, &tags);
    out
}

/// Make `mesh` the geometry's mesh part, packed for the GPU; its first `leaves.len()` vertices are of leaves (their
/// normal's w is 1: `mesh.wgsl` lights them through), each with its card's alpha byte (`leaf.rs`).
fn set_mesh(out: &mut TreeGeometry, mesh: Mesh, leaves: &[u8]) {
    out.vertices = mesh
        .positions
        .iter()
        .zip(&mesh.normals)
        .zip(&mesh.colors)
        .enumerate()
        .map(|(i, ((p, n), c))| MeshVertex {
            position: *p,
            normal: pack_snorm4(*n, if i < leaves.len() { 1.0 } else { 0.0 }),
            color: pack_unorm(*c) & 0x00ff_ffff | u32::from(leaves.get(i).copied().unwrap_or(NOT_A_CARD)) << 24,
        })
        .collect();
    out.indices = mesh.indices;
}

#[cfg(test)]
mod tests {
    use canopy_worlds::library;

    use super::*;

    fn conifer() -> SpeciesGraph {
        library::find("conifer").unwrap().load().unwrap()
    }

    #[test]
    fn full_detail_of_a_near_field_species_is_its_continuous_mesh() {
        let text = include_str!("../../../worlds/species/fig.species");
        let (g, d) = canopy_worlds::load::parse_source(&canopy_worlds::diag::SourceFile::new("fig.species", text));
        let g = g.unwrap_or_else(|| panic!("{d:?}"));
        let inst = Instance::new(3);
        let near = build_tree(&g, &inst, NearMode::Instanced, &Budget::default()).unwrap();
        let stream = amplify(&g, &inst, &Budget::default()).unwrap();
        let o = species_options(&g, &inst).unwrap().unwrap();
        let m = species_near_mesh(&stream, &o).unwrap();
        assert!(near.prims.is_empty(), "the continuous mesh replaces the unit primitives");
        assert_eq!(near.indices.len(), m.indices.len());
        assert_eq!(near.vertices.len(), m.positions.len());
        // Coarser details keep the ordinary path.
        let mid =
            build_tree(&g, &Instance { detail: 1, ..inst.clone() }, NearMode::Instanced, &Budget::default()).unwrap();
        assert!(!mid.prims.is_empty());
    }

    #[test]
    fn instanced_geometry_keeps_every_primitive() {
        let g = conifer();
        let inst = Instance::new(7);
        let stream = amplify(&g, &inst, &Budget::default()).unwrap();
        let geo = geometry_of(&stream, 0, NearMode::Instanced);
        let counts = stream.counts();
        // Cones and cylinders become frusta, spheres spheres, boxes boxes; leaves are meshed.
        assert_eq!(geo.shape_ranges[0].len(), counts[0] + counts[1]);
        assert_eq!(geo.shape_ranges[1].len(), counts[2]);
        assert_eq!(geo.shape_ranges[2].len(), counts[3]);
        assert_eq!(geo.prims.len(), counts[0] + counts[1] + counts[2] + counts[3]);
        assert_eq!(geo.primitives, stream.primitives.len());
        assert_eq!(size_of::<PrimInstance>(), 64);
        assert_eq!(size_of::<MeshVertex>(), 20);
        // The first frustum is the first cone or cylinder of the stream, transform and size intact.
        let first = stream.primitives.iter().find(|p| unit_instance(p).map(|u| u.0) == Some(UnitShape::Frustum));
        let first = first.unwrap();
        assert_eq!(geo.prims[0].rows[0][3], first.transform.m[3]);
        let (lo, hi) = stream.bounds();
        assert!(hi[1] - lo[1] > 5.0, "a conifer is several metres tall: {lo:?} {hi:?}");
    }

    #[test]
    fn merged_geometry_is_the_worlds_mesh_with_leaves_as_cards() {
        let g = library::find("monopodial").unwrap().load().unwrap();
        let inst = Instance::new(3).with_detail(0);
        let stream = amplify(&g, &inst, &Budget::default()).unwrap();
        let geo = geometry_of(&stream, 0, NearMode::Merged);
        let is_leaf = |p: &Primitive| matches!(p.shape, Shape::Leaf { .. });
        let mut rest = Mesh::new();
        mesh_into_where(&stream, &MeshOptions::for_detail(0), |_, p| !is_leaf(p), &mut rest);
        assert!(geo.prims.is_empty());
        // Every leaf of the monopodial is flat: a card of 4 corners and 2 triangles, first, marked thin and placed.
        let leaves = stream.primitives.iter().filter(|p| is_leaf(p)).count();
        assert!(leaves > 100, "{leaves}");
        let (cards, others) = geo.vertices.split_at(4 * leaves);
        assert!(cards.iter().all(|v| v.normal >> 24 == 127 && v.color >> 24 < 128), "leaf cards marked");
        assert!(others.iter().all(|v| v.normal >> 24 == 0 && v.color >> 24 == 255));
        assert_eq!(others.len(), rest.positions.len());
        // The rest: the same triangles as the world's mesh.
        let triangles = |idx: &[u32], at: &dyn Fn(u32) -> [f32; 3]| {
            let mut t: Vec<[u32; 9]> =
                idx.chunks_exact(3).map(|c| std::array::from_fn(|k| at(c[k / 3])[k % 3].to_bits())).collect();
            t.sort_unstable();
            t
        };
        let base = 4 * leaves as u32;
        assert_eq!(
            triangles(&geo.indices[6 * leaves..], &|i| geo.vertices[i as usize].position),
            triangles(&rest.indices, &|i| rest.positions[(i) as usize])
        );
        assert!(geo.indices[6 * leaves..].iter().all(|&i| i >= base));
        assert!(geo.gpu_bytes() > 0);
    }

    #[test]
    fn lod_substitutes_shrink_the_geometry() {
        let g = conifer();
        let sizes: Vec<usize> = (0..=3u8)
            .map(|d| build_tree(&g, &Instance::new(11).with_detail(d), NearMode::Instanced, &Budget::default()))
            .map(|r| r.unwrap().primitives)
            .collect();
        assert!(sizes.windows(2).all(|w| w[0] > w[1]), "primitives per detail level: {sizes:?}");
    }

    #[test]
    fn a_hostile_budget_ends_in_an_error() {
        let g = conifer();
        let tight = Budget { max_primitives: 10, ..Budget::default() };
        assert!(build_tree(&g, &Instance::new(1), NearMode::Instanced, &tight).is_err());
    }

    #[test]
    fn packing() {
        assert_eq!(pack_unorm([1.0, 0.0, 0.5]), 0xff80_00ff);
        assert_eq!(pack_unorm([2.0, -1.0, f32::NAN]) & 0xffff, 0x00ff);
        assert_eq!(pack_snorm([0.0, 1.0, -1.0]), 0x0081_7f00);
    }
}
