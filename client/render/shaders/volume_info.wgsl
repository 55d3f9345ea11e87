// A far-field volume's place in the 3D atlas and its box, and the atlas's bindings: shared by the far field of
// instances (volume.wgsl) and the forest of summary nodes (forest.wgsl), each concatenated after this.

struct VolumeInfo {
    // xyz: the volume's first texel in the atlas.
    atlas: vec4<u32>,
    // xyz: voxels per axis.
    dims: vec4<u32>,
    // xyz: voxel edge lengths in box units; w: the step Δs (the smallest edge).
    voxel: vec4<f32>,
    // xyz: lower corner of the non-empty voxels' box; w: metres per box unit.
    lo: vec4<f32>,
    // xyz: upper corner.
    hi: vec4<f32>,
    // xyz: the species origin in box units.
    origin: vec4<f32>,
};

@group(1) @binding(0) var atlas: texture_3d<f32>;
@group(1) @binding(1) var<storage, read> volumes: array<VolumeInfo>;

// Corner `vi` (0..36) of a unit cube's 12 triangles, counter-clockwise seen from outside: the proxy boxes of far
// instances and forest patches.
fn unit_cube(vi: u32) -> vec3<f32> {
    let corners = array<vec3<f32>, 36>(
        vec3(0., 0., 1.), vec3(1., 0., 1.), vec3(1., 1., 1.), vec3(0., 0., 1.), vec3(1., 1., 1.), vec3(0., 1., 1.),
        vec3(1., 0., 0.), vec3(0., 0., 0.), vec3(0., 1., 0.), vec3(1., 0., 0.), vec3(0., 1., 0.), vec3(1., 1., 0.),
        vec3(1., 0., 1.), vec3(1., 0., 0.), vec3(1., 1., 0.), vec3(1., 0., 1.), vec3(1., 1., 0.), vec3(1., 1., 1.),
        vec3(0., 0., 0.), vec3(0., 0., 1.), vec3(0., 1., 1.), vec3(0., 0., 0.), vec3(0., 1., 1.), vec3(0., 1., 0.),
        vec3(0., 1., 1.), vec3(1., 1., 1.), vec3(1., 1., 0.), vec3(0., 1., 1.), vec3(1., 1., 0.), vec3(0., 1., 0.),
        vec3(0., 0., 0.), vec3(1., 0., 0.), vec3(1., 0., 1.), vec3(0., 0., 0.), vec3(1., 0., 1.), vec3(0., 0., 1.),
    );
    return corners[vi];
}
