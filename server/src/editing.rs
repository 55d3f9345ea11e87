//! The edit pipeline of one server: editors' requests are checked against the world and the cell they change, given
//! the cell's next version, written durably in groups (group commit: one transaction, one sync for every request
//! that arrived meanwhile), and only then published to the [`LiveStore`], announced to the sessions
//! ([`crate::live::EditHub`]) and acknowledged.
//!
//! One writer thread owns the versions: it applies a group's edits to working copies of their cells' overlays, so
//! several edits of one cell in one group take consecutive versions, and a refused group (a conflict with another
//! writer of the same store, or a failed disk) leaves nothing published.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use canopy_edits::{CellEdit, EditStoreError, Overlay, StoredEdit};
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_protocol::sync::Locked;
use canopy_protocol::{CellCoord, InstanceId, InstanceRecord};
use tracing::{debug, warn};

use crate::live::{EditHub, LiveStore};
use canopy_session::Editor;
use canopy_session::counters::Histogram;
use canopy_session::{CellData, CellState, WorldStore};

/// Most requests written in one group.
pub(crate) const MAX_GROUP: usize = 4096;
/// Most requests waiting for the writer; beyond, new ones are denied at once.
pub(crate) const MAX_QUEUED: usize = 65_536;
/// How long the writer waits for a cell's expansion, or for its log to be readable, before it gives up on an edit
/// of it.
const CELL_WAIT: Duration = Duration::from_secs(30);
/// How often the writer looks again at requests whose cells are being expanded.
const CELL_POLL: Duration = Duration::from_millis(5);

/// Counters of the edit pipeline.
#[derive(Debug, Default)]
pub struct EditMetrics {
    /// Edits answered, by outcome: ok, denied, invalid, conflict.
    pub outcomes: [AtomicU64; 4],
    /// Groups written.
    pub groups: AtomicU64,
    /// Time from a group's first request to its durable commit.
    pub commit_time: Histogram,
    /// Requests dropped unwritten because their session ended first.
    pub abandoned: AtomicU64,
    /// Cells of a group whose append met a conflict (another writer changed the cell first).
    pub cell_conflicts: AtomicU64,
    /// Stored edits not served: the world cannot take them, or they do not decode ([`LiveStore::skipped`]).
    pub skipped: Arc<AtomicU64>,
}

impl EditMetrics {
    /// Count `n` edits refused before they reached the writer (by the sessions themselves).
    pub fn refused(&self, n: u64) {
        self.outcomes[1].fetch_add(n, Relaxed);
    }

    /// Count an outcome.
    pub fn count(&self, o: &EditOutcome) {
        let i = match o {
            EditOutcome::Ok { .. } => 0,
            EditOutcome::Denied(_) => 1,
            EditOutcome::Invalid(_) => 2,
            EditOutcome::Conflict => 3,
        };
        self.outcomes[i].fetch_add(1, Relaxed);
    }
}

/// One request for the writer.
pub struct EditJob {
    /// What to do.
    pub op: EditOp,
    /// Who asks.
    pub editor: Arc<Editor>,
    /// Called once with the outcome (after the edit is durable, for `Ok`).
    pub reply: Box<dyn Reply>,
}

/// Where an edit's outcome goes: any `FnOnce(EditOutcome)`, or a session that can say it is gone.
pub trait Reply: Send {
    /// Give the outcome.
    fn answer(self: Box<Self>, outcome: EditOutcome);
    /// Whether nobody waits for the outcome any more (the session ended): a request not yet written is then dropped
    /// unwritten and unanswered (its client was never told it would be made).
    fn abandoned(&self) -> bool {
        false
    }
}

impl<F: FnOnce(EditOutcome) + Send> Reply for F {
    fn answer(self: Box<Self>, outcome: EditOutcome) {
        (*self)(outcome)
    }
}

/// The edit pipeline (see the module docs).
pub struct EditService {
    tx: Mutex<Option<mpsc::SyncSender<(EditJob, Instant)>>>,
    thread: Mutex<Option<JoinHandle<()>>>,
    hub: Arc<EditHub>,
    metrics: Arc<EditMetrics>,
    /// Set by [`EditService::stop`]: requests whose fate cannot be read are left unanswered.
    stopping: Arc<AtomicBool>,
}

impl std::fmt::Debug for EditService {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EditService").finish()
    }
}

/// What the writer needs to check and apply edits.
struct Writer {
    live: Arc<LiveStore>,
    metrics: Arc<EditMetrics>,
    stopping: Arc<AtomicBool>,
}

