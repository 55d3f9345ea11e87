//! The streaming protocol's messages: one enum per direction, grouped by session phase, with a protocol version,
//! the ALPN token, a check that a message is legal in the current phase, and bounded, validating decoders.
//!
//! A session runs `Start → Hello → Welcomed → Streaming`:
//!
//! ```text
//! client                                   server
//!   Hello { version, client }       ──▶                       (control stream, client-opened, bidirectional)
//!                                   ◀──  Welcome { version, world, species table, AOI rules }
//!   Ready { have, viewpoint, cells } ──▶                      (have: species ids its cache already holds)
//!   Viewpoint …                     ──▶
//!                                   ◀──  Species, Cells, Release (server-opened lanes: ordered streams by priority)
//! ```
//!
//! Cells travel as records, or as grants for a client that expands them itself: see [`crate::grant`].
//!
//! Species are content-addressed: the welcome lists the SHA-256 of every species' encoding, the client answers with
//! the ids it already holds (from its on-disk cache, across sessions), and the server sends each remaining species
//! once, just before the first cell batch that needs it (demand-driven transmission, seed 001 §4).

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::aoi::{AoiParams, AoiParamsError, GridError, Viewpoint, ViewpointError};
use crate::edit::{CellDelta, Edit, EditResult, Resume};
use crate::frame::PREFIX;
pub use crate::grant::{CellDigest, CellGrant, CellMode, FarCell, WorldFunction, cell_digest};
use crate::record::{BatchError, CellBatch, CellCoord, InstanceId};
use crate::summary::{FarView, SummaryBatch, SummaryError};
pub use crate::world::{FractalDesc, TerrainDesc, WorldInfo};
use crate::{limits, netlimits};

/// The protocol version; a client and server speak only their own version.
pub const PROTOCOL_VERSION: u16 = 7;

/// The TLS application protocol (ALPN) token of this protocol version.
pub const ALPN: &[u8] = b"canopy/1";

/// A species' content address: the SHA-256 of its encoded graph ([`crate::SpeciesGraph::encode`]).
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct SpeciesHash(pub [u8; 32]);

impl SpeciesHash {
    /// The content address of an encoded species graph.
    pub fn of(encoded: &[u8]) -> SpeciesHash {
        SpeciesHash(Sha256::digest(encoded).into())
    }

    /// Lowercase hexadecimal, 64 characters.
    pub fn hex(&self) -> String {
        self.0.iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Parse 64 hexadecimal characters.
    pub fn from_hex(s: &str) -> Option<SpeciesHash> {
        if s.len() != 64 || !s.is_ascii() {
            return None;
        }
        let mut out = [0u8; 32];
        for (i, o) in out.iter_mut().enumerate() {
            *o = u8::from_str_radix(&s[2 * i..2 * i + 2], 16).ok()?;
        }
        Some(SpeciesHash(out))
    }
}

impl std::fmt::Debug for SpeciesHash {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "SpeciesHash({})", &self.hex()[..16])
    }
}

/// The fingerprint a client pins a server's certificate by: the SHA-256 of its DER encoding, lowercase hex.
pub fn certificate_fingerprint(der: &[u8]) -> String {
    SpeciesHash::of(der).hex()
}

/// A session phase: which messages are legal next.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Nothing exchanged yet: the client must say hello.
    Start,
    /// The client said hello: the server must welcome it.
    Hello,
    /// The server welcomed the client: the client must say it is ready.
    Welcomed,
    /// Viewpoints flow up, species, cell batches and releases flow down.
    Streaming,
}

/// A message that is not legal in the session's phase.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message} is not legal in phase {phase:?}")]
pub struct PhaseError {
    /// The phase the session was in.
    pub phase: Phase,
    /// The message's name.
    pub message: &'static str,
}

// ---------------------------------------------------------------------------------------------------------------
// Client → server

/// Every message a client sends, grouped by phase.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ClientMsg {
    /// Before streaming.
    Handshake(ClientHandshake),
    /// While streaming.
    Streaming(ClientStreaming),
}

/// The client's handshake messages.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ClientHandshake {
    /// The first message of a session.
    Hello(Hello),
    /// The answer to the welcome: what the client holds, where it looks from.
    Ready(Ready),
    /// Before `ready`, from a client that reconnects: cells it still holds and their versions.
    Resume(Resume),
}

