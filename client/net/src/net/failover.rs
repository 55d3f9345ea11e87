//! Clients across edges (issue 17): a world served by several stateless edges, a client that moves to another
//! edge when its own dies or closes, and resumes there with what it held — its species and its complete cells at
//! their versions — so only what is missing or changed travels. A server that says it is busy is asked again after
//! a pause that doubles each time.

use std::net::SocketAddr;
use std::time::Duration;

use canopy_protocol::aoi::Viewpoint;
use quinn::Endpoint;

use super::{ClientError, ConnectConfig, Connection};
use crate::state::ClientState;

/// How long a client with edges to fail over to may hear nothing from its edge before it counts the edge as lost
/// (keep-alives go every quarter of it).
pub const FAILOVER_IDLE: Duration = Duration::from_secs(4);

/// How long [`Connection::fail_over`] keeps trying the edges before it gives up.
pub const FAILOVER_TIMEOUT: Duration = Duration::from_secs(60);

/// How long one attempt at one edge may take.
const ATTEMPT_TIMEOUT: Duration = Duration::from_secs(5);

/// The pause after a round in which no edge answered.
const ROUND_PAUSE: Duration = Duration::from_millis(500);

/// How long [`Connection::connect_any`] keeps asking one server that says it is busy ([`ClientError::busy`]).
pub(super) const BUSY_TIMEOUT: Duration = Duration::from_secs(60);

/// The first pause after a busy answer; each next one doubles, up to [`BUSY_PAUSE_MAX`], and each is drawn between
/// half and one and a half of it, so that clients refused together do not come back together.
const BUSY_PAUSE: Duration = Duration::from_millis(250);

/// The longest pause between two attempts at a busy server.
const BUSY_PAUSE_MAX: Duration = Duration::from_secs(4);

/// The edges of one world, as given on a command line: `HOST:PORT[,HOST:PORT…]` (at least one, no address twice).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Edges(Vec<SocketAddr>);

impl Edges {
    /// One edge.
    pub fn one(addr: SocketAddr) -> Edges {
        Edges(vec![addr])
    }

    /// The first edge: where a client connects first.
    pub fn first(&self) -> SocketAddr {
        self.0[0]
    }

    /// How many.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Never: there is at least one.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The addresses, in order.
    pub fn to_vec(&self) -> Vec<SocketAddr> {
        self.0.clone()
    }

    /// The same edges starting at the `i`-th (modulo their number): spreads clients over edges.
    pub fn rotated(&self, i: usize) -> Edges {
        let mut v = self.0.clone();
        let n = v.len();
        v.rotate_left(i % n);
        Edges(v)
    }
}

impl std::str::FromStr for Edges {
    type Err = String;

    fn from_str(s: &str) -> Result<Edges, String> {
        let mut out: Vec<SocketAddr> = Vec::new();
        for part in s.split(',').map(str::trim) {
            if part.is_empty() {
                return Err(format!("`{s}`: an empty address (expected HOST:PORT[,HOST:PORT…])"));
            }
            let a: SocketAddr = part.parse().map_err(|e| format!("`{part}`: {e} (expected IP:PORT)"))?;
            if out.contains(&a) {
                return Err(format!("`{part}` is named twice"));
            }
            out.push(a);
        }
        Ok(Edges(out))
    }
}

impl std::fmt::Display for Edges {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (i, a) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(",")?;
            }
            write!(f, "{a}")?;
        }
        Ok(())
    }
}

/// The order in which to try `cfg`'s edges after `lost`: the ones after it in the list, then the ones before,
/// `lost` itself last (an edge that closed may come back).
fn order(cfg: &ConnectConfig, lost: SocketAddr) -> Vec<SocketAddr> {
    let edges = if cfg.edges.is_empty() { vec![cfg.server] } else { cfg.edges.clone() };
    let at = edges.iter().position(|a| *a == lost).map_or(0, |i| i + 1);
    let mut v: Vec<SocketAddr> = edges.iter().cycle().skip(at).take(edges.len()).copied().collect();
    if let Some(i) = v.iter().position(|a| *a == lost) {
        let a = v.remove(i);
        v.push(a);
    }
    v
}

impl Connection {
    /// Connect to the first of `cfg`'s edges that answers (`cfg.server` first, then the others in turn, rounds
    /// until `cfg.timeout`), as [`Connection::connect`]. With one edge, a server that says it is busy (it refused
    /// the connection, is full, or cut the handshake at its timeout) is asked again after a pause, until
    /// [`BUSY_TIMEOUT`]: a refusal under load means "later", not "never".
    pub async fn connect_any(
        endpoint: &Endpoint,
        cfg: &ConnectConfig,
        cache: Option<std::sync::Arc<crate::cache::SpeciesCache>>,
        viewpoint: impl Fn(&canopy_protocol::messages::Welcome) -> Viewpoint,
    ) -> Result<Connection, ClientError> {
        if cfg.edges.len() <= 1 {
            let deadline = tokio::time::Instant::now() + BUSY_TIMEOUT;
            let mut pause = BUSY_PAUSE;
            loop {
                match Connection::connect(endpoint, cfg, cache.clone(), &viewpoint).await {
                    Err(e) if e.busy() && tokio::time::Instant::now() + pause < deadline => {
                        let wait = jittered(pause);
                        tracing::debug!("{}: {e}; asking again in {wait:?}", cfg.server);
                        tokio::time::sleep(wait).await;
                        pause = (pause * 2).min(BUSY_PAUSE_MAX);
                    }
                    done => return done,
                }
            }
        }
        let mut edges = order(cfg, cfg.server);
        edges.rotate_right(1);
        try_edges(&edges, cfg.timeout, |at| {
            let mut one = cfg.clone();
            one.server = at;
            one.timeout = one.timeout.min(ATTEMPT_TIMEOUT);
            let cache = cache.clone();
            let viewpoint = &viewpoint;
            async move { Connection::connect(endpoint, &one, cache, viewpoint).await }
        })
        .await
    }

