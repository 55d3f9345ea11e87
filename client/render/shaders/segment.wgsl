// Draw segments, shared by the near and mid geometry shaders (appended to prims.wgsl and mesh.wgsl): a draw's
// segments and uniforms, finding an element's segment, and the vertex output both shaders shade.

// One instance's run of primitives (or mesh indices) in an arena, placed at `pos`, drawn through `mask`.
struct Segment {
    // Index of the segment's first element within its draw (a prefix sum of `count`).
    first: u32,
    // First element in the arena (primitives, or mesh indices).
    base: u32,
    // First vertex in the vertex arena (meshes only).
    vbase: u32,
    count: u32,
    pos: vec3<f32>,
    // Dither mask: m >= 0 keeps pixels whose Bayer threshold is below m; m < 0 keeps those at or above -m.
    mask: f32,
    // The instance's seed (its low 32 bits folded with the high), which keys its wind phase.
    seed: u32,
    // The tree's crown as its bounding sphere: the centre's height above `pos` and the radius (0: no occlusion).
    crown_y: f32,
    crown_r: f32,
    pad0: u32,
};

// Which segments a draw covers, and what it draws.
struct Draw {
    seg_first: u32,
    seg_count: u32,
    kind: u32,
    // The draw's first entry in the visible list, where the GPU culls (prims.wgsl `vs_prim_culled`).
    visible_base: u32,
};

@group(1) @binding(0) var<storage, read> segments: array<Segment>;
@group(2) @binding(0) var<uniform> draw: Draw;

// What the geometry vertex shaders hand their fragment shaders.
struct GeoOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) color: vec3<f32>,
    @location(3) @interpolate(flat) mask: f32,
    // 1 for a leaf (thin: lit through from behind), 0 otherwise.
    @location(4) thin: f32,
    // On a frustum's side (prims.wgsl `bark`): its normal's horizontal direction (x, z), its height, and
    // the fissures around it (w; 0 elsewhere).
    @location(5) bark: vec4<f32>,
    // The share of the sky's and the ambient light that reaches it (`crown_occlusion`).
    @location(6) ao: f32,
    // On a leaf card (w = 1; 0 elsewhere): u along the blade (0 petiole, 1 tip), v across it (-1..1) and where the
    // blade is widest (z), see `leaf_half_width`.
    @location(7) card: vec4<f32>,
};

// A leaf card's corner from its vertex's alpha byte (leaf.rs): bit 0 u, bit 1 the side, bits 2..=6 the widest
// point's level of 31 over 0.15..0.75, bit 7 set where the vertex is not on a card.
fn leaf_card(tag: u32) -> vec4<f32> {
    if tag >= 128u {
        return vec4<f32>(0.0);
    }
    let widest = 0.15 + 0.6 * f32((tag >> 2u) & 31u) / 31.0;
    return vec4<f32>(f32(tag & 1u), f32((tag >> 1u) & 1u) * 2.0 - 1.0, widest, 1.0);
}

// The blade's half-width at u (a share of the card's), widest at w: a sine lobe stretched to peak at w, cut by eight
// teeth a margin leaning toward the tip, 12 % deep (leaf.rs `half_width`, whose area sizes the card).
fn leaf_half_width(u: f32, w: f32) -> f32 {
    if u <= 0.0 || u >= 1.0 {
        return 0.0;
    }
    let t = select(0.5 + 0.5 * (u - w) / (1.0 - w), 0.5 * u / w, u < w);
    let teeth = 1.0 - 0.12 * fract(u * 8.0);
    return sin(3.14159265 * t) * teeth;
}

// How far inside the leaf a fragment is, in shares of the card's half-width (negative outside): within the blade
// or on its stalk; far inside everywhere off a card.
fn leaf_inside(card: vec4<f32>) -> f32 {
    if card.w < 0.5 {
        return 1.0e6;
    }
    let v = abs(card.y);
    return max(leaf_half_width(card.x, card.z) - v, min(0.05 - v, 0.12 - card.x));
}

// Whether a fragment is on the leaf (the silhouette one sample a pixel and the shadow maps cut).
fn leaf_keeps(card: vec4<f32>) -> bool {
    return leaf_inside(card) >= 0.0;
}

// The share of a pixel the leaf covers, from how far inside it the fragment is against how fast that changes across
// the pixel: what alpha-to-coverage turns into samples under multisampling (1 off a card).
fn leaf_coverage(card: vec4<f32>) -> f32 {
    let d = leaf_inside(card);
    return clamp(d / max(fwidth(d), 1.0e-6) + 0.5, 0.0, 1.0);
}

