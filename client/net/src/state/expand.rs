//! Cells the client expands itself ([`CellMode::Expand`]): the world function, grants waiting for their
//! expansion, the expansion's records laid in with the grant's overlay, and the digests the server checks.
//!
//! The expansion itself runs outside the sans-IO core (a driver's worker pool, [`crate::expand::Expander`]): a
//! grant gives an [`Event::Granted`]; the driver expands the cell with the world function and hands the records
//! back through [`ClientState::on_expanded`]. Until then the cell is held but not complete, and deltas that arrive
//! for it wait.

use std::sync::Arc;

use canopy_protocol::edit::CellDelta;
use canopy_protocol::messages::{CellDigest, CellGrant, CellMode, ClientStreaming, WorldFunction, cell_digest};
use canopy_protocol::record::ParamOverride;
use canopy_protocol::{CellCoord, ClientMsg, InstanceId, InstanceRecord};

use super::edits::apply_delta;
use super::{ClientState, Event, HeldCell, StateError};

/// Most deltas that wait for one cell's expansion; past them the cell is asked for again.
pub const MAX_DEFERRED_DELTAS: usize = 64;

/// By default, one cell in this many that the client expands is reported by digest for the server to check.
pub const DIGEST_EVERY: u32 = 64;

/// A granted cell waiting for its expansion.
#[derive(Clone, Debug)]
pub(super) struct Awaiting {
    pub(super) cell: CellCoord,
    grant: u32,
    /// The grant's overlay, from version 0.
    delta: Option<CellDelta>,
    /// Deltas that arrived meanwhile, in order.
    pub(super) deltas: Vec<CellDelta>,
}

impl ClientState {
    /// The answer to the welcome, choosing how cells come: the species held, the first viewpoint and the cell mode
    /// ([`CellMode::Expand`] only where the welcome names a world function; otherwise records).
    pub fn ready_with(
        &mut self,
        viewpoint: canopy_protocol::aoi::Viewpoint,
        cells: CellMode,
    ) -> Result<ClientMsg, StateError> {
        let offered = self.welcome.as_ref().is_some_and(|w| w.world.function.is_some());
        let cells = if offered { cells } else { CellMode::Records };
        let mut msg = self.ready(viewpoint)?;
        if let ClientMsg::Handshake(canopy_protocol::messages::ClientHandshake::Ready(r)) = &mut msg {
            r.cells = cells;
        }
        self.cell_mode = cells;
        Ok(msg)
    }

    /// How cells come in this session.
    pub fn cell_mode(&self) -> CellMode {
        self.cell_mode
    }

    /// A world function the client already holds (from a cache): taken if its hash is the welcome's.
    pub fn preload_function(&mut self, f: Arc<WorldFunction>) -> bool {
        let named = self.welcome.as_ref().and_then(|w| w.world.function);
        let fits = named == Some(f.hash());
        if fits {
            self.function = Some(f);
        }
        fits
    }

    /// The world function, once it arrived (or was preloaded).
    pub fn function(&self) -> Option<&Arc<WorldFunction>> {
        self.function.as_ref()
    }

    /// Take grants and expand nothing: a granted cell counts as held in full with no records, and deltas only move
    /// its version. For load generators (the server sees the traffic of clients that expand, at none of their
    /// cost); such a client holds no instances.
    pub fn set_grants_only(&mut self, on: bool) {
        self.grants_only = on;
    }

    /// Whether this client takes grants and expands nothing.
    pub fn grants_only(&self) -> bool {
        self.grants_only
    }

    /// Report one expanded cell in `every` by digest (0: none).
    pub fn set_digest_every(&mut self, every: u32) {
        self.digest_every = every;
    }

    pub(super) fn on_function(&mut self, f: WorldFunction) -> Result<Event, StateError> {
        let named = self.welcome.as_ref().and_then(|w| w.world.function);
        if named != Some(f.hash()) {
            return Err(StateError::Function("the world function does not match the welcome's hash"));
        }
        self.function = Some(Arc::new(f));
        Ok(Event::Function)
    }

