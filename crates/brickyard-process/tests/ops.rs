//! Operators against naive in-core references written here: direct (not
//! separable) convolution with clamped indices for the filters, and a
//! flood fill over the whole volume for the labels. Volumes have odd sizes;
//! blocks are much smaller than the volume.

use brickyard_core::{as_bytes, as_bytes_mut, cast_slice, DType, Dims3, Sample};
use brickyard_process::{build, label_pass1, LabelSource, Labeling, Pipeline, Sigma};
use brickyard_store::{NoProgress, Result, SourceMeta, StoreError, VolumeSource};
use std::ops::Range;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// A volume held in memory.
struct Mem {
    meta: SourceMeta,
    data: Vec<u8>,
}

impl Mem {
    fn new<T: Sample>(dims: Dims3, v: &[T]) -> Mem {
        Mem {
            meta: SourceMeta::new("/nonexistent/mem", dims, 1, T::DTYPE),
            data: as_bytes(v).to_vec(),
        }
    }
}

impl VolumeSource for Mem {
    fn meta(&self) -> &SourceMeta {
        &self.meta
    }
    fn read_region(
        &self,
        _c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> Result<()> {
        let s = self.meta.dtype.size();
        let d = self.meta.dims;
        let nx = (x.end - x.start) as usize * s;
        let mut o = 0;
        for zz in z {
            for yy in y.clone() {
                let i = ((zz * d[1] + yy) * d[2] + x.start) as usize * s;
                out[o..o + nx].copy_from_slice(&self.data[i..i + nx]);
                o += nx;
            }
        }
        Ok(())
    }
}

/// Deterministic pseudo-random numbers in [0, 1).
fn rng(seed: u64) -> impl FnMut() -> f64 {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A smooth-ish random volume of type `T` (values cover a good part of the
/// type's range; signed types get negative values).
fn volume<T: Sample + FromF64>(dims: Dims3, seed: u64) -> Vec<T> {
    let mut r = rng(seed);
    let n = dims.iter().product::<u64>() as usize;
    (0..n)
        .map(|i| {
            let z = (i as u64 / (dims[1] * dims[2])) as f64;
            let base = (z * 0.7).sin() * 40.0 + 50.0;
            T::from_f64(base + r() * 60.0 - 20.0)
        })
        .collect()
}

trait FromF64 {
    fn from_f64(v: f64) -> Self;
}
macro_rules! from_f64 {
    ($($t:ty),*) => {$(impl FromF64 for $t { fn from_f64(v: f64) -> Self { v as $t } })*};
}
from_f64!(u8, i8, u16, i16, u32, i32, f32, f64);

/// Read a whole channel through odd-sized region requests (so that region
/// edges fall inside the filter blocks).
fn read_all_regions(src: &dyn VolumeSource, step: Dims3) -> Vec<f64> {
    let m = src.meta();
    let d = m.dims;
    let mut out = vec![0.0; d.iter().product::<u64>() as usize];
    let mut z0 = 0;
    while z0 < d[0] {
        let z1 = (z0 + step[0]).min(d[0]);
        let mut y0 = 0;
        while y0 < d[1] {
            let y1 = (y0 + step[1]).min(d[1]);
            let mut x0 = 0;
            while x0 < d[2] {
                let x1 = (x0 + step[2]).min(d[2]);
                let n = ((z1 - z0) * (y1 - y0) * (x1 - x0)) as usize;
                let mut buf = vec![0u8; n * m.dtype.size()];
                src.read_region(0, z0..z1, y0..y1, x0..x1, &mut buf)
                    .unwrap();
                let vals: Vec<f64> = brickyard_core::dispatch_dtype!(m.dtype, T => {
                    cast_slice::<T>(&buf).iter().map(|v| v.to_f64()).collect()
                });
                let mut k = 0;
                for z in z0..z1 {
                    for y in y0..y1 {
                        for x in x0..x1 {
                            out[((z * d[1] + y) * d[2] + x) as usize] = vals[k];
                            k += 1;
                        }
                    }
                }
                x0 = x1;
            }
            y0 = y1;
        }
        z0 = z1;
    }
    out
}

/// Value at a clamped position (mode "nearest").
fn at(v: &[f64], d: Dims3, z: i64, y: i64, x: i64) -> f64 {
    let c = |g: i64, n: u64| g.clamp(0, n as i64 - 1) as u64;
    v[((c(z, d[0]) * d[1] + c(y, d[1])) * d[2] + c(x, d[2])) as usize]
}

/// scipy's 1D Gaussian (order 0 or 1) as a function of the offset, written
/// from the formula: φ(m) = exp(−m²/2σ²)/Σφ, order 1: m/σ² · φ(m) (the
/// correlation form of the derivative).
fn g1(sigma: f64, order: u32) -> (i64, Vec<f64>) {
    let r = (4.0 * sigma + 0.5).floor() as i64;
    let phi: Vec<f64> = (-r..=r)
        .map(|m| (-(m * m) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let s: f64 = phi.iter().sum();
    let w = (-r..=r)
        .zip(&phi)
        .map(|(m, p)| {
            if order == 0 {
                p / s
            } else {
                m as f64 / (sigma * sigma) * p / s
            }
        })
        .collect();
    (r, w)
}

/// Direct 3D correlation with the outer product of three 1D kernels.
fn direct(v: &[f64], d: Dims3, k: [&(i64, Vec<f64>); 3]) -> Vec<f64> {
    let mut out = vec![0.0; v.len()];
    for z in 0..d[0] as i64 {
        for y in 0..d[1] as i64 {
            for x in 0..d[2] as i64 {
                let mut s = 0.0;
                for (i, wz) in k[0].1.iter().enumerate() {
                    for (j, wy) in k[1].1.iter().enumerate() {
                        for (l, wx) in k[2].1.iter().enumerate() {
                            s += wz
                                * wy
                                * wx
                                * at(
                                    v,
                                    d,
                                    z + i as i64 - k[0].0,
                                    y + j as i64 - k[1].0,
                                    x + l as i64 - k[2].0,
                                );
                        }
                    }
                }
                out[((z as u64 * d[1] + y as u64) * d[2] + x as u64) as usize] = s;
            }
        }
    }
    out
}

fn gauss_ref(v: &[f64], d: Dims3, s: [f64; 3]) -> Vec<f64> {
    let k = s.map(|s| g1(s, 0));
    direct(v, d, [&k[0], &k[1], &k[2]])
}

fn gradmag_ref(v: &[f64], d: Dims3, s: [f64; 3]) -> Vec<f64> {
    let g = s.map(|s| g1(s, 0));
    let dd = s.map(|s| g1(s, 1));
    let a = direct(v, d, [&dd[0], &g[1], &g[2]]);
    let b = direct(v, d, [&g[0], &dd[1], &g[2]]);
    let c = direct(v, d, [&g[0], &g[1], &dd[2]]);
    (0..v.len())
        .map(|i| (a[i] * a[i] + b[i] * b[i] + c[i] * c[i]).sqrt())
        .collect()
}

fn sobel_ref(v: &[f64], d: Dims3) -> Vec<f64> {
    let dk = (1, vec![-1.0, 0.0, 1.0]);
    let sk = (1, vec![1.0, 2.0, 1.0]);
    let a = direct(v, d, [&dk, &sk, &sk]);
    let b = direct(v, d, [&sk, &dk, &sk]);
    let c = direct(v, d, [&sk, &sk, &dk]);
    (0..v.len())
        .map(|i| (a[i] * a[i] + b[i] * b[i] + c[i] * c[i]).sqrt())
        .collect()
}

fn assert_close(got: &[f64], want: &[f64], what: &str) {
    assert_eq!(got.len(), want.len());
    let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-12);
    let mut worst = 0.0f64;
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        // f32 results: a few ulps of the largest value.
        let e = (g - w).abs() / scale;
        worst = worst.max(e);
        assert!(e < 2e-6, "{what}: voxel {i}: {g} vs {w} (relative {e})");
    }
    eprintln!("{what}: worst relative error {worst:.2e}");
}

fn as_f64<T: Sample>(v: &[T]) -> Vec<f64> {
    v.iter().map(|x| x.to_f64()).collect()
}

fn run_filter<T: Sample + FromF64>(
    pipe: &str,
    dims: Dims3,
    seed: u64,
    block: Dims3,
    step: Dims3,
) -> (Vec<f64>, Vec<f64>, DType) {
    let v: Vec<T> = volume(dims, seed);
    let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(dims, &v));
    let p = Pipeline::parse(pipe).unwrap();
    let b = build(&p, src, 0, block).unwrap();
    let got = read_all_regions(b.source.as_ref(), step);
    (as_f64(&v), got, b.source.meta().dtype)
}

const DIMS: Dims3 = [13, 11, 17];

#[test]
fn gauss_equals_direct_convolution_for_every_dtype() {
    for (k, dt) in DType::ALL.iter().enumerate() {
        brickyard_core::dispatch_dtype!(*dt, T => {
            let (v, got, odt) = run_filter::<T>("gauss(1.2)", DIMS, k as u64, [4, 5, 3], [5, 3, 7]);
            assert_eq!(odt, DType::F32);
            assert_close(&got, &gauss_ref(&v, DIMS, [1.2; 3]), &format!("gauss {dt}"));
        });
    }
}

#[test]
fn gauss_anisotropic_and_wider_than_the_volume() {
    // σ = (x 0.8, y 2.0, z 3.1): z radius 12 reaches past the 13 slices.
    let (v, got, _) = run_filter::<f32>("gauss(0.8,2,3.1)", DIMS, 7, [3, 4, 6], [13, 11, 17]);
    assert_close(&got, &gauss_ref(&v, DIMS, [3.1, 2.0, 0.8]), "gauss aniso");
}

#[test]
fn gauss_in_physical_units_uses_the_spacing() {
    let v: Vec<u16> = volume(DIMS, 3);
    let mut m = Mem::new(DIMS, &v);
    m.meta.spacing = Some([2.0, 0.5, 0.5]);
    m.meta.unit = Some("micrometer".into());
    let p = Pipeline::parse("gauss(1um)").unwrap();
    let b = build(&p, Arc::new(m), 0, [4, 4, 4]).unwrap();
    let got = read_all_regions(b.source.as_ref(), [6, 6, 6]);
    // 1 µm = 0.5 voxel along z, 2 voxels along y and x.
    assert_close(
        &got,
        &gauss_ref(&as_f64(&v), DIMS, [0.5, 2.0, 2.0]),
        "gauss um",
    );
    // In nanometres against a micrometre grid.
    let mut m = Mem::new(DIMS, &v);
    m.meta.spacing = Some([2.0, 0.5, 0.5]);
    m.meta.unit = Some("micrometer".into());
    let p = Pipeline::parse("gauss(1000nm)").unwrap();
    let b = build(&p, Arc::new(m), 0, [4, 4, 4]).unwrap();
    assert_close(
        &read_all_regions(b.source.as_ref(), [13, 11, 17]),
        &gauss_ref(&as_f64(&v), DIMS, [0.5, 2.0, 2.0]),
        "gauss nm",
    );
    // No unit on the volume: a clear error.
    let p = Pipeline::parse("gauss(1um)").unwrap();
    let e = match build(&p, Arc::new(Mem::new(DIMS, &v)), 0, [4; 3]) {
        Err(e) => e,
        Ok(_) => panic!("built without a spacing"),
    };
    assert!(e.contains("no voxel spacing"), "{e}");
    assert!(matches!(
        p.ops[0],
        brickyard_process::Op::Gauss(Sigma::Physical { .. })
    ));
}

#[test]
fn gradmag_equals_direct_convolution() {
    for (k, dt) in [DType::U8, DType::I16, DType::F32, DType::F64]
        .iter()
        .enumerate()
    {
        brickyard_core::dispatch_dtype!(*dt, T => {
            let (v, got, _) = run_filter::<T>("gradmag(1.5)", DIMS, 10 + k as u64, [5, 3, 4], [4, 11, 9]);
            assert_close(&got, &gradmag_ref(&v, DIMS, [1.5; 3]), &format!("gradmag {dt}"));
        });
    }
}

#[test]
fn sobel_equals_direct_convolution() {
    for (k, dt) in [DType::U8, DType::I8, DType::U32, DType::F64]
        .iter()
        .enumerate()
    {
        brickyard_core::dispatch_dtype!(*dt, T => {
            let (v, got, _) = run_filter::<T>("sobel", DIMS, 20 + k as u64, [2, 3, 5], [3, 5, 2]);
            assert_close(&got, &sobel_ref(&v, DIMS), &format!("sobel {dt}"));
        });
    }
}

#[test]
fn chained_stages_equal_the_stages_applied_in_turn() {
    // gauss then sobel: the reference applies sobel (mode nearest) to the
    // f32-rounded gauss result, as writing each stage would.
    let (v, got, _) = run_filter::<i16>("gauss(1)|sobel", DIMS, 31, [4, 4, 4], [5, 5, 5]);
    let g: Vec<f64> = gauss_ref(&v, DIMS, [1.0; 3])
        .into_iter()
        .map(|x| x as f32 as f64)
        .collect();
    assert_close(&got, &sobel_ref(&g, DIMS), "gauss|sobel");
}

#[test]
fn threshold_and_window_make_u8_masks() {
    let (v, got, dt) = run_filter::<f32>("threshold(50.5)", DIMS, 40, [4, 4, 4], [5, 5, 5]);
    assert_eq!(dt, DType::U8);
    let want: Vec<f64> = v.iter().map(|&x| (x > 50.5) as u8 as f64).collect();
    assert_eq!(got, want);
    assert!(want.contains(&1.0) && want.contains(&0.0));
    let (v, got, _) = run_filter::<i8>("window(-3,40)", DIMS, 41, [4, 4, 4], [5, 5, 5]);
    let want: Vec<f64> = v
        .iter()
        .map(|&x| ((-3.0..=40.0).contains(&x)) as u8 as f64)
        .collect();
    assert_eq!(got, want);
    // The bounds are inclusive: a window on one value keeps exactly it.
    let (v, got, _) = run_filter::<u8>("window(60,60)", DIMS, 42, [4, 4, 4], [5, 5, 5]);
    let n = v.iter().filter(|&&x| x == 60.0).count();
    assert!(n > 0);
    assert_eq!(got.iter().filter(|&&x| x == 1.0).count(), n);
}

/// In-core reference: flood fill over the whole volume in raster order;
/// labels numbered by their first voxel.
fn flood(mask: &[bool], d: Dims3, conn: u8) -> (Vec<u32>, u32) {
    let (nz, ny, nx) = (d[0] as i64, d[1] as i64, d[2] as i64);
    let mut lab = vec![0u32; mask.len()];
    let mut n = 0;
    let mut queue = std::collections::VecDeque::new();
    for s in 0..mask.len() {
        if !mask[s] || lab[s] != 0 {
            continue;
        }
        n += 1;
        lab[s] = n;
        queue.push_back(s);
        while let Some(i) = queue.pop_front() {
            let (z, y, x) = (i as i64 / (ny * nx), i as i64 / nx % ny, i as i64 % nx);
            for dz in -1i64..=1 {
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let k = dz.abs() + dy.abs() + dx.abs();
                        if k == 0 || (conn == 6 && k > 1) {
                            continue;
                        }
                        let (a, b, c) = (z + dz, y + dy, x + dx);
                        if a < 0 || b < 0 || c < 0 || a >= nz || b >= ny || c >= nx {
                            continue;
                        }
                        let j = ((a * ny + b) * nx + c) as usize;
                        if mask[j] && lab[j] == 0 {
                            lab[j] = n;
                            queue.push_back(j);
                        }
                    }
                }
            }
        }
    }
    (lab, n)
}

