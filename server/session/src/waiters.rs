//! Work that sessions wait for without waiting: each key (a cell to expand, a summary node to compute, a cell's
//! edit log to read) is queued once however many sessions ask, with the wakers of those that asked; whoever does
//! the work takes the key from the queue and, when its result is ready, the wakers to wake. The cell cache, its
//! summary nodes and the live store's log loader all keep their work this way.

use std::collections::{HashMap, HashSet, VecDeque};
use std::hash::Hash;
use std::sync::Arc;

use crate::store::CellWaker;

/// Queued keys and who waits for each (see the module docs).
pub struct Waiters<K> {
    waiting: HashMap<K, Vec<Arc<dyn CellWaker>>>,
    queue: VecDeque<K>,
    /// Keys in the queue that nobody waits for any more ([`Waiters::unwait`]): skipped when taken.
    cancelled: HashSet<K>,
    /// Keys taken by [`Waiters::take`] or [`Waiters::take_if`] and not done.
    taken: HashSet<K>,
}

impl<K> Default for Waiters<K> {
    fn default() -> Self {
        Waiters { waiting: HashMap::new(), queue: VecDeque::new(), cancelled: HashSet::new(), taken: HashSet::new() }
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
        // A key cancelled while queued is still in the queue: it is wanted again.
        let revived = self.cancelled.remove(&key);
        let fresh = !self.waiting.contains_key(&key) && !revived;
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
        self.taken.remove(key);
        self.waiting.remove(key).unwrap_or_default()
    }

    /// `waker` no longer waits for `key` (its session moved on or ended): a queued key that nobody waits for any
    /// more leaves the queue, unworked; one being worked on is finished. Whether the key was cancelled.
    pub fn unwait(&mut self, key: &K, waker: &Arc<dyn CellWaker>) -> bool {
        let Some(wakers) = self.waiting.get_mut(key) else { return false };
        wakers.retain(|x| !std::ptr::addr_eq(Arc::as_ptr(x), Arc::as_ptr(waker)));
        if !wakers.is_empty() || self.taken.contains(key) {
            return false;
        }
        self.waiting.remove(key);
        self.cancelled.insert(key.clone());
        true
    }

    /// Take the oldest queued key that is still wanted (it stays waiting until [`Waiters::done`]).
    pub fn take(&mut self) -> Option<K> {
        while let Some(k) = self.queue.pop_front() {
            if !self.cancelled.remove(&k) {
                self.taken.insert(k.clone());
                return Some(k);
            }
        }
        None
    }

    /// Take every queued key that is still wanted and matches `pred` (they stay waiting until
    /// [`Waiters::done`]); cancelled keys met on the way leave the queue.
    pub fn take_if(&mut self, mut pred: impl FnMut(&K) -> bool) -> Vec<K> {
        let mut out = Vec::new();
        let (cancelled, taken) = (&mut self.cancelled, &mut self.taken);
        self.queue.retain(|k| {
            if cancelled.contains(k) {
                if pred(k) {
                    cancelled.remove(k);
                    return false;
                }
                return true;
            }
            if pred(k) {
                taken.insert(k.clone());
                out.push(k.clone());
                return false;
            }
            true
        });
        out
    }

    /// The raw queue, oldest first, for a worker that picks keys its own way (one that never cancels: a key
    /// taken from it stays waiting until [`Waiters::done`]).
    pub fn queue(&mut self) -> &mut VecDeque<K> {
        &mut self.queue
    }

    /// Keys queued, still wanted and not yet taken.
    pub fn queued(&self) -> usize {
        self.queue.len() - self.cancelled.len()
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

    #[test]
    fn a_key_nobody_waits_for_leaves_the_queue_unless_it_is_being_worked_on() {
        let mut w: Waiters<u32> = Waiters::default();
        let a: Arc<dyn CellWaker> = Arc::new(Count(AtomicUsize::new(0)));
        let b: Arc<dyn CellWaker> = Arc::new(Count(AtomicUsize::new(0)));
        for k in [1, 2, 3] {
            w.wait(k, Some(&a));
        }
        w.wait(2, Some(&b));
        assert!(w.unwait(&1, &a), "1 had only a");
        assert!(!w.unwait(&2, &a), "b still waits for 2");
        assert_eq!(w.queued(), 2);
        assert_eq!(w.take(), Some(2), "1 is skipped");
        assert!(!w.unwait(&2, &b), "2 is being worked on: it is finished");
        assert_eq!(w.done(&2).len(), 0);
        // Wanted again while its cancelled copy is still queued: the copy is revived, not doubled.
        assert!(w.unwait(&3, &a));
        assert!(!w.wait(3, Some(&b)));
        assert_eq!(w.queued(), 1);
        assert_eq!(w.take_if(|_| true), vec![3]);
        assert_eq!((w.take(), w.queued()), (None, 0));
        assert_eq!(w.done(&3).len(), 1);
    }
}
