//! The CPU reference renderer (§8): front-to-back raymarching with `α = 1 − (1 − µ)^(k·Δs)`, the step the smallest
//! voxel side, rays clipped to the tree's axis-aligned box and optionally to the secondary bounding spheres and the
//! condensation box (§8.2); an optional projection-ray cache (§8.2); shadow rays to the lights; ambient light
//! attenuated toward the interior (Reeves), diffuse and specular terms with procedural normals from the first-level
//! structure flow (§8.3); depth colour spans; supersampling with factor `s` (`s²` rays per pixel, §8.4).
//!
//! Shading is evaluated at voxel centres (a voxel is a homogeneous region), so it is memoised per voxel: each
//! visible voxel casts its shadow rays once. Empty bricks of 8³ voxels are skipped without changing which sample
//! positions are taken, so every option that only saves time (bounding scheme, skipping, ray cache) leaves the
//! image bit-identical — the tests check that. Single-threaded and deterministic.

// Negated comparisons are deliberate: they treat NaN as out of range.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use std::io::Cursor;

use super::storage::{BRICK_SHIFT, VoxelQuery, VoxelStore};
use super::{Aabb, Hypertree, Hypervolume, Voxel};
use crate::primitive::Fnv;
use crate::vec3::{cross, dot, norm, sub, unit};

mod mask;
use mask::{VoxelMask, brick_distances};

/// The unit of the raymarching step `Δs` in the opacity equation, as a fraction of the hypervolume's longest extent
/// (one voxel side at the paper's average resolution of 300).
pub const REFERENCE_STEP: f32 = 1.0 / 300.0;

/// Largest image side.
pub const MAX_IMAGE_SIDE: u32 = 8192;
/// Largest supersampling factor.
pub const MAX_SUPERSAMPLE: u32 = 8;

/// Which bounding volumes clip the projection rays (§8.2).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BoundingScheme {
    /// The axis-aligned box of the non-empty voxels.
    Aabb,
    /// The secondary bounding spheres and the condensation box, cross-sectioned with the box.
    Spheres,
}

/// The shading models of §8.3 and Figure 10.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shading {
    /// Shadow-attenuated ambient term only.
    Ambient,
    /// Attenuated ambient plus shadowed diffuse (the paper's recommended model).
    Diffuse,
    /// Ambient, diffuse and specular.
    Specular,
}

/// A directional light.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Light {
    /// Direction toward the light (normalised when rendering).
    pub direction: [f32; 3],
    /// Colour and intensity.
    pub color: [f32; 3],
}

/// Everything that decides an image.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOptions {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Supersampling factor `s`: `s × s` rays per pixel on a regular grid.
    pub supersample: u32,
    /// Camera azimuth around the vertical axis, degrees (0 looks from +z).
    pub azimuth: f32,
    /// Camera elevation, degrees.
    pub elevation: f32,
    /// Vertical field of view, degrees.
    pub fov: f32,
    /// Distance from the tree centre as a multiple of the distance that just fits the tree (1 fits).
    pub zoom_out: f32,
    /// Bounding volumes for projection rays.
    pub bounds: BoundingScheme,
    /// Skip empty 8³ bricks (saves time, same image).
    pub skip_empty: bool,
    /// The projection-ray cache of §8.2 (saves bisections, same image).
    pub ray_cache: bool,
    /// Cast shadow rays.
    pub shadows: bool,
    /// The shading model.
    pub shading: Shading,
    /// The lights.
    pub lights: Vec<Light>,
    /// Ambient intensity at the crown's surface.
    pub ambient: f32,
    /// Exponential falloff of ambient light toward the interior (0 = constant ambient).
    pub ambient_falloff: f32,
    /// Diffuse coefficient.
    pub diffuse: f32,
    /// Light from the sky, `sky_light · (½ + ½ n_y)` with the procedural normal `n` (the renderer's near meshes
    /// have this term; 0 leaves the paper's model).
    pub sky_light: f32,
    /// Specular coefficient.
    pub specular: f32,
    /// Specular exponent.
    pub shininess: f32,
    /// The normalisation coefficient `k` of the opacity equation (condenses or thins the tree); `Δs` is the step in
    /// units of [`REFERENCE_STEP`].
    pub density_scale: f32,
    /// Background colour at the top and bottom of the image.
    pub background: [[f32; 3]; 2],
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            width: 300,
            height: 300,
            supersample: 1,
            azimuth: 0.0,
            elevation: 8.0,
            fov: 30.0,
            zoom_out: 1.05,
            bounds: BoundingScheme::Aabb,
            skip_empty: true,
            ray_cache: false,
            shadows: true,
            shading: Shading::Diffuse,
            lights: vec![Light { direction: [-0.55, 0.75, 0.45], color: [1.0, 0.97, 0.9] }],
            ambient: 0.45,
            ambient_falloff: 1.6,
            diffuse: 0.85,
            sky_light: 0.0,
            specular: 0.35,
            shininess: 24.0,
            density_scale: 1.0,
            background: [[0.62, 0.76, 0.92], [0.93, 0.95, 0.97]],
        }
    }
}

