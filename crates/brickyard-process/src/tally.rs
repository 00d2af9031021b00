//! The statistics table of a label image that was not labelled here (one
//! converted from a file with `convert --labels`): one pass over its voxels
//! gives each label's voxel count, bounding box, centroid and, given the
//! image it labels, mean intensity — the table `process` writes for the
//! labels it makes ([`brickyard_core::label_table`]).
//!
//! The volume is read in blocks, several at once; each block is tallied on
//! its own and merged into one table per label. The table is bounded:
//! beyond `max_bytes` of it the pass stops and says so (a label image of
//! many millions of labels then has no table, and stays usable).

use brickyard_core::label_table::LabelRow;
use brickyard_core::{dispatch_dtype, DType, Dims3, Sample};
use brickyard_store::{Progress, Result, StoreError, VolumeSource};
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};

/// What one label accumulates.
#[derive(Clone, Debug)]
struct Tally {
    voxels: u64,
    min: [u64; 3],
    max: [u64; 3],
    sum: [f64; 3],
    sum_i: f64,
}

impl Tally {
    fn at(p: [u64; 3]) -> Tally {
        Tally {
            voxels: 0,
            min: p,
            max: p,
            sum: [0.0; 3],
            sum_i: 0.0,
        }
    }

    /// Add the run of `k` voxels from `p` along x, whose values sum to
    /// `v`.
    fn add_run(&mut self, p: [u64; 3], k: u64, v: f64) {
        let last = [p[0], p[1], p[2] + k - 1];
        self.voxels += k;
        for a in 0..3 {
            self.min[a] = self.min[a].min(p[a]);
            self.max[a] = self.max[a].max(last[a]);
        }
        let kf = k as f64;
        self.sum[0] += p[0] as f64 * kf;
        self.sum[1] += p[1] as f64 * kf;
        self.sum[2] += p[2] as f64 * kf + kf * (kf - 1.0) / 2.0;
        self.sum_i += v;
    }

    fn merge(&mut self, o: &Tally) {
        self.voxels += o.voxels;
        for a in 0..3 {
            self.min[a] = self.min[a].min(o.min[a]);
            self.max[a] = self.max[a].max(o.max[a]);
            self.sum[a] += o.sum[a];
        }
        self.sum_i += o.sum_i;
    }
}

/// Bytes the table takes per label (its entry in the map, with the map's
/// spare room counted).
pub const BYTES_PER_LABEL: u64 = 160;

/// Why a label image has no table.
#[derive(Debug, Clone, PartialEq)]
pub enum NoTable {
    /// More labels than `max_bytes` holds: how many were met by then.
    TooMany { labels: u64, max_bytes: u64 },
    /// A voxel holds a value that is not a label (negative, or not a whole
    /// number): the first such, and where (`[z, y, x]`).
    NotALabel { value: f64, at: Dims3 },
}

impl std::fmt::Display for NoTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NoTable::TooMany { labels, max_bytes } => write!(
                f,
                "more than {labels} labels: their table would take more than {} MiB \
                 ({BYTES_PER_LABEL} bytes a label)",
                max_bytes >> 20
            ),
            NoTable::NotALabel { value, at } => write!(
                f,
                "voxel {at:?} (z, y, x) holds {value}, not a label (a whole number, 0 or more)"
            ),
        }
    }
}

/// The rows of the table of `labels` (channel 0, label 0 the background
/// and left out), in increasing label order; with `intensity` (a volume on
/// the same grid and its channel), each row's mean is the mean of its
/// values under the label. Blocks of `block` voxels are read, twice as
/// many at once as there are threads (each holds 16 bytes a voxel beside
/// what it reads); `progress` counts the label image's bytes.
/// `Ok(Err(..))`: the image has no table, and why.
pub fn tally(
    labels: &dyn VolumeSource,
    intensity: Option<(&dyn VolumeSource, usize)>,
    block: Dims3,
    max_bytes: u64,
    progress: &dyn Progress,
    cancel: &AtomicBool,
) -> Result<std::result::Result<Vec<(u64, LabelRow)>, NoTable>> {
    let m = labels.meta();
    let dims = m.dims;
    if let Some((im, _)) = intensity {
        if im.meta().dims != dims {
            return Err(StoreError::invalid(
                &im.meta().path,
                "shape",
                format!(
                    "{:?} (z, y, x), the label image {dims:?}: a mean intensity needs one grid",
                    im.meta().dims
                ),
            ));
        }
    }
    let b = block.map(|v| v.max(1));
    let n = [0, 1, 2].map(|a| dims[a].div_ceil(b[a]));
    let blocks: Vec<Dims3> = (0..n[0])
        .flat_map(|z| (0..n[1]).flat_map(move |y| (0..n[2]).map(move |x| [z, y, x])))
        .collect();
    progress.start(dims.iter().product::<u64>() * m.dtype.size() as u64);
    let mut table: HashMap<u64, Tally> = HashMap::new();
    let per = rayon::current_num_threads().max(1) * 2;
    for batch in blocks.chunks(per) {
        if cancel.load(Ordering::SeqCst) {
            return Err(StoreError::Interrupted);
        }
        let parts: Vec<Result<std::result::Result<HashMap<u64, Tally>, NoTable>>> = batch
            .par_iter()
            .map(|&bi| {
                let lo = [0, 1, 2].map(|a| bi[a] * b[a]);
                let hi = [0, 1, 2].map(|a| (lo[a] + b[a]).min(dims[a]));
                let part = tally_block(labels, intensity, lo, hi);
                progress
                    .inc((0..3).map(|a| hi[a] - lo[a]).product::<u64>() * m.dtype.size() as u64);
                part
            })
            .collect();
        for part in parts {
            let part = match part? {
                Ok(p) => p,
                Err(why) => return Ok(Err(why)),
            };
            for (id, t) in part {
                table.entry(id).and_modify(|e| e.merge(&t)).or_insert(t);
            }
            let labels = table.len() as u64;
            if labels.saturating_mul(BYTES_PER_LABEL) > max_bytes {
                return Ok(Err(NoTable::TooMany { labels, max_bytes }));
            }
        }
    }
    let mut rows: Vec<(u64, LabelRow)> = table
        .into_iter()
        .map(|(id, t)| {
            let n = t.voxels as f64;
            let row = LabelRow {
                voxels: t.voxels,
                min: t.min,
                max: t.max,
                centroid: t.sum.map(|s| s / n),
                mean: intensity.map(|_| t.sum_i / n),
            };
            (id, row)
        })
        .collect();
    rows.sort_unstable_by_key(|r| r.0);
    Ok(Ok(rows))
}

