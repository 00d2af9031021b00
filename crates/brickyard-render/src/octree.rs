//! The residency octree (CPU model): a full, pointerless octree over the
//! normalized volume whose nodes say, per channel, in which resolution
//! levels some overlapping brick is resident (a bitmask) and which values
//! the node's samples can take at each level (min/max of the resident
//! voxels, else the store's per-brick statistics). Kept up to date from the virtual memory's map
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
//! The renderers sample level `l` by trilinear interpolation of that
//! level's voxels, whose values are not those of level 0, so ranges are
//! kept per level: one range for all levels would have to include the
//! coarsest brick, which covers the whole volume, and nothing could be
//! skipped. A leaf's range at level `l` is the union, over the level-`l`
//! bricks overlapping it, of
//!
//! - the range of the brick's voxels *that a sample inside the leaf can
//!   read* when the brick is mapped: read from the pool for resident data
//!   ([`VirtualMemory::peek`]), the value itself for an EMPTY (0) or
//!   CONSTANT entry (every voxel, apron included, has it);
//! - else the brick's statistics range ([`BrickRanges`], padded with the
//!   apron, so every voxel of the padded brick is inside it);
//! - else unknown (NaN, never skipped).
//!
//! Inner nodes are the union of their children (the bricks overlapping a
//! node are those overlapping its children). [`Octree::new`] gives the
//! statistics-only ranges (what the device computes, `octree.wgsl`);
//! [`Octree::sync`] and [`Octree::of_vm`] tighten them from the voxels.
//!
//! *The voxels a sample inside a leaf can read.* Take one axis, the
//! level's `n` voxels spanning `s` of them across the extent (`s = n` at
//! level 0; a coarser level's last voxel may reach past the extent:
//! `level_span`), voxel `j` centred at `j + ½`, and a leaf of depth `D`
//! with index `i`: it covers the continuous coordinates `[a, b)`, `a =
//! i·s/2^D`, `b = (i+1)·s/2^D`. A sample at `p` (continuous coordinate `x
//! = p·s ∈ [a, b)`) takes `q = clamp(x − ½, 0, n − 1)` (clamp to edge),
//! the base voxel `j₀ = ⌊q⌋` and reads `j₀` and `j₀ + 1` with weights `1 −
//! f` and `f = q − j₀`. If `q = n − 1` (the clamp at the upper edge), `f =
//! 0`: voxel `n` (the apron beyond the volume) gets no weight and `lerp(a,
//! b, 0) = a` exactly. So the voxels read with any weight lie in `[0, n −
//! 1]` and in `[⌊a − ½⌋, ⌊b − ½⌋ + 1] ⊆ [⌊a⌋ − 1, ⌈b⌉]`: the leaf's voxels
//! grown by one on each side. The slack is at least half a voxel on each
//! side, so a point computed in floating point slightly outside the leaf
//! (the traversal finds the node from `w / extent`, the sampler `q` from
//! `w · s / extent`) still reads only these voxels. Per brick the octree
//! keeps the range of the voxels of its padded box (apron included) in that
//! grown leaf box, clamped to `[0, n − 1]`.
//!
//! *Whichever brick is looked up.* The sampler looks up the brick holding
//! the base voxel `j₀`, which need not overlap the leaf (`x` just inside
//! the leaf at a brick's lower face: `j₀` is the previous brick's last
//! voxel). What it returns is still a convex combination of the *level's*
//! voxel values at the voxels above (an apron holds copies of the
//! neighbours' voxels; an EMPTY/CONSTANT entry is uniform, apron included,
//! so its value is that of every voxel it covers). And each voxel `j` of
//! the grown box is in the padded box of a brick overlapping the leaf: `j ∈
//! [⌊a⌋, ⌈b⌉ − 1]` is inside the leaf's own voxels, whose bricks overlap it
//! (the same integer test as below), and `⌊a⌋ − 1`, `⌈b⌉` are apron voxels
//! of the bricks of `⌊a⌋` and `⌈b⌉ − 1`. That brick's contribution
//! includes `j` (from its voxels if mapped, else inside its padded
//! statistics). So the leaf's range bounds every level-`l` sample taken
//! inside it, up to the rounding of the three lerps, which is absorbed by
//! widening a range with `lo < hi` by `max(|lo|, |hi|)·2⁻²⁰` on each side
//! ([`widen`]; one value, `lo == hi`, is exact: `a + (a − a)·t = a`). NaN
//! voxels (float volumes) make NaN, transparent samples and are left out,
//! as in the statistics; a brick part with only NaN voxels is unknown.
//! A sample that misses its brick and is served by a coarser level (an
//! incomplete frame) is not bounded by the level's range, as with the
//! statistics.
//!
//! *Memory.* Per mapped brick with data the ranges of the leaves it
//! overlaps (at most `⌈B·2^D/n⌉ + 1` per axis: 8 where a brick is no
//! smaller than a leaf), one range for an EMPTY/CONSTANT entry; dropped
//! on eviction. Per level and channel at most `Π (2^D + bricks)` entries
//! of 8 bytes with everything mapped; not counted in [`MAX_BYTES`]: the
//! large per-brick parts are those of the coarse levels, which have few
//! bricks. Updates: a map or evict event recomputes the leaves the brick
//! overlaps (each the union over its bricks) and then their ancestors.
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
use brickyard_cache::ranges::{BrickRanges, LevelRanges};
use brickyard_cache::vm::{BrickRef, VirtualMemory};
use brickyard_core::{cast_slice, dispatch_dtype, ConfigError, DType, Dims3, Sample};
use std::collections::{HashMap, HashSet};

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
    /// Per level, its ratio to level 0 ([`span`](Self::span)).
    ratio: Vec<Dims3>,
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
    /// Per level: the store's per-brick statistics (`None`: unknown).
    stats: Vec<Option<LevelRanges>>,
    /// Per mapped brick whose values were read (packed key): its ranges
    /// in the leaves it overlaps.
    resident: HashMap<u64, LeafRanges>,
    /// The effective events since the device's twin last took them
    /// ([`Octree::take_device_events`]); `None`: no twin on a device.
    device_events: Option<Vec<Event>>,
    /// Unique per octree made (kept by clones): which octree a device twin
    /// follows.
    id: u64,
    /// Changes whenever [`sync`](Self::sync) or [`apply`](Self::apply)
    /// changed masks or ranges (tables made from the octree are current
    /// while it stays).
    generation: u64,
    /// The traversal's last per-frame tables (`dvr::OctFrame`), reused
    /// while nothing they are made of changes.
    pub(crate) tables: dvr::TableCache,
}

