//! IFS transformations resolved for one tree: random parameter values fixed once from the instance seed (§3.2),
//! consecutive linear elementary transformations folded into one affine matrix, and nonlinear shears (§3.1) kept
//! as their own step — one pipeline per transformation and parameter level (§3.4, Figure 2). Also the transport of
//! bounding spheres through a pipeline (§8.2) and condensation sampling (§3.3).

use std::f32::consts::PI;

use canopy_protocol::hypertree::{Cone, Elementary, HypertreeDef, Param};

use crate::eval::{Draw, unit_f32};
use crate::rng::{Context, InstanceRng};
use crate::transform::Transform;

/// One step of a resolved pipeline.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Step {
    /// An affine map (several translations, rotations and scales folded together).
    Affine(Transform),
    /// The nonlinear shear: `p[others] += max · |clamp(p[axis], −1, 1)|^exponent`.
    Shear {
        /// The bending axis index.
        axis: usize,
        /// The two displaced axes.
        others: [usize; 2],
        /// Maximum displacements.
        max: [f32; 2],
        /// Bending exponent.
        exponent: Exponent,
    },
}

/// A shear exponent: small integers are evaluated by multiplication, others by `libm::powf`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Exponent {
    /// An integer exponent 0..=16.
    Int(u32),
    /// Any other exponent.
    Real(f32),
}

impl Exponent {
    fn of(e: f32) -> Exponent {
        if e == libm::floorf(e) && (0.0..=16.0).contains(&e) { Exponent::Int(e as u32) } else { Exponent::Real(e) }
    }

    #[inline]
    fn pow(self, h: f32) -> f32 {
        match self {
            Exponent::Int(n) => {
                let mut r = 1.0f32;
                for _ in 0..n {
                    r *= h;
                }
                r
            }
            Exponent::Real(e) => libm::powf(h, e),
        }
    }
}

/// A resolved transformation at one parameter level: its steps, in application order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Pipeline {
    /// The steps.
    pub steps: Vec<Step>,
}

impl Pipeline {
    /// Apply to a point.
    #[inline]
    pub fn apply(&self, mut p: [f32; 3]) -> [f32; 3] {
        if let [Step::Affine(t)] = self.steps.as_slice() {
            return t.point(p);
        }
        for s in &self.steps {
            match *s {
                Step::Affine(t) => p = t.point(p),
                Step::Shear { axis, others, max, exponent } => {
                    let h = p[axis].clamp(-1.0, 1.0).abs();
                    let f = exponent.pow(h);
                    p[others[0]] += max[0] * f;
                    p[others[1]] += max[1] * f;
                }
            }
        }
        p
    }

    /// Transport a bounding sphere (§8.2): move the centre, recondition the radius — by the largest singular value
    /// bound (Frobenius norm) for affine steps, by the paper's `(1 + d_max / r)²` for shears.
    pub fn sphere(&self, mut center: [f32; 3], mut radius: f32) -> ([f32; 3], f32) {
        for s in &self.steps {
            match *s {
                Step::Affine(t) => {
                    center = t.point(center);
                    let m = &t.m;
                    let frob = libm::sqrtf([0, 1, 2, 4, 5, 6, 8, 9, 10].iter().map(|&i| m[i] * m[i]).sum::<f32>());
                    radius *= frob;
                }
                Step::Shear { max, .. } => {
                    center = Pipeline { steps: vec![*s] }.apply(center);
                    let d = libm::sqrtf(max[0] * max[0] + max[1] * max[1]);
                    let r = radius.max(1e-6);
                    radius = r * (1.0 + d / r) * (1.0 + d / r);
                }
            }
        }
        (center, radius)
    }

    fn push_affine(&mut self, t: Transform) {
        if let Some(Step::Affine(prev)) = self.steps.last_mut() {
            *prev = t.mul(prev);
        } else {
            self.steps.push(Step::Affine(t));
        }
    }
}

/// A condensation resolved for one tree.
#[derive(Clone, Debug, PartialEq)]
pub struct ResolvedCondensation {
    /// The cone mapping.
    pub cone: Cone,
    /// The steps after the cone.
    pub then: Pipeline,
}

