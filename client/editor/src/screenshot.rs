//! The editor window rendered once offscreen (`canopy species edit FILE --screenshot out.png`): the same UI and
//! preview as the window, into a texture on a headless GPU (Mesa's lavapipe is enough), read back. The frame waits
//! for the preview's geometry and any raymarch, so the picture is the settled one.

use std::time::{Duration, Instant};

use canopy_render::offscreen::{padded_row, read_back};
use canopy_render::{Gpu, RenderConfig, RenderedImage};

use crate::EditorError;
use crate::preview::{FORMAT, Preview};
use crate::ui::EditorUi;

/// How long a screenshot waits for the preview to settle.
pub const SETTLE: Duration = Duration::from_secs(120);

/// A headless egui + preview frame renderer.
pub struct Headless {
    gpu: Gpu,
    ctx: egui::Context,
    egui: egui_wgpu::Renderer,
    /// The 3D preview.
    pub preview: Preview,
    size: (u32, u32),
    time: f64,
}

impl Headless {
    /// A GPU and an egui context for `size` frames.
    pub fn new(size: (u32, u32)) -> Result<Headless, EditorError> {
        let gpu = Gpu::headless(&RenderConfig::default())?;
        let egui = egui_wgpu::Renderer::new(&gpu.device, FORMAT, egui_wgpu::RendererOptions::default());
        let ctx = egui::Context::default();
        Ok(Headless { gpu, ctx, egui, preview: Preview::new(), size, time: 0.0 })
    }

    /// The GPU.
    pub fn gpu(&self) -> &Gpu {
        &self.gpu
    }

    /// The egui context.
    pub fn context(&self) -> &egui::Context {
        &self.ctx
    }

    /// Run the UI once at time `self.time` (advanced by `dt` seconds) and return its output.
    fn run_ui(&mut self, ui: &mut EditorUi, dt: f64) -> egui::FullOutput {
        self.time += dt;
        let input = egui::RawInput {
            screen_rect: Some(egui::Rect::from_min_size(
                egui::Pos2::ZERO,
                egui::vec2(self.size.0 as f32, self.size.1 as f32),
            )),
            time: Some(self.time),
            ..egui::RawInput::default()
        };
        let id = self.preview.texture_id();
        self.ctx.run_ui(input, |root| ui.show(root, id))
    }

    /// Lay the UI out, then draw the preview until it settles (and any raymarch finishes), then wait for the stats
    /// panel's numbers of the current model.
    pub fn settle(&mut self, ui: &mut EditorUi, timeout: Duration) -> Result<(), EditorError> {
        let started = Instant::now();
        self.settle_preview(ui, timeout)?;
        ui.wait_for_stats(timeout.saturating_sub(started.elapsed()));
        if ui.stats_pending() {
            return Err(EditorError::Screenshot(format!("the stats were not measured within {timeout:?}")));
        }
        let mut out = self.run_ui(ui, 0.0);
        self.apply_textures(&mut out);
        Ok(())
    }

    /// Lay the UI out, then draw the preview until it settles (and any raymarch finishes); the stats panel is not
    /// waited for. Returns the preview frames drawn.
    pub fn settle_preview(&mut self, ui: &mut EditorUi, timeout: Duration) -> Result<u32, EditorError> {
        let started = Instant::now();
        for _ in 0..2 {
            let mut out = self.run_ui(ui, 0.0);
            self.apply_textures(&mut out);
        }
        let mut frames = 0;
        loop {
            let stats = self.preview.frame(&self.gpu.device, &self.gpu.queue, &mut self.egui, ui, 0.0)?;
            frames += 1;
            let species = ui.model.species().is_some();
            ui.wait_for_volume(&self.ctx, Duration::from_millis(20));
            let mut out = self.run_ui(ui, 0.0);
            self.apply_textures(&mut out);
            if (!species || stats.settled()) && !ui.busy() {
                self.wait_for_gpu()?;
                return Ok(frames);
            }
            if started.elapsed() > timeout {
                return Err(EditorError::Screenshot(format!("the preview did not settle within {timeout:?}")));
            }
            self.preview.wait_for_workers(Duration::from_millis(20));
        }
    }

