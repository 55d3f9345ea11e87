//! Cells as a function: the placements of any rectangle of cells computed from the manifest and a bounded
//! neighbourhood (a halo) around it, so Poisson-disk spacing, the density ramps and `avoid` distances hold across
//! cell borders and any machine expanding any cell in any order gets the same records (the algorithm is described
//! in [`crate::world`]).

use std::collections::BTreeMap;
use std::ops::Range;

use super::fractal::Patch;
use super::tiles::MARGIN;
use super::{Bounds, CellKey, Placement, ScatterRule, World};
use crate::eval::unit_f32;
use crate::rng::{InstanceRng, child_key};

/// A dart's stream (`child_key(child_key(R, 1), x steps)` then `z steps`): its keep draw is word 0, its `n`-th
/// parameter word `1 + n`.
const WORD_KEEP: u64 = 0;
const WORD_PARAMS: u64 = 1;

/// Rounds of the priority Poisson-disk process: each round lets every empty background cell propose one more
/// dart.
pub const ROUNDS: u32 = 3;
/// Most background cells (summed over rules and rounds) one cell's expansion may visit, the tile variants it may
/// compute included; a manifest whose rules and `avoid` chains need more is refused at load.
pub const MAX_CELL_WORK: f64 = 16_777_216.0;
/// Most instances in one cell: an index in a cell fits 16 bits.
pub const MAX_CELL_INSTANCES: usize = 65_535;
/// Cells per side of the blocks a large region is expanded in (bounds the memory of one expansion).
pub const REGION_BLOCK: i32 = 32;

/// The populations of a manifest in the form expansion reads them: explicit instances indexed by cell, and the
/// file position of every population (a rule avoids only what was placed before it).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Populations {
    /// Explicit instances by cell, each with its statement's position among the populations, in file order.
    pub(crate) explicit: BTreeMap<CellKey, Vec<(u32, Placement)>>,
    /// Per rule, its statement's position among the populations.
    pub(crate) rule_order: Vec<u32>,
    /// Baked edits by cell, in file order: `(true, p)` fells the instance of `p.species` at exactly `p`'s position,
    /// `(false, p)` gives it `p.params` (each slot replaced or added). They apply after every statement placed the
    /// cell's instances (a felled instance still spaced its neighbours), to the first such instance; one that finds
    /// none changes nothing.
    pub(crate) edits: BTreeMap<CellKey, Vec<(bool, Placement)>>,
}

impl Populations {
    /// Explicit instances in the cells `c0 ..= c1`, as `(order, placement)` (keys order by x, then z).
    fn explicit_in(&self, c0: CellKey, c1: CellKey) -> impl Iterator<Item = &(u32, Placement)> {
        self.explicit.range(c0..=c1).filter(move |(k, _)| (c0.z..=c1.z).contains(&k.z)).flat_map(|(_, v)| v.iter())
    }
}

/// A rectangle on the ground, `[lo, hi)`, metres.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Rect {
    lo: [f64; 2],
    hi: [f64; 2],
}

impl Rect {
    fn grow(self, by: f64) -> Rect {
        Rect { lo: self.lo.map(|v| v - by), hi: self.hi.map(|v| v + by) }
    }

    fn union(self, o: Rect) -> Rect {
        Rect {
            lo: [self.lo[0].min(o.lo[0]), self.lo[1].min(o.lo[1])],
            hi: [self.hi[0].max(o.hi[0]), self.hi[1].max(o.hi[1])],
        }
    }

    fn clip(self, b: &Bounds) -> Rect {
        let lo = [self.lo[0].max(f64::from(b.min[0])), self.lo[1].max(f64::from(b.min[1]))];
        let hi = [self.hi[0].min(f64::from(b.max[0])), self.hi[1].min(f64::from(b.max[1]))];
        Rect { lo, hi }
    }

    fn contains(&self, x: f64, z: f64) -> bool {
        x >= self.lo[0] && x < self.hi[0] && z >= self.lo[1] && z < self.hi[1]
    }

    fn is_empty(&self) -> bool {
        !(self.lo[0] < self.hi[0] && self.lo[1] < self.hi[1])
    }
}

/// The rectangle each rule must be exact over for `target` to be: its own output, grown by the `avoid` distance
/// of every later rule that avoids its species, clipped to the rule's region. `None` where a rule contributes
/// nothing.
fn plan(world: &World, target: Rect) -> Vec<Option<Rect>> {
    let need = plan_unclipped(world, target);
    need.into_iter()
        .zip(&world.rules)
        .map(|(r, rule)| r.clip(&rule.region))
        .map(|r| (!r.is_empty()).then_some(r))
        .collect()
}

