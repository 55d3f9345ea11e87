//! One bounded least-recently-used map for every cache in Canopy (the server's overlays and summary nodes, the far
//! field's memo, the harness's ground truth and meshes, the renderer's resident geometry): entries carry a cost
//! (bytes, or 1 for a count bound), and the caller evicts the oldest down to its bound, told what left so that it
//! can act on it (stop a watch, count an eviction). Eviction order is by use only, so it is the same on every
//! machine.

use std::collections::{BTreeMap, HashMap};
use std::hash::Hash;

#[derive(Debug)]
struct Slot<V> {
    value: V,
    cost: usize,
    used: u64,
}

/// A map that remembers the order its entries were last used in (see the module docs).
#[derive(Debug)]
pub struct Lru<K, V> {
    map: HashMap<K, Slot<V>>,
    /// Keys by last use, oldest first.
    order: BTreeMap<u64, K>,
    clock: u64,
    cost: usize,
}

impl<K, V> Default for Lru<K, V> {
    fn default() -> Self {
        Lru { map: HashMap::new(), order: BTreeMap::new(), clock: 0, cost: 0 }
    }
}

impl<K: Hash + Eq + Clone, V> Lru<K, V> {
    /// An empty map.
    pub fn new() -> Lru<K, V> {
        Lru::default()
    }

    /// Entries held.
    pub fn len(&self) -> usize {
        self.map.len()
    }

    /// Whether it holds nothing.
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    /// The entries' total cost.
    pub fn cost(&self) -> usize {
        self.cost
    }

    /// Whether `key` is held (not a use).
    pub fn contains(&self, key: &K) -> bool {
        self.map.contains_key(key)
    }

    /// The value of `key`, not counted as a use.
    pub fn peek(&self, key: &K) -> Option<&V> {
        self.map.get(key).map(|s| &s.value)
    }

    /// The value of `key`, now the most recently used.
    pub fn get(&mut self, key: &K) -> Option<&mut V> {
        self.clock += 1;
        let slot = self.map.get_mut(key)?;
        self.order.remove(&slot.used);
        slot.used = self.clock;
        self.order.insert(self.clock, key.clone());
        Some(&mut slot.value)
    }

    /// Hold `value` for `key` at `cost`, the most recently used; the value it replaces, if any.
    pub fn insert(&mut self, key: K, value: V, cost: usize) -> Option<V> {
        let old = self.remove(&key);
        self.clock += 1;
        self.order.insert(self.clock, key.clone());
        self.map.insert(key, Slot { value, cost, used: self.clock });
        self.cost += cost;
        old
    }

    /// Change the cost of `key`'s entry (its value grew or shrank in place).
    pub fn set_cost(&mut self, key: &K, cost: usize) {
        if let Some(slot) = self.map.get_mut(key) {
            self.cost = self.cost - slot.cost + cost;
            slot.cost = cost;
        }
    }

    /// Take `key`'s entry out.
    pub fn remove(&mut self, key: &K) -> Option<V> {
        let slot = self.map.remove(key)?;
        self.order.remove(&slot.used);
        self.cost -= slot.cost;
        Some(slot.value)
    }

    /// The least recently used entry (not a use).
    pub fn oldest(&self) -> Option<(&K, &V)> {
        let key = self.order.values().next()?;
        Some((key, &self.map[key].value))
    }

    /// Take out the least recently used entry other than `keep`.
    pub fn pop_oldest(&mut self, keep: Option<&K>) -> Option<(K, V)> {
        let key = self.order.values().find(|k| keep != Some(*k))?.clone();
        let value = self.remove(&key)?;
        Some((key, value))
    }

    /// Take out least recently used entries (never `keep`) until the total cost is at most `limit`; what left,
    /// oldest first.
    pub fn evict_to(&mut self, limit: usize, keep: Option<&K>) -> Vec<(K, V)> {
        let mut out = Vec::new();
        while self.cost > limit {
            match self.pop_oldest(keep) {
                Some(e) => out.push(e),
                None => break,
            }
        }
        out
    }

    /// Every key and value, in no particular order (not a use).
    pub fn iter(&self) -> impl Iterator<Item = (&K, &V)> {
        self.map.iter().map(|(k, s)| (k, &s.value))
    }

    /// Drop everything.
    pub fn clear(&mut self) {
        self.map.clear();
        self.order.clear();
        self.cost = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evicts_the_least_recently_used_down_to_the_bound_and_keeps_what_it_is_told() {
        let mut l: Lru<u32, &str> = Lru::new();
        l.insert(1, "a", 10);
        l.insert(2, "b", 10);
        l.insert(3, "c", 10);
        assert_eq!(l.get(&1), Some(&mut "a"));
        assert_eq!(l.cost(), 30);
        assert_eq!(l.oldest(), Some((&2, &"b")));
        // 2 is the oldest now, then 3; 3 is kept.
        let out = l.evict_to(10, Some(&3));
        assert_eq!(out, vec![(2, "b"), (1, "a")]);
        assert_eq!((l.len(), l.cost()), (1, 10));
        assert_eq!(l.insert(3, "C", 4), Some("c"));
        l.set_cost(&3, 7);
        assert_eq!(l.cost(), 7);
        assert_eq!(l.evict_to(0, Some(&3)), vec![]);
        assert_eq!(l.remove(&3), Some("C"));
        assert!(l.is_empty() && l.cost() == 0);
    }
}
