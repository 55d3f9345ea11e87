//! Cells a client expands itself: the world function, a cell's grant and the digests a client reports of its
//! expansions.
//!
//! Cells travel one of two ways, the client's choice in its ready ([`CellMode`]). **Records**: every record of
//! every cell, in batches. **Expand** (seed 001: amplify where the result is drawn): the server sends the world
//! function once ([`WorldFunction`]: the manifest, a few KB, skipped when the client already holds the hash the
//! welcome names) and every species of the table, then for each cell only a [`CellGrant`]: its version and, for an
//! edited cell, its overlay as a delta from the world function's records; the client expands the cell itself. A
//! client may ask for any cell's records instead ([`crate::messages::ClientStreaming::Records`]), and reports digests of some of its
//! expansions ([`CellDigest`]) so the server can catch one that differs.

use serde::{Deserialize, Serialize};

use crate::edit::CellDelta;
use crate::messages::{MessageError, SpeciesHash};
use crate::record::{CellCoord, InstanceId};

/// How a client takes its cells (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum CellMode {
    /// Every record of every cell, in batches.
    Records,
    /// Cell grants (version and overlay) only: the client expands each cell from the world function, which the
    /// server sends unless the client says it holds the one the welcome names.
    Expand {
        /// The client holds the world function whose hash is [`crate::messages::WorldInfo::function`].
        have_function: bool,
    },
}

/// A client's digest of a cell it expanded: [`cell_digest`] of its records at `version`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CellDigest {
    /// The cell.
    pub cell: CellCoord,
    /// The version the client holds it at.
    pub version: u32,
    /// [`cell_digest`] of the records, overrides and felled indices at that version.
    pub digest: u64,
}

/// A 64-bit digest of a cell's records at a version: FNV-1a over each record's species and position steps, each
/// override's `(record, slot, value bits)` and each felled index, in index order. Server and client compute it the
/// same way from the same records.
pub fn cell_digest(
    records: &[crate::record::InstanceRecord],
    overrides: &[crate::record::ParamOverride],
    felled: impl IntoIterator<Item = u16>,
) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for &b in bytes {
            h ^= u64::from(b);
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
    };
    eat(&(records.len() as u32).to_le_bytes());
    for r in records {
        eat(&[r.species]);
        eat(&r.qx().to_le_bytes());
        eat(&r.qz().to_le_bytes());
    }
    eat(&(overrides.len() as u32).to_le_bytes());
    for o in overrides {
        eat(&o.record.to_le_bytes());
        eat(&o.slot.to_le_bytes());
        eat(&o.value.to_bits().to_le_bytes());
    }
    for i in felled {
        eat(&i.to_le_bytes());
    }
    h
}

/// A cell granted to a client in [`CellMode::Expand`]: it expands the cell from the world function and applies
/// `delta` (the cell's edits as a change from version 0), then holds the cell at `version` under `grant`, as if its
/// records had arrived. Later changes come as deltas, as for records.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellGrant {
    /// The cell.
    pub cell: CellCoord,
    /// Which grant of the cell this is (numbered like a batch's).
    pub grant: u32,
    /// The cell's version.
    pub version: u32,
    /// From version 0 to `version`; `None` for an unedited cell (version 0).
    pub delta: Option<CellDelta>,
}

impl CellGrant {
    /// Check the cell, and that the delta (if any) takes version 0 to the grant's.
    pub fn validate(&self) -> Result<(), MessageError> {
        let bad = |what| Err(MessageError::Edit(what));
        if !InstanceId::names(self.cell) {
            return bad("grant of a cell ids cannot name");
        }
        match &self.delta {
            None if self.version != 0 => bad("an edited cell's grant without its delta"),
            None => Ok(()),
            Some(d) if d.cell != self.cell || d.from_version != 0 || d.to_version != self.version => {
                bad("a grant's delta does not take its cell from version 0 to the grant's")
            }
            Some(d) => d.validate(),
        }
    }
}

/// An edited cell beyond the area of interest, sent to a client that expands cells and computes its far view
/// itself (issue 30, item 5): the cell's version and its edits as a delta from version 0 (numbered grant 0: no
/// grant holds it), so that the client corrects the summary nodes holding the cell by them. Sent again whenever
/// the cell's version changes while it lies within the far view's range; a client forgets the cells that leave it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FarCell {
    /// The cell.
    pub cell: CellCoord,
    /// From version 0 to the cell's version.
    pub delta: CellDelta,
}

impl FarCell {
    /// Check the cell and that the delta takes it from version 0 to a later one.
    pub fn validate(&self) -> Result<(), MessageError> {
        let d = &self.delta;
        if !InstanceId::names(self.cell) || d.cell != self.cell || d.from_version != 0 || d.grant != 0 {
            return Err(MessageError::Edit("a far cell's delta does not take its cell from version 0"));
        }
        d.validate()
    }

    /// The cell's version.
    pub fn version(&self) -> u32 {
        self.delta.to_version
    }
}

/// The world function: the manifest text the server's world was built from. Its species statements name the
/// welcome's species table in order (statement `i` is species `i`), and a terrain species is the welcome's terrain
/// graph, so the client builds the same world without reading a file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorldFunction {
    /// The manifest (at most [`crate::netlimits::MAX_FUNCTION_BYTES`]).
    pub manifest: String,
}

impl WorldFunction {
    /// The hash a welcome names it by ([`crate::messages::WorldInfo::function`]): SHA-256 of the manifest.
    pub fn hash(&self) -> SpeciesHash {
        SpeciesHash::of(self.manifest.as_bytes())
    }
}
