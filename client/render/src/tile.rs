//! Canopy tiles: a species' far-field volume (the same baked voxels the records' far band marches — its halved
//! resolution, which the far band draws at the sizes summaries are seen at — so colours match) repeated as a small
//! periodic stand of trees, seed 000 §10's hyperforest as one texture, which the summary patches of `forest.rs`
//! repeat over the ground (issue 15).
//!
//! A tile is [`TILE_TREES`] × [`TILE_TREES`] copies of the representative on a jittered grid of spacing
//! [`CROWN_SPACING`] crown widths (crowns overlap: a closed canopy at full density), each scaled by up to ±35 %,
//! wrapped around the tile's edges so that tiles join without seams. Trees are never turned or mirrored: the baked
//! shading has the sun on one side, as the far band shows it. Where crowns overlap their optical depths add and the
//! most lit colour shows (the far band draws each tree's outside over its neighbours'). Each tree belongs to one of
//! [`DENSITY_CLASSES`] classes (the 8 × 8 Bayer order over 8: every class spread over the tile), written into the
//! sign bits of the texel's colour channels, so that a patch keeps the first `k` classes to thin the stand to the
//! density its summary states.
//!
//! Opacity follows the reference's law: a voxel's `α` is the opacity of one step through it, so the source's
//! optical depth per metre, `−ln(1 − α) / Δs`, is what is resampled. The tile comes in [`TILE_MIPS`] resolutions,
//! each halving the last by fusing 2 × 2 × 2 voxels (mean optical depth; colours weighted by depth and by how much
//! of each voxel shows from above; the class of the densest), for patches whose pixels cover many voxels. Fusing
//! spreads a crown's depth over its gaps, so each coarser resolution is calibrated to the finest one's mean cover
//! seen from above and to the mean colour a far view sees of it.

use super::volume::{FarVolume, f16_bits, half_to_f32};

/// Trees per tile edge.
pub(crate) const TILE_TREES: u32 = 8;
/// Tree spacing on the tile's grid, in crown widths (crowns overlap as in a stand grown close).
pub(crate) const CROWN_SPACING: f32 = 0.4;
/// Resolutions of a tile (the first, then halved each time).
pub(crate) const TILE_MIPS: usize = 4;
/// Classes trees are thinned by (three sign bits).
pub(crate) const DENSITY_CLASSES: u32 = 8;
/// Height bands of a tile's [`CanopyProfile`].
pub(crate) const PROFILE_BANDS: usize = 16;
/// Smallest colour magnitude written (keeps the sign bit of every texel meaningful).
const MIN_COLOUR: f32 = 1.0 / 1024.0;
/// Largest source opacity resampled (an opaque voxel would have an infinite optical depth).
const MAX_ALPHA: f32 = 0.9999;
/// The 8 × 8 Bayer order, row-major: a tree's class is its entry over 8 (each class spread over the tile).
const BAYER8: [u8; 64] = [
    0, 32, 8, 40, 2, 34, 10, 42, 48, 16, 56, 24, 50, 18, 58, 26, 12, 44, 4, 36, 14, 46, 6, 38, 60, 28, 52, 20, 62, 30,
    54, 22, 3, 35, 11, 43, 1, 33, 9, 41, 51, 19, 59, 27, 49, 17, 57, 25, 15, 47, 7, 39, 13, 45, 5, 37, 63, 31, 55, 23,
    61, 29, 53, 21,
];

/// A species' canopy tile in its resolutions, each a [`FarVolume`] in tile metres (scale 1: the representative's
/// size), origin at the tile's corner on the ground.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct CanopyTile {
    /// Tile edge along x and z, metres at scale 1.
    pub period: f32,
    /// Height of the tile's box, metres at scale 1.
    pub top: f32,
    /// Trees per square metre at full density and scale 1.
    pub density: f32,
    /// The resolutions, finest first ([`TILE_MIPS`] of them).
    pub mips: Vec<FarVolume>,
    /// The stand as a layer of uniform medium, for pixels wider than a tree's spacing.
    pub profile: CanopyProfile,
}

