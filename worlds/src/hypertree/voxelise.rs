//! The volumetric interpretation of a species (the future work of §12): an amplified species instance is sampled
//! into a hypervolume with the same levels and depth colouring as an IFS hypertree, so every species gets a
//! far-field volume automatically, deterministic from its instance seed.
//!
//! Solid primitives are sampled at 4×4×4 points per voxel (thin ones — narrower than half a voxel — along their
//! axis, an eighth of a voxel or a radius apart); leaves at points a quarter of a voxel apart on their triangles. Levels come from the primitive's
//! thickness: the thickest wood is level 0 and each halving of thickness one level deeper, up to the branch depth;
//! leaves are the level after it, and a voxel is a leaf voxel where leaves cover more of it than wood. Each level's
//! colour is the mean material colour of its primitives.
//!
//! A voxel's density is how much of it the geometry covers, so that the far field is as open as the tree it stands
//! for (issue 35.3; [`Cover::coverage`]): thin geometry by its mean projected area (Cauchy: a quarter of a solid's
//! surface, half a leaf's area) over the voxel's face, less where the pieces clump, as the sub-cells of the voxel's
//! silhouettes along x, y and z that they cover show; solid wood (sampled 4×4×4) by its silhouettes; each less what
//! its neighbours along the axis cover beyond chance. The density is the `µ` for which the raymarcher's
//! `α = 1 − (1 − µ)^(k·Δs)` across the voxel is that coverage, rounded with its error carried on.

// Negated comparisons are deliberate: they treat NaN as out of range.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use canopy_protocol::hypertree::{DepthColor, MAX_RESOLUTION, MAX_TREE_DEPTH};
use canopy_protocol::{LeafTopology, SpeciesGraph};

use std::collections::HashMap;

use super::generate::MAX_DENSE_VOXELS;
use super::render::REFERENCE_STEP;
use super::storage::{BrickMap, VoxelList, VoxelStore};
use super::{Bounds, Flow, Hypertree, Hypervolume, StorageType, Voxel};
use crate::amplify::{AmplifyError, Budget, Instance, amplify};
use crate::primitive::{Primitive, PrimitiveStream, Shape};
use crate::vec3::{add, cross, norm, sub};

/// How to voxelise.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct VoxeliseOptions {
    /// Voxels along the longest axis (voxels are cubes).
    pub resolution: u32,
    /// Wood levels 0..=this; leaves are the level after.
    pub branch_depth: u8,
    /// The storage structure.
    pub storage: StorageType,
    /// Most sample points (bounds the work for any species).
    pub max_samples: u64,
    /// Most voxels covered (bounds the memory: what covers each is about a hundred bytes while it runs).
    pub max_covered: usize,
}

impl Default for VoxeliseOptions {
    fn default() -> Self {
        VoxeliseOptions {
            resolution: 200,
            branch_depth: 3,
            storage: StorageType::IndexBits,
            max_samples: 200_000_000,
            max_covered: 4_000_000,
        }
    }
}