/// [`plan`] before clipping: the same for every cell of a world, so it bounds every cell's work.
fn plan_unclipped(world: &World, target: Rect) -> Vec<Rect> {
    let rules = &world.rules;
    let mut need: Vec<Rect> = vec![target; rules.len()];
    for n in (0..rules.len()).rev() {
        let out = need[n];
        for &(species, d) in &rules[n].avoid {
            for m in 0..n {
                if rules[m].species == species {
                    need[m] = need[m].union(out.grow(f64::from(d) + 1.0));
                }
            }
        }
    }
    need
}

/// Background cells and rounds one cell's expansion costs at most, wherever the cell lies (the load-time bound):
/// every tile a rule's rectangle touches, each computed from its window of `(4 · MARGIN)²` background cells.
pub(crate) fn cell_work(world: &World) -> f64 {
    let s = f64::from(world.cell_size);
    let (step, _) = super::populate::position_step(world.cell_size);
    let target = Rect { lo: [0.0, 0.0], hi: [s, s] };
    let window = (4 * MARGIN * 4 * MARGIN) as f64 * f64::from(ROUNDS);
    plan_unclipped(world, target)
        .iter()
        .zip(&world.rules)
        .map(|(r, rule)| {
            let t = rule.tiles.side() as f64 * step;
            ((r.hi[0] - r.lo[0]) / t + 2.0) * ((r.hi[1] - r.lo[1]) / t + 2.0) * window
        })
        .sum()
}

/// Height and slope for density ramps: the world's terrain, read through a fractal patch when it has one (cell
/// expansion and the far view's leaves read it alike).
pub(crate) enum Ground<'a> {
    World(&'a World),
    Patch(Patch),
}

impl Ground<'_> {
    /// Height and `|∇h|²` (for [`super::SlopeRamp`]).
    pub(crate) fn height_and_gradient2(&self, x: f64, z: f64) -> (f32, f64) {
        match self {
            Ground::World(w) => w.height_and_gradient2(x as f32, z as f32),
            Ground::Patch(p) => p.height_and_gradient2(x, z),
        }
    }

    fn density(&self, rule: &ScatterRule, x: f64, z: f64) -> f32 {
        if !rule.has_ramps() {
            return rule.density;
        }
        let (h, g2) = self.height_and_gradient2(x, z);
        rule.keep(h, g2)
    }
}

/// Points to keep away from, each with its distance, in buckets of a uniform grid over a rectangle.
struct Buckets {
    origin: [f64; 2],
    size: f64,
    dims: [i64; 2],
    starts: Vec<u32>,
    points: Vec<[f64; 3]>,
}

impl Buckets {
    fn new(area: Rect, points: Vec<[f64; 3]>) -> Buckets {
        let distance = points.iter().map(|p| p[2]).fold(1.0, f64::max);
        let (w, d) = (area.hi[0] - area.lo[0], area.hi[1] - area.lo[1]);
        let size = distance.max(w.max(d) / 256.0);
        let dims = [(w / size).ceil() as i64 + 1, (d / size).ceil() as i64 + 1];
        let bucket = |p: &[f64; 3]| {
            let i = (((p[0] - area.lo[0]) / size) as i64).clamp(0, dims[0] - 1);
            let j = (((p[1] - area.lo[1]) / size) as i64).clamp(0, dims[1] - 1);
            (j * dims[0] + i) as usize
        };
        let mut starts = vec![0u32; (dims[0] * dims[1]) as usize + 1];
        for p in &points {
            starts[bucket(p) + 1] += 1;
        }
        for i in 1..starts.len() {
            starts[i] += starts[i - 1];
        }
        let mut fill = starts.clone();
        let mut sorted = vec![[0.0f64; 3]; points.len()];
        for p in points {
            let b = bucket(&p);
            sorted[fill[b] as usize] = p;
            fill[b] += 1;
        }
        Buckets { origin: area.lo, size, dims, starts, points: sorted }
    }

    /// Whether (x, z) is closer to any point than that point's distance.
    fn near(&self, x: f64, z: f64) -> bool {
        let i = (((x - self.origin[0]) / self.size) as i64).clamp(0, self.dims[0] - 1);
        let j = (((z - self.origin[1]) / self.size) as i64).clamp(0, self.dims[1] - 1);
        for bj in (j - 1).max(0)..=(j + 1).min(self.dims[1] - 1) {
            let row = (bj * self.dims[0]) as usize;
            let (b0, b1) = ((i - 1).max(0) as usize, (i + 1).min(self.dims[0] - 1) as usize);
            for p in &self.points[self.starts[row + b0] as usize..self.starts[row + b1 + 1] as usize] {
                let (dx, dz) = (p[0] - x, p[1] - z);
                if dx * dx + dz * dz < p[2] * p[2] {
                    return true;
                }
            }
        }
        false
    }
}

