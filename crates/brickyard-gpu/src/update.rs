//! The update step on the device: the device chooses the slots new bricks
//! take (by its LRU orders) and references them in its page tables, in
//! parallel; the host only reads the capped request list and the slots it
//! must write, and sends bricks and their keys.
//!
//! Over 800 lines: the device's update step beside its CPU twin `UpdateModel`, pass by pass.
//!
//! Per frame ([`DeviceCache::end_frame`], then [`DeviceCache::reference`]):
//! 1. every set's LRU order is compacted by the stamps the renderer wrote
//!    (brick pool and each intermediate page-table cache);
//! 2. `reserve`: the `k` least recently used pool slots not used this frame
//!    are unmapped from their owners; their ids go to the host (4 bytes
//!    each), which writes the bricks there;
//! 3. the items (key, kind, slot: 48 bytes each) are referenced level by
//!    level. Items whose entry at a level is not mapped claim it in a hash
//!    table; the lowest item index wins and only winners take blocks, so
//!    bricks that share a page-table block never make two (the sequential
//!    referencing this replaces avoided that by doing one brick at a time).
//!
//! [`UpdateModel`] is the CPU twin: the same steps, one item after the
//! other. `tests/update.rs` compares the two after every frame, exactly.

use crate::context::{Gpu, GpuError};
use crate::kernel::{Binding, Kernel};
use crate::lru::{LruBuffers, LruCompaction};
use crate::vm::{with_vm_common, DeviceVm, Layout};
use brickyard_cache::bookkeeping::compact_lru;
use brickyard_cache::vm::VirtualMemory;
use std::collections::HashMap;

pub const NONE: u32 = u32::MAX;
const FLAG_SHIFT: u32 = 30;
const MAPPED: u32 = 1;
const EMPTY: u32 = 2;
const CONSTANT: u32 = 3;
/// Words before the reserved slots in the output buffer.
const HEADER: usize = 16;

/// One brick to reference (see `update.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Item {
    pub level: u32,
    pub channel: u32,
    /// 1: data (slot in `brick[3]`), 2: empty, 3: constant (bits in `value`).
    pub kind: u32,
    pub value: u32,
    /// Brick coordinates `[z, y, x]`, then the pool slot of a data brick.
    pub brick: [u32; 4],
    cursor: u32,
    leader: u32,
    pad: [u32; 2],
}

impl Item {
    fn new(level: u8, channel: u16, brick: [u32; 3], kind: u32, value: u32, slot: u32) -> Item {
        Item {
            level: level as u32,
            channel: channel as u32,
            kind,
            value,
            brick: [brick[0], brick[1], brick[2], slot],
            cursor: NONE,
            leader: NONE,
            pad: [0; 2],
        }
    }
    /// A brick of data written into pool slot `slot`.
    pub fn data(key: brickyard_cache::brick::BrickKey, slot: u32) -> Item {
        Item::new(key.level, key.channel, key.brick, 1, 0, slot)
    }
    /// A brick known to be empty.
    pub fn empty(key: brickyard_cache::brick::BrickKey) -> Item {
        Item::new(key.level, key.channel, key.brick, EMPTY, 0, NONE)
    }
    /// A brick of one value (`bits`: the page entry's value word).
    pub fn constant(key: brickyard_cache::brick::BrickKey, bits: u32) -> Item {
        Item::new(key.level, key.channel, key.brick, CONSTANT, bits, NONE)
    }
}

/// Cumulative counts of the update step.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UpdateCounts {
    /// Bricks unmapped: evicted, or orphaned with their page-table block.
    pub bricks_unmapped: u32,
    /// Page-table blocks unmapped (evicted or orphaned).
    pub blocks_unmapped: u32,
    pub bricks_mapped: u32,
    /// Empty and constant entries set.
    pub flags_set: u32,
    /// Items that found no page-table block (every block in use).
    pub failed: u32,
    pub blocks_mapped: u32,
    /// Not cumulative: pool slots used at their own level in the frame
    /// last ended, pinned slots included (they are stamped so).
    pub exact_pool_slots: u32,
    /// Not cumulative: bricks the frame last ended evicted that a frame
    /// among the last `in_use_frames` used at their own level (views
    /// drawn in turn taking each other's bricks).
    pub evicted_in_use: u32,
}