fn random_mask(d: Dims3, density: f64, seed: u64) -> Vec<u8> {
    let mut r = rng(seed);
    (0..d.iter().product::<u64>())
        .map(|_| (r() < density) as u8)
        .collect()
}

fn label_ooc(
    src: Arc<dyn VolumeSource>,
    conn: u8,
    block: Dims3,
    inten: Option<&dyn VolumeSource>,
) -> (Vec<u32>, Labeling) {
    let cancel = AtomicBool::new(false);
    let lab = label_pass1(
        src.as_ref(),
        0,
        conn,
        block,
        inten.map(|s| (s, 0)),
        &NoProgress,
        &cancel,
    )
    .unwrap();
    let lab = Arc::new(lab);
    let ls = LabelSource::new(src.clone(), 0, lab.clone());
    let d = src.meta().dims;
    let mut out = vec![0u32; d.iter().product::<u64>() as usize];
    // Regions not aligned to the label blocks.
    let step = [5u64, 7, 3];
    let mut z0 = 0;
    while z0 < d[0] {
        let z1 = (z0 + step[0]).min(d[0]);
        let mut buf = vec![0u32; ((z1 - z0) * d[1] * d[2]) as usize];
        ls.read_region(0, z0..z1, 0..d[1], 0..d[2], as_bytes_mut(&mut buf))
            .unwrap();
        let o = (z0 * d[1] * d[2]) as usize;
        out[o..o + buf.len()].copy_from_slice(&buf);
        z0 = z1;
    }
    // And one odd box, checked against the whole.
    let bx = [2..5.min(d[0]), 1..5.min(d[1]), 3..8.min(d[2])];
    let n = bx.iter().map(|r| (r.end - r.start) as usize).product();
    let mut b = vec![0u32; n];
    ls.read_region(
        0,
        bx[0].clone(),
        bx[1].clone(),
        bx[2].clone(),
        as_bytes_mut(&mut b),
    )
    .unwrap();
    let mut k = 0;
    for z in bx[0].clone() {
        for y in bx[1].clone() {
            for x in bx[2].clone() {
                assert_eq!(b[k], out[((z * d[1] + y) * d[2] + x) as usize]);
                k += 1;
            }
        }
    }
    (out, Arc::try_unwrap(lab).unwrap_or_else(|a| (*a).clone()))
}

