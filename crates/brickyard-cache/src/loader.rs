//! The loader: a pool of I/O threads that turn brick requests into
//! [`LoadedBrick`]s.
//!
//! Over 800 lines: threads, queue, chunk cache and statistics share one locked state.
//!
//! The pool is made of plain OS threads, not the rayon pool: a thread
//! blocked in a read must never hold back compute.
//!
//! Requests are deduplicated (a brick that is cached, queued or being read
//! is not queued again), served highest priority first (ties: coarser level
//! first, then in request order) and can be withdrawn while they wait
//! ([`Loader::cancel_except`]). Finished bricks go into the [`HostCache`]
//! and are handed out by [`Loader::poll`].
//!
//! Loading a brick:
//! 1. If the store has per-brick statistics (`_brickyard/stats/<level>`) and
//!    every store brick that the *padded* region (brick + apron, clamped to
//!    the level) touches is constant with one common value, the brick is
//!    [`BrickContent::Empty`] (value 0) or [`BrickContent::Constant`],
//!    without reading any voxel.
//! 2. Otherwise the padded region clamped to the level is read (one
//!    `read_region`, whatever the store's chunking), and the parts of the
//!    apron outside the level are filled by replicating the border voxel.
//!    A trilinear sample inside the padded brick therefore equals a
//!    clamp-to-edge trilinear sample of the whole level. If the padded
//!    brick turns out uniform (stores without statistics, or statistics
//!    too coarse to tell), it is returned as empty/constant all the same.
//!
//! A failed load (unreadable store, corrupt chunk, even a panic in a codec)
//! never takes a worker down: it is reported by [`Loader::take_failures`]
//! and the key is not loaded again until [`Loader::retry_failed`].

use crate::assemble::{brick_buffer, finish_brick, uniform_brick, PaddedRegion};
use crate::brick::{BrickContent, BrickGeometry, BrickKey, LoadedBrick};
use crate::host_cache::HostCache;
use crate::ranges::BrickRanges;
use brickyard_core::{dispatch_dtype, Dims3, Sample};
use brickyard_store::brick_stats::LevelStats;
use brickyard_store::brick_stats::ReadBox;
use brickyard_store::error::{Result, StoreError};
use brickyard_store::import::zarr::{open, SharedChunkCache};
use brickyard_store::omezarr::{read_multiscale, STATS_DIR};
use brickyard_store::source::VolumeSource;
use std::cmp::Reverse;
use std::collections::{BTreeSet, HashMap, HashSet};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// A brick that could not be loaded.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadFailure {
    pub key: BrickKey,
    pub message: String,
    /// The store could not be read (a file or a server: an I/O error),
    /// as opposed to what it holds being wrong.
    pub io: bool,
}

impl LoadFailure {
    /// The level's voxels the failed brick covers, `[z, y, x]` from and
    /// to (by which the store's chunk is found: the engine's bricks need
    /// not be the store's).
    pub fn voxels(&self, g: &BrickGeometry) -> [Dims3; 2] {
        let lo = g.origin_of(&self.key);
        let ext = g.extent_of(&self.key);
        [lo, [0, 1, 2].map(|a| lo[a] + ext[a])]
    }

    /// Where the failure is, in the engine's bricks and in the level's
    /// voxels: "level 0 channel 0 brick [12, 7, 14] (voxels z 384..416,
    /// y 224..256, x 448..480)".
    pub fn place(&self, g: &BrickGeometry) -> String {
        let k = &self.key;
        let [lo, hi] = self.voxels(g);
        format!(
            "level {} channel {} brick {:?} (voxels z {}..{}, y {}..{}, x {}..{})",
            k.level, k.channel, k.brick, lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]
        )
    }
}

/// A snapshot of the loader's counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LoaderStats {
    /// Bytes of voxel data read from the store.
    pub bytes_read: u64,
    /// Bricks produced by the workers (data, empty and constant).
    pub bricks_loaded: u64,
    /// Of those, bricks returned empty / constant.
    pub bricks_empty: u64,
    pub bricks_constant: u64,
    /// Requests answered from the host cache without a load.
    pub bricks_from_cache: u64,
    /// Loads that failed.
    pub bricks_failed: u64,
    /// Byte ranges of the store the loader asked the system to read ahead
    /// (the chunks of the bricks queued next; see `VolumeSource::prefetch`).
    pub ranges_hinted: u64,
    /// Requests waiting for a worker.
    pub pending: usize,
    /// Bricks being read now.
    pub in_flight: usize,
}

/// Half the decoded-chunk cache of the loader by default ([`Loader::open`]
/// keeps twice this, shared by all levels, in one least-recently-used
/// order). [`Loader::open_with_chunk_cache`] sets the total.
pub const CHUNK_CACHE_BYTES: u64 = 64 << 20;

struct Level {
    /// The level's voxels: a store's array, or a procedural volume.
    src: Arc<dyn VolumeSource>,
    stats: Option<LevelStats>,
}

/// Turns level `l`'s stored array into the source a derived loader reads
/// (see [`Loader::open_derived`]); an error names what cannot be derived.
pub type Derive<'a> =
    &'a dyn Fn(usize, Arc<dyn VolumeSource>) -> std::result::Result<Arc<dyn VolumeSource>, String>;

/// Order of the request queue: the first element is served first.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct QueueEntry {
    priority: Reverse<u32>,
    /// Coarser (higher) level first.
    level: Reverse<u8>,
    seq: u64,
    key: BrickKey,
}

#[derive(Default)]
struct State {
    queue: BTreeSet<QueueEntry>,
    queued: HashMap<BrickKey, QueueEntry>,
    in_flight: HashSet<BrickKey>,
    done: Vec<Arc<LoadedBrick>>,
    done_keys: HashSet<BrickKey>,
    failures: Vec<LoadFailure>,
    failed_keys: HashSet<BrickKey>,
    /// Bricks whose store bytes were hinted to the system ahead of their
    /// load ([`Shared::ahead`]), until claimed.
    hinted: HashSet<BrickKey>,
    seq: u64,
    paused: bool,
    shutdown: bool,
}

