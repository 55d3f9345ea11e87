//! Offscreen rendering: the same [`Renderer`] into a texture, read back to memory and PNG — what `canopy render`
//! and the image tests use; it needs no window and no GPU (Mesa's lavapipe is enough).

use std::path::Path;
use std::time::Duration;

use super::camera::Camera;
use super::clock::Instant;
use super::gpu::{Gpu, GpuError};
use super::renderer::{FrameStats, Renderer};
use super::scene::Scene;
use super::{ConfigError, RenderConfig};

/// The offscreen target format: plain 8-bit RGBA, values written as computed (as the CPU reference writes them).
pub const OFFSCREEN_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// Largest offscreen image side.
pub const MAX_SIDE: u32 = 8192;

/// Why an offscreen render failed.
#[derive(Debug, thiserror::Error)]
pub enum OffscreenError {
    /// No usable GPU.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// The configuration is not valid.
    #[error("render configuration: {0}")]
    Config(#[from] ConfigError),
    /// The image size is out of range.
    #[error("image of {0}×{1} pixels (allowed 1..={MAX_SIDE} per side)")]
    Size(u32, u32),
    /// The workers could not be started.
    #[error("starting worker threads: {0}")]
    Workers(#[from] std::io::Error),
    /// Geometry for the view was not ready in time.
    #[error("the scene did not settle within {0:?} ({1} instances still waiting)")]
    Timeout(Duration, usize),
    /// Reading the image back failed.
    #[error("reading the image back: {0}")]
    Readback(String),
    /// Encoding or writing the PNG failed.
    #[error("writing {path}: {reason}")]
    Png {
        /// The file.
        path: String,
        /// Why.
        reason: String,
    },
}

/// An RGBA8 image, rows top to bottom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RenderedImage {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// `width · height · 4` bytes.
    pub rgba: Vec<u8>,
}

impl RenderedImage {
    /// Write a PNG file.
    pub fn save_png(&self, path: &Path) -> Result<(), OffscreenError> {
        let fail = |reason: String| OffscreenError::Png { path: path.display().to_string(), reason };
        let img = image::RgbaImage::from_raw(self.width, self.height, self.rgba.clone())
            .ok_or_else(|| fail("pixel buffer does not match the size".into()))?;
        img.save_with_format(path, image::ImageFormat::Png).map_err(|e| fail(e.to_string()))
    }

    /// The pixel at (x, y).
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 4] {
        let i = 4 * (y as usize * self.width as usize + x as usize);
        [self.rgba[i], self.rgba[i + 1], self.rgba[i + 2], self.rgba[i + 3]]
    }
}

/// A renderer with an offscreen target.
#[derive(Debug)]
pub struct Offscreen {
    /// The GPU.
    pub gpu: Gpu,
    /// The renderer.
    pub renderer: Renderer,
    target: wgpu::Texture,
    view: wgpu::TextureView,
    readback: wgpu::Buffer,
    padded_row: u32,
}

