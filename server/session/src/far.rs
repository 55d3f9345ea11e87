//! A session's far view (issue 15): which far-view summary nodes its client gets, in which order, and which it
//! must forget. Sans-IO like the session that owns it: `now` is an argument.
//!
//! The client says how it wants the far field ([`FarView`]: a screen-space error threshold, its viewport and
//! range, its altitude); the selection is the one both sides run ([`Selection`]: the rule
//! [`canopy_protocol::summary::Refine`] from the client's [`Eye`], coarse first, the most visible first, a node
//! after its parent, releases under the looser keep rule) over the store's nodes (a node not computed yet is asked
//! for and wakes the session when it is). Records keep priority: summaries take at most a quarter of the bytes
//! while cells are queued ([`FarSession::turn`]), under the session's pacing.
//!
//! A held node over a cell whose edits corrected it ([`WorldStore::summary_corrections`]) is sent again, as the
//! store computes it anew.
//!
//! Memory and work per session are bounded: at most [`canopy_protocol::farview::MAX_SESSION_NODES`] nodes held or
//! queued, a walk visits at most [`canopy_protocol::farview::MAX_VISITS`] nodes, a rebuild happens at most every
//! [`REBUILD_INTERVAL`] (between rebuilds, nodes it waited for walk on from themselves once ready, at most every
//! [`NODE_REBUILD_INTERVAL`]: the work of the new nodes only), and whatever a client asks, its range is at most
//! [`MAX_RANGE`] and its threshold at least [`MIN_ERROR_PX`] (the nodes it can make the cache compute).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
pub(crate) use canopy_protocol::farview::Eye;
pub use canopy_protocol::farview::REBUILD_INTERVAL;
use canopy_protocol::farview::{NodeState, Selection, Take};
use canopy_protocol::frame::frame;
use canopy_protocol::summary::{FarView, MAX_BATCH_NODES, MAX_BATCH_RELEASES, NodeKey};
use canopy_protocol::sync::Locked;

use canopy_protocol::messages::ServerMsgKind;

use crate::store::{CellWaker, EncodedSummary, SummaryState, WorldStore};
use crate::transmit::{StreamId, Transmit};

/// Once a node the session waits for is ready, the walk goes on from the nodes it waits for at most this often:
/// down a computed subtree at once instead of a level per [`REBUILD_INTERVAL`].
pub const NODE_REBUILD_INTERVAL: Duration = Duration::from_millis(20);
/// Largest summaries message the session builds, bytes of nodes (a few QUIC packets).
pub(crate) const BATCH_BYTES: usize = 8 * 1024;
/// The farthest a session's far view reaches, metres, whatever the client asks (bounds the nodes a client can make
/// the cache compute: a 32 km disc is about 800 km² of leaves, computed once and shared).
pub(crate) const MAX_RANGE: f32 = 32_768.0;
/// The finest screen-space error threshold a session applies, pixels.
pub(crate) const MIN_ERROR_PX: f32 = 2.0;

/// One session's far view (see the module docs).
#[derive(Debug)]
pub struct FarSession {
    view: FarView,
    /// What the client holds, wants and must forget.
    selection: Selection,
    dirty: bool,
    rebuilt: Option<Instant>,
    /// When the tree was last walked, whole or from the nodes it waited for.
    walked: Option<Instant>,
    generation: u64,
    /// Bytes of summaries messages built.
    bytes: u64,
    /// Registered with the nodes found pending: says one became ready.
    waker: Arc<NodeWaker>,
    /// The store's count of summary corrections seen (`None`: none asked yet).
    corrections: Option<u64>,
}

/// The far view's waker (see [`NODE_REBUILD_INTERVAL`]): remembers that a node the session asked for is ready and
/// wakes the session.
#[derive(Default)]
struct NodeWaker {
    ready: AtomicBool,
    session: Mutex<Option<Arc<dyn CellWaker>>>,
}

impl CellWaker for NodeWaker {
    fn wake(&self) {
        self.ready.store(true, Ordering::Release);
        let session = self.session.locked().clone();
        if let Some(w) = session {
            w.wake();
        }
    }
}

impl std::fmt::Debug for NodeWaker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NodeWaker").field("ready", &self.ready.load(Ordering::Relaxed)).finish_non_exhaustive()
    }
}

impl FarSession {
    /// A far view just asked for.
    pub fn new(view: FarView) -> FarSession {
        FarSession {
            view: bounded(view),
            selection: Selection::default(),
            dirty: true,
            rebuilt: None,
            walked: None,
            generation: 0,
            waker: Arc::default(),
            bytes: 0,
            corrections: None,
        }
    }

