//! A first-fit range allocator with coalescing free lists: the bookkeeping of the fixed-size GPU buffers that hold
//! every cached tree's primitives, vertices and indices. Their capacity is the geometry cache's memory bound.

use std::collections::BTreeMap;
use std::ops::Range;

/// Ranges of `0..capacity` handed out and returned (see the module docs).
#[derive(Clone, Debug)]
pub(crate) struct Arena {
    capacity: u64,
    /// Free ranges by start → length; never adjacent (they are merged).
    free: BTreeMap<u64, u64>,
    used: u64,
}

impl Arena {
    /// An empty arena of `capacity` units.
    pub(crate) fn new(capacity: u64) -> Arena {
        let mut free = BTreeMap::new();
        if capacity > 0 {
            free.insert(0, capacity);
        }
        Arena { capacity, free, used: 0 }
    }

    /// Units in use.
    pub(crate) fn used(&self) -> u64 {
        self.used
    }

    /// Total units.
    pub(crate) fn capacity(&self) -> u64 {
        self.capacity
    }

    /// A range of `n` units (the lowest that fits), or `None` when no free range is long enough. `n = 0` gives an
    /// empty range.
    pub(crate) fn alloc(&mut self, n: u64) -> Option<Range<u64>> {
        if n == 0 {
            return Some(0..0);
        }
        let (&start, &len) = self.free.iter().find(|(_, len)| **len >= n)?;
        self.free.remove(&start);
        if len > n {
            self.free.insert(start + n, len - n);
        }
        self.used += n;
        Some(start..start + n)
    }

    /// Return a range from [`Arena::alloc`].
    pub(crate) fn free(&mut self, r: Range<u64>) {
        if r.is_empty() {
            return;
        }
        debug_assert!(r.end <= self.capacity);
        self.used -= r.end - r.start;
        let (mut start, mut end) = (r.start, r.end);
        if let Some((&ps, &pl)) = self.free.range(..start).next_back() {
            debug_assert!(ps + pl <= start, "double free");
            if ps + pl == start {
                self.free.remove(&ps);
                start = ps;
            }
        }
        if let Some(&nl) = self.free.get(&end) {
            self.free.remove(&end);
            end += nl;
        }
        self.free.insert(start, end - start);
    }

    /// The longest free range.
    #[cfg(test)]
    fn largest_free(&self) -> u64 {
        self.free.values().copied().max().unwrap_or(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn allocates_first_fit_and_coalesces() {
        let mut a = Arena::new(100);
        let x = a.alloc(30).unwrap();
        let y = a.alloc(30).unwrap();
        let z = a.alloc(30).unwrap();
        assert_eq!((x.clone(), y.clone(), z.clone()), (0..30, 30..60, 60..90));
        assert_eq!(a.alloc(11), None, "only 10 left");
        assert_eq!(a.used(), 90);
        a.free(y);
        assert_eq!(a.alloc(31), None, "30 + 10 are not adjacent");
        a.free(x);
        assert_eq!(a.largest_free(), 60, "0..30 and 30..60 merged");
        a.free(z);
        assert_eq!(a.largest_free(), 100, "everything merged again");
        assert_eq!(a.used(), 0);
        assert_eq!(a.alloc(100), Some(0..100));
        assert_eq!(a.alloc(0), Some(0..0));
    }

    #[test]
    fn random_churn_keeps_the_books() {
        let mut a = Arena::new(1000);
        let mut held: Vec<Range<u64>> = Vec::new();
        let mut x = 12345u64;
        for _ in 0..5000 {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            if x >> 63 == 0 || held.is_empty() {
                if let Some(r) = a.alloc((x >> 40) % 60 + 1) {
                    assert!(held.iter().all(|h| h.end <= r.start || r.end <= h.start), "overlap");
                    held.push(r);
                }
            } else {
                let r = held.swap_remove(((x >> 20) as usize) % held.len());
                a.free(r);
            }
            assert_eq!(a.used(), held.iter().map(|r| r.end - r.start).sum::<u64>());
        }
        for r in held.drain(..) {
            a.free(r);
        }
        assert_eq!(a.largest_free(), 1000);
    }
}