/// The client's streaming messages.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ClientStreaming {
    /// The viewpoint moved: the area of interest follows it.
    Viewpoint(Viewpoint),
    /// Change the world (an editor's session).
    Edit(Edit),
    /// Send this held cell again, whole, at its current version (the client missed a version).
    Refresh(CellCoord),
    /// Send this species' program if it has not been sent (an editor about to plant it, a tool naming species).
    Fetch(u8),
    /// How the client wants the far field (summaries beyond the records); none are sent before the first.
    FarView(FarView),
    /// Send this cell's records from now on, in place of its grant (a client in [`CellMode::Expand`] that cannot
    /// expand it, or whose expansion was found to differ); the cell is granted again. At most as often as
    /// viewpoints.
    Records(CellCoord),
    /// A digest of the client's expansion of a cell ([`CellMode::Expand`]), for the server to check.
    Digest(CellDigest),
}

/// The first message of a session. `version` comes first so that any future version still decodes it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hello {
    /// The client's [`PROTOCOL_VERSION`].
    pub version: u16,
    /// A label for logs (at most [`netlimits::MAX_CLIENT_NAME`] bytes).
    pub client: String,
    /// An editor token (at most [`netlimits::MAX_TOKEN_BYTES`] bytes): a session without one is read-only.
    pub token: Option<Vec<u8>>,
}

/// The client is ready to stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ready {
    /// Ids (into the welcome's species table) of the species the client already holds, strictly increasing.
    pub have: Vec<u8>,
    /// Where the client looks from first.
    pub viewpoint: Viewpoint,
    /// How the client takes its cells ([`CellMode::Expand`] only where the welcome names a world function).
    pub cells: CellMode,
}

// ---------------------------------------------------------------------------------------------------------------
// Server → client

/// Every message a server sends, grouped by phase.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
// The large variant is the welcome, one a session: boxing it would cost every streaming message a branch for none.
#[allow(clippy::large_enum_variant)]
pub enum ServerMsg {
    /// Before streaming (on the control stream).
    Handshake(ServerHandshake),
    /// While streaming (on the lanes).
    Streaming(ServerStreaming),
}

/// The server's handshake messages.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ServerHandshake {
    /// The answer to a hello.
    Welcome(Welcome),
}

/// The server's streaming messages.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ServerStreaming {
    /// A species the client needs and does not hold.
    Species(SpeciesData),
    /// Instance records of a cell in the area of interest.
    Cells(CellBatch),
    /// A cell left the area of interest: forget the grant's records.
    Release(Release),
    /// Explicit geometry (the bandwidth baselines of `canopy bandwidth`: a server in an explicit payload mode sends
    /// meshes instead of species programs). One chunk of one encoded blob.
    Geometry(GeometryChunk),
    /// The answer to an edit (on the control stream).
    EditResult(EditResult),
    /// What changed in a held cell (on its grant's lane).
    Delta(CellDelta),
    /// Far-view summary nodes, and nodes to forget (on the last lane).
    Summaries(SummaryBatch),
    /// A cell granted to a client that expands cells itself: its version and overlay.
    Grant(CellGrant),
    /// The world function, for a client that expands cells itself.
    Function(WorldFunction),
    /// An edited cell beyond the area of interest, for a client that computes its far view itself (on the last
    /// lane).
    FarCell(FarCell),
}

/// The kind of a [`ServerMsg`], without its contents (for accounting: an index into per-kind counters).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ServerMsgKind {
    /// The welcome.
    Welcome = 0,
    /// A species graph.
    Species = 1,
    /// A cell batch of instance records.
    Cells = 2,
    /// A release.
    Release = 3,
    /// Explicit geometry (bandwidth baselines only).
    Geometry = 4,
    /// The answer to an edit.
    EditResult = 5,
    /// A change to a held cell.
    Delta = 6,
    /// Far-view summaries.
    Summaries = 7,
    /// A cell grant (clients that expand cells).
    Grant = 8,
    /// The world function (clients that expand cells).
    Function = 9,
    /// An edited cell beyond the area of interest (clients that expand cells).
    FarCell = 10,
}