/// The tallies of the block `lo..hi` (`[z, y, x]`).
fn tally_block(
    labels: &dyn VolumeSource,
    intensity: Option<(&dyn VolumeSource, usize)>,
    lo: Dims3,
    hi: Dims3,
) -> Result<std::result::Result<HashMap<u64, Tally>, NoTable>> {
    let d = [0, 1, 2].map(|a| (hi[a] - lo[a]) as usize);
    let len = d[0] * d[1] * d[2];
    let read = |src: &dyn VolumeSource, c: usize| -> Result<Vec<u8>> {
        let mut buf = vec![0u8; len * src.meta().dtype.size()];
        src.read_region(c, lo[0]..hi[0], lo[1]..hi[1], lo[2]..hi[2], &mut buf)?;
        Ok(buf)
    };
    let ids = match as_ids(labels.meta().dtype, &read(labels, 0)?) {
        Ok(ids) => ids,
        Err((i, value)) => {
            let at = [
                lo[0] + (i / (d[1] * d[2])) as u64,
                lo[1] + (i / d[2] % d[1]) as u64,
                lo[2] + (i % d[2]) as u64,
            ];
            return Ok(Err(NoTable::NotALabel { value, at }));
        }
    };
    let values: Option<Vec<f64>> = match intensity {
        Some((im, c)) => Some(as_f64(im.meta().dtype, &read(im, c)?)),
        None => None,
    };
    let mut out: HashMap<u64, Tally> = HashMap::new();
    // Runs of one label along x, added at once.
    let row = d[2];
    for z in 0..d[0] {
        for y in 0..d[1] {
            let at = (z * d[1] + y) * row;
            let mut x = 0;
            while x < row {
                let p = [lo[0] + z as u64, lo[1] + y as u64, lo[2] + x as u64];
                let id = ids[at + x];
                let mut end = x + 1;
                while end < row && ids[at + end] == id {
                    end += 1;
                }
                if id != 0 {
                    let v = values
                        .as_ref()
                        .map_or(0.0, |v| v[at + x..at + end].iter().sum::<f64>());
                    out.entry(id)
                        .or_insert_with(|| Tally::at(p))
                        .add_run(p, (end - x) as u64, v);
                }
                x = end;
            }
        }
    }
    Ok(Ok(out))
}

/// The labels of native-endian voxels of `dtype` (whole numbers, 0 or
/// more), or the first voxel that is not one: its index and value.
fn as_ids(dtype: DType, bytes: &[u8]) -> std::result::Result<Vec<u64>, (usize, f64)> {
    dispatch_dtype!(dtype, T => {
        bytes
            .chunks_exact(std::mem::size_of::<T>())
            .enumerate()
            .map(|(i, c)| {
                let v = <T as Sample>::from_le(c).to_f64();
                if v >= 0.0 && v.fract() == 0.0 && v < u64::MAX as f64 {
                    Ok(v as u64)
                } else {
                    Err((i, v))
                }
            })
            .collect()
    })
}

/// Native-endian voxels of `dtype` as f64.
fn as_f64(dtype: DType, bytes: &[u8]) -> Vec<f64> {
    dispatch_dtype!(dtype, T => {
        bytes
            .chunks_exact(std::mem::size_of::<T>())
            .map(|c| <T as Sample>::from_le(c).to_f64())
            .collect()
    })
}