    /// Bring the preview's renderer up to date without drawing anything (the UI is not run either): repeated until
    /// its geometry is built and uploaded — what a change costs before the GPU draws it. Returns the updates made.
    pub fn update_until_ready(&mut self, ui: &mut EditorUi, timeout: Duration) -> Result<u32, EditorError> {
        let started = Instant::now();
        let mut updates = 0;
        loop {
            let stats = self.preview.update(&self.gpu.device, &self.gpu.queue, &mut self.egui, ui, 0.0)?;
            updates += 1;
            if ui.model.species().is_none() || stats.settled() {
                return Ok(updates);
            }
            if started.elapsed() > timeout {
                return Err(EditorError::Screenshot(format!("the preview was not ready within {timeout:?}")));
            }
            self.preview.wait_for_workers(Duration::from_millis(1));
        }
    }

    /// One whole window frame as the window draws it — the UI, the preview, egui onto a window-sized target — and
    /// wait for the GPU to finish it.
    pub fn draw_frame(&mut self, ui: &mut EditorUi) -> Result<(), EditorError> {
        self.preview.frame(&self.gpu.device, &self.gpu.queue, &mut self.egui, ui, 0.0)?;
        let mut out = self.run_ui(ui, 0.0);
        self.apply_textures(&mut out);
        let target = self.window_target();
        let view = target.create_view(&wgpu::TextureViewDescriptor::default());
        let screen = egui_wgpu::ScreenDescriptor {
            size_in_pixels: [self.size.0, self.size.1],
            pixels_per_point: out.pixels_per_point,
        };
        let jobs = self.ctx.tessellate(std::mem::take(&mut out.shapes), out.pixels_per_point);
        draw_egui(&mut self.egui, &self.gpu.device, &self.gpu.queue, &view, &jobs, &screen);
        self.wait_for_gpu()
    }

    /// Block until the GPU has finished everything submitted.
    pub fn wait_for_gpu(&self) -> Result<(), EditorError> {
        self.gpu
            .device
            .poll(wgpu::PollType::Wait { submission_index: None, timeout: None })
            .map(|_| ())
            .map_err(|e| EditorError::Screenshot(e.to_string()))
    }

    fn window_target(&self) -> wgpu::Texture {
        let (w, h) = self.size;
        self.gpu.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("editor window"),
            size: wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        })
    }

    fn apply_textures(&mut self, out: &mut egui::FullOutput) {
        for (id, deltas) in &out.textures_delta.set {
            for delta in deltas {
                self.egui.update_texture(&self.gpu.device, &self.gpu.queue, *id, delta);
            }
        }
        for id in &out.textures_delta.free {
            self.egui.free_texture(id);
        }
        out.textures_delta.clear();
    }

    /// Run the UI once more and render the whole window into an image.
    pub fn capture(&mut self, ui: &mut EditorUi) -> Result<RenderedImage, EditorError> {
        self.preview.frame(&self.gpu.device, &self.gpu.queue, &mut self.egui, ui, 0.0)?;
        let mut out = self.run_ui(ui, 0.0);
        self.apply_textures(&mut out);
        let (w, h) = self.size;
        let target = self.window_target();
        let device = &self.gpu.device;
        let view = target.create_view(&wgpu::TextureViewDescriptor::default());
        let screen = egui_wgpu::ScreenDescriptor { size_in_pixels: [w, h], pixels_per_point: out.pixels_per_point };
        let jobs = self.ctx.tessellate(std::mem::take(&mut out.shapes), out.pixels_per_point);
        draw_egui(&mut self.egui, device, &self.gpu.queue, &view, &jobs, &screen);
        let row = padded_row(w);
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("editor readback"),
            size: u64::from(row) * u64::from(h),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        read_back(device, &self.gpu.queue, &target, &readback, row).map_err(|e| EditorError::Screenshot(e.to_string()))
    }
}

/// Encode egui's paint jobs into `view` (cleared first) and submit them.
pub fn draw_egui(
    egui: &mut egui_wgpu::Renderer,
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    view: &wgpu::TextureView,
    jobs: &[egui::ClippedPrimitive],
    screen: &egui_wgpu::ScreenDescriptor,
) -> wgpu::SubmissionIndex {
    let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("egui") });
    let extra = egui.update_buffers(device, queue, &mut enc, jobs, screen);
    {
        let pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("egui"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::BLACK), store: wgpu::StoreOp::Store },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        let mut pass = pass.forget_lifetime();
        egui.render(&mut pass, jobs, screen);
    }
    queue.submit(extra.into_iter().chain([enc.finish()]))
}

/// Render the editor window once: lay out, settle, capture.
pub fn render(ui: &mut EditorUi, size: (u32, u32)) -> Result<RenderedImage, EditorError> {
    let mut h = Headless::new(size)?;
    h.settle(ui, SETTLE)?;
    h.capture(ui)
}