/// Why voxelisation was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VoxeliseError {
    /// Resolution out of range.
    #[error("resolution {0} (allowed 1..={MAX_RESOLUTION})")]
    Resolution(u32),
    /// The branch depth is out of range.
    #[error("{0} is out of range")]
    Parameter(&'static str),
    /// The instance has no primitives, or their bounds are not finite.
    #[error("the instance has no finite geometry to voxelise")]
    Empty,
    /// Too many sample points.
    #[error("more than {0} sample points")]
    Samples(u64),
    /// Too many voxels are covered (each is about a hundred bytes while it is voxelised).
    #[error("more than {0} voxels covered (lower the resolution)")]
    Covered(usize),
    /// A dense array would be too large.
    #[error("a dense array of {0} voxels exceeds {MAX_DENSE_VOXELS}")]
    DenseTooLarge(u64),
    /// Amplification failed.
    #[error("amplification failed: {0}")]
    Amplify(#[from] AmplifyError),
}

/// Amplify `instance` of `graph` under `budget` and voxelise it.
pub fn voxelise_species(
    graph: &SpeciesGraph,
    instance: &Instance,
    budget: &Budget,
    opts: &VoxeliseOptions,
) -> Result<Hypertree, VoxeliseError> {
    let stream = amplify(graph, instance, budget)?;
    voxelise(&stream, &graph.name, opts)
}

/// World-space thickness of a wood primitive (radius times lateral scale), or `None` for leaves.
fn thickness(p: &Primitive) -> Option<f32> {
    let lateral = 0.5 * (p.transform.axis_scale(0) + p.transform.axis_scale(2));
    match solid_shape(&p.shape) {
        Shape::Cone { bottom, top, .. } => Some(bottom.max(top) * lateral),
        Shape::Cylinder { radius, .. } => Some(radius * lateral),
        Shape::Sphere { radius } => Some(radius * p.transform.max_axis_scale()),
        Shape::Box { size } => Some(0.5 * size[0].min(size[2]) * lateral),
        Shape::Leaf { .. } => None,
        Shape::TrunkBase(_) => unreachable!("solid_shape turns a trunk base into a cone"),
    }
}

/// A trunk base (seed 002) is voxelised as the frustum that holds its flares; every other shape as itself.
fn solid_shape(shape: &Shape) -> Shape {
    match shape {
        Shape::TrunkBase(b) => {
            let (bottom, top, height) = b.bounding_cone();
            Shape::Cone { bottom, top, height }
        }
        other => other.clone(),
    }
}

/// Whether the local point `q` is inside `shape`, a [`solid_shape`] (never a trunk base).
fn inside(shape: &Shape, q: [f32; 3]) -> bool {
    match *shape {
        Shape::Cone { bottom, top, height } => {
            if !(q[1] >= 0.0 && q[1] <= height) || height <= 0.0 {
                return false;
            }
            let r = bottom + (top - bottom) * (q[1] / height);
            q[0] * q[0] + q[2] * q[2] <= r * r
        }
        Shape::Cylinder { radius, height } => {
            q[1] >= 0.0 && q[1] <= height && q[0] * q[0] + q[2] * q[2] <= radius * radius
        }
        Shape::Sphere { radius } => q[0] * q[0] + q[1] * q[1] + q[2] * q[2] <= radius * radius,
        Shape::Box { size } => (0..3).all(|i| q[i].abs() <= 0.5 * size[i]),
        Shape::Leaf { .. } => false,
        Shape::TrunkBase(_) => unreachable!("solid_shape turns a trunk base into a cone"),
    }
}

/// Sample points per voxel edge inside thick solids (4 × 4 × 4 a voxel, each marking 2 × 2 sub-cells of a
/// silhouette: `MASK / 2`).
const SOLID_SAMPLES: u32 = MASK / 2;

/// The mean projected area of a solid primitive seen from every direction, world units² (Cauchy: a convex body's
/// is a quarter of its surface).
fn projected_area(p: &Primitive) -> f32 {
    let lateral = 0.5 * (p.transform.axis_scale(0) + p.transform.axis_scale(2));
    let frustum = |bottom: f32, top: f32, height: f32| {
        let (rb, rt, l) = (bottom * lateral, top * lateral, height * p.transform.axis_scale(1));
        0.25 * std::f32::consts::PI * ((rb + rt) * l + rb * rb + rt * rt)
    };
    match solid_shape(&p.shape) {
        Shape::Cone { bottom, top, height } => frustum(bottom, top, height),
        Shape::Cylinder { radius, height } => frustum(radius, radius, height),
        Shape::Sphere { radius } => {
            let r = radius * p.transform.max_axis_scale();
            std::f32::consts::PI * r * r
        }
        Shape::Box { size } => {
            let s: [f32; 3] = std::array::from_fn(|i| size[i] * p.transform.axis_scale(i));
            0.5 * (s[0] * s[1] + s[1] * s[2] + s[2] * s[0])
        }
        Shape::Leaf { .. } => 0.0,
        Shape::TrunkBase(_) => unreachable!("solid_shape turns a trunk base into a cone"),
    }
}

/// Sub-cells along a voxel's edge in its silhouettes.
const MASK: u32 = 8;
/// Samples per voxel edge on leaves (each marks the 2 × 2 sub-cells around it: the gaps between them closed).
const LEAF_SPACING: u32 = MASK / 2;

/// What covers one voxel.
#[derive(Clone, Copy, Debug, Default)]
struct Cover {
    /// The shallowest level of what covers it (the thickest wood, or leaves).
    level: u8,
    /// Optical depth of thin wood and of leaves: projected area over the voxel's face.
    depth: [f32; 2],
    /// The voxel's silhouette seen along x, y and z: the `MASK × MASK` sub-cells the thin geometry's samples fall
    /// in (a thin branch's marking its width).
    union: [u64; 3],
    /// The same counted primitive by primitive and summed: the sub-cells they would cover if none hid another.
    sum: [u32; 3],
    /// The silhouettes of the solid wood inside the voxel.
    solid: [u64; 3],
}

/// The voxel silhouettes around one voxel: before and after it along x, y and z, of its thin geometry and of its
/// solid wood.
type Around = [[[u64; 2]; 2]; 3];

impl Cover {
    /// How much of the voxel its geometry covers, seen along x, y and z (the mean of the three).
    ///
    /// Thin geometry covers Beer–Lambert's `1 − e^(−τ·Ω)`, with `Ω` (at most 1) how much less the pieces cover than
    /// if they were placed at random — the optical depth of the sub-cells they cover over that of the sum of each
    /// one's: needles in a tuft hide much of one another — and never more than the sub-cells they cover (a thin
    /// layer of leaves covers only its band of the voxel, however dense it is). Solid wood covers its silhouette.
    /// Each less the part its neighbours along the axis cover beyond chance, half of it for each: a twig seen end on
    /// covers the same spot in every voxel it runs through, the flank of a trunk the same strip, and the raymarcher
    /// takes voxels along a ray as independent.
    fn coverage(&self, around: &Around) -> f32 {
        let cells = (MASK * MASK) as f32;
        let shared = |m: u64, neighbours: [u64; 2]| -> f32 {
            neighbours
                .iter()
                .map(|&n| {
                    let chance = n.count_ones() as f32 / cells;
                    let seen = (m & n).count_ones() as f32 / m.count_ones().max(1) as f32;
                    if chance < 1.0 { ((seen - chance) / (1.0 - chance)).max(0.0) } else { 0.0 }
                })
                .sum()
        };
        let mut total = 0.0f32;
        for (a, near) in around.iter().enumerate() {
            let (m, solid) = (self.union[a], self.solid[a]);
            let (u, s) = (m.count_ones() as f32 / cells, self.sum[a] as f32 / cells);
            let thin = if s > 0.0 {
                let omega = (-libm::logf(1.0 - u.min(1.0 - 0.5 / cells)) / s).min(1.0);
                let depth = self.depth[0] + self.depth[1];
                (1.0 - libm::expf(-depth * omega)).min(u) * (1.0 - 0.5 * shared(m, near[0]))
            } else {
                0.0
            };
            let wood = solid.count_ones() as f32 / cells * (1.0 - 0.5 * shared(solid, near[1]));
            total += 1.0 - (1.0 - thin) * (1.0 - wood);
        }
        total / 3.0
    }
}

/// The 2 × 2 sub-cells of a `MASK × MASK` silhouette nearest `(u, w)` (sub-cell units).
fn block(u: f32, w: f32) -> u64 {
    let corner = |x: f32| (libm::floorf(x - 0.5).max(0.0) as u32).min(MASK - 2);
    0x0303u64 << (corner(u) * MASK + corner(w))
}

/// The sub-cells of a `MASK × MASK` silhouette within `r` of `(u, w)` (sub-cell units), and always the one that
/// holds it.
fn disc(u: f32, w: f32, r: f32) -> u64 {
    let cell = |x: f32| (x as u32).min(MASK - 1);
    let mut m = 1u64 << (cell(u) * MASK + cell(w));
    if r > 0.5 {
        // Row by row, the run of sub-cells whose centres lie within `r`.
        for i in cell((u - r).max(0.0))..=cell(u + r) {
            let du = i as f32 + 0.5 - u;
            let half = r * r - du * du;
            if half < 0.0 {
                continue;
            }
            let half = libm::sqrtf(half);
            let lo = libm::ceilf(w - half - 0.5).max(0.0);
            let hi = libm::floorf(w + half - 0.5).min((MASK - 1) as f32);
            if hi < lo {
                continue;
            }
            let (lo, hi) = (lo as u32, hi as u32);
            m |= ((1u64 << (hi - lo + 1)) - 1) << (i * MASK + lo);
        }
    }
    m
}

/// Voxel indices hashed by one multiplication: the maps below are keyed by our own samples' voxels, and what they
/// yield does not depend on their order.
#[derive(Clone, Copy, Default)]
struct IndexHasher(u64);

impl std::hash::Hasher for IndexHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
    }

    fn write_u32(&mut self, i: u32) {
        self.0 = u64::from(i).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
}