/// A canopy tile seen from so far that a pixel covers more than one tree: a horizontally uniform layer whose
/// extinction and colour vary only with height (the tile's mean per height band), drawn without marching the
/// tile's voxels. The extinction is given per number of density classes kept, and scaled so that seen from
/// straight above the layer covers the ground as the tile's trees do (a uniform medium would close the gaps
/// between crowns); the colours are scaled so that the layer's mean far view is the tile's.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct CanopyProfile {
    /// Per band, bottom first: extinction per metre at scale 1 with the first `n + 1` classes kept.
    pub sigma: [[f32; DENSITY_CLASSES as usize]; PROFILE_BANDS],
    /// Per band: the colour the layer shows there.
    pub colour: [[f32; 3]; PROFILE_BANDS],
}

impl CanopyProfile {
    /// The profile as the shader reads it: per band, the eight extinctions, then the colour (three `vec4`s).
    pub(crate) fn gpu(&self) -> Vec<[f32; 4]> {
        let mut out = Vec::with_capacity(3 * PROFILE_BANDS);
        for b in 0..PROFILE_BANDS {
            let s = &self.sigma[b];
            let c = self.colour[b];
            out.extend([[s[0], s[1], s[2], s[3]], [s[4], s[5], s[6], s[7]], [c[0], c[1], c[2], 0.0]]);
        }
        out
    }

    /// Optical depth straight down through the layer, `∫σ dh` over the tile's height `top`, with the first
    /// `classes` classes kept (its cover from above is `1 − e^(−depth)`).
    pub(crate) fn depth(&self, classes: usize, top: f32) -> f32 {
        if classes == 0 {
            return 0.0;
        }
        self.sigma.iter().map(|s| s[classes - 1]).sum::<f32>() * (top / PROFILE_BANDS as f32)
    }

    /// The mean colour the layer shows, as [`Grid::mean_view`] looks (straight down and at 30° elevation), with
    /// every class kept.
    fn mean_view(&self, top: f32) -> [f32; 3] {
        let band = top / PROFILE_BANDS as f32;
        let (mut sum, mut weight) = ([0.0f32; 3], 0.0f32);
        for sin in [1.0f32, 0.5, 0.5, 0.5, 0.5] {
            let mut trans = 1.0f32;
            for b in (0..PROFILE_BANDS).rev() {
                let a = trans * (1.0 - (-self.sigma[b][DENSITY_CLASSES as usize - 1] * band / sin).exp());
                (0..3).for_each(|i| sum[i] += a * self.colour[b][i]);
                weight += a;
                trans -= a;
            }
        }
        sum.map(|v| v / weight.max(1e-9))
    }
}

/// Why a tile could not be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub(crate) enum TileError {
    /// The source volume has no extent or no voxels.
    #[error("the species' far volume is empty")]
    Empty,
    /// The resolution is out of range.
    #[error("tile resolution {0} (allowed 8..=256, a power of two)")]
    Resolution(u32),
}

/// One tree of the tile.
struct Tree {
    at: [f32; 2],
    scale: f32,
    class: u8,
}

fn luminance(c: [f32; 3]) -> f32 {
    0.3 * c[0] + 0.6 * c[1] + 0.1 * c[2]
}

/// A small deterministic hash to [0, 1) (splitmix64).
fn unit(k: u64) -> f32 {
    let mut z = k.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
}

/// The source as the tile samples it: species metres at scale 1 → the voxel's colour and optical depth per metre.
struct Source<'a> {
    v: &'a FarVolume,
    step: f32,
}

