//! Hit recording during generation (§6 steps c and v): into a dense array, a brick grid, or raw keys that are
//! sorted and counted chunk by chunk; then validation into a store.

use super::super::{Hypervolume, StorageType, VoxelBox};
use super::VoxelStore;
use super::bricks::{BrickGrid, BrickMap};
use super::classes::{DensityClasses, classify};
use super::dense::DenseArray;
use super::sort::{radix_sort, radix_sort32};
use super::validate::{Compact, build_lists, merge_runs};

/// Raw hits flushed to the compact list once this many have accumulated (bounds memory for any iteration count).
const CHUNK: usize = 1 << 22;

/// Where generation records voxel hits (§6 steps c and v): straight into a dense array, or as an index list that
/// validation compacts (§5: sort, remove duplicates, count).
pub struct HitRecorder {
    mode: Mode,
    /// Hits recorded (including repeats).
    pub hits: u64,
}

enum Mode {
    Dense {
        array: DenseArray,
        touched: Vec<u32>,
    },
    /// Narrow keys `index << LEVEL_BITS | level` (subpart 0, index below 2²⁷, level below 32): half the memory
    /// traffic of the wide keys and fewer radix passes. A hit that does not fit widens every key for good.
    Keys32 {
        raw: Vec<u32>,
        compact: Vec<Compact>,
        scratch: Vec<u32>,
    },
    /// Hit counts and levels in bricks of 8³ allocated on first touch (subpart 0 only; for coherent hits such as
    /// line generators', which cross runs of neighbouring voxels): no sort at all. A hit of another subpart turns
    /// the bricks into compact records and switches to wide keys for good.
    Bricks(BrickGrid),
    Keys {
        raw: Vec<u64>,
        compact: Vec<Compact>,
        scratch: Vec<u64>,
    },
}

/// Level bits of a narrow key.
const LEVEL_BITS: u32 = 5;

/// Most voxels of a volume recorded in bricks (the brick slot table is 4 bytes per 512 voxels).
const BRICK_GRID_VOXELS: u64 = 1 << 30;

impl HitRecorder {
    /// A recorder for a volume of `resolution` that will be stored as `ty`.
    pub fn new(ty: StorageType, resolution: [u32; 3]) -> HitRecorder {
        let mode = match ty {
            StorageType::Dense => Mode::Dense { array: DenseArray::new(resolution), touched: Vec::new() },
            _ if resolution.iter().map(|&r| u64::from(r)).product::<u64>() <= 1 << (32 - LEVEL_BITS) => {
                Mode::Keys32 { raw: Vec::with_capacity(1 << 16), compact: Vec::new(), scratch: Vec::new() }
            }
            _ => Mode::Keys { raw: Vec::with_capacity(1 << 16), compact: Vec::new(), scratch: Vec::new() },
        };
        HitRecorder { mode, hits: 0 }
    }

    /// A recorder for hits that come in runs of neighbouring voxels (line generators): index lists of a volume
    /// of at most 2³⁰ voxels count them in bricks allocated on first touch instead of sorting the raw hits. The
    /// result is the same as [`HitRecorder::new`]'s.
    pub fn new_coherent(ty: StorageType, resolution: [u32; 3]) -> HitRecorder {
        if ty != StorageType::Dense && resolution.iter().map(|&r| u64::from(r)).product::<u64>() <= BRICK_GRID_VOXELS {
            return HitRecorder { mode: Mode::Bricks(BrickGrid::new(resolution)), hits: 0 };
        }
        HitRecorder::new(ty, resolution)
    }

    /// Record one hit of voxel `index` by a generator at `level` belonging to `subpart`.
    #[inline]
    pub fn record(&mut self, index: u32, level: u8, subpart: u8) {
        let v = match &self.mode {
            Mode::Dense { array, .. } => array.coords(index),
            Mode::Bricks(g) => g.coords(index),
            _ => [0; 3],
        };
        self.record_at(v, index, level, subpart);
    }

