//! GPU time per part of a frame ([`Part`]: the cull, the sun's shadow maps, sky and terrain, primitives, meshes, the far
//! field, its composite) from timestamp queries written between and inside the frame's passes — where the adapter
//! offers them (`canopy render --frames N` reports them). A tiling or software rasteriser (Mesa's lavapipe) runs a
//! pass's fragments at its end, so there only the whole is meaningful.

/// A part of a frame timed, in drawing order. Its time runs from the end of the previous part (the frame's start
/// for the first) to the stamp [`PassTimer::done`] writes for it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Part {
    /// The GPU cull: the terrain's depth, the occlusion pyramid and the cull's passes (`cull.rs`; 0 where the CPU
    /// culls).
    Cull,
    /// The sun's shadow maps (every cascade).
    Shadows,
    /// The sky and the terrain.
    Terrain,
    /// The near and mid trees' instanced primitives.
    Primitives,
    /// Their meshes (leaves, trunk bases, merged trees).
    Meshes,
    /// Far instances and forest patches (counts from the end of the scene pass).
    FarField,
    /// The far field laid over the scene.
    Composite,
}

/// The parts' names, in drawing order.
pub const PARTS: [&str; 7] = ["cull", "shadows", "sky+terrain", "primitives", "meshes", "far field", "composite"];

/// Timestamps: one at the frame's start and one after each part.
const STAMPS: u32 = PARTS.len() as u32 + 1;

/// The features a device needs for [`PassTimer`].
pub const FEATURES: wgpu::Features = wgpu::Features::TIMESTAMP_QUERY
    .union(wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS)
    .union(wgpu::Features::TIMESTAMP_QUERY_INSIDE_PASSES);

/// The query set, its resolve buffer and a mappable copy.
pub(super) struct PassTimer {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: wgpu::Buffer,
    /// Nanoseconds per timestamp tick.
    period: f64,
    /// Whether the last frame wrote timestamps that were not read yet.
    pending: bool,
}

impl PassTimer {
    /// A timer for `device`, or `None` where it lacks [`FEATURES`].
    pub(super) fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Option<PassTimer> {
        if !device.features().contains(FEATURES) {
            return None;
        }
        let set = device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("pass timer"),
            ty: wgpu::QueryType::Timestamp,
            count: STAMPS,
        });
        let bytes = u64::from(STAMPS) * wgpu::QUERY_SIZE as u64;
        let buffer = |label, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage,
                mapped_at_creation: false,
            })
        };
        let resolve = buffer("pass timer resolve", wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC);
        let read = buffer("pass timer read", wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST);
        Some(PassTimer { set, resolve, read, period: f64::from(queue.get_timestamp_period()), pending: false })
    }

    /// The frame starts (between passes).
    pub(super) fn start(&self, enc: &mut wgpu::CommandEncoder) {
        enc.write_timestamp(&self.set, 0);
    }

    /// `part` is done, inside a render pass.
    pub(super) fn done(&self, pass: &mut wgpu::RenderPass<'_>, part: Part) {
        pass.write_timestamp(&self.set, part as u32 + 1);
    }

    /// `part` is done, between passes.
    pub(super) fn done_between(&self, enc: &mut wgpu::CommandEncoder, part: Part) {
        enc.write_timestamp(&self.set, part as u32 + 1);
    }

    /// After the pass: resolve the timestamps into the mappable buffer.
    pub(super) fn resolve(&mut self, enc: &mut wgpu::CommandEncoder) {
        enc.resolve_query_set(&self.set, 0..STAMPS, &self.resolve, 0);
        enc.copy_buffer_to_buffer(&self.resolve, 0, &self.read, 0, self.resolve.size());
        self.pending = true;
    }

    /// Milliseconds of each part of the last frame submitted, once the GPU finished it (blocks until then); `None`
    /// if no frame was timed since the last read.
    pub(super) fn read(&mut self, device: &wgpu::Device) -> Option<[f64; PARTS.len()]> {
        if !std::mem::take(&mut self.pending) {
            return None;
        }
        let ticks: Vec<u64> = read_mapped(device, &self.read)?
            .chunks_exact(8)
            .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
            .collect();
        let mut ms = [0.0; PARTS.len()];
        for (k, m) in ms.iter_mut().enumerate() {
            *m = ticks[k + 1].saturating_sub(ticks[k]) as f64 * self.period / 1e6;
        }
        Some(ms)
    }
}

/// The bytes of a mappable buffer once the GPU finished what was submitted (blocks until then); `None` where mapping
/// fails.
pub(super) fn read_mapped(device: &wgpu::Device, buffer: &wgpu::Buffer) -> Option<Vec<u8>> {
    let (tx, rx) = std::sync::mpsc::channel();
    buffer.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    device.poll(wgpu::PollType::Wait { submission_index: None, timeout: None }).ok()?;
    rx.recv().ok()?.ok()?;
    let bytes = buffer.get_mapped_range(..).ok()?.to_vec();
    buffer.unmap();
    Some(bytes)
}