#[test]
fn out_of_core_labels_equal_in_core_labels() {
    let d: Dims3 = [15, 13, 17];
    // Densities around each connectivity's percolation threshold (about
    // 0.31 for 6, 0.1 for 26): many components, some spanning many blocks.
    for (conn, densities) in [(6u8, [0.2, 0.3, 0.4]), (26, [0.06, 0.1, 0.14])] {
        for (seed, density) in densities.into_iter().enumerate() {
            let m = random_mask(d, density, seed as u64);
            let mb: Vec<bool> = m.iter().map(|&v| v != 0).collect();
            let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(d, &m));
            let (want, n) = flood(&mb, d, conn);
            assert!(n > 3, "the test volume should have several components");
            for block in [
                [1, 1, 1],
                [2, 3, 2],
                [4, 5, 3],
                [8, 8, 8],
                [15, 13, 17],
                [64, 64, 64],
            ] {
                let (got, lab) = label_ooc(src.clone(), conn, block, None);
                assert_eq!(
                    lab.count(),
                    n,
                    "count, conn {conn} block {block:?} density {density}"
                );
                assert!(
                    got == want,
                    "labels differ: conn {conn} block {block:?} density {density}"
                );
            }
        }
    }
}

#[test]
fn components_that_only_touch_across_block_edges_and_corners() {
    // A diagonal line of voxels crossing block corners: one component with
    // 26-connectivity, one per voxel with 6.
    let d: Dims3 = [9, 9, 9];
    let mut m = vec![0u8; 729];
    for i in 0..9 {
        m[(i * 9 + i) * 9 + i] = 1;
    }
    // And an edge-diagonal (y and x change, z fixed).
    for i in 0..9 {
        m[(4 * 9 + i) * 9 + (8 - i)] = 1;
    }
    let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(d, &m));
    let mb: Vec<bool> = m.iter().map(|&v| v != 0).collect();
    for conn in [6u8, 26] {
        let (want, n) = flood(&mb, d, conn);
        for block in [[2, 2, 2], [3, 3, 3], [1, 2, 3]] {
            let (got, lab) = label_ooc(src.clone(), conn, block, None);
            assert_eq!(lab.count(), n);
            assert_eq!(got, want, "conn {conn} block {block:?}");
        }
    }
    assert_eq!(flood(&mb, d, 26).1, 1);
    assert_eq!(flood(&mb, d, 6).1, 17);
}