impl UpdateCounts {
    fn from_words(w: &[u32]) -> UpdateCounts {
        UpdateCounts {
            bricks_unmapped: w[0],
            blocks_unmapped: w[1],
            bricks_mapped: w[2],
            flags_set: w[3],
            failed: w[4],
            blocks_mapped: w[5],
            exact_pool_slots: w[6],
            evicted_in_use: w[15],
        }
    }
    /// Bricks resident now (orphans two levels down are not subtracted).
    pub fn resident_bricks(&self) -> u32 {
        self.bricks_mapped.saturating_sub(self.bricks_unmapped)
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    frame: u32,
    k: u32,
    n: u32,
    h: u32,
    /// Frames, this one included, whose use at its own level makes an
    /// evicted brick count as in use (word 15 of the output).
    in_use: u32,
    pad: [u32; 3],
}

/// Which of a slot's two stamps orders its set: for the pool, the frame
/// it was last used at its own level, so a brick that only stood in for
/// finer, missing data ages and gives way to that data when the pool is
/// full (a view whose finest bricks fit the pool completes); for
/// page-table blocks, the frame last passed through.
fn stamp_word(set: usize) -> u32 {
    u32::from(set == 0)
}

/// Indices into the stamp table (`set_base` + slot) of pinned slots, sorted.
fn pinned_indices(lay: &Layout, slots: &[(usize, u32)]) -> Vec<u32> {
    let mut v: Vec<u32> = slots
        .iter()
        .filter(|(set, s)| *set < lay.nmax as usize && *s < lay.set_base[*set][1])
        .map(|(set, s)| lay.set_base[*set][0] + s)
        .collect();
    v.sort_unstable();
    v.dedup();
    v
}

/// Sorted indices as runs `(first, count)`.
fn runs_of(v: &[u32]) -> Vec<(u32, u32)> {
    let mut runs: Vec<(u32, u32)> = vec![];
    for &i in v {
        match runs.last_mut() {
            Some((a, n)) if *a + *n == i => *n += 1,
            _ => runs.push((i, 1)),
        }
    }
    runs
}

/// Per-slot owners from the current page tables (entries mapping a slot).
fn owners_of(lay: &Layout, entries: &[[u32; 2]]) -> Vec<u32> {
    let nmax = lay.nmax as usize;
    let sets = (0..nmax).map(|n| lay.set_base[n]);
    let total: u32 = sets.map(|b| b[1]).sum();
    let mut owner = vec![NONE; total as usize];
    for t in 0..nmax {
        let (lo, hi) = (
            lay.table_off[t][0] as usize,
            if t + 1 < nmax {
                lay.table_off[t + 1][0] as usize
            } else {
                entries.len()
            },
        );
        // Table t maps into set t + 1 (the pool after the last one).
        let (set, grid) = if t + 1 < nmax {
            (t + 1, lay.pt_grid[t + 1])
        } else {
            (0, lay.brick_grid)
        };
        for (i, e) in entries[lo..hi].iter().enumerate() {
            if e[0] >> FLAG_SHIFT == MAPPED {
                owner[(lay.set_base[set][0] + slot_id(*e, grid)) as usize] = (lo + i) as u32;
            }
        }
    }
    owner
}

fn slot_id(e: [u32; 2], g: [u32; 4]) -> u32 {
    let z = (e[0] >> 20) & 0x3ff;
    let y = (e[0] >> 10) & 0x3ff;
    let x = e[0] & 0x3ff;
    (z * g[1] + y) * g[2] + x
}

fn mapped_word(s: u32, g: [u32; 4]) -> u32 {
    let z = s / (g[2] * g[1]);
    let y = (s / g[2]) % g[1];
    let x = s % g[2];
    (MAPPED << FLAG_SHIFT) | (z << 20) | (y << 10) | x
}

fn flag(e: [u32; 2]) -> u32 {
    e[0] >> FLAG_SHIFT
}

/// The CPU twin of the device's update step: the same state and steps,
/// sequentially.
#[derive(Clone)]
pub struct UpdateModel {
    lay: Layout,
    /// The page tables, as on the device.
    pub entries: Vec<[u32; 2]>,
    /// Two stamps per slot of every set.
    pub stamps: Vec<u32>,
    pub owner: Vec<u32>,
    /// LRU order per set (0: pool).
    pub order: Vec<Vec<u32>>,
    pub counts: UpdateCounts,
    /// Pinned slots (`set_base` index + slot): stamped as used at their
    /// own level at every frame's end, so they are never taken.
    pub pinned: Vec<u32>,
    /// See [`UpdateCounts::evicted_in_use`] (at least 1).
    pub in_use_frames: u32,
}

impl UpdateModel {
    /// The state a [`DeviceCache`] starts from for `dvm` (mirroring `vm`).
    pub fn new(dvm: &DeviceVm, vm: &VirtualMemory) -> UpdateModel {
        let lay = *dvm.layout();
        let entries: Vec<[u32; 2]> = vm
            .tables()
            .iter()
            .flat_map(|t| t.iter().map(|e| [e.word, e.value]))
            .collect();
        let owner = owners_of(&lay, &entries);
        let order = (0..lay.nmax as usize)
            .map(|n| (0..lay.set_base[n][1]).collect())
            .collect();
        UpdateModel {
            lay,
            stamps: vec![0; owner.len() * 2],
            entries,
            owner,
            order,
            counts: UpdateCounts::default(),
            pinned: pinned_indices(&lay, &vm.pinned_slots()),
            in_use_frames: 1,
        }
    }

