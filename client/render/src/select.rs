//! Per-frame selection, pure (no GPU, no clock; the level choice runs on every core, its lists joined in instance
//! order, so the plan is the same on any number of cores): from the camera, the scene's instances, their
//! level-of-detail state and what is resident, a [`FramePlan`] — which instance is in view, in which band and at
//! which level, which geometry the workers must make, the far instances front to back, the geometry draw lists
//! packed as the shaders read them, and the terrain chunks with their steps. The renderer submits the jobs and
//! writes the plan's buffers; nothing here touches wgpu.

use std::collections::HashSet;
use std::ops::Range;
use std::sync::Mutex;

use bytemuck::{Pod, Zeroable};
use canopy_protocol::sync::Locked;
use canopy_worlds::world::{InstanceId, par};
use glam::Vec3;

use super::cache::GeometryCache;
use super::camera::{Camera, Frustum};
use super::lod::{Band, InstanceLod, Level, LodConfig, projected_size};
use super::scene::{Scene, SceneInstance};
use super::stats::FrameStats;
use super::terrain::TerrainMesh;
use super::volume::FAR_LEVELS;
use super::volume::instance_scale;
use super::workers::TreeKey;

/// Height of the bounding sphere's centre above the species origin, metres at scale 1, while the species'
/// far-field volume (which gives the true sphere) is not known: about a mid-sized tree's crown.
pub(crate) const FALLBACK_CENTER_HEIGHT: f32 = 6.0;
/// Radius of that stand-in bounding sphere, metres at scale 1 (generous, so a tree is culled late rather than
/// early).
pub(crate) const FALLBACK_RADIUS: f32 = 8.0;
/// Terrain chunks take the coarsest step whose grid squares are at most this many pixels on screen.
pub(crate) const TERRAIN_SQUARE_PX: f32 = 12.0;
/// Nearest distance, metres, a terrain chunk's step is chosen for (a chunk around the eye counts as this far).
pub(crate) const TERRAIN_NEAREST: f32 = 1.0;
/// Unit shapes of primitive instances (frusta, spheres, boxes: [`super::geometry::UnitShape`]).
pub(crate) const UNIT_SHAPES: usize = 3;
/// Tessellations of the unit meshes, one per detail level (coarser levels share the last).
pub(crate) const TESSELLATIONS: usize = 4;
/// Alignment of per-draw uniforms (the WebGPU minimum for dynamic offsets).
pub(crate) const DRAW_STRIDE: u64 = 256;
/// Draw slots: for the camera and each shadow cascade, one per unit shape and tessellation and one for meshes.
pub(crate) const DRAW_SLOTS: u64 = 64;
const _: () = assert!(((UNIT_SHAPES * TESSELLATIONS + 1) * (1 + crate::SHADOW_CASCADES)) as u64 <= DRAW_SLOTS);
/// Bytes of one [`DrawUniform`] within its slot.
pub(crate) const DRAW_UNIFORM_BYTES: usize = size_of::<DrawUniform>();

/// The tessellation of a detail level.
pub(crate) fn tess(detail: u8) -> usize {
    usize::from(detail).min(TESSELLATIONS - 1)
}

/// A run of one tree's primitives (or mesh indices) drawn at a position, as the shaders read it.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub(crate) struct Segment {
    /// First instance (or index) of the run within its draw.
    pub first: u32,
    /// First primitive (or index) in the arena.
    pub base: u32,
    /// First vertex in the arena (meshes).
    pub vbase: u32,
    /// Primitives (or indices) of the run.
    pub count: u32,
    /// World position of the species origin.
    pub pos: [f32; 3],
    /// Dither mask (see [`super::lod::LodDraw::mask`]).
    pub mask: f32,
    /// The instance's seed folded to 32 bits ([`fold_seed`]): its phase in the wind.
    pub seed: u32,
    /// The crown for ambient occlusion: the tree's bounding sphere's centre height above `pos`, and its radius.
    pub crown: [f32; 2],
    /// To the shader's stride (48 bytes).
    pub pad: u32,
}

/// The bits of [`FarInstance::volume`] that index the volume (the rest is the instance's tint).
pub(crate) const VOLUME_INDEX: u32 = 0xff_ffff;

