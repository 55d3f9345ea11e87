//! The 3D view (wasm32): the project's renderer, `canopy-render`, on the browser's WebGPU, drawing on the `#view`
//! canvas what the native `canopy walk` window draws — the terrain from the welcome, the trees of every instance the
//! session holds (`ClientState::instances`, as the walk's scene snapshot builds them), the far view's summary nodes
//! beyond them (`ClientState::summaries`, computed in the page: `crate::far`), the sky and its fog — from the
//! page's camera. The renderer amplifies on the page's thread within a time budget a frame (`Renderer::run_jobs`):
//! a browser page has no worker threads.
//!
//! The GPU is set up asynchronously (`Gpu::from_canvas`); until then, and for good where the browser has no WebGPU,
//! no adapter or a device that cannot run the renderer, the page keeps its 2D map and [`View::describe`] says why
//! (`canopyState().renderer`, the HUD). With a GPU the map shrinks to a corner (the `gpu` class on `<body>`); M
//! toggles it between the corner and the whole page (`map-full`).

use std::cell::RefCell;
use std::rc::Rc;
use std::sync::Arc;

use canopy_protocol::CellCoord;
use canopy_render::camera::Camera as RenderCamera;
use canopy_render::{CullPath, FarPath, FrameStats, Gpu, RenderConfig, Renderer, Scene, SceneFar, SceneInstance};
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use web_sys::HtmlCanvasElement;

use super::{App, now};
use crate::camera::Camera;
use crate::session::Session;

/// Time a frame may spend amplifying, voxelising and baking (one job at least while any waits), milliseconds.
const JOB_BUDGET_MS: f64 = 10.0;
/// Renderer jobs queued at once (amplification, voxelisation, tiles).
const PAGE_JOBS: usize = 64;
/// The scene is rebuilt from the session at most this often while what it holds changes, milliseconds (the walk's
/// snapshot interval).
const SCENE_INTERVAL_MS: f64 = 250.0;
/// The vertical field of view, degrees (the native default view's).
const FOV_Y: f32 = 60.0;
/// The 3D view's backing store is at most this many pixels a side.
const MAX_SIDE: u32 = 2048;
/// On a CPU adapter (SwiftShader) the view is drawn at this fraction of its CSS size and stretched: a frame there
/// costs seconds at full size.
const CPU_SCALE: f64 = 0.5;

thread_local! {
    /// The first error the device reported outside any call (a validation error, a lost device): the view stops.
    static DEVICE_ERROR: RefCell<Option<String>> = const { RefCell::new(None) };
    /// Frames submitted and not finished on the GPU: a new frame is drawn only when none is, so that a slow GPU
    /// (SwiftShader) does not queue frames and the page's loop (network, expansion, map) keeps its pace.
    static IN_FLIGHT: std::cell::Cell<u32> = const { std::cell::Cell::new(0) };
}

/// A renderer drawing on the canvas.
struct Drawing {
    gpu: Gpu,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    renderer: Renderer,
    canvas: HtmlCanvasElement,
    adapter: String,
    /// The backing store's size over the canvas's CSS size.
    scale: f64,
}

/// Where the GPU set-up is.
enum Setup {
    /// Waiting for the adapter and the device.
    Starting,
    /// Drawing.
    Ready(Box<Drawing>),
    /// No 3D view, and why.
    Failed(String),
}

/// See the module docs.
pub(super) struct View {
    setup: Rc<RefCell<Setup>>,
    scene: Option<Arc<Scene>>,
    /// What the scene was built from: bytes read, cells expanded, cells held, instances held, the summary nodes'
    /// generation.
    built_from: (u64, u64, usize, usize, u64),
    built_at: f64,
    generation: u64,
    stats: FrameStats,
    /// Milliseconds the last frame spent in the renderer (jobs, update, encoding).
    spent_ms: f64,
    /// Frames submitted.
    frames: u64,
}

