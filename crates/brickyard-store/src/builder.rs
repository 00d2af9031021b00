//! The streaming pyramid builder: reads a source in slabs, writes level 0
//! and all coarser levels as sharded OME-Zarr 0.5, with per-brick statistics.
//!
//! Over 800 lines: the pass planner and the slab cascade of a conversion share one context.
//!
//! Memory is bounded by the configured budget whatever the volume size:
//! the volume is processed in tiles (x–y columns) of one brick of depth at a
//! time. Each level keeps one slab of bricks per tile; the downsampled rows
//! cascade level by level. A tile must be aligned to whole bricks at every
//! level it produces, so when the budget does not allow tiles that wide the
//! builder produces the levels in several passes, later passes reading back
//! the finest level of the previous one from the output (≤ 1/4 of its size).
//!
//! Output is written to `OUTPUT.partial` and renamed into place at the end,
//! so an interrupted conversion never leaves a store that looks complete.
//!
//! Several processes may share a conversion ([`Team`], MPI in
//! `brickyard-dist`): a pass's tiles are cut at *columns* (y–x blocks whole
//! in shards at every level of the pass), each column goes to one rank,
//! each rank writes the shards of its columns; rank 0 prepares the output,
//! gathers the statistics and writes the metadata last. Bricks reach a
//! shard in the same order whoever writes it, so the store is byte for byte
//! the one a single process writes.

use crate::codec::{BrickEncoder, Compression};
use crate::downsample::downsample;
use crate::error::{IoContext, Result, StoreError};
use crate::import::zarr::ZarrSource;
use crate::omezarr::{
    self, level_array_json, multiscales_json, omero_json, plain_array_json, write_json, ATTR,
    STATS_DIR,
};
use crate::shard::ShardSetWriter;
use crate::source::{SourceMeta, VolumeSource};
use brickyard_core::{as_bytes, dispatch_dtype, plan_levels, DType, Dims3, LevelPlan, Sample};
use rayon::prelude::*;
use serde::Serialize;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// The largest brick (inner chunk) edge a store may have, in voxels (a
/// 1024³ brick of 8-byte voxels is 8 GiB).
pub const MAX_BRICK: u64 = 1024;
/// The largest shard edge a store may have, in voxels.
pub const MAX_SHARD: u64 = 16384;

/// Options of a conversion.
#[derive(Debug, Clone)]
pub struct ConvertOptions {
    /// Brick (inner chunk) shape `[z, y, x]`; each must be even.
    pub brick: Dims3,
    /// Shard shape `[z, y, x]`, a multiple of the brick (clipped to the level).
    pub shard: Dims3,
    pub compression: Compression,
    /// Mode instead of mean for coarser levels.
    pub labels: bool,
    /// Memory budget in bytes.
    pub memory: u64,
    /// Replace an existing output.
    pub overwrite: bool,
    /// Overrides of what the source says (`[z, y, x]`).
    pub spacing: Option<[f64; 3]>,
    pub origin: Option<[f64; 3]>,
    pub unit: Option<String>,
    /// Columns the finer levels keep (see [`plan_passes`]): a pass goes on
    /// to coarser levels only while it has at least this many (or as many
    /// as its levels allow), so that this many processes can share it.
    /// 1 (the default): the fewest passes the memory budget allows.
    pub columns: u64,
}

impl Default for ConvertOptions {
    fn default() -> Self {
        ConvertOptions {
            brick: [64; 3],
            shard: [512; 3],
            compression: Compression::Lz4,
            labels: false,
            memory: 1 << 30,
            overwrite: false,
            spacing: None,
            origin: None,
            unit: None,
            columns: 1,
        }
    }
}

/// Receives progress in bytes of source data processed.
pub trait Progress: Sync {
    fn start(&self, total_bytes: u64);
    fn inc(&self, bytes: u64);
    fn message(&self, _msg: &str) {}
}

/// No progress reporting.
pub struct NoProgress;
impl Progress for NoProgress {
    fn start(&self, _: u64) {}
    fn inc(&self, _: u64) {}
}

/// Several processes converting one volume together (rank 0 prepares the
/// output and writes the metadata). Every rank calls the methods in the
/// same order; they are collective.
pub trait Team: Sync {
    fn rank(&self) -> usize;
    fn size(&self) -> usize;
    /// Every rank passes its outcome so far; each gets back the first
    /// failure, its message naming the rank.
    fn agree(&self, mine: std::result::Result<(), String>) -> std::result::Result<(), String>;
    /// Rank 0's `words` replace every other rank's.
    fn broadcast(&self, words: &mut Vec<u64>);
    /// Bitwise OR of `words` over all ranks, into rank 0's `words` (the
    /// others' are left as they are).
    fn or_to_root(&self, words: &mut [u64]);
    /// Sum of `words` over all ranks, into rank 0's `words`.
    fn sum_to_root(&self, words: &mut [u64]);
}

/// One process: the team of one.
pub struct Solo;
impl Team for Solo {
    fn rank(&self) -> usize {
        0
    }
    fn size(&self) -> usize {
        1
    }
    fn agree(&self, mine: std::result::Result<(), String>) -> std::result::Result<(), String> {
        mine
    }
    fn broadcast(&self, _: &mut Vec<u64>) {}
    fn or_to_root(&self, _: &mut [u64]) {}
    fn sum_to_root(&self, _: &mut [u64]) {}
}

/// What a conversion did.
#[derive(Debug, Clone, Serialize)]
pub struct ConvertReport {
    pub output: PathBuf,
    pub levels: Vec<LevelPlan>,
    pub channels: usize,
    pub dtype: DType,
    pub passes: Vec<PassPlan>,
    pub bytes_in: u64,
    pub bytes_written: u64,
    pub bricks: u64,
    pub bricks_empty: u64,
    pub bricks_constant: u64,
    pub seconds: f64,
    /// Bytes of slab memory the plan uses.
    pub planned_bytes: u64,
    /// The rescale of stored numbers the input asked for and what was done
    /// with it (see [`crate::import::scale`]).
    pub values: Option<crate::import::scale::ValueScaling>,
    /// What the importer did, or deliberately did not do, with header fields
    /// that change what values or positions mean.
    pub notes: Vec<String>,
}

/// One pass of the builder: levels `from+1 ..= to` (and `from` itself when
/// `from == 0`) produced from level `from`, in tiles of `tile` voxels
/// (`[y, x]`, in level-`from` voxels).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PassPlan {
    pub from: usize,
    pub to: usize,
    pub tile: [u64; 2],
    pub bytes: u64,
}

/// Fixed overhead we keep outside the slab plan (binary, allocator, codec
/// state, per-thread brick buffers are added separately).
const OVERHEAD: u64 = 48 << 20;

/// The memory one thread's Zstandard compressor takes for bricks of
/// `brick_bytes` at `compression`'s level (none for the other codecs): its
/// window, hash and chain tables grow with the level, up to the brick's
/// size (the encoder fits its parameters to the input). Measured on a 64³
/// u16 brick (512 KiB): about 0, 4 and 7–9 MiB a thread at levels 3, 9
/// and 15–22 beyond LZ4's memory; capped at level 22's full tables.
fn zstd_state(compression: &Compression, brick_bytes: u64) -> u64 {
    match compression {
        Compression::Zstd(l) => {
            let k = match *l {
                ..=3 => 2,
                4..=9 => 8,
                _ => 18,
            };
            (k * brick_bytes.next_power_of_two()).min(160 << 20)
        }
        _ => 0,
    }
}

/// Slab memory beyond which the planner prefers another pass to wider tiles.
const COMFORTABLE: u64 = 384 << 20;

fn gcd(a: u64, b: u64) -> u64 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// The column of a pass producing levels `from..=to`: the smallest y–x
/// block (in level-`from` voxels) whole in the shards of every one of
/// those levels (`shard` clipped to each level as the writer does), and how
/// many columns cover the level (`[y, x]`).
pub fn columns(
    levels: &[LevelPlan],
    from: usize,
    to: usize,
    brick: Dims3,
    shard: Dims3,
) -> ([u64; 2], [u64; 2]) {
    let b = &levels[from];
    let mut unit = [1u64, 1];
    for l in &levels[from..=to] {
        for (i, a) in [1usize, 2].into_iter().enumerate() {
            let sh = shard[a].min(l.dims[a].div_ceil(brick[a]) * brick[a]);
            let u = sh * (l.cum_ratio[a] / b.cum_ratio[a]);
            unit[i] = unit[i] / gcd(unit[i], u) * u;
        }
    }
    let n = [b.dims[1].div_ceil(unit[0]), b.dims[2].div_ceil(unit[1])];
    (unit, n)
}

