//! Browsers' sessions beside native ones on one UDP port (issue 34): a client speaking WebTransport (ALPN `h3`, an
//! HTTP/3 CONNECT to `/canopy`, as a browser does) is served by the same session loop as a native `canopy/1` one
//! and ends holding exactly its area of interest; each kind is given its own certificate (a browser pins the
//! short-lived one); bad WebTransport input (an unknown path, no CONNECT, no stream, oversized or malformed
//! frames) closes that session with a code and a reason while the others carry on.

use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;

use canopy_client::expand::Expander;
use canopy_client::net::{endpoint, tls};
use canopy_client::{ClientError, ConnectConfig, Connection, Trust};
use canopy_harness::bots::{self, BotsConfig, BotsSummary, PathKind, Progress};
use canopy_protocol::aoi::Viewpoint;
use canopy_protocol::frame::frame;
use canopy_protocol::{ClientMsg, CloseCode};
use canopy_server::session::SessionConfig;
use canopy_server::{ServeOptions, Served, Server, ServerConfig, WEB_PATH, serve_store};
use canopy_test_support::{forest, forest_store, pinned};
use web_transport_quinn::{Session, SessionError, WebTransportError};

async fn start_server() -> Served {
    let cfg = ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        session: SessionConfig { handshake_timeout: Duration::from_secs(3), ..SessionConfig::default() },
        ..ServerConfig::default()
    };
    serve_store(forest_store(), ServeOptions { server: cfg, ..ServeOptions::default() }).await.expect("server starts")
}

/// A WebTransport client's configuration, pinning the server's WebTransport certificate.
fn web(server: &Server) -> ConnectConfig {
    let trust = Trust::pinned(&server.web_fingerprint()).expect("a fingerprint pins");
    let mut cfg = ConnectConfig::new(server.local_addr(), trust);
    cfg.web = Some(WEB_PATH.to_owned());
    cfg
}