#[derive(Default)]
struct Counters {
    bytes_read: AtomicU64,
    loaded: AtomicU64,
    empty: AtomicU64,
    constant: AtomicU64,
    from_cache: AtomicU64,
    failed: AtomicU64,
    hinted: AtomicU64,
}

struct Shared {
    path: PathBuf,
    /// The local store as opened: loads after it was replaced fail
    /// instead of reading the new files through the old store's cached
    /// shard indexes and statistics.
    identity: Option<brickyard_store::storage::StoreIdentity>,
    geometry: BrickGeometry,
    store_brick: Option<Dims3>,
    levels: Vec<Level>,
    cache: Arc<HostCache>,
    state: Mutex<State>,
    /// Signalled when work arrives (or on pause changes / shutdown).
    work: Condvar,
    /// Signalled when a load finishes.
    finished: Condvar,
    counters: Counters,
    /// Artificial delay of every load that reads the store, in
    /// nanoseconds ([`Loader::set_read_delay`]).
    read_delay_ns: AtomicU64,
    /// Worker threads.
    workers: usize,
    /// How many queued bricks to hint ahead ([`Loader::set_read_ahead`]).
    read_ahead: AtomicUsize,
}

/// A read that met damage in the store (a chunk that does not decode, a
/// truncated shard, values the statistics contradict, data lost): worth a
/// read of fewer chunks. Of a remote store, only what the statistics
/// contradict: its reader's errors include a server that did not answer,
/// which the same read of fewer chunks would wait for again.
fn damaged(e: &StoreError, remote: bool) -> bool {
    match e {
        StoreError::Invalid { .. } => true,
        StoreError::Zarr { .. } => !remote,
        // A shard file gone where the statistics say there is data
        // (`LevelStats::check_lost`), of a local store.
        StoreError::Io { error, .. } => !remote && error.kind() == std::io::ErrorKind::NotFound,
        _ => false,
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Loads run outside the locks and panics inside them are caught, so a
    // poisoned lock still guards consistent data.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Shared {
    /// Load one brick (called by the workers, or directly). A load that
    /// met a chunk that was absent from what the reader kept (a shard
    /// index read while the file was missing, by a read-ahead hint) but is
    /// in the file now is done again: the reader forgot what it kept of
    /// that file. A brick with its apron reads up to 8 shards, each of
    /// which may be told so in turn.
    fn load(&self, key: &BrickKey) -> Result<LoadedBrick> {
        let mut tries = 0;
        loop {
            match self.load_once(key) {
                Err(StoreError::Changed { .. }) if tries < 8 => tries += 1,
                r => return r,
            }
        }
    }

    fn load_once(&self, key: &BrickKey) -> Result<LoadedBrick> {
        let g = &self.geometry;
        if !g.contains(key) {
            return Err(StoreError::invalid(
                &self.path,
                "brick key",
                format!("{key:?} is outside the volume"),
            ));
        }
        if let Some(id) = &self.identity {
            id.check()
                .map_err(|m| StoreError::io(&self.path, std::io::Error::other(m)))?;
        }
        let level = &self.levels[key.level as usize];
        let c = key.channel as u64;
        let reg = PaddedRegion::of(g, key);
        let (lo, hi) = (reg.lo, reg.hi);
        if let Some(v) = level.stats.as_ref().and_then(|s| s.uniform(c, lo, hi)) {
            return Ok(uniform_brick(*key, v, 0));
        }
        let remote = brickyard_store::storage::is_remote(&self.path);
        match self.uniform_by_apron(level, key, &reg) {
            Ok(Some(b)) => {
                self.simulated_delay();
                return Ok(b);
            }
            Ok(None) => {}
            // (Damage in the apron's slabs: the read below meets it too,
            // and falls back to the brick proper.)
            Err(e) if !damaged(&e, remote) => return Err(e),
            Err(_) => {}
        }
        match self.read_brick(key, level, &reg) {
            // A damaged chunk that only the apron reaches into (a
            // neighbour's): the brick proper is read, its apron repeats its
            // edge. Its neighbours were all drawn coarser, 58 bricks for
            // one damaged chunk of 64³ (bricks of 32³); now the damaged
            // chunk's own bricks are, and say so.
            Err(e) if damaged(&e, remote) && g.apron > 0 => {
                let o = g.origin_of(key);
                let ext = g.extent_of(key);
                let proper = PaddedRegion {
                    lo: o,
                    hi: [0, 1, 2].map(|a| o[a] + ext[a]),
                    at: [g.apron; 3],
                };
                if proper == reg {
                    return Err(e);
                }
                self.read_brick(key, level, &proper)
            }
            r => r,
        }
    }

    /// Read the region `reg` of `key`'s level into a new brick (the apron
    /// outside it repeats its edge), checked against the brick statistics.
    fn read_brick(&self, key: &BrickKey, level: &Level, reg: &PaddedRegion) -> Result<LoadedBrick> {
        let g = &self.geometry;
        let c = key.channel as u64;
        let (lo, hi) = (reg.lo, reg.hi);
        // The brick's final buffer: the level's voxels are read straight
        // into it, then the apron outside the level repeats the edge.
        let mut data = brick_buffer(g);
        let buf = Arc::get_mut(&mut data).expect("a new buffer is not shared");
        brickyard_store::import::zarr::take_fill_read();
        let read = level.src.read_region_into(
            key.channel as usize,
            [lo[0]..hi[0], lo[1]..hi[1], lo[2]..hi[2]],
            buf,
            g.padded(),
            reg.at,
        );
        self.simulated_delay();
        read?;
        // (Only a read that met a chunk read as the fill value can have
        // lost one: the others skip the look at their voxels.)
        if let Some(st) = level
            .stats
            .as_ref()
            .filter(|_| brickyard_store::import::zarr::take_fill_read())
        {
            // Zeros where the statistics say there is data: the store lost
            // it (a shard file removed, a chunk dropped from its index),
            // which a Zarr reader cannot tell from the fill value. Asked of
            // every store brick the read touched, not only of bricks that
            // came out empty: a lost chunk beside chunks that were read
            // leaves a brick that is partly zeros.
            let r = ReadBox {
                lo,
                hi,
                buf,
                dims: g.padded(),
                at: reg.at,
                es: g.dtype.size() as u64,
            };
            st.check_lost_read(&*level.src, c, &r)?;
        }
        let brick = finish_brick(g, *key, data, reg);
        if let Some(st) = &level.stats {
            // A chunk whose bytes changed decodes to values the statistics
            // exclude: a failure (drawn coarser, reported), not a brick of
            // wrong values. The brick proper's range against the range of
            // the store bricks it lies in costs nothing; only a brick
            // outside it is looked at store brick by store brick.
            let o = g.origin_of(key);
            let ext = g.extent_of(key);
            let e = [0, 1, 2].map(|a| o[a] + ext[a]);
            if let Some((lo_s, hi_s)) = st.range_over(c, o, e) {
                if brick.min < lo_s || brick.max > hi_s {
                    if let BrickContent::Data(d) = &brick.content {
                        let at = [0, 1, 2].map(|a| reg.at[a] + o[a] - lo[a]);
                        let r = ReadBox {
                            lo: o,
                            hi: e,
                            buf: d,
                            dims: g.padded(),
                            at,
                            es: g.dtype.size() as u64,
                        };
                        st.check_range_read(&*level.src, c, &r, g.dtype)?;
                    }
                    return Err(StoreError::invalid(
                        level
                            .src
                            .chunk_file(c as usize, o)
                            .unwrap_or(self.path.clone()),
                        format!("channel {c} brick at {o:?}"),
                        format!(
                            "values span {}..{}, but the statistics say {lo_s}..{hi_s}: a chunk's \
                             bytes changed since it was written",
                            brick.min, brick.max
                        ),
                    ));
                }
            }
        }
        Ok(brick)
    }

    /// A brick whose brick proper the statistics say is uniform, while its
    /// padded region touches store bricks with other values (data next
    /// door): it is uniform exactly when the apron's voxels inside the
    /// level all have the bits of the brick proper's. Only those voxels
    /// (and one of the brick proper) are read, not the padded brick:
    /// `Some(brick)` when uniform, `None` when the whole brick must be
    /// read (or the statistics cannot tell).
    fn uniform_by_apron(
        &self,
        level: &Level,
        key: &BrickKey,
        reg: &PaddedRegion,
    ) -> Result<Option<LoadedBrick>> {
        let g = &self.geometry;
        let Some(st) = &level.stats else {
            return Ok(None);
        };
        let c = key.channel as usize;
        let o = g.origin_of(key);
        let ext = g.extent_of(key);
        let e: Dims3 = [0, 1, 2].map(|a| o[a] + ext[a]);
        let Some(want) = st.uniform(c as u64, o, e).filter(|_| g.apron > 0) else {
            return Ok(None);
        };
        let es = g.dtype.size();
        let mut first = vec![0u8; es];
        level.src.read_region(
            c,
            o[0]..o[0] + 1,
            o[1]..o[1] + 1,
            o[2]..o[2] + 1,
            &mut first,
        )?;
        let v = dispatch_dtype!(g.dtype, T => {
            <T as Sample>::from_le(&first).to_f64()
        });
        if v.is_nan() || v != want {
            // Not the statistics' value: the store lost the brick (a
            // removed shard reads as the fill value) or they are stale;
            // the full read tells which, and reports a loss.
            return Ok(None);
        }
        let mut read = es as u64;
        let mut buf = vec![];
        for a in 0..3 {
            for (s, t) in [(reg.lo[a], o[a]), (e[a], reg.hi[a])] {
                if s >= t {
                    continue;
                }
                // Whole padded rows on the axes after `a`; the axes before
                // it had their apron slabs read already.
                let r: [std::ops::Range<u64>; 3] = [0, 1, 2].map(|b| match b.cmp(&a) {
                    std::cmp::Ordering::Less => o[b]..e[b],
                    std::cmp::Ordering::Equal => s..t,
                    std::cmp::Ordering::Greater => reg.lo[b]..reg.hi[b],
                });
                let n = r.iter().map(|r| r.end - r.start).product::<u64>() as usize * es;
                buf.clear();
                buf.resize(n, 0);
                let [rz, ry, rx] = r;
                level.src.read_region(c, rz, ry, rx, &mut buf)?;
                read += n as u64;
                // Every voxel equals the next and the first equals `first`.
                if buf[..es] != first[..] || buf[es..] != buf[..n - es] {
                    return Ok(None);
                }
            }
        }
        Ok(Some(uniform_brick(*key, v, read)))
    }

    /// Sleep for the delay set by [`Loader::set_read_delay`], if any.
    fn simulated_delay(&self) {
        let ns = self.read_delay_ns.load(Ordering::Relaxed);
        if ns > 0 {
            std::thread::sleep(Duration::from_nanos(ns));
        }
    }

    /// Take the next bricks to load: the first of the queue and, with
    /// several threads and enough work queued for each, the bricks after it
    /// along x with the same priority (at most [`RUN_MAX`] in all). A thread
    /// that builds neighbours along x one after the other finds the chunk
    /// rows of each one's apron column in its own caches, where the
    /// neighbour's body was just copied from; threads taking turns along a
    /// row each fetched them from memory. One thread serves in the queue's
    /// order.
    fn claim(&self, st: &mut State) -> Vec<QueueEntry> {
        let Some(e) = st.queue.pop_first() else {
            return vec![];
        };
        st.queued.remove(&e.key);
        st.in_flight.insert(e.key);
        let mut run = vec![e];
        let room = if self.workers > 1 {
            (st.queue.len() / self.workers).min(RUN_MAX - 1)
        } else {
            0
        };
        let mut k = e.key;
        while run.len() <= room {
            k.brick[2] += 1;
            match st.queued.get(&k) {
                Some(n) if n.priority == e.priority => {
                    let n = *n;
                    st.queue.remove(&n);
                    st.queued.remove(&k);
                    st.in_flight.insert(k);
                    run.push(n);
                }
                _ => break,
            }
        }
        run
    }

    /// The bricks to hint to the store now: those of `run` (just claimed)
    /// and the first [`READ_AHEAD`] (or as set) of the queue, leaving out those hinted
    /// before. Hints keep the disk reading the next bricks while this
    /// thread decodes; without them a thread reads, then decodes, and the
    /// disk waits in between.
    fn ahead(&self, st: &mut State, run: &[QueueEntry]) -> Vec<BrickKey> {
        let n = self.read_ahead.load(Ordering::Relaxed);
        let mut keys: Vec<BrickKey> = run
            .iter()
            .filter(|e| !st.hinted.remove(&e.key) && n > 0)
            .map(|e| e.key)
            .collect();
        let State { queue, hinted, .. } = st;
        for e in queue.iter().take(n) {
            if hinted.insert(e.key) {
                keys.push(e.key);
            }
        }
        if st.hinted.len() > 4 * n {
            // Hinted bricks cancelled before their load.
            let State { queued, hinted, .. } = st;
            hinted.retain(|k| queued.contains_key(k));
        }
        keys
    }

    /// Ask the store to start reading what loading `key` will read, unless
    /// the statistics answer the brick without a read of its body.
    fn hint(&self, key: &BrickKey) {
        let g = &self.geometry;
        if !g.contains(key) {
            return;
        }
        let level = &self.levels[key.level as usize];
        let o = g.origin_of(key);
        let ext = g.extent_of(key);
        let e: Dims3 = [0, 1, 2].map(|a| o[a] + ext[a]);
        if let Some(st) = &level.stats {
            if st.uniform(key.channel as u64, o, e).is_some() {
                return;
            }
        }
        let reg = PaddedRegion::of(g, key);
        let (lo, hi) = (reg.lo, reg.hi);
        let n = level.src.prefetch(
            key.channel as usize,
            [lo[0]..hi[0], lo[1]..hi[1], lo[2]..hi[2]],
        );
        self.counters.hinted.fetch_add(n as u64, Ordering::Relaxed);
    }

    fn worker(&self) {
        loop {
            let (run, ahead) = {
                let mut st = lock(&self.state);
                loop {
                    if st.shutdown {
                        return;
                    }
                    if !st.paused {
                        let run = self.claim(&mut st);
                        if !run.is_empty() {
                            let ahead = self.ahead(&mut st, &run);
                            break (run, ahead);
                        }
                    }
                    st = self.work.wait(st).unwrap_or_else(|e| e.into_inner());
                }
            };
            for k in &ahead {
                // A hint must not take the loader down: a panic in it is
                // the load's to report.
                let _ = catch_unwind(AssertUnwindSafe(|| self.hint(k)));
            }
            let mut rest = run.into_iter();
            while let Some(e) = rest.next() {
                self.load_one(e.key);
                if let Some(f) = RELIEF.get() {
                    f();
                }
                if rest.len() == 0 {
                    break;
                }
                // Paused or shutting down: the rest of the run goes back to
                // the queue, as if never taken.
                let mut st = lock(&self.state);
                if st.paused || st.shutdown {
                    for e in rest {
                        st.in_flight.remove(&e.key);
                        st.queue.insert(e);
                        st.queued.insert(e.key, e);
                    }
                    break;
                }
            }
        }
    }

    /// Load a claimed brick and hand out the result.
    fn load_one(&self, key: BrickKey) {
        let result = catch_unwind(AssertUnwindSafe(|| self.load(&key)));
        let result = match result {
            Ok(Ok(b)) => Ok(Arc::new(b)),
            Ok(Err(e)) => Err((e.to_string(), matches!(e, StoreError::Io { .. }))),
            Err(panic) => Err((
                format!(
                    "panic while loading: {}",
                    panic
                        .downcast_ref::<String>()
                        .map(String::as_str)
                        .or_else(|| panic.downcast_ref::<&str>().copied())
                        .unwrap_or("(no message)")
                ),
                false,
            )),
        };
        let c = &self.counters;
        match &result {
            Ok(b) => {
                c.bytes_read.fetch_add(b.bytes_read, Ordering::Relaxed);
                c.loaded.fetch_add(1, Ordering::Relaxed);
                match b.content {
                    BrickContent::Empty => c.empty.fetch_add(1, Ordering::Relaxed),
                    BrickContent::Constant(_) => c.constant.fetch_add(1, Ordering::Relaxed),
                    BrickContent::Data(_) => 0,
                };
                self.cache.insert(b.clone());
            }
            Err(_) => {
                c.failed.fetch_add(1, Ordering::Relaxed);
            }
        }
        let mut st = lock(&self.state);
        st.in_flight.remove(&key);
        match result {
            Ok(b) => {
                if st.done_keys.insert(key) {
                    st.done.push(b);
                }
            }
            Err((message, io)) => {
                st.failed_keys.insert(key);
                st.failures.push(LoadFailure { key, message, io });
            }
        }
        drop(st);
        self.finished.notify_all();
    }
}

/// The most bricks one thread claims at a time ([`Shared::claim`]).
const RUN_MAX: usize = 4;

/// What the loader's threads call after each brick they load (see
/// [`set_relief`]).
static RELIEF: std::sync::OnceLock<fn()> = std::sync::OnceLock::new();

/// Have every loader's threads call `f` after each brick they load: the
/// program's way to keep the process within its memory budget while a
/// frame waits for its bricks (heaps grow within one frame of a batch
/// render, which waits for all of them). `f` keeps its own pace. Set once
/// per process; later calls are ignored.
pub fn set_relief(f: fn()) {
    let _ = RELIEF.set(f);
}

/// How far ahead of the loads the loader hints the store's bytes to the
/// system, in queued bricks ([`Shared::ahead`]): 32 bricks of 64³ u8 keep
/// 8 MiB of reads in flight, enough for a disk's queue and little next to
/// the host cache.
pub const READ_AHEAD: usize = 32;

/// The environment variable that sets [`READ_AHEAD`] for every loader of
/// the process (0 to 4096 bricks; 0 turns the hints off).
pub const READ_AHEAD_VAR: &str = "BRICKYARD_READ_AHEAD";

/// The read-ahead from [`READ_AHEAD_VAR`], or [`READ_AHEAD`] when it is
/// not set; a value that is not a number of bricks from 0 to 4096 is an
/// error saying what was expected.
fn read_ahead_from_env() -> std::result::Result<usize, String> {
    match std::env::var(READ_AHEAD_VAR) {
        Err(_) => Ok(READ_AHEAD),
        Ok(v) if v.trim().is_empty() => Ok(READ_AHEAD),
        Ok(v) => v
            .trim()
            .parse::<usize>()
            .ok()
            .filter(|&n| n <= 4096)
            .ok_or(format!(
                "expected a number of bricks from 0 to 4096 (0: no read-ahead hints), found {v:?}"
            )),
    }
}

/// Reads bricks of one store on a pool of I/O threads.
///
/// One loader per store and one store per [`HostCache`]: keys do not name
/// the store.
pub struct Loader {
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<()>>,
}

impl Loader {
    /// Open every level of the (OME-)Zarr store at `store_path` (a bare
    /// Zarr array is one level) and start `threads` workers (at least one).
    /// `brick` is the engine's brick size `[z, y, x]` (independent of the
    /// store's chunking), `apron` the border added on every side.
    /// Statistics are used when the store has them and they match the
    /// level (brickyard stores); foreign stores are read without.
    pub fn open(
        store_path: &Path,
        brick: Dims3,
        apron: u64,
        threads: usize,
        cache: Arc<HostCache>,
    ) -> Result<Loader> {
        Self::open_with_chunk_cache(
            store_path,
            brick,
            apron,
            threads,
            cache,
            2 * CHUNK_CACHE_BYTES,
        )
    }

    /// Like [`Loader::open`], with the decoded-chunk cache of all levels
    /// together bounded by `chunk_bytes` (at least half a MiB): one cache
    /// for all levels, so the level being read may use all of it.
    pub fn open_with_chunk_cache(
        store_path: &Path,
        brick: Dims3,
        apron: u64,
        threads: usize,
        cache: Arc<HostCache>,
        chunk_bytes: u64,
    ) -> Result<Loader> {
        Self::open_inner(store_path, brick, apron, threads, cache, chunk_bytes, None)
    }

    /// A loader over a volume derived from the store: `derive(l, level)`
    /// turns each level's array into the source its bricks are read from
    /// (a filter computed when a brick is asked for). Bricks then go
    /// through the same queue, priorities, host cache and failure reports
    /// as stored ones. The store's statistics describe the stored values,
    /// not the derived ones, so none are used: nothing is known to be empty
    /// before it is computed. Every level's derived source must have the
    /// same channels and voxel type.
    #[allow(clippy::too_many_arguments)]
    pub fn open_derived(
        store_path: &Path,
        brick: Dims3,
        apron: u64,
        threads: usize,
        cache: Arc<HostCache>,
        chunk_bytes: u64,
        derive: Derive<'_>,
    ) -> Result<Loader> {
        Self::open_inner(
            store_path,
            brick,
            apron,
            threads,
            cache,
            chunk_bytes,
            Some(derive),
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn open_inner(
        store_path: &Path,
        brick: Dims3,
        apron: u64,
        threads: usize,
        cache: Arc<HostCache>,
        chunk_bytes: u64,
        derive: Option<Derive<'_>>,
    ) -> Result<Loader> {
        if brick.contains(&0) {
            return Err(StoreError::invalid(
                store_path,
                "brick",
                format!("brick size {brick:?} must be at least 1 on every axis"),
            ));
        }
        // Taken before any metadata is read: a store replaced from here on
        // is refused by every load.
        let identity = brickyard_store::storage::StoreIdentity::of(store_path);
        let ms = read_multiscale(store_path)?;
        let nlevels = ms.as_ref().map(|m| m.datasets.len()).unwrap_or(1);
        let by = ms.as_ref().and_then(|m| m.brickyard.as_ref());
        let store_brick: Option<Dims3> = by
            .and_then(|b| b.get("brick"))
            .and_then(|v| v.as_array())
            .filter(|a| a.len() == 3)
            .and_then(|a| {
                let v: Vec<u64> = a.iter().filter_map(|x| x.as_u64()).collect();
                (v.len() == 3 && !v.contains(&0)).then(|| [v[0], v[1], v[2]])
            });
        let stats_dir = store_path.join(
            by.and_then(|b| b.get("stats"))
                .and_then(|v| v.as_str())
                .unwrap_or(STATS_DIR),
        );
        let mut levels = Vec::with_capacity(nlevels);
        let mut dims = Vec::with_capacity(nlevels);
        let mut chunks: Option<SharedChunkCache> = None;
        for l in 0..nlevels {
            let mut stored = open(store_path, l)?;
            // Neighbouring bricks share the chunks their aprons reach into:
            // keep decoded chunks so each is decoded about once. One
            // budget for all levels: the level being read uses the room
            // the others leave.
            let cc = chunks.get_or_insert_with(|| {
                SharedChunkCache::new(chunk_bytes.max(512 << 10), apron, stored.meta().dtype)
            });
            stored.share_chunk_cache(cc);
            let src: Arc<dyn VolumeSource> = match &derive {
                None => Arc::new(stored),
                Some(d) => d(l, Arc::new(stored))
                    .map_err(|e| StoreError::invalid(store_path, "derived channel", e))?,
            };
            let m = src.meta();
            if let Some(first) = levels.first() {
                let f: &Level = first;
                let fm = f.src.meta();
                if fm.dtype != m.dtype || fm.channels != m.channels {
                    return Err(StoreError::invalid(
                        store_path,
                        "levels",
                        format!(
                            "level {l} has {} channel(s) of {} but level 0 has {} of {}",
                            m.channels, m.dtype, fm.channels, fm.dtype
                        ),
                    ));
                }
            }
            // Levels from the finest down: none larger than the one before
            // on any axis (levels out of order, or a shape edited, would
            // draw the wrong data at every level of detail).
            if let Some(prev) = dims.last() {
                let p: &Dims3 = prev;
                if (0..3).any(|a| m.dims[a] > p[a]) {
                    return Err(StoreError::invalid(
                        store_path,
                        "multiscales.datasets",
                        format!(
                            "level {l} is {:?} voxels (z, y, x) but level {} is {p:?}: expected \
                             levels from the finest down, each no larger than the one before",
                            m.dims,
                            l - 1
                        ),
                    ));
                }
            }
            let stats = store_brick.filter(|_| derive.is_none()).and_then(|sb| {
                LevelStats::open(&stats_dir.join(l.to_string()), sb, m.dims, m.channels)
            });
            dims.push(m.dims);
            levels.push(Level { src, stats });
        }
        Self::start(
            store_path,
            identity,
            store_brick.filter(|_| derive.is_none()),
            levels,
            dims,
            brick,
            apron,
            threads,
            cache,
        )
    }

    /// A loader over a procedural volume of `dims` voxels (`[z, y, x]`)
    /// that exists nowhere: each level is the function sampled at that
    /// level's voxel centres (the levels of `plan_levels` for bricks of
    /// `brick`), each brick computed when it is asked for. No statistics,
    /// so nothing is known to be empty before it is loaded. For benchmarks
    /// of volumes larger than any disk at hand.
    pub fn procedural(
        kind: brickyard_store::generate::Kind,
        dims: Dims3,
        dtype: brickyard_core::DType,
        brick: Dims3,
        apron: u64,
        threads: usize,
        cache: Arc<HostCache>,
    ) -> Result<Loader> {
        let name = PathBuf::from(format!(
            "<{} {}x{}x{}>",
            kind.name(),
            dims[2],
            dims[1],
            dims[0]
        ));
        if brick.contains(&0) || dims.contains(&0) {
            return Err(StoreError::invalid(
                &name,
                "size",
                format!("volume {dims:?} and brick {brick:?} must be at least 1 on every axis"),
            ));
        }
        let plan = brickyard_core::plan_levels(dims, [1.0; 3], [0.0; 3], brick);
        let dims: Vec<Dims3> = plan.levels.iter().map(|l| l.dims).collect();
        let levels = dims
            .iter()
            .map(|d| Level {
                src: Arc::new(brickyard_store::generate::Procedural::new(kind, *d, dtype))
                    as Arc<dyn VolumeSource>,
                stats: None,
            })
            .collect();
        Self::start(
            &name, None, None, levels, dims, brick, apron, threads, cache,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn start(
        store_path: &Path,
        identity: Option<brickyard_store::storage::StoreIdentity>,
        store_brick: Option<Dims3>,
        levels: Vec<Level>,
        dims: Vec<Dims3>,
        brick: Dims3,
        apron: u64,
        threads: usize,
        cache: Arc<HostCache>,
    ) -> Result<Loader> {
        let m0 = levels[0].src.meta();
        let geometry = BrickGeometry {
            brick,
            apron,
            levels: dims,
            channels: m0.channels,
            dtype: m0.dtype,
        };
        let read_ahead = read_ahead_from_env()
            .map_err(|msg| StoreError::invalid(store_path, READ_AHEAD_VAR, msg))?;
        if !geometry.keys_fit() {
            return Err(StoreError::unsupported(
                store_path,
                "brick grid",
                format!(
                    "{} levels, {} channels, {:?} bricks at level 0: brick keys hold at most 32 levels, 2048 channels and 65536 bricks per axis",
                    geometry.levels.len(),
                    geometry.channels,
                    geometry.bricks_per_level(0)
                ),
            ));
        }
        let shared = Arc::new(Shared {
            path: store_path.to_path_buf(),
            identity,
            geometry,
            store_brick,
            levels,
            cache,
            state: Mutex::new(State::default()),
            work: Condvar::new(),
            finished: Condvar::new(),
            counters: Counters::default(),
            read_delay_ns: AtomicU64::new(0),
            read_ahead: AtomicUsize::new(read_ahead),
            workers: threads.max(1),
        });
        let mut handles = Vec::new();
        for i in 0..threads.max(1) {
            let s = shared.clone();
            let h = std::thread::Builder::new()
                .name(format!("brickyard-loader-{i}"))
                .spawn(move || s.worker())
                .map_err(|e| StoreError::io(store_path, e))?;
            handles.push(h);
        }
        Ok(Loader {
            shared,
            threads: handles,
        })
    }

    /// The engine's brick grid over the store.
    pub fn geometry(&self) -> &BrickGeometry {
        &self.shared.geometry
    }

    /// The store's brick (inner chunk) size, for brickyard stores.
    pub fn store_brick(&self) -> Option<Dims3> {
        self.shared.store_brick
    }

    /// Whether per-brick statistics are used for `level`.
    pub fn has_stats(&self, level: usize) -> bool {
        self.shared
            .levels
            .get(level)
            .is_some_and(|l| l.stats.is_some())
    }

    /// The host cache the loader fills.
    pub fn cache(&self) -> &Arc<HostCache> {
        &self.shared.cache
    }

    /// Ask for bricks, each with a priority (higher first).
    ///
    /// - A brick in the host cache is not loaded: it is handed out by the
    ///   next [`Loader::poll`] (and counted in `bricks_from_cache`).
    /// - A brick already queued takes the new priority; one being read is
    ///   left alone.
    /// - A brick whose load failed is skipped until [`Loader::retry_failed`].
    /// - A key outside the volume is reported as a failure.
    ///
    /// Ties in priority go to the coarser level, then to the earlier request;
    /// with several threads, each takes with its brick the next few of the
    /// same priority along x (see `Shared::claim`).
    pub fn request(&self, keys: &[(BrickKey, u32)]) {
        let mut st = lock(&self.shared.state);
        let mut added = false;
        for &(key, priority) in keys {
            if st.in_flight.contains(&key) || st.failed_keys.contains(&key) {
                continue;
            }
            if !self.shared.geometry.contains(&key) {
                st.failed_keys.insert(key);
                st.failures.push(LoadFailure {
                    key,
                    message: format!(
                        "{}: {key:?} is outside the volume",
                        self.shared.path.display()
                    ),
                    io: false,
                });
                self.shared.counters.failed.fetch_add(1, Ordering::Relaxed);
                continue;
            }
            if let Some(old) = st.queued.get(&key).copied() {
                if old.priority.0 == priority {
                    continue;
                }
                st.queue.remove(&old);
            } else if !st.done_keys.contains(&key) {
                if let Some(b) = self.shared.cache.get(&key) {
                    self.shared
                        .counters
                        .from_cache
                        .fetch_add(1, Ordering::Relaxed);
                    st.done_keys.insert(key);
                    st.done.push(b);
                    continue;
                }
            } else {
                // Finished and not yet polled.
                continue;
            }
            let e = QueueEntry {
                priority: Reverse(priority),
                level: Reverse(key.level),
                seq: st.seq,
                key,
            };
            st.seq += 1;
            st.queue.insert(e);
            st.queued.insert(key, e);
            added = true;
        }
        drop(st);
        if added {
            self.shared.work.notify_all();
        }
    }

    /// Drop every queued request whose key is not in `wanted` (bricks being
    /// read, and those a thread took with them, are not interrupted).
    /// Returns the number of requests dropped.
    pub fn cancel_except(&self, wanted: &[BrickKey]) -> usize {
        let wanted: HashSet<BrickKey> = wanted.iter().copied().collect();
        let mut st = lock(&self.shared.state);
        let before = st.queue.len();
        st.queue.retain(|e| wanted.contains(&e.key));
        st.queued.retain(|k, _| wanted.contains(k));
        let dropped = before - st.queue.len();
        drop(st);
        if dropped > 0 {
            self.shared.finished.notify_all();
        }
        dropped
    }

    /// Bricks finished (or answered from the cache) since the last poll, in
    /// the order they finished. They are in the host cache already (unless
    /// larger than its whole budget).
    pub fn poll(&self) -> Vec<Arc<LoadedBrick>> {
        let mut st = lock(&self.shared.state);
        st.done_keys.clear();
        std::mem::take(&mut st.done)
    }

    /// Failures since the last call.
    pub fn take_failures(&self) -> Vec<LoadFailure> {
        std::mem::take(&mut lock(&self.shared.state).failures)
    }

    /// Keys that failed and are not requested again.
    pub fn failed_keys(&self) -> Vec<BrickKey> {
        let mut v: Vec<BrickKey> = lock(&self.shared.state)
            .failed_keys
            .iter()
            .copied()
            .collect();
        v.sort();
        v
    }

    /// Allow failed keys to be requested again (e.g. after the store was
    /// repaired).
    pub fn retry_failed(&self) {
        lock(&self.shared.state).failed_keys.clear();
    }

    /// Value ranges of every padded brick (apron included), from the
    /// store's per-brick statistics, for empty-space skipping. Levels
    /// without statistics (foreign stores) or with more than `max_bricks`
    /// bricks × channels are left out; a level's entry is `[NaN, NaN]`
    /// where the statistics cannot be read.
    pub fn brick_ranges(&self, max_bricks: u64) -> BrickRanges {
        let sh = &self.shared;
        let Some(sb) = sh.store_brick else {
            return BrickRanges {
                levels: vec![None; sh.levels.len()],
            };
        };
        BrickRanges::build(
            &sh.geometry,
            sb,
            max_bricks,
            |l| sh.levels[l].stats.is_some(),
            |l, c, b| sh.levels[l].stats.as_ref()?.get(c as u64, b),
        )
    }

    /// Chunks of the brick statistics found unreadable since the last
    /// call (a damaged or truncated file), each once: the view does not
    /// change (their bricks are loaded instead of skipped), but the store
    /// is damaged and the user should hear of it.
    pub fn take_stats_problems(&self) -> Vec<String> {
        self.shared
            .levels
            .iter()
            .filter_map(|l| l.stats.as_ref())
            .flat_map(|s| s.take_problems())
            .collect()
    }

    /// Stop (`true`) or resume (`false`) starting new loads; loads in
    /// progress finish. Requests keep being queued while paused.
    pub fn set_paused(&self, paused: bool) {
        lock(&self.shared.state).paused = paused;
        self.shared.work.notify_all();
        self.shared.finished.notify_all();
    }

    /// Make every load that reads the store sleep `d` after its read, on
    /// the thread doing the load (a worker, or the caller of
    /// [`Loader::load_now`]): a testing and benchmarking aid to simulate a
    /// slow disk or network store. Bricks answered from the statistics
    /// (empty / constant without a read) or from the host cache are not
    /// delayed. `Duration::ZERO` (the default) turns it off; a change
    /// applies to loads whose read finishes afterwards.
    pub fn set_read_delay(&self, d: Duration) {
        let ns = u64::try_from(d.as_nanos()).unwrap_or(u64::MAX);
        self.shared.read_delay_ns.store(ns, Ordering::Relaxed);
    }

    /// Hint the store's bytes of the next `bricks` queued bricks to the
    /// system ahead of their loads ([`READ_AHEAD`] by default, or
    /// [`READ_AHEAD_VAR`] from the environment; 0 turns the hints off). On local stores the kernel then reads them while
    /// the workers decode; a slow or deep device (network file systems,
    /// disk arrays) gains from more.
    pub fn set_read_ahead(&self, bricks: usize) {
        self.shared.read_ahead.store(bricks, Ordering::Relaxed);
    }

    /// The delay set by [`Loader::set_read_delay`].
    pub fn read_delay(&self) -> Duration {
        Duration::from_nanos(self.shared.read_delay_ns.load(Ordering::Relaxed))
    }

    /// Requests waiting for a worker.
    pub fn pending(&self) -> usize {
        lock(&self.shared.state).queue.len()
    }

    /// Bricks being read now.
    pub fn in_flight(&self) -> usize {
        lock(&self.shared.state).in_flight.len()
    }

    /// Block until nothing is queued or being read, or `timeout` passes.
    /// Returns whether the loader is idle. (While paused with requests
    /// queued it is not idle.)
    pub fn wait_idle(&self, timeout: Duration) -> bool {
        let end = Instant::now() + timeout;
        let mut st = lock(&self.shared.state);
        loop {
            if st.queue.is_empty() && st.in_flight.is_empty() {
                return true;
            }
            let now = Instant::now();
            if now >= end {
                return false;
            }
            st = self
                .shared
                .finished
                .wait_timeout(st, end - now)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    /// Load one brick on the calling thread, bypassing queue and cache.
    pub fn load_now(&self, key: &BrickKey) -> Result<LoadedBrick> {
        self.shared.load(key)
    }

    /// Bytes of voxel data read from the store so far.
    pub fn bytes_read(&self) -> u64 {
        self.shared.counters.bytes_read.load(Ordering::Relaxed)
    }

    /// Bricks produced by the workers so far.
    pub fn bricks_loaded(&self) -> u64 {
        self.shared.counters.loaded.load(Ordering::Relaxed)
    }

    /// Requests answered from the host cache.
    pub fn bricks_from_cache(&self) -> u64 {
        self.shared.counters.from_cache.load(Ordering::Relaxed)
    }

    /// All counters at once.
    pub fn stats(&self) -> LoaderStats {
        let c = &self.shared.counters;
        let st = lock(&self.shared.state);
        LoaderStats {
            bytes_read: c.bytes_read.load(Ordering::Relaxed),
            bricks_loaded: c.loaded.load(Ordering::Relaxed),
            bricks_empty: c.empty.load(Ordering::Relaxed),
            bricks_constant: c.constant.load(Ordering::Relaxed),
            bricks_from_cache: c.from_cache.load(Ordering::Relaxed),
            bricks_failed: c.failed.load(Ordering::Relaxed),
            ranges_hinted: c.hinted.load(Ordering::Relaxed),
            pending: st.queue.len(),
            in_flight: st.in_flight.len(),
        }
    }
}

impl Drop for Loader {
    /// Queued requests are dropped; loads in progress finish first.
    fn drop(&mut self) {
        lock(&self.shared.state).shutdown = true;
        self.shared.work.notify_all();
        for h in self.threads.drain(..) {
            let _ = h.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::assemble::replicate_edges;

    #[test]
    fn procedural_bricks_are_the_function_at_each_level() {
        use brickyard_store::generate::{Kind, Procedural};
        let cache = Arc::new(HostCache::new(1 << 20));
        let dims = [40, 48, 64];
        let l = Loader::procedural(
            Kind::Mandelbulb,
            dims,
            brickyard_core::DType::U8,
            [16; 3],
            1,
            2,
            cache,
        )
        .unwrap();
        let g = l.geometry().clone();
        assert!(g.levels.len() >= 3 && g.levels[0] == dims);
        for key in [
            BrickKey::new(0, 0, [1, 1, 2]),
            BrickKey::new(1, 0, [0, 1, 1]),
        ] {
            let d = g.levels[key.level as usize];
            let want = Procedural::new(Kind::Mandelbulb, d, brickyard_core::DType::U8);
            let b = l.load_now(&key).unwrap();
            let BrickContent::Data(bytes) = &b.content else {
                panic!("{key:?}: expected data");
            };
            // Padded voxel (i, j, k) is level voxel origin − 1 + (i, j, k),
            // clamped to the level.
            let p = g.padded();
            let o = g.padded_origin_of(&key);
            for (i, j, k) in [(1, 1, 1), (5, 9, 3), (17, 17, 17), (0, 0, 0)] {
                let v = [o[0] + i, o[1] + j, o[2] + k]
                    .iter()
                    .zip(d)
                    .map(|(&c, n)| c.clamp(0, n as i64 - 1) as u64)
                    .collect::<Vec<_>>();
                let mut one = [0u8; 1];
                want.read_region(0, v[0]..v[0] + 1, v[1]..v[1] + 1, v[2]..v[2] + 1, &mut one)
                    .unwrap();
                let idx = ((i as u64 * p[1] + j as u64) * p[2] + k as u64) as usize;
                assert_eq!(bytes[idx], one[0], "{key:?} voxel {v:?}");
            }
        }
    }

    #[test]
    fn replicate_edges_clamps_to_the_box() {
        // A 2×3×4 box of u16 at (1, 0, 2) in a 4×4×7 padded brick.
        let (p, at, r) = ([4u64, 4, 7], [1u64, 0, 2], [2u64, 3, 4]);
        let mut buf = vec![0u16; 4 * 4 * 7];
        let val = |z: u64, y: u64, x: u64| (100 * z + 10 * y + x) as u16;
        for z in 0..r[0] {
            for y in 0..r[1] {
                for x in 0..r[2] {
                    buf[(((at[0] + z) * p[1] + at[1] + y) * p[2] + at[2] + x) as usize] =
                        val(z, y, x);
                }
            }
        }
        replicate_edges(brickyard_core::as_bytes_mut(&mut buf), p, at, r, 2);
        for z in 0..p[0] {
            for y in 0..p[1] {
                for x in 0..p[2] {
                    let c = |v: u64, a: usize| {
                        (v as i64 - at[a] as i64).clamp(0, r[a] as i64 - 1) as u64
                    };
                    assert_eq!(
                        buf[((z * p[1] + y) * p[2] + x) as usize],
                        val(c(z, 0), c(y, 1), c(x, 2)),
                        "padded voxel {z} {y} {x}"
                    );
                }
            }
        }
    }

    #[test]
    fn queue_order() {
        let e = |p, l, s| QueueEntry {
            priority: Reverse(p),
            level: Reverse(l),
            seq: s,
            key: BrickKey::new(l, 0, [0; 3]),
        };
        let mut q = BTreeSet::new();
        q.insert(e(1, 0, 0));
        q.insert(e(5, 0, 1));
        q.insert(e(5, 2, 2));
        q.insert(e(5, 2, 3));
        let order: Vec<(u32, u8, u64)> = q
            .into_iter()
            .map(|x| (x.priority.0, x.level.0, x.seq))
            .collect();
        assert_eq!(order, [(5, 2, 2), (5, 2, 3), (5, 0, 1), (1, 0, 0)]);
    }
}
