//! A session's far view (issue 15): which far-view summary nodes its client gets, in which order, and which it
//! must forget. Sans-IO like the session that owns it: `now` is an argument.
//!
//! The client says how it wants the far field ([`FarView`]: a screen-space error threshold, its viewport and
//! range, its altitude); the rule both sides know is [`Refine`]: from the roots within range, a node's children are
//! wanted while its geometric error projects larger than the threshold. The session walks that tree over the
//! store's nodes (a node not computed yet is asked for and its subtree waits: coarse first), queues the nodes the
//! client does not hold by projected error (the most visible first; a node out of the view cone counts half), and
//! sends a node only after its parent. Held nodes are released under the looser keep rule (hysteresis), coarse
//! before fine, in the same messages. Records keep priority: summaries take at most a quarter of the bytes while
//! cells are queued ([`FarSession::turn`]), under the session's pacing.
//!
//! Memory and work per session are bounded: at most [`MAX_SESSION_NODES`] nodes held or queued, a rebuild visits at
//! most [`MAX_VISITS`] nodes, at most every [`REBUILD_INTERVAL`] (between rebuilds, nodes it waited for walk on
//! from themselves once ready, at most every [`NODE_REBUILD_INTERVAL`]: the work of the new nodes only), and
//! whatever a client asks, its range is at most [`MAX_RANGE`] and its threshold at least [`MIN_ERROR_PX`] (the
//! nodes it can make the cache compute).

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use canopy_protocol::frame::frame;
use canopy_protocol::summary::{FarView, MAX_BATCH_NODES, MAX_BATCH_RELEASES, NodeKey, Refine};
use canopy_protocol::sync::Locked;

use canopy_protocol::messages::ServerMsgKind;

use crate::store::{CellWaker, EncodedSummary, SummaryState, WorldStore};
use crate::transmit::{StreamId, Transmit};

/// Most summary nodes a session holds for its client or has queued.
pub const MAX_SESSION_NODES: usize = 16_384;
/// Most nodes one rebuild visits.
pub const MAX_VISITS: usize = 65_536;
/// A rebuild happens at most this often (viewpoints come up to 50 a second).
pub const REBUILD_INTERVAL: Duration = Duration::from_millis(200);
/// Once a node the session waits for is ready, the walk goes on from the nodes it waits for at most this often:
/// down a computed subtree at once instead of a level per [`REBUILD_INTERVAL`].
pub const NODE_REBUILD_INTERVAL: Duration = Duration::from_millis(20);
/// Largest summaries message the session builds, bytes of nodes (a few QUIC packets).
pub const BATCH_BYTES: usize = 8 * 1024;
/// The farthest a session's far view reaches, metres, whatever the client asks (bounds the nodes a client can make
/// the cache compute: a 32 km disc is about 800 km² of leaves, computed once and shared).
pub const MAX_RANGE: f32 = 32_768.0;
/// The finest screen-space error threshold a session applies, pixels.
pub const MIN_ERROR_PX: f32 = 2.0;

/// A node whose centre lies outside the view cone is queued as if its projected error were this much smaller.
pub const OUT_OF_VIEW_FACTOR: f32 = 0.5;

/// Where the client stands, as the far view needs it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Eye {
    /// Position on the ground plane (x, z).
    pub position: [f32; 2],
    /// Unit heading on the ground plane.
    pub heading: [f32; 2],
    /// Cosine of half the view cone's angle.
    pub cos_half_fov: f32,
    /// Radius the records cover.
    pub record_radius: f32,
}