/// An instance seed folded to the 32 bits a [`Segment`] carries.
pub(crate) fn fold_seed(seed: u64) -> u32 {
    (seed ^ (seed >> 32)) as u32
}

/// The uniform of one draw: its segments and unit shape.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub(crate) struct DrawUniform {
    /// First segment in the frame's segment list.
    pub seg_first: u32,
    /// Segments.
    pub seg_count: u32,
    /// Unit shape (0 for meshes).
    pub kind: u32,
    /// The draw's first entry in the visible list the GPU cull writes (`renderer/cull.rs`): the primitives of the
    /// view's draws before it.
    pub visible_base: u32,
}

/// One far instance as the volume pipeline reads it (a vertex buffer entry).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub(crate) struct FarInstance {
    /// Position of the species origin and the instance scale.
    pub pos_scale: [f32; 4],
    /// Index of the volume (full or low resolution) in the low 24 bits; the instance's tint (its folded seed's top
    /// byte, `common.wgsl` `instance_tint`) in the top 8.
    pub volume: u32,
    /// Dither mask.
    pub mask: f32,
}

/// One instanced primitive draw of the frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct PrimDraw {
    /// Unit shape.
    pub shape: usize,
    /// Tessellation.
    pub tess: usize,
    /// Uniform slot.
    pub slot: u32,
    /// Instances (primitives).
    pub instances: u32,
    /// Its segments in the frame's segment list: the first and how many.
    pub seg_first: u32,
    pub seg_count: u32,
    /// Its first entry in the visible list (the view's primitives in the draws before it).
    pub visible_base: u32,
}

/// One tree to draw from the geometry cache.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct GeoDraw {
    /// The cached geometry.
    pub key: TreeKey,
    /// World position of the species origin.
    pub position: [f32; 3],
    /// Dither mask.
    pub mask: f32,
    /// Centre and radius of the tree's bounding sphere (which shadow cascades it falls in).
    pub sphere: (Vec3, f32),
    /// Whether the camera sees it (false: drawn only into the shadow maps, for the shadow it casts into view).
    pub seen: bool,
}

/// What one view draws of the opaque geometry: the camera's, or a shadow cascade's.
#[derive(Debug, Default)]
pub(crate) struct ViewDraws {
    /// Instanced primitive draws, by unit shape then tessellation.
    pub prims: Vec<PrimDraw>,
    /// The mesh draw: uniform slot and index count.
    pub mesh: Option<(u32, u32)>,
    /// Terrain index ranges.
    pub terrain: Vec<Range<u32>>,
}

impl ViewDraws {
    fn clear(&mut self) {
        self.prims.clear();
        self.mesh = None;
        self.terrain.clear();
    }
}

/// Geometry the workers must make: a key for an instance, with its projected size as priority.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct JobRequest {
    /// What to make.
    pub key: TreeKey,
    /// Index of the instance in [`Scene::instances`] (its graph, seed and parameters).
    pub instance: usize,
    /// Projected size, pixels (bigger on screen first).
    pub priority: f32,
}

/// A species' far-field volumes, resident in the atlas.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SpeciesVol {
    /// Volume indices at full resolution, then halved, a quarter and an eighth of it (the coarsest there is
    /// repeated where a species has fewer).
    pub levels: [u32; FAR_LEVELS],
    /// Bounding sphere centre relative to the species origin, metres at scale 1.
    pub center: Vec3,
    /// Bounding sphere radius, metres at scale 1.
    pub radius: f32,
    /// The species' `height` parameter slot and the representative's value (instance scales).
    pub height: Option<(u16, f32)>,
}

/// Where a species' far-field volumes stand.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum VolState {
    /// Being voxelised.
    Pending,
    /// Resident.
    Ready(SpeciesVol),
    /// Voxelisation failed or the atlas is full: the species has no far field.
    Failed,
}

