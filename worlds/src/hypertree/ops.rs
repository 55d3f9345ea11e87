//! Operations on hypertrees (§7, §9): union (maximum of densities) and addition of two hypertrees, setting and
//! clearing a region (trimming), and level of detail by resolution reduction with weighted voxel fusion.
//!
//! Results keep the first operand's storage structure (unpartitioned: the subpart of a combined voxel is not
//! known) and stay conservative for rendering: bounding volumes are merged, and a region that is set is added to
//! them.

use super::storage::{VoxelList, VoxelQuery, VoxelStore};
use super::{Aabb, Bounds, Hypertree, Hypervolume, StorageType, Voxel};
use crate::hypertree::generate::MAX_DENSE_VOXELS;

/// Most voxels one set operation may fill.
pub const MAX_SET_VOXELS: u64 = 1 << 26;

/// Why an operation was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OpError {
    /// The two hypertrees do not share a hypervolume (resolution and extent).
    #[error("hypervolumes differ: {0:?} {1:?} vs {2:?} {3:?}")]
    VolumeMismatch([u32; 3], [f32; 3], [u32; 3], [f32; 3]),
    /// A reduced resolution is zero or larger than the current one.
    #[error("reduced resolution {new:?} must be between 1 and the current {old:?} on every axis")]
    Resolution {
        /// The current resolution.
        old: [u32; 3],
        /// The requested one.
        new: [u32; 3],
    },
    /// A region is not finite or empty.
    #[error("region {0:?}..{1:?} is not a finite, non-empty box")]
    Region([f32; 3], [f32; 3]),
    /// Setting a region would fill too many voxels.
    #[error("region covers {0} voxels (allowed {MAX_SET_VOXELS})")]
    RegionTooLarge(u64),
    /// Setting a region to density 0 (use clear).
    #[error("set density must be 1..=255 (use clear to empty a region)")]
    ZeroDensity,
    /// The result cannot be stored as a dense array.
    #[error("a dense array of {0} voxels exceeds {MAX_DENSE_VOXELS}")]
    DenseTooLarge(u64),
}

/// How two densities combine.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Unification {
    /// `µ = max(µ1, µ2)` (§7, the union of hypertrees); the level comes from the denser voxel (the shallower on a
    /// tie).
    Max,
    /// `µ = min(µ1 + µ2, 255)`; the shallower level.
    Add,
}

fn same_volume(a: &Hypervolume, b: &Hypervolume) -> Result<(), OpError> {
    if a.resolution != b.resolution || a.extent != b.extent {
        return Err(OpError::VolumeMismatch(a.resolution, a.extent, b.resolution, b.extent));
    }
    Ok(())
}

fn rebuild(like: &Hypertree, volume: Hypervolume, list: VoxelList, bounds: Bounds) -> Result<Hypertree, OpError> {
    let ty = like.store.storage_type();
    if ty == StorageType::Dense && volume.voxel_count() > MAX_DENSE_VOXELS {
        return Err(OpError::DenseTooLarge(volume.voxel_count()));
    }
    let store = VoxelStore::from_list(list, ty, &volume);
    Ok(Hypertree::new(
        like.name.clone(),
        volume,
        store,
        like.depth_colors.clone(),
        like.tree_depth,
        like.branch_depth,
        bounds,
        like.flows.clone(),
    ))
}

/// Combine two hypertrees voxel by voxel (§7): `a ∪ b` with [`Unification::Max`], `a + b` with
/// [`Unification::Add`].
pub fn combine(a: &Hypertree, b: &Hypertree, how: Unification) -> Result<Hypertree, OpError> {
    same_volume(&a.volume, &b.volume)?;
    let (la, lb) = (a.store.to_list(), b.store.to_list());
    let mut out = VoxelList::default();
    let (mut i, mut j) = (0, 0);
    while i < la.len() || j < lb.len() {
        let ia = la.indices.get(i).copied().unwrap_or(u32::MAX);
        let ib = lb.indices.get(j).copied().unwrap_or(u32::MAX);
        if i < la.len() && (j == lb.len() || ia < ib) {
            out.push(ia, Voxel { density: la.densities[i], level: la.levels[i] });
            i += 1;
        } else if j < lb.len() && (i == la.len() || ib < ia) {
            out.push(ib, Voxel { density: lb.densities[j], level: lb.levels[j] });
            j += 1;
        } else {
            let (va, vb) = (
                Voxel { density: la.densities[i], level: la.levels[i] },
                Voxel { density: lb.densities[j], level: lb.levels[j] },
            );
            let v = match how {
                Unification::Max => {
                    if va.density > vb.density || (va.density == vb.density && va.level <= vb.level) {
                        va
                    } else {
                        vb
                    }
                }
                Unification::Add => {
                    Voxel { density: va.density.saturating_add(vb.density), level: va.level.min(vb.level) }
                }
            };
            out.push(ia, v);
            i += 1;
            j += 1;
        }
    }
    let mut t = rebuild(a, a.volume, out, a.bounds.merged(&b.bounds))?;
    t.flows.extend(b.flows.iter().copied());
    t.tree_depth = a.tree_depth.max(b.tree_depth);
    t.name = format!("{}+{}", a.name, b.name);
    Ok(t)
}