/// Why rendering was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    /// Image side out of range.
    #[error("image of {0}×{1} pixels (allowed 1..={MAX_IMAGE_SIDE} per side)")]
    Size(u32, u32),
    /// Supersampling factor out of range.
    #[error("supersampling factor {0} (allowed 1..={MAX_SUPERSAMPLE})")]
    Supersample(u32),
    /// A camera, light or shading number is not finite or out of range.
    #[error("{0} is out of range")]
    Parameter(&'static str),
}

/// An RGB image, 8 bits per channel, rows top to bottom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// `width · height · 3` bytes.
    pub pixels: Vec<u8>,
}

impl Image {
    /// FNV-1a hash of the size and pixels (golden render tests).
    pub fn hash(&self) -> u64 {
        let mut h = Fnv::new();
        h.u32(self.width);
        h.u32(self.height);
        h.bytes(&self.pixels);
        h.finish()
    }

    /// Encode as PNG.
    pub fn encode_png(&self) -> Result<Vec<u8>, image::ImageError> {
        let img = image::RgbImage::from_raw(self.width, self.height, self.pixels.clone())
            .expect("pixel buffer matches the image size");
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png)?;
        Ok(out.into_inner())
    }

    /// The pixel at `(x, y)`.
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 3] {
        let i = 3 * (y as usize * self.width as usize + x as usize);
        [self.pixels[i], self.pixels[i + 1], self.pixels[i + 2]]
    }
}

/// Counters of one render (what the optimisations saved).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderStats {
    /// Projection rays cast.
    pub rays: u64,
    /// Projection-ray samples that queried the storage.
    pub samples: u64,
    /// Samples answered by the ray cache.
    pub cache_hits: u64,
    /// Voxels shaded (each casts its shadow rays once).
    pub shaded: u64,
    /// Shadow-ray samples that queried the storage.
    pub shadow_samples: u64,
}

fn check(o: &RenderOptions) -> Result<(), RenderError> {
    if o.width == 0 || o.height == 0 || o.width > MAX_IMAGE_SIDE || o.height > MAX_IMAGE_SIDE {
        return Err(RenderError::Size(o.width, o.height));
    }
    if o.supersample == 0 || o.supersample > MAX_SUPERSAMPLE {
        return Err(RenderError::Supersample(o.supersample));
    }
    let ok = |v: f32, lo: f32, hi: f32| v.is_finite() && v >= lo && v <= hi;
    let checks = [
        (ok(o.azimuth, -1e4, 1e4), "azimuth"),
        (ok(o.elevation, -89.0, 89.0), "elevation"),
        (ok(o.fov, 1.0, 170.0), "field of view"),
        (ok(o.zoom_out, 0.05, 1e3), "zoom"),
        (ok(o.ambient, 0.0, 100.0), "ambient"),
        (ok(o.ambient_falloff, 0.0, 100.0), "ambient falloff"),
        (ok(o.sky_light, 0.0, 100.0), "sky light"),
        (ok(o.diffuse, 0.0, 100.0), "diffuse"),
        (ok(o.specular, 0.0, 100.0), "specular"),
        (ok(o.shininess, 0.0, 1e4), "shininess"),
        (ok(o.density_scale, 0.0, 1e3), "density scale"),
        (o.lights.len() <= 16, "light count"),
    ];
    if let Some((_, what)) = checks.iter().find(|c| !c.0) {
        return Err(RenderError::Parameter(what));
    }
    for l in &o.lights {
        if !l.direction.iter().chain(&l.color).all(|v| v.is_finite() && v.abs() <= 1e3) || norm(l.direction) == 0.0 {
            return Err(RenderError::Parameter("light"));
        }
    }
    if !o.background.iter().flatten().all(|v| v.is_finite()) {
        return Err(RenderError::Parameter("background"));
    }
    Ok(())
}

