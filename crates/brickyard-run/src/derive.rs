//! `--derive PIPELINE` of `render` and `view`: a live derived channel, the
//! pipeline applied to one channel of the store level by level, each brick
//! computed when the view asks for it (see [`brickyard_process::derive`]).

use anyhow::{anyhow, Result};
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_process::{derive_level, level_factor, Pipeline};
use brickyard_store::import::zarr;
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
        };
        // Fail now, naming the stage, rather than on the first brick.
        d.dtype = d.level(stored)?.meta().dtype;
        Ok(d)
    }

    /// The derived source of one level's stored array.
    pub fn level(&self, stored: Arc<dyn VolumeSource>) -> Result<Arc<dyn VolumeSource>> {
        let f = level_factor(&self.level0, stored.meta());
        derive_level(&self.pipeline, stored, self.channel, f, BLOCK)
            .map_err(|e| anyhow!("derive {}: {e}", self.pipeline.text()))
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
