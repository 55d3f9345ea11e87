//! A session's outbox: the transmits its loop hands to its writer task, and the bytes the writer reports flushed.
//!
//! It replaces two channels. A channel keeps the blocks it grew to (32 transmits of ~72 bytes each, and more for
//! every burst) for the session's whole life; the outbox's queue starts empty and gives its memory back once a
//! burst is written, so an idle session costs a few words here, whatever it once sent.

use std::collections::VecDeque;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};

use canopy_protocol::sync::Locked;
use canopy_session::Transmit;
use tokio::sync::Notify;

/// Queued transmits a drained queue may keep room for before it gives its memory back.
const KEEP: usize = 8;

/// What passes between a session's loop and its writer task.
#[derive(Debug, Default)]
pub(crate) struct Outbox {
    queue: Mutex<VecDeque<Transmit>>,
    /// Woken when a transmit is queued (a permit is kept if the writer is not waiting yet: no wake-up is lost).
    queued: Notify,
    /// Bytes written since the session last took them.
    flushed: AtomicUsize,
    /// Woken when bytes were flushed.
    flushed_note: Notify,
}

impl Outbox {
    /// Queue `t` for the writer.
    pub(crate) fn push(&self, t: Transmit) {
        self.queue.locked().push_back(t);
        self.queued.notify_one();
    }

    /// The next transmit, waiting until there is one.
    pub(crate) async fn next(&self) -> Transmit {
        loop {
            {
                let mut queue = self.queue.locked();
                if let Some(t) = queue.pop_front() {
                    if queue.is_empty() && queue.capacity() > KEEP {
                        queue.shrink_to(KEEP);
                    }
                    return t;
                }
            }
            self.queued.notified().await;
        }
    }

    /// The writer wrote `bytes` of a transmit.
    pub(crate) fn flushed(&self, bytes: usize) {
        self.flushed.fetch_add(bytes, Relaxed);
        self.flushed_note.notify_one();
    }

    /// Bytes flushed since the last call, waiting until there are some.
    pub(crate) async fn take_flushed(&self) -> usize {
        loop {
            let n = self.flushed.swap(0, Relaxed);
            if n > 0 {
                return n;
            }
            self.flushed_note.notified().await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytes::Bytes;
    use canopy_protocol::messages::ServerMsgKind;
    use canopy_session::StreamId;

    fn transmit(n: u8) -> Transmit {
        let bytes = Bytes::from(vec![n; 3]);
        Transmit { stream: StreamId::Lane(0), bytes, body: Bytes::new(), class: ServerMsgKind::Cells, records: 0 }
    }

    #[tokio::test]
    async fn transmits_come_out_in_order_and_a_drained_burst_gives_its_memory_back() {
        let outbox = Outbox::default();
        for n in 0..200 {
            outbox.push(transmit(n));
        }
        for n in 0..200 {
            assert_eq!(outbox.next().await.bytes[0], n);
            outbox.flushed(3);
        }
        assert!(outbox.queue.locked().capacity() <= KEEP, "the burst's room was given back");
        assert_eq!(outbox.take_flushed().await, 600);
        // Nothing flushed since: the next take waits.
        let waited = tokio::time::timeout(std::time::Duration::from_millis(20), outbox.take_flushed()).await;
        assert!(waited.is_err());
    }

    #[tokio::test]
    async fn the_writer_waits_for_the_next_transmit() {
        let outbox = std::sync::Arc::new(Outbox::default());
        let writer = tokio::spawn({
            let outbox = std::sync::Arc::clone(&outbox);
            async move { outbox.next().await }
        });
        tokio::task::yield_now().await;
        outbox.push(transmit(7));
        assert_eq!(writer.await.unwrap().bytes[0], 7);
    }
}
