//! Hostile clients against a running `canopy-server`, for the hardening numbers of issue 14 (`scripts/hostile-run.sh`
//! drives it and reads the server's memory and metrics around each scenario). Loopback only; every scenario is
//! bounded in time.
//!
//! ```sh
//! cargo run --release -p canopy-harness --example hostile -- nonack --server 127.0.0.1:4433 --fingerprint HEX \
//!     --count 300 --hold 15
//! cargo run --release -p canopy-harness --example hostile -- flood --server 127.0.0.1:4433 --fingerprint HEX \
//!     --rate 1000 --duration 20 --bots 20
//! cargo run --release -p canopy-harness --example hostile -- vpflood --server 127.0.0.1:4433 --fingerprint HEX \
//!     --rate 0 --duration 20
//! ```
//!
//! - `nonack`: `--count` clients that never acknowledge: each behind its own UDP relay that forwards client → server
//!   always and server → client only until the welcome has arrived, then nothing (a black hole). Each asks for a
//!   radius-`--radius` area (512 m: the server's maximum) and teleports `--teleports` times; they hang for `--hold`
//!   seconds, then vanish (the relays stop: the server forgets them after its idle timeout). Prints `hanging` when
//!   all hang (the script samples the server then) and the stream bytes they read.
//! - `flood`: a half-open handshake flood: real client Initials (each from a fresh quinn connection to a socket that
//!   never answers, one per connection id) sent once each at `--rate` a second for `--duration` seconds from
//!   `--sources` loopback addresses (127.1.x.y: as a spoofing flood, from many addresses), never followed up, while
//!   `--bots` legitimate clients connect from 127.0.0.1, spread over the flood, each asking for a radius-100 area
//!   and waiting for it to be complete. Prints the fraction admitted and complete.
//! - `vpflood`: one client that reads everything it is sent and sends viewpoints — teleports to random places,
//!   radius 512 — at `--rate` a second (0: as fast as it can write) for `--duration` seconds or until the server
//!   closes it. Prints the viewpoint bytes, the bytes received and their ratio.

use canopy_harness::hole::HoleRelay;
use std::collections::{BTreeMap, HashSet};
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;

use canopy_client::net::endpoint;
use canopy_client::state::ClientState;
use canopy_client::{ConnectConfig, Connection, Trust};
use canopy_harness::numbers::{group, percentile};
use canopy_protocol::aoi::{Grid, Viewpoint};
use canopy_protocol::frame::{FrameDecoder, frame};
use canopy_protocol::{ServerMsg, netlimits};
use tokio::net::UdpSocket;
use tokio::task::JoinHandle;
use tokio::time::{Instant, sleep, timeout};

type Error = Box<dyn std::error::Error + Send + Sync>;

const USAGE: &str = "usage: hostile (nonack|flood|vpflood) --server ADDR --fingerprint HEX [--count N] [--radius M] \
[--teleports N] [--hold S] [--rate N] [--duration S] [--bots N] [--sources N]";

/// `--key value` pairs after the scenario's name.
struct Args(BTreeMap<String, String>);

impl Args {
    fn parse(args: &[String]) -> Result<Args, Error> {
        let mut map = BTreeMap::new();
        let mut it = args.iter();
        while let Some(k) = it.next() {
            let key = k.strip_prefix("--").ok_or_else(|| format!("unexpected `{k}`\n{USAGE}"))?;
            let value = it.next().ok_or_else(|| format!("`{k}` needs a value"))?;
            map.insert(key.to_string(), value.clone());
        }
        Ok(Args(map))
    }

    fn get<T: std::str::FromStr>(&self, key: &str, default: Option<T>) -> Result<T, Error> {
        match self.0.get(key) {
            Some(v) => v.parse().map_err(|_| format!("--{key}: cannot read `{v}`").into()),
            None => default.ok_or_else(|| format!("--{key} is required\n{USAGE}").into()),
        }
    }
}

