//! The browser client in a real browser (issue 34): headless Chromium, driven through chromedriver (WebDriver over
//! HTTP), opens the page an in-process `canopy-server` serves (`ServerConfig::web`, the page `scripts/build-web`
//! builds), connects over WebTransport pinning the short-lived certificate, expands its cells in the page, and
//! walks a scripted path. The test reads the page's state (`canopyState()`): its area of interest complete, the
//! digest of what it holds equal to the world function's for the same cells, before and after the walk. Edits cross
//! both ways: a plant from a native editor appears in the page, a plant from the page (an editor's token in its
//! query) reaches the native client. A screenshot is compared loosely to a reference.
//!
//! Needs Chromium, chromedriver and the built page: `scripts/test` installs the first two and builds the page. A
//! missing one fails the test with what to run; it never passes by skipping.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_client::net::endpoint;
use canopy_client::{ConnectConfig, Connection, Trust};
use canopy_protocol::CellCoord;
use canopy_protocol::aoi::Viewpoint;
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_server::edits::{EditStore, MemoryEditStore};
use canopy_server::session::{Editors, SessionConfig, editor_line};
use canopy_server::{Edits, ServeOptions, Served, ServerConfig, WebConfig, serve_store};
use canopy_test_support::{forest, forest_store};
use serde_json::{Value, json};

/// The editor's token the page and the native editor use.
const TOKEN: [u8; 32] = [7; 32];
/// How long the page may take to fill its area of interest (the cold wasm load included).
const WAIT: Duration = Duration::from_secs(180);

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// A minimal HTTP/1.1 exchange with chromedriver: `method path` with a JSON body; the JSON answer's `value`.
fn webdriver(port: u16, method: &str, path: &str, body: Option<&Value>) -> Value {
    let v = try_webdriver(port, method, path, body).unwrap_or_else(|e| panic!("{method} {path}: {e}"));
    // WebDriver's errors: `{"error", "message", "stacktrace"}` (a page state has an `error` field of its own).
    let failed = v["value"].get("error").is_some_and(Value::is_string) && v["value"].get("stacktrace").is_some();
    assert!(!failed, "{method} {path}: {v}");
    v["value"].clone()
}

/// One WebDriver request: chromedriver's whole answer, or why none came (the connection failed or closed early).
fn try_webdriver(port: u16, method: &str, path: &str, body: Option<&Value>) -> Result<Value, String> {
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    let mut s = TcpStream::connect(("127.0.0.1", port)).map_err(|e| format!("chromedriver does not answer: {e}"))?;
    s.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\
         Connection: close\r\n\r\n",
        body.len()
    );
    s.write_all(head.as_bytes()).and_then(|()| s.write_all(body.as_bytes())).map_err(|e| format!("request: {e}"))?;
    // Read the head, then the body by its length (chromedriver may keep the connection open).
    let mut raw = Vec::new();
    let mut buf = [0u8; 65536];
    let mut read = |raw: &mut Vec<u8>| match s.read(&mut buf) {
        Ok(0) => Err("chromedriver closed before answering".to_string()),
        Ok(n) => {
            raw.extend_from_slice(&buf[..n]);
            Ok(())
        }
        Err(e) => Err(format!("answer read: {e}")),
    };
    let at = loop {
        if let Some(i) = raw.windows(4).position(|w| w == b"\r\n\r\n") {
            break i + 4;
        }
        read(&mut raw)?;
    };
    let head = String::from_utf8_lossy(&raw[..at]).to_ascii_lowercase();
    let length = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))
        .map(|v| v.trim().parse::<usize>().expect("a length"))
        .ok_or_else(|| format!("no content-length in chromedriver's answer: {head}"))?;
    while raw.len() < at + length {
        read(&mut raw)?;
    }
    serde_json::from_slice(&raw[at..at + length]).map_err(|e| format!("chromedriver's answer is not JSON: {e}"))
}

