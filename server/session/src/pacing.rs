//! Per-client pacing: a token bucket on virtual time, so a bandwidth cap spends a slow link on the most important
//! records first instead of queueing everything in the transport; and the send budget all sessions share.

use std::sync::Arc;
use std::time::{Duration, Instant};

/// A token bucket in bytes. Sending may take the bucket into debt by one message; the next send waits until the
/// debt is repaid, so messages are never split and the long-run rate is exact.
#[derive(Clone, Debug)]
pub(crate) struct TokenBucket {
    rate: f64,
    burst: f64,
    tokens: f64,
    last: Instant,
}

impl TokenBucket {
    /// A full bucket refilling at `rate` bytes per second, holding at most `burst` bytes.
    pub(crate) fn new(rate: u64, burst: u64, now: Instant) -> TokenBucket {
        let burst = burst.max(1) as f64;
        TokenBucket { rate: rate.max(1) as f64, burst, tokens: burst, last: now }
    }

    fn refill(&mut self, now: Instant) {
        let dt = now.saturating_duration_since(self.last).as_secs_f64();
        self.tokens = (self.tokens + dt * self.rate).min(self.burst);
        self.last = now.max(self.last);
    }

    /// Whether a message may be sent now.
    pub(crate) fn ready(&mut self, now: Instant) -> bool {
        self.refill(now);
        self.tokens >= 0.0
    }

    /// Take `bytes` (possibly into debt).
    pub(crate) fn take(&mut self, now: Instant, bytes: usize) {
        self.refill(now);
        self.tokens -= bytes as f64;
    }

    /// When the bucket will be out of debt again (`None` if it is not in debt).
    pub(crate) fn ready_at(&self) -> Option<Instant> {
        (self.tokens < 0.0).then(|| self.last + Duration::from_secs_f64(-self.tokens / self.rate))
    }
}

/// Bytes handed to the transport and not yet flushed, summed over every session of a server, against a limit:
/// past it, sessions pause (they send releases, nothing new) until bytes are flushed, instead of queueing more.
#[derive(Debug)]
pub struct SendBudget {
    limit: usize,
    used: std::sync::atomic::AtomicUsize,
}

impl SendBudget {
    /// A budget of `limit` bytes, none used.
    pub fn new(limit: usize) -> Arc<SendBudget> {
        Arc::new(SendBudget { limit, used: std::sync::atomic::AtomicUsize::new(0) })
    }

    /// Bytes in use now.
    pub fn used(&self) -> usize {
        self.used.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Whether the budget is spent.
    pub fn spent(&self) -> bool {
        self.used() >= self.limit
    }

    pub(crate) fn add(&self, n: usize) {
        self.used.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
    }

    pub(crate) fn sub(&self, n: usize) {
        self.used.fetch_sub(n, std::sync::atomic::Ordering::Relaxed);
    }
}

impl PartialEq for SendBudget {
    fn eq(&self, other: &SendBudget) -> bool {
        std::ptr::eq(self, other)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_run_rate_is_the_configured_rate() {
        let t0 = Instant::now();
        let mut b = TokenBucket::new(10_000, 2_000, t0);
        let mut now = t0;
        let mut sent = 0usize;
        while now < t0 + Duration::from_secs(10) {
            if b.ready(now) {
                b.take(now, 700);
                sent += 700;
            } else {
                now = b.ready_at().expect("in debt");
            }
        }
        // 10 s at 10 kB/s plus the initial burst, within one message.
        assert!((100_000..=102_000 + 700).contains(&sent), "{sent}");
    }
}
