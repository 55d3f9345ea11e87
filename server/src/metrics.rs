//! Server-wide counters and their Prometheus text exposition (format 0.0.4): clients, bytes and messages by
//! message class, records sent and records per second, sessions closed by reason, process memory, and the cell
//! cache's hits, misses, expansions (count, rate, time percentiles), bytes and cells, and the edit pipeline's
//! outcomes, groups and commit times, and an edge's distributed engine (round trip, watched cells, edits in,
//! reconnects).

use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, OnceLock};
use std::time::Instant;

use canopy_protocol::CloseCode;
use canopy_protocol::messages::ByKind;
use canopy_protocol::sync::Locked;

use canopy_protocol::messages::ServerMsgKind;
pub(crate) use canopy_session::counters::{CellMetrics, Histogram};

use crate::admission::Refusal;

/// Counters shared by every connection of one server.
#[derive(Debug)]
pub struct Metrics {
    started: Instant,
    /// Clients connected now (handshake completed: holding a client slot).
    pub clients: AtomicU64,
    /// Of those, the clients of each of the server's endpoints (its UDP sockets on the one port).
    pub endpoint_clients: Box<[AtomicU64]>,
    /// Of those, the browsers' (WebTransport sessions, ALPN `h3`).
    pub web_clients: AtomicU64,
    /// QUIC handshakes in flight now.
    pub handshakes: AtomicU64,
    /// Incoming connections answered with a QUIC Retry (address validation).
    pub retries: AtomicU64,
    /// Incoming connections refused: server full, too many handshakes, the source's share taken.
    pub refused: [AtomicU64; Refusal::ALL.len()],
    /// Connections accepted since start.
    pub connections: AtomicU64,
    /// Sessions that reached the streaming phase.
    pub sessions: AtomicU64,
    /// Bytes by [`ServerMsgKind`].
    pub bytes: ByKind<AtomicU64>,
    /// Messages by [`ServerMsgKind`].
    pub messages: ByKind<AtomicU64>,
    /// Instance records sent.
    pub records: AtomicU64,
    /// Bytes received from clients (frames).
    pub bytes_in: AtomicU64,
    /// Viewpoints received.
    pub viewpoints: AtomicU64,
    /// Digests of clients' own expansions checked against the server's cells.
    pub digests_checked: AtomicU64,
    /// Digests that differed (each such cell is sent to that client as records from then on).
    pub digest_mismatches: AtomicU64,
    /// Connections closed, by [`CloseCode`] (index = code), plus one last slot for transport errors.
    pub closed: [AtomicU64; TRANSPORT + 1],
    /// Records per second over the last completed second (updated by [`Metrics::tick`]).
    pub records_per_second: AtomicU64,
    /// Cell expansions per second over the last completed second (updated by [`Metrics::tick`]).
    pub expansions_per_second: AtomicU64,
    last_tick: std::sync::Mutex<(Instant, u64, u64)>,
    /// The cell cache's counters, when the store has a cache.
    cells: OnceLock<Arc<CellMetrics>>,
    /// The edit pipeline's counters, when the server takes edits.
    edits: OnceLock<Arc<crate::editing::EditMetrics>>,
    /// The shared edit log's counters, when the server is an edge over a distributed engine.
    engine: OnceLock<Arc<EngineMetrics>>,
}

/// An edge's counters of the distributed engine that holds the edit log (NATS JetStream): what a call costs, what
/// the edge watches, what reaches it, how often its connection was re-established. Deltas out to the sessions are
/// `canopy_sent_messages_total{class="delta"}`.
#[derive(Debug, Default)]
pub struct EngineMetrics {
    /// Time of each call to the engine: a group's appends (acknowledged at the stream's replication), a cell's
    /// read, the start of a watch.
    pub round_trip: Histogram,
    /// Cells watched now.
    pub watched: AtomicU64,
    /// Edits the watches delivered (every edge's, this one's included).
    pub deltas_in: AtomicU64,
    /// Times the connection to the engine was lost.
    pub disconnects: AtomicU64,
    /// Times it was re-established after a loss.
    pub reconnects: AtomicU64,
    /// Calls that failed (no answer in time, no quorum).
    pub failures: AtomicU64,
    /// Messages read from cells' subjects one by one (a cell read again reads only its new ones).
    pub log_reads: AtomicU64,
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new(1)
    }
}