/// Render a hypertree (see the module docs). `progress(rows_done, rows)` is called after each image row.
pub fn render(
    tree: &Hypertree,
    opts: &RenderOptions,
    progress: &mut dyn FnMut(u32, u32),
) -> Result<(Image, RenderStats), RenderError> {
    check(opts)?;
    match &tree.store {
        VoxelStore::Dense(s) => render_with(tree, s, opts, progress),
        VoxelStore::IndexList(s) => render_with(tree, s, opts, progress),
        VoxelStore::IndexBits(s) => render_with(tree, s, opts, progress),
        VoxelStore::Partitioned(s) => render_with(tree, s, opts, progress),
    }
}

/// The camera of [`render`]: around the box of the non-empty voxels at `opts.azimuth` and `opts.elevation`, at
/// `opts.zoom_out` times the distance at which the box's bounding sphere just fits the field of view (vertical and
/// horizontal), looking at the box's centre with +y up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReferenceCamera {
    /// The eye, box units.
    pub eye: [f32; 3],
    /// Where it looks: the box's centre.
    pub center: [f32; 3],
    /// Unit view direction.
    pub forward: [f32; 3],
    /// Unit right vector of the image plane.
    pub right: [f32; 3],
    /// Unit up vector of the image plane.
    pub up: [f32; 3],
    /// `tan(fov / 2)`, the vertical half extent of the image plane at unit distance.
    pub tan_half: f32,
    /// Width over height.
    pub aspect: f32,
}

impl ReferenceCamera {
    /// The camera for a tree whose non-empty voxels span `aabb`, with the view and image size of `opts`.
    pub fn new(aabb: &Aabb, opts: &RenderOptions) -> ReferenceCamera {
        let center: [f32; 3] = std::array::from_fn(|i| 0.5 * (aabb.min[i] + aabb.max[i]));
        let half: [f32; 3] = std::array::from_fn(|i| 0.5 * (aabb.max[i] - aabb.min[i]));
        let radius = norm(half);
        let rad = |deg: f32| deg * (std::f32::consts::PI / 180.0);
        let (az, el) = (rad(opts.azimuth), rad(opts.elevation));
        let back = [libm::cosf(el) * libm::sinf(az), libm::sinf(el), libm::cosf(el) * libm::cosf(az)];
        let tan_half = libm::tanf(rad(opts.fov) * 0.5);
        let aspect = opts.width as f32 / opts.height as f32;
        let fit = radius / libm::sinf(rad(opts.fov) * 0.5).min(libm::sinf(libm::atanf(tan_half * aspect)));
        let dist = fit * opts.zoom_out;
        let eye: [f32; 3] = std::array::from_fn(|i| center[i] + back[i] * dist);
        let forward = back.map(|v| -v);
        let right = unit(cross(forward, [0.0, 1.0, 0.0]));
        let up = cross(right, forward);
        ReferenceCamera { eye, center, forward, right, up, tan_half, aspect }
    }

    /// The unit direction of the ray through image point `(fx, fy)`, both in `[0, 1]` from the top left corner.
    pub fn ray(&self, fx: f32, fy: f32) -> [f32; 3] {
        let nx = (2.0 * fx - 1.0) * self.tan_half * self.aspect;
        let ny = (1.0 - 2.0 * fy) * self.tan_half;
        unit(std::array::from_fn(|i| self.forward[i] + self.right[i] * nx + self.up[i] * ny))
    }
}

