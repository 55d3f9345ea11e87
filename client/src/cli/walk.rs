//! `canopy walk`: the walkthrough window. A winit loop on the main thread drives the renderer (fly or walk camera,
//! mouse look, WASD); a network thread runs the client library against a `canopy-server`, sends the viewpoint as
//! it moves and publishes scene snapshots (species, instances, terrain) that the renderer picks up without ever
//! waiting. The title shows fps, bytes received, instances held, species cached and counts per LOD band.
//!
//! Without `--server` it starts canopy-server in this process on the embedded default world (or `--world FILE`)
//! and connects to it, so `canopy walk` alone opens a walkthrough of the default world. That server takes edits
//! (kept in memory, or in `--data DIR`) from the walker alone, through a random token made for the session.
//!
//! Keys: W/A/S/D move, Space/C (or E/Q) up and down in fly mode, Shift ×4, mouse wheel or +/− change speed,
//! Tab switches fly/walk, a click captures the mouse for looking around (arrow keys look too), Esc releases it
//! and quits when it is free. As an editor (`--token`, or the in-process server): P plants the selected species
//! where the crosshair (the screen centre) meets the ground, F fells the instance nearest that point within a
//! few metres, `[`/`]` select the species (`walk_edit.rs`). Every change to a held cell, the walker's or another
//! editor's, republishes the scene at once, so edits show without moving.