/// Which of `ranks` ranks draws each of a pass's columns (row-major over
/// `n = [y, x]` columns of `unit` voxels of a level of `dims = [y, x]`):
/// the largest columns first, each to the rank with the fewest voxels so
/// far (ties: the lower rank, and among equal columns the earlier one).
pub fn column_owners(unit: [u64; 2], n: [u64; 2], dims: [u64; 2], ranks: usize) -> Vec<usize> {
    let area = |k: u64| {
        let (cy, cx) = (k / n[1], k % n[1]);
        let h = ((cy + 1) * unit[0]).min(dims[0]) - cy * unit[0];
        let w = ((cx + 1) * unit[1]).min(dims[1]) - cx * unit[1];
        h * w
    };
    let mut cols: Vec<u64> = (0..n[0] * n[1]).collect();
    cols.sort_by_key(|&k| (std::cmp::Reverse(area(k)), k));
    let mut load = vec![0u64; ranks.max(1)];
    let mut owner = vec![0usize; cols.len()];
    for k in cols {
        let r = (0..load.len()).min_by_key(|&r| (load[r], r)).unwrap();
        load[r] += area(k);
        owner[k as usize] = r;
    }
    owner
}

/// Plan the passes for levels `levels` under `budget` bytes of slab memory,
/// shards of `shard` voxels. A pass goes on to coarser levels only while its
/// columns ([`columns`]) number at least `min_columns`, or as many as its
/// first level (or, when fewer, its second) has; beyond, a later pass reads
/// its last level back (reading back costs: a 1024³ u8 volume in 256³ shards
/// converts in 0.8 s in one pass, 1.6 s in two). With `min_columns` 1 the
/// columns never end a pass.
pub fn plan_passes(
    levels: &[LevelPlan],
    brick: Dims3,
    shard: Dims3,
    esize: u64,
    budget: u64,
    readback_copy: bool,
    min_columns: u64,
) -> Option<Vec<PassPlan>> {
    let n = levels.len();
    let mut passes = vec![];
    let mut m = 0;
    if n == 1 {
        return Some(vec![plan_tile(
            levels,
            0,
            0,
            brick,
            esize,
            budget,
            readback_copy,
        )?]);
    }
    // Larger tiles do not make the work faster, and a later pass only reads
    // back a level that is a fraction of the size: so prefer the most levels
    // per pass that fit a comfortable slab memory, and use the whole budget
    // only when nothing fits that.
    let soft = budget.min(COMFORTABLE);
    while m < n - 1 {
        // The coarsest level that keeps the pass's columns (at least
        // min_columns of them, or as many as level m has).
        let count = |t: usize| {
            let c = columns(levels, m, t, brick, shard).1;
            c[0] * c[1]
        };
        // (A pass makes at least level m + 1: when that has fewer, the
        // pass goes on as long as the count stays at that.)
        let want = count(m).min(min_columns.max(1)).min(count(m + 1));
        let top = (m + 1..n)
            .take_while(|&t| count(t) >= want)
            .last()
            .unwrap_or(m + 1);
        let pick = |limit: u64| {
            (1..=top - m).rev().find_map(|j| {
                plan_tile(
                    levels,
                    m,
                    m + j,
                    brick,
                    esize,
                    limit,
                    readback_copy || m > 0,
                )
            })
        };
        let p = pick(soft).or_else(|| pick(budget))?;
        m = p.to;
        passes.push(p);
    }
    Some(passes)
}

fn pass_bytes(
    levels: &[LevelPlan],
    from: usize,
    to: usize,
    brick: Dims3,
    tile: [u64; 2],
    esize: u64,
    copy: bool,
) -> u64 {
    let b = &levels[from];
    let mut total = 0;
    for l in &levels[from..=to] {
        let ry = l.cum_ratio[1] / b.cum_ratio[1];
        let rx = l.cum_ratio[2] / b.cum_ratio[2];
        let ty = tile[0].div_ceil(ry).min(l.dims[1]);
        let tx = tile[1].div_ceil(rx).min(l.dims[2]);
        total += brick[0].min(l.dims[0]) * ty * tx * esize;
    }
    // The reader thread fills a second slab of the source level while the
    // first is processed.
    let slab = brick[0].min(b.dims[0]) * tile[0].min(b.dims[1]) * tile[1].min(b.dims[2]) * esize;
    total += slab;
    if copy {
        total += slab;
    }
    total
}

fn plan_tile(
    levels: &[LevelPlan],
    from: usize,
    to: usize,
    brick: Dims3,
    esize: u64,
    budget: u64,
    copy: bool,
) -> Option<PassPlan> {
    let b = &levels[from];
    let t = &levels[to];
    // Alignment unit in level-`from` voxels.
    let uy = brick[1] * (t.cum_ratio[1] / b.cum_ratio[1]);
    let ux = brick[2] * (t.cum_ratio[2] / b.cum_ratio[2]);
    let (dy, dx) = (b.dims[1], b.dims[2]);
    let bytes = |ty: u64, tx: u64| pass_bytes(levels, from, to, brick, [ty, tx], esize, copy);
    let (ty, mut tx) = (uy.min(dy), ux.min(dx));
    if bytes(ty, tx) > budget {
        return None;
    }
    // Prefer full-width tiles (contiguous reads); one alignment unit tall is
    // enough, taller tiles only cost memory.
    if bytes(ty, dx) <= budget {
        tx = dx;
    } else {
        while tx < dx && bytes(ty, (tx + ux).min(dx)) <= budget {
            tx = (tx + ux).min(dx);
        }
    }
    Some(PassPlan {
        from,
        to,
        tile: [ty, tx],
        bytes: bytes(ty, tx),
    })
}

/// Per-level output state.
struct LevelOut {
    plan: LevelPlan,
    nb: Dims3,
    per_shard: Dims3,
    writer: ShardSetWriter,
    stats: Mutex<Stats>,
}

struct Stats {
    /// `(min, max)` per channel and brick.
    minmax: Vec<[f64; 2]>,
    /// With several ranks: which bricks this rank wrote.
    mine: Vec<bool>,
}

impl LevelOut {
    fn expected_in_shard(&self, s: &[u64; 3]) -> u64 {
        (0..3)
            .map(|a| ((s[a] + 1) * self.per_shard[a]).min(self.nb[a]) - s[a] * self.per_shard[a])
            .product()
    }
}

struct Counters {
    bricks: AtomicU64,
    empty: AtomicU64,
    constant: AtomicU64,
}

/// What the memory plan of a conversion depends on.
struct MemoryPlan {
    levels: Vec<LevelPlan>,
    /// Bytes per voxel.
    esize: u64,
    /// Memory outside the slabs: [`OVERHEAD`], three bricks per thread, 16
    /// bytes of statistics per brick.
    fixed: u64,
    /// Whether a later pass's read-back is a copy (the input is a store).
    zarr_copy: bool,
}

impl MemoryPlan {
    /// The conversion's passes with `budget` bytes of slabs, if any fit.
    fn passes(&self, opts: &ConvertOptions, budget: u64) -> Option<Vec<PassPlan>> {
        plan_passes(
            &self.levels,
            opts.brick,
            opts.shard,
            self.esize,
            budget,
            self.zarr_copy,
            opts.columns,
        )
    }

    fn of(meta: &SourceMeta, opts: &ConvertOptions) -> MemoryPlan {
        let spacing = opts.spacing.or(meta.spacing).unwrap_or([1.0; 3]);
        let origin = opts.origin.or(meta.origin).unwrap_or([0.0; 3]);
        let levels = plan_levels(meta.dims, spacing, origin, opts.brick).levels;
        let esize = meta.dtype.size() as u64;
        let threads = rayon::current_num_threads() as u64;
        let brick_bytes = opts.brick.iter().product::<u64>() * esize;
        let nbricks_total: u64 = levels
            .iter()
            .map(|l| {
                (0..3)
                    .map(|a| l.dims[a].div_ceil(opts.brick[a]))
                    .product::<u64>()
            })
            .sum::<u64>()
            * meta.channels as u64;
        MemoryPlan {
            esize,
            fixed: OVERHEAD
                + threads
                    * (brick_bytes * 3
                        + meta.read_bytes
                        + zstd_state(&opts.compression, brick_bytes))
                + nbricks_total * 16,
            zarr_copy: meta.path.is_dir() || crate::storage::is_remote(&meta.path),
            levels,
        }
    }
}

