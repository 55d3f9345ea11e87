//! Cells as a function: the placements of any rectangle of cells computed from the manifest and a bounded
//! neighbourhood (a halo) around it, so Poisson-disk spacing, the density ramps and `avoid` distances hold across
//! cell borders and any machine expanding any cell in any order gets the same records (the algorithm is described
//! in [`crate::world`]).

use std::collections::BTreeMap;
use std::ops::Range;

use super::fractal::Patch;
use super::{Bounds, CellKey, Placement, ScatterRule, World, par};
use crate::eval::unit_f32;
use crate::rng::{InstanceRng, child_key};

/// Rounds of the priority Poisson-disk process: each round lets every empty background cell propose one more
/// dart.
pub const ROUNDS: u32 = 3;
/// Most background cells (summed over rules and rounds) one cell's expansion may visit; a manifest whose rules and
/// `avoid` chains need more is refused at load.
pub const MAX_CELL_WORK: f64 = 16_777_216.0;
/// Most instances in one cell: an index in a cell fits 16 bits.
pub const MAX_CELL_INSTANCES: usize = 65_535;
/// Cells per side of the blocks a large region is expanded in (bounds the memory of one expansion).
pub const REGION_BLOCK: i32 = 32;

/// Positions an empty background cell tries per round before it gives up proposing in that round.
pub const ATTEMPTS: u32 = 7;

/// Words of a background cell's stream: round `r` reads words `8r .. 8r + ATTEMPTS` for its positions and word
/// `8r + 7` for its priority (block 0 is read for every background cell, block 1 only for those still empty in the
/// last round); a placed dart's keep draw is word 24 and its parameters words 25, 26, ….
const WORDS_PER_ROUND: u64 = 8;
const ROUND_WORDS: usize = (WORDS_PER_ROUND * ROUNDS as u64) as usize;
const _: () = assert!(ROUND_WORDS == 24, "rounds 0 and 1 read block 0, round 2 block 1");
const WORD_KEEP: u64 = ROUND_WORDS as u64;
const WORD_PARAMS: u64 = WORD_KEEP + 1;

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

/// The background cell edge of a rule, `spacing / √2`.
fn background(rule: &ScatterRule) -> f64 {
    f64::from(rule.spacing) / std::f64::consts::SQRT_2
}

/// How far outside its output a rule must be computed for the output to be exact: the first round's decision at a
/// dart depends on proposals within `spacing`, every later round's on what the previous rounds placed within
/// `2 · spacing`; and a dart lies anywhere in its background cell.
fn halo(rule: &ScatterRule) -> f64 {
    f64::from(2 * ROUNDS - 1) * f64::from(rule.spacing) + 2.0 * background(rule)
}

/// The rectangle each rule must be exact over for `target` to be: its own output, grown by the halo and `avoid`
/// distance of every later rule that avoids its species, clipped to the rule's region. `None` where a rule
/// contributes nothing.
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
                    need[m] = need[m].union(out.grow(halo(&rules[n]) + f64::from(d) + 1.0));
                }
            }
        }
    }
    need
}

/// Background cells and rounds one cell's expansion costs at most, wherever the cell lies (the load-time bound).
pub(crate) fn cell_work(world: &World) -> f64 {
    let s = f64::from(world.cell_size);
    let target = Rect { lo: [0.0, 0.0], hi: [s, s] };
    plan_unclipped(world, target)
        .iter()
        .zip(&world.rules)
        .map(|(r, rule)| (r.grow(halo(rule)), background(rule)))
        .map(|(r, g)| ((r.hi[0] - r.lo[0]) / g + 2.0) * ((r.hi[1] - r.lo[1]) / g + 2.0) * f64::from(ROUNDS))
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

/// A window of background cells, row-major, with a border of two empty cells on every side so that every
/// neighbour of a window cell has an index.
struct Field {
    lo: [i64; 2],
    dims: [i64; 2],
    /// Index offsets of the cells that can hold a dart closer than `spacing = g·√2` to one in a cell: those within
    /// two, less the four corners (their nearest points are exactly `2·g·√2 − g·√2 = spacing` apart) and itself.
    near: [isize; 20],
}

impl Field {
    fn new(lo: [i64; 2], hi: [i64; 2]) -> Field {
        let dims = [hi[0] - lo[0] + 5, hi[1] - lo[1] + 5];
        // Nearest first: a conflict, when there is one, is found after a few comparisons.
        let mut offsets: Vec<(i64, i64)> = (-2i64..=2)
            .flat_map(|b| (-2i64..=2).map(move |a| (a, b)))
            .filter(|&(a, b)| !(a.abs() == 2 && b.abs() == 2) && (a, b) != (0, 0))
            .collect();
        offsets.sort_by_key(|&(a, b)| (a * a + b * b, b, a));
        let near = std::array::from_fn(|n| (offsets[n].1 * dims[0] + offsets[n].0) as isize);
        Field { lo, dims, near }
    }

    fn len(&self) -> usize {
        (self.dims[0] * self.dims[1]) as usize
    }

    /// The index of window cell (i, j).
    fn at(&self, i: i64, j: i64) -> usize {
        ((j - self.lo[1] + 2) * self.dims[0] + (i - self.lo[0] + 2)) as usize
    }

    fn neighbours(&self, k: usize) -> impl Iterator<Item = usize> + '_ {
        self.near.iter().map(move |&o| (k as isize + o) as usize)
    }
}

