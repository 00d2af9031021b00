//! Bricks over HTTP: a store's metadata and its bricks read with `GET`s
//! (byte ranges for shard indexes and inner chunks), decoded here and cut
//! into the same padded bricks the native loader hands out
//! ([`brickyard_cache::assemble`]). Shard indexes and decoded chunks are
//! kept in bounded caches, so the aprons of neighbouring bricks do not
//! fetch or decode their chunks again.
//!
//! Nothing here knows the browser: reads go through [`Fetch`], which the
//! page implements over `fetch()` and tests over files.

use crate::codec::{decode_chain, swap_bytes};
use crate::zarr::{self, Codec, Multiscale};
use brickyard_cache::assemble::{brick_buffer, finish_brick, PaddedRegion};
use brickyard_cache::brick::{BrickGeometry, BrickKey, LoadedBrick};
use brickyard_cache::ranges::BrickRanges;
use brickyard_core::Dims3;
use futures_util::future::{FutureExt, Shared};
use std::cell::RefCell;
use std::collections::{HashMap, VecDeque};
use std::future::Future;
use std::pin::Pin;
use std::rc::Rc;
use std::sync::Arc;

/// A future that stays on its thread (the browser has one).
pub type LocalFuture<T> = Pin<Box<dyn Future<Output = T>>>;

/// Which bytes of an object to get.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Range {
    All,
    /// `len` bytes from `start`.
    Span {
        start: u64,
        len: u64,
    },
    /// The last `len` bytes.
    Suffix(u64),
}

/// Reads objects of one store by path below its root. `Ok(None)`: the
/// object does not exist (a chunk never written: the fill value).
pub trait Fetch {
    fn get(&self, path: &str, range: Range) -> LocalFuture<Result<Option<Vec<u8>>, String>>;

    /// [`get`](Self::get), also giving the object's `ETag` where the
    /// server sends one, and sending `If-Match: if_match` where given: an
    /// object that is no longer the one of that tag (HTTP 412) is an error
    /// containing [`STORE_CHANGED`]. Without tags (files, servers without
    /// `ETag`): `get`, no tag, no check.
    fn get_tagged(
        &self,
        path: &str,
        range: Range,
        if_match: Option<&str>,
    ) -> LocalFuture<Result<Got, String>> {
        let _ = if_match;
        let f = self.get(path, range);
        Box::pin(async move {
            Ok(Got {
                bytes: f.await?,
                etag: None,
                whole: false,
            })
        })
    }
}

/// What a tagged read got: the bytes (`None`: not found) and the object's
/// `ETag`, where the server sends one.
#[derive(Clone, Debug, Default)]
pub struct Got {
    pub bytes: Option<Vec<u8>>,
    pub etag: Option<String>,
    /// The server ignored the range asked for and answered with the whole
    /// object (HTTP 200 to a `Range`): `bytes` holds all of it, for the
    /// reader to [`cut`] (and keep: [`WebSource`] keeps such objects, so
    /// the other ranges of one are not downloaded whole again).
    pub whole: bool,
}

/// The bytes of `range` of a whole object `b`.
pub fn cut(b: &[u8], range: Range) -> Result<&[u8], String> {
    match range {
        Range::All => Ok(b),
        Range::Span { start, len } => start
            .checked_add(len)
            .and_then(|e| b.get(start as usize..e as usize))
            .ok_or_else(|| {
                format!(
                    "range {start}+{len} past the end of the object ({} bytes)",
                    b.len()
                )
            }),
        Range::Suffix(n) => Ok(&b[b.len().saturating_sub(n as usize)..]),
    }
}

/// What a read of an object that changed since the page read it says
/// (a store reconverted in place while the page has it open).
pub const STORE_CHANGED: &str = "the store changed on the server since it was opened: reload";

/// What a request that never got an answer says (a [`Fetch`]'s error
/// containing it: the server is down, or CORS withheld the answer). The
/// first such error marks the source unreachable
/// ([`WebSource::unreachable`]): nothing more is asked of the server until
/// [`WebSource::probe`] finds it back.
pub const UNREACHABLE: &str =
    "could not reach the server (down, or the request was blocked by CORS)";

/// What a read not sent because the server was found unreachable says.
pub const NOT_ASKED: &str = "not asked for: the server could not be reached";

/// A brick named for people: level, channel and brick (z, y, x).
pub fn brick_name(k: &BrickKey) -> String {
    format!(
        "level {}, channel {}, brick (z {}, y {}, x {})",
        k.level, k.channel, k.brick[0], k.brick[1], k.brick[2]
    )
}

/// Counters of what a source fetched.
#[derive(Clone, Copy, Debug, Default)]
pub struct SourceStats {
    pub requests: u64,
    pub bytes: u64,
    pub chunks_decoded: u64,
    pub chunk_cache_hits: u64,
}

/// A cache of values with a byte size, least recently used out first.
struct Lru<K, V> {
    map: HashMap<K, (V, usize, u64)>,
    order: VecDeque<(K, u64)>,
    bytes: usize,
    budget: usize,
    tick: u64,
    /// The newest value stays even where it alone is over the budget.
    keep_newest: bool,
}

