//! The far-view summary hierarchy (issue 15): [`NodeSummary`] nodes of a quadtree over the cell grid, computed from
//! the world function — leaves as the *expectation* of a cell's expansion, parents by [`aggregate`] of their four
//! children — so that a server and a renderer can describe the forest to the horizon without expanding its cells.
//!
//! # Leaves
//!
//! A leaf (a level-0 node, one cell) is not an exact expansion ([`World::expand_cell`] costs milliseconds a cell);
//! it is the expectation of the same rules over the same terrain. The cell is split into [`COVER_SIDE`] ×
//! [`COVER_SIDE`] sub-squares, each sampled once (at one of 8 × 8 phases inside it, every phase once a cell, so that
//! a terrain lattice with the sub-square's period is not read at one phase only). At a sample, every `scatter`
//! rule in file order whose region holds the point has the expected density (instances per m²)
//!
//! ```text
//! ρ = density · altitude(h) · slope(s)  ·  PACKING / spacing²  ·  Π_B F_B(λ_B)
//! ```
//!
//! — the keep probability of [`ScatterRule::density_at`] (heights and slopes bit-equal to
//! [`World::height_and_slope`], read through one fractal [`Patch`] per block of 16 × 16 cells), the darts a full
//! Poisson-disk packing holds ([`PACKING`]), and, per species `B` the rule avoids (at its largest distance `d`), a
//! thinning factor of `λ_B`, the expected density of `B` from earlier rules at this sample: the fraction of ground
//! farther than `d` from every instance of `B`, where a dart of the rule survives (a rule's darts do not depend on
//! what it avoids). Where `B` stood at random that fraction would be `exp(−λ_B π d²)`; a Poisson-disk pattern's
//! discs overlap less, so `F_B = (1 − λπd²/n)ⁿ` with `n` growing from 1 as the discs can overlap
//! (`Avoid::log_factor` gives the model and its measured constants; `libm` for `log1p` and `pow`).
//! A sub-square's expected count is `ρ ·` its area. A species' count in the cell is `floor(Σ expected + u)`, `u` a
//! ChaCha8 draw in [0, 1) addressed by (world seed, cell, species) — stochastic rounding, unbiased and deterministic
//! — plus its explicit `instance` lines in the cell, exactly. Its height is the expected-count weighted mixture of
//! its rules' `height` parameter laws (a constant, or the uniform law of a range, discrete with a step; a species
//! default that is a constant or `uniform(a, b)`) and of its explicit instances' values: mean and standard
//! deviation in decimetres (0 for a species without a `height` parameter). A sub-square's coverage bit is set where
//! the species' expected count there (explicit instances included) is at least ½ (monotone in the expectation); a
//! species with a positive count and no such sub-square keeps the bit of its densest one.
//!
//! Not modelled: `avoid` distances to explicit instances (a handful of landmarks), baked `fell`/`set` edits (one
//! instance each), and the denser packing along a rule region's edge.
//!
//! # Edits
//!
//! A cell's live edits reach its leaf as [`LeafEdit`]s ([`World::leaf_edits`], `far_edits.rs`), counted as its
//! explicit instances are but signed: a felled instance takes one from its species' count (which stops at 0), its
//! sub-square's tally and the height moments, a planted one adds one, and a `set` of its height takes the old
//! height out and puts the new one in. A memo corrected so ([`Summaries::correct`], at most [`MAX_CORRECTED_CELLS`]
//! cells) drops every node holding the cell and caches nothing computed from the edits as they were before; the
//! parents follow, being sums. [`World::leaf_summaries`] and [`World::node_summary`] are the world function's alone.
//!
//! # Parents
//!
//! [`aggregate`] sums counts exactly, combines heights in integer arithmetic (means rounded half up, spreads
//! through `E[h²]` with one IEEE square root), sets a coverage bit where at least two of the four child bits under
//! it are set (so a mask keeps meaning "mostly covered" instead of growing by OR), keeps the most numerous
//! [`MAX_NODE_SPECIES`] species, and gives the node the error `cell_size · 2^level / 8`: its sub-square edge.
//!
//! Everything is f64 arithmetic in a fixed order, `libm` for `exp`, `log1p` and `pow`, ChaCha8 read by address and no hash-map
//! iteration, so a node is the same bits on every platform, in any order, alone or in a block, with or without a
//! cache ([`Summaries`]).

