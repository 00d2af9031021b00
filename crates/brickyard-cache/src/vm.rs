//! The virtual memory for voxels, on the CPU: a multi-level,
//! multi-resolution page-table hierarchy over a brick pool, with usage
//! tracking, LRU by order-preserving compaction, bounded request collection
//! and the update step. It is written as a sequence of data-parallel passes
//! (usage marking, compaction, request reduction, update) so that it is the
//! reference twin of the GPU kernels.
//!
//! Over 800 lines: its passes share the slot sets and tables; kept whole as the kernels' twin.
//!
//! Addresses are `(level, channel, p)` with `p ∈ [0, 1]³` the normalized
//! position in the real volume (`[z, y, x]`); the page tables are addressed
//! with the virtual position derived per level (equations 1–3 and the
//! real/virtual correction of `brickyard_core::vm`).
//!
//! Frame protocol:
//! 1. [`VirtualMemory::begin_frame`];
//! 2. consumers call [`VirtualMemory::sample`] (from any number of threads,
//!    each with its own [`Requests`]); misses fall back to the finest
//!    resident coarser level and are recorded as requests;
//! 3. [`VirtualMemory::end_frame`] merges the requests into a capped,
//!    prioritized list and compacts the LRU lists;
//! 4. bricks delivered by the loader are written with
//!    [`VirtualMemory::insert`] (evict from the LRU tail, write, reference),
//!    at most `upload_bytes_per_frame` per frame.

use crate::brick::{BrickContent, BrickKey, LoadedBrick};
use crate::cells::{cell_ranges, CellGrid};
use brickyard_core::cast_slice;
use brickyard_core::vm::{PageEntry, PageFlag, VirtualLayout};
use brickyard_core::{dispatch_dtype, DType, Dims3, Sample};
use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;

/// Configuration of a virtual memory. All budgets are hard limits.
#[derive(Debug, Clone)]
pub struct VmConfig {
    /// Brick size (without apron), `[z, y, x]`.
    pub brick: Dims3,
    /// Apron voxels on each side of a brick in the pool (≥ 1 for trilinear).
    pub apron: u64,
    /// Block size of the intermediate page tables.
    pub pt_block: Dims3,
    /// Largest directory (entries per channel) before another page-table
    /// level is added.
    pub max_dir_entries: u64,
    /// Bytes of the brick pool: at most; a pool never has more slots than
    /// the volume has bricks (all levels and channels).
    pub pool_bytes: u64,
    /// Blocks in each intermediate page-table cache.
    pub pt_cache_blocks: u64,
    /// Requests reported per frame (global cap).
    pub request_cap: usize,
    /// Brick bytes written into the pool per frame.
    pub upload_bytes_per_frame: u64,
}

impl Default for VmConfig {
    fn default() -> Self {
        VmConfig {
            brick: [32; 3],
            apron: 1,
            pt_block: [16; 3],
            max_dir_entries: 1 << 15,
            pool_bytes: 256 << 20,
            pt_cache_blocks: 512,
            request_cap: 256,
            upload_bytes_per_frame: 64 << 20,
        }
    }
}

impl VmConfig {
    /// Bytes of one pool slot for voxels of `dtype`: the brick with its
    /// apron and its cells' value ranges.
    pub fn slot_bytes(&self, dtype: DType) -> u64 {
        let padded: u64 = self.brick.iter().map(|b| b + 2 * self.apron).product();
        let cells = CellGrid::new(self.brick).len() * std::mem::size_of::<[f32; 2]>();
        padded * dtype.size() as u64 + cells as u64
    }

    /// Slots of the pool for a volume of `bricks` bricks (all levels and
    /// channels) of `dtype`: its bytes over a slot's, and no more than one
    /// per brick (more would never be used: a small volume takes a small
    /// pool, on a device too, whatever the budget).
    pub fn pool_slots(&self, dtype: DType, bricks: u64) -> u64 {
        (self.pool_bytes / self.slot_bytes(dtype)).min(bricks)
    }
}

/// Which entry references a slot or block (so that evicting it can unmap
/// that entry).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Owner {
    None,
    /// Index into the directory (channel-major).
    Dir(u32),
    /// Cache level `n` (1-based intermediate level), block, entry in block.
    Pt(u8, u32, u32),
}

/// A set of slots with usage timestamps and an LRU order.
struct SlotSet {
    grid: [u32; 3],
    usage: Vec<AtomicU32>,
    /// Brick pool only: the last frame in which the slot's brick served a
    /// sample at the level that sample asked for. A slot used in the
    /// current frame but not exactly was only a stand-in for finer data.
    exact: Vec<AtomicU32>,
    /// Brick pool only: level of the brick in the slot.
    level: Vec<u8>,
    /// The finest level for which no stand-in was found this frame (255:
    /// none failed yet), so a saturated pool is scanned once per frame.
    stand_in_failed: u8,
    /// Most recently used first.
    lru: Vec<u32>,
    /// Buffers of the compaction, kept between frames.
    spare: [Vec<u32>; 3],
    owner: Vec<Owner>,
    /// Slots whose owner disappeared (orphans) or that were never used.
    free: Vec<u32>,
    /// Next eviction candidate, counting from the tail of `lru`.
    cursor: usize,
    /// Slots never taken for another brick or block (the always-resident
    /// coarsest levels and the page-table blocks on their paths).
    pinned: Vec<bool>,
}

impl SlotSet {
    fn new(count: u64) -> SlotSet {
        // Exactly `count` slots (up to the grid's limit), ids row-major in a
        // grid that covers them; only the last row or layer is partly used.
        let max = brickyard_core::vm::MAX_SLOTS_PER_AXIS as u64;
        let count = count.min(max * max * max);
        let gx = count.clamp(1, max);
        let gy = count.div_ceil(gx).clamp(1, max);
        let gz = count.div_ceil(gx * gy).clamp(1, max);
        let n = count as u32;
        SlotSet {
            grid: [gz as u32, gy as u32, gx as u32],
            usage: (0..n).map(|_| AtomicU32::new(0)).collect(),
            exact: (0..n).map(|_| AtomicU32::new(0)).collect(),
            level: vec![0; n as usize],
            stand_in_failed: u8::MAX,
            lru: (0..n).collect(),
            spare: Default::default(),
            owner: vec![Owner::None; n as usize],
            free: (0..n).rev().collect(),
            cursor: 0,
            pinned: vec![false; n as usize],
        }
    }
    fn len(&self) -> usize {
        self.owner.len()
    }
    fn coords(&self, id: u32) -> [u32; 3] {
        let [_, gy, gx] = self.grid;
        [id / (gy * gx), (id / gx) % gy, id % gx]
    }
    fn id(&self, c: [u32; 3]) -> u32 {
        (c[0] * self.grid[1] + c[1]) * self.grid[2] + c[2]
    }
    /// Order-preserving compaction: slots used in `frame` first, then
    /// those stamped in the frame before, then the others, each group in
    /// its previous order. (A brick written after the previous frame's
    /// compaction, stamped with that frame, still sits where the slot it
    /// took was, at the tail: without the middle group it would be the
    /// next to go, and a view drawn in turn with others would lose its
    /// bricks to theirs before it is drawn again.)
    fn compact(&mut self, frame: u32) {
        // One pass; the buffers are kept from frame to frame.
        let before = frame.wrapping_sub(1);
        let [mut out, mut mid, mut rest] = std::mem::take(&mut self.spare);
        out.clear();
        mid.clear();
        rest.clear();
        for &s in &self.lru {
            match self.usage[s as usize].load(Ordering::Relaxed) {
                u if u == frame => out.push(s),
                u if u == before => mid.push(s),
                _ => rest.push(s),
            }
        }
        out.extend_from_slice(&mid);
        out.extend_from_slice(&rest);
        let old = std::mem::replace(&mut self.lru, out);
        self.spare = [old, mid, rest];
        self.cursor = 0;
        self.stand_in_failed = u8::MAX;
    }

