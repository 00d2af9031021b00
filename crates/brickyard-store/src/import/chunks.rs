//! Decoded chunks of a Zarr array for the loader's region reads: a cache of
//! decoded read-granularity chunks shared by the reading threads and bounded
//! in bytes (a chunk wanted by several threads at once is decoded by one
//! while the others wait for it), the direct reader of sharded arrays (shard
//! indexes cached, the byte ranges of the chunks one read needs coalesced
//! into one read per run of neighbours in the shard file, each chunk decoded
//! by the inner codecs), and the copy of a chunk's overlap with a read
//! straight into the caller's box.
//!
//! Over 800 lines: with its tests: 0.74k lines of code (cache, shells,
//! shard reader and copy belong together), 0.2k of tests.

use crate::error::{Result, StoreError};
use crate::shard::{self, IndexLayout};
use crate::storage::{self, Span, StoreAt};
use rustc_hash::{FxHashMap, FxHashSet};
use serde_json::Value;
use smallvec::SmallVec;
use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::num::NonZeroU64;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use zarrs::array::codec::api::CodecOptions;
use zarrs::array::{Array, ArrayToBytesCodecTraits, CodecChain, DataType, FillValue};
use zarrs::metadata::v3::MetadataV3;

/// Two byte ranges of one shard file closer than this are read as one (the
/// bytes between are read and dropped).
pub const COALESCE_GAP: u64 = 64 << 10;

/// Longest single read of coalesced ranges.
pub const COALESCE_MAX: u64 = 32 << 20;

/// Most shard indexes one reader keeps (the set is cleared past this).
const INDEX_CACHE_MAX: usize = 1024;

/// Bookkeeping charged per cached chunk on top of its bytes.
const ENTRY_COST: u64 = 128;

/// Chunks decoded by direct shard reads in this process (all arrays): for
/// benchmarks, to tell decodes from cache hits.
pub static CHUNKS_DECODED: AtomicU64 = AtomicU64::new(0);

/// A chunk's grid position (array axis order), or one prefixed with its
/// source in the cache: inline up to six axes, so that the lookups of a
/// brick's chunks allocate nothing.
pub(crate) type Idx = SmallVec<[u64; 6]>;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Decoding runs outside the lock; a panic inside it leaves consistent
    // data (see `Claim`).
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A decoded chunk: the box it covers (array axis order) and what is held
/// of it.
pub(crate) struct Decoded {
    pub origin: Vec<u64>,
    pub dims: Vec<u64>,
    pub body: Body,
}

pub(crate) enum Body {
    /// Every element is the fill value.
    Fill,
    /// Every element, in C order over the box.
    Data(Vec<u8>),
    /// Only the faces of the box (each in C order over its own box): what
    /// the aprons of neighbouring bricks read, kept after the whole chunk
    /// was evicted.
    Shell(Vec<Face>),
}

pub(crate) struct Face {
    origin: Vec<u64>,
    dims: Vec<u64>,
    data: Vec<u8>,
}

fn contains(origin: &[u64], dims: &[u64], lo: &[u64], hi: &[u64]) -> bool {
    (0..origin.len()).all(|a| origin[a] <= lo[a] && hi[a] <= origin[a] + dims[a])
}

impl Decoded {
    fn cost(&self) -> u64 {
        ENTRY_COST
            + match &self.body {
                Body::Fill => 0,
                Body::Data(d) => d.len() as u64,
                Body::Shell(f) => f.iter().map(|f| f.data.len() as u64 + ENTRY_COST).sum(),
            }
    }

    /// Whether the box `[lo, hi)` (inside the chunk) can be read from what
    /// is held.
    fn covers(&self, lo: &[u64], hi: &[u64]) -> bool {
        match &self.body {
            Body::Fill | Body::Data(_) => true,
            Body::Shell(faces) => faces.iter().any(|f| contains(&f.origin, &f.dims, lo, hi)),
        }
    }

    /// The faces `width` deep of a whole chunk of `es`-byte elements, on
    /// every axis longer than twice that; `None` when that would not be
    /// much smaller than the chunk.
    fn shell(&self, width: u64, es: usize) -> Option<Decoded> {
        let Body::Data(d) = &self.body else {
            return None;
        };
        let n = self.dims.len();
        let mut faces = vec![];
        for a in 0..n {
            if self.dims[a] <= 2 * width {
                continue;
            }
            for hi_side in [false, true] {
                let mut origin = self.origin.clone();
                let mut dims = self.dims.clone();
                if hi_side {
                    origin[a] += self.dims[a] - width;
                }
                dims[a] = width;
                let ranges: Vec<Range<u64>> =
                    (0..n).map(|b| origin[b]..origin[b] + dims[b]).collect();
                let mut stride = vec![1usize; n];
                for b in (0..n - 1).rev() {
                    stride[b] = stride[b + 1] * dims[b + 1] as usize;
                }
                let mut data = vec![0u8; dims.iter().product::<u64>() as usize * es];
                let fill = vec![0u8; es];
                copy_box(
                    &self.origin,
                    &self.dims,
                    Some(d.as_slice()),
                    &ranges,
                    &fill,
                    &mut data,
                    0,
                    &stride,
                );
                faces.push(Face { origin, dims, data });
            }
        }
        let s = Decoded {
            origin: self.origin.clone(),
            dims: self.dims.clone(),
            body: Body::Shell(faces),
        };
        (!faces_empty(&s) && s.cost() * 2 < self.cost()).then_some(s)
    }
}

fn faces_empty(d: &Decoded) -> bool {
    matches!(&d.body, Body::Shell(f) if f.is_empty())
}