impl ResolvedCondensation {
    /// The cone mapping of three uniform numbers: height uniform along the axis, a uniform point on the disc at
    /// that height (so every height slice of the stem gets the same number of hits). The condensation's further
    /// steps ([`ResolvedCondensation::then`]) are applied by the caller, to the whole generator.
    #[inline]
    pub fn cone_point(&self, u: [f32; 3]) -> [f32; 3] {
        let c = &self.cone;
        let (a, b) = (c.axis.index(), c.axis.others());
        let h = c.bottom + u[0] * (c.top - c.bottom);
        let r = (c.bottom_radius + u[0] * (c.top_radius - c.bottom_radius)) * libm::sqrtf(u[1]);
        let theta = 2.0 * PI * u[2];
        let mut p = [0.0f32; 3];
        p[a] = h;
        p[b[0]] = r * libm::cosf(theta);
        p[b[1]] = r * libm::sinf(theta);
        p
    }

    /// The stem axis (bottom centre to top centre) after the condensation's own steps.
    pub fn axis(&self) -> [[f32; 3]; 2] {
        let c = &self.cone;
        let a = c.axis.index();
        let mut p = [[0.0f32; 3]; 2];
        p[0][a] = c.bottom;
        p[1][a] = c.top;
        [self.then.apply(p[0]), self.then.apply(p[1])]
    }
}

/// The IFS of one tree with its random parameters fixed.
#[derive(Clone, Debug, PartialEq)]
pub struct ResolvedIfs {
    /// Parameter levels `m` (1..=3): values are constant from level `m` on.
    pub levels: usize,
    /// `pipelines[j][l - 1]`: transformation `j` at parameter level `l` (1..=3).
    pub pipelines: Vec<[Pipeline; 3]>,
    /// The condensations.
    pub condensations: Vec<ResolvedCondensation>,
}

fn draw(v: canopy_protocol::hypertree::RandomValue, ctx: &mut Context<'_>) -> f32 {
    // One draw per value, even for fixed ones, so changing one spread does not reshuffle the others.
    let u = unit_f32(ctx.next_u32());
    v.mean + v.spread * (2.0 * u - 1.0)
}

fn resolve_steps(steps: &[Elementary], ctx: &mut Context<'_>) -> [Pipeline; 3] {
    // Draw every level's values first (levels beyond a parameter's own count reuse its last value).
    let mut out: [Pipeline; 3] = Default::default();
    for e in steps {
        let vals: Vec<[f32; 3]> = e
            .params()
            .iter()
            .map(|p: &&Param| {
                let drawn: Vec<f32> = p.0.iter().map(|v| draw(*v, ctx)).collect();
                std::array::from_fn(|l| drawn[l.min(drawn.len() - 1)])
            })
            .collect();
        for (l, pipe) in out.iter_mut().enumerate() {
            let v = |i: usize| vals[i][l];
            match e {
                Elementary::Translate(_) => pipe.push_affine(Transform::translation(v(0), v(1), v(2))),
                Elementary::Scale(_) => pipe.push_affine(Transform::scale(v(0), v(1), v(2))),
                Elementary::Rotate { axis, .. } => {
                    let mut ax = [0.0f32; 3];
                    ax[axis.index()] = 1.0;
                    pipe.push_affine(Transform::rotation(ax, v(0)));
                }
                Elementary::Shear { axis, .. } => pipe.steps.push(Step::Shear {
                    axis: axis.index(),
                    others: axis.others(),
                    max: [v(0), v(1)],
                    exponent: Exponent::of(v(2).max(0.0)),
                }),
            }
        }
    }
    out
}

impl ResolvedIfs {
    /// Fix the random parameters of `def` from stream `key` of the instance RNG (§6 step 2).
    pub fn new(def: &HypertreeDef, rng: &mut InstanceRng, key: u64) -> ResolvedIfs {
        let mut ctx = Context { rng, key, counter: 0 };
        let condensations = def
            .condensations
            .iter()
            .map(|c| {
                let [then, _, _] = resolve_steps(&c.then, &mut ctx);
                ResolvedCondensation { cone: c.cone, then }
            })
            .collect();
        let pipelines = def.transformations.iter().map(|t| resolve_steps(&t.steps, &mut ctx)).collect();
        ResolvedIfs { levels: def.param_levels().clamp(1, 3), pipelines, condensations }
    }
}
