//! The far field: the far view the client asks for, when to ask again, and the summary nodes it holds.

use std::collections::BTreeMap;
use std::sync::Arc;

use canopy_protocol::ClientMsg;
use canopy_protocol::messages::{CellMode, ClientStreaming, FarCell};
use canopy_protocol::summary::{FarView, NodeKey, NodeSummary, SummaryBatch};

use super::{ClientState, Event, MAX_HELD_SUMMARIES, StateError};

impl ClientState {
    /// The message saying how the client wants the far field (summary nodes beyond the records); the server sends
    /// none before the first. See [`ClientState::far_view_due`] for when to send it again.
    pub fn set_far_view(&mut self, view: FarView) -> Result<ClientMsg, StateError> {
        let msg = ClientMsg::Streaming(ClientStreaming::FarView(view));
        msg.next_phase(self.phase)?;
        self.far_view = Some(view);
        Ok(msg)
    }

    /// Whether `view` differs enough from the far view last sent to send it: the first one, a change of anything
    /// but the altitude, or the altitude by more than an eighth (and more than 4 m).
    pub fn far_view_due(&self, view: &FarView) -> bool {
        let Some(last) = self.far_view else { return true };
        let same_rest = FarView { altitude: last.altitude, ..*view } == last;
        let moved = (view.altitude - last.altitude).abs();
        !same_rest || (moved > 4.0 && moved > last.altitude.abs() / 8.0)
    }

    /// The far view last sent.
    pub fn far_view(&self) -> Option<&FarView> {
        self.far_view.as_ref()
    }

    /// The far-view summary nodes held, by key.
    pub fn summaries(&self) -> &BTreeMap<NodeKey, Arc<NodeSummary>> {
        &self.summaries
    }

    /// Changes whenever the summary nodes held change.
    pub fn summaries_generation(&self) -> u64 {
        self.summaries_generation
    }

    /// An edited cell beyond the area of interest: handed to the driver where this client computes its far view
    /// (it expands cells), dropped otherwise or when the cell is not the world's.
    pub(crate) fn on_far_cell(&mut self, f: FarCell) -> Event {
        let in_world = self.welcome().is_some_and(|w| w.world.grid.contains(f.cell));
        if !in_world || !matches!(self.cell_mode(), CellMode::Expand { .. }) {
            return Event::Dropped;
        }
        self.stats.far_cells += 1;
        Event::FarCell(Box::new(f))
    }

    /// Releases first, then the nodes (a batch may release a node and send its replacement); a batch from the
    /// server, or one this client computed itself.
    pub(crate) fn on_summaries(&mut self, b: SummaryBatch) -> Result<Event, StateError> {
        let released = b.released.iter().filter(|k| self.summaries.remove(k).is_some()).count();
        let added = b.nodes.len();
        let table = self.species.len();
        if b.nodes.iter().flat_map(|n| &n.species).any(|s| usize::from(s.species) >= table) {
            let bad = b.nodes.iter().flat_map(|n| &n.species).map(|s| s.species).max().unwrap_or(0);
            return Err(StateError::UnknownSpecies(bad.min(255) as u8));
        }
        for n in b.nodes {
            self.summaries.insert(n.key, Arc::new(n));
        }
        if self.summaries.len() > MAX_HELD_SUMMARIES {
            return Err(StateError::TooManySummaries);
        }
        self.stats.summaries += added as u64;
        self.stats.summaries_released += released as u64;
        self.summaries_generation += 1;
        Ok(Event::Summaries { added, released })
    }
}
