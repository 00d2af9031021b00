//! A streaming session: the virtual memory fed by the loader, frame by
//! frame. Consumers sample through [`Session::vm`]; [`Session::finish_frame`]
//! sends the capped request list to the loader (cancelling queued requests
//! that are no longer wanted) and writes whatever bricks have arrived into
//! the pool, within the per-frame upload budget. Nothing here waits for I/O.

use crate::brick::{BrickKey, LoadedBrick};
use crate::host_cache::HostCache;
use crate::loader::{LoadFailure, Loader};
use crate::vm::{FrameReport, InsertReport, Requests, VirtualMemory, VmConfig};
use std::collections::VecDeque;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

/// Figures of one frame.
#[derive(Debug, Clone, Default)]
pub struct FrameStats {
    pub frame: FrameReport,
    pub insert: InsertReport,
    /// Bricks delivered by the loader this frame (from disk or host cache).
    pub delivered: usize,
    /// Requests cancelled because the view no longer wants them.
    pub cancelled: usize,
    /// Loader queue and reads in flight after this frame.
    pub pending: usize,
    pub in_flight: usize,
    /// Bricks that arrived but wait for a later frame's upload budget.
    pub waiting_upload: usize,
    /// Loads that failed this frame (see [`Session::failures`]).
    pub failed: usize,
}

/// What [`Session::pin_coarsest`] made resident for good.
#[derive(Debug, Clone, Default)]
pub struct PinReport {
    /// Levels pinned (coarsest first).
    pub levels: Vec<usize>,
    /// Data bricks pinned in the pool.
    pub bricks: usize,
    /// Empty or constant bricks pinned (no pool slot).
    pub flagged: usize,
    /// Pool bytes the pinned bricks take.
    pub bytes: u64,
    /// Pinned bricks that could not be loaded.
    pub failed: usize,
}

pub use crate::brick::PoolTooSmall;

/// Virtual memory + loader + host cache for one store.
pub struct Session {
    vm: VirtualMemory,
    loader: Loader,
    waiting: VecDeque<Arc<LoadedBrick>>,
    /// Batch mode: after sending a frame's requests, wait up to this long
    /// for them to load before inserting (see [`Session::set_batch`]).
    batch: Option<Duration>,
    /// Every load failure so far, oldest first.
    failures: Vec<LoadFailure>,
}

impl Session {
    /// Open `store` (an OME-Zarr written by brickyard or any other tool)
    /// with the given virtual-memory configuration, a host cache of
    /// `host_bytes` and `threads` loader threads.
    pub fn open(
        store: &Path,
        cfg: VmConfig,
        host_bytes: u64,
        threads: usize,
    ) -> brickyard_store::Result<Session> {
        Self::with_cache(store, cfg, Arc::new(HostCache::new(host_bytes)), threads)
    }

    /// Like [`Session::open`], with the loader's decoded-chunk caches
    /// bounded by `chunk_bytes` (plus half a MiB per level).
    pub fn open_with_budget(
        store: &Path,
        cfg: VmConfig,
        host_bytes: u64,
        chunk_bytes: u64,
        threads: usize,
    ) -> brickyard_store::Result<Session> {
        let cache = Arc::new(HostCache::new(host_bytes));
        let loader = Loader::open_with_chunk_cache(
            store,
            cfg.brick,
            cfg.apron,
            threads,
            cache,
            chunk_bytes,
        )?;
        Ok(Self::from_loader(loader, cfg))
    }

    /// Like [`Session::open_with_budget`], over a volume derived from the
    /// store level by level (see [`Loader::open_derived`]).
    pub fn open_derived(
        store: &Path,
        cfg: VmConfig,
        host_bytes: u64,
        chunk_bytes: u64,
        threads: usize,
        derive: crate::loader::Derive<'_>,
    ) -> brickyard_store::Result<Session> {
        let cache = Arc::new(HostCache::new(host_bytes));
        let loader = Loader::open_derived(
            store,
            cfg.brick,
            cfg.apron,
            threads,
            cache,
            chunk_bytes,
            derive,
        )?;
        Ok(Self::from_loader(loader, cfg))
    }

    /// Like [`Session::open`] with an existing host cache (of the same store).
    pub fn with_cache(
        store: &Path,
        cfg: VmConfig,
        cache: Arc<HostCache>,
        threads: usize,
    ) -> brickyard_store::Result<Session> {
        let loader = Loader::open(store, cfg.brick, cfg.apron, threads, cache)?;
        let g = loader.geometry().clone();
        let vm = VirtualMemory::new(&g.levels, g.channels, g.dtype, cfg);
        Ok(Session {
            vm,
            loader,
            waiting: VecDeque::new(),
            batch: None,
            failures: vec![],
        })
    }