/// One instance's selection state, carried across frames.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct InstState {
    /// The instance id.
    pub id: InstanceId,
    /// What it draws while levels change.
    pub lod: InstanceLod,
    /// The level chosen last (with hysteresis), whether or not it can be drawn.
    pub target: Option<Level>,
    /// The instance scale, once the species' volume gave its reference height (forgotten when an edit changes the
    /// parameters it was computed from).
    pub scale: Option<f32>,
    /// The hash of its parameters ([`TreeKey::params_hash`]), taken when a scene generation arrives rather than
    /// every frame (reading each instance's parameters from the heap was 40 % of a frame's selection).
    pub params: u64,
}

impl InstState {
    /// The state of an instance seen for the first time: nothing chosen or drawn yet.
    pub(crate) fn new(id: InstanceId) -> InstState {
        InstState { id, lod: InstanceLod::default(), target: None, scale: None, params: 0 }
    }
}

/// What is resident, as the selection sees it.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Residency<'a> {
    /// The geometry cache.
    pub cache: &'a GeometryCache,
    /// Far-field volumes by species id (`None`: not asked for yet).
    pub volumes: &'a [Option<VolState>],
}

impl Residency<'_> {
    fn volume(&self, species: u16) -> Option<SpeciesVol> {
        match self.volumes.get(usize::from(species)).copied().flatten() {
            Some(VolState::Ready(v)) => Some(v),
            _ => None,
        }
    }

    fn volume_pending(&self, species: u16) -> bool {
        matches!(self.volumes.get(usize::from(species)), Some(Some(VolState::Pending)))
    }
}

/// The camera as the selection needs it, and how far fades advance this frame.
#[derive(Clone, Copy, Debug)]
pub(crate) struct View {
    /// The view frustum.
    pub frustum: Frustum,
    /// Eye position.
    pub eye: Vec3,
    /// `tan(fov_y / 2)`.
    pub tan_half: f32,
    /// Viewport height, pixels.
    pub height_px: f32,
    /// Fade progress of this frame (`dt / fade_seconds`; 1 switches at once).
    pub progress: f32,
    /// The sun's shadows, where they are on.
    pub shadows: Option<ShadowView>,
}

/// The sun's shadows as the selection plans for them.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ShadowView {
    /// Unit direction toward the sun.
    pub sun: Vec3,
    /// How far from the eye shadows reach: a tree out of view within it whose shadow may fall in view is drawn too,
    /// for the shadow pass.
    pub reach: f32,
    /// Each cascade's volume (its four sides and its end away from the sun): what the cascade's map draws is planned
    /// as the camera's view is.
    pub cascades: [Frustum; crate::SHADOW_CASCADES],
}

impl View {
    /// The view of `camera` on a `size` viewport, `dt` seconds after the previous frame (`instant` finishes every
    /// fade at once).
    pub(crate) fn new(
        camera: &Camera,
        size: (u32, u32),
        near_clip: f32,
        lod: &LodConfig,
        dt: f32,
        instant: bool,
    ) -> View {
        let (w, h) = size;
        let vp = camera.view_projection(w as f32 / h as f32, near_clip);
        let progress = if instant || lod.fade_seconds <= 0.0 { 1.0 } else { (dt / lod.fade_seconds).max(0.0) };
        View {
            frustum: Frustum::from_matrix(vp),
            eye: camera.position,
            tan_half: camera.tan_half_fov(),
            height_px: h as f32,
            progress,
            shadows: None,
        }
    }

    /// Whether a tree out of view (bounding sphere at `center`, `radius`; its base `base` metres below the centre)
    /// may cast a shadow into view: within the shadow's reach, and the sphere moved along the sun's rays down to
    /// its base's height (grown by the shadow's length) is in view.
    fn casts_into_view(&self, center: Vec3, radius: f32, base: f32) -> bool {
        let Some(ShadowView { sun, reach, .. }) = self.shadows else { return false };
        if sun.y <= 0.05 || (center - self.eye).length() - radius > reach {
            return false;
        }
        let along = (base + radius) / sun.y;
        self.frustum.sphere_visible(center - sun * (0.5 * along), radius + 0.5 * along)
    }
}

/// Instances one job of the level choice takes: a fixed run, so that the jobs, and the lists joined from them in
/// instance order, are the same on any number of cores.
const LEVEL_RUN: usize = 4096;

