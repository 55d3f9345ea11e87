//! A cell batch encoded once and shared by every session that sends it.
//!
//! A framed [`ServerMsg`] carrying a [`CellBatch`] is the 4-byte length, the message tags, then the batch's fields
//! in order: `cell`, `grant`, then the rest. Only `grant` (and the length, whose value does not change with it but
//! whose encoding follows it) differs between sessions, so the rest — the body — is encoded once per cell and batch
//! size and shared as [`Bytes`]; a session writes a small head of its own ([`BatchBody::head`]) before it.

use std::sync::OnceLock;

use bytes::Bytes;
use canopy_protocol::frame::PREFIX;
use canopy_protocol::messages::ServerStreaming;
use canopy_protocol::{CellBatch, CellCoord, ServerMsg};

/// One batch's shared part: everything after its `grant`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BatchBody {
    /// The encoded fields after `grant`.
    pub body: Bytes,
    /// Index within the cell of the batch's first record.
    pub start: u16,
    /// One past the index of its last record.
    pub end: u16,
}

/// The postcard encoding of the tags that open a [`ServerStreaming::Cells`] message (the same for every batch).
fn tags() -> &'static [u8] {
    static TAGS: OnceLock<Vec<u8>> = OnceLock::new();
    TAGS.get_or_init(|| {
        let batch = CellBatch::new(CellCoord::new(0, 0), 0, 0, 0, vec![], &[]);
        let inner = postcard::to_allocvec(&batch).expect("encoding into a Vec cannot fail");
        let full = ServerMsg::Streaming(ServerStreaming::Cells(batch)).encode();
        full[..full.len() - inner.len()].to_vec()
    })
}

/// The encoding of a batch's first two fields.
fn cell_grant(cell: CellCoord, grant: u32) -> Vec<u8> {
    postcard::to_allocvec(&(cell, grant)).expect("encoding into a Vec cannot fail")
}

impl BatchBody {
    /// The shared part of `batch` (its `grant` does not matter).
    pub fn of(batch: &CellBatch) -> BatchBody {
        let inner = postcard::to_allocvec(batch).expect("encoding into a Vec cannot fail");
        let skip = cell_grant(batch.cell, batch.grant);
        debug_assert!(inner.starts_with(&skip), "a batch opens with its cell and grant");
        let end = batch.start + batch.records.len() as u16;
        BatchBody { body: Bytes::copy_from_slice(&inner[skip.len()..]), start: batch.start, end }
    }

    /// What one session writes before the body: the frame's length, the message tags, `cell` and `grant`.
    pub fn head(&self, cell: CellCoord, grant: u32) -> Bytes {
        let (tags, cg) = (tags(), cell_grant(cell, grant));
        let len = tags.len() + cg.len() + self.body.len();
        let mut head = Vec::with_capacity(PREFIX + tags.len() + cg.len());
        head.extend_from_slice(&(len as u32).to_le_bytes());
        head.extend_from_slice(tags);
        head.extend_from_slice(&cg);
        Bytes::from(head)
    }

    /// Bytes it holds.
    pub fn heap_bytes(&self) -> usize {
        self.body.len() + std::mem::size_of::<BatchBody>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_protocol::InstanceRecord;
    use canopy_protocol::record::ParamOverride;

    #[test]
    fn head_and_body_are_the_framed_message() {
        let records: Vec<InstanceRecord> =
            (0..40u16).map(|i| InstanceRecord::new((i % 3) as u8, i, 4095 - i)).collect();
        let overrides = [ParamOverride { record: 3, slot: 1, value: 2.5 }];
        for (cell, grant) in
            [(CellCoord::new(-5, 7), 1), (CellCoord::new(300, -2), 70_000), (CellCoord::new(0, 0), u32::MAX)]
        {
            let batch = CellBatch::new(cell, grant, 90, 50, records.clone(), &overrides);
            let body = BatchBody::of(&batch);
            let mut framed = body.head(cell, grant).to_vec();
            framed.extend_from_slice(&body.body);
            assert_eq!(framed, ServerMsg::Streaming(ServerStreaming::Cells(batch.clone())).encode_framed());
            // Another grant, the same body.
            let again = BatchBody::of(&CellBatch { grant: 9, ..batch });
            assert_eq!(again, body);
        }
    }
}
