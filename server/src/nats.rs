//! The edit log on NATS JetStream (issue 17): many stateless edges share one world's edits through a replicated
//! stream, one subject a cell (`canopy.edits.WORLD.X.Z`), each message a **run**: the consecutive versions one
//! group of a writer made to the cell ([`encode_run`], header `Canopy-Run`; a message without the header is one
//! [`StoredEdit`], as streams written before runs hold).
//!
//! - **Versions every edge agrees on.** A cell's versions are 1, 2, … in its subject's order. An append of a run
//!   from version v names the stream sequence of the message holding v − 1 (`Nats-Expected-Last-Subject-Sequence`):
//!   the engine refuses it if another edge got there first (compare-and-set), so no version is taken twice; the
//!   writer then reads the cell again and checks the edits once more. The store remembers each cell's last edit as
//!   (version, sequence), and an append whose v − 1 is not that edit (a watch already told of a later one) is
//!   refused without publishing — naming the later edit's sequence would let the engine take version v a second
//!   time. The engine's check is not serializable on a clustered stream before nats-server 2.9.21
//!   (nats-io/nats-server#4320; Debian ships 2.9.10): two publishes naming the same sequence may both be stored.
//!   So versions from v are the *first* run on the subject that starts at v (`first_wins`, the fold every reader
//!   and every watch applies; a run that starts at a version already taken is skipped whole), and a writer
//!   acknowledges its run only after reading that its message is the first from its version on the subject after
//!   the one it named (an earlier version's lost race, not yet taken out, is passed over); a loser is a conflict.
//!   `Nats-Msg-Id` (`X.Z.VERSION.DIGEST`) makes a retried publish a duplicate, not a second run (the id carries a
//!   digest of the run's bytes, so another run from the same version is no duplicate).
//! - **One round trip for a cell's whole group.** Writers that share a busy cell take turns on it; the one whose run
//!   is first takes every edit it had waiting for the cell, so a turn costs a publish and a read whatever the edits
//!   in it, and a cell's throughput is not one version a round trip.
//! - **Durable means replicated.** An append returns once JetStream acknowledged every message, which for a stream
//!   of `replicas` > 1 is after its Raft group committed it on a quorum.
//! - **Group commit.** A group's cells are published concurrently and stored or refused each on its own
//!   ([`EditStore::append_cells`]): a conflict in one cell does not hold back the others.
//! - **Watching.** An edge watches the cells whose overlays it keeps ([`EditStore::watch`]): an ordered consumer
//!   of the cell's subject from just after the last message its read of the log saw (so nothing between the read
//!   and the watch is missed, and only what the stream stored is told: a publish the engine refused is not, a lost
//!   race is skipped by the fold), kept when the cell is read again, dropped when the overlay is evicted; other
//!   edges' edits reach the [`EditWatcher`]. Beside them, one ordered consumer of the whole stream tells the edge's
//!   index of edited cells of every run published ([`EditStore::watch_all`]), so another edge's edit of a cell no
//!   session here holds reaches this edge's far views at once.
//!
//! The store's calls are synchronous (the [`EditStore`] trait); they run on a runtime of the store's own, on its
//! own thread, so they may be called from any thread (the edit writer, overlay loaders).

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use async_nats::jetstream::{self, context::PublishErrorKind, stream};
use canopy_edits::{EditStore, EditStoreError, EditWatcher, LogError, MAX_RUN, StoredEdit, decode_run, encode_run};
use canopy_protocol::CellCoord;
use canopy_protocol::sync::Locked;
use futures_util::{StreamExt, TryStreamExt};
use tracing::{debug, warn};

use crate::metrics::EngineMetrics;

/// How long a call may take before it fails (a cluster that lost its quorum).
const CALL_TIMEOUT: Duration = Duration::from_secs(10);

/// A call to the engine slower than this is logged.
const SLOW_CALL: Duration = Duration::from_millis(500);

/// How long the engine's acknowledgement of one publish is waited for before it is sent again.
const ACK_TIMEOUT: Duration = Duration::from_secs(2);

/// How long one publish is tried again (a node died, the stream elects a leader) before the append fails.
const PUBLISH_PATIENCE: Duration = Duration::from_secs(8);

/// The first pause before a publish is tried again (doubling up to [`PUBLISH_RETRY_MAX`]).
const PUBLISH_RETRY: Duration = Duration::from_millis(50);

/// The longest pause between two tries of one publish.
const PUBLISH_RETRY_MAX: Duration = Duration::from_secs(1);

/// The first pause before a cell's watch is set up again after it could not be (doubling up to
/// [`WATCH_RETRY_MAX`]).
const WATCH_RETRY: Duration = Duration::from_millis(100);

/// The longest pause between attempts to set up a cell's watch.
const WATCH_RETRY_MAX: Duration = Duration::from_secs(5);

/// Where and how the edit log lives.
#[derive(Clone, Debug, PartialEq)]
pub struct NatsConfig {
    /// NATS servers, `nats://HOST:PORT` (any of a cluster's).
    pub servers: Vec<String>,
    /// The world's name: the stream and subjects are named after it.
    pub world: String,
    /// Replicas of the stream (3 for a three-node cluster).
    pub replicas: usize,
}

