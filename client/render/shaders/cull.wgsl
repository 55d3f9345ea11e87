// The GPU cull (renderer/cull.rs), appended to the primitives' shader: three passes over a view's primitive draws
// (the camera's or a shadow cascade's), 256 primitives a workgroup (a block; a draw's blocks are its own).
// `cs_cull` tests each primitive against the view's frustum, the smallest size drawn and, for the camera, the
// occlusion pyramid (hiz.wgsl), and keeps a bit per primitive; `cs_scan`, one workgroup, numbers the kept primitives
// of each block within its draw and writes each draw's indirect arguments; `cs_compact` lists the kept primitives, in
// the draw's order, for `vs_prim_culled`. The order the CPU planned is kept, so a view culled on the GPU is the view
// drawn whole less what the tests dropped.

// One primitive draw of the view's.
struct CullDraw {
    seg_first: u32,
    seg_count: u32,
    // Primitives of the draw (its blocks: this over 256, rounded up).
    instances: u32,
    // The draw's first block.
    block_first: u32,
    // Its first entry in the visible list.
    visible_base: u32,
    // Indices of its unit mesh (the indirect draw's first argument).
    index_count: u32,
    // Its unit shape.
    kind: u32,
    pad: u32,
};

struct CullParams {
    // The view frustum's sides and near plane (camera.rs `Frustum`): n · p + d >= -r is inside.
    planes: array<vec4<f32>, 5>,
    // xyz: the eye; w: pixels a radian spans at the screen's centre (0 for a shadow cascade's orthographic view).
    eye: vec4<f32>,
    // x: the smallest projected size kept, pixels or texels (a bounding sphere's diameter); y: 1 where the pyramid
    // is tested; z: texels a metre of an orthographic view.
    limits: vec4<f32>,
    // x: draws; y: blocks; z: workgroups a row of the dispatch; w: the pyramid's levels.
    counts: vec4<u32>,
    // xy: the size of the pyramid's level 0 (powers of two; hiz.wgsl).
    pyramid_size: vec4<u32>,
};

@group(2) @binding(1) var<storage, read_write> kept: array<vec2<u32>>;
@group(2) @binding(2) var<storage, read> cull_draws: array<CullDraw>;
// Per block: a bit per primitive, 8 words a block; then, after every block's, each block's first kept primitive
// among the frame's, and the total after the last block.
@group(2) @binding(3) var<storage, read_write> blocks: array<u32>;
// Five words a draw: drawIndexedIndirect's arguments.
@group(2) @binding(4) var<storage, read_write> args: array<u32>;
@group(2) @binding(5) var<uniform> cp: CullParams;
// Primitives tested, then dropped outside the frustum, below the smallest size, and behind the terrain.
@group(2) @binding(6) var<storage, read_write> counters: array<atomic<u32>, 4>;
@group(2) @binding(7) var<storage, read> pyramid: array<f32>;

const BLOCK: u32 = 256u;
// Why a primitive is dropped (its counter), or kept.
const KEPT: u32 = 0u;
const OUTSIDE: u32 = 1u;
const SMALL: u32 = 2u;
const OCCLUDED: u32 = 3u;

var<workgroup> wg_mask: array<atomic<u32>, 8>;
var<workgroup> wg_count: array<atomic<u32>, 4>;
var<workgroup> wg_sums: array<u32, 256>;

fn block_of(wid: vec3<u32>) -> u32 {
    return wid.x + wid.y * cp.counts.z;
}

// The draw a block belongs to (the draws' blocks are in order; a dozen draws at most).
fn draw_of(block: u32) -> u32 {
    var d = 0u;
    for (var k = 1u; k < cp.counts.x; k++) {
        if cull_draws[k].block_first <= block {
            d = k;
        }
    }
    return d;
}

