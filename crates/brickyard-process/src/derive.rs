//! Live derived channels: a pipeline applied level by level to a pyramid,
//! each brick computed when a view asks for it.
//!
//! How a brick of a coarse level is made: the pipeline runs on that level's
//! own (downsampled) data, with every length scaled to the level, so that
//! the level is a stand-in for the finer result, as a stored pyramid is:
//! - `gauss(σ)` and `gradmag(σ)` with σ in voxels: σ is in level-0 voxels
//!   and becomes `σ / f` at a level whose voxels are `f` level-0 voxels
//!   wide (per axis); σ with a unit is converted with the level's spacing,
//!   which comes to the same;
//! - `gradmag` and `sobel` are derivatives: their values are per level-0
//!   voxel at every level (divided by `f`, the geometric mean of the three
//!   axes' factors when they differ), so that a ramp has the same gradient
//!   at every level and an edge the gradient of the finer result averaged
//!   over the coarse voxel (`sobel` keeps its three-voxel stencil, which
//!   spans a wider region at a coarser level);
//! - `threshold` and `window` act on each value: the same at every level.
//!
//! `label` needs the whole mask at once and has no live form: it is a job
//! for `brickyard process`.

use crate::filter::{Filter, FilterSource};
use crate::pipeline::{Op, Pipeline, Sigma};
use crate::{sigma_voxels, FilterMemory};
use brickyard_core::{as_bytes_mut, Dims3};
use brickyard_store::source::check_region;
use brickyard_store::{Result, SourceMeta, VolumeSource};
use std::ops::Range;
use std::sync::Arc;

/// Size of a voxel of `level` in voxels of `level0`, `[z, y, x]`: the ratio
/// of their spacings when both have one, else of their dimensions.
pub fn level_factor(level0: &SourceMeta, level: &SourceMeta) -> [f64; 3] {
    match (level0.spacing, level.spacing) {
        (Some(a), Some(b)) if a.iter().all(|v| *v > 0.0) => [0, 1, 2].map(|k| b[k] / a[k]),
        _ => [0, 1, 2].map(|k| level0.dims[k] as f64 / level.dims[k].max(1) as f64),
    }
}

/// Check that `p` can be derived live (no `label`, at least one stage).
pub fn check_live(p: &Pipeline) -> std::result::Result<(), String> {
    if p.ops.is_empty() {
        return Err("the pipeline has no stage".into());
    }
    if p.ops.iter().any(|o| matches!(o, Op::Label(_))) {
        return Err(
            "label needs the whole mask and has no live form; write labels with `brickyard process STORE PIPELINE --out NAME` and view them"
                .into(),
        );
    }
    Ok(())
}

/// The derived volume of `p` over channel `channel` of one pyramid level
/// (`level`, whose voxels are `factor` level-0 voxels wide), computed in
/// blocks of at most `block` voxels. One channel, of the last stage's type.
pub fn derive_level(
    p: &Pipeline,
    level: Arc<dyn VolumeSource>,
    channel: usize,
    factor: [f64; 3],
    block: Dims3,
) -> std::result::Result<Arc<dyn VolumeSource>, String> {
    derive_stages(p, level, channel, factor, block, usize::MAX).map(|(src, _)| src)
}

/// [`derive_level`] for readers that each ask for regions of at most `read`
/// voxels at once, `readers` of them at the same time (a loader's threads
/// reading padded bricks): each filter stage computes at most as many
/// blocks at once (up to `threads`) as keep the blocks in flight of all
/// readers within `budget` bytes, a block counted with its halo and no
/// larger than the region its stage is asked for (see
/// [`crate::filter::region_block_bytes`]; the region of an inner stage is
/// the outer block grown by the outer halo). An error, before anything is
/// computed, naming the stage, when even one block at a time per stage
/// does not fit; the plan's bytes are those of all readers together.
#[allow(clippy::too_many_arguments)]
pub fn derive_level_within(
    p: &Pipeline,
    level: Arc<dyn VolumeSource>,
    channel: usize,
    factor: [f64; 3],
    block: Dims3,
    read: Dims3,
    readers: usize,
    budget: u64,
    threads: usize,
) -> std::result::Result<(Arc<dyn VolumeSource>, FilterMemory), String> {
    let readers = readers.max(1) as u64;
    let (_, stages) = derive_stages(p, level.clone(), channel, factor, block, 1)?;
    // One block of each stage for a read of `read` voxels, outermost first
    // (the region each stage is asked for comes from the stage after it);
    // a rescaled stage's values are copied once more (f32).
    let mut region = read;
    let mut bytes = Vec::with_capacity(stages.len());
    for st in stages.iter().rev() {
        let (b, inner) = st.source.region_block_bytes(region);
        let scaled = if st.scaled {
            4 * region.iter().product::<u64>()
        } else {
            0
        };
        bytes.push((st.name.clone(), b + scaled));
        region = inner;
    }
    bytes.reverse();
    let plan = crate::plan_parallel(&bytes, budget / readers, threads)?;
    let (src, _) = derive_stages(p, level, channel, factor, block, plan.parallel)?;
    Ok((
        src,
        FilterMemory {
            parallel: plan.parallel,
            bytes: plan.bytes * readers,
        },
    ))
}