/// The slot of [`Metrics::closed`] that counts transport failures, after every [`CloseCode`].
const TRANSPORT: usize = CloseCode::ALL.len();

impl Metrics {
    /// All counters at zero, for a server with `endpoints` endpoints.
    pub fn new(endpoints: usize) -> Metrics {
        let now = Instant::now();
        Metrics {
            started: now,
            clients: AtomicU64::new(0),
            endpoint_clients: (0..endpoints.max(1)).map(|_| AtomicU64::new(0)).collect(),
            web_clients: AtomicU64::new(0),
            handshakes: AtomicU64::new(0),
            retries: AtomicU64::new(0),
            refused: Default::default(),
            connections: AtomicU64::new(0),
            sessions: AtomicU64::new(0),
            bytes: Default::default(),
            messages: Default::default(),
            records: AtomicU64::new(0),
            bytes_in: AtomicU64::new(0),
            viewpoints: AtomicU64::new(0),
            digests_checked: AtomicU64::new(0),
            digest_mismatches: AtomicU64::new(0),
            closed: Default::default(),
            records_per_second: AtomicU64::new(0),
            expansions_per_second: AtomicU64::new(0),
            last_tick: std::sync::Mutex::new((now, 0, 0)),
            cells: OnceLock::new(),
            edits: OnceLock::new(),
            engine: OnceLock::new(),
        }
    }

    /// Report the cell cache's counters too (once; later calls are ignored).
    pub fn attach_cells(&self, cells: Arc<CellMetrics>) {
        let _ = self.cells.set(cells);
    }

    /// Report the edit pipeline's counters too (once; later calls are ignored).
    pub fn attach_edits(&self, edits: Arc<crate::editing::EditMetrics>) {
        let _ = self.edits.set(edits);
    }

    /// Report the distributed engine's counters too (once; later calls are ignored).
    pub fn attach_engine(&self, engine: Arc<EngineMetrics>) {
        let _ = self.engine.set(engine);
    }

    /// The cell cache's counters, if attached.
    pub fn cells(&self) -> Option<&Arc<CellMetrics>> {
        self.cells.get()
    }

    /// Count one refused incoming connection.
    pub fn refused(&self, why: Refusal) {
        self.refused[why as usize].fetch_add(1, Relaxed);
    }

    /// Count one transmitted message.
    pub fn sent(&self, class: ServerMsgKind, bytes: usize, records: u32) {
        self.bytes[class].fetch_add(bytes as u64, Relaxed);
        self.messages[class].fetch_add(1, Relaxed);
        self.records.fetch_add(u64::from(records), Relaxed);
    }

    /// Count one closed connection (`None`: the transport failed or the peer vanished).
    pub fn closed(&self, code: Option<CloseCode>) {
        let i = code.map_or(TRANSPORT, |c| c as usize);
        self.closed[i].fetch_add(1, Relaxed);
    }

    /// Update the records- and expansions-per-second gauges; call about once a second.
    pub fn tick(&self, now: Instant) {
        let records = self.records.load(Relaxed);
        let expansions = self.cells.get().map_or(0, |c| c.expansions.load(Relaxed));
        let mut last = self.last_tick.locked();
        let dt = now.saturating_duration_since(last.0).as_secs_f64();
        if dt > 0.0 {
            let rate = |n: u64, before: u64| (n.saturating_sub(before) as f64 / dt).round() as u64;
            self.records_per_second.store(rate(records, last.1), Relaxed);
            self.expansions_per_second.store(rate(expansions, last.2), Relaxed);
            *last = (now, records, expansions);
        }
    }

