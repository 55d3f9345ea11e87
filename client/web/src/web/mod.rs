//! The page itself (wasm32 only): the exports the page's script calls (`start`, and the test hooks
//! `canopyState`, `canopyTeleport`, `canopyWalk`, `canopyRadius`), the animation loop (move the camera, send
//! viewpoints, expand cells within a time budget, draw), and the input handlers.

mod draw;
mod gpu; // The 3D view: canopy-render on WebGPU.
mod transport;

use std::cell::{Cell, RefCell};
use std::rc::Rc;
use std::time::Duration;

use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;

use crate::camera::{Camera, Keys, MOUSE_TURN, Walk};
use crate::map::Map;
use crate::page::{PageState, query_options};
use crate::session::{Fault, Link, Session};

/// Time a slice of cell expansion may take, milliseconds (one cell at least while any waits).
const EXPAND_BUDGET_MS: f64 = 8.0;
/// How often the expansion timer looks for granted cells while none waits, milliseconds.
const PUMP_IDLE_MS: i32 = 16;
/// How long connecting and the handshake may take, milliseconds (the native client's 20 s).
const HANDSHAKE_TIMEOUT_MS: f64 = 20_000.0;
/// Altitude over the ground the camera starts at, metres (the default view's).
const START_ALTITUDE: f32 = crate::session::DEFAULT_ALTITUDE;

/// The page's state (one per page, on its only thread).
pub(crate) struct App {
    session: Session,
    link: transport::Link,
    url: Option<String>,
    camera: Camera,
    keys: Keys,
    /// Metres from the camera to the map's nearer edge, as a multiple of the radius (the mouse wheel zooms).
    zoom: f32,
    map: Map,
    canvas: Option<draw::Canvas>,
    started: f64,
    last_frame: Option<f64>,
    /// When the last viewpoint was sent.
    sent_at: f64,
    /// Recent frame intervals, milliseconds.
    intervals: std::collections::VecDeque<f64>,
    frame_ms: f64,
    dragging: bool,
    /// The 3D view (gpu.rs).
    view: gpu::View,
}

thread_local! {
    static APP: RefCell<Option<Rc<RefCell<App>>>> = const { RefCell::new(None) };
    /// Set by `canopyPause(true)`: animation frames draw nothing (the link, the cells and the jobs go on).
    static PAUSED: Cell<bool> = const { Cell::new(false) };
}

fn app() -> Option<Rc<RefCell<App>>> {
    APP.with(|a| a.borrow().clone())
}

fn now() -> f64 {
    web_sys::window().and_then(|w| w.performance()).map_or(0.0, |p| p.now())
}

/// Start the client: read the options from the page's query (`x`, `z`, `yaw`, `radius`), connect, and run the
/// animation loop. Calling it again does nothing.
#[wasm_bindgen]
pub fn start() {
    if app().is_some() {
        return;
    }
    std::panic::set_hook(Box::new(|info| {
        let msg = format!("panic: {info}");
        web_sys::console::error_1(&msg.clone().into());
        if let Some(w) = web_sys::window() {
            let _ = js_sys::Reflect::set(&w, &"canopyPanic".into(), &msg.into());
        }
    }));
    let search = web_sys::window().and_then(|w| w.location().search().ok()).unwrap_or_default();
    let opts = query_options(&search);
    let document = web_sys::window().and_then(|w| w.document());
    let canvas = document.as_ref().and_then(draw::Canvas::find);
    let t = now();
    let app = Rc::new(RefCell::new(App {
        session: Session::new(opts),
        link: transport::Link::default(),
        url: None,
        camera: Camera::default(),
        keys: Keys::default(),
        zoom: 1.2,
        map: Map::default(),
        canvas,
        started: t,
        last_frame: None,
        sent_at: t,
        intervals: Default::default(),
        frame_ms: 0.0,
        dragging: false,
        view: gpu::View::start(),
    }));
    APP.with(|a| *a.borrow_mut() = Some(Rc::clone(&app)));
    listen(&app);
    gpu::listen(&app);
    let connecting = Rc::clone(&app);
    wasm_bindgen_futures::spawn_local(async move {
        if let Err(e) = transport::run(Rc::clone(&connecting)).await {
            connecting.borrow_mut().session.closed(e);
        }
        transport::flush(&connecting);
    });
    pump(Rc::clone(&app));
    animate(app);
}

