//! The frame's render passes, each with its inputs and outputs named (the shadow pass is `shadow.rs`, the far
//! field's compute march `far_march.rs`): [`ScenePass`] (sky, terrain, primitives, meshes into the target, through
//! [`Msaa`] where multisampled), [`resolve_depth`] (the scene's depth for the far field), the far field as boxes
//! ([`Renderer::raster_far_field`]), and [`composite`] (the far field laid over the scene). [`GeometryDraws`] is what
//! the scene and shadow passes both draw.

use super::GeometryGpu;
use super::cull::Culled;
use super::timing::{Part, PassTimer};
use super::{
    DEPTH_FORMAT, DRAW_STRIDE, FarInstance, GpuCore, PROXY_BOX_VERTICES, Pipelines, Renderer, SKY_VERTICES, TerrainGpu,
    ViewDraws,
};

/// One view's opaque geometry as a pass draws it, with whatever view its group 0 holds: the scene pass from the
/// camera, the shadow pass from the sun.
pub(super) struct GeometryDraws<'a> {
    pub draws: &'a ViewDraws,
    pub geometry: &'a GeometryGpu,
    pub terrain: Option<&'a TerrainGpu>,
    /// The primitives the GPU cull kept of `draws` (the camera's, where it culls), drawn indirectly.
    pub culled: Option<&'a Culled<'a>>,
}

impl GeometryDraws<'_> {
    /// The terrain chunks the plan chose.
    pub(super) fn terrain(&self, pass: &mut wgpu::RenderPass<'_>, pipeline: &wgpu::RenderPipeline) {
        let Some(t) = self.terrain else { return };
        pass.set_pipeline(pipeline);
        pass.set_vertex_buffer(0, t.vertices.slice(..));
        pass.set_index_buffer(t.indices.slice(..), wgpu::IndexFormat::Uint32);
        for r in &self.draws.terrain {
            pass.draw_indexed(r.clone(), 0, 0..1);
        }
    }

    /// The instanced primitives: a draw per unit shape and tessellation, through `whole`, or where the GPU culled
    /// them, through `culled` with the arguments the cull wrote.
    pub(super) fn prims(
        &self,
        pass: &mut wgpu::RenderPass<'_>,
        (whole, culled): (&wgpu::RenderPipeline, Option<&wgpu::RenderPipeline>),
        p: &Pipelines,
    ) {
        let (false, Some(bg)) = (self.draws.prims.is_empty(), &self.geometry.prims_bg) else { return };
        let culled = self.culled.zip(culled);
        match culled {
            Some((c, culled_pipeline)) => {
                pass.set_pipeline(culled_pipeline);
                pass.set_bind_group(1, &c.bg, &[]);
            }
            None => {
                pass.set_pipeline(whole);
                pass.set_bind_group(1, bg, &[]);
            }
        }
        for (k, d) in self.draws.prims.iter().enumerate() {
            let mesh = p.unit_mesh(d.shape, d.tess);
            pass.set_bind_group(2, &self.geometry.draw_bg, &[(u64::from(d.slot) * DRAW_STRIDE) as u32]);
            pass.set_vertex_buffer(0, mesh.vertices.slice(..));
            pass.set_index_buffer(mesh.indices.slice(..), wgpu::IndexFormat::Uint16);
            match culled {
                Some((c, _)) => pass.draw_indexed_indirect(c.args, k as u64 * super::cull::ARGS_BYTES),
                None => pass.draw_indexed(0..mesh.index_count, 0, 0..d.instances),
            }
        }
    }

    /// The meshes: one draw.
    pub(super) fn meshes(&self, pass: &mut wgpu::RenderPass<'_>, pipeline: &wgpu::RenderPipeline) {
        let (Some((slot, count)), Some(bg)) = (self.draws.mesh, &self.geometry.mesh_bg) else { return };
        pass.set_pipeline(pipeline);
        pass.set_bind_group(1, bg, &[]);
        pass.set_bind_group(2, &self.geometry.draw_bg, &[(u64::from(slot) * DRAW_STRIDE) as u32]);
        pass.draw(0..count, 0..1);
    }
}

/// The scene pass's multisampled colour and depth (the colour resolved into the frame's target, the depth into
/// [`GpuCore::depth`] by the depth resolve), and the depth's bind group for that resolve.
pub(super) struct Msaa {
    pub color: wgpu::TextureView,
    pub depth: wgpu::TextureView,
    pub resolve_bg: wgpu::BindGroup,
}

impl Msaa {
    pub(super) fn new(
        device: &wgpu::Device,
        p: &Pipelines,
        format: wgpu::TextureFormat,
        (w, h): (u32, u32),
        samples: u32,
    ) -> Msaa {
        let target = |label, format, usage| {
            device
                .create_texture(&wgpu::TextureDescriptor {
                    label: Some(label),
                    size: wgpu::Extent3d { width: w.max(1), height: h.max(1), depth_or_array_layers: 1 },
                    mip_level_count: 1,
                    sample_count: samples,
                    dimension: wgpu::TextureDimension::D2,
                    format,
                    usage: wgpu::TextureUsages::RENDER_ATTACHMENT | usage,
                    view_formats: &[],
                })
                .create_view(&wgpu::TextureViewDescriptor::default())
        };
        let color = target("multisampled colour", format, wgpu::TextureUsages::empty());
        let depth = target("multisampled depth", DEPTH_FORMAT, wgpu::TextureUsages::TEXTURE_BINDING);
        let resolve_bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("scene depth"),
            layout: &p.resolve_layout,
            entries: &[wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(&depth) }],
        });
        Msaa { color, depth, resolve_bg }
    }
}