impl EditService {
    /// Start the writer thread over `live`.
    pub fn start(live: Arc<LiveStore>) -> Arc<EditService> {
        let hub = Arc::clone(live.hub());
        let metrics = Arc::new(EditMetrics { skipped: Arc::clone(live.skipped()), ..EditMetrics::default() });
        let (tx, rx) = mpsc::sync_channel(MAX_QUEUED);
        let stopping = Arc::new(AtomicBool::new(false));
        let writer = Writer { live, metrics: Arc::clone(&metrics), stopping: Arc::clone(&stopping) };
        let thread = std::thread::Builder::new()
            .name("canopy-edits".into())
            .spawn(move || writer.run(rx))
            .expect("spawning the edit writer");
        Arc::new(EditService { tx: Mutex::new(Some(tx)), thread: Mutex::new(Some(thread)), hub, metrics, stopping })
    }

    /// The hub sessions listen on.
    pub fn hub(&self) -> &Arc<EditHub> {
        &self.hub
    }

    /// The pipeline's counters.
    pub fn metrics(&self) -> &Arc<EditMetrics> {
        &self.metrics
    }

    /// Hand a request to the writer; its reply comes through `job.reply` (at once when the queue is full or the
    /// service stopped).
    pub fn submit(&self, job: EditJob) {
        let tx = self.tx.locked().clone();
        let Some(tx) = tx else {
            job.reply.answer(EditOutcome::Denied("the server is shutting down".into()));
            return;
        };
        if let Err(e) = tx.try_send((job, Instant::now())) {
            let (job, why) = match e {
                mpsc::TrySendError::Full((j, _)) => (j, "too many edits waiting; try again"),
                mpsc::TrySendError::Disconnected((j, _)) => (j, "the edit writer stopped"),
            };
            let outcome = EditOutcome::Denied(why.into());
            self.metrics.count(&outcome);
            job.reply.answer(outcome);
        }
    }

    /// Stop taking requests, write what is queued, and wait for the writer.
    pub fn stop(&self) {
        self.tx.locked().take();
        self.stopping.store(true, Relaxed);
        if let Some(t) = self.thread.locked().take() {
            let _ = t.join();
        }
    }
}

impl Drop for EditService {
    fn drop(&mut self) {
        self.stop();
    }
}

/// A cell's state in the group being written: its world-function records and its overlay with the group's edits.
struct Working {
    base: Arc<CellData>,
    overlay: Overlay,
}

/// A request on its way through the writer, with the edits earlier attempts of it appended: any of them may be in
/// the store (an append that failed may have kept it), and finding one there is what acknowledges the request, so a
/// request is never stored twice.
struct Request {
    job: EditJob,
    /// Edits tried for it whose append failed, oldest first.
    attempts: Vec<StoredEdit>,
    /// Conflicts it met (another writer took the cell's version first), and when the first was.
    conflicts: (usize, Option<Instant>),
    /// Why it waits, when it came back for another reason than a conflict.
    waiting: Waiting,
}

impl Request {
    fn new(job: EditJob) -> Request {
        Request { job, attempts: Vec::new(), conflicts: (0, None), waiting: Waiting::No }
    }

    /// Count a conflict; whether the request has met enough to be answered `conflict` ([`CONFLICT_WAIT`]).
    fn conflicted(&mut self) -> bool {
        let (n, first) = &mut self.conflicts;
        *n += 1;
        let since = *first.get_or_insert_with(Instant::now);
        *n > CONFLICT_RETRIES && since.elapsed() >= CONFLICT_WAIT
    }

    /// The attempt `overlay` holds at its version, if any: the request's outcome.
    fn kept<'a>(attempts: impl IntoIterator<Item = &'a StoredEdit>, overlay: &Overlay) -> Option<&'a StoredEdit> {
        attempts.into_iter().find(|a| overlay.edit(a.version) == Some(*a))
    }
}

/// Why a request waits beside the writer instead of being answered.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Waiting {
    /// It does not (it is being written, or met a conflict).
    No,
    /// Its fate is not known: its cell could not be read after an append that failed.
    Unknown,
    /// Its cell is being expanded (since then): the writer goes on with other requests meanwhile.
    Cell(Instant),
    /// Its cell's log could not be read (since then), as during an engine's election: looked at again after the
    /// writer's pause, refused only after [`CELL_WAIT`].
    Unreadable(Instant),
}

