//! The residency octree (CPU model): a full, pointerless octree over the
//! normalized volume whose nodes say, per channel, in which resolution
//! levels some overlapping brick is resident (a bitmask) and which values
//! the node's samples can take at each level (min/max from the store's
//! per-brick statistics). Kept up to date from the virtual memory's map
//! and evict events, frame by frame; `octree/dvr.rs` traverses it. The
//! device twin of the update pass is `octree.wgsl` (`gpu/octree.rs`).
//!
//! # Layout
//!
//! Depth `D` (the user's choice, [`MIN_DEPTH`]`..=`[`MAX_DEPTH`]): nodes
//! of depth `d` split every axis into `2^d` equal parts of `[0, 1)`, and
//! are stored in level order: node `(z, y, x)` of depth `d` has index
//! `(8^d − 1)/7 + (z·2^d + y)·2^d + x`, its children are `(2z + i, 2y +
//! j, 2x + k)` of depth `d + 1`: no pointers. Per node and channel one
//! `u32` residency mask (bit `l`: level `l`), per node, channel and level
//! one `[min, max]`.
//!
//! # Overlap
//!
//! Brick `b` of level `l` covers the voxels `[b·B, min((b+1)·B, n))` of
//! that level's `n` per axis, i.e. the normalized interval `[b·B/n,
//! min((b+1)·B, n)/n)`; it overlaps a node when the two half-open
//! intervals intersect on every axis. The test is integer arithmetic
//! (`b·B·2^d < (i+1)·n` and `i·n < hi·2^d`), the same on the device.
//!
//! # Value ranges, per level
//!
//! A sample at normalized `p` of level `l` is a trilinear interpolation of
//! the voxels around `p·n − ½`, which lie in the *padded* brick (apron
//! included) whose box holds `p·n`. That brick overlaps every node that
//! holds `p`. So the union of the padded ranges ([`BrickRanges`]) of the
//! level-`l` bricks overlapping a node bounds every level-`l` sample
//! taken inside it: that is the node's range at level `l`. One range for
//! all levels would have to include the coarsest brick, which covers the
//! whole volume, and nothing could be skipped. A level without statistics
//! gives NaN (unknown: never skipped). Leaves are computed from the
//! bricks, inner nodes as the union of their children (the bricks
//! overlapping a node are those overlapping its children).
//!
//! # Residency, and why counters
//!
//! A node is *partially mapped* in level `l` when at least one level-`l`
//! brick overlapping it is mapped (data in the pool, or an EMPTY/CONSTANT
//! entry). Setting bits by OR-ing children's masks upwards works for
//! maps, but an OR cannot clear a bit on eviction. So each **leaf** keeps,
//! per channel and level, a counter of the mapped bricks overlapping it:
//! a map event adds one to every leaf the brick overlaps, an evict event
//! subtracts one; a leaf's bit `l` is `count > 0`, and inner masks are
//! recomputed bottom-up as the OR of their children, only for the
//! ancestors of leaves whose bits changed. [`Octree::apply`] is that pass;
//! its device twin runs the same steps.
//!
//! # Events
//!
//! [`Octree::sync`] turns the virtual memory's residency log
//! ([`VirtualMemory::take_residency`]: keys mapped, and whether anything
//! was unmapped) into events: each key mapped and still resident that the
//! octree does not count yet is a map event; when something was unmapped,
//! every key the octree counts is checked (one page-table walk each, only
//! on such frames) and those no longer mapped are evict events. So page-
//! table blocks orphaned with everything below them are caught as well as
//! single evictions.

pub mod device;
pub(crate) mod dvr;

use brickyard_cache::brick::BrickKey;
use brickyard_cache::ranges::BrickRanges;
use brickyard_cache::vm::VirtualMemory;
use brickyard_core::{ConfigError, Dims3};
use std::collections::HashSet;

/// Smallest depth (the root and its children).
pub const MIN_DEPTH: u32 = 1;
/// Largest depth (8⁷ ≈ 2.1 M leaves).
pub const MAX_DEPTH: u32 = 7;
/// Depth when none is chosen.
pub const DEFAULT_DEPTH: u32 = 4;
/// Most bytes the octree may take (masks, ranges, leaf counters).
pub const MAX_BYTES: u64 = 1 << 30;

/// Nodes of a full octree of depth `depth`.
pub fn node_count(depth: u32) -> usize {
    node_offset(depth + 1)
}

/// Index of the first node of depth `d`: `(8^d − 1)/7`.
#[inline]
pub fn node_offset(d: u32) -> usize {
    ((1usize << (3 * d)) - 1) / 7
}