fn main() -> Result<(), Error> {
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let Some((scenario, rest)) = argv.split_first() else { return Err(USAGE.into()) };
    let args = Args::parse(rest)?;
    let server: SocketAddr = args.get("server", Some("127.0.0.1:4433".parse()?))?;
    if !server.ip().is_loopback() {
        return Err("loopback servers only".into());
    }
    let fingerprint: String = args.get("fingerprint", None)?;
    let trust = Trust::pinned(&fingerprint).ok_or("--fingerprint: not a SHA-256 fingerprint")?;
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    rt.block_on(async move {
        match scenario.as_str() {
            "nonack" => nonack(&args, server, trust).await,
            "flood" => flood(&args, server, trust).await,
            "vpflood" => vpflood(&args, server, trust).await,
            other => Err(format!("unknown scenario `{other}`\n{USAGE}").into()),
        }
    })
}

/// A small deterministic generator (splitmix64) for places and ports.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// The point at fraction `f` of `grid`'s extent on each axis.
fn place(grid: &Grid, f: [f32; 2]) -> [f32; 2] {
    let (lo, hi) = (grid.cell_origin(grid.min), grid.cell_origin(grid.max));
    [lo[0] + f[0] * (hi[0] - lo[0]), lo[1] + f[1] * (hi[1] - lo[1])]
}

/// Count every byte of `stream` as it arrives; decode nothing.
fn count_stream(mut stream: quinn::RecvStream, read: Arc<AtomicU64>) -> JoinHandle<()> {
    tokio::spawn(async move {
        while let Ok(Some(chunk)) = stream.read_chunk(1 << 20, true).await {
            read.fetch_add(chunk.bytes.len() as u64, Relaxed);
        }
    })
}

/// A raw session: hello, the welcome read, ready sent; then every stream counted as it arrives.
struct Raw {
    conn: quinn::Connection,
    control: quinn::SendStream,
    state: ClientState,
    grid: Grid,
    seq: u32,
    /// Stream bytes read (the welcome included).
    read: Arc<AtomicU64>,
    /// Frame bytes written on the control stream.
    written: u64,
    readers: Vec<JoinHandle<()>>,
}

impl Drop for Raw {
    fn drop(&mut self) {
        for t in &self.readers {
            t.abort();
        }
    }
}

impl Raw {
    /// Connect to `to`, read the welcome, call `welcomed` (the black hole opens there), then send ready at `at` (a
    /// fraction of the world) with `radius`.
    async fn connect(
        ep: &quinn::Endpoint,
        cfg: &quinn::ClientConfig,
        to: SocketAddr,
        at: [f32; 2],
        radius: f32,
        welcomed: impl FnOnce(),
    ) -> Result<Raw, Error> {
        let conn = timeout(Duration::from_secs(20), ep.connect_with(cfg.clone(), to, "localhost")?).await??;
        let (mut control, mut recv) = conn.open_bi().await?;
        let mut state = ClientState::new();
        let hello = frame(&state.hello("hostile")?.encode());
        control.write_all(&hello).await?;
        let read = Arc::new(AtomicU64::new(0));
        let mut decoder = FrameDecoder::new(netlimits::MAX_SERVER_FRAME);
        let welcome = timeout(Duration::from_secs(20), async {
            loop {
                if let Some(f) = decoder.next_frame()? {
                    break Ok::<_, Error>(ServerMsg::decode(f)?);
                }
                let chunk = recv.read_chunk(1 << 20, true).await?.ok_or("the server ended before the welcome")?;
                read.fetch_add(chunk.bytes.len() as u64, Relaxed);
                decoder.push(&chunk.bytes);
            }
        })
        .await??;
        let grid = state.on_welcome(welcome)?.world.grid;
        welcomed();
        let ready = frame(&state.ready(Viewpoint::at(0, place(&grid, at), radius))?.encode());
        control.write_all(&ready).await?;
        let mut readers = vec![count_stream(recv, Arc::clone(&read))];
        let (lanes, lanes_read) = (conn.clone(), Arc::clone(&read));
        readers.push(tokio::spawn(async move {
            let mut streams = Vec::new();
            while let Ok(s) = lanes.accept_uni().await {
                streams.push(count_stream(s, Arc::clone(&lanes_read)));
            }
        }));
        let written = (hello.len() + ready.len()) as u64;
        Ok(Raw { conn, control, state, grid, seq: 0, read, written, readers })
    }

    /// Send a viewpoint at `to` (a fraction of the world) asking for `radius`.
    async fn viewpoint(&mut self, to: [f32; 2], radius: f32) -> Result<(), Error> {
        self.seq += 1;
        let msg = frame(&self.state.set_viewpoint(Viewpoint::at(self.seq, place(&self.grid, to), radius))?.encode());
        self.control.write_all(&msg).await?;
        self.written += msg.len() as u64;
        Ok(())
    }
}