/// A map from voxel index.
type VoxelMap<V> = HashMap<u32, V, std::hash::BuildHasherDefault<IndexHasher>>;

/// What the latest samples, all in one voxel, add to it (consecutive samples mostly fall in the same voxel).
#[derive(Clone, Copy)]
struct Pending {
    index: u32,
    level: u8,
    depth: [f32; 2],
    masks: [u64; 3],
}

struct Sampler {
    volume: Hypervolume,
    offset: [f32; 3],
    inv: [f32; 3],
    side: f32,
    /// What covers each voxel, by index (looked up, never iterated).
    covers: VoxelMap<Cover>,
    /// The silhouette masks of the primitive being sampled, by voxel index (merged into `covers` when it is done;
    /// iterated, but what it adds does not depend on the order).
    own: VoxelMap<[u64; 3]>,
    /// The latest samples' voxel, not yet in `covers` and `own`.
    pending: Option<Pending>,
    /// Whether the primitive being sampled is a leaf.
    leaf: bool,
    /// The radius a sample of thin wood marks, sub-cells (a leaf sample marks the [`block`] around it).
    radius: f32,
    samples: u64,
    max: u64,
    max_covered: usize,
}

impl Sampler {
    fn budget(&mut self, n: u64) -> Result<(), VoxeliseError> {
        self.samples += n;
        if self.samples > self.max { Err(VoxeliseError::Samples(self.max)) } else { Ok(()) }
    }