/// A filter stage of a derived level, for its memory plan.
struct Stage {
    name: String,
    source: Arc<FilterSource>,
    /// Followed by a [`Scaled`] copy (gradients per level-0 voxel).
    scaled: bool,
}

/// The derived level's chained stages, each computing at most `parallel`
/// blocks at once; and its filter stages, innermost first.
fn derive_stages(
    p: &Pipeline,
    level: Arc<dyn VolumeSource>,
    channel: usize,
    factor: [f64; 3],
    block: Dims3,
    parallel: usize,
) -> std::result::Result<(Arc<dyn VolumeSource>, Vec<Stage>), String> {
    check_live(p)?;
    let m = level.meta();
    if channel >= m.channels {
        return Err(format!(
            "channel {channel} asked for but the volume has {} channel(s)",
            m.channels
        ));
    }
    let (spacing, unit) = (m.spacing, m.unit.clone());
    let sigma = |s: &Sigma| -> std::result::Result<[f64; 3], String> {
        match s {
            Sigma::Voxels(v) => Ok([0, 1, 2].map(|k| v[k] / factor[k])),
            Sigma::Physical { .. } => sigma_voxels(s, spacing, unit.as_deref()),
        }
    };
    let mean_factor = factor.iter().product::<f64>().cbrt();
    let mut src = level;
    let mut ch = channel;
    let mut stages = Vec::with_capacity(p.ops.len());
    for op in &p.ops {
        let f = match op {
            Op::Gauss(s) => Filter::Gauss(sigma(s)?),
            Op::GradMag(s) => Filter::GradMag(sigma(s)?),
            Op::Sobel => Filter::Sobel,
            // The radius in level-0 voxels, at this level's.
            Op::Median(r) => {
                Filter::Median([0, 1, 2].map(|k| (r[k] as f64 / factor[k]).round() as usize))
            }
            Op::Threshold(t) => Filter::Threshold(*t),
            Op::Window(a, b) => Filter::Window(*a, *b),
            Op::Label(_) => unreachable!("checked by check_live"),
        };
        let name = op.text();
        let stage = Arc::new(
            FilterSource::try_new(src, ch, f, &name, block)
                .map_err(|e| format!("{name}: {e}"))?
                .with_parallel(parallel),
        );
        src = stage.clone();
        let scaled = matches!(op, Op::GradMag(_) | Op::Sobel) && (mean_factor - 1.0).abs() > 1e-12;
        if scaled {
            src = Arc::new(Scaled::new(src, 1.0 / mean_factor));
        }
        stages.push(Stage {
            name,
            source: stage,
            scaled,
        });
        ch = 0;
    }
    Ok((src, stages))
}

/// An f32 source with every value multiplied by a constant.
pub struct Scaled {
    inner: Arc<dyn VolumeSource>,
    by: f32,
    meta: SourceMeta,
}

impl Scaled {
    /// `inner` must be one channel of f32.
    pub fn new(inner: Arc<dyn VolumeSource>, by: f64) -> Scaled {
        let meta = inner.meta().clone();
        assert_eq!(meta.dtype, brickyard_core::DType::F32);
        Scaled {
            inner,
            by: by as f32,
            meta,
        }
    }
}

impl VolumeSource for Scaled {
    fn meta(&self) -> &SourceMeta {
        &self.meta
    }

    fn read_region(
        &self,
        c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> Result<()> {
        check_region(&self.meta, c, &z, &y, &x, out);
        let n = out.len() / 4;
        let mut v = vec![0f32; n];
        self.inner.read_region(c, z, y, x, as_bytes_mut(&mut v))?;
        for x in &mut v {
            *x *= self.by;
        }
        out.copy_from_slice(brickyard_core::as_bytes(&v));
        Ok(())
    }

    fn preferred_read(&self) -> Dims3 {
        self.inner.preferred_read()
    }
}