/// What the level choice lists for one run of instances (kept between frames, as the plan is).
#[derive(Debug, Default)]
struct ChosenRun {
    geo_draws: Vec<GeoDraw>,
    far: Vec<FarInstance>,
    /// Each far instance's distance from the eye as bits (non-negative floats order as their bits).
    far_dist: Vec<u32>,
    requests: Vec<JobRequest>,
    /// The counts the choice keeps: casters, in view, waiting and the bands.
    stats: FrameStats,
}

/// The level choice of the instances from `first` on whose states `run` holds, listed into `out` (emptied first; see
/// [`FramePlan::plan`]).
fn choose_run(input: &FrameInputs, levels: &[Level], first: usize, run: &mut [InstState], out: &mut ChosenRun) {
    let FrameInputs { scene, residency: res, lod, view, .. } = input;
    out.geo_draws.clear();
    out.far.clear();
    out.far_dist.clear();
    out.requests.clear();
    out.stats = FrameStats::default();
    let instances = scene.instances.get(first..).unwrap_or_default();
    for (idx, (si, st)) in (first..).zip(instances.iter().zip(run.iter_mut())) {
        let Some(graph) = scene.graph(si.species) else { continue };
        let vs = res.volume(si.species);
        let params = st.params;
        let scale = match (st.scale, vs) {
            (Some(s), _) => s,
            (None, Some(v)) => *st.scale.insert(instance_scale(graph, v.height, si.seed, &si.params)),
            (None, None) => 1.0,
        };
        let (c_off, radius) = match vs {
            Some(v) => (v.center * scale, v.radius * scale),
            None => (Vec3::new(0.0, FALLBACK_CENTER_HEIGHT, 0.0) * scale, FALLBACK_RADIUS * scale),
        };
        let center = Vec3::from(si.position) + c_off;
        let dist = (center - view.eye).length();
        let size = projected_size(radius, dist, view.tan_half, view.height_px);
        let key = |d: u8| TreeKey { species: si.species, seed: si.seed, detail: d, params };
        if !view.frustum.sphere_visible(center, radius) {
            // Out of view, it may still cast a shadow into view: drawn for that at the level its size asks for
            // where resident (without a fade: the shadow pass draws no masks), asked for behind what is seen.
            if size >= lod.cull_px
                && view.casts_into_view(center, radius, c_off.y)
                && let Level::Detail(d) = lod.select(st.target, size)
            {
                let k = key(d);
                if res.cache.get(&k).is_some() {
                    let sphere = (center, radius);
                    out.geo_draws.push(GeoDraw { key: k, position: si.position, mask: 1.0, sphere, seen: false });
                    out.stats.shadow_casters += 1;
                } else if !res.cache.is_pending(&k) && !res.cache.unavailable(&k) {
                    out.requests.push(JobRequest { key: k, instance: idx, priority: 0.25 * size });
                }
            }
            continue;
        }
        if size < lod.cull_px {
            continue;
        }
        out.stats.in_view += 1;
        let mut wanted = lod.select(st.target, size);
        st.target = Some(wanted);
        if let Level::Detail(d) = wanted
            && res.cache.unavailable(&key(d))
        {
            wanted = Level::Far;
        }
        let ready = |l: Level| match l {
            Level::Detail(d) => res.cache.get(&key(d)).is_some(),
            Level::Far => vs.is_some(),
        };
        if !ready(wanted) {
            match wanted {
                Level::Detail(d) => {
                    if !res.cache.is_pending(&key(d)) {
                        out.requests.push(JobRequest { key: key(d), instance: idx, priority: size });
                    }
                    out.stats.waiting += 1;
                }
                Level::Far => {
                    if res.volume_pending(si.species) {
                        out.stats.waiting += 1;
                    }
                }
            }
        }
        st.lod.step(wanted, view.progress, &ready, levels);
        match st.lod.shown.map(Level::band) {
            Some(Band::Near) => out.stats.near += 1,
            Some(Band::Mid) => out.stats.mid += 1,
            Some(Band::Far) => out.stats.far += 1,
            None => out.stats.hidden += 1,
        }
        for d in st.lod.draws() {
            match (d.level, vs) {
                (Level::Detail(det), _) => out.geo_draws.push(GeoDraw {
                    key: key(det),
                    position: si.position,
                    mask: d.mask,
                    sphere: (center, radius),
                    seen: true,
                }),
                (Level::Far, Some(v)) => {
                    // About as many voxels as pixels: one halving of the resolution below `low_res_px` and one
                    // more for each halving of the size, to the coarsest allowed.
                    let halvings = (lod.low_res_px / size.max(1e-6)).log2().floor() + 1.0;
                    let volume = v.levels[halvings.clamp(0.0, f32::from(lod.far_resolutions - 1)) as usize];
                    let [x, y, z] = si.position;
                    // The instance's tint rides in the top byte (volume indices stay far below 2²⁴).
                    let volume = (volume & VOLUME_INDEX) | (fold_seed(si.seed) & !VOLUME_INDEX);
                    out.far_dist.push(dist.max(0.0).to_bits());
                    out.far.push(FarInstance { pos_scale: [x, y, z, scale], volume, mask: d.mask });
                }
                (Level::Far, None) => {}
            }
        }
    }
}

