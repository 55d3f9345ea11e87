//! One edit as it is stored: the cell, the version it made, and what it did in the cell's own terms (indices and
//! quantised positions, never world coordinates), with its compact encoding.

use canopy_protocol::edit::check_params;
use canopy_protocol::{CellCoord, InstanceRecord};
use serde::{Deserialize, Serialize};

/// Most bytes one stored edit may take (a plant with every parameter is far below it).
pub const MAX_STORED_EDIT: usize = 512;

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
}