/// The voxel range `[lo, hi)` per axis whose centres lie in the box region.
fn region_voxels(v: &Hypervolume, min: [f32; 3], max: [f32; 3]) -> Result<([u32; 3], [u32; 3]), OpError> {
    if (0..3).any(|i| !(min[i].is_finite() && max[i].is_finite() && min[i] < max[i])) {
        return Err(OpError::Region(min, max));
    }
    let s = v.voxel_size();
    let mut lo = [0u32; 3];
    let mut hi = [0u32; 3];
    for i in 0..3 {
        // Centre (x + 0.5)·s inside [min, max)  ⇔  x in [min/s − 0.5, max/s − 0.5).
        let a = libm::ceilf(min[i] / s[i] - 0.5).clamp(0.0, v.resolution[i] as f32);
        let b = libm::ceilf(max[i] / s[i] - 0.5).clamp(0.0, v.resolution[i] as f32);
        lo[i] = a as u32;
        hi[i] = (b as u32).max(lo[i]);
    }
    Ok((lo, hi))
}

/// Clear every voxel whose centre lies in the box `[min, max)` (box coordinates): trimming as a postprocess (§7).
pub fn clear_region(t: &Hypertree, min: [f32; 3], max: [f32; 3]) -> Result<Hypertree, OpError> {
    let (lo, hi) = region_voxels(&t.volume, min, max)?;
    let mut out = VoxelList::default();
    t.store.for_each(|i, v| {
        let c = t.volume.coords(i);
        if !(0..3).all(|a| c[a] >= lo[a] && c[a] < hi[a]) {
            out.push(i, v);
        }
    });
    rebuild(t, t.volume, out, t.bounds.clone())
}

/// Set every voxel whose centre lies in `[min, max)` to `voxel` (which must not be empty).
pub fn set_region(t: &Hypertree, min: [f32; 3], max: [f32; 3], voxel: Voxel) -> Result<Hypertree, OpError> {
    if voxel.density == 0 {
        return Err(OpError::ZeroDensity);
    }
    let (lo, hi) = region_voxels(&t.volume, min, max)?;
    let n: u64 = (0..3).map(|a| u64::from(hi[a] - lo[a])).product();
    if n > MAX_SET_VOXELS {
        return Err(OpError::RegionTooLarge(n));
    }
    let mut region = VoxelList::default();
    for z in lo[2]..hi[2] {
        for y in lo[1]..hi[1] {
            for x in lo[0]..hi[0] {
                region.push(t.volume.index([x, y, z]), voxel);
            }
        }
    }
    let old = t.store.to_list();
    let mut out = VoxelList::default();
    let (mut i, mut j) = (0, 0);
    while i < old.len() || j < region.len() {
        if j == region.len() || (i < old.len() && old.indices[i] < region.indices[j]) {
            out.push(old.indices[i], Voxel { density: old.densities[i], level: old.levels[i] });
            i += 1;
        } else {
            if i < old.len() && old.indices[i] == region.indices[j] {
                i += 1;
            }
            out.push(region.indices[j], voxel);
            j += 1;
        }
    }
    let mut bounds = t.bounds.clone();
    if !bounds.is_empty() && n > 0 {
        let s = t.volume.voxel_size();
        bounds.boxes.push(
            Aabb {
                min: std::array::from_fn(|a| lo[a] as f32 * s[a]),
                max: std::array::from_fn(|a| hi[a] as f32 * s[a]),
            }
            .padded(s[0].max(s[1]).max(s[2])),
        );
    }
    rebuild(t, t.volume, out, bounds)
}

