//! A level's per-brick statistics as the store keeps them
//! (`_brickyard/stats/<level>`): what each store brick holds, read one
//! Zarr chunk at a time. Readers use them to cross bricks they need not
//! load, and to tell a lost chunk (read back as the fill value) from one
//! that holds zeros.

use crate::error::{Result, StoreError};
use crate::source::{Absence, VolumeSource};
use crate::storage::{self, StoreAt};
pub use brickyard_core::brick_stats::{finite_range, recorded};
use brickyard_core::Dims3;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use zarrs::array::Array;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Per-brick statistics of one level: `[C, bz, by, bx, 2]` float64 (min,
/// max), read lazily one Zarr chunk at a time.
pub struct LevelStats {
    array: Array<StoreAt>,
    /// Store brick size.
    pub brick: Dims3,
    /// Chunk shape of the statistics array (first four axes).
    chunk: [u64; 4],
    /// Decoded chunks (`None`: the chunk could not be read; the bricks it
    /// covers are treated as unknown). At most the size of the statistics
    /// array, 16 bytes per store brick and channel.
    chunks: Mutex<HashMap<[u64; 4], StatsChunk>>,
    /// The statistics array's folder, for reports.
    dir: PathBuf,
    /// What made chunks unreadable, once each (reported by
    /// [`Loader::take_stats_problems`]).
    problems: Mutex<Vec<String>>,
}

/// Whether every byte of `b` is 0, eight at a time (no early exit within
/// the slice: a row is short, and the OR of its words runs without
/// branches).
fn all_zero(b: &[u8]) -> bool {
    let words = b.chunks_exact(8);
    let rest = words.remainder().iter().fold(0u8, |a, &x| a | x);
    let or = words.fold(0u64, |a, w| {
        a | u64::from_ne_bytes(w.try_into().expect("8 bytes"))
    });
    or == 0 && rest == 0
}

/// A read as the checks see it: the voxels `[lo, hi)` of a level, placed
/// at `at` in a box of `dims` voxels (`[z, y, x]`) of `es` bytes each,
/// held in `buf`.
pub struct ReadBox<'a> {
    pub lo: Dims3,
    pub hi: Dims3,
    pub buf: &'a [u8],
    pub dims: Dims3,
    pub at: Dims3,
    pub es: u64,
}

impl ReadBox<'_> {
    fn is_empty(&self) -> bool {
        (0..3).any(|a| self.lo[a] >= self.hi[a])
    }

    /// The part `[blo, bhi)` of store brick `b` (bricks of `sb`) inside
    /// the read.
    fn part(&self, b: Dims3, sb: Dims3) -> (Dims3, Dims3) {
        (
            [0, 1, 2].map(|a| (b[a] * sb[a]).max(self.lo[a])),
            [0, 1, 2].map(|a| ((b[a] + 1) * sb[a]).min(self.hi[a])),
        )
    }

    /// The bytes of voxels `x0..x1` of row `(z, y)` (level coordinates).
    fn row(&self, z: u64, y: u64, x0: u64, x1: u64) -> &[u8] {
        let (lo, at, d) = (self.lo, self.at, self.dims);
        let i = (((z - lo[0] + at[0]) * d[1] + (y - lo[1] + at[1])) * d[2] + (x0 - lo[2] + at[2]))
            * self.es;
        &self.buf[i as usize..(i + (x1 - x0) * self.es) as usize]
    }
}

/// A decoded chunk of the statistics array, `None` when unreadable.
type StatsChunk = Option<Arc<Vec<f64>>>;

impl LevelStats {
    pub fn open(dir: &Path, brick: Dims3, dims: Dims3, channels: usize) -> Option<LevelStats> {
        if !storage::exists(&dir.join("zarr.json")) {
            return None;
        }
        let store = Arc::new(StoreAt::new(dir));
        let array = Array::open(store, "/").ok()?;
        let nb = [0, 1, 2].map(|a| dims[a].div_ceil(brick[a]));
        let want = [channels as u64, nb[0], nb[1], nb[2], 2];
        if array.shape() != want {
            return None;
        }
        let cs: Vec<u64> = array
            .chunk_shape(&[0; 5])
            .ok()?
            .iter()
            .map(|c| c.get())
            .collect();
        if cs.len() != 5 || cs[4] != 2 {
            return None;
        }
        Some(LevelStats {
            array,
            brick,
            chunk: [cs[0], cs[1], cs[2], cs[3]],
            chunks: Mutex::new(HashMap::new()),
            dir: dir.to_path_buf(),
            problems: Mutex::new(vec![]),
        })
    }

