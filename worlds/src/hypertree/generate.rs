//! The hypertree algorithm (§6): condensation every `k` generators, noise perturbation, `k − 1` selected
//! transformations applied through level-dependent pipelines (Figure 2, with the constant-after-level-`m` shortcut),
//! dummy and last-allowed-level rules, voxel hit recording with the shallowest level per voxel, then validation
//! into density classes and a storage structure. Deterministic from the instance seed; never reads the clock.
//!
//! Pipelines: after a condensation `X`, transformations `w_1 … w_{k−1}` are selected. Row `s` records
//! `Y_s = w_s^(1) ∘ w_{s−1}^(2) ∘ … ∘ w_1^(s) (X)` at level `s`, where the upper index is the parameter level. When
//! parameters are constant from level `m` on, the inner part `w_{s−m+1}^(m) ∘ … ∘ w_1^(m) (X)` grows by one
//! application per row and only the last `m − 1` transformations are recomputed, so a row costs `m` applications.
//!
//! Rules: transformation `j` is only selected at levels `s ≤ c_j` (its last allowed level; when none is allowed the
//! cycle ends early); a transformation that is dummy from level `d` is applied but its generator is not recorded
//! at levels `s ≥ d`.

// Negated comparisons are deliberate: they treat NaN as out of range.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use canopy_protocol::hypertree::{Generator, HypertreeDef, HypertreeError, MAX_RESOLUTION};

use super::format::Forest;
use super::ifs::{Pipeline, ResolvedIfs};
use super::noise::VectorNoise;
use super::storage::HitRecorder;
use super::{Aabb, BoundingSphere, Bounds, Flow, Hypertree, Hypervolume, StorageType};
use crate::eval::{Draw, unit_f32};
use crate::rng::{Context, InstanceRng};
use crate::vec3::{add, norm, sub};

/// RNG stream fixing the random transformation parameters.
pub const PARAM_STREAM: u64 = 0x4859_5045_5200_0001;
/// RNG stream driving the iteration (selections, condensation samples).
pub const ITERATION_STREAM: u64 = 0x4859_5045_5200_0002;
/// RNG stream seeding the perturbation noise.
pub const NOISE_STREAM: u64 = 0x4859_5045_5200_0003;

/// Most voxels of a dense array (256 Mi: 512 MiB with the level bytes).
pub const MAX_DENSE_VOXELS: u64 = 1 << 28;

/// Progress is reported every this many generators.
pub const PROGRESS_STEP: u64 = 1 << 16;

/// How to generate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GenerateOptions {
    /// The storage structure.
    pub storage: StorageType,
    /// Keep index lists per first-level subpart (not for the dense array).
    pub partitioned: bool,
    /// Override the definition's resolution.
    pub resolution: Option<[u32; 3]>,
    /// Override the definition's iteration count.
    pub iterations: Option<u64>,
}

impl Default for GenerateOptions {
    fn default() -> Self {
        GenerateOptions { storage: StorageType::IndexBits, partitioned: false, resolution: None, iterations: None }
    }
}

/// Why generation was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GenerateError {
    /// The definition is not valid.
    #[error("invalid hypertree definition: {0}")]
    Invalid(#[from] HypertreeError),
    /// An overridden resolution is out of range.
    #[error("resolution {0:?} (allowed 1..={MAX_RESOLUTION} per axis)")]
    Resolution([u32; 3]),
    /// An overridden iteration count is out of range.
    #[error("{0} iterations (allowed 1..={max})", max = canopy_protocol::hypertree::MAX_ITERATIONS)]
    Iterations(u64),
    /// A dense array would be too large.
    #[error("a dense array of {0} voxels exceeds {MAX_DENSE_VOXELS}; use an index list")]
    DenseTooLarge(u64),
    /// The dense array cannot be partitioned.
    #[error("a dense array cannot be partitioned")]
    PartitionedDense,
    /// A hyperforest without trees.
    #[error("a hyperforest needs at least one tree")]
    EmptyForest,
}

