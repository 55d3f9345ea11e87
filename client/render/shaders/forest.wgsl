// The far view's summaries as forest (issue 15; the plan is `src/forest.rs`): one instance per summary node and
// species, a proxy box over the node raymarched through the species' canopy tile (a periodic stand of its baked
// far volume, `src/tile.rs`) repeated in world coordinates over the ground, each repetition shifted at random
// (texture bombing). The ray walks the node's 8 × 8 sub-squares (a 2D DDA); in a sub-square the instance draws,
// it steps through the canopy layer between the ground (bilinear between the sub-square's corner heights) and the
// canopy's top, samples at `t0 + (n + j)·Δs` from the box entry (j a per-pixel jitter in [0, 1): a fixed offset
// would draw the step grid as bands), lights them by the slope relative to level ground, keeps the trees whose
// density class is below the patch's density (ramping toward its neighbours' at its edges) times the coverage
// interpolated between sub-square centres, and
// blends front to back; it stops at the ground or once the pixel is opaque (`march_patch`). Patches come front to
// back after the far instances, into the far field's accumulation: walked by the compute pass's tile lists
// (far_march.wgsl), or drawn as these boxes, blending under what is in front of them (far_accum.wgsl).
//
// Where a pixel is wider than the trees' spacing (most of a view from altitude) the tile's voxels would only
// alias: there the ray crosses the species' profile instead — the stand as a horizontally uniform layer whose
// extinction and colour vary with height (`CanopyProfile` in `src/tile.rs`) — a few samples per sub-square from a
// small table rather than a march through the 3D tile. The two meet in a dithered band of footprints.

// VolumeInfo, `atlas` and `volumes`: volume_info.wgsl.
// Heights at the sub-squares' corners of every drawn node, 9 × 9 per node, x first.
@group(2) @binding(0) var<storage, read> heights: array<f32>;
// Every resident tile's profile: per height band (16, bottom first) the extinction per metre with 1..8 classes
// kept (two vec4s) and the colour (one vec4).
@group(2) @binding(1) var<storage, read> profiles: array<vec4<f32>>;

// Most samples one ray takes.
const MAX_SAMPLES: i32 = 640;
// The proxy box is drawn this much nearer than it is (metres, and a fraction of the distance), along each eye ray:
// the canopy stands on the scene's ground, which the terrain drawn only approximates at a distance.
const PULL_METRES: f32 = 25.0;
const PULL_FRACTION: f32 = 0.02;
// CLASSES (density classes), BANDS (a profile's height bands) and TILE_MIPS (a tile's resolutions) come from
// `src/tile.rs`, prepended by `src/pipelines.rs`.
// Samples of the layer per sub-square the ray crosses it in.
const LAYER_SAMPLES: i32 = 4;
// Metres around a box within which the eye counts as inside it (its inner faces drawn; see `vs_forest`).
const INSIDE_MARGIN: f32 = 1.0;

struct PatchOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) @interpolate(flat) rect: vec4<f32>,
    @location(2) @interpolate(flat) span: vec2<f32>,
    @location(3) @interpolate(flat) cover: vec2<u32>,
    @location(4) @interpolate(flat) field: vec2<u32>,
    @location(5) @interpolate(flat) ids: vec2<u32>,
    @location(6) @interpolate(flat) params: vec3<f32>,
    @location(7) @interpolate(flat) profile: u32,
    @location(8) @interpolate(flat) layer_from: f32,
    @location(9) @interpolate(flat) mip_scale: f32,
    @location(10) @interpolate(flat) edges: vec4<f32>,
};