    pub(super) fn on_grant(&mut self, g: CellGrant) -> Result<Event, StateError> {
        let w = Arc::clone(self.welcome.as_ref().expect("streaming implies welcomed"));
        if !w.world.grid.contains(g.cell) || !InstanceId::names(g.cell) {
            return Err(StateError::Edit(g.cell, "a grant of a cell outside the grid"));
        }
        if self.tombstones.get(&g.cell).is_some_and(|&t| t >= g.grant)
            || self.cells.get(&g.cell).is_some_and(|h| h.grant >= g.grant)
        {
            self.stats.dropped += 1;
            return Ok(Event::Dropped);
        }
        let before = self.missing_at(g.cell);
        if !self.aoi.is_some_and(|a| a.is_kept(&w.world.grid, g.cell)) {
            return Ok(self.drop_out_of_range(g.cell, g.grant, before));
        }
        let held = HeldCell {
            grant: g.grant,
            total: 0,
            records: Vec::new(),
            overrides: Vec::new(),
            version: g.version,
            felled: Default::default(),
            expanding: !self.grants_only,
            refreshing: false,
        };
        self.cells.insert(g.cell, held);
        if self.grants_only {
            self.stats.grants += 1;
            self.missing = self.missing + self.missing_at(g.cell) - before;
            return Ok(Event::Records { cell: g.cell, count: 0, complete: true });
        }
        let awaiting = Awaiting { cell: g.cell, grant: g.grant, delta: g.delta, deltas: Vec::new() };
        self.expanding.insert(g.cell, awaiting);
        self.stats.grants += 1;
        self.missing = self.missing + self.missing_at(g.cell) - before;
        Ok(Event::Granted { cell: g.cell, grant: g.grant })
    }

    /// Whether grant `grant` of cell `c` still waits for its expansion (a driver drops work that no longer does).
    pub fn awaits_expansion(&self, c: CellCoord, grant: u32) -> bool {
        self.expanding.get(&c).is_some_and(|a| a.grant == grant)
    }

    /// Cells waiting for their expansion, with their grants.
    pub fn awaiting_expansion(&self) -> impl Iterator<Item = (CellCoord, u32)> + '_ {
        self.expanding.values().map(|a| (a.cell, a.grant))
    }

    /// The world function's records of cell `c` for grant `grant`, expanded by the driver (`overrides` by index
    /// in the cell, sorted): the grant's overlay and the deltas that waited are applied, and the cell is complete.
    /// A grant no longer waiting (released, evicted, replaced) is dropped.
    pub fn on_expanded(
        &mut self,
        c: CellCoord,
        grant: u32,
        records: Vec<InstanceRecord>,
        overrides: Vec<ParamOverride>,
    ) -> Result<Event, StateError> {
        if !self.awaits_expansion(c, grant) {
            self.stats.dropped += 1;
            return Ok(Event::Dropped);
        }
        let a = self.expanding.remove(&c).expect("awaited");
        let species = self.species.len();
        if let Some(r) = records.iter().find(|r| usize::from(r.species) >= species) {
            return Err(StateError::UnknownSpecies(r.species));
        }
        let before = self.missing_at(c);
        let h = self.cells.get_mut(&c).expect("an awaited cell is held");
        let count = records.len();
        let version = h.version;
        let refreshing = h.refreshing;
        h.total = records.len() as u16;
        h.records = records;
        h.overrides = overrides;
        h.version = 0;
        h.expanding = false;
        let mut gap = false;
        let mut differs = false;
        for d in a.delta.iter().chain(&a.deltas) {
            if d.from_version != h.version {
                gap = true;
                break;
            }
            // An overlay that does not fit the expansion (its total does not follow): this client's expansion
            // differs from the server's, and the cell is asked for as records.
            if let Err(StateError::Edit(..)) = apply_delta(h, d, species) {
                differs = true;
                break;
            }
        }
        if h.version < version {
            gap = true;
        }
        self.stats.records_expanded += count as u64;
        let every = self.digest_every;
        if every > 0 && !gap && !differs && digest_sampled(c, every) {
            let h = &self.cells[&c];
            let digest = cell_digest(&h.records, &h.overrides, h.felled.iter().copied());
            self.digests.push(CellDigest { cell: c, version: h.version, digest });
            self.stats.digests += 1;
        }
        self.missing = self.missing + self.missing_at(c) - before;
        if differs {
            self.stats.mismatches += 1;
            return Ok(Event::Differs(c));
        }
        if gap && !refreshing {
            self.stats.gaps += 1;
            self.cells.get_mut(&c).expect("held").refreshing = true;
            return Ok(Event::Gap(c));
        }
        Ok(Event::Records { cell: c, count, complete: true })
    }

    /// Digest messages due (sampled expanded cells), to send.
    pub fn take_digests(&mut self) -> Vec<ClientMsg> {
        std::mem::take(&mut self.digests)
            .into_iter()
            .map(|d| ClientMsg::Streaming(ClientStreaming::Digest(d)))
            .collect()
    }

    /// The message asking for cell `c`'s records in place of its grant (a client that cannot expand it).
    pub fn records(&mut self, c: CellCoord) -> Result<ClientMsg, StateError> {
        let msg = ClientMsg::Streaming(ClientStreaming::Records(c));
        msg.next_phase(self.phase)?;
        Ok(msg)
    }
}

/// Whether cell `c` is among the one in `every` reported by digest: a hash of the cell, so the cells checked are
/// spread over the world and the same for every client.
fn digest_sampled(c: CellCoord, every: u32) -> bool {
    let k = (u64::from(c.x as u32) << 32 | u64::from(c.z as u32)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    (k >> 32) % u64::from(every) == 0
}