impl<K: std::hash::Hash + Eq + Clone, V: Clone> Lru<K, V> {
    fn new(budget: usize) -> Self {
        Lru {
            map: HashMap::new(),
            order: VecDeque::new(),
            bytes: 0,
            budget,
            tick: 0,
            keep_newest: false,
        }
    }
    /// An `Lru` that keeps the newest value even where it alone is over
    /// the budget (whole objects downloaded: the next range of one read
    /// from it rather than downloaded whole again).
    fn keeping_newest(budget: usize) -> Self {
        Lru {
            keep_newest: true,
            ..Lru::new(budget)
        }
    }
    fn get(&mut self, k: &K) -> Option<V> {
        self.tick += 1;
        let t = self.tick;
        let e = self.map.get_mut(k)?;
        e.2 = t;
        self.order.push_back((k.clone(), t));
        Some(e.0.clone())
    }
    fn remove(&mut self, k: &K) {
        if let Some(e) = self.map.remove(k) {
            self.bytes -= e.1;
        }
    }
    fn put(&mut self, k: K, v: V, size: usize) {
        self.tick += 1;
        if let Some(old) = self.map.insert(k.clone(), (v, size, self.tick)) {
            self.bytes -= old.1;
        }
        self.bytes += size;
        self.order.push_back((k, self.tick));
        while self.bytes > self.budget {
            let Some((k, t)) = self.order.pop_front() else {
                break;
            };
            if self.keep_newest && t == self.tick {
                self.order.push_front((k, t));
                break;
            }
            if self.map.get(&k).is_some_and(|e| e.2 == t) {
                let e = self.map.remove(&k).expect("present");
                self.bytes -= e.1;
            }
        }
        // Stale order entries of keys used again: keep the queue bounded.
        if self.order.len() > 4 * self.map.len() + 64 {
            let map = &self.map;
            self.order
                .retain(|(k, t)| map.get(k).is_some_and(|e| e.2 == *t));
        }
    }
}

/// A shard's index: (offset, length) per inner chunk, `None` when the
/// shard does not exist; with the shard's `ETag` when the server sent one
/// (the later reads of its chunks ask for that version: `If-Match`).
type ShardIndex = Option<(Rc<Vec<[u64; 2]>>, Option<String>)>;

/// An OME-Zarr store read over [`Fetch`].
pub struct WebSource {
    fetch: Rc<dyn Fetch>,
    pub meta: Multiscale,
    pub geometry: BrickGeometry,
    indexes: RefCell<Lru<(usize, Vec<u64>), ShardIndex>>,
    chunks: RefCell<Lru<ChunkKey, Rc<Vec<u8>>>>,
    pub stats: RefCell<SourceStats>,
    inflight: RefCell<HashMap<(String, Range), SharedFetch>>,
    /// The server answered a range with the whole object (it ignores
    /// `Range`, as `python3 -m http.server`): later ranges are read from
    /// whole objects, downloaded once (concurrent reads of one object
    /// joined) and kept in `wholes` (least recently used out first, at
    /// most `chunk_budget` bytes, or the newest object alone where it is
    /// larger), not downloaded whole again per range.
    ranges_ignored: std::cell::Cell<bool>,
    /// Whole objects of a server that ignores ranges, with their `ETag`s.
    wholes: RefCell<Lru<String, Whole>>,
    /// The root document read at opening and its `ETag` (`None`: the
    /// server sends none; nothing is checked then).
    root: (String, Option<String>),
    /// The store changed on the server since it was opened: nothing more
    /// is read from it (its indexes and chunks may be another version's).
    changed: std::cell::Cell<bool>,
    /// A request found the server unreachable ([`UNREACHABLE`]): later
    /// reads fail at once, without a request, until
    /// [`probe`](Self::probe) gets an answer.
    unreachable: std::cell::Cell<bool>,
    /// Per level, the brick statistics read ([`brick_ranges`](Self::brick_ranges)):
    /// a chunk or shard absent where they say its bricks hold data fails
    /// the brick, as natively (`LevelStats::check_lost`).
    level_stats: RefCell<Vec<Option<Rc<LevelStats>>>>,
    chunk_budget: usize,
}

/// One level's brick statistics, decoded: per chunk of the array (by its
/// first four indexes), its values, `None` where the chunk could not be
/// read.
struct LevelStats {
    chunk: [u64; 4],
    chunks: HashMap<[u64; 4], Option<Vec<f64>>>,
    /// The store bricks' edge (`brickyard.brick`).
    brick: Dims3,
}

impl LevelStats {
    /// (min, max) of store brick `b` of channel `c`, `None` if unknown.
    fn get(&self, c: u64, b: Dims3) -> Option<(f64, f64)> {
        let p = [c, b[0], b[1], b[2]];
        let ch = self.chunk;
        let values = self
            .chunks
            .get(&[0, 1, 2, 3].map(|a| p[a] / ch[a]))?
            .as_ref()?;
        let r = [0, 1, 2, 3].map(|a| p[a] % ch[a]);
        let e = ((((r[0] * ch[1] + r[1]) * ch[2] + r[2]) * ch[3] + r[3]) * 2) as usize;
        Some((values[e], values[e + 1]))
    }
}

