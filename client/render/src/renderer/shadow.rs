//! The sun's shadow pass: [`SHADOW_CASCADES`] depth maps seen from the sun, each fitted around a slice of the view
//! (the slices growing geometrically out to [`Shadows::distance`]), into which the terrain and the frame's near and
//! mid trees are drawn depth-only, wind included; the scene pass then reads them (`shadow.wgsl`).
//!
//! Inputs: the frame's plan (its terrain chunks, primitive and mesh draws), the camera, the sun. Outputs: the maps
//! (group 3 of the terrain, primitive and mesh pipelines) and the cascades' matrices in the frame's globals.

use glam::{Mat4, Vec3};

use super::Pipelines;
use super::passes::GeometryDraws;
use super::uniforms::Globals;
use crate::camera::Camera;
use crate::{SHADOW_CASCADES, Shadows};

/// Format of the shadow maps (depth from the sun, 0 nearest; cleared to 1, `Less` passes).
pub(crate) const SHADOW_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// Metres beyond a cascade's slice toward the sun that its map still takes casters from (hills and trees between
/// the slice and the sun).
const CASTER_REACH: f32 = 400.0;

/// The weight of the logarithmic split against the uniform one (the "practical" split scheme of cascaded shadow
/// maps): nearer slices are shorter, so that a texel covers about as many pixels in each.
const LOG_SPLIT: f32 = 0.75;

/// One cascade: the sun's view-projection over it, its texel in metres, where its slice ends (metres along the view).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Cascade {
    pub view_proj: Mat4,
    pub texel: f32,
    pub end: f32,
}

/// The cascades for `camera` (target `aspect`, near plane `near`) and the sun in direction `sun` (toward it).
/// Each map is a square around its slice's bounding sphere, from a fixed orientation and moved in whole texels, so
/// that shadows do not shimmer as the camera moves or turns.
pub(super) fn fit_cascades(
    camera: &Camera,
    aspect: f32,
    near: f32,
    sun: Vec3,
    shadows: &Shadows,
) -> [Cascade; SHADOW_CASCADES] {
    let sun = sun.normalize_or(Vec3::Y);
    let (f, r) = (camera.forward(), camera.right());
    let u = r.cross(f);
    let (th, tw) = (camera.tan_half_fov(), camera.tan_half_fov() * aspect);
    let (n, far) = (near.max(0.1), shadows.distance.max(near + 1.0));
    let split = |k: usize| {
        let t = k as f32 / SHADOW_CASCADES as f32;
        LOG_SPLIT * n * (far / n).powf(t) + (1.0 - LOG_SPLIT) * (n + (far - n) * t)
    };
    let up = if sun.y.abs() > 0.99 { Vec3::Z } else { Vec3::Y };
    let light = glam::camera::rh::view::look_to_mat4(Vec3::ZERO, -sun, up);
    let res = shadows.resolution.max(1) as f32;
    std::array::from_fn(|k| {
        let (d0, d1) = (split(k), split(k + 1));
        let centre = camera.position + f * (0.5 * (d0 + d1));
        let radius = [d0, d1]
            .iter()
            .flat_map(|&d| [(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)].map(|(a, b)| (d, a, b)))
            .map(|(d, a, b)| (camera.position + f * d + r * (a * tw * d) + u * (b * th * d) - centre).length())
            .fold(0.0f32, f32::max)
            .ceil();
        let texel = 2.0 * radius / res;
        let c = light.transform_point3(centre);
        let (cx, cy) = ((c.x / texel).round() * texel, (c.y / texel).round() * texel);
        // The view looks down −z: the slice spans −c.z ± radius, casters reach toward the sun beyond it.
        let proj = glam::camera::rh::proj::directx::orthographic(
            cx - radius,
            cx + radius,
            cy - radius,
            cy + radius,
            -c.z - radius - CASTER_REACH,
            -c.z + radius,
        );
        Cascade { view_proj: proj * light, texel, end: d1 }
    })
}

