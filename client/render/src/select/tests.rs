//! Tests of the per-frame selection ([`super::FramePlan`]): bands and levels by projected size, hysteresis and
//! cross-fades, level state kept by instance id, jobs and stand-ins for missing geometry, the packed draw lists,
//! frustum culling, and terrain chunks.

use std::sync::Arc;

use canopy_worlds::world::{Terrain, World};

use super::*;
use crate::geometry::TreeGeometry;

const VIEWPORT: (u32, u32) = (1000, 1000);
/// Bounding radius of the test species' volume, metres.
const R: f32 = 5.0;

fn lod() -> LodConfig {
    LodConfig { near_px: 400.0, far_px: 50.0, mid_levels: 3, low_res_px: 24.0, ..LodConfig::default() }
}

/// A camera at the origin looking along +z with a 60° field of view.
fn camera() -> Camera {
    Camera { position: Vec3::ZERO, yaw: 0.0, pitch: 0.0, fov_y: 60.0 }
}

fn view(dt: f32, instant: bool) -> View {
    View::new(&camera(), VIEWPORT, 0.1, &lod(), dt, instant)
}

/// The distance along +z at which the test volume's sphere is `px` pixels tall.
fn at_size(px: f32) -> [f32; 3] {
    let tan_half = camera().tan_half_fov();
    [0.0, 0.0, R * VIEWPORT.1 as f32 / (px * tan_half)]
}

fn instance(id: u32, seed: u64, position: [f32; 3]) -> SceneInstance {
    SceneInstance { id: InstanceId(u64::from(id)), species: 0, position, seed, params: Vec::new() }
}

fn scene(instances: Vec<SceneInstance>) -> Scene {
    let graph = canopy_worlds::library::find("conifer").unwrap().load().unwrap();
    Scene {
        species: vec![Some(Arc::new(graph))],
        volumes: vec![None],
        instances,
        ground: Arc::new(Terrain::flat([0.0, 0.0], 1.0)).into(),
        cover: None,
        generation: 1,
        far: Default::default(),
    }
}

fn key(seed: u64, detail: u8) -> TreeKey {
    TreeKey { species: 0, seed, detail, params: 0 }
}

/// Geometry with `shapes[k]` primitives of unit shape `k` and `indices` mesh indices.
fn geometry(shapes: [u32; 3], indices: usize) -> TreeGeometry {
    let mut start = 0;
    let shape_ranges = shapes.map(|n| {
        start += n;
        start - n..start
    });
    TreeGeometry {
        prims: vec![Zeroable::zeroed(); start as usize],
        shape_ranges,
        vertices: vec![Zeroable::zeroed(); indices],
        indices: vec![0; indices],
        primitives: start as usize,
    }
}

/// A cache with these keys resident (ten frustum primitives each unless given).
fn resident(keys: &[(TreeKey, TreeGeometry)]) -> GeometryCache {
    let mut c = GeometryCache::new(10_000, 10_000, 10_000);
    for (k, g) in keys {
        c.finished(*k, Ok(g.clone()));
    }
    c.upload(1, u64::MAX, &mut FrameStats::default(), &mut |_, _| {});
    assert_eq!(c.len(), keys.len());
    c
}

fn ready_volume() -> Vec<Option<VolState>> {
    let v = SpeciesVol { levels: [10, 11, 12, 13], center: Vec3::ZERO, radius: R, height: None };
    vec![Some(VolState::Ready(v))]
}

/// Everything resident for seeds `seeds` at every detail.
fn all_resident(seeds: std::ops::RangeInclusive<u64>) -> GeometryCache {
    let keys: Vec<_> = seeds.flat_map(|s| (0..=3).map(move |d| (key(s, d), geometry([10, 0, 0], 0)))).collect();
    resident(&keys)
}

struct Frame {
    plan: FramePlan,
    state: LodState,
    stats: FrameStats,
    lod: LodConfig,
}

impl Frame {
    fn new() -> Frame {
        Frame { plan: FramePlan::default(), state: LodState::new(&lod()), stats: FrameStats::default(), lod: lod() }
    }

