//! Framing of messages on a QUIC stream: a 4-byte little-endian length, then that many bytes of one encoded
//! message. The decoder is sans-IO (push bytes in, take frames out) and rejects a length over its limit as soon as
//! the prefix arrives, before buffering or allocating for it.

/// Bytes of the length prefix.
pub const PREFIX: usize = 4;

/// Why a byte stream is not a sequence of acceptable frames.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// A length prefix announced more than the limit.
    #[error("frame of {len} bytes exceeds the limit of {max}")]
    TooLarge {
        /// The announced length.
        len: usize,
        /// The limit.
        max: usize,
    },
    /// A zero-length frame (no message is empty).
    #[error("empty frame")]
    Empty,
    /// The stream ended inside a frame.
    #[error("stream ended inside a frame ({0} bytes left over)")]
    Truncated(usize),
}

/// Append one frame holding `payload` to `out`.
fn write_frame(out: &mut Vec<u8>, payload: &[u8]) {
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(payload);
}

/// One frame holding `payload`.
pub fn frame(payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(PREFIX + payload.len());
    write_frame(&mut out, payload);
    out
}

/// Splits a byte stream into frames no longer than `max` bytes.
#[derive(Debug)]
pub struct FrameDecoder {
    buf: Vec<u8>,
    pos: usize,
    max: usize,
}

impl FrameDecoder {
    /// A decoder accepting frames of at most `max` payload bytes.
    pub fn new(max: usize) -> FrameDecoder {
        FrameDecoder { buf: Vec::new(), pos: 0, max }
    }

    /// Bytes received but not yet returned as frames.
    fn buffered(&self) -> usize {
        self.buf.len() - self.pos
    }

    /// Append received bytes. Call [`FrameDecoder::next_frame`] until it returns `Ok(None)` after each push, so
    /// the buffer never holds more than one partial frame plus this chunk.
    pub fn push(&mut self, bytes: &[u8]) {
        if self.pos > 0 && self.pos == self.buf.len() {
            self.buf.clear();
            self.pos = 0;
        } else if self.pos > 4096 && self.pos * 2 > self.buf.len() {
            self.buf.drain(..self.pos);
            self.pos = 0;
        }
        self.buf.extend_from_slice(bytes);
    }

    /// The next complete frame's payload, `Ok(None)` if more bytes are needed, or an error for an oversized or
    /// empty frame (after which the stream is unusable).
    pub fn next_frame(&mut self) -> Result<Option<&[u8]>, FrameError> {
        let avail = &self.buf[self.pos..];
        if avail.len() < PREFIX {
            return Ok(None);
        }
        let len = u32::from_le_bytes([avail[0], avail[1], avail[2], avail[3]]) as usize;
        if len > self.max {
            return Err(FrameError::TooLarge { len, max: self.max });
        }
        if len == 0 {
            return Err(FrameError::Empty);
        }
        if avail.len() < PREFIX + len {
            return Ok(None);
        }
        let start = self.pos + PREFIX;
        self.pos = start + len;
        Ok(Some(&self.buf[start..start + len]))
    }

    /// Call at the end of the stream: an error if a partial frame is left over.
    pub fn finish(&self) -> Result<(), FrameError> {
        match self.buffered() {
            0 => Ok(()),
            n => Err(FrameError::Truncated(n)),
        }
    }
}
