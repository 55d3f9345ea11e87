//! Terrain as a function (seed 001 §5 and §7): one midpoint-displacement fractal over the whole plane, whose height
//! at any point and any recursion depth is computed locally from a few numbers — the control heights, the fractal
//! dimension, the relief and a seed — by client and server alike. No height grid is stored or sent.
//!
//! # The surface
//!
//! Level `k` is a square lattice of spacing `s_k = tile / 2^k` anchored at `origin`; lattice point `(i, j)` of level
//! `k` lies at `origin + (i, j) · s_k`. Its height `V(k, i, j)`:
//! - level 0: the control height `corners[clamp(j)][clamp(i)]` (the grid extends its edge values outwards), or,
//!   without control heights, `relief · 2^H · n(0, i, j)`;
//! - level `k > 0`, `i` and `j` even: the parent point's height `V(k - 1, i / 2, j / 2)`;
//! - `i` odd, `j` even (or the reverse): `(a + b) · 0.5 + d_k · n(k, i, j)` with `a`, `b` the parent points at the
//!   ends of the edge, lower index first;
//! - both odd: `((a + b) + (c + d)) · 0.25 + d_k · n(k, i, j)` with the four parent corners in the order
//!   `(−,−) (+,−) (−,+) (+,+)`;
//!
//! where `d_k = relief · 2^(−(k − 1) · H)`, `H = 3 − dimension` (the Hurst exponent; `2^−H` through `libm::pow`),
//! and the noise `n(k, i, j) = 2 · unit_f32(w) − 1` with `w` word `(i & 3) + 4 · (j & 3)` of ChaCha8 stream
//! `child_key(child_key(seed, k), (i >> 2) as u32 << 32 | (j >> 2) as u32)`: a 4 × 4 block of lattice points
//! shares one ChaCha block. Every value is computed in f64 in that fixed order, so any machine gets the same bits,
//! and neighbouring squares agree on their shared edges (an edge's midpoint depends on its two ends only): no
//! cracks at any depth.
//!
//! At depth `D` the surface is the level-`D` lattice split into triangles along each square's `(0, 0)–(1, 1)`
//! diagonal; [`Fractal::height`] interpolates on that triangle, so a renderer that meshes the level-`D` lattice
//! draws exactly the surface instances stand on. A coarser depth is the same surface with fewer levels
//! (recursion-depth LOD): lattice heights shared by both depths are equal.

use canopy_protocol::messages::FractalDesc;

use super::terrain::slope_degrees;
use crate::eval::unit_f32;
use crate::rng::{InstanceRng, child_key};

/// Deepest subdivision of a fractal terrain (the welcome's bound too).
pub const MAX_FRACTAL_DEPTH: u32 = canopy_protocol::netlimits::MAX_FRACTAL_DEPTH;
/// Smallest lattice spacing at full depth, metres.
pub(super) const MIN_FRACTAL_SPACING: f64 = canopy_protocol::netlimits::MIN_FRACTAL_SPACING;
/// Most control heights.
pub(super) const MAX_CONTROL_HEIGHTS: usize = canopy_protocol::netlimits::MAX_CONTROL_HEIGHTS;
/// The fractal dimension's range: `[2, 3)`.
pub(super) const DIMENSION_RANGE: (f32, f32) = canopy_protocol::netlimits::FRACTAL_DIMENSION;

/// A fractal terrain: everything needed to compute a height anywhere.
#[derive(Clone, Debug, PartialEq)]
pub struct Fractal {
    /// Noise seed.
    pub seed: u64,
    /// World (x, z) of lattice point (0, 0) at every level.
    pub origin: [f64; 2],
    /// Level-0 lattice spacing, metres.
    pub tile: f64,
    /// Levels of subdivision at full detail.
    pub depth: u32,
    /// Fractal dimension in [2, 3).
    pub dimension: f32,
    /// Displacement amplitude of level 1, metres.
    pub relief: f32,
    /// Control heights at the level-0 lattice, `dims[0] × dims[1]`, rows of increasing z; empty for none.
    pub corners: Vec<f32>,
    /// Control grid points per axis (x, z); `[0, 0]` without control heights.
    pub dims: [u32; 2],
    /// `2^−H`, the displacement ratio between levels.
    ratio: f64,
}

