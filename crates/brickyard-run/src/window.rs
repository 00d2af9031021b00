//! The default data window of `render` and `view`: robust percentiles of
//! the values, so that a CT shows tissue rather than the cylinder of its
//! field of view, and a microscopy stack its cells rather than a few hot
//! pixels.

use anyhow::Result;
use brickyard_core::{as_bytes_mut, dispatch_dtype, Sample};
use brickyard_store::import::zarr;
use brickyard_store::VolumeSource;
use std::path::Path;

/// Voxels looked at most: the finest level at or under this is read.
const MAX_VOXELS: u64 = 1 << 22;
/// Values kept at most (every k-th voxel of the level, in its order): 8 MiB
/// of `f64`s.
const MAX_SAMPLES: u64 = 1 << 20;
/// Voxels read at once: whole planes, as many as the source reads at once
/// (a store's chunk depth, so that no chunk is decoded twice) or more.
const SLAB_VOXELS: u64 = 1 << 18;

/// The window of `values`: the 0.5th and 99.5th percentiles of the finite
/// values, leaving out a value that fills more than 5 % of the volume at
/// either end of the range (padding, the outside of a scanner's field of
/// view, an empty background). `None` without two distinct values.
pub fn robust_window(mut values: Vec<f64>) -> Option<(f64, f64)> {
    values.retain(|v| v.is_finite());
    if values.is_empty() {
        return None;
    }
    values.sort_unstable_by(|a, b| a.total_cmp(b));
    let n = values.len();
    let (min, max) = (values[0], values[n - 1]);
    if min == max {
        return None;
    }
    let run = |v: f64| {
        let lo = values.partition_point(|x| *x < v);
        let hi = values.partition_point(|x| *x <= v);
        (lo, hi)
    };
    let (mut a, mut b) = (0, n);
    let (_, min_end) = run(min);
    if min_end * 20 > n {
        a = min_end;
    }
    let (max_start, _) = run(max);
    if (n - max_start) * 20 > n {
        b = max_start;
    }
    if b <= a {
        return Some((min, max));
    }
    let s = &values[a..b];
    let q = |f: f64| s[((s.len() - 1) as f64 * f).round() as usize];
    let (lo, hi) = (q(0.005), q(0.995));
    if hi > lo {
        Some((lo, hi))
    } else {
        Some((s[0], s[s.len() - 1]))
            .filter(|(l, h)| h > l)
            .or(Some((min, max)))
    }
}

/// The default window of channel `c` of `store`, from the finest level of
/// at most four million voxels (every voxel, or every k-th beyond a million,
/// read slab by slab). A level that cannot be read
/// (a damaged chunk) gives way to the next coarser one; `None` when none
/// can be read.
pub fn auto_window(store: &Path, levels: usize, c: usize) -> Result<Option<(f64, f64)>> {
    let w = window_of_levels(levels, c, |l| {
        Ok(std::sync::Arc::new(zarr::open(store, l)?) as std::sync::Arc<dyn VolumeSource>)
    });
    give_back_freed_memory();
    w
}

/// Return the memory the window's reads freed to the system: the decoder
/// threads' heaps kept it (a float32 tomogram's window left 16 MiB resident
/// beside the budget's shares, which later allocations did not reuse).
pub fn give_back_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free heap pages to the system.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Like [`auto_window`], over the levels `open(l)` gives (finest first):
/// a store's, or those of a derived channel.
pub fn window_of_levels(
    levels: usize,
    c: usize,
    open: impl Fn(usize) -> Result<std::sync::Arc<dyn VolumeSource>>,
) -> Result<Option<(f64, f64)>> {
    window_of_levels_in(levels, c, None, open)
}

