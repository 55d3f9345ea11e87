//! Separate index lists per first-level subpart (§5), each with its voxel bounds.

use super::super::{Hypervolume, StorageType, Voxel};
use super::{IndexBits, IndexList, VoxelList, VoxelQuery};

/// The lists of one first-level subpart.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Part {
    /// Which subpart: 0 is the condensation (stem), `j + 1` the subparts made by transformation `j`.
    pub subpart: u8,
    /// Lowest voxel coordinates in the part.
    pub min: [u32; 3],
    /// Highest voxel coordinates in the part.
    pub max: [u32; 3],
    /// The part's voxels: an index list, or an index list with bit array.
    pub store: PartStore,
}

/// The structure of one part.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PartStore {
    /// Index list.
    IndexList(IndexList),
    /// Index list with bit array.
    IndexBits(IndexBits),
}

impl PartStore {
    /// The part's voxel list.
    pub fn voxels(&self) -> &VoxelList {
        match self {
            PartStore::IndexList(l) => &l.list,
            PartStore::IndexBits(b) => &b.list,
        }
    }
}

/// Separate lists per first-level subpart (§5). A voxel hit by several subparts is in each of their lists, with the
/// same density; a lookup returns that density and the shallowest level among the parts that hold it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Partitioned {
    /// The parts, by subpart number.
    pub parts: Vec<Part>,
    /// The volume's resolution (to test part bounds).
    pub resolution: [u32; 3],
    /// Distinct non-empty voxels.
    pub count: usize,
}

impl Partitioned {
    /// Build from per-subpart lists (each sorted; a voxel in several parts must carry the same density).
    pub fn from_parts(parts: Vec<(u8, VoxelList)>, ty: StorageType, volume: &Hypervolume) -> Partitioned {
        let mut all: Vec<u32> = parts.iter().flat_map(|p| p.1.indices.iter().copied()).collect();
        all.sort_unstable();
        all.dedup();
        let parts = parts
            .into_iter()
            .map(|(subpart, list)| {
                let (mut min, mut max) = ([u32::MAX; 3], [0u32; 3]);
                for &i in &list.indices {
                    let v = volume.coords(i);
                    for a in 0..3 {
                        min[a] = min[a].min(v[a]);
                        max[a] = max[a].max(v[a]);
                    }
                }
                let store = match ty {
                    StorageType::IndexBits => PartStore::IndexBits(IndexBits::new(list)),
                    _ => PartStore::IndexList(IndexList { list }),
                };
                Part { subpart, min, max, store }
            })
            .collect();
        Partitioned { parts, resolution: volume.resolution, count: all.len() }
    }
}

impl VoxelQuery for Partitioned {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        let [rx, ry, _] = self.resolution;
        let v = [index % rx, (index / rx) % ry, index / (rx * ry)];
        let mut out = Voxel::EMPTY;
        for p in &self.parts {
            if (0..3).any(|i| v[i] < p.min[i] || v[i] > p.max[i]) {
                continue;
            }
            let got = match &p.store {
                PartStore::IndexList(l) => l.voxel(index),
                PartStore::IndexBits(b) => b.voxel(index),
            };
            if got.density != 0 && (out.density == 0 || got.level < out.level) {
                out = got;
            }
        }
        out
    }
}