    /// This session ended with an error that [`ClientError::edge_lost`] calls a lost edge: connect to another edge
    /// of `cfg.edges` (the next ones in the list first, this one last) and resume there with what this session
    /// held ([`ClientState::resuming`]: species, complete cells at their versions; edit requests keep their
    /// numbers), at `viewpoint`. Rounds over the edges until [`FAILOVER_TIMEOUT`]; the last error if none answers.
    pub async fn fail_over(
        self,
        endpoint: &Endpoint,
        cfg: &ConnectConfig,
        viewpoint: Viewpoint,
    ) -> Result<Connection, ClientError> {
        let lost = self.server();
        let cache = self.cache.clone();
        self.conn.close(canopy_protocol::CloseCode::Normal as u32, b"failing over");
        let previous = self.state;
        let edges = order(cfg, lost);
        try_edges(&edges, FAILOVER_TIMEOUT, |at| {
            let mut one = cfg.clone();
            one.server = at;
            one.timeout = one.timeout.min(ATTEMPT_TIMEOUT);
            let state = ClientState::resuming(previous.clone());
            let cache = cache.clone();
            async move { Connection::connect_resuming(endpoint, &one, cache, state, |_| viewpoint).await }
        })
        .await
    }
}

/// Try `attempt` on each of `edges` in turn, rounds with a pause between, until one succeeds or `limit` passed.
/// `pause` times a factor between 0.5 and 1.5 taken from the clock's nanoseconds (spread, not reproducible: no
/// result depends on it).
fn jittered(pause: Duration) -> Duration {
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
    pause.mul_f64(0.5 + f64::from(nanos % 1024) / 1024.0)
}

async fn try_edges<F, Fut>(edges: &[SocketAddr], limit: Duration, mut attempt: F) -> Result<Connection, ClientError>
where
    F: FnMut(SocketAddr) -> Fut,
    Fut: std::future::Future<Output = Result<Connection, ClientError>>,
{
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        for &at in edges {
            match attempt(at).await {
                Ok(c) => return Ok(c),
                // A refusal that is no edge's fault (a bad token, a certificate not trusted) is the same everywhere.
                Err(e) if !e.edge_lost() && !matches!(e, ClientError::Closed { .. }) => return Err(e),
                Err(e) if tokio::time::Instant::now() >= deadline => return Err(e),
                Err(e) => tracing::debug!("edge {at}: {e}"),
            }
        }
        tokio::time::sleep(ROUND_PAUSE).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Trust;

    #[test]
    fn edges_parse_and_refuse() {
        let e: Edges = "127.0.0.1:1, 127.0.0.1:2,[::1]:3".parse().unwrap();
        assert_eq!(e.len(), 3);
        assert_eq!(e.to_string(), "127.0.0.1:1,127.0.0.1:2,[::1]:3");
        assert_eq!(e.rotated(4).first(), "127.0.0.1:2".parse().unwrap());
        assert!("127.0.0.1:1,".parse::<Edges>().unwrap_err().contains("empty"));
        assert!("127.0.0.1:1,127.0.0.1:1".parse::<Edges>().unwrap_err().contains("twice"));
        assert!("localhost".parse::<Edges>().is_err());
        assert!("".parse::<Edges>().is_err());
    }

    #[test]
    fn failover_tries_the_next_edges_and_the_lost_one_last() {
        let e: Edges = "127.0.0.1:1,127.0.0.1:2,127.0.0.1:3".parse().unwrap();
        let cfg = ConnectConfig::new_edges(&e, Trust::Insecure);
        assert_eq!(cfg.idle_timeout, FAILOVER_IDLE);
        let port = |v: Vec<SocketAddr>| v.iter().map(|a| a.port()).collect::<Vec<_>>();
        assert_eq!(port(order(&cfg, "127.0.0.1:2".parse().unwrap())), [3, 1, 2]);
        assert_eq!(port(order(&cfg, "127.0.0.1:3".parse().unwrap())), [1, 2, 3]);
        // A server not in the list (the client was sent elsewhere): every edge in order.
        assert_eq!(port(order(&cfg, "127.0.0.1:9".parse().unwrap())), [1, 2, 3]);
        let one = ConnectConfig::new_edges(&Edges::one("127.0.0.1:5".parse().unwrap()), Trust::Insecure);
        assert!(one.edges.is_empty());
        assert_eq!(port(order(&one, one.server)), [5]);
    }
}