#[test]
fn label_statistics_equal_those_of_the_labels() {
    let d: Dims3 = [11, 14, 9];
    let m = random_mask(d, 0.35, 9);
    let mb: Vec<bool> = m.iter().map(|&v| v != 0).collect();
    let inten: Vec<i16> = volume(d, 77);
    let isrc = Mem::new(d, &inten);
    let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(d, &m));
    let (want, n) = flood(&mb, d, 26);
    let (_, lab) = label_ooc(src, 26, [3, 4, 2], Some(&isrc));
    assert_eq!(lab.stats.len(), n as usize);
    for s in &lab.stats {
        let mut cnt = 0u64;
        let (mut mn, mut mx) = ([u64::MAX; 3], [0u64; 3]);
        let mut sum = [0.0; 3];
        let mut si = 0.0;
        for (i, &l) in want.iter().enumerate() {
            if l != s.label {
                continue;
            }
            let c = [
                i as u64 / (d[1] * d[2]),
                i as u64 / d[2] % d[1],
                i as u64 % d[2],
            ];
            cnt += 1;
            for a in 0..3 {
                mn[a] = mn[a].min(c[a]);
                mx[a] = mx[a].max(c[a]);
                sum[a] += c[a] as f64;
            }
            si += inten[i] as f64;
        }
        assert_eq!(s.voxels, cnt, "label {}", s.label);
        assert_eq!((s.min, s.max), (mn, mx), "label {}", s.label);
        for (c, sm) in s.centroid.iter().zip(sum) {
            assert!((c - sm / cnt as f64).abs() < 1e-9);
        }
        assert!((s.mean.unwrap() - si / cnt as f64).abs() < 1e-9);
    }
    let csv = brickyard_process::stats_csv(&lab.stats);
    assert_eq!(csv.lines().count(), n as usize + 1);
    assert!(csv.starts_with("label,voxels,min_z"));
    let json = brickyard_process::stats_json(&lab, &[]);
    assert!(json.contains(&format!("\"count\": {n}")));
}

