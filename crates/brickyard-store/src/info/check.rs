//! `brickyard info --check`: read and decode every chunk of every level and
//! of the statistics arrays, and list what is damaged.
//!
//! Over 800 lines: with its tests: 0.76k lines of code, 0.05k of tests.
//!
//! What Zarr allows is not reported: a chunk absent from its shard's index,
//! or a shard (or chunk) file missing altogether, reads as the fill value.
//! brickyard leaves out only bricks that are all 0, so where the store's
//! statistics say a brick holds anything else, its absence is reported.
//! Reported besides: files that cannot be opened or read (permissions), a
//! shard shorter than its index, an index whose CRC32C does not match, index
//! entries that point outside the shard's data, chunks that fail to decode or
//! decode to the wrong length, and decoded bricks whose minimum and maximum
//! are not those the statistics give.
//!
//! Shard indexes are read and verified here (the layout is the
//! `sharding_indexed` specification's: `(offset, length)` pairs of little-endian
//! u64 in C order, `u64::MAX` twice for an absent chunk, optionally followed
//! by a CRC32C); the chunks themselves are decoded by `zarrs` through the
//! array, one inner chunk at a time. Sharded arrays with other index codecs,
//! or array-to-array codecs before the sharding, are decoded whole shard by
//! whole shard through `zarrs`.

use crate::builder::Progress;
use crate::error::{Result, StoreError};
use crate::import::zarr::is_zarr;
use crate::omezarr::{read_json, read_multiscale, STATS_DIR};
use brickyard_core::{dispatch_dtype, DType, Sample};
use rayon::prelude::*;
use serde::Serialize;
use serde_json::Value;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::codec::api::CodecOptions;
use zarrs::array::{
    Array, ArrayBytes, ArrayShardedExt, ArrayShardedReadableExt, ArrayShardedReadableExtCache,
};
use zarrs::filesystem::FilesystemStore;

/// One damaged chunk, shard or array.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct CheckProblem {
    /// `level K` or `statistics of level K`.
    pub array: String,
    /// The inner chunk (brick) in the array's grid of inner chunks; `None`
    /// when the problem is the whole shard (or chunk file, or array).
    pub chunk: Option<Vec<u64>>,
    /// The shard (or, unsharded, the chunk) in the array's chunk grid.
    pub shard: Vec<u64>,
    /// The file concerned.
    pub path: PathBuf,
    pub error: String,
}

impl std::fmt::Display for CheckProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.chunk {
            Some(c) => write!(f, "{}, chunk {c:?}", self.array)?,
            None if self.shard.is_empty() => write!(f, "{}", self.array)?,
            None => write!(f, "{}, shard {:?} (whole file)", self.array, self.shard)?,
        }
        write!(f, ", {}: {}", self.path.display(), self.error)
    }
}

/// What `check` found.
#[derive(Debug, Clone, Serialize, Default)]
pub struct CheckReport {
    /// Arrays checked (levels and statistics).
    pub arrays: usize,
    /// Chunk positions inside the arrays (inner chunks of sharded arrays).
    pub chunks: u64,
    /// Chunks read and decoded.
    pub stored: u64,
    /// Chunks absent (fill value), legally or not.
    pub absent: u64,
    pub problems: Vec<CheckProblem>,
}

impl CheckReport {
    pub fn ok(&self) -> bool {
        self.problems.is_empty()
    }
}

/// Text summary: one line of counts, then one line per problem.
pub fn format_check(r: &CheckReport) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "  check: {} chunks in {} arrays: {} read and decoded, {} absent (fill value); {} bad",
        r.chunks,
        r.arrays,
        r.stored,
        r.absent,
        r.problems.len()
    );
    for p in &r.problems {
        let _ = writeln!(s, "  BAD: {p}");
    }
    s
}

/// The arrays of a store: `(name, directory)`, levels first, then the
/// statistics of each level that has them.
/// An array to check: its name in reports, its folder, and the level it is
/// (`None`: statistics).
type ArrayAt = (String, PathBuf, Option<usize>);