    /// A sample of thin geometry carrying `area` (world units²) of projected area.
    fn point(&mut self, p: [f32; 3], level: u8, area: f32) {
        let q: [f32; 3] = std::array::from_fn(|i| p[i] + self.offset[i]);
        if let Some(v) = self.volume.voxel_at(q, self.inv) {
            let index = self.volume.index(v);
            if self.pending.is_none_or(|p| p.index != index) {
                self.commit();
            }
            let p = self.pending.get_or_insert(Pending { index, level, depth: [0.0; 2], masks: [0; 3] });
            p.depth[usize::from(self.leaf)] += area / (self.side * self.side);
            let sub: [f32; 3] =
                std::array::from_fn(|i| ((q[i] * self.inv[i] - v[i] as f32) * MASK as f32).clamp(0.0, MASK as f32));
            let mark = |u: f32, w: f32| if self.leaf { block(u, w) } else { disc(u, w, self.radius) };
            p.masks[0] |= mark(sub[1], sub[2]);
            p.masks[1] |= mark(sub[0], sub[2]);
            p.masks[2] |= mark(sub[0], sub[1]);
        }
    }

    /// What covers voxel `index`, now covered at `level` too.
    fn cover(&mut self, index: u32, level: u8) -> &mut Cover {
        let c = self.covers.entry(index).or_insert(Cover { level, ..Cover::default() });
        c.level = c.level.min(level);
        c
    }