#[test]
fn labelling_a_filtered_mask_of_any_dtype() {
    // gauss | threshold | label on f64 and u16 volumes, blocks of 4.
    let d: Dims3 = [12, 9, 15];
    for dt in [DType::U16, DType::F64, DType::I32] {
        brickyard_core::dispatch_dtype!(dt, T => {
            let v: Vec<T> = volume(d, 5);
            let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(d, &v));
            let p = Pipeline::parse("gauss(0.7)|threshold(60)|label(6)").unwrap();
            let b = build(&p, src, 0, [4, 4, 4]).unwrap();
            assert_eq!(b.label, Some(6));
            let g = gauss_ref(&as_f64(&v), d, [0.7; 3]);
            let mb: Vec<bool> = g.iter().map(|&x| (x as f32 as f64) > 60.0).collect();
            let (want, n) = flood(&mb, d, 6);
            assert!(n > 1);
            let (got, _) = label_ooc(b.source.clone(), 6, [4, 4, 4], None);
            assert_eq!(got, want, "{dt}");
        });
    }
}

#[test]
fn a_cancelled_labelling_stops_with_interrupted() {
    let d: Dims3 = [8, 8, 8];
    let m = random_mask(d, 0.5, 4);
    let src = Mem::new(d, &m);
    let cancel = AtomicBool::new(true);
    let r = label_pass1(&src, 0, 26, [4, 4, 4], None, &NoProgress, &cancel);
    assert!(matches!(r, Err(StoreError::Interrupted)));
}

#[test]
fn results_do_not_depend_on_how_regions_are_cut() {
    // Labelling's pass 2 recomputes what pass 1 saw through other regions:
    // the values must be the same bit for bit.
    let v: Vec<i16> = volume(DIMS, 51);
    let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(DIMS, &v));
    let p = Pipeline::parse("gauss(1.3)|sobel|gradmag(0.9)").unwrap();
    let a = build(&p, src.clone(), 0, [4, 4, 4]).unwrap();
    let b = build(&p, src, 0, [7, 3, 5]).unwrap();
    let whole = read_all_regions(a.source.as_ref(), DIMS);
    for (s, step) in [
        (&a, [5, 3, 7]),
        (&a, [1, 11, 2]),
        (&b, [13, 2, 17]),
        (&b, [6, 6, 6]),
    ] {
        let got = read_all_regions(s.source.as_ref(), step);
        assert!(
            got.iter()
                .zip(&whole)
                .all(|(x, y)| x.to_bits() == y.to_bits()),
            "regions of {step:?} differ"
        );
    }
}

/// Mean of each 2×2×2 block (a pyramid's next level; sizes even here).
fn halve(v: &[f64], d: Dims3) -> (Vec<f64>, Dims3) {
    let h = d.map(|n| n / 2);
    let mut out = vec![0.0; h.iter().product::<u64>() as usize];
    for z in 0..h[0] {
        for y in 0..h[1] {
            for x in 0..h[2] {
                let mut s = 0.0;
                for (dz, dy, dx) in (0..8).map(|i| (i >> 2, (i >> 1) & 1, i & 1)) {
                    s += v[(((2 * z + dz) * d[1] + 2 * y + dy) * d[2] + 2 * x + dx) as usize];
                }
                out[((z * h[1] + y) * h[2] + x) as usize] = s / 8.0;
            }
        }
    }
    (out, h)
}

fn derived(pipe: &str, v: &[f64], d: Dims3, factor: [f64; 3]) -> Vec<f64> {
    let v32: Vec<f32> = v.iter().map(|x| *x as f32).collect();
    let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(d, &v32));
    let p = Pipeline::parse(pipe).unwrap();
    let s = brickyard_process::derive_level(&p, src, 0, factor, [7, 9, 8]).unwrap();
    read_all_regions(s.as_ref(), [5, 6, 7])
}

