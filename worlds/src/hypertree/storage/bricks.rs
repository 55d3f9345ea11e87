//! Bricks of 8³ voxels: the occupancy brick map for empty-space skipping, and the brick grid that counts the hits
//! of coherent generators without a sort.

use super::super::{Hypervolume, VoxelBox};
use super::validate::Compact;
use super::{IndexBits, VoxelList, VoxelStore};

/// Bricks of 8³ voxels, one bit each: set if any voxel of the brick is non-empty.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct BrickMap {
    /// Bricks along x, y, z.
    pub dims: [u32; 3],
    /// One bit per brick, brick index `bx + dims_x · (by + dims_y · bz)`.
    pub bits: Vec<u64>,
}

/// log2 of the brick side, in voxels.
pub const BRICK_SHIFT: u32 = 3;

impl BrickMap {
    /// The brick map and the voxel box of a store.
    pub fn build(volume: &Hypervolume, store: &VoxelStore) -> (BrickMap, Option<VoxelBox>) {
        match store {
            VoxelStore::IndexBits(IndexBits { list, .. }) => {
                BrickMap::from_indices(volume, list.indices.iter().copied())
            }
            _ => {
                let mut all = Vec::with_capacity(store.len());
                store.for_each(|i, _| all.push(i));
                BrickMap::from_indices(volume, all.into_iter())
            }
        }
    }

    /// The brick map and voxel box of the non-empty voxels `indices` (any order).
    pub fn from_indices(volume: &Hypervolume, indices: impl Iterator<Item = u32>) -> (BrickMap, Option<VoxelBox>) {
        let dims = volume.resolution.map(|r| r.div_ceil(1 << BRICK_SHIFT));
        let n = dims.iter().map(|&d| d as usize).product::<usize>();
        let mut map = BrickMap { dims, bits: vec![0u64; n.div_ceil(64)] };
        let mut lo = [u32::MAX; 3];
        let mut hi = [0u32; 3];
        let mut any = false;
        for i in indices {
            let v = volume.coords(i);
            any = true;
            for a in 0..3 {
                lo[a] = lo[a].min(v[a]);
                hi[a] = hi[a].max(v[a]);
            }
            let b = map.brick_index(v);
            map.bits[b >> 6] |= 1 << (b & 63);
        }
        (map, any.then_some((lo, hi)))
    }

    /// The brick index holding voxel `v`.
    #[inline]
    pub fn brick_index(&self, v: [u32; 3]) -> usize {
        let [bx, by, bz] = v.map(|c| (c >> BRICK_SHIFT) as usize);
        bx + self.dims[0] as usize * (by + self.dims[1] as usize * bz)
    }

    /// Whether the brick holding voxel `v` has anything in it.
    #[inline]
    pub fn occupied(&self, v: [u32; 3]) -> bool {
        let b = self.brick_index(v);
        self.bits[b >> 6] >> (b & 63) & 1 == 1
    }

    /// Bytes of the bit array.
    pub fn memory_bytes(&self) -> usize {
        self.bits.len() * 8
    }
}

/// Hit counts (saturating at 255) and shallowest levels of subpart 0, in bricks of 8³ voxels allocated on first
/// touch: the same counts as sorting the raw hits, without the sort.
pub struct BrickGrid {
    resolution: [u32; 3],
    dims: [u32; 3],
    /// Per brick (`bx + dims_x · (by + dims_y · bz)`), its slot or `u32::MAX`.
    slots: Vec<u32>,
    /// `[hits, level]`, 512 per slot, `z << 6 | y << 3 | x` inside the brick (level 255 where not hit).
    cells: Vec<[u8; 2]>,
    /// The brick of each slot.
    bricks: Vec<u32>,
}

impl BrickGrid {
    /// An empty grid for a volume of `resolution`.
    pub(super) fn new(resolution: [u32; 3]) -> BrickGrid {
        let dims = resolution.map(|r| r.div_ceil(1 << BRICK_SHIFT));
        let n = dims.iter().map(|&d| d as usize).product::<usize>();
        BrickGrid { resolution, dims, slots: vec![u32::MAX; n], cells: Vec::new(), bricks: Vec::new() }
    }

    /// The coordinates of voxel `index`.
    #[inline]
    pub(super) fn coords(&self, index: u32) -> [u32; 3] {
        let [rx, ry, _] = self.resolution;
        [index % rx, (index / rx) % ry, index / (rx * ry)]
    }

    /// The brick holding voxel `v`.
    #[inline]
    pub(super) fn brick(&self, v: [u32; 3]) -> u32 {
        (v[0] >> 3) + self.dims[0] * ((v[1] >> 3) + self.dims[1] * (v[2] >> 3))
    }

    /// The cell of voxel `v` inside its brick.
    #[inline]
    pub(super) fn local(v: [u32; 3]) -> usize {
        ((v[2] & 7) << 6 | (v[1] & 7) << 3 | (v[0] & 7)) as usize
    }