/// The scene pass. Inputs: the camera's draws, the frame's globals (group 0), the sun's shadow maps (group 3).
/// Outputs: the target's colour (resolved from [`Msaa`] where there is one) and, where `keep_depth`, the scene's
/// depth for the far field.
pub(super) struct ScenePass<'a> {
    pub gpu: &'a GpuCore,
    pub target: &'a wgpu::TextureView,
    pub draws: GeometryDraws<'a>,
    pub shadows: &'a wgpu::BindGroup,
    /// The sky's colour at the horizon, the clear colour.
    pub sky: [f32; 3],
    pub keep_depth: bool,
}

impl ScenePass<'_> {
    /// Encode the pass; the timer's parts from the shadows' end to the meshes' (and the far field's and the
    /// composite's, empty, where there is no far field).
    pub(super) fn encode(self, enc: &mut wgpu::CommandEncoder, timer: Option<&PassTimer>) {
        let (gpu, hz) = (self.gpu, self.sky);
        let done = |pass: &mut wgpu::RenderPass<'_>, part| {
            if let Some(t) = timer {
                t.done(pass, part);
            }
        };
        let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("scene"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: gpu.msaa.as_ref().map_or(self.target, |m| &m.color),
                depth_slice: None,
                resolve_target: gpu.msaa.as_ref().map(|_| self.target),
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color {
                        r: hz[0].into(),
                        g: hz[1].into(),
                        b: hz[2].into(),
                        a: 1.0,
                    }),
                    // Multisampled, only the resolved colour is kept.
                    store: if gpu.msaa.is_some() { wgpu::StoreOp::Discard } else { wgpu::StoreOp::Store },
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: gpu.msaa.as_ref().map_or(&gpu.depth, |m| &m.depth),
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(0.0),
                    // The far field is depth-tested against the scene after this pass.
                    store: if self.keep_depth { wgpu::StoreOp::Store } else { wgpu::StoreOp::Discard },
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_bind_group(0, &gpu.globals_bg, &[]);
        pass.set_bind_group(3, self.shadows, &[]);
        pass.set_pipeline(&gpu.p.sky);
        pass.draw(0..SKY_VERTICES, 0..1);
        self.draws.terrain(&mut pass, &gpu.p.terrain);
        done(&mut pass, Part::Terrain);
        self.draws.prims(&mut pass, (&gpu.p.prims, gpu.p.prims_culled.as_ref()), &gpu.p);
        done(&mut pass, Part::Primitives);
        self.draws.meshes(&mut pass, &gpu.p.mesh);
        done(&mut pass, Part::Meshes);
        if !self.keep_depth {
            done(&mut pass, Part::FarField);
            done(&mut pass, Part::Composite);
        }
    }
}

/// A pass that writes only `depth`, cleared first (to 0: reversed Z, the farthest).
pub(super) fn depth_pass<'e>(
    enc: &'e mut wgpu::CommandEncoder,
    depth: &wgpu::TextureView,
    label: &str,
) -> wgpu::RenderPass<'e> {
    enc.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some(label),
        color_attachments: &[],
        depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
            view: depth,
            depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(0.0), store: wgpu::StoreOp::Store }),
            stencil_ops: None,
        }),
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    })
}

/// The depth resolve, where the scene pass is multisampled. Input: the multisampled depth. Output: the nearest
/// sample of each pixel in [`GpuCore::depth`], which the far field reads.
pub(super) fn resolve_depth(gpu: &GpuCore, enc: &mut wgpu::CommandEncoder) {
    let (Some(m), Some(resolve)) = (&gpu.msaa, &gpu.p.depth_resolve) else { return };
    let mut pass = depth_pass(enc, &gpu.depth, "depth resolve");
    pass.set_pipeline(resolve);
    pass.set_bind_group(0, &m.resolve_bg, &[]);
    pass.draw(0..SKY_VERTICES, 0..1);
}

impl Renderer {
    /// The far field as boxes (the raster path). Inputs: the far instances and forest patches, the scene's depth.
    /// Output: the accumulation target.
    pub(super) fn raster_far_field(&self, enc: &mut wgpu::CommandEncoder, far_count: u32) {
        let gpu = &self.gpu;
        enc.clear_buffer(&gpu.accum.opacity, 0, None);
        let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("far field"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &gpu.accum.target,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &gpu.depth,
                depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Discard }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_bind_group(0, &gpu.globals_bg, &[]);
        pass.set_bind_group(3, &gpu.accum.opacity_bg, &[]);
        if let (true, Some(bg)) = (far_count > 0, &self.far.bg) {
            pass.set_pipeline(&gpu.p.volume);
            pass.set_bind_group(1, bg, &[]);
            let bytes = u64::from(far_count) * size_of::<FarInstance>() as u64;
            pass.set_vertex_buffer(0, self.far.instances.buffer.slice(..bytes));
            pass.draw(0..PROXY_BOX_VERTICES, 0..far_count);
        }
        self.draw_forest(&mut pass);
        if let Some(t) = &self.timer {
            t.done(&mut pass, Part::FarField);
        }
    }
}

/// The composite. Input: the far field's accumulation target. Output: the target, the far field laid over the scene.
pub(super) fn composite(
    gpu: &GpuCore,
    target: &wgpu::TextureView,
    enc: &mut wgpu::CommandEncoder,
    timer: Option<&PassTimer>,
) {
    let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("far-field composite"),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view: target,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store },
        })],
        depth_stencil_attachment: None,
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    pass.set_pipeline(&gpu.p.composite);
    pass.set_bind_group(0, &gpu.accum.composite_bg, &[]);
    pass.draw(0..SKY_VERTICES, 0..1);
    if let Some(t) = timer {
        t.done(&mut pass, Part::Composite);
    }
}
