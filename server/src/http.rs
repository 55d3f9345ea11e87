//! The server's two small HTTP/1.1 endpoints, one accept loop for both: the Prometheus metrics (`GET /metrics`)
//! and the browser client's page ([`WebPage`]: the page, its wasm and JS, and `/connect.json`, which tells the page
//! the UDP port and the WebTransport certificate's fingerprint to pin).
//!
//! Untrusted like everything from the network: a request head is read within 4 KiB and a timeout; connections
//! still open are capped (the next one accepted closes the oldest, so idle sockets cannot keep anyone out); only
//! `GET` of a plain file name under the page's root is answered from disk, and only a regular file within a size
//! limit. No TLS: on loopback a page is a secure context; elsewhere put it behind a TLS proxy (docs/web.md).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_protocol::sync::Locked;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::watch;
use tracing::warn;

use crate::metrics::Metrics;
use crate::tls::WebCertificate;

/// How long a connection may take to send its request head.
const READ_TIMEOUT: Duration = Duration::from_secs(5);

/// How long a connection may take to take its answer (the client's wasm is about a megabyte).
const WRITE_TIMEOUT: Duration = Duration::from_secs(60);

/// The largest file the page serves.
pub const MAX_PAGE_FILE: u64 = 16 << 20;

/// An answer.
pub(crate) struct Response {
    status: &'static str,
    content_type: &'static str,
    body: Vec<u8>,
}

impl Response {
    fn ok(content_type: &'static str, body: Vec<u8>) -> Response {
        Response { status: "200 OK", content_type, body }
    }

    fn not_found() -> Response {
        Response { status: "404 Not Found", content_type: "text/plain", body: b"not found\n".to_vec() }
    }
}

/// What a server answers to `GET path`.
pub(crate) type Route = Arc<dyn Fn(&str) -> Response + Send + Sync>;

/// The metrics endpoint's route.
pub(crate) fn metrics_route(metrics: Arc<Metrics>) -> Route {
    Arc::new(move |path| match path {
        "/metrics" | "/" => Response::ok("text/plain; version=0.0.4", metrics.render().into_bytes()),
        _ => Response::not_found(),
    })
}

/// The browser client's page: the files of `root` and `/connect.json`.
#[derive(Clone, Debug)]
pub struct WebPage {
    /// The folder built by `scripts/build-web` (`client/web/dist`): `index.html`, `canopy_web.js`,
    /// `canopy_web_bg.wasm`.
    pub root: PathBuf,
    /// The UDP port the page connects to over WebTransport.
    pub port: u16,
    /// The certificate the page pins.
    pub certificate: Arc<WebCertificate>,
}

impl WebPage {
    /// `/connect.json`: where and how the page connects.
    pub fn connect_json(&self) -> String {
        format!(
            "{{\"port\":{},\"path\":\"{}\",\"certificate_hash\":\"{}\"}}",
            self.port,
            crate::driver::WEB_PATH,
            self.certificate.fingerprint()
        )
    }

    /// The answer to `GET path`.
    pub(crate) fn answer(&self, path: &str) -> Response {
        if path == "/connect.json" {
            return Response::ok("application/json", self.connect_json().into_bytes());
        }
        let Some(name) = file_name(path) else { return Response::not_found() };
        match canopy_worlds::fsread::read_bounded(&self.root.join(name), MAX_PAGE_FILE) {
            Ok(body) => Response::ok(content_type(name), body),
            Err(_) => Response::not_found(),
        }
    }

    pub(crate) fn route(self) -> Route {
        Arc::new(move |path| self.answer(path))
    }
}

/// The file a request path names under the root: `/` is `index.html`; a name is made of letters, digits, `.`, `_`,
/// `-` and `/` between segments, and no segment starts with `.` (no `..`, no hidden files).
fn file_name(path: &str) -> Option<&str> {
    let path = path.split(['?', '#']).next().unwrap_or("");
    let name = path.strip_prefix('/')?;
    if name.is_empty() {
        return Some("index.html");
    }
    let plain = |c: char| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-');
    name.split('/').all(|seg| !seg.is_empty() && !seg.starts_with('.') && seg.chars().all(plain)).then_some(name)
}