use std::collections::HashSet;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use canopy_client::cache::{CacheLimits, SpeciesCache};
use canopy_client::fit::LinkFit;
use canopy_client::net::Edges;
use canopy_client::state::Event;
use canopy_client::{ConnectConfig, Connection, Trust};
use canopy_harness::bots::{DriveHooks, DrivePlan, Mover, drive};
use canopy_protocol::CellCoord;
use canopy_protocol::aoi::Viewpoint;
use canopy_protocol::edit::EditOp;
use canopy_protocol::summary::FarView;
use canopy_protocol::sync::Locked;
use canopy_render::camera::{Camera, CameraSpec};
use canopy_render::{FrameStats, Gpu, RenderConfig, Renderer, Scene, SceneFar, SceneInstance};
use canopy_worlds::world::{Ground, GroundCover};
use clap::Args;
use glam::Vec3;
use winit::application::ApplicationHandler;
use winit::event::{DeviceEvent, DeviceId, ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{CursorGrabMode, Window, WindowId};

use super::render::{RendererArgs, camera_spec};

use super::walk_edit::{EditKeys, EditLink};

/// Options of `canopy walk`.
#[derive(Args, Debug)]
pub(super) struct WalkArgs {
    /// Where to walk (without `--server`: canopy-server in this process on `--world`, or on the embedded default
    /// world).
    #[command(flatten)]
    pub(super) connect: super::ConnectArgs,
    /// World manifest for the in-process server (only without `--server`).
    #[arg(long, conflicts_with = "server")]
    world: Option<PathBuf>,
    /// With `--server`: the editor token (64 hexadecimal digits, as `canopy-server --add-editor` printed it), which
    /// turns on the editing keys; also read from `CANOPY_TOKEN`. The in-process server needs none: it makes the
    /// walker an editor itself.
    #[arg(long, env = "CANOPY_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Keep the in-process server's edits in DIR/edits.sqlite (default: in memory, gone when the window closes).
    #[arg(long, alias = "data", value_name = "DIR", conflicts_with = "server")]
    data_dir: Option<PathBuf>,
    /// Area-of-interest radius to ask for, metres (the server caps it).
    #[arg(long, default_value_t = 600.0)]
    radius: f32,
    /// The link's rate (bits a second: `1M`, `500k`): while moving, ask for the radius it carries at the camera's
    /// speed over the records around it, at most `--radius` (default: always `--radius`).
    #[arg(long, value_parser = super::bots::parse_link)]
    link: Option<u64>,
    /// Starting camera: a file, or statements inline (default: the default view of `canopy render`).
    #[arg(long)]
    camera: Option<String>,
    /// Window width.
    #[arg(long, default_value_t = 1280)]
    width: u32,
    /// Window height.
    #[arg(long, default_value_t = 720)]
    height: u32,
    /// Starting speed, metres per second.
    #[arg(long, default_value_t = 15.0)]
    speed: f32,
    /// Start in walk mode (eyes 1.7 m above the ground) instead of flying.
    #[arg(long)]
    walk: bool,
    /// Move forward on its own (demos and tests).
    #[arg(long)]
    autopilot: bool,
    /// Turn at this many degrees per second on autopilot.
    #[arg(long, default_value_t = 6.0)]
    autopilot_turn: f32,
    /// Close after this many seconds (0: when the window is closed).
    #[arg(long, default_value_t = 0.0)]
    pub(super) exit_after: f64,
    /// Present without waiting for vertical sync (for measuring frame rates).
    #[arg(long)]
    no_vsync: bool,
    #[command(flatten)]
    far: super::far::FarArgs,
    /// Species cache directory (default: none).
    #[arg(long)]
    cache_dir: Option<PathBuf>,
    #[command(flatten)]
    renderer: RendererArgs,
}

/// Where the camera is, for the network thread's viewpoint updates.
#[derive(Clone, Copy, Debug, Default)]
struct Pose {
    position: [f32; 2],
    yaw: f32,
    velocity: [f32; 2],
    /// Height of the eye above the ground under it (the far view's altitude).
    altitude: f32,
}

/// What the network thread reports.
#[derive(Clone, Debug, Default)]
struct NetStatus {
    connected: bool,
    world: String,
    bytes_received: u64,
    records: usize,
    species_held: usize,
    species_total: usize,
    complete: bool,
    error: Option<String>,
    /// The last edit sent or answered (or why a key did nothing).
    edit: Option<String>,
}

#[derive(Default)]
struct Shared {
    pose: Mutex<Pose>,
    scene: Mutex<Option<Arc<Scene>>>,
    status: Mutex<NetStatus>,
    /// Set when the window has closed: the network thread's walk ends.
    stop: tokio::sync::watch::Sender<bool>,
}

/// The scene of what the connection holds now, on `ground`, its colours from `cover`.
fn snapshot(conn: &Connection, ground: &Ground, cover: Option<&Arc<GroundCover>>, generation: u64) -> Scene {
    let state = conn.state();
    let welcome = conn.welcome();
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
    Scene {
        volumes: vec![None; species.len()],
        species,
        instances,
        ground: ground.clone(),
        cover: cover.cloned(),
        generation,
        far: SceneFar {
            nodes: state.summaries().values().cloned().collect(),
            cell_size: welcome.world.grid.cell_size,
            record_cells,
            generation,
        },
    }
}

/// How the network thread streams: the harness's walk loop at the window's pace, until the window closes (`stop`),
/// asking for `radius` metres (fitted to the link with `fit`) and the far view `far`.
fn window_plan(
    radius: f32,
    fit: Option<LinkFit>,
    far: Option<FarView>,
    stop: &tokio::sync::watch::Sender<bool>,
) -> DrivePlan {
    DrivePlan {
        radius,
        tick: Duration::from_millis(100),
        walk_until: Instant::now() + Duration::from_secs(100 * 365 * 86_400),
        settle: Duration::ZERO,
        sample: Some(Duration::from_millis(100)),
        stop: stop.subscribe(),
        far,
        fit,
    }
}

async fn net_session(
    cfg: ConnectConfig,
    plan: DrivePlan,
    cache: Option<Arc<SpeciesCache>>,
    shared: Arc<Shared>,
    mut edits: Option<EditLink>,
) -> anyhow::Result<()> {
    let bind: SocketAddr = if cfg.server.is_ipv6() { "[::]:0".parse()? } else { "0.0.0.0:0".parse()? };
    let endpoint = canopy_client::net::endpoint(bind)?;
    let start = *shared.pose.locked();
    let mut conn = Connection::connect_any(&endpoint, &cfg, cache, |_| Viewpoint {
        seq: 0,
        position: start.position,
        yaw: start.yaw,
        velocity: [0.0, 0.0],
        radius: plan.radius,
    })
    .await
    .with_context(|| format!("connecting to {}", cfg.server))?;
    if edits.is_some() {
        // An editor picks from the whole species table, not only the species of the trees around it.
        conn.fetch_all_species(cfg.timeout).await.context("fetching the species table")?;
    }
    let welcome = Arc::clone(conn.welcome());
    let ground = canopy_client::world::ground(&welcome.world.terrain).context("rebuilding the terrain")?;
    {
        let mut s = shared.status.locked();
        s.connected = true;
        s.world = welcome.world.name.clone();
        s.species_total = welcome.species.len();
    }
    let mut hooks = WindowHooks {
        shared: &shared,
        ground: &ground,
        edits: edits.as_mut(),
        cover: None,
        asked: None,
        generation: 1,
        dirty: false,
        changed: false,
        last_publish: Instant::now(),
    };
    *shared.scene.locked() = Some(Arc::new(snapshot(&conn, &ground, None, hooks.generation)));
    let mut camera = CameraMover { shared: &shared, pose: start };
    loop {
        match drive(&mut conn, &mut camera, plan.clone(), &mut hooks).await {
            // The edge is gone: resume on another with what this session held, at the camera's pose now.
            Err(e) if cfg.edges.len() > 1 && e.edge_lost() => {
                let lost = conn.server();
                camera.step(0.0);
                let vp = camera.viewpoint(plan.radius);
                shared.status.locked().edit = Some(format!("edge {lost} lost ({e}); failing over"));
                conn = conn.fail_over(&endpoint, &cfg, vp).await.context("failing over to another edge")?;
                let line = format!("edge {lost} lost; resumed on {}", conn.server());
                println!("{line}");
                shared.status.locked().edit = Some(line);
            }
            r => break r.map(drop)?,
        }
    }
    conn.close();
    endpoint.wait_idle().await;
    Ok(())
}

/// The window's camera as the harness's [`Mover`]: where the render thread last put it, read at each step.
struct CameraMover<'a> {
    shared: &'a Shared,
    pose: Pose,
}