/// The least `opts.memory` with which [`convert`] plans the conversion of
/// a source described by `meta` (on this thread pool): the fixed allowance
/// and the smallest slab memory whose passes fit. For callers that take
/// the converter's share out of a budget of their own (`brickyard
/// process`) and must say what that budget needs.
pub fn memory_needed(meta: &SourceMeta, opts: &ConvertOptions) -> u64 {
    let plan = MemoryPlan::of(meta, opts);
    let fits = |budget: u64| plan.passes(opts, budget).is_some();
    let fixed = plan.fixed;
    if fits(0) {
        return fixed;
    }
    // More slab memory never makes a plan fail.
    fixed.saturating_add(least_budget(1 << 20, fits))
}

/// The least budget of at least 1 that `fits`, for a `fits` that stays
/// true for every budget above one it holds for: doubling from `start`
/// to a budget that fits, then bisecting between it and the last that
/// did not. `u64::MAX` when none up to a quarter of that fits.
pub fn least_budget(start: u64, mut fits: impl FnMut(u64) -> bool) -> u64 {
    let (mut lo, mut hi) = (0u64, start.max(1));
    while !fits(hi) {
        if hi > u64::MAX / 4 {
            return u64::MAX;
        }
        (lo, hi) = (hi, hi * 2);
    }
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if fits(mid) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    hi
}

/// Refuse, before anything is written, a conversion into `output` of a
/// source described by `meta` as labels (`labels`: asked for, as
/// `--labels` does; or the source says so) that cannot be a label image:
/// float voxels (labels are integer ids; only when asked for) or more than
/// one channel (a label image holds one object id per voxel).
pub fn check_labels(output: &Path, meta: &SourceMeta, labels: bool) -> Result<()> {
    if labels && meta.dtype.is_float() {
        // Labels are integers (OME-Zarr's image-label); the mode of
        // float voxels would stand in for no object.
        return Err(StoreError::invalid(
            output,
            "labels",
            format!(
                "a label volume holds integers, this one holds {}: convert it without --labels",
                meta.dtype
            ),
        ));
    }
    if (labels || meta.labels) && meta.channels > 1 {
        // Its readers (render --labels, the label statistics) take one
        // channel: a label image of several would be written, listed,
        // and then refused by each of them.
        let why = match labels {
            true => "",
            false => " (its input marks it as labels)",
        };
        return Err(StoreError::invalid(
            output,
            "labels",
            format!(
                "a label image has one channel (one object id per voxel), and this volume has \
                 {} channels{why}: convert each channel as a label image of its own",
                meta.channels
            ),
        ));
    }
    Ok(())
}

/// Convert `src` into an OME-Zarr 0.5 pyramid at `output`. The volume is
/// treated as labels when `opts.labels` is set or the source says so
/// ([`SourceMeta::labels`](crate::SourceMeta::labels)).
pub fn convert(
    src: &dyn VolumeSource,
    output: &Path,
    opts: &ConvertOptions,
    progress: &dyn Progress,
    cancel: &AtomicBool,
) -> Result<ConvertReport> {
    convert_team(src, output, opts, progress, cancel, &Solo)
}