    /// The Prometheus text exposition of every counter.
    pub fn render(&self) -> String {
        let mut s = String::new();
        let mut metric = |name: &str, kind: &str, help: &str, samples: &[(String, u64)]| {
            let _ = writeln!(s, "# HELP {name} {help}\n# TYPE {name} {kind}");
            for (labels, v) in samples {
                let _ = writeln!(s, "{name}{labels} {v}");
            }
        };
        let one = |v: &AtomicU64| vec![(String::new(), v.load(Relaxed))];
        metric("canopy_clients", "gauge", "Clients connected now.", &one(&self.clients));
        let per_endpoint: Vec<(String, u64)> = (self.endpoint_clients.iter().enumerate())
            .map(|(i, n)| (format!("{{endpoint=\"{i}\"}}"), n.load(Relaxed)))
            .collect();
        let help = "Clients connected now, by the endpoint (UDP socket) that accepted them.";
        metric("canopy_endpoint_clients", "gauge", help, &per_endpoint);
        let help = "Clients connected now over WebTransport (browsers).";
        metric("canopy_web_clients", "gauge", help, &one(&self.web_clients));
        metric("canopy_handshakes", "gauge", "QUIC handshakes in flight now.", &one(&self.handshakes));
        metric("canopy_retries_total", "counter", "Incoming connections sent a QUIC Retry.", &one(&self.retries));
        let refused: Vec<(String, u64)> = Refusal::ALL
            .into_iter()
            .map(|r| (format!("{{reason=\"{}\"}}", r.label()), self.refused[r as usize].load(Relaxed)))
            .collect();
        metric("canopy_refused_total", "counter", "Incoming connections refused, by reason.", &refused);
        metric("canopy_connections_total", "counter", "Connections accepted.", &one(&self.connections));
        metric("canopy_sessions_total", "counter", "Sessions that reached streaming.", &one(&self.sessions));
        let by_class = |a: &ByKind<AtomicU64>| {
            a.iter().map(|(c, v)| (format!("{{class=\"{}\"}}", c.name()), v.load(Relaxed))).collect::<Vec<_>>()
        };
        metric("canopy_sent_bytes_total", "counter", "Bytes sent by message class.", &by_class(&self.bytes));
        metric("canopy_sent_messages_total", "counter", "Messages sent by message class.", &by_class(&self.messages));
        metric("canopy_records_sent_total", "counter", "Instance records sent.", &one(&self.records));
        metric(
            "canopy_records_per_second",
            "gauge",
            "Instance records sent per second, over the last second.",
            &one(&self.records_per_second),
        );
        metric("canopy_received_bytes_total", "counter", "Bytes received from clients.", &one(&self.bytes_in));
        metric("canopy_viewpoints_total", "counter", "Viewpoints received.", &one(&self.viewpoints));
        let help = "Digests of clients' own cell expansions checked.";
        metric("canopy_digests_checked_total", "counter", help, &one(&self.digests_checked));
        let help = "Clients' cell expansions found to differ (served as records since).";
        metric("canopy_digest_mismatches_total", "counter", help, &one(&self.digest_mismatches));
        let labels = CloseCode::ALL.iter().map(|c| c.label()).chain(["transport"]);
        let closed: Vec<_> =
            labels.zip(&self.closed).map(|(l, n)| (format!("{{reason=\"{l}\"}}"), n.load(Relaxed))).collect();
        metric("canopy_closed_total", "counter", "Connections closed, by reason.", &closed);
        metric(
            "canopy_uptime_seconds",
            "gauge",
            "Seconds since the server started.",
            &[(String::new(), self.started.elapsed().as_secs())],
        );
        if let Some(c) = self.cells.get() {
            metric("canopy_cell_cache_hits_total", "counter", "Cell lookups that found the cell ready.", &one(&c.hits));
            let help = "Cell lookups that queued an expansion (neither ready nor queued already).";
            metric("canopy_cell_cache_misses_total", "counter", help, &one(&c.misses));
            metric("canopy_cell_expansions_total", "counter", "Cell expansions finished.", &one(&c.expansions));
            let help = "Cell expansions per second, over the last second.";
            metric("canopy_cell_expansions_per_second", "gauge", help, &one(&self.expansions_per_second));
            metric("canopy_cell_evictions_total", "counter", "Cells evicted from the cache.", &one(&c.evictions));
            metric("canopy_cell_expansion_failures_total", "counter", "Cell expansions failed.", &one(&c.failures));
            metric("canopy_cell_cache_bytes", "gauge", "Bytes the cached cells hold.", &one(&c.bytes));
            metric("canopy_cell_cache_limit_bytes", "gauge", "The cell cache's bound.", &one(&c.limit));
            metric("canopy_cell_cache_cells", "gauge", "Cells cached.", &one(&c.cells));
            metric("canopy_cell_expansions_queued", "gauge", "Cells waiting for a worker.", &one(&c.queued));
            let help = "Queued cells dropped unexpanded: every session that wanted them moved on or left.";
            metric("canopy_cell_expansions_cancelled_total", "counter", help, &one(&c.cancelled));
            metric("canopy_summaries_total", "counter", "Far-view summary nodes computed.", &one(&c.summaries));
            metric(
                "canopy_summary_cache_bytes",
                "gauge",
                "Bytes the cached summary nodes hold.",
                &one(&c.summary_bytes),
            );
            for (q, label) in [(0.5, "p50"), (0.99, "p99")] {
                let us = c.expansion_time.quantile(q).map_or(0, |d| d.as_micros() as u64);
                let help = format!("Cell expansion time, {label}, microseconds (its histogram bucket's upper bound).");
                metric(&format!("canopy_cell_expansion_{label}_microseconds"), "gauge", &help, &[(String::new(), us)]);
            }
        }
        if let Some(e) = self.edits.get() {
            let outcomes: Vec<(String, u64)> = ["ok", "denied", "invalid", "conflict"]
                .iter()
                .zip(&e.outcomes)
                .map(|(l, n)| (format!("{{outcome=\"{l}\"}}"), n.load(Relaxed)))
                .collect();
            metric("canopy_edits_total", "counter", "Edits answered, by outcome.", &outcomes);
            let help = "Groups of edits written durably (one transaction each: group commit).";
            metric("canopy_edit_groups_total", "counter", help, &one(&e.groups));
            let help = "Stored edits not served: the world cannot take them, or they do not decode (at every read of their cell).";
            metric("canopy_edits_skipped_total", "counter", help, &one(&e.skipped));
            let help = "Edits dropped unwritten because their session ended before they were written.";
            metric("canopy_edits_abandoned_total", "counter", help, &one(&e.abandoned));
            let help = "Cells of a group another writer had changed first (their edits go round again).";
            metric("canopy_edit_cell_conflicts_total", "counter", help, &one(&e.cell_conflicts));
        }
        if let Some(e) = self.engine.get() {
            metric("canopy_engine_watched_cells", "gauge", "Cells whose edits this edge watches.", &one(&e.watched));
            let help = "Edits the engine's watches delivered to this edge.";
            metric("canopy_engine_deltas_in_total", "counter", help, &one(&e.deltas_in));
            let help = "Times the connection to the engine was lost.";
            metric("canopy_engine_disconnects_total", "counter", help, &one(&e.disconnects));
            let help = "Times the connection to the engine was re-established.";
            metric("canopy_engine_reconnects_total", "counter", help, &one(&e.reconnects));
            let help = "Calls to the engine that failed (no answer in time, no quorum).";
            metric("canopy_engine_failures_total", "counter", help, &one(&e.failures));
            let help = "Messages read from cells' subjects one by one (a cell read again reads only its new ones).";
            metric("canopy_engine_log_reads_total", "counter", help, &one(&e.log_reads));
        }
        if let Some(rss) = resident_bytes() {
            metric("canopy_resident_bytes", "gauge", "Resident memory of the server process.", &[(String::new(), rss)]);
        }
        if let Some(c) = self.cells.get() {
            let help = "Time to expand, quantise and encode one cell.";
            c.expansion_time.render(&mut s, "canopy_cell_expansion_seconds", help);
        }
        if let Some(e) = self.edits.get() {
            let help = "Time from a group's first edit to its durable commit.";
            e.commit_time.render(&mut s, "canopy_edit_commit_seconds", help);
        }
        if let Some(e) = self.engine.get() {
            let help = "Time of one call to the engine (a group's appends, a cell's read, a watch's start).";
            e.round_trip.render(&mut s, "canopy_engine_round_trip_seconds", help);
        }
        s
    }
}