/// What one generation did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GenerationStats {
    /// Generators produced (condensations, recorded and dummy transformations): the iteration count.
    pub generators: u64,
    /// Condensation cycles.
    pub cycles: u64,
    /// Generators not recorded because their transformation was dummy at that level.
    pub dummies: u64,
    /// Recorded generators that fell (wholly) outside the hypervolume.
    pub outside: u64,
    /// Voxel hits recorded (a line generator hits several voxels).
    pub hits: u64,
}

/// Generate a hypertree from its definition and an instance seed (§6).
pub fn generate(
    def: &HypertreeDef,
    seed: u64,
    opts: &GenerateOptions,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<(Hypertree, GenerationStats), GenerateError> {
    def.validate()?;
    let resolution = opts.resolution.unwrap_or(def.resolution);
    let volume = Hypervolume { resolution, extent: def.hypervolume };
    let iterations = opts.iterations.unwrap_or(def.iterations);
    check(opts, &volume, iterations)?;
    // A line generator's hits come in runs of neighbouring voxels: counted in bricks, not sorted.
    let mut recorder = match def.generator {
        Generator::Line { .. } => HitRecorder::new_coherent(opts.storage, volume.resolution),
        Generator::Point(_) => HitRecorder::new(opts.storage, volume.resolution),
    };
    let mut stats = GenerationStats::default();
    // Unpartitioned, every hit belongs to subpart 0; partitioned, to the first-level subpart that made it.
    let part = if opts.partitioned { None } else { Some(0) };
    let (bounds, flows) =
        run_tree(def, seed, def.displacement, &volume, iterations, part, &mut recorder, &mut stats, &mut |d| {
            progress(d, iterations)
        });
    stats.hits = recorder.hits;
    let finished = recorder.finish(opts.storage, opts.partitioned, &volume, def.density_classes, def.branch_depth);
    let tree = Hypertree::with_occupancy(
        def.name.clone(),
        volume,
        finished,
        def.depth_colors.clone(),
        def.tree_depth,
        def.branch_depth,
        bounds,
        flows,
    );
    Ok((tree, stats))
}

/// Generate a hyperforest (§10): every tree into one common volume, hits added (§7: running several IFSs on the same
/// volume with addition as the unification function), then validated together. The forest uses its first tree's
/// density classes, branch depth and depth colours; a partitioned forest keeps one part per tree.
pub fn generate_forest(
    forest: &Forest,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<(Hypertree, GenerationStats), GenerateError> {
    let first = forest.trees.first().ok_or(GenerateError::EmptyForest)?;
    let def = &forest.def;
    let volume = Hypervolume { resolution: def.resolution, extent: def.hypervolume };
    let opts =
        GenerateOptions { storage: def.storage, partitioned: def.partitioned, resolution: None, iterations: None };
    let total: u64 = forest.trees.iter().map(|t| t.iterations).sum();
    check(&opts, &volume, 1)?;
    let mut recorder = HitRecorder::new(def.storage, volume.resolution);
    let mut stats = GenerationStats::default();
    let mut bounds = Bounds::default();
    let mut flows = Vec::new();
    let mut done = 0u64;
    for (n, (tree, place)) in forest.trees.iter().zip(&def.trees).enumerate() {
        tree.validate()?;
        let part = Some(if def.partitioned { n.min(255) as u8 } else { 0 });
        let (b, f) = run_tree(
            tree,
            place.seed,
            place.origin,
            &volume,
            tree.iterations,
            part,
            &mut recorder,
            &mut stats,
            &mut |d| progress(done + d, total),
        );
        done += tree.iterations;
        bounds.spheres.extend(b.spheres);
        bounds.boxes.extend(b.boxes);
        flows.extend(f);
    }
    stats.hits = recorder.hits;
    let finished = recorder.finish(def.storage, def.partitioned, &volume, first.density_classes, first.branch_depth);
    let depth = forest.trees.iter().map(|t| t.tree_depth).max().unwrap_or(first.tree_depth);
    let tree = Hypertree::with_occupancy(
        def.name.clone(),
        volume,
        finished,
        first.depth_colors.clone(),
        depth,
        first.branch_depth,
        bounds,
        flows,
    );
    Ok((tree, stats))
}

fn check(opts: &GenerateOptions, volume: &Hypervolume, iterations: u64) -> Result<(), GenerateError> {
    if volume.resolution.iter().any(|&r| r == 0 || r > MAX_RESOLUTION) {
        return Err(GenerateError::Resolution(volume.resolution));
    }
    if iterations == 0 || iterations > canopy_protocol::hypertree::MAX_ITERATIONS {
        return Err(GenerateError::Iterations(iterations));
    }
    if opts.storage == StorageType::Dense {
        if opts.partitioned {
            return Err(GenerateError::PartitionedDense);
        }
        if volume.voxel_count() > MAX_DENSE_VOXELS {
            return Err(GenerateError::DenseTooLarge(volume.voxel_count()));
        }
    }
    Ok(())
}

/// A generator: a point or a line segment of preserved length.
trait Shape: Copy {
    fn apply(self, p: &Pipeline, len: f32) -> Self;
    fn hull(self, b: &mut Aabb);
    fn perturb(self, noise: &Perturb) -> Self;
    fn record(self, g: &mut Grid<'_>, level: u8, part: u8) -> bool;
}

impl Shape for [f32; 3] {
    #[inline]
    fn apply(self, p: &Pipeline, _: f32) -> Self {
        p.apply(self)
    }
    #[inline]
    fn hull(self, b: &mut Aabb) {
        b.add(self);
    }
    #[inline]
    fn perturb(self, n: &Perturb) -> Self {
        n.shift(self)
    }
    #[inline]
    fn record(self, g: &mut Grid<'_>, level: u8, part: u8) -> bool {
        g.point(self, level, part)
    }
}

#[derive(Clone, Copy)]
struct Segment([f32; 3], [f32; 3]);

impl Shape for Segment {
    #[inline]
    fn apply(self, p: &Pipeline, len: f32) -> Self {
        let (a, b) = (p.apply(self.0), p.apply(self.1));
        // Rescale the transformed segment to the original length about its midpoint (§4).
        let m: [f32; 3] = std::array::from_fn(|i| 0.5 * (a[i] + b[i]));
        let d = sub(b, a);
        let l = norm(d);
        if !(l > 0.0) || !l.is_finite() {
            return Segment(m, m);
        }
        let h = 0.5 * len / l;
        Segment(std::array::from_fn(|i| m[i] - d[i] * h), std::array::from_fn(|i| m[i] + d[i] * h))
    }
    fn hull(self, b: &mut Aabb) {
        b.add(self.0);
        b.add(self.1);
    }
    fn perturb(self, n: &Perturb) -> Self {
        if n.noise.is_none() {
            return self;
        }
        let m: [f32; 3] = std::array::from_fn(|i| 0.5 * (self.0[i] + self.1[i]));
        let s = n.shift(m);
        let d: [f32; 3] = std::array::from_fn(|i| s[i] - m[i]);
        Segment(std::array::from_fn(|i| self.0[i] + d[i]), std::array::from_fn(|i| self.1[i] + d[i]))
    }
    fn record(self, g: &mut Grid<'_>, level: u8, part: u8) -> bool {
        g.segment(self.0, self.1, level, part)
    }
}

struct Perturb {
    noise: Option<VectorNoise>,
    amplitude: [f32; 3],
    frequency: f32,
}

impl Perturb {
    #[inline]
    fn shift(&self, p: [f32; 3]) -> [f32; 3] {
        match &self.noise {
            None => p,
            Some(n) => {
                let v = n.sample(p.map(|c| c * self.frequency));
                std::array::from_fn(|i| p[i] + self.amplitude[i] * v[i])
            }
        }
    }
}

/// Maps tree points to voxels and records hits.
struct Grid<'a> {
    volume: Hypervolume,
    offset: [f32; 3],
    inv: [f32; 3],
    recorder: &'a mut HitRecorder,
    /// Point hits not yet recorded: voxel, index, level, subpart.
    points: Vec<([u32; 3], u32, u8, u8)>,
}

/// Point hits recorded at a time.
const POINT_BATCH: usize = 256;

impl Grid<'_> {
    #[inline]
    fn point(&mut self, p: [f32; 3], level: u8, part: u8) -> bool {
        let q: [f32; 3] = std::array::from_fn(|i| p[i] + self.offset[i]);
        match self.volume.voxel_at(q, self.inv) {
            Some(v) => {
                // Hits are queued and recorded in batches: their counts do not depend on the order, and a tight
                // loop of independent writes overlaps the cache misses of a large volume.
                self.points.push((v, self.volume.index(v), level, part));
                if self.points.len() == POINT_BATCH {
                    self.flush_points();
                }
                true
            }
            None => false,
        }
    }

    /// Record the queued point hits.
    fn flush_points(&mut self) {
        self.recorder.record_points(&self.points);
        self.points.clear();
    }

    /// Record every voxel the segment passes through (see [`dda`]): straight into a dense array or a brick grid,
    /// or handed to the recorder in batches (in order, so the result is the same).
    fn segment(&mut self, a: [f32; 3], b: [f32; 3], level: u8, part: u8) -> bool {
        let (volume, offset, inv) = (&self.volume, self.offset, self.inv);
        if let Some(mut dense) = self.recorder.dense_hits() {
            return dda(volume, offset, inv, a, b, |v, index| dense.hit(v, index, level));
        }
        if let Some(mut bricks) = self.recorder.brick_hits(part) {
            return dda(volume, offset, inv, a, b, |v, _| bricks.hit(v, level));
        }
        const BATCH: usize = 64;
        let mut buf = [([0u32; 3], 0u32); BATCH];
        let mut n = 0;
        let recorder = &mut *self.recorder;
        let inside = dda(volume, offset, inv, a, b, |v, index| {
            buf[n] = (v, index);
            n += 1;
            if n == BATCH {
                recorder.record_many(&buf, level, part);
                n = 0;
            }
        });
        recorder.record_many(&buf[..n], level, part);
        inside
    }
}

/// Visit every voxel (coordinates and index) the segment from `a` to `b` (tree coordinates, `offset` from the box
/// corner, `inv` voxels per unit) passes through, by a 3D DDA (Amanatides–Woo) over the part of the segment inside
/// the box, so the work is bounded by the volume's resolution, not by the segment. False when it misses the box.
#[inline(always)]
fn dda(
    volume: &Hypervolume,
    offset: [f32; 3],
    inv: [f32; 3],
    a: [f32; 3],
    b: [f32; 3],
    mut visit: impl FnMut([u32; 3], u32),
) -> bool {
    // Voxel coordinates.
    let a: [f32; 3] = std::array::from_fn(|i| (a[i] + offset[i]) * inv[i]);
    let b: [f32; 3] = std::array::from_fn(|i| (b[i] + offset[i]) * inv[i]);
    let d: [f32; 3] = std::array::from_fn(|i| b[i] - a[i]);
    let res = volume.resolution.map(|r| r as f32);
    // With both ends inside, the clip is [0, 1] (see `clip`), so the common case skips its divisions.
    let inside = |p: [f32; 3]| (0..3).all(|i| p[i] >= 0.0 && p[i] < res[i]);
    let (t0, t1) = if inside(a) && inside(b) {
        (0.0, 1.0)
    } else {
        match clip(a, d, res) {
            Some(t) => t,
            None => return false,
        }
    };
    let p: [f32; 3] = std::array::from_fn(|i| a[i] + d[i] * t0);
    let max = volume.resolution.map(|r| r as i64 - 1);
    let v: [i64; 3] = std::array::from_fn(|i| (p[i].max(0.0) as i64).min(max[i]));
    let end: [i64; 3] = std::array::from_fn(|i| ((a[i] + d[i] * t1).max(0.0) as i64).min(max[i]));
    let step: [i64; 3] = std::array::from_fn(|i| {
        if d[i] > 0.0 {
            1
        } else if d[i] < 0.0 {
            -1
        } else {
            0
        }
    });
    let delta: [f32; 3] = std::array::from_fn(|i| if d[i] != 0.0 { (1.0 / d[i]).abs() } else { f32::INFINITY });
    let next: [f32; 3] = std::array::from_fn(|i| {
        if d[i] > 0.0 {
            ((v[i] + 1) as f32 - a[i]) / d[i]
        } else if d[i] < 0.0 {
            (v[i] as f32 - a[i]) / d[i]
        } else {
            f32::INFINITY
        }
    });
    // At most one step per voxel boundary crossed: bounded by the sum of the resolutions. The index moves by
    // one stride per step.
    let limit = (volume.resolution.iter().sum::<u32>() + 3) as usize;
    let [rx, ry, _] = volume.resolution.map(i64::from);
    let stride = [step[0], step[1] * rx, step[2] * rx * ry];
    let mut idx = i64::from(volume.index([v[0] as u32, v[1] as u32, v[2] as u32]));
    // The axis state lives in scalars (not arrays indexed by the axis) so it stays in registers.
    let [mut v0, mut v1, mut v2] = v;
    let [mut n0, mut n1, mut n2] = next;
    let [e0, e1, e2] = end;
    for _ in 0..limit {
        visit([v0 as u32, v1 as u32, v2 as u32], idx as u32);
        if v0 == e0 && v1 == e1 && v2 == e2 {
            break;
        }
        if n0 <= n1 && n0 <= n2 {
            if n0 > t1 {
                break;
            }
            v0 += step[0];
            if v0 < 0 || v0 > max[0] {
                break;
            }
            idx += stride[0];
            n0 += delta[0];
        } else if n1 <= n2 {
            if n1 > t1 {
                break;
            }
            v1 += step[1];
            if v1 < 0 || v1 > max[1] {
                break;
            }
            idx += stride[1];
            n1 += delta[1];
        } else {
            if n2 > t1 {
                break;
            }
            v2 += step[2];
            if v2 < 0 || v2 > max[2] {
                break;
            }
            idx += stride[2];
            n2 += delta[2];
        }
    }
    true
}

/// The parameter range `[t0, t1]` of the segment `a + t·d`, `t ∈ [0, 1]`, inside the box `[0, res)`; `None` when it
/// misses. With both ends inside the result is `[0, 1]` exactly, up to the sign of a zero `t0` (which `a + d·t0`
/// does not see): rounding is monotonic, so the rounded distance to a face is never below the rounded `d`.
fn clip(a: [f32; 3], d: [f32; 3], res: [f32; 3]) -> Option<(f32, f32)> {
    let (mut t0, mut t1) = (0.0f32, 1.0f32);
    for i in 0..3 {
        if d[i] == 0.0 {
            if !(a[i] >= 0.0 && a[i] < res[i]) {
                return None;
            }
        } else {
            let (u, v) = ((0.0 - a[i]) / d[i], (res[i] - a[i]) / d[i]);
            t0 = t0.max(u.min(v));
            t1 = t1.min(u.max(v));
        }
    }
    (t0 <= t1).then_some((t0, t1))
}

/// Cumulative selection thresholds (out of 2³²) over the transformations allowed at one level, with a guide
/// table on the top 8 bits so a pick scans one or two thresholds.
struct Selection {
    thresholds: Vec<(u64, u8)>,
    guide: [u8; 256],
}

impl Selection {
    fn new(def: &HypertreeDef, level: usize) -> Selection {
        let allowed: Vec<(usize, f64)> = def
            .transformations
            .iter()
            .enumerate()
            .filter(|(_, t)| usize::from(t.last_level) >= level && t.probability > 0.0)
            .map(|(j, t)| (j, f64::from(t.probability)))
            .collect();
        let total: f64 = allowed.iter().map(|a| a.1).sum();
        let mut acc = 0.0f64;
        let mut thresholds = Vec::with_capacity(allowed.len());
        for (k, &(j, p)) in allowed.iter().enumerate() {
            acc += p;
            let t = if k + 1 == allowed.len() { 1u64 << 32 } else { (acc / total * 4_294_967_296.0) as u64 };
            thresholds.push((t, j as u8));
        }
        Selection::with_guide(thresholds)
    }

    fn with_guide(thresholds: Vec<(u64, u8)>) -> Selection {
        // guide[g] = the first threshold above g·2²⁴, where every pick with top byte g starts scanning.
        let guide = std::array::from_fn(|g| {
            let lo = (g as u64) << 24;
            thresholds.iter().position(|t| t.0 > lo).unwrap_or(thresholds.len()).min(255) as u8
        });
        Selection { thresholds, guide }
    }

    #[inline]
    fn pick(&self, bits: u32) -> Option<usize> {
        let b = u64::from(bits);
        let start = usize::from(self.guide[(bits >> 24) as usize]);
        self.thresholds.get(start..)?.iter().find(|t| b < t.0).map(|t| usize::from(t.1))
    }
}

/// Run one tree's IFS into `recorder`; returns its bounding volumes and first-level flows (box coordinates).
#[allow(clippy::too_many_arguments)]
fn run_tree(
    def: &HypertreeDef,
    seed: u64,
    offset: [f32; 3],
    volume: &Hypervolume,
    iterations: u64,
    part_override: Option<u8>,
    recorder: &mut HitRecorder,
    stats: &mut GenerationStats,
    progress: &mut dyn FnMut(u64),
) -> (Bounds, Vec<Flow>) {
    let mut rng = InstanceRng::new(seed);
    let ifs = ResolvedIfs::new(def, &mut rng, PARAM_STREAM);
    let p = &def.perturbation;
    let perturb = Perturb {
        noise: p.amplitude.iter().any(|&a| a > 0.0).then(|| VectorNoise::new(&mut rng, NOISE_STREAM)),
        amplitude: p.amplitude,
        frequency: p.frequency,
    };
    let inv = std::array::from_fn(|i| volume.resolution[i] as f32 / volume.extent[i]);
    let mut grid = Grid { volume: *volume, offset, inv, recorder, points: Vec::with_capacity(POINT_BATCH) };
    let mut run = Run {
        def,
        ifs: &ifs,
        perturb: &perturb,
        selections: (0..usize::from(def.tree_depth)).map(|s| Selection::new(def, s)).collect(),
        cond: Selection::new_weights(def.condensations.iter().map(|c| c.weight)),
        dummy_from: def.transformations.iter().map(|t| t.dummy_from.unwrap_or(u8::MAX)).collect(),
        part_override,
        inner: Aabb::EMPTY,
        stem: Aabb::EMPTY,
    };
    let mut ctx = Context { rng: &mut rng, key: ITERATION_STREAM, counter: 0 };
    let (len, shape_bound) = match def.generator {
        Generator::Point(p0) => {
            run.iterate(p0, 0.0, &mut grid, &mut ctx, iterations, stats, progress);
            grid.flush_points();
            (0.0, 0.0)
        }
        Generator::Line { from, to } => {
            let m: [f32; 3] = std::array::from_fn(|i| 0.5 * (from[i] + to[i]));
            let seg = Segment(std::array::from_fn(|i| from[i] - m[i]), std::array::from_fn(|i| to[i] - m[i]));
            let len = norm(sub(to, from));
            run.iterate(seg, len, &mut grid, &mut ctx, iterations, stats, progress);
            (len, 0.5 * len)
        }
    };
    let _ = len;
    // Bounding volumes (§8.2), made conservative: the perturbation's largest offset, half the line length and a
    // voxel diagonal (a sample anywhere in a hit voxel) are added.
    let vs = volume.voxel_size();
    let diag = norm(vs);
    let amp = libm::sqrtf(p.amplitude.iter().map(|a| a * a).sum::<f32>());
    let margin = amp + shape_bound + diag;
    let mut bounds = Bounds::default();
    if !run.stem.is_empty() {
        bounds.boxes.push(run.stem.padded(diag + amp).offset(offset));
    }
    let mut flows = Vec::new();
    for c in &ifs.condensations {
        let [a, b] = c.axis();
        flows.push(Flow { from: add(a, offset), to: add(b, offset) });
    }
    let stem_axis = ifs.condensations[0].axis();
    if !run.inner.is_empty() {
        let c: [f32; 3] = std::array::from_fn(|i| 0.5 * (run.inner.min[i] + run.inner.max[i]));
        let h: [f32; 3] = std::array::from_fn(|i| 0.5 * (run.inner.max[i] - run.inner.min[i]));
        let r = norm(h);
        for (j, t) in def.transformations.iter().enumerate() {
            if t.dummy_from == Some(1) || t.probability <= 0.0 {
                continue;
            }
            let pipe = &ifs.pipelines[j][0];
            let (center, radius) = pipe.sphere(c, r);
            bounds.spheres.push(BoundingSphere { center: add(center, offset), radius: radius * 1.0001 + margin });
            let (a, b) = (pipe.apply(stem_axis[0]), pipe.apply(stem_axis[1]));
            flows.push(Flow { from: add(a, offset), to: add(b, offset) });
        }
    }
    (bounds, flows)
}

impl Selection {
    fn new_weights(w: impl Iterator<Item = f32>) -> Selection {
        let w: Vec<f64> = w.map(f64::from).collect();
        let total: f64 = w.iter().sum();
        let mut acc = 0.0;
        let mut thresholds = Vec::new();
        for (k, p) in w.iter().enumerate() {
            acc += p;
            let t = if k + 1 == w.len() { 1u64 << 32 } else { (acc / total * 4_294_967_296.0) as u64 };
            thresholds.push((t, k as u8));
        }
        Selection::with_guide(thresholds)
    }
}

struct Run<'a> {
    def: &'a HypertreeDef,
    ifs: &'a ResolvedIfs,
    perturb: &'a Perturb,
    /// Selection among the transformations allowed at level `s` (index `s`; index 0 unused).
    selections: Vec<Selection>,
    cond: Selection,
    dummy_from: Vec<u8>,
    part_override: Option<u8>,
    /// Hull of every generator fed to a first-level transformation (the tree the secondary spheres transform).
    inner: Aabb,
    /// Hull of the recorded condensation generators.
    stem: Aabb,
}

