//! Meshing: turn a [`PrimitiveStream`] into one indexed triangle mesh with per-vertex normals and colours.
//!
//! Every primitive is built in its local frame (cones and cylinders stand on the origin along +Y, spheres and
//! boxes are centred on the origin, leaves use their local points), then mapped to species space by its
//! transform: positions by [`Transform::point`], normals by [`Transform::normal_matrix`] and normalised. Triangles
//! are wound counter-clockwise seen from the side their normals point to (glTF's front face); closed shapes face
//! outward. A mirroring transform (negative [`Transform::determinant`]) flips both normals and winding, so
//! mirrored geometry still faces outward.
//!
//! Determinism: the unit-circle tables come from `libm::sinf`/`libm::cosf`, all arithmetic is plain `f32` in a
//! fixed order (no fused multiply-add, no SIMD, no hashing), so the same stream and options give a bit-identical
//! mesh on every platform ([`Mesh::hash`] is the golden check).
//!
//! Degenerate primitives — a zero, negative or non-finite size, a leaf with fewer than three points or no area,
//! a non-finite transform, or anything whose vertices would not be finite — are skipped whole; a mesh from
//! [`mesh`] never holds a NaN or an infinity, and its normals are unit length.

use canopy_protocol::LeafTopology;

use crate::primitive::{Fnv, Primitive, PrimitiveStream, Shape};
use crate::transform::Transform;
use crate::vec3::{cross, normalize, sub};

/// An indexed triangle list: every vertex has a position, a unit normal and a linear RGB colour.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// Unit vertex normals, one per position.
    pub normals: Vec<[f32; 3]>,
    /// Linear RGB vertex colours in `0..=1`, one per position.
    pub colors: Vec<[f32; 3]>,
    /// Three indices per triangle, counter-clockwise seen from the front.
    pub indices: Vec<u32>,
}

impl Mesh {
    /// An empty mesh.
    pub fn new() -> Mesh {
        Mesh::default()
    }

    /// Number of vertices.
    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// True when the mesh has no triangles.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// Remove everything, keeping the allocations.
    pub fn clear(&mut self) {
        self.positions.clear();
        self.normals.clear();
        self.colors.clear();
        self.indices.clear();
    }

    /// A stable 64-bit FNV-1a hash over the counts and the bit patterns of every position, normal, colour and
    /// index, for golden tests.
    pub fn hash(&self) -> u64 {
        let mut h = Fnv::new();
        h.u32(self.positions.len() as u32);
        h.u32(self.indices.len() as u32);
        for v in &self.positions {
            h.f32s(v);
        }
        for v in &self.normals {
            h.f32s(v);
        }
        for v in &self.colors {
            h.f32s(v);
        }
        for &i in &self.indices {
            h.u32(i);
        }
        h.finish()
    }

    /// The axis-aligned bounds `(min, max)` of the positions; `([0; 3], [0; 3])` for an empty mesh.
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let Some(first) = self.positions.first() else {
            return ([0.0; 3], [0.0; 3]);
        };
        let (mut lo, mut hi) = (*first, *first);
        for p in &self.positions[1..] {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (lo, hi)
    }

    /// Append `other`, translated by `offset` (placing trees in a grove).
    pub fn append(&mut self, other: &Mesh, offset: [f32; 3]) {
        let base = self.positions.len() as u32;
        self.positions.extend(other.positions.iter().map(|p| [p[0] + offset[0], p[1] + offset[1], p[2] + offset[2]]));
        self.normals.extend_from_slice(&other.normals);
        self.colors.extend_from_slice(&other.colors);
        self.indices.extend(other.indices.iter().map(|&i| i + base));
    }
}

/// How finely primitives are tessellated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MeshOptions {
    /// Segments around cones and cylinders (default 8: an octagonal prism, as seed 003 draws branches); clamped to
    /// `3..=256`.
    pub radial_segments: u32,
    /// Latitude bands of a sphere (default 6); a sphere has twice as many longitude segments. Clamped to
    /// `2..=128`.
    pub sphere_rings: u32,
    /// Close the ends of cones and cylinders (default true), making them watertight.
    pub caps: bool,
}

impl Default for MeshOptions {
    fn default() -> Self {
        MeshOptions { radial_segments: 8, sphere_rings: 6, caps: true }
    }
}

