//! The far-field atlas: one 3D texture of fixed-size slots into which every species' volumes (full, halved and
//! coarser) and canopy tiles are placed, each placed volume's info record for the shaders, and the bind group over
//! both. The atlas grows by doubling its rows, re-uploading what it held from its CPU copies.

use std::sync::Arc;

use glam::Vec3;

use super::{GpuCore, Renderer, VolumeInfo};
use crate::pipelines::ATLAS_FORMAT;
use crate::volume::FarVolume;

/// Atlas slots per row at most (the atlas grows by doubling its rows).
const ATLAS_MAX_PER_ROW: u32 = 8;
/// Bytes of one atlas texel ([`ATLAS_FORMAT`]: four halves).
const ATLAS_TEXEL_BYTES: u32 = 4 * size_of::<u16>() as u32;

pub(super) struct Atlas {
    texture: wgpu::Texture,
    slot: u32,
    per_row: u32,
    rows: u32,
    /// Slots taken.
    used: u32,
    /// CPU copies of every volume with its first texel, to re-upload when the atlas grows (growing adds rows, so
    /// a slot keeps its place).
    volumes: Vec<([u32; 3], Arc<FarVolume>)>,
}

impl Renderer {
    /// Place a volume in an atlas slot of its own (growing the atlas if needed); returns its index and bounding
    /// sphere.
    pub(super) fn add_volume(&mut self, v: Arc<FarVolume>) -> Option<(u32, Vec3, f32)> {
        let (c, r) = v.bounding_sphere();
        Some((self.place_in_slot(vec![(v, [0; 3])])?, Vec3::from(c), r))
    }

    /// Place a species' halved volume and its coarser ones in one atlas slot (each at most half the last's edge:
    /// side by side along x at 0, ½ and ¾ of the slot); returns the halved one's index (the coarser follow it).
    pub(super) fn add_lower_volumes(&mut self, low: Arc<FarVolume>, coarser: Vec<FarVolume>) -> Option<u32> {
        let e = self.cfg.volume_resolution.next_power_of_two();
        let mut places = vec![(low, [0; 3])];
        let (mut x, mut edge) = (0, e / 2);
        for v in coarser {
            (x, edge) = (x + edge, edge / 2);
            if v.dims.iter().any(|&d| d > edge) {
                return None;
            }
            places.push((Arc::new(v), [x, 0, 0]));
        }
        if places[0].0.dims.iter().any(|&d| d > e / 2) {
            return None;
        }
        self.place_in_slot(places)
    }

    /// Take a free atlas slot and write `volumes` into it at their offsets, listing their infos (once, with one
    /// new bind group); returns the first one's index — the others follow it, in order. `None` when one would
    /// reach past the slot or no slot is left.
    pub(super) fn place_in_slot(&mut self, volumes: Vec<(Arc<FarVolume>, [u32; 3])>) -> Option<u32> {
        let e = self.cfg.volume_resolution.next_power_of_two();
        if volumes.is_empty() || volumes.iter().any(|(v, o)| (0..3).any(|i| o[i] + v.dims[i] > e)) {
            return None;
        }
        let slot = self.reserve_slot()?;
        let far = &mut self.far;
        let atlas = far.atlas.as_mut()?;
        let first = far.infos.len() as u32;
        for (v, o) in volumes {
            let origin = [slot[0] + o[0], slot[1] + o[1], slot[2] + o[2]];
            write_volume(&self.gpu.queue, &atlas.texture, origin, &v);
            far.infos.push(VolumeInfo {
                atlas: [origin[0], origin[1], origin[2], 0],
                dims: [v.dims[0], v.dims[1], v.dims[2], 0],
                voxel: [
                    v.voxel_size[0],
                    v.voxel_size[1],
                    v.voxel_size[2],
                    v.voxel_size[0].min(v.voxel_size[1]).min(v.voxel_size[2]),
                ],
                lo: [v.aabb_min[0], v.aabb_min[1], v.aabb_min[2], v.units],
                hi: [v.aabb_max[0], v.aabb_max[1], v.aabb_max[2], 0.0],
                origin: [v.origin[0], v.origin[1], v.origin[2], 0.0],
            });
            atlas.volumes.push((origin, v));
        }
        far.info_buf.write(&self.gpu.device, &self.gpu.queue, bytemuck::cast_slice(&far.infos));
        let view = atlas.texture.create_view(&wgpu::TextureViewDescriptor::default());
        far.bg = Some(self.gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("volumes"),
            layout: &self.gpu.p.volume_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(&view) },
                wgpu::BindGroupEntry { binding: 1, resource: far.info_buf.buffer.as_entire_binding() },
            ],
        }));
        Some(first)
    }

    /// Take a free atlas slot (growing the atlas if needed); returns its first texel.
    fn reserve_slot(&mut self) -> Option<[u32; 3]> {
        let slot_edge = self.cfg.volume_resolution.next_power_of_two();
        let max3d = self.gpu.device.limits().max_texture_dimension_3d;
        if slot_edge > max3d {
            return None;
        }
        let per_row = (max3d / slot_edge).clamp(1, ATLAS_MAX_PER_ROW);
        let max_rows = (max3d / slot_edge).max(1);
        let far = &mut self.far;
        let full = far.atlas.as_ref().is_some_and(|a| a.used >= a.per_row * a.rows);
        if full && far.atlas.as_ref().is_some_and(|a| a.rows * 2 > max_rows) {
            return None;
        }
        if far.atlas.is_none() || full {
            let (rows, used, old) = match far.atlas.take() {
                None => (1, 0, Vec::new()),
                Some(a) => (a.rows * 2, a.used, a.volumes),
            };
            far.atlas = Some(make_atlas(&self.gpu, slot_edge, per_row, rows, used, old));
        }
        let atlas = far.atlas.as_mut()?;
        let index = atlas.used;
        atlas.used += 1;
        Some([(index % atlas.per_row) * atlas.slot, 0, (index / atlas.per_row) * atlas.slot])
    }
}

fn make_atlas(
    gpu: &GpuCore,
    slot: u32,
    per_row: u32,
    rows: u32,
    used: u32,
    volumes: Vec<([u32; 3], Arc<FarVolume>)>,
) -> Atlas {
    let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("far-field atlas"),
        size: wgpu::Extent3d { width: slot * per_row, height: slot, depth_or_array_layers: slot * rows },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D3,
        format: ATLAS_FORMAT,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    for (origin, v) in &volumes {
        write_volume(&gpu.queue, &texture, *origin, v);
    }
    Atlas { texture, slot, per_row, rows, used, volumes }
}

fn write_volume(queue: &wgpu::Queue, texture: &wgpu::Texture, origin: [u32; 3], v: &FarVolume) {
    queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d { x: origin[0], y: origin[1], z: origin[2] },
            aspect: wgpu::TextureAspect::All,
        },
        bytemuck::cast_slice(&v.texels),
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(v.dims[0] * ATLAS_TEXEL_BYTES),
            rows_per_image: Some(v.dims[1]),
        },
        wgpu::Extent3d { width: v.dims[0], height: v.dims[1], depth_or_array_layers: v.dims[2] },
    );
}
