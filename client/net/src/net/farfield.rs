//! The far field computed on this client (issue 30, item 5): a connection that expands its cells computes the
//! far-view summary nodes it wants from the same world function, instead of asking the server for them. The
//! selection is the server session's ([`Selection`]: the same nodes, coarse first, a node after its parent), over
//! a memo of nodes computed on a thread of this connection (coarsest request first; a root computes the subtree it
//! covers, so its descendants follow from the memo; cells go first: it computes only while no cell waits for the
//! expander, as a server's cache does); the nodes reach the state as the server's batches would
//! ([`ClientState::on_summaries`]). A connection that takes records asks the server, as before.

use std::cmp::Reverse;
use std::collections::BTreeSet;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use canopy_protocol::farview::{DEFAULT_FOV_DEG, Eye, MAX_SESSION_NODES, NodeState, REBUILD_INTERVAL, Selection, Take};
use canopy_protocol::summary::{
    FarView, MAX_BATCH_NODES, MAX_BATCH_RELEASES, NodeKey, SummaryBatch, overlaps, root_level,
};
use canopy_protocol::sync::{Locked, Waited};
use canopy_worlds::world::far::Summaries;
use tokio::sync::mpsc;

use crate::expand::{ExpandWorld, Expander};
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
    /// Says that a node was computed (or that the selection has nodes to hand out).
    tx: mpsc::UnboundedSender<()>,
    rx: mpsc::UnboundedReceiver<()>,
}

/// Where the nodes come from: the world and its memo, and the thread computing what the walks ask for.
struct Source {
    world: Arc<ExpandWorld>,
    memo: Arc<Mutex<Summaries>>,
    root_level: u8,
    requests: Arc<Requests>,
}

/// Nodes asked for, coarsest first, and whether the connection is gone.
#[derive(Default)]
struct Requests {
    queue: Mutex<Asked>,
    ready: Condvar,
}

/// The nodes asked for (coarsest first) and whether the connection is gone.
type Asked = (BTreeSet<(Reverse<u8>, NodeKey)>, bool);

impl Drop for Source {
    fn drop(&mut self) {
        self.requests.queue.locked().1 = true;
        self.requests.ready.notify_all();
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
        let _ = self.tx.send(());
    }

    /// The viewpoint moved.
    pub(super) fn moved(&mut self) {
        if self.view.is_some() {
            self.dirty = true;
            let _ = self.tx.send(());
        }
    }

    /// Whether it computes from a world yet.
    pub(super) fn has_source(&self) -> bool {
        self.source.is_some()
    }

    /// Compute from `world` from now on (once the connection has built it), sharing `memo` with whoever computes
    /// the same world, whenever no cell waits for `cells`.
    pub(super) fn set_world(&mut self, world: &Arc<ExpandWorld>, memo: Arc<Mutex<Summaries>>, cells: Arc<Expander>) {
        if self.source.as_ref().is_some_and(|s| Arc::ptr_eq(&s.world, world)) {
            return;
        }
        let requests = Arc::new(Requests::default());
        let (r, m, tx) = (Arc::clone(&requests), Arc::clone(&memo), self.tx.clone());
        let spawned = std::thread::Builder::new().name("canopy-far".into()).spawn(move || compute(&r, &m, &cells, &tx));
        if spawned.is_err() {
            return;
        }
        let root_level = root_level(world.grid.cell_size);
        self.source = Some(Source { world: Arc::clone(world), memo, root_level, requests });
        self.dirty = true;
        let _ = self.tx.send(());
    }

    /// Wait until there may be something to do: a wake-up, or the moment a walk held back by
    /// [`REBUILD_INTERVAL`] is due (pending forever before a far view and a world).
    pub(super) async fn next(&mut self) -> Option<()> {
        let held_back = self.dirty && self.view.is_some() && self.source.is_some();
        match self.rebuilt.filter(|_| held_back) {
            Some(t) => {
                let due = tokio::time::Instant::from_std(t + REBUILD_INTERVAL);
                tokio::select! {
                    r = self.rx.recv() => r,
                    () = tokio::time::sleep_until(due) => Some(()),
                }
            }
            None => self.rx.recv().await,
        }
    }

    /// Whether a wake-up is already there.
    pub(super) fn try_next(&mut self) -> bool {
        self.rx.try_recv().is_ok()
    }

    /// Walk (again, for a move; on, for computed nodes) and lay the nodes that can go into the state: `None`
    /// when nothing changed.
    pub(super) fn advance(&mut self, state: &mut ClientState, now: Instant) -> Option<Result<Event, StateError>> {
        let (Some(view), Some(source)) = (self.view, &self.source) else { return None };
        let (Some(vp), Some(aoi)) = (state.viewpoint(), state.aoi()) else { return None };
        let grid = source.world.grid;
        let eye = Eye::new(aoi, vp.heading(), DEFAULT_FOV_DEG);
        let refine = eye.refine(view, &grid, source.root_level);
        let node_state = |k: NodeKey| {
            if !k.is_valid() || k.level > source.root_level || !overlaps(&grid, k) {
                return NodeState::Unavailable;
            }
            if let Some(n) = source.memo.locked().peek(k) {
                return NodeState::Ready(n.error);
            }
            let mut q = source.requests.queue.locked();
            if q.0.len() < MAX_SESSION_NODES {
                q.0.insert((Reverse(k.level), k));
                source.requests.ready.notify_one();
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
            match source.memo.locked().peek(k) {
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
            let _ = self.tx.send(());
        }
        if nodes.is_empty() && released.is_empty() {
            return None;
        }
        Some(state.on_summaries(SummaryBatch { nodes, released }))
    }
}

/// How long the computing thread waits for the expander's queue to empty before it looks again.
const CELLS_FIRST: Duration = Duration::from_millis(2);

/// The computing thread: the coarsest node asked for, into the memo, once no cell waits, until the connection is
/// gone.
fn compute(requests: &Requests, memo: &Mutex<Summaries>, cells: &Expander, tx: &mpsc::UnboundedSender<()>) {
    loop {
        while cells.queued() > 0 {
            if requests.queue.locked().1 {
                return;
            }
            std::thread::sleep(CELLS_FIRST);
        }
        let key = {
            let mut q = requests.queue.locked();
            loop {
                if q.1 {
                    return;
                }
                if let Some((_, k)) = q.0.pop_first() {
                    break k;
                }
                q = requests.ready.waited(q);
            }
        };
        if memo.locked().peek(key).is_none() {
            Summaries::get_shared(memo, key);
        }
        if tx.send(()).is_err() {
            return;
        }
    }
}