/// A smooth ramp with a ball (a step edge) in it, level 0 and level 1.
fn ramp_and_ball() -> (Vec<f64>, Dims3, Vec<f64>, Dims3) {
    let d: Dims3 = [32, 36, 40];
    let mut v = vec![0.0; d.iter().product::<u64>() as usize];
    for z in 0..d[0] {
        for y in 0..d[1] {
            for x in 0..d[2] {
                let r2 = (z as f64 - 16.0).powi(2)
                    + (y as f64 - 18.0).powi(2)
                    + (x as f64 - 20.0).powi(2);
                let ball = if r2 < 81.0 { 200.0 } else { 0.0 };
                v[((z * d[1] + y) * d[2] + x) as usize] = 3.0 * x as f64 + ball;
            }
        }
    }
    let (h, hd) = halve(&v, d);
    (v, d, h, hd)
}

#[test]
fn a_derived_coarse_level_is_the_pipeline_on_that_level_with_lengths_scaled() {
    let (_, _, h, hd) = ramp_and_ball();
    let f = [2.0; 3];
    // σ in level-0 voxels: σ 2 is σ 1 at a level of twice the voxel size.
    assert_close(
        &derived("gauss(2)", &h, hd, f),
        &gauss_ref(&h, hd, [1.0; 3]),
        "gauss level 1",
    );
    // Gradients are per level-0 voxel: halved at level 1.
    let want: Vec<f64> = gradmag_ref(&h, hd, [1.0; 3])
        .iter()
        .map(|g| g / 2.0)
        .collect();
    assert_close(&derived("gradmag(2)", &h, hd, f), &want, "gradmag level 1");
    // Sobel is the level's own three-voxel stencil, per level-0 voxel too.
    let want: Vec<f64> = sobel_ref(&h, hd).iter().map(|g| g / 2.0).collect();
    assert_close(&derived("sobel", &h, hd, f), &want, "sobel level 1");
    // Anisotropic factors (z kept, y and x halved): σ scaled per axis.
    let got = derived("gauss(2)", &h, hd, [1.0, 2.0, 2.0]);
    assert_close(
        &got,
        &gauss_ref(&h, hd, [2.0, 1.0, 1.0]),
        "gauss anisotropic level",
    );
    // Level 0 is the pipeline itself.
    assert_close(
        &derived("gauss(1.5)|sobel", &h, hd, [1.0; 3]),
        &{
            let g = gauss_ref(&h, hd, [1.5; 3]);
            sobel_ref(&g, hd)
        },
        "level 0",
    );
}

#[test]
fn a_derived_coarse_level_stands_in_for_the_finer_result() {
    // The choice above makes level 1 of the derived channel close to the
    // finer result downsampled, as a stored pyramid's level 1 is: for the
    // gradient of the ramp (3 per level-0 voxel) and of the ball's edge.
    let (v, d, h, hd) = ramp_and_ball();
    for pipe in ["gauss(2)", "gradmag(2)", "gauss(2)|sobel"] {
        let fine = derived(pipe, &v, d, [1.0; 3]);
        let (fine_down, _) = halve(&fine, d);
        let coarse = derived(pipe, &h, hd, [2.0; 3]);
        // Away from the faces (where "nearest" differs between levels).
        let (mut err, mut mag, mut n) = (0.0, 0.0, 0.0);
        for z in 4..hd[0] - 4 {
            for y in 4..hd[1] - 4 {
                for x in 4..hd[2] - 4 {
                    let i = ((z * hd[1] + y) * hd[2] + x) as usize;
                    err += (coarse[i] - fine_down[i]).abs();
                    mag += fine_down[i].abs();
                    n += 1.0;
                }
            }
        }
        let rel = err / mag;
        eprintln!("{pipe}: level 1 vs level 0 downsampled: mean relative difference {rel:.4} over {n} voxels");
        // Sobel's stencil is not scaled with the level (it reaches three
        // coarse voxels, six fine ones): a looser stand-in.
        let bound = if pipe.ends_with("sobel") { 0.15 } else { 0.05 };
        assert!(rel < bound, "{pipe}: {rel}");
    }
    // The ramp's gradient, far from the ball: 3 per level-0 voxel at both.
    let coarse = derived("gradmag(2)", &h, hd, [2.0; 3]);
    let i = ((2 * hd[1] + 2) * hd[2] + 10) as usize;
    assert!((coarse[i] - 3.0).abs() < 0.01, "{}", coarse[i]);
}

#[test]
fn label_has_no_live_form() {
    let v = vec![0.0f32; 8];
    let src: Arc<dyn VolumeSource> = Arc::new(Mem::new([2, 2, 2], &v));
    let p = Pipeline::parse("threshold(0)|label(6)").unwrap();
    let e = brickyard_process::derive_level(&p, src, 0, [1.0; 3], [8; 3])
        .err()
        .expect("label refused");
    assert!(e.contains("brickyard process"), "{e}");
}

