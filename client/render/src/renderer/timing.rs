//! GPU time per part of a frame (sky and terrain, primitives, meshes, the far field, its composite) from timestamp queries written inside the frame's render passes — where the adapter offers them
//! (`canopy render --frames N` reports them). A tiling or software rasteriser (Mesa's lavapipe) runs a pass's
//! fragments at its end, so there only the whole is meaningful.

/// The parts of a frame timed, in drawing order (the far field, instances and forest, counts from the end of the
/// scene pass).
pub const PARTS: [&str; 5] = ["sky+terrain", "primitives", "meshes", "far field", "composite"];

/// Timestamps: one before the first part and one after each.
pub(super) const STAMPS: u32 = PARTS.len() as u32 + 1;

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

    /// Write timestamp `index` (0 before the first part, `k + 1` after part `k`).
    pub(super) fn stamp(&self, pass: &mut wgpu::RenderPass<'_>, index: u32) {
        pass.write_timestamp(&self.set, index);
    }

    /// The same between passes.
    pub(super) fn stamp_encoder(&self, enc: &mut wgpu::CommandEncoder, index: u32) {
        enc.write_timestamp(&self.set, index);
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
        let (tx, rx) = std::sync::mpsc::channel();
        self.read.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        device.poll(wgpu::PollType::Wait { submission_index: None, timeout: None }).ok()?;
        rx.recv().ok()?.ok()?;
        let ticks: Vec<u64> = {
            let view = self.read.get_mapped_range(..).ok()?;
            view.chunks_exact(8).map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes"))).collect()
        };
        self.read.unmap();
        let mut ms = [0.0; PARTS.len()];
        for (k, m) in ms.iter_mut().enumerate() {
            *m = ticks[k + 1].saturating_sub(ticks[k]) as f64 * self.period / 1e6;
        }
        Some(ms)
    }
}