impl NatsConfig {
    /// The world's name as a subject token and stream-name part: ASCII letters, digits, `-` and `_`.
    fn token(&self) -> String {
        let t: String =
            self.world.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' { c } else { '_' }).collect();
        if t.is_empty() { "world".into() } else { t }
    }

    /// The stream's name.
    pub fn stream(&self) -> String {
        format!("CANOPY_EDITS_{}", self.token())
    }

    /// The subject of cell `c`.
    pub fn subject(&self, c: CellCoord) -> String {
        format!("canopy.edits.{}.{}.{}", self.token(), c.x, c.z)
    }

    /// Every cell's subjects.
    fn wildcard(&self) -> String {
        format!("canopy.edits.{}.>", self.token())
    }

    /// The cell a subject names.
    fn cell_of(&self, subject: &str) -> Option<CellCoord> {
        let rest = subject.strip_prefix(&format!("canopy.edits.{}.", self.token()))?;
        let (x, z) = rest.split_once('.')?;
        Some(CellCoord::new(x.parse().ok()?, z.parse().ok()?))
    }
}

/// A cell's last edit as far as this store knows: its version and its stream sequence.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord)]
struct Known {
    version: u32,
    sequence: u64,
}

/// A cell's log as last read: its edits and the stream sequence of the last message read on its subject.
struct Tail {
    edits: Vec<StoredEdit>,
    last: u64,
}

/// Bytes of cells' logs kept so that reading a cell again reads only what follows ([`Inner::load`]).
const TAIL_CACHE_BYTES: usize = 32 << 20;

/// What one kept edit costs in the tail cache (the edit and its share of the vector), roughly.
const TAIL_EDIT_BYTES: usize = 64;

/// What the store's thread holds.
struct Inner {
    cfg: NatsConfig,
    metrics: Arc<EngineMetrics>,
    js: jetstream::Context,
    stream: stream::Stream,
    /// Per cell, the version of its last edit this store knows and that edit's stream sequence ((0, 0): none).
    last: Mutex<HashMap<CellCoord, Known>>,
    /// Watched cells and the tasks forwarding their subjects.
    watches: Mutex<HashMap<CellCoord, (tokio::task::JoinHandle<()>, WatcherSlot)>>,
    /// The task forwarding the whole stream ([`EditStore::watch_all`]).
    stream_watch: Mutex<Option<tokio::task::JoinHandle<()>>>,
    /// Cells' logs as last read, bounded by [`TAIL_CACHE_BYTES`]: a cell read again (after a conflict, another
    /// edge's edit) costs a round trip a new message, not one a message of its whole log.
    tails: Mutex<canopy_protocol::lru::Lru<CellCoord, Tail>>,
}

/// The edit log on NATS JetStream (see the module docs).
pub struct NatsEditStore {
    inner: Arc<Inner>,
    metrics: Arc<EngineMetrics>,
    handle: tokio::runtime::Handle,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for NatsEditStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NatsEditStore").field("cfg", &self.inner.cfg).finish()
    }
}

impl Drop for NatsEditStore {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn io(what: &str, e: impl std::fmt::Display) -> EditStoreError {
    EditStoreError::Io(format!("NATS {what}: {e}"))
}

impl NatsEditStore {
    /// Connect to the cluster and make sure the world's stream exists (created with `cfg.replicas` replicas on
    /// file storage if it does not).
    pub fn connect(cfg: NatsConfig) -> Result<NatsEditStore, EditStoreError> {
        let (handle_tx, handle_rx) = std::sync::mpsc::channel();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::Builder::new()
            .name("canopy-nats".into())
            .spawn(move || {
                let rt = match tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build() {
                    Ok(rt) => rt,
                    Err(e) => {
                        let _ = handle_tx.send(Err(io("runtime", e)));
                        return;
                    }
                };
                let _ = handle_tx.send(Ok(rt.handle().clone()));
                rt.block_on(async {
                    let _ = stopped.await;
                });
                rt.shutdown_timeout(Duration::from_secs(1));
            })
            .map_err(|e| io("thread", e))?;
        let handle = handle_rx.recv().map_err(|e| io("runtime", e))??;
        let metrics = Arc::new(EngineMetrics::default());
        let inner = run(&handle, &metrics, "connecting", Inner::connect(cfg, Arc::clone(&metrics)))?;
        Ok(NatsEditStore { inner: Arc::new(inner), metrics, handle, stop: Some(stop), thread: Some(thread) })
    }

    /// Its configuration.
    pub fn config(&self) -> &NatsConfig {
        &self.inner.cfg
    }

    /// Its counters (for the edge's metrics endpoint: [`crate::metrics::Metrics::attach_engine`]).
    pub fn metrics(&self) -> &Arc<EngineMetrics> {
        &self.metrics
    }

    fn run<T: Send + 'static>(
        &self,
        what: &'static str,
        fut: impl std::future::Future<Output = Result<T, EditStoreError>> + Send + 'static,
    ) -> Result<T, EditStoreError> {
        run(&self.handle, &self.metrics, what, fut)
    }
}