impl Run<'_> {
    #[allow(clippy::too_many_arguments)]
    fn iterate<S: Shape + Offset>(
        &mut self,
        init: S,
        len: f32,
        grid: &mut Grid<'_>,
        ctx: &mut Context<'_>,
        iterations: u64,
        stats: &mut GenerationStats,
        progress: &mut dyn FnMut(u64),
    ) {
        let k = usize::from(self.def.tree_depth);
        let m = self.ifs.levels;
        let single_cond = self.ifs.condensations.len() == 1;
        let mut sel = [0usize; 33];
        let mut produced = 0u64;
        let (mut cycles, mut dummies, mut outside) = (0u64, 0u64, 0u64);
        let mut next_report = PROGRESS_STEP;
        while produced < iterations {
            cycles += 1;
            // a. Condensation: a uniform point of the stem cone, the generator placed on it.
            let ci = if single_cond { 0 } else { self.cond.pick(ctx.next_u32()).unwrap_or(0) };
            let cond = &self.ifs.condensations[ci];
            let u = [unit_f32(ctx.next_u32()), unit_f32(ctx.next_u32()), unit_f32(ctx.next_u32())];
            let x = init.at(cond.cone_point(u)).apply(&cond.then, len);
            // b, c. Perturb and record into the trunk list.
            let x = x.perturb(self.perturb);
            x.hull(&mut self.stem);
            if !x.record(grid, 0, self.part_override.unwrap_or(0)) {
                outside += 1;
            }
            produced += 1;
            // d. Select up to k − 1 transformations among those allowed at each level.
            let mut rows = 0;
            let budget = (iterations - produced).min(k as u64 - 1) as usize;
            while rows < budget {
                match self.selections[rows + 1].pick(ctx.next_u32()) {
                    Some(j) => {
                        sel[rows + 1] = j;
                        rows += 1;
                    }
                    None => break,
                }
            }
            // e. Rows: Z holds positions 1..=s−m+1 at the constant level m.
            let mut z = x;
            for s in 1..=rows {
                let c = s as isize - m as isize + 1;
                let mut u_in = z;
                if c >= 1 {
                    let pos = c as usize;
                    if pos == s {
                        u_in = z;
                    }
                    z = z.apply(&self.ifs.pipelines[sel[pos]][m - 1], len);
                }
                let j = sel[s];
                produced += 1;
                if s >= usize::from(self.dummy_from[j]) {
                    dummies += 1;
                    continue;
                }
                let y = if c as usize == s && c >= 1 {
                    z
                } else {
                    let mut v = z;
                    let first = if c >= 1 { c as usize + 1 } else { 1 };
                    for (t, &j_t) in sel.iter().enumerate().take(s + 1).skip(first) {
                        if t == s {
                            u_in = v;
                        }
                        v = v.apply(&self.ifs.pipelines[j_t][s - t], len);
                    }
                    v
                };
                u_in.hull(&mut self.inner);
                let y = y.perturb(self.perturb);
                let part = self.part_override.unwrap_or((j + 1).min(255) as u8);
                if !y.record(grid, s as u8, part) {
                    outside += 1;
                }
            }
            if produced >= next_report {
                progress(produced);
                next_report = produced + PROGRESS_STEP;
            }
        }
        stats.generators += produced;
        stats.cycles += cycles;
        stats.dummies += dummies;
        stats.outside += outside;
        progress(produced);
    }
}

