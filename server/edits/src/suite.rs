//! The edit-store contract as one test every store runs ([`check`]): the in-memory store, the embedded SQLite store
//! and the JetStream store of the edges pass the same suite. It panics at the first rule a store breaks, naming it.
//!
//! The rules ([`EditStore`]'s docs): an append returns once its edits are durable; a `(cell, version)` already
//! stored — or named twice in one group — is refused as [`EditStoreError::Conflict`] naming it; a transactional
//! store keeps nothing of a failed group, a store without multi-key transactions at most a prefix of each cell's
//! edits in it (never an edit it was not given, never one over a version already stored); `load` gives a cell's edits in version order exactly as appended;
//! `cells` every edited cell with its latest version, in cell order; `count` every edit stored.

use crate::{CellEdit, EditStore, EditStoreError, MemoryEditStore, StoredEdit};
use canopy_protocol::xorshift::XorShift64;
use canopy_protocol::{CellCoord, InstanceRecord};

/// Cells the suite edits: the corners of the coordinate range among them.
const CELLS: [CellCoord; 6] = [
    CellCoord::new(0, 0),
    CellCoord::new(-1, 1),
    CellCoord::new(i32::MIN, i32::MAX),
    CellCoord::new(i32::MAX, i32::MIN),
    CellCoord::new(123_456, -987_654),
    CellCoord::new(7, -3),
];

fn plant(cell: CellCoord, version: u32, index: u16, species: u8, params: Vec<(u16, f32)>) -> StoredEdit {
    let record = InstanceRecord::new(species, index.wrapping_mul(37) % 4096, 4095 - index % 4096);
    StoredEdit { cell, version, op: CellEdit::Plant { index, record, params } }
}

fn conflict(r: Result<(), EditStoreError>, cell: CellCoord, version: u32, rule: &str) {
    match r {
        Err(EditStoreError::Conflict { cell: c, version: v }) => {
            assert_eq!((c, v), (cell, version), "{rule}: the conflict names the wrong edit")
        }
        other => panic!("{rule}: expected a conflict on {cell:?} version {version}, got {other:?}"),
    }
}

/// Run the suite on `store`, which must hold no edits yet.
pub fn check(store: &dyn EditStore) {
    let [a, b, c, d, ..] = CELLS;
    assert_eq!(store.count().unwrap(), 0, "the suite needs an empty store");
    assert_eq!(store.load(a).unwrap(), vec![], "a cell never edited has no edits");
    assert_eq!(store.cells().unwrap(), vec![], "an empty store has no edited cells");

    // A group: consecutive versions of one cell, and another cell, stored and read back exactly.
    let first = vec![
        plant(a, 1, 40, 3, vec![(0, 12.5), (3, -0.25)]),
        StoredEdit { cell: a, version: 2, op: CellEdit::Fell { index: 7 } },
        StoredEdit { cell: a, version: 3, op: CellEdit::Set { index: 40, params: vec![(1, 1e30), (2, -1e-30)] } },
        plant(b, 1, 0, 255, vec![]),
    ];
    store.append(&first).unwrap();
    assert_eq!(store.load(a).unwrap(), first[..3], "a cell's edits come back in version order, as appended");
    assert_eq!(store.load(b).unwrap(), first[3..], "another cell's edit comes back");
    assert_eq!(store.count().unwrap(), 4, "count is every edit stored");
    let mut expected_cells = vec![(a, 3), (b, 1)];
    expected_cells.sort_unstable();
    assert_eq!(store.cells().unwrap(), expected_cells, "cells: every edited cell, its latest version, cell order");

    // A version already stored is refused, and the cell is as it was.
    conflict(store.append(&[plant(a, 3, 41, 0, vec![])]), a, 3, "a version stored already");
    conflict(store.append(&[plant(a, 1, 41, 0, vec![])]), a, 1, "an early version stored already");
    assert_eq!(store.load(a).unwrap(), first[..3], "a refused edit leaves its cell as it was");
    // A version named twice in one group is refused; of that cell at most the first is kept (a prefix).
    let twice = [plant(c, 1, 1, 0, vec![]), plant(c, 1, 2, 0, vec![])];
    conflict(store.append(&twice), c, 1, "a version named twice");
    let kept = store.load(c).unwrap();
    assert!(twice[..1].starts_with(&kept), "a version named twice: at most the first is kept, not {kept:?}");

    // A group that conflicts in one cell: that cell is untouched; another cell of the group keeps at most what it
    // was given (a store without multi-key transactions may keep it).
    let mixed = vec![plant(d, 1, 5, 1, vec![]), plant(d, 2, 6, 1, vec![]), plant(b, 1, 9, 9, vec![])];
    conflict(store.append(&mixed), b, 1, "a group conflicting in one of its cells");
    assert_eq!(store.load(b).unwrap(), first[3..], "the conflicting cell is untouched");
    let kept = store.load(d).unwrap();
    assert!(mixed[..2].starts_with(&kept), "a failed group keeps at most a prefix of a cell's edits: {kept:?}");
    let d_versions = kept.len() as u32;

    // The next versions go on from what is stored, in groups, as a writer would append them; compared with the
    // in-memory reference all along.
    let reference = MemoryEditStore::new();
    for cell in CELLS {
        let have = store.load(cell).unwrap();
        if !have.is_empty() {
            reference.append(&have).unwrap();
        }
    }
    let mut rng = XorShift64::new(0x5eed_0057_0e55);
    let mut next: Vec<u32> = CELLS.iter().map(|&c| reference.load(c).unwrap().len() as u32 + 1).collect();
    assert_eq!(next[3], d_versions + 1);
    for round in 0..40 {
        let mut group = Vec::new();
        for _ in 0..1 + rng.next() % 3 {
            let i = (rng.next() % CELLS.len() as u64) as usize;
            for _ in 0..1 + rng.next() % 3 {
                let v = next[i];
                next[i] += 1;
                let op = match rng.next() % 3 {
                    0 => plant(CELLS[i], v, (v % 65_000) as u16, (rng.next() % 256) as u8, vec![(0, v as f32)]),
                    1 => StoredEdit { cell: CELLS[i], version: v, op: CellEdit::Fell { index: (v % 100) as u16 } },
                    _ => StoredEdit {
                        cell: CELLS[i],
                        version: v,
                        op: CellEdit::Set { index: (v % 100) as u16, params: vec![(4, -(v as f32))] },
                    },
                };
                group.push(op);
            }
        }
        store.append(&group).unwrap_or_else(|e| panic!("round {round}: {e}"));
        reference.append(&group).unwrap();
    }
    for cell in CELLS {
        assert_eq!(store.load(cell).unwrap(), reference.load(cell).unwrap(), "cell {cell:?} after the rounds");
    }
    assert_eq!(store.cells().unwrap(), reference.cells().unwrap(), "cells after the rounds");
    assert_eq!(store.count().unwrap(), reference.count().unwrap(), "count after the rounds");
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_memory_store_passes() {
        super::check(&super::MemoryEditStore::new());
    }
}
