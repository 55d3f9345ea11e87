//! The cell cache's far-view summary nodes (issue 15): computed on the cache's workers when no cell waits, encoded
//! once ([`EncodedSummary`]) and shared by every session, kept in an LRU bounded by bytes, with the wakers of the
//! sessions that found a node pending. Sans-IO: the cache's lock guards it, the workers fill it (and a lookup of a
//! node the memo already holds, computed with an ancestor, fills it at once: `CellCache::summary`).

use std::sync::Arc;

use canopy_protocol::lru::Lru;
use canopy_protocol::summary::NodeKey;
pub use canopy_protocol::summary::{overlaps, root_level};

use crate::store::{CellWaker, EncodedSummary, SummaryState};
use crate::waiters::Waiters;

/// Most summary nodes queued for computing; a lookup past it answers pending without queueing (the session asks
/// again later), so a flood of far views cannot grow the queue.
pub(crate) const MAX_QUEUED: usize = 16_384;

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
}
