//! Work that sessions wait for without waiting: each key (a cell to expand, a summary node to compute, a cell's
//! edit log to read) is queued once however many sessions ask, with the wakers of those that asked; whoever does
//! the work takes the key from the queue and, when its result is ready, the wakers to wake. The cell cache, its
//! summary nodes and the live store's log loader all keep their work this way.

use std::collections::{HashMap, VecDeque};
use std::hash::Hash;
use std::sync::Arc;

use crate::store::CellWaker;

/// Queued keys and who waits for each (see the module docs).
pub struct Waiters<K> {
    waiting: HashMap<K, Vec<Arc<dyn CellWaker>>>,
    queue: VecDeque<K>,
}

impl<K> Default for Waiters<K> {
    fn default() -> Self {
        Waiters { waiting: HashMap::new(), queue: VecDeque::new() }
    }
}

impl<K: Hash + Eq + Clone> Waiters<K> {
    /// Whether `key` is queued or being worked on.
    pub fn is_waiting(&self, key: &K) -> bool {
        self.waiting.contains_key(key)
    }

    /// Have `waker` woken when `key` is ready (once, however often it asks), queueing `key` unless it is queued or
    /// being worked on already; whether it was queued now.
    pub fn wait(&mut self, key: K, waker: Option<&Arc<dyn CellWaker>>) -> bool {
        let fresh = !self.waiting.contains_key(&key);
        let wakers = self.waiting.entry(key.clone()).or_default();
        if let Some(w) = waker
            && !wakers.iter().any(|x| std::ptr::addr_eq(Arc::as_ptr(x), Arc::as_ptr(w)))
        {
            wakers.push(Arc::clone(w));
        }
        if fresh {
            self.queue.push_back(key);
        }
        fresh
    }

    /// `key` is ready (or failed): the wakers to wake; asked again, it is queued again.
    pub fn done(&mut self, key: &K) -> Vec<Arc<dyn CellWaker>> {
        self.waiting.remove(key).unwrap_or_default()
    }

    /// The queue, oldest first (the worker takes from it; a key taken stays waiting until [`Waiters::done`]).
    pub fn queue(&mut self) -> &mut VecDeque<K> {
        &mut self.queue
    }

    /// Keys queued and not yet taken.
    pub fn queued(&self) -> usize {
        self.queue.len()
    }

    /// Keys queued or being worked on.
    pub fn waiting(&self) -> usize {
        self.waiting.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    struct Count(AtomicUsize);

    impl CellWaker for Count {
        fn wake(&self) {
            self.0.fetch_add(1, Ordering::Relaxed);
        }
    }

    #[test]
    fn a_key_is_queued_once_and_each_waker_woken_once() {
        let mut w: Waiters<u32> = Waiters::default();
        let a: Arc<dyn CellWaker> = Arc::new(Count(AtomicUsize::new(0)));
        let b: Arc<dyn CellWaker> = Arc::new(Count(AtomicUsize::new(0)));
        assert!(w.wait(7, Some(&a)));
        assert!(!w.wait(7, Some(&a)));
        assert!(!w.wait(7, Some(&b)));
        assert!(!w.wait(7, None));
        assert_eq!((w.queued(), w.waiting()), (1, 1));
        assert_eq!(w.queue().pop_front(), Some(7));
        assert!(w.is_waiting(&7), "taken, not done");
        assert!(!w.wait(7, None), "being worked on: not queued again");
        assert_eq!(w.done(&7).len(), 2);
        assert!(!w.is_waiting(&7) && w.wait(7, None), "asked again after it was done: queued again");
    }
}
