// Sun shadows, read by what receives them (terrain, primitives, meshes: appended to their shaders): the cascaded
// shadow maps the shadow pass drew (`renderer/shadow.rs`) and the sun's visibility at a point.

@group(3) @binding(0) var shadow_map: texture_depth_2d_array;
@group(3) @binding(1) var shadow_sampler: sampler_comparison;

// How much of the sun reaches `world` (surface normal `n`), 0..1: 3 × 3 filtered comparisons in the cascade that
// covers the point, fading to fully lit over the last tenth of the shadow distance.
fn sun_visibility(world: vec3<f32>, n: vec3<f32>) -> f32 {
    let d = distance(world, g.eye.xyz);
    if g.shadow_split.w < 0.5 || d >= g.shadow_split.z {
        return 1.0;
    }
    var c = 0u;
    if d > g.shadow_split.x {
        c = 1u;
    }
    if d > g.shadow_split.y {
        c = 2u;
    }
    // Look up a texel and a half off the surface, along its normal, so that it does not shadow itself.
    let p = world + n * (1.5 * g.shadow_texel[c]);
    let l = g.shadow[c] * vec4<f32>(p, 1.0);
    let uv = vec2<f32>(0.5 + 0.5 * l.x, 0.5 - 0.5 * l.y);
    if any(uv < vec2<f32>(0.0)) || any(uv > vec2<f32>(1.0)) || l.z > 1.0 {
        return 1.0;
    }
    let texel = 1.0 / vec2<f32>(textureDimensions(shadow_map));
    var lit = 0.0;
    for (var y = -1; y <= 1; y++) {
        for (var x = -1; x <= 1; x++) {
            let at = uv + vec2<f32>(f32(x), f32(y)) * texel;
            lit += textureSampleCompareLevel(shadow_map, shadow_sampler, at, c, l.z);
        }
    }
    let fade = smoothstep(0.9 * g.shadow_split.z, g.shadow_split.z, d);
    return mix(lit / 9.0, 1.0, fade);
}
