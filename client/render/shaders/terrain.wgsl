// The terrain: one vertex buffer of the height grid (and chunk skirts), drawn chunk by chunk.

struct TerrainOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) color: vec3<f32>,
};

@vertex
fn vs_terrain(@location(0) pos: vec3<f32>, @location(1) normal: u32, @location(2) color: u32) -> TerrainOut {
    var out: TerrainOut;
    out.clip = g.view_proj * vec4<f32>(pos, 1.0);
    out.world = pos;
    out.normal = unpack4x8snorm(normal).xyz;
    out.color = unpack4x8unorm(color).rgb;
    return out;
}

// Rock where the ground is steeper than about 35° (all rock past 50°).
const ROCK: vec3<f32> = vec3<f32>(0.36, 0.34, 0.31);

// A hash of a lattice point, 0..1 (after Dave Hoskins' hash12).
fn hash12(p: vec2<f32>) -> f32 {
    var p3 = fract(p.xyx * 0.1031);
    p3 += dot(p3, p3.yzx + 33.33);
    return fract((p3.x + p3.y) * p3.z);
}

// Smooth value noise on the unit lattice, 0..1.
fn value_noise(p: vec2<f32>) -> f32 {
    let i = floor(p);
    let f = fract(p);
    let u = f * f * (3.0 - 2.0 * f);
    let a = mix(hash12(i), hash12(i + vec2<f32>(1.0, 0.0)), u.x);
    let b = mix(hash12(i + vec2<f32>(0.0, 1.0)), hash12(i + vec2<f32>(1.0, 1.0)), u.x);
    return mix(a, b, u.y);
}

// The ground's material at `world` with normal `n`: the terrain species' colour, rock on steep slopes, patches of
// drier and greener ground (a 9 m noise, fading out by 600 m) and detail near the eye (1.7 m and 0.37 m noise,
// fading out by 120 m, where a pixel would alias it).
fn ground_material(base: vec3<f32>, world: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let d = distance(world, g.eye.xyz);
    let steep = smoothstep(0.18, 0.36, 1.0 - n.y);
    var c = mix(base, ROCK, steep);
    if d < 600.0 {
        let patches = (value_noise(world.xz / 9.0) - 0.5) * (1.0 - smoothstep(200.0, 600.0, d));
        c *= vec3<f32>(1.0 + 0.25 * patches, 1.0 + 0.1 * patches, 1.0 - 0.2 * patches);
    }
    if d < 120.0 {
        let fine = value_noise(world.xz / 1.7) * 0.6 + value_noise(world.xz / 0.37) * 0.4 - 0.5;
        c *= 1.0 + 0.3 * fine * (1.0 - smoothstep(30.0, 120.0, d));
    }
    return c;
}

@fragment
fn fs_terrain(in: TerrainOut) -> @location(0) vec4<f32> {
    let n = normalize(in.normal);
    let c = shade_lit(ground_material(in.color, in.world, n), n, sun_visibility(in.world, n));
    return vec4<f32>(with_fog(c, in.world), 1.0);
}
