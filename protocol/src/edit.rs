//! Live world edits on the wire: what an editor asks for ([`Edit`]: plant, fell, set parameters), what the server
//! answers ([`EditResult`]), and how every client holding a cell learns of it ([`CellDelta`]).
//!
//! A cell's records are the world function's records followed by the instances planted in it, each at the next
//! index of the cell (an [`InstanceId`] is still `(cell, index)`, and a planted instance's seed derives from it like
//! any other's). Felling an instance leaves a hole: its index is never reused. Every edit raises the cell's
//! **version** by one; version 0 is the world function alone. A client holds each cell at a version; a delta takes
//! it from one version to a later one, and a batch says the version of the records it carries.
//!
//! A client that reconnects names the cells it still holds and their versions ([`ResumeCell`], in the handshake)
//! and receives deltas instead of whole cells.

use serde::{Deserialize, Serialize};

use crate::messages::MessageError;
use crate::netlimits;
use crate::record::{CellCoord, InstanceId, InstanceRecord, PackedF32};

/// What an editor asks the world to do.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum EditOp {
    /// Plant an instance of `species` at world `(x, z)` with these parameters (`(slot, value)`, slots increasing).
    Plant {
        /// Species id (index into the welcome's table).
        species: u8,
        /// World x, metres.
        x: f32,
        /// World z, metres.
        z: f32,
        /// Parameter values that differ from the species defaults.
        params: Vec<(u16, f32)>,
    },
    /// Fell (remove) an instance.
    Fell {
        /// The instance.
        id: InstanceId,
    },
    /// Give an instance new values for some parameters (the slots named; the others keep theirs).
    Set {
        /// The instance.
        id: InstanceId,
        /// `(slot, value)`, slots increasing.
        params: Vec<(u16, f32)>,
    },
}

impl EditOp {
    /// The op's name, for logs and errors.
    pub fn name(&self) -> &'static str {
        match self {
            EditOp::Plant { .. } => "plant",
            EditOp::Fell { .. } => "fell",
            EditOp::Set { .. } => "set",
        }
    }

    /// Check counts and numbers (finite coordinates and values, slots increasing, at most
    /// [`netlimits::MAX_EDIT_PARAMS`]).
    pub fn validate(&self) -> Result<(), MessageError> {
        let params = match self {
            EditOp::Plant { x, z, params, .. } => {
                if !(x.is_finite() && z.is_finite()) {
                    return Err(MessageError::Edit("plant position is not finite"));
                }
                params
            }
            EditOp::Fell { .. } => return Ok(()),
            EditOp::Set { params, .. } => {
                if params.is_empty() {
                    return Err(MessageError::Edit("set names no parameter"));
                }
                params
            }
        };
        check_params(params)
    }
}

/// Check a `(slot, value)` list: at most [`netlimits::MAX_EDIT_PARAMS`], slots strictly increasing, values finite.
pub fn check_params(params: &[(u16, f32)]) -> Result<(), MessageError> {
    if params.len() > netlimits::MAX_EDIT_PARAMS {
        return Err(MessageError::Count {
            what: "edit parameters",
            len: params.len(),
            max: netlimits::MAX_EDIT_PARAMS,
        });
    }
    if params.windows(2).any(|w| w[0].0 >= w[1].0) {
        return Err(MessageError::Edit("parameter slots are not increasing"));
    }
    if !params.iter().all(|(_, v)| v.is_finite()) {
        return Err(MessageError::Edit("parameter value is not finite"));
    }
    Ok(())
}

/// An edit request from a client: `request` is the client's number for it, echoed in the [`EditResult`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Edit {
    /// The client's request number.
    pub request: u32,
    /// What to do.
    pub op: EditOp,
}

/// How an edit ended.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum EditOutcome {
    /// Applied and durable: the instance it made or changed, and the cell's new version.
    Ok {
        /// The instance planted, felled or set.
        id: InstanceId,
        /// The cell's version after the edit.
        version: u32,
    },
    /// The session may not make this edit (read-only, outside the editor's region, over its rate).
    Denied(String),
    /// The edit names something that does not exist or values out of range.
    Invalid(String),
    /// The cell changed under the edit and it could not be applied; try again.
    Conflict,
}

impl EditOutcome {
    /// A short label, for logs and metrics.
    pub fn label(&self) -> &'static str {
        match self {
            EditOutcome::Ok { .. } => "ok",
            EditOutcome::Denied(_) => "denied",
            EditOutcome::Invalid(_) => "invalid",
            EditOutcome::Conflict => "conflict",
        }
    }
}