/// Run `fut` on the store's runtime and wait for it (from any thread but the runtime's own), at most
/// [`CALL_TIMEOUT`]; its time goes to `metrics`, and a call slower than [`SLOW_CALL`] to the log as `what`.
fn run<T: Send + 'static>(
    handle: &tokio::runtime::Handle,
    metrics: &EngineMetrics,
    what: &'static str,
    fut: impl std::future::Future<Output = Result<T, EditStoreError>> + Send + 'static,
) -> Result<T, EditStoreError> {
    let started = std::time::Instant::now();
    let r = run_untimed(handle, fut);
    let took = started.elapsed();
    metrics.round_trip.record(took);
    if took > SLOW_CALL {
        warn!("the engine took {took:.1?} {what}{}", if r.is_err() { " and failed" } else { "" });
    }
    if r.is_err() {
        metrics.failures.fetch_add(1, Relaxed);
    }
    r
}

fn run_untimed<T: Send + 'static>(
    handle: &tokio::runtime::Handle,
    fut: impl std::future::Future<Output = Result<T, EditStoreError>> + Send + 'static,
) -> Result<T, EditStoreError> {
    let (tx, rx) = std::sync::mpsc::channel();
    handle.spawn(async move {
        let r = match tokio::time::timeout(CALL_TIMEOUT, fut).await {
            Ok(r) => r,
            Err(_) => Err(EditStoreError::Unanswered(format!("NATS: no answer within {CALL_TIMEOUT:?}"))),
        };
        let _ = tx.send(r);
    });
    rx.recv().map_err(|e| io("runtime", e))?
}

impl Inner {
    async fn connect(cfg: NatsConfig, metrics: Arc<EngineMetrics>) -> Result<Inner, EditStoreError> {
        let addrs: Vec<async_nats::ServerAddr> = cfg
            .servers
            .iter()
            .map(|s| s.parse::<async_nats::ServerAddr>().map_err(|e| io(&format!("address {s}"), e)))
            .collect::<Result<_, _>>()?;
        let events = Arc::clone(&metrics);
        let lost = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let client = async_nats::ConnectOptions::new()
            .event_callback(move |event| {
                let (events, lost) = (Arc::clone(&events), Arc::clone(&lost));
                async move {
                    match event {
                        async_nats::Event::Disconnected => {
                            lost.store(true, Relaxed);
                            events.disconnects.fetch_add(1, Relaxed);
                            warn!("lost the connection to NATS; reconnecting");
                        }
                        async_nats::Event::Connected if lost.swap(false, Relaxed) => {
                            events.reconnects.fetch_add(1, Relaxed);
                            warn!("connected to NATS again");
                        }
                        _ => {}
                    }
                }
            })
            .retry_on_initial_connect()
            .connection_timeout(Duration::from_secs(5))
            .connect(addrs)
            .await
            .map_err(|e| io("connect", e))?;
        let mut js = jetstream::new(client.clone());
        // An acknowledgement lost with a node is waited for this long before the publish is sent again.
        js.set_timeout(ACK_TIMEOUT);
        let config = stream::Config {
            name: cfg.stream(),
            subjects: vec![cfg.wildcard()],
            num_replicas: cfg.replicas.max(1),
            storage: stream::StorageType::File,
            duplicate_window: Duration::from_secs(120),
            ..Default::default()
        };
        // A cluster that just started may not have elected its meta leader yet: ask a few times.
        let mut tries = 0;
        let stream = loop {
            match js.get_or_create_stream(config.clone()).await {
                Ok(s) => break s,
                Err(e) if tries < 20 => {
                    debug!("creating the edit stream: {e}; again");
                    tries += 1;
                    tokio::time::sleep(Duration::from_millis(250)).await;
                }
                Err(e) => return Err(io("creating the edit stream", e)),
            }
        };
        Ok(Inner {
            cfg,
            metrics,
            js,
            stream,
            last: Mutex::default(),
            watches: Mutex::default(),
            stream_watch: Mutex::default(),
            tails: Mutex::new(canopy_protocol::lru::Lru::new()),
        })
    }

    fn last(&self, c: CellCoord) -> Known {
        self.last.locked().get(&c).copied().unwrap_or_default()
    }

    /// Learn of a cell's message: the cell's version is at least `k.version`, its subject's last sequence at least
    /// `k.sequence` (a race's loser raises the sequence, not the version).
    fn learn(&self, c: CellCoord, k: Known) {
        let mut last = self.last.locked();
        let known = last.entry(c).or_default();
        known.version = known.version.max(k.version);
        known.sequence = known.sequence.max(k.sequence);
    }

    /// The stream sequence an append of `version` must name as the cell's last edit: that of version − 1, if that
    /// is the last edit this store knows. Otherwise the writer's overlay is behind (a watch told of a later edit)
    /// or ahead of what this store read: the append is refused as a conflict, and the writer reads the cell again.
    /// (Naming the sequence of a later edit would let the engine take the version a second time.)
    fn expected(&self, c: CellCoord, version: u32) -> Option<u64> {
        let k = self.last(c);
        (k.version + 1 == version).then_some(k.sequence)
    }