impl Mover for CameraMover<'_> {
    /// Read the camera's pose now (it never jumps: a teleport is a move `viewpoint_due` sees).
    fn step(&mut self, _dt: f32) -> bool {
        self.pose = *self.shared.pose.locked();
        false
    }
    fn position(&self) -> [f32; 2] {
        self.pose.position
    }
    fn yaw(&self) -> f32 {
        self.pose.yaw
    }
    fn velocity(&self) -> [f32; 2] {
        self.pose.velocity
    }
    fn altitude(&self) -> f32 {
        self.pose.altitude
    }
}

/// What the window does along the harness's [`drive`]: publish scene snapshots and the status, send the editor's
/// keys as edits and show their answers.
struct WindowHooks<'a> {
    shared: &'a Shared,
    ground: &'a Ground,
    edits: Option<&'a mut EditLink>,
    /// The ground's cover, once the world is built from its function (one `Arc`: the renderer colours the terrain
    /// again only when it changes).
    cover: Option<Arc<GroundCover>>,
    /// What the edit being sent is, until its request number is known.
    asked: Option<String>,
    generation: u64,
    /// Events applied since the last snapshot.
    dirty: bool,
    /// A held cell changed (an edit) since the last snapshot: shown at once, not after the 250 ms of batches.
    changed: bool,
    last_publish: Instant,
}

impl WindowHooks<'_> {
    /// Publish a snapshot when something arrived: at once for a changed cell, batches and releases at most every
    /// 250 ms; and the status.
    fn publish(&mut self, conn: &Connection) {
        if self.cover.is_none()
            && let Some(world) = conn.world()
        {
            self.cover = Some(Arc::new(GroundCover::of_world(world)));
            self.dirty = true;
        }
        if self.dirty && (self.changed || self.last_publish.elapsed() > Duration::from_millis(250)) {
            self.generation += 1;
            let scene = snapshot(conn, self.ground, self.cover.as_ref(), self.generation);
            *self.shared.scene.locked() = Some(Arc::new(scene));
            (self.dirty, self.changed) = (false, false);
            self.last_publish = Instant::now();
        }
        let mut s = self.shared.status.locked();
        s.bytes_received = conn.bytes_received();
        s.records = conn.state().record_count();
        s.species_held = conn.state().species_held();
        s.complete = conn.state().is_complete();
    }
}

impl DriveHooks<CameraMover<'_>> for WindowHooks<'_> {
    fn event(&mut self, ev: &Event) {
        self.changed |= matches!(ev, Event::Changed { .. });
        self.dirty = true;
        if let Some(line) = self.edits.as_mut().and_then(|l| l.answer(ev)) {
            println!("{line}");
            self.shared.status.locked().edit = Some(line);
        }
    }
    fn changed(&mut self, conn: &Connection) {
        self.publish(conn);
    }
    fn sample(&mut self, conn: &Connection, _camera: &CameraMover<'_>, _settling: bool) {
        self.publish(conn);
    }
    fn edit_every(&self) -> Option<Duration> {
        // A key's edit waits at most this long for the network thread.
        self.edits.is_some().then_some(Duration::from_millis(20))
    }
    fn edit(&mut self, _now: Instant, _conn: &Connection, _camera: &CameraMover<'_>) -> Option<EditOp> {
        let req = self.edits.as_mut()?.try_next()?;
        self.asked = Some(req.what);
        Some(req.op)
    }
    fn edit_sent(&mut self, request: u32, _op: &EditOp, _at: Instant) {
        if let (Some(link), Some(what)) = (self.edits.as_mut(), self.asked.take()) {
            link.sent(request, what);
        }
    }
}