impl MeshOptions {
    /// Options for a detail level (0 is full detail, as in [`crate::amplify::Instance::detail`]): each step up
    /// removes two radial segments (8, 6, 4, then 3) and two sphere rings (6, 4, then 2).
    pub fn for_detail(detail: u8) -> MeshOptions {
        let d = u32::from(detail);
        MeshOptions {
            radial_segments: 8u32.saturating_sub(2 * d).max(3),
            sphere_rings: 6u32.saturating_sub(2 * d).max(2),
            caps: true,
        }
    }

    fn radial(&self) -> u32 {
        self.radial_segments.clamp(3, 256)
    }

    fn rings(&self) -> u32 {
        self.sphere_rings.clamp(2, 128)
    }
}

/// Mesh a primitive stream.
pub fn mesh(stream: &PrimitiveStream, opts: &MeshOptions) -> Mesh {
    let mut out = Mesh::default();
    mesh_into(stream, opts, &mut out);
    out
}

/// Like [`mesh`], but appends to `out` (reuse its allocations; clear it first for a fresh mesh). Indices of the
/// new triangles refer to the new vertices, wherever they land in `out`.
pub fn mesh_into(stream: &PrimitiveStream, opts: &MeshOptions, out: &mut Mesh) {
    mesh_into_where(stream, opts, |_, _| true, out);
}

/// Like [`mesh_into`], but only the primitives `keep` accepts (given each one's index in the stream and itself):
/// the same triangles as meshing a copy of the stream that holds just those primitives (and every leaf point),
/// without making the copy.
pub fn mesh_into_where(
    stream: &PrimitiveStream,
    opts: &MeshOptions,
    keep: impl Fn(usize, &Primitive) -> bool,
    out: &mut Mesh,
) {
    let tables = Tables::new(opts);
    for (_, p) in stream.primitives.iter().enumerate().filter(|(i, p)| keep(*i, p)) {
        let (nv, ni) = (out.positions.len(), out.indices.len());
        let ok = primitive(stream, p, &tables, opts.caps, out);
        if !ok {
            out.positions.truncate(nv);
            out.normals.truncate(nv);
            out.colors.truncate(nv);
            out.indices.truncate(ni);
        }
    }
}

/// The explicit-geometry size of a stream in bytes, as seed 001 §7 counts it to compare against the species
/// graph: 4 bytes per float, and
/// - a cone or cylinder: 7 floats (bottom centre, top centre, radius);
/// - a sphere: 4 floats (centre, radius);
/// - a box: 12 triangles of 3 vertices of 3 floats (432 bytes);
/// - a trunk base: the triangles of its surface, 3 vertices of 3 floats each;
/// - a leaf polygon of `n` points: `n − 2` fan triangles of 3 vertices of 3 floats; a leaf strip of `n` points:
///   `n − 2` triangles likewise (nothing for fewer than 3 points).
///
/// Every primitive in the stream counts, degenerate or not.
pub fn explicit_bytes(stream: &PrimitiveStream) -> usize {
    const FLOAT: usize = 4;
    const TRIANGLE: usize = 3 * 3 * FLOAT;
    stream
        .primitives
        .iter()
        .map(|p| match p.shape {
            Shape::Cone { .. } | Shape::Cylinder { .. } => 7 * FLOAT,
            Shape::Sphere { .. } => 4 * FLOAT,
            Shape::Box { .. } => 12 * TRIANGLE,
            Shape::Leaf { start, end, .. } => (end.saturating_sub(start) as usize).saturating_sub(2) * TRIANGLE,
            Shape::TrunkBase(b) => b.triangle_count() * TRIANGLE,
        })
        .sum()
}

/// Unit-circle tables for one set of options.
struct Tables {
    /// Radial segments around cones and cylinders.
    radial: usize,
    /// `(cos, sin)` of `k · π / radial` for `k` in `0..2 · radial`: even `k` are the ring, odd `k` the midpoints.
    circle: Vec<(f32, f32)>,
    /// Sphere latitude bands.
    rings: usize,
    /// `(cos, sin)` of `j · π / rings` for `j` in `0..=rings` (latitude from the north pole).
    latitude: Vec<(f32, f32)>,
    /// `(cos, sin)` of `i · π / rings` for `i` in `0..2 · rings` (longitude).
    longitude: Vec<(f32, f32)>,
}