/// A mapped brick's value ranges in the leaves `[lo, hi)` it overlaps
/// (`[z][y][x]`, relative to `lo`; one range: the same in all, for an
/// EMPTY or CONSTANT entry).
#[derive(Debug, Clone)]
struct LeafRanges {
    lo: Dims3,
    hi: Dims3,
    range: Vec<[f32; 2]>,
}

impl LeafRanges {
    #[inline]
    fn get(&self, leaf: Dims3) -> [f32; 2] {
        if self.range.len() == 1 {
            return self.range[0];
        }
        let (lo, hi) = (self.lo, self.hi);
        let e = [0, 1, 2].map(|a| hi[a] - lo[a]);
        self.range[(((leaf[0] - lo[0]) * e[1] + leaf[1] - lo[1]) * e[2] + leaf[2] - lo[2]) as usize]
    }
}

impl Octree {
    /// Whether an octree of `depth` over `levels` levels of `channels`
    /// channels can be made: the depth in range, one mask bit per level,
    /// and its tables within `MAX_BYTES`.
    pub fn check(depth: u32, levels: usize, channels: usize) -> Result<(), ConfigError> {
        let bad = |m: String| Err(ConfigError::new("residency octree", "octree_depth", m));
        if !(MIN_DEPTH..=MAX_DEPTH).contains(&depth) {
            return bad(format!(
                "depth must be {MIN_DEPTH} to {MAX_DEPTH}, got {depth}"
            ));
        }
        let nl = levels;
        if nl == 0 || nl > 32 {
            return bad(format!("1 to 32 levels (one mask bit each), got {nl}"));
        }
        let bytes = Octree::bytes(depth, nl, channels);
        if bytes > MAX_BYTES {
            return bad(format!(
                "depth {depth} with {channels} channels and {nl} levels needs {} MiB (at most {} MiB): choose a smaller depth",
                bytes >> 20,
                MAX_BYTES >> 20
            ));
        }
        Ok(())
    }