fn net_thread(
    cfg: ConnectConfig,
    plan: DrivePlan,
    cache: Option<Arc<SpeciesCache>>,
    shared: Arc<Shared>,
    edits: Option<EditLink>,
) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
            Ok(rt) => rt,
            Err(e) => {
                shared.status.locked().error = Some(format!("tokio runtime: {e}"));
                return;
            }
        };
        if let Err(e) = rt.block_on(net_session(cfg, plan, cache, Arc::clone(&shared), edits)) {
            shared.status.locked().error = Some(format!("{e:#}"));
        }
    })
}

struct Graphics {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    gpu: Gpu,
    renderer: Renderer,
}

struct App {
    args: WalkArgs,
    cfg: RenderConfig,
    spec: CameraSpec,
    shared: Arc<Shared>,
    gfx: Option<Graphics>,
    error: Option<anyhow::Error>,
    camera: Camera,
    camera_placed: bool,
    scene: Option<Arc<Scene>>,
    keys: HashSet<KeyCode>,
    grabbed: bool,
    walking: bool,
    speed: f32,
    started: Instant,
    last_frame: Instant,
    frames: u64,
    window_frames: (Instant, u64),
    fps: f64,
    last_title: Instant,
    last_print: Instant,
    stats: FrameStats,
    /// The editing keys, for an editor.
    edit: Option<EditKeys>,
}

impl App {
    fn init(&mut self, event_loop: &ActiveEventLoop) -> anyhow::Result<()> {
        let attrs = Window::default_attributes()
            .with_title("Canopy")
            .with_inner_size(winit::dpi::PhysicalSize::new(self.args.width, self.args.height));
        let window = Arc::new(event_loop.create_window(attrs).context("opening the window")?);
        let instance = Gpu::instance();
        let surface = instance.create_surface(Arc::clone(&window)).context("creating the window surface")?;
        let gpu = Gpu::with_instance(instance, Some(&surface), &self.cfg)?;
        let size = window.inner_size();
        let present = if self.args.no_vsync { wgpu::PresentMode::AutoNoVsync } else { wgpu::PresentMode::AutoVsync };
        let config = gpu
            .surface_config(&surface, (size.width, size.height), present)
            .context("the surface supports no format")?;
        let format = config.format;
        surface.configure(&gpu.device, &config);
        let renderer = Renderer::new(&gpu.device, &gpu.queue, format, (config.width, config.height), self.cfg.clone())?;
        println!("adapter: {}; surface {:?} {}×{}", gpu.describe(), format, config.width, config.height);
        self.gfx = Some(Graphics { window, surface, config, gpu, renderer });
        Ok(())
    }

    fn move_camera(&mut self, dt: f32) {
        let key = |k: KeyCode| self.keys.contains(&k);
        let look = 1.2 * dt;
        let turn = |a: bool, b: bool| f32::from(u8::from(a)) - f32::from(u8::from(b));
        self.camera.turn(
            look * turn(key(KeyCode::ArrowRight), key(KeyCode::ArrowLeft)),
            look * turn(key(KeyCode::ArrowUp), key(KeyCode::ArrowDown)),
        );
        let mut speed = self.speed;
        if key(KeyCode::ShiftLeft) || key(KeyCode::ShiftRight) {
            speed *= 4.0;
        }
        let mut forward = self.camera.forward();
        if self.walking {
            forward.y = 0.0;
            forward = forward.normalize_or(Vec3::Z);
        }
        let right = self.camera.right();
        let mut v = Vec3::ZERO;
        v += forward * turn(key(KeyCode::KeyW), key(KeyCode::KeyS));
        v += right * turn(key(KeyCode::KeyD), key(KeyCode::KeyA));
        if !self.walking {
            v += Vec3::Y * turn(key(KeyCode::Space) || key(KeyCode::KeyE), key(KeyCode::KeyC) || key(KeyCode::KeyQ));
        }
        if self.args.autopilot {
            v += forward;
            self.camera.turn(self.args.autopilot_turn.to_radians() * dt, 0.0);
        }
        let v = v.normalize_or_zero() * speed;
        self.camera.position += v * dt;
        if let Some(scene) = &self.scene {
            let ground = scene.ground.height(self.camera.position.x, self.camera.position.z);
            if self.walking {
                self.camera.position.y = ground + 1.7;
            } else {
                self.camera.position.y = self.camera.position.y.max(ground + 0.5);
            }
        }
        let altitude = match &self.scene {
            Some(scene) => self.camera.position.y - scene.ground.height(self.camera.position.x, self.camera.position.z),
            None => self.camera.position.y,
        };
        *self.shared.pose.locked() = Pose {
            position: [self.camera.position.x, self.camera.position.z],
            yaw: self.camera.yaw,
            velocity: [v.x, v.z],
            altitude,
        };
    }

