//! The packed index list (§5): per voxel one byte of its index and a palette code, about 2–3 bytes a voxel.

use super::super::Voxel;
use super::{VoxelList, VoxelQuery};

/// Indices per block of a [`PackedList`] (one byte of an index is stored per voxel).
const PACK_BLOCK: usize = 256;
/// Blocks per super-block of a [`PackedList`] (block offsets are 16-bit inside a super-block).
const PACK_SUPER: usize = 256;

/// The index list + density list structure (§5), packed: per voxel the low byte of its index (relative to the
/// lowest index) and a one-byte code into a palette of the (density, level) pairs that occur (two bytes when more
/// than 256 occur); the rest of the index comes from its block of 256 indices, whose first entry is a 16-bit
/// offset from its super-block's (65 536 indices) 32-bit first entry. A lookup reads two table entries and scans
/// the few entries of one block. About 2–3 bytes a voxel instead of 6; the same voxels as the list it is built from.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PackedList {
    /// Lowest index.
    lo: u32,
    /// First entry of each super-block, and the entry count after the last.
    supers: Vec<u32>,
    /// First entry of each block, from its super-block's first entry; one more block than the span needs.
    blocks: Vec<u16>,
    /// `(index − lo) mod 256` per voxel.
    low: Vec<u8>,
    /// Palette codes per voxel.
    codes: Codes,
    /// The distinct (density, level) pairs, sorted.
    palette: Vec<Voxel>,
}

#[derive(Clone, Debug, PartialEq, Eq)]
enum Codes {
    Narrow(Vec<u8>),
    Wide(Vec<u16>),
}

impl Default for Codes {
    fn default() -> Self {
        Codes::Narrow(Vec::new())
    }
}

impl PackedList {
    /// Pack a validated list.
    pub fn new(list: &VoxelList) -> PackedList {
        let (Some(&lo), Some(&hi)) = (list.indices.first(), list.indices.last()) else {
            return PackedList { supers: vec![0], blocks: vec![0], ..PackedList::default() };
        };
        let nblocks = ((hi - lo) as usize + 1).div_ceil(PACK_BLOCK) + 1;
        let mut supers = vec![0u32; nblocks.div_ceil(PACK_SUPER) + 1];
        let mut blocks = vec![0u16; nblocks];
        // Entries per block, then prefix sums (per super-block for the blocks).
        let mut counts = vec![0u32; nblocks];
        for &i in &list.indices {
            counts[(i - lo) as usize / PACK_BLOCK] += 1;
        }
        let mut total = 0u32;
        for (s, chunk) in counts.chunks(PACK_SUPER).enumerate() {
            supers[s] = total;
            let mut within = 0u32;
            for (k, &c) in chunk.iter().enumerate() {
                blocks[s * PACK_SUPER + k] = within as u16;
                within += c;
            }
            total += within;
        }
        for s in supers.iter_mut().skip(nblocks.div_ceil(PACK_SUPER)) {
            *s = total;
        }
        let low = list.indices.iter().map(|&i| (i - lo) as u8).collect();
        let mut seen = vec![false; 1 << 16];
        for k in 0..list.len() {
            seen[usize::from(list.densities[k]) << 8 | usize::from(list.levels[k])] = true;
        }
        let palette: Vec<Voxel> =
            (0..1usize << 16).filter(|&p| seen[p]).map(|p| Voxel { density: (p >> 8) as u8, level: p as u8 }).collect();
        let mut code_of = vec![0u16; 1 << 16];
        for (c, v) in palette.iter().enumerate() {
            code_of[usize::from(v.density) << 8 | usize::from(v.level)] = c as u16;
        }
        let code = |k: usize| code_of[usize::from(list.densities[k]) << 8 | usize::from(list.levels[k])];
        let codes = if palette.len() <= 256 {
            Codes::Narrow((0..list.len()).map(|k| code(k) as u8).collect())
        } else {
            Codes::Wide((0..list.len()).map(code).collect())
        };
        PackedList { lo, supers, blocks, low, codes, palette }
    }

    /// Number of voxels.
    #[inline]
    pub fn len(&self) -> usize {
        self.low.len()
    }

    /// Whether the list is empty.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.low.is_empty()
    }

    /// The first entry of block `b` (`b` up to the block count).
    #[inline]
    fn start(&self, b: usize) -> usize {
        self.supers[b / PACK_SUPER] as usize + usize::from(self.blocks[b])
    }

    #[inline]
    fn at(&self, pos: usize) -> Voxel {
        match &self.codes {
            Codes::Narrow(c) => self.palette[usize::from(c[pos])],
            Codes::Wide(c) => self.palette[usize::from(c[pos])],
        }
    }

    /// Position of `index` in the list.
    #[inline]
    pub fn position(&self, index: u32) -> Option<usize> {
        let o = index.checked_sub(self.lo)? as usize;
        let b = o / PACK_BLOCK;
        if b + 1 >= self.blocks.len() {
            return None;
        }
        let (start, end) = (self.start(b), self.start(b + 1));
        let want = o as u8;
        self.low[start..end].iter().position(|&l| l >= want).filter(|&k| self.low[start + k] == want).map(|k| start + k)
    }

    /// Visit every voxel in increasing index order.
    pub fn for_each(&self, mut f: impl FnMut(u32, Voxel)) {
        for b in 0..self.blocks.len() - 1 {
            let base = self.lo + (b * PACK_BLOCK) as u32;
            for pos in self.start(b)..self.start(b + 1) {
                f(base + u32::from(self.low[pos]), self.at(pos));
            }
        }
    }

    /// The voxels as a validated list.
    pub fn to_list(&self) -> VoxelList {
        let mut out = VoxelList::default();
        self.for_each(|i, v| out.push(i, v));
        out
    }

    /// Bytes of the payload: low bytes, codes, palette and the two block tables.
    pub fn bytes(&self) -> usize {
        let codes = match &self.codes {
            Codes::Narrow(c) => c.len(),
            Codes::Wide(c) => c.len() * 2,
        };
        self.low.len() + codes + self.palette.len() * 2 + self.supers.len() * 4 + self.blocks.len() * 2
    }
}

impl VoxelQuery for PackedList {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        match self.position(index) {
            Some(p) => self.at(p),
            None => Voxel::EMPTY,
        }
    }
}
