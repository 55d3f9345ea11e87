//! Density classes (§4, Figure 3): hit counts to densities by histogram equalisation.

use super::VoxelList;

/// The mapping from hit counts to densities (§4, Figure 3): hit counts are distributed into classes so that each
/// class holds about the same number of voxels — histogram equalisation: hit count `n` goes to class
/// `⌈F(n) · (C − 1)⌉`, where `F` is the cumulative share of voxels hit at most `n` times. A hit count shared by more
/// than a class's share of the voxels (the many voxels hit once) fills its class alone and the classes it spans
/// stay empty. Class `c` of `C − 1` non-empty classes has density `round(255 · c / (C − 1))`; two classes make a
/// binary (solid) hypertree.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DensityClasses {
    /// Density for each hit count 0..=255 (0 hits → 0).
    pub density: [u8; 256],
    /// Class index for each hit count.
    pub class: [u8; 256],
}

impl DensityClasses {
    /// Equalise `histogram` (voxels per hit count) into `classes` classes, the empty one included.
    pub fn equalise(histogram: &[u64; 256], classes: u8) -> DensityClasses {
        let nonempty = u64::from(classes.max(2) - 1);
        let total: u64 = histogram[1..].iter().sum::<u64>().max(1);
        let mut density = [0u8; 256];
        let mut class = [0u8; 256];
        let mut cum = 0u64;
        for n in 1..256 {
            cum += histogram[n];
            let c = (cum * nonempty).div_ceil(total).clamp(1, nonempty);
            class[n] = c as u8;
            density[n] = ((255 * c + nonempty / 2) / nonempty) as u8;
        }
        DensityClasses { density, class }
    }
}

/// Densities from hit counts: equalised density classes, full density for branch levels (≤ `branch_depth`).
pub(super) fn classify(mut list: VoxelList, hits_of: &[u8], classes: u8, branch_depth: u8) -> VoxelList {
    let mut histogram = [0u64; 256];
    for &h in hits_of {
        histogram[h as usize] += 1;
    }
    let dc = DensityClasses::equalise(&histogram, classes);
    for (d, (&h, &l)) in list.densities.iter_mut().zip(hits_of.iter().zip(&list.levels)) {
        *d = if l <= branch_depth { 255 } else { dc.density[h as usize] };
    }
    list
}