/// The QUIC configuration of a hostile client: huge receive windows (so only the server's own send window stops
/// it), the server's idle timeout.
fn hostile_config(trust: Trust) -> Result<quinn::ClientConfig, Error> {
    let mut cfg = ConnectConfig::new("127.0.0.1:1".parse()?, trust).client_config()?;
    let mut t = quinn::TransportConfig::default();
    t.max_concurrent_uni_streams(quinn::VarInt::from_u32(16))
        .max_concurrent_bidi_streams(quinn::VarInt::from_u32(0))
        .stream_receive_window(quinn::VarInt::from_u32(64 << 20))
        .receive_window(quinn::VarInt::from_u32(256 << 20))
        .max_idle_timeout(None);
    cfg.transport_config(Arc::new(t));
    Ok(cfg)
}

/// `nonack`: clients that never acknowledge hang, then vanish.
async fn nonack(args: &Args, server: SocketAddr, trust: Trust) -> Result<(), Error> {
    let count: usize = args.get("count", Some(300))?;
    let radius: f32 = args.get("radius", Some(512.0))?;
    let teleports: usize = args.get("teleports", Some(3))?;
    let hold: f64 = args.get("hold", Some(15.0))?;
    let cfg = hostile_config(trust)?;
    let ep = endpoint("127.0.0.1:0".parse()?)?;
    let started = Instant::now();
    // Connect 32 at a time.
    let gate = Arc::new(tokio::sync::Semaphore::new(32));
    let mut tasks = Vec::new();
    for i in 0..count {
        let (ep, cfg, gate) = (ep.clone(), cfg.clone(), Arc::clone(&gate));
        tasks.push(tokio::spawn(async move {
            let _permit = gate.acquire_owned().await?;
            let mut rng = Rng(i as u64);
            let relay = HoleRelay::start(server).await?;
            let at = [rng.unit(), rng.unit()];
            let raw = Raw::connect(&ep, &cfg, relay.addr, at, radius, || relay.black_hole()).await?;
            Ok::<_, Error>((relay, raw, rng))
        }));
    }
    let mut hostile = Vec::new();
    let mut failed = 0;
    for t in tasks {
        match t.await? {
            Ok(h) => hostile.push(h),
            Err(e) => {
                failed += 1;
                eprintln!("hostile: a client failed to connect: {e}");
            }
        }
    }
    let connected = started.elapsed();
    for _ in 0..teleports {
        sleep(Duration::from_millis(300)).await;
        for (_, raw, rng) in &mut hostile {
            let to = [rng.unit(), rng.unit()];
            if let Err(e) = raw.viewpoint(to, radius).await {
                eprintln!("hostile: a teleport failed: {e}");
            }
        }
    }
    let read = |h: &[(HoleRelay, Raw, Rng)]| h.iter().map(|(_, r, _)| r.read.load(Relaxed)).sum::<u64>();
    println!(
        "hanging {} clients that never acknowledge ({failed} failed to connect, connected in {:.1} s); read {} B",
        hostile.len(),
        connected.as_secs_f64(),
        read(&hostile)
    );
    sleep(Duration::from_secs_f64(hold)).await;
    println!("leaving: {} clients read {} B of stream data in all", hostile.len(), read(&hostile));
    for (relay, _, _) in &hostile {
        relay.cut();
    }
    drop(hostile);
    ep.close(quinn::VarInt::from_u32(0), b"");
    Ok(())
}

