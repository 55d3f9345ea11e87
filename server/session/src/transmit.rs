//! What a session hands its transport: a framed message ([`Transmit`]) and the stream it goes on ([`StreamId`]).
//! The session and the far view both make them; neither needs the other for it.

use bytes::Bytes;
use canopy_protocol::messages::ServerMsgKind;

/// Which stream a transmit goes on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum StreamId {
    /// The client-opened bidirectional control stream.
    Control,
    /// A server-opened ordered lane; lower is more important.
    Lane(u8),
}

/// One framed message to write: `bytes`, then `body`.
#[derive(Clone, Debug, PartialEq)]
pub struct Transmit {
    /// Where it goes.
    pub stream: StreamId,
    /// The framed bytes (shared, not copied, where every session sends the same: the species), or for a cell batch
    /// sent procedurally the frame's head of this session (length, tags, cell, grant).
    pub bytes: Bytes,
    /// The rest of the frame after `bytes`: a cell batch's body, encoded once per cell and shared by every
    /// session that sends it ([`crate::batch`]); empty otherwise.
    pub body: Bytes,
    /// What it is.
    pub class: ServerMsgKind,
    /// Instance records it carries.
    pub records: u32,
}

impl Transmit {
    /// The frame's length, bytes.
    pub fn len(&self) -> usize {
        self.bytes.len() + self.body.len()
    }

    /// Whether it carries no bytes (never, for a framed message).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The whole frame in one buffer (a copy when it has a body).
    pub fn frame(&self) -> Bytes {
        if self.body.is_empty() {
            return self.bytes.clone();
        }
        let mut v = Vec::with_capacity(self.len());
        v.extend_from_slice(&self.bytes);
        v.extend_from_slice(&self.body);
        Bytes::from(v)
    }
}
