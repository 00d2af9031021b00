//! Filter stages as volume sources: reading a region of a stage reads the
//! region plus the stage's halo from the stage before it, fills the halo
//! outside the volume with the boundary mode, and computes.
//!
//! Boundary mode: `nearest` everywhere (scipy's `mode="nearest"`: the edge
//! voxel repeated), for every stage, also on the results of earlier stages,
//! which is what scipy does when stages are applied one after the other.
//!
//! A stage computes on the CPU in f64 by default, or on the device in f32
//! ([`FilterSource::with_device`], [`crate::gpu`]); both store the same
//! types.

use crate::gpu::{DeviceFilter, FilterKernels};
use crate::kernels::{
    fold_weights, gaussian_radius, gaussian_weights, gaussian_weights_folded, magnitude_nearest,
    max_sigma, median_nearest_until, separable_nearest, threshold, window, Real, MAX_RADIUS,
    SOBEL_D, SOBEL_S,
};
use brickyard_core::{as_bytes_mut, dispatch_dtype, DType, Dims3, Sample};
use brickyard_store::source::check_region;
use brickyard_store::{Result, SourceMeta, StoreError, VolumeSource};
use rayon::prelude::*;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// scipy's default `truncate`: kernels reach `int(4σ + 0.5)` voxels.
pub const TRUNCATE: f64 = 4.0;

/// What a filter stage computes.
#[derive(Debug, Clone)]
pub enum Filter {
    /// `gaussian_filter(x, σ, mode="nearest")`, σ `[z, y, x]` in voxels.
    Gauss([f64; 3]),
    /// `gaussian_gradient_magnitude(x, σ, mode="nearest")`.
    GradMag([f64; 3]),
    /// `generic_gradient_magnitude(x, sobel, mode="nearest")`.
    Sobel,
    /// `x > t`, as u8 0/1.
    Threshold(f64),
    /// `lo <= x <= hi`, as u8 0/1.
    Window(f64, f64),
    /// `median_filter(x, size=2r+1, mode="nearest")`, the radius `[z, y, x]`
    /// in voxels (CPU only: no device kernel).
    Median([usize; 3]),
    /// A float filter on a volume of `dims` `[z, y, x]` whose kernels reach
    /// past the volume: the weights beyond `dims − 1` voxels from the
    /// centre summed onto the taps `±(dims − 1)` (boundary mode "nearest"
    /// reads the edge voxel there whatever voxel is computed, so the result
    /// is the filter's), the halo at most `dims − 1`. Made by
    /// [`Filter::on_volume`].
    Folded(Box<Filter>, [u64; 3]),
}

impl Filter {
    /// Voxel type of the result.
    pub fn out_dtype(&self) -> DType {
        match self {
            Filter::Gauss(_) | Filter::GradMag(_) | Filter::Sobel | Filter::Median(_) => DType::F32,
            Filter::Threshold(_) | Filter::Window(..) => DType::U8,
            Filter::Folded(f, _) => f.out_dtype(),
        }
    }

    /// The filter as computed on a volume of `dims` `[z, y, x]`: itself, or
    /// [`Filter::Folded`] when a kernel reaches farther than the volume
    /// (the same result, a halo of at most the volume's extent). An error
    /// for σ past [`max_sigma`] (its weights would take too long to sum),
    /// naming σ and the largest allowed.
    pub fn on_volume(self, dims: Dims3) -> std::result::Result<Filter, String> {
        if let Filter::Gauss(s) | Filter::GradMag(s) = &self {
            if let Some(v) = s
                .iter()
                .find(|&&v| gaussian_radius(v, TRUNCATE) > MAX_RADIUS)
            {
                // (The radius, ⌈truncate·σ⌉, saturates for a huge σ: said
                // as a product then.)
                let reach = match gaussian_radius(*v, TRUNCATE) {
                    r if r < u64::MAX => r.to_string(),
                    _ if (TRUNCATE * v).is_finite() => format!("about {:.1e}", TRUNCATE * v),
                    _ => "more than 1e308".to_string(),
                };
                return Err(format!(
                    "σ {} voxels is too large: its kernel would reach {reach} voxels; σ may be \
                     at most {} voxels (a kernel that reaches past the volume is folded onto its \
                     edge voxels, so a wider one gives the same result)",
                    crate::pipeline::short(*v),
                    max_sigma(TRUNCATE)
                ));
            }
        }
        let h = self.halo();
        // (Whether it is separable, without making its kernels: unfolded,
        // a σ of a million voxels has eight million taps per axis.)
        let separable = matches!(self, Filter::Gauss(_) | Filter::GradMag(_) | Filter::Sobel);
        if (0..3).any(|a| h[a] as u64 >= dims[a].max(1)) && separable {
            Ok(Filter::Folded(Box::new(self), dims))
        } else {
            Ok(self)
        }
    }