use canopy_protocol::summary::{COVER_SIDE, MAX_NODE_SPECIES, NodeKey, NodeSummary, SpeciesCover};
use canopy_protocol::{CellCoord, Expr, Func, Op};

mod memo;

pub use memo::Summaries;

use super::cells::Ground;
use super::far_edits::Corrections;
pub use super::far_edits::{LeafEdit, MAX_CORRECTED_CELLS};
use super::{CellKey, ParamValue, ScatterRule, World, par};
use crate::eval::unit_f32;
use crate::rng::{InstanceRng, child_key};

/// Darts per `spacing²` that the Poisson-disk process of `scatter` (priority rounds on a background grid of
/// `spacing / √2`, [`super::ROUNDS`] rounds of [`super::ATTEMPTS`] attempts) places on flat open ground at density
/// one. Measured: 0.6213 (a rule of spacing 4 over 16 × 16 cells of 64 m: 40,720 darts in 1,048,576 m²; spacings
/// 2.6, 5 and 6.5 give 0.6210, 0.6217 and 0.6222). `packing_constant_matches_the_poisson_disk_process` in
/// `worlds/tests/far.rs` holds it within 2 % of the measurement.
pub const PACKING: f64 = 0.6215;

/// Level of the blocks leaves are computed in: one fractal patch per aligned block of 16 × 16 cells.
pub const LEAF_BLOCK_LEVEL: u8 = 4;

/// Default bound on the nodes a [`Summaries`] keeps (about 200 bytes each for a few species: ~25 MiB).
pub const DEFAULT_CACHE_NODES: usize = 1 << 17;

/// Salt of the stochastic-rounding stream: word `species` of stream `child_key(SUMMARY_SALT, cell)`.
const SUMMARY_SALT: u64 = 0x7375_6d6d_6172_7900;

/// Sub-squares of a node: the coverage mask's bits.
const SUBS: usize = (COVER_SIDE * COVER_SIDE) as usize;

/// Cells per side of a leaf block.
const BLOCK: i32 = 1 << LEAF_BLOCK_LEVEL;

/// A parameter's distribution: mean and variance.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Law {
    mean: f64,
    var: f64,
}

impl Law {
    /// The law of a rule's parameter: a constant, or uniform over a range (continuous, or on `lo + k · step`).
    fn of(value: &ParamValue) -> Law {
        match *value {
            ParamValue::Constant(v) => Law { mean: f64::from(v), var: 0.0 },
            ParamValue::Range { lo, hi, step: None } => {
                let (lo, hi) = (f64::from(lo), f64::from(hi));
                Law { mean: (lo + hi) * 0.5, var: (hi - lo) * (hi - lo) / 12.0 }
            }
            ParamValue::Range { lo, hi, step: Some(step) } => {
                let (lo, hi, step) = (f64::from(lo), f64::from(hi), f64::from(step));
                let n = ((hi - lo) / step).floor() + 1.0;
                Law { mean: lo + step * (n - 1.0) * 0.5, var: step * step * (n * n - 1.0) / 12.0 }
            }
        }
    }

    /// The law of a species' default expression where it is one we can read: a constant, or `uniform(a, b)` of
    /// two constants. `None` for anything else (its mean is not known without evaluating it).
    fn of_default(e: &Expr) -> Option<Law> {
        match e.ops.as_slice() {
            [Op::Const(v)] => Some(Law::of(&ParamValue::Constant(*v))),
            [Op::Const(a), Op::Const(b), Op::Call(Func::Uniform)] => {
                let (lo, hi) = (f64::from(a.min(*b)), f64::from(a.max(*b)));
                Some(Law { mean: (lo + hi) * 0.5, var: (hi - lo) * (hi - lo) / 12.0 })
            }
            _ => None,
        }
    }
}

/// One species a rule avoids, as the leaf model reads it (see [`Avoid::log_factor`]).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Avoid {
    /// The avoided species.
    species: usize,
    /// `π · d²` at the rule's largest distance from that species.
    area: f64,
    /// How far the avoided pattern's discs can overlap: `(d / s_B − 0.55)^1.5`, 0 while they cannot.
    overlap: f64,
    /// `s_B² / PACKING`: the keep fraction of the avoided species is `λ · s_B² / PACKING`.
    keep_per_lambda: f64,
}

