//! A streaming session: the virtual memory fed by the loader, frame by
//! frame. Consumers sample through [`Session::vm`]; [`Session::finish_frame`]
//! sends the capped request list to the loader (cancelling queued requests
//! that are no longer wanted) and writes whatever bricks have arrived into
//! the pool, within the per-frame upload budget. Nothing here waits for I/O.

use crate::brick::{BrickKey, LoadedBrick};
use crate::host_cache::HostCache;
use crate::loader::Loader;
use crate::vm::{FrameReport, InsertReport, Requests, VirtualMemory, VmConfig};
use std::collections::VecDeque;
use std::path::Path;
use std::sync::Arc;

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
}

/// Virtual memory + loader + host cache for one store.
pub struct Session {
    vm: VirtualMemory,
    loader: Loader,
    waiting: VecDeque<Arc<LoadedBrick>>,
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

    /// Start a frame.
    pub fn begin_frame(&mut self) {
        self.vm.begin_frame();
    }

    /// For a device that decides its updates itself (the host's virtual
    /// memory stays empty): send the device's capped request list (most
    /// wanted first; the device asks only for bricks it lacks) to the
    /// loader, cancelling queued requests no longer wanted, and collect
    /// the bricks that arrived into [`waiting`](Self::waiting) (each key
    /// once). Returns (delivered, cancelled).
    pub fn exchange(&mut self, requests: &[BrickKey]) -> (usize, usize) {
        let n = requests.len() as u32;
        let wanted: Vec<(BrickKey, u32)> = requests
            .iter()
            .enumerate()
            .map(|(i, k)| (*k, n - i as u32))
            .collect();
        let cancelled = self.loader.cancel_except(requests);
        self.loader.request(&wanted);
        let arrived = self.loader.poll();
        let delivered = arrived.len();
        let have: std::collections::HashSet<BrickKey> =
            self.waiting.iter().map(|b| b.key).collect();
        self.waiting
            .extend(arrived.into_iter().filter(|b| !have.contains(&b.key)));
        // Do not hoard (see `finish_frame`).
        let keep = self.vm.config().request_cap * 2;
        while self.waiting.len() > keep {
            self.waiting.pop_back();
        }
        (delivered, cancelled)
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
        let frame = self.vm.end_frame(collectors);
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
        let arrived = self.loader.poll();
        let delivered = arrived.len();
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
        }
    }
}