/// A map (`mapped`) or evict event of brick `key`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Event {
    pub key: BrickKey,
    pub mapped: bool,
}

/// The residency octree of one volume (see the module's documentation).
#[derive(Debug, Clone)]
pub struct Octree {
    pub depth: u32,
    pub channels: usize,
    /// Voxels per level `[z, y, x]`.
    pub dims: Vec<Dims3>,
    /// Brick edge in voxels `[z, y, x]`.
    pub brick: Dims3,
    /// `[node][channel]`: bit `l` set when some overlapping brick of level
    /// `l` is mapped.
    pub mask: Vec<u32>,
    /// `[node][channel][level]`: `[min, max]` of every sample of that
    /// level inside the node; NaN: unknown.
    pub range: Vec<[f32; 2]>,
    /// `[leaf][channel][level]`: mapped bricks overlapping the leaf.
    pub count: Vec<u32>,
    /// Keys counted as mapped (packed).
    counted: HashSet<u64>,
}

impl Octree {
    /// An octree of depth `depth` for a volume of `dims` per level and
    /// `channels`, bricks of `brick` voxels, node ranges from `ranges`
    /// (`None`: unknown), nothing mapped.
    pub fn new(
        depth: u32,
        dims: &[Dims3],
        brick: Dims3,
        channels: usize,
        ranges: Option<&BrickRanges>,
    ) -> Result<Octree, ConfigError> {
        let bad = |m: String| Err(ConfigError::new("residency octree", "octree_depth", m));
        if !(MIN_DEPTH..=MAX_DEPTH).contains(&depth) {
            return bad(format!(
                "depth must be {MIN_DEPTH} to {MAX_DEPTH}, got {depth}"
            ));
        }
        let nl = dims.len();
        if nl == 0 || nl > 32 {
            return bad(format!("1 to 32 levels (one mask bit each), got {nl}"));
        }
        let nodes = node_count(depth) as u64;
        let leaves = 1u64 << (3 * depth);
        let c = channels as u64;
        let bytes = nodes * c * 4 + nodes * c * nl as u64 * 8 + leaves * c * nl as u64 * 4;
        if bytes > MAX_BYTES {
            return bad(format!(
                "depth {depth} with {channels} channels and {nl} levels needs {} MiB (at most {} MiB): choose a smaller depth",
                bytes >> 20,
                MAX_BYTES >> 20
            ));
        }
        let mut o = Octree {
            depth,
            channels,
            dims: dims.to_vec(),
            brick,
            mask: vec![0; nodes as usize * channels],
            range: vec![[f32::NAN; 2]; nodes as usize * channels * nl],
            count: vec![0; leaves as usize * channels * nl],
            counted: HashSet::new(),
        };
        o.build_ranges(ranges);
        Ok(o)
    }

    /// The octree of `vm`'s volume with what `vm` has mapped now, logging
    /// the virtual memory's residency from now on for [`sync`](Self::sync).
    pub fn attach(
        depth: u32,
        dims: &[Dims3],
        vm: &mut VirtualMemory,
        ranges: Option<&BrickRanges>,
    ) -> Result<Octree, ConfigError> {
        vm.track_residency();
        vm.take_residency();
        Octree::of_vm(depth, dims, vm, ranges)
    }

    /// The octree of `vm`'s volume with what `vm` has mapped now (every
    /// brick key checked once: one page-table walk each).
    pub fn of_vm(
        depth: u32,
        dims: &[Dims3],
        vm: &VirtualMemory,
        ranges: Option<&BrickRanges>,
    ) -> Result<Octree, ConfigError> {
        let mut o = Octree::new(depth, dims, vm.config().brick, vm.channels(), ranges)?;
        let mut events = vec![];
        for l in 0..dims.len() {
            let nb = o.bricks(l);
            for c in 0..o.channels {
                for z in 0..nb[0] {
                    for y in 0..nb[1] {
                        for x in 0..nb[2] {
                            let key =
                                BrickKey::new(l as u8, c as u16, [z as u32, y as u32, x as u32]);
                            if vm.is_resident(key) {
                                events.push(Event { key, mapped: true });
                            }
                        }
                    }
                }
            }
        }
        o.apply(&events);
        Ok(o)
    }

    pub fn levels(&self) -> usize {
        self.dims.len()
    }

    /// Bricks per axis of level `l`.
    pub fn bricks(&self, l: usize) -> Dims3 {
        [0, 1, 2].map(|a| self.dims[l][a].div_ceil(self.brick[a]))
    }

    /// Keys the octree counts as mapped.
    pub fn mapped_count(&self) -> usize {
        self.counted.len()
    }