/// [`convert`] shared by the ranks of `team` (each with the same source
/// and options): the same store, byte for byte. Every rank returns the
/// report of the whole conversion (counts summed) or the first rank's
/// failure; the progress is the rank's own share.
pub fn convert_team(
    src: &dyn VolumeSource,
    output: &Path,
    opts: &ConvertOptions,
    progress: &dyn Progress,
    cancel: &AtomicBool,
    team: &dyn Team,
) -> Result<ConvertReport> {
    let t0 = Instant::now();
    let root_rank = team.rank() == 0;
    // A failure of any rank at a meeting point, as this rank's error.
    let team_err = |e: String| StoreError::Team(e);
    let meta = src.meta().clone();
    check_labels(output, &meta, opts.labels)?;
    let with_labels;
    let opts = if meta.labels && !opts.labels {
        with_labels = ConvertOptions {
            labels: true,
            ..opts.clone()
        };
        &with_labels
    } else {
        opts
    };
    for a in 0..3 {
        if opts.brick[a] < 2 || !opts.brick[a].is_multiple_of(2) || opts.brick[a] > MAX_BRICK {
            return Err(StoreError::invalid(
                output,
                "brick",
                format!(
                    "brick sizes must be even, from 2 to {MAX_BRICK}, got {:?}",
                    opts.brick
                ),
            ));
        }
        if opts.shard[a] > MAX_SHARD {
            return Err(StoreError::invalid(
                output,
                "shard",
                format!(
                    "shard sizes must be at most {MAX_SHARD}, got {:?}",
                    opts.shard
                ),
            ));
        }
        if opts.shard[a] == 0 || !opts.shard[a].is_multiple_of(opts.brick[a]) {
            return Err(StoreError::invalid(
                output,
                "shard",
                format!(
                    "shard {:?} must be a multiple of the brick {:?}",
                    opts.shard, opts.brick
                ),
            ));
        }
    }
    // Nothing is created above the output: its folder must exist.
    check_parent(output)?;
    check_not_link(output)?;
    check_not_in_node(output)?;
    // Refuse to touch existing data unless asked; never convert onto the input.
    if output.exists() && !opts.overwrite {
        return Err(StoreError::Refused {
            path: output.into(),
            msg: "output exists; pass --overwrite to replace it".into(),
        });
    }
    if output.exists() && !replaceable(output) {
        return Err(StoreError::Refused {
            path: output.into(),
            msg: "exists and is not a Zarr store (no zarr.json, .zgroup or .zarray in it): \
                  --overwrite replaces stores only; remove it yourself or choose another output"
                .into(),
        });
    }
    if output.exists() {
        let lost = not_remade(output);
        if !lost.is_empty() {
            let more = lost.len().saturating_sub(8);
            let mut names = lost.iter().take(8).cloned().collect::<Vec<_>>().join(", ");
            if more > 0 {
                names.push_str(&format!(" and {more} more"));
            }
            return Err(StoreError::Refused {
                path: output.into(),
                msg: format!(
                    "--overwrite would delete what a conversion does not make again: {names}; \
                     move it out of the store first, or remove the store yourself"
                ),
            });
        }
    }
    // (An output that does not exist yet: its folder's real path and name.)
    let out_real = output
        .canonicalize()
        .or_else(|e| match (output.parent(), output.file_name()) {
            (Some(p), Some(n)) => {
                let p = if p.as_os_str().is_empty() {
                    Path::new(".")
                } else {
                    p
                };
                p.canonicalize().map(|p| p.join(n))
            }
            _ => Err(e),
        });
    if let (Ok(a), Ok(b)) = (out_real, meta.path.canonicalize()) {
        if b.starts_with(&a) || a.starts_with(&b) {
            return Err(StoreError::Refused {
                path: output.into(),
                msg: "output and input overlap".into(),
            });
        }
    }
    // A unit the user names must be one OME-Zarr knows; one from the
    // input's header that is not is left out.
    if let Some(u) = &opts.unit {
        omezarr::known_unit(u).map_err(|why| StoreError::invalid(output, "unit", why))?;
    }
    let unit = opts
        .unit
        .clone()
        .or(meta.unit.clone())
        .and_then(|u| omezarr::normalize_unit(&u));
    let plan = MemoryPlan::of(&meta, opts);
    check_geometry(&plan.levels, &meta, opts, output)?;
    let budget = opts.memory.saturating_sub(plan.fixed);
    let planned = plan.passes(opts, budget);
    let MemoryPlan {
        levels,
        esize,
        fixed,
        zarr_copy,
    } = plan;
    let passes = planned.ok_or_else(|| {
        // Enough for the smallest pass from each level to the next (one
        // alignment unit of that level tall and wide), as plan_passes
        // needs it: level 0 alone understated it.
        let min_pass = |m: usize, t: usize| {
            let (b, l) = (&levels[m], &levels[t]);
            let tile =
                [1, 2].map(|a| (opts.brick[a] * (l.cum_ratio[a] / b.cum_ratio[a])).min(b.dims[a]));
            pass_bytes(&levels, m, t, opts.brick, tile, esize, zarr_copy || m > 0)
        };
        let need = (0..levels.len().saturating_sub(1))
            .map(|m| min_pass(m, m + 1))
            .chain([min_pass(0, 0)])
            .max()
            .unwrap_or(0)
            + fixed;
        StoreError::invalid(
            output,
            "memory",
            format!(
                "budget of {} is too small for bricks of {:?}{}: need at least {} MiB",
                crate::info::human_bytes(opts.memory),
                opts.brick,
                match meta.read_bytes >= 1 << 20 {
                    true => format!(
                        " and the input's chunks, {} MiB a read holds decoded",
                        meta.read_bytes >> 20
                    ),
                    false => String::new(),
                },
                need.div_ceil(1 << 20)
            ),
        )
    })?;
    // Rank 0's plan for everyone (the thread count enters the plan).
    let passes = if team.size() > 1 {
        let mut w: Vec<u64> = passes
            .iter()
            .flat_map(|p| [p.from as u64, p.to as u64, p.tile[0], p.tile[1], p.bytes])
            .collect();
        team.broadcast(&mut w);
        w.chunks_exact(5)
            .map(|c| PassPlan {
                from: c[0] as usize,
                to: c[1] as usize,
                tile: [c[2], c[3]],
                bytes: c[4],
            })
            .collect()
    } else {
        passes
    };
    let planned_bytes = passes.iter().map(|p| p.bytes).max().unwrap_or(0) + fixed;

    // Prepare the partial output next to the final one.
    let partial = partial_path(output);
    // One writer of `output` at a time: a second one would take the
    // first's partial output for a stale one and remove it.
    let mut _lock = None;
    let prepared = (|| -> Result<()> {
        if root_rank {
            _lock = Some(crate::lock::PidLock::take(
                &lock_path(output),
                &format!("writing {}", output.display()),
            )?);
            check_old(output)?;
            if output.exists() {
                crate::lock::refuse_if_in_use(output)?;
            }
            if partial.exists() {
                std::fs::remove_dir_all(&partial).at(&partial)?;
            }
            std::fs::create_dir_all(&partial).at(&partial)?;
        }
        Ok(())
    })();
    if team.size() == 1 {
        prepared?;
    } else {
        team.agree(prepared.map_err(|e| e.to_string()))
            .map_err(team_err)?;
    }
    let name = meta
        .path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let c = meta.channels;
    let dim_names: Vec<&str> = if c > 1 {
        vec!["c", "z", "y", "x"]
    } else {
        vec!["z", "y", "x"]
    };
    // Channel names: the source's, else "channel i".
    let labels: Vec<String> = (0..c)
        .map(|i| {
            meta.channel_names
                .get(i)
                .cloned()
                .unwrap_or_else(|| format!("channel {i}"))
        })
        .collect();
    // How the channels are shown, where the source says (a store's
    // `omero`): kept; defaults for the rest.
    let display: Vec<crate::ChannelDisplay> = match meta.channel_display.len() == c {
        true => meta.channel_display.clone(),
        false => vec![],
    };
    let root = |complete: bool, omero: Option<Value>| {
        let mut ome = json!({"version": "0.5", "multiscales": multiscales_json(&levels, c, unit.as_deref(), &name, opts.labels)});
        if let Some(o) = omero {
            ome["omero"] = o;
        }
        json!({
            "zarr_format": 3,
            "node_type": "group",
            "attributes": {
                "ome": ome,
                ATTR: {
                    "version": 1,
                    "complete": complete,
                    "brick": opts.brick,
                    "labels": opts.labels,
                    "stats": STATS_DIR,
                    "source": meta.path.to_string_lossy(),
                    "source_notes": meta.notes,
                    "source_values": meta.scaling,
                    "ratios": levels.iter().map(|l| l.ratio).collect::<Vec<_>>(),
                }
            }
        })
    };
    let mut outs = vec![];
    let mut prepared: Result<()> = if root_rank {
        write_json(&partial.join("zarr.json"), &root(false, None))
    } else {
        Ok(())
    };
    for (k, l) in levels.iter().enumerate() {
        let shard: Vec<u64> = (0..3)
            .map(|a| opts.shard[a].min(l.dims[a].div_ceil(opts.brick[a]) * opts.brick[a]))
            .collect();
        let nb: Dims3 = [0, 1, 2].map(|a| l.dims[a].div_ceil(opts.brick[a]));
        let per_shard: Dims3 = [0, 1, 2].map(|a| shard[a] / opts.brick[a]);
        let (shape, sh, inner, ps): (Vec<u64>, Vec<u64>, Vec<u64>, Vec<u64>) = if c > 1 {
            (
                [&[c as u64][..], &l.dims].concat(),
                [&[1][..], &shard[..]].concat(),
                [&[1][..], &opts.brick[..]].concat(),
                [&[1][..], &per_shard[..]].concat(),
            )
        } else {
            (
                l.dims.to_vec(),
                shard.clone(),
                opts.brick.to_vec(),
                per_shard.to_vec(),
            )
        };
        let dir = partial.join(k.to_string());
        if root_rank && prepared.is_ok() {
            prepared = write_json(
                &dir.join("zarr.json"),
                &level_array_json(
                    &shape,
                    &sh,
                    &inner,
                    meta.dtype,
                    opts.compression,
                    &dim_names,
                ),
            );
        }
        outs.push(LevelOut {
            plan: l.clone(),
            nb,
            per_shard,
            writer: ShardSetWriter::new(&dir, ps),
            stats: Mutex::new(Stats {
                minmax: vec![[f64::NAN; 2]; c * (nb.iter().product::<u64>() as usize)],
                mine: vec![
                    false;
                    if team.size() > 1 {
                        c * (nb.iter().product::<u64>() as usize)
                    } else {
                        0
                    }
                ],
            }),
        });
    }
    if team.size() == 1 {
        if let Err(e) = prepared {
            let _ = std::fs::remove_dir_all(&partial);
            return Err(e);
        }
    } else if let Err(e) = team.agree(prepared.map_err(|e| e.to_string())) {
        if root_rank {
            let _ = std::fs::remove_dir_all(&partial);
        }
        return Err(team_err(e));
    }

    let total: u64 = passes
        .iter()
        .map(|p| {
            let cols = columns(&levels, p.from, p.to, opts.brick, opts.shard);
            let d = levels[p.from].dims;
            let owners = column_owners(cols.0, cols.1, [d[1], d[2]], team.size());
            let mine: u64 = (0..cols.1[0] * cols.1[1])
                .filter(|&k| owners[k as usize] == team.rank())
                .map(|k| {
                    let (cy, cx) = (k / cols.1[1], k % cols.1[1]);
                    let h = ((cy + 1) * cols.0[0]).min(d[1]) - cy * cols.0[0];
                    let w = ((cx + 1) * cols.0[1]).min(d[2]) - cx * cols.0[1];
                    h * w
                })
                .sum();
            d[0] * mine * esize * c as u64
        })
        .sum();
    progress.start(total);
    let counters = Counters {
        bricks: AtomicU64::new(0),
        empty: AtomicU64::new(0),
        constant: AtomicU64::new(0),
    };
    let encoder = BrickEncoder::new(opts.compression, meta.dtype);
    let ctx = Ctx {
        opts,
        outs: &outs,
        encoder: &encoder,
        counters: &counters,
        cancel,
        channels: c,
        team,
    };
    // Leave nothing behind that could be mistaken for a store: rank 0
    // removes the partial output once every rank has stopped writing.
    let give_up = |e: String| {
        if root_rank {
            let _ = std::fs::remove_dir_all(&partial);
        }
        team_err(e)
    };
    let mut own_error: Option<StoreError> = None;
    let mut keep = |r: Result<()>| -> std::result::Result<(), String> {
        match r {
            Ok(()) => Ok(()),
            Err(e) => {
                let m = e.to_string();
                own_error.get_or_insert(e);
                Err(m)
            }
        }
    };
    for p in &passes {
        let r = (|| -> Result<()> {
            // Later passes read back the finest level of the previous pass.
            let readback;
            let source: &dyn VolumeSource = if p.from == 0 {
                src
            } else {
                readback = ZarrSource::open_level_array(&partial.join(p.from.to_string()))?;
                &readback
            };
            for ch in 0..c {
                dispatch_dtype!(meta.dtype, T => { run_pass::<T>(&ctx, source, p, ch, progress)?; });
            }
            Ok(())
        })();
        let mine = keep(r);
        // Every rank's shards of this pass are written before the next
        // reads them back.
        if let Err(e) = team.agree(mine) {
            let _ = give_up(String::new());
            // One process: its own error as it was.
            return Err(match (team.size(), own_error) {
                (1, Some(own)) => own,
                _ => team_err(e),
            });
        }
    }
    let r = (|| -> Result<()> {
        for o in &outs {
            o.writer.finish()?;
        }
        Ok(())
    })();
    let mine = keep(r);
    if let Err(e) = team.agree(mine) {
        let _ = give_up(String::new());
        return Err(match (team.size(), own_error) {
            (1, Some(own)) => own,
            _ => team_err(e),
        });
    }
    // The statistics and counts of every rank, on rank 0.
    if team.size() > 1 {
        for o in &outs {
            let mut st = o.stats.lock().unwrap();
            let st = &mut *st;
            // Bricks another rank wrote are zero bits here: the OR is each
            // brick's value as its writer computed it, bit for bit.
            for chunk in (0..st.minmax.len()).step_by(1 << 16) {
                let end = (chunk + (1 << 16)).min(st.minmax.len());
                let mut w: Vec<u64> = (chunk..end)
                    .flat_map(|i| match st.mine[i] {
                        true => [st.minmax[i][0].to_bits(), st.minmax[i][1].to_bits()],
                        false => [0, 0],
                    })
                    .collect();
                team.or_to_root(&mut w);
                if root_rank {
                    for (k, i) in (chunk..end).enumerate() {
                        st.minmax[i] = [f64::from_bits(w[2 * k]), f64::from_bits(w[2 * k + 1])];
                    }
                }
            }
        }
    }
    let mut sums = vec![
        outs.iter()
            .map(|o| o.writer.bytes.load(Ordering::Relaxed))
            .sum::<u64>(),
        counters.bricks.load(Ordering::Relaxed),
        counters.empty.load(Ordering::Relaxed),
        counters.constant.load(Ordering::Relaxed),
    ];
    team.sum_to_root(&mut sums);
    team.broadcast(&mut sums);
    let bytes_written = sums[0];
    let finished = if root_rank {
        finish_store(&partial, output, &outs, c, (&labels, &display), &root)
    } else {
        Ok(())
    };
    let mine = keep(finished);
    if let Err(e) = team.agree(mine) {
        let _ = give_up(String::new());
        return Err(match (team.size(), own_error) {
            (1, Some(own)) => own,
            _ => team_err(e),
        });
    }
    let notes = {
        let mut n = meta.notes.clone();
        if meta.spacing.is_none() && opts.spacing.is_none() {
            n.push(
                "the input gives no voxel spacing: 1 unit per voxel on each axis (--spacing X,Y,Z \
                 and --unit set it)"
                    .into(),
            );
        }
        // Ranks that had nothing to do in the first pass.
        let first = passes.first().map(|p| {
            let c = columns(&levels, p.from, p.to, opts.brick, opts.shard).1;
            c[0] * c[1]
        });
        if let Some(k) = first.filter(|&k| (k as usize) < team.size()) {
            n.push(format!(
                "the first pass had {k} column(s) of whole shards: {} of {} ranks had nothing \
                 to do in it; --columns {} plans passes that many ranks can share (at the \
                 cost of reading a level back)",
                team.size() - k as usize,
                team.size(),
                team.size()
            ));
        }
        n
    };
    Ok(ConvertReport {
        output: output.to_path_buf(),
        levels,
        channels: c,
        dtype: meta.dtype,
        passes,
        bytes_in: meta.channel_bytes() * c as u64,
        bytes_written,
        bricks: sums[1],
        bricks_empty: sums[2],
        bricks_constant: sums[3],
        seconds: t0.elapsed().as_secs_f64(),
        planned_bytes,
        values: meta.scaling.clone(),
        notes,
    })
}