    fn sets(&self) -> usize {
        self.lay.nmax as usize
    }

    fn compact(&mut self, set: usize, frame: u32) {
        let base = self.lay.set_base[set][0];
        let w = stamp_word(set) as usize;
        let stamps = &self.stamps;
        self.order[set] = compact_lru(&self.order[set], |s| {
            stamps[2 * (base + s) as usize + w] == frame
        });
    }

    /// What the renderer does for a slot it used: stamp it (`exact`: a
    /// pool slot used at its own level).
    pub fn stamp(&mut self, set: usize, slot: u32, frame: u32, exact: bool) {
        let i = 2 * (self.lay.set_base[set][0] + slot) as usize;
        self.stamps[i] = frame;
        if exact && set == 0 {
            self.stamps[i + 1] = frame;
        }
    }

    /// Move the last `r` slots of set `set`'s order to its front (the slots
    /// just taken from the tail become the most recently used).
    fn rotate(&mut self, set: usize, r: usize) {
        let o = &mut self.order[set];
        let n = o.len();
        if n > 0 {
            o.rotate_right(r % n);
        }
    }

    /// Pin `(set, slot)`s (as [`VirtualMemory::pinned_slots`] lists them;
    /// [`UpdateModel::new`] takes those of the virtual memory it mirrors).
    pub fn pin(&mut self, slots: &[(usize, u32)]) {
        self.pinned = pinned_indices(&self.lay, slots);
    }

    /// Compact every set, then reserve `k` pool slots (NONE where none).
    pub fn end_frame(&mut self, frame: u32, k: usize) -> Vec<u32> {
        self.counts.evicted_in_use = 0;
        for &i in &self.pinned {
            self.stamps[2 * i as usize] = frame;
            self.stamps[2 * i as usize + 1] = frame;
        }
        for set in 0..self.sets() {
            self.compact(set, frame);
        }
        let [base, n, ..] = self.lay.set_base[0];
        self.counts.exact_pool_slots = (base..base + n)
            .filter(|&i| self.stamps[2 * i as usize + 1] == frame)
            .count() as u32;
        let reserved = self.reserve(frame, k);
        let r = reserved.iter().filter(|&&s| s != NONE).count();
        self.rotate(0, r);
        reserved
    }