    /// Node `(z, y, x)` of depth `d`.
    #[inline]
    pub fn node(&self, d: u32, c: [u64; 3]) -> usize {
        let n = 1u64 << d;
        node_offset(d) + ((c[0] * n + c[1]) * n + c[2]) as usize
    }

    /// Leaves `[lo, hi)` per axis that brick `b` of level `l` overlaps.
    pub fn leaves_of(&self, l: usize, b: Dims3) -> (Dims3, Dims3) {
        overlap(self.depth, self.dims[l], self.brick, b)
    }

    /// The mask of `node` for channel `c`.
    #[inline]
    pub fn mask_of(&self, node: usize, c: usize) -> u32 {
        self.mask[node * self.channels + c]
    }

    /// The range of `node` for channel `c` at level `l`.
    #[inline]
    pub fn range_of(&self, node: usize, c: usize, l: usize) -> [f32; 2] {
        self.range[(node * self.channels + c) * self.levels() + l]
    }

    fn build_ranges(&mut self, ranges: Option<&BrickRanges>) {
        let nl = self.levels();
        let ch = self.channels;
        let d = self.depth;
        let leaf0 = node_offset(d);
        let n = 1u64 << d;
        for l in 0..nl {
            let Some(r) = ranges.and_then(|r| r.level(l)) else {
                continue;
            };
            if r.channels < ch {
                continue;
            }
            let nb = self.bricks(l);
            // Leaves start empty for this level (then NaN spreads).
            for leaf in 0..(n * n * n) as usize {
                for c in 0..ch {
                    self.range[((leaf0 + leaf) * ch + c) * nl + l] =
                        [f32::INFINITY, f32::NEG_INFINITY];
                }
            }
            for bz in 0..nb[0] {
                for by in 0..nb[1] {
                    for bx in 0..nb[2] {
                        let b = [bz, by, bx];
                        let (lo, hi) = self.leaves_of(l, b);
                        for c in 0..ch {
                            let br = r.get(c, b);
                            for z in lo[0]..hi[0] {
                                for y in lo[1]..hi[1] {
                                    for x in lo[2]..hi[2] {
                                        let leaf = leaf0 + ((z * n + y) * n + x) as usize;
                                        let i = (leaf * ch + c) * nl + l;
                                        self.range[i] = union(self.range[i], br);
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        // Inner nodes: union of the children, deepest first.
        for dd in (0..d).rev() {
            let m = 1u64 << dd;
            for z in 0..m {
                for y in 0..m {
                    for x in 0..m {
                        let node = self.node(dd, [z, y, x]);
                        for c in 0..ch {
                            for l in 0..nl {
                                let mut acc = [f32::INFINITY, f32::NEG_INFINITY];
                                for k in 0..8u64 {
                                    let cc =
                                        [2 * z + (k >> 2), 2 * y + (k >> 1 & 1), 2 * x + (k & 1)];
                                    acc = union(acc, self.range_of(self.node(dd + 1, cc), c, l));
                                }
                                self.range[(node * ch + c) * nl + l] = acc;
                            }
                        }
                    }
                }
            }
        }
    }

    /// Turn `vm`'s residency log into events and [`apply`](Self::apply)
    /// them (see the module's documentation). Returns the events.
    pub fn sync(&mut self, vm: &mut VirtualMemory) -> Vec<Event> {
        let (mapped, lost) = vm.take_residency();
        let mut events = vec![];
        let mut seen = HashSet::new();
        for key in mapped {
            let k = key.pack();
            if !self.counted.contains(&k) && seen.insert(k) && vm.is_resident(key) {
                events.push(Event { key, mapped: true });
            }
        }
        if lost {
            let mut gone: Vec<u64> = self
                .counted
                .iter()
                .copied()
                .filter(|&k| !vm.is_resident(BrickKey::unpack(k)))
                .collect();
            gone.sort_unstable();
            events.extend(gone.into_iter().map(|k| Event {
                key: BrickKey::unpack(k),
                mapped: false,
            }));
        }
        self.apply(&events);
        events
    }

    /// Filter then pass: [`effective`](Self::effective) events through
    /// [`pass`](Self::pass).
    pub fn apply(&mut self, events: &[Event]) {
        let e = self.effective(events);
        self.pass(&e);
    }

    /// The events that change something, in order: map events of keys not
    /// counted yet, evict events of keys counted (the set of counted keys
    /// follows). What the device's pass is given.
    pub fn effective(&mut self, events: &[Event]) -> Vec<Event> {
        let (nl, ch) = (self.levels(), self.channels);
        events
            .iter()
            .filter(|e| {
                let k = e.key.pack();
                (e.key.level as usize) < nl
                    && (e.key.channel as usize) < ch
                    && if e.mapped {
                        self.counted.insert(k)
                    } else {
                        self.counted.remove(&k)
                    }
            })
            .copied()
            .collect()
    }

    /// The update pass (device twin `octree.wgsl`): counters of the
    /// overlapped leaves per event, the masks of the leaves changed, then
    /// their ancestors' masks as the OR of their children. `events` must
    /// be [`effective`](Self::effective).
    pub fn pass(&mut self, events: &[Event]) {
        let nl = self.levels();
        let ch = self.channels;
        let d = self.depth;
        let n = 1u64 << d;
        let mut touched: Vec<u64> = vec![];
        for e in events {
            let (l, c) = (e.key.level as usize, e.key.channel as usize);
            let b = e.key.brick.map(|x| x as u64);
            let (lo, hi) = self.leaves_of(l, b);
            for z in lo[0]..hi[0] {
                for y in lo[1]..hi[1] {
                    for x in lo[2]..hi[2] {
                        let leaf = (z * n + y) * n + x;
                        let cnt = &mut self.count[(leaf as usize * ch + c) * nl + l];
                        if e.mapped {
                            *cnt += 1;
                        } else {
                            *cnt -= 1;
                        }
                        touched.push(leaf * ch as u64 + c as u64);
                    }
                }
            }
        }
        touched.sort_unstable();
        touched.dedup();
        // Leaves' masks from their counters.
        let leaf0 = node_offset(d);
        let mut dirty: Vec<u64> = vec![]; // (node at depth dd) * ch + c
        for &lc in &touched {
            let (leaf, c) = ((lc / ch as u64) as usize, (lc % ch as u64) as usize);
            let cnt = &self.count[(leaf * ch + c) * nl..(leaf * ch + c + 1) * nl];
            let m = cnt
                .iter()
                .enumerate()
                .fold(0u32, |m, (l, &k)| m | ((k > 0) as u32) << l);
            let i = (leaf0 + leaf) * ch + c;
            if self.mask[i] != m {
                self.mask[i] = m;
                dirty.push(lc);
            }
        }
        // Up the tree, one depth at a time: parents of changed nodes.
        for dd in (0..d).rev() {
            let m = 1u64 << (dd + 1);
            let mut parents: Vec<u64> = dirty
                .iter()
                .map(|&lc| {
                    let (node, c) = (lc / ch as u64, lc % ch as u64);
                    let (z, y, x) = (node / (m * m), node / m % m, node % m);
                    let pm = m / 2;
                    (((z / 2) * pm + y / 2) * pm + x / 2) * ch as u64 + c
                })
                .collect();
            parents.sort_unstable();
            parents.dedup();
            dirty.clear();
            let pm = m / 2;
            for &pc in &parents {
                let (p, c) = (pc / ch as u64, (pc % ch as u64) as usize);
                let (z, y, x) = (p / (pm * pm), p / pm % pm, p % pm);
                let mut acc = 0u32;
                for k in 0..8u64 {
                    let cc = [2 * z + (k >> 2), 2 * y + (k >> 1 & 1), 2 * x + (k & 1)];
                    acc |= self.mask_of(self.node(dd + 1, cc), c);
                }
                let i = self.node(dd, [z, y, x]) * ch + c;
                if self.mask[i] != acc {
                    self.mask[i] = acc;
                    dirty.push(pc);
                }
            }
            if dirty.is_empty() {
                break;
            }
        }
    }
}

/// The union of two ranges; NaN (unknown) wins.
#[inline]
pub(crate) fn union(a: [f32; 2], b: [f32; 2]) -> [f32; 2] {
    if a[0].is_nan() || b[0].is_nan() || a[1].is_nan() || b[1].is_nan() {
        return [f32::NAN; 2];
    }
    [a[0].min(b[0]), a[1].max(b[1])]
}

/// Leaves `[lo, hi)` per axis of an octree of depth `depth` that brick `b`
/// (edge `brick` voxels) of a level of `dims` voxels overlaps.
pub fn overlap(depth: u32, dims: Dims3, brick: Dims3, b: Dims3) -> (Dims3, Dims3) {
    let n = 1u64 << depth;
    let mut lo = [0; 3];
    let mut hi = [0; 3];
    for a in 0..3 {
        let v0 = b[a] * brick[a];
        let v1 = ((b[a] + 1) * brick[a]).min(dims[a]);
        // Leaves i with i·dims < v1·n and v0·n < (i + 1)·dims.
        lo[a] = (v0 * n) / dims[a];
        hi[a] = (v1 * n).div_ceil(dims[a]).min(n);
    }
    (lo, hi)
}

#[cfg(test)]
mod tests;