/// Why a request could not be made into an edit now.
enum Refusal {
    /// Its answer.
    Answer(EditOutcome),
    /// Its cell is not ready yet.
    Pending,
    /// Its cell's log could not be read: why.
    Unreadable(String),
}

impl From<EditOutcome> for Refusal {
    fn from(o: EditOutcome) -> Refusal {
        Refusal::Answer(o)
    }
}

/// One accepted request of a group (kept whole: a conflict sends it round again).
struct Accepted {
    request: Request,
    id: InstanceId,
    version: u32,
}

/// The instance an edit of `cell` made or changed.
fn edit_id(e: &StoredEdit) -> InstanceId {
    InstanceId::new(e.cell, e.op.index()).expect("a grid cell can be named")
}

/// How long a request that meets conflicts (another writer took the cell's version) is checked and written again,
/// from its first conflict and at least [`CONFLICT_RETRIES`] times, before it is answered `conflict`: writers that
/// share a busy cell take turns on it, and each turn costs a conflict to all but one of them. (Time spent waiting
/// for a store in an election does not count.)
pub(crate) const CONFLICT_WAIT: Duration = Duration::from_secs(2);

/// The fewest conflicts a request meets before it is answered `conflict`.
pub(crate) const CONFLICT_RETRIES: usize = 3;

/// The first pause before requests whose fate is not known yet (their cell's log could not be read) are looked at
/// again; it doubles up to [`UNKNOWN_PAUSE_MAX`].
const UNKNOWN_PAUSE: Duration = Duration::from_millis(50);

/// The longest pause between two looks at requests whose fate is not known yet.
const UNKNOWN_PAUSE_MAX: Duration = Duration::from_secs(2);

impl Writer {
    fn run(self, rx: mpsc::Receiver<(EditJob, Instant)>) {
        // Requests that come back from a group: those that met a conflict go round again at once, with whatever
        // arrived meanwhile (so a writer that lost a busy cell to another writer takes it back with every edit
        // waiting for it, in one run); those whose fate is not known yet (their cell could not be read) are looked at
        // again with the next group or after a pause that grows while they stay unknown; those whose cell is being
        // expanded, every few milliseconds. The writer goes on with other requests meanwhile.
        let mut carried: Vec<Request> = Vec::new();
        let mut pause = UNKNOWN_PAUSE;
        loop {
            let waiting = |r: &Vec<Request>| r.iter().filter(|r| r.waiting != Waiting::No).count();
            let first = if carried.iter().any(|r| r.waiting == Waiting::No) {
                rx.try_recv().ok()
            } else if carried.is_empty() {
                rx.recv().ok()
            } else {
                let cell_pending = carried.iter().any(|r| matches!(r.waiting, Waiting::Cell(_)));
                match rx.recv_timeout(if cell_pending { CELL_POLL } else { pause }) {
                    Ok(first) => Some(first),
                    Err(mpsc::RecvTimeoutError::Timeout) => None,
                    Err(mpsc::RecvTimeoutError::Disconnected) if self.stopping.load(Relaxed) => {
                        // What became of these is not known and the server is going: they stay unanswered (their
                        // sessions end with it), never answered by a guess.
                        warn!(
                            "{} edits stay unanswered: their cells could not be read before the server stopped",
                            carried.len()
                        );
                        return;
                    }
                    Err(mpsc::RecvTimeoutError::Disconnected) => {
                        std::thread::sleep(pause);
                        None
                    }
                }
            };
            let started = first.as_ref().map_or_else(Instant::now, |f| f.1);
            let mut requests = std::mem::take(&mut carried);
            let (fresh, unknown) = (requests.len(), waiting(&requests));
            if let Some((job, _)) = first {
                requests.push(Request::new(job));
                while requests.len() - fresh < MAX_GROUP {
                    match rx.try_recv() {
                        Ok((j, _)) => requests.push(Request::new(j)),
                        Err(_) => break,
                    }
                }
            } else if requests.is_empty() {
                // The queue is closed and nothing waits.
                return;
            }
            carried = self.try_group(requests, started);
            // Longer pauses only while nothing that was unknown became known.
            pause = if waiting(&carried) < unknown.max(1) { UNKNOWN_PAUSE } else { (pause * 2).min(UNKNOWN_PAUSE_MAX) };
        }
    }

    fn reply(&self, reply: Box<dyn Reply>, outcome: EditOutcome) {
        self.metrics.count(&outcome);
        reply.answer(outcome);
    }