/// Rank 0 at the end: the statistics, the root metadata saying the store
/// is complete, and the swap into place.
fn finish_store(
    partial: &Path,
    output: &Path,
    outs: &[LevelOut],
    c: usize,
    (labels, display): (&[String], &[crate::ChannelDisplay]),
    root: &dyn Fn(bool, Option<Value>) -> Value,
) -> Result<()> {
    write_stats(partial, outs, c)?;
    // Each channel's data range, from level 0's brick statistics, for the
    // `omero` windows.
    let ranges: Vec<(f64, f64)> = {
        let st = outs[0].stats.lock().unwrap();
        let st = &st.minmax;
        let per = st.len() / c.max(1);
        (0..c)
            .map(|ch| {
                st[ch * per..(ch + 1) * per]
                    .iter()
                    .filter_map(|m| crate::brick_stats::finite_range(m[0], m[1]))
                    .fold((f64::NAN, f64::NAN), |(lo, hi), m| {
                        (lo.min(m.0), hi.max(m.1))
                    })
            })
            .collect()
    };
    write_json(
        &partial.join("zarr.json"),
        &root(true, Some(omero_json(labels, &ranges, display))),
    )?;
    // Swap into place: the old output (if any) is removed only after the new
    // one is complete.
    if output.exists() {
        // (A job that began inside it since the start: the new store waits
        // beside it, as the partial output of a stopped run.)
        crate::lock::refuse_if_in_use(output)?;
        let old = old_path(output);
        std::fs::rename(output, &old).at(output)?;
        std::fs::rename(partial, output).at(output)?;
        remove_replaced(&old)?;
    } else {
        std::fs::rename(partial, output).at(output)?;
    }
    Ok(())
}

/// Refuse an output that is a symbolic link: a store is written beside
/// its output and renamed into place, which would put a folder where the
/// link was and empty the store it pointed to.
pub fn check_not_link(output: &Path) -> Result<()> {
    if output
        .symlink_metadata()
        .is_ok_and(|m| m.file_type().is_symlink())
    {
        let to = std::fs::read_link(output)
            .map(|t| format!(" (to {})", t.display()))
            .unwrap_or_default();
        return Err(StoreError::Refused {
            path: output.into(),
            msg: format!(
                "is a symbolic link{to}: give the path of the store itself (outputs are \
                 written beside it and renamed into place, which would replace the link)"
            ),
        });
    }
    Ok(())
}

/// Refuse an output whose parent folder does not exist (or is not a
/// folder): writers create the output itself, never the folders above it,
/// so a mistyped path is an error rather than a new tree of folders. A
/// path without a parent (a bare name) is in the working directory.
pub fn check_parent(output: &Path) -> Result<()> {
    if crate::storage::is_remote(output) {
        return Err(StoreError::Refused {
            path: output.into(),
            msg: "cannot write there: outputs are local paths (remote stores are read-only)".into(),
        });
    }
    // The output is made under its own name (and swapped into place by
    // renames): `.`, `..` or `/` name no new entry.
    if output.file_name().is_none() {
        return Err(StoreError::Refused {
            path: output.into(),
            msg: "expected a path that names the output to create (such as out.zarr), \
                  not a folder like `.` or `..`"
                .into(),
        });
    }
    let Some(parent) = output.parent().filter(|p| !p.as_os_str().is_empty()) else {
        return Ok(());
    };
    if parent.is_dir() {
        return Ok(());
    }
    let why = if parent.exists() {
        "is not a folder"
    } else {
        "does not exist (create it first)"
    };
    Err(StoreError::Refused {
        path: output.into(),
        msg: format!(
            "cannot write there: the parent folder {} {why}",
            parent.display()
        ),
    })
}

/// Refuse a store written inside a Zarr array (arrays hold chunks, not
/// other nodes: readers would take it for chunks, or never see it) or
/// inside a store's own `_brickyard` folder (its statistics and tables).
fn check_not_in_node(output: &Path) -> Result<()> {
    let refuse = |why: String| {
        Err(StoreError::Refused {
            path: output.into(),
            msg: format!("cannot write a store there: {why}"),
        })
    };
    let abs = std::path::absolute(output).unwrap_or_else(|_| output.to_path_buf());
    for dir in abs.ancestors().skip(1) {
        let array = dir.join(".zarray").is_file()
            || crate::omezarr::read_json(&dir.join("zarr.json"))
                .is_ok_and(|j| j.get("node_type").and_then(Value::as_str) == Some("array"));
        if array {
            return refuse(format!(
                "{} is a Zarr array, whose folder holds its chunks only",
                dir.display()
            ));
        }
        let in_store = dir.parent().is_some_and(|p| p.join("zarr.json").is_file());
        if dir.file_name().is_some_and(|n| n == "_brickyard") && in_store {
            return refuse(format!(
                "{} holds its store's statistics and tables",
                dir.display()
            ));
        }
    }
    Ok(())
}