    /// The client changed its far view.
    pub fn set_view(&mut self, view: FarView) {
        self.view = bounded(view);
        self.dirty = true;
    }

    /// The far view applied: the client's, bounded ([`MAX_RANGE`], [`MIN_ERROR_PX`]).
    pub fn view(&self) -> &FarView {
        &self.view
    }

    /// The viewpoint moved.
    pub fn moved(&mut self) {
        self.dirty = true;
    }

    /// Nodes the client holds.
    pub fn held(&self) -> impl Iterator<Item = NodeKey> + '_ {
        self.selection.held()
    }

    /// Nodes queued to send.
    pub fn queued(&self) -> usize {
        self.selection.queued()
    }

    /// Whether there is something to send.
    pub fn has_work(&self) -> bool {
        self.selection.has_work()
    }

    /// When a rebuild held back by [`REBUILD_INTERVAL`], or a walk from ready nodes held back by
    /// [`NODE_REBUILD_INTERVAL`], is due.
    pub fn due_at(&self, store: &dyn WorldStore) -> Option<Instant> {
        let full = self.dirty || store.generation() != self.generation;
        let full = full.then(|| self.rebuilt.map(|t| t + REBUILD_INTERVAL)).flatten();
        let partial = self.waiting_ready().then(|| self.walked.map(|t| t + NODE_REBUILD_INTERVAL)).flatten();
        match (full, partial) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Whether a node the session waits for became ready.
    fn waiting_ready(&self) -> bool {
        self.selection.is_waiting() && self.waker.ready.load(Ordering::Acquire)
    }

    /// The waker to register with pending nodes, waking `session` too.
    fn node_waker(&self, session: Option<&Arc<dyn CellWaker>>) -> Arc<dyn CellWaker> {
        if let Some(w) = session {
            let mut slot = self.waker.session.locked();
            if !slot.as_ref().is_some_and(|s| Arc::ptr_eq(s, w)) {
                *slot = Some(Arc::clone(w));
            }
        }
        Arc::clone(&self.waker) as Arc<dyn CellWaker>
    }

    /// Whether summaries go next rather than records: releases always do; nodes while their bytes are under a
    /// third of the records' (a quarter of the total while cells are queued).
    pub fn turn(&self, cell_bytes: u64) -> bool {
        self.selection.has_releases() || self.bytes.saturating_mul(3) <= cell_bytes
    }

    /// Rebuild the queue and the releases for where the client stands, if anything changed (a far view, the
    /// viewpoint, a node computed) and the last rebuild is [`REBUILD_INTERVAL`] old; between rebuilds, once a node
    /// it waits for is ready and the last walk is [`NODE_REBUILD_INTERVAL`] old, walk on from the nodes it waits
    /// for only (the work is that of the new nodes, not of the whole tree). `waker` is woken when one is ready.
    pub fn update(&mut self, now: Instant, store: &dyn WorldStore, waker: Option<&Arc<dyn CellWaker>>, eye: &Eye) {
        self.take_corrections(store);
        let generation = store.generation();
        let full =
            (self.dirty || generation != self.generation) && self.rebuilt.is_none_or(|t| now >= t + REBUILD_INTERVAL);
        let partial = !full && self.waiting_ready() && self.walked.is_none_or(|t| now >= t + NODE_REBUILD_INTERVAL);
        if !full && !partial {
            return;
        }
        let waker = self.node_waker(waker);
        self.waker.ready.store(false, Ordering::Release);
        self.walked = Some(now);
        let refine = eye.refine(self.view, store.grid(), store.summary_root_level());
        let state = |k| match store.summary(k, Some(&waker)) {
            SummaryState::Ready(n) => NodeState::Ready(n.node.error),
            SummaryState::Pending => NodeState::Pending,
            SummaryState::Unavailable => NodeState::Unavailable,
        };
        if partial {
            self.selection.walk_on(&refine, eye, state);
            return;
        }
        self.dirty = false;
        self.rebuilt = Some(now);
        self.generation = generation;
        self.selection.rebuild(&refine, eye, state);
    }

    /// Nodes held over cells the store corrected since last asked go again, as the store has them after the next
    /// walk on from them; all of them after the next whole walk if the store no longer remembers which.
    fn take_corrections(&mut self, store: &dyn WorldStore) {
        let since = *self.corrections.get_or_insert_with(|| store.summary_corrections(u64::MAX).now);
        let corrected = store.summary_corrections(since);
        if corrected.now == since {
            return;
        }
        self.corrections = Some(corrected.now);
        match corrected.cells {
            // Walked on from at the next update (as if a node it waited for were ready).
            Some(cells) => {
                cells.into_iter().for_each(|c| self.selection.stale(c));
                self.waker.ready.store(true, Ordering::Release);
            }
            None => {
                self.selection.all_stale();
                self.dirty = true;
            }
        }
    }

    /// Held nodes to send again (corrected by edits since they were sent).
    pub fn stale(&self) -> usize {
        self.selection.stale_count()
    }

    /// The next summaries message, on `lane`: releases, then the most visible queued nodes whose parents the client
    /// holds (or roots); `None` when nothing can go.
    pub fn next_batch(
        &mut self,
        store: &dyn WorldStore,
        waker: Option<&Arc<dyn CellWaker>>,
        lane: u8,
    ) -> Option<Transmit> {
        let root = store.summary_root_level();
        let waker = self.node_waker(waker);
        let waker = Some(&waker);
        let mut nodes: Vec<Arc<EncodedSummary>> = Vec::new();
        let mut size = 0;
        self.selection.next(root, |k| {
            if nodes.len() >= MAX_BATCH_NODES || size >= BATCH_BYTES {
                return Take::Stop;
            }
            match store.summary(k, waker) {
                SummaryState::Ready(n) => {
                    size += n.bytes.len();
                    let error = n.node.error;
                    nodes.push(n);
                    Take::Node(error)
                }
                _ => Take::Skip,
            }
        });
        let released = self.selection.releases(MAX_BATCH_RELEASES);
        if nodes.is_empty() && released.is_empty() {
            return None;
        }
        let bytes = Bytes::from(frame(&encode_batch(&nodes, &released)));
        self.bytes += bytes.len() as u64;
        Some(Transmit {
            stream: StreamId::Lane(lane),
            bytes,
            body: Bytes::new(),
            class: ServerMsgKind::Summaries,
            records: 0,
        })
    }
}