    fn run(&mut self, scene: &Scene, cache: &GeometryCache, vols: &[Option<VolState>], view: &View, room: usize) {
        self.state.sync(scene.generation, &scene.instances);
        self.stats = FrameStats::default();
        let residency = Residency { cache, volumes: vols };
        let input = FrameInputs { scene, residency, lod: &self.lod, view: *view, terrain: None, job_room: room };
        self.plan.plan(&input, &mut self.state, &mut self.stats);
    }

    fn shown(&self) -> Vec<Option<Level>> {
        self.state.inst.iter().map(|s| s.lod.shown).collect()
    }
}

#[test]
fn instances_fall_in_bands_by_projected_size() {
    let sizes = [800.0, 300.0, 150.0, 80.0, 30.0, 10.0];
    let s = scene(sizes.iter().enumerate().map(|(i, &px)| instance(i as u32, i as u64, at_size(px))).collect());
    let cache = all_resident(0..=5);
    let mut f = Frame::new();
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 100);
    use Level::{Detail, Far};
    assert_eq!(
        f.shown(),
        vec![Some(Detail(0)), Some(Detail(1)), Some(Detail(2)), Some(Detail(3)), Some(Far), Some(Far)]
    );
    assert_eq!((f.stats.in_view, f.stats.near, f.stats.mid, f.stats.far), (6, 1, 3, 2));
    assert_eq!((f.stats.waiting, f.stats.hidden), (0, 0));
    assert!(f.plan.jobs.is_empty(), "everything is resident");
    // Geometry draws in instance order; the far field front to back, the smallest (10 px, under half of
    // `low_res_px`) at a quarter of the full resolution.
    let drawn: Vec<_> = f.plan.geo_draws.iter().map(|g| g.key).collect();
    assert_eq!(drawn, vec![key(0, 0), key(1, 1), key(2, 2), key(3, 3)]);
    assert!(f.plan.geo_draws.iter().all(|g| g.mask == 1.0));
    let far: Vec<_> = f.plan.far_sorted.iter().map(|fi| (fi.pos_scale[2], fi.volume & VOLUME_INDEX)).collect();
    assert_eq!(far, vec![(at_size(30.0)[2], 10), (at_size(10.0)[2], 12)]);
}

#[test]
fn far_instances_take_a_coarser_volume_at_each_halving_of_their_size() {
    let sizes = [40.0, 20.0, 10.0, 4.0];
    let s = scene(sizes.iter().enumerate().map(|(i, &px)| instance(i as u32, i as u64, at_size(px))).collect());
    let cache = all_resident(0..=3);
    let volumes = |resolutions: u8| {
        let mut f = Frame::new();
        f.lod = LodConfig { far_resolutions: resolutions, ..f.lod };
        f.run(&s, &cache, &ready_volume(), &view(0.0, true), 100);
        let mut v: Vec<_> = f.plan.far_sorted.iter().map(|fi| (fi.pos_scale[2], fi.volume & VOLUME_INDEX)).collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        v.into_iter().map(|(_, v)| v).collect::<Vec<_>>()
    };
    // Nearest first: full, halved, a quarter, an eighth; with two resolutions, the halved one below 24 px.
    assert_eq!(volumes(4), [10, 11, 12, 13]);
    assert_eq!(volumes(3), [10, 11, 12, 12]);
    assert_eq!(volumes(2), [10, 11, 11, 11]);
}

#[test]
fn an_instance_whose_parameters_an_edit_set_is_amplified_again() {
    let cache = all_resident(0..=0);
    let vols = ready_volume();
    let mut f = Frame::new();
    let mut s = scene(vec![instance(0, 0, at_size(300.0))]);
    f.run(&s, &cache, &vols, &view(0.0, true), 100);
    assert!(f.plan.jobs.is_empty(), "resident with its default parameters");
    // The same instance (id, seed) with a parameter set: new geometry is asked for, not the old shape drawn.
    s.instances[0].params = vec![(0, 30.0)];
    s.generation += 1;
    f.run(&s, &cache, &vols, &view(0.0, true), 100);
    let want = TreeKey { params: TreeKey::params_hash(&[(0, 30.0)]), ..key(0, 1) };
    assert_ne!(want.params, 0);
    assert_eq!(f.plan.jobs.iter().map(|j| j.key).collect::<Vec<_>>(), vec![want]);
}