/// Why a chunk reads as the fill value: its file (shard or chunk) is not
/// there, or its shard's index has no entry for it.
const ABSENT_FILE: &str = "not found (HTTP 404)";
const ABSENT_ENTRY: &str = "its shard's index has no entry for this chunk";

/// A whole object (of a server that ignores ranges) and its `ETag`.
type Whole = (Rc<Vec<u8>>, Option<String>);

/// (level, chunk or shard index, inner chunk or `usize::MAX`).
type ChunkKey = (usize, Vec<u64>, usize);

/// A read's bytes (`None`: not found), the object's `ETag`, and whether
/// the bytes are the whole object though a range was asked for
/// ([`Got::whole`]).
type Tagged = Result<(Option<Rc<Vec<u8>>>, Option<String>, bool), String>;

type SharedFetch = Shared<LocalFuture<Tagged>>;

async fn get_json(fetch: &dyn Fetch, path: &str) -> Result<Option<Vec<u8>>, String> {
    fetch.get(path, Range::All).await
}

impl WebSource {
    /// Open the store: its root metadata, then every level's array.
    /// `brick` is the engine's brick edge, `chunk_budget` the bytes of
    /// decoded chunks kept.
    pub async fn open(
        fetch: Rc<dyn Fetch>,
        brick: u64,
        apron: u64,
        chunk_budget: usize,
    ) -> Result<WebSource, String> {
        let root = fetch.get_tagged("zarr.json", Range::All, None).await?;
        let (mut ms, paths, root) = match root.bytes {
            Some(t) => {
                let (ms, paths) = zarr::parse_root(3, &t).map_err(|e| e.to_string())?;
                (ms, paths, ("zarr.json".to_string(), root.etag))
            }
            None => match fetch.get_tagged(".zattrs", Range::All, None).await? {
                Got {
                    bytes: Some(t),
                    etag,
                    ..
                } => {
                    let (ms, paths) = zarr::parse_root(2, &t).map_err(|e| e.to_string())?;
                    (ms, paths, (".zattrs".to_string(), etag))
                }
                Got { bytes: None, .. } => {
                    return Err(
                        "zarr.json: not found (nor .zattrs): not a Zarr store, or the URL does not name its root"
                            .into(),
                    )
                }
            },
        };
        if let Some(why) = ms.incomplete {
            return Err(format!("zarr.json: the store is incomplete: {why}"));
        }
        for p in &paths {
            let a = if ms.zarr_format == 3 {
                let doc = format!("{p}/zarr.json");
                let t = get_json(&*fetch, &doc)
                    .await?
                    .ok_or(format!("{doc}: not found"))?;
                zarr::parse_v3_array(p, &t)
            } else {
                let doc = format!("{p}/.zarray");
                let t = get_json(&*fetch, &doc)
                    .await?
                    .ok_or(format!("{doc}: not found"))?;
                zarr::parse_v2_array(p, &t)
            }
            .map_err(|e| e.to_string())?;
            ms.levels.push(a);
        }
        zarr::check_levels(&ms).map_err(|e| e.to_string())?;
        let geometry = BrickGeometry {
            brick: [brick; 3],
            apron,
            levels: (0..ms.levels.len()).map(|l| ms.dims(l)).collect(),
            channels: ms.n_channels(),
            dtype: ms.levels[0].dtype,
        };
        if !geometry.keys_fit() {
            return Err(format!("the volume has too many bricks of {brick}³ per axis for brick keys; use larger bricks"));
        }
        Ok(WebSource {
            fetch,
            meta: ms,
            geometry,
            indexes: RefCell::new(Lru::new(8 << 20)),
            chunks: RefCell::new(Lru::new(chunk_budget)),
            stats: RefCell::new(SourceStats::default()),
            inflight: RefCell::new(HashMap::new()),
            ranges_ignored: std::cell::Cell::new(false),
            wholes: RefCell::new(Lru::keeping_newest(chunk_budget)),
            root,
            changed: std::cell::Cell::new(false),
            unreachable: std::cell::Cell::new(false),
            level_stats: RefCell::new(vec![]),
            chunk_budget,
        })
    }

    /// Whether the store changed on the server since it was opened (seen
    /// by a read of a shard's chunk that asked for the version of its
    /// index, or by [`check_changed`](Self::check_changed)).
    pub fn changed(&self) -> bool {
        self.changed.get()
    }

    /// Whether a request found the server unreachable (and no
    /// [`probe`](Self::probe) found it back since): reads fail at once,
    /// with [`NOT_ASKED`], rather than a request per brick.
    pub fn unreachable(&self) -> bool {
        self.unreachable.get()
    }

    /// Ask the server for the store's root document, once, past the
    /// [`unreachable`](Self::unreachable) mark: any answer clears the mark
    /// (reads go to the server again) and returns `true`; no answer keeps
    /// it and returns `false`.
    pub async fn probe(&self) -> bool {
        match self.fetch.get(&self.root.0, Range::All).await {
            Err(e) if e.contains(UNREACHABLE) => false,
            _ => {
                self.unreachable.set(false);
                true
            }
        }
    }