    /// Voxels read beyond the region on each side, `[z, y, x]`.
    pub fn halo(&self) -> [usize; 3] {
        match self {
            Filter::Gauss(s) | Filter::GradMag(s) => s.map(|v| {
                if v > 0.0 {
                    (TRUNCATE * v + 0.5) as usize
                } else {
                    0
                }
            }),
            Filter::Sobel => [1; 3],
            Filter::Median(r) => *r,
            Filter::Threshold(_) | Filter::Window(..) => [0; 3],
            Filter::Folded(f, d) => {
                let h = f.halo();
                [0, 1, 2].map(|a| h[a].min(d[a].max(1) as usize - 1))
            }
        }
    }

    /// The separable passes of a float filter: one weight vector per axis
    /// `[z, y, x]` for each component, and whether the result is the root of
    /// the components' sum of squares (a gradient magnitude) rather than the
    /// one component. `None` for threshold and window.
    pub fn components(&self) -> Option<(Vec<[Vec<f64>; 3]>, bool)> {
        match self {
            Filter::Gauss(s) => Some((vec![s.map(|v| gaussian_weights(v, 0, TRUNCATE))], false)),
            Filter::GradMag(s) => {
                let [g0, g1, g2] = s.map(|v| gaussian_weights(v, 0, TRUNCATE));
                let [d0, d1, d2] = s.map(|v| gaussian_weights(v, 1, TRUNCATE));
                Some((
                    vec![
                        [d0, g1.clone(), g2.clone()],
                        [g0.clone(), d1, g2],
                        [g0, g1, d2],
                    ],
                    true,
                ))
            }
            Filter::Sobel => {
                let (d, s) = (SOBEL_D.to_vec(), SOBEL_S.to_vec());
                Some((
                    vec![
                        [d.clone(), s.clone(), s.clone()],
                        [s.clone(), d.clone(), s.clone()],
                        [s.clone(), s, d],
                    ],
                    true,
                ))
            }
            Filter::Threshold(_) | Filter::Window(..) | Filter::Median(_) => None,
            Filter::Folded(f, d) => {
                let (cs, mag) = match &**f {
                    Filter::Gauss(s) => (
                        vec![[0, 1, 2].map(|a| gaussian_weights_folded(s[a], 0, TRUNCATE, d[a]))],
                        false,
                    ),
                    Filter::GradMag(s) => {
                        let g = |a: usize| gaussian_weights_folded(s[a], 0, TRUNCATE, d[a]);
                        let dv = |a: usize| gaussian_weights_folded(s[a], 1, TRUNCATE, d[a]);
                        (
                            vec![
                                [dv(0), g(1), g(2)],
                                [g(0), dv(1), g(2)],
                                [g(0), g(1), dv(2)],
                            ],
                            true,
                        )
                    }
                    other => {
                        let (cs, mag) = other.components()?;
                        let cs = cs
                            .into_iter()
                            .map(|c| [0, 1, 2].map(|a| fold_weights(&c[a], d[a])))
                            .collect();
                        (cs, mag)
                    }
                };
                Some((cs, mag))
            }
        }
    }

    /// Compute on a block padded by [`Filter::halo`]; `dims` are the padded
    /// dimensions. Returns the block's values. In f64 this is the CPU
    /// filter; in f32 it is the twin of [`crate::gpu::DeviceFilter::apply`]
    /// (the same kernels in the same order, weights rounded to f32).
    pub fn apply<R: Real>(&self, data: Vec<R>, dims: [usize; 3]) -> Vec<R> {
        let h = self.halo();
        for a in 0..3 {
            assert!(dims[a] >= 2 * h[a], "block thinner than the halo");
        }
        let first = h.map(|v| v as i64);
        let len = [0, 1, 2].map(|a| dims[a] - 2 * h[a]);
        self.apply_nearest(data, dims, first, len)
    }