#[test]
fn hysteresis_holds_a_level_near_its_threshold() {
    let cache = all_resident(0..=0);
    let vols = ready_volume();
    let mut f = Frame::new();
    let at = |px: f32| scene(vec![instance(0, 0, at_size(px))]);
    f.run(&at(210.0), &cache, &vols, &view(0.0, true), 100);
    assert_eq!(f.shown(), vec![Some(Level::Detail(1))]);
    // Detail 1 is [200, 400) px: 180 px is within 15 % of its border, 160 px is not.
    f.run(&at(180.0), &cache, &vols, &view(0.0, true), 100);
    assert_eq!(f.shown(), vec![Some(Level::Detail(1))]);
    f.run(&at(160.0), &cache, &vols, &view(0.0, true), 100);
    assert_eq!(f.shown(), vec![Some(Level::Detail(2))]);
    // Back up to 220 px stays at detail 2; 240 px goes back to detail 1.
    f.run(&at(220.0), &cache, &vols, &view(0.0, true), 100);
    assert_eq!(f.shown(), vec![Some(Level::Detail(2))]);
    f.run(&at(240.0), &cache, &vols, &view(0.0, true), 100);
    assert_eq!(f.shown(), vec![Some(Level::Detail(1))]);
    // A fresh instance at 180 px takes the ideal level at once.
    let mut fresh = Frame::new();
    fresh.run(&at(180.0), &cache, &vols, &view(0.0, true), 100);
    assert_eq!(fresh.shown(), vec![Some(Level::Detail(2))]);
}

#[test]
fn a_level_change_cross_fades_with_complementary_masks() {
    let cache = all_resident(0..=0);
    let vols = ready_volume();
    let mut f = Frame::new();
    let at = |px: f32| scene(vec![instance(0, 0, at_size(px))]);
    // A fresh instance fades in from nothing; a whole fade time later it shows detail 1.
    f.run(&at(300.0), &cache, &vols, &view(lod().fade_seconds, false), 100);
    assert_eq!(f.plan.geo_draws.iter().map(|g| (g.key.detail, g.mask)).collect::<Vec<_>>(), vec![(1, 1.0)]);
    // A quarter of the fade time later, at 120 px: detail 2 fades in over detail 1.
    f.run(&at(120.0), &cache, &vols, &view(lod().fade_seconds / 4.0, false), 100);
    let draws: Vec<_> = f.plan.geo_draws.iter().map(|g| (g.key.detail, g.mask)).collect();
    assert_eq!(draws, vec![(2, 0.25), (1, -0.25)]);
    assert_eq!(f.stats.mid, 1, "counted once, at the level fading in");
}

#[test]
fn missing_geometry_is_asked_for_and_the_nearest_resident_level_stands_in() {
    // Instance 0 wants detail 1 and has detail 3 resident; instance 1 wants detail 0 and has nothing but the
    // far volume.
    let s = scene(vec![instance(0, 1, at_size(300.0)), instance(1, 2, at_size(1000.0))]);
    let mut cache = resident(&[(key(1, 3), geometry([10, 0, 0], 0))]);
    let mut f = Frame::new();
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 100);
    assert_eq!(f.shown(), vec![Some(Level::Detail(3)), Some(Level::Far)], "coarser stand-ins first");
    assert_eq!(f.stats.waiting, 2);
    let jobs: Vec<_> = f.plan.jobs.iter().map(|j| (j.key, j.instance)).collect();
    assert_eq!(jobs, vec![(key(2, 0), 1), (key(1, 1), 0)], "biggest on screen first");
    assert!(f.plan.jobs[0].priority > f.plan.jobs[1].priority);
    // Once asked for, a key is not asked for again; the stand-ins stay.
    for j in &f.plan.jobs {
        cache.mark_pending(j.key);
    }
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 100);
    assert!(f.plan.jobs.is_empty());
    assert_eq!((f.stats.waiting, f.shown()), (2, vec![Some(Level::Detail(3)), Some(Level::Far)]));
    // A key that failed is drawn far instead, and neither waited for nor asked for.
    cache.finished(key(1, 1), Err("budget".into()));
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 100);
    assert_eq!(f.state.inst[0].lod.shown, Some(Level::Far));
    assert_eq!(f.stats.waiting, 1);
    // Without a volume or any geometry, nothing is drawn; the instance waits for its volume.
    let pending = vec![Some(VolState::Pending)];
    let mut bare = Frame::new();
    bare.run(&s, &GeometryCache::new(100, 100, 100), &pending, &view(0.0, true), 100);
    assert_eq!(bare.shown(), vec![None, None]);
    assert_eq!((bare.stats.hidden, bare.stats.waiting), (2, 2));
    assert!(bare.plan.geo_draws.is_empty() && bare.plan.far_sorted.is_empty());
}

