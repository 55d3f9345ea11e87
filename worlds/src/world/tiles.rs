//! Corner-coloured tiles of a `scatter` rule's Poisson-disk pattern: the priority process run once per tile
//! variant, so a cell's darts are looked up instead of computed over a halo (Lagae & Dutré's procedural object
//! distribution function, with the corner colours of their corner tiles; the layout is described in
//! [`crate::world`]).
//!
//! The plane is cut into tiles of `2 · MARGIN` background cells a side. Every tile corner gets one of [`COLOURS`]
//! colours from a hash of its lattice position, and the random words of the background cells in the square of one
//! tile side centred on a corner depend only on that colour and the cell's place in the square. The priority
//! process decides a dart from the words within its halo, which is at most `MARGIN` background cells, so the darts
//! of a tile are a function of its four corner colours: `COLOURS⁴` variants, each computed once, on first use, from
//! the 2 × 2 corner squares around it. Neighbouring tiles share the corner squares they both read, so the pattern is
//! one Poisson-disk process over the whole plane: spacing holds across every tile border. The caches of a world's
//! rules share one bound ([`TILE_CACHE_BYTES`]): a world function from the network cannot make them grow past it.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};

use super::{ROUNDS, par};
use crate::rng::{InstanceRng, child_key, mix64};

/// Colours of a tile corner: a rule has `COLOURS⁴` tile variants.
pub const COLOURS: u32 = 4;
/// Background cells from a tile corner to the tile's centre: at least the process's halo
/// `(2 · ROUNDS − 1) · spacing + 2 · g` in cells of `g ≥ spacing / √2` (8 cells of `spacing / √2` hold `5.66 ·
/// spacing`).
pub const MARGIN: i64 = 10;
const _: () = assert!(((MARGIN - 2) * (MARGIN - 2)) as f64 >= 2.0 * ((2 * ROUNDS - 1) * (2 * ROUNDS - 1)) as f64);

/// Positions an empty background cell tries per round before it gives up proposing in that round.
pub const ATTEMPTS: u32 = 7;

/// Words of a background cell's stream: round `r` reads words `8r .. 8r + ATTEMPTS` for its positions and word
/// `8r + 7` for its priority.
const WORDS_PER_ROUND: usize = 8;
const ROUND_WORDS: usize = WORDS_PER_ROUND * ROUNDS as usize;
const _: () = assert!(ROUND_WORDS == 24, "rounds 0 and 1 read block 0, round 2 block 1");

/// Most bytes the tile caches of one world keep, over all its rules (the words and the variants; a few rules
/// take about 0.4 MiB each). Past it, a variant or a rule's words are computed for the expansion that needs them
/// and not kept: a world function with many rules costs time, not memory.
pub(super) const TILE_CACHE_BYTES: usize = 32 << 20;

/// Variants computed on all cores at once when one lookup needs at least this many.
const PARALLEL_VARIANTS: usize = 4;

/// The darts of one tile variant: positions in the tile, steps.
type Variant = Box<[[u32; 2]]>;

/// What a cached variant costs.
fn variant_bytes(v: &Variant) -> usize {
    std::mem::size_of_val(&**v) + std::mem::size_of::<Variant>()
}

/// No dart.
const EMPTY: [i64; 2] = [i64::MIN, i64::MIN];

/// The tile variants of one rule, computed on first use. Positions are in position steps (the world's
/// `cell / POSITION_STEPS`), so the whole pattern is integer arithmetic.
pub(crate) struct Tiles {
    /// The rule's key.
    key: u64,
    /// The world seed (the ChaCha key of every word).
    seed: u64,
    /// Background cell edge, steps: `⌈spacing / √2⌉` on the position grid.
    g: i64,
    /// `spacing²` in steps², rounded up: two darts conflict when their squared distance is below it.
    r2: i64,
    /// The words of every background cell of a corner square, by colour, row-major in the square (computed on
    /// first use).
    words: OnceLock<Box<[[u32; ROUND_WORDS]]>>,
    /// Per variant (corner colours `c00 + C·c10 + C²·c01 + C³·c11`), its darts' positions in the tile, steps,
    /// row-major by background cell.
    variants: Box<[OnceLock<Variant>]>,
    /// Bytes the world's tile caches may still take (shared by its rules; see [`TILE_CACHE_BYTES`]).
    budget: Arc<AtomicUsize>,
}

impl Tiles {
    /// A world's budget for its tile caches: [`TILE_CACHE_BYTES`].
    pub(crate) fn budget() -> Arc<AtomicUsize> {
        Arc::new(AtomicUsize::new(TILE_CACHE_BYTES))
    }