    /// The subject's last sequence as the engine's compare-and-set takes it, where that is not `known` though no
    /// message follows `known` on the subject; `None` where one does (a real conflict) or the engine agrees.
    ///
    /// nats-server 2.9 loses track of a subject's last message once that message is deleted (a lost race's
    /// publish, taken out by its writer): it answers "no message" for the subject's last and its compare-and-set
    /// then wants 0, though earlier messages remain. Without this a cell whose last message was a deleted one could
    /// never be edited again.
    async fn engine_last(&self, subject: &str, known: u64) -> Result<Option<u64>, EditStoreError> {
        match self.stream.raw_message_builder().sequence(known + 1).next_by_subject(subject.to_string()).send().await {
            Ok(_) => return Ok(None),
            Err(e) if e.kind() == stream::RawMessageErrorKind::NoMessageFound => {}
            Err(e) => return Err(io("checking a cell's last edit", e)),
        }
        let last = match self.stream.get_last_raw_message_by_subject(subject).await {
            Ok(m) => m.sequence,
            Err(e) if e.kind() == stream::LastRawMessageErrorKind::NoMessageFound => 0,
            Err(e) => return Err(io("reading a cell's last edit", e)),
        };
        Ok((last != known).then_some(last))
    }

    /// Publish one cell's edits of a group: each run of consecutive versions (at most [`MAX_RUN`]) one message,
    /// naming the subject sequence of the cell's last edit before it.
    async fn append_cell(self: Arc<Self>, c: CellCoord, edits: Vec<StoredEdit>) -> Result<(), EditStoreError> {
        for run in runs(&edits) {
            self.append_run(c, run).await?;
        }
        Ok(())
    }

    /// Publish one run of a cell's consecutive versions as one message (see the module docs).
    async fn append_run(&self, c: CellCoord, run: &[StoredEdit]) -> Result<(), EditStoreError> {
        let subject = self.cfg.subject(c);
        let (version, last_version) = (run[0].version, run[run.len() - 1].version);
        let payload = encode_run(run);
        // The id names this very run (its bytes, not only its versions): a publish retried after a lost
        // acknowledgement is a duplicate, another run from the same version is not (the compare-and-set refuses
        // that one).
        let digest: [u8; 32] = sha2::Digest::finalize(<sha2::Sha256 as sha2::Digest>::new_with_prefix(&payload)).into();
        let id: String = digest[..12].iter().map(|b| format!("{b:02x}")).collect();
        let payload = bytes::Bytes::from(payload);
        let id = format!("{}.{}.{version}.{id}", c.x, c.z);
        let Some(known) = self.expected(c, version) else {
            return Err(EditStoreError::Conflict { cell: c, version });
        };
        // What the publish names as the subject's last sequence: the last message known, unless the engine
        // has lost track of it (`engine_last`).
        let mut expected = known;
        let mut asked_engine = false;
        // A publish whose answer was lost (its node died, the stream is electing a leader) is sent again, the
        // same message with the same id: if the first was stored, the engine answers the retry as a duplicate
        // (or, having the run as the cell's last, refuses it as a conflict, and the writer finds the run
        // stored when it reads the cell again). Never a second copy.
        let deadline = tokio::time::Instant::now() + PUBLISH_PATIENCE;
        let mut pause = PUBLISH_RETRY;
        loop {
            let msg = jetstream::message::PublishMessage::build()
                .payload(payload.clone())
                .message_id(id.clone())
                .header(RUN_HEADER, "1")
                .expected_last_subject_sequence(expected);
            let ack = async { self.js.send_publish(subject.clone(), msg).await?.await }.await;
            match ack {
                Ok(ack) => {
                    // The engine's compare-and-set is not serializable on a clustered stream in nats-server
                    // before 2.9.21 (nats-io/nats-server#4320): two publishes naming the same last sequence
                    // may both be taken. The first of a cell's messages from a version is that version (the
                    // fold every reader applies, `first_wins`); this one is the version only if it is the
                    // first message on the subject after the one it named.
                    // Messages from earlier versions after the one it named are lost races of those versions
                    // that their writers have not taken out yet: they do not count (counting one made a
                    // winner take itself out, leaving a version missing).
                    let mut from = known + 1;
                    let (first, first_last) = loop {
                        let m = self
                            .stream
                            .raw_message_builder()
                            .sequence(from)
                            .next_by_subject(subject.clone())
                            .send()
                            .await
                            // Stored, but whether first on the subject is not known.
                            .map_err(|err| EditStoreError::Unanswered(format!("NATS checking a publish: {err}")))?;
                        let other = decode_message(Some(&m.headers), &m.payload).ok();
                        let span = other.as_ref().map(|o| (o[0].version, o[o.len() - 1].version));
                        match race_step(version, ack.sequence, m.sequence, span.map(|s| s.0)) {
                            Race::Earlier => from = m.sequence + 1,
                            Race::Decided => break (m, span.map_or(0, |s| s.1)),
                        }
                    };
                    if first.sequence != ack.sequence {
                        // Lost: the message is refused, so it is taken out of the stream too — readers skip
                        // it anyway, and the stream then holds exactly the edits acknowledged. Should the delete
                        // fail, readers still skip it.
                        match self.stream.delete_message(ack.sequence).await {
                            // The winner, from this very version, is the cell's last message again (or a later one
                            // is, which the store learns when it reads or watches the cell).
                            Ok(_) => self.learn(c, Known { version: first_last, sequence: first.sequence }),
                            // Its sequence is not learned: messages between the winner and it are not known, and
                            // naming it would let a run take a version one of them holds. An append naming the
                            // winner finds it there and reads the cell again.
                            Err(err) => debug!(?c, "deleting a lost publish: {err}"),
                        }
                        // The winner's run is told to the cell's watcher now, as its watch will tell it again: the
                        // writer goes on from it without reading the cell again.
                        if let Ok(winner) = decode_message(Some(&first.headers), &first.payload)
                            && winner[0].cell == c
                            && winner[0].version == version
                        {
                            self.advance_tail(c, version - 1, first.sequence, Some(&winner));
                            self.tell(c, winner);
                        }
                        return Err(EditStoreError::Conflict { cell: c, version });
                    }
                    self.learn(c, Known { version: last_version, sequence: ack.sequence });
                    self.advance_tail(c, version - 1, ack.sequence, Some(run));
                    return Ok(());
                }
                Err(err) if err.kind() == PublishErrorKind::WrongLastSequence => {
                    if !asked_engine {
                        asked_engine = true;
                        if let Some(last) = self.engine_last(&subject, known).await? {
                            debug!(?c, known, last, "the engine names another last sequence; again with it");
                            expected = last;
                            continue;
                        }
                    }
                    return Err(EditStoreError::Conflict { cell: c, version });
                }
                Err(err) if tokio::time::Instant::now() + pause < deadline => {
                    debug!(?c, "publishing an edit: {err}; again in {pause:?}");
                    tokio::time::sleep(pause).await;
                    pause = (pause * 2).min(PUBLISH_RETRY_MAX);
                }
                // An answer lost with a node: the publish may yet be stored.
                Err(err) => return Err(EditStoreError::Unanswered(format!("NATS publishing an edit: {err}"))),
            }
        }
    }