/// Expand one rule over `exact`: the darts of its tiles inside `exact` and its region, far enough from what it
/// avoids, kept by density, row-major by position, with their parameter values.
fn scatter(
    world: &World,
    rule: &ScatterRule,
    exact: Rect,
    ground: &Ground,
    avoid: Option<&Buckets>,
    rng: &mut InstanceRng,
) -> Vec<Placement> {
    // Where the rule's density is 0 over the whole area, it places nothing (its darts would all be thinned out).
    if let Ground::Patch(p) = ground
        && rule.altitude.max_over(p.height_range()) <= 0.0
    {
        return Vec::new();
    }
    let (step, inv_step) = super::populate::position_step(world.cell_size);
    // The position steps `k` with `k · step` in `[lo, hi)` (the step is a power of two: exact).
    let first = |v: f64| (v * inv_step).ceil() as i64;
    let lo = [first(exact.lo[0]), first(exact.lo[1])];
    let hi = [first(exact.hi[0]) - 1, first(exact.hi[1]) - 1];
    if lo[0] > hi[0] || lo[1] > hi[1] {
        return Vec::new();
    }
    let graph = &world.species[usize::from(rule.species)].graph;
    let darts = child_key(rule.key, 1);
    let mut kept = Vec::new();
    for [kx, kz] in rule.tiles.darts(lo, hi) {
        let (x, z) = (kx as f64 * step, kz as f64 * step);
        // Inside `exact` by the step range, so inside the rule's region too (`exact` is clipped to it).
        if avoid.is_some_and(|b| b.near(x, z)) {
            continue;
        }
        let density = ground.density(rule, x, z);
        if density <= 0.0 {
            continue;
        }
        let stream = child_key(child_key(darts, kx as u64), kz as u64);
        if unit_f32(rng.word(stream, WORD_KEEP)) >= density {
            continue;
        }
        let mut params = Vec::new();
        for (m, &(slot, value)) in rule.params.iter().enumerate() {
            let v = value.value(rng.word(stream, WORD_PARAMS + m as u64));
            if !super::populate::is_default(graph, slot, v) {
                params.push((slot, v));
            }
        }
        kept.push(Placement { species: rule.species, x, z, params });
    }
    kept
}

/// The placements of cells `c0 ..= c1` (inclusive, row-major by cell), each cell's in index order: explicit
/// instances and rules in file order, a rule's darts in row-major order of their background cells. Large
/// rectangles are expanded in blocks of [`REGION_BLOCK`] cells (the result does not depend on the blocks).
pub(crate) fn expand(world: &World, c0: CellKey, c1: CellKey) -> Vec<(CellKey, Vec<Placement>)> {
    let mut out = Vec::new();
    let mut bz = c0.z;
    while bz <= c1.z {
        let ez = bz.saturating_add(REGION_BLOCK - 1).min(c1.z);
        let mut rows: Vec<Vec<(CellKey, Vec<Placement>)>> = Vec::new();
        let mut bx = c0.x;
        while bx <= c1.x {
            let ex = bx.saturating_add(REGION_BLOCK - 1).min(c1.x);
            rows.push(expand_block(world, CellKey { x: bx, z: bz }, CellKey { x: ex, z: ez }));
            bx = ex.saturating_add(1);
            if ex == i32::MAX {
                break;
            }
        }
        // Blocks side by side: emit row-major over the whole rectangle.
        let width = (i64::from(c1.x) - i64::from(c0.x) + 1) as usize;
        let mut cells: Vec<Option<(CellKey, Vec<Placement>)>> = vec![None; width * (ez - bz + 1) as usize];
        for (key, list) in rows.into_iter().flatten() {
            let k = (key.z - bz) as usize * width + (i64::from(key.x) - i64::from(c0.x)) as usize;
            cells[k] = Some((key, list));
        }
        out.extend(cells.into_iter().flatten());
        bz = ez.saturating_add(1);
        if ez == i32::MAX {
            break;
        }
    }
    out
}