/// Everything a frame's plan reads.
#[derive(Clone, Copy, Debug)]
pub(crate) struct FrameInputs<'a> {
    /// The scene.
    pub scene: &'a Scene,
    /// What is resident.
    pub residency: Residency<'a>,
    /// Bands, thresholds, hysteresis and fade time.
    pub lod: &'a LodConfig,
    /// The camera.
    pub view: View,
    /// The terrain mesh, once there is one.
    pub terrain: Option<&'a TerrainMesh>,
    /// Jobs the workers can take now (the job bound less what is queued, running or waiting for upload).
    pub job_room: usize,
}

/// The selection state of every instance, carried across frames and scene generations.
#[derive(Debug)]
pub(crate) struct LodState {
    /// Per instance, in [`Scene::instances`] order.
    pub inst: Vec<InstState>,
    /// The previous generation's states while they are carried over (kept for its allocation).
    spare: Vec<InstState>,
    generation: Option<u64>,
    /// Every level an instance can show, finest first (for stand-ins).
    levels: Vec<Level>,
    /// Switch levels at once instead of cross-fading (offscreen stills).
    pub instant: bool,
}

impl LodState {
    /// No instances yet; levels `0..=mid_levels` and the far field.
    pub(crate) fn new(lod: &LodConfig) -> LodState {
        LodState {
            inst: Vec::new(),
            spare: Vec::new(),
            generation: None,
            levels: (0..=lod.mid_levels).map(Level::Detail).chain([Level::Far]).collect(),
            instant: false,
        }
    }

    /// Follow a new scene generation: carry states over by id (both lists are sorted by id, so one merge pass; an
    /// instance the old list does not have starts afresh).
    pub(crate) fn sync(&mut self, generation: u64, instances: &[SceneInstance]) {
        if self.generation == Some(generation) && self.inst.len() == instances.len() {
            return;
        }
        let mut old = std::mem::replace(&mut self.inst, std::mem::take(&mut self.spare));
        self.inst.clear();
        let mut j = 0;
        for i in instances {
            while old.get(j).is_some_and(|s| s.id < i.id) {
                j += 1;
            }
            let state = match old.get(j) {
                Some(s) if s.id == i.id => *s,
                _ => InstState::new(i.id),
            };
            let params = TreeKey::params_hash(&i.params);
            let scale = state.scale.filter(|_| state.params == params);
            self.inst.push(InstState { params, scale, ..state });
        }
        old.clear();
        self.spare = old;
        self.generation = Some(generation);
    }
}

