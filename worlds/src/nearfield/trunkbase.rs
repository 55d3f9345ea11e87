//! The trunk–root junction of seed 002 §3.1 and §4: a stack of horizontal cross-sections that go from a
//! hypocycloid at the ground (an astroid by default: four root flares) to a circle at the top of the base.
//!
//! Two transitions, as the paper describes them:
//! - [`Transition::Ellipses`] (default): every cross-section is the envelope of co-axial generator ellipses whose
//!   semi-axes have a constant sum at that level ([`GeneratorEllipses`]); going up, the sum moves from the ground
//!   value to twice the top radius and the spread of the family shrinks to zero, so the astroid's cusps retract
//!   and the section becomes the circle.
//! - [`Transition::Folium`]: the exact hypocycloid at the ground, a rose with one petal per cusp (the
//!   quadrifolium for four) half-way, and the circle at the top, blended by cubic Hermite interpolation.
//!
//! The base randomiser adds the semi-random perturbation: each root flare gets its own reach and a small turn,
//! and every section a few low harmonics, all fading out towards the top. Its draws come from ChaCha8 seeded by
//! the primitive's `seed` (the species draws it per instance), with the explicit bit→float formula of
//! [`crate::eval::unit_f32`]. The tilt spread shears the sections towards +Z.
//!
//! Sizes: the base radius `r_b` is the section's radius between the flares; the flares reach `spread · r_b`.
//! With `spread = 2` and no perturbation the ground section is exactly the astroid of cusp radius `2 r_b` (in the
//! limit of many generator ellipses).

use core::f64::consts::{PI, TAU};

use crate::eval::{Draw, unit_f32};
use crate::nearfield::curves::{GeneratorEllipses, hypocycloid_radius};
use crate::nearfield::{NearFieldError, Surface};
use crate::rng::{Context, InstanceRng};

/// Most points on one cross-section.
pub const MAX_RESOLUTION: u32 = 1024;
/// Most generator ellipses in one family.
pub const MAX_ELLIPSES: u32 = 512;
/// Most cusps (root flares).
pub const MAX_LOBES: u32 = 16;
/// Most cross-sections stacked up one trunk base.
pub const MAX_LEVELS: u32 = 256;

/// How the cross-sections go from the hypocycloid to the circle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Transition {
    /// Envelopes of generator ellipses with a constant sum of semi-axes per level (the paper's construction).
    Ellipses,
    /// Hypocycloid → rose (quadrifolium for four cusps) → circle, blended by cubic Hermite interpolation.
    Folium,
}

/// A trunk base as traversal evaluated it (the numbers of [`canopy_protocol::species::TrunkBaseNode`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrunkBase {
    /// Base spread factor (≥ 1): the flares reach `spread · bottom`.
    pub spread: f32,
    /// Height of the base.
    pub height: f32,
    /// Base radius, between the flares at the ground.
    pub bottom: f32,
    /// Top radius.
    pub top: f32,
    /// Tilt spread in degrees (towards +Z), below 60.
    pub tilt: f32,
    /// Cusps, rounded and clamped to `3..=16`.
    pub lobes: f32,
    /// Generator ellipse count, rounded and clamped to `1..=512`.
    pub ellipses: f32,
    /// Curve resolution: points per cross-section, rounded and clamped to `8..=1024`.
    pub resolution: f32,
    /// Base randomiser factor in `0..=1`.
    pub randomiser: f32,
    /// 0: [`Transition::Ellipses`]; otherwise [`Transition::Folium`].
    pub transition: f32,
    /// Seeds the perturbation (its bits are the ChaCha8 seed).
    pub seed: f32,
}

impl Default for TrunkBase {
    fn default() -> Self {
        TrunkBase {
            spread: 2.0,
            height: 1.5,
            bottom: 0.4,
            top: 0.3,
            tilt: 0.0,
            lobes: 4.0,
            ellipses: 32.0,
            resolution: 48.0,
            randomiser: 0.0,
            transition: 0.0,
            seed: 0.0,
        }
    }
}

