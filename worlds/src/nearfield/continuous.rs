//! One continuous triangle mesh of a tree's whole branching structure (seed 004): contours at the start and end
//! of every piece of the [`Skeleton`], each parent contour stitched to its children's, so the branches form a
//! single closed surface without overlapping primitives.
//!
//! - A piece with no children is closed by a cap (a fan), or ends in its apex when its top radius is zero; a root
//!   piece is closed at its base the same way, and a trunk base brings its own cross-sections.
//! - A piece with one child (an I junction, a continuation) shares one contour with it: the section of the
//!   parent's cylinder by the plane that bisects the bend (the mitre).
//! - A piece with several children (Y and T junctions) ends in its contour `L`. **Direct** (the paper's Figure
//!   3): `L` is stitched to the children's base contours at once, bridged into one loop at their closest points.
//!   **Refined by intervals** (§3.3, Figures 4–7): cutting planes across the parent's axis, equi-spaced by
//!   `interval` times the parent's radius, cut every child's cylinder in an ellipse (minor radius `r`, major
//!   `r / cos α`, centred on the child's axis); while a group of ellipses still intersects, their merged outer
//!   contour is a new contour of the junction; where a group separates, its last contour is stitched to the
//!   parts (the children's ellipses, or merged contours of groups still joined), bridged at their closest
//!   points — the crotch. Children at more than 70° from the parent's axis do not cut the planes usefully and
//!   join at the first separation with a contour just outside the parent.
//!
//! Vertex normals are averaged over the faces that share the vertex (seed 002 §4). Every vertex carries its
//! contour's radius and branching order (the LOD chain decimates thin branches first), every triangle a
//! [`TriangleTag`] (the bark needs the trunk's rings and columns).

use crate::mesh::{Mesh, MeshOptions, mesh};
use crate::nearfield::contour::{bridge, circle, ellipse, overlap, perimeter, resample, stitch, union_outline};
use crate::nearfield::skeleton::Skeleton;
use crate::nearfield::{
    NearFieldError, V3, add, cross, dot, face_averaged_normals, norm, normalize, perpendicular, scale, sub,
};
use crate::primitive::PrimitiveStream;

/// Most contour vertices.
pub const MAX_CONTOUR: u32 = 256;
/// Most cutting planes at one junction.
pub const MAX_INTERVALS: u32 = 64;

/// How the continuous mesh is built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContinuousOptions {
    /// Contour resolution: vertices per branch contour (`3..=256`).
    pub contour: u32,
    /// Refine junctions by intervals (otherwise the direct method).
    pub refine: bool,
    /// Spacing of the cutting planes, as a fraction of the parent's radius (`0.05..=4`).
    pub interval: f64,
    /// Most triangles the mesh may have.
    pub max_triangles: usize,
    /// Add contours along the trunk's long pieces (branching order 0; at most 64 per piece) so their quads are
    /// about square, as the double bark's plates want; off, contours stand only at the pieces' ends and
    /// junctions, as seed 004 counts them.
    pub subdivide: bool,
}

impl Default for ContinuousOptions {
    fn default() -> Self {
        ContinuousOptions { contour: 12, refine: true, interval: 0.5, max_triangles: 8_000_000, subdivide: false }
    }
}

impl ContinuousOptions {
    /// Check the ranges.
    pub fn check(&self) -> Result<(), NearFieldError> {
        if !(3..=MAX_CONTOUR).contains(&self.contour) {
            return Err(NearFieldError::Option { name: "contour", value: self.contour as f32 });
        }
        if !(0.05..=4.0).contains(&self.interval) {
            return Err(NearFieldError::Option { name: "interval", value: self.interval as f32 });
        }
        Ok(())
    }
}

/// What a triangle of the continuous mesh belongs to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriangleTag {
    /// The skeleton piece it was built for.
    pub piece: u32,
    /// Branching order of that piece (0: the trunk).
    pub order: u16,
    /// Which vertex of its lower contour it starts from (its column around the branch).
    pub column: u32,
    /// How many contours lie below its lower contour along the branch (its ring).
    pub ring: u32,
    /// The unit axis of its branch (the bark's vertical direction).
    pub axis: [f32; 3],
    /// Whether it closes an end (a cap or an apex fan) rather than covering a branch's side.
    pub cap: bool,
}

