//! Double bark (seed 002 §3.2): over the inner bark — the surface itself — an outer layer of the same triangles
//! pushed out by the bark depth, each shrunk and some chiselled out, so the older outer bark looks cracked and
//! fissured over the younger inner one.
//!
//! - **Shrink** (first chisel factor): the outer layer is cut into plates (a column of quads three rings tall),
//!   and every plate shrinks about its centroid by a pseudo-random factor in `[1 − shrink, 1]` across the branch
//!   and by up to 0.3 of that along its vertical direction: the radial pressure opens vertical cracks.
//! - **Remove** (second chisel factor): fissures along the vertical — each column of plates around the trunk
//!   is cut into runs of six rings, and a run is removed with probability `removal`.
//!
//! Draws come from ChaCha8 ([`crate::rng::InstanceRng`]) addressed by piece, column and run or ring, with the
//! explicit bit→float formula of [`crate::eval::unit_f32`]: the same tree gets the same bark everywhere.

use std::collections::BTreeMap;

use crate::eval::unit_f32;
use crate::mesh::Mesh;
use crate::nearfield::{NearFieldError, V3, add, dot, scale, sub};
use crate::rng::InstanceRng;

/// Which chisel effects the outer bark gets (the paper's chisel mode).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ChiselMode {
    /// Shrink the outer triangles.
    Shrink,
    /// Remove runs of outer triangles.
    Remove,
    /// Both.
    Both,
}

impl ChiselMode {
    /// 1 shrink, 2 remove, anything else both (the numbers of a species file's `chisel`).
    pub fn from_number(v: f32) -> ChiselMode {
        match v.round() as i64 {
            1 => ChiselMode::Shrink,
            2 => ChiselMode::Remove,
            _ => ChiselMode::Both,
        }
    }

    fn shrinks(self) -> bool {
        self != ChiselMode::Remove
    }

    fn removes(self) -> bool {
        self != ChiselMode::Shrink
    }
}

/// The outer bark's parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BarkOptions {
    /// Bark depth: how far the outer bark stands off the inner one, metres.
    pub depth: f32,
    /// Chisel mode.
    pub chisel: ChiselMode,
    /// First chisel factor, `0..=0.95`: how much a triangle may shrink.
    pub shrink: f32,
    /// Second chisel factor, `0..=1`: the probability that a run of triangles is removed.
    pub removal: f32,
    /// Seeds the draws (the instance seed).
    pub seed: u64,
}

impl BarkOptions {
    /// Check the ranges.
    pub fn check(&self) -> Result<(), NearFieldError> {
        if !(self.depth > 0.0 && self.depth.is_finite()) {
            return Err(NearFieldError::Option { name: "bark depth", value: self.depth });
        }
        if !(0.0..=0.95).contains(&self.shrink) {
            return Err(NearFieldError::Option { name: "shrink", value: self.shrink });
        }
        if !(0.0..=1.0).contains(&self.removal) {
            return Err(NearFieldError::Option { name: "removal", value: self.removal });
        }
        Ok(())
    }
}

/// Where an inner triangle sits on its branch: which branch piece, column around it, ring along it, and the
/// vertical direction. Triangles with the same piece, column and ring (the two halves of a quad) make one plate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BarkPlace {
    /// The branch piece (any number that tells branches apart).
    pub piece: u32,
    /// Column around the branch.
    pub column: u32,
    /// Ring along the branch.
    pub ring: u32,
    /// Unit vertical (axis) direction.
    pub up: [f32; 3],
}

/// Rings of triangles one outer bark plate spans (plates are taller than wide, like bark's).
const PLATE_RINGS: u32 = 3;

/// Streams of the bark's draws.
const REMOVAL_STREAM: u64 = 0x6261_726b_0000_0000;
const SHRINK_STREAM: u64 = 0x6261_726b_0000_0001;