impl Source<'_> {
    fn sample(&self, p: [f32; 3]) -> Option<([f32; 3], f32)> {
        let v = self.v;
        let mut c = [0usize; 3];
        for i in 0..3 {
            let b = p[i] / v.units + v.origin[i];
            let k = (b / v.voxel_size[i]).floor();
            if !(k >= 0.0 && k < v.dims[i] as f32) {
                return None;
            }
            c[i] = k as usize;
        }
        let idx = c[0] + v.dims[0] as usize * (c[1] + v.dims[1] as usize * c[2]);
        let t = &v.texels[4 * idx..4 * idx + 4];
        let a = half_to_f32(t[3]).min(MAX_ALPHA);
        if a <= 0.0 {
            return None;
        }
        let rgb = [half_to_f32(t[0]), half_to_f32(t[1]), half_to_f32(t[2])];
        Some((rgb, -(1.0 - a).ln() / self.step))
    }
}

/// One resolution while it is built: per voxel the optical depth of one step, the colour, the class, and how much
/// of it shows from above.
struct Grid {
    dims: [u32; 3],
    voxel: [f32; 3],
    tau: Vec<f32>,
    rgb: Vec<[f32; 3]>,
    class: Vec<u8>,
    /// Transmittance from the top of the tile down to the voxel's centre (a crown's lit outside shows; its dark
    /// inside hardly does).
    vis: Vec<f32>,
}

impl Grid {
    fn new(dims: [u32; 3], voxel: [f32; 3]) -> Grid {
        let n = (dims[0] * dims[1] * dims[2]) as usize;
        Grid { dims, voxel, tau: vec![0.0; n], rgb: vec![[0.0; 3]; n], class: vec![0; n], vis: vec![1.0; n] }
    }

    fn index(&self, x: u32, y: u32, z: u32) -> usize {
        (x + self.dims[0] * (y + self.dims[1] * z)) as usize
    }

    /// Fill in `vis`: the transmittance from the top of each column down to each voxel's centre.
    fn see_from_above(&mut self) {
        let [dx, dy, dz] = self.dims;
        let per_voxel = self.voxel[1] / self.voxel[0].min(self.voxel[1]);
        for z in 0..dz {
            for x in 0..dx {
                let mut depth = 0.0;
                for y in (0..dy).rev() {
                    let i = self.index(x, y, z);
                    let t = self.tau[i] * per_voxel;
                    self.vis[i] = (-(depth + 0.5 * t)).exp();
                    depth += t;
                }
            }
        }
    }