/// The continuous mesh of a stream and what goes with it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ContinuousMesh {
    /// The branches: one closed surface per tree (per root of the skeleton).
    pub mesh: Mesh,
    /// Radius of the contour each vertex lies on.
    pub radius: Vec<f32>,
    /// Branching order of each vertex.
    pub order: Vec<u16>,
    /// One tag per triangle.
    pub tags: Vec<TriangleTag>,
    /// Everything else in the stream (leaves, spheres, boxes), meshed as usual.
    pub foliage: Mesh,
    /// Roots of the skeleton: branch systems that touch no other, each a frustum (or trunk base) whose base is
    /// neither on an earlier one's top nor on its axis. [`ContinuousMesh::mesh`] is one closed body per root, so
    /// a species that draws pieces apart (needle tufts along a twig nothing draws) cannot be one body.
    pub roots: usize,
}

impl ContinuousMesh {
    /// Why the branches are not one body, in words, or `None` when they are (one root of the skeleton).
    pub fn why_not_one_body(&self) -> Option<String> {
        match self.roots {
            1 => None,
            0 => Some("the stream has no cones, cylinders or trunk bases to mesh as branches".to_string()),
            n => Some(format!(
                "the species draws {n} branch systems that touch no other (a cone, cylinder or trunk base whose base \
                 is neither on another's top nor on its axis, such as needles or leaves drawn as cones apart from any \
                 branch), so the continuous mesh is {n} closed bodies"
            )),
        }
    }
}

#[derive(Clone, Debug)]
struct Loop {
    ids: Vec<u32>,
    ring: u32,
}

struct Builder {
    pos: Vec<V3>,
    color: Vec<[f32; 3]>,
    radius: Vec<f32>,
    order: Vec<u16>,
    tris: Vec<[u32; 3]>,
    tags: Vec<TriangleTag>,
    max: usize,
}

#[derive(Clone, Copy)]
struct Tag {
    piece: u32,
    order: u16,
    color: [f32; 3],
    axis: V3,
}

impl Builder {
    fn vertex(&mut self, p: V3, r: f64, t: Tag) -> u32 {
        self.pos.push(p);
        self.color.push(t.color);
        self.radius.push(r as f32);
        self.order.push(t.order);
        (self.pos.len() - 1) as u32
    }

    fn contour(&mut self, pts: &[V3], r: f64, t: Tag, ring: u32) -> Loop {
        Loop { ids: pts.iter().map(|&p| self.vertex(p, r, t)).collect(), ring }
    }

    fn push(&mut self, tri: [u32; 3], t: Tag, column: u32, ring: u32) -> Result<(), NearFieldError> {
        self.push_tagged(tri, t, column, ring, false)
    }

    fn push_tagged(&mut self, tri: [u32; 3], t: Tag, column: u32, ring: u32, cap: bool) -> Result<(), NearFieldError> {
        if self.tris.len() >= self.max {
            return Err(NearFieldError::TooLarge(self.max));
        }
        self.tris.push(tri);
        self.tags.push(TriangleTag {
            piece: t.piece,
            order: t.order,
            column,
            ring,
            axis: t.axis.map(|x| x as f32),
            cap,
        });
        Ok(())
    }

