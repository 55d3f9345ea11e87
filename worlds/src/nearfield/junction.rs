//! Branch junctions as seed 002 §3.3 builds them, one mesh per branch (the alternative to the continuous mesh):
//!
//! - **I junction** (a continuation: one child at the parent's top, bent by less than 45°): the parent's
//!   cylinder is extrapolated into the child's — both end on the same contour, the section of the parent's
//!   cylinder by the plane bisecting the bend — so no seam shows.
//! - **T junction** (a lateral growing out of a parent that extends further): the child's base is not a flat
//!   circle but follows the parent's surface — for every point of the base the child's generator line is cut
//!   where it leaves the parent's cylinder, which varies sinusoidally around the child — and is embedded a
//!   further `embed` times the child's radius into the parent, so the joint has no gap.
//! - **Y junction** (several children at the parent's top, or one bent by more than 45°): the parent is closed
//!   by a spherical cap of its top radius, and the children get sinusoidal bases embedded into the parent's
//!   cylinder and cap as for T.
//!
//! Vertex normals are averaged over the faces that share the vertex (§4).

use core::f64::consts::{FRAC_PI_2, TAU};

use crate::mesh::Mesh;
use crate::nearfield::skeleton::{Segment, Skeleton};
use crate::nearfield::{V3, add, cross, dot, face_averaged_normals, normalize, perpendicular, scale, sub};
use crate::primitive::PrimitiveStream;

/// How junction meshes are built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JunctionOptions {
    /// Points around each branch (`3..=256`).
    pub radial: u32,
    /// How deep a child's base is embedded into its parent, as a fraction of the child's radius.
    pub embed: f64,
    /// Latitude rings of a Y junction's spherical cap.
    pub cap_rings: u32,
}

impl Default for JunctionOptions {
    fn default() -> Self {
        JunctionOptions { radial: 16, embed: 0.3, cap_rings: 4 }
    }
}

/// How a segment meets its parent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JunctionKind {
    /// No parent: the base is closed by a flat cap.
    Root,
    /// Continuation of the parent (shared mitre contour).
    I,
    /// Lateral on the parent's side.
    T,
    /// One of several children at the parent's top, or a strongly bent one.
    Y,
}

/// Each segment's junction with its parent and its parent's segment index (as [`Skeleton::segments`] orders them).
pub fn classify(sk: &Skeleton) -> Vec<(JunctionKind, Option<usize>)> {
    let mut out = vec![(JunctionKind::Root, None); sk.segments.len()];
    let mut last_piece = vec![usize::MAX; sk.segments.len()];
    for (id, p) in sk.pieces.iter().enumerate() {
        last_piece[p.segment] = id;
    }
    for (id, p) in sk.pieces.iter().enumerate() {
        if p.t0 != 0.0 {
            continue;
        }
        let Some(parent) = p.parent else { continue };
        let host = sk.pieces[parent].segment;
        let kind = if last_piece[host] != parent {
            JunctionKind::T
        } else {
            let siblings = sk.pieces[parent].children.len();
            let bend = dot(sk.segments[host].axis, sk.segments[p.segment].axis);
            if siblings == 1 && bend > libm::cos(FRAC_PI_2 / 2.0) { JunctionKind::I } else { JunctionKind::Y }
        };
        let _ = id;
        out[p.segment] = (kind, Some(host));
    }
    out
}