    /// A session over an open loader (e.g. [`Loader::procedural`]).
    pub fn from_loader(loader: Loader, cfg: VmConfig) -> Session {
        let g = loader.geometry().clone();
        let vm = VirtualMemory::new(&g.levels, g.channels, g.dtype, cfg);
        Session {
            vm,
            loader,
            waiting: VecDeque::new(),
            batch: None,
            failures: vec![],
        }
    }

    /// The virtual memory, mutable: for a device mirror to take its
    /// changes ([`VirtualMemory::take_changes`]).
    pub fn vm_mut(&mut self) -> &mut VirtualMemory {
        &mut self.vm
    }

    pub fn vm(&self) -> &VirtualMemory {
        &self.vm
    }
    pub fn loader(&self) -> &Loader {
        &self.loader
    }

    /// Batch mode (`Some(limit)`): a frame that sends requests waits, up
    /// to `limit`, for the loader to deliver them before inserting, so a
    /// render that nobody watches loads its working set at the loader's
    /// full rate instead of drawing a frame for each batch. `None`: never
    /// wait (interactive views).
    pub fn set_batch(&mut self, wait: Option<Duration>) {
        self.batch = wait;
    }

    /// Every load failure so far (key and message), oldest first.
    pub fn failures(&self) -> &[LoadFailure] {
        &self.failures
    }

    /// Let every brick that failed be asked for again (a server back, a
    /// file repaired): the virtual memory and the loader forget them. The
    /// failures stay in [`Session::failures`]; those of a new try are added.
    pub fn retry_failed(&mut self) {
        self.collect_failures();
        self.vm.clear_failed();
        self.loader.retry_failed();
    }

    /// Take the loader's new failures: the bricks are marked failed in the
    /// virtual memory (never requested again; drawn from coarser data).
    fn collect_failures(&mut self) -> usize {
        let new = self.loader.take_failures();
        for f in &new {
            self.vm.mark_failed(f.key);
        }
        let n = new.len();
        self.failures.extend(new);
        n
    }

    /// Make the coarsest levels of every channel resident for good, so that
    /// every sample finds data at some level whatever the pool's pressure:
    /// the coarsest level always, and finer ones (never level 0) while all
    /// pinned bricks stay within an eighth of the pool and `max_bricks`. Loads them now
    /// (waiting up to `timeout`). Fails when the pool can hold neither
    /// twice the coarsest level nor the whole volume.
    pub fn pin_coarsest(
        &mut self,
        max_bricks: usize,
        timeout: Duration,
    ) -> Result<PinReport, PoolTooSmall> {
        let g = self.loader.geometry().clone();
        let slots = self.vm.pool_slots();
        // (Of the configuration, not the pool's bytes over its slots: a
        // pool too small for one slot has neither.)
        let slot_bytes = self.vm.slot_bytes() as u64;
        let levels = g.pinned_levels(slots, slot_bytes, max_bricks)?;
        let mut keys: Vec<BrickKey> = vec![];
        for &l in &levels {
            for c in 0..g.channels {
                keys.extend(g.keys(l, c));
            }
        }
        let wanted: Vec<(BrickKey, u32)> = keys.iter().map(|k| (*k, u32::MAX)).collect();
        self.loader.request(&wanted);
        self.loader.wait_idle(timeout);
        let arrived: Vec<Arc<LoadedBrick>> = self.loader.poll();
        let failed = self.collect_failures();
        // The pool has room for all of them (checked above); write them in
        // upload-budget-sized portions.
        let mut rest = &arrived[..];
        while !rest.is_empty() {
            let r = self.vm.insert(rest);
            if r.processed == 0 {
                break;
            }
            rest = &rest[r.processed..];
        }
        let mut report = PinReport {
            levels,
            failed,
            ..Default::default()
        };
        for b in &arrived {
            if self.vm.pin(b.key) {
                match b.content {
                    crate::brick::BrickContent::Data(_) => report.bricks += 1,
                    _ => report.flagged += 1,
                }
            }
        }
        report.bytes = report.bricks as u64 * slot_bytes;
        Ok(report)
    }

    /// Start a frame.
    pub fn begin_frame(&mut self) {
        self.vm.begin_frame();
    }