    /// Stop using what was read of the store: its shard indexes and
    /// chunks are dropped, and every later load fails with
    /// [`STORE_CHANGED`] (bricks already resident stay drawn).
    fn mark_changed(&self) {
        if !self.changed.replace(true) {
            *self.indexes.borrow_mut() = Lru::new(8 << 20);
            *self.chunks.borrow_mut() = Lru::new(self.chunk_budget);
            *self.wholes.borrow_mut() = Lru::keeping_newest(self.chunk_budget);
        }
    }

    /// Ask the server whether the store's root document is still the one
    /// read at opening (`If-Match` its `ETag`; a reconversion writes it
    /// anew): `true` when it changed (then as
    /// [`mark_changed`](Self::mark_changed)). Servers without `ETag`: never.
    /// A failed request (the server down) says nothing.
    pub async fn check_changed(&self) -> bool {
        if self.changed.get() {
            return true;
        }
        let (doc, Some(tag)) = &self.root else {
            return false;
        };
        if self.unreachable.get() {
            return false;
        }
        match self.fetch.get_tagged(doc, Range::All, Some(tag)).await {
            Err(e) if e.contains(STORE_CHANGED) => self.mark_changed(),
            Err(e) if e.contains(UNREACHABLE) => self.unreachable.set(true),
            Ok(Got { bytes: None, .. }) => self.mark_changed(),
            Ok(Got { etag: Some(t), .. }) if t != *tag => self.mark_changed(),
            _ => {}
        }
        self.changed.get()
    }

    /// The store's per-brick statistics (`brickyard.stats`: per level an
    /// array `[channel, brick z, y, x, 2]` of (min, max) per store brick
    /// of `brickyard.brick` voxels) as the value ranges of the engine's
    /// padded bricks, as the native loader makes them
    /// ([`Loader::brick_ranges`](brickyard_cache::loader)): the renderers
    /// cross bricks their transfer function hides without loading them,
    /// and the residency octree knows what nodes hold before their bricks
    /// arrive. A level without statistics, with an array of another shape
    /// or type, or of more than `max_bricks` engine bricks × channels is
    /// left out; a chunk that cannot be read leaves its bricks unknown
    /// (loaded to learn what they hold). What went wrong comes back, one
    /// line each, for the page to report; a store without statistics is
    /// not a problem.
    pub async fn brick_ranges(&self, max_bricks: u64) -> (BrickRanges, Vec<String>) {
        let g = &self.geometry;
        let none = || BrickRanges {
            levels: vec![None; g.levels.len()],
        };
        let (Some(dir), Some(sb)) = (&self.meta.stats, self.meta.stats_brick) else {
            return (none(), vec![]);
        };
        if sb.contains(&0) || self.meta.zarr_format != 3 {
            return (none(), vec![]);
        }
        let mut problems = vec![];
        let mut levels: Vec<Option<Rc<LevelStats>>> = vec![];
        for (l, dims) in g.levels.iter().enumerate() {
            let count = g.bricks_per_level(l).iter().product::<u64>() * g.channels as u64;
            let stats = if count > max_bricks {
                None
            } else {
                self.level_stats(&format!("{dir}/{l}"), sb, *dims, &mut problems)
                    .await
                    .map(Rc::new)
            };
            levels.push(stats);
        }
        let r = BrickRanges::build(
            g,
            sb,
            max_bricks,
            |l| levels[l].is_some(),
            |l, c, b| levels[l].as_ref()?.get(c as u64, b),
        );
        *self.level_stats.borrow_mut() = levels;
        (r, problems)
    }

    /// One level's statistics array at `path`, read whole (its chunks at
    /// once): `None` when absent, or (with a line in `problems`) when it
    /// is not the array expected.
    async fn level_stats(
        &self,
        path: &str,
        sb: Dims3,
        dims: Dims3,
        problems: &mut Vec<String>,
    ) -> Option<LevelStats> {
        let doc = format!("{path}/zarr.json");
        let text = match self.fetch.get(&doc, Range::All).await {
            Ok(Some(t)) => t,
            Ok(None) => return None,
            Err(e) => {
                problems.push(format!("{doc}: {e}"));
                return None;
            }
        };
        let a = match zarr::parse_v3_array(path, &text) {
            Ok(a) => a,
            Err(e) => {
                problems.push(e.to_string());
                return None;
            }
        };
        let nb = [0, 1, 2].map(|i| dims[i].div_ceil(sb[i]));
        let want = vec![self.geometry.channels as u64, nb[0], nb[1], nb[2], 2];
        if a.shape != want
            || a.dtype != brickyard_core::DType::F64
            || a.chunk[4] != 2
            || a.sharding().is_some()
        {
            problems.push(format!(
                "{doc}: expected an unsharded float64 array of shape {want:?} with chunks \
                 ending in 2, found {:?} {:?} chunks {:?}: the level's bricks are loaded to \
                 learn what they hold",
                a.dtype, a.shape, a.chunk
            ));
            return None;
        }
        let ch = [a.chunk[0], a.chunk[1], a.chunk[2], a.chunk[3]];
        let grid = [0, 1, 2, 3].map(|i| a.shape[i].div_ceil(ch[i]));
        let mut idx = vec![];
        for c in 0..grid[0] {
            for z in 0..grid[1] {
                for y in 0..grid[2] {
                    for x in 0..grid[3] {
                        idx.push([c, z, y, x]);
                    }
                }
            }
        }
        let n = ch.iter().product::<u64>() as usize * 2;
        let reads = idx.iter().map(|i| {
            let key = a.chunk_key(&[i[0], i[1], i[2], i[3], 0]);
            async move { (key.clone(), self.fetch.get(&key, Range::All).await) }
        });
        let mut chunks = HashMap::new();
        for (i, (key, got)) in idx.iter().zip(futures_util::future::join_all(reads).await) {
            let values = match got {
                // Never written: the fill value (NaN: nothing but NaN),
                // as Zarr and the native loader read it.
                Ok(None) => {
                    let fill = f64::from_ne_bytes(a.fill[..8].try_into().expect("f64 fill"));
                    Ok(vec![fill; n])
                }
                Ok(Some(b)) => decode_chain(&a.codecs, b).and_then(|(mut b, big)| {
                    if big {
                        swap_bytes(&mut b, 8);
                    }
                    if b.len() != n * 8 {
                        return Err(format!("{} bytes, {} expected", b.len(), n * 8));
                    }
                    Ok(b.chunks_exact(8)
                        .map(|v| f64::from_le_bytes(v.try_into().expect("8 bytes")))
                        .collect())
                }),
                Err(e) => Err(e),
            };
            match values {
                Ok(v) => {
                    chunks.insert(*i, Some(v));
                }
                Err(e) => {
                    problems.push(format!(
                        "{key}: cannot be read ({e}): its bricks are loaded to learn what \
                         they hold, none is skipped as empty"
                    ));
                    chunks.insert(*i, None);
                }
            }
        }
        Some(LevelStats {
            chunk: ch,
            chunks,
            brick: sb,
        })
    }