    /// The tiles of a rule of `spacing` metres keyed `key`, on a grid of `step` metres, caching within `budget`.
    pub(crate) fn new(seed: u64, key: u64, spacing: f32, step: f64, budget: Arc<AtomicUsize>) -> Tiles {
        let s = f64::from(spacing) / step;
        let g = (s / std::f64::consts::SQRT_2).ceil().max(1.0) as i64;
        let r2 = (s * s).ceil() as i64;
        let variants = (0..COLOURS.pow(4)).map(|_| OnceLock::new()).collect();
        Tiles { key, seed, g, r2, words: OnceLock::new(), variants, budget }
    }

    /// Tile edge, steps.
    pub(crate) fn side(&self) -> i64 {
        2 * MARGIN * self.g
    }

    /// The colour of tile corner (a, b).
    fn colour(&self, a: i64, b: i64) -> u32 {
        (mix64(child_key(child_key(self.key, 2), a as u64) ^ b as u64) % u64::from(COLOURS)) as u32
    }

    /// The variant of tile (a, b): its corner colours.
    fn variant(&self, a: i64, b: i64) -> usize {
        let c = [self.colour(a, b), self.colour(a + 1, b), self.colour(a, b + 1), self.colour(a + 1, b + 1)];
        c.iter().rev().fold(0, |v, &c| v * COLOURS as usize + c as usize)
    }

    /// Every dart of the pattern in the steps `lo ..= hi` (inclusive, both axes), as `(x, z)` steps, row-major by
    /// position (z, then x).
    pub(crate) fn darts(&self, lo: [i64; 2], hi: [i64; 2]) -> Vec<[i64; 2]> {
        let t = self.side();
        let (a0, a1) = (lo[0].div_euclid(t), hi[0].div_euclid(t));
        let (b0, b1) = (lo[1].div_euclid(t), hi[1].div_euclid(t));
        let tiles: Vec<(i64, i64, usize)> =
            (b0..=b1).flat_map(|b| (a0..=a1).map(move |a| (a, b))).map(|(a, b)| (a, b, self.variant(a, b))).collect();
        // Variants not yet computed, on all cores when there are several: kept within the budget, else held here
        // for this expansion only.
        let mut missing: Vec<usize> = tiles.iter().map(|t| t.2).filter(|&v| self.variants[v].get().is_none()).collect();
        missing.sort_unstable();
        missing.dedup();
        let computed = if missing.len() >= PARALLEL_VARIANTS {
            par::map(&missing, || (), |_, &v| self.compute(v))
        } else {
            missing.iter().map(|&v| self.compute(v)).collect()
        };
        let mut local = BTreeMap::new();
        for (v, darts) in missing.into_iter().zip(computed) {
            if let Err(darts) = self.keep(&self.variants[v], darts, variant_bytes) {
                local.insert(v, darts);
            }
        }
        let mut out = Vec::new();
        for (a, b, v) in tiles {
            let origin = [a * t, b * t];
            let darts = self.variants[v].get().or_else(|| local.get(&v)).expect("computed above");
            for d in darts.iter() {
                let p = [origin[0] + i64::from(d[0]), origin[1] + i64::from(d[1])];
                if p[0] >= lo[0] && p[0] <= hi[0] && p[1] >= lo[1] && p[1] <= hi[1] {
                    out.push(p);
                }
            }
        }
        out.sort_unstable_by_key(|p| (p[1], p[0]));
        out
    }

    /// The darts of variant `v`: the priority process over the 2 × 2 corner squares around the tile, kept in the
    /// tile.
    fn compute(&self, v: usize) -> Variant {
        let c = COLOURS as usize;
        let colours = [v % c, (v / c) % c, (v / (c * c)) % c, v / (c * c * c)];
        let window = self.process(&colours, 2);
        window.tile(MARGIN, self.g)
    }