    /// Half the resolution: 2 × 2 × 2 voxels fused (the step doubles, so the mean depth counts twice; colours
    /// weighted by depth and by how much of each shows from above, as a far ray sees the canopy's outside).
    fn halved(&self) -> Grid {
        let dims = self.dims.map(|d| d.div_ceil(2).max(1));
        let mut out = Grid::new(dims, [0, 1, 2].map(|i| self.voxel[i] * self.dims[i] as f32 / dims[i] as f32));
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let (mut tau, mut rgb, mut best, mut class) = (0.0f32, [0.0f32; 3], 0.0f32, 0u8);
                    let (mut weight, mut vis) = (0.0f32, 0.0f32);
                    for (dx, dy, dz) in (0..8u32).map(|k| (k & 1, k >> 1 & 1, k >> 2)) {
                        let (sx, sy, sz) = (2 * x + dx, 2 * y + dy, 2 * z + dz);
                        if sx >= self.dims[0] || sy >= self.dims[1] || sz >= self.dims[2] {
                            continue;
                        }
                        let i = self.index(sx, sy, sz);
                        let t = self.tau[i];
                        let w = t * (self.vis[i] + 1e-3);
                        tau += t;
                        weight += w;
                        vis += self.vis[i] / 8.0;
                        (0..3).for_each(|c| rgb[c] += w * self.rgb[i][c]);
                        if t > best {
                            (best, class) = (t, self.class[i]);
                        }
                    }
                    let o = out.index(x, y, z);
                    out.tau[o] = tau / 4.0;
                    out.rgb[o] = if weight > 0.0 { rgb.map(|c| c / weight) } else { [0.0; 3] };
                    out.class[o] = class;
                    out.vis[o] = vis;
                }
            }
        }
        out
    }

    /// Mean opacity of the vertical columns seen from above with every depth times `k` (a vertical ray takes
    /// `voxel.y / step` samples per voxel).
    fn cover_from_above(&self, k: f32) -> f32 {
        let [dx, dy, dz] = self.dims;
        let per_voxel = self.voxel[1] / self.voxel[0].min(self.voxel[1]);
        let mut sum = 0.0f64;
        for z in 0..dz {
            for x in 0..dx {
                let tau: f32 = (0..dy).map(|y| self.tau[self.index(x, y, z)]).sum();
                sum += f64::from(1.0 - (-k * per_voxel * tau).exp());
            }
        }
        (sum / f64::from(dx * dz)) as f32
    }

    /// Scale every depth so that the mean cover from above is `target`: fusing voxels spreads a crown's depth over
    /// its gaps, which would close the canopy at coarse resolutions (crowns are correlated up a column).
    fn calibrate(&mut self, target: f32) {
        let (mut lo, mut hi) = (0.0f32, 1.0f32);
        if self.cover_from_above(hi) <= target {
            return;
        }
        for _ in 0..24 {
            let mid = 0.5 * (lo + hi);
            if self.cover_from_above(mid) < target {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        self.tau.iter_mut().for_each(|t| *t *= 0.5 * (lo + hi));
    }

    /// The mean colour a far view sees of the tile (straight down, and at 30° elevation from four sides: rays
    /// from every column of the top, marched as the shader marches, front to back, wrapping around the tile),
    /// un-premultiplied.
    fn mean_view(&self) -> [f32; 3] {
        let [dx, dy, dz] = self.dims;
        let size = [0, 1, 2].map(|i| self.voxel[i] * self.dims[i] as f32);
        let step = self.voxel[0].min(self.voxel[1]);
        let (c30, s30) = (30f32.to_radians().cos(), 30f32.to_radians().sin());
        let dirs = [[0.0, -1.0, 0.0], [c30, -s30, 0.0], [-c30, -s30, 0.0], [0.0, -s30, c30], [0.0, -s30, -c30]];
        let (mut sum, mut weight) = ([0.0f64; 3], 0.0f64);
        for d in dirs {
            for z in 0..dz {
                for x in 0..dx {
                    let mut p = [(x as f32 + 0.5) * self.voxel[0], size[1], (z as f32 + 0.5) * self.voxel[2]];
                    let (mut c, mut a) = ([0.0f32; 3], 0.0f32);
                    while p[1] > 0.0 && a < 0.995 {
                        let v = |i: usize| {
                            let q = p[i] - size[i] * (p[i] / size[i]).floor();
                            ((q / self.voxel[i]) as u32).min(self.dims[i] - 1)
                        };
                        let k = self.index(v(0), ((p[1] / self.voxel[1]) as u32).min(dy - 1), v(2));
                        let w = (1.0 - a) * (1.0 - (-self.tau[k]).exp());
                        (0..3).for_each(|i| c[i] += w * self.rgb[k][i]);
                        a += w;
                        (0..3).for_each(|i| p[i] += d[i] * step);
                    }
                    (0..3).for_each(|i| sum[i] += f64::from(c[i]));
                    weight += f64::from(a);
                }
            }
        }
        sum.map(|v| (v / weight.max(1e-9)) as f32)
    }

    /// The stand as a uniform layer (see [`CanopyProfile`]): per height band, the mean extinction of the voxels
    /// of each class and below and the colour of what shows from above, calibrated to the grid's cover from above
    /// per classes kept and to its mean far view `colour`.
    fn profile(&self, top: f32, colour: [f32; 3]) -> CanopyProfile {
        const CLASSES: usize = DENSITY_CLASSES as usize;
        let [dx, dy, dz] = self.dims;
        let step = self.voxel[0].min(self.voxel[1]);
        let band_of =
            |y: u32| (((y as f32 + 0.5) * self.voxel[1] / top * PROFILE_BANDS as f32) as usize).min(PROFILE_BANDS - 1);
        let mut sigma = [[0.0f32; CLASSES]; PROFILE_BANDS];
        let (mut rgb, mut weight) = ([[0.0f32; 3]; PROFILE_BANDS], [0.0f32; PROFILE_BANDS]);
        // Per column and classes kept: the optical depth straight down, for the cover the layer is held to.
        let mut cover = [0.0f64; CLASSES];
        for z in 0..dz {
            for x in 0..dx {
                let mut column = [0.0f32; CLASSES];
                for y in 0..dy {
                    let i = self.index(x, y, z);
                    let t = self.tau[i];
                    if t <= 0.0 {
                        continue;
                    }
                    let b = band_of(y);
                    // Extinction per metre times the voxel's share of its band's volume.
                    let share = t / step * self.voxel[1] / (top / PROFILE_BANDS as f32) / (dx * dz) as f32;
                    let class = usize::from(self.class[i]).min(CLASSES - 1);
                    for n in class..CLASSES {
                        sigma[b][n] += share;
                        column[n] += t * self.voxel[1] / step;
                    }
                    let w = t * (self.vis[i] + 1e-3);
                    (0..3).for_each(|c| rgb[b][c] += w * self.rgb[i][c]);
                    weight[b] += w;
                }
                for n in 0..CLASSES {
                    cover[n] += f64::from(1.0 - (-column[n]).exp());
                }
            }
        }
        let colours: [[f32; 3]; PROFILE_BANDS] =
            std::array::from_fn(|b| if weight[b] > 0.0 { rgb[b].map(|c| c / weight[b]) } else { [0.0; 3] });
        let mut profile = CanopyProfile { sigma, colour: colours };
        for n in 0..CLASSES {
            let target = (cover[n] / f64::from(dx * dz)) as f32;
            let depth = profile.depth(n + 1, top);
            if depth > 0.0 {
                let want = -(1.0 - target.min(MAX_ALPHA)).ln();
                profile.sigma.iter_mut().for_each(|s| s[n] *= want / depth);
            }
        }
        let seen = profile.mean_view(top);
        let gain: [f32; 3] = std::array::from_fn(|i| (colour[i] / seen[i].max(1e-6)).clamp(0.5, 2.0));
        profile.colour.iter_mut().for_each(|c| *c = std::array::from_fn(|i| c[i] * gain[i]));
        profile
    }

    /// The baked volume: colour with the class in its sign bits, opacity `1 − e^(−τ)`.
    fn volume(&self) -> FarVolume {
        let mut texels = vec![0u16; 4 * self.tau.len()];
        let mut voxels = 0;
        for (i, t) in self.tau.iter().enumerate() {
            if *t <= 0.0 {
                continue;
            }
            voxels += 1;
            let c = self.class[i];
            let px = &mut texels[4 * i..4 * i + 4];
            for (k, (out, v)) in px.iter_mut().zip(self.rgb[i]).enumerate() {
                let m = v.max(MIN_COLOUR);
                *out = f16_bits(if c >> k & 1 == 1 { -m } else { m });
            }
            px[3] = f16_bits(1.0 - (-t).exp());
        }
        FarVolume {
            dims: self.dims,
            voxel_size: self.voxel,
            aabb_min: [0.0; 3],
            aabb_max: [0, 1, 2].map(|i| self.voxel[i] * self.dims[i] as f32),
            origin: [0.0; 3],
            units: 1.0,
            texels,
            voxels,
        }
    }
}

/// The density class of a tile texel (its colour's sign bits) and its colour.
#[cfg(test)]
pub(crate) fn texel_class(t: &[u16]) -> (u32, [f32; 3]) {
    let class = (0..3).map(|k| u32::from(t[k] >> 15) << k).sum();
    (class, [0, 1, 2].map(|k| half_to_f32(t[k] & 0x7fff)))
}

/// Bake a species' canopy tile from its far volume, `resolution` voxels along x and z (a power of two: the
/// atlas slot's edge), half as many up.
pub(crate) fn bake_tile(v: &FarVolume, resolution: u32) -> Result<CanopyTile, TileError> {
    if !(8..=256).contains(&resolution) || !resolution.is_power_of_two() {
        return Err(TileError::Resolution(resolution));
    }
    let ext = |i: usize| (v.aabb_max[i] - v.aabb_min[i]) * v.units;
    let crown = 0.5 * (ext(0) + ext(2));
    let height = (v.aabb_max[1] - v.origin[1]) * v.units;
    if v.voxels == 0 || !(crown > 0.0 && height > 0.0) {
        return Err(TileError::Empty);
    }
    // How far a crown reaches from its trunk.
    let reach = [0, 2].map(|i| (v.origin[i] - v.aabb_min[i]).max(v.aabb_max[i] - v.origin[i]) * v.units);
    let reach = reach[0].max(reach[1]);
    let spacing = CROWN_SPACING * crown;
    let period = spacing * TILE_TREES as f32;
    let trees: Vec<Tree> = (0..TILE_TREES * TILE_TREES)
        .map(|k| {
            let (i, j) = ((k % TILE_TREES) as f32, (k / TILE_TREES) as f32);
            let h = |salt: u64| unit(u64::from(k) * 8 + salt);
            Tree {
                at: [(i + 0.5 + 0.6 * (h(0) - 0.5)) * spacing, (j + 0.5 + 0.6 * (h(1) - 0.5)) * spacing],
                scale: 0.65 + 0.7 * h(2),
                class: BAYER8[k as usize % BAYER8.len()] / 8,
            }
        })
        .collect();
    let top = height * 1.35;
    let (rh, rv) = (resolution, resolution / 2);
    let voxel = [period / rh as f32, top / rv as f32, period / rh as f32];
    let step = voxel[0].min(voxel[1]);
    let src = Source { v, step: v.voxel_size.iter().copied().fold(f32::INFINITY, f32::min) * v.units };
    let mut grid = Grid::new([rh, rv, rh], voxel);
    let wrap = |d: f32| d - period * (d / period).round();
    // The trees whose crowns reach a column of voxels, with their offsets from it: the same all the way up.
    let mut reaching: Vec<(f32, f32, &Tree)> = Vec::with_capacity(trees.len());
    for z in 0..rh {
        for x in 0..rh {
            let (px, pz) = ((x as f32 + 0.5) * voxel[0], (z as f32 + 0.5) * voxel[2]);
            reaching.clear();
            reaching.extend(trees.iter().filter_map(|t| {
                let (dx, dz) = (wrap(px - t.at[0]), wrap(pz - t.at[1]));
                (dx.abs().max(dz.abs()) <= reach * t.scale + voxel[0]).then_some((dx, dz, t))
            }));
            for y in 0..rv {
                let py = (y as f32 + 0.5) * voxel[1];
                let (mut tau, mut rgb, mut best, mut class) = (0.0f32, [0.0f32; 3], 0.0f32, 0u8);
                for &(dx, dz, t) in &reaching {
                    // Never turned or mirrored: the baked shading has the sun on one side.
                    let Some((c, per_metre)) = src.sample([dx / t.scale, py / t.scale, dz / t.scale]) else {
                        continue;
                    };
                    // Optical depth of one tile step through this tree, scaled by `scale`.
                    let d = per_metre * step / t.scale;
                    tau += d;
                    // Where crowns overlap, the one lit most shows (the far band draws each tree's outside over
                    // its neighbours', not a neighbour's dark inside mixed in).
                    if luminance(c) >= luminance(rgb) {
                        rgb = c;
                    }
                    if d > best {
                        (best, class) = (d, t.class);
                    }
                }
                let i = grid.index(x, y, z);
                grid.tau[i] = tau;
                grid.rgb[i] = rgb;
                grid.class[i] = class;
            }
        }
    }
    grid.see_from_above();
    let mut mips = vec![grid.volume()];
    let target = grid.cover_from_above(1.0);
    let colour = grid.mean_view();
    let profile = grid.profile(top, colour);
    for _ in 1..TILE_MIPS {
        grid = grid.halved();
        let mut calibrated = Grid {
            tau: grid.tau.clone(),
            rgb: grid.rgb.clone(),
            class: grid.class.clone(),
            vis: grid.vis.clone(),
            ..grid
        };
        calibrated.calibrate(target);
        // Fused colours lean toward a crown's shaded inside: keep what a far view sees on average.
        let seen = calibrated.mean_view();
        let gain: [f32; 3] = std::array::from_fn(|i| (colour[i] / seen[i].max(1e-6)).clamp(0.5, 2.0));
        calibrated.rgb.iter_mut().for_each(|c| *c = std::array::from_fn(|i| c[i] * gain[i]));
        mips.push(calibrated.volume());
    }
    let density = (TILE_TREES * TILE_TREES) as f32 / (period * period);
    Ok(CanopyTile { period, top, density, mips, profile })
}

#[cfg(test)]
mod tests {
    use canopy_worlds::amplify::Budget;
    use canopy_worlds::library;

    use super::*;
    use crate::Lighting;
    use crate::volume::species_volumes;

    fn conifer_tile(resolution: u32) -> (FarVolume, CanopyTile) {
        let g = library::find("conifer").unwrap().load().unwrap();
        let v = species_volumes(&g, 40, &Budget::default(), &Lighting::default()).unwrap();
        let t = bake_tile(&v.full, resolution).unwrap();
        (v.full, t)
    }

    /// Mean opacity of vertical columns, seen from above (a sample per step), keeping the first `keep_classes`
    /// classes.
    fn cover(v: &FarVolume, keep_classes: u32) -> f32 {
        let [dx, dy, dz] = v.dims;
        let per_voxel = v.voxel_size[1] / v.voxel_size[0].min(v.voxel_size[1]);
        let mut covered = 0.0;
        for z in 0..dz {
            for x in 0..dx {
                let mut trans = 1.0f32;
                for y in 0..dy {
                    let i = (x + dx * (y + dy * z)) as usize;
                    let t = &v.texels[4 * i..4 * i + 4];
                    if texel_class(t).0 < keep_classes {
                        trans *= (1.0 - half_to_f32(t[3])).powf(per_voxel);
                    }
                }
                covered += 1.0 - trans;
            }
        }
        covered / (dx * dz) as f32
    }

    #[test]
    fn a_tile_is_a_closed_canopy_that_thins_by_class_and_keeps_the_species_colour() {
        let (src, tile) = conifer_tile(32);
        assert_eq!(tile.mips.len(), TILE_MIPS);
        assert_eq!(tile.mips[0].dims, [32, 16, 32]);
        assert_eq!(tile.mips[3].dims, [4, 2, 4]);
        for m in &tile.mips {
            assert!((m.aabb_max[0] - tile.period).abs() < 1e-3 && (m.aabb_max[1] - tile.top).abs() < 1e-3);
        }
        let full = cover(&tile.mips[0], DENSITY_CLASSES);
        let thinned: Vec<f32> = (0..=DENSITY_CLASSES).map(|k| cover(&tile.mips[0], k)).collect();
        eprintln!("cover from above keeping 0..=8 classes: {thinned:?}");
        // Crowns as open as the trees they stand for (issue 35.3): about 0.82 of the ground hidden from above.
        assert!(full > 0.75, "a closed canopy from above: {full}");
        assert!(thinned.windows(2).all(|w| w[0] < w[1]), "each class kept adds cover: {thinned:?}");
        assert!(thinned[1] < 0.4 * full, "an eighth of the trees leaves most ground open: {thinned:?}");
        assert_eq!(thinned[0], 0.0);
        // Every class is used, and the mean colour is the source's (the same baked shading).
        let mean = |v: &FarVolume| {
            let (mut s, mut n) = ([0.0f64; 3], 0.0f64);
            let mut classes = [0u32; DENSITY_CLASSES as usize];
            for t in v.texels.chunks_exact(4).filter(|t| half_to_f32(t[3]) > 0.0) {
                let (c, rgb) = texel_class(t);
                classes[c as usize] += 1;
                (0..3).for_each(|k| s[k] += f64::from(rgb[k]));
                n += 1.0;
            }
            (s.map(|v| v / n), classes)
        };
        let (tile_rgb, classes) = mean(&tile.mips[0]);
        let (src_rgb, _) = mean(&src);
        assert!(classes.iter().all(|&c| c > 0), "{classes:?}");
        for k in 0..3 {
            assert!((tile_rgb[k] - src_rgb[k]).abs() < 0.05, "{tile_rgb:?} against {src_rgb:?}");
        }
        // Coarser resolutions keep the cover seen from above (optical depth is conserved).
        let coarse = cover(&tile.mips[2], DENSITY_CLASSES);
        assert!((coarse - full).abs() < 0.25, "{coarse} against {full}");
    }

    #[test]
    fn the_profile_covers_the_ground_as_the_trees_do() {
        let (_, tile) = conifer_tile(32);
        let p = &tile.profile;
        for k in 1..=DENSITY_CLASSES {
            let (layer, trees) = (1.0 - (-p.depth(k as usize, tile.top)).exp(), cover(&tile.mips[0], k));
            assert!((layer - trees).abs() < 0.02, "{k} classes: the layer covers {layer}, the trees {trees}");
        }
        // Extinction grows with every class kept, in every band; the crowns' band holds the most.
        for s in &p.sigma {
            assert!(s.windows(2).all(|w| w[0] <= w[1]), "{s:?}");
        }
        let depth = |b: usize| p.sigma[b][DENSITY_CLASSES as usize - 1];
        let densest = (0..PROFILE_BANDS).max_by(|&a, &b| depth(a).total_cmp(&depth(b))).unwrap();
        assert!(depth(densest) > 0.0 && depth(PROFILE_BANDS - 1) < depth(densest), "{:?}", p.sigma);
        // Colours are the tile's: green above all.
        let seen = p.mean_view(tile.top);
        assert!(seen[1] > seen[0] && seen[1] > seen[2] && seen[1] > 0.02, "{seen:?}");
        assert_eq!(p.gpu().len(), 3 * PROFILE_BANDS);
    }

    #[test]
    fn tiles_repeat_without_seams() {
        let (_, tile) = conifer_tile(32);
        let v = &tile.mips[0];
        // Opacity summed over each x = const plane: crowns reach across the tile's edges from the other side, so
        // the planes at the edges are as full as the others (without wrapping they would hold half the crowns).
        let [dx, dy, dz] = v.dims;
        let plane = |x: u32| -> f32 {
            let mut s = 0.0;
            for z in 0..dz {
                for y in 0..dy {
                    s += half_to_f32(v.texels[4 * (x + dx * (y + dy * z)) as usize + 3]);
                }
            }
            s
        };
        let planes: Vec<f32> = (0..dx).map(plane).collect();
        let mean = planes.iter().sum::<f32>() / dx as f32;
        eprintln!("{planes:?}");
        assert!(planes[0] > 0.75 * mean && planes[dx as usize - 1] > 0.75 * mean, "{planes:?}");
        assert!(bake_tile(v, 12).is_err());
    }
}