/// The state a test reads (see `PageState`): phase, error, complete, records, cells, pending, position, digest...
#[wasm_bindgen(js_name = canopyState)]
pub fn canopy_state() -> JsValue {
    let json = match app() {
        Some(a) => a.borrow().page_state(true).to_json(),
        None => PageState::of(&Session::new(Default::default()), [0.0; 3], 0.0).to_json(),
    };
    js_sys::JSON::parse(&json).unwrap_or(JsValue::NULL)
}

/// Put the camera at (x, z), `altitude` metres over the ground (default: as high as it is now over the ground
/// there, at least half a metre); stops a scripted walk.
#[wasm_bindgen(js_name = canopyTeleport)]
pub fn canopy_teleport(x: f32, z: f32, altitude: Option<f32>) -> Result<(), JsValue> {
    if !(x.is_finite() && z.is_finite() && altitude.is_none_or(f32::is_finite)) {
        return Err("canopyTeleport: x, z and altitude must be finite numbers".into());
    }
    let a = app().ok_or("canopyTeleport: the client has not started")?;
    let mut a = a.borrow_mut();
    let a = &mut *a;
    let [cx, cy, cz] = a.camera.position;
    let altitude = altitude.unwrap_or(cy - a.session.height(cx, cz));
    let session = &a.session;
    a.camera.teleport(x, z, altitude, &|x, z| session.height(x, z));
    Ok(())
}

/// Walk the camera through `points` (`[[x, z], ...]`) at `speed` metres a second (default 15), facing each leg;
/// any movement key stops it. `canopyState().walking` says whether it is under way.
#[wasm_bindgen(js_name = canopyWalk)]
pub fn canopy_walk(points: JsValue, speed: Option<f32>) -> Result<(), JsValue> {
    let text = js_sys::JSON::stringify(&points).map(String::from).unwrap_or_default();
    let points: Vec<[f32; 2]> =
        serde_json::from_str(&text).map_err(|e| JsValue::from_str(&format!("canopyWalk: points: {e}")))?;
    let walk = Walk::new(points, speed.unwrap_or(15.0)).ok_or("canopyWalk: no points, or a number not finite")?;
    let a = app().ok_or("canopyWalk: the client has not started")?;
    a.borrow_mut().camera.walk(walk);
    Ok(())
}

/// Ask for another area-of-interest radius, metres (sent with the next viewpoint; the server caps it).
#[wasm_bindgen(js_name = canopyRadius)]
pub fn canopy_radius(radius: f32) -> Result<(), JsValue> {
    let a = app().ok_or("canopyRadius: the client has not started")?;
    a.borrow_mut().session.set_radius(radius);
    Ok(())
}

/// Plant an instance of species `species` at world (x, z) (an editor's page: `?token=HEX`); the request number,
/// whose outcome `canopyState().edits` shows when the server has answered.
#[wasm_bindgen(js_name = canopyPlant)]
pub fn canopy_plant(species: u8, x: f32, z: f32) -> Result<u32, JsValue> {
    let a = app().ok_or("canopyPlant: the client has not started")?;
    let op = canopy_protocol::edit::EditOp::Plant { species, x, z, params: Vec::new() };
    a.borrow_mut().session.edit(op).map_err(|e| JsValue::from_str(&format!("canopyPlant: {e}")))
}