/// The avoid model's constants (`an_avoiding_rule_is_estimated_within_tolerance` in `worlds/tests/far.rs` checks
/// them on pairs and triples of rules like the embedded worlds').
const TRIALS_FROM: f64 = 0.55;
const TRIALS_SCALE: f64 = 4.0;
const TRIALS_THINNED: f64 = 1.5;

impl Avoid {
    /// `ln` of the factor by which the avoided species' expected density `lambda` (per m²) thins the rule: the
    /// fraction of ground farther than `d` from every instance of the avoided species, where a dart of the rule
    /// survives (the rule's pattern does not depend on the avoided one).
    ///
    /// That fraction is `f = (1 − λπd² / n)ⁿ`: exactly `1 − λπd²` while a Poisson-disk pattern's discs of radius
    /// `d` cannot overlap (`d ≤ 0.55 · s_B`, n = 1), tending to the Poisson `exp(−λπd²)` as
    /// `n = 1 + (4 + 1.5 (1 − p)) (d / s_B − 0.55)^1.5` grows (`p` the avoided pattern's keep fraction: a
    /// thinned pattern is less regular). Measured on patterns of `s_B` = 4 m, `d / s_B` 0.3 to 1.5, `p` 0.3 to 1.
    fn log_factor(&self, lambda: f64) -> f64 {
        let x = lambda * self.area;
        let thinned = 1.0 - (lambda * self.keep_per_lambda).min(1.0);
        let trials = 1.0 + (TRIALS_SCALE + TRIALS_THINNED * thinned) * self.overlap;
        if x >= trials {
            return f64::NEG_INFINITY;
        }
        trials * libm::log1p(-x / trials)
    }
}

/// A `scatter` rule as the leaf model reads it.
#[derive(Clone, Debug)]
struct RuleModel {
    species: usize,
    /// `PACKING / spacing²`: expected darts per m² where the rule keeps every dart.
    darts: f64,
    /// Whether the rule has an altitude or slope ramp (else its keep probability is its density).
    ramps: bool,
    /// The species it avoids that earlier rules place (each once, at its largest distance).
    avoid: Vec<Avoid>,
    /// The law of the species' `height` parameter under this rule.
    height: Option<Law>,
}

/// What the leaf model needs of a world, resolved once.
#[derive(Clone, Debug)]
struct Model {
    rules: Vec<RuleModel>,
    /// Per species: its `height` slot and the law of its default.
    heights: Vec<Option<(u16, Option<Law>)>>,
}

impl Model {
    fn new(world: &World) -> Model {
        let heights: Vec<Option<(u16, Option<Law>)>> = world
            .species
            .iter()
            .map(|s| {
                let slot = s.graph.param_slot("height")?;
                Some((slot, Law::of_default(&s.graph.params[usize::from(slot)].default)))
            })
            .collect();
        let rules = world
            .rules
            .iter()
            .enumerate()
            .map(|(n, r)| {
                let species = usize::from(r.species);
                let spacing = f64::from(r.spacing);
                let mut avoid: Vec<Avoid> = Vec::new();
                for &(b, d) in &r.avoid {
                    let b = usize::from(b);
                    // The avoided species' pattern: the smallest spacing of the earlier rules placing it.
                    let earlier = world.rules[..n].iter().filter(|e| usize::from(e.species) == b);
                    let Some(sb) = earlier.map(|e| f64::from(e.spacing)).reduce(f64::min) else { continue };
                    let d = f64::from(d);
                    let entry = Avoid {
                        species: b,
                        area: std::f64::consts::PI * d * d,
                        overlap: libm::pow((d / sb - TRIALS_FROM).max(0.0), 1.5),
                        keep_per_lambda: sb * sb / PACKING,
                    };
                    match avoid.iter_mut().find(|a| a.species == b) {
                        Some(a) if a.area < entry.area => *a = entry,
                        Some(_) => {}
                        None => avoid.push(entry),
                    }
                }
                let height = heights[species].and_then(|(slot, default)| {
                    r.params.iter().find(|(s, _)| *s == slot).map(|(_, v)| Law::of(v)).or(default)
                });
                RuleModel { species, darts: PACKING / (spacing * spacing), ramps: r.has_ramps(), avoid, height }
            })
            .collect();
        Model { rules, heights }
    }
}