/// One frame's plan (see the module docs). Kept between frames so that a frame allocates only when a list grows.
#[derive(Debug, Default)]
pub(crate) struct FramePlan {
    /// Trees to draw from the geometry cache, in instance order.
    pub geo_draws: Vec<GeoDraw>,
    /// What each run of the level choice listed, joined into the lists here.
    runs: Vec<ChosenRun>,
    /// Far instances, in instance order.
    far: Vec<FarInstance>,
    /// Their sort keys: the distance's bits (non-negative floats order as their bits) above the index in `far`.
    far_keys: Vec<u64>,
    /// The radix sort's second buffer.
    far_spare: Vec<u64>,
    /// Far instances front to back, as uploaded.
    pub far_sorted: Vec<FarInstance>,
    /// Geometry wanted and not pending, in instance order.
    requests: Vec<JobRequest>,
    /// Keys already taken into `jobs`.
    requested: HashSet<TreeKey>,
    /// Jobs to submit: biggest on screen first, each key once, within the job bound.
    pub jobs: Vec<JobRequest>,
    /// Segments per (unit shape, tessellation).
    lists: [[Vec<Segment>; TESSELLATIONS]; UNIT_SHAPES],
    /// Mesh segments.
    meshes: Vec<Segment>,
    /// Every segment of the frame, as uploaded (never empty: a zeroed one when nothing is drawn).
    pub segments: Vec<Segment>,
    /// The per-draw uniforms, as uploaded: [`DRAW_SLOTS`] slots of [`DRAW_STRIDE`] bytes.
    pub uniforms: Vec<u8>,
    /// What the camera draws.
    pub camera: ViewDraws,
    /// What each shadow cascade's map draws (empty where shadows are off).
    pub cascades: [ViewDraws; crate::SHADOW_CASCADES],
}

impl FramePlan {
    /// Draw nothing but the sky.
    pub(crate) fn clear(&mut self) {
        self.geo_draws.clear();
        self.far_sorted.clear();
        self.jobs.clear();
        self.camera.clear();
        self.cascades.iter_mut().for_each(ViewDraws::clear);
    }

    /// Far instances to draw.
    pub(crate) fn far_count(&self) -> u32 {
        self.far_sorted.len() as u32
    }

    /// Plan a frame: levels (stepping `state`), jobs, draw lists, far instances, terrain chunks; counts in `stats`.
    /// The caller submits [`FramePlan::jobs`], marks the drawn keys used and uploads the lists.
    pub(crate) fn plan(&mut self, input: &FrameInputs, state: &mut LodState, stats: &mut FrameStats) {
        self.choose_levels(input, state, stats);
        self.choose_jobs(input.job_room);
        self.build_draw_lists(input.residency.cache, input.view.shadows.as_ref().map(|s| &s.cascades), stats);
        self.sort_far();
        self.choose_terrain(input.terrain, &input.view, stats);
        // The sky, the terrain chunks, the primitive draws, the meshes, the far field; and the cascades'.
        let calls = |v: &ViewDraws| v.terrain.len() as u32 + v.prims.len() as u32 + u32::from(v.mesh.is_some());
        stats.draw_calls = 1
            + calls(&self.camera)
            + u32::from(!self.far_sorted.is_empty())
            + self.cascades.iter().map(calls).sum::<u32>();
    }

    /// Cull, choose each instance's level with hysteresis, ask for what is missing, step the cross-fades and list
    /// the draws: runs of [`LEVEL_RUN`] instances on every core, their lists joined in instance order.
    fn choose_levels(&mut self, input: &FrameInputs, state: &mut LodState, stats: &mut FrameStats) {
        self.geo_draws.clear();
        self.far.clear();
        self.far_keys.clear();
        self.requests.clear();
        let LodState { inst, levels, .. } = state;
        let levels: &[Level] = levels;
        self.runs.resize_with(inst.len().div_ceil(LEVEL_RUN), ChosenRun::default);
        let runs: Vec<_> = (inst.chunks_mut(LEVEL_RUN))
            .zip(self.runs.iter_mut())
            .enumerate()
            .map(|(k, run)| (k * LEVEL_RUN, Mutex::new(run)))
            .collect();
        par::map(
            &runs,
            || (),
            |(), (first, run)| {
                let (states, out) = &mut *run.locked();
                choose_run(input, levels, *first, states, out);
            },
        );
        drop(runs);
        for run in &self.runs {
            let base = self.far.len();
            let keys = run.far_dist.iter().enumerate().map(|(i, &d)| u64::from(d) << 32 | (base + i) as u64);
            self.far_keys.extend(keys);
            self.far.extend_from_slice(&run.far);
            self.geo_draws.extend_from_slice(&run.geo_draws);
            self.requests.extend_from_slice(&run.requests);
            let c = &run.stats;
            stats.shadow_casters += c.shadow_casters;
            stats.in_view += c.in_view;
            stats.waiting += c.waiting;
            stats.near += c.near;
            stats.mid += c.mid;
            stats.far += c.far;
            stats.hidden += c.hidden;
        }
    }