impl Tables {
    fn new(opts: &MeshOptions) -> Tables {
        let (radial, rings) = (opts.radial(), opts.rings());
        let table = |steps: u32, count: u32| -> Vec<(f32, f32)> {
            let step = core::f32::consts::PI / steps as f32;
            (0..count)
                .map(|k| {
                    let a = k as f32 * step;
                    (libm::cosf(a), libm::sinf(a))
                })
                .collect()
        };
        Tables {
            radial: radial as usize,
            circle: table(radial, 2 * radial),
            rings: rings as usize,
            latitude: table(rings, rings + 1),
            longitude: table(rings, 2 * rings),
        }
    }
}

/// Writes one primitive's vertices and triangles into the mesh, in species space.
struct Emitter<'a> {
    out: &'a mut Mesh,
    transform: Transform,
    normal_matrix: [[f32; 3]; 3],
    mirror: bool,
    color: [f32; 3],
    finite: bool,
}

impl Emitter<'_> {
    /// Add a vertex from a local position and a local unit normal; returns its index.
    fn vertex(&mut self, p: [f32; 3], n: [f32; 3]) -> u32 {
        let i = self.out.positions.len() as u32;
        let w = self.transform.point(p);
        self.finite &= w.iter().all(|x| x.is_finite());
        let m = &self.normal_matrix;
        let mut wn = [
            m[0][0] * n[0] + m[0][1] * n[1] + m[0][2] * n[2],
            m[1][0] * n[0] + m[1][1] * n[1] + m[1][2] * n[2],
            m[2][0] * n[0] + m[2][1] * n[1] + m[2][2] * n[2],
        ];
        if self.mirror {
            wn = [-wn[0], -wn[1], -wn[2]];
        }
        let wn = normalize(wn).unwrap_or([0.0, 1.0, 0.0]);
        self.out.positions.push(w);
        self.out.normals.push(wn);
        self.out.colors.push(self.color);
        i
    }

    /// Add a triangle, counter-clockwise in the local frame (reversed under a mirroring transform).
    fn tri(&mut self, a: u32, b: u32, c: u32) {
        if self.mirror {
            self.out.indices.extend_from_slice(&[a, c, b]);
        } else {
            self.out.indices.extend_from_slice(&[a, b, c]);
        }
    }
}

/// A size is usable when it is positive and finite.
fn size_ok(x: f32) -> bool {
    x > 0.0 && x.is_finite()
}

/// A colour channel clamped to `0..=1`, NaN to 0 (glTF requires clamped vertex colours).
fn channel(x: f32) -> f32 {
    if x > 0.0 { x.min(1.0) } else { 0.0 }
}

/// Mesh one primitive; false when it is degenerate (the caller rolls back whatever was written).
fn primitive(stream: &PrimitiveStream, p: &Primitive, tables: &Tables, caps: bool, out: &mut Mesh) -> bool {
    if !p.transform.m.iter().all(|x| x.is_finite()) {
        return false;
    }
    let det = p.transform.determinant();
    let mut e = Emitter {
        out,
        transform: p.transform,
        normal_matrix: p.transform.normal_matrix(),
        mirror: det < 0.0,
        color: [channel(p.color[0]), channel(p.color[1]), channel(p.color[2])],
        finite: true,
    };
    let ok = match p.shape {
        Shape::Cone { bottom, top, height } => frustum(&mut e, tables, bottom, top, height, caps),
        Shape::Cylinder { radius, height } => size_ok(radius) && frustum(&mut e, tables, radius, radius, height, caps),
        Shape::Sphere { radius } => sphere(&mut e, tables, radius),
        Shape::Box { size } => cuboid(&mut e, size),
        Shape::Leaf { topology, start, end } => match stream.leaf_points.get(start as usize..end as usize) {
            Some(points) => match topology {
                LeafTopology::Polygon => polygon(&mut e, points),
                LeafTopology::Strip => strip(&mut e, points),
            },
            None => false,
        },
        Shape::TrunkBase(b) => trunk_base(&mut e, &b),
    };
    ok && e.finite
}