    fn band(&mut self, a: &Loop, b: &[u32], t: Tag) -> Result<(), NearFieldError> {
        let column: std::collections::BTreeMap<u32, u32> =
            a.ids.iter().enumerate().map(|(i, &v)| (v, i as u32)).collect();
        let n = a.ids.len();
        let mid = |pos: &[V3], p: u32, q: u32| scale(add(pos[p as usize], pos[q as usize]), 0.5);
        let lower: Vec<V3> = (0..n).map(|i| mid(&self.pos, a.ids[i], a.ids[(i + 1) % n])).collect();
        for tri in stitch(&self.pos, &a.ids, b) {
            // A triangle on a lower edge is in that edge's column; one on an upper edge in the column of the lower
            // edge nearest to it, so a quad's two triangles share a column however the diagonal runs.
            let col = if column.contains_key(&tri[1]) {
                column.get(&tri[0]).copied().unwrap_or(0)
            } else {
                let m = mid(&self.pos, tri[1], tri[2]);
                (0..n).min_by(|&x, &y| norm(sub(lower[x], m)).total_cmp(&norm(sub(lower[y], m)))).unwrap_or(0) as u32
            };
            self.push(tri, t, col, a.ring)?;
        }
        Ok(())
    }

    /// A fan from a centre vertex: facing along the loop's orientation (`up`) or against it.
    fn fan(&mut self, centre: u32, l: &Loop, up: bool, t: Tag) -> Result<(), NearFieldError> {
        let n = l.ids.len();
        for i in 0..n {
            let (p, q) = (l.ids[i], l.ids[(i + 1) % n]);
            self.push_tagged(if up { [centre, p, q] } else { [centre, q, p] }, t, i as u32, l.ring, true)?;
        }
        Ok(())
    }
}