#[test]
fn jobs_are_bounded_and_each_key_is_asked_for_once() {
    // Instances 0 and 3 share a seed: one key.
    let s = scene(vec![
        instance(0, 7, at_size(500.0)),
        instance(1, 8, at_size(900.0)),
        instance(2, 9, at_size(450.0)),
        instance(3, 7, at_size(1000.0)),
    ]);
    let cache = GeometryCache::new(100, 100, 100);
    let mut f = Frame::new();
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 2);
    let jobs: Vec<_> = f.plan.jobs.iter().map(|j| (j.key.seed, j.instance)).collect();
    assert_eq!(jobs, vec![(7, 3), (8, 1)]);
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 10);
    let jobs: Vec<_> = f.plan.jobs.iter().map(|j| (j.key.seed, j.instance)).collect();
    assert_eq!(jobs, vec![(7, 3), (8, 1), (9, 2)]);
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 0);
    assert!(f.plan.jobs.is_empty());
    assert_eq!(f.stats.waiting, 4, "every instance still waits");
}

#[test]
fn draw_lists_group_segments_by_shape_and_tessellation() {
    let s = scene(vec![instance(0, 1, at_size(800.0)), instance(1, 2, at_size(150.0))]);
    // Seed 1 at detail 0: 4 frusta, 6 spheres and a 9-index mesh; seed 2 at detail 2: 3 frusta and 2 boxes.
    let cache = resident(&[(key(1, 0), geometry([4, 6, 0], 9)), (key(2, 2), geometry([3, 0, 2], 0))]);
    let e1 = cache.get(&key(1, 0)).unwrap().clone();
    let e2 = cache.get(&key(2, 2)).unwrap().clone();
    let mut f = Frame::new();
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 100);
    let draws: Vec<_> = f.plan.camera.prims.iter().map(|d| (d.shape, d.tess, d.slot, d.instances)).collect();
    assert_eq!(draws, vec![(0, 0, 0, 4), (0, 2, 1, 3), (1, 0, 2, 6), (2, 2, 3, 2)]);
    assert_eq!(f.plan.camera.mesh, Some((4, 9)));
    let seg = |base: u64, count: u32, pos: [f32; 3]| (base as u32, count, pos);
    let segs: Vec<_> = f.plan.segments.iter().map(|s| (s.base, s.count, s.pos)).collect();
    let (a, b) = (at_size(800.0), at_size(150.0));
    assert_eq!(
        segs,
        vec![
            seg(e1.prims.start, 4, a),
            seg(e2.prims.start, 3, b),
            seg(e1.prims.start + 4, 6, a),
            seg(e2.prims.start + 3, 2, b),
            seg(e1.indices.start, 9, a),
        ]
    );
    assert_eq!(f.plan.segments[4].vbase, e1.verts.start as u32);
    // Each draw's uniform names its segments, its shape and its place in the visible list (the primitives before it).
    let uniform = |slot: u64| -> DrawUniform {
        let at = (slot * DRAW_STRIDE) as usize;
        bytemuck::pod_read_unaligned(&f.plan.uniforms[at..at + DRAW_UNIFORM_BYTES])
    };
    assert_eq!(f.plan.uniforms.len() as u64, DRAW_STRIDE * DRAW_SLOTS);
    assert_eq!(uniform(1), DrawUniform { seg_first: 1, seg_count: 1, kind: 0, visible_base: 4 });
    assert_eq!(uniform(3), DrawUniform { seg_first: 3, seg_count: 1, kind: 2, visible_base: 13 });
    assert_eq!(uniform(4), DrawUniform { seg_first: 4, seg_count: 1, kind: 0, visible_base: 0 });
    assert_eq!((f.stats.primitives, f.stats.mesh_triangles), (15, 3));
    // The sky, four primitive draws, the meshes (no terrain, no far field).
    assert_eq!(f.stats.draw_calls, 6);
}