/// One non-empty voxel's shading as [`render`] computes it: lit colour (not premultiplied) and the opacity of one
/// step through it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShadedVoxel {
    /// The voxel's index in the hypervolume.
    pub index: u32,
    /// Base colour times the light it receives.
    pub color: [f32; 3],
    /// `α = 1 − (1 − µ)^(k·Δs)` for a step of the smallest voxel side.
    pub alpha: f32,
}

/// The view-independent shading of every non-empty voxel, in index order, exactly as [`render`] shades them at
/// voxel centres with `opts` (attenuated ambient, diffuse with procedural normals, shadow rays to the lights);
/// the specular term depends on the eye and is left out (`Shading::Specular` shades like `Shading::Diffuse`).
/// The image size and camera of `opts` are not used, but are checked like every other number. For baking the
/// shading into a volume that a GPU only marches.
pub fn shade_voxels(tree: &Hypertree, opts: &RenderOptions) -> Result<Vec<ShadedVoxel>, RenderError> {
    check(opts)?;
    Ok(match &tree.store {
        VoxelStore::Dense(s) => shade_with(tree, s, opts),
        VoxelStore::IndexList(s) => shade_with(tree, s, opts),
        VoxelStore::IndexBits(s) => shade_with(tree, s, opts),
        VoxelStore::Partitioned(s) => shade_with(tree, s, opts),
    })
}

fn shade_with<Q: VoxelQuery>(tree: &Hypertree, q: &Q, opts: &RenderOptions) -> Vec<ShadedVoxel> {
    let Some(aabb) = tree.aabb() else { return Vec::new() };
    let mut o = opts.clone();
    if o.shading == Shading::Specular {
        o.shading = Shading::Diffuse;
    }
    let mut scene = Scene::new(tree, q, aabb, &o, [0.0; 3]);
    let mut out = Vec::new();
    let vol = tree.volume;
    tree.store.for_each(|i, voxel| {
        if voxel.density != 0 {
            let color = scene.lit(voxel, vol.coords(i));
            out.push(ShadedVoxel { index: i, color, alpha: scene.alpha[usize::from(voxel.density)] });
        }
    });
    out
}

/// The entry and exit parameters of a ray through a box, if it meets it ahead of the origin.
#[inline]
fn box_interval(o: [f32; 3], inv_d: [f32; 3], b: &Aabb) -> Option<(f32, f32)> {
    let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
    for i in 0..3 {
        let a = (b.min[i] - o[i]) * inv_d[i];
        let c = (b.max[i] - o[i]) * inv_d[i];
        let (lo, hi) = if a <= c { (a, c) } else { (c, a) };
        // NaN (a zero direction component exactly on a face) is treated as "inside" on that axis.
        if lo > t0 {
            t0 = lo;
        }
        if hi < t1 {
            t1 = hi;
        }
    }
    (t0 <= t1).then_some((t0, t1))
}

struct FlowSeg {
    a: [f32; 3],
    d: [f32; 3],
    dd: f32,
    dir: [f32; 3],
}

struct Scene<'a, Q: VoxelQuery> {
    q: &'a Q,
    vol: Hypervolume,
    inv: [f32; 3],
    vsize: [f32; 3],
    mask: VoxelMask,
    /// Chebyshev distance, in bricks, from each brick to the nearest brick that the occupancy map or the voxels
    /// mark occupied (capped at 255).
    brick_dist: Vec<u8>,
    skip: bool,
    step: f32,
    alpha: [f32; 256],
    aabb: Aabb,
    spheres: Vec<([f32; 3], f32)>,
    boxes: Vec<Aabb>,
    colors: [[f32; 3]; 256],
    flows: Vec<FlowSeg>,
    crown_center: [f32; 3],
    crown_inv_half: [f32; 3],
    lights: Vec<([f32; 3], [f32; 3])>,
    eye: [f32; 3],
    o: RenderOptions,
    /// Shading memo by voxel rank (NaN: not shaded yet).
    memo: Vec<[f32; 3]>,
    ray_cache: Vec<(u32, Voxel)>,
    stats: RenderStats,
}