enum Entry {
    /// A thread is reading and decoding it.
    Loading,
    Ready {
        chunk: Arc<Decoded>,
        tick: u64,
    },
}

#[derive(Default)]
struct CacheState {
    map: FxHashMap<Idx, Entry>,
    /// Ready entries by last use.
    lru: BTreeMap<u64, Idx>,
    bytes: u64,
    tick: u64,
    /// Chunks hinted for read-ahead ([`ChunkCache::to_hint`]) and not
    /// loaded since: a chunk is hinted once however many bricks touch it.
    hinted: FxHashSet<Idx>,
}

/// The most chunks remembered as hinted (about 64 bytes each, outside the
/// cache's budget; the loader's hints keep under a thousand waiting for
/// their load); past it the memory starts over (a chunk may then be
/// hinted twice, which costs a system call).
const HINTED_MAX: usize = 1 << 12;

/// Decoded chunks, least recently used evicted first, at most `budget`
/// bytes held (chunks being read by a thread, and those handed out, are
/// not counted: at most one read's worth per reading thread).
pub(crate) struct ChunkCache {
    budget: u64,
    /// Depth of the shells kept of evicted chunks (0: none), and the
    /// element size.
    shell: u64,
    elem: usize,
    state: Mutex<CacheState>,
    /// Signalled when chunks being loaded become ready (or fail).
    ready: Condvar,
}

/// Chunks a thread claimed for loading: dropped (on success, failure or a
/// panic in a codec), whatever is still marked loading is unmarked and the
/// waiting threads are woken.
struct Claim<'a> {
    cache: &'a ChunkCache,
    keys: Vec<Idx>,
}

impl Drop for Claim<'_> {
    fn drop(&mut self) {
        let mut st = lock(&self.cache.state);
        for k in &self.keys {
            if matches!(st.map.get(k), Some(Entry::Loading)) {
                st.map.remove(k);
            }
        }
        drop(st);
        self.cache.ready.notify_all();
    }
}

impl ChunkCache {
    /// A cache of `budget` bytes; whole chunks it evicts leave their faces
    /// `shell` elements deep (`elem` bytes each) behind, while they fit.
    pub fn new(budget: u64, shell: u64, elem: usize) -> ChunkCache {
        ChunkCache {
            budget,
            shell,
            elem,
            state: Mutex::new(CacheState::default()),
            ready: Condvar::new(),
        }
    }

    /// Bytes held now.
    pub fn bytes(&self) -> u64 {
        lock(&self.state).bytes
    }

    /// Insert a chunk, evicting the least recently used; returns the whole
    /// chunks evicted (to leave their shells).
    fn insert(
        &self,
        st: &mut CacheState,
        key: Idx,
        chunk: Arc<Decoded>,
    ) -> Vec<(Idx, Arc<Decoded>)> {
        let mut evicted = vec![];
        let n = chunk.cost();
        if n > self.budget {
            st.map.remove(&key);
            return evicted;
        }
        while st.bytes + n > self.budget {
            let Some((_, old)) = st.lru.pop_first() else {
                break;
            };
            if let Some(Entry::Ready { chunk, .. }) = st.map.remove(&old) {
                st.bytes -= chunk.cost();
                if matches!(chunk.body, Body::Data(_)) {
                    evicted.push((old, chunk));
                }
            }
        }
        st.tick += 1;
        let tick = st.tick;
        st.hinted.remove(&key);
        st.lru.insert(tick, key.clone());
        st.bytes += n;
        st.map.insert(key, Entry::Ready { chunk, tick });
        evicted
    }

    /// Keep the shells of evicted chunks that nobody loaded again since.
    fn keep_shells(&self, evicted: Vec<(Idx, Arc<Decoded>)>) {
        if self.shell == 0 || evicted.is_empty() {
            return;
        }
        let shells: Vec<(Idx, Decoded)> = evicted
            .into_iter()
            .filter_map(|(k, c)| Some((k, c.shell(self.shell, self.elem)?)))
            .collect();
        let mut st = lock(&self.state);
        for (k, s) in shells {
            if !st.map.contains_key(&k) {
                // Chunks this evicts are dropped whole (no cascade).
                self.insert(&mut st, k, Arc::new(s));
            }
        }
    }

    /// Drop the chunks `chunk_keys` of `source` that the cache holds (not
    /// those being loaded now): they are read again when next asked for.
    /// For chunks read while their data was missing, once it may be back.
    pub fn forget(&self, source: u64, chunk_keys: &[Idx]) {
        let mut st = lock(&self.state);
        let st = &mut *st;
        for k in chunk_keys {
            let key: Idx = std::iter::once(source).chain(k.iter().copied()).collect();
            if let Some(Entry::Ready { chunk, tick }) = st.map.get(&key) {
                let (tick, cost) = (*tick, chunk.cost());
                st.lru.remove(&tick);
                st.bytes -= cost;
                st.map.remove(&key);
            }
        }
    }

    /// The positions of the chunks `chunk_keys` of `source` worth a
    /// read-ahead hint: those the cache neither holds (whole, or as a shell
    /// with the part `need`) nor is loading now, and that were not hinted
    /// since they were last loaded. They count as hinted from now on.
    pub fn to_hint(&self, source: u64, chunk_keys: &[Idx], need: &[(Idx, Idx)]) -> Vec<usize> {
        let mut st = lock(&self.state);
        let st = &mut *st;
        if st.hinted.len() > HINTED_MAX {
            st.hinted.clear();
        }
        let mut key = Idx::new();
        (0..chunk_keys.len())
            .filter(|&i| {
                key.clear();
                key.push(source);
                key.extend(chunk_keys[i].iter().copied());
                let absent = match st.map.get(&key) {
                    Some(Entry::Ready { chunk, .. }) => !chunk.covers(&need[i].0, &need[i].1),
                    Some(Entry::Loading) => false,
                    None => true,
                };
                absent && st.hinted.insert(key.clone())
            })
            .collect()
    }

