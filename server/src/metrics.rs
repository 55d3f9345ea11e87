//! Server-wide counters and their Prometheus text exposition (format 0.0.4): clients, bytes and messages by
//! message class, records sent and records per second, sessions closed by reason, process memory.

use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Instant;

use canopy_protocol::CloseCode;
use canopy_protocol::messages::ByKind;

use crate::admission::Refusal;
use crate::session::MsgClass;

/// Counters shared by every connection of one server.
#[derive(Debug)]
pub struct Metrics {
    started: Instant,
    /// Clients connected now (handshake completed: holding a client slot).
    pub clients: AtomicU64,
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
    /// Bytes by [`MsgClass`].
    pub bytes: ByKind<AtomicU64>,
    /// Messages by [`MsgClass`].
    pub messages: ByKind<AtomicU64>,
    /// Instance records sent.
    pub records: AtomicU64,
    /// Bytes received from clients (frames).
    pub bytes_in: AtomicU64,
    /// Viewpoints received.
    pub viewpoints: AtomicU64,
    /// Connections closed, by [`CloseCode`] (index = code), plus one last slot for transport errors.
    pub closed: [AtomicU64; TRANSPORT + 1],
    /// Records per second over the last completed second (updated by [`Metrics::tick`]).
    pub records_per_second: AtomicU64,
    last_tick: std::sync::Mutex<(Instant, u64)>,
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new()
    }
}

/// The slot of [`Metrics::closed`] that counts transport failures, after every [`CloseCode`].
const TRANSPORT: usize = CloseCode::ALL.len();

impl Metrics {
    /// All counters at zero.
    pub fn new() -> Metrics {
        let now = Instant::now();
        Metrics {
            started: now,
            clients: AtomicU64::new(0),
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
            closed: Default::default(),
            records_per_second: AtomicU64::new(0),
            last_tick: std::sync::Mutex::new((now, 0)),
        }
    }

    /// Count one refused incoming connection.
    pub fn refused(&self, why: Refusal) {
        self.refused[why as usize].fetch_add(1, Relaxed);
    }

    /// Count one transmitted message.
    pub fn sent(&self, class: MsgClass, bytes: usize, records: u32) {
        self.bytes[class].fetch_add(bytes as u64, Relaxed);
        self.messages[class].fetch_add(1, Relaxed);
        self.records.fetch_add(u64::from(records), Relaxed);
    }

    /// Count one closed connection (`None`: the transport failed or the peer vanished).
    pub fn closed(&self, code: Option<CloseCode>) {
        let i = code.map_or(TRANSPORT, |c| c as usize);
        self.closed[i].fetch_add(1, Relaxed);
    }

    /// Update the records-per-second gauge; call about once a second.
    pub fn tick(&self, now: Instant) {
        let records = self.records.load(Relaxed);
        let mut last = self.last_tick.lock().unwrap_or_else(|e| e.into_inner());
        let dt = now.saturating_duration_since(last.0).as_secs_f64();
        if dt > 0.0 {
            let rate = (records.saturating_sub(last.1)) as f64 / dt;
            self.records_per_second.store(rate.round() as u64, Relaxed);
            *last = (now, records);
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
        if let Some(rss) = resident_bytes() {
            metric("canopy_resident_bytes", "gauge", "Resident memory of the server process.", &[(String::new(), rss)]);
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

    #[test]
    fn exposition_has_every_family_and_counts() {
        let m = Metrics::new();
        m.sent(MsgClass::Cells, 100, 20);
        m.sent(MsgClass::Species, 900, 0);
        m.closed(Some(CloseCode::Malformed));
        let text = m.render();
        assert!(text.contains("canopy_sent_bytes_total{class=\"cells\"} 100"), "{text}");
        assert!(text.contains("canopy_sent_bytes_total{class=\"species\"} 900"), "{text}");
        assert!(text.contains("canopy_records_sent_total 20"), "{text}");
        assert!(text.contains("canopy_closed_total{reason=\"malformed\"} 1"), "{text}");
        assert!(text.contains("# TYPE canopy_clients gauge"), "{text}");
    }
}