/// Mesh every frustum of a stream with seed 002's junctions (trunk bases and foliage are left to the ordinary
/// mesher).
pub fn junction_mesh(stream: &PrimitiveStream, opts: &JunctionOptions) -> Mesh {
    let sk = Skeleton::from_stream(stream);
    let kinds = classify(&sk);
    let n = opts.radial.clamp(3, 256) as usize;
    let mut out = Mesh::default();
    // Which segments are capped by a sphere (Y parents) or continue into an I child.
    let mut sphere_top = vec![false; sk.segments.len()];
    let mut i_child = vec![None; sk.segments.len()];
    for (s, &(kind, host)) in kinds.iter().enumerate() {
        match (kind, host) {
            (JunctionKind::Y, Some(h)) => sphere_top[h] = true,
            (JunctionKind::I, Some(h)) => i_child[h] = Some(s),
            _ => {}
        }
    }
    for (s, seg) in sk.segments.iter().enumerate() {
        if seg.sections.is_some() {
            continue;
        }
        let mut m = Mesh::default();
        let (kind, host) = kinds[s];
        // The base contour.
        let base: Vec<V3> = match (kind, host) {
            (JunctionKind::I, Some(h)) => mitre(&sk.segments[h], seg, n),
            (JunctionKind::T | JunctionKind::Y, Some(h)) => {
                embedded_base(&sk.segments[h], seg, n, opts.embed, kind == JunctionKind::Y)
            }
            _ => ring(seg, 0.0, n),
        };
        let top: Vec<V3> = match i_child[s] {
            Some(c) => mitre(seg, &sk.segments[c], n),
            None => ring(seg, seg.length, n),
        };
        let color = seg.color;
        let push = |m: &mut Mesh, p: V3| {
            m.positions.push(p.map(|x| x as f32));
            m.colors.push(color);
            (m.positions.len() - 1) as u32
        };
        let b0 = m.positions.len() as u32;
        for &p in &base {
            push(&mut m, p);
        }
        let t0 = m.positions.len() as u32;
        for &p in &top {
            push(&mut m, p);
        }
        let nn = n as u32;
        for j in 0..nn {
            let jn = (j + 1) % nn;
            m.indices.extend_from_slice(&[b0 + j, b0 + jn, t0 + j, b0 + jn, t0 + jn, t0 + j]);
        }
        if kind == JunctionKind::Root {
            let c = push(&mut m, seg.base);
            for j in 0..nn {
                m.indices.extend_from_slice(&[c, b0 + (j + 1) % nn, b0 + j]);
            }
        }
        if i_child[s].is_none() {
            let o = seg.top_centre();
            if sphere_top[s] && seg.top > 0.0 {
                // A spherical cap of the top radius: latitude rings up to the pole.
                let rings = opts.cap_rings.max(1);
                let mut prev = t0;
                for k in 1..=rings {
                    let phi = FRAC_PI_2 * f64::from(k) / f64::from(rings);
                    if k == rings {
                        let pole = push(&mut m, add(o, scale(seg.axis, seg.top)));
                        for j in 0..nn {
                            m.indices.extend_from_slice(&[prev + j, prev + (j + 1) % nn, pole]);
                        }
                    } else {
                        let r = seg.top * libm::cos(phi);
                        let c = add(o, scale(seg.axis, seg.top * libm::sin(phi)));
                        let start = m.positions.len() as u32;
                        for p in circle_at(seg, c, r, n) {
                            push(&mut m, p);
                        }
                        for j in 0..nn {
                            let jn = (j + 1) % nn;
                            m.indices.extend_from_slice(&[
                                prev + j,
                                prev + jn,
                                start + j,
                                prev + jn,
                                start + jn,
                                start + j,
                            ]);
                        }
                        prev = start;
                    }
                }
            } else if seg.top > 0.0 {
                let c = push(&mut m, o);
                for j in 0..nn {
                    m.indices.extend_from_slice(&[c, t0 + j, t0 + (j + 1) % nn]);
                }
            }
        }
        m.normals = face_averaged_normals(&m.positions, &m.indices);
        out.append(&m, [0.0; 3]);
    }
    out
}

fn frame(seg: &Segment) -> (V3, V3) {
    let u =
        normalize(sub(seg.side, scale(seg.axis, dot(seg.side, seg.axis)))).unwrap_or_else(|| perpendicular(seg.axis));
    (u, cross(seg.axis, u))
}

fn circle_at(seg: &Segment, c: V3, r: f64, n: usize) -> Vec<V3> {
    let (u, v) = frame(seg);
    (0..n)
        .map(|j| {
            let a = TAU * j as f64 / n as f64;
            add(c, add(scale(u, r * libm::cos(a)), scale(v, r * libm::sin(a))))
        })
        .collect()
}

fn ring(seg: &Segment, t: f64, n: usize) -> Vec<V3> {
    circle_at(seg, seg.at(t), seg.radius(t), n)
}

/// The contour shared by a parent and its continuation: the parent's top ring projected along the parent's
/// axis onto the plane bisecting the bend (the parent cylinder extrapolated to the mitre).
fn mitre(parent: &Segment, child: &Segment, n: usize) -> Vec<V3> {
    let o = parent.top_centre();
    let m = normalize(add(parent.axis, child.axis)).unwrap_or(parent.axis);
    let denom = dot(parent.axis, m).max(0.3);
    ring(parent, parent.length, n)
        .into_iter()
        .map(|p| {
            let t = -dot(sub(p, o), m) / denom;
            add(p, scale(parent.axis, t))
        })
        .collect()
}

/// A child's base that follows the parent's surface: each base point is moved along the child's axis to where
/// its generator line leaves the parent's cylinder (or, on a Y junction, the spherical cap), then `embed` times
/// the child's radius back into the parent.
fn embedded_base(parent: &Segment, child: &Segment, n: usize, embed: f64, cap: bool) -> Vec<V3> {
    let d = child.axis;
    let r0 = child.bottom.max(1e-9);
    ring(child, 0.0, n)
        .into_iter()
        .map(|p| {
            let q = sub(p, parent.base);
            let qa = dot(q, parent.axis);
            let qp = sub(q, scale(parent.axis, qa));
            let dp = sub(d, scale(parent.axis, dot(d, parent.axis)));
            let r = parent.radius(qa.clamp(0.0, parent.length));
            let (aa, bb, cc) = (dot(dp, dp), dot(qp, dp), dot(qp, qp) - r * r);
            let mut t = 0.0f64;
            if aa > 1e-12 && bb * bb - aa * cc >= 0.0 {
                let exit = (-bb + libm::sqrt(bb * bb - aa * cc)) / aa;
                if dot(add(q, scale(d, exit)), parent.axis) <= parent.length || !cap {
                    t = exit;
                }
            }
            if cap {
                let s = sub(p, parent.top_centre());
                let (bs, cs) = (dot(s, d), dot(s, s) - parent.top * parent.top);
                if bs * bs - cs >= 0.0 {
                    t = t.max(-bs + libm::sqrt(bs * bs - cs));
                }
            }
            let t = t.clamp(-2.0 * r0, 0.9 * child.length) - embed * r0;
            add(p, scale(d, t))
        })
        .collect()
}