    fn reserve(&mut self, frame: u32, k: usize) -> Vec<u32> {
        let cnt = self.lay.set_base[0][1] as usize;
        (0..k)
            .map(|i| {
                if i >= cnt {
                    return NONE;
                }
                let s = self.order[0][cnt - 1 - i];
                if self.stamps[2 * s as usize + 1] == frame {
                    return NONE;
                }
                let o = self.owner[s as usize];
                if o != NONE {
                    let e = self.entries[o as usize];
                    if flag(e) == MAPPED && slot_id(e, self.lay.brick_grid) == s {
                        self.entries[o as usize] = [0, 0];
                        self.counts.bricks_unmapped += 1;
                        let used = self.stamps[2 * s as usize + 1];
                        if used != 0 && frame.wrapping_sub(used) < self.in_use_frames {
                            self.counts.evicted_in_use += 1;
                        }
                    }
                }
                self.owner[s as usize] = NONE;
                self.stamps[2 * s as usize] = frame;
                self.stamps[2 * s as usize + 1] = frame;
                s
            })
            .collect()
    }

    fn voxel_of(&self, it: &Item) -> [u32; 3] {
        let b = self.lay.block[self.lay.nmax as usize];
        [0, 1, 2].map(|a| it.brick[a] * b[a])
    }

    /// Reference `items` (after [`end_frame`](Self::end_frame)).
    pub fn reference(&mut self, frame: u32, items: &[Item]) {
        let lay = self.lay;
        let nmax = lay.nmax as usize;
        let mut cursor: Vec<u32> = items.iter().map(|it| self.dir_index(it)).collect();
        for n in 1..nmax {
            let g = lay.pt_grid[n];
            let base = lay.set_base[n][0];
            let cnt = lay.set_base[n][1];
            for &p in &cursor {
                if p != NONE && flag(self.entries[p as usize]) == MAPPED {
                    let b = slot_id(self.entries[p as usize], g);
                    self.stamps[2 * (base + b) as usize] = frame;
                }
            }
            self.compact(n, frame);
            // Claims: the first item for each entry not mapped; winners
            // rank in item order.
            let mut seen: HashMap<u32, ()> = HashMap::new();
            let mut leaders = vec![NONE; items.len()];
            let mut rank = 0u32;
            for (i, &p) in cursor.iter().enumerate() {
                if p == NONE || flag(self.entries[p as usize]) == MAPPED {
                    continue;
                }
                if seen.insert(p, ()).is_some() {
                    continue;
                }
                let r = rank;
                rank += 1;
                if r < cnt {
                    let b = self.order[n][(cnt - 1 - r) as usize];
                    if self.stamps[2 * (base + b) as usize] != frame {
                        leaders[i] = b;
                    }
                }
            }
            for (i, &b) in leaders.iter().enumerate() {
                if b == NONE {
                    continue;
                }
                let p = cursor[i];
                let o = self.owner[(base + b) as usize];
                if o != NONE {
                    let e = self.entries[o as usize];
                    if flag(e) == MAPPED && slot_id(e, g) == b {
                        self.entries[o as usize] = [0, 0];
                        self.counts.blocks_unmapped += 1;
                    }
                }
                self.owner[(base + b) as usize] = p;
                self.stamps[2 * (base + b) as usize] = frame;
                let first = (lay.table_off[n][0] + b * g[3]) as usize;
                let mut orphans = 0;
                for e in &mut self.entries[first..first + g[3] as usize] {
                    if flag(*e) == MAPPED {
                        orphans += 1;
                    }
                    *e = [0, 0];
                }
                if n + 1 == nmax {
                    self.counts.bricks_unmapped += orphans;
                } else {
                    self.counts.blocks_unmapped += orphans;
                }
                self.entries[p as usize] = [mapped_word(b, g), 0];
                self.counts.blocks_mapped += 1;
            }
            let taken = leaders.iter().filter(|&&b| b != NONE).count();
            self.rotate(n, taken);
            for (i, it) in items.iter().enumerate() {
                let p = cursor[i];
                if p == NONE {
                    continue;
                }
                let e = self.entries[p as usize];
                if flag(e) != MAPPED {
                    cursor[i] = NONE;
                    self.counts.failed += 1;
                    continue;
                }
                cursor[i] = self.block_index(it, n, slot_id(e, g));
            }
        }
        for (i, it) in items.iter().enumerate() {
            let p = cursor[i];
            if p == NONE || flag(self.entries[p as usize]) != 0 {
                continue;
            }
            match it.kind {
                1 => {
                    let s = it.brick[3];
                    self.entries[p as usize] = [mapped_word(s, lay.brick_grid), 0];
                    self.owner[s as usize] = p;
                    self.stamps[2 * s as usize] = frame;
                    self.stamps[2 * s as usize + 1] = frame;
                    self.counts.bricks_mapped += 1;
                }
                EMPTY => {
                    self.entries[p as usize] = [EMPTY << FLAG_SHIFT, 0];
                    self.counts.flags_set += 1;
                }
                _ => {
                    self.entries[p as usize] = [CONSTANT << FLAG_SHIFT, it.value];
                    self.counts.flags_set += 1;
                }
            }
        }
    }