    /// The dense array's hit counting, for a caller that records voxel by voxel without batching; `None` for the
    /// lists.
    #[inline]
    pub(crate) fn dense_hits(&mut self) -> Option<DenseHits<'_>> {
        match &mut self.mode {
            Mode::Dense { array, touched } => Some(DenseHits { array, touched, hits: &mut self.hits }),
            _ => None,
        }
    }

    /// The brick grid's hit counting for hits of `subpart`, for a caller that records the voxels of one
    /// generator one at a time; `None` unless hits are counted in bricks and `subpart` is 0.
    #[inline]
    pub(crate) fn brick_hits(&mut self, subpart: u8) -> Option<BrickHits<'_>> {
        match &mut self.mode {
            Mode::Bricks(grid) if subpart == 0 => {
                Some(BrickHits { grid, hits: &mut self.hits, last: u32::MAX, base: 0 })
            }
            _ => None,
        }
    }

    /// Record one hit of each voxel in `hits` (coordinates and index), all by one generator: the same as calling
    /// [`HitRecorder::record_at`] for each in order, with the narrow keys' test made once. (A dense array or a
    /// brick grid is better fed one voxel at a time: [`HitRecorder::dense_hits`], [`HitRecorder::brick_hits`].)
    #[inline]
    pub fn record_many(&mut self, hits: &[([u32; 3], u32)], level: u8, subpart: u8) {
        match &mut self.mode {
            Mode::Keys32 { raw, compact, scratch } if subpart == 0 && u32::from(level) < 1 << LEVEL_BITS => {
                self.hits += hits.len() as u64;
                for &(_, index) in hits {
                    raw.push(index << LEVEL_BITS | u32::from(level));
                }
                if raw.len() >= CHUNK {
                    flush32(raw, compact, scratch);
                }
            }
            _ => {
                for &(v, index) in hits {
                    self.record_at(v, index, level, subpart);
                }
            }
        }
    }

    /// Record one hit of each voxel in `hits` (coordinates, index, level, subpart); the order of hits never changes
    /// the result.
    pub fn record_points(&mut self, hits: &[([u32; 3], u32, u8, u8)]) {
        match &mut self.mode {
            Mode::Dense { array, touched } => {
                self.hits += hits.len() as u64;
                for &(v, index, level, _) in hits {
                    array.hit(v, index, level, touched);
                }
            }
            _ => {
                for &(v, index, level, subpart) in hits {
                    self.record_at(v, index, level, subpart);
                }
            }
        }
    }

    /// Record one hit of voxel `v` whose index is `index` (the dense array addresses by coordinates, the lists by
    /// index, so a caller that knows both saves the divisions).
    #[inline]
    pub fn record_at(&mut self, v: [u32; 3], index: u32, level: u8, subpart: u8) {
        self.hits += 1;
        match &mut self.mode {
            Mode::Dense { array, touched } => array.hit(v, index, level, touched),
            Mode::Keys32 { raw, compact, scratch } => {
                if subpart != 0 || u32::from(level) >= 1 << LEVEL_BITS {
                    self.widen();
                    self.hits -= 1;
                    return self.record_at(v, index, level, subpart);
                }
                raw.push(index << LEVEL_BITS | u32::from(level));
                if raw.len() >= CHUNK {
                    flush32(raw, compact, scratch);
                }
            }
            Mode::Bricks(grid) => {
                if subpart != 0 {
                    self.widen();
                    self.hits -= 1;
                    return self.record_at(v, index, level, subpart);
                }
                grid.hit(v, level);
            }
            Mode::Keys { raw, compact, scratch } => {
                // Level in the low byte (the shallowest sorts first), the index above it and the subpart on top,
                // so an unpartitioned index list needs only the passes its index bits take.
                raw.push(u64::from(subpart) << 40 | u64::from(index) << 8 | u64::from(level));
                if raw.len() >= CHUNK {
                    flush(raw, compact, scratch);
                }
            }
        }
    }

    /// Validation (§6 steps 5–7): compact the hits, turn hit counts into densities by `classes` density classes
    /// (branch voxels, level ≤ `branch_depth`, get full density), and build the store, its occupancy brick map and
    /// voxel box (from the hits, so a dense array is never scanned).
    pub fn finish(
        self,
        ty: StorageType,
        partitioned: bool,
        volume: &Hypervolume,
        classes: u8,
        branch_depth: u8,
    ) -> (VoxelStore, BrickMap, Option<VoxelBox>) {
        match self.mode {
            Mode::Dense { mut array, touched } => {
                let mut histogram = [0u64; 256];
                let offsets: Vec<usize> = touched.iter().map(|&i| array.offset(array.coords(i))).collect();
                for &o in &offsets {
                    histogram[array.cells[o][0] as usize] += 1;
                }
                let dc = DensityClasses::equalise(&histogram, classes);
                for &o in &offsets {
                    let c = &mut array.cells[o];
                    c[0] = if c[1] <= branch_depth { 255 } else { dc.density[c[0] as usize] };
                }
                array.count = touched.len();
                let (map, vbox) = BrickMap::from_indices(volume, touched.iter().copied());
                (VoxelStore::Dense(array), map, vbox)
            }
            Mode::Keys32 { mut raw, mut compact, mut scratch } => {
                flush32(&mut raw, &mut compact, &mut scratch);
                drop(raw);
                drop(scratch);
                let store = build_lists(&compact, ty, partitioned, volume, classes, branch_depth);
                let (map, vbox) = BrickMap::build(volume, &store);
                (store, map, vbox)
            }
            Mode::Bricks(grid) if !partitioned => {
                let (list, hits_of, map, vbox) = grid.into_list();
                let list = classify(list, &hits_of, classes, branch_depth);
                (VoxelStore::from_list(list, ty, volume), map, vbox)
            }
            Mode::Bricks(grid) => {
                let (compact, map, vbox) = grid.into_compact();
                let store = build_lists(&compact, ty, partitioned, volume, classes, branch_depth);
                (store, map, vbox)
            }
            Mode::Keys { mut raw, mut compact, mut scratch } => {
                flush(&mut raw, &mut compact, &mut scratch);
                drop(raw);
                drop(scratch);
                let store = build_lists(&compact, ty, partitioned, volume, classes, branch_depth);
                let (map, vbox) = BrickMap::build(volume, &store);
                (store, map, vbox)
            }
        }
    }
}