/// One horizontal cross-section of a trunk base: its level `s` in `0..=1`, centre and points (counter-clockwise
/// seen from above), in the primitive's local frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Section {
    /// Level: 0 at the ground, 1 at the top.
    pub level: f64,
    /// Centre of the section.
    pub centre: [f64; 3],
    /// The contour's points.
    pub points: Vec<[f64; 3]>,
}

/// The per-instance perturbation: reach and turn of every flare, and low harmonics of every section.
struct Perturbation {
    reach: Vec<f64>,
    phase: Vec<f64>,
    harmonics: Vec<(f64, f64, f64)>,
}

impl TrunkBase {
    /// How many numbers a trunk base has (those of [`canopy_protocol::species::TrunkBaseNode`]).
    pub const LEN: usize = canopy_protocol::species::TrunkBaseNode::LEN;

    /// The numbers in field order (the order of the node's expressions, hashed in primitive streams).
    pub fn to_array(&self) -> [f32; TrunkBase::LEN] {
        let TrunkBase { spread, height, bottom, top, tilt, lobes, ellipses, resolution, randomiser, transition, seed } =
            *self;
        [spread, height, bottom, top, tilt, lobes, ellipses, resolution, randomiser, transition, seed]
    }

    /// The frustum that holds the flares, `(bottom radius, top radius, height)` standing on the origin along +Y:
    /// what bounds and voxelises a trunk base.
    pub fn bounding_cone(&self) -> (f32, f32, f32) {
        (self.bottom * self.spread.max(1.0), self.top, self.height)
    }

    /// The trunk base from its numbers in field order (the inverse of [`TrunkBase::to_array`]).
    pub fn from_array(v: [f32; TrunkBase::LEN]) -> TrunkBase {
        let [spread, height, bottom, top, tilt, lobes, ellipses, resolution, randomiser, transition, seed] = v;
        TrunkBase { spread, height, bottom, top, tilt, lobes, ellipses, resolution, randomiser, transition, seed }
    }

    /// The number of cusps.
    pub fn cusps(&self) -> u32 {
        clamp_round(self.lobes, 3, MAX_LOBES)
    }

    /// Points per cross-section.
    pub fn points_per_section(&self) -> u32 {
        clamp_round(self.resolution, 8, MAX_RESOLUTION)
    }

    /// The transition.
    pub fn transition_kind(&self) -> Transition {
        if self.transition == 0.0 || self.transition.is_nan() { Transition::Ellipses } else { Transition::Folium }
    }