    /// The requests biggest on screen first (stable among equals), each key once, at most `room`.
    fn choose_jobs(&mut self, room: usize) {
        self.requests.sort_by(|a, b| b.priority.total_cmp(&a.priority));
        self.jobs.clear();
        self.requested.clear();
        for r in &self.requests {
            if self.jobs.len() >= room {
                break;
            }
            if self.requested.insert(r.key) {
                self.jobs.push(*r);
            }
        }
    }

    /// Geometry draw lists of the camera and of each shadow cascade: per view one list per (unit shape,
    /// tessellation) and one for meshes, all packed into one segment list with a uniform slot per draw.
    fn build_draw_lists(
        &mut self,
        cache: &GeometryCache,
        cascades: Option<&[Frustum; crate::SHADOW_CASCADES]>,
        stats: &mut FrameStats,
    ) {
        self.segments.clear();
        self.uniforms.clear();
        self.uniforms.resize((DRAW_STRIDE * DRAW_SLOTS) as usize, 0);
        let mut slot = 0u32;
        let mut camera = std::mem::take(&mut self.camera);
        self.view_lists(cache, |g| g.seen, &mut slot, &mut camera);
        stats.primitives = camera.prims.iter().map(|d| u64::from(d.instances)).sum();
        stats.mesh_triangles = camera.mesh.map_or(0, |(_, n)| u64::from(n / 3));
        self.camera = camera;
        let mut lists = std::mem::take(&mut self.cascades);
        lists.iter_mut().for_each(ViewDraws::clear);
        for (f, draws) in cascades.into_iter().flatten().zip(&mut lists) {
            self.view_lists(cache, |g| f.sphere_visible(g.sphere.0, g.sphere.1), &mut slot, draws);
            stats.shadow_primitives += draws.prims.iter().map(|d| u64::from(d.instances)).sum::<u64>();
        }
        self.cascades = lists;
        if self.segments.is_empty() {
            self.segments.push(Segment::zeroed());
        }
    }

    /// One view's lists: the trees `keep` accepts, appended to the segments with uniform slots from `slot` on.
    fn view_lists(
        &mut self,
        cache: &GeometryCache,
        keep: impl Fn(&GeoDraw) -> bool,
        slot: &mut u32,
        out: &mut ViewDraws,
    ) {
        self.lists.iter_mut().flatten().for_each(Vec::clear);
        self.meshes.clear();
        for g in self.geo_draws.iter().filter(|g| keep(g)) {
            let Some(e) = cache.get(&g.key) else { continue };
            let segment = |base: u64, vbase: u64, count: u32| Segment {
                first: 0,
                base: base as u32,
                vbase: vbase as u32,
                count,
                pos: g.position,
                mask: g.mask,
                seed: fold_seed(g.key.seed),
                crown: [g.sphere.0.y - g.position[1], g.sphere.1],
                pad: 0,
            };
            for (k, r) in e.shape_ranges.iter().enumerate() {
                if !r.is_empty() {
                    let s = segment(e.prims.start + u64::from(r.start), 0, r.len() as u32);
                    self.lists[k][tess(g.key.detail)].push(s);
                }
            }
            if !e.indices.is_empty() {
                let count = (e.indices.end - e.indices.start) as u32;
                self.meshes.push(segment(e.indices.start, e.verts.start, count));
            }
        }
        let put = |u: DrawUniform, slot: u32, uniforms: &mut Vec<u8>| {
            let at = (u64::from(slot) * DRAW_STRIDE) as usize;
            uniforms[at..at + DRAW_UNIFORM_BYTES].copy_from_slice(bytemuck::bytes_of(&u));
        };
        // Number a list's segments within its draw and append them; (first segment, segments, instances).
        let append = |list: &mut Vec<Segment>, all: &mut Vec<Segment>| -> (u32, u32, u32) {
            let first = all.len() as u32;
            let mut total = 0u32;
            for s in list.iter_mut() {
                s.first = total;
                total += s.count;
            }
            all.extend_from_slice(list);
            (first, list.len() as u32, total)
        };
        out.prims.clear();
        let mut visible_base = 0;
        for (shape, per_tess) in self.lists.iter_mut().enumerate() {
            for (t, list) in per_tess.iter_mut().enumerate() {
                if list.is_empty() {
                    continue;
                }
                let (seg_first, seg_count, instances) = append(list, &mut self.segments);
                let u = DrawUniform { seg_first, seg_count, kind: shape as u32, visible_base };
                put(u, *slot, &mut self.uniforms);
                out.prims.push(PrimDraw { shape, tess: t, slot: *slot, instances, seg_first, seg_count, visible_base });
                visible_base += instances;
                *slot += 1;
            }
        }
        out.mesh = if self.meshes.is_empty() {
            None
        } else {
            let (first, count, total) = append(&mut self.meshes, &mut self.segments);
            let u = DrawUniform { seg_first: first, seg_count: count, kind: 0, visible_base: 0 };
            put(u, *slot, &mut self.uniforms);
            *slot += 1;
            Some((*slot - 1, total))
        };
    }

