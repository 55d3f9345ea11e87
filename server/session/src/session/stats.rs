//! What a session has sent and received, counted: for tests, logs and the server's metrics.

use canopy_protocol::messages::ByKind;
#[cfg(doc)]
use canopy_protocol::messages::ServerMsgKind;
#[cfg(doc)]
use canopy_protocol::netlimits;

/// What a session has sent, for tests, logs and metrics.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SessionStats {
    /// Bytes by [`ServerMsgKind`], framing included.
    pub bytes: ByKind<u64>,
    /// Messages by [`ServerMsgKind`].
    pub messages: ByKind<u64>,
    /// Explicit-geometry blobs not sent because they exceed [`netlimits::MAX_GEOMETRY_BYTES`].
    pub oversize: u64,
    /// Instance records sent.
    pub records: u64,
    /// Viewpoints received.
    pub viewpoints: u64,
    /// Grants opened.
    pub grants: u64,
    /// Edits received.
    pub edits: u64,
    /// Deltas sent.
    pub deltas: u64,
    /// Edits the session denied itself (read-only, over the editor's rate, too many waiting), before the writer.
    pub edits_denied: u64,
    /// Cells granted to the client to expand itself (no records sent).
    pub expand_grants: u64,
    /// Digests of the client's expansions checked against the server's.
    pub digests_checked: u64,
    /// Digests that differed: the cell is sent as records from then on.
    pub digest_mismatches: u64,
    /// Digests of cells not held at that version (released or changed since): not checked.
    pub digests_stale: u64,
}