    /// (min, max) of store brick `b` of channel `c`, `None` if unknown.
    pub fn get(&self, c: u64, b: Dims3) -> Option<(f64, f64)> {
        let p = [c, b[0], b[1], b[2]];
        let ci = [0, 1, 2, 3].map(|a| p[a] / self.chunk[a]);
        let cached = lock(&self.chunks).get(&ci).cloned();
        let chunk = match cached {
            Some(ch) => ch,
            None => {
                let idx = [ci[0], ci[1], ci[2], ci[3], 0];
                let n = self.chunk.iter().product::<u64>() as usize * 2;
                let ch = match self.array.retrieve_chunk::<Vec<f64>>(&idx) {
                    Ok(v) if v.len() == n => Some(Arc::new(v)),
                    got => {
                        let why = match got {
                            Ok(v) => format!("{} values, {n} expected", v.len()),
                            Err(e) => e.to_string(),
                        };
                        lock(&self.problems).push(format!(
                            "{}: chunk {:?} cannot be read ({why}): its bricks are loaded to \
                             learn what they hold, none is skipped as empty",
                            self.dir.display(),
                            &idx[..4]
                        ));
                        None
                    }
                };
                lock(&self.chunks).insert(ci, ch.clone());
                ch
            }
        }?;
        let ch = self.chunk;
        let r = [0, 1, 2, 3].map(|a| p[a] % ch[a]);
        let e = ((((r[0] * ch[1] + r[1]) * ch[2] + r[2]) * ch[3] + r[3]) * 2) as usize;
        Some((chunk[e], chunk[e + 1]))
    }

    /// The store bricks touching `[lo, hi)` whose statistics say they hold
    /// something other than zeros: `(brick, min, max)` each.
    pub fn data_in(&self, c: u64, lo: Dims3, hi: Dims3) -> Vec<(Dims3, f64, f64)> {
        let sb = self.brick;
        let r = [0, 1, 2].map(|a| lo[a] / sb[a]..=(hi[a] - 1) / sb[a]);
        let mut out = vec![];
        for z in r[0].clone() {
            for y in r[1].clone() {
                for x in r[2].clone() {
                    if let Some((mn, mx)) = self.get(c, [z, y, x]) {
                        if mn != 0.0 || mx != 0.0 {
                            out.push(([z, y, x], mn, mx));
                        }
                    }
                }
            }
        }
        out
    }

    /// The range of values the store bricks touching `[lo, hi)` hold
    /// together (bricks of NaN alone passed over); `None` when any is
    /// unknown.
    pub fn range_over(&self, c: u64, lo: Dims3, hi: Dims3) -> Option<(f64, f64)> {
        let sb = self.brick;
        let r = [0, 1, 2].map(|a| lo[a] / sb[a]..=(hi[a] - 1) / sb[a]);
        let mut out = (f64::INFINITY, f64::NEG_INFINITY);
        for z in r[0].clone() {
            for y in r[1].clone() {
                for x in r[2].clone() {
                    let (mn, mx) = self.get(c, [z, y, x])?;
                    if let Some((mn, mx)) = finite_range(mn, mx) {
                        out = (out.0.min(mn), out.1.max(mx));
                    }
                }
            }
        }
        Some(out)
    }

    /// The common value of every store brick touching `[lo, hi)` if they
    /// are all constant with the same value.
    pub fn uniform(&self, c: u64, lo: Dims3, hi: Dims3) -> Option<f64> {
        let sb = self.brick;
        let r = [0, 1, 2].map(|a| lo[a] / sb[a]..=(hi[a] - 1) / sb[a]);
        let mut val = None;
        for z in r[0].clone() {
            for y in r[1].clone() {
                for x in r[2].clone() {
                    let (mn, mx) = self.get(c, [z, y, x])?;
                    // NaN fails both comparisons (a brick of NaN alone,
                    // and one recorded as `(v, NaN)`: see `finite_range`).
                    if mn != mx || val.is_some_and(|v| v != mn) {
                        return None;
                    }
                    val = Some(mn);
                }
            }
        }
        val
    }

    /// Lost data among the store bricks of channel `c` touching `[lo,
    /// hi)` that `src` read: a brick the statistics say holds data, that
    /// read as all zeros (`zero(brick)`: the fill value), and whose chunk
    /// `src` says is absent, is an error naming the chunk's file (an I/O
    /// failure where the file is gone, bad content where its shard's
    /// index left it out). A Zarr reader cannot tell such a chunk from one
    /// never written; the statistics can. The loader asks this of bricks
    /// that came out empty, conversion and processing of every read
    /// (`ZarrSource::check_against_stats`).
    pub fn check_lost(
        &self,
        src: &dyn VolumeSource,
        c: u64,
        lo: Dims3,
        hi: Dims3,
        mut zero: impl FnMut(Dims3) -> bool,
    ) -> Result<()> {
        for (b, mn, mx) in self.data_in(c, lo, hi) {
            if !zero(b) {
                continue;
            }
            let v = [0, 1, 2].map(|a| b[a] * self.brick[a]);
            let Some((file, why)) = src.chunk_absent(c as usize, v) else {
                continue;
            };
            let field = format!("channel {c} store brick {b:?}");
            // (No range at all: the statistics were read as their fill
            // value, gone as well, which said "[NaN, NaN]" of a store
            // replaced by another with fewer levels.)
            let held = match mn.is_nan() && mx.is_nan() {
                true => "its brick statistics are missing too (was the store replaced or damaged? \
                         open it again)"
                    .to_string(),
                false => format!("the statistics say this brick holds values in [{mn}, {mx}]"),
            };
            return Err(match why {
                Absence::FileMissing => StoreError::io(
                    file,
                    std::io::Error::new(
                        std::io::ErrorKind::NotFound,
                        format!("{field}: the file is missing, but {held}"),
                    ),
                ),
                Absence::NoEntry(why) => {
                    StoreError::invalid(file, field, format!("{why}, but {held}"))
                }
                Absence::ChangedSince(why) => StoreError::Changed {
                    path: file,
                    field,
                    msg: format!("{why}; {held}"),
                },
            });
        }
        Ok(())
    }