    /// Index of `it`'s directory entry.
    fn dir_index(&self, it: &Item) -> u32 {
        let lay = &self.lay;
        let v = self.voxel_of(it);
        let d: [u32; 3] =
            [0, 1, 2].map(|a| lay.dir_base[it.level as usize][a] + v[a] / lay.span[0][a]);
        let dd = lay.dir_dims;
        it.channel * lay.dir_len + (d[0] * dd[1] + d[1]) * dd[2] + d[2]
    }

    /// Index of `it`'s entry in block `b` of intermediate level `n`.
    fn block_index(&self, it: &Item, n: usize, b: u32) -> u32 {
        let lay = &self.lay;
        let v = self.voxel_of(it);
        let bl = lay.block[n];
        let o: [u32; 3] = [0, 1, 2].map(|a| (v[a] / lay.span[n][a]) % bl[a]);
        lay.table_off[n][0] + b * lay.pt_grid[n][3] + (o[0] * bl[1] + o[1]) * bl[2] + o[2]
    }

    /// Walk down to `it`'s brick: the last entry reached (the first not
    /// mapped on the way, or the brick's) with its index, and the
    /// page-table blocks passed `(level, block)`.
    fn walk(&self, it: &Item) -> (u32, [u32; 2], Vec<(usize, u32)>) {
        let mut p = self.dir_index(it);
        let mut path = vec![];
        for n in 1..self.lay.nmax as usize {
            let e = self.entries[p as usize];
            if flag(e) != MAPPED {
                return (p, e, path);
            }
            let b = slot_id(e, self.lay.pt_grid[n]);
            path.push((n, b));
            p = self.block_index(it, n, b);
        }
        (p, self.entries[p as usize], path)
    }

    /// The entry the tables hold for the brick of `it` (walking down; the
    /// first entry not mapped on the way), and its index.
    pub fn entry_for(&self, it: &Item) -> (u32, [u32; 2]) {
        let (p, e, _) = self.walk(it);
        (p, e)
    }

    /// The slots a walk to `it`'s brick passes through: `(set, slot)` of
    /// each page-table block, then the brick's pool slot if it is mapped
    /// (what a renderer stamps).
    pub fn path_of(&self, it: &Item) -> Vec<(usize, u32)> {
        let (_, e, mut path) = self.walk(it);
        if flag(e) == MAPPED {
            path.push((0, slot_id(e, self.lay.brick_grid)));
        }
        path
    }

