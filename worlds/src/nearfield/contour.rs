//! Contours and how seed 004 §3.2 joins them: sampling a branch contour, stitching two contours into a band of
//! triangles (one contour to the next), one contour to several (the parent's contour to its children's, with the
//! children's contours bridged into one loop at their closest points: the crotch), and the merged outer contour
//! of intersecting ellipse sections (§3.3, Figure 6).
//!
//! Stitching follows the surfaces-from-contours tradition the paper builds on: a dynamic programme over the two
//! vertex sequences that minimises the summed length of the triangles' cross edges. Combinatorially every band is
//! an annulus: each contour edge is used by exactly one band triangle, so a band between two closed contours is
//! edge-manifold and consistently wound whatever the geometry.

use core::f64::consts::TAU;

use crate::nearfield::{V3, add, cross, dot, norm, normalize, perpendicular, scale, sub};

/// `n` points of the circle of `radius` about `centre` in the plane across the unit `axis`, starting in the
/// direction of `side` (projected into the plane), counter-clockwise seen from the tip of the axis.
pub fn circle(centre: V3, axis: V3, side: V3, radius: f64, n: usize) -> Vec<V3> {
    ellipse(centre, axis, side, radius, radius, n)
}

/// `n` points of the ellipse about `centre` in the plane across the unit `axis`, with semi-axis `major` along
/// `side` (projected into the plane; any direction in it when `side` is along the axis) and `minor` across it,
/// counter-clockwise seen from the tip of the axis.
pub fn ellipse(centre: V3, axis: V3, side: V3, major: f64, minor: f64, n: usize) -> Vec<V3> {
    // A `side` (nearly) along the axis has no direction in the plane: rounding would make one up along the axis,
    // and the ellipse would collapse onto a line.
    let across = sub(side, scale(axis, dot(side, axis)));
    let u = normalize(across).filter(|_| norm(across) > 1e-6 * norm(side)).unwrap_or_else(|| perpendicular(axis));
    let v = cross(axis, u);
    (0..n)
        .map(|j| {
            let a = TAU * j as f64 / n as f64;
            add(centre, add(scale(u, major * libm::cos(a)), scale(v, minor * libm::sin(a))))
        })
        .collect()
}

/// Triangles of the band between a lower loop `a` and an upper loop `b` (vertex ids; both counter-clockwise seen
/// from above), as index triples into `positions`. `b` may visit a vertex twice (a bridged loop); `a` may not.
/// The band has `a.len() + b.len()` triangles, no vertex of `a` is joined to two visits of one vertex of `b`.
pub fn stitch(positions: &[V3], a: &[u32], b: &[u32]) -> Vec<[u32; 3]> {
    let (n, m) = (a.len(), b.len());
    if n == 0 || m == 0 {
        return Vec::new();
    }
    // Candidate starts: visits of b that are not repeated, nearest to a[0] first.
    let mut count = std::collections::BTreeMap::new();
    for &v in b {
        *count.entry(v).or_insert(0u32) += 1;
    }
    let pa0 = positions[a[0] as usize];
    let mut starts: Vec<usize> = (0..m).filter(|&j| count[&b[j]] == 1).collect();
    starts.sort_by(|&x, &y| {
        let dx = norm(sub(positions[b[x] as usize], pa0));
        let dy = norm(sub(positions[b[y] as usize], pa0));
        dx.total_cmp(&dy).then(x.cmp(&y))
    });
    if starts.is_empty() {
        starts.push(0);
    }
    let mut fallback = None;
    for &b0 in starts.iter().take(8) {
        let tris = stitch_from(positions, a, b, b0);
        if joins_twice(a, &tris, b) {
            fallback.get_or_insert(tris);
            continue;
        }
        return tris;
    }
    fallback.unwrap_or_default()
}