/// Placing the generator at a condensation point.
trait Offset {
    fn at(self, p: [f32; 3]) -> Self;
}

impl Offset for [f32; 3] {
    #[inline]
    fn at(self, p: [f32; 3]) -> Self {
        add(self, p)
    }
}

impl Offset for Segment {
    #[inline]
    fn at(self, p: [f32; 3]) -> Self {
        Segment(add(self.0, p), add(self.1, p))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Segments with both ends inside the box clip to exactly `[0, 1]`, so `dda` may skip the clip: checked on
    /// random segments and on ends at the faces (0 and the largest coordinate below the resolution).
    #[test]
    fn clip_of_inside_segments_is_the_whole_segment() {
        let mut rng = InstanceRng::new(5);
        let mut ctx = Context { rng: &mut rng, key: 1, counter: 0 };
        for n in 0..200_000 {
            let res: [f32; 3] = std::array::from_fn(|_| (1 + ctx.next_u32() % 400) as f32);
            let mut end = |i: usize| {
                let r = res[i];
                match ctx.next_u32() % 8 {
                    0 => 0.0,
                    1 => f32::from_bits(r.to_bits() - 1),
                    2 => f32::from_bits(r.to_bits() - 1 - ctx.next_u32() % 64),
                    _ => unit_f32(ctx.next_u32()) * r,
                }
            };
            let a: [f32; 3] = std::array::from_fn(&mut end);
            let mut b: [f32; 3] = std::array::from_fn(&mut end);
            if n % 5 == 0 {
                // Nearly parallel to an axis, or very short.
                b[n % 3] = a[n % 3];
            }
            let d: [f32; 3] = std::array::from_fn(|i| b[i] - a[i]);
            assert!((0..3).all(|i| a[i] < res[i] && b[i] < res[i]));
            let (t0, t1) = clip(a, d, res).expect("inside segments are not clipped away");
            assert_eq!(t1, 1.0, "a {a:?} b {b:?} res {res:?}");
            assert_eq!(t0, 0.0, "a {a:?} b {b:?} res {res:?}");
            for i in 0..3 {
                assert_eq!((a[i] + d[i] * t0).to_bits(), a[i].to_bits(), "a {a:?} b {b:?}");
            }
        }
    }
}
