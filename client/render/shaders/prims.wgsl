// Near and mid geometry by instancing: unit frusta, spheres and boxes, shaped per primitive in the vertex shader.
// Every instance of a draw finds its segment (one tree at one detail level) by binary search, so one draw call
// covers every tree of the frame that uses this unit mesh.

struct Prim {
    r0: vec4<f32>,
    r1: vec4<f32>,
    r2: vec4<f32>,
    // xyz: size (frustum: bottom radius, top radius, height; sphere: radius; box: edges); w: packed colour.
    shape: vec4<f32>,
};

// `segments` is binding 0 of group 1 and `draw` binding 0 of group 2 (segment.wgsl).
@group(1) @binding(1) var<storage, read> prims: array<Prim>;

// What the GPU cull (cull.wgsl) kept of a draw, in the draw's order: each primitive's segment and its place in the
// arena, from `draw.visible_base` on.
@group(1) @binding(2) var<storage, read> visible: array<vec2<u32>>;

@vertex
fn vs_prim(@location(0) p: vec4<f32>, @location(1) un: vec4<f32>, @builtin(instance_index) ii: u32) -> GeoOut {
    let s = segments[find_segment(ii, draw.seg_first, draw.seg_count)];
    return shape_prim(p, un, s, prims[s.base + ii - s.first]);
}

// The same, for a draw the GPU culled: the instance is the kept primitive's place in the visible list.
@vertex
fn vs_prim_culled(@location(0) p: vec4<f32>, @location(1) un: vec4<f32>, @builtin(instance_index) ii: u32) -> GeoOut {
    let e = visible[draw.visible_base + ii];
    return shape_prim(p, un, segments[e.x], prims[e.y]);
}

// A point of the primitive's own space in the species' space.
fn prim_point(prim: Prim, local: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(
        dot(prim.r0.xyz, local) + prim.r0.w,
        dot(prim.r1.xyz, local) + prim.r1.w,
        dot(prim.r2.xyz, local) + prim.r2.w,
    );
}

// The primitive's transform without its translation: its axes as columns.
fn prim_axes(prim: Prim) -> mat3x3<f32> {
    return transpose(mat3x3<f32>(prim.r0.xyz, prim.r1.xyz, prim.r2.xyz));
}

// A vertex `p` (normal `un`) of the unit shape of `draw.kind`, shaped and placed as `prim` of the tree `s`.
fn shape_prim(p: vec4<f32>, un: vec4<f32>, s: Segment, prim: Prim) -> GeoOut {
    var local: vec3<f32>;
    var n: vec3<f32>;
    switch draw.kind {
        case 0u: {
            // Frustum: p = (cos, 0 bottom / 1 top, sin, 1 on a cap).
            let r = mix(prim.shape.x, prim.shape.y, p.y);
            local = vec3<f32>(p.x * r, p.y * prim.shape.z, p.z * r);
            if p.w > 0.5 {
                n = vec3<f32>(0.0, select(-1.0, 1.0, p.y > 0.5), 0.0);
            } else {
                n = vec3<f32>(p.x * prim.shape.z, prim.shape.x - prim.shape.y, p.z * prim.shape.z);
            }
        }
        case 1u: {
            local = p.xyz * prim.shape.x;
            n = p.xyz;
        }
        default: {
            local = p.xyz * prim.shape.xyz;
            n = un.xyz;
        }
    }
    let species = prim_point(prim, local);
    // Normals by the cofactor matrix (the inverse transpose up to the determinant's sign).
    let m = prim_axes(prim);
    let a = m[0];
    let b = m[1];
    let c = m[2];
    let det = dot(a, cross(b, c));
    let wn = (cross(b, c) * n.x + cross(c, a) * n.y + cross(a, b) * n.z) * sign(det);
    var out: GeoOut;
    let world = species + s.pos + wind_offset(species + s.pos, s.pos, s.seed);
    out.clip = g.view_proj * vec4<f32>(world, 1.0);
    out.world = world;
    out.normal = wn;
    out.color = unpack4x8unorm(bitcast<u32>(prim.shape.w)).rgb * instance_tint(s.seed);
    out.mask = s.mask;
    out.thin = 0.0;
    out.ao = crown_occlusion(species, s);
    out.bark = vec4<f32>(0.0);
    out.card = vec4<f32>(0.0);
    if draw.kind == 0u && p.w < 0.5 {
        // Fissures about every 12 cm around the mean circumference, a whole number of them.
        let around = max(round(3.14159265 * (prim.shape.x + prim.shape.y) / BARK_SPACING), 3.0);
        // The side's direction and height in the world, not the primitive's own: the pattern runs on across a
        // trunk's segments, each turned about its axis by the phyllotaxis.
        out.bark = vec4<f32>(wn.x, wn.z, world.y, around);
    }
    return out;
}

// Metres between bark fissures around a trunk or branch.
const BARK_SPACING: f32 = 0.12;

// Bark on a frustum's side (seed 002's bark, procedurally): vertical fissures, a whole number around the axis
// (so the pattern closes on itself), wandering along it; darker in the fissures. Faded out by 25 m, where they
// would be finer than a pixel.
fn bark(base: vec3<f32>, b: vec4<f32>, world: vec3<f32>) -> vec3<f32> {
    let fade = 1.0 - smoothstep(10.0, 25.0, distance(world, g.eye.xyz));
    if b.w <= 0.0 || fade <= 0.0 {
        return base;
    }
    let t = atan2(b.y, b.x);
    let wander = 0.8 * sin(b.z * 2.3 + 3.0 * t) + 0.4 * sin(b.z * 7.1 - 5.0 * t);
    let s = sin(t * b.w + wander);
    let fissure = smoothstep(0.55, 0.95, s);
    return base * (1.0 - 0.45 * fissure * fade);
}

@fragment
fn fs_prim(in: GeoOut) -> SceneFragment {
    let samples = dither_samples(in.mask, in.clip.xy);
    if samples == 0u {
        discard;
    }
    let n = normalize(in.normal);
    let lit = shade_occluded(bark(in.color, in.bark, in.world), n, sun_visibility(in.world, n), in.ao);
    return SceneFragment(vec4<f32>(with_fog(lit, in.world), 1.0), samples);
}