/// The mean of each rule's `height` parameter (the rule's value, else its species' default where that is a
/// constant or `uniform` of two), in rule order; `None` where the species has no `height` or its default is an
/// expression only evaluating would tell (the ground's cover reads trees by it).
pub(super) fn rule_heights(world: &World) -> Vec<Option<f64>> {
    Model::new(world).rules.iter().map(|r| r.height.map(|l| l.mean)).collect()
}

/// The mean of a species default the leaf model reads ([`Law::of_default`]: a constant, or `uniform(a, b)` of two
/// constants), as an instance's height.
pub(super) fn default_mean(e: &Expr) -> Option<f32> {
    Law::of_default(e).map(|l| l.mean as f32)
}

/// Per-species sums over one cell while it is computed.
#[derive(Clone, Debug)]
struct Tally {
    /// Expected count per sub-square, from the rules.
    sub: [f64; SUBS],
    /// Explicit instances per sub-square, and edits (signed).
    explicit: [i64; SUBS],
    /// Height moments: Σ w, Σ w · mean, Σ w · (var + mean²).
    w: f64,
    wm: f64,
    wq: f64,
    /// Σ |w| of the edits' heights: what `w` may have lost to cancellation (0 for a cell without edits).
    edited: f64,
}

impl Tally {
    const EMPTY: Tally = Tally { sub: [0.0; SUBS], explicit: [0; SUBS], w: 0.0, wm: 0.0, wq: 0.0, edited: 0.0 };

    fn add_height(&mut self, weight: f64, law: Law) {
        self.w += weight;
        self.wm += weight * law.mean;
        self.wq += weight * (law.var + law.mean * law.mean);
    }
}

/// Decimetres from metres, rounded half up and clamped to `u16`.
fn decimetres(m: f64) -> u16 {
    (m * 10.0 + 0.5).floor().clamp(0.0, f64::from(u16::MAX)) as u16
}

/// Keep the most numerous [`MAX_NODE_SPECIES`] (ties by lower id), in increasing id order.
fn keep_top(mut species: Vec<SpeciesCover>) -> Vec<SpeciesCover> {
    if species.len() > MAX_NODE_SPECIES {
        species.sort_by(|a, b| b.count.cmp(&a.count).then(a.species.cmp(&b.species)));
        species.truncate(MAX_NODE_SPECIES);
        species.sort_by_key(|s| s.species);
    }
    species
}

/// The geometric error of a node with something in it: its sub-square edge, `cell_size · 2^level / 8`.
fn node_error(cell_size: f32, level: u8) -> f32 {
    cell_size * (1u32 << level) as f32 / COVER_SIDE as f32
}

/// Where in sub-square `(i, j)` a leaf samples: phases `(a, b)` of 8 per axis, point `((a + ½) / 8, (b + ½) / 8)` of
/// the sub-square. `(a, b) = (i + 2j, 3i + j) mod 8` is a bijection of the 64 sub-squares onto the 64 phases (the
/// matrix has an odd determinant), so a cell samples every phase once: a terrain whose lattice repeats with the
/// sub-square's period (a grid of 4 or 8 m under 8 m sub-squares) is not read at one phase of it only — its slopes
/// near coarse lattice points differ from those between them, which biased sampling at centres by up to 15 %.
fn phase(i: u32, j: u32) -> (u32, u32) {
    ((i + 2 * j) % 8, (3 * i + j) % 8)
}