/// Refuse voxel spacings and origins that do not stay finite numbers at
/// every level: OME-Zarr's `scale` and `translation` hold numbers only.
/// The error names where they came from: the options or the input.
fn check_geometry(
    levels: &[LevelPlan],
    meta: &SourceMeta,
    opts: &ConvertOptions,
    output: &Path,
) -> Result<()> {
    let (spacing_at, spacing_fix): (&Path, &str) = if opts.spacing.is_some() {
        (output, "choose smaller ones")
    } else {
        (&meta.path, "pass --spacing to set others")
    };
    let (origin_at, origin_fix): (&Path, &str) = if opts.origin.is_some() {
        (output, "expected finite numbers")
    } else {
        (&meta.path, "pass --origin to set another")
    };
    // Bricks are stored whole (the edge ones padded), and blosc takes at
    // most 2 GiB less its 16-byte header at once.
    let brick_bytes = opts.brick.iter().product::<u64>() * meta.dtype.size() as u64;
    if opts.compression == crate::Compression::Lz4 && brick_bytes > i32::MAX as u64 - 16 {
        return Err(StoreError::invalid(
            output,
            "brick",
            format!(
                "bricks of {:?} {} hold {} MiB, and blosc compresses at most 2 GiB less 16 bytes \
                 at once: a smaller --brick, or --compression zstd or none",
                opts.brick,
                meta.dtype,
                brick_bytes >> 20
            ),
        ));
    }
    let xyz = |v: [f64; 3]| [v[2], v[1], v[0]];
    // Spacings given here must be positive numbers (a header's that are
    // not are taken as 1, with the input's other oddities).
    if let Some(sp) = opts.spacing {
        if sp.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(StoreError::invalid(
                output,
                "spacing",
                format!("expected positive numbers, found {:?} (x, y, z)", xyz(sp)),
            ));
        }
    }
    if let Some(o) = opts.origin.or(meta.origin) {
        if o.iter().any(|v| !v.is_finite()) {
            return Err(StoreError::invalid(
                origin_at,
                "origin",
                format!("{:?} (x, y, z) is not finite; {origin_fix}", xyz(o)),
            ));
        }
    }
    // The volume's size in world units, where viewers place their cameras
    // (a renderer refuses one beyond 1e15 units, or one that cannot be
    // told from its target).
    if let Some(l0) = levels.first() {
        let size = [0, 1, 2].map(|a| meta.dims[a] as f64 * l0.scale[a]);
        let (lo, hi) = (1e-12, 1e13);
        if size.iter().any(|v| v.is_finite() && !(lo..=hi).contains(v)) {
            return Err(StoreError::invalid(
                spacing_at,
                "spacing",
                format!(
                    "{:?} (x, y, z) makes the volume {:?} units across: expected each axis \
                     from {lo:e} to {hi:e} units (a store no viewer could place a camera \
                     around); {}",
                    xyz(l0.scale),
                    xyz(size),
                    if opts.spacing.is_some() {
                        "choose others"
                    } else {
                        spacing_fix
                    }
                ),
            ));
        }
    }
    for (n, l) in levels.iter().enumerate() {
        if l.scale.iter().any(|v| !v.is_finite()) {
            return Err(StoreError::invalid(
                spacing_at,
                "spacing",
                format!(
                    "{:?} (x, y, z) is too large: level {n}'s voxel spacing {:?} is not a finite \
                     number; {spacing_fix}",
                    xyz(levels[0].scale),
                    xyz(l.scale)
                ),
            ));
        }
        if l.translation.iter().any(|v| !v.is_finite()) {
            return Err(StoreError::invalid(
                origin_at,
                "origin",
                format!(
                    "level {n}'s origin {:?} (x, y, z) is not a finite number (origin {:?}, \
                     spacing {:?})",
                    xyz(l.translation),
                    xyz(levels[0].translation),
                    xyz(levels[0].scale)
                ),
            ));
        }
    }
    Ok(())
}

/// Whether `--overwrite` may replace `path`: an empty directory or a
/// Zarr store (v3 `zarr.json`, v2 `.zgroup` or `.zarray` at its top), never
/// a file or a folder of other things.
pub fn replaceable(path: &Path) -> bool {
    if !path.is_dir() {
        return false;
    }
    let marked = ["zarr.json", ".zgroup", ".zarray"]
        .iter()
        .any(|m| path.join(m).is_file());
    marked
        || std::fs::read_dir(path)
            .map(|mut d| d.next().is_none())
            .unwrap_or(false)
}

/// What in the store at `path` a conversion into it does not write again
/// (results of `process` under `labels/` and `derived/`, label images,
/// other files and folders), as paths relative to it: `--overwrite`
/// would delete them with the old store.
pub fn not_remade(path: &Path) -> Vec<String> {
    let own = |n: &str| {
        matches!(
            n,
            "zarr.json" | ".zgroup" | ".zattrs" | ".zarray" | ".zmetadata" | "_brickyard"
        ) || (!n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
    };
    let names = |p: &Path| -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(p)
            .map(|d| {
                d.flatten()
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .collect()
            })
            .unwrap_or_default();
        v.sort();
        v
    };
    let mut lost = vec![];
    for n in names(path) {
        if own(&n) {
            continue;
        }
        if (n == "labels" || n == "derived") && path.join(&n).is_dir() {
            // (Hidden names there are what interrupted jobs left: their
            // locks and partial output, not results.)
            for m in names(&path.join(&n)) {
                if !m.starts_with('.') && m != "zarr.json" {
                    lost.push(format!("{n}/{m}"));
                }
            }
            continue;
        }
        lost.push(n);
    }
    lost
}

/// The shard edge when none is given: [`DEFAULT_SHARD`] voxels, at least
/// the brick and a multiple of it.
pub fn default_shard(brick: u64) -> u64 {
    DEFAULT_SHARD.max(brick).div_ceil(brick) * brick
}

/// The shard edge asked for when none is given (see [`default_shard`]).
pub const DEFAULT_SHARD: u64 = 512;

/// Where an unfinished conversion of `output` is written.
pub fn partial_path(output: &Path) -> PathBuf {
    beside(output, "partial")
}

/// Where a replaced store stays while its replacement is swapped in.
pub(crate) fn old_path(output: &Path) -> PathBuf {
    beside(output, "old")
}

/// The lock that keeps `output` to one writer at a time.
pub(crate) fn lock_path(output: &Path) -> PathBuf {
    beside(output, "lock")
}

/// `output`'s name with `.ext` appended, in its folder.
fn beside(output: &Path, ext: &str) -> PathBuf {
    output.with_file_name(format!(
        "{}.{ext}",
        output
            .file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    ))
}

/// The file that marks a replaced store as being removed
/// ([`remove_replaced`]): what is left of it after a kill may go.
const REPLACED_MARK: &str = ".brickyard-replaced";

/// Remove `old`, a store that a new one replaced: marked first, then its
/// metadata (so that no part of it passes for a store), then the rest,
/// the mark last. A run killed on the way leaves a marked folder, which
/// the next conversion of the same output removes ([`check_old`]).
fn remove_replaced(old: &Path) -> Result<()> {
    std::fs::write(old.join(REPLACED_MARK), b"").at(old)?;
    for m in ["zarr.json", ".zgroup", ".zattrs", ".zarray"] {
        let p = old.join(m);
        if p.is_file() {
            std::fs::remove_file(&p).at(&p)?;
        }
    }
    for e in std::fs::read_dir(old).at(old)? {
        let p = e.at(old)?.path();
        if p.file_name() == Some(std::ffi::OsStr::new(REPLACED_MARK)) {
            continue;
        }
        if p.is_dir() && !p.is_symlink() {
            std::fs::remove_dir_all(&p).at(&p)?;
        } else {
            std::fs::remove_file(&p).at(&p)?;
        }
    }
    std::fs::remove_dir_all(old).at(old)
}

/// Refuse to start when `OUTPUT.old` is in the way: the swap at the end
/// moves the old store there. One is left when a run is killed during its
/// swap: beside the new store (the old one half removed), or instead of
/// it (the old store whole: it is all there is of `output`). What a run
/// killed while it removed the old store left (marked so) is removed.
fn check_old(output: &Path) -> Result<()> {
    let old = old_path(output);
    if std::fs::symlink_metadata(&old).is_err() {
        return Ok(());
    }
    if output.exists() && old.join(REPLACED_MARK).is_file() && !old.is_symlink() {
        return std::fs::remove_dir_all(&old).at(&old);
    }
    let msg = if output.exists() {
        format!(
            "is in the way of replacing {}: left by a run stopped while it swapped in a new \
             store? remove it (or rename it) and run again",
            output.display()
        )
    } else {
        format!(
            "exists while {} does not: a run was stopped while it replaced that store, and this \
             is the store it replaced; rename it back to {} (or remove it) and run again",
            output.display(),
            output.display()
        )
    };
    Err(StoreError::Refused { path: old, msg })
}

struct Ctx<'a> {
    opts: &'a ConvertOptions,
    outs: &'a [LevelOut],
    encoder: &'a BrickEncoder,
    counters: &'a Counters,
    cancel: &'a AtomicBool,
    channels: usize,
    team: &'a dyn Team,
}

