//! Admission: which incoming QUIC connections the server takes, sans-IO (the driver feeds it each `Incoming`'s
//! source and whether its address is validated, and tells it when handshakes end and sessions close).
//!
//! The rules, so that spoofed or half-open handshakes cannot lock honest clients out:
//! - a handshake holds a **handshake slot** (at most [`AdmissionConfig::max_handshakes`]), not a client slot; it
//!   takes one of the [`AdmissionConfig::max_clients`] client slots only when it completes — and a completed QUIC
//!   handshake has proved its address;
//! - while many handshakes are in flight ([`AdmissionConfig::retry_above`]), a source whose address is not yet
//!   validated is sent a QUIC Retry first: a spoofed source never answers it, and the server keeps no state for it;
//! - one source address holds at most [`AdmissionConfig::max_per_source`] connections, handshakes included.

use std::collections::BTreeMap;
use std::net::IpAddr;

/// The admission limits.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AdmissionConfig {
    /// Most clients with a completed handshake at once; more are refused ([`Refusal::Full`]).
    pub max_clients: usize,
    /// Most handshakes in flight at once.
    pub max_handshakes: usize,
    /// Handshakes in flight above which unvalidated sources are sent a Retry.
    pub retry_above: usize,
    /// Most connections (handshakes included) from one source address.
    pub max_per_source: usize,
}

impl Default for AdmissionConfig {
    fn default() -> Self {
        AdmissionConfig { max_clients: 20_000, max_handshakes: 2_048, retry_above: 64, max_per_source: 4_096 }
    }
}

/// Why an incoming connection is refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// Every client slot is taken.
    Full = 0,
    /// Too many handshakes are in flight.
    Busy = 1,
    /// The source address already holds its share.
    PerSource = 2,
}

impl Refusal {
    /// Every reason, in index order (`ALL[r as usize] == r`).
    pub const ALL: [Refusal; 3] = [Refusal::Full, Refusal::Busy, Refusal::PerSource];

    /// A snake_case label, for metrics.
    pub fn label(self) -> &'static str {
        match self {
            Refusal::Full => "full",
            Refusal::Busy => "busy",
            Refusal::PerSource => "per_source",
        }
    }
}

/// What to do with an incoming connection.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Verdict {
    /// Go on with the handshake (it now holds a handshake slot).
    Accept,
    /// Answer with a QUIC Retry (no state kept).
    Retry,
    /// Refuse it.
    Refuse(Refusal),
}

/// The counts admission decides on.
#[derive(Debug, Default)]
pub(crate) struct Admission {
    cfg: AdmissionConfig,
    handshaking: usize,
    clients: usize,
    per_source: BTreeMap<IpAddr, usize>,
}

impl Admission {
    /// Admission under `cfg`, with nobody connected.
    pub(crate) fn new(cfg: AdmissionConfig) -> Admission {
        Admission { cfg, ..Admission::default() }
    }

    /// An incoming connection from `source`; `validated`: its address is proved (after a Retry).
    pub(crate) fn incoming(&mut self, source: IpAddr, validated: bool) -> Verdict {
        let from_source = self.per_source.get(&source).copied().unwrap_or(0);
        let verdict = if from_source >= self.cfg.max_per_source {
            Verdict::Refuse(Refusal::PerSource)
        } else if self.clients >= self.cfg.max_clients {
            Verdict::Refuse(Refusal::Full)
        } else if !validated && self.handshaking >= self.cfg.retry_above {
            Verdict::Retry
        } else if self.handshaking >= self.cfg.max_handshakes {
            Verdict::Refuse(Refusal::Busy)
        } else {
            Verdict::Accept
        };
        if verdict == Verdict::Accept {
            self.handshaking += 1;
            *self.per_source.entry(source).or_insert(0) += 1;
        }
        verdict
    }

    /// An accepted handshake from `source` ended: completed (`true`: it takes a client slot if one is free, and the
    /// answer says whether it did) or failed.
    pub(crate) fn handshake_done(&mut self, source: IpAddr, completed: bool) -> bool {
        self.handshaking = self.handshaking.saturating_sub(1);
        if completed && self.clients < self.cfg.max_clients {
            self.clients += 1;
            true
        } else {
            self.release(source);
            false
        }
    }