@vertex
fn vs_forest(
    @builtin(vertex_index) vi: u32,
    @location(0) rect: vec4<f32>,
    @location(1) span: vec2<f32>,
    @location(2) cover: vec2<u32>,
    @location(3) field: vec2<u32>,
    @location(4) ground: u32,
    @location(5) volume: u32,
    @location(6) scale: f32,
    @location(7) keep: f32,
    @location(8) mask: f32,
    @location(9) profile: u32,
    @location(10) layer_from: f32,
    @location(11) mip_scale: f32,
    @location(12) edges_x: vec2<f32>,
    @location(13) edges_z: vec2<f32>,
) -> PatchOut {
    // The box drawn spans the sub-squares the instance marches, not the whole node: a ray that meets none of
    // them draws nothing (the fragment shader still walks the node's box, so what it draws is the same).
    let cols = (cover.x | (cover.x >> 8u) | (cover.x >> 16u) | (cover.x >> 24u) | cover.y | (cover.y >> 8u)
        | (cover.y >> 16u) | (cover.y >> 24u)) & 0xffu;
    var rows = 0u;
    for (var r = 0u; r < 4u; r++) {
        rows |= select(0u, 1u << r, ((cover.x >> (8u * r)) & 0xffu) != 0u);
        rows |= select(0u, 1u << (r + 4u), ((cover.y >> (8u * r)) & 0xffu) != 0u);
    }
    let cell = rect.z / 8.0;
    let first = vec2<f32>(f32(firstTrailingBit(cols)), f32(firstTrailingBit(rows)));
    let last = vec2<f32>(f32(firstLeadingBit(cols)), f32(firstLeadingBit(rows))) + 1.0;
    let lo = vec3<f32>(rect.x + first.x * cell, span.x, rect.y + first.y * cell);
    let size = vec3<f32>((last.x - first.x) * cell, span.y - span.x, (last.y - first.y) * cell);
    // Back faces are culled: from outside a box its front faces march. From inside (or within INSIDE_MARGIN of
    // it) each triangle's corners come in reverse order, so that the faces seen from inside wind counter-clockwise
    // and are the ones drawn (the ray then marches from the eye): the same triangles, half the fragments.
    let e = g.eye.xyz - lo;
    let inside = all(e > vec3<f32>(-INSIDE_MARGIN)) && all(e < size + vec3<f32>(INSIDE_MARGIN));
    let corner = vi % 3u;
    let world = lo + size * unit_cube(select(vi, vi - corner + 2u - corner, inside));
    let to = world - g.eye.xyz;
    let d = max(length(to), 1e-3);
    var out: PatchOut;
    out.clip = g.view_proj * vec4<f32>(world - to * (pull(d) / d), 1.0);
    out.world = world;
    out.rect = rect;
    out.span = span;
    out.cover = cover;
    out.field = field;
    out.ids = vec2<u32>(ground, volume);
    out.params = vec3<f32>(scale, keep, mask);
    out.profile = profile;
    out.layer_from = layer_from;
    out.mip_scale = mip_scale;
    out.edges = vec4<f32>(edges_x, edges_z);
    return out;
}

// A hash of the pixel to [0, 1): where the first sample falls within a step (sampling from the box entry at a
// fixed offset would draw the layer's intersections with the step grid as bands).
fn jitter(frag: vec2<f32>) -> f32 {
    var x = (u32(frag.x) * 0x9e3779b1u) ^ (u32(frag.y) * 0x85ebca77u);
    x ^= x >> 15u;
    x *= 0x2c1b3c6du;
    x ^= x >> 12u;
    return f32(x & 0xffffu) / 65536.0;
}

// Where a tile placed at tile cell (cx, cz) starts within the tile, [0, 1)² (texture bombing: every repetition
// shifted at random, so that the stand does not repeat in rows a far view turns into moiré).
fn shift(cx: f32, cz: f32) -> vec2<f32> {
    var x = (bitcast<u32>(i32(cx)) * 0x8da6b343u) ^ (bitcast<u32>(i32(cz)) * 0xd8163841u);
    x ^= x >> 16u;
    x *= 0x7feb352du;
    x ^= x >> 15u;
    return vec2<f32>(f32(x & 0xffffu), f32(x >> 16u)) / 65536.0;
}