    fn status_line(&self) -> String {
        let s = self.shared.status.locked().clone();
        let st = &self.stats;
        let net = match (&s.error, s.connected) {
            (Some(e), _) => format!("network error: {e}"),
            (None, false) => "connecting…".into(),
            (None, true) => format!(
                "{}: {:.2} MB received | {} instances held{} | species {}/{} cached",
                s.world,
                s.bytes_received as f64 / 1e6,
                s.records,
                if s.complete { "" } else { " (loading)" },
                s.species_held,
                s.species_total,
            ),
        };
        let edit = match &self.edit {
            Some(keys) => {
                let last = s.edit.as_deref().map(|l| format!(" | {l}")).unwrap_or_default();
                format!(" | {}{last}", keys.hud(&self.camera, self.scene.as_deref()))
            }
            None => String::new(),
        };
        format!(
            "Canopy — {:.0} fps | {net} | near {} mid {} far {} (in view {}) | {:.0} m/s {}{edit}",
            self.fps,
            st.near,
            st.mid,
            st.far,
            st.in_view,
            self.speed,
            if self.walking { "walk" } else { "fly" },
        )
    }

    fn edit_key(&mut self, code: KeyCode) {
        let Some(keys) = self.edit.as_mut() else { return };
        if let Some(line) = keys.key(code, &self.camera, self.scene.as_deref()) {
            println!("{line}");
            self.shared.status.locked().edit = Some(line);
            // Show it now rather than at the next title update.
            self.last_title = self.last_title.checked_sub(Duration::from_secs(1)).unwrap_or(self.last_title);
        }
    }