/// Why a fractal's numbers are not acceptable.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FractalError {
    /// Depth or spacing out of range.
    #[error(
        "fractal terrain: depth {depth} with tile {tile} m gives a {spacing} m lattice (allowed: depth ≤ {MAX_FRACTAL_DEPTH}, lattice ≥ {MIN_FRACTAL_SPACING} m)"
    )]
    Depth {
        /// The depth.
        depth: u32,
        /// The tile.
        tile: f64,
        /// The finest spacing.
        spacing: f64,
    },
    /// Dimension outside [2, 3), or a relief or tile that is not finite and positive.
    #[error("fractal terrain: the dimension must lie in [2, 3) and the tile and relief be finite (≥ 0)")]
    Numbers,
    /// The control grid is not rectangular or too large.
    #[error("fractal terrain: {0} control heights, expected a rectangle of at most {MAX_CONTROL_HEIGHTS}")]
    Corners(usize),
}

impl Fractal {
    /// A fractal from its numbers; `rows` are the control heights by rows of increasing z (may be empty).
    pub fn new(
        seed: u64,
        origin: [f64; 2],
        tile: f64,
        depth: u32,
        dimension: f32,
        relief: f32,
        rows: &[Vec<f32>],
    ) -> Result<Fractal, FractalError> {
        let spacing = tile / f64::from(1u32 << depth.min(31));
        if depth > MAX_FRACTAL_DEPTH || spacing.is_nan() || spacing < MIN_FRACTAL_SPACING {
            return Err(FractalError::Depth { depth, tile, spacing });
        }
        let numbers_ok = (DIMENSION_RANGE.0..DIMENSION_RANGE.1).contains(&dimension)
            && relief.is_finite()
            && relief >= 0.0
            && tile.is_finite()
            && origin.iter().all(|v| v.is_finite());
        if !numbers_ok {
            return Err(FractalError::Numbers);
        }
        let count: usize = rows.iter().map(Vec::len).sum();
        let width = rows.first().map_or(0, Vec::len);
        if count > MAX_CONTROL_HEIGHTS || rows.iter().any(|r| r.len() != width) {
            return Err(FractalError::Corners(count));
        }
        if rows.iter().flatten().any(|h| !h.is_finite()) {
            return Err(FractalError::Numbers);
        }
        let hurst = 3.0 - f64::from(dimension);
        Ok(Fractal {
            seed,
            origin,
            tile,
            depth,
            dimension,
            relief,
            corners: rows.concat(),
            dims: [width as u32, rows.len() as u32],
            ratio: libm::pow(2.0, -hurst),
        })
    }

    /// The numbers a welcome carries ([`FractalDesc`]): everything a client needs to compute the same heights.
    pub fn describe(&self) -> FractalDesc {
        FractalDesc {
            seed: self.seed,
            origin: self.origin,
            tile: self.tile,
            depth: self.depth,
            dimension: self.dimension,
            relief: self.relief,
            dims: self.dims,
            heights: self.corners.clone(),
        }
    }

    /// The lattice spacing at depth `depth`.
    pub fn spacing(&self, depth: u32) -> f64 {
        self.tile / f64::from(1u32 << depth)
    }

    /// Height at (x, z) at full depth.
    pub fn height(&self, x: f64, z: f64) -> f32 {
        self.height_and_slope(x, z).0
    }

    /// Height and slope (degrees) at (x, z) at full depth.
    pub fn height_and_slope(&self, x: f64, z: f64) -> (f32, f32) {
        self.patch([x, z], [x, z], self.depth).height_and_slope(x, z)
    }

    /// Height and `|∇h|²` at (x, z) at full depth ([`Patch::height_and_gradient2`]).
    pub fn height_and_gradient2(&self, x: f64, z: f64) -> (f32, f64) {
        self.patch([x, z], [x, z], self.depth).height_and_gradient2(x, z)
    }