/// The outer bark over the triangles of `inner` for which `place` is `Some`: its corners moved out along the inner
/// vertex normals by the depth, one plate per piece, column and ring (the two triangles of a quad), each shrunk
/// about its centroid and kept or chiselled out as a whole; plates have their own vertices and are wound like the
/// inner triangles. Colours are the inner ones darkened and greyed: older bark over the younger inner bark.
pub fn outer_bark(inner: &Mesh, place: &[Option<BarkPlace>], opts: &BarkOptions) -> Result<Mesh, NearFieldError> {
    opts.check()?;
    let mut rng = InstanceRng::new(opts.seed);
    let depth = f64::from(opts.depth);
    let offset = |i: u32| {
        let p = inner.positions[i as usize].map(f64::from);
        let n = inner.normals[i as usize].map(f64::from);
        add(p, scale(n, depth))
    };
    // Plates: the centroid of their offset corners, in first-seen order.
    let mut plates: BTreeMap<(u32, u32, u32), (V3, f64)> = BTreeMap::new();
    for (t, tri) in inner.indices.chunks_exact(3).enumerate() {
        let Some(pl) = place.get(t).copied().flatten() else { continue };
        let e = plates.entry((pl.piece, pl.column, pl.ring / PLATE_RINGS)).or_insert(([0.0; 3], 0.0));
        for &i in tri {
            e.0 = add(e.0, offset(i));
            e.1 += 1.0;
        }
    }
    let mut out = Mesh::default();
    for (t, tri) in inner.indices.chunks_exact(3).enumerate() {
        let Some(pl) = place.get(t).copied().flatten() else { continue };
        if opts.chisel.removes() && opts.removal > 0.0 {
            let u = unit_f32(rng.word(
                REMOVAL_STREAM ^ u64::from(pl.column) ^ u64::from(pl.piece) << 32,
                u64::from(pl.ring / (2 * PLATE_RINGS)),
            ));
            if u < opts.removal {
                continue;
            }
        }
        let (sum, count) = plates[&(pl.piece, pl.column, pl.ring / PLATE_RINGS)];
        let g = scale(sum, 1.0 / count);
        let (fv, fh) = if opts.chisel.shrinks() {
            let stream = SHRINK_STREAM ^ u64::from(pl.column) ^ u64::from(pl.piece) << 32;
            let plate = u64::from(pl.ring / PLATE_RINGS);
            let u1 = f64::from(unit_f32(rng.word(stream, 2 * plate)));
            let u2 = f64::from(unit_f32(rng.word(stream, 2 * plate + 1)));
            (1.0 - 0.3 * f64::from(opts.shrink) * u1, 1.0 - f64::from(opts.shrink) * u2)
        } else {
            (1.0, 1.0)
        };
        let up = pl.up.map(f64::from);
        let base = out.positions.len() as u32;
        for &i in tri {
            let d = sub(offset(i), g);
            let vertical = scale(up, dot(d, up));
            let across = sub(d, vertical);
            let q = add(g, add(scale(vertical, fv), scale(across, fh)));
            out.positions.push(q.map(|x| x as f32));
            out.normals.push(inner.normals[i as usize]);
            let c = inner.colors[i as usize];
            out.colors.push([c[0] * 0.55, c[1] * 0.5, c[2] * 0.45]);
        }
        out.indices.extend_from_slice(&[base, base + 1, base + 2]);
    }
    Ok(out)
}

/// Where the double bark goes on a continuous mesh: the sides of the trunk's axis (branching order 0, trunk base
/// included), as the paper double-barks the trunk and gives branches a single bark; caps get none.
pub fn trunk_places(tags: &[crate::nearfield::continuous::TriangleTag]) -> Vec<Option<BarkPlace>> {
    tags.iter()
        .map(|t| {
            (t.order == 0 && !t.cap).then_some(BarkPlace { piece: t.piece, column: t.column, ring: t.ring, up: t.axis })
        })
        .collect()
}
