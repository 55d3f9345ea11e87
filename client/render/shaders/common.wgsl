// Shared by every Canopy shader (prepended by the renderer): frame globals, fog, sky, dithering.

struct Globals {
    view_proj: mat4x4<f32>,
    inv_view_proj: mat4x4<f32>,
    // xyz: eye position; w: unused.
    eye: vec4<f32>,
    // xyz: unit direction toward the sun; w: ambient intensity.
    sun_dir: vec4<f32>,
    // rgb: sun colour; w: diffuse coefficient.
    sun_color: vec4<f32>,
    // rgb: sky at the zenith; w: fog density per metre.
    sky_zenith: vec4<f32>,
    // rgb: sky at the horizon and fog colour; w: unused.
    sky_horizon: vec4<f32>,
    // width, height, 1/width, 1/height of the target.
    viewport: vec4<f32>,
    // xy: horizontal direction the wind blows toward (x, z), unit; z: strength (0: still); w: time, seconds.
    wind: vec4<f32>,
    // xyz: distance from the eye where each shadow cascade ends; w: 1 when shadows are on.
    shadow_split: vec4<f32>,
    // xyz: each cascade's texel, metres; w: unused.
    shadow_texel: vec4<f32>,
    // Each cascade's view-projection from the sun (depth 0..1, nearest the sun 0).
    shadow: array<mat4x4<f32>, 3>,
};

@group(0) @binding(0) var<uniform> g: Globals;

fn bayer4(p: vec2<f32>) -> f32 {
    let m = array<f32, 16>(0.0, 8.0, 2.0, 10.0, 12.0, 4.0, 14.0, 6.0, 3.0, 11.0, 1.0, 9.0, 15.0, 7.0, 13.0, 5.0);
    let x = u32(p.x) & 3u;
    let y = u32(p.y) & 3u;
    return (m[y * 4u + x] + 0.5) / 16.0;
}

fn dither_keeps(mask: f32, frag: vec2<f32>) -> bool {
    let b = bayer4(frag);
    if mask >= 0.0 {
        return b < mask;
    }
    return b >= -mask;
}

fn fog_factor(dist: f32) -> f32 {
    return 1.0 - exp(-g.sky_zenith.w * dist);
}

fn with_fog(c: vec3<f32>, world: vec3<f32>) -> vec3<f32> {
    let f = fog_factor(distance(world, g.eye.xyz));
    return mix(c, g.sky_horizon.rgb, f);
}

// Lambert with the sun plus ambient light, the same model the far field's baked shading uses.
fn shade(base: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    return shade_lit(base, n, 1.0);
}

// `shade` where `sun` of the sun's light arrives (shadow.wgsl `sun_visibility`).
fn shade_lit(base: vec3<f32>, n: vec3<f32>, sun: f32) -> vec3<f32> {
    let lambert = sun * max(dot(n, g.sun_dir.xyz), 0.0);
    // A little sky light from above so that faces turned from the sun keep their shape (`Lighting::sky_light`).
    let sky = g.sky_horizon.w * (0.5 + 0.5 * n.y);
    return base * (g.sun_dir.w + sky + g.sun_color.w * lambert * g.sun_color.rgb);
}

// An instance's own shade of its species' colours, from the top byte of its folded seed (select.rs `fold_seed`):
// brightness ×0.87..1.11 from the low nibble, a shift toward yellow or blue of about ±5 % from the high one; 0x88
// is the species' colours as they are. Near, mid and far draw the same tint, so a tree keeps its shade across its
// levels.
fn instance_tint(seed: u32) -> vec3<f32> {
    let b = f32((seed >> 24u) & 15u) - 8.0;
    let h = f32(seed >> 28u) - 8.0;
    return vec3<f32>(1.0 + 0.006 * h, 1.0, 1.0 - 0.006 * h) * (1.0 + 0.016 * b);
}

fn sky_color(dir: vec3<f32>) -> vec3<f32> {
    let up = clamp(dir.y, 0.0, 1.0);
    return mix(g.sky_horizon.rgb, g.sky_zenith.rgb, sqrt(up));
}
