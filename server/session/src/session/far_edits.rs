//! Edited cells beyond the area of interest, for a client that expands cells and computes its far view itself
//! (issue 30, item 5): the nearest [`MAX_FAR_CELLS`] edited cells within its far view's range go to it as
//! [`FarCell`]s (the cell's edits as a delta from version 0), and again whenever their version changes, so that the
//! summary nodes it computes from the world function show the edits. The store says which cells are edited
//! ([`WorldStore::edited_cells`]); a cell told of is told again as soon as it changes; the session looks again when
//! the client moves by an eighth of the range, when another cell within it changes, or when announcements were
//! missed — at most every [`LOOK_INTERVAL`], each look in rings of growing radius until it has found enough (a
//! look's work is bounded by [`MAX_LOOKED`] cells a ring).

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;
use canopy_protocol::edit::CellDelta;
use canopy_protocol::messages::{FarCell, ServerMsgKind, ServerStreaming};
use canopy_protocol::{CellCoord, ServerMsg};

use super::Session;
use crate::store::Changes;
#[cfg(doc)]
use crate::store::WorldStore;
use crate::transmit::{StreamId, Transmit};

/// Most edited cells a session keeps a client's far view told of (the nearest).
pub const MAX_FAR_CELLS: usize = 256;
/// Most edited cells a session reads from the store in one ring of a look (the store's answer is cut there).
const MAX_LOOKED: usize = 4 * MAX_FAR_CELLS;
/// Least time between two looks of a session (edits near a client that come fast are looked at together).
pub(super) const LOOK_INTERVAL: Duration = Duration::from_millis(250);

/// A session's far cells (see the module docs).
#[derive(Debug, Default)]
pub(super) struct FarEdits {
    /// The far view's range, metres.
    range: f32,
    /// The cells told of, or to tell of, with the version told (0: not yet).
    told: BTreeMap<CellCoord, u32>,
    /// Cells to tell of, nearest first.
    queue: VecDeque<CellCoord>,
    /// Where the last look was made from (`None`: look again).
    looked_from: Option<[f32; 2]>,
    /// When the last look was made.
    looked_at: Option<Instant>,
}

impl FarEdits {
    pub(super) fn new(range: f32) -> FarEdits {
        FarEdits { range, ..FarEdits::default() }
    }

    /// The far view's range changed: look again.
    pub(super) fn set_range(&mut self, range: f32) {
        self.range = range;
        self.looked_from = None;
    }

    /// Whether a cell is to be told of.
    pub(super) fn has_work(&self) -> bool {
        !self.queue.is_empty()
    }

    /// When a look held back by [`LOOK_INTERVAL`] is due (`None`: none is held back; a move is seen at the next
    /// poll).
    pub(super) fn look_due(&self) -> Option<Instant> {
        self.looked_from.is_none().then_some(self.looked_at.map(|t| t + LOOK_INTERVAL)).flatten()
    }

    /// Cells told of (for tests).
    pub(super) fn told(&self) -> impl Iterator<Item = (CellCoord, u32)> + '_ {
        self.told.iter().map(|(c, v)| (*c, *v))
    }
}

impl Session {
    /// A cell changed: one told of already is told again at once (if its version moved); else, if it may be
    /// within the far view's range, look again.
    pub(super) fn far_cell_changed(&mut self, c: CellCoord) {
        let (Some(far), Some(vp)) = (&mut self.far_edits, self.viewpoint) else { return };
        if far.told.contains_key(&c) {
            if !far.queue.contains(&c) {
                far.queue.push_front(c);
            }
            return;
        }
        let grid = self.store.grid();
        if grid.centre_distance2(c, vp.position).sqrt() <= far.range + grid.cell_size {
            far.looked_from = None;
        }
    }

    /// Changes were missed: look again.
    pub(super) fn far_changes_missed(&mut self) {
        if let Some(far) = &mut self.far_edits {
            far.looked_from = None;
        }
    }