    /// Compute at positions `first..first + len` (per axis) of `data`
    /// (`dims`), a tap outside `data` reading its nearest end: on a block's
    /// box grown by the halo and clamped to the volume, the boundary mode
    /// "nearest" without padding (the same values as [`Filter::apply`] on
    /// the padded box, bit for bit).
    pub fn apply_nearest<R: Real>(
        &self,
        data: Vec<R>,
        dims: [usize; 3],
        first: [i64; 3],
        len: [usize; 3],
    ) -> Vec<R> {
        self.apply_with(self.components(), data, dims, first, len, None)
    }

    /// [`Filter::apply_nearest`] with the filter's
    /// [`Filter::components`] computed once beforehand. A median gives up
    /// once `stop` is set (see [`median_nearest_until`]).
    #[allow(clippy::type_complexity)]
    fn apply_with<R: Real>(
        &self,
        components: Option<(Vec<[Vec<f64>; 3]>, bool)>,
        data: Vec<R>,
        dims: [usize; 3],
        first: [i64; 3],
        len: [usize; 3],
        stop: Option<&AtomicBool>,
    ) -> Vec<R> {
        match (self, components) {
            (_, Some((cs, mag))) => {
                let cs: Vec<[Vec<R>; 3]> = cs
                    .iter()
                    .map(|c| {
                        c.each_ref()
                            .map(|w| w.iter().map(|&v| R::from_f64(v)).collect())
                    })
                    .collect();
                fn refs<R>(c: &[Vec<R>; 3]) -> [&[R]; 3] {
                    [&c[0], &c[1], &c[2]]
                }
                if mag {
                    let ws = [refs(&cs[0]), refs(&cs[1]), refs(&cs[2])];
                    magnitude_nearest(&data, dims, ws, first, len).0
                } else {
                    separable_nearest(data, dims, refs(&cs[0]), first, len).0
                }
            }
            (Filter::Median(r), None) => median_nearest_until(&data, dims, *r, first, len, stop),
            (Filter::Threshold(t), None) => threshold(&data, *t),
            (Filter::Window(lo, hi), None) => window(&data, *lo, *hi),
            _ => unreachable!("float filters have components"),
        }
    }
}

/// One filter stage over channel `channel` of `inner`.
pub struct FilterSource {
    inner: Arc<dyn VolumeSource>,
    channel: usize,
    filter: Filter,
    meta: SourceMeta,
    /// Largest block computed at once; regions are cut into such blocks and
    /// the blocks computed in parallel.
    block: Dims3,
    /// Set by [`FilterSource::with_device`]: reads compute on the device.
    device: Option<DeviceStage>,
    /// Most blocks computed at once on the CPU (the memory budget's share,
    /// see [`FilterSource::with_parallel`]).
    parallel: usize,
    /// The filter's weights ([`Filter::components`]), computed once.
    #[allow(clippy::type_complexity)]
    components: Option<(Vec<[Vec<f64>; 3]>, bool)>,
    /// Set from outside (Ctrl-C): reads end with
    /// [`StoreError::Interrupted`] before their next block.
    stop: Option<Arc<AtomicBool>>,
    /// Counts the voxels this stage has computed ([`FilterSource::with_meter`]).
    meter: Option<Arc<AtomicU64>>,
}

/// A stage's filter on the device, and the most voxels of a padded piece.
struct DeviceStage {
    filter: Mutex<DeviceFilter>,
    max_voxels: u64,
}

/// Bytes that computing one block of `filter` on the CPU holds at its peak
/// (an upper bound): the block's box grown by the halo and clamped to the
/// volume `dims`, read as `in_size`-byte values and converted to f64, the
/// passes' results (one more f64 box for a separable filter, two for a
/// magnitude, which keeps its input), and the block's values (f64 and their
/// output type). Blocks are at most 1.5 `block` long (see [`split`]).
pub fn block_bytes(filter: &Filter, dims: Dims3, block: Dims3, in_size: usize) -> u64 {
    region_block_bytes(filter, dims, block, dims, in_size).0
}