/// The process's resident set size (VmRSS from /proc/self/status), where the platform has one.
pub fn resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn exposition_has_every_family_and_counts() {
        let m = Metrics::new(2);
        m.endpoint_clients[1].fetch_add(3, Relaxed);
        m.sent(ServerMsgKind::Cells, 100, 20);
        m.sent(ServerMsgKind::Species, 900, 0);
        m.closed(Some(CloseCode::Malformed));
        let text = m.render();
        assert!(text.contains("canopy_sent_bytes_total{class=\"cells\"} 100"), "{text}");
        assert!(text.contains("canopy_sent_bytes_total{class=\"species\"} 900"), "{text}");
        assert!(text.contains("canopy_records_sent_total 20"), "{text}");
        assert!(text.contains("canopy_closed_total{reason=\"malformed\"} 1"), "{text}");
        assert!(text.contains("# TYPE canopy_clients gauge"), "{text}");
        assert!(text.contains("canopy_endpoint_clients{endpoint=\"0\"} 0"), "{text}");
        assert!(text.contains("canopy_endpoint_clients{endpoint=\"1\"} 3"), "{text}");
        assert!(!text.contains("canopy_cell_"), "no cache, no cache families");
    }

    #[test]
    fn the_cell_cache_families_and_expansion_percentiles() {
        let m = Metrics::new(1);
        let cells = Arc::new(CellMetrics::default());
        m.attach_cells(Arc::clone(&cells));
        // 98 fast expansions (≤ 64 µs), 2 slow ones (≤ 8 ms).
        for _ in 0..98 {
            cells.expansion_time.record(Duration::from_micros(40));
        }
        for _ in 0..2 {
            cells.expansion_time.record(Duration::from_micros(5_000));
        }
        cells.expansions.store(100, Relaxed);
        cells.hits.store(7, Relaxed);
        assert_eq!(cells.expansion_time.quantile(0.5), Some(Duration::from_micros(64)));
        assert_eq!(cells.expansion_time.quantile(0.98), Some(Duration::from_micros(64)));
        assert_eq!(cells.expansion_time.quantile(0.99), Some(Duration::from_micros(8192)));
        assert_eq!(Histogram::default().quantile(0.5), None);
        let t0 = Instant::now();
        m.tick(t0 + Duration::from_secs(2));
        let text = m.render();
        assert!(text.contains("canopy_cell_expansions_total 100"), "{text}");
        assert!(text.contains("canopy_cell_cache_hits_total 7"), "{text}");
        assert!(text.contains("canopy_cell_expansion_p50_microseconds 64"), "{text}");
        assert!(text.contains("canopy_cell_expansion_p99_microseconds 8192"), "{text}");
        assert!(text.contains("canopy_cell_expansion_seconds_bucket{le=\"+Inf\"} 100"), "{text}");
        assert!(text.contains("canopy_cell_expansion_seconds_count 100"), "{text}");
        assert!(text.contains("# TYPE canopy_cell_expansion_seconds histogram"), "{text}");
        let rate: u64 = text
            .lines()
            .find_map(|l| l.strip_prefix("canopy_cell_expansions_per_second "))
            .and_then(|v| v.parse().ok())
            .expect("the rate gauge");
        assert!(rate > 0 && rate <= 100, "{rate}");
    }
}