    /// The bounding box of every label in the label image's statistics
    /// ([`label_table`]), read whole in one request: `None` where the
    /// store has none or it is larger than `max_bytes`.
    pub async fn label_boxes(
        &self,
        max_bytes: usize,
    ) -> Result<Option<std::collections::HashMap<u64, [u64; 6]>>, String> {
        use brickyard_core::label_table;
        let path = label_table::PATH;
        let Some(b) = self.fetch.get(path, Range::All).await? else {
            return Ok(None);
        };
        if b.len() > max_bytes {
            return Ok(None);
        }
        let mut out = std::collections::HashMap::new();
        label_table::parse_table(&String::from_utf8_lossy(&b), |id, r| {
            out.insert(id, r.bounds());
        })
        .map_err(|e| format!("{path}: {e}"))?;
        Ok(Some(out))
    }

    /// One read; reads of the same bytes already under way are joined,
    /// not sent again (neighbouring bricks ask for the same chunks).
    /// `if_match`: the object's version expected (its `ETag`); another
    /// one marks the store changed ([`changed`](Self::changed)). From a
    /// server that ignores ranges, ranges are cut from whole objects, each
    /// downloaded once while kept ([`ranges_ignored`](Self::ranges_ignored)).
    async fn get(
        &self,
        path: &str,
        range: Range,
        if_match: Option<&str>,
    ) -> Result<(Option<Vec<u8>>, Option<String>), String> {
        let mut ask = range;
        if range != Range::All && self.ranges_ignored.get() {
            let kept = self.wholes.borrow_mut().get(&path.to_string());
            if let Some((b, tag)) = kept {
                if if_match.is_none() || if_match == tag.as_deref() {
                    let piece = cut(&b, range).map_err(|e| format!("{path}: {e}"))?;
                    return Ok((Some(piece.to_vec()), tag));
                }
                self.wholes.borrow_mut().remove(&path.to_string());
            }
            // The whole object, one download for every range of it.
            ask = Range::All;
        }
        let (got, tag, whole) = self.get_joined(path, ask, if_match).await?;
        let Some(b) = got else {
            return Ok((None, tag));
        };
        if range == Range::All {
            return Ok((
                Some(Rc::try_unwrap(b).unwrap_or_else(|b| (*b).clone())),
                tag,
            ));
        }
        if ask == Range::All || whole {
            // (A server that answers a range with as many bytes as asked
            // for, whole, is not taken for one that ignores ranges.)
            let n = match range {
                Range::Span { len, .. } | Range::Suffix(len) => len,
                Range::All => 0,
            };
            if ask == Range::All || b.len() as u64 > n {
                self.ranges_ignored.set(true);
                let size = b.len();
                self.wholes
                    .borrow_mut()
                    .put(path.to_string(), (b.clone(), tag.clone()), size);
            }
            let piece = cut(&b, range).map_err(|e| format!("{path}: {e}"))?;
            return Ok((Some(piece.to_vec()), tag));
        }
        Ok((
            Some(Rc::try_unwrap(b).unwrap_or_else(|b| (*b).clone())),
            tag,
        ))
    }

    /// Whether the server was found to ignore ranges (it answered one with
    /// the whole object): ranges are cut from whole objects then.
    pub fn ranges_ignored(&self) -> bool {
        self.ranges_ignored.get()
    }

