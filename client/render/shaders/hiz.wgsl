// The occlusion pyramid the GPU cull tests against (renderer/cull.rs): the terrain's depth drawn from the camera,
// halved level by level, each texel the farthest depth (reversed Z: the least) of the four beneath it. The levels lie
// one after another in a storage buffer, row by row (a buffer rather than a texture's mips: a load's level then
// varies freely between invocations, which some drivers' texture loads do not honour). Level 0 is half the
// depth buffer's size rounded up to powers of two (the texels past its edge repeat it), so that each level is exactly
// half the one beneath.

// One level: where its source and it lie in the pyramid, and their sizes.
struct Level {
    src_offset: u32,
    src_w: u32,
    src_h: u32,
    dst_offset: u32,
    dst_w: u32,
    dst_h: u32,
    pad0: u32,
    pad1: u32,
};

@group(0) @binding(0) var src_depth: texture_depth_2d;
@group(0) @binding(1) var<storage, read_write> pyramid: array<f32>;
@group(0) @binding(2) var<uniform> level: Level;

fn store(id: vec2<u32>, a: f32, b: f32, c: f32, d: f32) {
    pyramid[level.dst_offset + id.y * level.dst_w + id.x] = min(min(a, b), min(c, d));
}

// Level 0, from the depth buffer.
@compute @workgroup_size(8, 8)
fn cs_hiz_depth(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= level.dst_w || id.y >= level.dst_h {
        return;
    }
    let last = vec2<i32>(textureDimensions(src_depth)) - 1;
    let p = vec2<i32>(id.xy) * 2;
    let a = textureLoad(src_depth, min(p, last), 0);
    let b = textureLoad(src_depth, min(p + vec2<i32>(1, 0), last), 0);
    let c = textureLoad(src_depth, min(p + vec2<i32>(0, 1), last), 0);
    let d = textureLoad(src_depth, min(p + vec2<i32>(1, 1), last), 0);
    store(id.xy, a, b, c, d);
}

fn src_at(x: u32, y: u32) -> f32 {
    return pyramid[level.src_offset + min(y, level.src_h - 1u) * level.src_w + min(x, level.src_w - 1u)];
}

// Every level above, from the one beneath.
@compute @workgroup_size(8, 8)
fn cs_hiz_level(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= level.dst_w || id.y >= level.dst_h {
        return;
    }
    let p = id.xy * 2u;
    store(id.xy, src_at(p.x, p.y), src_at(p.x + 1u, p.y), src_at(p.x, p.y + 1u), src_at(p.x + 1u, p.y + 1u));
}
