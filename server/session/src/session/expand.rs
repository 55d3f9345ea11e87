//! A session whose client expands cells itself ([`CellMode::Expand`]): the world function and every species
//! first, grants in place of batches, the cells it asks records for, and its digests checked against the store.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Instant;

use bytes::Bytes;
use canopy_protocol::edit::CellDelta;
use canopy_protocol::messages::{
    CellDigest, CellGrant, CellMode, MessageError, ServerMsgKind, ServerStreaming, cell_digest,
};
use canopy_protocol::{CellCoord, ServerMsg};

use super::{Held, MAX_DIGESTS_WAITING, MAX_RECORD_CELLS, Session, SessionError};
use crate::store::{CellState, Changes, VersionState, WorldStore};
use crate::transmit::{StreamId, Transmit};

impl Session {
    /// After the ready: a client that expands cells (where the store offers a world function) gets the function
    /// (unless it holds it) and every species, first.
    pub(super) fn start_expanding(&mut self, cells: CellMode) {
        let (CellMode::Expand { have_function }, Some(function)) = (cells, self.store.function_frame()) else {
            return;
        };
        self.expand = true;
        if !have_function {
            let t = Transmit {
                stream: StreamId::Lane(0),
                bytes: function,
                body: Bytes::new(),
                class: ServerMsgKind::Function,
                records: 0,
            };
            self.urgent.push_back(t);
        }
        for id in 0..self.store.species().len() {
            self.send_species_once(id as u8, StreamId::Lane(0));
        }
    }

    /// The client asks for cell `c`'s records in place of its grant: the cell is granted again, as records. At most
    /// as often as viewpoints.
    pub(super) fn on_records(&mut self, now: Instant, c: CellCoord) -> Result<(), SessionError> {
        self.take_request(now)?;
        if self.expand && self.record_cells.len() < MAX_RECORD_CELLS && self.record_cells.insert(c) {
            self.release(c);
            self.dirty = true;
        }
        Ok(())
    }

    /// A digest of the client's expansion of a cell, checked when the store has the cell
    /// ([`Session::check_digests`]). Each may cost the server a cell's expansion: the same budget as viewpoints.
    pub(super) fn on_digest(&mut self, now: Instant, d: CellDigest) -> Result<(), SessionError> {
        self.take_request(now)?;
        if !self.store.grid().contains(d.cell) {
            return Err(SessionError::Message(MessageError::Edit("digest of a cell outside the world")));
        }
        // A digest of a cell not held at that version (released since, or changed) is stale: not checked.
        let held = self.held.get(&d.cell).is_some_and(|h| h.expanded && h.version == d.version);
        self.stats.digests_stale += u64::from(!held);
        if held && self.digests.0.len() < MAX_DIGESTS_WAITING {
            self.digests.0.push_back(d);
            self.digests.1 = None;
        }
        Ok(())
    }

    /// Grant queued cell `cell` to a client that expands it: its version, and for an edited cell the delta from
    /// version 0. `Some(true)`: granted (staged on the cell's lane and paced like a batch); `Some(false)`: the store
    /// does not know yet (the waker is registered); `None`: no delta can be made, send records.
    pub(super) fn grant(&mut self, store: &dyn WorldStore, cell: CellCoord, key: f32) -> Option<bool> {
        let delta = match store.version(cell, self.waker.as_ref()) {
            VersionState::Pending => return Some(false),
            VersionState::Unedited => None,
            VersionState::Edited => match store.changes(cell, 0, self.waker.as_ref()) {
                Changes::Pending => return Some(false),
                Changes::Current { .. } => None,
                Changes::Delta(d) => Some(d),
                Changes::Whole => return None,
            },
            VersionState::Outside => unreachable!("queued cells are in the grid"),
        };
        let grant = self.next_grant;
        self.next_grant = self.next_grant.wrapping_add(1).max(1);
        self.stats.grants += 1;
        self.stats.expand_grants += 1;
        let lane = self.lane_for(key);
        let (version, total) = delta.as_ref().map_or((0, 0), |d| (d.to_version, d.total));
        self.held.insert(cell, Held { grant, lane, sent: total, total, version, expanded: true });
        let delta = delta.map(|d| CellDelta { grant, ..d });
        let msg = ServerMsg::Streaming(ServerStreaming::Grant(CellGrant { cell, grant, version, delta }));
        self.staged.push_back((cell, Self::transmit(StreamId::Lane(lane), &msg)));
        Some(true)
    }

    /// Check the client's digests of its expansions against the store's cells (expanded for it where they are not
    /// already): a cell that differs is counted and granted again as records.
    pub(super) fn check_digests(&mut self) {
        let store = Arc::clone(&self.store);
        let generation = store.generation();
        if self.digests.0.is_empty() || self.digests.1 == Some(generation) {
            return;
        }
        self.digests.1 = Some(generation);
        let mut waiting = VecDeque::new();
        while let Some(d) = self.digests.0.pop_front() {
            // A digest of a grant since released, or of an older version, is stale.
            if !self.held.get(&d.cell).is_some_and(|h| h.expanded && h.version == d.version) {
                continue;
            }
            let data = match store.cell(d.cell, self.waker.as_ref()) {
                CellState::Ready(data) => data,
                CellState::Pending => {
                    waiting.push_back(d);
                    continue;
                }
                CellState::Outside => continue,
            };
            if data.version != d.version {
                continue;
            }
            self.stats.digests_checked += 1;
            if cell_digest(&data.records, &data.overrides, data.felled.iter().copied()) != d.digest {
                self.stats.digest_mismatches += 1;
                if self.record_cells.len() < MAX_RECORD_CELLS {
                    self.record_cells.insert(d.cell);
                    self.release(d.cell);
                    self.dirty = true;
                }
            }
        }
        self.digests.0 = waiting;
    }
}