/// The leaves of cells `c0 ..= c1` (row-major), which must lie in one block (the patch is made for them), each
/// corrected by its `edits`.
fn leaf_block(world: &World, model: &Model, c0: CellKey, c1: CellKey, edits: &Corrections) -> Vec<NodeSummary> {
    let s = f64::from(world.cell_size);
    let sub = s / f64::from(COVER_SIDE);
    let area = sub * sub;
    // Sub-square `i` of cell `c`, at phase `a` of 8 within it (see `phase`).
    let at = |c: i32, i: u32, a: u32| f64::from(c) * s + (f64::from(i) + (f64::from(a) + 0.5) / 8.0) * sub;
    let lo = [at(c0.x, 0, 0), at(c0.z, 0, 0)];
    let hi = [at(c1.x, COVER_SIDE - 1, 7), at(c1.z, COVER_SIDE - 1, 7)];
    let heights = match &world.fractal {
        Some(f) => Ground::Patch(f.patch(lo, hi, f.depth)),
        None => Ground::World(world),
    };
    // Rules that can place nothing in the block are skipped (their densities there are exactly 0).
    let active: Vec<usize> = (0..world.rules.len())
        .filter(|&r| {
            let rule: &ScatterRule = &world.rules[r];
            let g = &rule.region;
            let meets = f64::from(g.min[0]) <= hi[0]
                && f64::from(g.max[0]) > lo[0]
                && f64::from(g.min[1]) <= hi[1]
                && f64::from(g.max[1]) > lo[1];
            let reachable = match &heights {
                Ground::Patch(p) => rule.altitude.max_over(p.height_range()) > 0.0,
                Ground::World(_) => true,
            };
            meets && reachable && rule.density > 0.0
        })
        .collect();
    let species = world.species.len();
    let mut rng = InstanceRng::new(world.seed);
    let mut lambda = vec![0.0f64; species];
    let mut tallies = vec![Tally::EMPTY; species];
    let mut expected = vec![0.0f64; world.rules.len()];
    // The last densities each rule's avoid factors were computed for, and the factors: where the ramps are flat
    // (most of the ground) neighbouring samples meet the same densities, and `log1p` and `exp` are pure.
    let mut last: Vec<(Vec<Memo>, Memo)> =
        model.rules.iter().map(|m| (vec![Memo::EMPTY; m.avoid.len()], Memo::EMPTY)).collect();
    let mut out = Vec::new();
    for cz in c0.z..=c1.z {
        for cx in c0.x..=c1.x {
            tallies.iter_mut().for_each(|t| *t = Tally::EMPTY);
            expected.iter_mut().for_each(|e| *e = 0.0);
            for j in 0..COVER_SIDE {
                for i in 0..COVER_SIDE {
                    let (a, b) = phase(i, j);
                    let (x, z) = (at(cx, i, a), at(cz, j, b));
                    let k = (j * COVER_SIDE + i) as usize;
                    let mut ground: Option<(f32, f64)> = None;
                    lambda.iter_mut().for_each(|l| *l = 0.0);
                    for &r in &active {
                        let (rule, m) = (&world.rules[r], &model.rules[r]);
                        if !rule.region.contains(x, z) {
                            continue;
                        }
                        // The keep probability, in f32 exactly as cell expansion takes it.
                        let p = if m.ramps {
                            let (h, g2) = *ground.get_or_insert_with(|| heights.height_and_gradient2(x, z));
                            rule.keep(h, g2)
                        } else {
                            rule.density
                        };
                        if p <= 0.0 {
                            continue;
                        }
                        let mut rho = f64::from(p) * m.darts;
                        let mut log_factor = 0.0;
                        let (avoids, factor) = &mut last[r];
                        for (a, memo) in m.avoid.iter().zip(avoids.iter_mut()) {
                            if lambda[a.species] > 0.0 {
                                log_factor += memo.get(lambda[a.species], |l| a.log_factor(l));
                            }
                        }
                        if log_factor < 0.0 {
                            rho *= factor.get(log_factor, libm::exp);
                        }
                        lambda[m.species] += rho;
                        expected[r] += rho;
                        tallies[m.species].sub[k] += rho * area;
                    }
                }
            }
            let cell = CellKey { x: cx, z: cz };
            for (r, m) in model.rules.iter().enumerate() {
                if let Some(law) = m.height
                    && expected[r] > 0.0
                {
                    tallies[m.species].add_height(expected[r] * area, law);
                }
            }
            let sub_of = |v: f64, o: i32| ((v - f64::from(o) * s) / sub).floor().clamp(0.0, 7.0) as u32;
            for (_, p) in world.populations.explicit.get(&cell).into_iter().flatten() {
                let t = &mut tallies[usize::from(p.species)];
                t.explicit[(sub_of(p.z, cz) * COVER_SIDE + sub_of(p.x, cx)) as usize] += 1;
                if let Some((slot, default)) = model.heights[usize::from(p.species)] {
                    let own =
                        p.params.iter().find(|(s, _)| *s == slot).map(|&(_, v)| Law::of(&ParamValue::Constant(v)));
                    if let Some(law) = own.or(default) {
                        t.add_height(1.0, law);
                    }
                }
            }
            // The cell's edits, counted as its explicit instances are but signed (an unknown species, a sign of 0
            // and a height that is not finite count nothing).
            for e in edits.get(&cell).into_iter().flat_map(|e| e.iter()).filter(|e| e.sign != 0) {
                let Some(t) = tallies.get_mut(usize::from(e.species)) else { continue };
                let sign = e.sign.signum();
                t.explicit[(sub_of(e.z, cz) * COVER_SIDE + sub_of(e.x, cx)) as usize] += i64::from(sign);
                let h = e.height.filter(|h| h.is_finite());
                if let (Some(Some(_)), Some(h)) = (model.heights.get(usize::from(e.species)), h) {
                    t.add_height(f64::from(sign), Law::of(&ParamValue::Constant(h)));
                    t.edited += 1.0;
                }
            }
            out.push(leaf(world, model, &mut rng, cell, &tallies));
        }
    }
    out
}