// Where within a class a repetition of the tile at tile cell (cx, cz) draws its line, [0, 1): a tree of class n is
// kept where (n + phase) / CLASSES < keep × coverage. Drawn at random per repetition, so the trees kept are the
// fraction `keep` on average wherever it falls between classes. (One phase of ½ everywhere rounded every patch to
// whole classes, a node and each of its children differently: the seams between finer and coarser nodes showed
// as lighter and darker blocks.)
fn keep_phase(cx: f32, cz: f32) -> f32 {
    var x = (bitcast<u32>(i32(cx)) * 0x9e3779b1u) ^ (bitcast<u32>(i32(cz)) * 0x632be5abu);
    x ^= x >> 15u;
    x *= 0x2c1b3c6du;
    x ^= x >> 12u;
    x *= 0x297a2d39u;
    x ^= x >> 15u;
    return f32(x >> 8u) / 16777216.0;
}

// The slope's light over flat ground's (the terrain's lighting model): the canopy follows the ground, and its
// baked shading is a lone tree's on level ground.
fn relief(h00: f32, h10: f32, h01: f32, h11: f32, cell: f32) -> vec3<f32> {
    let gx = 0.5 * (h10 - h00 + h11 - h01) / cell;
    let gz = 0.5 * (h01 - h00 + h11 - h10) / cell;
    let n = normalize(vec3<f32>(-gx, 1.0, -gz));
    return shade(vec3<f32>(1.0), n) / shade(vec3<f32>(1.0), vec3<f32>(0.0, 1.0, 0.0));
}

fn bit(m: vec2<u32>, i: i32, j: i32) -> bool {
    let k = u32(j * 8 + i);
    let w = select(m.x, m.y, k >= 32u);
    return ((w >> (k & 31u)) & 1u) == 1u;
}

// The coverage field at (u, v), in sub-squares from the node's corner: the mask's bits bilinear between sub-square
// centres (clamped at the node's edges).
fn coverage(m: vec2<u32>, u: f32, v: f32) -> f32 {
    let a = vec2<f32>(u - 0.5, v - 0.5);
    let f = a - floor(a);
    let i0 = clamp(i32(floor(a.x)), 0, 7);
    let j0 = clamp(i32(floor(a.y)), 0, 7);
    let i1 = clamp(i32(floor(a.x)) + 1, 0, 7);
    let j1 = clamp(i32(floor(a.y)) + 1, 0, 7);
    let b = vec4<f32>(
        select(0.0, 1.0, bit(m, i0, j0)),
        select(0.0, 1.0, bit(m, i1, j0)),
        select(0.0, 1.0, bit(m, i0, j1)),
        select(0.0, 1.0, bit(m, i1, j1)),
    );
    return mix(mix(b.x, b.y, f.x), mix(b.z, b.w, f.x), f.y);
}

// Height of `p` (node-relative) above sub-square (i, j)'s ground, bilinear between its corner heights `h` (00, 10,
// 01, 11).
fn above_ground(p: vec3<f32>, i: i32, j: i32, cell: f32, h: vec4<f32>) -> f32 {
    let u = clamp(p.x / cell - f32(i), 0.0, 1.0);
    let v = clamp(p.z / cell - f32(j), 0.0, 1.0);
    return p.y - mix(mix(h.x, h.y, u), mix(h.z, h.w, u), v);
}

// The layer's extinction per metre (tile scale 1) at band position `b` (in bands from the ground) with `m` of
// the classes kept (fractional: the extinctions between whole classes are interpolated).
fn layer_sigma(base: u32, b: f32, m: f32) -> f32 {
    let k = clamp(m, 0.0, CLASSES);
    let n = min(u32(k), u32(CLASSES) - 1u);
    let f = k - f32(n);
    let bi = u32(clamp(b, 0.0, BANDS - 1.0));
    let lo = base + 3u * bi;
    let upper = profiles[lo + n / 4u][n % 4u];
    var lower = 0.0;
    if n > 0u {
        lower = profiles[lo + (n - 1u) / 4u][(n - 1u) % 4u];
    }
    return mix(lower, upper, f);
}

