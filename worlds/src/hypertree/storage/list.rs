//! The validated voxel list every structure is built from, and the plain index list + density list of §5.

use super::super::Voxel;
use super::VoxelQuery;

/// Non-empty voxels sorted by index, without duplicates: the validated form every structure is built from.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct VoxelList {
    /// Voxel indices, strictly increasing.
    pub indices: Vec<u32>,
    /// Densities (non-zero), parallel to `indices`.
    pub densities: Vec<u8>,
    /// Levels, parallel to `indices`.
    pub levels: Vec<u8>,
}

impl VoxelList {
    /// Number of voxels.
    #[inline]
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    /// Whether the list is empty.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// Append a voxel (its index must exceed every index already present).
    #[inline]
    pub fn push(&mut self, index: u32, v: Voxel) {
        debug_assert!(self.indices.last().is_none_or(|&l| l < index));
        self.indices.push(index);
        self.densities.push(v.density);
        self.levels.push(v.level);
    }

    /// Position of `index` by bisection (§5).
    #[inline]
    pub fn position(&self, index: u32) -> Option<usize> {
        let ix = &self.indices;
        let mut lo = 0usize;
        let mut len = ix.len();
        if len == 0 {
            return None;
        }
        // Branch-light bisection: halve the window until one candidate remains.
        while len > 1 {
            let half = len / 2;
            if ix[lo + half] <= index {
                lo += half;
            }
            len -= half;
        }
        (ix[lo] == index).then_some(lo)
    }

    /// The voxel at position `k` of the list.
    #[inline]
    pub(super) fn at(&self, k: usize) -> Voxel {
        Voxel { density: self.densities[k], level: self.levels[k] }
    }

    /// Bytes of the three arrays.
    #[inline]
    pub(super) fn bytes(&self) -> usize {
        self.indices.len() * 4 + self.densities.len() + self.levels.len()
    }
}

impl VoxelQuery for VoxelList {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        match self.position(index) {
            Some(p) => self.at(p),
            None => Voxel::EMPTY,
        }
    }
}

/// The index list + density list structure (§5), looked up by bisection.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct IndexList {
    /// The voxels.
    pub list: VoxelList,
}

impl VoxelQuery for IndexList {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        self.list.voxel(index)
    }
}