impl<'a, Q: VoxelQuery> Scene<'a, Q> {
    /// Everything but the shading memo and the ray cache (empty), for a tree whose non-empty voxels span `aabb`,
    /// seen from `eye`.
    fn new(tree: &Hypertree, q: &'a Q, aabb: Aabb, opts: &RenderOptions, eye: [f32; 3]) -> Self {
        let vol = tree.volume;
        let vsize = vol.voxel_size();
        let step = vsize[0].min(vsize[1]).min(vsize[2]);
        // α = 1 − (1 − µ)^(k·Δs), Δs measured in units of REFERENCE_STEP of the longest extent, so a voxel of a
        // given density is as opaque per unit length at every resolution (a reduced hypertree keeps its look).
        let longest = vol.extent[0].max(vol.extent[1]).max(vol.extent[2]);
        let ds = step / (longest * REFERENCE_STEP);
        let alpha = std::array::from_fn(|d| {
            let mu = d as f32 / 255.0;
            if d == 0 {
                0.0
            } else if d == 255 {
                1.0
            } else {
                1.0 - libm::powf(1.0 - mu, opts.density_scale * ds)
            }
        });
        let center: [f32; 3] = std::array::from_fn(|i| 0.5 * (aabb.min[i] + aabb.max[i]));
        let half: [f32; 3] = std::array::from_fn(|i| 0.5 * (aabb.max[i] - aabb.min[i]));
        let flows = tree
            .flows
            .iter()
            .map(|f| {
                let d = sub(f.to, f.from);
                FlowSeg { a: f.from, d, dd: dot(d, d), dir: unit(d) }
            })
            .collect();
        let mut colors = [[0.0f32; 3]; 256];
        for (l, c) in colors.iter_mut().enumerate() {
            *c = tree.level_color(l as u8);
        }
        let use_spheres = opts.bounds == BoundingScheme::Spheres && !tree.bounds.is_empty();
        let mut o = opts.clone();
        if !use_spheres {
            o.bounds = BoundingScheme::Aabb;
        }
        let mask = VoxelMask::build(tree, opts.skip_empty);
        Scene {
            q,
            vol,
            inv: std::array::from_fn(|i| 1.0 / vsize[i]),
            vsize,
            brick_dist: brick_distances(&tree.occupancy, &mask),
            mask,
            skip: opts.skip_empty,
            step,
            alpha,
            aabb,
            spheres: tree.bounds.spheres.iter().map(|s| (s.center, s.radius)).collect(),
            boxes: tree.bounds.boxes.clone(),
            colors,
            flows,
            crown_center: center,
            crown_inv_half: half.map(|v| if v > 0.0 { 1.0 / v } else { 0.0 }),
            lights: opts.lights.iter().map(|l| (unit(l.direction), l.color)).collect(),
            eye,
            o,
            memo: Vec::new(),
            ray_cache: Vec::new(),
            stats: RenderStats::default(),
        }
    }
}

