//! The LOD chain of a continuous mesh (seed 004 §4–5): decimation with meshoptimizer's simplifier, thin branches
//! first and the trunk last — level `k` of `n` may collapse only vertices on contours no thicker than the
//! `k / n` quantile of the contour radii (the others are locked), so the last level is the only one that touches
//! the trunk — and every level keeps its error bound.
//!
//! The bound is checked, not trusted: after each simplification every vertex of the full mesh is measured against
//! the decimated surface (point-to-triangle distance over a uniform grid), and a level that strays beyond its
//! bound is simplified again with a tighter target (halved, then the level keeps the previous one's triangles). So
//! [`LodLevel::error`] ≤ [`LodLevel::bound`] always holds.
//!
//! The topology is checked too ([`crate::nearfield::topology`], vertices welded at bit-identical positions): the
//! simplifier may collapse two nearby sheets of the surface onto one edge (thin branches side by side, a crotch),
//! pinching it. A level whose topology differs from the full mesh's (bodies, open, non-manifold or misoriented
//! edges, Euler characteristic, degenerate triangles) is simplified again with the vertices at the defects and
//! their neighbours in the previous level locked, so every level is as closed and manifold as the full mesh.

use std::collections::{BTreeMap, BTreeSet};

use meshopt::{SimplifyOptions, VertexDataAdapter, simplify_with_locks, typed_to_bytes};

use crate::mesh::Mesh;
use crate::nearfield::continuous::ContinuousMesh;
use crate::nearfield::topology::{Topology, Weld, check, defects, weld};
use crate::nearfield::{NearFieldError, V3, add, dot, scale, sub};

/// How the chain is built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LodOptions {
    /// Levels after the full mesh (`1..=16`).
    pub levels: u32,
    /// Error bound of the last level, metres; level `k` gets `k / levels` of it.
    pub error: f32,
}

impl Default for LodOptions {
    fn default() -> Self {
        LodOptions { levels: 4, error: 0.02 }
    }
}

/// One level of the chain.
#[derive(Clone, Debug, PartialEq)]
pub struct LodLevel {
    /// The decimated mesh (unused vertices removed).
    pub mesh: Mesh,
    /// Contours no thicker than this were free to collapse.
    pub max_radius: f32,
    /// The error bound of this level, metres.
    pub bound: f32,
    /// The measured error: the largest distance from a vertex of the full mesh to this level's surface.
    pub error: f32,
}

