//! An emulated network link in process: a UDP relay between one client and the server that, per direction, drops
//! packets at random (loss), queues them behind a rate limit (a bottleneck of `rate` bits per second with a
//! drop-tail queue of `queue` milliseconds), and delivers them after a one-way `latency`. It shapes every byte —
//! QUIC handshakes, acknowledgements, retransmissions and the IP/UDP headers it counts — so the transport really
//! sees a slow, lossy, distant link and its congestion control has to cope.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use tokio::net::UdpSocket;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::Instant;

use crate::bots::Rng;

/// IPv4 + UDP header bytes, counted against the rate like the payload.
pub const HEADER_BYTES: usize = 28;

/// Largest datagram relayed (QUIC's datagrams are far smaller).
pub const MAX_DATAGRAM: usize = 65_535;

/// Most packets waiting for delivery per direction (the rate queue is bounded by time; this bounds memory when
/// there is no rate limit).
pub const MAX_IN_FLIGHT: usize = 16_384;

/// The properties of one emulated link (the same both ways).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinkSpec {
    /// Bottleneck rate, bits per second (`None`: unlimited).
    pub rate: Option<u64>,
    /// One-way latency.
    pub latency: Duration,
    /// Probability that a packet is dropped, `0..1`.
    pub loss: f64,
    /// Bottleneck queue, as time at the link rate: packets that would wait longer are dropped.
    pub queue: Duration,
}

impl Default for LinkSpec {
    fn default() -> Self {
        LinkSpec { rate: None, latency: Duration::ZERO, loss: 0.0, queue: Duration::from_millis(250) }
    }
}

impl LinkSpec {
    /// A link of `rate` bits per second with `latency_ms` one-way latency and `loss` drop probability.
    pub fn new(rate: Option<u64>, latency_ms: u64, loss: f64) -> LinkSpec {
        LinkSpec { rate, latency: Duration::from_millis(latency_ms), loss, ..LinkSpec::default() }
    }

    /// Whether the link changes anything (otherwise clients connect directly).
    pub fn is_shaped(&self) -> bool {
        self.rate.is_some() || !self.latency.is_zero() || self.loss > 0.0
    }

    /// A short label: `1 Mbit/s, 20 ms, 0.5 % loss`.
    pub fn label(&self) -> String {
        let rate = match self.rate {
            None => "unlimited".to_string(),
            Some(r) if r >= 1_000_000 && r % 1_000_000 == 0 => format!("{} Mbit/s", r / 1_000_000),
            Some(r) if r >= 1_000 => format!("{} kbit/s", r / 1_000),
            Some(r) => format!("{r} bit/s"),
        };
        let mut s = format!("{rate}, {} ms", self.latency.as_millis());
        if self.loss > 0.0 {
            s += &format!(", {} % loss", self.loss * 100.0);
        }
        s
    }
}

/// Parse a rate: `56k`, `1M`, `10M`, `2.5M`, `800000` (bits per second), or `none`/`0` for unlimited.
pub fn parse_rate(s: &str) -> Result<Option<u64>, String> {
    let t = s.trim().trim_end_matches("bit/s").trim_end_matches("bps").trim();
    if t.eq_ignore_ascii_case("none") || t == "0" || t.eq_ignore_ascii_case("unlimited") {
        return Ok(None);
    }
    let (num, mul) = match t.chars().last() {
        Some('k' | 'K') => (&t[..t.len() - 1], 1e3),
        Some('m' | 'M') => (&t[..t.len() - 1], 1e6),
        Some('g' | 'G') => (&t[..t.len() - 1], 1e9),
        _ => (t, 1.0),
    };
    let v: f64 = num.trim().parse().map_err(|_| format!("`{s}` is not a rate like 56k, 1M or 10M"))?;
    if !(v.is_finite() && v > 0.0 && v * mul <= 1e12) {
        return Err(format!("rate `{s}` out of range"));
    }
    Ok(Some((v * mul).round().max(1.0) as u64))
}

/// Counters of one direction of a link.
#[derive(Debug, Default)]
pub struct DirectionStats {
    /// Packets that entered the link.
    pub packets: AtomicU64,
    /// Their bytes (UDP payload).
    pub bytes: AtomicU64,
    /// Packets dropped at random (loss).
    pub lost: AtomicU64,
    /// Packets dropped because the bottleneck queue was full.
    pub overflow: AtomicU64,
    /// Packets delivered.
    pub delivered: AtomicU64,
}

