//! Live edits and resuming: asking for edits, applying the server's deltas to held cells, asking for a cell again
//! after a gap, and carrying the complete cells of an earlier session into a new one (resume messages).

use std::collections::HashMap;
use std::sync::Arc;

use canopy_protocol::edit::{CellDelta, Edit, EditOp, Resume, ResumeCell};
use canopy_protocol::messages::{ClientStreaming, WorldInfo};
use canopy_protocol::record::ParamOverride;
use canopy_protocol::{CellCoord, ClientMsg, SpeciesGraph};

use super::{ClientState, Event, HeldCell, StateError};

/// What a resuming session keeps of an earlier one: its world, species table and graphs, and complete cells.
#[derive(Clone, Debug)]
pub(super) struct Resumable {
    world: WorldInfo,
    table: Vec<canopy_protocol::messages::SpeciesEntry>,
    species: Vec<Option<Arc<SpeciesGraph>>>,
    cells: HashMap<CellCoord, HeldCell>,
}

impl ClientState {
    /// A session that resumes `previous` (an earlier session of a server of the same world, say one that went
    /// away): if the welcome describes the same world, the cells it held in full are named in resume messages
    /// ([`ClientState::resume`]) and kept, and the server sends only what changed since their versions.
    pub fn resuming(previous: ClientState) -> ClientState {
        let mut s = ClientState::new();
        if let Some(w) = &previous.welcome {
            let cells = previous.cells.into_iter().filter(|(_, h)| h.is_complete()).collect();
            let (world, table, species) = (w.world.clone(), w.species.clone(), previous.species);
            s.resumable = Some(Resumable { world, table, species, cells });
        }
        // Edit requests go on numbering where the earlier session stopped: an answer lost with it is never taken
        // for a new request's.
        s.next_request = previous.next_request;
        s
    }

    /// The resume messages to send after the welcome and before [`ClientState::ready`] (none for a fresh
    /// session, or when the world differs). The cells named take grants 1, 2, … in cell order, as the server
    /// numbers them.
    pub fn resume(&mut self) -> Result<Vec<ClientMsg>, StateError> {
        let Some(Resumable { world, table, species, mut cells }) = self.resumable.take() else { return Ok(Vec::new()) };
        let Some(w) = self.welcome.clone() else { return Ok(Vec::new()) };
        if world != w.world {
            return Ok(Vec::new());
        }
        if table == w.species {
            // The same species table: the graphs held are the ones it names.
            for (id, g) in species.into_iter().enumerate() {
                if let Some(g) = g {
                    self.preload_species(id as u8, g);
                }
            }
        }
        let mut order: Vec<CellCoord> = cells.keys().copied().filter(|c| w.world.grid.contains(*c)).collect();
        order.sort_unstable();
        order.truncate(canopy_protocol::netlimits::MAX_RESUME_CELLS);
        let mut msgs = Vec::new();
        for chunk in order.chunks(canopy_protocol::netlimits::MAX_RESUME_PER_MESSAGE) {
            let named = chunk.iter().map(|c| ResumeCell { cell: *c, version: cells[c].version }).collect();
            let msg = ClientMsg::Handshake(canopy_protocol::messages::ClientHandshake::Resume(Resume { cells: named }));
            self.phase = msg.next_phase(self.phase)?;
            msgs.push(msg);
        }
        for (i, c) in order.iter().enumerate() {
            let mut h = cells.remove(c).expect("named above");
            h.grant = i as u32 + 1;
            // The server sends what changed since the version named: nothing is asked for again.
            h.refreshing = false;
            self.cells.insert(*c, h);
        }
        Ok(msgs)
    }

    /// The message asking for an edit, and the request number its
    /// [`EditResult`](canopy_protocol::edit::EditResult) will carry.
    pub fn edit(&mut self, op: EditOp) -> Result<(u32, ClientMsg), StateError> {
        let request = self.next_request;
        self.next_request = self.next_request.wrapping_add(1);
        let msg = ClientMsg::Streaming(ClientStreaming::Edit(Edit { request, op }));
        msg.next_phase(self.phase)?;
        Ok((request, msg))
    }