/// [`block_bytes`] of a stage that is asked for regions of at most
/// `region` voxels per axis at once (its blocks are no larger than the
/// region), and the largest region such a block asks the stage before it
/// for: the block grown by the halo, clamped to the volume.
pub fn region_block_bytes(
    filter: &Filter,
    dims: Dims3,
    block: Dims3,
    region: Dims3,
    in_size: usize,
) -> (u64, Dims3) {
    let h = filter.halo();
    let b = [0, 1, 2].map(|a| {
        (block[a].max(1) * 3)
            .div_ceil(2)
            .min(region[a].max(1))
            .min(dims[a])
    });
    let inner = [0, 1, 2].map(|a| (b[a] + 2 * h[a] as u64).min(dims[a]));
    let read: u64 = inner.iter().product();
    let out: u64 = b.iter().product();
    let boxes = match filter.components() {
        // The window's values, per thread: small beside the boxes.
        None if matches!(filter, Filter::Median(_)) => 1,
        None => 0,
        Some((_, false)) => 1,
        Some((_, true)) => 2,
    };
    (
        read * (in_size as u64 + 8 + 8 * boxes) + out * (8 + filter.out_dtype().size() as u64),
        inner,
    )
}

impl FilterSource {
    /// A stage of `filter` over `inner` (see [`FilterSource::try_new`]);
    /// panics where that is an error.
    pub fn new(
        inner: Arc<dyn VolumeSource>,
        channel: usize,
        filter: Filter,
        name: &str,
        block: Dims3,
    ) -> FilterSource {
        FilterSource::try_new(inner, channel, filter, name, block).unwrap_or_else(|e| panic!("{e}"))
    }

    /// A stage of `filter` over channel `channel` of `inner`, computed in
    /// blocks of at most `block` voxels. A kernel that reaches past the
    /// volume is folded ([`Filter::on_volume`]); an error for σ too large
    /// to compute (the message names σ and the largest allowed).
    pub fn try_new(
        inner: Arc<dyn VolumeSource>,
        channel: usize,
        filter: Filter,
        name: &str,
        block: Dims3,
    ) -> std::result::Result<FilterSource, String> {
        let filter = filter.on_volume(inner.meta().dims)?;
        let components = filter.components();
        let im = inner.meta();
        let mut meta = SourceMeta::new(im.path.join(name), im.dims, 1, filter.out_dtype());
        meta.spacing = im.spacing;
        meta.origin = im.origin;
        meta.unit = im.unit.clone();
        meta.labels = matches!(filter, Filter::Threshold(_) | Filter::Window(..));
        meta.notes = im.notes.clone();
        Ok(FilterSource {
            inner,
            channel,
            filter,
            meta,
            block: block.map(|b| b.max(1)),
            device: None,
            parallel: usize::MAX,
            stop: None,
            meter: None,
            components,
        })
    }

    /// Compute at most `n` blocks at once on the CPU (at least 1), so that
    /// `n` times [`FilterSource::block_bytes`] stays in a memory budget.
    pub fn with_parallel(mut self, n: usize) -> FilterSource {
        self.parallel = n.max(1);
        self
    }

    /// Reads stop before their next block once `stop` is set (a job's
    /// Ctrl-C: a region of a slow filter takes many seconds).
    pub fn with_stop(mut self, stop: Option<Arc<AtomicBool>>) -> FilterSource {
        self.stop = stop;
        self
    }

    /// Each block this stage computes adds its voxels to `meter` as soon
    /// as it is done: a job's progress within a region, which a slow
    /// filter (a median) takes minutes over.
    pub fn with_meter(mut self, meter: Option<Arc<AtomicU64>>) -> FilterSource {
        self.meter = meter;
        self
    }

    /// Add a computed block `b` to the meter.
    fn count(&self, b: &[Range<u64>; 3]) {
        if let Some(m) = &self.meter {
            m.fetch_add(
                b.iter().map(|r| r.end - r.start).product(),
                Ordering::Relaxed,
            );
        }
    }

    fn stopped(&self) -> Result<()> {
        match &self.stop {
            Some(s) if s.load(Ordering::Relaxed) => Err(StoreError::Interrupted),
            _ => Ok(()),
        }
    }