fn arrays_of(path: &Path) -> Result<Vec<ArrayAt>> {
    if crate::storage::is_remote(path) {
        return Err(StoreError::unsupported(
            path,
            "--check",
            "a remote store is checked where it is stored (`brickyard info --check` reads \
             every shard file of a local directory)",
        ));
    }
    if !path.exists() {
        return Err(StoreError::not_found(path));
    }
    if !is_zarr(path) {
        return Err(StoreError::invalid(
            path,
            "zarr.json",
            "not a Zarr store (no zarr.json, .zgroup or .zarray)",
        ));
    }
    let levels: Vec<PathBuf> = match read_multiscale(path)? {
        Some(m) => m.datasets.iter().map(|d| path.join(&d.path)).collect(),
        None => {
            if super::is_plain_group(path) {
                // A plain group (a store's `labels/`): no array to read.
                return Err(StoreError::invalid(
                    path,
                    "zarr.json",
                    "a Zarr group with no image of its own: check the images in it one by one \
                     (`brickyard info --check GROUP/NAME`)",
                ));
            }
            vec![path.to_path_buf()]
        }
    };
    let mut out = vec![];
    for (k, dir) in levels.iter().enumerate() {
        out.push((format!("level {k}"), dir.clone(), Some(k)));
    }
    for k in 0..levels.len() {
        let dir = path.join(STATS_DIR).join(k.to_string());
        if dir.join("zarr.json").exists() {
            out.push((format!("statistics of level {k}"), dir, None));
        }
    }
    Ok(out)
}

/// Per-brick `(min, max)` of one level, `None` where unknown.
struct LevelStats {
    channels: u64,
    grid: [u64; 3],
    v: Vec<Option<[f64; 2]>>,
}

impl LevelStats {
    fn get(&self, c: u64, b: &[u64]) -> Option<[f64; 2]> {
        if c >= self.channels || (0..3).any(|a| b[a] >= self.grid[a]) {
            return None;
        }
        let i = ((c * self.grid[0] + b[0]) * self.grid[1] + b[1]) * self.grid[2] + b[2];
        self.v[i as usize]
    }
}

/// How a sharded array's index is laid out, when it is one this module
/// reads itself.
#[derive(Clone, Copy)]
struct IndexLayout {
    at_end: bool,
    crc: bool,
}

fn index_layout(dir: &Path) -> Option<IndexLayout> {
    let j = read_json(&dir.join("zarr.json")).ok()?;
    let codecs = j["codecs"].as_array()?;
    // Exclusively sharded: the sharding codec is the only codec.
    let [sh] = codecs.as_slice() else {
        return None;
    };
    if sh["name"] != "sharding_indexed" {
        return None;
    }
    let conf = &sh["configuration"];
    let at_end = match conf.get("index_location").and_then(Value::as_str) {
        None | Some("end") => true,
        Some("start") => false,
        Some(_) => return None,
    };
    let names: Vec<&str> = conf["index_codecs"]
        .as_array()?
        .iter()
        .map(|c| c["name"].as_str().unwrap_or("?"))
        .collect();
    let little = |c: &Value| {
        c["configuration"]["endian"]
            .as_str()
            .is_none_or(|e| e == "little")
    };
    let crc = match names.as_slice() {
        ["bytes"] => false,
        ["bytes", "crc32c"] => true,
        _ => return None,
    };
    if !little(&conf["index_codecs"][0]) {
        return None;
    }
    Some(IndexLayout { at_end, crc })
}

/// One array to check.
struct Target<'a> {
    name: &'a str,
    dir: &'a Path,
    array: Array<FilesystemStore>,
    dtype: Option<DType>,
    /// The statistics of this level, for the expectation and the
    /// comparison of decoded bricks.
    stats: Option<&'a LevelStats>,
    /// Inner chunk shape and grid (the chunk's own for unsharded arrays).
    sub: Vec<u64>,
    subgrid: Vec<u64>,
    /// Chunks per shard along each axis (1 when unsharded).
    per_shard: Vec<u64>,
    /// Set when each inner chunk is checked on its own.
    index: Option<IndexLayout>,
    sharded: bool,
}

#[derive(Default)]
struct Tally {
    stored: u64,
    absent: u64,
    problems: Vec<CheckProblem>,
    /// Decoded values of statistics chunks: `(chunk indices, values)`.
    values: Vec<(Vec<u64>, Vec<f64>)>,
}

impl Tally {
    fn merge(mut self, o: Tally) -> Tally {
        self.stored += o.stored;
        self.absent += o.absent;
        self.problems.extend(o.problems);
        self.values.extend(o.values);
        self
    }
}