    /// The chunks `keys`: from the cache, or by `load` (called outside the
    /// lock with the keys this thread claimed, each at most once, returning
    /// their chunks in that order). Chunks another thread is loading are
    /// waited for (a thread loads what it claimed before it waits, so two
    /// threads never wait for each other).
    ///
    /// `need[i]`: the box (`lo`, `hi`) of chunk `i` the caller reads; a
    /// shell that does not hold it counts as missing. `source` tells the
    /// chunks of the sources sharing the cache apart (`load` gets the
    /// chunk indices without it).
    pub fn get_or_load(
        &self,
        source: u64,
        chunk_keys: &[Idx],
        need: &[(Idx, Idx)],
        load: impl Fn(&[Vec<u64>]) -> Result<Vec<Decoded>>,
    ) -> Result<Vec<Arc<Decoded>>> {
        let keys: Vec<Idx> = chunk_keys
            .iter()
            .map(|k| std::iter::once(source).chain(k.iter().copied()).collect())
            .collect();
        let mut out: Vec<Option<Arc<Decoded>>> = vec![None; keys.len()];
        loop {
            let mut mine = vec![];
            let mut waiting = false;
            {
                let mut st = lock(&self.state);
                for (i, k) in keys.iter().enumerate() {
                    if out[i].is_some() {
                        continue;
                    }
                    st.tick += 1;
                    let now = st.tick;
                    let st = &mut *st;
                    if let Some(Entry::Ready { chunk, tick }) = st.map.get(k) {
                        if !chunk.covers(&need[i].0, &need[i].1) {
                            // A shell without the part wanted: load whole.
                            let (tick, cost) = (*tick, chunk.cost());
                            st.lru.remove(&tick);
                            st.bytes -= cost;
                            st.map.remove(k);
                        }
                    }
                    match st.map.get_mut(k) {
                        Some(Entry::Ready { chunk, tick }) => {
                            out[i] = Some(chunk.clone());
                            if let Some(key) = st.lru.remove(tick) {
                                st.lru.insert(now, key);
                            }
                            *tick = now;
                        }
                        Some(Entry::Loading) => waiting = true,
                        None => {
                            st.map.insert(k.clone(), Entry::Loading);
                            mine.push(i);
                        }
                    }
                }
            }
            if !mine.is_empty() {
                let claim = Claim {
                    cache: self,
                    keys: mine.iter().map(|&i| keys[i].clone()).collect(),
                };
                let mine_keys: Vec<Vec<u64>> =
                    mine.iter().map(|&i| chunk_keys[i].to_vec()).collect();
                let loaded = load(&mine_keys)?;
                debug_assert_eq!(loaded.len(), mine.len());
                let mut st = lock(&self.state);
                let mut evicted = vec![];
                for (&i, d) in mine.iter().zip(loaded) {
                    let d = Arc::new(d);
                    evicted.extend(self.insert(&mut st, keys[i].clone(), d.clone()));
                    out[i] = Some(d);
                }
                drop(st);
                drop(claim);
                self.keep_shells(evicted);
            }
            if waiting {
                let mut st = lock(&self.state);
                while keys
                    .iter()
                    .zip(&out)
                    .any(|(k, o)| o.is_none() && matches!(st.map.get(k), Some(Entry::Loading)))
                {
                    st = self.ready.wait(st).unwrap_or_else(|e| e.into_inner());
                }
            }
            if out.iter().all(Option::is_some) {
                return Ok(out.into_iter().flatten().collect());
            }
        }
    }
}

/// A shard's checked index, `(offset, bytes)` per inner chunk; `None`: no
/// shard file.
type ShardIndex = Option<Arc<Vec<[u64; 2]>>>;

/// Byte ranges of one shard read together: the range read, and the chunks
/// in it as `(offset, bytes, position in the request)`.
type Run = (Range<u64>, Vec<(u64, u64, usize)>);

/// One shard's part of a read ([`ShardReader::plan`]).
struct ShardPlan {
    file: PathBuf,
    /// Positions of the keys the shard's index has no entry for.
    absent: Vec<usize>,
    runs: Vec<Run>,
}

/// The direct reader of a sharded array whose shard index layout is known
/// (`sharding_indexed` first among the array's codecs).
pub(crate) struct ShardReader {
    layout: IndexLayout,
    /// Shard and inner chunk shapes (array axis order).
    shard: Vec<u64>,
    inner: Vec<u64>,
    inner_nz: Vec<NonZeroU64>,
    codecs: CodecChain,
    data_type: DataType,
    fill_value: FillValue,
    elem: usize,
    /// Checked indexes by shard grid index (`None`: no shard file).
    indexes: Mutex<HashMap<Vec<u64>, ShardIndex>>,
}

impl ShardReader {
    /// `config`: the `sharding_indexed` codec's configuration. `None` when
    /// the inner codecs cannot be built here (the Zarr library reads such
    /// arrays) or the element size is not fixed.
    pub fn new(
        layout: IndexLayout,
        shard: &[u64],
        config: &Value,
        data_type: &DataType,
        fill_value: &FillValue,
        elem: usize,
    ) -> Option<ShardReader> {
        let inner: Vec<u64> = config
            .get("chunk_shape")?
            .as_array()?
            .iter()
            .map(Value::as_u64)
            .collect::<Option<_>>()?;
        let inner_nz: Vec<NonZeroU64> = inner
            .iter()
            .map(|&v| NonZeroU64::new(v))
            .collect::<Option<_>>()?;
        if inner.len() != shard.len() || fill_value.as_ne_bytes().len() != elem {
            return None;
        }
        let metas: Vec<MetadataV3> = serde_json::from_value(config.get("codecs")?.clone()).ok()?;
        let codecs = CodecChain::from_metadata(&metas).ok()?;
        Some(ShardReader {
            layout,
            shard: shard.to_vec(),
            inner,
            inner_nz,
            codecs,
            data_type: data_type.clone(),
            fill_value: fill_value.clone(),
            elem,
            indexes: Mutex::new(HashMap::new()),
        })
    }

