//! The far field computed on this client (issue 30, item 5): a connection that expands its cells computes the
//! far-view summary nodes it wants from the same world function, instead of asking the server for them. The
//! selection is the server session's ([`Selection`]: the same nodes, coarse first, a node after its parent), over
//! the world's memo of nodes ([`ExpandWorld::summaries`]), which the expander's workers fill ([`FarJob`]: the
//! coarsest first, a root's subtree with it, and only while no cell waits, as a server's cache does); the nodes
//! reach the state as the server's batches would ([`ClientState::on_summaries`]). A connection that takes records
//! asks the server, as before.
//!
//! Edits reach the far view as **far cells**: the server tells this client of the edited cells within its far
//! view's range beyond its area of interest, each with its edits from version 0 ([`FarCell`]). A blocking task
//! expands the cell from the world function and lays the edits against it ([`World::leaf_edits`]); the memo's
//! nodes holding the cell are corrected by them ([`Summaries::correct`]), and the walk lays those the state holds
//! into it again ([`FarWalk::corrected`]). A cell's newest version wins.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use canopy_protocol::CellCoord;
use canopy_protocol::messages::FarCell;
use canopy_protocol::summary::{FarView, NodeKey, root_level};
use canopy_protocol::sync::Locked;
use canopy_worlds::world::far::{LeafEdit, cell_key};
#[cfg(doc)]
use canopy_worlds::world::{Summaries, World};
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
    tx: mpsc::UnboundedSender<Wake>,
    rx: mpsc::UnboundedReceiver<Wake>,
    /// Far cells by cell: the newest version told (at most [`MAX_FAR_CELLS`]).
    far_cells: BTreeMap<CellCoord, u32>,
    /// Far cells told before the world was built, to correct by once it is.
    early: Vec<FarCell>,
}

/// Most far cells a connection keeps track of (the server tells of the nearest 256 at a time).
const MAX_FAR_CELLS: usize = 4096;

/// What wakes the far field.
enum Wake {
    /// The selection has nodes to hand out.
    Walk,
    /// A node asked for is computed.
    Node(NodeKey),
    /// A far cell's edits were laid against its expansion: its version and the leaf edits.
    Corrected(CellCoord, u32, Arc<[LeafEdit]>),
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
        let (far_cells, early) = (BTreeMap::new(), Vec::new());
        FarField { view: None, walk: FarWalk::default(), source: None, tx, rx, far_cells, early }
    }

    /// An edited cell beyond the area of interest: correct the far view by its edits (on a blocking task: it
    /// expands the cell), unless a newer version of it was told already.
    pub(super) fn far_cell(&mut self, f: FarCell) {
        let version = f.version();
        let newest = self.far_cells.get(&f.cell).is_none_or(|&v| v < version);
        if !newest || (self.far_cells.len() >= MAX_FAR_CELLS && !self.far_cells.contains_key(&f.cell)) {
            return;
        }
        self.far_cells.insert(f.cell, version);
        let Some(source) = &self.source else {
            self.early.push(f);
            return;
        };
        let (world, tx) = (Arc::clone(&source.world), self.tx.clone());
        tokio::task::spawn_blocking(move || {
            let key = cell_key(f.cell);
            let base = world.world.expand_cell(key);
            let edits: Arc<[LeafEdit]> = world.world.leaf_edits(key, &base, &f.delta).into();
            let _ = tx.send(Wake::Corrected(f.cell, version, edits));
        });
    }

    /// The far view changed.
    pub(super) fn set_view(&mut self, view: FarView) {
        self.view = Some(view);
        self.walk.touch();
        let _ = self.tx.send(Wake::Walk);
    }

    /// The viewpoint moved.
    pub(super) fn moved(&mut self) {
        if self.view.is_some() {
            self.walk.touch();
            let _ = self.tx.send(Wake::Walk);
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
        let _ = self.tx.send(Wake::Walk);
        for f in std::mem::take(&mut self.early) {
            self.far_cells.remove(&f.cell);
            self.far_cell(f);
        }
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
                    () = tokio::time::sleep_until(due) => Some(Wake::Walk),
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

    fn woken(&mut self, wake: Wake) {
        let Some(source) = &self.source else { return };
        match wake {
            Wake::Walk => {}
            Wake::Node(k) => self.walk.computed(k),
            Wake::Corrected(cell, version, edits) => {
                // An older version's task finishing late is not laid over a newer one. The memo may hold this
                // version already (another connection of the process was told of it): the nodes held here are
                // laid again all the same.
                if self.far_cells.get(&cell) == Some(&version) && source.world.correct(cell, version, edits) {
                    self.walk.corrected(cell);
                }
            }
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
                    let _ = tx.send(Wake::Node(k));
                }),
            });
        };
        let grid = source.world.grid;
        let done = self.walk.advance(view, state, (&grid, source.root_level), now, &peek, &mut ask);
        if done.more {
            // More than one batch: come back.
            let _ = self.tx.send(Wake::Walk);
        }
        done.event
    }
}
