//! End-to-end tests of the pyramid builder: every level read back with the
//! `zarrs` reader (not ours) and compared with an independent, naive
//! reference downsample of the level above.

use brickyard_core::{dispatch_dtype, DType, Dims3, Sample};
use brickyard_store::builder::{convert, partial_path, ConvertOptions, NoProgress};
use brickyard_store::error::{Result as SResult, StoreError};
use brickyard_store::omezarr::read_multiscale;
use brickyard_store::source::{SourceMeta, VolumeSource};
use std::ops::Range;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use zarrs::array::{Array, ArraySubset};
use zarrs::filesystem::FilesystemStore;

/// An in-memory source (channel-major, x fastest) that can be told to fail.
struct MemSource {
    meta: SourceMeta,
    data: Vec<u8>,
    fail_after: Option<usize>,
    reads: AtomicUsize,
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

fn lcg(seed: &mut u64) -> u64 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    *seed >> 33
}

/// A volume with smooth structure, noise, empty and constant regions.
fn make_source(dims: Dims3, channels: usize, dtype: DType, seed: u64) -> MemSource {
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

fn from_f64<T: Sample>(v: f64) -> T {
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
fn naive_level(
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

fn read_level(store: &Path, k: usize, c: Option<u64>, dtype: DType) -> (Vec<f64>, Dims3) {
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

fn source_values(src: &MemSource, c: usize) -> Vec<f64> {
    let n = src.meta.dims.iter().product::<u64>() as usize;
    let es = src.meta.dtype.size();
    let b = &src.data[c * n * es..(c + 1) * n * es];
    dispatch_dtype!(src.meta.dtype, T => {
        b.chunks_exact(es).map(|e| <T as Sample>::from_le(e).to_f64()).collect()
    })
}

fn check_store(src: &MemSource, out: &Path, labels: bool) {
    let ms = read_multiscale(out).unwrap().expect("multiscales");
    assert_eq!(ms.version, "0.5");
    let c = src.meta.channels;
    for ch in 0..c {
        let chan = if c > 1 { Some(ch as u64) } else { None };
        let (l0, d0) = read_level(out, 0, chan, src.meta.dtype);
        assert_eq!(d0, src.meta.dims);
        let want = source_values(src, ch);
        assert!(
            l0.iter()
                .zip(&want)
                .all(|(a, b)| a.to_bits() == b.to_bits() || a == b),
            "level 0 differs"
        );
        let mut prev = (l0, d0);
        for k in 1..ms.datasets.len() {
            let s0 = ms.datasets[k - 1].scale.clone().unwrap();
            let s1 = ms.datasets[k].scale.clone().unwrap();
            let off = s0.len() - 3;
            let r = [0, 1, 2].map(|a| (s1[off + a] / s0[off + a]).round() as u64);
            let (want, wd) = naive_level(&prev.0, prev.1, r, src.meta.dtype, labels);
            let got = read_level(out, k, chan, src.meta.dtype);
            assert_eq!(got.1, wd, "level {k} dims");
            for (i, (g, w)) in got.0.iter().zip(&want).enumerate() {
                assert!(
                    g == w,
                    "level {k} channel {ch} voxel {i}: got {g}, want {w}"
                );
            }
            prev = got;
        }
        let last = prev.1;
        assert!(last.iter().all(|&d| d <= 64), "coarsest level fits a brick");
    }
}

fn opts(brick: u64, shard: u64) -> ConvertOptions {
    ConvertOptions {
        brick: [brick; 3],
        shard: [shard; 3],
        ..Default::default()
    }
}

#[test]
fn awkward_shapes_round_trip_and_levels_match_reference() {
    let cases: &[(Dims3, usize, DType, u64, u64)] = &[
        ([37, 45, 51], 1, DType::U8, 8, 16), // not a multiple of the brick
        ([5, 6, 7], 1, DType::U16, 8, 8),    // smaller than one brick
        ([1, 40, 33], 1, DType::I16, 8, 16), // one voxel thick
        ([20, 3, 1], 1, DType::F32, 4, 8),   // thin in two axes
        ([19, 23, 17], 3, DType::U16, 8, 16), // several channels
        ([17, 18, 21], 1, DType::U32, 4, 8),
        ([18, 17, 16], 1, DType::I32, 4, 16),
        ([15, 16, 17], 1, DType::F64, 4, 8),
        ([16, 16, 16], 1, DType::I8, 4, 8),
    ];
    for (i, &(dims, c, dt, brick, shard)) in cases.iter().enumerate() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("o.ome.zarr");
        let src = make_source(dims, c, dt, 100 + i as u64);
        let r = convert(
            &src,
            &out,
            &opts(brick, shard),
            &NoProgress,
            &AtomicBool::new(false),
        )
        .unwrap();
        assert!(r.levels.len() >= 1);
        check_store(&src, &out, false);
        assert!(!partial_path(&out).exists());
    }
}

#[test]
fn labels_use_the_mode() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("l.ome.zarr");
    let mut src = make_source([21, 26, 30], 1, DType::U8, 7);
    // Few distinct labels so that ties and majorities both happen.
    for b in src.data.iter_mut() {
        *b %= 3;
    }
    let mut o = opts(4, 8);
    o.labels = true;
    convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    check_store(&src, &out, true);
}

#[test]
fn small_budget_uses_tiles_and_passes_and_stays_exact() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t.ome.zarr");
    let src = make_source([70, 150, 260], 1, DType::U16, 3);
    // The volume is 5.5 MB; allow ~300 KB of slabs beyond the fixed overhead.
    let mut o = opts(8, 32);
    let threads = rayon::current_num_threads() as u64;
    o.memory = (48 << 20) + threads * 8 * 8 * 8 * 2 * 3 + 200_000 + (300 << 10);
    let r = convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    assert!(
        r.passes.len() > 1,
        "expected several passes: {:?}",
        r.passes
    );
    assert!(
        r.passes[0].tile[0] < 150 || r.passes[0].tile[1] < 260,
        "expected tiles: {:?}",
        r.passes
    );
    assert!(r.planned_bytes <= o.memory);
    check_store(&src, &out, false);
}

#[test]
fn brick_statistics_are_stored() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("s.ome.zarr");
    let src = make_source([32, 20, 24], 1, DType::U8, 5);
    let r = convert(
        &src,
        &out,
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    assert!(r.bricks_empty > 0 && r.bricks_constant > r.bricks_empty);
    let info = brickyard_store::info::inspect(&out).unwrap();
    assert_eq!(info.complete, Some(true));
    let s0 = info.levels[0].stats.clone().unwrap();
    assert_eq!(s0.bricks, 4 * 3 * 3);
    // z < 8 is zero, 8 <= z < 16 is 37: one layer of bricks each.
    assert_eq!(s0.empty, 9);
    assert_eq!(s0.constant, 18);
    // Check every brick's min/max against level 0 read back.
    let fs = Arc::new(FilesystemStore::new(out.join("_brickyard/stats/0")).unwrap());
    let a = Array::open(fs, "/").unwrap();
    let st: Vec<f64> = a
        .retrieve_array_subset::<Vec<f64>>(&ArraySubset::new_with_ranges(&[
            0..1,
            0..4,
            0..3,
            0..3,
            0..2,
        ]))
        .unwrap();
    let (l0, d) = read_level(&out, 0, None, DType::U8);
    for bz in 0..4u64 {
        for by in 0..3u64 {
            for bx in 0..3u64 {
                let (mut mn, mut mx) = (f64::INFINITY, f64::NEG_INFINITY);
                for z in bz * 8..((bz + 1) * 8).min(d[0]) {
                    for y in by * 8..((by + 1) * 8).min(d[1]) {
                        for x in bx * 8..((bx + 1) * 8).min(d[2]) {
                            let v = l0[((z * d[1] + y) * d[2] + x) as usize];
                            mn = mn.min(v);
                            mx = mx.max(v);
                        }
                    }
                }
                let i = (((bz * 3 + by) * 3 + bx) * 2) as usize;
                assert_eq!([st[i], st[i + 1]], [mn, mx], "brick {bz},{by},{bx}");
            }
        }
    }
}

#[test]
fn failures_leave_nothing_and_never_damage_existing_output() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("f.ome.zarr");
    // A failing read: no output, no partial store.
    let mut src = make_source([40, 20, 20], 1, DType::U8, 9);
    src.fail_after = Some(2);
    let e = convert(
        &src,
        &out,
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap_err();
    assert!(e.to_string().contains("simulated"), "{e}");
    assert!(!out.exists() && !partial_path(&out).exists());
    // A good store, then a refused and a failing overwrite: it stays intact.
    let good = make_source([40, 20, 20], 1, DType::U8, 9);
    convert(
        &good,
        &out,
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    let e = convert(
        &good,
        &out,
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap_err();
    assert!(e.to_string().contains("--overwrite"), "{e}");
    let mut o = opts(8, 16);
    o.overwrite = true;
    src.reads.store(0, Ordering::SeqCst);
    convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap_err();
    check_store(&good, &out, false);
    // Cancellation.
    let e = convert(
        &good,
        &dir.path().join("c.ome.zarr"),
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(true),
    )
    .unwrap_err();
    assert!(matches!(e, StoreError::Interrupted));
    assert!(!dir.path().join("c.ome.zarr").exists());
    assert!(!partial_path(&dir.path().join("c.ome.zarr")).exists());
}