impl View {
    /// Find `#view` and start setting up the GPU on it; a view that says why where there is no canvas.
    pub(super) fn start() -> View {
        let setup = Rc::new(RefCell::new(Setup::Starting));
        let canvas: Option<HtmlCanvasElement> = web_sys::window()
            .and_then(|w| w.document())
            .and_then(|d| d.get_element_by_id("view"))
            .and_then(|e| e.dyn_into().ok());
        match canvas {
            None => *setup.borrow_mut() = Setup::Failed("the page has no #view canvas".into()),
            Some(canvas) => {
                let slot = Rc::clone(&setup);
                wasm_bindgen_futures::spawn_local(async move {
                    let done = match set_up(canvas).await {
                        Ok(d) => {
                            set_body_class("gpu", true);
                            Setup::Ready(Box::new(d))
                        }
                        Err(e) => Setup::Failed(e),
                    };
                    *slot.borrow_mut() = done;
                });
            }
        }
        View {
            setup,
            scene: None,
            built_from: (0, 0, 0, 0, 0),
            built_at: f64::NEG_INFINITY,
            generation: 0,
            stats: FrameStats::default(),
            spent_ms: 0.0,
            frames: 0,
        }
    }

    /// `"webgpu: <adapter>"`, `"none: <reason>"`, or `"starting"` while the adapter is asked for.
    pub(super) fn describe(&self) -> String {
        match &*self.setup.borrow() {
            Setup::Starting => "starting".into(),
            Setup::Ready(d) => format!("webgpu: {}", d.adapter),
            Setup::Failed(why) => format!("none: {why}"),
        }
    }

    /// Run the renderer's queued jobs while `more()` says so, between frames (the page's timer); how many ran.
    pub(super) fn run_jobs(&mut self, more: &mut dyn FnMut() -> bool) -> usize {
        match &mut *self.setup.borrow_mut() {
            Setup::Ready(d) => d.renderer.run_jobs(more),
            _ => 0,
        }
    }

    /// Frames submitted so far.
    pub(super) fn frames(&self) -> u64 {
        self.frames
    }

    /// The renderer's jobs waiting at the last frame.
    pub(super) fn jobs(&self) -> usize {
        self.stats.jobs
    }

    /// Whether the last frame drew everything in view at its wanted level: no job queued or running, no geometry
    /// waiting for its upload, the far field's tiles made (what `Offscreen::settle` waits for natively).
    pub(super) fn settled(&self) -> bool {
        self.frames > 0 && self.stats.settled()
    }

    /// The HUD's line about the 3D view.
    pub(super) fn hud(&self) -> String {
        let s = &self.stats;
        match &*self.setup.borrow() {
            Setup::Ready(_) => format!(
                "renderer: {}   {:.1} ms   near {} mid {} far {} (in view {})   jobs {}   M: map",
                self.describe(),
                self.spent_ms,
                s.near,
                s.mid,
                s.far,
                s.in_view,
                s.jobs,
            ),
            _ => format!("renderer: {}", self.describe()),
        }
    }

