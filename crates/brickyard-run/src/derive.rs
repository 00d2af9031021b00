//! `--derive PIPELINE` of `render` and `view`: a live derived channel, the
//! pipeline applied to one channel of the store level by level, each brick
//! computed when the view asks for it (see [`brickyard_process::derive`]).

use anyhow::{anyhow, Result};
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_process::{derive_level, derive_level_within, level_factor, Pipeline};
use brickyard_store::import::zarr;
use brickyard_store::info::human_bytes;
use brickyard_store::{SourceMeta, VolumeSource};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Largest block a derived brick is computed in: a brick with its apron
/// and the stages' halos is one block.
const BLOCK: [u64; 3] = [160; 3];

/// A parsed `--derive` over one channel of a store.
#[derive(Clone, Debug)]
pub struct Derived {
    pub pipeline: Pipeline,
    /// The store's channel it is computed from.
    pub channel: usize,
    store: PathBuf,
    level0: SourceMeta,
    /// Voxel type of the derived channel (the last stage's).
    pub dtype: brickyard_core::DType,
    /// Set by [`Derived::within`]: the filters' blocks held to a budget.
    within: Option<Within>,
}

/// What the filters' blocks are held to (see [`Derived::within`]).
#[derive(Clone, Copy, Debug)]
struct Within {
    /// Bytes for all readers together.
    budget: u64,
    /// Brick reads at once (the loader's threads).
    readers: usize,
    /// The largest region a read asks for (a padded brick).
    read: [u64; 3],
    /// Blocks a stage may compute at once, at most.
    threads: usize,
}

impl Derived {
    /// Parse `text` for channel `channel` of `store`; the error names the
    /// offending stage or channel.
    pub fn new(store: &Path, text: &str, channel: usize) -> Result<Derived> {
        let pipeline = Pipeline::parse(text).map_err(|e| anyhow!("derive: {e}"))?;
        brickyard_process::check_live(&pipeline).map_err(|e| anyhow!("derive: {e}"))?;
        let stored = Arc::new(zarr::open(store, 0)?);
        let level0 = stored.meta().clone();
        if channel >= level0.channels {
            return Err(anyhow!(
                "derive: channel {channel} asked for but {} has {} channel(s)",
                store.display(),
                level0.channels
            ));
        }
        let mut d = Derived {
            pipeline,
            channel,
            store: store.to_path_buf(),
            level0,
            dtype: brickyard_core::DType::F32,
            within: None,
        };
        // Fail now, naming the stage, rather than on the first brick.
        d.dtype = d.level(stored)?.meta().dtype;
        Ok(d)
    }

    /// [`new`](Self::new) with the filters held to a quarter of the
    /// memory budget (`memory`, or the default when `None`; as `process`
    /// gives its filters) for `loader_threads` reads at once of padded
    /// bricks of `brick` voxels: see [`within`](Self::within). Returns the
    /// derived channel and the bytes its filters may hold at once (to be
    /// set aside in the memory split); an error naming the stage, the
    /// share of `--memory` and the loader threads when even one block at a
    /// time does not fit.
    pub fn new_within(
        store: &Path,
        text: &str,
        channel: usize,
        memory: Option<u64>,
        loader_threads: usize,
        brick: u64,
    ) -> Result<(Derived, u64)> {
        let mut d = Derived::new(store, text, channel)?;
        let total = memory.unwrap_or_else(crate::memory::default_memory);
        let share = total / 4;
        let padded = brick + 2 * VmConfig::default().apron;
        let e = match d.within(share, loader_threads, [padded; 3]) {
            Ok(bytes) => return Ok((d, bytes)),
            Err(e) => e,
        };
        // The least --memory whose quarter holds the filters' blocks (in
        // whole MiB), when some does.
        let mib = 1u64 << 20;
        let least = brickyard_store::builder::least_budget(total.saturating_add(1), |m| {
            d.within(m / 4, loader_threads, [padded; 3]).is_ok()
        });
        let raise = if least < u64::MAX / 4 {
            format!("--memory {}MiB runs it", least.div_ceil(mib))
        } else {
            "raise --memory".into()
        };
        // What makes the blocks smaller: a σ (gauss, gradmag), a radius
        // (median).
        use brickyard_process::pipeline::Op;
        let ops = &d.pipeline.ops;
        let smaller = match (
            ops.iter()
                .any(|o| matches!(o, Op::Gauss(_) | Op::GradMag(_))),
            ops.iter().any(|o| matches!(o, Op::Median(_))),
        ) {
            (true, true) => " or use a smaller σ or median radius",
            (true, false) => " or use a smaller σ",
            (false, true) => " or use a smaller median radius",
            (false, false) => "",
        };
        Err(anyhow!(
            "{e:#}; the filters of --derive get a quarter of --memory ({} of {}{}): \
             {raise}; or lower --loader-threads{smaller}",
            human_bytes(share),
            human_bytes(total),
            if memory.is_some() {
                ""
            } else {
                ", the default: a quarter of RAM"
            }
        ))
    }