    /// Far instances front to back (they blend under what is in front, and stop where it is opaque).
    /// Nearest first and, at the same distance, in instance order: a radix sort of the keys' distance bits (sorting
    /// the 32-byte pairs by their float took 8 ms for 95,000 far instances, the keys by comparison 5 ms).
    fn sort_far(&mut self) {
        radix_sort_high(&mut self.far_keys, &mut self.far_spare);
        self.far_sorted.clear();
        self.far_sorted.extend(self.far_keys.iter().map(|&k| self.far[k as u32 as usize]));
    }

    /// Terrain chunks in view, each at the coarsest step whose squares stay within [`TERRAIN_SQUARE_PX`] of the
    /// camera; and those in each shadow cascade, at the same steps (so that the ground shadows itself where it is
    /// drawn).
    fn choose_terrain(&mut self, terrain: Option<&TerrainMesh>, view: &View, stats: &mut FrameStats) {
        self.camera.terrain.clear();
        let Some(mesh) = terrain else { return };
        let px_per_rad = view.height_px / (2.0 * view.tan_half);
        for c in &mesh.chunks {
            let d = ((c.center - view.eye).length() - c.radius).max(TERRAIN_NEAREST);
            let r = c.levels[mesh.level_for(d, px_per_rad, TERRAIN_SQUARE_PX)].clone();
            if view.frustum.sphere_visible(c.center, c.radius) {
                stats.terrain_triangles += u64::from(r.end - r.start) / 3;
                self.camera.terrain.push(r.clone());
            }
            for (f, draws) in view.shadows.iter().flat_map(|s| &s.cascades).zip(&mut self.cascades) {
                if f.sphere_visible(c.center, c.radius) {
                    draws.terrain.push(r.clone());
                }
            }
        }
    }
}

/// Sort `keys` by their high 32 bits, keeping the order of equal ones (an LSD radix sort, 11 bits a pass; `spare`
/// is scratch).
fn radix_sort_high(keys: &mut Vec<u64>, spare: &mut Vec<u64>) {
    const BITS: u32 = 11;
    spare.clear();
    spare.resize(keys.len(), 0);
    for pass in 0..3 {
        let shift = 32 + pass * BITS;
        let digit = |k: u64| ((k >> shift) & ((1 << BITS) - 1)) as usize;
        let mut counts = [0usize; 1 << BITS];
        for &k in keys.iter() {
            counts[digit(k)] += 1;
        }
        let mut at = 0;
        for c in counts.iter_mut() {
            (*c, at) = (at, at + *c);
        }
        for &k in keys.iter() {
            let d = digit(k);
            spare[counts[d]] = k;
            counts[d] += 1;
        }
        std::mem::swap(keys, spare);
    }
}

#[cfg(test)]
mod tests;
