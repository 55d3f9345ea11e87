//! The cell cache's far-view summary nodes (issue 15): computed on the cache's workers when no cell waits, encoded
//! once ([`EncodedSummary`]) and shared by every session, kept in an LRU bounded by bytes, with the wakers of the
//! sessions that found a node pending. Sans-IO: the cache's lock guards it, the workers fill it (and a lookup of a
//! node the memo already holds, computed with an ancestor, fills it at once: `CellCache::summary`).
//!
//! It also counts the corrections of cells' nodes by their edits ([`SummaryLru::correct`]) and remembers the last
//! [`MAX_RECENT_CORRECTIONS`] corrected cells, so that sessions holding nodes over them send them again
//! ([`SummaryLru::corrected_since`]); a node computed across a correction is not cached
//! ([`SummaryLru::corrections`]).

use std::collections::VecDeque;
use std::sync::Arc;

use canopy_protocol::CellCoord;

use canopy_protocol::lru::Lru;
use canopy_protocol::summary::NodeKey;
pub use canopy_protocol::summary::{overlaps, root_level};

use crate::store::{CellWaker, EncodedSummary, SummaryCorrections, SummaryState};
use crate::waiters::Waiters;

/// Most summary nodes queued for computing; a lookup past it answers pending without queueing (the session asks
/// again later), so a flood of far views cannot grow the queue.
pub(crate) const MAX_QUEUED: usize = 16_384;
/// Most corrected cells remembered for the sessions; a session further behind sends every node it holds again.
pub const MAX_RECENT_CORRECTIONS: usize = 4096;

/// What a cached node costs the cache: its bytes and its slot's (map entry, recency).
fn cost(node: &EncodedSummary) -> usize {
    node.heap_bytes() + std::mem::size_of::<Arc<EncodedSummary>>() + 64
}

/// Cached, queued and pending summary nodes (see the module docs).
#[derive(Default)]
pub struct SummaryLru {
    cached: Lru<NodeKey, Arc<EncodedSummary>>,
    /// Nodes queued or being computed, with the wakers to wake when each is ready.
    pending: Waiters<NodeKey>,
    /// Corrections made, and the last cells corrected with the count each made.
    corrections: u64,
    recent: VecDeque<(u64, CellCoord)>,
}

impl SummaryLru {
    /// The node if cached (marking it used); else queue it, once, registering `waker`. The flag says whether it
    /// was queued now (a worker should be woken).
    pub fn lookup(&mut self, key: NodeKey, waker: Option<&Arc<dyn CellWaker>>) -> (SummaryState, bool) {
        if let Some(node) = self.cached(key) {
            return (SummaryState::Ready(node), false);
        }
        if !self.pending.is_waiting(&key) && self.pending.queued() >= MAX_QUEUED {
            return (SummaryState::Pending, false);
        }
        let queued = self.pending.wait(key, waker);
        (SummaryState::Pending, queued)
    }

    /// The node if cached, marking it used.
    pub fn cached(&mut self, key: NodeKey) -> Option<Arc<EncodedSummary>> {
        self.cached.get(&key).map(|n| Arc::clone(n))
    }

    /// The next queued node to compute (coarsest first: a finer node's parent is usually wanted first, and
    /// computing it leaves the children's nodes in the memo). Nodes cached meanwhile (answered from the memo) leave
    /// the queue.
    pub fn next_queued(&mut self) -> Option<NodeKey> {
        let cached = &self.cached;
        let queue = self.pending.queue();
        queue.retain(|k| !cached.contains(k));
        let best = queue.iter().enumerate().max_by_key(|(i, k)| (k.level, std::cmp::Reverse(*i)))?.0;
        queue.remove(best)
    }

    /// Cache a computed node, evicting the least recently used past `limit` bytes; the wakers of its waiters.
    pub fn insert(&mut self, key: NodeKey, node: Arc<EncodedSummary>, limit: usize) -> Vec<Arc<dyn CellWaker>> {
        let bytes = cost(&node);
        self.cached.insert(key, node, bytes);
        // The node just computed stays even past the bound (it was asked for).
        self.cached.evict_to(limit, Some(&key));
        self.pending.done(&key)
    }

    /// A computed node's waiters, without caching it (it was computed across a correction): they ask again.
    pub fn abandon(&mut self, key: NodeKey) -> Vec<Arc<dyn CellWaker>> {
        self.pending.done(&key)
    }

