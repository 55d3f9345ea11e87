//! One edit as it is stored: the cell, the version it made, and what it did in the cell's own terms (indices and
//! quantised positions, never world coordinates), with its compact encoding.

use canopy_protocol::edit::check_params;
use canopy_protocol::{CellCoord, InstanceRecord};
use serde::{Deserialize, Serialize};

/// Most bytes one stored edit may take (a plant with every parameter is far below it).
pub(crate) const MAX_STORED_EDIT: usize = 512;

/// What one edit did to its cell.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum CellEdit {
    /// An instance planted at `index` (the cell's total before it).
    Plant {
        /// Its index in the cell.
        index: u16,
        /// Species and quantised position in the cell.
        record: InstanceRecord,
        /// `(slot, value)` overrides, slots increasing.
        params: Vec<(u16, f32)>,
    },
    /// The instance at `index` felled.
    Fell {
        /// Its index in the cell.
        index: u16,
    },
    /// New values for some parameters of the instance at `index`.
    Set {
        /// Its index in the cell.
        index: u16,
        /// `(slot, value)`, slots increasing.
        params: Vec<(u16, f32)>,
    },
}

impl CellEdit {
    /// The index of the instance it planted, felled or set.
    pub fn index(&self) -> u16 {
        match self {
            CellEdit::Plant { index, .. } | CellEdit::Fell { index } | CellEdit::Set { index, .. } => *index,
        }
    }
}

/// One edit of the log: cell `cell` went from version `version - 1` to `version` by `op`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredEdit {
    /// The cell.
    pub cell: CellCoord,
    /// The version the edit made (1 for a cell's first edit).
    pub version: u32,
    /// What it did.
    pub op: CellEdit,
}

/// Why stored bytes are not an edit.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LogError {
    /// The bytes are longer than [`MAX_STORED_EDIT`].
    #[error("stored edit of {0} bytes (allowed {MAX_STORED_EDIT})")]
    TooLarge(usize),
    /// postcard could not decode them, or bytes were left over.
    #[error("stored edit does not decode: {0}")]
    Decode(String),
    /// Its parameters are not acceptable.
    #[error("stored edit: {0}")]
    Params(canopy_protocol::MessageError),
}

impl CellEdit {
    /// The compact encoding of the op (postcard).
    pub fn encode(&self) -> Vec<u8> {
        postcard::to_allocvec(self).expect("encoding into a Vec cannot fail")
    }

    /// Decode stored bytes, bounded and checked (parameters finite, slots increasing).
    pub fn decode(bytes: &[u8]) -> Result<CellEdit, LogError> {
        if bytes.len() > MAX_STORED_EDIT {
            return Err(LogError::TooLarge(bytes.len()));
        }
        let (op, rest): (CellEdit, &[u8]) =
            postcard::take_from_bytes(bytes).map_err(|e| LogError::Decode(e.to_string()))?;
        if !rest.is_empty() {
            return Err(LogError::Decode(format!("{} trailing bytes", rest.len())));
        }
        match &op {
            CellEdit::Plant { params, .. } | CellEdit::Set { params, .. } => {
                check_params(params).map_err(LogError::Params)?
            }
            CellEdit::Fell { .. } => {}
        }
        Ok(op)
    }
}

impl StoredEdit {
    /// The compact encoding of the whole edit, cell and version included (postcard): what a store that keeps
    /// whole records (a message log) holds.
    pub fn encode(&self) -> Vec<u8> {
        postcard::to_allocvec(self).expect("encoding into a Vec cannot fail")
    }

    /// Decode stored bytes, bounded and checked like [`CellEdit::decode`].
    pub fn decode(bytes: &[u8]) -> Result<StoredEdit, LogError> {
        if bytes.len() > MAX_STORED_EDIT {
            return Err(LogError::TooLarge(bytes.len()));
        }
        let (e, rest): (StoredEdit, &[u8]) =
            postcard::take_from_bytes(bytes).map_err(|e| LogError::Decode(e.to_string()))?;
        if !rest.is_empty() {
            return Err(LogError::Decode(format!("{} trailing bytes", rest.len())));
        }
        // The op's own checks.
        CellEdit::decode(&e.op.encode())?;
        Ok(e)
    }
}

/// Most edits one stored run holds ([`encode_run`]).
pub const MAX_RUN: usize = 256;

/// Most bytes one stored run may take.
pub(crate) const MAX_RUN_BYTES: usize = MAX_RUN * MAX_STORED_EDIT;

/// A run of consecutive versions of one cell as a message log stores it: one message, one compare-and-set, for
/// every edit a group made to the cell ([`encode_run`], [`decode_run`]).
#[derive(Serialize, Deserialize)]
struct Run {
    cell: CellCoord,
    first: u32,
    ops: Vec<CellEdit>,
}

/// Encode `edits`, consecutive versions of one cell (1 to [`MAX_RUN`] of them), as one run.
///
/// # Panics
/// If the edits are not such a run: a writer's bug.
pub fn encode_run(edits: &[StoredEdit]) -> Vec<u8> {
    let first = edits.first().expect("a run holds an edit");
    assert!(edits.len() <= MAX_RUN, "a run of {} edits", edits.len());
    assert!(
        edits.iter().zip(first.version..).all(|(e, v)| e.cell == first.cell && e.version == v),
        "a run is consecutive versions of one cell"
    );
    let run = Run { cell: first.cell, first: first.version, ops: edits.iter().map(|e| e.op.clone()).collect() };
    postcard::to_allocvec(&run).expect("encoding into a Vec cannot fail")
}