    /// Height at (x, z) at a coarser depth (recursion-depth LOD); `depth` is clamped to the full depth.
    pub fn height_at_depth(&self, x: f64, z: f64, depth: u32) -> f32 {
        self.patch([x, z], [x, z], depth.min(self.depth)).height_and_slope(x, z).0
    }

    /// The lattice of depth `depth` over the rectangle `lo ..= hi` (world x, z): every square that touches it.
    /// Heights anywhere in the rectangle then cost one lookup. Equal, bit for bit, to [`Fractal::height`].
    pub fn patch(&self, lo: [f64; 2], hi: [f64; 2], depth: u32) -> Patch {
        let depth = depth.min(self.depth);
        let s = self.spacing(depth);
        let cell = |v: f64, o: f64| ((v - o) / s).floor() as i64;
        // Lattice points of the finest level covering the rectangle: the squares' corners.
        let mut lo_i = [cell(lo[0], self.origin[0]), cell(lo[1], self.origin[1])];
        let mut hi_i = [cell(hi[0], self.origin[0]) + 1, cell(hi[1], self.origin[1]) + 1];
        // The windows of every level, finest last: a level's window holds its parents' ends.
        let mut windows = vec![(lo_i, hi_i)];
        for _ in 0..depth {
            lo_i = lo_i.map(|v| v.div_euclid(2));
            hi_i = hi_i.map(|v| (v + 1).div_euclid(2));
            windows.push((lo_i, hi_i));
        }
        windows.reverse();
        let mut rng = InstanceRng::new(self.seed);
        let (lo0, hi0) = windows[0];
        let mut values = Grid::new(lo0, hi0);
        for j in lo0[1]..=hi0[1] {
            for i in lo0[0]..=hi0[0] {
                let v = self.level0(&mut rng, i, j);
                values.set(i, j, v);
            }
        }
        for (k, &(lo_k, hi_k)) in windows.iter().enumerate().skip(1) {
            let d = f64::from(self.relief) * pow_int(self.ratio, k as u32 - 1);
            let stream = child_key(self.seed, k as u64);
            let mut next = Grid::new(lo_k, hi_k);
            // Tile by tile of 4 × 4 points, the points that share a noise block (`noise`): one ChaCha block each.
            // Every point depends on the level above only, so the order changes no value.
            for tj in lo_k[1] >> 2..=hi_k[1] >> 2 {
                for ti in lo_k[0] >> 2..=hi_k[0] >> 2 {
                    for j in (tj * 4).max(lo_k[1])..=(tj * 4 + 3).min(hi_k[1]) {
                        for i in (ti * 4).max(lo_k[0])..=(ti * 4 + 3).min(hi_k[0]) {
                            let p = |a: i64, b: i64| values.get(a.div_euclid(2), b.div_euclid(2));
                            let n = |rng: &mut InstanceRng| d * noise(rng, stream, i, j);
                            let v = match (i & 1, j & 1) {
                                (0, 0) => p(i, j),
                                (1, 0) => (p(i - 1, j) + p(i + 1, j)) * 0.5 + n(&mut rng),
                                (0, _) => (p(i, j - 1) + p(i, j + 1)) * 0.5 + n(&mut rng),
                                _ => {
                                    ((p(i - 1, j - 1) + p(i + 1, j - 1)) + (p(i - 1, j + 1) + p(i + 1, j + 1))) * 0.25
                                        + n(&mut rng)
                                }
                            };
                            next.set(i, j, v);
                        }
                    }
                }
            }
            values = next;
        }
        Patch { origin: self.origin, spacing: s, values }
    }

    /// A level-0 lattice height.
    fn level0(&self, rng: &mut InstanceRng, i: i64, j: i64) -> f64 {
        if self.corners.is_empty() {
            let d = f64::from(self.relief) / self.ratio;
            return d * noise(rng, child_key(self.seed, 0), i, j);
        }
        let ci = i.clamp(0, i64::from(self.dims[0]) - 1) as usize;
        let cj = j.clamp(0, i64::from(self.dims[1]) - 1) as usize;
        f64::from(self.corners[cj * self.dims[0] as usize + ci])
    }
}

