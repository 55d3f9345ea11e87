//! The far view's summaries on the GPU (issue 15): each species' canopy tile baked on a worker and packed, in its
//! four resolutions, into one atlas slot, its profile appended to the profiles buffer; the frame's [`ForestPlan`] run after the instances' plan, its patches
//! and ground heights uploaded, and drawn ([`Renderer::draw_forest`]) after the far instances (front to back).

use std::sync::Arc;
use std::time::Duration;

use super::{Growable, INITIAL_LIST_BYTES, PROXY_BOX_VERTICES, Renderer};
use crate::camera::Camera;
use crate::forest::{ForestInputs, ForestPatch, ForestPlan, TileState, TileVol};
use crate::scene::Scene;
use crate::select::{View, VolState};
use crate::stats::FrameStats;
use crate::tile::{CanopyTile, TILE_MIPS};
use crate::workers::Job;

/// Priority of tile jobs: after the species' volumes, before any amplification.
const TILE_PRIORITY: f32 = 1.0e30;

/// The forest's state: the plan, the tiles by species, and the frame's buffers.
pub(super) struct ForestGpu {
    plan: ForestPlan,
    /// Tiles by species id.
    tiles: Vec<Option<TileState>>,
    /// Whether a tile job was submitted, by species id.
    submitted: Vec<bool>,
    patches: Growable,
    ground: Growable,
    /// Every resident tile's profile, in the order they were placed (`TileVol::profile` indexes it).
    profiles: Vec<[f32; 4]>,
    profiles_gpu: Growable,
    /// Whether `profiles` changed since it was uploaded.
    profiles_dirty: bool,
    bg: Option<wgpu::BindGroup>,
}

impl ForestGpu {
    pub(super) fn new(device: &wgpu::Device) -> ForestGpu {
        ForestGpu {
            plan: ForestPlan::default(),
            tiles: Vec::new(),
            submitted: Vec::new(),
            patches: Growable::new(
                device,
                "forest patches",
                INITIAL_LIST_BYTES,
                wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::STORAGE,
            ),
            ground: Growable::new(device, "forest ground", INITIAL_LIST_BYTES, wgpu::BufferUsages::STORAGE),
            profiles: Vec::new(),
            profiles_gpu: Growable::new(device, "canopy profiles", INITIAL_LIST_BYTES, wgpu::BufferUsages::STORAGE),
            profiles_dirty: false,
            bg: None,
        }
    }

    /// Draw no patches (a frame before any scene).
    pub(super) fn clear(&mut self) {
        self.plan.patches.clear();
    }

    /// This frame's patches, front to back, as uploaded.
    pub(super) fn patches(&self) -> &[ForestPatch] {
        &self.plan.patches
    }

    /// The buffer holding them.
    pub(super) fn patch_buffer(&self) -> &wgpu::Buffer {
        &self.patches.buffer
    }

    /// The ground heights and profiles bound (the far field's march binds them whether or not there are patches);
    /// `None` before the first frame's plan.
    pub(super) fn bind_group(&self) -> Option<&wgpu::BindGroup> {
        self.bg.as_ref()
    }
}

/// Where resolution `m` of a tile lies in its atlas slot of edge `e` (the first fills the lower half; the others
/// side by side above it).
fn mip_offset(m: usize, e: u32) -> [u32; 3] {
    match m {
        0 => [0, 0, 0],
        1 => [0, e / 2, 0],
        2 => [e / 2, e / 2, 0],
        _ => [3 * e / 4, e / 2, 0],
    }
}