    /// Draw a frame at `t` (milliseconds, `dt` since the last) from `camera` of what `session` holds.
    pub(super) fn frame(&mut self, session: &Session, camera: &Camera, t: f64, dt: f64) {
        if let Some(e) = DEVICE_ERROR.with(|d| d.borrow_mut().take()) {
            set_body_class("gpu", false);
            *self.setup.borrow_mut() = Setup::Failed(format!("the device reported: {e}"));
        }
        if !matches!(&*self.setup.borrow(), Setup::Ready(_)) {
            return;
        }
        let started = now();
        self.rebuild_scene(session, t);
        let setup = Rc::clone(&self.setup);
        let mut setup = setup.borrow_mut();
        let Setup::Ready(d) = &mut *setup else { return };
        d.fit_canvas();
        // At least one job a frame while any waits, then while the budget lasts.
        let deadline = started + JOB_BUDGET_MS;
        let mut first = true;
        d.renderer.run_jobs(&mut || std::mem::take(&mut first) || now() < deadline);
        if IN_FLIGHT.with(std::cell::Cell::get) > 0 {
            self.spent_ms = now() - started;
            return;
        }
        let cam = RenderCamera {
            position: glam::Vec3::from(camera.position),
            yaw: camera.yaw,
            pitch: camera.pitch,
            fov_y: FOV_Y,
        };
        // The wind blows by the page's clock.
        d.renderer.set_time((t / 1e3) as f32);
        match &self.scene {
            Some(scene) => self.stats = d.renderer.update(scene, &cam, (dt / 1e3).min(0.25) as f32),
            None => d.renderer.update_view(&cam),
        }
        match d.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(frame) | wgpu::CurrentSurfaceTexture::Suboptimal(frame) => {
                let view = frame.texture.create_view(&wgpu::TextureViewDescriptor::default());
                d.renderer.render(&view);
                IN_FLIGHT.with(|n| n.set(n.get() + 1));
                self.frames += 1;
                d.gpu.queue.on_submitted_work_done(|| IN_FLIGHT.with(|n| n.set(n.get().saturating_sub(1))));
                d.gpu.queue.present(frame);
            }
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                d.surface.configure(&d.gpu.device, &d.config);
            }
            _ => {}
        }
        self.spent_ms = now() - started;
    }

    /// Build the scene again from the session when what it holds changed, at most every [`SCENE_INTERVAL_MS`].
    fn rebuild_scene(&mut self, session: &Session, t: f64) {
        let (Some(ground), Some(welcome)) = (session.ground(), session.welcome()) else { return };
        let state = session.state();
        let from = (
            session.bytes_in(),
            session.expanded(),
            state.cells().len(),
            state.record_count(),
            state.summaries_generation(),
        );
        if (self.scene.is_some() && from == self.built_from) || t - self.built_at < SCENE_INTERVAL_MS {
            return;
        }
        self.generation += 1;
        let species = (0..welcome.species.len()).map(|id| state.species(id as u8).cloned()).collect::<Vec<_>>();
        let height = |x: f32, z: f32| ground.height(x, z);
        let mut instances: Vec<SceneInstance> = state
            .instances(&height)
            .map(|v| SceneInstance {
                id: v.id,
                species: u16::from(v.species),
                position: v.position,
                seed: v.seed,
                params: v.params,
            })
            .collect();
        instances.sort_by_key(|i| i.id);
        let mut record_cells: Vec<CellCoord> =
            state.cells().iter().filter(|(_, h)| h.is_complete()).map(|(c, _)| *c).collect();
        record_cells.sort_unstable();
        self.scene = Some(Arc::new(Scene {
            volumes: vec![None; species.len()],
            species,
            instances,
            ground: ground.clone(),
            cover: session.cover().cloned(),
            generation: self.generation,
            far: SceneFar {
                nodes: state.summaries().values().cloned().collect(),
                cell_size: welcome.world.grid.cell_size,
                record_cells,
                generation: self.generation,
            },
        }));
        (self.built_from, self.built_at) = (from, t);
    }
}

impl Drawing {
    /// Size the canvas's backing store to its size on the page, and the surface and renderer with it.
    fn fit_canvas(&mut self) {
        let (w, h) = backing_size(&self.canvas, self.scale);
        if (w, h) == (self.config.width, self.config.height) {
            return;
        }
        self.canvas.set_width(w);
        self.canvas.set_height(h);
        (self.config.width, self.config.height) = (w, h);
        self.surface.configure(&self.gpu.device, &self.config);
        self.renderer.resize(w, h);
    }
}

/// The renderer's configuration in a page: the native walk's defaults, with one amplification "worker" (the page's
/// thread) and, on a CPU adapter, what the renderer picks for one natively (one sample a pixel, the far field as
/// boxes, trees culled whole on the CPU).
fn config(cpu: bool) -> RenderConfig {
    // Jobs queued a frame: the page's timer runs them between frames (`View::run_jobs`), which a slow GPU makes
    // far apart, so a frame queues as many as a pool of worker threads would take.
    let mut cfg = RenderConfig { workers: 1, max_jobs: PAGE_JOBS, ..RenderConfig::default() };
    if cpu {
        cfg.msaa = 1;
        cfg.far_path = FarPath::Raster;
        cfg.cull = CullPath::Cpu;
        // No sun shadows: drawing every caster into three maps in software doubled a frame there (a 150 m view of
        // the default world: 8.5 s → 4.3 s a frame on SwiftShader, docs/web.md).
        cfg.shadows.resolution = 0;
    }
    cfg
}