    /// Structural check: every mapped entry maps a slot whose owner is that
    /// entry, so no block or slot is mapped twice and no page-table
    /// region has two blocks; every owned slot's owner maps it or is
    /// stale (orphan).
    pub fn check(&self) -> Result<(), String> {
        let lay = &self.lay;
        let nmax = lay.nmax as usize;
        let mut mapped_by: HashMap<u32, u32> = HashMap::new();
        for t in 0..nmax {
            let lo = lay.table_off[t][0] as usize;
            let hi = if t + 1 < nmax {
                lay.table_off[t + 1][0] as usize
            } else {
                self.entries.len()
            };
            let (set, g) = if t + 1 < nmax {
                (t + 1, lay.pt_grid[t + 1])
            } else {
                (0, lay.brick_grid)
            };
            for i in lo..hi {
                let e = self.entries[i];
                if flag(e) != MAPPED {
                    continue;
                }
                let s = slot_id(e, g);
                if s >= lay.set_base[set][1] {
                    return Err(format!(
                        "entry {i} maps slot {s} of set {set}, past its end"
                    ));
                }
                let gs = lay.set_base[set][0] + s;
                if let Some(prev) = mapped_by.insert(gs, i as u32) {
                    return Err(format!(
                        "slot {s} of set {set} is mapped by entries {prev} and {i}"
                    ));
                }
                if self.owner[gs as usize] != i as u32 {
                    return Err(format!(
                        "entry {i} maps slot {s} of set {set} whose owner is {}",
                        self.owner[gs as usize]
                    ));
                }
            }
        }
        Ok(())
    }
}

/// What [`DeviceCache::read_state`] returns: two stamps per slot of every
/// set, owners, and each set's LRU order.
pub struct CacheState {
    pub stamps: Vec<u32>,
    pub owner: Vec<u32>,
    pub orders: Vec<Vec<u32>>,
}

/// The device's update step (see the module text).
pub struct DeviceCache {
    kernel: Kernel,
    lru: LruCompaction,
    orders: Vec<LruBuffers>,
    /// Two stamps per slot of every set; the renderer writes them.
    pub stamps: wgpu::Buffer,
    owner: wgpu::Buffer,
    items: wgpu::Buffer,
    items_cap: usize,
    claims: wgpu::Buffer,
    out: wgpu::Buffer,
    out_cap: usize,
    sets: usize,
    counts: UpdateCounts,
    /// Pinned slots as runs `(first stamp-table index, count)`.
    pinned: Vec<(u32, u32)>,
    /// See [`UpdateCounts::evicted_in_use`] (at least 1).
    in_use_frames: u32,
}

impl DeviceCache {
    /// Pin `(set, slot)`s (as [`VirtualMemory::pinned_slots`] lists them):
    /// at every frame's end they are stamped as used at their own level,
    /// so the update step never takes them. [`DeviceCache::new`] pins what
    /// the virtual memory it starts from has pinned.
    pub fn pin(&mut self, dvm: &DeviceVm, slots: &[(usize, u32)]) {
        self.pinned = runs_of(&pinned_indices(dvm.layout(), slots));
    }

    /// The update step for `dvm`, starting from what it holds (mirroring
    /// `vm`): owners from its tables, LRU orders by slot id, no stamps.
    pub fn new(gpu: &Gpu, dvm: &DeviceVm, vm: &VirtualMemory) -> Result<DeviceCache, GpuError> {
        let m = UpdateModel::new(dvm, vm);
        let orders = m
            .order
            .iter()
            .map(|o| LruBuffers::order_only(gpu, o))
            .collect::<Result<Vec<_>, _>>()?;
        use Binding::*;
        let kernel = Kernel::new(
            gpu,
            "update",
            &with_vm_common(include_str!("shaders/update.wgsl")),
            &[
                "reserve", "start", "path", "claim", "assign", "take", "descend", "finish",
                "rotate",
            ],
            &[
                Uniform, ReadWrite, Texture3d, Uniform, ReadWrite, ReadWrite, Read, ReadWrite,
                ReadWrite, ReadWrite,
            ],
        );
        Ok(DeviceCache {
            kernel,
            lru: LruCompaction::new(gpu),
            orders,
            stamps: gpu.storage_buffer("usage stamps", &m.stamps),
            owner: gpu.storage_buffer("owners", &m.owner),
            items: gpu.storage_buffer_zeroed("update items", 48),
            items_cap: 1,
            // Also the scratch of `rotate`: room for the largest set.
            claims: gpu.storage_buffer_zeroed(
                "claims",
                m.order.iter().map(|o| o.len()).max().unwrap_or(1).max(4) as u64 * 4,
            ),
            out: gpu.storage_buffer_zeroed("update out", HEADER as u64 * 4),
            out_cap: 0,
            sets: m.order.len(),
            counts: UpdateCounts::default(),
            pinned: runs_of(&m.pinned),
            in_use_frames: 1,
        })
    }

