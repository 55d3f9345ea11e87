// The far field in one compute pass (bindings from 1: binding 0 of group 3 is the fragment path's opacity,
// far_accum.wgsl, in the same module): a workgroup per 16 × 16-pixel tile (`src/bins.rs`), each pixel walking its
// tile's list of far instances and forest patches front to back along its eye ray, compositing what it meets
// (`march_volume` in volume.wgsl, `march_patch` in forest.wgsl) until it is opaque, and writing the result to the
// accumulation target that is then laid over the scene. Nothing behind the opaque scene is marched: its depth
// gives each ray's end. (GPUs whose graphics stages run on a few of their cores, such as NVIDIA's H100 and H200,
// run this on all of them.)

@group(3) @binding(1) var scene_depth: texture_depth_2d;
@group(3) @binding(2) var accum_out: texture_storage_2d<rgba16float, write>;
// Where each tile's list starts in `tile_items`, and one more for the end.
@group(3) @binding(3) var<storage, read> tile_offsets: array<u32>;
// Items: a far instance's index, or a forest patch's with PATCH_BIT set.
@group(3) @binding(4) var<storage, read> tile_items: array<u32>;
// The frame's far instances, 6 words each (`FarInstance`: position and scale, volume, dither mask).
@group(3) @binding(5) var<storage, read> far_words: array<u32>;
// The frame's forest patches, 18 words each (`ForestPatch`).
@group(3) @binding(6) var<storage, read> patch_words: array<u32>;

// PATCH_BIT and MARCH_TILE (a tile's side, the workgroup's) come from `src/bins.rs`, prepended by
// `src/pipelines.rs`; OPAQUE (where a ray stops) and `stop_alpha` from far_accum.wgsl.

fn word_f(w: u32) -> f32 {
    return bitcast<f32>(w);
}

fn load_patch(i: u32) -> Patch {
    let b = i * 22u;
    let w = array<u32, 22>(
        patch_words[b], patch_words[b + 1u], patch_words[b + 2u], patch_words[b + 3u], patch_words[b + 4u],
        patch_words[b + 5u], patch_words[b + 6u], patch_words[b + 7u], patch_words[b + 8u], patch_words[b + 9u],
        patch_words[b + 10u], patch_words[b + 11u], patch_words[b + 12u], patch_words[b + 13u],
        patch_words[b + 14u], patch_words[b + 15u], patch_words[b + 16u], patch_words[b + 17u],
        patch_words[b + 18u], patch_words[b + 19u], patch_words[b + 20u], patch_words[b + 21u],
    );
    return Patch(
        vec4<f32>(word_f(w[0]), word_f(w[1]), word_f(w[2]), word_f(w[3])),
        vec2<f32>(word_f(w[4]), word_f(w[5])),
        vec2<u32>(w[6], w[7]),
        vec2<u32>(w[8], w[9]),
        vec2<u32>(w[10], w[11]),
        vec3<f32>(word_f(w[12]), word_f(w[13]), word_f(w[14])),
        w[15],
        word_f(w[16]),
        word_f(w[17]),
        vec2<f32>(word_f(w[18]), word_f(w[19])),
        vec2<f32>(word_f(w[20]), word_f(w[21])),
    );
}

@compute @workgroup_size(MARCH_TILE, MARCH_TILE)
fn cs_far(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(workgroup_id) wg: vec3<u32>) {
    let size = vec2<u32>(g.viewport.xy);
    if gid.x >= size.x || gid.y >= size.y {
        return;
    }
    let frag = vec2<f32>(gid.xy) + 0.5;
    let tiles_x = (size.x + MARCH_TILE - 1u) / MARCH_TILE;
    let tile = wg.y * tiles_x + wg.x;
    let first = tile_offsets[tile];
    let last = tile_offsets[tile + 1u];
    var color = vec3<f32>(0.0);
    var alpha = 0.0;
    if first < last {
        // The eye ray through the pixel's centre, and how far the opaque scene is along it (reversed Z: 0 is
        // nothing).
        let ndc = vec2<f32>(frag.x * g.viewport.z * 2.0 - 1.0, 1.0 - frag.y * g.viewport.w * 2.0);
        let near = g.inv_view_proj * vec4<f32>(ndc, 1.0, 1.0);
        let d = normalize(near.xyz / near.w - g.eye.xyz);
        let depth = textureLoad(scene_depth, vec2<i32>(gid.xy), 0);
        var t_scene = 1e30;
        if depth > 0.0 {
            let p = g.inv_view_proj * vec4<f32>(ndc, depth, 1.0);
            t_scene = distance(p.xyz / p.w, g.eye.xyz);
        }
        for (var k = first; k < last; k++) {
            let item = tile_items[k];
            let stop = stop_alpha(alpha);
            var c = vec4<f32>(0.0);
            if (item & PATCH_BIT) != 0u {
                let p = load_patch(item & ~PATCH_BIT);
                if dither_keeps(p.params.z, frag) {
                    c = march_patch(p, d, frag, stop, t_scene);
                }
            } else {
                let b = item * 6u;
                let inst = vec4<f32>(word_f(far_words[b]), word_f(far_words[b + 1u]), word_f(far_words[b + 2u]),
                    word_f(far_words[b + 3u]));
                if dither_keeps(word_f(far_words[b + 5u]), frag) {
                    c = march_volume(inst, far_words[b + 4u], d, stop, t_scene);
                }
            }
            color += (1.0 - alpha) * c.rgb;
            alpha += (1.0 - alpha) * c.a;
            if alpha >= OPAQUE {
                break;
            }
        }
    }
    textureStore(accum_out, vec2<i32>(gid.xy), vec4<f32>(color, alpha));
}
