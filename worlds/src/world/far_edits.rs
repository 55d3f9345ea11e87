//! A cell's live edits as its far-view leaf takes them ([`LeafEdit`]s): what a delta from version 0 changes against
//! the world function's placements of the cell — every felled instance out, every planted one in, an instance
//! whose `height` was set out at its old height and in at its new one.

use std::collections::BTreeMap;
use std::sync::Arc;

use canopy_protocol::edit::CellDelta;

use super::far::default_mean;
use super::{CellKey, Placement, World};

/// One instance a cell's edits add to (`sign` +1) or take from (−1) the cell's leaf summary
/// ([`World::leaf_edits`], [`super::Summaries::correct`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LeafEdit {
    /// Species id.
    pub species: u16,
    /// World position, metres.
    pub x: f64,
    /// World position, metres.
    pub z: f64,
    /// Its `height` parameter where the species has one (the instance's value, or the species default's mean).
    pub height: Option<f32>,
    /// +1 (planted, or a new height) or −1 (felled, or the old height); a leaf counts any other value by its sign.
    pub sign: i8,
}

/// Cells' edits as their leaves take them, by cell.
pub(super) type Corrections = BTreeMap<CellKey, Arc<[LeafEdit]>>;

/// Most cells a [`super::Summaries`] takes edits for (they come from the network): past it,
/// [`super::Summaries::correct`] refuses a new cell's edits and keeps those it has, so that cell's leaf stays the
/// world function's until a corrected cell is given back (`correct(cell, None)`).
pub const MAX_CORRECTED_CELLS: usize = 4096;

impl World {
    /// The leaf edits of `cell`: what `delta` (its edits from version 0: instances planted at indices
    /// `total − adds.len() ..`, indices felled, parameters set on the world function's instances) changes against
    /// its world-function placements `base` ([`World::expand_cell`], in index order). An instance planted and
    /// felled in the same delta gives nothing; indices naming nothing are skipped.
    pub fn leaf_edits(&self, cell: CellKey, base: &[Placement], delta: &CellDelta) -> Vec<LeafEdit> {
        let slot_of = |species: u16| {
            let s = self.species.get(usize::from(species))?;
            let slot = s.graph.param_slot("height")?;
            Some((slot, s.graph.params.get(usize::from(slot))?))
        };
        // An instance's height: its own value for the slot, else the species default's mean where it is a
        // constant or `uniform` of two.
        let height = |species: u16, own: &[(u16, f32)]| -> Option<f32> {
            let (slot, param) = slot_of(species)?;
            own.iter().find(|(s, _)| *s == slot).map(|&(_, v)| v).or_else(|| default_mean(&param.default))
        };
        let first_added = usize::from(delta.total).saturating_sub(delta.adds.len());
        // The world function's instances: those below the first planted index (a `base` longer than that does
        // not agree with the delta, and its tail is not read).
        let base = &base[..base.len().min(first_added)];
        let felled = |i: usize| delta.removes.binary_search(&(i as u16)).is_ok();
        let mut out = Vec::new();
        for &i in &delta.removes {
            if let Some(p) = base.get(usize::from(i)) {
                let h = height(p.species, &p.params);
                out.push(LeafEdit { species: p.species, x: p.x, z: p.z, height: h, sign: -1 });
            }
        }
        for (k, a) in delta.adds.iter().enumerate() {
            if felled(first_added + k) {
                continue;
            }
            let species = u16::from(a.record.species);
            let [x, z] = self.dequantize(cell, [a.record.qx(), a.record.qz()]);
            let own: Vec<(u16, f32)> = a.params.iter().map(|&(s, v)| (s, v.0)).collect();
            let h = height(species, &own);
            out.push(LeafEdit { species, x, z, height: h, sign: 1 });
        }
        for (i, set) in &delta.updates {
            let Some(p) = base.get(usize::from(*i)).filter(|_| !felled(usize::from(*i))) else { continue };
            let Some((slot, _)) = slot_of(p.species) else { continue };
            let Some(&(_, new)) = set.iter().find(|(s, _)| *s == slot) else { continue };
            let old = height(p.species, &p.params);
            if old.map(f32::to_bits) == Some(new.0.to_bits()) {
                continue;
            }
            out.push(LeafEdit { species: p.species, x: p.x, z: p.z, height: old, sign: -1 });
            out.push(LeafEdit { species: p.species, x: p.x, z: p.z, height: Some(new.0), sign: 1 });
        }
        out
    }
}
