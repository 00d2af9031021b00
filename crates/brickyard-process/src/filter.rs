//! Filter stages as volume sources: reading a region of a stage reads the
//! region plus the stage's halo from the stage before it, fills the halo
//! outside the volume with the boundary mode, and computes.
//!
//! Boundary mode: `nearest` everywhere (scipy's `mode="nearest"`: the edge
//! voxel repeated), for every stage, also on the results of earlier stages,
//! which is what scipy does when stages are applied one after the other.

use crate::kernels::{gaussian_weights, magnitude, separable, SOBEL_D, SOBEL_S};
use brickyard_core::{as_bytes_mut, dispatch_dtype, DType, Dims3, Sample};
use brickyard_store::source::check_region;
use brickyard_store::{Result, SourceMeta, VolumeSource};
use rayon::prelude::*;
use std::ops::Range;
use std::sync::Arc;

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
}

impl Filter {
    /// Voxel type of the result.
    pub fn out_dtype(&self) -> DType {
        match self {
            Filter::Gauss(_) | Filter::GradMag(_) | Filter::Sobel => DType::F32,
            Filter::Threshold(_) | Filter::Window(..) => DType::U8,
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
            Filter::Threshold(_) | Filter::Window(..) => [0; 3],
        }
    }

    /// Compute on a block padded by [`Filter::halo`]; `dims` are the padded
    /// dimensions. Returns the block's values (f64).
    pub fn apply(&self, data: Vec<f64>, dims: [usize; 3]) -> Vec<f64> {
        match self {
            Filter::Gauss(s) => {
                let w = s.map(|v| gaussian_weights(v, 0, TRUNCATE));
                separable(data, dims, [&w[0], &w[1], &w[2]]).0
            }
            Filter::GradMag(s) => {
                let g = s.map(|v| gaussian_weights(v, 0, TRUNCATE));
                let d = s.map(|v| gaussian_weights(v, 1, TRUNCATE));
                magnitude(
                    &data,
                    dims,
                    [
                        [&d[0], &g[1], &g[2]],
                        [&g[0], &d[1], &g[2]],
                        [&g[0], &g[1], &d[2]],
                    ],
                )
                .0
            }
            Filter::Sobel => {
                magnitude(
                    &data,
                    dims,
                    [
                        [&SOBEL_D, &SOBEL_S, &SOBEL_S],
                        [&SOBEL_S, &SOBEL_D, &SOBEL_S],
                        [&SOBEL_S, &SOBEL_S, &SOBEL_D],
                    ],
                )
                .0
            }
            Filter::Threshold(t) => data
                .into_iter()
                .map(|v| if v > *t { 1.0 } else { 0.0 })
                .collect(),
            Filter::Window(lo, hi) => data
                .into_iter()
                .map(|v| if *lo <= v && v <= *hi { 1.0 } else { 0.0 })
                .collect(),
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
}

impl FilterSource {
    pub fn new(
        inner: Arc<dyn VolumeSource>,
        channel: usize,
        filter: Filter,
        name: &str,
        block: Dims3,
    ) -> FilterSource {
        let im = inner.meta();
        let mut meta = SourceMeta::new(im.path.join(name), im.dims, 1, filter.out_dtype());
        meta.spacing = im.spacing;
        meta.origin = im.origin;
        meta.unit = im.unit.clone();
        meta.labels = matches!(filter, Filter::Threshold(_) | Filter::Window(..));
        meta.notes = im.notes.clone();
        FilterSource {
            inner,
            channel,
            filter,
            meta,
            block: block.map(|b| b.max(1)),
        }
    }

    pub fn filter(&self) -> &Filter {
        &self.filter
    }

    /// Values of one block, computed from the inner source.
    fn compute(&self, z: Range<u64>, y: Range<u64>, x: Range<u64>) -> Result<Vec<f64>> {
        let h = self.filter.halo();
        let d = self.meta.dims;
        let want = [z, y, x];
        // The padded box, and the part of it inside the volume.
        let lo: [i64; 3] = [0, 1, 2].map(|a| want[a].start as i64 - h[a] as i64);
        let hi: [i64; 3] = [0, 1, 2].map(|a| want[a].end as i64 + h[a] as i64);
        let rlo: [u64; 3] = [0, 1, 2].map(|a| lo[a].max(0) as u64);
        let rhi: [u64; 3] = [0, 1, 2].map(|a| (hi[a] as u64).min(d[a]));
        let rd: [usize; 3] = [0, 1, 2].map(|a| (rhi[a] - rlo[a]) as usize);
        let read: Vec<f64> = dispatch_dtype!(self.inner.meta().dtype, T => {
            read_f64::<T>(self.inner.as_ref(), self.channel, [rlo[0]..rhi[0], rlo[1]..rhi[1], rlo[2]..rhi[2]], rd)?
        });
        let pd: [usize; 3] = [0, 1, 2].map(|a| (hi[a] - lo[a]) as usize);
        let padded = if pd == rd {
            read
        } else {
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
            p
        };
        Ok(self.filter.apply(padded, pd))
    }
}

/// Read a region of `src` as f64.
pub(crate) fn read_f64<T: Sample>(
    src: &dyn VolumeSource,
    c: usize,
    r: [Range<u64>; 3],
    rd: [usize; 3],
) -> Result<Vec<f64>> {
    let mut buf = vec![T::default(); rd.iter().product()];
    let [z, y, x] = r;
    src.read_region(c, z, y, x, as_bytes_mut(&mut buf))?;
    Ok(buf.into_iter().map(Sample::to_f64).collect())
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
        let blocks = split(&r, self.block);
        // Each block is cast to the output type as soon as it is computed
        // (the f64 values of a whole region are never held at once).
        match self.meta.dtype {
            DType::F32 => {
                let vals: Vec<Result<Vec<f32>>> = blocks
                    .par_iter()
                    .map(|b| {
                        let v = self.compute(b[0].clone(), b[1].clone(), b[2].clone())?;
                        Ok(v.into_iter().map(|x| x as f32).collect())
                    })
                    .collect();
                let o = brickyard_core::cast_slice_mut::<f32>(out);
                for (b, v) in blocks.iter().zip(vals) {
                    place(o, &r, b, &v?);
                }
            }
            DType::U8 => {
                let vals: Vec<Result<Vec<u8>>> = blocks
                    .par_iter()
                    .map(|b| {
                        let v = self.compute(b[0].clone(), b[1].clone(), b[2].clone())?;
                        Ok(v.into_iter().map(|x| x as u8).collect())
                    })
                    .collect();
                for (b, v) in blocks.iter().zip(vals) {
                    place(out, &r, b, &v?);
                }
            }
            t => unreachable!("filters write f32 or u8, not {t}"),
        }
        Ok(())
    }

    fn preferred_read(&self) -> Dims3 {
        self.block
    }
}
