//! The edit ledger: every edit the bots had acknowledged, checked against what the edit store holds at the end —
//! none lost (each acknowledged edit is stored at the version its answer named, as asked) and none duplicated (no
//! edit stored twice, as a publish retried after a lost acknowledgement could be). Read straight from the store
//! (SQLite or JetStream), not through a server.

use std::collections::BTreeMap;

use canopy_protocol::CellCoord;
use canopy_protocol::aoi::Grid;
use canopy_protocol::edit::EditOp;
use canopy_protocol::record::InstanceRecord;
use canopy_server::edits::{CellEdit, EditStore, EditStoreError, StoredEdit};

use super::edits::Acknowledged;

/// What the check found.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct EditLedger {
    /// Edits acknowledged to the bots.
    pub acknowledged: u64,
    /// Acknowledged edits not stored at the version their answer named, or stored differently.
    pub lost: u64,
    /// Extra copies of acknowledged edits in the store (an edit stored twice counts once here).
    pub duplicated: u64,
    /// Edits stored in the cells the bots edited (unanswered edits the store took count here too).
    pub stored: u64,
    /// Cells read.
    pub cells: usize,
    /// The first problem, for the summary.
    pub first_problem: Option<String>,
}

/// Whether the stored `edit` is what `op` asked for in `cell` (a plant at any index: a copy takes the next one).
fn same_content(edit: &CellEdit, op: &EditOp, cell: CellCoord, grid: &Grid) -> bool {
    content(edit) == asked_content(op, cell, grid)
}

/// Check `acknowledged` against `store` (every cell they touched is read once) on the world's `grid`.
pub fn check_ledger<'a>(
    store: &dyn EditStore,
    grid: &Grid,
    acknowledged: impl IntoIterator<Item = &'a Acknowledged>,
) -> Result<EditLedger, EditStoreError> {
    let mut by_cell: BTreeMap<CellCoord, Vec<&Acknowledged>> = BTreeMap::new();
    for a in acknowledged {
        by_cell.entry(a.id.cell()).or_default().push(a);
    }
    let mut l = EditLedger { cells: by_cell.len(), ..EditLedger::default() };
    for (cell, acks) in by_cell {
        let log: Vec<StoredEdit> = store.load(cell)?;
        l.stored += log.len() as u64;
        // Each content stored (a plant's species, position and parameters; a fell's or set's target): the versions
        // that hold it.
        let mut stored: BTreeMap<Vec<u8>, Vec<u32>> = BTreeMap::new();
        for e in &log {
            stored.entry(content(&e.op)).or_default().push(e.version);
        }
        // Each content acknowledged: the versions its answers named (two bots may ask for the same plant).
        let mut asked: BTreeMap<Vec<u8>, Vec<u32>> = BTreeMap::new();
        for a in &acks {
            l.acknowledged += 1;
            let at = log.iter().find(|e| e.version == a.version);
            let kept = at.is_some_and(|e| e.op.index() == a.id.index() && same_content(&e.op, &a.op, cell, grid));
            if !kept {
                l.lost += 1;
                l.first_problem.get_or_insert_with(|| {
                    format!("lost: {:?} acknowledged as version {} of cell {cell:?}, stored: {at:?}", a.op, a.version)
                });
            }
            asked.entry(asked_content(&a.op, cell, grid)).or_default().push(a.version);
        }
        // Copies beyond the requests that asked for a content are duplicates.
        for (key, versions) in &asked {
            let copies = stored.get(key).map_or(&[][..], Vec::as_slice);
            if copies.len() > versions.len() {
                l.duplicated += (copies.len() - versions.len()) as u64;
                l.first_problem.get_or_insert_with(|| {
                    let op = acks.iter().find(|a| asked_content(&a.op, cell, grid) == *key);
                    format!(
                        "duplicated: {:?} stored {} times in cell {cell:?} (versions {copies:?}), acknowledged as \
                         versions {versions:?}",
                        op.map(|a| &a.op),
                        copies.len()
                    )
                });
            }
        }
    }
    Ok(l)
}

/// What a stored edit did, without the index a plant happened to take (a copy takes the next one).
fn content(op: &CellEdit) -> Vec<u8> {
    match op {
        CellEdit::Plant { record, params, .. } => {
            CellEdit::Plant { index: 0, record: *record, params: params.clone() }.encode()
        }
        op => op.encode(),
    }
}

/// [`content`] of what `op` asked for in `cell`.
fn asked_content(op: &EditOp, cell: CellCoord, grid: &Grid) -> Vec<u8> {
    let edit = match op {
        EditOp::Plant { species, x, z, params } => {
            let [qx, qz] = grid.steps(cell, (*x).into(), (*z).into());
            CellEdit::Plant { index: 0, record: InstanceRecord::new(*species, qx, qz), params: params.clone() }
        }
        EditOp::Fell { id } => CellEdit::Fell { index: id.index() },
        EditOp::Set { id, params } => CellEdit::Set { index: id.index(), params: params.clone() },
    };
    content(&edit)
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_protocol::InstanceId;
    use canopy_protocol::record::quantize;
    use canopy_server::edits::MemoryEditStore;

    #[test]
    fn lost_and_duplicated_edits_are_found() {
        let grid = Grid { origin: [0.0, 0.0], cell_size: 64.0, min: CellCoord::new(0, 0), max: CellCoord::new(3, 3) };
        let cell = CellCoord::new(1, 0);
        let plant = EditOp::Plant { species: 2, x: 70.0, z: 10.0, params: vec![(0, 3.0)] };
        let record = InstanceRecord::new(2, quantize(70.0, 64.0, 64.0), quantize(10.0, 0.0, 64.0));
        let stored = |version, index| StoredEdit {
            cell,
            version,
            op: CellEdit::Plant { index, record, params: vec![(0, 3.0)] },
        };
        let store = MemoryEditStore::default();
        store.append(&[stored(1, 40)]).unwrap();
        let ack =
            |version, index| Acknowledged { op: plant.clone(), id: InstanceId::new(cell, index).unwrap(), version };
        let ok = check_ledger(&store, &grid, &[ack(1, 40)]).unwrap();
        assert_eq!((ok.acknowledged, ok.lost, ok.duplicated, ok.stored), (1, 0, 0, 1));
        // An acknowledged version that is not there, or holds another edit: lost.
        let fell = Acknowledged { op: EditOp::Fell { id: InstanceId::new(cell, 3).unwrap() }, ..ack(2, 3) };
        let lost = check_ledger(&store, &grid, &[ack(1, 40), fell]).unwrap();
        assert_eq!((lost.lost, lost.duplicated), (1, 0));
        assert!(lost.first_problem.unwrap().contains("lost"));
        // The same plant stored again at the next version: duplicated.
        store.append(&[stored(2, 41)]).unwrap();
        let dup = check_ledger(&store, &grid, &[ack(1, 40)]).unwrap();
        assert_eq!((dup.lost, dup.duplicated, dup.stored), (0, 1, 2));
        assert!(dup.first_problem.unwrap().contains("versions [1, 2]"));
        // Two bots that asked for the same plant, each acknowledged: no duplicate.
        let both = check_ledger(&store, &grid, &[ack(1, 40), ack(2, 41)]).unwrap();
        assert_eq!((both.lost, both.duplicated), (0, 0));
        // A third copy is one too many.
        store.append(&[stored(3, 42)]).unwrap();
        let three = check_ledger(&store, &grid, &[ack(1, 40), ack(2, 41)]).unwrap();
        assert_eq!((three.lost, three.duplicated), (0, 1));
    }
}