impl ServerMsgKind {
    /// Every kind, in index order.
    pub const ALL: [ServerMsgKind; 11] = [
        ServerMsgKind::Welcome,
        ServerMsgKind::Species,
        ServerMsgKind::Cells,
        ServerMsgKind::Release,
        ServerMsgKind::Geometry,
        ServerMsgKind::EditResult,
        ServerMsgKind::Delta,
        ServerMsgKind::Summaries,
        ServerMsgKind::Grant,
        ServerMsgKind::Function,
        ServerMsgKind::FarCell,
    ];

    /// The kind's name, for logs, errors and metrics.
    pub fn name(self) -> &'static str {
        match self {
            ServerMsgKind::Welcome => "welcome",
            ServerMsgKind::Species => "species",
            ServerMsgKind::Cells => "cells",
            ServerMsgKind::Release => "release",
            ServerMsgKind::Geometry => "geometry",
            ServerMsgKind::EditResult => "edit_result",
            ServerMsgKind::Delta => "delta",
            ServerMsgKind::Summaries => "summaries",
            ServerMsgKind::Grant => "grant",
            ServerMsgKind::Function => "function",
            ServerMsgKind::FarCell => "far_cell",
        }
    }

    /// The phase after a message of this kind, or an error if it is not legal in `phase`: the welcome answers a
    /// hello, everything else streams.
    pub fn next_phase(self, phase: Phase) -> Result<Phase, PhaseError> {
        match (self, phase) {
            (ServerMsgKind::Welcome, Phase::Hello) => Ok(Phase::Welcomed),
            (ServerMsgKind::Welcome, _) => Err(PhaseError { phase, message: self.name() }),
            (_, Phase::Streaming) => Ok(Phase::Streaming),
            _ => Err(PhaseError { phase, message: self.name() }),
        }
    }
}

/// One value per [`ServerMsgKind`], indexed by the kind: the per-class byte and message counters of sessions,
/// metrics, clients and the harness.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ByKind<T>(pub [T; ServerMsgKind::ALL.len()]);

impl<T> std::ops::Index<ServerMsgKind> for ByKind<T> {
    type Output = T;
    fn index(&self, kind: ServerMsgKind) -> &T {
        &self.0[kind as usize]
    }
}

impl<T> std::ops::IndexMut<ServerMsgKind> for ByKind<T> {
    fn index_mut(&mut self, kind: ServerMsgKind) -> &mut T {
        &mut self.0[kind as usize]
    }
}

impl<T> ByKind<T> {
    /// Every kind with its value, in index order.
    pub fn iter(&self) -> impl Iterator<Item = (ServerMsgKind, &T)> {
        ServerMsgKind::ALL.into_iter().zip(&self.0)
    }

    /// A value per kind computed from this one's.
    pub fn map<U>(&self, f: impl FnMut(&T) -> U) -> ByKind<U> {
        ByKind(self.0.each_ref().map(f))
    }
}

impl ByKind<u64> {
    /// The sum over every kind.
    pub fn total(&self) -> u64 {
        self.0.iter().sum()
    }
}

/// The server's answer to a hello: the world, its species table and the area-of-interest rules.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Welcome {
    /// The server's [`PROTOCOL_VERSION`].
    pub version: u16,
    /// What the client needs to place instances.
    pub world: WorldInfo,
    /// The species table: index = species id in [`crate::record::InstanceRecord::species`].
    pub species: Vec<SpeciesEntry>,
    /// The area-of-interest rules the server applies.
    pub aoi: AoiParams,
}

/// One entry of the species table.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SpeciesEntry {
    /// The content address of the species' encoding.
    pub hash: SpeciesHash,
    /// Its encoded size in bytes.
    pub size: u32,
}

/// A species' encoded graph.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpeciesData {
    /// The species id (index into the welcome's table).
    pub id: u8,
    /// [`crate::SpeciesGraph::encode`]'s bytes; their SHA-256 is the table entry's hash.
    pub graph: Vec<u8>,
}

/// What an explicit-geometry blob is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum GeometryKind {
    /// One instance's own amplified mesh (`id`: the [`InstanceId`]), quantised and meshopt-compressed.
    InstanceMesh,
    /// One mesh per species (`id`: the species id, below [`netlimits::MAX_SPECIES`]), quantised and
    /// meshopt-compressed, for instancing.
    SpeciesMesh,
    /// Per-instance transforms of a cell batch (`id`: the [`InstanceId`] of the batch's first record, i.e. its cell
    /// and `start`), as glTF `EXT_mesh_gpu_instancing` carries them (translation, rotation, scale),
    /// meshopt-compressed.
    Transforms,
}