fn unravel(mut i: u64, dims: &[u64]) -> Vec<u64> {
    let mut idx = vec![0; dims.len()];
    for a in (0..dims.len()).rev() {
        idx[a] = i % dims[a];
        i /= dims[a];
    }
    idx
}

fn same(a: f64, b: f64) -> bool {
    a == b || (a.is_nan() && b.is_nan())
}

/// The rows (along the last axis) of the part of a decoded chunk of shape
/// `cs` that lies inside the array: `valid` elements along each axis.
fn clipped_rows<'a, T>(
    v: &'a [T],
    cs: &'a [u64],
    valid: &'a [u64],
) -> impl Iterator<Item = &'a [T]> {
    let n = cs.len();
    let row = valid[n - 1] as usize;
    let rows: u64 = valid[..n - 1].iter().product();
    (0..rows).map(move |r| {
        let idx = unravel(r, &valid[..n - 1]);
        let mut off = 0u64;
        for a in 0..n - 1 {
            off = off * cs[a] + idx[a];
        }
        let off = (off * cs[n - 1]) as usize;
        &v[off..off + row]
    })
}

/// Minimum and maximum (NaN ignored, as the statistics are made) of the
/// part of a decoded chunk of shape `cs` that lies inside the array:
/// `valid` elements along each axis.
fn clipped_min_max<T: Sample>(v: &[T], cs: &[u64], valid: &[u64]) -> Option<(f64, f64)> {
    let n = cs.len();
    let row = valid[n - 1] as usize;
    if row == 0 || valid.contains(&0) {
        return None;
    }
    if valid == cs {
        let (a, b) = T::min_max(v);
        return Some((a.to_f64(), b.to_f64()));
    }
    let mut mm: Option<(T, T)> = None;
    for r in clipped_rows(v, cs, valid) {
        let (a, b) = T::min_max(r);
        mm = Some(match mm {
            None => (a, b),
            Some((m0, m1)) => (T::min_max(&[m0, a]).0, T::min_max(&[m1, b]).1),
        });
    }
    mm.map(|(a, b)| (a.to_f64(), b.to_f64()))
}