/// `base^n` by repeated multiplication (a fixed order, the same everywhere).
fn pow_int(base: f64, n: u32) -> f64 {
    (0..n).fold(1.0, |acc, _| acc * base)
}

/// The noise `n(k, i, j)` in [−1, 1) of level stream `stream = child_key(seed, k)`.
fn noise(rng: &mut InstanceRng, stream: u64, i: i64, j: i64) -> f64 {
    let block = (u64::from((i >> 2) as u32) << 32) | u64::from((j >> 2) as u32);
    let w = rng.word(child_key(stream, block), ((i & 3) + 4 * (j & 3)) as u64);
    2.0 * f64::from(unit_f32(w)) - 1.0
}

/// Lattice values over an inclusive window of indices.
#[derive(Clone, Debug)]
struct Grid {
    lo: [i64; 2],
    width: usize,
    values: Vec<f64>,
}

impl Grid {
    fn new(lo: [i64; 2], hi: [i64; 2]) -> Grid {
        let width = (hi[0] - lo[0] + 1) as usize;
        let rows = (hi[1] - lo[1] + 1) as usize;
        Grid { lo, width, values: vec![0.0; width * rows] }
    }

    fn index(&self, i: i64, j: i64) -> usize {
        (j - self.lo[1]) as usize * self.width + (i - self.lo[0]) as usize
    }

    fn get(&self, i: i64, j: i64) -> f64 {
        self.values[self.index(i, j)]
    }

    fn set(&mut self, i: i64, j: i64, v: f64) {
        let k = self.index(i, j);
        self.values[k] = v;
    }
}

/// The lattice of one depth over a rectangle ([`Fractal::patch`]).
#[derive(Clone, Debug)]
pub struct Patch {
    origin: [f64; 2],
    spacing: f64,
    values: Grid,
}

impl Patch {
    /// The lattice spacing, metres.
    pub fn spacing(&self) -> f64 {
        self.spacing
    }

    /// Lattice indices `lo ..= hi` the patch holds.
    pub fn window(&self) -> ([i64; 2], [i64; 2]) {
        let rows = (self.values.values.len() / self.values.width) as i64;
        (self.values.lo, [self.values.lo[0] + self.values.width as i64 - 1, self.values.lo[1] + rows - 1])
    }

    /// The lowest and highest lattice height, each widened by a metre: the surface over the patch lies strictly
    /// inside them, whatever the rounding.
    pub fn height_range(&self) -> [f32; 2] {
        let v = &self.values.values;
        let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        [(lo - 1.0) as f32, (hi + 1.0) as f32]
    }

    /// The height of lattice point (i, j), which must lie in [`Patch::window`].
    pub fn lattice(&self, i: i64, j: i64) -> f64 {
        self.values.get(i, j)
    }

    /// Height and slope (degrees) at (x, z), which must lie in the rectangle the patch was made for: on the
    /// triangle of the lattice square under it (split along `(0, 0)–(1, 1)`).
    pub fn height_and_slope(&self, x: f64, z: f64) -> (f32, f32) {
        let (h, g2) = self.height_and_gradient2(x, z);
        (h, slope_degrees(g2))
    }

