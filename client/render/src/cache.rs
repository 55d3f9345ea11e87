//! The geometry cache's bookkeeping, without the GPU: which (species, seed, detail) keys are resident in the three
//! arenas and where, which are being made, which failed or were given up for a while, the finished geometry waiting
//! for upload budget, and least-recently-used eviction. [`GeometryCache::upload`] places geometry in the arenas and
//! hands each placement to a writer: the renderer's buffer writes, or nothing in tests.

use std::collections::{HashMap, HashSet, VecDeque};
use std::ops::Range;

use canopy_protocol::lru::Lru;

use super::arena::Arena;
use super::geometry::{MeshVertex, PrimInstance, TreeGeometry};
use super::stats::FrameStats;
use super::workers::TreeKey;

/// Frames before geometry that did not fit the cache is asked for again.
pub(crate) const DEFER_FRAMES: u64 = 120;

/// Keys given up in one frame because the cache is full of what is in view, at most; after that the frame's
/// uploads stop (the rest waits for the next frame).
pub(crate) const MAX_DEFERRED_PER_FRAME: usize = 8;

/// Bytes of one mesh index.
pub(crate) const INDEX_BYTES: u64 = size_of::<u32>() as u64;

/// One resident key: its ranges in the arenas (in units of the arena: primitives, vertices, indices).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct CacheEntry {
    /// Primitive instances.
    pub prims: Range<u64>,
    /// The range of each unit shape within `prims`, relative to its start.
    pub shape_ranges: [Range<u32>; 3],
    /// Mesh vertices.
    pub verts: Range<u64>,
    /// Mesh indices.
    pub indices: Range<u64>,
    /// The frame that last drew it.
    pub last_used: u64,
}

/// Where one piece of geometry was placed, in arena units (what the writer copies it to).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Placement {
    /// Primitive instances.
    pub prims: Range<u64>,
    /// Mesh vertices.
    pub verts: Range<u64>,
    /// Mesh indices.
    pub indices: Range<u64>,
}

/// The cache (see the module docs).
#[derive(Debug)]
pub(crate) struct GeometryCache {
    prim_arena: Arena,
    vert_arena: Arena,
    index_arena: Arena,
    /// Resident keys, least recently drawn first (each costs 1: the arenas bound what fits).
    entries: Lru<TreeKey, CacheEntry>,
    /// Keys asked of the workers and not yet uploaded (or given up): never asked for twice.
    pending: HashSet<TreeKey>,
    /// Keys whose geometry did not fit the cache, by the frame they were given up; retried after
    /// [`DEFER_FRAMES`].
    deferred: HashMap<TreeKey, u64>,
    /// Keys that failed to amplify, or amplified to nothing, or are larger than the whole cache.
    failed: HashSet<TreeKey>,
    /// Finished geometry in arrival order, waiting for upload budget.
    uploads: VecDeque<(TreeKey, TreeGeometry)>,
}

impl GeometryCache {
    /// An empty cache over arenas of these many primitives, vertices and indices.
    pub(crate) fn new(prim_units: u64, vert_units: u64, index_units: u64) -> GeometryCache {
        GeometryCache {
            prim_arena: Arena::new(prim_units),
            vert_arena: Arena::new(vert_units),
            index_arena: Arena::new(index_units),
            entries: Lru::new(),
            pending: HashSet::new(),
            deferred: HashMap::new(),
            failed: HashSet::new(),
            uploads: VecDeque::new(),
        }
    }

    /// The resident entry of a key.
    pub(crate) fn get(&self, key: &TreeKey) -> Option<&CacheEntry> {
        self.entries.peek(key)
    }

    /// Whether a key is being made or waits for upload.
    pub(crate) fn is_pending(&self, key: &TreeKey) -> bool {
        self.pending.contains(key)
    }

    /// Record that a key was asked of the workers; false when it already was.
    pub(crate) fn mark_pending(&mut self, key: TreeKey) -> bool {
        self.pending.insert(key)
    }

    /// Whether a key must not be asked for now: it failed, or it was given up for lack of room a short while ago.
    pub(crate) fn unavailable(&self, key: &TreeKey) -> bool {
        self.failed.contains(key) || self.deferred.contains_key(key)
    }

    /// A worker's result for a key. The key stays pending until its geometry is uploaded (or given up), so it is
    /// not asked for twice.
    pub(crate) fn finished(&mut self, key: TreeKey, result: Result<TreeGeometry, String>) {
        match result {
            Ok(geo) if !geo.is_empty() => self.uploads.push_back((key, geo)),
            Ok(_) => {
                self.pending.remove(&key);
                self.failed.insert(key);
            }
            Err(e) => {
                self.pending.remove(&key);
                tracing::warn!("species {} seed {:#x} detail {}: {e}", key.species, key.seed, key.detail);
                self.failed.insert(key);
            }
        }
    }