/// [`expand`] of one block.
fn expand_block(world: &World, c0: CellKey, c1: CellKey) -> Vec<(CellKey, Vec<Placement>)> {
    let s = f64::from(world.cell_size);
    let target = Rect {
        lo: [f64::from(c0.x) * s, f64::from(c0.z) * s],
        hi: [(f64::from(c1.x) + 1.0) * s, (f64::from(c1.z) + 1.0) * s],
    }
    .clip(&world.bounds);
    let cells = CellRange { c0, c1 };
    let mut per_cell: Vec<Vec<Placement>> = vec![Vec::new(); cells.len()];
    if !target.is_empty() {
        let need = plan(world, target);
        // One ground patch over everything any rule computes.
        let ground = match (&world.fractal, need.iter().flatten().copied().reduce(Rect::union)) {
            (Some(f), Some(r)) => Ground::Patch(f.patch(r.lo, r.hi, f.depth)),
            _ => Ground::World(world),
        };
        // Populations in file order: each rule's output, and what later rules avoid.
        let pops = &world.populations;
        let mut placed: Vec<(u32, Vec<Placement>)> = Vec::new();
        let mut rng = InstanceRng::new(world.seed);
        for (n, rule) in world.rules.iter().enumerate() {
            let Some(exact) = need[n] else {
                placed.push((pops.rule_order[n], Vec::new()));
                continue;
            };
            let order = pops.rule_order[n];
            let avoid = (!rule.avoid.is_empty()).then(|| {
                let area = exact;
                let distance = |sp: u16| rule.avoid.iter().filter(|a| a.0 == sp).map(|a| a.1).reduce(f32::max);
                let earlier_rules = placed.iter().filter(|(o, _)| *o < order).flat_map(|(_, v)| v.iter());
                let reach = f64::from(rule.avoid.iter().map(|a| a.1).fold(0.0, f32::max)) + 1.0;
                let (e0, e1) = cell_span(world, area.grow(reach));
                let explicit = pops.explicit_in(e0, e1).filter(|(o, _)| *o < order).map(|(_, p)| p);
                let points = earlier_rules
                    .chain(explicit)
                    .filter_map(|p| distance(p.species).map(|d| [p.x, p.z, f64::from(d)]))
                    .collect();
                Buckets::new(area.grow(reach), points)
            });
            placed.push((order, scatter(world, rule, exact, &ground, avoid.as_ref(), &mut rng)));
        }
        // Every population into its cells, in file order.
        let mut items: Vec<(u32, &Placement)> = pops.explicit_in(c0, c1).map(|(o, p)| (*o, p)).collect();
        items.extend(placed.iter().flat_map(|(o, v)| v.iter().map(move |p| (*o, p))));
        items.sort_by_key(|&(o, _)| o);
        for (_, p) in items {
            let key = world.cell_of(p.x, p.z);
            if let Some(k) = cells.index(key)
                && target.contains(p.x, p.z)
            {
                per_cell[k].push(p.clone());
            }
        }
        for (key, edits) in pops.edits.range(c0..=c1).filter(|(k, _)| (c0.z..=c1.z).contains(&k.z)) {
            let Some(k) = cells.index(*key) else { continue };
            for (fell, e) in edits {
                let list = &mut per_cell[k];
                let Some(i) = list.iter().position(|p| p.species == e.species && p.x == e.x && p.z == e.z) else {
                    continue;
                };
                if *fell {
                    list.remove(i);
                } else {
                    let params = &mut list[i].params;
                    params.retain(|(slot, _)| e.params.iter().all(|(s, _)| s != slot));
                    params.extend_from_slice(&e.params);
                    params.sort_by_key(|&(slot, _)| slot);
                }
            }
        }
    }
    cells.keys().zip(per_cell).collect()
}

/// The cells covering a rectangle.
fn cell_span(world: &World, r: Rect) -> (CellKey, CellKey) {
    let s = f64::from(world.cell_size);
    let c = |v: f64| (v / s).floor().clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32;
    (CellKey { x: c(r.lo[0]), z: c(r.lo[1]) }, CellKey { x: c(r.hi[0]), z: c(r.hi[1]) })
}

/// An inclusive rectangle of cells, row-major.
#[derive(Clone, Copy)]
struct CellRange {
    c0: CellKey,
    c1: CellKey,
}

impl CellRange {
    fn width(&self) -> usize {
        (i64::from(self.c1.x) - i64::from(self.c0.x) + 1) as usize
    }

    fn len(&self) -> usize {
        self.width() * (i64::from(self.c1.z) - i64::from(self.c0.z) + 1) as usize
    }

    fn index(&self, c: CellKey) -> Option<usize> {
        let inside = (self.c0.x..=self.c1.x).contains(&c.x) && (self.c0.z..=self.c1.z).contains(&c.z);
        inside.then(|| (c.z - self.c0.z) as usize * self.width() + (i64::from(c.x) - i64::from(self.c0.x)) as usize)
    }

    fn keys(self) -> impl Iterator<Item = CellKey> {
        let Range { start, end } = 0..self.len();
        let w = self.width();
        (start..end).map(move |k| CellKey { x: self.c0.x + (k % w) as i32, z: self.c0.z + (k / w) as i32 })
    }
}
