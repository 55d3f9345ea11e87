//! Counters a store keeps for whoever reports them: a lock-free histogram of durations and the cell cache's counts
//! (the server's metrics endpoint renders both).

use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;

/// Upper bounds of the expansion-time histogram's buckets, microseconds: 1 µs, 2 µs, 4 µs, … 8.4 s (then +Inf).
const BUCKETS_US: [u64; 24] = {
    let mut b = [0u64; 24];
    let mut i = 0;
    while i < 24 {
        b[i] = 1 << i;
        i += 1;
    }
    b
};

/// A histogram of durations in fixed power-of-two buckets, lock-free.
#[derive(Debug, Default)]
pub struct Histogram {
    /// Counts per bucket of [`BUCKETS_US`], and one for longer.
    counts: [AtomicU64; BUCKETS_US.len() + 1],
    sum_us: AtomicU64,
}

impl Histogram {
    /// Count one duration.
    pub fn record(&self, d: Duration) {
        let us = d.as_micros().min(u128::from(u64::MAX)) as u64;
        let i = BUCKETS_US.iter().position(|&b| us <= b).unwrap_or(BUCKETS_US.len());
        self.counts[i].fetch_add(1, Relaxed);
        self.sum_us.fetch_add(us, Relaxed);
    }

    /// How many durations were counted.
    pub fn count(&self) -> u64 {
        self.counts.iter().map(|c| c.load(Relaxed)).sum()
    }

    /// The `q`-quantile (0..=1) as the upper bound of the bucket it falls in (`None`: nothing counted; the
    /// overflow bucket answers with the largest bound).
    pub fn quantile(&self, q: f64) -> Option<Duration> {
        let counts: Vec<u64> = self.counts.iter().map(|c| c.load(Relaxed)).collect();
        let total: u64 = counts.iter().sum();
        if total == 0 {
            return None;
        }
        let rank = ((q.clamp(0.0, 1.0) * total as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (i, c) in counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return Some(Duration::from_micros(BUCKETS_US[i.min(BUCKETS_US.len() - 1)]));
            }
        }
        Some(Duration::from_micros(BUCKETS_US[BUCKETS_US.len() - 1]))
    }

    /// Prometheus histogram lines for `name` (`_bucket` by `le` in seconds, `_sum`, `_count`).
    pub fn render(&self, s: &mut String, name: &str, help: &str) {
        let _ = writeln!(s, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut cumulative = 0;
        for (i, c) in self.counts.iter().enumerate() {
            cumulative += c.load(Relaxed);
            let le = BUCKETS_US.get(i).map_or("+Inf".to_owned(), |&us| format!("{}", us as f64 / 1e6));
            let _ = writeln!(s, "{name}_bucket{{le=\"{le}\"}} {cumulative}");
        }
        let _ = writeln!(s, "{name}_sum {}", self.sum_us.load(Relaxed) as f64 / 1e6);
        let _ = writeln!(s, "{name}_count {cumulative}");
    }
}

/// The cell cache's counters: updated by the cache (the server's cell cache), read by the metrics endpoint.
#[derive(Debug, Default)]
pub struct CellMetrics {
    /// Lookups that found the cell ready.
    pub hits: AtomicU64,
    /// Lookups that found it neither ready nor queued, and queued its expansion.
    pub misses: AtomicU64,
    /// Expansions finished (a cell evicted and asked for again is expanded again).
    pub expansions: AtomicU64,
    /// Cells evicted to keep the cache within its bound.
    pub evictions: AtomicU64,
    /// Expansions that failed (the cell went out empty; a bug in the world, logged).
    pub failures: AtomicU64,
    /// Bytes the cached cells hold now.
    pub bytes: AtomicU64,
    /// Cells cached now.
    pub cells: AtomicU64,
    /// The cache's bound, bytes.
    pub limit: AtomicU64,
    /// Cells queued for expansion now.
    pub queued: AtomicU64,
    /// Queued cells dropped unexpanded: every session that wanted them moved on or left.
    pub cancelled: AtomicU64,
    /// How long expansions took (expanding, quantising and encoding a cell).
    pub expansion_time: Histogram,
    /// Far-view summary nodes computed.
    pub summaries: AtomicU64,
    /// Bytes the cached summary nodes hold now.
    pub summary_bytes: AtomicU64,
    /// How long a summary node took (its leaves and the nodes between, where not cached).
    pub summary_time: Histogram,
}
