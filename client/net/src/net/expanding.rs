//! A connection's cells expanded on this client: the expander it uses, the world built from the server's world
//! function once the function and every species are held, the jobs in flight (cancelled when their grant is no
//! longer wanted) and their results, and the digests and requests for records to send.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use canopy_protocol::messages::CellMode;
use canopy_protocol::{CellCoord, ClientMsg, SpeciesGraph};
use tokio::sync::mpsc;

use super::ClientError;
use crate::expand::{ExpandWorld, Expanded, Expander, Job};
use crate::state::{ClientState, Event};

/// An expanded cell coming back: `(cell, grant, records)`.
pub(super) type Done = (CellCoord, u32, Arc<Expanded>);

/// See the module docs.
pub(super) struct Expanding {
    expander: Option<Arc<Expander>>,
    /// Take grants and expand nothing.
    grants_only: bool,
    world: Option<Arc<ExpandWorld>>,
    /// Grants whose jobs were submitted, with their cancel flags.
    jobs: HashMap<CellCoord, (u32, Arc<AtomicBool>)>,
    /// Grants that came before the world was built.
    deferred: Vec<(CellCoord, u32)>,
    /// Cells to ask records for.
    records: Vec<CellCoord>,
    tx: mpsc::UnboundedSender<Done>,
    rx: mpsc::UnboundedReceiver<Done>,
}

impl Expanding {
    pub(super) fn new(expander: Option<Arc<Expander>>, grants_only: bool) -> Expanding {
        let (tx, rx) = mpsc::unbounded_channel();
        let (jobs, deferred, records) = (HashMap::new(), Vec::new(), Vec::new());
        Expanding { expander, grants_only, world: None, jobs, deferred, records, tx, rx }
    }

    /// The cell mode to ask for (between the welcome and the ready): expand where there is an expander and the
    /// server offers a world function, preloading the function if this process holds it.
    pub(super) fn mode(&self, state: &mut ClientState) -> CellMode {
        let Some(hash) = state.welcome().and_then(|w| w.world.function) else { return CellMode::Records };
        if self.grants_only {
            state.set_grants_only(true);
            state.set_digest_every(0);
            return CellMode::Expand { have_function: false };
        }
        let Some(expander) = &self.expander else { return CellMode::Records };
        let have_function = expander.function(&hash).is_some_and(|f| state.preload_function(f));
        CellMode::Expand { have_function }
    }

    /// Whether this connection expands its cells (and so computes its far field too): it has an expander and asked
    /// for [`CellMode::Expand`] to use it.
    pub(super) fn expands(&self, state: &ClientState) -> bool {
        self.expander.is_some() && !self.grants_only && matches!(state.cell_mode(), CellMode::Expand { .. })
    }

    /// The world and the expander, once the world is built.
    pub(super) fn built(&self) -> Option<(&Arc<ExpandWorld>, &Arc<Expander>)> {
        Some((self.world.as_ref()?, self.expander.as_ref()?))
    }

    /// Follow an event the state gave: expand granted cells, build the world when the function and species are
    /// in, cancel what is no longer wanted, ask records for cells whose expansion differs.
    pub(super) fn on_event(&mut self, state: &mut ClientState, e: &Event) -> Result<(), ClientError> {
        match e {
            Event::Granted { cell, grant } => {
                self.deferred.push((*cell, *grant));
                self.build(state)?;
            }
            Event::Function | Event::Species { .. } => self.build(state)?,
            Event::Released(_) | Event::Dropped | Event::Records { .. } => self.sweep(state),
            Event::Differs(c) => self.records.push(*c),
            _ => {}
        }
        Ok(())
    }

    /// Build the world once the function and every species are held, then submit the grants waiting for it.
    fn build(&mut self, state: &ClientState) -> Result<(), ClientError> {
        let Some(expander) = self.expander.clone() else { return Ok(()) };
        if self.world.is_none() {
            let (Some(w), Some(f)) = (state.welcome(), state.function()) else { return Ok(()) };
            let n = w.species.len();
            let species: Option<Vec<SpeciesGraph>> =
                (0..n).map(|i| state.species(i as u8).map(|g| (**g).clone())).collect();
            let Some(species) = species else { return Ok(()) };
            let terrain = match &w.world.terrain.graph {
                Some(bytes) => Some(SpeciesGraph::decode(bytes).map_err(|e| ClientError::Function(e.to_string()))?),
                None => None,
            };
            let world = expander
                .world(&w.world.name, f, &species, terrain.as_ref(), w.world.grid)
                .map_err(ClientError::Function)?;
            self.world = Some(world);
        }
        let world = Arc::clone(self.world.as_ref().expect("built"));
        let position = state.viewpoint().map_or([0.0, 0.0], |v| v.position);
        for (cell, grant) in std::mem::take(&mut self.deferred) {
            if !state.awaits_expansion(cell, grant) {
                continue;
            }
            let cancelled = Arc::new(AtomicBool::new(false));
            if let Some((_, old)) = self.jobs.insert(cell, (grant, Arc::clone(&cancelled))) {
                Job::cancel(&old);
            }
            let tx = self.tx.clone();
            expander.submit(Job {
                priority: world.grid.distance2(cell, position),
                world: Arc::clone(&world),
                cell,
                cancelled,
                done: Box::new(move |e| {
                    let _ = tx.send((cell, grant, e));
                }),
            });
        }
        Ok(())
    }

    /// Cancel the jobs whose grants no longer wait (released, evicted, replaced).
    pub(super) fn sweep(&mut self, state: &ClientState) {
        self.jobs.retain(|c, (grant, cancelled)| {
            let wanted = state.awaits_expansion(*c, *grant);
            if !wanted {
                Job::cancel(cancelled);
            }
            wanted
        });
    }

    /// Lay an expanded cell into the state.
    pub(super) fn on_expanded(
        &mut self,
        state: &mut ClientState,
        (cell, grant, e): Done,
    ) -> Result<Event, ClientError> {
        if self.jobs.get(&cell).is_some_and(|(g, _)| *g == grant) {
            self.jobs.remove(&cell);
        }
        let ev = state.on_expanded(cell, grant, e.records.clone(), e.overrides.clone())?;
        if let Event::Differs(c) = ev {
            self.records.push(c);
        }
        Ok(ev)
    }

    /// The next expanded cell (pending forever without an expander).
    pub(super) async fn next(&mut self) -> Option<Done> {
        self.rx.recv().await
    }

    /// An expanded cell that is already back, if any.
    pub(super) fn try_next(&mut self) -> Option<Done> {
        self.rx.try_recv().ok()
    }

    /// Messages to send: digests due and requests for records.
    pub(super) fn outbox(&mut self, state: &mut ClientState) -> Result<Vec<ClientMsg>, ClientError> {
        let mut out = state.take_digests();
        for c in std::mem::take(&mut self.records) {
            out.push(state.records(c)?);
        }
        Ok(out)
    }
}
