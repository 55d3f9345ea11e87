//! The far field computed on this client (issue 30, item 5): a connection that expands its cells computes the
//! far-view summary nodes it wants from the same world function, instead of asking the server for them. The
//! selection is the server session's ([`Selection`]: the same nodes, coarse first, a node after its parent), over
//! the world's memo of nodes ([`ExpandWorld::summaries`]), which the expander's workers fill ([`FarJob`]: the
//! coarsest first, a root's subtree with it, and only while no cell waits, as a server's cache does); the nodes
//! reach the state as the server's batches would ([`ClientState::on_summaries`]). A connection that takes records
//! asks the server, as before.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use canopy_protocol::farview::{DEFAULT_FOV_DEG, Eye, MAX_SESSION_NODES, NodeState, REBUILD_INTERVAL, Selection, Take};
use canopy_protocol::summary::{
    FarView, MAX_BATCH_NODES, MAX_BATCH_RELEASES, NodeKey, SummaryBatch, overlaps, root_level,
};
use canopy_protocol::sync::Locked;
use tokio::sync::mpsc;

use crate::expand::{ExpandWorld, Expander, FarJob};
use crate::state::{ClientState, Event, StateError};

/// See the module docs.
pub(super) struct FarField {
    /// The far view the client wants, once it said.
    view: Option<FarView>,
    selection: Selection,
    source: Option<Source>,
    /// The viewpoint or the far view changed since the last walk.
    dirty: bool,
    rebuilt: Option<Instant>,
    /// Wake-ups: a node computed (`Some`), or the selection has nodes to hand out (`None`).
    tx: mpsc::UnboundedSender<Option<NodeKey>>,
    rx: mpsc::UnboundedReceiver<Option<NodeKey>>,
}

/// Where the nodes come from: the world (and its memo), the expander computing them, and what was asked.
struct Source {
    world: Arc<ExpandWorld>,
    expander: Arc<Expander>,
    root_level: u8,
    /// Nodes asked for and not computed yet (at most [`MAX_SESSION_NODES`]).
    asked: BTreeSet<NodeKey>,
    /// Set when this source is dropped: its queued nodes are no longer wanted.
    cancelled: Arc<AtomicBool>,
}

impl Drop for Source {
    fn drop(&mut self) {
        self.cancelled.store(true, Ordering::Relaxed);
    }
}

impl FarField {
    pub(super) fn new() -> FarField {
        let (tx, rx) = mpsc::unbounded_channel();
        FarField { view: None, selection: Selection::default(), source: None, dirty: false, rebuilt: None, tx, rx }
    }

    /// The far view changed.
    pub(super) fn set_view(&mut self, view: FarView) {
        self.view = Some(view);
        self.dirty = true;
        let _ = self.tx.send(None);
    }

    /// The viewpoint moved.
    pub(super) fn moved(&mut self) {
        if self.view.is_some() {
            self.dirty = true;
            let _ = self.tx.send(None);
        }
    }

    /// Whether it computes from a world yet.
    pub(super) fn has_source(&self) -> bool {
        self.source.is_some()
    }

    /// Compute from `world` from now on (once the connection has built it; a connection builds one), with
    /// `expander`'s workers.
    pub(super) fn set_world(&mut self, world: &Arc<ExpandWorld>, expander: &Arc<Expander>) {
        self.source = Some(Source {
            world: Arc::clone(world),
            expander: Arc::clone(expander),
            root_level: root_level(world.grid.cell_size),
            asked: BTreeSet::new(),
            cancelled: Arc::new(AtomicBool::new(false)),
        });
        self.dirty = true;
        let _ = self.tx.send(None);
    }

    /// Wait until there may be something to do: a wake-up, or the moment a walk held back by
    /// [`REBUILD_INTERVAL`] is due (pending forever before a far view and a world).
    pub(super) async fn next(&mut self) -> Option<()> {
        let held_back = self.dirty && self.view.is_some() && self.source.is_some();
        let wake = match self.rebuilt.filter(|_| held_back) {
            Some(t) => {
                let due = tokio::time::Instant::from_std(t + REBUILD_INTERVAL);
                tokio::select! {
                    r = self.rx.recv() => r,
                    () = tokio::time::sleep_until(due) => Some(None),
                }
            }
            None => self.rx.recv().await,
        };
        wake.map(|w| self.woken(w))
    }

    /// Whether a wake-up is already there.
    pub(super) fn try_next(&mut self) -> bool {
        self.rx.try_recv().map(|w| self.woken(w)).is_ok()
    }

    fn woken(&mut self, computed: Option<NodeKey>) {
        if let (Some(k), Some(source)) = (computed, &mut self.source) {
            source.asked.remove(&k);
        }
    }

    /// Walk (again, for a move; on, for computed nodes) and lay the nodes that can go into the state: `None`
    /// when nothing changed.
    pub(super) fn advance(&mut self, state: &mut ClientState, now: Instant) -> Option<Result<Event, StateError>> {
        let (Some(view), Some(source)) = (self.view, &mut self.source) else { return None };
        let (Some(vp), Some(aoi)) = (state.viewpoint(), state.aoi()) else { return None };
        let grid = source.world.grid;
        let eye = Eye::new(aoi, vp.heading(), DEFAULT_FOV_DEG);
        let refine = eye.refine(view, &grid, source.root_level);
        let tx = &self.tx;
        let node_state = |k: NodeKey| {
            if !k.is_valid() || k.level > source.root_level || !overlaps(&grid, k) {
                return NodeState::Unavailable;
            }
            if let Some(n) = source.world.summaries().locked().peek(k) {
                return NodeState::Ready(n.error);
            }
            if source.asked.len() < MAX_SESSION_NODES && source.asked.insert(k) {
                let tx = tx.clone();
                source.expander.submit_far(FarJob {
                    world: Arc::clone(&source.world),
                    node: k,
                    cancelled: Arc::clone(&source.cancelled),
                    done: Box::new(move || {
                        let _ = tx.send(Some(k));
                    }),
                });
            }
            NodeState::Pending
        };
        if self.dirty && self.rebuilt.is_none_or(|t| now >= t + REBUILD_INTERVAL) {
            self.dirty = false;
            self.rebuilt = Some(now);
            self.selection.rebuild(&refine, &eye, node_state);
        } else if self.selection.is_waiting() {
            self.selection.walk_on(&refine, &eye, node_state);
        }
        let mut nodes = Vec::new();
        self.selection.next(source.root_level, |k| {
            if nodes.len() >= MAX_BATCH_NODES {
                return Take::Stop;
            }
            match source.world.summaries().locked().peek(k) {
                Some(n) => {
                    nodes.push((**n).clone());
                    Take::Node(n.error)
                }
                None => Take::Skip,
            }
        });
        let released = self.selection.releases(MAX_BATCH_RELEASES);
        if self.selection.has_work() {
            // More than one batch: come back.
            let _ = self.tx.send(None);
        }
        if nodes.is_empty() && released.is_empty() {
            return None;
        }
        Some(state.on_summaries(SummaryBatch { nodes, released }))
    }
}
