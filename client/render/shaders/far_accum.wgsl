// The far field's accumulation (far instances, then forest patches, front to back; `src/renderer.rs`): each pixel's
// opacity so far, composited in front, kept beside the accumulation target so that a fragment behind an opaque
// pixel stops before its march and a march stops once the pixel is opaque. Fragments of one pass may run at once:
// a fragment reads what was finished when it started, never more than the truth (the pixel's opacity only grows,
// and each write is the opacity in front it read composited with its own), so at worst it works more.

@group(3) @binding(0) var<storage, read_write> opacity: array<atomic<u32>>;

// Opacity at which a ray stops (the march's early exit; what lies behind adds less than half a percent).
const OPAQUE: f32 = 0.995;

fn pixel_index(frag: vec2<f32>) -> u32 {
    return u32(frag.y) * u32(g.viewport.x) + u32(frag.x);
}

// The opacity composited in front of this fragment so far (a non-negative float's bits order as the float).
fn opacity_in_front(pixel: u32) -> f32 {
    return bitcast<f32>(atomicLoad(&opacity[pixel]));
}

// The fragment's own opacity at which the pixel becomes opaque, given `front`.
fn stop_alpha(front: f32) -> f32 {
    return 1.0 - (1.0 - OPAQUE) / max(1.0 - front, 1.0 - OPAQUE);
}

// Composite the fragment's `alpha` behind `front` into the pixel's opacity.
fn add_opacity(pixel: u32, front: f32, alpha: f32) {
    atomicMax(&opacity[pixel], bitcast<u32>(1.0 - (1.0 - front) * (1.0 - alpha)));
}
