//! The memo of one world's summary nodes ([`Summaries`]): nodes answered from the cache, from cached descendants,
//! or from leaves computed in blocks, each cell's leaf corrected by its edits.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use canopy_protocol::lru::Lru;
use canopy_protocol::summary::{NodeKey, NodeSummary};
use canopy_protocol::sync::Locked;

use super::{
    Corrections, DEFAULT_CACHE_NODES, LEAF_BLOCK_LEVEL, LeafEdit, MAX_CORRECTED_CELLS, Model, aggregate, cell_coord,
    subtree,
};
use crate::world::{CellKey, World, par};

/// Memoised summary nodes of one world, for the server's far view and `canopy render`: [`Summaries::get`] answers
/// a node from the cache, from cached descendants, or from leaves computed in blocks of 16 × 16 cells (on the
/// available cores). At most `capacity` nodes are kept; the least recently used goes first. Nodes are pure
/// functions of the world, the cells' edits ([`Summaries::correct`]) and the key: what is cached, and the order of
/// requests, never changes an answer. Without edits a node is [`World::node_summary`]'s, bit for bit.
///
/// A memo shared between threads is asked through [`Summaries::get_shared`], which computes the leaves outside its
/// lock. Two threads asking for overlapping nodes at once may compute a block twice; both get the same nodes.
pub struct Summaries {
    world: Arc<World>,
    model: Arc<Model>,
    capacity: usize,
    nodes: Lru<NodeKey, Arc<NodeSummary>>,
    /// Cells' edits the leaves take ([`Summaries::correct`]), and how many times they changed.
    edits: Arc<Corrections>,
    corrections: u64,
    /// Most cells whose edits are kept ([`MAX_CORRECTED_CELLS`] unless set).
    max_corrected: usize,
}

impl std::fmt::Debug for Summaries {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (capacity, nodes, corrected) = (self.capacity, self.nodes.len(), self.edits.len());
        f.debug_struct("Summaries")
            .field("capacity", &capacity)
            .field("nodes", &nodes)
            .field("corrected", &corrected)
            .finish()
    }
}

/// The nodes of levels 1 ..= [`LEAF_BLOCK_LEVEL`] of one block (1 + 4 + 16 + 64), which a block hands back for
/// caching, and its leaves (handed back too when a leaf is asked for).
const BLOCK_NODES: usize = 85;
const BLOCK_LEAVES: usize = 256;

/// What computing one node needs beyond the cache ([`Summaries::plan`]): the blocks of leaves to compute.
#[derive(Debug)]
struct Plan {
    key: NodeKey,
    world: Arc<World>,
    model: Arc<Model>,
    /// The edits as they were when the plan was made, and their count of changes then.
    edits: Arc<Corrections>,
    corrections: u64,
    /// Nodes found cached on the way down, held so that evictions meanwhile do not matter.
    local: BTreeMap<NodeKey, Arc<NodeSummary>>,
    /// Blocks (level [`LEAF_BLOCK_LEVEL`]) to compute, sorted.
    missing: Vec<NodeKey>,
    /// Most nodes below the blocks' roots to hand back for caching (half the memo's capacity).
    keep: usize,
}

/// A [`Plan`] computed, for [`Summaries::finish`].
#[derive(Debug)]
struct Computed {
    key: NodeKey,
    /// The memo's count of corrections when the plan was made: a result computed before a correction is answered
    /// but not cached.
    corrections: u64,
    local: BTreeMap<NodeKey, Arc<NodeSummary>>,
    /// The blocks' roots.
    roots: Vec<NodeSummary>,
    /// Nodes computed on the way (levels ≥ 1, leaves too when a leaf is asked for), to cache.
    found: Vec<NodeSummary>,
}

impl Plan {
    /// Compute the plan's blocks (on the available cores), touching no memo.
    fn compute(self) -> Computed {
        let Plan { key, world, model, edits, corrections, local, missing, keep } = self;
        let leaves = key.level == 0;
        let per_block = if leaves { BLOCK_NODES + BLOCK_LEAVES } else { BLOCK_NODES };
        let kept_blocks = (keep / per_block).max(1);
        let computed = par::map(
            &missing,
            || (),
            |_, &b| {
                let mut found = Vec::new();
                let n = missing.partition_point(|&m| m < b);
                let root = subtree(&world, &model, b, &edits, |node| {
                    if n < kept_blocks && (node.key.level >= 1 || leaves) && node.key != b {
                        found.push(node.clone());
                    }
                });
                (root, found)
            },
        );
        let (roots, found): (Vec<NodeSummary>, Vec<Vec<NodeSummary>>) = computed.into_iter().unzip();
        Computed { key, corrections, local, roots, found: found.into_iter().flatten().collect() }
    }
}