#[test]
fn segments_of_one_draw_are_numbered_within_it() {
    let s = scene((0..3).map(|i| instance(i, 1, [i as f32, 0.0, at_size(800.0)[2]])).collect());
    let cache = resident(&[(key(1, 0), geometry([5, 0, 0], 0))]);
    let mut f = Frame::new();
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 100);
    assert_eq!(f.plan.camera.prims.len(), 1);
    assert_eq!(f.plan.camera.prims[0].instances, 15);
    let firsts: Vec<_> = f.plan.segments.iter().map(|s| (s.first, s.pos[0])).collect();
    assert_eq!(firsts, vec![(0, 0.0), (5, 1.0), (10, 2.0)]);
    // Nothing to draw: one zeroed segment, so the buffer is never empty.
    f.run(&scene(Vec::new()), &cache, &ready_volume(), &view(0.0, true), 100);
    assert_eq!(f.plan.segments, vec![Segment::zeroed()]);
    assert_eq!((f.plan.camera.prims.len(), f.plan.camera.mesh, f.stats.draw_calls), (0, None, 1));
}

#[test]
fn the_frustum_culls_instances_behind_and_beside_and_tiny_ones() {
    let z = at_size(300.0)[2];
    // The 60° frustum's side plane at this depth; a sphere just beyond it by less than its radius is in view.
    let edge = z * camera().tan_half_fov();
    let beyond = |m: f32| [edge + m / (30f32.to_radians().cos()), 0.0, z];
    let s = scene(vec![
        instance(0, 0, [0.0, 0.0, z]),
        instance(1, 0, [0.0, 0.0, -z]),
        instance(2, 0, beyond(R * 0.9)),
        instance(3, 0, beyond(R * 1.1)),
        instance(4, 0, [0.0, 0.0, z * 1000.0]),
    ]);
    let cache = all_resident(0..=0);
    let mut f = Frame::new();
    f.run(&s, &cache, &ready_volume(), &view(0.0, true), 100);
    assert_eq!(f.stats.in_view, 2, "ahead and just touching the side; not behind, beyond, or below a pixel");
    assert_eq!(f.shown(), vec![Some(Level::Detail(1)), None, Some(Level::Detail(1)), None, None]);
    assert_eq!(f.plan.geo_draws.len(), 2);
    // Without a volume the stand-in sphere (FALLBACK_RADIUS, raised FALLBACK_CENTER_HEIGHT) decides: 1.1 R
    // beyond the plane is within it. Its projected size is bigger too: instance 0 wants full detail.
    let mut g = Frame::new();
    g.run(&s, &GeometryCache::new(100, 100, 100), &[Some(VolState::Pending)], &view(0.0, true), 100);
    const { assert!(R * 1.1 < FALLBACK_RADIUS) };
    assert_eq!(g.stats.in_view, 3, "all but the one behind and the one below a pixel");
    let jobs: Vec<_> = g.plan.jobs.iter().map(|j| (j.key, j.instance)).collect();
    assert_eq!(jobs, vec![(key(0, 0), 0), (key(0, 1), 2)], "instances 2 and 3 share a key");
}

#[test]
fn lod_state_is_carried_over_by_id() {
    let mut st = LodState::new(&lod());
    let ids = |v: &[u32]| v.iter().map(|&id| instance(id, 0, [0.0; 3])).collect::<Vec<_>>();
    st.sync(1, &ids(&[1, 3, 5]));
    for s in &mut st.inst {
        s.target = Some(Level::Detail(s.id.0 as u8));
    }
    st.sync(2, &ids(&[0, 3, 4, 5, 9]));
    let got: Vec<_> = st.inst.iter().map(|s| (s.id.0, s.target)).collect();
    use Level::Detail;
    assert_eq!(got, vec![(0, None), (3, Some(Detail(3))), (4, None), (5, Some(Detail(5))), (9, None)]);
    // The same generation keeps everything.
    st.inst[0].target = Some(Level::Far);
    st.sync(2, &ids(&[0, 3, 4, 5, 9]));
    assert_eq!(st.inst[0].target, Some(Level::Far));
}