/// Stop drawing (`true`) or draw again (`false`): a paused page submits no GPU work and keeps its last picture, so
/// a screenshot needs nothing from a busy GPU (a CPU adapter's frame can take seconds); the link, the cells and the
/// renderer's jobs go on. The camera resumes from where it was.
#[wasm_bindgen(js_name = canopyPause)]
pub fn canopy_pause(paused: bool) {
    PAUSED.with(|p| p.set(paused));
}

/// The instances held in the cell at world (x, z): `[[species, x, y, z], ...]` by index in the cell.
#[wasm_bindgen(js_name = canopyCell)]
pub fn canopy_cell(x: f32, z: f32) -> Result<JsValue, JsValue> {
    let a = app().ok_or("canopyCell: the client has not started")?;
    let a = a.borrow();
    let grid = a.session.welcome().map(|w| w.world.grid).ok_or("canopyCell: not welcomed yet")?;
    let list: Vec<[f32; 4]> = (a.session.cell_instances(grid.cell_of(x, z)).into_iter())
        .map(|(species, [x, y, z])| [f32::from(species), x, y, z])
        .collect();
    let json = serde_json::to_string(&list).map_err(|e| JsValue::from_str(&e.to_string()))?;
    js_sys::JSON::parse(&json)
}

impl App {
    fn page_state(&self, full: bool) -> PageState {
        let (session, position, yaw) = (&self.session, self.camera.position, self.camera.yaw);
        let mut s =
            if full { PageState::of(session, position, yaw) } else { PageState::summary(session, position, yaw) };
        s.frame_ms = self.frame_ms;
        s.frame_ms_max = self.intervals.iter().copied().fold(0.0, f64::max);
        s.walking = self.camera.walking();
        s.renderer = self.view.describe();
        s.frames = self.view.frames();
        s.jobs = self.view.jobs();
        s.settled = self.view.settled();
        s
    }

    /// One animation frame at time `t` (milliseconds).
    fn frame(&mut self, t: f64) {
        let dt = self.last_frame.map_or(0.0, |l| t - l);
        self.last_frame = Some(t);
        if dt > 0.0 {
            self.intervals.push_back(dt);
            if self.intervals.len() > 60 {
                self.intervals.pop_front();
            }
            self.frame_ms = if self.frame_ms == 0.0 { dt } else { self.frame_ms * 0.9 + dt * 0.1 };
        }
        if self.session.link() == Link::Connecting && t - self.started > HANDSHAKE_TIMEOUT_MS {
            self.session
                .fail(Fault { code: Some(canopy_protocol::CloseCode::Timeout), reason: "timed out connecting".into() });
        }
        // Place the camera at the first viewpoint once the welcome is in.
        if !self.camera.placed
            && let Some(vp) = self.session.state().viewpoint()
        {
            let [x, z] = vp.position;
            let yaw = vp.yaw;
            let session = &self.session;
            self.camera.teleport(x, z, START_ALTITUDE, &|x, z| session.height(x, z));
            self.camera.yaw = yaw;
            self.sent_at = t;
        }
        let session = &self.session;
        let velocity = self.camera.step(&self.keys, (dt / 1000.0) as f32, &|x, z| session.height(x, z));
        if self.camera.placed {
            let [x, _, z] = self.camera.position;
            let since = Duration::from_secs_f64(((t - self.sent_at) / 1000.0).max(0.0));
            if self.session.move_to([x, z], self.camera.yaw, velocity, since) {
                self.sent_at = t;
            }
        }
        let [x, y, z] = self.camera.position;
        let altitude = y - self.session.height(x, z);
        self.session.set_altitude(altitude);
        self.view.frame(&self.session, &self.camera, t, dt);
        let span = self.session.radius().min(self.session.welcome().map_or(f32::MAX, |w| w.aoi.max_radius)) * self.zoom;
        if let Some(c) = &self.canvas {
            c.draw(&mut self.map, &self.session, &self.camera, span);
            c.hud(&format!("{}\n{}", self.hud_text(), self.view.hud()));
        }
    }

