//! The index list plus a bit array of non-empty voxels (§5), with a rank directory instead of bisection.

use super::super::Voxel;
use super::{VoxelList, VoxelQuery};

/// Words of the bit array per rank-directory entry.
const RANK_WORDS: usize = 8;

/// The index list plus a bit array of non-empty voxels between the lowest and highest index (§5). An empty voxel is
/// answered from the bit array alone; a non-empty one by its rank in the bit array (a popcount directory every 512
/// bits), which gives its position in the lists without bisection.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct IndexBits {
    /// The voxels.
    pub list: VoxelList,
    /// Lowest non-empty index (bit 0).
    pub lo: u32,
    /// Bit `i` is set if voxel `lo + i` is not empty.
    pub bits: Vec<u64>,
    /// Set bits before each group of [`RANK_WORDS`] words.
    pub rank: Vec<u32>,
}

impl IndexBits {
    /// Build from a validated list.
    pub fn new(list: VoxelList) -> IndexBits {
        let (lo, hi) = match (list.indices.first(), list.indices.last()) {
            (Some(&a), Some(&b)) => (a, b),
            _ => return IndexBits { list, lo: 0, bits: Vec::new(), rank: Vec::new() },
        };
        let span = (hi - lo) as usize + 1;
        let mut bits = vec![0u64; span.div_ceil(64)];
        for &i in &list.indices {
            let o = (i - lo) as usize;
            bits[o >> 6] |= 1 << (o & 63);
        }
        let mut rank = Vec::with_capacity(bits.len().div_ceil(RANK_WORDS));
        let mut acc = 0u32;
        for chunk in bits.chunks(RANK_WORDS) {
            rank.push(acc);
            acc += chunk.iter().map(|w| w.count_ones()).sum::<u32>();
        }
        IndexBits { list, lo, bits, rank }
    }

    /// Whether voxel `index` is non-empty (the bit array alone).
    #[inline]
    pub fn occupied(&self, index: u32) -> bool {
        let Some(o) = index.checked_sub(self.lo) else { return false };
        let o = o as usize;
        self.bits.get(o >> 6).is_some_and(|w| w >> (o & 63) & 1 == 1)
    }
}

impl VoxelQuery for IndexBits {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        let Some(o) = index.checked_sub(self.lo) else { return Voxel::EMPTY };
        let o = o as usize;
        let w = o >> 6;
        let Some(&word) = self.bits.get(w) else { return Voxel::EMPTY };
        let bit = o & 63;
        if word >> bit & 1 == 0 {
            return Voxel::EMPTY;
        }
        let group = w / RANK_WORDS;
        let mut pos = self.rank[group] as usize;
        for &x in &self.bits[group * RANK_WORDS..w] {
            pos += x.count_ones() as usize;
        }
        pos += (word & ((1u64 << bit) - 1)).count_ones() as usize;
        Voxel { density: self.list.densities[pos], level: self.list.levels[pos] }
    }
}