    /// The message asking for held cell `c` again, whole (after a [`Event::Gap`]).
    pub fn refresh(&mut self, c: CellCoord) -> Result<ClientMsg, StateError> {
        let msg = ClientMsg::Streaming(ClientStreaming::Refresh(c));
        msg.next_phase(self.phase)?;
        Ok(msg)
    }

    pub(super) fn on_delta(&mut self, d: CellDelta) -> Result<Event, StateError> {
        let bad = |what| Err(StateError::Edit(d.cell, what));
        let Some(h) = self.cells.get_mut(&d.cell) else {
            self.stats.dropped += 1;
            return Ok(Event::Dropped);
        };
        if h.grant != d.grant {
            // A delta of an older grant (a newer one carries its changes), or of a newer one whose batches have
            // not come: a newer grant's delta follows its batches on its lane, so that cannot be.
            if h.grant > d.grant {
                self.stats.dropped += 1;
                return Ok(Event::Dropped);
            }
            return bad("delta of a grant not held");
        }
        if h.refreshing {
            // Asked for again: the new grant brings this change too.
            self.stats.dropped += 1;
            return Ok(Event::Dropped);
        }
        if self.grants_only {
            // Nothing held to change: the version moves.
            h.version = d.to_version;
            self.stats.deltas += 1;
            return Ok(Event::Changed { cell: d.cell, version: d.to_version });
        }
        if let Some(later) = self.expanding.get_mut(&d.cell) {
            // The cell is still being expanded here: its changes wait for it (a client too slow to keep up asks
            // for it again).
            if later.deltas.len() >= super::expand::MAX_DEFERRED_DELTAS {
                self.stats.gaps += 1;
                h.refreshing = true;
                return Ok(Event::Gap(d.cell));
            }
            later.deltas.push(d);
            return Ok(Event::Deferred(later.cell));
        }
        if !h.is_complete() {
            return bad("delta before the grant's batches");
        }
        if h.version != d.from_version {
            self.stats.gaps += 1;
            h.refreshing = true;
            return Ok(Event::Gap(d.cell));
        }
        apply_delta(h, &d, self.species.len())?;
        self.stats.deltas += 1;
        Ok(Event::Changed { cell: d.cell, version: d.to_version })
    }
}

/// Apply delta `d` to held cell `h` (at `d.from_version`, checked by the caller); `species`: the table's size.
pub(super) fn apply_delta(h: &mut HeldCell, d: &CellDelta, species: usize) -> Result<(), StateError> {
    let bad = |what| Err(StateError::Edit(d.cell, what));
    {
        if usize::from(d.total) != h.records.len() + d.adds.len() {
            return bad("delta's total does not follow the cell's");
        }
        if let Some(a) = d.adds.iter().find(|a| usize::from(a.record.species) >= species) {
            return Err(StateError::UnknownSpecies(a.record.species));
        }
        let first = h.records.len() as u16;
        for (i, a) in d.adds.iter().enumerate() {
            let record = first + i as u16;
            h.records.push(a.record);
            h.overrides.extend(a.params.iter().map(|&(slot, v)| ParamOverride { record, slot, value: v.0 }));
        }
        h.felled.extend(d.removes.iter().copied());
        for (index, params) in &d.updates {
            h.overrides.retain(|o| o.record != *index || params.iter().all(|p| p.0 != o.slot));
            h.overrides.extend(params.iter().map(|&(slot, v)| ParamOverride { record: *index, slot, value: v.0 }));
        }
        h.overrides.sort_by_key(|o| (o.record, o.slot));
        h.total = d.total;
        h.version = d.to_version;
    }
    Ok(())
}