impl Summaries {
    /// A cache of at most [`DEFAULT_CACHE_NODES`] nodes.
    pub fn new(world: Arc<World>) -> Summaries {
        Summaries::with_capacity(world, DEFAULT_CACHE_NODES)
    }

    /// A cache of at most `capacity` nodes (at least 1).
    pub fn with_capacity(world: Arc<World>, capacity: usize) -> Summaries {
        let model = Arc::new(Model::new(&world));
        let edits = Arc::new(Corrections::new());
        let max_corrected = MAX_CORRECTED_CELLS;
        Summaries { world, model, capacity: capacity.max(1), nodes: Lru::new(), edits, corrections: 0, max_corrected }
    }

    /// Keep the edits of at most `cells` cells from now on, instead of [`MAX_CORRECTED_CELLS`] (a server, whose
    /// edits come from its own store, keeps as many as it indexes). Cells kept already stay.
    pub fn set_max_corrected(&mut self, cells: usize) {
        self.max_corrected = cells;
    }

    /// Correct the leaf of `cell` by `edits` (`None` or empty: the world function alone again) from now on: every
    /// cached node holding the cell (its leaf and each ancestor) is dropped, and a node computed from a plan made
    /// before is answered but not cached. Whether the cell's edits changed; `false` too for a new cell past
    /// [`MAX_CORRECTED_CELLS`] (the edits come from the network: a bounded number is kept; see
    /// [`Summaries::set_max_corrected`]).
    pub fn correct(&mut self, cell: CellKey, edits: Option<Arc<[LeafEdit]>>) -> bool {
        let edits = edits.filter(|e| !e.is_empty());
        let now = self.edits.get(&cell);
        if now.map(|e| &**e) == edits.as_deref() {
            return false;
        }
        if now.is_none() && self.edits.len() >= self.max_corrected {
            return false;
        }
        let map = Arc::make_mut(&mut self.edits);
        match edits {
            Some(e) => map.insert(cell, e),
            None => map.remove(&cell),
        };
        self.corrections += 1;
        let c = cell_coord(cell);
        for level in 0..=canopy_protocol::summary::MAX_LEVEL {
            self.nodes.remove(&NodeKey::of_cell(c, level));
        }
        true
    }

    /// The cells whose leaves take edits.
    pub fn corrected_cells(&self) -> usize {
        self.edits.len()
    }

    /// The edits the leaf of `cell` takes, if any.
    pub fn edits_of(&self, cell: CellKey) -> Option<&Arc<[LeafEdit]>> {
        self.edits.get(&cell)
    }

    /// The world.
    pub fn world(&self) -> &Arc<World> {
        &self.world
    }

    /// Nodes cached now.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    /// Whether nothing is cached.
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// A cached node, computing nothing and leaving the order of use as it is.
    pub fn peek(&self, key: NodeKey) -> Option<&Arc<NodeSummary>> {
        self.nodes.peek(&key)
    }

    /// The summary of `key`: computed (and cached, with the nodes computed on the way: every node of level ≥ 1 of
    /// the blocks computed, and the leaves too when a leaf is asked for) unless cached.
    pub fn get(&mut self, key: NodeKey) -> Arc<NodeSummary> {
        match self.plan(key) {
            Ok(hit) => hit,
            Err(plan) => self.finish(plan.compute()),
        }
    }

    /// [`Summaries::get`] on a memo shared between threads: what is cached is looked up, and the result cached,
    /// under its lock; the leaves are computed outside it, so several threads compute at once. A poisoned lock is
    /// taken as it is (the memo holds only pure results).
    pub fn get_shared(memo: &Mutex<Summaries>, key: NodeKey) -> Arc<NodeSummary> {
        let lock = || memo.locked();
        let plan = lock().plan(key);
        match plan {
            Ok(hit) => hit,
            Err(plan) => {
                let computed = plan.compute();
                lock().finish(computed)
            }
        }
    }