// A leaf's veins: a lighter midrib and darker side veins running out toward the tip (1 off a card).
fn leaf_veins(card: vec4<f32>) -> f32 {
    if card.w < 0.5 {
        return 1.0;
    }
    let v = abs(card.y);
    let midrib = 1.0 - smoothstep(0.03, 0.06, v);
    let side = smoothstep(0.8, 0.95, abs(fract(card.x * 7.0 - v * 1.6) - 0.5) * 2.0);
    return 1.0 + 0.18 * midrib - 0.1 * side * (1.0 - midrib);
}

// Ambient occlusion inside a crown: how much of the sky's and the ambient light reaches a point `rel` from the
// tree's base, the crown taken as its bounding sphere. Whole at the sphere's surface and outside it; toward the
// centre less by up to g.haze.z (`Lighting::crown_occlusion`), the lower half of the crown darker than the upper
// (the foliage above shades it from the sky).
fn crown_occlusion(rel: vec3<f32>, s: Segment) -> f32 {
    if s.crown_r <= 0.0 {
        return 1.0;
    }
    let q = (rel - vec3<f32>(0.0, s.crown_y, 0.0)) / s.crown_r;
    let inner = 1.0 - smoothstep(0.25, 1.0, length(q));
    let low = 1.0 - 0.5 * clamp(0.5 + 0.5 * q.y, 0.0, 1.0);
    return 1.0 - g.haze.z * inner * low;
}

// The segment holding element `i` of the draw: the last one whose `first` is <= i (binary search).
fn find_segment(i: u32, seg_first: u32, seg_count: u32) -> u32 {
    var lo = seg_first;
    var hi = seg_first + seg_count;
    loop {
        if hi - lo <= 1u {
            break;
        }
        let mid = (lo + hi) / 2u;
        if segments[mid].first <= i {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}

// Where wind moves `world`, a point of the instance standing at `base` with `seed`, at time `g.wind.w` (the same
// offset for the same point, so primitives meeting at a joint stay joined): the trunk sways by its height squared,
// a steady lean and two slow oscillations; branches and leaves flutter, fast and small, by their distance from the
// trunk's axis, in a phase that varies over the crown. Each tree has its own phase.
fn wind_offset(world: vec3<f32>, base: vec3<f32>, seed: u32) -> vec3<f32> {
    let s = g.wind.z;
    if s <= 0.0 {
        return vec3<f32>(0.0);
    }
    let dir = vec3<f32>(g.wind.x, 0.0, g.wind.y);
    let t = g.wind.w;
    let phase = f32(seed & 0xffffu) * (6.2831853 / 65536.0);
    let rel = world - base;
    let h = max(rel.y, 0.0);
    let gust = 0.6 + 0.3 * sin(0.9 * t + phase) + 0.15 * sin(2.3 * t + 1.7 * phase);
    let sway = s * 0.0012 * h * h * gust;
    let r = length(rel.xz);
    let flutter = s * 0.015 * r * sin(5.3 * t + phase + dot(rel, vec3<f32>(0.9, 0.6, 1.3)));
    return dir * (sway + 0.5 * flutter) + vec3<f32>(0.0, flutter, 0.0);
}

// Samples a pixel of the scene pass: set by the pipeline where the pass is multisampled.
override SAMPLES: u32 = 1u;

// The samples of a pixel a dithered cross-fade keeps, as a sample mask. Each sample of each pixel of a 4 × 4 block
// has a threshold of its own, spread evenly over 0..1 (sample s of every pixel between s / SAMPLES and
// (s + 1) / SAMPLES, in the pixels' Bayer order): half-way through a fade each pixel keeps half its samples of
// either level and is resolved to their mean, where one sample a pixel leaves a checkerboard of whole pixels.
fn dither_samples(mask: f32, frag: vec2<f32>) -> u32 {
    let b = bayer4(frag);
    var kept = 0u;
    for (var s = 0u; s < SAMPLES; s++) {
        if mask_keeps(mask, (f32(s) + b) / f32(SAMPLES)) {
            kept |= 1u << s;
        }
    }
    return kept;
}

// A scene-pass fragment of a near or mid tree: its colour and the samples its level's dither keeps.
struct SceneFragment {
    @location(0) color: vec4<f32>,
    @builtin(sample_mask) samples: u32,
}
