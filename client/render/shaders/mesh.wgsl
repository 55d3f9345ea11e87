// Meshes by vertex pulling: leaves, trunk bases and (in merged mode) whole trees. Vertex `i` of a draw finds its
// segment by binary search, reads its index from the index arena and its vertex from the vertex arena.

// `segments` is binding 0 of group 1 and `draw` binding 0 of group 2 (segment.wgsl).
@group(1) @binding(1) var<storage, read> verts: array<u32>;
@group(1) @binding(2) var<storage, read> indices: array<u32>;

@vertex
fn vs_mesh(@builtin(vertex_index) vi: u32) -> GeoOut {
    let s = segments[find_segment(vi, draw.seg_first, draw.seg_count)];
    let idx = indices[s.base + vi - s.first];
    let w = (s.vbase + idx) * 5u;
    let p = vec3<f32>(bitcast<f32>(verts[w]), bitcast<f32>(verts[w + 1u]), bitcast<f32>(verts[w + 2u]));
    var out: GeoOut;
    let world = p + s.pos + wind_offset(p + s.pos, s.pos, s.seed);
    out.clip = g.view_proj * vec4<f32>(world, 1.0);
    out.world = world;
    let n = unpack4x8snorm(verts[w + 3u]);
    out.normal = n.xyz;
    out.thin = n.w;
    out.bark = vec4<f32>(0.0);
    out.ao = crown_occlusion(p, s);
    let c = verts[w + 4u];
    out.color = unpack4x8unorm(c).rgb * instance_tint(s.seed);
    out.card = leaf_card(c >> 24u);
    out.mask = s.mask;
    return out;
}

// A mesh into the sun's shadow maps: depth only, a leaf card's silhouette cut out.
@fragment
fn fs_mesh_shadow(in: GeoOut) {
    if !leaf_keeps(in.card) {
        discard;
    }
}

// The share of the sun's light a leaf passes to its far side.
const TRANSLUCENCY: f32 = 0.5;

// Set where the scene pass is multisampled: a leaf card's edge becomes its coverage (alpha-to-coverage), not a cut
// a whole pixel at a time.
override ALPHA_TO_COVERAGE: bool = false;

@fragment
fn fs_mesh(in: GeoOut, @builtin(front_facing) front: bool) -> SceneFragment {
    // Before any discard: its derivative needs the whole quad.
    let coverage = leaf_coverage(in.card);
    let samples = dither_samples(in.mask, in.clip.xy);
    if samples == 0u || coverage <= select(0.5, 0.0, ALPHA_TO_COVERAGE) {
        discard;
    }
    // Leaves are two-sided: light the side that faces the viewer.
    var n = normalize(in.normal);
    if !front {
        n = -n;
    }
    // The sun's visibility on the sunlit side (a leaf seen from behind is lit through: its own shadow is behind it).
    let toward = dot(n, g.sun_dir.xyz);
    let sun = sun_visibility(in.world, select(n, -n, toward < 0.0));
    let color = in.color * leaf_veins(in.card);
    var lit = shade_occluded(color, n, sun, in.ao);
    // Light through a leaf with the sun behind it: a share of the sun's diffuse light, in the leaf's colour.
    lit += in.thin * TRANSLUCENCY * sun * max(-toward, 0.0) * g.sun_color.w * g.sun_color.rgb * color;
    return SceneFragment(vec4<f32>(with_fog(lit, in.world), select(1.0, coverage, ALPHA_TO_COVERAGE)), samples);
}
