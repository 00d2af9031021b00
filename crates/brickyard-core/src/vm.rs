//! Virtual-address math of the voxel virtual memory: real and virtual sizes,
//! the multi-resolution page directory layout, page-table levels, lookups,
//! page-table entries and the memory footprint of the whole structure.
//!
//! Over 800 lines: 0.7k lines of address math, 0.75k of tests against the published tables.
//!
//! Source: Sarton et al. 2020 (TVCG) §5.1–5.5, equations 1–5, Fig. 4 and
//! Table 1; Sarton's thesis §3.6 (overlap-aware addressing) and §6.3
//! (footprint tables). This module is pure arithmetic: it allocates no
//! cache, does no I/O and knows nothing about GPUs.
//!
//! # The hierarchy
//!
//! A voxel of resolution level `l` is reached by walking `nmax + 1`
//! *virtualization levels* `n`:
//!
//! * `n = 0` is the **directory** (the paper's MRPD): one dense grid of
//!   entries per resolution level, always fully resident;
//! * `0 < n < nmax` are **page-table caches**: their entries are stored in
//!   blocks of `b_n` entries, and only some blocks are resident;
//! * `n = nmax` is the **brick pool**: voxels stored in bricks of
//!   `b_nmax` voxels (the brick size without apron).
//!
//! An entry of level `n < nmax` points at one block of level `n + 1`.
//! With no page-table level (`nmax = 1`) a directory entry points straight
//! at a brick.
//!
//! # Real and virtual sizes (equations 4 and 5)
//!
//! `real[l][n]` is how many elements level `n` needs to cover the data of
//! resolution level `l`: at `n = nmax` it is the number of voxels; one
//! level up it is the number of bricks (each axis rounded up); one more up,
//! the number of page-table blocks holding those brick entries, and so on to
//! the directory. Each step divides by the block size of the level below and
//! rounds up (equation 4).
//!
//! `virt[l][n]` goes the other way: start from the directory
//! (`virt[l][0] = real[l][0]`) and multiply by each block size on the way
//! down (equation 5). Because every rounding up adds a partially used block,
//! the virtual volume can be larger than the real one
//! (`virt[l][n] >= real[l][n]`, and `virt[l][nmax]` is a whole number of
//! bricks, of page-table blocks, and so on). The normalized position
//! `p ∈ [0,1]³` used by the lookups spans the *virtual* volume of its level;
//! [`VirtualLayout::virtual_from_real`] converts a position normalized to the
//! real volume (the same for every level) into it (§5.5).
//!
//! # Axis order
//!
//! Everything here is `[z, y, x]`, x fastest, like the rest of brickyard. The
//! papers write `[x, y, z]`; the tests translate their examples.

use crate::{DType, Dims3};
use serde::Serialize;

/// Element-wise ceiling division of two 3D sizes.
fn ceil_div3(a: Dims3, b: Dims3) -> Dims3 {
    [
        a[0].div_ceil(b[0]),
        a[1].div_ceil(b[1]),
        a[2].div_ceil(b[2]),
    ]
}

/// Element-wise product of two 3D sizes.
fn mul3(a: Dims3, b: Dims3) -> Dims3 {
    [a[0] * b[0], a[1] * b[1], a[2] * b[2]]
}

fn count(d: Dims3) -> u64 {
    d[0] * d[1] * d[2]
}

/// The geometry of the virtual memory for one multi-resolution volume:
/// real and virtual sizes of every resolution level at every
/// virtualization level, and where each level lives in the directory.
///
/// ## Directory layout
///
/// The directory is one 3D grid holding one sub-grid per resolution level.
/// The sub-grids are placed next to each other along **x**, level 0 first
/// (as in the paper's Fig. 4): level `l` starts at
/// `dir_base[l] = [0, 0, Σ_{k<l} virt[k][0].x]`. The directory is as wide
/// as the sum of the sub-grid widths and as tall/deep as the largest
/// sub-grid in y and z; the cells beside the smaller sub-grids are unused
/// (they stay [`PageEntry::unmapped`]). [`VirtualLayout::dir_entries`]
/// counts them too, because the directory is allocated as one dense grid.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct VirtualLayout {
    /// Voxels per resolution level, `[z, y, x]`, level 0 finest.
    pub levels: Vec<Dims3>,
    /// Brick size without apron, `b_nmax`.
    pub brick: Dims3,
    /// Block size (in entries) of each intermediate page-table level,
    /// `b_1` first. Empty: the directory points straight at bricks.
    pub pt_blocks: Vec<Dims3>,
    /// `real[l][n]`, `n = 0 ..= nmax` (equation 4).
    pub real: Vec<Vec<Dims3>>,
    /// `virt[l][n]`, `n = 0 ..= nmax` (equation 5).
    pub virt: Vec<Vec<Dims3>>,
    /// Where level `l`'s sub-grid starts in the directory (`PageDirBase[l]`).
    pub dir_base: Vec<Dims3>,
    /// Size of the whole directory, in entries.
    pub dir_dims: Dims3,
}

impl VirtualLayout {
    /// Computes the layout of a volume with the given levels (voxels per
    /// level, `[z, y, x]`), brick size (without apron) and intermediate
    /// page-table block sizes (`b_1` first; empty for a single
    /// virtualization level).
    ///
    /// Panics when `levels` is empty or any size is zero.
    pub fn new(levels: Vec<Dims3>, brick: Dims3, pt_blocks: Vec<Dims3>) -> Self {
        assert!(!levels.is_empty(), "a volume needs at least one level");
        assert!(
            levels.iter().all(|d| d.iter().all(|&v| v > 0)),
            "empty level in {levels:?}"
        );
        assert!(brick.iter().all(|&v| v > 0), "empty brick {brick:?}");
        assert!(
            pt_blocks.iter().all(|d| d.iter().all(|&v| v > 0)),
            "empty page-table block in {pt_blocks:?}"
        );
        let nmax = pt_blocks.len() + 1;
        let block = |n: usize| if n == nmax { brick } else { pt_blocks[n - 1] };

        let mut real = Vec::with_capacity(levels.len());
        let mut virt = Vec::with_capacity(levels.len());
        for &dims in &levels {
            // Equation 4, from the voxels up to the directory.
            let mut r = vec![[0u64; 3]; nmax + 1];
            r[nmax] = dims;
            for n in (0..nmax).rev() {
                r[n] = ceil_div3(r[n + 1], block(n + 1));
            }
            // Equation 5, from the directory down to the voxels.
            let mut v = vec![[0u64; 3]; nmax + 1];
            v[0] = r[0];
            for n in 1..=nmax {
                v[n] = mul3(v[n - 1], block(n));
            }
            real.push(r);
            virt.push(v);
        }

        let mut dir_base = Vec::with_capacity(levels.len());
        let mut dir_dims = [0u64; 3];
        for v in &virt {
            dir_base.push([0, 0, dir_dims[2]]);
            dir_dims[0] = dir_dims[0].max(v[0][0]);
            dir_dims[1] = dir_dims[1].max(v[0][1]);
            dir_dims[2] += v[0][2];
        }

        VirtualLayout {
            levels,
            brick,
            pt_blocks,
            real,
            virt,
            dir_base,
            dir_dims,
        }
    }

    /// Chooses the number of intermediate page-table levels (all with blocks
    /// of `pt_block` entries): the smallest depth `0, 1, 2, …` whose directory
    /// has at most `max_dir_entries` entries.
    ///
    /// Adding a level divides every sub-grid by `pt_block` (rounded up), so
    /// the directory shrinks until each level's sub-grid is a single entry.
    /// If the cap is below that floor (fewer entries than levels, or a
    /// `pt_block` of `[1, 1, 1]` that never shrinks anything), the returned
    /// layout is the shallowest one with the smallest reachable directory;
    /// callers that treat the cap as a hard limit check
    /// [`VirtualLayout::dir_entries`].
    pub fn auto(levels: Vec<Dims3>, brick: Dims3, pt_block: Dims3, max_dir_entries: u64) -> Self {
        let mut best = VirtualLayout::new(levels.clone(), brick, Vec::new());
        let mut depth = 0;
        while best.dir_entries() > max_dir_entries {
            depth += 1;
            let next = VirtualLayout::new(levels.clone(), brick, vec![pt_block; depth]);
            if next.dir_entries() >= best.dir_entries() {
                break; // saturated: one more level would not shrink anything
            }
            best = next;
        }
        best
    }

    /// Index of the brick pool level: `pt_blocks.len() + 1`.
    pub fn nmax(&self) -> usize {
        self.pt_blocks.len() + 1
    }

    /// Number of intermediate page-table levels (`nmax - 1`).
    pub fn pt_levels(&self) -> usize {
        self.pt_blocks.len()
    }

    /// Number of resolution levels.
    pub fn num_levels(&self) -> usize {
        self.levels.len()
    }