impl HitRecorder {
    /// Switch from narrow keys or bricks to wide keys (a hit of a subpart other than 0, or a narrow key's level
    /// of 32 or more).
    #[cold]
    fn widen(&mut self) {
        if let Mode::Keys32 { raw, compact, .. } = &mut self.mode {
            let raw: Vec<u64> =
                raw.iter().map(|&k| u64::from(k >> LEVEL_BITS) << 8 | u64::from(k & ((1 << LEVEL_BITS) - 1))).collect();
            self.mode = Mode::Keys { raw, compact: std::mem::take(compact), scratch: Vec::new() };
        } else if let Mode::Bricks(grid) = &mut self.mode {
            let (compact, _, _) = std::mem::replace(grid, BrickGrid::new([0; 3])).into_compact();
            self.mode = Mode::Keys { raw: Vec::with_capacity(1 << 16), compact, scratch: Vec::new() };
        }
    }
}

/// A dense recorder's array, borrowed to count hits one at a time ([`HitRecorder::dense_hits`]).
pub(crate) struct DenseHits<'a> {
    array: &'a mut DenseArray,
    touched: &'a mut Vec<u32>,
    hits: &'a mut u64,
}

impl DenseHits<'_> {
    /// Count one hit of voxel `v` (index `index`) at `level`, as [`HitRecorder::record_at`] does.
    #[inline(always)]
    pub(crate) fn hit(&mut self, v: [u32; 3], index: u32, level: u8) {
        *self.hits += 1;
        self.array.hit(v, index, level, self.touched);
    }
}

/// A brick-counting recorder's grid, borrowed to count one generator's hits one at a time
/// ([`HitRecorder::brick_hits`]).
pub(crate) struct BrickHits<'a> {
    grid: &'a mut BrickGrid,
    hits: &'a mut u64,
    /// The brick of the last hit and its slot's first cell: neighbouring voxels of a segment mostly share a
    /// brick, so its slot is looked up once per brick.
    last: u32,
    base: usize,
}

impl BrickHits<'_> {
    /// Count one hit of voxel `v` at `level`, as [`HitRecorder::record_at`] does.
    #[inline(always)]
    pub(crate) fn hit(&mut self, v: [u32; 3], level: u8) {
        *self.hits += 1;
        let b = self.grid.brick(v);
        if b != self.last {
            self.last = b;
            self.base = self.grid.slot(b) << 9;
        }
        self.grid.bump(self.base | BrickGrid::local(v), level);
    }
}

/// [`flush`] for narrow keys: the same compact records.
fn flush32(raw: &mut Vec<u32>, compact: &mut Vec<Compact>, scratch: &mut Vec<u32>) {
    if raw.is_empty() {
        return;
    }
    radix_sort32(raw, scratch);
    let mut runs: Vec<Compact> = Vec::with_capacity(raw.len() / 2);
    let mut k = 0;
    while k < raw.len() {
        let key = raw[k] >> LEVEL_BITS;
        let level = (raw[k] & ((1 << LEVEL_BITS) - 1)) as u8;
        let start = k;
        k += 1;
        while k < raw.len() && raw[k] >> LEVEL_BITS == key {
            k += 1;
        }
        runs.push(Compact { key: u64::from(key), hits: (k - start).min(255) as u8, level });
    }
    raw.clear();
    merge_runs(compact, runs);
}

/// Sort the raw hits, count repeats and merge them into the compact list.
fn flush(raw: &mut Vec<u64>, compact: &mut Vec<Compact>, scratch: &mut Vec<u64>) {
    if raw.is_empty() {
        return;
    }
    radix_sort(raw, scratch);
    let mut runs: Vec<Compact> = Vec::new();
    let mut k = 0;
    while k < raw.len() {
        let key = raw[k] >> 8;
        let level = (raw[k] & 0xff) as u8;
        let mut n = 0usize;
        while k < raw.len() && raw[k] >> 8 == key {
            n += 1;
            k += 1;
        }
        runs.push(Compact { key, hits: n.min(255) as u8, level });
    }
    raw.clear();
    merge_runs(compact, runs);
}
