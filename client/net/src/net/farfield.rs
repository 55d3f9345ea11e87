//! The far field computed on this client (issue 30, item 5): a connection that expands its cells computes the
//! far-view summary nodes it wants from the same world function, instead of asking the server for them. The
//! selection is the server session's ([`Selection`]: the same nodes, coarse first, a node after its parent), over
//! the world's memo of nodes ([`ExpandWorld::summaries`]), which the expander's workers fill ([`FarJob`]: the
//! coarsest first, a root's subtree with it, and only while no cell waits, as a server's cache does); the nodes
//! reach the state as the server's batches would ([`ClientState::on_summaries`]). A connection that takes records
//! asks the server, as before.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use canopy_protocol::summary::{FarView, NodeKey, root_level};
use canopy_protocol::sync::Locked;
use tokio::sync::mpsc;

use crate::expand::{ExpandWorld, Expander, FarJob};
use crate::farwalk::FarWalk;
use crate::state::{ClientState, Event, StateError};

/// See the module docs.
pub(super) struct FarField {
    /// The far view the client wants, once it said.
    view: Option<FarView>,
    /// The selection and what was asked for (the pure part, shared with the browser client).
    walk: FarWalk<Instant>,
    source: Option<Source>,
    /// Wake-ups: a node computed (`Some`), or the selection has nodes to hand out (`None`).
    tx: mpsc::UnboundedSender<Option<NodeKey>>,
    rx: mpsc::UnboundedReceiver<Option<NodeKey>>,
}

/// Where the nodes come from: the world (and its memo) and the expander computing them.
struct Source {
    world: Arc<ExpandWorld>,
    expander: Arc<Expander>,
    root_level: u8,
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
        FarField { view: None, walk: FarWalk::default(), source: None, tx, rx }
    }

    /// The far view changed.
    pub(super) fn set_view(&mut self, view: FarView) {
        self.view = Some(view);
        self.walk.touch();
        let _ = self.tx.send(None);
    }

    /// The viewpoint moved.
    pub(super) fn moved(&mut self) {
        if self.view.is_some() {
            self.walk.touch();
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
            cancelled: Arc::new(AtomicBool::new(false)),
        });
        self.walk.forget_asked();
        self.walk.touch();
        let _ = self.tx.send(None);
    }

    /// Wait until there may be something to do: a wake-up, or the moment a walk held back by
    /// [`REBUILD_INTERVAL`](canopy_protocol::farview::REBUILD_INTERVAL) is due (pending forever before a far view
    /// and a world).
    pub(super) async fn next(&mut self) -> Option<()> {
        let ready = self.view.is_some() && self.source.is_some();
        let wake = match self.walk.held_back_until().filter(|_| ready) {
            Some(t) => {
                let due = tokio::time::Instant::from_std(t);
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
        if let (Some(k), Some(_)) = (computed, &self.source) {
            self.walk.computed(k);
        }
    }

    /// Walk (again, for a move; on, for computed nodes) and lay the nodes that can go into the state: `None`
    /// when nothing changed.
    pub(super) fn advance(&mut self, state: &mut ClientState, now: Instant) -> Option<Result<Event, StateError>> {
        let (Some(view), Some(source)) = (self.view, &self.source) else { return None };
        let tx = &self.tx;
        let peek = |k: NodeKey| source.world.summaries().locked().peek(k).cloned();
        let mut ask = |k: NodeKey| {
            let tx = tx.clone();
            source.expander.submit_far(FarJob {
                world: Arc::clone(&source.world),
                node: k,
                cancelled: Arc::clone(&source.cancelled),
                done: Box::new(move || {
                    let _ = tx.send(Some(k));
                }),
            });
        };
        let grid = source.world.grid;
        let done = self.walk.advance(view, state, (&grid, source.root_level), now, &peek, &mut ask);
        if done.more {
            // More than one batch: come back.
            let _ = self.tx.send(None);
        }
        done.event
    }
}