    /// When [`take`](Self::take) finds every slot in use: the least
    /// recently used slot that only stood in, this frame, for finer data
    /// and holds a brick coarser than `level` — the brick to be written
    /// replaces what it stood in for. Slots used at their own level are
    /// never taken, so the exact working set of a view that fits the pool
    /// always completes.
    fn take_stand_in(&mut self, frame: u32, level: u8) -> Option<u32> {
        if level >= self.stand_in_failed {
            return None;
        }
        // The finest such stand-in (least recently used among equals):
        // what it covered falls back to a coarser one still resident,
        // rather than to nothing.
        let found = self
            .lru
            .iter()
            .rev()
            .copied()
            .filter(|&s| {
                let s = s as usize;
                self.owner[s] != Owner::None
                    && !self.pinned[s]
                    && self.usage[s].load(Ordering::Relaxed) == frame
                    && self.exact[s].load(Ordering::Relaxed) != frame
                    && self.level[s] > level
            })
            .min_by_key(|&s| self.level[s as usize]);
        if found.is_none() {
            self.stand_in_failed = level;
        }
        found
    }
    /// A slot that may be (re)used now: a free one, else the least recently
    /// used one not used in `frame`. `None` when every slot is in use.
    fn take(&mut self, frame: u32) -> Option<u32> {
        while let Some(s) = self.free.pop() {
            if self.owner[s as usize] == Owner::None
                && !self.pinned[s as usize]
                && self.usage[s as usize].load(Ordering::Relaxed) != frame
            {
                return Some(s);
            }
        }
        // Walk from the tail; slots used this frame (including ones just
        // filled from the free list) are skipped. The cursor only moves
        // forward, so a frame costs O(slots) at most.
        while self.cursor < self.lru.len() {
            let s = self.lru[self.lru.len() - 1 - self.cursor];
            self.cursor += 1;
            if self.usage[s as usize].load(Ordering::Relaxed) != frame && !self.pinned[s as usize] {
                return Some(s);
            }
        }
        None
    }
}

/// Requests collected by one consumer thread during a frame. Memory is
/// bounded by its capacity, independent of the volume size; keys beyond
/// it are dropped (and counted).
#[derive(Debug, Clone)]
pub struct Requests {
    map: HashMap<u64, u32>,
    cap: usize,
    /// Misses that could not be recorded because the collector was full.
    pub dropped: u64,
}

impl Requests {
    pub fn with_capacity(cap: usize) -> Requests {
        Requests {
            // Grown on demand up to `cap` (large caps are common in batch
            // renders; most collectors see few misses).
            map: HashMap::with_capacity(cap.min(1024)),
            cap,
            dropped: 0,
        }
    }
    #[inline]
    pub fn add(&mut self, key: BrickKey, samples: u32) {
        let k = key.pack();
        if let Some(c) = self.map.get_mut(&k) {
            *c += samples;
        } else if self.map.len() < self.cap {
            self.map.insert(k, samples);
        } else {
            self.dropped += 1;
        }
    }
    pub fn len(&self) -> usize {
        self.map.len()
    }
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }
    /// The bricks recorded and their samples, in no particular order.
    pub fn iter(&self) -> impl Iterator<Item = (BrickKey, u32)> + '_ {
        self.map.iter().map(|(&k, &n)| (BrickKey::unpack(k), n))
    }
    /// Bytes this collector may use at most.
    pub fn max_bytes(&self) -> u64 {
        // hashbrown: key + value + control byte per bucket, buckets ≤ 2 × cap.
        (self.cap as u64 * 2) * (8 + 4 + 1)
    }
}

/// How a sample was served.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lookup {
    pub value: f32,
    /// The level that served the sample (`None`: nothing resident at all).
    pub level: Option<u8>,
}

/// What [`VirtualMemory::brick`] finds for a brick.
#[derive(Debug, Clone, Copy)]
pub enum BrickRef<'a> {
    /// Not mapped at this level: request it, use a coarser level meanwhile.
    Unmapped,
    /// Every voxel (apron included) is 0.
    Empty,
    /// Every voxel (apron included) has this value.
    Constant(f32),
    /// Resident: the padded brick's bytes in the pool and its slot.
    Data { voxels: &'a [u8], slot: u32 },
}

/// Per-frame figures.
#[derive(Debug, Clone, Default)]
pub struct FrameReport {
    pub frame: u32,
    /// The capped, prioritized request list (most wanted first).
    pub requests: Vec<BrickKey>,
    /// Distinct bricks asked for before the cap.
    pub requested: usize,
    pub dropped: u64,
    pub resident_bricks: usize,
    pub resident_pt_blocks: Vec<usize>,
    /// Pool slots whose brick served samples at its own level this frame
    /// (the part of the pool the view's working set fills; pinned slots
    /// only when used so).
    pub exact_slots: usize,
    /// Requests for bricks that failed to load, left out of the list
    /// (their regions are drawn from coarser data).
    pub failed_requested: usize,
}

/// Figures of one insert step.
#[derive(Debug, Clone, Default)]
pub struct InsertReport {
    pub inserted: usize,
    pub flagged: usize,
    pub bytes_uploaded: u64,
    pub evicted_bricks: usize,
    pub evicted_pt_blocks: usize,
    pub orphans_reclaimed: usize,
    /// Bricks that found no slot (every slot in use this frame); dropped,
    /// they will be requested again.
    pub deferred: usize,
    /// Bricks consumed from the front of the input; the rest did not fit
    /// this frame's upload budget and should be offered again next frame.
    pub processed: usize,
    /// Evicted bricks that a frame among the last
    /// [`set_in_use_frames`](VirtualMemory::set_in_use_frames) used at
    /// their own level: views drawn in turn whose bricks together do not
    /// fit the pool take each other's.
    pub evicted_in_use: usize,
}

