//! The reference renderer's view of which voxels are non-empty: a bit mask per occupied brick of 8³ voxels with
//! the rank of each non-empty voxel (the index of its shading memo), and each brick's Chebyshev distance to the
//! nearest occupied brick (how many samples a ray may skip).

use crate::hypertree::Hypertree;
use crate::hypertree::storage::{BRICK_SHIFT, BrickMap, VoxelStore};

/// Which voxels of the occupied bricks are non-empty: per brick a slot (or [`VoxelMask::NONE`]) into 512-bit
/// masks, bit `z << 6 | y << 3 | x` of the brick-local coordinates, and the number of non-empty voxels before
/// each slot, so a non-empty voxel has a rank: the index of its shading memo, which keeps the memo of one brick
/// together. Built once per render from the store; an empty voxel inside an occupied brick is answered without
/// querying the storage structure (the same answer, so the image is unchanged).
pub(super) struct VoxelMask {
    pub(super) slots: Vec<u32>,
    masks: Vec<[u64; 8]>,
    ranks: Vec<u32>,
    dims: [usize; 2],
}

impl VoxelMask {
    /// No voxels and not marked in the occupancy map.
    const NONE: u32 = u32::MAX;
    /// Flag of a slot entry: the occupancy map does not mark the brick (rays skip it when skipping is on).
    pub(super) const UNMARKED: u32 = 1 << 31;

    /// With `skip`, only the bricks the occupancy map marks are read from a dense array (projection and shadow
    /// rays never sample the others then).
    pub(super) fn build(tree: &Hypertree, skip: bool) -> VoxelMask {
        let dims = tree.volume.resolution.map(|r| r.div_ceil(1 << BRICK_SHIFT) as usize);
        let mut m = VoxelMask {
            slots: vec![Self::NONE; dims[0] * dims[1] * dims[2]],
            masks: Vec::new(),
            ranks: Vec::new(),
            dims: [dims[0], dims[1]],
        };
        match &tree.store {
            VoxelStore::Dense(d) => {
                // Bricks of the dense array are laid out in the same brick order, 512 cells each.
                let occ = &tree.occupancy;
                for (b, cells) in d.cells.chunks_exact(512).enumerate() {
                    if skip && occ.bits[b >> 6] >> (b & 63) & 1 == 0 {
                        continue;
                    }
                    let mut words = [0u64; 8];
                    for (w, word) in words.iter_mut().enumerate() {
                        for (k, c) in cells[w * 64..w * 64 + 64].iter().enumerate() {
                            *word |= u64::from(c[0] != 0) << k;
                        }
                    }
                    if words.iter().any(|&w| w != 0) {
                        m.slots[b] = m.masks.len() as u32;
                        m.masks.push(words);
                    }
                }
            }
            _ => {
                let [rx, ry, _] = tree.volume.resolution;
                let (mut row, mut y, mut z) = (u32::MAX, 0u32, 0u32);
                tree.store.for_each(|i, _| {
                    let r = i / rx;
                    if r != row {
                        row = r;
                        y = r % ry;
                        z = r / ry;
                    }
                    m.set([i - r * rx, y, z]);
                });
            }
        }
        // Fold the occupancy map in, so one load per sample answers both "skip this brick?" and "where is its mask?":
        // a marked brick without voxels gets an empty mask, an unmarked one with voxels the flag.
        let occ = &tree.occupancy;
        for b in 0..m.slots.len() {
            let marked = occ.bits[b >> 6] >> (b & 63) & 1 == 1;
            if marked && m.slots[b] == Self::NONE {
                m.slots[b] = m.masks.len() as u32;
                m.masks.push([0; 8]);
            } else if !marked && m.slots[b] != Self::NONE {
                m.slots[b] |= Self::UNMARKED;
            }
        }
        let mut acc = 0u32;
        m.ranks = m
            .masks
            .iter()
            .map(|w| {
                let r = acc;
                acc += w.iter().map(|x| x.count_ones()).sum::<u32>();
                r
            })
            .collect();
        m
    }