    async fn load(&self, c: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError> {
        let subject = self.cfg.subject(c);
        // The cell's runs, each the next on the subject after the previous, until there is none (reads go to the
        // stream's leader, so a write another edge saw acknowledged is there). Not bounded by the subject's last
        // message as the engine reports it: nats-server 2.9 can answer "no message" for the last message of a
        // subject whose last message was deleted (a lost race's publish, taken out), though earlier ones remain.
        // A cell read before is read on from the last message read then: messages only ever join a subject at higher
        // sequences, and the fold over them (`first_wins`) is the same taken in parts.
        let (mut out, mut last) = match self.tails.locked().get(&c) {
            Some(t) => (t.edits.clone(), t.last),
            None => (Vec::new(), 0),
        };
        let mut seq = last + 1;
        loop {
            let m = match self.stream.raw_message_builder().sequence(seq).next_by_subject(subject.clone()).send().await
            {
                Ok(m) => m,
                Err(e) if e.kind() == stream::RawMessageErrorKind::NoMessageFound => break,
                Err(e) => return Err(io("reading a cell's edits", e)),
            };
            self.metrics.log_reads.fetch_add(1, Relaxed);
            let run = match decode_message(Some(&m.headers), &m.payload) {
                Ok(run) => run,
                Err(e) => {
                    return Err(EditStoreError::Damaged {
                        store: format!("NATS stream {} sequence {}", self.cfg.stream(), m.sequence),
                        cell: c,
                        version: out.len() as u32 + 1,
                        why: e.to_string(),
                        readable: out,
                    });
                }
            };
            if run[0].cell != c {
                return Err(EditStoreError::Corrupt(format!(
                    "cell {c:?} sequence {} holds {:?}",
                    m.sequence, run[0].cell
                )));
            }
            if first_wins(out.len() as u32, run[0].version)
                .map_err(|v| EditStoreError::Corrupt(format!("cell {c:?} sequence {}: {v}", m.sequence)))?
            {
                out.extend(run);
            }
            last = m.sequence;
            seq = m.sequence + 1;
        }
        self.learn(c, Known { version: out.len() as u32, sequence: last });
        let mut tails = self.tails.locked();
        let cost = TAIL_EDIT_BYTES * (out.len() + 1);
        tails.insert(c, Tail { edits: out.clone(), last }, cost);
        tails.evict_to(TAIL_CACHE_BYTES, Some(&c));
        Ok(out)
    }

    /// The fold of cell `c`'s subject went on over the message at `sequence` from `before` versions, taking `run`
    /// (a winner) or skipping it (`None`, a lost race): the cell's kept tail follows if it was at that state and
    /// behind the message, so reading the cell again reads only what neither this edge wrote nor its watch told.
    /// (Two states of the fold with the same versions have only lost races between them.)
    fn advance_tail(&self, c: CellCoord, before: u32, sequence: u64, run: Option<&[StoredEdit]>) {
        let mut tails = self.tails.locked();
        let Some(t) = tails.get(&c) else { return };
        if t.edits.len() as u32 != before || t.last >= sequence {
            return;
        }
        t.edits.extend_from_slice(run.unwrap_or_default());
        t.last = sequence;
        let cost = TAIL_EDIT_BYTES * (t.edits.len() + 1);
        tails.set_cost(&c, cost);
        tails.evict_to(TAIL_CACHE_BYTES, Some(&c));
    }

    /// Tell cell `c`'s watcher, if the cell is watched, of `run` (a winner of the fold).
    fn tell(&self, c: CellCoord, run: Vec<StoredEdit>) {
        // Not under the lock: a watcher may stop watching cells.
        let watcher = self.watches.locked().get(&c).map(|(_, slot)| Arc::clone(&*slot.locked()));
        if let Some(watcher) = watcher {
            for e in run {
                watcher.edited(e);
            }
        }
    }

    /// Every edited cell and its latest version, as the last message on its subject says (one request a cell, a
    /// few at a time); a subject whose last message the engine cannot name (deleted: see `load`) is read whole.
    async fn versions(self: &Arc<Self>) -> Result<Vec<(CellCoord, u32)>, EditStoreError> {
        let mut subjects = self.stream.info_with_subjects(self.cfg.wildcard()).await.map_err(|e| io("info", e))?;
        let mut cells = Vec::new();
        while let Some((subject, _)) = subjects.try_next().await.map_err(|e| io("info", e))? {
            cells.extend(self.cfg.cell_of(&subject));
        }
        let mut out: Vec<(CellCoord, u32)> = futures_util::stream::iter(cells)
            .map(|c| async move {
                let m = match self.stream.get_last_raw_message_by_subject(&self.cfg.subject(c)).await {
                    Ok(m) => m,
                    Err(e) if e.kind() == stream::LastRawMessageErrorKind::NoMessageFound => {
                        return Ok((c, self.load(c).await?.len() as u32));
                    }
                    Err(e) => return Err(io("reading a cell's last edit", e)),
                };
                let run = decode_message(Some(&m.headers), &m.payload)
                    .map_err(|e| EditStoreError::Corrupt(format!("cell {c:?} sequence {}: {e}", m.sequence)))?;
                Ok((c, run[run.len() - 1].version))
            })
            .buffer_unordered(32)
            .try_collect()
            .await?;
        out.retain(|&(_, v)| v > 0);
        out.sort_unstable();
        Ok(out)
    }
}

/// The header that marks a message as a run of edits ([`encode_run`]); a message without it is one
/// [`StoredEdit`] (what streams written before runs hold).
const RUN_HEADER: &str = "Canopy-Run";

/// The edits of a message on a cell's subject: a run, or one edit.
fn decode_message(headers: Option<&async_nats::HeaderMap>, payload: &[u8]) -> Result<Vec<StoredEdit>, LogError> {
    match headers.and_then(|h| h.get(RUN_HEADER)) {
        Some(_) => decode_run(payload),
        None => StoredEdit::decode(payload).map(|e| vec![e]),
    }
}

/// A cell's edits of a group cut into runs: consecutive versions, at most [`MAX_RUN`] a run (a version that does
/// not follow the one before starts a run of its own, which the store refuses as a conflict).
fn runs(edits: &[StoredEdit]) -> impl Iterator<Item = &[StoredEdit]> {
    edits.chunk_by(|a, b| b.version == a.version + 1).flat_map(|run| run.chunks(MAX_RUN))
}

/// What a message after the one a publish named says of the publish's race ([`race_step`]).
#[derive(Debug, PartialEq, Eq)]
enum Race {
    /// A lost race of an earlier version its writer has not taken out yet: look at the next message.
    Earlier,
    /// The race is decided: won if this message is the publish itself, lost otherwise.
    Decided,
}

/// A publish of a run from `version` acknowledged at sequence `ours` meets the message at `sequence` (a run from
/// `other`'s version, `None` if it does not decode), the next after the one it named: is that message the race's
/// first, or one to pass?
fn race_step(version: u32, ours: u64, sequence: u64, other: Option<u32>) -> Race {
    match other {
        Some(v) if sequence != ours && v < version => Race::Earlier,
        _ => Race::Decided,
    }
}

/// The fold every reader of a cell's subject applies, given the versions taken so far and the first version of the
/// next message's run: `Ok(true)` the run is the next versions; `Ok(false)` it starts at a version already taken — the loser of a race
/// the engine let through, never acknowledged (its writer checked), skipped; `Err` a version skipped: damage.
fn first_wins(taken: u32, version: u32) -> Result<bool, String> {
    match version {
        v if v == taken + 1 => Ok(true),
        v if v <= taken => Ok(false),
        v => Err(format!("version {v} after version {taken}")),
    }
}

/// Who a watch tells, replaceable while it runs: a cell read again keeps its watch.
type WatcherSlot = Arc<Mutex<Arc<dyn EditWatcher>>>;

/// Forward cell `c`'s edits from subject sequence `next` on to the watcher, for as long as the task lives: an ordered
/// consumer of the cell's subject, created again from just after the last message seen whenever it cannot be created
/// or its stream ends or fails (a node died), with a growing pause between attempts. `taken` is the cell's version
/// before `next`; the watch applies the readers' fold (`first_wins`), so a lost race not yet taken out is never told.
async fn watch_cell(inner: Arc<Inner>, c: CellCoord, mut next: u64, mut taken: u32, watcher: WatcherSlot) {
    let mut pause = WATCH_RETRY;
    // Once a message does not decode or leaves a gap, this watch no longer moves the kept tail on.
    let mut damaged = false;
    loop {
        let from = jetstream::consumer::DeliverPolicy::ByStartSequence { start_sequence: next };
        let mut messages = ordered(&inner, inner.cfg.subject(c), from, &mut pause).await;
        while let Some(m) = messages.next().await {
            let m = match m {
                Ok(m) => m,
                Err(e) => {
                    warn!(?c, "watching the cell: {e}; watching again from sequence {next}");
                    break;
                }
            };
            let Ok(sequence) = m.info().map(|i| i.stream_sequence) else {
                warn!(?c, "watching the cell: a message without its stream sequence");
                continue;
            };
            next = next.max(sequence + 1);
            let run = match decode_message(m.headers.as_ref(), &m.payload) {
                Ok(run) if run[0].cell == c => run,
                other => {
                    match other {
                        Ok(_) => warn!(?c, "a message on the cell's subject names another cell"),
                        Err(e) => warn!(?c, "watching the cell: sequence {sequence}: {e}"),
                    }
                    // The kept tail stays before it: a read of the cell meets it and reports it.
                    damaged = true;
                    continue;
                }
            };
            let last = run[run.len() - 1].version;
            let winner = first_wins(taken, run[0].version);
            if !damaged && let Ok(won) = winner {
                inner.advance_tail(c, taken, sequence, won.then_some(&run[..]));
            }
            match winner {
                // A lost race its writer has not taken out yet: what the next append must name as the subject's
                // last message while it stays, not a version.
                Ok(false) => inner.learn(c, Known { version: 0, sequence }),
                // The next versions, or a gap (damage): told either way, the watcher reads the cell again on a gap.
                Ok(true) | Err(_) => {
                    damaged |= winner.is_err();
                    taken = last;
                    // What this edge's next append to the cell must name as the cell's last edit, and its version.
                    inner.learn(c, Known { version: last, sequence });
                    inner.metrics.deltas_in.fetch_add(run.len() as u64, Relaxed);
                    let watcher = Arc::clone(&*watcher.locked());
                    for e in run {
                        watcher.edited(e);
                    }
                }
            }
        }
        tokio::time::sleep(pause).await;
    }
}

/// The messages of an ordered consumer of `filter_subject` from `from`, created again until it can be, after a pause
/// that doubles from [`WATCH_RETRY`] up to [`WATCH_RETRY_MAX`] (`pause`: the watch's, back to the first once
/// created).
async fn ordered(
    inner: &Inner,
    filter_subject: String,
    from: jetstream::consumer::DeliverPolicy,
    pause: &mut Duration,
) -> jetstream::consumer::pull::Ordered {
    loop {
        let config = jetstream::consumer::pull::OrderedConfig {
            filter_subject: filter_subject.clone(),
            deliver_policy: from,
            ..Default::default()
        };
        let created = match inner.stream.create_consumer(config).await {
            Ok(consumer) => consumer.messages().await.map_err(|e| e.to_string()),
            Err(e) => Err(e.to_string()),
        };
        match created {
            Ok(m) => {
                *pause = WATCH_RETRY;
                return m;
            }
            Err(e) => {
                warn!(subject = filter_subject, "watching: {e}; trying again in {pause:?}");
                tokio::time::sleep(*pause).await;
                *pause = (*pause * 2).min(WATCH_RETRY_MAX);
            }
        }
    }
}

/// Tell `watcher` of every run any writer publishes on the world's subjects from now on, as published (a lost
/// race's too: the edge's index of edited cells takes only versions from it, as [`Inner::versions`] takes a subject's
/// last message): one ordered consumer of the whole stream a store, created again from just after the last
/// message seen whenever it cannot be created or its stream ends or fails.
async fn watch_stream(inner: Arc<Inner>, watcher: Arc<dyn EditWatcher>) {
    let mut pause = WATCH_RETRY;
    let mut next: Option<u64> = None;
    loop {
        let from = match next {
            Some(start_sequence) => jetstream::consumer::DeliverPolicy::ByStartSequence { start_sequence },
            None => jetstream::consumer::DeliverPolicy::New,
        };
        let mut messages = ordered(&inner, inner.cfg.wildcard(), from, &mut pause).await;
        while let Some(m) = messages.next().await {
            let m = match m {
                Ok(m) => m,
                Err(e) => {
                    warn!("watching the edit stream: {e}; watching again");
                    break;
                }
            };
            if let Ok(info) = m.info() {
                next = Some(info.stream_sequence + 1);
            }
            let cell = inner.cfg.cell_of(m.subject.as_str());
            match decode_message(m.headers.as_ref(), &m.payload) {
                Ok(run) if Some(run[0].cell) == cell => run.into_iter().for_each(|e| watcher.edited(e)),
                // A cell's own watch and reads report what does not decode.
                _ => {}
            }
        }
        tokio::time::sleep(pause).await;
    }
}

impl EditStore for NatsEditStore {
    fn append(&self, edits: &[StoredEdit]) -> Result<(), EditStoreError> {
        self.append_cells(edits).into_iter().map(|(_, r)| r).find(Result::is_err).unwrap_or(Ok(()))
    }