/// Counters of a link: server → client (`down`) and client → server (`up`).
#[derive(Debug, Default)]
pub struct LinkStats {
    /// Towards the client.
    pub down: DirectionStats,
    /// Towards the server.
    pub up: DirectionStats,
}

/// The state of one direction's bottleneck: when it is next free, and a deterministic generator for losses.
#[derive(Clone, Debug)]
pub struct Shaper {
    spec: LinkSpec,
    free_at: Option<Instant>,
    rng: Rng,
}

/// What the shaper decided for one packet.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Deliver at this instant.
    Deliver(Instant),
    /// Dropped at random.
    Lost,
    /// Dropped: the queue is full.
    Overflow,
}

impl Shaper {
    /// A shaper for `spec`, losses drawn from `seed`.
    pub fn new(spec: LinkSpec, seed: u64) -> Shaper {
        Shaper { spec, free_at: None, rng: Rng(seed) }
    }

    /// Decide the fate of a packet of `len` bytes arriving at `now`.
    pub fn admit(&mut self, now: Instant, len: usize) -> Verdict {
        if self.spec.loss > 0.0 && self.rng.unit_f64() < self.spec.loss {
            return Verdict::Lost;
        }
        let Some(rate) = self.spec.rate else { return Verdict::Deliver(now + self.spec.latency) };
        let start = self.free_at.map_or(now, |f| f.max(now));
        let waiting = start.saturating_duration_since(now);
        if waiting > self.spec.queue {
            return Verdict::Overflow;
        }
        let serialise = Duration::from_secs_f64(((len + HEADER_BYTES) * 8) as f64 / rate as f64);
        let done = start + serialise;
        self.free_at = Some(done);
        Verdict::Deliver(done + self.spec.latency)
    }
}

/// A running relay: clients send to [`Relay::addr`], it forwards to the server through the emulated link.
#[derive(Debug)]
pub struct Relay {
    addr: SocketAddr,
    stats: Arc<LinkStats>,
    tasks: Vec<JoinHandle<()>>,
}

impl Drop for Relay {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

impl Relay {
    /// Start a relay on loopback towards `server` (one client per relay).
    pub async fn start(server: SocketAddr, spec: LinkSpec, seed: u64) -> std::io::Result<Relay> {
        let bind = canopy_client::net::loopback_for(server);
        let front = Arc::new(UdpSocket::bind(bind).await?);
        let back = Arc::new(UdpSocket::bind(bind).await?);
        back.connect(server).await?;
        let addr = front.local_addr()?;
        let stats = Arc::new(LinkStats::default());
        // The client's address, from its first datagram (one client per relay).
        let client: Arc<OnceLock<SocketAddr>> = Arc::default();
        let (up_tx, up_rx) = mpsc::channel::<(Instant, Vec<u8>)>(MAX_IN_FLIGHT);
        let (down_tx, down_rx) = mpsc::channel::<(Instant, Vec<u8>)>(MAX_IN_FLIGHT);
        let (up_shaper, down_shaper) = (Shaper::new(spec, seed ^ 0x5550), Shaper::new(spec, seed ^ 0x444f));
        let tasks = vec![
            // Up: client → front → shaper → back → server.
            spawn_ingress(Arc::clone(&front), Some(Arc::clone(&client)), Arc::clone(&stats), up_shaper, up_tx),
            tokio::spawn(deliver(up_rx, Arc::clone(&stats), true, {
                let back = Arc::clone(&back);
                move |p| {
                    let back = Arc::clone(&back);
                    async move { back.send(&p).await.is_ok() }
                }
            })),
            // Down: server → back → shaper → front → client.
            spawn_ingress(Arc::clone(&back), None, Arc::clone(&stats), down_shaper, down_tx),
            tokio::spawn(deliver(down_rx, Arc::clone(&stats), false, move |p| {
                let (front, to) = (Arc::clone(&front), client.get().copied());
                async move {
                    match to {
                        Some(to) => front.send_to(&p, to).await.is_ok(),
                        None => false,
                    }
                }
            })),
        ];
        Ok(Relay { addr, stats, tasks })
    }

