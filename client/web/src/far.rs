//! The far view computed in the page (sans-IO), as the native connection's `FarField` computes it: the server
//! session's selection ([`FarWalk`], shared with the native client) over a memo of the world's summary nodes
//! ([`Summaries`]), the nodes asked for computed in the page's timer slices — coarsest first, then the oldest, and
//! only while no granted cell waits (the [`crate::session::Session`] checks that) — within the slice's budget, and
//! laid into the state as the server's batches would be. A node above a leaf block is computed a block at a time,
//! so that one step stays short (a block is 16 × 16 cells' leaves); the node itself then only aggregates.
//!
//! Edited cells beyond the area of interest the server tells of (far cells) correct the memo as natively: each is
//! expanded and its edits laid against it in a step of its own, before the nodes, the newest version winning.

use std::cmp::Reverse;
use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::Duration;

use canopy_client::farwalk::FarWalk;
use canopy_client::state::{ClientState, StateError};
use canopy_protocol::CellCoord;
use canopy_protocol::aoi::Grid;
use canopy_protocol::messages::FarCell;
use canopy_protocol::summary::{FarView, NodeKey, root_level};
use canopy_worlds::world::World;
use canopy_worlds::world::far::{LEAF_BLOCK_LEVEL, Summaries, cell_key};

/// The far view's screen-space error, pixels (the native walk's `--far-error` default).
pub(crate) const FAR_ERROR_PX: f32 = 16.0;
/// How far the far view reaches, metres (the native walk's `--far-range` default).
pub(crate) const FAR_RANGE: f32 = 20_000.0;
/// The viewport height the far view is refined for, pixels (the native walk's `--height` default).
pub(crate) const FAR_HEIGHT_PX: u16 = 720;
/// The vertical field of view the far view is refined for, degrees (the native default view's, the page's).
pub(crate) const FAR_FOV_Y_DEG: f32 = 60.0;
/// Most batches laid into the state in one go.
const MAX_BATCHES: usize = 64;
/// Most far cells kept track of (the server tells of the nearest 256 at a time).
const MAX_FAR_CELLS: usize = 4096;

/// The far view the native walk asks for by default, with the eye `altitude` metres over the ground (2 at least).
pub(crate) fn default_view(altitude: f32) -> FarView {
    FarView {
        error_px: FAR_ERROR_PX,
        height_px: FAR_HEIGHT_PX,
        fov_y: FAR_FOV_Y_DEG.to_radians(),
        range: FAR_RANGE,
        altitude: if altitude.is_finite() { altitude.max(2.0) } else { 2.0 },
    }
}

/// The world's nodes and the grid they are keyed on.
struct Source {
    memo: Summaries,
    grid: Grid,
    root_level: u8,
}

/// See the module docs.
#[derive(Default)]
pub struct Far {
    view: Option<FarView>,
    walk: FarWalk<Duration>,
    source: Option<Source>,
    /// Nodes asked for, coarsest first, then the oldest.
    queue: BTreeMap<(Reverse<u8>, u64), NodeKey>,
    asked: u64,
    computed: u64,
    /// Far cells to correct the memo by, oldest first, and the newest version told of each.
    far_cells: VecDeque<FarCell>,
    versions: BTreeMap<CellCoord, u32>,
}

impl std::fmt::Debug for Far {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Far")
            .field("view", &self.view)
            .field("queued", &self.queue.len())
            .field("computed", &self.computed)
            .finish_non_exhaustive()
    }
}

impl Far {
    /// The far view changed.
    pub fn set_view(&mut self, view: FarView) {
        self.view = Some(view);
        self.walk.touch();
    }

    /// The far view set, if any.
    pub fn view(&self) -> Option<&FarView> {
        self.view.as_ref()
    }

    /// The viewpoint moved.
    pub fn moved(&mut self) {
        if self.view.is_some() {
            self.walk.touch();
        }
    }

    /// Whether it computes from a world yet.
    pub fn has_world(&self) -> bool {
        self.source.is_some()
    }

    /// Compute from `world`, whose records are on `grid`, from now on.
    pub fn set_world(&mut self, world: Arc<World>, grid: Grid) {
        let root_level = root_level(grid.cell_size);
        self.source = Some(Source { memo: Summaries::new(world), grid, root_level });
        self.queue.clear();
        self.walk.forget_asked();
        self.walk.touch();
    }

    /// Nodes asked for and not computed yet.
    pub fn queued(&self) -> usize {
        self.queue.len()
    }

    /// Nodes computed (asked for and finished).
    pub fn computed(&self) -> u64 {
        self.computed
    }

