// The far field (seed 000 §8): each far instance is a proxy box around its species' hypertree volume, raymarched
// front to back through a 3D texture atlas of baked voxels (rgb: lit colour, a: opacity α = 1 − (1 − µ)^k), with
// the CPU reference renderer's sampling: steps of the smallest voxel side from the entry into the voxels' box,
// sample n at t0 + (n + ½)·Δs, nearest-voxel lookups, early exit once the pixel is 99.5 % opaque
// (`march_volume`). Instances come front to back into the far field's accumulation: walked by the compute pass's
// tile lists (far_march.wgsl), or drawn as these boxes, blending under what is in front of them (far_accum.wgsl).
// VolumeInfo, `atlas` and `volumes`: volume_info.wgsl.

struct VolumeOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) @interpolate(flat) inst: vec4<f32>,
    @location(2) @interpolate(flat) volume: u32,
    @location(3) @interpolate(flat) mask: f32,
};

@vertex
fn vs_volume(
    @builtin(vertex_index) vi: u32,
    @location(0) pos_scale: vec4<f32>,
    @location(1) volume: u32,
    @location(2) mask: f32,
) -> VolumeOut {
    let info = volumes[volume & 0xffffffu];
    let b = mix(info.lo.xyz, info.hi.xyz, unit_cube(vi));
    let k = pos_scale.w * info.lo.w;
    let world = pos_scale.xyz + k * (b - info.origin.xyz);
    var out: VolumeOut;
    out.clip = g.view_proj * vec4<f32>(world, 1.0);
    out.world = world;
    out.inst = pos_scale;
    out.volume = volume;
    out.mask = mask;
    return out;
}

// Depth tests before the shader although it writes the pixel's opacity: a fragment behind the opaque scene does
// nothing.
@fragment @early_depth_test(force)
fn fs_volume(in: VolumeOut) -> @location(0) vec4<f32> {
    if !dither_keeps(in.mask, in.clip.xy) {
        discard;
    }
    let pixel = pixel_index(in.clip.xy);
    let front = opacity_in_front(pixel);
    if front >= OPAQUE {
        discard;
    }
    let c = march_volume(in.inst, in.volume, normalize(in.world - g.eye.xyz), stop_alpha(front), 1e30);
    if c.a < 1.0 / 512.0 {
        discard;
    }
    add_opacity(pixel, front, c.a);
    return c;
}

// The far instance at `inst` (position, scale) of volume `volume` (`FarInstance::volume`: the index in its low
// 24 bits, the instance's tint in its top 8) along the eye ray `d`: premultiplied colour and opacity, the march
// stopping at opacity `stop`; nothing if its box begins beyond `t_scene` metres (the opaque scene in front of it).
fn march_volume(inst: vec4<f32>, volume: u32, d: vec3<f32>, stop: f32, t_scene: f32) -> vec4<f32> {
    let info = volumes[volume & 0xffffffu];
    let k = inst.w * info.lo.w;
    // The ray in box units (a uniform scale keeps directions).
    let o = (g.eye.xyz - inst.xyz) / k + info.origin.xyz;
    let inv_d = 1.0 / d;
    let ta = (info.lo.xyz - o) * inv_d;
    let tb = (info.hi.xyz - o) * inv_d;
    let tmin = min(ta, tb);
    let tmax = max(ta, tb);
    let t0 = max(max(max(tmin.x, tmin.y), tmin.z), 0.0);
    let t1 = min(min(tmax.x, tmax.y), tmax.z);
    if t1 < t0 || t0 * k >= t_scene {
        return vec4<f32>(0.0);
    }
    let step = info.voxel.w;
    let last = i32(floor((t1 - t0) / step - 0.5));
    let dims = vec3<i32>(info.dims.xyz);
    let base = vec3<i32>(info.atlas.xyz);
    var color = vec3<f32>(0.0);
    var alpha = 0.0;
    var first_hit = -1.0;
    for (var n = 0; n <= min(last, 1024); n++) {
        let t = t0 + (f32(n) + 0.5) * step;
        let p = o + d * t;
        let v = vec3<i32>(floor(p / info.voxel.xyz));
        if any(v < vec3<i32>(0)) || any(v >= dims) {
            continue;
        }
        let s = textureLoad(atlas, base + v, 0);
        if s.a > 0.0 {
            if first_hit < 0.0 {
                first_hit = t;
            }
            let w = (1.0 - alpha) * s.a;
            color += w * s.rgb;
            alpha += w;
            if alpha >= stop {
                break;
            }
        }
    }
    if alpha < 1.0 / 512.0 {
        return vec4<f32>(0.0);
    }
    // Fog at the first voxel hit, premultiplied like the colour.
    let hit = g.eye.xyz + d * (first_hit * k);
    return with_fog_premultiplied(color * instance_tint(volume & 0xff000000u), alpha, hit);
}