/// A slab of one level inside a tile: rows `z0..z0+rows` of the tile
/// `[y0, y0+ty) × [x0, x0+tx)`, in that level's voxels.
struct Slab<T> {
    data: Vec<T>,
    z0: u64,
    rows: u64,
    y0: u64,
    x0: u64,
    ty: u64,
    tx: u64,
}

fn run_pass<T: Sample>(
    ctx: &Ctx,
    src: &dyn VolumeSource,
    p: &PassPlan,
    ch: usize,
    progress: &dyn Progress,
) -> Result<()> {
    let base = &ctx.outs[p.from].plan;
    let [_, dy, dx] = base.dims;
    let levels: Vec<LevelPlan> = ctx.outs.iter().map(|o| o.plan.clone()).collect();
    let (unit, ncols) = columns(&levels, p.from, p.to, ctx.opts.brick, ctx.opts.shard);
    let owners = column_owners(unit, ncols, [dy, dx], ctx.team.size());
    let rank = ctx.team.rank();
    // The tiles in the order one process draws them; each cut where a
    // column ends (a tile is never taller than a column), the pieces of
    // this rank's columns drawn.
    let mut ty0 = 0;
    while ty0 < dy {
        let ty = p.tile[0].min(dy - ty0);
        let mut tx0 = 0;
        while tx0 < dx {
            let tx = p.tile[1].min(dx - tx0);
            let mut x = tx0;
            while x < tx0 + tx {
                let end = ((x / unit[1] + 1) * unit[1]).min(tx0 + tx);
                let col = (ty0 / unit[0]) * ncols[1] + x / unit[1];
                if owners[col as usize] == rank {
                    run_tile::<T>(ctx, src, p, ch, progress, [ty0, ty], [x, end - x])?;
                }
                x = end;
            }
            tx0 += tx;
        }
        ty0 += ty;
    }
    Ok(())
}

/// One tile (or the piece of a tile in one column) of a pass: `[y0, ty]`
/// and `[x0, tx]` in level-`p.from` voxels, all its depth.
fn run_tile<T: Sample>(
    ctx: &Ctx,
    src: &dyn VolumeSource,
    p: &PassPlan,
    ch: usize,
    progress: &dyn Progress,
    [ty0, ty]: [u64; 2],
    [tx0, tx]: [u64; 2],
) -> Result<()> {
    let outs = ctx.outs;
    let bz = ctx.opts.brick[0];
    let base = &outs[p.from].plan;
    let [dz, _, _] = base.dims;
    {
        {
            // Accumulators of the coarser levels for this tile.
            let mut accs: Vec<Slab<T>> = (p.from + 1..=p.to)
                .map(|k| {
                    let l = &outs[k].plan;
                    let ry = l.cum_ratio[1] / base.cum_ratio[1];
                    let rx = l.cum_ratio[2] / base.cum_ratio[2];
                    let (y0, x0) = (ty0 / ry, tx0 / rx);
                    let (y1, x1) = (
                        (ty0 + ty).div_ceil(ry).min(l.dims[1]),
                        (tx0 + tx).div_ceil(rx).min(l.dims[2]),
                    );
                    Slab {
                        data: Vec::new(),
                        z0: 0,
                        rows: 0,
                        y0,
                        x0,
                        ty: y1 - y0,
                        tx: x1 - x0,
                    }
                })
                .collect();
            // A reader thread fetches slab i+1 while slab i is processed
            // (two slab buffers in flight; the plan counts both).
            std::thread::scope(|scope| -> Result<()> {
                let (tx_slab, rx_slab) =
                    std::sync::mpsc::sync_channel::<Result<(u64, u64, Vec<T>)>>(0);
                let (tx_back, rx_back) = std::sync::mpsc::channel::<Vec<T>>();
                let (y_rng, x_rng) = (ty0..ty0 + ty, tx0..tx0 + tx);
                scope.spawn(move || {
                    let mut z0 = 0;
                    while z0 < dz {
                        let h = bz.min(dz - z0);
                        let mut buf = rx_back.try_recv().unwrap_or_default();
                        buf.resize((h * ty * tx) as usize, T::default());
                        let r = src
                            .read_region(
                                ch,
                                z0..z0 + h,
                                y_rng.clone(),
                                x_rng.clone(),
                                brickyard_core::as_bytes_mut(&mut buf),
                            )
                            .map(|()| (z0, h, buf));
                        let failed = r.is_err();
                        if tx_slab.send(r).is_err() || failed {
                            return;
                        }
                        z0 += h;
                    }
                });
                for msg in rx_slab {
                    if ctx.cancel.load(Ordering::Relaxed) {
                        return Err(StoreError::Interrupted);
                    }
                    let (z0, h, data) = msg?;
                    progress.inc(data.len() as u64 * std::mem::size_of::<T>() as u64);
                    let slab = Slab {
                        data,
                        z0,
                        rows: h,
                        y0: ty0,
                        x0: tx0,
                        ty,
                        tx,
                    };
                    if p.from == 0 {
                        write_bricks(ctx, 0, ch, &slab)?;
                    }
                    if p.to > p.from {
                        cascade(ctx, p, ch, p.from + 1, &slab, &mut accs)?;
                    }
                    let _ = tx_back.send(slab.data);
                }
                Ok(())
            })?;
        }
    }
    Ok(())
}

/// Downsample `fine` (a slab of level k-1) into the accumulator of level k;
/// when that is full (or the level ends), write its bricks and go on down.
fn cascade<T: Sample>(
    ctx: &Ctx,
    p: &PassPlan,
    ch: usize,
    k: usize,
    fine: &Slab<T>,
    accs: &mut [Slab<T>],
) -> Result<()> {
    let l = &ctx.outs[k].plan;
    let r = l.ratio;
    let bz = ctx.opts.brick[0];
    let (first, rest) = accs.split_at_mut(1);
    let acc = &mut first[0];
    if acc.rows == 0 {
        acc.z0 = fine.z0 / r[0] as u64;
        acc.data
            .resize((bz.min(l.dims[0]) * acc.ty * acc.tx) as usize, T::default());
    }
    let rows = fine.rows.div_ceil(r[0] as u64);
    debug_assert_eq!(fine.ty.div_ceil(r[1] as u64), acc.ty);
    debug_assert_eq!(fine.tx.div_ceil(r[2] as u64), acc.tx);
    let off = (acc.rows * acc.ty * acc.tx) as usize;
    let len = (rows * acc.ty * acc.tx) as usize;
    downsample(
        &fine.data[..(fine.rows * fine.ty * fine.tx) as usize],
        [fine.rows as usize, fine.ty as usize, fine.tx as usize],
        r,
        ctx.opts.labels,
        &mut acc.data[off..off + len],
    );
    acc.rows += rows;
    if acc.rows == bz || acc.z0 + acc.rows == l.dims[0] {
        let full = Slab {
            data: std::mem::take(&mut acc.data),
            z0: acc.z0,
            rows: acc.rows,
            y0: acc.y0,
            x0: acc.x0,
            ty: acc.ty,
            tx: acc.tx,
        };
        write_bricks(ctx, k, ch, &full)?;
        if k < p.to {
            cascade(ctx, p, ch, k + 1, &full, rest)?;
        }
        acc.data = full.data;
        acc.rows = 0;
    }
    Ok(())
}

/// A brick ready for its shard: statistics index, `(min, max)`, chunk key,
/// encoded bytes (`None`: all fill value), bricks expected in its shard.
type Encoded = (usize, [f64; 2], Vec<u64>, Option<Vec<u8>>, u64);

