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

pub use derive::{check_live, derive_level, level_factor};
pub use filter::{Filter, FilterSource};
pub use gpu::{DeviceFilter, FilterKernels};
pub use label::{label_pass1, stats_csv, stats_json, LabelSource, LabelStats, Labeling};
pub use pipeline::{Op, ParseError, Pipeline, Sigma};

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
            let (a, b) = (pipeline::unit_meters(u), pipeline::unit_meters(su));
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
    for op in &p.ops {
        let f = match op {
            Op::Gauss(s) => Filter::Gauss(sigma_voxels(s, spacing, unit.as_deref())?),
            Op::GradMag(s) => Filter::GradMag(sigma_voxels(s, spacing, unit.as_deref())?),
            Op::Sobel => Filter::Sobel,
            Op::Threshold(t) => Filter::Threshold(*t),
            Op::Window(a, b) => Filter::Window(*a, *b),
            Op::Label(c) => {
                label = Some(*c);
                continue;
            }
        };
        let mut stage = FilterSource::new(src, ch, f, &op.text(), block);
        if let Some(k) = device {
            stage = stage.with_device(k);
        }
        src = Arc::new(stage);
        ch = 0;
    }
    Ok(Built {
        source: src,
        channel: ch,
        label,
    })
}