// Depth tests before the shader although it writes the pixel's opacity (see volume.wgsl).
@fragment @early_depth_test(force)
fn fs_forest(in: PatchOut) -> @location(0) vec4<f32> {
    if !dither_keeps(in.params.z, in.clip.xy) {
        discard;
    }
    let pixel = pixel_index(in.clip.xy);
    let front = opacity_in_front(pixel);
    if front >= OPAQUE {
        discard;
    }
    let p = Patch(
        in.rect, in.span, in.cover, in.field, in.ids, in.params, in.profile, in.layer_from, in.mip_scale, in.edges.xy,
        in.edges.zw,
    );
    let c = march_patch(p, normalize(in.world - g.eye.xyz), in.clip.xy, stop_alpha(front), 1e30);
    if c.a < 1.0 / 512.0 {
        discard;
    }
    add_opacity(pixel, front, c.a);
    return c;
}

// A forest patch as its march reads it (`ForestPatch` in `src/forest.rs`; ids: ground, volume; params: scale,
// keep, dither mask).
struct Patch {
    rect: vec4<f32>,
    span: vec2<f32>,
    cover: vec2<u32>,
    field: vec2<u32>,
    ids: vec2<u32>,
    params: vec3<f32>,
    profile: u32,
    layer_from: f32,
    mip_scale: f32,
    // The fraction kept at the node's -x and +x edges, and at its -z and +z edges (`keep_at`).
    edges_x: vec2<f32>,
    edges_z: vec2<f32>,
};

// The fraction of the tile's trees kept at (x, z) metres from the patch's node's corner: the node's own (params.y)
// in its middle, ramping linearly to the value at each edge (the mean of its density and the neighbour's there).
fn keep_at(in: Patch, x: f32, z: f32) -> f32 {
    let k = in.params.y;
    let u = clamp(2.0 * x / in.rect.z - 1.0, -1.0, 1.0);
    let v = clamp(2.0 * z / in.rect.z - 1.0, -1.0, 1.0);
    let dx = (select(in.edges_x.y, in.edges_x.x, u < 0.0) - k) * abs(u);
    let dz = (select(in.edges_z.y, in.edges_z.x, v < 0.0) - k) * abs(v);
    return clamp(k + dx + dz, 0.0, 1.0);
}

// How much nearer than its box a patch counts for the opaque scene in front of it, at `d` metres: the canopy
// stands on the scene's ground, which the terrain drawn only approximates at a distance.
fn pull(d: f32) -> f32 {
    return min(PULL_METRES + PULL_FRACTION * d, 0.5 * d);
}

