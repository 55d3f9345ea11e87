//! The live 3D preview: the model's species drawn by the renderer crate ([`canopy_render::Renderer`]) into a
//! texture that egui shows. One instance (or an N × N grove of seeds) on flat ground, the orbit camera of the UI.
//!
//! The renderer caches geometry and far-field volumes by species id, so every new model takes a fresh id (its old
//! one is emptied); every [`RENEW_AFTER`] models the renderer is made again to give back its arenas. The detail
//! level is imposed through the level-of-detail thresholds (detail 0: everything near; detail d: everything in the
//! mid band at level d), which also means a new renderer when the detail changes.

use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_protocol::SpeciesGraph;
use canopy_protocol::record::{CellCoord, InstanceId};
use canopy_render::{Camera, FrameStats, LodConfig, RenderConfig, Renderer, Scene, SceneInstance};
use canopy_worlds::world::Terrain;
use glam::Vec3;

use crate::EditorError;
use crate::ui::{EditorUi, View};

/// The preview's texture format (what egui-wgpu samples for a native texture).
pub const FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// Models drawn by one renderer before it is made again.
pub const RENEW_AFTER: u16 = 32;

/// What the scene was built from.
#[derive(Clone, Debug, PartialEq)]
struct Shown {
    graph: *const SpeciesGraph,
    revision: u64,
    view: View,
    grove: u32,
}

/// The time from a change of the model to a preview drawn at its wanted level.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Latency {
    /// Milliseconds from the scene change to the first settled frame (workers' amplification, upload, render).
    pub millis: f64,
    /// Frames it took.
    pub frames: u32,
}

/// The render target and its egui id.
struct Target {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    size: [u32; 2],
}

/// The preview (see the module docs).
pub struct Preview {
    cfg: RenderConfig,
    renderer: Option<(Renderer, u8)>,
    target: Option<Target>,
    texture_id: Option<egui::TextureId>,
    scene: Scene,
    shown: Option<Shown>,
    species_id: u16,
    changed_at: Option<(Instant, u32)>,
    /// The last change's latency.
    pub latency: Option<Latency>,
    /// The last update's renderer statistics.
    pub stats: FrameStats,
}

impl std::fmt::Debug for Preview {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Preview").field("species_id", &self.species_id).field("latency", &self.latency).finish()
    }
}

impl Preview {
    /// A preview with the renderer's defaults (two worker threads at least: the volume and the tree of a new
    /// model are worked on together).
    pub fn new() -> Preview {
        let mut cfg = RenderConfig::default();
        cfg.workers = cfg.workers.max(2);
        cfg.max_jobs = RenderConfig::jobs_for(cfg.workers);
        cfg.prim_memory = 32 << 20;
        cfg.mesh_memory = 48 << 20;
        cfg.lighting.fog_density = 0.0;
        Preview {
            cfg,
            renderer: None,
            target: None,
            texture_id: None,
            scene: Scene::empty(Arc::new(Terrain::flat([-32.0, -32.0], 64.0))),
            shown: None,
            species_id: 0,
            changed_at: None,
            latency: None,
            stats: FrameStats::default(),
        }
    }

    /// The texture egui shows, once rendered.
    pub fn texture_id(&self) -> Option<egui::TextureId> {
        self.texture_id
    }

    /// The level-of-detail thresholds that draw every instance at `detail`.
    fn lod_for(detail: u8) -> LodConfig {
        let base = LodConfig { cull_px: 0.0, low_res_px: 0.0, fade_seconds: 0.0, ..LodConfig::default() };
        match detail {
            0 => LodConfig { near_px: 0.0, far_px: 0.0, mid_levels: 0, ..base },
            d => LodConfig { near_px: 1e7, far_px: 0.0, mid_levels: d, ..base },
        }
    }