    /// Look for the edited cells within range if due: the nearest [`MAX_FAR_CELLS`] outside the area of interest
    /// (cells in it are granted with their edits), those whose version the client was not told queued.
    pub(super) fn look_for_far_cells(&mut self, now: Instant) {
        let (Some(far), Some(vp), Some(aoi)) = (&mut self.far_edits, self.viewpoint, self.aoi) else { return };
        let at = vp.position;
        let moved = far.looked_from.is_none_or(|p| (p[0] - at[0]).hypot(p[1] - at[1]) > far.range / 8.0);
        if !moved || far.looked_at.is_some_and(|t| now < t + LOOK_INTERVAL) {
            if moved {
                far.looked_from = None;
            }
            return;
        }
        (far.looked_from, far.looked_at) = (Some(at), Some(now));
        let store = Arc::clone(&self.store);
        let grid = store.grid();
        let centre = grid.cell_of(at[0], at[1]);
        // Rings of growing radius, the nearest first, until enough are found or the range is covered.
        let mut found: Vec<(f32, CellCoord, u32)> = Vec::new();
        for radius in [far.range / 8.0, far.range / 4.0, far.range / 2.0, far.range] {
            let reach = (radius / grid.cell_size).ceil() as i32 + 1;
            let lo = CellCoord::new(centre.x.saturating_sub(reach), centre.z.saturating_sub(reach));
            let hi = CellCoord::new(centre.x.saturating_add(reach), centre.z.saturating_add(reach));
            let r2 = radius * radius;
            found = store
                .edited_cells(lo, hi, MAX_LOOKED)
                .into_iter()
                .filter(|(c, _)| !aoi.is_kept(grid, *c))
                .filter_map(|(c, version)| {
                    let d2 = grid.centre_distance2(c, at);
                    (d2 <= r2).then_some((d2, c, version))
                })
                .collect();
            if found.len() >= MAX_FAR_CELLS {
                break;
            }
        }
        found.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        found.truncate(MAX_FAR_CELLS);
        let told: BTreeMap<CellCoord, u32> =
            found.iter().map(|&(_, c, _)| (c, far.told.get(&c).copied().unwrap_or(0))).collect();
        far.queue = found.iter().filter(|&&(_, c, version)| told[&c] != version).map(|&(_, c, _)| c).collect();
        far.told = told;
    }

    /// The next far cell to send, on the last lane: `None` when there is none, or the nearest waits for the store
    /// (its waker is registered).
    pub(super) fn next_far_cell(&mut self) -> Option<Transmit> {
        let store = Arc::clone(&self.store);
        let lane = self.cfg.lanes - 1;
        loop {
            let far = self.far_edits.as_mut()?;
            let &c = far.queue.front()?;
            match store.changes(c, 0, self.waker.as_ref()) {
                Changes::Pending => return None,
                // Told of this version already (announced again).
                Changes::Delta(d) if far.told.get(&c) == Some(&d.to_version) => {
                    far.queue.pop_front();
                }
                Changes::Delta(d) => {
                    far.queue.pop_front();
                    far.told.insert(c, d.to_version);
                    let delta = CellDelta { grant: 0, ..d };
                    let msg = ServerMsg::Streaming(ServerStreaming::FarCell(FarCell { cell: c, delta }));
                    let bytes = Bytes::from(msg.encode_framed());
                    let t = Transmit {
                        stream: StreamId::Lane(lane),
                        bytes,
                        body: Bytes::new(),
                        class: ServerMsgKind::FarCell,
                        records: 0,
                    };
                    return Some(t);
                }
                // Unedited after all (the store's index ran ahead of its logs), or more edits than a delta can
                // carry from version 0: nothing to tell now (the cell is looked at again when it changes).
                Changes::Current { .. } | Changes::Whole => {
                    far.queue.pop_front();
                }
            }
        }
    }

    /// The edited cells beyond the area of interest this client was told of, with their versions (0: not yet).
    pub fn far_cells(&self) -> Vec<(CellCoord, u32)> {
        self.far_edits.as_ref().map(|f| f.told().collect()).unwrap_or_default()
    }
}

/// What [`WorldStore::edited_cells`] answers, for stores that keep an index of edited cells.
pub fn cells_in(index: &BTreeMap<CellCoord, u32>, lo: CellCoord, hi: CellCoord, max: usize) -> Vec<(CellCoord, u32)> {
    let mut out: Vec<(&CellCoord, &u32)> = Vec::new();
    if lo.x > hi.x || lo.z > hi.z {
        return Vec::new();
    }
    // Column by column (cells order by x, then z), or over the whole index where it is smaller than the columns.
    if index.len() <= (hi.x - lo.x) as usize + 1 {
        out.extend(
            index.iter().filter(|(c, _)| (lo.x..=hi.x).contains(&c.x) && (lo.z..=hi.z).contains(&c.z)).take(max),
        );
    } else {
        for x in lo.x..=hi.x {
            out.extend(index.range(CellCoord::new(x, lo.z)..=CellCoord::new(x, hi.z)).take(max - out.len()));
            if out.len() >= max {
                break;
            }
        }
    }
    out.into_iter().map(|(c, v)| (*c, *v)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_in_a_rectangle_by_columns_or_by_scan() {
        let index: BTreeMap<CellCoord, u32> =
            [(0, 0), (1, 5), (2, 2), (3, -1), (40, 3)].iter().map(|&(x, z)| (CellCoord::new(x, z), 1)).collect();
        let got = |lo: (i32, i32), hi: (i32, i32), max| {
            cells_in(&index, CellCoord::new(lo.0, lo.1), CellCoord::new(hi.0, hi.1), max)
                .into_iter()
                .map(|(c, _)| (c.x, c.z))
                .collect::<Vec<_>>()
        };
        // Fewer cells than columns: a scan; more: column by column. The same answer.
        assert_eq!(got((0, 0), (3, 4), 10), vec![(0, 0), (2, 2)]);
        assert_eq!(got((0, 0), (1, 5), 10), vec![(0, 0), (1, 5)]);
        assert_eq!(got((-100, -100), (100, 100), 3).len(), 3);
        assert!(got((5, 5), (4, 4), 10).is_empty());
    }
}