impl Target<'_> {
    fn problem(
        &self,
        chunk: Option<Vec<u64>>,
        shard: &[u64],
        path: &Path,
        error: String,
    ) -> CheckProblem {
        CheckProblem {
            array: self.name.to_string(),
            chunk,
            shard: shard.to_vec(),
            path: path.to_path_buf(),
            error,
        }
    }

    /// The statistics' `(min, max)` of the brick that inner chunk `g` is.
    fn expected(&self, g: &[u64]) -> Option<[f64; 2]> {
        let st = self.stats?;
        match g.len() {
            3 => st.get(0, g),
            4 => st.get(g[0], &g[1..]),
            _ => None,
        }
    }

    /// Whether the statistics say inner chunk `g` holds something other
    /// than 0 (then brickyard stored it).
    fn holds_data(&self, g: &[u64]) -> Option<[f64; 2]> {
        self.expected(g).filter(|m| !(m[0] == 0.0 && m[1] == 0.0))
    }

    fn shard_path(&self, s: &[u64]) -> PathBuf {
        self.dir.join(self.array.chunk_key(s).as_str())
    }

    /// The inner chunks of shard `s` that lie inside the array, with their
    /// position in the shard's C-order index.
    fn inner_chunks(&self, s: &[u64]) -> Vec<(usize, Vec<u64>)> {
        let n: u64 = self.per_shard.iter().product();
        (0..n)
            .filter_map(|j| {
                let local = unravel(j, &self.per_shard);
                let g: Vec<u64> = (0..s.len())
                    .map(|a| s[a] * self.per_shard[a] + local[a])
                    .collect();
                (0..g.len())
                    .all(|a| g[a] < self.subgrid[a])
                    .then_some((j as usize, g))
            })
            .collect()
    }

    /// Compare a decoded inner chunk `g` with the statistics.
    fn compare<T: Sample>(&self, g: &[u64], v: &[T]) -> Option<String> {
        let want = self.expected(g)?;
        let shape = self.array.shape();
        let valid: Vec<u64> = (0..g.len())
            .map(|a| self.sub[a].min(shape[a].saturating_sub(g[a] * self.sub[a])))
            .collect();
        let (mn, mx) = clipped_min_max(v, &self.sub, &valid)?;
        // (Not NaN: the one value unequal to itself.)
        #[allow(clippy::eq_op)]
        let has_nan = T::DTYPE.is_float()
            && mn == mx
            && clipped_rows(v, &self.sub, &valid).any(|r| r.iter().any(|x| x != x));
        let (mn, mx) = brickyard_core::brick_stats::recorded(mn, mx, has_nan);
        if has_nan && same(mn, want[0]) && same(mn, want[1]) {
            return Some(format!(
                "its values besides NaN are all {mn}, and the statistics say {mn}..{mn}: a \
                 constant brick, so its NaN voxels are drawn as {mn} (statistics written \
                 before NaN was recorded; convert the source again)"
            ));
        }
        (!same(mn, want[0]) || !same(mx, want[1])).then(|| {
            format!(
                "decoded values span {mn}..{mx}, the statistics say {}..{}",
                want[0], want[1]
            )
        })
    }

    /// Decode inner chunk `g` through the array; `Err` describes why it is
    /// bad.
    fn decode_inner(
        &self,
        cache: &ArrayShardedReadableExtCache,
        g: &[u64],
        opts: &CodecOptions,
        values: &mut Option<Vec<f64>>,
    ) -> std::result::Result<(), String> {
        let want_len = self.sub.iter().product::<u64>() as usize;
        let check_len = |n: usize| {
            if n == want_len {
                Ok(())
            } else {
                Err(format!(
                    "decoded to {n} elements, expected {want_len} (chunk shape {:?})",
                    self.sub
                ))
            }
        };
        let decode_err = |e: zarrs::array::ArrayError| format!("cannot decode: {e}");
        match self.dtype {
            Some(dt) => dispatch_dtype!(dt, T => {
                let v: Vec<T> = if self.sharded {
                    self.array.retrieve_subchunk_opt(cache, g, opts)
                } else {
                    self.array.retrieve_chunk_opt(g, opts)
                }
                .map_err(decode_err)?;
                check_len(v.len())?;
                if let Some(e) = self.compare(g, &v) {
                    return Err(e);
                }
                if values.is_some() {
                    *values = Some(v.iter().map(|x| x.to_f64()).collect());
                }
                Ok(())
            }),
            None => {
                // A data type brickyard does not know: decoding is the check
                // (the `bytes` codec validates the length).
                let _: ArrayBytes<'static> = if self.sharded {
                    self.array.retrieve_subchunk_opt(cache, g, opts)
                } else {
                    self.array.retrieve_chunk_opt(g, opts)
                }
                .map_err(decode_err)?;
                Ok(())
            }
        }
    }

    /// Check one shard (or, unsharded, one chunk file).
    fn check_shard(&self, s: &[u64], opts: &CodecOptions) -> Tally {
        let mut t = Tally::default();
        let path = self.shard_path(s);
        let inner = self.inner_chunks(s);
        // (Also of the images inside: "labels/NAME statistics of level K".)
        let want_values = self.stats.is_none() && self.name.contains("statistics of level ");
        // Open the file first: a missing file is legal (fill value), an
        // unreadable one is not.
        let mut file = match crate::storage::open_regular(&path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound && want_values => {
                // The statistics are written whole, every chunk: one
                // missing was lost (its bricks are loaded to learn what
                // they hold, none is skipped as empty).
                t.absent += inner.len() as u64;
                t.problems.push(
                    self.problem(
                        None,
                        s,
                        &path,
                        "the file is missing: the statistics are written whole, every chunk \
                     (readers load the bricks it describes to learn what they hold)"
                            .into(),
                    ),
                );
                return t;
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                t.absent += inner.len() as u64;
                let data: Vec<&Vec<u64>> = inner
                    .iter()
                    .filter(|(_, g)| self.holds_data(g).is_some())
                    .map(|(_, g)| g)
                    .collect();
                if let Some(first) = data.first() {
                    let m = self.holds_data(first).unwrap();
                    t.problems.push(self.problem(
                        Some((*first).clone()),
                        s,
                        &path,
                        format!(
                            "the file is missing, but the statistics say {} of its chunks hold data (this one: {}..{})",
                            data.len(),
                            m[0],
                            m[1]
                        ),
                    ));
                }
                return t;
            }
            Err(e) => {
                t.problems
                    .push(self.problem(None, s, &path, format!("cannot open: {e}")));
                return t;
            }
        };
        let cache = ArrayShardedReadableExtCache::new(&self.array);
        let Some(layout) = self.index else {
            // Decoded by zarrs as a whole (unsharded chunks, or shards whose
            // index this module does not read).
            drop(file);
            let mut values = want_values.then(Vec::new);
            let r = if self.sharded {
                let bytes: std::result::Result<ArrayBytes<'static>, _> =
                    self.array.retrieve_chunk_opt(s, opts);
                bytes.map(|_| ()).map_err(|e| format!("cannot decode: {e}"))
            } else {
                self.decode_inner(&cache, s, opts, &mut values)
            };
            match r {
                Ok(()) => {
                    t.stored += inner.len() as u64;
                    if let Some(v) = values {
                        t.values.push((s.to_vec(), v));
                    }
                }
                Err(e) => {
                    let chunk = (!self.sharded).then(|| s.to_vec());
                    t.problems.push(self.problem(chunk, s, &path, e));
                }
            }
            return t;
        };
        // The index.
        let n = self.per_shard.iter().product::<u64>();
        let index_bytes = n * 16 + if layout.crc { 4 } else { 0 };
        let size = match file.metadata() {
            Ok(m) => m.len(),
            Err(e) => {
                t.problems
                    .push(self.problem(None, s, &path, format!("cannot stat: {e}")));
                return t;
            }
        };
        if size < index_bytes {
            t.problems.push(self.problem(
                None,
                s,
                &path,
                format!("the file has {size} bytes, fewer than its index ({index_bytes} bytes): truncated?"),
            ));
            return t;
        }
        let index_at = if layout.at_end { size - index_bytes } else { 0 };
        let mut index = vec![0u8; index_bytes as usize];
        if let Err(e) = file
            .seek(SeekFrom::Start(index_at))
            .and_then(|_| file.read_exact(&mut index))
        {
            t.problems.push(self.problem(
                None,
                s,
                &path,
                format!("cannot read the shard index: {e}"),
            ));
            return t;
        }
        let body = &index[..(n * 16) as usize];
        if layout.crc {
            let stored = u32::from_le_bytes(index[(n * 16) as usize..].try_into().unwrap());
            let computed = crc32c::crc32c(body);
            if stored != computed {
                t.problems.push(self.problem(
                    None,
                    s,
                    &path,
                    format!(
                        "shard index CRC32C mismatch (stored {stored:08x}, computed {computed:08x}): index damaged or file truncated"
                    ),
                ));
                return t;
            }
        }
        let (data_lo, data_hi) = if layout.at_end {
            (0, size - index_bytes)
        } else {
            (index_bytes, size)
        };
        drop(file);
        for (j, g) in inner {
            let e = |k: usize| u64::from_le_bytes(body[16 * j + 8 * k..][..8].try_into().unwrap());
            let (off, len) = (e(0), e(1));
            if off == u64::MAX && len == u64::MAX {
                t.absent += 1;
                if let Some(m) = self.holds_data(&g) {
                    t.problems.push(self.problem(
                        Some(g),
                        s,
                        &path,
                        format!(
                            "absent from the shard index, but the statistics say it holds data ({}..{})",
                            m[0], m[1]
                        ),
                    ));
                }
                continue;
            }
            match off.checked_add(len) {
                Some(end) if off >= data_lo && end <= data_hi => {}
                _ => {
                    t.problems.push(self.problem(
                        Some(g),
                        s,
                        &path,
                        format!(
                            "the index gives bytes {off}..{} (length {len}), outside the shard's data (bytes {data_lo}..{data_hi} of a {size}-byte file)",
                            off as u128 + len as u128
                        ),
                    ));
                    continue;
                }
            }
            let mut values = want_values.then(Vec::new);
            match self.decode_inner(&cache, &g, opts, &mut values) {
                Ok(()) => {
                    t.stored += 1;
                    if let Some(v) = values {
                        t.values.push((g, v));
                    }
                }
                Err(err) => t.problems.push(self.problem(Some(g), s, &path, err)),
            }
        }
        t
    }

    /// Chunk positions this array counts.
    fn positions(&self) -> u64 {
        self.subgrid.iter().product()
    }
}