/// The server's answer to an [`Edit`] (on the control stream).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct EditResult {
    /// The client's request number.
    pub request: u32,
    /// How it ended.
    pub outcome: EditOutcome,
}

/// An instance planted by a delta: its record and parameters (`(slot, value)`, slots increasing).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Planted {
    /// Species and position in the cell.
    pub record: InstanceRecord,
    /// Parameter values that differ from the species defaults.
    pub params: Vec<(u16, PackedF32)>,
}

/// What changed in a cell from `from_version` to `to_version`, for a client that holds the cell's `grant` at
/// `from_version`: instances planted (at indices `total - adds.len()..total`), indices felled (perhaps some just
/// planted), and parameters set on instances that were there before. Sent on the grant's lane, after its batches.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellDelta {
    /// The cell.
    pub cell: CellCoord,
    /// The grant it applies to.
    pub grant: u32,
    /// The version the client must hold.
    pub from_version: u32,
    /// The version it holds afterwards.
    pub to_version: u32,
    /// How many records the cell has afterwards (felled ones included: their indices stay taken).
    pub total: u16,
    /// Instances planted, in index order.
    pub adds: Vec<Planted>,
    /// Indices felled, increasing.
    pub removes: Vec<u16>,
    /// `(index, (slot, value)…)`: parameters set, indices increasing.
    pub updates: Vec<(u16, Vec<(u16, PackedF32)>)>,
}

impl CellDelta {
    /// Check counts, versions, ranges and order.
    pub fn validate(&self) -> Result<(), MessageError> {
        let bad = |what| Err(MessageError::Edit(what));
        if self.to_version <= self.from_version {
            return bad("delta does not raise the version");
        }
        if !InstanceId::names(self.cell) {
            return bad("delta cell outside the cells ids can name");
        }
        let entries = self.adds.len() + self.removes.len() + self.updates.len();
        if entries > netlimits::MAX_DELTA_ENTRIES {
            return Err(MessageError::Count { what: "delta entries", len: entries, max: netlimits::MAX_DELTA_ENTRIES });
        }
        if self.adds.len() > usize::from(self.total) {
            return bad("delta plants more than the cell's total");
        }
        if self.removes.windows(2).any(|w| w[0] >= w[1]) || self.removes.last().is_some_and(|&i| i >= self.total) {
            return bad("delta removes out of order or range");
        }
        if self.updates.windows(2).any(|w| w[0].0 >= w[1].0) || self.updates.last().is_some_and(|u| u.0 >= self.total) {
            return bad("delta updates out of order or range");
        }
        let packed = |p: &[(u16, PackedF32)]| p.iter().map(|&(s, v)| (s, v.0)).collect::<Vec<_>>();
        for p in self.adds.iter().map(|a| &a.params).chain(self.updates.iter().map(|u| &u.1)) {
            check_params(&packed(p))?;
        }
        if self.updates.iter().any(|u| u.1.is_empty()) {
            return bad("delta update names no parameter");
        }
        Ok(())
    }
}

/// A cell a reconnecting client still holds, at a version.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ResumeCell {
    /// The cell.
    pub cell: CellCoord,
    /// The version of the records the client holds.
    pub version: u32,
}

/// Cells a reconnecting client still holds, sent after the welcome and before `ready` (in as many messages as it
/// needs, cells increasing across them). The server numbers their grants `1, 2, …` in this order and sends only
/// what changed since each version; cells it will not keep are released as usual.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Resume {
    /// The cells, increasing (at most [`netlimits::MAX_RESUME_PER_MESSAGE`] a message).
    pub cells: Vec<ResumeCell>,
}

impl Resume {
    /// Check the count and the order.
    pub fn validate(&self) -> Result<(), MessageError> {
        let n = self.cells.len();
        if n > netlimits::MAX_RESUME_PER_MESSAGE || self.cells.windows(2).any(|w| w[0].cell >= w[1].cell) {
            return Err(MessageError::Count { what: "resumed cells", len: n, max: netlimits::MAX_RESUME_PER_MESSAGE });
        }
        if self.cells.iter().any(|c| !InstanceId::names(c.cell)) {
            return Err(MessageError::Edit("resumed cell outside the cells ids can name"));
        }
        Ok(())
    }
}