    /// The priority process over `squares × squares` corner squares of these colours (row-major), exact inside it away from
    /// its border by the halo.
    fn process(&self, colours: &[usize], squares: i64) -> Window {
        let (g, side) = (self.g, 2 * MARGIN);
        let n = squares * side;
        let words = self.words();
        let square = (side * side) as usize;
        // A window of n × n background cells with a border of two empty cells on every side.
        let dims = n + 4;
        let at = |i: i64, j: i64| ((j + 2) * dims + i + 2) as usize;
        let mut offsets: Vec<(i64, i64)> = (-2i64..=2)
            .flat_map(|b| (-2i64..=2).map(move |a| (a, b)))
            .filter(|&(a, b)| !(a.abs() == 2 && b.abs() == 2) && (a, b) != (0, 0))
            .collect();
        // Nearest first: a conflict, when there is one, is found after a few comparisons.
        offsets.sort_by_key(|&(a, b)| (a * a + b * b, b, a));
        let near: Vec<isize> = offsets.iter().map(|&(a, b)| (b * dims + a) as isize).collect();
        let len = (dims * dims) as usize;
        let mut placed = vec![EMPTY; len];
        let mut proposals = vec![(EMPTY, 0u32); len];
        let r2 = self.r2;
        let closer = |d: [i64; 2], x: i64, z: i64| d != EMPTY && (d[0] - x).pow(2) + (d[1] - z).pow(2) < r2;
        for round in 0..ROUNDS as usize {
            let base = round * WORDS_PER_ROUND;
            // Proposals: every empty background cell tries up to ATTEMPTS positions and proposes the first that
            // keeps `spacing` from the placed darts.
            for j in 0..n {
                for i in 0..n {
                    let k = at(i, j);
                    proposals[k] = (EMPTY, 0);
                    if placed[k] != EMPTY {
                        continue;
                    }
                    let colour = colours[((j / side) * squares + i / side) as usize];
                    let block = &words[colour * square + ((j % side) * side + i % side) as usize];
                    let clear = |x: i64, z: i64| {
                        round == 0 || !near.iter().any(|&o| closer(placed[(k as isize + o) as usize], x, z))
                    };
                    let proposal = block[base..base + ATTEMPTS as usize].iter().find_map(|&w| {
                        let x = i * g + ((i64::from(w & 0xffff) * g) >> 16);
                        let z = j * g + ((i64::from(w >> 16) * g) >> 16);
                        clear(x, z).then_some([x, z])
                    });
                    if let Some(p) = proposal {
                        proposals[k] = (p, block[base + WORDS_PER_ROUND - 1]);
                    }
                }
            }
            // Acceptance: a proposal is placed if it outranks every proposal within `spacing` (priority, then the
            // background cell in row-major order: a strict order, so two darts closer than `spacing` are never
            // both placed).
            for j in 0..n {
                for i in 0..n {
                    let k = at(i, j);
                    let (d, priority) = proposals[k];
                    if d == EMPTY {
                        continue;
                    }
                    let wins = near.iter().all(|&o| {
                        let q = (k as isize + o) as usize;
                        let (other, p) = proposals[q];
                        !closer(other, d[0], d[1]) || (priority, k) > (p, q)
                    });
                    if wins {
                        placed[k] = d;
                    }
                }
            }
        }
        Window { placed, dims }
    }

    /// Cache `value` in `slot` if the world's budget has its bytes; else hand it back.
    fn keep<T>(&self, slot: &OnceLock<T>, value: T, bytes: fn(&T) -> usize) -> Result<(), T> {
        let n = bytes(&value);
        if self.budget.fetch_update(Ordering::AcqRel, Ordering::Acquire, |left| left.checked_sub(n)).is_err() {
            return Err(value);
        }
        if slot.set(value).is_err() {
            // Another thread cached it first.
            self.budget.fetch_add(n, Ordering::AcqRel);
        }
        Ok(())
    }

    /// The words of every corner square: cached, computed and cached within the budget, or computed for this use.
    fn words(&self) -> Cow<'_, [[u32; ROUND_WORDS]]> {
        if let Some(w) = self.words.get() {
            return Cow::Borrowed(w);
        }
        match self.keep(&self.words, self.compute_words(), |w| std::mem::size_of_val(&**w)) {
            Ok(()) => Cow::Borrowed(self.words.get().expect("just set")),
            Err(w) => Cow::Owned(w.into_vec()),
        }
    }

    /// The words of every background cell of every corner square: cell `(i, j)` of the square of colour `c`
    /// reads stream `child_key(child_key(child_key(R, 0), c), i << 32 | j)`.
    fn compute_words(&self) -> Box<[[u32; ROUND_WORDS]]> {
        let side = 2 * MARGIN;
        let mut rng = InstanceRng::new(self.seed);
        let root = child_key(self.key, 0);
        let mut out = vec![[0u32; ROUND_WORDS]; (side * side) as usize * COLOURS as usize];
        for (k, block) in out.iter_mut().enumerate() {
            let k = k as i64;
            let (colour, j, i) = (k / (side * side), (k / side) % side, k % side);
            let stream = child_key(child_key(root, colour as u64), (i as u64) << 32 | j as u64);
            for (w, word) in block.iter_mut().enumerate() {
                *word = rng.word(stream, w as u64);
            }
        }
        out.into_boxed_slice()
    }
}

/// The darts of a window of background cells, with a border of two empty cells on every side.
struct Window {
    placed: Vec<[i64; 2]>,
    dims: i64,
}