async fn complete(cfg: &ConnectConfig, at: [f32; 2]) -> Connection {
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let mut c = Connection::connect(&ep, cfg, None, |_| Viewpoint::at(0, at, 100.0)).await.unwrap();
    c.wait_complete(Duration::from_secs(60)).await.unwrap();
    c
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn native_and_webtransport_clients_share_one_port_and_hold_exactly_their_area_of_interest() {
    let server = start_server().await;
    let native = complete(&pinned(&server), [0.0, 0.0]).await;
    let records = complete(&web(&server), [300.0, -200.0]).await;
    let mut expanding = web(&server);
    expanding.expander = Some(Expander::new(2, 8 << 20));
    let expanding = complete(&expanding, [0.0, 0.0]).await;
    for c in [&native, &records, &expanding] {
        bots::verify(c.state(), forest()).unwrap();
    }
    assert!(expanding.state().stats().records_expanded > 100, "the WebTransport client expanded its cells");
    assert_eq!(expanding.state().record_count(), native.state().record_count(), "the same viewpoint, the same set");
    let m = server.metrics();
    assert_eq!((m.clients.load(Relaxed), m.web_clients.load(Relaxed)), (3, 2));
    // Bots over WebTransport, moving: every one exact.
    let mut cfg = BotsConfig::new(5, web(&server));
    cfg.path = PathKind::Random;
    cfg.speed = 25.0;
    cfg.duration = Duration::from_secs(3);
    cfg.radius = 100.0;
    cfg.verify = Some(Arc::clone(forest()));
    let reports = bots::run(cfg, Arc::new(Progress::default())).await.unwrap();
    let summary = BotsSummary::new(&reports, Duration::ZERO);
    assert!(summary.ok() && summary.verified == 5, "{summary}");
    for c in [native, records, expanding] {
        c.close();
    }
    server.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_kind_of_client_is_given_its_own_certificate() {
    let server = start_server().await;
    assert_ne!(server.web_fingerprint(), server.fingerprint());
    let der = server.web_certificate().der();
    assert_eq!(canopy_protocol::messages::certificate_fingerprint(der.as_ref()), server.web_fingerprint());
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let at = |_: &_| Viewpoint::at(0, [0.0, 0.0], 10.0);
    // A browser pinning the long-lived certificate is refused: it is shown the short-lived one.
    let mut cfg = web(&server);
    cfg.trust = Trust::pinned(server.fingerprint()).unwrap();
    let err = Connection::connect(&ep, &cfg, None, at).await.unwrap_err();
    assert!(matches!(err, ClientError::Lost(_)), "{err}");
    // And a native client pinning the browsers' certificate.
    let cfg = ConnectConfig::new(server.local_addr(), Trust::pinned(&server.web_fingerprint()).unwrap());
    let err = Connection::connect(&ep, &cfg, None, at).await.unwrap_err();
    assert!(matches!(err, ClientError::Lost(_)), "{err}");
    server.shutdown(Duration::from_secs(1)).await;
}

/// A WebTransport session opened by hand (HTTP/3 settings and CONNECT to `path`), for misbehaving in.
async fn session(server: &Server, path: &str) -> Result<Session, web_transport_quinn::ClientError> {
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let trust = Trust::pinned(&server.web_fingerprint()).unwrap();
    let quic = tls::client_config_alpn(trust, Duration::from_secs(30), b"h3").unwrap();
    let conn = ep.connect_with(quic, server.local_addr(), "localhost").unwrap().await.unwrap();
    let url = url::Url::parse(&format!("https://localhost:{}{path}", server.local_addr().port())).unwrap();
    Session::connect(conn, web_transport_quinn::proto::ConnectRequest::new(url)).await
}

/// How the server closed `s`: its code and reason.
async fn closed(s: &Session) -> (Option<CloseCode>, String) {
    match tokio::time::timeout(Duration::from_secs(20), s.closed()).await.expect("the server closes in time") {
        SessionError::WebTransportError(WebTransportError::Closed(code, reason)) => {
            (CloseCode::from_code(u64::from(code)), reason)
        }
        e => panic!("expected a WebTransport close, got {e}"),
    }
}

/// Open a session, write `bytes` on its control stream (none: open no stream), and return how it was closed.
async fn misbehave(server: &Server, bytes: Option<Vec<u8>>) -> (Option<CloseCode>, String) {
    let s = session(server, WEB_PATH).await.expect("the session opens");
    let _stream = match bytes {
        Some(bytes) => {
            let (mut send, recv) = s.open_bi().await.unwrap();
            let _ = send.write_all(&bytes).await;
            Some((send, recv))
        }
        None => None,
    };
    closed(&s).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_webtransport_input_closes_that_session_with_a_reason_and_the_others_carry_on() {
    let server = start_server().await;
    let mut good = complete(&web(&server), [0.0, 0.0]).await;
    // A CONNECT to another path is answered 404 and closed.
    match session(&server, "/elsewhere").await {
        Err(e) => assert!(e.to_string().contains("404") || e.to_string().contains("no WebTransport endpoint"), "{e}"),
        Ok(s) => {
            let (code, why) = closed(&s).await;
            panic!("a CONNECT to an unknown path was accepted, then closed with {code:?}: {why}");
        }
    }
    let cases: Vec<(Option<Vec<u8>>, CloseCode, &str)> = vec![
        (None, CloseCode::Timeout, "no control stream"),
        (Some((1u32 << 20).to_le_bytes().to_vec()), CloseCode::TooLarge, "exceeds the limit"),
        (Some(frame(&[0xff, 0xff, 0xff, 0xff])), CloseCode::Malformed, "malformed message"),
        (
            Some(frame(&ClientMsg::viewpoint(Viewpoint::at(1, [0.0, 0.0], 50.0)).encode())),
            CloseCode::OutOfOrder,
            "not legal in phase Start",
        ),
    ];
    for (bytes, code, reason) in cases {
        let (got, why) = misbehave(&server, bytes).await;
        assert_eq!(got, Some(code), "{why}");
        assert!(why.contains(reason), "expected `{reason}` in `{why}`");
    }
    // A QUIC connection that speaks h3 but never sends its CONNECT is closed at the handshake timeout.
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let quic = tls::client_config_alpn(Trust::Insecure, Duration::from_secs(30), b"h3").unwrap();
    let conn = ep.connect_with(quic, server.local_addr(), "localhost").unwrap().await.unwrap();
    match tokio::time::timeout(Duration::from_secs(20), conn.closed()).await.expect("closed in time") {
        quinn::ConnectionError::ApplicationClosed(c) => {
            assert_eq!(CloseCode::from_code(c.error_code.into_inner()), Some(CloseCode::Timeout));
            assert!(String::from_utf8_lossy(&c.reason).contains("no WebTransport CONNECT"));
        }
        e => panic!("expected an application close, got {e}"),
    }
    // The well-behaved session carries on.
    good.set_viewpoint(Viewpoint::at(0, [200.0, 300.0], 100.0)).await.unwrap();
    good.wait_complete(Duration::from_secs(60)).await.unwrap();
    bots::verify(good.state(), forest()).unwrap();
    let m = server.metrics();
    for _ in 0..100 {
        if m.clients.load(Relaxed) == 1 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!((m.clients.load(Relaxed), m.web_clients.load(Relaxed)), (1, 1));
    good.close();
    server.shutdown(Duration::from_secs(1)).await;
}