    fn hud_text(&self) -> String {
        let s = self.page_state(false);
        let link = match (&s.error, &s.world) {
            (Some(e), _) => format!("{}: {e}", s.phase),
            (None, Some(w)) => format!("{} (world {w})", s.phase),
            (None, None) => format!("{} {}", s.phase, self.url.as_deref().unwrap_or("")),
        };
        let [x, y, z] = s.position;
        format!(
            "link: {link}\narea of interest complete: {}{}\nrecords held: {}   cells held: {}   pending: {}   expanded: {}\n\
             species: {}/{}   frame: {:.1} ms (max {:.1})   dots: {}\n\
             camera: {x:.0} {y:.0} {z:.0}  heading {:.0}°  speed {:.0} m/s  radius {:.0} m{}\n\
             W/A/S/D move, Q/E down/up, Shift faster, drag or click to look, +/- speed, wheel zooms the map",
            if s.complete { "yes" } else { "no" },
            if s.missing > 0 { format!(" ({} cells to come)", s.missing) } else { String::new() },
            s.records,
            s.cells,
            s.pending,
            s.expanded,
            s.species[0],
            s.species[1],
            s.frame_ms,
            s.frame_ms_max,
            self.map.dots,
            s.yaw.to_degrees(),
            self.camera.speed,
            self.session.radius(),
            if s.walking { "  (scripted walk)" } else { "" },
        )
    }
}

/// Run `frame` on every animation frame, and flush what it wrote.
fn animate(app: Rc<RefCell<App>>) {
    type Callback = Closure<dyn FnMut(f64)>;
    let slot: Rc<RefCell<Option<Callback>>> = Rc::new(RefCell::new(None));
    let again = Rc::clone(&slot);
    *slot.borrow_mut() = Some(Closure::new(move |t: f64| {
        if PAUSED.with(Cell::get) {
            // No step from the time paused when it resumes.
            app.borrow_mut().last_frame = None;
        } else {
            app.borrow_mut().frame(t);
        }
        transport::flush(&app);
        if let (Some(w), Some(cb)) = (web_sys::window(), again.borrow().as_ref()) {
            let _ = w.request_animation_frame(cb.as_ref().unchecked_ref());
        }
    }));
    if let (Some(w), Some(cb)) = (web_sys::window(), slot.borrow().as_ref()) {
        let _ = w.request_animation_frame(cb.as_ref().unchecked_ref());
    }
}

/// Expand granted cells in slices of [`EXPAND_BUDGET_MS`] on a timer of their own, not in the animation frames:
/// where the GPU is slow (a CPU adapter draws a frame in seconds) frames are rare, and cells must not wait for them.
/// While no cell waits, the slices compute the far view's summary nodes instead (`Session::far_step`), with the
/// same budget, then run the renderer's queued jobs. Between slices the page's events run, so input never waits
/// longer than a slice.
fn pump(app: Rc<RefCell<App>>) {
    type Callback = Closure<dyn FnMut()>;
    let slot: Rc<RefCell<Option<Callback>>> = Rc::new(RefCell::new(None));
    let again = Rc::clone(&slot);
    let schedule = |cb: &Callback, delay: i32| {
        if let Some(w) = web_sys::window() {
            let _ = w.set_timeout_with_callback_and_timeout_and_arguments_0(cb.as_ref().unchecked_ref(), delay);
        }
    };
    *slot.borrow_mut() = Some(Closure::new(move || {
        let waiting = {
            let mut a = app.borrow_mut();
            let deadline = now() + EXPAND_BUDGET_MS;
            a.session.expand(&mut || now() < deadline);
            if a.session.pending() == 0 && now() < deadline {
                let at = Duration::from_secs_f64(now().max(0.0) / 1e3);
                a.session.far_step(at, &mut || now() < deadline);
            }
            // What time is left goes to the renderer's jobs, which a slow GPU's rare frames would hold back.
            let jobs = if now() < deadline { a.view.run_jobs(&mut || now() < deadline) } else { 0 };
            a.session.pending() > 0 || a.session.far().busy() || jobs > 0
        };
        transport::flush(&app);
        if let Some(cb) = again.borrow().as_ref() {
            schedule(cb, if waiting { 0 } else { PUMP_IDLE_MS });
        }
    }));
    if let Some(cb) = slot.borrow().as_ref() {
        schedule(cb, 0);
    }
}