/// Cut a slab into bricks, compute their statistics, encode and write them.
fn write_bricks<T: Sample>(ctx: &Ctx, k: usize, ch: usize, s: &Slab<T>) -> Result<()> {
    let out = &ctx.outs[k];
    let b = ctx.opts.brick;
    let bzi = s.z0 / b[0];
    debug_assert_eq!(s.z0 % b[0], 0);
    debug_assert_eq!(s.y0 % b[1], 0);
    debug_assert_eq!(s.x0 % b[2], 0);
    let bys = s.y0 / b[1]..(s.y0 + s.ty).div_ceil(b[1]);
    let bxs = s.x0 / b[2]..(s.x0 + s.tx).div_ceil(b[2]);
    let list: Vec<(u64, u64)> = bys.flat_map(|y| bxs.clone().map(move |x| (y, x))).collect();
    // Bricks are encoded in parallel a few at a time and appended to their
    // shards in list order: a shard's bytes do not depend on the threads'
    // timing (nor on which process writes it).
    let batch = 2 * rayon::current_num_threads().max(1);
    let mut st = out.stats.lock().unwrap();
    for part in list.chunks(batch) {
        // A slab's bricks take long at a slow compressor (zstd:19: about
        // 0.2 s a brick a thread): Ctrl-C is answered between batches.
        if ctx.cancel.load(Ordering::Relaxed) {
            return Err(StoreError::Interrupted);
        }
        let encoded: Vec<Encoded> = part
            .par_iter()
            .map(|&(byi, bxi)| {
                let (oy, ox) = (byi * b[1] - s.y0, bxi * b[2] - s.x0);
                let vy = b[1].min(s.ty - oy) as usize;
                let vx = b[2].min(s.tx - ox) as usize;
                let vz = s.rows as usize;
                let (bz_, by_, bx_) = (b[0] as usize, b[1] as usize, b[2] as usize);
                let mut brick = vec![T::default(); bz_ * by_ * bx_];
                let mut mm: Option<(T, T)> = None;
                for z in 0..vz {
                    for y in 0..vy {
                        let src = ((z as u64 * s.ty + oy + y as u64) * s.tx + ox) as usize;
                        let row = &s.data[src..src + vx];
                        let dst = (z * by_ + y) * bx_;
                        brick[dst..dst + vx].copy_from_slice(row);
                        let (a, b) = T::min_max(row);
                        mm = Some(match mm {
                            None => (a, b),
                            Some((m0, m1)) => (T::min_max(&[m0, a]).0, T::min_max(&[m1, b]).1),
                        });
                    }
                }
                let (mn, mx) = mm
                    .map(|(a, b)| (a.to_f64(), b.to_f64()))
                    .unwrap_or((f64::NAN, f64::NAN));
                // One value besides NaN: recorded so that no reader takes
                // the brick for constant (the padding is 0, never NaN).
                #[allow(clippy::eq_op)]
                let has_nan = T::DTYPE.is_float() && mn == mx && brick.iter().any(|v| v != v);
                let (mn, mx) = crate::brick_stats::recorded(mn, mx, has_nan);
                let bytes = as_bytes(&brick);
                // Padding is zero, so for integers min/max tell whether the brick
                // is all fill value; floats also need -0.0 kept (bit test).
                let nonzero = if T::DTYPE.is_float() {
                    !(mn == 0.0 && mx == 0.0) || bytes.iter().any(|&x| x != 0)
                } else {
                    !(mn == 0.0 && mx == 0.0)
                };
                let key: Vec<u64> = if ctx.channels > 1 {
                    vec![ch as u64, bzi, byi, bxi]
                } else {
                    vec![bzi, byi, bxi]
                };
                let sidx = [
                    bzi / out.per_shard[0],
                    byi / out.per_shard[1],
                    bxi / out.per_shard[2],
                ];
                let expected = out.expected_in_shard(&sidx);
                let enc = nonzero.then(|| ctx.encoder.encode(bytes));
                let idx = ((ch as u64 * out.nb[0] + bzi) * out.nb[1] + byi) * out.nb[2] + bxi;
                (idx as usize, [mn, mx], key, enc, expected)
            })
            .collect();
        for (i, mm, key, enc, expected) in encoded {
            out.writer.put(&key, enc.as_deref(), expected)?;
            if enc.is_none() {
                ctx.counters.empty.fetch_add(1, Ordering::Relaxed);
            }
            if mm[0] == mm[1] {
                ctx.counters.constant.fetch_add(1, Ordering::Relaxed);
            }
            ctx.counters.bricks.fetch_add(1, Ordering::Relaxed);
            st.minmax[i] = mm;
            if let Some(m) = st.mine.get_mut(i) {
                *m = true;
            }
        }
    }
    Ok(())
}

/// Write the per-brick statistics as Zarr v3 arrays `_brickyard/stats/<k>`
/// of shape `[c, bz, by, bx, 2]` (min, max) in float64.
fn write_stats(root: &Path, outs: &[LevelOut], c: usize) -> Result<()> {
    write_json(
        &root.join("_brickyard/zarr.json"),
        &json!({"zarr_format": 3, "node_type": "group", "attributes": {}}),
    )?;
    write_json(
        &root.join(STATS_DIR).join("zarr.json"),
        &json!({"zarr_format": 3, "node_type": "group", "attributes": {
        "description": "per-brick (min, max) of every level: shape [channel, brick z, brick y, brick x, 2]"}}),
    )?;
    let enc = BrickEncoder::new(Compression::Zstd(3), DType::F64);
    for (k, o) in outs.iter().enumerate() {
        let nb = o.nb;
        let chunk = [1, nb[0].min(32), nb[1].min(32), nb[2].min(32), 2];
        let shape = [c as u64, nb[0], nb[1], nb[2], 2];
        let dir = root.join(STATS_DIR).join(k.to_string());
        write_json(
            &dir.join("zarr.json"),
            &plain_array_json(&shape, &chunk, DType::F64, Compression::Zstd(3)),
        )?;
        let st = o.stats.lock().unwrap();
        let st = &st.minmax;
        for ci in 0..c as u64 {
            for cz in 0..nb[0].div_ceil(chunk[1]) {
                for cy in 0..nb[1].div_ceil(chunk[2]) {
                    for cx in 0..nb[2].div_ceil(chunk[3]) {
                        let mut data =
                            vec![f64::NAN; (chunk[1] * chunk[2] * chunk[3] * 2) as usize];
                        for z in 0..chunk[1] {
                            for y in 0..chunk[2] {
                                for x in 0..chunk[3] {
                                    let (gz, gy, gx) =
                                        (cz * chunk[1] + z, cy * chunk[2] + y, cx * chunk[3] + x);
                                    if gz < nb[0] && gy < nb[1] && gx < nb[2] {
                                        let i = (((ci * nb[0] + gz) * nb[1] + gy) * nb[2] + gx)
                                            as usize;
                                        let d = (((z * chunk[2] + y) * chunk[3] + x) * 2) as usize;
                                        data[d..d + 2].copy_from_slice(&st[i]);
                                    }
                                }
                            }
                        }
                        let p = dir.join(format!("c/{ci}/{cz}/{cy}/{cx}/0"));
                        std::fs::create_dir_all(p.parent().unwrap()).at(&p)?;
                        std::fs::write(&p, enc.encode(as_bytes(&data))).at(&p)?;
                    }
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod column_tests {
    use super::*;

    #[test]
    fn owners_balance_uneven_columns() {
        // 384 voxels in columns of 256: areas 256², 256·128, 128·256, 128².
        let o = column_owners([256, 256], [2, 2], [384, 384], 2);
        // 65536 to rank 0, 32768 twice to rank 1, the last 16384 to the
        // lower rank of a tie: 81920 against 65536 voxels.
        assert_eq!(o, vec![0, 1, 1, 0]);
        // One rank takes everything; more ranks than columns leave some idle.
        assert_eq!(column_owners([8, 8], [3, 2], [24, 16], 1), vec![0; 6]);
        let o = column_owners([8, 8], [1, 2], [8, 16], 4);
        assert_eq!(o, vec![0, 1]);
    }

    #[test]
    fn passes_keep_enough_columns() {
        let brick = [16; 3];
        let shard = [32; 3];
        let plan = plan_levels([64, 256, 256], [1.0; 3], [0.0; 3], brick);
        let passes = plan_passes(&plan.levels, brick, shard, 2, 1 << 30, false, 64).unwrap();
        // Level 0 has 8×8 columns of 32, level 1 4×4 (columns of 64),
        // level 2 2×2, level 3 one: the first pass keeps level 0's 64
        // columns only with level 0 itself; its level 1 (16 columns) is
        // as many as a pass including it can have, so pass 0 makes
        // levels 0 and 1; pass 1 reads level 1 back and makes level 2 (4
        // columns); the last reads level 2 back for the rest.
        let spans: Vec<(usize, usize)> = passes.iter().map(|p| (p.from, p.to)).collect();
        assert_eq!(spans, vec![(0, 1), (1, 2), (2, 4)], "{passes:?}");
        // min_columns 1: one pass, as the memory allows.
        let passes = plan_passes(&plan.levels, brick, shard, 2, 1 << 30, false, 1).unwrap();
        assert_eq!(passes.len(), 1, "{passes:?}");
        assert_eq!(passes.last().unwrap().to, plan.levels.len() - 1);
        // One shard column: one pass as before.
        let plan = plan_levels([64, 100, 100], [1.0; 3], [0.0; 3], brick);
        let passes = plan_passes(&plan.levels, brick, [512; 3], 2, 1 << 30, false, 64).unwrap();
        assert_eq!(passes.len(), 1);
    }
}