    /// Each cell's runs are published on their own, concurrently: one cell's conflict leaves the others stored.
    fn append_cells(&self, edits: &[StoredEdit]) -> Vec<(CellCoord, Result<(), EditStoreError>)> {
        let mut by_cell: BTreeMap<CellCoord, Vec<StoredEdit>> = BTreeMap::new();
        for e in edits {
            by_cell.entry(e.cell).or_default().push(e.clone());
        }
        let cells: Vec<CellCoord> = by_cell.keys().copied().collect();
        let inner = Arc::clone(&self.inner);
        let all = self.run("appending edits", async move {
            let tasks: Vec<_> =
                by_cell.into_iter().map(|(c, v)| tokio::spawn(Arc::clone(&inner).append_cell(c, v))).collect();
            let mut out = Vec::with_capacity(tasks.len());
            for t in tasks {
                out.push(t.await.map_err(|e| io("append task", e)).and_then(|r| r));
            }
            Ok(out)
        });
        match all {
            Ok(each) => cells.into_iter().zip(each).collect(),
            // No answer in time: whether any cell was stored is not known.
            Err(e) => cells.into_iter().map(|c| (c, Err(e.clone()))).collect(),
        }
    }

    fn load(&self, c: CellCoord) -> Result<Vec<StoredEdit>, EditStoreError> {
        let inner = Arc::clone(&self.inner);
        self.run("reading a cell's edits", async move { inner.load(c).await })
    }