/// Times chromedriver and Chromium are started before a test gives up: on a loaded machine chromedriver has
/// dropped the connection that asked for a session, before any page was opened (CI on 2026-11-29).
const BROWSER_STARTS: usize = 3;

/// chromedriver with one headless Chromium session; both end when this drops.
struct Browser {
    driver: Child,
    port: u16,
    session: String,
}

impl Browser {
    fn start(flags: &[&str]) -> Browser {
        let which = |name: &str| {
            ["/usr/bin", "/usr/local/bin", "/usr/lib/chromium"]
                .iter()
                .map(|d| Path::new(d).join(name))
                .find(|p| p.is_file())
        };
        let chromedriver = which("chromedriver").unwrap_or_else(|| {
            panic!("chromedriver not found: install Debian's chromium and chromium-driver (scripts/test does)")
        });
        let chromium = which("chromium").unwrap_or_else(|| panic!("chromium not found (scripts/test installs it)"));
        let mut why = Vec::new();
        for _ in 0..BROWSER_STARTS {
            match Browser::try_start(&chromedriver, &chromium, flags) {
                Ok(b) => return b,
                Err(e) => why.push(e),
            }
        }
        panic!("no browser session in {BROWSER_STARTS} starts: {why:?}");
    }

    /// Start chromedriver and ask it for a session; `Err` (chromedriver stopped) when the session was not made.
    fn try_start(chromedriver: &Path, chromium: &Path, flags: &[&str]) -> Result<Browser, String> {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let driver = Command::new(chromedriver)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver starts");
        let started = Instant::now();
        while TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(started.elapsed() < Duration::from_secs(20), "chromedriver did not listen on {port}");
            std::thread::sleep(Duration::from_millis(50));
        }
        let profile = tempfile::tempdir().unwrap();
        let mut args: Vec<String> = [
            "--headless=new",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--window-size=800,600",
        ]
        .iter()
        .chain(flags)
        .map(|s| s.to_string())
        .collect();
        args.push(format!("--user-data-dir={}", profile.keep().display()));
        // Chromium's sandbox refuses to run as root (CI's user); the page is ours, on loopback.
        args.push("--no-sandbox".into());
        let caps = json!({"capabilities": {"alwaysMatch": {"browserName": "chrome",
            "goog:chromeOptions": {"binary": chromium, "args": args}}}});
        let mut b = Browser { driver, port, session: String::new() };
        // Asked once: a WebDriver error (chromedriver's own answer) fails the test; no answer at all starts again.
        let s = try_webdriver(port, "POST", "/session", Some(&caps))?;
        assert!(s["value"].get("stacktrace").is_none(), "POST /session: {s}");
        b.session = s["value"]["sessionId"].as_str().expect("a session id").to_owned();
        Ok(b)
    }

    fn call(&self, method: &str, path: &str, body: Option<&Value>) -> Value {
        webdriver(self.port, method, &format!("/session/{}{path}", self.session), body)
    }

    fn open(&self, url: &str) {
        self.call("POST", "/url", Some(&json!({ "url": url })));
    }

    /// The value of the script `body` (a function body: `return ...`).
    fn eval(&self, body: &str) -> Value {
        self.call("POST", "/execute/sync", Some(&json!({ "script": body, "args": [] })))
    }

    fn state(&self) -> Value {
        self.eval("return window.canopyState ? window.canopyState() : null;")
    }

    /// Poll the page's state until `done` holds (panics with the last state after [`WAIT`]).
    fn until(&self, what: &str, done: impl Fn(&Value) -> bool) -> Value {
        let started = Instant::now();
        loop {
            let s = self.state();
            if done(&s) {
                return s;
            }
            assert!(s["phase"] != "closed", "the page closed while waiting for {what}: {s}");
            assert!(started.elapsed() < WAIT, "waited {WAIT:?} for {what}: {s}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    fn screenshot(&self) -> Vec<u8> {
        use std::io::Cursor;
        let b64 = self.call("GET", "/screenshot", None);
        let png = base64(b64.as_str().expect("base64 text"));
        let img = image::ImageReader::new(Cursor::new(png)).with_guessed_format().unwrap().decode().unwrap();
        img.into_rgb8().into_raw()
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if !self.session.is_empty() {
            let _ = std::panic::catch_unwind(|| {
                webdriver(self.port, "DELETE", &format!("/session/{}", self.session), None)
            });
        }
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

fn base64(s: &str) -> Vec<u8> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        _ => 63,
    };
    let digits: Vec<u8> = s.bytes().filter(|c| c.is_ascii_alphanumeric() || *c == b'+' || *c == b'/').collect();
    let mut out = Vec::with_capacity(digits.len() * 3 / 4);
    for chunk in digits.chunks(4) {
        let n = chunk.iter().enumerate().fold(0u32, |n, (i, &c)| n | u32::from(value(c)) << (18 - 6 * i));
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    out
}

async fn start_server() -> (Served, Arc<MemoryEditStore>) {
    let dist = root().join("client/web/dist");
    for f in ["index.html", "canopy_web.js", "canopy_web_bg.wasm"] {
        assert!(dist.join(f).is_file(), "{} is missing: build the page with scripts/build-web", dist.join(f).display());
    }
    let edits = Arc::new(MemoryEditStore::new());
    let editors = editor_line("page", &TOKEN, None, Some(100));
    let cfg = ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        web: Some(WebConfig { listen: "127.0.0.1:0".parse().unwrap(), root: dist }),
        session: SessionConfig {
            editors: Some(Arc::new(Editors::parse("editors", &editors).unwrap())),
            ..SessionConfig::default()
        },
        ..ServerConfig::default()
    };
    let opts = ServeOptions {
        server: cfg,
        edits: Edits::Store(Arc::clone(&edits) as Arc<dyn EditStore>),
        overlay_cache_bytes: 1 << 20,
        ..ServeOptions::default()
    };
    (serve_store(forest_store(), opts).await.expect("server starts"), edits)
}

/// The page's digest is the world's for the cells it holds, and it holds some.
fn assert_holds_the_world(s: &Value) {
    let cells: Vec<CellCoord> = s["held_cells"]
        .as_array()
        .expect("held_cells")
        .iter()
        .map(|c| CellCoord::new(c[0].as_i64().unwrap() as i32, c[1].as_i64().unwrap() as i32))
        .collect();
    assert!(cells.len() >= 4, "{s}");
    let (digest, count) = canopy_web::page::world_digest(forest(), &cells);
    assert_eq!(s["digest"], format!("{digest:016x}"), "the page's instances are not the world's: {s}");
    assert_eq!(s["records"], count, "{s}");
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_walks_the_forest_over_webtransport_and_edits_cross_both_ways() {
    let started = Instant::now();
    let (server, _edits) = start_server().await;
    let page = format!("http://{}/?x=0&z=0&yaw=0&radius=150&token={}", server.web_addr().unwrap(), hex(&TOKEN));
    let browser = tokio::task::block_in_place(|| {
        let b = Browser::start(&[]);
        b.open(&page);
        b
    });
    let first = tokio::task::block_in_place(|| {
        browser.until("the first complete area of interest", |s| s["complete"] == true && s["pending"] == 0)
    });
    let to_complete = started.elapsed();
    eprintln!("server start to a complete area of interest in the page: {to_complete:.2?}");
    assert_eq!(first["phase"], "streaming");
    assert_eq!(first["editor"], true, "{first}");
    // Without WebGPU (Chromium's default here: no GPU) the page says why and draws the 2D map.
    assert!(first["renderer"].as_str().is_some_and(|r| r.starts_with("none")), "{first}");
    assert_holds_the_world(&first);
    assert_eq!(server.metrics().web_clients.load(std::sync::atomic::Ordering::Relaxed), 1);

    // A scripted walk: the area of interest follows and is complete, and exact, where it ends.
    let walked = tokio::task::block_in_place(|| {
        browser.eval("window.canopyWalk([[0, 120], [120, 120]], 60); return true;");
        browser.until("the walk's end", |s| s["walking"] == false && s["complete"] == true && s["pending"] == 0)
    });
    let [x, z] = [walked["position"][0].as_f64().unwrap(), walked["position"][2].as_f64().unwrap()];
    assert!((x - 120.0).abs() < 1.0 && (z - 120.0).abs() < 1.0, "{walked}");
    assert_ne!(walked["held_cells"], first["held_cells"]);
    assert_holds_the_world(&walked);

    // A native editor plants beside the page's camera: the plant appears in the page.
    let trust = Trust::pinned(server.fingerprint()).unwrap();
    let mut cfg = ConnectConfig::new(server.local_addr(), trust);
    cfg.token = Some(TOKEN.to_vec());
    let ep = endpoint("127.0.0.1:0".parse().unwrap()).unwrap();
    let mut native = Connection::connect(&ep, &cfg, None, |_| Viewpoint::at(0, [120.0, 120.0], 100.0)).await.unwrap();
    native.wait_complete(WAIT).await.unwrap();
    let request = native.edit(EditOp::Plant { species: 1, x: 131.5, z: 127.25, params: vec![] }).await.unwrap();
    let outcome = wait_edit(&mut native, request).await;
    assert!(matches!(outcome, EditOutcome::Ok { .. }), "{outcome:?}");
    tokio::task::block_in_place(|| {
        let started = Instant::now();
        loop {
            let cell = browser.eval("return window.canopyCell(131.5, 127.25);");
            let near = |e: &Value| {
                e[0] == 1.0
                    && (e[1].as_f64().unwrap() - 131.5).abs() < 0.1
                    && (e[3].as_f64().unwrap() - 127.25).abs() < 0.1
            };
            if cell.as_array().expect("a list").iter().any(near) {
                break;
            }
            assert!(started.elapsed() < WAIT, "the native plant never reached the page: {cell}");
            std::thread::sleep(Duration::from_millis(100));
        }
    });

    // The page plants (its hello carried the token): the server applies it and the native client holds it.
    let asked = tokio::task::block_in_place(|| browser.eval("return window.canopyPlant(2, 112.5, 108.75);"));
    let request = asked.as_u64().expect("a request number");
    let answered = tokio::task::block_in_place(|| {
        browser.until("the page's edit answered", |s| {
            s["edits"]
                .as_array()
                .is_some_and(|e| e.iter().any(|e| e["request"] == request && e["outcome"] != "waiting"))
        })
    });
    let edit = answered["edits"].as_array().unwrap().iter().find(|e| e["request"] == request).unwrap().clone();
    assert_eq!(edit["outcome"], "ok", "{answered}");
    let started_wait = Instant::now();
    loop {
        let height = |_: f32, _: f32| 0.0;
        let seen = native
            .state()
            .instances(&height)
            .any(|i| i.species == 2 && (i.position[0] - 112.5).abs() < 0.1 && (i.position[2] - 108.75).abs() < 0.1);
        if seen {
            break;
        }
        assert!(started_wait.elapsed() < WAIT, "the page's plant never reached the native client");
        let _ = tokio::time::timeout(Duration::from_millis(200), native.next_event()).await;
    }

    // The page as it looks now, loosely against the reference (the HUD's numbers differ from run to run).
    let shot = tokio::task::block_in_place(|| browser.screenshot());
    compare_loosely(&shot, "page-2d.png");
    native.close();
    drop(browser);
    server.shutdown(Duration::from_secs(1)).await;
}

/// Chromium's flags for WebGPU on SwiftShader (Vulkan on the CPU), as no GPU is needed.
const WEBGPU: [&str; 7] = [
    "--enable-unsafe-webgpu",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--enable-features=Vulkan",
    "--use-vulkan=swiftshader",
    "--use-webgpu-adapter=swiftshader",
    "--ignore-gpu-blocklist",
];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_webgpu_the_page_draws_the_forest_with_the_native_renderer() {
    let started = Instant::now();
    let (server, _edits) = start_server().await;
    let page = format!("http://{}/?x=40&z=-760&yaw=20&radius=150", server.web_addr().unwrap());
    let (state, shot) = tokio::task::block_in_place(|| {
        let browser = Browser::start(&WEBGPU);
        browser.open(&page);
        let s = browser.until("the renderer and a complete area of interest", |s| {
            s["complete"] == true && s["pending"] == 0 && s["renderer"].as_str().is_some_and(|r| r != "starting")
        });
        assert!(s["renderer"].as_str().is_some_and(|r| r.starts_with("webgpu")), "no WebGPU renderer: {s}");
        // Frames drawn after the area of interest filled: the near trees amplified (a budget a frame).
        let drawn = s["frames"].as_u64().unwrap_or(0);
        let s = browser.until("frames drawn with the trees", |t| {
            t["frames"].as_u64().unwrap_or(0) >= drawn + 2 && t["settled"] == true
        });
        // A still page for the screenshot: while SwiftShader draws (seconds a frame on a loaded machine) the renderer
        // does not answer chromedriver, which gives up after 10 s, again and again.
        browser.eval("window.canopyPause(true); return null;");
        (s, browser.screenshot())
    });
    let drawn = started.elapsed();
    assert_holds_the_world(&state);
    eprintln!(
        "WebGPU on SwiftShader ({}): server start to the complete area of interest drawn with its trees {drawn:.2?}, \
         {} frames, the last {:.0} ms",
        state["renderer"], state["frames"], state["frame_ms"]
    );
    compare_loosely(&shot, "page-webgpu.png");
    server.shutdown(Duration::from_secs(1)).await;
}

async fn wait_edit(c: &mut Connection, request: u32) -> EditOutcome {
    let started = Instant::now();
    loop {
        assert!(started.elapsed() < WAIT, "no answer to edit {request}");
        if let Ok(Ok(canopy_client::state::Event::EditResult(r))) =
            tokio::time::timeout(Duration::from_millis(200), c.next_event()).await
            && r.request == request
        {
            return r.outcome;
        }
    }
}

/// Compare an 800 × 600 RGB screenshot with the reference `name` in `tests/tests/browser/` on 8 × 8 blocks: the
/// mean absolute difference of the blocks' mean colours under 12 of 255. `CANOPY_BLESS=1` writes a missing
/// reference.
fn compare_loosely(rgb: &[u8], name: &str) {
    let (w, h) = (800usize, rgb.len() / 3 / 800);
    let path = root().join("tests/tests/browser").join(name);
    if !path.exists() && std::env::var_os("CANOPY_BLESS").is_some() {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        image::RgbImage::from_raw(w as u32, h as u32, rgb.to_vec()).unwrap().save(&path).unwrap();
    }
    let reference =
        image::open(&path).unwrap_or_else(|e| panic!("{}: {e} (CANOPY_BLESS=1 writes it)", path.display())).into_rgb8();
    assert_eq!((reference.width() as usize, reference.height() as usize), (w, h), "the window size changed");
    let blocks = |px: &[u8]| -> Vec<f64> {
        let mut out = vec![0.0; (w / 8) * (h / 8) * 3];
        for y in 0..h / 8 * 8 {
            for x in 0..w / 8 * 8 {
                for c in 0..3 {
                    out[((y / 8) * (w / 8) + x / 8) * 3 + c] += f64::from(px[(y * w + x) * 3 + c]) / 64.0;
                }
            }
        }
        out
    };
    let (a, b) = (blocks(rgb), blocks(reference.as_raw()));
    let diff = a.iter().zip(&b).map(|(a, b)| (a - b).abs()).sum::<f64>() / a.len() as f64;
    if diff >= 12.0 {
        let actual = path.with_file_name(name.replace(".png", "-actual.png"));
        image::RgbImage::from_raw(w as u32, h as u32, rgb.to_vec()).unwrap().save(&actual).unwrap();
        panic!(
            "the page looks different from {}: mean block difference {diff:.1} (see {})",
            path.display(),
            actual.display()
        );
    }
}