/// [`window_of_levels`], each read at most `limit` voxels `[z, y, x]` (a
/// derived channel, whose filters' memory is planned for reads of a
/// brick: slabs of whole planes went 33 MiB past an 80 MiB --memory).
pub fn window_of_levels_in(
    levels: usize,
    c: usize,
    limit: Option<[u64; 3]>,
    open: impl Fn(usize) -> Result<std::sync::Arc<dyn VolumeSource>>,
) -> Result<Option<(f64, f64)>> {
    for l in 0..levels {
        // A level that cannot be opened gives way as one that cannot be
        // read does (the render's own reads then say what is wrong).
        let Ok(src) = open(l) else {
            continue;
        };
        let m = src.meta().clone();
        let [z, y, x] = m.dims;
        if z * y * x > MAX_VOXELS {
            continue;
        }
        // Read region by region and keep every `stride`-th value in read
        // order: what this takes stays a few MiB (the level whole as `f64`s
        // beside its own copy went over small budgets by up to 64 MiB).
        // Regions are slabs of whole planes (raster order), or at most
        // `limit` where given.
        let n = z * y * x;
        let stride = n.div_ceil(MAX_SAMPLES).max(1);
        let depth = src.preferred_read()[0].max(1);
        let planes = (SLAB_VOXELS / (y * x).max(1)).div_ceil(depth).max(1) * depth;
        let [bz, by, bx] = limit.unwrap_or([planes, y, x]).map(|v| v.max(1));
        let values: Option<Vec<f64>> = dispatch_dtype!(m.dtype, T => {
            let mut values = Vec::with_capacity(n.div_ceil(stride) as usize);
            let mut buf = vec![];
            let mut seen = 0u64;
            let mut ok = true;
            'read: for z0 in (0..z).step_by(bz as usize) {
                for y0 in (0..y).step_by(by as usize) {
                    for x0 in (0..x).step_by(bx as usize) {
                        let (z1, y1, x1) = ((z0 + bz).min(z), (y0 + by).min(y), (x0 + bx).min(x));
                        buf.clear();
                        buf.resize(((z1 - z0) * (y1 - y0) * (x1 - x0)) as usize, T::default());
                        if src.read_region(c, z0..z1, y0..y1, x0..x1, as_bytes_mut(&mut buf)).is_err() {
                            ok = false;
                            break 'read;
                        }
                        // The first value whose index counted from the
                        // start is a multiple of the stride.
                        let skip = (seen.div_ceil(stride) * stride - seen) as usize;
                        values.extend(buf.iter().skip(skip).step_by(stride as usize).map(|v| v.to_f64()));
                        seen += buf.len() as u64;
                    }
                }
            }
            ok.then_some(values)
        });
        if let Some(v) = values {
            return Ok(robust_window(v));
        }
    }
    Ok(None)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_ct_like_volume_leaves_out_its_padding_and_outliers() {
        // 30 % padding at -3024, air around -1000, tissue 0..100, a few
        // metal voxels at 3000.
        let mut v = vec![-3024.0; 3000];
        v.extend((0..3000).map(|i| -1000.0 + (i % 20) as f64));
        v.extend((0..3990).map(|i| (i % 100) as f64));
        v.extend([3000.0; 10]);
        let (lo, hi) = robust_window(v).unwrap();
        assert!((-1000.0..=-990.0).contains(&lo), "{lo}");
        assert!((90.0..=99.0).contains(&hi), "{hi}");
    }

    /// A level of more than [`MAX_SAMPLES`] voxels is read in slabs and
    /// every k-th voxel kept: the same values as taking every k-th voxel
    /// of the level read whole.
    #[test]
    fn large_levels_are_sampled_slab_by_slab() {
        use brickyard_store::generate::{Kind, Procedural};
        let dims = [150, 161, 170]; // 4.1 M voxels: every 4th kept
        let src = Procedural::new(Kind::Mandelbulb, dims, brickyard_core::DType::F32);
        let mut all = vec![0f32; (dims[0] * dims[1] * dims[2]) as usize];
        src.read_region(
            0,
            0..dims[0],
            0..dims[1],
            0..dims[2],
            as_bytes_mut(&mut all),
        )
        .unwrap();
        let every4: Vec<f64> = all.iter().step_by(4).map(|&v| v as f64).collect();
        let want = robust_window(every4).unwrap();
        let src: std::sync::Arc<dyn VolumeSource> = std::sync::Arc::new(src);
        let got = window_of_levels(1, 0, |_| Ok(src.clone()))
            .unwrap()
            .unwrap();
        assert_eq!(got, want);
        // And close to the window of every voxel.
        let full = robust_window(all.iter().map(|&v| v as f64).collect()).unwrap();
        assert!((full.0 - got.0).abs() < 0.01 && (full.1 - got.1).abs() < 0.01);
    }

    #[test]
    fn plain_ranges_and_degenerate_inputs() {
        let v: Vec<f64> = (0..1001).map(|i| i as f64).collect();
        let (lo, hi) = robust_window(v).unwrap();
        assert_eq!((lo, hi), (5.0, 995.0));
        assert_eq!(robust_window(vec![7.0; 10]), None);
        assert_eq!(robust_window(vec![f64::NAN; 3]), None);
        // Two values, both frequent: the whole range.
        let mut v = vec![0.0; 50];
        v.extend([1.0; 50]);
        assert_eq!(robust_window(v), Some((0.0, 1.0)));
    }
}
