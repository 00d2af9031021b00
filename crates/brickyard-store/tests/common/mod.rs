//! Helpers shared by the integration tests.
#![allow(dead_code)]

use brickyard_core::{dispatch_dtype, DType, Dims3, Sample};
use brickyard_store::error::{Result as SResult, StoreError};
use brickyard_store::omezarr::read_multiscale;
use brickyard_store::source::{SourceMeta, VolumeSource};
use std::ops::Range;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use zarrs::array::{Array, ArraySubset};
use zarrs::filesystem::FilesystemStore;

/// An in-memory source (channel-major, x fastest) that can be told to fail.
pub struct MemSource {
    pub meta: SourceMeta,
    pub data: Vec<u8>,
    pub fail_after: Option<usize>,
    pub reads: AtomicUsize,
}

impl VolumeSource for MemSource {
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
    ) -> SResult<()> {
        let n = self.reads.fetch_add(1, Ordering::SeqCst);
        if self.fail_after.is_some_and(|f| n >= f) {
            return Err(StoreError::invalid(
                &self.meta.path,
                "data",
                "simulated read failure",
            ));
        }
        let es = self.meta.dtype.size() as u64;
        let [dz, dy, dx] = self.meta.dims;
        let base = c as u64 * dz * dy * dx;
        let row = ((x.end - x.start) * es) as usize;
        let mut o = 0;
        for zz in z {
            for yy in y.clone() {
                let s = ((base + (zz * dy + yy) * dx + x.start) * es) as usize;
                out[o..o + row].copy_from_slice(&self.data[s..s + row]);
                o += row;
            }
        }
        Ok(())
    }
}

pub fn lcg(seed: &mut u64) -> u64 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    *seed >> 33
}

/// A volume with smooth structure, noise, empty and constant regions.
pub fn make_source(dims: Dims3, channels: usize, dtype: DType, seed: u64) -> MemSource {
    let n = (dims.iter().product::<u64>() as usize) * channels;
    let mut s = seed;
    let mut data = Vec::with_capacity(n * dtype.size());
    for i in 0..n {
        let v = lcg(&mut s);
        let pos = i % (dims.iter().product::<u64>() as usize);
        let z = pos as u64 / (dims[1] * dims[2]);
        // A zero slab and a constant slab make empty / constant bricks.
        let val: f64 = if z < dims[0] / 4 {
            0.0
        } else if z < dims[0] / 2 {
            37.0
        } else {
            (v % 251) as f64 + (pos % 7) as f64
        };
        dispatch_dtype!(dtype, T => {
            let t: T = from_f64::<T>(val - if dtype == DType::I16 || dtype == DType::I8 { 60.0 } else { 0.0 });
            data.extend_from_slice(brickyard_core::as_bytes(std::slice::from_ref(&t)));
        });
    }
    let mut meta = SourceMeta::new("mem", dims, channels, dtype);
    meta.spacing = Some([2.0, 1.0, 1.0]);
    MemSource {
        meta,
        data,
        fail_after: None,
        reads: AtomicUsize::new(0),
    }
}

pub fn from_f64<T: Sample>(v: f64) -> T {
    let mut out = T::default();
    let b: &mut [u8] = unsafe {
        std::slice::from_raw_parts_mut(&mut out as *mut T as *mut u8, std::mem::size_of::<T>())
    };
    match T::DTYPE {
        DType::U8 => b.copy_from_slice(&(v as u8).to_le_bytes()),
        DType::I8 => b.copy_from_slice(&(v as i8).to_le_bytes()),
        DType::U16 => b.copy_from_slice(&(v as u16 * 250).to_le_bytes()),
        DType::I16 => b.copy_from_slice(&((v * 100.0) as i16).to_le_bytes()),
        DType::U32 => b.copy_from_slice(&((v as u32) * 16_000_000).to_le_bytes()),
        DType::I32 => b.copy_from_slice(&((v as i32) * -1000).to_le_bytes()),
        DType::F32 => b.copy_from_slice(&((v * 0.37) as f32).to_le_bytes()),
        DType::F64 => b.copy_from_slice(&(v * 1.3e-3).to_le_bytes()),
    }
    out
}