/// The shadow maps, their views and bind groups, and each cascade's globals (the frame's, seen from the sun).
///
/// The farthest cascade is drawn every other frame: between, the frame keeps its map and the matrix it was drawn
/// with (its texels are the coarsest, and what it covers moves least as the camera moves).
pub(super) struct ShadowPass {
    /// The farthest cascade as last drawn, once it has been.
    far: Option<Cascade>,
    /// The farthest cascade this frame draws, if it does (decided by [`ShadowPass::write`]).
    draw_far: Option<Cascade>,
    /// Frames written.
    frames: u64,
    /// One view a cascade, drawn into.
    layers: Vec<wgpu::TextureView>,
    /// Group 3 of the pipelines that receive shadows: the maps as an array and the comparison sampler.
    receive: wgpu::BindGroup,
    /// A globals buffer and bind group a cascade (none where shadows are off).
    globals: Vec<(wgpu::Buffer, wgpu::BindGroup)>,
}

impl ShadowPass {
    /// Maps of `shadows.resolution` texels a side (a 1 × 1 placeholder that the shaders never read when it is 0).
    pub(super) fn new(device: &wgpu::Device, p: &Pipelines, shadows: &Shadows) -> ShadowPass {
        let side = shadows.resolution.max(1);
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("shadow maps"),
            size: wgpu::Extent3d { width: side, height: side, depth_or_array_layers: SHADOW_CASCADES as u32 },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: SHADOW_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            view_formats: &[],
        });
        let layers = (0..SHADOW_CASCADES as u32)
            .map(|k| {
                texture.create_view(&wgpu::TextureViewDescriptor {
                    label: Some("shadow cascade"),
                    dimension: Some(wgpu::TextureViewDimension::D2),
                    base_array_layer: k,
                    array_layer_count: Some(1),
                    ..Default::default()
                })
            })
            .collect();
        let array = texture.create_view(&wgpu::TextureViewDescriptor {
            label: Some("shadow maps"),
            dimension: Some(wgpu::TextureViewDimension::D2Array),
            ..Default::default()
        });
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("shadow comparison"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            compare: Some(wgpu::CompareFunction::LessEqual),
            ..Default::default()
        });
        let receive = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("shadow maps"),
            layout: &p.shadow_layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(&array) },
                wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::Sampler(&sampler) },
            ],
        });
        let globals = (0..if shadows.resolution > 0 { SHADOW_CASCADES } else { 0 })
            .map(|_| super::uniforms::globals_binding(device, &p.globals_layout, "shadow cascade globals"))
            .collect();
        ShadowPass { far: None, draw_far: None, frames: 0, layers, receive, globals }
    }

    /// The receivers' bind group (group 3).
    pub(super) fn receive(&self) -> &wgpu::BindGroup {
        &self.receive
    }

    /// Put `cascades` into the frame's globals `g` (nothing where shadows are off; the farthest as last drawn on
    /// the frames that keep it), and write each cascade's globals: `g` seen from the sun.
    pub(super) fn write(&mut self, queue: &wgpu::Queue, g: &mut Globals, cascades: &[Cascade; SHADOW_CASCADES]) {
        if self.globals.is_empty() {
            return;
        }
        self.frames += 1;
        let mut cascades = *cascades;
        let last = SHADOW_CASCADES - 1;
        self.draw_far = None;
        match self.far {
            Some(kept) if self.frames % 2 == 1 => cascades[last] = kept,
            _ => self.draw_far = Some(cascades[last]),
        }
        for (k, c) in cascades.iter().enumerate() {
            g.shadow[k] = c.view_proj.to_cols_array_2d();
            g.shadow_split[k] = c.end;
            g.shadow_texel[k] = c.texel;
        }
        g.shadow_split[3] = 1.0;
        for ((buffer, _), c) in self.globals.iter().zip(&cascades) {
            let seen = Globals { view_proj: c.view_proj.to_cols_array_2d(), ..*g };
            queue.write_buffer(buffer, 0, bytemuck::bytes_of(&seen));
        }
    }

    /// Draw the casters into each cascade's map (the farthest only on the frames that redraw it).
    pub(super) fn encode(
        &mut self,
        enc: &mut wgpu::CommandEncoder,
        p: &Pipelines,
        cascades: &[GeometryDraws<'_>; SHADOW_CASCADES],
    ) {
        let drawn = if self.draw_far.is_some() { SHADOW_CASCADES } else { SHADOW_CASCADES - 1 };
        if self.draw_far.is_some() {
            self.far = self.draw_far;
        }
        for ((layer, (_, bg)), draws) in self.layers.iter().zip(&self.globals).zip(cascades).take(drawn) {
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("shadow cascade"),
                color_attachments: &[],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: layer,
                    depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(1.0), store: wgpu::StoreOp::Store }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_bind_group(0, bg, &[]);
            draws.terrain(&mut pass, &p.shadow_terrain);
            draws.prims(&mut pass, (&p.shadow_prims, p.shadow_prims_culled.as_ref()), p);
            draws.meshes(&mut pass, &p.shadow_mesh);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cascades_cover_their_slices_and_grow_outward() {
        let camera = Camera::looking_at(Vec3::new(100.0, 40.0, -300.0), Vec3::new(180.0, 20.0, -100.0), 60.0);
        let shadows = Shadows { resolution: 1024, distance: 300.0 };
        let sun = Vec3::new(-0.55, 0.75, 0.45);
        let cs = fit_cascades(&camera, 16.0 / 9.0, 0.25, sun, &shadows);
        assert!((cs[2].end - 300.0).abs() < 1e-3, "{cs:?}");
        for k in 0..SHADOW_CASCADES {
            if k > 0 {
                assert!(cs[k].end > cs[k - 1].end && cs[k].texel > cs[k - 1].texel, "{cs:?}");
            }
            // Points of the slice's far end land inside the map, within depth 0..1.
            let d = cs[k].end;
            for (a, b) in [(-1.0, -1.0), (1.0, 1.0), (0.0, 0.0), (1.0, -1.0)] {
                let t = camera.tan_half_fov();
                let u = camera.right().cross(camera.forward());
                let p = camera.position
                    + camera.forward() * d
                    + camera.right() * (a * t * 16.0 / 9.0 * d)
                    + u * (b * t * d);
                let q = cs[k].view_proj.project_point3(p);
                assert!(q.x.abs() <= 1.0 && q.y.abs() <= 1.0 && (0.0..=1.0).contains(&q.z), "cascade {k}: {q}");
                // A caster 50 m toward the sun from it is nearer the sun, and still in the map.
                let c = cs[k].view_proj.project_point3(p + sun.normalize() * 50.0);
                assert!(c.z < q.z && c.z >= 0.0, "cascade {k}: {c} {q}");
            }
        }
        // Each cascade's volume holds the points of its slice and not those far beside it.
        for c in &cs {
            let f = crate::camera::Frustum::from_matrix(c.view_proj);
            let p = camera.position + camera.forward() * c.end;
            assert!(f.sphere_visible(p, 0.1), "{c:?}");
            assert!(!f.sphere_visible(p + camera.right() * (4.0 * c.end), 0.1), "{c:?}");
        }
        // Moving the camera a fraction of a texel moves no map by a fraction of a texel.
        let mut moved = camera;
        moved.position += Vec3::new(0.013, 0.0, 0.007);
        let ms = fit_cascades(&moved, 16.0 / 9.0, 0.25, sun, &shadows);
        for (a, b) in cs.iter().zip(&ms) {
            let shift =
                (a.view_proj.project_point3(Vec3::ZERO) - b.view_proj.project_point3(Vec3::ZERO)) * 0.5 * 1024.0;
            assert!((shift.x - shift.x.round()).abs() < 0.02 && (shift.y - shift.y.round()).abs() < 0.02, "{shift}");
        }
    }
}