    /// The bytes of the tables of an octree of depth `depth` over `levels`
    /// levels of `channels` channels: masks and value ranges per node,
    /// per-leaf entries.
    pub fn bytes(depth: u32, levels: usize, channels: usize) -> u64 {
        let nodes = node_count(depth.min(MAX_DEPTH)) as u64;
        let leaves = 1u64 << (3 * depth.min(MAX_DEPTH));
        let (c, nl) = (channels as u64, levels as u64);
        nodes * c * 4 + nodes * c * nl * 8 + leaves * c * nl * 4
    }

    /// What an octree of depth `depth` takes while views are drawn
    /// through it: its own tables ([`bytes`](Self::bytes)) and the
    /// traversal's per-frame tables over its nodes and levels, the last
    /// frame's kept beside the one being made (measured on the CPU: about
    /// 80 bytes per node and level at depths 6 and 7, whatever the
    /// channels).
    /// Bytes of the tables a device frame through an octree of `depth`
    /// binds in one storage buffer (residency masks, depths, level
    /// offsets), beside the transfer functions.
    pub fn device_table_bytes(depth: u32, levels: usize, channels: usize) -> u64 {
        dvr::OctFrame::device_layout(depth.min(MAX_DEPTH), levels, channels)[2] as u64 * 4
    }

    pub fn working_bytes(depth: u32, levels: usize, channels: usize) -> u64 {
        Octree::bytes(depth, levels, channels)
            + node_count(depth.min(MAX_DEPTH)) as u64 * levels as u64 * 80
    }

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
        Octree::check(depth, dims.len(), channels)?;
        let nodes = node_count(depth) as u64;
        let leaves = 1u64 << (3 * depth);
        let nl = dims.len();
        let mut o = Octree {
            depth,
            channels,
            dims: dims.to_vec(),
            brick,
            ratio: (0..nl)
                .map(|l| brickyard_core::level_ratio(dims, l))
                .collect(),
            mask: vec![0; nodes as usize * channels],
            range: vec![[f32::NAN; 2]; nodes as usize * channels * nl],
            count: vec![0; leaves as usize * channels * nl],
            counted: HashSet::new(),
            stats: (0..nl)
                .map(|l| {
                    ranges
                        .and_then(|r| r.level(l))
                        .filter(|r| r.channels >= channels)
                        .cloned()
                })
                .collect(),
            resident: HashMap::new(),
            device_events: None,
            id: {
                static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
                NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
            },
            generation: 0,
            tables: dvr::TableCache::default(),
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
    /// brick key checked once: one page-table walk each), node ranges
    /// tightened by the mapped bricks' values.
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
        let e = o.effective(&events);
        o.pass(&e);
        o.pass_ranges(&e, Some(vm));
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
        overlap(self.depth, self.dims[l], self.span(l), self.brick, b)
    }

    /// Level `l`'s span (its voxels across the extent) as the fraction
    /// `num / den` per axis: level 0's voxels over the level's ratio
    /// ([`level_span`](brickyard_core::level_span)).
    pub fn span(&self, l: usize) -> (Dims3, Dims3) {
        (self.dims[0], self.ratio[l])
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
        let e = self.effective(&events);
        self.pass(&e);
        self.pass_ranges(&e, Some(vm));
        self.logged(&e);
        events
    }

    /// After `e` (effective) was applied: kept for the device twin, and a
    /// new generation when anything changed.
    fn logged(&mut self, e: &[Event]) {
        if e.is_empty() {
            return;
        }
        self.generation += 1;
        if let Some(d) = &mut self.device_events {
            d.extend_from_slice(e);
        }
    }

