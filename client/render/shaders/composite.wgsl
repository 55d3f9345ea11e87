// The far field's accumulation target (premultiplied, composited front to back) laid over the scene: a
// full-screen triangle.

@group(0) @binding(0) var accum: texture_2d<f32>;

@vertex
fn vs_composite(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

@fragment
fn fs_composite(@builtin(position) frag: vec4<f32>) -> @location(0) vec4<f32> {
    let c = textureLoad(accum, vec2<i32>(frag.xy), 0);
    if c.a <= 0.0 {
        discard;
    }
    return c;
}
