//! The uniform and storage structs the renderer shares with its WGSL shaders, and the test that holds each to the
//! shader's layout of it (field by field, parsed from the shaders by naga).

use bytemuck::{Pod, Zeroable};

/// The frame's globals (`common.wgsl` `Globals`): camera, light, sky, wind and the sun's shadow cascades.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct Globals {
    pub view_proj: [[f32; 4]; 4],
    pub inv_view_proj: [[f32; 4]; 4],
    pub eye: [f32; 4],
    pub sun_dir: [f32; 4],
    pub sun_color: [f32; 4],
    pub sky_zenith: [f32; 4],
    pub sky_horizon: [f32; 4],
    pub viewport: [f32; 4],
    pub wind: [f32; 4],
    pub shadow_split: [f32; 4],
    pub shadow_texel: [f32; 4],
    pub haze: [f32; 4],
    pub shadow: [[[f32; 4]; 4]; crate::SHADOW_CASCADES],
}

/// A buffer for the frame's [`Globals`] and its bind group (group 0, `layout`): the camera's, or a shadow
/// cascade's.
pub(super) fn globals_binding(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    label: &str,
) -> (wgpu::Buffer, wgpu::BindGroup) {
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: size_of::<Globals>() as u64,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout,
        entries: &[wgpu::BindGroupEntry { binding: 0, resource: buffer.as_entire_binding() }],
    });
    (buffer, bg)
}

/// A far-field volume's place in the atlas and its box (`volume_info.wgsl` `VolumeInfo`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(super) struct VolumeInfo {
    pub atlas: [u32; 4],
    pub dims: [u32; 4],
    pub voxel: [f32; 4],
    pub lo: [f32; 4],
    pub hi: [f32; 4],
    pub origin: [f32; 4],
}

#[cfg(test)]
mod tests {
    use super::super::cull::{CullDraw, CullParams, HizLevel};
    use super::*;
    use crate::forest::ForestPatch;
    use crate::geometry::PrimInstance;
    use crate::select::{DrawUniform, Segment};

    /// A struct's size and its members' (name, offset), as naga lays out `name` in `source`.
    fn wgsl_layout(source: &str, name: &str) -> (u32, Vec<(String, u32)>) {
        let module = naga::front::wgsl::parse_str(source).unwrap_or_else(|e| panic!("{}", e.emit_to_string(source)));
        let ty = module.types.iter().find(|(_, t)| t.name.as_deref() == Some(name)).expect("the struct");
        let naga::TypeInner::Struct { members, span } = &ty.1.inner else { panic!("{name} is not a struct") };
        (*span, members.iter().map(|m| (m.name.clone().unwrap_or_default(), m.offset)).collect())
    }

    /// `Type { wgsl_member: rust_field, … }`: the Rust struct's size and (WGSL member name, Rust offset).
    macro_rules! rust_layout {
        ($t:ty { $($w:ident : $r:ident),* $(,)? }) => {
            (size_of::<$t>() as u32, vec![$((stringify!($w).to_string(), std::mem::offset_of!($t, $r) as u32)),*])
        };
    }

    const COMMON: &str = include_str!("../../shaders/common.wgsl");

    #[test]
    fn shared_structs_match_their_wgsl_layouts() {
        let segment = crate::pipelines::PRIMS_PARTS.concat();
        let mesh = crate::pipelines::MESH_PARTS.concat();
        let info = include_str!("../../shaders/volume_info.wgsl");
        let forest = crate::pipelines::forest_source();
        let cull = super::super::cull::cull_source();
        let cases = [
            (
                wgsl_layout(COMMON, "Globals"),
                rust_layout!(Globals {
                    view_proj: view_proj,
                    inv_view_proj: inv_view_proj,
                    eye: eye,
                    sun_dir: sun_dir,
                    sun_color: sun_color,
                    sky_zenith: sky_zenith,
                    sky_horizon: sky_horizon,
                    viewport: viewport,
                    wind: wind,
                    shadow_split: shadow_split,
                    shadow_texel: shadow_texel,
                    haze: haze,
                    shadow: shadow,
                }),
            ),
            (
                wgsl_layout(&segment, "Segment"),
                rust_layout!(Segment {
                    first: first,
                    base: base,
                    vbase: vbase,
                    count: count,
                    pos: pos,
                    mask: mask,
                    seed: seed,
                    crown_y: crown,
                    pad0: pad,
                }),
            ),
            (
                wgsl_layout(&mesh, "Draw"),
                rust_layout!(DrawUniform {
                    seg_first: seg_first,
                    seg_count: seg_count,
                    kind: kind,
                    visible_base: visible_base,
                }),
            ),
            (
                wgsl_layout(info, "VolumeInfo"),
                rust_layout!(VolumeInfo { atlas: atlas, dims: dims, voxel: voxel, lo: lo, hi: hi, origin: origin }),
            ),
            (wgsl_layout(&segment, "Prim"), rust_layout!(PrimInstance { r0: rows, shape: shape })),
            (
                wgsl_layout(&cull, "CullDraw"),
                rust_layout!(CullDraw {
                    seg_first: seg_first,
                    seg_count: seg_count,
                    instances: instances,
                    block_first: block_first,
                    visible_base: visible_base,
                    index_count: index_count,
                    kind: kind,
                    pad: pad,
                }),
            ),
            (
                wgsl_layout(&cull, "CullParams"),
                rust_layout!(CullParams {
                    planes: planes,
                    eye: eye,
                    limits: limits,
                    counts: counts,
                    pyramid_size: pyramid_size,
                }),
            ),
            (
                wgsl_layout(include_str!("../../shaders/hiz.wgsl"), "Level"),
                rust_layout!(HizLevel {
                    src_offset: src_offset,
                    src_w: src_w,
                    src_h: src_h,
                    dst_offset: dst_offset,
                    dst_w: dst_w,
                    dst_h: dst_h,
                    pad0: pad,
                }),
            ),
        ];
        for ((wsize, wmembers), (rsize, rmembers)) in cases {
            assert_eq!(wsize, rsize, "sizes differ: WGSL {wmembers:?}, Rust {rmembers:?}");
            for (name, offset) in rmembers {
                let w = wmembers.iter().find(|(n, _)| *n == name).unwrap_or_else(|| panic!("no WGSL member {name}"));
                assert_eq!(w.1, offset, "member {name}: WGSL offset {}, Rust {offset}", w.1);
            }
        }
        // A forest patch is read word by word (`far_march.wgsl` `load_patch`): its members where `Patch` has them,
        // and as many words as the Rust struct has.
        let (_, wmembers) = wgsl_layout(&forest, "Patch");
        let (rsize, rmembers) = rust_layout!(ForestPatch {
            rect: rect,
            span: span,
            cover: cover,
            field: field,
            ids: ground,
            params: scale,
            profile: profile,
            layer_from: layer_from,
            mip_scale: mip_scale,
            edges_x: edges_x,
            edges_z: edges_z,
        });
        assert_eq!(rmembers, wmembers);
        let words = format!("let b = i * {}u;", rsize / 4);
        assert!(include_str!("../../shaders/far_march.wgsl").contains(&words), "`load_patch` reads {words}");
    }
}