    /// One request, joined with one for the same bytes under way; counted
    /// in [`stats`](Self::stats) by the bytes it downloaded.
    async fn get_joined(
        &self,
        path: &str,
        range: Range,
        if_match: Option<&str>,
    ) -> Result<(Option<Rc<Vec<u8>>>, Option<String>, bool), String> {
        if self.changed.get() {
            return Err(STORE_CHANGED.into());
        }
        if self.unreachable.get() {
            return Err(format!("{path}: {NOT_ASKED}"));
        }
        let k = (path.to_string(), range);
        let shared = self.inflight.borrow().get(&k).cloned();
        let fut = match shared {
            Some(f) => f,
            None => {
                let f = self.fetch.get_tagged(path, range, if_match);
                let f: LocalFuture<Tagged> = Box::pin(async move {
                    f.await
                        .map(|g| (g.bytes.map(Rc::new), g.etag, g.whole && range != Range::All))
                });
                let f: SharedFetch = f.shared();
                self.inflight.borrow_mut().insert(k.clone(), f.clone());
                let r = f.clone().await;
                self.inflight.borrow_mut().remove(&k);
                let mut s = self.stats.borrow_mut();
                s.requests += 1;
                if let Ok((Some(b), _, _)) = &r {
                    s.bytes += b.len() as u64;
                }
                f
            }
        };
        match fut.await {
            Ok(r) => Ok(r),
            Err(e) if e.contains(STORE_CHANGED) => {
                self.mark_changed();
                Err(STORE_CHANGED.into())
            }
            Err(e) => {
                if e.contains(UNREACHABLE) {
                    self.unreachable.set(true);
                }
                Err(format!("{path}: {e}"))
            }
        }
    }

    /// The index of shard `idx` of level `l`.
    async fn shard_index(
        &self,
        l: usize,
        idx: &[u64],
        inner: usize,
        codecs: &[Codec],
        at_end: bool,
    ) -> Result<ShardIndex, String> {
        let k = (l, idx.to_vec());
        if let Some(v) = self.indexes.borrow_mut().get(&k) {
            return Ok(v);
        }
        let a = &self.meta.levels[l];
        let key = a.chunk_key(idx);
        let checksum = codecs.iter().any(|c| matches!(c, Codec::Crc32c));
        let len = inner as u64 * 16 + if checksum { 4 } else { 0 };
        let range = if at_end {
            Range::Suffix(len)
        } else {
            Range::Span { start: 0, len }
        };
        let (got, tag) = self.get(&key, range, None).await?;
        let v = match got {
            None => None,
            Some(b) => {
                if b.len() as u64 != len {
                    return Err(format!(
                        "{key}: shard index of {} bytes, expected {len}",
                        b.len()
                    ));
                }
                let (b, _) =
                    decode_chain(codecs, b).map_err(|e| format!("{key}: shard index: {e}"))?;
                Some((
                    Rc::new(
                        b.chunks_exact(16)
                            .map(|e| {
                                [
                                    u64::from_le_bytes(e[..8].try_into().unwrap()),
                                    u64::from_le_bytes(e[8..].try_into().unwrap()),
                                ]
                            })
                            .collect(),
                    ),
                    tag,
                ))
            }
        };
        self.indexes
            .borrow_mut()
            .put(k, v.clone(), len as usize + 64);
        Ok(v)
    }

