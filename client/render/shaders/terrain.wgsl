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

@fragment
fn fs_terrain(in: TerrainOut) -> @location(0) vec4<f32> {
    let n = normalize(in.normal);
    let c = shade_lit(in.color, n, sun_visibility(in.world, n));
    return vec4<f32>(with_fog(c, in.world), 1.0);
}
