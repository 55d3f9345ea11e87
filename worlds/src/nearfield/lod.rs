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
            let Measure { error: err, far } = measure(&used, &m.positions, &simplified, f64::from(bound));
            if err > f64::from(bound) {
                // Vertices the simplifier took away at no cost by its measure (slivers weigh nothing in its
                // quadrics) can still stray from the surface: keep them and their neighbours; a level that strays
                // without such a vertex tries a tighter target.
                let far: Vec<u32> = far.into_iter().map(|i| welded[used_ids[i] as usize]).collect();
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
    measure(points, positions, indices, bound).error
}

/// How far points are from a surface: [`measure`].
pub struct Measure {
    /// The largest distance from a point to the surface, exact up to the bound (`f64::INFINITY` where a point is
    /// farther).
    pub error: f64,
    /// The points (their indices) farther than the bound from every triangle, in order.
    pub far: Vec<usize>,
}

/// How far the points `points` are from the triangles `indices` over `positions`, up to `bound`. A point's search
/// ends once a triangle is found no farther than the largest distance so far (it cannot raise it): the result is
/// what measuring every point exactly would give, in a fraction of the work.
pub fn measure(points: &[V3], positions: &[[f32; 3]], indices: &[u32], bound: f64) -> Measure {
    if indices.is_empty() {
        let far: Vec<usize> = (0..points.len()).collect();
        let error = if far.is_empty() { 0.0 } else { f64::INFINITY };
        return Measure { error, far };
    }
    let tris: Vec<[V3; 3]> =
        indices.chunks_exact(3).map(|t| [0, 1, 2].map(|k| positions[t[k] as usize].map(f64::from))).collect();
    let boxes: Vec<[V3; 2]> = tris
        .iter()
        .map(|t| {
            let lo = [0, 1, 2].map(|k| t[0][k].min(t[1][k]).min(t[2][k]));
            let hi = [0, 1, 2].map(|k| t[0][k].max(t[1][k]).max(t[2][k]));
            [lo, hi]
        })
        .collect();
    // Cells at least as large as the bound (so every triangle within it of a point is in the point's cell or a
    // neighbour) and as the median triangle (so a triangle is listed in a few cells, not thousands). The result
    // does not depend on the cell size: it is the distance to the nearest triangle either way.
    let mut extents: Vec<f64> =
        boxes.iter().map(|[lo, hi]| (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max)).collect();
    extents.sort_by(f64::total_cmp);
    let median = extents.get(extents.len() / 2).copied().filter(|e| e.is_finite()).unwrap_or(0.0);
    // Cells are numbered from the triangles' lowest corner, 21 bits an axis (larger cells where the triangles span
    // more than 2^20 of them): a cell is one `u64`, and the grid and the points are sorted as plain numbers.
    let lowest = [0, 1, 2].map(|k| boxes.iter().map(|b| b[0][k]).fold(f64::INFINITY, f64::min));
    let span = (0..3).map(|k| boxes.iter().map(|b| b[1][k] - lowest[k]).fold(0.0, f64::max)).fold(0.0, f64::max);
    let cell = bound.max(median).max(span / f64::from(1u32 << 20)).max(1e-9);
    // Two cells of margin below and above: a point farther out than one cell from every triangle keeps an empty
    // neighbourhood when clamped.
    let axis = |x: f64, k: usize| (libm::floor((x - lowest[k]) / cell) + 2.0).clamp(0.0, f64::from((1u32 << 21) - 1));
    let cell_of = |p: V3| [0, 1, 2].map(|k| axis(p[k], k) as u64);
    let pack = |c: [u64; 3]| (c[0] << 42) | (c[1] << 21) | c[2];
    // The grid: (cell, triangle) pairs, sorted.
    let mut grid: Vec<u128> = Vec::new();
    let mut big = Vec::new();
    for (i, [lo, hi]) in boxes.iter().enumerate() {
        let (lo, hi) = (cell_of(*lo), cell_of(*hi));
        let count: u64 = (0..3).map(|k| hi[k] - lo[k] + 1).product();
        if count > 4096 {
            big.push(i as u32);
            continue;
        }
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    grid.push(u128::from(pack([x, y, z])) << 32 | i as u128);
                }
            }
        }
    }
    grid.sort_unstable();
    let in_cell = |c: u64| {
        let from = grid.partition_point(|&e| ((e >> 32) as u64) < c);
        let to = from + grid[from..].partition_point(|&e| (e >> 32) as u64 == c);
        grid[from..to].iter().map(|&e| e as u32)
    };
    // Corners as their f32 coordinates' bits (a point that is not three f32s is no corner).
    let as_f32 = |p: V3| {
        let q = p.map(|x| x as f32);
        (0..3).all(|k| f64::from(q[k]) == p[k]).then(|| q.iter().fold(0u128, |a, x| a << 32 | u128::from(x.to_bits())))
    };
    let mut corners: Vec<u128> = indices.iter().filter_map(|&v| as_f32(positions[v as usize].map(f64::from))).collect();
    corners.sort_unstable();
    corners.dedup();
    // Points by cell: the triangles of a cell's neighbourhood are gathered once for all its points.
    let mut order: Vec<u128> =
        points.iter().enumerate().map(|(i, &p)| u128::from(pack(cell_of(p))) << 32 | i as u128).collect();
    order.sort_unstable();
    // The largest distance (squared) of a point within the bound so far; the bound's square, with a margin that
    // keeps rounding from ever ruling out a triangle the full search would pick (the result is the same bits).
    let mut largest = 0.0f64;
    let beyond = bound * bound * (1.0 + 1e-6);
    let mut far = Vec::new();
    let mut near: Vec<u32> = Vec::new();
    for run in order.chunk_by(|a, b| a >> 32 == b >> 32) {
        let c = (run[0] >> 32) as u64;
        let [cx, cy, cz] = [c >> 42, c >> 21 & 0x1f_ffff, c & 0x1f_ffff];
        let mut gathered = false;
        for &i in run {
            let i = i as u32;
            let p = points[i as usize];
            // A point that is a corner of a triangle (a vertex the simplifier kept) is on the surface.
            let corner = as_f32(p).is_some_and(|q| corners.binary_search(&q).is_ok());
            let mut best = if corner { 0.0 } else { f64::INFINITY };
            // A corner cannot raise the largest distance: its cell's neighbourhood is gathered only for others.
            if best > largest && !gathered {
                // The point's own cell first: a near triangle found early lets the boxes rule out most others.
                near.clear();
                near.extend(in_cell(c));
                for d in NEIGHBOURS {
                    // Cells of the margin have no neighbours below 0 nor above the range: skipped, not wrapped.
                    let step = |v: u64, d: i64| v.checked_add_signed(d).filter(|&v| v < 1 << 21);
                    if let (Some(x), Some(y), Some(z)) = (step(cx, d[0]), step(cy, d[1]), step(cz, d[2])) {
                        near.extend(in_cell(pack([x, y, z])));
                    }
                }
                near.extend_from_slice(&big);
                gathered = true;
            }
            // (Ungathered, `near` is another cell's: the first look below stops before reading it.)
            for &t in &near {
                if best <= largest {
                    break;
                }
                // A triangle whose box is farther than the nearest so far, or than the bound, cannot change the
                // result.
                let b = box_distance_squared(p, &boxes[t as usize]);
                if b > best * (1.0 + 1e-6) || b > beyond {
                    continue;
                }
                best = best.min(point_triangle_squared(p, &tris[t as usize]));
            }
            if libm::sqrt(best) > bound {
                far.push(i as usize);
            } else {
                largest = largest.max(best);
            }
        }
    }
    far.sort_unstable();
    let error = if far.is_empty() { libm::sqrt(largest) } else { f64::INFINITY };
    Measure { error, far }
}