    /// [`block_bytes`] of this stage.
    pub fn block_bytes(&self) -> u64 {
        block_bytes(
            &self.filter,
            self.meta.dims,
            self.block,
            self.inner.meta().dtype.size(),
        )
    }

    /// [`region_block_bytes`] of this stage: one block's bytes when it is
    /// asked for regions of at most `region` voxels, and the largest
    /// region it then asks the stage before it for.
    pub fn region_block_bytes(&self, region: Dims3) -> (u64, Dims3) {
        region_block_bytes(
            &self.filter,
            self.meta.dims,
            self.block,
            region,
            self.inner.meta().dtype.size(),
        )
    }

    /// Compute this stage's reads on the device of `k`, in f32 (see
    /// [`crate::gpu`] for the tolerance against the CPU's f64). A region is
    /// computed in pieces of at most [`FilterKernels::max_voxels`] padded
    /// voxels: its input is read and padded on the CPU, the piece computed
    /// on the device. A stage whose halo alone exceeds that (a Gaussian of
    /// σ ≳ 25 voxels on every axis) stays on the CPU.
    pub fn with_device(mut self, k: &Arc<FilterKernels>) -> FilterSource {
        let max_voxels = k.max_voxels();
        let h = self.filter.halo();
        // A median has no device kernel: it stays on the CPU.
        if matches!(self.filter, Filter::Median(_)) {
            return self;
        }
        if h.iter().map(|&v| 2 * v as u64 + 1).product::<u64>() <= max_voxels {
            self.device = Some(DeviceStage {
                filter: Mutex::new(DeviceFilter::new(k.clone(), self.filter.clone())),
                max_voxels,
            });
        }
        self
    }

    /// Whether reads compute on the device.
    pub fn on_device(&self) -> bool {
        self.device.is_some()
    }

    pub fn filter(&self) -> &Filter {
        &self.filter
    }

    /// The box `want` grown by the halo, read from the inner source as `R`,
    /// with the halo outside the volume filled by the boundary mode; and its
    /// dimensions.
    fn padded<R: Real>(&self, want: &[Range<u64>; 3]) -> Result<(Vec<R>, [usize; 3])> {
        let h = self.filter.halo();
        let d = self.meta.dims;
        // The padded box, and the part of it inside the volume.
        let lo: [i64; 3] = [0, 1, 2].map(|a| want[a].start as i64 - h[a] as i64);
        let hi: [i64; 3] = [0, 1, 2].map(|a| want[a].end as i64 + h[a] as i64);
        let rlo: [u64; 3] = [0, 1, 2].map(|a| lo[a].max(0) as u64);
        let rhi: [u64; 3] = [0, 1, 2].map(|a| (hi[a] as u64).min(d[a]));
        let rd: [usize; 3] = [0, 1, 2].map(|a| (rhi[a] - rlo[a]) as usize);
        let read: Vec<R> = dispatch_dtype!(self.inner.meta().dtype, T => {
            read_as::<T, R>(self.inner.as_ref(), self.channel, [rlo[0]..rhi[0], rlo[1]..rhi[1], rlo[2]..rhi[2]], rd)?
        });
        let pd: [usize; 3] = [0, 1, 2].map(|a| (hi[a] - lo[a]) as usize);
        if pd == rd {
            return Ok((read, pd));
        }
        // Boundary mode "nearest": clamp the coordinate into the volume.
        let idx = |a: usize| -> Vec<usize> {
            (lo[a]..hi[a])
                .map(|g| (g.clamp(0, d[a] as i64 - 1) as u64 - rlo[a]) as usize)
                .collect()
        };
        let (iz, iy, ix) = (idx(0), idx(1), idx(2));
        let mut p = Vec::with_capacity(pd.iter().product());
        for &zz in &iz {
            for &yy in &iy {
                let row = (zz * rd[1] + yy) * rd[2];
                p.extend(ix.iter().map(|&xx| read[row + xx]));
            }
        }
        Ok((p, pd))
    }

