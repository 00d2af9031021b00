//! The cache-management passes of the virtual memory as plain functions:
//! what [`crate::vm`] runs on the CPU, and the reference twins of the
//! device's kernels (`brickyard-gpu`), which must give the same results.
//!
//! - [`compact_lru`]: the LRU order after a frame, by order-preserving
//!   compaction of the slots used in it.
//! - [`BrickIds`]: one 32-bit id per brick of every level and channel,
//!   ordered like [`BrickKey`]s, for request tables on devices without
//!   64-bit atomics.
//! - [`RequestTable`] and [`prioritize`]: bounded request collection and
//!   the capped request list, most wanted first.

use crate::brick::BrickKey;
use brickyard_core::Dims3;

/// Order-preserving compaction of an LRU order (most recently used first):
/// the slots `used` in this frame first, then the others, each group in its
/// previous order. Used slots thereby move to the front and the least
/// recently used ones stay at the tail.
pub fn compact_lru(order: &[u32], used: impl Fn(u32) -> bool) -> Vec<u32> {
    let (mut front, rest): (Vec<u32>, Vec<u32>) = order.iter().partition(|&&s| used(s));
    front.extend(rest);
    front
}

/// Dense 32-bit ids of the bricks of a volume: levels in order, then
/// channels, then bricks row-major `[z, y, x]`. Comparing ids compares the
/// keys ([`BrickKey`]'s order is level, channel, z, y, x).
#[derive(Debug, Clone)]
pub struct BrickIds {
    /// Bricks per axis of each level.
    grid: Vec<Dims3>,
    channels: u64,
    /// First id of each level, and the total at the end.
    first: Vec<u64>,
}

/// The id no brick has: an empty request-table bucket.
pub const NO_BRICK: u32 = u32::MAX;

impl BrickIds {
    /// Ids for levels with `grid[l]` bricks per axis and `channels`
    /// channels; `None` when there are `u32::MAX` bricks or more (about
    /// 140 TB of 8-bit voxels in 32³ bricks).
    pub fn new(grid: &[Dims3], channels: usize) -> Option<BrickIds> {
        let mut first = vec![0u64];
        for g in grid {
            let n = g.iter().product::<u64>().checked_mul(channels as u64)?;
            first.push(first.last()?.checked_add(n)?);
        }
        (*first.last()? < NO_BRICK as u64).then(|| BrickIds {
            grid: grid.to_vec(),
            channels: channels as u64,
            first,
        })
    }

    /// Number of ids.
    pub fn len(&self) -> u32 {
        *self.first.last().expect("one entry at least") as u32
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// First id of each level, then the total (`levels + 1` entries).
    pub fn level_starts(&self) -> Vec<u32> {
        self.first.iter().map(|&f| f as u32).collect()
    }

    pub fn id(&self, k: BrickKey) -> u32 {
        let l = k.level as usize;
        let g = self.grid[l];
        let [z, y, x] = k.brick.map(|b| b as u64);
        (self.first[l] + (k.channel as u64 * g[0] + z) * g[1] * g[2] + y * g[2] + x) as u32
    }

    pub fn level_of(&self, id: u32) -> usize {
        self.first.partition_point(|&f| f <= id as u64) - 1
    }

    pub fn key(&self, id: u32) -> BrickKey {
        let l = self.level_of(id);
        let g = self.grid[l];
        let mut i = id as u64 - self.first[l];
        let x = i % g[2];
        i /= g[2];
        let y = i % g[1];
        i /= g[1];
        let z = i % g[0];
        let c = i / g[0];
        debug_assert!(c < self.channels);
        BrickKey::new(l as u8, c as u16, [z as u32, y as u32, x as u32])
    }
}

/// Bounded request collection keyed by brick id: open addressing with
/// linear probing over a power-of-two number of buckets. A key that finds
/// no bucket (the table is full) is dropped and counted. The device twin
/// inserts the same way with atomics; without overflow both hold the same
/// (id, samples) pairs whatever the order of insertion.
#[derive(Debug, Clone)]
pub struct RequestTable {
    pub keys: Vec<u32>,
    pub counts: Vec<u32>,
    pub dropped: u64,
}

/// Bucket of `id` in a table of `mask + 1` buckets (a multiplicative hash;
/// the device computes the same).
#[inline]
pub fn request_bucket(id: u32, mask: u32) -> u32 {
    (id.wrapping_mul(0x9E37_79B1) >> 7) & mask
}

impl RequestTable {
    /// A table of `buckets` buckets (rounded up to a power of two).
    pub fn new(buckets: usize) -> RequestTable {
        let n = buckets.max(1).next_power_of_two();
        RequestTable {
            keys: vec![NO_BRICK; n],
            counts: vec![0; n],
            dropped: 0,
        }
    }