    /// Check, write and answer a group; the requests that must go round again come back (a conflict, or a store
    /// that could not be read to tell whether an earlier attempt was kept, a cell not ready: [`Request::waiting`]).
    fn try_group(&self, requests: Vec<Request>, started: Instant) -> Vec<Request> {
        let mut working: BTreeMap<CellCoord, Working> = BTreeMap::new();
        let mut edits = Vec::with_capacity(requests.len());
        let mut accepted = Vec::with_capacity(requests.len());
        let mut again = Vec::new();
        for mut request in requests {
            let waited = std::mem::replace(&mut request.waiting, Waiting::No);
            // Its session ended before it was written: nobody was told it would be made, so it is not.
            if request.attempts.is_empty() && request.job.reply.abandoned() {
                self.metrics.abandoned.fetch_add(1, Relaxed);
                continue;
            }
            // Tried before: if the store kept an attempt, that is the request's outcome.
            if let Some(last) = request.attempts.last() {
                match self.working(last.cell, &mut working) {
                    Ok(w) => {
                        if let Some(kept) = Request::kept(&request.attempts, &w.overlay) {
                            let outcome = EditOutcome::Ok { id: edit_id(kept), version: kept.version };
                            self.reply(request.job.reply, outcome);
                            continue;
                        }
                    }
                    // Not known yet: asked again later, never answered by a guess.
                    Err(_) => {
                        request.waiting = Waiting::Unknown;
                        again.push(request);
                        continue;
                    }
                }
            }
            match self.prepare(&request.job.op, &request.job.editor, &mut working) {
                Ok((edit, id)) => {
                    accepted.push(Accepted { request, id, version: edit.version });
                    edits.push(edit);
                }
                Err(Refusal::Answer(outcome)) => self.reply(request.job.reply, outcome),
                Err(Refusal::Pending) => {
                    let why = "the cell is not ready; try again".to_string();
                    self.wait_or_refuse(request, waited, Waiting::Cell, why, &mut again);
                }
                Err(Refusal::Unreadable(e)) => {
                    let why = format!("the cell's edits could not be read: {e}");
                    self.wait_or_refuse(request, waited, Waiting::Unreadable, why, &mut again);
                }
            }
        }
        if edits.is_empty() {
            return again;
        }
        // Cell by cell: a conflict in one cell of the group (another edge's edit) leaves the others acknowledged.
        let mut failed: BTreeMap<CellCoord, EditStoreError> = BTreeMap::new();
        let results = self.live.edit_store().append_cells(&edits);
        let written = results.len();
        for (cell, result) in results {
            if let Err(e) = result {
                failed.insert(cell, e);
            }
        }
        if failed.len() < written {
            self.metrics.groups.fetch_add(1, Relaxed);
            self.metrics.commit_time.record(started.elapsed());
        }
        let bases: BTreeMap<CellCoord, Arc<CellData>> =
            working.iter().filter(|(c, _)| failed.contains_key(c)).map(|(c, w)| (*c, Arc::clone(&w.base))).collect();
        let (mut stored, mut settle) = (Vec::new(), Vec::new());
        for (a, e) in accepted.into_iter().zip(edits) {
            if failed.contains_key(&e.cell) { settle.push((a, e)) } else { stored.push(a) }
        }
        for (cell, w) in working {
            if !failed.contains_key(&cell) && stored.iter().any(|a| a.id.cell() == cell) {
                self.live.publish(cell, w.overlay);
            }
        }
        for a in stored {
            self.reply(a.request.job.reply, EditOutcome::Ok { id: a.id, version: a.version });
        }
        for (cell, e) in &failed {
            match e {
                EditStoreError::Conflict { version, .. } => {
                    self.metrics.cell_conflicts.fetch_add(1, Relaxed);
                    // Routine where edges share busy cells: counted, not logged at info.
                    debug!(?cell, version, "another writer changed the cell first: checking its edits again")
                }
                e => warn!(?cell, "writing the cell's edits: {e}"),
            }
        }
        if !settle.is_empty() {
            again.extend(self.settle_failed(bases, settle, &failed));
        }
        again
    }

    /// A request that cannot be prepared yet: back to wait as `waiting` (since it first did so, `waited` if that is
    /// the same kind of wait), or refused with `why` after [`CELL_WAIT`].
    fn wait_or_refuse(
        &self,
        mut request: Request,
        waited: Waiting,
        waiting: fn(Instant) -> Waiting,
        why: String,
        again: &mut Vec<Request>,
    ) {
        let since = match waited {
            Waiting::Cell(since) | Waiting::Unreadable(since) if waiting(since) == waited => since,
            _ => Instant::now(),
        };
        if since.elapsed() >= CELL_WAIT {
            self.reply(request.job.reply, EditOutcome::Denied(why));
        } else {
            request.waiting = waiting(since);
            again.push(request);
        }
    }