    /// Where clients connect.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The link's counters.
    pub fn stats(&self) -> &Arc<LinkStats> {
        &self.stats
    }
}

/// One direction's way in: read datagrams from `socket` (from the client, whose address is noted in `client`, or
/// from the server when `client` is `None`), count them, and queue what the shaper admits for delivery.
fn spawn_ingress(
    socket: Arc<UdpSocket>,
    client: Option<Arc<OnceLock<SocketAddr>>>,
    stats: Arc<LinkStats>,
    mut shaper: Shaper,
    tx: mpsc::Sender<(Instant, Vec<u8>)>,
) -> JoinHandle<()> {
    tokio::spawn(async move {
        let dir = if client.is_some() { &stats.up } else { &stats.down };
        let mut buf = vec![0u8; MAX_DATAGRAM];
        loop {
            let n = match &client {
                Some(client) => {
                    let Ok((n, from)) = socket.recv_from(&mut buf).await else { return };
                    client.get_or_init(|| from);
                    n
                }
                None => {
                    let Ok(n) = socket.recv(&mut buf).await else { return };
                    n
                }
            };
            dir.packets.fetch_add(1, Relaxed);
            dir.bytes.fetch_add(n as u64, Relaxed);
            match shaper.admit(Instant::now(), n) {
                Verdict::Deliver(at) => {
                    if tx.try_send((at, buf[..n].to_vec())).is_err() {
                        dir.overflow.fetch_add(1, Relaxed);
                    }
                }
                Verdict::Lost => drop(dir.lost.fetch_add(1, Relaxed)),
                Verdict::Overflow => drop(dir.overflow.fetch_add(1, Relaxed)),
            }
        }
    })
}

async fn deliver<F, Fut>(mut rx: mpsc::Receiver<(Instant, Vec<u8>)>, stats: Arc<LinkStats>, up: bool, send: F)
where
    F: Fn(Vec<u8>) -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let dir = if up { &stats.up } else { &stats.down };
    while let Some((at, packet)) = rx.recv().await {
        tokio::time::sleep_until(at).await;
        if send(packet).await {
            dir.delivered.fetch_add(1, Relaxed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_parse() {
        assert_eq!(parse_rate("56k"), Ok(Some(56_000)));
        assert_eq!(parse_rate("1M"), Ok(Some(1_000_000)));
        assert_eq!(parse_rate("2.5Mbit/s"), Ok(Some(2_500_000)));
        assert_eq!(parse_rate("none"), Ok(None));
        assert!(parse_rate("fast").is_err() && parse_rate("-1M").is_err());
        assert_eq!(LinkSpec::new(Some(56_000), 100, 0.01).label(), "56 kbit/s, 100 ms, 1 % loss");
    }

    #[test]
    fn shaper_serialises_at_the_rate_and_drops_tail() {
        let spec = LinkSpec {
            rate: Some(8_000),
            latency: Duration::from_millis(50),
            loss: 0.0,
            queue: Duration::from_secs(1),
        };
        let mut s = Shaper::new(spec, 1);
        let t0 = Instant::now();
        // 972 + 28 bytes = 8000 bits = 1 s at 8 kbit/s.
        assert_eq!(s.admit(t0, 972), Verdict::Deliver(t0 + Duration::from_millis(1050)));
        assert_eq!(s.admit(t0, 972), Verdict::Deliver(t0 + Duration::from_millis(2050)));
        // The queue now holds 2 s of packets, beyond its 1 s: the next one is dropped.
        assert_eq!(s.admit(t0, 972), Verdict::Overflow);
        // Later, the link has drained.
        let t1 = t0 + Duration::from_secs(3);
        assert_eq!(s.admit(t1, 972), Verdict::Deliver(t1 + Duration::from_millis(1050)));
    }

    #[test]
    fn loss_is_about_its_probability_and_deterministic() {
        let spec = LinkSpec { loss: 0.1, ..LinkSpec::default() };
        let run = |seed| {
            let mut s = Shaper::new(spec, seed);
            let t = Instant::now();
            (0..10_000).filter(|_| s.admit(t, 100) == Verdict::Lost).count()
        };
        let lost = run(7);
        assert_eq!(lost, run(7));
        assert!((800..1200).contains(&lost), "{lost}");
    }
}