/// A pure function's last argument and value, to skip recomputing it for the same argument (bit for bit).
#[derive(Clone, Copy, Debug)]
struct Memo {
    arg: u64,
    value: f64,
}

impl Memo {
    /// Matches no argument a leaf computes (a NaN).
    const EMPTY: Memo = Memo { arg: u64::MAX, value: 0.0 };

    fn get(&mut self, arg: f64, f: impl FnOnce(f64) -> f64) -> f64 {
        if arg.to_bits() != self.arg {
            *self = Memo { arg: arg.to_bits(), value: f(arg) };
        }
        self.value
    }
}

/// One leaf from its tallies.
fn leaf(world: &World, model: &Model, rng: &mut InstanceRng, cell: CellKey, tallies: &[Tally]) -> NodeSummary {
    let stream = child_key(SUMMARY_SALT, (u64::from(cell.x as u32) << 32) | u64::from(cell.z as u32));
    let mut species = Vec::new();
    for (id, t) in tallies.iter().enumerate() {
        let sum: f64 = t.sub.iter().sum();
        let explicit: i64 = t.explicit.iter().sum();
        let drawn = if sum > 0.0 { (sum + f64::from(unit_f32(rng.word(stream, id as u64)))).floor() } else { 0.0 };
        let count = (drawn as i64).saturating_add(explicit).clamp(0, i64::from(u32::MAX)) as u32;
        if count == 0 {
            continue;
        }
        let at = |k: usize| t.sub[k] + t.explicit[k] as f64;
        let mut cover = (0..SUBS).filter(|&k| at(k) >= 0.5).fold(0u64, |m, k| m | 1 << k);
        if cover == 0 {
            let densest = (0..SUBS).fold(0, |best, k| if at(k) > at(best) { k } else { best });
            cover = 1 << densest;
        }
        // Edits can take the weight to 0 or below, or leave a rounding residue of a cancellation: no height then.
        let (height_dm, spread_dm) = if model.heights[id].is_some() && t.w > t.edited * 1e-9 {
            let mean = t.wm / t.w;
            let var = (t.wq / t.w - mean * mean).max(0.0);
            (decimetres(mean), decimetres(var.sqrt()))
        } else {
            (0, 0)
        };
        species.push(SpeciesCover { species: id as u16, count, height_dm, spread_dm, cover });
    }
    let species = keep_top(species);
    let error = if species.is_empty() { 0.0 } else { node_error(world.cell_size, 0) };
    NodeSummary { key: NodeKey { level: 0, x: cell.x, z: cell.z }, error, species }
}

/// One species' sums over the four children of a node.
#[derive(Clone, Debug)]
struct Merge {
    species: u16,
    count: u64,
    /// Σ count · height_dm.
    heights: u128,
    /// Σ count · (spread_dm² + height_dm²).
    squares: u128,
    /// Per parent sub-square: how many of the child bits under it are set.
    bits: [u8; SUBS],
    /// Per child: its count.
    quadrants: [u64; 4],
}