    /// Values of one block, computed from the inner source on the CPU: the
    /// block's box grown by the halo is read as far as it lies in the
    /// volume, and taps beyond it read the edge voxel (boundary mode
    /// "nearest", without padding the box: a halo as wide as the volume
    /// costs no more than the volume).
    fn compute(&self, b: &[Range<u64>; 3]) -> Result<Vec<f64>> {
        let h = self.filter.halo();
        let d = self.meta.dims;
        let rlo: [u64; 3] = [0, 1, 2].map(|a| b[a].start.saturating_sub(h[a] as u64));
        let rhi: [u64; 3] = [0, 1, 2].map(|a| (b[a].end + h[a] as u64).min(d[a]));
        let rd: [usize; 3] = [0, 1, 2].map(|a| (rhi[a] - rlo[a]) as usize);
        let read: Vec<f64> = dispatch_dtype!(self.inner.meta().dtype, T => {
            read_as::<T, f64>(self.inner.as_ref(), self.channel, [rlo[0]..rhi[0], rlo[1]..rhi[1], rlo[2]..rhi[2]], rd)?
        });
        let first = [0, 1, 2].map(|a| (b[a].start - rlo[a]) as i64);
        let len = [0, 1, 2].map(|a| (b[a].end - b[a].start) as usize);
        let v = self.filter.apply_with(
            self.components.clone(),
            read,
            rd,
            first,
            len,
            self.stop.as_deref(),
        );
        // (A median stopped halfway is thrown away.)
        self.stopped()?;
        Ok(v)
    }

    /// Values of one piece, computed on the device.
    fn compute_device(&self, dev: &DeviceStage, b: &[Range<u64>; 3]) -> Result<Vec<f32>> {
        let (padded, pd) = self.padded::<f32>(b)?;
        let fail = |e: String| {
            StoreError::io(
                &self.meta.path,
                std::io::Error::other(format!("computing on the device: {e}")),
            )
        };
        let mut f = dev.filter.lock().map_err(|e| fail(e.to_string()))?;
        Ok(f.apply(&padded, pd).map_err(|e| fail(e.to_string()))?.0)
    }

    /// Cut region `r` into pieces whose padded boxes have at most
    /// `max_voxels` voxels: halve the longest side until one fits.
    fn device_pieces(&self, r: &[Range<u64>; 3], max_voxels: u64) -> Vec<[Range<u64>; 3]> {
        let h = self.filter.halo();
        let mut p: [u64; 3] = [0, 1, 2].map(|a| r[a].end - r[a].start);
        let padded = |p: &[u64; 3]| (0..3).map(|a| p[a] + 2 * h[a] as u64).product::<u64>();
        while padded(&p) > max_voxels {
            // `with_device` made sure that a single voxel fits.
            let a = (0..3).max_by_key(|&a| p[a]).unwrap();
            p[a] = p[a].div_ceil(2);
        }
        tile(r, p)
    }
}

/// Read a region of `src` as f64.
pub(crate) fn read_f64<T: Sample>(
    src: &dyn VolumeSource,
    c: usize,
    r: [Range<u64>; 3],
    rd: [usize; 3],
) -> Result<Vec<f64>> {
    read_as::<T, f64>(src, c, r, rd)
}

/// Read a region of `src` as `R` (each value rounded once).
fn read_as<T: Sample, R: Real>(
    src: &dyn VolumeSource,
    c: usize,
    r: [Range<u64>; 3],
    rd: [usize; 3],
) -> Result<Vec<R>> {
    let mut buf = vec![T::default(); rd.iter().product()];
    let [z, y, x] = r;
    src.read_region(c, z, y, x, as_bytes_mut(&mut buf))?;
    Ok(buf.into_iter().map(|v| R::from_f64(v.to_f64())).collect())
}

/// The blocks of at most `block` voxels that tile a region, as
/// `[z, y, x]` ranges.
pub(crate) fn tile(r: &[Range<u64>; 3], block: Dims3) -> Vec<[Range<u64>; 3]> {
    let mut v = vec![];
    let steps = |a: usize| {
        let rr = r[a].clone();
        (rr.start..rr.end)
            .step_by(block[a] as usize)
            .map(move |s| s..(s + block[a]).min(rr.end))
    };
    for bz in steps(0) {
        for by in steps(1) {
            for bx in steps(2) {
                v.push([bz.clone(), by.clone(), bx]);
            }
        }
    }
    v
}

