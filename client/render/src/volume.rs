//! The far field on the CPU side: a species' hypertree volume (voxelised from a representative instance, or given
//! by the scene) with its shading baked per voxel, ready to upload as a 3D texture (seed 000 §8).
//!
//! The CPU reference renderer (`canopy_worlds::hypertree::render`) shades at voxel centres — a voxel is a
//! homogeneous region — so its default shading (attenuated ambient toward the crown's interior, diffuse with
//! procedural normals from the first-level structure flow, shadow rays to the sun, depth colour spans) is
//! view-independent: it is taken from the reference once per voxel (`shade_voxels`) and only packed here. The GPU
//! then only marches: samples at the same positions (`t0 + (n + ½)·Δs`, `Δs` the smallest voxel side, from the
//! entry into the voxels' box), nearest-voxel lookups, `α = 1 − (1 − µ)^(k·Δs)` (Δs in the reference's units) and
//! front-to-back accumulation with the same early exit — so a GPU image of a lone hypertree matches the
//! reference's (tested in `client/tests/render.rs`).
//!
//! Texels are RGBA16F: rgb the lit colour, a the voxel's opacity α.

use canopy_protocol::SpeciesGraph;
use canopy_worlds::amplify::{AmplifyError, Budget, Instance, amplify, instance_params};
use canopy_worlds::hypertree::render::{RenderError, shade_voxels};
use canopy_worlds::hypertree::voxelise::{VoxeliseError, VoxeliseOptions, voxelise};
use canopy_worlds::hypertree::{Hypertree, StorageType, ops};
use canopy_worlds::rng::InstanceRng;

use super::Lighting;

/// Largest volume edge in voxels (an atlas slot); larger scene volumes are reduced to fit (§9 voxel fusion).
pub const MAX_SLOT: u32 = 128;

/// The seed of the representative instance a species' far-field volume is voxelised from.
pub const REPRESENTATIVE_SEED: u64 = 0x005e_ed0f_ca40_b1e5;

/// A hypertree volume ready for the GPU.
#[derive(Clone, Debug, PartialEq)]
pub struct FarVolume {
    /// Voxels per axis.
    pub dims: [u32; 3],
    /// Voxel edge lengths, box units.
    pub voxel_size: [f32; 3],
    /// Lower corner of the non-empty voxels' box, box units.
    pub aabb_min: [f32; 3],
    /// Upper corner of the non-empty voxels' box, box units.
    pub aabb_max: [f32; 3],
    /// Where the species origin (the instance's position) lies, box units.
    pub origin: [f32; 3],
    /// Metres per box unit.
    pub units: f32,
    /// RGBA16F texels, x fastest then y then z (4 halves per voxel).
    pub texels: Vec<u16>,
    /// Non-empty voxels.
    pub voxels: usize,
}