#[test]
fn kernels_wider_than_the_volume_equal_direct_convolution() {
    // Radii 16, 24 and 40 on a 13 × 11 × 17 volume: folded onto the edge
    // voxels on y and z, whole on x; blocks and regions much smaller.
    let (v, got, _) = run_filter::<u16>("gauss(4,6,10)", DIMS, 41, [4, 5, 3], [5, 3, 7]);
    assert_close(&got, &gauss_ref(&v, DIMS, [10.0, 6.0, 4.0]), "wide gauss");
    let (v, got, _) = run_filter::<f32>("gradmag(2,6,9)", DIMS, 42, [3, 4, 6], [13, 11, 17]);
    assert_close(
        &got,
        &gradmag_ref(&v, DIMS, [9.0, 6.0, 2.0]),
        "wide gradmag",
    );
}

/// A live derived level held to a budget: a stage's blocks are counted no
/// larger than the region it is asked for (a small read needs less than a
/// whole block), `readers` reads at once take `readers` times as much, a
/// budget that holds not one block per stage for each reader is an error
/// naming the stage, and the values are those of the unbounded level.
#[test]
fn a_derived_level_within_a_budget_counts_its_reads() {
    let v: Vec<f32> = volume(DIMS, 6);
    let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(DIMS, &v));
    // At a level of twice the voxel size: σ halved, the gradient rescaled.
    let p = Pipeline::parse("gauss(1)|sobel").unwrap();
    let within = |read: Dims3, readers: usize, budget: u64, threads: usize| {
        brickyard_process::derive_level_within(
            &p,
            src.clone(),
            0,
            [2.0; 3],
            [8; 3],
            read,
            readers,
            budget,
            threads,
        )
    };
    let (_, small) = within([4; 3], 1, u64::MAX, 1).unwrap();
    let (_, whole) = within(DIMS, 1, u64::MAX, 1).unwrap();
    assert_eq!(small.parallel, 1);
    assert!(
        0 < small.bytes && small.bytes < whole.bytes,
        "{small:?} {whole:?}"
    );
    let (_, three) = within([4; 3], 3, u64::MAX, 1).unwrap();
    assert_eq!(three.bytes, 3 * small.bytes);
    let e = within([4; 3], 3, 3 * small.bytes - 1, 4).err().unwrap();
    assert!(
        (e.starts_with("gauss(1): ") || e.starts_with("sobel: ")) && e.contains("budget"),
        "{e}"
    );
    let (held, m) = within([4; 3], 3, 3 * small.bytes, 4).unwrap();
    assert_eq!((m.parallel, m.bytes), (1, 3 * small.bytes));
    let free = brickyard_process::derive_level(&p, src.clone(), 0, [2.0; 3], [8; 3]).unwrap();
    assert_eq!(
        read_all_regions(held.as_ref(), [5, 6, 7]),
        read_all_regions(free.as_ref(), [5, 6, 7])
    );
}

#[test]
fn an_impossible_sigma_or_budget_is_an_error_not_a_panic() {
    let v: Vec<f32> = volume(DIMS, 5);
    let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(DIMS, &v));
    for pipe in ["gauss(1e9)", "sobel|gradmag(2e6,1,1)"] {
        let p = Pipeline::parse(pipe).unwrap();
        let e = build(&p, src.clone(), 0, [8; 3]).err().expect(pipe);
        assert!(e.contains("1048576") && e.contains('σ'), "{pipe}: {e}");
        let e = brickyard_process::derive_level(&p, src.clone(), 0, [1.0; 3], [8; 3])
            .err()
            .expect(pipe);
        assert!(e.contains("1048576"), "{pipe}: {e}");
    }
    let p = Pipeline::parse("gauss(1)|gradmag(3)").unwrap();
    let e = brickyard_process::build_within(
        &p,
        src.clone(),
        0,
        [8; 3],
        None,
        1000,
        4,
        Default::default(),
    )
    .err()
    .unwrap();
    assert!(e.starts_with("gradmag(3): ") && e.contains("budget"), "{e}");
    // A budget for one block at a time per stage computes one at a time,
    // and the same values.
    let need = brickyard_process::filter_bytes_at_least(&p, src.clone(), 0, [8; 3]).unwrap();
    let (b, m) = brickyard_process::build_within(
        &p,
        src.clone(),
        0,
        [8; 3],
        None,
        need,
        4,
        Default::default(),
    )
    .unwrap();
    assert_eq!(m.parallel, 1);
    assert!(m.bytes <= need);
    let free = build(&p, src, 0, [8; 3]).unwrap();
    assert_eq!(
        read_all_regions(b.source.as_ref(), [5, 6, 7]),
        read_all_regions(free.source.as_ref(), [5, 6, 7])
    );
}