    /// Block size `b_n` of level `n`, `1 <= n <= nmax`: a page-table block
    /// (in entries) for `n < nmax`, the brick (in voxels) for `n = nmax`.
    pub fn block(&self, n: usize) -> Dims3 {
        assert!(
            (1..=self.nmax()).contains(&n),
            "level n = {n} has no blocks (1..={})",
            self.nmax()
        );
        if n == self.nmax() {
            self.brick
        } else {
            self.pt_blocks[n - 1]
        }
    }

    /// Voxels (per axis) covered by one element of level `n`: `[1, 1, 1]`
    /// at `n = nmax`, a brick at `nmax - 1`, and the product of all block
    /// sizes below `n` in general. A ray that meets an empty or unmapped
    /// entry of level `n` can skip this many voxels of its level.
    pub fn entry_span(&self, n: usize) -> Dims3 {
        assert!(n <= self.nmax(), "n = {n} > nmax = {}", self.nmax());
        (n + 1..=self.nmax()).fold([1, 1, 1], |acc, k| mul3(acc, self.block(k)))
    }

    /// Entries in the whole directory (used and unused cells).
    pub fn dir_entries(&self) -> u64 {
        count(self.dir_dims)
    }

    /// Number of bricks of the whole pyramid (real bricks only).
    pub fn brick_count(&self) -> u64 {
        let n = self.nmax() - 1;
        self.real.iter().map(|r| count(r[n])).sum()
    }

    /// Size of the brick grids of all levels laid side by side along x,
    /// the way the directory would be with a single virtualization level.
    /// The paper's request buffer has exactly this shape, whatever the
    /// number of page-table levels (one 4-byte timestamp per brick of the
    /// pyramid, §5.2; thesis Table 6.3 keeps it constant across depths).
    pub fn brick_dir_dims(&self) -> Dims3 {
        let n = self.nmax() - 1;
        self.real.iter().fold([0, 0, 0], |acc, r| {
            [acc[0].max(r[n][0]), acc[1].max(r[n][1]), acc[2] + r[n][2]]
        })
    }

    /// Index of the voxel at `p` in level `l`'s virtual volume, clamped to
    /// the volume (so `p = 1.0`, or anything outside `[0, 1]`, stays in).
    fn voxel_index(&self, l: usize, p: [f64; 3]) -> Dims3 {
        let v = self.virt[l][self.nmax()];
        let mut i = [0u64; 3];
        for a in 0..3 {
            // `as u64` saturates: negative values and NaN become 0.
            let f = (p[a] * v[a] as f64).floor() as u64;
            i[a] = f.min(v[a] - 1);
        }
        i
    }

    /// Which element of level `n`'s virtualized grid (`virt[l][n]`
    /// elements) holds position `p` of level `l`: `⌊p ⊙ virt[l][n]⌋`,
    /// clamped. For `n < nmax` that is a page-table entry (the directory
    /// entry relative to the level's sub-grid for `n = 0`); for `n = nmax`
    /// it is the voxel.
    ///
    /// All levels are derived from the voxel index by integer division
    /// (`virt[l][nmax] = virt[l][n] ⊙ entry_span(n)` exactly), which is
    /// mathematically the same as flooring `p ⊙ virt[l][n]` directly but
    /// guarantees that the levels agree with each other even when `p` sits
    /// on a block boundary and floating-point rounding would tip one of the
    /// floors the other way.
    pub fn pt_entry_index(&self, l: usize, n: usize, p: [f64; 3]) -> Dims3 {
        let i = self.voxel_index(l, p);
        let s = self.entry_span(n);
        [i[0] / s[0], i[1] / s[1], i[2] / s[2]]
    }

    /// Equation 1: the directory cell for position `p` of level `l`, i.e.
    /// the level's sub-grid origin plus `⌊p ⊙ virt[l][0]⌋` (clamped, so
    /// `p = 1.0` stays inside the sub-grid).
    pub fn dir_entry(&self, l: usize, p: [f64; 3]) -> Dims3 {
        let e = self.pt_entry_index(l, 0, p);
        let b = self.dir_base[l];
        [b[0] + e[0], b[1] + e[1], b[2] + e[2]]
    }

    /// The offset part of equation 2 for `1 <= n <= nmax`:
    /// `⌊p ⊙ virt[l][n]⌋ mod b_n`, the position of the wanted element inside
    /// the block that the level above points at. Adding it to that block's
    /// origin in the cache of level `n` gives the cache cell. For
    /// `n = nmax` this is the voxel inside the brick (without apron: a pool
    /// with an apron of `a` voxels adds `a` on every axis, thesis eq. 3.6).
    pub fn offset_in_block(&self, l: usize, n: usize, p: [f64; 3]) -> Dims3 {
        let b = self.block(n);
        let e = self.pt_entry_index(l, n, p);
        [e[0] % b[0], e[1] % b[1], e[2] % b[2]]
    }

    /// Brick coordinates (in level `l`'s brick grid) of the brick holding
    /// `p`; the same as the entry index at level `nmax - 1`.
    pub fn brick_index(&self, l: usize, p: [f64; 3]) -> Dims3 {
        self.pt_entry_index(l, self.nmax() - 1, p)
    }

    /// §5.5: converts a position normalized to level `l`'s *real* volume
    /// (`p_real = 1` at the last real voxel's far face) into the position
    /// normalized to its *virtual* volume, which the lookups take:
    /// `p_real ⊙ real[l][nmax] ⊘ virt[l][nmax]`.
    ///
    /// The paper writes this product with the names the other way round
    /// (`p_real = p_virtual ⊙ (r ⊘ v)`); the thesis (`p' = p ⊙ (r ⊘ v)`)
    /// makes clear that the input is the user's position and the output the
    /// one fed to equations 1–2, which is what this function does. Positions
    /// normalized to the real volume are the ones that mean the same place
    /// at every level.
    pub fn virtual_from_real(&self, l: usize, p_real: [f64; 3]) -> [f64; 3] {
        let n = self.nmax();
        let (r, v) = (self.real[l][n], self.virt[l][n]);
        [0, 1, 2].map(|a| p_real[a] * r[a] as f64 / v[a] as f64)
    }

    /// Inverse of [`VirtualLayout::virtual_from_real`]:
    /// `p_virtual ⊙ virt[l][nmax] ⊘ real[l][nmax]` (values above 1 are in
    /// the padding beyond the real volume).
    pub fn real_from_virtual(&self, l: usize, p_virtual: [f64; 3]) -> [f64; 3] {
        let n = self.nmax();
        let (r, v) = (self.real[l][n], self.virt[l][n]);
        [0, 1, 2].map(|a| p_virtual[a] * v[a] as f64 / r[a] as f64)
    }

    /// Converts voxel-centre coordinates of level `l` (voxel `i` has its
    /// centre at coordinate `i`, so integer coordinates are voxel centres)
    /// into the normalized *virtual* position: `(voxel + 0.5) ⊘ virt[l][nmax]`.
    /// Integer coordinates map to the middle of their voxel, so
    /// `pt_entry_index(l, nmax, voxel_to_p(l, i)) == i` without any
    /// rounding hazard. (The paper's example uses the voxel's corner,
    /// `p = i ⊘ v`; both fall in the same voxel.)
    pub fn voxel_to_p(&self, l: usize, voxel: [f64; 3]) -> [f64; 3] {
        let v = self.virt[l][self.nmax()];
        [0, 1, 2].map(|a| (voxel[a] + 0.5) / v[a] as f64)
    }
}

/// Largest slot coordinate (exclusive) a [`PageEntry`] can store per axis:
/// slots are packed in 10 bits per axis, so a brick pool or page-table
/// cache can be at most 1024 blocks along each axis (2³⁰ blocks in all —
/// far beyond what GPU 3D texture limits allow anyway).
pub const MAX_SLOTS_PER_AXIS: u32 = 1 << PageEntry::SLOT_BITS;

/// The state of a page-table entry (top two bits of [`PageEntry::word`]).
#[repr(u32)]
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize)]
pub enum PageFlag {
    /// Not resident: a lookup reaching it is a cache miss. Zero, so a
    /// zero-filled buffer is a valid, fully unmapped table.
    Unmapped = 0,
    /// Resident: the entry carries the slot of its block/brick in the
    /// cache of the next level.
    Mapped = 1,
    /// Everything below this entry is empty (contributes nothing): no slot,
    /// and no cache miss either.
    Empty = 2,
    /// Every voxel below this entry has the same value, stored in
    /// [`PageEntry::value`]: no slot, no cache miss.
    Constant = 3,
}

/// One page-table entry (directory or page-table cache), 8 bytes: one
/// `Rg32Uint` texel on the GPU.
///
/// `word` layout (bit 31 highest):
///
/// ```text
///  31 30 | 29 ....... 20 | 19 ....... 10 | 9 ......... 0
///  flag  |    slot z     |    slot y     |    slot x
/// ```
///
/// The slot is the 3D index, in *blocks*, of the block (page-table block or
/// brick) in the cache of the next level; its first cell is
/// `slot ⊙ b_{n+1}` (plus the apron, in a brick pool with aprons: the
/// paper stores the cell coordinate itself, which would not fit in 10 bits).
/// The slot bits are zero unless the flag is [`PageFlag::Mapped`].
///
/// `value` is zero except for [`PageFlag::Constant`], where it holds the
/// voxel value's bits (see [`PageEntry::constant_of`]).
#[repr(C)]
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Default)]
pub struct PageEntry {
    pub word: u32,
    pub value: u32,
}