    /// Add `samples` misses of brick `id`.
    pub fn add(&mut self, id: u32, samples: u32) {
        let mask = self.keys.len() as u32 - 1;
        let mut b = request_bucket(id, mask);
        for _ in 0..self.keys.len() {
            let k = &mut self.keys[b as usize];
            if *k == NO_BRICK {
                *k = id;
            }
            if *k == id {
                self.counts[b as usize] = self.counts[b as usize].saturating_add(samples);
                return;
            }
            b = (b + 1) & mask;
        }
        self.dropped += 1;
    }

    /// The (id, samples) pairs held.
    pub fn entries(&self) -> Vec<(u32, u32)> {
        self.keys
            .iter()
            .zip(&self.counts)
            .filter(|(&k, _)| k != NO_BRICK)
            .map(|(&k, &c)| (k, c))
            .collect()
    }
}

/// The request list: most samples first; among equals, coarser levels
/// first (they cover more of the view), then keys in order; at most `cap`.
pub fn prioritize(mut list: Vec<(BrickKey, u32)>, cap: usize) -> Vec<(BrickKey, u32)> {
    list.sort_by(|a, b| {
        b.1.cmp(&a.1)
            .then(b.0.level.cmp(&a.0.level))
            .then(a.0.cmp(&b.0))
    });
    list.truncate(cap);
    list
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compaction_keeps_each_group_in_order() {
        let order = [5, 3, 9, 0, 7, 1];
        let used = |s: u32| s == 9 || s == 1 || s == 5;
        assert_eq!(compact_lru(&order, used), vec![5, 9, 1, 3, 0, 7]);
        assert_eq!(compact_lru(&[], used), Vec::<u32>::new());
    }

    #[test]
    fn brick_ids_are_dense_and_ordered_like_keys() {
        let grid = [[3, 4, 5], [2, 2, 3], [1, 1, 2]];
        let ids = BrickIds::new(&grid, 2).unwrap();
        assert_eq!(ids.len(), 2 * (60 + 12 + 2));
        let mut keys = vec![];
        for (l, g) in grid.iter().enumerate() {
            for c in 0..2u16 {
                for z in 0..g[0] as u32 {
                    for y in 0..g[1] as u32 {
                        for x in 0..g[2] as u32 {
                            keys.push(BrickKey::new(l as u8, c, [z, y, x]));
                        }
                    }
                }
            }
        }
        keys.sort();
        for (i, k) in keys.iter().enumerate() {
            assert_eq!(ids.id(*k), i as u32, "{k:?}");
            assert_eq!(ids.key(i as u32), *k);
            assert_eq!(ids.level_of(i as u32), k.level as usize);
        }
        assert!(BrickIds::new(&[[1 << 11, 1 << 11, 1 << 10]], 1).is_none());
    }

    #[test]
    fn table_sums_and_drops_beyond_its_buckets() {
        let mut t = RequestTable::new(4);
        for (id, n) in [(7, 1), (9, 2), (7, 3), (100, 1), (5, 1), (6, 1), (9, 1)] {
            t.add(id, n);
        }
        let mut e = t.entries();
        e.sort();
        assert_eq!(e, vec![(5, 1), (7, 4), (9, 3), (100, 1)]);
        assert_eq!(t.dropped, 1);
    }

    #[test]
    fn prioritize_orders_by_samples_then_coarser_then_key() {
        let k = |l, x| BrickKey::new(l, 0, [0, 0, x]);
        let list = vec![
            (k(0, 1), 5),
            (k(1, 0), 5),
            (k(0, 0), 9),
            (k(0, 0), 1),
            (k(2, 3), 1),
        ];
        let p = prioritize(list, 4);
        assert_eq!(
            p,
            vec![(k(0, 0), 9), (k(1, 0), 5), (k(0, 1), 5), (k(2, 3), 1)]
        );
    }
}