    /// Forget keys given up [`DEFER_FRAMES`] or more before `frame`, so that they are asked for again.
    pub(crate) fn expire_deferred(&mut self, frame: u64) {
        self.deferred.retain(|_, at| *at + DEFER_FRAMES > frame);
    }

    /// Mark a resident key as drawn in `frame` (no-op for a key not resident).
    pub(crate) fn touch(&mut self, key: TreeKey, frame: u64) {
        if self.entries.peek(&key).is_some_and(|e| e.last_used != frame)
            && let Some(e) = self.entries.get(&key)
        {
            e.last_used = frame;
        }
    }

    /// Resident keys.
    pub(crate) fn len(&self) -> usize {
        self.entries.len()
    }

    /// Finished geometry waiting for upload budget.
    pub(crate) fn uploads_waiting(&self) -> usize {
        self.uploads.len()
    }

    /// Keys that failed.
    pub(crate) fn failed(&self) -> usize {
        self.failed.len()
    }

    /// Bytes of the arenas in use.
    pub(crate) fn bytes_used(&self) -> u64 {
        self.prim_arena.used() * size_of::<PrimInstance>() as u64
            + self.vert_arena.used() * size_of::<MeshVertex>() as u64
            + self.index_arena.used() * INDEX_BYTES
    }

    /// Evict the least recently drawn entry, unless the previous frame drew it (this frame most likely draws it
    /// again); false when nothing could be evicted.
    fn evict_one(&mut self, frame: u64) -> bool {
        if self.entries.oldest().is_none_or(|(_, e)| e.last_used + 1 >= frame) {
            return false;
        }
        if let Some((_, e)) = self.entries.pop_oldest(None) {
            self.free(e);
        }
        true
    }

    fn free(&mut self, e: CacheEntry) {
        self.prim_arena.free(e.prims);
        self.vert_arena.free(e.verts);
        self.index_arena.free(e.indices);
    }

    /// Ranges for `need` (primitives, vertices, indices), evicting old entries as needed; `None` when the cache is
    /// full of what the last frames drew.
    fn place(&mut self, need: (u64, u64, u64), frame: u64, stats: &mut FrameStats) -> Option<Placement> {
        loop {
            let p = self.prim_arena.alloc(need.0);
            let v = p.as_ref().and_then(|_| self.vert_arena.alloc(need.1));
            let i = v.as_ref().and_then(|_| self.index_arena.alloc(need.2));
            match (p, v, i) {
                (Some(prims), Some(verts), Some(indices)) => return Some(Placement { prims, verts, indices }),
                (p, v, _) => {
                    if let Some(p) = p {
                        self.prim_arena.free(p);
                    }
                    if let Some(v) = v {
                        self.vert_arena.free(v);
                    }
                    if !self.evict_one(frame) {
                        return None;
                    }
                    stats.evicted += 1;
                }
            }
        }
    }