impl Window {
    /// The darts of the tile whose first background cell is `(first, first)`, in steps from its corner
    /// (background cells of `g` steps).
    fn tile(&self, first: i64, g: i64) -> Variant {
        let origin = first * g;
        let mut out = Vec::new();
        for j in first..first + 2 * MARGIN {
            for i in first..first + 2 * MARGIN {
                let d = self.placed[((j + 2) * self.dims + i + 2) as usize];
                if d != EMPTY {
                    out.push([(d[0] - origin) as u32, (d[1] - origin) as u32]);
                }
            }
        }
        out.into_boxed_slice()
    }
}

impl Clone for Tiles {
    fn clone(&self) -> Tiles {
        Tiles { words: self.words.clone(), variants: self.variants.clone(), budget: Arc::clone(&self.budget), ..*self }
    }
}

impl PartialEq for Tiles {
    /// Tiles are derived from the rule: two are equal when they derive from the same parameters, whatever each
    /// has computed so far.
    fn eq(&self, o: &Tiles) -> bool {
        (self.key, self.seed, self.g, self.r2) == (o.key, o.seed, o.g, o.r2)
    }
}

impl std::fmt::Debug for Tiles {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let computed = self.variants.iter().filter(|v| v.get().is_some()).count();
        f.debug_struct("Tiles").field("cell", &self.g).field("r2", &self.r2).field("computed", &computed).finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The invariant the tiles rest on: the process decides every dart of a tile from the 2 × 2 corner squares
    /// around it. Computed over 4 × 4 corner squares (a margin of one more square on every side), the middle tile
    /// has the same darts as its variant.
    #[test]
    fn a_tile_is_decided_by_its_four_corners() {
        for (spacing, step) in [(2.6f32, 1.0 / 64.0), (3.0, 1.0 / 64.0), (5.0, 1.0 / 16.0), (0.7, 1.0 / 256.0)] {
            let tiles = Tiles::new(7, 0x5eed ^ u64::from(spacing.to_bits()), spacing, step, Tiles::budget());
            for seed in 0..6u64 {
                let colours: Vec<usize> =
                    (0..16).map(|q| (mix64(seed * 16 + q) % u64::from(COLOURS)) as usize).collect();
                let wide = tiles.process(&colours, 4);
                // The tile between corners 1 and 2 of the wide window: its first cell is one square and a margin in.
                let got = wide.tile(2 * MARGIN + MARGIN, tiles.g);
                let c = COLOURS as usize;
                let corners = [colours[5], colours[6], colours[9], colours[10]];
                let v = corners.iter().rev().fold(0, |v, &k| v * c + k);
                assert_eq!(got, tiles.compute(v), "spacing {spacing}, corners {corners:?}");
                assert!(got.len() > 50, "a tile holds darts: {}", got.len());
            }
        }
    }

    #[test]
    fn darts_keep_their_spacing_across_tile_borders() {
        let tiles = Tiles::new(3, 11, 2.0, 1.0 / 64.0, Tiles::budget());
        let side = tiles.side();
        let darts = tiles.darts([-2 * side, -2 * side], [3 * side - 1, 3 * side - 1]);
        for (n, a) in darts.iter().enumerate() {
            for b in &darts[n + 1..] {
                let d2 = (a[0] - b[0]).pow(2) + (a[1] - b[1]).pow(2);
                assert!(d2 >= tiles.r2, "{a:?} and {b:?} closer than the spacing");
            }
        }
        // Row-major by position, inside the rectangle.
        assert!(darts.windows(2).all(|w| (w[0][1], w[0][0]) < (w[1][1], w[1][0])));
        assert!(darts.len() > 25 * 100, "{} darts", darts.len());
    }

    #[test]
    fn past_the_budget_tiles_are_computed_not_kept() {
        let (lo, hi) = ([-3000, -2000], [9000, 7000]);
        let kept = Tiles::new(5, 9, 2.6, 1.0 / 64.0, Tiles::budget());
        let none = Tiles::new(5, 9, 2.6, 1.0 / 64.0, Arc::new(AtomicUsize::new(0)));
        assert_eq!(kept.darts(lo, hi), none.darts(lo, hi));
        assert!(none.words.get().is_none() && none.variants.iter().all(|v| v.get().is_none()), "nothing kept");
        let cached = kept.variants.iter().filter(|v| v.get().is_some()).count();
        assert!(kept.words.get().is_some() && cached > 4, "{cached} variants kept");
        assert!(kept.budget.load(Ordering::Relaxed) < TILE_CACHE_BYTES);
    }
}
