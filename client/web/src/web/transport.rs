//! WebTransport, bound by hand (web-sys has it only behind `--cfg=web_sys_unstable_apis`), and the tasks that
//! connect, read the control stream and each lane the server opens, and write the control stream. Every byte goes
//! through the sans-IO [`Session`](crate::session::Session); these tasks only move bytes and report how the
//! transport ended.

use std::cell::RefCell;
use std::rc::Rc;

use js_sys::{Array, Object, Reflect, Uint8Array};
use wasm_bindgen::prelude::*;
use wasm_bindgen::{JsCast, JsValue};
use wasm_bindgen_futures::{JsFuture, spawn_local};
use web_sys::{ReadableStream, ReadableStreamDefaultReader, WritableStream, WritableStreamDefaultWriter};

use super::App;
use canopy_protocol::CloseCode;

use crate::page::ConnectInfo;
use crate::session::Fault;

#[wasm_bindgen]
extern "C" {
    /// The browser's `WebTransport`.
    #[derive(Clone, Debug)]
    pub type WebTransport;

    #[wasm_bindgen(constructor, catch, js_class = "WebTransport")]
    fn new(url: &str, options: &JsValue) -> Result<WebTransport, JsValue>;

    #[wasm_bindgen(method, getter)]
    fn ready(this: &WebTransport) -> js_sys::Promise;

    #[wasm_bindgen(method, getter)]
    fn closed(this: &WebTransport) -> js_sys::Promise;

    #[wasm_bindgen(method, js_name = createBidirectionalStream)]
    fn create_bidirectional_stream(this: &WebTransport) -> js_sys::Promise;

    #[wasm_bindgen(method, getter, js_name = incomingUnidirectionalStreams)]
    fn incoming_unidirectional_streams(this: &WebTransport) -> ReadableStream;

    #[wasm_bindgen(method, catch)]
    fn close(this: &WebTransport, info: &JsValue) -> Result<(), JsValue>;
}

/// The transport and the control stream's writer, once they exist.
#[derive(Default)]
pub(super) struct Link {
    transport: Option<WebTransport>,
    writer: Option<WritableStreamDefaultWriter>,
    /// Whether the transport was closed from this side.
    closed: bool,
}

/// A JavaScript error as text: its message (with a WebTransport error's source and code), else its string form.
pub(super) fn describe(e: &JsValue) -> String {
    let field = |k: &str| Reflect::get(e, &JsValue::from_str(k)).ok().filter(|v| !v.is_undefined() && !v.is_null());
    let mut out = match field("message").and_then(|m| m.as_string()) {
        Some(m) if !m.is_empty() => m,
        _ => e.as_string().unwrap_or_else(|| format!("{e:?}")),
    };
    if let Some(s) = field("source").and_then(|s| s.as_string()) {
        out.push_str(&format!(" (source: {s})"));
    }
    if let Some(c) = field("streamErrorCode").and_then(|c| c.as_f64()) {
        out.push_str(&format!(" (stream error {c})"));
    }
    out
}

/// Write what the session has for the control stream, and close the transport if the session failed by a fault
/// of the server's.
pub(super) fn flush(app: &Rc<RefCell<App>>) {
    let (bytes, close, writer, transport) = {
        let mut a = app.borrow_mut();
        let bytes = if a.link.writer.is_some() { a.session.take_outbox() } else { Vec::new() };
        let mut close = a.session.take_close();
        let ended = a.session.link() == crate::session::Link::Closed;
        // A session that ended (by a fault, or a timeout before the transport was up) closes the transport once;
        // closing one the server already closed is a no-op.
        let transport = match (a.link.transport.clone(), ended, a.link.closed) {
            (Some(t), true, false) => {
                a.link.closed = true;
                close.get_or_insert(Fault { code: Some(CloseCode::Normal), reason: "bye".into() });
                Some(t)
            }
            _ => None,
        };
        (bytes, close, a.link.writer.clone(), transport)
    };
    if let (false, Some(w)) = (bytes.is_empty(), writer) {
        let written = w.write_with_chunk(&Uint8Array::from(&bytes[..]));
        let app = Rc::clone(app);
        spawn_local(async move {
            if let Err(e) = JsFuture::from(written).await {
                app.borrow_mut().session.closed(format!("writing the control stream: {}", describe(&e)));
            }
        });
    }
    if let (Some(Fault { code: Some(code), reason }), Some(t)) = (close, transport) {
        let info = Object::new();
        let _ = Reflect::set(&info, &"closeCode".into(), &JsValue::from(code as u32));
        // The reason is at most 1,024 bytes on the wire.
        let reason: String = reason.chars().take(200).collect();
        let _ = Reflect::set(&info, &"reason".into(), &JsValue::from_str(&reason));
        let _ = t.close(&info);
    }
}

/// The next value of a stream reader (`None`: the stream ended).
async fn next(reader: &ReadableStreamDefaultReader) -> Result<Option<JsValue>, JsValue> {
    let r = JsFuture::from(reader.read()).await?;
    if Reflect::get(&r, &"done".into())?.as_bool().unwrap_or(false) {
        return Ok(None);
    }
    Ok(Some(Reflect::get(&r, &"value".into())?))
}

/// The next chunk of a byte stream.
async fn next_bytes(reader: &ReadableStreamDefaultReader) -> Result<Option<Vec<u8>>, JsValue> {
    match next(reader).await? {
        Some(v) => Ok(Some(v.dyn_into::<Uint8Array>()?.to_vec())),
        None => Ok(None),
    }
}