    /// A client from `source` that held a client slot left.
    pub(crate) fn closed(&mut self, source: IpAddr) {
        self.clients = self.clients.saturating_sub(1);
        self.release(source);
    }

    fn release(&mut self, source: IpAddr) {
        if let Some(n) = self.per_source.get_mut(&source) {
            *n -= 1;
            if *n == 0 {
                self.per_source.remove(&source);
            }
        }
    }

    /// Clients holding a slot now.
    #[cfg(test)]
    pub(crate) fn clients(&self) -> usize {
        self.clients
    }

    /// Handshakes in flight now.
    #[cfg(test)]
    pub(crate) fn handshaking(&self) -> usize {
        self.handshaking
    }

    /// Whether the server is near capacity (nine tenths of the client slots taken): then sessions that hold a slot
    /// without streaming may be closed.
    pub(crate) fn near_capacity(&self) -> bool {
        self.clients.saturating_mul(10) >= self.cfg.max_clients.saturating_mul(9)
    }

    /// Source addresses with a connection now (the per-source table's size; it holds no more).
    #[cfg(test)]
    pub(crate) fn sources(&self) -> usize {
        self.per_source.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(last: u8) -> IpAddr {
        IpAddr::from([127, 0, 0, last])
    }

    #[test]
    fn half_open_handshakes_never_take_client_slots() {
        let cfg = AdmissionConfig { max_clients: 2, max_handshakes: 1_000, retry_above: 10, max_per_source: 100 };
        let mut a = Admission::new(cfg);
        // A flood of Initials from one source: ten are taken, the rest are asked to prove their address.
        let verdicts: Vec<Verdict> = (0..50).map(|_| a.incoming(ip(1), false)).collect();
        assert_eq!(verdicts.iter().filter(|v| **v == Verdict::Accept).count(), 10);
        assert!(verdicts[10..].iter().all(|v| *v == Verdict::Retry));
        assert_eq!((a.handshaking(), a.clients()), (10, 0));
        // An honest client from elsewhere answers the Retry and gets in, then takes a client slot.
        assert_eq!(a.incoming(ip(2), false), Verdict::Retry);
        assert_eq!(a.incoming(ip(2), true), Verdict::Accept);
        assert!(a.handshake_done(ip(2), true));
        assert_eq!(a.clients(), 1);
        // The flood's handshakes time out: their slots come back and nothing is left of the source.
        for _ in 0..10 {
            assert!(!a.handshake_done(ip(1), false));
        }
        assert_eq!((a.handshaking(), a.clients(), a.sources()), (0, 1, 1));
        a.closed(ip(2));
        assert_eq!((a.clients(), a.sources()), (0, 0));
    }

    #[test]
    fn per_source_cap_full_and_busy() {
        let cfg = AdmissionConfig { max_clients: 3, max_handshakes: 4, retry_above: 100, max_per_source: 2 };
        let mut a = Admission::new(cfg);
        assert_eq!(a.incoming(ip(1), true), Verdict::Accept);
        assert_eq!(a.incoming(ip(1), true), Verdict::Accept);
        assert_eq!(a.incoming(ip(1), true), Verdict::Refuse(Refusal::PerSource));
        assert_eq!(a.incoming(ip(2), true), Verdict::Accept);
        assert_eq!(a.incoming(ip(3), true), Verdict::Accept);
        assert_eq!(a.incoming(ip(4), true), Verdict::Refuse(Refusal::Busy), "four handshakes in flight");
        for s in [1, 1, 2] {
            assert!(a.handshake_done(ip(s), true));
        }
        assert!(a.near_capacity());
        assert!(!a.handshake_done(ip(3), true), "the fourth completed handshake finds no client slot");
        assert_eq!(a.incoming(ip(5), true), Verdict::Refuse(Refusal::Full));
        a.closed(ip(1));
        assert_eq!(a.incoming(ip(5), true), Verdict::Accept);
    }
}