    fn frame(&mut self, event_loop: &ActiveEventLoop) {
        let now = Instant::now();
        let dt = now.duration_since(self.last_frame).as_secs_f32().min(0.25);
        self.last_frame = now;
        if let Ok(mut g) = self.shared.scene.try_lock()
            && let Some(s) = g.take()
        {
            self.scene = Some(s);
        }
        if let (false, Some(scene)) = (self.camera_placed, &self.scene) {
            let g = scene.ground.clone();
            self.camera = self.spec.resolve(&|x, z| g.height(x, z));
            self.camera_placed = true;
        }
        self.move_camera(dt);
        let Some(gfx) = self.gfx.as_mut() else { return };
        // The wind blows by the wall clock.
        gfx.renderer.set_time(now.duration_since(self.started).as_secs_f32());
        if let Some(scene) = &self.scene {
            self.stats = gfx.renderer.update(scene, &self.camera, dt);
        } else {
            gfx.renderer.update_view(&self.camera);
        }
        match gfx.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(frame) | wgpu::CurrentSurfaceTexture::Suboptimal(frame) => {
                let view = frame.texture.create_view(&wgpu::TextureViewDescriptor::default());
                gfx.renderer.render(&view);
                gfx.window.pre_present_notify();
                gfx.gpu.queue.present(frame);
                self.frames += 1;
            }
            wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {}
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                gfx.surface.configure(&gfx.gpu.device, &gfx.config);
            }
            wgpu::CurrentSurfaceTexture::Validation => {
                self.error = Some(anyhow::anyhow!("the surface reported a validation error"));
                event_loop.exit();
            }
        }
        let (t0, f0) = self.window_frames;
        if t0.elapsed() >= Duration::from_millis(500) {
            self.fps = (self.frames - f0) as f64 / t0.elapsed().as_secs_f64();
            self.window_frames = (Instant::now(), self.frames);
        }
        if self.last_title.elapsed() >= Duration::from_millis(500) {
            let line = self.status_line();
            if let Some(gfx) = &self.gfx {
                gfx.window.set_title(&line);
            }
            self.last_title = Instant::now();
            if self.last_print.elapsed() >= Duration::from_secs(2) {
                println!("{:6.1}s  {line}", self.started.elapsed().as_secs_f64());
                self.last_print = Instant::now();
            }
        }
        if self.args.exit_after > 0.0 && self.started.elapsed().as_secs_f64() >= self.args.exit_after {
            event_loop.exit();
        }
    }

    fn set_grab(&mut self, grab: bool) {
        let Some(gfx) = &self.gfx else { return };
        if grab {
            let ok = gfx
                .window
                .set_cursor_grab(CursorGrabMode::Locked)
                .or_else(|_| gfx.window.set_cursor_grab(CursorGrabMode::Confined));
            if ok.is_err() {
                return;
            }
        } else {
            let _ = gfx.window.set_cursor_grab(CursorGrabMode::None);
        }
        gfx.window.set_cursor_visible(!grab);
        self.grabbed = grab;
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gfx.is_some() {
            return;
        }
        if let Err(e) = self.init(event_loop) {
            self.error = Some(e);
            event_loop.exit();
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                if let Some(gfx) = self.gfx.as_mut() {
                    gfx.config.width = size.width.max(1);
                    gfx.config.height = size.height.max(1);
                    gfx.surface.configure(&gfx.gpu.device, &gfx.config);
                    gfx.renderer.resize(gfx.config.width, gfx.config.height);
                }
            }
            WindowEvent::KeyboardInput { event, is_synthetic, .. } => {
                let PhysicalKey::Code(code) = event.physical_key else { return };
                match event.state {
                    ElementState::Pressed => {
                        self.keys.insert(code);
                        match code {
                            KeyCode::Escape if self.grabbed => self.set_grab(false),
                            KeyCode::Escape => event_loop.exit(),
                            // A focused window gets presses of the keys held meanwhile (`is_synthetic`): they move,
                            // but do not toggle or edit again.
                            KeyCode::Tab if !event.repeat && !is_synthetic => self.walking = !self.walking,
                            KeyCode::Equal | KeyCode::NumpadAdd => self.speed = (self.speed * 1.25).min(2000.0),
                            KeyCode::Minus | KeyCode::NumpadSubtract => self.speed = (self.speed / 1.25).max(0.5),
                            k if EditKeys::handles(k) && !event.repeat && !is_synthetic => self.edit_key(k),
                            _ => {}
                        }
                    }
                    ElementState::Released => {
                        self.keys.remove(&code);
                    }
                }
            }
            WindowEvent::MouseInput { state: ElementState::Pressed, button: MouseButton::Left, .. } => {
                self.set_grab(true)
            }
            WindowEvent::MouseWheel { delta, .. } => {
                let steps = match delta {
                    MouseScrollDelta::LineDelta(_, y) => y,
                    MouseScrollDelta::PixelDelta(p) => (p.y / 40.0) as f32,
                };
                self.speed = (self.speed * 1.25f32.powf(steps)).clamp(0.5, 2000.0);
            }
            WindowEvent::Focused(false) => self.keys.clear(),
            WindowEvent::RedrawRequested => self.frame(event_loop),
            _ => {}
        }
    }

    fn device_event(&mut self, _event_loop: &ActiveEventLoop, _id: DeviceId, event: DeviceEvent) {
        if let (true, DeviceEvent::MouseMotion { delta }) = (self.grabbed, event) {
            self.camera.turn(delta.0 as f32 * 0.0025, -delta.1 as f32 * 0.0025);
        }
    }

    fn about_to_wait(&mut self, _event_loop: &ActiveEventLoop) {
        if let Some(gfx) = &self.gfx {
            gfx.window.request_redraw();
        }
    }
}

/// A canopy-server in this process, for `canopy walk` without `--server`: it takes edits from the walker alone.
struct LocalServer {
    runtime: tokio::runtime::Runtime,
    server: canopy_server::Served,
    /// The walker's editor token, made for this session.
    token: Vec<u8>,
}