fn open_target<'a>(name: &'a str, dir: &'a Path) -> std::result::Result<Target<'a>, String> {
    let store = FilesystemStore::new(dir).map_err(|e| e.to_string())?;
    let array =
        Array::open(Arc::new(store), "/").map_err(|e| format!("cannot open the array: {e}"))?;
    // 64-bit integers (read narrowed by conversion) are checked by
    // decoding alone, as types brickyard does not store are.
    let known = |name: Option<&str>, v2: bool| {
        crate::import::zarr::zarr_dtype(name?, v2).and_then(|(d, wide)| wide.is_none().then_some(d))
    };
    let dtype = read_json(&dir.join("zarr.json"))
        .ok()
        .and_then(|j| known(j["data_type"].as_str(), false))
        .or_else(|| {
            read_json(&dir.join(".zarray"))
                .ok()
                .and_then(|j| known(j["dtype"].as_str(), true))
        });
    let sharded = array.is_sharded();
    let chunk: Vec<u64> = array
        .chunk_shape(&vec![0; array.dimensionality()])
        .map_err(|e| e.to_string())?
        .iter()
        .map(|c| c.get())
        .collect();
    // Inner chunks are checked one by one where this module reads the
    // index; otherwise each shard (or chunk) is one position.
    let inner: Option<(Vec<u64>, IndexLayout)> = match array.subchunk_shape() {
        Some(sub) if sharded && array.is_exclusively_sharded() => {
            let sub: Vec<u64> = sub.iter().map(|c| c.get()).collect();
            let divides =
                sub.len() == chunk.len() && (0..sub.len()).all(|a| chunk[a].is_multiple_of(sub[a]));
            index_layout(dir).filter(|_| divides).map(|l| (sub, l))
        }
        _ => None,
    };
    let (sub, per_shard, index) = match inner {
        Some((sub, layout)) => {
            let per = (0..chunk.len()).map(|a| chunk[a] / sub[a]).collect();
            (sub, per, Some(layout))
        }
        None => (chunk.clone(), vec![1; chunk.len()], None),
    };
    let shape = array.shape().to_vec();
    let subgrid: Vec<u64> = (0..shape.len())
        .map(|a| shape[a].div_ceil(sub[a]))
        .collect();
    Ok(Target {
        name,
        dir,
        array,
        dtype,
        stats: None,
        sub,
        subgrid,
        per_shard,
        index,
        sharded,
    })
}