/// A frustum (cone, truncated cone or cylinder) on the origin along +Y; a zero radius makes an apex.
fn frustum(e: &mut Emitter<'_>, t: &Tables, bottom: f32, top: f32, height: f32, caps: bool) -> bool {
    let radius_ok = |r: f32| r >= 0.0 && r.is_finite();
    if !size_ok(height) || !radius_ok(bottom) || !radius_ok(top) || !(bottom > 0.0 || top > 0.0) {
        return false;
    }
    let n = t.radial;
    let ring = |k: usize| t.circle[2 * (k % n)];
    let mid = |k: usize| t.circle[2 * k + 1];
    // The side normal in the (radial, y) plane: perpendicular to the slant (bottom → top).
    let Some([a, b, _]) = normalize([height, bottom - top, 0.0]) else {
        return false;
    };
    let side = |(c, s): (f32, f32)| [a * c, b, a * s];
    let at = |(c, s): (f32, f32), r: f32, y: f32| [r * c, y, r * s];

    if bottom > 0.0 && top > 0.0 {
        let b0 = e.out.positions.len() as u32;
        for k in 0..n {
            e.vertex(at(ring(k), bottom, 0.0), side(ring(k)));
        }
        let t0 = e.out.positions.len() as u32;
        for k in 0..n {
            e.vertex(at(ring(k), top, height), side(ring(k)));
        }
        for k in 0..n as u32 {
            let j = (k + 1) % n as u32;
            e.tri(b0 + k, t0 + k, b0 + j);
            e.tri(b0 + j, t0 + k, t0 + j);
        }
    } else if top == 0.0 {
        // Apex on top: one apex vertex per segment, with the normal of the segment's middle.
        let b0 = e.out.positions.len() as u32;
        for k in 0..n {
            e.vertex(at(ring(k), bottom, 0.0), side(ring(k)));
        }
        let a0 = e.out.positions.len() as u32;
        for k in 0..n {
            e.vertex([0.0, height, 0.0], side(mid(k)));
        }
        for k in 0..n as u32 {
            e.tri(b0 + k, a0 + k, b0 + (k + 1) % n as u32);
        }
    } else {
        // Apex at the bottom.
        let a0 = e.out.positions.len() as u32;
        for k in 0..n {
            e.vertex([0.0, 0.0, 0.0], side(mid(k)));
        }
        let t0 = e.out.positions.len() as u32;
        for k in 0..n {
            e.vertex(at(ring(k), top, height), side(ring(k)));
        }
        for k in 0..n as u32 {
            e.tri(a0 + k, t0 + k, t0 + (k + 1) % n as u32);
        }
    }

    if caps {
        for (r, y, ny) in [(bottom, 0.0, -1.0), (top, height, 1.0)] {
            if r == 0.0 {
                continue;
            }
            let c = e.vertex([0.0, y, 0.0], [0.0, ny, 0.0]);
            let r0 = e.out.positions.len() as u32;
            for k in 0..n {
                e.vertex(at(ring(k), r, y), [0.0, ny, 0.0]);
            }
            for k in 0..n as u32 {
                let j = (k + 1) % n as u32;
                if ny < 0.0 {
                    e.tri(c, r0 + k, r0 + j);
                } else {
                    e.tri(c, r0 + j, r0 + k);
                }
            }
        }
    }
    true
}

/// A UV sphere centred on the origin: `rings` latitude bands, `2 · rings` longitude segments, one vertex at
/// each pole.
fn sphere(e: &mut Emitter<'_>, t: &Tables, radius: f32) -> bool {
    if !size_ok(radius) {
        return false;
    }
    let (rings, segs) = (t.rings, t.longitude.len());
    let north = e.vertex([0.0, radius, 0.0], [0.0, 1.0, 0.0]);
    let first = e.out.positions.len() as u32;
    for &(cp, sp) in &t.latitude[1..rings] {
        for &(ct, st) in &t.longitude {
            let n = [sp * ct, cp, sp * st];
            e.vertex([radius * n[0], radius * n[1], radius * n[2]], n);
        }
    }
    let south = e.vertex([0.0, -radius, 0.0], [0.0, -1.0, 0.0]);
    let segs32 = segs as u32;
    let at = |ring: usize, k: u32| first + (ring as u32) * segs32 + k % segs32;
    for k in 0..segs32 {
        e.tri(at(0, k), north, at(0, k + 1));
    }
    for ring in 0..rings - 2 {
        let (u, l) = (ring, ring + 1);
        for k in 0..segs32 {
            e.tri(at(l, k), at(u, k), at(l, k + 1));
            e.tri(at(l, k + 1), at(u, k), at(u, k + 1));
        }
    }
    for k in 0..segs32 {
        e.tri(south, at(rings - 2, k), at(rings - 2, k + 1));
    }
    true
}