impl<Q: VoxelQuery> Scene<'_, Q> {
    #[inline]
    fn brick_exit(&self, v: [u32; 3], o: [f32; 3], inv_d: [f32; 3]) -> f32 {
        let mut t = f32::INFINITY;
        for i in 0..3 {
            let b = v[i] >> BRICK_SHIFT;
            let lo = (b << BRICK_SHIFT) as f32 * self.vsize[i];
            let hi = (((b + 1) << BRICK_SHIFT).min(self.vol.resolution[i])) as f32 * self.vsize[i];
            let plane = if inv_d[i] > 0.0 { hi } else { lo };
            let ti = (plane - o[i]) * inv_d[i];
            if ti < t {
                t = ti;
            }
        }
        t
    }

    /// How many samples on from a sample in empty brick `brick` are certainly empty too: a sample moves at most one
    /// voxel along each axis per step (the step is the smallest voxel side), and every voxel closer than
    /// `8·(K − 1) + 1` along some axis lies in a brick nearer than `K`, the brick's Chebyshev distance to the
    /// nearest occupied brick; one voxel of margin absorbs rounding. Skipping only empty samples leaves the image
    /// unchanged.
    #[inline]
    fn clear_run(&self, brick: usize) -> i64 {
        let k = i64::from(self.brick_dist[brick]);
        (8 * (k - 1)).max(1)
    }

    /// Front-to-back accumulation along one projection ray: premultiplied colour and opacity.
    fn march(&mut self, o: [f32; 3], d: [f32; 3], intervals: &mut Vec<(f32, f32)>) -> ([f32; 3], f32) {
        let inv_d = d.map(|v| 1.0 / v);
        let Some((t0, t1)) = box_interval(o, inv_d, &self.aabb) else { return ([0.0; 3], 0.0) };
        intervals.clear();
        match self.o.bounds {
            BoundingScheme::Aabb => intervals.push((t0, t1)),
            BoundingScheme::Spheres => {
                for &(c, r) in &self.spheres {
                    let oc = sub(o, c);
                    let b = dot(oc, d);
                    let disc = b * b - (dot(oc, oc) - r * r);
                    if disc >= 0.0 {
                        let s = libm::sqrtf(disc);
                        let (a, e) = ((-b - s).max(t0), (-b + s).min(t1));
                        if a <= e {
                            intervals.push((a, e));
                        }
                    }
                }
                for bx in &self.boxes {
                    if let Some((a, e)) = box_interval(o, inv_d, bx) {
                        let (a, e) = (a.max(t0), e.min(t1));
                        if a <= e {
                            intervals.push((a, e));
                        }
                    }
                }
                intervals.sort_by(|x, y| x.0.total_cmp(&y.0));
            }
        }
        self.stats.rays += 1;
        let mut color = [0.0f32; 3];
        let mut alpha = 0.0f32;
        let mut next = 0i64; // first sample number not yet taken
        let mut cache_valid = self.o.ray_cache;
        for &(a, b) in intervals.iter() {
            let mut n = (ceil_i((a - t0) / self.step - 0.5)).max(next);
            let end = floor_i((b - t0) / self.step - 0.5);
            while n <= end {
                let t = t0 + (n as f32 + 0.5) * self.step;
                let p = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
                let Some(v) = self.vol.voxel_at(p, self.inv) else {
                    n += 1;
                    continue;
                };
                let b = self.mask.brick(v);
                let slot = self.mask.slots[b];
                if self.skip && slot & VoxelMask::UNMARKED != 0 {
                    let te = self.brick_exit(v, o, inv_d);
                    n = (n + 1).max(floor_i((te - t0) / self.step - 0.5)).max(n + self.clear_run(b));
                    continue;
                }
                let Some(rank) = self.mask.rank_in(slot, v) else {
                    // Empty: nothing to accumulate (the storage would answer Voxel::EMPTY).
                    n += 1;
                    continue;
                };
                let idx = self.vol.index(v);
                let voxel = if cache_valid {
                    let slot = n as usize;
                    match self.ray_cache.get(slot) {
                        Some(&(i, vx)) if i == idx => {
                            self.stats.cache_hits += 1;
                            vx
                        }
                        _ => {
                            cache_valid = false;
                            self.stats.samples += 1;
                            let vx = self.q.voxel_at(v, idx);
                            if let Some(e) = self.ray_cache.get_mut(slot) {
                                *e = (idx, vx);
                            }
                            vx
                        }
                    }
                } else {
                    self.stats.samples += 1;
                    let vx = self.q.voxel_at(v, idx);
                    if self.o.ray_cache
                        && let Some(e) = self.ray_cache.get_mut(n as usize)
                    {
                        *e = (idx, vx);
                    }
                    vx
                };
                if voxel.density != 0 {
                    let a = self.alpha[voxel.density as usize];
                    let c = self.shade(rank, voxel, v);
                    let w = (1.0 - alpha) * a;
                    for i in 0..3 {
                        color[i] += w * c[i];
                    }
                    alpha += w;
                    if alpha >= 0.995 {
                        return (color, alpha);
                    }
                }
                n += 1;
            }
            next = next.max(end + 1);
        }
        (color, alpha)
    }

    /// Transmittance from a voxel centre toward a light (a shadow ray).
    fn transmittance(&mut self, c: [f32; 3], l: [f32; 3]) -> f32 {
        let inv_d = l.map(|v| 1.0 / v);
        let Some((_, t1)) = box_interval(c, inv_d, &self.aabb) else { return 1.0 };
        let mut t_tr = 1.0f32;
        let mut n = 1i64;
        let end = floor_i(t1 / self.step);
        while n <= end {
            let t = n as f32 * self.step;
            let p = [c[0] + l[0] * t, c[1] + l[1] * t, c[2] + l[2] * t];
            let Some(v) = self.vol.voxel_at(p, self.inv) else { break };
            let b = self.mask.brick(v);
            let slot = self.mask.slots[b];
            if self.skip && slot & VoxelMask::UNMARKED != 0 {
                let te = self.brick_exit(v, c, inv_d);
                n = (n + 1).max(floor_i(te / self.step)).max(n + self.clear_run(b));
                continue;
            }
            if self.mask.rank_in(slot, v).is_none() {
                n += 1;
                continue;
            }
            self.stats.shadow_samples += 1;
            let voxel = self.q.voxel_at(v, self.vol.index(v));
            if voxel.density != 0 {
                t_tr *= 1.0 - self.alpha[voxel.density as usize];
                if t_tr < 0.01 {
                    return 0.0;
                }
            }
            n += 1;
        }
        t_tr
    }

    /// Procedural normal from the first-level structure flow (§8.3, Figure 4): flow directions and the radial
    /// offsets from the flow axes, interpolated with inverse-square distance weights; the normal is the radial part
    /// perpendicular to the interpolated flow.
    fn normal(&self, c: [f32; 3]) -> [f32; 3] {
        let mut radial = [0.0f32; 3];
        let mut flow = [0.0f32; 3];
        for f in &self.flows {
            let t = if f.dd > 0.0 { (dot(sub(c, f.a), f.d) / f.dd).clamp(0.0, 1.0) } else { 0.0 };
            let q = [f.a[0] + f.d[0] * t, f.a[1] + f.d[1] * t, f.a[2] + f.d[2] * t];
            let r = sub(c, q);
            let d2 = dot(r, r);
            let w = 1.0 / (d2 + 1e-6);
            let rn = unit(r);
            for i in 0..3 {
                radial[i] += w * rn[i];
                flow[i] += w * f.dir[i];
            }
        }
        let t = unit(flow);
        let k = dot(radial, t);
        let n = [radial[0] - k * t[0], radial[1] - k * t[1], radial[2] - k * t[2]];
        if norm(n) > 1e-6 { unit(n) } else { unit(sub(c, self.crown_center)) }
    }

    fn shade(&mut self, rank: u32, voxel: Voxel, v: [u32; 3]) -> [f32; 3] {
        let memo = self.memo[rank as usize];
        if !memo[0].is_nan() {
            return memo;
        }
        let out = self.lit(voxel, v);
        self.memo[rank as usize] = out;
        out
    }

    /// The shading of non-empty voxel `v` (not memoised).
    fn lit(&mut self, voxel: Voxel, v: [u32; 3]) -> [f32; 3] {
        self.stats.shaded += 1;
        let c = self.vol.center(v);
        let base = self.colors[voxel.level as usize];
        // Reeves' ambient attenuation: exponential in the depth below the crown's ellipsoidal shell.
        let e: [f32; 3] = std::array::from_fn(|i| (c[i] - self.crown_center[i]) * self.crown_inv_half[i]);
        let depth = (1.0 - norm(e)).max(0.0);
        let ambient = self.o.ambient * libm::expf(-self.o.ambient_falloff * depth);
        let mut light = [ambient; 3];
        let mut spec = [0.0f32; 3];
        match self.o.shading {
            Shading::Ambient => {
                let s = match self.lights.first() {
                    Some(&(l, _)) if self.o.shadows => self.transmittance(c, l),
                    _ => 1.0,
                };
                light = [ambient * (0.35 + 0.65 * s); 3];
            }
            Shading::Diffuse | Shading::Specular => {
                let n = self.normal(c);
                let view = unit(sub(self.eye, c));
                light = light.map(|a| a + self.o.sky_light * (0.5 + 0.5 * n[1]));
                for k in 0..self.lights.len() {
                    let (l, col) = self.lights[k];
                    let lambert = dot(n, l).max(0.0);
                    let s = if self.o.shadows { self.transmittance(c, l) } else { 1.0 };
                    for i in 0..3 {
                        light[i] += self.o.diffuse * lambert * s * col[i];
                    }
                    if self.o.shading == Shading::Specular {
                        let h = unit([l[0] + view[0], l[1] + view[1], l[2] + view[2]]);
                        let sp = self.o.specular * libm::powf(dot(n, h).max(0.0), self.o.shininess) * s;
                        for i in 0..3 {
                            spec[i] += sp * col[i];
                        }
                    }
                }
            }
        }
        std::array::from_fn(|i| base[i] * light[i] + spec[i])
    }
}