fn run_target(t: &Target, progress: &dyn Progress, opts: &CodecOptions) -> Tally {
    let shards: u64 = t.array.chunk_grid_shape().iter().product();
    let grid = t.array.chunk_grid_shape().to_vec();
    (0..shards)
        .into_par_iter()
        .map(|i| {
            let s = unravel(i, &grid);
            let r = t.check_shard(&s, opts);
            progress.inc(t.inner_chunks(&s).len() as u64);
            r
        })
        .reduce(Tally::default, Tally::merge)
}

/// Per-brick statistics from the decoded chunks of a statistics array of
/// shape `[c, bz, by, bx, 2]`.
fn collect_stats(t: &Target, values: &[(Vec<u64>, Vec<f64>)]) -> Option<LevelStats> {
    let shape = t.array.shape();
    if shape.len() != 5 || shape[4] != 2 || t.sub.len() != 5 {
        return None;
    }
    let (channels, grid) = (shape[0], [shape[1], shape[2], shape[3]]);
    let mut v = vec![None; (channels * grid[0] * grid[1] * grid[2]) as usize];
    let cs = &t.sub;
    for (idx, data) in values {
        for e in 0..(cs[0] * cs[1] * cs[2] * cs[3]) {
            let l = unravel(e, &cs[..4]);
            let g: Vec<u64> = (0..4).map(|a| idx[a] * cs[a] + l[a]).collect();
            if (0..4).any(|a| g[a] >= shape[a]) {
                continue;
            }
            let at = (e * cs[4]) as usize;
            let i = ((g[0] * grid[0] + g[1]) * grid[1] + g[2]) * grid[2] + g[3];
            v[i as usize] = Some([data[at], data[at + 1]]);
        }
    }
    Some(LevelStats { channels, grid, v })
}