    /// Whether a step has nodes to compute or far cells to correct by.
    pub fn busy(&self) -> bool {
        !self.queue.is_empty() || !self.far_cells.is_empty()
    }

    /// An edited cell beyond the area of interest: the memo is corrected by its edits at a coming step, unless a
    /// newer version of it was told already.
    pub fn far_cell(&mut self, f: FarCell) {
        let known = self.versions.contains_key(&f.cell);
        if self.versions.get(&f.cell).is_some_and(|&v| v >= f.version())
            || (!known && self.versions.len() >= MAX_FAR_CELLS)
        {
            return;
        }
        self.versions.insert(f.cell, f.version());
        self.far_cells.retain(|g| g.cell != f.cell);
        self.far_cells.push_back(f);
    }

    /// Whether nothing is left to do: no node to compute, and no whole walk held back by
    /// [`REBUILD_INTERVAL`](canopy_protocol::farview::REBUILD_INTERVAL) (the next step after it takes it).
    pub fn settled(&self) -> bool {
        self.queue.is_empty() && self.far_cells.is_empty() && self.walk.held_back_until().is_none()
    }

    /// One slice at `now` (time since any fixed moment): walk and lay what is ready, then compute asked nodes —
    /// one block or node at least where any is asked, then as long as `more()` says there is time — and lay them.
    /// Returns the nodes computed.
    pub fn step(
        &mut self,
        state: &mut ClientState,
        now: Duration,
        more: &mut dyn FnMut() -> bool,
    ) -> Result<usize, StateError> {
        if self.view.is_none() || self.source.is_none() {
            return Ok(0);
        }
        self.advance(state, now)?;
        let Some(source) = &mut self.source else { return Ok(0) };
        let (mut steps, mut done) = (0, 0);
        // Far cells first: each a cell's expansion (a step of its own), its nodes laid again once computed anew
        // (the walk asks for them).
        let mut corrected = false;
        while !self.far_cells.is_empty() && (steps == 0 || more()) {
            let f = self.far_cells.pop_front().expect("a far cell");
            steps += 1;
            let key = cell_key(f.cell);
            let world = Arc::clone(source.memo.world());
            let edits = world.leaf_edits(key, &world.expand_cell(key), &f.delta);
            if source.memo.correct(key, Some(edits.into())) {
                self.walk.corrected(f.cell);
                corrected = true;
            }
        }
        if corrected {
            self.advance(state, now)?;
        }
        let Some(source) = &mut self.source else { return Ok(0) };
        while let Some((&slot, &k)) = self.queue.first_key_value() {
            if steps > 0 && !more() {
                break;
            }
            steps += 1;
            if compute_step(&mut source.memo, k) {
                self.queue.remove(&slot);
                self.walk.computed(k);
                done += 1;
            }
        }
        self.computed += done as u64;
        if done > 0 {
            self.advance(state, now)?;
        }
        Ok(done)
    }

    /// Walk and lay the batches that are ready.
    fn advance(&mut self, state: &mut ClientState, now: Duration) -> Result<(), StateError> {
        let (Some(view), Some(source)) = (self.view, &self.source) else { return Ok(()) };
        let memo = &source.memo;
        let peek = |k: NodeKey| memo.peek(k).cloned();
        let (queue, asked) = (&mut self.queue, &mut self.asked);
        let mut ask = |k: NodeKey| {
            *asked += 1;
            queue.insert((Reverse(k.level), *asked), k);
        };
        for _ in 0..MAX_BATCHES {
            let a = self.walk.advance(view, state, (&source.grid, source.root_level), now, &peek, &mut ask);
            let laid = a.event.transpose()?.is_some();
            if !(laid && a.more) {
                break;
            }
        }
        Ok(())
    }
}

/// One step towards node `k` in `memo`: the first of its leaf blocks not held yet (a node above
/// [`LEAF_BLOCK_LEVEL`]), else the node itself. Whether the node is held now.
fn compute_step(memo: &mut Summaries, k: NodeKey) -> bool {
    if k.level > LEAF_BLOCK_LEVEL {
        let side = 1i32 << (k.level - LEAF_BLOCK_LEVEL);
        let blocks = (0..side * side).map(|i| NodeKey {
            level: LEAF_BLOCK_LEVEL,
            x: k.x * side + i % side,
            z: k.z * side + i / side,
        });
        // A node already held needs none of its blocks.
        if memo.peek(k).is_none()
            && let Some(b) = blocks.into_iter().find(|&b| memo.peek(b).is_none())
        {
            memo.get(b);
            return false;
        }
    }
    memo.get(k);
    true
}