/// The parent of four nodes (`children` in [`NodeKey::children`] order): counts summed exactly, the count-weighted
/// height mean in integers (rounded half up), the spread through `E[h²]` (`√(n·Σc(s²+h²) − (Σch)²) / n` with one
/// f64 square root), a coverage bit where at least 2 of the 4 child bits under it are set (the densest one kept
/// for a species that would lose every bit), the most numerous [`MAX_NODE_SPECIES`] species, and the error twice
/// the children's (`cell_size · 2^level / 8`; 0 for an empty node).
pub fn aggregate(key: NodeKey, children: [&NodeSummary; 4]) -> NodeSummary {
    let mut merged: Vec<Merge> = Vec::new();
    for (q, child) in children.iter().enumerate() {
        let (qi, qj) = ((q & 1) as u32 * COVER_SIDE / 2, (q >> 1) as u32 * COVER_SIDE / 2);
        for s in &child.species {
            let at = match merged.binary_search_by_key(&s.species, |m| m.species) {
                Ok(at) => at,
                Err(at) => {
                    let m = Merge {
                        species: s.species,
                        count: 0,
                        heights: 0,
                        squares: 0,
                        bits: [0; SUBS],
                        quadrants: [0; 4],
                    };
                    merged.insert(at, m);
                    at
                }
            };
            let m = &mut merged[at];
            let (c, h, sp) = (u128::from(s.count), u128::from(s.height_dm), u128::from(s.spread_dm));
            m.count += u64::from(s.count);
            m.quadrants[q] += u64::from(s.count);
            m.heights += c * h;
            m.squares += c * (sp * sp + h * h);
            for bit in 0..SUBS as u32 {
                if s.cover >> bit & 1 == 1 {
                    let (i, j) = (bit % COVER_SIDE, bit / COVER_SIDE);
                    m.bits[((qj + j / 2) * COVER_SIDE + qi + i / 2) as usize] += 1;
                }
            }
        }
    }
    let species = merged
        .into_iter()
        .filter(|m| m.count > 0)
        .map(|m| {
            let n = u128::from(m.count);
            let height_dm = ((2 * m.heights + n) / (2 * n)).min(u128::from(u16::MAX)) as u16;
            let var = (n * m.squares).saturating_sub(m.heights * m.heights);
            let spread = (var as f64).sqrt() / (n as f64);
            let spread_dm = (spread + 0.5).floor().min(f64::from(u16::MAX)) as u16;
            let mut cover = (0..SUBS).filter(|&k| m.bits[k] >= 2).fold(0u64, |c, k| c | 1 << k);
            if cover == 0 {
                let densest = (0..SUBS).fold(0, |best, k| if m.bits[k] > m.bits[best] { k } else { best });
                cover = if m.bits[densest] > 0 {
                    1 << densest
                } else {
                    // Only when a child listed the species with an empty mask: its quadrant's first sub-square.
                    let q = (0..4).fold(0, |best, q| if m.quadrants[q] > m.quadrants[best] { q } else { best });
                    1 << ((q >> 1) * SUBS / 2 + (q & 1) * COVER_SIDE as usize / 2)
                };
            }
            let count = m.count.min(u64::from(u32::MAX)) as u32;
            SpeciesCover { species: m.species, count, height_dm, spread_dm, cover }
        })
        .collect();
    let species = keep_top(species);
    let error = if species.is_empty() { 0.0 } else { 2.0 * children.iter().map(|c| c.error).fold(0.0, f32::max) };
    NodeSummary { key, error, species }
}

/// The parents of a row-major grid of nodes of side `side` (even) whose first node is `first`.
fn parents(nodes: &[NodeSummary], side: usize, first: NodeKey) -> Vec<NodeSummary> {
    let half = side / 2;
    let mut out = Vec::with_capacity(half * half);
    for j in 0..half {
        for i in 0..half {
            let at = |a: usize, b: usize| &nodes[(2 * j + b) * side + 2 * i + a];
            let key = NodeKey { level: first.level + 1, x: (first.x >> 1) + i as i32, z: (first.z >> 1) + j as i32 };
            out.push(aggregate(key, [at(0, 0), at(1, 0), at(0, 1), at(1, 1)]));
        }
    }
    out
}

/// Aggregate a row-major grid of `side × side` nodes (side a power of two, first node aligned) level by level up
/// to its root, handing every node, the given ones included, to `sink`.
fn build_up(mut nodes: Vec<NodeSummary>, mut side: usize, mut sink: impl FnMut(&NodeSummary)) -> NodeSummary {
    loop {
        nodes.iter().for_each(&mut sink);
        if side == 1 {
            return nodes.pop().expect("one root");
        }
        let first = nodes[0].key;
        nodes = parents(&nodes, side, first);
        side /= 2;
    }
}

/// The node `key` (level ≤ [`LEAF_BLOCK_LEVEL`]) from its leaves (corrected by `edits`), every node of its subtree
/// handed to `sink`.
fn subtree(
    world: &World,
    model: &Model,
    key: NodeKey,
    edits: &Corrections,
    sink: impl FnMut(&NodeSummary),
) -> NodeSummary {
    let c = key.first_cell();
    let n = key.side();
    let (c0, c1) = (CellKey { x: c.x, z: c.z }, CellKey { x: c.x + n - 1, z: c.z + n - 1 });
    let leaves = leaf_block(world, model, c0, c1, edits);
    build_up(leaves, n as usize, sink)
}