// A primitive's bounding sphere in the world, wind included: xyz the centre, w the radius.
fn prim_sphere(prim: Prim, s: Segment, kind: u32) -> vec4<f32> {
    var c = vec3<f32>(0.0);
    var r: f32;
    switch kind {
        case 0u: {
            c = vec3<f32>(0.0, 0.5 * prim.shape.z, 0.0);
            r = length(vec2<f32>(max(abs(prim.shape.x), abs(prim.shape.y)), 0.5 * prim.shape.z));
        }
        case 1u: {
            r = abs(prim.shape.x);
        }
        default: {
            r = 0.5 * length(prim.shape.xyz);
        }
    }
    let species = prim_point(prim, c);
    // The Frobenius norm bounds how far the transform stretches any direction (a column's length would not, for a
    // scale after a rotation).
    let m = prim_axes(prim);
    let radius = r * sqrt(dot(m[0], m[0]) + dot(m[1], m[1]) + dot(m[2], m[2]));
    let world = species + s.pos;
    // The wind moves the centre by its offset there; the rest of the primitive by up to the sway's change over its
    // height and the flutter's change over its reach (segment.wgsl `wind_offset`), which the radius grows by.
    let h = max(species.y, 0.0);
    let reach = length(species.xz);
    let pad = g.wind.z * (0.0013 * (2.0 * h * radius + radius * radius) + 0.04 * (reach + radius));
    return vec4<f32>(world + wind_offset(world, s.pos, s.seed), radius + pad);
}

// A level's size, and where it starts in the pyramid.
fn level_size(level: u32) -> vec2<u32> {
    return max(cp.pyramid_size.xy >> vec2<u32>(level), vec2<u32>(1u));
}

fn level_offset(level: u32) -> u32 {
    var at = 0u;
    for (var l = 0u; l < level; l++) {
        let s = level_size(l);
        at += s.x * s.y;
    }
    return at;
}

// Whether the pyramid shows terrain nearer than all of the sphere wherever it could be on screen.
fn occluded(sphere: vec4<f32>) -> bool {
    if cp.limits.y < 0.5 {
        return false;
    }
    var lo = vec2<f32>(1.0e9);
    var hi = vec2<f32>(-1.0e9);
    var nearest = 0.0;
    for (var k = 0u; k < 8u; k++) {
        let corner = sphere.xyz + sphere.w * vec3<f32>(
            select(-1.0, 1.0, (k & 1u) != 0u),
            select(-1.0, 1.0, (k & 2u) != 0u),
            select(-1.0, 1.0, (k & 4u) != 0u),
        );
        let clip = g.view_proj * vec4<f32>(corner, 1.0);
        // A corner at or behind the near plane: the sphere reaches the eye; not tested.
        if clip.w <= clip.z {
            return false;
        }
        let ndc = clip.xyz / clip.w;
        let px = vec2<f32>(0.5 + 0.5 * ndc.x, 0.5 - 0.5 * ndc.y) * g.viewport.xy;
        lo = min(lo, px);
        hi = max(hi, px);
        nearest = max(nearest, ndc.z);
    }
    lo = max(lo, vec2<f32>(0.0));
    hi = min(hi, g.viewport.xy - 1.0);
    if any(hi < lo) {
        return false;
    }
    // The level whose texels (2^(level+1) pixels) are at least the rectangle's size: it covers 2 × 2 of them.
    let span = max(max(hi.x - lo.x, hi.y - lo.y) * 0.5, 1.0);
    let level = min(u32(ceil(log2(span))), cp.counts.w - 1u);
    let texel = f32(1u << (level + 1u));
    let size = level_size(level);
    let at = level_offset(level);
    let a = min(vec2<u32>(floor(lo / texel)), size - 1u);
    let b = min(vec2<u32>(floor(hi / texel)), size - 1u);
    var farthest = 1.0;
    for (var y = a.y; y <= b.y; y++) {
        for (var x = a.x; x <= b.x; x++) {
            farthest = min(farthest, pyramid[at + y * size.x + x]);
        }
    }
    // Reversed Z: the nearest point of the sphere's box is farther than the farthest terrain over it.
    return nearest < farthest;
}

// Why the primitive `i` of draw `d` is dropped, or KEPT.
fn test_prim(d: CullDraw, i: u32) -> u32 {
    let s = segments[find_segment(i, d.seg_first, d.seg_count)];
    let sphere = prim_sphere(prims[s.base + i - s.first], s, d.kind);
    for (var k = 0u; k < 5u; k++) {
        let p = cp.planes[k];
        if dot(p.xyz, sphere.xyz) + p.w < -sphere.w {
            return OUTSIDE;
        }
    }
    // Its size on screen: seen in perspective (eye.w pixels a radian) or, for a shadow cascade, orthographically
    // (limits.z texels a metre).
    if cp.eye.w > 0.0 {
        let dist = distance(sphere.xyz, cp.eye.xyz);
        if dist > sphere.w && 2.0 * sphere.w * cp.eye.w / dist < cp.limits.x {
            return SMALL;
        }
    } else if 2.0 * sphere.w * cp.limits.z < cp.limits.x {
        return SMALL;
    }
    if occluded(sphere) {
        return OCCLUDED;
    }
    return KEPT;
}

