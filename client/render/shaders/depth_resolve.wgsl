// The multisampled scene's depth resolved to one sample a pixel for the far field (which reads it in its march, or
// tests its boxes against it): the nearest of the pixel's samples (reversed Z: the greatest), so the far field
// stops at whatever covers any part of the pixel.

@group(0) @binding(0) var scene_depth: texture_depth_multisampled_2d;

@vertex
fn vs_resolve(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let uv = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
    return vec4<f32>(uv * 2.0 - 1.0, 0.0, 1.0);
}

@fragment
fn fs_resolve(@builtin(position) frag: vec4<f32>) -> @builtin(frag_depth) f32 {
    let p = vec2<i32>(frag.xy);
    var d = 0.0;
    for (var s = 0; s < i32(textureNumSamples(scene_depth)); s++) {
        d = max(d, textureLoad(scene_depth, p, s));
    }
    return d;
}