    /// Chunk `inner` of (shard or chunk) `idx` of level `l`, decoded to
    /// native-endian values (`Err(why)`: not stored, the fill value).
    async fn chunk(
        &self,
        l: usize,
        idx: &[u64],
        inner: Option<usize>,
    ) -> Result<Result<Rc<Vec<u8>>, &'static str>, String> {
        let ck = (l, idx.to_vec(), inner.unwrap_or(usize::MAX));
        if let Some(v) = self.chunks.borrow_mut().get(&ck) {
            self.stats.borrow_mut().chunk_cache_hits += 1;
            return Ok(Ok(v));
        }
        let a = &self.meta.levels[l];
        let key = a.chunk_key(idx);
        let es = a.dtype.size();
        let (bytes, codecs, shape): (Option<Vec<u8>>, &[Codec], &[u64]) =
            match (a.sharding(), inner) {
                (Some((ishape, icodecs, index_codecs, at_end)), Some(i)) => {
                    let n: usize = a
                        .chunk
                        .iter()
                        .zip(ishape)
                        .map(|(s, c)| s.div_ceil(*c) as usize)
                        .product();
                    let Some((index, tag)) =
                        self.shard_index(l, idx, n, index_codecs, at_end).await?
                    else {
                        return Ok(Err(ABSENT_FILE));
                    };
                    let [off, len] = index[i];
                    if off == u64::MAX && len == u64::MAX {
                        (None, icodecs, ishape)
                    } else {
                        // The chunk of the shard whose index was read: a
                        // shard written anew since (a store reconverted in
                        // place) answers 412, and the store is marked
                        // changed rather than its new bytes cut by the old
                        // index.
                        let (b, _) = self
                            .get(&key, Range::Span { start: off, len }, tag.as_deref())
                            .await?;
                        match b {
                            Some(b) if b.len() as u64 == len => (Some(b), icodecs, ishape),
                            Some(b) => {
                                return Err(format!(
                                    "{key}: inner chunk {i}: {} bytes read, the index says {len}",
                                    b.len()
                                ))
                            }
                            None => {
                                return Err(format!("{key}: the shard vanished while being read"))
                            }
                        }
                    }
                }
                _ => match self.get(&key, Range::All, None).await? {
                    (None, _) => return Ok(Err(ABSENT_FILE)),
                    (b, _) => (b, &a.codecs[..], &a.chunk[..]),
                },
            };
        let Some(bytes) = bytes else {
            return Ok(Err(ABSENT_ENTRY));
        };
        let (mut v, big) = decode_chain(codecs, bytes).map_err(|e| format!("{key}: {e}"))?;
        let want = shape.iter().product::<u64>() as usize * es;
        if v.len() != want {
            return Err(format!(
                "{key}: decoded to {} bytes, a chunk of {shape:?} is {want}",
                v.len()
            ));
        }
        if big || a.big_endian {
            swap_bytes(&mut v, es);
        }
        self.stats.borrow_mut().chunks_decoded += 1;
        let v = Rc::new(v);
        let size = v.len();
        self.chunks.borrow_mut().put(ck, v.clone(), size);
        Ok(Ok(v))
    }

    /// A piece of brick `key` found absent (`why`) over `[plo, phi)` (the
    /// level's voxels, z y x): an error where the brick statistics say a
    /// store brick there holds values other than zeros, as the native
    /// loader's `LevelStats::check_lost` (a shard or chunk lost, not one
    /// never written). Only where the fill value is zeros, as there.
    fn check_lost(
        &self,
        key: &BrickKey,
        file: &str,
        why: &str,
        plo: Dims3,
        phi: Dims3,
    ) -> Result<(), String> {
        let a = &self.meta.levels[key.level as usize];
        if a.fill.iter().any(|&b| b != 0) || (0..3).any(|i| plo[i] >= phi[i]) {
            return Ok(());
        }
        let ls = self.level_stats.borrow();
        let Some(st) = ls.get(key.level as usize).and_then(|s| s.clone()) else {
            return Ok(());
        };
        let sb = st.brick;
        let c = key.channel as u64;
        for z in plo[0] / sb[0]..=(phi[0] - 1) / sb[0] {
            for y in plo[1] / sb[1]..=(phi[1] - 1) / sb[1] {
                for x in plo[2] / sb[2]..=(phi[2] - 1) / sb[2] {
                    if let Some((mn, mx)) = st.get(c, [z, y, x]) {
                        if mn != 0.0 || mx != 0.0 {
                            return Err(format!(
                                "{file}: {why}, but the statistics say store brick (z {z}, y {y}, \
                                 x {x}) of channel {c} holds values in [{mn}, {mx}]"
                            ));
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// Load one padded brick.
    pub async fn load(&self, key: BrickKey) -> Result<LoadedBrick, String> {
        let g = &self.geometry;
        if !g.contains(&key) {
            return Err(format!("{} is outside the volume", brick_name(&key)));
        }
        if self.changed.get() {
            return Err(STORE_CHANGED.into());
        }
        if self.unreachable.get() {
            return Err(NOT_ASKED.into());
        }
        let l = key.level as usize;
        let a = &self.meta.levels[l];
        let reg = PaddedRegion::of(g, &key);
        let mut data = brick_buffer(g);
        let buf = Arc::get_mut(&mut data).expect("new buffer");
        let p = g.padded();
        let es = g.dtype.size();
        let nd = a.shape.len();
        // The region on every array axis.
        let mut lo = vec![0u64; nd];
        let mut hi = vec![1u64; nd];
        for (s, ax) in self.meta.space.iter().enumerate() {
            if let Some(ax) = *ax {
                lo[ax] = reg.lo[s];
                hi[ax] = reg.hi[s];
            }
        }
        if let Some(c) = self.meta.channel_axis {
            lo[c] = key.channel as u64;
            hi[c] = key.channel as u64 + 1;
        }
        // Unit grid: shards or chunks, and inside shards inner chunks.
        let (unit, inner_shape) = match a.sharding() {
            Some((ishape, ..)) => (a.chunk.clone(), Some(ishape.to_vec())),
            None => (a.chunk.clone(), None),
        };
        let piece = inner_shape.clone().unwrap_or_else(|| unit.clone());
        // Every piece (inner chunk or chunk) the region touches, by its
        // array-wide piece index.
        let first: Vec<u64> = (0..nd).map(|d| lo[d] / piece[d]).collect();
        let last: Vec<u64> = (0..nd).map(|d| (hi[d] - 1) / piece[d]).collect();
        let mut pi = first.clone();
        loop {
            let porig: Vec<u64> = (0..nd).map(|d| pi[d] * piece[d]).collect();
            let (outer, inner) = match &inner_shape {
                Some(is) => {
                    let outer: Vec<u64> = (0..nd).map(|d| porig[d] / unit[d]).collect();
                    let per: Vec<u64> = (0..nd).map(|d| unit[d].div_ceil(is[d])).collect();
                    let mut i = 0u64;
                    for d in 0..nd {
                        i = i * per[d] + (porig[d] - outer[d] * unit[d]) / is[d];
                    }
                    (outer, Some(i as usize))
                }
                None => (pi.clone(), None),
            };
            let chunk = match self.chunk(l, &outer, inner).await? {
                Ok(c) => Some(c),
                Err(why) => {
                    // The piece's part of the region, in the level's voxels.
                    let mut plo = [0u64; 3];
                    let mut phi = [1u64; 3];
                    for (s, ax) in self.meta.space.iter().enumerate() {
                        if let Some(ax) = *ax {
                            plo[s] = lo[ax].max(porig[ax]);
                            phi[s] = hi[ax].min(porig[ax] + piece[ax]);
                        }
                    }
                    if let Err(e) = self.check_lost(&key, &a.chunk_key(&outer), why, plo, phi) {
                        // Lost: what is kept of the shard (its index, or its
                        // absence) is forgotten, so that a retry reads it
                        // again once it is back.
                        self.indexes.borrow_mut().remove(&(l, outer.clone()));
                        return Err(e);
                    }
                    None
                }
            };
            copy_piece(
                buf,
                p,
                &reg,
                &self.meta.space,
                &lo,
                &hi,
                &porig,
                &piece,
                chunk.as_deref().map(|v| &v[..]),
                &a.fill,
                es,
            );
            // Next piece index (odometer, last axis fastest).
            let mut d = nd;
            loop {
                if d == 0 {
                    return Ok(finish_brick(g, key, data, &reg));
                }
                d -= 1;
                if pi[d] < last[d] {
                    pi[d] += 1;
                    break;
                }
                pi[d] = first[d];
            }
        }
    }
}

/// Copy the part of one decoded piece (`porig`, `shape`, C order; `None`:
/// the fill value) inside the region `lo..hi` into the padded brick
/// buffer (`p` voxels, `[z, y, x]`).
#[allow(clippy::too_many_arguments)]
fn copy_piece(
    buf: &mut [u8],
    p: Dims3,
    reg: &PaddedRegion,
    space: &[Option<usize>; 3],
    lo: &[u64],
    hi: &[u64],
    porig: &[u64],
    shape: &[u64],
    data: Option<&[u8]>,
    fill: &[u8],
    es: usize,
) {
    let nd = shape.len();
    let s: Vec<u64> = (0..nd).map(|d| lo[d].max(porig[d])).collect();
    let e: Vec<u64> = (0..nd).map(|d| hi[d].min(porig[d] + shape[d])).collect();
    if (0..nd).any(|d| s[d] >= e[d]) {
        return;
    }
    // Strides of the piece (C order) and of the brick per array axis.
    let mut pstride = vec![0usize; nd];
    let mut acc = 1usize;
    for d in (0..nd).rev() {
        pstride[d] = acc;
        acc *= shape[d] as usize;
    }
    let bstride_zyx = [(p[1] * p[2]) as usize, p[2] as usize, 1usize];
    let mut bstride = vec![0usize; nd];
    let mut boff = vec![0i64; nd];
    for (k, ax) in space.iter().enumerate() {
        if let Some(ax) = *ax {
            bstride[ax] = bstride_zyx[k];
            boff[ax] = reg.at[k] as i64 - reg.lo[k] as i64;
        }
    }
    let last = nd - 1;
    let run = (e[last] - s[last]) as usize;
    let contiguous = bstride[last] == 1;
    let mut i = s.clone();
    loop {
        let mut src = 0usize;
        let mut dst = 0usize;
        for d in 0..nd {
            src += (i[d] - porig[d]) as usize * pstride[d];
            dst += (i[d] as i64 + boff[d]) as usize * bstride[d];
        }
        if contiguous {
            let out = &mut buf[dst * es..(dst + run) * es];
            match data {
                Some(v) => out.copy_from_slice(&v[src * es..(src + run) * es]),
                None => {
                    for o in out.chunks_exact_mut(es) {
                        o.copy_from_slice(fill);
                    }
                }
            }
        } else {
            for k in 0..run {
                let o = (dst + k * bstride[last]) * es;
                match data {
                    Some(v) => {
                        buf[o..o + es].copy_from_slice(&v[(src + k) * es..(src + k + 1) * es])
                    }
                    None => buf[o..o + es].copy_from_slice(fill),
                }
            }
        }
        // Next row.
        let mut d = last;
        loop {
            if d == 0 {
                return;
            }
            d -= 1;
            i[d] += 1;
            if i[d] < e[d] {
                break;
            }
            i[d] = s[d];
        }
    }
}

/// Reads a store's objects from a directory (tests and native tools).
pub struct FileFetch(pub std::path::PathBuf);

impl Fetch for FileFetch {
    fn get(&self, path: &str, range: Range) -> LocalFuture<Result<Option<Vec<u8>>, String>> {
        let p = self.0.join(path);
        let r = (|| {
            let b = match std::fs::read(&p) {
                Ok(b) => b,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
                Err(e) => return Err(e.to_string()),
            };
            let n = b.len() as u64;
            Ok(Some(match range {
                Range::All => b,
                Range::Span { start, len } => {
                    if start + len > n {
                        return Err(format!("range {start}+{len} past the end ({n} bytes)"));
                    }
                    b[start as usize..(start + len) as usize].to_vec()
                }
                Range::Suffix(len) => b[n.saturating_sub(len) as usize..].to_vec(),
            }))
        })();
        Box::pin(async move { r })
    }
}