    /// Add the pending samples to their voxel.
    fn commit(&mut self) {
        if let Some(p) = self.pending.take() {
            let c = self.cover(p.index, p.level);
            c.depth[0] += p.depth[0];
            c.depth[1] += p.depth[1];
            let m = self.own.entry(p.index).or_default();
            for (m, add) in m.iter_mut().zip(p.masks) {
                *m |= add;
            }
        }
    }

    /// The primitive is done: add its silhouettes to the voxels', and refuse more than `max_covered` voxels.
    fn flush(&mut self) -> Result<(), VoxeliseError> {
        self.commit();
        for (index, m) in self.own.drain() {
            let c = self.covers.entry(index).or_default();
            for (a, mask) in m.into_iter().enumerate() {
                c.union[a] |= mask;
                c.sum[a] += mask.count_ones();
            }
        }
        let max = self.max_covered;
        if self.covers.len() > max { Err(VoxeliseError::Covered(max)) } else { Ok(()) }
    }

    /// A thin primitive along `a`–`b` whose projected area is `area`.
    fn line(&mut self, a: [f32; 3], b: [f32; 3], level: u8, area: f32) -> Result<(), VoxeliseError> {
        let d = sub(b, a);
        let len = norm(d);
        // A sample every sub-cell, or every radius for a branch wider than that (its discs still join).
        let n = (len * MASK as f32 / (self.side * self.radius.max(1.0))).min(1e7) as u64 + 1;
        self.budget(n + 1)?;
        let share = area / (n + 1) as f32;
        for k in 0..=n {
            let t = k as f32 / n as f32;
            self.point(std::array::from_fn(|i| a[i] + d[i] * t), level, share);
        }
        Ok(())
    }

    /// A leaf triangle: half its area is its mean projected area.
    fn triangle(&mut self, a: [f32; 3], b: [f32; 3], c: [f32; 3], level: u8) -> Result<(), VoxeliseError> {
        let e = |p: [f32; 3], q: [f32; 3]| norm(sub(q, p));
        let longest = e(a, b).max(e(b, c)).max(e(c, a));
        let n = (longest * LEAF_SPACING as f32 / self.side).min(1e4) as u64 + 1;
        let count = (n + 1) * (n + 2) / 2;
        self.budget(count)?;
        let share = 0.25 * norm(cross(sub(b, a), sub(c, a))) / count as f32;
        for i in 0..=n {
            for j in 0..=(n - i) {
                let (u, v) = (i as f32 / n as f32, j as f32 / n as f32);
                let w = 1.0 - u - v;
                self.point(std::array::from_fn(|k| a[k] * w + b[k] * u + c[k] * v), level, share);
            }
        }
        Ok(())
    }