    /// Height and `|∇h|²` at (x, z) (the slope before its `atan`, see [`slope_degrees`]), as
    /// [`Patch::height_and_slope`].
    pub fn height_and_gradient2(&self, x: f64, z: f64) -> (f32, f64) {
        let (u, v) = ((x - self.origin[0]) / self.spacing, (z - self.origin[1]) / self.spacing);
        let (i, j) = (u.floor(), v.floor());
        let (fx, fz) = (u - i, v - j);
        let (i, j) = (i as i64, j as i64);
        let c00 = self.values.get(i, j);
        let c10 = self.values.get(i + 1, j);
        let c01 = self.values.get(i, j + 1);
        let c11 = self.values.get(i + 1, j + 1);
        let (gx, gz) = if fx >= fz { (c10 - c00, c11 - c10) } else { (c11 - c01, c01 - c00) };
        let h = c00 + gx * fx + gz * fz;
        (h as f32, (gx * gx + gz * gz) / (self.spacing * self.spacing))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fractal(rows: &[Vec<f32>]) -> Fractal {
        Fractal::new(7, [-4096.0, -4096.0], 4096.0, 10, 2.2, 300.0, rows).expect("valid")
    }

    #[test]
    fn a_point_equals_the_patch_around_it_bit_for_bit() {
        let f = fractal(&[vec![100.0, 200.0, 50.0], vec![0.0, 400.0, 80.0], vec![10.0, 20.0, 30.0]]);
        let patch = f.patch([-500.0, 300.0], [700.0, 900.0], f.depth);
        for k in 0..200 {
            let x = -500.0 + f64::from(k) * 6.03;
            let z = 300.0 + f64::from(k) * 2.97;
            let (a, b) = (f.height_and_slope(x, z), patch.height_and_slope(x, z));
            assert_eq!((a.0.to_bits(), a.1.to_bits()), (b.0.to_bits(), b.1.to_bits()), "at ({x}, {z})");
        }
    }

    #[test]
    fn level_zero_points_are_the_control_heights_and_shared_lattice_points_agree_across_depths() {
        let rows = [vec![100.0, 200.0], vec![0.0, 400.0]];
        let f = fractal(&rows);
        assert_eq!(f.height(-4096.0, -4096.0), 100.0);
        assert_eq!(f.height(0.0, 0.0), 400.0);
        // Outside the control grid the edge values extend.
        assert_eq!(f.height(4096.0, -4096.0), 200.0);
        // A lattice point of depth 3 has the same height at every depth ≥ 3.
        let (x, z) = (-4096.0 + 3.0 * 512.0, -4096.0 + 5.0 * 512.0);
        let h3 = f.height_at_depth(x, z, 3);
        for d in 3..=f.depth {
            assert_eq!(f.height_at_depth(x, z, d).to_bits(), h3.to_bits(), "depth {d}");
        }
    }

    #[test]
    fn no_cracks_far_from_the_origin_and_the_relief_is_bounded() {
        let f = Fractal::new(99, [0.0, 0.0], 8192.0, 14, 2.3, 200.0, &[]).expect("valid");
        let far = 6.0e7;
        let s = f.spacing(f.depth);
        // The two triangles of a square agree on its diagonal and neighbouring squares on their edge.
        let x = far + 17.0 * s;
        let (a, _) = f.height_and_slope(x - 1e-9, far + 3.0 * s);
        let (b, _) = f.height_and_slope(x, far + 3.0 * s);
        assert!((a - b).abs() < 1e-3, "{a} vs {b}");
        let bound = 200.0 * 2.0 / (1.0 - libm::pow(2.0, -0.7)) + 1.0;
        for k in 0..500 {
            let h = f.height(f64::from(k) * 977.0 - 2.0e5, f64::from(k) * 331.0 + 1.0e6);
            assert!(f64::from(h).abs() < bound, "{h}");
        }
    }

    #[test]
    fn bad_numbers_are_refused() {
        assert!(matches!(Fractal::new(0, [0.0; 2], 4096.0, 21, 2.2, 1.0, &[]), Err(FractalError::Depth { .. })));
        assert!(matches!(Fractal::new(0, [0.0; 2], 1.0, 3, 2.2, 1.0, &[]), Err(FractalError::Depth { .. })));
        assert_eq!(Fractal::new(0, [0.0; 2], 4096.0, 8, 3.0, 1.0, &[]), Err(FractalError::Numbers));
        assert_eq!(Fractal::new(0, [0.0; 2], 4096.0, 8, 2.2, f32::NAN, &[]), Err(FractalError::Numbers));
        let ragged = [vec![1.0, 2.0], vec![3.0]];
        assert_eq!(Fractal::new(0, [0.0; 2], 4096.0, 8, 2.2, 1.0, &ragged), Err(FractalError::Corners(3)));
    }
}
