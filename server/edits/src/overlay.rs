//! A cell's overlay: its edit log folded over the world function's records. It says what the cell holds at its
//! current version (records, parameters, felled indices), checks a new edit against that, and composes the delta
//! between an older version and the current one from the latest edits it keeps.

use std::collections::{BTreeMap, BTreeSet, VecDeque};

use canopy_protocol::edit::{CellDelta, Planted};
use canopy_protocol::record::{PackedF32, ParamOverride};
use canopy_protocol::{InstanceRecord, ServerMsg, netlimits};

use crate::log::{CellEdit, StoredEdit};
use crate::rules::EditRules;

/// The latest edits an overlay keeps to compose deltas from; a client holding an older version gets the whole cell.
pub(crate) const LOG_KEEP: usize = 1024;

/// Why an edit does not apply to a cell.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum OverlayError {
    /// The edit does not make the cell's next version.
    #[error("edit makes version {got}, the cell's next is {expected}")]
    Version {
        /// The next version.
        expected: u32,
        /// The edit's.
        got: u32,
    },
    /// No instance has this index in the cell.
    #[error("no instance {0} in the cell")]
    NoInstance(u16),
    /// The instance was felled.
    #[error("instance {0} was felled")]
    Felled(u16),
    /// A plant not at the cell's next index.
    #[error("plant at index {got}, the cell's next index is {expected}")]
    PlantIndex {
        /// The next index.
        expected: u16,
        /// The plant's.
        got: u16,
    },
    /// The cell holds 65,535 instances, felled ones included.
    #[error("the cell is full (65,535 instances, felled ones included)")]
    Full,
}

/// A cell's edits folded over its `base_total` world-function records (see the module docs).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overlay {
    base_total: u16,
    version: u32,
    /// Planted instances: index `base_total + i`, with their parameters (sets included).
    planted: Vec<(InstanceRecord, Vec<(u16, f32)>)>,
    felled: BTreeSet<u16>,
    /// Parameters set on world-function instances, by index (merged over their own).
    set: BTreeMap<u16, Vec<(u16, f32)>>,
    /// The latest edits, oldest first, at most [`LOG_KEEP`].
    log: VecDeque<StoredEdit>,
}

/// A cell's records at an overlay's version: the world function's, then the planted ones.
#[derive(Clone, Debug, PartialEq)]
pub struct Applied {
    /// Every record by index, felled ones included.
    pub records: Vec<InstanceRecord>,
    /// Parameter overrides, `record` = index in the cell, sorted by `(record, slot)`.
    pub overrides: Vec<ParamOverride>,
    /// Indices felled, increasing.
    pub felled: Vec<u16>,
}

/// `over`'s slots replace or join `base`'s; both sorted by slot, and so is the result.
pub fn merge_params(base: &[(u16, f32)], over: &[(u16, f32)]) -> Vec<(u16, f32)> {
    let mut out: Vec<(u16, f32)> =
        base.iter().filter(|(s, _)| over.binary_search_by_key(s, |o| o.0).is_err()).copied().collect();
    out.extend_from_slice(over);
    out.sort_by_key(|p| p.0);
    out
}

impl Overlay {
    /// A cell of `base_total` world-function records, never edited (version 0).
    pub fn new(base_total: u16) -> Overlay {
        Overlay { base_total, ..Overlay::default() }
    }