/// Build the continuous mesh of a stream.
pub fn continuous_mesh(stream: &PrimitiveStream, opts: &ContinuousOptions) -> Result<ContinuousMesh, NearFieldError> {
    opts.check()?;
    let sk = Skeleton::from_stream(stream);
    let mut b = Builder {
        pos: Vec::new(),
        color: Vec::new(),
        radius: Vec::new(),
        order: Vec::new(),
        tris: Vec::new(),
        tags: Vec::new(),
        max: opts.max_triangles,
    };
    let res = opts.contour as usize;
    let mut work: Vec<(usize, Option<Loop>)> = sk.roots.iter().rev().map(|&r| (r, None)).collect();
    while let Some((id, base)) = work.pop() {
        let piece = &sk.pieces[id];
        let seg = sk.segment(id);
        let tag = Tag { piece: id as u32, order: piece.order, color: seg.color, axis: seg.axis };
        let (a, o) = (seg.axis, seg.at(piece.t1));
        let r_top = seg.radius(piece.t1);
        // The piece's base loop and, for a trunk base, its cross-sections up to the top.
        let mut lower = match (base, &seg.sections) {
            (_, Some(sections)) => {
                let c = b.vertex(sections[0].centre, seg.bottom, tag);
                let mut prev = b.contour(&sections[0].points, seg.bottom, tag, 0);
                b.fan(c, &prev, false, tag)?;
                for (k, s) in sections.iter().enumerate().skip(1) {
                    let r = seg.bottom + (seg.top - seg.bottom) * s.level;
                    let next = b.contour(&s.points, r, tag, k as u32);
                    b.band(&prev, &next.ids, tag)?;
                    prev = next;
                }
                prev
            }
            (Some(l), None) => l,
            (None, None) => {
                let p0 = seg.at(piece.t0);
                let r0 = seg.radius(piece.t0);
                let c = b.vertex(p0, r0, tag);
                let l = b.contour(&circle(p0, a, seg.side, r0, res), r0, tag, 0);
                b.fan(c, &l, false, tag)?;
                l
            }
        };
        let children = &piece.children;
        let is_base = seg.sections.is_some();
        if opts.subdivide && !is_base && piece.order == 0 {
            // Rings from just above the whole base loop (a junction's section may lean) up to the top.
            let base_point = seg.at(piece.t0);
            let lift = lower.ids.iter().map(|&v| dot(sub(b.pos[v as usize], base_point), a)).fold(0.0, f64::max);
            let t_lo = piece.t0 + lift;
            let spacing = core::f64::consts::TAU * (0.5 * (seg.radius(t_lo) + r_top)).max(1e-6) / res as f64;
            let count = (((piece.t1 - t_lo) / spacing).floor().max(0.0) as usize).min(64);
            for k in 1..count {
                let t = t_lo + (piece.t1 - t_lo) * k as f64 / count as f64;
                let ring =
                    b.contour(&circle(seg.at(t), a, seg.side, seg.radius(t), res), seg.radius(t), tag, lower.ring + 1);
                b.band(&lower, &ring.ids, tag)?;
                lower = ring;
            }
        }
        match children.len() {
            0 => {
                if r_top <= 1e-6 * seg.bottom.max(seg.top) {
                    let apex = b.vertex(o, 0.0, tag);
                    let n = lower.ids.len();
                    for i in 0..n {
                        b.push_tagged([lower.ids[i], lower.ids[(i + 1) % n], apex], tag, i as u32, lower.ring, true)?;
                    }
                } else {
                    if !is_base {
                        let top = b.contour(&circle(o, a, seg.side, r_top, res), r_top, tag, lower.ring + 1);
                        b.band(&lower, &top.ids, tag)?;
                        lower = top;
                    }
                    let c = b.vertex(o, r_top, tag);
                    b.fan(c, &lower, true, tag)?;
                }
            }
            1 => {
                let child = children[0];
                let top = if is_base {
                    lower
                } else {
                    let ac = sk.segment(child).axis;
                    let m = normalize(add(a, ac)).filter(|_| dot(a, ac) > -0.5).unwrap_or(a);
                    let bend = normalize(sub(ac, a)).unwrap_or(seg.side);
                    let cos_half = dot(m, a).max(0.3);
                    let r = r_top.max(1e-9);
                    let mitre = ellipse(o, m, bend, r / cos_half, r, res);
                    let top = b.contour(&mitre, r, tag, lower.ring + 1);
                    b.band(&lower, &top.ids, tag)?;
                    top
                };
                work.push((child, Some(top)));
            }
            _ => {
                let l = if is_base {
                    lower
                } else {
                    let top = b.contour(&circle(o, a, seg.side, r_top.max(1e-9), res), r_top, tag, lower.ring + 1);
                    b.band(&lower, &top.ids, tag)?;
                    top
                };
                let starts = junction(&mut b, &sk, id, o, a, r_top.max(1e-9), &l, opts)?;
                for (c, lp) in starts.into_iter().rev() {
                    work.push((c, Some(lp)));
                }
            }
        }
    }
    let positions: Vec<[f32; 3]> = b.pos.iter().map(|p| p.map(|x| x as f32)).collect();
    let indices: Vec<u32> = b.tris.iter().flatten().copied().collect();
    let normals = face_averaged_normals(&positions, &indices);
    let mut foliage_stream = PrimitiveStream { primitives: Vec::new(), leaf_points: stream.leaf_points.clone() };
    foliage_stream.primitives.extend(sk.foliage.iter().map(|&i| stream.primitives[i].clone()));
    Ok(ContinuousMesh {
        mesh: Mesh { positions, normals, colors: b.color, indices },
        radius: b.radius,
        order: b.order,
        tags: b.tags,
        foliage: mesh(&foliage_stream, &MeshOptions::default()),
        roots: sk.roots.len(),
    })
}

/// A child of a junction, seen from the junction.
struct Child {
    piece: usize,
    origin: V3,
    dir: V3,
    side: V3,
    length: f64,
    t0: f64,
    steep: bool,
}