fn content_type(name: &str) -> &'static str {
    match name.rsplit_once('.').map(|(_, ext)| ext) {
        Some("html") => "text/html; charset=utf-8",
        Some("js") => "text/javascript",
        Some("wasm") => "application/wasm",
        Some("css") => "text/css",
        Some("json") => "application/json",
        Some("png") => "image/png",
        _ => "application/octet-stream",
    }
}

/// Serve `route` on `listener` until `shutdown`, with at most `max_open` connections open (`name` is for logs).
pub(crate) async fn serve_http(
    listener: tokio::net::TcpListener,
    name: &'static str,
    max_open: usize,
    route: Route,
    mut shutdown: watch::Receiver<bool>,
) {
    // Connections open, oldest first: (number, task).
    let open: Arc<std::sync::Mutex<std::collections::VecDeque<(u64, tokio::task::AbortHandle)>>> = Arc::default();
    let mut backoff = AcceptBackoff::default();
    for number in 0u64.. {
        let accepted = tokio::select! {
            a = listener.accept() => a,
            _ = shutdown.changed() => return,
        };
        let mut sock = match accepted {
            Ok((sock, _)) => {
                backoff.accepted();
                sock
            }
            Err(e) => {
                // At the file-descriptor limit (EMFILE, ENFILE) accept fails at once, again and again: wait before
                // the next try, longer each time, and log once per interval instead of once per failure.
                let (wait, log) = backoff.failed(Instant::now());
                if let Some(suppressed) = log {
                    warn!("{name} endpoint: {e} ({suppressed} more since the last report); retrying in {wait:?}");
                }
                tokio::select! {
                    _ = tokio::time::sleep(wait) => continue,
                    _ = shutdown.changed() => return,
                }
            }
        };
        let (route, others) = (Arc::clone(&route), Arc::clone(&open));
        // Held until the task is in the list, so it cannot take itself out before it is put in.
        let mut list = open.locked();
        if list.len() >= max_open
            && let Some((_, oldest)) = list.pop_front()
        {
            oldest.abort();
        }
        let task = tokio::spawn(async move {
            // Read the request head (bounded in size and time).
            let mut buf = vec![0u8; 4096];
            let mut n = 0;
            let read = tokio::time::timeout(READ_TIMEOUT, async {
                while n < buf.len() {
                    match sock.read(&mut buf[n..]).await {
                        Ok(0) | Err(_) => break,
                        Ok(m) => n += m,
                    }
                    if buf[..n].windows(4).any(|w| w == b"\r\n\r\n") {
                        break;
                    }
                }
            });
            if read.await.is_ok() {
                let head = String::from_utf8_lossy(&buf[..n]);
                let mut words = head.split(' ');
                let response = match (words.next(), words.next()) {
                    (Some("GET"), Some(path)) => route(path),
                    _ => Response { status: "405 Method Not Allowed", content_type: "text/plain", body: Vec::new() },
                };
                let head = format!(
                    "HTTP/1.1 {}\r\nContent-Type: {}\r\nContent-Length: {}\r\nCache-Control: no-cache\r\n\
                     Connection: close\r\n\r\n",
                    response.status,
                    response.content_type,
                    response.body.len()
                );
                let _ = tokio::time::timeout(WRITE_TIMEOUT, async {
                    let _ = sock.write_all(head.as_bytes()).await;
                    let _ = sock.write_all(&response.body).await;
                    let _ = sock.shutdown().await;
                })
                .await;
            }
            others.locked().retain(|(k, _)| *k != number);
        });
        list.push_back((number, task.abort_handle()));
    }
}

/// The accept loop's answer to failures: exponential backoff from 10 ms to 1 s, and a log line at most every
/// 10 s that counts the failures it did not report. Sans-IO: `now` is an argument.
#[derive(Debug, Default)]
struct AcceptBackoff {
    /// Failures in a row.
    failures: u32,
    /// When a failure was last logged.
    logged: Option<Instant>,
    /// Failures since then.
    unreported: u64,
}