    fn cells(&self) -> Result<Vec<(CellCoord, u32)>, EditStoreError> {
        let inner = Arc::clone(&self.inner);
        self.run("listing the edited cells", async move { inner.versions().await })
    }

    /// The sum of the cells' versions. A subject whose last message is a lost race its writer could not take out
    /// counts that run's last version (the store then under-counts until the next edit of the cell).
    fn count(&self) -> Result<u64, EditStoreError> {
        Ok(self.cells()?.iter().map(|&(_, v)| u64::from(v)).sum())
    }

    fn describe(&self) -> String {
        format!("NATS stream {} at {}", self.inner.cfg.stream(), self.inner.cfg.servers.join(","))
    }

    fn watch(&self, c: CellCoord, watcher: Arc<dyn EditWatcher>) {
        let inner = Arc::clone(&self.inner);
        let mut watches = self.inner.watches.locked();
        // A cell read again (another edge's edit, a conflict) keeps the watch it has: the watch folds the subject
        // itself, so it tells exactly the versions that follow whatever it told before, and a new consumer for
        // every conflict would cost the engine more than the conflict.
        if let Some((task, slot)) = watches.get(&c)
            && !task.is_finished()
        {
            *slot.locked() = watcher;
            return;
        }
        // The watch starts just after the last message the read of the log saw; it is set up on the store's runtime,
        // not here: a cluster electing a leader can take seconds to create a consumer, and neither the writer nor
        // a loader waits for that (nothing is missed: the consumer starts at that sequence whenever it starts).
        let (next, taken) = match inner.tails.locked().peek(&c) {
            Some(t) => (t.last + 1, t.edits.len() as u32),
            None => {
                let k = inner.last(c);
                (k.sequence + 1, k.version)
            }
        };
        let slot: WatcherSlot = Arc::new(Mutex::new(watcher));
        let task = self.handle.spawn(watch_cell(inner, c, next, taken, Arc::clone(&slot)));
        if let Some((old, _)) = watches.insert(c, (task, slot)) {
            old.abort();
        }
        self.metrics.watched.store(watches.len() as u64, Relaxed);
    }