/// Decode a stored run into its edits, bounded and checked like [`StoredEdit::decode`] (at most [`MAX_RUN`] edits,
/// versions from 1 that do not overflow).
pub fn decode_run(bytes: &[u8]) -> Result<Vec<StoredEdit>, LogError> {
    if bytes.len() > MAX_RUN_BYTES {
        return Err(LogError::TooLarge(bytes.len()));
    }
    let (run, rest): (Run, &[u8]) = postcard::take_from_bytes(bytes).map_err(|e| LogError::Decode(e.to_string()))?;
    if !rest.is_empty() {
        return Err(LogError::Decode(format!("{} trailing bytes", rest.len())));
    }
    if run.ops.is_empty() || run.ops.len() > MAX_RUN {
        return Err(LogError::Decode(format!("a run of {} edits (1 to {MAX_RUN})", run.ops.len())));
    }
    if run.first == 0 || run.first.checked_add(run.ops.len() as u32).is_none() {
        return Err(LogError::Decode(format!("a run from version {}", run.first)));
    }
    run.ops
        .into_iter()
        .zip(run.first..)
        .map(|(op, version)| {
            CellEdit::decode(&op.encode())?;
            Ok(StoredEdit { cell: run.cell, version, op })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ops_round_trip_and_bad_bytes_are_refused() {
        let ops = [
            CellEdit::Plant {
                index: 70,
                record: InstanceRecord::new(3, 100, 4095),
                params: vec![(0, 12.5), (2, -1.0)],
            },
            CellEdit::Fell { index: 65_534 },
            CellEdit::Set { index: 0, params: vec![(1, 3.0)] },
        ];
        for op in ops {
            let bytes = op.encode();
            assert!(bytes.len() < 32, "{op:?} takes {} bytes", bytes.len());
            assert_eq!(CellEdit::decode(&bytes), Ok(op));
        }
        assert!(matches!(CellEdit::decode(&[9, 9]), Err(LogError::Decode(_))));
        let mut trailing = CellEdit::Fell { index: 1 }.encode();
        trailing.push(0);
        assert!(matches!(CellEdit::decode(&trailing), Err(LogError::Decode(_))));
        let nan = CellEdit::Set { index: 0, params: vec![(1, f32::NAN)] }.encode();
        assert!(matches!(CellEdit::decode(&nan), Err(LogError::Params(_))));
        assert!(matches!(CellEdit::decode(&[0; 600]), Err(LogError::TooLarge(600))));
    }

    #[test]
    fn runs_round_trip_and_bad_runs_are_refused() {
        let cell = CellCoord::new(-3, 7);
        let ops = [
            CellEdit::Plant { index: 9, record: InstanceRecord::new(1, 2, 3), params: vec![(0, 1.5)] },
            CellEdit::Fell { index: 2 },
            CellEdit::Set { index: 9, params: vec![(1, -2.0)] },
        ];
        let edits: Vec<StoredEdit> =
            ops.iter().zip(41..).map(|(op, version)| StoredEdit { cell, version, op: op.clone() }).collect();
        let bytes = encode_run(&edits);
        assert_eq!(decode_run(&bytes), Ok(edits.clone()));
        assert!(bytes.len() < 40, "a run of three edits takes {} bytes", bytes.len());
        let full: Vec<StoredEdit> =
            (1..=MAX_RUN as u32).map(|v| StoredEdit { cell, version: v, op: CellEdit::Fell { index: 1 } }).collect();
        assert_eq!(decode_run(&encode_run(&full)).map(|r| r.len()), Ok(MAX_RUN));

        let run = |first: u32, ops: Vec<CellEdit>| postcard::to_allocvec(&Run { cell, first, ops }).unwrap();
        assert!(matches!(decode_run(&run(1, vec![])), Err(LogError::Decode(_))), "an empty run");
        let long = vec![CellEdit::Fell { index: 0 }; MAX_RUN + 1];
        assert!(matches!(decode_run(&run(1, long)), Err(LogError::Decode(_))), "a run too long");
        assert!(matches!(decode_run(&run(0, ops.to_vec())), Err(LogError::Decode(_))), "version 0");
        assert!(matches!(decode_run(&run(u32::MAX - 1, ops.to_vec())), Err(LogError::Decode(_))), "overflow");
        let nan = vec![CellEdit::Set { index: 0, params: vec![(1, f32::NAN)] }];
        assert!(matches!(decode_run(&run(1, nan)), Err(LogError::Params(_))));
        let mut trailing = bytes.clone();
        trailing.push(0);
        assert!(matches!(decode_run(&trailing), Err(LogError::Decode(_))));
        assert!(matches!(decode_run(&vec![0; MAX_RUN_BYTES + 1]), Err(LogError::TooLarge(_))));
        // A huge declared length is refused without allocating for it.
        let mut lying = postcard::to_allocvec(&(cell, 1u32)).unwrap();
        lying.extend_from_slice(&[0xff, 0xff, 0xff, 0xff, 0x0f]);
        assert!(decode_run(&lying).is_err());
    }
}
