//! The editor window: winit's event loop, egui-winit for input, a wgpu surface, and per frame the UI, the 3D
//! preview into its texture, then egui onto the surface. The file on disk is watched; a change reloads it.

use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_render::{Gpu, RenderConfig};
use winit::application::ApplicationHandler;
use winit::event::WindowEvent;
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::window::{Window, WindowId};

use crate::EditorError;
use crate::preview::Preview;
use crate::screenshot::draw_egui;
use crate::ui::EditorUi;
use crate::watch::FileWatch;

struct Graphics {
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    gpu: Gpu,
    egui: egui_wgpu::Renderer,
    state: egui_winit::State,
}

struct App {
    ui: EditorUi,
    size: (u32, u32),
    gfx: Option<Graphics>,
    preview: Preview,
    watch: Option<FileWatch>,
    error: Option<EditorError>,
    last: Instant,
    frames: u64,
    /// How long to stay open (`--exit-after`), and from when the window opened, the moment to close.
    exit_after: Option<Duration>,
    deadline: Option<Instant>,
}

impl App {
    fn init(&mut self, event_loop: &ActiveEventLoop) -> Result<(), EditorError> {
        let fail = |e: String| EditorError::Window(e);
        let attrs = Window::default_attributes()
            .with_title(format!("Canopy species editor — {}", self.ui.model.name()))
            .with_inner_size(winit::dpi::PhysicalSize::new(self.size.0, self.size.1));
        let window = Arc::new(event_loop.create_window(attrs).map_err(|e| fail(e.to_string()))?);
        let instance = Gpu::instance();
        let surface = instance.create_surface(Arc::clone(&window)).map_err(|e| fail(e.to_string()))?;
        let gpu = Gpu::with_instance(instance, Some(&surface), &RenderConfig::default())?;
        let size = window.inner_size();
        let config = gpu
            .surface_config(&surface, (size.width, size.height), wgpu::PresentMode::AutoVsync)
            .ok_or_else(|| fail("the surface supports no format".into()))?;
        let format = config.format;
        surface.configure(&gpu.device, &config);
        let egui = egui_wgpu::Renderer::new(&gpu.device, format, egui_wgpu::RendererOptions::default());
        let ctx = egui::Context::default();
        let state = egui_winit::State::new(
            ctx,
            egui::ViewportId::ROOT,
            &window,
            Some(window.scale_factor() as f32),
            None,
            Some(gpu.device.limits().max_texture_dimension_2d as usize),
        );
        println!("adapter: {}; surface {:?} {}×{}", gpu.describe(), format, config.width, config.height);
        self.gfx = Some(Graphics { window, surface, config, gpu, egui, state });
        self.deadline = self.exit_after.map(|d| Instant::now() + d);
        Ok(())
    }

