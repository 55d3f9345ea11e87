//! Topology of a triangle mesh as an outside tool sees it: vertices at coincident positions are welded first (a
//! glTF viewer or trimesh does the same), then the triangles are counted into bodies (connected over shared
//! edges), and every edge is checked for the two faces a closed edge-manifold surface gives it.
//!
//! The mesh builders may give two vertices the same position (a trunk base's cap rim and its first section, two
//! roots on one point), so index topology alone can call a surface closed that a welding tool sees pinched: this
//! checker is the one the tests hold the continuous meshes to.
//!
//! **Welding** is explicit ([`Weld`]): [`Weld::Exact`] merges vertices whose `f32` positions are bit-identical
//! (after `-0.0` is read as `0.0`); [`Weld::Quantised`] merges vertices whose positions round to the same point of
//! a grid of the given step (`round(x / step)` per coordinate), which catches near-coincident vertices the exact
//! weld misses (two points either side of a grid plane can still stay apart). The report is deterministic (sorted
//! vectors, no hashing).

use crate::nearfield::{V3, cross, norm, sub};

/// How coincident vertices are merged before the topology is read.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Weld {
    /// Bit-identical `f32` positions (`-0.0` and `0.0` are the same).
    Exact,
    /// Positions that round to the same point of a grid of this step (metres, positive and finite).
    Quantised(f32),
}

/// What [`check`] found.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Topology {
    /// Distinct vertices after welding (only those some triangle uses).
    pub vertices: usize,
    /// Vertices that were merged into another one by the weld (among those triangles use).
    pub welded: usize,
    /// Triangles, degenerate ones included.
    pub triangles: usize,
    /// Triangles with two welded corners the same, or no area (a zero cross product in `f64`).
    pub degenerate: usize,
    /// Connected components of the non-degenerate triangles, two triangles being connected when they share an
    /// edge (welded); trimesh's `split()` counts the same.
    pub bodies: usize,
    /// Undirected edges (welded) of the non-degenerate triangles.
    pub edges: usize,
    /// Edges used by exactly one triangle: holes (the mesh is not watertight).
    pub boundary_edges: usize,
    /// Edges used by more than two triangles (pinched or fused surfaces).
    pub non_manifold_edges: usize,
    /// Edges used by exactly two triangles in the same direction (the winding flips across them).
    pub misoriented_edges: usize,
    /// Euler characteristic `V − E + F` of the non-degenerate triangles and the vertices they use.
    pub euler: i64,
}

impl Topology {
    /// Closed: no boundary edges and no non-manifold edges.
    pub fn is_watertight(&self) -> bool {
        self.boundary_edges == 0 && self.non_manifold_edges == 0
    }

    /// One closed, edge-manifold, consistently wound body without degenerate triangles.
    pub fn is_one_closed_body(&self) -> bool {
        self.bodies == 1 && self.is_watertight() && self.misoriented_edges == 0 && self.degenerate == 0
    }
}

impl core::fmt::Display for Topology {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "{} bodies, {} triangles ({} degenerate), {} vertices ({} welded), {} edges: {} boundary, {} non-manifold, \
             {} misoriented, Euler {}",
            self.bodies,
            self.triangles,
            self.degenerate,
            self.vertices,
            self.welded,
            self.edges,
            self.boundary_edges,
            self.non_manifold_edges,
            self.misoriented_edges,
            self.euler
        )
    }
}

/// The welded id of every vertex: the smallest original index at the same (welded) position.
pub fn weld(positions: &[[f32; 3]], how: Weld) -> Vec<u32> {
    let key = |p: &[f32; 3]| match how {
        // `+ 0.0` turns -0.0 into 0.0; bits of other values are unchanged.
        Weld::Exact => p.map(|x| i64::from((x + 0.0).to_bits())),
        Weld::Quantised(step) => p.map(|x| libm::round(f64::from(x) / f64::from(step)) as i64),
    };
    // Sorted by (position key, index): each run of one key maps to its first, smallest index.
    let mut order: Vec<([i64; 3], u32)> = positions.iter().enumerate().map(|(i, p)| (key(p), i as u32)).collect();
    order.sort_unstable();
    let mut map = vec![0u32; positions.len()];
    let mut run_start = 0;
    for k in 0..order.len() {
        if order[k].0 != order[run_start].0 {
            run_start = k;
        }
        map[order[k].1 as usize] = order[run_start].1;
    }
    map
}

/// Weld `positions` as `how` says and read the topology of the triangles `indices` (three per triangle; an index
/// out of range counts the triangle as degenerate).
pub fn check(positions: &[[f32; 3]], indices: &[u32], how: Weld) -> Topology {
    analyse(positions, indices, how).0
}