    fn solid(&mut self, p: &Primitive, corners: &[[f32; 3]], level: u8) -> Result<(), VoxeliseError> {
        let Some(inv) = p.transform.inverse() else { return Ok(()) };
        let shape = solid_shape(&p.shape);
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for c in corners {
            let w = p.transform.point(*c);
            for i in 0..3 {
                lo[i] = lo[i].min(w[i] + self.offset[i]);
                hi[i] = hi[i].max(w[i] + self.offset[i]);
            }
        }
        let range: [(u32, u32); 3] = std::array::from_fn(|i| {
            let r = self.volume.resolution[i] as f32;
            let a = (lo[i] * self.inv[i]).clamp(0.0, r - 1.0) as u32;
            let b = (hi[i] * self.inv[i]).clamp(0.0, r - 1.0) as u32;
            (a, b)
        });
        let count: u64 = range.iter().map(|(a, b)| u64::from(b - a + 1)).product();
        let n = SOLID_SAMPLES;
        self.budget(count * u64::from(n * n * n))?;
        let vs = self.volume.voxel_size();
        let mut any = false;
        for z in range[2].0..=range[2].1 {
            for y in range[1].0..=range[1].1 {
                for x in range[0].0..=range[0].1 {
                    let idx = self.volume.index([x, y, z]);
                    let mut masks = [0u64; 3];
                    for s in 0..n * n * n {
                        let sub = [s % n, (s / n) % n, s / (n * n)];
                        let world: [f32; 3] = std::array::from_fn(|i| {
                            ([x, y, z][i] as f32 + (sub[i] as f32 + 0.5) / n as f32) * vs[i] - self.offset[i]
                        });
                        if inside(&shape, inv.point(world)) {
                            // Each sample stands for the 2 × 2 sub-cells of a silhouette around it.
                            let c = sub.map(|c| (2 * c + 1) as f32);
                            masks[0] |= block(c[1], c[2]);
                            masks[1] |= block(c[0], c[2]);
                            masks[2] |= block(c[0], c[1]);
                        }
                    }
                    if masks != [0; 3] {
                        any = true;
                        let c = self.cover(idx, level);
                        for (m, add) in c.solid.iter_mut().zip(masks) {
                            *m |= add;
                        }
                    }
                }
            }
        }
        if !any {
            // Smaller than the sampling grid: keep it as one hit at its centre.
            let mut c = [0.0f32; 3];
            for k in corners {
                for i in 0..3 {
                    c[i] += k[i] / corners.len() as f32;
                }
            }
            self.point(p.transform.point(c), level, projected_area(p));
        }
        Ok(())
    }
}