/// Windows of at least this many background cells are worked on in bands of rows on the available cores.
const PARALLEL_CELLS: usize = 1 << 16;

/// Bands of a field's rows for [`par::each`]: one band for a small window.
struct Bands {
    /// Per band: its first and last row (background cell coordinates) and its first padded row.
    rows: Vec<(i64, i64, usize)>,
    /// Padded row width.
    width: usize,
}

impl Bands {
    fn new(field: &Field, lo: i64, hi: i64) -> Bands {
        let count = if field.len() >= PARALLEL_CELLS { 8 } else { 1 };
        let per = ((hi - lo + count) / count).max(1);
        let rows = (0..count)
            .map(|b| (lo + b * per, (lo + (b + 1) * per - 1).min(hi)))
            .filter(|(a, b)| a <= b)
            .map(|(a, b)| (a, b, (a - lo + 2) as usize))
            .collect();
        Bands { rows, width: field.dims[0] as usize }
    }

    /// The jobs of one phase writing `out`: per band, its rows of `out`, the index of their first slot and the
    /// band's first and last row.
    fn jobs<'a, T>(&self, out: &'a mut [T]) -> Vec<(&'a mut [T], usize, (i64, i64))> {
        let first = self.rows.first().map_or(0, |r| r.2 * self.width);
        let mut lengths = vec![first];
        lengths.extend(self.rows.iter().map(|&(a, b, _)| (b - a + 1) as usize * self.width));
        let mut runs = par::split_runs(out, &lengths).into_iter().skip(1);
        self.rows
            .iter()
            .map(|&(a, b, start)| (runs.next().expect("one run per band"), start * self.width, (a, b)))
            .collect()
    }
}

/// No dart: x is NaN.
const EMPTY: [f64; 2] = [f64::NAN, f64::NAN];

/// Whether a dart at `d` lies closer than `√r2` to (x, z) (an empty slot never does).
#[inline]
fn closer(d: [f64; 2], x: f64, z: f64, r2: f64) -> bool {
    let (dx, dz) = (d[0] - x, d[1] - z);
    dx * dx + dz * dz < r2
}

/// The ChaCha8 stream of background cell (i, j) of a rule.
fn cell_stream(rule: &ScatterRule, i: i64, j: i64) -> u64 {
    child_key(child_key(rule.key, 0), (u64::from(i as u32) << 32) | u64::from(j as u32))
}

