//! Hit recording during generation (§6 steps c and v): into a dense array, a brick grid, or raw keys that are
//! sorted and counted chunk by chunk; then validation into a store.

use super::super::{Hypervolume, StorageType, VoxelBox};
use super::VoxelStore;
use super::bricks::{BrickGrid, BrickMap};
use super::classes::{DensityClasses, classify};
use super::dense::DenseArray;
use super::sort::{RadixKey, radix_sort};
use super::validate::{Compact, build_lists, merge_runs};

/// Raw hits flushed to the compact list once this many have accumulated (bounds memory for any iteration count).
const CHUNK: usize = 1 << 22;

/// Most voxels of a volume recorded in bricks (the brick slot table is 4 bytes per 512 voxels).
const BRICK_GRID_VOXELS: u64 = 1 << 30;

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
    /// Narrow keys `index << 5 | level` (subpart 0, index below 2²⁷, level below 32): half the memory traffic of
    /// the wide keys and fewer radix passes. A hit that does not fit widens every key for good.
    Narrow(Keys<u32>),
    /// Hit counts and levels in bricks of 8³ allocated on first touch (subpart 0 only; for coherent hits such as
    /// line generators', which cross runs of neighbouring voxels): no sort at all. A hit of another subpart turns
    /// the bricks into compact records and switches to wide keys for good.
    Bricks(BrickGrid),
    /// Wide keys `subpart << 40 | index << 8 | level`: the level in the low byte (the shallowest sorts first), the
    /// index above it and the subpart on top, so an unpartitioned index list needs only the passes its index bits
    /// take.
    Wide(Keys<u64>),
}

/// A raw hit as a sortable key: the record `subpart << 32 | index` above [`HitKey::LEVEL_BITS`] bits of level, so
/// keys sort by subpart, then voxel, then shallowest level first.
trait HitKey: RadixKey {
    /// Bits of the level, below the record.
    const LEVEL_BITS: u32;

    /// The key of a hit of voxel `index` of `subpart` at `level` (they must fit the key).
    fn pack(index: u32, subpart: u8, level: u8) -> Self;

    /// The record, `subpart << 32 | index`.
    #[inline(always)]
    fn record(self) -> u64 {
        self.to_u64() >> Self::LEVEL_BITS
    }

    /// The level.
    #[inline(always)]
    fn level(self) -> u8 {
        (self.to_u64() & ((1 << Self::LEVEL_BITS) - 1)) as u8
    }
}

impl HitKey for u32 {
    const LEVEL_BITS: u32 = 5;

    #[inline(always)]
    fn pack(index: u32, subpart: u8, level: u8) -> u32 {
        debug_assert!(subpart == 0 && u32::from(level) < 1 << Self::LEVEL_BITS && index < 1 << (32 - Self::LEVEL_BITS));
        index << Self::LEVEL_BITS | u32::from(level)
    }
}

impl HitKey for u64 {
    const LEVEL_BITS: u32 = 8;

    #[inline(always)]
    fn pack(index: u32, subpart: u8, level: u8) -> u64 {
        (u64::from(subpart) << 32 | u64::from(index)) << Self::LEVEL_BITS | u64::from(level)
    }
}

/// Whether a hit of `subpart` at `level` fits a narrow key (its index always does: the volume was checked).
#[inline(always)]
fn fits_narrow(subpart: u8, level: u8) -> bool {
    subpart == 0 && u32::from(level) < 1 << <u32 as HitKey>::LEVEL_BITS
}

/// Raw hit keys of one width and the compact records counted from them so far.
struct Keys<K> {
    raw: Vec<K>,
    compact: Vec<Compact>,
    scratch: Vec<K>,
}

impl<K: HitKey> Keys<K> {
    fn new() -> Keys<K> {
        Keys { raw: Vec::with_capacity(1 << 16), compact: Vec::new(), scratch: Vec::new() }
    }

    /// Add one raw key, flushing once [`CHUNK`] have accumulated.
    #[inline]
    fn push(&mut self, key: K) {
        self.raw.push(key);
        if self.raw.len() >= CHUNK {
            self.flush();
        }
    }