/// `count` distinct client Initial datagrams: real quinn connections to a socket that never answers, the first
/// datagram of each connection id kept.
async fn initials(count: usize) -> Result<Vec<Vec<u8>>, Error> {
    let trap = UdpSocket::bind("127.0.0.1:0").await?;
    let to = trap.local_addr()?;
    let cfg = ConnectConfig::new(to, Trust::Insecure).client_config()?;
    let ep = endpoint("127.0.0.1:0".parse()?)?;
    let mut seen = HashSet::new();
    let mut out = Vec::with_capacity(count);
    let mut buf = vec![0u8; 2048];
    while out.len() < count {
        let batch = (count - out.len()).min(64);
        let pending: Vec<_> = (0..batch).map(|_| ep.connect_with(cfg.clone(), to, "localhost")).collect();
        let want = out.len() + batch;
        // Until the batch is in, or the trap has been quiet for 100 ms (a datagram lost in a full buffer).
        while out.len() < want {
            let Ok(r) = timeout(Duration::from_millis(100), trap.recv_from(&mut buf)).await else { break };
            let (n, _) = r?;
            // A long header: flags, version (4), the destination connection id's length and bytes.
            if n < 1200 || buf[0] & 0x80 == 0 || n < 6 + usize::from(buf[5]) {
                continue;
            }
            if seen.insert(buf[6..6 + usize::from(buf[5])].to_vec()) {
                out.push(buf[..n].to_vec());
            }
        }
        drop(pending);
    }
    ep.close(quinn::VarInt::from_u32(0), b"");
    Ok(out)
}

/// `flood`: half-open handshakes at a rate while legitimate bots connect.
async fn flood(args: &Args, server: SocketAddr, trust: Trust) -> Result<(), Error> {
    let rate: u32 = args.get("rate", Some(1000))?;
    let duration: f64 = args.get("duration", Some(20.0))?;
    let bots: usize = args.get("bots", Some(20))?;
    let sources: usize = args.get("sources", Some(256))?;
    let total = (f64::from(rate) * duration).round() as usize;
    let t0 = Instant::now();
    let pool = initials(total.clamp(1, 20_000)).await?;
    println!("flood: {} distinct Initials made in {:.1} s", pool.len(), t0.elapsed().as_secs_f64());
    // Sources 127.1.x.y, each draining (and counting) what the server answers.
    let answered = Arc::new(AtomicU64::new(0));
    let mut sockets = Vec::new();
    let mut drains = Vec::new();
    for i in 0..sources.max(1) {
        let ip = IpAddr::V4(Ipv4Addr::new(127, 1, (i / 250) as u8, (i % 250 + 1) as u8));
        let s = Arc::new(UdpSocket::bind(SocketAddr::new(ip, 0)).await?);
        let (rx, answered) = (Arc::clone(&s), Arc::clone(&answered));
        drains.push(tokio::spawn(async move {
            let mut buf = vec![0u8; 2048];
            while let Ok(n) = rx.recv(&mut buf).await {
                answered.fetch_add(n as u64, Relaxed);
            }
        }));
        sockets.push(s);
    }
    let (sent, sent_bytes) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let begin = Instant::now();
    let flooding = {
        let (sent, sent_bytes) = (Arc::clone(&sent), Arc::clone(&sent_bytes));
        tokio::spawn(async move {
            let start = begin;
            let mut tick = tokio::time::interval(Duration::from_millis(10));
            let mut i = 0usize;
            while start.elapsed().as_secs_f64() < duration {
                tick.tick().await;
                // Catch up to the rate (the ticker may be late on a loaded machine).
                let due = (start.elapsed().as_secs_f64() * f64::from(rate)) as usize;
                while i < due.min(total) {
                    let (p, s) = (&pool[i % pool.len()], &sockets[i % sockets.len()]);
                    if s.send_to(p, server).await.is_ok() {
                        sent.fetch_add(1, Relaxed);
                        sent_bytes.fetch_add(p.len() as u64, Relaxed);
                    }
                    i += 1;
                }
            }
        })
    };
    // Legitimate bots from 127.0.0.1, spread over the flood.
    let ep = endpoint("127.0.0.1:0".parse()?)?;
    let mut legit = Vec::new();
    for b in 0..bots {
        let start_at = begin + Duration::from_secs_f64((0.5 + b as f64) * duration / bots.max(1) as f64);
        let (ep, mut cfg) = (ep.clone(), ConnectConfig::new(server, trust.clone()));
        cfg.timeout = Duration::from_secs(10);
        legit.push(tokio::spawn(async move {
            tokio::time::sleep_until(start_at).await;
            let began = Instant::now();
            let mut rng = Rng(1000 + b as u64);
            let to = [rng.unit(), rng.unit()];
            let connected =
                Connection::connect(&ep, &cfg, None, |w| Viewpoint::at(0, place(&w.world.grid, to), 100.0)).await;
            let latency = began.elapsed();
            match connected {
                Ok(mut c) => {
                    let complete = c.wait_complete(Duration::from_secs(10)).await.is_ok();
                    c.close();
                    (true, complete, latency)
                }
                Err(e) => {
                    eprintln!("flood: a legitimate bot was not admitted: {e}");
                    (false, false, latency)
                }
            }
        }));
    }
    flooding.await?;
    let flood_time = duration;
    let (mut admitted, mut complete, mut latencies) = (0, 0, Vec::new());
    for l in legit {
        let (a, c, t) = l.await?;
        admitted += usize::from(a);
        complete += usize::from(c);
        if a {
            latencies.push(t);
        }
    }
    sleep(Duration::from_millis(500)).await;
    for d in drains {
        d.abort();
    }
    latencies.sort();
    let ms = |q| percentile(&latencies, q).map_or(0.0, |d: Duration| d.as_secs_f64() * 1e3);
    let (n, bytes, back) = (sent.load(Relaxed), sent_bytes.load(Relaxed), answered.load(Relaxed));
    println!(
        "flood: {} Initials ({:.0}/s for {flood_time} s) from {sources} addresses, {} B; answered with {} B ({:.2}× \
         the bytes received); legitimate bots admitted {admitted}/{bots} ({:.0} %), complete {complete}/{bots}; \
         connect p50 {:.0} ms, max {:.0} ms",
        group(n),
        n as f64 / flood_time,
        group(bytes),
        group(back),
        back as f64 / bytes.max(1) as f64,
        100.0 * admitted as f64 / bots.max(1) as f64,
        ms(0.5),
        ms(1.0),
    );
    ep.close(quinn::VarInt::from_u32(0), b"");
    Ok(())
}