/// The level-[`LEAF_BLOCK_LEVEL`] descendants of `key` (level above it), row-major.
fn blocks_of(key: NodeKey) -> (Vec<NodeKey>, usize) {
    let side = 1i32 << (key.level - LEAF_BLOCK_LEVEL);
    let (x0, z0) = (key.x * side, key.z * side);
    let keys = (0..side)
        .flat_map(|j| (0..side).map(move |i| NodeKey { level: LEAF_BLOCK_LEVEL, x: x0 + i, z: z0 + j }))
        .collect();
    (keys, side as usize)
}

/// A world cell from a protocol cell.
pub fn cell_key(c: CellCoord) -> CellKey {
    CellKey { x: c.x, z: c.z }
}

/// A protocol cell from a world cell.
pub fn cell_coord(c: CellKey) -> CellCoord {
    CellCoord::new(c.x, c.z)
}

/// The encoded size of a node, bytes (postcard, as the wire carries it).
pub fn summary_bytes(n: &NodeSummary) -> usize {
    postcard::to_allocvec(n).expect("encoding a node summary into a Vec cannot fail").len()
}

impl World {
    /// The level-0 summaries (leaves) of every cell of `c0 ..= c1`, row-major (z outer, x inner): the expectation
    /// of each cell's expansion (see [`crate::world::far`]). Computed in aligned blocks of 16 × 16 cells on the
    /// available cores; a cell's leaf is the same whatever rectangle it was asked in. Empty for an empty rectangle.
    pub fn leaf_summaries(&self, c0: CellKey, c1: CellKey) -> Vec<NodeSummary> {
        if c0.x > c1.x || c0.z > c1.z {
            return Vec::new();
        }
        let model = Model::new(self);
        let block = |v: i32| v.div_euclid(BLOCK);
        let mut parts = Vec::new();
        for bz in block(c0.z)..=block(c1.z) {
            for bx in block(c0.x)..=block(c1.x) {
                let lo = CellKey { x: (bx * BLOCK).max(c0.x), z: (bz * BLOCK).max(c0.z) };
                let hi = CellKey { x: (bx * BLOCK + BLOCK - 1).min(c1.x), z: (bz * BLOCK + BLOCK - 1).min(c1.z) };
                parts.push((lo, hi));
            }
        }
        let none = Corrections::new();
        let computed = par::map(&parts, || (), |_, &(lo, hi)| leaf_block(self, &model, lo, hi, &none));
        let width = (i64::from(c1.x) - i64::from(c0.x) + 1) as usize;
        let height = (i64::from(c1.z) - i64::from(c0.z) + 1) as usize;
        let mut slots: Vec<Option<NodeSummary>> = vec![None; width * height];
        for ((lo, hi), leaves) in parts.into_iter().zip(computed) {
            let w = (hi.x - lo.x + 1) as usize;
            let (dx, dz) = ((i64::from(lo.x) - i64::from(c0.x)) as usize, (i64::from(lo.z) - i64::from(c0.z)) as usize);
            for (k, n) in leaves.into_iter().enumerate() {
                slots[(dz + k / w) * width + dx + k % w] = Some(n);
            }
        }
        slots.into_iter().map(|n| n.expect("every cell computed")).collect()
    }

    /// The summary of node `key`, from its leaves aggregated level by level through [`aggregate`] (cost ∝ 4^level
    /// cells; blocks of 16 × 16 cells on the available cores). Equal to `aggregate` of its children's.
    pub fn node_summary(&self, key: NodeKey) -> NodeSummary {
        let model = Model::new(self);
        node_with(self, &model, key)
    }
}

/// [`World::node_summary`] with the model resolved.
fn node_with(world: &World, model: &Model, key: NodeKey) -> NodeSummary {
    if key.level <= LEAF_BLOCK_LEVEL {
        return subtree(world, model, key, &Corrections::new(), |_| {});
    }
    let (blocks, side) = blocks_of(key);
    let none = Corrections::new();
    let roots = par::map(&blocks, || (), |_, &b| subtree(world, model, b, &none, |_| {}));
    build_up(roots, side, |_| {})
}
