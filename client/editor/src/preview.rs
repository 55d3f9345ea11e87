//! The live 3D preview: the model's species drawn by the renderer crate ([`canopy_render::Renderer`]) into a
//! texture that egui shows. One instance (or an N × N grove of seeds) on flat ground with a grid ([`crate::grid`],
//! drawn as one more species), the orbit camera of the UI.
//!
//! Near-field mode: the renderer draws a species that declares `nearfield(continuous = 1, …)` with its continuous
//! mesh at detail 0 and has no switch for it; when the UI asks for primitives the preview hands the renderer a copy
//! of the graph whose `continuous` is 0 (amplification ignores the node, so the stream is the same).
//!
//! The renderer caches geometry and far-field volumes by species id, so every new model takes a fresh id (its old
//! one is emptied); every [`RENEW_AFTER`] models the renderer is made again to give back its arenas. The detail
//! level is imposed through the level-of-detail thresholds (detail 0: everything near; detail d: everything in the
//! mid band at level d), which also means a new renderer when the detail changes.

use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_protocol::record::{CellCoord, InstanceId};
use canopy_protocol::{Expr, Node, SpeciesGraph};
use canopy_render::{Camera, FrameStats, LodConfig, RenderConfig, Renderer, Scene, SceneInstance};
use canopy_worlds::world::Terrain;
use glam::Vec3;

use crate::EditorError;
use crate::grid::GridLayout;
use crate::ui::{EditorUi, View};

/// The preview's texture format (what egui-wgpu samples for a native texture).
pub const FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
/// How long the first frame after a change waits for the renderer's workers before drawing (what is not ready by
/// then is drawn by a later frame).
pub const CHANGE_WAIT: Duration = Duration::from_millis(40);
/// Models drawn by one renderer before it is made again.
pub const RENEW_AFTER: u16 = 32;

/// What the scene was built from.
#[derive(Clone, Debug, PartialEq)]
struct Shown {
    graph: *const SpeciesGraph,
    revision: u64,
    view: View,
    grove: u32,
    near_field: bool,
}

/// The grid's species id in the scene (models take the ids after it).
const GRID: u16 = 0;

/// Whether a species declares `nearfield(…)` (the renderer then meshes it continuously at detail 0, when its
/// `continuous` argument is non-zero).
pub fn has_nearfield(graph: &SpeciesGraph) -> bool {
    graph.nodes.iter().any(|n| matches!(n, Node::NearField(_)))
}

/// A copy of `graph` whose `nearfield(…)` asks for no continuous mesh (the renderer then draws its primitives).
pub fn without_nearfield(graph: &SpeciesGraph) -> SpeciesGraph {
    let mut g = graph.clone();
    for n in &mut g.nodes {
        if let Node::NearField(nf) = n {
            nf.continuous = Expr::constant(0.0);
        }
    }
    g
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
    grid: Option<Arc<SpeciesGraph>>,
    /// The primitives-only copy of a near-field species: (the graph it was made from, the copy).
    primitives_graph: Option<(Arc<SpeciesGraph>, Arc<SpeciesGraph>)>,
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
            species_id: GRID + 1,
            grid: crate::grid::graph().map(Arc::new),
            primitives_graph: None,
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

    /// The graph the renderer gets for the model: the model's own, or its primitives-only copy.
    fn drawn_graph(&mut self, graph: &Arc<SpeciesGraph>, near_field: bool) -> Arc<SpeciesGraph> {
        if near_field || !has_nearfield(graph) {
            return Arc::clone(graph);
        }
        match &self.primitives_graph {
            Some((from, copy)) if Arc::ptr_eq(from, graph) => Arc::clone(copy),
            _ => {
                let copy = Arc::new(without_nearfield(graph));
                self.primitives_graph = Some((Arc::clone(graph), Arc::clone(&copy)));
                copy
            }
        }
    }

    /// Rebuild the scene when the model, view, grove or near-field mode changed; true when it did.
    fn sync(&mut self, ui: &EditorUi) -> bool {
        let Some(species) = ui.model.species() else { return false };
        let drawn = self.drawn_graph(&species.graph, ui.near_field);
        let graph = Arc::as_ptr(&drawn);
        let shown =
            Shown { graph, revision: ui.model.revision(), view: ui.view, grove: ui.grove, near_field: ui.near_field };
        if self.shown.as_ref() == Some(&shown) {
            return false;
        }
        let new_graph = self.shown.as_ref().is_none_or(|s| s.graph != graph);
        if new_graph {
            if self.species_id + 1 >= RENEW_AFTER {
                self.renderer = None;
                self.species_id = GRID + 1;
                self.scene.species.clear();
                self.scene.volumes.clear();
            } else if self.shown.is_some() {
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
            self.scene.species[usize::from(GRID)] = self.grid.clone();
            self.scene.species[id] = Some(drawn);
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
        if let (Some(grid), Some((lo, hi))) = (&self.grid, ui.model_bounds())
            && let Some(id) = InstanceId::new(CellCoord { x: 0, z: 0 }, (n * n) as u16)
        {
            let layout = GridLayout::around(lo, hi);
            self.scene.instances.push(SceneInstance {
                id,
                species: GRID,
                position: [layout.centre[0], 0.0, layout.centre[1]],
                seed: 0,
                params: layout.params(grid),
            });
        }
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

    /// Bring the renderer up to date with the UI without rendering: the target and renderer made as needed, the
    /// scene synced, the workers' finished geometry collected and uploaded. Returns the renderer's statistics.
    pub fn update(
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
        let (Some((renderer, _)), Some(_)) = (&mut self.renderer, &self.target) else {
            return Ok(FrameStats::default());
        };
        let camera = Preview::camera(ui);
        let stats = renderer.update(&self.scene, &camera, dt);
        self.stats = stats.clone();
        Ok(stats)
    }

    /// Prepare ([`Preview::update`]) and render one frame of the preview at the size the UI asked for; registers
    /// (or updates) its texture with egui. Returns the renderer's statistics.
    pub fn frame(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        egui: &mut egui_wgpu::Renderer,
        ui: &EditorUi,
        dt: f32,
    ) -> Result<FrameStats, EditorError> {
        let mut stats = self.update(device, queue, egui, ui, dt)?;
        if let (Some((renderer, _)), Some(target)) = (&mut self.renderer, &self.target) {
            // Just after a change, wait a little for the workers, so that the frame drawn now shows it rather than
            // the one after (a frame on a software rasteriser costs far more than amplifying a tree).
            if self.changed_at.is_some_and(|(_, frames)| frames == 0) {
                let until = Instant::now() + CHANGE_WAIT;
                let camera = Preview::camera(ui);
                while !stats.settled() {
                    let left = until.saturating_duration_since(Instant::now());
                    if left.is_zero() {
                        break;
                    }
                    renderer.wait_for_workers(left);
                    stats = renderer.update(&self.scene, &camera, 0.0);
                }
                self.stats = stats.clone();
            }
            renderer.render(&target.view);
        }
        if let Some((t, frames)) = &mut self.changed_at {
            *frames += 1;
            if stats.settled() {
                self.latency = Some(Latency { millis: t.elapsed().as_secs_f64() * 1e3, frames: *frames });
                self.changed_at = None;
            }
        }
        Ok(stats)
    }

    /// Whether the preview still waits for geometry (the window keeps repainting).
    pub fn waiting(&self) -> bool {
        self.changed_at.is_some() || !self.stats.settled()
    }

    /// Block up to `timeout` for the renderer's workers (offscreen frames wait; the window waits only [`CHANGE_WAIT`]
    /// in the first frame after a change).
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