/// A box centred on the origin: four vertices per face with the face's normal, two triangles per face.
fn cuboid(e: &mut Emitter<'_>, size: [f32; 3]) -> bool {
    if !size.iter().all(|&s| size_ok(s)) {
        return false;
    }
    let h = [size[0] * 0.5, size[1] * 0.5, size[2] * 0.5];
    for axis in 0..3 {
        for sign in [1.0f32, -1.0] {
            // Tangent axes (u, v) with u × v = the outward normal.
            let (u, v) = if sign > 0.0 { ((axis + 1) % 3, (axis + 2) % 3) } else { ((axis + 2) % 3, (axis + 1) % 3) };
            let mut normal = [0.0f32; 3];
            normal[axis] = sign;
            let first = e.out.positions.len() as u32;
            for (su, sv) in [(-1.0f32, -1.0f32), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                let mut p = [0.0f32; 3];
                p[axis] = sign * h[axis];
                p[u] = su * h[u];
                p[v] = sv * h[v];
                e.vertex(p, normal);
            }
            e.tri(first, first + 1, first + 2);
            e.tri(first, first + 2, first + 3);
        }
    }
    true
}

/// A trunk–root junction: its closed surface from [`crate::nearfield::trunkbase`], false when its sizes are bad.
fn trunk_base(e: &mut Emitter<'_>, b: &crate::nearfield::TrunkBase) -> bool {
    let Ok(s) = b.surface() else { return false };
    let first = e.out.positions.len() as u32;
    for (&p, &n) in s.positions.iter().zip(&s.normals) {
        e.vertex(p, n);
    }
    for t in s.indices.chunks_exact(3) {
        e.tri(first + t[0], first + t[1], first + t[2]);
    }
    true
}

/// A convex leaf polygon, fan-triangulated from point 0, with its Newell normal on every vertex.
fn polygon(e: &mut Emitter<'_>, points: &[[f32; 3]]) -> bool {
    if points.len() < 3 || !points.iter().flatten().all(|x| x.is_finite()) {
        return false;
    }
    let mut sum = [0.0f32; 3];
    for (i, &a) in points.iter().enumerate() {
        let b = points[(i + 1) % points.len()];
        sum[0] += (a[1] - b[1]) * (a[2] + b[2]);
        sum[1] += (a[2] - b[2]) * (a[0] + b[0]);
        sum[2] += (a[0] - b[0]) * (a[1] + b[1]);
    }
    let Some(normal) = normalize(sum) else {
        return false;
    };
    let first = e.out.positions.len() as u32;
    for &p in points {
        e.vertex(p, normal);
    }
    for i in 1..points.len() as u32 - 1 {
        e.tri(first, first + i, first + i + 1);
    }
    true
}