impl Renderer {
    /// Plan the summary patches of this frame, ask for the tiles they need, and upload them.
    pub(super) fn plan_forest(&mut self, scene: &Scene, camera: &Camera, dt: f32, stats: &mut FrameStats) {
        let view = View::new(camera, self.gpu.size, self.cfg.near_clip, &self.cfg.lod, dt, self.lod.instant);
        let f = &mut self.forest;
        let input = ForestInputs {
            far: &scene.far,
            ground: &scene.ground,
            tiles: &f.tiles,
            view,
            cull_px: self.cfg.lod.cull_px,
            layer: self.cfg.forest_layer,
        };
        f.plan.plan(&input, stats);
        let mut grew = false;
        if !f.plan.patches.is_empty() {
            stats.draw_calls += 1;
            f.patches.write(&self.gpu.device, &self.gpu.queue, bytemuck::cast_slice(&f.plan.patches));
            grew = f.ground.write(&self.gpu.device, &self.gpu.queue, bytemuck::cast_slice(&f.plan.ground));
            if f.profiles_dirty {
                grew |= f.profiles_gpu.write(&self.gpu.device, &self.gpu.queue, bytemuck::cast_slice(&f.profiles));
                f.profiles_dirty = false;
            }
        }
        if grew || f.bg.is_none() {
            f.bg = Some(self.gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("forest ground and profiles"),
                layout: &self.gpu.p.forest_layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: f.ground.buffer.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: f.profiles_gpu.buffer.as_entire_binding() },
                ],
            }));
        }
        self.request_tiles();
    }

    /// Ask for the tiles of the species the nodes list: baked once the species' far volume is resident.
    fn request_tiles(&mut self) {
        let slot_edge = self.cfg.volume_resolution.next_power_of_two();
        let f = &mut self.forest;
        for &s in &f.plan.species {
            let at = usize::from(s);
            if f.tiles.len() <= at {
                f.tiles.resize(at + 1, None);
                f.submitted.resize(at + 1, false);
            }
            if f.submitted[at] {
                continue;
            }
            f.tiles[at] = match (self.far.vols.get(at).copied().flatten(), self.far.sources.get(at).cloned().flatten())
            {
                (Some(VolState::Ready(_)), Some(volume)) => {
                    self.workers.submit(Job::Tile { species: s, volume, resolution: slot_edge }, TILE_PRIORITY);
                    f.submitted[at] = true;
                    Some(TileState::Pending)
                }
                (Some(VolState::Pending), _) => Some(TileState::Pending),
                (Some(_), _) => Some(TileState::Failed),
                (None, _) => None,
            };
        }
    }

    /// A tile came back from a worker: pack its resolutions into one atlas slot.
    pub(super) fn tile_finished(&mut self, species: u16, result: Result<CanopyTile, String>, took: Duration) {
        let state = match result {
            Ok(tile) => match self.place_tile(species, tile) {
                Some(t) => {
                    tracing::debug!("species {species}: canopy tile in {took:?}");
                    TileState::Ready(t)
                }
                None => {
                    tracing::warn!("species {species}: no room for its canopy tile in the far-field atlas");
                    TileState::Failed
                }
            },
            Err(e) => {
                tracing::warn!("species {species}: no canopy tile: {e}");
                TileState::Failed
            }
        };
        if let Some(slot) = self.forest.tiles.get_mut(usize::from(species)) {
            *slot = Some(state);
        }
    }

    fn place_tile(&mut self, species: u16, tile: CanopyTile) -> Option<TileVol> {
        let e = self.cfg.volume_resolution.next_power_of_two();
        if tile.mips.len() != TILE_MIPS || tile.mips[0].dims != [e, e / 2, e] {
            return None;
        }
        let reference = match self.far.vols.get(usize::from(species)).copied().flatten() {
            Some(VolState::Ready(v)) => v.height.map(|h| h.1),
            _ => None,
        };
        let voxel = tile.mips[0].voxel_size[0];
        let places = tile.mips.into_iter().enumerate().map(|(m, v)| (Arc::new(v), mip_offset(m, e))).collect();
        let volume = self.place_in_slot(places)?;
        let profile = self.forest.profiles.len() as u32;
        self.forest.profiles.extend(tile.profile.gpu());
        self.forest.profiles_dirty = true;
        Some(TileVol { volume, period: tile.period, top: tile.top, voxel, density: tile.density, reference, profile })
    }

    /// Draw the frame's summary patches (in the far field's pass, after the far instances: front to back).
    pub(super) fn draw_forest(&self, pass: &mut wgpu::RenderPass<'_>) {
        let f = &self.forest;
        let count = f.plan.patches.len() as u32;
        if let (true, Some(volumes), Some(ground)) = (count > 0, &self.far.bg, &f.bg) {
            pass.set_pipeline(&self.gpu.p.forest);
            pass.set_bind_group(1, volumes, &[]);
            pass.set_bind_group(2, ground, &[]);
            let bytes = u64::from(count) * size_of::<ForestPatch>() as u64;
            pass.set_vertex_buffer(0, f.patches.buffer.slice(..bytes));
            pass.draw(0..PROXY_BOX_VERTICES, 0..count);
        }
    }
}