/// Expand one rule over `exact` (computing over it grown by the halo): the kept darts inside `exact`, in
/// row-major order of their background cells, with their parameter values.
fn scatter(
    world: &World,
    rule: &ScatterRule,
    exact: Rect,
    ground: &Ground,
    avoid: Option<&Buckets>,
    rng: &mut InstanceRng,
) -> Vec<Placement> {
    let g = background(rule);
    let area = exact.grow(halo(rule)).clip(&rule.region);
    let lo = [(area.lo[0] / g).floor() as i64, (area.lo[1] / g).floor() as i64];
    let hi = [(area.hi[0] / g).floor() as i64, (area.hi[1] / g).floor() as i64];
    let field = Field::new(lo, hi);
    let n = field.len();
    let mut placed = vec![EMPTY; n];
    let (step, inv_step) = super::populate::position_step(world.cell_size);
    let r2 = f64::from(rule.spacing) * f64::from(rule.spacing);
    let region = Rect { lo: rule.region.min.map(f64::from), hi: rule.region.max.map(f64::from) };
    // Grid positions `k · step` inside background cell `i`: `(first k, count)`.
    let positions = |i: i64| {
        let first = ((i as f64 * g) * inv_step).ceil() as i64;
        (first, (((i + 1) as f64 * g) * inv_step).ceil() as i64 - first)
    };
    // Where the rule's density is 0 over the whole area, it places nothing (its darts would all be thinned out).
    if let Ground::Patch(p) = ground
        && rule.altitude.max_over(p.height_range()) <= 0.0
    {
        return Vec::new();
    }
    // Every phase below is independent per background cell: it writes the cell's own slot and reads only what the
    // phase before wrote. A large window runs in bands of rows on the available cores, with the same result.
    let bands = Bands::new(&field, lo[1], hi[1]);
    let seed = world.seed;
    // Block 0 of every background cell's stream (rounds 0 and 1); block 1 (round 2) only for the cells still
    // empty when it begins.
    let mut words = vec![[0u32; ROUND_WORDS]; n];
    let fill = |words: &mut [[u32; ROUND_WORDS]], offset: usize, rows: (i64, i64), placed: &[[f64; 2]], part: usize| {
        let mut rng = InstanceRng::new(seed);
        for j in rows.0..=rows.1 {
            for i in lo[0]..=hi[0] {
                let k = field.at(i, j);
                if part == 1 && !placed[k][0].is_nan() {
                    continue;
                }
                let stream = cell_stream(rule, i, j);
                let range = if part == 0 { 0..16 } else { 16..ROUND_WORDS };
                for w in range {
                    words[k - offset][w] = rng.word(stream, w as u64);
                }
            }
        }
    };
    par::each(bands.jobs(&mut words), |(slice, offset, rows)| fill(slice, offset, rows, &placed, 0));
    // Per background cell: this round's proposal (NaN for none) and its priority.
    let mut proposals = vec![(EMPTY, 0u32); n];
    for round in 0..ROUNDS as usize {
        if round * WORDS_PER_ROUND as usize == 16 {
            par::each(bands.jobs(&mut words), |(slice, offset, rows)| fill(slice, offset, rows, &placed, 1));
        }
        // Proposals: every empty background cell tries up to ATTEMPTS positions and proposes the first that keeps
        // `spacing` from the placed darts and the `avoid` distances.
        let base = round * WORDS_PER_ROUND as usize;
        let propose = |out: &mut [([f64; 2], u32)], offset: usize, rows: (i64, i64)| {
            for j in rows.0..=rows.1 {
                let (kz, cz) = positions(j);
                for i in lo[0]..=hi[0] {
                    let k = field.at(i, j);
                    out[k - offset] = (EMPTY, 0);
                    let (kx, cx) = positions(i);
                    if !placed[k][0].is_nan() || cx < 1 || cz < 1 {
                        continue;
                    }
                    let block = &words[k];
                    let proposal = block[base..base + ATTEMPTS as usize].iter().find_map(|&w| {
                        let x = (kx + ((i64::from(w & 0xffff) * cx) >> 16)) as f64 * step;
                        let z = (kz + ((i64::from(w >> 16) * cz) >> 16)) as f64 * step;
                        let inside = region.contains(x, z) && area.contains(x, z);
                        let clear = inside && !field.neighbours(k).any(|q| closer(placed[q], x, z, r2));
                        (clear && !avoid.is_some_and(|b| b.near(x, z))).then_some([x, z])
                    });
                    if let Some(p) = proposal {
                        out[k - offset] = (p, block[base + WORDS_PER_ROUND as usize - 1]);
                    }
                }
            }
        };
        par::each(bands.jobs(&mut proposals), |(slice, offset, rows)| propose(slice, offset, rows));
        // Acceptance: a proposal is placed if it outranks every proposal within `spacing` (priority, then the
        // background cell in row-major order: a strict order, so two darts closer than `spacing` are never both
        // placed).
        let accept = |out: &mut [[f64; 2]], offset: usize, rows: (i64, i64)| {
            for j in rows.0..=rows.1 {
                for i in lo[0]..=hi[0] {
                    let k = field.at(i, j);
                    let (d, priority) = proposals[k];
                    if d[0].is_nan() {
                        continue;
                    }
                    let wins = field.neighbours(k).all(|q| {
                        let (o, other) = proposals[q];
                        !closer(o, d[0], d[1], r2) || (priority, k) > (other, q)
                    });
                    if wins {
                        out[k - offset] = d;
                    }
                }
            }
        };
        par::each(bands.jobs(&mut placed), |(slice, offset, rows)| accept(slice, offset, rows));
    }
    // Thinning and parameters, inside the exact rectangle only.
    let mut kept = Vec::new();
    let graph = &world.species[usize::from(rule.species)].graph;
    for j in lo[1]..=hi[1] {
        for i in lo[0]..=hi[0] {
            let [x, z] = placed[field.at(i, j)];
            if x.is_nan() || !exact.contains(x, z) {
                continue;
            }
            let stream = cell_stream(rule, i, j);
            if unit_f32(rng.word(stream, WORD_KEEP)) >= ground.density(rule, x, z) {
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
        let all = need.iter().zip(&world.rules).filter_map(|(r, rule)| r.map(|r| r.grow(halo(rule))));
        let ground = match (&world.fractal, all.reduce(Rect::union)) {
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
                let area = exact.grow(halo(rule));
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