// Patch `in` along the eye ray `d` at pixel `frag`: premultiplied colour and opacity, the march stopping at opacity
// `stop`; nothing if its box begins (pulled nearer) beyond `t_scene` metres.
fn march_patch(in: Patch, d: vec3<f32>, frag: vec2<f32>, stop: f32, t_scene: f32) -> vec4<f32> {
    let scale = in.params.x;
    let lo = vec3<f32>(in.rect.x, in.span.x, in.rect.y);
    let ext = vec3<f32>(in.rect.z, in.span.y - in.span.x, in.rect.z);
    // The ray, relative to the box's lower corner (precision far from the origin). Only the faces that march
    // arrive (see `vs_forest`).
    let o = g.eye.xyz - lo;
    let inv_d = 1.0 / d;
    let ta = -o * inv_d;
    let tb = (ext - o) * inv_d;
    let tmin = min(ta, tb);
    let tmax = max(ta, tb);
    let t0 = max(max(max(tmin.x, tmin.y), tmin.z), 0.0);
    let t1 = min(min(tmax.x, tmax.y), tmax.z);
    if t1 <= t0 || t0 - pull(t0) >= t_scene {
        return vec4<f32>(0.0);
    }
    let info = volumes[in.ids.y];
    let period = info.hi.xz * scale;
    let top = in.rect.w;
    let cell = in.rect.z / 8.0;
    let gbase = i32(in.ids.x);

    // The 2D walk over sub-squares.
    let p0 = o + d * t0;
    var i = clamp(i32(floor(p0.x / cell)), 0, 7);
    var j = clamp(i32(floor(p0.z / cell)), 0, 7);
    let si = select(-1, 1, d.x > 0.0);
    let sj = select(-1, 1, d.z > 0.0);
    let big = 1e30;
    var next_x = big;
    var next_z = big;
    if d.x != 0.0 {
        next_x = (f32(i + select(0, 1, d.x > 0.0)) * cell - o.x) * inv_d.x;
    }
    if d.z != 0.0 {
        next_z = (f32(j + select(0, 1, d.z > 0.0)) * cell - o.z) * inv_d.z;
    }
    let delta_x = select(big, cell * abs(inv_d.x), d.x != 0.0);
    let delta_z = select(big, cell * abs(inv_d.z), d.z != 0.0);

    var color = vec3<f32>(0.0);
    var alpha = 0.0;
    var first_hit = -1.0;
    var samples = 0;
    var t_in = t0;
    var grounded = false;
    let offset = jitter(frag);
    // The layer beyond the patch's distance (where a pixel spans `RenderConfig::forest_layer` tree spacings),
    // dithered over ±25 %.
    let layer = t0 > in.layer_from * (0.75 + 0.5 * offset);
    let band = top / BANDS;
    for (var walked = 0; walked < 17; walked++) {
        let t_out = min(min(next_x, next_z), t1);
        let h = gbase + j * 9 + i;
        let h00 = heights[h] - lo.y;
        let h10 = heights[h + 1] - lo.y;
        let h01 = heights[h + 9] - lo.y;
        let h11 = heights[h + 10] - lo.y;
        let ya = o.y + d.y * t_in;
        let yb = o.y + d.y * t_out;
        if max(ya, yb) < min(min(h00, h10), min(h01, h11)) {
            break;
        }
        let corners = vec4<f32>(h00, h10, h01, h11);
        if bit(in.cover, i, j) && min(ya, yb) <= max(max(h00, h10), max(h01, h11)) + top {
            let light = relief(h00, h10, h01, h11, cell);
            if layer {
                // Height above the ground at the sub-square's entry and exit, and the part of the crossing within
                // the layer (the ground taken as linear along it), sampled LAYER_SAMPLES times.
                let wa = above_ground(o + d * t_in, i, j, cell, corners);
                let wb = above_ground(o + d * t_out, i, j, cell, corners);
                var sa = 0.0;
                var sb = 1.0;
                let dw = wb - wa;
                if abs(dw) > 1e-6 {
                    let s_top = (top - wa) / dw;
                    let s_ground = -wa / dw;
                    sa = clamp(min(s_top, s_ground), 0.0, 1.0);
                    sb = clamp(max(s_top, s_ground), 0.0, 1.0);
                } else if wa < 0.0 || wa > top {
                    sb = 0.0;
                }
                let ds = (sb - sa) * (t_out - t_in) / f32(LAYER_SAMPLES);
                if ds > 0.0 {
                    // Classes kept at the crossing's ends (the coverage field is smooth within a sub-square): the
                    // fraction `keep` of the tile's trees, continuous (the march rounds to whole classes; the layer
                    // draws the summary's count as it is, sparse species too).
                    let ta = t_in + sa * (t_out - t_in);
                    let tb = t_in + sb * (t_out - t_in);
                    let qa = o + d * ta;
                    let qb = o + d * tb;
                    let ma = CLASSES * keep_at(in, qa.x, qa.z) * coverage(in.field, qa.x / cell, qa.z / cell);
                    let mb = CLASSES * keep_at(in, qb.x, qb.z) * coverage(in.field, qb.x / cell, qb.z / cell);
                    for (var k = 0; k < LAYER_SAMPLES; k++) {
                        let f = (f32(k) + offset) / f32(LAYER_SAMPLES);
                        let w = mix(wa, wb, sa + (sb - sa) * f);
                        let b = clamp(w / band - 0.5, 0.0, BANDS - 1.0);
                        let b0 = floor(b);
                        let fb = b - b0;
                        let m = mix(ma, mb, f);
                        let sigma_lo = layer_sigma(in.profile, b0, m);
                        let sigma = mix(sigma_lo, layer_sigma(in.profile, b0 + 1.0, m), fb) / scale;
                        let a = 1.0 - exp(-sigma * ds);
                        if a <= 0.0 {
                            continue;
                        }
                        let at = in.profile + 3u * u32(b0) + 2u;
                        let above = min(at + 3u, in.profile + 3u * u32(BANDS) - 1u);
                        let c = mix(profiles[at].rgb, profiles[above].rgb, fb);
                        if first_hit < 0.0 {
                            first_hit = mix(ta, tb, f);
                        }
                        let wgt = (1.0 - alpha) * a;
                        color += wgt * c * light;
                        alpha += wgt;
                        if alpha >= stop {
                            break;
                        }
                    }
                }
                // The ground is under the layer's lower end when the crossing left it downward.
                if wb < 0.0 {
                    grounded = true;
                }
            } else {
                // How fast the ray can close on the canopy's top over this sub-square: its descent plus the
                // steepest the bilinear ground can rise along it. A sample `w - top` above the top is followed by at
                // least `(w - top) / closing` of ray with nothing to hit, whose samples are skipped (they would all
                // be above the top: the picture is the same, the work is not).
                let gx = max(abs(h10 - h00), abs(h11 - h01)) / cell;
                let gz = max(abs(h01 - h00), abs(h11 - h10)) / cell;
                let closing = max(-d.y + gx * abs(d.x) + gz * abs(d.z), 1e-4);
                // The tile resolution whose voxels are about VOXEL_PX pixels where the ray enters the sub-square (the
                // tile's resolutions are consecutive volumes, finest first).
                let level = u32(clamp(floor(log2(max(t_in * in.mip_scale, 1.0))), 0.0, f32(TILE_MIPS - 1u)));
                let mip = volumes[in.ids.y + level];
                let vox = mip.voxel.xyz * scale;
                let step = mip.voxel.w * scale;
                let dims = vec3<i32>(mip.dims.xyz);
                let base = vec3<i32>(mip.atlas.xyz);
                var n = max(ceil((t_in - t0) / step - offset), 0.0);
                loop {
                    let t = t0 + (n + offset) * step;
                    if t >= t_out || samples >= MAX_SAMPLES {
                        break;
                    }
                    samples++;
                    n += 1.0;
                    let p = o + d * t;
                    let w = above_ground(p, i, j, cell, corners);
                    if w < 0.0 {
                        grounded = true;
                        break;
                    }
                    if w >= top {
                        n += max(floor((w - top) / closing / step), 0.0);
                        continue;
                    }
                    // Tile coordinates: world x and z in tile periods, each repetition shifted; height above the
                    // ground.
                    let wt = vec2<f32>(p.x + lo.x, p.z + lo.z) / period;
                    let cell_t = floor(wt);
                    let ft = fract(wt - cell_t + shift(cell_t.x, cell_t.y)) * period;
                    let q = vec3<f32>(ft.x, w, ft.y);
                    let c = clamp(vec3<i32>(floor(q / vox)), vec3<i32>(0), dims - vec3<i32>(1));
                    let s = textureLoad(atlas, base + c, 0);
                    if s.a <= 0.0 {
                        continue;
                    }
                    let bits = vec3<u32>(bitcast<u32>(s.r), bitcast<u32>(s.g), bitcast<u32>(s.b)) >> vec3<u32>(31u);
                    let cls = f32(bits.x + 2u * bits.y + 4u * bits.z);
                    let kept = keep_at(in, p.x, p.z) * coverage(in.field, p.x / cell, p.z / cell);
                    if (cls + keep_phase(cell_t.x, cell_t.y)) / CLASSES >= kept {
                        continue;
                    }
                    if first_hit < 0.0 {
                        first_hit = t;
                    }
                    let wgt = (1.0 - alpha) * s.a;
                    color += wgt * abs(s.rgb) * light;
                    alpha += wgt;
                    if alpha >= stop {
                        break;
                    }
                }
            }
        }
        if grounded || alpha >= stop || samples >= MAX_SAMPLES || t_out >= t1 {
            break;
        }
        if next_x < next_z {
            i += si;
            t_in = next_x;
            next_x += delta_x;
        } else {
            j += sj;
            t_in = next_z;
            next_z += delta_z;
        }
        if i < 0 || i > 7 || j < 0 || j > 7 {
            break;
        }
    }
    if alpha < 1.0 / 512.0 {
        return vec4<f32>(0.0);
    }
    return with_fog_premultiplied(color, alpha, g.eye.xyz + d * first_hit);
}