impl PageEntry {
    /// Position of the flag in `word`.
    pub const FLAG_SHIFT: u32 = 30;
    /// Mask of the flag bits in `word`.
    pub const FLAG_MASK: u32 = 0b11 << Self::FLAG_SHIFT;
    /// Bits per slot axis.
    pub const SLOT_BITS: u32 = 10;
    /// Mask of one slot axis (after shifting).
    pub const SLOT_MASK: u32 = (1 << Self::SLOT_BITS) - 1;
    /// Flag bits of an unmapped entry (0).
    pub const UNMAPPED: u32 = (PageFlag::Unmapped as u32) << Self::FLAG_SHIFT;
    /// Flag bits of a mapped entry.
    pub const MAPPED: u32 = (PageFlag::Mapped as u32) << Self::FLAG_SHIFT;
    /// Flag bits of an empty entry.
    pub const EMPTY: u32 = (PageFlag::Empty as u32) << Self::FLAG_SHIFT;
    /// Flag bits of a constant entry.
    pub const CONSTANT: u32 = (PageFlag::Constant as u32) << Self::FLAG_SHIFT;

    /// A non-resident entry (all zero).
    pub const fn unmapped() -> Self {
        PageEntry { word: 0, value: 0 }
    }

    /// A resident entry pointing at block `slot` (`[z, y, x]`, in blocks) of
    /// the next level's cache. Panics if a coordinate is not below
    /// [`MAX_SLOTS_PER_AXIS`].
    pub fn mapped(slot: [u32; 3]) -> Self {
        Self::try_mapped(slot).unwrap_or_else(|| {
            panic!("slot {slot:?} does not fit in a page entry (max {MAX_SLOTS_PER_AXIS} per axis)")
        })
    }

    /// Like [`PageEntry::mapped`], `None` when the slot does not fit.
    pub fn try_mapped(slot: [u32; 3]) -> Option<Self> {
        if slot.iter().any(|&s| s >= MAX_SLOTS_PER_AXIS) {
            return None;
        }
        let b = Self::SLOT_BITS;
        Some(PageEntry {
            word: Self::MAPPED | (slot[0] << (2 * b)) | (slot[1] << b) | slot[2],
            value: 0,
        })
    }

    /// An entry whose whole region is empty.
    pub const fn empty() -> Self {
        PageEntry {
            word: Self::EMPTY,
            value: 0,
        }
    }

    /// An entry whose whole region holds one value, given as raw bits.
    pub const fn constant(bits: u32) -> Self {
        PageEntry {
            word: Self::CONSTANT,
            value: bits,
        }
    }

    /// The 32-bit pattern that a constant of type `dtype` and value `value`
    /// is stored as:
    ///
    /// * `u8`, `u16`, `u32`: the value itself;
    /// * `i8`, `i16`, `i32`: the value as `i32`, bit-cast (sign-extended,
    ///   so a shader reads it back with `bitcast<i32>`);
    /// * `f32`: its bits;
    /// * `f64`: **narrowed to `f32`** and stored as the `f32` bits. The GPU
    ///   path samples `f32` anyway; producers that need the exact `f64`
    ///   value back (CPU processing) should mark a brick constant only when
    ///   `value as f32 as f64 == value`.
    pub fn constant_bits_of(dtype: DType, value: f64) -> u32 {
        match dtype {
            DType::U8 | DType::U16 | DType::U32 => value as u32,
            DType::I8 | DType::I16 | DType::I32 => (value as i32) as u32,
            DType::F32 | DType::F64 => (value as f32).to_bits(),
        }
    }

    /// A constant entry for `value` of type `dtype` (see
    /// [`PageEntry::constant_bits_of`]).
    pub fn constant_of(dtype: DType, value: f64) -> Self {
        Self::constant(Self::constant_bits_of(dtype, value))
    }

    /// The flag of this entry.
    pub fn flag(self) -> PageFlag {
        match self.word >> Self::FLAG_SHIFT {
            0 => PageFlag::Unmapped,
            1 => PageFlag::Mapped,
            2 => PageFlag::Empty,
            _ => PageFlag::Constant,
        }
    }

    /// The slot (`[z, y, x]`, in blocks) of a mapped entry; `None` otherwise.
    pub fn slot(self) -> Option<[u32; 3]> {
        if self.flag() != PageFlag::Mapped {
            return None;
        }
        let (b, m) = (Self::SLOT_BITS, Self::SLOT_MASK);
        Some([
            (self.word >> (2 * b)) & m,
            (self.word >> b) & m,
            self.word & m,
        ])
    }

    /// The raw constant bits of a constant entry; `None` otherwise.
    pub fn constant_bits(self) -> Option<u32> {
        (self.flag() == PageFlag::Constant).then_some(self.value)
    }

    /// The constant value of a constant entry, read back as `dtype`
    /// (`f64` volumes get the `f32`-rounded value); `None` otherwise.
    pub fn constant_value(self, dtype: DType) -> Option<f64> {
        let bits = self.constant_bits()?;
        Some(match dtype {
            DType::U8 | DType::U16 | DType::U32 => bits as f64,
            DType::I8 | DType::I16 | DType::I32 => bits as i32 as f64,
            DType::F32 | DType::F64 => f32::from_bits(bits) as f64,
        })
    }
}

/// Bytes per usage-buffer entry (a `u32` frame timestamp per slot/block).
pub const USAGE_BYTES: u64 = 4;
/// Bytes per LRU entry in brickyard (a `u32` slot index).
pub const LRU_BYTES: u64 = 4;
/// Request-hash slots per request of the per-frame cap.
pub const REQUEST_HASH_SLOTS_PER_CAP: u64 = 8;
/// Bytes per request-hash slot: 64-bit brick key, `u32` hit count, 4 bytes
/// padding.
pub const REQUEST_HASH_ENTRY_BYTES: u64 = 16;
/// Bytes per entry of the capped request list read back to the CPU (same
/// record as the hash slot).
pub const REQUEST_LIST_ENTRY_BYTES: u64 = 16;

/// The thesis's page entry: `uint4` (three coordinates and a flag).
pub const PAPER_ENTRY_BYTES: u64 = 16;
/// The thesis's request-buffer entry: a `u32` timestamp per brick.
pub const PAPER_REQUEST_BYTES: u64 = 4;
/// The thesis's usage-buffer entry: a `u32` timestamp per slot.
pub const PAPER_USAGE_BYTES: u64 = 4;
/// The thesis's LRU entry: cache position (3 × u32), level (i32) and
/// position `p` (3 × f32) = 28 bytes.
pub const PAPER_LRU_BYTES: u64 = 28;

/// Memory of the virtual-memory structures, line by line, in bytes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Footprint {
    /// `(what, bytes)`, in a stable order.
    pub lines: Vec<(String, u64)>,
}

impl Footprint {
    /// brickyard's own footprint for `layout` with a brick pool of
    /// `pool_slots` bricks of `brick_bytes_with_apron` bytes, page-table
    /// caches of `pt_cache_blocks[n-1]` blocks for each intermediate level
    /// `n` (one number per page-table level), and at most `request_cap`
    /// requests read back per frame.
    ///
    /// Lines: `directory` (8-byte [`PageEntry`] per cell), `pt cache n`
    /// (blocks × entries per block × 8 B), `usage: pool` / `usage: pt cache
    /// n` and `lru: pool` / `lru: pt cache n` (4 B per slot or block each),
    /// `request hash`, `request list`, and `pool`.
    ///
    /// Requests are collected in an open-addressing hash of
    /// `request_cap × 8` slots of 16 bytes (64-bit brick key, `u32` count of
    /// samples that asked for it, padding): each miss inserts or bumps its
    /// brick, the hash keeps the distinct misses of a frame with their
    /// counts (so the `request_cap` most wanted can be chosen), and a full
    /// hash drops further new keys until the next frame. Unlike the paper's
    /// request buffer (one timestamp per brick of the pyramid), its size
    /// does not depend on the volume.
    pub fn of(
        layout: &VirtualLayout,
        pool_slots: u64,
        pt_cache_blocks: &[u64],
        brick_bytes_with_apron: u64,
        request_cap: u64,
    ) -> Footprint {
        assert_eq!(
            pt_cache_blocks.len(),
            layout.pt_levels(),
            "one page-table cache size per page-table level"
        );
        let entry = std::mem::size_of::<PageEntry>() as u64;
        let mut lines = vec![("directory".to_string(), layout.dir_entries() * entry)];
        for (i, &blocks) in pt_cache_blocks.iter().enumerate() {
            let per_block = count(layout.block(i + 1));
            lines.push((format!("pt cache {}", i + 1), blocks * per_block * entry));
        }
        lines.push(("usage: pool".to_string(), pool_slots * USAGE_BYTES));
        for (i, &blocks) in pt_cache_blocks.iter().enumerate() {
            lines.push((format!("usage: pt cache {}", i + 1), blocks * USAGE_BYTES));
        }
        lines.push(("lru: pool".to_string(), pool_slots * LRU_BYTES));
        for (i, &blocks) in pt_cache_blocks.iter().enumerate() {
            lines.push((format!("lru: pt cache {}", i + 1), blocks * LRU_BYTES));
        }
        lines.push((
            "request hash".to_string(),
            request_cap * REQUEST_HASH_SLOTS_PER_CAP * REQUEST_HASH_ENTRY_BYTES,
        ));
        lines.push((
            "request list".to_string(),
            request_cap * REQUEST_LIST_ENTRY_BYTES,
        ));
        lines.push(("pool".to_string(), pool_slots * brick_bytes_with_apron));
        Footprint { lines }
    }