fn local_server(world: Option<&PathBuf>, data_dir: Option<&PathBuf>) -> anyhow::Result<LocalServer> {
    use canopy_server::session::{Editors, editor_line, new_token};
    use canopy_server::{Edits, ServeOptions, ServerConfig, serve};
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    let world = super::load_world(world.map(PathBuf::as_path)).map_err(|d| anyhow::anyhow!("{d}"))?;
    let (name, eager) = (world.name.clone(), world.instances.len());
    let token = new_token().context("making the walker's editor token")?.to_vec();
    let walker = Editors::parse("canopy walk", &editor_line("walker", &token, None, None))?;
    let mut opts = ServeOptions {
        server: ServerConfig { listen: SocketAddr::from(([127, 0, 0, 1], 0)), ..Default::default() },
        // Edits as canopy-server keeps them (`--data DIR`: the same `edits.sqlite`), or in memory for this session.
        edits: data_dir.map_or(Edits::Memory, |dir| Edits::Sqlite(dir.clone())),
        ..ServeOptions::default()
    };
    opts.server.session.editors = Some(Arc::new(walker));
    // A world expanded at load is served whole; a large one (the highlands) cell by cell on demand (`Cells::Auto`).
    let server = runtime.block_on(serve(world, opts))?;
    println!(
        "canopy-server (in-process) on {} serving {name}: {eager} instances at load; {} edits kept in {}",
        server.local_addr(),
        server.edit_count(),
        server.edits_at()
    );
    Ok(LocalServer { runtime, server, token })
}

