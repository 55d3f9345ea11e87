//! The far field marched by a compute pass ([`crate::bins`], `shaders/far_march.wgsl`): each frame the far instances
//! and forest patches are listed in the screen tiles their boxes cover, front to back, and one workgroup per tile
//! marches its pixels' rays through them into the accumulation target.

use glam::Vec3;

use super::{Growable, INITIAL_LIST_BYTES, Renderer};
use crate::bins::{PATCH_BIT, TileBins};

/// The tile lists and their buffers.
pub(super) struct FarMarch {
    bins: TileBins,
    /// The frame's far instances' and patches' boxes, in drawing order (kept for its allocation).
    boxes: Vec<(u32, Vec3, Vec3)>,
    offsets: Growable,
    items: Growable,
}

impl FarMarch {
    pub(super) fn new(device: &wgpu::Device) -> FarMarch {
        FarMarch {
            bins: TileBins::default(),
            boxes: Vec::new(),
            offsets: Growable::new(device, "far-field tiles", INITIAL_LIST_BYTES, wgpu::BufferUsages::STORAGE),
            items: Growable::new(device, "far-field tile items", INITIAL_LIST_BYTES, wgpu::BufferUsages::STORAGE),
        }
    }
}

/// The box a forest patch marches (the sub-squares of its cover mask, as `vs_forest` draws it).
fn patch_box(p: &crate::forest::ForestPatch) -> Option<(Vec3, Vec3)> {
    let m = u64::from(p.cover[1]) << 32 | u64::from(p.cover[0]);
    let (mut cols, mut rows) = (0u8, 0u8);
    for j in 0..8 {
        let row = (m >> (8 * j)) as u8;
        cols |= row;
        rows |= u8::from(row != 0) << j;
    }
    if cols == 0 {
        return None;
    }
    let cell = p.rect[2] / 8.0;
    let at = |bits: u8| (bits.trailing_zeros() as f32, (8 - bits.leading_zeros()) as f32);
    let ((i0, i1), (j0, j1)) = (at(cols), at(rows));
    Some((
        Vec3::new(p.rect[0] + i0 * cell, p.span[0], p.rect[1] + j0 * cell),
        Vec3::new(p.rect[0] + i1 * cell, p.span[1], p.rect[1] + j1 * cell),
    ))
}

impl Renderer {
    /// List this frame's far instances and forest patches in the tiles they cover and upload the lists.
    pub(super) fn bin_far_field(&mut self, view_proj: &glam::Mat4) {
        let size = self.gpu.size;
        let Some(m) = &mut self.march else { return };
        m.bins.begin(size);
        let boxes = &mut m.boxes;
        boxes.clear();
        for (i, f) in self.plan.far_sorted.iter().enumerate() {
            let Some(info) = self.far.infos.get((f.volume & crate::select::VOLUME_INDEX) as usize) else { continue };
            let k = f.pos_scale[3] * info.lo[3];
            let pos = Vec3::new(f.pos_scale[0], f.pos_scale[1], f.pos_scale[2]);
            let corner = |c: [f32; 4]| {
                pos + k * (Vec3::new(c[0], c[1], c[2]) - Vec3::new(info.origin[0], info.origin[1], info.origin[2]))
            };
            boxes.push((i as u32, corner(info.lo), corner(info.hi)));
        }
        for (i, p) in self.forest.patches().iter().enumerate() {
            if let Some((lo, hi)) = patch_box(p) {
                boxes.push((PATCH_BIT | i as u32, lo, hi));
            }
        }
        m.bins.add_all(&m.boxes, view_proj, size);
        m.bins.finish();
        m.offsets.write(&self.gpu.device, &self.gpu.queue, bytemuck::cast_slice(&m.bins.offsets));
        m.items.write(&self.gpu.device, &self.gpu.queue, bytemuck::cast_slice(&m.bins.items));
    }

    /// March the far field into the accumulation target (after the scene pass, whose depth it reads).
    pub(super) fn march_far_field(&self, m: &FarMarch, enc: &mut wgpu::CommandEncoder) {
        let gpu = &self.gpu;
        let (Some(volumes), Some(forest)) = (&self.far.bg, self.forest.bind_group()) else { return };
        let bg = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("far-field march"),
            layout: &gpu.p.march_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::TextureView(&gpu.depth) },
                wgpu::BindGroupEntry { binding: 2, resource: wgpu::BindingResource::TextureView(&gpu.accum.target) },
                wgpu::BindGroupEntry { binding: 3, resource: m.offsets.buffer.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 4, resource: m.items.buffer.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 5, resource: self.far.instances.buffer.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 6, resource: self.forest.patch_buffer().as_entire_binding() },
            ],
        });
        let mut pass =
            enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("far field"), timestamp_writes: None });
        pass.set_pipeline(&gpu.p.far_march);
        pass.set_bind_group(0, &gpu.globals_bg, &[]);
        pass.set_bind_group(1, volumes, &[]);
        pass.set_bind_group(2, forest, &[]);
        pass.set_bind_group(3, &bg, &[]);
        // One workgroup of TILE_PX × TILE_PX per tile.
        let (tx, ty) = m.bins.tiles;
        pass.dispatch_workgroups(tx, ty, 1);
    }
}