/// One chunk of an explicit-geometry blob: `bytes` are `offset..offset + bytes.len()` of a blob of `total` bytes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeometryChunk {
    /// What the blob is.
    pub kind: GeometryKind,
    /// Which instance, species or batch it belongs to (see [`GeometryKind`]): an [`InstanceId`]'s bits or a
    /// species id.
    pub id: u64,
    /// Where the chunk starts in the blob.
    pub offset: u32,
    /// The blob's size (at most [`netlimits::MAX_GEOMETRY_BYTES`]).
    pub total: u32,
    /// The chunk (at most [`netlimits::MAX_GEOMETRY_CHUNK`] bytes).
    pub bytes: Vec<u8>,
}

impl GeometryChunk {
    /// The instance (an instance mesh) or the batch's first instance (transforms) the chunk belongs to; `None` for
    /// a species mesh.
    pub fn instance(&self) -> Option<InstanceId> {
        match self.kind {
            GeometryKind::InstanceMesh | GeometryKind::Transforms => Some(InstanceId(self.id)),
            GeometryKind::SpeciesMesh => None,
        }
    }
}

/// A grant of a cell is over: the client forgets its records.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Release {
    /// The cell.
    pub cell: CellCoord,
    /// The grant being released (an older or newer grant of the same cell is unaffected).
    pub grant: u32,
}

/// How a server or client closes a connection: the QUIC application error code. The reason text says more.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum CloseCode {
    /// The session ended normally.
    Normal = 0,
    /// The peer speaks another protocol version.
    Version = 1,
    /// A message did not decode.
    Malformed = 2,
    /// A frame or message was larger than its limit.
    TooLarge = 3,
    /// A message was not legal in the session's phase.
    OutOfOrder = 4,
    /// A message decoded but its values are not acceptable.
    Invalid = 5,
    /// The peer took too long.
    Timeout = 6,
    /// The server has no room for another client.
    Full = 7,
    /// The server is shutting down.
    Shutdown = 8,
    /// Something went wrong on the closing side.
    Internal = 9,
}

impl CloseCode {
    /// Every code, in code order (`ALL[i] as usize == i`).
    pub const ALL: [CloseCode; 10] = {
        use CloseCode::*;
        [Normal, Version, Malformed, TooLarge, OutOfOrder, Invalid, Timeout, Full, Shutdown, Internal]
    };

    /// The code for a QUIC application error code, if it is one of ours.
    pub fn from_code(code: u64) -> Option<CloseCode> {
        usize::try_from(code).ok().and_then(|i| CloseCode::ALL.get(i).copied())
    }

    /// A short snake_case label, for metrics and logs.
    pub fn label(self) -> &'static str {
        match self {
            CloseCode::Normal => "normal",
            CloseCode::Version => "version",
            CloseCode::Malformed => "malformed",
            CloseCode::TooLarge => "too_large",
            CloseCode::OutOfOrder => "out_of_order",
            CloseCode::Invalid => "invalid",
            CloseCode::Timeout => "timeout",
            CloseCode::Full => "full",
            CloseCode::Shutdown => "shutdown",
            CloseCode::Internal => "internal",
        }
    }
}

// ---------------------------------------------------------------------------------------------------------------
// Decoding and validation