/// Run `canopy walk`.
pub(super) fn run(args: WalkArgs) -> anyhow::Result<ExitCode> {
    let spec = camera_spec(args.camera.as_deref())?;
    let cfg = args.renderer.config()?;
    let local = match &args.connect.server {
        Some(_) => None,
        None if args.connect.trust_given() => bail!("--cert-fingerprint and --insecure name the trust of a --server"),
        None => Some(local_server(args.world.as_ref(), args.data_dir.as_ref())?),
    };
    let token = match (&local, &args.token) {
        (Some(l), _) => Some(l.token.clone()),
        (None, Some(t)) => Some(
            canopy_server::session::unhex(t.trim())
                .filter(|t| !t.is_empty())
                .context("--token: expected hexadecimal digits")?,
        ),
        (None, None) => None,
    };
    let (server, trust) = match &local {
        Some(l) => (Edges::one(l.server.local_addr()), {
            let fingerprint =
                if args.connect.web_transport { l.server.web_fingerprint() } else { l.server.fingerprint().to_owned() };
            Trust::pinned(&fingerprint).context("the in-process server's fingerprint")?
        }),
        None => (args.connect.edges(), args.connect.trust()?),
    };
    if !(args.radius.is_finite() && args.radius > 0.0 && args.speed.is_finite() && args.speed > 0.0) {
        bail!("--radius and --speed must be positive");
    }
    if !(0.0..=1e6).contains(&args.exit_after) {
        bail!("--exit-after must be between 0 and 1e6 seconds");
    }
    let cache = match &args.cache_dir {
        Some(dir) => Some(Arc::new(
            SpeciesCache::open(dir, CacheLimits::default())
                .with_context(|| format!("species cache {}", dir.display()))?,
        )),
        None => None,
    };
    let shared = Arc::new(Shared::default());
    let camera = spec.resolve(&|_, _| 0.0);
    *shared.pose.locked() = Pose {
        position: [camera.position.x, camera.position.z],
        yaw: camera.yaw,
        velocity: [0.0; 2],
        altitude: camera.position.y,
    };
    let far = args.far.view(args.height, camera.fov_y, camera.position.y)?;
    let mut connect = args.connect.config(&server, trust);
    connect.client_name = "canopy walk".into();
    connect.expander = args.connect.expander();
    // An editor's keys send their edits through the network thread, which sends them on the connection.
    let (edit_keys, edit_link) = match &token {
        Some(_) => {
            let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
            (Some(EditKeys::new(tx)), Some(EditLink::new(rx)))
        }
        None => (None, None),
    };
    connect.token = token;
    let fit = args.link.map(|rate| LinkFit { link_bits: rate as f64 });
    let plan = window_plan(args.radius, fit, far, &shared.stop);
    let net = net_thread(connect, plan, cache, Arc::clone(&shared), edit_link);
    let event_loop = EventLoop::new().context("opening the display (is DISPLAY or WAYLAND_DISPLAY set?)")?;
    event_loop.set_control_flow(ControlFlow::Poll);
    let now = Instant::now();
    let mut app = App {
        walking: args.walk,
        speed: args.speed,
        args,
        cfg,
        spec,
        shared: Arc::clone(&shared),
        gfx: None,
        error: None,
        camera,
        camera_placed: false,
        scene: None,
        keys: HashSet::new(),
        grabbed: false,
        started: now,
        last_frame: now,
        frames: 0,
        window_frames: (now, 0),
        fps: 0.0,
        last_title: now,
        last_print: now,
        stats: FrameStats::default(),
        edit: edit_keys,
    };
    let ran = event_loop.run_app(&mut app);
    shared.stop.send_replace(true);
    let elapsed = app.started.elapsed().as_secs_f64();
    let status = shared.status.locked().clone();
    println!("{}", app.status_line());
    println!(
        "frames presented: {} in {:.1} s ({:.1} fps); instances held {}, species {}/{}, {} bytes received",
        app.frames,
        elapsed,
        app.frames as f64 / elapsed.max(1e-9),
        status.records,
        status.species_held,
        status.species_total,
        status.bytes_received
    );
    drop(app.gfx.take());
    let _ = net.join();
    if let Some(l) = local {
        l.runtime.block_on(l.server.shutdown(Duration::from_secs(1)));
    }
    ran.context("the window's event loop")?;
    if let Some(e) = app.error {
        return Err(e);
    }
    if let Some(e) = status.error {
        bail!("network: {e}");
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::walk_edit::EditRequest;

    /// The network thread without a window (the harness's `drive`, the camera its mover): it fills the camera's
    /// area of interest and the ground's cover into the published scene, and an editor key's edit goes out, its answer reaches the status
    /// line and its tree the next scene, shown without moving.
    #[test]
    fn the_network_thread_streams_the_camera_s_area_and_sends_the_keys_edits() {
        let local = local_server(None, None).expect("the in-process server on the default world");
        let shared = Arc::new(Shared::default());
        *shared.pose.locked() = Pose { position: [0.0, 0.0], yaw: 0.0, velocity: [0.0; 2], altitude: 2.0 };
        let mut connect =
            ConnectConfig::new(local.server.local_addr(), Trust::pinned(local.server.fingerprint()).unwrap());
        connect.token = Some(local.token.clone());
        // As `canopy walk` connects by default: expanding its cells from the world function.
        connect.expander = Some(canopy_client::expand::Expander::default_pool());
        let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
        let plan = window_plan(120.0, None, None, &shared.stop);
        let net = net_thread(connect, plan, None, Arc::clone(&shared), Some(EditLink::new(rx)));
        let wait = |what: &str, done: &dyn Fn(&Shared) -> bool| {
            let started = Instant::now();
            while !done(&shared) {
                let status = shared.status.locked().clone();
                assert!(status.error.is_none() && !net.is_finished(), "the network thread stopped: {status:?}");
                assert!(started.elapsed() < Duration::from_secs(120), "waited 120 s for {what}: {status:?}");
                std::thread::sleep(Duration::from_millis(20));
            }
        };
        wait("a complete area of interest", &|s| s.status.locked().complete);
        let held = |s: &Shared| s.scene.locked().as_ref().map_or(0, |scene| scene.instances.len());
        wait("the area's trees in the scene", &|s| held(s) > 0);
        // The world built from its function colours the ground: the scene carries the world's cover.
        let covered = |s: &Shared| s.scene.locked().as_ref().and_then(|scene| scene.cover.clone());
        wait("the ground's cover in the scene", &|s| covered(s).is_some());
        let world = canopy_worlds::world::World::default_world();
        assert_eq!(*covered(&shared).unwrap(), GroundCover::of_world(&world), "the world's own cover");
        let before = held(&shared);
        let (x, z) = (7.25, -3.5);
        let what = format!("plant at ({x}, {z})");
        let op = EditOp::Plant { species: 0, x, z, params: Vec::new() };
        tx.send(EditRequest { op, what: what.clone() }).unwrap();
        wait("the edit's answer", &|s| s.status.locked().edit.as_deref().is_some_and(|l| l.starts_with(&what)));
        let line = shared.status.locked().edit.clone().unwrap();
        assert!(line.starts_with(&format!("{what}: ok, instance")), "{line}");
        let planted = |s: &Shared| {
            s.scene.locked().as_ref().is_some_and(|scene| {
                scene.instances.iter().any(|i| (i.position[0] - x).abs() < 0.1 && (i.position[2] - z).abs() < 0.1)
            })
        };
        wait("the planted tree in the scene", &planted);
        assert_eq!(held(&shared), before + 1, "one tree more, the rest kept");
        shared.stop.send_replace(true);
        net.join().unwrap();
        assert!(shared.status.locked().error.is_none(), "{:?}", shared.status.locked().error);
        local.runtime.block_on(local.server.shutdown(Duration::from_secs(1)));
    }
}