/// `vpflood`: one client sends viewpoints (teleports) as fast as allowed or as it can.
async fn vpflood(args: &Args, server: SocketAddr, trust: Trust) -> Result<(), Error> {
    let rate: u32 = args.get("rate", Some(0))?;
    let duration: f64 = args.get("duration", Some(20.0))?;
    let radius: f32 = args.get("radius", Some(512.0))?;
    let cfg = hostile_config(trust)?;
    let ep = endpoint("127.0.0.1:0".parse()?)?;
    let mut raw = Raw::connect(&ep, &cfg, server, [0.5, 0.5], radius, || ()).await?;
    let mut rng = Rng(7);
    let start = Instant::now();
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / f64::from(rate.max(1))));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut sent = 0u64;
    let ended = loop {
        if start.elapsed().as_secs_f64() >= duration {
            break None;
        }
        if let Some(reason) = raw.conn.close_reason() {
            break Some(reason.to_string());
        }
        if rate > 0 {
            tick.tick().await;
        }
        let to = [rng.unit(), rng.unit()];
        match timeout(Duration::from_secs(1), raw.viewpoint(to, radius)).await {
            Ok(Ok(())) => sent += 1,
            Ok(Err(e)) => break Some(raw.conn.close_reason().map_or_else(|| e.to_string(), |r| r.to_string())),
            Err(_) => {} // flow control: the server is not reading; try again
        }
    };
    let flood_time = start.elapsed().as_secs_f64();
    // What is still on its way arrives (the client keeps reading).
    sleep(Duration::from_secs(2)).await;
    let stats = raw.conn.stats();
    let (written, read) = (raw.written, raw.read.load(Relaxed));
    println!(
        "vpflood: {} viewpoints in {flood_time:.1} s ({:.0}/s asked {}), {} B of frames written; received {} B of \
         frames: {:.1} B per viewpoint byte (UDP {} B out, {} B in: {:.1}×); {}",
        group(sent),
        sent as f64 / flood_time.max(1e-9),
        if rate == 0 { "as fast as possible".to_string() } else { format!("{rate}/s") },
        group(written),
        group(read),
        read as f64 / written.max(1) as f64,
        group(stats.udp_tx.bytes),
        group(stats.udp_rx.bytes),
        stats.udp_rx.bytes as f64 / stats.udp_tx.bytes.max(1) as f64,
        match ended.or_else(|| raw.conn.close_reason().map(|r| r.to_string())) {
            Some(r) => format!("closed: {r}"),
            None => "still connected".into(),
        },
    );
    raw.conn.close(quinn::VarInt::from_u32(0), b"done");
    ep.wait_idle().await;
    Ok(())
}