    /// The nodes holding `cell` (levels `0 ..= root_level`) changed: drop those cached and count a correction.
    pub fn correct(&mut self, cell: CellCoord, root_level: u8) {
        for level in 0..=root_level {
            self.cached.remove(&NodeKey::of_cell(cell, level));
        }
        self.corrections += 1;
        self.recent.push_back((self.corrections, cell));
        if self.recent.len() > MAX_RECENT_CORRECTIONS {
            self.recent.pop_front();
        }
    }

    /// Corrections made so far: a node computed from the memo while this count stayed the same may be cached.
    pub fn corrections(&self) -> u64 {
        self.corrections
    }

    /// The cells corrected after the count was `since` (see [`SummaryCorrections`]).
    pub fn corrected_since(&self, since: u64) -> SummaryCorrections {
        let now = self.corrections;
        if since >= now {
            return SummaryCorrections { now, cells: Some(Vec::new()) };
        }
        // The entries hold consecutive counts up to `now`: the first after `since` is `since + 1`.
        let remembered = self.recent.front().is_some_and(|&(n, _)| n <= since + 1);
        let cells = remembered.then(|| self.recent.iter().filter(|(n, _)| *n > since).map(|(_, c)| *c).collect());
        SummaryCorrections { now, cells }
    }

    /// Nodes cached.
    pub fn len(&self) -> usize {
        self.cached.len()
    }

    /// Whether none is cached.
    pub fn is_empty(&self) -> bool {
        self.cached.is_empty()
    }

    /// Bytes the cached nodes hold.
    pub fn bytes(&self) -> usize {
        self.cached.cost()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_protocol::summary::NodeSummary;

    #[test]
    fn bounded_by_bytes_least_recently_used_first_and_queued_once() {
        let mut lru = SummaryLru::default();
        let k = |x| NodeKey { level: 1, x, z: 0 };
        let node = |x| Arc::new(EncodedSummary::new(Arc::new(NodeSummary { key: k(x), error: 0.0, species: vec![] })));
        assert!(matches!(lru.lookup(k(0), None), (SummaryState::Pending, true)));
        assert!(matches!(lru.lookup(k(0), None), (SummaryState::Pending, false)), "queued once");
        assert_eq!(lru.next_queued(), Some(k(0)));
        let one = cost(&node(0));
        for x in 0..4 {
            lru.insert(k(x), node(x), 3 * one);
        }
        assert_eq!(lru.len(), 3);
        assert!(lru.bytes() <= 3 * one);
        assert!(matches!(lru.lookup(k(0), None).0, SummaryState::Pending), "the oldest went first");
        assert!(matches!(lru.lookup(k(3), None).0, SummaryState::Ready(_)));
        // Coarse first.
        lru.lookup(NodeKey { level: 4, x: 0, z: 0 }, None);
        assert_eq!(lru.next_queued(), Some(NodeKey { level: 4, x: 0, z: 0 }));
    }

    #[test]
    fn a_correction_drops_the_nodes_over_its_cell_and_is_told_to_sessions_until_forgotten() {
        let mut lru = SummaryLru::default();
        let cell = CellCoord::new(5, -3);
        let node =
            |k: NodeKey| Arc::new(EncodedSummary::new(Arc::new(NodeSummary { key: k, error: 0.0, species: vec![] })));
        let over = NodeKey::of_cell(cell, 2);
        let beside = NodeKey::of_cell(CellCoord::new(400, 400), 2);
        for k in [over, beside] {
            lru.insert(k, node(k), usize::MAX);
        }
        let seen = lru.corrections();
        assert_eq!(lru.corrected_since(seen), SummaryCorrections { now: 0, cells: Some(vec![]) });
        lru.correct(cell, 6);
        assert!(lru.cached(over).is_none() && lru.cached(beside).is_some());
        assert_eq!(lru.corrected_since(seen), SummaryCorrections { now: 1, cells: Some(vec![cell]) });
        assert_eq!(lru.corrected_since(1).cells, Some(vec![]));
        // Past what is remembered: a session that far behind is told so.
        for i in 0..MAX_RECENT_CORRECTIONS as i32 {
            lru.correct(CellCoord::new(i, 0), 6);
        }
        let now = lru.corrections();
        assert_eq!(lru.corrected_since(seen), SummaryCorrections { now, cells: None });
        assert_eq!(lru.corrected_since(1).cells.map(|c| c.len()), Some(MAX_RECENT_CORRECTIONS));
        assert_eq!(lru.corrected_since(now - 2).cells, Some(vec![CellCoord::new(4094, 0), CellCoord::new(4095, 0)]));
    }
}