    /// The read granularity: the inner chunk shape.
    pub fn inner(&self) -> &[u64] {
        &self.inner
    }

    /// The checked index of shard `shard_idx` (at `file`), read once and
    /// kept.
    pub(crate) fn index(&self, file: &Path, shard_idx: &[u64]) -> Result<ShardIndex> {
        if let Some(ix) = lock(&self.indexes).get(shard_idx) {
            return Ok(ix.clone());
        }
        let ix = shard::read_index(file, &self.layout)?.map(Arc::new);
        let mut m = lock(&self.indexes);
        if m.len() >= INDEX_CACHE_MAX {
            m.clear();
        }
        m.insert(shard_idx.to_vec(), ix.clone());
        Ok(ix)
    }

    /// Forget the index of shard `shard_idx`: the next read reads it again.
    pub(crate) fn forget_index(&self, shard_idx: &[u64]) {
        lock(&self.indexes).remove(shard_idx);
    }

    /// Where the inner chunks `keys` (inner chunk grid indices) of `array`
    /// (stored at `dir`) lie: per shard, its file, the positions in `keys`
    /// of the chunks its index has no entry for (they read as the fill
    /// value), and the byte ranges to read for the others, neighbouring
    /// ranges joined into one.
    fn plan(
        &self,
        array: &Array<StoreAt>,
        dir: &Path,
        keys: &[Vec<u64>],
    ) -> Result<Vec<ShardPlan>> {
        let n = self.inner.len();
        let per: Vec<u64> = (0..n).map(|a| self.shard[a] / self.inner[a]).collect();
        // Group by shard.
        let mut by_shard: BTreeMap<Vec<u64>, Vec<usize>> = BTreeMap::new();
        for (i, k) in keys.iter().enumerate() {
            let s: Vec<u64> = (0..n).map(|a| k[a] / per[a]).collect();
            by_shard.entry(s).or_default().push(i);
        }
        let mut plans = Vec::with_capacity(by_shard.len());
        for (s, members) in by_shard {
            let file = dir.join(array.chunk_key(&s).as_str());
            let index = self.index(&file, &s)?;
            // Present chunks: (offset, bytes, key position).
            let mut present = vec![];
            let mut absent = vec![];
            for &i in &members {
                let k = &keys[i];
                let mut entry = 0u64;
                for a in 0..n {
                    entry = entry * per[a] + k[a] % per[a];
                }
                let e = index
                    .as_ref()
                    .and_then(|ix| ix.get(entry as usize))
                    .copied()
                    .unwrap_or([u64::MAX, u64::MAX]);
                if e == [u64::MAX, u64::MAX] {
                    absent.push(i);
                } else {
                    present.push((e[0], e[1], i));
                }
            }
            present.sort_unstable();
            // Runs of neighbouring ranges, one read each.
            let mut runs: Vec<Run> = vec![];
            for p in present {
                let end = p.0 + p.1;
                match runs.last_mut() {
                    Some((r, m))
                        if p.0 <= r.end.saturating_add(COALESCE_GAP)
                            && end.max(r.end) - r.start <= COALESCE_MAX =>
                    {
                        r.end = r.end.max(end);
                        m.push(p);
                    }
                    _ => runs.push((p.0..end, vec![p])),
                }
            }
            plans.push(ShardPlan { file, absent, runs });
        }
        Ok(plans)
    }

    /// Read and decode the inner chunks `keys` (inner chunk grid indices)
    /// of `array` (stored at `dir`), in the order given.
    pub fn load(
        &self,
        array: &Array<StoreAt>,
        dir: &Path,
        keys: &[Vec<u64>],
    ) -> Result<Vec<Decoded>> {
        let mut out: Vec<Option<Decoded>> = keys.iter().map(|_| None).collect();
        for ShardPlan { file, absent, runs } in self.plan(array, dir, keys)? {
            for i in absent {
                out[i] = Some(self.fill(&keys[i]));
            }
            if runs.is_empty() {
                continue;
            }
            let spans: Vec<Span> = runs.iter().map(|(r, _)| Span::Range(r.clone())).collect();
            let found = storage::read_spans_with(&file, &spans, |j, buf| {
                let (r, m) = &runs[j];
                for &(off, len, i) in m {
                    let at = (off - r.start) as usize;
                    let bytes = &buf[at..at + len as usize];
                    out[i] = Some(self.decode(&file, &keys[i], bytes)?);
                }
                Ok(())
            })?;
            if !found {
                // The shard vanished after its index was read: the store
                // cannot be read (an I/O failure, not bad content).
                return Err(StoreError::io(
                    &file,
                    std::io::Error::new(
                        std::io::ErrorKind::NotFound,
                        "shard: the shard file is gone (it held chunks when its index was read)",
                    ),
                ));
            }
        }
        Ok(out
            .into_iter()
            .map(|d| d.expect("every key read"))
            .collect())
    }