    fn watch_all(&self, watcher: Arc<dyn EditWatcher>) {
        let task = self.handle.spawn(watch_stream(Arc::clone(&self.inner), watcher));
        if let Some(old) = self.inner.stream_watch.locked().replace(task) {
            old.abort();
        }
    }

    fn unwatch(&self, c: CellCoord) {
        let mut watches = self.inner.watches.locked();
        if let Some((t, _)) = watches.remove(&c) {
            // Dropping the consumer's message stream with its task ends it (an ordered consumer is ephemeral).
            t.abort();
        }
        self.metrics.watched.store(watches.len() as u64, Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_message_of_a_version_wins() {
        assert_eq!(first_wins(0, 1), Ok(true));
        assert_eq!(first_wins(4, 5), Ok(true));
        // A race's loser: the version is taken already.
        assert_eq!(first_wins(5, 5), Ok(false));
        assert_eq!(first_wins(5, 3), Ok(false));
        // A version skipped is damage.
        assert!(first_wins(5, 7).is_err());
        assert!(first_wins(0, 2).is_err());
    }

    #[test]
    fn an_earlier_versions_lost_race_does_not_decide_a_publish() {
        // Version 5 published at 810 after a version-4 loser at 805 not yet taken out: pass it, then 810 is ours.
        assert_eq!(race_step(5, 810, 805, Some(4)), Race::Earlier);
        assert_eq!(race_step(5, 810, 810, Some(5)), Race::Decided);
        // Another version 5 first: lost; a message that does not decode decides too (it is not passed over).
        assert_eq!(race_step(5, 810, 807, Some(5)), Race::Decided);
        assert_eq!(race_step(5, 810, 807, None), Race::Decided);
    }

    #[test]
    fn subjects_name_their_cells() {
        let cfg = NatsConfig { servers: vec![], world: "the forest!".into(), replicas: 3 };
        assert_eq!(cfg.stream(), "CANOPY_EDITS_the_forest_");
        let c = CellCoord::new(-3, 17);
        assert_eq!(cfg.cell_of(&cfg.subject(c)), Some(c));
        assert_eq!(cfg.cell_of("canopy.edits.other.1.2"), None);
    }
}