/// Read and decode every chunk of every level of the store at `path` and of
/// its statistics arrays, in parallel (rayon's pool); `progress` counts
/// chunks. `Err` only when `path` is not a store at all.
pub fn check(path: &Path, progress: &dyn Progress) -> Result<CheckReport> {
    // The store's own arrays, then those of the images `brickyard process`
    // wrote into it (`labels/NAME`, `derived/NAME`): a damaged result is
    // as much a damaged store.
    let mut images: Vec<(PathBuf, Vec<ArrayAt>)> = vec![(path.to_path_buf(), arrays_of(path)?)];
    let mut problems = vec![];
    for (rel, dir) in inner_images(path) {
        match arrays_of(&dir) {
            Ok(a) => images.push((
                dir,
                a.into_iter()
                    .map(|(n, d, l)| (format!("{rel} {n}"), d, l))
                    .collect(),
            )),
            Err(e) => problems.push(CheckProblem {
                array: rel,
                chunk: None,
                shard: vec![],
                path: dir,
                error: e.to_string(),
            }),
        }
    }
    let opts = CodecOptions::default();
    let mut report = CheckReport::default();
    // Open everything first (the progress bar needs the total).
    let mut opened = vec![];
    for (dir, arrays) in &images {
        let mut levels = vec![];
        let mut stats_targets = vec![];
        for (name, adir, level) in arrays {
            match (open_target(name, adir), level) {
                (Ok(t), Some(k)) => levels.push((*k, t)),
                (Ok(t), None) => stats_targets.push(t),
                (Err(e), _) => problems.push(CheckProblem {
                    array: name.clone(),
                    chunk: None,
                    shard: vec![],
                    path: adir.clone(),
                    error: e,
                }),
            }
        }
        let nlev = arrays.iter().filter(|a| a.2.is_some()).count();
        opened.push((dir, levels, stats_targets, nlev));
    }
    let positions: u64 = opened
        .iter()
        .map(|(_, levels, stats_targets, _)| {
            levels.iter().map(|(_, t)| t.positions()).sum::<u64>()
                + stats_targets.iter().map(Target::positions).sum::<u64>()
        })
        .sum();
    progress.start(positions);
    report.chunks = positions;
    for (dir, levels, stats_targets, nlev) in opened {
        report.arrays += levels.len() + stats_targets.len();
        // Statistics first: they say which bricks must be there.
        let mut stats: Vec<Option<LevelStats>> = (0..nlev).map(|_| None).collect();
        for t in &stats_targets {
            let tally = run_target(t, progress, &opts);
            let k: Option<usize> = t
                .name
                .rsplit_once("statistics of level ")
                .and_then(|(_, k)| k.parse().ok());
            if let Some(k) = k.filter(|&k| k < nlev) {
                stats[k] = collect_stats(t, &tally.values);
            }
            report.stored += tally.stored;
            report.absent += tally.absent;
            problems.extend(tally.problems);
        }
        for (k, t) in levels {
            // The statistics apply when their grid is this level's grid of
            // inner chunks (bricks).
            let st = stats[k].as_ref().filter(|st| {
                let g = &t.subgrid;
                match g.len() {
                    3 => st.channels == 1 && g[..] == st.grid[..],
                    4 => t.sub[0] == 1 && g[0] == st.channels && g[1..] == st.grid[..],
                    _ => false,
                }
            });
            if stats[k].is_some() && st.is_none() {
                problems.push(CheckProblem {
                    array: t.name.to_string(),
                    chunk: None,
                    shard: vec![],
                    path: dir.join(STATS_DIR).join(k.to_string()),
                    error: format!(
                        "the statistics do not match the level's grid of bricks {:?}: not used",
                        t.subgrid
                    ),
                });
            }
            let t = Target { stats: st, ..t };
            let tally = run_target(&t, progress, &opts);
            report.stored += tally.stored;
            report.absent += tally.absent;
            problems.extend(tally.problems);
        }
        let name = dir
            .strip_prefix(path)
            .map_or(String::new(), |r| r.to_string_lossy().into_owned());
        problems.extend(label_table_problem(
            dir,
            &name,
            stats.first().and_then(Option::as_ref),
        ));
    }
    // A stable order: by array as listed, then shard, then chunk.
    let listed: Vec<&str> = images
        .iter()
        .flat_map(|(_, a)| a.iter().map(|x| x.0.as_str()))
        .collect();
    let order = |a: &str| listed.iter().position(|x| *x == a).unwrap_or(usize::MAX);
    problems.sort_by(|a, b| {
        (order(&a.array), &a.shard, &a.chunk).cmp(&(order(&b.array), &b.shard, &b.chunk))
    });
    report.problems = problems;
    Ok(report)
}