/// Whether some vertex of `a` is joined to two different visits of one vertex of `b` (the band would not be
/// manifold): found as a vertex of `a` sharing more than the usual triangles with a repeated vertex of `b`.
fn joins_twice(a: &[u32], tris: &[[u32; 3]], b: &[u32]) -> bool {
    let mut count = std::collections::BTreeMap::new();
    for &v in b {
        *count.entry(v).or_insert(0u32) += 1;
    }
    let mut edges = std::collections::BTreeMap::new();
    for t in tris {
        for (x, y) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            *edges.entry((x.min(y), x.max(y))).or_insert(0u32) += 1;
        }
    }
    // A cross edge is shared by two band triangles; joining the same pair twice makes it four.
    a.iter().any(|&va| {
        count
            .iter()
            .filter(|(_, c)| **c > 1)
            .any(|(&vb, _)| edges.get(&(va.min(vb), va.max(vb))).copied().unwrap_or(0) > 2)
    })
}

/// The dynamic programme for one start: row `i` (vertex `a[i mod n]`) is joined to the visits `s_i..=e_i` of `b`
/// (rotated to start at `b0`), rows are consecutive (`s_(i+1) = e_i`), the cost is the summed length of all cross
/// edges, and no row contains two visits of one vertex.
fn stitch_from(positions: &[V3], a: &[u32], b: &[u32], b0: usize) -> Vec<[u32; 3]> {
    let (n, m) = (a.len(), b.len());
    let bi = |j: usize| b[(b0 + j) % m];
    let pa = |i: usize| positions[a[i % n] as usize];
    let pb = |j: usize| positions[bi(j) as usize];
    // lim[s]: the last visit a row starting at s may reach without a repeated vertex.
    let mut lim = vec![m; m + 1];
    let mut next_same: std::collections::BTreeMap<u32, usize> = std::collections::BTreeMap::new();
    for j in (0..=m).rev() {
        let v = bi(j % m);
        let own = if j < m { next_same.get(&v).map(|&k| k - 1).unwrap_or(m) } else { m };
        lim[j] = if j < m { own.min(lim[j + 1]) } else { m };
        if j < m {
            next_same.insert(v, j);
        }
    }
    // Visit m is b_0 again: no row may hold both visit 0 and visit m.
    lim[0] = lim[0].min(m - 1);
    let window = (4 * m.div_ceil(n)).max(16);
    const INF: f64 = f64::INFINITY;
    // cost[i][j] prefix sums of |a_i − b_j| over j.
    let mut best = vec![INF; (n + 1) * (m + 1)];
    let mut from = vec![0usize; (n + 1) * (m + 1)];
    let mut prefix = vec![0.0f64; m + 2];
    for i in 0..=n {
        for j in 0..=m {
            prefix[j + 1] = prefix[j] + norm(sub(pa(i), pb(j)));
        }
        let row_cost = |s: usize, e: usize| prefix[e + 1] - prefix[s];
        for e in 0..=m {
            let lo = e.saturating_sub(window);
            let mut bv = INF;
            let mut bs = 0;
            // Row 0 is the start diagonal (a_0, b_0) alone, so a_0's whole fan is row n, which starts after
            // b_0: no diagonal is visited twice. (Trying several b_0 covers the fans row 0 would have had.)
            if i == 0 {
                if e == 0 {
                    bv = row_cost(0, e);
                }
            } else {
                for s in lo.max(usize::from(i == n))..=e {
                    let prev = best[(i - 1) * (m + 1) + s];
                    if prev < INF && lim[s] >= e {
                        let c = prev + row_cost(s, e);
                        if c < bv {
                            bv = c;
                            bs = s;
                        }
                    }
                }
            }
            best[i * (m + 1) + e] = bv;
            from[i * (m + 1) + e] = bs;
        }
    }
    // Trace back the row ranges; an unreachable end (should not happen) falls back to even spacing.
    let mut ranges = vec![(0usize, 0usize); n + 1];
    if best[n * (m + 1) + m] < INF {
        let mut e = m;
        for i in (0..=n).rev() {
            let s = if i == 0 { 0 } else { from[i * (m + 1) + e] };
            ranges[i] = (s, e);
            e = s;
        }
    } else {
        let mut s = 0;
        for (i, r) in ranges.iter_mut().enumerate() {
            let e = if i == n { m } else { (i + 1) * m / (n + 1) };
            *r = (s, e.max(s));
            s = e.max(s);
        }
    }
    let mut tris = Vec::with_capacity(n + m);
    for (i, &(s, e)) in ranges.iter().enumerate() {
        for j in s..e {
            tris.push([a[i % n], bi(j + 1), bi(j)]);
        }
        if i < n {
            tris.push([a[i % n], a[(i + 1) % n], bi(e)]);
        }
    }
    tris
}