    /// A frame's end when a device decides updates (the host's virtual
    /// memory stays empty): collect the bricks that arrived into
    /// [`waiting`](Self::waiting) (each key once), then send the device's
    /// request list (most wanted first; the device asks only for bricks it
    /// lacks) to the loader without the bricks already here, capped at the
    /// configuration's `request_cap`, cancelling queued requests no longer
    /// wanted. A device list longer than the cap lets the cap go to bricks
    /// not here yet (asked for again, bricks that had just arrived took the
    /// cap's places, and every other frame loaded nothing). Returns
    /// (delivered, cancelled, the list sent).
    pub fn exchange(&mut self, requests: &[BrickKey]) -> (usize, usize, Vec<BrickKey>) {
        let early = self.loader.poll();
        let mut delivered = early.len();
        self.take_arrivals(early);
        let here: std::collections::HashSet<BrickKey> =
            self.waiting.iter().map(|b| b.key).collect();
        let sent: Vec<BrickKey> = requests
            .iter()
            .filter(|k| !here.contains(k))
            .take(self.vm.config().request_cap)
            .copied()
            .collect();
        let n = sent.len() as u32;
        let wanted: Vec<(BrickKey, u32)> = sent
            .iter()
            .enumerate()
            .map(|(i, k)| (*k, n - i as u32))
            .collect();
        let cancelled = self.loader.cancel_except(&sent);
        self.loader.request(&wanted);
        if let Some(limit) = self.batch {
            self.loader.wait_idle(limit);
        }
        let arrived = self.loader.poll();
        delivered += arrived.len();
        self.take_arrivals(arrived);
        (delivered, cancelled, sent)
    }

    /// Bricks arrived for a device: into [`waiting`](Self::waiting), each
    /// key once, and no more than twice the request cap.
    fn take_arrivals(&mut self, arrived: Vec<Arc<LoadedBrick>>) {
        self.collect_failures();
        let have: std::collections::HashSet<BrickKey> =
            self.waiting.iter().map(|b| b.key).collect();
        self.waiting
            .extend(arrived.into_iter().filter(|b| !have.contains(&b.key)));
        // Do not hoard (see `finish_frame`).
        let keep = self.vm.config().request_cap * 2;
        while self.waiting.len() > keep {
            self.waiting.pop_back();
        }
    }

    /// Bricks that arrived and wait to be handed to a device, oldest first.
    pub fn waiting(&self) -> &VecDeque<Arc<LoadedBrick>> {
        &self.waiting
    }

    /// Drop the waiting bricks for which `done` is true (handed over).
    pub fn hand_over(&mut self, done: &[bool]) {
        let mut i = 0;
        self.waiting.retain(|_| {
            let keep = !done.get(i).copied().unwrap_or(false);
            i += 1;
            keep
        });
    }

    /// End a frame: requests out, arrived bricks in.
    pub fn finish_frame<'a>(
        &mut self,
        collectors: impl IntoIterator<Item = &'a Requests>,
    ) -> FrameStats {
        // Bricks that arrived while the frame was drawn are inserted below:
        // they are not asked for again, and the cap goes to the next most
        // wanted. (Asked for again, they took the cap's places: a streamed
        // view without waits then loaded nothing every other frame.)
        let early = self.loader.poll();
        let mut delivered = early.len();
        self.waiting.extend(early);
        let here: std::collections::HashSet<BrickKey> =
            self.waiting.iter().map(|b| b.key).collect();
        let frame = self.vm.end_frame_without(collectors, |k| here.contains(&k));
        let n = frame.requests.len() as u32;
        let wanted: Vec<(BrickKey, u32)> = frame
            .requests
            .iter()
            .enumerate()
            .filter(|(_, k)| !self.vm.is_resident(**k))
            .map(|(i, k)| (*k, n - i as u32))
            .collect();
        let keys: Vec<BrickKey> = wanted.iter().map(|w| w.0).collect();
        let cancelled = self.loader.cancel_except(&keys);
        self.loader.request(&wanted);
        if let Some(limit) = self.batch {
            if !wanted.is_empty() {
                self.loader.wait_idle(limit);
            }
        }
        let arrived = self.loader.poll();
        let failed = self.collect_failures();
        delivered += arrived.len();
        self.waiting.extend(arrived);
        let batch: Vec<Arc<LoadedBrick>> = self.waiting.iter().cloned().collect();
        let insert = self.vm.insert(&batch);
        self.waiting.drain(..insert.processed);
        // Do not hoard: bricks waiting for upload are also in the host cache
        // and will be asked for again if still wanted.
        let keep = self.vm.config().request_cap * 2;
        while self.waiting.len() > keep {
            self.waiting.pop_back();
        }
        FrameStats {
            frame,
            insert,
            delivered,
            cancelled,
            pending: self.loader.pending(),
            in_flight: self.loader.in_flight(),
            waiting_upload: self.waiting.len(),
            failed,
        }
    }
}
