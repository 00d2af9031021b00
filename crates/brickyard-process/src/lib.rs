//! brickyard-process: processing of volumes larger than memory.
//!
//! Operators follow `scipy.ndimage` with `mode="nearest"` and `truncate=4`
//! (see [`filter`]); connected components are labelled out of core in two
//! passes (see [`label`]). Each stage is a
//! [`VolumeSource`](brickyard_store::VolumeSource), so a pipeline is a chain
//! of sources that computes a region when it is read, and
//! [`brickyard_store::convert`] writes any stage as a multiresolution
//! OME-Zarr image under a memory budget.
//!
//! The filters also run on the device ([`gpu`]): WGSL kernels, each the
//! twin of the CPU kernel of the same name, chosen per pipeline with
//! [`build_on`].

pub mod derive;
pub mod filter;
pub mod gpu;
pub mod kernels;
pub mod label;
pub mod pipeline;
pub mod tally;

pub use derive::{check_live, derive_level, derive_level_within, level_factor};
pub use filter::{Filter, FilterSource};
pub use gpu::{DeviceFilter, FilterKernels};
pub use label::{
    label_pass1, label_pass1_within, stats_csv, stats_json, write_stats_csv, write_stats_json,
    LabelSource, LabelStats, Labeling,
};
pub use pipeline::{Op, ParseError, Pipeline, Sigma};

use brickyard_core::grid::unit_in_meters;
use brickyard_core::Dims3;
use brickyard_store::VolumeSource;
use std::sync::Arc;

/// The sources of a pipeline's filter stages, ready to read.
pub struct Built {
    /// The last filter stage (the input itself when there is none).
    pub source: Arc<dyn VolumeSource>,
    /// Channel of `source` to read (the input channel when there is no
    /// filter stage, else 0).
    pub channel: usize,
    /// `Some(connectivity)` when the pipeline ends in `label`: `source` is
    /// then the mask to label.
    pub label: Option<u8>,
}

/// σ `[z, y, x]` in voxels of a volume with `spacing` and `unit`.
pub fn sigma_voxels(
    s: &Sigma,
    spacing: Option<[f64; 3]>,
    unit: Option<&str>,
) -> Result<[f64; 3], String> {
    match s {
        Sigma::Voxels(v) => Ok(*v),
        Sigma::Physical { value, unit: u } => {
            let sp = spacing.ok_or_else(|| {
                format!("σ given in {u} but the volume has no voxel spacing; give σ in voxels")
            })?;
            let su = unit.ok_or_else(|| {
                format!("σ given in {u} but the volume's spacing has no unit; give σ in voxels")
            })?;
            let (a, b) = (unit_in_meters(u), unit_in_meters(su));
            let f = match (a, b) {
                (Some(a), Some(b)) => a / b,
                _ => {
                    return Err(format!(
                        "σ in {u} cannot be converted to the volume's unit {su}"
                    ))
                }
            };
            Ok([0, 1, 2].map(|k| value[k] * f / sp[k]))
        }
    }
}

/// Chain the filter stages of `p` over channel `channel` of `input`,
/// computing in blocks of at most `block` voxels, on the CPU.
pub fn build(
    p: &Pipeline,
    input: Arc<dyn VolumeSource>,
    channel: usize,
    block: Dims3,
) -> Result<Built, String> {
    build_on(p, input, channel, block, None)
}

/// [`build`], with the filter stages computing on the device of `device`
/// when it is given (see [`FilterSource::with_device`]). Labelling stays on
/// the CPU.
pub fn build_on(
    p: &Pipeline,
    input: Arc<dyn VolumeSource>,
    channel: usize,
    block: Dims3,
    device: Option<&Arc<FilterKernels>>,
) -> Result<Built, String> {
    build_stages(
        p,
        input,
        channel,
        block,
        device,
        usize::MAX,
        Hooks::default(),
    )
    .map(|(b, _)| b)
}

/// What [`build_within`] plans for the filters' memory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FilterMemory {
    /// Most blocks each filter stage computes at once on the CPU.
    pub parallel: usize,
    /// The most bytes the filter stages' blocks hold at once (an upper
    /// bound; what the pipeline's reads take beyond the regions asked for).
    pub bytes: u64,
}

/// What a job hands the stages [`build_within`] makes.
#[derive(Clone, Default)]
pub struct Hooks {
    /// Once set, the stages' reads end before their next block
    /// ([`FilterSource::with_stop`]).
    pub stop: Option<Arc<std::sync::atomic::AtomicBool>>,
    /// Counts the voxels the last filter stage has computed
    /// ([`FilterSource::with_meter`]): progress within a region.
    pub meter: Option<Arc<std::sync::atomic::AtomicU64>>,
}

/// [`build_on`] within a memory budget: each filter stage computes at most
/// as many blocks at once (up to `threads`) as keep the blocks in flight of
/// all stages within `budget` bytes, counting a block's box grown by its
/// halo ([`filter::block_bytes`]; an inner stage's blocks are computed
/// inside each of the outer stage's blocks, so `n` blocks at once per stage
/// can mean `n^k` of the k-th stage from the end). An error, before
/// anything is computed, naming the stage, when even one block at a time
/// per stage does not fit. `hooks` stops the stages' reads and counts
/// what they compute ([`Hooks`]).
#[allow(clippy::too_many_arguments)]
pub fn build_within(
    p: &Pipeline,
    input: Arc<dyn VolumeSource>,
    channel: usize,
    block: Dims3,
    device: Option<&Arc<FilterKernels>>,
    budget: u64,
    threads: usize,
    hooks: Hooks,
) -> Result<(Built, FilterMemory), String> {
    // The stages' blocks, innermost first.
    let (_, stages) = build_stages(
        p,
        input.clone(),
        channel,
        block,
        device,
        1,
        Hooks::default(),
    )?;
    let plan = plan_parallel(&stages, budget, threads)?;
    let (built, _) = build_stages(p, input, channel, block, device, plan.parallel, hooks)?;
    Ok((built, plan))
}

