//! The host cache: loaded bricks kept in RAM under a hard byte budget, least
//! recently used evicted first.
//!
//! Accounting: an entry costs its voxel bytes ([`BrickContent::data_bytes`],
//! 0 for empty and constant bricks) plus [`ENTRY_OVERHEAD`] bytes for the
//! bookkeeping (the `LoadedBrick` and its `Arc` header, the `Arc<[u8]>`
//! header, the hash-map slot and the list node: about 200 bytes on 64-bit
//! targets, rounded up). The sum over the entries held never exceeds the
//! budget, at any moment; an entry that alone exceeds the budget is not
//! cached. Bricks handed out (`Arc`s held by callers) stay alive after
//! eviction but no longer count: the budget is what the cache holds.
//!
//! Every operation is O(1): a hash map from key to a slot of a `Vec` of
//! nodes that form an intrusive doubly linked list in recency order.

use crate::brick::{BrickContent, BrickKey, LoadedBrick};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

/// Bytes charged per entry on top of its voxel data.
pub const ENTRY_OVERHEAD: u64 = 256;

const NIL: usize = usize::MAX;

/// What one brick costs in the cache.
pub fn entry_cost(b: &LoadedBrick) -> u64 {
    ENTRY_OVERHEAD + b.content.data_bytes() as u64
}

struct Node {
    key: BrickKey,
    brick: Option<Arc<LoadedBrick>>,
    cost: u64,
    /// Towards the most recently used end.
    prev: usize,
    /// Towards the least recently used end.
    next: usize,
}

struct Inner {
    map: HashMap<BrickKey, usize>,
    nodes: Vec<Node>,
    free: Vec<usize>,
    /// Most recently used.
    head: usize,
    /// Least recently used.
    tail: usize,
    bytes: u64,
    budget: u64,
}

impl Inner {
    fn unlink(&mut self, i: usize) {
        let (p, n) = (self.nodes[i].prev, self.nodes[i].next);
        if p == NIL {
            self.head = n;
        } else {
            self.nodes[p].next = n;
        }
        if n == NIL {
            self.tail = p;
        } else {
            self.nodes[n].prev = p;
        }
        self.nodes[i].prev = NIL;
        self.nodes[i].next = NIL;
    }

    fn push_front(&mut self, i: usize) {
        self.nodes[i].prev = NIL;
        self.nodes[i].next = self.head;
        if self.head != NIL {
            self.nodes[self.head].prev = i;
        } else {
            self.tail = i;
        }
        self.head = i;
    }

    /// Remove slot `i` entirely; returns its brick.
    fn remove_slot(&mut self, i: usize) -> Option<Arc<LoadedBrick>> {
        self.unlink(i);
        let key = self.nodes[i].key;
        self.map.remove(&key);
        self.bytes -= self.nodes[i].cost;
        self.nodes[i].cost = 0;
        self.free.push(i);
        self.nodes[i].brick.take()
    }

    /// Evict from the LRU end until `extra` more bytes fit. Returns the
    /// number of entries evicted.
    fn make_room(&mut self, extra: u64) -> u64 {
        let mut n = 0;
        while self.bytes + extra > self.budget && self.tail != NIL {
            let t = self.tail;
            self.remove_slot(t);
            n += 1;
        }
        n
    }
}

/// A thread-safe LRU cache of loaded bricks with a byte budget.
pub struct HostCache {
    inner: Mutex<Inner>,
    hits: AtomicU64,
    misses: AtomicU64,
    evictions: AtomicU64,
}