/// Naive reference: each output voxel is the mean (or mode) of the voxels
/// of its box that exist, computed in f64/i128 with round-half-up.
pub fn naive_level(
    prev: &[f64],
    pd: Dims3,
    r: [u64; 3],
    dtype: DType,
    labels: bool,
) -> (Vec<f64>, Dims3) {
    let od = [
        pd[0].div_ceil(r[0]),
        pd[1].div_ceil(r[1]),
        pd[2].div_ceil(r[2]),
    ];
    let mut out = Vec::with_capacity(od.iter().product::<u64>() as usize);
    for z in 0..od[0] {
        for y in 0..od[1] {
            for x in 0..od[2] {
                let mut vals = vec![];
                for k in z * r[0]..((z + 1) * r[0]).min(pd[0]) {
                    for j in y * r[1]..((y + 1) * r[1]).min(pd[1]) {
                        for i in x * r[2]..((x + 1) * r[2]).min(pd[2]) {
                            vals.push(prev[((k * pd[1] + j) * pd[2] + i) as usize]);
                        }
                    }
                }
                let v = if labels {
                    let mut best = (0usize, f64::INFINITY);
                    for &a in &vals {
                        let c = vals.iter().filter(|&&b| b == a).count();
                        if c > best.0 || (c == best.0 && a < best.1) {
                            best = (c, a);
                        }
                    }
                    best.1
                } else if dtype.is_float() {
                    let m = vals.iter().sum::<f64>() / vals.len() as f64;
                    if dtype == DType::F32 {
                        m as f32 as f64
                    } else {
                        m
                    }
                } else {
                    let s: i128 = vals.iter().map(|&v| v as i128).sum();
                    let n = vals.len() as i128;
                    (2 * s + n).div_euclid(2 * n) as f64
                };
                out.push(v);
            }
        }
    }
    (out, od)
}

pub fn read_level(store: &Path, k: usize, c: Option<u64>, dtype: DType) -> (Vec<f64>, Dims3) {
    let fs = Arc::new(FilesystemStore::new(store.join(k.to_string())).unwrap());
    let a = Array::open(fs, "/").unwrap();
    let shape = a.shape().to_vec();
    let (ranges, dims): (Vec<Range<u64>>, Dims3) = match c {
        Some(c) => (
            vec![c..c + 1, 0..shape[1], 0..shape[2], 0..shape[3]],
            [shape[1], shape[2], shape[3]],
        ),
        None => (
            shape.iter().map(|&s| 0..s).collect(),
            [shape[0], shape[1], shape[2]],
        ),
    };
    let sub = ArraySubset::new_with_ranges(&ranges);
    let v: Vec<f64> = dispatch_dtype!(dtype, T => {
        a.retrieve_array_subset::<Vec<T>>(&sub).unwrap().into_iter().map(|v| v.to_f64()).collect()
    });
    (v, dims)
}

/// All voxels of channel `c` of a source, read through `read_region`.
pub fn source_values(src: &dyn VolumeSource, c: usize) -> Vec<f64> {
    let m = src.meta();
    let [dz, dy, dx] = m.dims;
    let es = m.dtype.size();
    let mut b = vec![0u8; (dz * dy * dx) as usize * es];
    src.read_region(c, 0..dz, 0..dy, 0..dx, &mut b).unwrap();
    dispatch_dtype!(m.dtype, T => {
        b.chunks_exact(es).map(|e| <T as Sample>::from_le(e).to_f64()).collect()
    })
}

pub fn check_store(src: &dyn VolumeSource, out: &Path, labels: bool) {
    let ms = read_multiscale(out).unwrap().expect("multiscales");
    assert_eq!(ms.version, "0.5");
    let c = src.meta().channels;
    for ch in 0..c {
        let chan = if c > 1 { Some(ch as u64) } else { None };
        let (l0, d0) = read_level(out, 0, chan, src.meta().dtype);
        assert_eq!(d0, src.meta().dims);
        let want = source_values(src, ch);
        assert!(
            l0.iter()
                .zip(&want)
                .all(|(a, b)| a.to_bits() == b.to_bits() || a == b),
            "level 0 differs"
        );
        let mut prev = (l0, d0);
        let mut dims = vec![d0];
        for k in 1..ms.datasets.len() {
            let s0 = ms.datasets[k - 1].scale.clone().unwrap();
            let s1 = ms.datasets[k].scale.clone().unwrap();
            let off = s0.len() - 3;
            let r = [0, 1, 2].map(|a| (s1[off + a] / s0[off + a]).round() as u64);
            let (want, wd) = naive_level(&prev.0, prev.1, r, src.meta().dtype, labels);
            let got = read_level(out, k, chan, src.meta().dtype);
            assert_eq!(got.1, wd, "level {k} dims");
            for (i, (g, w)) in got.0.iter().zip(&want).enumerate() {
                assert!(
                    g == w,
                    "level {k} channel {ch} voxel {i}: got {g}, want {w}"
                );
            }
            dims.push(got.1);
            prev = got;
        }
        // The pyramid goes down to one brick (the inner chunk).
        let info = brickyard_store::info::inspect(out).unwrap();
        let lv0 = &info.levels[0];
        let inner = lv0.inner_chunk.clone().unwrap_or_else(|| lv0.chunk.clone());
        let brick = &inner[inner.len() - 3..];
        let last = prev.1;
        assert!(
            (0..3).all(|a| last[a] <= brick[a]),
            "coarsest level {last:?} fits a brick {brick:?}"
        );
        if let [.., above, _] = &dims[..] {
            assert!(
                (0..3).any(|a| above[a] > brick[a]),
                "the level above the coarsest, {above:?}, fits a brick already"
            );
        }
    }
}