    fn set(&mut self, v: [u32; 3]) {
        let b = self.brick(v);
        if self.slots[b] == Self::NONE {
            self.slots[b] = self.masks.len() as u32;
            self.masks.push([0; 8]);
        }
        let bit = Self::bit(v);
        self.masks[self.slots[b] as usize][bit >> 6] |= 1 << (bit & 63);
    }

    /// Non-empty voxels.
    pub(super) fn count(&self) -> usize {
        match (self.ranks.last(), self.masks.last()) {
            (Some(&r), Some(w)) => r as usize + w.iter().map(|x| x.count_ones() as usize).sum::<usize>(),
            _ => 0,
        }
    }

    #[inline]
    pub(super) fn brick(&self, v: [u32; 3]) -> usize {
        let [bx, by, bz] = v.map(|c| (c >> BRICK_SHIFT) as usize);
        bx + self.dims[0] * (by + self.dims[1] * bz)
    }

    #[inline]
    fn bit(v: [u32; 3]) -> usize {
        ((v[2] & 7) << 6 | (v[1] & 7) << 3 | (v[0] & 7)) as usize
    }

    /// The rank of voxel `v` (inside the volume) if it is non-empty, given its brick's slot entry.
    #[inline]
    pub(super) fn rank_in(&self, s: u32, v: [u32; 3]) -> Option<u32> {
        if s == Self::NONE {
            return None;
        }
        let s = s & !Self::UNMARKED;
        let bit = Self::bit(v);
        let words = &self.masks[s as usize];
        let w = bit >> 6;
        let word = words[w];
        if word >> (bit & 63) & 1 == 0 {
            return None;
        }
        let mut r = self.ranks[s as usize] + (word & ((1u64 << (bit & 63)) - 1)).count_ones();
        for x in &words[..w] {
            r += x.count_ones();
        }
        Some(r)
    }
}

/// Chebyshev distance transform of the occupied bricks (occupancy map or voxel mask), separable for L∞:
/// `d(b) = min_z max(|Δz|, min_y max(|Δy|, min_x |Δx|))`. Capped at 255; 0 for an occupied brick.
pub(super) fn brick_distances(occupancy: &BrickMap, mask: &VoxelMask) -> Vec<u8> {
    let [nx, ny, nz] = occupancy.dims.map(|d| d as usize);
    let at = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
    const FAR: u32 = 255;
    let mut d = vec![FAR; nx * ny * nz];
    for (b, v) in d.iter_mut().enumerate() {
        if occupancy.bits[b >> 6] >> (b & 63) & 1 == 1 || mask.slots[b] != VoxelMask::NONE {
            *v = 0;
        }
    }
    // One axis at a time: along a line, the new distance is the least of max(|i − j|, old(j)).
    let mut line = Vec::new();
    let mut pass = |d: &mut Vec<u32>, len: usize, lines: Vec<Vec<usize>>| {
        for cells in lines {
            line.clear();
            line.extend(cells.iter().map(|&c| d[c]));
            for i in 0..len {
                let mut best = FAR;
                for (j, &old) in line.iter().enumerate() {
                    best = best.min((i.abs_diff(j) as u32).max(old));
                }
                d[cells[i]] = best;
            }
        }
    };
    pass(&mut d, nx, (0..ny * nz).map(|yz| (0..nx).map(|x| at(x, yz % ny, yz / ny)).collect()).collect());
    pass(&mut d, ny, (0..nx * nz).map(|xz| (0..ny).map(|y| at(xz % nx, y, xz / nx)).collect()).collect());
    pass(&mut d, nz, (0..nx * ny).map(|xy| (0..nz).map(|z| at(xy % nx, xy / nx, z)).collect()).collect());
    d.into_iter().map(|v| v.min(255) as u8).collect()
}