fn render_with<Q: VoxelQuery>(
    tree: &Hypertree,
    q: &Q,
    opts: &RenderOptions,
    progress: &mut dyn FnMut(u32, u32),
) -> Result<(Image, RenderStats), RenderError> {
    let (w, h, s) = (opts.width, opts.height, opts.supersample);
    let mut pixels = vec![0u8; w as usize * h as usize * 3];
    let bg = |y: f32| -> [f32; 3] {
        std::array::from_fn(|i| opts.background[0][i] + (opts.background[1][i] - opts.background[0][i]) * y)
    };
    let Some(aabb) = tree.aabb() else {
        for y in 0..h {
            let c = bg((y as f32 + 0.5) / h as f32);
            for x in 0..w {
                let i = 3 * (y as usize * w as usize + x as usize);
                for k in 0..3 {
                    pixels[i + k] = to_u8(c[k]);
                }
            }
            progress(y + 1, h);
        }
        return Ok((Image { width: w, height: h, pixels }, RenderStats::default()));
    };
    let cam = ReferenceCamera::new(&aabb, opts);
    let eye = cam.eye;
    let mut scene = Scene::new(tree, q, aabb, opts, eye);
    let diag_steps = (norm(std::array::from_fn(|i| aabb.max[i] - aabb.min[i])) / scene.step) as usize + 4;
    scene.memo = vec![[f32::NAN; 3]; scene.mask.count()];
    if opts.ray_cache {
        scene.ray_cache = vec![(u32::MAX, Voxel::EMPTY); diag_steps];
    }
    let mut intervals = Vec::new();
    let inv_s = 1.0 / s as f32;
    let weight = 1.0 / (s * s) as f32;
    for py in 0..h {
        for px in 0..w {
            let mut acc = [0.0f32; 3];
            for sy in 0..s {
                for sx in 0..s {
                    let fx = (px as f32 + (sx as f32 + 0.5) * inv_s) / w as f32;
                    let fy = (py as f32 + (sy as f32 + 0.5) * inv_s) / h as f32;
                    let d = cam.ray(fx, fy);
                    let (c, a) = scene.march(eye, d, &mut intervals);
                    let b = bg(fy);
                    for i in 0..3 {
                        acc[i] += weight * (c[i] + (1.0 - a) * b[i]);
                    }
                }
            }
            let i = 3 * (py as usize * w as usize + px as usize);
            for k in 0..3 {
                pixels[i + k] = to_u8(acc[k]);
            }
        }
        progress(py + 1, h);
    }
    Ok((Image { width: w, height: h, pixels }, scene.stats))
}

/// `⌊x⌋` for the sample numbers along a ray (exact; `x` is finite and far below 2⁶³).
#[inline]
fn floor_i(x: f32) -> i64 {
    let i = x as i64;
    if (i as f32) > x { i - 1 } else { i }
}

/// `⌈x⌉`, likewise.
#[inline]
fn ceil_i(x: f32) -> i64 {
    let i = x as i64;
    if (i as f32) < x { i + 1 } else { i }
}

#[inline]
fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}