    /// The thesis's accounting of management memory (§6.3, Tables 6.2–6.4),
    /// for comparison: a directory of 16-byte entries (`MRPD`), a request
    /// buffer of 4 bytes per cell of the brick grids laid out like a
    /// one-level directory (`request buffer`, see
    /// [`VirtualLayout::brick_dir_dims`]), and per cache a 4-byte usage
    /// entry and a 28-byte LRU entry per element (`usage: brick cache`,
    /// `usage: pt cache n`, `LRU: brick cache`, `LRU: pt cache n`). The
    /// brick cache holds [`Footprint::paper_capacity`] bricks;
    /// `pt_cache_blocks` gives the page-table cache sizes (one per
    /// page-table level; Table 6.3 implies 2000 blocks). Caches themselves
    /// are not counted, as in the thesis.
    pub fn paper_equivalent(
        layout: &VirtualLayout,
        cache_bytes: u64,
        brick_bytes: u64,
        pt_cache_blocks: &[u64],
    ) -> Footprint {
        assert_eq!(
            pt_cache_blocks.len(),
            layout.pt_levels(),
            "one page-table cache size per page-table level"
        );
        let cap = Self::paper_capacity(cache_bytes, brick_bytes);
        let mut lines = vec![
            ("MRPD".to_string(), layout.dir_entries() * PAPER_ENTRY_BYTES),
            (
                "request buffer".to_string(),
                count(layout.brick_dir_dims()) * PAPER_REQUEST_BYTES,
            ),
            ("usage: brick cache".to_string(), cap * PAPER_USAGE_BYTES),
        ];
        for (i, &blocks) in pt_cache_blocks.iter().enumerate() {
            lines.push((
                format!("usage: pt cache {}", i + 1),
                blocks * PAPER_USAGE_BYTES,
            ));
        }
        lines.push(("LRU: brick cache".to_string(), cap * PAPER_LRU_BYTES));
        for (i, &blocks) in pt_cache_blocks.iter().enumerate() {
            lines.push((format!("LRU: pt cache {}", i + 1), blocks * PAPER_LRU_BYTES));
        }
        Footprint { lines }
    }

    /// Bricks in a brick cache of `cache_bytes`, as the thesis counts them:
    /// rounded **up** (its Table 6.2 lists 61036 bricks of 64 KiB for
    /// 4 GB = 4·10⁹ B, i.e. ⌈61035.2⌉).
    pub fn paper_capacity(cache_bytes: u64, brick_bytes: u64) -> u64 {
        cache_bytes.div_ceil(brick_bytes)
    }

    /// Sum of all lines.
    pub fn total(&self) -> u64 {
        self.lines.iter().map(|(_, b)| b).sum()
    }

    /// Bytes of the line called `name`.
    pub fn get(&self, name: &str) -> Option<u64> {
        self.lines.iter().find(|(n, _)| n == name).map(|&(_, b)| b)
    }