    /// [`Summaries::get_shared`] a block of leaves at a time, on the calling thread: `key` when its last missing
    /// block is the one computed now (or none was missing), else `None` after computing and caching the first
    /// missing block, so that a worker can take more urgent work between the blocks of a coarse node (each is
    /// 256 cells: a few milliseconds) and then ask again. A node needing more blocks than the memo keeps at once
    /// is computed whole, as [`Summaries::get_shared`] does (on every core), for its blocks would evict each other.
    pub fn step_shared(memo: &Mutex<Summaries>, key: NodeKey) -> Option<Arc<NodeSummary>> {
        let plan = memo.locked().plan(key);
        match plan {
            Ok(hit) => Some(hit),
            Err(plan) if plan.missing.len() <= 1 || plan.missing.len() > plan.keep / BLOCK_NODES => {
                let computed = plan.compute();
                Some(memo.locked().finish(computed))
            }
            Err(mut plan) => {
                let block = plan.missing[0];
                plan.key = block;
                plan.missing.truncate(1);
                plan.local.clear();
                let computed = plan.compute();
                memo.locked().finish(computed);
                None
            }
        }
    }

    /// `key` if it is cached, else what computing it needs: the cached nodes below it and the missing blocks.
    fn plan(&mut self, key: NodeKey) -> Result<Arc<NodeSummary>, Plan> {
        if let Some(hit) = self.touch(key) {
            return Ok(hit);
        }
        let mut local: BTreeMap<NodeKey, Arc<NodeSummary>> = BTreeMap::new();
        let mut missing = Vec::new();
        if key.level <= LEAF_BLOCK_LEVEL {
            let shift = LEAF_BLOCK_LEVEL - key.level;
            missing.push(NodeKey { level: LEAF_BLOCK_LEVEL, x: key.x >> shift, z: key.z >> shift });
        } else {
            let mut stack = vec![key];
            while let Some(k) = stack.pop() {
                if let Some(n) = self.touch(k) {
                    local.insert(k, n);
                } else if k.level == LEAF_BLOCK_LEVEL {
                    missing.push(k);
                } else if let Some(children) = k.children() {
                    stack.extend(children);
                }
            }
            missing.sort();
        }
        let (world, model, edits) = (Arc::clone(&self.world), Arc::clone(&self.model), Arc::clone(&self.edits));
        let corrections = self.corrections;
        Err(Plan { key, world, model, edits, corrections, local, missing, keep: self.capacity / 2 })
    }

    /// Cache what a plan computed and answer its node (aggregating the levels above the blocks).
    fn finish(&mut self, computed: Computed) -> Arc<NodeSummary> {
        let Computed { key, corrections, mut local, roots, found } = computed;
        // Computed from edits since changed: answered, not cached (nor what is aggregated from it).
        let current = corrections == self.corrections;
        let mut wanted = None;
        for n in found.into_iter().chain(roots) {
            let n = Arc::new(n);
            if n.key == key {
                wanted = Some(n.clone());
            }
            if n.key.level == LEAF_BLOCK_LEVEL {
                local.insert(n.key, n.clone());
            }
            if current {
                self.insert(n);
            }
        }
        if !current {
            return wanted.unwrap_or_else(|| resolve_uncached(key, &mut local));
        }
        match wanted {
            Some(n) => {
                self.touch(key);
                n
            }
            None => self.resolve(key, &mut local),
        }
    }

    /// `key` from `local` (cached nodes and computed blocks), aggregating missing levels and caching them.
    fn resolve(&mut self, key: NodeKey, local: &mut BTreeMap<NodeKey, Arc<NodeSummary>>) -> Arc<NodeSummary> {
        if let Some(n) = local.get(&key) {
            return n.clone();
        }
        let children = key.children().expect("every block below the key is held").map(|c| self.resolve(c, local));
        let node = Arc::new(aggregate(key, [&*children[0], &*children[1], &*children[2], &*children[3]]));
        self.insert(node.clone());
        local.insert(key, node.clone());
        node
    }

    /// A cached node, marked as just used.
    fn touch(&mut self, key: NodeKey) -> Option<Arc<NodeSummary>> {
        self.nodes.get(&key).map(|n| n.clone())
    }