impl Offscreen {
    /// Set up a GPU (headless) and a renderer for `width × height` images.
    pub fn new(cfg: RenderConfig, width: u32, height: u32) -> Result<Offscreen, OffscreenError> {
        cfg.validate()?;
        if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
            return Err(OffscreenError::Size(width, height));
        }
        let gpu = Gpu::headless(&cfg)?;
        let mut renderer = Renderer::new(&gpu.device, &gpu.queue, OFFSCREEN_FORMAT, (width, height), cfg)?;
        renderer.set_instant_transitions(true);
        let target = gpu.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("offscreen"),
            size: wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: OFFSCREEN_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let view = target.create_view(&wgpu::TextureViewDescriptor::default());
        let padded_row = padded_row(width);
        let readback = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: u64::from(padded_row) * u64::from(height),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(Offscreen { gpu, renderer, target, view, readback, padded_row })
    }

    /// Update until everything in view is drawn at its wanted level (waiting for the workers, which a window never
    /// does), or fail after `timeout`.
    pub fn settle(&mut self, scene: &Scene, camera: &Camera, timeout: Duration) -> Result<FrameStats, OffscreenError> {
        let started = Instant::now();
        loop {
            let stats = self.renderer.update(scene, camera, 1.0);
            if stats.settled() {
                return Ok(stats);
            }
            if started.elapsed() > timeout {
                return Err(OffscreenError::Timeout(timeout, stats.waiting));
            }
            if stats.uploads_waiting == 0 {
                self.renderer.wait_for_workers(Duration::from_millis(50));
            }
        }
    }

    /// Render the prepared frame and wait for the GPU to finish (for timings, without reading back).
    pub fn render_and_wait(&mut self) -> Result<(), OffscreenError> {
        let index = self.submit();
        self.wait(index)
    }

    /// Submit the prepared frame without waiting: the CPU may prepare the next one meanwhile, as a window does.
    pub fn submit(&mut self) -> wgpu::SubmissionIndex {
        self.renderer.render(&self.view)
    }

    /// Wait for the GPU to finish the submission `index`.
    pub fn wait(&self, index: wgpu::SubmissionIndex) -> Result<(), OffscreenError> {
        self.gpu
            .device
            .poll(wgpu::PollType::Wait { submission_index: Some(index), timeout: None })
            .map_err(|e| OffscreenError::Readback(e.to_string()))?;
        Ok(())
    }

    /// Render the prepared frame and read it back.
    pub fn render(&mut self) -> Result<RenderedImage, OffscreenError> {
        self.renderer.render(&self.view);
        read_back(&self.gpu.device, &self.gpu.queue, &self.target, &self.readback, self.padded_row)
    }
}

/// Bytes per row of a `width`-pixel RGBA8 readback, padded to wgpu's copy alignment.
pub fn padded_row(width: u32) -> u32 {
    (width * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT
}

/// Copy an RGBA8 texture (with `COPY_SRC`) into `readback` (a `MAP_READ | COPY_DST` buffer of
/// `padded_row · height` bytes), wait for the GPU and return the image. The editor's screenshots read their window
/// back with it too.
pub fn read_back(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
    readback: &wgpu::Buffer,
    padded_row: u32,
) -> Result<RenderedImage, OffscreenError> {
    let (width, height) = (texture.width(), texture.height());
    let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("readback") });
    enc.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: readback,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(padded_row),
                rows_per_image: Some(height),
            },
        },
        wgpu::Extent3d { width, height, depth_or_array_layers: 1 },
    );
    let index = queue.submit([enc.finish()]);
    let (tx, rx) = std::sync::mpsc::channel();
    readback.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    device
        .poll(wgpu::PollType::Wait { submission_index: Some(index), timeout: None })
        .map_err(|e| OffscreenError::Readback(e.to_string()))?;
    rx.recv()
        .map_err(|e| OffscreenError::Readback(e.to_string()))?
        .map_err(|e| OffscreenError::Readback(e.to_string()))?;
    let mut rgba = Vec::with_capacity((width * height * 4) as usize);
    {
        let data = readback.get_mapped_range(..).map_err(|e| OffscreenError::Readback(e.to_string()))?;
        for row in data.chunks_exact(padded_row as usize) {
            rgba.extend_from_slice(&row[..(width * 4) as usize]);
        }
    }
    readback.unmap();
    Ok(RenderedImage { width, height, rgba })
}

/// Render one still: set up, settle within `timeout`, render and read back.
pub fn render_still(
    cfg: RenderConfig,
    scene: &Scene,
    camera: &Camera,
    width: u32,
    height: u32,
    timeout: Duration,
) -> Result<(RenderedImage, FrameStats), OffscreenError> {
    let mut off = Offscreen::new(cfg, width, height)?;
    let stats = off.settle(scene, camera, timeout)?;
    Ok((off.render()?, stats))
}