/// Join several loops (vertex ids, each counter-clockwise seen from above) into one loop by bridges between
/// their closest vertices, a spanning tree grown from loop 0; the result visits each bridge's two ends twice and
/// goes round every loop once, so it is the outline of the loops and their bridges (the crotches).
pub fn bridge(positions: &[V3], loops: &[Vec<u32>]) -> Vec<u32> {
    let k = loops.len();
    if k == 0 {
        return Vec::new();
    }
    let mut used = std::collections::BTreeSet::new();
    let mut in_tree = vec![false; k];
    in_tree[0] = true;
    // bridge_at[(loop, position)] = (other loop, its position)
    let mut bridge_at: std::collections::BTreeMap<(usize, usize), (usize, usize)> = std::collections::BTreeMap::new();
    for _ in 1..k {
        let mut best: Option<(f64, usize, usize, usize, usize)> = None;
        for p in (0..k).filter(|&p| in_tree[p]) {
            for q in (0..k).filter(|&q| !in_tree[q]) {
                for (i, &u) in loops[p].iter().enumerate() {
                    if used.contains(&(p, i)) {
                        continue;
                    }
                    for (j, &v) in loops[q].iter().enumerate() {
                        let d = norm(sub(positions[u as usize], positions[v as usize]));
                        if best.is_none_or(|b| d < b.0) {
                            best = Some((d, p, i, q, j));
                        }
                    }
                }
            }
        }
        let Some((_, p, i, q, j)) = best else { break };
        used.insert((p, i));
        used.insert((q, j));
        in_tree[q] = true;
        bridge_at.insert((p, i), (q, j));
        bridge_at.insert((q, j), (p, i));
    }
    // Walk the tree of loops: round each loop from its entry, detouring through each bridge to a new loop.
    struct Frame {
        l: usize,
        entry: usize,
        step: usize,
        detoured: bool,
        ret: Option<u32>,
    }
    let mut out = Vec::new();
    let mut visited = vec![false; k];
    visited[0] = true;
    let mut stack = vec![Frame { l: 0, entry: 0, step: 0, detoured: false, ret: None }];
    while let Some(f) = stack.last_mut() {
        let len = loops[f.l].len();
        if f.step == len {
            let done = stack.pop().expect("frame");
            if let Some(x) = done.ret {
                out.push(loops[done.l][done.entry]);
                out.push(x);
            }
            continue;
        }
        let pos = (f.entry + f.step) % len;
        let x = loops[f.l][pos];
        if !f.detoured {
            out.push(x);
            f.detoured = true;
            if let Some(&(q, j)) = bridge_at.get(&(f.l, pos))
                && !visited[q]
            {
                visited[q] = true;
                stack.push(Frame { l: q, entry: j, step: 0, detoured: false, ret: Some(x) });
                continue;
            }
        }
        f.step += 1;
        f.detoured = false;
    }
    out
}