    fn frame(&mut self, event_loop: &ActiveEventLoop) {
        let Some(gfx) = &mut self.gfx else { return };
        let dt = self.last.elapsed().as_secs_f32();
        self.last = Instant::now();
        let input = gfx.state.take_egui_input(&gfx.window);
        let ctx = gfx.state.egui_ctx().clone();
        let id = self.preview.texture_id();
        let ui = &mut self.ui;
        let mut out = ctx.run_ui(input, |root| ui.show(root, id));
        gfx.state.handle_platform_output(&gfx.window, std::mem::take(&mut out.platform_output));
        for (id, deltas) in &out.textures_delta.set {
            for delta in deltas {
                gfx.egui.update_texture(&gfx.gpu.device, &gfx.gpu.queue, *id, delta);
            }
        }
        // Freed textures go after this frame is drawn.
        let free = std::mem::take(&mut out.textures_delta.free);
        out.textures_delta.clear();
        if let Err(e) = self.preview.frame(&gfx.gpu.device, &gfx.gpu.queue, &mut gfx.egui, &self.ui, dt) {
            self.error = Some(e);
            event_loop.exit();
            return;
        }
        if let Some(l) = self.preview.latency.take() {
            self.ui.status = format!(
                "preview updated {:.1} ms after the change ({} frames); amplification {:.1} ms",
                l.millis,
                l.frames,
                self.ui.model.amplified().map_or(0.0, |a| a.millis)
            );
        }
        match gfx.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(frame) | wgpu::CurrentSurfaceTexture::Suboptimal(frame) => {
                let view = frame.texture.create_view(&wgpu::TextureViewDescriptor::default());
                let screen = egui_wgpu::ScreenDescriptor {
                    size_in_pixels: [gfx.config.width, gfx.config.height],
                    pixels_per_point: out.pixels_per_point,
                };
                let jobs = ctx.tessellate(std::mem::take(&mut out.shapes), out.pixels_per_point);
                draw_egui(&mut gfx.egui, &gfx.gpu.device, &gfx.gpu.queue, &view, &jobs, &screen);
                gfx.window.pre_present_notify();
                gfx.gpu.queue.present(frame);
                self.frames += 1;
            }
            wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {}
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                gfx.surface.configure(&gfx.gpu.device, &gfx.config);
            }
            wgpu::CurrentSurfaceTexture::Validation => {
                self.error = Some(EditorError::Window("the surface reported a validation error".into()));
                event_loop.exit();
            }
        }
        for id in &free {
            gfx.egui.free_texture(id);
        }
        let busy = self.preview.waiting() || self.ui.busy();
        let delay = out.viewport_output.get(&egui::ViewportId::ROOT).map_or(Duration::MAX, |v| v.repaint_delay);
        if busy || delay.is_zero() {
            gfx.window.request_redraw();
        } else {
            // Wake at least every 100 ms to look at the file watcher (and the deadline).
            event_loop.set_control_flow(ControlFlow::WaitUntil(Instant::now() + delay.min(Duration::from_millis(100))));
        }
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gfx.is_none()
            && let Err(e) = self.init(event_loop)
        {
            self.error = Some(e);
            event_loop.exit();
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        let Some(gfx) = &mut self.gfx else { return };
        let response = gfx.state.on_window_event(&gfx.window, &event);
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                gfx.config.width = size.width.max(1);
                gfx.config.height = size.height.max(1);
                gfx.surface.configure(&gfx.gpu.device, &gfx.config);
                gfx.window.request_redraw();
            }
            WindowEvent::RedrawRequested => self.frame(event_loop),
            _ => {
                if response.repaint {
                    gfx.window.request_redraw();
                }
            }
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        if self.deadline.is_some_and(|d| Instant::now() >= d) {
            event_loop.exit();
            return;
        }
        // The loop wakes at least every 100 ms (see `frame`), so a change on disk is seen within that.
        let changed = self.watch.as_ref().is_some_and(FileWatch::changed);
        if changed {
            self.ui.status = match self.ui.model.reload() {
                Ok(true) => "reloaded: the file changed on disk".into(),
                Ok(false) => self.ui.status.clone(),
                Err(e) => e.to_string(),
            };
        }
        if let Some(gfx) = &self.gfx
            && (changed || self.preview.waiting() || self.ui.busy())
        {
            gfx.window.request_redraw();
        }
    }
}

/// Open the window on the UI and run until it is closed (or `exit_after` has passed since it opened, with the GPU
/// set up). Prints the adapter when the window opens and, at the end, the frames presented (`N frames, preview
/// settled` or `… waiting`). Closing by itself having presented no frame is an error.
pub(crate) fn run(ui: EditorUi, size: (u32, u32), exit_after: Option<Duration>) -> Result<(), EditorError> {
    let watch = match ui.model.path().filter(|p| p.exists()) {
        Some(p) => match FileWatch::new(p) {
            Ok(w) => Some(w),
            Err(e) => {
                tracing::warn!("not watching {}: {e}", p.display());
                None
            }
        },
        None => None,
    };
    let event_loop = EventLoop::new()
        .map_err(|e| EditorError::Window(format!("opening the display (is DISPLAY or WAYLAND_DISPLAY set?): {e}")))?;
    event_loop.set_control_flow(ControlFlow::Wait);
    let mut app = App {
        ui,
        size,
        gfx: None,
        preview: Preview::new(),
        watch,
        error: None,
        last: Instant::now(),
        frames: 0,
        exit_after,
        deadline: None,
    };
    event_loop.run_app(&mut app).map_err(|e| EditorError::Window(e.to_string()))?;
    let settled = if app.preview.waiting() { "waiting" } else { "settled" };
    println!("{} frames, preview {settled}", app.frames);
    match app.error {
        Some(e) => Err(e),
        None if exit_after.is_some() && app.frames == 0 => {
            Err(EditorError::Window("no frame was presented before --exit-after".into()))
        }
        None => Ok(()),
    }
}