/// A leaf triangle strip: triangle `k` is `(k, k+1, k+2)` for even `k` and `(k+1, k, k+2)` for odd `k`, so all
/// are wound alike. Vertex normals average the unit normals of the triangles that use the vertex.
fn strip(e: &mut Emitter<'_>, points: &[[f32; 3]]) -> bool {
    if points.len() < 3 || !points.iter().flatten().all(|x| x.is_finite()) {
        return false;
    }
    let n = points.len();
    let corners = |k: usize| if k.is_multiple_of(2) { [k, k + 1, k + 2] } else { [k + 1, k, k + 2] };
    let mut sums = vec![[0.0f32; 3]; n];
    let mut total = [0.0f32; 3];
    for k in 0..n - 2 {
        let [a, b, c] = corners(k);
        let Some(f) = normalize(cross(sub(points[b], points[a]), sub(points[c], points[a]))) else {
            continue;
        };
        for i in [a, b, c] {
            for d in 0..3 {
                sums[i][d] += f[d];
            }
        }
        for d in 0..3 {
            total[d] += f[d];
        }
    }
    let Some(fallback) = normalize(total) else {
        return false;
    };
    let first = e.out.positions.len() as u32;
    for (&p, &s) in points.iter().zip(&sums) {
        e.vertex(p, normalize(s).unwrap_or(fallback));
    }
    for k in 0..n - 2 {
        let [a, b, c] = corners(k);
        e.tri(first + a as u32, first + b as u32, first + c as u32);
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::dot;
    use std::collections::BTreeMap;

    fn prim(shape: Shape, transform: Transform) -> Primitive {
        Primitive { shape, transform, color: [0.4, 0.3, 0.2] }
    }

    fn single(shape: Shape, transform: Transform) -> PrimitiveStream {
        PrimitiveStream { primitives: vec![prim(shape, transform)], leaf_points: Vec::new() }
    }

    fn leaf_stream(topology: LeafTopology, points: &[[f32; 3]], transform: Transform) -> PrimitiveStream {
        PrimitiveStream {
            primitives: vec![Primitive {
                shape: Shape::Leaf { topology, start: 0, end: points.len() as u32 },
                transform,
                color: [0.1, 0.6, 0.1],
            }],
            leaf_points: points.to_vec(),
        }
    }

    fn tilted() -> Transform {
        Transform::translation(1.0, 2.0, -3.0)
            .mul(&Transform::rotation([0.3, 1.0, 0.2], 37.0))
            .mul(&Transform::scale(1.5, 0.7, 2.0))
    }

    fn mirrored() -> Transform {
        Transform::translation(-2.0, 0.5, 1.0).mul(&Transform::scale(-1.0, 2.0, 1.0))
    }

    /// Every edge, keyed by its endpoints' bit patterns, must appear exactly once in each direction.
    fn assert_watertight(m: &Mesh) {
        let key = |i: u32| m.positions[i as usize].map(f32::to_bits);
        let mut edges: BTreeMap<([u32; 3], [u32; 3]), i32> = BTreeMap::new();
        for t in m.indices.chunks(3) {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *edges.entry((key(a), key(b))).or_default() += 1;
            }
        }
        for (&(a, b), &count) in &edges {
            assert_eq!(count, 1, "edge {a:?} → {b:?} used {count} times in one direction");
            assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a:?} → {b:?} has no opposite");
        }
    }

    /// Normals are unit length, and every triangle's winding agrees with its vertices' normals.
    fn assert_consistent(m: &Mesh) {
        assert_eq!(m.positions.len(), m.normals.len());
        assert_eq!(m.positions.len(), m.colors.len());
        for n in &m.normals {
            assert!((dot(*n, *n).sqrt() - 1.0).abs() < 1e-5, "normal {n:?} is not unit length");
        }
        for t in m.indices.chunks(3) {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| m.positions[i as usize]);
            let face = cross(sub(b, a), sub(c, a));
            for &i in t {
                assert!(dot(face, m.normals[i as usize]) > 0.0, "triangle {t:?} is wound against its normals");
            }
        }
    }

    #[test]
    fn cylinder_with_8_segments_has_expected_counts() {
        let s = single(Shape::Cylinder { radius: 0.5, height: 2.0 }, Transform::IDENTITY);
        let m = mesh(&s, &MeshOptions::default());
        // Side: 8 bottom + 8 top vertices, 16 triangles; each cap: centre + 8 ring vertices, 8 triangles.
        assert_eq!(m.vertex_count(), 16 + 2 * 9);
        assert_eq!(m.triangle_count(), 16 + 2 * 8);
        let open = mesh(&s, &MeshOptions { caps: false, ..MeshOptions::default() });
        assert_eq!((open.vertex_count(), open.triangle_count()), (16, 16));
        let (lo, hi) = m.bounds();
        assert_eq!((lo[1], hi[1]), (0.0, 2.0));
        assert!((hi[0] - 0.5).abs() < 1e-6 && (lo[0] + 0.5).abs() < 1e-6);
    }

    #[test]
    fn all_shapes_have_unit_normals_and_consistent_winding() {
        for t in [Transform::IDENTITY, tilted(), mirrored()] {
            for shape in [
                Shape::Cylinder { radius: 0.5, height: 2.0 },
                Shape::Cone { bottom: 0.5, top: 0.2, height: 1.0 },
                Shape::Cone { bottom: 0.5, top: 0.0, height: 1.0 },
                Shape::Cone { bottom: 0.0, top: 0.3, height: 1.0 },
                Shape::Sphere { radius: 0.8 },
                Shape::Box { size: [1.0, 2.0, 0.5] },
            ] {
                for opts in [MeshOptions::default(), MeshOptions::for_detail(5)] {
                    let m = mesh(&single(shape.clone(), t), &opts);
                    assert!(m.triangle_count() > 0, "{shape:?}");
                    assert_consistent(&m);
                    assert_watertight(&m);
                }
            }
        }
    }

    #[test]
    fn closed_cylinder_is_watertight() {
        let s = single(Shape::Cylinder { radius: 0.25, height: 3.0 }, tilted());
        assert_watertight(&mesh(&s, &MeshOptions::default()));
    }

    #[test]
    fn mirrored_sphere_keeps_outward_normals() {
        let t = mirrored();
        assert!(t.determinant() < 0.0);
        let m = mesh(&single(Shape::Sphere { radius: 1.0 }, t), &MeshOptions::default());
        let centre = t.point([0.0; 3]);
        for (p, n) in m.positions.iter().zip(&m.normals) {
            assert!(dot(*n, sub(*p, centre)) > 0.0, "normal {n:?} at {p:?} points inward");
        }
        assert_consistent(&m);
        // 2 poles + 5 rings of 12; 12 · 2 fan triangles + 4 bands of 24.
        assert_eq!((m.vertex_count(), m.triangle_count()), (2 + 5 * 12, 24 + 4 * 24));
    }

    #[test]
    fn leaf_strip_winding_is_consistent() {
        // A zig-zag strip in the xy plane, bent up along z at the end.
        let pts =
            [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 2.0, 0.5], [1.0, 2.0, 0.5]];
        for t in [Transform::IDENTITY, tilted(), mirrored()] {
            let m = mesh(&leaf_stream(LeafTopology::Strip, &pts, t), &MeshOptions::default());
            assert_eq!((m.vertex_count(), m.triangle_count()), (6, 4));
            assert_consistent(&m);
            // Interior edges appear once in each direction.
            let mut directed = BTreeMap::new();
            for tri in m.indices.chunks(3) {
                for (a, b) in [(tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])] {
                    assert!(directed.insert((a, b), ()).is_none(), "edge {a} → {b} twice: inconsistent winding");
                }
            }
        }
        // Identity: the first triangle faces +z (counter-clockwise seen from above).
        let m = mesh(&leaf_stream(LeafTopology::Strip, &pts, Transform::IDENTITY), &MeshOptions::default());
        assert!(m.normals[0][2] > 0.9);
    }

    #[test]
    fn leaf_polygon_is_a_fan() {
        let pts = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.5, 1.0, 0.0], [0.5, 2.0, 0.0], [-0.5, 1.0, 0.0]];
        let m = mesh(&leaf_stream(LeafTopology::Polygon, &pts, tilted()), &MeshOptions::default());
        assert_eq!((m.vertex_count(), m.triangle_count()), (5, 3));
        assert_eq!(m.indices, [0, 1, 2, 0, 2, 3, 0, 3, 4]);
        assert_consistent(&m);
    }

    #[test]
    fn degenerate_primitives_are_skipped() {
        let nan = f32::NAN;
        let mut s = PrimitiveStream::default();
        for shape in [
            Shape::Cylinder { radius: 0.0, height: 1.0 },
            Shape::Cylinder { radius: 1.0, height: -1.0 },
            Shape::Cylinder { radius: nan, height: 1.0 },
            Shape::Cone { bottom: 0.0, top: 0.0, height: 1.0 },
            Shape::Cone { bottom: -1.0, top: 1.0, height: 1.0 },
            Shape::Cone { bottom: 1.0, top: 1.0, height: f32::INFINITY },
            Shape::Sphere { radius: 0.0 },
            Shape::Sphere { radius: nan },
            Shape::Box { size: [1.0, 0.0, 1.0] },
            Shape::Box { size: [1.0, nan, 1.0] },
            Shape::Leaf { topology: LeafTopology::Polygon, start: 0, end: 3 },
            Shape::Leaf { topology: LeafTopology::Strip, start: 0, end: 3 },
            Shape::Leaf { topology: LeafTopology::Polygon, start: 3, end: 5 },
            Shape::Leaf { topology: LeafTopology::Strip, start: 5, end: 99 },
        ] {
            s.primitives.push(prim(shape, Transform::IDENTITY));
        }
        // Collinear points: no area.
        s.leaf_points.extend([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [0.0; 3], [1.0; 3]]);
        // A good sphere under a non-finite or overflowing transform.
        let mut bad = Transform::IDENTITY;
        bad.m[3] = nan;
        s.primitives.push(prim(Shape::Sphere { radius: 1.0 }, bad));
        s.primitives.push(prim(Shape::Sphere { radius: 1e30 }, Transform::scale(1e30, 1.0, 1.0)));
        let m = mesh(&s, &MeshOptions::default());
        assert!(m.is_empty() && m.positions.is_empty(), "{m:?}");
        // A good primitive after the bad ones still meshes, with its indices starting at 0.
        s.primitives.push(prim(Shape::Box { size: [1.0; 3] }, Transform::IDENTITY));
        let m = mesh(&s, &MeshOptions::default());
        assert_eq!((m.vertex_count(), m.triangle_count()), (24, 12));
        assert!(m.positions.iter().chain(&m.normals).flatten().all(|x| x.is_finite()));
    }

    #[test]
    fn colours_are_clamped() {
        let mut s = single(Shape::Sphere { radius: 1.0 }, Transform::IDENTITY);
        s.primitives[0].color = [1.5, f32::NAN, -0.5];
        let m = mesh(&s, &MeshOptions::default());
        assert!(m.colors.iter().all(|c| *c == [1.0, 0.0, 0.0]));
    }

    #[test]
    fn append_offsets_positions_and_indices() {
        let a = mesh(&single(Shape::Box { size: [1.0; 3] }, Transform::IDENTITY), &MeshOptions::default());
        let mut grove = a.clone();
        grove.append(&a, [10.0, 0.0, 0.0]);
        assert_eq!((grove.vertex_count(), grove.triangle_count()), (48, 24));
        assert_eq!(grove.indices[36], a.indices[0] + 24);
        assert_eq!(grove.bounds(), ([-0.5; 3], [10.5, 0.5, 0.5]));
        assert_eq!(Mesh::new().bounds(), ([0.0; 3], [0.0; 3]));
    }

    #[test]
    fn options_for_detail_lower_counts() {
        assert_eq!(MeshOptions::for_detail(0), MeshOptions::default());
        let counts: Vec<(u32, u32)> =
            (0..5).map(MeshOptions::for_detail).map(|o| (o.radial_segments, o.sphere_rings)).collect();
        assert_eq!(counts, [(8, 6), (6, 4), (4, 2), (3, 2), (3, 2)]);
        assert_eq!(MeshOptions::for_detail(255).radial_segments, 3);
    }

    #[test]
    fn explicit_bytes_counts_as_seed_001() {
        let mut s = leaf_stream(LeafTopology::Polygon, &[[0.0; 3]; 5], Transform::IDENTITY);
        s.primitives.push(prim(Shape::Leaf { topology: LeafTopology::Strip, start: 0, end: 4 }, Transform::IDENTITY));
        s.primitives.push(prim(Shape::Cone { bottom: 1.0, top: 0.5, height: 1.0 }, Transform::IDENTITY));
        s.primitives.push(prim(Shape::Cylinder { radius: 1.0, height: 1.0 }, Transform::IDENTITY));
        s.primitives.push(prim(Shape::Sphere { radius: 1.0 }, Transform::IDENTITY));
        s.primitives.push(prim(Shape::Box { size: [1.0; 3] }, Transform::IDENTITY));
        assert_eq!(explicit_bytes(&s), 3 * 36 + 2 * 36 + 28 + 28 + 16 + 12 * 36);
    }

    /// A small fixed stream with every kind of primitive, shared with the golden test.
    fn sample() -> PrimitiveStream {
        let mut s = PrimitiveStream::default();
        s.primitives.push(prim(Shape::Cylinder { radius: 0.1, height: 1.0 }, Transform::IDENTITY));
        let up = Transform::translation(0.0, 1.0, 0.0).mul(&Transform::rotation([0.0, 0.0, 1.0], 30.0));
        s.primitives.push(prim(Shape::Cone { bottom: 0.1, top: 0.05, height: 0.8 }, up));
        s.primitives.push(prim(Shape::Sphere { radius: 0.3 }, up.translated(0.0, 0.8, 0.0)));
        s.primitives.push(prim(Shape::Box { size: [0.2, 0.1, 0.3] }, mirrored()));
        s.leaf_points.extend([[0.0, 0.0, 0.0], [0.1, 0.1, 0.0], [0.0, 0.3, 0.0], [-0.1, 0.1, 0.0]]);
        s.primitives.push(Primitive {
            shape: Shape::Leaf { topology: LeafTopology::Polygon, start: 0, end: 4 },
            transform: up,
            color: [0.2, 0.7, 0.1],
        });
        s
    }

    #[test]
    fn golden_hash_of_a_small_stream() {
        let m = mesh(&sample(), &MeshOptions::default());
        assert_eq!((m.vertex_count(), m.triangle_count()), (34 + 34 + 62 + 24 + 4, 32 + 32 + 120 + 12 + 2));
        assert_eq!(m, mesh(&sample(), &MeshOptions::default()));
        assert_eq!(m.hash(), 4_288_507_319_540_419_895, "golden mesh hash changed");
    }
}