/// Keys, the mouse (drag, or click for pointer lock) and the wheel.
fn listen(app: &Rc<RefCell<App>>) {
    let Some(window) = web_sys::window() else { return };
    let on = |target: &web_sys::EventTarget, name: &str, f: Box<dyn FnMut(web_sys::Event)>| {
        let cb = Closure::wrap(f);
        let _ = target.add_event_listener_with_callback(name, cb.as_ref().unchecked_ref());
        // The page lives as long as its listeners.
        cb.forget();
    };
    for (name, down) in [("keydown", true), ("keyup", false)] {
        let app = Rc::clone(app);
        on(
            &window,
            name,
            Box::new(move |e| {
                let Some(e) = e.dyn_ref::<web_sys::KeyboardEvent>() else { return };
                let mut a = app.borrow_mut();
                let code = e.code();
                let handled = a.keys.set(&code, down)
                    || match (down, code.as_str()) {
                        (true, "Equal" | "NumpadAdd") => {
                            a.camera.speed = (a.camera.speed * 1.25).min(2000.0);
                            true
                        }
                        (true, "Minus" | "NumpadSubtract") => {
                            a.camera.speed = (a.camera.speed / 1.25).max(0.5);
                            true
                        }
                        // An editor's page plants the world's first species 8 m ahead.
                        (true, "KeyP") if a.session.editor() => {
                            let [x, _, z] = a.camera.position;
                            let [dx, dz] = a.camera.heading();
                            let op = canopy_protocol::edit::EditOp::Plant {
                                species: 0,
                                x: x + 8.0 * dx,
                                z: z + 8.0 * dz,
                                params: Vec::new(),
                            };
                            let _ = a.session.edit(op);
                            true
                        }
                        _ => false,
                    };
                if handled {
                    e.prevent_default();
                }
            }),
        );
    }
    {
        let app = Rc::clone(app);
        on(&window, "blur", Box::new(move |_| app.borrow_mut().keys = Keys::default()));
    }
    let Some(canvas) = app.borrow().canvas.as_ref().map(|c| c.element().clone()) else { return };
    {
        let app = Rc::clone(app);
        let target = canvas.clone();
        on(
            &canvas,
            "mousedown",
            Box::new(move |_| {
                app.borrow_mut().dragging = true;
                target.request_pointer_lock();
            }),
        );
    }
    {
        let app = Rc::clone(app);
        on(&window, "mouseup", Box::new(move |_| app.borrow_mut().dragging = false));
    }
    {
        let app = Rc::clone(app);
        on(
            &window,
            "mousemove",
            Box::new(move |e| {
                let Some(e) = e.dyn_ref::<web_sys::MouseEvent>() else { return };
                let locked =
                    web_sys::window().and_then(|w| w.document()).and_then(|d| d.pointer_lock_element()).is_some();
                let mut a = app.borrow_mut();
                if locked || a.dragging {
                    a.camera.turn(e.movement_x() as f32 * MOUSE_TURN, -(e.movement_y() as f32) * MOUSE_TURN);
                }
            }),
        );
    }
    {
        let app = Rc::clone(app);
        on(
            &canvas,
            "wheel",
            Box::new(move |e| {
                let Some(e) = e.dyn_ref::<web_sys::WheelEvent>() else { return };
                let mut a = app.borrow_mut();
                let k = if e.delta_y() > 0.0 { 1.15 } else { 1.0 / 1.15 };
                a.zoom = (a.zoom * k).clamp(0.05, 20.0);
                e.prevent_default();
            }),
        );
    }
}
