//! The far view's summaries corrected by edits, for clients that take records (issue 30, item 5): every edited
//! cell the live store hears of (an announcement, the index's reads) is queued, and one thread corrects the base
//! store's summary nodes holding it by the cell's edits from version 0 ([`WorldStore::correct_summaries`]), then
//! announces the cell again so that the sessions holding nodes over it send them anew
//! ([`WorldStore::summary_corrections`]). Nothing is corrected until a session first asks for a summary node: a
//! server whose clients all expand cells (and correct their own far views) spends nothing here.
//!
//! Bounded: at most [`MAX_INDEXED`] cells queued or remembered as corrected; a cell whose edits no delta from version
//! 0 can carry stays as the world function has it in the far view (its records, near, are exact).

use std::collections::BTreeMap;
use std::sync::atomic::Ordering::{Acquire, Release};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use canopy_protocol::CellCoord;
use canopy_protocol::sync::{Locked, Waited};
use canopy_session::{CellState, CellWaker, WorldStore};

use super::{CellChange, MAX_INDEXED, Shared};

/// Cells to correct and corrected, with their versions.
#[derive(Default)]
pub(super) struct Corrections {
    /// Cells to correct, with the newest version announced.
    queue: BTreeMap<CellCoord, u32>,
    /// Cells corrected, with the version their nodes show.
    done: BTreeMap<CellCoord, u32>,
    stop: bool,
}

/// The corrector's queue and its wake-up.
#[derive(Default)]
pub(super) struct Corrector {
    state: Mutex<Corrections>,
    work: Condvar,
}

/// Woken when the base store has a cell ready (the corrector waits for it on its own thread).
#[derive(Default)]
struct Ready {
    ready: Mutex<bool>,
    cv: Condvar,
}

impl CellWaker for Ready {
    fn wake(&self) {
        *self.ready.locked() = true;
        self.cv.notify_all();
    }
}

impl Corrector {
    /// Stop the thread.
    pub(super) fn stop(&self) {
        self.state.locked().stop = true;
        self.work.notify_all();
    }

    fn stopped(&self) -> bool {
        self.state.locked().stop
    }
}

impl Shared {
    /// Queue cell `c`, edited up to `version`, for correcting its summary nodes (unless they show it already).
    pub(super) fn queue_correction(&self, c: CellCoord, version: u32) {
        let mut st = self.corrector.state.locked();
        if version == 0 || st.done.get(&c).is_some_and(|&v| v >= version) {
            return;
        }
        let known = st.done.contains_key(&c) || st.queue.contains_key(&c);
        if !known && st.done.len() + st.queue.len() >= MAX_INDEXED {
            return;
        }
        let queued = st.queue.entry(c).or_insert(version);
        *queued = (*queued).max(version);
        drop(st);
        if self.summaries_wanted.load(Acquire) {
            self.corrector.work.notify_one();
        }
    }

    /// A session asked for a summary node: corrections start (once).
    pub(super) fn want_summaries(&self) {
        if !self.summaries_wanted.load(Acquire) {
            // Under the queue's lock, so the thread cannot miss it between its look and its wait.
            let _st = self.corrector.state.locked();
            self.summaries_wanted.store(true, Release);
            self.corrector.work.notify_one();
        }
    }

    /// The corrector thread (see the module docs).
    pub(super) fn run_corrector(self: &Arc<Self>, base: &Arc<dyn WorldStore>) {
        let ready = Arc::new(Ready::default());
        let waker: Arc<dyn CellWaker> = Arc::clone(&ready) as Arc<dyn CellWaker>;
        loop {
            let (cell, version) = {
                let mut st = self.corrector.state.locked();
                loop {
                    if st.stop {
                        return;
                    }
                    if self.summaries_wanted.load(Acquire)
                        && let Some(next) = st.queue.pop_first()
                    {
                        break next;
                    }
                    st = self.corrector.work.waited(st);
                }
            };
            // The cell's world-function records, expanded by the base store's workers, to read its log against.
            *ready.ready.locked() = false;
            let records = loop {
                match base.cell(cell, Some(&waker)) {
                    CellState::Ready(records) => break Some(records),
                    CellState::Outside => break None,
                    CellState::Pending => {
                        let r = ready.ready.locked();
                        if !*r {
                            drop(ready.cv.waited_for(r, Duration::from_millis(100)));
                        }
                        if self.corrector.stopped() {
                            return;
                        }
                    }
                }
            };
            let Some(records) = records else { continue };
            let overlay = match self.load(cell, &records) {
                Ok(overlay) => overlay,
                Err(e) => {
                    // Asked again later, as a loader would (not at once: a store that is down is not hammered).
                    self.failed(cell, &e);
                    self.queue_correction(cell, version);
                    std::thread::sleep(Duration::from_millis(100));
                    continue;
                }
            };
            let now = overlay.version();
            let delta = overlay.delta(0);
            if now > 0 && delta.is_none() {
                tracing::debug!(
                    ?cell,
                    version = now,
                    "more edits than a delta carries: the far view keeps the world function"
                );
            }
            self.corrector.state.locked().done.insert(cell, now);
            if base.correct_summaries(cell, delta.as_ref()) {
                self.hub.announce(CellChange { cell, version: now });
            }
        }
    }
}
