//! Hypertree storage (§5): the dense 3D array, the sorted index list with its density list, and the index list
//! with a bit array of non-empty voxels; optionally partitioned per first-level subpart. Also hit recording during
//! generation, the validation that compacts hits (sort, dedupe, count), density classes (§4, Figure 3) and the
//! occupancy brick map used for empty-space skipping.
//!
//! Every structure answers the same query — [`VoxelQuery::voxel`] by index — and the tests hold them equal voxel
//! for voxel. Memory is reported by [`VoxelStore::memory_bytes`].
//!
//! Files by role: this one holds the query trait and [`VoxelStore`], the store of any structure; `list` the
//! validated [`VoxelList`] and the plain [`IndexList`]; `packed` the [`PackedList`]; `bits` [`IndexBits`]; `dense`
//! the [`DenseArray`]; `partitioned` the per-subpart lists; `hits` the [`HitRecorder`]; `validate` the compact
//! records it is validated through; `sort` the radix sort; `classes` the [`DensityClasses`]; `bricks` the
//! occupancy [`BrickMap`] and the hit-counting [`BrickGrid`].

mod bits;
mod bricks;
mod classes;
mod dense;
mod hits;
mod list;
mod packed;
mod partitioned;
mod sort;
mod validate;

pub use bits::IndexBits;
pub use bricks::{BRICK_SHIFT, BrickGrid, BrickMap};
pub use classes::DensityClasses;
pub use dense::DenseArray;
pub use hits::HitRecorder;
pub use list::{IndexList, VoxelList};
pub use packed::PackedList;
pub use partitioned::{Part, PartStore, Partitioned};
pub use sort::{RadixKey, radix_sort};

use super::{Hypervolume, StorageType, Voxel};

/// Answers "what is in voxel `index`?".
pub trait VoxelQuery {
    /// The voxel at `index` ([`Voxel::EMPTY`] if nothing is there; `index` need not be inside the volume).
    fn voxel(&self, index: u32) -> Voxel;

    /// The voxel at coordinates `v` (inside the volume) whose index is `index`: the renderer's query, which lets a
    /// structure use whichever of the two it addresses by.
    #[inline]
    fn voxel_at(&self, v: [u32; 3], index: u32) -> Voxel {
        let _ = v;
        self.voxel(index)
    }
}

/// A hypertree's voxels in one of the storage structures.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum VoxelStore {
    /// Dense 3D array.
    Dense(DenseArray),
    /// Index list (packed).
    IndexList(PackedList),
    /// Index list and bit array.
    IndexBits(IndexBits),
    /// Index lists (with or without bit arrays) per first-level subpart.
    Partitioned(Partitioned),
}

impl VoxelQuery for VoxelStore {
    #[inline]
    fn voxel_at(&self, v: [u32; 3], index: u32) -> Voxel {
        match self {
            VoxelStore::Dense(d) => d.voxel_at(v, index),
            other => other.voxel(index),
        }
    }

    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        match self {
            VoxelStore::Dense(d) => d.voxel(index),
            VoxelStore::IndexList(l) => l.voxel(index),
            VoxelStore::IndexBits(b) => b.voxel(index),
            VoxelStore::Partitioned(p) => p.voxel(index),
        }
    }
}

impl VoxelStore {
    /// Build a store of `ty` from a validated list (`volume` sizes the dense array).
    pub fn from_list(list: VoxelList, ty: StorageType, volume: &Hypervolume) -> VoxelStore {
        match ty {
            StorageType::IndexList => VoxelStore::IndexList(PackedList::new(&list)),
            StorageType::IndexBits => VoxelStore::IndexBits(IndexBits::new(list)),
            StorageType::Dense => {
                let mut d = DenseArray::new(volume.resolution);
                for (k, &i) in list.indices.iter().enumerate() {
                    let o = d.offset(d.coords(i));
                    d.cells[o] = [list.densities[k], list.levels[k]];
                }
                d.count = list.len();
                VoxelStore::Dense(d)
            }
        }
    }