    /// Add raw keys, flushing once [`CHUNK`] have accumulated.
    #[inline]
    fn extend(&mut self, keys: impl IntoIterator<Item = K>) {
        self.raw.extend(keys);
        if self.raw.len() >= CHUNK {
            self.flush();
        }
    }

    /// Sort the raw keys, count repeats into runs (hit count saturating at 255, the shallowest level: the first
    /// key of a run) and merge them into the compact records.
    fn flush(&mut self) {
        let raw = &mut self.raw;
        if raw.is_empty() {
            return;
        }
        radix_sort(raw, &mut self.scratch);
        let mut runs: Vec<Compact> = Vec::with_capacity(raw.len() / 2);
        let mut k = 0;
        while k < raw.len() {
            let key = raw[k].record();
            let level = raw[k].level();
            let start = k;
            k += 1;
            while k < raw.len() && raw[k].record() == key {
                k += 1;
            }
            runs.push(Compact { key, hits: (k - start).min(255) as u8, level });
        }
        raw.clear();
        merge_runs(&mut self.compact, runs);
    }

    /// Every hit as compact records sorted by (subpart, index); the raw buffers are freed.
    fn into_compact(mut self) -> Vec<Compact> {
        self.flush();
        self.compact
    }
}

impl HitRecorder {
    /// A recorder for a volume of `resolution` that will be stored as `ty`.
    pub fn new(ty: StorageType, resolution: [u32; 3]) -> HitRecorder {
        let mode = match ty {
            StorageType::Dense => Mode::Dense { array: DenseArray::new(resolution), touched: Vec::new() },
            _ if resolution.iter().map(|&r| u64::from(r)).product::<u64>()
                <= 1 << (32 - <u32 as HitKey>::LEVEL_BITS) =>
            {
                Mode::Narrow(Keys::new())
            }
            _ => Mode::Wide(Keys::new()),
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
            Mode::Narrow(keys) if fits_narrow(subpart, level) => {
                self.hits += hits.len() as u64;
                keys.extend(hits.iter().map(|&(_, index)| u32::pack(index, subpart, level)));
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
            Mode::Narrow(keys) => {
                if !fits_narrow(subpart, level) {
                    self.widen();
                    self.hits -= 1;
                    return self.record_at(v, index, level, subpart);
                }
                keys.push(u32::pack(index, subpart, level));
            }
            Mode::Bricks(grid) => {
                if subpart != 0 {
                    self.widen();
                    self.hits -= 1;
                    return self.record_at(v, index, level, subpart);
                }
                grid.hit(v, level);
            }
            Mode::Wide(keys) => keys.push(u64::pack(index, subpart, level)),
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
        let lists = |compact: Vec<Compact>| build_lists(&compact, ty, partitioned, volume, classes, branch_depth);
        let with_map = |store: VoxelStore| {
            let (map, vbox) = BrickMap::build(volume, &store);
            (store, map, vbox)
        };
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
            Mode::Narrow(keys) => with_map(lists(keys.into_compact())),
            Mode::Wide(keys) => with_map(lists(keys.into_compact())),
            Mode::Bricks(grid) if !partitioned => {
                let (list, hits_of, map, vbox) = grid.into_list();
                let list = classify(list, &hits_of, classes, branch_depth);
                (VoxelStore::from_list(list, ty, volume), map, vbox)
            }
            Mode::Bricks(grid) => {
                let (compact, map, vbox) = grid.into_compact();
                (lists(compact), map, vbox)
            }
        }
    }

    /// Switch from narrow keys or bricks to wide keys (a hit of a subpart other than 0, or a narrow key's level
    /// of 32 or more).
    #[cold]
    fn widen(&mut self) {
        let wide = match &mut self.mode {
            Mode::Narrow(keys) => Keys {
                raw: keys.raw.iter().map(|&k| u64::pack(k.record() as u32, 0, k.level())).collect(),
                compact: std::mem::take(&mut keys.compact),
                scratch: Vec::new(),
            },
            Mode::Bricks(grid) => {
                let (compact, _, _) = std::mem::replace(grid, BrickGrid::new([0; 3])).into_compact();
                Keys { compact, ..Keys::new() }
            }
            Mode::Dense { .. } | Mode::Wide(_) => return,
        };
        self.mode = Mode::Wide(wide);
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