impl AcceptBackoff {
    const FIRST: Duration = Duration::from_millis(10);
    const MAX: Duration = Duration::from_secs(1);
    const LOG_EVERY: Duration = Duration::from_secs(10);

    /// An accept succeeded: the next failure waits the shortest time again.
    fn accepted(&mut self) {
        self.failures = 0;
    }

    /// An accept failed at `now`: how long to wait, and `Some(failures not reported)` if this one is to be logged.
    fn failed(&mut self, now: Instant) -> (Duration, Option<u64>) {
        let wait = Self::FIRST.saturating_mul(1 << self.failures.min(7)).min(Self::MAX);
        self.failures = self.failures.saturating_add(1);
        let log = match self.logged {
            Some(t) if now.duration_since(t) < Self::LOG_EVERY => {
                self.unreported += 1;
                None
            }
            _ => {
                self.logged = Some(now);
                Some(std::mem::take(&mut self.unreported))
            }
        };
        (wait, log)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_plain_file_names_under_the_root_are_served() {
        assert_eq!(file_name("/"), Some("index.html"));
        assert_eq!(file_name("/canopy_web_bg.wasm"), Some("canopy_web_bg.wasm"));
        assert_eq!(file_name("/index.html?x=1&z=2"), Some("index.html"));
        assert_eq!(file_name("/assets/a-b_c.js"), Some("assets/a-b_c.js"));
        for bad in ["/../Cargo.toml", "/a/../../b", "/.git/config", "//etc/passwd", "/a%2e%2e/b", "relative", "/a b"] {
            assert_eq!(file_name(bad), None, "{bad}");
        }
        assert_eq!(content_type("canopy_web_bg.wasm"), "application/wasm");
        assert_eq!(content_type("canopy_web.js"), "text/javascript");
    }

    #[test]
    fn the_page_serves_its_files_and_connect_json_and_nothing_else() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::write(tmp.path().join("index.html"), b"<html></html>").unwrap();
        std::fs::create_dir(tmp.path().join("dir")).unwrap();
        let certificate = Arc::new(WebCertificate::generate(std::time::SystemTime::now()).unwrap());
        let page = WebPage { root: tmp.path().to_path_buf(), port: 4433, certificate: Arc::clone(&certificate) };
        let r = page.answer("/");
        assert_eq!((r.status, r.body.as_slice()), ("200 OK", &b"<html></html>"[..]));
        assert_eq!(page.answer("/dir").status, "404 Not Found", "a folder is not a regular file");
        assert_eq!(page.answer("/missing.js").status, "404 Not Found");
        let json = String::from_utf8(page.answer("/connect.json").body).unwrap();
        let expected =
            format!("{{\"port\":4433,\"path\":\"/canopy\",\"certificate_hash\":\"{}\"}}", certificate.fingerprint());
        assert_eq!(json, expected);
    }

    #[test]
    fn accept_failures_back_off_and_log_once_per_interval() {
        let t0 = Instant::now();
        let mut b = AcceptBackoff::default();
        let mut logged = 0;
        let mut waited = Duration::ZERO;
        // A million failures within 10 s of virtual time (an accept loop at the fd limit).
        for i in 0..1_000_000u32 {
            let now = t0 + Duration::from_micros(u64::from(i) * 9);
            let (wait, log) = b.failed(now);
            assert!(wait >= AcceptBackoff::FIRST && wait <= AcceptBackoff::MAX);
            waited += wait;
            logged += usize::from(log.is_some());
        }
        assert_eq!(logged, 1, "one line for a burst under 10 s");
        assert!(waited >= Duration::from_secs(900_000), "the waits add up: at most ~1 try a second once backed off");
        let (wait, log) = b.failed(t0 + Duration::from_secs(11));
        assert_eq!(wait, AcceptBackoff::MAX);
        assert_eq!(log, Some(999_999), "the next line counts what was not reported");
        b.accepted();
        assert_eq!(b.failed(t0 + Duration::from_secs(12)).0, AcceptBackoff::FIRST);
    }
}