    /// After a failed append, answer each edit by what the store holds: a store that is not transactional (or a
    /// commit that failed after its data reached the disk, or an acknowledgement lost with an engine node) may have
    /// kept some of the group. Each cell's log is read again: an edit found at its version is acknowledged (it is
    /// durable); the others go round again after a conflict, and are refused after any other failure. A cell whose
    /// log cannot be read now leaves its edits pending: they come back, to be looked for when it can be read — an
    /// edit is never called "not stored" on the strength of a read that failed.
    fn settle_failed(
        &self,
        mut bases: BTreeMap<CellCoord, Arc<CellData>>,
        settle: Vec<(Accepted, StoredEdit)>,
        errors: &BTreeMap<CellCoord, EditStoreError>,
    ) -> Vec<Request> {
        // Each cell read once again (and watched again, for a shared store): what the sessions get, and what says
        // which edits were stored. A cell lost to another writer whose overlay here is already past the version tried (the store told of the
        // winner, or a watch did) is not read: what this server holds is the store's fold.
        let mut read: BTreeMap<CellCoord, Arc<Overlay>> = BTreeMap::new();
        bases.retain(|c, _| {
            let EditStoreError::Conflict { version, .. } = errors[c] else { return true };
            match self.live.cached(*c) {
                Some(overlay) if overlay.version() >= version => {
                    read.insert(*c, overlay);
                    false
                }
                _ => true,
            }
        });
        // The others at once, a thread each: a network store's reads are round trips, and writers sharing busy
        // cells lose several of them a turn.
        let reads: Vec<(CellCoord, Result<Arc<Overlay>, EditStoreError>)> = std::thread::scope(|s| {
            let reading: Vec<_> =
                bases.iter().map(|(c, base)| (*c, s.spawn(move || self.live.reload(*c, base)))).collect();
            reading.into_iter().map(|(c, t)| (c, t.join().expect("a cell's read does not panic"))).collect()
        });
        for (c, overlay) in reads {
            match overlay {
                Ok(overlay) => {
                    read.insert(c, overlay);
                }
                Err(e) => warn!(?c, "reading the cell's edits again (its edits wait until it can be read): {e}"),
            }
        }
        let mut again = Vec::new();
        for (a, e) in settle {
            let mut request = a.request;
            let error = &errors[&e.cell];
            let Some(overlay) = read.get(&e.cell) else {
                request.attempts.push(e);
                request.waiting = Waiting::Unknown;
                again.push(request);
                continue;
            };
            // This attempt or an earlier one of the request.
            let kept = Request::kept(std::iter::once(&e).chain(&request.attempts), overlay);
            let outcome = match error {
                _ if let Some(kept) = kept => EditOutcome::Ok { id: edit_id(kept), version: kept.version },
                EditStoreError::Conflict { .. } => {
                    if !request.conflicted() {
                        request.attempts.push(e);
                        again.push(request);
                        continue;
                    }
                    EditOutcome::Conflict
                }
                // Not stored now, but the append may yet land: tried again (the same edit at the same version
                // where the cell is unchanged, so a store that deduplicates takes it once) after a pause, found
                // when it lands, never answered by a guess.
                EditStoreError::Unanswered(_) => {
                    request.attempts.push(e);
                    request.waiting = Waiting::Unknown;
                    again.push(request);
                    continue;
                }
                e => EditOutcome::Denied(format!("the edit could not be stored: {e}")),
            };
            self.reply(request.job.reply, outcome);
        }
        again
    }