/// A label image's table of label statistics (`_brickyard/labels.csv`,
/// which `render --only-labels` and the viewer's readout go by) that
/// cannot be read, or that lists fewer labels than its voxels hold: the
/// largest label in level 0's brick statistics is above the table's
/// largest (a table cut short, or one of another image). `None` when the
/// image has no table.
fn label_table_problem(dir: &Path, name: &str, stats: Option<&LevelStats>) -> Option<CheckProblem> {
    use brickyard_core::label_table;
    let path = dir.join(label_table::PATH);
    let text = std::fs::read(&path).ok()?;
    let problem = |error: String| CheckProblem {
        array: match name {
            "" => "label table".to_string(),
            n => format!("{n} label table"),
        },
        chunk: None,
        shard: vec![],
        path: path.clone(),
        error,
    };
    let Ok(text) = String::from_utf8(text) else {
        return Some(problem("not UTF-8 text".into()));
    };
    let (mut top, mut rows) = (0u64, 0u64);
    let read = label_table::parse_table(&text, |id, _| {
        top = top.max(id);
        rows += 1;
    });
    if let Err(e) = read {
        return Some(problem(e));
    }
    let held = stats?
        .v
        .iter()
        .flatten()
        .filter_map(|m| brickyard_core::brick_stats::finite_range(m[0], m[1]))
        .map(|(_, hi)| hi)
        .fold(f64::NEG_INFINITY, f64::max);
    (held > top as f64).then(|| {
        problem(format!(
            "the table lists {rows} label(s), up to {top}, but level 0's voxels hold labels up \
             to {held} (by the brick statistics): a table cut short or of another image; \
             --only-labels and --hide-labels go by it (process the image again to write it)"
        ))
    })
}

/// The images under a local store's `labels/` and `derived/` groups (what
/// `brickyard process` writes), as `(group/name, folder)`; hidden
/// leftovers of interrupted jobs and the `NAME.partial` of interrupted
/// conversions are not images (`info` names them as problems).
fn inner_images(path: &Path) -> Vec<(String, PathBuf)> {
    ["labels", "derived"]
        .into_iter()
        .flat_map(|g| {
            super::group_folders(path, g)
                .into_iter()
                .filter(|n| !n.starts_with('.') && !n.ends_with(".partial"))
                .map(move |n| (format!("{g}/{n}"), path.join(g).join(n)))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn min_max_of_the_part_inside_the_array() {
        // A 2×3×4 chunk of which 2×2×3 lie inside the array; the outside
        // holds the extremes, which must not count.
        let cs = [2, 3, 4];
        let mut v = vec![0u8; 24];
        for (i, x) in v.iter_mut().enumerate() {
            let (y, xx) = (i / 4 % 3, i % 4);
            *x = if y < 2 && xx < 3 {
                10 + i as u8
            } else {
                255 - i as u8
            };
        }
        // Inside: indices 0–2, 4–6, 12–14 and 16–18.
        assert_eq!(clipped_min_max(&v, &cs, &[2, 2, 3]), Some((10.0, 28.0)));
        // The whole chunk: outside, index 3 holds 252.
        assert_eq!(clipped_min_max(&v, &cs, &cs), Some((10.0, 252.0)));
        assert_eq!(clipped_min_max(&v, &cs, &[0, 2, 3]), None);
        // NaN is left out, as in the statistics; all NaN gives NaN.
        let f = [f32::NAN, 2.0, -1.0, f32::NAN];
        assert_eq!(
            clipped_min_max(&f, &[1, 1, 4], &[1, 1, 4]),
            Some((-1.0, 2.0))
        );
        let (a, b) = clipped_min_max(&f, &[1, 1, 4], &[1, 1, 1]).unwrap();
        assert!(a.is_nan() && b.is_nan());
    }

    #[test]
    fn problems_read_as_one_line_each() {
        let p = CheckProblem {
            array: "level 0".into(),
            chunk: Some(vec![1, 2, 3]),
            shard: vec![0, 1, 1],
            path: "s/0/c/0/1/1".into(),
            error: "cannot decode: x".into(),
        };
        assert_eq!(
            p.to_string(),
            "level 0, chunk [1, 2, 3], s/0/c/0/1/1: cannot decode: x"
        );
        let q = CheckProblem { chunk: None, ..p };
        assert_eq!(
            q.to_string(),
            "level 0, shard [0, 1, 1] (whole file), s/0/c/0/1/1: cannot decode: x"
        );
    }
}