/// Why bytes did not decode to an acceptable message.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MessageError {
    /// The encoding is larger than the direction's frame limit.
    #[error("message of {len} bytes exceeds {max}")]
    TooLarge {
        /// Its size.
        len: usize,
        /// The limit.
        max: usize,
    },
    /// postcard could not decode the bytes.
    #[error("malformed message: {0}")]
    Postcard(#[from] postcard::Error),
    /// Bytes were left over after the message.
    #[error("{0} trailing bytes after the message")]
    Trailing(usize),
    /// A list or string is longer than its limit, or a list is not in canonical order.
    #[error("{what} of {len} (allowed {max}) or not in order")]
    Count {
        /// What was counted.
        what: &'static str,
        /// Its length.
        len: usize,
        /// The limit.
        max: usize,
    },
    /// The world's numbers are not acceptable.
    #[error("world: {0}")]
    World(&'static str),
    /// The grid is not acceptable.
    #[error(transparent)]
    Grid(#[from] GridError),
    /// The area-of-interest rules are not acceptable.
    #[error(transparent)]
    Aoi(#[from] AoiParamsError),
    /// A viewpoint is not acceptable.
    #[error(transparent)]
    Viewpoint(#[from] ViewpointError),
    /// A cell batch is not acceptable.
    #[error(transparent)]
    Batch(#[from] BatchError),
    /// An edit, delta or resume is not acceptable.
    #[error("edit: {0}")]
    Edit(&'static str),
    /// A summary batch or far view is not acceptable.
    #[error(transparent)]
    Summary(#[from] SummaryError),
}

impl MessageError {
    /// The close code this error calls for.
    pub fn close_code(&self) -> CloseCode {
        match self {
            MessageError::TooLarge { .. } => CloseCode::TooLarge,
            MessageError::Postcard(_) | MessageError::Trailing(_) => CloseCode::Malformed,
            _ => CloseCode::Invalid,
        }
    }
}

pub(crate) fn count(what: &'static str, len: usize, max: usize) -> Result<(), MessageError> {
    if len > max { Err(MessageError::Count { what, len, max }) } else { Ok(()) }
}

fn decode_bounded<'a, T: Deserialize<'a>>(bytes: &'a [u8], max: usize) -> Result<T, MessageError> {
    if bytes.len() > max {
        return Err(MessageError::TooLarge { len: bytes.len(), max });
    }
    let (msg, rest): (T, &[u8]) = postcard::take_from_bytes(bytes)?;
    if !rest.is_empty() {
        return Err(MessageError::Trailing(rest.len()));
    }
    Ok(msg)
}

impl ClientMsg {
    /// Encode with postcard.
    pub fn encode(&self) -> Vec<u8> {
        postcard::to_allocvec(self).expect("encoding a message into a Vec cannot fail")
    }

    /// Decode untrusted bytes: bounded by [`netlimits::MAX_CLIENT_FRAME`], checked to the end, validated.
    pub fn decode(bytes: &[u8]) -> Result<ClientMsg, MessageError> {
        let msg: ClientMsg = decode_bounded(bytes, netlimits::MAX_CLIENT_FRAME)?;
        msg.validate()?;
        Ok(msg)
    }

    /// Check every count and value.
    pub fn validate(&self) -> Result<(), MessageError> {
        match self {
            ClientMsg::Handshake(ClientHandshake::Hello(h)) => {
                count("editor token", h.token.as_ref().map_or(0, Vec::len), netlimits::MAX_TOKEN_BYTES)?;
                count("client name", h.client.len(), netlimits::MAX_CLIENT_NAME)
            }
            ClientMsg::Handshake(ClientHandshake::Resume(r)) => r.validate(),
            ClientMsg::Handshake(ClientHandshake::Ready(r)) => {
                count("have-list", r.have.len(), netlimits::MAX_SPECIES)?;
                if r.have.windows(2).any(|w| w[0] >= w[1]) {
                    return Err(MessageError::Count { what: "have-list", len: r.have.len(), max: 0 });
                }
                Ok(r.viewpoint.validate()?)
            }
            ClientMsg::Streaming(ClientStreaming::Viewpoint(v)) => Ok(v.validate()?),
            ClientMsg::Streaming(ClientStreaming::Edit(e)) => e.op.validate(),
            ClientMsg::Streaming(ClientStreaming::Fetch(_)) => Ok(()),
            ClientMsg::Streaming(ClientStreaming::FarView(f)) => Ok(f.validate()?),
            ClientMsg::Streaming(ClientStreaming::Refresh(c) | ClientStreaming::Records(c)) => {
                if InstanceId::names(*c) {
                    Ok(())
                } else {
                    Err(MessageError::Edit("refresh of a cell ids cannot name"))
                }
            }
            ClientMsg::Streaming(ClientStreaming::Digest(d)) => {
                if InstanceId::names(d.cell) {
                    Ok(())
                } else {
                    Err(MessageError::Edit("digest of a cell ids cannot name"))
                }
            }
        }
    }

    /// The message's name, for logs and errors.
    pub fn name(&self) -> &'static str {
        match self {
            ClientMsg::Handshake(ClientHandshake::Hello(_)) => "hello",
            ClientMsg::Handshake(ClientHandshake::Ready(_)) => "ready",
            ClientMsg::Handshake(ClientHandshake::Resume(_)) => "resume",
            ClientMsg::Streaming(ClientStreaming::Viewpoint(_)) => "viewpoint",
            ClientMsg::Streaming(ClientStreaming::Edit(_)) => "edit",
            ClientMsg::Streaming(ClientStreaming::Refresh(_)) => "refresh",
            ClientMsg::Streaming(ClientStreaming::Fetch(_)) => "fetch",
            ClientMsg::Streaming(ClientStreaming::FarView(_)) => "far_view",
            ClientMsg::Streaming(ClientStreaming::Records(_)) => "records",
            ClientMsg::Streaming(ClientStreaming::Digest(_)) => "digest",
        }
    }

    /// The phase after this message, or an error if it is not legal in `phase`.
    pub fn next_phase(&self, phase: Phase) -> Result<Phase, PhaseError> {
        match (self, phase) {
            (ClientMsg::Handshake(ClientHandshake::Hello(_)), Phase::Start) => Ok(Phase::Hello),
            (ClientMsg::Handshake(ClientHandshake::Ready(_)), Phase::Welcomed) => Ok(Phase::Streaming),
            (ClientMsg::Handshake(ClientHandshake::Resume(_)), Phase::Welcomed) => Ok(Phase::Welcomed),
            (ClientMsg::Streaming(_), Phase::Streaming) => Ok(Phase::Streaming),
            _ => Err(PhaseError { phase, message: self.name() }),
        }
    }
}

impl ServerMsg {
    /// Encode with postcard.
    pub fn encode(&self) -> Vec<u8> {
        postcard::to_allocvec(self).expect("encoding a message into a Vec cannot fail")
    }

    /// Encode with postcard as one frame ([`crate::frame`]: the 4-byte length, then the encoding), the same bytes
    /// as `frame(&self.encode())` without encoding into one buffer and copying into another.
    pub fn encode_framed(&self) -> Vec<u8> {
        finish_frame(postcard::to_extend(self, vec![0; PREFIX]).expect("encoding a message into a Vec cannot fail"))
    }

    /// Decode untrusted bytes: bounded by [`netlimits::MAX_SERVER_FRAME`], checked to the end, validated.
    pub fn decode(bytes: &[u8]) -> Result<ServerMsg, MessageError> {
        let msg: ServerMsg = decode_bounded(bytes, netlimits::MAX_SERVER_FRAME)?;
        msg.validate()?;
        Ok(msg)
    }

    /// Check every count and value. (That a species' bytes hash to its table entry and decode to a valid graph
    /// is checked by the client, which holds the table.)
    pub fn validate(&self) -> Result<(), MessageError> {
        match self {
            ServerMsg::Handshake(ServerHandshake::Welcome(w)) => {
                count("species table", w.species.len(), netlimits::MAX_SPECIES)?;
                w.world.validate()?;
                if w.species.iter().any(|s| s.size as usize > limits::MAX_SPECIES_BYTES) {
                    return Err(MessageError::World("species larger than the species limit"));
                }
                Ok(w.aoi.validate()?)
            }
            ServerMsg::Streaming(ServerStreaming::Species(s)) => {
                count("species graph", s.graph.len(), limits::MAX_SPECIES_BYTES)
            }
            ServerMsg::Streaming(ServerStreaming::Cells(b)) => Ok(b.validate()?),
            ServerMsg::Streaming(ServerStreaming::Release(_)) => Ok(()),
            ServerMsg::Streaming(ServerStreaming::EditResult(r)) => match &r.outcome {
                crate::edit::EditOutcome::Denied(why) | crate::edit::EditOutcome::Invalid(why) => {
                    count("edit reason", why.len(), netlimits::MAX_EDIT_REASON)
                }
                _ => Ok(()),
            },
            ServerMsg::Streaming(ServerStreaming::Delta(d)) => d.validate(),
            ServerMsg::Streaming(ServerStreaming::Summaries(b)) => Ok(b.validate()?),
            ServerMsg::Streaming(ServerStreaming::Grant(g)) => g.validate(),
            ServerMsg::Streaming(ServerStreaming::FarCell(f)) => f.validate(),
            ServerMsg::Streaming(ServerStreaming::Function(f)) => {
                count("world function", f.manifest.len(), netlimits::MAX_FUNCTION_BYTES)
            }
            ServerMsg::Streaming(ServerStreaming::Geometry(g)) => {
                count("geometry chunk", g.bytes.len(), netlimits::MAX_GEOMETRY_CHUNK)?;
                count("geometry blob", g.total as usize, netlimits::MAX_GEOMETRY_BYTES)?;
                let end = u64::from(g.offset) + g.bytes.len() as u64;
                if end > u64::from(g.total) {
                    return Err(MessageError::Count {
                        what: "geometry chunk end",
                        len: end as usize,
                        max: g.total as usize,
                    });
                }
                // Every u64 names some (cell, index); a species id must fit the table.
                if g.kind == GeometryKind::SpeciesMesh && g.id >= netlimits::MAX_SPECIES as u64 {
                    return Err(MessageError::Count {
                        what: "geometry species id",
                        len: usize::try_from(g.id).unwrap_or(usize::MAX),
                        max: netlimits::MAX_SPECIES - 1,
                    });
                }
                Ok(())
            }
        }
    }

    /// The message's kind.
    pub fn kind(&self) -> ServerMsgKind {
        match self {
            ServerMsg::Handshake(ServerHandshake::Welcome(_)) => ServerMsgKind::Welcome,
            ServerMsg::Streaming(ServerStreaming::Species(_)) => ServerMsgKind::Species,
            ServerMsg::Streaming(ServerStreaming::Cells(_)) => ServerMsgKind::Cells,
            ServerMsg::Streaming(ServerStreaming::Release(_)) => ServerMsgKind::Release,
            ServerMsg::Streaming(ServerStreaming::Geometry(_)) => ServerMsgKind::Geometry,
            ServerMsg::Streaming(ServerStreaming::EditResult(_)) => ServerMsgKind::EditResult,
            ServerMsg::Streaming(ServerStreaming::Delta(_)) => ServerMsgKind::Delta,
            ServerMsg::Streaming(ServerStreaming::Summaries(_)) => ServerMsgKind::Summaries,
            ServerMsg::Streaming(ServerStreaming::Grant(_)) => ServerMsgKind::Grant,
            ServerMsg::Streaming(ServerStreaming::Function(_)) => ServerMsgKind::Function,
            ServerMsg::Streaming(ServerStreaming::FarCell(_)) => ServerMsgKind::FarCell,
        }
    }

    /// The message's name, for logs, errors and the metrics' message classes.
    pub fn name(&self) -> &'static str {
        self.kind().name()
    }

    /// Instance records the message carries (those of a cell batch).
    pub fn records(&self) -> u32 {
        match self {
            ServerMsg::Streaming(ServerStreaming::Cells(b)) => b.records.len() as u32,
            _ => 0,
        }
    }

    /// The phase after this message, or an error if it is not legal in `phase`.
    pub fn next_phase(&self, phase: Phase) -> Result<Phase, PhaseError> {
        self.kind().next_phase(phase)
    }
}

/// Write the length of the encoding after the [`PREFIX`] bytes reserved at the start of `out` into them.
fn finish_frame(mut out: Vec<u8>) -> Vec<u8> {
    let len = (out.len() - PREFIX) as u32;
    out[..PREFIX].copy_from_slice(&len.to_le_bytes());
    out
}

/// The framed encoding of a welcome up to its area-of-interest rules: the part (world, terrain, species table) that
/// is the same for every client of a world, encoded once and completed per session by [`WelcomeHead::framed`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WelcomeHead(Vec<u8>);

impl WelcomeHead {
    /// The head of the welcome to `world` with this species table, at this [`PROTOCOL_VERSION`].
    pub fn new(world: &WorldInfo, species: &[SpeciesEntry]) -> WelcomeHead {
        // `aoi` is the welcome's last field and postcard encodes fields one after the other, so the welcome's
        // encoding is the head followed by the encoding of its rules.
        let aoi = AoiParams::default();
        let welcome = Welcome { version: PROTOCOL_VERSION, world: world.clone(), species: species.to_vec(), aoi };
        let mut bytes = ServerMsg::Handshake(ServerHandshake::Welcome(welcome)).encode_framed();
        bytes.truncate(bytes.len() - postcard::to_allocvec(&aoi).expect("encoding into a Vec cannot fail").len());
        WelcomeHead(bytes)
    }

    /// The framed welcome with the area-of-interest rules `aoi`: the same bytes as the framed encoding of the
    /// whole [`Welcome`].
    pub fn framed(&self, aoi: &AoiParams) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.0.len() + 32);
        out.extend_from_slice(&self.0);
        finish_frame(postcard::to_extend(aoi, out).expect("encoding into a Vec cannot fail"))
    }
}

/// Shorthand constructors, so callers need not spell out the phase grouping.
impl ClientMsg {
    /// `ClientMsg::Handshake(ClientHandshake::Hello(..))` at this protocol version.
    pub fn hello(client: impl Into<String>) -> ClientMsg {
        ClientMsg::Handshake(ClientHandshake::Hello(Hello {
            version: PROTOCOL_VERSION,
            client: client.into(),
            token: None,
        }))
    }

    /// `ClientMsg::Handshake(ClientHandshake::Ready(..))`, taking records.
    pub fn ready(have: Vec<u8>, viewpoint: Viewpoint) -> ClientMsg {
        ClientMsg::Handshake(ClientHandshake::Ready(Ready { have, viewpoint, cells: CellMode::Records }))
    }

    /// `ClientMsg::Streaming(ClientStreaming::Viewpoint(..))`.
    pub fn viewpoint(viewpoint: Viewpoint) -> ClientMsg {
        ClientMsg::Streaming(ClientStreaming::Viewpoint(viewpoint))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::aoi::Grid;
    use crate::frame::frame;
    use crate::record::POSITION_STEPS;

    fn welcome() -> Welcome {
        let terrain = TerrainDesc {
            graph: Some(vec![1, 2, 3]),
            seed: 9,
            origin: [-1.0, 2.0],
            tile_size: 64.0,
            tiles: [1, 2],
            depth: 3,
            corners: vec![0.5; 6],
            params: vec![(1, 2.5)],
            fractal: None,
        };
        let grid = Grid { origin: [0.0, 0.0], cell_size: 32.0, min: CellCoord::new(-2, -2), max: CellCoord::new(1, 1) };
        let world = WorldInfo {
            name: "wörld".into(),
            seed: 7,
            grid,
            position_steps: POSITION_STEPS,
            instances: 12,
            terrain,
            function: Some(SpeciesHash::of(b"world")),
        };
        let species = vec![SpeciesEntry { hash: SpeciesHash::of(b"a"), size: 300 }; 3];
        Welcome {
            version: PROTOCOL_VERSION,
            world,
            species,
            aoi: AoiParams { max_radius: 123.0, ..AoiParams::default() },
        }
    }

    #[test]
    fn close_codes_are_in_code_order() {
        for (i, c) in CloseCode::ALL.into_iter().enumerate() {
            assert_eq!(c as usize, i);
            assert_eq!(CloseCode::from_code(i as u64), Some(c));
        }
        assert_eq!(CloseCode::from_code(CloseCode::ALL.len() as u64), None);
        assert_eq!(CloseCode::from_code(u64::MAX), None);
    }

    #[test]
    fn kinds_are_in_index_order() {
        for (i, k) in ServerMsgKind::ALL.into_iter().enumerate() {
            assert_eq!(k as usize, i);
        }
    }

    #[test]
    fn encode_framed_is_frame_of_encode() {
        let msgs = [
            ServerMsg::Handshake(ServerHandshake::Welcome(welcome())),
            ServerMsg::Streaming(ServerStreaming::Species(SpeciesData { id: 3, graph: vec![7; 300] })),
            ServerMsg::Streaming(ServerStreaming::Release(Release { cell: CellCoord::new(-1, 4), grant: 77 })),
        ];
        for m in msgs {
            assert_eq!(m.encode_framed(), frame(&m.encode()), "{}", m.name());
        }
    }

    #[test]
    fn welcome_head_completes_to_the_whole_welcome() {
        let w = welcome();
        let head = WelcomeHead::new(&w.world, &w.species);
        for aoi in [w.aoi, AoiParams::default()] {
            let whole = ServerMsg::Handshake(ServerHandshake::Welcome(Welcome { aoi, ..w.clone() }));
            assert_eq!(head.framed(&aoi), frame(&whole.encode()));
        }
    }
}