    /// Rebuild the scene when the model, view or grove changed; true when it did.
    fn sync(&mut self, ui: &EditorUi) -> bool {
        let Some(species) = ui.model.species() else { return false };
        let graph = Arc::as_ptr(&species.graph);
        let shown = Shown { graph, revision: ui.model.revision(), view: ui.view, grove: ui.grove };
        if self.shown.as_ref() == Some(&shown) {
            return false;
        }
        let new_graph = self.shown.as_ref().is_none_or(|s| s.graph != graph);
        if new_graph {
            if self.species_id + 1 >= RENEW_AFTER {
                self.renderer = None;
                self.species_id = 0;
                self.scene.species.clear();
            } else if !self.scene.species.is_empty() {
                self.species_id += 1;
            }
            for s in &mut self.scene.species {
                *s = None;
            }
            let id = usize::from(self.species_id);
            if self.scene.species.len() <= id {
                self.scene.species.resize(id + 1, None);
                self.scene.volumes.resize(id + 1, None);
            }
            self.scene.species[id] = Some(Arc::clone(&species.graph));
        }
        let inst = ui.model.instance();
        let n = if ui.view == View::Grove { ui.grove.max(1) } else { 1 };
        let step = ui.grove_spacing();
        self.scene.instances = (0..n * n)
            .filter_map(|i| {
                let id = InstanceId::new(CellCoord { x: 0, z: 0 }, i as u16)?;
                Some(SceneInstance {
                    id,
                    species: self.species_id,
                    position: [(i % n) as f32 * step, 0.0, (i / n) as f32 * step],
                    seed: inst.seed.wrapping_add(u64::from(i)),
                    params: inst.params.clone(),
                })
            })
            .collect();
        let extent = (step * n as f32 * 8.0).max(1_000.0);
        let centre = step * (n - 1) as f32 / 2.0;
        self.scene.ground = Arc::new(Terrain::flat([centre - extent / 2.0, centre - extent / 2.0], extent)).into();
        self.scene.generation += 1;
        self.shown = Some(shown);
        true
    }

    /// The camera of the UI's orbit.
    pub fn camera(ui: &EditorUi) -> Camera {
        Camera::looking_at(Vec3::from(ui.orbit.eye()), Vec3::from(ui.orbit.target), 45.0)
    }

    /// Prepare and render one frame of the preview at the size the UI asked for; registers (or updates) its
    /// texture with egui. Returns the renderer's statistics.
    pub fn frame(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        egui: &mut egui_wgpu::Renderer,
        ui: &EditorUi,
        dt: f32,
    ) -> Result<FrameStats, EditorError> {
        let size = ui.preview_px.map(|v| v.clamp(16, 4096));
        if self.target.as_ref().is_none_or(|t| t.size != size) {
            let texture = device.create_texture(&wgpu::TextureDescriptor {
                label: Some("preview"),
                size: wgpu::Extent3d { width: size[0], height: size[1], depth_or_array_layers: 1 },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: FORMAT,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                    | wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            });
            let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
            match self.texture_id {
                Some(id) => egui.update_egui_texture_from_wgpu_texture(device, &view, wgpu::FilterMode::Linear, id),
                None => self.texture_id = Some(egui.register_native_texture(device, &view, wgpu::FilterMode::Linear)),
            }
            if let Some((r, _)) = &mut self.renderer {
                r.resize(size[0], size[1]);
            }
            self.target = Some(Target { texture, view, size });
        }
        let detail = ui.model.detail();
        if self.renderer.as_ref().is_some_and(|(_, d)| *d != detail) {
            self.renderer = None;
        }
        if self.sync(ui) {
            self.changed_at = Some((Instant::now(), 0));
        }
        if self.renderer.is_none() {
            let cfg = RenderConfig { lod: Preview::lod_for(detail), ..self.cfg.clone() };
            let mut r = Renderer::new(device, queue, FORMAT, (size[0], size[1]), cfg)
                .map_err(|e| EditorError::Renderer(e.to_string()))?;
            r.set_instant_transitions(true);
            self.renderer = Some((r, detail));
            // A new renderer holds nothing: the scene's state must be rebuilt.
            self.scene.generation += 1;
        }
        let (Some((renderer, _)), Some(target)) = (&mut self.renderer, &self.target) else {
            return Ok(FrameStats::default());
        };
        let camera = Preview::camera(ui);
        let stats = renderer.update(&self.scene, &camera, dt);
        renderer.render(&target.view);
        if let Some((t, frames)) = &mut self.changed_at {
            *frames += 1;
            if stats.settled() && stats.jobs == 0 {
                self.latency = Some(Latency { millis: t.elapsed().as_secs_f64() * 1e3, frames: *frames });
                self.changed_at = None;
            }
        }
        self.stats = stats.clone();
        Ok(stats)
    }

    /// Whether the preview still waits for geometry (the window keeps repainting).
    pub fn waiting(&self) -> bool {
        self.changed_at.is_some() || !self.stats.settled() || self.stats.jobs > 0
    }

    /// Block up to `timeout` for the renderer's workers (offscreen frames wait; the window never does).
    pub fn wait_for_workers(&mut self, timeout: Duration) {
        if let Some((r, _)) = &mut self.renderer {
            r.wait_for_workers(timeout);
        }
    }

    /// The render target texture (for reading the preview back in tests).
    pub fn texture(&self) -> Option<&wgpu::Texture> {
        self.target.as_ref().map(|t| &t.texture)
    }
}

impl Default for Preview {
    fn default() -> Self {
        Preview::new()
    }
}