/// The outline of the union of convex polygons (each counter-clockwise, at least 3 points), traced as seed 004
/// Figure 6 does: start at a point outside all others, follow the current polygon until an edge enters another,
/// continue along that one. `None` if the trace does not close (numerical trouble).
pub fn union_outline(polys: &[Vec<[f64; 2]>]) -> Option<Vec<[f64; 2]>> {
    let total: usize = polys.iter().map(Vec::len).sum();
    let (mut p, mut e) = (0usize, 0usize);
    for (pi, poly) in polys.iter().enumerate() {
        for (ei, q) in poly.iter().enumerate() {
            let c = polys[p][e];
            if q[0] > c[0] || (q[0] == c[0] && q[1] > c[1]) {
                (p, e) = (pi, ei);
            }
        }
    }
    let (start_p, start_e) = (p, e);
    let mut x = polys[p][e];
    let mut out = vec![x];
    for _ in 0..4 * total + 16 {
        let poly = &polys[p];
        let end = poly[(e + 1) % poly.len()];
        let d = [end[0] - x[0], end[1] - x[1]];
        // The nearest entering crossing of another polygon's edge along x → end.
        let mut hit: Option<(f64, usize, usize, [f64; 2])> = None;
        for (qi, q) in polys.iter().enumerate() {
            if qi == p {
                continue;
            }
            for f in 0..q.len() {
                let (a, b) = (q[f], q[(f + 1) % q.len()]);
                let g = [b[0] - a[0], b[1] - a[1]];
                let den = d[0] * g[1] - d[1] * g[0];
                // Entering q (counter-clockwise): crossing its edge from right to left.
                let entering = g[0] * d[1] - g[1] * d[0];
                if entering.is_nan() || entering <= 0.0 || den == 0.0 {
                    continue;
                }
                let w = [a[0] - x[0], a[1] - x[1]];
                let s = (w[0] * g[1] - w[1] * g[0]) / den;
                let u = (w[0] * d[1] - w[1] * d[0]) / den;
                if s > 1e-9 && s <= 1.0 && (0.0..=1.0).contains(&u) && hit.is_none_or(|h| s < h.0) {
                    hit = Some((s, qi, f, [x[0] + d[0] * s, x[1] + d[1] * s]));
                }
            }
        }
        match hit {
            Some((_, qi, f, y)) => {
                out.push(y);
                (p, e, x) = (qi, f, y);
            }
            None => {
                e = (e + 1) % poly.len();
                x = end;
                if p == start_p && e == start_e {
                    return Some(out);
                }
                out.push(x);
            }
        }
    }
    None
}

/// Whether two convex polygons (counter-clockwise) overlap: an edge of one crosses an edge of the other, or one
/// holds a vertex of the other.
pub fn overlap(a: &[[f64; 2]], b: &[[f64; 2]]) -> bool {
    let inside = |poly: &[[f64; 2]], p: [f64; 2]| {
        (0..poly.len()).all(|i| {
            let (s, t) = (poly[i], poly[(i + 1) % poly.len()]);
            (t[0] - s[0]) * (p[1] - s[1]) - (t[1] - s[1]) * (p[0] - s[0]) >= 0.0
        })
    };
    if inside(a, b[0]) || inside(b, a[0]) {
        return true;
    }
    let orient = |p: [f64; 2], q: [f64; 2], r: [f64; 2]| (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]);
    for i in 0..a.len() {
        let (p, q) = (a[i], a[(i + 1) % a.len()]);
        for j in 0..b.len() {
            let (r, s) = (b[j], b[(j + 1) % b.len()]);
            let (o1, o2) = (orient(p, q, r), orient(p, q, s));
            let (o3, o4) = (orient(r, s, p), orient(r, s, q));
            if o1 * o2 < 0.0 && o3 * o4 < 0.0 {
                return true;
            }
        }
    }
    false
}

/// `count` points spaced evenly by arc length along a closed polyline, starting at its first point.
pub fn resample(points: &[[f64; 2]], count: usize) -> Vec<[f64; 2]> {
    let n = points.len();
    let seg = |i: usize| {
        let (a, b) = (points[i], points[(i + 1) % n]);
        libm::sqrt((b[0] - a[0]) * (b[0] - a[0]) + (b[1] - a[1]) * (b[1] - a[1]))
    };
    let total: f64 = (0..n).map(seg).sum();
    if n == 0 || count == 0 || total.is_nan() || total <= 0.0 {
        return points.to_vec();
    }
    let mut out = Vec::with_capacity(count);
    let (mut i, mut walked) = (0usize, 0.0f64);
    for k in 0..count {
        let target = total * k as f64 / count as f64;
        while i < n - 1 && walked + seg(i) < target {
            walked += seg(i);
            i += 1;
        }
        let l = seg(i);
        let f = if l > 0.0 { ((target - walked) / l).clamp(0.0, 1.0) } else { 0.0 };
        let (a, b) = (points[i], points[(i + 1) % n]);
        out.push([a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f]);
    }
    out
}

/// Perimeter of a closed polyline.
pub fn perimeter(points: &[[f64; 2]]) -> f64 {
    let n = points.len();
    (0..n)
        .map(|i| {
            let (a, b) = (points[i], points[(i + 1) % n]);
            libm::sqrt((b[0] - a[0]) * (b[0] - a[0]) + (b[1] - a[1]) * (b[1] - a[1]))
        })
        .sum()
}