/// The backing store's size for `canvas` drawn at `scale` of its CSS size.
fn backing_size(canvas: &HtmlCanvasElement, scale: f64) -> (u32, u32) {
    let side = |css: i32| ((f64::from(css.max(1)) * scale).round() as u32).clamp(1, MAX_SIDE);
    (side(canvas.client_width()), side(canvas.client_height()))
}

/// The GPU, the surface on `canvas` and the renderer, or why not.
async fn set_up(canvas: HtmlCanvasElement) -> Result<Drawing, String> {
    let (gpu, surface) = Gpu::from_canvas(canvas.clone(), &config(false)).await.map_err(|e| match e {
        // Not the native advice (a Vulkan driver): what the browser said.
        canopy_render::GpuError::NoAdapter(why) => format!("no WebGPU adapter: {why}"),
        e => e.to_string(),
    })?;
    let info = gpu.adapter.get_info();
    let adapter = if info.name.is_empty() { "unnamed adapter".to_owned() } else { info.name.clone() };
    // SwiftShader is a CPU adapter even where the browser does not call it a fallback.
    let cpu = info.device_type == wgpu::DeviceType::Cpu || adapter.to_lowercase().contains("swiftshader");
    let cfg = config(cpu);
    cfg.validate().map_err(|e| e.to_string())?;
    gpu.device.on_uncaptured_error(Arc::new(|e: wgpu::Error| {
        let msg = e.to_string();
        web_sys::console::error_1(&JsValue::from_str(&format!("WebGPU: {msg}")));
        DEVICE_ERROR.with(|d| {
            d.borrow_mut().get_or_insert(msg);
        });
    }));
    let scale = if cpu { CPU_SCALE } else { 1.0 };
    let (w, h) = backing_size(&canvas, scale);
    canvas.set_width(w);
    canvas.set_height(h);
    let config =
        gpu.surface_config(&surface, (w, h), wgpu::PresentMode::AutoVsync).ok_or("the canvas supports no format")?;
    let format = config.format;
    surface.configure(&gpu.device, &config);
    let renderer = Renderer::new(&gpu.device, &gpu.queue, format, (w, h), cfg).map_err(|e| e.to_string())?;
    let adapter = format!("{adapter}{}", if cpu { " (CPU)" } else { "" });
    Ok(Drawing { gpu, surface, config, renderer, canvas, adapter, scale })
}

/// Set or clear a class of `<body>`.
fn set_body_class(class: &str, on: bool) {
    let Some(body) = web_sys::window().and_then(|w| w.document()).and_then(|d| d.body()) else { return };
    let list = body.class_list();
    let _ = if on { list.add_1(class) } else { list.remove_1(class) };
}

/// The 3D view's input: a press on it looks around as one on the map does (drag, or pointer lock); M toggles the
/// map between its corner and the whole page.
pub(super) fn listen(app: &Rc<RefCell<App>>) {
    let Some(window) = web_sys::window() else { return };
    let view = window.document().and_then(|d| d.get_element_by_id("view"));
    if let Some(view) = view {
        let app = Rc::clone(app);
        let target = view.clone();
        let cb = Closure::<dyn FnMut(web_sys::Event)>::new(move |_| {
            app.borrow_mut().dragging = true;
            target.request_pointer_lock();
        });
        let _ = view.add_event_listener_with_callback("mousedown", cb.as_ref().unchecked_ref());
        // The page lives as long as its listeners.
        cb.forget();
    }
    let cb = Closure::<dyn FnMut(web_sys::Event)>::new(move |e: web_sys::Event| {
        let Some(e) = e.dyn_ref::<web_sys::KeyboardEvent>() else { return };
        if e.code() == "KeyM" && !e.repeat() {
            let full = web_sys::window()
                .and_then(|w| w.document())
                .and_then(|d| d.body())
                .is_some_and(|b| b.class_list().contains("map-full"));
            set_body_class("map-full", !full);
        }
    });
    let _ = window.add_event_listener_with_callback("keydown", cb.as_ref().unchecked_ref());
    cb.forget();
}