    /// Ask the system to start reading the stored bytes of the inner
    /// chunks `keys` (as [`ShardReader::load`] would read them), without
    /// waiting for them: a later `load` of these chunks then finds them in
    /// memory. Reads the shard indexes it does not hold yet. Returns how
    /// many byte ranges were hinted (0 where the store gives no such hint).
    pub fn prefetch(&self, array: &Array<StoreAt>, dir: &Path, keys: &[Vec<u64>]) -> Result<usize> {
        let mut hinted = 0;
        for plan in self.plan(array, dir, keys)? {
            if plan.runs.is_empty() {
                continue;
            }
            let ranges: Vec<Range<u64>> = plan.runs.iter().map(|(r, _)| r.clone()).collect();
            hinted += storage::will_need(&plan.file, &ranges);
        }
        Ok(hinted)
    }

    fn origin(&self, k: &[u64]) -> Vec<u64> {
        k.iter().zip(&self.inner).map(|(i, c)| i * c).collect()
    }

    fn fill(&self, k: &[u64]) -> Decoded {
        Decoded {
            origin: self.origin(k),
            dims: self.inner.clone(),
            body: Body::Fill,
        }
    }

    fn decode(&self, file: &Path, k: &[u64], bytes: &[u8]) -> Result<Decoded> {
        CHUNKS_DECODED.fetch_add(1, Ordering::Relaxed);
        let origin = self.origin(k);
        let err = |e: String| StoreError::zarr(file, format!("chunk at {origin:?}: {e}"));
        let d = self
            .codecs
            .decode(
                Cow::Borrowed(bytes),
                &self.inner_nz,
                &self.data_type,
                &self.fill_value,
                &CodecOptions::default(),
            )
            .map_err(|e| err(e.to_string()))?
            .into_fixed()
            .map_err(|e| err(e.to_string()))?
            .into_owned();
        let want = self.inner.iter().product::<u64>() * self.elem as u64;
        if d.len() as u64 != want {
            return Err(err(format!(
                "decoded to {} bytes, expected {want}",
                d.len()
            )));
        }
        Ok(Decoded {
            origin,
            dims: self.inner.clone(),
            body: Body::Data(d),
        })
    }
}