/// Cut a region into about `len / block` near-equal pieces per axis
/// (at least one; pieces up to 1.5 blocks long). A region one halo larger
/// than a block — what the next stage asks for — stays one piece instead of
/// a block and a sliver that would need its own halo.
pub(crate) fn split(r: &[Range<u64>; 3], block: Dims3) -> Vec<[Range<u64>; 3]> {
    let cuts = |a: usize| -> Vec<Range<u64>> {
        let len = r[a].end - r[a].start;
        let n = ((len + block[a] / 2) / block[a]).max(1);
        (0..n)
            .map(|i| r[a].start + len * i / n..r[a].start + len * (i + 1) / n)
            .filter(|p| p.end > p.start)
            .collect()
    };
    let (cz, cy, cx) = (cuts(0), cuts(1), cuts(2));
    let mut v = vec![];
    for z in &cz {
        for y in &cy {
            for x in &cx {
                v.push([z.clone(), y.clone(), x.clone()]);
            }
        }
    }
    v
}

/// Copy a dense block `b` (box `bb`) into `out` (box `r`), as `T`.
pub(crate) fn place<T: Copy>(out: &mut [T], r: &[Range<u64>; 3], bb: &[Range<u64>; 3], b: &[T]) {
    let (ry, rx) = (r[1].end - r[1].start, r[2].end - r[2].start);
    let (by, bx) = (bb[1].end - bb[1].start, bb[2].end - bb[2].start);
    for z in 0..bb[0].end - bb[0].start {
        for y in 0..by {
            let s = ((z * by + y) * bx) as usize;
            let d = (((bb[0].start - r[0].start + z) * ry + bb[1].start - r[1].start + y) * rx
                + bb[2].start
                - r[2].start) as usize;
            out[d..d + bx as usize].copy_from_slice(&b[s..s + bx as usize]);
        }
    }
}

impl VolumeSource for FilterSource {
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
        let r = [z, y, x];
        if let Some(dev) = &self.device {
            // The pieces' inputs are read and padded in parallel; the device
            // computes one piece at a time.
            let pieces = self.device_pieces(&r, dev.max_voxels);
            let vals: Vec<Result<Vec<f32>>> = pieces
                .par_iter()
                .map(|b| {
                    self.stopped()?;
                    let v = self.compute_device(dev, b)?;
                    self.count(b);
                    Ok(v)
                })
                .collect();
            for (b, v) in pieces.iter().zip(vals) {
                let v = v?;
                match self.meta.dtype {
                    DType::F32 => place(brickyard_core::cast_slice_mut::<f32>(out), &r, b, &v),
                    DType::U8 => {
                        let m: Vec<u8> = v.into_iter().map(|x| x as u8).collect();
                        place(out, &r, b, &m)
                    }
                    t => unreachable!("filters write f32 or u8, not {t}"),
                }
            }
            return Ok(());
        }
        let blocks = split(&r, self.block);
        // Each block is cast to the output type as soon as it is computed
        // (the f64 values of a whole region are never held at once), and at
        // most `parallel` blocks are computed at once.
        for group in blocks.chunks(self.parallel) {
            match self.meta.dtype {
                DType::F32 => {
                    let vals: Vec<Result<Vec<f32>>> = group
                        .par_iter()
                        .map(|b| {
                            self.stopped()?;
                            let v = self.compute(b)?;
                            self.count(b);
                            Ok(v.into_iter().map(|x| x as f32).collect())
                        })
                        .collect();
                    let o = brickyard_core::cast_slice_mut::<f32>(out);
                    for (b, v) in group.iter().zip(vals) {
                        place(o, &r, b, &v?);
                    }
                }
                DType::U8 => {
                    let vals: Vec<Result<Vec<u8>>> = group
                        .par_iter()
                        .map(|b| {
                            self.stopped()?;
                            let v = self.compute(b)?;
                            self.count(b);
                            Ok(v.into_iter().map(|x| x as u8).collect())
                        })
                        .collect();
                    for (b, v) in group.iter().zip(vals) {
                        place(out, &r, b, &v?);
                    }
                }
                t => unreachable!("filters write f32 or u8, not {t}"),
            }
        }
        Ok(())
    }

    fn preferred_read(&self) -> Dims3 {
        self.block
    }
}