/// Voxelise a primitive stream (species units, +Y up) into a hypertree.
pub fn voxelise(stream: &PrimitiveStream, name: &str, opts: &VoxeliseOptions) -> Result<Hypertree, VoxeliseError> {
    if opts.resolution == 0 || opts.resolution > MAX_RESOLUTION {
        return Err(VoxeliseError::Resolution(opts.resolution));
    }
    if opts.branch_depth + 2 > MAX_TREE_DEPTH {
        return Err(VoxeliseError::Parameter("branch depth"));
    }
    // The world box of every primitive.
    let (lo, hi) = stream.bounds();
    if stream.primitives.is_empty() || !(0..3).all(|i| lo[i].is_finite() && hi[i].is_finite() && lo[i] <= hi[i]) {
        return Err(VoxeliseError::Empty);
    }
    let ext: [f32; 3] = std::array::from_fn(|i| hi[i] - lo[i]);
    let longest = ext[0].max(ext[1]).max(ext[2]).max(1e-6);
    let pad = 0.02 * longest;
    let side = (longest + 2.0 * pad) / opts.resolution as f32;
    let resolution: [u32; 3] =
        std::array::from_fn(|i| (libm::ceilf((ext[i] + 2.0 * pad) / side) as u32).clamp(1, opts.resolution));
    let volume = Hypervolume { resolution, extent: resolution.map(|r| r as f32 * side) };
    if opts.storage == StorageType::Dense && volume.voxel_count() > MAX_DENSE_VOXELS {
        return Err(VoxeliseError::DenseTooLarge(volume.voxel_count()));
    }
    let offset: [f32; 3] = std::array::from_fn(|i| pad - lo[i]);
    // Levels by thickness.
    let trunk = stream.primitives.iter().filter_map(thickness).fold(0.0f32, f32::max);
    let leaf_level = opts.branch_depth + 1;
    let level_of = |p: &Primitive| -> u8 {
        match thickness(p) {
            None => leaf_level,
            Some(t) if t > 0.0 && trunk > 0.0 => {
                (libm::roundf(libm::log2f(trunk / t)).max(0.0) as u32).min(u32::from(opts.branch_depth)) as u8
            }
            Some(_) => opts.branch_depth,
        }
    };
    let mut sampler = Sampler {
        volume,
        offset,
        inv: [1.0 / side; 3],
        side,
        covers: VoxelMap::default(),
        own: VoxelMap::default(),
        pending: None,
        leaf: false,
        radius: 0.0,
        samples: 0,
        max: opts.max_samples,
        max_covered: opts.max_covered,
    };
    let mut color_sum = vec![([0.0f64; 3], 0u64); usize::from(leaf_level) + 1];
    let mut flows: Vec<(f32, Flow)> = Vec::new();
    for p in &stream.primitives {
        let level = level_of(p);
        let cs = &mut color_sum[usize::from(level)];
        for i in 0..3 {
            cs.0[i] += f64::from(p.color[i]);
        }
        cs.1 += 1;
        sampler.flush()?;
        sampler.leaf = level == leaf_level;
        sampler.radius = 0.0;
        match &p.shape {
            Shape::Leaf { topology, .. } => {
                let pts: Vec<[f32; 3]> = stream.leaf(p).iter().map(|&q| p.transform.point(q)).collect();
                for k in 1..pts.len().saturating_sub(1) {
                    let (a, b, c) = match topology {
                        LeafTopology::Polygon => (pts[0], pts[k], pts[k + 1]),
                        LeafTopology::Strip => (pts[k - 1], pts[k], pts[k + 1]),
                    };
                    sampler.triangle(a, b, c, level)?;
                }
            }
            shape => {
                let t = thickness(p).unwrap_or(0.0);
                let axis = match solid_shape(shape) {
                    Shape::Cone { height, .. } | Shape::Cylinder { height, .. } => Some(height),
                    _ => None,
                };
                let base = p.transform.point([0.0; 3]);
                if let Some(h) = axis {
                    let tip = p.transform.point([0.0, h, 0.0]);
                    if level <= 1 {
                        flows.push((t, Flow { from: add(base, offset), to: add(tip, offset) }));
                    }
                    if t < 0.5 * side {
                        sampler.radius = t * MASK as f32 / side;
                        sampler.line(base, tip, level, projected_area(p))?;
                        continue;
                    }
                }
                sampler.solid(p, &stream.local_bounds(p), level)?;
            }
        }
    }
    sampler.flush()?;
    let covers = std::mem::take(&mut sampler.covers);
    // Densities from optical depth: across one voxel (Δs = 1 / (R · REFERENCE_STEP) of the raymarcher's units,
    // R the longest axis in voxels) `(1 − µ)^Δs = e^(−τ)`.
    let longest_axis = volume.resolution.iter().copied().max().unwrap_or(1) as f32;
    // A voxel takes the colour of what covers most of it: leaves where their depth exceeds the wood's (its level is
    // the thickest wood's, so a twig among leaves would otherwise colour them all as bark).
    // Densities are bytes: the rounding error is carried to the next voxel in index order, so that the sparse fringe
    // of a crown, each voxel of it under one step, keeps its total cover (a voxel that rounds to nothing is dropped).
    let mut indices: Vec<u32> = covers.keys().copied().collect();
    indices.sort_unstable();
    let mut list = VoxelList::default();
    let mut carry = 0.0f32;
    for index in indices {
        let cover = &covers[&index];
        let v = volume.coords(index);
        let around: Around = std::array::from_fn(|a| {
            let [before, after] = [-1i64, 1].map(|d| {
                let c = i64::from(v[a]) + d;
                if c < 0 || c >= i64::from(volume.resolution[a]) {
                    return None;
                }
                let mut w = v;
                w[a] = c as u32;
                covers.get(&volume.index(w))
            });
            let of = |n: Option<&Cover>, solid: bool| n.map_or(0, |n| if solid { n.solid[a] } else { n.union[a] });
            [[of(before, false), of(after, false)], [of(before, true), of(after, true)]]
        });
        let [wood, leaves] = cover.depth;
        let wood = wood + cover.solid.iter().map(|m| m.count_ones() as f32).sum::<f32>() / (3 * MASK * MASK) as f32;
        let depth = -libm::logf(1.0 - cover.coverage(&around).min(0.999));
        let mu = 1.0 - libm::expf(-depth * longest_axis * REFERENCE_STEP);
        let want = 255.0 * mu + carry;
        let density = libm::roundf(want).clamp(0.0, 255.0) as u8;
        carry = want - f32::from(density);
        if density != 0 {
            list.push(index, Voxel { density, level: if leaves > wood { leaf_level } else { cover.level } });
        }
    }
    let (map, vbox) = BrickMap::from_indices(&volume, list.indices.iter().copied());
    let finished = (VoxelStore::from_list(list, opts.storage, &volume), map, vbox);
    let depth_colors = color_sum
        .iter()
        .enumerate()
        .filter(|(_, c)| c.1 > 0)
        .map(|(l, (sum, n))| {
            let c: [f32; 3] = std::array::from_fn(|i| ((sum[i] / *n as f64) as f32).clamp(0.0, 1.0));
            DepthColor { levels: [l as u8, l as u8], from: c, to: c }
        })
        .collect();
    // The thickest axes are the first-level structure flow (at most 64, thickest first, ties in stream order).
    let mut order: Vec<usize> = (0..flows.len()).collect();
    order.sort_by(|&a, &b| flows[b].0.total_cmp(&flows[a].0).then(a.cmp(&b)));
    let flows = order.into_iter().take(64).map(|i| flows[i].1).collect();
    Ok(Hypertree::with_occupancy(
        name.to_string(),
        volume,
        finished,
        depth_colors,
        leaf_level + 1,
        opts.branch_depth,
        Bounds::default(),
        flows,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Silhouettes of one voxel: the thin geometry's `union` along every axis, `sum` counted per piece.
    fn thin(depth: f32, union: u64, sum: u32) -> Cover {
        Cover { level: 0, depth: [depth, 0.0], union: [union; 3], sum: [sum; 3], solid: [0; 3] }
    }

    const NONE: Around = [[[0; 2]; 2]; 3];

    #[test]
    fn marks_stay_inside_the_silhouette() {
        for (u, w) in [(0.0, 0.0), (8.0, 8.0), (8.0, 0.0), (0.0, 8.0), (3.3, 7.9)] {
            for r in [0.0, 0.4, 1.0, 3.0, 9.0] {
                assert_ne!(disc(u, w, r), 0);
            }
            assert_eq!(block(u, w).count_ones(), 4);
        }
        assert_eq!(disc(4.0, 4.0, 9.0), u64::MAX);
        assert_eq!(disc(0.5, 0.5, 0.4), 1);
    }

    #[test]
    fn pieces_placed_as_by_chance_cover_as_beer_lambert_says() {
        // Eight sub-cells of 64, none shared: Ω is about 1.
        let c = thin(0.1, 0xff, 8).coverage(&NONE);
        assert!((c - (1.0 - libm::expf(-0.1))).abs() < 0.01, "{c}");
    }

    #[test]
    fn clumped_pieces_cover_less_and_never_more_than_their_sub_cells() {
        let spread = thin(0.5, 0xffff, 16).coverage(&NONE);
        let tuft = thin(0.5, 0xffff, 64).coverage(&NONE);
        assert!(tuft < 0.6 * spread, "{tuft} {spread}");
        // A dense layer in two rows of the silhouette covers at most those rows.
        let layer = thin(5.0, 0xffff, 16).coverage(&NONE);
        assert!((layer - 0.25).abs() < 1e-6, "{layer}");
    }

    #[test]
    fn what_the_neighbours_along_an_axis_cover_too_counts_half_for_each() {
        let m = 0x0f0f;
        let alone = thin(0.2, m, 8).coverage(&NONE);
        // The same spot covered before and after along x only: a third of the mean loses all of it.
        let mut around = NONE;
        around[0][0] = [m, m];
        let chained = thin(0.2, m, 8).coverage(&around);
        assert!((chained - alone * 2.0 / 3.0).abs() < 1e-6, "{chained} {alone}");
        // Solid wood inside a trunk, full silhouettes all round: still opaque.
        let full = Cover { solid: [u64::MAX; 3], ..Cover::default() };
        assert_eq!(full.coverage(&[[[0; 2], [u64::MAX; 2]]; 3]), 1.0);
    }
}
