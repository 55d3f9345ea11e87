//! The far view's walk on a client that computes its own summary nodes (issue 30, item 5), without threads or a
//! clock: the server session's [`Selection`] over whatever memo of nodes the client has, asking for the nodes it
//! lacks (at most [`MAX_SESSION_NODES`] asked at once) and laying the nodes that can go into the state as the
//! server's batches would ([`ClientState::on_summaries`]). The native connection (`net/farfield.rs`) computes the
//! asked nodes on the expander's workers; the browser page (`canopy-web`) in its timer's slices. The time is the
//! caller's (`T`: an `Instant`, or a `Duration` since the page started).

use std::collections::BTreeSet;
use std::ops::Add;
use std::sync::Arc;
use std::time::Duration;

use canopy_protocol::CellCoord;
use canopy_protocol::aoi::Grid;
use canopy_protocol::farview::{DEFAULT_FOV_DEG, Eye, MAX_SESSION_NODES, NodeState, REBUILD_INTERVAL, Selection, Take};
use canopy_protocol::summary::{
    FarView, MAX_BATCH_NODES, MAX_BATCH_RELEASES, NodeKey, NodeSummary, SummaryBatch, overlaps,
};

use crate::state::{ClientState, Event, StateError};

/// See the module docs.
#[derive(Debug)]
pub struct FarWalk<T> {
    selection: Selection,
    /// Nodes asked for and not computed yet (at most [`MAX_SESSION_NODES`]).
    asked: BTreeSet<NodeKey>,
    /// The viewpoint, the far view or the source changed since the last whole walk.
    dirty: bool,
    rebuilt: Option<T>,
}

impl<T> Default for FarWalk<T> {
    fn default() -> FarWalk<T> {
        FarWalk { selection: Selection::default(), asked: BTreeSet::new(), dirty: false, rebuilt: None }
    }
}

/// What one [`FarWalk::advance`] did.
#[derive(Debug)]
pub struct Advanced {
    /// The batch laid into the state (`None`: nothing changed).
    pub event: Option<Result<Event, StateError>>,
    /// More than one batch was ready: advance again.
    pub more: bool,
}

impl<T: Copy + PartialOrd + Add<Duration, Output = T>> FarWalk<T> {
    /// Walk the whole tree again at the next advance (held back to one walk every [`REBUILD_INTERVAL`]): the
    /// viewpoint moved, the far view changed, or the nodes come from another source now.
    pub fn touch(&mut self) {
        self.dirty = true;
    }

    /// When a whole walk held back by [`REBUILD_INTERVAL`] is due (`None`: none is held back).
    pub fn held_back_until(&self) -> Option<T> {
        self.rebuilt.filter(|_| self.dirty).map(|t| t + REBUILD_INTERVAL)
    }

    /// Forget what was asked for (the source that was to compute it is gone).
    pub fn forget_asked(&mut self) {
        self.asked.clear();
    }

    /// Node `k` asked for is computed (or will not be).
    pub fn computed(&mut self, k: NodeKey) {
        self.asked.remove(&k);
    }

    /// The memo's nodes holding `cell` changed (its edits corrected them): every one the state holds is laid into
    /// it again, computed anew, at the next advances ([`Selection::stale`]).
    pub fn corrected(&mut self, cell: CellCoord) {
        self.selection.stale(cell);
    }

    /// Nodes asked for and not computed yet.
    pub fn asked(&self) -> usize {
        self.asked.len()
    }

    /// Walk (again, for a move; on, for computed nodes) for `view` over `grid`, whose roots are at `root_level`,
    /// and lay the nodes that can go into `state`. `peek` says what the memo holds; `ask` is called once for each
    /// node wanted and not computed (until [`FarWalk::computed`]).
    pub fn advance(
        &mut self,
        view: FarView,
        state: &mut ClientState,
        (grid, root_level): (&Grid, u8),
        now: T,
        peek: &dyn Fn(NodeKey) -> Option<Arc<NodeSummary>>,
        ask: &mut dyn FnMut(NodeKey),
    ) -> Advanced {
        let none = Advanced { event: None, more: false };
        let (Some(vp), Some(aoi)) = (state.viewpoint(), state.aoi()) else { return none };
        let eye = Eye::new(aoi, vp.heading(), DEFAULT_FOV_DEG);
        let refine = eye.refine(view, grid, root_level);
        let asked = &mut self.asked;
        let node_state = |k: NodeKey| {
            if !k.is_valid() || k.level > root_level || !overlaps(grid, k) {
                return NodeState::Unavailable;
            }
            if let Some(n) = peek(k) {
                return NodeState::Ready(n.error);
            }
            if asked.len() < MAX_SESSION_NODES && asked.insert(k) {
                ask(k);
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
        self.selection.next(root_level, |k| {
            if nodes.len() >= MAX_BATCH_NODES {
                return Take::Stop;
            }
            match peek(k) {
                Some(n) => {
                    let error = n.error;
                    nodes.push(Arc::unwrap_or_clone(n));
                    Take::Node(error)
                }
                None => Take::Skip,
            }
        });
        let released = self.selection.releases(MAX_BATCH_RELEASES);
        let more = self.selection.has_work();
        if nodes.is_empty() && released.is_empty() {
            return Advanced { event: None, more };
        }
        Advanced { event: Some(state.on_summaries(SummaryBatch { nodes, released })), more }
    }
}