/// How many blocks at once (up to `threads`) each filter stage may compute
/// so that the blocks in flight of all `stages` (name and bytes of one
/// block, innermost first) stay within `budget`: an inner stage's blocks
/// are computed inside each of the outer stage's blocks, so `n` blocks at
/// once per stage can mean `n^k` of the k-th stage from the end. An error
/// naming the stage of the largest block when even one block at a time
/// per stage does not fit.
pub(crate) fn plan_parallel(
    stages: &[(String, u64)],
    budget: u64,
    threads: usize,
) -> Result<FilterMemory, String> {
    let need = |n: usize| -> u64 {
        let k = stages.len();
        stages
            .iter()
            .enumerate()
            .map(|(i, (_, b))| {
                let depth = (k - i) as u32;
                (n as u64).saturating_pow(depth).saturating_mul(*b)
            })
            .fold(0u64, u64::saturating_add)
    };
    if need(1) > budget {
        let (name, b) = stages.iter().max_by_key(|(_, b)| *b).cloned().unwrap();
        return Err(format!(
            "{name}: one block with its halo takes {} MiB and the stages together {} MiB, over \
             the {} MiB the memory budget leaves for filtering",
            b.div_ceil(1 << 20),
            need(1).div_ceil(1 << 20),
            budget >> 20,
        ));
    }
    let n = (1..=threads.max(1))
        .take_while(|&n| need(n) <= budget)
        .last()
        .unwrap_or(1);
    Ok(FilterMemory {
        parallel: n,
        bytes: need(n),
    })
}

/// The most bytes the filter stages of `p` hold at once when each computes
/// one block at a time: the least budget [`build_within`] accepts.
pub fn filter_bytes_at_least(
    p: &Pipeline,
    input: Arc<dyn VolumeSource>,
    channel: usize,
    block: Dims3,
) -> Result<u64, String> {
    Ok(plan_result(p, input, channel, block)?.0)
}

/// [`filter_bytes_at_least`] and what the pipeline's result is as a
/// volume (what a writer is given): the last filter stage's, or for a
/// labelling the labels (u32) of its mask ([`LabelSource::meta_of`]).
pub fn plan_result(
    p: &Pipeline,
    input: Arc<dyn VolumeSource>,
    channel: usize,
    block: Dims3,
) -> Result<(u64, brickyard_store::SourceMeta), String> {
    let (built, stages) = build_stages(p, input, channel, block, None, 1, Hooks::default())?;
    let m = built.source.meta();
    let meta = match built.label {
        None => m.clone(),
        Some(conn) => LabelSource::meta_of(m, conn),
    };
    Ok((stages.iter().map(|(_, b)| b).sum(), meta))
}

/// The chained stages, each computing at most `parallel` blocks at once;
/// and per filter stage its name and [`FilterSource::block_bytes`].
fn build_stages(
    p: &Pipeline,
    input: Arc<dyn VolumeSource>,
    channel: usize,
    block: Dims3,
    device: Option<&Arc<FilterKernels>>,
    parallel: usize,
    hooks: Hooks,
) -> Result<(Built, Vec<(String, u64)>), String> {
    let m = input.meta();
    if channel >= m.channels {
        return Err(format!(
            "channel {channel} asked for but the volume has {} channel(s)",
            m.channels
        ));
    }
    let (spacing, unit) = (m.spacing, m.unit.clone());
    let mut src = input;
    let mut ch = channel;
    let mut label = None;
    let mut stages = vec![];
    // The stage whose blocks the meter counts: the last filter's.
    let last = p.ops.iter().rposition(|o| !matches!(o, Op::Label(_)));
    for (i, op) in p.ops.iter().enumerate() {
        let f = match op {
            Op::Gauss(s) => Filter::Gauss(sigma_voxels(s, spacing, unit.as_deref())?),
            Op::GradMag(s) => Filter::GradMag(sigma_voxels(s, spacing, unit.as_deref())?),
            Op::Sobel => Filter::Sobel,
            Op::Median(r) => Filter::Median(r.map(|v| v as usize)),
            Op::Threshold(t) => Filter::Threshold(*t),
            Op::Window(a, b) => Filter::Window(*a, *b),
            Op::Label(c) => {
                label = Some(*c);
                continue;
            }
        };
        let name = op.text();
        let mut stage = FilterSource::try_new(src, ch, f, &name, block)
            .map_err(|e| format!("{name}: {e}"))?
            .with_parallel(parallel)
            .with_stop(hooks.stop.clone())
            .with_meter(hooks.meter.clone().filter(|_| Some(i) == last));
        stages.push((name, stage.block_bytes()));
        if let Some(k) = device {
            stage = stage.with_device(k);
        }
        src = Arc::new(stage);
        ch = 0;
    }
    Ok((
        Built {
            source: src,
            channel: ch,
            label,
        },
        stages,
    ))
}