    /// Hold the filters' blocks to `budget` bytes while `readers` brick
    /// reads (the loader's threads) of at most `read` voxels run at once:
    /// each stage computes only as many blocks at once as fit (see
    /// [`derive_level_within`]). Checked now on level 0, whose blocks are
    /// the largest: an error naming the stage when even one block at a time
    /// does not fit. Returns the bytes the filters may then hold at once.
    pub fn within(&mut self, budget: u64, readers: usize, read: [u64; 3]) -> Result<u64> {
        self.within = Some(Within {
            budget,
            readers: readers.max(1),
            read,
            threads: rayon::current_num_threads(),
        });
        let stored: Arc<dyn VolumeSource> = Arc::new(zarr::open(&self.store, 0)?);
        Ok(self.planned(stored)?.1)
    }

    /// The derived source of one level's stored array, and the most bytes
    /// its filters hold at once (0 when not held to a budget).
    fn planned(&self, stored: Arc<dyn VolumeSource>) -> Result<(Arc<dyn VolumeSource>, u64)> {
        let f = level_factor(&self.level0, stored.meta());
        let name = self.pipeline.text();
        match self.within {
            None => derive_level(&self.pipeline, stored, self.channel, f, BLOCK)
                .map(|s| (s, 0))
                .map_err(|e| anyhow!("derive {name}: {e}")),
            Some(w) => derive_level_within(
                &self.pipeline,
                stored,
                self.channel,
                f,
                BLOCK,
                w.read,
                w.readers,
                w.budget,
                w.threads,
            )
            .map(|(s, m)| (s, m.bytes))
            .map_err(|e| {
                anyhow!(
                    "derive {name}: {e} per brick read ({} at once, one per loader thread)",
                    w.readers
                )
            }),
        }
    }

    /// The largest region a read of the derived channel may ask for within
    /// its filters' share of --memory (a padded brick), when held to one.
    pub fn read_limit(&self) -> Option<[u64; 3]> {
        self.within.as_ref().map(|w| w.read)
    }

    /// The derived source of one level's stored array.
    pub fn level(&self, stored: Arc<dyn VolumeSource>) -> Result<Arc<dyn VolumeSource>> {
        Ok(self.planned(stored)?.0)
    }

    /// The derived source of level `l`, opened from the store.
    pub fn open_level(&self, l: usize) -> Result<Arc<dyn VolumeSource>> {
        self.level(Arc::new(zarr::open(&self.store, l)?))
    }

    /// A session whose bricks are the derived channel's (one channel).
    pub fn session(
        &self,
        cfg: VmConfig,
        host_bytes: u64,
        chunk_bytes: u64,
        threads: usize,
    ) -> Result<Session> {
        let f = |_l: usize, stored: Arc<dyn VolumeSource>| {
            self.level(stored).map_err(|e| format!("{e:#}"))
        };
        Ok(Session::open_derived(
            &self.store,
            cfg,
            host_bytes,
            chunk_bytes,
            threads,
            &f,
        )?)
    }
}