/// Decimate a continuous mesh into a chain of `opts.levels` levels, each starting from the previous one.
pub fn lod_chain(cm: &ContinuousMesh, opts: &LodOptions) -> Result<Vec<LodLevel>, NearFieldError> {
    if !(1..=16).contains(&opts.levels) {
        return Err(NearFieldError::Option { name: "levels", value: opts.levels as f32 });
    }
    if !(opts.error > 0.0 && opts.error.is_finite()) {
        return Err(NearFieldError::Option { name: "error", value: opts.error });
    }
    let m = &cm.mesh;
    if m.indices.is_empty() {
        return Err(NearFieldError::Empty);
    }
    // meshoptimizer reads these arrays unchecked: check them here.
    if !m.indices.len().is_multiple_of(3) || m.indices.iter().any(|&i| i as usize >= m.positions.len()) {
        return Err(NearFieldError::Malformed("index out of range"));
    }
    if cm.radius.len() != m.positions.len() || !m.positions.iter().flatten().all(|x| x.is_finite()) {
        return Err(NearFieldError::Malformed("radii or positions"));
    }
    let mut radii: Vec<f32> = cm.radius.clone();
    radii.sort_by(f32::total_cmp);
    let bytes = typed_to_bytes(&m.positions);
    let adapter = VertexDataAdapter::new(bytes, 12, 0).map_err(|_| NearFieldError::Empty)?;
    // The full mesh's vertices that its triangles use: every level is measured against them.
    let used_ids: Vec<u32> = {
        let mut v = m.indices.clone();
        v.sort_unstable();
        v.dedup();
        v
    };
    let used: Vec<V3> = used_ids.iter().map(|&i| m.positions[i as usize].map(f64::from)).collect();
    let mut current = m.indices.clone();
    // Every level keeps the full mesh's topology as a welding tool sees it (one closed body stays one).
    let full = check(&m.positions, &m.indices, Weld::Exact);
    let welded = weld(&m.positions, Weld::Exact);
    // The measured error of `current` (unknown for the full mesh until a first level needs it).
    let mut current_err: Option<f64> = None;
    let mut out = Vec::new();
    for k in 1..=opts.levels {
        let max_radius = if k == opts.levels {
            f32::INFINITY
        } else {
            radii[((radii.len() - 1) as u64 * u64::from(k) / u64::from(opts.levels)) as usize]
        };
        let bound = opts.error * k as f32 / opts.levels as f32;
        let mut locks: Vec<bool> = cm.radius.iter().map(|&r| r > max_radius).collect();
        let mut target = bound;
        let mut chosen: Option<(Vec<u32>, f64)> = None;
        for _ in 0..MAX_ATTEMPTS {
            let simplified = simplify_with_locks(
                &current,
                &adapter,
                &locks,
                0,
                target,
                SimplifyOptions::ErrorAbsolute | SimplifyOptions::LockBorder,
                None,
            );
            let distances = nearest(&used, &m.positions, &simplified, f64::from(bound));
            let err = distances.iter().fold(0.0f64, |a, &d| a.max(d));
            if err > f64::from(bound) {
                // Vertices the simplifier took away at no cost by its measure (slivers weigh nothing in its
                // quadrics) can still stray from the surface: keep them and their neighbours; a level that strays
                // without such a vertex tries a tighter target.
                let far: Vec<u32> = distances
                    .iter()
                    .zip(&used_ids)
                    .filter(|(d, _)| **d > f64::from(bound))
                    .map(|(_, &v)| welded[v as usize])
                    .collect();
                if far.iter().all(|&v| locks[v as usize]) {
                    target *= 0.5;
                } else {
                    lock_around(&mut locks, &welded, &far, &current);
                }
                continue;
            }
            // The simplifier may pinch two parts of the surface together (an edge in four triangles after
            // welding) or open it: lock where it did, with the vertices around them in the previous level, and
            // simplify again.
            let (topology, bad) = defects(&m.positions, &simplified, Weld::Exact);
            if same_topology(&topology, &full) {
                chosen = Some((simplified, err));
                break;
            }
            if bad.is_empty() {
                target *= 0.5;
                continue;
            }
            lock_around(&mut locks, &welded, &bad, &current);
        }
        // Keeping the previous level: its error, measured under a smaller bound, is exact here too (`hausdorff` is
        // exact up to its bound, and the bounds grow with the level).
        let (indices, err) = match chosen {
            Some(c) => c,
            None => {
                let err = current_err.unwrap_or_else(|| hausdorff(&used, &m.positions, &current, f64::from(bound)));
                (current.clone(), err)
            }
        };
        current = indices;
        current_err = Some(err).filter(|e| e.is_finite());
        out.push(LodLevel { mesh: compact(m, &current), max_radius, bound, error: err as f32 });
    }
    Ok(out)
}

/// Simplifications tried per level (each halving the target error, or locking more vertices around defects)
/// before the level keeps the previous one's triangles.
const MAX_ATTEMPTS: usize = 16;

/// Whether a level has the topology of the full mesh: the same bodies, open, non-manifold and misoriented edges
/// and Euler characteristic, and no degenerate triangles.
fn same_topology(level: &Topology, full: &Topology) -> bool {
    level.degenerate == 0
        && (level.bodies, level.boundary_edges, level.non_manifold_edges, level.misoriented_edges, level.euler)
            == (full.bodies, full.boundary_edges, full.non_manifold_edges, full.misoriented_edges, full.euler)
}

/// Lock every vertex welded to one of `bad` (welded ids) and every vertex of a triangle of `current` that has one.
fn lock_around(locks: &mut [bool], welded: &[u32], bad: &[u32], current: &[u32]) {
    let bad: BTreeSet<u32> = bad.iter().copied().collect();
    for (v, w) in welded.iter().enumerate() {
        if bad.contains(w) {
            locks[v] = true;
        }
    }
    for t in current.chunks_exact(3) {
        if t.iter().any(|&v| bad.contains(&welded[v as usize])) {
            for &v in t {
                locks[v as usize] = true;
            }
        }
    }
}

/// The mesh with only the vertices `indices` use, renumbered in first-use order.
fn compact(m: &Mesh, indices: &[u32]) -> Mesh {
    let mut map: BTreeMap<u32, u32> = BTreeMap::new();
    let mut out = Mesh::default();
    for &i in indices {
        let next = map.len() as u32;
        let j = *map.entry(i).or_insert_with(|| {
            out.positions.push(m.positions[i as usize]);
            out.normals.push(m.normals[i as usize]);
            out.colors.push(m.colors[i as usize]);
            next
        });
        out.indices.push(j);
    }
    out
}