    /// Place waiting geometry in the arenas in arrival order, within `budget` bytes this frame (the first upload of a
    /// frame always goes), calling `write` with each piece and where it goes. Counts uploaded bytes, evictions and
    /// deferrals in `stats`.
    pub(crate) fn upload(
        &mut self,
        frame: u64,
        budget: u64,
        stats: &mut FrameStats,
        write: &mut dyn FnMut(&TreeGeometry, &Placement),
    ) {
        while let Some((key, geo)) = self.uploads.front() {
            let bytes = geo.gpu_bytes();
            if stats.uploaded_bytes > 0 && stats.uploaded_bytes + bytes > budget {
                break;
            }
            let need = (geo.prims.len() as u64, geo.vertices.len() as u64, geo.indices.len() as u64);
            if need.0 > self.prim_arena.capacity()
                || need.1 > self.vert_arena.capacity()
                || need.2 > self.index_arena.capacity()
            {
                tracing::warn!("species {} seed {:#x}: geometry larger than the cache", key.species, key.seed);
                let key = *key;
                self.pending.remove(&key);
                self.failed.insert(key);
                self.uploads.pop_front();
                continue;
            }
            let Some(placed) = self.place(need, frame, stats) else {
                // The cache is full of what the last frames drew: this instance keeps its stand-in for a while
                // (and asks again later), and smaller geometry behind it may still fit.
                let (key, _) = self.uploads.pop_front().expect("front exists");
                self.pending.remove(&key);
                self.deferred.insert(key, frame);
                stats.deferred += 1;
                if stats.deferred >= MAX_DEFERRED_PER_FRAME {
                    break;
                }
                continue;
            };
            let (key, geo) = self.uploads.pop_front().expect("front exists");
            self.pending.remove(&key);
            write(&geo, &placed);
            stats.uploaded_bytes += bytes;
            // A stale duplicate (requested again after an eviction) replaces the old entry.
            if let Some(old) = self.entries.remove(&key) {
                self.free(old);
            }
            let entry = CacheEntry {
                prims: placed.prims,
                shape_ranges: geo.shape_ranges.clone(),
                verts: placed.verts,
                indices: placed.indices,
                last_used: frame,
            };
            self.entries.insert(key, entry, 1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geo(prims: usize, verts: usize, indices: usize) -> TreeGeometry {
        TreeGeometry {
            prims: vec![bytemuck::Zeroable::zeroed(); prims],
            shape_ranges: [0..prims as u32, 0..0, 0..0],
            vertices: vec![bytemuck::Zeroable::zeroed(); verts],
            indices: vec![0; indices],
            primitives: prims,
        }
    }

    fn key(seed: u64) -> TreeKey {
        TreeKey { species: 0, seed, detail: 0, params: 0 }
    }

    #[test]
    fn uploads_place_geometry_and_evict_the_least_recently_drawn() {
        let mut c = GeometryCache::new(100, 100, 100);
        let mut stats = FrameStats::default();
        let mut placed = Vec::new();
        for seed in 1..=2 {
            assert!(c.mark_pending(key(seed)));
            c.finished(key(seed), Ok(geo(40, 0, 0)));
        }
        c.upload(1, u64::MAX, &mut stats, &mut |g, p| placed.push((g.prims.len(), p.prims.clone())));
        assert_eq!(placed, vec![(40, 0..40), (40, 40..80)]);
        assert_eq!(c.get(&key(1)).map(|e| e.prims.clone()), Some(0..40));
        assert!(!c.is_pending(&key(1)) && !c.is_pending(&key(2)));
        assert_eq!(c.bytes_used(), 80 * size_of::<PrimInstance>() as u64);
        // Frame 5 drew key 2 only; key 3 needs room: key 1 goes.
        c.touch(key(2), 5);
        c.finished(key(3), Ok(geo(40, 0, 0)));
        let mut stats = FrameStats::default();
        c.upload(6, u64::MAX, &mut stats, &mut |_, _| {});
        assert_eq!(stats.evicted, 1);
        assert!(c.get(&key(1)).is_none() && c.get(&key(2)).is_some() && c.get(&key(3)).is_some());
    }

    #[test]
    fn what_the_last_frame_drew_is_never_evicted_and_the_newcomer_waits() {
        let mut c = GeometryCache::new(100, 100, 100);
        c.finished(key(1), Ok(geo(80, 0, 0)));
        c.upload(1, u64::MAX, &mut FrameStats::default(), &mut |_, _| {});
        c.touch(key(1), 9);
        c.mark_pending(key(2));
        c.finished(key(2), Ok(geo(80, 0, 0)));
        let mut stats = FrameStats::default();
        c.upload(10, u64::MAX, &mut stats, &mut |_, _| panic!("nothing fits"));
        assert_eq!((stats.evicted, stats.deferred), (0, 1));
        assert!(c.unavailable(&key(2)) && !c.is_pending(&key(2)));
        c.expire_deferred(10 + DEFER_FRAMES - 1);
        assert!(c.unavailable(&key(2)));
        c.expire_deferred(10 + DEFER_FRAMES);
        assert!(!c.unavailable(&key(2)), "asked for again after DEFER_FRAMES");
    }

    #[test]
    fn the_budget_holds_back_all_but_the_first_upload_and_failures_are_remembered() {
        let mut c = GeometryCache::new(1000, 1000, 1000);
        for seed in 1..=3 {
            c.finished(key(seed), Ok(geo(10, 0, 0)));
        }
        let one = geo(10, 0, 0).gpu_bytes();
        let mut stats = FrameStats::default();
        c.upload(1, one + one / 2, &mut stats, &mut |_, _| {});
        assert_eq!((stats.uploaded_bytes, c.len(), c.uploads_waiting()), (one, 1, 2));
        c.mark_pending(key(7));
        c.finished(key(7), Ok(TreeGeometry::default()));
        c.mark_pending(key(8));
        c.finished(key(8), Err("too many primitives".into()));
        c.finished(key(9), Ok(geo(2000, 0, 0)));
        c.upload(2, u64::MAX, &mut FrameStats::default(), &mut |_, _| {});
        assert_eq!(c.failed(), 3, "empty, failed and larger than the cache");
        assert!(c.unavailable(&key(7)) && c.unavailable(&key(8)) && c.unavailable(&key(9)));
        assert_eq!(c.len(), 3);
    }
}