fn reader(stream: &ReadableStream) -> ReadableStreamDefaultReader {
    stream.get_reader().unchecked_into()
}

fn closing(app: &Rc<RefCell<App>>) -> bool {
    app.borrow().session.link() == crate::session::Link::Closed
}

/// Fetch `connect.json`, connect, say hello, and read the control stream until it ends; lanes are read by tasks
/// of their own. An error is why the session could not go on.
pub(super) async fn run(app: Rc<RefCell<App>>) -> Result<(), String> {
    let window = web_sys::window().ok_or("no window")?;
    let response = JsFuture::from(window.fetch_with_str("connect.json"))
        .await
        .map_err(|e| format!("fetching connect.json: {}", describe(&e)))?;
    let response: web_sys::Response = response.dyn_into().map_err(|_| "fetch gave no response")?;
    if !response.ok() {
        return Err(format!("fetching connect.json: HTTP {}", response.status()));
    }
    let text = response.text().map_err(|e| describe(&e))?;
    let text = JsFuture::from(text).await.map_err(|e| format!("reading connect.json: {}", describe(&e)))?;
    let info = ConnectInfo::parse(&text.as_string().unwrap_or_default())?;
    let host = window.location().hostname().map_err(|e| describe(&e))?;
    let url = info.url(&host);
    let hash = info.hash()?;

    let pin = Object::new();
    let _ = Reflect::set(&pin, &"algorithm".into(), &"sha-256".into());
    let _ = Reflect::set(&pin, &"value".into(), &Uint8Array::from(&hash[..]));
    let options = Object::new();
    let _ = Reflect::set(&options, &"serverCertificateHashes".into(), &Array::of1(&pin));
    let transport =
        WebTransport::new(&url, &options).map_err(|e| format!("WebTransport to {url}: {}", describe(&e)))?;
    app.borrow_mut().link.transport = Some(transport.clone());
    app.borrow_mut().url = Some(url.clone());
    let watched = Rc::clone(&app);
    let closed = transport.closed();
    spawn_local(async move {
        let why = match JsFuture::from(closed).await {
            Ok(info) => {
                let code = Reflect::get(&info, &"closeCode".into()).ok().and_then(|c| c.as_f64()).unwrap_or(0.0);
                let reason = Reflect::get(&info, &"reason".into()).ok().and_then(|r| r.as_string()).unwrap_or_default();
                format!("the server closed the connection (code {code}): {reason}")
            }
            Err(e) if watched.borrow().session.link() == crate::session::Link::Connecting => {
                format!("connecting to {}: {}", watched.borrow().url.as_deref().unwrap_or("?"), describe(&e))
            }
            Err(e) => format!("connection lost: {}", describe(&e)),
        };
        watched.borrow_mut().session.closed(why);
    });
    JsFuture::from(transport.ready()).await.map_err(|e| format!("connecting to {url}: {}", describe(&e)))?;

    let bidi = JsFuture::from(transport.create_bidirectional_stream())
        .await
        .map_err(|e| format!("opening the control stream: {}", describe(&e)))?;
    let readable: ReadableStream = Reflect::get(&bidi, &"readable".into()).map_err(|e| describe(&e))?.unchecked_into();
    let writable: WritableStream = Reflect::get(&bidi, &"writable".into()).map_err(|e| describe(&e))?.unchecked_into();
    let writer = writable.get_writer().map_err(|e| format!("the control stream's writer: {}", describe(&e)))?;
    app.borrow_mut().link.writer = Some(writer);
    flush(&app);

    spawn_local(accept_lanes(Rc::clone(&app), transport.incoming_unidirectional_streams()));

    let control = reader(&readable);
    loop {
        if closing(&app) {
            return Ok(());
        }
        match next_bytes(&control).await {
            Ok(Some(bytes)) => app.borrow_mut().session.on_control(&bytes),
            Ok(None) => {
                app.borrow_mut().session.end_control();
                flush(&app);
                return Ok(());
            }
            Err(e) => return Err(format!("reading the control stream: {}", describe(&e))),
        }
        flush(&app);
    }
}

/// Take each lane the server opens and read it on a task of its own.
async fn accept_lanes(app: Rc<RefCell<App>>, incoming: ReadableStream) {
    let lanes = reader(&incoming);
    loop {
        if closing(&app) {
            return;
        }
        match next(&lanes).await {
            Ok(Some(stream)) => {
                let lane = app.borrow_mut().session.open_lane();
                spawn_local(read_lane(Rc::clone(&app), stream.unchecked_into(), lane));
            }
            Ok(None) => return,
            Err(e) => {
                app.borrow_mut().session.closed(format!("accepting a lane: {}", describe(&e)));
                return;
            }
        }
    }
}

async fn read_lane(app: Rc<RefCell<App>>, stream: ReadableStream, lane: usize) {
    let r = reader(&stream);
    loop {
        if closing(&app) {
            return;
        }
        match next_bytes(&r).await {
            Ok(Some(bytes)) => app.borrow_mut().session.on_lane(lane, &bytes),
            Ok(None) => {
                app.borrow_mut().session.end_lane(lane);
                flush(&app);
                return;
            }
            Err(e) => {
                app.borrow_mut().session.closed(format!("reading a lane: {}", describe(&e)));
                return;
            }
        }
        flush(&app);
    }
}