    /// The slot of brick `b`, allocated on first touch.
    #[inline]
    pub(super) fn slot(&mut self, b: u32) -> usize {
        let mut s = self.slots[b as usize];
        if s == u32::MAX {
            s = self.bricks.len() as u32;
            self.slots[b as usize] = s;
            self.bricks.push(b);
            // Levels start at 255 so a hit is the same branch-free update whether or not it is the first.
            self.cells.resize(self.cells.len() + 512, [0, u8::MAX]);
        }
        s as usize
    }

    /// One more hit of voxel `v` at `level`.
    #[inline]
    pub(super) fn hit(&mut self, v: [u32; 3], level: u8) {
        let o = self.slot(self.brick(v)) << 9 | Self::local(v);
        self.bump(o, level);
    }

    /// One more hit of cell `o` at `level`.
    #[inline]
    pub(super) fn bump(&mut self, o: usize, level: u8) {
        let c = &mut self.cells[o];
        c[0] = c[0].saturating_add(1);
        c[1] = c[1].min(level);
    }

    /// The compact records in index order, the occupancy brick map and the voxel box.
    pub(super) fn into_compact(self) -> (Vec<Compact>, BrickMap, Option<VoxelBox>) {
        let mut out = Vec::new();
        let (map, vbox) = self.visit(|index, hits, level| out.push(Compact { key: u64::from(index), hits, level }));
        (out, map, vbox)
    }

    /// The voxels as a list (densities still 1), their hit counts, the occupancy brick map and the voxel box.
    pub(super) fn into_list(self) -> (VoxelList, Vec<u8>, BrickMap, Option<VoxelBox>) {
        let mut list = VoxelList::default();
        let mut hits_of = Vec::new();
        let (map, vbox) = self.visit(|index, hits, level| {
            list.indices.push(index);
            list.levels.push(level);
            hits_of.push(hits);
        });
        list.densities = vec![1; list.indices.len()];
        (list, hits_of, map, vbox)
    }

    /// Visit every hit voxel in index order (index, hits, level); returns the brick map and the voxel box.
    fn visit(&self, mut emit: impl FnMut(u32, u8, u8)) -> (BrickMap, Option<VoxelBox>) {
        let mut any = false;
        let [rx, ry, rz] = self.resolution;
        let [nx, ny, _] = self.dims;
        let mut map = BrickMap { dims: self.dims, bits: vec![0u64; (self.slots.len()).div_ceil(64)] };
        let mut order: Vec<u32> = (0..self.bricks.len() as u32).collect();
        order.sort_unstable_by_key(|&s| self.bricks[s as usize]);
        let (mut lo, mut hi) = ([u32::MAX; 3], [0u32; 3]);
        // Slabs of bricks with equal bz; inside one, rows of bricks with equal by (bricks in x order).
        let mut k = 0;
        while k < order.len() {
            let bz = self.bricks[order[k] as usize] / (nx * ny);
            let mut end = k;
            while end < order.len() && self.bricks[order[end] as usize] / (nx * ny) == bz {
                end += 1;
            }
            let slab = &order[k..end];
            for lz in 0..8 {
                let z = bz * 8 + lz;
                if z >= rz {
                    break;
                }
                let mut r = 0;
                while r < slab.len() {
                    let by = self.bricks[slab[r] as usize] / nx % ny;
                    let mut rend = r;
                    while rend < slab.len() && self.bricks[slab[rend] as usize] / nx % ny == by {
                        rend += 1;
                    }
                    for ly in 0..8 {
                        let y = by * 8 + ly;
                        if y >= ry {
                            break;
                        }
                        for &s in &slab[r..rend] {
                            let bx = self.bricks[s as usize] % nx;
                            let base = (s as usize) << 9 | (lz << 6 | ly << 3) as usize;
                            // Most rows of a touched brick are empty: test the row's 8 cells at once.
                            if self.cells[base..base + 8].iter().fold(0u8, |a, c| a | c[0]) == 0 {
                                continue;
                            }
                            for lx in 0..8 {
                                let x = bx * 8 + lx;
                                if x >= rx {
                                    break;
                                }
                                let [hits, level] = self.cells[base | lx as usize];
                                if hits != 0 {
                                    emit(x + rx * (y + ry * z), hits, level);
                                    any = true;
                                    for (a, c) in [x, y, z].into_iter().enumerate() {
                                        lo[a] = lo[a].min(c);
                                        hi[a] = hi[a].max(c);
                                    }
                                }
                            }
                        }
                    }
                    r = rend;
                }
            }
            k = end;
        }
        for &b in &self.bricks {
            map.bits[b as usize >> 6] |= 1 << (b & 63);
        }
        (map, any.then_some((lo, hi)))
    }
}