/// The virtual memory.
pub struct VirtualMemory {
    layout: VirtualLayout,
    /// Per level, its voxels across the extent (`level_span`).
    spans: Vec<[f64; 3]>,
    cfg: VmConfig,
    channels: usize,
    dtype: DType,
    frame: u32,
    /// Frames whose exact use makes an evicted brick count as in use.
    in_use_frames: u32,
    uploaded: u64,
    /// Channel-major directory.
    dir: Vec<PageEntry>,
    dir_len: usize,
    /// Intermediate page-table caches `n = 1 .. nmax-1`: entries and slots.
    pt: Vec<(Vec<PageEntry>, SlotSet)>,
    pt_block_len: Vec<usize>,
    /// Brick pool (8-byte words so that every slot is aligned for any
    /// sample type: slot offsets are multiples of the padded brick's
    /// voxel count times the sample size).
    pool: Vec<u64>,
    /// Per pool slot, the value ranges of its brick's cells
    /// ([`crate::cells`]), `cell_grid.len()` entries a slot. Counted in the
    /// pool's budget.
    cells: Vec<[f32; 2]>,
    cell_grid: CellGrid,
    slots: SlotSet,
    padded: [usize; 3],
    brick_bytes: usize,
    merged: Requests,
    /// Bricks that failed to load (packed keys): never requested again;
    /// samples there fall back to coarser data.
    failed: HashSet<u64>,
    /// Change tracking for a device mirror (`None`: off): indices into
    /// [`VirtualMemory::tables`] of entries set, and pool slots written,
    /// since the last [`VirtualMemory::take_changes`].
    changes: Option<(Vec<u32>, Vec<u32>)>,
    /// Residency log for an index kept beside the page tables (`None`:
    /// off): keys mapped since the last [`VirtualMemory::take_residency`],
    /// and whether any mapping was removed since.
    residency: Option<(Vec<BrickKey>, bool)>,
}

/// What changed in a virtual memory since the last
/// [`VirtualMemory::take_changes`]: page-table entries (index into the
/// concatenated tables, new value; each index once) and pool slots whose
/// brick was written.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct VmChanges {
    pub entries: Vec<(u32, PageEntry)>,
    pub slots: Vec<u32>,
}

/// `u64` words viewed as bytes.
fn words_as_bytes(w: &[u64]) -> &[u8] {
    // SAFETY: same memory, 8 bytes a word, any bit pattern is a valid u8.
    unsafe { std::slice::from_raw_parts(w.as_ptr() as *const u8, w.len() * 8) }
}

fn entry_kind(e: &PageEntry, dtype: DType) -> Kind {
    match e.flag() {
        PageFlag::Mapped => Kind::Mapped(e.slot().expect("mapped entries carry a slot")),
        PageFlag::Empty => Kind::Empty,
        PageFlag::Constant => Kind::Constant(e.constant_value(dtype).unwrap_or(0.0) as f32),
        PageFlag::Unmapped => Kind::Unmapped,
    }
}

enum Kind {
    Unmapped,
    Mapped([u32; 3]),
    Empty,
    Constant(f32),
}

impl VirtualMemory {
    /// A virtual memory for a volume with `levels` (voxels per level,
    /// `[z, y, x]`), `channels` and `dtype`.
    pub fn new(levels: &[Dims3], channels: usize, dtype: DType, cfg: VmConfig) -> VirtualMemory {
        let layout = VirtualLayout::auto(
            levels.to_vec(),
            cfg.brick,
            cfg.pt_block,
            cfg.max_dir_entries,
        );
        let dir_len = layout.dir_dims.iter().product::<u64>() as usize;
        let nmax = layout.nmax();
        let mut pt = vec![];
        let mut pt_block_len = vec![];
        for n in 1..nmax {
            let b = layout.pt_blocks[n - 1];
            let len = b.iter().product::<u64>() as usize;
            // No more blocks than the entries of the level above can point
            // to in every channel (a small volume under a large cache).
            let most: u64 = layout
                .real
                .iter()
                .map(|r| r[n - 1].iter().product::<u64>())
                .sum::<u64>()
                * channels.max(1) as u64;
            let slots = SlotSet::new(cfg.pt_cache_blocks.min(most.max(1)));
            pt.push((vec![PageEntry::unmapped(); slots.len() * len], slots));
            pt_block_len.push(len);
        }
        let padded = cfg.brick.map(|b| (b + 2 * cfg.apron) as usize);
        let brick_bytes = padded.iter().product::<usize>() * dtype.size();
        let cell_grid = CellGrid::new(cfg.brick);
        let bricks = layout.brick_count() * channels.max(1) as u64;
        let slots = SlotSet::new(cfg.pool_slots(dtype, bricks));
        VirtualMemory {
            merged: Requests::with_capacity(cfg.request_cap * 8),
            spans: (0..layout.levels.len())
                .map(|l| brickyard_core::level_span(&layout.levels, l))
                .collect(),
            layout,
            channels,
            dtype,
            frame: 1,
            in_use_frames: 1,
            uploaded: 0,
            dir: vec![PageEntry::unmapped(); dir_len * channels],
            dir_len,
            pt,
            pt_block_len,
            pool: vec![0u64; (slots.len() * brick_bytes).div_ceil(8)],
            cells: vec![[f32::NAN; 2]; slots.len() * cell_grid.len()],
            cell_grid,
            slots,
            padded,
            brick_bytes,
            cfg,
            failed: HashSet::new(),
            changes: None,
            residency: None,
        }
    }

    /// Record changes for [`take_changes`](Self::take_changes) from now on
    /// (a device mirror turns this on; it costs a few bytes per change
    /// until taken).
    pub fn track_changes(&mut self) {
        self.changes.get_or_insert_with(Default::default);
    }

    /// Log residency from now on for [`take_residency`](Self::take_residency).
    pub fn track_residency(&mut self) {
        self.residency.get_or_insert_with(Default::default);
    }

    /// Since the last call (tracking must be on): the keys mapped (data,
    /// EMPTY or CONSTANT; a key may since have been unmapped again), and
    /// whether any mapping was removed (a brick evicted, or page-table
    /// blocks orphaned with what lies below them).
    pub fn take_residency(&mut self) -> (Vec<BrickKey>, bool) {
        match self.residency.as_mut() {
            Some((keys, lost)) => (std::mem::take(keys), std::mem::replace(lost, false)),
            None => (vec![], false),
        }
    }