    /// The storage structure (a partitioned store reports its parts' structure).
    pub fn storage_type(&self) -> StorageType {
        match self {
            VoxelStore::Dense(_) => StorageType::Dense,
            VoxelStore::IndexList(_) => StorageType::IndexList,
            VoxelStore::IndexBits(_) => StorageType::IndexBits,
            VoxelStore::Partitioned(p) => match p.parts.first().map(|p| &p.store) {
                Some(PartStore::IndexBits(_)) => StorageType::IndexBits,
                _ => StorageType::IndexList,
            },
        }
    }

    /// Whether the store is partitioned per first-level subpart.
    pub fn is_partitioned(&self) -> bool {
        matches!(self, VoxelStore::Partitioned(_))
    }

    /// Number of distinct non-empty voxels.
    pub fn len(&self) -> usize {
        match self {
            VoxelStore::Dense(d) => d.count,
            VoxelStore::IndexList(l) => l.len(),
            VoxelStore::IndexBits(b) => b.list.len(),
            VoxelStore::Partitioned(p) => p.count,
        }
    }

    /// Whether no voxel is set.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes the structure occupies (the payload: arrays and lists, not the struct headers).
    pub fn memory_bytes(&self) -> usize {
        match self {
            VoxelStore::Dense(d) => d.cells.len() * 2,
            VoxelStore::IndexList(l) => l.bytes(),
            VoxelStore::IndexBits(b) => b.list.bytes() + b.bits.len() * 8 + b.rank.len() * 4,
            VoxelStore::Partitioned(p) => p
                .parts
                .iter()
                .map(|part| {
                    28 + match &part.store {
                        PartStore::IndexList(l) => l.list.bytes(),
                        PartStore::IndexBits(b) => b.list.bytes() + b.bits.len() * 8 + b.rank.len() * 4,
                    }
                })
                .sum(),
        }
    }

    /// Visit every non-empty voxel in increasing index order.
    pub fn for_each(&self, mut f: impl FnMut(u32, Voxel)) {
        match self {
            VoxelStore::Dense(d) => {
                let [rx, ry, rz] = d.resolution;
                let mut i = 0u32;
                for z in 0..rz {
                    for y in 0..ry {
                        for x in 0..rx {
                            let [density, level] = d.cells[d.offset([x, y, z])];
                            if density != 0 {
                                f(i, Voxel { density, level });
                            }
                            i += 1;
                        }
                    }
                }
            }
            VoxelStore::IndexList(l) => l.for_each(f),
            VoxelStore::IndexBits(IndexBits { list, .. }) => {
                for k in 0..list.len() {
                    f(list.indices[k], Voxel { density: list.densities[k], level: list.levels[k] });
                }
            }
            VoxelStore::Partitioned(_) => {
                let l = self.to_list();
                for k in 0..l.len() {
                    f(l.indices[k], Voxel { density: l.densities[k], level: l.levels[k] });
                }
            }
        }
    }

    /// The voxels as one validated list.
    pub fn to_list(&self) -> VoxelList {
        match self {
            VoxelStore::IndexList(l) => l.to_list(),
            VoxelStore::IndexBits(b) => b.list.clone(),
            VoxelStore::Dense(_) => {
                let mut out = VoxelList::default();
                self.for_each(|i, v| out.push(i, v));
                out
            }
            VoxelStore::Partitioned(p) => {
                // Merge the parts: equal indices carry equal densities; keep the shallowest level.
                let mut all: Vec<(u32, u8, u8)> =
                    Vec::with_capacity(p.parts.iter().map(|x| x.store.voxels().len()).sum());
                for part in &p.parts {
                    let l = part.store.voxels();
                    all.extend((0..l.len()).map(|k| (l.indices[k], l.levels[k], l.densities[k])));
                }
                all.sort_unstable();
                let mut out = VoxelList::default();
                for (i, level, density) in all {
                    if out.indices.last() != Some(&i) {
                        out.push(i, Voxel { density, level });
                    }
                }
                out
            }
        }
    }
}