/// The junction at the end of piece `id` with contour `l`; returns each child's base loop.
#[allow(clippy::too_many_arguments)]
fn junction(
    b: &mut Builder,
    sk: &Skeleton,
    id: usize,
    o: V3,
    a: V3,
    r: f64,
    l: &Loop,
    opts: &ContinuousOptions,
) -> Result<Vec<(usize, Loop)>, NearFieldError> {
    let res = opts.contour as usize;
    let ptag = Tag { piece: id as u32, order: sk.pieces[id].order, color: sk.segment(id).color, axis: a };
    let children: Vec<Child> = sk.pieces[id]
        .children
        .iter()
        .map(|&c| {
            let s = sk.segment(c);
            let p = &sk.pieces[c];
            Child {
                piece: c,
                origin: s.at(p.t0),
                dir: s.axis,
                side: s.side,
                length: p.t1 - p.t0,
                t0: p.t0,
                steep: dot(s.axis, a) < 0.342,
            }
        })
        .collect();
    let ctag = |c: &Child| Tag {
        piece: c.piece as u32,
        order: sk.pieces[c.piece].order,
        color: sk.segment(c.piece).color,
        axis: c.dir,
    };
    let radius_of = |c: &Child, t: f64| sk.segment(c.piece).radius(c.t0 + t);
    let mut starts: Vec<(usize, Loop)> = Vec::new();
    let ring = l.ring + 1;

    if !opts.refine {
        // Each child's base contour stands half the parent's radius up its own axis (at most half its length): a
        // continuation's contour at its origin would be the parent's contour `l` itself, or a copy turned about
        // the axis, and the band between them would have no area.
        let loops: Vec<Loop> = children
            .iter()
            .map(|c| {
                let t = (0.5 * r).min(0.5 * c.length);
                let r0 = radius_of(c, t).max(1e-9);
                b.contour(&circle(add(c.origin, scale(c.dir, t)), c.dir, c.side, r0, res), r0, ctag(c), ring)
            })
            .collect();
        let all: Vec<Vec<u32>> = loops.iter().map(|x| x.ids.clone()).collect();
        b.band(l, &bridge(&b.pos, &all), ptag)?;
        starts.extend(children.iter().zip(loops).map(|(c, lp)| (c.piece, lp)));
        return Ok(starts);
    }

    // Plane coordinates across the parent's axis.
    let x_axis = perpendicular(a);
    let y_axis = cross(a, x_axis);
    let to2 = |p: V3| {
        let q = sub(p, o);
        [dot(q, x_axis), dot(q, y_axis)]
    };
    let from2 = |q: [f64; 2], h: f64| add(o, add(add(scale(x_axis, q[0]), scale(y_axis, q[1])), scale(a, h)));
    // The section of child `c`'s cylinder by the plane at height `h`: centre, in-plane major direction, radii.
    let section = |c: &Child, h: f64| {
        let cos = dot(c.dir, a);
        let t = h / cos;
        let centre = add(c.origin, scale(c.dir, t));
        // A child along the parent's axis cuts the plane in a circle: its major direction is any (rounding would
        // otherwise make one up along the axis).
        let lean = sub(c.dir, scale(a, cos));
        let major = normalize(lean).filter(|_| norm(lean) > 1e-6).unwrap_or(x_axis);
        let rr = radius_of(c, t).max(1e-9);
        (centre, major, rr / cos, rr, t)
    };
    let fine = (4 * res).max(32);
    let polygon = |c: &Child, h: f64| -> Vec<[f64; 2]> {
        let (centre, major, ra, rb, _) = section(c, h);
        ellipse(centre, a, major, ra, rb, fine).into_iter().map(to2).collect()
    };
    // Steep children: a contour just outside the parent, across their own axis.
    let mut steep_loops: Vec<(usize, Loop)> = children
        .iter()
        .filter(|c| c.steep)
        .map(|c| {
            let t = (1.1 * r).min(0.5 * c.length);
            let rr = radius_of(c, t).max(1e-9);
            (c.piece, b.contour(&circle(add(c.origin, scale(c.dir, t)), c.dir, c.side, rr, res), rr, ctag(c), ring))
        })
        .collect();
    let delta = opts.interval * r;
    struct Group {
        members: Vec<usize>,
        lp: Loop,
    }
    let members: Vec<usize> = (0..children.len()).filter(|&i| !children[i].steep).collect();
    let mut active = if members.is_empty() { Vec::new() } else { vec![Group { members, lp: l.clone() }] };
    if active.is_empty() {
        let all: Vec<Vec<u32>> = steep_loops.iter().map(|(_, x)| x.ids.clone()).collect();
        b.band(l, &bridge(&b.pos, &all), ptag)?;
        return Ok(steep_loops);
    }
    for level in 1..=MAX_INTERVALS {
        let mut next = Vec::new();
        for g in active {
            let first = level == 1 && !steep_loops.is_empty();
            let mut h = delta * f64::from(level);
            // A child shorter than the plane: separate here, lower if need be (its contour must stay on it).
            let reach = g
                .members
                .iter()
                .map(|&i| 0.85 * children[i].length * dot(children[i].dir, a))
                .fold(f64::INFINITY, f64::min);
            let consumed = reach < h || level == MAX_INTERVALS;
            if consumed {
                h = reach.min(h).max(delta * (f64::from(level) - 0.9));
            }
            // Components of intersecting sections.
            let polys: Vec<Vec<[f64; 2]>> = g.members.iter().map(|&i| polygon(&children[i], h)).collect();
            let k = polys.len();
            let mut comp: Vec<usize> = (0..k).collect();
            if !consumed {
                for i in 0..k {
                    for j in i + 1..k {
                        if overlap(&polys[i], &polys[j]) {
                            let (ci, cj) = (comp[i], comp[j]);
                            let (lo, hi) = (ci.min(cj), ci.max(cj));
                            for c in comp.iter_mut() {
                                if *c == hi {
                                    *c = lo;
                                }
                            }
                        }
                    }
                }
            }
            let mut labels: Vec<usize> = comp.clone();
            labels.sort_unstable();
            labels.dedup();
            let mut parts: Vec<Loop> = Vec::new();
            // Each part is a merged contour of several children (`Ok`) or one child's section (`Err`).
            let mut part_groups: Vec<Result<Vec<usize>, usize>> = Vec::new();
            for &lab in &labels {
                let idx: Vec<usize> = (0..k).filter(|&i| comp[i] == lab).collect();
                if idx.len() > 1 {
                    let sub_polys: Vec<Vec<[f64; 2]>> = idx.iter().map(|&i| polys[i].clone()).collect();
                    if let Some(outline) = union_outline(&sub_polys) {
                        let count = ((res as f64 * perimeter(&outline) / (core::f64::consts::TAU * r)).round()
                            as usize)
                            .clamp(res, res * idx.len());
                        let pts: Vec<V3> = resample(&outline, count).into_iter().map(|q| from2(q, h)).collect();
                        let rr = idx.iter().map(|&i| section(&children[g.members[i]], h).3).fold(0.0, f64::max);
                        parts.push(b.contour(&pts, rr, ptag, g.lp.ring + 1));
                        part_groups.push(Ok(idx.iter().map(|&i| g.members[i]).collect()));
                        continue;
                    }
                }
                // Separated (or an outline that did not close): each child starts from its own section.
                for &i in &idx {
                    let c = &children[g.members[i]];
                    let (centre, major, ra, rb, _) = section(c, h);
                    parts.push(b.contour(&ellipse(centre, a, major, ra, rb, res), rb, ctag(c), g.lp.ring + 1));
                    part_groups.push(Err(g.members[i]));
                }
            }
            if parts.len() == 1 && !first {
                // Still one merged contour: a new contour of the junction.
                let lp = parts.pop().expect("one part");
                b.band(&g.lp, &lp.ids, ptag)?;
                match part_groups.pop() {
                    Some(Ok(members)) => next.push(Group { members, lp }),
                    Some(Err(i)) => starts.push((children[i].piece, lp)),
                    None => {}
                }
                continue;
            }
            // The group separates: its last contour goes to all parts at once, bridged at the crotches.
            let mut all: Vec<Vec<u32>> = parts.iter().map(|p| p.ids.clone()).collect();
            if first {
                all.extend(steep_loops.iter().map(|(_, x)| x.ids.clone()));
            }
            b.band(&g.lp, &bridge(&b.pos, &all), ptag)?;
            for (lp, grp) in parts.into_iter().zip(part_groups) {
                match grp {
                    Ok(members) => next.push(Group { members, lp }),
                    Err(i) => starts.push((children[i].piece, lp)),
                }
            }
            if first {
                starts.append(&mut steep_loops);
            }
        }
        active = next;
        if active.is_empty() {
            break;
        }
    }
    Ok(starts)
}
