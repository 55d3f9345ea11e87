//! A relay that stops a client from acknowledging: for the hostile-client tests and `examples/hostile.rs`, a client
//! whose server → client packets vanish after a point, so the server's sends stay unacknowledged.

use std::net::SocketAddr;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::atomic::{AtomicBool, AtomicU64};
use std::sync::{Arc, OnceLock};

use tokio::net::UdpSocket;
use tokio::task::JoinHandle;

/// A UDP relay for one client on loopback: client → server always, server → client until [`HoleRelay::black_hole`].
pub struct HoleRelay {
    /// Where the client sends (the relay's front socket).
    pub addr: SocketAddr,
    down_open: Arc<AtomicBool>,
    /// Server → client bytes dropped since the black hole opened.
    pub dropped: Arc<AtomicU64>,
    tasks: Vec<JoinHandle<()>>,
}

impl HoleRelay {
    /// A relay to `server` on loopback.
    pub async fn start(server: SocketAddr) -> std::io::Result<HoleRelay> {
        let front = Arc::new(UdpSocket::bind("127.0.0.1:0").await?);
        let back = Arc::new(UdpSocket::bind("127.0.0.1:0").await?);
        back.connect(server).await?;
        let addr = front.local_addr()?;
        let client: Arc<OnceLock<SocketAddr>> = Arc::default();
        let down_open = Arc::new(AtomicBool::new(true));
        let dropped = Arc::new(AtomicU64::new(0));
        let up = {
            let (front, back, client) = (Arc::clone(&front), Arc::clone(&back), Arc::clone(&client));
            tokio::spawn(async move {
                let mut buf = vec![0u8; 65_536];
                while let Ok((n, from)) = front.recv_from(&mut buf).await {
                    client.get_or_init(|| from);
                    let _ = back.send(&buf[..n]).await;
                }
            })
        };
        let down = {
            let (open, dropped) = (Arc::clone(&down_open), Arc::clone(&dropped));
            tokio::spawn(async move {
                let mut buf = vec![0u8; 65_536];
                while let Ok(n) = back.recv(&mut buf).await {
                    match client.get() {
                        Some(to) if open.load(Relaxed) => drop(front.send_to(&buf[..n], *to).await),
                        _ => drop(dropped.fetch_add(n as u64, Relaxed)),
                    }
                }
            })
        };
        Ok(HoleRelay { addr, down_open, dropped, tasks: vec![up, down] })
    }

    /// From now on nothing the server sends reaches the client (so the client acknowledges nothing new).
    pub fn black_hole(&self) {
        self.down_open.store(false, Relaxed);
    }

    /// Stop relaying either way: to the server, the client is gone.
    pub fn cut(&self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

impl Drop for HoleRelay {
    fn drop(&mut self) {
        self.cut();
    }
}