/// One session's far view (see the module docs).
#[derive(Debug)]
pub struct FarSession {
    view: FarView,
    /// Nodes the client holds, with their geometric errors.
    held: BTreeMap<NodeKey, f32>,
    /// Nodes to send, least important first (the next at the end).
    queue: Vec<(f32, NodeKey)>,
    /// Nodes to tell the client to forget.
    releases: Vec<NodeKey>,
    dirty: bool,
    rebuilt: Option<Instant>,
    /// When the tree was last walked, whole or from the nodes it waited for.
    walked: Option<Instant>,
    /// Nodes the last walks found pending (wanted, not computed yet): a walk goes on from them once they are ready.
    waiting: Vec<NodeKey>,
    generation: u64,
    /// Bytes of summaries messages built.
    bytes: u64,
    /// Registered with the nodes found pending: says one became ready.
    waker: Arc<NodeWaker>,
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
            held: BTreeMap::new(),
            queue: Vec::new(),
            releases: Vec::new(),
            dirty: true,
            rebuilt: None,
            walked: None,
            waiting: Vec::new(),
            generation: 0,
            waker: Arc::default(),
            bytes: 0,
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
        self.held.keys().copied()
    }

    /// Nodes queued to send.
    pub fn queued(&self) -> usize {
        self.queue.len()
    }

    /// Whether there is something to send.
    pub fn has_work(&self) -> bool {
        !self.queue.is_empty() || !self.releases.is_empty()
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
        !self.waiting.is_empty() && self.waker.ready.load(Ordering::Acquire)
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
        !self.releases.is_empty() || self.bytes.saturating_mul(3) <= cell_bytes
    }

    fn refine(&self, store: &dyn WorldStore, eye: &Eye) -> Refine {
        let grid = store.grid();
        Refine {
            view: self.view,
            eye: eye.position,
            origin: grid.origin,
            cell_size: grid.cell_size,
            root_level: store.summary_root_level(),
            record_radius: eye.record_radius,
        }
    }

    /// Rebuild the queue and the releases for where the client stands, if anything changed (a far view, the
    /// viewpoint, a node computed) and the last rebuild is [`REBUILD_INTERVAL`] old; between rebuilds, once a node
    /// it waits for is ready and the last walk is [`NODE_REBUILD_INTERVAL`] old, walk on from the nodes it waits
    /// for only (the work is that of the new nodes, not of the whole tree). `waker` is woken when one is ready.
    pub fn update(&mut self, now: Instant, store: &dyn WorldStore, waker: Option<&Arc<dyn CellWaker>>, eye: &Eye) {
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
        let refine = self.refine(store, eye);
        if partial {
            let from = std::mem::take(&mut self.waiting);
            self.walk(from, &refine, eye, store, &waker);
            return;
        }
        self.dirty = false;
        self.rebuilt = Some(now);
        self.generation = generation;
        // Releases, coarse first; a node whose parent goes goes too.
        let mut by_level: Vec<NodeKey> = self.held.keys().copied().collect();
        by_level.sort_unstable_by(|a, b| b.level.cmp(&a.level).then(a.cmp(b)));
        let mut gone = BTreeSet::new();
        for k in by_level {
            let parent_gone = k.parent().is_some_and(|p| gone.contains(&p));
            if parent_gone || !refine.selects(k, true, |p| self.held.get(&p).copied()) {
                gone.insert(k);
            }
        }
        for k in &gone {
            self.held.remove(k);
            self.releases.push(*k);
        }
        // What is wanted and not held, from the roots down to where the error is small enough or unknown.
        self.queue.clear();
        self.waiting.clear();
        self.walk(refine.roots(false), &refine, eye, store, &waker);
    }

    /// Queue what is wanted and not held from `stack` down, noting the nodes found pending, then order the queue.
    fn walk(
        &mut self,
        mut stack: Vec<NodeKey>,
        refine: &Refine,
        eye: &Eye,
        store: &dyn WorldStore,
        waker: &Arc<dyn CellWaker>,
    ) {
        let mut visits = 0;
        while let Some(k) = stack.pop() {
            visits += 1;
            if visits > MAX_VISITS {
                break;
            }
            let error = match self.held.get(&k) {
                Some(&e) => e,
                None => match store.summary(k, Some(waker)) {
                    SummaryState::Ready(n) => {
                        if self.held.len() + self.queue.len() < MAX_SESSION_NODES {
                            self.queue.push((self.priority(refine, eye, k), k));
                        }
                        n.node.error
                    }
                    SummaryState::Pending => {
                        if self.waiting.len() < MAX_SESSION_NODES {
                            self.waiting.push(k);
                        }
                        continue;
                    }
                    SummaryState::Unavailable => continue,
                },
            };
            if refine.refines(k, error, false) {
                stack.extend(k.children().into_iter().flatten().filter(|c| refine.in_range(*c, false)));
            }
        }
        // Least important first; ties by key, so the order is deterministic.
        self.queue.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(b.1.cmp(&a.1)));
    }

    /// How visible a node is: its nominal error (an eighth of its edge) projected, halved out of the view cone.
    fn priority(&self, refine: &Refine, eye: &Eye, k: NodeKey) -> f32 {
        let [x0, z0, x1, z1] = refine.rect(k);
        let (dx, dz) = ((x0 + x1) * 0.5 - eye.position[0], (z0 + z1) * 0.5 - eye.position[1]);
        let len = (dx * dx + dz * dz).sqrt();
        let inside = refine.ground_distance(k) == 0.0;
        let in_view = inside || len == 0.0 || dx * eye.heading[0] + dz * eye.heading[1] >= eye.cos_half_fov * len;
        let nominal = (x1 - x0) / canopy_protocol::summary::COVER_SIDE as f32;
        let sse = refine.screen_error(k, nominal);
        if in_view { sse } else { sse * OUT_OF_VIEW_FACTOR }
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
        let mut deferred = Vec::new();
        while nodes.len() < MAX_BATCH_NODES && size < BATCH_BYTES && self.held.len() < MAX_SESSION_NODES {
            let Some((p, k)) = self.queue.pop() else { break };
            if self.held.contains_key(&k) {
                continue;
            }
            let parent_held = k.level >= root || k.parent().is_some_and(|p| self.held.contains_key(&p));
            if !parent_held {
                deferred.push((p, k));
                continue;
            }
            if let SummaryState::Ready(n) = store.summary(k, waker) {
                self.held.insert(k, n.node.error);
                size += n.bytes.len();
                nodes.push(n);
            }
        }
        self.queue.extend(deferred.into_iter().rev());
        let n_releases = self.releases.len().min(MAX_BATCH_RELEASES);
        if nodes.is_empty() && n_releases == 0 {
            return None;
        }
        let released: Vec<NodeKey> = self.releases.drain(..n_releases).collect();
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
pub fn encode_batch(nodes: &[Arc<EncodedSummary>], released: &[NodeKey]) -> Vec<u8> {
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