    /// [`check_lost`](Self::check_lost) of the read `r` of channel `c`: a
    /// store brick counts as read as zeros when every
    /// byte of its part of the region is 0 (the scan stops at the first
    /// other byte, so bricks holding data cost a few bytes' look).
    pub fn check_lost_read(&self, src: &dyn VolumeSource, c: u64, r: &ReadBox<'_>) -> Result<()> {
        if r.is_empty() {
            return Ok(());
        }
        let zero = |b: Dims3| {
            let (blo, bhi) = r.part(b, self.brick);
            (blo[0]..bhi[0])
                .all(|z| (blo[1]..bhi[1]).all(|y| all_zero(r.row(z, y, blo[2], bhi[2]))))
        };
        self.check_lost(src, c, r.lo, r.hi, zero)
    }

    /// Values outside the statistics' range among the store bricks of
    /// channel `c` that the read `r` (native-endian `dtype`) touched: an
    /// error naming
    /// the chunk's file. The codecs here carry no checksum, so a chunk
    /// whose bytes changed can decode to other values; the statistics,
    /// written from the stored voxels, tell (NaN is ignored).
    pub fn check_range_read(
        &self,
        src: &dyn VolumeSource,
        c: u64,
        r: &ReadBox<'_>,
        dtype: brickyard_core::DType,
    ) -> Result<()> {
        use brickyard_core::Sample;
        if r.is_empty() {
            return Ok(());
        }
        let sb = self.brick;
        let span = [0, 1, 2].map(|a| r.lo[a] / sb[a]..=(r.hi[a] - 1) / sb[a]);
        for bz in span[0].clone() {
            for by in span[1].clone() {
                for bx in span[2].clone() {
                    let b = [bz, by, bx];
                    let Some((mn, mx)) = self.get(c, b).and_then(|(a, b)| finite_range(a, b))
                    else {
                        continue;
                    };
                    let (blo, bhi) = r.part(b, sb);
                    let (vmin, vmax) = brickyard_core::dispatch_dtype!(dtype, T => {
                        // In the type itself, a row at a time (selects the
                        // compiler turns into vector min/max); NaN fails
                        // both comparisons and is passed over.
                        let mut acc: Option<(T, T)> = None;
                        for z in blo[0]..bhi[0] {
                            for y in blo[1]..bhi[1] {
                                // (The element size a constant of the type:
                                // a dynamic one keeps the loop scalar.)
                                let mut vals = r
                                    .row(z, y, blo[2], bhi[2])
                                    .chunks_exact(std::mem::size_of::<T>())
                                    .map(<T as Sample>::from_le);
                                // (Not NaN: the one value unequal to itself.)
                                #[allow(clippy::eq_op)]
                                let Some(first) = vals.by_ref().find(|v| v == v) else {
                                    continue;
                                };
                                let (a, b) = vals.fold((first, first), |(a, b), v| {
                                    (if v < a { v } else { a }, if v > b { v } else { b })
                                });
                                acc = Some(match acc {
                                    None => (a, b),
                                    Some((x, y)) => {
                                        (if a < x { a } else { x }, if b > y { b } else { y })
                                    }
                                });
                            }
                        }
                        acc.map_or((mn, mx), |(a, b)| (a.to_f64(), b.to_f64()))
                    });
                    if vmin < mn || vmax > mx {
                        let v = [0, 1, 2].map(|a| b[a] * sb[a]);
                        let file = src
                            .chunk_file(c as usize, v)
                            .unwrap_or_else(|| self.dir.clone());
                        return Err(StoreError::invalid(
                            file,
                            format!("channel {c} store brick {b:?}"),
                            format!(
                                "decoded values span {vmin}..{vmax}, but the statistics say \
                                 {mn}..{mx}: the chunk's bytes changed since it was written \
                                 (its codecs carry no checksum)"
                            ),
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    /// What made chunks of the statistics unreadable since the last call,
    /// once each.
    pub fn take_problems(&self) -> Vec<String> {
        std::mem::take(&mut *lock(&self.problems))
    }
}