/// [`check`], and the welded ids (see [`weld`]) of the vertices where the surface is not closed and manifold: the
/// ends of boundary, non-manifold and misoriented edges and the corners of degenerate triangles, sorted.
pub fn defects(positions: &[[f32; 3]], indices: &[u32], how: Weld) -> (Topology, Vec<u32>) {
    analyse(positions, indices, how)
}

fn analyse(positions: &[[f32; 3]], indices: &[u32], how: Weld) -> (Topology, Vec<u32>) {
    let map = weld(positions, how);
    let mut bad: Vec<u32> = Vec::new();
    let mut used = vec![false; positions.len()];
    let mut used_original = vec![false; positions.len()];
    let mut faces: Vec<[u32; 3]> = Vec::new();
    let mut degenerate = 0;
    let triangles = indices.len() / 3;
    for t in indices.chunks_exact(3) {
        if t.iter().any(|&i| i as usize >= positions.len()) {
            degenerate += 1;
            continue;
        }
        for &i in t {
            used_original[i as usize] = true;
        }
        let w = [map[t[0] as usize], map[t[1] as usize], map[t[2] as usize]];
        let [a, b, c]: [V3; 3] = w.map(|i| positions[i as usize].map(f64::from));
        let area = norm(cross(sub(b, a), sub(c, a)));
        if w[0] == w[1] || w[1] == w[2] || w[0] == w[2] || area.is_nan() || area == 0.0 {
            degenerate += 1;
            bad.extend(w);
            continue;
        }
        for &i in &w {
            used[i as usize] = true;
        }
        faces.push(w);
    }
    // Every undirected edge with the face that uses it and whether it runs from the smaller id, sorted so that
    // the uses of one edge are adjacent.
    let mut edges: Vec<(u32, u32, u32, bool)> = Vec::with_capacity(3 * faces.len());
    for (f, t) in faces.iter().enumerate() {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            edges.push((a.min(b), a.max(b), f as u32, a < b));
        }
    }
    edges.sort_unstable();
    // Bodies: union-find over faces joined by an edge.
    let mut parent: Vec<usize> = (0..faces.len()).collect();
    fn find(p: &mut [usize], mut x: usize) -> usize {
        while p[x] != x {
            p[x] = p[p[x]];
            x = p[x];
        }
        x
    }
    let (mut edge_count, mut boundary_edges, mut non_manifold_edges, mut misoriented_edges) = (0, 0, 0, 0);
    let mut start = 0;
    while start < edges.len() {
        let (a, b) = (edges[start].0, edges[start].1);
        let mut end = start + 1;
        while end < edges.len() && (edges[end].0, edges[end].1) == (a, b) {
            end += 1;
        }
        let users = &edges[start..end];
        edge_count += 1;
        let ok = match users.len() {
            1 => {
                boundary_edges += 1;
                false
            }
            2 if users[0].3 == users[1].3 => {
                misoriented_edges += 1;
                false
            }
            2 => true,
            _ => {
                non_manifold_edges += 1;
                false
            }
        };
        if !ok {
            bad.extend([a, b]);
        }
        for w in users.windows(2) {
            let (x, y) = (find(&mut parent, w[0].2 as usize), find(&mut parent, w[1].2 as usize));
            if x != y {
                parent[x.max(y)] = x.min(y);
            }
        }
        start = end;
    }
    let bodies = (0..faces.len()).filter(|&f| find(&mut parent, f) == f).count();
    let vertices = used.iter().filter(|&&u| u).count();
    let topology = Topology {
        vertices,
        welded: (0..positions.len()).filter(|&i| used_original[i] && map[i] as usize != i).count(),
        triangles,
        degenerate,
        bodies,
        edges: edge_count,
        boundary_edges,
        non_manifold_edges,
        misoriented_edges,
        euler: vertices as i64 - edge_count as i64 + faces.len() as i64,
    };
    bad.sort_unstable();
    bad.dedup();
    (topology, bad)
}