/// The 26 cells around a cell.
const NEIGHBOURS: [[i64; 3]; 26] = {
    let mut out = [[0; 3]; 26];
    let mut n = 0;
    let mut k = 0;
    while k < 27 {
        let d = [k / 9 - 1, k / 3 % 3 - 1, k % 3 - 1];
        if k != 13 {
            out[n] = d;
            n += 1;
        }
        k += 1;
    }
    out
};

/// The squared distance from `p` to the box `[lo, hi]` (0 inside it).
fn box_distance_squared(p: V3, [lo, hi]: &[V3; 2]) -> f64 {
    (0..3).map(|k| (lo[k] - p[k]).max(p[k] - hi[k]).max(0.0)).map(|d| d * d).sum()
}

/// Distance from `p` to the triangle `t` (closest point by regions, after Ericson's Real-Time Collision
/// Detection §5.1.5).
pub fn point_triangle(p: V3, t: &[V3; 3]) -> f64 {
    libm::sqrt(point_triangle_squared(p, t))
}

/// The squared distance from `p` to the triangle `t` ([`point_triangle`] before its square root).
fn point_triangle_squared(p: V3, t: &[V3; 3]) -> f64 {
    let [a, b, c] = *t;
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    let dist = |q: V3| dot(sub(p, q), sub(p, q));
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