@compute @workgroup_size(256)
fn cs_cull(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    if li < 8u {
        atomicStore(&wg_mask[li], 0u);
    }
    if li < 4u {
        atomicStore(&wg_count[li], 0u);
    }
    workgroupBarrier();
    let block = block_of(wid);
    if block < cp.counts.y {
        let d = cull_draws[draw_of(block)];
        let i = (block - d.block_first) * BLOCK + li;
        if i < d.instances {
            let why = test_prim(d, i);
            atomicAdd(&wg_count[why], 1u);
            if why == KEPT {
                atomicOr(&wg_mask[li / 32u], 1u << (li % 32u));
            }
        }
    }
    workgroupBarrier();
    if block < cp.counts.y {
        if li < 8u {
            blocks[block * 8u + li] = atomicLoad(&wg_mask[li]);
        }
        if li < 4u {
            let n = atomicLoad(&wg_count[li]);
            // Counter 0 counts every primitive tested: the kept ones and the dropped.
            var tested = 0u;
            if li == 0u {
                tested = atomicLoad(&wg_count[0]) + atomicLoad(&wg_count[1]) + atomicLoad(&wg_count[2]) +
                    atomicLoad(&wg_count[3]);
            }
            atomicAdd(&counters[li], select(n, tested, li == 0u));
        }
    }
}

// Where the blocks' offsets start in `blocks`, after their masks.
fn offsets_at() -> u32 {
    return cp.counts.y * 8u;
}

fn kept_in(block: u32) -> u32 {
    var n = 0u;
    for (var w = 0u; w < 8u; w++) {
        n += countOneBits(blocks[block * 8u + w]);
    }
    return n;
}

@compute @workgroup_size(256)
fn cs_scan(@builtin(local_invocation_index) li: u32) {
    let n = cp.counts.y;
    let per = (n + BLOCK - 1u) / BLOCK;
    let lo = min(li * per, n);
    let hi = min(lo + per, n);
    var total = 0u;
    for (var b = lo; b < hi; b++) {
        total += kept_in(b);
    }
    wg_sums[li] = total;
    workgroupBarrier();
    for (var step = 1u; step < BLOCK; step <<= 1u) {
        var v = 0u;
        if li >= step {
            v = wg_sums[li - step];
        }
        workgroupBarrier();
        wg_sums[li] += v;
        workgroupBarrier();
    }
    var run = wg_sums[li] - total;
    for (var b = lo; b < hi; b++) {
        blocks[offsets_at() + b] = run;
        run += kept_in(b);
    }
    if li == BLOCK - 1u {
        blocks[offsets_at() + n] = wg_sums[li];
    }
    storageBarrier();
    workgroupBarrier();
    if li < cp.counts.x {
        let d = cull_draws[li];
        let end = d.block_first + (d.instances + BLOCK - 1u) / BLOCK;
        args[li * 5u] = d.index_count;
        args[li * 5u + 1u] = blocks[offsets_at() + end] - blocks[offsets_at() + d.block_first];
        args[li * 5u + 2u] = 0u;
        args[li * 5u + 3u] = 0u;
        args[li * 5u + 4u] = 0u;
    }
}

@compute @workgroup_size(256)
fn cs_compact(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let block = block_of(wid);
    if block >= cp.counts.y {
        return;
    }
    let word = blocks[block * 8u + li / 32u];
    let bit = 1u << (li % 32u);
    if (word & bit) == 0u {
        return;
    }
    var before = countOneBits(word & (bit - 1u));
    for (var w = 0u; w < li / 32u; w++) {
        before += countOneBits(blocks[block * 8u + w]);
    }
    let d = cull_draws[draw_of(block)];
    let i = (block - d.block_first) * BLOCK + li;
    let si = find_segment(i, d.seg_first, d.seg_count);
    let s = segments[si];
    let at = blocks[offsets_at() + block] - blocks[offsets_at() + d.block_first] + before;
    kept[d.visible_base + at] = vec2<u32>(si, s.base + i - s.first);
}