    /// The counts as of the last [`end_frame`](Self::end_frame).
    pub fn counts(&self) -> UpdateCounts {
        self.counts
    }

    fn bind(
        &self,
        gpu: &Gpu,
        dvm: &DeviceVm,
        params: Params,
        order: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        let res = dvm.resources(gpu, 0);
        let p = gpu.uniform_buffer("update params", &params);
        self.kernel.bind_resources(
            gpu,
            vec![
                res.layout.as_entire_binding(),
                res.entries.as_entire_binding(),
                wgpu::BindingResource::TextureView(&res.pool),
                p.as_entire_binding(),
                self.stamps.as_entire_binding(),
                self.owner.as_entire_binding(),
                order.as_entire_binding(),
                self.items.as_entire_binding(),
                self.claims.as_entire_binding(),
                self.out.as_entire_binding(),
            ],
        )
    }

    fn grow_out(&mut self, gpu: &Gpu, k: usize) {
        if k > self.out_cap {
            let cap = k.next_power_of_two();
            let new = gpu.storage_buffer_zeroed("update out", (HEADER + cap) as u64 * 4);
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            enc.copy_buffer_to_buffer(&self.out, 0, &new, 0, HEADER as u64 * 4);
            gpu.queue.submit([enc.finish()]);
            self.out = new;
            self.out_cap = cap;
        }
    }

    /// How many frames, this one included, count for
    /// [`UpdateCounts::evicted_in_use`] (the views drawn in turn).
    pub fn set_in_use_frames(&mut self, n: u32) {
        self.in_use_frames = n.max(1);
    }

    /// End frame `frame` (the renderer has stamped what it used): compact
    /// every set's LRU order and reserve `k` pool slots for bricks to
    /// come, unmapping what they held. Returns the slots (`NONE` where
    /// every slot is in use; those come last) — 4 bytes each read back,
    /// with the counts (32 bytes).
    pub fn end_frame(
        &mut self,
        gpu: &Gpu,
        dvm: &DeviceVm,
        frame: u32,
        k: usize,
    ) -> Result<Vec<u32>, GpuError> {
        self.grow_out(gpu, k);
        // This frame's counts of slots taken start at 0.
        gpu.queue.write_buffer(&self.out, 28, &[0u8; 36]);
        for &(first, n) in &self.pinned {
            let words = vec![frame; 2 * n as usize];
            gpu.queue
                .write_buffer(&self.stamps, first as u64 * 8, bytemuck::cast_slice(&words));
        }
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        for set in 0..self.sets {
            let base = dvm.layout().set_base[set][0];
            self.lru.record_with(
                gpu,
                &mut enc,
                &self.orders[set],
                &self.stamps,
                [base, 2, stamp_word(set)],
                frame,
            );
        }
        // The compaction of the pool's order counted the slots used at
        // their own level (its stamp word): word 6 of the output.
        self.orders[0].copy_used_count(&mut enc, &self.out, 6 * 4);
        if k > 0 {
            let params = Params {
                frame,
                k: k as u32,
                n: 0,
                h: 1,
                in_use: self.in_use_frames,
                pad: [0; 3],
            };
            let bind = self.bind(gpu, dvm, params, &self.orders[0].order);
            self.kernel
                .dispatch(&mut enc, "reserve", &bind, [(k as u32).div_ceil(64), 1, 1]);
            self.record_rotate(gpu, dvm, &mut enc, frame, 0);
        }
        gpu.queue.submit([enc.finish()]);
        let w = gpu.read_u32("reserved slots", &self.out, HEADER + k)?;
        self.counts = UpdateCounts::from_words(&w);
        Ok(w[HEADER..].to_vec())
    }