    /// A cell's overlay from its whole log (versions 1, 2, … in order).
    pub fn from_log<'a>(
        base_total: u16,
        log: impl IntoIterator<Item = &'a StoredEdit>,
    ) -> Result<Overlay, OverlayError> {
        let mut o = Overlay::new(base_total);
        for e in log {
            o.apply(e)?;
        }
        Ok(o)
    }

    /// A cell's overlay from its whole log as the world can take it: an edit the `rules` refuse (a species the
    /// world lacks, an undeclared slot, a value out of range) is skipped — it keeps its version, a plant keeps its
    /// index as a felled instance, and nothing of it is served — and named in the list returned, with why.
    /// `base_species(i)`: the species of the world function's record `i`. An edit that does not fit the cell at
    /// all (a version gap, an index that does not exist) is still an error: the log itself is damaged.
    pub fn from_log_checked<'a>(
        base_total: u16,
        base_species: impl Fn(u16) -> Option<u8>,
        rules: &EditRules,
        log: impl IntoIterator<Item = &'a StoredEdit>,
    ) -> Result<(Overlay, Vec<(u32, String)>), OverlayError> {
        let mut o = Overlay::new(base_total);
        let mut skipped = Vec::new();
        for e in log {
            match o.refusal(e, &base_species, rules) {
                None => o.apply(e)?,
                Some(why) => {
                    o.skip(e)?;
                    skipped.push((e.version, why));
                }
            }
        }
        Ok((o, skipped))
    }

    /// Why the world's `rules` refuse `e` as this cell's next edit (`None`: they take it).
    pub fn refusal(
        &self,
        e: &StoredEdit,
        base_species: impl Fn(u16) -> Option<u8>,
        rules: &EditRules,
    ) -> Option<String> {
        match &e.op {
            CellEdit::Plant { record, params, .. } => {
                rules.check_species(record.species).and_then(|()| rules.check_params(record.species, params)).err()
            }
            CellEdit::Set { index, params } => {
                let species = match index.checked_sub(self.base_total) {
                    Some(p) => self.planted(p).map(|r| r.species),
                    None => base_species(*index),
                };
                match species {
                    Some(s) => rules.check_params(s, params).err(),
                    None => Some(format!("the species of instance {index} is not known")),
                }
            }
            CellEdit::Fell { .. } => None,
        }
    }

    /// Take `e` as the cell's next version without applying it (the rules refused it): a plant's index stays
    /// taken by a felled instance of species 0 without parameters; deltas across it are not composed (a client
    /// holding an older version gets the whole cell).
    pub fn skip(&mut self, e: &StoredEdit) -> Result<(), OverlayError> {
        let expected = self.version + 1;
        if e.version != expected {
            return Err(OverlayError::Version { expected, got: e.version });
        }
        self.check(&e.op)?;
        if let CellEdit::Plant { index, record, .. } = &e.op {
            self.planted.push((InstanceRecord::new(0, record.qx(), record.qz()), Vec::new()));
            self.felled.insert(*index);
        }
        self.version = expected;
        self.log.clear();
        Ok(())
    }

    /// The cell's version: how many edits it had.
    pub fn version(&self) -> u32 {
        self.version
    }

    /// How many world-function records the cell has.
    pub fn base_total(&self) -> u16 {
        self.base_total
    }

    /// How many records the cell has (felled ones included: their indices stay taken).
    pub fn total(&self) -> u16 {
        self.base_total + self.planted.len() as u16
    }

    /// Whether the instance at `index` exists and was not felled.
    pub fn is_live(&self, index: u16) -> bool {
        index < self.total() && !self.felled.contains(&index)
    }

    /// The record of the `i`-th planted instance (index `base_total + i`).
    pub fn planted(&self, i: u16) -> Option<InstanceRecord> {
        self.planted.get(usize::from(i)).map(|p| p.0)
    }

    /// Indices felled, increasing.
    pub fn felled(&self) -> impl Iterator<Item = u16> + '_ {
        self.felled.iter().copied()
    }

    /// Whether `op` can be the cell's next edit.
    pub fn check(&self, op: &CellEdit) -> Result<(), OverlayError> {
        match op {
            CellEdit::Plant { index, .. } => {
                if self.total() == u16::MAX {
                    return Err(OverlayError::Full);
                }
                if *index != self.total() {
                    return Err(OverlayError::PlantIndex { expected: self.total(), got: *index });
                }
                Ok(())
            }
            CellEdit::Fell { index } | CellEdit::Set { index, .. } => {
                if *index >= self.total() {
                    Err(OverlayError::NoInstance(*index))
                } else if self.felled.contains(index) {
                    Err(OverlayError::Felled(*index))
                } else {
                    Ok(())
                }
            }
        }
    }

    /// Apply the cell's next edit.
    pub fn apply(&mut self, e: &StoredEdit) -> Result<(), OverlayError> {
        let expected = self.version + 1;
        if e.version != expected {
            return Err(OverlayError::Version { expected, got: e.version });
        }
        self.check(&e.op)?;
        match &e.op {
            CellEdit::Plant { record, params, .. } => self.planted.push((*record, params.clone())),
            CellEdit::Fell { index } => {
                self.felled.insert(*index);
                self.set.remove(index);
            }
            CellEdit::Set { index, params } => match index.checked_sub(self.base_total) {
                Some(p) => {
                    let slot = &mut self.planted[usize::from(p)].1;
                    *slot = merge_params(slot, params);
                }
                None => {
                    let slot = self.set.entry(*index).or_default();
                    *slot = merge_params(slot, params);
                }
            },
        }
        self.version = expected;
        if self.log.len() == LOG_KEEP {
            self.log.pop_front();
        }
        self.log.push_back(e.clone());
        Ok(())
    }

    /// The cell's records at this version from its world-function `records` and `overrides` (`record` = index,
    /// sorted by `(record, slot)`; `records.len()` must be the base total).
    pub fn apply_to(&self, records: &[InstanceRecord], overrides: &[ParamOverride]) -> Applied {
        debug_assert_eq!(records.len(), usize::from(self.base_total));
        let mut all = Vec::with_capacity(usize::from(self.total()));
        all.extend_from_slice(records);
        all.extend(self.planted.iter().map(|(r, _)| *r));
        let mut out = Vec::with_capacity(overrides.len() + self.planted.len());
        let mut rest = overrides;
        for (&index, set) in &self.set {
            let lo = rest.partition_point(|o| o.record < index);
            let hi = rest.partition_point(|o| o.record <= index);
            out.extend_from_slice(&rest[..lo]);
            let own: Vec<(u16, f32)> = rest[lo..hi].iter().map(|o| (o.slot, o.value)).collect();
            out.extend(merge_params(&own, set).into_iter().map(|(slot, value)| ParamOverride {
                record: index,
                slot,
                value,
            }));
            rest = &rest[hi..];
        }
        out.extend_from_slice(rest);
        for (i, (_, params)) in self.planted.iter().enumerate() {
            let record = self.base_total + i as u16;
            out.extend(params.iter().map(|&(slot, value)| ParamOverride { record, slot, value }));
        }
        Applied { records: all, overrides: out, felled: self.felled.iter().copied().collect() }
    }

    /// The edit that made `version`, if it is among the last [`LOG_KEEP`] edits kept.
    pub fn edit(&self, version: u32) -> Option<&StoredEdit> {
        let first = self.log.front()?.version;
        self.log.get(usize::try_from(version.checked_sub(first)?).ok()?)
    }

    /// The oldest version a delta can start from (the one before the oldest edit kept).
    pub fn oldest_base(&self) -> u32 {
        self.log.front().map_or(self.version, |e| e.version - 1)
    }

    /// How many records the cell had at version `v` (`None`: older than the edits kept, or newer than the cell).
    pub fn total_at(&self, v: u32) -> Option<u16> {
        if v > self.version || v < self.oldest_base() {
            return None;
        }
        let later = self.log.iter().filter(|e| e.version > v && matches!(e.op, CellEdit::Plant { .. })).count();
        Some(self.total() - later as u16)
    }

    /// What changed from version `from` to this one, as a delta for grant 0 (the sender sets its grant). `None`
    /// when it cannot be composed: `from` is not older than this version, older than the edits kept, or the delta
    /// would be larger than a frame or [`netlimits::MAX_DELTA_ENTRIES`] (send the whole cell then).
    pub fn delta(&self, from: u32) -> Option<CellDelta> {
        if from >= self.version || from < self.oldest_base() {
            return None;
        }
        type Add = (u16, InstanceRecord, Vec<(u16, f32)>);
        let mut adds: Vec<Add> = Vec::new();
        let mut removes = BTreeSet::new();
        let mut updates: BTreeMap<u16, Vec<(u16, f32)>> = BTreeMap::new();
        for e in self.log.iter().filter(|e| e.version > from) {
            match &e.op {
                CellEdit::Plant { index, record, params } => adds.push((*index, *record, params.clone())),
                CellEdit::Fell { index } => {
                    removes.insert(*index);
                }
                CellEdit::Set { index, params } => match adds.iter_mut().find(|a| a.0 == *index) {
                    Some(a) => a.2 = merge_params(&a.2, params),
                    None => {
                        let u = updates.entry(*index).or_default();
                        *u = merge_params(u, params);
                    }
                },
            }
        }
        updates.retain(|i, _| !removes.contains(i));
        if adds.len() + removes.len() + updates.len() > netlimits::MAX_DELTA_ENTRIES {
            return None;
        }
        let packed = |p: Vec<(u16, f32)>| p.into_iter().map(|(s, v)| (s, PackedF32(v))).collect();
        let delta = CellDelta {
            cell: self.log.back().expect("a version above 0 has edits").cell,
            grant: 0,
            from_version: from,
            to_version: self.version,
            total: self.total(),
            adds: adds.into_iter().map(|(_, record, params)| Planted { record, params: packed(params) }).collect(),
            removes: removes.into_iter().collect(),
            updates: updates.into_iter().map(|(i, p)| (i, packed(p))).collect(),
        };
        let msg = ServerMsg::Streaming(canopy_protocol::messages::ServerStreaming::Delta(delta));
        if msg.encode().len() > netlimits::MAX_SERVER_FRAME - 16 {
            return None;
        }
        let ServerMsg::Streaming(canopy_protocol::messages::ServerStreaming::Delta(delta)) = msg else {
            unreachable!("built above")
        };
        Some(delta)
    }

    /// Bytes it holds.
    pub fn heap_bytes(&self) -> usize {
        let params = |p: &Vec<(u16, f32)>| p.capacity() * 8;
        std::mem::size_of::<Overlay>()
            + self.planted.iter().map(|(_, p)| 16 + params(p)).sum::<usize>()
            + self.felled.len() * 16
            + self.set.values().map(|p| 32 + params(p)).sum::<usize>()
            + self.log.iter().map(|e| std::mem::size_of::<StoredEdit>() + 8 * self.op_params(e)).sum::<usize>()
    }

    fn op_params(&self, e: &StoredEdit) -> usize {
        match &e.op {
            CellEdit::Plant { params, .. } | CellEdit::Set { params, .. } => params.len(),
            CellEdit::Fell { .. } => 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_protocol::CellCoord;

    const CELL: CellCoord = CellCoord::new(3, -2);

    fn edit(version: u32, op: CellEdit) -> StoredEdit {
        StoredEdit { cell: CELL, version, op }
    }

    fn base() -> (Vec<InstanceRecord>, Vec<ParamOverride>) {
        let records = (0..4).map(|i| InstanceRecord::new(i as u8, i * 100, 7)).collect();
        let overrides = vec![
            ParamOverride { record: 1, slot: 0, value: 5.0 },
            ParamOverride { record: 1, slot: 2, value: 6.0 },
            ParamOverride { record: 3, slot: 1, value: 7.0 },
        ];
        (records, overrides)
    }

    fn plant(index: u16) -> CellEdit {
        CellEdit::Plant { index, record: InstanceRecord::new(9, index % 4096, index % 4096), params: vec![(0, 1.5)] }
    }

    #[test]
    fn edits_the_world_cannot_take_are_skipped_keeping_versions_and_indices() {
        let (records, overrides) = base();
        // Species 0..4 of the base; the world has 2 species now, species 0 with 3 slots, species 1 with none.
        let rules = EditRules::new(vec![vec![0, 1, 2], vec![]]);
        let ok_plant = CellEdit::Plant { index: 5, record: InstanceRecord::new(0, 10, 10), params: vec![(2, 1.0)] };
        let log = [
            edit(1, plant(4)),                                               // species 9: gone
            edit(2, ok_plant),                                               // index 5: the skipped plant kept 4
            edit(3, CellEdit::Set { index: 0, params: vec![(99, 1.0e30)] }), // slot 99 of species 0
            edit(4, CellEdit::Set { index: 5, params: vec![(1, 2.0)] }),
            edit(5, CellEdit::Set { index: 1, params: vec![(0, 1.0)] }), // species 1 declares no slot
        ];
        let species = |i: u16| records.get(usize::from(i)).map(|r| r.species);
        let (o, skipped) = Overlay::from_log_checked(4, species, &rules, &log).unwrap();
        assert_eq!(skipped.iter().map(|s| s.0).collect::<Vec<_>>(), vec![1, 3, 5]);
        assert!(skipped[0].1.contains("species 9") && skipped[1].1.contains("slot 99"), "{skipped:?}");
        assert_eq!((o.version(), o.total()), (5, 6));
        assert!(!o.is_live(4) && o.is_live(5));
        let a = o.apply_to(&records, &overrides);
        assert_eq!(a.felled, vec![4]);
        assert_eq!(a.records[4].species, 0);
        assert!(a.overrides.iter().all(|p| p.value.abs() < 100.0 && p.slot < 3), "{:?}", a.overrides);
        // No delta across a skipped edit: the whole cell goes to a client that holds an older version.
        assert_eq!(o.delta(4), None);
        assert_eq!(o.oldest_base(), 5);
        // Unchecked, the same log folds as stored.
        assert_eq!(Overlay::from_log(4, &log).unwrap().planted(0).unwrap().species, 9);
        // A log that does not fit the cell is still damaged.
        let gap = [edit(2, plant(4))];
        assert!(Overlay::from_log_checked(4, species, &rules, &gap).is_err());
    }

    #[test]
    fn edits_fold_into_records_parameters_and_holes() {
        let (records, overrides) = base();
        let log = [
            edit(1, plant(4)),
            edit(2, CellEdit::Set { index: 1, params: vec![(1, 9.0), (2, 8.0)] }),
            edit(3, CellEdit::Fell { index: 0 }),
            edit(4, CellEdit::Set { index: 4, params: vec![(0, 2.5), (3, 1.0)] }),
            edit(5, plant(5)),
            edit(6, CellEdit::Fell { index: 5 }),
        ];
        let o = Overlay::from_log(4, &log).unwrap();
        assert_eq!((o.version(), o.total()), (6, 6));
        let a = o.apply_to(&records, &overrides);
        assert_eq!(a.records.len(), 6);
        assert_eq!(a.records[4], InstanceRecord::new(9, 4, 4));
        assert_eq!(a.felled, vec![0, 5]);
        let got: Vec<(u16, u16, f32)> = a.overrides.iter().map(|o| (o.record, o.slot, o.value)).collect();
        assert_eq!(
            got,
            vec![(1, 0, 5.0), (1, 1, 9.0), (1, 2, 8.0), (3, 1, 7.0), (4, 0, 2.5), (4, 3, 1.0), (5, 0, 1.5)]
        );
        assert!(!o.is_live(0) && o.is_live(1) && !o.is_live(5) && !o.is_live(6));
    }

    #[test]
    fn bad_edits_are_refused_and_change_nothing() {
        let mut o = Overlay::from_log(4, &[edit(1, CellEdit::Fell { index: 2 })]).unwrap();
        let before = o.clone();
        assert_eq!(o.apply(&edit(3, plant(4))), Err(OverlayError::Version { expected: 2, got: 3 }));
        assert_eq!(o.apply(&edit(2, plant(7))), Err(OverlayError::PlantIndex { expected: 4, got: 7 }));
        assert_eq!(o.apply(&edit(2, CellEdit::Fell { index: 2 })), Err(OverlayError::Felled(2)));
        assert_eq!(
            o.apply(&edit(2, CellEdit::Set { index: 9, params: vec![(0, 1.0)] })),
            Err(OverlayError::NoInstance(9))
        );
        assert_eq!(o, before);
        let mut full = Overlay::new(u16::MAX);
        assert_eq!(full.apply(&edit(1, plant(u16::MAX))), Err(OverlayError::Full));
    }

    #[test]
    fn deltas_compose_what_changed_since_a_version() {
        let log = [
            edit(1, plant(4)),
            edit(2, CellEdit::Set { index: 1, params: vec![(1, 9.0)] }),
            edit(3, plant(5)),
            edit(4, CellEdit::Set { index: 5, params: vec![(2, 3.0)] }),
            edit(5, CellEdit::Fell { index: 1 }),
            edit(6, CellEdit::Set { index: 2, params: vec![(0, 4.0)] }),
        ];
        let o = Overlay::from_log(4, &log).unwrap();
        assert!(o.delta(6).is_none() && o.delta(7).is_none());
        let d = o.delta(1).unwrap();
        assert_eq!((d.from_version, d.to_version, d.total), (1, 6, 6));
        assert_eq!(d.adds.len(), 1, "only the plant after version 1");
        let p: Vec<(u16, f32)> = d.adds[0].params.iter().map(|&(s, v)| (s, v.0)).collect();
        assert_eq!(p, vec![(0, 1.5), (2, 3.0)], "a set on a plant in the range is folded into it");
        assert_eq!(d.removes, vec![1]);
        let u: Vec<u16> = d.updates.iter().map(|u| u.0).collect();
        assert_eq!(u, vec![2], "the set on the felled instance is dropped");
        d.validate().unwrap();
        assert_eq!((o.edit(3), o.edit(0), o.edit(7)), (Some(&log[2]), None, None));
        assert_eq!(o.total_at(0), Some(4));
        assert_eq!(o.total_at(2), Some(5));
        assert_eq!(o.total_at(7), None);
    }

    #[test]
    fn deltas_older_than_the_kept_log_are_refused() {
        let mut o = Overlay::new(0);
        for v in 1..=(LOG_KEEP as u32 + 10) {
            let op = if v == 1 { plant(0) } else { CellEdit::Set { index: 0, params: vec![(0, v as f32)] } };
            o.apply(&edit(v, op)).unwrap();
        }
        assert_eq!(o.oldest_base(), 10);
        assert!(o.delta(9).is_none());
        assert!(o.delta(10).is_some());
        assert_eq!(o.total_at(5), None);
    }
}