    /// The cell's working state, read on first need; [`Refusal::Pending`] while the cell is being expanded (the
    /// writer never waits for an expansion: it goes on with other requests).
    fn working<'w>(
        &self,
        c: CellCoord,
        working: &'w mut BTreeMap<CellCoord, Working>,
    ) -> Result<&'w mut Working, Refusal> {
        if let std::collections::btree_map::Entry::Vacant(slot) = working.entry(c) {
            let (base, overlay) = match self.live.base_and_overlay(c, None) {
                Ok(Some(found)) => found,
                Ok(None) => {
                    return match self.live.base().cell(c, None) {
                        CellState::Outside => Err(EditOutcome::Invalid("the cell is outside the world".into()).into()),
                        // Pending, or expanded since the look above: looked at again shortly.
                        _ => Err(Refusal::Pending),
                    };
                }
                // A store in an election or a disk that fails for a while: the request waits instead of being refused.
                Err(e) => return Err(Refusal::Unreadable(e.to_string())),
            };
            if let Some(why) = self.live.damaged(c) {
                return Err(EditOutcome::Denied(format!(
                    "the cell's stored edits are damaged ({why}); it takes no edits until the store is repaired"
                ))
                .into());
            }
            slot.insert(Working { base, overlay: (*overlay).clone() });
        }
        Ok(working.get_mut(&c).expect("inserted above"))
    }

    /// Check one request against the world and its cell, and apply it to the cell's working overlay.
    fn prepare(
        &self,
        op: &EditOp,
        editor: &Editor,
        working: &mut BTreeMap<CellCoord, Working>,
    ) -> Result<(StoredEdit, InstanceId), Refusal> {
        let invalid = |why: String| Err(Refusal::Answer(EditOutcome::Invalid(why)));
        let grid = *self.live.grid();
        let rules = self.live.rules();
        let check_params =
            |species: u8, params: &[(u16, f32)]| rules.check_params(species, params).map_err(EditOutcome::Invalid);
        let (cell, cell_op) = match op {
            EditOp::Plant { species, x, z, params } => {
                let cell = grid.cell_of(*x, *z);
                let [x0, z0, x1, z1] = self.live.head().bounds();
                let in_bounds = (x0..x1).contains(x) && (z0..z1).contains(z);
                if !(grid.contains(cell) && in_bounds) {
                    return invalid(format!("({x}, {z}) is outside the world"));
                }
                rules.check_species(*species).map_err(EditOutcome::Invalid)?;
                if !editor.may_edit_at(*x, *z) {
                    return Err(EditOutcome::Denied(format!("({x}, {z}) is outside {}'s region", editor.name)).into());
                }
                check_params(*species, params)?;
                let q = grid.steps(cell, (*x).into(), (*z).into());
                let record = InstanceRecord::new(*species, q[0], q[1]);
                (cell, CellEdit::Plant { index: 0, record, params: params.clone() })
            }
            EditOp::Fell { id } | EditOp::Set { id, .. } => {
                let cell = id.cell();
                if !grid.contains(cell) {
                    return invalid(format!("instance {} is outside the world", id.0));
                }
                // Authorised before any work: a cell wholly outside the editor's region is never built for it.
                let [x0, z0] = grid.cell_origin(cell);
                if !editor.may_edit_in([x0, z0, x0 + grid.cell_size, z0 + grid.cell_size]) {
                    return Err(
                        EditOutcome::Denied(format!("cell {cell:?} is outside {}'s region", editor.name)).into()
                    );
                }
                let index = id.index();
                let op = match op {
                    EditOp::Set { params, .. } => CellEdit::Set { index, params: params.clone() },
                    _ => CellEdit::Fell { index },
                };
                (cell, op)
            }
        };
        let w = self.working(cell, working)?;
        let mut cell_op = cell_op;
        if let CellEdit::Plant { index, .. } = &mut cell_op {
            *index = w.overlay.total();
        }
        w.overlay.check(&cell_op).map_err(|e| EditOutcome::Invalid(e.to_string()))?;
        if let CellEdit::Fell { index } | CellEdit::Set { index, .. } = cell_op {
            let record = match index.checked_sub(w.overlay.base_total()) {
                None => w.base.records[usize::from(index)],
                Some(p) => w.overlay.planted(p).expect("checked: the index exists"),
            };
            let origin = grid.cell_origin(cell);
            let step = canopy_protocol::record::position_step(grid.cell_size);
            let (x, z) = (origin[0] + f32::from(record.qx()) * step, origin[1] + f32::from(record.qz()) * step);
            if !editor.may_edit_at(x, z) {
                return Err(
                    EditOutcome::Denied(format!("instance at ({x}, {z}) is outside {}'s region", editor.name)).into()
                );
            }
            if let CellEdit::Set { params, .. } = &cell_op {
                check_params(record.species, params)?;
            }
        }
        let edit = StoredEdit { cell, version: w.overlay.version() + 1, op: cell_op };
        w.overlay.apply(&edit).map_err(|e| EditOutcome::Invalid(e.to_string()))?;
        let id = InstanceId::new(cell, edit.op.index()).expect("a grid cell can be named");
        Ok((edit, id))
    }
}