/// The far view a session applies: the client's, its range at most [`MAX_RANGE`] and its threshold at least
/// [`MIN_ERROR_PX`].
fn bounded(view: FarView) -> FarView {
    FarView { range: view.range.min(MAX_RANGE), error_px: view.error_px.max(MIN_ERROR_PX), ..view }
}

/// A summaries message from nodes encoded once: `ServerMsg::Streaming` (1), `ServerStreaming::Summaries` (6), the
/// nodes' count and encodings, the releases' count and keys — postcard's encoding of the same
/// [`canopy_protocol::summary::SummaryBatch`], without decoding and encoding each node again.
pub(crate) fn encode_batch(nodes: &[Arc<EncodedSummary>], released: &[NodeKey]) -> Vec<u8> {
    let mut out = vec![1u8, 6];
    push_varint(&mut out, nodes.len() as u64);
    for n in nodes {
        out.extend_from_slice(&n.bytes);
    }
    push_varint(&mut out, released.len() as u64);
    for k in released {
        out = postcard::to_extend(k, out).expect("encoding a key into a Vec cannot fail");
    }
    out
}

fn push_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_protocol::ServerMsg;
    use canopy_protocol::messages::ServerStreaming;
    use canopy_protocol::summary::{NodeSummary, SpeciesCover, SummaryBatch};

    #[test]
    fn a_hostile_far_view_is_bounded() {
        let greedy = FarView { error_px: 0.5, height_px: u16::MAX, fov_y: 0.02, range: 65_536.0, altitude: 2.0 };
        greedy.validate().unwrap();
        let mut far = FarSession::new(greedy);
        assert_eq!((far.view().range, far.view().error_px), (MAX_RANGE, MIN_ERROR_PX));
        far.set_view(FarView { range: 100.0, error_px: 30.0, ..greedy });
        assert_eq!((far.view().range, far.view().error_px), (100.0, 30.0));
    }

    #[test]
    fn a_batch_encoded_from_shared_nodes_is_the_message() {
        let node = |x: i32, n: u32| NodeSummary {
            key: NodeKey { level: 2, x, z: -x },
            error: 32.0,
            species: vec![SpeciesCover { species: 1, count: n, height_dm: 120, spread_dm: 9, cover: u64::MAX >> x }],
        };
        let nodes: Vec<NodeSummary> = (0..200).map(|x| node(x % 60, 3 + x as u32 * 1000)).take(64).collect();
        let released: Vec<NodeKey> = (0..130).map(|x| NodeKey { level: 1, x, z: 7 }).collect();
        let encoded: Vec<_> = nodes.iter().map(|n| Arc::new(EncodedSummary::new(Arc::new(n.clone())))).collect();
        let bytes = encode_batch(&encoded, &released);
        let want = ServerMsg::Streaming(ServerStreaming::Summaries(SummaryBatch { nodes, released }));
        assert_eq!(bytes, want.encode());
        assert_eq!(ServerMsg::decode(&bytes), Ok(want));
    }
}