    /// Which state of the octree this is ([`id`](Self::id) and a counter
    /// of the changes by events).
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// Which octree this is (unique per octree made; a clone keeps it).
    pub fn id(&self) -> u64 {
        self.id
    }

    /// From now on, keep the effective events of [`sync`](Self::sync) and
    /// [`apply`](Self::apply) for a twin on a device (made from the octree
    /// as it is now), until [`take_device_events`](Self::take_device_events).
    pub fn log_for_device(&mut self) {
        self.device_events = Some(vec![]);
    }

    /// The effective events since the last call (or since
    /// [`log_for_device`](Self::log_for_device)), for the device twin's
    /// update pass ([`device::DeviceOctree::update`]).
    pub fn take_device_events(&mut self) -> Vec<Event> {
        self.device_events
            .as_mut()
            .map(std::mem::take)
            .unwrap_or_default()
    }

    /// Filter then pass: [`effective`](Self::effective) events through
    /// [`pass`](Self::pass) and [`pass_ranges`](Self::pass_ranges) without
    /// voxels (mapped bricks keep their statistics ranges; evicted ones
    /// drop what was read of them).
    pub fn apply(&mut self, events: &[Event]) {
        let e = self.effective(events);
        self.pass(&e);
        self.pass_ranges(&e, None);
        self.logged(&e);
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

/// Node ranges from the resident voxels (see the module's documentation).
impl Octree {
    /// Bricks `[lo, hi)` per axis of level `l` that leaf `leaf` overlaps:
    /// the inverse of [`overlap`] (the same integer test).
    pub fn bricks_of_leaf(&self, l: usize, leaf: Dims3) -> (Dims3, Dims3) {
        let d = self.depth;
        let (dims, brick) = (self.dims[l], self.brick);
        let (num, den) = self.span(l);
        let mut lo = [0; 3];
        let mut hi = [0; 3];
        for a in 0..3 {
            // The leaf's voxels [v0, v1): its continuous coordinates
            // [i·s/2^d, (i + 1)·s/2^d), s = num/den, widened to voxels.
            let v0 = (leaf[a] * num[a]) / (den[a] << d);
            let v1 = ((leaf[a] + 1) * num[a]).div_ceil(den[a] << d);
            lo[a] = v0 / brick[a];
            hi[a] = v1.div_ceil(brick[a]).min(dims[a].div_ceil(brick[a]));
        }
        (lo, hi)
    }

    /// The statistics range of brick `b` of level `l`, channel `c` (NaN:
    /// unknown).
    #[inline]
    fn stat(&self, l: usize, c: usize, b: Dims3) -> [f32; 2] {
        match &self.stats[l] {
            Some(r) => r.get(c, b),
            None => [f32::NAN; 2],
        }
    }

    /// Leaf `leaf`'s range for channel `c` at level `l`: the union over
    /// its bricks of their ranges in it (read) or statistics.
    fn leaf_range(&self, l: usize, c: usize, leaf: Dims3) -> [f32; 2] {
        let (lo, hi) = self.bricks_of_leaf(l, leaf);
        let mut acc = [f32::INFINITY, f32::NEG_INFINITY];
        for z in lo[0]..hi[0] {
            for y in lo[1]..hi[1] {
                for x in lo[2]..hi[2] {
                    let b = [z, y, x];
                    let key = BrickKey::new(l as u8, c as u16, b.map(|v| v as u32));
                    let r = match self.resident.get(&key.pack()) {
                        Some(lr) => lr.get(leaf),
                        None => self.stat(l, c, b),
                    };
                    acc = union(acc, r);
                    if acc[0].is_nan() {
                        return acc;
                    }
                }
            }
        }
        acc
    }

    /// The ranges of brick `key` in the leaves it overlaps from what `vm`
    /// maps for it (`None`: unmapped, or no apron to bound the samples).
    fn read_brick(&self, key: BrickKey, vm: &VirtualMemory) -> Option<LeafRanges> {
        let l = key.level as usize;
        let b = key.brick.map(|v| v as u64);
        let (lo, hi) = self.leaves_of(l, b);
        let e = [0, 1, 2].map(|a| hi[a] - lo[a]);
        let leaves = (e[0] * e[1] * e[2]) as usize;
        let one = |v: f32| {
            Some(LeafRanges {
                lo,
                hi,
                range: vec![[v, v]],
            })
        };
        let voxels = match vm.peek(key) {
            BrickRef::Unmapped => return None,
            BrickRef::Empty => return one(0.0),
            BrickRef::Constant(v) => return one(v),
            BrickRef::Data { voxels, .. } => voxels,
        };
        let apron = vm.config().apron;
        if apron == 0 {
            return None;
        }
        let (d, dims, brick) = (self.depth, self.dims[l], self.brick);
        let (num, den) = self.span(l);
        let padded = vm.padded();
        // Per axis and leaf: the voxels read, as local indices `[s, t]`
        // in the padded brick (empty when s > t).
        let spans: Vec<Vec<(usize, usize)>> = (0..3)
            .map(|a| {
                let p0 = (b[a] * brick[a]) as i64 - apron as i64;
                let p1 = p0 + padded[a] as i64 - 1;
                (lo[a]..hi[a])
                    .map(|i| {
                        let g0 = ((i * num[a]) / (den[a] << d)) as i64 - 1;
                        let g1 = ((i + 1) * num[a]).div_ceil(den[a] << d) as i64;
                        let s = g0.max(0).max(p0);
                        let t = g1.min(dims[a] as i64 - 1).min(p1);
                        if t < s {
                            (1, 0) // nothing (cannot happen for an overlapping brick)
                        } else {
                            ((s - p0) as usize, (t - p0) as usize)
                        }
                    })
                    .collect()
            })
            .collect();
        let dtype: DType = vm.dtype();
        let mut range = Vec::with_capacity(leaves);
        dispatch_dtype!(dtype, T => {
            let v = cast_slice::<T>(voxels);
            for &(z0, z1) in &spans[0] {
                for &(y0, y1) in &spans[1] {
                    for &(x0, x1) in &spans[2] {
                        let (mut mn, mut mx) = (f32::INFINITY, f32::NEG_INFINITY);
                        for z in z0..=z1 {
                            for y in y0..=y1 {
                                let row = (z * padded[1] + y) * padded[2];
                                for &s in &v[row + x0..=row + x1] {
                                    let f = <T as Sample>::to_f32(s);
                                    mn = mn.min(f);
                                    mx = mx.max(f);
                                }
                            }
                        }
                        range.push(if mn > mx { [f32::NAN; 2] } else { widen([mn, mx]) });
                    }
                }
            }
        });
        Some(LeafRanges { lo, hi, range })
    }

    /// The range pass: for the map events in `events` (which must be
    /// [`effective`](Self::effective)) whose values `vm` gives, their
    /// ranges in the leaves they overlap are read; evict events drop them;
    /// the leaves changed are recomputed, then their ancestors as the
    /// union of their children. Without `vm` mapped bricks keep their
    /// statistics.
    pub fn pass_ranges(&mut self, events: &[Event], vm: Option<&VirtualMemory>) {
        let (nl, ch, d) = (self.levels(), self.channels, self.depth);
        let n = 1u64 << d;
        // (leaf · ch + c) · nl + l
        let mut touched: Vec<u64> = vec![];
        for e in events {
            let k = e.key.pack();
            let changed = if e.mapped {
                match vm.and_then(|vm| self.read_brick(e.key, vm)) {
                    Some(r) => self.resident.insert(k, r).is_none(),
                    None => false,
                }
            } else {
                self.resident.remove(&k).is_some()
            };
            if !changed {
                continue;
            }
            let (l, c) = (e.key.level as usize, e.key.channel as usize);
            let (lo, hi) = self.leaves_of(l, e.key.brick.map(|v| v as u64));
            for z in lo[0]..hi[0] {
                for y in lo[1]..hi[1] {
                    for x in lo[2]..hi[2] {
                        let leaf = (z * n + y) * n + x;
                        touched.push((leaf * ch as u64 + c as u64) * nl as u64 + l as u64);
                    }
                }
            }
        }
        touched.sort_unstable();
        touched.dedup();
        let leaf0 = node_offset(d);
        let mut dirty: Vec<u64> = vec![]; // (node at depth dd · ch + c) · nl + l
        for &t in &touched {
            let l = (t % nl as u64) as usize;
            let c = (t / nl as u64 % ch as u64) as usize;
            let leaf = t / nl as u64 / ch as u64;
            let r = self.leaf_range(l, c, [leaf / (n * n), leaf / n % n, leaf % n]);
            let i = ((leaf0 + leaf as usize) * ch + c) * nl + l;
            if !same(self.range[i], r) {
                self.range[i] = r;
                dirty.push(t);
            }
        }
        for dd in (0..d).rev() {
            let m = 1u64 << (dd + 1);
            let pm = m / 2;
            let mut parents: Vec<u64> = dirty
                .iter()
                .map(|&t| {
                    let cl = t % (ch * nl) as u64;
                    let node = t / (ch * nl) as u64;
                    let (z, y, x) = (node / (m * m), node / m % m, node % m);
                    (((z / 2) * pm + y / 2) * pm + x / 2) * (ch * nl) as u64 + cl
                })
                .collect();
            parents.sort_unstable();
            parents.dedup();
            dirty.clear();
            for &t in &parents {
                let l = (t % nl as u64) as usize;
                let c = (t / nl as u64 % ch as u64) as usize;
                let p = t / (ch * nl) as u64;
                let (z, y, x) = (p / (pm * pm), p / pm % pm, p % pm);
                let mut acc = [f32::INFINITY, f32::NEG_INFINITY];
                for k in 0..8u64 {
                    let cc = [2 * z + (k >> 2), 2 * y + (k >> 1 & 1), 2 * x + (k & 1)];
                    acc = union(acc, self.range_of(self.node(dd + 1, cc), c, l));
                }
                let i = (self.node(dd, [z, y, x]) * ch + c) * nl + l;
                if !same(self.range[i], acc) {
                    self.range[i] = acc;
                    dirty.push(t);
                }
            }
            if dirty.is_empty() {
                break;
            }
        }
    }

    /// Bricks whose values were read (for tests and figures).
    pub fn read_bricks(&self) -> usize {
        self.resident.len()
    }
}

/// A range read from voxels, widened for the rounding of trilinear
/// interpolation: by `max(|lo|, |hi|)·2⁻²⁰` on each side when `lo < hi`
/// (one value is exact).
#[inline]
pub fn widen(r: [f32; 2]) -> [f32; 2] {
    if r[0] < r[1] {
        let m = r[0].abs().max(r[1].abs()) * (1.0 / (1u32 << 20) as f32);
        [r[0] - m, r[1] + m]
    } else {
        r
    }
}

/// Equal ranges, NaN equal to NaN.
#[inline]
fn same(a: [f32; 2], b: [f32; 2]) -> bool {
    a[0].to_bits() == b[0].to_bits() && a[1].to_bits() == b[1].to_bits()
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
/// (edge `brick` voxels) of a level of `dims` voxels overlaps, the level
/// spanning `num / den` of its voxels across the extent (`span`,
/// [`Octree::span`]; `(dims, [1; 3])` for level 0).
pub fn overlap(
    depth: u32,
    dims: Dims3,
    span: (Dims3, Dims3),
    brick: Dims3,
    b: Dims3,
) -> (Dims3, Dims3) {
    let n = 1u64 << depth;
    let (num, den) = span;
    let mut lo = [0; 3];
    let mut hi = [0; 3];
    for a in 0..3 {
        let v0 = b[a] * brick[a];
        let v1 = ((b[a] + 1) * brick[a]).min(dims[a]);
        // Leaf i covers the continuous coordinates [i·s/n, (i + 1)·s/n),
        // s = num/den: leaves with i·num < v1·n·den and v0·n·den <
        // (i + 1)·num.
        lo[a] = ((v0 * n * den[a]) / num[a]).min(n);
        hi[a] = (v1 * n * den[a]).div_ceil(num[a]).min(n);
    }
    (lo, hi)
}

#[cfg(test)]
mod tests;