/// The statistics table of a label volume, tallied in blocks smaller than
/// the volume, against a naive tally voxel by voxel here: counts, boxes,
/// centroids and means; and the two ways a volume gets no table.
#[test]
fn label_tables_from_voxels_equal_a_naive_tally() {
    use brickyard_process::tally::{tally, NoTable};
    use std::collections::BTreeMap;
    let dims = [13, 17, 23];
    let n = dims.iter().product::<u64>() as usize;
    let mut r = rng(5);
    // Runs of labels along x (as segmentations have), ids up to 40 with
    // gaps, a third background.
    let mut ids = vec![0u32; n];
    let mut i = 0;
    while i < n {
        let id = if r() < 0.33 {
            0
        } else {
            1 + (r() * 40.0) as u32 * 3
        };
        let run = 1 + (r() * 9.0) as usize;
        ids[i..(i + run).min(n)].fill(id);
        i += run;
    }
    let image: Vec<f32> = (0..n).map(|_| (r() * 1000.0 - 200.0) as f32).collect();
    let (lab, im) = (Mem::new(dims, &ids), Mem::new(dims, &image));
    let stop = AtomicBool::new(false);
    let rows = tally(&lab, Some((&im, 0)), [4, 5, 6], 1 << 30, &NoProgress, &stop)
        .unwrap()
        .unwrap();
    // The naive tally.
    type Acc = (u64, [u64; 3], [u64; 3], [f64; 3], f64);
    let mut want: BTreeMap<u64, Acc> = BTreeMap::new();
    for (i, &id) in ids.iter().enumerate() {
        if id == 0 {
            continue;
        }
        let p = [
            i as u64 / (dims[1] * dims[2]),
            i as u64 / dims[2] % dims[1],
            i as u64 % dims[2],
        ];
        let e = want
            .entry(id as u64)
            .or_insert((0, [u64::MAX; 3], [0; 3], [0.0; 3], 0.0));
        e.0 += 1;
        for (a, &v) in p.iter().enumerate() {
            e.1[a] = e.1[a].min(v);
            e.2[a] = e.2[a].max(v);
            e.3[a] += v as f64;
        }
        e.4 += image[i] as f64;
    }
    assert!(want.len() > 30, "a volume of many labels");
    assert_eq!(
        rows.iter().map(|r| r.0).collect::<Vec<_>>(),
        want.keys().copied().collect::<Vec<_>>(),
        "one row per label, in increasing order"
    );
    for (id, row) in &rows {
        let w = &want[id];
        assert_eq!(
            (row.voxels, row.min, row.max),
            (w.0, w.1, w.2),
            "label {id}"
        );
        for a in 0..3 {
            assert!(
                (row.centroid[a] - w.3[a] / w.0 as f64).abs() < 1e-9,
                "label {id}"
            );
        }
        let mean = w.4 / w.0 as f64;
        assert!(
            (row.mean.unwrap() - mean).abs() < 1e-9 * mean.abs().max(1.0),
            "label {id}"
        );
    }
    // Without an image: no means.
    let rows = tally(&lab, None, [13, 17, 23], 1 << 30, &NoProgress, &stop)
        .unwrap()
        .unwrap();
    assert!(rows.iter().all(|r| r.1.mean.is_none()));
    // A table beyond its bytes: none, saying how many labels were met.
    let small = 10 * brickyard_process::tally::BYTES_PER_LABEL;
    match tally(&lab, None, [4, 5, 6], small, &NoProgress, &stop).unwrap() {
        Err(NoTable::TooMany { labels, .. }) => assert!(labels > 10),
        other => panic!("expected too many labels, got {other:?}"),
    }
    // A negative value is not a label: named with its place.
    let mut signed: Vec<i16> = ids.iter().map(|&v| v as i16).collect();
    signed[3 * 17 * 23 + 2 * 23 + 7] = -4;
    let neg = Mem::new(dims, &signed);
    match tally(&neg, None, [4, 5, 6], 1 << 30, &NoProgress, &stop).unwrap() {
        Err(NoTable::NotALabel { value, at }) => assert_eq!((value, at), (-4.0, [3, 2, 7])),
        other => panic!("expected a value that is not a label, got {other:?}"),
    }
}

/// A job's meter counts the voxels of the last filter stage's blocks, each
/// once as it is computed: a region read in pieces adds up to the region,
/// the inner stages' blocks (grown by the outer stage's halo) are not
/// counted, and a labelling's mask stage is the last filter stage.
#[test]
fn the_meter_counts_the_last_filter_stages_voxels_once() {
    use std::sync::atomic::{AtomicU64, Ordering};
    let v: Vec<f32> = volume(DIMS, 6);
    let src: Arc<dyn VolumeSource> = Arc::new(Mem::new(DIMS, &v));
    let n: u64 = DIMS.iter().product();
    for pipe in [
        "median(1)",
        "gauss(1)|median(1)",
        "gauss(1)|threshold(0.5)|label(6)",
    ] {
        let p = Pipeline::parse(pipe).unwrap();
        let meter = Arc::new(AtomicU64::new(0));
        let hooks = brickyard_process::Hooks {
            stop: None,
            meter: Some(meter.clone()),
        };
        let (b, _) =
            brickyard_process::build_within(&p, src.clone(), 0, [8; 3], None, 1 << 30, 4, hooks)
                .unwrap();
        // Read in pieces of several blocks each, the meter checked after each.
        let mut seen = 0;
        let [dz, dy, dx] = DIMS;
        let mut buf = vec![0u8; (5 * dy * dx) as usize * b.source.meta().dtype.size()];
        for z in (0..dz).step_by(5) {
            let h = 5.min(dz - z);
            let out = &mut buf[..(h * dy * dx) as usize * b.source.meta().dtype.size()];
            b.source
                .read_region(b.channel, z..z + h, 0..dy, 0..dx, out)
                .unwrap();
            let now = meter.load(Ordering::Relaxed);
            assert_eq!(now - seen, h * dy * dx, "{pipe}: planes {z}..{}", z + h);
            seen = now;
        }
        assert_eq!(seen, n, "{pipe}");
    }
}