    /// Record the rotation of set `set`'s order by the slots taken from its
    /// tail this frame (they become the most recently used).
    fn record_rotate(
        &self,
        gpu: &Gpu,
        dvm: &DeviceVm,
        enc: &mut wgpu::CommandEncoder,
        frame: u32,
        set: usize,
    ) {
        let o = &self.orders[set];
        if o.n == 0 {
            return;
        }
        let params = Params {
            frame,
            k: 0,
            n: set as u32,
            h: 1,
            in_use: self.in_use_frames,
            pad: [0; 3],
        };
        let bind = self.bind(gpu, dvm, params, &o.order);
        self.kernel
            .dispatch(enc, "rotate", &bind, [o.n.div_ceil(64), 1, 1]);
        enc.copy_buffer_to_buffer(&self.claims, 0, &o.order, 0, o.n as u64 * 4);
    }

    /// Reference `items` (bricks written into the slots
    /// [`end_frame`](Self::end_frame) gave, and empty or constant ones) in
    /// frame `frame`. Queued; returns the bytes sent.
    pub fn reference(&mut self, gpu: &Gpu, dvm: &DeviceVm, frame: u32, items: &[Item]) -> u64 {
        if items.is_empty() {
            return 0;
        }
        let k = items.len();
        if k > self.items_cap {
            self.items_cap = k.next_power_of_two();
            self.items = gpu.storage_buffer_zeroed("update items", self.items_cap as u64 * 48);
        }
        gpu.queue
            .write_buffer(&self.items, 0, bytemuck::cast_slice(items));
        let h = (2 * k).next_power_of_two().max(64);
        if self.claims.size() < h as u64 * 8 {
            let largest = self.orders.iter().map(|o| o.n).max().unwrap_or(1) as u64 * 4;
            self.claims = gpu.storage_buffer_zeroed("claims", (h as u64 * 8).max(largest));
        }
        let groups = [(k as u32).div_ceil(64), 1, 1];
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        let p = |n: u32| Params {
            frame,
            k: k as u32,
            n,
            h: h as u32,
            in_use: self.in_use_frames,
            pad: [0; 3],
        };
        let bind0 = self.bind(gpu, dvm, p(0), &self.orders[0].order);
        self.kernel.dispatch(&mut enc, "start", &bind0, groups);
        for n in 1..self.sets {
            let bind = self.bind(gpu, dvm, p(n as u32), &self.orders[n].order);
            self.kernel.dispatch(&mut enc, "path", &bind, groups);
            let base = dvm.layout().set_base[n][0];
            self.lru.record_with(
                gpu,
                &mut enc,
                &self.orders[n],
                &self.stamps,
                [base, 2, 0],
                frame,
            );
            enc.clear_buffer(&self.claims, 0, Some(h as u64 * 8));
            self.kernel.dispatch(&mut enc, "claim", &bind, groups);
            self.kernel.dispatch(&mut enc, "assign", &bind, [1, 1, 1]);
            self.kernel.dispatch(&mut enc, "take", &bind, groups);
            self.record_rotate(gpu, dvm, &mut enc, frame, n);
            self.kernel.dispatch(&mut enc, "descend", &bind, groups);
        }
        self.kernel.dispatch(&mut enc, "finish", &bind0, groups);
        gpu.queue.submit([enc.finish()]);
        k as u64 * 48
    }

    /// The device's state, read back (for tests).
    pub fn read_state(&self, gpu: &Gpu) -> Result<CacheState, GpuError> {
        let n = self.owner.size() as usize / 4;
        let stamps = gpu.read_u32("stamps", &self.stamps, 2 * n)?;
        let owner = gpu.read_u32("owners", &self.owner, n)?;
        let orders = self
            .orders
            .iter()
            .map(|o| o.read_order(gpu))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(CacheState {
            stamps,
            owner,
            orders,
        })
    }
}