    /// The changes since the last call (tracking must be on), each entry
    /// and slot once, in index order.
    pub fn take_changes(&mut self) -> VmChanges {
        let Some((entries, slots)) = self.changes.as_mut() else {
            return VmChanges::default();
        };
        let (mut e, mut s) = (std::mem::take(entries), std::mem::take(slots));
        e.sort_unstable();
        e.dedup();
        s.sort_unstable();
        s.dedup();
        let tables = self.tables();
        let offsets = self.table_offsets();
        let entries = e
            .into_iter()
            .map(|i| {
                let t = offsets.partition_point(|&o| o <= i) - 1;
                (i, tables[t][(i - offsets[t]) as usize])
            })
            .collect();
        VmChanges { entries, slots: s }
    }

    /// The page tables: the directory (channel-major, `channels ×
    /// directory entries`), then the cache of each intermediate level
    /// (`blocks × block entries`, blocks in slot order).
    pub fn tables(&self) -> Vec<&[PageEntry]> {
        std::iter::once(&self.dir[..])
            .chain(self.pt.iter().map(|(e, _)| &e[..]))
            .collect()
    }

    /// First index of each table of [`tables`](Self::tables) in their
    /// concatenation, then the total.
    pub fn table_offsets(&self) -> Vec<u32> {
        let mut o = vec![0u32];
        for t in self.tables() {
            o.push(o.last().copied().unwrap_or(0) + t.len() as u32);
        }
        o
    }

    /// Slots per axis `[z, y, x]` of the brick pool (`brick`) or of the
    /// cache of intermediate level `n` (`1 ≤ n < nmax`): a slot id is
    /// `(z·gy + y)·gx + x` of the coordinates a page entry holds.
    pub fn slot_grid(&self, n: Option<usize>) -> [u32; 3] {
        match n {
            None => self.slots.grid,
            Some(n) => self.pt[n - 1].1.grid,
        }
    }

    /// Entries in one block of intermediate level `n`.
    pub fn pt_block_len(&self, n: usize) -> usize {
        self.pt_block_len[n - 1]
    }

    /// Entries of one channel's directory.
    pub fn dir_len(&self) -> usize {
        self.dir_len
    }

    /// Pool slots that hold a brick.
    pub fn resident_slots(&self) -> Vec<u32> {
        (0..self.slots.len() as u32)
            .filter(|&s| self.slots.owner[s as usize] != Owner::None)
            .collect()
    }

    /// The padded brick in pool slot `s` (native-endian voxels).
    pub fn slot_voxels(&self, s: u32) -> &[u8] {
        let bb = self.brick_bytes;
        &self.pool()[s as usize * bb..(s as usize + 1) * bb]
    }

    /// Index in the concatenated tables of an owner's entry.
    fn table_index(&self, o: Owner) -> Option<u32> {
        match o {
            Owner::None => None,
            Owner::Dir(i) => Some(i),
            Owner::Pt(n, b, e) => {
                let base: usize = self.dir.len()
                    + self.pt[..n as usize - 1]
                        .iter()
                        .map(|(t, _)| t.len())
                        .sum::<usize>();
                let len = self.pt_block_len[n as usize - 1];
                Some((base + b as usize * len + e as usize) as u32)
            }
        }
    }

    pub fn layout(&self) -> &VirtualLayout {
        &self.layout
    }
    pub fn config(&self) -> &VmConfig {
        &self.cfg
    }
    pub fn frame(&self) -> u32 {
        self.frame
    }
    /// Bricks currently in the pool.
    pub fn resident_bricks(&self) -> usize {
        self.slots
            .owner
            .iter()
            .filter(|o| **o != Owner::None)
            .count()
    }

    /// Number of brick slots in the pool.
    pub fn pool_slots(&self) -> usize {
        self.slots.len()
    }
    /// Bytes of the pool: its slots, each a padded brick and the value
    /// ranges of its cells.
    pub fn pool_bytes(&self) -> usize {
        self.slots.len() * self.slot_bytes()
    }

    /// Bytes of one pool slot: a padded brick and its cells' value ranges
    /// ([`VmConfig::slot_bytes`]).
    pub fn slot_bytes(&self) -> usize {
        self.cfg.slot_bytes(self.dtype) as usize
    }

    /// Bytes of the bricks in the pool.
    fn brick_pool_bytes(&self) -> usize {
        self.slots.len() * self.brick_bytes
    }

    /// How bricks are cut into cells for [`cell_ranges`](Self::cell_ranges).
    pub fn cell_grid(&self) -> CellGrid {
        self.cell_grid
    }

    fn pool(&self) -> &[u8] {
        &words_as_bytes(&self.pool)[..self.brick_pool_bytes()]
    }

    fn pool_mut(&mut self) -> &mut [u8] {
        let n = self.brick_pool_bytes();
        // SAFETY: as in `pool`; `n ≤ 8 · pool.len()`.
        unsafe { std::slice::from_raw_parts_mut(self.pool.as_mut_ptr() as *mut u8, n) }
    }

    /// Sample type of the pool.
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// Padded brick size `[z, y, x]` (brick + apron on both sides).
    pub fn padded(&self) -> [usize; 3] {
        self.padded
    }

    /// Number of levels.
    pub fn levels(&self) -> usize {
        self.layout.levels.len()
    }