impl FarVolume {
    /// The bounding sphere of the non-empty voxels in species metres, relative to the species origin.
    pub fn bounding_sphere(&self) -> ([f32; 3], f32) {
        let c: [f32; 3] =
            std::array::from_fn(|i| (0.5 * (self.aabb_min[i] + self.aabb_max[i]) - self.origin[i]) * self.units);
        let h: [f32; 3] = std::array::from_fn(|i| 0.5 * (self.aabb_max[i] - self.aabb_min[i]) * self.units);
        (c, (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt())
    }
}

/// A species' far field: the full and the halved resolution, and how instances scale.
#[derive(Clone, Debug, PartialEq)]
pub struct SpeciesVolumes {
    /// Full resolution.
    pub full: FarVolume,
    /// Halved resolution (voxel fusion, seed 000 §9), for the farthest instances.
    pub low: FarVolume,
    /// Further halvings of `low` (a quarter and an eighth of the full resolution: [`COARSER`] of them, or fewer
    /// where a volume is already a few voxels), for instances smaller still on screen: a ray marches about as many
    /// samples as the instance is pixels tall, not as the full resolution has voxels.
    pub coarser: Vec<FarVolume>,
    /// The slot of the species' `height` parameter and the representative's value of it: instances scale by their
    /// own value over this one (species without a `height` parameter draw every instance at the representative's
    /// size).
    pub height: Option<(u16, f32)>,
}

/// Why a species' volume could not be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VolumeError {
    /// Amplifying the representative failed.
    #[error("amplifying the representative instance: {0}")]
    Amplify(#[from] AmplifyError),
    /// Voxelising it failed.
    #[error("voxelising the representative instance: {0}")]
    Voxelise(#[from] VoxeliseError),
    /// Reducing the resolution failed.
    #[error("reducing the volume: {0}")]
    Reduce(String),
    /// The lighting is out of the reference shading's range.
    #[error("shading the volume: {0}")]
    Shade(#[from] RenderError),
    /// The volume has no voxels.
    #[error("the volume is empty")]
    Empty,
}

/// Voxelise a species' representative instance and bake both resolutions.
pub fn species_volumes(
    graph: &SpeciesGraph,
    resolution: u32,
    budget: &Budget,
    lighting: &Lighting,
) -> Result<SpeciesVolumes, VolumeError> {
    let (tree, origin) = voxelise_representative(graph, resolution, budget)?;
    let mut v = volumes_of(&tree, origin, 1.0, resolution, lighting)?;
    v.height = height_param(graph);
    Ok(v)
}

/// The slot of a species' `height` parameter and its value for the representative instance.
pub fn height_param(graph: &SpeciesGraph) -> Option<(u16, f32)> {
    let slot = graph.params.iter().position(|p| p.name == "height")? as u16;
    let mut rng = InstanceRng::new(REPRESENTATIVE_SEED);
    let (values, _) = instance_params(graph, &Instance::new(REPRESENTATIVE_SEED), &mut rng).ok()?;
    let v = values[usize::from(slot)];
    (v.is_finite() && v > 0.0).then_some((slot, v))
}

/// The scale of an instance relative to the representative: its `height` over the representative's (1 without a
/// `height` parameter), clamped to `[0.05, 20]`.
pub fn instance_scale(graph: &SpeciesGraph, height: Option<(u16, f32)>, seed: u64, params: &[(u16, f32)]) -> f32 {
    let Some((slot, reference)) = height else { return 1.0 };
    let value = match params.iter().rev().find(|(s, _)| *s == slot) {
        Some(&(_, v)) => v,
        None => {
            let mut rng = InstanceRng::new(seed);
            let inst = Instance { seed, params: params.to_vec(), detail: 0 };
            match instance_params(graph, &inst, &mut rng) {
                Ok((values, _)) => values[usize::from(slot)],
                Err(_) => reference,
            }
        }
    };
    let s = value / reference;
    if s.is_finite() { s.clamp(0.05, 20.0) } else { 1.0 }
}

/// Amplify the representative instance at full detail and voxelise it; returns the hypertree and the species
/// origin in box coordinates (the voxeliser pads the primitives' bounds by 2 % of the longest side).
pub fn voxelise_representative(
    graph: &SpeciesGraph,
    resolution: u32,
    budget: &Budget,
) -> Result<(Hypertree, [f32; 3]), VolumeError> {
    let stream = amplify(graph, &Instance::new(REPRESENTATIVE_SEED), budget)?;
    let opts = VoxeliseOptions { resolution, storage: StorageType::IndexList, ..VoxeliseOptions::default() };
    let tree = voxelise(&stream, &graph.name, &opts)?;
    let (lo, hi) = stream.bounds();
    let longest = (0..3).map(|i| hi[i] - lo[i]).fold(0.0f32, f32::max).max(1e-6);
    let pad = 0.02 * longest;
    Ok((tree, std::array::from_fn(|i| pad - lo[i])))
}

/// Halvings of a species' volume below the halved one.
pub const COARSER: usize = 2;
/// Resolutions a far instance can be drawn at: full, halved and the [`COARSER`] ones.
pub const FAR_LEVELS: usize = 2 + COARSER;

/// Bake a hypertree at its resolution (reduced so that no axis exceeds `max_edge` voxels, at most [`MAX_SLOT`]),
/// at half of it, and at up to [`COARSER`] further halvings.
pub fn volumes_of(
    tree: &Hypertree,
    origin: [f32; 3],
    units: f32,
    max_edge: u32,
    lighting: &Lighting,
) -> Result<SpeciesVolumes, VolumeError> {
    let fit = |t: &Hypertree, edge: u32| -> Result<Option<Hypertree>, VolumeError> {
        let r = t.volume.resolution;
        let longest = r[0].max(r[1]).max(r[2]);
        if longest <= edge {
            return Ok(None);
        }
        let target = r.map(|v| ((u64::from(v) * u64::from(edge)).div_ceil(u64::from(longest)) as u32).clamp(1, edge));
        ops::reduce(t, target).map(Some).map_err(|e| VolumeError::Reduce(e.to_string()))
    };
    let full_tree = fit(tree, max_edge.clamp(1, MAX_SLOT))?;
    let full_tree = full_tree.as_ref().unwrap_or(tree);
    let halve = |t: &Hypertree| {
        ops::reduce(t, t.volume.resolution.map(|v| v.div_ceil(2).max(1)))
            .map_err(|e| VolumeError::Reduce(e.to_string()))
    };
    let mut last = halve(full_tree)?;
    let low = bake(&last, origin, units, lighting)?;
    let mut coarser = Vec::with_capacity(COARSER);
    for _ in 0..COARSER {
        if last.volume.resolution.iter().copied().max().unwrap_or(0) <= 4 {
            break;
        }
        last = halve(&last)?;
        coarser.push(bake(&last, origin, units, lighting)?);
    }
    Ok(SpeciesVolumes { full: bake(full_tree, origin, units, lighting)?, low, coarser, height: None })
}

/// Bake one hypertree: per-voxel lit colour and opacity (see the module docs).
pub fn bake(tree: &Hypertree, origin: [f32; 3], units: f32, lighting: &Lighting) -> Result<FarVolume, VolumeError> {
    let aabb = tree.aabb().ok_or(VolumeError::Empty)?;
    let vol = tree.volume;
    let shaded = shade_voxels(tree, &lighting.reference_options())?;
    let mut texels = vec![0u16; 4 * vol.voxel_count() as usize];
    for s in &shaded {
        let [r, g, b] = s.color.map(f16_bits);
        texels[4 * s.index as usize..][..4].copy_from_slice(&[r, g, b, f16_bits(s.alpha)]);
    }
    Ok(FarVolume {
        dims: vol.resolution,
        voxel_size: vol.voxel_size(),
        aabb_min: aabb.min,
        aabb_max: aabb.max,
        origin,
        units,
        texels,
        voxels: shaded.len(),
    })
}

/// One ray through a baked volume exactly as `shaders/volume.wgsl` marches it (origin and unit direction in box
/// units): premultiplied colour and opacity. The CPU twin of the shader, for tests and tools.
pub fn march(v: &FarVolume, o: [f32; 3], d: [f32; 3]) -> ([f32; 3], f32) {
    let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
    for i in 0..3 {
        let inv = 1.0 / d[i];
        let (a, b) = ((v.aabb_min[i] - o[i]) * inv, (v.aabb_max[i] - o[i]) * inv);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    if t1 < t0 {
        return ([0.0; 3], 0.0);
    }
    let step = v.voxel_size[0].min(v.voxel_size[1]).min(v.voxel_size[2]);
    let last = ((t1 - t0) / step - 0.5).floor() as i64;
    let (mut color, mut alpha) = ([0.0f32; 3], 0.0f32);
    for n in 0..=last.min(1024) {
        let t = t0 + (n as f32 + 0.5) * step;
        let p: [f32; 3] = std::array::from_fn(|i| o[i] + d[i] * t);
        let c: [i64; 3] = std::array::from_fn(|i| (p[i] / v.voxel_size[i]).floor() as i64);
        if (0..3).any(|i| c[i] < 0 || c[i] >= i64::from(v.dims[i])) {
            continue;
        }
        let idx = (c[0] + i64::from(v.dims[0]) * (c[1] + i64::from(v.dims[1]) * c[2])) as usize;
        let a = half_to_f32(v.texels[4 * idx + 3]);
        if a > 0.0 {
            let w = (1.0 - alpha) * a;
            for (i, c) in color.iter_mut().enumerate() {
                *c += w * half_to_f32(v.texels[4 * idx + i]);
            }
            alpha += w;
            if alpha >= 0.995 {
                break;
            }
        }
    }
    (color, alpha)
}

/// The value of IEEE 754 binary16 bits.
pub fn half_to_f32(h: u16) -> f32 {
    let e = (h >> 10) & 0x1f;
    let m = f32::from(h & 0x3ff);
    let v = match e {
        0 => m * 2f32.powi(-24),
        31 if m == 0.0 => f32::INFINITY,
        31 => f32::NAN,
        _ => (1.0 + m / 1024.0) * 2f32.powi(i32::from(e) - 15),
    };
    if h & 0x8000 != 0 { -v } else { v }
}

/// IEEE 754 binary16 bits of `v`, rounded to nearest even (overflow to infinity, tiny values to subnormals).
pub fn f16_bits(v: f32) -> u16 {
    let b = v.to_bits();
    let sign = ((b >> 16) & 0x8000) as u16;
    let exp = ((b >> 23) & 0xff) as i32;
    let man = b & 0x7f_ffff;
    if exp == 0xff {
        return sign | 0x7c00 | if man != 0 { 0x200 } else { 0 };
    }
    let e = exp - 127 + 15;
    if e >= 31 {
        return sign | 0x7c00;
    }
    let round = |m: u32, shift: u32| -> u32 {
        let h = m >> shift;
        let rem = m & ((1 << shift) - 1);
        let halfway = 1 << (shift - 1);
        if rem > halfway || (rem == halfway && h & 1 == 1) { h + 1 } else { h }
    };
    if e <= 0 {
        if e < -10 {
            return sign;
        }
        return sign | round(man | 0x80_0000, (14 - e) as u32) as u16;
    }
    // A carry out of the mantissa correctly bumps the exponent (up to infinity).
    sign | (((e as u32) << 10) + round(man, 13)) as u16
}

#[cfg(test)]
mod tests {
    use canopy_worlds::library;

    use super::*;

    #[test]
    fn half_floats() {
        assert_eq!(f16_bits(0.0), 0);
        assert_eq!(f16_bits(-0.0), 0x8000);
        assert_eq!(f16_bits(1.0), 0x3c00);
        assert_eq!(f16_bits(0.5), 0x3800);
        assert_eq!(f16_bits(-2.0), 0xc000);
        assert_eq!(f16_bits(65504.0), 0x7bff);
        assert_eq!(f16_bits(1e6), 0x7c00);
        assert_eq!(f16_bits(f32::NAN) & 0x7e00, 0x7e00);
        assert_eq!(f16_bits(6.103_515_6e-5), 0x0400, "smallest normal");
        assert_eq!(f16_bits(5.960_464_5e-8), 0x0001, "smallest subnormal");
        assert_eq!(f16_bits(1e-9), 0);
        assert_eq!(f16_bits(1.0 + 1.0 / 2048.0), 0x3c00, "ties to even");
        assert_eq!(f16_bits(1.0 + 3.0 / 2048.0), 0x3c02, "ties to even, upward");
        assert_eq!(f16_bits(0.1), 0x2e66);
    }

    #[test]
    fn the_representative_volume_lines_up_with_the_species() {
        let g = library::find("conifer").unwrap().load().unwrap();
        let (tree, origin) = voxelise_representative(&g, 48, &Budget::default()).unwrap();
        let stream = amplify(&g, &Instance::new(REPRESENTATIVE_SEED), &Budget::default()).unwrap();
        let (lo, hi) = stream.bounds();
        let aabb = tree.aabb().unwrap();
        let s = tree.volume.voxel_size();
        for i in 0..3 {
            // The voxels' box, moved back to species space, matches the primitives' bounds within a voxel or two.
            assert!((aabb.min[i] - origin[i] - lo[i]).abs() <= 2.0 * s[i], "axis {i}: {aabb:?} {origin:?} {lo:?}");
            assert!((aabb.max[i] - origin[i] - hi[i]).abs() <= 2.0 * s[i], "axis {i}: {aabb:?} {origin:?} {hi:?}");
        }
    }

    #[test]
    fn baked_volumes_shade_the_sunny_side_brighter_and_fade_to_empty() {
        let g = library::find("conifer").unwrap().load().unwrap();
        let v = species_volumes(&g, 40, &Budget::default(), &Lighting::default()).unwrap();
        assert_eq!(v.full.dims.iter().copied().max(), Some(40));
        assert_eq!(v.low.dims.iter().copied().max(), Some(20));
        assert!(v.full.voxels > 100 && v.low.voxels > 10 && v.low.voxels < v.full.voxels);
        let edges: Vec<u32> = v.coarser.iter().map(|c| c.dims.iter().copied().max().unwrap()).collect();
        assert_eq!(edges, [10, 5]);
        assert!(v.coarser.iter().all(|c| c.voxels > 0 && c.voxels < v.low.voxels));
        assert_eq!(v.height.map(|h| h.0), Some(0), "conifer declares height first");
        let (c, r) = v.full.bounding_sphere();
        assert!(r > 3.0 && c[1] > 0.0, "{c:?} {r}");
        // Mean brightness of the half of the crown toward the sun (−x, +z) against the other half.
        let (mut lit, mut shade) = ((0.0f64, 0u32), (0.0f64, 0u32));
        let [dx, dy, _] = v.full.dims;
        let mid = 0.5 * (v.full.aabb_min[0] + v.full.aabb_max[0]);
        for (i, t) in v.full.texels.chunks_exact(4).enumerate() {
            if t[3] == 0 {
                continue;
            }
            let x = (i as u32 % dx) as f32 + 0.5;
            let _ = dy;
            let g = half_to_f32(t[1]) as f64;
            if x * v.full.voxel_size[0] < mid {
                lit = (lit.0 + g, lit.1 + 1);
            } else {
                shade = (shade.0 + g, shade.1 + 1);
            }
        }
        assert!(lit.0 / lit.1 as f64 > shade.0 / shade.1 as f64, "sunny side {lit:?}, far side {shade:?}");
        let scale = instance_scale(&g, v.height, 5, &[(0, 2.0 * v.height.unwrap().1)]);
        assert!((scale - 2.0).abs() < 1e-6);
        assert_eq!(instance_scale(&g, None, 5, &[]), 1.0);
    }

    #[test]
    fn half_round_trip() {
        for v in [0.0f32, 0.25, 0.3, 0.777, 1.3, 3.5, 100.0] {
            assert!((half_to_f32(f16_bits(v)) - v).abs() <= v * 1e-3, "{v}");
        }
    }

    #[test]
    fn marching_the_baked_volume_reproduces_the_cpu_reference() {
        use canopy_worlds::hypertree::generate::{GenerateOptions, generate};
        use canopy_worlds::hypertree::render::{ReferenceCamera, RenderOptions, render};
        let def = canopy_worlds::hypertree::library::find("apple").unwrap().load().unwrap();
        let opts = GenerateOptions { resolution: Some([40, 40, 40]), ..GenerateOptions::default() };
        let (tree, _) = generate(&def, 3, &opts, &mut |_, _| {}).unwrap();
        let (w, h) = (64u32, 64u32);
        let bg = [0.5f32, 0.6, 0.7];
        let ro = RenderOptions { width: w, height: h, background: [bg, bg], ..Lighting::default().reference_options() };
        let (img, _) = render(&tree, &ro, &mut |_, _| {}).unwrap();
        let v = volumes_of(&tree, [0.0; 3], 1.0, 64, &Lighting::default()).unwrap().full;
        let cam = ReferenceCamera::new(&tree.aabb().unwrap(), &ro);
        let mut bad = 0;
        for py in 0..h {
            for px in 0..w {
                let d = cam.ray((px as f32 + 0.5) / w as f32, (py as f32 + 0.5) / h as f32);
                let (col, a) = march(&v, cam.eye, d);
                let ours: [u8; 3] =
                    std::array::from_fn(|i| ((col[i] + (1.0 - a) * bg[i]).clamp(0.0, 1.0) * 255.0 + 0.5) as u8);
                let theirs = img.pixel(px, py);
                if (0..3).any(|i| ours[i].abs_diff(theirs[i]) > 3) {
                    bad += 1;
                }
            }
        }
        assert!(bad <= (w * h / 100) as usize, "{bad} of {} pixels differ", w * h);
    }
}