#[test]
fn terrain_chunks_are_culled_and_coarser_far_away() {
    let world = World::default_world();
    let mesh = TerrainMesh::build(&world.terrain, None);
    // In the middle of the 2 km world, looking north-east.
    let eye = Vec3::new(0.0, world.height(0.0, 0.0) + 20.0, 0.0);
    let cam = Camera { position: eye, yaw: 45f32.to_radians(), pitch: -0.05, fov_y: 60.0 };
    let v = View::new(&cam, VIEWPORT, 0.1, &lod(), 0.0, true);
    let mut plan = FramePlan::default();
    let mut stats = FrameStats::default();
    plan.choose_terrain(Some(&mesh), &v, &mut stats);
    let drawn = &plan.camera.terrain;
    assert!(!drawn.is_empty() && drawn.len() < mesh.chunks.len(), "{} of {}", drawn.len(), mesh.chunks.len());
    // (distance, step) of each drawn chunk, nearest first.
    let mut steps: Vec<(f32, usize)> = drawn
        .iter()
        .map(|r| {
            let (c, level) = mesh
                .chunks
                .iter()
                .find_map(|c| c.levels.iter().position(|l| l == r).map(|level| (c, level)))
                .expect("a chunk's level");
            ((c.center - eye).length(), level)
        })
        .collect();
    steps.sort_by(|a, b| a.0.total_cmp(&b.0));
    assert_eq!(steps[0].1, 0, "the chunk under the eye at full detail");
    assert!(steps.last().unwrap().1 >= 1, "the farthest chunk coarser: {steps:?}");
    let tris: u64 = drawn.iter().map(|r| u64::from(r.end - r.start) / 3).sum();
    assert_eq!(stats.terrain_triangles, tris);
    // Chunks behind the camera are not drawn.
    let behind = mesh.chunks.iter().filter(|c| (c.center - eye).dot(cam.forward()) < -c.radius).count();
    assert!(behind > 0 && drawn.len() <= mesh.chunks.len() - behind);
}

#[test]
fn each_shadow_cascade_draws_the_trees_in_its_volume_and_those_out_of_view_that_shade_the_view() {
    // The sun straight above and a little to −z; cascades as boxes around the camera's first 40 m and beyond.
    let sun = Vec3::new(0.0, 1.0, -0.2).normalize();
    let near = glam::camera::rh::proj::directx::orthographic(-40.0, 40.0, -40.0, 40.0, -500.0, 100.0);
    let light = glam::camera::rh::view::look_to_mat4(Vec3::ZERO, -sun, Vec3::Z);
    // The other two cascades far away, holding nothing.
    let away =
        Frustum::from_matrix(glam::camera::rh::proj::directx::orthographic(1e4, 1e4 + 1.0, 1e4, 1e4 + 1.0, 0.0, 1.0));
    let mut v = view(0.0, true);
    v.shadows = Some(ShadowView { sun, reach: 300.0, cascades: [Frustum::from_matrix(near * light), away, away] });
    // In view near and far; out of view behind the camera, 12 m back (its shadow falls short of the view), and
    // beside it, just out of view (its shadow does not reach in either: the sun is above).
    let s = scene(vec![
        instance(0, 1, at_size(800.0)),
        instance(1, 2, at_size(60.0)),
        instance(2, 3, [0.0, 0.0, -12.0]),
        instance(3, 4, [60.0, 0.0, 30.0]),
    ]);
    let cache = all_resident(1..=4);
    let mut f = Frame::new();
    f.run(&s, &cache, &ready_volume(), &v, 100);
    let count = |d: &ViewDraws| d.prims.iter().map(|p| p.instances).sum::<u32>();
    assert_eq!(count(&f.plan.camera), 20, "the two trees in view");
    assert_eq!(count(&f.plan.cascades[0]), 10, "only the near one lies in the near cascade");
    assert!(f.plan.cascades[1].prims.is_empty() && f.plan.cascades[2].prims.is_empty());
    assert_eq!(f.stats.shadow_casters, 0, "{:?}", f.stats);
    // Lower the sun toward −z: the tree behind the camera now casts into view; drawn for the cascades only.
    let low = Vec3::new(0.0, 0.3, -1.0).normalize();
    let light = glam::camera::rh::view::look_to_mat4(Vec3::ZERO, -low, Vec3::Y);
    v.shadows = Some(ShadowView { sun: low, reach: 300.0, cascades: [Frustum::from_matrix(near * light), away, away] });
    f.run(&s, &cache, &ready_volume(), &v, 100);
    assert_eq!(f.stats.shadow_casters, 1, "{:?}", f.stats);
    assert_eq!(count(&f.plan.camera), 20, "the caster out of view is not drawn by the camera");
    assert!(count(&f.plan.cascades[0]) >= 20, "{}", count(&f.plan.cascades[0]));
}