    /// Resolve brick `brick` (brick coordinates, `[z, y, x]`) of level `l`,
    /// channel `c` for a consumer that walks bricks instead of sampling
    /// point by point: marks it (and its page-table blocks) used this frame
    /// and returns what its entry says. A resident brick comes with its
    /// padded voxels (sample type [`dtype`](Self::dtype), x fastest, aligned
    /// for that type): voxel `v` of the level, with `v` inside the brick or
    /// one apron voxel around it, is at local index
    /// `v − brick·B + apron` per axis. Nothing is requested: the consumer
    /// adds misses to its [`Requests`] itself.
    ///
    /// `exact` says whether the consumer samples the brick at its own level
    /// (rather than as a stand-in for a finer one); see
    /// [`mark_exact`](Self::mark_exact).
    pub fn brick(&self, l: usize, c: usize, brick: [u64; 3], exact: bool) -> BrickRef<'_> {
        let v = [0, 1, 2].map(|a| brick[a] * self.cfg.brick[a]);
        let r = self.brick_ref(self.resolve(l, c, v));
        if let BrickRef::Data { slot, .. } = r {
            self.slots.usage[slot as usize].store(self.frame, Ordering::Relaxed);
            if exact {
                self.mark_exact(slot);
            }
        }
        r
    }

    /// What brick `key`'s entry says, as [`brick`](Self::brick) does, but
    /// without side effects (no usage marks, nothing requested): for
    /// readers of a brick's voxels outside of sampling (the residency
    /// octree's value ranges).
    pub fn peek(&self, key: BrickKey) -> BrickRef<'_> {
        let v = [0, 1, 2].map(|a| key.brick[a] as u64 * self.cfg.brick[a]);
        let e = self.walk(key.level as usize, key.channel as usize, v, false);
        self.brick_ref(entry_kind(&e, self.dtype))
    }

    /// An entry's kind as a consumer sees it (a mapped brick with its
    /// padded voxels in the pool).
    fn brick_ref(&self, kind: Kind) -> BrickRef<'_> {
        match kind {
            Kind::Mapped(slot) => {
                let s = self.slots.id(slot);
                let o = s as usize * self.brick_bytes;
                BrickRef::Data {
                    voxels: &self.pool()[o..o + self.brick_bytes],
                    slot: s,
                }
            }
            Kind::Empty => BrickRef::Empty,
            Kind::Constant(v) => BrickRef::Constant(v),
            Kind::Unmapped => BrickRef::Unmapped,
        }
    }

    /// The value ranges of the cells of the brick in pool slot `slot`
    /// (from [`BrickRef::Data`]): one per cell of [`cell_grid`](Self::cell_grid),
    /// `[z][y][x]`; see [`crate::cells`].
    #[inline]
    pub fn cell_ranges(&self, slot: u32) -> &[[f32; 2]] {
        let n = self.cell_grid.len();
        &self.cells[slot as usize * n..(slot as usize + 1) * n]
    }

    fn write_cells(&mut self, slot: u32) {
        let bb = self.brick_bytes;
        let o = slot as usize * bb;
        let (padded, brick, apron) = (self.padded, self.cfg.brick, self.cfg.apron);
        let n = self.cell_grid.len();
        let c = slot as usize * n;
        let pool = words_as_bytes(&self.pool);
        let out = &mut self.cells[c..c + n];
        dispatch_dtype!(self.dtype, T => {
            cell_ranges(cast_slice::<T>(&pool[o..o + bb]), padded, brick, apron, out)
        });
    }

    /// Record that pool slot `slot` (from [`BrickRef::Data`]) served a
    /// sample at its own level this frame. Bricks used only as stand-ins
    /// for finer, missing ones may be evicted in favour of finer bricks
    /// when the pool is full.
    #[inline]
    pub fn mark_exact(&self, slot: u32) {
        self.slots.exact[slot as usize].store(self.frame, Ordering::Relaxed);
    }

    /// Mark pool slot `slot` as used this frame (and `exact`: used at its
    /// own level), with the page-table blocks on the path to it: what a
    /// walk and sample on the host marks, for samples taken elsewhere (the
    /// device's renderers report the slots they used).
    pub fn mark_used(&self, slot: u32, exact: bool) {
        let Some(&owner) = self.slots.owner.get(slot as usize) else {
            return;
        };
        self.slots.usage[slot as usize].store(self.frame, Ordering::Relaxed);
        if exact {
            self.mark_exact(slot);
        }
        let mut o = owner;
        while let Owner::Pt(n, b, _) = o {
            let set = &self.pt[n as usize - 1].1;
            set.usage[b as usize].store(self.frame, Ordering::Relaxed);
            o = set.owner[b as usize];
        }
    }

    /// A request collector sized for this virtual memory.
    pub fn requests(&self) -> Requests {
        Requests::with_capacity(self.cfg.request_cap * 8)
    }

    /// How many frames, this one included, count for
    /// [`InsertReport::evicted_in_use`]: the views drawn in turn (at
    /// least 1).
    pub fn set_in_use_frames(&mut self, n: u32) {
        self.in_use_frames = n.max(1);
    }

    /// See [`set_in_use_frames`](Self::set_in_use_frames).
    pub fn in_use_frames(&self) -> u32 {
        self.in_use_frames
    }

    /// Start a new frame.
    pub fn begin_frame(&mut self) {
        self.frame += 1;
        self.uploaded = 0;
        self.merged.map.clear();
        self.merged.dropped = 0;
    }

    fn dir_index(&self, l: usize, c: usize, p: [f64; 3]) -> usize {
        let e = self.layout.dir_entry(l, p);
        let d = self.layout.dir_dims;
        c * self.dir_len + ((e[0] * d[1] + e[1]) * d[2] + e[2]) as usize
    }

    fn block_entry(&self, n: usize, l: usize, p: [f64; 3]) -> usize {
        let o = self.layout.offset_in_block(l, n, p);
        let b = self.layout.pt_blocks[n - 1];
        ((o[0] * b[1] + o[1]) * b[2] + o[2]) as usize
    }

    /// Virtual position of the centre of voxel `v` of level `l`.
    fn p_of_voxel(&self, l: usize, v: [u64; 3]) -> [f64; 3] {
        let vv = self.layout.virt[l][self.layout.nmax()];
        [0, 1, 2].map(|a| (v[a] as f64 + 0.5) / vv[a] as f64)
    }

    /// Walk the hierarchy for the brick holding voxel `v` of level `l`.
    /// Marks usage on the way. Returns the final entry kind, or `Unmapped`
    /// at the first missing level.
    fn resolve(&self, l: usize, c: usize, v: [u64; 3]) -> Kind {
        entry_kind(&self.walk(l, c, v, true), self.dtype)
    }

    /// The entry the hierarchy holds for the brick of voxel `v` of level
    /// `l`: the first non-mapped entry on the way down, or the brick's.
    /// `mark`: mark the page-table blocks passed as used this frame.
    fn walk(&self, l: usize, c: usize, v: [u64; 3], mark: bool) -> PageEntry {
        let p = self.p_of_voxel(l, v);
        let mut e = self.dir[self.dir_index(l, c, p)];
        for n in 1..self.layout.nmax() {
            let Kind::Mapped(slot) = entry_kind(&e, self.dtype) else {
                return e;
            };
            let (entries, set) = &self.pt[n - 1];
            let b = set.id(slot);
            if mark {
                set.usage[b as usize].store(self.frame, Ordering::Relaxed);
            }
            e = entries[b as usize * self.pt_block_len[n - 1] + self.block_entry(n, l, p)];
        }
        e
    }

    /// [`walk`](Self::walk) without side effects: the twin of the device's
    /// page-table walk.
    pub fn entry_of(&self, l: usize, c: usize, v: [u64; 3]) -> PageEntry {
        self.walk(l, c, v, false)
    }

    /// Trilinear sample of channel `c` at level `l` with voxel base `base`
    /// (`[z, y, x]`, at most the level's last voxel) and fractions `frac`,
    /// if its brick is mapped (resident or flagged); no fallback, no usage
    /// marks: the twin of the device's sampler.
    pub fn sample_at(&self, l: usize, c: usize, base: [u64; 3], frac: [f32; 3]) -> Option<f32> {
        match entry_kind(&self.entry_of(l, c, base), self.dtype) {
            Kind::Unmapped => None,
            Kind::Empty => Some(0.0),
            Kind::Constant(v) => Some(v),
            Kind::Mapped(slot) => Some(self.trilinear_in(self.slots.id(slot), base, frac)),
        }
    }

    /// Trilinear sample in pool slot `s` at level voxel `base` + `frac`.
    fn trilinear_in(&self, s: u32, base: [u64; 3], frac: [f32; 3]) -> f32 {
        let a = self.cfg.apron as usize;
        let b = self.cfg.brick;
        let local = [0, 1, 2].map(|i| (base[i] % b[i]) as usize + a);
        brickyard_core::trilinear_of(
            |dz, dy, dx| self.voxel(s, [local[0] + dz, local[1] + dy, local[2] + dx]),
            frac,
            true,
        )
    }

    fn key_of(&self, l: usize, c: usize, v: [u64; 3]) -> BrickKey {
        let b = self.cfg.brick;
        BrickKey {
            level: l as u8,
            channel: c as u16,
            brick: [0, 1, 2].map(|a| (v[a] / b[a]) as u32),
        }
    }

    #[inline]
    fn voxel(&self, slot: u32, local: [usize; 3]) -> f32 {
        let [_, py, px] = self.padded;
        let i = (local[0] * py + local[1]) * px + local[2];
        let base = slot as usize * self.brick_bytes;
        let es = self.dtype.size();
        let b = &self.pool()[base + i * es..base + (i + 1) * es];
        dispatch_dtype!(self.dtype, T => { <T as Sample>::from_le(b).to_f64() as f32 })
    }

    /// Sample channel `c` at the normalized real position `p` (`[z, y, x]`)
    /// of level `l`, nearest or trilinear. On a miss the brick is requested
    /// and the finest resident coarser level answers.
    pub fn sample(
        &self,
        l: usize,
        c: usize,
        p: [f64; 3],
        trilinear: bool,
        req: &mut Requests,
    ) -> Lookup {
        let nl = self.layout.levels.len();
        let l0 = l.min(nl - 1);
        // Coarser misses, requested only if nothing serves the sample (a
        // sample served by a stand-in asks for its own level only).
        let mut missed = [None; 32];
        for lv in l0..nl {
            let dims = self.layout.levels[lv];
            // Continuous voxel coordinates (voxel centres at i + 0.5; the
            // level's voxels across the extent: `level_span`).
            let span = self.spans[lv];
            let pos = [0, 1, 2].map(|a| p[a] * span[a]);
            let (base, frac) = if trilinear {
                let q = [0, 1, 2].map(|a| (pos[a] - 0.5).clamp(0.0, (dims[a] - 1) as f64));
                // q ≥ 0 after the clamp: truncation is floor (and avoids a libm call).
                let b = q.map(|x| (x as u64) as f64);
                (
                    [0, 1, 2].map(|a| b[a] as u64),
                    [0, 1, 2].map(|a| (q[a] - b[a]) as f32),
                )
            } else {
                (
                    [0, 1, 2].map(|a| (pos[a].floor().max(0.0) as u64).min(dims[a] - 1)),
                    [0.0; 3],
                )
            };
            match self.resolve(lv, c, base) {
                Kind::Mapped(slot) => {
                    let s = self.slots.id(slot);
                    self.slots.usage[s as usize].store(self.frame, Ordering::Relaxed);
                    if lv == l.min(nl - 1) {
                        self.mark_exact(s);
                    }
                    let value = if trilinear {
                        self.trilinear_in(s, base, frac)
                    } else {
                        let a = self.cfg.apron as usize;
                        let b = self.cfg.brick;
                        self.voxel(s, [0, 1, 2].map(|i| (base[i] % b[i]) as usize + a))
                    };
                    return Lookup {
                        value,
                        level: Some(lv as u8),
                    };
                }
                Kind::Empty => {
                    return Lookup {
                        value: 0.0,
                        level: Some(lv as u8),
                    }
                }
                Kind::Constant(v) => {
                    return Lookup {
                        value: v,
                        level: Some(lv as u8),
                    }
                }
                Kind::Unmapped if lv == l0 => req.add(self.key_of(lv, c, base), 1),
                Kind::Unmapped => missed[lv.min(31)] = Some(self.key_of(lv, c, base)),
            }
        }
        // Nothing resident: request the whole chain so something shows soon.
        for k in missed.iter().flatten() {
            req.add(*k, 1);
        }
        Lookup {
            value: 0.0,
            level: None,
        }
    }

    /// End the frame: merge the collectors into the capped, prioritized
    /// request list (most samples first; ties: coarser level first), and
    /// reorder the LRU lists by compaction.
    pub fn end_frame<'a>(
        &mut self,
        collectors: impl IntoIterator<Item = &'a Requests>,
    ) -> FrameReport {
        self.end_frame_without(collectors, |_| false)
    }

    /// [`end_frame`](Self::end_frame), leaving out of the request list,
    /// before it is capped, the bricks for which `here` is true (bricks
    /// that have arrived and are about to be inserted): the cap goes to
    /// the next most wanted.
    pub fn end_frame_without<'a>(
        &mut self,
        collectors: impl IntoIterator<Item = &'a Requests>,
        here: impl Fn(BrickKey) -> bool,
    ) -> FrameReport {
        let mut dropped = 0;
        for r in collectors {
            dropped += r.dropped;
            for (&k, &n) in &r.map {
                let key = BrickKey::unpack(k);
                self.merged.add(key, n);
            }
        }
        dropped += self.merged.dropped;
        let mut failed_requested = 0;
        let list: Vec<(BrickKey, u32)> = self
            .merged
            .map
            .iter()
            .filter(|(k, _)| {
                let f = self.failed.contains(*k);
                failed_requested += usize::from(f);
                !f
            })
            .map(|(&k, &n)| (BrickKey::unpack(k), n))
            .filter(|(k, _)| !here(*k))
            .collect();
        let requested = list.len();
        let list = crate::bookkeeping::prioritize(list, self.cfg.request_cap);
        let frame = self.frame;
        self.slots.compact(frame);
        for (_, s) in &mut self.pt {
            s.compact(frame);
        }
        let exact_slots = self
            .slots
            .exact
            .iter()
            .zip(&self.slots.owner)
            .filter(|(e, o)| **o != Owner::None && e.load(Ordering::Relaxed) == frame)
            .count();
        FrameReport {
            exact_slots,
            failed_requested,
            frame,
            requests: list.into_iter().map(|(k, _)| k).collect(),
            requested,
            dropped,
            resident_bricks: self
                .slots
                .owner
                .iter()
                .filter(|o| **o != Owner::None)
                .count(),
            resident_pt_blocks: self
                .pt
                .iter()
                .map(|(_, s)| s.owner.iter().filter(|o| **o != Owner::None).count())
                .collect(),
        }
    }

    /// Unmap the entry `o` refers to.
    fn unmap_owner(&mut self, o: Owner) {
        self.set_entry(o, PageEntry::unmapped());
    }

    /// Forget the children of page-table block `b` of cache `n` (after it
    /// lost its owner): their slots become free, recursively, and the
    /// block's entries are cleared so no stale mapping survives.
    fn orphan_children(&mut self, n: usize, b: u32, report: &mut InsertReport) {
        let len = self.pt_block_len[n - 1];
        for i in 0..len {
            let e = self.pt[n - 1].0[b as usize * len + i];
            if let Kind::Mapped(slot) = entry_kind(&e, self.dtype) {
                if n + 1 < self.layout.nmax() {
                    let child = self.pt[n].1.id(slot);
                    self.pt[n].1.owner[child as usize] = Owner::None;
                    self.pt[n].1.free.push(child);
                    self.orphan_children(n + 1, child, report);
                } else {
                    let child = self.slots.id(slot);
                    self.slots.owner[child as usize] = Owner::None;
                    self.slots.free.push(child);
                }
                report.orphans_reclaimed += 1;
            }
            self.set_entry(Owner::Pt(n as u8, b, i as u32), PageEntry::unmapped());
        }
    }

    /// Take a block of PT cache `n` for a new reference, evicting if needed.
    fn take_pt_block(&mut self, n: usize, report: &mut InsertReport) -> Option<u32> {
        let frame = self.frame;
        let b = self.pt[n - 1].1.take(frame)?;
        let old = self.pt[n - 1].1.owner[b as usize];
        if old != Owner::None {
            self.unmap_owner(old);
            report.evicted_pt_blocks += 1;
        }
        self.pt[n - 1].1.owner[b as usize] = Owner::None;
        self.orphan_children(n, b, report);
        Some(b)
    }

    /// Insert loaded bricks (in the given order, most wanted first) in the
    /// paper's order: evict from the LRU tail and unmap, write the brick into
    /// its slot, then reference it, creating page-table blocks as needed.
    /// Empty and constant bricks are mapped by flag and take no slot.
    pub fn insert(&mut self, bricks: &[Arc<LoadedBrick>]) -> InsertReport {
        let mut report = InsertReport::default();
        let frame = self.frame;
        for lb in bricks {
            let key = lb.key;
            let l = key.level as usize;
            let c = key.channel as usize;
            let v = [0, 1, 2].map(|a| key.brick[a] as u64 * self.cfg.brick[a]);
            let data = matches!(lb.content, BrickContent::Data(_));
            if data
                && report.bytes_uploaded + self.brick_bytes as u64 > self.cfg.upload_bytes_per_frame
            {
                // Over this frame's upload budget: this brick and the rest
                // are offered again next frame.
                break;
            }
            // From here on the brick is consumed: written, flagged, found
            // resident already, or dropped for want of a slot (it will be
            // requested again if still wanted).
            report.processed += 1;
            let p = self.p_of_voxel(l, v);
            // Walk down, creating page-table blocks as needed.
            let mut owner = Owner::Dir(self.dir_index(l, c, p) as u32);
            let mut ok = true;
            for n in 1..self.layout.nmax() {
                let e = self.entry(owner);
                let b = match entry_kind(&e, self.dtype) {
                    Kind::Mapped(slot) => self.pt[n - 1].1.id(slot),
                    _ => match self.take_pt_block(n, &mut report) {
                        Some(b) => {
                            let coords = self.pt[n - 1].1.coords(b);
                            self.set_entry(owner, PageEntry::mapped(coords));
                            self.pt[n - 1].1.owner[b as usize] = owner;
                            b
                        }
                        None => {
                            ok = false;
                            break;
                        }
                    },
                };
                self.pt[n - 1].1.usage[b as usize].store(frame, Ordering::Relaxed);
                owner = Owner::Pt(n as u8, b, self.block_entry(n, l, p) as u32);
            }
            if !ok {
                report.deferred += 1;
                continue;
            }
            if !matches!(entry_kind(&self.entry(owner), self.dtype), Kind::Unmapped) {
                continue; // already resident (a brick may be delivered twice)
            }
            match &lb.content {
                BrickContent::Empty => {
                    self.set_entry(owner, PageEntry::empty());
                    self.log_mapped(key);
                    report.flagged += 1;
                }
                BrickContent::Constant(v) => {
                    self.set_entry(owner, PageEntry::constant_of(self.dtype, *v));
                    self.log_mapped(key);
                    report.flagged += 1;
                }
                BrickContent::Data(bytes) => {
                    let Some(s) = self
                        .slots
                        .take(frame)
                        .or_else(|| self.slots.take_stand_in(frame, key.level))
                    else {
                        report.deferred += 1;
                        continue;
                    };
                    // 1. evict and unmap
                    let old = self.slots.owner[s as usize];
                    if old != Owner::None {
                        self.unmap_owner(old);
                        report.evicted_bricks += 1;
                        let used = self.slots.exact[s as usize].load(Ordering::Relaxed);
                        if used != 0 && frame.wrapping_sub(used) < self.in_use_frames {
                            report.evicted_in_use += 1;
                        }
                    }
                    // 2. write
                    let bb = self.brick_bytes;
                    let dst = &mut self.pool_mut()[s as usize * bb..(s as usize + 1) * bb];
                    assert_eq!(bytes.len(), dst.len(), "brick size mismatch");
                    dst.copy_from_slice(bytes);
                    self.write_cells(s);
                    if let Some((_, slots)) = self.changes.as_mut() {
                        slots.push(s);
                    }
                    // 3. reference
                    let coords = self.slots.coords(s);
                    self.set_entry(owner, PageEntry::mapped(coords));
                    self.slots.owner[s as usize] = owner;
                    self.log_mapped(key);
                    self.slots.usage[s as usize].store(frame, Ordering::Relaxed);
                    // Fresh bricks are not taken back as stand-ins this frame.
                    self.slots.exact[s as usize].store(frame, Ordering::Relaxed);
                    self.slots.level[s as usize] = key.level;
                    report.inserted += 1;
                    report.bytes_uploaded += self.brick_bytes as u64;
                    self.uploaded += self.brick_bytes as u64;
                }
            }
        }
        report
    }

    fn log_mapped(&mut self, key: BrickKey) {
        if let Some((keys, _)) = self.residency.as_mut() {
            keys.push(key);
        }
    }

    fn entry(&self, o: Owner) -> PageEntry {
        match o {
            Owner::None => PageEntry::unmapped(),
            Owner::Dir(i) => self.dir[i as usize],
            Owner::Pt(n, b, e) => {
                let len = self.pt_block_len[n as usize - 1];
                self.pt[n as usize - 1].0[b as usize * len + e as usize]
            }
        }
    }

    fn set_entry(&mut self, o: Owner, e: PageEntry) {
        if let Some((_, lost)) = self.residency.as_mut() {
            if e.flag() == PageFlag::Unmapped {
                *lost = true;
            }
        }
        if self.changes.is_some() {
            if let Some(i) = self.table_index(o) {
                if let Some((entries, _)) = self.changes.as_mut() {
                    entries.push(i);
                }
            }
        }
        match o {
            Owner::None => {}
            Owner::Dir(i) => self.dir[i as usize] = e,
            Owner::Pt(n, b, i) => {
                let len = self.pt_block_len[n as usize - 1];
                self.pt[n as usize - 1].0[b as usize * len + i as usize] = e;
            }
        }
    }

    /// Keep brick `key` (resident or flagged) and the page-table blocks on
    /// its path resident for good: they are never evicted nor taken as
    /// stand-ins. Returns false (and pins nothing) if it is not mapped.
    pub fn pin(&mut self, key: BrickKey) -> bool {
        let l = key.level as usize;
        let c = key.channel as usize;
        let v = [0, 1, 2].map(|a| key.brick[a] as u64 * self.cfg.brick[a]);
        let p = self.p_of_voxel(l, v);
        let mut e = self.dir[self.dir_index(l, c, p)];
        let mut path = vec![];
        for n in 1..self.layout.nmax() {
            let Kind::Mapped(slot) = entry_kind(&e, self.dtype) else {
                return false;
            };
            let (entries, set) = &self.pt[n - 1];
            let b = set.id(slot);
            path.push((n, b));
            e = entries[b as usize * self.pt_block_len[n - 1] + self.block_entry(n, l, p)];
        }
        let slot = match entry_kind(&e, self.dtype) {
            Kind::Unmapped => return false,
            Kind::Mapped(slot) => Some(self.slots.id(slot)),
            Kind::Empty | Kind::Constant(_) => None,
        };
        for (n, b) in path {
            self.pt[n - 1].1.pinned[b as usize] = true;
        }
        if let Some(s) = slot {
            self.slots.pinned[s as usize] = true;
        }
        true
    }

    /// Pinned slots: `(set, slot)` with set 0 the brick pool and set `n`
    /// the `n`-th page-table cache (the device's numbering).
    pub fn pinned_slots(&self) -> Vec<(usize, u32)> {
        let mut out: Vec<(usize, u32)> = (0..self.slots.len() as u32)
            .filter(|&s| self.slots.pinned[s as usize])
            .map(|s| (0, s))
            .collect();
        for (n, (_, set)) in self.pt.iter().enumerate() {
            out.extend(
                (0..set.len() as u32)
                    .filter(|&b| set.pinned[b as usize])
                    .map(|b| (n + 1, b)),
            );
        }
        out
    }

    /// Pool slots pinned.
    pub fn pinned_bricks(&self) -> usize {
        self.slots.pinned.iter().filter(|p| **p).count()
    }

    /// Mark `key` as failed to load: it is left out of request lists from
    /// now on (samples there fall back to coarser data).
    pub fn mark_failed(&mut self, key: BrickKey) {
        self.failed.insert(key.pack());
    }

    /// Whether `key` was marked failed.
    pub fn is_failed(&self, key: BrickKey) -> bool {
        self.failed.contains(&key.pack())
    }

    /// Forget which bricks failed: they may be requested again.
    pub fn clear_failed(&mut self) {
        self.failed.clear();
    }

    /// Bricks marked failed.
    pub fn failed_count(&self) -> usize {
        self.failed.len()
    }

    /// Whether brick `key` is mapped (resident or flagged).
    pub fn is_resident(&self, key: BrickKey) -> bool {
        let v = [0, 1, 2].map(|a| key.brick[a] as u64 * self.cfg.brick[a]);
        !matches!(
            self.resolve(key.level as usize, key.channel as usize, v),
            Kind::Unmapped
        )
    }

    /// Check the structural invariants (for tests): every mapped entry
    /// points at a slot whose owner is that entry, and every owned slot is
    /// pointed at by its owner.
    pub fn check_invariants(&self) -> Result<(), String> {
        let check = |o: Owner, e: PageEntry, set: &SlotSet| -> Result<(), String> {
            if let Kind::Mapped(slot) = entry_kind(&e, self.dtype) {
                let id = set.id(slot);
                if set.owner[id as usize] != o {
                    return Err(format!(
                        "entry {o:?} maps slot {id} owned by {:?}",
                        set.owner[id as usize]
                    ));
                }
            }
            Ok(())
        };
        let nmax = self.layout.nmax();
        for (i, e) in self.dir.iter().enumerate() {
            let set = if nmax > 1 { &self.pt[0].1 } else { &self.slots };
            check(Owner::Dir(i as u32), *e, set)?;
        }
        for n in 1..nmax {
            let (entries, set) = &self.pt[n - 1];
            let len = self.pt_block_len[n - 1];
            let below = if n + 1 < nmax {
                &self.pt[n].1
            } else {
                &self.slots
            };
            for b in 0..set.len() {
                if set.owner[b] == Owner::None {
                    // An unowned block must hold no mapping.
                    if entries[b * len..(b + 1) * len]
                        .iter()
                        .any(|e| !matches!(entry_kind(e, self.dtype), Kind::Unmapped))
                    {
                        return Err(format!(
                            "unowned PT block {b} of level {n} still maps entries"
                        ));
                    }
                    continue;
                }
                for i in 0..len {
                    check(
                        Owner::Pt(n as u8, b as u32, i as u32),
                        entries[b * len + i],
                        below,
                    )?;
                }
            }
        }
        for (s, o) in self.slots.owner.iter().enumerate() {
            if *o != Owner::None {
                match entry_kind(&self.entry(*o), self.dtype) {
                    Kind::Mapped(c) if self.slots.id(c) == s as u32 => {}
                    _ => return Err(format!("slot {s} owned by {o:?} which does not map it")),
                }
            }
        }
        Ok(())
    }

    /// Management memory of this configuration, line by line (the same
    /// accounting as `brickyard vm footprint`).
    pub fn footprint(&self) -> brickyard_core::vm::Footprint {
        let pt: Vec<u64> = self.pt.iter().map(|(_, set)| set.len() as u64).collect();
        brickyard_core::vm::Footprint::of(
            &self.layout,
            self.slots.len() as u64,
            &pt,
            self.brick_bytes as u64,
            self.cfg.request_cap as u64,
        )
    }

    pub fn channels(&self) -> usize {
        self.channels
    }
}