/// Level of detail by resolution reduction (§9): each new voxel is the weighted average of the old voxels it
/// covers, weights being the shares of old voxels inside it (the 3D form of Figure 5's formula, any reduction
/// factor ≥ 1); its level is the most represented level by share among its non-empty old voxels (the shallower on
/// a tie). The extent is kept.
pub fn reduce(t: &Hypertree, resolution: [u32; 3]) -> Result<Hypertree, OpError> {
    let old = t.volume;
    if (0..3).any(|i| resolution[i] == 0 || resolution[i] > old.resolution[i]) {
        return Err(OpError::Resolution { old: old.resolution, new: resolution });
    }
    let new = Hypervolume { resolution, extent: old.extent };
    let r: [f64; 3] = std::array::from_fn(|i| f64::from(old.resolution[i]) / f64::from(resolution[i]));
    let norm = r[0] * r[1] * r[2];
    let list = t.store.to_list();
    let plane = old.resolution[0] * old.resolution[1];
    let mut out = VoxelList::default();
    let mut contributions: Vec<(u32, f64, u8, f64)> = Vec::new();
    let mut levels = [0f64; 256];
    // Process one new z-slab at a time: the old voxels whose z overlaps it form a contiguous run of the list.
    for nz in 0..resolution[2] {
        let z0 = f64::from(nz) * r[2];
        let z1 = z0 + r[2];
        let (oz0, oz1) = (libm::floor(z0) as u32, (libm::ceil(z1) as u32).min(old.resolution[2]));
        let start = list.indices.partition_point(|&i| i < oz0 * plane);
        let end = list.indices.partition_point(|&i| i < oz1 * plane);
        contributions.clear();
        for k in start..end {
            let c = old.coords(list.indices[k]);
            let wz = overlap(c[2], nz, r[2]);
            if wz <= 0.0 {
                continue;
            }
            let mu = f64::from(list.densities[k]);
            let (x0, x1) = new_range(c[0], r[0], resolution[0]);
            let (y0, y1) = new_range(c[1], r[1], resolution[1]);
            for ny in y0..=y1 {
                let wy = overlap(c[1], ny, r[1]);
                if wy <= 0.0 {
                    continue;
                }
                for nx in x0..=x1 {
                    let wx = overlap(c[0], nx, r[0]);
                    if wx <= 0.0 {
                        continue;
                    }
                    let w = wx * wy * wz;
                    contributions.push((new.index([nx, ny, nz]), w * mu, list.levels[k], w));
                }
            }
        }
        // A stable sort keeps each new voxel's contributions in old-index order: deterministic sums.
        contributions.sort_by_key(|c| c.0);
        let mut k = 0;
        while k < contributions.len() {
            let idx = contributions[k].0;
            let mut sum = 0.0f64;
            let mut touched: Vec<u8> = Vec::new();
            while k < contributions.len() && contributions[k].0 == idx {
                let (_, wmu, level, share) = contributions[k];
                sum += wmu;
                if levels[level as usize] == 0.0 {
                    touched.push(level);
                }
                levels[level as usize] += share;
                k += 1;
            }
            let density = libm::round(sum / norm).clamp(0.0, 255.0) as u8;
            touched.sort_unstable();
            let mut best = (touched[0], -1.0f64);
            for &l in &touched {
                if levels[l as usize] > best.1 {
                    best = (l, levels[l as usize]);
                }
                levels[l as usize] = 0.0;
            }
            if density > 0 {
                out.push(idx, Voxel { density, level: best.0 });
            }
        }
    }
    rebuild(t, new, out, t.bounds.clone())
}

/// Overlap length, in old voxels, of old voxel `o` with new voxel `n` along an axis of reduction factor `r`.
fn overlap(o: u32, n: u32, r: f64) -> f64 {
    let (a0, a1) = (f64::from(o), f64::from(o) + 1.0);
    let (b0, b1) = (f64::from(n) * r, f64::from(n + 1) * r);
    (a1.min(b1) - a0.max(b0)).max(0.0)
}

/// The new voxels an old voxel `o` overlaps along one axis.
fn new_range(o: u32, r: f64, res: u32) -> (u32, u32) {
    let a = (libm::floor(f64::from(o) / r) as u32).min(res - 1);
    let b = (libm::floor((f64::from(o) + 1.0) / r) as u32).min(res - 1);
    (a, b)
}

impl Hypertree {
    /// The density at `index` as a fraction (for tests and tools).
    pub fn density(&self, index: u32) -> f32 {
        f32::from(self.store.voxel(index).density) / 255.0
    }
}
