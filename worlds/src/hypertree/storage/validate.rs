//! Validation (§5): compact hit records (voxel, subpart, hit count, shallowest level), merged chunk by chunk, then
//! combined per voxel, classified into densities and built into a store.

use super::super::{Hypervolume, StorageType, Voxel};
use super::classes::classify;
use super::sort::radix_sort;
use super::{Partitioned, VoxelList, VoxelStore};

/// One compacted hit record: voxel, subpart, hit count (saturating at 255) and the shallowest level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Compact {
    /// `subpart << 32 | index`: records sort by subpart, then voxel.
    pub(super) key: u64,
    /// Hits of the voxel by the subpart, saturating at 255.
    pub(super) hits: u8,
    /// The shallowest level among them.
    pub(super) level: u8,
}

/// Merge freshly counted runs (sorted by key) into the compact list.
pub(super) fn merge_runs(compact: &mut Vec<Compact>, runs: Vec<Compact>) {
    if compact.is_empty() {
        *compact = runs;
        return;
    }
    let old = std::mem::take(compact);
    let mut out = Vec::with_capacity(old.len() + runs.len());
    let (mut a, mut b) = (0, 0);
    while a < old.len() || b < runs.len() {
        let take_a = b == runs.len() || (a < old.len() && old[a].key <= runs[b].key);
        let take_b = a == old.len() || (b < runs.len() && runs[b].key <= old[a].key);
        if take_a && take_b {
            let (x, y) = (old[a], runs[b]);
            out.push(Compact { key: x.key, hits: x.hits.saturating_add(y.hits), level: x.level.min(y.level) });
            a += 1;
            b += 1;
        } else if take_a {
            out.push(old[a]);
            a += 1;
        } else {
            out.push(runs[b]);
            b += 1;
        }
    }
    *compact = out;
}

/// Build index lists (per part if `partitioned`) from compact records sorted by (subpart, index).
pub(super) fn build_lists(
    compact: &[Compact],
    ty: StorageType,
    partitioned: bool,
    volume: &Hypervolume,
    classes: u8,
    branch_depth: u8,
) -> VoxelStore {
    // Combine subparts per voxel: total hits (saturating) and shallowest level. Unpartitioned records are already
    // in index order; partitioned ones are re-sorted by index first.
    let mut merged: Vec<u64>;
    let records: &mut dyn Iterator<Item = (u32, u8, u8)> = if partitioned {
        merged =
            compact.iter().map(|c| (c.key & 0xffff_ffff) << 16 | u64::from(c.level) << 8 | u64::from(c.hits)).collect();
        let mut scratch = Vec::new();
        radix_sort(&mut merged, &mut scratch);
        &mut merged.iter().map(|&k| ((k >> 16) as u32, (k & 0xff) as u8, (k >> 8 & 0xff) as u8))
    } else {
        &mut compact.iter().map(|c| (c.key as u32, c.hits, c.level))
    };
    let mut combined = VoxelList::default();
    let mut hits_of: Vec<u8> = Vec::new();
    for (index, hits, level) in records {
        if combined.indices.last() == Some(&index) {
            let h = hits_of.last_mut().expect("parallel to the list");
            *h = h.saturating_add(hits);
            let l = combined.levels.last_mut().expect("non-empty");
            *l = (*l).min(level);
        } else {
            hits_of.push(hits);
            combined.push(index, Voxel { density: 1, level });
        }
    }
    let combined = classify(combined, &hits_of, classes, branch_depth);
    if !partitioned || ty == StorageType::Dense {
        return VoxelStore::from_list(combined, ty, volume);
    }
    // One list per subpart: records of a subpart are contiguous and in index order.
    let mut parts: Vec<(u8, VoxelList)> = Vec::new();
    for rec in compact {
        let sub = (rec.key >> 32) as u8;
        let index = rec.key as u32;
        if parts.last().is_none_or(|p| p.0 != sub) {
            parts.push((sub, VoxelList::default()));
        }
        let density = combined.position(index).map_or(1, |p| combined.densities[p]);
        parts.last_mut().expect("pushed").1.push(index, Voxel { density, level: rec.level });
    }
    VoxelStore::Partitioned(Partitioned::from_parts(parts, ty, volume))
}
