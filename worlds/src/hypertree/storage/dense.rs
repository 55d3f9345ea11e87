//! The dense 3D array (§5): a density and a level byte per voxel, laid out in bricks of 8³.

use super::super::Voxel;
use super::VoxelQuery;

/// The dense 3D array: per voxel one density byte and, beside it, one level byte. Cells are laid out in bricks of
/// 8³ voxels (x fastest inside a brick, bricks in x, y, z order), so the samples of a ray stay within a few cache
/// lines and pages instead of striding a whole slice per step along z.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct DenseArray {
    /// `[density, level]` per voxel, brick-major (density 0 is empty; the level is meaningless there).
    pub cells: Vec<[u8; 2]>,
    /// The volume's resolution.
    pub resolution: [u32; 3],
    /// Bricks along x and y.
    pub bricks: [u32; 2],
    /// Number of non-empty voxels.
    pub count: usize,
}

impl DenseArray {
    /// An empty array for a volume of `resolution`.
    pub fn new(resolution: [u32; 3]) -> DenseArray {
        let b = resolution.map(|r| r.div_ceil(8));
        let n = b.iter().map(|&x| x as usize).product::<usize>() * 512;
        DenseArray { cells: vec![[0u8; 2]; n], resolution, bricks: [b[0], b[1]], count: 0 }
    }

    /// The cell offset of voxel `v`.
    #[inline]
    pub fn offset(&self, v: [u32; 3]) -> usize {
        let brick = ((v[2] >> 3) * self.bricks[1] + (v[1] >> 3)) * self.bricks[0] + (v[0] >> 3);
        ((brick as usize) << 9) | (((v[2] & 7) << 6 | (v[1] & 7) << 3 | (v[0] & 7)) as usize)
    }

    /// Count one hit of voxel `v` (index `index`) at `level`: the shallowest level wins, and a voxel's first hit
    /// adds its index to `touched`.
    #[inline]
    pub(super) fn hit(&mut self, v: [u32; 3], index: u32, level: u8, touched: &mut Vec<u32>) {
        let o = self.offset(v);
        let c = &mut self.cells[o];
        if c[0] == 0 {
            touched.push(index);
            *c = [1, level];
        } else {
            c[0] = c[0].saturating_add(1);
            c[1] = c[1].min(level);
        }
    }

    /// The coordinates of voxel `index`.
    #[inline]
    pub(super) fn coords(&self, index: u32) -> [u32; 3] {
        let [rx, ry, _] = self.resolution;
        [index % rx, (index / rx) % ry, index / (rx * ry)]
    }
}

impl VoxelQuery for DenseArray {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        let [rx, ry, rz] = self.resolution;
        if u64::from(index) >= u64::from(rx) * u64::from(ry) * u64::from(rz) {
            return Voxel::EMPTY;
        }
        self.voxel_at(self.coords(index), index)
    }

    #[inline]
    fn voxel_at(&self, v: [u32; 3], _: u32) -> Voxel {
        match self.cells.get(self.offset(v)) {
            Some(&[d, l]) if d != 0 => Voxel { density: d, level: l },
            _ => Voxel::EMPTY,
        }
    }
}