    /// Check the sizes: positive finite height and radii, spread at least 1, tilt below 60 degrees, randomiser in
    /// `0..=1`.
    pub fn check(&self) -> Result<(), NearFieldError> {
        let positive = |name: &'static str, v: f32| {
            if v > 0.0 && v.is_finite() { Ok(()) } else { Err(NearFieldError::TrunkBase { name, value: v }) }
        };
        positive("height", self.height)?;
        positive("bottom", self.bottom)?;
        positive("top", self.top)?;
        if !(self.spread >= 1.0 && self.spread.is_finite()) {
            return Err(NearFieldError::TrunkBase { name: "spread", value: self.spread });
        }
        if self.tilt.is_nan() || self.tilt.abs() >= 60.0 {
            return Err(NearFieldError::TrunkBase { name: "tilt", value: self.tilt });
        }
        if !(0.0..=1.0).contains(&self.randomiser) {
            return Err(NearFieldError::TrunkBase { name: "randomiser", value: self.randomiser });
        }
        for (name, v) in [("lobes", self.lobes), ("ellipses", self.ellipses), ("resolution", self.resolution)] {
            if !v.is_finite() {
                return Err(NearFieldError::TrunkBase { name, value: v });
            }
        }
        Ok(())
    }

    /// Number of cross-sections above the ground one: about square quads on the trunk, in `4..=256`.
    pub fn levels(&self) -> u32 {
        let n = f64::from(self.points_per_section());
        let around = PI * (f64::from(self.bottom) + f64::from(self.top));
        let l = libm::ceil(n * f64::from(self.height) / around.max(1e-9));
        if l.is_nan() { 4 } else { (l as u32).clamp(4, MAX_LEVELS) }
    }

    /// Triangles of [`TrunkBase::surface`]: two per quad of the sides and one per point on each cap.
    pub fn triangle_count(&self) -> usize {
        let (n, l) = (self.points_per_section() as usize, self.levels() as usize);
        2 * n * l + 2 * n
    }

    fn perturbation(&self) -> Perturbation {
        let n = self.cusps() as usize;
        let rho = f64::from(self.randomiser.clamp(0.0, 1.0));
        let mut rng = InstanceRng::new(u64::from(self.seed.to_bits()));
        let mut ctx = Context { rng: &mut rng, key: 0, counter: 0 };
        let mut draw = || f64::from(unit_f32(ctx.next_u32()));
        let lobe = TAU / n as f64;
        let mut reach = Vec::with_capacity(n);
        let mut phase = Vec::with_capacity(n);
        for _ in 0..n {
            reach.push(1.0 - 0.6 * rho * draw());
            phase.push(0.3 * rho * lobe * (draw() - 0.5));
        }
        let harmonics = (2..6)
            .map(|m| {
                let amp = 0.05 * rho * draw() / f64::from(m);
                (f64::from(m), amp, TAU * draw())
            })
            .collect();
        Perturbation { reach, phase, harmonics }
    }

    /// The cross-section radius in direction `theta` at level `s` (0 ground, 1 top).
    fn radius(&self, p: &Perturbation, family: Option<&GeneratorEllipses>, theta: f64, s: f64) -> f64 {
        let (rb, rt, spread) = (f64::from(self.bottom), f64::from(self.top), f64::from(self.spread));
        let n = self.cusps();
        let base = match (self.transition_kind(), family) {
            (Transition::Ellipses, Some(f)) => f.lobed_radius(n, &p.reach, &p.phase, theta),
            _ => {
                let lobe = TAU / f64::from(n);
                let k = (libm::round(theta / lobe) as i64).rem_euclid(i64::from(n)) as usize;
                let reach = p.reach.get(k).copied().unwrap_or(1.0);
                let t = theta - p.phase.get(k).copied().unwrap_or(0.0);
                // Ground: the exact hypocycloid with cusps at `spread · r_b`, filled out to the trunk's radius.
                let hyp = rb + (spread * rb * hypocycloid_radius(n, t) - rb).max(0.0) * reach;
                // Half-way: a rose with a petal on every cusp (the quadrifolium for four).
                let (core, tip) = (0.5 * (rb + rt), 0.5 * (rb + rt) + 0.5 * (spread - 1.0) * rb * reach);
                let rose = core + (tip - core) * libm::fabs(libm::cos(0.5 * f64::from(n) * t));
                if s < 0.5 { lerp(hyp, rose, smoothstep(2.0 * s)) } else { lerp(rose, rt, smoothstep(2.0 * s - 1.0)) }
            }
        };
        let fade = (1.0 - s) * (1.0 - s);
        let wobble: f64 = p.harmonics.iter().map(|&(m, amp, ph)| amp * libm::sin(m * theta + ph)).sum();
        base * (1.0 + fade * wobble)
    }

    /// The generator ellipse family at level `s`: the semi-axis sum goes from `c₀` at the ground to `2 r_t` at the
    /// top and the spread from `w₀` to 0, both along `e = 1 − (1 − s)²` (the flares fall off fast).
    pub fn family(&self, s: f64) -> GeneratorEllipses {
        let (rb, rt, spread) = (f64::from(self.bottom), f64::from(self.top), f64::from(self.spread));
        let c0 = spread.max(2.0) * rb;
        let w0 = 2.0 * spread * rb - c0;
        let e = 1.0 - (1.0 - s) * (1.0 - s);
        GeneratorEllipses::new(clamp_round(self.ellipses, 1, MAX_ELLIPSES), lerp(c0, 2.0 * rt, e), w0 * (1.0 - e))
    }

    /// The cross-sections from the ground (level 0) to the top (level 1), `levels() + 1` of them, each with
    /// `points_per_section()` points at angles `2πj / n`, counter-clockwise seen from above
    /// (`(r cos θ, 0, −r sin θ)` about the centre).
    pub fn sections(&self) -> Result<Vec<Section>, NearFieldError> {
        self.check()?;
        let p = self.perturbation();
        let (n, levels) = (self.points_per_section(), self.levels());
        let shear = libm::tan(f64::from(self.tilt).to_radians());
        let h = f64::from(self.height);
        let mut out = Vec::with_capacity(levels as usize + 1);
        for k in 0..=levels {
            let s = f64::from(k) / f64::from(levels);
            let family = (self.transition_kind() == Transition::Ellipses).then(|| self.family(s));
            let centre = [0.0, s * h, s * h * shear];
            let points = (0..n)
                .map(|j| {
                    let theta = TAU * f64::from(j) / f64::from(n);
                    let r = if k == levels { f64::from(self.top) } else { self.radius(&p, family.as_ref(), theta, s) };
                    [centre[0] + r * libm::cos(theta), centre[1], centre[2] - r * libm::sin(theta)]
                })
                .collect();
            out.push(Section { level: s, centre, points });
        }
        Ok(out)
    }

    /// The closed surface: the sections joined by quads (two triangles each), a flat cap on the ground and one on
    /// top (their own vertices, so the rim stays sharp). Side normals are averaged over the faces that share the
    /// vertex (seed 002 §4).
    pub fn surface(&self) -> Result<Surface, NearFieldError> {
        let sections = self.sections()?;
        let n = sections[0].points.len() as u32;
        let mut s = Surface::default();
        for sec in &sections {
            s.positions.extend(sec.points.iter().map(|p| p.map(|x| x as f32)));
        }
        for k in 0..sections.len() as u32 - 1 {
            let (a, b) = (k * n, (k + 1) * n);
            for j in 0..n {
                let jn = (j + 1) % n;
                s.indices.extend_from_slice(&[a + j, a + jn, b + j, a + jn, b + jn, b + j]);
            }
        }
        s.normals = crate::nearfield::face_averaged_normals(&s.positions, &s.indices);
        for (sec, down) in [(&sections[0], true), (&sections[sections.len() - 1], false)] {
            let normal = if down { [0.0, -1.0, 0.0] } else { [0.0, 1.0, 0.0] };
            let c = s.positions.len() as u32;
            s.positions.push(sec.centre.map(|x| x as f32));
            s.normals.push(normal);
            s.positions.extend(sec.points.iter().map(|p| p.map(|x| x as f32)));
            s.normals.extend(std::iter::repeat_n(normal, n as usize));
            for j in 0..n {
                let (p, q) = (c + 1 + j, c + 1 + (j + 1) % n);
                if down {
                    s.indices.extend_from_slice(&[c, q, p]);
                } else {
                    s.indices.extend_from_slice(&[c, p, q]);
                }
            }
        }
        Ok(s)
    }
}

fn clamp_round(v: f32, lo: u32, hi: u32) -> u32 {
    if v.is_nan() { lo } else { (libm::roundf(v).max(lo as f32).min(hi as f32)) as u32 }
}

fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a + (b - a) * t
}

/// Cubic Hermite interpolation with zero end slopes, `3t² − 2t³` on `0..=1`.
fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}