thread_local! {
    /// Whether a read on this thread since the last [`take_fill_read`] may
    /// have met a chunk the store does not hold (read as the fill value).
    static FILL_READ: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Note that a read met (or, through a path that cannot tell, may have
/// met) a chunk read as the fill value.
pub(crate) fn note_fill() {
    FILL_READ.with(|f| f.set(true));
}

/// Whether the reads of this thread since the last call met a chunk read
/// as the fill value (an absent chunk, or one not stored because it was
/// all fill), or went through a path that cannot tell; cleared. A reader
/// that checks for lost chunks need not look at a read for which this is
/// false: none of its chunks was absent.
pub fn take_fill_read() -> bool {
    FILL_READ.with(|f| f.replace(false))
}

/// Copy the part of `chunk` inside `ranges` (array axis order) into `out`:
/// the element at array position `p` goes to element
/// `base + Σ_a (p[a] − ranges[a].start) · stride[a]` of `out`, whose
/// elements are `fill.len()` bytes (the fill value, written where the chunk
/// is all fill). A shell must hold the part (see `ChunkCache::get_or_load`).
pub(crate) fn copy_into(
    chunk: &Decoded,
    ranges: &[Range<u64>],
    fill: &[u8],
    out: &mut [u8],
    base: usize,
    stride: &[usize],
) {
    match &chunk.body {
        Body::Fill => {
            note_fill();
            copy_box(
                &chunk.origin,
                &chunk.dims,
                None,
                ranges,
                fill,
                out,
                base,
                stride,
            )
        }
        Body::Data(d) => copy_box(
            &chunk.origin,
            &chunk.dims,
            Some(d.as_slice()),
            ranges,
            fill,
            out,
            base,
            stride,
        ),
        Body::Shell(faces) => {
            let n = ranges.len();
            let lo: Vec<u64> = (0..n)
                .map(|a| ranges[a].start.max(chunk.origin[a]))
                .collect();
            let hi: Vec<u64> = (0..n)
                .map(|a| ranges[a].end.min(chunk.origin[a] + chunk.dims[a]))
                .collect();
            if (0..n).any(|a| lo[a] >= hi[a]) {
                return;
            }
            let f = faces
                .iter()
                .find(|f| contains(&f.origin, &f.dims, &lo, &hi))
                .expect("a shell is used only for parts it holds");
            copy_box(
                &f.origin,
                &f.dims,
                Some(f.data.as_slice()),
                ranges,
                fill,
                out,
                base,
                stride,
            )
        }
    }
}

/// Copy `rows` runs of `B` bytes: run `r` from byte `so + r·cs` of `src`
/// to byte `oo + r·os` of `dst`, each in one move of a fixed size (an
/// element of an apron column, or a whole row). The bounds are checked once
/// for all the rows.
#[inline(always)]
fn copy_runs<const B: usize>(
    dst: &mut [u8],
    src: &[u8],
    (so, cs): (usize, usize),
    (oo, os): (usize, usize),
    rows: usize,
) {
    if rows == 0 {
        return;
    }
    let last = rows - 1;
    assert!(so + last * cs + B <= src.len() && oo + last * os + B <= dst.len());
    let (src, dst) = (src.as_ptr(), dst.as_mut_ptr());
    for r in 0..rows {
        // SAFETY: every byte moved lies within the bounds asserted above
        // (the offsets grow with `r`), and `src` and `dst` are distinct
        // slices.
        unsafe {
            std::ptr::copy_nonoverlapping(src.add(so + r * cs), dst.add(oo + r * os), B);
        }
    }
}

/// [`copy_runs`] of `run` (one or two) elements of `B` bytes per row, one
/// column at a time (not a loop over the elements of a row, which the
/// compiler turns into a `memcpy` call per row).
#[inline(always)]
fn copy_columns<const B: usize>(
    dst: &mut [u8],
    src: &[u8],
    (so, cs): (usize, usize),
    (oo, os): (usize, usize),
    rows: usize,
    run: usize,
) {
    copy_runs::<B>(dst, src, (so, cs), (oo, os), rows);
    if run == 2 {
        copy_runs::<B>(dst, src, (so + B, cs), (oo + B, os), rows);
    }
}

/// [`copy_into`] from a box at `origin` of `dims` elements (`None`: fill).
#[allow(clippy::too_many_arguments)]
fn copy_box(
    origin: &[u64],
    dims: &[u64],
    data: Option<&[u8]>,
    ranges: &[Range<u64>],
    fill: &[u8],
    out: &mut [u8],
    base: usize,
    stride: &[usize],
) {
    let n = ranges.len();
    let es = fill.len();
    let lo: Idx = (0..n).map(|a| ranges[a].start.max(origin[a])).collect();
    let hi: Idx = (0..n)
        .map(|a| ranges[a].end.min(origin[a] + dims[a]))
        .collect();
    if (0..n).any(|a| lo[a] >= hi[a]) {
        return;
    }
    let mut cstride: SmallVec<[usize; 6]> = smallvec::smallvec![1usize; n];
    for a in (0..n - 1).rev() {
        cstride[a] = cstride[a + 1] * dims[a + 1] as usize;
    }
    // Runs along the last axis, rows along the one before, an odometer
    // over the others (one position for a channel or a 3D array).
    let last = n - 1;
    let rows_axis = n.saturating_sub(2);
    let rows = if n >= 2 {
        (hi[rows_axis] - lo[rows_axis]) as usize
    } else {
        1
    };
    let (cs_row, os_row) = if n >= 2 {
        (cstride[rows_axis] * es, stride[rows_axis] * es)
    } else {
        (0, 0)
    };
    let run = (hi[last] - lo[last]) as usize;
    let contiguous = stride[last] == 1;
    let os_el = stride[last] * es;
    let uniform_fill = fill.iter().all(|&b| b == fill[0]);
    let outer = n.saturating_sub(2);
    let mut p = lo.clone();
    loop {
        let mut so = 0usize;
        let mut oo = base;
        for a in 0..n {
            so += (p[a] - origin[a]) as usize * cstride[a];
            oo += (p[a] - ranges[a].start) as usize * stride[a];
        }
        let (mut so, mut oo) = (so * es, oo * es);
        if let (Some(d), true) = (data, contiguous) {
            // Rows of the chunk into rows of the output. Runs of a voxel
            // or two (an apron one deep, a shell's face across the last
            // axis) element by element, and rows of the usual brick widths
            // in moves of a fixed size: no `memcpy` call per row, the
            // bounds checked once per column of rows.
            let (s, o) = ((so, cs_row), (oo, os_row));
            match (run * es, es) {
                (_, 1) if run <= 2 => copy_columns::<1>(out, d, s, o, rows, run),
                (_, 2) if run <= 2 => copy_columns::<2>(out, d, s, o, rows, run),
                (_, 4) if run <= 2 => copy_columns::<4>(out, d, s, o, rows, run),
                (_, 8) if run <= 2 => copy_columns::<8>(out, d, s, o, rows, run),
                (32, _) => copy_runs::<32>(out, d, s, o, rows),
                (64, _) => copy_runs::<64>(out, d, s, o, rows),
                (128, _) => copy_runs::<128>(out, d, s, o, rows),
                (256, _) => copy_runs::<256>(out, d, s, o, rows),
                (b, _) => {
                    for r in 0..rows {
                        let (s, o) = (so + r * cs_row, oo + r * os_row);
                        out[o..o + b].copy_from_slice(&d[s..s + b]);
                    }
                }
            }
        } else {
            for _ in 0..rows {
                match data {
                    Some(d) => {
                        for i in 0..run {
                            let o = oo + i * os_el;
                            out[o..o + es].copy_from_slice(&d[so + i * es..so + (i + 1) * es]);
                        }
                    }
                    None if contiguous && uniform_fill => out[oo..oo + run * es].fill(fill[0]),
                    None => {
                        for i in 0..run {
                            let o = oo + i * os_el;
                            out[o..o + es].copy_from_slice(fill);
                        }
                    }
                }
                so += cs_row;
                oo += os_row;
            }
        }
        // Next position over the outer axes.
        let mut a = outer;
        loop {
            if a == 0 {
                return;
            }
            a -= 1;
            p[a] += 1;
            if p[a] < hi[a] {
                break;
            }
            p[a] = lo[a];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;

    fn chunk(origin: [u64; 2], dims: [u64; 2], base: u8) -> Decoded {
        let n = (dims[0] * dims[1]) as usize;
        Decoded {
            origin: origin.to_vec(),
            dims: dims.to_vec(),
            body: Body::Data((0..n).map(|i| base.wrapping_add(i as u8)).collect()),
        }
    }

    fn first(d: &Decoded) -> u8 {
        match &d.body {
            Body::Data(v) => v[0],
            _ => panic!("not a whole chunk"),
        }
    }

    /// Whole boxes wanted of keys `[i, 0]` (chunks of 1×4 at row i).
    fn whole(keys: &[Idx]) -> Vec<(Idx, Idx)> {
        keys.iter()
            .map(|k| {
                (
                    smallvec::smallvec![k[0], 0],
                    smallvec::smallvec![k[0] + 1, 4],
                )
            })
            .collect()
    }

    #[test]
    fn copy_into_places_the_overlap() {
        // Chunk covers rows 2..4, columns 4..8; the read 3..5 × 2..6 into a
        // 4×6 box at (1, 1).
        let c = chunk([2, 4], [2, 4], 0);
        let mut out = vec![9u8; 24];
        copy_into(&c, &[3..5, 2..6], &[0], &mut out, 6 + 1, &[6, 1]);
        // Overlap: row 3, columns 4..6 → chunk elements 4, 5 at box (1, 3..5).
        let mut want = vec![9u8; 24];
        want[6 + 3] = 4;
        want[6 + 4] = 5;
        assert_eq!(out, want);
        // All-fill chunk.
        let f = Decoded {
            origin: vec![2, 4],
            dims: vec![2, 4],
            body: Body::Fill,
        };
        let mut out = vec![9u8; 24];
        copy_into(&f, &[3..5, 2..6], &[7], &mut out, 7, &[6, 1]);
        want[6 + 3] = 7;
        want[6 + 4] = 7;
        assert_eq!(out, want);
    }

    /// `copy_into` equals a copy element by element from the chunk's C
    /// order, for elements of 1, 2, 4, 8 and 3 bytes, rows whose bytes
    /// are and are not one of the fixed-size moves (32, 64, 128, 256),
    /// apron columns one and two deep, into a larger box (contiguous rows)
    /// and with a stride along the last axis.
    #[test]
    fn copies_equal_an_element_by_element_copy() {
        let mut seed = 7u64;
        let mut rnd = |n: u64| {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) % n
        };
        let mut checked = 0;
        for es in [1usize, 2, 3, 4, 8] {
            for width in [8u64, 16, 32, 64, 5, 24] {
                // A 3-D chunk of `width` along x at (4, 6, 8·width).
                let dims = [5u64, 7, width];
                let origin = [4u64, 6, 8 * width];
                let n = dims.iter().product::<u64>() as usize * es;
                let data: Vec<u8> = (0..n).map(|_| rnd(256) as u8).collect();
                let c = Decoded {
                    origin: origin.to_vec(),
                    dims: dims.to_vec(),
                    body: Body::Data(data.clone()),
                };
                for trial in 0..40 {
                    // The read box: around the chunk, or one or two deep
                    // along x at one of its faces.
                    let mut ranges: Vec<Range<u64>> = (0..3)
                        .map(|a| {
                            let lo = origin[a] - 1 + rnd(dims[a] + 1);
                            lo..(lo + 1 + rnd(dims[a] + 2)).min(origin[a] + dims[a] + 2)
                        })
                        .collect();
                    let deep = 1 + rnd(2);
                    match trial % 3 {
                        0 => ranges[2] = origin[2] + width - deep..origin[2] + width + 3,
                        1 => ranges[2] = origin[2] - 3..origin[2] + deep,
                        _ => {}
                    }
                    let box_dims: Vec<u64> = ranges.iter().map(|r| r.end - r.start + 2).collect();
                    let sx = 1 + (trial % 5 == 4) as usize;
                    let stride = [
                        (box_dims[1] * box_dims[2]) as usize * sx,
                        box_dims[2] as usize * sx,
                        sx,
                    ];
                    let base = stride[0] + stride[1] + stride[2];
                    let total = box_dims.iter().product::<u64>() as usize * sx * es + 8 * es;
                    let mut got = vec![0xAAu8; total];
                    copy_into(&c, &ranges, &vec![0; es], &mut got, base, &stride);
                    let mut want = vec![0xAAu8; total];
                    for z in ranges[0].clone() {
                        for y in ranges[1].clone() {
                            for x in ranges[2].clone() {
                                let p = [z, y, x];
                                if (0..3).any(|a| p[a] < origin[a] || p[a] >= origin[a] + dims[a]) {
                                    continue;
                                }
                                let si = (((z - origin[0]) * dims[1] + y - origin[1]) * dims[2] + x
                                    - origin[2]) as usize
                                    * es;
                                let oi = (base
                                    + (z - ranges[0].start) as usize * stride[0]
                                    + (y - ranges[1].start) as usize * stride[1]
                                    + (x - ranges[2].start) as usize * stride[2])
                                    * es;
                                want[oi..oi + es].copy_from_slice(&data[si..si + es]);
                            }
                        }
                    }
                    assert_eq!(got, want, "es {es} width {width} trial {trial} {ranges:?}");
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, 5 * 6 * 40);
    }

    #[test]
    fn shells_hold_the_faces_and_read_like_the_chunk() {
        // A 64×64 chunk at (64, 128), shell one deep.
        let c = chunk([64, 128], [64, 64], 0);
        let s = c.shell(1, 1).unwrap();
        assert!(s.cost() < c.cost() / 2);
        // Each edge row / column is held, and parts of them; the middle is not.
        for (lo, hi) in [
            ([64, 128], [65, 192]),
            ([127, 128], [128, 192]),
            ([64, 128], [128, 129]),
            ([64, 191], [128, 192]),
            ([90, 191], [100, 192]),
        ] {
            assert!(s.covers(&lo, &hi), "{lo:?}..{hi:?}");
            let ranges = [lo[0]..hi[0], lo[1]..hi[1]];
            let n = ((hi[0] - lo[0]) * (hi[1] - lo[1])) as usize;
            let stride = [(hi[1] - lo[1]) as usize, 1];
            let (mut a, mut b) = (vec![0u8; n], vec![1u8; n]);
            copy_into(&c, &ranges, &[0], &mut a, 0, &stride);
            copy_into(&s, &ranges, &[0], &mut b, 0, &stride);
            assert_eq!(a, b, "{lo:?}..{hi:?}");
        }
        assert!(!s.covers(&[65, 129], &[66, 130]));
        assert!(!s.covers(&[64, 128], &[66, 130]));
        // Too small to be worth a shell.
        assert!(chunk([0, 0], [8, 8], 0).shell(1, 1).is_none());
    }

    #[test]
    fn cache_loads_each_chunk_once_and_stays_in_budget() {
        let budget = 3 * (ENTRY_COST + 4);
        let cache = ChunkCache::new(budget, 0, 1);
        let loads = AtomicUsize::new(0);
        let load = |ks: &[Vec<u64>]| -> Result<Vec<Decoded>> {
            loads.fetch_add(ks.len(), Ordering::Relaxed);
            Ok(ks
                .iter()
                .map(|k| chunk([k[0], 0], [1, 4], k[0] as u8))
                .collect())
        };
        let keys: Vec<Idx> = (0..3).map(|i| smallvec::smallvec![i, 0]).collect();
        let got = cache.get_or_load(0, &keys, &whole(&keys), load).unwrap();
        assert_eq!(first(&got[2]), 2);
        cache.get_or_load(0, &keys, &whole(&keys), load).unwrap();
        assert_eq!(loads.load(Ordering::Relaxed), 3);
        // A fourth chunk evicts the least recently used (chunk 0).
        let k3: [Idx; 1] = [smallvec::smallvec![3, 0]];
        cache.get_or_load(0, &k3, &whole(&k3), load).unwrap();
        assert!(cache.bytes() <= budget);
        cache
            .get_or_load(0, &keys[1..], &whole(&keys[1..]), load)
            .unwrap();
        assert_eq!(loads.load(Ordering::Relaxed), 4);
        cache
            .get_or_load(0, &keys[..1], &whole(&keys[..1]), load)
            .unwrap();
        assert_eq!(loads.load(Ordering::Relaxed), 5);
        assert!(cache.bytes() <= budget);
    }

    #[test]
    fn evicted_chunks_leave_shells_that_serve_aprons() {
        // Room for two 64×64 chunks and a shell.
        let whole_cost = ENTRY_COST + 64 * 64;
        let budget = 2 * whole_cost + 1000;
        let cache = ChunkCache::new(budget, 1, 1);
        let loads = AtomicUsize::new(0);
        let load = |ks: &[Vec<u64>]| -> Result<Vec<Decoded>> {
            loads.fetch_add(ks.len(), Ordering::Relaxed);
            Ok(ks
                .iter()
                .map(|k| chunk([64 * k[0], 0], [64, 64], k[0] as u8))
                .collect())
        };
        let all = |k: u64| -> (Idx, Idx) {
            (
                smallvec::smallvec![64 * k, 0],
                smallvec::smallvec![64 * k + 64, 64],
            )
        };
        for k in 0..3 {
            cache
                .get_or_load(0, &[smallvec::smallvec![k, 0]], &[all(k)], load)
                .unwrap();
            assert!(cache.bytes() <= budget);
        }
        assert_eq!(loads.load(Ordering::Relaxed), 3);
        // Chunk 0 was evicted whole: its last row is still there.
        let got = cache
            .get_or_load(
                0,
                &[smallvec::smallvec![0, 0]],
                &[(smallvec::smallvec![63, 0], smallvec::smallvec![64, 64])],
                load,
            )
            .unwrap();
        assert!(matches!(got[0].body, Body::Shell(_)));
        assert_eq!(loads.load(Ordering::Relaxed), 3);
        // Its middle is not: loaded again.
        let got = cache
            .get_or_load(0, &[smallvec::smallvec![0, 0]], &[all(0)], load)
            .unwrap();
        assert_eq!(first(&got[0]), 0);
        assert_eq!(loads.load(Ordering::Relaxed), 4);
        assert!(cache.bytes() <= budget);
    }

    #[test]
    fn failed_and_panicking_loads_release_their_claims() {
        let cache = ChunkCache::new(1 << 20, 0, 1);
        let k: Vec<Idx> = vec![smallvec::smallvec![0, 0]];
        let need = whole(&k);
        let e = cache.get_or_load(0, &k, &need, |_| {
            Err(StoreError::invalid(Path::new("x"), "chunk", "bad"))
        });
        assert!(e.is_err());
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            let _ = cache.get_or_load(0, &k, &need, |_| panic!("codec"));
        }));
        assert!(r.is_err());
        // Neither left the chunk marked as loading: this returns.
        let got = cache
            .get_or_load(0, &k, &need, |ks| {
                Ok(ks.iter().map(|_| chunk([0, 0], [1, 4], 5)).collect())
            })
            .unwrap();
        assert_eq!(first(&got[0]), 5);
    }

    #[test]
    fn threads_share_a_chunk_being_loaded() {
        let cache = ChunkCache::new(1 << 20, 0, 1);
        let loads = AtomicUsize::new(0);
        let keys: Vec<Idx> = (0..8).map(|i| smallvec::smallvec![i, 0]).collect();
        let need = whole(&keys);
        std::thread::scope(|s| {
            for _ in 0..4 {
                s.spawn(|| {
                    let got = cache
                        .get_or_load(0, &keys, &need, |ks| {
                            loads.fetch_add(ks.len(), Ordering::Relaxed);
                            std::thread::sleep(std::time::Duration::from_millis(5));
                            Ok(ks
                                .iter()
                                .map(|k| chunk([k[0], 0], [1, 4], k[0] as u8))
                                .collect())
                        })
                        .unwrap();
                    for (i, g) in got.iter().enumerate() {
                        assert_eq!(first(g), i as u8);
                    }
                });
            }
        });
        assert_eq!(loads.load(Ordering::Relaxed), 8);
    }
}