impl HostCache {
    /// An empty cache that will hold at most `budget` bytes.
    pub fn new(budget: u64) -> Self {
        HostCache {
            inner: Mutex::new(Inner {
                map: HashMap::new(),
                nodes: Vec::new(),
                free: Vec::new(),
                head: NIL,
                tail: NIL,
                bytes: 0,
                budget,
            }),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
            evictions: AtomicU64::new(0),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // The critical sections cannot panic half-way through an update
        // except on allocation failure; a poisoned lock is still consistent.
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The brick for `key`, marking it most recently used. Counts a hit or
    /// a miss.
    pub fn get(&self, key: &BrickKey) -> Option<Arc<LoadedBrick>> {
        let mut g = self.lock();
        match g.map.get(key).copied() {
            Some(i) => {
                g.unlink(i);
                g.push_front(i);
                self.hits.fetch_add(1, Ordering::Relaxed);
                g.nodes[i].brick.clone()
            }
            None => {
                self.misses.fetch_add(1, Ordering::Relaxed);
                None
            }
        }
    }

    /// Whether `key` is cached (does not touch it nor count).
    pub fn contains(&self, key: &BrickKey) -> bool {
        self.lock().map.contains_key(key)
    }

    /// Insert (or replace) a brick as the most recently used, evicting the
    /// least recently used entries until it fits. A brick that costs more
    /// than the whole budget is not cached (and any older entry for its key
    /// is dropped). Returns whether the brick is now cached.
    pub fn insert(&self, brick: Arc<LoadedBrick>) -> bool {
        let cost = entry_cost(&brick);
        let mut g = self.lock();
        if let Some(i) = g.map.get(&brick.key).copied() {
            g.remove_slot(i);
        }
        if cost > g.budget {
            return false;
        }
        let ev = g.make_room(cost);
        self.evictions.fetch_add(ev, Ordering::Relaxed);
        let key = brick.key;
        let node = Node {
            key,
            brick: Some(brick),
            cost,
            prev: NIL,
            next: NIL,
        };
        let i = match g.free.pop() {
            Some(i) => {
                g.nodes[i] = node;
                i
            }
            None => {
                g.nodes.push(node);
                g.nodes.len() - 1
            }
        };
        g.push_front(i);
        g.map.insert(key, i);
        g.bytes += cost;
        debug_assert!(g.bytes <= g.budget);
        true
    }

    /// Remove one entry.
    pub fn remove(&self, key: &BrickKey) -> Option<Arc<LoadedBrick>> {
        let mut g = self.lock();
        let i = g.map.get(key).copied()?;
        g.remove_slot(i)
    }

    /// Remove every entry.
    pub fn clear(&self) {
        let mut g = self.lock();
        g.map.clear();
        g.nodes.clear();
        g.free.clear();
        g.head = NIL;
        g.tail = NIL;
        g.bytes = 0;
    }

    /// Change the budget, evicting least recently used entries to fit.
    pub fn set_budget(&self, budget: u64) {
        let mut g = self.lock();
        g.budget = budget;
        let ev = g.make_room(0);
        self.evictions.fetch_add(ev, Ordering::Relaxed);
    }

    /// Number of cached bricks.
    pub fn len(&self) -> usize {
        self.lock().map.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes charged for the cached bricks (≤ [`HostCache::budget`]).
    pub fn bytes(&self) -> u64 {
        self.lock().bytes
    }

    pub fn budget(&self) -> u64 {
        self.lock().budget
    }

    /// `get` calls that found their brick.
    pub fn hits(&self) -> u64 {
        self.hits.load(Ordering::Relaxed)
    }

    /// `get` calls that did not.
    pub fn misses(&self) -> u64 {
        self.misses.load(Ordering::Relaxed)
    }

    /// Entries evicted to make room (not counting replacements and
    /// explicit removals).
    pub fn evictions(&self) -> u64 {
        self.evictions.load(Ordering::Relaxed)
    }

    /// Cached keys from the most to the least recently used.
    pub fn keys_by_recency(&self) -> Vec<BrickKey> {
        let g = self.lock();
        let mut out = Vec::with_capacity(g.map.len());
        let mut i = g.head;
        while i != NIL {
            out.push(g.nodes[i].key);
            i = g.nodes[i].next;
        }
        out
    }

    /// Counts of cached bricks by kind: `(empty, constant, data)`.
    pub fn composition(&self) -> (usize, usize, usize) {
        let g = self.lock();
        let mut c = (0, 0, 0);
        for &i in g.map.values() {
            match g.nodes[i].brick.as_ref().map(|b| &b.content) {
                Some(BrickContent::Empty) => c.0 += 1,
                Some(BrickContent::Constant(_)) => c.1 += 1,
                _ => c.2 += 1,
            }
        }
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brick(i: u32, data: usize) -> Arc<LoadedBrick> {
        Arc::new(LoadedBrick {
            key: BrickKey::new(0, 0, [0, 0, i]),
            content: if data == 0 {
                BrickContent::Empty
            } else {
                BrickContent::Data(vec![1u8; data].into())
            },
            min: 0.0,
            max: 1.0,
            bytes_read: data as u64,
        })
    }

    #[test]
    fn overhead_covers_the_bookkeeping() {
        use std::mem::size_of;
        // Arc<LoadedBrick> (two counters + the brick), the Arc<[u8]> header,
        // the list node, and a hash-map slot (key, index, control byte).
        let per_entry = 2 * size_of::<usize>()
            + size_of::<LoadedBrick>()
            + 2 * size_of::<usize>()
            + size_of::<Node>()
            + size_of::<(BrickKey, usize)>()
            + 1;
        assert!(per_entry as u64 <= ENTRY_OVERHEAD, "{per_entry}");
    }

    #[test]
    fn evicts_least_recently_used() {
        let c = HostCache::new(3 * (ENTRY_OVERHEAD + 100));
        for i in 0..3 {
            assert!(c.insert(brick(i, 100)));
        }
        assert_eq!(c.bytes(), 3 * (ENTRY_OVERHEAD + 100));
        assert!(c.get(&brick(0, 0).key).is_some()); // 0 is now MRU
        assert!(c.insert(brick(3, 100))); // evicts 1
        assert!(!c.contains(&brick(1, 0).key));
        assert_eq!(
            c.keys_by_recency(),
            [3, 0, 2].map(|i| brick(i, 0).key).to_vec()
        );
        assert_eq!(c.evictions(), 1);
        assert_eq!((c.hits(), c.misses()), (1, 0));
        assert!(c.get(&brick(1, 0).key).is_none());
        assert_eq!(c.misses(), 1);
    }

    #[test]
    fn uniform_bricks_cost_only_the_overhead() {
        let c = HostCache::new(10 * ENTRY_OVERHEAD);
        for i in 0..10 {
            assert!(c.insert(brick(i, 0)));
        }
        assert_eq!(c.len(), 10);
        assert_eq!(c.bytes(), 10 * ENTRY_OVERHEAD);
        assert_eq!(c.composition(), (10, 0, 0));
    }

    #[test]
    fn too_large_is_not_cached_and_replacement_accounts() {
        let c = HostCache::new(1000);
        assert!(!c.insert(brick(0, 1000)));
        assert!(c.is_empty());
        assert!(c.insert(brick(0, 10)));
        assert!(c.insert(brick(0, 20)));
        assert_eq!(c.len(), 1);
        assert_eq!(c.bytes(), ENTRY_OVERHEAD + 20);
        assert!(!c.insert(brick(0, 2000)));
        assert_eq!(c.len(), 0);
        assert_eq!(c.bytes(), 0);
        assert!(c.insert(brick(1, 100)));
        c.set_budget(ENTRY_OVERHEAD);
        assert_eq!(c.len(), 0);
        c.set_budget(10_000);
        assert!(c.insert(brick(2, 100)));
        assert!(c.remove(&brick(2, 0).key).is_some());
        assert_eq!(c.bytes(), 0);
        assert!(c.insert(brick(3, 100)));
        c.clear();
        assert_eq!((c.len(), c.bytes()), (0, 0));
    }
}