/// [`check`] on a [`crate::mesh::Mesh`].
pub fn check_mesh(m: &crate::mesh::Mesh, how: Weld) -> Topology {
    check(&m.positions, &m.indices, how)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit cube at `o`, 8 vertices, 12 triangles facing out.
    fn cube(o: [f32; 3], positions: &mut Vec<[f32; 3]>, indices: &mut Vec<u32>) {
        let base = positions.len() as u32;
        for k in 0..8u32 {
            positions.push([o[0] + (k & 1) as f32, o[1] + ((k >> 1) & 1) as f32, o[2] + ((k >> 2) & 1) as f32]);
        }
        // Faces as quads (counter-clockwise from outside), two triangles each.
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        for q in quads {
            indices.extend([q[0], q[1], q[2], q[0], q[2], q[3]].map(|i| base + i));
        }
    }

    #[test]
    fn a_cube_is_one_watertight_body() {
        let (mut p, mut i) = (Vec::new(), Vec::new());
        cube([0.0; 3], &mut p, &mut i);
        let t = check(&p, &i, Weld::Exact);
        assert!(t.is_one_closed_body(), "{t}");
        assert_eq!((t.vertices, t.edges, t.triangles, t.euler), (8, 18, 12, 2));
    }

    #[test]
    fn two_cubes_are_two_bodies() {
        let (mut p, mut i) = (Vec::new(), Vec::new());
        cube([0.0; 3], &mut p, &mut i);
        cube([3.0, 0.0, 0.0], &mut p, &mut i);
        let t = check(&p, &i, Weld::Exact);
        assert_eq!(t.bodies, 2);
        assert!(t.is_watertight() && !t.is_one_closed_body(), "{t}");
        assert_eq!(t.euler, 4);
    }

    #[test]
    fn a_bow_tie_has_a_non_manifold_edge() {
        // Three triangles on one edge (0, 1): a fin.
        let p = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.5, -1.0, 0.0], [0.5, 0.0, 1.0]];
        let i = vec![0, 1, 2, 1, 0, 3, 0, 1, 4];
        let t = check(&p, &i, Weld::Exact);
        assert_eq!(t.non_manifold_edges, 1, "{t}");
        assert_eq!(t.boundary_edges, 6);
        assert_eq!(defects(&p, &i, Weld::Exact).1, vec![0, 1, 2, 3, 4], "every vertex is on an open edge");
        assert_eq!(t.bodies, 1);
        assert!(!t.is_watertight());
    }

    #[test]
    fn duplicate_vertices_are_welded_and_pinch_a_surface() {
        // Two cubes, the second with its own copies of two positions of the first (the edge x = 1, y = 1): index
        // topology sees two closed cubes, the weld sees four triangles on that edge.
        let (mut p, mut i) = (Vec::new(), Vec::new());
        cube([0.0; 3], &mut p, &mut i);
        cube([1.0, 1.0, 0.0], &mut p, &mut i);
        let t = check(&p, &i, Weld::Exact);
        // Corners (1,1,0) and (1,1,1) of the first cube are corners 0 and 4 of the second.
        assert_eq!(p[3], p[8]);
        assert_eq!(p[7], p[12]);
        assert_eq!(t.welded, 2, "{t}");
        assert_eq!(t.non_manifold_edges, 1, "{t}");
        assert_eq!(t.bodies, 1, "joined over the pinched edge: {t}");
        assert!(!t.is_watertight());
    }

    #[test]
    fn an_open_box_has_boundary_edges() {
        let (mut p, mut i) = (Vec::new(), Vec::new());
        cube([0.0; 3], &mut p, &mut i);
        i.truncate(30); // drop the last face
        let t = check(&p, &i, Weld::Exact);
        assert_eq!(t.boundary_edges, 4, "{t}");
        assert_eq!(defects(&p, &i, Weld::Exact).1, vec![1, 3, 5, 7], "the open face's corners");
        assert_eq!(t.bodies, 1);
        assert!(!t.is_watertight());
    }

    #[test]
    fn flipped_triangles_are_misoriented_and_degenerate_ones_counted() {
        let (mut p, mut i) = (Vec::new(), Vec::new());
        cube([0.0; 3], &mut p, &mut i);
        i.swap(0, 1); // flip one triangle
        let t = check(&p, &i, Weld::Exact);
        assert_eq!(t.misoriented_edges, 3, "{t}");
        assert!(t.is_watertight() && !t.is_one_closed_body());
        i.swap(0, 1);
        // A sliver with a repeated corner and a collinear one.
        p.push([2.0, 0.0, 0.0]);
        i.extend([0, 1, 8, 0, 0, 1]);
        let t = check(&p, &i, Weld::Exact);
        assert_eq!(t.degenerate, 2, "{t}");
        assert!(t.is_watertight(), "degenerate triangles take no part in the edge counts: {t}");
    }

    #[test]
    fn quantised_weld_merges_near_coincident_vertices() {
        let p = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0 + 1e-7, 0.0, 0.0], [-0.0, 0.0, 0.0]];
        assert_eq!(weld(&p, Weld::Exact), vec![0, 1, 2, 0], "-0.0 is 0.0; 1 + 1e-7 stays apart");
        assert_eq!(weld(&p, Weld::Quantised(1e-5)), vec![0, 1, 1, 0]);
    }
}
