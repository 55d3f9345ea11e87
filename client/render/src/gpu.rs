//! Choosing a GPU: the wgpu instance (backends from `WGPU_BACKEND`, e.g. `vulkan` for Mesa lavapipe), an adapter
//! (`WGPU_ADAPTER_NAME` narrows it) and a device with the limits the renderer needs — or a clear error.

use super::RenderConfig;

/// Why no usable GPU could be set up.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GpuError {
    /// No adapter matched (no driver, no Vulkan ICD such as Mesa's lavapipe, or none for the window).
    #[error(
        "no graphics adapter found ({0}); install a Vulkan driver (on Debian without a GPU: `apt-get install mesa-vulkan-drivers`) and set WGPU_BACKEND=vulkan"
    )]
    NoAdapter(String),
    /// The adapter lacks something the renderer needs.
    #[error("the adapter {adapter} cannot run the renderer: {missing}")]
    Unsupported {
        /// Adapter name.
        adapter: String,
        /// What is missing.
        missing: String,
    },
    /// The device could not be created.
    #[error("creating the device: {0}")]
    Device(String),
    /// The window surface could not be created or configured.
    #[error("window surface: {0}")]
    Surface(String),
}

/// An adapter, its device and queue.
#[derive(Debug)]
pub struct Gpu {
    /// The wgpu instance.
    pub instance: wgpu::Instance,
    /// The adapter.
    pub adapter: wgpu::Adapter,
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
}

impl Gpu {
    /// How to present on `surface` at `size` (pixels; at least 1 each): a non-sRGB format where the surface offers
    /// one, so a window shows the colours the offscreen images write (computed, not re-encoded), else the first it
    /// offers; `present_mode`; the surface's first alpha mode. `None`: the surface offers no format.
    pub fn surface_config(
        &self,
        surface: &wgpu::Surface<'_>,
        size: (u32, u32),
        present_mode: wgpu::PresentMode,
    ) -> Option<wgpu::SurfaceConfiguration> {
        let caps = surface.get_capabilities(&self.adapter);
        let format = caps.formats.iter().copied().find(|f| !f.is_srgb()).or_else(|| caps.formats.first().copied())?;
        Some(wgpu::SurfaceConfiguration {
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            format,
            color_space: wgpu::SurfaceColorSpace::Auto,
            width: size.0.max(1),
            height: size.1.max(1),
            desired_maximum_frame_latency: 2,
            present_mode,
            alpha_mode: caps.alpha_modes.first().copied().unwrap_or(wgpu::CompositeAlphaMode::Auto),
            view_formats: vec![],
        })
    }

    /// An instance whose backends come from `WGPU_BACKEND` (all native backends by default).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn instance() -> wgpu::Instance {
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env())
    }

    /// A GPU for offscreen rendering.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn headless(cfg: &RenderConfig) -> Result<Gpu, GpuError> {
        Gpu::with_instance(Gpu::instance(), None, cfg)
    }

    /// A GPU able to present to `surface` (created from `instance`): [`Gpu::request`], waited for.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn with_instance(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
        cfg: &RenderConfig,
    ) -> Result<Gpu, GpuError> {
        pollster::block_on(Gpu::request(instance, surface, cfg))
    }

    /// A GPU able to present to `surface` (created from `instance`), set up asynchronously: natively
    /// [`Gpu::with_instance`] waits for it; in a browser the page awaits it (`Gpu::from_canvas`).
    pub async fn request(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
        cfg: &RenderConfig,
    ) -> Result<Gpu, GpuError> {
        let adapter = wgpu::util::initialize_adapter_from_env_or_default(&instance, surface)
            .await
            .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let down = adapter.get_downlevel_capabilities();
        if !down.flags.contains(wgpu::DownlevelFlags::VERTEX_STORAGE) {
            return Err(GpuError::Unsupported {
                adapter: info.name,
                missing: "storage buffers in vertex shaders".into(),
            });
        }
        if !down.flags.contains(wgpu::DownlevelFlags::FRAGMENT_WRITABLE_STORAGE) {
            return Err(GpuError::Unsupported {
                adapter: info.name,
                missing: "writable storage buffers in fragment shaders (the far field's opacity)".into(),
            });
        }
        let have = adapter.limits();
        let need_binding = cfg.prim_memory.max(cfg.vertex_memory()).max(cfg.index_memory());
        if have.max_storage_buffer_binding_size < need_binding || have.max_buffer_size < need_binding {
            return Err(GpuError::Unsupported {
                adapter: info.name,
                missing: format!(
                    "storage buffers of {need_binding} bytes (the adapter allows {}); lower the geometry memory",
                    have.max_storage_buffer_binding_size.min(have.max_buffer_size)
                ),
            });
        }
        let limits = wgpu::Limits {
            max_storage_buffer_binding_size: need_binding.max(wgpu::Limits::default().max_storage_buffer_binding_size),
            max_buffer_size: need_binding.max(wgpu::Limits::default().max_buffer_size),
            ..wgpu::Limits::default()
        }
        .using_resolution(have.clone());
        let limits = wgpu::Limits {
            max_storage_buffer_binding_size: limits
                .max_storage_buffer_binding_size
                .min(have.max_storage_buffer_binding_size),
            max_buffer_size: limits.max_buffer_size.min(have.max_buffer_size),
            ..limits
        };
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("canopy"),
                // Where the adapter has them: timestamps inside passes (`canopy render --frames` reports GPU time
                // per part) and depth tests forced before the far field's shaders (which write the pixel's opacity).
                required_features: adapter.features()
                    & (super::renderer::timing::FEATURES | wgpu::Features::SHADER_EARLY_DEPTH_TEST),
                required_limits: limits,
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::Device(e.to_string()))?;
        Ok(Gpu { instance, adapter, device, queue })
    }

    /// A GPU on the browser's WebGPU and a surface on `canvas` (wasm32 only). `Err` where the browser has no
    /// WebGPU (`navigator.gpu` missing: WebGL2 cannot run this renderer, which needs storage buffers in vertex
    /// shaders and writable storage in fragment shaders), no adapter, or a device without what the renderer needs.
    #[cfg(target_arch = "wasm32")]
    pub async fn from_canvas(
        canvas: web_sys::HtmlCanvasElement,
        cfg: &RenderConfig,
    ) -> Result<(Gpu, wgpu::Surface<'static>), GpuError> {
        let gpu = js_sys_gpu();
        if !gpu {
            return Err(GpuError::NoAdapter("the browser has no WebGPU (navigator.gpu is missing)".into()));
        }
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends: wgpu::Backends::BROWSER_WEBGPU,
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        let surface = instance
            .create_surface(wgpu::SurfaceTarget::Canvas(canvas))
            .map_err(|e| GpuError::Surface(e.to_string()))?;
        let gpu = Gpu::request(instance, Some(&surface), cfg).await?;
        Ok((gpu, surface))
    }

    /// "name (backend, driver)".
    pub fn describe(&self) -> String {
        let i = self.adapter.get_info();
        format!("{} ({:?}, {} {})", i.name, i.backend, i.driver, i.driver_info)
    }
}

/// Whether the page's `navigator.gpu` exists (wgpu's instance would otherwise fail later, less clearly).
#[cfg(target_arch = "wasm32")]
fn js_sys_gpu() -> bool {
    web_sys::window().is_some_and(|w| {
        let gpu = js_sys::Reflect::get(&w.navigator(), &"gpu".into());
        gpu.is_ok_and(|g| !g.is_undefined() && !g.is_null())
    })
}