    /// Cache a node, evicting the least recently used past the capacity.
    fn insert(&mut self, node: Arc<NodeSummary>) {
        // Each node counts one: the bound is a count of nodes.
        self.nodes.insert(node.key, node, 1);
        self.nodes.evict_to(self.capacity, None);
    }
}

/// `key` from `local` (cached nodes and computed blocks), aggregating missing levels, caching nothing.
fn resolve_uncached(key: NodeKey, local: &mut BTreeMap<NodeKey, Arc<NodeSummary>>) -> Arc<NodeSummary> {
    if let Some(n) = local.get(&key) {
        return n.clone();
    }
    let children = key.children().expect("every block below the key is held").map(|c| resolve_uncached(c, local));
    let node = Arc::new(aggregate(key, [&*children[0], &*children[1], &*children[2], &*children[3]]));
    local.insert(key, node.clone());
    node
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A node of 2 × 2 blocks stepped a block at a time is the node computed whole, answered with the last block;
    /// a memo too small to keep its blocks at once computes it whole at the first step.
    #[test]
    fn a_coarse_node_stepped_a_block_at_a_time_is_the_node_computed_whole() {
        let text = "seed 7\nbounds -1024 -1024 1024 1024\ncell 64\nspecies a conifer\nscatter a {\n  spacing 8\n}\n";
        let src = crate::diag::SourceFile::new("t.world", text);
        let world = Arc::new(World::parse(&src, None).expect("loads"));
        let key = NodeKey::of_cell(canopy_protocol::CellCoord::new(0, 0), LEAF_BLOCK_LEVEL + 1);
        let whole = world.node_summary(key);
        let memo = Mutex::new(Summaries::new(Arc::clone(&world)));
        let mut steps = 1;
        let stepped = loop {
            match Summaries::step_shared(&memo, key) {
                Some(n) => break n,
                None => {
                    assert_eq!(memo.locked().len(), steps * BLOCK_NODES, "each step caches one block's nodes");
                    steps += 1;
                }
            }
        };
        assert_eq!(steps, 4, "four blocks, the node with the last");
        assert_eq!(*stepped, whole);
        assert!(Arc::ptr_eq(&Summaries::step_shared(&memo, key).expect("cached"), &stepped));
        let small = Mutex::new(Summaries::with_capacity(Arc::clone(&world), 2 * BLOCK_NODES));
        assert_eq!(*Summaries::step_shared(&small, key).expect("computed whole"), whole);
    }

    /// A plan made before a correction is answered from the edits it was made with, and not cached.
    #[test]
    fn a_node_computed_across_a_correction_is_answered_not_cached() {
        let text = "seed 7\nbounds -512 -512 512 512\ncell 64\nspecies a conifer\nscatter a {\n  spacing 4\n}\n";
        let src = crate::diag::SourceFile::new("t.world", text);
        let mut memo = Summaries::new(Arc::new(World::parse(&src, None).expect("loads")));
        let (cell, leaf, top) = (
            CellKey { x: 1, z: 2 },
            NodeKey { level: 0, x: 1, z: 2 },
            NodeKey::of_cell(canopy_protocol::CellCoord::new(1, 2), 6),
        );
        let felled: Arc<[LeafEdit]> = Arc::new([LeafEdit { species: 0, x: 65.0, z: 129.0, height: None, sign: -1 }]);
        for key in [leaf, top] {
            let Err(plan) = memo.plan(key) else { panic!("nothing is cached yet") };
            assert!(memo.correct(cell, Some(felled.clone())));
            let held = memo.len();
            let stale = memo.finish(plan.compute());
            assert_eq!(*stale, memo.world.node_summary(key), "answered from the world function alone");
            assert!(memo.len() == held && memo.peek(key).is_none(), "and not cached");
            let count = |n: &NodeSummary| n.species.first().map_or(0, |s| s.count);
            assert_eq!(count(&memo.get(key)), count(&stale) - 1, "a plan made now takes the edit");
            assert!(memo.peek(key).is_some());
            assert!(memo.correct(cell, None));
            assert!(memo.peek(key).is_none() && memo.peek(leaf).is_none(), "nodes holding the cell are dropped");
            assert_eq!(*memo.get(key), *stale, "the world function alone again");
        }
    }
}
