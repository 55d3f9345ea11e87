//! A session's edits and the changes of held cells: edits handed to the writer and their answers, and what
//! changed in a held cell sent as a delta from the version the client holds (or the cell again, whole).

use std::collections::BTreeSet;
use std::sync::Arc;

use canopy_protocol::CellCoord;
use canopy_protocol::ServerMsg;
use canopy_protocol::edit::{EditOp, EditOutcome, EditResult};
use canopy_protocol::messages::ServerStreaming;

use super::Session;
use crate::editors::Editor;
use crate::store::Changes;
use crate::transmit::StreamId;

impl Session {
    /// The editor this session edits as (`None`: read-only).
    pub fn editor(&self) -> Option<&Arc<Editor>> {
        self.editor.as_ref()
    }

    /// The next edit to hand to the writer, with the editor it is made as; answer it with
    /// [`Session::on_edit_result`].
    pub fn poll_edit(&mut self) -> Option<(u32, EditOp, Arc<Editor>)> {
        let editor = Arc::clone(self.editor.as_ref()?);
        let (request, op) = self.edits_out.pop_front()?;
        Some((request, op, editor))
    }

    /// The writer answered edit `request`: tell the client.
    pub fn on_edit_result(&mut self, request: u32, outcome: EditOutcome) {
        self.edits_in_flight = self.edits_in_flight.saturating_sub(1);
        self.answer(request, outcome);
    }

    pub(super) fn answer(&mut self, request: u32, outcome: EditOutcome) {
        let msg = ServerMsg::Streaming(ServerStreaming::EditResult(EditResult { request, outcome }));
        self.urgent.push_back(Self::transmit(StreamId::Control, &msg));
    }

    /// Cell `c` changed (it is at a newer version now): if the client holds it, it gets what changed once the
    /// cell's batches are out.
    pub fn on_cell_changed(&mut self, c: CellCoord) {
        if self.held.contains_key(&c) {
            self.changed.0.insert(c);
            self.changed.1 = None;
        }
        self.far_cell_changed(c);
    }

    /// Changes were missed (the announcements overflowed): look at every held cell.
    pub fn on_changes_missed(&mut self) {
        self.changed.0.extend(self.held.keys().copied());
        self.changed.1 = None;
        self.far_changes_missed();
    }

    /// Send what changed in held cells whose batches are all out: a delta from the client's version, or the
    /// whole cell again under a new grant when no delta can be made.
    pub(super) fn send_changes(&mut self) {
        let store = Arc::clone(&self.store);
        let generation = store.generation();
        if self.changed.0.is_empty() || self.changed.1 == Some(generation) {
            return;
        }
        self.changed.1 = Some(generation);
        let cells: Vec<CellCoord> = self.changed.0.iter().copied().collect();
        for cell in cells {
            let Some(h) = self.held.get(&cell).copied() else {
                self.changed.0.remove(&cell);
                continue;
            };
            // The grant's batches first: its delta follows them on its lane.
            if h.sent < h.total || self.staged.iter().any(|(c, _)| *c == cell) {
                continue;
            }
            match store.changes(cell, h.version, self.waker.as_ref()) {
                Changes::Pending => continue,
                Changes::Current { total } => {
                    let held = self.held.get_mut(&cell).expect("held");
                    (held.sent, held.total) = (total, total);
                }
                Changes::Delta(mut d) => {
                    d.grant = h.grant;
                    // Species of planted instances go first, on the same lane, if the client lacks them.
                    for species in d.adds.iter().map(|a| a.record.species).collect::<BTreeSet<u8>>() {
                        self.send_species_once(species, StreamId::Lane(h.lane));
                    }
                    let held = self.held.get_mut(&cell).expect("held");
                    (held.sent, held.total, held.version) = (d.total, d.total, d.to_version);
                    self.stats.deltas += 1;
                    let msg = ServerMsg::Streaming(ServerStreaming::Delta(d));
                    self.urgent.push_back(Self::transmit(StreamId::Lane(h.lane), &msg));
                }
                Changes::Whole => {
                    self.release(cell);
                    self.dirty = true;
                }
            }
            self.changed.0.remove(&cell);
        }
    }
}
