// Shared by every Canopy shader (prepended by the renderer): frame globals, haze, sky, dithering.

struct Globals {
    view_proj: mat4x4<f32>,
    inv_view_proj: mat4x4<f32>,
    // xyz: eye position; w: unused.
    eye: vec4<f32>,
    // xyz: unit direction toward the sun; w: ambient intensity.
    sun_dir: vec4<f32>,
    // rgb: sun colour; w: diffuse coefficient.
    sun_color: vec4<f32>,
    // rgb: sky at the zenith; w: haze density per metre at height 0.
    sky_zenith: vec4<f32>,
    // rgb: sky at the horizon and the colour of thick haze; w: the sky's light on surfaces.
    sky_horizon: vec4<f32>,
    // width, height, 1/width, 1/height of the target.
    viewport: vec4<f32>,
    // xy: horizontal direction the wind blows toward (x, z), unit; z: strength (0: still); w: time, seconds.
    wind: vec4<f32>,
    // xyz: distance from the eye where each shadow cascade ends; w: 1 when shadows are on.
    shadow_split: vec4<f32>,
    // xyz: each cascade's texel, metres; w: unused.
    shadow_texel: vec4<f32>,
    // x: the haze's scale height, metres (0: the same density at every height); y: the sun's glow through it;
    // z: the most ambient occlusion deep in a crown (segment.wgsl `crown_occlusion`); w: unused.
    haze: vec4<f32>,
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

// Whether a dither mask keeps the threshold `t` (0..1): m >= 0 keeps those below m, m < 0 those at or above -m, so
// the two levels of a cross-fade (m and -m) share nothing and leave nothing out.
fn mask_keeps(mask: f32, t: f32) -> bool {
    if mask >= 0.0 {
        return t < mask;
    }
    return t >= -mask;
}

fn dither_keeps(mask: f32, frag: vec2<f32>) -> bool {
    return mask_keeps(mask, bayer4(frag));
}

// Aerial perspective. The haze's density is `ρ · exp(−y / H)` (ρ = g.sky_zenith.w at height 0, H = g.haze.x):
// valleys lie under more of it than ridges, and a view from altitude looks down through thin air yet sees the
// horizon fade. Its optical depth from the eye to `world`, in closed form along the straight ray:
// ρ · d · (exp(−y₀/H) − exp(−y₁/H)) / ((y₁ − y₀)/H).
fn haze_depth(world: vec3<f32>) -> f32 {
    let d = distance(world, g.eye.xyz);
    let h = g.haze.x;
    if h <= 0.0 {
        return g.sky_zenith.w * d;
    }
    let a = clamp(-g.eye.y / h, -60.0, 60.0);
    let b = clamp(-world.y / h, -60.0, 60.0);
    let k = a - b;
    var mean = exp(a) * (1.0 - 0.5 * k);
    if abs(k) > 1e-3 {
        mean = (exp(a) - exp(b)) / k;
    }
    return g.sky_zenith.w * d * mean;
}

// The share of the light from `world` that the haze replaces.
fn haze_amount(world: vec3<f32>) -> f32 {
    return 1.0 - exp(-haze_depth(world));
}

// The sun's glow toward `dir` (unit): forward scattering in the haze, and around the sun in the sky.
fn sun_glow(dir: vec3<f32>) -> vec3<f32> {
    let c = max(dot(dir, g.sun_dir.xyz), 0.0);
    let c2 = c * c;
    let c4 = c2 * c2;
    return g.haze.y * c4 * c4 * g.sun_color.rgb;
}

// The colour of haze `f` thick toward `world`: blue where thin (the sky's light scattered in), the horizon's where
// thick, brighter toward the sun.
fn haze_color(world: vec3<f32>, f: f32) -> vec3<f32> {
    let dir = normalize(world - g.eye.xyz);
    return mix(mix(g.sky_zenith.rgb, g.sky_horizon.rgb, 0.6 + 0.4 * f), g.sky_horizon.rgb, 0.5) + sun_glow(dir);
}

fn with_fog(c: vec3<f32>, world: vec3<f32>) -> vec3<f32> {
    let f = haze_amount(world);
    return mix(c, haze_color(world, f), f);
}

// `with_fog` of a premultiplied colour of opacity `alpha`.
fn with_fog_premultiplied(color: vec3<f32>, alpha: f32, world: vec3<f32>) -> vec4<f32> {
    let f = haze_amount(world);
    return vec4<f32>(color * (1.0 - f) + haze_color(world, f) * f * alpha, alpha);
}

// Lambert with the sun plus ambient light, the same model the far field's baked shading uses.
fn shade(base: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    return shade_lit(base, n, 1.0);
}

// `shade` where `sun` of the sun's light arrives (shadow.wgsl `sun_visibility`).
fn shade_lit(base: vec3<f32>, n: vec3<f32>, sun: f32) -> vec3<f32> {
    return shade_occluded(base, n, sun, 1.0);
}

// `shade_lit` where `ao` of the ambient and the sky's light arrives (ambient occlusion).
fn shade_occluded(base: vec3<f32>, n: vec3<f32>, sun: f32, ao: f32) -> vec3<f32> {
    let lambert = sun * max(dot(n, g.sun_dir.xyz), 0.0);
    // A little sky light from above so that faces turned from the sun keep their shape (`Lighting::sky_light`).
    let sky = g.sky_horizon.w * (0.5 + 0.5 * n.y);
    return base * (ao * (g.sun_dir.w + sky) + g.sun_color.w * lambert * g.sun_color.rgb);
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
    return mix(g.sky_horizon.rgb, g.sky_zenith.rgb, sqrt(up)) + sun_glow(dir);
}