    /// Sum of the lines whose name starts with `prefix`.
    pub fn sum_prefix(&self, prefix: &str) -> u64 {
        self.lines
            .iter()
            .filter(|(n, _)| n.starts_with(prefix))
            .map(|(_, b)| b)
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Paper `[x, y, z]` → brickyard `[z, y, x]`.
    fn zyx(xyz: [u64; 3]) -> Dims3 {
        [xyz[2], xyz[1], xyz[0]]
    }
    fn zyx_f(xyz: [f64; 3]) -> [f64; 3] {
        [xyz[2], xyz[1], xyz[0]]
    }

    /// The Fig. 4(a) volume: L0 8×4×1, L1 4×2×1, L2 as given (x, y, z).
    fn fig4_levels(l2_xyz: [u64; 3]) -> Vec<Dims3> {
        vec![zyx([8, 4, 1]), zyx([4, 2, 1]), zyx(l2_xyz)]
    }

    /// Table 1 rows, paper `[x, y, z]` per cell, converted to `[z, y, x]`.
    fn rows(xyz: &[&[[u64; 3]]]) -> Vec<Vec<Dims3>> {
        xyz.iter()
            .map(|r| r.iter().map(|&c| zyx(c)).collect())
            .collect()
    }

    /// Table 1(a) (configuration of Fig. 4(b)): one virtualization level,
    /// bricks of 2×2×1 voxels (x, y, z). Our `real[l]` is
    /// `[r_0 (MRPD = brick grid), r_1 (voxels)]`; the paper prints the brick
    /// grid twice (as "Vol. bricks" and as "MRPD"), both equal to `r_0`.
    ///
    /// The table lists L2 as 2×2×1 voxels although Fig. 4(a) says the
    /// coarsest level is 2×1 voxels padded to one brick: the table counts
    /// the padded brick as the real volume. With `levels` L2 = [2, 2, 1]
    /// (x, y, z) every cell matches; with the true 2×1 only `r[2]_nmax`
    /// differs (it is then the true [2, 1, 1]).
    #[test]
    fn table1a_one_level() {
        let lay = VirtualLayout::new(fig4_levels([2, 2, 1]), zyx([2, 2, 1]), vec![]);
        assert_eq!(lay.nmax(), 1);
        let real = rows(&[
            &[[4, 2, 1], [8, 4, 1]],
            &[[2, 1, 1], [4, 2, 1]],
            &[[1, 1, 1], [2, 2, 1]],
        ]);
        assert_eq!(lay.real, real);
        assert_eq!(lay.virt, real, "one level: virtual = real here");
        // Thesis Table 3.1: PageDirBase L0 [0,0,0], L1 [4,0,0], L2 [6,0,0].
        assert_eq!(
            lay.dir_base,
            vec![zyx([0, 0, 0]), zyx([4, 0, 0]), zyx([6, 0, 0])]
        );
        assert_eq!(lay.dir_dims, zyx([7, 2, 1]));
        assert_eq!(lay.block(1), zyx([2, 2, 1]));

        // The true coarsest level (2×1 voxels) changes only r[2]_nmax.
        let t = VirtualLayout::new(fig4_levels([2, 1, 1]), zyx([2, 2, 1]), vec![]);
        let mut real_true = real.clone();
        real_true[2][1] = zyx([2, 1, 1]);
        assert_eq!(t.real, real_true);
        assert_eq!(t.virt, real);
        assert_eq!(
            (t.dir_base.clone(), t.dir_dims),
            (lay.dir_base, lay.dir_dims)
        );
    }

    /// Table 1(b) (configuration of Fig. 4(c)): one page-table level with
    /// blocks of 1×2×1 entries, bricks of 2×2×1 voxels (x, y, z); nmax = 2.
    /// Our `real[l] = [r_0 (MRPD), r_1 (PT 1 entries = brick grid),
    /// r_2 (voxels)]`. The paper's real half prints "Vol. bricks" (= r_1)
    /// and then "PT 1" and "MRPD", both equal to r_0 (the number of PT
    /// blocks is the number of MRPD entries); its virtual half prints
    /// "MRPD" and "PT 1" (both v_0), then v_1 ("Vol. bricks") and v_2.
    /// Its header says `n = 2 = nmax` for the voxel column, which is n = 2
    /// here too; the thesis's Table 3.3 gives the same numbers.
    #[test]
    fn table1b_two_levels() {
        let lay = VirtualLayout::new(fig4_levels([2, 2, 1]), zyx([2, 2, 1]), vec![zyx([1, 2, 1])]);
        assert_eq!(lay.nmax(), 2);
        let real = rows(&[
            &[[4, 1, 1], [4, 2, 1], [8, 4, 1]],
            &[[2, 1, 1], [2, 1, 1], [4, 2, 1]],
            &[[1, 1, 1], [1, 1, 1], [2, 2, 1]],
        ]);
        let virt = rows(&[
            &[[4, 1, 1], [4, 2, 1], [8, 4, 1]],
            &[[2, 1, 1], [2, 2, 1], [4, 4, 1]],
            &[[1, 1, 1], [1, 2, 1], [2, 4, 1]],
        ]);
        assert_eq!(lay.real, real);
        assert_eq!(lay.virt, virt);
        assert_eq!(
            lay.dir_base,
            vec![zyx([0, 0, 0]), zyx([4, 0, 0]), zyx([6, 0, 0])]
        );
        assert_eq!(lay.dir_dims, zyx([7, 1, 1]));
        assert_eq!(
            (lay.block(1), lay.block(2)),
            (zyx([1, 2, 1]), zyx([2, 2, 1]))
        );
        assert_eq!(lay.entry_span(0), zyx([2, 4, 1]));

        let t = VirtualLayout::new(fig4_levels([2, 1, 1]), zyx([2, 2, 1]), vec![zyx([1, 2, 1])]);
        let mut real_true = real.clone();
        real_true[2][2] = zyx([2, 1, 1]);
        assert_eq!(t.real, real_true);
        assert_eq!(t.virt, virt);

        // §5.5: the real volume of L1 fills half of its virtual volume in y,
        // so the real centre sits at a quarter of the virtual y extent.
        let c = lay.virtual_from_real(1, [0.5, 0.5, 0.5]);
        assert_eq!(c, zyx_f([0.5, 0.25, 0.5]));
        assert_eq!(lay.real_from_virtual(1, c), [0.5, 0.5, 0.5]);
    }

    /// A tiny resolver over plain arrays: equations 1–3 applied literally.
    /// Returns the cells visited (directory cell, then the cell of each
    /// cache level) and either the data-cache voxel or the level and flag
    /// where the walk stopped.
    struct Hierarchy {
        dir: Vec<PageEntry>,
        /// `(entries, dims in entries)` of each page-table cache.
        pt: Vec<(Vec<PageEntry>, Dims3)>,
    }

    fn at(dims: Dims3, c: Dims3) -> usize {
        assert!((0..3).all(|a| c[a] < dims[a]), "{c:?} outside {dims:?}");
        ((c[0] * dims[1] + c[1]) * dims[2] + c[2]) as usize
    }

    type Walk = (Vec<Dims3>, Result<Dims3, (usize, PageFlag)>);

    fn resolve(lay: &VirtualLayout, h: &Hierarchy, l: usize, p: [f64; 3]) -> Walk {
        let mut trail = vec![lay.dir_entry(l, p)];
        let mut entry = h.dir[at(lay.dir_dims, trail[0])];
        for n in 1..=lay.nmax() {
            let Some(slot) = entry.slot() else {
                return (trail, Err((n - 1, entry.flag())));
            };
            let b = lay.block(n);
            let off = lay.offset_in_block(l, n, p);
            let cell = [0, 1, 2].map(|a| slot[a] as u64 * b[a] + off[a]);
            trail.push(cell);
            if n == lay.nmax() {
                return (trail, Ok(cell));
            }
            let (entries, dims) = &h.pt[n - 1];
            entry = entries[at(*dims, cell)];
        }
        unreachable!()
    }

    fn set(v: &mut [PageEntry], dims: Dims3, c: Dims3, e: PageEntry) {
        v[at(dims, c)] = e;
    }

    /// §5.4 worked example (Fig. 4(b) and thesis Fig. 3.12a), one
    /// virtualization level. The data cache is 2×2 bricks (4×4 voxels).
    /// From the text: MRPD[0,0,0] points at the brick whose first voxel is
    /// [2,0,0] in the data cache (brick slot [1,0,0], x, y, z), and from the
    /// update example (§5.6 / thesis §3.7.1) the L0 brick at x = 2 (MRPD
    /// [2,0,0]) sits in the data cache at [0,0,0]. Other entries unmapped.
    #[test]
    fn worked_example_one_level() {
        let lay = VirtualLayout::new(fig4_levels([2, 1, 1]), zyx([2, 2, 1]), vec![]);
        let mut dir = vec![PageEntry::unmapped(); lay.dir_entries() as usize];
        let d = lay.dir_dims;
        set(&mut dir, d, zyx([0, 0, 0]), PageEntry::mapped([0, 0, 1]));
        set(&mut dir, d, zyx([2, 0, 0]), PageEntry::mapped([0, 0, 0]));
        let h = Hierarchy { dir, pt: vec![] };

        // l = 0, p = [1/8, 1/4, 0] (x, y, z).
        let p = zyx_f([1.0 / 8.0, 1.0 / 4.0, 0.0]);
        assert_eq!(lay.dir_entry(0, p), zyx([0, 0, 0]));
        assert_eq!(lay.offset_in_block(0, 1, p), zyx([1, 1, 0]));
        let (trail, hit) = resolve(&lay, &h, 0, p);
        assert_eq!(
            hit,
            Ok(zyx([3, 1, 0])),
            "the paper's data-cache coordinates"
        );
        assert_eq!(trail, vec![zyx([0, 0, 0]), zyx([3, 1, 0])]);
        // The same voxel through voxel-centre coordinates (voxel x=1, y=1).
        let pc = lay.voxel_to_p(0, [0.0, 1.0, 1.0]);
        assert_eq!(resolve(&lay, &h, 0, pc).1, Ok(zyx([3, 1, 0])));

        // Voxel (5, 1, 0) lives in the brick at data-cache slot [0, 0, 0].
        let q = lay.voxel_to_p(0, [0.0, 1.0, 5.0]);
        assert_eq!(resolve(&lay, &h, 0, q).1, Ok(zyx([1, 1, 0])));
        // Voxel (3, 0, 0): MRPD [1, 0, 0] is unmapped → miss at the directory.
        let r = lay.voxel_to_p(0, [0.0, 0.0, 3.0]);
        assert_eq!(
            resolve(&lay, &h, 0, r),
            (vec![zyx([1, 0, 0])], Err((0, PageFlag::Unmapped)))
        );
        // L1 lives at x = 4.. in the directory, L2 at x = 6.
        assert_eq!(lay.dir_entry(1, [0.0, 0.9, 0.9]), zyx([5, 0, 0]));
        assert_eq!(lay.dir_entry(2, [1.0, 1.0, 1.0]), zyx([6, 0, 0]));
    }

    /// §5.4 with two virtualization levels (Fig. 4(c), thesis Fig. 3.12b):
    /// the MRPD points at PT blocks of 1×2 entries, PT entries at bricks.
    /// From the thesis's walk-through: MRPD[0,0,0].c = [2,0,0] (PT block at
    /// PT-cache column 2, block slot [2,0,0]), PTCache_1[2,0,0].c = [2,0,0]
    /// (brick slot [1,0,0]) → data cache [3,1,0]. From its update example:
    /// MRPD[2,0,0] points at PT block [1,0,0], whose entry [1,0,0] points at
    /// the brick in data-cache slot [0,0,0]. The PT cache is 3×1 blocks
    /// (3×2 entries), enough for those two blocks.
    #[test]
    fn worked_example_two_levels() {
        let lay = VirtualLayout::new(fig4_levels([2, 1, 1]), zyx([2, 2, 1]), vec![zyx([1, 2, 1])]);
        let d = lay.dir_dims;
        let mut dir = vec![PageEntry::unmapped(); lay.dir_entries() as usize];
        set(&mut dir, d, zyx([0, 0, 0]), PageEntry::mapped([0, 0, 2]));
        set(&mut dir, d, zyx([2, 0, 0]), PageEntry::mapped([0, 0, 1]));
        let pd = zyx([3, 2, 1]);
        let mut pt = vec![PageEntry::unmapped(); count(pd) as usize];
        set(&mut pt, pd, zyx([2, 0, 0]), PageEntry::mapped([0, 0, 1]));
        set(&mut pt, pd, zyx([1, 0, 0]), PageEntry::mapped([0, 0, 0]));
        let h = Hierarchy {
            dir,
            pt: vec![(pt, pd)],
        };

        let p = zyx_f([1.0 / 8.0, 1.0 / 4.0, 0.0]);
        let (trail, hit) = resolve(&lay, &h, 0, p);
        assert_eq!(hit, Ok(zyx([3, 1, 0])));
        // PDentry = [0,0,0], Centry_1 = [2,0,0], Centry_2 = [3,1,0].
        assert_eq!(trail, vec![zyx([0, 0, 0]), zyx([2, 0, 0]), zyx([3, 1, 0])]);

        let q = lay.voxel_to_p(0, [0.0, 1.0, 5.0]);
        let (trail, hit) = resolve(&lay, &h, 0, q);
        assert_eq!(hit, Ok(zyx([1, 1, 0])));
        assert_eq!(trail[1], zyx([1, 0, 0]), "the thesis's PT entry [1,0,0]");
        // Voxel (4, 2, 0): MRPD [2,0,0] is mapped, but the PT entry
        // [1,1,0] is not → miss at level 1.
        let r = lay.voxel_to_p(0, [0.0, 2.0, 4.0]);
        assert_eq!(
            resolve(&lay, &h, 0, r),
            (
                vec![zyx([2, 0, 0]), zyx([1, 1, 0])],
                Err((1, PageFlag::Unmapped))
            )
        );
    }

    #[test]
    fn page_entry_round_trips() {
        assert_eq!(std::mem::size_of::<PageEntry>(), 8);
        assert_eq!(std::mem::align_of::<PageEntry>(), 4);
        assert_eq!(PageEntry::default(), PageEntry::unmapped());
        assert_eq!(PageEntry::unmapped().flag(), PageFlag::Unmapped);
        assert_eq!(PageEntry::unmapped().word, 0);
        assert_eq!(PageEntry::empty().flag(), PageFlag::Empty);
        assert_eq!(PageEntry::empty().slot(), None);
        assert_eq!(PageEntry::empty().constant_bits(), None);

        let m = MAX_SLOTS_PER_AXIS - 1;
        for s in [[0, 0, 0], [1, 2, 3], [m, 0, m], [m, m, m], [7, m, 512]] {
            let e = PageEntry::mapped(s);
            assert_eq!(e.flag(), PageFlag::Mapped);
            assert_eq!(e.slot(), Some(s));
            assert_eq!(e.constant_bits(), None);
            assert_eq!(e.word & PageEntry::FLAG_MASK, PageEntry::MAPPED);
        }
        assert_eq!(
            PageEntry::mapped([1, 2, 3]).word,
            (1 << 30) | (1 << 20) | (2 << 10) | 3
        );
        assert_eq!(MAX_SLOTS_PER_AXIS, 1024);
        assert!(PageEntry::try_mapped([0, MAX_SLOTS_PER_AXIS, 0]).is_none());

        for bits in [0, 1, 0x8000_0000, u32::MAX, 1.5f32.to_bits()] {
            let e = PageEntry::constant(bits);
            assert_eq!(e.flag(), PageFlag::Constant);
            assert_eq!(e.constant_bits(), Some(bits));
            assert_eq!(e.slot(), None);
        }
        let cases = [
            (DType::U8, 255.0, 255u32),
            (DType::U16, 65535.0, 65535),
            (DType::U32, 4e9, 4_000_000_000),
            (DType::I8, -1.0, u32::MAX),
            (DType::I16, -300.0, (-300i32) as u32),
            (DType::I32, 123.0, 123),
            (DType::F32, 0.25, 0.25f32.to_bits()),
            (DType::F64, 0.5, 0.5f32.to_bits()),
        ];
        for (dt, v, bits) in cases {
            let e = PageEntry::constant_of(dt, v);
            assert_eq!(e.constant_bits(), Some(bits), "{dt:?}");
            assert_eq!(e.constant_value(dt), Some(v), "{dt:?}");
        }
        // f64 constants go through f32.
        let e = PageEntry::constant_of(DType::F64, 0.1);
        assert_eq!(e.constant_value(DType::F64), Some(0.1f32 as f64));
    }

    #[test]
    #[should_panic(expected = "does not fit")]
    fn mapped_rejects_slots_beyond_10_bits() {
        PageEntry::mapped([MAX_SLOTS_PER_AXIS, 0, 0]);
    }

    /// Deterministic pseudo-random numbers (SplitMix64).
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        fn range(&mut self, lo: u64, hi: u64) -> u64 {
            lo + self.next() % (hi - lo + 1)
        }
        fn unit(&mut self) -> f64 {
            (self.next() >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    #[test]
    fn equations_4_5_invariants_random() {
        let mut rng = Rng(0x5eed);
        for case in 0..400 {
            let nlev = rng.range(1, 5) as usize;
            let mut levels = vec![[0; 3].map(|_| rng.range(1, 3000))];
            for _ in 1..nlev {
                let last = *levels.last().unwrap();
                levels.push(last.map(|d| d.div_ceil(rng.range(1, 2))));
            }
            let brick = [0; 3].map(|_| rng.range(1, 40));
            let npt = rng.range(0, 3) as usize;
            let pts: Vec<Dims3> = (0..npt).map(|_| [0; 3].map(|_| rng.range(1, 9))).collect();
            let lay = VirtualLayout::new(levels.clone(), brick, pts);
            let nmax = lay.nmax();
            let ctx = format!("case {case}: {lay:?}");

            let mut used = 0;
            for (l, &dims) in levels.iter().enumerate() {
                let (r, v) = (&lay.real[l], &lay.virt[l]);
                assert_eq!(r.len(), nmax + 1);
                assert_eq!(r[nmax], dims, "{ctx}");
                assert_eq!(v[0], r[0], "{ctx}");
                for n in 0..=nmax {
                    let span = lay.entry_span(n);
                    for a in 0..3 {
                        assert!(v[n][a] >= r[n][a], "{ctx}");
                        if n < nmax {
                            assert_eq!(r[n][a], r[n + 1][a].div_ceil(lay.block(n + 1)[a]));
                        }
                        if n >= 1 {
                            assert_eq!(v[n][a], v[n - 1][a] * lay.block(n)[a]);
                            assert_eq!(v[n][a] % lay.block(n)[a], 0);
                        }
                        // Nested ceilings are one ceiling: the virtual size
                        // is the real size rounded up to a whole number of
                        // directory entries' worth of level-n elements.
                        let per_dir_entry: u64 = (1..=n).map(|k| lay.block(k)[a]).product();
                        assert_eq!(
                            v[n][a],
                            r[n][a].div_ceil(per_dir_entry) * per_dir_entry,
                            "{ctx}"
                        );
                        assert_eq!(v[nmax][a], v[n][a] * span[a]);
                    }
                }
                for a in 0..3 {
                    assert_eq!(v[nmax][a] % brick[a], 0, "{ctx}");
                }
                // Sub-grids lie side by side along x inside the directory.
                assert_eq!(lay.dir_base[l], [0, 0, used]);
                used += v[0][2];
                assert!(v[0][0] <= lay.dir_dims[0] && v[0][1] <= lay.dir_dims[1]);

                // Lookups agree with each other and with the voxel index.
                for _ in 0..20 {
                    let vox = [0, 1, 2].map(|a| rng.range(0, r[nmax][a] - 1));
                    let p = lay.voxel_to_p(l, vox.map(|x| x as f64));
                    assert_eq!(lay.pt_entry_index(l, nmax, p), vox, "{ctx}");
                    assert_eq!(lay.brick_index(l, p), [0, 1, 2].map(|a| vox[a] / brick[a]));
                    assert_eq!(
                        lay.offset_in_block(l, nmax, p),
                        [0, 1, 2].map(|a| vox[a] % brick[a])
                    );
                    for n in 1..=nmax {
                        let b = lay.block(n);
                        let up = lay.pt_entry_index(l, n - 1, p);
                        let here = lay.pt_entry_index(l, n, p);
                        let off = lay.offset_in_block(l, n, p);
                        for a in 0..3 {
                            assert_eq!(here[a] / b[a], up[a]);
                            assert_eq!(here[a] % b[a], off[a]);
                        }
                    }
                    let de = lay.dir_entry(l, p);
                    let e0 = lay.pt_entry_index(l, 0, p);
                    assert_eq!(de, [e0[0], e0[1], lay.dir_base[l][2] + e0[2]]);
                    assert!(
                        e0.iter().zip(&r[0]).all(|(e, d)| e < d),
                        "real data has real entries"
                    );

                    let q = [rng.unit(), rng.unit(), rng.unit()];
                    let back = lay.real_from_virtual(l, lay.virtual_from_real(l, q));
                    assert!((0..3).all(|a| (back[a] - q[a]).abs() < 1e-12));
                    // Real positions land in the real part of the volume.
                    let i = lay.pt_entry_index(l, nmax, lay.virtual_from_real(l, q));
                    assert!((0..3).all(|a| i[a] < r[nmax][a]), "{ctx}");
                }
                // p = 1.0 (and beyond) stays inside; p < 0 clamps to 0.
                let hi = lay.pt_entry_index(l, nmax, [1.0, 1.0, 1.0]);
                assert_eq!(hi, v[nmax].map(|x| x - 1));
                assert_eq!(lay.pt_entry_index(l, nmax, [2.0, 1.5, f64::INFINITY]), hi);
                assert_eq!(lay.pt_entry_index(l, 0, [-1.0, f64::NAN, -0.0]), [0, 0, 0]);
                let de = lay.dir_entry(l, [1.0, 1.0, 1.0]);
                assert_eq!(de[2], lay.dir_base[l][2] + v[0][2] - 1);
            }
            assert_eq!(lay.dir_dims[2], used);
            assert_eq!(
                lay.brick_count(),
                levels
                    .iter()
                    .map(|&d| count(ceil_div3(d, brick)))
                    .sum::<u64>()
            );
        }
    }

    /// The thesis's pyramid: every axis halved (rounded up) until the
    /// coarsest level fits in one brick. Reproduces its brick counts.
    fn halving_pyramid(dims: Dims3, brick: u64) -> Vec<Dims3> {
        let mut v = vec![dims];
        while v.last().unwrap().iter().any(|&d| d > brick) {
            let last = *v.last().unwrap();
            v.push(last.map(|d| d.div_ceil(2)));
        }
        v
    }

    /// Tera Mouse brain, 64000×50000×114 (x, y, z).
    const TERA: [u64; 3] = [114, 50000, 64000];
    /// Hippocampus, 2160×2560×1072 (x, y, z).
    const HIPPO: [u64; 3] = [1072, 2560, 2160];
    /// Giga Mandelbulb, 4352³.
    const MANDEL: [u64; 3] = [4352, 4352, 4352];

    #[test]
    fn auto_picks_depth() {
        let levels = halving_pyramid(TERA, 32);
        let depth = |max| VirtualLayout::auto(levels.clone(), [32; 3], [32; 3], max).pt_levels();
        // Directory sizes at depth 0..=3: 25014252, 6419, 26, 12.
        assert_eq!(depth(u64::MAX), 0);
        assert_eq!(depth(25_014_252), 0);
        assert_eq!(depth(25_014_251), 1);
        assert_eq!(depth(6419), 1);
        assert_eq!(depth(6418), 2);
        assert_eq!(depth(26), 2);
        assert_eq!(depth(25), 3);
        assert_eq!(depth(12), 3);
        // Twelve levels need twelve entries at least: saturates at depth 3.
        let sat = VirtualLayout::auto(levels.clone(), [32; 3], [32; 3], 1);
        assert_eq!((sat.pt_levels(), sat.dir_entries()), (3, 12));
        // A block of one entry never shrinks anything.
        let one = VirtualLayout::auto(levels.clone(), [32; 3], [1, 1, 1], 10);
        assert_eq!(one.pt_levels(), 0);
        // Small volume: one level is enough for any reasonable cap.
        let small = VirtualLayout::auto(halving_pyramid(HIPPO, 64), [64; 3], [32; 3], 1 << 20);
        assert_eq!((small.pt_levels(), small.dir_entries()), (0, 48280));
    }

    /// `bytes` truncated to the digits printed (`printed` in `unit` bytes),
    /// as the thesis does: every value in Tables 6.2–6.4 is the exact byte
    /// count cut (not rounded) after the printed digits, e.g. 12.9768 MB is
    /// printed 12.97 and 0.176 kB 0.17.
    fn truncated(bytes: u64, unit: u64, printed: &str) -> String {
        let dec = printed.split('.').nth(1).map_or(0, str::len) as u32;
        let scaled = bytes as u128 * 10u128.pow(dec) / unit as u128;
        if dec == 0 {
            scaled.to_string()
        } else {
            let s = format!("{:0>w$}", scaled, w = dec as usize + 1);
            let (i, f) = s.split_at(s.len() - dec as usize);
            format!("{i}.{f}")
        }
    }

    const GB4: u64 = 4_000_000_000;

    /// One column of a thesis footprint table.
    struct ThesisCol {
        name: &'static str,
        mrpd_kb: &'static str,
        request_kb: &'static str,
        usage_kb: &'static str,
        lru_kb: &'static str,
        total_mb: &'static str,
        bricks: u64,
        capacity: u64,
    }

    fn compare(fp: &Footprint, t: &ThesisCol) -> Vec<(String, String, String)> {
        vec![
            ("MRPD kB", fp.get("MRPD").unwrap(), 1000, t.mrpd_kb),
            (
                "request kB",
                fp.get("request buffer").unwrap(),
                1000,
                t.request_kb,
            ),
            ("usage kB", fp.sum_prefix("usage"), 1000, t.usage_kb),
            ("LRU kB", fp.sum_prefix("LRU"), 1000, t.lru_kb),
            ("total MB", fp.total(), 1_000_000, t.total_mb),
        ]
        .into_iter()
        .map(|(what, bytes, unit, printed)| {
            (
                what.to_string(),
                truncated(bytes, unit, printed),
                printed.to_string(),
            )
        })
        .collect()
    }

    fn print_rows(title: &str, rows: &[(String, String, String)]) {
        println!("{title}");
        for (what, ours, thesis) in rows {
            let mark = if ours == thesis { "" } else { "   <- differs" };
            println!("  {what:<14} ours {ours:>12}   thesis {thesis:>12}{mark}");
        }
    }

    /// Thesis Table 6.2: 4 GB brick cache, one virtualization level, three
    /// datasets × three brick sizes. Every byte figure matches exactly after
    /// truncation to the printed digits, and so do brick counts and
    /// capacities.
    #[test]
    fn thesis_table_6_2() {
        #[rustfmt::skip]
        let table = [
            (HIPPO, 2, 32, ThesisCol { name: "Hippocampus 32³", mrpd_kb: "6049", request_kb: "1512", usage_kb: "244", lru_kb: "1709", total_mb: "9.51", bricks: 211688, capacity: 61036 }),
            (MANDEL, 4, 32, ThesisCol { name: "Mandelbulb 32³", mrpd_kb: "81382", request_kb: "20345", usage_kb: "122", lru_kb: "854", total_mb: "102.70", bricks: 2874995, capacity: 30518 }),
            (TERA, 4, 32, ThesisCol { name: "Tera Mouse 32³", mrpd_kb: "400228", request_kb: "100057", usage_kb: "122", lru_kb: "854", total_mb: "501.26", bricks: 14328922, capacity: 30518 }),
            (HIPPO, 2, 64, ThesisCol { name: "Hippocampus 64³", mrpd_kb: "772", request_kb: "193", usage_kb: "30", lru_kb: "213", total_mb: "1.20", bricks: 26728, capacity: 7630 }),
            (MANDEL, 4, 64, ThesisCol { name: "Mandelbulb 64³", mrpd_kb: "10283", request_kb: "2570", usage_kb: "15", lru_kb: "106", total_mb: "12.97", bricks: 359539, capacity: 3815 }),
            (TERA, 4, 64, ThesisCol { name: "Tera Mouse 64³", mrpd_kb: "50073", request_kb: "12518", usage_kb: "15", lru_kb: "106", total_mb: "62.71", bricks: 1824922, capacity: 3815 }),
            (HIPPO, 2, 128, ThesisCol { name: "Hippocampus 128³", mrpd_kb: "106", request_kb: "26", usage_kb: "3.8", lru_kb: "26", total_mb: "0.16", bricks: 3608, capacity: 954 }),
            (MANDEL, 4, 128, ThesisCol { name: "Mandelbulb 128³", mrpd_kb: "1313", request_kb: "328", usage_kb: "1.9", lru_kb: "13", total_mb: "1.65", bricks: 45107, capacity: 477 }),
            (TERA, 4, 128, ThesisCol { name: "Tera Mouse 128³", mrpd_kb: "6262", request_kb: "1565", usage_kb: "1.9", lru_kb: "13", total_mb: "7.84", bricks: 260922, capacity: 477 }),
        ];
        println!("Thesis Table 6.2 (4 GB = 4e9 B cache, 1 virtualization level)");
        for (dims, bpv, b, t) in table {
            let lay = VirtualLayout::new(halving_pyramid(dims, b), [b; 3], vec![]);
            let brick_bytes = b * b * b * bpv;
            let fp = Footprint::paper_equivalent(&lay, GB4, brick_bytes, &[]);
            let rows = compare(&fp, &t);
            let mut all = rows.clone();
            all.push((
                "bricks".into(),
                lay.brick_count().to_string(),
                t.bricks.to_string(),
            ));
            let cap = Footprint::paper_capacity(GB4, brick_bytes);
            all.push(("max cached".into(), cap.to_string(), t.capacity.to_string()));
            print_rows(t.name, &all);
            for (what, ours, thesis) in all {
                assert_eq!(ours, thesis, "{}: {what}", t.name);
            }
        }
    }

    /// Thesis Table 6.3: Tera Mouse brain, 32³ bricks, 32³ PT blocks, 1–3
    /// virtualization levels; PT caches of 2000 blocks each (what the
    /// usage/LRU rows imply: +8 kB usage and +56 kB LRU per PT cache).
    ///
    /// One level matches exactly. For 2 and 3 levels the request, usage and
    /// LRU rows match exactly, but the MRPD does not: the side-by-side
    /// layout of equations 4–5 gives 6419 entries (131×49×1) and 26 entries
    /// (13×2×1), the thesis prints 763 and 11. 763 is ⌊25014252 / 32³⌋, the
    /// one-level count divided by the block volume, which ignores the
    /// per-level rounding up and the x-side-by-side padding; 11 fits no
    /// formula we found for this configuration (it is the exact count for
    /// 64³ bricks with two 32³ PT levels). So the test pins our counts and
    /// checks that substituting the thesis's MRPD count into our accounting
    /// reproduces its totals exactly, i.e. the whole difference is that
    /// count (0.09 % of the 2-level total, nothing visible at 3 levels).
    #[test]
    fn thesis_table_6_3() {
        let levels = halving_pyramid(TERA, 32);
        #[rustfmt::skip]
        let table = [
            (0, 25014252u64, 25014252u64, ThesisCol { name: "1 level", mrpd_kb: "400228", request_kb: "100057", usage_kb: "122", lru_kb: "854", total_mb: "501.26", bricks: 14328922, capacity: 30518 }),
            (1, 6419, 763, ThesisCol { name: "2 levels", mrpd_kb: "12", request_kb: "100057", usage_kb: "130", lru_kb: "910", total_mb: "101.10", bricks: 14328922, capacity: 30518 }),
            (2, 26, 11, ThesisCol { name: "3 levels", mrpd_kb: "0.17", request_kb: "100057", usage_kb: "138", lru_kb: "966", total_mb: "101.16", bricks: 14328922, capacity: 30518 }),
        ];
        println!(
            "Thesis Table 6.3 (Tera Mouse brain, 32³ bricks, 32³ PT blocks, 2000-block PT caches)"
        );
        for (npt, ours_entries, thesis_entries, t) in table {
            let lay = VirtualLayout::new(levels.clone(), [32; 3], vec![[32; 3]; npt]);
            let pt = vec![2000; npt];
            let fp = Footprint::paper_equivalent(&lay, GB4, 32 * 32 * 32 * 4, &pt);
            let mut rows = compare(&fp, &t);
            rows.push((
                "MRPD entries".into(),
                lay.dir_entries().to_string(),
                thesis_entries.to_string(),
            ));
            print_rows(t.name, &rows);
            assert_eq!(lay.dir_entries(), ours_entries);
            assert_eq!(lay.brick_count(), t.bricks);
            for (what, ours, thesis) in &rows[1..4] {
                assert_eq!(ours, thesis, "{}: {what}", t.name);
            }
            // With the thesis's MRPD entry count the totals are exact.
            let mrpd_thesis = thesis_entries * PAPER_ENTRY_BYTES;
            let total = fp.total() - fp.get("MRPD").unwrap() + mrpd_thesis;
            assert_eq!(
                truncated(total, 1_000_000, t.total_mb),
                t.total_mb,
                "{}",
                t.name
            );
            assert_eq!(
                truncated(mrpd_thesis, 1000, t.mrpd_kb),
                t.mrpd_kb,
                "{}",
                t.name
            );
            if npt == 0 {
                for (what, ours, thesis) in &rows {
                    assert_eq!(ours, thesis, "{}: {what}", t.name);
                }
            }
        }
    }

    /// Thesis Table 6.4: Hippocampus, 64³ bricks, one level, 4/8/16 GB
    /// caches. All byte rows match exactly after truncation. The capacity
    /// row does not quite: the thesis lists 15260 and 30520 bricks, exactly
    /// 2× and 4× its 4 GB figure (7630 = ⌈7629.4⌉), whereas
    /// ⌈8e9 / 524288⌉ = 15259 and ⌈16e9 / 524288⌉ = 30518; we accept a
    /// difference of up to 2 bricks (the byte rows are equal either way).
    #[test]
    fn thesis_table_6_4() {
        let lay = VirtualLayout::new(halving_pyramid(HIPPO, 64), [64; 3], vec![]);
        let brick_bytes = 64 * 64 * 64 * 2;
        #[rustfmt::skip]
        let table = [
            (GB4, ThesisCol { name: "4 GB", mrpd_kb: "772", request_kb: "193", usage_kb: "30", lru_kb: "213", total_mb: "1.20", bricks: 26728, capacity: 7630 }),
            (2 * GB4, ThesisCol { name: "8 GB", mrpd_kb: "772", request_kb: "193", usage_kb: "61", lru_kb: "427", total_mb: "1.45", bricks: 26728, capacity: 15260 }),
            (4 * GB4, ThesisCol { name: "16 GB", mrpd_kb: "772", request_kb: "193", usage_kb: "122", lru_kb: "854", total_mb: "1.94", bricks: 26728, capacity: 30520 }),
        ];
        println!("Thesis Table 6.4 (Hippocampus, 64³ bricks, 1 level)");
        for (cache, t) in table {
            let fp = Footprint::paper_equivalent(&lay, cache, brick_bytes, &[]);
            let mut rows = compare(&fp, &t);
            let cap = Footprint::paper_capacity(cache, brick_bytes);
            rows.push(("max cached".into(), cap.to_string(), t.capacity.to_string()));
            print_rows(t.name, &rows);
            for (what, ours, thesis) in &rows[..5] {
                assert_eq!(ours, thesis, "{}: {what}", t.name);
            }
            assert!(cap.abs_diff(t.capacity) <= 2, "{}: capacity {cap}", t.name);
            assert_eq!(lay.brick_count(), t.bricks);
        }
    }

    /// §5.2: 16384³ RGBA, 64³ bricks, 9 levels → the paper's request buffer
    /// is 511 × 256 × 256 timestamps ≈ 134 MB (< 3.5 % of a 4 GB cache);
    /// ours is a fixed-size hash that does not grow with the volume.
    #[test]
    fn request_buffer_134mb_example() {
        let levels = halving_pyramid([16384; 3], 64);
        assert_eq!(levels.len(), 9);
        let lay = VirtualLayout::new(levels, [64; 3], vec![]);
        assert_eq!(lay.brick_dir_dims(), [256, 256, 511]);
        let paper = Footprint::paper_equivalent(&lay, GB4, 64 * 64 * 64 * 4, &[]);
        let req = paper.get("request buffer").unwrap();
        assert_eq!(req, 511 * 256 * 256 * 4);
        assert_eq!(req / 1_000_000, 133); // "around 134 MB": 133.96 MB
        assert!((req as f64) < 0.035 * GB4 as f64);

        let pool = 1000;
        let ours = Footprint::of(&lay, pool, &[], 66 * 66 * 66 * 4, 1024);
        let hash = ours.get("request hash").unwrap();
        assert_eq!(hash, 1024 * 8 * 16);
        let small = VirtualLayout::new(halving_pyramid(HIPPO, 64), [64; 3], vec![]);
        let ours_small = Footprint::of(&small, pool, &[], 66 * 66 * 66 * 4, 1024);
        assert_eq!(
            ours_small.get("request hash"),
            Some(hash),
            "independent of the volume"
        );
        println!(
            "request structures, 16384³: paper {} B, ours {} B (hash) + {} B (list)",
            req,
            hash,
            ours.get("request list").unwrap()
        );
    }

    /// brickyard's own footprint next to the thesis's accounting for the
    /// Tera Mouse brain (32³ bricks, apron 1 → 34³ stored, RGBA, 4 GB pool,
    /// `auto` depth under a 1 Mi-entry directory).
    #[test]
    fn footprint_ours_vs_paper() {
        let levels = halving_pyramid(TERA, 32);
        let lay = VirtualLayout::auto(levels, [32; 3], [32; 3], 1 << 20);
        assert_eq!(lay.pt_levels(), 1);
        let brick_bytes = 34 * 34 * 34 * 4;
        let slots = GB4 / brick_bytes;
        let pt = [2000];
        let ours = Footprint::of(&lay, slots, &pt, brick_bytes, 4096);
        let paper = Footprint::paper_equivalent(&lay, GB4, 32 * 32 * 32 * 4, &pt);

        let e = std::mem::size_of::<PageEntry>() as u64;
        assert_eq!(ours.get("directory"), Some(6419 * e));
        assert_eq!(ours.get("pt cache 1"), Some(2000 * 32 * 32 * 32 * e));
        assert_eq!(ours.get("usage: pool"), Some(slots * 4));
        assert_eq!(ours.get("usage: pt cache 1"), Some(2000 * 4));
        assert_eq!(ours.get("lru: pool"), Some(slots * 4));
        assert_eq!(ours.get("lru: pt cache 1"), Some(2000 * 4));
        assert_eq!(ours.get("request hash"), Some(4096 * 8 * 16));
        assert_eq!(ours.get("request list"), Some(4096 * 16));
        assert_eq!(ours.get("pool"), Some(slots * brick_bytes));
        assert_eq!(ours.total(), ours.lines.iter().map(|l| l.1).sum::<u64>());
        assert_eq!(ours.get("nothing"), None);

        let management = ours.total() - ours.get("pool").unwrap() - ours.get("pt cache 1").unwrap();
        println!(
            "brickyard vs thesis accounting, Tera Mouse brain 32³, depth {}",
            lay.pt_levels()
        );
        for (n, b) in &ours.lines {
            println!("  ours   {n:<20} {b:>14} B");
        }
        for (n, b) in &paper.lines {
            println!("  paper-eq {n:<18} {b:>14} B");
        }
        println!(
            "  management (without pool and PT cache data): ours {management} B, paper-eq {} B",
            paper.total()
        );
        assert!(
            management * 10 < paper.total(),
            "bounded requests dominate the saving"
        );
    }
}