/// The largest distance from a point of `points` to the triangles `indices` over `positions`, exact up to
/// `bound` (a point farther than `bound` from every triangle counts as `f64::INFINITY`).
pub fn hausdorff(points: &[V3], positions: &[[f32; 3]], indices: &[u32], bound: f64) -> f64 {
    nearest(points, positions, indices, bound).into_iter().fold(0.0, f64::max)
}

/// The distance from each point of `points` to the nearest of the triangles `indices` over `positions`, exact up
/// to `bound` (`f64::INFINITY` beyond it).
pub fn nearest(points: &[V3], positions: &[[f32; 3]], indices: &[u32], bound: f64) -> Vec<f64> {
    if indices.is_empty() {
        return vec![f64::INFINITY; points.len()];
    }
    let tris: Vec<[V3; 3]> =
        indices.chunks_exact(3).map(|t| [0, 1, 2].map(|k| positions[t[k] as usize].map(f64::from))).collect();
    // Cells at least as large as the bound (so every triangle within it of a point is in the point's cell or a
    // neighbour) and as the median triangle (so a triangle is listed in a few cells, not thousands). The result
    // does not depend on the cell size: it is the distance to the nearest triangle either way.
    let mut extents: Vec<f64> = tris
        .iter()
        .map(|t| {
            (0..3).map(|k| t[0][k].max(t[1][k]).max(t[2][k]) - t[0][k].min(t[1][k]).min(t[2][k])).fold(0.0, f64::max)
        })
        .collect();
    extents.sort_by(f64::total_cmp);
    let median = extents.get(extents.len() / 2).copied().filter(|e| e.is_finite()).unwrap_or(0.0);
    let cell = bound.max(median).max(1e-9);
    let key = |p: V3| p.map(|x| libm::floor(x / cell) as i64);
    let mut grid: BTreeMap<[i64; 3], Vec<usize>> = BTreeMap::new();
    let mut big = Vec::new();
    for (i, t) in tris.iter().enumerate() {
        let lo = key([0, 1, 2].map(|k| t[0][k].min(t[1][k]).min(t[2][k])));
        let hi = key([0, 1, 2].map(|k| t[0][k].max(t[1][k]).max(t[2][k])));
        let count: i64 = (0..3).map(|k| hi[k] - lo[k] + 1).product();
        if count > 4096 {
            big.push(i);
            continue;
        }
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    grid.entry([x, y, z]).or_default().push(i);
                }
            }
        }
    }
    let mut out = Vec::with_capacity(points.len());
    for &p in points {
        let c = key(p);
        let mut best = f64::INFINITY;
        for &i in &big {
            best = best.min(point_triangle(p, &tris[i]));
        }
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(list) = grid.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                        for &i in list {
                            best = best.min(point_triangle(p, &tris[i]));
                        }
                    }
                }
            }
        }
        out.push(if best > bound { f64::INFINITY } else { best });
    }
    out
}

/// Distance from `p` to the triangle `t` (closest point by regions, after Ericson's Real-Time Collision
/// Detection §5.1.5).
pub fn point_triangle(p: V3, t: &[V3; 3]) -> f64 {
    let [a, b, c] = *t;
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    let dist = |q: V3| libm::sqrt(dot(sub(p, q), sub(p, q)));
    if d1 <= 0.0 && d2 <= 0.0 {
        return dist(a);
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(ab, bp), dot(ac, bp));
    if d3 >= 0.0 && d4 <= d3 {
        return dist(b);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return dist(add(a, scale(ab, d1 / (d1 - d3))));
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(ab, cp), dot(ac, cp));
    if d6 >= 0.0 && d5 <= d6 {
        return dist(c);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return dist(add(a, scale(ac, d2 / (d2 - d6))));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return dist(add(b, scale(sub(c, b), (d4 - d3) / ((d4 - d3) + (d5 - d6)))));
    }
    let denom = va + vb + vc;
    if denom == 0.0 {
        // A degenerate triangle: the nearest of its corners.
        return dist(a).min(dist(b)).min(dist(c));
    }
    let (v, w) = (vb / denom, vc / denom);
    dist(add(a, add(scale(ab, v), scale(ac, w))))
}