#[test]
fn the_radix_sort_orders_by_the_high_bits_and_keeps_ties_in_order() {
    let mut rng = 0x9e37_79b9_7f4a_7c15u64;
    let mut keys: Vec<u64> = (0..5000u64)
        .map(|i| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            // Few distinct high words, so that many keys tie.
            (rng % 97 * 0x0101_0101 % (1 << 32)) << 32 | i
        })
        .collect();
    let mut expected = keys.clone();
    expected.sort_by_key(|k| (k >> 32, k & 0xffff_ffff));
    super::radix_sort_high(&mut keys, &mut Vec::new());
    assert_eq!(keys, expected);
}

#[test]
fn instances_over_many_runs_are_chosen_as_one_run_would_choose_them() {
    // Three runs and a part: bands, stand-ins, requests and culled instances in every run.
    let sizes = [800.0, 300.0, 150.0, 80.0, 30.0, 10.0];
    let n = 3 * LEVEL_RUN + 123;
    let instances = (0..n)
        .map(|i| {
            let [x, y, z] = at_size(sizes[i % sizes.len()]);
            let z = if i % 7 == 0 { -z } else { z };
            instance(i as u32, (i % 50) as u64, [x + (i % 13) as f32, y, z])
        })
        .collect();
    let s = scene(instances);
    let cache = all_resident(0..=29);
    let vols = ready_volume();
    let mut runs = Frame::new();
    runs.run(&s, &cache, &vols, &view(0.0, true), 64);

    let mut one = Frame::new();
    one.state.sync(s.generation, &s.instances);
    let residency = Residency { cache: &cache, volumes: &vols };
    let input = FrameInputs { scene: &s, residency, lod: &one.lod, view: view(0.0, true), terrain: None, job_room: 64 };
    let mut whole = ChosenRun::default();
    choose_run(&input, &one.state.levels.clone(), 0, &mut one.state.inst, &mut whole);

    let same = |a: String, b: String, what: &str| assert!(a == b, "{what} differ");
    same(format!("{:?}", runs.plan.geo_draws), format!("{:?}", whole.geo_draws), "geometry draws");
    // The plan has ordered its requests by priority since (stably: instance order among equals).
    let mut requests = whole.requests.clone();
    requests.sort_by(|a, b| b.priority.total_cmp(&a.priority));
    same(format!("{:?}", runs.plan.requests), format!("{requests:?}"), "requests");
    let mut order: Vec<usize> = (0..whole.far.len()).collect();
    order.sort_by_key(|&i| (whole.far_dist[i], i));
    let far: Vec<FarInstance> = order.iter().map(|&i| whole.far[i]).collect();
    same(format!("{:?}", runs.plan.far_sorted), format!("{far:?}"), "far instances");
    let counts = |s: &FrameStats| (s.shadow_casters, s.in_view, s.waiting, s.near, s.mid, s.far, s.hidden);
    assert_eq!(counts(&runs.stats), counts(&whole.stats));
    same(format!("{:?}", runs.shown()), format!("{:?}", one.shown()), "levels shown");
    // Every kind of outcome is there to be joined.
    let c = counts(&runs.stats);
    assert!(c.1 > 0 && c.2 > 0 && c.3 > 0 && c.4 > 0 && c.5 > 0 && c.1 < n, "{c:?}");
    assert!(!whole.requests.is_empty() && whole.far.len() > LEVEL_RUN, "{} far", whole.far.len());
}
