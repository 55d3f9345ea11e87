// Draw segments, shared by the near and mid geometry shaders (appended to prims.wgsl and mesh.wgsl): a draw's
// segments and uniforms, finding an element's segment, and the vertex output both shaders shade.

// One instance's run of primitives (or mesh indices) in an arena, placed at `pos`, drawn through `mask`.
struct Segment {
    // Index of the segment's first element within its draw (a prefix sum of `count`).
    first: u32,
    // First element in the arena (primitives, or mesh indices).
    base: u32,
    // First vertex in the vertex arena (meshes only).
    vbase: u32,
    count: u32,
    pos: vec3<f32>,
    // Dither mask: m >= 0 keeps pixels whose Bayer threshold is below m; m < 0 keeps those at or above -m.
    mask: f32,
};

// Which segments a draw covers, and what it draws.
struct Draw {
    seg_first: u32,
    seg_count: u32,
    kind: u32,
    pad: u32,
};

@group(1) @binding(0) var<storage, read> segments: array<Segment>;
@group(2) @binding(0) var<uniform> draw: Draw;

// What the geometry vertex shaders hand their fragment shaders.
struct GeoOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) color: vec3<f32>,
    @location(3) @interpolate(flat) mask: f32,
};

// The segment holding element `i` of the draw: the last one whose `first` is <= i (binary search).
fn find_segment(i: u32, seg_first: u32, seg_count: u32) -> u32 {
    var lo = seg_first;
    var hi = seg_first + seg_count;
    loop {
        if hi - lo <= 1u {
            break;
        }
        let mid = (lo + hi) / 2u;
        if segments[mid].first <= i {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}
